r"""Singular solutions of EPDiff (Section 3.1): peakons and landmarks.

**The continuous system.** EPDiff for a velocity field $u$ with kinetic energy
$l[u] = \tfrac12\|u\|_V^2$, where $K$ is the reproducing kernel of the norm $\|\cdot\|_V$
($u = K * m$, $m = \delta l/\delta u$), has the singular solutions
$m = \sum_b P_b\,\delta(x - Q_b)$, $u(x) = \sum_b K(x - Q_b) P_b$. In the paper's Clebsch
principle (equations 8–10) $Q$ are the particle positions, $\mathcal L_u Q = u(Q)$, $P$ the
multipliers, $\delta l/\delta u = P \diamond Q$ is that sum of delta functions, and
$\dot Q = u(Q)$, $\dot P = -(\nabla u(Q))^T P$: the geodesic equations of
$H(Q, P) = \tfrac12\sum_{a,b} P_a\cdot K(Q_a - Q_b) P_b$.

**The finite parametrisation (the engine needs ξ in a finite-dimensional V).** $u$ enters the
Clebsch constraint $\dot Q = u(Q)$ only through its values at the particles, so we take

$$ \xi = u(Q) \in \mathbb R^{N\times d}, \qquad \mathcal L_\xi Q = \xi \quad(\text{translations of the positions}), $$
$$ l(\xi, Q) = \min\{\tfrac12\|u\|_V^2 : u(Q_a) = \xi_a\} = \tfrac12\,\xi\cdot K(Q)^{-1}\xi, \qquad K(Q)_{ab} = K(Q_a - Q_b). $$

The minimiser is exactly the singular field $u = \sum_b K(\cdot - Q_b)P_b$ with $P = K(Q)^{-1}\xi$:
varying the part of $u$ that vanishes at the particles does not touch the constraint, so its
stationarity in the infinite-dimensional principle *is* this minimisation — the reduction loses
nothing. Then $\delta l/\delta\xi = K(Q)^{-1}\xi = P$ (the diamond of a translation is
$P\diamond Q = -P$), $\xi = K(Q)P$ recovers $u(Q_a) = \sum_b K(Q_a - Q_b)P_b$, and the Clebsch
equations of Lemma 20's continuous limit are Hamilton's equations of $H = \tfrac12 P\cdot K(Q)P$,
i.e. equations (9)–(10). $l$ depends on $Q$ (a "potential" in the engine's sense, Definition 14),
so `scheme="left"`/`"right"` are first order (symplectic Euler) and `scheme="midpoint"` — here
$L_d = \Delta t\, l\big((Q^{n+1}-Q^n)/\Delta t,\ (Q^n+Q^{n+1})/2\big)$ — is symmetric and second
order. `integrate`'s default is `"left"`: pass `scheme="midpoint"`.

**Closure (Definition 10).** Translations are a Lie algebra action of the abelian algebra
$\mathbb R^{N\times d}$ on itself: `check_closure` reports **closed**, with structure constants
and bracket residuals exactly zero and rank $N d$. The paper's velocity map $u \mapsto u\circ Q$ is
closed too, with the Lie bracket of vector fields; the finite parametrisation trades that bracket
for the $Q$-dependence of $l$. Theorem 16 then gives $\dot m = -\delta l/\delta Q \diamond Q =
\partial l/\partial Q$ with $m = \delta l/\delta\xi = P$ and $\mathrm{ad}^* = 0$ — Hamilton's
equations again, with nothing eliminated: since $l$ depends on $Q$, $Q$ must be kept (the engine's
reduced march, which needs right multiplication on a matrix group, does not apply; `integrate`
runs the full march). The other natural choice, ξ the momenta with $\mathcal L_\xi Q = K(Q)\xi$,
would make $l(\xi, Q) = \tfrac12\xi\cdot K(Q)\xi$ and a velocity map that is *not* closed
(`check_closure` finds bracket residuals of 2–3·10⁻² for three peakons or landmarks); the
translation form keeps the engine's contract (a linear velocity map, $l$ regular in ξ) with the
simplest closed action.

**Kernels** (width $\alpha$, an array leaf of the system, so `jax.vmap` over it sweeps widths):

- `peakons`: Camassa–Holm, $d = 1$, $K(x) = e^{-|x|/\alpha}$. Then
  $l = \frac{1}{4\alpha}\int u^2 + \alpha^2 u_x^2\,dx$, $u - \alpha^2u_{xx} = 2\alpha\sum_b P_b\delta(x - Q_b)$,
  and for $\alpha = 1$ these are the standard peakons $u = \sum_b p_b e^{-|x-q_b|}$,
  $H = \tfrac12\sum p_ap_b e^{-|q_a-q_b|}$ (a lone peakon moves at speed $p$). The kernel is not
  differentiable at 0; we use the peakon convention $K'(0) = 0$ (the average of the one-sided
  slopes): the diagonal of $K(Q)$ is the constant $K(0) = 1$, and for coincident distinct
  particles the derivative of $|x|$ is $\mathrm{sign}(0) = 0$, so all derivatives are finite.
  Q and ξ have shape (N,).
- `landmarks`: the Gaussian kernel $K(x) = e^{-|x|^2/(2\alpha^2)}\,\mathrm{Id}_d$ in $\mathbb R^d$
  (image-registration landmarks). Q and ξ have shape (N, d).

$K(Q)^{-1}\xi$ is a Cholesky solve (never an explicit inverse) with all pairwise kernel
values formed at once. $K(Q)$ is symmetric positive definite for distinct particles and
singular when two coincide (its Cholesky factor is then NaN, never plausible numbers).

**Collisions.** A peakon–antipeakon pair ($p_1 > 0 > p_2$, $q_1 < q_2$) collides at a finite
$t^*$ with momenta growing like $1/(t^*-t)$; the ODE solution ends there. With the midpoint
scheme, for the symmetric pair the discrete step before $t^*$ has no root and Newton's method
fails (`MAX_ITERATIONS`), which `integrate` reports; for a non-symmetric pair, however, the
plain forward difference lets a step find a spurious root on the far side of the collision — the
peaks pass through each other, the energy jumps by orders of magnitude, and every step reports
success.
`peakons` therefore uses `ordered_difference` by default, the forward difference defined only for
steps that keep the order of the peaks (NaN otherwise), so the step that would cross fails with
status `NONFINITE` near $t^*$. Landmarks with a Gaussian kernel do not collide in finite time but
can close in on each other exponentially with growing momenta; when $K(Q)$ becomes too
ill-conditioned for the step to be solved to round-off, Newton's method fails
(`MAX_ITERATIONS`) and `integrate` reports it.

**Companion functions** take `(Q, P_or_xi, width)` with any leading axes (time, batch) and are
differentiable and vmappable: Hamiltonians, $\xi = K(Q)P$ (`*_velocity`, the consistent `xi0`),
$P = K(Q)^{-1}\xi$ (`*_momenta`), the field $u(x)$ (`*_field`) and, for landmarks, the angular
momentum $\sum_a Q_a\times P_a$. The total momentum is $\sum_a P_a$ (`P.sum(axis=-2)` for
landmarks, `P.sum(axis=-1)` for peakons); on a solution `Solution.momentum` (= $-p\diamond Q$)
is the discrete momentum $p^n$ itself.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
from jax.tree_util import Partial

from ..core import linalg as _linalg
from ..core.derivative_maps import DerivativeMap, VectorSpaceDifference, forward_difference
from ..core.system import ClebschSystem
from ..core.validation import is_traced, nan_unless

__all__ = [
    "peakons",
    "ordered_difference",
    "OrderedDifference",
    "peakon_kernel_matrix",
    "peakon_hamiltonian",
    "peakon_velocity",
    "peakon_momenta",
    "peakon_field",
    "landmarks",
    "landmark_kernel_matrix",
    "landmark_hamiltonian",
    "landmark_velocity",
    "landmark_momenta",
    "landmark_field",
    "landmark_angular_momentum",
]


# --------------------------------------------------------------------------------------------
# Kernels: K(x) for a batch of displacements, and the pairwise matrix K(Q)_ab = K(Q_a - Q_b).


def _peakon_k(width, d):
    """e^{-|d|/α} for displacements d (any shape); d|x|/dx at 0 is sign(0) = 0 (peakon convention)."""
    return jnp.exp(-jnp.abs(d) / width)


def _gauss_k(width, d):
    """e^{-|d|²/(2α²)} for displacements d of shape (..., dim)."""
    return jnp.exp(-jnp.sum(d * d, axis=-1) / (2.0 * width * width))


def _pairwise(k, width, Q):
    """K(Q) (N, N) with the constant K(0) = 1 on the diagonal (no derivative through it)."""
    d = Q[:, None] - Q[None, :]
    eye = jnp.eye(Q.shape[0], dtype=bool)
    return jnp.where(eye, 1.0, k(width, d)).astype(Q.dtype)


def _peakon_matrix(width, Q):
    return _pairwise(_peakon_k, width, Q)


def _landmark_matrix(width, Q):
    return _pairwise(_gauss_k, width, Q)


# --------------------------------------------------------------------------------------------
# The Clebsch system: l(ξ, Q) = ½ ξ·K(Q)⁻¹ξ, L_ξ Q = ξ.


def _peakon_lagrangian(width, xi, Q):
    return 0.5 * jnp.sum(xi * _linalg.spd_solve(_peakon_matrix(width, Q), xi))


def _landmark_lagrangian(width, xi, Q):
    return 0.5 * jnp.sum(xi * _linalg.spd_solve(_landmark_matrix(width, Q), xi))


def _translation(xi, Q):
    del Q
    return xi


def _width(width) -> jax.Array:
    """The kernel width α as a float scalar, checked finite and positive when concrete; when
    traced (under `jax.jit`/`jax.vmap` over it, in `cj.sweep`) made NaN unless positive, which
    `integrate` reports as `Status.INVALID_INPUT` at step 0."""
    w = jnp.asarray(width, dtype=jnp.result_type(float))
    if w.shape != ():
        raise ValueError(f"width: expected a scalar kernel width, got shape {w.shape} (vmap over a batch of widths).")
    if is_traced(w):
        return nan_unless(w, w > 0)  # reported by integrate as Status.INVALID_INPUT
    if not (bool(w > 0) and bool(jnp.isfinite(w))):
        raise ValueError(f"width: must be finite and positive, got {float(w)}.")
    return w


def _system(lagrangian, width, derivative_map) -> ClebschSystem:
    # Module-level functions (hashable, equal across calls: one compiled program per shape)
    # with the width as the Partial's array leaf.
    return ClebschSystem(
        lagrangian=Partial(lagrangian, _width(width)),
        velocity_map=_translation,
        derivative_map=derivative_map,
    )


@dataclasses.dataclass(frozen=True)
class OrderedDifference(VectorSpaceDifference):
    r"""The forward difference on the configuration space of peaks *in a fixed order*.

    On the line, N distinct peaks form a configuration space with one component per ordering
    (the collision set $Q_a = Q_b$ separates them) and the continuous flow never leaves its
    component: a peakon–antipeakon pair reaches the collision at a finite $t^*$ with momenta
    growing like $1/(t^*-t)$, where the solution (as an ODE solution) ends. A derivative map is
    only needed near the diagonal (Definition 18), so this one is defined for pairs
    $(Q^{n+1}, Q^n)$ with the same ordering (every $\mathrm{sign}(Q_a - Q_b)$ equal) and is NaN
    otherwise. Without it a midpoint step near a non-symmetric collision has a spurious root on
    the far side, where the peaks have passed through each other with a thousandfold energy;
    with it the step that would cross fails (status NONFINITE) and `integrate` reports it.
    Otherwise it is `clebsch_jax.forward_difference`.
    """

    name: str = "forward difference (peak order kept)"

    def __call__(self, Q_next, Q, dt):
        return _same_order(Q_next, Q) * (Q_next - Q) / dt

    def at_midpoint(self, Q_next, Q, dt):
        return 0.5 * (Q + Q_next), _same_order(Q_next, Q) * (Q_next - Q) / dt


def _same_order(Q_next, Q):
    """1 when the pairwise orderings of two configurations (N,) agree, NaN otherwise."""
    same = jnp.all(jnp.sign(Q_next[:, None] - Q_next[None, :]) == jnp.sign(Q[:, None] - Q[None, :]))
    return jnp.where(same, 1.0, jnp.nan).astype(Q.dtype)


ordered_difference = OrderedDifference()
"""`OrderedDifference`: the default derivative map of `peakons`."""


def peakons(width=1.0, derivative_map: DerivativeMap = ordered_difference) -> ClebschSystem:
    r"""Camassa–Holm peakons as a Clebsch system (see the module docstring).

    - `width`: the kernel width α > 0 of $K(x) = e^{-|x|/\alpha}$ (a scalar array leaf: `vmap`
      over it to sweep; a concrete width is checked, a `ValueError` naming `width`, while
      under `jax.jit`/`jax.vmap` a bad one is reported as `Status.INVALID_INPUT` at step 0);
    - Q: positions, shape (N,); ξ = u(Q): the velocities at the peaks, shape (N,);
    - $l(\xi, Q) = \tfrac12\xi\cdot K(Q)^{-1}\xi$, $\mathcal L_\xi Q = \xi$;
    - `derivative_map`: a vector-space map; the default `ordered_difference` is the forward
      difference restricted to steps that keep the order of the peaks, so that a collision
      fails loudly instead of jumping through (`clebsch_jax.forward_difference` lifts this).

    `integrate(peakons(a), Q0, peakon_velocity(Q0, P0, a), dt=..., n_steps=..., scheme="midpoint")`
    marches the peakon ODEs $\dot q = \partial H/\partial p$, $\dot p = -\partial H/\partial q$ for
    $H = \tfrac12\sum_{a,b}p_ap_be^{-|q_a-q_b|/\alpha}$; `Solution.momentum` are the momenta
    $p^n$ (conserving $\sum_a p_a$ to round-off), `Solution.xi` the velocities $u(Q^n)$.
    """
    return _system(_peakon_lagrangian, width, derivative_map)


def landmarks(width=1.0, derivative_map: DerivativeMap = forward_difference) -> ClebschSystem:
    r"""Landmarks with the Gaussian kernel $K(x) = e^{-|x|^2/(2\alpha^2)}$ (see the module docstring).

    - `width`: α > 0 (a scalar array leaf: `vmap` over it to sweep; checked when concrete,
      as for `peakons`);
    - Q: positions, shape (N, d); ξ = u(Q): velocities, shape (N, d);
    - $l(\xi, Q) = \tfrac12\sum_{i}\xi_{:,i}\cdot K(Q)^{-1}\xi_{:,i}$, $\mathcal L_\xi Q = \xi$.

    The discrete flow (any scheme) conserves the total momentum $\sum_a p_a$ and, since the
    kernel is rotation invariant, the angular momentum `landmark_angular_momentum(Q, p)` to
    round-off (discrete Noether theorem).
    """
    return _system(_landmark_lagrangian, width, derivative_map)


# --------------------------------------------------------------------------------------------
# Companion functions on configurations with leading axes.


def _over(fn, matrix, Q, arrays, width, point_ndim):
    """fn(matrix, width, q, *a) on every configuration q along the leading axes of Q (jitted:
    one small program per model, function and shape)."""
    w = _width(width)
    Q = jnp.asarray(Q, dtype=jnp.result_type(float))
    arrays = [jnp.asarray(a, dtype=Q.dtype) for a in arrays]
    if Q.ndim < point_ndim:
        raise ValueError(f"Q: expected at least {point_ndim} axes, got shape {Q.shape}.")
    for a in arrays:
        if a.shape != Q.shape:
            raise ValueError(f"expected an array of Q's shape {Q.shape}, got {a.shape}.")
    return _mapped(fn, matrix, Q.ndim - point_ndim, w, Q, *arrays)


@functools.partial(jax.jit, static_argnums=(0, 1, 2))
def _mapped(fn, matrix, n_lead, w, Q, *arrays):
    lead, cfg = Q.shape[:n_lead], Q.shape[n_lead:]
    flats = [a.reshape((-1,) + cfg) for a in (Q,) + arrays]
    out = jax.vmap(lambda q, *a: fn(matrix, w, q, *a))(*flats)
    return out.reshape(lead + out.shape[1:])


def _kernel_matrix(matrix, w, q):
    return matrix(w, q)


def _hamiltonian(matrix, w, q, p):
    return 0.5 * jnp.sum(p * (matrix(w, q) @ p))


def _velocity(matrix, w, q, p):
    return matrix(w, q) @ p


def _momenta(matrix, w, q, xi):
    return _linalg.spd_solve(matrix(w, q), xi)


def peakon_kernel_matrix(Q, width=1.0) -> jax.Array:
    r"""$K(Q)_{ab} = e^{-|Q_a - Q_b|/\alpha}$ for Q of shape (..., N); shape (..., N, N)."""
    return _over(_kernel_matrix, _peakon_matrix, Q, (), width, 1)


def peakon_hamiltonian(Q, P, width=1.0) -> jax.Array:
    r"""$H = \tfrac12\sum_{a,b} P_aP_b e^{-|Q_a - Q_b|/\alpha}$; shape of Q's leading axes."""
    return _over(_hamiltonian, _peakon_matrix, Q, (P,), width, 1)


