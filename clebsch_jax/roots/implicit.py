"""Derivatives of a root by the implicit function theorem: every root finder of the engine is
wrapped here, so gradients with respect to what the residual closes over (initial data, model
parameters) never differentiate the iterations."""

from __future__ import annotations

import functools
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from ..core import linalg
from ..core.jit import in_undifferentiated, undifferentiated
from ..core.validation import is_traced

__all__ = ["implicit_root", "dense_tangent_solve", "undifferentiated", "in_undifferentiated"]


def dense_tangent_solve(g, y):
    """The tangent system g(x) = y with the dense Jacobian of the linear map g."""
    return linalg.solve(jax.jacfwd(g)(y), y)


def implicit_root(F: Callable, x0: jax.Array, loop: Callable, tangent_solve: Callable):
    r"""`loop(F, x0) -> (x, NewtonStats, extra)` with derivatives of the root x by the implicit
    function theorem: $F(x^*(c), c) = 0$ gives $\partial_x F\,\dot x = -\partial_c F\,\dot c$ for
    the values c that F closes over, solved by `tangent_solve(g, y)` (g the linear map
    $\partial_x F$ at the root). The iterations are never differentiated; `extra` (e.g. a
    carried matrix) and the statistics pass through without derivatives.

    The semantics of `jax.lax.custom_root`, as a `jax.custom_jvp` whose rule is traced only
    when a derivative is taken: `custom_root` traces the linearisation and the tangent solve
    with every solve, which made up a large share of the tracing of a march that is never
    differentiated. F and the loop are closure-converted (`_closure_convert`), so the values
    they close over pass the custom-derivative boundary as arguments.
    Returns `(x, NewtonStats, extra)`."""
    if in_undifferentiated():  # the caller's program is never differentiated (`undifferentiated`)
        return loop(F, x0)
    F_conv, F_consts = _closure_convert(F, x0)
    solve = lambda x, *consts: loop(lambda z: F_conv(z, *consts), x)
    solve_conv, loop_consts = _closure_convert(solve, x0, *F_consts)  # their tangents are not used
    return _root(F_conv, solve_conv, tangent_solve, x0, tuple(F_consts), tuple(loop_consts))


def _closure_convert(fun: Callable, *example_args):
    """(converted, hoisted): `fun` traced once at the example arguments' shapes, as a function
    `converted(*args, *hoisted)` of its arguments and of the tracers it closes over, which are
    hoisted. Unlike `jax.closure_convert`, which keeps non-differentiable tracers (integers,
    booleans) in the closure, every closed-over tracer is hoisted: a custom derivative's
    function must not close over another trace's values."""
    closed, out_shape = jax.make_jaxpr(fun, return_shape=True)(*example_args)
    out_tree = jax.tree_util.tree_structure(out_shape)
    is_tracer = [is_traced(c) for c in closed.consts]
    kept = [c for c, t in zip(closed.consts, is_tracer) if not t]
    hoisted = [c for c, t in zip(closed.consts, is_tracer) if t]
    n_args = len(example_args)

    def converted(*args_and_hoisted):
        args, given = args_and_hoisted[:n_args], iter(args_and_hoisted[n_args:])
        kept_iter = iter(kept)
        consts = [next(given) if t else next(kept_iter) for t in is_tracer]
        out = jax.core.eval_jaxpr(closed.jaxpr, consts, *jax.tree_util.tree_leaves(args))
        return jax.tree_util.tree_unflatten(out_tree, out)

    return converted, hoisted


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1, 2))
def _root(F_conv, solve_conv, tangent_solve, x0, F_consts, loop_consts):
    return solve_conv(x0, *F_consts, *loop_consts)


@_root.defjvp
def _root_jvp(F_conv, solve_conv, tangent_solve, primals, tangents):
    x0, F_consts, loop_consts = primals
    _, dF_consts, _ = tangents
    out = _root(F_conv, solve_conv, tangent_solve, x0, F_consts, loop_consts)
    x = out[0]
    _, rhs = jax.jvp(lambda c: F_conv(x, *c), (F_consts,), (dF_consts,))
    _, lin = jax.linearize(lambda z: F_conv(z, *F_consts), x)
    dx = -tangent_solve(lin, rhs)
    return out, (dx,) + tuple(jax.tree_util.tree_map(_zero_tangent, out[1:]))


def _zero_tangent(a):
    a = jnp.asarray(a)
    if jnp.issubdtype(a.dtype, jnp.inexact):
        return jnp.zeros_like(a)
    return np.zeros(a.shape, jax.dtypes.float0)
