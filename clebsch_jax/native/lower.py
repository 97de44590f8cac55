"""The translation of a jaxpr of one member into LLVM IR, entry by entry (`values`).

`eval_jaxpr(em, jaxpr, consts, args)` walks the equations and applies each primitive's rule
(`RULES`) to the entries of its operands: elementwise primitives emit one vector instruction per
entry (or fold known entries in NumPy, for the exactly rounded ones: their rules are in
`clebsch_jax.native.elementwise`); structural primitives re-index the entry arrays; contractions
and reductions are unrolled in index order (large contractions run as loops over stack arrays,
`clebsch_jax.native.loops`). Loops and branches are in
`clebsch_jax.native.control`, dynamic indexing in `clebsch_jax.native.indexing`, small dense
linear algebra in `clebsch_jax.native.linalg`: each adds its rules to `RULES`. A primitive
without a rule raises `Unsupported` with its name.
"""

from __future__ import annotations

import collections
import math

import numpy as np
from jax.extend import core as jcore

from .elementwise import (
    ELEMENTWISE,
    FOLD,
    LIBM,
    clamp,
    convert,
    convert_array,
    elementwise_rule,
    emit_bool,
    emit_float,
    emit_int,
    in_dtype,
    out_dtype,
    product,
    select_n,
)
from . import axis_loops, fused, loops
from . import rows as _rows
from .values import Emitter, Unsupported, is_known, known_array

__all__ = ["eval_jaxpr", "RULES", "copy_array"]


def eval_jaxpr(em: Emitter, jaxpr, consts, args) -> list:
    """The outputs (entry arrays) of `jaxpr` (an open jaxpr) on entry arrays `consts`, `args`."""
    with axis_loops.enter(em):  # the buffers its sums' loops store
        return _eval(em, jaxpr, consts, args)


def _eval(em: Emitter, jaxpr, consts, args) -> list:
    env: dict = {}
    live = _live(jaxpr)
    uses = collections.Counter(v for e in live for v in e.invars if not isinstance(v, jcore.Literal))
    live = {id(e) for e in live}
    dropped: set = set()  # outputs of unneeded equations not translated
    uses.update(v for v in jaxpr.outvars if not isinstance(v, jcore.Literal))

    def read(v):
        if isinstance(v, jcore.Literal):
            return known_array(np.asarray(v.val, v.aval.dtype))
        return env[v]

    for v, x in zip(jaxpr.constvars, consts):
        env[v] = x
    for v, x in zip(jaxpr.invars, args):
        env[v] = x
    for eqn in jaxpr.eqns:
        rule = RULES.get(eqn.primitive.name)
        if rule is None:
            raise Unsupported(f"primitive {eqn.primitive.name!r}")
        if id(eqn) not in live and (
            eqn.primitive.name in LIBM or any(v in dropped for v in eqn.invars if not isinstance(v, jcore.Literal))
        ):
            dropped.update(eqn.outvars)
            continue
        args = [read(v) for v in eqn.invars]
        if id(eqn) not in live and any(isinstance(a, fused.Lazy) for a in args):
            dropped.update(eqn.outvars)  # a sum the outputs do not need: its loop is not emitted
            continue
        if not em.rows and fused.defers(eqn):  # emitted where it is used (a sum over an axis: a loop)
            env[eqn.outvars[0]] = fused.Lazy(eqn, args, uses[eqn.outvars[0]])
            continue
        if em.rows or eqn.primitive.name not in _TAKES_LAZY:
            args = [fused.materialize(em, a, RULES) for a in args]
        outs = _rows.apply(em, eqn, args, RULES) if em.rows else None  # long arrays held as rows
        if outs is None:
            em.count(sum(math.prod(v.aval.shape) for v in eqn.outvars if hasattr(v.aval, "shape")))
            outs = rule(em, eqn, args)
        if not eqn.primitive.multiple_results:
            outs = [outs]
        for v, x in zip(eqn.outvars, outs):
            if not isinstance(v, jcore.DropVar):
                env[v] = x
    return [fused.materialize(em, read(v), RULES) for v in jaxpr.outvars]


def _live(jaxpr) -> list:
    """The equations of `jaxpr` that its outputs need, or with effects. Of the others, those
    LLVM would keep are not translated, nor what follows from them: libm calls (they may set
    `errno`) and sums of a `fused.Lazy` (loops, with such calls in them): a gradient's primal
    value left unused. The rest is translated as before (LLVM deletes it)."""
    live = {v for v in jaxpr.outvars if not isinstance(v, jcore.Literal)}
    kept = []
    for eqn in reversed(jaxpr.eqns):
        if eqn.effects or any(v in live for v in eqn.outvars if not isinstance(v, jcore.DropVar)):
            kept.append(eqn)
            live.update(v for v in eqn.invars if not isinstance(v, jcore.Literal))
    return kept[::-1]


