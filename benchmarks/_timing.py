"""What the benchmark scripts share: the timing harness, the command line, machine information,
the `--quick` switch, the watchdog, table printing, plotting helpers and writing the results.

A script uses it as

    def run_case(label, n, run):
        timings, outs = run.time({"ours": call, "numpy_rk4": peer}, what=label)  # interleaved
        return {...}                                                             # one result row

    with Run("vortex_step_cost", argv, description=...) as run:  # parses --quick/--out/...
        rows = run.measure(DEFAULT_CASES, QUICK_CASES, describe,  # a progress line per case
                           lambda *case: run_case(*case, run))
    summary = run.summary(config={...}, results=rows)
    run.finish(summary, print_report, plot)           # prints the report, writes JSON, then PNG

Method (as diffrax `benchmarks/against_scan.py`): the first call of every method is timed
alone (for JAX it compiles); one more call fixes `number`, the calls per sample, so that a
sample lasts at least `--min-sample` seconds; then `--repeats` rounds each take one sample of
every method in turn, the starting method rotating from round to round, so a change of machine
load during a case hits all methods alike. Every call must block until its result is ready
(`jax.block_until_ready`). The reported time per call is the median over samples of
(sample wall time / number), by `time.perf_counter`; the CPU time of the process (all threads)
per call is recorded beside it. Nothing here asserts a wall time.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import faulthandler
import json
import math
import os
import platform
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

import jax
import numpy as np

import clebsch_jax as cj

RESULTS_DIR = Path(__file__).resolve().parent / "results"
# --quick turns most XLA optimisation off, to compile faster: JAX's global flag (for plain
# `integrate` calls, which compile inside and take no compiler options) and these compiler
# options for the scripts' own `jax.jit`s.
QUICK_FLAG = "jax_disable_most_optimizations"
QUICK_COMPILER_OPTIONS = {"xla_backend_optimization_level": 0}
STATISTIC = (
    "median over samples of (sample wall time / calls per sample); the methods of a case are "
    "sampled in turn, the first one rotating"
)


# --------------------------------------------------------------------------------------------
# Timing.


class Watchdog:
    """Exit with a message and all thread stacks if a phase overruns: a wedged XLA CPU run
    would otherwise hang forever (benchmarks/README.md, "Known problem"). `seconds <= 0`
    disables it."""

    def __init__(self, seconds: float, what: str, prog: str = "benchmark"):
        self.seconds, self.what, self.prog = seconds, what, prog
        self._timer = None

    def _fire(self):
        print(
            f"\n{self.prog}: '{self.what}' did not finish within {self.seconds:.0f} s; the JAX run is "
            "probably wedged (benchmarks/README.md, 'Known problem'). Stacks follow.",
            file=sys.stderr,
            flush=True,
        )
        faulthandler.dump_traceback(all_threads=True)
        os._exit(3)

    def __enter__(self):
        if self.seconds > 0:
            self._timer = threading.Timer(self.seconds, self._fire)
            self._timer.daemon = True
            self._timer.start()
            # backstop that needs no GIL, in case the timer thread cannot run
            faulthandler.dump_traceback_later(self.seconds + 30, exit=True)
        return self

    def __exit__(self, *exc):
        if self._timer is not None:
            self._timer.cancel()
            faulthandler.cancel_dump_traceback_later()
        return False


def sample(call, number: int) -> tuple[float, float]:
    """(wall, CPU) seconds per call over `number` back-to-back calls; CPU = this process's CPU
    time over all its threads, so CPU/wall > 1 means the call used several cores."""
    tic, cpu = time.perf_counter(), time.process_time()
    for _ in range(number):
        call()
    return (time.perf_counter() - tic) / number, (time.process_time() - cpu) / number


def time_interleaved(
    calls: dict, *, repeats: int, min_sample_s: float, guard=lambda name: contextlib.nullcontext()
) -> tuple[dict, dict]:
    """Median wall time of each blocking `calls[name]()` (module docstring: first call alone,
    a second call to fix the calls per sample, then `repeats` rotating rounds).

    Returns (timings, the first call's output per name). `timings[name]` holds `per_call_s`
    (the median), `samples_s`, `calls_per_sample`, `first_call_s`, `second_call_s` (right
    after the first, under the same load: first - second is the compile time) and
    `cpu_per_call_s` (median). `guard(name)` is a context manager around every phase (the
    watchdog).
    """
    names = list(calls)
    outs, first, second, number = {}, {}, {}, {}
    for name in names:
        with guard(name):
            tic = time.perf_counter()
            outs[name] = calls[name]()
            first[name] = time.perf_counter() - tic
            second[name], _ = sample(calls[name], 1)
        number[name] = max(1, math.ceil(min_sample_s / max(second[name], 1e-9)))
    wall = {name: [] for name in names}
    cpu = {name: [] for name in names}
    for r in range(repeats):
        k = r % len(names)
        for name in names[k:] + names[:k]:
            with guard(name):
                w, c = sample(calls[name], number[name])
            wall[name].append(w)
            cpu[name].append(c)
    timings = {
        name: {
            "per_call_s": statistics.median(wall[name]),
            "samples_s": wall[name],
            "calls_per_sample": number[name],
            "first_call_s": first[name],
            "second_call_s": second[name],
            # CPU time per call (median over samples), all threads of the process
            "cpu_per_call_s": statistics.median(cpu[name]),
        }
        for name in names
    }
    return timings, outs


def paired_ratios(num: list, den: list) -> dict:
    """Ratios of samples taken in the same round (back to back, under similar load): median,
    min and max over the rounds; a check on the ratio of medians when the load drifts."""
    r = [a / b for a, b in zip(num, den)]
    return {"median": statistics.median(r), "min": min(r), "max": max(r)}


# --------------------------------------------------------------------------------------------
# Machine information.


def git_revision() -> dict:
    """Commit of the checkout that `clebsch_jax` was imported from (None outside a checkout);
    `git_dirty`: uncommitted changes to tracked files."""
    root = Path(cj.__file__).resolve().parent.parent
    if not (root / ".git").exists():
        return {"git_commit": None, "git_dirty": None}
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, timeout=10
        ).stdout.strip()
        dirty = (
            subprocess.run(
                ["git", "status", "--porcelain", "--untracked-files=no"],
                cwd=root,
                capture_output=True,
                text=True,
                timeout=10,
            ).stdout.strip()
            != ""
        )
    except (OSError, subprocess.SubprocessError):
        return {"git_commit": None, "git_dirty": None}
    return {"git_commit": commit or None, "git_dirty": dirty if commit else None}


def source_digest() -> str:
    """SHA-256 (first 12 hex digits) of the `clebsch_jax` sources this run imported, to tell
    runs of one uncommitted working tree apart."""
    import hashlib

    digest = hashlib.sha256()
    package = Path(cj.__file__).resolve().parent
    for path in sorted(package.rglob("*.py")):
        digest.update(str(path.relative_to(package)).encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()[:12]


def load_average() -> float | None:
    """1-minute load average (other processes compete for the cores; compare with cpu_count)."""
    return os.getloadavg()[0] if hasattr(os, "getloadavg") else None


def cpu_model() -> str | None:
    """The CPU's model name and its widest vector extension (Linux: /proc/cpuinfo; else
    `platform.processor()`, or None). Hosts of the same kind differ: the same script ran ~2×
    faster on one 2-core host than on another, and ours/peer time ratios moved by up to ~1.4×."""
    name, flags = None, set()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name") and name is None:
                    name = line.split(":", 1)[1].strip()
                elif line.startswith("flags") and not flags:
                    flags = set(line.split(":", 1)[1].split())
    except OSError:
        return platform.processor() or None
    simd = next((f for f in ("avx512f", "avx2", "avx", "sse4_2") if f in flags), None)
    return f"{name}, {simd}" if name and simd else name


def machine_info() -> dict:
    import jaxlib

    affinity = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    xla_flags = os.environ.get("XLA_FLAGS")
    cache_dir = jax.config.values.get("jax_compilation_cache_dir")
    return {
        "platform": platform.platform(),
        "machine": platform.machine(),
        "python": platform.python_version(),
        "cpu_count": os.cpu_count(),
        "cpu_model": cpu_model(),
        "cpus_usable": affinity,
        # other processes compete for the cores; > 0 before the run means a loaded machine
        "load_average_1min_at_start": load_average(),
        "jax": jax.__version__,
        "jaxlib": jaxlib.__version__,
        "numpy": np.__version__,
        "clebsch_jax": cj.__version__,
        "jax_backend": jax.default_backend(),
        "jax_devices": [str(d) for d in jax.devices()],
        "jax_enable_x64": bool(jax.config.jax_enable_x64),
        # a persistent compilation cache would hide compile times (never a path here)
        "jax_persistent_compilation_cache": bool(cache_dir),
        "xla_flags": None if xla_flags is None else ("<set>" if "/" in xla_flags else xla_flags),
        "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        **git_revision(),
        "clebsch_jax_source_sha256": source_digest(),
    }


# --------------------------------------------------------------------------------------------
# One run of a benchmark script.


def parse_args(argv, *, prog: str, description: str, add_arguments=None) -> argparse.Namespace:
    """The flags every benchmark takes (`--quick`, `--out`, `--repeats`, `--min-sample`,
    `--timeout`) plus any that `add_arguments(parser)` adds. `repeats` and `min_sample` come
    back resolved (5 and 0.2 s; 2 and 0.01 s with `--quick`)."""
    parser = argparse.ArgumentParser(prog=prog, description=description)
    parser.add_argument(
        "--quick",
        action="store_true",
        help="small sizes and few repeats, XLA optimisation off (a smoke test, not a measurement)",
    )
    parser.add_argument("--out", type=Path, default=RESULTS_DIR, help="output directory (default: benchmarks/results)")
    parser.add_argument(
        "--repeats", type=int, default=None, help="timing samples per method and case (default 5; 2 with --quick)"
    )
    parser.add_argument(
        "--min-sample",
        type=float,
        default=None,
        dest="min_sample",
        help="minimum seconds per timing sample (default 0.2; 0.01 with --quick)",
    )
    parser.add_argument(
        "--timeout",
        type=float,
        default=600.0,
        help="exit with a message if one measurement takes longer (seconds, 0: never)",
    )
    if add_arguments is not None:
        add_arguments(parser)
    args = parser.parse_args(argv)
    if args.repeats is not None and args.repeats < 1:
        parser.error("--repeats must be >= 1")
    args.repeats = args.repeats or (2 if args.quick else 5)
    args.min_sample = args.min_sample if args.min_sample is not None else (0.01 if args.quick else 0.2)
    return args


@contextlib.contextmanager
def quick_mode(quick: bool):
    """With `quick`, JAX's `jax_disable_most_optimizations` on for the block (restored after):
    programs compile faster, run slower. Programs compiled meanwhile stay in JAX's in-memory
    cache: correct, just less optimised."""
    before = bool(jax.config.values.get(QUICK_FLAG, False))
    try:
        if quick:
            jax.config.update(QUICK_FLAG, True)
        yield
    finally:
        jax.config.update(QUICK_FLAG, before)


class Run:
    """One run of a benchmark script: its arguments, the machine at the start, the `--quick`
    switch (on between `__enter__` and `__exit__`), timing with the watchdog, progress lines,
    and writing `<name>.json` and `<name>.png` to `--out`."""

    def __init__(self, name: str, argv=None, *, description: str, add_arguments=None):
        self.name = name
        self.args = parse_args(argv, prog=f"{name}.py", description=description, add_arguments=add_arguments)
        self.quick = bool(self.args.quick)
        self.repeats, self.min_sample_s, self.timeout_s = self.args.repeats, self.args.min_sample, self.args.timeout
        self.compiler_options = QUICK_COMPILER_OPTIONS if self.quick else None
        self._flag_before = bool(jax.config.values.get(QUICK_FLAG, False))
        self._quick_mode = quick_mode(self.quick)

    def __enter__(self):
        self.t_begin = time.perf_counter()
        self.machine = machine_info()  # before the run: date and load average at the start
        self._quick_mode.__enter__()
        return self

    def __exit__(self, *exc):
        return self._quick_mode.__exit__(*exc)

    def guard(self, what: str) -> Watchdog:
        return Watchdog(self.timeout_s, what, self.name)

    def time(self, calls: dict, *, what: str, repeats: int | None = None) -> tuple[dict, dict]:
        """`time_interleaved` with this run's settings and the watchdog around every phase."""
        return time_interleaved(
            calls,
            repeats=repeats or self.repeats,
            min_sample_s=self.min_sample_s,
            guard=lambda method: self.guard(f"{method}, {what}"),
        )

    def measure(self, default_cases, quick_cases, describe, measure_case) -> list:
        """`measure_case(*case)` for each case of this run (`self.cases`: `quick_cases` with
        `--quick`), with a progress line `describe(*case)` for each; the list of their results."""
        self.cases = quick_cases if self.quick else default_cases
        results = []
        for case in self.cases:
            with self.case(describe(*case)):
                results.append(measure_case(*case))
        return results

    @contextlib.contextmanager
    def case(self, description: str):
        """Prints `running <description> ... <seconds> s` around a case."""
        print(f"running {description} ...", end=" ", flush=True)
        tic = time.perf_counter()
        yield
        print(f"{time.perf_counter() - tic:.0f} s (load {load_average():.2f})", flush=True)

    def config(self, **extra) -> dict:
        """The run's settings for the JSON `config`, with the script's own entries."""
        return {
            "quick": self.quick,
            "repeats": self.repeats,
            "min_sample_s": self.min_sample_s,
            "statistic": STATISTIC,
            "compiler_options": self.compiler_options,
            "jax_disable_most_optimizations": self.quick or self._flag_before,
            **extra,
        }

    def summary(self, *, config: dict, results: list, **extra) -> dict:
        return {
            "benchmark": self.name,
            "config": self.config(**config),
            **extra,
            "machine": self.machine,
            "results": results,
        }

    def finish(self, summary: dict, print_report, plot) -> dict:
        """Prints `print_report(summary)`, writes `<name>.json` (first, so the numbers survive a
        failing plot), then `plot(summary, path)` to `<name>.png`; returns the summary."""
        print_report(summary)
        out = Path(self.args.out)
        out.mkdir(parents=True, exist_ok=True)
        json_path, png_path = out / f"{self.name}.json", out / f"{self.name}.png"
        summary["total_runtime_s"] = time.perf_counter() - self.t_begin
        summary["load_average_1min_at_end"] = load_average()
        with open(json_path, "w") as fh:
            json.dump(summary, fh, indent=2)
        plot(summary, png_path)
        print(
            f"\ntotal {summary['total_runtime_s']:.0f} s (load {summary['load_average_1min_at_end']:.2f} at the "
            f"end); wrote {json_path.name} and {png_path.name} in {display_path(out)}"
        )
        return summary


