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

Each subcommand is a module with an `add(subparsers)` function that registers its parser and
sets `handler`: `_demo_command`, `_run_command`, `_bench_command`, `_sweep`; the parsing they
share is `_arguments` (argument types, limits, help text), their setup `_setup` (output folder,
matplotlib, compilation cache, `fail`), and `_progress` and `_tables` what they show.

Exit codes: 0 success, 1 the command failed (one line on stderr: an integration failure, a
missing dependency or folder, a benchmark that failed), 2 bad command line (one line on
stderr, as argparse does but without the usage block), 130 interrupted.

Nothing here imports matplotlib before it draws (`--help` stays light).
"""

from __future__ import annotations

import argparse
import sys

import clebsch_jax as cj
from clebsch_jax._startup import release_startup

from . import _bench_command, _demo_command, _run_command, _sweep
from ._arguments import PROG, Parser

# the command line's limits and values, and its error and help helpers, still read from here
from ._arguments import GAUSS_ORDERS, LONG_RUN, MAX_BATCH, MAX_STEPS, ORDERS, SCHEMES, paragraphs  # noqa: F401
from ._setup import fail  # noqa: F401

__all__ = ["main"]


def _build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog=PROG,
        description="Structure-preserving integrators from Clebsch variational principles, in JAX.",
        epilog="'clebsch-jax COMMAND --help' describes each command.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {cj.__version__}")
    subparsers = parser.add_subparsers(title="commands", dest="command", metavar="COMMAND", required=True)
    _demo_command.add(subparsers)
    _run_command.add(subparsers)
    _bench_command.add(subparsers)
    _sweep.add(subparsers)
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
