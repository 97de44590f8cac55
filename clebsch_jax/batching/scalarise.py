r"""`scalarise`: `jax.vmap` for many small members, each component of a member its own (B,) row.

`clebsch_jax.batch` stores a batched value of member shape S as one array of shape S + (B,);
XLA then runs every operation of the member's program on the whole stack, and a sum over a
member axis (a dot product, a 3×3 matrix-vector product, the max-norm of a Newton update) is
a reduction with a launch of its own. `scalarise` evaluates the same per-member program
(`jax.make_jaxpr` of one member) with every *small* batched value held as a NumPy object
array of shape S whose entries are (B,) JAX arrays, one per component — the shape of a
kernel written by hand with one row per component:

- elementwise operations map over the entries;
- broadcast, reshape, squeeze, slice, transpose, reverse and concatenate only re-index the
  entries (no operation at all);
- reductions and small `dot_general`s become explicit sums of products of rows;
- the carries of `scan`, `while` and `cond` are flat lists of rows (a `while` whose predicate
  differs between members runs until the last member stops, the others held by a select, as
  under `jax.vmap`).

Components known when the program is traced (the entries of `jnp.eye`, the zero tangents
of a Jacobian's columns, a predictor's coefficients) stay NumPy scalars in the rows: a product
with 0 or 1 and a sum with 0 are not emitted. (x·0 is then 0 where IEEE gives NaN for x NaN
or inf; callers that must see non-finite members test values that do not pass through such
products — `sweep`'s fast path checks each solve's residual.)

A value is small when its member shape has at most `MAX_ROWS` components. Larger values (a
trajectory, a cluster of a hundred particles) stay stacked batch-last and go through the rules
of `clebsch_jax.batching.batch_last`, as does every primitive without a rule here (a gather, a
callback): the rows are stacked around it. The result is `jax.vmap`'s up to round-off (the
same operations on the same numbers).
"""

from __future__ import annotations

import functools
import math
import threading
from typing import Callable

import jax
import jax.extend.core as jex
import jax.numpy as jnp
import numpy as np
from jax import lax

from . import batch_last as _bl

__all__ = ["scalarise", "MAX_ROWS"]

MAX_ROWS = 32
"""Batched values with at most this many components per member are held as rows."""

SCAN_UNROLL = 4
"""`scan`s of rows are unrolled this many times (at least): XLA then keeps the rows of the
carry in place instead of copying each after every iteration."""

SHORT_SCAN = 8
"""... except scans of at most this many iterations outside every loop (a small factorisation's
loop over its columns, run once per call, not once per step as a loop inside a march's loop
body is): their copies cost nothing worth saving, while XLA compiles every unrolled copy of
their body (the lean chunk's minimum-norm cotangent, a loop of three, unrolled: about a third
of its compile time)."""


class _TraceState(threading.local):
    """The evaluator's state while it traces, the calling thread's own (a sweep traces its
    batches' programs from several threads at once, `clebsch_jax.sweep`'s `threads`):

    - `depth`: how many `scan` or `while` bodies the evaluator is inside;
    - `in_loop`: whether small values are held as rows here (the last entry): inside a `scan`
      body, and everywhere under `scalarise(..., loops_only=False)`; elsewhere every value
      stays stacked as `batch_last` holds it (a scan's trajectory outputs and what is computed
      from them are large)."""

    def __init__(self):
        self.depth = 0
        self.in_loop = [False]


_TRACE = _TraceState()

MAX_PRODUCTS = 512
"""A `dot_general` (or reduction) of rows with more products than this is stacked instead."""


# A value in the evaluator is (kind, x): U unbatched (an array of the member's shape), S stacked
# batch-last (member shape + (B,)), R rows (a NumPy object array of the member's shape with
# (B,) entries).
U, S, R = "u", "s", "r"


