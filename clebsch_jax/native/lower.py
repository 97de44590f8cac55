"""The translation of a jaxpr of one member into LLVM IR, entry by entry (`values`).

`eval_jaxpr(em, jaxpr, consts, args)` walks the equations and applies each primitive's rule
to the entries of its operands: elementwise primitives emit one vector instruction per entry
(or fold known entries in NumPy, for the exactly rounded ones); structural primitives
re-index the entry arrays; contractions and reductions are unrolled in index order. Loops and
branches are in `clebsch_jax.native.control`. A primitive without a rule raises `Unsupported`
with its name.
"""

from __future__ import annotations

import numpy as np
from jax.extend import core as jcore

from .values import Emitter, Unsupported, is_known, known_array

__all__ = ["eval_jaxpr", "RULES"]


def eval_jaxpr(em: Emitter, jaxpr, consts, args) -> list:
    """The outputs (entry arrays) of `jaxpr` (an open jaxpr) on entry arrays `consts`, `args`."""
    env: dict = {}

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
        em.count(sum(int(np.prod(v.aval.shape, dtype=int)) for v in eqn.outvars if hasattr(v.aval, "shape")))
        outs = rule(em, eqn, [read(v) for v in eqn.invars])
        if not eqn.primitive.multiple_results:
            outs = [outs]
        for v, x in zip(eqn.outvars, outs):
            if not isinstance(v, jcore.DropVar):
                env[v] = x
    return [read(v) for v in jaxpr.outvars]


def eval_closed(em: Emitter, closed, args) -> list:
    """`eval_jaxpr` of a closed jaxpr (its constants become known entries, or arrays of them)."""
    return eval_jaxpr(em, closed.jaxpr, [known_array(np.asarray(c)) for c in closed.consts], args)


def _out_dtype(eqn, i: int = 0):
    return np.dtype(eqn.outvars[i].aval.dtype)


def _in_dtype(eqn, i: int = 0):
    return np.dtype(eqn.invars[i].aval.dtype)


# ---------------------------------------------------------------------------------------------
# Elementwise primitives: a fold in NumPy (exactly rounded operations only) and an emitter.


def _trunc_div(a, b):
    q = np.abs(a) // np.abs(b)
    return np.where((a < 0) != (b < 0), -q, q)


def _trunc_rem(a, b):
    return a - _trunc_div(a, b) * b


_FOLD = {
    "add": np.add,
    "sub": np.subtract,
    "mul": np.multiply,
    "neg": np.negative,
    "max": np.maximum,
    "min": np.minimum,
    "abs": np.abs,
    "sqrt": np.sqrt,
    "eq": np.equal,
    "ne": np.not_equal,
    "lt": np.less,
    "le": np.less_equal,
    "gt": np.greater,
    "ge": np.greater_equal,
    "and": np.bitwise_and,
    "or": np.bitwise_or,
    "xor": np.bitwise_xor,
    "not": lambda a: ~a if a.dtype != np.bool_ else np.logical_not(a),
    "floor": np.floor,
    "ceil": np.ceil,
    "is_finite": np.isfinite,
    "sign": np.sign,
    "square": np.square,
    "copy": lambda a: a,
    "copy_p": lambda a: a,
    "stop_gradient": lambda a: a,
}


def _fold_div(a, b):
    return _trunc_div(a, b) if a.dtype.kind in "iu" else np.divide(a, b)


def _fold_rem(a, b):
    return _trunc_rem(a, b) if a.dtype.kind in "iu" else np.fmod(a, b)


_FOLD.update(div=_fold_div, rem=_fold_rem)

_FCMP = {"eq": "==", "ne": "!=", "lt": "<", "le": "<=", "gt": ">", "ge": ">="}
_LIBM = {
    "exp": "exp",
    "log": "log",
    "sin": "sin",
    "cos": "cos",
    "tan": "tan",
    "tanh": "tanh",
    "atan": "atan",
    "asin": "asin",
    "acos": "acos",
    "sinh": "sinh",
    "cosh": "cosh",
    "asinh": "asinh",
    "acosh": "acosh",
    "atanh": "atanh",
    "expm1": "expm1",
    "log1p": "log1p",
    "cbrt": "cbrt",
    "erf": "erf",
    "erfc": "erfc",
    "exp2": "exp2",
    "atan2": "atan2",
    "pow": "pow",
}


