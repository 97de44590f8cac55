r"""Per-step cost of the variational (midpoint) march of planar point vortices, next to a NumPy RK4.

Run from the repository root:

    python benchmarks/vortex_step_cost.py            # default run, ~3-5 min on 2 cores (14 compiles)
    python benchmarks/vortex_step_cost.py --quick    # smoke test, tiny sizes (not a measurement)

What is timed, in one process and one run, on the same initial conditions, `dt` and `n_steps`:

- **ours**: `clebsch_jax.integrate(point_vortices(G), Q0, vortex_velocity(G, Q0), dt=dt,
  n_steps=n, jacobian=...)` — the midpoint principle of a degenerate Lagrangian, which for
  point vortices is the implicit midpoint rule, each step solved to round-off
  (`rtol = atol = 0`), with

  - **blocks** (`jacobian="blocks"`): chord iterations with the lumped block-diagonal
    Jacobian, one 2×2 block per vortex (`clebsch_jax.roots.blocks`), for every N;
  - **dense** (`jacobian="dense"`, the default): Newton with the dense (2N)×(2N) Jacobian,
    only for N = 4;

  for one system as a plain call (the system and `xi0` built once, outside the timing), and
  for a batch of B systems as `jax.jit(jax.vmap(lambda G, Q0: integrate(point_vortices(G), Q0,
  vortex_velocity(G, Q0), ..., throw=False)))` (failures are checked after the timing);
- **NumPy RK4**: classical RK4 of the Biot–Savart velocities
  $\dot Q_a = \sum_{b\ne a} \frac{\Gamma_b}{2\pi} \frac{(-(y_a - y_b),\ x_a - x_b)}{|Q_a - Q_b|^2}$,
  broadcast over all pairs and over the batch (a Python loop over the steps only), four
  velocity evaluations per step. Like `integrate` it stores the whole trajectory.

Two costs per step of ours are reported. `seconds_per_step` (the headline, and the only one for
RK4) is per step of one long call: the median call time divided by `n_steps`, the call's fixed
cost included. A call of ours has a fixed cost besides its steps: input validation (a few
`jax.eval_shape` traces, plain calls only), the initial multiplier (a dense least-squares solve
by SVD for up to 256 unknowns, i.e. N <= 128 vortices, which alone takes ~10-800 ms at
N = 100-128 on 2 busy cores, conjugate gradients above) and the failure check. So each variant
of ours is also called with `n_short` steps, interleaved with the rest, and
`marginal_seconds_per_step` = (t(n_steps) - t(n_short)) / (n_steps - n_short), the cost of one
more step, and `fixed_cost_per_call_s` = t(n_short) - n_short * marginal are reported beside it.
The marginal cost is what a long run pays per step; being a difference of two noisy times, it
is the noisier of the two.

Method (the harness shared by the benchmarks, `_timing.py`): a first call of each method compiles; every call ends in
`jax.block_until_ready`; one more call fixes `number`, the calls per sample, so that a sample
lasts at least `--min-sample` seconds; then `--repeats` rounds each take one sample of every
method of the case in turn (the starting method rotates from round to round), so a change of
machine load hits all methods alike. The reported time is the median over samples of (sample
time / number), wall time by `time.perf_counter`. The ratio ours/RK4 is the ratio of these
medians; the ratios of the two samples of each round (taken back to back) are reported as a
check when the load drifts. CPU time of the process per call (all threads) is reported too:
XLA may use both cores, NumPy here uses one. Compile time = first call minus the second call
(made right after it, under the same load). Accuracy (final positions against RK4, drift of
the linear impulse and of H) is reported for context only.

Outputs (in `--out`, default `benchmarks/results` next to this file): `vortex_step_cost.json`
(numbers and machine info) and `vortex_step_cost.png` (seconds per step against N, log-log,
and the ratio ours/RK4). Nothing here asserts a wall time.
"""

from __future__ import annotations

import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import _timing as harness
import clebsch_jax as cj
from clebsch_jax import models

DT = 0.01
SEED = 0
RK4 = "numpy_rk4"
JACOBIANS = ("blocks", "dense")  # the variants of ours: the `jacobian=` keyword of `integrate`
METHODS = JACOBIANS + (RK4,)
# The target: at N = 1000 one variational step costs at most 3x one RK4 step.
TARGET_N = 1000
TARGET_OURS_OVER_RK4 = 3.0

