"""Native kernels (issue "Native kernels"): the documented sweep against the hardware's yardsticks.

Run: `python benchmarks/native.py` (`--quick` for a smoke run; `--threads-only` for the threads
part alone, written to `native_threads.json`; `--rigid-only` for parts 1 and 2, written to
`native_rigid.json`; `--vortices-only` for the vortex clusters alone, written to
`native_vortices.json`). Four parts, in one process (the compile part in
fresh child processes):

1. **Rigid-body sweep** — `cj.sweep(rigid_body, …, reconstruct=False)` with default options
   (`backend="auto"`: the per-member program as a native kernel, `clebsch_jax.native`), the same
   sweep with `backend="xla"` (XLA's paths, the default before the native backend), the
   hand-written JAX rows kernel (`throughput.hand_rows_march`: fixed chord updates, no checks),
   the C kernel with bodies in SIMD lanes (`throughput.c_kernel`, built at run time; skipped
   without a compiler) and NumPy RK4 of Euler's equations, at B = 10³ … 10⁵ (10⁶ with
   `--large`) × 200 steps. M body-steps/s, ratios, energy errors.
2. **Threads** — the native sweep with `threads=1` and `threads=2` at the largest B: the kernels
   release the GIL, so the sweep's threads run batches side by side. Beside it, the C kernel on
   the batch's two halves from two threads against the whole batch on one: the machine's own
   ceiling for two threads (a shared or virtual host may give less than 2).
3. **Compile** — a fresh process's first sweep call minus its second (B = 10⁴ × 200), with an
   empty disk cache of native kernels (cold) and with the cache the first child wrote (warm).
4. **Vortex clusters** — sweeps of 10³ clusters of N = 4 and 10 point vortices (default
   options; `backend="xla"`; `backend="native"`, which compiles the kernel that "auto" leaves
   to XLA for N = 10) against one NumPy RK4 step of the same batch (`vortex_step_cost.rk4_march`).

Timing: `_timing.Run` (the methods of a case sampled in turn, median of repeats, first call
timed apart). Nothing is asserted; the targets of the issue are printed beside the ratios.
Outputs: `benchmarks/results/native.json` and `native.png`.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _timing as harness  # noqa: E402
import rigid_body_step_cost as rigid  # noqa: E402
import throughput  # noqa: E402
import vortex_step_cost as vortex  # noqa: E402

import clebsch_jax as cj  # noqa: E402
from clebsch_jax import models  # noqa: E402

RESULTS_NAME = "native"
SWEEP_DEFAULT = ((1_000, 200), (10_000, 200), (100_000, 200))
SWEEP_LARGE = ((1_000_000, 200),)
SWEEP_QUICK = ((16, 10),)
VORTEX_DEFAULT = ((4, 1000, 100), (10, 1000, 50))
VORTEX_QUICK = ((4, 8, 5),)
COMPILE_CASE = (10_000, 200)
COMPILE_QUICK = (16, 10)
TARGETS = {
    "sweep_over_c_from_1e4": 0.5,
    "sweep_over_c_at_1e3": 0.3,
    "sweep_over_hand": 1.5,
    "compile_cold_s": 1.5,
    "compile_cached_s": 0.2,
    "two_threads_over_one": 1.8,
    "vortex_step_over_rk4_step": 0.5,
}
INERTIA = throughput.SWEEP_INERTIA
C_SIMD, HAND, RK4 = throughput.C_SIMD, throughput.HAND_ROWS, throughput.RK4


def _sweep(inertias, Q0, omega0, n_steps, **extra):
    return lambda: cj.sweep(
        models.rigid_body, inertias, Q0, omega0, dt=rigid.DT, n_steps=n_steps, reconstruct=False, **extra
    )


def rigid_case(batch: int, n_steps: int, run: harness.Run) -> dict:
    omega0 = rigid.initial_conditions(batch)[1]
    inertia = np.asarray(INERTIA)
    inertias = np.broadcast_to(inertia, (batch, 3))
    Q0 = np.broadcast_to(np.eye(3), (batch, 3, 3))
    hand = throughput.hand_rows_march(inertia, rigid.DT, n_steps)
    xi0 = jnp.asarray(omega0)
    calls = {
        "sweep": _sweep(inertias, Q0, omega0, n_steps),
        "sweep_xla": _sweep(inertias, Q0, omega0, n_steps, backend="xla"),
        HAND: lambda: jax.block_until_ready(hand(xi0)),
        RK4: lambda: throughput.rk4_euler_final(inertia, omega0, rigid.DT, n_steps),
    }
    c_march, c_flags = throughput.c_kernel()
    if c_march is not None:
        calls[C_SIMD] = lambda: c_march(inertia, rigid.DT, n_steps, omega0)
    timings, outs = run.time(calls, what=f"rigid-body sweep B={batch} n_steps={n_steps}", repeats=run.repeats or 3)
    row = {"part": "sweep", "batch": batch, "n_steps": n_steps, "methods": list(calls), "c_flags": c_flags}
    for m in calls:
        row[m] = throughput._rates(timings[m], n_steps, batch, "body")
        row[m]["compile_s"] = timings[m]["first_call_s"] - timings[m]["second_call_s"]
    mu_hand = np.asarray(outs[HAND][0])
    for m in ("sweep", "sweep_xla"):
        res = outs[m].raise_if_failed()
        row[m]["max_energy_error"] = float(np.max(res.energy_error))
        row[m]["max_abs_final_momentum_diff_vs_hand"] = float(np.max(np.abs(res.final_momentum - mu_hand)))
    row["sweep"]["max_abs_final_momentum_diff_vs_xla"] = float(
        np.max(np.abs(outs["sweep"].final_momentum - outs["sweep_xla"].final_momentum))
    )
    row[HAND]["max_energy_error"] = float(np.max(np.asarray(outs[HAND][1])))
    row[RK4]["max_energy_error"] = float(np.max(outs[RK4][1]))
    if C_SIMD in calls:
        row[C_SIMD]["max_energy_error"] = float(np.max(outs[C_SIMD][1]))
    rate = {m: row[m]["body_steps_per_second"] for m in calls}
    row["ratios"] = {
        f"sweep_over_{k}": rate["sweep"] / rate[m]
        for k, m in (("xla", "sweep_xla"), ("hand", HAND), ("numpy_rk4", RK4), ("c", C_SIMD))
        if m in rate
    }
    return row


def threads_case(batch: int, n_steps: int, run: harness.Run) -> dict:
    omega0 = rigid.initial_conditions(batch)[1]
    inertias = np.broadcast_to(np.asarray(INERTIA), (batch, 3))
    Q0 = np.broadcast_to(np.eye(3), (batch, 3, 3))
    calls = {f"threads={k}": _sweep(inertias, Q0, omega0, n_steps, threads=k) for k in (1, 2)}
    c_march, _ = throughput.c_kernel()
    if c_march is not None:
        calls |= {f"c_threads={k}": _c_threads(c_march, omega0, n_steps, k) for k in (1, 2)}
    timings, outs = run.time(calls, what=f"native sweep threads B={batch}", repeats=run.repeats or 3)
    row = {"part": "threads", "batch": batch, "n_steps": n_steps}
    for m in calls:
        row[m] = throughput._rates(timings[m], n_steps, batch, "body")
    assert np.array_equal(outs["threads=1"].final_momentum, outs["threads=2"].final_momentum)
    row["two_over_one"] = row["threads=2"]["body_steps_per_second"] / row["threads=1"]["body_steps_per_second"]
    if c_march is not None:
        # the machine's own ceiling for two threads: the C kernel (pure arithmetic, no Python
        # inside the call, the GIL released by ctypes) on the two halves of the batch at once
        row["c_two_over_one"] = (
            row["c_threads=2"]["body_steps_per_second"] / row["c_threads=1"]["body_steps_per_second"]
        )
    return row


def _c_threads(c_march, omega0, n_steps: int, threads: int):
    """The C kernel over the batch split into `threads` parts, each part on its own thread."""
    parts = np.array_split(np.asarray(omega0), threads)

    def call():
        if threads == 1:
            return c_march(np.asarray(INERTIA), rigid.DT, n_steps, parts[0])
        with ThreadPoolExecutor(threads) as pool:
            outs = list(pool.map(lambda x: c_march(np.asarray(INERTIA), rigid.DT, n_steps, x), parts))
        return np.concatenate([o[0] for o in outs]), np.concatenate([o[1] for o in outs])

    return call


_CHILD = """
import json, sys, time
import numpy as np
import clebsch_jax as cj
B, n = int(sys.argv[1]), int(sys.argv[2])
rng = np.random.default_rng(0)
args = (cj.models.rigid_body, np.broadcast_to([0.5, 0.6, 1.0], (B, 3)), np.broadcast_to(np.eye(3), (B, 3, 3)),
        rng.normal(size=(B, 3)))
