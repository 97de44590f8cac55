r"""Sums over an axis of elementwise expressions, emitted as loops over that axis (`Lazy`).

A model written with broadcasting over its particles — pairwise differences `x[:, None] - x[None,
:]`, a kernel of them, its sum over one axis or both, and the same sums in its gradient by
`jax.grad` — computes (N, N) arrays whose only use is to be summed. Written out entry by entry
(`clebsch_jax.native.values`), each is N² instructions per evaluation. Here an elementwise
equation (`DEFERRED`: elementwise primitives, selects, conversions, broadcasts, `iota`) with at
least `MIN_ENTRIES` entries is not emitted where it stands: it is kept as a `Lazy` (the equation
and its operands), and any use but a sum writes it out there (`materialize`), with the code it
would have had. A `reduce_sum` of a `Lazy` over axes of at least `MIN_AXIS` entries is a loop nest
(`axis_loops.loop`) over those of its reduced axes that come first and over its large kept axes;
its body evaluates the expression at the loops' indices (`_Slices`: for an (N, N) sum over both
axes, one entry per equation) and carries the running sums in phis; a `dot_general` contracting
such an axis is a loop over it. Operands that vary with the loops' indices and are not `Lazy` are
stored before the loops into an alloca they index (`axis_loops.Buffer`; once per jaxpr: later
loops reuse the stores that precede them), and a `Lazy` read by more than one equation whose
evaluation is not cheap (`SHARED_COST`) is computed once into memory by loops of its own, so that
the forward values of a gradient are not recomputed by each of its sums.

The sums keep the unrolled form's order: the entries of the reduced axes in C order (the loops
over the first of them, the others summed inside the body in order), each sum from the additive
identity -0.0, exact (-0.0 + x is x, bit for bit; a known factor 1 is not multiplied, as
unrolled). So the results are the unrolled code's, bit for bit. A sum whose varying operands have
known entries is written out, as its unrolled sums are known and fold into what follows.
"""

from __future__ import annotations

import math
import types

import numpy as np

from .elementwise import ELEMENTWISE, emit_float, emit_int, product
from .axis_loops import Buffer, as_array, fill, loop, scopes, splat
from .values import Emitter, is_known

__all__ = [
    "MIN_ENTRIES",
    "MIN_AXIS",
    "SHARED_COST",
    "DEFERRED",
    "Lazy",
    "defers",
    "materialize",
    "reduce_rule",
    "dot_rule",
]

MIN_ENTRIES = 64
"""An elementwise equation is deferred (`Lazy`) from this many entries of its output on."""

MIN_AXIS = 8
"""A sum of a `Lazy` runs as a loop over an axis of at least this many entries; over a shorter
axis the expression is written out and summed unrolled."""

SHARED_COST = 4
"""A `Lazy` read by more than one equation whose slice evaluates at least this many equations is
computed once into memory (`_Slices._stored`) rather than in the body of every sum that reads it."""

DEFERRED = frozenset(ELEMENTWISE) | {"select_n", "convert_element_type", "broadcast_in_dim", "iota"}


class Lazy:
    """The output of an equation not yet emitted: `eqn` applied to `args` (entry arrays or
    `Lazy`); `value` its entries once written out."""

    __slots__ = ("eqn", "args", "shape", "dtype", "value", "uses")

    def __init__(self, eqn, args, uses: int = 1):
        self.eqn, self.args, self.uses = eqn, args, uses  # `uses`: equations reading it
        aval = eqn.outvars[0].aval
        self.shape, self.dtype, self.value = tuple(aval.shape), np.dtype(aval.dtype), None

    @property
    def ndim(self) -> int:
        return len(self.shape)


def defers(eqn) -> bool:
    """Whether the translation keeps `eqn`'s output as a `Lazy`: a `DEFERRED` equation of one
    output of at least `MIN_ENTRIES` entries whose operands are of its rank or scalars."""
    if eqn.primitive.name not in DEFERRED or eqn.primitive.multiple_results or len(eqn.outvars) != 1:
        return False
    shape = tuple(getattr(eqn.outvars[0].aval, "shape", ()))
    if math.prod(shape) < MIN_ENTRIES:
        return False
    if eqn.primitive.name == "broadcast_in_dim":
        return len(eqn.invars) == 1
    return all(len(getattr(v.aval, "shape", ())) in (0, len(shape)) for v in eqn.invars)


def materialize(em: Emitter, x, rules):
    """The entries of `x` (a `Lazy` written out where this is called, once; anything else as it is)."""
    if not isinstance(x, Lazy):
        return x
    if x.value is None:
        args = [materialize(em, a, rules) for a in x.args]
        em.count(math.prod(x.shape))
        x.value = rules[x.eqn.primitive.name](em, x.eqn, args)
    return x.value


