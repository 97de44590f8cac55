r"""The Gauss–Legendre discretisation of the Clebsch principle (the paper's outlook: higher order
through partitioned Runge–Kutta discretisations).

The Clebsch action $\int l(\xi, Q) + \langle P, \dot Q - \mathcal L_\xi Q\rangle\,dt$ is the
phase-space action $\int \langle P, \dot Q\rangle - H\,dt$ of the *Clebsch Hamiltonian*

$$ H(\xi, Q, P) = \langle P, \mathcal L_\xi Q\rangle - l(\xi, Q), $$

extremised over $\xi$ pointwise in time. Discretising it with the quadrature and the
collocation polynomial of the s-stage Gauss–Legendre method (the variational partitioned
Runge–Kutta construction: Marsden & West, Acta Numerica 2001, §2.6.5; Hairer, Lubich & Wanner,
*Geometric Numerical Integration*, §VI.6.3) gives, for the stage values $(\xi_i, Q_i, P_i)$ of
a step of size h from $(Q^n, P^n)$,

$$ Q_i = Q^n + h\sum_j a_{ij}\,\partial_P H_j, \qquad P_i = P^n - h\sum_j a_{ij}\,\partial_Q H_j,
   \qquad \partial_\xi H(\xi_i, Q_i, P_i) = 0, $$

and $Q^{n+1} = Q^n + h\sum_i b_i\,\partial_P H_i$, $P^{n+1} = P^n - h\sum_i b_i\,\partial_Q H_i$:
the Gauss method on both parts (for Gauss the adjoint coefficients $b_j - b_j a_{ji}/b_i$ of the
P part are $a_{ij}$ again). The third equation is the Clebsch relation
$\delta l/\delta\xi = \partial_\xi\langle P, \mathcal L_\xi Q\rangle$ at each stage. Every
derivative is `jax.grad` of H: nothing model-specific is written by hand.

Facts: order 2s, symmetric, symplectic in $(Q, P)$; it keeps every quadratic invariant of the
Clebsch equations exactly — in particular the momentum map of every linear symmetry (Noether)
and, for a velocity map linear in Q, the invariants of the linear flow ($Q^TQ$ on $SO(n)$,
$|Q|^2$, $|P|^2$, $Q\cdot P$ on $\mathbb R^3$). It is G-equivariant for linear actions, so on
a Clebsch representation of $\mathfrak{so}(3)^*$ it descends to a Lie–Poisson map of the body
momentum that keeps the Casimir $|\Pi|^2$ to round-off (McLachlan, Modin & Verdier, *Collective
symplectic integrators*, Nonlinearity 27 (2014) 1525). The derivative map of the system is not
used: the collocation polynomial supplies $\dot Q$. One stage is the implicit midpoint rule
(the midpoint principle with `forward_difference`).

**Degenerate Lagrangians** (l affine in ξ, `degenerate=True`: point vortices). H is then affine
in ξ, and the third equation, $C(Q_i, P_i) := \partial_\xi H = 0$, no longer involves $\xi_i$: it
constrains the stage values, and the $\xi_i$ are the multipliers that keep them on it (as the
midpoint principle does for one stage). `degenerate_sweep` corrects them through the constraints'
Poisson-bracket matrix $\{C_a, C_b\}$ (formed by autodiff once per step); its fixed points are
the same stage equations. For point vortices ($C = P - \theta(Q)$ with θ linear) the method is
the Gauss collocation of the vortex equations, and it keeps the constraint, the linear and the
angular impulse exactly.

**Round-off.** The symplecticity condition $b_ia_{ij} + b_ja_{ji} = b_ib_j$ does not hold
exactly for rounded coefficients, and its residue (the coefficients' round-off) makes
quadratic invariants drift linearly, by the same bias every step. As proposed by
Antoñana, Makazaga & Murua (SIAM J. Sci. Comput. 39 (2017) A2411) the stages are written with
$\mu_{ij} = a_{ij}/b_j$ and the increments $\Delta Q_j = h b_j \dot Q_j$,
$Q_i = Q^n + \sum_j\mu_{ij}\Delta Q_j$: the condition becomes $\mu_{ij} + \mu_{ji} = 1$, which
the stored μ satisfy exactly in floating point ($\mu_{ii} = 1/2$; of each pair the entry below
1/2 is stored as 1 minus the other, exact by Sterbenz's lemma). The drift then becomes a
random walk of round-off (`tests/test_gauss.py`, `test_invariants_rigid_body`: |Q|², |P|², Q·P
and |Π|² over 4000 steps of order 8).
Two more sources of round-off are the state update and the iteration's leftover:
`gauss_update` with a compensation adds the increments by compensated summation (the state is
rounded at the size of the increment, not of the state), and the stepper then sweeps the
increments to their own round-off (`steppers.gauss.GaussLegendre(compensated=True)`, the
default). A leftover at the state's round-off is a smooth function of the state, so it drifts
the energy linearly (over 10⁶ steps, `benchmarks/README.md`); the energy error is then a random
walk of about εΔt√n (`test_compensated_summation_energy_round_off_is_a_small_random_walk`).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..core import linalg as _linalg
from ..core.system import ClebschSystem

__all__ = [
    "GaussLegendre",
    "gauss_legendre",
    "GaussUnknowns",
    "clebsch_hamiltonian",
    "stage_values",
    "stage_hessians",
    "gauss_sweep",
    "constraint_matrix_inverse",
    "degenerate_sweep",
    "gauss_update",
    "extrapolate",
    "from_substeps",
    "GAUSS_ORDERS",
]

GAUSS_ORDERS = (2, 4, 6, 8, 10, 12, 14, 16)
"""Orders `integrate(..., scheme="gauss", order=k)` accepts (k/2 stages). Above 8 they are for
large steps on smooth problems, where a high order at a large step can be both more accurate
and faster than order 8 at a small one (`benchmarks/work_precision.py`; its runs are in
`benchmarks/README.md`); the tableau keeps its order conditions to round-off up to 8 stages
(tested)."""


@dataclasses.dataclass(frozen=True)
class GaussLegendre:
    """The s-stage Gauss–Legendre tableau in the form the march uses, with its facts.

    - `c` (s,): nodes in (0, 1); `b` (s,): weights; `a` (s, s): the Butcher matrix;
    - `mu` (s, s): $a_{ij}/b_j$ with $\\mu_{ij} + \\mu_{ji} = 1$ exactly (module docstring);
    - `extrapolation` (s, s): the values at $1 + c_i$ of the Lagrange polynomials through the
      nodes $c_j$ — the next step's stage guesses from this step's stages (error O(hˢ)).
    All NumPy float64 constants (static)."""

    stages: int
    c: np.ndarray
    b: np.ndarray
    a: np.ndarray
    mu: np.ndarray
    extrapolation: np.ndarray

    @property
    def order(self) -> int:
        return 2 * self.stages

    @property
    def name(self) -> str:
        return f"Gauss-Legendre {self.stages}-stage PRK"

    symmetric = True
    symplectic = True

    def __hash__(self):
        return hash(self.stages)

    def __eq__(self, other):
        return isinstance(other, GaussLegendre) and other.stages == self.stages


def _lagrange(c, j, t):
    """The Lagrange basis polynomial of node j of the nodes c at t, in product form (stable)."""
    return np.prod([(t - c[k]) / (c[j] - c[k]) for k in range(len(c)) if k != j], axis=0)


@functools.lru_cache(maxsize=None)
def gauss_legendre(stages: int) -> GaussLegendre:
    """The `GaussLegendre` tableau with `stages` stages (order 2·stages)."""
    if not isinstance(stages, int) or stages < 1:
        raise ValueError(f"stages: expected an int >= 1, got {stages!r}.")
    x, w = np.polynomial.legendre.leggauss(stages)
    c, b = (x + 1.0) / 2.0, w / 2.0
    s = stages

    # collocation: a_ij = ∫₀^{c_i} ℓ_j, by the s-point Gauss rule on [0, c_i] (exact for the
    # degree s-1 of ℓ_j); through monomial coefficients it lost digits as s grew, while this
    # way C(s) holds to round-off up to 8 stages (tests/test_gauss.py, the order conditions)
    a = np.array([[c[i] * np.sum(b * _lagrange(c, j, c[i] * c)) for j in range(s)] for i in range(s)])
    E = np.array([[_lagrange(c, j, 1.0 + c[i]) for j in range(s)] for i in range(s)])
    mu = a / b[None, :]
    for i in range(s):
        mu[i, i] = 0.5
        for j in range(i + 1, s):  # keep the entry >= 1/2; the other is 1 minus it, exactly
            if mu[i, j] >= 0.5:
                mu[j, i] = 1.0 - mu[i, j]
            else:
                mu[i, j] = 1.0 - mu[j, i]
    return GaussLegendre(stages=s, c=c, b=b, a=a, mu=mu, extrapolation=E)


class GaussUnknowns(NamedTuple):
    """The unknowns of a Gauss–Legendre step, stacked over stages (leading axis s): the stage
    velocities ξᵢ and the increments ΔQᵢ = h bᵢ ∂H/∂P, ΔPᵢ = −h bᵢ ∂H/∂Q."""

    xi: jax.Array
    dQ: jax.Array
    dP: jax.Array


def clebsch_hamiltonian(system: ClebschSystem, xi, Q, P) -> jax.Array:
    r"""$H(\xi, Q, P) = \langle P, \mathcal L_\xi Q\rangle - l(\xi, Q)$ (module docstring)."""
    return jnp.sum(P * system.velocity_map(xi, Q)) - system.l(xi, Q)


def _constraint(system: ClebschSystem, xi, Q, P):
    r"""$\partial_\xi H(\xi, Q, P) = \partial_\xi\langle P, \mathcal L_\xi Q\rangle - \delta l/\delta\xi$:
    the residual of the Clebsch relation (for a degenerate l, a constraint on (Q, P))."""
    return jax.grad(clebsch_hamiltonian, argnums=1)(system, xi, Q, P)


def _flow(system: ClebschSystem, xi, Q, P):
    r"""The Hamiltonian vector field of H at fixed ξ: $(\dot Q, \dot P) = (\partial_P H, -\partial_Q H)$."""
    dH_dQ, dH_dP = jax.grad(clebsch_hamiltonian, argnums=(2, 3))(system, xi, Q, P)
    return dH_dP, -dH_dQ


def _constraint_flow(system: ClebschSystem, xi, d, Q, P):
    r"""The Hamiltonian vector field of $\langle d, \partial_\xi H(\xi, \cdot)\rangle$ at (Q, P):
    how a change d of ξ moves (Q, P) (H is affine in ξ for a degenerate l)."""
    gq, gp = jax.grad(lambda q, p: jnp.sum(d * _constraint(system, xi, q, p)), argnums=(0, 1))(Q, P)
    return gp, -gq


def _per_stage(f):
    """`f` of one stage's values, mapped over the stages (leading axis s) as one call: a `jit`
    inside the `vmap`. XLA inlines it (the same program as a plain `vmap`); the native
    translation can emit one stage's program once, in a loop over the stages
    (`clebsch_jax.native.row_calls`), where a plain `vmap` writes every stage's entries out."""
    return jax.vmap(jax.jit(f))


