r"""The reduced march (Theorem 27, Corollary 29): dim V unknowns per step instead of
dim V + 2 dim M. The state is the body momentum $\mu^n = -p^n\diamond Q^n$; Q is carried only
when l depends on it (Definition 14) or the caller asks for it, and updated explicitly,
$Q^{n+1} = Q^n\,\overline{\exp}(\Delta t X(\xi^n))$."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from ._march_full import initial_multiplier
from ._newton import newton_solve
from ._reduction import MatrixGroupReduction, outgoing_body_momentum, reduced_residual
from ._residual import nodal_residual
from ._scan import assemble, extrapolate, gate
from ._system import ClebschSystem, momentum_map

__all__ = ["march_reduced"]


def march_reduced(system: ClebschSystem, red: MatrixGroupReduction, Q0, xi0, P0, dt, t0, *, n_steps,
                  scheme, rtol, atol, max_newton_iterations, P0_given, order, carry_Q, need_P):
    newton = functools.partial(newton_solve, rtol=rtol, atol=atol, max_iterations=max_newton_iterations)
    if P0_given:
        mu0 = momentum_map(system, P0, Q0, xi0)
        # seed only; node 0 is solved and checked with the other nodes after the march
        xi0, _ = newton(lambda x: nodal_residual(system, Q0, mu0, x), xi0)
    else:
        mu0 = jax.grad(lambda x: system.l(x, Q0))(xi0)
    # Without a potential the reduced Lagrangian is left-invariant: evaluate at the identity.
    Qc0 = Q0 if carry_Q else jnp.eye(Q0.shape[0], dtype=Q0.dtype)

    def step(carry, _):
        mu, Q, xi_prev, xi_pp, n, alive = carry
        guess = extrapolate(n, xi0, xi_prev, xi_pp)
        xi, stats = newton(lambda x: reduced_residual(system, red, scheme, dt, mu, Q, x), guess)
        mu1, Q1 = outgoing_body_momentum(system, red, scheme, dt, Q, xi)
        ok, stats, (xi, mu1, Q1) = gate(alive, stats, (xi, mu1, Q1))
        Q_next = Q1 if carry_Q else Q
        return (mu1, Q_next, xi, xi_prev, n + 1, ok), (xi, mu1, Q1, stats)

    init = (mu0, Qc0, xi0, xi0, jnp.asarray(0, jnp.int32), jnp.asarray(True))
    _, (xis, mus, Q1s, stats) = jax.lax.scan(step, init, None, length=n_steps)
    mus = jnp.concatenate([mu0[None], mus])
    if carry_Q:
        Qs = jnp.concatenate([Q0[None], Q1s])
        nodal_Q = Qs
    else:
        Qs = None
        nodal_Q = jnp.broadcast_to(Qc0, (n_steps + 1,) + Qc0.shape)
    Ps = None
    if need_P:
        anchors = Qs[:-1] if scheme == "left" else Qs[1:]
        Ps = jax.vmap(lambda q, x: initial_multiplier(system, q, x))(anchors, xis)
    return assemble(system=system, dt=dt, t0=t0, Q0=Q0, xi0=xi0, stats=stats, xi_steps=xis, Qs=Qs,
                    ps=None, Ps=Ps, mus=mus, rtol=rtol, atol=atol, max_iterations=max_newton_iterations,
                    form="reduced", scheme=scheme, order=order, nodal_Q=nodal_Q)
