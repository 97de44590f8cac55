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
of `clebsch_jax.batch` (`clebsch_jax.batching.rules`), as does every primitive without a rule
here (a gather, a callback): the rows are stacked around it. The result is `jax.vmap`'s up to
round-off (the same operations on the same numbers).

This module is the loop over the program and its control flow; the values, their conversions
and the rules of the other primitives on rows are `clebsch_jax.batching.rows`.
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

from .rows import (
    MAX_ROWS,
    ROW_RULES,
    R,
    S,
    U,
    as_kind,
    canonical_kind,
    concrete,
    entry,
    flatten,
    lift,
    numpy_fold,
    small,
    stacked,
    to_batch_first,
    unflatten,
)
from .rules import CALLS, batch_members, bind, cond_flags, fallback, flat_axes, scan_carry_flags, while_carry_flags
from .rules import RULES as STACKED_RULES

__all__ = ["scalarise", "MAX_ROWS"]


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
        axes = flat_axes(in_axes, args)
        B, leaves, member = batch_members(leaves, axes)

        def flat_fun(*flat):
            return fun(*jax.tree_util.tree_unflatten(tree, flat))

        closed, out_shapes = jax.make_jaxpr(flat_fun, return_shape=True)(*member)
        ins = [(S, jnp.moveaxis(x, 0, -1)) if a == 0 else (U, x) for x, a in zip(leaves, axes)]
        _TRACE.in_loop.append(not loops_only)
        try:
            outs = _eval(closed.jaxpr, closed.consts, ins, B)
        finally:
            _TRACE.in_loop.pop()
        flat_out = [to_batch_first(o, v.aval.shape, B) for o, v in zip(outs, closed.jaxpr.outvars)]
        return jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(out_shapes), flat_out)

    return batched


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
where it has a rule (`numpy_fold`), not an eager JAX operation: a few hundred of those, each
dispatched and, per new shape, compiled, made much of a lean chunk's trace time."""


def _unbatched(eqn, xs):
    """An operation on unbatched operands: folded to NumPy constants when it can be
    (`FOLD_SIZE`), else emitted as it is."""
    foldable = all(math.prod(v.aval.shape) <= FOLD_SIZE for v in eqn.outvars if hasattr(v.aval, "shape"))
    if foldable and not eqn.effects and eqn.primitive.name not in _CONTROL and eqn.primitive.name not in CALLS:
        known = [concrete(x) for x in xs]
        if all(k is not None for k in known):
            outs = numpy_fold(eqn, known)
            if outs is None:
                with jax.ensure_compile_time_eval():
                    outs = bind(eqn, [jnp.asarray(k) for k in known])
            return [np.asarray(o, dtype=v.aval.dtype) for o, v in zip(outs, eqn.outvars)]
    return bind(eqn, xs)


def _apply(eqn, vals, B):
    name = eqn.primitive.name
    if name in CALLS:
        inner = eqn.params[CALLS[name]]
        if isinstance(inner, jex.ClosedJaxpr):
            return _eval(inner.jaxpr, inner.consts, vals, B)
        return _eval(inner, (), vals, B)
    rule = _RULES.get(name)
    if not _TRACE.in_loop[-1] and name != "scan":
        return _stacked_rule(eqn, vals, B)
    shapes_small = all(
        small(v.aval.shape)
        for v in list(eqn.invars) + list(eqn.outvars)
        if not isinstance(v, jex.Literal) and hasattr(v.aval, "shape")
    )
    if rule is not None and (shapes_small or name in _CONTROL):
        out = rule(eqn, vals, B)
        if out is not None:
            return out
    return _stacked_rule(eqn, vals, B)


def _stacked_rule(eqn, vals, B):
    """The primitive on stacked batch-last operands, by its batch-last rule (`clebsch_jax.batching.rules`)."""
    arrays = [x if k == U else stacked((k, x), v.aval.shape, B) for (k, x), v in zip(vals, eqn.invars)]
    flags = [k != U for k, _ in vals]
    rule = STACKED_RULES.get(eqn.primitive.name)
    outs, out_flags = fallback(eqn, arrays, flags, B) if rule is None else rule(eqn, arrays, flags, B)
    return [(S, o) if f else (U, o) for o, f in zip(outs, out_flags)]


# Control flow: carries in their canonical kinds (rows when small), flattened to lists.


def _kinds(avals, flags):
    return [canonical_kind(tuple(a.shape), f) for a, f in zip(avals, flags)]


def _canon(vals, kinds, avals, B):
    return [as_kind(v, k, tuple(a.shape), B, a.dtype) for v, k, a in zip(vals, kinds, avals)]


def _pack(vals, B):
    return [flatten(v, B) for v in vals]


def _unpack(packed, kinds, avals):
    return [unflatten(k, tuple(a.shape), list(p)) for p, k, a in zip(packed, kinds, avals)]


def _scan(eqn, vals, B):
    p = eqn.params
    nc, nk = p["num_consts"], p["num_carry"]
    flags = [k != U for k, _ in vals]
    carry_flags, out_flags = scan_carry_flags(p, flags)
    body = p["jaxpr"]
    in_avals = body.in_avals
    carry_avals = in_avals[nc : nc + nk]
    ys_avals = body.out_avals[nk:]
    carry_kinds = _kinds(carry_avals, carry_flags)
    ys_kinds = [canonical_kind(tuple(a.shape), f) for a, f in zip(ys_avals, out_flags[nk:])]
    consts = vals[:nc]
    init = _pack(_canon(vals[nc : nc + nk], carry_kinds, carry_avals, B), B)
    # xs: sliced along the scan axis, so stacked (or unbatched)
    xs = [
        x if k == U else stacked((k, x), v.aval.shape, B) for (k, x), v in zip(vals[nc + nk :], eqn.invars[nc + nk :])
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
    carry_flags, pred_batched = while_carry_flags(p, flags)
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
            return lift(entry(pred(c), (), (), B, jnp.bool_), B, jnp.bool_)

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
    out_flags = cond_flags(eqn.params, flags)
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
    idx = lift(entry(index, (), (), B, eqn.invars[0].aval.dtype), B)
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

_RULES = {**ROW_RULES, "scan": _scan, "while": _while, "cond": _cond}
