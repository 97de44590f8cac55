"""The first-step check (`FIRST_STEP_RTOL`): step 0 against two half steps of size Δt/2 from the
start, made as the first iterations of the march's own loop (`clebsch_jax.march.scan.run_chunk`,
concrete or traced, and a sweep's `clebsch_jax.batching.member.member_chunk`), by a call of the
native march's chunk (`first_step_probe`) or traced into a sweep's XLA fast paths
(`half_steps`); a spurious root of step 0's equations differs
from them by as much as it moves (`first_step_failed`)."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..roots.status import Status
from ..steppers.base import AbstractStepper
from .carry import Carry, gate

__all__ = [
    "FIRST_STEP_RTOL",
    "FIRST_STEP_FLOOR",
    "FirstStepProbe",
    "first_step_probe",
    "first_step_failed",
    "half_steps",
]


FIRST_STEP_RTOL = 0.5
r"""The first-step check (with `check_energy`, at a run's start — not when continuing from a
`march_state`; a spurious root
in step 0 can change E by little compared with the sizes of its terms, which are largest there,
as at the perihelion of an eccentric orbit):
step 0 fails with `Status.FIRST_STEP` when it converged but two half steps from the start do
not, or when the node it reaches differs from the node the half steps reach by more than this
fraction of the half steps' own displacement, in the configuration and in the momentum map alike
(each beyond a round-off floor, `FIRST_STEP_FLOOR`). A step of a method of order p differs from two half
steps by $O(\Delta t^{p+1})$, a small fraction of its $O(\Delta t)$ displacement; a root of the
step equations that is not the motion's step (a spurious root) differs by as much as it moves."""

FIRST_STEP_FLOOR = 1e-10
"""... the floor: differences below this times max(1, |x|) are round-off (a quantity that the
step conserves, or hardly moves)."""


class FirstStepProbe(NamedTuple):
    """The node two half steps of size Δt/2 reach from the start (`first_step_probe`): its
    configuration `Q` (the stepper's `nodal_Q`), momentum map `momentum`, and `ok` (both half
    steps converged)."""

    Q: jax.Array
    momentum: jax.Array
    ok: jax.Array


def first_step_probe(
    chunk_program, stepper: AbstractStepper, system, carry: Carry, dt, chunk_steps: int, check_energy: bool
) -> FirstStepProbe:
    """Two steps of size dt/2 from the start (`carry`), each with the stepper's own guesses, made
    by a concrete march's own compiled chunk (`chunk_program`: XLA's `run_chunk` or the native
    kernel of `clebsch_jax.march.native_chunk`; dt is one of its arguments, so nothing is
    compiled for them): the node they reach, to check the first step against
    (`first_step_failed`). A traced `march` makes them in its scan instead (`run_chunk`'s
    `first_step_check`)."""
    half = np.asarray(np.asarray(dt) / 2)  # a host array: the programs take it as a device one
    _, chunk = chunk_program(stepper, system, carry, half, chunk_steps, np.asarray(2, np.int32), check_energy)
    ok = np.all(np.asarray(chunk.stats.status)[:2] == Status.SUCCESS)
    return FirstStepProbe(_node_2(chunk.nodes.nodal_Q), _node_2(chunk.nodes.momentum), ok)


def _node_2(a):
    """Entry 2 of a chunk's node record, read on the host unless it is traced (indexing a device
    array is a program of its own)."""
    return a[2] if isinstance(a, jax.core.Tracer) else np.asarray(a)[2]


def first_step_failed(xp, probe: FirstStepProbe, Qs, momenta, status0):
    """Whether step 0 (nodes `Qs[:2]`, `momenta[:2]`, its status `status0`) fails the first-step
    check (`FIRST_STEP_RTOL`): it converged, and either the half steps did not (nothing confirms
    a root that smaller steps cannot reach) or its node differs from theirs by more than
    `FIRST_STEP_RTOL` of their displacement in both Q and the momentum."""

    def far(x, half):
        size = lambda a: xp.max(xp.abs(a))
        floor = FIRST_STEP_FLOOR * xp.maximum(1.0, size(half))
        return size(x[1] - half) > FIRST_STEP_RTOL * size(half - x[0]) + floor

    converged = status0 == Status.SUCCESS
    return converged & (~probe.ok | (far(Qs, probe.Q) & far(momenta, probe.momentum)))


def half_steps(stepper: AbstractStepper, system, state, memory, alive, dt, count) -> FirstStepProbe:
    """`first_step_probe` traced into the caller's program (a sweep's per-member program): up to
    two steps of size dt/2 from the start (`state`, `memory`, `alive`: `start`'s carry), each
    with the stepper's own guesses, gated as the march gates its steps. `count` (an int32 array,
    2 or 0) is the trip count of their loop, so that a program that makes them only in a run's
    first chunk costs nothing in the others (a loop of 0 iterations). Returns the
    `FirstStepProbe` of the node they reach; `ok` is False where `count` is 0."""
    half = dt / 2
    probe_of = lambda s, prev, out: stepper.nodes(system, prev, _one(s), _one(out))

    def body(k, c):
        s, m, ok, _, _ = c
        new, m, out, stats = stepper.step(system, s, m, half, k, ok)
        ok, _, (new, out) = gate(ok, stats, (new, out))
        nodes = probe_of(new, s, out)
        return new, m, ok, nodes.nodal_Q[1], nodes.momentum[1]

    shapes = jax.eval_shape(lambda: body(0, (state, memory, alive, None, None))[3:])
    nan = jax.tree_util.tree_map(lambda a: jnp.full(a.shape, jnp.nan, a.dtype), shapes)
    count = jnp.asarray(count, jnp.int32)
    _, _, ok, Q, momentum = jax.lax.fori_loop(0, count, body, (state, memory, jnp.asarray(alive), *nan))
    return FirstStepProbe(Q, momentum, ok & (count > 0))


def _one(tree):
    return jax.tree_util.tree_map(lambda a: a[None], tree)
