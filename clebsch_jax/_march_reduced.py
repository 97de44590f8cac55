r"""The reduced march (Theorem 27, Corollary 29): dim V unknowns per step instead of
dim V + 2 dim M. The state is the body momentum $\mu^n = -p^n\diamond Q^n$; Q is carried only
when l depends on it (Definition 14) or the caller asks for it, and updated explicitly,
$Q^{n+1} = Q^n\,\overline{\exp}(\Delta t X(\xi^n))$.

Each step is cheap because it is small: a few hundred flops for the rigid body, so the cost
is the number of operations XLA runs (each with a fixed cost on CPU) and the number of Newton
updates. Hence (measured in `benchmarks/README.md`):

- the residual and the outgoing momentum come from one evaluation (`reduced_step`), in closed
  form for the Cayley map;
- the inverse Jacobian is carried from step to step (`newton_solve_reusing`): formed at step 0
  and again only when its chord updates stop contracting well;
- the guess is a polynomial extrapolation of up to `PREDICTOR_ORDER` degree (`predict`), so
  3-4 updates reach round-off.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from ._march_full import initial_multiplier
from ._newton import max_abs, newton_solve, newton_solve_reusing
from ._reduction import MatrixGroupReduction, reduced_step
from ._residual import nodal_residual
from ._scan import assemble, gate
from ._system import ClebschSystem, momentum_map

__all__ = ["march_reduced"]

PREDICTOR_ORDER = 5
"""Highest degree of the polynomial through the last step velocities that predicts the next
one (`predict`)."""


def predict(n, xi0, history):
    """Initial guess of step n's velocity: ξ⁰ (the initial nodal velocity) at n = 0, then the
    polynomial extrapolation of the last step velocities `history` (newest first) in Newton's
    backward-difference form ξⁿ ≈ Σⱼ ∇ʲξⁿ⁻¹, j = 0 … p.

    The degree p is at most min(n − 1, PREDICTOR_ORDER) (the differences the steps made so far
    support) and, beyond 1, a difference is used only while the differences decrease by at
    least half each (max-norm): over a smooth, well-resolved trajectory the predictor is then
    of high order (error O(Δtᵖ⁺¹): 4e-9 against 5e-4 for a linear predictor on the
    benchmark's rigid body at Δt = 0.05, which saves Newton updates), while an under-resolved
    or rough one (where high-degree extrapolation amplifies) falls back to low degree."""
    p = history.shape[0] - 1
    H = history.reshape(p + 1, -1)
    # rows of D: the backward differences ∇ʲξⁿ⁻¹ = Σᵢ (-1)ⁱ C(j, i) ξⁿ⁻¹⁻ⁱ, j = 0 … p, and their sizes,
    # each computed in one piece (elementwise, which XLA fuses into one operation)
    C = np.array([[(-1) ** i * math.comb(j, i) for i in range(p + 1)] for j in range(p + 1)], dtype=float)
    D = functools.reduce(jnp.add, [jnp.asarray(C[:, i:i + 1], H.dtype) * H[i] for i in range(p + 1)])
    size = max_abs(D)
    total, keep = D[0], jnp.asarray(True)
    for j in range(1, p + 1):
        if j >= 2:
            keep = keep & (size[j] <= 0.5 * size[j - 1])
        keep = keep & (n > j)
        total = total + jnp.where(keep, D[j], 0.0)
    return jnp.where(n == 0, xi0, total.reshape(xi0.shape))


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
    solve = functools.partial(newton_solve_reusing, rtol=rtol, atol=atol, max_iterations=max_newton_iterations)

    def step(carry, _):
        mu, Q, history, H, n, alive = carry

        def residual(x):
            return reduced_step(system, red, scheme, dt, mu, Q, x, outgoing=False)[0]

        def finish(x):  # the residual at the solution and the outgoing μⁿ⁺¹, Qⁿ⁺¹, sharing work
            r, mu1, Q1 = reduced_step(system, red, scheme, dt, mu, Q, x)
            return r, (mu1, Q1)

        # The inverse Jacobian of the last solve is reused (refreshed when it stops contracting,
        # formed at step 0); a member that has failed iterates on NaNs without forming any.
        xi, stats, H, (mu1, Q1) = solve(residual, predict(n, xi0, history), H, (n > 0) | ~alive, finish=finish)
        ok, stats, (xi, mu1, Q1) = gate(alive, stats, (xi, mu1, Q1))
        Q_next = Q1 if carry_Q else Q
        history = jnp.concatenate([xi[None], history[:-1]])
        return (mu1, Q_next, history, H, n + 1, ok), (xi, mu1, Q1, stats)

    history = jnp.broadcast_to(xi0, (PREDICTOR_ORDER + 1,) + xi0.shape)
    H = jnp.eye(xi0.size, dtype=xi0.dtype)  # not used at step 0
    init = (mu0, Qc0, history, H, jnp.asarray(0, jnp.int32), jnp.asarray(True))
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
