"""Loops and branches of the native translation, with the lanes masked as under `jax.vmap`.

- `while`: a loop that runs while any lane of the current mask still satisfies its condition.
  A lane whose condition is false keeps its carry (a select per entry), as `vmap` of a while
  loop does; its body is emitted under the mask of the lanes still iterating, so that loops
  nested in it stop when those lanes are done. A condition with an entry per element of the
  carries' leading axes (`jax.vmap` of a loop inside the member's program) holds while any
  entry does, and an element whose entry is false keeps its carry, as XLA's loop does; one at
  the kernel's top level whose condition every lane computes alike (`uniform`) keeps none.
- `scan`: a counted loop (the count is the same in every lane); the carry is phis in the
  loop's head (as for `while`), the per-iteration inputs and outputs in arrays indexed by the
  counter. Short scans are unrolled, unless unrolling would take the program past
  `MAX_ENTRIES` (`unroll_policy`): the stage loops of a composition and the solves of a
  Gauss–Legendre step then stay loops.
- `cond`: a known index picks its branch; otherwise every branch is emitted under the mask of
  its lanes and the outputs are selected lane by lane.
"""

from __future__ import annotations

import math

import numpy as np
from llvmlite import ir

from . import row_calls
from . import rows as _rows
from .loops import extra_entries
from .lower import RULES, eval_closed
from .row_program import row_equation
from .rows import ROWS_MIN
from .values import MAX_ENTRIES, Emitter, Unsupported, is_known

__all__ = ["SHORT_SCAN", "UNROLL_BUDGET", "ROLLED_BUDGET", "POLICIES", "unroll_policy", "entries"]

SHORT_SCAN = 4
"""Scans of at most this many iterations are unrolled (no loop, no arrays in memory) ..."""

UNROLL_BUDGET = 20_000
"""... and longer ones whose body, counted in entries computed (`_size`), times their length
stays within this budget: their counter is then known in each copy, so that indexing by it
(the column loops of small matrix factorisations) costs no code."""


def _size(jaxpr) -> int:
    """Entries a jaxpr computes (each equation's outputs; nested jaxprs counted once)."""
    from jax.extend import core as jcore

    n = 0
    for eqn in jaxpr.eqns:
        n += sum(math.prod(v.aval.shape) for v in eqn.outvars if hasattr(v.aval, "shape")) or 1
        for v in eqn.params.values():
            for x in v if isinstance(v, (tuple, list)) else [v]:
                if isinstance(x, jcore.ClosedJaxpr):
                    n += _size(x.jaxpr)
                elif isinstance(x, jcore.Jaxpr):
                    n += _size(x)
    return n


ROLLED_BUDGET = 2_000
"""The unroll budget of a program that unrolled by the rules above would pass `MAX_ENTRIES`
(`unroll_policy`): only scans of small bodies (the column loops of small factorisations) are
unrolled; the rest (a composition's stages, a Gauss–Legendre step's substeps and untested
sweeps) run as loops. A loop computes what its unrolled copies compute, in the same order."""

POLICIES = ((SHORT_SCAN, UNROLL_BUDGET), (0, UNROLL_BUDGET), (0, ROLLED_BUDGET))
"""`(short, budget)` pairs, from the most unrolled: a scan is unrolled when its length is at
most `short` or its length times its body's size is at most `budget`."""


def _unrolled(length: int, body, policy) -> bool:
    short, budget = policy
    return length <= short or length * _size(body) <= budget


def _entries_held(shape, rows: bool) -> int:
    """Entries of an array of `shape`; with `rows`, a long leading axis counted once (`Rows`)."""
    shape = tuple(shape)
    if rows and shape and shape[0] >= ROWS_MIN:
        shape = shape[1:]
    return math.prod(shape)


