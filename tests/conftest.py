import atexit
import gc
import os
import shutil
import tempfile

import jax
import pytest

# float64 everywhere (the package also enables it on import); strict promotion is not
# turned on because user models legitimately mix Python floats with arrays.
jax.config.update("jax_enable_x64", True)

# The command line keeps compiled programs on disk by default; tests call it in-process and
# must neither write to the user's cache nor change JAX's global cache settings for the tests
# that follow (subprocesses inherit this too). tests/test_compilation_cache.py tests the cache.
os.environ["CLEBSCH_JAX_NO_CACHE"] = "1"

# No persistent compilation cache: nothing is serialised, and each worker keeps JAX's
# in-memory caches. (With a shared one, a slow-run worker was aborted inside XLA's serialiser,
# and without it inside XLA's compiler: both after thousands of compiled programs, whose memory
# mappings grow towards Linux's limit per process; `_release_compiled_programs` below.)
# `--max-worker-restart=0` (pyproject.toml) makes a crashed worker fail the run at once: a
# replaced worker had left pytest-xdist waiting until CI's time limit.

# Native kernels (clebsch_jax.native) are kept on disk: in a directory of this run, shared
# by the workers, never the user's cache.
_NATIVE_VARIABLE = "CLEBSCH_JAX_NATIVE_CACHE"
if not os.environ.get("CLEBSCH_JAX_TEST_RUN_NATIVE_CACHE"):
    os.environ["CLEBSCH_JAX_TEST_RUN_NATIVE_CACHE"] = tempfile.mkdtemp(prefix="clebsch-jax-test-native-")
    atexit.register(shutil.rmtree, os.environ["CLEBSCH_JAX_TEST_RUN_NATIVE_CACHE"], ignore_errors=True)
os.environ[_NATIVE_VARIABLE] = os.environ["CLEBSCH_JAX_TEST_RUN_NATIVE_CACHE"]


MAPPINGS_BEFORE_CLEARING = 20_000
"""`_release_compiled_programs` clears JAX's caches after a test once the process holds more
memory mappings than this (Linux's default limit per process is 65 530)."""


def _mappings() -> int:
    try:
        with open("/proc/self/maps") as f:
            return sum(1 for _ in f)
    except OSError:  # not Linux: no count, and no such limit to guard
        return 0


@pytest.fixture(autouse=True)
def _release_compiled_programs():
    """JAX's caches are cleared after a test once the worker holds many memory mappings: every
    compiled XLA program keeps a few mappings of its code for as long as it is cached, and a
    worker that compiled the thousands of programs of the slow run passed Linux's limit of
    65 530 mappings per process (`vm.max_map_count`), where XLA's compiler then aborted or
    crashed. Clearing only past a threshold keeps the programs that tests share while few."""
    yield
    if _mappings() > MAPPINGS_BEFORE_CLEARING:
        jax.clear_caches()
        gc.collect()