def eval_closed(em: Emitter, closed, args) -> list:
    """`eval_jaxpr` of a closed jaxpr (its constants become known entries, or arrays of them)."""
    return eval_jaxpr(em, closed.jaxpr, [known_array(np.asarray(c)) for c in closed.consts], args)


# ---------------------------------------------------------------------------------------------
# Re-indexing primitives (no code).


def copy_array(a):
    out = np.empty(a.shape, object)
    out[...] = a
    return out


def _broadcast_in_dim(em, eqn, args):
    a, shape, dims = args[0], eqn.params["shape"], eqn.params["broadcast_dimensions"]
    tmp = [1] * len(shape)
    for i, d in enumerate(dims):
        tmp[d] = a.shape[i]
    return copy_array(np.broadcast_to(a.reshape(tmp), shape))


def _reshape(em, eqn, args):
    return copy_array(args[0].reshape(eqn.params["new_sizes"]))


def _squeeze(em, eqn, args):
    return copy_array(np.squeeze(args[0], axis=tuple(eqn.params["dimensions"])))


def _expand_dims(em, eqn, args):
    return copy_array(np.expand_dims(args[0], tuple(eqn.params["dimensions"])))


def _transpose(em, eqn, args):
    return copy_array(np.transpose(args[0], eqn.params["permutation"]))


def _slice(em, eqn, args):
    p = eqn.params
    strides = p["strides"] or (1,) * len(p["start_indices"])
    idx = tuple(slice(s, e, st) for s, e, st in zip(p["start_indices"], p["limit_indices"], strides))
    return copy_array(args[0][idx])


def _concatenate(em, eqn, args):
    return np.concatenate(args, axis=eqn.params["dimension"])


def _stack(em, eqn, args):
    return np.stack(args, axis=eqn.params["axis"])


def _unstack(em, eqn, args):
    moved = np.moveaxis(args[0], eqn.params["axis"], 0)
    return [copy_array(moved[i, ...]) for i in range(moved.shape[0])]


def _rev(em, eqn, args):
    return copy_array(np.flip(args[0], axis=tuple(eqn.params["dimensions"])))


def _split(em, eqn, args):
    cuts = np.cumsum(eqn.params["sizes"])[:-1]
    return [copy_array(x) for x in np.split(args[0], cuts, axis=eqn.params["axis"])]


def _pad(em, eqn, args):
    a, value = args
    fill = value[()]
    out = a
    for axis, (lo, hi, interior) in enumerate(eqn.params["padding_config"]):
        n = out.shape[axis]
        size = n + max(n - 1, 0) * interior
        shape = list(out.shape)
        shape[axis] = size
        grown = np.empty(shape, object)
        grown[...] = fill
        sel = [slice(None)] * out.ndim
        sel[axis] = slice(0, size, interior + 1)
        grown[tuple(sel)] = out
        if lo < 0:
            grown = np.take(grown, range(-lo, size), axis=axis)
            lo = 0
        if hi < 0:
            grown = np.take(grown, range(0, grown.shape[axis] + hi), axis=axis)
            hi = 0
        widths = [(0, 0)] * out.ndim
        widths[axis] = (lo, hi)
        padded = np.empty([s + w[0] + w[1] for s, w in zip(grown.shape, widths)], object)
        padded[...] = fill
        sel = tuple(slice(w[0], w[0] + s) for s, w in zip(grown.shape, widths))
        padded[sel] = grown
        out = padded
    return out


def _iota(em, eqn, args):
    p = eqn.params
    shape, dim = p["shape"], p["dimension"]
    a = np.arange(shape[dim], dtype=p["dtype"]).reshape([-1 if i == dim else 1 for i in range(len(shape))])
    return known_array(np.broadcast_to(a, shape))


def _identity(em, eqn, args):
    return [copy_array(a) for a in args] if eqn.primitive.multiple_results else copy_array(args[0])


def _nothing(em, eqn, args):
    return []


def _platform_index(em, eqn, args):
    """The branch of `lax.platform_dependent` that XLA's CPU backend takes: the entry naming
    "cpu", else the default (None) entry."""
    platforms = eqn.params["platforms"]
    for i, names in enumerate(platforms):
        if names is not None and "cpu" in names:
            return known_array(np.asarray(i, np.int32))
    return known_array(np.asarray(platforms.index(None), np.int32))


