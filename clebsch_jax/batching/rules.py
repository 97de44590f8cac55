r"""The batch-last interpreter: a program of one member evaluated for B members at once.

A value is (array, batched); a batched array has shape member_shape + (B,), the batch axis
last. `evaluate` walks a jaxpr and applies each primitive by its rule (`RULES`): elementwise
operations, broadcasts, reshapes, slices, reductions and small `dot_general`s keep the batch
axis last at no cost; `scan`, `while` and `cond` are evaluated with batch-last bodies (a
`while` whose predicate differs between members runs until the last member stops, the others
held by a select, as under `jax.vmap`); calls (`jit`, `custom_jvp_call`, …) are entered. Any
other primitive falls back on `jax.vmap` of that one primitive with the batch axis moved last
around it (`fallback`). `clebsch_jax.batch` (`batch_last.py`) and the scalarising evaluator
(`scalarise.py`, for what it does not hold as rows) share these rules.
"""

from __future__ import annotations

import math

import jax
import jax.extend.core as jex
import jax.numpy as jnp
from jax import lax

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


def eval_closed(closed, args, flags, B):
    return evaluate(closed.jaxpr, closed.consts, args, flags, B)


def evaluate(jaxpr, consts, args, flags, B):
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
            outs = bind(eqn, vals)
            out_flags = [False] * len(outs)
        else:
            rule = RULES.get(prim.name)
            if rule is None:
                outs, out_flags = fallback(eqn, vals, bs, B)
            else:
                outs, out_flags = rule(eqn, list(vals), list(bs), B)
        for v, o, f in zip(eqn.outvars, outs, out_flags):
            if not isinstance(v, jex.DropVar):
                env[v] = (o, f)
    results = [read(v) for v in jaxpr.outvars]
    return [r[0] for r in results], [r[1] for r in results]


def fallback(eqn, vals, bs, B):
    """`jax.vmap` of the one primitive, the batch axis moved last around it."""

    def f(*xs):
        return bind(eqn, xs)

    outs = jax.vmap(f, in_axes=[-1 if b else None for b in bs], out_axes=-1, axis_size=B)(*vals)
    return outs, [True] * len(outs)


def bind(eqn, vals, **changes):
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


# Calls: evaluate the called program with the same interpreter.


def _call(key):
    def rule(eqn, vals, bs, B):
        inner = eqn.params[key]
        if isinstance(inner, jex.ClosedJaxpr):
            return evaluate(inner.jaxpr, inner.consts, vals, bs, B)
        return evaluate(inner, (), vals, bs, B)

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
        if name in CALLS:
            out = _flags(eqn.params[CALLS[name]], bs)
        elif not any(bs):
            out = [False] * len(eqn.outvars)
        elif name == "while":
            out = while_carry_flags(eqn.params, bs)[0]
        elif name == "scan":
            out = scan_carry_flags(eqn.params, bs)[1]
        elif name == "cond":
            out = cond_flags(eqn.params, bs)
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


def while_carry_flags(p, bs):
    nc, nb = p["cond_nconsts"], p["body_nconsts"]
    carry, _ = _stable_carry(p["body_jaxpr"], bs[nc : nc + nb], list(bs[nc + nb :]))
    pred = _flags(p["cond_jaxpr"], list(bs[:nc]) + carry)[0]
    if pred:
        carry = [True] * len(carry)
    return carry, pred


def scan_carry_flags(p, bs):
    nc, nk = p["num_consts"], p["num_carry"]
    carry, out = _stable_carry(p["jaxpr"], bs[:nc], list(bs[nc : nc + nk]), bs[nc + nk :])
    return carry, carry + out[nk:]


def cond_flags(p, bs):
    if bs[0]:
        return [True] * len(p["branches"][0].jaxpr.outvars)
    per_branch = [_flags(br, bs[1:]) for br in p["branches"]]
    return [any(fs) for fs in zip(*per_branch)]


def _while(eqn, vals, bs, B):
    p = eqn.params
    nc, nb = p["cond_nconsts"], p["body_nconsts"]
    carry_flags, pred_batched = while_carry_flags(p, bs)
    cc, bc = vals[:nc], vals[nc : nc + nb]
    ccf, bcf = bs[:nc], bs[nc : nc + nb]
    init = _match(vals[nc + nb :], bs[nc + nb :], carry_flags, B)
    cond_j, body_j = p["cond_jaxpr"], p["body_jaxpr"]

    def pred(carry):
        return eval_closed(cond_j, list(cc) + list(carry), list(ccf) + carry_flags, B)[0][0]

    def body(carry):
        outs, fs = eval_closed(body_j, list(bc) + list(carry), list(bcf) + carry_flags, B)
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
    carry_flags, out_flags = scan_carry_flags(p, bs)
    consts, cf = vals[:nc], bs[:nc]
    init = _match(vals[nc : nc + nk], bs[nc : nc + nk], carry_flags, B)
    xs, xf = vals[nc + nk :], bs[nc + nk :]
    ys_flags = out_flags[nk:]

    def body(carry, x):
        outs, fs = eval_closed(p["jaxpr"], list(consts) + list(carry) + list(x), list(cf) + carry_flags + list(xf), B)
        return _match(outs[:nk], fs[:nk], carry_flags, B), _match(outs[nk:], fs[nk:], ys_flags, B)

    carry, ys = lax.scan(body, init, list(xs), length=p["length"], reverse=p["reverse"], unroll=p["unroll"])
    return list(carry) + list(ys), out_flags


def _cond(eqn, vals, bs, B):
    branches = eqn.params["branches"]
    index, ops, opf = vals[0], vals[1:], bs[1:]
    out_flags = cond_flags(eqn.params, bs)

    def branch(br):
        def run(*xs):
            outs, fs = eval_closed(br, list(xs), list(opf), B)
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

CALLS = {
    "jit": "jaxpr",
    "pjit": "jaxpr",
    "closed_call": "call_jaxpr",
    "core_call": "call_jaxpr",
    "custom_jvp_call": "call_jaxpr",
    "custom_vjp_call": "call_jaxpr",
    "remat": "jaxpr",
    "checkpoint": "jaxpr",
}

RULES = {
    **{name: _elementwise for name in ELEMENTWISE},
    **{name: _same_params for name in _SAME_PARAMS},
    **{name: _call(key) for name, key in CALLS.items()},
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
