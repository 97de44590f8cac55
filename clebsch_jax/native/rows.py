r"""Arrays with a long leading axis held in memory and computed row by row in loops (`Rows`).

The translation (`clebsch_jax.native.values`) writes out every entry of an array: a program
whose arrays grow with a count — the records of a long `scan`, and what is computed from them
afterwards (the nodes, energies and `Solution` of a march of `n_steps` steps) — grows with it,
and past `MAX_ENTRIES` it is refused. Where a program has a scan of at least `ROWS_MIN`
iterations (`wants_rows`), arrays with a leading axis of at least `ROWS_MIN` entries are
instead `Rows`: their rows (the entries of one index of the leading axis) live in memory (a
scan's records, an array concatenated along the axis), are the same for every row (a
broadcast), or are the row's index (an `iota`). An equation that computes each row of its
result from the same row of its operands (`row_program.row_plan`: elementwise primitives,
selects, broadcasts, re-indexing and reductions of the other axes, contractions batched over
the axis) is emitted as a loop over the rows, which evaluates the equation's rule (`RULES`) on
one row; so is an equation with nested programs whose every equation keeps the rows apart
(`row_program.row_equation`: `jax.vmap` of a Newton loop, a solve or a short scan over the
nodes of a trajectory), whose program for one row is emitted once, in the loop. A reduction
along the axis, a concatenation or a slice along it, and indexing a row at a run-time index
are loops or views of their own. Any other equation gets the entries of its `Rows` operands
written out (`materialize`), as before: the code then grows with the axis.
The kernel writes `Rows` outputs in a loop (`clebsch_jax.native.kernel.build_ir`).

Memory rows live in one buffer per kernel call (`Emitter.arena`, allocated on the heap: the
records of 10⁴ steps outgrow a stack; when it cannot be allocated, the kernel runs nothing and
returns its size, and the call raises `MemoryError`: `Emitter.close_entry`). The rows are the
same numbers, in the same order of operations per entry, as the unrolled entries: only where
they are held changes.
"""

from __future__ import annotations

import types

import numpy as np
from llvmlite import ir

from .loops import for_range
from .row_program import CALL_PROGRAMS, REDUCE, row_equation, row_plan
from .values import Emitter, is_known, llvm_type

__all__ = [
    "ROWS_MIN",
    "Rows",
    "wants_rows",
    "apply",
    "row_loop",
    "row_at",
    "memory",
    "store_row",
    "materialize",
    "loop",
]

ROWS_MIN = 32
"""The shortest leading axis held as `Rows` (and the shortest scan that turns them on)."""


class Rows:
    """An array of shape (n, *row) held row by row: `kind` "memory" (`slots`: a pointer per
    entry of a row to n vectors, from row `offset` on), "uniform" (`value`: every row's
    entries) or "iota" (row i: i in every entry)."""

    def __init__(self, n: int, row: tuple, dtype, kind: str, slots=None, offset: int = 0, value=None):
        self.n, self.row, self.dtype, self.kind = int(n), tuple(row), np.dtype(dtype), kind
        self.slots, self.offset, self.value = slots, offset, value

    @property
    def shape(self) -> tuple:
        return (self.n,) + self.row

    @property
    def ndim(self) -> int:
        return 1 + len(self.row)


def wants_rows(jaxpr) -> bool:
    """Whether the translation of `jaxpr` holds long arrays as `Rows`: it has a scan of at
    least `ROWS_MIN` iterations (at its top level)."""
    return any(e.primitive.name == "scan" and e.params["length"] >= ROWS_MIN for e in jaxpr.eqns)


def memory(em: Emitter, n: int, row: tuple, dtype) -> Rows:
    """Rows in the kernel's buffer: n vectors per entry of a row."""
    slots = np.empty(row, object)
    for idx in np.ndindex(row):
        slots[idx] = em.arena(n)
    return Rows(n, row, dtype, "memory", slots)


def _ptr(em: Emitter, slot, i, dtype):
    return em.b.gep(slot, [i], source_etype=em.vtype(dtype))


def _index(i):
    return ir.Constant(ir.IntType(64), i) if isinstance(i, (int, np.integer)) else i


