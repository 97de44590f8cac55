r"""The one march: steps of a stepper in `jax.lax.scan`, then the `Solution`.

A step whose solve fails makes the member's state NaN from then on and marks the later steps
`Status.SKIPPED` (`gate`): never plausible-looking numbers. After the steps the stepper says
what the nodes are (`AbstractStepper.nodes`), the nodal velocities are recovered from
Lemma 7's relation at every node (except for degenerate systems), and the overall result and
first failure are found.

The march is cut into **chunks** (`run_chunk`): a loop over a fixed number of steps that
hands its carry — the stepper's state and memory, the step number, the failure flag and the
last step velocity — to the next chunk. Called with concrete arguments (and maps that close
over no traced value), `integrate` runs the march as `march_chunked`: one compiled program
for the start and one for a chunk of `chunk_length` steps, whose loop stops at the run's
number of steps (`n_total`, an argument), so a new `n_steps` or `dt` reuses both programs.
Under a JAX transformation (`jit`, `vmap`, `grad`) the march is one `lax.scan` of exactly
`n_steps` steps (`march`), traced into the caller's program. Both assemble the `Solution`
with the same code, on NumPy arrays or traced ones, and the carry is handed over exactly: the
chunked march is the same arithmetic as the single scan.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..core.isotropy import IsotropyGauge, isotropy_dimension, rank_holds
from ..core.jit import QUICK_COMPILE, filter_jit
from ..core.validation import any_traced, nan_unless
from ..discrete.legendre import explicit_nodal_velocity
from ..discrete.residual import nodal_residual
from ..roots.status import NewtonStats, Status, skip_stats
from ..steppers.base import AbstractStepper, Nodes
from .solution import Solution

__all__ = [
    "march",
    "march_chunked",
    "run_chunk",
    "advance_step",
    "start",
    "gate",
    "failed_to_nan",
    "nodal_velocities",
    "nodal_velocity",
    "input_ok",
    "energy_terms",
    "node_energy",
    "node_energies",
    "energy_jump",
    "chunk_length",
    "CHUNK_STEPS",
    "CHUNK_VALUES",
    "MIN_CHUNK_STEPS",
    "NATIVE_CHUNK_FACTOR",
    "ENERGY_STEP_RTOL",
    "FIRST_STEP_RTOL",
    "FIRST_STEP_FLOOR",
    "first_step_probe",
    "first_step_failed",
    "half_steps",
]

CHUNK_STEPS = 1024
"""The most steps per compiled chunk of `march_chunked` (`chunk_length`)."""

CHUNK_VALUES = 32768
"""`chunk_length`: a chunk of a large member (many particles) holds about this many values of
its state per record (Q and ξ per node), so that a short run of a large system does not fill
and copy buffers of `CHUNK_STEPS` nodes."""

MIN_CHUNK_STEPS = 64
"""The fewest steps per chunk (`chunk_length`)."""

NATIVE_CHUNK_FACTOR = 8
"""A chunk of a native march (`clebsch_jax.march.native_chunk`) is this many times
`chunk_length`: its length compiles nothing (the kernel loops over a run-time count), and each
chunk costs the host a fixed amount of work around the kernel's call."""