# (label, N vortices, batch size B or None for one plain `integrate` call, n_steps, n_short,
# variants of ours). n_steps makes a compiled call of ours last ~0.2-2 s on an idle 2-core
# machine; at N = 1000 a step costs ~0.4-1 s, so 7 steps there. Each variant of ours is also
# called with n_short steps (None: not), interleaved with the rest, to separate a call's fixed
# cost from its cost per step (see the module docstring). Every (case, variant, n) is a program
# to compile (~3-12 s each on 2 cores).
DEFAULT_CASES = (
    ("single", 4, None, 2000, 200, ("blocks", "dense")),
    ("single", 100, None, 100, 10, ("blocks",)),
    ("single", 1000, None, 7, 2, ("blocks",)),
    ("vmap", 4, 100, 200, 20, ("blocks", "dense")),
    ("vmap", 100, 10, 24, 4, ("blocks",)),
)
QUICK_CASES = (
    ("single", 4, None, 10, None, ("blocks", "dense")),
    ("vmap", 4, 3, 6, 2, ("blocks",)),
)

RESULTS_NAME = "vortex_step_cost"


# --------------------------------------------------------------------------------------------
# Initial conditions and the peer: classical RK4 of the Biot–Savart velocities, in NumPy.


def initial_conditions(n_vortices: int, batch: int, seed: int = SEED):
    """B systems of N vortices: circulations uniform(0.5, 1.5) with a random sign, positions
    standard normal times sqrt(N) (mean spacing ~1 whatever N). Shapes (B, N) and (B, N, 2)."""
    rng = np.random.default_rng(seed)
    gamma = rng.uniform(0.5, 1.5, (batch, n_vortices)) * rng.choice([-1.0, 1.0], (batch, n_vortices))
    Q0 = rng.normal(size=(batch, n_vortices, 2)) * math.sqrt(n_vortices)
    return gamma, Q0


def biot_savart(gamma: np.ndarray, Q: np.ndarray) -> np.ndarray:
    r"""Velocities of B systems of N vortices, shapes (B, N) and (B, N, 2) -> (B, N, 2):
    $\dot x_a = -\sum_b w_{ab}(y_a - y_b)$, $\dot y_a = \sum_b w_{ab}(x_a - x_b)$ with
    $w_{ab} = \Gamma_b / (2\pi|Q_a - Q_b|^2)$ and $w_{aa} = 0$, over all pairs at once."""
    d = Q[:, :, None, :] - Q[:, None, :, :]  # (B, N, N, 2): Q_a - Q_b
    r2 = d[..., 0] ** 2 + d[..., 1] ** 2
    idx = np.arange(Q.shape[1])
    r2[:, idx, idx] = np.inf  # no self-interaction: w_aa = 0
    w = gamma[:, None, :] / (2.0 * np.pi * r2)
    out = np.empty_like(Q)
    out[..., 0] = -np.einsum("bij,bij->bi", w, d[..., 1])
    out[..., 1] = np.einsum("bij,bij->bi", w, d[..., 0])
    return out


def rk4_march(gamma: np.ndarray, Q0: np.ndarray, dt: float, n_steps: int) -> np.ndarray:
    """Classical RK4 for B systems at once; returns the trajectory (n_steps + 1, B, N, 2)."""
    Q = Q0.copy()
    Qs = np.empty((n_steps + 1,) + Q.shape)
    Qs[0] = Q
    h = 0.5 * dt
    for n in range(n_steps):
        k1 = biot_savart(gamma, Q)
        k2 = biot_savart(gamma, Q + h * k1)
        k3 = biot_savart(gamma, Q + h * k2)
        k4 = biot_savart(gamma, Q + dt * k3)
        Q = Q + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        Qs[n + 1] = Q
    return Qs


# --------------------------------------------------------------------------------------------
# One case.


