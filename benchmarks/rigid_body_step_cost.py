r"""Per-step cost of the rigid-body march, full $(\xi, P, Q)$ against reduced $\xi$-only, next
to a NumPy RK4.

Run from the repository root:

    python benchmarks/rigid_body_step_cost.py            # default run, ~2.5 min on 2 idle cores
    python benchmarks/rigid_body_step_cost.py --quick    # smoke test, small sizes

What is timed, in one process and one run, on the same initial conditions, `dt` and `n_steps`:

- three variants of `clebsch_jax.integrate(rigid_body(inertia), Q0, xi0, dt=dt, n_steps=n, ...)`:

  - **full** (`reduce=False`): Newton on the Lemma 20 residual for $(\xi^n, P^n, Q^{n+1})$
    every step (21 unknowns), then the nodal velocities;
  - **reduced** (`reduce=True`, `reconstruct=True`): Theorem 27 / Corollary 29, Newton for
    $\xi^n$ only (3 unknowns) from the body momentum, $Q^{n+1}$ reconstructed explicitly;
  - **reduced_no_Q** (`reduce=True`, `reconstruct=False`): the same without $Q$
    (`Solution.Q is None`, so no orthogonality error);

  each for one trajectory as a plain call, and for a batch of B bodies as
  `jax.jit(jax.vmap(...))` with `throw=False` (failures are checked after the timing);
- **NumPy RK4**: classical RK4 of Euler's equations $\mathbb I\dot\omega = (\mathbb I\omega)
  \times\omega$ with $\dot Q = Q\hat\omega$, vectorised over the batch by broadcasting (a Python
  loop over steps, none over bodies). Like `integrate` it stores the whole trajectory.

Method (the harness shared by the benchmarks, `_timing.py`; as diffrax
`benchmarks/against_scan.py`): one warm-up call compiles; every call ends in
`jax.block_until_ready`; a timing sample is `number` back-to-back calls with `number` chosen so
a sample lasts at least `--min-sample` seconds; the reported time is the median of `--repeats`
samples, wall time by `time.perf_counter`. The samples of the four methods of a case are taken
in turn (round robin), so a change of machine load hits all of them alike. Compile time =
first call minus the median compiled call. Accuracy at that `dt` is reported
for context only.

Outputs (in `--out`, default `benchmarks/results` next to this file):
`rigid_body_step_cost.json` (numbers and machine info) and `rigid_body_step_cost.png`
(time per body-step against batch size, log-log, and the full/reduced ratio). Nothing here
asserts a wall time.
"""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import _timing as harness
import clebsch_jax as cj
from clebsch_jax import diagnostics

INERTIA = (2.0, 1.0, 2.0 / 3.0)  # the standard test body
DT = 0.05
SEED = 0

# The variants of our march: (name, keywords passed to `integrate`, expected `Solution.form`,
# whether `Solution.Q` is computed).
VARIANTS = (
    ("full", {"reduce": False}, "full", True),
    ("reduced", {"reduce": True, "reconstruct": True}, "reduced", True),
    ("reduced_no_Q", {"reduce": True, "reconstruct": False}, "reduced", False),
)
VARIANT_NAMES = tuple(v[0] for v in VARIANTS)
RK4 = "numpy_rk4"
METHODS = VARIANT_NAMES + (RK4,)
# The target: the reduced step at least this many times cheaper than the full step.
TARGET_FULL_OVER_REDUCED = 10.0

# (label, batch size or None for one plain `integrate` call, n_steps). n_steps shrinks with
# the batch so a compiled call of the full march lasts ~0.2-2 s. Every (case, variant) is a
# new program to compile (~4-12 s each on 2 cores), so the default run (~2.5 min) is mostly
# compilation; B = 10 is left out to keep it short.
DEFAULT_CASES = (
    ("single", None, 1000),
    ("vmap", 1, 1000),
    ("vmap", 100, 100),
    ("vmap", 1000, 20),
)
QUICK_CASES = (
    ("single", None, 10),
    ("vmap", 4, 10),
)

RESULTS_NAME = "rigid_body_step_cost"


# --------------------------------------------------------------------------------------------
# The peer: classical RK4 of Euler's equations with reconstruction, in NumPy.


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a × b over the last axis, broadcasting (component-wise: cheaper than np.cross here)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a1 * b2 - a2 * b1
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


def euler_rhs(inertia: np.ndarray, omega: np.ndarray, Q: np.ndarray):
    r"""$\dot\omega = ((\mathbb I\omega)\times\omega)/\mathbb I$ and $\dot Q = Q\hat\omega$
    (row i of $Q\hat\omega$ is $Q_{i\cdot}\times\omega$). Shapes (B, 3) and (B, 3, 3)."""
    return _cross(inertia * omega, omega) / inertia, _cross(Q, omega[..., None, :])