ENERGY_STEP_RTOL = 0.1
r"""The energy check (`check_energy`), a per-step error indicator: step n fails with
`Status.ENERGY_JUMP` when it changes the energy $E = \langle\delta l/\delta\xi, \xi\rangle - l$ by
more than this fraction of the energy's size so far,

$$ |E^{n+1} - E^n| > \texttt{ENERGY\_STEP\_RTOL}\;\max_{k \le n}
\bigl(|\langle\delta l/\delta\xi, \xi^k\rangle| + |l(\xi^k, Q^k)|\bigr) . $$

The exact flow conserves E, and a step of a convergent method of order p changes it by
$O(\Delta t^{p+1})$ relative to the sizes of its two terms, so $|E^{n+1} - E^n|$ over that size
is the step's own relative error in the one quantity the march can check for free. A step that
changes E by a tenth of its terms does not resolve the motion: it crossed a singularity of the
model (Newton found a root on the far side, in one step or in a few growing ones, as a particle
falling into a $1/r$ potential with the left principle does), or it is far too large for the
motion there. Runs that resolve their motion, even coarsely (the rigid body with the Cayley step
at steps of a large fraction of its period, an eccentric Kepler orbit with the first-order left
principle), stay far below it, and a particle that crosses a $1/r$ singularity with the left or
right principle exceeds it within a step or two of the crossing (`tests/test_step_error.py`).
The size is taken up to the node the step leaves, not the one it arrives at: a spurious root
near a singularity arrives where l is huge. It is the size of the energy's terms as written: a
constant added to l makes the check looser."""


FIRST_STEP_RTOL = 0.5
r"""The first-step check (with `check_energy`, on concrete runs — `march_chunked`; a spurious root
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
    step fields (C entries), the nodal velocities and their statistics, and `valid` per node."""

    nodes: Nodes
    stats: NewtonStats
    xi: Any
    nodal_stats: NewtonStats
    valid: jax.Array
    energy: Any = None  # (E, size) at the nodes, when the energy check is on (`node_energies`)


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
    ok = ok & finite(system.l(xi0, Q0)) & finite(system.velocity_map(xi0, Q0))
    traced_check = getattr(system.check_Q, "traced", None)
    if traced_check is not None:
        ok = ok & jnp.asarray(traced_check(Q0), bool)
    gauge = system.lagrangian
    if isinstance(gauge, IsotropyGauge):  # the isotropy its gauge was built for (`rank_holds`)
        ok = ok & rank_holds(gauge.velocity_map, Q0, xi0.shape, gauge.rank)
    return ok


def start(stepper: AbstractStepper, system, Q0, xi0, P0, dt, check_inputs: bool = False):
    """The stepper's initial state as a `Carry`, and the iterations its start-up took. With
    `check_inputs` a member whose input is not valid (`input_ok`) starts failed: it makes no
    step and its step 0 is reported `Status.INVALID_INPUT`."""
    state0, startup_iterations = stepper.init(system, Q0, xi0, P0, dt)
    alive = input_ok(system, Q0, xi0, P0, dt) if check_inputs else jnp.asarray(True)
    carry = Carry(state0, stepper.init_memory(system, state0), jnp.asarray(0, jnp.int32), alive, jnp.zeros_like(xi0))
    return carry, jnp.asarray(startup_iterations, jnp.int32)


def first_step_probe(
    chunk_program, stepper: AbstractStepper, system, carry: Carry, dt, chunk_steps: int, check_energy: bool
) -> FirstStepProbe:
    """Two steps of size dt/2 from the start (`carry`), each with the stepper's own guesses, made
    by the march's own compiled chunk (`chunk_program`, `run_chunk`: dt is one of its arguments,
    so nothing is compiled for them): the node they reach, to check the first step against
    (`first_step_failed`)."""
    half = jnp.asarray(np.asarray(dt) / 2)
    _, chunk = chunk_program(stepper, system, carry, half, chunk_steps, np.asarray(2, np.int32), check_energy)
    ok = np.all(np.asarray(chunk.stats.status)[:2] == Status.SUCCESS)
    return FirstStepProbe(chunk.nodes.nodal_Q[2], chunk.nodes.momentum[2], ok)


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


def advance_step(stepper: AbstractStepper, system, dt, c: Carry):
    """One step of the march from `c`, gated (`gate`): (the carry after it, its record: the
    state, the step's output, its statistics, whether the member was alive before it)."""
    state, memory, out, stats = stepper.step(system, c.state, c.memory, dt, c.n, c.alive)
    ok, stats, (state, out) = gate(c.alive, stats, (state, out))
    return c._replace(state=state, memory=memory, n=c.n + 1, alive=ok), (state, out, stats, c.alive)


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


