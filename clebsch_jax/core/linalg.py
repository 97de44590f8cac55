"""Small dense linear algebra that XLA can fuse.

On CPU, `jnp.linalg.solve` on a 3×3 matrix is a LAPACK custom call with fixed overhead that
dwarfs the arithmetic, and under `vmap` it becomes a batched call that is slower still. For
n ≤ 3 the adjugate formulas below are a handful of multiply-adds that fuse with the
surrounding code; larger systems eliminate with partial pivoting in XLA operations
(straight-line up to `ELIMINATION_MAX`, the `lu_factor` loop above), never LAPACK: jaxlib's
batched LAPACK kernels (LU, SVD, triangular solves) run on XLA's intra-op thread pool and
deadlock when two host devices call them side by side (a sweep with `devices=2`), and even on
one device for a batched Cholesky solve. `spd_solve` calls LAPACK for one matrix and XLA
operations for a batch. The matrices solved here (Cayley factors I ± X/2, group elements near
I, Newton Jacobians of small steps) are well conditioned, where the adjugate formula is as
accurate as LU (the tests compare them).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = [
    "inv",
    "solve",
    "spd_solve",
    "cholesky",
    "cholesky_solve",
    "factor",
    "inverse",
    "solve_factored",
    "lu_factor",
    "lu_solve",
    "matmul",
    "matvec",
    "weighted_sum",
]

CLOSED_FORM_MAX = 3

UNROLL_MAX = 4
"""`matmul` and `matvec` write contractions over at most this many terms as multiply-adds."""


def matmul(A: jax.Array, B: jax.Array) -> jax.Array:
    """A @ B for matrices (broadcasting leading axes).

    For an inner dimension ≤ `UNROLL_MAX` the product is a sum of outer products of columns
    and rows: elementwise multiply-adds, which XLA fuses with the surrounding elementwise code.
    XLA on CPU emits every small matrix product as its own unfused dot, whose fixed cost
    dominates a 3×3 computation. (Chains of such products fused into one kernel recompute
    their operands, so this pays for short chains, not for long ones.)"""
    k = A.shape[-1]
    if k > UNROLL_MAX:
        return A @ B
    out = A[..., :, 0:1] * B[..., 0:1, :]
    for i in range(1, k):
        out = out + A[..., :, i : i + 1] * B[..., i : i + 1, :]
    return out


def weighted_sum(terms, dtype):
    """Σ c·t over the (Python float c, array t) pairs `terms`, left to right; a coefficient ±1
    multiplies nothing; 0 (of `dtype`) for no terms. Sums with constant coefficients (sparse
    maps, polynomial terms, Runge–Kutta stage combinations) written as multiply-adds that XLA
    fuses with their neighbours."""
    acc = None
    for c, t in terms:
        t = t if c == 1.0 else (-t if c == -1.0 else c * t)
        acc = t if acc is None else acc + t
    return jnp.zeros((), dtype) if acc is None else acc


def matvec(A: jax.Array, v: jax.Array) -> jax.Array:
    """A v (broadcasting leading axes), unrolled like `matmul` for small sizes."""
    k = A.shape[-1]
    if k > UNROLL_MAX:
        return jnp.einsum("...ij,...j->...i", A, v)
    out = A[..., :, 0] * v[..., None, 0]
    for i in range(1, k):
        out = out + A[..., :, i] * v[..., None, i]
    return out


def _adjugate_and_det(A: jax.Array):
    n = A.shape[-1]
    if n == 1:
        return jnp.ones_like(A), A[..., 0, 0]
    if n == 2:
        a, b, c, d = A[..., 0, 0], A[..., 0, 1], A[..., 1, 0], A[..., 1, 1]
        adj = jnp.stack([jnp.stack([d, -b], -1), jnp.stack([-c, a], -1)], -2)
        return adj, a * d - b * c
    # n == 3: rows of the adjugate are cross products of the columns
    c0, c1, c2 = A[..., :, 0], A[..., :, 1], A[..., :, 2]
    r0, r1, r2 = jnp.cross(c1, c2), jnp.cross(c2, c0), jnp.cross(c0, c1)
    adj = jnp.stack([r0, r1, r2], axis=-2)
    return adj, jnp.sum(c0 * r0, axis=-1)


def inv(A: jax.Array) -> jax.Array:
    """Matrix inverse (adjugate / determinant for n ≤ 3, elimination otherwise: `_lu_apply`)."""
    if A.shape[-1] <= CLOSED_FORM_MAX:
        adj, d = _adjugate_and_det(A)
        return adj / d[..., None, None]
    return _lu_apply(A, jnp.broadcast_to(jnp.eye(A.shape[-1], dtype=A.dtype), A.shape))


def solve(A: jax.Array, B: jax.Array, *, unroll: bool = False) -> jax.Array:
    """Solve A X = B for a matrix or a vector B (closed form for n ≤ 3, elimination otherwise:
    `_lu_apply`).

    `unroll`: write the closed form's products with `matmul`/`matvec` (fusible multiply-adds)
    instead of dot operations; same formula, rounding may differ in the last bit.

    The closed form is followed by one step of iterative refinement, X += A⁻¹(B − AX): the
    rounding of the computed determinant otherwise scales every solution by the same 1 + O(ε),
    a bias that a march accumulates (Q drifted off SO(3) linearly in the number of steps);
    after refinement the error is second order, as with pivoted LU."""
    if A.shape[-1] <= CLOSED_FORM_MAX:
        adj, d = _adjugate_and_det(A)
        vec = B.ndim == A.ndim - 1
        if unroll:
            product = matvec if vec else matmul
        else:
            product = (lambda M, v: jnp.einsum("...ij,...j->...i", M, v)) if vec else (lambda M, v: M @ v)
        scale = d[..., None] if vec else d[..., None, None]
        X = product(adj, B) / scale
        return X + product(adj, B - product(A, X)) / scale
    return _lu_apply(A, B)


ELIMINATION_MAX = 8
"""Up to this size `solve` and `inv` eliminate in straight-line code (`_eliminate`); above, the
`lu_factor` loop."""


def _eliminate(a: jax.Array, b: jax.Array) -> jax.Array:
    """a⁻¹b for one small a (n, n) and b (n, k): Gaussian elimination with partial pivoting,
    unrolled over the n columns, the row swaps written as arithmetic with one-hot rows (no
    gather), then back substitution.

    The pivots and the elimination factors are computed from a alone and applied to b, so the
    result is linear in b as JAX sees it: reverse mode can transpose it when b is a tangent (the
    implicit derivative's tangent solve, `clebsch_jax.roots.implicit`), which the elimination of
    the augmented matrix [a | b] could not (its divisions read rows that held b)."""
    n = a.shape[-1]
    U, X = a, b
    rows = jnp.arange(n)
    for k in range(n):
        col = jnp.where(rows >= k, jnp.abs(U[:, k]), -1.0)
        hot = (rows == jnp.argmax(col)).astype(U.dtype)  # the pivot's row
        swap = (rows == k).astype(U.dtype) - hot
        # swap rows k and p (none if p = k)
        U = U + swap[:, None] * (hot @ U - U[k])[None, :]
        X = X + swap[:, None] * (hot @ X - X[k])[None, :]
        pivot = U[k, k]
        factors = jnp.where(rows > k, U[:, k] / jnp.where(pivot == 0.0, 1.0, pivot), 0.0)
        U = U - factors[:, None] * U[k][None, :]
        X = X - factors[:, None] * X[k][None, :]
    out = [None] * n
    for i in reversed(range(n)):
        acc = X[i]
        for j in range(i + 1, n):
            acc = acc - U[i, j] * out[j]
        out[i] = acc / U[i, i]
    return jnp.stack(out)


def cholesky(K: jax.Array) -> jax.Array:
    """The lower Cholesky factor L (L Lᵀ = K) of one symmetric positive definite K (n, n) in XLA
    operations: a `fori_loop` over the columns (one compiled body whatever n; straight-line code
    compiled several times slower in differentiated marches), reading K's lower triangle; NaN
    where K is not numerically positive definite (a pivot's square root of a negative number)."""
    K = jnp.asarray(K)
    n = K.shape[-1]
    idx = jnp.arange(n)

    def column(j, L):
        row = jnp.where(idx < j, L[j], 0.0)  # L[j, :j]
        d = jnp.sqrt(K[j, j] - jnp.sum(row * row))
        col = (K[:, j] - L @ row) / d
        return jnp.where(idx[None, :] == j, jnp.where(idx > j, col, jnp.where(idx == j, d, 0.0))[:, None], L)

    return jax.lax.fori_loop(0, n, column, jnp.zeros_like(K))


def cholesky_solve(L: jax.Array, b: jax.Array) -> jax.Array:
    """(L Lᵀ)⁻¹b for a lower Cholesky factor L (n, n) and b of shape (n, ...): two triangular
    solves in XLA operations, each a `fori_loop` over the rows."""
    L, b = jnp.asarray(L), jnp.asarray(b)
    n = L.shape[-1]
    idx = jnp.arange(n)
    rhs = b.reshape(n, -1)

    def forward(i, y):  # L y = b, row i
        yi = (rhs[i] - jnp.where(idx < i, L[i], 0.0) @ y) / L[i, i]
        return jnp.where((idx == i)[:, None], yi[None, :], y)

    def backward(k, x):  # Lᵀ x = y, row i = n - 1 - k
        i = n - 1 - k
        xi = (x[i] - jnp.where(idx > i, L[:, i], 0.0) @ x) / L[i, i]
        return jnp.where((idx == i)[:, None], xi[None, :], x)

    y = jax.lax.fori_loop(0, n, forward, jnp.zeros_like(rhs))
    return jax.lax.fori_loop(0, n, backward, y).reshape(b.shape)


@jax.custom_batching.custom_vmap
def _cholesky_factor(K: jax.Array) -> jax.Array:
    return jax.lax.linalg.cholesky(K, symmetrize_input=False)


@_cholesky_factor.def_vmap
def _cholesky_factor_batched(axis_size, in_batched, K):
    del axis_size, in_batched
    return jax.vmap(cholesky)(K), True


@jax.custom_batching.custom_vmap
def _cholesky_apply(L: jax.Array, b: jax.Array) -> jax.Array:
    return jax.scipy.linalg.cho_solve((L, True), b)


@_cholesky_apply.def_vmap
def _cholesky_apply_batched(axis_size, in_batched, L, b):
    if not in_batched[0]:  # one factor, many right-hand sides (a Jacobian's tangents): one call
        columns = jnp.moveaxis(b, 0, -1)
        x = _cholesky_apply(L, columns.reshape(columns.shape[0], -1)).reshape(columns.shape)
        return jnp.moveaxis(x, -1, 0), True
    b = b if in_batched[1] else jnp.broadcast_to(b, (axis_size,) + b.shape)
    return jax.vmap(cholesky_solve)(L, b), True


def spd_solve(K: jax.Array, b: jax.Array) -> jax.Array:
    """K⁻¹b for one symmetric positive definite K (n, n) and b of shape (n, ...) by Cholesky;
    NaN where K is not numerically positive definite.

    One K is factored and solved by LAPACK (with many right-hand sides at once when only b is
    batched, as in `jax.jacfwd`); when K is batched by `jax.vmap` the factor and the triangular
    solves are `cholesky` and `cholesky_solve`, XLA operations
    (`jax.custom_batching.custom_vmap`): jaxlib's batched LAPACK triangular solve deadlocked a
    sweep of 2048 peakon systems on one device. Derivatives are implicit
    (`jax.lax.custom_linear_solve`): the tangent of x = K⁻¹b is K⁻¹(ḃ − K̇x), solved with the
    same factor, so no derivative of any order runs through the factorisation."""
    K, b = jnp.asarray(K), jnp.asarray(b)
    L = _cholesky_factor(jax.lax.stop_gradient(K))
    return jax.lax.custom_linear_solve(lambda x: K @ x, b, lambda _, r: _cholesky_apply(L, r), symmetric=True)


def _lu_apply(A: jax.Array, B: jax.Array) -> jax.Array:
    """A⁻¹B by `_eliminate` (n ≤ `ELIMINATION_MAX`) or `lu_factor` / `lu_solve` (B a vector or
    a matrix; leading axes broadcast)."""
    vec = B.ndim == A.ndim - 1
    lead = jnp.broadcast_shapes(A.shape[:-2], B.shape[:-1] if vec else B.shape[:-2])
    A = jnp.broadcast_to(A, lead + A.shape[-2:])
    B = jnp.broadcast_to(B, lead + B.shape[-1 if vec else -2 :])

    def one(a, b):
        if a.shape[-1] <= ELIMINATION_MAX:
            x = _eliminate(a, b[:, None] if vec else b)
            return x[:, 0] if vec else x
        fac = lu_factor(a)
        return lu_solve(fac, b) if vec else jax.vmap(lambda col: lu_solve(fac, col), in_axes=1, out_axes=1)(b)

    for _ in lead:
        one = jax.vmap(one)
    return one(A, B)


def factor(A: jax.Array, fence: bool = False):
    """Factor A once for repeated solves: the inverse (n ≤ 3) or LU. Returns (factor, singular).
    `fence`: the closed form's adjugate and determinant are formed behind an
    `optimization_barrier` (`clebsch_jax.roots.newton.fence`)."""
    n = A.shape[-1]
    eps = jnp.finfo(A.dtype).eps
    if n <= CLOSED_FORM_MAX:
        adj, d = _adjugate_and_det(A)
        if fence:
            adj, d = jax.lax.optimization_barrier((adj, d))
        bound = jnp.prod(jnp.linalg.norm(A, axis=-1), axis=-1)
        # one reciprocal and n² products, not n² divisions: XLA copies the determinant (cheap
        # arithmetic) into every consumer, so each entry's division would recompute it and A
        # (in a batch of rows, the whole Jacobian for every entry); the reciprocal, a division,
        # is computed once and read (the entries differ from adj / d in the last bit, which
        # a chord matrix may: the iteration's fixed point is set by the residual)
        return adj * (1 / d)[..., None, None], jnp.abs(d) <= n * eps * bound
    lu, perm = lu_factor(A)
    pivots = jnp.abs(jnp.diagonal(lu, axis1=-2, axis2=-1))
    return (lu, perm), jnp.min(pivots, axis=-1) <= n * eps * jnp.max(pivots, axis=-1)


def inverse(A: jax.Array, fence: bool = False):
    """Explicit inverse (closed form for n ≤ 3, LU otherwise) and the singularity flag of
    `factor` (`fence` as there). Returns (inverse, singular)."""
    fac, singular = factor(A, fence)
    if isinstance(fac, tuple):
        eye = jnp.eye(A.shape[-1], dtype=A.dtype)
        return jax.vmap(lambda e: lu_solve(fac, e), out_axes=-1)(eye), singular
    return fac, singular


def solve_factored(fac, b: jax.Array) -> jax.Array:
    """Solve with the result of `factor`."""
    if isinstance(fac, tuple):
        return lu_solve(fac, b)
    return jnp.einsum("...ij,...j->...i", fac, b)


def lu_factor(A: jax.Array):
    """LU with partial pivoting in plain XLA operations (a `fori_loop` over columns).

    Used instead of LAPACK inside the march: batched LAPACK calls on CPU are slow for small
    matrices and, in jaxlib 0.10, were seen to hang in large `vmap`ped runs; this loop batches
    as ordinary elementwise work. Returns (LU packed in one matrix, row permutation)."""
    n = A.shape[-1]
    rows = jnp.arange(n)

    def step(k, state):
        M, perm = state
        col = jnp.where(rows >= k, jnp.abs(M[:, k]), -1.0)
        p = jnp.argmax(col)
        swap = jnp.where(rows == k, p, jnp.where(rows == p, k, rows))
        M, perm = M[swap], perm[swap]
        pivot = M[k, k]
        safe = jnp.where(pivot == 0.0, 1.0, pivot)  # an exact zero pivot: flagged by `factor`
        factors = jnp.where(rows > k, M[:, k] / safe, 0.0)
        M = M - factors[:, None] * jnp.where(rows > k, M[k], 0.0)[None, :]
        M = M.at[:, k].set(jnp.where(rows > k, factors, M[:, k]))
        return M, perm

    return jax.lax.fori_loop(0, n, step, (A, rows))


def lu_solve(fac, b: jax.Array) -> jax.Array:
    """Solve with `lu_factor`'s result by forward and back substitution."""
    M, perm = fac
    n = M.shape[-1]
    rows = jnp.arange(n)
    y = b[perm]
    y = jax.lax.fori_loop(0, n, lambda i, y: y.at[i].add(-jnp.sum(jnp.where(rows < i, M[i], 0.0) * y)), y)

    def back(j, x):
        i = n - 1 - j
        return x.at[i].set((x[i] - jnp.sum(jnp.where(rows > i, M[i], 0.0) * x)) / M[i, i])

    return jax.lax.fori_loop(0, n, back, y)
