"""What a command sets up before it integrates: its output folder, matplotlib, the persistent
compilation cache; and `fail`, the one-line error every command ends with."""

from __future__ import annotations

import os
import sys

import clebsch_jax as cj

from ._arguments import PROG


def fail(message: str, *, code: int = 1, prog: str = PROG) -> int:
    """Print `prog: error: message` on stderr; return the exit code."""
    print(f"{prog}: error: {message}", file=sys.stderr)
    return code


def check_out_dir(out_dir: str, prog: str) -> int | None:
    """Exit code 2 (one line) when `out_dir` exists and is not a folder, else None."""
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        return fail(f"--out: {out_dir!r} exists and is not a folder", code=2, prog=prog)
    return None


def make_out_dir(out_dir: str, prog: str) -> int | None:
    """Create `out_dir`; exit code 1 (one line) when that is impossible, else None."""
    try:
        os.makedirs(out_dir, exist_ok=True)
    except OSError as err:
        return fail(f"could not create {out_dir!r}: {err.strerror or err}", prog=prog)
    if not os.access(out_dir, os.W_OK):
        return fail(f"{out_dir!r} is not writable", prog=prog)
    return None


def require_matplotlib(prog: str) -> int | None:
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return fail(
            'the plots are drawn with matplotlib, which is not installed: pip install "clebsch-jax[plot]"', prog=prog
        )
    return None


def use_compilation_cache(args, prog: str) -> None:
    """The persistent compilation cache (`enable_compilation_cache`), unless `--no-cache` or the
    environment variable CLEBSCH_JAX_NO_CACHE is set; a cache that cannot be used is reported
    on stderr and the run goes on without it."""
    if args.no_cache or os.environ.get("CLEBSCH_JAX_NO_CACHE"):
        return
    try:
        cj.enable_compilation_cache()
    except (OSError, ValueError) as exc:
        print(f"{prog}: compiling without the cache: {exc}", file=sys.stderr)
