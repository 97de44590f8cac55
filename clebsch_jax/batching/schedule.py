r"""A sweep's schedule: batches on devices and threads, chunk by chunk, with reruns and progress.

`run_batches` is the one function behind an in-process sweep, a stored one and a Dask task. It
runs batches in one of two ways. Native kernels that report no progress: each of the host
threads (kept from call to call, `workers`) takes the next batch no thread has taken, marches it
through every chunk and writes its rows. Otherwise a group of batches (one per device and
thread) is marched side by side through every chunk, each chunk by the backend the plan chose —
a native kernel call (`clebsch_jax.batching.chunks_native`) or XLA's programs
(`clebsch_jax.batching.chunks_xla`), whose fast path reruns the members whose check failed on
the general path — with progress reported after each.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import os
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, NamedTuple

import jax
import numpy as np

from ..core.jit import QUICK_COMPILE, jit_with_options, memo
from ..core.validation import positive_int
from ..native.layout import Workspace
from . import chunks_xla, tables
from .chunks_native import native_call, native_program_of
from .config import Carry, Config, Members, Run
from .probe import Shapes
from .tables import SweepProgress, Tables, allocate_tables


FAST_GIVE_UP = 2
"""A batch in which at least half the members' checks failed in this many fast-path calls in a
row (a call covers a chunk, or `LEAN_CHUNKS` for the lean chunk) runs its remaining chunks on
the general path directly (the table is the same: a member whose check failed is run again by
the general path anyway): the fast path does not suit its march — e.g. a Lagrangian that is not
quadratic in ξ, whose nodal relation the lean chunk's two fixed updates do not solve to
round-off, or steps too large for them — and trying each chunk twice would make the sweep
slower than `fast=False`. A call in which fewer members failed reruns only those
(`FALLBACK_BATCH`) and keeps the fast path."""

FALLBACK_BATCH = 256
"""Members per call of the general path where it reruns the members whose fast-path check
failed in a call (gathered from the batch, the last group padded with copies of its last
member; at most the batch size): a few hard members — fast rotations, steps too large for the
fixed updates — then cost the general path's time for themselves only, not for their whole
batch, and every rerun compiles the same program. General batches of this size run at the
general path's full rate (`benchmarks/throughput.py --sweep-only`)."""

LEAN_CHUNKS = 4
"""Chunks of `chunk_steps` steps per call of the lean chunk, at most (`_calls`): its start and
end (the momentum map, node 0's velocity, the warm-up steps, the cotangent P of the last node)
are then paid once per that many chunks."""

THREADS_MAX = 2
"""`sweep`'s default `threads`: the CPU cores the process may use, at most this many (measured
on a 2-core host, `benchmarks/README.md`; more threads on more cores are the caller's choice)."""

THREAD_MIN_MEMBERS = 256
"""... and only as many threads as give each a batch of at least this many members (a smaller
sweep runs as before: its batches gain little from running side by side)."""