def run_chunk(
    stepper: AbstractStepper,
    system,
    carry: Carry,
    dt,
    length: int,
    n_total,
    check_energy: bool = False,
    exact: bool = False,
) -> tuple[Carry, Chunk]:
    """`length` steps from `carry`, their nodes and nodal velocities (and, with `check_energy`,
    their energies: `node_energies`); the steps numbered `n_total` (an int32 array: the run's
    number of steps) and later are not made and leave the carry unchanged.

    Two shapes of program, the same arithmetic per step and node:

    - `exact=True` (`march`, traced into the caller's program): every one of the `length` steps
      is made (`n_total - carry.n >= length`): one `lax.scan`, transposable for reverse-mode
      derivatives.
    - `exact=False` (`march_chunked`, concrete values): the steps run in a `lax.while_loop`
      that stops at `n_total`; the records of the steps not made stay zero (`valid` False), so
      a chunk that runs past the end of a run costs nothing for those steps. (A loop whose trip
      count depends on the data cannot be transposed: this shape is for values that are not
      differentiated.) The nodal velocities of the nodes not reached start from NaN seeds,
      whose solves stop at their first update."""

    advance = lambda c: advance_step(stepper, system, dt, c)
    if exact:
        last, (states, outs, stats, valid) = jax.lax.scan(lambda c, _: advance(c), carry, None, length=length)
    else:
        # jitted (inlined) so that it is traced once, for the records' shapes and the loop body
        last, (states, outs, stats, valid) = _steps_until(jax.jit(advance, inline=True), carry, length, n_total)
    nodes = stepper.nodes(system, carry.state, states, outs)
    made = jnp.clip(n_total - carry.n, 0, length)
    xi_last = jnp.where(made > 0, nodes.xi_step[jnp.maximum(made - 1, 0)], carry.xi_last)
    valid = jnp.concatenate([valid, last.alive[None]])
    # seeds of the nodal solves: the velocity of the step leaving the node (the given ξ⁰ at
    # node 0), or, where that step failed or at the last node, of the step arriving at it
    leaving = jnp.concatenate(
        [jnp.where(carry.n == 0, nodes.xi_seed, nodes.xi_step[0])[None], nodes.xi_step[1:], xi_last[None]]
    )
    first = jnp.where(carry.n == 0, nodes.xi_seed, carry.xi_last)
    arriving = jnp.concatenate([first[None], nodes.xi_step[:-1], xi_last[None]])
    guesses = jnp.where(_finite_rows(leaving), leaving, arriving)
    if system.degenerate:  # Lemma 7 does not determine nodal velocities: none are solved for
        zero = jnp.zeros(length + 1, jnp.int32)
        xi = None
        nodal = skip_stats(
            NewtonStats(
                iterations=zero,
                residual_norm=jnp.zeros(length + 1, dt.dtype),
                status=jnp.full(length + 1, Status.SUCCESS, jnp.int32),
                jacobians=zero,
            ),
            valid,
        )
    else:
        xi, nodal = nodal_velocities(system, stepper.nodal_solver, nodes.nodal_Q, nodes.momentum, guesses, valid)
    energy = node_energies(system, nodes.nodal_Q, xi) if check_energy and xi is not None else None
    return last._replace(xi_last=xi_last), Chunk(nodes, stats, xi, nodal, valid, energy)


def _zeros(shapes, lead: tuple = ()):
    """Zero arrays of the shapes and dtypes `shapes` (from `jax.eval_shape`), with the leading
    axes `lead`."""
    return jax.tree_util.tree_map(lambda s: jnp.zeros(lead + s.shape, s.dtype), shapes)


