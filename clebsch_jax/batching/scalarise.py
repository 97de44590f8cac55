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

The walk over the program and its control flow is `clebsch_jax.batching.walk`'s, the one
`cj.batch` uses; this module is its layout of rows (`RowsLayout`: which values are rows, the
carries of loops as flat lists of rows, the unroll of scans) and `scalarise`; the values,
their conversions and the rules of the other primitives on rows are
`clebsch_jax.batching.rows`.
"""

from __future__ import annotations

import contextlib
import functools
import math
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
from .rules import Stacked, batch_members, flat_axes
from .walk import CALLS, CONTROL, S, U, bind, evaluate

__all__ = ["scalarise", "RowsLayout", "MAX_ROWS"]


SCAN_UNROLL = 4
"""`scan`s of rows are unrolled this many times (at least): XLA then keeps the rows of the
carry in place instead of copying each after every iteration."""

SHORT_SCAN = 8
"""... except scans of at most this many iterations outside every loop (a small factorisation's
loop over its columns, run once per call, not once per step as a loop inside a march's loop
body is): their copies cost nothing worth saving, while XLA compiles every unrolled copy of
their body (the lean chunk's minimum-norm cotangent, a loop of three, unrolled: about a third
of its compile time)."""


def scalarise(fun: Callable, in_axes=0, *, loops_only: bool = True) -> Callable:
    """`jax.vmap(fun, in_axes)` evaluated with each component of a small member value as its
    own (B,) row (module docstring).

    **Arguments:** `fun`, a function of arrays that `jax.vmap` could batch; `in_axes`, 0 or None
    per positional argument (as `clebsch_jax.batch`); `loops_only`: hold values as rows only
    inside loop bodies (`RowsLayout`), or, False, wherever they are small — for a program whose
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
        outs = evaluate(closed.jaxpr, closed.consts, ins, RowsLayout(B, everywhere=not loops_only))
        flat_out = [to_batch_first(o, v.aval.shape, B) for o, v in zip(outs, closed.jaxpr.outvars)]
        return jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(out_shapes), flat_out)

    return batched


FOLD_SIZE = 64
"""An unbatched operation whose operands are all known when the program is traced, with at most
this many output elements, is evaluated then (a NumPy constant): the entries of `jnp.eye`
(the tangents a forward-mode Jacobian pushes through the step), the predictor's coefficients.
Products with their zeros and ones are then not emitted at all. The evaluation is NumPy's own
where it has a rule (`numpy_fold`), not an eager JAX operation: a few hundred of those, each
dispatched and, per new shape, compiled, made much of a lean chunk's trace time."""

_NOT_FOLDED = set(CONTROL) | {"optimization_barrier"}


