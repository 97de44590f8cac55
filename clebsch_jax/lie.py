"""Matrix Lie group helpers: hat/vee maps, the Cayley transform, exp and log.

All functions are pure `jax.numpy` code: jit-, vmap- and grad-compatible.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from .core import linalg as _linalg

__all__ = [
    "hat",
    "vee",
    "so3_left_generators",
    "se2_hat",
    "cayley_exp",
    "cayley_log",
    "expm",
    "exp_and_phi1",
    "logm",
    "sqrtm",
    "so3_exp",
    "so3_log",
]


def hat(w: jax.Array) -> jax.Array:
    r"""The isomorphism $\mathbb R^3 \to \mathfrak{so}(3)$, $\hat w v = w \times v$."""
    w = jnp.asarray(w)
    z = jnp.zeros_like(w[..., 0])
    return jnp.stack(
        [
            jnp.stack([z, -w[..., 2], w[..., 1]], axis=-1),
            jnp.stack([w[..., 2], z, -w[..., 0]], axis=-1),
            jnp.stack([-w[..., 1], w[..., 0], z], axis=-1),
        ],
        axis=-2,
    )


def vee(W: jax.Array) -> jax.Array:
    r"""Inverse of `hat` on the skew part: $\mathfrak{so}(3) \to \mathbb R^3$."""
    W = jnp.asarray(W)
    return 0.5 * jnp.stack(
        [W[..., 2, 1] - W[..., 1, 2], W[..., 0, 2] - W[..., 2, 0], W[..., 1, 0] - W[..., 0, 1]],
        axis=-1,
    )


def so3_left_generators(Q: jax.Array) -> jax.Array:
    r"""The generators $\hat e_k Q$, k = 1, 2, 3, of the left $SO(3)$ action (spatial rotations)
    at Q, shape (3, 3, 3): pass to `diagnostics.noether_momentum` for the spatial angular
    momentum."""
    Q = jnp.asarray(Q)
    return jnp.stack([hat(e) @ Q for e in jnp.eye(3, dtype=Q.dtype)])


def se2_hat(xi: jax.Array) -> jax.Array:
    r"""$\xi = (\omega, v_1, v_2) \mapsto \begin{pmatrix} 0 & -\omega & v_1 \\ \omega & 0 & v_2 \\ 0 & 0 & 0 \end{pmatrix} \in \mathfrak{se}(2)$."""
    xi = jnp.asarray(xi)
    z = jnp.zeros_like(xi[..., 0])
    return jnp.stack(
        [
            jnp.stack([z, -xi[..., 0], xi[..., 1]], axis=-1),
            jnp.stack([xi[..., 0], z, xi[..., 2]], axis=-1),
            jnp.stack([z, z, z], axis=-1),
        ],
        axis=-2,
    )


def _eye_like(A: jax.Array) -> jax.Array:
    return jnp.broadcast_to(jnp.eye(A.shape[-1], dtype=A.dtype), A.shape)


def cayley_exp(X: jax.Array) -> jax.Array:
    r"""Cayley transform $\overline{\exp}(X) = (I - X/2)^{-1}(I + X/2)$ (Example 30).

    The two factors commute, so this equals the paper's $(I + X/2)(I - X/2)^{-1}$.
    It maps quadratic Lie algebras ($\mathfrak{so}(n)$, $\mathfrak{se}(n)$ in homogeneous
    form) into their groups and is second-order accurate: $\overline{\exp}(X) = \exp(X)
    + O(X^3)$.
    """
    eye = _eye_like(X)
    return _linalg.solve(eye - 0.5 * X, eye + 0.5 * X)


def cayley_log(A: jax.Array) -> jax.Array:
    r"""Inverse Cayley transform $\overline{\log}(A) = 2(A + I)^{-1}(A - I)$ (Example 30).

    Defined wherever $A + I$ is invertible, so it is a local diffeomorphism on all of
    $GL(n)$ near $I$, not only on the group.
    """
    eye = _eye_like(A)
    return 2.0 * _linalg.solve(A + eye, A - eye)


_PADE13 = (
    64764752532480000.0,
    32382376266240000.0,
    7771770303897600.0,
    1187353796428800.0,
    129060195264000.0,
    10559470521600.0,
    670442572800.0,
    33522128640.0,
    1323241920.0,
    40840800.0,
    960960.0,
    16380.0,
    182.0,
    1.0,
)
_PADE13_THETA = 5.371920351148152  # largest 1-norm where the [13/13] Padé approximant is exact to ε (Higham 2005)
EXPM_MAX_SQUARINGS = 16
"""`expm` scales its argument by at most 2⁻¹⁶ (1-norms up to about 3.5·10⁵ are exact)."""


def expm(X: jax.Array) -> jax.Array:
    """Matrix exponential of X (..., n, n): the [13/13] Padé approximant with scaling and
    squaring (Higham 2005), in XLA operations — the denominator solved by
    `clebsch_jax.core.linalg.solve`, the squarings a scan of `EXPM_MAX_SQUARINGS` steps that
    square only as often as the scaling needs (so reverse mode works). `jax.scipy.linalg.expm`
    is the same algorithm with a LAPACK LU, whose batched kernel is what deadlocked sweeps
    (`clebsch_jax.core.linalg`); the tests compare the two."""
    X = jnp.asarray(X)
    eye = _eye_like(X)
    s = _halvings(X, _PADE13_THETA, EXPM_MAX_SQUARINGS)
    A = X / (2.0**s)[..., None, None]
    mm = _linalg.matmul
    A2 = mm(A, A)
    A4 = mm(A2, A2)
    A6 = mm(A4, A2)
    b = _PADE13
    U = mm(A, mm(A6, b[13] * A6 + b[11] * A4 + b[9] * A2) + b[7] * A6 + b[5] * A4 + b[3] * A2 + b[1] * eye)
    V = mm(A6, b[12] * A6 + b[10] * A4 + b[8] * A2) + b[6] * A6 + b[4] * A4 + b[2] * A2 + b[0] * eye
    R = _linalg.solve(V - U, V + U)

    def square(R, k):
        return jnp.where((k < s)[..., None, None], mm(R, R), R), None

    return jax.lax.scan(square, R, jnp.arange(EXPM_MAX_SQUARINGS))[0]


def _halvings(X: jax.Array, theta: float, at_most: int) -> jax.Array:
    """The least number of halvings (0 … `at_most`) that bring X's 1-norm to `theta` or below:
    the scaling of a scaling-and-squaring method (`expm`, `exp_and_phi1`)."""
    norm = jnp.max(jnp.sum(jnp.abs(X), axis=-2), axis=-1)
    return jnp.clip(jnp.ceil(jnp.log2(jnp.maximum(norm, jnp.finfo(X.dtype).tiny) / theta)), 0, at_most)


PHI1_MAX_SCALING = 8
"""The most halvings (and doublings back) of `exp_and_phi1`: its series is at round-off for
|A|₁ up to 0.4·2⁸ ≈ 100 (for a compact group a step that large is far past the logarithm's
branch cut already) and loses accuracy gradually beyond. Each doubling costs its products
whether it is applied or not (a select)."""

PHI1_DEGREE = 13
"""Terms of the Taylor series of e^B and φ₁(B) at the scaled argument B, |B|₁ ≤ 0.4: the first
term left out is below 10⁻¹⁷ of the sum."""


def exp_and_phi1(A: jax.Array):
    r"""$(e^A, \varphi_1(A))$, $\varphi_1(z) = (e^z - 1)/z$, for a small m×m matrix A: the Taylor
    series $\varphi_1(B) = \sum_k B^k/(k+1)!$ (Horner) at $B = A/2^s$ with s the least
    number of halvings that makes $|B|_1 \le 0.4$, $e^B = I + B\varphi_1(B)$, then s doublings
    $\varphi_1(2B) = \tfrac12\varphi_1(B)(I + e^B)$, $e^{2B} = (e^B)^2$: m×m products only,
    no solve. The doublings are `PHI1_MAX_SCALING` steps each applied only while it is needed
    (a select, so under `vmap` every member may need a different s); under `vmap` this costs
    far less than the exponential of the 2m×2m block matrix that holds φ₁ too. One matrix
    (`jax.vmap` for many); jit-, vmap- and grad-compatible (no loop whose length depends on
    the data). Used by the reduced march of the exponential map
    (`clebsch_jax.discrete.reduction`)."""
    A = jnp.asarray(A)
    eye = jnp.eye(A.shape[-1], dtype=A.dtype)
    s = _halvings(A, 0.4, PHI1_MAX_SCALING)
    B = A / 2.0**s  # exact: a power of two
    phi = eye / math.factorial(PHI1_DEGREE + 1)
    for k in range(PHI1_DEGREE, 0, -1):  # Σ_k B^k/(k+1)!, from the highest term
        phi = eye / math.factorial(k) + _linalg.matmul(B, phi)
    E = eye + _linalg.matmul(B, phi)
    for i in range(PHI1_MAX_SCALING):
        more = i < s
        phi, E = (jnp.where(more, 0.5 * _linalg.matmul(phi, eye + E), phi), jnp.where(more, _linalg.matmul(E, E), E))
    return E, phi


def sqrtm(A: jax.Array, *, iterations: int = 8) -> jax.Array:
    r"""Principal matrix square root near the identity (Denman–Beavers iteration).

    `iterations` fixed steps (quadratic convergence): exact to round-off with the default for
    matrices within about a rotation of 2 rad of the identity, where the midpoint of a step
    $Q^n ((Q^n)^{-1} Q^{n+1})^{1/2}$ is taken."""
    return _sqrtm_denman_beavers(A, iterations)


def _sqrtm_denman_beavers(A: jax.Array, iterations: int) -> jax.Array:
    def body(_, YZ):
        Y, Z = YZ
        return 0.5 * (Y + _linalg.inv(Z)), 0.5 * (Z + _linalg.inv(Y))

    return jax.lax.fori_loop(0, iterations, body, (A, _eye_like(A)))[0]


def logm(A: jax.Array, *, square_roots: int = 2, sqrt_iterations: int = 8, terms: int = 15) -> jax.Array:
    r"""Principal matrix logarithm near the identity, on all of $GL(n)$.

    Inverse scaling and squaring: take `square_roots` square roots (Denman–Beavers
    iteration), then sum the Gregory series
    $\log A = 2\,\mathrm{artanh}\,Z = 2\sum_k Z^{2k+1}/(2k+1)$ with $Z = (A+I)^{-1}(A-I)$.
    With the defaults the result is exact to round-off for matrices whose eigenvalues have
    arguments below about 2 rad (per step: rotation angles $|\Delta t\,\omega| < 2$), which is
    where a derivative map is used. Unlike a Rodrigues formula it is a local diffeomorphism
    of $GL(n)$, which the full (ξ, P, Q) Newton solve in ambient coordinates needs.
    """
    A = jax.lax.fori_loop(0, square_roots, lambda _, B: _sqrtm_denman_beavers(B, sqrt_iterations), A)
    eye = _eye_like(A)
    Z = _linalg.solve(A + eye, A - eye)
    Z2 = Z @ Z

    def body(k, acc):
        term, total = acc
        term = term @ Z2
        return term, total + term / (2 * k + 1)

    _, total = jax.lax.fori_loop(1, terms, body, (Z, Z))
    return (2.0 ** (square_roots + 1)) * total


def so3_exp(w: jax.Array) -> jax.Array:
    r"""Rodrigues' formula $\exp(\hat w) = I + \frac{\sin\theta}{\theta}\hat w + \frac{1-\cos\theta}{\theta^2}\hat w^2$.

    Uses Taylor expansions near $\theta = 0$ so values and derivatives are exact there.
    """
    w = jnp.asarray(w)
    th2 = jnp.sum(w * w, axis=-1)
    small = th2 < 1e-8
    th2_safe = jnp.where(small, 1.0, th2)
    th = jnp.sqrt(th2_safe)
    a = jnp.where(small, 1.0 - th2 / 6.0 + th2**2 / 120.0, jnp.sin(th) / th)
    b = jnp.where(small, 0.5 - th2 / 24.0 + th2**2 / 720.0, (1.0 - jnp.cos(th)) / th2_safe)
    W = hat(w)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=W.dtype), W.shape)
    return eye + a[..., None, None] * W + b[..., None, None] * (W @ W)


def so3_log(R: jax.Array) -> jax.Array:
    r"""Inverse of `so3_exp` on $SO(3)$ for rotation angles below $\pi$: returns $w \in \mathbb R^3$.

    Only valid on the group (it reads the skew part of $R$); use `logm` off the group.
    """
    R = jnp.asarray(R)
    c = jnp.clip(0.5 * (jnp.trace(R, axis1=-2, axis2=-1) - 1.0), -1.0, 1.0)
    th = jnp.arccos(c)
    small = th < 1e-4
    th_safe = jnp.where(small, 1.0, th)
    f = jnp.where(small, 1.0 + th**2 / 6.0 + 7.0 * th**4 / 360.0, th_safe / jnp.sin(th_safe))
    return f[..., None] * vee(R)
