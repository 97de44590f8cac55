"""Indexing by values in the native translation: dynamic slices, gathers and scatters.

Indices known while translating (constants, unrolled loop counters) are resolved then: a
gather or scatter with known indices is the index map of the same primitive applied to
positions, computed once, and costs no code. Indices computed at run time differ from lane to
lane; two forms, by the number of places an index vector can reach:

- a few places (`SELECT_STARTS`): each place's value, selected lane by lane;
- more: the operand is stored to a lane-major array on the stack once (`stored`: before the
  outermost loop being emitted that computes none of it, else once per block), and each
  entry read is one gather of every lane's own place (`llvm.masked.gather`): a few lines of
  IR per entry, not a load and an insert per lane. Loads are copies, so the values are those
  of any other form bit for bit.

Indices are clamped (`CLIP`, `PROMISE_IN_BOUNDS`, dynamic slices) or out-of-range entries
filled (`FILL_OR_DROP`) as XLA does.
"""

from __future__ import annotations

import itertools

import numpy as np
from llvmlite import ir

from .elementwise import emit_float, emit_int, out_dtype
from .lower import RULES, copy_array
from .values import Emitter, Unsupported, is_known

__all__ = ["SELECT_STARTS", "SCATTER_SELECTS"]

SELECT_STARTS = 8
"""Index vectors that can reach at most this many places are resolved by selects; beyond,
each entry is gathered from memory, each lane at its own place."""

SCATTER_SELECTS = 4096
"""A scatter whose indices reach more than `SELECT_STARTS` places is still resolved by selects
when places × updated entries stays within this many (one select per place and update: a
column set at a loop counter, `M.at[:, k].set(v)`, costs one select per entry of M). Those
selects count as entries of the program (`Emitter.count`), so a member whose loops scatter
much stays within the size limit or on XLA."""

_MAX_STARTS = 4096


def _ivec(em: Emitter, t, v):
    return ir.Constant(ir.VectorType(t, em.W), [ir.Constant(t, int(v))] * em.W)


def _i64(em: Emitter, x):
    """An index entry as an i64 vector."""
    t = ir.VectorType(ir.IntType(64), em.W)
    if is_known(x):
        return _ivec(em, ir.IntType(64), int(x))
    if x.type.element.width == 64:
        return x
    return em.b.sext(x, t) if x.type.element.width > 1 else em.b.zext(x, t)


def _clamp(em: Emitter, x, lo: int, hi: int):
    """An i64 index vector clamped to [lo, hi]."""
    b = em.b
    x = b.select(b.icmp_signed("<", x, _ivec(em, ir.IntType(64), lo)), _ivec(em, ir.IntType(64), lo), x)
    return b.select(b.icmp_signed(">", x, _ivec(em, ir.IntType(64), hi)), _ivec(em, ir.IntType(64), hi), x)


class _Stored:
    """An entry array stored lane-major on the stack ([size · W] scalars), read by one masked
    gather per entry (all lanes on), or a scalar load per lane for booleans (stored packed)."""

    def __init__(self, em: Emitter, a: np.ndarray, dtype, before: ir.Block | None = None):
        """`before`: a block (ended) where `a` is stored, before its branch; else here."""
        self.em, self.dtype, self.flat = em, np.dtype(dtype), a.reshape(-1)
        self.scalar = em.vtype(dtype).element
        self.type = ir.ArrayType(self.scalar, self.flat.size * em.W)
        self.ptr = em.alloca(self.type)
        self._scaled: dict = {}
        here = em.b.block
        if before is not None:
            em.b.position_before(before.terminator)
        zero = ir.Constant(ir.IntType(64), 0)
        for k, e in enumerate(self.flat):
            at = em.b.gep(self.ptr, [zero, ir.Constant(ir.IntType(64), k * em.W)], source_etype=self.type)
            at = em.b.bitcast(at, em.vtype(dtype).as_pointer())
            em.b.store(em.vec(e, dtype), at, align=self.dtype.itemsize)
        if before is not None:
            em.b.position_at_end(here)

    def load(self, flat_index, offset: int = 0):
        """Each lane's entry at its own flat index (an i64 vector, in range) plus `offset`."""
        em, b = self.em, self.em.b
        i64 = ir.IntType(64)
        if self.dtype == np.bool_:
            if offset:
                flat_index = b.add(flat_index, _ivec(em, i64, offset))
            return self._scalar_loads(flat_index)
        # lane l of entry i sits at i·W + l: the lanes' scaled base, once per index vector
        key = (b.block, id(flat_index))  # computed where it is used (the copy may be before a loop)
        scaled = self._scaled.get(key)
        if scaled is None:
            lanes = ir.Constant(ir.VectorType(i64, em.W), [ir.Constant(i64, lane) for lane in range(em.W)])
            scaled = b.add(b.mul(flat_index, _ivec(em, i64, em.W)), lanes)
            self._scaled[key] = (scaled, flat_index)
        else:
            scaled = scaled[0]
        at = b.add(scaled, _ivec(em, i64, offset * em.W)) if offset else scaled
        pointers = b.gep(self.ptr, [at], source_etype=self.scalar)
        pointers.type = ir.VectorType(ir.PointerType(), em.W)  # a vector index: a vector of pointers
        return b.call(
            _gather_intrinsic(em, self.dtype),
            [
                pointers,
                ir.Constant(ir.IntType(32), self.dtype.itemsize),
                em.const(True, np.bool_),
                ir.Constant(em.vtype(self.dtype), ir.Undefined),
            ],
        )

    def _scalar_loads(self, flat_index):
        em, b = self.em, self.em.b
        zero = ir.Constant(ir.IntType(64), 0)
        out = ir.Constant(em.vtype(self.dtype), ir.Undefined)
        for lane in range(em.W):
            i = b.extract_element(flat_index, ir.Constant(ir.IntType(32), lane))
            at = b.add(b.mul(i, ir.Constant(ir.IntType(64), em.W)), ir.Constant(ir.IntType(64), lane))
            x = b.load(b.gep(self.ptr, [zero, at], source_etype=self.type), typ=self.scalar)
            out = b.insert_element(out, x, ir.Constant(ir.IntType(32), lane))
        return out