def _combine(row, d):
    """Σⱼ rowⱼ dⱼ for one row of constant (NumPy) coefficients and d stacked over stages."""
    return _linalg.weighted_sum(((float(c), dj) for c, dj in zip(row, d)), d.dtype)


def stage_values(tab: GaussLegendre, Q, P, z: GaussUnknowns):
    """The stage configurations and multipliers $Q_i, P_i$ (leading axis s)."""
    Qi = jnp.stack([Q + _combine(row, z.dQ) for row in tab.mu])
    Pi = jnp.stack([P + _combine(row, z.dP) for row in tab.mu])
    return Qi, Pi


def stage_hessians(system: ClebschSystem, tab: GaussLegendre, Q, P, z: GaussUnknowns):
    """The inverse Hessians of l in ξ at the stage values of `z` (s, dim V, dim V): the matrix
    of the Newton updates of the Clebsch relations in `gauss_sweep`, formed once per step at the
    guess (the Hessian moves little within a step; for l quadratic in ξ it is constant)."""
    Qi, _ = stage_values(tab, Q, P, z)

    def one(xi, q):
        hess = jax.hessian(lambda x: system.l(x.reshape(xi.shape), q))(xi.ravel())
        return _linalg.inverse(hess)[0]

    return jax.vmap(one)(z.xi, Qi)


