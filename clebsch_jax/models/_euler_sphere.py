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

**Two forms.** The default, `form="unitary"`, declares the group by its velocity map,
`clebsch_jax.UnitaryAlgebra(N)`: ξ is a real N×N matrix S of coordinates of
$Z(S) = \tfrac12(S - S^T) + \tfrac i2(S + S^T) \in \mathfrak u(N)$ (dim V = N², the Frobenius
product of S the pairing $\mathrm{Re\,tr}(Z_1^HZ_2)$), and the reduced step computes with
complex N×N matrices. The Lagrangian is

$$ l(S) = \hbar\,\langle S, -\hat\Delta_N S\rangle = \hbar\,\mathrm{Re\,tr}\big(Z^H(-\hat\Delta_N Z)\big), $$

($\Delta_N$ has real coefficients and commutes with transposition, so it acts on S as on Z),
with $-\hat\Delta_N M = -\Delta_N M + \kappa\tfrac{\mathrm{tr}\,M}{N}I$: $-\Delta_N$ on the
trace-free part, κ on the centre ($\Delta_N$ is singular there), which makes the Legendre map
invertible, $S = (-\hat\Delta_N)^{-1}\mu/(2\hbar)$ (`inverse_legendre`, by tridiagonal solves).
Its momentum is $\mu = 2\,s(W)$, twice the coordinates of the vorticity matrix
($W = \tfrac12 Z(\mu)$, `euler_sphere_vorticity`), and its energy is that of the real form.

`form="real"` represents $\mathfrak{gl}(N, \mathbb C)$ in $\mathfrak{gl}(2N, \mathbb R)$ by

$$ R(A + iB) = \begin{pmatrix} A & -B \\ B & A \end{pmatrix}, \qquad R(Z_1Z_2) = R(Z_1)R(Z_2),
   \quad \langle R(Z_1), R(Z_2)\rangle = 2\,\mathrm{Re\,tr}(Z_1^HZ_2) , $$

with real 2N×2N matrices Q and ξ, the velocity map $Q\xi$ on all of
$\mathfrak{gl}(2N, \mathbb R)$ (the engine finds the reduction itself,
`MatrixAlgebraReduction`) and

$$ l(\xi) = \tfrac\hbar2\big\langle \xi,\ K\xi\big\rangle, \qquad
   K\xi = R\big(-\hat\Delta_N W(\xi)\big) + \kappa\big(\xi - R(W(\xi))\big) , $$

$W(\xi)$ the skew-Hermitian part of the complex matrix ξ represents: κ also on the complement
of $R(\mathfrak u(N))$. Its momentum is $R(W)$. It carries 4N² numbers for the N² of
$\mathfrak u(N)$ and its products cost twice the flops of complex ones; both forms step the
same vorticity (the tests compare them).

In both, data in $\mathfrak u(N)$ stay there, the vorticity has zero mean (Gauss:
$\int\omega = 0$ on a closed surface) and $\mathrm{tr}\,\mu$ is a Casimir, so κ only fixes
the trace part of ξ, which in the Cayley step is of order $\Delta t^2$ (Modin and Viviani take
it zero, the limit κ → ∞; both are isospectral and of order 2).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from ..core.derivative_maps import CayleyDifference, DerivativeMap, cayley
from ..core.representation import UnitaryAlgebra
from ..core.system import ClebschSystem
from ._euler_sphere_laplacian import (
    check_N,
    euler_sphere_hbar,
    neg_laplacian_hat,
    neg_laplacian_hat_inverse,
    outer_weight,
)

