"""Compiled programs kept on disk, so that a new Python process does not compile them again.

Most of the first call of `integrate` is XLA compiling the march; once the compiled program
is on disk, only tracing and lowering remain (the compile times per model, cold and from the
cache, are measured by `benchmarks/throughput.py`). Notebook kernels restart and the command
line starts a new process every time, so both pay the compilation again and again. JAX's
persistent compilation cache removes it; this module only chooses a directory for it and
switches it on.
"""

from __future__ import annotations

import os
import pathlib

import jax

__all__ = ["enable_compilation_cache", "default_cache_directory"]

ENVIRONMENT_VARIABLE = "CLEBSCH_JAX_CACHE_DIR"


def default_cache_directory() -> pathlib.Path:
    """`$CLEBSCH_JAX_CACHE_DIR` if set, else `$XDG_CACHE_HOME/clebsch-jax/xla` (XDG_CACHE_HOME
    defaulting to `~/.cache`)."""
    explicit = os.environ.get(ENVIRONMENT_VARIABLE)
    if explicit:
        return pathlib.Path(explicit).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or pathlib.Path.home() / ".cache"
    return pathlib.Path(base).expanduser() / "clebsch-jax" / "xla"


def enable_compilation_cache(
    directory: str | os.PathLike | None = None, *, min_compile_time: float = 0.0
) -> pathlib.Path:
    """Switch on JAX's persistent compilation cache in `directory` (created if missing).

    After this call every program JAX compiles in this process — `integrate`, `sweep`,
    `control` and the user's own `jax.jit` functions — is written to `directory`, and a later
    process that enables the same directory loads it instead of compiling. Tracing still
    happens each time (most of what remains of a first call). The cache key is JAX's: the
    program, the JAX/jaxlib version, the XLA flags and the device, so a stale entry is never
    used for a changed program.

    This sets JAX's global options `jax_compilation_cache_dir` and
    `jax_persistent_cache_min_compile_time_secs`, which affect the whole process (JAX has no
    per-library cache). The command line (`clebsch-jax run`, `demo`) calls it unless given
    `--no-cache`.

    **Arguments:**

    - `directory`: where to keep the programs. Default: `default_cache_directory()`.
    - `min_compile_time`: only programs that took at least this many seconds to compile are
      written (JAX's default is 1 s; 0 keeps the engine's small helper programs as well).

    **Returns:** the directory, as an absolute path.

    **Raises:** `TypeError` for a `directory` that is not a path; `ValueError` for a negative or
    non-finite `min_compile_time`, or a `directory` that exists but is not a writable directory.
    """
    if directory is None:
        directory = default_cache_directory()
    if not isinstance(directory, (str, os.PathLike)):
        raise TypeError(
            f"enable_compilation_cache: `directory` must be a path (str or os.PathLike), got {type(directory).__name__}"
        )
    if isinstance(min_compile_time, bool) or not isinstance(min_compile_time, (int, float)):
        raise TypeError(
            f"enable_compilation_cache: `min_compile_time` must be a number of seconds, "
            f"got {type(min_compile_time).__name__}"
        )
    if not (0.0 <= float(min_compile_time) < float("inf")):
        raise ValueError(
            f"enable_compilation_cache: `min_compile_time` must be finite and >= 0, got {min_compile_time}"
        )
    path = pathlib.Path(directory).expanduser().resolve()
    if path.exists() and not path.is_dir():
        raise ValueError(f"enable_compilation_cache: `directory` {str(path)!r} exists and is not a directory")
    path.mkdir(parents=True, exist_ok=True)
    if not os.access(path, os.W_OK | os.X_OK):
        raise ValueError(f"enable_compilation_cache: `directory` {str(path)!r} is not writable")
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_time))
    return path
