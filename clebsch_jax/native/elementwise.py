"""The translation's elementwise rules (`clebsch_jax.native.lower` walks the jaxpr and applies
them): each elementwise primitive emits one vector instruction per entry (`emit_float`,
`emit_int`, and the boolean ones), or folds known entries in NumPy for the exactly rounded
operations; and the selects, conversions and clamps, entry by entry."""

from __future__ import annotations

import math

import numpy as np
from llvmlite import ir

from .values import Emitter, Unsupported, is_known

__all__ = [
    "out_dtype",
    "in_dtype",
    "FOLD",
    "LIBM",
    "emit_float",
    "emit_int",
    "emit_bool",
    "product",
    "convert_array",
    "elementwise_rule",
    "ELEMENTWISE",
    "ALIASES",
    "select_n",
    "convert",
    "clamp",
]


def out_dtype(eqn, i: int = 0):
    return np.dtype(eqn.outvars[i].aval.dtype)


def in_dtype(eqn, i: int = 0):
    return np.dtype(eqn.invars[i].aval.dtype)


# ---------------------------------------------------------------------------------------------
# Elementwise primitives: a fold in NumPy (exactly rounded operations only) and an emitter.


def _trunc_div(a, b):
    q = np.abs(a) // np.abs(b)
    return np.where((a < 0) != (b < 0), -q, q)


def _trunc_rem(a, b):
    return a - _trunc_div(a, b) * b


