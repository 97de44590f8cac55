r"""The one jaxpr interpreter of `batching/`: a program of one member evaluated for B members,
with the layout of the batched values as a parameter.

`evaluate(jaxpr, consts, args, layout)` walks the equations of a jaxpr of one member. A value
is `(kind, x)`: `U` unbatched (an array of the member's shape, the same for every member),
`S` stacked batch-last (member shape + (B,)), or a kind of the layout's own (the rows of
`clebsch_jax.batching.rows`: one (B,) array per component). The walk is written once:

- an equation whose operands are all unbatched is the layout's `unbatched` (bound as it is,
  or folded when its operands are known);
- calls (`jit`, `custom_jvp_call`, `custom_vjp_call`, …: `CALLS`) are entered, their program
  walked with the same layout;
- `scan`, `while` and `cond` (`CONTROL`) are walked here, their carries in the kinds the layout
  gives them (`Layout.kinds`), flattened to lists of arrays for JAX's loops (`Layout.pack`,
  `Layout.unpack`); a `while` whose predicate differs between members runs until the last
  member stops, the others held by a select, and a `cond` with a batched index runs every
  branch and selects, as under `jax.vmap`;
- any other equation is the layout's `apply`, which applies its rule for the primitive (and may
  hand control flow to the walk, or an equation to another layout).

Two layouts stand behind it: `clebsch_jax.batching.rules.Stacked` (every batched value
batch-last: `cj.batch`) and `clebsch_jax.batching.scalarise.RowsLayout` (small values as rows,
the others stacked: the sweep's fast and lean chunks). Which outputs of a program come out
batched is predicted before a loop (`scan_carry_flags`, `while_carry_flags`, `cond_flags`), so
that its carries are made batched before it.
"""

from __future__ import annotations

from typing import Protocol

import jax.extend.core as jex
import jax.numpy as jnp
from jax import lax

__all__ = [
    "U",
    "S",
    "CALLS",
    "CONTROL",
    "Layout",
    "evaluate",
    "evaluate_closed",
    "call",
    "bind",
    "scan_carry_flags",
    "while_carry_flags",
    "cond_flags",
]

U, S = "u", "s"
"""The kinds of values every layout knows: unbatched, and stacked batch-last."""

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
"""The call primitives the walk enters, and the parameter that holds the called program."""


class Layout(Protocol):
    """How the batched values of one walk are held: the rules of the primitives and of the
    carries of control flow (`evaluate`)."""

    B: int

    def unbatched(self, eqn, xs) -> list:
        """The outputs (arrays) of an equation whose operands `xs` are all unbatched."""

    def apply(self, eqn, vals) -> list:
        """The output values of an equation (not a call) with a batched operand."""

    def kinds(self, avals, flags) -> list:
        """The kinds of loop carries of these avals, batched where `flags` say."""

    def canon(self, vals, kinds, avals) -> list:
        """`vals` in the `kinds` (an unbatched value made batched where its kind says)."""

    def pack(self, vals) -> list:
        """Each value as a list of arrays (a loop's carry)."""

    def unpack(self, packed, kinds, avals) -> list:
        """`pack`'s inverse."""

    def loop_body(self, scan: bool):
        """A context in which the body of a loop is walked (`scan`: a scan's, else a while's)."""

    def scan_inputs(self, vals, invars) -> tuple:
        """(arrays sliced by a scan, the kind of each slice)."""

    def unroll(self, params) -> int:
        """The unroll of a scan of these parameters."""

    def series(self, ys, kinds, avals, length) -> list:
        """A scan's stacked outputs from what its body returned (`pack`ed)."""

    def predicate(self, val):
        """A `while`'s batched predicate as an array whose last axis is the batch."""

    def select(self, go, new, old, pred_shape, pred_batched):
        """`new` where the predicate `go` holds, else `old` (a masked `while` body)."""

    def index(self, val):
        """A `cond`'s batched index, as `choose` takes it."""

    def choose(self, index, results, kinds, avals) -> list:
        """The outputs of a `cond` with a batched `index` (`Layout.index`) from every branch's
        (`pack`ed)."""


def evaluate(jaxpr, consts, args, layout) -> list:
    """The output values of `jaxpr` (its constants `consts`, unbatched) on the values `args`."""
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
            outs = [(U, o) for o in layout.unbatched(eqn, [x for _, x in vals])]
        elif eqn.primitive.name in CALLS:
            outs = call(eqn, vals, layout)
        else:
            outs = layout.apply(eqn, vals)
        for v, o in zip(eqn.outvars, outs):
            if not isinstance(v, jex.DropVar):
                env[v] = o
    return [read(v) for v in jaxpr.outvars]


def evaluate_closed(closed, args, layout) -> list:
    """`evaluate` of a program held as a `ClosedJaxpr` or an open `Jaxpr`."""
    if isinstance(closed, jex.ClosedJaxpr):
        return evaluate(closed.jaxpr, closed.consts, args, layout)
    return evaluate(closed, (), args, layout)


def bind(eqn, vals, **changes):
    """Apply the equation's primitive to `vals`, with some parameters changed."""
    params = eqn.primitive.get_bind_params(eqn.params)
    subfuns = ()
    if isinstance(params, tuple):  # JAX < 0.8 returns (subfuns, params)
        subfuns, params = params
    with eqn.ctx.manager:
        out = eqn.primitive.bind(*subfuns, *vals, **{**params, **changes})
    return list(out) if eqn.primitive.multiple_results else [out]


def call(eqn, vals, layout) -> list:
    """A call entered: its program walked with the same layout."""
    return evaluate_closed(eqn.params[CALLS[eqn.primitive.name]], vals, layout)


