"""`filter_jit`: `jax.jit` with every array leaf of the arguments traced and every other leaf
(user functions, steppers, options) static, so that user closures can be passed."""

from __future__ import annotations

import functools

import jax

from .validation import is_array

__all__ = ["filter_jit", "ONCE_PER_CALL"]

ONCE_PER_CALL = {"xla_backend_optimization_level": 0}
"""XLA options for small programs that run once per call (the model checks, the closure
test): compiled without LLVM's optimisations, which cost more compile time than they could
ever save at run time there."""


class _Dynamic:
    def __repr__(self):
        return "<dynamic>"


_DYNAMIC = _Dynamic()


def filter_jit(fun, compiler_options: dict | None = None):
    """`fun` compiled with its array leaves traced and its other leaves static (hashed); one
    program per distinct static part and array shapes (`compiler_options`: XLA's, as for
    `jax.jit`)."""

    @functools.partial(jax.jit, static_argnums=(0, 1), compiler_options=compiler_options)
    def jitted(treedef, static, dynamic):
        leaves = [d if s is _DYNAMIC else s for s, d in zip(static, dynamic)]
        args, kwargs = jax.tree_util.tree_unflatten(treedef, leaves)
        return fun(*args, **kwargs)

    @functools.wraps(fun)
    def wrapper(*args, **kwargs):
        leaves, treedef = jax.tree_util.tree_flatten((args, kwargs))
        static = tuple(_DYNAMIC if is_array(x) else x for x in leaves)
        dynamic = [x if is_array(x) else None for x in leaves]
        return jitted(treedef, static, dynamic)

    return wrapper
