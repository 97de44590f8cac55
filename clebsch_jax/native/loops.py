"""Dense linear algebra of larger matrices as LLVM loops over entries held in stack arrays.

Unrolled entry by entry (`clebsch_jax.native.linalg`), an n×n LU factorisation is of the order
of n³ instructions (its row swaps, selected per lane, as many as its eliminations), and a
member with a few such matrices outgrows a kernel. Here the same algorithms run as loops: the
matrix's entries are stored into an alloca of `<W x T>` vectors (`Stack`), indexed by the loop
counters, and read back after the loops. Every operation is the unrolled form's, in the same
order (LAPACK's, as XLA's CPU backend computes it): the pivot of each column chosen per lane
(the first row of largest magnitude), rows swapped lane by lane (a select per entry, in the
rows some lane picked), the same substitutions in index order. So the results are the unrolled
form's, bit for bit, and XLA's to round-off.

Which matrices loop is a function of their shapes alone (`loops_lu`, …), so that the entries a
program translates to can be counted from its jaxpr (`control.entries`); a looped form counts
the entries it stores into its stack arrays and the instructions of its loop bodies, once
(`extra_entries`), on top of its outputs, which every equation counts.
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir

from .elementwise import emit_float
from .values import Emitter

__all__ = ["LOOP_MIN_SIZE", "DOT_LOOP_PRODUCTS", "looped", "extra_entries", "Stack", "for_range"]
__all__ += ["lu", "triangular_solve", "cholesky", "dot"]

LOOP_MIN_SIZE = 12
"""Factorisations and triangular solves of matrices of at least this order run as loops;
smaller ones stay unrolled (no memory, known entries folded). `benchmarks/README.md` (section
of `native.py`) has the measurement behind it."""

DOT_LOOP_PRODUCTS = 1024
"""A contraction of at least this many products (and a contracted size of at least
`LOOP_MIN_SIZE`) runs as loops."""

_I64 = ir.IntType(64)


def looped(eqn) -> bool:
    """Whether the translation emits `eqn` (lu, triangular_solve, cholesky, dot_general) as
    loops: float matrices (no batch of them) of at least `LOOP_MIN_SIZE` rows, contractions
    of at least `DOT_LOOP_PRODUCTS` float products. A function of the shapes alone."""
    name = eqn.primitive.name
    if name not in _BODY:
        return False
    avals = [v.aval for v in eqn.invars]
    if any(np.dtype(a.dtype).kind != "f" for a in avals):
        return False
    if name in ("lu", "cholesky"):
        return avals[0].ndim == 2 and min(avals[0].shape) >= LOOP_MIN_SIZE
    if name == "triangular_solve":
        return avals[0].ndim == 2 and avals[1].ndim == 2 and avals[0].shape[0] >= LOOP_MIN_SIZE
    if name == "dot_general":
        if np.dtype(avals[0].dtype) != np.dtype(avals[1].dtype):
            return False
        (lc, _), _ = eqn.params["dimension_numbers"]
        k = int(np.prod([avals[0].shape[d] for d in lc], dtype=int))
        out = int(np.prod(eqn.outvars[0].aval.shape, dtype=int))
        return k >= LOOP_MIN_SIZE and out * k >= DOT_LOOP_PRODUCTS
    return False


def extra_entries(eqn) -> int:
    """The entries a looped `eqn` counts besides its outputs: the entries it stores into its
    stack arrays and the instructions of its loop bodies, once. 0 for an unrolled one."""
    if not looped(eqn):
        return 0
    name = eqn.primitive.name
    sizes = [int(np.prod(v.aval.shape, dtype=int)) for v in eqn.invars]
    if name == "lu":
        m = eqn.invars[0].aval.shape[0]
        return sizes[0] + m + _BODY["lu"]
    if name == "dot_general":
        return sizes[0] + sizes[1] + _BODY[name]
    return sum(sizes) + _BODY[name]


_BODY = {"lu": 200, "triangular_solve": 100, "cholesky": 150, "dot_general": 120}
"""Instructions of each looped form's loop bodies and counters, counted once: bounds of the
lines of IR that do not grow with the matrix (read off kernels of orders 12, 16 and 20)."""


class Stack:
    """An alloca of `<W x T>` vectors holding the entries of an array of `shape` in C order,
    addressed by indices that are Python ints or i64 values (loop counters)."""

    def __init__(self, em: Emitter, shape, dtype):
        self.em, self.shape, self.dtype = em, tuple(shape), np.dtype(dtype)
        self.vt = em.vtype(dtype)
        self.t = ir.ArrayType(self.vt, max(1, int(np.prod(self.shape, dtype=int))))
        self.ptr = em.alloca(self.t)
        self.strides = [int(np.prod(self.shape[d + 1 :], dtype=int)) for d in range(len(self.shape))]

    def at(self, *idx):
        b = self.em.b
        flat = None
        for i, s in zip(idx, self.strides):
            term = ir.Constant(_I64, i * s) if isinstance(i, int) else (i if s == 1 else b.mul(i, ir.Constant(_I64, s)))
            flat = term if flat is None else b.add(flat, term)
        return b.bitcast(b.gep(self.ptr, [ir.Constant(_I64, 0), flat], source_etype=self.t), self.vt.as_pointer())

    def load(self, *idx):
        return self.em.b.load(self.at(*idx), typ=self.vt)

    def store(self, value, *idx):
        self.em.b.store(value, self.at(*idx))

    def fill(self, entries) -> None:
        """Store every entry of an object array of this shape (known ones as constants)."""
        for idx in np.ndindex(self.shape):
            self.store(self.em.vec(entries[idx], self.dtype), *idx)

    def read(self, only=None) -> np.ndarray:
        """The entries as an object array of loads (`only(idx)` False: the entry is not read)."""
        out = np.empty(self.shape, object)
        for idx in np.ndindex(self.shape):
            out[idx] = self.load(*idx) if only is None or only(idx) else None
        return out


def for_range(em: Emitter, lo, hi, body, reverse: bool = False) -> None:
    """`body(i)` for i = lo … hi - 1 (i an i64; `reverse`: from hi - 1 down to lo), as a loop
    whose counter lives in an alloca. `lo`, `hi`: Python ints or i64 values."""
    b = em.b
    lo = ir.Constant(_I64, lo) if isinstance(lo, int) else lo
    hi = ir.Constant(_I64, hi) if isinstance(hi, int) else hi
    counter = em.alloca(_I64)
    b.store(lo, counter)
    fn = b.function
    head, block, done = (fn.append_basic_block(f"for.{s}") for s in ("head", "body", "done"))
    b.branch(head)
    b.position_at_end(head)
    k = b.load(counter, typ=_I64)
    b.cbranch(b.icmp_signed("<", k, hi), block, done)
    b.position_at_end(block)
    body(b.sub(b.add(lo, b.sub(hi, ir.Constant(_I64, 1))), k) if reverse else k)
    b.store(b.add(b.load(counter, typ=_I64), ir.Constant(_I64, 1)), counter)
    b.branch(head)
    b.position_at_end(done)


class _Var:
    """A vector variable of the loops (an alloca in the entry block)."""

    def __init__(self, em: Emitter, dtype, value):
        self.em, self.vt = em, em.vtype(dtype)
        self.ptr = em.alloca(self.vt)
        em.b.store(em.vec(value, dtype), self.ptr)

    def get(self):
        return self.em.b.load(self.ptr, typ=self.vt)

    def set(self, value) -> None:
        self.em.b.store(value, self.ptr)


def _splat_index(em: Emitter, i, dtype):
    """The i64 counter `i` as a vector of `dtype` (an integer type) in every lane."""
    b = em.b
    vt = em.vtype(dtype)
    x = b.trunc(i, vt.element) if vt.element.width < 64 else i
    one = b.insert_element(ir.Constant(vt, ir.Undefined), x, ir.Constant(ir.IntType(32), 0))
    return b.shuffle_vector(
        one, ir.Constant(vt, ir.Undefined), ir.Constant(ir.VectorType(ir.IntType(32), em.W), [0] * em.W)
    )


def lu(em: Emitter, a, dtype, idx_dtype):
    """`lu` of the m×n entry array `a` as loops: (LU, pivots, permutation), the unrolled form's."""
    b = em.b
    m, n = a.shape
    f = lambda name, *xs: emit_float(em, name, dtype, list(xs), None)
    A = Stack(em, (m, n), dtype)
    A.fill(a)
    perm = Stack(em, (m,), idx_dtype)
    perm.fill(np.asarray([np.asarray(i, idx_dtype)[()] for i in range(m)], object))
    piv = Stack(em, (min(m, n),), idx_dtype)
    best, where = _Var(em, dtype, 0.0), _Var(em, idx_dtype, 0)

    def column(j):
        # the pivot: the first row of largest |a_ij| at or below the diagonal (LAPACK's idamax)
        best.set(f("abs", A.load(j, j)))
        where.set(_splat_index(em, j, idx_dtype))

        def search(i):
            v = f("abs", A.load(i, j))
            better = b.fcmp_ordered(">", v, best.get())
            best.set(b.select(better, v, best.get()))
            where.set(b.select(better, _splat_index(em, i, idx_dtype), where.get()))

        below = b.add(j, ir.Constant(_I64, 1))
        for_range(em, below, m, search)
        w = where.get()
        piv.store(w, j)

        # swap rows j and the pivot's, lane by lane, in the rows some lane picked
        def swap(i):
            hit = b.icmp_signed("==", w, _splat_index(em, i, idx_dtype))
            fn = b.function
            yes, after = fn.append_basic_block("swap.rows"), fn.append_basic_block("swap.done")
            b.cbranch(em.any_lane(hit), yes, after)
            b.position_at_end(yes)

            def entry(k):
                aj, ai = A.load(j, k), A.load(i, k)
                A.store(b.select(hit, ai, aj), j, k)
                A.store(b.select(hit, aj, ai), i, k)

            for_range(em, 0, n, entry)
            pj, pi = perm.load(j), perm.load(i)
            perm.store(b.select(hit, pi, pj), j)
            perm.store(b.select(hit, pj, pi), i)
            b.branch(after)
            b.position_at_end(after)

        for_range(em, below, m, swap)

        # eliminate below the pivot
        def eliminate(i):
            lij = f("div", A.load(i, j), A.load(j, j))
            A.store(lij, i, j)
            for_range(em, below, n, lambda k: A.store(f("sub", A.load(i, k), f("mul", lij, A.load(j, k))), i, k))

        for_range(em, below, m, eliminate)

    for_range(em, 0, min(m, n), column)
    return [A.read(), piv.read(), perm.read()]


