"""Pieces shared by every march inside `jax.lax.scan`: initial guesses, failure gating, nodal
velocities and the assembly of the `Solution`."""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from ._newton import NewtonStats, Status, max_abs, newton_solve
from ._residual import nodal_residual
from ._solution import Solution
from ._system import ClebschSystem

__all__ = ["predict", "push", "march", "slots", "combine_stats", "gate", "nodal_velocities", "assemble"]


PREDICTOR_ORDER = 5
"""Highest degree of the polynomial through the last solutions that predicts the next one
(`predict`)."""


def predict(n, first, history):
    """Initial guess of step n's unknowns: `first` at n = 0, then the polynomial extrapolation
    of the solutions of the last steps, `history` (newest first, leading axis p + 1), in
    Newton's backward-difference form zⁿ ≈ Σⱼ ∇ʲzⁿ⁻¹, j = 0 … p.

    The degree p is at most min(n − 1, PREDICTOR_ORDER) (the differences the steps made so far
    support) and, beyond 1, a difference is used only while the differences decrease by at
    least half each (max-norm): over a smooth, well-resolved trajectory the predictor is then
    of high order (error O(Δtᵖ⁺¹): 4e-9 against 5e-4 for a linear predictor on the
    benchmark's rigid body at Δt = 0.05, which saves Newton updates), while an under-resolved
    or rough one (where high-degree extrapolation amplifies) falls back to low degree."""
    p = history.shape[0] - 1
    H = history.reshape(p + 1, -1)
    # rows of D: the backward differences ∇ʲzⁿ⁻¹ = Σᵢ (-1)ⁱ C(j, i) zⁿ⁻¹⁻ⁱ, j = 0 … p, and their
    # sizes, each computed in one piece (elementwise, which XLA fuses into one operation)
    C = np.array([[(-1) ** i * math.comb(j, i) for i in range(p + 1)] for j in range(p + 1)], dtype=float)
    D = functools.reduce(jnp.add, [jnp.asarray(C[:, i:i + 1], H.dtype) * H[i] for i in range(p + 1)])
    size = max_abs(D)
    total, keep = D[0], jnp.asarray(True)
    for j in range(1, p + 1):
        if j >= 2:
            keep = keep & (size[j] <= 0.5 * size[j - 1])
        keep = keep & (n > j)
        total = total + jnp.where(keep, D[j], 0.0)
    return jnp.where(n == 0, first, total.reshape(first.shape))


def push(history, z):
    """`history` with z in front and the oldest entry dropped."""
    return jnp.concatenate([z[None], history[:-1]])


def _first_failure(status):
    """The first status that is not SUCCESS along the last axis (SUCCESS if none)."""
    failed = status != Status.SUCCESS
    return jnp.where(jnp.any(failed, axis=-1),
                     jnp.take_along_axis(status, jnp.argmax(failed, axis=-1)[..., None], axis=-1)[..., 0],
                     Status.SUCCESS).astype(jnp.int32)


def combine_stats(stats: NewtonStats) -> NewtonStats:
    """One `NewtonStats` for a step made of several solves (stacked along the last axis): the
    updates and Jacobians add up, the residual is the worst, the status the first failure."""
    return NewtonStats(iterations=jnp.sum(stats.iterations, axis=-1).astype(jnp.int32),
                       residual_norm=jnp.max(stats.residual_norm, axis=-1),
                       status=_first_failure(stats.status),
                       jacobians=jnp.sum(stats.jacobians, axis=-1).astype(jnp.int32))