def _gather_intrinsic(em: Emitter, dtype):
    """`llvm.masked.gather` of `dtype`'s vectors (declared once per kernel)."""
    vt = em.vtype(dtype)
    dtype = np.dtype(dtype)
    name = f"llvm.masked.gather.v{em.W}{'f' if dtype.kind == 'f' else 'i'}{8 * dtype.itemsize}.v{em.W}p0"
    fn = em.module.globals.get(name)
    if fn is None:
        args = [ir.VectorType(ir.PointerType(), em.W), ir.IntType(32), em.vtype(np.bool_), vt]
        fn = ir.Function(em.module, ir.FunctionType(vt, args), name)
    return fn


def stored(em: Emitter, a: np.ndarray, dtype) -> _Stored:
    """`a` stored for lane loads (`_Stored`), once: before the outermost loop being emitted
    (`Emitter.loops`) whose blocks compute none of its entries (a loop's invariant operand,
    the matrix of a triangular solve's rows), else in the block being emitted; an array stored
    before at that place (which precedes every load here) is read again from there."""
    dtype = np.dtype(dtype)
    flat = a.reshape(-1)
    at, before = em.b.block, None
    for pre, outside in em.loops:
        if all(not isinstance(e, ir.Instruction) or id(e.parent) in outside for e in flat):
            at = before = pre
            break
    key = (at, dtype, a.shape) + tuple(
        ("known", np.asarray(e).dtype.str, np.asarray(e).tobytes()) if is_known(e) else id(e) for e in flat
    )
    found = em.stored.get(key)
    if found is None:
        found = em.stored[key] = _Stored(em, a, dtype, before)  # holds the entries: their ids stay theirs
    return found


def _strides(shape) -> list:
    return [int(np.prod(shape[d + 1 :], dtype=int)) for d in range(len(shape))]


def _offset(em: Emitter, starts, dims, strides):
    """Σ start_j · stride(dim_j) as an i64 vector (the starts already clamped)."""
    b = em.b
    total = None
    for s, d in zip(starts, dims):
        term = b.mul(s, _ivec(em, ir.IntType(64), strides[d]))
        total = term if total is None else b.add(total, term)
    return total


def _conds(em: Emitter, starts, combo, his):
    """Lane condition that the (clamped) starts equal `combo`."""
    cond = None
    for s, v, hi in zip(starts, combo, his):
        if is_known(s):
            continue
        t = s.type.element
        eq = em.b.icmp_signed("==", s, _ivec(em, t, v))
        if v == 0:
            eq = em.b.or_(eq, em.b.icmp_signed("<", s, _ivec(em, t, 0)))
        if v == hi:
            eq = em.b.or_(eq, em.b.icmp_signed(">", s, _ivec(em, t, hi)))
        cond = eq if cond is None else em.b.and_(cond, eq)
    return cond