def ours_call(N, batch, n_steps, gamma, Q0, jacobian, compiler_options=None, batching=jax.vmap):
    """A blocking call of our march on the initial conditions (gamma, Q0) of shapes (B, N) and
    (B, N, 2): for `batch` None one plain `integrate` call on the first system, else
    `jax.jit(batching(integrate))` over all of them (`jax.vmap`, or e.g. `cj.batch`)."""
    if batch is None:  # one system: the plain public call (validation and failure check included)
        G, Q = jnp.asarray(gamma[0]), jnp.asarray(Q0[0])
        system, xi0 = models.point_vortices(G), models.vortex_velocity(G, Q)

        def call():
            return jax.block_until_ready(cj.integrate(system, Q, xi0, dt=DT, n_steps=n_steps, jacobian=jacobian))

        return call

    G, Q = jnp.asarray(gamma), jnp.asarray(Q0)
    march = jax.jit(
        batching(
            lambda g, q: cj.integrate(
                models.point_vortices(g),
                q,
                models.vortex_velocity(g, q),
                dt=DT,
                n_steps=n_steps,
                jacobian=jacobian,
                throw=False,
            )
        ),
        compiler_options=compiler_options,
    )

    def call():
        return jax.block_until_ready(march(G, Q))

    return call


def _per_step(timing: dict, N: int, B: int, n_steps: int) -> dict:
    per_step = timing["per_call_s"] / n_steps
    return {
        "seconds_per_step": per_step,  # one step of the whole batch
        "cpu_seconds_per_step": timing["cpu_per_call_s"] / n_steps,
        "seconds_per_vortex_step": per_step / (N * B),
        "vortex_steps_per_second": N * B / per_step,
    }


def _trajectory_checks(gamma: np.ndarray, Qs: np.ndarray) -> dict:
    """Drift of the linear impulse and of H over a trajectory Qs (B, n + 1, N, 2)."""
    lin = np.stack([np.asarray(models.vortex_linear_impulse(g, q)) for g, q in zip(gamma, Qs)])  # (B, n+1, 2)
    H = np.stack([np.asarray(models.vortex_hamiltonian(g, q)) for g, q in zip(gamma, Qs)])  # (B, n+1)
    return {
        "max_linear_impulse_drift": float(np.max(np.abs(lin - lin[:, :1]))),
        "max_rel_hamiltonian_error": float(np.max(np.abs(H - H[:, :1]) / np.abs(H[:, :1]))),
    }


def _short(v: str) -> str:
    return f"{v}_short"


