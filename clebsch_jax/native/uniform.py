"""Which loop conditions of a member's program are the same in every lane.

A kernel's inputs that are not batched (`build_ir`'s `batched`: a sweep's time step, its
chunk's first step and offset, the shared parameters) hold one value for every member, and so
does whatever is computed from them alone: a loop counter that starts from such a value and
moves by such values, compared with such a bound. `uniform_loops` finds the `while` loops whose
condition is computed from such values only — `jax.vmap`'s own rule for which values of a
program are batched — so that the translation of such a loop at the kernel's top level runs
every lane through the same iterations without keeping a carry per lane (`control._while`):
the selects that keep a stopped lane's carry are left out, since no lane stops before another.
A sweep's chunk (a loop over its steps) is such a loop.

The analysis is conservative: a loop met in several places counts as uniform only where it is
uniform in all of them, a value of a primitive with a nested program it does not know is
batched when any operand is, and the loops inside such a primitive never count.
"""

from __future__ import annotations

__all__ = ["uniform_loops"]

# primitives that call a nested program on their operands, and the parameter that holds it
_CALLS = {
    "pjit": ("jaxpr",),
    "jit": ("jaxpr",),
    "closed_call": ("call_jaxpr",),
    "core_call": ("call_jaxpr",),
    "custom_jvp_call": ("call_jaxpr",),
    "custom_vmap_call": ("call", "call_jaxpr"),
    "custom_vjp_call": ("call_jaxpr", "fun_jaxpr"),
    "checkpoint": ("jaxpr",),
    "remat": ("jaxpr",),
}


def uniform_loops(closed, batched) -> frozenset:
    """The ids of the `while` equations of `closed` (a closed jaxpr, nested ones included)
    whose condition is unbatched wherever the program evaluates them, when its inputs are
    batched as `batched` (one bool per input)."""
    verdict: dict = {}  # id(eqn) -> uniform in every visit so far
    _walk(closed.jaxpr, [False] * len(closed.jaxpr.constvars), list(batched), verdict)
    return frozenset(k for k, uniform in verdict.items() if uniform)


def _open(x):
    """(jaxpr, its constants' count) of a closed or open jaxpr."""
    jaxpr = getattr(x, "jaxpr", x)
    return jaxpr, len(jaxpr.constvars)


def _walk(jaxpr, consts: list, args: list, verdict: dict) -> list:
    """Whether each output of `jaxpr` is batched, given its constants' and inputs' flags."""
    from jax.extend import core as jcore

    env = dict(zip(jaxpr.constvars, consts))
    env.update(zip(jaxpr.invars, args))
    read = lambda v: False if isinstance(v, jcore.Literal) else env.get(v, True)  # noqa: E731
    for eqn in jaxpr.eqns:
        ins = [read(v) for v in eqn.invars]
        outs = _equation(eqn, ins, verdict)
        for v, b in zip(eqn.outvars, outs):
            env[v] = b
    return [read(v) for v in jaxpr.outvars]


def _closed(x, args: list, verdict: dict) -> list:
    jaxpr, n = _open(x)
    return _walk(jaxpr, [False] * n, args, verdict)


def _equation(eqn, ins: list, verdict: dict) -> list:
    name, p = eqn.primitive.name, eqn.params
    n_out = len(eqn.outvars)
    if name == "while":
        cc, bc = p["cond_nconsts"], p["body_nconsts"]
        cconsts, bconsts, carry = ins[:cc], ins[cc : cc + bc], list(ins[cc + bc :])
        while True:  # the carry's flags to their fixed point (they only ever turn batched)
            new = [a or b for a, b in zip(carry, _closed(p["body_jaxpr"], bconsts + carry, {}))]
            pred = _closed(p["cond_jaxpr"], cconsts + new, {})[0]
            if pred:  # lanes stop at different iterations: every carry differs between them
                new = [True] * len(new)
            if new == carry:
                break
            carry = new
        _closed(p["body_jaxpr"], bconsts + carry, verdict)
        _closed(p["cond_jaxpr"], cconsts + carry, verdict)
        verdict[id(eqn)] = verdict.get(id(eqn), True) and not pred
        return carry
    if name == "scan":
        nc, ncar = p["num_consts"], p["num_carry"]
        consts, carry, xs = ins[:nc], list(ins[nc : nc + ncar]), ins[nc + ncar :]
        while True:
            outs = _closed(p["jaxpr"], consts + carry + xs, {})
            new = [a or b for a, b in zip(carry, outs[:ncar])]
            if new == carry:
                break
            carry = new
        return carry + _closed(p["jaxpr"], consts + carry + xs, verdict)[ncar:]
    if name == "cond":
        outs = [_closed(br, ins[1:], verdict) for br in p["branches"]]
        return [ins[0] or any(o[j] for o in outs) for j in range(n_out)]
    if name in _CALLS:
        sub = next((p[k] for k in _CALLS[name] if p.get(k) is not None), None)
        if sub is not None:
            return _closed(sub, ins, verdict)
    for v in p.values():  # a nested program of another primitive: its loops never count
        for x in v if isinstance(v, (tuple, list)) else [v]:
            if hasattr(x, "eqns") or hasattr(getattr(x, "jaxpr", None), "eqns"):
                jaxpr, n = _open(x)
                _walk(jaxpr, [True] * n, [True] * len(jaxpr.invars), _never(verdict))
    return [any(ins)] * n_out


class _never(dict):
    """A verdict that marks every loop it is told of as not uniform, in the dict it wraps."""

    def __init__(self, verdict: dict):
        super().__init__()
        self._verdict = verdict

    def get(self, key, default=None):
        return False

    def __setitem__(self, key, value):
        self._verdict[key] = False
