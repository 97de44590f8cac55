r"""The one march: steps of a stepper in `jax.lax.scan`, then the `Solution`.

A step whose solve fails makes the member's state NaN from then on and marks the later steps
`Status.SKIPPED` (`gate`): never plausible-looking numbers. After the steps the stepper says
what the nodes are (`AbstractStepper.nodes`), the nodal velocities are recovered from
Lemma 7's relation at every node (except for degenerate systems), and the overall result and
first failure are found.

Its pieces are modules of their own: the carry a chunk hands the next, the start and one
gated step (`carry`), the energy check (`energy_check`), the first-step check (`first_step`) and
the `Solution` from a march's records (`assemble`); their names are importable from here too.

The march is cut into **chunks** (`run_chunk`): a loop over a fixed number of steps that
hands its carry — the stepper's state and memory, the step number, the failure flag and the
last step velocity — to the next chunk. Called with concrete arguments (and maps that close
over no traced value), `integrate` runs the march as `march_chunked`: one compiled program
for the start and one for a chunk of `chunk_length` steps, whose loop stops at the run's
number of steps (`n_total`, an argument), so a new `n_steps` or `dt` reuses both programs.
Under a JAX transformation (`jit`, `vmap`, `grad`) the march is one `lax.scan` of exactly
`n_steps` steps (`march`), traced into the caller's program. Both assemble the `Solution`
with the same code, on NumPy arrays or traced ones, and the carry is handed over exactly: the
chunked march is the same arithmetic as the single scan. With the energy check both make the
first-step check: the single scan as its first iterations (`run_chunk`'s `first_step_check`:
one copy of the step in the program), the chunked march by a call of its chunk's own program
with dt/2 (`first_step_probe`: nothing compiled for it).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ..core.jit import QUICK_COMPILE, filter_jit
from ..core.manifold_checks import traced_first_step_check
from ..core.validation import any_traced
from ..discrete.legendre import explicit_nodal_velocity
from ..discrete.residual import nodal_residual
from ..roots.status import NewtonStats, Status, skip_stats
from ..steppers.base import AbstractStepper
from .assemble import assemble
from .carry import Carry, Chunk, advance_step, failed_to_nan, gate, input_ok, resume, start
from .energy_check import (
    ENERGY_STEP_RTOL,
    energy_jump,
    energy_rtol,
    energy_terms,
    jump_step,
    node_energies,
    node_energy,
    zero_nan,
)
from .first_step import (
    FIRST_STEP_FLOOR,
    FIRST_STEP_RTOL,
    FirstStepProbe,
    first_step_failed,
    first_step_probe,
    half_steps,
)
from .solution import Solution

__all__ = [
    "march",
    "march_chunked",
    "run_chunk",
    "nodal_velocities",
    "nodal_velocity",
    "chunk_length",
    "start_program",
    "CHUNK_STEPS",
    "CHUNK_VALUES",
    "MIN_CHUNK_STEPS",
    "NATIVE_CHUNK_FACTOR",
    # the march's pieces, defined in carry, energy_check and first_step, importable from here
    "Carry",
    "Chunk",
    "advance_step",
    "start",
    "resume",
    "gate",
    "failed_to_nan",
    "input_ok",
    "energy_terms",
    "node_energy",
    "node_energies",
    "energy_jump",
    "jump_step",
    "zero_nan",
    "ENERGY_STEP_RTOL",
    "FirstStepProbe",
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

NATIVE_CHUNK_FACTOR = 64
"""A chunk of a native march (`clebsch_jax.march.native_chunk`) is this many times
`chunk_length`: its length compiles nothing (the kernel loops over a run-time count), and each
chunk costs the host a fixed amount of work around the kernel's call and a copy of its records
when the chunks are joined (a run of one chunk is not copied). Chunks stay bounded so that a
long run can still be interrupted between them."""


def run_chunk(
    stepper: AbstractStepper,
    system,
    carry: Carry,
    dt,
    length: int,
    n_total,
    check_energy: bool = False,
    exact: bool = False,
    first_step_check: bool = False,
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
      whose solves stop at their first update.

    With `first_step_check` the run's first chunk (`carry.n` 0; with `exact`, the chunk is the
    run) also makes the first-step check's two half steps (`first_step_probe`), by the loop's
    own step with Δt/2 before the chunk's steps, which start again from `carry`: the scan's
    first two iterations (`_scan_steps`), or a first run of the while loop (`_steps_until`) —
    one copy of the step in the program. The node they reach is the chunk's `probe` (`ok`
    False in a chunk that did not make them)."""
    probes = 2 if first_step_check else 0  # the most half steps a chunk of this program makes
    advance = lambda c, h: advance_step(stepper, system, h, c)
    if exact:
        last, (states, outs, stats, valid), probe = _scan_steps(advance, carry, dt, length, probes)
    else:
        # jitted (inlined) so that it is traced once, for the records' shapes and the loop body
        last, (states, outs, stats, valid), probe = _steps_until(
            jax.jit(advance, inline=True), carry, dt, length, n_total, probes
        )
    if probe is not None:  # the half steps' node, read as `first_step_probe` reads it
        probe_states, probe_outs, probe_ok = probe
        half = stepper.nodes(system, carry.state, probe_states, probe_outs)
        probe = FirstStepProbe(half.nodal_Q[2], half.momentum[2], probe_ok)
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
    return last._replace(xi_last=xi_last), Chunk(nodes, stats, xi, nodal, valid, energy, probe)