def rk4_march(inertia: np.ndarray, Q0: np.ndarray, omega0: np.ndarray, dt: float, n_steps: int):
    """Classical RK4, vectorised over the batch; returns the trajectory (omega, Q), each with a
    leading time axis of length n_steps + 1."""
    omega, Q = omega0.copy(), Q0.copy()
    omegas = np.empty((n_steps + 1,) + omega.shape)
    Qs = np.empty((n_steps + 1,) + Q.shape)
    omegas[0], Qs[0] = omega, Q
    h = 0.5 * dt
    for n in range(n_steps):
        k1w, k1q = euler_rhs(inertia, omega, Q)
        k2w, k2q = euler_rhs(inertia, omega + h * k1w, Q + h * k1q)
        k3w, k3q = euler_rhs(inertia, omega + h * k2w, Q + h * k2q)
        k4w, k4q = euler_rhs(inertia, omega + dt * k3w, Q + dt * k3q)
        omega = omega + (dt / 6.0) * (k1w + 2.0 * k2w + 2.0 * k3w + k4w)
        Q = Q + (dt / 6.0) * (k1q + 2.0 * k2q + 2.0 * k3q + k4q)
        omegas[n + 1], Qs[n + 1] = omega, Q
    return omegas, Qs


# --------------------------------------------------------------------------------------------
# One case: the three variants of ours and RK4 on the same initial conditions.


def initial_conditions(batch: int, seed: int = SEED):
    """B random unit body momenta m; returns Q0 = identity (B, 3, 3) and xi0 = omega0 = m / I (B, 3)."""
    m = np.random.default_rng(seed).normal(size=(batch, 3))
    m /= np.linalg.norm(m, axis=1, keepdims=True)
    omega0 = m / np.asarray(INERTIA)
    Q0 = np.broadcast_to(np.eye(3), (batch, 3, 3)).copy()
    return Q0, omega0


def _max_rel_energy_error(E: np.ndarray) -> float:
    E = np.asarray(E, dtype=float)
    return float(np.max(np.abs(E - E[..., :1]) / np.abs(E[..., :1])))


def _max_orthogonality_error(Q: np.ndarray) -> float:
    Q = np.asarray(Q, dtype=float)
    return float(np.max(np.abs(np.swapaxes(Q, -1, -2) @ Q - np.eye(3))))


def _per_step(timing: dict, batch: int, n_steps: int) -> dict:
    per_call = timing["per_call_s"]
    return {
        "seconds_per_step": per_call / n_steps,
        "seconds_per_body_step": per_call / (n_steps * batch),
        "body_steps_per_second": n_steps * batch / per_call,
    }


def ours_call(system, batch, n_steps, Q0, omega0, kwargs, compiler_options=None, batching=jax.vmap):
    """A blocking call of one variant of our march on the initial conditions (Q0, omega0):
    for `batch` None one plain `integrate` call on the first body, else
    `jax.jit(batching(integrate))` over all of them (`jax.vmap`, or e.g. `cj.batch`)."""
    if batch is None:  # one trajectory, the plain public call (validation and failure check included)
        Q0_j, xi0_j = jnp.asarray(Q0[0]), jnp.asarray(omega0[0])

        def call():
            return jax.block_until_ready(cj.integrate(system, Q0_j, xi0_j, dt=DT, n_steps=n_steps, **kwargs))

        return call

    Q0_j, xi0_j = jnp.asarray(Q0), jnp.asarray(omega0)
    march = jax.jit(
        batching(lambda q, x: cj.integrate(system, q, x, dt=DT, n_steps=n_steps, throw=False, **kwargs)),
        compiler_options=compiler_options,
    )

    def call():
        return jax.block_until_ready(march(Q0_j, xi0_j))

    return call


