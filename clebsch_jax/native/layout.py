r"""A kernel call's arrays laid out batch-last, and the rows reused from call to call.

A kernel (`clebsch_jax.native.kernel.Kernel`) reads and writes every array as rows: one row
of `stride` members per entry of the member's shape, `stride` the batch rounded up to whole
blocks of lanes, the padding lanes repeating the last member. `input_rows` lays a call's
arrays out so, `output_rows` makes the rows the kernel writes, `results` gives them back
member-major.

A `Workspace` keeps those rows for the calls one thread makes: without it every call takes
fresh memory, whose first writes fault its pages in (inside the kernel, where two threads'
faults also wait for each other). With it a call reuses the rows of the call before the last
one, an input that is a carry output of the last call (`results` returns those as views
of its rows) is read in place instead of copied, and an input that repeats one member (a
broadcast view) is not written again into rows that hold that member already.

`prefetch_next_block` emits, in a kernel's loop over blocks, the prefetches of the next block's
rows (a block reads one cache line of each of its inputs' rows and writes one of each
output's).
"""

from __future__ import annotations

import sys
import threading

import numpy as np

__all__ = [
    "Workspace",
    "SpareRows",
    "SPARE_ROWS",
    "aligned_empty",
    "input_rows",
    "output_rows",
    "results",
    "prefetch_next_block",
]

ALIGNMENT = 64
"""Bytes: `jax.device_put` of a contiguous NumPy array aligned so takes its memory as it is (on
CPU), where it copies one that is not (NumPy's large arrays start 16 bytes into their pages)."""


class Workspace:
    """The rows of the kernel calls one thread makes, kept for its next calls. The outputs of
    a call stay valid until the second call after it with the same workspace (the outputs
    alternate between two sets of rows, so that a call can read the last call's in place); a
    workspace must not be shared by two threads at once. It knows its rows' addresses and the
    last call's carry outputs by identity, so that a call reads neither from NumPy again."""

    def __init__(self):
        self._rows: dict = {}
        self._addresses: dict = {}  # id(rows) -> (rows, the address of their data)
        self._returned: dict = {}  # id(output) -> (output, its rows): the last call's carry outputs
        self._filled: dict = {}  # key -> what its input rows hold, where they repeat one member
        self._set = 0

    def next_set(self) -> int:
        """The set of output rows of the next call (the one the call before the last wrote)."""
        self._set ^= 1
        return self._set

    def rows(self, key, shape: tuple, dtype) -> np.ndarray:
        """The rows under `key`, made (uninitialised) on first use or when the shape changed."""
        found = self._rows.get(key)
        if found is None or found.shape != shape or found.dtype != dtype:
            if found is not None:
                self._addresses.pop(id(found), None)
            self._filled.pop(key, None)
            found = self._rows[key] = np.empty(shape, dtype)
            self._addresses[id(found)] = (found, found.ctypes.data)
        return found

    def address(self, a: np.ndarray) -> int:
        """The address of `a`'s data (kept for the workspace's rows)."""
        found = self._addresses.get(id(a))
        return found[1] if found is not None and found[0] is a else a.ctypes.data

    def returned(self, outputs: list, rows: list) -> None:
        """Record a call's carry outputs (`results`' views of their `rows`), which the next call
        may be given back as inputs (`passed_back`)."""
        self._returned = {id(a): (a, r) for a, r in zip(outputs, rows) if a.base is r}

    def passed_back(self, a: np.ndarray) -> np.ndarray | None:
        """The rows of `a` if it is one of the last call's carry outputs, else None."""
        found = self._returned.get(id(a))
        return found[1] if found is not None and found[0] is a else None

    def holds(self, key, member) -> bool:
        """Whether the input rows under `key` hold `member` (see `fill`) in every lane."""
        return self._filled.get(key) == member

    def fill(self, key, member) -> None:
        """Record that the input rows under `key` now hold `member` in every lane (None: other
        values). Only `input_rows` writes input rows, so they keep it until it writes them again."""
        if member is None:
            self._filled.pop(key, None)
        else:
            self._filled[key] = member

    def trim(self, keep: int) -> None:
        """Let go of the rows when they take more than `keep` bytes (the next call makes them
        again); the arrays a caller still holds stay valid."""
        if sum(a.nbytes for a in self._rows.values()) > keep:
            self._rows, self._addresses, self._returned, self._filled = {}, {}, {}, {}


SPARE_MAX_BYTES = 1 << 25
"""`SpareRows` keeps a run's rows for the next only up to this many bytes."""