__all__ = [
    "euler_sphere",
    "EULER_SPHERE_FORMS",
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


EULER_SPHERE_FORMS = ("unitary", "real")
"""The forms of `euler_sphere` (module docstring): the first is the default."""


def check_form(form) -> str:
    if form not in EULER_SPHERE_FORMS:
        raise ValueError(f"form: expected one of {EULER_SPHERE_FORMS}, got {form!r}.")
    return form


@jax.jit
def euler_sphere_laplacian(W):
    r"""$\Delta_N W$ for a complex or real (..., N, N) matrix W (applied along the diagonals:
    O(N²) work). Its eigenvalues are $-l(l+1)$, the spherical harmonics' degree l ≤ N − 1."""
    W = jnp.asarray(W)
    N = W.shape[-1]
    trace = jnp.trace(W, axis1=-2, axis2=-1)[..., None, None] / N * jnp.eye(N) * outer_weight(N)
    if jnp.iscomplexobj(W):
        return -(neg_laplacian_hat(W.real) + 1j * neg_laplacian_hat(W.imag)) + trace
    return -neg_laplacian_hat(W) + trace


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
        return -(neg_laplacian_hat_inverse(centred.real) + 1j * neg_laplacian_hat_inverse(centred.imag))
    return -neg_laplacian_hat_inverse(centred)


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


def euler_sphere_vorticity(mu, form: str = "unitary"):
    r"""The vorticity matrix $W \in \mathfrak u(N)$ (complex) of the model's momentum μ:
    `Solution.momentum` → vorticity matrices. `form` is the model's (`euler_sphere`): for
    "unitary", μ is real (..., N, N) and $W = \tfrac12 Z(\mu)$; for "real", μ is real
    (..., 2N, 2N) and W is the skew-Hermitian part of the complex matrix it represents."""
    return _vorticity(jnp.asarray(mu), check_form(form))


@functools.partial(jax.jit, static_argnames="form")
def _vorticity(mu, form):
    if form == "unitary":
        return 0.5 * UnitaryAlgebra(mu.shape[-1]).X(mu)
    A, B = _skew_hermitian_parts(mu)
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
    op = neg_laplacian_hat_inverse if inverse else neg_laplacian_hat
    on_u = op(jnp.stack([A, B]))
    projected = _real(A, B)
    kappa = outer_weight(X.shape[-1] // 2)
    return _real(on_u[0], on_u[1]) + (X - projected) * (1.0 / kappa if inverse else kappa)


class _Lagrangian(_Operator):
    r"""$l(\xi) = \tfrac\hbar2\langle\xi, K\xi\rangle$ (see the module docstring)."""

    def __call__(self, xi):
        return _kinetic(xi)


def _symmetric_quadratic(apply_K, weight):
    r"""$x \mapsto c\,\langle x, Kx\rangle$ for a symmetric K (`apply_K`) and $c$ = `weight(x)` (a
    function of x's shape), with its derivative $2c\langle Kx, \dot x\rangle$ stated: one
    application of K, where reverse mode through the quadratic form would apply K and its
    transpose (the pads and slices of the Laplacian transposed) and average them."""

    @jax.custom_jvp
    def quadratic(x):
        return weight(x) * jnp.sum(x * apply_K(x))

    @quadratic.defjvp
    def _jvp(primals, tangents):
        (x,), (x_dot,) = primals, tangents
        c, K_x = weight(x), apply_K(x)
        return c * jnp.sum(x * K_x), 2.0 * c * jnp.sum(K_x * x_dot)

    return quadratic


_kinetic = _symmetric_quadratic(
    lambda xi: _apply_K(xi, inverse=False), lambda xi: 0.5 * euler_sphere_hbar(xi.shape[-1] // 2)
)
r"""$\tfrac\hbar2\langle\xi, K\xi\rangle$ of the real form: K is symmetric (an orthogonal
projection onto $R(\mathfrak u(N))$, $-\hat\Delta_N$ on it and κ on its complement)."""


class _InverseLegendre(_Operator):
    r"""$\xi = K^{-1}\mu/\hbar$: the velocity whose momentum $\nabla l(\xi) = \hbar K\xi$ is μ."""

    def __call__(self, mu, Q=None):
        return _apply_K(mu, inverse=True) / euler_sphere_hbar(self.N)


class _UnitaryLagrangian(_Operator):
    r"""$l(S) = \hbar\langle S, -\hat\Delta_N S\rangle$ (the unitary form: module docstring)."""

    def __call__(self, xi):
        return _kinetic_unitary(xi)


_kinetic_unitary = _symmetric_quadratic(neg_laplacian_hat, lambda S: euler_sphere_hbar(S.shape[-1]))
r"""$\hbar\langle S, -\hat\Delta_N S\rangle$ of the unitary form ($-\hat\Delta_N$ is symmetric)."""


class _UnitaryInverseLegendre(_Operator):
    r"""$S = (-\hat\Delta_N)^{-1}\mu/(2\hbar)$: the velocity whose momentum is μ."""

    def __call__(self, mu, Q=None):
        return neg_laplacian_hat_inverse(mu) / (2.0 * euler_sphere_hbar(self.N))


def _right_multiplication(xi, Q):
    return Q @ xi


def euler_sphere(N: int, derivative_map: DerivativeMap = cayley, *, form: str = "unitary") -> ClebschSystem:
    r"""Incompressible Euler on the unit sphere, quantised at size N (Euler–Zeitlin), as a
    Clebsch system on $U(N)$ (module docstring).

    - `form="unitary"` (default): ξ and the momentum are real N×N matrices of coordinates of
      $\mathfrak u(N)$, the velocity map `clebsch_jax.UnitaryAlgebra(N)` (right multiplication,
      declared with its complex products), Q a real 2N×2N matrix (the real form of a unitary
      one); $l(S) = \hbar\langle S, -\hat\Delta_N S\rangle$, the kinetic energy. The reduced
      step computes with complex N×N matrices. Cayley map only (`derivative_map=cayley`).
    - `form="real"`: Q and ξ real 2N×2N matrices, velocity map $Q\xi$,
      $l(\xi) = \tfrac\hbar2\langle\xi, K\xi\rangle$; derivative map `clebsch_jax.cayley`
      or `clebsch_jax.exponential`.
    - In both, the momentum gives the vorticity matrix (`euler_sphere_vorticity(mu, form)`),
      `integrate` runs the reduced march (the isospectral midpoint method for the Cayley map),
      and `inverse_legendre` (tridiagonal solves) preconditions its fixed-point sweeps (no
      N²×N² matrix anywhere).

    Start from `euler_sphere_start(W, form)`, with W from `euler_sphere_quantise`.
    """
    N = check_N(N)
    if check_form(form) == "unitary":
        if not isinstance(derivative_map, CayleyDifference):
            raise ValueError(
                f"derivative_map: the unitary form computes the Cayley step in complex matrices; got "
                f"{derivative_map!r}: use clebsch_jax.cayley, or form='real' for other maps."
            )
        return ClebschSystem(
            lagrangian=_UnitaryLagrangian(N),
            velocity_map=UnitaryAlgebra(N),
            derivative_map=derivative_map,
            inverse_legendre=_UnitaryInverseLegendre(N),
        )
    return ClebschSystem(
        lagrangian=_Lagrangian(N),
        velocity_map=_right_multiplication,
        derivative_map=derivative_map,
        inverse_legendre=_InverseLegendre(N),
    )


def euler_sphere_start(W, form: str = "unitary"):
    r"""`(Q0, xi0)` for `integrate(euler_sphere(N, form=form), Q0, xi0, ...)` from a vorticity
    matrix W (complex N×N, skew-Hermitian and trace-free; e.g. `euler_sphere_quantise(coeffs)`):
    $Q_0 = I$ (2N×2N) and ξ0 the velocity of stream matrix P, $\Delta_N P = W$: the coordinates
    S of $Z(S) = -P/\hbar$ (N×N, unitary form) or $R(-P)/\hbar$ (2N×2N, real form)."""
    W = jnp.asarray(W)
    if W.ndim != 2 or W.shape[0] != W.shape[1]:
        raise ValueError(f"W: expected a square N x N vorticity matrix, got shape {W.shape}.")
    N = W.shape[0]
    check_N(N)
    return _start(W.astype(jnp.complex128), check_form(form))


@functools.partial(jax.jit, static_argnames="form")
def _start(W, form):
    N = W.shape[0]
    if form == "unitary":  # μ = 2 s(W), s(W) = Re W + Im W the coordinates of W
        xi0 = _UnitaryInverseLegendre(N)(2.0 * (W.real + W.imag))
    else:
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