def _variant_report(system, sol, timing: dict, B: int, n_steps: int, sol_full) -> dict:
    """Timing, accuracy and Newton statistics of one variant (outside the timings)."""
    E = np.asarray(diagnostics.energy(system, sol))
    iters = np.asarray(sol.stats.iterations, dtype=float).reshape(B, n_steps)
    nodal = np.asarray(sol.nodal_stats.iterations, dtype=float).reshape(B, n_steps + 1)
    # engines whose Newton reuses a Jacobian (chord steps) also count the Jacobians formed
    jacobians = getattr(sol.stats, "jacobians", None)
    jacobians = None if jacobians is None else np.asarray(jacobians, dtype=float).reshape(B, n_steps)
    return {
        **_per_step(timing, B, n_steps),
        **timing,
        "compile_s": timing["first_call_s"] - timing["per_call_s"],
        "form": sol.form,
        "Q_computed": sol.Q is not None,
        "max_rel_energy_error": _max_rel_energy_error(E),
        # None when Q is not computed (reduced_no_Q)
        "max_orthogonality_error": None if sol.Q is None else _max_orthogonality_error(sol.Q),
        # same trajectory as the full march? (nodal velocities; None for the full march itself)
        "max_abs_xi_diff_vs_full": None
        if sol is sol_full
        else float(np.max(np.abs(np.asarray(sol.xi) - np.asarray(sol_full.xi)))),
        "newton_iterations_per_step_mean": float(iters.mean()),
        "newton_iterations_per_step_max": float(iters.max()),
        # under vmap the Newton while_loop runs until the slowest member has converged
        "newton_iterations_per_step_slowest_member_mean": float(iters.max(axis=0).mean()),
        "newton_jacobians_per_step_mean": None if jacobians is None else float(jacobians.mean()),
        "newton_jacobians_per_step_slowest_member_mean": None
        if jacobians is None
        else float(jacobians.max(axis=0).mean()),
        "nodal_newton_iterations_per_node_mean": float(nodal.mean()),
    }


def run_case(label: str, batch: int | None, n_steps: int, run: harness.Run) -> dict:
    system = cj.models.rigid_body(jnp.asarray(INERTIA))
    inertia = np.asarray(INERTIA)
    B = 1 if batch is None else batch
    Q0, omega0 = initial_conditions(B)
    name = f"{label} B={B} n_steps={n_steps}"

    calls = {
        v: ours_call(system, batch, n_steps, Q0, omega0, kwargs, run.compiler_options) for v, kwargs, _, _ in VARIANTS
    }
    calls[RK4] = lambda: rk4_march(inertia, Q0, omega0, DT, n_steps)
    timings, outs = run.time(calls, what=name)

    for v, kwargs, form, has_Q in VARIANTS:
        sol = outs[v].raise_if_failed()
        if sol.form != form or (sol.Q is not None) != has_Q:
            raise RuntimeError(
                f"{name}: integrate(..., {', '.join(f'{k}={x!r}' for k, x in kwargs.items())}) ran "
                f"form={sol.form!r} with Q {'computed' if sol.Q is not None else 'not computed'}; the "
                f"'{v}' variant expects form={form!r} with Q {'computed' if has_Q else 'not computed'}."
            )

    row = {
        "case": label,
        "batch": B,
        "n_steps": n_steps,
        "t_final": n_steps * DT,
        "call": (
            "integrate(system, Q0, xi0, dt=dt, n_steps=n, **variant)"
            if batch is None
            else "jax.jit(jax.vmap(lambda Q0, xi0: integrate(system, Q0, xi0, dt=dt, n_steps=n, throw=False, **variant)))"
        ),
    }
    # accuracy at this dt and Newton statistics, for context (outside the timings)
    with run.guard(f"diagnostics, {name}"):
        for v in VARIANT_NAMES:
            row[v] = _variant_report(system, outs[v], timings[v], B, n_steps, outs["full"])
    omegas, Qs = outs[RK4]
    E_rk4 = 0.5 * np.sum(inertia * omegas**2, axis=-1)  # (n_steps + 1, B)
    row[RK4] = {
        **_per_step(timings[RK4], B, n_steps),
        **timings[RK4],
        "max_rel_energy_error": _max_rel_energy_error(E_rk4.T),
        "max_orthogonality_error": _max_orthogonality_error(Qs),
    }
    per = {m: row[m]["seconds_per_body_step"] for m in METHODS}
    row["ratios"] = {
        **{f"{v}_over_rk4_per_body_step": per[v] / per[RK4] for v in VARIANT_NAMES},
        # the target ratio: how many times cheaper the reduced step is than the full one
        "full_over_reduced": per["full"] / per["reduced"],
        "full_over_reduced_no_Q": per["full"] / per["reduced_no_Q"],
    }
    return row


# --------------------------------------------------------------------------------------------
# Printing and plotting.


_SHORT = {"full": "full", "reduced": "reduced", "reduced_no_Q": "reduced_no_Q", RK4: "NumPy RK4"}