def _steps_until(advance, carry: Carry, length: int, n_total):
    """(last carry, outputs of `length` steps) as a scan of `advance` would give them, with the
    steps from `n_total` on not made: their records are zero (`valid` False) and their states
    the last state, which the node after the run's last step (the chunk's last node) holds."""
    stop = jnp.minimum(n_total, carry.n + length)
    out0 = _zeros(jax.eval_shape(lambda c: advance(c)[1], carry), (length,))

    def body(state):
        c, i, out = state
        c, y = advance(c)
        return c, i + 1, jax.tree_util.tree_map(lambda o, v: o.at[i].set(v), out, y)

    last, made, (states, *records) = jax.lax.while_loop(
        lambda st: st[0].n < stop, body, (carry, jnp.asarray(0, jnp.int32), out0)
    )
    idle = jnp.arange(length) >= made
    states = jax.tree_util.tree_map(
        lambda a, s: jnp.where(idle.reshape((-1,) + (1,) * s.ndim), s, a), states, last.state
    )
    return last, (states, *records)


def energy_terms(system, Q, xi):
    r"""The two terms of the energy $E = \langle \delta l/\delta\xi, \xi\rangle - l(\xi, Q)$ at one
    node: (the pairing, $l$). At a nodal velocity $\delta l/\delta\xi$ is the node's momentum
    (Lemma 7), so $E$ is the Hamiltonian of Lemma 8 there."""
    lval, g = jax.value_and_grad(lambda y: system.l(y, Q))(xi)
    return jnp.sum(g * xi), lval


def node_energies(system, Qs, xis):
    r"""The energy $E^n$ at every node (`energy_terms`) and its size
    $|\langle\delta l/\delta\xi, \xi^n\rangle| + |l(\xi^n, Q^n)|$, for the energy check. Read
    from the nodal velocities alone: the momenta are not needed (a program that does not
    return them never stores them)."""
    return jax.vmap(lambda q, x: node_energy(system, q, x))(Qs, xis)


def node_energy(system, Q, xi):
    """`node_energies` at one node: (E, its size)."""
    pairing, lagrangian = energy_terms(system, Q, xi)
    return pairing - lagrangian, jnp.abs(pairing) + jnp.abs(lagrangian)


def _finite_rows(a):
    finite = jnp.isfinite(a).reshape(a.shape[0], -1).all(axis=1)
    return finite.reshape((-1,) + (1,) * (a.ndim - 1))


def nodal_velocities(system, finder, Qs, mus, guesses, valid):
    """Solve Lemma 7's relation for ξ at every node (`nodal_velocity`, vmapped), gated by
    `valid`: a node that is not valid starts from a NaN seed, and its solve stops at the first
    update."""
    return jax.vmap(lambda q, mu, g, v: nodal_velocity(system, finder, q, mu, g, v))(Qs, mus, guesses, valid)


def nodal_velocity(system, finder, Q, mu, guess, valid):
    """`nodal_velocities` at one node: (ξ, the solve's statistics), ξ NaN where the node is not
    valid or its solve failed."""
    seed = jnp.where(valid, guess, jnp.nan)
    if system.inverse_legendre is not None:  # Lemma 8's G is given: evaluated, not solved for
        xin, st = explicit_nodal_velocity(system, Q, jnp.where(jnp.isnan(seed), jnp.nan, mu))
    else:
        xin, st = finder.solve(lambda x: nodal_residual(system, Q, mu, x), seed)
    ok = valid & (st.status == Status.SUCCESS)  # a failed nodal solve leaves no plausible-looking ξ
    return jnp.where(ok, xin, jnp.nan), skip_stats(st, valid)