t, c = time.perf_counter(), time.process_time(); cj.sweep(*args, dt=0.05, n_steps=n, reconstruct=False)
first, first_cpu = time.perf_counter() - t, time.process_time() - c
t, c = time.perf_counter(), time.process_time(); cj.sweep(*args, dt=0.05, n_steps=n, reconstruct=False)
second, second_cpu = time.perf_counter() - t, time.process_time() - c
print(json.dumps({"first_call_s": first, "second_call_s": second, "first_call_cpu_s": first_cpu,
                  "second_call_cpu_s": second_cpu}))
"""


def compile_case(batch: int, n_steps: int, run: harness.Run) -> dict:
    """A fresh process's first call minus its second: with an empty native cache, then with it
    written (XLA's persistent cache is off in both)."""
    row = {"part": "compile", "batch": batch, "n_steps": n_steps}
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "CLEBSCH_JAX_NATIVE_CACHE": cache}
        for label in ("cold", "cached"):
            with run.guard(f"compile child ({label})"):
                out = subprocess.run(
                    [sys.executable, "-c", _CHILD, str(batch), str(n_steps)],
                    env=env,
                    capture_output=True,
                    text=True,
                    check=True,
                )
            t = json.loads(out.stdout.strip().splitlines()[-1])
            row[label] = {
                **t,
                "compile_s": t["first_call_s"] - t["second_call_s"],
                # CPU time of the process (all its threads): less moved by other processes' load
                "compile_cpu_s": t["first_call_cpu_s"] - t["second_call_cpu_s"],
            }
    return row