def _ranges(starts, his, clip=True):
    out = []
    for s, hi in zip(starts, his):
        if is_known(s):
            v = int(s)
            out.append([int(np.clip(v, 0, hi))] if clip else ([v] if 0 <= v <= hi else []))
        else:
            out.append(list(range(hi + 1)))
    return out


def _n_combos(ranges) -> int:
    return int(np.prod([len(r) for r in ranges], dtype=np.int64))


# ---------------------------------------------------------------------------------------------
# Dynamic slices.


def _dynamic_slice(em: Emitter, eqn, args):
    a, *starts = args
    starts = [s[()] for s in starts]
    sizes = eqn.params["slice_sizes"]
    dtype = out_dtype(eqn)
    his = [n - k for n, k in zip(a.shape, sizes)]
    ranges = _ranges(starts, his)
    if _n_combos(ranges) <= SELECT_STARTS:
        out = None
        for combo in itertools.product(*ranges):
            cond = _conds(em, starts, combo, his)
            piece = a[tuple(slice(c, c + k) for c, k in zip(combo, sizes))]
            if out is None:
                out = copy_array(piece)
            else:
                for idx in np.ndindex(piece.shape):
                    out[idx] = em.select(cond, piece[idx], out[idx], dtype)
        return out
    stored_a = stored(em, a, dtype)
    strides = _strides(a.shape)
    clamped = [_clamp(em, _i64(em, s), 0, hi) for s, hi in zip(starts, his)]
    base = _offset(em, clamped, range(a.ndim), strides)
    out = np.empty(tuple(sizes), object)
    for idx in np.ndindex(tuple(sizes)):
        out[idx] = stored_a.load(base, sum(i * st for i, st in zip(idx, strides)))
    return out


def _dynamic_update_slice(em: Emitter, eqn, args):
    a, update, *starts = args
    starts = [s[()] for s in starts]
    dtype = out_dtype(eqn)
    his = [n - k for n, k in zip(a.shape, update.shape)]
    ranges = _ranges(starts, his)
    out = copy_array(a)
    if _n_combos(ranges) <= SELECT_STARTS:
        for combo in itertools.product(*ranges):
            cond = _conds(em, starts, combo, his)
            region = tuple(slice(c, c + k) for c, k in zip(combo, update.shape))
            sub = out[region]
            for idx in np.ndindex(update.shape):
                sub[idx] = update[idx] if cond is None else em.select(cond, update[idx], sub[idx], dtype)
            out[region] = sub
        return out
    # each operand entry: the update's entry at (its position − start) where that is inside
    stored_u = stored(em, update, dtype)
    ustrides = _strides(update.shape)
    b = em.b
    i64 = ir.IntType(64)
    clamped = [_clamp(em, _i64(em, s), 0, hi) for s, hi in zip(starts, his)]
    for pos in np.ndindex(a.shape):
        inside, at = None, None
        for d, (p, s, k) in enumerate(zip(pos, clamped, update.shape)):
            rel = b.sub(_ivec(em, i64, p), s)
            ok = b.and_(b.icmp_signed(">=", rel, _ivec(em, i64, 0)), b.icmp_signed("<", rel, _ivec(em, i64, k)))
            inside = ok if inside is None else b.and_(inside, ok)
            rel = _clamp(em, rel, 0, k - 1)
            term = b.mul(rel, _ivec(em, i64, ustrides[d]))
            at = term if at is None else b.add(at, term)
        out[pos] = em.select(inside, stored_u.load(at), a[pos], dtype)
    return out


# ---------------------------------------------------------------------------------------------
# Gathers.


def _gather_map(eqn, operand_shape, idx) -> np.ndarray:
    """Where each output entry of the gather `eqn` comes from with the concrete indices `idx`:
    the operand's flat position, or -1 where the gather fills (XLA's gather semantics, with
    the index vector on the last axis of the indices)."""
    p = eqn.params
    dn, sizes = p["dimension_numbers"], p["slice_sizes"]
    fill = "FILL" in str(p["mode"])
    rank = len(operand_shape)
    window_dims = [d for d in range(rank) if d not in dn.collapsed_slice_dims and d not in dn.operand_batching_dims]
    out_shape = eqn.outvars[0].aval.shape
    batch_out = [d for d in range(len(out_shape)) if d not in dn.offset_dims]
    strides = _strides(operand_shape)
    his = [operand_shape[d] - sizes[d] for d in range(rank)]
    where = np.full(out_shape, -1, np.int64)
    for o in np.ndindex(out_shape):
        bpos = tuple(o[d] for d in batch_out)
        where[o] = _place(
            idx[bpos],
            dn.start_index_map,
            bpos,
            dn.operand_batching_dims,
            dn.start_indices_batching_dims,
            his,
            fill,
            [o[d] for d in dn.offset_dims],
            window_dims,
            strides,
        )
    return where


