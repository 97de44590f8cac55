"""The free rigid body on SO(3) (Example 9 and Example 30), and in Clebsch variables on R³."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.tree_util import Partial

from .. import lie
from ..core.derivative_maps import DerivativeMap, cayley, forward_difference
from ..core.system import ClebschSystem
from ..core.validation import is_traced, nan_unless

__all__ = [
    "rigid_body",
    "rigid_body_vector",
    "rigid_body_vector_start",
    "check_rotation",
    "rotation_ok",
    "ROTATION_TOLERANCE",
]


ROTATION_TOLERANCE = float(np.sqrt(np.finfo(np.float64).eps))
r"""How far from orthogonal a configuration of an $SO(n)$ model may be: $\max|Q^TQ - I| \le
\sqrt\varepsilon \approx 1.5\cdot10^{-8}$. The marches keep $Q^TQ - I$ at its initial size to
round-off, so a larger defect is not a rotation that lost a few digits but a mistake (float32
data, degrees for radians, a transposed or scaled matrix)."""


def check_rotation(Q) -> str | None:
    r"""None if `Q` is a rotation matrix ($Q^TQ = I$ to `ROTATION_TOLERANCE` and $\det Q = +1$),
    else a sentence saying what is wrong: the `check_Q` of the $SO(n)$ models
    (`ClebschSystem(..., check_Q=...)`). `Q` is a concrete array (NumPy).

    `check_rotation.batched` (`check_rotations`) checks a whole stack at once, for `cj.sweep`."""
    Q = np.asarray(Q, dtype=np.float64)
    if Q.ndim != 2 or Q.shape[0] != Q.shape[1]:
        return f"expected a square rotation matrix, got shape {Q.shape}."
    found = check_rotations(Q[None])
    return None if found is None else found[1]


def check_rotations(Qs) -> tuple[int, str] | None:
    """`check_rotation` of every matrix of a stack `Qs` (B, n, n), vectorised: None if all are
    rotations, else (index, sentence) of the first that is not."""
    Qs = np.asarray(Qs, dtype=np.float64)
    if Qs.ndim != 3 or Qs.shape[1] != Qs.shape[2]:
        return 0, f"expected a stack of square rotation matrices, got shape {Qs.shape}."
    defect = np.max(np.abs(np.swapaxes(Qs, 1, 2) @ Qs - np.eye(Qs.shape[1])), axis=(1, 2))
    not_orthogonal = ~(defect <= ROTATION_TOLERANCE)  # NaN counts as not orthogonal
    with np.errstate(invalid="ignore"):
        det = np.linalg.det(Qs)
    bad = not_orthogonal | (det < 0)
    if not np.any(bad):
        return None
    j = int(np.argmax(bad))
    if not_orthogonal[j]:
        return j, (
            f"not a rotation matrix: max|Q^T Q - I| = {defect[j]:.2e} > {ROTATION_TOLERANCE:.1e}. "
            "Pass an orthogonal matrix (e.g. orthogonalise it with a QR or polar decomposition)."
        )
    return j, (
        f"det Q = {det[j]:.6g}: an orthogonal matrix that is a reflection, not a rotation "
        "(SO(n) needs det Q = +1; flip the sign of one column)."
    )


def rotation_ok(Q) -> jax.Array:
    """`check_rotation` as a traced boolean (True: a rotation), for values known only inside
    `jax.jit`/`jax.vmap`: there `integrate` reports a member whose `Q0` is not a rotation with
    `Status.INVALID_INPUT` at step 0."""
    Q = jnp.asarray(Q)
    defect = jnp.max(jnp.abs(Q.T @ Q - jnp.eye(Q.shape[-1], dtype=Q.dtype)))
    return (defect <= ROTATION_TOLERANCE) & (jnp.linalg.det(Q) > 0)


check_rotation.batched = check_rotations
check_rotation.traced = rotation_ok


def principal_moments(inertia, name: str = "inertia") -> jax.Array:
    """`inertia` as a float array of shape (3,), checked: finite and positive when concrete (a
    `ValueError`); when traced (under `jax.vmap`/`jax.jit`, in `cj.sweep`) made NaN unless
    positive (`nan_unless`), which `integrate` reports as `Status.INVALID_INPUT` at step 0."""
    if np.iscomplexobj(inertia):
        raise ValueError(f"{name}: the principal moments must be real, got a complex array.")
    inertia = jnp.asarray(inertia, dtype=jnp.result_type(float))
    if inertia.shape != (3,):
        raise ValueError(f"{name}: expected the three principal moments, shape (3,), got {inertia.shape}.")
    if not is_traced(inertia):
        values = np.asarray(inertia)
        if not np.all(np.isfinite(values)) or not np.all(values > 0):
            raise ValueError(f"{name}: the principal moments must be finite and positive, got {values.tolist()}.")
        return inertia
    return nan_unless(inertia, jnp.all(inertia > 0))


def _kinetic_energy(inertia: jax.Array, xi: jax.Array) -> jax.Array:
    # ξ² as jnp.square, whose derivative is the one product 2ξ·dξ: δl/δξ = (𝕀/2)(2ξ), exactly 𝕀ξ,
    # where ξ·ξ's product rule gives two terms (𝕀ξ/2 + 𝕀ξ/2, the same number) in every solve
    return 0.5 * jnp.sum(inertia * jnp.square(xi))


def body_velocity(inertia: jax.Array, mu: jax.Array, Q: jax.Array) -> jax.Array:
    r"""The inverse Legendre map (Lemma 8) of $l(\Omega) = \tfrac12\Omega\cdot\mathbb I\Omega$
    (plus any potential of Q alone): $\delta l/\delta\Omega = \mathbb I\Omega = \mu$ gives
    $\Omega = \mathbb I^{-1}\mu$, componentwise with the principal moments `inertia`, whatever
    Q. The `inverse_legendre` of the rigid-body models, held as
    `Partial(body_velocity, inertia)`."""
    return mu / inertia


def right_multiplication(xi: jax.Array, Q: jax.Array) -> jax.Array:
    return Q @ lie.hat(xi)


def rigid_body(inertia, derivative_map: DerivativeMap = cayley) -> ClebschSystem:
    r"""The free rigid body as a Clebsch system on $SO(3)$ (Example 9).

    - $\xi = \Omega \in \mathbb R^3$, the body angular velocity;
    - $l(\Omega) = \tfrac12 \Omega \cdot \mathbb I \Omega$ with principal moments `inertia`
      (shape (3,), finite and positive; an array leaf: `vmap` over it to sweep);
    - $Q \in SO(3)$ a 3×3 rotation, velocity map $\mathcal L_\Omega Q = Q\hat\Omega$;
    - derivative map: `clebsch_jax.cayley` (Example 30, the CAY integrator) by default, or
      `clebsch_jax.exponential`.

    Its momentum map $-P \diamond Q$ (`clebsch_jax.momentum_map`, by autodiff) is the body
    angular momentum, equal to $\mathbb I\Omega$ on solutions (Lemma 7); the system gives the
    inverse Legendre map $\Omega = \mathbb I^{-1}\mu$ (`body_velocity`), so nodal velocities
    are evaluated, not solved for.

    Bad values raise `ValueError` naming the argument: `inertia` not finite and positive
    (checked here when concrete; under `jax.jit`/`jax.vmap` over it a bad one is reported as
    `Status.INVALID_INPUT` at step 0), and, in `integrate`, a `Q0` that is not a rotation
    (`check_rotation`, on a concrete `Q0`; `rotation_ok` under tracing).
    """
    inertia = principal_moments(inertia)
    return ClebschSystem(
        lagrangian=Partial(_kinetic_energy, inertia),
        velocity_map=right_multiplication,
        derivative_map=derivative_map,
        check_Q=check_rotation,
        inverse_legendre=Partial(body_velocity, inertia),
    )


def _rotated_vector(xi: jax.Array, Q: jax.Array) -> jax.Array:
    return jnp.cross(Q, xi)


def rigid_body_vector(inertia, derivative_map: DerivativeMap = forward_difference) -> ClebschSystem:
    r"""The free rigid body in Clebsch variables on $\mathbb R^3$: the same Euler equations as
    `rigid_body`, with a vector in place of the rotation.

    - $\xi = \Omega$ and $l(\Omega) = \tfrac12\Omega\cdot\mathbb I\Omega$ as in `rigid_body`
      (and its inverse Legendre map $\Omega = \mathbb I^{-1}\mu$);
    - $Q \in \mathbb R^3$, velocity map $\mathcal L_\Omega Q = Q \times \Omega$ (the
      infinitesimal rotation of a body-fixed vector seen from the body, a Lie algebra action);
    - momentum map $-P\diamond Q = P \times Q = \Pi$, the body angular momentum;
    - derivative map: `clebsch_jax.forward_difference` (Q lives in a vector space).

    $(Q, P) \mapsto P \times Q$ is a Poisson map from $T^*\mathbb R^3$ onto $\mathfrak{so}(3)^*$,
    so the body momentum follows Euler's equations $\dot\Pi = \Pi\times\Omega$ whatever pair
    $(Q, P)$ represents $\Pi(0)$. Six numbers per body instead of eighteen for $(Q, P)$ on
    $SO(3)$: the cheap carrier for `scheme="gauss"`, whose Gauss–Legendre steps descend to the
    same map of Π as on $SO(3)$ (tested).

    Start from `rigid_body_vector_start(Pi0)`, which returns a pair $(Q_0, P_0)$ with
    $P_0\times Q_0 = \Pi_0$: a $Q_0$ not perpendicular to $\Pi_0$ cannot represent it.

    Use it with `scheme="midpoint"` or `"gauss"`, which treat Q and P alike and so descend to a
    map of Π that keeps $|\Pi|$ to round-off (the midpoint principle is one-stage Gauss here;
    `tests/test_gauss.py` checks order 8). The left and right principles (symplectic Euler
    here) mix Q and P unevenly, do not descend, and let $|\Pi|^2$ wander by the method's
    error, far above round-off.
    """
    inertia = principal_moments(inertia)
    return ClebschSystem(
        lagrangian=Partial(_kinetic_energy, inertia),
        velocity_map=_rotated_vector,
        derivative_map=derivative_map,
        inverse_legendre=Partial(body_velocity, inertia),
    )


def rigid_body_vector_start(Pi0) -> tuple[jax.Array, jax.Array]:
    r"""Clebsch variables for the body momentum `Pi0` (shape (3,), nonzero): a unit $Q_0 \perp
    \Pi_0$ and $P_0 = Q_0\times\Pi_0$, so that $P_0\times Q_0 = \Pi_0$ and $P_0 \perp Q_0$.
    Works under `jax.jit` and `jax.vmap` (Q₀ is built from the coordinate axis least aligned
    with Π₀)."""
    Pi0 = jnp.asarray(Pi0, dtype=jnp.result_type(float))
    if Pi0.shape != (3,):
        raise ValueError(f"Pi0: expected a body momentum of shape (3,), got {Pi0.shape}.")
    if not is_traced(Pi0) and not np.any(np.asarray(Pi0)):
        raise ValueError("Pi0: the zero momentum has no Clebsch pair with a unit Q0; expected a nonzero vector.")
    axis = jax.nn.one_hot(jnp.argmin(jnp.abs(Pi0)), 3, dtype=Pi0.dtype)
    Q0 = jnp.cross(Pi0, axis)
    Q0 = Q0 / jnp.linalg.norm(Q0)
    return Q0, jnp.cross(Q0, Pi0)