def entries(jaxpr, policy, rows: bool = False) -> int:
    """The entries the translation of `jaxpr` counts (`Emitter.count`) with the unrolling
    `policy`: an unrolled scan's body once per iteration, every branch of a `cond`, a
    `custom_linear_solve` its solve, a factorisation, solve or contraction that runs as loops
    what it stores and its loop bodies (`loops.extra_entries`), any other nested jaxpr once
    (a bound: a branch known while translating is the only one translated)."""
    from jax.extend import core as jcore

    n = 0
    for eqn in jaxpr.eqns:
        eqn = _one_row(eqn) if rows else eqn
        n += sum(_entries_held(v.aval.shape, rows) for v in eqn.outvars if hasattr(v.aval, "shape"))
        n += extra_entries(eqn)
        p = eqn.params
        if eqn.primitive.name == "scan":
            body = p["jaxpr"].jaxpr
            long = rows and p["length"] >= ROWS_MIN  # a loop keeping its records as rows (`_scan`)
            n += entries(body, policy) * (p["length"] if not long and _unrolled(p["length"], body, policy) else 1)
            continue
        if eqn.primitive.name == "custom_linear_solve":
            n += entries(p["jaxprs"].solve.jaxpr, policy)
            continue
        looped = _looped_call(eqn, policy)
        if looped is not None and not (rows and looped[1] >= ROWS_MIN):  # one row's program, in a loop (`row_calls`)
            row_eqn, _ = looped
            n += entries(row_calls.row_body(row_eqn), policy)
            n += sum(math.prod(v.aval.shape) for v in row_eqn.outvars)
            continue
        for v in p.values():
            for x in v if isinstance(v, (tuple, list)) else [v]:
                if isinstance(x, jcore.ClosedJaxpr):
                    n += entries(x.jaxpr, policy)
                elif isinstance(x, jcore.Jaxpr):
                    n += entries(x, policy)
    return n


def _one_row(eqn):
    """`eqn`, or, where it is a loop, a branch or a solve that keeps the rows of its long
    operands apart, its equation of one row (`row_program.row_equation`), which the translation
    emits once in a loop over the rows (`rows.apply`); its outputs are then one row's."""
    name = eqn.primitive.name
    if name not in ("while", "scan", "cond", "custom_linear_solve") or (
        name == "scan" and eqn.params["length"] >= ROWS_MIN
    ):
        return eqn
    lead = [tuple(getattr(v.aval, "shape", ()))[:1] for v in eqn.invars]
    n = next((s[0] for s in lead if s and s[0] >= ROWS_MIN), None)
    found = None if n is None else row_equation(eqn, [0 if s == (n,) else None for s in lead], n)
    if found is None or any(a not in (0, None) for a in found[1]):
        return eqn
    return found[0]


def unroll_policy(jaxpr, rows: bool = False):
    """The most unrolled of `POLICIES` whose program stays within `MAX_ENTRIES` (the last,
    the least unrolled, when none does: the translation then refuses the program). A function
    of the jaxpr alone, so the kernel of a program is always the same code. With `rows` (long
    arrays held as `Rows`), a long leading axis counts once: the policy does not depend on it."""
    for policy in POLICIES:
        if entries(jaxpr, policy, rows) <= MAX_ENTRIES:
            return policy
    return POLICIES[-1]


PHI_MIN_ENTRIES = 256
"""A loop whose changing carries have at least this many entries holds them as phis in its
head (`_heads`, `_back`): one instruction per entry and iteration's way in. Smaller ones keep
an alloca per entry (`_slots`), stored before the loop and at the latch and loaded in the head
and after the loop, which LLVM's mem2reg turns into phis: the same values, but four or five
lines of IR per entry (LLVM's time grows with them, `AUTO_MAX_IR_LINES`) and, as phis made
here, a different schedule of the same instructions (the rigid body's sweep kernel, whose
loops are all smaller, is then the code it was measured with)."""


