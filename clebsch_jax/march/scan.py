r"""The one march: `n_steps` steps of a stepper in `jax.lax.scan`, then the `Solution`.

A step whose solve fails makes the member's state NaN from then on and marks the later steps
`Status.SKIPPED` (`gate`): never plausible-looking numbers. After the scan the stepper says
what the nodes are (`AbstractStepper.nodes`), the nodal velocities are recovered from
Lemma 7's relation at every node (except for degenerate systems), and the overall result and
first failure are found.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..discrete.residual import nodal_residual
from ..roots.status import NewtonStats, Status, skip_stats
from ..steppers.base import AbstractStepper, Nodes
from .solution import Solution

__all__ = ["march", "gate", "nodal_velocities"]


def gate(alive, stats: NewtonStats, values):
    """After a failed step a member's values become NaN and later steps are marked SKIPPED,
    with no Newton updates or Jacobians counted (the loop only ran over NaNs beside the live
    members) and a NaN residual. Returns (ok, stats with statuses, gated values)."""
    ok = alive & (stats.status == Status.SUCCESS)
    values = jax.tree_util.tree_map(lambda a: jnp.where(ok, a, jnp.nan), values)
    return ok, skip_stats(stats, alive), values


def march(stepper: AbstractStepper, system, Q0, xi0, P0, dt, t0, n_steps: int) -> Solution:
    """Run `stepper` (prepared for `system`) for `n_steps` steps of size `dt` from
    $(Q^0, \\xi^0)$ (and $P^0$, if not None) and assemble the `Solution`."""
    state0, startup_iterations = stepper.init(system, Q0, xi0, P0, dt)

    def body(carry, _):
        state, memory, n, alive = carry
        state, memory, out, stats = stepper.step(system, state, memory, dt, n, alive)
        ok, stats, (state, out) = gate(alive, stats, (state, out))
        return (state, memory, n + 1, ok), (state, out, stats)

    init = (state0, stepper.init_memory(system, state0), jnp.asarray(0, jnp.int32), jnp.asarray(True))
    _, (states, outs, stats) = jax.lax.scan(body, init, None, length=n_steps)
    if not (isinstance(startup_iterations, int) and startup_iterations == 0):  # work that belongs to step 0
        stats = stats._replace(iterations=stats.iterations.at[0].add(startup_iterations.astype(stats.iterations.dtype)))
    nodes = stepper.nodes(system, state0, states, outs)
    return _assemble(stepper, system, nodes, stats, dt, t0, Q0, xi0)


def nodal_velocities(system, finder, Qs, mus, guesses, valid):
    """Solve Lemma 7's relation for ξ at every node (vmapped `finder.solve`), gated by `valid`."""
    expand = lambda v, a: v.reshape(v.shape + (1,) * (a.ndim - 1))
    xin, st = jax.vmap(lambda q, mu, g: finder.solve(lambda x: nodal_residual(system, q, mu, x), g))(
        Qs, mus, jnp.where(expand(valid, guesses), guesses, jnp.nan)
    )
    ok = valid & (st.status == Status.SUCCESS)  # a failed nodal solve leaves no plausible-looking ξ
    return jnp.where(expand(ok, xin), xin, jnp.nan), skip_stats(st, valid)


def _step_guesses(xi0, xi_steps):
    """Seeds for the nodal solves: the velocity of the step leaving each node (last: arriving).
    Where the leaving step failed (its velocity is NaN) the node itself is still valid: it is
    seeded with the arriving step's velocity (ξ⁰ at node 0)."""
    leaving = jnp.concatenate([xi0[None], xi_steps[1:], xi_steps[-1:]])
    arriving = jnp.concatenate([xi0[None], xi_steps])
    finite = jnp.isfinite(leaving).reshape(leaving.shape[0], -1).all(axis=1)
    return jnp.where(finite.reshape((-1,) + (1,) * (leaving.ndim - 1)), leaving, arriving)


def _assemble(stepper, system, nodes: Nodes, stats: NewtonStats, dt, t0, Q0, xi0) -> Solution:
    """Valid mask, nodal velocities, overall result and the `Solution`."""
    facts = stepper.facts(system)
    n_steps = nodes.xi_step.shape[0]
    failed = stats.status != Status.SUCCESS
    valid = jnp.concatenate([jnp.array([True]), jnp.cumsum(failed) == 0])
    if system.degenerate:  # Lemma 7 does not determine nodal velocities: none are solved for
        zero = jnp.zeros(n_steps + 1, jnp.int32)
        xin = None
        nodal = skip_stats(NewtonStats(iterations=zero, residual_norm=jnp.zeros(n_steps + 1, dt.dtype),
                                       status=jnp.full(n_steps + 1, Status.SUCCESS, jnp.int32), jacobians=zero), valid)
    else:
        xin, nodal = nodal_velocities(system, stepper.nodal_solver, nodes.nodal_Q, nodes.momentum,
                                      _step_guesses(nodes.xi_seed, nodes.xi_step), valid)
    any_step, first_step = jnp.any(failed), jnp.argmax(failed)
    nodal_failed = valid & (nodal.status != Status.SUCCESS)
    any_nodal, first_node = jnp.any(nodal_failed), jnp.argmax(nodal_failed)
    result = jnp.where(any_step, stats.status[first_step],
                       jnp.where(any_nodal, Status.LEGENDRE, Status.SUCCESS)).astype(jnp.int32)
    failed_step = jnp.where(any_step, first_step, jnp.where(any_nodal, first_node, -1)).astype(jnp.int32)
    # Gauss–Legendre takes Q̇ from its collocation polynomial, not from the derivative map
    derivative_map = ("none (collocation)" if facts.scheme == "gauss"
                      else getattr(system.derivative_map, "name", repr(system.derivative_map)))
    return Solution(
        ts=t0 + dt * jnp.arange(n_steps + 1, dtype=dt.dtype), Q=nodes.Q, p=nodes.p, xi=xin, xi_step=nodes.xi_step,
        P=nodes.P, momentum=nodes.momentum, stats=stats, nodal_stats=nodal, result=result, failed_step=failed_step,
        valid=valid, scheme=facts.scheme, form=facts.form, order=facts.order, method=facts.name,
        derivative_map=derivative_map, q_ndim=Q0.ndim, xi_ndim=xi0.ndim,
    )
