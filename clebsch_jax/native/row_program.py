r"""One row of an equation over a long leading axis: which equations compute row k of their
outputs from row k of their operands, and their program for one row (no IR here: the
translation, `clebsch_jax.native.rows`, emits it in a loop over the rows).

`row_plan(eqn, n)` covers equations without nested programs by their shapes alone
(elementwise primitives, selects, broadcasts, re-indexing and reductions of the other axes,
contractions batched over the axis). `row_equation(eqn, split, n)` covers every equation, given
which operands are split by rows (`split`; the others are whole, the same for every row): it
returns a `JaxprEqn` of one row, whose nested programs (`while`, `scan`, `cond`,
`custom_linear_solve`, calls) are their programs for one row (`row_jaxpr`), made equation by
equation, and which outputs are split by rows. An equation none of whose operands is split
stays as it is (every row computes it alike), except a broadcast along the axis, which is split
(each row its operand).

A `while` whose predicate has one entry per row (`jax.vmap` of a loop: a row whose entry is
false keeps its carry while the others iterate) becomes one row's loop with that row's scalar
predicate: a row's carry changes only while its own predicate holds, and its body reads only
its own row, so the row's loop makes the same iterations on the same numbers and stops where
the batched loop stops changing it. So a program of `jax.vmap` over the nodes of a trajectory
(the nodal velocities' Newton loops, Lemma 7) is one row's program, emitted once, whatever the
number of nodes.
"""

from __future__ import annotations

import numpy as np
from jax.extend import core as jcore
from jax.extend.core.primitives import squeeze_p

from .elementwise import ELEMENTWISE

__all__ = ["ROWWISE", "REDUCE", "CALL_PROGRAMS", "row_plan", "row_equation", "row_jaxpr"]

ROWWISE = set(ELEMENTWISE) | {"select_n", "convert_element_type", "clamp", "erf_inv", "nextafter"}
"""Primitives applied entry by entry: each row of the result from the same row of the operands."""

REDUCE = {"reduce_sum", "reduce_max", "reduce_min", "reduce_and", "reduce_or", "reduce_prod", "argmax", "argmin"}
"""Reductions: row by row when they do not reduce the rows' axis."""

CALL_PROGRAMS = {
    "pjit": "jaxpr",
    "jit": "jaxpr",
    "closed_call": "call_jaxpr",
    "core_call": "call_jaxpr",
    "custom_jvp_call": "call_jaxpr",
    "custom_vjp_call": "call_jaxpr",
    "checkpoint": "jaxpr",
    "remat": "jaxpr",
}
"""Calls, by the parameter holding the program they call."""


def _shape(v) -> tuple:
    return tuple(getattr(v.aval, "shape", ()))