# ---------------------------------------------------------------------------------------------
# Contractions and reductions, unrolled in index order.


def _sum_products(em: Emitter, pairs, dtype):
    """Σ a·b over `pairs` in order, with known products folded."""
    acc = None
    for a, c in pairs:
        p = product(em, a, c, dtype)
        if acc is None:
            acc = p
        elif is_known(acc) and is_known(p):
            acc = (np.asarray(acc, dtype) + np.asarray(p, dtype))[()]
        else:
            acc = (emit_float if dtype.kind == "f" else emit_int)(em, "add", dtype, [acc, p], None)
    return np.zeros((), dtype)[()] if acc is None else acc


def _dot_general(em, eqn, args):
    lhs, rhs = args
    (lc, rc), (lb, rb) = eqn.params["dimension_numbers"]
    dtype = out_dtype(eqn)
    lhs = convert_array(em, lhs, in_dtype(eqn), dtype) if in_dtype(eqn) != dtype else lhs
    rhs = convert_array(em, rhs, in_dtype(eqn, 1), dtype) if in_dtype(eqn, 1) != dtype else rhs
    lf = [d for d in range(lhs.ndim) if d not in lc and d not in lb]
    rf = [d for d in range(rhs.ndim) if d not in rc and d not in rb]
    L = np.transpose(lhs, list(lb) + lf + list(lc))
    R = np.transpose(rhs, list(rb) + rf + list(rc))
    nb, nk = len(lb), len(lc)
    bshape = L.shape[:nb]
    lfs, rfs = L.shape[nb : L.ndim - nk], R.shape[nb : R.ndim - nk]
    K = int(np.prod(L.shape[L.ndim - nk :], dtype=int))
    L = L.reshape(bshape + lfs + (K,))
    R = R.reshape(bshape + rfs + (K,))
    if loops.looped(eqn):  # a large contraction: loops over stack arrays, the same sums
        em.count(loops.extra_entries(eqn))
        size = lambda s: int(np.prod(s, dtype=int))
        flat = lambda x, free: x.reshape((size(bshape), size(free), K))
        return loops.dot(em, flat(L, lfs), flat(R, rfs), dtype).reshape(bshape + lfs + rfs)
    out = np.empty(bshape + lfs + rfs, object)
    for bi in np.ndindex(bshape):
        for i in np.ndindex(lfs):
            for j in np.ndindex(rfs):
                out[bi + i + j] = _sum_products(em, zip(L[bi + i], R[bi + j]), dtype)
    return out


def _reduce(op: str):
    def rule(em, eqn, args):
        (a,) = args
        axes = tuple(eqn.params["axes"])
        dtype = out_dtype(eqn)
        keep = [d for d in range(a.ndim) if d not in axes]
        moved = np.transpose(a, keep + list(axes))
        rest = moved.shape[: len(keep)]
        moved = moved.reshape(rest + (-1,))
        out = np.empty(rest, object)
        fake = type("E", (), {"params": {}})()
        for idx in np.ndindex(rest):
            acc = None
            for x in moved[idx]:
                if acc is None:
                    acc = x
                elif is_known(acc) and is_known(x):
                    acc = np.asarray(FOLD[op](np.asarray(acc, dtype), np.asarray(x, dtype))).astype(dtype)[()]
                else:
                    emit = emit_float if dtype.kind == "f" else emit_bool if dtype == np.bool_ else emit_int
                    acc = emit(em, op, dtype, [acc, x], fake)
            out[idx] = acc if acc is not None else _IDENTITY[op](dtype)
        return out

    return rule


_IDENTITY = {
    "add": lambda d: np.zeros((), d)[()],
    "mul": lambda d: np.ones((), d)[()],
    "max": lambda d: (
        np.array(-np.inf, d) if d.kind == "f" else np.array(np.iinfo(d).min, d) if d.kind in "iu" else np.array(False)
    )[()],
    "min": lambda d: (
        np.array(np.inf, d) if d.kind == "f" else np.array(np.iinfo(d).max, d) if d.kind in "iu" else np.array(True)
    )[()],
    "and": lambda d: np.array(True)[()],
    "or": lambda d: np.array(False)[()],
}