def vortex_case(N: int, batch: int, n_steps: int, run: harness.Run) -> dict:
    G, Q0 = vortex.initial_conditions(N, batch)
    xi0 = np.asarray(jax.vmap(models.vortex_velocity)(jnp.asarray(G), jnp.asarray(Q0)))
    calls = {
        "sweep": lambda: cj.sweep(models.point_vortices, G, Q0, xi0, dt=vortex.DT, n_steps=n_steps),
        "sweep_xla": lambda: cj.sweep(models.point_vortices, G, Q0, xi0, dt=vortex.DT, n_steps=n_steps, backend="xla"),
        # the native kernel asked for: the same as "sweep" where "auto" takes it, else past auto's limits
        "sweep_native": lambda: cj.sweep(
            models.point_vortices, G, Q0, xi0, dt=vortex.DT, n_steps=n_steps, backend="native"
        ),
        RK4: lambda: vortex.rk4_march(G, Q0, vortex.DT, n_steps),
    }
    timings, outs = run.time(calls, what=f"vortex clusters N={N} B={batch}", repeats=run.repeats or 3)
    row = {"part": "vortices", "N": N, "batch": batch, "n_steps": n_steps}
    for m in calls:
        row[m] = throughput._rates(timings[m], n_steps, N * batch, "vortex")
        row[m]["compile_s"] = timings[m]["first_call_s"] - timings[m]["second_call_s"]
    for m in ("sweep", "sweep_xla", "sweep_native"):
        res = outs[m]
        row[m]["failed_members"] = int(np.sum(res.status != 0))
        row[m]["max_energy_error"] = float(np.nanmax(res.energy_error))
    row["step_over_rk4_step"] = {
        m: row[m]["seconds_per_step"] / row[RK4]["seconds_per_step"] for m in ("sweep", "sweep_xla", "sweep_native")
    }
    return row


def _print_sweep(rows: list, names: list) -> None:
    print("\nM body-steps/s (compile s):")
    harness.print_table(
        f"{'B':>8}{'steps':>6} |" + "".join(f"{m:>22}" for m in names) + " | sweep/C | sweep/hand | sweep/xla",
        (
            f"{r['batch']:>8}{r['n_steps']:>6} |"
            + "".join(f"{r[m]['body_steps_per_second'] / 1e6:>14.3g} ({r[m]['compile_s']:5.2f})" for m in names)
            + f" | {r['ratios'].get('sweep_over_c', float('nan')):7.3g} | {r['ratios']['sweep_over_hand']:10.3g}"
            f" | {r['ratios']['sweep_over_xla']:9.3g}"
            for r in rows
        ),
    )
    print(
        "max energy error: "
        + "; ".join(f"B={r['batch']}: " + ", ".join(f"{m} {r[m]['max_energy_error']:.2e}" for m in names) for r in rows)
    )
    print(
        "native vs XLA sweep, max |final momentum difference|: "
        + "; ".join(f"B={r['batch']}: {r['sweep']['max_abs_final_momentum_diff_vs_xla']:.1e}" for r in rows)
    )