def row_at(em: Emitter, r: Rows, i) -> np.ndarray:
    """The entries of row `i` (an i64 value or a Python int) of `r`."""
    if r.kind == "uniform":
        return r.value
    out = np.empty(r.row, object)
    if r.kind == "iota":
        if isinstance(i, (int, np.integer)):
            out[...] = np.asarray(i, r.dtype)[()]
            return out
        t = llvm_type(r.dtype)
        x = em.b.sitofp(i, t) if r.dtype.kind == "f" else em.b.trunc(i, t) if t.width < 64 else i
        vec = em.b.insert_element(ir.Constant(em.vtype(r.dtype), ir.Undefined), x, ir.Constant(ir.IntType(32), 0))
        vec = em.b.shuffle_vector(
            vec, ir.Constant(vec.type, ir.Undefined), ir.Constant(ir.VectorType(ir.IntType(32), em.W), [0] * em.W)
        )
        out[...] = vec
        return out
    at = _index(i)
    if r.offset:
        at = (
            em.b.add(at, ir.Constant(ir.IntType(64), r.offset))
            if not isinstance(at, ir.Constant)
            else _index(int(at.constant) + r.offset)
        )
    for idx in np.ndindex(r.row):
        out[idx] = em.b.load(_ptr(em, r.slots[idx], at, r.dtype), typ=em.vtype(r.dtype), align=8)
    return out


def store_row(em: Emitter, r: Rows, i, entries) -> None:
    """Store `entries` as row `i` of memory rows `r`."""
    at, entries = _index(i), np.asarray(entries, object) if isinstance(entries, np.ndarray) else _scalar(entries)
    for idx in np.ndindex(r.row):
        em.b.store(em.vec(entries[idx], r.dtype), _ptr(em, r.slots[idx], at, r.dtype), align=8)


def _scalar(e) -> np.ndarray:
    out = np.empty((), object)
    out[()] = e
    return out


def loop(em: Emitter, n: int, body) -> None:
    """Emit `for i in range(n): body(i)` (i an i64 value): `loops.for_range` from 0."""
    for_range(em, 0, n, body)


def materialize(em: Emitter, r) -> np.ndarray:
    """The entries of `r` written out (an entry array of its full shape); other values as they are."""
    if not isinstance(r, Rows):
        return r
    em.count(r.n * int(np.prod(r.row, dtype=int)))
    if r.kind == "uniform":
        return np.stack([r.value] * r.n) if r.n else np.empty(r.shape, object)
    return np.stack([row_at(em, r, k) for k in range(r.n)]) if r.n else np.empty(r.shape, object)


def _as_rows(em: Emitter, x, n: int, dtype) -> Rows:
    """An entry array of leading axis n as rows: uniform when its rows are the same known
    entries, else stored to memory (its entries are written out already)."""
    if isinstance(x, Rows):
        return x
    first = x[0, ...]
    if all(is_known(e) for e in x.reshape(-1)) and all(np.array_equal(x[k, ...], first) for k in range(1, n)):
        return Rows(n, x.shape[1:], dtype, "uniform", value=first)
    r = memory(em, n, x.shape[1:], dtype)
    for k in range(n):
        store_row(em, r, k, x[k, ...])
    return r


def _aval(shape, dtype):
    return types.SimpleNamespace(aval=types.SimpleNamespace(shape=tuple(shape), dtype=np.dtype(dtype), ndim=len(shape)))


