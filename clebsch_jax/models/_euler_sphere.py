r"""Incompressible Euler on the sphere as a Clebsch system on $U(N)$: Zeitlin's model
(Euler–Zeitlin), the discretisation in space that section 3 and the closing section of the
paper ask for — one whose velocity map stays a Lie algebra action (Theorem 12), so that Q and P
are eliminated and the step is a discrete Euler–Poincaré equation (Theorem 27).

Vorticity on the unit sphere, $\omega$, is quantised to a skew-Hermitian matrix
$W = -i\,\hat\omega \in \mathfrak u(N)$ in the Hoppe basis $T_{lm}$ (`euler_sphere_quantise`);
the stream matrix $P$ solves $\Delta_N P = W$ with the Hoppe–Yau Laplacian

$$ \Delta_N P = -\sum_{a=1}^3 [J_a, [J_a, P]] = -2s(s+1)P + 2J_3PJ_3 + J_+PJ_- + J_-PJ_+ ,
   \qquad s = \tfrac{N-1}2 , $$

($J_a$ the spin-s matrices, $J_3 = \mathrm{diag}(s, s-1, \dots, -s)$: row 0 is the north pole),
whose eigenvalues are $-l(l+1)$, $l = 0, \dots, N-1$, as for the Laplacian of the sphere. It
couples the entry $(i, j)$ only with $(i \pm 1, j \pm 1)$: it is tridiagonal along each
diagonal of the matrix, and is applied and inverted that way (tridiagonal solves: forward
and backward substitution along all diagonals at once, with factors computed once per N),
never as an $N^2 \times N^2$ matrix. Euler's equation $\dot\omega = \{\psi, \omega\}$,
$\Delta\psi = \omega$, becomes

$$ \dot W = \tfrac1\hbar [P, W], \qquad \hbar = \frac{2}{\sqrt{N^2 - 1}} , $$

the Euler–Poincaré equation on $\mathfrak u(N)$ of $l(\xi) = \tfrac\hbar2\langle\xi,
-\Delta_N\xi\rangle$ for the right action $Q \mapsto Q\xi$ of $U(N)$ on itself, with
$\xi = -P/\hbar$ and the momentum $\mu = W$. The reduced Cayley step of this system is the
isospectral midpoint method of Modin & Viviani (J. Fluid Mech. 2020):
$\mu^{n+1} = C\mu^nC^{-1}$ with $C$ a Cayley transform, so the Casimirs $\mathrm{tr}(W^k)$
are conserved to round-off.

**The real form.** The engine works with real arrays (its pairings are the real Frobenius
product and its gradients `jax.grad` of real functions), so $\mathfrak{gl}(N, \mathbb C)$ is
represented in $\mathfrak{gl}(2N, \mathbb R)$ by

$$ R(A + iB) = \begin{pmatrix} A & -B \\ B & A \end{pmatrix}, \qquad R(Z_1Z_2) = R(Z_1)R(Z_2),
   \quad \langle R(Z_1), R(Z_2)\rangle = 2\,\mathrm{Re\,tr}(Z_1^HZ_2) . $$

$Q$ and $\xi$ are real $2N\times2N$ matrices; the velocity map is $Q\xi$ on all of
$\mathfrak{gl}(2N, \mathbb R)$ (closed: the engine's reduction takes it, `MatrixAlgebraReduction`),
and the Lagrangian is

$$ l(\xi) = \tfrac\hbar2\big\langle \xi,\ K\xi \big\rangle, \qquad
   K\xi = R\big(-\hat\Delta_N W(\xi)\big) + \big(\xi - R(W(\xi))\big) , $$

with $W(\xi)$ the skew-Hermitian part of the complex matrix $\xi$ represents and
$-\hat\Delta_N W = -\Delta_NW + \tfrac{\mathrm{tr}\,W}{N}I$: $-\Delta_N$ on the trace-free part,
the identity on the centre ($\Delta_N$ is singular there) and on the complement of
$R(\mathfrak u(N))$. Both additions make the Legendre map invertible, $\xi = K^{-1}\mu/\hbar$
(`inverse_legendre`, by tridiagonal solves). Data in $R(\mathfrak u(N))$ stay there (the
gradient of l maps it to itself, and it is a subalgebra), the vorticity has zero mean
(Gauss: $\int\omega = 0$ on a closed surface) and $\mathrm{tr}\,\mu$ is a Casimir, so the
additions only fix the trace part of ξ, which in the Cayley step is of order $\Delta t^2$
(Modin and Viviani take it zero, the limit κ → ∞; both are isospectral and of order 2).

Matrix products cost twice what complex $N\times N$ products would (8 against 4 real
multiplications per complex one).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from ..core.derivative_maps import DerivativeMap, cayley
from ..core.system import ClebschSystem

__all__ = [
    "euler_sphere",
    "euler_sphere_hbar",
    "euler_sphere_laplacian",
    "euler_sphere_inverse_laplacian",
    "euler_sphere_real_form",
    "euler_sphere_complex_form",
    "euler_sphere_start",
    "euler_sphere_vorticity",
    "euler_sphere_casimirs",
    "euler_sphere_energy",
    "euler_sphere_angular_momentum",
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
    lam_hat = np.concatenate([[_outer_weight(N)], lam[1:]])
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


def _neg_laplacian_hat(M):
    r"""$-\hat\Delta_N M = -\Delta_N M + \kappa\tfrac{\mathrm{tr}\,M}{N}I$ for real (..., N, N) M (the real
    and imaginary parts of a complex matrix separately: $\Delta_N$ has real coefficients)."""
    N = M.shape[-1]
    D = laplacian_data(N)
    Mp = jnp.pad(M, [(0, 0)] * (M.ndim - 2) + [(0, 1), (0, 1)])
    Mm = jnp.pad(M, [(0, 0)] * (M.ndim - 2) + [(1, 0), (1, 0)])
    lap = D["centre"] * M + D["up"] * Mp[..., 1:, 1:] + D["down"] * Mm[..., :-1, :-1]
    trace = jnp.trace(M, axis1=-2, axis2=-1)[..., None, None] / N
    return -lap + _outer_weight(N) * trace * jnp.eye(N, dtype=M.dtype)


def _neg_laplacian_hat_inverse(M):
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


@jax.jit
def euler_sphere_laplacian(W):
    r"""$\Delta_N W$ for a complex or real (..., N, N) matrix W (applied along the diagonals:
    O(N²) work). Its eigenvalues are $-l(l+1)$, the spherical harmonics' degree l ≤ N − 1."""
    W = jnp.asarray(W)
    N = W.shape[-1]
    trace = jnp.trace(W, axis1=-2, axis2=-1)[..., None, None] / N * jnp.eye(N) * _outer_weight(N)
    if jnp.iscomplexobj(W):
        return -(_neg_laplacian_hat(W.real) + 1j * _neg_laplacian_hat(W.imag)) + trace
    return -_neg_laplacian_hat(W) + trace


