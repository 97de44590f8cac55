"""The `clebsch-jax` command line.

Subcommands:

- `demo`: the scene of Figure 1 of the paper (rigid body, Example 30); writes two PNGs and
  `summary.json` and prints a table of the conserved quantities and timings. Then every
  built-in scene (`clebsch_jax.cli._scenes`) briefly, each into a subfolder, and one combined
  table. `--only NAME` runs one of them.
- `run SCENE`: one built-in scene with `--dt`, `--steps`, `--order`, `--scheme`, `--batch`, `--out`:
  a summary table on the terminal, `summary.json` and a PNG in the output folder, a progress
  bar on stderr for long runs.
- `bench [NAME ...]`: the scripts of the repository's `benchmarks/` folder, each in a
  subprocess with this Python (`--quick` passed through).
- `sweep CONFIG.toml --store OUT.zarr [--workers N | --scheduler ADDRESS]`: a parameter sweep
  described by a TOML file into a resumable Zarr store, here or on Dask workers (`_sweep`).

Each subcommand is a `_add_<name>(subparsers)` function that registers its parser and sets
`handler`.

Exit codes: 0 success, 1 the command failed (one line on stderr: an integration failure, a
missing dependency or folder, a benchmark that failed), 2 bad command line (one line on
stderr, as argparse does but without the usage block), 130 interrupted.

Nothing here imports matplotlib before it draws (`--help` stays light).
"""

from __future__ import annotations

import argparse
import ast
import math
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import clebsch_jax as cj
from clebsch_jax._startup import release_startup

__all__ = ["main"]

PROG = "clebsch-jax"

MAX_STEPS = 1_000_000
"""Largest accepted `--steps` (keeps the stored diagnostics within a few hundred MB)."""

MAX_BATCH = 10_000
"""Largest accepted `--batch` of `run` (for larger sweeps use `clebsch_jax.sweep`)."""

ORDERS = tuple(sorted({c.order for c in cj.COMPOSITIONS.values()} | {2}))
"""`--order` values without `--scheme gauss`: 2 and the orders of the compositions
(`integrate(..., order=)`)."""

GAUSS_ORDERS = cj.GAUSS_ORDERS
"""`--order` values with `--scheme gauss`."""

SCHEMES = cj.SCHEMES + ("gauss",)
"""`--scheme` values (`integrate(..., scheme=)`)."""

LONG_RUN = 100_000
"""Runs of at least this many member-steps show a progress bar even when stderr is not a terminal."""


class _Parser(argparse.ArgumentParser):
    """An `ArgumentParser` whose errors are one line on stderr (exit code 2)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


# --------------------------------------------------------------------------------------------
# Argument types: each rejects a bad value with one line naming what was expected.


def _whole_number(text: str, low: int, high: float, not_a_number: str, out_of_range: str) -> int:
    """`text` as an int in [low, high]; the messages are formatted with `text` and `value`."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(not_a_number.format(text=text)) from None
    if not low <= value <= high:
        raise argparse.ArgumentTypeError(out_of_range.format(text=text, value=value))
    return value


def _steps(text: str) -> int:
    return _whole_number(
        text,
        1,
        MAX_STEPS,
        "expected a whole number of steps, got {text!r}",
        f"expected 1 to {MAX_STEPS:,} steps, got {{value}}",
    )


