r"""Soak: 10⁶ steps of the reduced rigid body and of four leapfrogging point vortices, with no
trajectory kept.

Run from the repository root:

    python benchmarks/soak.py            # default run: 10⁶ steps of each case
    python benchmarks/soak.py --quick    # smoke test: 10⁴ steps each, XLA optimisation off (not a measurement)
    python benchmarks/soak.py --steps N  # another length (a multiple of --chunk)

What runs (issue 8, "Hard cases and long runs"):

- **rigid_body**: `integrate(rigid_body((2, 1, 2/3)), I, m0/𝕀, dt=0.1, ...)`, the reduced march
  (Theorem 27; Example 30's CAY method, order 2), $m_0 = (\cos 1.1, 0, \sin 1.1)$, $|m_0| = 1$;
- **rigid_body_order4**: the same with `order=4` (Suzuki's p4s5 composition, 5 sub-steps);
- **vortices_4**: two leapfrogging pairs (circulations (1, −1, 1, −1) at (0, ±1), (0, ±0.5),
  as in `tests/test_vortices.py`), the midpoint principle (the implicit midpoint rule) with
  `jacobian="blocks"`, dt = 0.02.

**How it runs without storing the trajectory.** The run is cut into chunks of `chunk_steps`
steps. One chunk is one jitted function: an `integrate(..., P0=p, t0=t, throw=False)` call
that continues from the last node's canonical state $(Q^n, p^n)$ (`clebsch_jax.continue_from`:
for the reduced march $p^n$ is rebuilt from the body momentum $\mu^n$ as the minimum-norm
cotangent, the hand-over `clebsch_jax.sweep` makes) and that reduces its nodes to a few
numbers before returning: for every monitored quantity $f$ the maximum of $\|f^k - f^0\|_\infty$ over each block of
`chunk_steps / BLOCKS` steps (and the maximum of its round-off scale over the block), the
Newton statistics and the state to continue from. Only those leave the device: memory does
not grow with the number of steps (the resident set size is read from `/proc/self/statm`
after every chunk; `resource.getrusage` where that file is missing).

**What is measured**, per case: for the energy ($\tfrac12\xi\cdot\mathbb I\xi$; for vortices
$H$) its error against node 0, per chunk, with a least-squares slope of the chunk maxima
against time — a drift would show as a slope times the run length comparable with the error
itself; for the momentum maps — the Casimir $|\mu|^2$, the spatial angular momentum $Q\mu$
(Noether, left invariance) and $|Q^TQ - I|$ for the rigid body, the linear and angular
impulses for the vortices — the running maximum of $\|f^n - f^0\|$ against the round-off
accumulation of a random walk, $\sqrt n\,\varepsilon\,s(n)$, with $s(n)$ the quantity's
round-off scale ($|\mu|^2$, $|\mu|$, 1; $\sum_a|\Gamma_a||Q_a|$ and
$\sum_a|\Gamma_a||Q_a|^2$, which grow as the pairs travel), and the log-log slope of that
running maximum over its scale against n (½ for a random walk, 1 for a systematic bias per
step). Wall time
per chunk and the resident set size, for the memory curve.

Outputs (in `--out`, default `benchmarks/results`): `soak.json` (per case: the summary
numbers, per-chunk series and the running maxima at ~10 log-spaced points per decade) and
`soak.png` (per case: errors against steps, log-log, with the $\sqrt n\,\varepsilon$ line; energy
error per chunk against time; memory against steps). Nothing here asserts anything; the slow
test `tests/test_hard_cases.py::test_soak_1e5_steps` runs `soak()` for 10⁵ steps and does.
"""

from __future__ import annotations

import contextlib
import functools
import math
import os
import resource
import time
from pathlib import Path
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import clebsch_jax as cj
from clebsch_jax import models

RESULTS_NAME = "soak"
EPS = float(np.finfo(np.float64).eps)
BLOCKS = 100  # blocks per chunk: the resolution of the running maxima
DEFAULT_STEPS, QUICK_STEPS = 1_000_000, 10_000
# Chunks of 2000 steps: with 10⁴-step chunks the allocator grows the heap in steps of a few MB
# early in a run (a chunk's working set, never given back), which blurs the memory curve.
DEFAULT_CHUNK, QUICK_CHUNK = 2_000, 1_000
MAX_ROWS = 200  # per-chunk rows kept in the JSON