def gauss_sweep(
    system: ClebschSystem, tab: GaussLegendre, h, Q, P, z: GaussUnknowns, inverse_hessians=None
) -> GaussUnknowns:
    r"""One sweep of the iteration whose fixed point is the Gauss–Legendre step.

    From the stage values of `z`: one Newton update of each stage's Clebsch relation
    $\partial_\xi H(\xi_i, Q_i, P_i) = 0$ in $\xi_i$, with the inverse Hessians of l in ξ
    `inverse_hessians` (`stage_hessians`; formed here at `z` if None) — exact in one update
    for l quadratic in ξ — then the increments $\Delta Q_i, \Delta P_i$ at the updated
    $\xi_i$. A contraction for small enough h (at moderate steps a sweep gains about one
    digit). Its fixed points are the solutions of the stage equations whatever the matrices,
    as long as they are invertible."""
    Qi, Pi = stage_values(tab, Q, P, z)
    if inverse_hessians is None:
        inverse_hessians = stage_hessians(system, tab, Q, P, z)

    def one(xi, q, p, hinv):
        r = _constraint(system, xi, q, p)  # ∂ξ⟨p, L_ξ q⟩ − δl/δξ
        xi = xi + _linalg.matvec(hinv, r.ravel()).reshape(xi.shape)
        return (xi,) + _flow(system, xi, q, p)

    xi, Qdot, Pdot = _per_stage(one)(z.xi, Qi, Pi, inverse_hessians)
    w = jnp.asarray(tab.b, dtype=Qdot.dtype).reshape((-1,) + (1,) * (Qdot.ndim - 1)) * h
    return GaussUnknowns(xi=xi, dQ=w * Qdot, dP=w * Pdot)


