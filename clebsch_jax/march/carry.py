"""What a chunk of the march hands the next (`Carry`) and what it records (`Chunk`); how a march
starts (`start`, with the input check `input_ok`) or continues (`resume`); and one step of it,
gated (`advance_step`, `gate`): after a failed step a member's values are NaN, with NaN
derivatives (`failed_to_nan`), and its later steps `Status.SKIPPED`."""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..core.isotropy import IsotropyGauge, rank_holds
from ..core.model_checks import DENSE_CHECK_MAX, LINEAR_RTOL
from ..core.representation import MatrixRepresentation
from ..core.validation import nan_unless
from ..roots.status import NewtonStats, Status, skip_stats
from ..steppers.base import AbstractStepper, Nodes

__all__ = [
    "Carry",
    "Chunk",
    "failed_to_nan",
    "gate",
    "input_ok",
    "velocity_map_linear",
    "start",
    "resume",
    "advance_step",
]


class Carry(NamedTuple):
    """What one chunk hands to the next: the stepper's `state` and `memory`, the number `n`
    of the next step, `alive` (no step failed yet) and `xi_last`, the velocity of the last
    step made (the seed of the nodal solve at the node it arrives at)."""

    state: Any
    memory: Any
    n: jax.Array
    alive: jax.Array
    xi_last: jax.Array


class Chunk(NamedTuple):
    """The record of a chunk of C steps starting at step n₀: the nodes n₀ … n₀ + C (node
    fields have C + 1 entries; the last is the node after the last step actually made), the
    step fields (C entries), the nodal velocities and their statistics, and `valid` per node.
    C is the chunk's length for XLA's chunk (`run_chunk`: the steps not made padded), the steps
    it made for the native one (`clebsch_jax.march.native_chunk.native_run_chunk`)."""

    nodes: Nodes
    stats: NewtonStats
    xi: Any
    nodal_stats: NewtonStats
    valid: jax.Array
    energy: Any = None  # (E, size) at the nodes, when the energy check is on (`node_energies`)
    probe: Any = None  # the first-step check's half steps made in XLA's chunk (`run_chunk`), or None


def failed_to_nan(a, ok):
    """`a` where `ok`, NaN elsewhere — and NaN derivatives there too (`nan_unless`): a value
    computed from a failed step's state has a NaN gradient, never a zero one (a plain `where`
    would give the NaN a zero derivative, and an optimiser would stall with no clue)."""
    return nan_unless(a, ok)


def gate(alive, stats: NewtonStats, values):
    """After a failed step a member's values become NaN (with NaN derivatives:
    `failed_to_nan`) and later steps are marked SKIPPED, with no Newton updates or Jacobians
    counted (the loop only ran over NaNs beside the live members) and a NaN residual. Returns
    (ok, stats with statuses, gated values)."""
    ok = alive & (stats.status == Status.SUCCESS)
    values = jax.tree_util.tree_map(
        lambda a: failed_to_nan(a, ok) if jnp.issubdtype(a.dtype, jnp.inexact) else jnp.where(ok, a, jnp.nan), values
    )
    return ok, skip_stats(stats, alive), values


def input_ok(system, Q0, xi0, P0, dt):
    r"""Whether a member's input is valid, as a traced boolean: the checks `integrate` makes
    before compiling on concrete values, for values only known inside jit/vmap. `dt` finite and
    positive; `Q0`, `xi0`, `P0` and the system's array leaves (its parameters) finite; `Q0`
    on the manifold, when `system.check_Q` has a
    traced form (`check_Q.traced(Q) -> bool`, as the SO(n) models' rotation check has); the
    Lagrangian and the velocity map finite at $(\xi^0, Q^0)$ (the built-in models make their
    Lagrangian NaN for parameters out of range when these are traced); for a system whose
    isotropy gauge is fixed (`clebsch_jax.core.isotropy.IsotropyGauge`), the velocity map of
    the rank the gauge was built for at $Q^0$ (`rank_holds`: a sweep's member of another orbit
    type than the member its gauge was found on)."""
    finite = lambda a: jnp.all(jnp.isfinite(a))
    ok = finite(dt) & (dt > 0) & finite(Q0) & finite(xi0)
    if P0 is not None:
        ok = ok & finite(P0)
    for leaf in jax.tree_util.tree_leaves(system):  # the model's parameters
        if hasattr(leaf, "dtype") and jnp.issubdtype(leaf.dtype, jnp.inexact):
            ok = ok & finite(leaf)
    ok = ok & finite(system.l(xi0, Q0)) & finite(_velocity(system, xi0, Q0))
    traced_check = getattr(system.check_Q, "traced", None)
    if traced_check is not None:
        ok = ok & jnp.asarray(traced_check(Q0), bool)
    gauge = system.lagrangian
    if isinstance(gauge, IsotropyGauge):  # the isotropy its gauge was built for (`rank_holds`)
        ok = ok & rank_holds(gauge.velocity_map, Q0, xi0.shape, gauge.rank)
    return ok


