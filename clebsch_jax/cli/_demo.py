r"""The main demo: the scene of Figure 1 of Cotter & Holm (Example 30).

The free rigid body with principal moments $\mathbb I = (0.5, 0.6, 1)$, integrated with the
discrete Clebsch integrator of Example 30 (Cayley derivative map, the CAY integrator) at
$\Delta t = 0.1$, from a small batch of body angular momenta on the sphere $|m| = 1$: orbits
about the minor axis ($I_1 = 0.5$), about the major axis ($I_3 = 1$), and a pair on each side
of the separatrix through the middle axis. The batch runs under `jax.vmap`.

The paper integrates over 100 periods: ~18,400 steps for the slowest orbit shown here. The
default run covers them, up to `MAX_DEFAULT_STEPS`; the summary reports how many periods each
orbit actually covered and how many steps 100 periods of the slowest orbit take (pass them as
`n_steps`, or `clebsch-jax demo --steps N`).

The march runs in equal chunks of steps, each chunk one call of the same compiled function
restarted from the last chunk's $(Q, p)$ (`clebsch_jax.continue_from`). The first call pays for
compilation; the later ones are already compiled and give the steps-per-second figure, so
the run is not done twice just to time it. Chaining is exact for the discrete flow: the step
map is a function of $(Q^n, p^n)$ alone.
"""

from __future__ import annotations

import json
import math
import numbers
import operator
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

import clebsch_jax as cj
from clebsch_jax import diagnostics, lie
from clebsch_jax.models import rigid_body

from ._demo_plots import orbit_colors, plot_invariants, plot_orbits

__all__ = ["figure1", "MissingPlotDependency"]

INERTIA = (0.5, 0.6, 1.0)
"""Principal moments of inertia of Figure 1."""

DT = 0.1
"""Time step of Figure 1."""

TARGET_PERIODS = 100
"""Figure 1 integrates over 100 periods."""

MAX_DEFAULT_STEPS = 20_000
"""Cap on the default number of steps (100 periods of the slowest orbit need ~18,400)."""

QUICK_STEPS = 200
"""Default number of steps with `quick=True`."""

_CHUNK_STEPS = 1000
"""Target number of steps per compiled call."""

_QUICK_COMPILER_OPTIONS = {"xla_backend_optimization_level": 0}

# Initial momenta m = (cos a, 0, sin a) and their opposites -m, angle a in degrees from the
# minor axis e1 toward the major axis e3. The separatrix through the middle axis e2 meets
# this great circle at a = arctan(1/sqrt 2) = 35.26 deg; 32 and 38.5 lie on either side.
_ANGLES = (8.0, 20.0, 32.0, 38.5, 52.0, 72.0)
_QUICK_ANGLES = (20.0, 52.0)


class MissingPlotDependency(ImportError):
    """Raised (before any computation) when matplotlib, needed for the figures, is missing."""


def _require_matplotlib() -> None:
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise MissingPlotDependency(
            'the demo draws its figures with matplotlib, which is not installed: pip install "clebsch-jax[plot]"'
        ) from None


# --------------------------------------------------------------------------------------------
# The scene.


def initial_momenta(quick: bool = False) -> np.ndarray:
    """Unit body angular momenta of the demo's orbits, shape (K, 3).

    **Arguments:**

    - `quick`: if True, a smaller batch (one orbit about each stable axis, and their mirror
      images).
    """
    a = np.deg2rad(np.asarray(_QUICK_ANGLES if quick else _ANGLES))
    m = np.stack([np.cos(a), np.zeros_like(a), np.sin(a)], axis=-1)
    return np.concatenate([m, -m])


def _agm_ellipk(k2: float) -> float:
    """Complete elliptic integral of the first kind K(k), parameter k^2 in [0, 1)."""
    a, b = 1.0, math.sqrt(1.0 - k2)
    for _ in range(60):
        a, b = 0.5 * (a + b), math.sqrt(a * b)
        if abs(a - b) <= 1e-16 * a:
            break
    return math.pi / (2.0 * a)


