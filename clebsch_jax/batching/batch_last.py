r"""`batch`: `jax.vmap` for many small independent systems on the CPU, with the batch axis last.

`jax.vmap` puts the batch axis first: a batch of B rigid bodies holds its velocities as a
(B, 3) array, and every component a step touches, ξ₁ say, is a strided column of it. On the
CPU XLA then vectorises across the three components of one body, not across bodies, and a
step of a few hundred flops runs far below the machine's speed; the same straight-line step
written with the bodies along the last axis runs much faster.

`batch(fun)` has `jax.vmap`'s meaning (in_axes 0 or None, out_axes 0) but evaluates `fun`
differently: it traces `fun` once for one member (`jax.make_jaxpr`) and evaluates that program
with every batched value stored *batch-last*, shape (…member shape, B): each component of a
member is a contiguous row of B numbers, which XLA vectorises across members. Each primitive
is applied by a rule (`_RULES`) that knows where the batch axis is — elementwise operations,
broadcasts, reshapes, slices, reductions and small `dot_general`s keep it last at no cost;
`scan`, `while` and `cond` are evaluated with batch-last bodies (a `while` whose predicate
differs between members runs until the last member stops, the others held by a select, as
under `jax.vmap`); calls (`jit`, `custom_jvp_call`, …) are entered. Any other primitive (a
gather, a callback, a large dot) falls back on `jax.vmap` of that one primitive with the batch
axis moved last around it: slower, never wrong.

The batch is also cut into chunks of `chunk` members, marched to the end one chunk after the
other (`jax.lax.map`): the arrays of one chunk stay in cache, so the rate falls less as B
grows. (The measurements behind the layout and the chunks: `benchmarks/README.md`,
"Measurements behind the engine's choices".)

The result is `jax.vmap`'s up to round-off: the same operations on the same numbers; XLA may
fuse them differently for another layout. Each member's result does not depend on the other
members (padding members of the last chunk are copies of the last member, dropped).
"""

from __future__ import annotations

import functools
import math
from typing import Callable

import jax
import jax.extend.core as jex
import jax.numpy as jnp
import numpy as np
from jax import lax

from ..core.validation import check_memory, is_traced
from ..march.integrate import check_member, recording_calls

__all__ = ["batch"]

DEFAULT_CHUNK = 1024
"""Members per chunk: the working set of the built-in models' steps stays in the L2 cache."""

SMALL_DOT = 4096
"""A `dot_general` whose output times contraction size is at most this many products is
evaluated as a broadcast multiply and a sum (batch-last, fused); larger ones fall back on
`jax.vmap`."""


