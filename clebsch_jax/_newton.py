"""Newton's method for the small dense systems of one step, with failure as a value.

One generic driver serves every residual (full march, nodal Legendre solve, later the reduced
march): the method supplies only the residual and the initial guess. Under `jax.vmap` the
`while_loop` runs until every batch member has stopped; each member keeps its own status.

The solve is wrapped in `jax.lax.custom_root`, so derivatives of the solution with respect to
anything the residual closes over (initial data, model parameters) come from the implicit
function theorem, never from differentiating the iterations.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

__all__ = ["NewtonStats", "Status", "newton_solve"]


class Status:
    """Per-step status codes carried through the march (failure is a value)."""

    SUCCESS = 0
    MAX_ITERATIONS = 1
    NONFINITE = 2
    SINGULAR = 3
    SKIPPED = 4  # not attempted: an earlier step of this batch member failed
    LEGENDRE = 5  # the nodal velocity could not be recovered from (Q, p)

    MESSAGES = {
        SUCCESS: "converged",
        MAX_ITERATIONS: "Newton's method reached the maximum number of iterations",
        NONFINITE: "the residual or the Newton iterate became non-finite (NaN/inf)",
        SINGULAR: "the Newton Jacobian is singular",
        SKIPPED: "not attempted because an earlier step failed",
        LEGENDRE: "the nodal velocity could not be recovered from (Q, p) by Lemma 7's "
        "relation dl/dxi(xi, Q) = -p<>Q",
    }


class NewtonStats(NamedTuple):
    """Statistics of one Newton solve: Jacobian evaluations, final residual max-norm, status."""

    iterations: jax.Array
    residual_norm: jax.Array
    status: jax.Array


def _newton_loop(F: Callable, z0: jax.Array, rtol, atol, max_iterations: int):
    n = z0.shape[0]
    eps = jnp.finfo(z0.dtype).eps

    def value_and_jac(z):
        Fz = F(z)
        return Fz, Fz

    jac = jax.jacfwd(value_and_jac, has_aux=True)

    def cond(state):
        k, _, status, done = state
        return (~done) & (k < max_iterations)

    def body(state):
        k, z, _, _ = state
        J, Fz = jac(z)
        lu, piv = jax.scipy.linalg.lu_factor(J)
        d = jnp.abs(jnp.diagonal(lu))
        singular = jnp.min(d) <= n * eps * jnp.max(d)
        dz = jax.scipy.linalg.lu_solve((lu, piv), Fz)
        z_new = z - dz
        nonfinite = ~(jnp.all(jnp.isfinite(z_new)) & jnp.all(jnp.isfinite(Fz)))
        small = jnp.max(jnp.abs(dz)) <= atol + rtol * jnp.max(jnp.abs(z_new))
        status = jnp.where(
            nonfinite,
            Status.NONFINITE,
            jnp.where(singular, Status.SINGULAR, Status.SUCCESS),
        )
        done = nonfinite | singular | small
        z_keep = jnp.where(nonfinite | singular, z, z_new)
        return k + 1, z_keep, status.astype(jnp.int32), done

    init = (jnp.asarray(0, jnp.int32), z0, jnp.asarray(Status.SUCCESS, jnp.int32), jnp.asarray(False))
    k, z, status, done = jax.lax.while_loop(cond, body, init)
    status = jnp.where(done, status, Status.MAX_ITERATIONS).astype(jnp.int32)
    res = F(z)
    res_norm = jnp.max(jnp.abs(res))
    status = jnp.where((status == Status.SUCCESS) & ~jnp.isfinite(res_norm), Status.NONFINITE, status)
    return z, NewtonStats(iterations=k, residual_norm=res_norm, status=status.astype(jnp.int32))


def newton_solve(F: Callable, guess, *, rtol: float, atol: float, max_iterations: int):
    r"""Solve $F(z) = 0$ for a pytree $z$ by Newton's method with an exact (forward-mode) Jacobian.

    Stops when the Newton update satisfies $\|\Delta z\|_\infty \le \text{atol} + \text{rtol}\,
    \|z\|_\infty$ (after that update the error is $O(\|\Delta z\|^2)$, round-off level for the
    default tolerances), or with status `SINGULAR` / `NONFINITE` / `MAX_ITERATIONS`.

    **Returns:** `(z, NewtonStats)`. On failure `z` is the last finite iterate.
    """
    flat0, unravel = ravel_pytree(guess)

    def F_flat(x):
        return ravel_pytree(F(unravel(x)))[0]

    def solve(f, x0):
        z, stats = _newton_loop(f, x0, rtol, atol, max_iterations)
        # custom_root's JVP gives integer aux outputs integer (not float0) tangents, which
        # JAX then rejects; carry the statistics as floats through it and cast back below.
        return z, jax.tree_util.tree_map(lambda a: a.astype(x0.dtype), stats)

    def tangent_solve(g, y):
        return jnp.linalg.solve(jax.jacfwd(g)(y), y)

    flat, stats = jax.lax.custom_root(F_flat, flat0, solve, tangent_solve, has_aux=True)
    stats = NewtonStats(
        iterations=stats.iterations.astype(jnp.int32),
        residual_norm=stats.residual_norm,
        status=stats.status.astype(jnp.int32),
    )
    return unravel(flat), stats