def constraint_matrix_inverse(system: ClebschSystem, xi, Q, P, *, blocks: bool = False):
    r"""For a degenerate system: the inverse of the matrix $M$ of the constraints' Poisson
    brackets, $M_{ab} = \{C_a, C_b\}$ at $(Q, P)$, with $C(Q, P) = \partial_\xi H$ (for l
    affine in ξ, H is affine in ξ and C does not depend on it). $M\delta\xi$ is the rate at
    which C changes along the flow of the Hamiltonian $\langle\delta\xi, C\rangle$, so a change
    δξ of the stage velocities moves the stage constraints by $h(A\otimes M)\delta\xi$
    (`degenerate_sweep`). Built by autodiff.

    - `blocks=False`: M whole (dim V JVPs), inverted by LU;
    - `blocks=True`: for particles (ξ of shape (N, …)), M *lumped* into one k×k block per
      particle, $M_a = \sum_b M_{ab}$ (k = ξ.size / N JVPs, the tangent on one component of
      every particle at once), inverted block by block: exact where M is block diagonal (point
      vortices: $-\Gamma_a J$ per vortex), a preconditioner otherwise (the sweep's fixed points do
      not depend on M).

    Returns (inverse, singular): (dim V, dim V) or (N, k, k)."""

    def bracket(d):  # M d: the derivative of C along the Hamiltonian vector field of ⟨d, C⟩
        tangent = _constraint_flow(system, xi, d.reshape(xi.shape), Q, P)
        return jax.jvp(lambda q, p: _constraint(system, xi, q, p), (Q, P), tangent)[1]

    if not blocks:
        M = jax.jacfwd(lambda d: bracket(d).ravel())(jnp.zeros(xi.size, Q.dtype))
        return _linalg.inverse(M)
    n, k = xi.shape[0], xi.size // xi.shape[0]
    eye = jnp.eye(k, dtype=Q.dtype)
    cols = [bracket(jnp.broadcast_to(eye[c], (n, k))).reshape(n, k) for c in range(k)]
    inverse, singular = _linalg.inverse(jnp.stack(cols, axis=-1))  # (N, k, k): column c from tangent c
    return inverse, jnp.any(singular)