def row_plan(eqn, n: int):
    """(params of one row's equation, which operands are split by rows) when `eqn` computes row
    k of its output from row k of the operands flagged (the others whole), else None; read off
    the shapes (an operand with a leading axis of `n` is split, one of 1 is "one": its one row
    for every row)."""
    name, p = eqn.primitive.name, eqn.params
    shapes = [_shape(v) for v in eqn.invars]
    lead = [len(s) > 0 and s[0] == n for s in shapes]
    out = tuple(eqn.outvars[0].aval.shape) if len(eqn.outvars) == 1 else None
    if out is None or not out or out[0] != n:
        return None
    if name in ROWWISE:  # operands of the output's shape, or broadcast to it along axes of size 1
        fits = lambda s: len(s) == len(out) and s[0] in (1, n) and all(a in (1, b) for a, b in zip(s[1:], out[1:]))
        if any(len(s) > 0 and not fits(s) for s in shapes):
            return None
        return dict(p), [True if len(s) > 0 and s[0] == n else "one" if len(s) > 0 else False for s in shapes]
    if name == "broadcast_in_dim":
        dims = tuple(p["broadcast_dimensions"])
        if dims and dims[0] == 0 and lead[0]:
            row = dict(p, shape=tuple(p["shape"][1:]), broadcast_dimensions=tuple(d - 1 for d in dims[1:]))
            return row, [True] + [False] * (len(shapes) - 1)
        if 0 not in dims and len(shapes) == 1:
            return dict(p, shape=tuple(p["shape"][1:]), broadcast_dimensions=tuple(d - 1 for d in dims)), [False]
        return None
    if not lead[0] or (any(lead[1:]) and name not in ("concatenate", "dot_general")):
        return None
    if name == "reshape" and p.get("dimensions") is None and p["new_sizes"][0] == n:
        return dict(p, new_sizes=tuple(p["new_sizes"][1:])), lead
    if name == "squeeze" and 0 not in p["dimensions"]:
        return dict(p, dimensions=tuple(d - 1 for d in p["dimensions"])), lead
    if name == "transpose" and p["permutation"][0] == 0:
        return dict(p, permutation=tuple(d - 1 for d in p["permutation"][1:])), lead
    if name == "slice" and p["start_indices"][0] == 0 and p["limit_indices"][0] == n:
        if p["strides"] is None or p["strides"][0] == 1:
            strides = None if p["strides"] is None else tuple(p["strides"][1:])
            return dict(
                p, start_indices=p["start_indices"][1:], limit_indices=p["limit_indices"][1:], strides=strides
            ), lead
    if name == "concatenate" and p["dimension"] != 0 and all(lead):
        return dict(p, dimension=p["dimension"] - 1), lead
    if name in REDUCE and 0 not in p["axes"]:
        return dict(p, axes=tuple(a - 1 for a in p["axes"])), lead
    if name in ("cumsum", "cumprod", "cummax", "cummin", "cumlogsumexp") and p["axis"] != 0:
        return dict(p, axis=p["axis"] - 1), lead
    if name == "dot_general":
        (lc, rc), (lb, rb) = p["dimension_numbers"]
        sub = lambda ds: tuple(d - 1 for d in ds)
        if all(lead) and lb and rb and lb[0] == 0 and rb[0] == 0:  # batched over the rows
            return dict(p, dimension_numbers=((sub(lc), sub(rc)), (sub(lb[1:]), sub(rb[1:])))), lead
        if not lb and not rb and 0 not in lc:  # the rows a free axis of the left operand, the right one whole
            return dict(p, dimension_numbers=((sub(lc), tuple(rc)), ((), ()))), [True, False]
    return None


def _drop(dims, axis: int) -> tuple:
    """Axis numbers `dims` (none of them `axis`) once `axis` is removed."""
    return tuple(int(d) - (int(d) > axis) for d in dims)


def _without(seq, axis: int) -> tuple:
    return tuple(x for k, x in enumerate(seq) if k != axis)


def _one_axis(split):
    """The rows' axis of the split operands when they all share one, else None."""
    axes = {a for a in split if a is not None}
    return axes.pop() if len(axes) == 1 else None


def _elementwise(eqn, split, n):
    a = _one_axis(split)
    out = _shape(eqn.outvars[0])
    if a is None or any(x is None and _shape(v) != () for x, v in zip(split, eqn.invars)):
        return None  # a whole operand of the output's shape would have to give its rows
    return (dict(eqn.params), [a]) if all(_shape(v)[a : a + 1] == (n,) for v in eqn.outvars) and out else None


def _broadcast(p, split, n, out_shape):
    (a,) = split
    dims = tuple(p["broadcast_dimensions"])
    if a is None:  # a whole operand broadcast along a new leading axis of the rows: each row the operand
        if out_shape[:1] != (n,) or 0 in dims:
            return None
        return dict(p, shape=tuple(p["shape"][1:]), broadcast_dimensions=_drop(dims, 0)), [0]
    b = dims[a]
    if out_shape[b] != n:
        return None
    return dict(p, shape=_without(p["shape"], b), broadcast_dimensions=_drop(_without(dims, a), b)), [b]