def _emit_float(em: Emitter, name: str, dtype, xs, eqn):
    b = em.b
    v = [em.vec(x, dtype) for x in xs]
    if name == "add":
        return b.fadd(*v)
    if name == "sub":
        return b.fsub(*v)
    if name == "mul":
        return b.fmul(*v)
    if name == "div":
        return b.fdiv(*v)
    if name == "rem":
        return b.frem(*v)
    if name == "neg":
        return b.fneg(v[0])
    if name == "max":
        return em.call_intrinsic("llvm.maximum", dtype, *v)
    if name == "min":
        return em.call_intrinsic("llvm.minimum", dtype, *v)
    if name == "abs":
        return em.call_intrinsic("llvm.fabs", dtype, v[0])
    if name == "sqrt":
        return em.call_intrinsic("llvm.sqrt", dtype, v[0])
    if name == "rsqrt":
        return b.fdiv(em.const(1.0, dtype), em.call_intrinsic("llvm.sqrt", dtype, v[0]))
    if name in ("floor", "ceil"):
        return em.call_intrinsic(f"llvm.{name}", dtype, v[0])
    if name == "round":
        method = int(eqn.params.get("rounding_method", 0))
        return em.call_intrinsic("llvm.roundeven" if method == 1 else "llvm.round", dtype, v[0])
    if name == "square":
        return b.fmul(v[0], v[0])
    if name == "sign":
        zero, one = em.const(0.0, dtype), em.const(1.0, dtype)
        pos = b.select(b.fcmp_ordered(">", v[0], zero), one, zero)
        neg = b.select(b.fcmp_ordered("<", v[0], zero), em.const(-1.0, dtype), pos)
        return b.select(b.fcmp_ordered("==", v[0], zero), v[0], neg)  # ±0 and NaN as they are
    if name == "is_finite":
        return b.fcmp_ordered("!=", em.call_intrinsic("llvm.fabs", dtype, v[0]), em.const(np.inf, dtype))
    if name in _FCMP:
        return (b.fcmp_unordered if name == "ne" else b.fcmp_ordered)(_FCMP[name], *v)
    if name == "integer_pow":
        return _integer_pow(em, v[0], int(eqn.params["y"]), dtype)
    if name in _LIBM:
        return em.libm(_LIBM[name], dtype, *v)
    if name == "logistic":
        one = em.const(1.0, dtype)
        return b.fdiv(one, b.fadd(one, em.libm("exp", dtype, b.fneg(v[0]))))
    if name in ("copy", "copy_p", "stop_gradient", "reduce_precision"):
        return v[0]
    raise Unsupported(f"primitive {name!r} on {dtype}")


def _integer_pow(em: Emitter, x, y: int, dtype):
    """x**y by repeated squaring (XLA's expansion of integer_pow)."""
    b = em.b
    if y == 0:
        return em.const(1, dtype)
    n, acc, base = abs(y), None, x
    while n:
        if n & 1:
            acc = base if acc is None else (b.fmul(acc, base) if np.dtype(dtype).kind == "f" else b.mul(acc, base))
        n >>= 1
        if n:
            base = b.fmul(base, base) if np.dtype(dtype).kind == "f" else b.mul(base, base)
    return b.fdiv(em.const(1.0, dtype), acc) if y < 0 else acc


def _emit_int(em: Emitter, name: str, dtype, xs, eqn):
    b = em.b
    signed = np.dtype(dtype).kind == "i"
    v = [em.vec(x, dtype) for x in xs]
    if name == "add":
        return b.add(*v)
    if name == "sub":
        return b.sub(*v)
    if name == "mul":
        return b.mul(*v)
    if name == "div":
        return b.sdiv(*v) if signed else b.udiv(*v)
    if name == "rem":
        return b.srem(*v) if signed else b.urem(*v)
    if name == "neg":
        return b.neg(v[0])
    if name in ("max", "min"):
        cmp = b.icmp_signed if signed else b.icmp_unsigned
        return b.select(cmp(">" if name == "max" else "<", v[0], v[1]), v[0], v[1])
    if name == "abs":
        return b.select(b.icmp_signed("<", v[0], em.const(0, dtype)), b.neg(v[0]), v[0])
    if name in _FCMP:
        return (b.icmp_signed if signed else b.icmp_unsigned)(_FCMP[name], *v)
    if name == "and":
        return b.and_(*v)
    if name == "or":
        return b.or_(*v)
    if name == "xor":
        return b.xor(*v)
    if name == "not":
        return b.not_(v[0])
    if name == "shift_left":
        return b.shl(*v)
    if name == "shift_right_arithmetic":
        return b.ashr(*v)
    if name == "shift_right_logical":
        return b.lshr(*v)
    if name == "sign":
        zero = em.const(0, dtype)
        pos = b.zext(b.icmp_signed(">", v[0], zero), em.vtype(dtype))
        return b.select(b.icmp_signed("<", v[0], zero), em.const(-1, dtype), pos)
    if name == "integer_pow":
        return _integer_pow(em, v[0], int(eqn.params["y"]), dtype)
    if name in ("copy", "copy_p", "stop_gradient"):
        return v[0]
    raise Unsupported(f"primitive {name!r} on {dtype}")