def apply(em: Emitter, eqn, args, rules):
    """The outputs of `eqn` where `Rows` are involved (made or read), else None (the caller
    applies `rules` as usual). An equation that keeps the rows apart runs in a loop over them
    (`row_plan`, `row_loop`); the others get their `Rows` operands written out, and the
    programs nested in them are translated without `Rows`."""
    name = eqn.primitive.name
    has_rows = any(isinstance(a, Rows) for a in args)
    if not getattr(em, "rows", False):
        return None
    out_shape = tuple(getattr(eqn.outvars[0].aval, "shape", ())) if eqn.outvars else ()
    n = next((a.n for a in args if isinstance(a, Rows)), out_shape[0] if out_shape else 0)
    if name in CALL_PROGRAMS and name in rules:  # entered: its equations see the rows (and count their entries)
        return rules[name](em, eqn, args)
    if name == "scan" and has_rows and eqn.params["length"] < ROWS_MIN:  # a short scan of each row: a loop over them
        looped = row_loop(em, eqn, args, n, rules)
        if looped is not None:
            return looped
    if name == "scan" and (has_rows or eqn.params["length"] >= ROWS_MIN):  # records kept as rows: `control`
        nc, ncar = eqn.params["num_consts"], eqn.params["num_carry"]
        return rules["scan"](em, eqn, [materialize(em, a) if k < nc + ncar else a for k, a in enumerate(args)])
    if not has_rows:
        if name == "iota" and eqn.params["dimension"] == 0 and n >= ROWS_MIN:
            return Rows(n, out_shape[1:], eqn.params["dtype"], "iota")
        if name != "broadcast_in_dim" or n < ROWS_MIN or 0 in eqn.params["broadcast_dimensions"]:
            return None
    special = _special(em, eqn, args, n)
    if special is not None:
        return special
    plan = row_plan(eqn, n) if n >= ROWS_MIN else None
    if plan is None:
        looped = row_loop(em, eqn, args, n, rules) if n >= ROWS_MIN else None
        if looped is not None:
            return looped
        return _nested(em, lambda: rules[name](em, eqn, [materialize(em, a) for a in args]))
    params, split = plan
    ins = [
        Rows(n, tuple(v.aval.shape[1:]), v.aval.dtype, "uniform", value=materialize(em, a)[0, ...])
        if s == "one"
        else _as_rows(em, a, n, v.aval.dtype)
        if s
        else materialize(em, a)
        for a, s, v in zip(args, split, eqn.invars)
    ]
    row_eqn = types.SimpleNamespace(
        primitive=eqn.primitive,
        params=params,
        invars=[_aval(v.aval.shape[1:], v.aval.dtype) if s else v for v, s in zip(eqn.invars, split)],
        outvars=[_aval(v.aval.shape[1:], v.aval.dtype) for v in eqn.outvars],
        effects=eqn.effects,
    )
    rule = rules[name]
    em.count(int(np.prod(out_shape[1:], dtype=int)))
    dtype = np.dtype(eqn.outvars[0].aval.dtype)
    if all(not isinstance(a, Rows) or a.kind == "uniform" for a in ins):  # every row the same
        value = rule(em, row_eqn, [a.value if isinstance(a, Rows) else a for a in ins])
        return Rows(n, out_shape[1:], dtype, "uniform", value=value)
    result = memory(em, n, out_shape[1:], dtype)
    loop(
        em,
        n,
        lambda i: store_row(
            em, result, i, rule(em, row_eqn, [row_at(em, a, i) if isinstance(a, Rows) else a for a in ins])
        ),
    )
    return result


def row_loop(em: Emitter, eqn, args, n: int, rules):
    """An equation (a loop, a solve, …) each of whose outputs' rows is computed from the same
    rows of its operands (`row_program.row_equation`), as a loop over the rows running its
    program for one row; None where it is not such an equation. An output that is the same for
    every row (a loop's counter) is kept from the rows' loop in allocas."""
    split = [0 if isinstance(a, Rows) or (np.ndim(a) > 0 and np.shape(a)[0] == n) else None for a in args]
    found = row_equation(eqn, split, n)
    if found is None or any(a not in (0, None) for a in found[1]):  # rows held on the leading axis only
        return None
    row_eqn, axes = found
    ins = [
        materialize(em, a) if s is None else _as_rows(em, a, n, v.aval.dtype)
        for a, s, v in zip(args, split, eqn.invars)
    ]
    outs = [
        memory(em, n, tuple(v.aval.shape[1:]), v.aval.dtype) if a == 0 else _slots(em, v.aval)
        for v, a in zip(eqn.outvars, axes)
    ]
    em.count(
        sum(int(np.prod(v.aval.shape[1:] if a == 0 else v.aval.shape, dtype=int)) for v, a in zip(eqn.outvars, axes))
    )

    def body(i):
        row = [row_at(em, a, i) if isinstance(a, Rows) else a for a in ins]
        got = _nested(em, lambda: rules[eqn.primitive.name](em, row_eqn, row))
        for r, g, v in zip(outs, got if eqn.primitive.multiple_results else [got], eqn.outvars):
            if isinstance(r, Rows):
                store_row(em, r, i, g)
                continue
            for idx in np.ndindex(r.shape):
                em.b.store(em.vec(np.asarray(g, object)[idx], v.aval.dtype), r[idx])

    loop(em, n, body)
    outs = [r if isinstance(r, Rows) else _loaded(em, r, v.aval.dtype) for r, v in zip(outs, eqn.outvars)]
    return outs if eqn.primitive.multiple_results else outs[0]