def print_report(summary: dict) -> None:
    harness.print_header(
        summary,
        "Native kernels",
        f"Free rigid body {INERTIA}, reduced CAY march (reconstruct=False), dt = {rigid.DT}; "
        "the sweep keeps final states and energy errors only.",
    )
    rows = [r for r in summary["results"] if r["part"] == "sweep"]
    names = [m for m in ("sweep", "sweep_xla", HAND, C_SIMD, RK4) if rows and m in rows[0]]
    if rows:
        _print_sweep(rows, names)
    for r in (r for r in summary["results"] if r["part"] == "threads"):
        print(
            f"\nThreads (B={r['batch']}): 1 thread {r['threads=1']['body_steps_per_second'] / 1e6:.3g}, "
            f"2 threads {r['threads=2']['body_steps_per_second'] / 1e6:.3g} M body-steps/s: "
            f"2/1 = {r['two_over_one']:.3g}"
            + (f"; the C kernel on two threads: 2/1 = {r['c_two_over_one']:.3g}" if "c_two_over_one" in r else "")
        )
    for r in (r for r in summary["results"] if r["part"] == "compile"):
        print(
            f"\nCompile (fresh process, B={r['batch']} x {r['n_steps']}): cold {r['cold']['compile_s']:.2f} s, "
            f"from the disk cache {r['cached']['compile_s']:.2f} s (first calls {r['cold']['first_call_s']:.2f} / "
            f"{r['cached']['first_call_s']:.2f} s; CPU time {r['cold']['compile_cpu_s']:.2f} / "
            f"{r['cached']['compile_cpu_s']:.2f} s)"
        )
    vrows = [r for r in summary["results"] if r["part"] == "vortices"]
    if vrows:
        print("\nVortex clusters, ms per step of the batch (compile s):")
        harness.print_table(
            f"{'N':>4}{'B':>7}{'steps':>6} |{'sweep':>18}{'sweep_xla':>18}{'sweep_native':>18}{'RK4':>9} |"
            " sweep/RK4 | xla/RK4 | native/RK4",
            (
                f"{r['N']:>4}{r['batch']:>7}{r['n_steps']:>6} |"
                + "".join(
                    f"{r[m]['seconds_per_step'] * 1e3:>10.3g} ({r[m]['compile_s']:4.1f})"
                    for m in ("sweep", "sweep_xla", "sweep_native")
                )
                + f"{r[RK4]['seconds_per_step'] * 1e3:>9.3g} | {r['step_over_rk4_step']['sweep']:9.3g} | "
                f"{r['step_over_rk4_step']['sweep_xla']:7.3g} | {r['step_over_rk4_step']['sweep_native']:10.3g}"
                for r in vrows
            ),
        )
    t = TARGETS
    print(
        f"\nTargets (reported, never asserted): sweep >= {t['sweep_over_c_from_1e4']}x C from B=1e4, "
        f">= {t['sweep_over_c_at_1e3']}x at 1e3, >= {t['sweep_over_hand']}x the hand JAX kernel; cold compile <= "
        f"{t['compile_cold_s']} s, cached <= {t['compile_cached_s']} s; "
        f"2 threads >= {t['two_threads_over_one']}x one; "
        f"a vortex-cluster step <= {t['vortex_step_over_rk4_step']}x an RK4 step."
    )


def plot(summary: dict, path: Path) -> None:
    fig, (ax, bx) = harness.figure((1, 1), size=(11, 4.4))
    styles = {"sweep": ("o", "C2"), "sweep_xla": ("*", "C3"), HAND: ("^", "C7"), C_SIMD: ("x", "k"), RK4: ("s", "C1")}
    for m, (marker, color) in styles.items():
        pts = [
            (r["batch"], r[m]["body_steps_per_second"]) for r in summary["results"] if r["part"] == "sweep" and m in r
        ]
        if pts:
            ax.loglog(*zip(*pts), marker=marker, color=color, label=m)
    ax.set_xlabel("batch size B (bodies)")
    ax.set_ylabel("body-steps per second")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("rigid-body sweep", fontsize=9)
    vrows = [r for r in summary["results"] if r["part"] == "vortices"]
    labels = [f"N={r['N']}" for r in vrows]
    x = np.arange(len(vrows))
    for k, (m, color) in enumerate((("sweep", "C2"), ("sweep_xla", "C3"), ("sweep_native", "C4"), (RK4, "C1"))):
        bx.bar(x + 0.2 * (k - 1.5), [r[m]["seconds_per_step"] * 1e3 for r in vrows], width=0.2, color=color, label=m)
    bx.set_xticks(x, labels)
    bx.set_ylabel("ms per step of 1000 clusters")
    bx.legend(fontsize=8)
    bx.set_title("vortex clusters", fontsize=9)
    fig.suptitle(harness.plot_title(summary, "native kernels"), fontsize=9)
    fig.savefig(path, dpi=120)