def _argminmax(greater: bool):
    def rule(em, eqn, args):
        (a,) = args
        (axis,) = eqn.params["axes"]
        src, idx_dtype = in_dtype(eqn), np.dtype(eqn.params["index_dtype"])
        moved = np.moveaxis(a, axis, -1)
        out = np.empty(moved.shape[:-1], object)
        b = em.b
        for idx in np.ndindex(out.shape):
            row = moved[idx]
            best, where = row[0], np.asarray(0, idx_dtype)[()]
            for k in range(1, len(row)):
                x = row[k]
                if src.kind == "f":
                    bv, xv = em.vec(best, src), em.vec(x, src)
                    better = b.fcmp_ordered(">" if greater else "<", xv, bv)
                    # NaN counts as the extreme (the first one wins), as in XLA's comparator
                    better = b.or_(better, b.and_(b.fcmp_unordered("uno", xv, xv), b.fcmp_ordered("ord", bv, bv)))
                elif src == np.bool_:
                    bv, xv = em.vec(best, src), em.vec(x, src)
                    better = b.and_(xv, b.not_(bv)) if greater else b.and_(bv, b.not_(xv))
                else:
                    cmp = b.icmp_signed if src.kind == "i" else b.icmp_unsigned
                    better = cmp(">" if greater else "<", em.vec(x, src), em.vec(best, src))
                best = em.select(better, x, best, src)
                where = em.select(better, np.asarray(k, idx_dtype)[()], where, idx_dtype)
            out[idx] = where
        return out

    return rule


def _cumulative(op: str):
    def rule(em, eqn, args):
        (a,) = args
        axis, reverse = eqn.params["axis"], eqn.params.get("reverse", False)
        dtype = out_dtype(eqn)
        moved = np.moveaxis(a, axis, -1)
        out = np.empty(moved.shape, object)
        emit = emit_float if dtype.kind == "f" else emit_int
        order = range(moved.shape[-1] - 1, -1, -1) if reverse else range(moved.shape[-1])
        for idx in np.ndindex(moved.shape[:-1]):
            acc = None
            for k in order:
                x = moved[idx + (k,)]
                acc = x if acc is None else emit(em, op, dtype, [acc, x], None)
                out[idx + (k,)] = acc
        return np.moveaxis(out, -1, axis)

    return rule


def _call_rule(*keys: str):
    def rule(em, eqn, args):
        closed = next(eqn.params[k] for k in keys if k in eqn.params)
        if hasattr(closed, "consts"):
            return eval_closed(em, closed, args)
        return eval_jaxpr(em, closed, [], args)

    return rule


def _custom_vjp(em, eqn, args):
    closed = eqn.params.get("call_jaxpr") or eqn.params["fun_jaxpr"]
    return eval_closed(em, closed, args)


RULES = {name: elementwise_rule for name in ELEMENTWISE}
RULES.update(
    select_n=select_n,
    convert_element_type=convert,
    clamp=clamp,
    broadcast_in_dim=_broadcast_in_dim,
    reshape=_reshape,
    squeeze=_squeeze,
    expand_dims=_expand_dims,
    transpose=_transpose,
    slice=_slice,
    concatenate=_concatenate,
    stack=_stack,
    unstack=_unstack,
    rev=_rev,
    split=_split,
    pad=_pad,
    iota=_iota,
    optimization_barrier=_identity,
    device_put=_identity,  # a placement, no value changes (the kernel runs on the host)
    reduce_precision=_identity,
    dot_general=_dot_general,
    reduce_sum=_reduce("add"),
    reduce_prod=_reduce("mul"),
    reduce_max=_reduce("max"),
    reduce_min=_reduce("min"),
    reduce_and=_reduce("and"),
    reduce_or=_reduce("or"),
    argmax=_argminmax(True),
    argmin=_argminmax(False),
    cumsum=_cumulative("add"),
    cumprod=_cumulative("mul"),
    cummax=_cumulative("max"),
    cummin=_cumulative("min"),
    debug_callback=_nothing,
    platform_index=_platform_index,
    pjit=_call_rule("jaxpr"),
    jit=_call_rule("jaxpr"),
    closed_call=_call_rule("call_jaxpr"),
    core_call=_call_rule("call_jaxpr"),
    custom_jvp_call=_call_rule("call_jaxpr"),
    custom_vmap_call=_call_rule("call", "call_jaxpr"),
    custom_vjp_call=_custom_vjp,
    checkpoint=_call_rule("jaxpr"),
    remat=_call_rule("jaxpr"),
)
RULES.update(reduce_sum=fused.reduce_rule(RULES["reduce_sum"], RULES), dot_general=fused.dot_rule(_dot_general, RULES))
_TAKES_LAZY = frozenset({"reduce_sum", "dot_general"})  # rules that loop over a `fused.Lazy` operand