def march(
    stepper: AbstractStepper,
    system,
    Q0,
    xi0,
    P0,
    dt,
    t0,
    n_steps: int,
    check_energy: bool = False,
    check_inputs: bool = False,
    march_state: Carry | None = None,
) -> Solution:
    """Run `stepper` (prepared for `system`) for `n_steps` steps of size `dt` from
    $(Q^0, \\xi^0)$ (and $P^0$, if not None) in one scan and assemble the `Solution`. With
    `check_energy` a step whose energy jumps fails (`Status.ENERGY_JUMP`); with `check_inputs`
    an invalid input fails step 0 (`Status.INVALID_INPUT`: `input_ok`). With `march_state`
    (the `Carry` a march ended with, `Solution.march_state`) the march continues from it
    (`resume`) instead of starting."""
    carry, startup, n_total = resume(stepper, system, Q0, xi0, P0, dt, check_inputs, march_state, n_steps)
    last, chunk = run_chunk(stepper, system, carry, dt, n_steps, n_total, check_energy, exact=True)
    sol = _assemble(jnp, stepper, system, [chunk], n_steps, startup, dt, t0, Q0, xi0, carry.alive)
    return dataclasses.replace(sol, march_state=last)


def resume(stepper: AbstractStepper, system, Q0, xi0, P0, dt, check_inputs: bool, march_state, n_steps: int):
    """The `Carry` a march of `n_steps` steps starts from, the iterations its start-up took and
    the step number it stops at: `start`'s, or with `march_state` (the carry an earlier march
    ended with) that carry — its stepper state, its guesses and predictor history, its step
    count — so that the steps made are those the unbroken march would make. A member that had
    failed stays failed (its step 0 reports `Status.INVALID_INPUT`, as for NaN input)."""
    if march_state is None:
        carry, startup = start(stepper, system, Q0, xi0, P0, dt, check_inputs)
        return carry, startup, jnp.asarray(n_steps, jnp.int32)
    alive = march_state.alive & input_ok(system, Q0, xi0, P0, dt) if check_inputs else march_state.alive
    carry = march_state._replace(alive=jnp.asarray(alive, bool))
    return carry, jnp.zeros((), jnp.int32), (carry.n + n_steps).astype(jnp.int32)


_PROGRAMS = {
    quick: (
        filter_jit(start, compiler_options=QUICK_COMPILE if quick else None),
        filter_jit(run_chunk, compiler_options=QUICK_COMPILE if quick else None),
    )
    for quick in (False, True)
}
"""The compiled start and chunk of `march_chunked`, by the stepper's `quick_compile`."""