def _as_phis(init, fixed) -> bool:
    """Whether a loop holds its carries as phis (`PHI_MIN_ENTRIES`)."""
    return sum(math.prod(np.shape(x)) for x, keep in zip(init, fixed) if not keep) >= PHI_MIN_ENTRIES


def _slots(em: Emitter, values, dtypes, fixed):
    """Allocas holding each entry of the carries that change (None for those that do not)."""
    slots = []
    for x, dtype, keep in zip(values, dtypes, fixed):
        if keep:
            slots.append(None)
            continue
        arr = np.empty(x.shape, object)
        for idx in np.ndindex(x.shape):
            arr[idx] = em.alloca(em.vtype(dtype))
            em.b.store(em.vec(x[idx], dtype), arr[idx])
        slots.append(arr)
    return slots


def _load(em: Emitter, slots, values, dtypes):
    out = []
    for s, x, dtype in zip(slots, values, dtypes):
        if s is None:
            out.append(x)
            continue
        arr = np.empty(s.shape, object)
        for idx in np.ndindex(s.shape):
            arr[idx] = em.b.load(s[idx], typ=em.vtype(dtype))
        out.append(arr)
    return out


def _store(em: Emitter, slots, new, old, dtypes, where):
    for s, n, o, dtype in zip(slots, new, old, dtypes):
        if s is None:
            continue
        for idx in np.ndindex(s.shape):
            value = n[idx] if where is None else em.select(where, n[idx], o[idx], dtype)
            em.b.store(em.vec(value, dtype), s[idx])


def _heads(em: Emitter, values, dtypes, fixed, pre):
    """The carries at the loop's head: a phi per entry of those that change, coming in from the
    block before the loop (`pre`) with the entry's value (`_back` adds the other way in); the
    values themselves for those that do not. Called first in the head; each phi goes before the
    ones made before it (in the other order the rigid body's sweep, had its loops phis, ran more
    machine instructions per step, `benchmarks/native_instructions.py`). Returns (phis, values)."""
    phis, out = [], []
    for x, dtype, keep in zip(values, dtypes, fixed):
        if keep:
            phis.append(None)
            out.append(x)
            continue
        arr = np.empty(x.shape, object)
        for idx in np.ndindex(x.shape):
            head = em.b.block
            em.b.position_at_start(head)
            arr[idx] = em.b.phi(em.vtype(dtype))
            em.b.position_at_end(head)
            arr[idx].add_incoming(em.vec(x[idx], dtype), pre)
        phis.append(arr)
        out.append(arr)
    return phis, out


def _back(em: Emitter, phis, new, old, dtypes, where):
    """The carries the next iteration starts from, coming into the head's phis from the current
    block (which then branches back): the body's values, or where `where` is false the old ones."""
    for ph, n, o, dtype in zip(phis, new, old, dtypes):
        if ph is None:
            continue
        for idx in np.ndindex(ph.shape):
            value = n[idx] if where is None else em.select(where, n[idx], o[idx], dtype)
            ph[idx].add_incoming(em.vec(value, dtype), em.b.block)


