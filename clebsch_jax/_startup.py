"""Ctrl-C while the `clebsch-jax` command line starts: a clean exit, not a lost interrupt.

Importing JAX takes a while; a KeyboardInterrupt raised inside it lands in an extension's
initialisation (a crash or a traceback) or in a callback whose exceptions Python ignores (a
garbage-collector callback of jaxlib's), where it is lost and the command runs on. So when this
process is the command line (`clebsch-jax ...`, `python -m clebsch_jax ...`,
`python -m clebsch_jax.cli ...`), the package, as its first action, makes SIGINT print one line
and exit with status 130 at once; `clebsch_jax.cli.main` gives SIGINT back to Python
(`KeyboardInterrupt`, which it handles) once the command itself starts. An interrupt that a
callback would swallow later on also exits with 130 (`sys.unraisablehook`). Importing the package
as a library changes nothing.
"""

from __future__ import annotations

import os
import signal
import sys

PROG = "clebsch-jax"
INTERRUPTED = 130


_WITH_VALUE = ("-W", "-X", "--check-hash-based-pycs")
"""Interpreter options followed by a value."""


def _is_cli(argv: list[str] | None = None) -> bool:
    """Whether this process runs the command line, read from the interpreter's own arguments
    (`sys.orig_argv`): its options, then `-m MODULE`, `-c CODE` or a script (the `clebsch-jax`
    script), after which come the program's own arguments."""
    args = iter((list(sys.orig_argv) if argv is None else argv)[1:])
    for arg in args:
        if arg == "-m":
            return next(args, None) in ("clebsch_jax", "clebsch_jax.cli")
        if arg == "-c" or arg == "-":
            return False
        if arg in _WITH_VALUE:
            next(args, None)
        elif not arg.startswith("-"):
            return os.path.splitext(os.path.basename(arg))[0] == PROG
    return False


def _exit_interrupted(*_) -> None:
    try:
        os.write(2, f"{PROG}: interrupted\n".encode())
    finally:
        os._exit(INTERRUPTED)


def _hook(previous):
    def hook(unraisable):
        if isinstance(unraisable.exc_value, KeyboardInterrupt):  # a Ctrl-C a callback would swallow
            _exit_interrupted()
        previous(unraisable)

    return hook


def guard_startup() -> None:
    """In a command-line process: SIGINT exits at once with one line and 130 until
    `release_startup`, and an interrupt a callback would swallow exits likewise."""
    if not _is_cli():
        return
    signal.signal(signal.SIGINT, _exit_interrupted)
    sys.unraisablehook = _hook(sys.unraisablehook)


def release_startup() -> None:
    """SIGINT raises `KeyboardInterrupt` again (the command's own handling), if `guard_startup`
    had taken it."""
    if signal.getsignal(signal.SIGINT) is _exit_interrupted:
        signal.signal(signal.SIGINT, signal.default_int_handler)
