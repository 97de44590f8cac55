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
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from . import _linalg
from ._closure import check_closure
from ._derivative_maps import MatrixGroupDifference
from ._system import ClebschSystem

__all__ = ["MatrixGroupReduction", "find_reduction", "reduced_residual", "outgoing_body_momentum"]


@dataclasses.dataclass(frozen=True)
class MatrixGroupReduction:
    """What the reduced march needs: the basis X(e_k) of the algebra and its pseudo-inverse.

    `basis` (m, n, n) and `pinv` (m, n·n) are NumPy constants (static: found once per system)."""

    basis: np.ndarray
    pinv: np.ndarray
    xi_shape: tuple

    def X(self, xi):
        return jnp.tensordot(jnp.ravel(xi), jnp.asarray(self.basis), axes=1)

    def X_inv(self, Y):
        return (jnp.asarray(self.pinv) @ jnp.ravel(Y)).reshape(self.xi_shape)

    def __hash__(self):
        return hash((self.basis.tobytes(), self.xi_shape))

    def __eq__(self, other):
        return (isinstance(other, MatrixGroupReduction) and self.xi_shape == other.xi_shape
                and np.array_equal(self.basis, other.basis))


def _concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


_CACHE: dict = {}


def find_reduction(system: ClebschSystem, Q0, xi0) -> tuple[MatrixGroupReduction | None, str]:
    """`_find_reduction`, cached: the verdict depends only on the two maps and the shapes."""
    leaves = jax.tree_util.tree_leaves(system.velocity_map)
    if any(isinstance(x, jax.core.Tracer) for x in leaves):
        return _find_reduction(system, Q0, xi0)
    key = (system.velocity_map, system.derivative_map, tuple(np.shape(Q0)), tuple(np.shape(xi0)))
    try:
        hit = _CACHE.get(key)
    except TypeError:  # an unhashable map
        return _find_reduction(system, Q0, xi0)
    if hit is None:
        hit = _find_reduction(system, Q0, xi0)
        if len(_CACHE) >= 256:
            _CACHE.clear()
        _CACHE[key] = hit
    return hit


def _find_reduction(system: ClebschSystem, Q0, xi0) -> tuple[MatrixGroupReduction | None, str]:
    # Evaluate eagerly even inside a user's jit: only the maps and the shapes matter here.
    with jax.ensure_compile_time_eval():
        return _inspect(system, Q0, xi0)


def _inspect(system: ClebschSystem, Q0, xi0) -> tuple[MatrixGroupReduction | None, str]:
    r"""Decide whether the reduced march applies; returns `(reduction or None, reason)`.

    It applies when (1) the derivative map is a `MatrixGroupDifference` (Definition 25),
    (2) Q is a square matrix and the velocity map is right multiplication,
    $\mathcal L_\xi G = G\,\mathcal L_\xi I$ (checked at a fixed random G), and (3) the velocity
    map is closed (`check_closure`, Theorem 12), so that $X(V)$ is a Lie algebra.
    """
    if not isinstance(system.derivative_map, MatrixGroupDifference):
        return None, "the derivative map is not a matrix-group map (Definition 25)"
    shape = tuple(np.shape(Q0))
    if len(shape) != 2 or shape[0] != shape[1]:
        return None, f"Q is not a square matrix (shape {shape})"
    n = shape[0]
    xi_shape = tuple(np.shape(xi0))
    m = int(np.prod(xi_shape)) if xi_shape else 1
    eye = jnp.eye(n)
    E = jnp.eye(m).reshape((m,) + xi_shape)
    G = np.eye(n) + 0.3 * np.random.default_rng(7).normal(size=(n, n))
    basis = jnp.stack([system.velocity_map(e, eye) for e in E])
    moved = jnp.stack([system.velocity_map(e, jnp.asarray(G)) for e in E])
    if not (_concrete(basis) and _concrete(moved)):
        return None, "the velocity map depends on traced values, so it cannot be inspected"
    basis, moved = np.asarray(basis), np.asarray(moved)
    scale = max(float(np.max(np.abs(moved))), 1.0)
    if np.max(np.abs(moved - G @ basis)) > 1e-12 * scale:
        return None, "the velocity map is not right multiplication Q·X(xi)"
    B = basis.reshape(m, n * n).T
    if np.linalg.matrix_rank(B) < m:
        return None, "xi -> X(xi) is not injective"
    closure = check_closure(system, np.eye(n), np.zeros(xi_shape))
    if not closure.closed:
        return None, f"the velocity map is not closed (residual {closure.worst_residual:.1e})"
    return MatrixGroupReduction(basis=basis, pinv=np.linalg.pinv(B), xi_shape=xi_shape), "applies"


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