def degenerate_sweep(
    system: ClebschSystem, tab: GaussLegendre, h, Q, P, z: GaussUnknowns, constraint_inverse
) -> GaussUnknowns:
    r"""One sweep of the Gauss–Legendre step of a *degenerate* system (l affine in ξ, so
    $\partial_\xi H$ does not involve ξ and the stage Clebsch relations $C(Q_i, P_i) = 0$ are
    constraints on the stage values that ξ enforces as a multiplier).

    1. Stage values from the increments, and the increments they give at the current ξ
       (`gauss_sweep`'s slopes): $\Delta\tilde Y_i = h b_i X_H(\xi_i, Y_i)$, Y = (Q, P);
    2. the constraints at the stage values those increments make, $\tilde C_i$;
    3. the velocities that cancel them to first order: $h(A\otimes M)\,\delta\xi = -\tilde C$,
       $\delta\xi_i = -h^{-1} M^{-1}\sum_j (A^{-1})_{ij}\tilde C_j$, with `constraint_inverse`
       $= M^{-1}$ (`constraint_matrix_inverse`, formed once per step; whole, or as per-particle
       blocks of shape (N, k, k));
    4. the increments at the new velocities, $\Delta\tilde Y_i + h b_i X_{\langle\delta\xi_i,
       C\rangle}(Y_i)$ (H is affine in ξ: no second evaluation of its ξ-free part, the
       potential).

    Its fixed points are the Gauss–Legendre stage equations (δξ = 0 there, whatever M). For
    point vortices (C = P − θ(Q) linear) a sweep is exactly the fixed-point sweep of the Gauss
    collocation of the vortex ODE: step 3 returns $\xi_i = \dot Q(Q_i)$."""
    Qi, Pi = stage_values(tab, Q, P, z)
    w = jnp.asarray(tab.b, dtype=Q.dtype).reshape((-1,) + (1,) * Q.ndim) * h

    Qdot, Pdot = _per_stage(lambda xi, q, p: _flow(system, xi, q, p))(z.xi, Qi, Pi)
    trial = GaussUnknowns(xi=z.xi, dQ=w * Qdot, dP=w * Pdot)
    Qt, Pt = stage_values(tab, Q, P, trial)
    C = _per_stage(lambda xi, q, p: _constraint(system, xi, q, p))(z.xi, Qt, Pt)
    a_inv = np.linalg.inv(tab.a)
    mixed = jnp.stack([_combine(row, C) for row in a_inv])
    if constraint_inverse.ndim == 3:  # lumped blocks, one per particle
        n = z.xi.shape[1]
        dxi = jax.vmap(lambda c: _linalg.matvec(constraint_inverse, c.reshape(n, -1)))(mixed)
    else:
        dxi = jax.vmap(lambda c: _linalg.matvec(constraint_inverse, c.ravel()))(mixed)
    dxi = -dxi.reshape(z.xi.shape) / h

    cQ, cP = _per_stage(lambda xi, d, q, p: _constraint_flow(system, xi, d, q, p))(z.xi, dxi, Qi, Pi)
    return GaussUnknowns(xi=z.xi + dxi, dQ=trial.dQ + w * cQ, dP=trial.dP + w * cP)


