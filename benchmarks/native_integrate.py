"""Native kernels for a single trajectory (issue "Native kernels", item 3): `cj.integrate` on the
heavy top with `backend="native"` (the chunk's steps, nodes, nodal velocities and energies made
by one loop kernel, `clebsch_jax.march.native_chunk`) against `backend="xla"` (XLA's compiled
chunk, the path before), in the same process.

Run: `python benchmarks/native_integrate.py` (`--quick` for a smoke run). The case: the heavy
top's default method (the reduced left step paired with its adjoint), Δt = 0.01, 10⁵ steps
(10², 10³ and 10⁴ too: a short call, as in a notebook, costs mostly the call's fixed work); the
whole call, with its checks, its first-step check and the Solution's assembly. Reported: seconds
per call and per step (wall and CPU over all threads), the ratio XLA / native per round
(`_timing.paired_ratios`) and the largest relative difference of the two Solutions'
configurations. The issue's target is a time per step at most 1/20 of XLA's. Nothing is
asserted. Outputs: `benchmarks/results/native_integrate.json` and `.png`.

A second part (`"part": "batch"` rows): `cj.batch` of the same march over members whose ξ⁰
differ a little, called on concrete arrays with `backend="native"` (one native kernel call for
all members, `clebsch_jax.batching.batch_native`) against `jax.jit(cj.batch(...,
backend="xla"))` (the batch-last evaluation compiled by XLA); seconds per member-step after
the first call, and the first call's (compile) time: many members on a short march, and long
marches (the kernel of `integrate`'s traced march does not grow with its number of steps:
`clebsch_jax.native.rows`). `--batch-only` runs this part alone.
"""

from __future__ import annotations

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _timing as harness  # noqa: E402

import clebsch_jax as cj  # noqa: E402

RESULTS_NAME = "native_integrate"
DEFAULT_CASES = ((100,), (1_000,), (10_000,), (100_000,))
QUICK_CASES = ((200,),)
TARGET = 20.0  # XLA's time per step over the native one
DT = 0.01
TOP = cj.models.heavy_top(jnp.array([1.0, 1.0, 0.4]), 1.5)
Q0, XI0 = cj.lie.so3_exp(jnp.array([0.5, 0.0, 0.0])), jnp.array([0.3, -0.2, 2.0])
BACKENDS = ("native", "xla")
BATCH_CASES = ((1_000, 30), (64, 1_000), (1_024, 200))  # (members, steps)
QUICK_BATCH_CASES = ((8, 5),)


def case(n_steps: int, run: harness.Run) -> dict:
    calls = {b: (lambda b=b: cj.integrate(TOP, Q0, XI0, dt=DT, n_steps=n_steps, backend=b)) for b in BACKENDS}
    timings, outs = run.time(calls, what=f"{n_steps} steps")
    Qn, Qx = np.asarray(outs["native"].Q), np.asarray(outs["xla"].Q)
    row = {
        "n_steps": n_steps,
        "method": outs["native"].method,
        "max_difference_Q": float(np.max(np.abs(Qn - Qx))),
    }
    return _timed(row, timings, n_steps)


def batch_case(members: int, n_steps: int, run: harness.Run) -> dict:
    xi0s = XI0 + 0.05 * jnp.asarray(np.random.default_rng(0).normal(size=(members, 3)))
    Q0s = jnp.broadcast_to(Q0, (members, 3, 3))
    march = lambda q, x: cj.integrate(TOP, q, x, dt=DT, n_steps=n_steps, throw=False)
    native, xla = cj.batch(march, backend="native"), jax.jit(cj.batch(march, backend="xla"))
    calls = {
        "native": lambda: native(Q0s, xi0s),
        "xla": lambda: jax.block_until_ready(xla(Q0s, xi0s)),
    }
    timings, outs = run.time(calls, what=f"batch of {members} x {n_steps} steps")
    Qn, Qx = np.asarray(outs["native"].Q), np.asarray(outs["xla"].Q)
    row = {
        "part": "batch",
        "members": members,
        "n_steps": n_steps,
        "method": outs["native"].method,
        "max_difference_Q": float(np.max(np.abs(Qn - Qx))),
    }
    return _timed(row, timings, members * n_steps)  # per member-step


def _trajectories(summary: dict) -> list:
    return [r for r in summary["results"] if r.get("part") != "batch"]