def _place(vector, index_dims, bpos, batching_dims, index_batching_dims, his, drop, window, window_dims, strides):
    """The flat operand position of one window entry: the start from the index `vector` (along
    `index_dims`) and the batch position (along `batching_dims`), then the window's
    coordinates; -1 where `drop` and the start is out of range, else the start clamped."""
    rank = len(his)
    start = [0] * rank
    for j, d in enumerate(index_dims):
        start[d] = int(vector[j])
    for k, d in enumerate(batching_dims):
        start[d] = bpos[index_batching_dims[k]]
    if drop and not all(0 <= start[d] <= his[d] for d in range(rank)):
        return -1
    start = [min(max(v, 0), hi) for v, hi in zip(start, his)]
    for w, d in zip(window, window_dims):
        start[d] += w
    return sum(v * st for v, st in zip(start, strides))


def _fill_value(eqn):
    dtype = out_dtype(eqn)
    value = eqn.params.get("fill_value")
    if value is None:
        value = (
            np.nan
            if dtype.kind == "f"
            else np.iinfo(dtype).min
            if dtype.kind == "i"
            else np.iinfo(dtype).max
            if dtype.kind == "u"
            else True
        )
    return np.asarray(value).astype(dtype)[()]


def _gather(em: Emitter, eqn, args):
    a, indices = args
    flat = a.reshape(-1)
    idx_dtype = np.dtype(eqn.invars[1].aval.dtype)
    dtype = out_dtype(eqn)
    fill = _fill_value(eqn)
    dnums = eqn.params["dimension_numbers"]
    # batching dimensions need nothing of their own: the index maps of the primitive itself
    # place each index vector's window, and its starts move it along `start_index_map` only
    if all(is_known(x) for x in indices.flat):
        idx = np.asarray([x for x in indices.flat], idx_dtype).reshape(indices.shape)
        where = _gather_map(eqn, a.shape, idx)
        out = np.empty(where.shape, object)
        for i in np.ndindex(where.shape):
            out[i] = flat[where[i]] if where[i] >= 0 else fill
        return out
    sizes = eqn.params["slice_sizes"]
    clip = "FILL" not in str(eqn.params["mode"])
    out_shape = eqn.outvars[0].aval.shape
    batch_dims = [d for d in range(len(out_shape)) if d not in dnums.offset_dims]
    out = np.empty(out_shape, object)
    out[...] = fill
    dims = list(dnums.start_index_map)
    his = [a.shape[d] - sizes[d] for d in dims]
    strides = _strides(a.shape)
    stored_a = None
    # where each output entry comes from when every start is 0; a start c_j moves the window
    # by c_j along operand dimension start_index_map[j] (windows are contiguous)
    zero = np.zeros(indices.shape, idx_dtype)
    where0 = _gather_map(eqn, a.shape, zero)
    for bpos in np.ndindex(indices.shape[:-1]):
        comps = [indices[bpos + (j,)] for j in range(indices.shape[-1])]
        mine = [o for o in np.ndindex(out_shape) if tuple(o[d] for d in batch_dims) == bpos]
        ranges = _ranges(comps, his, clip)
        if _n_combos(ranges) <= SELECT_STARTS:
            for n_combo, combo in enumerate(itertools.product(*ranges)):
                shift = sum(c * strides[d] for c, d in zip(combo, dims))
                cond = _conds(em, comps, combo, his)
                for o in mine:
                    value = flat[where0[o] + shift]
                    out[o] = (
                        value if (cond is None or (clip and n_combo == 0)) else em.select(cond, value, out[o], dtype)
                    )
            continue
        # memory: the entry at the window's position plus the (clamped) start's offset
        if stored_a is None:
            stored_a = stored(em, a, dtype)
        starts = [_i64(em, c) for c in comps]
        inside = None
        if not clip:
            b, i64 = em.b, ir.IntType(64)
            for s, hi in zip(starts, his):
                ok = b.and_(b.icmp_signed(">=", s, _ivec(em, i64, 0)), b.icmp_signed("<=", s, _ivec(em, i64, hi)))
                inside = ok if inside is None else b.and_(inside, ok)
        clamped = [_clamp(em, s, 0, hi) for s, hi in zip(starts, his)]
        base = _offset(em, clamped, dims, strides)
        for o in mine:
            value = stored_a.load(base, int(where0[o]))
            out[o] = value if inside is None else em.select(inside, value, fill, dtype)
    return out