def _slots(em: Emitter, aval) -> np.ndarray:
    out = np.empty(tuple(aval.shape), object)
    for idx in np.ndindex(out.shape):
        out[idx] = em.alloca(em.vtype(aval.dtype))
    return out


def _loaded(em: Emitter, slots, dtype) -> np.ndarray:
    out = np.empty(slots.shape, object)
    for idx in np.ndindex(slots.shape):
        out[idx] = em.b.load(slots[idx], typ=em.vtype(dtype))
    return out


def _nested(em: Emitter, run):
    """`run()` with no new `Rows` made (the programs nested in loops and branches read entries)."""
    before, em.rows = em.rows, False
    try:
        return run()
    finally:
        em.rows = before


def _special(em: Emitter, eqn, args, n: int):
    """Equations along the rows' axis: slices and reshapes as views, concatenations as copies,
    reductions over the axis and indexing at a run-time row as loops."""
    name, p = eqn.primitive.name, eqn.params
    a = args[0] if args else None
    if name == "slice" and isinstance(a, Rows) and a.kind != "uniform":
        start, limit, strides = p["start_indices"], p["limit_indices"], p["strides"]
        if all(s == 0 for s in start[1:]) and tuple(limit[1:]) == a.row and (strides is None or set(strides) == {1}):
            size = limit[0] - start[0]
            if a.kind == "iota" and start[0] == 0:
                return (
                    Rows(size, a.row, a.dtype, "iota")
                    if size >= ROWS_MIN
                    else materialize(em, Rows(size, a.row, a.dtype, "iota"))
                )
            if a.kind == "memory":
                view = Rows(size, a.row, a.dtype, "memory", a.slots, a.offset + start[0])
                return view if size >= ROWS_MIN else materialize(em, view)
    if name == "slice" and isinstance(a, Rows) and a.kind == "uniform" and p["strides"] is None:
        size = p["limit_indices"][0] - p["start_indices"][0]
        idx = tuple(slice(s, e) for s, e in zip(p["start_indices"][1:], p["limit_indices"][1:]))
        r = Rows(
            size,
            tuple(e - s for s, e in zip(p["start_indices"][1:], p["limit_indices"][1:])),
            a.dtype,
            "uniform",
            value=a.value[idx],
        )
        return r if size >= ROWS_MIN else materialize(em, r)
    if name == "reshape" and isinstance(a, Rows) and a.kind in ("memory", "uniform") and p.get("dimensions") is None:
        new = tuple(p["new_sizes"])
        if new and new[0] == a.n:
            if a.kind == "memory":
                return Rows(a.n, new[1:], a.dtype, "memory", a.slots.reshape(new[1:]), a.offset)
            return Rows(a.n, new[1:], a.dtype, "uniform", value=a.value.reshape(new[1:]))
    if name == "concatenate" and p["dimension"] == 0:
        dtype = np.dtype(eqn.outvars[0].aval.dtype)
        total = sum(x.shape[0] for x in args)
        result = memory(em, total, tuple(eqn.outvars[0].aval.shape[1:]), dtype)
        at = 0
        for x in args:
            if isinstance(x, Rows):
                start = at
                loop(
                    em,
                    x.n,
                    lambda i, x=x, start=start: store_row(em, result, em.b.add(i, _index(start)), row_at(em, x, i)),
                )
            else:
                for k in range(x.shape[0]):
                    store_row(em, result, at + k, x[k, ...])
            at += x.shape[0]
        em.count(int(np.prod(result.row, dtype=int)))
        return result if total >= ROWS_MIN else materialize(em, result)
    if name in REDUCE and isinstance(a, Rows) and tuple(p["axes"]) == (0,) and not a.row:
        return _reduce_rows(em, eqn, a)
    if (
        name == "dynamic_slice"
        and isinstance(a, Rows)
        and p["slice_sizes"][0] == 1
        and not any(isinstance(x, Rows) for x in args[1:])
    ):
        return _row_at_index(em, eqn, a, args[1:])
    return None