# --------------------------------------------------------------------------------------------
# Which outputs come out batched: the same rules as the walk, without evaluating anything.


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
    """(the carries' batched flags, whether the predicate is batched) of a `while`."""
    nc, nb = p["cond_nconsts"], p["body_nconsts"]
    carry, _ = _stable_carry(p["body_jaxpr"], bs[nc : nc + nb], list(bs[nc + nb :]))
    pred = _flags(p["cond_jaxpr"], list(bs[:nc]) + carry)[0]
    if pred:
        carry = [True] * len(carry)
    return carry, pred


def scan_carry_flags(p, bs):
    """(the carries' batched flags, the outputs' (carries, then stacked outputs)) of a `scan`."""
    nc, nk = p["num_consts"], p["num_carry"]
    carry, out = _stable_carry(p["jaxpr"], bs[:nc], list(bs[nc : nc + nk]), bs[nc + nk :])
    return carry, carry + out[nk:]


def cond_flags(p, bs):
    """The outputs' batched flags of a `cond`."""
    if bs[0]:
        return [True] * len(p["branches"][0].jaxpr.outvars)
    per_branch = [_flags(br, bs[1:]) for br in p["branches"]]
    return [any(fs) for fs in zip(*per_branch)]


# --------------------------------------------------------------------------------------------
# Control flow, once for every layout.


def _scan(eqn, vals, layout):
    p = eqn.params
    nc, nk = p["num_consts"], p["num_carry"]
    carry_flags, out_flags = scan_carry_flags(p, [k != U for k, _ in vals])
    body = p["jaxpr"]
    carry_avals, ys_avals = body.in_avals[nc : nc + nk], body.out_avals[nk:]
    carry_kinds, ys_kinds = layout.kinds(carry_avals, carry_flags), layout.kinds(ys_avals, out_flags[nk:])
    consts = vals[:nc]
    init = layout.pack(layout.canon(vals[nc : nc + nk], carry_kinds, carry_avals))
    xs, x_kinds = layout.scan_inputs(vals[nc + nk :], eqn.invars[nc + nk :])

    def step(carry, x):
        c = layout.unpack(carry, carry_kinds, carry_avals)
        with layout.loop_body(scan=True):
            outs = evaluate(body.jaxpr, body.consts, list(consts) + c + list(zip(x_kinds, x)), layout)
        new = layout.pack(layout.canon(outs[:nk], carry_kinds, carry_avals))
        return new, layout.pack(layout.canon(outs[nk:], ys_kinds, ys_avals))

    unroll = layout.unroll(p)
    carry, ys = lax.scan(step, init, xs, length=p["length"], reverse=p["reverse"], unroll=unroll)
    return layout.unpack(carry, carry_kinds, carry_avals) + layout.series(ys, ys_kinds, ys_avals, p["length"])


def _while(eqn, vals, layout):
    p = eqn.params
    nc, nb = p["cond_nconsts"], p["body_nconsts"]
    carry_flags, pred_batched = while_carry_flags(p, [k != U for k, _ in vals])
    cond_j, body_j = p["cond_jaxpr"], p["body_jaxpr"]
    carry_avals = body_j.out_avals
    kinds = layout.kinds(carry_avals, carry_flags)
    cc, bc = vals[:nc], vals[nc : nc + nb]
    init = layout.pack(layout.canon(vals[nc + nb :], kinds, carry_avals))

    def pred(carry):
        return evaluate(cond_j.jaxpr, cond_j.consts, list(cc) + layout.unpack(carry, kinds, carry_avals), layout)[0]

    def body(carry):
        with layout.loop_body(scan=False):
            outs = evaluate(body_j.jaxpr, body_j.consts, list(bc) + layout.unpack(carry, kinds, carry_avals), layout)
        return layout.pack(layout.canon(outs, kinds, carry_avals))

    # A `while` batched by `jax.vmap` inside the program has a predicate of shape S (its own
    # batch) and carries with leading axes S: it runs while any entry is true and updates the
    # entries whose predicate is true. The walk adds the batch axis, last, to the same rule.
    pred_shape = tuple(cond_j.out_avals[0].shape)
    if not pred_batched and not pred_shape:
        out = lax.while_loop(lambda c: pred(c)[1], body, init)
    else:
        go = lambda c: layout.predicate(pred(c))  # noqa: E731

        def masked(carry):
            g = go(carry)
            new = body(carry)
            return [
                [layout.select(g, n, o, pred_shape, pred_batched) for n, o in zip(ns, os)] for ns, os in zip(new, carry)
            ]

        out = lax.while_loop(lambda c: jnp.any(go(c)), masked, init)
    return layout.unpack(out, kinds, carry_avals)


def _cond(eqn, vals, layout):
    branches = eqn.params["branches"]
    out_flags = cond_flags(eqn.params, [k != U for k, _ in vals])
    out_avals = branches[0].out_avals
    kinds = layout.kinds(out_avals, out_flags)
    index, ops = vals[0], vals[1:]

    def run(br, operands):
        return layout.pack(layout.canon(evaluate_closed(br, list(operands), layout), kinds, out_avals))

    if index[0] == U:
        op_kinds, op_avals = [k for k, _ in ops], [v.aval for v in eqn.invars[1:]]

        def branch(br):
            return lambda packed: run(br, layout.unpack(packed, op_kinds, op_avals))

        out = lax.switch(index[1], [branch(br) for br in branches], layout.pack(ops))
        return layout.unpack(out, kinds, out_avals)
    index = layout.index(index)
    return layout.choose(index, [run(br, ops) for br in branches], kinds, out_avals)


CONTROL = {"scan": _scan, "while": _while, "cond": _cond}
"""The control flow the walk evaluates for every layout: `CONTROL[name](eqn, vals, layout)`."""