def _timed(row: dict, timings: dict, steps: int) -> dict:
    """`row` with each backend's times per step (a call's time over its `steps`), its first
    call's, and the ratios XLA / native."""
    for b in BACKENDS:
        t = timings[b]
        row[b] = {
            "per_call_s": t["per_call_s"],
            "cpu_per_call_s": t["cpu_per_call_s"],
            "per_step_s": t["per_call_s"] / steps,
            "cpu_per_step_s": t["cpu_per_call_s"] / steps,
            "first_call_s": t["first_call_s"],
            "samples_s": t["samples_s"],
        }
    row["xla_over_native"] = harness.paired_ratios(timings["xla"]["samples_s"], timings["native"]["samples_s"])
    row["xla_over_native_cpu"] = timings["xla"]["cpu_per_call_s"] / timings["native"]["cpu_per_call_s"]
    return row


def print_report(summary: dict) -> None:
    harness.print_header(
        summary,
        f"integrate on the heavy top ({summary['results'][0]['method']}), dt = {DT}",
        "native: backend='native' (one loop kernel per chunk); xla: backend='xla' (XLA's chunk)",
    )
    head = (
        f"{'steps':>8} {'native ms/call':>15} {'xla ms/call':>12} {'native us/step':>15} {'xla us/step':>12} "
        f"{'xla/native':>11} {'(min..max)':>14} {'cpu ratio':>10} {'|dQ|':>9}"
    )
    lines = []
    for r in _trajectories(summary):
        ratio = r["xla_over_native"]
        lines.append(
            f"{r['n_steps']:>8} {r['native']['per_call_s'] * 1e3:>15.2f} {r['xla']['per_call_s'] * 1e3:>12.2f} "
            f"{r['native']['per_step_s'] * 1e6:>15.3f} {r['xla']['per_step_s'] * 1e6:>12.3f} "
            f"{ratio['median']:>11.1f} {ratio['min']:>6.1f}..{ratio['max']:<6.1f} {r['xla_over_native_cpu']:>10.1f} "
            f"{r['max_difference_Q']:>9.1e}"
        )
    harness.print_table(head, lines)
    print(f"target: xla/native >= {TARGET:g} (the issue's single-trajectory target)")
    head = f"{'members':>8} {'steps':>6} {'native us/member-step':>22} {'xla us/member-step':>19} {'xla/native':>11} {'first call native / xla s':>26} {'|dQ|':>9}"
    lines = []
    for r in summary["results"]:
        if r.get("part") == "batch":
            lines.append(
                f"{r['members']:>8} {r['n_steps']:>6} {r['native']['per_step_s'] * 1e6:>22.4f} "
                f"{r['xla']['per_step_s'] * 1e6:>19.4f} {r['xla_over_native']['median']:>11.1f} "
                f"{r['native']['first_call_s']:>12.1f} / {r['xla']['first_call_s']:<11.1f} {r['max_difference_Q']:>9.1e}"
            )
    print("cj.batch of the march: native (concrete call) against jax.jit(cj.batch(..., backend='xla'))")
    harness.print_table(head, lines)


def plot(summary: dict, path: Path) -> None:
    fig, (ax, bx) = harness.figure((1, 1))
    rows = _trajectories(summary)
    n = [r["n_steps"] for r in rows]
    for b, marker in zip(BACKENDS, "os"):
        ax.loglog(n, [r[b]["per_step_s"] * 1e6 for r in rows], marker=marker, label=f"{b} (wall)")
        ax.loglog(n, [r[b]["cpu_per_step_s"] * 1e6 for r in rows], marker=marker, ls=":", label=f"{b} (CPU)")
    ax.set_xlabel("steps per call")
    ax.set_ylabel("µs per step")
    ax.legend()
    bx.semilogx(n, [r["xla_over_native"]["median"] for r in rows], marker="o", label="wall, paired median")
    bx.semilogx(n, [r["xla_over_native_cpu"] for r in rows], marker="s", ls=":", label="CPU")
    bx.axhline(TARGET, color="0.5", ls="--", label=f"target {TARGET:g}×")
    bx.set_xlabel("steps per call")
    bx.set_ylabel("XLA time per step / native")
    bx.legend()
    fig.suptitle(harness.plot_title(summary, "integrate, heavy top: native kernel against XLA's chunk"))
    fig.savefig(path, dpi=120)


def main(argv=None) -> dict:
    only = lambda parser: parser.add_argument("--batch-only", action="store_true", help="the cj.batch part alone")
    with harness.Run(RESULTS_NAME, argv, description=__doc__.splitlines()[0], add_arguments=only) as run:
        rows = []
        if not run.args.batch_only:
            rows += run.measure(DEFAULT_CASES, QUICK_CASES, lambda n: f"{n} steps", lambda n: case(n, run))
        rows += run.measure(
            BATCH_CASES, QUICK_BATCH_CASES, lambda b, n: f"batch of {b} x {n} steps", lambda b, n: batch_case(b, n, run)
        )
    summary = run.summary(config={"dt": DT, "target_xla_over_native": TARGET}, results=rows)
    return run.finish(summary, print_report, plot)


if __name__ == "__main__":
    main()
