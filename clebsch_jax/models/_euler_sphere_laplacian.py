r"""The Hoppe–Yau Laplacian $\Delta_N$ of the Euler–Zeitlin fluid (`euler_sphere`) and its
inverse, applied along the diagonals of a matrix (tridiagonal there), never as an N²×N² matrix;
the constants behind them, computed once per N."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "euler_sphere_hbar",
    "check_N",
    "laplacian_data",
    "neg_laplacian_hat",
    "neg_laplacian_hat_inverse",
    "outer_weight",
    "pack",
    "unpack",
]


def euler_sphere_hbar(N: int) -> float:
    r"""$\hbar = 2/\sqrt{N^2 - 1}$: the scale at which $\tfrac1\hbar[\hat f, \hat g]$ quantises the
    Poisson bracket $\{f, g\}$ of the unit sphere."""
    return 2.0 / np.sqrt(N * N - 1.0)


def check_N(N) -> int:
    if isinstance(N, bool) or not isinstance(N, (int, np.integer)) or N < 2:
        raise ValueError(f"N: expected an integer matrix size N >= 2, got {N!r}.")
    return int(N)


@functools.lru_cache(maxsize=16)
def laplacian_data(N: int):
    r"""NumPy constants of $\Delta_N$ for size N: the coefficients of its entrywise form, its
    tridiagonal matrices along the diagonals 1..N−1 (skewed: row k holds diagonal k, padded with
    identity rows), the Thomas factors of the same systems in the packed layout the inverse
    solves in (`pack`) and the eigen-decomposition of its (singular) matrix on diagonal 0."""
    s = 0.5 * (N - 1)
    m = s - np.arange(N)  # J3's eigenvalues, row 0 the north pole
    c = np.sqrt(np.maximum(s * (s + 1) - m * (m + 1), 0.0))  # (J+)_{i-1,i} = c_i, c_0 = 0
    c_next = np.append(c[1:], 0.0)  # c_{i+1}, 0 past the last row
    centre = -2 * s * (s + 1) + 2 * np.outer(m, m)
    up = np.outer(c_next, c_next)  # coefficient of P[i+1, j+1]
    down = np.outer(c, c)  # coefficient of P[i-1, j-1]
    # along diagonal k (entries (i, i+k)): d_i = centre[i, i+k], coupling (i, i+1): up[i, i+k]
    k, i = np.meshgrid(np.arange(N), np.arange(N), indexing="ij")
    valid = i < N - k
    j = np.where(valid, i + k, 0)
    d = np.where(valid, centre[i, j], 1.0)
    inner = valid & (i + 1 < N - k)
    e = np.where(inner, up[i, j], 0.0)  # A[i, i+1] = A[i+1, i] on diagonal k
    du = e
    # the singular diagonal 0: its eigenbasis, with -Δ̂'s eigenvalue κ on the constant
    T0 = np.diag(d[0]) + np.diag(e[0, :-1], 1) + np.diag(e[0, :-1], -1)
    lam, V0 = np.linalg.eigh(-T0)  # l(l+1) ascending, l = 0 first
    lam_hat = np.concatenate([[outer_weight(N)], lam[1:]])
    # The Thomas factors of the packed systems (`pack`): column k ≥ 1 of the packed matrix holds
    # diagonal k (rows 0..N−k−1) and diagonal −(N+1−k) (rows N−k..N−2), two tridiagonal
    # systems with no coupling between them (the coefficient `up` of an entry on the last
    # column or row is 0), and an identity row for the padding; column 0, diagonal 0, is
    # singular and is solved in its eigenbasis instead (an identity column here). T = L U with
    # unit upper U, U[i, i+1] = upper[i], and pivots pivot[i]; the systems of diagonals k ≠ 0
    # hold only degrees l ≥ |k| ≥ 1, so they are definite and need no pivoting.
    d_packed = np.where(_pack_mask(N), _pack_np(centre), 1.0)
    e_packed = np.where(_pack_mask(N), _pack_np(up), 0.0)
    d_packed[:, 0], e_packed[:, 0] = 1.0, 0.0
    pivot, upper = np.empty_like(d_packed), np.empty_like(d_packed)
    pivot[0], upper[0] = d_packed[0], e_packed[0] / d_packed[0]
    for r in range(1, N):
        pivot[r] = d_packed[r] - e_packed[r - 1] * upper[r - 1]
        upper[r] = e_packed[r] / pivot[r]
    return dict(
        centre=centre,
        up=up,
        down=down,
        d=d,
        du=du,
        V0=V0,
        inv0=(V0 / lam_hat) @ V0.T,
        pivot=pivot,
        upper=upper,
        lower=np.concatenate([np.zeros((1, N + 1)), e_packed[:-1]]),
    )


def pack(M):
    r"""The (..., N, N + 1) packing of (..., N, N) matrices whose column k holds diagonal k of M
    and, below it, diagonal −(N + 1 − k): entry (i, k) is M's entry of flat index
    $i(N + 1) + k$, i.e. $M_{i, i+k}$ for $i + k < N$ and $M_{i+1, i+k-N}$ after it (zero
    padding past the end). A pad and two reshapes, no gather; `unpack` inverts it. Along a
    column, consecutive entries are neighbours (i, j), (i + 1, j + 1) of one diagonal."""
    N = M.shape[-1]
    lead = M.shape[:-2]
    flat = jnp.pad(M.reshape(lead + (N * N,)), [(0, 0)] * len(lead) + [(0, N)])
    return flat.reshape(lead + (N, N + 1))


def unpack(S):
    """The (..., N, N) matrices of packed (..., N, N + 1) arrays (`pack`'s inverse)."""
    N = S.shape[-2]
    lead = S.shape[:-2]
    return S.reshape(lead + (N * (N + 1),))[..., : N * N].reshape(lead + (N, N))


def _pack_np(M):
    N = M.shape[-1]
    return np.pad(M.reshape(N * N), (0, N)).reshape(N, N + 1)


def _pack_mask(N: int):
    """Where the packing holds an entry of the matrix (False on its padding)."""
    return _pack_np(np.ones((N, N))) > 0


def neg_laplacian_hat(M):
    r"""$-\hat\Delta_N M = -\Delta_N M + \kappa\tfrac{\mathrm{tr}\,M}{N}I$ for real (..., N, N) M (the real
    and imaginary parts of a complex matrix separately: $\Delta_N$ has real coefficients)."""
    N = M.shape[-1]
    D = laplacian_data(N)
    Mp = jnp.pad(M, [(0, 0)] * (M.ndim - 2) + [(0, 1), (0, 1)])
    Mm = jnp.pad(M, [(0, 0)] * (M.ndim - 2) + [(1, 0), (1, 0)])
    lap = D["centre"] * M + D["up"] * Mp[..., 1:, 1:] + D["down"] * Mm[..., :-1, :-1]
    trace = jnp.trace(M, axis1=-2, axis2=-1)[..., None, None] / N
    return -lap + outer_weight(N) * trace * jnp.eye(N, dtype=M.dtype)


def neg_laplacian_hat_inverse(M):
    r"""$(-\hat\Delta_N)^{-1}M$ for real (..., N, N) M: the diagonals k ≠ 0 by tridiagonal
    solves along the columns of M's packing (`pack`: all of them at once, with no gather),
    diagonal 0 in its eigenbasis (where $\Delta_N$ is singular); O(N²) work per matrix."""
    N = M.shape[-1]
    D = laplacian_data(N)
    packed = pack(M)
    sol = _thomas(D, -packed)
    diag0 = packed[..., :, 0] @ jnp.asarray(D["inv0"], M.dtype)  # inv0 is symmetric
    first = jnp.arange(N + 1) == 0
    return unpack(jnp.where(first, diag0[..., :, None], sol))


def _thomas(D, rhs):
    r"""Solve $\Delta_N$'s packed tridiagonal systems (`laplacian_data`) for `rhs` (..., N, N + 1),
    with their constant factors: a forward and a backward substitution, each one scan over the
    N rows of every column at once."""
    along = jnp.moveaxis(rhs, -2, 0)  # (N, ..., N + 1): row i of every column
    factors = {name: jnp.asarray(D[name], rhs.dtype) for name in ("pivot", "upper", "lower")}

    def forward(y, row):
        b, lower, pivot = row
        y = (b - lower * y) / pivot
        return y, y

    def backward(x, row):
        y, upper = row
        x = y - upper * x
        return x, x

    zero = jnp.zeros_like(along[0])
    _, y = jax.lax.scan(forward, zero, (along, factors["lower"], factors["pivot"]))
    _, x = jax.lax.scan(backward, zero, (y, factors["upper"]), reverse=True)
    return jnp.moveaxis(x, 0, -2)


def outer_weight(N: int) -> float:
    r"""κ = N², the weight of l on the centre of $\mathfrak u(N)$ and on the complement of
    $R(\mathfrak u(N))$: above every eigenvalue $l(l+1) \le N(N-1)$ of $-\Delta_N$, so that
    the velocity of a stray component of the momentum there (round-off of the products) is
    smaller than that of any mode of the fluid: the step's sweeps contract on it fastest, and
    it does not feed back into the march."""
    return float(N * N)