def chunk_length(Q0, xi0) -> int:
    """Steps per chunk of `march_chunked` for a member of these shapes: `CHUNK_STEPS`, or for a
    large member the power of two that keeps about `CHUNK_VALUES` values of Q and ξ per chunk
    (at least `MIN_CHUNK_STEPS`). A function of the shapes only, so the programs stay
    independent of `n_steps`."""
    per_node = max(1, int(np.size(Q0)) + int(np.size(xi0)))
    steps = 1 << max(0, (CHUNK_VALUES // per_node).bit_length() - 1)
    return int(min(CHUNK_STEPS, max(MIN_CHUNK_STEPS, steps)))


def march_chunked(
    stepper: AbstractStepper,
    system,
    Q0,
    xi0,
    P0,
    dt,
    t0,
    n_steps: int,
    chunk_steps: int | None = None,
    check_energy: bool = False,
    march_state: Carry | None = None,
    backend: str = "xla",
) -> Solution:
    """`march` with concrete arguments, as compiled chunks of `chunk_steps` steps (default
    `chunk_length`): the programs depend on the stepper, the system and the shapes, not on
    `n_steps` or `dt`. With `march_state` the march continues from it (`resume`); its first
    step is then not checked as a run's first step (`first_step_probe`). `backend` ("xla",
    "native" or "auto", `integrate`'s): which program makes a chunk's steps
    (`clebsch_jax.march.native_chunk.native_chunk_program`)."""
    from .native_chunk import native_chunk_program

    start_jit, chunk_jit = _PROGRAMS[bool(stepper.quick_compile)]
    probe = None
    if march_state is None:
        carry, startup = start_jit(stepper, system, Q0, xi0, P0, dt)
    else:
        carry = march_state
    native = native_chunk_program(stepper, system, carry, dt, check_energy, backend)
    if chunk_steps is None:  # a native chunk costs no compile per step: longer chunks, less host work
        chunk_steps = chunk_length(Q0, xi0) * (NATIVE_CHUNK_FACTOR if native is not None else 1)
    chunk_jit = native or chunk_jit
    if march_state is None:
        if check_energy and n_steps > 0 and not any_traced(carry):
            probe = first_step_probe(chunk_jit, stepper, system, carry, dt, chunk_steps, check_energy)
        total = np.asarray(n_steps, np.int32)  # a NumPy scalar: no conversion program
    else:  # a continued march: its first step is not a run's first step (it has its guesses)
        carry, startup = march_state, np.zeros((), np.int32)
        total = np.asarray(np.asarray(carry.n) + n_steps, np.int32)
    chunks = []
    for _ in range(-(-n_steps // chunk_steps)):
        carry, chunk = chunk_jit(stepper, system, carry, dt, chunk_steps, total, check_energy)
        chunks.append(chunk)
    if any_traced(chunks, startup, probe):
        # a function the map checks do not call closed over a traced value (the caller is
        # inside jit/vmap; integrate sends maps that close over one to `march`)
        sol = _assemble(jnp, stepper, system, chunks, n_steps, startup, dt, t0, Q0, xi0, probe=probe)
        return dataclasses.replace(sol, march_state=carry)
    chunks, startup, dt, t0, probe = jax.tree_util.tree_map(np.asarray, (chunks, startup, dt, t0, probe))
    sol = _assemble(np, stepper, system, chunks, n_steps, startup, dt, t0, Q0, xi0, probe=probe)
    return dataclasses.replace(jax.device_put(sol), march_state=jax.device_put(carry))


def _join(xp, chunks, n_steps: int, node: bool):
    """The chunks' records of a field joined: N step entries, or N + 1 node entries."""
    first = [c[:-1] if node else c for c in chunks]
    joined = xp.concatenate(first)[:n_steps] if len(first) > 1 else first[0][:n_steps]
    return xp.concatenate([joined, chunks[-1][-1:]]) if node else joined


def _running_max(a):
    """max(a[0], …, a[n]) for every n (NumPy), NaN entries counting as 0."""
    return np.maximum.accumulate(np.where(np.isnan(a), 0.0, a))


def energy_jump(xp, energy, size, status, largest=0.0, size_max=0.0):
    """The first step that fails the energy check (`ENERGY_STEP_RTOL`) before any other
    failure, and whether there is one, for nodes `energy`, `size` (`node_energies`) and steps
    `status`. Non-finite energies (after a failure, or at a node whose velocity was not
    recovered) are not compared. `largest` and `size_max` are the running maxima of the steps'
    changes and the nodes' sizes before these (a run checked in pieces, as `sweep` does; the
    largest change is carried for the sweep's records, the rule reads only the sizes); returned
    with the jump are their values after these steps: (jumped, step, largest, size_max).

    On NumPy arrays the running maxima are vectorised; traced, the check is one scan over the
    steps (XLA's cumulative max and sum on CPU, associative scans, cost several times more)."""
    change = xp.abs(energy[1:] - energy[:-1])
    if xp is np:
        running_change, running_size = _running_max(change), _running_max(size)
        size_before = np.maximum(size_max, running_size[:-1])
        jumped = change > ENERGY_STEP_RTOL * size_before
        jumped = jumped & (np.cumsum(status != Status.SUCCESS) == 0)  # before any other failure
        return (
            np.any(jumped),
            np.argmax(jumped),
            np.maximum(largest, running_change[-1]),
            np.maximum(size_max, running_size[-1]),
        )

    def step(c, x):
        largest, size_max, clean, first, n = c
        d, s, st = x
        clean = clean & (st == Status.SUCCESS)
        largest, size_max, jumped = jump_step(largest, size_max, d, s)
        jumped = clean & jumped
        first = jnp.where(jumped & (first < 0), n, first)
        return (largest, size_max, clean, first, n + 1), None

    dtype = change.dtype
    init = (
        jnp.asarray(largest, dtype),
        jnp.asarray(size_max, dtype),
        jnp.asarray(True),
        jnp.asarray(-1, jnp.int32),
        jnp.asarray(0, jnp.int32),
    )
    (largest, size_max, _, first, _), _ = jax.lax.scan(step, init, (change, size[:-1], status))
    return first >= 0, jnp.maximum(first, 0), largest, jnp.maximum(size_max, zero_nan(size[-1]))


def zero_nan(a):
    """a with NaN made 0 (a size or change the running maxima of the energy check skip)."""
    return jnp.where(jnp.isnan(a), 0.0, a)


def jump_step(largest, size_max, change, size):
    """One step of the energy check (`ENERGY_STEP_RTOL`): (running largest change, running
    largest size after the step, whether the step failed it), for the step's energy change and
    the size at the node it leaves (`node_energies`); `size_max` holds the sizes of the nodes
    before that one."""
    size_max = jnp.maximum(size_max, zero_nan(size))
    jumped = change > ENERGY_STEP_RTOL * size_max
    return jnp.maximum(largest, zero_nan(change)), size_max, jumped


def _fail_from(xp, step, code, stats, nodal, valid, fields):
    """The records with step `step` failed (`code`): later steps SKIPPED, the nodes after it
    invalid, with NaN values (and NaN derivatives: `failed_to_nan`); `fields` are (array,
    node?) pairs. `step` may be len(steps): nothing fails."""
    n_steps = stats.status.shape[0]
    steps, nodes = xp.arange(n_steps), xp.arange(n_steps + 1)
    stats = stats._replace(status=xp.where(steps == step, code, stats.status).astype(stats.status.dtype))
    stats = skip_stats(stats, steps <= step) if xp is jnp else _np_skip(stats, steps <= step)
    keep_node = nodes <= step
    nodal = skip_stats(nodal, keep_node) if xp is jnp else _np_skip(nodal, keep_node)
    valid = valid & keep_node

    def mask(a, keep):
        if a is None:
            return None
        keep = keep.reshape(keep.shape + (1,) * (a.ndim - 1))
        return np.where(keep, a, np.nan) if xp is np else failed_to_nan(a, keep)

    out = [mask(a, keep_node if node else steps < step) for a, node in fields]
    return stats, nodal, valid, out


def _np_skip(stats: NewtonStats, attempted) -> NewtonStats:
    """`skip_stats` on NumPy arrays."""
    return NewtonStats(
        iterations=np.where(attempted, stats.iterations, 0).astype(stats.iterations.dtype),
        residual_norm=np.where(attempted, stats.residual_norm, np.nan),
        status=np.where(attempted, stats.status, Status.SKIPPED).astype(np.int32),
        jacobians=np.where(attempted, stats.jacobians, 0).astype(stats.jacobians.dtype),
    )


def _assemble(
    xp,
    stepper,
    system,
    chunks: list[Chunk],
    n_steps: int,
    startup,
    dt,
    t0,
    Q0,
    xi0,
    input_ok=None,
    probe: FirstStepProbe | None = None,
) -> Solution:
    """The `Solution` from the chunks' records (`xp`: `numpy` or `jax.numpy`, as they are).
    `input_ok` (traced runs with `check_inputs`): False makes step 0 `Status.INVALID_INPUT`.
    `probe` (concrete runs with the energy check): step 0, unless the energy check failed it,
    checked against two half steps (`first_step_failed`)."""

    def join(get, node):
        fields = [get(c) for c in chunks]
        if fields[0] is None:
            return None
        return jax.tree_util.tree_map(lambda *a: _join(xp, list(a), n_steps, node), *fields)

    nodes = join(lambda c: c.nodes._replace(P=None, xi_step=None, xi_seed=None), True)
    stats = join(lambda c: c.stats, False)
    stats = stats._replace(
        iterations=stats.iterations + xp.where(xp.arange(n_steps) == 0, startup, 0).astype(stats.iterations.dtype)
    )  # start-up work belongs to step 0
    P, xi_step = join(lambda c: c.nodes.P, False), join(lambda c: c.nodes.xi_step, False)
    xin, nodal, valid = join(lambda c: c.xi, True), join(lambda c: c.nodal_stats, True), join(lambda c: c.valid, True)
    if input_ok is not None:  # an invalid member made no step: its step 0 says why
        stats = stats._replace(
            status=xp.where((xp.arange(n_steps) == 0) & ~input_ok, Status.INVALID_INPUT, stats.status).astype(
                stats.status.dtype
            )
        )
    fields_of = lambda: [
        (nodes.Q, True),
        (nodes.p, True),
        (nodes.momentum, True),
        (xin, True),
        (xi_step, False),
        (P, False),
    ]
    energy = join(lambda c: c.energy, True)
    jumped, step = energy_jump(xp, *energy, stats.status)[:2] if energy is not None else (False, None)
    if energy is not None and (xp is jnp or bool(jumped)):  # on the host, only a jump costs a pass
        step = xp.where(jumped, step, n_steps)
        stats, nodal, valid, out = _fail_from(xp, step, Status.ENERGY_JUMP, stats, nodal, valid, fields_of())
        Qn, pn, mun, xin, xi_step, P = out
        nodes = nodes._replace(Q=Qn, p=pn, momentum=mun)
    if probe is not None:  # after the energy check, which every path makes: a step 0 it fails keeps its status
        first = first_step_failed(xp, probe, nodes.nodal_Q[:2], nodes.momentum[:2], stats.status[0])
        if xp is jnp or bool(first):  # on the host, only a failure costs a pass
            stats, nodal, valid, out = _fail_from(
                xp, xp.where(first, 0, n_steps), Status.FIRST_STEP, stats, nodal, valid, fields_of()
            )
            Qn, pn, mun, xin, xi_step, P = out
            nodes = nodes._replace(Q=Qn, p=pn, momentum=mun)
    facts = stepper.facts(system)
    failed = stats.status != Status.SUCCESS
    any_step, first_step = xp.any(failed), xp.argmax(failed)
    nodal_failed = valid & (nodal.status != Status.SUCCESS)
    any_nodal, first_node = xp.any(nodal_failed), xp.argmax(nodal_failed)
    result = xp.where(any_step, stats.status[first_step], xp.where(any_nodal, Status.LEGENDRE, Status.SUCCESS)).astype(
        xp.int32
    )
    failed_step = xp.where(any_step, first_step, xp.where(any_nodal, first_node, -1)).astype(xp.int32)
    # Gauss–Legendre takes Q̇ from its collocation polynomial, not from the derivative map
    derivative_map = (
        "none (collocation)"
        if facts.scheme == "gauss"
        else getattr(system.derivative_map, "name", repr(system.derivative_map))
    )
    return Solution(
        ts=t0 + dt * xp.arange(n_steps + 1, dtype=dt.dtype),
        Q=nodes.Q,
        p=nodes.p,
        xi=xin,
        xi_step=xi_step,
        P=P,
        momentum=nodes.momentum,
        stats=stats,
        nodal_stats=nodal,
        result=result,
        failed_step=failed_step,
        valid=valid,
        scheme=facts.scheme,
        form=facts.form,
        order=facts.order,
        method=facts.name,
        derivative_map=derivative_map,
        q_ndim=Q0.ndim,
        xi_ndim=xi0.ndim,
        solves_per_step=facts.solves_per_step,
        isotropy=isotropy_dimension(system),
    )