def _aval(shape, dtype):
    return types.SimpleNamespace(aval=types.SimpleNamespace(shape=tuple(shape), dtype=np.dtype(dtype), ndim=len(shape)))


DYN = "dyn"
"""An axis fixed at the loop's index (while planning: `_Slices.prepare`)."""


def _dynamic(f) -> bool:
    return f is not None and not isinstance(f, int)


def _varies(x, fix) -> bool:
    """Whether `x` (with `fix`: per axis None, kept; 0, at index 0; else at a loop's index)
    varies with the loops' indices."""
    return np.ndim(x) > 0 and any(_dynamic(f) for f in fix)


def _operand_fix(x, a, fix):
    """`fix` of the operand `a` of the `Lazy` `x` (None: a scalar, taken as it is)."""
    if np.ndim(a) == 0:
        return None
    shape = np.shape(a)
    if x.eqn.primitive.name == "broadcast_in_dim":
        dims = x.eqn.params["broadcast_dimensions"]
        return tuple(None if fix[d] is None else 0 if shape[m] == 1 else fix[d] for m, d in enumerate(dims))
    return tuple(None if f is None else 0 if n == 1 else f for f, n in zip(fix, shape))


class _Slices:
    """The slices of an expression at the loops' indices: `prepare` (before the loops) writes
    out what does not vary with them and stores the operands that vary and are not `Lazy`
    (`Buffer`); `at` (in the loops' body) emits each `Lazy`'s slice once."""

    def __init__(self, em: Emitter, rules):
        self.em, self.rules = em, rules
        self.buffers: dict = {}  # id of an entry array -> its `Buffer`
        self.seen: set = set()
        self.entries = 0  # entries the loops' body and the buffers count

    def loops(self, x, fix) -> bool:
        """Whether a loop pays for `x`: every operand that varies with the loops' indices and is
        not `Lazy` has no known entry (the unrolled sums of known entries are known, and fold
        into what follows; a loop's are not), and there is one."""
        leaves: list = []
        self._leaves(x, fix, leaves, set())
        return bool(leaves) and not any(is_known(e) for leaf in leaves for e in np.asarray(leaf, object).reshape(-1))

    def _leaves(self, x, fix, out: list, seen: set) -> None:
        if fix is None or not _varies(x, fix) or (id(x), fix) in seen:
            return
        seen.add((id(x), fix))
        if not isinstance(x, Lazy):
            out.append(x)
            return
        for a in x.args if x.eqn.primitive.name != "iota" else ():
            self._leaves(a, _operand_fix(x, a, fix), out, seen)

    def prepare(self, x, fix, dtype, root: bool = False) -> None:
        if fix is None:
            return
        if not _varies(x, fix):
            materialize(self.em, x, self.rules)
            return
        if (id(x), fix) in self.seen:
            return
        self.seen.add((id(x), fix))
        if not isinstance(x, Lazy):
            if id(x) not in self.buffers:
                self.buffers[id(x)] = self._buffer(x, dtype)
            return
        if not root and x.uses > 1 and _cost(x, set()) >= SHARED_COST:
            self.buffers[id(x)] = self._stored(x)
            return
        self.entries += math.prod(n for n, f in zip(x.shape, fix) if f is None)
        if x.eqn.primitive.name != "iota":
            for a, v in zip(x.args, x.eqn.invars):
                self.prepare(a, _operand_fix(x, a, fix), v.aval.dtype)

    def _buffer(self, x, dtype) -> Buffer:
        """`x`'s entries in memory: stored where this equation stands, or found among those
        stored earlier by the jaxprs being translated (`scopes`: each is emitted in order, after
        the code of the jaxprs it is nested in, so those stores precede the loop)."""
        flat = np.asarray(x, object).reshape(-1)
        key = (np.dtype(dtype), tuple(map(id, flat)))
        for scope in reversed(scopes(self.em)):
            if key in scope:
                return scope[key][1].reshaped(np.shape(x))
        buffer = Buffer(self.em, (flat.size,), dtype, flat)
        scopes(self.em)[-1][key] = (flat, buffer)  # the entries kept alive: their ids stay theirs
        self.entries += flat.size
        return buffer.reshaped(np.shape(x))

    def _stored(self, x: Lazy) -> Buffer:
        """A `Lazy` read by more than one equation, and not cheap, in memory: computed once, in
        loops over its axes of at least `MIN_AXIS` entries (found among those stored earlier,
        as `_buffer`), so that the sums that read it do not each compute it."""
        key = ("stored", id(x))
        for scope in reversed(scopes(self.em)):
            if key in scope:
                return scope[key][1]
        loops = [(d, n) for d, n in enumerate(x.shape) if n >= MIN_AXIS]
        inner = _Slices(self.em, self.rules)
        inner.prepare(x, tuple(DYN if n >= MIN_AXIS else None for n in x.shape), x.dtype, root=True)
        buffer = Buffer(self.em, x.shape, x.dtype)

        def values(fixes):
            fix = tuple(fixes.get(d) for d in range(x.ndim))
            return np.asarray(inner.at(x, fix, {}), object).reshape(-1)

        fill(self.em, buffer, loops, values)
        scopes(self.em)[-1][key] = (x, buffer)
        self.entries += inner.entries + math.prod(x.shape)
        return buffer

    def at(self, x, fix, memo: dict):
        """The entries of `x` at `fix` (its kept axes, in order)."""
        if fix is None or np.ndim(x) == 0:
            return x
        if not _varies(x, fix):
            whole = np.asarray(x.value if isinstance(x, Lazy) else x, object)
            return as_array(whole[tuple(slice(None) if f is None else 0 for f in fix)])
        kept = [n for n, f in zip(np.shape(x), fix) if f is None]
        if not isinstance(x, Lazy) or id(x) in self.buffers:
            buffer, out = self.buffers[id(x)], np.empty(kept, object)
            for kidx in np.ndindex(*kept):
                it = iter(kidx)
                out[kidx] = buffer.load(tuple(next(it) if f is None else f for f in fix))
            return out
        key = (id(x), tuple(f if f is None or isinstance(f, int) else id(f) for f in fix))
        if key not in memo:
            memo[key] = self._slice(x, fix, kept, memo)
        return memo[key]

    def _slice(self, x: Lazy, fix, kept, memo: dict):
        eqn, em = x.eqn, self.em
        name = eqn.primitive.name
        if name == "iota":
            d = eqn.params["dimension"]
            out = np.empty(kept, object)
            if _dynamic(fix[d]):
                out[...] = splat(em, fix[d], x.dtype)
                return out
            at = [k for k in range(x.ndim) if fix[k] is None]
            for kidx in np.ndindex(*kept):
                out[kidx] = np.asarray(kidx[at.index(d)] if d in at else fix[d], x.dtype)[()]
            return out
        if name == "broadcast_in_dim":
            (a,), dims = x.args, eqn.params["broadcast_dimensions"]
            fa = _operand_fix(x, a, fix)
            part = np.asarray(self.at(a, fa, memo), object)
            at = [k for k in range(x.ndim) if fix[k] is None]
            tmp = [1] * len(kept)
            for m, d in enumerate(dims):
                if fa[m] is None:
                    tmp[at.index(d)] = np.shape(a)[m]
            return as_array(np.broadcast_to(part.reshape(tmp), kept))
        args = [self.at(a, _operand_fix(x, a, fix), memo) for a in x.args]
        row = types.SimpleNamespace(
            primitive=eqn.primitive,
            params=eqn.params,
            invars=[_aval(np.shape(a), v.aval.dtype) for a, v in zip(args, eqn.invars)],
            outvars=[_aval(kept, x.dtype)],
            effects=eqn.effects,
        )
        return self.rules[name](em, row, args)