def peakon_velocity(Q, P, width=1.0) -> jax.Array:
    r"""$\xi_a = u(Q_a) = \sum_b e^{-|Q_a - Q_b|/\alpha}P_b$: the `xi0` matching momenta P."""
    return _over(_velocity, _peakon_matrix, Q, (P,), width, 1)


def peakon_momenta(Q, xi, width=1.0) -> jax.Array:
    r"""$P = K(Q)^{-1}\xi = \delta l/\delta\xi$: the momenta of the velocities ξ at the peaks."""
    return _over(_momenta, _peakon_matrix, Q, (xi,), width, 1)


def peakon_field(x, Q, P, width=1.0) -> jax.Array:
    r"""The velocity field $u(x) = \sum_b P_b e^{-|x - Q_b|/\alpha}$ at points x (any shape), for
    one configuration Q, P of shape (N,)."""
    return _peakon_field(jnp.asarray(x, float), jnp.asarray(Q, float), jnp.asarray(P, float), _width(width))


@jax.jit
def _peakon_field(x, Q, P, w):
    return jnp.sum(_peakon_k(w, x[..., None] - Q) * P, axis=-1)


def landmark_kernel_matrix(Q, width=1.0) -> jax.Array:
    r"""$K(Q)_{ab} = e^{-|Q_a - Q_b|^2/(2\alpha^2)}$ for Q of shape (..., N, d); shape (..., N, N)."""
    return _over(_kernel_matrix, _landmark_matrix, Q, (), width, 2)


