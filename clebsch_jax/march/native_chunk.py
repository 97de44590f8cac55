r"""A chunk of `integrate`'s march as a native loop kernel (`clebsch_jax.native.compile_loop`).

On XLA a chunk (`run_chunk`) is a `lax.while_loop` of the step (`advance_step`) writing each
step's record, then the nodes, their nodal velocities and energies, vectorised over the chunk's
nodes; XLA's CPU runtime charges each operation of the loop's body microseconds, whatever its
size. Here the whole chunk is one call of a kernel compiled with LLVM from one iteration's
jaxpr (`_stream_body`): the step, and the node it leaves — its configuration and momentum
(`stepper.nodes`), its nodal velocity from the seed `run_chunk` gives it (`nodal_velocity`), its
energy — with the carry in registers and every iteration's records stored to the chunk's
arrays. One more iteration, which makes no step, gives the chunk's last node. The host takes the
records as the kernel writes them, those of the steps made (`native_run_chunk`).

`native_run_chunk` has `run_chunk`'s signature and results (without the padding of a chunk's
steps not made, which `assemble` drops), so `march_chunked` and its first-step check (`first_step_probe`, which XLA's chunk makes in its loop instead) run it in place of the XLA chunk: the same steps, statuses,
Newton statistics and failure handling; the values differ from XLA's only where XLA's own
transcendental functions or contractions round differently from libm's (the tests compare them
to 1e-12).

A single trajectory is one member: the kernel is compiled with one lane (`LANES`).
"""

from __future__ import annotations

import threading
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..core.jit import undifferentiated
from ..core.validation import any_traced, is_array
from ..roots.status import NewtonStats, Status, skip_stats
from ..steppers.base import AbstractStepper, Nodes
from .carry import Carry, Chunk, advance_step
from .energy_check import node_energy
from .scan import nodal_velocity

__all__ = [
    "LANES",
    "native_run_chunk",
    "run_members",
    "member_chunks",
    "native_loop",
    "native_chunk_program",
    "BoundLoop",
    "NativeChunks",
]

LANES = 1
"""Lanes of the kernel of one trajectory: a single member in a vector of one lane. Wider
vectors would only repeat it in the other lanes, with the same instructions: the libm calls
(sin, cos, …) and the records' stores are made once per lane."""

_LOOPS: dict = {}
_LOOPS_LOCK = threading.Lock()
_LOOPS_MAX = 32


class _Dynamic:
    """The place of an array leaf in a static description of a pytree's leaves."""


_DYNAMIC = _Dynamic()


def _split(tree):
    """(treedef, static leaves with `_DYNAMIC` for each array, the arrays on the host)."""
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    static = tuple(_DYNAMIC if is_array(x) else x for x in leaves)
    return treedef, static, [np.asarray(x) for x in leaves if is_array(x)]


def _aval(x) -> tuple:
    return np.shape(x), np.asarray(x).dtype


def _finite(a):
    return jnp.all(jnp.isfinite(a))