# ---------------------------------------------------------------------------------------------
# Scatters (known indices, or a few places).


def _scatter_targets(eqn, operand_shape, updates_shape, idx) -> np.ndarray:
    """For each update entry (flat), the flat operand position it lands on, or -1 where XLA
    drops it (`FILL_OR_DROP` and a window outside the operand); starts clamped otherwise."""
    p = eqn.params
    dn = p["dimension_numbers"]
    drop = "FILL" in str(p["mode"])
    rank = len(operand_shape)
    scatter_dims = [d for d in range(len(updates_shape)) if d not in dn.update_window_dims]
    window_dims = [d for d in range(rank) if d not in dn.inserted_window_dims and d not in dn.operand_batching_dims]
    window_size = dict(zip(window_dims, (updates_shape[d] for d in dn.update_window_dims)))
    strides = _strides(operand_shape)
    his = [operand_shape[d] - window_size.get(d, 1) for d in range(rank)]
    target = np.full(int(np.prod(updates_shape, dtype=int)), -1, np.int64)
    for n, u in enumerate(np.ndindex(tuple(updates_shape))):
        spos = tuple(u[d] for d in scatter_dims)
        target[n] = _place(
            idx[spos],
            dn.scatter_dims_to_operand_dims,
            spos,
            dn.operand_batching_dims,
            dn.scatter_indices_batching_dims,
            his,
            drop,
            [u[d] for d in dn.update_window_dims],
            window_dims,
            strides,
        )
    return target


def _scatter(combine: str | None):
    def rule(em: Emitter, eqn, args):
        a, indices, updates = args
        dtype = out_dtype(eqn)
        dnums = eqn.params["dimension_numbers"]
        if dnums.operand_batching_dims:
            raise Unsupported("scatter with batching dimensions")
        idx_dtype = np.dtype(eqn.invars[1].aval.dtype)
        emit = emit_float if dtype.kind == "f" else emit_int
        flat_u = updates.reshape(-1)
        comps = list(indices.reshape(-1))
        ranges = [[int(c)] if is_known(c) else None for c in comps]
        if any(r is None for r in ranges):
            # every place a lane's indices can reach: small index spaces only
            his = [a.shape[d] for d in dnums.scatter_dims_to_operand_dims] * (
                len(comps) // max(1, len(dnums.scatter_dims_to_operand_dims))
            )
            ranges = [[int(c)] if is_known(c) else list(range(hi)) for c, hi in zip(comps, his)]
            n = _n_combos(ranges)
            if n > SELECT_STARTS and n * max(1, flat_u.size) > SCATTER_SELECTS:
                raise Unsupported(f"scatter with indices computed at run time ({_n_combos(ranges)} places)")
        out = copy_array(a)
        base = copy_array(a)
        combos = list(itertools.product(*ranges))
        if len(combos) > 1:  # a select per place and update: counted against the program's size
            em.count(len(combos) * flat_u.size)
        for combo in combos:
            idx = np.asarray(combo, idx_dtype).reshape(indices.shape)
            target = _scatter_targets(eqn, a.shape, updates.shape, idx)
            if combine == "add" and len(set(t for t in target if t >= 0)) < int(np.sum(target >= 0)):
                raise Unsupported("scatter-add of several updates onto one entry")
            cond = None
            for c, v in zip(comps, combo):
                if not is_known(c):
                    eq = em.b.icmp_signed("==", c, em.const(v, idx_dtype))
                    cond = eq if cond is None else em.b.and_(cond, eq)
            flat_out, flat_base = out.reshape(-1), base.reshape(-1)
            for u, t in enumerate(target):
                if t < 0:
                    continue
                value = flat_u[u] if combine is None else emit(em, combine, dtype, [flat_base[t], flat_u[u]], None)
                flat_out[t] = value if cond is None else em.select(cond, value, flat_out[t], dtype)
            out = flat_out.reshape(a.shape)
        return out

    return rule


RULES.update(
    {
        "dynamic_slice": _dynamic_slice,
        "dynamic_update_slice": _dynamic_update_slice,
        "gather": _gather,
        "scatter": _scatter(None),
        "scatter-add": _scatter("add"),
        "scatter_add": _scatter("add"),
        "scatter-mul": _scatter("mul"),
        "scatter_mul": _scatter("mul"),
    }
)