def march(substep, state0, memory0, plan, dt, n_steps):
    r"""The time loop shared by every march: `n_steps` steps of `plan` (a `StepPlan`) in
    `jax.lax.scan`, each step the composition of the plan's sub-steps.

    `substep(state, memory, h, scheme, n, alive) -> (state, memory, out, stats)` makes one
    Newton-solved sub-step of size h with the principle `scheme` (static). `memory` is the
    sub-step's own slot — e.g. the history of its solutions in earlier steps, for `predict`,
    and a carried inverse Jacobian — so each stage of a composition extrapolates from the
    same stage of the previous steps (same h, smooth in n). `memory0` holds every slot, with
    leading axes (stages, members of the base step) (see `slots`; none for a plan of one solve).

    A step whose sub-step fails makes the member's state NaN from then on (`gate`); its
    statistics combine those of its sub-steps (`combine_stats`). Returns the per-step
    `(state after the step, out of the step's first sub-step, stats)`, stacked over steps.
    """
    gammas = jnp.asarray(plan.gammas, dtype=dt.dtype)
    take = lambda tree, i: jax.tree_util.tree_map(lambda a: a[i], tree)
    stack = lambda trees: jax.tree_util.tree_map(lambda *a: jnp.stack(a), *trees)

    def stage(n, alive):
        def body(state, xs):
            gamma, memory = xs
            memories, outs, stats = [], [], []
            for j, (scheme, fraction) in enumerate(plan.substeps):
                state, mem, out, st = substep(state, take(memory, j), gamma * fraction * dt, scheme, n, alive)
                memories.append(mem), outs.append(out), stats.append(st)
            return state, (stack(memories), outs[0], stack(stats))
        return body

    def step(carry, _):
        state, memory, n, alive = carry
        if plan.solves_per_step == 1:  # a single solve per step: no slot axes, nothing to combine
            (scheme, fraction), = plan.substeps
            c = plan.gammas[0] * fraction
            state, memory, out, stats = substep(state, memory, dt if c == 1.0 else c * dt, scheme, n, alive)
        else:
            state, (memory, outs, stats) = jax.lax.scan(stage(n, alive), state, (gammas, memory))
            out = take(outs, 0)
            stats = combine_stats(jax.tree_util.tree_map(lambda a: a.reshape(-1), stats))
        ok, stats, (state, out) = gate(alive, stats, (state, out))
        return (state, memory, n + 1, ok), (state, out, stats)

    init = (state0, memory0, jnp.asarray(0, jnp.int32), jnp.asarray(True))
    _, ys = jax.lax.scan(step, init, None, length=n_steps)
    return ys


def slots(plan, tree):
    """`tree` broadcast to every sub-step slot of `plan`: leading axes (stages, members); `tree`
    itself when a step is a single solve."""
    if plan.solves_per_step == 1:
        return tree
    shape = (len(plan.gammas), len(plan.substeps))
    return jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, shape + a.shape), tree)


def gate(alive, stats: NewtonStats, values):
    """After a failed step a member's values become NaN and later steps are marked SKIPPED,
    with no Newton updates or Jacobians counted (the loop only ran over NaNs beside the live
    members) and a NaN residual: never plausible-looking numbers. Returns (ok, stats with
    statuses, gated values)."""
    ok = alive & (stats.status == Status.SUCCESS)
    values = jax.tree_util.tree_map(lambda a: jnp.where(ok, a, jnp.nan), values)
    return ok, _skip(stats, alive), values


def _skip(stats: NewtonStats, attempted) -> NewtonStats:
    """`stats` with the solves that were not `attempted` marked SKIPPED, counting nothing."""
    return NewtonStats(iterations=jnp.where(attempted, stats.iterations, 0).astype(stats.iterations.dtype),
                       residual_norm=jnp.where(attempted, stats.residual_norm, jnp.nan),
                       status=jnp.where(attempted, stats.status, Status.SKIPPED).astype(jnp.int32),
                       jacobians=jnp.where(attempted, stats.jacobians, 0).astype(stats.jacobians.dtype))