class SpareRows:
    """The record rows of the last run of a loop kernel (`clebsch_jax.native.NativeLoop`'s
    `record_rows`), taken again by a run of the same shapes once nothing else holds them: the
    `Solution` made from them was dropped. Fresh rows fault their pages in as the kernel first
    writes them, and the kernel (zeroing pages) pays that once per page, a good part of a long
    run's time; rows already written are not faulted again. Whether another object holds them
    is read from the reference counts of their memory (each array of `aligned_empty` is the one
    view of its own buffer, and every other view of it refers to that buffer), under a lock, so
    that two threads' runs never share them. The process keeps one set (`SPARE_ROWS`), of at
    most `SPARE_MAX_BYTES`."""

    def __init__(self):
        self._rows: list | None = None
        self._lock = threading.Lock()

    def take(self, specs: list) -> list | None:
        """The kept rows if they have these (shape, dtype) `specs` and no other object refers to
        their memory, else None (they are let go)."""
        with self._lock:
            rows, self._rows = self._rows, None
        if rows is None or [(r.shape, r.dtype) for r in rows] != specs:
            return None
        # a view of the buffer (`rows`' own) and getrefcount's argument: nothing else
        return rows if all(sys.getrefcount(r.base) == 2 for r in rows) else None

    def keep(self, rows: list) -> None:
        """Keep a run's rows (`aligned_empty` arrays) for a next run, up to `SPARE_MAX_BYTES`."""
        if sum(r.nbytes for r in rows) <= SPARE_MAX_BYTES:
            with self._lock:
                self._rows = rows


SPARE_ROWS = SpareRows()
"""The process's `SpareRows`."""


def aligned_empty(shape: tuple, dtype) -> np.ndarray:
    """An uninitialised C-contiguous array whose data start on an `ALIGNMENT`-byte boundary."""
    dtype = np.dtype(dtype)
    nbytes = int(np.prod(shape, dtype=int)) * dtype.itemsize
    raw = np.empty(nbytes + ALIGNMENT, np.uint8)
    start = -raw.ctypes.data % ALIGNMENT
    return raw[start : start + nbytes].view(dtype).reshape(shape)


def _fresh(key, shape: tuple, dtype) -> np.ndarray:
    return np.empty(shape, dtype)


def _rows_of(view: np.ndarray, rows: np.ndarray) -> bool:
    """Whether `view` (entries, B) lies on `rows`' first B columns (the stride of an axis of
    length 1 is any)."""
    return view.strides[1] == rows.strides[1] and (view.shape[0] == 1 or view.strides[0] == rows.strides[0])


def input_rows(arrays, layout: list, batched: list, B: int, stride: int, workspace: Workspace | None) -> list:
    """The kernel's input buffers: a shared array flattened; a batched one (B, *shape) as
    (entries, stride) rows, its padding lanes repeating member B − 1. With a `workspace`, the
    rows are reused, and a carry output of its last call is passed as it is."""
    take = _fresh if workspace is None else workspace.rows
    buffers = []
    for j, (a, (shape, size, storage), bat) in enumerate(zip(arrays, layout, batched)):
        a = np.asarray(a)
        if not bat:
            if a.shape != shape:
                raise ValueError(f"expected a shared array of shape {shape}, got {a.shape}")
            buffers.append(np.ascontiguousarray(a.reshape(-1), storage))
            continue
        if a.shape != (B,) + shape:
            raise ValueError(f"expected an array of shape {(B,) + shape}, got {a.shape}")
        if stride == 1:  # one member, one lane: its rows are its entries in order (the kernel only reads them)
            buffers.append(np.ascontiguousarray(a, storage))
            continue
        view = a.reshape(B, size).T
        own = None if workspace is None else workspace.passed_back(a)
        if own is not None and own.shape == (size, stride) and own.dtype == storage and _rows_of(view, own):
            # rows the last call wrote: their padding lanes ran copies of member B − 1, so they
            # hold its outputs, which the copy below would write there too
            buffers.append(own)
            continue
        rows = take(("in", j), (size, stride), storage)
        # one member repeated (a broadcast view, e.g. a carry's zeros): rows that hold it already,
        # from this thread's last batch or call, are not written again
        member = (B, stride, a.dtype.str, a[0].tobytes()) if workspace is not None and a.strides[0] == 0 else None
        if member is None or not workspace.holds(("in", j), member):
            rows[:, :B] = view
            rows[:, B:] = rows[:, B - 1 : B]  # padding lanes repeat the last member
            if workspace is not None:
                workspace.fill(("in", j), member)
        buffers.append(rows)
    return buffers