def run_case(label, N, batch, n_steps, n_short, variants, run: harness.Run) -> dict:
    B = 1 if batch is None else batch
    gamma, Q0 = initial_conditions(N, B)
    name = f"{label} N={N} B={B} n_steps={n_steps}"

    calls = {}
    for v in variants:
        calls[v] = ours_call(N, batch, n_steps, gamma, Q0, v, run.compiler_options)
        if n_short:
            calls[_short(v)] = ours_call(N, batch, n_short, gamma, Q0, v, run.compiler_options)
    calls[RK4] = lambda: rk4_march(gamma, Q0, DT, n_steps)
    timings, outs = run.time(calls, what=name)

    row = {
        "case": label,
        "N": N,
        "batch": B,
        "n_steps": n_steps,
        "n_steps_short": n_short,
        "t_final": n_steps * DT,
        "variants": list(variants),
        "call": (
            "integrate(point_vortices(G), Q0, vortex_velocity(G, Q0), dt=dt, n_steps=n, jacobian=v)"
            if batch is None
            else "jax.jit(jax.vmap(lambda G, Q0: integrate(point_vortices(G), Q0, vortex_velocity(G, Q0), "
            "dt=dt, n_steps=n, jacobian=v, throw=False)))"
        ),
    }
    with run.guard(f"diagnostics, {name}"):
        Qs_rk4 = np.moveaxis(outs[RK4], 0, 1)  # (B, n+1, N, 2)
        row[RK4] = {**_per_step(timings[RK4], N, B, n_steps), **timings[RK4], **_trajectory_checks(gamma, Qs_rk4)}
        sols = {}
        for v in variants:
            sol = outs[v].raise_if_failed()
            sols[v] = sol
            Qs = np.asarray(sol.Q).reshape(B, n_steps + 1, N, 2)
            iters = np.asarray(sol.stats.iterations, dtype=float).reshape(B, n_steps)
            jacs = np.asarray(sol.stats.jacobians, dtype=float).reshape(B, n_steps)
            row[v] = {
                **_per_step(timings[v], N, B, n_steps),
                **timings[v],
                # the second call runs right after the first, under the same machine load
                "compile_s": timings[v]["first_call_s"] - timings[v]["second_call_s"],
                "form": sol.form,
                "scheme": sol.scheme,
                # Newton: updates and block (or dense) matrices per step; under vmap the while
                # loops run until the slowest member has converged
                "newton_iterations_per_step_mean": float(iters.mean()),
                "newton_iterations_per_step_max": float(iters.max()),
                "newton_iterations_per_step_slowest_member_mean": float(iters.max(axis=0).mean()),
                "newton_jacobians_per_step_mean": float(jacs.mean()),
                "newton_jacobians_per_step_slowest_member_mean": float(jacs.max(axis=0).mean()),
                "newton_jacobians_first_step_mean": float(jacs[:, 0].mean()),
                "max_residual_norm": float(np.max(np.asarray(sol.stats.residual_norm))),
                "max_abs_final_position_diff_vs_rk4": float(np.max(np.abs(Qs[:, -1] - Qs_rk4[:, -1]))),
                **_trajectory_checks(gamma, Qs),
            }
            if n_short:
                outs[_short(v)].raise_if_failed()
                t_short = timings[_short(v)]
                marginal = (timings[v]["per_call_s"] - t_short["per_call_s"]) / (n_steps - n_short)
                row[v]["short_call"] = {
                    **t_short,
                    "n_steps": n_short,
                    "compile_s": t_short["first_call_s"] - t_short["second_call_s"],
                }
                # (t(n_steps) - t(n_short)) / (n_steps - n_short): the cost of one more step
                row[v]["marginal_seconds_per_step"] = marginal
                row[v]["marginal_vortex_steps_per_second"] = N * B / marginal if marginal > 0 else None
                # t(n) ~ fixed + n * marginal: validation, initial multiplier, failure check, ...
                row[v]["fixed_cost_per_call_s"] = t_short["per_call_s"] - n_short * marginal
        if "dense" in sols and "blocks" in sols:  # the two Newton matrices reach the same root
            row["dense"]["max_abs_Q_diff_vs_blocks"] = float(
                np.max(np.abs(np.asarray(sols["dense"].Q) - np.asarray(sols["blocks"].Q)))
            )
    row["position_scale"] = float(np.max(np.abs(Q0)))  # to read the position differences against
    rk4 = row[RK4]["seconds_per_step"]
    row["ratios"] = {f"{v}_over_rk4": row[v]["seconds_per_step"] / rk4 for v in variants}
    # The same ratios from the samples of one round (taken back to back, so under similar load):
    # median, min and max over the rounds; a check on the ratio of medians when the load drifts.
    per_step_samples = lambda m, n: [t / n for t in timings[m]["samples_s"]]  # noqa: E731
    row["paired_ratios"] = {
        f"{v}_over_rk4": harness.paired_ratios(per_step_samples(v, n_steps), per_step_samples(RK4, n_steps))
        for v in variants
    }
    if n_short:
        for v in variants:
            row["ratios"][f"{v}_marginal_over_rk4"] = row[v]["marginal_seconds_per_step"] / rk4
            marginal = [
                (a - b) / (n_steps - n_short) for a, b in zip(timings[v]["samples_s"], timings[_short(v)]["samples_s"])
            ]
            row["paired_ratios"][f"{v}_marginal_over_rk4"] = harness.paired_ratios(
                marginal, per_step_samples(RK4, n_steps)
            )
    return row


# --------------------------------------------------------------------------------------------
# Printing and plotting.