def batch(fun: Callable, in_axes=0, *, chunk: int | None = DEFAULT_CHUNK) -> Callable:
    r"""`jax.vmap(fun, in_axes)` evaluated batch-last and in chunks: the fast way to run many
    small independent systems (a sweep of rigid bodies, a batch of vortex clusters) on the CPU.

    ```python
    march = jax.jit(cj.batch(lambda Q0, xi0: cj.integrate(body, Q0, xi0, dt=0.05, n_steps=200,
                                                          throw=False)))
    sol = march(Q0s, xi0s)    # the Solution jax.vmap would give, batch axis first
    ```

    **Arguments:**

    - `fun`: a function of arrays (pytrees of arrays) that `jax.vmap` could batch.
    - `in_axes`: 0 (batched along the leading axis) or None (shared), for all positional
      arguments or as a tuple with one entry per positional argument (which applies to every
      array in that argument).
    - `chunk`: members per chunk (default `DEFAULT_CHUNK`), or None for one chunk. Chunks run
      one after the other; the last is padded with copies of the last member. A loop in
      `fun` (Newton's) runs, in each chunk, until the chunk's slowest member stops: members
      that need very different numbers of iterations (clusters of point vortices, where a
      few members need many times the mean) run faster in small chunks (e.g. 64), while
      uniform ones (rigid bodies) prefer large chunks, where each operation's fixed cost is
      shared by more members (the runs: `benchmarks/README.md`, `throughput.py`).

    **Returns:** a function with `jax.vmap(fun, in_axes)`'s signature and outputs (every output
    batched along axis 0).

    Checks, before anything is evaluated or compiled: the outputs of all members, estimated
    from one member's trace, must fit in memory (twice: batch-last and in `jax.vmap`'s layout;
    a `ValueError` naming `batch` gives the estimate). Called on concrete arrays (not inside
    `jax.jit`), each `clebsch_jax.integrate` call in `fun` is also checked on the first
    member's values as `integrate` checks a plain call (`clebsch_jax.march.integrate.
    check_member`: the model by autodiff, the configuration, the first step on the manifold),
    which under tracing it cannot do itself; not when its arguments are computed by a loop or
    inside a transformation of `fun`'s own.

    Transformations: jit-compatible (trace it inside `jax.jit`; it is not jitted itself).
    Not for differentiation: the program is evaluated primitive by primitive, so custom
    derivative rules (`custom_jvp`, the implicit differentiation of `integrate`'s Newton
    solves) are not seen by an outer `jax.grad`, which then meets the Newton `while_loop`s
    themselves and raises JAX's error for reverse mode through them; differentiate with
    `jax.vmap` instead. Not batchable again by `jax.vmap` in a useful way (flatten the batch
    instead).
    """
    if chunk is not None and (not isinstance(chunk, int) or isinstance(chunk, bool) or chunk < 1):
        raise ValueError(f"chunk: expected a whole number >= 1 or None, got {chunk!r}.")

    @functools.wraps(fun)
    def batched(*args):
        leaves, tree = jax.tree_util.tree_flatten(args)
        axes = _flat_axes(in_axes, args)
        B, leaves, member = _members(leaves, axes)
        if B == 0:  # an empty batch: jax.vmap's empty outputs (no chunk to run)
            return jax.vmap(fun, in_axes=in_axes)(*args)
        flags = [a == 0 for a in axes]

        def flat_fun(*flat):
            return fun(*jax.tree_util.tree_unflatten(tree, flat))

        closed, out_shapes, calls = _trace(flat_fun, member, record=not any(is_traced(x) for x in leaves))
        out_tree = jax.tree_util.tree_structure(out_shapes)
        n_out = out_tree.num_leaves
        c = B if chunk is None else min(chunk, B)
        n_chunks = -(-B // c)
        pad = n_chunks * c - B
        _check_outputs(out_shapes, B, pad)
        if calls:
            _check_first_member(closed, calls, n_out, leaves, flags, B)

        def run(chunk_leaves):  # batched leaves batch-last, (…, c)
            outs, out_flags = _eval_closed(closed, chunk_leaves, flags, c)
            return [_to_batched(o, f, c) for o, f in zip(outs[:n_out], out_flags[:n_out])]

        def split(x, a):  # (B, …) -> (n_chunks, …, c)
            if a != 0:
                return x
            if pad:
                x = jnp.concatenate([x, jnp.broadcast_to(x[-1:], (pad,) + x.shape[1:])])
            return jnp.moveaxis(x.reshape((n_chunks, c) + x.shape[1:]), 1, -1)

        chunked = [split(x, a) for x, a in zip(leaves, axes)]
        if n_chunks == 1:
            outs = [o[None] for o in run([x[0] if f else x for x, f in zip(chunked, flags)])]
        else:
            dyn = [x for x, f in zip(chunked, flags) if f]

            def one(dyn_chunk):
                it = iter(dyn_chunk)
                return run([next(it) if f else x for x, f in zip(chunked, flags)])

            outs = lax.map(one, dyn)
        outs = [jnp.moveaxis(o, -1, 1).reshape((n_chunks * c,) + o.shape[1:-1])[:B] for o in outs]
        return jax.tree_util.tree_unflatten(out_tree, outs)

    return batched


def _trace(flat_fun, member, record: bool):
    """`jax.make_jaxpr` of one member's `flat_fun`: (closed jaxpr, output shapes, recorded
    `integrate` calls). With `record` (the batch's values are concrete), the traced `integrate`
    calls inside are recorded (`clebsch_jax.march.integrate.recording_calls`) and their array
    arguments added as extra outputs of the jaxpr, after the function's own, so that they can
    be evaluated for the first member (`_check_first_member`). Calls whose arguments belong to
    a trace inside the function (its own `jit`, `vmap`, `scan`) cannot be outputs: the function
    is then traced again without recording (and those calls are not checked)."""
    if record:
        found = []

        def probe(*flat):
            with recording_calls() as calls:
                out = flat_fun(*flat)
            found.extend(calls)
            return out, [[x for x in jax.tree_util.tree_leaves(call.args) if _is_value(x)] for call in calls]

        try:
            closed, (out_shapes, _) = jax.make_jaxpr(probe, return_shape=True)(*member)
            return closed, out_shapes, found
        except jax.errors.UnexpectedTracerError:
            pass
    closed, out_shapes = jax.make_jaxpr(flat_fun, return_shape=True)(*member)
    return closed, out_shapes, []


def _is_value(x) -> bool:
    """Whether a leaf of `integrate`'s arguments is a value (an array, a tracer, a number),
    which the trace can output, and not a function or other static object."""
    return is_traced(x) or isinstance(x, (jax.Array, np.ndarray, np.generic, int, float, complex))


RESULT_COPIES = 2
"""`_check_outputs` counts the batch's outputs this many times: they are made batch-last, then
moved to `jax.vmap`'s layout (a copy) — a lower bound of what the program needs, whose own
intermediate arrays (a march's stacked steps) come on top."""


def _check_outputs(out_shapes, B: int, pad: int) -> None:
    """Refuse, before compiling, a batch whose outputs alone would not fit in memory
    (`clebsch_jax.core.validation.check_memory`, `integrate`'s guard), e.g. the `Solution`s of
    10⁴ members of thousands of steps each (`pad`: the copies that fill the last chunk): the
    estimate and the ways out."""
    per = sum(int(np.prod(x.shape)) * np.dtype(x.dtype).itemsize for x in jax.tree_util.tree_leaves(out_shapes))
    check_memory(
        "batch",
        f"{B} members",
        RESULT_COPIES * per * (B + pad),
        "Run fewer members per call, return less per member (e.g. sol.Q[-1] or a reduction instead of the "
        "whole Solution), or use clebsch_jax.sweep, which runs members in batches and keeps per-member "
        "reductions and every k-th node (save_every=k) instead of trajectories.",
        detail=f" for the outputs ({per} bytes per member, {RESULT_COPIES} copies: batch-last and batch-first)",
    )


MEMBER_CHECK_MAX_EQNS = 200
"""`_check_first_member` evaluates the operations that compute `integrate`'s arguments from the
batch's for a member, one by one, when there are at most this many and none is a loop:
arguments computed by a long program (another march's result) are not checked."""

MEMBER_CHECK_TRIES = 8
"""`_check_first_member` checks the first member whose arguments are valid (finite, dt > 0)
among the first this many members."""


def _check_first_member(closed, calls: list, n_out: int, leaves: list, flags: list, B: int) -> None:
    """`integrate`'s checks that need values (`clebsch_jax.march.integrate.check_member`: the model
    by autodiff, the configuration, Q0 in the velocity map's group, the first step on the
    manifold) of each recorded `integrate` call, for the batch's first member whose arguments are
    valid (a member with non-finite values or dt <= 0 reports `Status.INVALID_INPUT` in the
    batch, as under `jax.vmap`), before the batch is compiled: its arguments are the jaxpr's
    extra outputs (after the `n_out` outputs of the function), evaluated for that member."""
    jaxpr = closed.jaxpr
    extras = jaxpr.outvars[n_out:]
    needed = {v for v in extras if not isinstance(v, jex.Literal)}
    kept = []
    for eqn in reversed(jaxpr.eqns):
        if any(v in needed for v in eqn.outvars if not isinstance(v, jex.DropVar)):
            kept.append(eqn)
            needed.update(v for v in eqn.invars if not isinstance(v, jex.Literal))
    if len(kept) > MEMBER_CHECK_MAX_EQNS or any(eqn.primitive.name in ("while", "scan") for eqn in kept):
        return
    kept.reverse()
    host = [np.asarray(x) if f else x for x, f in zip(leaves, flags)]
    for m in range(min(B, MEMBER_CHECK_TRIES)):
        env = dict(zip(jaxpr.constvars, closed.consts))
        env.update(zip(jaxpr.invars, [x[m] if f else x for x, f in zip(host, flags)]))
        for eqn in kept:
            vals = [v.val if isinstance(v, jex.Literal) else env[v] for v in eqn.invars]
            env.update(zip(eqn.outvars, _bind(eqn, vals)))
        values = [np.asarray(v.val if isinstance(v, jex.Literal) else env[v]) for v in extras]
        if all(np.all(np.isfinite(v)) for v in values if np.issubdtype(v.dtype, np.inexact)):
            break
    else:
        return
    values = iter(values)
    for call in calls:
        flat, tree = jax.tree_util.tree_flatten(call.args)
        flat = [next(values) if _is_value(x) else x for x in flat]  # functions stay as they are
        system, Q0, xi0, P0, dt, t0 = jax.tree_util.tree_unflatten(tree, flat)
        if not np.all(np.asarray(dt) > 0):
            continue  # reported by the batch (INVALID_INPUT), as under jax.vmap
        try:
            check_member(system, Q0, xi0, dt=dt, P0=P0, t0=t0, **call.options)
        except (ValueError, TypeError) as err:
            raise type(err)(f"batch: member {m} is rejected by integrate's checks: {err}") from err


def _members(leaves, axes):
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


def _flat_axes(in_axes, args):
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


# --------------------------------------------------------------------------------------------
# The interpreter. A value is (array, batched); a batched array has shape member_shape + (B,).


def _to_batched(x, batched, B):
    if batched:
        return x
    x = jnp.asarray(x)
    return lax.broadcast_in_dim(x, x.shape + (B,), tuple(range(x.ndim)))


def _match(values, flags, wants, B):
    """`values` (batched where `flags`) made batched wherever `wants` says."""
    return [_to_batched(x, f, B) if w else x for x, f, w in zip(values, flags, wants)]


def _eval_closed(closed, args, flags, B):
    return _eval(closed.jaxpr, closed.consts, args, flags, B)


def _eval(jaxpr, consts, args, flags, B):
    env = {}

    def read(v):
        if isinstance(v, jex.Literal):
            return v.val, False
        return env[v]

    for v, c in zip(jaxpr.constvars, consts):
        env[v] = (c, False)
    for v, a, f in zip(jaxpr.invars, args, flags):
        env[v] = (a, bool(f))
    for eqn in jaxpr.eqns:
        vals, bs = zip(*(read(v) for v in eqn.invars)) if eqn.invars else ((), ())
        prim = eqn.primitive
        if not any(bs):
            outs = _bind(eqn, vals)
            out_flags = [False] * len(outs)
        else:
            rule = _RULES.get(prim.name)
            if rule is None:
                outs, out_flags = _fallback(eqn, vals, bs, B)
            else:
                outs, out_flags = rule(eqn, list(vals), list(bs), B)
        for v, o, f in zip(eqn.outvars, outs, out_flags):
            if not isinstance(v, jex.DropVar):
                env[v] = (o, f)
    results = [read(v) for v in jaxpr.outvars]
    return [r[0] for r in results], [r[1] for r in results]


def _fallback(eqn, vals, bs, B):
    """`jax.vmap` of the one primitive, the batch axis moved last around it."""

    def f(*xs):
        return _bind(eqn, xs)

    outs = jax.vmap(f, in_axes=[-1 if b else None for b in bs], out_axes=-1, axis_size=B)(*vals)
    return outs, [True] * len(outs)


def _bind(eqn, vals, **changes):
    """Apply the equation's primitive to `vals`, with some parameters changed."""
    params = eqn.primitive.get_bind_params(eqn.params)
    subfuns = ()
    if isinstance(params, tuple):  # JAX < 0.8 returns (subfuns, params)
        subfuns, params = params
    with eqn.ctx.manager:
        out = eqn.primitive.bind(*subfuns, *vals, **{**params, **changes})
    return list(out) if eqn.primitive.multiple_results else [out]


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
    return _bind(eqn, args), [True] * len(eqn.outvars)


def _same_params(eqn, vals, bs, B):
    """Operations whose parameters name member axes only (reductions, squeeze, split,
    cumulative sums, concatenate, stack): with every operand batched the batch axis, last, is
    untouched."""
    return _bind(eqn, _match(vals, bs, [True] * len(vals), B)), [True] * len(eqn.outvars)


def _as_is(eqn, vals, bs, B):
    """`optimization_barrier`: applied to the operands as they are, all made batched (as
    `_flags` predicts for an operation with a batched operand)."""
    return _bind(eqn, _match(vals, bs, [True] * len(vals), B)), [True] * len(vals)


def _broadcast_in_dim(eqn, vals, bs, B):
    x, *dyn = vals
    if dyn or not bs[0]:
        return _fallback(eqn, vals, bs, B)
    shape = tuple(eqn.params["shape"]) + (B,)
    dims = tuple(eqn.params["broadcast_dimensions"]) + (len(shape) - 1,)
    return _bind(eqn, [x], shape=shape, broadcast_dimensions=dims), [True]


def _reshape(eqn, vals, bs, B):
    if len(vals) != 1 or eqn.params.get("dimensions") is not None:
        return _fallback(eqn, vals, bs, B)
    return _bind(eqn, vals, new_sizes=tuple(eqn.params["new_sizes"]) + (B,)), [True]


def _slice(eqn, vals, bs, B):
    p = eqn.params
    strides = None if p["strides"] is None else tuple(p["strides"]) + (1,)
    return _bind(
        eqn,
        vals,
        start_indices=tuple(p["start_indices"]) + (0,),
        limit_indices=tuple(p["limit_indices"]) + (B,),
        strides=strides,
    ), [True]


def _pad(eqn, vals, bs, B):
    if bs[1]:
        return _fallback(eqn, vals, bs, B)
    return _bind(eqn, vals, padding_config=tuple(eqn.params["padding_config"]) + ((0, 0, 0),)), [True]


def _transpose(eqn, vals, bs, B):
    perm = tuple(eqn.params["permutation"])
    return _bind(eqn, vals, permutation=perm + (len(perm),)), [True]


def _dot_general(eqn, vals, bs, B):
    """Small contractions as a broadcast multiply and a sum over the contracted axes."""
    (lc, rc), (lb, rb) = eqn.params["dimension_numbers"]
    ls, rs = (tuple(v.aval.shape) for v in eqn.invars)
    out_shape = tuple(eqn.outvars[0].aval.shape)
    contracted = math.prod(ls[d] for d in lc)
    if math.prod(out_shape) * contracted > SMALL_DOT or not jnp.issubdtype(eqn.outvars[0].aval.dtype, jnp.inexact):
        return _fallback(eqn, vals, bs, B)
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


# Calls: evaluate the called program with the same interpreter.


def _call(key):
    def rule(eqn, vals, bs, B):
        inner = eqn.params[key]
        if isinstance(inner, jex.ClosedJaxpr):
            return _eval(inner.jaxpr, inner.consts, vals, bs, B)
        return _eval(inner, (), vals, bs, B)

    return rule


# Control flow. `_flags` predicts which outputs of a program come out batched (the same rules
# as the interpreter), so loop carries can be made batched before the loop.


def _flags(closed, in_flags) -> list:
    jaxpr = closed.jaxpr if isinstance(closed, jex.ClosedJaxpr) else closed
    env = {v: bool(f) for v, f in zip(jaxpr.invars, in_flags)}
    read = lambda v: False if isinstance(v, jex.Literal) else env.get(v, False)
    for eqn in jaxpr.eqns:
        bs = [read(v) for v in eqn.invars]
        name = eqn.primitive.name
        if name in _CALLS:
            out = _flags(eqn.params[_CALLS[name]], bs)
        elif not any(bs):
            out = [False] * len(eqn.outvars)
        elif name == "while":
            out = _while_carry_flags(eqn.params, bs)[0]
        elif name == "scan":
            out = _scan_carry_flags(eqn.params, bs)[1]
        elif name == "cond":
            out = _cond_flags(eqn.params, bs)
        else:
            out = [True] * len(eqn.outvars)
        for v, f in zip(eqn.outvars, out):
            env[v] = f
    return [read(v) for v in jaxpr.outvars]


def _stable_carry(body, consts, carry, xs=()):
    """The batched flags of a loop's carries: a carry is batched once one pass of `body`
    (inputs: consts, carries, xs; outputs: carries first) makes it so. Returns (carry flags,
    the body's output flags)."""
    while True:
        out = _flags(body, list(consts) + carry + list(xs))
        new = [a or b for a, b in zip(carry, out)]
        if new == carry:
            return carry, out
        carry = new


def _while_carry_flags(p, bs):
    nc, nb = p["cond_nconsts"], p["body_nconsts"]
    carry, _ = _stable_carry(p["body_jaxpr"], bs[nc : nc + nb], list(bs[nc + nb :]))
    pred = _flags(p["cond_jaxpr"], list(bs[:nc]) + carry)[0]
    if pred:
        carry = [True] * len(carry)
    return carry, pred


def _scan_carry_flags(p, bs):
    nc, nk = p["num_consts"], p["num_carry"]
    carry, out = _stable_carry(p["jaxpr"], bs[:nc], list(bs[nc : nc + nk]), bs[nc + nk :])
    return carry, carry + out[nk:]


def _cond_flags(p, bs):
    if bs[0]:
        return [True] * len(p["branches"][0].jaxpr.outvars)
    per_branch = [_flags(br, bs[1:]) for br in p["branches"]]
    return [any(fs) for fs in zip(*per_branch)]


def _while(eqn, vals, bs, B):
    p = eqn.params
    nc, nb = p["cond_nconsts"], p["body_nconsts"]
    carry_flags, pred_batched = _while_carry_flags(p, bs)
    cc, bc = vals[:nc], vals[nc : nc + nb]
    ccf, bcf = bs[:nc], bs[nc : nc + nb]
    init = _match(vals[nc + nb :], bs[nc + nb :], carry_flags, B)
    cond_j, body_j = p["cond_jaxpr"], p["body_jaxpr"]

    def pred(carry):
        return _eval_closed(cond_j, list(cc) + list(carry), list(ccf) + carry_flags, B)[0][0]

    def body(carry):
        outs, fs = _eval_closed(body_j, list(bc) + list(carry), list(bcf) + carry_flags, B)
        return _match(outs, fs, carry_flags, B)

    # A `while` batched by `jax.vmap` inside `fun` has a predicate of shape S (its own batch)
    # and carries with leading axes S: it runs while any entry is true and updates the
    # entries whose predicate is true. Ours adds the batch axis, last, to the same rule.
    pred_shape = tuple(cond_j.out_avals[0].shape)
    if not pred_batched and not pred_shape:
        out = lax.while_loop(pred, body, init)
    else:

        def select(go, new, old):
            dims = tuple(range(len(pred_shape))) + ((new.ndim - 1,) if pred_batched else ())
            return lax.select(lax.broadcast_in_dim(go, new.shape, dims), new, old)

        def masked_body(carry):
            go = pred(carry)
            return [select(go, n, o) for n, o in zip(body(carry), carry)]

        out = lax.while_loop(lambda c: jnp.any(pred(c)), masked_body, init)
    return list(out), carry_flags


def _scan(eqn, vals, bs, B):
    p = eqn.params
    nc, nk = p["num_consts"], p["num_carry"]
    carry_flags, out_flags = _scan_carry_flags(p, bs)
    consts, cf = vals[:nc], bs[:nc]
    init = _match(vals[nc : nc + nk], bs[nc : nc + nk], carry_flags, B)
    xs, xf = vals[nc + nk :], bs[nc + nk :]
    ys_flags = out_flags[nk:]

    def body(carry, x):
        outs, fs = _eval_closed(p["jaxpr"], list(consts) + list(carry) + list(x), list(cf) + carry_flags + list(xf), B)
        return _match(outs[:nk], fs[:nk], carry_flags, B), _match(outs[nk:], fs[nk:], ys_flags, B)

    carry, ys = lax.scan(body, init, list(xs), length=p["length"], reverse=p["reverse"], unroll=p["unroll"])
    return list(carry) + list(ys), out_flags


def _cond(eqn, vals, bs, B):
    branches = eqn.params["branches"]
    index, ops, opf = vals[0], vals[1:], bs[1:]
    out_flags = _cond_flags(eqn.params, bs)

    def branch(br):
        def run(*xs):
            outs, fs = _eval_closed(br, list(xs), list(opf), B)
            return _match(outs, fs, out_flags, B)

        return run

    if not bs[0]:
        return list(lax.switch(index, [branch(br) for br in branches], *ops)), out_flags
    results = [branch(br)(*ops) for br in branches]
    outs = []
    for k in range(len(out_flags)):
        cases = [r[k] for r in results]
        idx = lax.broadcast_in_dim(index, cases[0].shape, (cases[0].ndim - 1,))
        outs.append(lax.select_n(idx if idx.dtype == jnp.bool_ else idx.astype(jnp.int32), *cases))
    return outs, out_flags


_ELEMENTWISE = """
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

_CALLS = {
    "jit": "jaxpr",
    "pjit": "jaxpr",
    "closed_call": "call_jaxpr",
    "core_call": "call_jaxpr",
    "custom_jvp_call": "call_jaxpr",
    "custom_vjp_call": "call_jaxpr",
    "remat": "jaxpr",
    "checkpoint": "jaxpr",
}

_RULES = {
    **{name: _elementwise for name in _ELEMENTWISE},
    **{name: _same_params for name in _SAME_PARAMS},
    **{name: _call(key) for name, key in _CALLS.items()},
    "broadcast_in_dim": _broadcast_in_dim,
    "reshape": _reshape,
    "slice": _slice,
    "pad": _pad,
    "transpose": _transpose,
    "dot_general": _dot_general,
    "concatenate": _same_params,
    "optimization_barrier": _as_is,
    "stack": _same_params,
    "while": _while,
    "scan": _scan,
    "cond": _cond,
}