def _while(em: Emitter, eqn, args):
    p = eqn.params
    cc, bc = p["cond_nconsts"], p["body_nconsts"]
    cconsts, bconsts, init = args[:cc], args[cc : cc + bc], args[cc + bc :]
    cond_j, body_j = p["cond_jaxpr"], p["body_jaxpr"]
    body_in = body_j.jaxpr.invars[bc:]
    fixed = [o is i for o, i in zip(body_j.jaxpr.outvars, body_in)]
    dtypes = [np.dtype(v.aval.dtype) for v in body_in]
    phi = _as_phis(init, fixed)
    slots = None if phi else _slots(em, init, dtypes, fixed)
    b = em.b
    fn = b.function
    em.enter_loop(b.block)  # until its exit, after the loop
    head, body, done = (
        fn.append_basic_block("while.head"),
        fn.append_basic_block("while.body"),
        fn.append_basic_block("while.done"),
    )
    pre = b.block
    b.branch(head)
    b.position_at_end(head)
    phis, cur = _heads(em, init, dtypes, fixed, pre) if phi else (None, _load(em, slots, init, dtypes))
    (pred,) = eval_closed(em, cond_j, list(cconsts) + cur)
    elements = np.asarray(pred, object)
    unknown = [e for e in elements.reshape(-1) if not is_known(e)]
    if any(bool(e) for e in elements.reshape(-1) if is_known(e)):
        raise Unsupported("a while loop whose condition is always true")
    if not unknown:
        b.branch(done)
        b.position_at_end(done)
        em.exit_loop()
        return list(init)
    if em.mask is None and not elements.shape and id(eqn) in em.uniform:
        # every lane runs the same iterations (`uniform.uniform_loops`): no lane keeps its carry
        b.cbranch(b.extract_element(unknown[0], ir.Constant(ir.IntType(32), 0)), body, done)
        b.position_at_end(body)
        new = eval_closed(em, body_j, list(bconsts) + cur)
        _back(em, phis, new, cur, dtypes, None) if phi else _store(em, slots, new, cur, dtypes, None)
        b.branch(head)
        b.position_at_end(done)
        em.exit_loop()
        return cur if phi else _load(em, slots, init, dtypes)
    anywhere = unknown[0]
    for e in unknown[1:]:  # a predicate per element (jax.vmap of a loop): while any holds
        anywhere = b.or_(anywhere, e)
    active = em.mask_and(anywhere)
    b.cbranch(em.any_lane(active), body, done)
    b.position_at_end(body)
    outer, em.mask = em.mask, active
    new = eval_closed(em, body_j, list(bconsts) + cur)
    em.mask = outer
    if elements.shape:
        new = [_held(em, elements, n, c, dtype) for n, c, dtype in zip(new, cur, dtypes)]
    _back(em, phis, new, cur, dtypes, active) if phi else _store(em, slots, new, cur, dtypes, active)
    b.branch(head)
    b.position_at_end(done)
    em.exit_loop()
    return cur if phi else _load(em, slots, init, dtypes)  # the phis: the head is the exit's only predecessor


def _held(em: Emitter, elements, new, cur, dtype):
    """A carry of a while loop whose predicate has one entry per element of the carry's
    leading axes (`elements`, as `jax.vmap` of a loop makes it): the body's value where the
    element's predicate holds, else the carry as it was (XLA's select)."""
    k = elements.ndim
    if np.shape(new)[:k] != elements.shape:
        raise Unsupported(
            f"a while loop with a predicate of shape {elements.shape} on a carry of shape {np.shape(new)}"
        )
    out = np.empty(np.shape(new), object)
    for idx in np.ndindex(out.shape):
        out[idx] = em.select(elements[idx[:k]], new[idx], cur[idx], dtype)
    return out


def _array_slots(em: Emitter, length: int, shape, dtype):
    """An alloca of `length` vectors per entry of `shape` (a scan's inputs or outputs)."""
    arr = np.empty(shape, object)
    t = ir.ArrayType(em.vtype(dtype), length)
    for idx in np.ndindex(shape):
        arr[idx] = (em.alloca(t), t)
    return arr


def _at(em: Emitter, slot, i):
    """A pointer to entry `i` (an i64) of an array slot, typed as its element."""
    ptr, t = slot
    zero = ir.Constant(ir.IntType(64), 0)
    return em.b.bitcast(em.b.gep(ptr, [zero, i], source_etype=t), t.element.as_pointer())


def _scan(em: Emitter, eqn, args):
    p = eqn.params
    length, nc, ncar, reverse = p["length"], p["num_consts"], p["num_carry"], p["reverse"]
    closed = p["jaxpr"]
    consts, init, xs = list(args[:nc]), list(args[nc : nc + ncar]), list(args[nc + ncar :])
    order = range(length - 1, -1, -1) if reverse else range(length)
    long = em.rows and length >= ROWS_MIN  # records kept as rows in memory (`rows`)
    outer_rows, em.rows = em.rows, False  # the body reads and makes entries
    try:
        return _scan_emit(em, closed, length, nc, ncar, reverse, order, consts, init, xs, long)
    finally:
        em.rows = outer_rows