def print_report(summary: dict) -> None:
    rows, fmt = summary["results"], harness.fmt
    harness.print_header(
        summary,
        f"Planar point vortices, dt = {summary['config']['dt']}",
        "ours = integrate(point_vortices(G), ...) (implicit midpoint, solved to round-off), "
        "jacobian='blocks' or 'dense'; 'single' = one plain call,\n  'vmap' = jax.jit(jax.vmap(integrate)) "
        "over B systems. Per step = median call time / n_steps (one step of the whole batch).",
    )

    def case_cells(r):
        return f"{r['case']:<7}{r['N']:>5}{r['batch']:>5}"

    print("\nWall time per step [s] (vortex-steps per second = N*B / time per step):")

    def step_cells(r):
        cells = "".join(
            f"{'-':>21}"
            if m not in r
            else f"{r[m]['seconds_per_step']:>10.3e} ({r[m]['vortex_steps_per_second']:8.2e})"
            for m in METHODS
        )
        ratios = "".join(fmt(r["ratios"].get(f"{v}_over_rk4"), ".3g", w) for v, w in (("blocks", 12), ("dense", 11)))
        return f"{case_cells(r)}{r['n_steps']:>6} |{cells}{ratios}"

    harness.print_table(
        f"{'case':<7}{'N':>5}{'B':>5}{'steps':>6} |"
        + "".join(f"{m:>21}" for m in ("ours blocks", "ours dense", "NumPy RK4"))
        + f"{'blocks/RK4':>12}{'dense/RK4':>11}",
        map(step_cells, rows),
    )
    t = summary["target"]
    if t["met"] is None:
        verdict = "not measured (no single N = 1000 case in this run)"
    else:
        verdict = f"{'met' if t['met'] else 'NOT met'}: blocks/RK4 = {t['ours_over_rk4']:.3g}"
        if t.get("marginal_ours_over_rk4") is not None:
            verdict += f" (marginal: {t['marginal_ours_over_rk4']:.3g})"
    print(f"Issue target, one variational step <= {t['max_ours_over_rk4']:g}x one RK4 step at N = {t['N']}: {verdict}.")

    print(
        "\nOurs, a call's fixed cost and the cost of one more step, from calls of n_short and n steps "
        "(interleaved with the rest):\n  marginal = (t(n) - t(n_short)) / (n - n_short), fixed = t(n_short) - "
        "n_short * marginal; marginal/RK4 against RK4's time per step:"
    )
    harness.print_table(
        f"{'case':<7}{'N':>5}{'B':>5} {'variant':<7}{'n_short':>8}{'t(n_short)':>12}{'n':>6}{'t(n)':>11} |"
        f"{'marginal s/step':>16}{'fixed s':>10}{'marginal/RK4':>14}{'(per call)/RK4':>16}",
        (
            f"{case_cells(r)} {v:<7}{r['n_steps_short']:>8}"
            f"{r[v]['short_call']['per_call_s']:>12.3e}{r['n_steps']:>6}{r[v]['per_call_s']:>11.3e} |"
            f"{r[v]['marginal_seconds_per_step']:>16.3e}{r[v]['fixed_cost_per_call_s']:>10.3f}"
            f"{r['ratios'][f'{v}_marginal_over_rk4']:>14.3g}{r['ratios'][f'{v}_over_rk4']:>16.3g}"
            for r in rows
            if r["n_steps_short"]
            for v in r["variants"]
        ),
    )

    def members(r):
        return f"  {r['case']:<6} N={r['N']:<5} B={r['batch']:<4}"

    print(
        "\nNewton per step: updates (mean, max; under vmap also the mean of the slowest member) and "
        "matrices formed (blocks: the N 2x2 lumped blocks; dense: one (2N)x(2N) Jacobian):"
    )
    for r in rows:
        for v in r["variants"]:
            o = r[v]
            slow = (
                f" (slowest member {o['newton_iterations_per_step_slowest_member_mean']:.2f})" if r["batch"] > 1 else ""
            )
            slow_j = (
                f" (slowest member {o['newton_jacobians_per_step_slowest_member_mean']:.2f})" if r["batch"] > 1 else ""
            )
            print(
                f"{members(r)} {v:<7} updates "
                f"{o['newton_iterations_per_step_mean']:.2f}{slow}, max {o['newton_iterations_per_step_max']:.0f}; "
                f"matrices {o['newton_jacobians_per_step_mean']:.2f}{slow_j}, first step "
                f"{o['newton_jacobians_first_step_mean']:.2f}; max residual {o['max_residual_norm']:.1e}"
            )

    print(
        "\nPaired ratios ours/RK4 of time per step: per round of samples (taken back to back), "
        "median [min, max] over rounds:"
    )
    for r in rows:
        print(
            members(r)
            + " "
            + ", ".join(
                f"{k.replace('_over_rk4', '')}/RK4 {q['median']:.3g} [{q['min']:.3g}, {q['max']:.3g}]"
                for k, q in r["paired_ratios"].items()
            )
        )

    print("\nCPU time per step [s] of this process, all threads (CPU/wall > 1: more than one core used):")
    for r in rows:
        print(
            members(r)
            + " "
            + ", ".join(
                f"{m} {r[m]['cpu_seconds_per_step']:.3e} "
                f"({r[m]['cpu_seconds_per_step'] / r[m]['seconds_per_step']:.2f})"
                for m in (*r["variants"], RK4)
            )
        )

    print(
        "\nCompile time [s] (first call minus the second call: tracing + XLA compilation; "
        "in brackets the program of n_short steps):"
    )
    for r in rows:
        print(
            members(r)
            + " "
            + ", ".join(
                f"{v} {r[v]['compile_s']:.1f}"
                + (f" ({r[v]['short_call']['compile_s']:.1f})" if "short_call" in r[v] else "")
                for v in r["variants"]
            )
        )

    print(
        "\nAccuracy at this dt, for context (max over nodes and members): |Q - Q_RK4| at t_final "
        "(ours order 2, RK4 order 4; positions of size ~|Q0|max), drift of the linear impulse "
        "sum(G Q), relative drift of H:"
    )

    def accuracy_cells(r):
        def get(m, k):
            return r[m][k] if m in r else None

        dq = "".join(
            fmt(get(v, "max_abs_final_position_diff_vs_rk4"), ".2e", w) for v, w in (("blocks", 11), ("dense", 10))
        )
        dp = "".join(fmt(get(m, "max_linear_impulse_drift"), ".2e", w) for m, w in zip(METHODS, (10, 10, 10)))
        dh = "".join(fmt(get(m, "max_rel_hamiltonian_error"), ".2e", w) for m, w in zip(METHODS, (12, 10, 10)))
        return f"{case_cells(r)}{r['t_final']:>6.3g}{r['position_scale']:>8.3g} | {dq} | {dp} | {dh}"

    harness.print_table(
        f"{'case':<7}{'N':>5}{'B':>5}{'T':>6}{'|Q0|max':>8} | {'|dQ| blocks':>11}{'dense':>10} | "
        f"{'dP: blocks':>10}{'dense':>10}{'RK4':>10} | {'dH/H: blocks':>12}{'dense':>10}{'RK4':>10}",
        map(accuracy_cells, rows),
    )
    for r in rows:
        if "dense" in r and "max_abs_Q_diff_vs_blocks" in r["dense"]:
            print(
                f"  {r['case']} N={r['N']} B={r['batch']}: max |Q_dense - Q_blocks| = "
                f"{r['dense']['max_abs_Q_diff_vs_blocks']:.1e} (same root)"
            )