@jax.jit
def euler_sphere_inverse_laplacian(W):
    r"""The stream matrix P with $\Delta_N P = W$ and $\mathrm{tr}\,P = 0$, for a trace-free W
    (its trace part, the kernel of $\Delta_N$, is dropped), by tridiagonal solves along the
    diagonals."""
    W = jnp.asarray(W)
    N = W.shape[-1]
    eye = jnp.eye(N)
    centred = W - jnp.trace(W, axis1=-2, axis2=-1)[..., None, None] / N * eye
    if jnp.iscomplexobj(W):
        return -(_neg_laplacian_hat_inverse(centred.real) + 1j * _neg_laplacian_hat_inverse(centred.imag))
    return -_neg_laplacian_hat_inverse(centred)


@jax.jit
def euler_sphere_real_form(W):
    r"""$R(W) = \begin{pmatrix} \mathrm{Re}\,W & -\mathrm{Im}\,W \\ \mathrm{Im}\,W & \mathrm{Re}\,W
    \end{pmatrix}$: the real 2N×2N matrix of a complex (..., N, N) matrix (the model's momentum
    of a vorticity matrix W)."""
    W = jnp.asarray(W)
    A, B = jnp.real(W), jnp.imag(W)
    return jnp.concatenate([jnp.concatenate([A, -B], axis=-1), jnp.concatenate([B, A], axis=-1)], axis=-2)


def _blocks(X):
    N = X.shape[-1] // 2
    return X[..., :N, :N], X[..., :N, N:], X[..., N:, :N], X[..., N:, N:]


def _skew_hermitian_parts(X):
    """Real and imaginary parts (A, B) of the skew-Hermitian part of the complex matrix that
    the real 2N×2N matrix X represents (its J-commuting part)."""
    X11, X12, X21, X22 = _blocks(X)
    A, B = 0.5 * (X11 + X22), 0.5 * (X21 - X12)
    return 0.5 * (A - jnp.swapaxes(A, -1, -2)), 0.5 * (B + jnp.swapaxes(B, -1, -2))


def _real(A, B):
    return jnp.concatenate([jnp.concatenate([A, -B], axis=-1), jnp.concatenate([B, A], axis=-1)], axis=-2)