def output_rows(layout: list, n_carry: int, stride: int, steps: int, capacity: int, workspace, records=None) -> list:
    """The rows the kernel writes: each carry output's (entries, stride), each record's
    (capacity · entries, stride), zero after the `steps` records written. `records`: the
    records' rows given by the caller (for example views of a longer run's arrays, which the
    kernel then fills in place), checked for their shape and dtype."""
    which = None if workspace is None else workspace.next_set()
    take = _fresh if workspace is None else lambda j, shape, dtype: workspace.rows(("out", which, j), shape, dtype)
    outs = [take(j, (size, stride), storage) for j, (_, size, storage) in enumerate(layout[:n_carry])]
    given = None if records is None else list(records)
    if given is not None and len(given) != len(layout) - n_carry:
        raise ValueError(f"records: expected {len(layout) - n_carry} arrays of rows, got {len(given)}")
    for j, (_, size, storage) in enumerate(layout[n_carry:], n_carry):
        if given is None:
            rows = take(j, (capacity * size, stride), storage)
        else:
            rows = given[j - n_carry]
            if rows.shape != (capacity * size, stride) or rows.dtype != storage or not rows.flags.c_contiguous:
                raise ValueError(
                    f"records[{j - n_carry}]: expected C-contiguous rows of shape {(capacity * size, stride)} and "
                    f"dtype {storage}, got {rows.shape} {rows.dtype}"
                )
        rows[steps * size :] = 0
        outs.append(rows)
    return outs


def results(outs: list, layout: list, dtypes: list, n_carry: int, B: int, stride: int, capacity: int) -> list:
    """The outputs member-major: a carry's (B, *shape), a view of its rows (a next call's
    input rows are copied from it row by row, or read in place: `input_rows`); a record's
    (B, capacity, *shape), a copy."""
    result = []
    for j, (rows, (shape, size, _), dtype) in enumerate(zip(outs, layout, dtypes)):
        if stride == 1:  # the rows in order are the member's entries, record after record
            r = rows.reshape(((1,) if j < n_carry else (1, capacity)) + shape)
        elif j < n_carry:
            r = rows[:, :B].T.reshape((B,) + shape)
            result.append(r.astype(np.bool_) if dtype == np.bool_ else r)
            continue
        else:  # (capacity·size, stride) -> (B, capacity, *shape)
            r = rows[:, :B].reshape(capacity, size, B).transpose(2, 0, 1).reshape((B, capacity) + shape)
        result.append(r.astype(np.bool_) if dtype == np.bool_ else np.ascontiguousarray(r))
    return result


def prefetch_next_block(b, entry, arrays, stride, ahead, ins: list, outs: list) -> None:
    """Emit, with the IR builder `b` in a kernel's block body (`clebsch_jax.native.kernel`), the
    prefetches of the next block's entries: of the inputs `ins` to read, of the outputs `outs`
    to write, each a list of (array index, entries, bytes per entry); `ahead` is the next
    block's first member. Each entry is a row of its own, so a block touches one cache line in
    each of many rows far apart: too many streams for the hardware's prefetchers, and every
    line missed would stall the block's first loads and last stores. A prefetch changes no
    value, and past the last block it reads nothing (prefetches do not fault). Two loops over
    constant tables of the rows (array, entry, bytes per entry), so the IR does not grow with
    the member's entries; their counters are allocas of the `entry` block (LLVM makes them
    registers)."""
    from llvmlite import ir

    i8, i32, i64 = ir.IntType(8), ir.IntType(32), ir.IntType(64)
    module, triple = b.module, ir.ArrayType(i64, 3)
    fn = module.globals.get("llvm.prefetch.p0") or ir.Function(
        module, ir.FunctionType(ir.VoidType(), [ir.PointerType(), i32, i32, i32]), "llvm.prefetch.p0"
    )
    for write, specs in ((0, ins), (1, outs)):
        rows = [(j, e, itemsize) for j, size, itemsize in specs for e in range(size)]
        if not rows:
            continue
        table_type = ir.ArrayType(triple, len(rows))
        table = ir.GlobalVariable(module, table_type, f"prefetch.rows.{write}")
        table.global_constant, table.linkage = True, "private"
        table.initializer = ir.Constant(table_type, [ir.Constant(triple, list(r)) for r in rows])
        body = b.block
        b.position_at_end(entry)
        at = b.alloca(i64)
        b.position_at_end(body)
        loop, done = b.append_basic_block(f"prefetch.{write}"), b.append_basic_block(f"prefetch.{write}.done")
        b.store(ir.Constant(i64, 0), at)
        b.branch(loop)
        b.position_at_end(loop)
        r = b.load(at, typ=i64)
        j, e, itemsize = (
            b.load(b.gep(table, [ir.Constant(i64, 0), r, ir.Constant(i32, k)], source_etype=table_type), typ=i64)
            for k in range(3)
        )
        data = b.load(b.gep(arrays, [j], source_etype=ir.PointerType()), typ=ir.PointerType())
        byte = b.mul(b.add(b.mul(e, stride), ahead), itemsize)
        b.call(fn, [b.gep(data, [byte], source_etype=i8), *(ir.Constant(i32, x) for x in (write, 3, 1))])
        b.store(b.add(r, ir.Constant(i64, 1)), at)
        b.cbranch(b.icmp_signed("<", b.add(r, ir.Constant(i64, 1)), ir.Constant(i64, len(rows))), loop, done)
        b.position_at_end(done)
