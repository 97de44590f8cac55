"""Derivatives of a root by the implicit function theorem (`jax.lax.custom_root`): every root
finder of the engine is wrapped here, so gradients with respect to what the residual closes
over (initial data, model parameters) never differentiate the iterations."""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp

from ..core import linalg
from .status import NewtonStats

__all__ = ["implicit_root", "dense_tangent_solve"]


def dense_tangent_solve(g, y):
    """The tangent system of `custom_root` with the dense Jacobian of g."""
    return linalg.solve(jax.jacfwd(g)(y), y)


def implicit_root(F: Callable, x0: jax.Array, loop: Callable, tangent_solve: Callable):
    """`jax.lax.custom_root` around `loop(F, x0) -> (x, NewtonStats, extra)`: derivatives of the
    root by the implicit function theorem, with `tangent_solve` for the tangent systems. `extra`
    (e.g. a carried inverse Jacobian; None if unused) passes through without derivatives.
    Returns `(x, NewtonStats, extra)`."""

    def solve(f, x):
        x, stats, extra = loop(f, x)
        # custom_root's JVP gives integer aux outputs integer (not float0) tangents, which
        # JAX then rejects; carry the statistics as floats through it and cast back below.
        return x, (jax.tree_util.tree_map(lambda a: a.astype(x.dtype), stats), extra)

    x, (stats, extra) = jax.lax.custom_root(F, x0, solve, tangent_solve, has_aux=True)
    return x, NewtonStats(
        iterations=stats.iterations.astype(jnp.int32),
        residual_norm=stats.residual_norm,
        status=stats.status.astype(jnp.int32),
        jacobians=stats.jacobians.astype(jnp.int32),
    ), extra