def _scan_emit(em, closed, length, nc, ncar, reverse, order, consts, init, xs, long):
    if not long and _unrolled(length, closed.jaxpr, em.unroll or POLICIES[0]):  # a long one: rows
        xs = [_rows.materialize(em, x) for x in xs]
        carry, ys = init, []
        for i in order:
            outs = eval_closed(em, closed, consts + carry + [x[i, ...] for x in xs])
            carry, y = outs[:ncar], outs[ncar:]
            ys.append(y)
        if reverse:
            ys = ys[::-1]
        stacked = [np.stack([y[k] for y in ys]) if ys else None for k in range(len(closed.jaxpr.outvars) - ncar)]
        return carry + stacked

    jaxpr = closed.jaxpr
    body_in = jaxpr.invars[nc : nc + ncar]
    fixed = [o is i for o, i in zip(jaxpr.outvars[:ncar], body_in)]
    dtypes = [np.dtype(v.aval.dtype) for v in body_in]
    phi = _as_phis(init, fixed)
    slots = None if phi else _slots(em, init, dtypes, fixed)
    b = em.b
    i64 = ir.IntType(64)
    # the inputs, stored in arrays indexed by the counter (known entries stay known when all
    # iterations share them)
    x_dtypes = [np.dtype(v.aval.dtype) for v in jaxpr.invars[nc + ncar :]]
    x_slots = []
    for x, dtype in zip(xs, x_dtypes):
        if isinstance(x, _rows.Rows):  # read row by row where they are
            x_slots.append(x)
            continue
        arr = _array_slots(em, length, x.shape[1:], dtype)
        for idx in np.ndindex(x.shape[1:]):
            for i in range(length):
                b.store(em.vec(x[(i,) + idx], dtype), _at(em, arr[idx], ir.Constant(i64, i)))
        x_slots.append(arr)
    y_avals = [v.aval for v in jaxpr.outvars[ncar:]]
    if long:
        y_slots = [_rows.memory(em, length, tuple(a.shape), a.dtype) for a in y_avals]
    else:
        y_slots = [_array_slots(em, length, a.shape, a.dtype) for a in y_avals]

    counter = em.alloca(i64)
    b.store(ir.Constant(i64, 0), counter)
    fn = b.function
    em.enter_loop(b.block)  # until its exit, after the loop
    head, body, done = (
        fn.append_basic_block("scan.head"),
        fn.append_basic_block("scan.body"),
        fn.append_basic_block("scan.done"),
    )
    pre = b.block
    b.branch(head)
    b.position_at_end(head)
    if phi:
        phis, cur = _heads(em, init, dtypes, fixed, pre)  # also the loop's results, after it
    k = b.load(counter, typ=i64)
    b.cbranch(b.icmp_signed("<", k, ir.Constant(i64, length)), body, done)
    b.position_at_end(body)
    i = b.sub(ir.Constant(i64, length - 1), k) if reverse else k
    if not phi:
        cur = _load(em, slots, init, dtypes)
    x_now = []
    for arr, dtype in zip(x_slots, x_dtypes):
        if isinstance(arr, _rows.Rows):
            x_now.append(_rows.row_at(em, arr, i))
            continue
        v = np.empty(arr.shape, object)
        for idx in np.ndindex(arr.shape):
            v[idx] = b.load(_at(em, arr[idx], i), typ=em.vtype(dtype))
        x_now.append(v)
    outs = eval_closed(em, closed, consts + cur + x_now)
    if not phi:
        _store(em, slots, outs[:ncar], cur, dtypes, None)
    for arr, y, a in zip(y_slots, outs[ncar:], y_avals):
        if long:
            _rows.store_row(em, arr, i, y)
            continue
        for idx in np.ndindex(arr.shape):
            b.store(em.vec(y[idx], a.dtype), _at(em, arr[idx], i))
    b.store(b.add(b.load(counter, typ=i64), ir.Constant(i64, 1)), counter)
    if phi:
        _back(em, phis, outs[:ncar], cur, dtypes, None)  # from the block that branches back
    b.branch(head)
    b.position_at_end(done)
    em.exit_loop()
    carry = cur if phi else _load(em, slots, init, dtypes)
    if long:
        return carry + y_slots
    ys = []
    for arr, a in zip(y_slots, y_avals):
        out = np.empty((length,) + tuple(a.shape), object)
        for idx in np.ndindex(arr.shape):
            for n in range(length):
                out[(n,) + idx] = b.load(_at(em, arr[idx], ir.Constant(i64, n)), typ=em.vtype(a.dtype))
        ys.append(out)
    return carry + ys