def display_path(path: Path) -> str:
    """`path` relative to the working directory when below it (never an absolute path in logs)."""
    try:
        return str(path.resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


# --------------------------------------------------------------------------------------------
# Printing and plotting.


def fmt(x, spec: str, width: int, missing: str = "-") -> str:
    """`x` formatted right-aligned in `width`, or `missing` for None."""
    return f"{missing:>{width}}" if x is None else f"{x:>{width}{spec}}"


def print_header(summary: dict, what: str, legend: str) -> None:
    """The first lines of a report: `what`, the statistic, then `legend` (what the methods are)."""
    cfg = summary["config"]
    print(
        f"\n{what}; median of {cfg['repeats']} samples, each >= {cfg['min_sample_s']} s, the methods of a "
        f"case sampled in turn.\n{legend}"
    )


def print_table(head: str, lines) -> None:
    """A header, a rule as wide as the header, and the lines."""
    print(head)
    print("-" * len(head))
    for line in lines:
        print(line)


def rows_by(rows: list, key: str = "case") -> dict:
    """The result rows grouped by `row[key]` (the `case` label: "single", "vmap", ...), in order."""
    out = {}
    for r in rows:
        out.setdefault(r[key], []).append(r)
    return out


def figure(width_ratios, *, size=(11, 4.6)):
    """A matplotlib Figure (Agg, no pyplot state) with one row of axes."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, layout="constrained")
    FigureCanvasAgg(fig)
    return fig, fig.subplots(1, len(width_ratios), gridspec_kw={"width_ratios": list(width_ratios)})


def hollow_marker(label: str):
    """A legend entry for the hollow markers of the plots."""
    from matplotlib.lines import Line2D

    return Line2D([], [], color="0.3", marker="o", mfc="none", ms=9, ls="none", label=label)


def plot_title(summary: dict, what: str) -> str:
    """`what`, the statistic, and the machine and its load at the start, for a plot title."""
    mach, cfg = summary["machine"], summary["config"]
    load = mach.get("load_average_1min_at_start")
    return (
        f"{what}, median of {cfg['repeats']}{' (--quick: not a measurement)' if cfg['quick'] else ''}\n"
        f"{mach['cpu_count']} CPUs, load {'?' if load is None else f'{load:.2f}'} at start, "
        f"jax {mach['jax']}, numpy {mach['numpy']}"
    )
