"""Where a call of the documented rigid-body sweep spends its time: the native kernel against the rest.

Run: `python benchmarks/native_split.py` (`--batch 10000 100000`, `--rounds 15`). The sweep of
`native.py` (`cj.sweep(rigid_body, …, reconstruct=False)`, default options, 200 steps), with
the kernel's function (`clebsch_jax.native.kernel.Kernel`'s ctypes call) timed from inside for
this process. Per batch size, after two warm calls:

- `threads=1`: the calling thread's CPU time per call, of it the kernel's function, and the rest
  (the checks, the batches' host arrays, the kernel call's rows, the table);
- the default threads: the wall time from the call's start to the first kernel call's start and
  from the last one's end to the call's return — the serial part no second thread shortens.

CPU time of one thread moves little with the machine's load (the kernel's far less than its
wall time); the spans are wall time, so read them with the load. Minimum and median over the
rounds. Outputs: `benchmarks/results/native_split.json` and `.png` (the kernel's and the rest's
CPU per call, the serial spans). `--quick` (as `clebsch-jax bench --quick` passes it): 64
members, two rounds, a smoke run.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _timing as harness  # noqa: E402
import rigid_body_step_cost as rigid  # noqa: E402
import throughput  # noqa: E402

import clebsch_jax as cj  # noqa: E402
from clebsch_jax.native import kernel as K  # noqa: E402

_KERNEL_CPU = threading.local()  # ns of the kernel's function on this thread
_SPANS: list = []  # (start, end) wall time of each kernel call
_CALL = K.Kernel.__call__


def _timed_call(self, *args, **kwargs):
    """`Kernel.__call__`, its function timed (wrapped once per kernel)."""
    if not getattr(self, "_split_timed", False):
        fn = self._fn

        def timed(*a):
            start, cpu = time.perf_counter(), time.thread_time_ns()
            try:
                return fn(*a)
            finally:
                _KERNEL_CPU.ns = getattr(_KERNEL_CPU, "ns", 0) + time.thread_time_ns() - cpu
                _SPANS.append((start, time.perf_counter()))

        self._fn, self._split_timed = timed, True
    return _CALL(self, *args, **kwargs)


def _sweep(batch: int, **extra):
    omega0 = rigid.initial_conditions(batch)[1]
    inertias = np.broadcast_to(np.asarray(throughput.SWEEP_INERTIA), (batch, 3))
    Q0 = np.broadcast_to(np.eye(3), (batch, 3, 3))
    return lambda: cj.sweep(
        cj.models.rigid_body, inertias, Q0, omega0, dt=rigid.DT, n_steps=200, reconstruct=False, **extra
    )


def _stats(values) -> dict:
    return {"min_ms": round(float(np.min(values)) * 1e3, 3), "median_ms": round(float(np.median(values)) * 1e3, 3)}


def split(batch: int, rounds: int) -> dict:
    """The CPU split with one thread and the serial spans with the default threads."""
    one = _sweep(batch, threads=1)
    one(), one()
    total, kernel = [], []
    for _ in range(rounds):
        _KERNEL_CPU.ns = 0
        cpu = time.thread_time_ns()
        one()
        total.append((time.thread_time_ns() - cpu) / 1e9)
        kernel.append(_KERNEL_CPU.ns / 1e9)
    outside = np.subtract(total, kernel)
    default = _sweep(batch)
    default(), default()
    before, after = [], []
    for _ in range(rounds):
        _SPANS.clear()
        start = time.perf_counter()
        default()
        end = time.perf_counter()
        before.append(min(s for s, _ in _SPANS) - start)
        after.append(end - max(e for _, e in _SPANS))
    return {
        "batch": batch,
        "threads=1": {"call_cpu": _stats(total), "kernel_cpu": _stats(kernel), "outside_cpu": _stats(outside)},
        "default threads": {"before_first_kernel": _stats(before), "after_last_kernel": _stats(after)},
        "load_average": os.getloadavg()[0],
    }


def _arguments(parser) -> None:
    parser.add_argument("--batch", type=int, nargs="+", default=[10_000, 100_000])
    parser.add_argument("--rounds", type=int, default=15)


def _report(summary: dict) -> None:
    lines = []
    for r in summary["results"]:
        one, spans = r["threads=1"], r["default threads"]
        lines.append(
            f"{r['batch']:>8} {one['call_cpu']['min_ms']:>10.2f} {one['kernel_cpu']['min_ms']:>10.2f} "
            f"{one['outside_cpu']['min_ms']:>10.2f} {spans['before_first_kernel']['min_ms']:>10.2f} "
            f"{spans['after_last_kernel']['min_ms']:>10.2f}"
        )
    harness.print_table(
        f"{'B':>8} {'call CPU':>10} {'kernel':>10} {'rest':>10} {'before':>10} {'after':>10}   (ms, minimum)", lines
    )


def _plot(summary: dict, path) -> None:
    fig, (cpu, spans) = harness.figure((1, 1))
    rows = summary["results"]
    x = np.arange(len(rows))
    kernel = [r["threads=1"]["kernel_cpu"]["min_ms"] for r in rows]
    rest = [r["threads=1"]["outside_cpu"]["min_ms"] for r in rows]
    cpu.bar(x, kernel, label="kernel's function")
    cpu.bar(x, rest, bottom=kernel, label="the rest of the call")
    cpu.set(xticks=x, xticklabels=[f"B = {r['batch']}" for r in rows], ylabel="thread CPU per call (ms)")
    cpu.set_title("threads=1: CPU per call, minimum")
    cpu.legend()
    for key, offset in (("before_first_kernel", -0.2), ("after_last_kernel", 0.2)):
        spans.bar(x + offset, [r["default threads"][key]["min_ms"] for r in rows], 0.4, label=key.replace("_", " "))
    spans.set(xticks=x, xticklabels=[f"B = {r['batch']}" for r in rows], ylabel="wall time (ms)")
    spans.set_title("default threads: serial spans, minimum")
    spans.legend()
    fig.suptitle(f"native sweep call split ({summary['machine']['cpu_count']} CPUs)")
    fig.savefig(path, dpi=110)


def main(argv=None) -> dict:
    with harness.Run("native_split", argv, description=__doc__.splitlines()[0], add_arguments=_arguments) as run:
        args = run.args
        if run.quick:
            args.batch, args.rounds = [64], 2
        K.Kernel.__call__ = _timed_call
        try:
            results = [split(batch, args.rounds) for batch in args.batch]
        finally:
            K.Kernel.__call__ = _CALL
        summary = run.summary(config={"batch": args.batch, "rounds": args.rounds, "n_steps": 200}, results=results)
        return run.finish(summary, _report, _plot)


if __name__ == "__main__":
    main()