def triangular_solve(em: Emitter, A, B, dtype, lower: bool, unit: bool):
    """X with op(A) X = B (A n×n, B n×c entry arrays, `lower` after any transposition) as
    loops, the unrolled form's substitutions in the same order."""
    b = em.b
    n, c = B.shape
    f = lambda name, *xs: emit_float(em, name, dtype, list(xs), None)
    SA = Stack(em, (n, n), dtype)
    SA.fill(A)
    X = Stack(em, (n, c), dtype)  # B, overwritten by X row by row
    X.fill(B)
    s = _Var(em, dtype, 0.0)

    def solve_column(col):
        def row(i):
            s.set(X.load(i, col))

            def term(k):
                s.set(f("sub", s.get(), f("mul", SA.load(i, k), X.load(k, col))))

            if lower:
                for_range(em, 0, i, term)
            else:
                for_range(em, b.add(i, ir.Constant(_I64, 1)), n, term)
            X.store(s.get() if unit else f("div", s.get(), SA.load(i, i)), i, col)

        for_range(em, 0, n, row, reverse=not lower)

    for_range(em, 0, c, solve_column)
    return X.read()


def cholesky(em: Emitter, a, dtype):
    """The lower Cholesky factor of the n×n entry array `a` as loops (the unrolled form's
    order; the strictly upper entries are zero, known)."""
    b = em.b
    n = a.shape[0]
    f = lambda name, *xs: emit_float(em, name, dtype, list(xs), None)
    L = Stack(em, (n, n), dtype)  # the lower triangle of a, overwritten by L column by column
    for idx in np.ndindex((n, n)):
        if idx[1] <= idx[0]:
            L.store(em.vec(a[idx], dtype), *idx)
    s = _Var(em, dtype, 0.0)

    def column(j):
        s.set(L.load(j, j))
        for_range(em, 0, j, lambda k: s.set(f("sub", s.get(), f("mul", L.load(j, k), L.load(j, k)))))
        L.store(f("sqrt", s.get()), j, j)  # NaN for a matrix that is not positive definite

        def row(i):
            s.set(L.load(i, j))
            for_range(em, 0, j, lambda k: s.set(f("sub", s.get(), f("mul", L.load(i, k), L.load(j, k)))))
            L.store(f("div", s.get(), L.load(j, j)), i, j)

        for_range(em, b.add(j, ir.Constant(_I64, 1)), n, row)

    for_range(em, 0, n, column)
    out = L.read(only=lambda idx: idx[1] <= idx[0])
    out[np.triu_indices(n, 1)] = np.zeros((), dtype)[()]
    return out


def dot(em: Emitter, L, R, dtype):
    """Σ_k L[b, i, k]·R[b, j, k] for entry arrays L (nb, ni, K) and R (nb, nj, K) as loops:
    out (nb, ni, nj), each sum in k's order from the first product, as the unrolled form."""
    nb, ni, K = L.shape
    nj = R.shape[1]
    f = lambda name, *xs: emit_float(em, name, dtype, list(xs), None)
    SL, SR = Stack(em, L.shape, dtype), Stack(em, R.shape, dtype)
    SL.fill(L)
    SR.fill(R)
    out = Stack(em, (nb, ni, nj), dtype)
    acc = _Var(em, dtype, 0.0)

    def entry(bi, i, j):
        acc.set(f("mul", SL.load(bi, i, 0), SR.load(bi, j, 0)))
        for_range(em, 1, K, lambda k: acc.set(f("add", acc.get(), f("mul", SL.load(bi, i, k), SR.load(bi, j, k)))))
        out.store(acc.get(), bi, i, j)

    for_range(em, 0, nb, lambda bi: for_range(em, 0, ni, lambda i: for_range(em, 0, nj, lambda j: entry(bi, i, j))))
    return out.read()