@jax.jit
def euler_sphere_complex_form(X):
    r"""The complex N×N matrix $Z$ with $R(Z)$ the J-commuting part of the real (..., 2N, 2N)
    matrix X (exactly $R^{-1}$ on matrices of the form $R(Z)$)."""
    X11, X12, X21, X22 = _blocks(jnp.asarray(X))
    return 0.5 * (X11 + X22) + 0.5j * (X21 - X12)


@jax.jit
def euler_sphere_vorticity(mu):
    r"""The vorticity matrix $W \in \mathfrak u(N)$ (complex) of the model's momentum μ, real
    (..., 2N, 2N): `Solution.momentum` → vorticity matrices."""
    A, B = _skew_hermitian_parts(jnp.asarray(mu))
    return A + 1j * B


class _Operator:
    """A callable of the model identified by N (hashable: static under `jax.jit`)."""

    def __init__(self, N: int):
        self.N = N

    def __hash__(self):
        return hash((type(self), self.N))

    def __eq__(self, other):
        return type(self) is type(other) and self.N == other.N

    def __repr__(self):
        return f"{type(self).__name__}(N={self.N})"


def _apply_K(X, inverse: bool):
    A, B = _skew_hermitian_parts(X)
    op = _neg_laplacian_hat_inverse if inverse else _neg_laplacian_hat
    on_u = op(jnp.stack([A, B]))
    projected = _real(A, B)
    kappa = _outer_weight(X.shape[-1] // 2)
    return _real(on_u[0], on_u[1]) + (X - projected) * (1.0 / kappa if inverse else kappa)


def _outer_weight(N: int) -> float:
    r"""κ = N², the weight of l on the centre of $\mathfrak u(N)$ and on the complement of
    $R(\mathfrak u(N))$: above every eigenvalue $l(l+1) \le N(N-1)$ of $-\Delta_N$, so that
    the velocity of a stray component of the momentum there (round-off of the products) is
    smaller than that of any mode of the fluid: the step's sweeps contract on it fastest, and
    it does not feed back into the march."""
    return float(N * N)


class _Lagrangian(_Operator):
    r"""$l(\xi) = \tfrac\hbar2\langle\xi, K\xi\rangle$ (see the module docstring)."""

    def __call__(self, xi):
        return _kinetic(xi)


@jax.custom_jvp
def _kinetic(xi):
    r"""$\tfrac\hbar2\langle\xi, K\xi\rangle$, with its derivative $\langle\hbar K\xi, \dot\xi\rangle$
    stated (`_kinetic_jvp`): K is symmetric (an orthogonal projection onto $R(\mathfrak u(N))$,
    $-\hat\Delta_N$ on it and κ on its complement), so $\nabla l = \hbar K\xi$ is one
    application of K, where reverse mode through the quadratic form would apply K and its
    transpose (the pads and slices of the Laplacian transposed) and average them."""
    return 0.5 * euler_sphere_hbar(xi.shape[-1] // 2) * jnp.sum(xi * _apply_K(xi, inverse=False))


@_kinetic.defjvp
def _kinetic_jvp(primals, tangents):
    (xi,), (xi_dot,) = primals, tangents
    hbar = euler_sphere_hbar(xi.shape[-1] // 2)
    K_xi = _apply_K(xi, inverse=False)
    return 0.5 * hbar * jnp.sum(xi * K_xi), hbar * jnp.sum(K_xi * xi_dot)


class _InverseLegendre(_Operator):
    r"""$\xi = K^{-1}\mu/\hbar$: the velocity whose momentum $\nabla l(\xi) = \hbar K\xi$ is μ."""

    def __call__(self, mu, Q=None):
        return _apply_K(mu, inverse=True) / euler_sphere_hbar(self.N)


def _right_multiplication(xi, Q):
    return Q @ xi


def euler_sphere(N: int, derivative_map: DerivativeMap = cayley) -> ClebschSystem:
    r"""Incompressible Euler on the unit sphere, quantised at size N (Euler–Zeitlin), as a
    Clebsch system on $U(N)$ in its real form (module docstring).

    - $Q \in U(N)$ and $\xi$ are real 2N×2N matrices, velocity map $\mathcal L_\xi Q = Q\xi$
      (right multiplication: closed, so `integrate` runs the reduced march);
    - $l(\xi) = \tfrac\hbar2\langle\xi, K\xi\rangle$, the kinetic energy
      $\tfrac\hbar2\langle\xi, -\Delta_N\xi\rangle$ on $\mathfrak u(N)$;
    - its momentum $\mu = \hbar K\xi$ is the real form $R(W)$ of the vorticity matrix
      (`euler_sphere_vorticity`), and $\xi = R(-P)/\hbar$ with $\Delta_N P = W$;
    - derivative map: `clebsch_jax.cayley` (default: the isospectral midpoint method) or
      `clebsch_jax.exponential`;
    - `inverse_legendre`: $\xi = K^{-1}\mu/\hbar$ by tridiagonal solves, which the reduced
      march's fixed-point sweeps use as their preconditioner (no N²×N² matrix anywhere).

    Start from `euler_sphere_start(W)`, with W from `euler_sphere_quantise`.
    """
    N = check_N(N)
    return ClebschSystem(
        lagrangian=_Lagrangian(N),
        velocity_map=_right_multiplication,
        derivative_map=derivative_map,
        inverse_legendre=_InverseLegendre(N),
    )


def euler_sphere_start(W):
    r"""`(Q0, xi0)` for `integrate(euler_sphere(N), Q0, xi0, ...)` from a vorticity matrix W
    (complex N×N, skew-Hermitian and trace-free; e.g. `euler_sphere_quantise(coeffs)`):
    $Q_0 = I$ (2N×2N) and $\xi_0 = R(-P)/\hbar$, $\Delta_N P = W$."""
    W = jnp.asarray(W)
    if W.ndim != 2 or W.shape[0] != W.shape[1]:
        raise ValueError(f"W: expected a square N x N vorticity matrix, got shape {W.shape}.")
    N = W.shape[0]
    check_N(N)
    return _start(W.astype(jnp.complex128))


@jax.jit
def _start(W):
    N = W.shape[0]
    xi0 = _InverseLegendre(N)(euler_sphere_real_form(W))
    return jnp.eye(2 * N, dtype=xi0.dtype), xi0


@functools.partial(jax.jit, static_argnames="powers")
def euler_sphere_casimirs(W, powers=(2, 3, 4)):
    r"""$\mathrm{tr}(W^k)$ for k in `powers` (real: $i^{-k}\mathrm{tr}(W^k)$ for skew-Hermitian W,
    i.e. $\mathrm{tr}(\hat\omega^k)$ with $W = -i\hat\omega$), for W of shape (..., N, N).
    **Returns:** an array (..., len(powers))."""
    W = jnp.asarray(W)
    H = 1j * W  # Hermitian: ω̂
    out, power = [], None
    for k in range(1, max(powers) + 1):
        power = H if power is None else power @ H
        if k in powers:
            out.append(jnp.real(jnp.trace(power, axis1=-2, axis2=-1)))
    return jnp.stack(out, axis=-1)


@jax.jit
def euler_sphere_energy(W):
    r"""The model's energy at the vorticity matrix W (complex (..., N, N), trace-free): its
    Lagrangian at the velocity of W, $\tfrac\hbar2\langle\xi, K\xi\rangle =
    -\tfrac1\hbar\,\mathrm{Re\,tr}(P^HW)$ with $\Delta_N P = W$ (the quantised
    $-\tfrac12\int\psi\omega$ up to the factor $\tfrac{N\hbar}{4\pi}\cdot\tfrac{2}{\hbar^2}$)."""
    W = jnp.asarray(W)
    P = euler_sphere_inverse_laplacian(W)
    return -jnp.real(jnp.sum(jnp.conj(P) * W, axis=(-2, -1))) / euler_sphere_hbar(W.shape[-1])


@jax.jit
def euler_sphere_angular_momentum(W):
    r"""The total angular momentum $\int_{S^2}\omega\,\mathbf n\,dA$ of the vorticity matrix W
    (complex (..., N, N)), quantised: $\tfrac{4\pi}N\mathrm{tr}(\hat\omega\,\hat n_a)$ with
    $\hat\omega = iW$ and $\hat n_a = \hbar J_a$ the quantised coordinate functions. It sees
    only the degree-1 part of W, and is conserved (the Noether momentum of the rotations).
    **Returns:** (..., 3) real."""
    W = jnp.asarray(W)
    N = W.shape[-1]
    J1, J2, J3 = _spin_matrices(N)
    hbar = euler_sphere_hbar(N)
    H = 1j * W
    return jnp.stack([4 * np.pi / N * hbar * jnp.real(jnp.sum(H * J.T, axis=(-2, -1))) for J in (J1, J2, J3)], axis=-1)


def _spin_matrices(N: int):
    """$J_1, J_2, J_3$ of spin (N − 1)/2 (NumPy; row 0 the state $m = s$)."""
    s = 0.5 * (N - 1)
    m = s - np.arange(N)
    Jp = np.diag(np.sqrt(np.maximum(s * (s + 1) - m[1:] * (m[1:] + 1), 0.0)), 1)
    return 0.5 * (Jp + Jp.T), (Jp - Jp.T) / 2j, np.diag(m)
