"""The `clebsch-jax` command line.

Subcommands:

- `demo`: the scene of Figure 1 of the paper (rigid body, Example 30); writes two PNGs and
  `summary.json` and prints a table of the conserved quantities and timings.

Each subcommand is a `_add_<name>(subparsers)` function that registers its parser and sets
`handler`; later subcommands (`run`, `bench`) plug in the same way.

Exit codes: 0 success, 1 the command failed (one line on stderr), 2 bad command line (one
line on stderr, as argparse does but without the usage block), 130 interrupted.
"""

from __future__ import annotations

import argparse
import os
import sys

__all__ = ["main"]

PROG = "clebsch-jax"

MAX_STEPS = 1_000_000
"""Largest accepted `--steps` (keeps the stored diagnostics within a few hundred MB)."""


class _Parser(argparse.ArgumentParser):
    """An `ArgumentParser` whose errors are one line on stderr (exit code 2)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def _steps(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number of steps, got {text!r}") from None
    if not 1 <= value <= MAX_STEPS:
        raise argparse.ArgumentTypeError(f"expected 1 to {MAX_STEPS:,} steps, got {value}")
    return value


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
        ("steps/s (compiled)", f"{timing['steps_per_s']:,.0f} x {scene['n_orbits']} orbits "
                               f"= {timing['orbit_steps_per_s']:,.0f} orbit-steps/s{unoptimised}"),
        ("compile + first call", _fmt_time(timing["compile_and_first_call_s"])),
        ("demo total (after imports)", _fmt_time(timing["total_s"])),
    ]
    width = max(len(k) for k, _ in rows)
    lines = [f"Figure 1 scene: rigid body, I = ({inertia}), dt = {scene['dt']:g}, "
             f"{scene['derivative_map']} derivative map"]
    lines += [f"  {k:<{width}}  {v}" for k, v in rows]
    if not scene["quick"] and cov["min"] < summary["target_periods"] - 0.5:
        lines.append(f"  (the paper shows {summary['target_periods']} periods: "
                     f"--steps {summary['steps_for_target_periods']} covers them for the slowest orbit)")
    lines.append(f"wrote {', '.join(summary['files'])} to {out_dir}")
    return "\n".join(lines)


def _run_demo(args) -> int:
    from ._demo import MissingPlotDependency, figure1
    from ._solution import IntegrationError

    out_dir = args.out
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        return _fail(f"--out: {out_dir!r} exists and is not a folder", code=2, prog=f"{PROG} demo")
    print(f"{PROG} demo: integrating the Figure 1 scene"
          f"{' (quick)' if args.quick else ''}; compiling first takes a few seconds...", flush=True)
    try:
        summary = figure1(out_dir, quick=args.quick, n_steps=args.steps)
    except MissingPlotDependency as err:
        return _fail(str(err), prog=f"{PROG} demo")
    except IntegrationError as err:
        return _fail(str(err), prog=f"{PROG} demo")
    except OSError as err:
        return _fail(f"could not write to {out_dir!r}: {err.strerror or err}", prog=f"{PROG} demo")
    print(_demo_table(summary, out_dir))
    return 0


def _add_demo(subparsers) -> None:
    from ._demo import MAX_DEFAULT_STEPS, QUICK_STEPS, TARGET_PERIODS

    p = subparsers.add_parser(
        "demo",
        help="reproduce the rigid-body scene of the paper's Figure 1 (PNGs + summary.json)",
        description=(
            "Integrate a batch of free rigid-body orbits (inertia (0.5, 0.6, 1), dt = 0.1, "
            "Cayley derivative map: Example 30 / Figure 1 of Cotter & Holm) under jax.vmap, "
            "write figure1_orbits.png, figure1_invariants.png and summary.json into the "
            "output folder, and print the conservation errors and timings. The paper shows "
            f"{TARGET_PERIODS} periods; by default the run is capped at {MAX_DEFAULT_STEPS} steps "
            "(about 25 s on 2 CPU cores), and the table says how many periods it covered and "
            "which --steps covers all of them."
        ),
    )
    p.add_argument("--out", metavar="DIR", default="clebsch-jax-demo",
                   help="output folder, created if needed (default: ./clebsch-jax-demo)")
    p.add_argument("--steps", metavar="N", type=_steps, default=None,
                   help=f"number of time steps (default: {TARGET_PERIODS} periods of the slowest orbit, "
                        f"capped at {MAX_DEFAULT_STEPS}; {QUICK_STEPS} with --quick)")
    p.add_argument("--quick", action="store_true",
                   help="fewer orbits and steps: a smoke test (a few seconds plus compilation)")
    p.set_defaults(handler=_run_demo)


# --------------------------------------------------------------------------------------------


def _fail(message: str, *, code: int = 1, prog: str = PROG) -> int:
    print(f"{prog}: error: {message}", file=sys.stderr)
    return code


def _build_parser() -> argparse.ArgumentParser:
    from . import __version__

    parser = _Parser(
        prog=PROG,
        description="Structure-preserving integrators from Clebsch variational principles, in JAX.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    subparsers = parser.add_subparsers(title="commands", dest="command", metavar="COMMAND", required=True)
    _add_demo(subparsers)
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
        return args.handler(args)
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