def scalarise(fun: Callable, in_axes=0, *, loops_only: bool = True) -> Callable:
    """`jax.vmap(fun, in_axes)` evaluated with each component of a small member value as its
    own (B,) row (module docstring).

    **Arguments:** `fun`, a function of arrays that `jax.vmap` could batch; `in_axes`, 0 or None
    per positional argument (as `clebsch_jax.batch`); `loops_only`: hold values as rows only
    inside loop bodies (`_TraceState.in_loop`), or, False, wherever they are small — for a program whose
    work outside its loops is on small values too (the lean chunk's start and end: a momentum
    map, a minimum-norm cotangent, whose small products would otherwise be stacked
    `dot_general`s).

    **Returns:** a function with `jax.vmap(fun, in_axes)`'s signature and outputs (every output
    batched along axis 0).

    Transformations: jit-compatible (trace it inside `jax.jit`). Not for differentiation or a
    second `vmap`, for the reasons `clebsch_jax.batch` gives.
    """

    @functools.wraps(fun)
    def batched(*args):
        leaves, tree = jax.tree_util.tree_flatten(args)
        axes = _bl._flat_axes(in_axes, args)
        B, leaves, member = _bl._members(leaves, axes)

        def flat_fun(*flat):
            return fun(*jax.tree_util.tree_unflatten(tree, flat))

        closed, out_shapes = jax.make_jaxpr(flat_fun, return_shape=True)(*member)
        ins = [(S, jnp.moveaxis(x, 0, -1)) if a == 0 else (U, x) for x, a in zip(leaves, axes)]
        _TRACE.in_loop.append(not loops_only)
        try:
            outs = _eval(closed.jaxpr, closed.consts, ins, B)
        finally:
            _TRACE.in_loop.pop()
        flat_out = [_to_batch_first(o, v.aval.shape, B) for o, v in zip(outs, closed.jaxpr.outvars)]
        return jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(out_shapes), flat_out)

    return batched


# --------------------------------------------------------------------------------------------
# Values and their conversions.


def _small(shape) -> bool:
    return math.prod(shape) <= MAX_ROWS


def _obj(shape, entries) -> np.ndarray:
    out = np.empty(len(entries), dtype=object)
    for i, e in enumerate(entries):
        out[i] = e
    return out.reshape(shape)


def _to_batch_first(val, shape, B):
    kind, x = val
    if kind == U:
        x = jnp.asarray(x)
        return jnp.broadcast_to(x, (B,) + x.shape)
    return jnp.moveaxis(_stacked(val, shape, B), -1, 0)


def _row_of_const(c, B, dtype=None):
    c = jnp.asarray(c, dtype)
    return lax.broadcast_in_dim(c, (B,), ())


def _is_const(e) -> bool:
    """A component known at trace time (a NumPy scalar), not a (B,) row."""
    return isinstance(e, (np.ndarray, np.generic))


def _concrete(x):
    """x as a NumPy array if its value is known at trace time, else None."""
    if isinstance(x, jax.core.Tracer):
        return None
    try:
        return np.asarray(x)
    except Exception:  # an abstract value
        return None


def _lift(e, B, dtype=None):
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


def _stacked(val, shape, B):
    """Any value as a stacked batch-last array."""
    kind, x = val
    if kind == S:
        return x
    if kind == U:
        x = jnp.asarray(x)
        return lax.broadcast_in_dim(x, x.shape + (B,), tuple(range(x.ndim)))
    entries = [_lift(e, B) for e in x.ravel()]
    return jnp.stack(entries, axis=0).reshape(tuple(shape) + (B,)) if entries else jnp.zeros(tuple(shape) + (B,))


def _rows(val, shape, B, dtype=None):
    """A batched or unbatched value as rows."""
    kind, x = val
    if kind == R:
        return x
    if kind == S:
        return _obj(shape, [x[idx] for idx in np.ndindex(*shape)])
    c = _concrete(x)
    if c is not None:
        c = c.astype(dtype) if dtype is not None else c
        return _obj(shape, [np.asarray(c[idx]) for idx in np.ndindex(*shape)])
    x = jnp.asarray(x, dtype)
    return _obj(shape, [_row_of_const(x[idx], B) for idx in np.ndindex(*shape)])


def _canonical_kind(shape, batched) -> str:
    if not batched:
        return U
    return R if _small(shape) else S


def _as_kind(val, kind, shape, B, dtype=None):
    if kind == U:
        if val[0] != U:
            raise AssertionError("a batched value cannot become unbatched")
        return val
    return (R, _rows(val, shape, B, dtype)) if kind == R else (S, _stacked(val, shape, B))


def _flatten(val, B):
    """A value as a list of arrays for a loop's carry."""
    kind, x = val
    return [_lift(e, B) for e in x.ravel()] if kind == R else [x]