_STYLE = {  # method -> (marker, colour, label)
    "blocks": ("o", "C0", "ours, jacobian='blocks'"),
    "dense": ("D", "C2", "ours, jacobian='dense'"),
    RK4: ("s", "C1", "NumPy RK4 (broadcast over pairs)"),
}


def plot(summary: dict, path: Path) -> None:
    by_case = harness.rows_by(summary["results"])
    single, batched = by_case.get("single", []), by_case.get("vmap", [])
    fig, (ax, ax_r) = harness.figure((3, 2))
    hollow = harness.hollow_marker("hollow: jit(vmap) batch, time per step / B")

    for m in METHODS:
        marker, color, label = _STYLE[m]
        pts = [(r["N"], r[m]["seconds_per_step"]) for r in single if m in r]
        if pts:
            ax.loglog(*zip(*pts), marker=marker, color=color, ls="-" if len(pts) > 1 else "none", label=label)
        pts = [
            (r["N"], r[m]["marginal_seconds_per_step"])
            for r in single
            if m in r and r[m].get("marginal_seconds_per_step", 0) > 0
        ]
        if pts:
            ax.loglog(*zip(*pts), marker=marker, ms=4, color=color, ls=":", label=f"{label}, marginal")
        for r in batched:
            if m in r:
                ax.loglog(
                    [r["N"]],
                    [r[m]["seconds_per_step"] / r["batch"]],
                    marker=marker,
                    mfc="none",
                    ms=10,
                    ls="none",
                    color=color,
                )
    ax.set_xlabel("N vortices")
    ax.set_ylabel("wall time per step of one system [s]")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(handles=ax.get_legend_handles_labels()[0] + [hollow], fontsize=8)
    ax.set_title(harness.plot_title(summary, f"Point vortices, dt = {summary['config']['dt']}"), fontsize=9)

    for v in JACOBIANS:
        marker, color, _ = _STYLE[v]
        pts = [(r["N"], r["ratios"][f"{v}_over_rk4"]) for r in single if v in r]
        if pts:
            ax_r.semilogx(
                *zip(*pts), marker=marker, color=color, ls="-" if len(pts) > 1 else "none", label=f"{v} / RK4"
            )
        pts = [
            (r["N"], r["ratios"][f"{v}_marginal_over_rk4"])
            for r in single
            if r["ratios"].get(f"{v}_marginal_over_rk4", 0) > 0
        ]
        if pts:
            ax_r.semilogx(*zip(*pts), marker=marker, ms=4, color=color, ls=":", label=f"{v} marginal / RK4")
        for r in batched:
            if v in r:
                ax_r.semilogx(
                    [r["N"]], [r["ratios"][f"{v}_over_rk4"]], marker=marker, mfc="none", ms=10, ls="none", color=color
                )
    t = summary["target"]
    ax_r.plot(
        [t["N"]],
        [t["max_ours_over_rk4"]],
        marker="_",
        ms=30,
        mew=2,
        color="k",
        ls="none",
        label=f"issue target at N = {t['N']}: <= {t['max_ours_over_rk4']:g}x",
    )
    ax_r.axhline(1.0, color="k", lw=0.8)
    ax_r.set_yscale("log")
    ax_r.set_xlabel("N vortices")
    ax_r.set_ylabel("ours / RK4 (time per step)")
    ax_r.grid(True, which="both", alpha=0.3)
    ax_r.legend(
        handles=ax_r.get_legend_handles_labels()[0] + [harness.hollow_marker("hollow: jit(vmap) batch")], fontsize=8
    )
    ax_r.set_title("cost of one variational step in RK4 steps (> 1: ours slower)", fontsize=9)
    fig.savefig(path, dpi=120)