def _reshape(p, a, n, in_shape):
    if p.get("dimensions") is not None:
        return None
    new = tuple(p["new_sizes"])
    before, after = int(np.prod(in_shape[:a], dtype=int)), int(np.prod(in_shape[a + 1 :], dtype=int))
    for b in range(len(new)):  # the rows' axis kept whole, the same sizes before and after it
        if (
            new[b] == n
            and int(np.prod(new[:b], dtype=int)) == before
            and int(np.prod(new[b + 1 :], dtype=int)) == after
        ):
            return dict(p, new_sizes=_without(new, b)), [b]
    return None


def _dot(p, split, shapes):
    (lc, rc), (lb, rb) = p["dimension_numbers"]
    la, ra = split
    nb = len(lb)
    if la is not None and ra is not None:  # batched over the rows, at the same batch position
        j = next((k for k in range(nb) if lb[k] == la and rb[k] == ra), None)
        if j is None:
            return None
        dn = ((_drop(lc, la), _drop(rc, ra)), (_drop(_without(lb, j), la), _drop(_without(rb, j), ra)))
        return dict(p, dimension_numbers=dn), [j]
    side, a = (0, la) if la is not None else (1, ra)
    contract, batch = (lc, lb) if side == 0 else (rc, rb)
    if a in contract or a in batch:
        return None
    rank = len(shapes[side])
    free = [d for d in range(rank) if d not in contract and d not in batch]
    b = nb + free.index(a)
    if side == 1:
        lrank = len(shapes[0])
        b += lrank - len(lc) - nb
    if side == 0:
        dn = ((_drop(lc, a), tuple(rc)), (_drop(lb, a), tuple(rb)))
    else:
        dn = ((tuple(lc), _drop(rc, a)), (tuple(lb), _drop(rb, a)))
    return dict(p, dimension_numbers=dn), [b]


def _gather(p, split, n, shapes, out_rank):
    """A gather whose operand's rows are a whole window, at indices the same for every row; one
    batched over the rows (`operand_batching_dims`), each row at its own indices; or one of a
    whole operand at indices split by rows, each row at its own indices."""
    a, c = split
    dn = p["dimension_numbers"]
    batch_out = [d for d in range(out_rank) if d not in dn.offset_dims]
    if a is None:  # a whole operand at indices split by rows (on a batch axis of theirs)
        if c is None or c >= len(shapes[1]) - 1 or c in dn.start_indices_batching_dims:
            return None
        b = batch_out[c]
        row = dn._replace(
            offset_dims=_drop(dn.offset_dims, b),
            start_indices_batching_dims=_drop(dn.start_indices_batching_dims, c),
        )
        return dict(p, dimension_numbers=row), [b]
    window = [
        d for d in range(len(shapes[0])) if d not in dn.collapsed_slice_dims and d not in dn.operand_batching_dims
    ]
    if c is None and a in window and p["slice_sizes"][a] == n and a not in dn.start_index_map:
        b, offsets, index_batch = dn.offset_dims[window.index(a)], _without(dn.offset_dims, window.index(a)), None
    elif c is not None and a in dn.operand_batching_dims and c < len(shapes[1]) - 1:
        j = list(dn.operand_batching_dims).index(a)
        if dn.start_indices_batching_dims[j] != c:
            return None
        b, offsets, index_batch = batch_out[c], dn.offset_dims, j
    else:
        return None
    row = dn._replace(
        offset_dims=_drop(offsets, b),
        collapsed_slice_dims=_drop(dn.collapsed_slice_dims, a),
        start_index_map=_drop(dn.start_index_map, a),
        operand_batching_dims=_drop(_without(dn.operand_batching_dims, -1 if index_batch is None else index_batch), a),
        start_indices_batching_dims=dn.start_indices_batching_dims
        if index_batch is None
        else _drop(_without(dn.start_indices_batching_dims, index_batch), c),
    )
    return dict(p, dimension_numbers=row, slice_sizes=_without(p["slice_sizes"], a)), [b]