RB_INERTIA = (2.0, 1.0, 2.0 / 3.0)
RB_M0 = (math.cos(1.1), 0.0, math.sin(1.1))
RB_DT = 0.1
LEAPFROG_GAMMA = (1.0, -1.0, 1.0, -1.0)
LEAPFROG_Q0 = ((0.0, 1.0), (0.0, -1.0), (0.0, 0.5), (0.0, -0.5))
VORTEX_DT = 0.02


class Case(NamedTuple):
    """One soak case: a system, its initial data, `integrate` options, and what to monitor.

    `monitors(system, sol)` returns {name: (values, scale)} with `values` (n+1, ...) per node
    of one chunk's `Solution` and `scale` (n+1,) the quantity's round-off scale per node.
    `energy` names the energy among them; `kinds[name]` is "energy" or "momentum"."""

    name: str
    description: str
    system: cj.ClebschSystem
    Q0: np.ndarray
    xi0: np.ndarray
    dt: float
    options: dict
    monitors: Callable
    kinds: dict


def _rigid_body_monitors(system, sol):
    mu = sol.momentum
    ones = jnp.ones(mu.shape[0], mu.dtype)
    norm = jnp.linalg.norm(mu, axis=-1)
    return {
        "energy": (cj.diagnostics.energy(system, sol), 0.5 * jnp.sum(mu * sol.xi, -1)),
        "casimir": (jnp.sum(mu * mu, -1), norm**2),
        "spatial_momentum": (jnp.einsum("nij,nj->ni", sol.Q, mu), norm),
        "orthogonality": (cj.diagnostics.orthogonality_error(sol.Q), ones),
    }


def _vortex_monitors(gamma, system, sol):
    Q = sol.Q
    r2 = jnp.sum(Q * Q, -1)  # (n+1, N)
    g = jnp.abs(gamma)
    H = cj.diagnostics.energy(system, sol)
    return {
        "energy": (H, jnp.abs(H)),
        "linear_impulse": (models.vortex_linear_impulse(gamma, Q), jnp.sum(g * jnp.sqrt(r2), -1)),
        "angular_impulse": (models.vortex_angular_impulse(gamma, Q), jnp.sum(g * r2, -1)),
    }


def rigid_body_case(order=None) -> Case:
    inertia, m0 = np.array(RB_INERTIA), np.array(RB_M0)
    opts = {} if order is None else {"order": order}
    return Case(
        name="rigid_body" if order is None else f"rigid_body_order{order}",
        description=f"reduced rigid body, inertia (2, 1, 2/3), dt {RB_DT}"
        + ("" if order is None else f", order {order}"),
        system=models.rigid_body(inertia),
        Q0=np.eye(3),
        xi0=m0 / inertia,
        dt=RB_DT,
        options=opts,
        monitors=_rigid_body_monitors,
        kinds={"energy": "energy", "casimir": "momentum", "spatial_momentum": "momentum", "orthogonality": "momentum"},
    )


def vortex_case() -> Case:
    gamma, Q0 = np.array(LEAPFROG_GAMMA), np.array(LEAPFROG_Q0)
    return Case(
        name="vortices_4",
        description=f"4 leapfrogging vortices, midpoint, blocks, dt {VORTEX_DT}",
        system=models.point_vortices(gamma),
        Q0=Q0,
        xi0=np.asarray(models.vortex_velocity(gamma, Q0)),
        dt=VORTEX_DT,
        options={"jacobian": "blocks"},
        monitors=functools.partial(_vortex_monitors, jnp.asarray(gamma)),
        kinds={"energy": "energy", "linear_impulse": "momentum", "angular_impulse": "momentum"},
    )


CASES = {
    "rigid_body": rigid_body_case,
    "rigid_body_order4": lambda: rigid_body_case(order=4),
    "vortices_4": vortex_case,
}


# --------------------------------------------------------------------------------------------
# Memory.


def rss_mb() -> float:
    """Resident set size of this process now, MB (`/proc/self/statm`), or the peak from
    `resource.getrusage` where /proc is missing."""
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        return max_rss_mb()


