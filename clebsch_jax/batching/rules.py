r"""The stacked layout: every batched value batch-last, a rule per primitive.

A batched value is `(S, x)` with x of shape member_shape + (B,), the batch axis last; an
unbatched one `(U, x)`. `Stacked` is the layout of `clebsch_jax.batching.walk.evaluate` that
holds them so: elementwise operations, broadcasts, reshapes, slices, reductions and small
`dot_general`s keep the batch axis last at no cost (`RULES`, each `rule(eqn, arrays, flags,
B)`); the walk evaluates `scan`, `while` and `cond` with batch-last bodies and enters calls.
Any other primitive falls back on `jax.vmap` of that one primitive with the batch axis moved
last around it (`fallback`). `clebsch_jax.batch` (`batch_last.py`) walks a program with this
layout, and the rows layout (`scalarise.py`) hands it what it does not hold as rows.
"""

from __future__ import annotations

import contextlib
import math

import jax
import jax.numpy as jnp
from jax import lax

from .walk import CONTROL, S, U, bind, evaluate_closed

SMALL_DOT = 4096
"""A `dot_general` whose output times contraction size is at most this many products is
evaluated as a broadcast multiply and a sum (batch-last, fused); larger ones fall back on
`jax.vmap`."""


def flat_axes(in_axes, args):
    """One entry, 0 or None, per leaf of `args`."""
    if in_axes is None or isinstance(in_axes, int):
        in_axes = (in_axes,) * len(args)
    if not isinstance(in_axes, (tuple, list)) or len(in_axes) != len(args):
        raise ValueError(
            f"in_axes: expected 0, None or a tuple of them with one entry per argument ({len(args)}), got {in_axes!r}."
        )
    axes = []
    for ax, arg in zip(in_axes, args):
        if ax not in (0, None) or isinstance(ax, bool):
            raise ValueError(f"in_axes: expected 0 or None for every argument, got {ax!r}.")
        axes.extend([ax] * len(jax.tree_util.tree_leaves(arg)))
    return axes


def batch_members(leaves, axes):
    """The batch size B, the leaves as arrays and one member's shapes (checked: every batched
    leaf has a leading axis, all of one size)."""
    sizes = {jnp.shape(x)[0] for x, a in zip(leaves, axes) if a == 0 and jnp.ndim(x) > 0}
    if any(a == 0 and jnp.ndim(x) == 0 for x, a in zip(leaves, axes)):
        raise ValueError("in_axes: a batched argument is a scalar; it has no axis 0 to batch over.")
    if len(sizes) != 1:
        raise ValueError(
            "in_axes: the batched arguments must share one leading axis size, got "
            f"{sorted(sizes) if sizes else 'no batched argument'}."
        )
    leaves = [jnp.asarray(x) for x in leaves]
    member = [jax.ShapeDtypeStruct(x.shape[1:] if a == 0 else x.shape, x.dtype) for x, a in zip(leaves, axes)]
    return sizes.pop(), leaves, member


def to_batched(x, batched, B):
    if batched:
        return x
    x = jnp.asarray(x)
    return lax.broadcast_in_dim(x, x.shape + (B,), tuple(range(x.ndim)))


def _match(values, flags, wants, B):
    """`values` (batched where `flags`) made batched wherever `wants` says."""
    return [to_batched(x, f, B) if w else x for x, f, w in zip(values, flags, wants)]


def fallback(eqn, vals, bs, B):
    """`jax.vmap` of the one primitive, the batch axis moved last around it."""

    def f(*xs):
        return bind(eqn, xs)

    outs = jax.vmap(f, in_axes=[-1 if b else None for b in bs], out_axes=-1, axis_size=B)(*vals)
    return outs, [True] * len(outs)