def _scatter(p, split, n, shapes):
    """A scatter into an operand whose rows are a whole window of the updates (the same for
    every row, at indices the same for every row)."""
    a, idx, c = split
    dn = p["dimension_numbers"]
    if a is None or idx is not None or c is None or a in dn.scatter_dims_to_operand_dims:
        return None
    window = [
        d for d in range(len(shapes[0])) if d not in dn.inserted_window_dims and d not in dn.operand_batching_dims
    ]
    if a not in window or dn.update_window_dims[window.index(a)] != c or shapes[2][c] != n:
        return None
    row = dn._replace(
        update_window_dims=_drop(_without(dn.update_window_dims, window.index(a)), c),
        inserted_window_dims=_drop(dn.inserted_window_dims, a),
        scatter_dims_to_operand_dims=_drop(dn.scatter_dims_to_operand_dims, a),
        operand_batching_dims=_drop(dn.operand_batching_dims, a),
    )
    return dict(p, dimension_numbers=row), [a]


def _plain(eqn, split, n):
    """(params of one row, the rows' axis of each output) of an equation without nested
    programs, its split operands' rows on the axes `split` (None: whole)."""
    name, p = eqn.primitive.name, eqn.params
    shapes = [_shape(v) for v in eqn.invars]
    a = _one_axis(split)
    if name in ROWWISE:
        return _elementwise(eqn, split, n)
    if name == "broadcast_in_dim" and len(split) == 1:
        return _broadcast(p, split, n, _shape(eqn.outvars[0]))
    if name == "dot_general":
        return _dot(p, split, shapes)
    if name == "gather":
        return _gather(p, split, n, shapes, len(_shape(eqn.outvars[0])))
    if name.startswith("scatter") and len(split) == 3:  # its update jaxpr: the primitive's combination of two entries
        return _scatter(p, split, n, shapes)
    if name == "pad" and a is not None and split[1] is None and tuple(p["padding_config"][a]) == (0, 0, 0):
        return dict(p, padding_config=_without(p["padding_config"], a)), [a]
    if a is None or any(x is None for x in split):  # below: every operand split on one axis
        return None
    if name == "reshape":
        return _reshape(p, a, n, shapes[0])
    if name == "squeeze" and a not in p["dimensions"]:
        return dict(p, dimensions=_drop(p["dimensions"], a)), [a - sum(d < a for d in p["dimensions"])]
    if name == "transpose":
        perm = tuple(p["permutation"])
        b = perm.index(a)
        return dict(p, permutation=_drop(_without(perm, b), a)), [b]
    if name == "slice" and (p["start_indices"][a], p["limit_indices"][a]) == (0, n):
        if p["strides"] is None or p["strides"][a] == 1:
            strides = None if p["strides"] is None else _without(p["strides"], a)
            row = dict(p, start_indices=_without(p["start_indices"], a), limit_indices=_without(p["limit_indices"], a))
            return dict(row, strides=strides), [a]
    if name in ("concatenate",) and p["dimension"] != a:
        return dict(p, dimension=_drop([p["dimension"]], a)[0]), [a]
    if name in REDUCE and a not in p["axes"]:
        return dict(p, axes=_drop(p["axes"], a)), [a - sum(d < a for d in p["axes"])]
    if name in ("cumsum", "cumprod", "cummax", "cummin", "cumlogsumexp", "rev", "split", "sort"):
        key = {"rev": "dimensions", "sort": "dimension"}.get(name, "axis")
        dims = p[key] if name == "rev" else (p[key],)
        if a in dims:
            return None
        value = _drop(dims, a) if name == "rev" else _drop(dims, a)[0]
        return dict(p, **{key: value}), [a] * len(eqn.outvars)
    if name == "unstack" and p["axis"] != a:
        return dict(p, axis=_drop([p["axis"]], a)[0]), [a - (p["axis"] < a)] * len(eqn.outvars)
    if name == "stack":
        axis = p["axis"]
        return dict(p, axis=axis if axis <= a else axis - 1), [a + 1 if axis <= a else a]
    if name in ("lu", "cholesky") and a < len(shapes[0]) - 2:
        return dict(p), [a] * len(eqn.outvars)
    if name == "triangular_solve" and a < len(shapes[0]) - 2:
        return dict(p), [a]
    return None