def _unflatten(kind, shape, arrays):
    if kind == R:
        return R, _obj(shape, arrays)
    return kind, arrays[0]


# --------------------------------------------------------------------------------------------
# The interpreter.


def _eval(jaxpr, consts, args, B):
    env = {}

    def read(v):
        if isinstance(v, jex.Literal):
            return U, v.val
        return env[v]

    for v, c in zip(jaxpr.constvars, consts):
        env[v] = (U, c)
    for v, a in zip(jaxpr.invars, args):
        env[v] = a
    for eqn in jaxpr.eqns:
        vals = [read(v) for v in eqn.invars]
        if all(k == U for k, _ in vals):
            outs = [(U, o) for o in _unbatched(eqn, [x for _, x in vals])]
        else:
            outs = _apply(eqn, vals, B)
        for v, o in zip(eqn.outvars, outs):
            if not isinstance(v, jex.DropVar):
                env[v] = o
    return [read(v) for v in jaxpr.outvars]


FOLD_SIZE = 64
"""An unbatched operation whose operands are all known when the program is traced, with at most
this many output elements, is evaluated then (a NumPy constant): the entries of `jnp.eye`
(the tangents a forward-mode Jacobian pushes through the step), the predictor's coefficients.
Products with their zeros and ones are then not emitted at all. The evaluation is NumPy's own
where it has a rule (`_numpy_fold`), not an eager JAX operation: a few hundred of those, each
dispatched and, per new shape, compiled, made much of a lean chunk's trace time."""


def _unbatched(eqn, xs):
    """An operation on unbatched operands: folded to NumPy constants when it can be
    (`FOLD_SIZE`), else emitted as it is."""
    small = all(math.prod(v.aval.shape) <= FOLD_SIZE for v in eqn.outvars if hasattr(v.aval, "shape"))
    if small and not eqn.effects and eqn.primitive.name not in _CONTROL and eqn.primitive.name not in _bl._CALLS:
        known = [_concrete(x) for x in xs]
        if all(k is not None for k in known):
            outs = _numpy_fold(eqn, known)
            if outs is None:
                with jax.ensure_compile_time_eval():
                    outs = _bl._bind(eqn, [jnp.asarray(k) for k in known])
            return [np.asarray(o, dtype=v.aval.dtype) for o, v in zip(outs, eqn.outvars)]
    return _bl._bind(eqn, xs)


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


def _numpy_fold(eqn, known):
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


def _apply(eqn, vals, B):
    name = eqn.primitive.name
    if name in _bl._CALLS:
        inner = eqn.params[_bl._CALLS[name]]
        if isinstance(inner, jex.ClosedJaxpr):
            return _eval(inner.jaxpr, inner.consts, vals, B)
        return _eval(inner, (), vals, B)
    rule = _RULES.get(name)
    if not _TRACE.in_loop[-1] and name != "scan":
        return _stacked_rule(eqn, vals, B)
    shapes_small = all(
        _small(v.aval.shape)
        for v in list(eqn.invars) + list(eqn.outvars)
        if not isinstance(v, jex.Literal) and hasattr(v.aval, "shape")
    )
    if rule is not None and (shapes_small or name in _CONTROL):
        out = rule(eqn, vals, B)
        if out is not None:
            return out
    return _stacked_rule(eqn, vals, B)


def _stacked_rule(eqn, vals, B):
    """The primitive on stacked batch-last operands, by `batch_last`'s rule."""
    arrays = [x if k == U else _stacked((k, x), v.aval.shape, B) for (k, x), v in zip(vals, eqn.invars)]
    flags = [k != U for k, _ in vals]
    rule = _bl._RULES.get(eqn.primitive.name)
    outs, out_flags = _bl._fallback(eqn, arrays, flags, B) if rule is None else rule(eqn, arrays, flags, B)
    return [(S, o) if f else (U, o) for o, f in zip(outs, out_flags)]


def _entry(val, idx, aval_shape, B, dtype):
    """Component idx of an operand (scalars and size-1 axes broadcast): a (B,) row, or a NumPy
    scalar when it is known at trace time."""
    kind, x = val
    src = tuple(i if n != 1 else 0 for i, n in zip(idx[len(idx) - len(aval_shape) :], aval_shape))
    if kind == R:
        return x[src]
    if kind == S:
        return x[src]
    c = _concrete(x)
    if c is not None:
        return np.asarray(c.astype(dtype)[src])
    return _row_of_const(jnp.asarray(x, dtype)[src] if aval_shape else x, B, dtype)