def print_report(summary: dict) -> None:
    cfg, rows = summary["config"], summary["results"]
    fmt = harness.fmt
    harness.print_header(
        summary,
        f"Rigid body, inertia {cfg['inertia_label']}, dt = {cfg['dt']}",
        "Variants of integrate: full = reduce=False (21 unknowns per step); reduced = reduce=True "
        "(3 unknowns, Q reconstructed);\n  reduced_no_Q = reduce=True, reconstruct=False (Q not computed). "
        "'single' = one plain integrate(...) call;\n  'vmap' = jax.jit(jax.vmap(integrate)) over B bodies.",
    )

    print("\nWall time per body-step [s] (body-steps per second):")
    harness.print_table(
        f"{'case':<7}{'B':>5}{'steps':>7} |" + "".join(f"{_SHORT[m]:>21}" for m in METHODS),
        (
            f"{r['case']:<7}{r['batch']:>5}{r['n_steps']:>7} |"
            + "".join(f"{r[m]['seconds_per_body_step']:>10.3e} ({r[m]['body_steps_per_second']:8.2e})" for m in METHODS)
            for r in rows
        ),
    )

    print(
        "\nRatios of time per body-step (full/reduced = how many times cheaper the reduced step is; "
        "X/RK4 > 1: X is slower than RK4):"
    )
    cols = ("full/reduced", "full/reduced_no_Q", "full/RK4", "reduced/RK4", "reduced_no_Q/RK4")

    def ratio_cells(q):
        return (
            f"{q['full_over_reduced']:.3g}x",
            f"{q['full_over_reduced_no_Q']:.3g}x",
            *(f"{q[f'{v}_over_rk4_per_body_step']:.3g}" for v in VARIANT_NAMES),
        )

    harness.print_table(
        f"{'case':<7}{'B':>5} |" + "".join(f"{c:>18}" for c in cols),
        (f"{r['case']:<7}{r['batch']:>5} |" + "".join(f"{x:>18}" for x in ratio_cells(r["ratios"])) for r in rows),
    )
    target = summary["target_full_over_reduced"]
    met = [r for r in rows if r["ratios"]["full_over_reduced"] >= target]
    ratios = [r["ratios"]["full_over_reduced"] for r in rows]
    print(
        f"Issue target, reduced step >= {target:g}x cheaper than the full step (full/reduced): met in "
        f"{len(met)} of {len(rows)} cases (full/reduced from {min(ratios):.3g}x to {max(ratios):.3g}x)."
    )

    print("\nCompile time [s] (first call minus a compiled call: tracing + XLA compilation):")
    harness.print_table(
        f"{'case':<7}{'B':>5}{'steps':>7} |" + "".join(f"{v:>14}" for v in VARIANT_NAMES),
        (
            f"{r['case']:<7}{r['batch']:>5}{r['n_steps']:>7} |"
            + "".join(f"{r[v]['compile_s']:>14.1f}" for v in VARIANT_NAMES)
            for r in rows
        ),
    )

    print(
        "\nAccuracy at this dt, for context (max over the run and the batch); "
        "max|xi - xi_full|: nodal velocities against the full march:"
    )

    def accuracy_cells(r):
        e = "".join(fmt(r[m]["max_rel_energy_error"], ".2e", w, "n/a") for m, w in zip(METHODS, (12, 10, 10, 10)))
        o = "".join(fmt(r[m]["max_orthogonality_error"], ".2e", w, "n/a") for m, w in zip(METHODS, (13, 10, 10, 10)))
        x = "".join(
            fmt(r[v]["max_abs_xi_diff_vs_full"], ".2e", w, "n/a") for v, w in (("reduced", 14), ("reduced_no_Q", 10))
        )
        return f"{r['case']:<7}{r['batch']:>5}{r['t_final']:>6.3g} | {e} | {o} | {x}"

    harness.print_table(
        f"{'case':<7}{'B':>5}{'T':>6} | {'rel dE: full':>12}{'reduced':>10}{'red_no_Q':>10}{'RK4':>10} | "
        f"{'|QtQ-I|: full':>13}{'reduced':>10}{'red_no_Q':>10}{'RK4':>10} | {'|dxi|: reduced':>14}{'red_no_Q':>10}",
        map(accuracy_cells, rows),
    )

    print(
        "\nNewton updates per step solve (mean, max; under vmap also the mean of the slowest member), "
        "Jacobians formed per step, nodal-velocity updates per node:"
    )
    for r in rows:
        for v in VARIANT_NAMES:
            o = r[v]
            slowest = (
                f", slowest member {o['newton_iterations_per_step_slowest_member_mean']:.2f}" if r["batch"] > 1 else ""
            )
            jac = o.get("newton_jacobians_per_step_mean")
            jac_slow = (
                f" (slowest member {o['newton_jacobians_per_step_slowest_member_mean']:.2f})"
                if r["batch"] > 1 and jac is not None
                else ""
            )
            jac = "" if jac is None else f"; Jacobians: mean {jac:.2f}{jac_slow}"
            print(
                f"  {r['case']:<6} B={r['batch']:<5} {v:<13} updates: mean "
                f"{o['newton_iterations_per_step_mean']:.2f}, max {o['newton_iterations_per_step_max']:.0f}"
                f"{slowest}{jac}; nodal: mean {o['nodal_newton_iterations_per_node_mean']:.2f}"
            )