def _emit_bool(em: Emitter, name: str, dtype, xs, eqn):
    b = em.b
    v = [em.vec(x, np.bool_) for x in xs]
    ops = {"and": b.and_, "or": b.or_, "xor": b.xor}
    if name in ops:
        return ops[name](*v)
    if name == "not":
        return b.not_(v[0])
    if name in ("eq", "ne"):
        return b.icmp_unsigned(_FCMP[name], *v)
    if name in ("copy", "copy_p", "stop_gradient"):
        return v[0]
    if name in ("max", "min"):
        return (b.or_ if name == "max" else b.and_)(*v)
    raise Unsupported(f"primitive {name!r} on bool")


def _elementwise(em: Emitter, eqn, args):
    name = _ALIASES.get(eqn.primitive.name, eqn.primitive.name)
    dtype = _in_dtype(eqn)
    out_dtype = _out_dtype(eqn)
    shape = eqn.outvars[0].aval.shape
    args = [np.broadcast_to(a, shape) for a in args]
    out = np.empty(shape, object)
    fold = _FOLD.get(name)
    emit = _emit_float if dtype.kind == "f" else _emit_bool if dtype == np.bool_ else _emit_int
    for idx in np.ndindex(shape):
        xs = [a[idx] for a in args]
        if fold is not None and all(is_known(x) for x in xs):
            with np.errstate(all="ignore"):
                out[idx] = np.asarray(fold(*[np.asarray(x, dtype) for x in xs])).astype(out_dtype)[()]
        else:
            out[idx] = emit(em, name, dtype, xs, eqn)
    return out


_ALIASES = {"add_any": "add"}

_ELEMENTWISE = """add add_any sub mul div rem neg max min abs sqrt rsqrt floor ceil round square sign is_finite eq ne
lt le
gt ge integer_pow exp log sin cos tan tanh atan asin acos sinh cosh asinh acosh atanh expm1 log1p cbrt erf erfc exp2
atan2 pow logistic and or xor not shift_left shift_right_arithmetic shift_right_logical copy copy_p
stop_gradient""".split()


# ---------------------------------------------------------------------------------------------
# Selects, conversions, clamps.


def _select_n(em: Emitter, eqn, args):
    which, *cases = args
    dtype = _out_dtype(eqn)
    shape = eqn.outvars[0].aval.shape
    which = np.broadcast_to(which, shape)
    cases = [np.broadcast_to(c, shape) for c in cases]
    out = np.empty(shape, object)
    pred_bool = _in_dtype(eqn) == np.bool_
    for idx in np.ndindex(shape):
        w = which[idx]
        if is_known(w):
            out[idx] = cases[int(w)][idx]
            continue
        if pred_bool:
            out[idx] = em.select(w, cases[1][idx], cases[0][idx], dtype)
            continue
        r = cases[-1][idx]
        for k in range(len(cases) - 2, -1, -1):
            r = em.select(em.b.icmp_signed("==", w, em.const(k, _in_dtype(eqn))), cases[k][idx], r, dtype)
        out[idx] = r
    return out


def _convert_entry(em: Emitter, x, src, dst):
    src, dst = np.dtype(src), np.dtype(dst)
    if is_known(x):
        with np.errstate(all="ignore"):
            return np.asarray(x, src).astype(dst)[()]
    b, t = em.b, em.vtype(dst)
    if src == dst:
        return x
    if dst == np.bool_:
        return (
            b.fcmp_unordered("!=", x, em.const(0.0, src))
            if src.kind == "f"
            else b.icmp_unsigned("!=", x, em.const(0, src))
        )
    if src == np.bool_:
        return b.uitofp(x, t) if dst.kind == "f" else b.zext(x, t)
    if src.kind == "f" and dst.kind == "f":
        return b.fpext(x, t) if dst.itemsize > src.itemsize else b.fptrunc(x, t)
    if src.kind == "f":
        return b.fptosi(x, t) if dst.kind == "i" else b.fptoui(x, t)
    if dst.kind == "f":
        return b.sitofp(x, t) if src.kind == "i" else b.uitofp(x, t)
    if dst.itemsize > src.itemsize:
        return b.sext(x, t) if src.kind == "i" else b.zext(x, t)
    if dst.itemsize < src.itemsize:
        return b.trunc(x, t)
    return x


def _convert_array(em: Emitter, a, src, dst):
    out = np.empty(a.shape, object)
    for idx in np.ndindex(a.shape):
        out[idx] = _convert_entry(em, a[idx], src, dst)
    return out


def _convert(em: Emitter, eqn, args):
    return _convert_array(em, args[0], _in_dtype(eqn), _out_dtype(eqn))