def _stream_body(stepper: AbstractStepper, check_energy: bool, system, dt, stop, loop):
    """Iteration k of a chunk's loop: step k (`advance_step`) while the run has steps left
    (`loop` carry's n < `stop`), and the node it leaves — its configuration and momentum from the
    state before the step (`stepper.nodes`), its velocity solved from the seed `run_chunk`
    gives it (the velocity of the step leaving it, else of the step arriving at it), its energy.
    The iteration after the last step (k = steps made) makes no step: its node is the chunk's
    last, seeded with the last step's velocity. Returns ((carry, arriving velocity), records)."""
    c, arriving = loop
    do_step = c.n < stop
    new, (state, out, stats, _) = advance_step(stepper, system, dt, c)
    one = lambda tree: jax.tree_util.tree_map(lambda a: a[None], tree)
    nodes = stepper.nodes(system, c.state, one(state), one(out))
    leaving = jnp.where(do_step, jnp.where(c.n == 0, nodes.xi_seed, nodes.xi_step[0]), jnp.nan)
    arriving = jnp.where(c.n == 0, nodes.xi_seed, arriving)  # at the run's first node: the given ξ⁰
    guess = jnp.where(_finite(leaving), leaving, arriving)
    at = lambda a: None if a is None else a[0]
    if system.degenerate:  # as run_chunk: no nodal velocity, statistics of a skipped solve
        xi, energy = None, None
        zero = jnp.zeros((), jnp.int32)
        nodal = skip_stats(
            NewtonStats(zero, jnp.zeros((), dt.dtype), jnp.asarray(Status.SUCCESS, jnp.int32), zero), c.alive
        )
    else:
        xi, nodal = nodal_velocity(system, stepper.nodal_solver, nodes.nodal_Q[0], nodes.momentum[0], guess, c.alive)
        energy = node_energy(system, nodes.nodal_Q[0], xi) if check_energy else None
    keep = lambda a, b: jnp.where(do_step, a, b)
    records = dict(
        stats=stats,
        xi_step=nodes.xi_step[0],
        P=at(nodes.P),
        Q=at(nodes.Q),
        p=at(nodes.p),
        momentum=nodes.momentum[0],
        # the configuration again where the stepper's nodal configuration is it (a reduced
        # march that carries Q): not stored twice, `_chunk_of` hands on `Q`'s records
        nodal_Q=None if nodes.nodal_Q is nodes.Q else nodes.nodal_Q[0],
        xi=xi,
        nodal=nodal,
        valid=c.alive,
        energy=energy,
    )
    return (jax.tree_util.tree_map(keep, new, c), keep(nodes.xi_step[0], arriving)), records


def native_loop(
    stepper: AbstractStepper, system, carry: Carry, dt, check_energy: bool, max_lines=None, width: int = LANES
):
    """The native loop kernel of `_stream_body` for this stepper, system structure, shapes and
    energy check (compiled once per process, from the disk cache when another process compiled
    it), and the system's and Δt's arrays it takes. Raises `clebsch_jax.native.Unsupported`
    (and remembers it) for a step the translation does not cover, or, with `max_lines`, whose
    kernel would be larger; a refusal for its size is remembered on disk too, under the
    fingerprint of the stepper and the system's structure (`clebsch_jax.native.TooLarge`), so
    that a new process does not trace the step again. `width`: members per vector (`LANES` for
    one trajectory; the host's lanes for several marched together, `clebsch_jax.march.members`)."""
    from ..native import compile_loop, compiled_once

    treedef, static, arrays = _split((system, dt))
    loop = (jax.tree_util.tree_map(np.asarray, carry), np.asarray(carry.xi_last))
    key = (
        stepper,
        bool(check_energy),
        treedef,
        static,
        tuple(_aval(a) for a in arrays),
        jax.tree_util.tree_structure(loop),
        tuple(_aval(a) for a in jax.tree_util.tree_leaves(loop)),
        max_lines,
        width,
    )

    def body(dynamic, stop, c):
        it = iter(dynamic)
        leaves = [next(it) if s is _DYNAMIC else s for s in static]
        sys_, dt_ = jax.tree_util.tree_unflatten(treedef, leaves)
        with undifferentiated():  # the march's values are not differentiated here
            return _stream_body(stepper, check_energy, sys_, dt_, stop, c)

    def compile():
        # what the body is made from, under which a refusal for its size is kept on disk
        # (the arrays' shapes and dtypes are added to it by `compile_loop`)
        from ..native.fingerprint import fingerprint

        disk = fingerprint(("integrate-loop", stepper, bool(check_energy), treedef, static))
        return compile_loop(body, arrays, np.zeros((), np.int32), loop, width=width, max_lines=max_lines, key=disk)

    found = compiled_once(_LOOPS, _LOOPS_LOCK, _LOOPS_MAX, key, compile)
    return found, arrays


