r"""A member's program without the work its outputs do not need, for the native translation.

The native translation writes out every entry of every equation it is given, used or not, and
refuses programs past a size (`clebsch_jax.native.values.MAX_ENTRIES`); JAX's traces keep the
equations whose results are dropped (XLA drops them when it compiles). A function of a batch
that returns part of what it computes — `cj.integrate(...).Q[-1]`, whose march computes the
nodes, their velocities and energies for every step — would translate all of it.

`pruned(closed)` is a function that evaluates `closed` (a closed jaxpr) binding only the
equations that its outputs need: calls (`clebsch_jax.batching.walk.CALLS`: `jit`,
`custom_jvp_call`, `closed_call`, `checkpoint`, …) are entered, their unneeded outputs
dropped in turn; loops and branches are bound whole when any output is needed; an equation
with effects (a host callback) is always kept. Traced
again (`jax.make_jaxpr`, `clebsch_jax.native.compile_member`), it gives the program the
outputs need, with the same primitives on the same values: the native kernel computes the
same numbers. Custom derivative rules of the calls entered are dropped: the kernel is never
differentiated.
"""

from __future__ import annotations

import contextlib

import jax.extend.core as jex

from .walk import CALLS  # the call primitives entered, and the parameter holding the program

__all__ = ["pruned"]


def pruned(closed):
    """A function of `closed`'s inputs returning its outputs, binding only what they need."""
    needed = [True] * len(closed.jaxpr.outvars)
    return lambda *args: _evaluate(closed.jaxpr, closed.consts, list(args), needed)


def _inner(eqn):
    """(jaxpr, consts) of a call the evaluation enters, else None."""
    name = CALLS.get(eqn.primitive.name)
    if name is None or eqn.effects:
        return None
    program = eqn.params.get(name)
    if isinstance(program, jex.ClosedJaxpr):
        return program.jaxpr, program.consts
    if isinstance(program, jex.Jaxpr) and not program.constvars:
        return program, []
    return None


def _plan(jaxpr, needed: list):
    """The equations to bind, in order, each with the outputs needed of a call entered (None
    for one bound whole), and which of `jaxpr`'s inputs they read."""
    want = {v for v, n in zip(jaxpr.outvars, needed) if n and isinstance(v, jex.Var)}
    kept = []
    for eqn in reversed(jaxpr.eqns):
        outs = [not isinstance(v, jex.DropVar) and v in want for v in eqn.outvars]
        if not (any(outs) or eqn.effects):
            continue
        inner = _inner(eqn)
        if inner is None:
            reads = [True] * len(eqn.invars)
            kept.append((eqn, None))
        else:
            reads = _plan(inner[0], outs)[1]
            kept.append((eqn, outs))
        want.update(v for v, r in zip(eqn.invars, reads) if r and isinstance(v, jex.Var))
    kept.reverse()
    return kept, [v in want for v in jaxpr.invars]


def _evaluate(jaxpr, consts, args: list, needed: list) -> list:
    """`jaxpr`'s outputs (None where not `needed`) from `args`, binding only what they need."""
    env = dict(zip(jaxpr.constvars, consts))
    env.update(zip(jaxpr.invars, args))
    read = lambda v: v.val if isinstance(v, jex.Literal) else env.get(v)
    kept, _ = _plan(jaxpr, needed)
    for eqn, outs in kept:
        values = [read(v) for v in eqn.invars]
        if outs is not None:
            inner, inner_consts = _inner(eqn)
            results = _evaluate(inner, inner_consts, values, outs)
        else:
            results = _bind(eqn, values)
        env.update((v, r) for v, r in zip(eqn.outvars, results) if not isinstance(v, jex.DropVar))
    return [read(v) if n else None for v, n in zip(jaxpr.outvars, needed)]


def _bind(eqn, values: list) -> list:
    """The equation applied to `values`, as `jax.extend.core.jaxpr_as_fun` applies it."""
    bound = eqn.primitive.get_bind_params(eqn.params)
    subfuns, params = bound if isinstance(bound, tuple) else ((), bound)  # JAX versions differ
    context = getattr(getattr(eqn, "ctx", None), "manager", None) or contextlib.nullcontext()
    with context:
        results = eqn.primitive.bind(*subfuns, *values, **params)
    return results if eqn.primitive.multiple_results else [results]