FOLD = {
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


FOLD.update(div=_fold_div, rem=_fold_rem)

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
LIBM = frozenset(_LIBM)
"""The primitives emitted as calls of libm, lane by lane (LLVM keeps such a call whose value is
unused: it may set `errno`)."""


def emit_float(em: Emitter, name: str, dtype, xs, eqn):
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
        if sign_clear(v[0]) and sign_clear(v[1]):
            return _max_sign_clear(em, v[0], v[1], dtype)
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


_SIGN_CLEAR_DEPTH = 4
"""How many selects deep `sign_clear` looks through."""


def sign_clear(v, depth: int = _SIGN_CLEAR_DEPTH) -> bool:
    """Whether every lane of the float vector `v` has its sign bit clear, as the translation
    can tell from how `v` was made: a constant of such lanes, an `llvm.fabs`, a maximum of such
    values (`_max_sign_clear`), or a select between such values. (+0, a positive number, +inf or
    a NaN whose sign bit is clear: NaNs made by the hardware, e.g. from ∞ − ∞, have it set.)"""
    if isinstance(v, ir.Constant):
        lanes = v.constant if isinstance(v.constant, list) else [v]
        return all(isinstance(c.constant, float) and math.copysign(1.0, c.constant) > 0 for c in lanes)
    if getattr(v, "sign_clear", False):
        return True
    if isinstance(v, ir.CallInstr):
        return getattr(v.callee, "name", "").startswith("llvm.fabs.")
    if isinstance(v, ir.SelectInstr) and depth > 0:
        return sign_clear(v.operands[1], depth - 1) and sign_clear(v.operands[2], depth - 1)
    return False


def _max_sign_clear(em: Emitter, a, b, dtype):
    """`llvm.maximum(a, b)` of two vectors whose lanes have the sign bit clear (`sign_clear`):
    the larger bit pattern as a signed integer, which is the larger number, or the NaN where
    either is one (a NaN's pattern, sign bit clear, is above +inf's). One integer maximum where
    the floating-point one expands to a NaN test, a blend and the ordering of signed zeros."""
    bld = em.b
    it = ir.VectorType(ir.IntType(8 * np.dtype(dtype).itemsize), em.W)
    x, y = bld.bitcast(a, it), bld.bitcast(b, it)
    out = bld.bitcast(bld.select(bld.icmp_signed(">", x, y), x, y), a.type)
    out.sign_clear = True
    return out


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


def emit_int(em: Emitter, name: str, dtype, xs, eqn):
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


def emit_bool(em: Emitter, name: str, dtype, xs, eqn):
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


def product(em: Emitter, a, c, dtype):
    """a·c of two entries, folded when both are known, and not multiplied where one is a known
    1 (exact): a term of a contraction."""
    if is_known(a) and is_known(c):
        return (np.asarray(a, dtype) * np.asarray(c, dtype))[()]
    if is_known(a) and float(a) == 1.0:
        return c
    if is_known(c) and float(c) == 1.0:
        return a
    return (emit_float if np.dtype(dtype).kind == "f" else emit_int)(em, "mul", dtype, [a, c], None)


def elementwise_rule(em: Emitter, eqn, args):
    name = ALIASES.get(eqn.primitive.name, eqn.primitive.name)
    dtype = in_dtype(eqn)
    result_dtype = out_dtype(eqn)
    shape = eqn.outvars[0].aval.shape
    # broadcast only where needed (`np.broadcast_to` costs more than the rest of a scalar's rule)
    args = [a if isinstance(a, np.ndarray) and a.shape == shape else np.broadcast_to(a, shape) for a in args]
    if name == "pow" and np.dtype(eqn.invars[1].aval.dtype) != dtype:
        # an integer exponent: XLA converts it to the base's type and takes the power (JAX's pow lowering)
        args[1] = convert_array(em, args[1], eqn.invars[1].aval.dtype, dtype)
    out = np.empty(shape, object)
    fold = FOLD.get(name)
    emit = emit_float if dtype.kind == "f" else emit_bool if dtype == np.bool_ else emit_int
    for idx in np.ndindex(shape):
        xs = [a[idx] for a in args]
        if fold is not None and all(is_known(x) for x in xs):
            with np.errstate(all="ignore"):
                out[idx] = np.asarray(fold(*[np.asarray(x, dtype) for x in xs])).astype(result_dtype)[()]
        else:
            out[idx] = emit(em, name, dtype, xs, eqn)
    return out


ALIASES = {"add_any": "add"}

ELEMENTWISE = """add add_any sub mul div rem neg max min abs sqrt rsqrt floor ceil round square sign is_finite eq ne
lt le
gt ge integer_pow exp log sin cos tan tanh atan asin acos sinh cosh asinh acosh atanh expm1 log1p cbrt erf erfc exp2
atan2 pow logistic and or xor not shift_left shift_right_arithmetic shift_right_logical copy copy_p
stop_gradient""".split()


# ---------------------------------------------------------------------------------------------
# Selects, conversions, clamps.


def select_n(em: Emitter, eqn, args):
    which, *cases = args
    dtype = out_dtype(eqn)
    shape = eqn.outvars[0].aval.shape
    which = np.broadcast_to(which, shape)
    cases = [np.broadcast_to(c, shape) for c in cases]
    out = np.empty(shape, object)
    pred_bool = in_dtype(eqn) == np.bool_
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
            r = em.select(em.b.icmp_signed("==", w, em.const(k, in_dtype(eqn))), cases[k][idx], r, dtype)
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


def convert_array(em: Emitter, a, src, dst):
    out = np.empty(a.shape, object)
    for idx in np.ndindex(a.shape):
        out[idx] = _convert_entry(em, a[idx], src, dst)
    return out


def convert(em: Emitter, eqn, args):
    return convert_array(em, args[0], in_dtype(eqn), out_dtype(eqn))


def clamp(em: Emitter, eqn, args):
    lo, x, hi = args
    dtype = out_dtype(eqn)
    shape = eqn.outvars[0].aval.shape
    lo, x, hi = (np.broadcast_to(a, shape) for a in (lo, x, hi))
    emit = emit_float if dtype.kind == "f" else emit_int
    out = np.empty(shape, object)
    for idx in np.ndindex(shape):
        if all(is_known(a[idx]) for a in (lo, x, hi)):
            out[idx] = np.minimum(np.maximum(np.asarray(x[idx], dtype), lo[idx]), hi[idx])[()]
        else:
            out[idx] = emit(em, "min", dtype, [emit(em, "max", dtype, [x[idx], lo[idx]], eqn), hi[idx]], eqn)
    return out