def _reduce_rows(em: Emitter, eqn, a: Rows):
    """A reduction of a vector of rows over its one axis: an accumulator through a loop, in
    index order (argmax/argmin: the first index of the extreme, NaN the greatest)."""
    from .lower import RULES

    name = eqn.primitive.name
    dtype, out_dtype = a.dtype, np.dtype(eqn.outvars[0].aval.dtype)
    b = em.b
    pair = _aval((2,), dtype)
    # the reduction's own rule, applied to (the result so far, the next row): a pair reduced
    pair_eqn = types.SimpleNamespace(
        primitive=eqn.primitive,
        params=dict(eqn.params, axes=(0,)),
        invars=[pair],
        outvars=[_aval((), out_dtype)],
        effects=eqn.effects,
    )
    if name in ("argmax", "argmin"):
        best, where = em.alloca(em.vtype(dtype)), em.alloca(em.vtype(out_dtype))
        b.store(em.vec(row_at(em, a, 0)[()], dtype), best)
        b.store(em.const(0, out_dtype), where)

        def step(i):
            x = row_at(em, a, i)[()]
            cur = b.load(best, typ=em.vtype(dtype))
            # the existing rule on (best so far, row i) decides with its own comparison: index 1 wins
            pick = RULES[name](em, pair_eqn, [np.asarray([cur, x], object)])[()]
            take = b.icmp_signed("==", em.vec(pick, out_dtype), em.const(1, out_dtype))
            b.store(b.select(take, x, cur), best)
            idx = row_at(em, Rows(a.n, (), out_dtype, "iota"), i)[()]
            b.store(b.select(take, idx, b.load(where, typ=em.vtype(out_dtype))), where)

        loop(em, a.n - 1, lambda i: step(b.add(i, _index(1))))
        out = np.empty((), object)
        out[()] = b.load(where, typ=em.vtype(out_dtype))
        return out
    acc = em.alloca(em.vtype(out_dtype))
    b.store(em.vec(row_at(em, a, 0)[()], out_dtype), acc)

    def step(i):
        x = row_at(em, a, i)[()]
        value = RULES[name](em, pair_eqn, [np.asarray([b.load(acc, typ=em.vtype(out_dtype)), x], object)])[()]
        b.store(em.vec(value, out_dtype), acc)

    loop(em, a.n - 1, lambda i: step(b.add(i, _index(1))))
    out = np.empty((), object)
    out[()] = b.load(acc, typ=em.vtype(out_dtype))
    return out


def _row_at_index(em: Emitter, eqn, a: Rows, starts):
    """`dynamic_slice` of one row at a run-time index (clamped, as XLA does), lane by lane."""
    from .lower import RULES

    b, i64, i32 = em.b, ir.IntType(64), ir.IntType(32)
    s = starts[0][()]
    if is_known(s):
        row = row_at(em, a, int(np.clip(int(s), 0, a.n - 1)))
    else:
        row = np.empty(a.row, object)
        for idx in np.ndindex(a.row):
            row[idx] = ir.Constant(em.vtype(a.dtype), ir.Undefined)
        for lane in range(em.W):
            k = b.extract_element(s, ir.Constant(i32, lane))
            k = b.sext(k, i64) if k.type.width < 64 else k
            k = b.select(b.icmp_signed("<", k, ir.Constant(i64, 0)), ir.Constant(i64, 0), k)
            k = b.select(b.icmp_signed(">", k, ir.Constant(i64, a.n - 1)), ir.Constant(i64, a.n - 1), k)
            got = row_at(em, a, k)
            for idx in np.ndindex(a.row):
                lane_value = b.extract_element(got[idx], ir.Constant(i32, lane))
                row[idx] = b.insert_element(row[idx], lane_value, ir.Constant(i32, lane))
    whole = row[None]
    if not a.row:
        return whole
    fake = types.SimpleNamespace(
        primitive=eqn.primitive,
        params=dict(eqn.params),
        invars=[_aval((1,) + a.row, a.dtype)] + list(eqn.invars[1:]),
        outvars=eqn.outvars,
        effects=eqn.effects,
    )
    zero = np.empty((), object)
    zero[()] = np.asarray(0, eqn.invars[1].aval.dtype)[()]
    return RULES["dynamic_slice"](em, fake, [whole, zero] + list(starts[1:]))