def _dt(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a positive finite time step, got {text}")
    return value


def _order(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = None
    if value not in ORDERS + GAUSS_ORDERS:
        raise argparse.ArgumentTypeError(
            f"expected one of {', '.join(map(str, ORDERS))} (with --scheme gauss "
            f"an even order up to {GAUSS_ORDERS[-1]}), got {text!r}"
        )
    return value


def _batch(text: str) -> int:
    return _whole_number(
        text,
        1,
        MAX_BATCH,
        "expected a whole number of members, got {text!r}",
        f"expected 1 to {MAX_BATCH:,} members, got {{value}} (for larger batches use clebsch_jax.sweep)",
    )


def _seed(text: str) -> int:
    message = "expected a whole number >= 0, got {text!r}"
    return _whole_number(text, 0, math.inf, message, message)


def _chunk(text: str) -> int:
    message = "expected a whole number of steps >= 1, got {text!r}"
    return _whole_number(text, 1, MAX_STEPS, message, message)


def _scene_names() -> list:
    from ._scenes import SCENES

    return list(SCENES)


def _scene(text: str) -> str:
    name = text.strip().lower().replace("_", "-")
    names = _scene_names()
    if name not in names:
        raise argparse.ArgumentTypeError(f"unknown scene {text!r}; known scenes: {', '.join(names)}")
    return name


def fail(message: str, *, code: int = 1, prog: str = PROG) -> int:
    """Print `prog: error: message` on stderr; return the exit code."""
    print(f"{prog}: error: {message}", file=sys.stderr)
    return code


def _check_out_dir(out_dir: str, prog: str) -> int | None:
    """Exit code 2 (one line) when `out_dir` exists and is not a folder, else None."""
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        return fail(f"--out: {out_dir!r} exists and is not a folder", code=2, prog=prog)
    return None


def _make_out_dir(out_dir: str, prog: str) -> int | None:
    """Create `out_dir`; exit code 1 (one line) when that is impossible, else None."""
    try:
        os.makedirs(out_dir, exist_ok=True)
    except OSError as err:
        return fail(f"could not create {out_dir!r}: {err.strerror or err}", prog=prog)
    if not os.access(out_dir, os.W_OK):
        return fail(f"{out_dir!r} is not writable", prog=prog)
    return None


def _require_matplotlib(prog: str) -> int | None:
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return fail(
            'the plots are drawn with matplotlib, which is not installed: pip install "clebsch-jax[plot]"', prog=prog
        )
    return None


# --------------------------------------------------------------------------------------------
# A tiny progress bar (no dependency).


class _ProgressBar:
    """A one-line progress bar on `stream`: redrawn in place on a terminal; elsewhere (a log)
    printed as a new line at every tenth of the run. Call it with (done, total, elapsed_s)."""

    def __init__(self, label: str, stream=None, tty: bool | None = None, width: int = 28):
        self.label, self.width = label, width
        self.stream = sys.stderr if stream is None else stream
        self.tty = _isatty(self.stream) if tty is None else tty
        self.first = None  # (done, elapsed) after the first call, which includes compilation
        self.last_draw = -math.inf
        self.last_tenth = -1
        self.drawn = False

    def __call__(self, done: int, total: int, elapsed: float) -> None:
        if self.first is None and done > 0:
            self.first = (done, elapsed)  # this call included the compilation
        frac = done / total if total else 1.0
        now = time.perf_counter()
        if self.tty:
            if done < total and now - self.last_draw < 0.1:
                return
        elif int(10 * frac) <= self.last_tenth and done < total:
            return
        self.last_draw, self.last_tenth = now, int(10 * frac)
        filled = int(round(self.width * frac))
        eta = ", compiling..." if done == 0 else ""
        d0, e0 = self.first or (done, elapsed)
        if d0 < done < total:
            eta = f", ~{(elapsed - e0) / (done - d0) * (total - done):.0f} s left"
        line = (
            f"{self.label} [{'#' * filled}{'.' * (self.width - filled)}] {100 * frac:3.0f}% "
            f"{done:,}/{total:,} steps, {elapsed:.1f} s{eta}"
        )
        if self.tty:
            self.stream.write("\r" + line + "\x1b[K")
        else:
            self.stream.write(line + "\n")
        self.stream.flush()
        self.drawn = True

    def close(self) -> None:
        if self.tty and self.drawn:
            self.stream.write("\n")
            self.stream.flush()


def paragraphs(*texts: str) -> str:
    """Help text: each paragraph wrapped to 79 columns, except those with line breaks (lists)."""
    return "\n\n".join(t if "\n" in t else textwrap.fill(t, 79) for t in texts)


def _isatty(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


# --------------------------------------------------------------------------------------------
# Scene runs: shared by `run` and `demo`.


def _fmt(x, spec: str = ".2e") -> str:
    return "n/a" if x is None else format(x, spec)


def _failure_text(summary: dict) -> str:
    """'none', or how many members failed, the first one's step, time and reason, the others' steps."""
    fails = summary["failures"]
    if not fails["count"]:
        return "none"
    first, others = fails["members"][0], fails["members"][1:6]
    text = (
        f"{fails['count']} of {summary['scene']['members']} members failed: member {first['member']} at "
        f"step {first['step']} (t = {first['t']:.4g}): {first['reason']}"
    )
    if others:
        text += "; also " + ", ".join(f"member {f['member']} (step {f['step']})" for f in others)
        if fails["count"] > 1 + len(others):
            text += f" and {fails['count'] - 1 - len(others)} more"
    return text


def _run_scene_into(
    scene, out_dir: str, *, dt=None, steps=None, order=None, batch=1, seed=0, chunk=None, progress=None, scheme=None
) -> dict:
    """`run_scene`, then write `<scene>.png` and `summary.json` into `out_dir` (which exists)."""
    from ._scene_report import write_plot, write_summary
    from ._scene_run import run_scene

    summary = run_scene(
        scene,
        dt=dt,
        n_steps=steps,
        order=order,
        batch=batch,
        seed=seed,
        chunk_steps=chunk,
        progress=progress,
        scheme=scheme,
    )
    tic = time.perf_counter()
    png = f"{scene.name}.png"
    write_plot(scene, summary, os.path.join(out_dir, png))
    summary["timing"]["plot_s"] = time.perf_counter() - tic
    write_summary(summary, out_dir, [png, "summary.json"])
    summary["files"] = [png, "summary.json"]
    return summary


def _run_table(scene, summary: dict, out_dir: str) -> str:
    """The terminal table of one `run`."""
    run, inv, newton, timing = summary["run"], summary["invariants"], summary["newton_iterations"], summary["timing"]
    members = summary["scene"]["members"]
    rows = [
        ("method", f"{run['method']} ({run['form']} march, order {run['order']}, {run['derivative_map']})"),
        (
            "steps",
            f"{run['n_steps']:,} x {members} member{'s' if members > 1 else ''}, dt = {run['dt']:g}, "
            f"t = 0 to {run['t_final']:g} ({run['chunks']} chunk{'s' if run['chunks'] > 1 else ''} "
            f"of {run['steps_per_chunk']:,})",
        ),
        ("wall time", f"{timing['wall_s']:.2f} s (compile + first chunk {timing['first_chunk_s']:.2f} s)"),
        ("energy error (max rel.)", _fmt(summary["errors"]["energy_rel_max"])),
    ]
    for name, entry in inv.items():
        if name == "energy":
            continue
        what = "max rel. drift" if entry["kind"] == "drift" else "max"
        rows.append((f"{entry['label']} ({what})", _fmt(entry["max"])))
    if summary["reference"] is not None:
        rows.append((f"{summary['reference']['label']} (max)", _fmt(summary["reference"]["max"])))
    rows += [
        ("Newton iterations/step", f"{_fmt(newton['mean'], '.2f')} mean, {newton['max']} max"),
        ("failures", _failure_text(summary)),
    ]
    width = max(len(k) for k, _ in rows)
    lines = [f"{scene.name}: {scene.description}"]
    lines += [f"  {k:<{width}}  {v}" for k, v in rows]
    lines.append(f"wrote {', '.join(summary['files'])} to {out_dir}")
    return "\n".join(lines)


def _short_invariants(summary: dict) -> str:
    parts = [f"{e['label']} {_fmt(e['max'], '.1e')}" for k, e in summary["invariants"].items() if k != "energy"]
    if summary.get("reference"):
        parts.append(f"{summary['reference']['label']} {_fmt(summary['reference']['max'], '.1e')}")
    return "; ".join(parts)


def _combined_table(rows: list) -> str:
    """Rows of (scene, method, steps, wall, energy, invariants, newton, failures) as columns."""
    header = (
        "scene",
        "method",
        "steps x members",
        "wall",
        "energy err.",
        "Newton it./step",
        "failures",
        "invariants (max rel. drift / max error)",
    )
    table = [header] + [tuple(r) for r in rows]
    widths = [max(len(r[i]) for r in table) for i in range(len(header) - 1)]
    fmt = lambda r: "  ".join(f"{c:<{w}}" for c, w in zip(r, widths)) + "  " + r[-1]
    return "\n".join(["  " + fmt(header)] + ["  " + fmt(r) for r in table[1:]])


def _scene_row(summary: dict) -> tuple:
    run, newton = summary["run"], summary["newton_iterations"]
    fails = summary["failures"]["count"]
    return (
        summary["scene"]["name"],
        run["method"],
        f"{run['n_steps']} x {summary['scene']['members']}",
        f"{summary['timing']['wall_s']:.1f} s",
        _fmt(summary["errors"]["energy_rel_max"]),
        f"{_fmt(newton['mean'], '.1f')} / {newton['max']}",
        "0"
        if not fails
        else f"{fails} (member {summary['failures']['members'][0]['member']} "
        f"at step {summary['failures']['members'][0]['step']})",
        _short_invariants(summary),
    )


def _figure1_row(summary: dict) -> tuple:
    err, newton, scene = summary["errors"], summary["newton_iterations"], summary["scene"]
    return (
        "figure-1",
        f"CAY, Example 30 ({scene['march']} march)",
        f"{scene['n_steps']} x {scene['n_orbits']}",
        f"{summary['timing']['total_s']:.1f} s",
        _fmt(err["energy_rel_max"]),
        f"{newton['mean']:.1f} / {newton['max']}",
        "0",
        f"Casimir |m|^2 {err['casimir_rel_max']:.1e}; spatial ang. momentum "
        f"{err['spatial_momentum_drift_rel_max']:.1e}; |Q^T Q - I| {err['orthogonality_max']:.1e}",
    )


# --------------------------------------------------------------------------------------------
# run


def _use_compilation_cache(args, prog: str) -> None:
    """The persistent compilation cache (`enable_compilation_cache`), unless `--no-cache` or the
    environment variable CLEBSCH_JAX_NO_CACHE is set; a cache that cannot be used is reported
    on stderr and the run goes on without it."""
    if args.no_cache or os.environ.get("CLEBSCH_JAX_NO_CACHE"):
        return
    try:
        cj.enable_compilation_cache()
    except (OSError, ValueError) as exc:
        print(f"{prog}: compiling without the cache: {exc}", file=sys.stderr)


def _add_cache_flag(p) -> None:
    p.add_argument(
        "--no-cache",
        action="store_true",
        help="do not keep compiled programs on disk (by default they are kept in "
        "$CLEBSCH_JAX_CACHE_DIR or ~/.cache/clebsch-jax/xla, so a second run "
        "skips most of the compilation; CLEBSCH_JAX_NO_CACHE=1 does the same)",
    )


def _run_run(args) -> int:
    from ._scene_run import chunk_steps_for
    from ._scenes import SCENES

    prog = f"{PROG} run"
    scene = SCENES[args.scene]
    out_dir = args.out if args.out is not None else os.path.join("clebsch-jax-run", scene.name)
    code = _check_out_dir(out_dir, prog) or _require_matplotlib(prog) or _make_out_dir(out_dir, prog)
    if code:
        return code
    if args.order is not None and args.order not in (GAUSS_ORDERS if args.scheme == "gauss" else ORDERS):
        return fail(
            f"--order {args.order} needs --scheme gauss (the compositions have orders {', '.join(map(str, ORDERS))})",
            code=2,
            prog=prog,
        )
    _use_compilation_cache(args, prog)
    steps = scene.steps if args.steps is None else args.steps
    chunk = args.chunk or chunk_steps_for(args.batch, steps)
    show = (
        not args.quiet
        and -(-steps // chunk) > 1
        and (args.progress or _isatty(sys.stderr) or args.batch * steps >= LONG_RUN)
    )
    bar = _ProgressBar(f"{scene.name}") if show else None
    if not args.quiet:
        print(
            f"{prog}: integrating {scene.name} ({steps:,} steps x {args.batch} member"
            f"{'s' if args.batch > 1 else ''}); compiling first takes a few seconds...",
            flush=True,
        )
    try:
        summary = _run_scene_into(
            scene,
            out_dir,
            dt=args.dt,
            steps=steps,
            order=args.order,
            batch=args.batch,
            seed=args.seed,
            chunk=chunk,
            progress=bar,
            scheme=args.scheme,
        )
    except OSError as err:
        return fail(f"could not write to {out_dir!r}: {err.strerror or err}", prog=prog)
    except ValueError as err:  # integrate refused the scheme for this scene's system, before compiling
        if args.scheme is None:
            raise
        return fail(f"--scheme {args.scheme} on {scene.name}: {str(err).splitlines()[0]}", code=2, prog=prog)
    finally:
        if bar is not None:
            bar.close()
    print(_run_table(scene, summary, out_dir))
    if summary["failures"]["count"]:
        return fail(f"{_failure_text(summary)}. Try a smaller --dt.", prog=prog)
    return 0


def _add_run(subparsers) -> None:
    from ._scenes import SCENES

    scenes = "\n".join(
        f"  {s.name:<11} {s.description}\n"
        + textwrap.fill(s.details, 79, initial_indent=" " * 14, subsequent_indent=" " * 14)
        for s in SCENES.values()
    )
    p = subparsers.add_parser(
        "run",
        help="integrate one built-in scene (rigid-body, heavy-top, vortices, peakons, landmarks)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=paragraphs(
            "Integrate a built-in scene with the discrete Clebsch integrator (integrate(..., "
            "throw=False) under jax.vmap over --batch members), print a summary table (method, "
            "steps, wall time, energy error, the scene's momentum/Casimir errors, Newton "
            "iterations, failures) and write summary.json and SCENE.png (trajectories and "
            "invariant errors against time) into --out.",
            "scenes:\n" + scenes,
            "Member 0 is the scene's canonical initial condition; with --batch B the others are "
            "drawn at random (--seed). A failing member (e.g. too large a --dt) does not stop "
            "the others: it is reported with its step, and the exit code is 1. Long runs go in "
            "chunks of steps with a progress bar on stderr (on a terminal, or for runs of "
            f"{LONG_RUN:,} member-steps and more); runs of at most 20,000 member-steps are "
            "compiled with XLA's backend optimisation off (compilation dominates them).",
        ),
        epilog="examples: clebsch-jax run vortices --steps 20000 --order 4 --batch 8\n"
        "          clebsch-jax run vortices --scheme gauss --order 12 --dt 0.25 --steps 2000",
    )
    p.add_argument("scene", type=_scene, metavar="SCENE", help=f"one of: {', '.join(SCENES)}")
    p.add_argument(
        "--dt",
        type=_dt,
        default=None,
        metavar="DT",
        help="time step > 0 (default: the scene's, " + ", ".join(f"{s.name} {s.dt:g}" for s in SCENES.values()) + ")",
    )
    p.add_argument(
        "--steps",
        type=_steps,
        default=None,
        metavar="N",
        help=f"number of time steps, 1 to {MAX_STEPS:,} (default: the scene's, "
        + ", ".join(f"{s.name} {s.steps}" for s in SCENES.values())
        + ")",
    )
    p.add_argument(
        "--order",
        type=_order,
        default=None,
        metavar="K",
        help="order of the method: 2, 4, 6 or 8 (symmetric compositions of discrete "
        "Clebsch steps; default 2); with --scheme gauss an even order up to 16 "
        "(order/2 Gauss-Legendre stages)",
    )
    p.add_argument(
        "--scheme",
        choices=SCHEMES,
        default=None,
        metavar="S",
        help="discrete principle: left, right, midpoint, or gauss (the Gauss-Legendre "
        "discretisation of the Clebsch principle); default the scene's. A scheme the "
        "scene's system does not admit (left/right for the degenerate vortices) is "
        "refused before compiling",
    )
    p.add_argument(
        "--batch",
        type=_batch,
        default=1,
        metavar="B",
        help=f"number of members, 1 to {MAX_BATCH:,} (default 1), run under jax.vmap",
    )
    p.add_argument(
        "--seed", type=_seed, default=0, metavar="S", help="seed of the random members 1, ..., B-1 (default 0)"
    )
    p.add_argument(
        "--out", metavar="DIR", default=None, help="output folder, created if needed (default: ./clebsch-jax-run/SCENE)"
    )
    p.add_argument(
        "--chunk",
        type=_chunk,
        default=None,
        metavar="N",
        help="steps per compiled call (default: automatic, at most ~50 chunks; "
        "smaller chunks use less memory and update the progress bar more often)",
    )
    p.add_argument("--progress", action="store_true", help="draw the progress bar even when stderr is not a terminal")
    p.add_argument(
        "--quiet", action="store_true", help="no progress bar or status line (the summary table is still printed)"
    )
    _add_cache_flag(p)
    p.set_defaults(handler=_run_run)


# --------------------------------------------------------------------------------------------
# demo


def _fmt_time(seconds: float) -> str:
    return f"{seconds:.2f} s"


def _demo_table(summary: dict, out_dir: str) -> str:
    """The terminal table of `figure1`'s summary."""
    scene, err, timing = summary["scene"], summary["errors"], summary["timing"]
    newton = summary["newton_iterations"]
    cov = summary["periods_covered"]
    inertia = ", ".join(f"{x:g}" for x in scene["inertia"])
    unoptimised = " (XLA optimisation off for --quick)" if scene.get("compiler_options") else ""
    rows = [
        ("orbits", f"{scene['n_orbits']} on |m| = 1 (vmapped)"),
        ("march", f"{scene['march']} (Solution.form)"),
        ("time steps", f"{scene['n_steps']} (t = 0 to {scene['t_final']:g})"),
        ("periods covered", f"{cov['min']:.3g} (slowest orbit) to {cov['max']:.3g} (fastest)"),
        ("energy error (max rel.)", f"{err['energy_rel_max']:.2e}"),
        ("Casimir |m|^2 error (max rel.)", f"{err['casimir_rel_max']:.2e}"),
        ("spatial momentum drift (max rel.)", f"{err['spatial_momentum_drift_rel_max']:.2e}"),
        ("orthogonality error (max)", f"{err['orthogonality_max']:.2e}"),
        ("Newton iterations/step", f"{newton['mean']:.2f} mean, {newton['max']} max"),
        (
            "steps/s (compiled)",
            f"{timing['steps_per_s']:,.0f} x {scene['n_orbits']} orbits "
            f"= {timing['orbit_steps_per_s']:,.0f} orbit-steps/s{unoptimised}",
        ),
        ("compile + first call", _fmt_time(timing["compile_and_first_call_s"])),
        ("demo total (after imports)", _fmt_time(timing["total_s"])),
    ]
    width = max(len(k) for k, _ in rows)
    lines = [
        f"Figure 1 scene: rigid body, I = ({inertia}), dt = {scene['dt']:g}, {scene['derivative_map']} derivative map"
    ]
    lines += [f"  {k:<{width}}  {v}" for k, v in rows]
    if not scene["quick"] and cov["min"] < summary["target_periods"] - 0.5:
        lines.append(
            f"  (the paper shows {summary['target_periods']} periods: "
            f"--steps {summary['steps_for_target_periods']} covers them for the slowest orbit)"
        )
    lines.append(f"wrote {', '.join(summary['files'])} to {out_dir}")
    return "\n".join(lines)


FIGURE1 = "figure-1"
"""`demo --only` name of the Figure 1 scene."""


def _demo_figure1(args, out_dir: str, prog: str):
    """Run the Figure 1 scene; returns (exit code or None, summary or None)."""
    from ._demo import MissingPlotDependency, figure1

    print(
        f"{PROG} demo: integrating the Figure 1 scene"
        f"{' (quick)' if args.quick else ''}; compiling first takes a few seconds...",
        flush=True,
    )
    try:
        summary = figure1(out_dir, quick=args.quick, n_steps=args.steps)
    except MissingPlotDependency as err:
        return fail(str(err), prog=prog), None
    except cj.IntegrationError as err:
        return fail(str(err), prog=prog), None
    except OSError as err:
        return fail(f"could not write to {out_dir!r}: {err.strerror or err}", prog=prog), None
    print(_demo_table(summary, out_dir))
    return None, summary


def _run_demo(args) -> int:
    from ._scenes import SCENES

    prog = f"{PROG} demo"
    out_dir = args.out
    code = _check_out_dir(out_dir, prog)
    if code:
        return code
    _use_compilation_cache(args, prog)
    only = args.only
    rows = []
    if only in (None, FIGURE1):
        code, fig = _demo_figure1(args, out_dir, prog)
        if code:
            return code
        if only == FIGURE1:
            return 0
        rows.append(_figure1_row(fig))
    code = _require_matplotlib(prog) or _make_out_dir(out_dir, prog)
    if code:
        return code
    scenes = [SCENES[only]] if only else list(SCENES.values())
    failed = []
    print(
        f"{prog}: the built-in scenes, briefly ({'each' if len(scenes) > 1 else 'it'} mostly compiles: "
        "XLA optimisation off)...",
        flush=True,
    )
    for scene in scenes:
        steps = args.steps if only and args.steps is not None else scene.quick_steps
        sub = os.path.join(out_dir, scene.name)
        code = _check_out_dir(sub, prog) or _make_out_dir(sub, prog)
        if code:
            return code
        print(f"  {scene.name}: {steps} steps x {scene.quick_batch} members...", flush=True)
        try:
            summary = _run_scene_into(scene, sub, steps=steps, batch=scene.quick_batch)
        except OSError as err:
            return fail(f"could not write to {sub!r}: {err.strerror or err}", prog=prog)
        rows.append(_scene_row(summary))
        if summary["failures"]["count"]:
            failed.append(f"{scene.name}: {_failure_text(summary)}")
    print(f"Built-in scenes (files in {out_dir}{os.sep}SCENE{os.sep}; clebsch-jax run SCENE for longer runs):")
    print(_combined_table(rows))
    if failed:
        return fail("; ".join(failed), prog=prog)
    return 0


def _add_demo(subparsers) -> None:
    from ._demo import MAX_DEFAULT_STEPS, QUICK_STEPS, TARGET_PERIODS
    from ._scenes import SCENES

    p = subparsers.add_parser(
        "demo",
        help="the paper's Figure 1 scene (rigid body), then every built-in scene briefly",
        description=(
            "Integrate a batch of free rigid-body orbits (inertia (0.5, 0.6, 1), dt = 0.1, "
            "Cayley derivative map: Example 30 / Figure 1 of Cotter & Holm) under jax.vmap, "
            "write figure1_orbits.png, figure1_invariants.png and summary.json into the "
            "output folder, and print the conservation errors and timings. The paper shows "
            f"{TARGET_PERIODS} periods; by default the run is capped at {MAX_DEFAULT_STEPS} steps, "
            "and the table says how many periods it covered and which --steps covers all of "
            "them. Then run every built-in scene (" + ", ".join(SCENES) + ") for a few hundred "
            "steps, each into a subfolder, and print one combined table (each scene's time is "
            "mostly compilation)."
        ),
    )
    p.add_argument(
        "--out",
        metavar="DIR",
        default="clebsch-jax-demo",
        help="output folder, created if needed (default: ./clebsch-jax-demo)",
    )
    p.add_argument(
        "--steps",
        metavar="N",
        type=_steps,
        default=None,
        help=f"number of time steps of the Figure 1 scene (default: {TARGET_PERIODS} periods "
        f"of the slowest orbit, capped at {MAX_DEFAULT_STEPS}; {QUICK_STEPS} with --quick), "
        "or of the --only scene",
    )
    p.add_argument(
        "--quick",
        action="store_true",
        help="fewer orbits and steps in the Figure 1 scene: a smoke test (a few seconds plus compilation)",
    )
    p.add_argument(
        "--only",
        metavar="NAME",
        default=None,
        type=_demo_name,
        help=f"run only one scene: {FIGURE1} (the Figure 1 scene) or one of {', '.join(SCENES)}",
    )
    _add_cache_flag(p)
    p.set_defaults(handler=_run_demo)


def _demo_name(text: str) -> str:
    if text.strip().lower().replace("_", "-") in (FIGURE1, "figure1"):
        return FIGURE1
    try:
        return _scene(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(
            f"unknown scene {text!r}; known: {FIGURE1}, {', '.join(_scene_names())}"
        ) from None


# --------------------------------------------------------------------------------------------
# bench


def _benchmarks_dir() -> Path:
    """The repository's `benchmarks/` folder, next to the package folder (an editable install
    from a clone); it does not exist in an installed wheel."""
    return Path(cj.__file__).resolve().parent.parent / "benchmarks"


def _benchmarks(folder: Path) -> dict:
    """{name: path} of the benchmark scripts: every `*.py` not starting with `_`."""
    return {p.stem: p for p in sorted(folder.glob("*.py")) if not p.name.startswith("_")}


def _first_doc_line(path: Path) -> str:
    try:
        doc = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8")))
    except (OSError, SyntaxError, UnicodeDecodeError):
        return ""
    return " ".join(doc.strip().split("\n\n")[0].split()) if doc else ""


def _run_bench(args) -> int:
    prog = f"{PROG} bench"
    folder = _benchmarks_dir()
    scripts = _benchmarks(folder) if folder.is_dir() else {}
    if not scripts:
        return fail(
            f"no benchmarks folder next to the package ({folder}): the benchmarks ship with the "
            "repository, not the installed package; clone it and `pip install -e .` to run them",
            prog=prog,
        )
    unknown = [n for n in args.names if n not in scripts]
    if unknown:
        return fail(
            f"unknown benchmark{'s' if len(unknown) > 1 else ''} {', '.join(map(repr, unknown))}; "
            f"known: {', '.join(scripts)}",
            code=2,
            prog=prog,
        )
    names = list(dict.fromkeys(args.names)) or list(scripts)
    if args.list:
        width = max(len(n) for n in scripts)
        for name, path in scripts.items():
            print(f"{name:<{width}}  {_first_doc_line(path)}")
        return 0
    out_dir = args.out
    if out_dir is None and args.quick:
        out_dir = "clebsch-jax-bench-quick"  # smoke numbers must not replace the recorded results
    if out_dir is not None:
        code = _check_out_dir(out_dir, prog) or _make_out_dir(out_dir, prog)
        if code:
            return code
    results = []
    for name in names:
        cmd = (
            [sys.executable, str(scripts[name])]
            + (["--quick"] if args.quick else [])
            + (["--out", os.path.abspath(out_dir)] if out_dir is not None else [])
        )
        print(
            f"== {prog}: {name}{' --quick' if args.quick else ''} (results in {out_dir or folder / 'results'}) ==",
            flush=True,
        )
        tic = time.perf_counter()
        rc = subprocess.run(cmd).returncode
        results.append((name, rc, time.perf_counter() - tic))
    width = max(len(n) for n, _, _ in results)
    print(f"{prog}: done")
    for name, rc, wall in results:
        print(f"  {name:<{width}}  {'ok' if rc == 0 else f'FAILED (exit code {rc})'}  {wall:.1f} s")
    bad = [n for n, rc, _ in results if rc != 0]
    if bad:
        return fail(
            f"{len(bad)} of {len(results)} benchmarks failed: {', '.join(bad)} (their output is above)", prog=prog
        )
    return 0


def _add_bench(subparsers) -> None:
    p = subparsers.add_parser(
        "bench",
        help="run the repository's benchmark scripts (benchmarks/*.py)",
        description=(
            "Run the scripts of the repository's benchmarks/ folder (rigid_body_step_cost, "
            "vortex_step_cost, throughput, work_precision and any other *.py there not starting "
            "with '_'), each in a subprocess with this Python, one after the other. Each prints "
            "its own report and writes a JSON and a PNG. The folder ships with the repository, "
            "not with an installed wheel: run from a clone (pip install -e .). Full runs take "
            "minutes each; nothing here asserts a time."
        ),
    )
    p.add_argument("names", nargs="*", metavar="NAME", help="benchmarks to run (default: all; see --list)")
    p.add_argument(
        "--quick",
        action="store_true",
        help="pass --quick to each script (small sizes, XLA optimisation off: a smoke run); "
        "results go to ./clebsch-jax-bench-quick unless --out is given",
    )
    p.add_argument("--list", action="store_true", help="list the benchmarks and what each measures, then exit")
    p.add_argument(
        "--out",
        metavar="DIR",
        default=None,
        help="output folder passed to the scripts (default: benchmarks/results, the recorded "
        "results; ./clebsch-jax-bench-quick with --quick)",
    )
    p.set_defaults(handler=_run_bench)


# --------------------------------------------------------------------------------------------


def _add_sweep(subparsers) -> None:
    from ._sweep import add

    add(subparsers)


def _build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog=PROG,
        description="Structure-preserving integrators from Clebsch variational principles, in JAX.",
        epilog="'clebsch-jax COMMAND --help' describes each command.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {cj.__version__}")
    subparsers = parser.add_subparsers(title="commands", dest="command", metavar="COMMAND", required=True)
    _add_demo(subparsers)
    _add_run(subparsers)
    _add_bench(subparsers)
    _add_sweep(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the `clebsch-jax` command line; returns the exit code.

    **Arguments:**

    - `argv`: the arguments after the program name (default: `sys.argv[1:]`).

    `--help`, `--version` and command-line errors return their exit codes (0, 0, 2) instead of
    raising `SystemExit`, so `main` can be called from Python.
    """
    parser = _build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version, or a one-line error already printed
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    try:
        release_startup()  # Ctrl-C raises KeyboardInterrupt from here on (clebsch_jax._startup)
        return args.handler(args)
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
