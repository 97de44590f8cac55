r"""A call `jax.vmap`ped over a leading axis, emitted as a loop over its rows.

`jax.vmap(jax.jit(f))(xs)` leaves one call equation in the member's jaxpr whose program is `f`
batched over the leading axis of `xs`: its operands with that axis are split by rows, the others
are whole (`in_axes=None`), and every output has the axis. Where that program keeps the rows
apart (`row_program.row_equation`: row k of each output from row k of the split operands), the
translation can emit `f`'s program for one row once, in a loop over the rows, instead of its
entries for every row: the columns of a lumped block Jacobian (`clebsch_jax.roots.blocks`, one
Jacobian-vector product per unknown of a particle) and the inverses of its blocks (one per
particle). The call is then treated as a scan of as many iterations as it has rows
(`control.unroll_policy`): unrolled where the policy unrolls such a scan, a loop otherwise. A row
computes what its entries would, in the same order: only where the rows are held changes
(the split operands and the outputs in the kernel's buffer, `rows.memory`).
"""

from __future__ import annotations

from .row_program import CALL_PROGRAMS, row_equation

__all__ = ["CALLS", "MIN_ROW_SIZE", "row_call", "row_body", "emit"]

CALLS = {name: CALL_PROGRAMS[name] for name in ("pjit", "jit", "closed_call")}
"""The call primitives a `jax.vmap` of a `jit` leaves, by the parameter holding the program they
call."""

MIN_ROW_SIZE = 200
"""A call runs as a loop over its rows only where one row's program computes at least this many
entries (`control._size`): a smaller one (`jnp.where` over a vector, a call of a few entries
per row) would cost more as a loop, its rows through memory, than written out."""


def _shape(v) -> tuple:
    return tuple(getattr(v.aval, "shape", ()))


def row_call(eqn):
    """(the call's equation of one row, its number of rows) when `eqn` is a call whose outputs
    all have a leading axis of the same length n ≥ 2, whose operands with that leading axis are
    split by rows and the others whole, and whose program keeps the rows apart; else None."""
    if eqn.primitive.name not in CALLS or not eqn.outvars:
        return None
    outs = [_shape(v) for v in eqn.outvars]
    n = outs[0][0] if outs[0] else 0
    if n < 2 or any(s[:1] != (n,) for s in outs):
        return None
    split = [0 if _shape(v)[:1] == (n,) else None for v in eqn.invars]
    if all(a is None for a in split):
        return None
    found = row_equation(eqn, split, n)
    if found is None or any(a != 0 for a in found[1]):
        return None
    return found[0], n


def row_body(row_eqn):
    """The program (a `Jaxpr`) of one row of a `row_call`."""
    program = row_eqn.params[CALLS[row_eqn.primitive.name]]
    return getattr(program, "jaxpr", program)


def emit(em, eqn, args, n: int, rules) -> list:
    """The outputs (entry arrays) of the call `eqn` (a `row_call` of `n` rows) by a loop over
    its rows that runs its program for one row (`rows.row_loop`), read back entry by entry."""
    from . import rows as _rows

    looped = _rows.row_loop(em, eqn, args, n, rules)
    outs = looped if eqn.primitive.multiple_results else [looped]
    outs = [_rows.materialize(em, r) for r in outs]
    return outs if eqn.primitive.multiple_results else outs[0]