def _plot_threads(summary: dict, path: Path) -> None:
    """`--threads-only`: two threads over one, the sweep's beside the C kernel's."""
    fig, ax = harness.figure((1,), size=(5, 3.6))
    r = next(r for r in summary["results"] if r["part"] == "threads")
    bars = {"sweep": r["two_over_one"], "C kernel": r.get("c_two_over_one", float("nan"))}
    ax.bar(list(bars), list(bars.values()), color=["C2", "k"])
    ax.axhline(TARGETS["two_threads_over_one"], color="C3", ls="--", label="target")
    ax.set_ylabel(f"2 threads / 1 thread (B = {r['batch']})")
    ax.legend(fontsize=8)
    fig.suptitle(harness.plot_title(summary, "native threads"), fontsize=9)
    fig.savefig(path, dpi=120)


def _add_arguments(parser) -> None:
    parser.add_argument("--large", action="store_true", help="add B = 10^6 to the rigid-body sweep")
    parser.add_argument(
        "--threads-only",
        action="store_true",
        help="the threads part alone, written to native_threads.json (the other parts' results are kept)",
    )
    parser.add_argument(
        "--vortices-only",
        action="store_true",
        help="the vortex clusters alone, written to native_vortices.json (the other parts' results are kept)",
    )
    parser.add_argument(
        "--rigid-only",
        action="store_true",
        help="the rigid-body sweep and threads parts alone, written to native_rigid.json (no compile children, "
        "no vortex clusters; the other parts' results are kept)",
    )


def main(argv=None) -> dict:
    argv = sys.argv[1:] if argv is None else argv
    only = {"--threads-only": "_threads", "--vortices-only": "_vortices", "--rigid-only": "_rigid"}
    part = next((name for flag, name in only.items() if flag in argv), "")
    run = harness.Run(
        RESULTS_NAME + part,
        argv,
        description="Native kernels against the hand JAX and C kernels, "
        "XLA's sweep and NumPy RK4 (see module docstring).",
        add_arguments=_add_arguments,
    )
    default = SWEEP_DEFAULT + (SWEEP_LARGE if run.args.large else ())
    with run:
        largest = (SWEEP_QUICK if run.quick else default)[-1]
        threads = lambda: run.measure(  # noqa: E731
            (largest,), (largest,), lambda B, n: f"threads B={B}", lambda B, n: threads_case(B, n, run)
        )
        if run.args.threads_only:
            summary = run.summary(config={"inertia": list(INERTIA), "dt": rigid.DT}, results=threads(), targets=TARGETS)
            return run.finish(summary, print_report, _plot_threads)
        vortices = lambda: run.measure(  # noqa: E731
            VORTEX_DEFAULT,
            VORTEX_QUICK,
            lambda N, B, n: f"vortex clusters N={N} B={B}",
            lambda N, B, n: vortex_case(N, B, n, run),
        )
        config = {"inertia": list(INERTIA), "dt": rigid.DT, "vortex_dt": vortex.DT}
        if run.args.vortices_only:
            return run.finish(run.summary(config=config, results=vortices(), targets=TARGETS), print_report, plot)
        rows = run.measure(
            default, SWEEP_QUICK, lambda B, n: f"sweep B={B} n_steps={n}", lambda B, n: rigid_case(B, n, run)
        )
        rows += threads()
        if run.args.rigid_only:
            summary = run.summary(config={"inertia": list(INERTIA), "dt": rigid.DT}, results=rows, targets=TARGETS)
            return run.finish(summary, print_report, plot)
        rows += run.measure(
            (COMPILE_CASE,), (COMPILE_QUICK,), lambda B, n: f"compile B={B}", lambda B, n: compile_case(B, n, run)
        )
        rows += vortices()
    summary = run.summary(config=config, results=rows, targets=TARGETS)
    return run.finish(summary, print_report, plot)


if __name__ == "__main__":
    main()