def velocity_map_linear(system, Q0, xi0):
    r"""Whether the velocity map is additive at $Q^0$, as a traced boolean: the traced form of
    `integrate`'s check of Definition 1 on concrete values (`clebsch_jax.core.model_checks`),
    for calls under `jax.jit`/`jax.vmap`/`jax.grad`, where that check cannot run.
    $|\mathcal L_{2\xi^0 + d} - 2\mathcal L_{\xi^0} - \mathcal L_d| \le$ `LINEAR_RTOL` times the
    sizes of the three, with d a fixed direction of the size of ξ⁰ (a pattern without symmetry
    among the components; all ones above `DENSE_CHECK_MAX` components): a term nonlinear in ξ,
    or a constant term, fails it; round-off of a linear map is far below it. Three evaluations
    of the velocity map at step 0 (of its factor X for a declared representation: `_velocity`)."""
    if xi0.size <= DENSE_CHECK_MAX:  # a constant of the program, with no symmetry among components
        pattern = np.sin(np.arange(1, xi0.size + 1, dtype=float)).reshape(xi0.shape)
    else:  # large ξ (a fluid): no constant of its size in the program
        pattern = np.ones((), float)
    d = jnp.broadcast_to(pattern * (jnp.max(jnp.abs(xi0)) + 1.0), xi0.shape).astype(xi0.dtype)
    v0, vd, v2 = (_velocity(system, x, Q0) for x in (xi0, d, 2.0 * xi0 + d))
    norm = lambda a: jnp.sqrt(jnp.sum(jnp.abs(a) ** 2))  # X may be complex (`_velocity`)
    return norm(v2 - 2.0 * v0 - vd) <= LINEAR_RTOL * (2.0 * norm(v0) + norm(vd) + norm(v2))


def _velocity(system, xi, Q0):
    r"""What the traced checks evaluate of the velocity map at (ξ, Q⁰): the map itself, or for a
    declared `MatrixRepresentation` ($\mathcal L_\xi Q = Q\,X(\xi)$) the factor $X(\xi)$ — the
    map is finite where X is (Q⁰ is checked finite) and linear in ξ when X is (the stricter
    check), and X costs O(dim V) where the product with Q⁰ costs a matrix product of the
    ambient size (for the fluid, (2N)³)."""
    vm = system.velocity_map
    return vm.X(xi) if isinstance(vm, MatrixRepresentation) else vm(xi, Q0)


def _checked(system, Q0, xi0, P0, dt):
    """`input_ok` and `velocity_map_linear`: what a traced `integrate` call checks per member."""
    return input_ok(system, Q0, xi0, P0, dt) & velocity_map_linear(system, Q0, xi0)


def start(stepper: AbstractStepper, system, Q0, xi0, P0, dt, check_inputs: bool = False):
    """The stepper's initial state as a `Carry`, and the iterations its start-up took. With
    `check_inputs` a member whose input is not valid (`input_ok`) or whose velocity map is not
    linear in ξ (`velocity_map_linear`) starts failed: it makes no step and its step 0 is
    reported `Status.INVALID_INPUT`."""
    state0, startup_iterations = stepper.init(system, Q0, xi0, P0, dt)
    alive = _checked(system, Q0, xi0, P0, dt) if check_inputs else jnp.asarray(True)
    carry = Carry(state0, stepper.init_memory(system, state0), jnp.asarray(0, jnp.int32), alive, jnp.zeros_like(xi0))
    return carry, jnp.asarray(startup_iterations, jnp.int32)


def resume(stepper: AbstractStepper, system, Q0, xi0, P0, dt, check_inputs: bool, march_state, n_steps: int):
    """The `Carry` a march of `n_steps` steps starts from, the iterations its start-up took and
    the step number it stops at: `start`'s, or with `march_state` (the carry an earlier march
    ended with) that carry — its stepper state, its guesses and predictor history, its step
    count — so that the steps made are those the unbroken march would make. A member that had
    failed stays failed (its step 0 reports `Status.INVALID_INPUT`, as for NaN input)."""
    if march_state is None:
        carry, startup = start(stepper, system, Q0, xi0, P0, dt, check_inputs)
        return carry, startup, jnp.asarray(n_steps, jnp.int32)
    alive = march_state.alive & _checked(system, Q0, xi0, P0, dt) if check_inputs else march_state.alive
    carry = march_state._replace(alive=jnp.asarray(alive, bool))
    return carry, jnp.zeros((), jnp.int32), (carry.n + n_steps).astype(jnp.int32)


def advance_step(stepper: AbstractStepper, system, dt, c: Carry):
    """One step of the march from `c`, gated (`gate`): (the carry after it, its record: the
    state, the step's output, its statistics, whether the member was alive before it)."""
    state, memory, out, stats = stepper.step(system, c.state, c.memory, dt, c.n, c.alive)
    ok, stats, (state, out) = gate(c.alive, stats, (state, out))
    return c._replace(state=state, memory=memory, n=c.n + 1, alive=ok), (state, out, stats, c.alive)
