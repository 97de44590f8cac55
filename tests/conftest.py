import jax

# float64 everywhere (the package also enables it on import); strict promotion is not
# turned on because user models legitimately mix Python floats with arrays.
jax.config.update("jax_enable_x64", True)