def _zeros(shapes, lead: tuple = ()):
    """Zero arrays of the shapes and dtypes `shapes` (from `jax.eval_shape`), with the leading
    axes `lead`."""
    return jax.tree_util.tree_map(lambda s: jnp.zeros(lead + s.shape, s.dtype), shapes)


def _where(cond, a, b):
    """`jnp.where(cond, a, b)` leaf by leaf over two pytrees of one structure."""
    return jax.tree_util.tree_map(lambda x, y: jnp.where(cond, x, y), a, b)


def _probe_of(records, probes: int):
    """The half steps' record from a loop's records whose first `probes` rows are theirs: their
    states and outputs, and whether both converged (as `first_step_probe` reads them)."""
    states, outs, stats, _ = jax.tree_util.tree_map(lambda a: a[:probes], records)
    return states, outs, jnp.all(stats.status == Status.SUCCESS)


def _scan_steps(advance, carry: Carry, dt, length: int, probes: int):
    """(last carry, records of `length` steps, half steps' record) as one `lax.scan`, of
    `length + probes` iterations: the first `probes` the first-step check's half steps (Δt/2),
    after which the loop starts again from `carry` (iteration `probes` steps from it); their
    records are the half steps'. (The restart selects the step's input, not the carry a step
    leaves: XLA then fuses the select into the step, a smaller program than a select of
    every carry leaf after it; the iteration count is carried, not scanned over.)"""
    if not probes:
        last, records = jax.lax.scan(lambda c, _: advance(c, dt), carry, None, length=length)
        return last, records, None

    def body(state, _):
        c, j = state
        new, y = advance(_where(j == probes, carry, c), jnp.where(j < probes, dt / 2, dt))
        return (new, j + 1), y

    (last, _), records = jax.lax.scan(body, (carry, jnp.asarray(0, jnp.int32)), None, length=length + probes)
    return last, jax.tree_util.tree_map(lambda a: a[probes:], records), _probe_of(records, probes)


def _steps_until(advance, carry: Carry, dt, length: int, n_total, probes: int = 0):
    """(last carry, outputs of `length` steps, half steps' record) as a scan of `advance` would
    give them, with the steps from `n_total` on not made: their records are zero (`valid`
    False) and their states the last state, which the node after the run's last step (the
    chunk's last node) holds.

    With `probes` (2) the loop runs twice, from `carry` both times: first the first-step
    check's half steps (Δt/2), in a chunk starting the run (`carry.n` 0; none in the others),
    recorded in the first `probes` rows, then the chunk's steps. The loop (one copy of the step
    in the program) is the same as without them: the two runs differ only in their step size,
    where they stop and the row they record at."""
    stop = jnp.minimum(n_total, carry.n + length)
    out0 = _zeros(jax.eval_shape(lambda c: advance(c, dt)[1], carry), (length + probes,))

    def steps(c, row, out, h, until):
        def body(state):
            c, i, out = state
            c, y = advance(c, h)
            return c, i + 1, jax.tree_util.tree_map(lambda o, v: o.at[i].set(v), out, y)

        return jax.lax.while_loop(lambda st: st[0].n < until, body, (c, row, out))

    if not probes:
        last, made, (states, *records) = steps(carry, jnp.asarray(0, jnp.int32), out0, dt, stop)
        probe = None
    else:
        count = jnp.where(carry.n == 0, probes, 0).astype(jnp.int32)

        def run(k, state):  # k = 0: the half steps (rows from 0), k = 1: the chunk's steps (rows from probes)
            out, _, _ = state
            half = k == 0
            row = jnp.where(half, 0, probes).astype(jnp.int32)
            return steps(carry, row, out, jnp.where(half, dt / 2, dt), jnp.where(half, count, stop))[::-1]

        out, made, last = jax.lax.fori_loop(0, 2, run, (out0, jnp.asarray(0, jnp.int32), carry))
        states, outs, ok = _probe_of(out, probes)
        probe = (states, outs, ok & (count > 0))
        states, *records = jax.tree_util.tree_map(lambda a: a[probes:], out)
        made = made - probes
    idle = jnp.arange(length) >= made
    states = jax.tree_util.tree_map(
        lambda a, s: jnp.where(idle.reshape((-1,) + (1,) * s.ndim), s, a), states, last.state
    )
    return last, (states, *records), probe


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
    check_energy: bool | float = False,
    check_inputs: bool = False,
    march_state: Carry | None = None,
) -> Solution:
    """Run `stepper` (prepared for `system`) for `n_steps` steps of size `dt` from
    $(Q^0, \\xi^0)$ (and $P^0$, if not None) in one scan and assemble the `Solution`. With
    `check_energy` (True or a tolerance, `energy_rtol`) a step whose energy jumps fails
    (`Status.ENERGY_JUMP`); with `check_inputs`
    an invalid input fails step 0 (`Status.INVALID_INPUT`: `input_ok`). With `march_state`
    (the `Carry` a march ended with, `Solution.march_state`) the march continues from it
    (`resume`) instead of starting."""
    rtol = energy_rtol(check_energy)
    carry, startup, n_total = resume(stepper, system, Q0, xi0, P0, dt, check_inputs, march_state, n_steps)
    probe = rtol is not None and march_state is None  # the first-step check, in the scan's first iterations
    last, chunk = run_chunk(
        stepper, system, carry, dt, n_steps, n_total, rtol is not None, exact=True, first_step_check=probe
    )
    # `integrate`'s check of the first step on the manifold, which cannot raise on traced values
    leaves = traced_first_step_check(system, Q0, xi0) if chunk.nodes.Q is not None else None
    off = None if leaves is None else leaves(chunk.nodes.Q[0], chunk.nodes.Q[1])
    sol = assemble(
        jnp,
        stepper,
        system,
        [chunk],
        n_steps,
        startup,
        dt,
        t0,
        Q0,
        xi0,
        carry.alive,
        probe=chunk.probe,
        energy_rtol=rtol,
        off_manifold=off,
    )
    return dataclasses.replace(sol, march_state=last)