def max_rss_mb() -> float:
    """Peak resident set size of this process, MB (`ru_maxrss` is in kB on Linux)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


# --------------------------------------------------------------------------------------------
# One chunk: integrate, reduce, hand over.


def make_chunk(case: Case, chunk_steps: int, blocks: int = BLOCKS, compiler_options=None):
    """The jitted chunk function of `case`:
    `chunk(start, ref, first) -> (start, ref, block_dev, block_scale, stats)` with `start` a
    `clebsch_jax.Start` (the chunk's initial state; returned: its last node's, to continue
    from), `ref` the monitored values at node 0 of the run (taken from this chunk's node 0 when
    `first`), `block_dev[name]` (blocks,) the maximum of $\\|f^k - f^0\\|_\\infty$ over each block
    of nodes 1..n of the chunk and `block_scale[name]` (blocks,) the maximum scale there, and
    `stats` the status (first failure), failed step, Newton updates summed and the worst
    residual."""
    if chunk_steps % blocks:
        raise ValueError(f"chunk_steps: must be a multiple of {blocks}, got {chunk_steps}.")
    system = case.system

    def chunk(start, ref, first):
        sol = cj.integrate(system, **start._asdict(), dt=case.dt, n_steps=chunk_steps, throw=False, **case.options)
        mon = case.monitors(system, sol)
        ref = {k: jnp.where(first, v[0], ref[k]) for k, (v, _) in mon.items()}
        dev, scale = {}, {}
        for k, (v, s) in mon.items():
            d = jnp.abs(v[1:] - ref[k]).reshape(chunk_steps, -1).max(axis=1)
            dev[k] = d.reshape(blocks, -1).max(axis=1)
            scale[k] = s[1:].reshape(blocks, -1).max(axis=1)
        attempted = sol.stats.status != cj.Status.SKIPPED
        good = sol.stats.status == cj.Status.SUCCESS
        stats = {
            "status": sol.result,
            "failed_step": sol.failed_step,
            "iterations": jnp.sum(jnp.where(attempted, sol.stats.iterations, 0)),
            "max_residual": jnp.max(jnp.where(good, sol.stats.residual_norm, 0.0)),
        }
        # the canonical state only (as the first chunk's): one compiled program for every chunk
        return cj.continue_from(system, sol)._replace(march_state=None), ref, dev, scale, stats

    def probe():  # shapes only (traced, not compiled): the method's facts and the monitors' shapes
        sol = cj.integrate(system, case.Q0, case.xi0, dt=case.dt, n_steps=1, throw=False, **case.options)
        return sol, {k: v[0] for k, (v, _) in case.monitors(system, sol).items()}

    facts, ref_shapes = jax.eval_shape(probe)
    return jax.jit(chunk, compiler_options=compiler_options), facts, ref_shapes


# --------------------------------------------------------------------------------------------
# The soak.


def log_points(n_total: int, every: int, per_decade: int = 10) -> np.ndarray:
    """Block ends (multiples of `every` up to `n_total`) nearest to `per_decade` log-spaced
    points per decade, without repeats."""
    k = np.unique(
        np.round(
            np.logspace(0, math.log10(n_total / every), 1 + int(per_decade * math.log10(max(n_total / every, 1.0))))
        )
    ).astype(int)
    return np.unique(np.clip(k, 1, n_total // every)) * every


def _fit_drift(t: np.ndarray, e: np.ndarray) -> dict:
    """Least-squares line through the chunk maxima e(t): slope, its standard error, and the
    change it implies over the run relative to the mean chunk maximum."""
    if len(t) < 3:
        return {"slope_per_time": None, "slope_stderr": None, "drift_over_run": None, "drift_over_run_relative": None}
    A = np.stack([t, np.ones_like(t)], 1)
    coef, *_ = np.linalg.lstsq(A, e, rcond=None)
    resid = e - A @ coef
    stderr = math.sqrt(float(resid @ resid) / (len(t) - 2) / float(np.sum((t - t.mean()) ** 2)))
    drift = float(coef[0]) * float(t[-1] - t[0])
    return {
        "slope_per_time": float(coef[0]),
        "slope_stderr": stderr,
        "drift_over_run": drift,
        "drift_over_run_relative": drift / float(np.mean(e)) if np.mean(e) > 0 else None,
    }


def soak(
    case: Case | str,
    n_steps: int = DEFAULT_STEPS,
    chunk_steps: int = DEFAULT_CHUNK,
    *,
    blocks: int = BLOCKS,
    compiler_options=None,
    guard=None,
    progress: Callable | None = None,
) -> dict:
    """Run `case` (a `Case` or a name in `CASES`) for `n_steps` steps in chunks of `chunk_steps`
    without storing the trajectory (module docstring); return a JSON-able dict of the results.

    `guard(what)`: a context manager around every chunk (the benchmark's watchdog).
    `progress(chunk_index, n_chunks, row)`: called after every chunk with its row."""
    if isinstance(case, str):
        case = CASES[case]()
    if n_steps % chunk_steps:
        raise ValueError(f"n_steps: must be a multiple of chunk_steps={chunk_steps}, got {n_steps}.")
    guard = guard or (lambda what: contextlib.nullcontext())
    every = chunk_steps // blocks
    n_chunks = n_steps // chunk_steps
    chunk, facts, ref_shapes = make_chunk(case, chunk_steps, blocks, compiler_options)

    names = list(case.kinds)
    points = log_points(n_steps, every)  # steps where the running maxima are kept
    running = {k: np.full(len(points), np.nan) for k in names}
    running_scale = {k: np.full(len(points), np.nan) for k in names}
    run_max = {k: 0.0 for k in names}
    run_scale = {k: 0.0 for k in names}
    rows = {
        "step": [],
        "t": [],
        "wall_s": [],
        "rss_mb": [],
        "newton_updates_per_step": [],
        **{f"{k}_max": [] for k in names},
    }

    Q, xi = jnp.asarray(case.Q0), jnp.asarray(case.xi0)
    start = cj.Start(
        Q0=Q,
        xi0=xi,
        P0=cj.initial_multiplier(case.system, Q, xi),  # as integrate starts
        t0=jnp.zeros(()),
    )
    ref = {k: jnp.zeros(v.shape, v.dtype) for k, v in ref_shapes.items()}  # replaced at chunk 0
    status, failed_step, iterations, max_residual, initial = 0, -1, 0, 0.0, None
    rss_start = rss_mb()
    tic = time.perf_counter()
    for c in range(n_chunks):
        with guard(f"{case.name}, chunk {c + 1}/{n_chunks}"):
            start, ref, dev, scale, stats = chunk(start, ref, jnp.asarray(c == 0))
            dev, scale, stats = jax.device_get((dev, scale, stats))
        wall = time.perf_counter() - tic
        if initial is None:
            initial = jax.device_get(ref)
        if status == 0 and int(stats["status"]) != 0:
            status, failed_step = int(stats["status"]), c * chunk_steps + int(stats["failed_step"])
        iterations += int(stats["iterations"])
        max_residual = max(max_residual, float(stats["max_residual"]))
        for k in names:
            cm = np.maximum.accumulate(np.maximum(dev[k], run_max[k]))
            cs = np.maximum.accumulate(np.maximum(scale[k], run_scale[k]))
            run_max[k], run_scale[k] = float(cm[-1]), float(cs[-1])
            sel = (points > c * chunk_steps) & (points <= (c + 1) * chunk_steps)
            idx = (points[sel] - c * chunk_steps) // every - 1
            running[k][sel], running_scale[k][sel] = cm[idx], cs[idx]
            rows[f"{k}_max"].append(float(np.max(dev[k])))
        rows["step"].append((c + 1) * chunk_steps)
        rows["t"].append(float(start.t0))
        rows["wall_s"].append(wall)
        rows["rss_mb"].append(rss_mb())
        rows["newton_updates_per_step"].append(int(stats["iterations"]) / chunk_steps)
        if progress is not None:
            progress(c, n_chunks, {k: v[-1] for k, v in rows.items()})
    wall_total = time.perf_counter() - tic

    t = np.asarray(rows["t"])
    steady = slice(1, None) if n_chunks > 2 else slice(None)  # chunk 0 compiles
    walls = np.diff(np.concatenate([[0.0], rows["wall_s"]]))
    rss = np.asarray(rows["rss_mb"])
    stride = max(1, -(-n_chunks // MAX_ROWS))
    kept = sorted(set(range(0, n_chunks, stride)) | {n_chunks - 1})
    result = {
        "case": case.name,
        "description": case.description,
        "n_steps": n_steps,
        "chunk_steps": chunk_steps,
        "blocks_per_chunk": blocks,
        "dt": case.dt,
        "T": n_steps * case.dt,
        "options": case.options,
        "form": facts.form,
        "scheme": facts.scheme,
        "order": int(facts.order),
        "method": facts.method,
        "status": status,
        "failed_step": failed_step,
        "newton_updates_per_step": iterations / n_steps,
        "max_residual": max_residual,
        "wall_s": wall_total,
        "first_chunk_s": float(walls[0]),
        "seconds_per_step": float(np.median(walls[steady])) / chunk_steps,
        "memory": {
            "rss_mb_before": rss_start,
            "rss_mb_after_first_chunk": float(rss[0]),
            "rss_mb_end": float(rss[-1]),
            "growth_after_first_chunk_mb": float(rss[-1] - rss[0]),
            "max_growth_after_first_chunk_mb": float(np.max(rss) - rss[0]),
            "max_rss_mb": max_rss_mb(),
        },
        "quantities": {},
        # at most MAX_ROWS chunks kept (every `stride`-th and the last); the fits use them all
        "chunks": {"stride": stride, **{k: [v[i] for i in kept] for k, v in rows.items()}},
        "running_max": {
            "step": points.tolist(),
            **{k: running[k].tolist() for k in names},
            **{f"{k}_scale": running_scale[k].tolist() for k in names},
        },
    }
    for k in names:
        v0 = np.asarray(initial[k])
        q = {"kind": case.kinds[k], "initial": v0.tolist(), "max_error": run_max[k], "max_scale": run_scale[k]}
        if case.kinds[k] == "energy":
            e = np.asarray(rows[f"{k}_max"])
            q["relative_max_error"] = run_max[k] / float(np.max(np.abs(v0)))
            q["drift"] = _fit_drift(t, e)
            k10 = max(1, n_chunks // 10)
            q["envelope_ratio_chunks"] = float(np.max(e[-k10:]) / np.max(e[:k10])) if np.max(e[:k10]) > 0 else None
        else:
            bound = np.sqrt(points) * EPS * running_scale[k]
            ratio = running[k] / bound
            pos = running[k] > 0
            slope = None
            if np.count_nonzero(pos & (points >= 100)) >= 3:  # of the drift relative to its scale
                m = pos & (points >= 100)
                slope = float(np.polyfit(np.log(points[m]), np.log(running[k][m] / running_scale[k][m]), 1)[0])
            q.update(
                {
                    "sqrt_n_eps_scale_at_end": float(bound[-1]),
                    "ratio_to_sqrt_n_eps_scale_at_end": float(ratio[-1]),
                    "max_ratio_to_sqrt_n_eps_scale": float(np.nanmax(ratio)),
                    "loglog_slope": slope,
                }
            )
        result["quantities"][k] = q
    return result


# --------------------------------------------------------------------------------------------
# Report and plot.


def print_report(summary: dict) -> None:
    for r in summary["results"]:
        mem = r["memory"]
        print(
            f"\n{r['case']}: {r['description']}; {r['n_steps']} steps (T = {r['T']:g}), {r['form']} march, "
            f"{r['method'] or r['scheme']}, order {r['order']}; status {r['status']}"
        )
        print(
            f"  wall {r['wall_s']:.1f} s (first chunk, compiling: {r['first_chunk_s']:.1f} s), "
            f"{1e6 * r['seconds_per_step']:.1f} µs/step, {r['newton_updates_per_step']:.2f} Newton updates/step, "
            f"worst residual {r['max_residual']:.1e}"
        )
        print(
            f"  memory: RSS {mem['rss_mb_after_first_chunk']:.0f} MB after the first chunk, "
            f"{mem['rss_mb_end']:.0f} MB at the end (growth {mem['growth_after_first_chunk_mb']:+.2f} MB, "
            f"at most {mem['max_growth_after_first_chunk_mb']:+.2f} MB)"
        )
        for k, q in r["quantities"].items():
            if q["kind"] == "energy":
                d = q["drift"]
                rel = d["drift_over_run_relative"]
                print(
                    f"  {k:17s} max error {q['max_error']:.3e} (relative {q['relative_max_error']:.2e}); "
                    f"fitted drift over the run {'-' if rel is None else f'{rel:+.2e}'} of the mean chunk max; "
                    f"envelope last/first tenth {q['envelope_ratio_chunks']:.3f}"
                )
            else:
                s = q["loglog_slope"]
                print(
                    f"  {k:17s} max drift {q['max_error']:.3e}; sqrt(n)·eps·scale at the end "
                    f"{q['sqrt_n_eps_scale_at_end']:.3e} (ratio {q['ratio_to_sqrt_n_eps_scale_at_end']:.2f}, "
                    f"max {q['max_ratio_to_sqrt_n_eps_scale']:.2f}); "
                    f"log-log slope {'-' if s is None else f'{s:.2f}'}"
                )


def plot(summary: dict, path: Path) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    rows = summary["results"]
    fig = Figure(figsize=(13, 3.6 * len(rows)), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(len(rows), 3, squeeze=False, gridspec_kw={"width_ratios": [3, 2, 2]})
    mach = summary["machine"]
    fig.suptitle(
        f"Soak: errors, energy and memory over {rows[0]['n_steps']:.0e} steps"
        f"{' (--quick: not a measurement)' if summary['config']['quick'] else ''}; "
        f"{mach['cpu_count']} CPUs, load {mach['load_average_1min_at_start']:.2f} at start",
        fontsize=10,
    )
    for (ax, ax_e, ax_m), r in zip(axes, rows):
        rm = r["running_max"]
        n = np.asarray(rm["step"], float)
        for k, q in r["quantities"].items():
            y = np.asarray(rm[k], float) / np.asarray(rm[f"{k}_scale"], float)
            ax.loglog(n, np.where(y > 0, y, np.nan), marker=".", ms=3, label=f"{k} / scale")
        ax.loglog(n, np.sqrt(n) * EPS, "k--", lw=1, label=r"$\sqrt{n}\,\varepsilon$")
        ax.set_xlabel("steps n")
        ax.set_ylabel(r"max$_{k\leq n}\|f^k - f^0\|$ / scale")
        ax.set_title(f"{r['case']}: {r['description']}", fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
        ch = r["chunks"]
        ax_e.plot(ch["t"], ch["energy_max"], ".-", ms=3)
        ax_e.set_ylim(0, 1.2 * max(ch["energy_max"]))
        ax_e.set_xlabel("t (end of chunk)")
        ax_e.set_ylabel("max |E - E0| over the chunk")
        rel = r["quantities"]["energy"]["drift"]["drift_over_run_relative"]
        ax_e.set_title(
            "energy error per chunk" + ("" if rel is None else f" (fitted drift {rel:+.1e} of it)"), fontsize=9
        )
        ax_e.grid(True, alpha=0.3)
        ax_m.plot(ch["step"], ch["rss_mb"], ".-", ms=3)
        lo, hi = min(ch["rss_mb"]), max(ch["rss_mb"])
        ax_m.set_ylim(lo - max(5, 0.1 * (hi - lo)), hi + max(5, 0.1 * (hi - lo)))
        ax_m.set_xlabel("steps")
        ax_m.set_ylabel("resident set size, MB")
        ax_m.set_title(
            f"memory (growth after chunk 1: {r['memory']['growth_after_first_chunk_mb']:+.1f} MB)", fontsize=9
        )
        ax_m.grid(True, alpha=0.3)
    fig.savefig(path, dpi=110)


# --------------------------------------------------------------------------------------------


def main(argv=None) -> dict:
    """Runs the soak of every case, prints the summary, writes the JSON and the PNG."""
    import _timing as harness  # the benchmarks' shared harness (this script's folder is on sys.path)

    def add_arguments(parser):
        parser.add_argument(
            "--steps",
            type=int,
            default=None,
            help=f"steps per case (default {DEFAULT_STEPS:.0e}; {QUICK_STEPS:.0e} with --quick)",
        )
        parser.add_argument(
            "--chunk",
            type=int,
            default=None,
            help=f"steps per chunk (default {DEFAULT_CHUNK}; {QUICK_CHUNK} with --quick)",
        )
        parser.add_argument(
            "--cases", nargs="+", choices=list(CASES), default=list(CASES), help="which cases to run (default: all)"
        )

    with harness.Run(
        RESULTS_NAME,
        argv,
        description="Soak: long runs without storing the trajectory (see module docstring).",
        add_arguments=add_arguments,
    ) as run:
        n_steps = run.args.steps or (QUICK_STEPS if run.quick else DEFAULT_STEPS)
        chunk = run.args.chunk or (QUICK_CHUNK if run.quick else DEFAULT_CHUNK)
        results = []
        for name in run.args.cases:

            def progress(c, n, row, name=name):
                if (c + 1) % max(1, n // 10) == 0 or c == 0:
                    print(
                        f"  {name}: chunk {c + 1}/{n}, step {row['step']}, {row['wall_s']:.0f} s, "
                        f"RSS {row['rss_mb']:.0f} MB, energy error {row['energy_max']:.2e}",
                        flush=True,
                    )

            with run.case(f"{name}, {n_steps} steps in chunks of {chunk}"):
                print()
                results.append(
                    soak(
                        name, n_steps, chunk, compiler_options=run.compiler_options, guard=run.guard, progress=progress
                    )
                )
    summary = run.summary(
        config={
            "n_steps": n_steps,
            "chunk_steps": chunk,
            "blocks_per_chunk": BLOCKS,
            "cases": run.args.cases,
            "eps": EPS,
        },
        results=results,
    )
    return run.finish(summary, print_report, plot)


if __name__ == "__main__":
    main()
