r"""The scalarising evaluator's values and the rules of its primitives on rows.

A value is (kind, x): `U` unbatched (an array of the member's shape), `S` stacked batch-last
(member shape + (B,)), `R` rows (a NumPy object array of the member's shape whose entries are
(B,) JAX arrays, one per component, or NumPy scalars for components known when the program is
traced). The conversions between kinds, the folding of known values in NumPy
(`numpy_fold`), and one rule per primitive on rows (`ROW_RULES`: elementwise operations map
over the entries, re-indexing moves entries, reductions and small `dot_general`s are sums of
products of rows). The walk over a jaxpr and its control flow: `clebsch_jax.batching.walk`, with
the layout of rows of `clebsch_jax.batching.scalarise`.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .rules import ELEMENTWISE
from .walk import S, U

MAX_ROWS = 32
"""Batched values with at most this many components per member are held as rows."""

MAX_PRODUCTS = 512
"""A `dot_general` (or reduction) of rows with more products than this is stacked instead."""


R = "r"
"""The kind of rows (a NumPy object array of the member's shape with (B,) entries), besides the
walk's U (unbatched) and S (stacked batch-last): `clebsch_jax.batching.walk`."""


# --------------------------------------------------------------------------------------------
# Values and their conversions.


def small(shape) -> bool:
    return math.prod(shape) <= MAX_ROWS


def _obj(shape, entries) -> np.ndarray:
    out = np.empty(len(entries), dtype=object)
    for i, e in enumerate(entries):
        out[i] = e
    return out.reshape(shape)


def to_batch_first(val, shape, B):
    kind, x = val
    if kind == U:
        x = jnp.asarray(x)
        return jnp.broadcast_to(x, (B,) + x.shape)
    return jnp.moveaxis(stacked(val, shape, B), -1, 0)


def _row_of_const(c, B, dtype=None):
    c = jnp.asarray(c, dtype)
    return lax.broadcast_in_dim(c, (B,), ())


def _is_const(e) -> bool:
    """A component known at trace time (a NumPy scalar), not a (B,) row."""
    return isinstance(e, (np.ndarray, np.generic))


def concrete(x):
    """x as a NumPy array if its value is known at trace time, else None."""
    if isinstance(x, jax.core.Tracer):
        return None
    try:
        return np.asarray(x)
    except Exception:  # an abstract value
        return None


def lift(e, B, dtype=None):
    """A component as a (B,) row."""
    return _row_of_const(e, B, dtype if dtype is not None else e.dtype) if _is_const(e) else e


def _add(a, b):
    if _is_const(a) and _is_const(b):
        return np.asarray(a + b)
    if _is_const(a) and not a.any():
        return b
    if _is_const(b) and not b.any():
        return a
    return lax.add(*_lift_pair(a, b))


def _mul(a, b, dtype):
    if _is_const(a) and _is_const(b):
        return np.asarray(a * b, dtype)
    for c, other in ((a, b), (b, a)):
        if _is_const(c):
            if not c.any():
                return np.zeros((), dtype)
            if c == 1:
                return other
    return lax.mul(*_lift_pair(a, b))


def _lift_pair(a, b):
    if _is_const(a):
        return _row_of_const(a, b.shape[0], b.dtype), b
    if _is_const(b):
        return a, _row_of_const(b, a.shape[0], a.dtype)
    return a, b


def stacked(val, shape, B):
    """Any value as a stacked batch-last array."""
    kind, x = val
    if kind == S:
        return x
    if kind == U:
        x = jnp.asarray(x)
        return lax.broadcast_in_dim(x, x.shape + (B,), tuple(range(x.ndim)))
    entries = [lift(e, B) for e in x.ravel()]
    return jnp.stack(entries, axis=0).reshape(tuple(shape) + (B,)) if entries else jnp.zeros(tuple(shape) + (B,))


def _rows(val, shape, B, dtype=None):
    """A batched or unbatched value as rows."""
    kind, x = val
    if kind == R:
        return x
    if kind == S:
        return _obj(shape, [x[idx] for idx in np.ndindex(*shape)])
    c = concrete(x)
    if c is not None:
        c = c.astype(dtype) if dtype is not None else c
        return _obj(shape, [np.asarray(c[idx]) for idx in np.ndindex(*shape)])
    x = jnp.asarray(x, dtype)
    return _obj(shape, [_row_of_const(x[idx], B) for idx in np.ndindex(*shape)])


def canonical_kind(shape, batched) -> str:
    if not batched:
        return U
    return R if small(shape) else S


def as_kind(val, kind, shape, B, dtype=None):
    if kind == U:
        if val[0] != U:
            raise AssertionError("a batched value cannot become unbatched")
        return val
    return (R, _rows(val, shape, B, dtype)) if kind == R else (S, stacked(val, shape, B))


def flatten(val, B):
    """A value as a list of arrays for a loop's carry."""
    kind, x = val
    return [lift(e, B) for e in x.ravel()] if kind == R else [x]


def unflatten(kind, shape, arrays):
    if kind == R:
        return R, _obj(shape, arrays)
    return kind, arrays[0]


# --------------------------------------------------------------------------------------------
# Known values folded in NumPy.


def _slice_np(x, p):
    return x[
        tuple(
            slice(a, b, None if p["strides"] is None else p["strides"][i])
            for i, (a, b) in enumerate(zip(p["start_indices"], p["limit_indices"]))
        )
    ]


def _broadcast_np(x, p):
    shape, dims = tuple(p["shape"]), tuple(p["broadcast_dimensions"])
    expanded = np.reshape(x, [x.shape[dims.index(d)] if d in dims else 1 for d in range(len(shape))])
    return np.broadcast_to(expanded, shape)


def _iota_np(p):
    shape, d = tuple(p["shape"]), p["dimension"]
    return np.broadcast_to(np.arange(shape[d]).reshape([-1 if i == d else 1 for i in range(len(shape))]), shape)


def _split_np(x, p):
    edges = np.cumsum(p["sizes"])[:-1]
    return np.split(x, edges, axis=p["axis"])


_NUMPY_FOLD = {  # exactly rounded IEEE operations (and pure re-indexing), which NumPy and XLA agree on
    "add": lambda p, a, b: [a + b],
    "add_any": lambda p, a, b: [a + b],
    "sub": lambda p, a, b: [a - b],
    "mul": lambda p, a, b: [a * b],
    "neg": lambda p, a: [-a],
    "max": lambda p, a, b: [np.maximum(a, b)],
    "min": lambda p, a, b: [np.minimum(a, b)],
    "eq": lambda p, a, b: [a == b],
    "ne": lambda p, a, b: [a != b],
    "lt": lambda p, a, b: [a < b],
    "le": lambda p, a, b: [a <= b],
    "gt": lambda p, a, b: [a > b],
    "ge": lambda p, a, b: [a >= b],
    "and": lambda p, a, b: [a & b],
    "or": lambda p, a, b: [a | b],
    "not": lambda p, a: [~a],
    "abs": lambda p, a: [np.abs(a)],
    "select_n": lambda p, c, *xs: [np.choose(np.asarray(c, np.int64), np.broadcast_arrays(*xs))],
    "convert_element_type": lambda p, a: [a.astype(p["new_dtype"])],
    "broadcast_in_dim": lambda p, a: [_broadcast_np(a, p)],
    "reshape": lambda p, a: [np.reshape(a, p["new_sizes"])],
    "squeeze": lambda p, a: [np.squeeze(a, tuple(p["dimensions"]))],
    "slice": lambda p, a: [_slice_np(a, p)],
    "transpose": lambda p, a: [np.transpose(a, p["permutation"])],
    "rev": lambda p, a: [np.flip(a, tuple(p["dimensions"]))],
    "concatenate": lambda p, *xs: [np.concatenate(xs, axis=p["dimension"])],
    "stack": lambda p, *xs: [np.stack(xs, axis=p["axis"])],
    "split": lambda p, a: _split_np(a, p),
    "iota": lambda p: [_iota_np(p)],
}


def numpy_fold(eqn, known):
    """An unbatched operation on known operands evaluated in NumPy (None where it has no rule
    here): JAX would run it eagerly, a dispatch and, for each new shape, a compile of its own.
    Floating-point division is folded too (exactly rounded); integer division is not (C
    semantics, which NumPy's differs from)."""
    name = eqn.primitive.name
    if name == "div" and all(np.issubdtype(k.dtype, np.floating) for k in known):
        with np.errstate(all="ignore"):
            return [known[0] / known[1]]
    rule = _NUMPY_FOLD.get(name)
    if rule is None:
        return None
    if name in ("and", "or", "not") and not all(k.dtype == bool or np.issubdtype(k.dtype, np.integer) for k in known):
        return None
    try:
        with np.errstate(all="ignore"):  # IEEE results (inf·0 = NaN, x/0 = inf), silently, as JAX
            return rule(eqn.params, *known)
    except (KeyError, TypeError, ValueError):  # parameters this rule does not know: JAX evaluates it
        return None


# --------------------------------------------------------------------------------------------
# Rules of the primitives on rows.


def entry(val, idx, aval_shape, B, dtype):
    """Component idx of an operand (scalars and size-1 axes broadcast): a (B,) row, or a NumPy
    scalar when it is known at trace time."""
    kind, x = val
    src = tuple(i if n != 1 else 0 for i, n in zip(idx[len(idx) - len(aval_shape) :], aval_shape))
    if kind == R:
        return x[src]
    if kind == S:
        return x[src]
    c = concrete(x)
    if c is not None:
        return np.asarray(c.astype(dtype)[src])
    return _row_of_const(jnp.asarray(x, dtype)[src] if aval_shape else x, B, dtype)


def _elementwise(eqn, vals, B):
    shape = tuple(eqn.outvars[0].aval.shape)
    params = eqn.params
    out = [np.empty(shape, dtype=object) for _ in eqn.outvars]
    for idx in np.ndindex(*shape):
        args = [entry(val, idx, tuple(v.aval.shape), B, v.aval.dtype) for val, v in zip(vals, eqn.invars)]
        res = _fold(eqn, args)
        if res is None:
            if all(_is_const(a) for a in args):
                res = numpy_fold(eqn, [np.asarray(a) for a in args])
                if res is None:
                    with eqn.ctx.manager, jax.ensure_compile_time_eval():
                        res = eqn.primitive.bind(*[jnp.asarray(a) for a in args], **params)
                    res = res if eqn.primitive.multiple_results else [res]
                res = [np.asarray(r, dtype=v.aval.dtype) for r, v in zip(res, eqn.outvars)]
            else:
                args = [lift(a, B, v.aval.dtype) for a, v in zip(args, eqn.invars)]
                with eqn.ctx.manager:
                    res = eqn.primitive.bind(*args, **params)
                res = list(res) if eqn.primitive.multiple_results else [res]
        for o, r in zip(out, res):
            o[idx] = r
    return [(R, o) for o in out]


def _fold(eqn, args):
    """The result of an elementwise operation with an operand known at trace time that makes it
    trivial (x·0, x·1, x + 0, x - 0, a select with a known choice), or None."""
    name, dtype = eqn.primitive.name, eqn.outvars[0].aval.dtype
    if any(_is_const(a) for a in args) and not all(_is_const(a) for a in args):
        if name == "mul" and jnp.issubdtype(dtype, jnp.inexact):
            return [_mul(args[0], args[1], dtype)]
        if name in ("add", "add_any") and jnp.issubdtype(dtype, jnp.inexact):
            return [_add(args[0], args[1])]
        if name == "sub" and _is_const(args[1]) and not args[1].any():
            return [args[0]]
        if name == "select_n" and _is_const(args[0]):
            return [args[1 + int(args[0])]]
    return None


def _one_rows(eqn, vals, B):
    v = eqn.invars[0]
    return _rows(vals[0], tuple(v.aval.shape), B, v.aval.dtype)


def _broadcast_in_dim(eqn, vals, B):
    if len(vals) != 1:
        return None
    x = _one_rows(eqn, vals, B)
    shape, dims = tuple(eqn.params["shape"]), tuple(eqn.params["broadcast_dimensions"])
    out = np.empty(shape, dtype=object)
    for idx in np.ndindex(*shape):
        out[idx] = x[tuple(idx[d] if x.shape[i] != 1 else 0 for i, d in enumerate(dims))]
    return [(R, out)]


def _reshape(eqn, vals, B):
    if len(vals) != 1 or eqn.params.get("dimensions") is not None:
        return None
    return [(R, _one_rows(eqn, vals, B).reshape(tuple(eqn.params["new_sizes"])))]


def _squeeze(eqn, vals, B):
    return [(R, _one_rows(eqn, vals, B).reshape(tuple(eqn.outvars[0].aval.shape)))]


def _slice(eqn, vals, B):
    p = eqn.params
    strides = p["strides"] or (1,) * len(p["start_indices"])
    sl = tuple(slice(a, b, c) for a, b, c in zip(p["start_indices"], p["limit_indices"], strides))
    return [(R, _one_rows(eqn, vals, B)[sl])]


def _transpose(eqn, vals, B):
    return [(R, _one_rows(eqn, vals, B).transpose(tuple(eqn.params["permutation"])))]


def _rev(eqn, vals, B):
    return [(R, np.flip(_one_rows(eqn, vals, B), axis=tuple(eqn.params["dimensions"])))]


def _concatenate(eqn, vals, B):
    parts = [_rows(val, tuple(v.aval.shape), B, v.aval.dtype) for val, v in zip(vals, eqn.invars)]
    return [(R, np.concatenate(parts, axis=eqn.params["dimension"]))]


def _split(eqn, vals, B):
    x = _one_rows(eqn, vals, B)
    axis = eqn.params["axis"]
    bounds = np.cumsum([0] + [int(n) for n in eqn.params["sizes"]])
    pick = lambda a, b: tuple(slice(a, b) if d == axis else slice(None) for d in range(x.ndim))
    return [(R, x[pick(a, b)]) for a, b in zip(bounds[:-1], bounds[1:])]


def _stack(eqn, vals, B):
    parts = [_rows(val, tuple(v.aval.shape), B, v.aval.dtype) for val, v in zip(vals, eqn.invars)]
    return [(R, np.stack(parts, axis=eqn.params["axis"]))]


def _identity(eqn, vals, B):
    return [(R, _one_rows(eqn, vals, B))]


def _barrier(eqn, vals, B):
    """`optimization_barrier` over every row of its operands (known components pass through):
    XLA fuses on neither side of it, so a long straight-line step is not fused into a few
    huge fusions that recompute shared terms."""
    flat = [(k, x.ravel().tolist() if k == R else [x]) for k, x in vals]
    live = [e for k, es in flat for e in es if not (k == R and _is_const(e))]
    it = iter(lax.optimization_barrier(live) if live else [])
    outs = []
    for (k, es), v in zip(flat, eqn.invars):
        new = [e if (k == R and _is_const(e)) else next(it) for e in es]
        outs.append((R, _obj(tuple(v.aval.shape), new)) if k == R else (k, new[0]))
    return outs


def _dynamic_slice(eqn, vals, B):
    """A slice at unbatched (traced) starts: a select among the few possible slices."""
    x = _one_rows(eqn, vals, B)
    starts = vals[1:]
    if any(k != U for k, _ in starts):
        return None
    sizes = tuple(eqn.params["slice_sizes"])
    x_dtype = eqn.invars[0].aval.dtype
    # XLA clamps the starts into range: start ∈ [0, n - size]
    clamped = [jnp.clip(jnp.asarray(s, jnp.int32), 0, n - m) for (_, s), n, m in zip(starts, x.shape, sizes)]

    def pick(idx, d, prefix):
        if d == x.ndim:
            return x[tuple(prefix)]
        n = x.shape[d] - sizes[d] + 1
        if n == 1:
            return pick(idx, d + 1, prefix + [idx[d]])
        return lax.select_n(clamped[d], *[lift(pick(idx, d + 1, prefix + [k + idx[d]]), B, x_dtype) for k in range(n)])

    out = np.empty(sizes, dtype=object)
    for idx in np.ndindex(*sizes):
        out[idx] = pick(idx, 0, [])
    return [(R, out)]


_REDUCERS = {
    "reduce_sum": lax.add,
    "reduce_max": lax.max,
    "reduce_min": lax.min,
    "reduce_prod": lax.mul,
    "reduce_and": lax.bitwise_and,
    "reduce_or": lax.bitwise_or,
}


def _reduce(eqn, vals, B):
    x = _one_rows(eqn, vals, B)
    axes = tuple(eqn.params["axes"])
    keep = [d for d in range(x.ndim) if d not in axes]
    moved = x.transpose(keep + list(axes))
    out_shape = moved.shape[: len(keep)]
    k = math.prod(moved.shape[len(keep) :])
    if k == 0 or math.prod(out_shape) * k > MAX_PRODUCTS:
        return None
    flat = moved.reshape(out_shape + (k,))
    op = _REDUCERS[eqn.primitive.name]
    out = np.empty(out_shape, dtype=object)
    for idx in np.ndindex(*out_shape):
        if op is lax.add:
            out[idx] = functools.reduce(_add, list(flat[idx]))
        else:
            out[idx] = functools.reduce(op, [lift(e, B, eqn.invars[0].aval.dtype) for e in flat[idx]])
    return [(R, out)]


def _place(ndim, *groups):
    """An index of `ndim` axes with the axes of each group (axes, values) set to its values."""
    idx = [0] * ndim
    for axes, values in groups:
        for d, i in zip(axes, values):
            idx[d] = i
    return tuple(idx)


def _dot_general(eqn, vals, B):
    (lc, rc), (lb, rb) = eqn.params["dimension_numbers"]
    lv, rv = eqn.invars
    ls, rs = tuple(lv.aval.shape), tuple(rv.aval.shape)
    out_shape = tuple(eqn.outvars[0].aval.shape)
    contracted = [ls[d] for d in lc]
    dtype = eqn.outvars[0].aval.dtype
    if math.prod(out_shape) * math.prod(contracted) > MAX_PRODUCTS or not jnp.issubdtype(dtype, jnp.inexact):
        return None
    lf = [d for d in range(len(ls)) if d not in lc and d not in lb]
    rf = [d for d in range(len(rs)) if d not in rc and d not in rb]
    L, Rr = _rows(vals[0], ls, B, lv.aval.dtype), _rows(vals[1], rs, B, rv.aval.dtype)
    out = np.empty(out_shape, dtype=object)
    for idx in np.ndindex(*out_shape):
        bi, li, ri = idx[: len(lb)], idx[len(lb) : len(lb) + len(lf)], idx[len(lb) + len(lf) :]
        terms = []
        for ci in np.ndindex(*contracted):
            l_idx = _place(len(ls), (lb, bi), (lf, li), (lc, ci))
            r_idx = _place(len(rs), (rb, bi), (rf, ri), (rc, ci))
            terms.append(_mul(L[l_idx], Rr[r_idx], dtype))
        out[idx] = functools.reduce(_add, terms) if terms else np.zeros((), dtype)
    return [(R, out)]


ROW_RULES = {
    **{name: _elementwise for name in ELEMENTWISE},
    **{name: _reduce for name in _REDUCERS},
    "broadcast_in_dim": _broadcast_in_dim,
    "reshape": _reshape,
    "squeeze": _squeeze,
    "slice": _slice,
    "transpose": _transpose,
    "rev": _rev,
    "concatenate": _concatenate,
    "split": _split,
    "stack": _stack,
    "stop_gradient": _identity,
    "optimization_barrier": _barrier,
    "dynamic_slice": _dynamic_slice,
    "dot_general": _dot_general,
}
"""The rules of the primitives on rows, but control flow (`scalarise._RULES`); a rule returns
None where it does not apply (a value too large for rows), and the primitive is then stacked."""
