r"""The reduced march (Theorem 27, Corollary 29): dim V unknowns per step instead of
dim V + 2 dim M. The state is the body momentum $\mu^n = -p^n\diamond Q^n$; Q is carried only
when l depends on it (Definition 14) or the caller asks for it, and updated explicitly,
$Q^{n+1} = Q^n\,\overline{\exp}(\Delta t X(\xi^n))$.

Each step is cheap because it is small: a few hundred flops for the rigid body, so the cost
is the number of operations XLA runs (each with a fixed cost on CPU) and the number of Newton
updates. Hence (measured in `benchmarks/README.md`):

- the residual and the outgoing momentum come from one evaluation (`reduced_step`), in closed
  form for the Cayley map;
- the guess is the last velocity plus a polynomial extrapolation, of degree up to
  `PREDICTOR_ORDER` (`_scan.predict`), of the increments this sub-step made in earlier steps;
- for the Cayley map (`_fresh_jacobians`) every solve forms the exact Jacobian at that guess,
  from the cheap closed-form residual: Newton converges quadratically from the good guess, so
  one update reaches round-off and a second confirms it (work-precision run: 2.0-4.4 updates
  per sub-step on average, 2.1-5.2 for the slowest member of a batch, against 3.9-7.8 and
  5.3-9.1 with a carried Jacobian);
- for other maps, whose residual goes through autodiff of exp̄ and loḡ and makes a Jacobian
  expensive, the inverse Jacobian is carried from step to step (`newton_solve_reusing`): formed
  at step 0 and again only when its chord updates stop contracting well (3-4 updates per step
  at Δt = 0.05).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from ._march_full import initial_multiplier
from ._newton import newton_solve, newton_solve_reusing
from ._reduction import MatrixGroupReduction, _is_cayley, reduced_step
from ._residual import nodal_residual
from ._scan import PREDICTOR_ORDER, assemble, march, predict, push, slots
from ._system import ClebschSystem, momentum_map

__all__ = ["march_reduced"]


def _fresh_jacobians(system: ClebschSystem) -> bool:
    """Whether every solve forms a fresh Jacobian instead of carrying one: for the Cayley map
    (closed-form residual, `_reduction._cayley_step`, so a Jacobian is dim V cheap JVPs).
    Measured (scratch, interleaved processes, 2 cores): batches through `cj.batch` or `vmap`
    1.2-1.8× faster (1000 bodies at order 2, Δt 0.05: 37 against 46 ms per 100 steps; 200
    bodies at order 8, Δt 0.25: 135-186 against 213-234 ms, under vmap 160 against 241-290 ms),
    since a batched loop pays its slowest member's updates; a single unbatched trajectory
    1.2-1.8× slower (order 2: 4.8-5.6 against 4.1-4.3 ms per 1000 steps), where the mean count
    matters and the Jacobian is the extra cost. Batches are what this library is for."""
    return _is_cayley(system.derivative_map)


def march_reduced(system: ClebschSystem, red: MatrixGroupReduction, Q0, xi0, P0, dt, t0, *, n_steps,
                  scheme, plan, rtol, atol, max_newton_iterations, P0_given, carry_Q, need_P):
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
    fresh = _fresh_jacobians(system)

    def substep(state, memory, h, scheme, n, alive):
        mu, Q, xi_last = state
        history, H = memory

        def residual(x):
            return reduced_step(system, red, scheme, h, mu, Q, x, outgoing=False)[0]

        def finish(x):  # the residual at the solution and the outgoing μⁿ⁺¹, Qⁿ⁺¹, sharing work
            r, mu1, Q1 = reduced_step(system, red, scheme, h, mu, Q, x)
            return r, (mu1, Q1)

        # Cayley: a fresh Jacobian at the guess (see `_fresh_jacobians`). Otherwise the inverse
        # Jacobian of this slot's last solve is reused (refreshed when it stops contracting,
        # formed at step 0); a member that has failed iterates on NaNs without forming any.
        guess = xi_last + predict(n, jnp.zeros_like(xi_last), history)
        reuse = False if fresh else (n > 0) | ~alive
        xi, stats, H, (mu1, Q1) = solve(residual, guess, H, reuse, finish=finish)
        return (mu1, Q1 if carry_Q else Q, xi), (push(history, xi - xi_last), H), (xi, Q1), stats

    history = jnp.zeros((PREDICTOR_ORDER + 1,) + xi0.shape, xi0.dtype)  # not used at step 0
    H = jnp.eye(xi0.size, dtype=xi0.dtype)  # not used at step 0
    (mus, Qs_after, _), (xis, Q_first), stats = march(substep, (mu0, Qc0, xi0), slots(plan, (history, H)),
                                                      plan, dt, n_steps)
    mus = jnp.concatenate([mu0[None], mus])
    if carry_Q:
        Qs = jnp.concatenate([Q0[None], Qs_after])
        nodal_Q = Qs
    else:
        Qs = None
        nodal_Q = jnp.broadcast_to(Qc0, (n_steps + 1,) + Qc0.shape)
    Ps = None
    if need_P:  # the multiplier of each step's first sub-step, at that sub-step's anchor
        anchors = Qs[:-1] if plan.substeps[0][0] == "left" else Q_first
        Ps = jax.vmap(lambda q, x: initial_multiplier(system, q, x))(anchors, xis)
    return assemble(system=system, dt=dt, t0=t0, Q0=Q0, xi0=xi0, stats=stats, xi_steps=xis, Qs=Qs,
                    ps=None, Ps=Ps, mus=mus, rtol=rtol, atol=atol, max_iterations=max_newton_iterations,
                    form="reduced", scheme=scheme, plan=plan, nodal_Q=nodal_Q)