def _add(em: Emitter, dtype, acc, x):
    return (emit_float if dtype.kind == "f" else emit_int)(em, "add", dtype, [acc, em.vec(x, dtype)], None)


def _cost(x, seen: set) -> int:
    """The equations a slice of `x` evaluates (broadcasts and `iota` free)."""
    if not isinstance(x, Lazy) or id(x) in seen:
        return 0
    seen.add(id(x))
    own = x.eqn.primitive.name not in ("broadcast_in_dim", "iota")
    return own + sum(_cost(a, seen) for a in x.args)


def _sums(em: Emitter, out_shape, dtype, out_loops: list, sums) -> np.ndarray:
    """The entries of an output of `out_shape` whose axes `out_loops` (`(axis, size)`) are
    loops (the others computed in their body): `sums(fixes)` gives the body's entries (a list,
    C order) for `fixes`, the outer loops' indices by axis."""
    if not out_loops:
        return as_array(np.asarray(sums({}), object).reshape(out_shape))
    result = Buffer(em, out_shape, dtype)
    fill(em, result, out_loops, sums)
    out = np.empty(out_shape, object)
    for idx in np.ndindex(*out_shape):
        out[idx] = result.load(idx)
    return out


def _identity(dtype):
    return np.asarray(-0.0 if dtype.kind == "f" else 0, dtype)[()]


