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

from . import _linalg

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
    """Statistics of one solve: updates made (`iterations`), final residual max-norm, status,
    and the number of Jacobians formed (`jacobians`)."""

    iterations: jax.Array
    residual_norm: jax.Array
    status: jax.Array
    jacobians: jax.Array


MAX_CHORD_ITERATIONS = 8
"""Chord (simplified Newton) updates per Jacobian before the Jacobian is refreshed."""


def jacobian(F: Callable, z: jax.Array):
    """F(z) and its Jacobian by forward mode: one linearisation, its JVP batched over columns."""
    Fz, lin = jax.linearize(F, z)
    J = jax.vmap(lin, out_axes=-1)(jnp.eye(z.shape[0], dtype=z.dtype))
    return Fz, J


def _tolerance(z, rtol, atol):
    return atol + rtol * jnp.max(jnp.abs(z))


def _converged(eta, eta_prev, k, tol, z):
    """Whether the iterate after an update of size η is final.

    - the update is at round-off size, η ≤ 8ε·max(1, |z|): nothing left to gain;
    - the estimated remaining error is below tol: with θ = η/η_prev, θ/(1-θ)·η ≤ tol (with
      tol = 0, the default, this never triggers before round-off);
    - a first update below tol/100;
    - stagnation at the noise floor of an ill-conditioned system: the update stopped
      shrinking (θ ≥ 1/2) while already tiny (η ≤ 10⁴ε·max(1, |z|)); continuing would only
      report a false failure.
    """
    eps = jnp.finfo(z.dtype).eps
    scale = jnp.maximum(1.0, jnp.max(jnp.abs(z)))
    theta = jnp.where(k == 0, jnp.inf, eta / eta_prev)
    roundoff = eta <= 8.0 * eps * scale
    estimate = (theta < 1.0) & (theta * eta <= (1.0 - theta) * tol)
    stagnant = (k > 0) & (theta >= 0.5) & (eta <= 1e4 * eps * scale)
    return roundoff | estimate | (eta <= 0.01 * tol) | stagnant


def _dense_factor(F: Callable, z: jax.Array):
    """The exact Jacobian at z, factored: `(factor, singular)`."""
    _, J = jacobian(F, z)
    return _linalg.factor(J)


def _chord(F, z0, fac, rtol, atol, solve=_linalg.solve_factored, max_updates=MAX_CHORD_ITERATIONS):
    """Updates with one factored matrix until `_converged`, until they stop contracting
    (θ ≥ 1: time for a fresh matrix), an iterate is non-finite, or `max_updates`.
    Returns (z, updates, converged, nonfinite)."""

    def cond(state):
        k, _, _, stop, _, _ = state
        return (~stop) & (k < max_updates)

    def body(state):
        k, z, eta_prev, _, _, _ = state
        Fz = F(z)
        dz = solve(fac, Fz)
        z_new = z - dz
        eta = jnp.max(jnp.abs(dz))
        nonfinite = ~(jnp.all(jnp.isfinite(z_new)) & jnp.all(jnp.isfinite(Fz)))
        converged = ~nonfinite & _converged(eta, eta_prev, k, _tolerance(z_new, rtol, atol), z_new)
        stop = converged | nonfinite | ((k > 0) & (eta >= eta_prev))
        return k + 1, jnp.where(nonfinite, z, z_new), eta, stop, converged, nonfinite

    false = jnp.asarray(False)
    init = (jnp.asarray(0, jnp.int32), z0, jnp.asarray(jnp.inf, z0.dtype), false, false, false)
    k, z, _, _, converged, nonfinite = jax.lax.while_loop(cond, body, init)
    return z, k, converged, nonfinite