def _elementwise(eqn, vals, B):
    shape = tuple(eqn.outvars[0].aval.shape)
    params = eqn.params
    out = [np.empty(shape, dtype=object) for _ in eqn.outvars]
    for idx in np.ndindex(*shape):
        args = [_entry(val, idx, tuple(v.aval.shape), B, v.aval.dtype) for val, v in zip(vals, eqn.invars)]
        res = _fold(eqn, args)
        if res is None:
            if all(_is_const(a) for a in args):
                res = _numpy_fold(eqn, [np.asarray(a) for a in args])
                if res is None:
                    with eqn.ctx.manager, jax.ensure_compile_time_eval():
                        res = eqn.primitive.bind(*[jnp.asarray(a) for a in args], **params)
                    res = res if eqn.primitive.multiple_results else [res]
                res = [np.asarray(r, dtype=v.aval.dtype) for r, v in zip(res, eqn.outvars)]
            else:
                args = [_lift(a, B, v.aval.dtype) for a, v in zip(args, eqn.invars)]
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
        return lax.select_n(clamped[d], *[_lift(pick(idx, d + 1, prefix + [k + idx[d]]), B, x_dtype) for k in range(n)])

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
            out[idx] = functools.reduce(op, [_lift(e, B, eqn.invars[0].aval.dtype) for e in flat[idx]])
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


# Control flow: carries in their canonical kinds (rows when small), flattened to lists.


def _kinds(avals, flags):
    return [_canonical_kind(tuple(a.shape), f) for a, f in zip(avals, flags)]


def _canon(vals, kinds, avals, B):
    return [_as_kind(v, k, tuple(a.shape), B, a.dtype) for v, k, a in zip(vals, kinds, avals)]


def _pack(vals, B):
    return [_flatten(v, B) for v in vals]


def _unpack(packed, kinds, avals):
    return [_unflatten(k, tuple(a.shape), list(p)) for p, k, a in zip(packed, kinds, avals)]


def _scan(eqn, vals, B):
    p = eqn.params
    nc, nk = p["num_consts"], p["num_carry"]
    flags = [k != U for k, _ in vals]
    carry_flags, out_flags = _bl._scan_carry_flags(p, flags)
    body = p["jaxpr"]
    in_avals = body.in_avals
    carry_avals = in_avals[nc : nc + nk]
    ys_avals = body.out_avals[nk:]
    carry_kinds = _kinds(carry_avals, carry_flags)
    ys_kinds = [_canonical_kind(tuple(a.shape), f) for a, f in zip(ys_avals, out_flags[nk:])]
    consts = vals[:nc]
    init = _pack(_canon(vals[nc : nc + nk], carry_kinds, carry_avals, B), B)
    # xs: sliced along the scan axis, so stacked (or unbatched)
    xs = [
        x if k == U else _stacked((k, x), v.aval.shape, B) for (k, x), v in zip(vals[nc + nk :], eqn.invars[nc + nk :])
    ]
    x_kinds = [U if k == U else S for k, _ in vals[nc + nk :]]

    def step(carry, x):
        c = _unpack(carry, carry_kinds, carry_avals)
        xv = [(k, xi) for k, xi in zip(x_kinds, x)]
        _TRACE.in_loop.append(True)
        _TRACE.depth += 1
        try:
            outs = _eval(body.jaxpr, body.consts, list(consts) + c + xv, B)
        finally:
            _TRACE.in_loop.pop()
            _TRACE.depth -= 1
        new = _pack(_canon(outs[:nk], carry_kinds, carry_avals, B), B)
        # each row of an output its own stacked series: XLA writes them in place
        return new, _pack(_canon(outs[nk:], ys_kinds, ys_avals, B), B)

    # an unroll the program asks for is kept; otherwise at least SCAN_UNROLL, except for a short
    # scan outside every loop
    if int(p["unroll"]) > 1:
        unroll = int(p["unroll"])
    elif p["length"] <= SHORT_SCAN and _TRACE.depth == 0:
        unroll = 1
    else:
        unroll = min(SCAN_UNROLL, p["length"])
    carry, ys = lax.scan(step, init, xs, length=p["length"], reverse=p["reverse"], unroll=unroll)
    return _unpack(carry, carry_kinds, carry_avals) + [
        _series(k, y, a.shape, p["length"], B) for k, y, a in zip(ys_kinds, ys, ys_avals)
    ]


