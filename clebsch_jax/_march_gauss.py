r"""The Gauss–Legendre march (`scheme="gauss"`): the s-stage partitioned Runge–Kutta
discretisation of the Clebsch principle (`clebsch_jax._collocation`), order 2s, carrying the
canonical pair $(Q^n, P^n)$ in `jax.lax.scan`.

Each step finds its stage velocities and increments by the fixed-point iteration of
`gauss_sweep` (`fixed_point_solve`), to round-off by default, from the guess of the previous
step's collocation polynomials continued over one step (step 0: of `FIRST_STEP_SUBSTEPS`
solved substeps); the inverse Hessians of l in ξ that the sweeps use are formed once per step,
at that guess (for a degenerate l: the inverse of the constraint bracket matrix,
`degenerate_sweep`). A sweep evaluates the model's gradients once per stage and forms no
Jacobian. Measured on the rigid body in Clebsch variables
(`models.rigid_body_vector`), 4 stages, 200 bodies through `cj.batch`, scratch runs: 18-19
sweeps per step on average at Δt = 0.5, 12.6 at 0.25, 9.3 at 0.125; 1.7 µs per body-step at
Δt = 0.25 (2.2 µs before the first `UNTESTED_SWEEPS` sweeps went untested and a test became a
single reduction), where a step of the order-8 composition of Cayley steps costs ~9 µs (17
solves of ~0.53 µs) and is 120–135× less accurate (`benchmarks/work_precision.py`).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from ._collocation import (GaussUnknowns, constraint_matrix_inverse, degenerate_sweep, extrapolate, from_substeps,
                           gauss_legendre, gauss_sweep, gauss_update, stage_hessians)
from ._march_full import initial_multiplier, nodal_velocity
from ._newton import Status, fixed_point_solve
from ._scan import assemble, march
from ._system import ClebschSystem, momentum_map

__all__ = ["march_gauss", "SWEEPS_PER_NEWTON_ITERATION", "UNTESTED_SWEEPS", "FIRST_STEP_SUBSTEPS"]

UNTESTED_SWEEPS = 4
"""Sweeps of a step before its first convergence test. A test costs about as much as a sweep,
and every step measured needs more than 4 sweeps from its extrapolated guess (200 rigid bodies:
order 8 takes 8-14 sweeps at Δt = 0.0625-0.25, order 4 takes 6 at Δt = 0.01)."""

FIRST_STEP_SUBSTEPS = 4
"""The first step has no previous step to extrapolate: its guess comes from this many substeps
of a quarter of its size, each solved from the one before (the first from constant slopes).
From constant slopes alone the sweeps diverged on fast rigid bodies at Δt = 1.25 (order 16),
where every later step converges from its extrapolated guess."""

SWEEPS_PER_NEWTON_ITERATION = 5
"""`max_newton_iterations` read for sweeps: a step may take `SWEEPS_PER_NEWTON_ITERATION ×
max_newton_iterations` sweeps (100 by default), a sweep gaining about one digit where a Newton
update gains many."""


def march_gauss(system: ClebschSystem, Q0, xi0, P0, dt, t0, *, n_steps, scheme, plan, rtol, atol,
                max_newton_iterations, P0_given, jacobian="dense"):
    tab = gauss_legendre(plan.order // 2)
    if not P0_given:
        P0 = initial_multiplier(system, Q0, xi0)
    elif not system.degenerate:  # seeds the first step only; node 0 is solved and checked afterwards
        xi0, _ = nodal_velocity(system, Q0, P0, xi0, rtol=rtol, atol=atol, max_iterations=max_newton_iterations)
    solve = functools.partial(fixed_point_solve, rtol=rtol, atol=atol, untested=UNTESTED_SWEEPS,
                              max_iterations=SWEEPS_PER_NEWTON_ITERATION * max_newton_iterations)
    s = tab.stages

    def matrices(Q, P, z):  # formed once per step, at the guess
        if system.degenerate:
            return constraint_matrix_inverse(system, z.xi[0], Q, P, blocks=jacobian == "blocks")[0]
        return stage_hessians(system, tab, Q, P, z)

    def sweep(h, Q, P, z, matrices):
        if system.degenerate:
            return degenerate_sweep(system, tab, h, Q, P, z, matrices)
        return gauss_sweep(system, tab, h, Q, P, z, matrices)

    def solve_step(h, Q, P, guess):
        mats = matrices(Q, P, guess)
        # sizes are judged against the state the increments are added to, and ξ
        size = jnp.max(jnp.abs(jnp.concatenate([Q.ravel(), P.ravel(), guess.xi.ravel()])))
        return solve(lambda z: sweep(h, Q, P, z, mats), guess, size=size)

    def advance(h, state):  # one solved step: the next (Q, P, guess), its unknowns and statistics
        Q, P, guess = state
        z, stats = solve_step(h, Q, P, guess)
        Q1, P1 = gauss_update(Q, P, z)
        return (Q1, P1, extrapolate(tab, z)), z, stats

    def substep(state, memory, h, scheme, n, alive):
        state, z, stats = advance(h, state)
        xi_mean = jnp.tensordot(jnp.asarray(tab.b, z.xi.dtype), z.xi, axes=1)
        return state, memory, xi_mean, stats

    # Step 0's guess: FIRST_STEP_SUBSTEPS solved substeps, the first from constant slopes (one
    # sweep from zero increments at the initial velocity); if one fails, constant slopes, and
    # step 0 reports what its own solve meets.
    zero = jnp.zeros((s,) + Q0.shape, Q0.dtype)
    still = GaussUnknowns(jnp.broadcast_to(xi0, (s,) + xi0.shape), zero, zero)
    h_sub, m0 = dt / FIRST_STEP_SUBSTEPS, matrices(Q0, P0, still)
    crude = sweep(h_sub, Q0, P0, still, m0)

    def first_substep(state, _):
        state, z, st = advance(h_sub, state)
        return state, (z, st.status, st.iterations)

    _, (zs, status, sub_sweeps) = jax.lax.scan(first_substep, (Q0, P0, crude), None, length=FIRST_STEP_SUBSTEPS)
    ok = jnp.all(status == Status.SUCCESS)
    guess0 = jax.tree_util.tree_map(lambda a, b: jnp.where(ok, a, b), from_substeps(tab, zs),
                                    sweep(dt, Q0, P0, still, m0))
    (Qs, Ps, _), xis, stats = march(substep, (Q0, P0, guess0), None, plan, dt, n_steps)
    # the substeps' sweeps are step 0's work too
    stats = stats._replace(iterations=stats.iterations.at[0].add(jnp.sum(sub_sweeps).astype(stats.iterations.dtype)))
    Qs = jnp.concatenate([Q0[None], Qs])
    pn = jnp.concatenate([P0[None], Ps])
    mus = jax.vmap(lambda q, p: momentum_map(system, p, q, xi0))(Qs, pn)
    return assemble(system=system, dt=dt, t0=t0, Q0=Q0, xi0=xi0, stats=stats, xi_steps=xis,
                    Qs=Qs, ps=pn, Ps=pn[:-1], mus=mus, rtol=rtol, atol=atol,
                    max_iterations=max_newton_iterations, form="full", scheme=scheme, plan=plan, nodal_Q=Qs)