_STYLE = {  # method -> (marker, line style, colour, legend label for the batched curve)
    "full": ("o", "-", "C0", "full march (reduce=False)"),
    "reduced": ("^", "-", "C2", "reduced (reduce=True)"),
    "reduced_no_Q": ("v", "--", "C3", "reduced, reconstruct=False"),
    RK4: ("s", "-", "C1", "NumPy RK4 (broadcast over bodies)"),
}


def plot(summary: dict, path: Path) -> None:
    rows = summary["results"]
    by_case = harness.rows_by(rows)
    vmap_rows, single = by_case.get("vmap", []), by_case.get("single", [])
    fig, (ax, ax_r) = harness.figure((3, 2))
    hollow = harness.hollow_marker("hollow: one plain integrate call\n(RK4: same single trajectory)")

    B = [r["batch"] for r in vmap_rows]
    for m in METHODS:
        marker, ls, color, label = _STYLE[m]
        ax.loglog(B, [r[m]["seconds_per_body_step"] for r in vmap_rows], marker=marker, ls=ls, color=color, label=label)
        for r in single:
            ax.loglog([1], [r[m]["seconds_per_body_step"]], marker=marker, mfc="none", ms=11, ls="none", color=color)
    ax.set_xlabel("batch size B (bodies); ours: jit(vmap(integrate))")
    ax.set_ylabel("wall time per body-step [s]")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(handles=ax.get_legend_handles_labels()[0] + [hollow], fontsize=8)
    ax.set_title(harness.plot_title(summary, f"Rigid body, dt = {summary['config']['dt']}"), fontsize=9)

    target = summary["target_full_over_reduced"]
    for v in ("reduced", "reduced_no_Q"):
        marker, ls, color, _ = _STYLE[v]
        key = f"full_over_{v}"
        ax_r.semilogx(B, [r["ratios"][key] for r in vmap_rows], marker=marker, ls=ls, color=color, label=f"full / {v}")
        for r in single:
            ax_r.semilogx([1], [r["ratios"][key]], marker=marker, mfc="none", ms=11, ls="none", color=color)
    ax_r.axhline(target, color="k", ls=":", lw=1.0, label=f"issue target {target:g}x")
    ax_r.axhline(1.0, color="k", lw=0.8)
    top = max([target] + [r["ratios"][k] for r in rows for k in ("full_over_reduced", "full_over_reduced_no_Q")])
    ax_r.set_ylim(0, 1.15 * top)
    ax_r.set_xlabel("batch size B (bodies)")
    ax_r.set_ylabel("full / reduced (time per body-step)")
    ax_r.grid(True, which="both", alpha=0.3)
    ax_r.legend(handles=ax_r.get_legend_handles_labels()[0] + [hollow], fontsize=8, loc="lower right")
    ax_r.set_title("how many times cheaper the reduced step is", fontsize=9)
    fig.savefig(path, dpi=120)


# --------------------------------------------------------------------------------------------


def main(argv=None) -> dict:
    """Runs the cases, prints the report, writes the JSON and the PNG; returns the summary."""
    with harness.Run(
        RESULTS_NAME,
        argv,
        description="Per-step cost of the full and reduced rigid-body marches "
        "against a NumPy RK4 (see module docstring).",
    ) as run:
        results = run.measure(
            DEFAULT_CASES,
            QUICK_CASES,
            lambda label, batch, n: f"{label} B={batch or 1} n_steps={n}: {', '.join(METHODS)}",
            lambda *case: run_case(*case, run),
        )
    summary = run.summary(
        config={
            "inertia": list(INERTIA),
            "inertia_label": "(2, 1, 2/3)",
            "dt": DT,
            "seed": SEED,
            "initial_conditions": "random unit body momenta m, xi0 = m / I, Q0 = identity",
            "variants": {v: kwargs for v, kwargs, _, _ in VARIANTS},
            "methods": list(METHODS),
            "cases": [{"case": c, "batch": b or 1, "n_steps": n} for c, b, n in run.cases],
        },
        results=results,
        target_full_over_reduced=TARGET_FULL_OVER_REDUCED,
    )
    return run.finish(summary, print_report, plot)


if __name__ == "__main__":
    main()
