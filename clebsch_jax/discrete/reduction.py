r"""Reduction (Theorem 12, Theorem 27, Corollary 29): when Q and P can be eliminated.

For a velocity map that is right multiplication on a matrix group, $\mathcal L_\xi Q = Q\,X(\xi)$
with $X(\xi) = \mathcal L_\xi I$, and a derivative map of Definition 25,
$\phi_{\Delta t}(Q^{n+1}, Q^n) = Q^n\,\overline{\log}((Q^n)^{-1}Q^{n+1})/\Delta t$, the constraint of
Lemma 20 is solved explicitly, $Q^{n+1} = Q^n F^n$ with $F^n = \overline{\exp}(\Delta t X(\xi^n))$.
Eliminating $P^n$ leaves the reduced discrete Lagrangian

$$ \ell_d(F, Q^a) = \Delta t\; l\big(X^{-1}(\overline{\log} F/\Delta t),\, Q^a\big) $$

($Q^a$ the anchor of the scheme; with the right scheme $\xi = -X^{-1}\overline{\log}(F^{-1})/\Delta t$).
Varying $Q^n$ along the group, $\delta Q^n = Q^n X(\eta)$ — exactly the velocity-map directions —
moves $F^{n-1} \to F^{n-1}(I + X(\eta))$ and $F^n \to (I - X(\eta))F^n$. With the body momentum
$\mu^n = \nabla_\eta\, \ell_d(F^{n-1}(I + X(\eta)), \cdot)|_{\eta=0}$ (the momentum map
$-p^n\diamond Q^n$ of the full march), stationarity is

$$ \mu^n + \nabla_\eta\, \ell_d\big((I - X(\eta))F^n,\ Q^a(\eta)\big)\big|_{\eta=0} = 0 , $$

dim V equations for $\xi^n$ — Corollary 29's discrete Euler–Poincaré equation (Example 30's CAY
recursion for the rigid body), obtained by `jax.grad`. When l depends on Q (Definition 14) the
anchor $Q^a$ moves with the variation too, which is how the advected quantity of Theorem 16
enters; Q is then carried (and updated explicitly) but is not an unknown.

`reduced_residual` and `outgoing_body_momentum` state these two gradients as written above. The
march evaluates them with `reduced_step`: both from one gradient of $\ell_d$, and for the Cayley
map in closed form (its logarithm has an explicit derivative), which leaves a few 3×3 products
per residual instead of two matrix solves and a reverse pass through them — and, for algebras
of moderate dimension, not even those: a sparse polynomial in $(\xi, \nabla l)$ whose
coefficients come from the basis (`CayleyPolynomial`).

Whether the reduction applies, and the algebra's basis it needs, are found by
`clebsch_jax.discrete.matrix_group` (`find_reduction`, `MatrixGroupReduction`,
`MatrixAlgebraReduction`, `matrix_group_basis`: importable from here too).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from .. import lie
from ..core import linalg as _linalg
from ..core.derivative_maps import CayleyDifference
from .matrix_group import MatrixAlgebraReduction, MatrixGroupReduction, find_reduction, matrix_group_basis

__all__ = [
    "MatrixGroupReduction",
    "MatrixAlgebraReduction",
    "find_reduction",
    "matrix_group_basis",
    "reduced_residual",
    "outgoing_body_momentum",
    "reduced_step",
]


def _xi_of(red: MatrixGroupReduction, log, scheme, F, dt):
    if scheme == "left":
        return red.X_inv(log(F)) / dt
    return -red.X_inv(log(_linalg.inv(F))) / dt


def reduced_lagrangian(system, red, scheme, dt, F, Qa):
    r"""$\ell_d(F, Q^a) = \Delta t\, l(\xi(F), Q^a)$ (see the module docstring)."""
    xi = _xi_of(red, system.derivative_map.log, scheme, F, dt)
    return dt * system.l(xi, Qa)


def reduced_residual(system, red, scheme, dt, mu, Q0, xi):
    r"""Residual of one reduced step: $\mu^n + \nabla_\eta \ell_d((I - X(\eta))F,\ Q^a(\eta))|_0$.

    `Q0` is the carried configuration (the identity when l has no potential: the reduced
    Lagrangian is then left-invariant and Q drops out)."""
    F = system.derivative_map.exp(dt * red.X(xi))
    Q1 = Q0 @ F

    def perturbed(eta):
        Xe = red.X(eta)
        Qa = Q0 + Q0 @ Xe if scheme == "left" else Q1
        return reduced_lagrangian(system, red, scheme, dt, F - Xe @ F, Qa)

    return mu + jax.grad(perturbed)(jnp.zeros_like(xi))


def outgoing_body_momentum(system, red, scheme, dt, Q0, xi):
    r"""$\mu^{n+1} = \nabla_\eta \ell_d(F(I + X(\eta)),\ Q^a(\eta))|_0$ and $Q^{n+1} = Q^n F$."""
    F = system.derivative_map.exp(dt * red.X(xi))
    Q1 = Q0 @ F

    def perturbed(eta):
        Xe = red.X(eta)
        Qa = Q0 if scheme == "left" else Q1 + Q1 @ Xe
        return reduced_lagrangian(system, red, scheme, dt, F + F @ Xe, Qa)

    return jax.grad(perturbed)(jnp.zeros_like(xi)), Q1


def reduced_step(system, red, scheme, dt, mu, Q0, xi, *, outgoing: bool = True, need_Q1: bool = True, gradient=None):
    r"""`reduced_residual` and `outgoing_body_momentum` of one step, sharing their work.

    Both are derivatives of $\ell_d(F, Q^a)$ at $F = \overline{\exp}(\Delta t X(\xi))$ along
    group directions: with $G_F = \partial\ell_d/\partial F$ and $G_Q = \partial\ell_d/\partial Q^a$
    (ambient gradients) and $X^T M = (\langle X(e_k), M\rangle)_k$,

    $$ r = \mu^n - X^T(G_F F^T) + [\text{left}]\; X^T((Q^n)^T G_Q), \qquad
       \mu^{n+1} = X^T(F^T G_F) + [\text{right}]\; X^T((Q^{n+1})^T G_Q) , $$

    the chain rule applied to the variations $F \to (I - X(\eta))F$, $Q^a \to Q^n(I + X(\eta))$
    (left) of the residual and $F \to F(I + X(\eta))$, $Q^a \to Q^{n+1}(I + X(\eta))$ (right)
    of the outgoing momentum: one evaluation of $\overline{\exp}$, $\overline{\log}$ and one
    reverse pass serve both. For the Cayley map the derivative of $\overline{\log}$ is
    explicit (`_cayley_step`); for the exponential pair it is $\varphi_1(\mathrm{ad})^{-1}$
    (`_exponential_step`), not traced through the logarithm's algorithm. Returns
    `(r, mu1, Q1)`; `mu1` is None unless `outgoing`, and `Q1` may be None when `outgoing` is
    False, or (for the Cayley map) when `need_Q1` is False: a march that does not carry Q skips
    its solve.

    `gradient`: $\nabla_\xi l(\xi)$ when the caller already has it, for an l without potential
    (the fixed-point sweeps iterate on it, `ReducedStep._sweep`); the Cayley map's closed form
    then uses it instead of differentiating l again. Other maps ignore it."""
    if isinstance(system.derivative_map, CayleyDifference):
        return _cayley_step(system, red, scheme, dt, mu, Q0, xi, outgoing, need_Q1, gradient)
    if getattr(system.derivative_map, "exponential_pair", False) and isinstance(red, MatrixGroupReduction):
        return _exponential_step(system, red, scheme, dt, mu, Q0, xi, outgoing)
    F = system.derivative_map.exp(dt * red.X(xi))
    Q1 = Q0 @ F
    Qa = Q0 if scheme == "left" else Q1
    if system.has_potential:
        G_F, G_Q = jax.grad(lambda f, q: reduced_lagrangian(system, red, scheme, dt, f, q), argnums=(0, 1))(F, Qa)
    else:
        G_F, G_Q = jax.grad(lambda f: reduced_lagrangian(system, red, scheme, dt, f, Qa))(F), None
    r = mu - red.X_adjoint(G_F @ F.T)
    if G_Q is not None and scheme == "left":
        r = r + red.X_adjoint(Q0.T @ G_Q)
    if not outgoing:
        return r, None, Q1
    mu1 = red.X_adjoint(F.T @ G_F)
    if G_Q is not None and scheme == "right":
        mu1 = mu1 + red.X_adjoint(Q1.T @ G_Q)
    return r, mu1, Q1


def _cayley_step(system, red, scheme, dt, mu, Q0, xi, outgoing, need_Q1=True, gradient=None):
    r"""`reduced_step` for the Cayley pair $\overline{\exp}(Y) = (I - Y/2)^{-1}(I + Y/2)$,
    $\overline{\log}(A) = 2(A + I)^{-1}(A - I)$ (Example 30), in closed form.

    With $L = \overline{\log}(A)$ the derivative of the Cayley logarithm is
    $d\overline{\log}_A[V] = (I - L/2)\,V\,(I - L/2)$ (from $(A + I)^{-1} = (I - L/2)/2$), and at
    $F = \overline{\exp}(Y)$, $L = Y$ and $F(I - Y/2) = (I - Y/2)F = I + Y/2$. So with
    $Y = \Delta t X(\xi)$, $F_\mp = I \mp Y/2$ and $P$ the matrix with
    $\langle P, M\rangle = \nabla_\xi l \cdot X^{-1}(M)$:

    $$ \partial_\eta\, \ell_d((I - X(\eta))F)\big|_0 = -X^T(F_-^T P F_+^T), \qquad
       \partial_\eta\, \ell_d(F(I + X(\eta)))\big|_0 = X^T(F_+^T P F_-^T) , $$

    the discrete Euler–Poincaré equation of the CAY method for any matrix group, with no
    matrix solve and no logarithm (ξ(F) = ξ: the Cayley pair is an exact inverse pair, and
    $\overline{\log}(F^{-1}) = -\overline{\log}(F)$ makes both schemes use it). F itself is
    formed only for $Q^{n+1}$ (`outgoing`) or a potential evaluated at $Q^{n+1}$ (right scheme).
    The potential terms are those of `reduced_step`, with $G_Q = \Delta t\,\partial l/\partial Q$.
    Both momentum maps are evaluated as the polynomial `cayley_polynomial(red)` when the
    algebra has one, else as the matrix products written here, in the reduction's form
    (`clebsch_jax.core.representation`): real matrices with ᵀ, or a declared representation's
    own products and adjoint (complex n×n with ᴴ for `UnitaryAlgebra`, where the same
    variations under the pairing Re tr(AᴴB) give the same formulas with ᵀ → ᴴ).

    **Round-off.** $\mu^{n+1}$ and $Q^{n+1}$ are formed as the old value plus an $O(\Delta t)$
    increment — $\mu^{n+1} = \mu^n + X^T(Y^TP - PY^T)$ (exact at the root, since
    $F_+^TPF_-^T - F_-^TPF_+^T = Y^TP - PY^T$) and $Q^{n+1} = Q^n + Q^n(I - Y/2)^{-1}Y$ — not as
    new products of O(1) matrices. The rounding error of a step is then ε times the small
    increment, and the invariants drift like a random walk, √n·ε (Brouwer's law; Hairer,
    McLachlan & Razakarivony 2008): over 2·10⁵ rigid-body steps the Casimir and the spatial
    momentum drift 0.40 and 0.28 √n·ε (log-log slopes 0.48, 0.54) instead of 5.5 and 9.2
    (slopes 0.69, 0.84) with the products."""
    Y = dt * red.X(xi)
    n = Y.shape[-1]
    eye = jnp.eye(n, dtype=Y.dtype)
    Fm = eye - 0.5 * Y
    mm, dag = red.matmul, red.dagger  # the representation's products and adjoint (ᵀ or ᴴ)
    need_F = (outgoing and need_Q1) or (system.has_potential and scheme == "right")
    # F = lie.cayley_exp(Y), with its products written out for XLA to fuse
    # Q¹ = Q⁰F as Q⁰ + Q⁰(F − I), F − I = (I − Y/2)⁻¹Y: an O(Δt) increment (see the docstring)
    Q1 = _cayley_update(red, Fm, Y, Q0) if need_F else None
    Qa = Q0 if scheme == "left" else Q1
    if system.has_potential:
        g, g_Q = jax.grad(system.l, argnums=(0, 1))(xi, Qa)
    elif gradient is not None:
        g, g_Q = gradient, None
    else:
        g, g_Q = jax.grad(lambda x: system.l(x, Q0))(xi), None
    poly = cayley_polynomial(red)
    if poly is not None:  # the same two maps as polynomials in (ξ, g): see `CayleyPolynomial`
        even, odd = poly(dt, xi, g)
        r = mu - even - odd
    elif red.skew_adjoint:  # Y† = −Y: both maps from C = YP (`RealMatrices.cayley_parts`)
        even, odd = red.cayley_parts(Y, red.X_inv_adjoint(g))
        r = mu - even - odd
    else:
        P = red.X_inv_adjoint(g)
        r = mu - red.X_adjoint(mm(mm(dag(Fm), P), dag(eye + 0.5 * Y)))
    if g_Q is not None and scheme == "left":
        r = r + dt * red.X_adjoint(mm(Q0.T, g_Q))
    if not outgoing:
        return r, None, Q1
    # μ¹ = Xᵀ(F₊ᵀPF₋ᵀ) as μ plus its increment: F₊ᵀPF₋ᵀ − F₋ᵀPF₊ᵀ = YᵀP − PYᵀ, and at the
    # root Xᵀ(F₋ᵀPF₊ᵀ) = μ (+ the left potential term); ᵀ is the representation's adjoint
    if poly is not None or red.skew_adjoint:
        mu1 = mu - 2.0 * odd
    else:
        mu1 = mu + red.X_adjoint(mm(dag(Y), P) - mm(P, dag(Y)))
    if g_Q is not None and scheme == "left":
        mu1 = mu1 + dt * red.X_adjoint(mm(Q0.T, g_Q))
    if g_Q is not None and scheme == "right":
        mu1 = mu1 + dt * red.X_adjoint(mm(Q1.T, g_Q))
    return r, mu1, Q1


def _cayley_update(red, Fm, Y, Q0):
    r"""$Q^1 = Q^0 + Q^0(I - Y/2)^{-1}Y$, the increment $(I - Y/2)^{-1}Y = \overline{\exp}(Y) - I$.

    On $\mathfrak{so}(3)$ (`_skew3`: $Y = \hat y$, $Y^2 = yy^T - |y|^2 I$, $Y^3 = -|y|^2 Y$) the
    increment is $(Y + Y^2/2)/(1 + |y|^2/4)$, so a row $q$ of $Q^0$ moves by
    $(a + \tfrac12\, a \times y)/(1 + |y|^2/4)$ with $a = q \times y = qY$ (and
    $a \times y = qY^2$): a few dozen products instead of a 3×3 solve with its refinement step
    (the heavy top forms $Q^1$ in both half steps' outgoing values and, with its potential, in
    every residual). Elsewhere the representation's solve.

    **The same bits in every layout.** XLA's CPU backend contracts a product that feeds an
    addition into a fused multiply-add; when both operands of an addition are products, which
    one it contracts depends on how LLVM orders and shares them, and that depends on the layout
    of the fusion around the step (one trajectory, a `jax.vmap` batch, `cj.batch`'s batch-last
    layout). Written as $(Y + Y^2/2)\,r$ with $|y|^2$ and $q\cdot y$ as sums of products, the
    update rounded differently alone and in a batch. Here every addition has at most one
    inexact product among its operands, or is a difference of two (the cross products, whose
    order LLVM keeps): $1 + |y|^2/4$ is accumulated from 1 with the exact products $y_k^2/4$,
    the ½ and ¼ are exact, and $Q^1 = Q^0 + r\,T$ adds one product to data. Every layout then
    contracts the same products."""
    if not _skew3(red):
        return Q0 + red.from_ambient(red.matmul(red.to_ambient(Q0), red.solve(Fm, Y)))
    y = [Y[..., 2, 1, None], Y[..., 0, 2, None], Y[..., 1, 0, None]]  # (…, 1): broadcast over rows
    c = [Q0[..., :, j] for j in range(3)]  # the columns of Q⁰: component j of every row q

    def cross(u):  # u × y, each component a difference of two products
        return [u[(j + 1) % 3] * y[(j + 2) % 3] - u[(j + 2) % 3] * y[(j + 1) % 3] for j in range(3)]

    a = cross(c)
    b = cross(a)
    d = 1.0
    for v in y:  # 1 + |y|²/4, accumulated from 1: each term is an exact product (¼ of a square)
        d = d + 0.25 * (v * v)
    r = 1.0 / d
    return jnp.stack([c[j] + r * (a[j] + 0.5 * b[j]) for j in range(3)], axis=-1)


@functools.lru_cache(maxsize=64)
def _skew3(red) -> bool:
    """Whether `red` is a `MatrixGroupReduction` of an algebra of skew 3×3 matrices (so(3))."""
    if not isinstance(red, MatrixGroupReduction) or red.basis.shape[1:] != (3, 3):
        return False
    return bool(np.array_equal(red.basis, -np.swapaxes(red.basis, 1, 2)))


def _exponential_step(system, red, scheme, dt, mu, Q0, xi, outgoing):
    r"""`reduced_step` for the exponential pair ($\overline{\exp} = \exp$, $\overline{\log}$ the
    principal logarithm), with the derivative of the logarithm in closed form.

    At $F = \exp(Y)$, $Y = \Delta t X(\xi)$, $\log F = Y$ and, to first order in Z,
    $\log(e^{Z}F) = Y + \varphi_1(\mathrm{ad}_Y)^{-1}Z$ and $\log(F e^{Z}) = Y +
    \varphi_1(-\mathrm{ad}_Y)^{-1}Z$, with $\varphi_1(z) = (e^z - 1)/z$ (the derivative of the
    exponential). In the algebra's coordinates $\mathrm{ad}_Y$ is the m×m matrix $A$ with
    $[Y, X(e_b)] = X(A e_b)$, so with $g = \nabla_\xi l$

    $$ X^T(G_F F^T) = \varphi_1(A)^{-T} g, \qquad X^T(F^T G_F) = \varphi_1(-A)^{-T} g , $$

    the two maps `reduced_step` takes from the ambient gradient $G_F$ of $\ell_d$: the same
    equations as differentiating `log` (which goes through every step of the matrix
    logarithm's algorithm in reverse mode), for $|Y|$ below the logarithm's branch cut.
    $e^A$ and $\varphi_1(A)$ come from `lie.exp_and_phi1`, and $\varphi_1(-A) = e^{-A}\varphi_1(A)$
    gives the second map from the first solve. Both schemes give the same $\xi(F)$ for this
    pair ($\log F^{-1} = -\log F$); the potential terms are those of `reduced_step`, with
    $G_Q = \Delta t\,\partial l/\partial Q$."""
    y = dt * jnp.ravel(xi)
    C = _ad_constants(red)  # A = Σ_a y_a C[a]
    E, Phi = lie.exp_and_phi1(jnp.tensordot(y, jnp.asarray(C, y.dtype), axes=1))
    need_F = outgoing or (system.has_potential and scheme == "right")
    Q1 = Q0 @ system.derivative_map.exp(dt * red.X(xi)) if need_F else None
    Qa = Q0 if scheme == "left" else Q1
    if system.has_potential:
        g, g_Q = jax.grad(system.l, argnums=(0, 1))(xi, Qa)
    else:
        g, g_Q = jax.grad(lambda x: system.l(x, Q0))(xi), None
    w = _linalg.solve(Phi.T, jnp.ravel(g))  # φ₁(A)^{-T} g
    r = mu - w.reshape(xi.shape)
    if g_Q is not None and scheme == "left":
        r = r + dt * red.X_adjoint(Q0.T @ g_Q)
    if not outgoing:
        return r, None, Q1
    # φ₁(-A) = e^{-A} φ₁(A), so φ₁(-A)^{-T} g = (e^A)^T φ₁(A)^{-T} g: no second solve; as
    # `outgoing_body_momentum`, no term of the left potential
    mu1 = (E.T @ w).reshape(xi.shape)
    if g_Q is not None and scheme == "right":
        mu1 = mu1 + dt * red.X_adjoint(Q1.T @ g_Q)
    return r, mu1, Q1


@functools.lru_cache(maxsize=64)
def _ad_constants(red: MatrixGroupReduction) -> np.ndarray:
    r"""C (m, m, m) with $[X(e_a), X(e_b)] = X(C[a] e_b)$: the algebra's structure constants in
    its basis (NumPy, found once per reduction), so that $\mathrm{ad}_{X(y)} = \sum_a y_a C[a]$."""
    B = red.basis
    m = B.shape[0]
    brackets = np.einsum("aij,bjk->abik", B, B) - np.einsum("bij,ajk->abik", B, B)  # [X_a, X_b]
    coords = np.einsum("ln,abn->abl", red.pinv, brackets.reshape(m, m, -1))  # X^{-1} of each
    C = np.swapaxes(coords, 1, 2)  # C[a][:, b] = X^{-1}[X_a, X_b]
    cut = 1e-14 * max(np.max(np.abs(C)), 1e-300)
    return np.where(np.abs(C) > cut, C, 0.0)


POLYNOMIAL_MAX_TERMS = 512
"""`cayley_polynomial` gives up (the matrix form is used) above this many nonzero coefficients."""


@dataclasses.dataclass(frozen=True, eq=False)
class CayleyPolynomial:
    r"""The Cayley step's momentum maps as polynomials on the algebra's coordinates.

    With $Y = \Delta t\,X(\xi)$, $P = X^{-T}g$ ($g = \nabla_\xi l$) and $F_\mp = I \mp Y/2$,

    $$ X^T(F_-^T P F_+^T) = A_0 g + \Delta t\, A_1(\xi, g) + \Delta t^2 A_2(\xi, \xi, g), $$

    $A_0 g = X^T(P)$, $A_1(\xi, g) = \tfrac12 X^T(PX(\xi)^T - X(\xi)^TP)$ and
    $A_2(\xi, \xi, g) = -\tfrac14 X^T(X(\xi)^TPX(\xi)^T)$: the residual is
    $\mu^n - A_0g - \Delta t A_1 - \Delta t^2 A_2$ and the outgoing increment
    $X^T(Y^TP - PY^T) = -2\Delta t A_1$. The coefficient tensors follow from the basis alone
    (structure constants of the algebra, found once per reduction in NumPy). They are very
    sparse — 18 nonzero coefficients for so(3) where the matrix form makes two 3×3 products,
    the adjoint maps around them and the matrices' layout changes — so the residual is a few
    dozen scalar multiply-adds, which XLA fuses. Same equations, different rounding. XLA on the
    CPU runs each small operation with a fixed cost, so fewer operations make a single
    trajectory faster and quicker to compile; in a batch (`vmap`, `clebsch_jax.batch`) that
    cost is shared by the members and the Newton loop's own operations, not the residual, take
    the time (the runs: `benchmarks/README.md`, "Notes: making the reduced step cheap").

    `terms[d][k]` lists, for component k of the degree-d part (in ξ), pairs of a coefficient
    and the indices of the ξ and g factors, `(c, (i, ..., l))`: g's index last."""

    terms: tuple

    def __call__(self, dt, xi, g):
        """`(A₀g + Δt²A₂(ξ, ξ, g), Δt A₁(ξ, g))`, the parts even and odd in Δt, shaped like ξ."""
        # the scalars, each indexed once (tracing an index is not cheap), and the products ξᵢξⱼ
        # that occur, formed once each
        x, gg = _unstack(jnp.ravel(xi)), _unstack(jnp.ravel(g))
        x2, dtype = {}, jnp.result_type(xi, g)

        def factor(ix):
            if len(ix) == 1:
                return gg[ix[0]]
            if len(ix) == 2:
                return x[ix[0]] * gg[ix[1]]
            if ix[:2] not in x2:
                x2[ix[:2]] = x[ix[0]] * x[ix[1]]
            return x2[ix[:2]] * gg[ix[2]]

        def part(d, k):
            return _linalg.weighted_sum(((c, factor(ix)) for c, ix in self.terms[d][k]), dtype)

        m = len(self.terms[0])
        even = jnp.stack([part(0, k) + (dt * dt) * part(2, k) for k in range(m)]).reshape(xi.shape)
        odd = jnp.stack([dt * part(1, k) for k in range(m)]).reshape(xi.shape)
        return even, odd


def _unstack(v):
    return [jnp.squeeze(p, 0) for p in jnp.split(v, v.shape[0])] if v.shape[0] > 1 else [v[0]]


@functools.lru_cache(maxsize=64)
def cayley_polynomial(red: MatrixGroupReduction) -> CayleyPolynomial | None:
    """The `CayleyPolynomial` of `red`'s algebra, or None when it has more than
    `POLYNOMIAL_MAX_TERMS` nonzero coefficients (large algebras: the matrix form is cheaper).
    Coefficients below 1e-14 of the largest, the round-off of the pseudo-inverse, count as zero
    (as in `_constant_map`)."""
    if not isinstance(red, MatrixGroupReduction):
        return None  # ξ is the matrix: the products are the cheap form
    basis = red.basis
    m, n = basis.shape[0], basis.shape[1]
    P = red.pinv.reshape(m, n, n)  # P[l] = X^{-T} e_l
    XT = lambda M: np.einsum("kab,...ab->...k", basis, M)  # output index k last
    Xt = np.swapaxes(basis, 1, 2)  # X(e_i)^T
    A0 = XT(P)  # [l, k]
    # [i, l, k]: ½ Xᵀ(P_l X_iᵀ − X_iᵀ P_l)
    A1 = 0.5 * XT(np.einsum("lab,ibc->ilac", P, Xt) - np.einsum("iab,lbc->ilac", Xt, P))
    # [i, j, l, k]: −¼ Xᵀ(X_iᵀ P_l X_jᵀ), summed over both orders of (i, j) for i < j (the
    # products ξᵢξⱼ are formed for i ≤ j only); i = j once
    A2 = -0.25 * XT(np.einsum("iab,lbc,jcd->ijlad", Xt, P, Xt))
    A2 = A2 + np.swapaxes(A2, 0, 1)
    A2[np.arange(m), np.arange(m)] *= 0.5
    cut = 1e-14 * max(np.max(np.abs(A0)), np.max(np.abs(A1)), np.max(np.abs(A2)), 1e-300)

    def nonzero(A, factors):  # per output k: (coefficient, factor indices) where it is not zero
        return tuple(tuple((float(A[ix + (k,)]), ix) for ix in factors if abs(A[ix + (k,)]) > cut) for k in range(m))

    pairs = [(i, j) for i in range(m) for j in range(i, m)]
    terms = (
        nonzero(A0, [(l,) for l in range(m)]),
        nonzero(A1, [(i, l) for i in range(m) for l in range(m)]),
        nonzero(A2, [ij + (l,) for ij in pairs for l in range(m)]),
    )
    if sum(len(t) for part in terms for t in part) > POLYNOMIAL_MAX_TERMS:
        return None
    return CayleyPolynomial(terms=terms)