def nodal_velocities(system, Qs, mus, guesses, valid, *, rtol, atol, max_iterations, solver=newton_solve):
    """Solve Lemma 7's relation for ξ at every node (vmapped Newton), gated by `valid`."""
    expand = lambda v, a: v.reshape(v.shape + (1,) * (a.ndim - 1))
    solve = functools.partial(solver, rtol=rtol, atol=atol, max_iterations=max_iterations)
    xin, st = jax.vmap(lambda q, mu, g: solve(lambda x: nodal_residual(system, q, mu, x), g))(
        Qs, mus, jnp.where(expand(valid, guesses), guesses, jnp.nan)
    )
    ok = valid & (st.status == Status.SUCCESS)  # a failed nodal solve leaves no plausible-looking ξ
    return jnp.where(expand(ok, xin), xin, jnp.nan), _skip(st, valid)


def step_guesses(xi0, xi_steps):
    """Seeds for the nodal solves: the velocity of the step leaving each node (last: arriving).
    Where the leaving step failed (its velocity is NaN) the node itself is still valid: it is
    seeded with the arriving step's velocity (ξ⁰ at node 0)."""
    leaving = jnp.concatenate([xi0[None], xi_steps[1:], xi_steps[-1:]])
    arriving = jnp.concatenate([xi0[None], xi_steps])
    finite = jnp.isfinite(leaving).reshape(leaving.shape[0], -1).all(axis=1)
    return jnp.where(finite.reshape((-1,) + (1,) * (leaving.ndim - 1)), leaving, arriving)


def assemble(*, system, dt, t0, Q0, xi0, stats, xi_steps, Qs, ps, Ps, mus, rtol, atol,
             max_iterations, form, scheme, plan, nodal_Q, solver=newton_solve):
    """Valid mask, nodal velocities, overall result and the `Solution`.

    `nodal_Q` are the configurations the Lagrangian is evaluated at for the nodal solve (the
    trajectory, or the identity broadcast when a reduced march does not carry Q); `solver` is
    the Newton solver for it (`newton_solve` or `block_newton_solve`)."""
    n_steps = xi_steps.shape[0]
    failed = stats.status != Status.SUCCESS
    valid = jnp.concatenate([jnp.array([True]), jnp.cumsum(failed) == 0])
    if system.degenerate:  # Lemma 7 does not determine nodal velocities: none are solved for
        zero = jnp.zeros(n_steps + 1, jnp.int32)
        xin = None
        nodal = _skip(NewtonStats(iterations=zero, residual_norm=jnp.zeros(n_steps + 1, dt.dtype),
                                  status=jnp.full(n_steps + 1, Status.SUCCESS, jnp.int32), jacobians=zero), valid)
    else:
        xin, nodal = nodal_velocities(system, nodal_Q, mus, step_guesses(xi0, xi_steps), valid,
                                      rtol=rtol, atol=atol, max_iterations=max_iterations, solver=solver)
    any_step, first_step = jnp.any(failed), jnp.argmax(failed)
    nodal_failed = valid & (nodal.status != Status.SUCCESS)
    any_nodal, first_node = jnp.any(nodal_failed), jnp.argmax(nodal_failed)
    result = jnp.where(any_step, stats.status[first_step],
                       jnp.where(any_nodal, Status.LEGENDRE, Status.SUCCESS)).astype(jnp.int32)
    failed_step = jnp.where(any_step, first_step, jnp.where(any_nodal, first_node, -1)).astype(jnp.int32)
    return Solution(
        ts=t0 + dt * jnp.arange(n_steps + 1, dtype=dt.dtype), Q=Qs, p=ps, xi=xin, xi_step=xi_steps,
        P=Ps, momentum=mus, stats=stats, nodal_stats=nodal, result=result, failed_step=failed_step,
        valid=valid, scheme=scheme, form=form, order=plan.order, method=plan.name,
        # Gauss–Legendre takes Q̇ from its collocation polynomial, not from the derivative map
        derivative_map="none (collocation)" if scheme == "gauss" else getattr(system.derivative_map, "name",
                                                                              repr(system.derivative_map)),
        q_ndim=Q0.ndim, xi_ndim=xi0.ndim,
    )