def _cond(em: Emitter, eqn, args):
    branches = eqn.params["branches"]
    index, ops = args[0][()], list(args[1:])
    n = len(branches)
    if is_known(index):
        return eval_closed(em, branches[int(np.clip(int(index), 0, n - 1))], ops)
    b = em.b
    idx_dtype = np.dtype(eqn.invars[0].aval.dtype)
    conds, results = [], []
    outer = em.mask
    for k, branch in enumerate(branches):
        c = b.icmp_signed("==", index, em.const(k, idx_dtype))
        if k == 0:
            c = b.or_(c, b.icmp_signed("<", index, em.const(0, idx_dtype)))
        if k == n - 1:
            c = b.or_(c, b.icmp_signed(">", index, em.const(n - 1, idx_dtype)))
        conds.append(c)
        em.mask = em.mask_and(c) if outer is not None else c
        results.append(eval_closed(em, branch, ops))
        em.mask = outer
    out = []
    for j, v in enumerate(eqn.outvars):
        dtype = np.dtype(v.aval.dtype)
        r = results[-1][j]
        merged = np.empty(r.shape, object)
        for idx in np.ndindex(r.shape):
            e = r[idx]
            for k in range(n - 2, -1, -1):
                e = em.select(conds[k], results[k][j][idx], e, dtype)
            merged[idx] = e
        out.append(merged)
    return out


def _looped_call(eqn, policy):
    """`row_calls.row_call(eqn)` where the call's rows run as a loop under the unrolling
    `policy` (as a scan of as many iterations as rows would) and one row's program is not small
    (`row_calls.MIN_ROW_SIZE`); else None (its entries written out)."""
    if eqn.primitive.name not in row_calls.CALLS or _size(row_calls.row_body(eqn)) < 2 * row_calls.MIN_ROW_SIZE:
        return None  # not a call, or too small to have two rows of `MIN_ROW_SIZE` (spares `row_call`'s walk)
    found = row_calls.row_call(eqn)
    if found is None or _unrolled(found[1], row_calls.row_body(found[0]), policy):
        return None
    return found if _size(row_calls.row_body(found[0])) >= row_calls.MIN_ROW_SIZE else None


def _call_rule(plain):
    """The rule of a call: a call vmapped over its rows (`row_calls`) as a loop over them where
    the unroll policy keeps such a scan a loop, else `plain` (its program entered)."""

    def rule(em: Emitter, eqn, args):
        if not any(isinstance(a, _rows.Rows) for a in args):  # rows of a long axis: `rows.apply`
            looped = _looped_call(eqn, em.unroll or POLICIES[0])
            if looped is not None:
                return row_calls.emit(em, eqn, args, looped[1], RULES)
        return plain(em, eqn, args)

    return rule


RULES.update({"while": _while, "scan": _scan, "cond": _cond})
RULES.update({name: _call_rule(RULES[name]) for name in row_calls.CALLS})
