import os

import jax

# float64 everywhere (the package also enables it on import); strict promotion is not
# turned on because user models legitimately mix Python floats with arrays.
jax.config.update("jax_enable_x64", True)

# The command line keeps compiled programs on disk by default; tests call it in-process and
# must neither write to the user's cache nor change JAX's global cache settings for the tests
# that follow (subprocesses inherit this too). tests/test_compilation_cache.py tests the cache.
os.environ["CLEBSCH_JAX_NO_CACHE"] = "1"