def _same_carry(found, carry: list):
    """`found` (a loop body's row program) where the body keeps each carry's split (a carry that
    starts whole and comes out split would have to take its rows from the whole), else None."""
    return found if found is not None and found[1][: len(carry)] == list(carry) else None


def _while(p, split, n):
    cc, bc = p["cond_nconsts"], p["body_nconsts"]
    cflags, bflags, init = split[:cc], split[cc : cc + bc], split[cc + bc :]
    body = _same_carry(row_jaxpr(p["body_jaxpr"], bflags + init, n), init)
    cond = None if body is None else row_jaxpr(p["cond_jaxpr"], cflags + init, n)
    if cond is None:
        return None
    (pred,), (pred_axis,) = cond[0].out_avals, cond[1]
    # a predicate per row holds each row's carry (its leading axis): every carry must be split
    # there; a whole predicate is a scalar
    if pred.shape != () or (pred_axis is not None and any(a != 0 for a in init)):
        return None
    return dict(p, cond_jaxpr=cond[0], body_jaxpr=body[0]), list(init)


def _scan(p, split, n):
    nc, ncar = p["num_consts"], p["num_carry"]
    xs = split[nc + ncar :]
    if any(a == 0 for a in xs):  # a scan over the rows
        return None
    # an input scanned over has its rows one axis further than the body's slice of it, and so
    # do the records
    inner = list(split[: nc + ncar]) + [None if a is None else a - 1 for a in xs]
    body = _same_carry(row_jaxpr(p["jaxpr"], inner, n), split[nc : nc + ncar])
    if body is None:
        return None
    out = body[1][:ncar] + [None if a is None else a + 1 for a in body[1][ncar:]]
    return dict(p, jaxpr=body[0]), out


def _cond(p, split, n):
    if split[0] is not None:  # a branch per row: vmap makes it a select, never a cond
        return None
    found = [row_jaxpr(b, split[1:], n) for b in p["branches"]]
    if any(f is None for f in found) or any(f[1] != found[0][1] for f in found):
        return None
    return dict(p, branches=tuple(f[0] for f in found)), found[0][1]


def _linear_solve(p, split, n):
    lengths, jaxprs = p["const_lengths"], p["jaxprs"]
    b = split[sum(lengths) :]
    made, at, out = {}, 0, None
    for key in ("matvec", "vecmat", "solve", "transpose_solve"):
        count = getattr(lengths, key)
        closed = getattr(jaxprs, key)
        consts, at = split[at : at + count], at + count
        if closed is None:
            continue
        found = row_jaxpr(closed, consts + b, n)
        if found is None:
            return None
        made[key] = found[0]
        out = found[1] if key == "solve" else out
    return (dict(p, jaxprs=jaxprs._replace(**made)), out) if out is not None else None


_NESTED = {"while": _while, "scan": _scan, "cond": _cond, "custom_linear_solve": _linear_solve}


def row_equation(eqn, split: list, n: int):
    """(the equation of one row, which of its outputs are split) when `eqn` computes row k of
    each split output from row k of the operands flagged in `split` (the others whole: the same
    for every row), with the whole outputs the same for every row; else None."""
    name, p = eqn.primitive.name, eqn.params
    if name in _NESTED:
        found = _NESTED[name](p, split, n)
    elif name in CALL_PROGRAMS and p.get(CALL_PROGRAMS[name]) is not None:
        inner = row_jaxpr(p[CALL_PROGRAMS[name]], split, n)
        found = None if inner is None else (dict(p, **{CALL_PROGRAMS[name]: inner[0]}), inner[1])
    elif not name.startswith("scatter") and any(isinstance(v, (jcore.ClosedJaxpr, jcore.Jaxpr)) for v in p.values()):
        return None
    else:
        found = _plain(eqn, split, n)
    if found is None:
        return None
    params, out = found
    invars = [v if a is None or isinstance(v, jcore.Literal) else _row_var(v, a) for v, a in zip(eqn.invars, split)]
    outvars = [v if a is None else _row_var(v, a) for v, a in zip(eqn.outvars, out)]
    return jcore.new_jaxpr_eqn(invars, outvars, eqn.primitive, params, eqn.effects), list(out)


