r"""The sweep's lean chunk: steps, nodal velocities and the sweep's reductions in one loop.

A sweep keeps per-member reductions, not trajectories (`clebsch_jax.sweep`). The general chunk
(`integrate` over the chunk's steps, then the nodal velocities, the energies and the invariants
of every node) records each step and node and reduces them afterwards. The lean chunk makes
the same steps with the fast path's method (`clebsch_jax.batching.fast`: a fixed number of
Newton updates and a check per member and step) and, at each new node, in the same loop body:

- the nodal velocity (Lemma 7: $\delta l/\delta\xi(\xi, Q) = \mu$), by fixed Newton updates
  from $\tfrac32\xi^n - \tfrac12\xi^{n-1}$ (the velocities of the two steps before the node,
  extrapolated to it) and a check;
- the energy $E = \langle\delta l/\delta\xi, \xi\rangle - l$, its running drift from the
  run's first node, and `integrate`'s energy check (`clebsch_jax.march.energy_check.jump_step`);
- whether anything failed: a step or nodal solve that its check does not accept, a
  non-finite value, an energy jump, an invalid input.

Nothing is stored per step, so the loop body is all the program holds. The chunk's outputs are
the general chunk's (the carry handed to the next chunk, the reductions); a member that failed
before the chunk stays failed. A member that was alive and failed in the chunk is run again
by `sweep` with the general path (in the sweep's chunks: one lean chunk covers several,
`clebsch_jax.batching.schedule.LEAN_CHUNKS`), which reports the failure's status and step: the
lean chunk only has to notice that something failed, never to say what.

The first `warmup` steps of a chunk (the fast method's `FixedNewton.warmup`), while the
predictor has few earlier steps, take `WARMUP_ROUNDS` rounds of a fresh Jacobian and
`LEAN_UPDATES` chord updates, the later steps one round: the rounds are a loop inside the solve
whose trip count is the step's (a value every member shares), so the step, the nodal
velocities, the energy check and the reductions are compiled once for every step, and the
solve once (`FixedNewton.warmup_rounds`). A warm-up step that its check does not accept fails
the member's chunk, which then runs again on the general path.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from ..core.system import momentum_map
from ..discrete.legendre import cotangent_from_momentum, explicit_nodal_velocity
from ..discrete.residual import nodal_residual
from ..march.carry import input_ok
from ..march.energy_check import jump_step, node_energy, zero_nan
from ..march.first_step import first_step_failed, half_steps
from ..roots.implicit import undifferentiated
from ..roots.newton import fixed_newton_solve
from ..roots.solvers import FixedNewton
from ..roots.status import Status
from ..steppers.base import AbstractWrapper, innermost
from ..steppers.reduced import ReducedStep

__all__ = ["lean_chunk", "supports", "carries_Q", "LEAN_UPDATES", "NODAL_UPDATES", "WARMUP_ROUNDS"]

NODAL_UPDATES = 2
"""Chord updates of a node's velocity solve: the relation is linear for a Lagrangian quadratic
in ξ (one update is exact, the second is at the noise floor, which the check needs)."""


LEAN_UPDATES = 2
"""Chord updates per step after the warm-up. With the predictor's high order the first update
is at round-off in a well-resolved march and the second at the noise floor; the check then
tells a converged solve from one still contracting (a chunk where it fails runs again with the
general path)."""

WARMUP_ROUNDS = 4
"""Rounds (a fresh Jacobian and `LEAN_UPDATES` chord updates each) of a warm-up step. Step 0
starts from the last velocity (a guess off by O(Δt)); two chord updates take an error e to
O(e³), so a few rounds reach round-off from any guess the general loop would accept in its
first few Jacobians. Instead of the general loop, which compiled as a second solve."""

UNROLL = 2
"""Steps per iteration of the loop: XLA keeps the carry's rows in place over an unrolled pair;
more copies of the long step body cost compile time for no further gain."""


def _with_finder(stepper, **changes):
    """`stepper` with its reduced step's `FixedNewton` changed (`changes`), through wrappers."""
    if isinstance(stepper, AbstractWrapper):
        return dataclasses.replace(stepper, base=_with_finder(stepper.base, **changes))
    return dataclasses.replace(stepper, root_finder=dataclasses.replace(stepper.root_finder, **changes))