def _elementwise(eqn, vals, bs, B):
    shape = tuple(eqn.outvars[0].aval.shape)
    full = shape + (B,)
    args = []
    for x, b, v in zip(vals, bs, eqn.invars):
        s = tuple(v.aval.shape)
        # jaxprs broadcast scalars and size-1 axes implicitly: make every operand full
        if b and s != shape:
            x = lax.broadcast_in_dim(x, full, tuple(range(len(s))) + (len(shape),) if s else (len(shape),))
        elif not b:  # (XLA fuses the broadcasts into the operation)
            x = lax.broadcast_in_dim(x, full, tuple(range(len(s))))
        args.append(x)
    return bind(eqn, args), [True] * len(eqn.outvars)


def _same_params(eqn, vals, bs, B):
    """Operations whose parameters name member axes only (reductions, squeeze, split,
    cumulative sums, concatenate, stack): with every operand batched the batch axis, last, is
    untouched."""
    return bind(eqn, _match(vals, bs, [True] * len(vals), B)), [True] * len(eqn.outvars)


def _as_is(eqn, vals, bs, B):
    """`optimization_barrier`: applied to the operands as they are, all made batched (as
    `_flags` predicts for an operation with a batched operand)."""
    return bind(eqn, _match(vals, bs, [True] * len(vals), B)), [True] * len(vals)


def _broadcast_in_dim(eqn, vals, bs, B):
    x, *dyn = vals
    if dyn or not bs[0]:
        return fallback(eqn, vals, bs, B)
    shape = tuple(eqn.params["shape"]) + (B,)
    dims = tuple(eqn.params["broadcast_dimensions"]) + (len(shape) - 1,)
    return bind(eqn, [x], shape=shape, broadcast_dimensions=dims), [True]


def _reshape(eqn, vals, bs, B):
    if len(vals) != 1 or eqn.params.get("dimensions") is not None:
        return fallback(eqn, vals, bs, B)
    return bind(eqn, vals, new_sizes=tuple(eqn.params["new_sizes"]) + (B,)), [True]


def _slice(eqn, vals, bs, B):
    p = eqn.params
    strides = None if p["strides"] is None else tuple(p["strides"]) + (1,)
    return bind(
        eqn,
        vals,
        start_indices=tuple(p["start_indices"]) + (0,),
        limit_indices=tuple(p["limit_indices"]) + (B,),
        strides=strides,
    ), [True]


def _pad(eqn, vals, bs, B):
    if bs[1]:
        return fallback(eqn, vals, bs, B)
    return bind(eqn, vals, padding_config=tuple(eqn.params["padding_config"]) + ((0, 0, 0),)), [True]


def _transpose(eqn, vals, bs, B):
    perm = tuple(eqn.params["permutation"])
    return bind(eqn, vals, permutation=perm + (len(perm),)), [True]


def _dot_general(eqn, vals, bs, B):
    """Small contractions as a broadcast multiply and a sum over the contracted axes."""
    (lc, rc), (lb, rb) = eqn.params["dimension_numbers"]
    ls, rs = (tuple(v.aval.shape) for v in eqn.invars)
    out_shape = tuple(eqn.outvars[0].aval.shape)
    contracted = math.prod(ls[d] for d in lc)
    if math.prod(out_shape) * contracted > SMALL_DOT or not jnp.issubdtype(eqn.outvars[0].aval.dtype, jnp.inexact):
        return fallback(eqn, vals, bs, B)
    lf = [d for d in range(len(ls)) if d not in lc and d not in lb]
    rf = [d for d in range(len(rs)) if d not in rc and d not in rb]
    l, r = _match(vals, bs, (True, True), B)
    # member axes ordered (batch dims, lhs free, rhs free, contracted), B last
    l = jnp.transpose(l, tuple(lb) + tuple(lf) + tuple(lc) + (len(ls),))
    r = jnp.transpose(r, tuple(rb) + tuple(rf) + tuple(rc) + (len(rs),))
    nb, nlf, nrf, nc = len(lb), len(lf), len(rf), len(lc)
    l = l.reshape(l.shape[: nb + nlf] + (1,) * nrf + l.shape[nb + nlf :])
    r = r.reshape(r.shape[:nb] + (1,) * nlf + r.shape[nb:])
    prod = l * r
    out = jnp.sum(prod, axis=tuple(range(nb + nlf + nrf, nb + nlf + nrf + nc))) if nc else prod
    return [out.astype(eqn.outvars[0].aval.dtype)], [True]