class BoundLoop(NamedTuple):
    """The kernel `native_loop` found for a march (`native_chunk_program`) and the host arrays of
    its system and Δt: the march's chunks and its first-step probe (Δt/2) take them instead of
    looking the kernel up again, which flattens and hashes the system and the carry each time.
    The carry they pass is the march's start or the kernel's own, of the shapes it was found for."""

    stepper: AbstractStepper
    system: object
    kernel: object
    arrays: list
    dt_aval: tuple
    check_energy: bool

    def takes(self, stepper, system, dt, check_energy: bool) -> bool:
        """Whether a chunk of `stepper` on `system` with this `dt` and energy check runs this
        kernel: the same stepper and system objects, a Δt array of the shape and dtype it was
        found for (Δt is the last of `arrays`, after the system's) and the same energy check."""
        return (
            stepper is self.stepper
            and system is self.system
            and bool(check_energy) == self.check_energy
            and is_array(dt)
            and _aval(dt) == self.dt_aval
        )


def native_run_chunk(
    stepper: AbstractStepper,
    system,
    carry: Carry,
    dt,
    length: int,
    n_total,
    check_energy: bool = False,
    max_lines=None,
    bound: "BoundLoop | None" = None,
    into=None,
) -> tuple[Carry, Chunk]:
    """`run_chunk` (concrete values, `exact=False`) as one call of the native kernel
    (`native_loop`, with its `max_lines`; or `bound`'s, when it was found for this stepper and
    system, `BoundLoop.takes`): the steps from `carry.n` up to `n_total` (at most `length`) and
    the nodes they leave, then the chunk's last node, in one loop (host arrays).

    The records are those of the steps made alone, as the kernel writes them: `made` step
    entries and `made + 1` node entries, the last the chunk's last node (`run_chunk`'s entry
    `length`). `run_chunk` pads them to `length` (the steps not made zero, the nodes past the
    last one repeating it, their solves skipped), which `assemble` cuts off again: every chunk
    of a run but its last makes `length` steps, and of the last it keeps the steps made and
    the last node. The first-step check (`first_step_probe`) reads the first two steps.
    `into` (rows, start): the kernel writes its records into records start, start + 1, … of a
    run's rows (`NativeLoop.record_rows`, `NativeChunks.run`) instead of new arrays."""
    kernel, arrays = _kernel_of(stepper, system, carry, dt, check_energy, max_lines, bound)
    n = int(np.asarray(carry.n))
    made = int(np.clip(int(np.asarray(n_total)) - n, 0, length))
    host = jax.tree_util.tree_map(lambda a: np.asarray(a)[None], carry)
    records = None if into is None else kernel.record_views(into[0], into[1], into[1] + made + 1)
    last, rec = run_members(kernel, [a[None] for a in arrays], host, made, records)
    first = lambda tree: jax.tree_util.tree_map(lambda a: a[0], tree)
    return first(last), _chunk_of(first(rec), made)


def run_members(kernel, arrays: list, carry: Carry, made: int, records=None):
    """`made` steps of B members' marches from `carry` (host leaves with a leading member axis,
    every member at the same step), `arrays` the members' system and Δt arrays (a leading
    member axis too), and the node each leaves, then the last node: one call of the loop
    kernel, the members in its lanes. Returns (the carries after them, `xi_last` the last
    step's velocity; the records, (B, made + 1, …) leaves)."""
    B = int(np.shape(carry.n)[0])
    stop = np.full(B, int(np.asarray(carry.n)[0]) + made, np.int32)
    (last, _), rec = kernel(
        arrays, stop, (carry, np.asarray(carry.xi_last)), steps=made + 1, capacity=made + 1, records=records
    )
    xi_last = rec["xi_step"][:, made - 1] if made > 0 else np.asarray(carry.xi_last)
    return last._replace(xi_last=xi_last), rec


def member_chunks(records, made: int) -> list:
    """Each member's `Chunk` of `made` steps from `run_members`' records (a leading member axis)."""
    return [_chunk_of(jax.tree_util.tree_map(lambda a, m=m: a[m], records), made) for m in range(len(records["valid"]))]


def _kernel_of(stepper, system, carry, dt, check_energy, max_lines, bound):
    """The kernel of a chunk and its arrays (the system's and Δt's): `bound`'s when it takes
    these, else `native_loop`'s."""
    if bound is not None and bound.takes(stepper, system, dt, check_energy):
        return bound.kernel, [*bound.arrays[:-1], np.asarray(dt)]
    return native_loop(stepper, system, carry, dt, check_energy, max_lines)


