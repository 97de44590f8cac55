r"""Quantisation of the Euler–Zeitlin fluid (`clebsch_jax.models.euler_sphere`): a field on the
sphere, as spherical-harmonic coefficients $c_{lm}$, to its vorticity matrix in the Hoppe basis
$T_{lm}$ (`euler_sphere_quantise`) and back (`euler_sphere_coefficients`), and the field of a
vorticity matrix on a grid or as an orthographic image, for initial conditions and plots.

The $T_{lm}$ are the eigenvectors of the Hoppe–Yau Laplacian $\Delta_N$ along each diagonal
(`_euler_sphere_laplacian.laplacian_data`), normalised and phased as the spherical harmonics."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from ._euler_sphere_laplacian import check_N, laplacian_data

__all__ = [
    "euler_sphere_quantise",
    "euler_sphere_coefficients",
    "euler_sphere_field",
    "euler_sphere_basis",
    "euler_sphere_orthographic",
]


@functools.lru_cache(maxsize=8)
def euler_sphere_basis(N: int) -> tuple:
    r"""The Hoppe basis of $\mathfrak{gl}(N, \mathbb C)$: a tuple whose entry m (0 ≤ m < N) is the
    real (N − m, N − m) array $V_m$ whose column l − m holds the entries of $T_{lm}$ along the
    m-th upper diagonal ($T_{lm}[i, i+m] = \sqrt{N/4\pi}\,V_m[i, l-m]$), for l = m, …, N − 1.

    The $T_{lm}$ are the eigenvectors of $\Delta_N$ (eigenvalue $-l(l+1)$) on each diagonal,
    normalised as the spherical harmonics, $\langle T_{lm}, T_{l'm'}\rangle = \tfrac{N}{4\pi}
    \delta_{ll'}\delta_{mm'}$ (so $\hat 1 = I$ and $\tfrac{4\pi}N\mathrm{tr}$ quantises
    $\int_{S^2}$), with the phases of $Y_{lm}$ (Condon–Shortley): $T_{l0}$ positive at the north
    pole (entry (0, 0)) and $[J_-, T_{lm}] = \sqrt{(l+m)(l-m+1)}\,T_{l,m-1}$. Negative orders:
    $T_{l,-m} = (-1)^mT_{lm}^H$. Computed once per N in NumPy (eigen-decompositions of the
    N tridiagonal matrices, O(N⁴) flops)."""
    N = check_N(N)
    D = laplacian_data(N)
    s = 0.5 * (N - 1)
    c = np.sqrt(np.maximum(s * (s + 1) - (s - np.arange(N)) * (s - np.arange(N) + 1), 0.0))
    bases, previous = [], None
    for m in range(N):
        n = N - m
        T = np.diag(D["d"][m, :n]) + np.diag(D["du"][m, : n - 1], 1) + np.diag(D["du"][m, : n - 1], -1)
        _, V = np.linalg.eigh(-T)  # l(l+1) ascending: l = m, ..., N-1
        if m == 0:
            V = V * np.sign(V[0])
        else:
            # [J-, T] on diagonal m-1 at row i: c_i t_{i-1} - t_i c_{i+m}
            t = np.vstack([np.zeros((1, n)), V, np.zeros((1, n))])  # t[i + 1] = t_i
            rows = np.arange(n + 1)
            lowered = c[rows][:, None] * t[rows] - t[rows + 1] * np.append(c, 0.0)[np.minimum(rows + m, N)][:, None]
            V = V * np.sign(np.sum(lowered * previous[:, 1:], axis=0))
        bases.append(V)
        previous = V
    return tuple(bases)


DIAGONALS_PER_PRODUCT = 16
"""Diagonals of the Hoppe basis applied by one batched product in `euler_sphere_quantise` and
`euler_sphere_coefficients` (`_basis_blocks`): the programs hold about N/16 products instead
of one per diagonal, each padded to its block's longest diagonal (a few per cent more
entries than the basis itself)."""


@functools.lru_cache(maxsize=8)
def _basis_blocks(N: int) -> tuple:
    """`euler_sphere_basis(N)` in blocks of `DIAGONALS_PER_PRODUCT` diagonals: for the block
    from diagonal m0, an array (b, N − m0, N − m0) whose entry k holds $V_{m_0+k}$ in its
    top-left corner and zeros elsewhere. Built in NumPy and moved to the device once per N
    (concrete even when the call is traced), so that later calls pass them without a copy."""
    bases = euler_sphere_basis(N)
    blocks = []
    for m0 in range(0, N, DIAGONALS_PER_PRODUCT):
        ms = range(m0, min(m0 + DIAGONALS_PER_PRODUCT, N))
        padded = np.zeros((len(ms), N - m0, N - m0))
        for k, m in enumerate(ms):
            padded[k, : N - m, : N - m] = bases[m]
        blocks.append(padded)
    with jax.ensure_compile_time_eval():
        return tuple(jax.device_put(b) for b in blocks)


def _skew_index(N: int):
    """Index arrays of the skewed layout (row m: diagonal m, entry i at (i, i + m)): `rows`,
    `cols` and the mask `valid` of its entries, and for each (i, j) of a matrix its diagonal
    |j − i| and position min(i, j) there."""
    m, i = np.meshgrid(np.arange(N), np.arange(N), indexing="ij")
    valid = i < N - m
    a, b = np.meshgrid(np.arange(N), np.arange(N), indexing="ij")
    return np.where(valid, i, 0), np.where(valid, i + m, 0), valid, np.abs(b - a), np.minimum(a, b)


def _check_coefficients(coeffs):
    coeffs = np.asarray(coeffs) if not isinstance(coeffs, jax.Array) else coeffs
    if coeffs.ndim != 2 or coeffs.shape[0] != coeffs.shape[1]:
        raise ValueError(f"coeffs: expected an (N, N) array c[l, m] (0 <= m <= l < N), got shape {coeffs.shape}.")
    return coeffs


def euler_sphere_quantise(coeffs):
    r"""The vorticity matrix $W = -i\hat\omega$ of the real field
    $\omega = \sum_l \big[c_{l0}Y_{l0} + 2\,\mathrm{Re}\sum_{m>0} c_{lm}Y_{lm}\big]$ (orthonormal
    complex spherical harmonics with the Condon–Shortley phase), $\hat\omega = \sum c_{lm}T_{lm}$
    over $|m| \le l < N$ with $c_{l,-m} = (-1)^m\bar c_{lm}$.

    **Arguments:** `coeffs`, complex (N, N): `coeffs[l, m]` for 0 ≤ m ≤ l (entries with m > l
    are ignored; the imaginary part of `coeffs[:, 0]` too, the field being real).
    **Returns:** W, complex (N, N), skew-Hermitian."""
    coeffs = _check_coefficients(coeffs)
    return _quantise(coeffs, _basis_blocks(coeffs.shape[0]))


@jax.jit
def _quantise(coeffs, blocks):
    N = coeffs.shape[0]
    rows, _, valid, diagonal, position = _skew_index(N)
    coeffs = jnp.asarray(coeffs, jnp.complex128)
    # column m of the coefficients from l = m on, as row m of a skewed array: c[m + i, m]
    along = jnp.where(valid, coeffs[np.minimum(rows + np.arange(N)[:, None], N - 1), np.arange(N)[:, None]], 0.0)
    # row m: the entries of Σ_l c_lm T_lm along diagonal m, by one product per block
    parts, m0 = [], 0
    for V in blocks:
        b, n = V.shape[0], V.shape[1]
        u = jnp.einsum("kil,kl->ki", jnp.asarray(V), along[m0 : m0 + b, :n])
        parts.append(jnp.pad(u, ((0, 0), (0, N - n))))
        m0 += b
    skewed = np.sqrt(N / (4 * np.pi)) * jnp.concatenate(parts)
    skewed = skewed.at[0].set(jnp.real(skewed[0]))  # the zonal part is real
    entries = skewed[diagonal, position]  # the upper triangle's entries, mirrored
    upper = np.arange(N)[:, None] <= np.arange(N)[None, :]
    return -1j * jnp.where(upper, entries, jnp.conj(entries))


def euler_sphere_coefficients(W):
    r"""The inverse of `euler_sphere_quantise`: `coeffs[l, m]` (complex (N, N), zero for m > l)
    of the field whose vorticity matrix is W, $c_{lm} = \tfrac{4\pi}{N}\langle T_{lm},
    \hat\omega\rangle$, $\hat\omega = iW$ (W skew-Hermitian, complex (N, N))."""
    W = jnp.asarray(W)
    if W.ndim != 2 or W.shape[0] != W.shape[1]:
        raise ValueError(f"W: expected a square N x N vorticity matrix, got shape {W.shape}.")
    return _coefficients(W, _basis_blocks(W.shape[0]))


@jax.jit
def _coefficients(W, blocks):
    N = W.shape[0]
    rows, cols, valid, _, _ = _skew_index(N)
    skewed = jnp.where(valid, (1j * W)[rows, cols], 0.0)  # row m: diagonal m of ω̂ = iW
    parts, m0 = [], 0
    for V in blocks:  # row m: V_mᵀ (diagonal m), l = m, ..., N − 1 at l − m
        b, n = V.shape[0], V.shape[1]
        c = jnp.einsum("kil,ki->kl", jnp.asarray(V), skewed[m0 : m0 + b, :n])
        parts.append(jnp.pad(c, ((0, 0), (0, N - n))))
        m0 += b
    by_order = np.sqrt(4 * np.pi / N) * jnp.concatenate(parts)  # [m, l − m]
    l, m = np.meshgrid(np.arange(N), np.arange(N), indexing="ij")
    return jnp.where(l >= m, by_order[m, np.maximum(l - m, 0)], 0.0)


def _legendre(lmax: int, x: np.ndarray) -> np.ndarray:
    r"""$\bar P_{lm}(x)$, (lmax+1, lmax+1, len(x)): the associated Legendre functions normalised
    so that $Y_{lm}(\theta, \phi) = \bar P_{lm}(\cos\theta)e^{im\phi}$ is orthonormal on the sphere,
    with the Condon–Shortley phase (the standard stable recursion in l at fixed m)."""
    x = np.asarray(x, float)
    sin = np.sqrt(np.maximum(1.0 - x * x, 0.0))
    P = np.zeros((lmax + 1, lmax + 1) + x.shape)
    P[0, 0] = np.sqrt(1.0 / (4 * np.pi))
    for m in range(1, lmax + 1):
        P[m, m] = -np.sqrt((2 * m + 1) / (2.0 * m)) * sin * P[m - 1, m - 1]
    for m in range(lmax):
        P[m + 1, m] = np.sqrt(2 * m + 3.0) * x * P[m, m]
        for l in range(m + 2, lmax + 1):
            a = np.sqrt((4.0 * l * l - 1) / (l * l - m * m))
            b = np.sqrt(((l - 1.0) ** 2 - m * m) / (4.0 * (l - 1) ** 2 - 1))
            P[l, m] = a * (x * P[l - 1, m] - b * P[l - 2, m])
    return P


def euler_sphere_field(W, theta, phi) -> np.ndarray:
    r"""The field ω of the vorticity matrix W at colatitudes `theta` and longitudes `phi`
    (1-D arrays, radians): $\omega(\theta_a, \phi_b)$ from its spherical-harmonic coefficients
    (`euler_sphere_coefficients`), for plots. NumPy (concrete W). **Returns:** (len(theta),
    len(phi)) real array."""
    c = np.asarray(euler_sphere_coefficients(W))
    N = c.shape[0]
    P = _legendre(N - 1, np.cos(np.asarray(theta, float)))  # (l, m, θ)
    g = np.einsum("lm,lmt->mt", c, P)  # Σ_l c_lm P_lm(cos θ), per m
    phase = np.exp(1j * np.outer(np.arange(N), np.asarray(phi, float)))  # (m, φ)
    weight = np.where(np.arange(N) == 0, 1.0, 2.0)[:, None]
    return np.real(np.einsum("mt,mp->tp", weight * g, phase))


def euler_sphere_orthographic(
    W, *, colatitude: float = 0.9, longitude: float = 0.4, resolution: int = 181, grid: int = 181
) -> np.ndarray:
    r"""The field of W on the hemisphere seen from the direction (`colatitude`, `longitude`)
    (radians), in orthographic projection: a (resolution, resolution) image over the square
    $[-1, 1]^2$ (x to the right, y up; NaN outside the disc), for `imshow(..., origin="lower",
    extent=(-1, 1, -1, 1))`. The field is evaluated on a `grid` × 2`grid` grid in (θ, φ)
    (`euler_sphere_field`) and read at the nearest grid point. NumPy (concrete W)."""
    x, y = np.meshgrid(np.linspace(-1, 1, resolution), np.linspace(-1, 1, resolution))
    z = np.sqrt(np.clip(1 - x**2 - y**2, 0, None))
    out = np.array([np.sin(colatitude) * np.cos(longitude), np.sin(colatitude) * np.sin(longitude), np.cos(colatitude)])
    right = np.array([-np.sin(longitude), np.cos(longitude), 0.0])
    up = np.cross(out, right)
    p = x[..., None] * right + y[..., None] * up + z[..., None] * out
    theta, phi = np.arccos(np.clip(p[..., 2], -1, 1)), np.arctan2(p[..., 1], p[..., 0])
    n_theta, n_phi = grid, 2 * grid - 1
    f = euler_sphere_field(W, np.linspace(0, np.pi, n_theta), np.linspace(-np.pi, np.pi, n_phi))
    values = f[
        np.rint(theta / np.pi * (n_theta - 1)).astype(int),
        np.rint((phi + np.pi) / (2 * np.pi) * (n_phi - 1)).astype(int),
    ]
    return np.where(x**2 + y**2 <= 1, values, np.nan)
