"""Dense linear algebra of the native translation: small matrices unrolled entry by entry.

The primitives `jax.numpy.linalg` and `jax.scipy.linalg` use for a member's matrices:
`lu` (partial pivoting, the pivot chosen per lane by selects), `triangular_solve`,
`cholesky` and `custom_linear_solve` (its `solve` jaxpr). Each is written as XLA's CPU
backend computes it (LAPACK's algorithms) to round-off: the same pivots, the same
substitutions, in index order. Matrices of `loops.LOOP_MIN_SIZE` rows or more run the same
algorithms as loops over stack arrays (`clebsch_jax.native.loops`), which count the entries
they store and their loop bodies on top of their outputs (`loops.extra_entries`).
"""

from __future__ import annotations

import numpy as np

from . import loops
from .elementwise import emit_float, emit_int
from .lower import RULES, eval_closed
from .values import Emitter, Unsupported, is_known

__all__: list = []


class _Ops:
    """Arithmetic on entries (known or emitted) of one dtype."""

    def __init__(self, em: Emitter, dtype):
        self.em, self.dtype = em, np.dtype(dtype)
        self._emit = emit_float if self.dtype.kind == "f" else emit_int

    def op(self, name, *xs):
        if all(is_known(x) for x in xs):
            import numpy

            f = {
                "add": numpy.add,
                "sub": numpy.subtract,
                "mul": numpy.multiply,
                "div": numpy.divide,
                "abs": numpy.abs,
                "sqrt": numpy.sqrt,
                "gt": numpy.greater,
                "neg": numpy.negative,
            }[name]
            with numpy.errstate(all="ignore"):
                return numpy.asarray(f(*[numpy.asarray(x, self.dtype) for x in xs]))[()]
        return self._emit(self.em, name, self.dtype, list(xs), None)

    def select(self, cond, a, b):
        return self.em.select(cond, a, b, self.dtype)


def _lu(em: Emitter, eqn, args):
    (a,) = args
    m, n = a.shape[-2:]
    if a.ndim != 2:
        raise Unsupported("lu of a batch of matrices")
    dtype = np.dtype(eqn.outvars[0].aval.dtype)
    idx_dtype = np.dtype(eqn.outvars[1].aval.dtype)
    if loops.looped(eqn):
        em.count(loops.extra_entries(eqn))
        return loops.lu(em, a, dtype, idx_dtype)
    o = _Ops(em, dtype)
    A = a.copy()
    perm = np.empty(m, object)
    for i in range(m):
        perm[i] = np.asarray(i, idx_dtype)[()]
    pivots = np.empty(min(m, n), object)
    for j in range(min(m, n)):
        # the pivot: the first row of largest |a_ij| at or below the diagonal (LAPACK's idamax)
        best, where = o.op("abs", A[j, j]), np.asarray(j, idx_dtype)[()]
        for i in range(j + 1, m):
            v = o.op("abs", A[i, j])
            better = o.op("gt", v, best)
            best, where = o.select(better, v, best), em.select(better, np.asarray(i, idx_dtype)[()], where, idx_dtype)
        pivots[j] = where
        # swap rows j and the pivot's, lane by lane
        row_j = A[j].copy()
        perm_j = perm[j]
        for i in range(j + 1, m):
            hit = _equals(em, where, i, idx_dtype)
            if is_known(hit) and not hit:
                continue
            for k in range(n):
                A[j, k] = em.select(hit, A[i, k], A[j, k], dtype)
                A[i, k] = em.select(hit, row_j[k], A[i, k], dtype)
            perm[j] = em.select(hit, perm[i], perm[j], idx_dtype)
            perm[i] = em.select(hit, perm_j, perm[i], idx_dtype)
        # eliminate below the pivot
        for i in range(j + 1, m):
            A[i, j] = o.op("div", A[i, j], A[j, j])
            for k in range(j + 1, n):
                A[i, k] = o.op("sub", A[i, k], o.op("mul", A[i, j], A[j, k]))
    return [A, pivots, perm]


def _equals(em: Emitter, x, v: int, dtype):
    if is_known(x):
        return np.asarray(int(x) == v)[()]
    return em.b.icmp_signed("==", x, em.const(v, dtype))


def _triangular_solve(em: Emitter, eqn, args):
    a, b = args
    p = eqn.params
    if a.ndim != 2 or b.ndim != 2:
        raise Unsupported("triangular_solve of a batch of matrices")
    if p.get("conjugate_a", False) and np.dtype(eqn.invars[0].aval.dtype).kind == "c":
        raise Unsupported("triangular_solve of a complex conjugate")
    dtype = np.dtype(eqn.outvars[0].aval.dtype)
    o = _Ops(em, dtype)
    A = a.T if p["transpose_a"] else a
    lower = p["lower"] != bool(p["transpose_a"])
    unit = p["unit_diagonal"]
    left = p["left_side"]
    # op(A) X = B (left) or X op(A) = B (right, as the transposed left system)
    if not left:
        A, lower, b = A.T, not lower, b.T
    n = A.shape[0]
    if loops.looped(eqn):
        em.count(loops.extra_entries(eqn))
        X = loops.triangular_solve(em, A, b, dtype, lower, unit)
        return X if left else X.T
    X = np.empty(b.shape, object)
    order = range(n) if lower else range(n - 1, -1, -1)
    for c in range(b.shape[1]):
        for i in order:
            s = b[i, c]
            ks = range(i) if lower else range(i + 1, n)
            for k in ks:
                s = o.op("sub", s, o.op("mul", A[i, k], X[k, c]))
            X[i, c] = s if unit else o.op("div", s, A[i, i])
    return X if left else X.T


def _cholesky(em: Emitter, eqn, args):
    (a,) = args
    if a.ndim != 2:
        raise Unsupported("cholesky of a batch of matrices")
    dtype = np.dtype(eqn.outvars[0].aval.dtype)
    if loops.looped(eqn):
        em.count(loops.extra_entries(eqn))
        return loops.cholesky(em, a, dtype)
    o = _Ops(em, dtype)
    n = a.shape[0]
    L = np.empty((n, n), object)
    zero = np.zeros((), dtype)[()]
    L[...] = zero
    for j in range(n):
        s = a[j, j]
        for k in range(j):
            s = o.op("sub", s, o.op("mul", L[j, k], L[j, k]))
        L[j, j] = o.op("sqrt", s)  # NaN for a matrix that is not positive definite
        for i in range(j + 1, n):
            t = a[i, j]
            for k in range(j):
                t = o.op("sub", t, o.op("mul", L[i, k], L[j, k]))
            L[i, j] = o.op("div", t, L[j, j])
    return L


def _custom_linear_solve(em: Emitter, eqn, args):
    lengths = eqn.params["const_lengths"]
    jaxprs = eqn.params["jaxprs"]
    start = lengths.matvec + lengths.vecmat
    consts = list(args[start : start + lengths.solve])
    rest = list(args[sum(lengths) :])
    return eval_closed(em, jaxprs.solve, consts + rest)


RULES.update(lu=_lu, triangular_solve=_triangular_solve, cholesky=_cholesky, custom_linear_solve=_custom_linear_solve)