def _chunk_of(rec: dict, made: int) -> Chunk:
    """The `Chunk` of `made` steps' records (`made + 1` entries each, as the kernel writes them:
    the last iteration made no step, its step entries are dropped)."""
    steps = lambda a: None if a is None else a[:made]
    nodes = Nodes(
        Q=rec["Q"],
        p=rec["p"],
        P=steps(rec["P"]),
        momentum=rec["momentum"],
        xi_step=steps(rec["xi_step"]),
        nodal_Q=rec["Q"] if rec["nodal_Q"] is None else rec["nodal_Q"],
        xi_seed=None,
    )
    stats = NewtonStats(*(steps(x) for x in rec["stats"]))
    return Chunk(nodes, stats, rec["xi"], rec["nodal"], rec["valid"], rec["energy"])


class NativeChunks(NamedTuple):
    """`native_chunk_program`'s chunk program: called, one chunk (`native_run_chunk`, the
    signature of XLA's `run_chunk`; the first-step check calls it so); `run`, all the chunks of
    a march, written in place into the run's arrays."""

    bound: BoundLoop
    max_lines: object

    def __call__(self, stepper, system, carry, dt, length, n_total, check_energy=False):
        return native_run_chunk(stepper, system, carry, dt, length, n_total, check_energy, self.max_lines, self.bound)

    def run(self, stepper, system, carry: Carry, dt, length: int, n_total, check_energy: bool, n_steps: int):
        """The march's `n_steps` steps from `carry` (up to `n_total`) in chunks of `length`, as
        `march_chunked`'s loop of chunks makes them, but the kernel writes every chunk's records
        into one set of the run's rows (`NativeLoop.record_rows`: aligned, so that
        `jax.device_put` takes them without a copy): returns (the carry, [one `Chunk` of all the
        records]), which `assemble` reads without joining (a copy). A chunk's last node is the
        next chunk's first, written again by it, as `assemble` joins them."""
        if n_steps <= 0:
            return carry, []
        kernel = _kernel_of(stepper, system, carry, dt, check_energy, self.max_lines, self.bound)[0]
        rows, start = kernel.record_rows(n_steps + 1), 0
        for _ in range(-(-n_steps // length)):
            carry, chunk = native_run_chunk(
                stepper, system, carry, dt, length, n_total, check_energy, self.max_lines, self.bound, (rows, start)
            )
            start += chunk.stats.status.shape[0]
        records = _chunk_of(kernel.records(rows, start + 1), start)
        kernel.keep_rows(rows)  # for the next run, once this one's Solution is let go
        return carry, [records]


def native_chunk_program(
    stepper: AbstractStepper, system, carry: Carry, dt, check_energy: bool, backend: str, width: int = LANES
):
    """The chunk program of a concrete march for `backend` ("auto", "native" or "xla"):
    `native_run_chunk` where the native kernel applies, else None (XLA's `run_chunk`).
    `"auto"` says once why not (`clebsch_jax.native.warn_once`, a `NativeFallbackWarning`
    naming the reason: llvmlite missing, a primitive the translation does not cover, a kernel
    past `AUTO_MAX_IR_LINES`); `"native"` raises a `ValueError` with the reason."""
    if backend == "xla":
        return None
    from ..native import AUTO_MAX_IR_LINES, Unsupported, native_unavailable, warn_once

    why = native_unavailable()
    if why is None and any_traced(system, carry, dt):
        why = "a map closes over a value traced by the caller"
    if why is None:
        limit = AUTO_MAX_IR_LINES if backend == "auto" else None
        try:
            kernel, arrays = native_loop(stepper, system, carry, dt, check_energy, limit, width)
            bound = BoundLoop(stepper, system, kernel, arrays, _aval(dt), bool(check_energy))
            return NativeChunks(bound, limit)
        except Unsupported as err:
            why = f"the native translation does not cover the step: {err}"
    if backend == "native":
        raise ValueError(f"backend='native': {why}.")
    warn_once(why, what="integrate's march", stacklevel=4)
    return None