class RowsLayout:
    """The layout of small batched values as rows (`clebsch_jax.batching.walk.Layout`), one per
    call of a `scalarise`d function (so its state is that trace's own):

    - `depth`: how many `scan` or `while` bodies the walk is inside (a short scan outside every
      loop is not unrolled, `SHORT_SCAN`);
    - `in_loop`: whether small values are held as rows here (the last entry): inside a `scan`
      body, and everywhere with `everywhere` (`scalarise(..., loops_only=False)`); elsewhere
      every equation is the stacked layout's (a scan's trajectory outputs and what is computed
      from them are large)."""

    def __init__(self, B: int, everywhere: bool = False):
        self.B, self.depth, self.in_loop = B, 0, [everywhere]
        self.stacked = Stacked(B)

    def unbatched(self, eqn, xs) -> list:
        """Folded to NumPy constants when it can be (`FOLD_SIZE`), else emitted as it is."""
        foldable = all(math.prod(v.aval.shape) <= FOLD_SIZE for v in eqn.outvars if hasattr(v.aval, "shape"))
        if foldable and not eqn.effects and eqn.primitive.name not in _NOT_FOLDED and eqn.primitive.name not in CALLS:
            known = [concrete(x) for x in xs]
            if all(k is not None for k in known):
                outs = numpy_fold(eqn, known)
                if outs is None:
                    with jax.ensure_compile_time_eval():
                        outs = bind(eqn, [jnp.asarray(k) for k in known])
                return [np.asarray(o, dtype=v.aval.dtype) for o, v in zip(outs, eqn.outvars)]
        return bind(eqn, xs)

    def apply(self, eqn, vals) -> list:
        name = eqn.primitive.name
        if not self.in_loop[-1] and name != "scan":
            return self.on_stacked(eqn, vals)
        if name in CONTROL:
            if name == "while" and tuple(eqn.params["cond_jaxpr"].out_avals[0].shape):
                return self.on_stacked(eqn, vals)  # a predicate with member axes: stacked
            return CONTROL[name](eqn, vals, self)
        shapes_small = all(
            small(v.aval.shape)
            for v in list(eqn.invars) + list(eqn.outvars)
            if not isinstance(v, jex.Literal) and hasattr(v.aval, "shape")
        )
        rule = ROW_RULES.get(name)
        if rule is not None and (shapes_small or name == "optimization_barrier"):
            out = rule(eqn, vals, self.B)
            if out is not None:
                return out
        return self.on_stacked(eqn, vals)

    def on_stacked(self, eqn, vals) -> list:
        """The equation on stacked batch-last operands, by the stacked layout
        (`clebsch_jax.batching.rules.Stacked`: its rule, or the walk of its control flow)."""
        ins = [(U, x) if k == U else (S, stacked((k, x), v.aval.shape, self.B)) for (k, x), v in zip(vals, eqn.invars)]
        return self.stacked.apply(eqn, ins)

    # carries: in their canonical kinds (rows when small), flattened to lists of arrays
    def kinds(self, avals, flags) -> list:
        return [canonical_kind(tuple(a.shape), f) for a, f in zip(avals, flags)]

    def canon(self, vals, kinds, avals) -> list:
        return [as_kind(v, k, tuple(a.shape), self.B, a.dtype) for v, k, a in zip(vals, kinds, avals)]

    def pack(self, vals) -> list:
        return [flatten(v, self.B) for v in vals]

    def unpack(self, packed, kinds, avals) -> list:
        return [unflatten(k, tuple(a.shape), list(p)) for p, k, a in zip(packed, kinds, avals)]

    @contextlib.contextmanager
    def loop_body(self, scan: bool):
        """A loop's body: deeper by one; a scan's holds small values as rows."""
        if scan:
            self.in_loop.append(True)
        self.depth += 1
        try:
            yield
        finally:
            if scan:
                self.in_loop.pop()
            self.depth -= 1

    def scan_inputs(self, vals, invars) -> tuple:
        """Sliced along the scan axis, so stacked (or unbatched)."""
        xs = [x if k == U else stacked((k, x), v.aval.shape, self.B) for (k, x), v in zip(vals, invars)]
        return xs, [U if k == U else S for k, _ in vals]

    def unroll(self, p) -> int:
        """An unroll the program asks for is kept; otherwise at least `SCAN_UNROLL`, except for a
        short scan outside every loop (`SHORT_SCAN`)."""
        if int(p["unroll"]) > 1:
            return int(p["unroll"])
        if p["length"] <= SHORT_SCAN and self.depth == 0:
            return 1
        return min(SCAN_UNROLL, p["length"])

    def series(self, ys, kinds, avals, length) -> list:
        """A scan's stacked outputs, (n, …member shape, B), from their rows' series (each (n, B)):
        each row of an output its own series, which XLA writes in place."""
        out = []
        for kind, arrays, a in zip(kinds, ys, avals):
            if kind == R:
                series = jnp.stack(arrays, axis=1) if arrays else jnp.zeros((length, 0, self.B))
                out.append((S, series.reshape((length,) + tuple(a.shape) + (self.B,))))
            else:
                out.append((kind, arrays[0]))
        return out

    def predicate(self, val):
        return lift(entry(val, (), (), self.B, jnp.bool_), self.B, jnp.bool_)

    def select(self, go, new, old, pred_shape, pred_batched):
        return lax.select(go if new.ndim == 1 else lax.broadcast_in_dim(go, new.shape, (new.ndim - 1,)), new, old)

    def index(self, val):
        idx = lift(entry(val, (), (), self.B, None), self.B)
        return idx if idx.dtype == jnp.bool_ else idx.astype(jnp.int32)

    def choose(self, index, results, kinds, avals) -> list:
        outs = []
        for k in range(len(kinds)):
            arrays = []
            for parts in zip(*[r[k] for r in results]):
                sel = index if parts[0].ndim == 1 else lax.broadcast_in_dim(index, parts[0].shape, (parts[0].ndim - 1,))
                arrays.append(lax.select_n(sel, *parts))
            outs.append(arrays)
        return self.unpack(outs, kinds, avals)