def exact_period(inertia, m) -> float:
    r"""Period of the exact body angular momentum $m(t)$ of the free rigid body.

    Landau & Lifshitz §37: with $I_1 < I_2 < I_3$, $M^2 = |m|^2$ and $2E = \sum m_i^2/I_i$,
    for $M^2 > 2EI_2$ (orbits about $e_3$)
    $T = 4K(k)\sqrt{I_1I_2I_3 / ((I_3 - I_2)(M^2 - 2EI_1))}$ with
    $k^2 = (I_2 - I_1)(2EI_3 - M^2) / ((I_3 - I_2)(M^2 - 2EI_1))$; for $M^2 < 2EI_2$ swap
    the roles of $I_1$ and $I_3$. Infinite on the separatrix.

    **Arguments:**

    - `inertia`: the three principal moments, distinct and in increasing order.
    - `m`: a body angular momentum, shape (3,).
    """
    i1, i2, i3 = (float(x) for x in inertia)
    m = np.asarray(m, dtype=float)
    M2 = float(m @ m)
    E2 = float(np.sum(m * m / np.asarray(inertia, dtype=float)))
    a, c = (i1, i3) if M2 > E2 * i2 else (i3, i1)
    denom = (c - i2) * (M2 - E2 * a)
    k2 = (i2 - a) * (E2 * c - M2) / denom
    if not 0.0 <= k2 < 1.0:
        return math.inf
    return 4.0 * _agm_ellipk(k2) * math.sqrt(i1 * i2 * i3 / denom)


def measured_period(t: np.ndarray, m: np.ndarray) -> float:
    """Period of a closed orbit m(t), from its returns through its starting point.

    Counts the upward crossings of the plane through `m[0]` normal to the initial direction of
    motion (near `m[0]`), interpolating linearly between nodes; the period is the time of the
    last return divided by the number of returns. NaN when the orbit never returns.

    **Arguments:**

    - `t`: times, shape (N+1,). `m`: the trajectory, shape (N+1, 3).
    """
    t = np.asarray(t)
    m = np.asarray(m)
    if len(t) < 3:
        return math.nan
    v = m[1] - m[0]
    f = (m - m[0]) @ v
    near = np.linalg.norm(m - m[0], axis=-1) < 0.5 * np.max(np.linalg.norm(m - m[0], axis=-1))
    idx = np.nonzero((f[1:-1] < 0.0) & (f[2:] >= 0.0) & near[2:])[0] + 2
    if len(idx) == 0:
        return math.nan
    n = idx[-1]
    t_cross = t[n - 1] + (t[n] - t[n - 1]) * (-f[n - 1]) / (f[n] - f[n - 1])
    return float(t_cross / len(idx))


def _chunk_function(system, dt: float, n_steps: int, compiler_options=None):
    """A jitted, vmapped march of `n_steps` steps from a batch of `clebsch_jax.Start`s, with
    diagnostics; returns (Solution, diagnostics, the `Start` at the last node)."""

    def one(start):
        sol = cj.integrate(system, **start._asdict(), dt=dt, n_steps=n_steps, throw=False)
        diag = {
            "m": diagnostics.body_momentum(system, sol),
            "E": diagnostics.energy(system, sol),
            "J": diagnostics.noether_momentum(sol, lie.so3_left_generators, system),
            "orth": diagnostics.orthogonality_error(sol.Q),
        }
        # the canonical state only: the first chunk starts from one, so one program serves every chunk
        return sol, diag, cj.continue_from(system, sol)._replace(march_state=None)

    return jax.jit(jax.vmap(one), compiler_options=compiler_options)