def reduce_rule(base, rules):
    """`reduce_sum`: loops over the reduced axes of at least `MIN_AXIS` entries that come first
    (the rest summed in the body, in order) and the kept axes of at least `MIN_AXIS` entries,
    where the operand is a `Lazy` that varies along them; else `base` on the entries."""

    def rule(em: Emitter, eqn, args):
        (a,) = args
        axes = sorted(eqn.params["axes"])
        dtype = np.dtype(eqn.outvars[0].aval.dtype)
        red = []
        for d in axes:  # a prefix of the reduced axes: the sums keep their order
            if not isinstance(a, Lazy) or a.shape[d] < MIN_AXIS:
                break
            red.append(d)
        if not red or dtype == np.bool_:
            return base(em, eqn, [materialize(em, a, rules)])
        kept = [d for d in range(a.ndim) if d not in axes]
        out_loops = [(m, a.shape[d]) for m, d in enumerate(kept) if a.shape[d] >= MIN_AXIS]
        looped = set(red) | {kept[m] for m, _ in out_loops}
        slices = _Slices(em, rules)
        pattern = tuple(DYN if d in looped else None for d in range(a.ndim))
        if not slices.loops(a, pattern):
            return base(em, eqn, [materialize(em, a, rules)])
        slices.prepare(a, pattern, a.dtype)
        out_shape = tuple(eqn.outvars[0].aval.shape)
        em.count(slices.entries + math.prod(out_shape))
        body_axes = [d for d in range(a.ndim) if d not in looped]  # the slice's axes
        order = [body_axes.index(d) for d in body_axes if d not in axes]
        order += [body_axes.index(d) for d in body_axes if d in axes]
        size = math.prod(a.shape[d] for d in body_axes if d not in axes)

        def sums(fixes):
            def run(level, fixed, accs):
                if level == len(red):
                    fix = tuple(fixed.get(d) for d in range(a.ndim))
                    part = np.transpose(np.asarray(slices.at(a, fix, {}), object), order).reshape(size, -1)
                    new = []
                    for acc, xs in zip(accs, part):
                        for x in xs:
                            acc = _add(em, dtype, acc, x)
                        new.append(acc)
                    return new
                d = red[level]
                return loop(em, a.shape[d], accs, lambda i, accs: run(level + 1, {**fixed, d: i}, accs))

            init = [em.vec(_identity(dtype), dtype)] * size
            return run(0, {kept[m]: i for m, i in fixes.items()}, init)

        return _sums(em, out_shape, dtype, out_loops, sums)

    return rule


def dot_rule(base, rules):
    """`dot_general` contracting one axis of at least `MIN_AXIS` entries along which a `Lazy`
    operand varies (of one float type): a loop over that axis, each output entry Σ_k l·r from
    the identity in k's order, as the unrolled form (a known factor 1 not multiplied, exact);
    else `base` on the entries."""

    def rule(em: Emitter, eqn, args):
        lhs, rhs = args
        (lc, rc), (lb, rb) = eqn.params["dimension_numbers"]
        dtype = np.dtype(eqn.outvars[0].aval.dtype)
        same = all(np.dtype(v.aval.dtype) == dtype for v in eqn.invars) and dtype.kind == "f"
        lazy = len(lc) == 1 and any(
            isinstance(x, Lazy) and x.shape[c[0]] >= MIN_AXIS for x, c in ((lhs, lc), (rhs, rc))
        )
        if not (same and lazy):
            return base(em, eqn, [materialize(em, x, rules) for x in args])
        n = np.shape(lhs)[lc[0]]
        slices = _Slices(em, rules)
        fixes = [tuple(DYN if d == c[0] else None for d in range(np.ndim(x))) for x, c in ((lhs, lc), (rhs, rc))]
        if not all(slices.loops(x, f) for x, f in zip(args, fixes) if isinstance(x, Lazy)):
            return base(em, eqn, [materialize(em, x, rules) for x in args])
        for x, f in zip(args, fixes):
            slices.prepare(x, f, dtype)
        out_shape = tuple(eqn.outvars[0].aval.shape)
        em.count(slices.entries + math.prod(out_shape))
        nb = len(lb)

        def arrange(part, c, batch, contract):  # a slice's axes as (batch, free)
            ndim = np.ndim(part) + 1
            free = [d for d in range(ndim) if d not in contract and d not in batch]
            less = lambda ds: [d - (d > c) for d in ds]
            return np.transpose(np.asarray(part, object), less(batch) + less(free))

        def body(i, accs):
            memo: dict = {}
            at = lambda x, c: slices.at(x, tuple(i if d == c else None for d in range(np.ndim(x))), memo)
            L = arrange(at(lhs, lc[0]), lc[0], lb, lc)
            R = arrange(at(rhs, rc[0]), rc[0], rb, rc)
            nl = L.ndim - nb
            new = []
            for idx, acc in zip(np.ndindex(*out_shape), accs):
                p = product(em, L[idx[: nb + nl]], R[idx[:nb] + idx[nb + nl :]], dtype)
                new.append(_add(em, dtype, acc, p))
            return new

        init = [em.vec(_identity(dtype), dtype)] * math.prod(out_shape)
        return as_array(np.asarray(loop(em, n, init, body), object).reshape(out_shape))

    return rule