def _row_var(v, axis: int):
    """A variable for one row of `v`, whose rows are on `axis`."""
    aval = v.aval.update(shape=_without(v.aval.shape, axis))
    return jcore.DropVar(aval) if isinstance(v, jcore.DropVar) else jcore.Var(aval)


def _broadcast_rows(eqn, n: int) -> bool:
    """Whether `eqn` (of whole operands) broadcasts them along a leading axis of `n`: each row
    its operand."""
    if eqn.primitive.name != "broadcast_in_dim" or len(eqn.invars) != 1:
        return False
    return _shape(eqn.outvars[0])[:1] == (n,) and 0 not in eqn.params["broadcast_dimensions"]


def _one_rows(eqn, flags: list, n: int, atom, eqns: list, rename: dict, is_split: dict):
    """`eqn` (elementwise) with each whole operand of one entry on the rows' axis (broadcast
    along it, as `lax` lets elementwise operands be) replaced by a stand-in split on that axis,
    whose row is the operand without the axis (a squeeze, appended to `eqns`); `flags` updated."""
    a = _one_axis(flags)
    out = _shape(eqn.outvars[0])
    invars = list(eqn.invars)
    for k, v in enumerate(eqn.invars):
        s = _shape(v)
        if flags[k] is not None or len(s) != len(out) or s[a] != 1 or n == 1:
            continue
        row = jcore.Var(v.aval.update(shape=_without(s, a)))
        eqns.append(jcore.new_jaxpr_eqn([atom(v)], [row], squeeze_p, {"dimensions": (a,)}, jcore.no_effects))
        invars[k] = jcore.Var(v.aval.update(shape=s[:a] + (n,) + s[a + 1 :]))
        rename[invars[k]], is_split[invars[k]], flags[k] = row, a, a
    return eqn.replace(invars=invars)


def row_jaxpr(program, split: list, n: int):
    """(`program`'s program of one row, which of its outputs are split) for its inputs split as
    flagged (`program` a `ClosedJaxpr` or a `Jaxpr`; the result of the same kind), or None where
    some row of an output depends on another row, or an equation is not covered."""
    closed = isinstance(program, jcore.ClosedJaxpr)
    jaxpr = program.jaxpr if closed else program
    rename: dict = {}
    is_split: dict = {}

    def atom(v):
        return v if isinstance(v, jcore.Literal) else rename.get(v, v)

    def axis(v):
        return None if isinstance(v, jcore.Literal) else is_split.get(v)

    invars = []
    for v, a in zip(jaxpr.invars, split):
        invars.append(v if a is None else _row_var(v, a))
        rename[v], is_split[v] = invars[-1], a
    eqns = []
    for eqn in jaxpr.eqns:
        flags = [axis(v) for v in eqn.invars]
        if all(a is None for a in flags) and not _broadcast_rows(eqn, n):  # every row computes it alike
            eqns.append(eqn)
            continue
        if eqn.primitive.name in ROWWISE and _one_axis(flags) is not None:
            eqn = _one_rows(eqn, flags, n, atom, eqns, rename, is_split)
        found = row_equation(eqn, flags, n)
        if found is None:
            return None
        row, out = found
        row = row.replace(invars=[atom(v) for v in eqn.invars])
        for v, r, s in zip(eqn.outvars, row.outvars, out):
            rename[v], is_split[v] = r, s
        eqns.append(row)
    outvars = [atom(v) for v in jaxpr.outvars]
    made = jcore.Jaxpr(jaxpr.constvars, invars, outvars, eqns, jaxpr.effects, jaxpr.debug_info)
    return (jcore.ClosedJaxpr(made, program.consts) if closed else made), [axis(v) for v in jaxpr.outvars]
