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

Each nested program is walked once per pattern of its inputs' flags and way of recording
(`_Walk`): a program called from many places (a solve's residual, a derivative rule) with the
same flags gives the same flags out and the same verdicts, so a second visit is only looked up.
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
    walk = _Walk()
    walk.jaxpr(closed.jaxpr, [False] * len(closed.jaxpr.constvars) + list(batched), _RECORD)
    return frozenset(k for k, uniform in walk.verdict.items() if uniform)


# How a walk records the verdicts of the loops it meets: in the verdict (`_RECORD`), not at all
# (`_SCRATCH`: the iterations of a fixed point), or each as not uniform (`_NEVER`: the loops
# inside a primitive the analysis does not know).
_RECORD, _SCRATCH, _NEVER = "record", "scratch", "never"


def _open(x):
    """(jaxpr, its constants' count) of a closed or open jaxpr."""
    jaxpr = getattr(x, "jaxpr", x)
    return jaxpr, len(jaxpr.constvars)


class _Walk:
    """One analysis: `verdict` (id(eqn) -> uniform in every visit so far), and the walks made,
    each kept under its program, its flags (constants', then inputs') and how it recorded."""

    def __init__(self):
        self.verdict: dict = {}
        self._outs: dict = {}  # (id(jaxpr), flags) -> the outputs' flags
        self._recorded: set = set()  # (id(jaxpr), flags, mode) walked with that recording

    def jaxpr(self, jaxpr, flags: list, mode: str) -> list:
        """Whether each output of `jaxpr` is batched, given its constants' and inputs' flags.
        (The jaxprs are those of the program analysed, alive for the whole walk: their ids
        stay theirs.)"""
        key = (id(jaxpr), tuple(flags))
        if key in self._outs and (mode == _SCRATCH or (*key, mode) in self._recorded):
            return self._outs[key]
        from jax.extend import core as jcore

        env = dict(zip(list(jaxpr.constvars) + list(jaxpr.invars), flags))
        read = lambda v: False if isinstance(v, jcore.Literal) else env.get(v, True)  # noqa: E731
        for eqn in jaxpr.eqns:
            outs = self.equation(eqn, [read(v) for v in eqn.invars], mode)
            for v, b in zip(eqn.outvars, outs):
                env[v] = b
        outs = [read(v) for v in jaxpr.outvars]
        self._outs[key] = outs
        if mode != _SCRATCH:
            self._recorded.add((*key, mode))
        return outs

    def closed(self, x, args: list, mode: str) -> list:
        jaxpr, n = _open(x)
        return self.jaxpr(jaxpr, [False] * n + list(args), mode)

    def record(self, eqn, uniform: bool, mode: str) -> None:
        if mode != _SCRATCH:
            self.verdict[id(eqn)] = self.verdict.get(id(eqn), True) and uniform and mode != _NEVER

    def equation(self, eqn, ins: list, mode: str) -> list:
        name, p = eqn.primitive.name, eqn.params
        n_out = len(eqn.outvars)
        if name == "while":
            cc, bc = p["cond_nconsts"], p["body_nconsts"]
            cconsts, bconsts, carry = ins[:cc], ins[cc : cc + bc], list(ins[cc + bc :])
            while True:  # the carry's flags to their fixed point (they only ever turn batched)
                new = [a or b for a, b in zip(carry, self.closed(p["body_jaxpr"], bconsts + carry, _SCRATCH))]
                pred = self.closed(p["cond_jaxpr"], cconsts + new, _SCRATCH)[0]
                if pred:  # lanes stop at different iterations: every carry differs between them
                    new = [True] * len(new)
                if new == carry:
                    break
                carry = new
            self.closed(p["body_jaxpr"], bconsts + carry, mode)
            self.closed(p["cond_jaxpr"], cconsts + carry, mode)
            self.record(eqn, not pred, mode)
            return carry
        if name == "scan":
            nc, ncar = p["num_consts"], p["num_carry"]
            consts, carry, xs = ins[:nc], list(ins[nc : nc + ncar]), ins[nc + ncar :]
            while True:
                outs = self.closed(p["jaxpr"], consts + carry + xs, _SCRATCH)
                new = [a or b for a, b in zip(carry, outs[:ncar])]
                if new == carry:
                    break
                carry = new
            return carry + self.closed(p["jaxpr"], consts + carry + xs, mode)[ncar:]
        if name == "cond":
            outs = [self.closed(br, ins[1:], mode) for br in p["branches"]]
            return [ins[0] or any(o[j] for o in outs) for j in range(n_out)]
        if name in _CALLS:
            sub = next((p[k] for k in _CALLS[name] if p.get(k) is not None), None)
            if sub is not None:
                return self.closed(sub, ins, mode)
        for v in p.values():  # a nested program of another primitive: its loops never count
            for x in v if isinstance(v, (tuple, list)) else [v]:
                if hasattr(x, "eqns") or hasattr(getattr(x, "jaxpr", None), "eqns"):
                    jaxpr, n = _open(x)
                    self.jaxpr(jaxpr, [True] * (n + len(jaxpr.invars)), _SCRATCH if mode == _SCRATCH else _NEVER)
        return [any(ins)] * n_out