# --------------------------------------------------------------------------------------------


def _describe(label, N, batch, n_steps, n_short, variants) -> str:
    return (
        f"{label} N={N} B={batch or 1} n_steps={n_steps}{'' if n_short is None else f' (and {n_short})'}: "
        f"{', '.join(variants + (RK4,))}"
    )


def main(argv=None) -> dict:
    """Run the benchmark: the cases, the report, the JSON and the PNG; returns the summary."""
    with harness.Run(
        RESULTS_NAME,
        argv,
        description="Per-step cost of the variational point-vortex march against a NumPy RK4 (see module docstring).",
    ) as run:
        results = run.measure(DEFAULT_CASES, QUICK_CASES, _describe, lambda *case: run_case(*case, run))
    at_target = [r for r in results if r["case"] == "single" and r["N"] == TARGET_N]
    target_ratio = at_target[0]["ratios"]["blocks_over_rk4"] if at_target else None
    target_marginal = at_target[0]["ratios"].get("blocks_marginal_over_rk4") if at_target else None
    summary = run.summary(
        config={
            "dt": DT,
            "seed": SEED,
            "initial_conditions": "circulations uniform(0.5, 1.5) * random sign, positions normal * sqrt(N), "
            "xi0 = vortex_velocity(G, Q0)",
            "per_step": "seconds_per_step = per-call time / n_steps",
            "methods": list(METHODS),
            "cases": [
                {"case": c, "N": N, "batch": b or 1, "n_steps": n, "n_steps_short": ns, "variants": list(v)}
                for c, N, b, n, ns, v in run.cases
            ],
        },
        results=results,
        target={
            "N": TARGET_N,
            "max_ours_over_rk4": TARGET_OURS_OVER_RK4,
            "ours_over_rk4": target_ratio,
            "marginal_ours_over_rk4": target_marginal,
            "met": None if target_ratio is None else bool(target_ratio <= TARGET_OURS_OVER_RK4),
        },
    )
    return run.finish(summary, print_report, plot)


if __name__ == "__main__":
    main()
