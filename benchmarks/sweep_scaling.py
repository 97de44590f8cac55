r"""Sweep scaling (issue 21): one process against a Dask LocalCluster of 2 worker processes × 1
thread, and the cost of writing the table to Zarr against keeping it in memory.

Run from the repository root (needs the extra `pip install -e ".[sweep]"`):

    python benchmarks/sweep_scaling.py            # default sizes
    python benchmarks/sweep_scaling.py --quick    # smoke test, tiny sizes (not a measurement)
    python benchmarks/sweep_scaling.py --members 100000 --steps 1000   # the issue's example size

The same sweep — free rigid bodies (`rigid_body`, inertias drawn around (2, 1, 2/3)), random
body velocities, Q0 = I, the default (reduced) march, dt = 0.05, `batch_size` members per
compiled call, `chunk_steps` steps per `integrate` call — run four ways with `cj.sweep`:

- **in_process**: no store, this process (the table in memory);
- **in_process_zarr**: `store=` a fresh Zarr store per call, this process;
- **cluster_zarr**: `client=` a `distributed.Client` of a `LocalCluster(n_workers=2,
  threads_per_worker=1, processes=True)`, `store=` a fresh store per call (workers write
  their batches);
- **cluster**: the same cluster, no store (the rows come back through Dask).

Timed with the harness the benchmarks share (`_timing.py`: the first call of each compiles —
for the cluster, in each worker —, every call returns NumPy arrays, so it has finished; the
median over `--repeats` rounds, the methods of a round in turn). Member-steps per second =
members × steps / time per call. Reported ratios (paired per round, median): **scaling** =
in_process_zarr / cluster_zarr (the same work, the store written by both; the issue's target
>= 1.7× on 2 cores) and in_process / cluster; **Zarr overhead** = in_process_zarr / in_process
− 1 (target <= 5 %). Nothing is asserted. Worker processes are started with XLA's CPU
intra-op threading off (`XLA_FLAGS`), so each uses one core as its Dask thread count says;
the in-process runs use XLA's defaults, as a user's process does. Other processes on the
machine take cores from both: the load average is recorded at the start and the end.

With `--quick`, XLA optimisation is off here and in the workers; such unoptimised programs need
not give the same bits under the workers' one-thread XLA settings, so only the default run's
"tables identical" check speaks for the library (the tests check it too).

Outputs (in `--out`, default `benchmarks/results`): `sweep_scaling.json` and
`sweep_scaling.png` (member-steps per second of each method; the ratios against their targets).
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _timing as harness  # noqa: E402

import clebsch_jax as cj  # noqa: E402

RESULTS_NAME = "sweep_scaling"
DT = 0.05
SEED = 0
WORKERS, THREADS = 2, 1
TARGET_SCALING = 1.7
TARGET_ZARR_OVERHEAD = 0.05
DEFAULT_CASES = [(100_000, 200, 10_000, 100)]  # (members, steps, batch_size, chunk_steps)
QUICK_CASES = [(64, 20, 16, 10)]
METHODS = ("in_process", "in_process_zarr", "cluster_zarr", "cluster")
WORKER_XLA_FLAGS = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"


def members(n: int, seed: int = SEED):
    """n inertias near (2, 1, 2/3) (each a real body: the triangle inequality holds) and n
    random body velocities; one member per row (grid=False)."""
    rng = np.random.default_rng(seed)
    inertia = np.array([2.0, 1.0, 2.0 / 3.0]) * (1 + 0.1 * rng.uniform(-1, 1, (n, 3)))
    xi0 = rng.standard_normal((n, 3))
    return inertia, np.broadcast_to(np.eye(3), (n, 3, 3)), xi0


def run_case(n: int, steps: int, batch: int, chunk: int, run: harness.Run, client, scratch: Path) -> dict:
    inertia, Q0, xi0 = members(n)
    kw = dict(dt=DT, n_steps=steps, batch_size=batch, chunk_steps=chunk)
    count = iter(range(10**9))

    def fresh_store() -> str:
        return str(scratch / f"sweep-{next(count)}.zarr")

    calls = {
        "in_process": lambda: cj.sweep(cj.models.rigid_body, inertia, Q0, xi0, **kw),
        "in_process_zarr": lambda: cj.sweep(cj.models.rigid_body, inertia, Q0, xi0, store=fresh_store(), **kw),
        "cluster_zarr": lambda: cj.sweep(
            cj.models.rigid_body, inertia, Q0, xi0, store=fresh_store(), client=client, **kw
        ),
        "cluster": lambda: cj.sweep(cj.models.rigid_body, inertia, Q0, xi0, client=client, **kw),
    }
    timings, outs = run.time(calls, what=f"{n} members x {steps} steps")
    ref = outs["in_process"]
    identical = {}
    for m in METHODS[1:]:  # each method's table against the in-process one, to the bit
        same = [
            np.array_equal(a, b, equal_nan=True)
            for a, b in zip(jax.tree_util.tree_leaves(ref), jax.tree_util.tree_leaves(outs[m]))
        ]
        identical[m] = bool(all(same))
    shutil.rmtree(scratch, ignore_errors=True)
    scratch.mkdir()
    row = {
        "members": n,
        "n_steps": steps,
        "batch_size": batch,
        "chunk_steps": chunk,
        "n_batches": -(-n // batch),
        "failed_members": int(len(ref.failed_members)),
        "tables_identical_to_in_process": identical,
    }
    for m in METHODS:
        t = timings[m]
        row[m] = {**t, "member_steps_per_second": n * steps / t["per_call_s"]}
    s = {m: timings[m]["samples_s"] for m in METHODS}
    row["ratios"] = {
        "scaling_zarr": harness.paired_ratios(s["in_process_zarr"], s["cluster_zarr"]),
        "scaling_no_store": harness.paired_ratios(s["in_process"], s["cluster"]),
        "zarr_over_memory_in_process": harness.paired_ratios(s["in_process_zarr"], s["in_process"]),
        "zarr_over_memory_cluster": harness.paired_ratios(s["cluster_zarr"], s["cluster"]),
    }
    return row


def print_report(summary: dict) -> None:
    rows = summary["results"]
    harness.print_header(
        summary,
        f"Rigid-body sweep, dt = {DT}, one process against a LocalCluster of {WORKERS} processes x {THREADS} thread",
        "in_process: cj.sweep, table in memory; in_process_zarr: store= a fresh Zarr store; cluster_zarr: "
        "client= the LocalCluster, store=;\n  cluster: client=, no store.",
    )
    print("\nMember-steps per second (time per call [s]):")
    harness.print_table(
        f"{'members':>8}{'steps':>7}{'batch':>7} |" + "".join(f"{m:>26}" for m in METHODS),
        (
            f"{r['members']:>8}{r['n_steps']:>7}{r['batch_size']:>7} |"
            + "".join(f"{r[m]['member_steps_per_second']:>15.3e} ({r[m]['per_call_s']:7.2f})" for m in METHODS)
            for r in rows
        ),
    )
    print("\nRatios (paired per round: median [min, max]):")
    for r in rows:
        q = r["ratios"]
        for key, what in (
            ("scaling_zarr", f"scaling in_process_zarr / cluster_zarr (target >= {TARGET_SCALING})"),
            ("scaling_no_store", "scaling in_process / cluster"),
            (
                "zarr_over_memory_in_process",
                f"in_process_zarr / in_process (Zarr overhead target <= {1 + TARGET_ZARR_OVERHEAD:.2f})",
            ),
            ("zarr_over_memory_cluster", "cluster_zarr / cluster"),
        ):
            print(f"  {what:<72} {q[key]['median']:.3f} [{q[key]['min']:.3f}, {q[key]['max']:.3f}]")
        print(f"  tables identical to the in-process one, to the bit: {r['tables_identical_to_in_process']}")
    t = summary["targets"]
    print(
        f"\nIssue targets: scaling >= {TARGET_SCALING}: {'met' if t['scaling']['met'] else 'not met'}; "
        f"Zarr overhead <= {TARGET_ZARR_OVERHEAD:.0%}: {'met' if t['zarr_overhead']['met'] else 'not met'} "
        f"(load {summary['machine']['load_average_1min_at_start']:.2f} at the start on "
        f"{summary['machine']['cpu_count']} CPUs)."
    )


def plot(summary: dict, path: Path) -> None:
    rows = summary["results"]
    fig, (ax, ax_r) = harness.figure((3, 2))
    r = rows[-1]
    ax.bar(range(len(METHODS)), [r[m]["member_steps_per_second"] for m in METHODS], color=["C0", "C0", "C2", "C2"])
    ax.set_xticks(range(len(METHODS)), METHODS, fontsize=8)
    ax.set_ylabel("member-steps per second")
    ax.set_title(harness.plot_title(summary, f"{r['members']} rigid bodies x {r['n_steps']} steps"), fontsize=9)
    ax.grid(True, axis="y", alpha=0.3)
    keys = ("scaling_zarr", "scaling_no_store", "zarr_over_memory_in_process", "zarr_over_memory_cluster")
    med = [r["ratios"][k]["median"] for k in keys]
    lo = [m - r["ratios"][k]["min"] for m, k in zip(med, keys)]
    hi = [r["ratios"][k]["max"] - m for m, k in zip(med, keys)]
    ax_r.bar(range(len(keys)), med, yerr=[lo, hi], color=["C2", "C2", "C1", "C1"], capsize=4)
    ax_r.axhline(TARGET_SCALING, color="C2", ls=":", label=f"scaling target {TARGET_SCALING}")
    ax_r.axhline(1 + TARGET_ZARR_OVERHEAD, color="C1", ls=":", label=f"Zarr target {1 + TARGET_ZARR_OVERHEAD}")
    ax_r.set_xticks(
        range(len(keys)),
        [
            "1 proc / cluster\n(Zarr)",
            "1 proc / cluster\n(memory)",
            "Zarr / memory\n(1 proc)",
            "Zarr / memory\n(cluster)",
        ],
        fontsize=7,
    )
    ax_r.legend(fontsize=8)
    ax_r.grid(True, axis="y", alpha=0.3)
    ax_r.set_title("ratios of time per sweep (median, min-max)", fontsize=9)
    fig.savefig(path, dpi=120)


def add_arguments(parser) -> None:
    parser.add_argument("--members", type=int, default=None, help="members of the sweep (default: see the script)")
    parser.add_argument("--steps", type=int, default=None, help="steps per member")
    parser.add_argument("--batch-size", type=int, default=None, dest="batch_size", help="members per batch")


def main(argv=None) -> dict:
    try:
        import distributed
    except ImportError:
        raise SystemExit('sweep_scaling needs the extra [sweep]: pip install -e ".[sweep]"') from None
    with harness.Run(
        RESULTS_NAME,
        argv,
        description="One process against a 2-process LocalCluster, and "
        "the Zarr overhead, for a rigid-body cj.sweep (see module docstring).",
        add_arguments=add_arguments,
    ) as run:
        a = run.args
        default = [
            (a.members or n, a.steps or s, a.batch_size or b, min(c, a.steps or s)) for n, s, b, c in DEFAULT_CASES
        ]
        # the workers' environment: one XLA thread each; with --quick, XLA optimisation off as here
        env = {"XLA_FLAGS": " ".join(filter(None, [os.environ.get("XLA_FLAGS"), WORKER_XLA_FLAGS]))}
        if run.quick:
            env[harness.QUICK_FLAG.upper()] = "1"
        cluster = distributed.LocalCluster(
            n_workers=WORKERS, threads_per_worker=THREADS, processes=True, dashboard_address=None, env=env
        )
        scratch = Path(tempfile.mkdtemp(prefix="sweep-scaling-"))
        try:
            with cluster, distributed.Client(cluster) as client:
                results = run.measure(
                    default,
                    QUICK_CASES,
                    lambda n, s, b, c: f"{n} members x {s} steps (batches of {b}): {', '.join(METHODS)}",
                    lambda *case: run_case(*case, run, client, scratch),
                )
        finally:
            shutil.rmtree(scratch, ignore_errors=True)
    r = results[-1]["ratios"]
    summary = run.summary(
        config={
            "model": "rigid_body, inertias (2, 1, 2/3) x (1 + U(-0.1, 0.1))",
            "dt": DT,
            "seed": SEED,
            "workers": WORKERS,
            "threads_per_worker": THREADS,
            "worker_xla_flags": WORKER_XLA_FLAGS,
            "methods": list(METHODS),
            "cases": [{"members": n, "n_steps": s, "batch_size": b, "chunk_steps": c} for n, s, b, c in run.cases],
        },
        results=results,
        targets={
            "scaling": {
                "target": TARGET_SCALING,
                "value": r["scaling_zarr"]["median"],
                "met": r["scaling_zarr"]["median"] >= TARGET_SCALING,
            },
            "zarr_overhead": {
                "target": TARGET_ZARR_OVERHEAD,
                "value": r["zarr_over_memory_in_process"]["median"] - 1,
                "met": r["zarr_over_memory_in_process"]["median"] - 1 <= TARGET_ZARR_OVERHEAD,
            },
        },
    )
    return run.finish(summary, print_report, plot)


if __name__ == "__main__":
    main()