def _newton_loop(F: Callable, z0: jax.Array, rtol, atol, max_iterations: int, *, factorize=_dense_factor,
                 solve=_linalg.solve_factored, max_updates=MAX_CHORD_ITERATIONS):
    """Newton's method with the Jacobian refreshed only when chord updates stop contracting.

    Outer loop: form and factor the Jacobian (at most `max_iterations` times); inner loop:
    chord updates with it. With a good guess — a time march with extrapolated guesses — one
    Jacobian per solve suffices; a hard step gets fresh Jacobians, i.e. full Newton. The
    Jacobian appears once in the program, and under `vmap` the outer loop runs only as often
    as the slowest member needs.

    `factorize(F, z) -> (factor, singular)` and `solve(factor, r)` choose the matrix: the exact
    dense Jacobian by default; `clebsch_jax._block_newton` passes its block-diagonal one."""

    def cond(state):
        j, _, _, done, _ = state
        return (~done) & (j < max_iterations)

    def body(state):
        j, z, _, _, updates = state
        fac, singular = factorize(F, z)
        z1, k, converged, nonfinite = _chord(F, z, fac, rtol, atol, solve, max_updates)
        status = jnp.where(singular, Status.SINGULAR,
                           jnp.where(nonfinite, Status.NONFINITE, Status.SUCCESS)).astype(jnp.int32)
        done = converged | singular | nonfinite
        return j + 1, jnp.where(singular, z, z1), status, done, updates + jnp.where(singular, 0, k)

    init = (jnp.asarray(0, jnp.int32), z0, jnp.asarray(Status.SUCCESS, jnp.int32), jnp.asarray(False),
            jnp.asarray(0, jnp.int32))
    j, z, status, done, updates = jax.lax.while_loop(cond, body, init)
    status = jnp.where(done, status, Status.MAX_ITERATIONS)
    res_norm = jnp.max(jnp.abs(F(z)))
    status = jnp.where((status == Status.SUCCESS) & ~jnp.isfinite(res_norm), Status.NONFINITE, status)
    return z, NewtonStats(iterations=updates, residual_norm=res_norm, status=status.astype(jnp.int32),
                          jacobians=j)


def newton_solve(F: Callable, guess, *, rtol: float, atol: float, max_iterations: int):
    r"""Solve $F(z) = 0$ for a pytree $z$ by Newton's method with an exact (forward-mode) Jacobian.

    The Jacobian is formed at the initial guess and kept while the updates contract (chord,
    or simplified Newton, iterations), and refreshed when they stop contracting — one
    Jacobian per solve when the guess is good, full Newton on hard steps; `max_iterations`
    caps the number of Jacobians. It stops when the error left after an update, estimated from
    the contraction $\theta = \|\Delta z_k\|/\|\Delta z_{k-1}\|$ as $\theta\|\Delta z_k\|/(1-\theta)$,
    is below $\text{atol} + \text{rtol}\,\|z\|_\infty$, or when the update is at round-off (see
    `_converged`), or with status `SINGULAR` / `NONFINITE` / `MAX_ITERATIONS`. Variational
    integrators conserve momenta only as well as each step is solved, and errors of 1e-15 per
    step add up over 10⁴ steps, so the march's default is `rtol = atol = 0`: iterate to
    round-off.

    **Returns:** `(z, NewtonStats)`. On failure `z` is the last finite iterate.
    """
    flat0, unravel = ravel_pytree(guess)

    def F_flat(x):
        return ravel_pytree(F(unravel(x)))[0]

    def tangent_solve(g, y):
        return _linalg.solve(jax.jacfwd(g)(y), y)

    flat, stats = implicit_root(F_flat, flat0, lambda f, x0: _newton_loop(f, x0, rtol, atol, max_iterations),
                                tangent_solve)
    return unravel(flat), stats


def implicit_root(F: Callable, x0: jax.Array, loop: Callable, tangent_solve: Callable):
    """`jax.lax.custom_root` around `loop(F, x0) -> (x, NewtonStats)`: derivatives of the root by
    the implicit function theorem, with `tangent_solve` for the tangent systems."""

    def solve(f, x):
        x, stats = loop(f, x)
        # custom_root's JVP gives integer aux outputs integer (not float0) tangents, which
        # JAX then rejects; carry the statistics as floats through it and cast back below.
        return x, jax.tree_util.tree_map(lambda a: a.astype(x.dtype), stats)

    x, stats = jax.lax.custom_root(F, x0, solve, tangent_solve, has_aux=True)
    return x, NewtonStats(
        iterations=stats.iterations.astype(jnp.int32),
        residual_norm=stats.residual_norm,
        status=stats.status.astype(jnp.int32),
        jacobians=stats.jacobians.astype(jnp.int32),
    )
