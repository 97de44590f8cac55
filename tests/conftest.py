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

# One persistent compilation cache for the whole test run, in a temporary directory: tests build
# equal programs from different Python objects (the same model built again, the same lambda in
# two tests), which JAX's in-memory cache cannot see but its persistent cache (keyed on the
# program) can, and pytest-xdist's workers share it. The process that creates the directory
# removes it at exit; workers find it through the environment. Only this run's programs are
# in it, so every run starts cold, as CI does. JAX ignores the variable name used here, so
# subprocesses (tests/test_compilation_cache.py) are not affected.
_CACHE_VARIABLE = "CLEBSCH_JAX_TEST_RUN_XLA_CACHE"
if not os.environ.get(_CACHE_VARIABLE):
    os.environ[_CACHE_VARIABLE] = tempfile.mkdtemp(prefix="clebsch-jax-test-xla-")
    atexit.register(shutil.rmtree, os.environ[_CACHE_VARIABLE], ignore_errors=True)
jax.config.update("jax_compilation_cache_dir", os.environ[_CACHE_VARIABLE])

# Native kernels (clebsch_jax.native) are kept on disk too: in a directory of this run, shared
# by the workers, never the user's cache.
_NATIVE_VARIABLE = "CLEBSCH_JAX_NATIVE_CACHE"
if not os.environ.get("CLEBSCH_JAX_TEST_RUN_NATIVE_CACHE"):
    os.environ["CLEBSCH_JAX_TEST_RUN_NATIVE_CACHE"] = tempfile.mkdtemp(prefix="clebsch-jax-test-native-")
    atexit.register(shutil.rmtree, os.environ["CLEBSCH_JAX_TEST_RUN_NATIVE_CACHE"], ignore_errors=True)
os.environ[_NATIVE_VARIABLE] = os.environ["CLEBSCH_JAX_TEST_RUN_NATIVE_CACHE"]
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
