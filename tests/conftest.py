import atexit
import os
import shutil
import tempfile

import jax

# float64 everywhere (the package also enables it on import); strict promotion is not
# turned on because user models legitimately mix Python floats with arrays.
jax.config.update("jax_enable_x64", True)

# The command line keeps compiled programs on disk by default; tests call it in-process and
# must neither write to the user's cache nor change JAX's global cache settings for the tests
# that follow (subprocesses inherit this too). tests/test_compilation_cache.py tests the cache.
os.environ["CLEBSCH_JAX_NO_CACHE"] = "1"

# No persistent compilation cache: with two pytest-xdist workers sharing one, XLA aborted a
# worker (SIGABRT inside `executable.serialize()`, writing a cache entry) in the slow run, and
# the run then hung until CI's time limit; it did not happen with one worker. Each worker
# keeps JAX's in-memory caches; `--max-worker-restart=0` (pyproject.toml) makes any crashed
# worker fail the run at once rather than hang it.

# Native kernels (clebsch_jax.native) are kept on disk too: in a directory of this run, shared
# by the workers, never the user's cache.
_NATIVE_VARIABLE = "CLEBSCH_JAX_NATIVE_CACHE"
if not os.environ.get("CLEBSCH_JAX_TEST_RUN_NATIVE_CACHE"):
    os.environ["CLEBSCH_JAX_TEST_RUN_NATIVE_CACHE"] = tempfile.mkdtemp(prefix="clebsch-jax-test-native-")
    atexit.register(shutil.rmtree, os.environ["CLEBSCH_JAX_TEST_RUN_NATIVE_CACHE"], ignore_errors=True)
os.environ[_NATIVE_VARIABLE] = os.environ["CLEBSCH_JAX_TEST_RUN_NATIVE_CACHE"]