def thread_count(threads, devices: list, B: int) -> int:
    """Host threads per device (`sweep`'s `threads`): the given number, or by default the CPU
    cores this process may use, at most `THREADS_MAX`, shared by the devices, for CPU devices
    (1 for others: an accelerator runs its queue in order) — and never more than give each
    thread a batch of `THREAD_MIN_MEMBERS` members."""
    if threads is not None:
        return positive_int(threads, "threads")
    if any(d is not None and d.platform != "cpu" for d in devices) or (
        devices == [None] and jax.default_backend() != "cpu"
    ):
        return 1
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on every platform
        cores = os.cpu_count() or 1
    per_device = max(1, min(THREADS_MAX, cores) // len(devices))
    return max(1, min(per_device, B // (len(devices) * THREAD_MIN_MEMBERS)))


@dataclasses.dataclass
class Batch:
    """One batch on its device: its members' inputs and the carry handed from chunk to chunk."""

    index: int
    rows: slice  # its members' rows of the table (without the padding)
    n_real: int  # members that are not padding
    params: object
    dt: jax.Array
    shared: list | None
    carry: Carry
    fallbacks_in_a_row: int = 0  # fast chunks of this batch rerun by the general path, the last ones


def start_batch(cfg: Config, members: Members, shapes: Shapes, b: int, batch_size: int, device) -> Batch:
    """Batch b on `device` (None: JAX's default placement); the last batch is padded with copies
    of the last member."""
    member = np.minimum(np.arange(b * batch_size, (b + 1) * batch_size), members.B - 1)
    rows = batch_rows(b, batch_size, members.B)
    ic = members.ic_index[member]
    # host arrays moved to the device as they are: a transfer each, no JAX operation to compile;
    # a native kernel reads host arrays, so they stay there, as views where they can: the
    # kernel's call lays them out in its own rows (`clebsch_jax.native.layout`) and writes
    # none of them, so a batch of consecutive rows takes views of them and its zeros are one
    # entry broadcast (no copy, and no fresh memory for a carry its first chunk replaces)
    # (leaf by leaf: np.asarray of a tuple of parameter arrays would stack them into one array)
    if cfg.native:
        put, take, fill = _host, _host_rows, _broadcast
    else:
        put = functools.partial(_on_device, device)
        take, fill = (lambda a, idx: a[idx]), np.full
    params = None if members.builder is None else put(_rows(take, members.params, members.param_index[member]))
    Q, xi = put(take(members.Q0, ic)), put(take(members.xi0, ic))
    shared = None if members.shared is None else put(members.shared)
    # without P0, a placeholder that the first chunk's program replaces (`chunks_xla._with_start_P`)
    P = put(
        fill((len(ic),) + members.Q0.shape[1:], 0, members.Q0.dtype) if members.P0 is None else take(members.P0, ic)
    )
    zeros = lambda shape, dtype=np.float64: put(fill((batch_size,) + shape, 0, dtype))
    carry = Carry(
        Q=Q,
        P=P,
        xi=xi,
        t=zeros(()),
        status=zeros((), np.int32),
        failed_step=put(fill((batch_size,), -1, np.int32)),
        iterations=zeros((), np.int64),
        max_residual=zeros(()),
        initial={k: zeros(v.shape[1:], v.dtype) for k, v in shapes.invariants.items()},
        drift={k: zeros(()) for k in shapes.invariants},
        momentum=zeros(shapes.xi),
        final_xi=zeros(shapes.xi) if shapes.has_xi else None,
        energy_change=zeros(()),
        energy_size=zeros(()),
        march=None if shapes.march is None else jax.tree_util.tree_map(lambda s: zeros(s.shape, s.dtype), shapes.march),
        march_ok=None if shapes.march is None else zeros((), bool),
        gauge=None if cfg.isotropy is None else zeros(()),
    )
    return Batch(b, rows, rows.stop - rows.start, params, put(take(members.dt, member)), shared, carry)


def _rows(take, tree, idx):
    return jax.tree_util.tree_map(lambda a: take(a, idx), tree)


def _host(tree):
    return jax.tree_util.tree_map(np.asarray, tree)


def _on_device(device, tree):
    return jax.tree_util.tree_map(functools.partial(jax.device_put, device=device), tree)


def _host_rows(a, idx: np.ndarray):
    """`a[idx]`, a view where `idx` is a run of consecutive rows (no padding) or `a` repeats one row."""
    n = len(idx)
    a = np.asarray(a)
    if n and a.ndim and len(a) and a.strides[0] == 0:
        return np.broadcast_to(a[:1], (n,) + a.shape[1:])
    if n and np.array_equal(idx, np.arange(idx[0], idx[0] + n)):
        return a[int(idx[0]) : int(idx[0]) + n]
    return a[idx]


def _broadcast(shape: tuple, value, dtype) -> np.ndarray:
    """A read-only array of `shape` filled with `value`: one entry broadcast, one view for every batch."""
    make = lambda: np.broadcast_to(np.asarray(value, dtype), shape)  # noqa: E731
    return memo(_BROADCASTS, (shape, value, np.dtype(dtype).str), make, 256)


def batch_rows(b: int, batch_size: int, B: int) -> slice:
    """The rows of the sweep's table that batch b's members fill (its padding has none)."""
    return slice(b * batch_size, min((b + 1) * batch_size, B))


def _calls(run: Run, lean: bool) -> list:
    """The chunks of `run.chunks` that each call of the fast path covers: one each, or for the
    lean chunk up to `LEAN_CHUNKS` consecutive full chunks — as many as divide their number, so
    that every call but a short last chunk's has the same length (one compiled program)."""
    full = [c for c in run.chunks if c[1] == run.chunk_steps]
    rest = [[c] for c in run.chunks[len(full) :]]
    per = max(d for d in range(1, LEAN_CHUNKS + 1) if len(full) % d == 0) if lean else 1
    return [full[i : i + per] for i in range(0, len(full), per)] + rest


def _general_chunks(cfg: Config, run: Run, one: Batch, chunks: list, saved: dict | None):
    """The general path over `chunks` from the batch's carry (dispatched, not waited for): the
    new carry; each chunk's saved nodes go to `saved`."""
    carry = one.carry
    for st, n in chunks:
        carry, chunk_saved = chunks_xla.run_chunk(_steps(cfg, run, n), one.params, carry, one.dt, one.shared, *_at(st))
        _save(saved, run, one, st, n, chunk_saved)
    return carry


@functools.partial(jit_with_options, compiler_options=QUICK_COMPILE)
def _take_members(tree, idx):
    """The rows `idx` of every leaf of a batch's pytree (params, dt, carry)."""
    return jax.tree_util.tree_map(lambda a: a[idx], tree)


@functools.partial(jit_with_options, compiler_options=QUICK_COMPILE)
def _put_members(tree, idx, rows):
    """`tree` with its rows `idx` replaced by `rows`; an index past the end (padding) is dropped."""
    return jax.tree_util.tree_map(lambda a, r: a.at[idx].set(r, mode="drop"), tree, rows)


def _rerun(cfg: Config, run: Run, one: Batch, chunks: list, saved: dict | None, members: np.ndarray, carry):
    """The general path over `chunks` from the batch's carry for its `members` (indices of real
    members), in groups of `FALLBACK_BATCH`: `carry` (the fast path's new carry) with those
    members' rows replaced by the general path's; their saved nodes go to `saved`. All the
    batch's members in one group: the batch itself, as `_general_chunks`."""
    size = min(FALLBACK_BATCH, len(one.dt))
    if len(members) == one.n_real and size == len(one.dt):
        return _general_chunks(cfg, run, one, chunks, saved)
    table_rows = np.arange(one.rows.start, one.rows.stop)
    for g in range(0, len(members), size):
        part = members[g : g + size]
        pad = size - len(part)
        take = np.concatenate([part, np.full(pad, part[-1])]).astype(np.int32)
        params, dt, start = _take_members((one.params, one.dt, one.carry), take)
        sub = Batch(one.index, table_rows[part], len(part), params, dt, one.shared, start)
        new = _general_chunks(cfg, run, sub, chunks, saved)
        put = np.concatenate([part, np.full(pad, len(one.dt))]).astype(np.int32)  # padding: dropped
        carry = _put_members(carry, put, new)
    return carry


def _steps(cfg: Config, run: Run, n: int) -> Config:
    """`cfg` for a call of n steps (the same object for the run's chunk length)."""
    return cfg if n == run.chunk_steps else dataclasses.replace(cfg, n=n)


def _at(st: int):
    """A chunk's (first, offset) arguments: host values, so no eager JAX operation."""
    return np.asarray(st == 0), np.asarray(st, np.int32)


def _save(saved: dict | None, run: Run, one: Batch, st: int, n: int, chunk_saved):
    """A chunk's saved nodes into the batch's rows of `saved` (`one.rows`: a slice, or the
    table rows of a rerun's members)."""
    if saved is None:
        return
    k0, kn = st // run.save_every, len(range(0, n, run.save_every))
    for key in ("t", "Q", "xi", "momentum"):
        if saved[key] is not None:
            saved[key][one.rows, k0 : k0 + kn] = np.asarray(chunk_saved[key])[: one.n_real]


def _run_chunks(cfg: Config, group: list, run: Run, saved: dict | None, report: Callable, fell_back: list):
    """March a group of batches (one per device and thread, side by side) through every chunk:
    each batch's carry moves on, the chunks' saved nodes go to `saved`, each fast-path call's
    (chunks, members rerun) to `fell_back`, `report(group, step)` follows each call.

    A call of the fast path covers one chunk, or `LEAN_CHUNKS` for the lean chunk (which
    records nothing, so its length costs no memory, and its work at the start and end of a call
    is then shared by more steps); the members whose check failed in it are run again by the
    general path, chunk by chunk from the call's start (`_rerun`). Each batch of a group is
    called from a host thread of its own (`sweep`'s `threads`): one thread would run the
    programs it gives one device one after the other."""
    pool = ThreadPoolExecutor(len(group), thread_name_prefix="clebsch-jax-sweep") if len(group) > 1 else None
    # the caller's default device (`jax.default_device`, a context of the calling thread) holds
    # in the pool's threads too: the batches were placed there
    default = jax.config.jax_default_device

    def in_context(call, one):
        if default is None:
            return call(one)
        with jax.default_device(default):
            return call(one)

    try:
        for chunks in _calls(run, cfg.lean):
            st, n = chunks[0][0], sum(k for _, k in chunks)
            c = _steps(cfg, run, n)
            call = functools.partial(_call, cfg, c, run, chunks, st, n, saved, pool is not None)
            done = list(pool.map(functools.partial(in_context, call), group)) if pool is not None else [call(group[0])]
            fell_back.extend(d for d in done if d is not None)
            report(group, st + n)
    finally:
        if pool is not None:
            pool.shutdown()


def _call(cfg: Config, c: Config, run: Run, chunks: list, st: int, n: int, saved: dict | None, wait: bool, one: Batch):
    """One call of `_run_chunks` for one batch: the fast call (`c`: its chunk's configuration),
    then the general path for the members whose check failed; a batch in which most members
    failed `FAST_GIVE_UP` times in a row runs the general chunks directly. `wait`: return only
    when the general path's programs have run (called from a thread of a group: the group's
    batches then run side by side; a batch alone dispatches them and goes on). Returns the
    fast call's (chunks, members rerun), or None without one."""
    if cfg.native:
        one.carry = native_call(c, one, st)
        return None
    if cfg.fast_method is None or one.fallbacks_in_a_row >= FAST_GIVE_UP:
        # the general path: for every batch without a fast method, or given up
        one.carry = (
            _general_chunks(cfg, run, one, chunks, saved)
            if cfg.fast_method is None
            else _rerun(cfg, run, one, chunks, saved, np.arange(one.n_real), one.carry)
        )
        if wait:
            jax.block_until_ready(one.carry)
        return None
    f = chunks_xla.run_fast_chunk(c, one.params, one.carry, one.dt, one.shared, *_at(st))
    failed = np.flatnonzero(~np.asarray(jax.device_get(f[2]))[: one.n_real])
    _save(saved, run, one, st, n, f[1])  # a rerun member's rows are written again by `_rerun`
    one.carry = _rerun(cfg, run, one, chunks, saved, failed, f[0]) if failed.size else f[0]
    one.fallbacks_in_a_row = one.fallbacks_in_a_row + 1 if 2 * failed.size >= one.n_real else 0
    return len(chunks), failed.size


def reporter(progress, n_batches: int, n_steps: int, B: int, batch_size: int) -> Callable:
    """`report(group, step)` after each chunk: nothing (progress False), a line on stderr (True),
    or a `SweepProgress` to the callable. Reporting waits for the chunk to finish."""
    start_time = time.perf_counter()
    if progress is False:
        silent = lambda group, step: None  # noqa: E731
        silent.silent = True  # the schedule need not wait for a group's chunks to report them
        return silent

    def report(group, step):
        jax.block_until_ready([one.carry for one in group])
        done = group[0].index * batch_size + (sum(one.n_real for one in group) if step == n_steps else 0)
        info = SweepProgress(
            group[-1].index, n_batches, step, n_steps, min(done, B), B, time.perf_counter() - start_time
        )
        if progress is True:
            print(
                f"\rsweep: batch {info.batch + 1}/{n_batches}, step {step}/{n_steps}, "
                f"{info.members_done}/{B} members done, {info.elapsed:.1f} s",
                end="",
                file=sys.stderr,
                flush=True,
            )
        else:
            progress(info)

    return report


class Plan(NamedTuple):
    """Everything a batch needs, built once by `sweep` (and sent once to each Dask worker)."""

    cfg: Config
    members: Members
    shapes: Shapes
    run: Run  # with progress False and devices [None]
    batch_size: int

    @property
    def n_batches(self) -> int:
        """The number of batches: the last one may be short (it is padded when it runs)."""
        return -(-self.members.B // self.batch_size)

    def rows(self, b: int) -> slice:
        """Batch b's rows of the sweep's table (`batch_rows`)."""
        return batch_rows(b, self.batch_size, self.members.B)

    def size(self, b: int) -> int:
        """Batch b's number of members (its padding not counted)."""
        rows = self.rows(b)
        return rows.stop - rows.start


class Rows(NamedTuple):
    """The table rows of some batches: `tables` holds them one after the other, or at `rows` when
    it is the sweep's own table (`run_batches`'s `table`)."""

    batches: list  # batch indices
    rows: list  # each batch's rows of the sweep's table (slices)
    tables: Tables
    devices: set  # the devices they ran on
    fast_chunks: tuple = (0, 0, 0)  # chunks run by the fast path, those with members rerun by the
    # general one, and the (member, chunk) pairs rerun


def run_batches(plan: Plan, batches: list, devices: list, report: Callable, table: Tables | None = None) -> Rows:
    """Run batches (`devices`: the device of each of a group's batches, None for JAX's default
    placement; their number is the batches run side by side) → their table rows. The one
    function behind an in-process sweep, a stored one and a Dask task: the same program on the
    same padded inputs, so the rows are the same to the bit wherever and however they are
    computed. With `table` (the sweep's), each batch's rows are written at its own rows there;
    without, into a table of these batches' rows one after the other (`Rows.tables`).

    Native kernels with nothing to report (`reporter`'s silent one) run as `_take_batches`:
    each thread takes the next batch no thread has taken. Otherwise the batches run in groups of
    `len(devices)`, side by side chunk by chunk (`_run_chunks`), with progress after each."""
    cfg, members, shapes, run, bs = plan
    rows = [batch_rows(b, bs, members.B) for b in batches]
    n_real = [r.stop - r.start for r in rows]
    if table is None:  # these batches' rows one after the other
        ends = np.cumsum(n_real)
        table, targets = allocate_tables(int(ends[-1]), shapes, run), [slice(e - n, e) for e, n in zip(ends, n_real)]
    else:
        targets = rows
    if cfg.native and getattr(report, "silent", False):
        _take_batches(plan, batches, len(devices), table, targets)
        return Rows(list(batches), rows, table, {"native"})
    used, fell_back = set(), []
    for g in range(0, len(batches), len(devices)):
        group = [start_batch(cfg, members, shapes, b, bs, dev) for b, dev in zip(batches[g:], devices)]
        for one, target in zip(group, targets[g:]):
            one.rows = target
        _run_chunks(cfg, group, run, table.saved, report, fell_back)
        for one in group:
            used.update(one.carry.status.devices() if hasattr(one.carry.status, "devices") else ["native"])
            tables.collect(table, one, run)
    fast = (sum(k for k, _ in fell_back), sum(k for k, m in fell_back if m), sum(k * m for k, m in fell_back))
    return Rows(list(batches), rows, table, used, fast)


def _take_batches(plan: Plan, batches: list, threads: int, table: Tables, targets: list) -> None:
    """Native batches without progress reports: `threads` host threads (the calling one and
    `workers`') each take the next batch no thread has taken, march it through every chunk
    (`native_call`, with the thread's kernel rows, `Workspace`) and write its rows to `targets`
    in `table` (the rows of two batches are disjoint). No thread waits for another between
    batches or chunks, and one the machine slows takes fewer batches. The kernel (one for every
    chunk length) is looked up once per call, not once per chunk. A batch's error stops the
    threads from taking more, and is raised once they stopped."""
    cfg, members, shapes, run, bs = plan
    pending, errors, lock = collections.deque(range(len(batches))), [], threading.Lock()
    programs: list = []

    def program(c: Config, one: Batch):
        with lock:  # one look-up, whichever thread needs it first
            if not programs:
                programs.append(native_program_of(c, one))
            return programs[0]

    def take() -> None:
        workspace = _workspace()
        try:
            while not errors:
                try:
                    k = pending.popleft()
                except IndexError:
                    return
                one = start_batch(cfg, members, shapes, batches[k], bs, None)
                for st, n in run.chunks:
                    c = _steps(cfg, run, n)
                    one.carry = native_call(c, one, st, workspace, program(c, one))
                one.rows = targets[k]
                tables.collect(table, one, run)  # before the thread's next call overwrites its rows
        except BaseException as err:  # noqa: BLE001 -- raised by the calling thread below
            errors.append(err)
        finally:
            workspace.trim(WORKSPACE_KEEP_BYTES)

    others = [workers(threads - 1).submit(take) for _ in range(min(threads, len(batches)) - 1)]
    try:
        take()
        for f in others:
            f.result()
    except BaseException as err:  # e.g. Ctrl-C while waiting: the other threads take no more batches
        errors.append(err)
        raise
    if errors:
        raise errors[0]


WORKSPACE_KEEP_BYTES = 1 << 26
"""A host thread's kernel rows (`Workspace`) kept after its native batches, at most: rows up to
this size are reused by the thread's next sweep — fresh rows cost page faults on their first
writes, and freeing them gives their pages back (`benchmarks/README.md`: the faults were all of a
warm sweep's system time) — larger ones, batches of large members, are let go, so that an idle
process does not hold them."""

_WORKERS: list = []  # [the pool, its threads]
_BROADCASTS: dict = {}  # `_broadcast`'s views
_WORKERS_LOCK = threading.Lock()
_ROWS = threading.local()


def workers(n: int) -> ThreadPoolExecutor:
    """A pool of at least `n` host threads kept for the process's native sweeps (`_take_batches`):
    starting threads for each call costs more than a small sweep's batches, and kept threads
    keep their kernel rows (`WORKSPACE_KEEP_BYTES`). Grown, never shrunk, when more are asked."""
    with _WORKERS_LOCK:
        if not _WORKERS or _WORKERS[1] < n:
            if _WORKERS:
                _WORKERS[0].shutdown(wait=False)  # its threads end once idle
            _WORKERS[:] = [ThreadPoolExecutor(n, thread_name_prefix="clebsch-jax-sweep"), n]
        return _WORKERS[0]


def _workspace() -> Workspace:
    """The calling thread's kernel rows, kept from call to call (`WORKSPACE_KEEP_BYTES`)."""
    found = getattr(_ROWS, "rows", None)
    if found is None:
        found = _ROWS.rows = Workspace()
    return found