def supports(stepper, system) -> bool:
    """Whether the lean chunk runs this fast method: reduced steps (possibly wrapped) with fixed
    Newton solves, for a system with nodal velocities."""
    base = innermost(stepper)
    return isinstance(base, ReducedStep) and isinstance(base.root_finder, FixedNewton) and not system.degenerate


def carries_Q(stepper, system) -> bool:
    """Whether the lean chunk carries the configuration Q from step to step: not for a reduced
    step that does not reconstruct it (`ReducedStep.reconstruct=False` and an l without
    potential), whose Q stays the chunk's start — and whose sweep then reports no final Q."""
    base = innermost(stepper)
    return base._carry_Q(system) if isinstance(base, ReducedStep) else True


def _nodal_velocity(system, finder: FixedNewton, Q, mu, guess):
    """ξ at a node from its momentum μ, by `NODAL_UPDATES` chord updates and the check, or by
    the system's inverse Legendre map when it gives one (as `integrate` evaluates it)."""
    if system.inverse_legendre is not None:
        return explicit_nodal_velocity(system, Q, mu)
    xi, stats, _, _ = fixed_newton_solve(
        lambda x: nodal_residual(system, Q, mu, x), guess, updates=NODAL_UPDATES, rtol=finder.rtol, atol=finder.atol
    )
    return xi, stats


def lean_chunk(stepper, system, carry, dt, n: int, first, derive_momentum=False):
    r"""`n` steps of one member from the sweep's carry, with the reductions made in the loop.

    **Arguments:** `stepper`, the fast method prepared for `system` (`supports`); `carry`, the
    sweep's carry (`clebsch_jax.batching.config.Carry`: the canonical state (Q, P), the nodal
    velocity ξ, t and the running reductions); `dt`; `n` the chunk's steps; `first` whether
    this is the run's first chunk (the energy drift's reference is then this chunk's node 0);
    `derive_momentum` (a traced bool, or False) whether the carry's multiplier P is a
    placeholder and node 0's momentum is $\mu^0 = \delta l/\delta\xi(\xi^0, Q^0)$ (Lemma 7: the
    momentum of the minimum-norm multiplier, without forming it) instead of $-P\diamond Q$.

    **Returns:** `(new carry, ok)`: `ok` False when anything failed in the chunk for a member
    that was alive at its start (the caller reruns the chunk with the general path; the new
    carry's status is then not the one to report).

    Not differentiable: its solves are traced without their implicit derivative rules
    (`clebsch_jax.roots.implicit.undifferentiated`), which would trace each one twice."""
    with undifferentiated():
        return _lean_chunk(stepper, system, carry, dt, n, first, derive_momentum)


