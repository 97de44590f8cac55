"""`clebsch-jax bench [NAME ...]`: the scripts of the repository's `benchmarks/` folder, each in
a subprocess with this Python (`--quick` passed through)."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
import time
from pathlib import Path

import clebsch_jax as cj

from ._arguments import PROG
from ._setup import check_out_dir, fail, make_out_dir


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


def run(args) -> int:
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
        code = check_out_dir(out_dir, prog) or make_out_dir(out_dir, prog)
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


def add(subparsers) -> None:
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
    p.set_defaults(handler=run)