def _clamp(em: Emitter, eqn, args):
    lo, x, hi = args
    dtype = _out_dtype(eqn)
    shape = eqn.outvars[0].aval.shape
    lo, x, hi = (np.broadcast_to(a, shape) for a in (lo, x, hi))
    emit = _emit_float if dtype.kind == "f" else _emit_int
    out = np.empty(shape, object)
    for idx in np.ndindex(shape):
        if all(is_known(a[idx]) for a in (lo, x, hi)):
            out[idx] = np.minimum(np.maximum(np.asarray(x[idx], dtype), lo[idx]), hi[idx])[()]
        else:
            out[idx] = emit(em, "min", dtype, [emit(em, "max", dtype, [x[idx], lo[idx]], eqn), hi[idx]], eqn)
    return out


# ---------------------------------------------------------------------------------------------
# Re-indexing primitives (no code).


def _copy(a):
    out = np.empty(a.shape, object)
    out[...] = a
    return out


def _broadcast_in_dim(em, eqn, args):
    a, shape, dims = args[0], eqn.params["shape"], eqn.params["broadcast_dimensions"]
    tmp = [1] * len(shape)
    for i, d in enumerate(dims):
        tmp[d] = a.shape[i]
    return _copy(np.broadcast_to(a.reshape(tmp), shape))


def _reshape(em, eqn, args):
    return _copy(args[0].reshape(eqn.params["new_sizes"]))


def _squeeze(em, eqn, args):
    return _copy(np.squeeze(args[0], axis=tuple(eqn.params["dimensions"])))


def _expand_dims(em, eqn, args):
    return _copy(np.expand_dims(args[0], tuple(eqn.params["dimensions"])))


def _transpose(em, eqn, args):
    return _copy(np.transpose(args[0], eqn.params["permutation"]))


def _slice(em, eqn, args):
    p = eqn.params
    strides = p["strides"] or (1,) * len(p["start_indices"])
    idx = tuple(slice(s, e, st) for s, e, st in zip(p["start_indices"], p["limit_indices"], strides))
    return _copy(args[0][idx])


def _concatenate(em, eqn, args):
    return np.concatenate(args, axis=eqn.params["dimension"])


def _stack(em, eqn, args):
    return np.stack(args, axis=eqn.params["axis"])


def _unstack(em, eqn, args):
    moved = np.moveaxis(args[0], eqn.params["axis"], 0)
    return [_copy(moved[i, ...]) for i in range(moved.shape[0])]


def _rev(em, eqn, args):
    return _copy(np.flip(args[0], axis=tuple(eqn.params["dimensions"])))


def _split(em, eqn, args):
    cuts = np.cumsum(eqn.params["sizes"])[:-1]
    return [_copy(x) for x in np.split(args[0], cuts, axis=eqn.params["axis"])]


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
    return [_copy(a) for a in args] if eqn.primitive.multiple_results else _copy(args[0])


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
        if is_known(a) and is_known(c):
            p = (np.asarray(a, dtype) * np.asarray(c, dtype))[()]
        elif is_known(a) and float(a) == 1.0:
            p = c
        elif is_known(c) and float(c) == 1.0:
            p = a
        else:
            p = (
                _emit_float(em, "mul", dtype, [a, c], None)
                if dtype.kind == "f"
                else _emit_int(em, "mul", dtype, [a, c], None)
            )
        if acc is None:
            acc = p
        elif is_known(acc) and is_known(p):
            acc = (np.asarray(acc, dtype) + np.asarray(p, dtype))[()]
        else:
            acc = (_emit_float if dtype.kind == "f" else _emit_int)(em, "add", dtype, [acc, p], None)
    return np.zeros((), dtype)[()] if acc is None else acc


def _dot_general(em, eqn, args):
    lhs, rhs = args
    (lc, rc), (lb, rb) = eqn.params["dimension_numbers"]
    dtype = _out_dtype(eqn)
    lhs = _convert_array(em, lhs, _in_dtype(eqn), dtype) if _in_dtype(eqn) != dtype else lhs
    rhs = _convert_array(em, rhs, _in_dtype(eqn, 1), dtype) if _in_dtype(eqn, 1) != dtype else rhs
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
        dtype = _out_dtype(eqn)
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
                    acc = np.asarray(_FOLD[op](np.asarray(acc, dtype), np.asarray(x, dtype))).astype(dtype)[()]
                else:
                    emit = _emit_float if dtype.kind == "f" else _emit_bool if dtype == np.bool_ else _emit_int
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
        src, idx_dtype = _in_dtype(eqn), np.dtype(eqn.params["index_dtype"])
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
        dtype = _out_dtype(eqn)
        moved = np.moveaxis(a, axis, -1)
        out = np.empty(moved.shape, object)
        emit = _emit_float if dtype.kind == "f" else _emit_int
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


RULES = {name: _elementwise for name in _ELEMENTWISE}
RULES.update(
    select_n=_select_n,
    convert_element_type=_convert,
    clamp=_clamp,
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