def _lean_chunk(stepper, system, carry, dt, n: int, first, derive_momentum):
    alive0 = carry.status == Status.SUCCESS
    nan_unless = lambda a: jnp.where(alive0, a, jnp.nan)
    Q0, P0, xi0 = nan_unless(carry.Q), nan_unless(carry.P), nan_unless(carry.xi)
    finder = innermost(stepper).root_finder
    ok = input_ok(system, Q0, xi0, P0, dt)

    # node 0: its momentum and velocity (what the general path's start and nodal solve give)
    mu0 = momentum_map(system, P0, Q0, xi0)
    if derive_momentum is not False:
        mu0 = jnp.where(derive_momentum, jax.grad(lambda x: system.l(x, Q0))(xi0), mu0)
    xin0, st0 = _nodal_velocity(system, finder, Q0, mu0, xi0)
    ok = ok & (st0.status == Status.SUCCESS)
    state0, _ = stepper.init(system, Q0, xin0, None, dt)
    state0 = (mu0,) + tuple(state0[1:])  # a reduced step's state (μ, Q, ξ): μ = −P⋄Q as given
    memory0 = stepper.init_memory(system, state0)
    E0, size0 = node_energy(system, Q0, xin0)
    ref = jnp.where(first, E0, carry.initial["energy"])
    carries = carries_Q(stepper, system)  # else Q stays the chunk's start (reconstruct=False)
    reductions = dict(
        ok=ok,
        iterations=jnp.asarray(0, carry.iterations.dtype),
        residual=jnp.zeros((), dt.dtype),
        change=carry.energy_change,
        size=jnp.maximum(carry.energy_size, zero_nan(size0)),
        E=E0,
        drift=jnp.abs(E0 - ref),
        xin=xin0,
        mu=mu0,
        xstep=xin0,
        **({"Q": Q0} if carries else {}),
        Q1=jnp.full_like(Q0, jnp.nan),
        mu1=jnp.full_like(mu0, jnp.nan),
    )

    # warm-up steps by WARMUP_ROUNDS rounds, the others by one round of LEAN_UPDATES (module docstring)
    method = _with_finder(stepper, warmup=min(finder.warmup, n), updates=LEAN_UPDATES, warmup_rounds=WARMUP_ROUNDS)

    # integrate's first-step check, in the run's first chunk: a step 0 far from where two half
    # steps arrive (or whose half steps fail) fails the chunk, which the general path then reruns
    probe = half_steps(method, system, state0, memory0, ok, dt, jnp.where(first, 2, 0))

    def body(k, c):
        state_prev, memory, red = c
        state, memory, out, stats = method.step(system, state_prev, memory, dt, k, jnp.asarray(True))
        nodes = method.nodes(system, state_prev, _one(state), _one(out))
        Qn, mun, xi_step = nodes.nodal_Q[1], nodes.momentum[1], nodes.xi_step[0]
        # the guess extrapolates the velocities of the two steps before the node: no node's
        # solved velocity feeds the next node's solve (a chain from step to step that made the
        # loop slower); the chunk's first node extrapolates from node 0
        guess = jnp.where(k == 0, 2 * xi_step - xin0, 1.5 * xi_step - 0.5 * red["xstep"])
        xin, nst = _nodal_velocity(system, finder, Qn, mun, guess)
        E, size = node_energy(system, Qn, xin)
        # red["size"] holds the sizes of the nodes up to the one this step leaves
        change, _, jumped = jump_step(red["change"], red["size"], jnp.abs(E - red["E"]))
        size_max = jnp.maximum(red["size"], zero_nan(size))
        good = (stats.status == Status.SUCCESS) & (nst.status == Status.SUCCESS) & ~jumped
        red = dict(
            ok=red["ok"] & good,
            iterations=red["iterations"] + stats.iterations,
            residual=jnp.maximum(red["residual"], stats.residual_norm),
            change=change,
            size=size_max,
            E=E,
            drift=jnp.maximum(red["drift"], jnp.abs(E - ref)),
            xin=xin,
            mu=mun,
            xstep=xi_step,
            **({"Q": nodes.Q[1]} if carries else {}),
            # step 0's node, for the first-step check after the loop
            Q1=jnp.where(k == 0, Qn, red["Q1"]),
            mu1=jnp.where(k == 0, mun, red["mu1"]),
        )
        return state, memory, red

    c = jax.lax.fori_loop(0, n, body, (state0, memory0, reductions), unroll=min(UNROLL, n))
    red = c[2]
    Qn, mun = red.get("Q", Q0), red["mu"]
    ok = alive0 & red["ok"] & jnp.isfinite(red["drift"])
    if n > 0:  # integrate's first-step check (the general path's rerun reports it)
        nodes0 = (jnp.stack([Q0, red["Q1"]]), jnp.stack([mu0, red["mu1"]]))
        ok = ok & ~(first & first_step_failed(jnp, probe, *nodes0, Status.SUCCESS))
    status = jnp.where(alive0 & ~ok, Status.MAX_ITERATIONS, carry.status).astype(carry.status.dtype)
    initial = {**carry.initial, "energy": ref}
    drift = {**carry.drift, "energy": jnp.maximum(carry.drift["energy"], red["drift"])}
    new = carry._replace(
        Q=Qn,
        P=cotangent_from_momentum(system, Qn, mun, unroll=True),
        xi=red["xin"],
        t=carry.t + dt * n,
        status=status,
        iterations=carry.iterations + red["iterations"],
        max_residual=jnp.maximum(carry.max_residual, red["residual"]),
        initial=initial,
        drift=drift,
        momentum=mun,
        final_xi=red["xin"],
        energy_change=red["change"],
        energy_size=red["size"],
        # the lean chunk marches with another method: the general chunk's march state is stale
        march_ok=None if carry.march_ok is None else jnp.zeros_like(carry.march_ok),
    )
    return new, ok | ~alive0


def _one(tree):
    return jax.tree_util.tree_map(lambda a: a[None], tree)