ELEMENTWISE = """
abs acos acosh add add_any and asin asinh atan atan2 atanh cbrt ceil clamp conj convert_element_type
copy copy_p cos cosh digamma div eq erf erf_inv erfc exp exp2 expm1 floor ge gt imag integer_pow
is_finite le lgamma log log1p logistic lt max min mul ne neg nextafter not or pow real reduce_precision
rem round rsqrt select_n shift_left shift_right_arithmetic shift_right_logical sign sin sinh sqrt square
sub tan tanh xor
""".split()

_SAME_PARAMS = """
argmax argmin cumlogsumexp cummax cummin cumprod cumsum reduce_and reduce_max reduce_min reduce_or
reduce_prod reduce_sum reduce_xor rev split squeeze
""".split()

RULES = {
    **{name: _elementwise for name in ELEMENTWISE},
    **{name: _same_params for name in _SAME_PARAMS},
    "broadcast_in_dim": _broadcast_in_dim,
    "reshape": _reshape,
    "slice": _slice,
    "pad": _pad,
    "transpose": _transpose,
    "dot_general": _dot_general,
    "concatenate": _same_params,
    "optimization_barrier": _as_is,
    "stack": _same_params,
}
"""The rule of each primitive on stacked values (calls and control flow: the walk's)."""


class Stacked:
    """The layout of every batched value stacked batch-last (`clebsch_jax.batching.walk.Layout`)."""

    def __init__(self, B: int):
        self.B = B

    def unbatched(self, eqn, xs) -> list:
        return bind(eqn, xs)

    def apply(self, eqn, vals) -> list:
        name = eqn.primitive.name
        if name in CONTROL:
            return CONTROL[name](eqn, vals, self)
        arrays, flags = [x for _, x in vals], [k != U for k, _ in vals]
        rule = RULES.get(name)
        outs, out_flags = fallback(eqn, arrays, flags, self.B) if rule is None else rule(eqn, arrays, flags, self.B)
        return [(S if f else U, o) for o, f in zip(outs, out_flags)]

    def kinds(self, avals, flags) -> list:
        return [S if f else U for f in flags]

    def canon(self, vals, kinds, avals) -> list:
        return [(S, to_batched(x, False, self.B)) if w == S and k == U else (k, x) for (k, x), w in zip(vals, kinds)]

    def pack(self, vals) -> list:
        return [[x] for _, x in vals]

    def unpack(self, packed, kinds, avals) -> list:
        return [(k, p[0]) for p, k in zip(packed, kinds)]

    def loop_body(self, scan: bool):
        return contextlib.nullcontext()

    def scan_inputs(self, vals, invars) -> tuple:
        return [x for _, x in vals], [k for k, _ in vals]

    def unroll(self, params) -> int:
        return params["unroll"]

    def series(self, ys, kinds, avals, length) -> list:
        return [(k, y[0]) for y, k in zip(ys, kinds)]

    def predicate(self, val):
        return val[1]

    def select(self, go, new, old, pred_shape, pred_batched):
        dims = tuple(range(len(pred_shape))) + ((new.ndim - 1,) if pred_batched else ())
        return lax.select(lax.broadcast_in_dim(go, new.shape, dims), new, old)

    def index(self, val):
        return val[1]

    def choose(self, index, results, kinds, avals) -> list:
        outs = []
        for k, kind in enumerate(kinds):
            cases = [r[k][0] for r in results]
            idx = lax.broadcast_in_dim(index, cases[0].shape, (cases[0].ndim - 1,))
            outs.append((kind, lax.select_n(idx if idx.dtype == jnp.bool_ else idx.astype(jnp.int32), *cases)))
        return outs


def eval_closed(closed, args, flags, B):
    """`closed` walked with the stacked layout on `args` (batched where `flags`): (the output
    arrays, their batched flags)."""
    outs = evaluate_closed(closed, [(S if f else U, a) for a, f in zip(args, flags)], Stacked(B))
    return [x for _, x in outs], [k != U for k, _ in outs]
