"""Pieces shared by every march inside `jax.lax.scan`: initial guesses, failure gating, nodal
velocities and the assembly of the `Solution`."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from ._newton import NewtonStats, Status, newton_solve
from ._residual import nodal_residual
from ._solution import Solution
from ._system import ClebschSystem

__all__ = ["extrapolate", "gate", "nodal_velocities", "assemble"]


def extrapolate(n, first, prev, before):
    """Initial guess of step n: `first` at n = 0, then linear extrapolation 2·prev − before."""
    return jax.tree_util.tree_map(lambda f, a, b: jnp.where(n == 0, f, 2.0 * a - b), first, prev, before)


def gate(alive, stats: NewtonStats, values):
    """After a failed step a member's values become NaN and later steps are marked SKIPPED:
    never plausible-looking numbers. Returns (ok, stats with statuses, gated values)."""
    ok = alive & (stats.status == Status.SUCCESS)
    status = jnp.where(alive, stats.status, Status.SKIPPED).astype(jnp.int32)
    values = jax.tree_util.tree_map(lambda a: jnp.where(ok, a, jnp.nan), values)
    return ok, stats._replace(status=status), values


def nodal_velocities(system, Qs, mus, guesses, valid, *, rtol, atol, max_iterations, solver=newton_solve):
    """Solve Lemma 7's relation for ξ at every node (vmapped Newton), gated by `valid`."""
    expand = lambda v, a: v.reshape(v.shape + (1,) * (a.ndim - 1))
    solve = functools.partial(solver, rtol=rtol, atol=atol, max_iterations=max_iterations)
    xin, st = jax.vmap(lambda q, mu, g: solve(lambda x: nodal_residual(system, q, mu, x), g))(
        Qs, mus, jnp.where(expand(valid, guesses), guesses, jnp.nan)
    )
    status = jnp.where(valid, st.status, Status.SKIPPED).astype(jnp.int32)
    return jnp.where(expand(valid, xin), xin, jnp.nan), st._replace(status=status)


def step_guesses(xi0, xi_steps):
    """Seeds for the nodal solves: the velocity of the step leaving each node (last: arriving)."""
    return jnp.concatenate([xi0[None], xi_steps[1:], xi_steps[-1:]])


def assemble(*, system, dt, t0, Q0, xi0, stats, xi_steps, Qs, ps, Ps, mus, rtol, atol,
             max_iterations, form, scheme, order, nodal_Q, solver=newton_solve):
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
        nodal = NewtonStats(iterations=zero, residual_norm=jnp.zeros(n_steps + 1, dt.dtype),
                            status=jnp.where(valid, Status.SUCCESS, Status.SKIPPED).astype(jnp.int32),
                            jacobians=zero)
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
        valid=valid, scheme=scheme, form=form, order=order,
        derivative_map=getattr(system.derivative_map, "name", repr(system.derivative_map)),
        q_ndim=Q0.ndim, xi_ndim=xi0.ndim,
    )