def landmark_hamiltonian(Q, P, width=1.0) -> jax.Array:
    r"""$H = \tfrac12\sum_{a,b} K(Q_a - Q_b)\,P_a\cdot P_b$; shape of Q's leading axes."""
    return _over(_hamiltonian, _landmark_matrix, Q, (P,), width, 2)


def landmark_velocity(Q, P, width=1.0) -> jax.Array:
    r"""$\xi_a = u(Q_a) = \sum_b K(Q_a - Q_b)P_b$: the `xi0` matching momenta P; shape of Q."""
    return _over(_velocity, _landmark_matrix, Q, (P,), width, 2)


def landmark_momenta(Q, xi, width=1.0) -> jax.Array:
    r"""$P = K(Q)^{-1}\xi = \delta l/\delta\xi$; shape of Q."""
    return _over(_momenta, _landmark_matrix, Q, (xi,), width, 2)


def landmark_field(x, Q, P, width=1.0) -> jax.Array:
    r"""$u(x) = \sum_b K(x - Q_b)P_b$ at points x of shape (..., d), for one configuration
    Q, P of shape (N, d); shape of x."""
    return _landmark_field(jnp.asarray(x, float), jnp.asarray(Q, float), jnp.asarray(P, float), _width(width))


@jax.jit
def _landmark_field(x, Q, P, w):
    return jnp.einsum("...b,bi->...i", _gauss_k(w, x[..., None, :] - Q), P)


def landmark_angular_momentum(Q, P) -> jax.Array:
    r"""$\sum_a Q_a\times P_a$ for Q, P of shape (..., N, d), d = 2 (a scalar per configuration)
    or d = 3 (a vector). Conserved: the kernel is rotation invariant."""
    Q, P = jnp.asarray(Q, float), jnp.asarray(P, float)
    if Q.shape != P.shape or Q.ndim < 2 or Q.shape[-1] not in (2, 3):
        raise ValueError(f"Q, P: expected equal shapes (..., N, 2) or (..., N, 3), got {Q.shape} and {P.shape}.")
    return _angular_momentum(Q, P)


@jax.jit
def _angular_momentum(Q, P):
    if Q.shape[-1] == 2:
        return jnp.sum(Q[..., 0] * P[..., 1] - Q[..., 1] * P[..., 0], axis=-1)
    return jnp.sum(jnp.cross(Q, P), axis=-2)
