r"""The discrete Legendre side of a node (Lemma 7): from a velocity to the multiplier and back.

At a node, $\delta l/\delta\xi(\xi, Q) = -p\diamond Q = \mu$ ties the velocity ξ to the
canonical momentum p through the momentum map μ. These functions start a march (the initial
multiplier from $(Q^0, \xi^0)$), hand a reduced march's momentum back to a cotangent vector,
and recover nodal velocities."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..core.system import ClebschSystem, momentum_map
from ..roots.newton import newton_solve
from .residual import nodal_residual

__all__ = ["initial_multiplier", "cotangent_from_momentum", "nodal_velocity"]


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
                   rtol: float = 0.0, atol: float = 0.0, max_iterations: int = 20, solver=None):
    r"""Solve Lemma 7's $\delta l/\delta\xi(\xi, Q) = -p \diamond Q$ for $\xi$ by Newton
    (`solver`: `newton_solve`, or `block_newton_solve` for many particles).

    Returns `(xi, NewtonStats)`. Requires $l$ to be regular in $\xi$ (Lemma 8).
    """
    mu = momentum_map(system, p, Q, guess)
    solver = newton_solve if solver is None else solver
    return solver(lambda x: nodal_residual(system, Q, mu, x), guess,
                  rtol=rtol, atol=atol, max_iterations=max_iterations)
