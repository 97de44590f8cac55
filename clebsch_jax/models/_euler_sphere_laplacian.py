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
    identity rows) and the eigen-decomposition of its (singular) matrix on diagonal 0."""
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
    du, dl = e, np.concatenate([np.zeros((N, 1)), e[:, :-1]], axis=1)
    # the singular diagonal 0: its eigenbasis, with -Δ̂'s eigenvalue κ on the constant
    T0 = np.diag(d[0]) + np.diag(e[0, :-1], 1) + np.diag(e[0, :-1], -1)
    lam, V0 = np.linalg.eigh(-T0)  # l(l+1) ascending, l = 0 first
    lam_hat = np.concatenate([[outer_weight(N)], lam[1:]])
    # The Thomas factors of diagonals 1..N−1 (their matrices are constant): the elimination
    # T = L U with unit upper U, U[i, i+1] = upper[i], and pivots pivot[i]. Diagonals k ≥ 1 hold
    # only degrees l ≥ k ≥ 1, so these matrices are definite and need no pivoting.
    pivot, upper = np.empty((N - 1, N)), np.empty((N - 1, N))
    pivot[:, 0], upper[:, 0] = d[1:, 0], e[1:, 0] / d[1:, 0]
    for r in range(1, N):
        pivot[:, r] = d[1:, r] - e[1:, r - 1] * upper[:, r - 1]
        upper[:, r] = e[1:, r] / pivot[:, r]
    return dict(
        centre=centre,
        up=up,
        down=down,
        rows=np.where(valid, i, 0),
        cols=j,
        valid=valid,
        d=d,
        du=du,
        dl=dl,
        V0=V0,
        inv0=(V0 / lam_hat) @ V0.T,
        pivot=pivot,
        upper=upper,
        lower=dl[1:],
    )


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
    r"""$(-\hat\Delta_N)^{-1}M$ for real (..., N, N) M: the upper diagonals of M and of $M^T$ are
    solved along each diagonal (N − 1 tridiagonal systems each, batched), diagonal 0 in its
    eigenbasis (where $\Delta_N$ is singular); O(N²) work per matrix."""
    N = M.shape[-1]
    D = laplacian_data(N)
    both = jnp.stack([M, jnp.swapaxes(M, -1, -2)], axis=-3)  # (..., 2, N, N)
    skewed = jnp.where(D["valid"], both[..., D["rows"], D["cols"]], 0.0)  # row k: diagonal k
    sol = _thomas(D, -skewed[..., 1:, :])
    diag0 = skewed[..., 0, :] @ jnp.asarray(D["inv0"], M.dtype)  # inv0 is symmetric
    solved = jnp.concatenate([diag0[..., None, :], sol], axis=-2)  # (..., 2, N, N), row k: diagonal k
    i, j = np.meshgrid(np.arange(N), np.arange(N), indexing="ij")
    upper = solved[..., 0, np.clip(j - i, 0, None), i]  # P[i, j] = diagonal j−i at row i, j >= i
    lower = solved[..., 1, np.clip(i - j, 0, None), j]  # from the transposed matrix, i > j
    return jnp.where(j >= i, upper, lower)


def _thomas(D, rhs):
    r"""Solve $\Delta_N$'s tridiagonal systems of diagonals 1..N−1 for `rhs` (..., N − 1, N)
    (row k: diagonal k), with the constant factors of `laplacian_data`: a forward and a
    backward substitution, each one scan over the N entries of every diagonal at once."""
    along = jnp.moveaxis(rhs, -1, 0)  # (N, ..., N − 1): entry i of every diagonal
    factors = {name: jnp.asarray(D[name].T, rhs.dtype) for name in ("pivot", "upper", "lower")}

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
    return jnp.moveaxis(x, 0, -1)


def outer_weight(N: int) -> float:
    r"""κ = N², the weight of l on the centre of $\mathfrak u(N)$ and on the complement of
    $R(\mathfrak u(N))$: above every eigenvalue $l(l+1) \le N(N-1)$ of $-\Delta_N$, so that
    the velocity of a stray component of the momentum there (round-off of the products) is
    smaller than that of any mode of the fluid: the step's sweeps contract on it fastest, and
    it does not feed back into the march."""
    return float(N * N)