_PROGRAMS = {
    quick: (
        filter_jit(start, compiler_options=QUICK_COMPILE if quick else None),
        filter_jit(run_chunk, compiler_options=QUICK_COMPILE if quick else None),
    )
    for quick in (False, True)
}
"""The compiled start and chunk of `march_chunked`, by the stepper's `quick_compile`."""


def start_program(stepper: AbstractStepper):
    """The compiled `start` of `march_chunked` for this stepper (by its `quick_compile`)."""
    return _PROGRAMS[bool(stepper.quick_compile)][0]


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
    check_energy: bool | float = False,
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

    rtol = energy_rtol(check_energy)
    check_energy = rtol is not None  # the programs see whether, the assembly how much
    start_jit, chunk_jit = _PROGRAMS[bool(stepper.quick_compile)]
    probe = None
    if march_state is None:
        carry, startup = start_jit(stepper, system, Q0, xi0, P0, dt)
    else:
        carry = march_state
    native = native_chunk_program(stepper, system, carry, dt, check_energy, backend)
    if chunk_steps is None:  # a native chunk costs no compile per step: longer chunks, less host work
        chunk_steps = chunk_length(Q0, xi0) * (NATIVE_CHUNK_FACTOR if native is not None else 1)
    # the first-step check of a concrete march: a call of the chunk's own program with dt/2
    # (`first_step_probe`: nothing compiled for it); a traced `march` makes its half steps in its
    # scan's first iterations instead (`run_chunk`'s `first_step_check`)
    if native is not None:
        chunk_jit = native
    if march_state is None:
        if check_energy and n_steps > 0:
            probe = first_step_probe(chunk_jit, stepper, system, carry, dt, chunk_steps, check_energy)
        total = np.asarray(n_steps, np.int32)  # a NumPy scalar: no conversion program
    else:  # a continued march: its first step is not a run's first step (it has its guesses)
        carry, startup = march_state, np.zeros((), np.int32)
        total = np.asarray(np.asarray(carry.n) + n_steps, np.int32)
    if native is not None:  # the chunks write their records into the run's arrays: no join
        carry, chunks = native.run(stepper, system, carry, dt, chunk_steps, total, check_energy, n_steps)
    else:
        chunks = []
        for _ in range(-(-n_steps // chunk_steps)):
            carry, chunk = chunk_jit(stepper, system, carry, dt, chunk_steps, total, check_energy)
            chunks.append(chunk)
    if any_traced(chunks, startup, probe):
        # a function the map checks do not call closed over a traced value (the caller is
        # inside jit/vmap; integrate sends maps that close over one to `march`)
        sol = assemble(jnp, stepper, system, chunks, n_steps, startup, dt, t0, Q0, xi0, probe=probe, energy_rtol=rtol)
        return dataclasses.replace(sol, march_state=carry)
    chunks, startup, dt, t0, probe = jax.tree_util.tree_map(np.asarray, (chunks, startup, dt, t0, probe))
    sol = assemble(np, stepper, system, chunks, n_steps, startup, dt, t0, Q0, xi0, probe=probe, energy_rtol=rtol)
    sol, carry = jax.device_put((sol, carry))  # one transfer of all the leaves
    return dataclasses.replace(sol, march_state=carry)