def _series(kind, arrays, shape, n, B):
    """A scan's stacked output, (n, …member shape, B), from its rows' series (each (n, B))."""
    if kind == R:
        stacked = jnp.stack(arrays, axis=1) if arrays else jnp.zeros((n, 0, B))
        return S, stacked.reshape((n,) + tuple(shape) + (B,))
    return kind, arrays[0]


def _while(eqn, vals, B):
    p = eqn.params
    nc, nb = p["cond_nconsts"], p["body_nconsts"]
    flags = [k != U for k, _ in vals]
    carry_flags, pred_batched = _bl._while_carry_flags(p, flags)
    cond_j, body_j = p["cond_jaxpr"], p["body_jaxpr"]
    if tuple(cond_j.out_avals[0].shape):
        return None  # a predicate with member axes: leave it to batch_last
    carry_avals = body_j.out_avals
    kinds = _kinds(carry_avals, carry_flags)
    cc, bc = vals[:nc], vals[nc : nc + nb]
    init = _pack(_canon(vals[nc + nb :], kinds, carry_avals, B), B)

    def pred(carry):
        return _eval(cond_j.jaxpr, cond_j.consts, list(cc) + _unpack(carry, kinds, carry_avals), B)[0]

    def body(carry):
        _TRACE.depth += 1
        try:
            outs = _eval(body_j.jaxpr, body_j.consts, list(bc) + _unpack(carry, kinds, carry_avals), B)
        finally:
            _TRACE.depth -= 1
        return _pack(_canon(outs, kinds, carry_avals, B), B)

    if not pred_batched:
        out = lax.while_loop(lambda c: pred(c)[1], body, init)
    else:

        def go_row(c):
            return _lift(_entry(pred(c), (), (), B, jnp.bool_), B, jnp.bool_)

        def masked(carry):
            go = go_row(carry)
            new = body(carry)
            return [
                [
                    lax.select(go if n.ndim == 1 else lax.broadcast_in_dim(go, n.shape, (n.ndim - 1,)), n, o)
                    for n, o in zip(ns, os)
                ]
                for ns, os in zip(new, carry)
            ]

        out = lax.while_loop(lambda c: jnp.any(go_row(c)), masked, init)
    return _unpack(out, kinds, carry_avals)


def _cond(eqn, vals, B):
    branches = eqn.params["branches"]
    flags = [k != U for k, _ in vals]
    out_flags = _bl._cond_flags(eqn.params, flags)
    out_avals = branches[0].out_avals
    kinds = _kinds(out_avals, out_flags)
    index, ops = vals[0], vals[1:]

    def run(br, operands):
        outs = _eval(br.jaxpr, br.consts, list(operands), B)
        return _pack(_canon(outs, kinds, out_avals, B), B)

    if index[0] == U:
        op_kinds = [k for k, _ in ops]
        op_avals = [v.aval for v in eqn.invars[1:]]
        packed = _pack(ops, B)

        def branch(br):
            return lambda ps: run(br, _unpack(ps, op_kinds, op_avals))

        out = lax.switch(index[1], [branch(br) for br in branches], packed)
        return _unpack(out, kinds, out_avals)
    idx = _lift(_entry(index, (), (), B, eqn.invars[0].aval.dtype), B)
    idx = idx if idx.dtype == jnp.bool_ else idx.astype(jnp.int32)
    results = [run(br, ops) for br in branches]
    outs = []
    for k in range(len(kinds)):
        arrays = []
        for parts in zip(*[r[k] for r in results]):
            sel = idx if parts[0].ndim == 1 else lax.broadcast_in_dim(idx, parts[0].shape, (parts[0].ndim - 1,))
            arrays.append(lax.select_n(sel, *parts))
        outs.append(arrays)
    return _unpack(outs, kinds, out_avals)


_CONTROL = {"scan", "while", "cond", "optimization_barrier"}

_RULES = {
    **{name: _elementwise for name in _bl._ELEMENTWISE},
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
    "scan": _scan,
    "while": _while,
    "cond": _cond,
}