def _march(system, m0: np.ndarray, dt: float, n_steps: int, compiler_options=None):
    """Run the batch in chunks. Returns (trajectory diagnostics, Newton iterations, timing)."""
    n_chunks = max(2, round(n_steps / _CHUNK_STEPS))
    chunk = -(-n_steps // n_chunks)
    n_chunks = -(-n_steps // chunk)
    n_chunks = max(n_chunks, 2)
    run = _chunk_function(system, dt, chunk, compiler_options)

    xi = jnp.asarray(m0 / np.asarray(INERTIA)[None, :])  # xi0 = m / I (Lemma 7: m = I xi)
    Q = jnp.broadcast_to(jnp.eye(3), (len(m0), 3, 3))

    t_start = time.perf_counter()
    P = jax.vmap(lambda q, x: cj.initial_multiplier(system, q, x))(Q, xi)
    start = cj.Start(Q0=Q, xi0=xi, P0=P, t0=jnp.zeros(len(m0)))
    pieces, iters, call_times = [], [], []
    for c in range(n_chunks):
        tic = time.perf_counter()
        sol, diag, start = jax.block_until_ready(run(start))
        call_times.append(time.perf_counter() - tic + (tic - t_start if c == 0 else 0.0))
        try:
            sol.raise_if_failed()
        except cj.IntegrationError as err:  # step numbers in the message count from the chunk start
            raise cj.IntegrationError(
                f"{err} (The demo runs in chunks of {chunk} steps; this was chunk {c + 1} of "
                f"{n_chunks}, starting at step {c * chunk}.)"
            ) from None
        keep = slice(0 if c == 0 else 1, None)
        pieces.append({k: np.asarray(v)[:, keep] for k, v in diag.items()} | {"t": np.asarray(sol.ts)[0, keep]})
        iters.append(np.asarray(sol.stats.iterations))

    out = {k: np.concatenate([p[k] for p in pieces], axis=1 if k != "t" else 0) for k in pieces[0]}
    out = {k: (v[: n_steps + 1] if k == "t" else v[:, : n_steps + 1]) for k, v in out.items()}
    iterations = np.concatenate(iters, axis=1)[:, :n_steps]
    timed = sum(call_times[1:])
    timing = {
        "compile_and_first_call_s": call_times[0],
        "compiled_calls": n_chunks - 1,
        "steps_per_call": chunk,
        "compiled_s": timed,
        "steps_per_s": (n_chunks - 1) * chunk / timed if timed > 0 else math.nan,
        "orbit_steps_per_s": len(m0) * (n_chunks - 1) * chunk / timed if timed > 0 else math.nan,
        "form": sol.form,  # "reduced": Example 30's CAY recursion in ξ alone (Corollary 29)
    }
    return out, iterations, timing


# --------------------------------------------------------------------------------------------
# Entry point.


def figure1(out_dir, *, quick: bool = False, n_steps: int | None = None) -> dict:
    r"""Reproduce the scene of Figure 1 (Example 30) and write its figures and numbers.

    Integrates a batch of rigid-body orbits (`INERTIA`, `DT`, Cayley derivative map) under
    `jax.vmap`, and writes into `out_dir` (created if needed):

    - `figure1_orbits.png`: the body angular momenta on the sphere $|m| = 1$ (3-D view and
      the three projections), with the separatrix dashed;
    - `figure1_invariants.png`: relative energy error, Casimir $|m|^2$ error, drift of the
      spatial angular momentum (the discrete Noether momentum of the left $SO(3)$ action)
      and orthogonality error of $Q$, against time;
    - `summary.json`: the returned dictionary.

    **Arguments:**

    - `out_dir`: output folder (str or path-like).
    - `quick`: fewer orbits (4) and steps (`QUICK_STEPS`): a smoke test whose time is mostly
      compilation, so it is compiled with XLA's backend optimisation off (compiles faster,
      runs slower per step; recorded in the summary's `compiler_options`).
    - `n_steps`: number of steps (int >= 1). Default: enough for `TARGET_PERIODS` periods of
      the slowest orbit, capped at `MAX_DEFAULT_STEPS` (`QUICK_STEPS` with `quick`).

    **Returns:** the summary dictionary (JSON-serialisable): the scene, one entry per orbit
    (initial momentum, exact and measured period, periods covered), the maximum errors,
    Newton iterations per step and timings.

    Raises `MissingPlotDependency` (before computing anything) if matplotlib is missing,
    `OSError` if `out_dir` cannot be created or written, and `clebsch_jax.IntegrationError`
    if a step fails.
    """
    n_steps = _checked_steps(n_steps)
    _require_matplotlib()
    t_begin = time.perf_counter()
    out_dir = _writable_folder(out_dir)

    m0 = initial_momenta(quick)
    periods_exact = np.array([exact_period(np.asarray(INERTIA), m) for m in m0])
    if n_steps is None:
        n_steps = QUICK_STEPS if quick else min(_steps_for_target(periods_exact), MAX_DEFAULT_STEPS)
    options = _QUICK_COMPILER_OPTIONS if quick else None
    system = rigid_body(jnp.asarray(INERTIA))
    traj, iterations, timing = _march(system, m0, DT, n_steps, options)
    errors = _errors(traj)
    t_final = float(traj["t"][-1])
    periods_meas = np.array([measured_period(traj["t"], mk) for mk in traj["m"]])
    periods_used = np.where(np.isfinite(periods_meas), periods_meas, periods_exact)
    covered = t_final / periods_used

    files = ["figure1_orbits.png", "figure1_invariants.png", "summary.json"]
    tic = time.perf_counter()
    _draw(out_dir, files, traj, errors, covered, n_steps)
    timing = timing | {"plot_s": time.perf_counter() - tic}
    summary = {
        "scene": _scene_facts(system, timing["form"], len(m0), n_steps, t_final, quick, options),
        "periods_covered": {"min": float(covered.min()), "max": float(covered.max())},
        "target_periods": TARGET_PERIODS,
        # The discrete period is O(dt^2) longer than the exact one: once measured, it sets the
        # number of steps that really covers the target.
        "steps_for_target_periods": _steps_for_target(periods_used, slack=1e-9),
        "orbits": _orbits(m0, traj["E"], periods_exact, periods_meas, covered, errors),
        "errors": {
            "energy_rel_max": float(np.max(errors["energy"])),
            "casimir_rel_max": float(np.max(errors["casimir"])),
            "spatial_momentum_drift_rel_max": float(np.max(errors["spatial"])),
            "orthogonality_max": float(np.max(errors["orthogonality"])),
        },
        "newton_iterations": {"mean": float(np.mean(iterations)), "max": int(np.max(iterations))},
        "timing": timing | {"total_s": time.perf_counter() - t_begin},
        "files": files,
        "versions": {"jax": jax.__version__, "numpy": np.__version__},
    }
    with open(os.path.join(out_dir, files[2]), "w") as fh:
        json.dump(summary, fh, indent=2)
        fh.write("\n")
    return summary


def _checked_steps(n_steps):
    """`n_steps` as an int >= 1, or None; a `ValueError` otherwise."""
    if n_steps is None:
        return None
    if isinstance(n_steps, bool) or not isinstance(n_steps, numbers.Integral) or n_steps < 1:
        raise ValueError(f"n_steps: expected an int >= 1, got {n_steps!r}.")
    return operator.index(n_steps)


def _writable_folder(out_dir) -> str:
    """`out_dir` as a str, created if needed; `PermissionError` before the run, not after it,
    if it cannot be written."""
    out_dir = os.fspath(out_dir)
    os.makedirs(out_dir, exist_ok=True)
    if not os.access(out_dir, os.W_OK):
        raise PermissionError(f"{out_dir!r} is not writable")
    return out_dir


def _steps_for_target(periods: np.ndarray, slack: float = 0.0) -> int:
    """Steps of `DT` that cover `TARGET_PERIODS` periods of the slowest orbit."""
    return int(math.ceil(TARGET_PERIODS * np.max(periods) / DT - slack))


def _errors(traj: dict) -> dict:
    """Per orbit and node: the relative energy and Casimir errors, the relative drift of the
    spatial angular momentum and the orthogonality error of Q."""
    m, E, J = traj["m"], traj["E"], traj["J"]
    m2 = np.sum(m * m, axis=-1)
    J_scale = np.max(np.abs(J[:, :1]), axis=-1)
    return {
        "energy": np.abs(E - E[:, :1]) / np.abs(E[:, :1]),
        "casimir": np.abs(m2 - m2[:, :1]) / m2[:, :1],
        "spatial": np.max(np.abs(J - J[:, :1]), axis=-1) / J_scale,
        "orthogonality": traj["orth"],
    }


def _orbits(m0, E, periods_exact, periods_meas, covered, errors) -> list:
    """The summary's entry for every orbit: initial momentum, energy, the axis it turns about,
    exact and measured periods, periods covered and its largest energy error."""
    energy2 = 2.0 * np.asarray(E[:, 0])
    axis_names = (f"minor (I1 = {INERTIA[0]:g})", f"major (I3 = {INERTIA[2]:g})")
    return [
        {
            "m0": [float(x) for x in m0[k]],
            "energy": float(E[k, 0]),
            "axis": axis_names[0] if energy2[k] > 1.0 / INERTIA[1] else axis_names[1],
            "period_exact": float(periods_exact[k]),
            "period_measured": float(periods_meas[k]) if np.isfinite(periods_meas[k]) else None,
            "periods_covered": float(covered[k]),
            "energy_error": float(np.max(errors["energy"][k])),
        }
        for k in range(len(m0))
    ]


def _scene_facts(system, march: str, n_orbits: int, n_steps: int, t_final: float, quick: bool, options) -> dict:
    """The summary's `scene` entry: what was integrated, and how."""
    return {
        "paper": (
            "C. J. Cotter and D. D. Holm, Continuous and discrete Clebsch variational principles: Example 30, Figure 1"
        ),
        "inertia": list(INERTIA),
        "dt": DT,
        "derivative_map": getattr(system.derivative_map, "name", "cayley"),
        "march": march,
        "scheme": "left",
        "n_orbits": n_orbits,
        "n_steps": n_steps,
        "t_final": t_final,
        "quick": bool(quick),
        "compiler_options": dict(options or {}),
    }


def _draw(out_dir: str, files: list, traj: dict, errors: dict, covered: np.ndarray, n_steps: int) -> None:
    """The two figures, `files[0]` (orbits) and `files[1]` (invariants), into `out_dir`."""
    t, m = traj["t"], traj["m"]
    span = f"{covered.min():.3g} to {covered.max():.3g} periods"
    title = (
        f"Rigid body, I = {INERTIA}, dt = {DT}, Cayley (Example 30): {len(m)} orbits, "
        f"{n_steps} steps (t = {float(t[-1]):g}), {span}"
    )
    colors = orbit_colors(2.0 * np.asarray(traj["E"][:, 0]), INERTIA)
    plot_orbits(os.path.join(out_dir, files[0]), m, colors, title, INERTIA)
    plot_invariants(os.path.join(out_dir, files[1]), t, errors, colors, title)
