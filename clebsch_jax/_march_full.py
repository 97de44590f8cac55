r"""The full march: every step solves Lemma 20 for $(\xi^n, P^n, Q^{n+1})$ (dim V + 2 dim M
unknowns) and carries the symplectic state $(Q^n, p^n)$."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

from ._block_newton import block_newton_solve, block_newton_solve_reusing, identity_blocks
from ._newton import newton_solve
from ._residual import StepUnknowns, nodal_residual, outgoing_momentum, step_residual
from ._scan import PREDICTOR_ORDER, assemble, march, predict, push, slots
from ._system import ClebschSystem, momentum_map

__all__ = ["initial_multiplier", "cotangent_from_momentum", "nodal_velocity", "march_full"]


def initial_multiplier(system: ClebschSystem, Q0: jax.Array, xi0: jax.Array) -> jax.Array:
    r"""The minimum-norm $P^0$ with $\delta l/\delta\xi(\xi^0, Q^0) = -P^0 \diamond Q^0$ (Lemma 7).

    With $A = \partial_\xi \mathcal L_\xi Q^0$ (a matrix from $V$ to $T_{Q^0}M$, by forward-mode
    autodiff) the condition is $A^T P^0 = \delta l/\delta \xi$; among its solutions we take the
    one of least Euclidean norm, $P^0 = (A^T)^+ \,\delta l/\delta\xi$. Components of $P^0$
    that the velocity map cannot see (e.g. the symmetric part of $Q^T P$ on $SO(3)$) are zero.
    """
    return cotangent_from_momentum(system, Q0, jax.grad(lambda x: system.l(x, Q0))(xi0))


_DENSE_MAX = 256
"""Above this many components of V the minimum-norm cotangent is found matrix-free."""


def cotangent_from_momentum(system: ClebschSystem, Q: jax.Array, mu: jax.Array) -> jax.Array:
    r"""The minimum-norm $p \in T^*_QM$ with momentum map $-p\diamond Q = \mu$.

    Solves $A^T p = \mu$, $A = \partial_\xi \mathcal L_\xi Q$, by least squares (`mu` has ξ's
    shape). Used for the initial multiplier and to rebuild momenta from a reduced march. For
    large V (more than `_DENSE_MAX` components, e.g. many particles) $A$ is never formed: the
    minimum-norm solution $p = A y$, $A^TA\,y = \mu$, is found by conjugate gradients with
    products by $A$ and $A^T$ (one iteration when the velocity map is a translation).
    """
    lin = lambda x: system.velocity_map(x.reshape(mu.shape), Q)
    if mu.size <= _DENSE_MAX:
        A = jax.jacfwd(lambda x: lin(x).ravel())(jnp.zeros(mu.size, Q.dtype))
        return jnp.linalg.lstsq(A.T, mu.ravel())[0].reshape(Q.shape)
    _, vjp = jax.vjp(lin, jnp.zeros_like(mu))
    y, _ = jax.scipy.sparse.linalg.cg(lambda v: vjp(lin(v))[0], mu, tol=1e-15, atol=0.0, maxiter=200)
    return lin(y)



def nodal_velocity(system: ClebschSystem, Q: jax.Array, p: jax.Array, guess: jax.Array, *,
                   rtol: float = 0.0, atol: float = 0.0, max_iterations: int = 20, solver=newton_solve):
    r"""Solve Lemma 7's $\delta l/\delta\xi(\xi, Q) = -p \diamond Q$ for $\xi$ by Newton
    (`solver`: `newton_solve`, or `block_newton_solve` for many particles).

    Returns `(xi, NewtonStats)`. Requires $l$ to be regular in $\xi$ (Lemma 8).
    """
    mu = momentum_map(system, p, Q, guess)
    return solver(lambda x: nodal_residual(system, Q, mu, x), guess,
                  rtol=rtol, atol=atol, max_iterations=max_iterations)


SOLVERS = {"dense": newton_solve, "blocks": block_newton_solve}


def march_full(system, Q0, xi0, P0, dt, t0, *, n_steps, scheme, plan, rtol, atol, max_newton_iterations,
               P0_given, jacobian="dense"):
    solver = SOLVERS[jacobian]
    newton = functools.partial(solver, rtol=rtol, atol=atol, max_iterations=max_newton_iterations)
    if not P0_given:
        P0 = initial_multiplier(system, Q0, xi0)
    elif not system.degenerate:
        # Seeds the first step's guess only; node 0's nodal velocity is solved (and its
        # status checked and reported) with all the other nodes after the march.
        xi0, _ = nodal_velocity(system, Q0, P0, xi0, rtol=rtol, atol=atol,
                                max_iterations=max_newton_iterations, solver=solver)
    _, unravel = ravel_pytree(StepUnknowns(xi0, P0, Q0))

    reuse_blocks = jacobian == "blocks"

    def substep(state, memory, h, scheme, n, alive):
        Q, p, xi_last = state
        history, H = memory  # H: the carried inverse blocks (None with the dense Jacobian)
        # The guess is (ξ, P, Q¹) = (ξ_last, p, Q) + the predicted increment: at step 0 the
        # explicit (0, 0, h L_ξ Q), later the extrapolation of this sub-step's past increments.
        base = ravel_pytree(StepUnknowns(xi_last, p, Q))[0]
        first = ravel_pytree(StepUnknowns(jnp.zeros_like(xi_last), jnp.zeros_like(p),
                                          h * system.velocity_map(xi_last, Q)))[0]
        residual = lambda z: step_residual(system, scheme, h, Q, p, z)
        guess = unravel(base + predict(n, first, history))
        if reuse_blocks:  # the inverse lumped blocks of this slot's last solve are carried on
            z, stats, H = block_newton_solve_reusing(residual, guess, H, (n > 0) | ~alive, rtol=rtol, atol=atol,
                                                     max_iterations=max_newton_iterations)
        else:
            z, stats = newton(residual, guess)
        p1 = outgoing_momentum(system, scheme, h, Q, z)
        history = push(history, ravel_pytree(z)[0] - base)
        return (z.Q1, p1, z.xi), (history, H), (z.xi, z.P), stats

    history = jnp.zeros((PREDICTOR_ORDER + 1, 2 * Q0.size + xi0.size), Q0.dtype)  # not used at step 0
    memory = (history, identity_blocks(StepUnknowns(xi0, P0, Q0)) if reuse_blocks else None)
    (Qs, ps, _), (xis, Ps), stats = march(substep, (Q0, P0, xi0), slots(plan, memory), plan, dt, n_steps)

    Qs = jnp.concatenate([Q0[None], Qs])
    pn = jnp.concatenate([P0[None], ps])
    mus = jax.vmap(lambda q, p: momentum_map(system, p, q, xi0))(Qs, pn)
    return assemble(system=system, dt=dt, t0=t0, Q0=Q0, xi0=xi0, stats=stats, xi_steps=xis,
                    Qs=Qs, ps=pn, Ps=Ps, mus=mus, rtol=rtol, atol=atol,
                    max_iterations=max_newton_iterations, form="full", scheme=scheme, plan=plan,
                    nodal_Q=Qs, solver=solver)