def gauss_update(Q, P, z: GaussUnknowns, compensation=None):
    r"""The step's end point $(Q^{n+1}, P^{n+1}) = (Q^n + \sum_i \Delta Q_i, P^n + \sum_i \Delta P_i)$.

    With `compensation` = $(c_Q, c_P)$ (arrays like Q and P, zeros at the start) the sums are
    compensated (Kahan): the increment $d = \sum_i \Delta Q_i + c_Q$ is added as
    $Q^{n+1} = \mathrm{fl}(Q^n + d)$, and $c_Q = (Q^n + d) - Q^{n+1}$, the part of d that
    rounding $Q^{n+1}$ lost (exactly, by Knuth's TwoSum: entries of Q may be smaller than their
    increments), is added to the next step's increment. A step then rounds the state at the size of its increment, not of the state,
    so round-off no longer accumulates at $\varepsilon|Q|$ per step (Hairer, McLachlan &
    Razakarivony, *Achieving Brouwer's law with implicit Runge–Kutta methods*, BIT 48 (2008)
    231). **Returns:** `(Q1, P1)`, or `(Q1, P1, compensation1)` when `compensation` is given."""
    dQ, dP = jnp.sum(z.dQ, axis=0), jnp.sum(z.dP, axis=0)
    if compensation is None:
        return Q + dQ, P + dP
    (Q1, cQ), (P1, cP) = _compensated_sum(Q, dQ, compensation[0]), _compensated_sum(P, dP, compensation[1])
    return Q1, P1, (cQ, cP)


def _compensated_sum(x, d, c):
    """x + (d + c) rounded, and exactly what the rounding lost (Knuth's TwoSum, 6 operations,
    exact for any magnitudes in round-to-nearest; both backends keep its order: no fast-math)."""
    d = d + c
    x1 = x + d
    d_part = x1 - x
    return x1, (x - (x1 - d_part)) + (d - d_part)


def extrapolate(tab: GaussLegendre, z: GaussUnknowns) -> GaussUnknowns:
    """The guess for the next step's stages: the collocation polynomials of ξ and of the stage
    derivatives through this step's stages, continued to the next step's nodes (error O(hˢ);
    a guess through the stages of the last two steps is worse: stage values are only accurate
    to O(hˢ⁺¹), and extrapolating them further amplifies that). The increments carry the
    weights h·bⱼ, divided out and put back."""
    E = tab.extrapolation
    scale = E * (tab.b[:, None] / tab.b[None, :])
    return GaussUnknowns(
        xi=jnp.stack([_combine(row, z.xi) for row in E]),
        dQ=jnp.stack([_combine(row, z.dQ) for row in scale]),
        dP=jnp.stack([_combine(row, z.dP) for row in scale]),
    )


def from_substeps(tab: GaussLegendre, zs: GaussUnknowns) -> GaussUnknowns:
    """The stage guess of a step from the solved unknowns `zs` (leading axis k) of k equal
    substeps that cover it: each node $c_i$ of the step falls in substep m at local time τ,
    where that substep's collocation polynomials give ξ and the slope; the increment is the
    slope times $h b_i$. The error is that of interpolating inside a substep, O((h/k)ˢ), where
    `extrapolate` continues a polynomial past its step (O(hˢ) with the large constants of
    extrapolation)."""
    k, s = zs.xi.shape[0], tab.stages
    xis, dQs, dPs = [], [], []
    for i in range(s):
        m = min(int(tab.c[i] * k), k - 1)
        row = np.array([_lagrange(tab.c, j, tab.c[i] * k - m) for j in range(s)])
        slope_row = k * tab.b[i] * row / tab.b
        xis.append(_combine(row, zs.xi[m]))
        dQs.append(_combine(slope_row, zs.dQ[m]))
        dPs.append(_combine(slope_row, zs.dP[m]))
    return GaussUnknowns(xi=jnp.stack(xis), dQ=jnp.stack(dQs), dP=jnp.stack(dPs))
