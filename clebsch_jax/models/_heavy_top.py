"""The heavy top on SO(3): a rigid body with a fixed point in a uniform gravity field
(Definition 14's potential energy; Theorem 16's advected quantity is Γ = Qᵀe₃)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jax.tree_util import Partial

from ..core.derivative_maps import DerivativeMap, cayley
from ..core.system import ClebschSystem
from ..core.validation import is_traced, nan_unless
from ._rigid_body import body_velocity, check_rotation, principal_moments, right_multiplication

__all__ = ["heavy_top"]


def _lagrangian(inertia, mgl, chi, xi, Q):
    # kinetic energy (ξ² as jnp.square, as the free body's `_kinetic_energy`) minus the height
    # of the centre of mass, e₃·(Qχ) = (Qᵀe₃)·χ = Γ·χ
    return 0.5 * jnp.sum(inertia * jnp.square(xi)) - mgl * jnp.dot(Q[2], chi)


def heavy_top(
    inertia, mass_gravity_length, center_of_mass=(0.0, 0.0, 1.0), derivative_map: DerivativeMap = cayley
) -> ClebschSystem:
    r"""The heavy top as a Clebsch system with potential energy (Definition 14).

    $$ l(\Omega, Q) = \tfrac12\,\Omega\cdot\mathbb I\Omega - m g \ell\; e_3\cdot(Q\chi), \qquad
       \mathcal L_\Omega Q = Q\hat\Omega , $$

    **Arguments:**

    - `inertia` (3,): principal moments about the fixed point (body frame), finite and positive.
    - `mass_gravity_length`: $mg\ell$, mass × gravity × distance from the fixed point to the
      centre of mass (a finite scalar; 0 is the free body, a negative value flips $\chi$).
    - `center_of_mass` (3,): direction $\chi$ of the centre of mass in the body frame
      (finite, nonzero; normalised here; $\ell$ is in `mass_gravity_length`). Gravity points
      along $-e_3$.
    - `derivative_map`: `cayley` (default) or `exponential`.

    The potential does not depend on Ω, so the inverse Legendre map is the free body's,
    $\Omega = \mathbb I^{-1}\mu$ (`inverse_legendre`).

    The reduced equations (Theorem 16) are $\dot\Pi = \Pi\times\Omega + mg\ell\,\Gamma\times\chi$,
    $\dot\Gamma = \Gamma\times\Omega$ with $\Gamma = Q^Te_3$ the advected vertical. Every array
    argument is a traced leaf: `vmap` over them to sweep.

    Bad values raise `ValueError` naming the argument; value checks run when the arguments are
    concrete; under `jax.jit`/`jax.vmap` over them a bad inertia, a zero centre of mass or a
    non-finite value is reported as `Status.INVALID_INPUT` at step 0. In `integrate`, `Q0` must
    be a rotation (`check_rotation`; traced: `rotation_ok`).
    """
    dtype = jnp.result_type(float)
    inertia = principal_moments(inertia)
    chi = jnp.asarray(center_of_mass, dtype=dtype)
    if chi.shape != (3,):
        raise ValueError(f"center_of_mass: expected a 3-vector, got shape {chi.shape}.")
    if not is_traced(chi):
        values = np.asarray(chi)
        if not np.all(np.isfinite(values)) or not np.any(values != 0):
            raise ValueError(f"center_of_mass: must be a finite, nonzero direction, got {values.tolist()}.")
    else:
        chi = nan_unless(chi, jnp.any(chi != 0))
    chi = chi / jnp.linalg.norm(chi)
    mgl = jnp.asarray(mass_gravity_length, dtype=dtype)
    if mgl.shape != ():
        raise ValueError(f"mass_gravity_length: expected a scalar, got shape {mgl.shape} (vmap over a batch).")
    if not is_traced(mgl) and not np.isfinite(float(mgl)):
        raise ValueError(f"mass_gravity_length: must be finite, got {float(mgl)}.")
    return ClebschSystem(
        lagrangian=Partial(_lagrangian, inertia, mgl, chi),
        velocity_map=right_multiplication,
        derivative_map=derivative_map,
        check_Q=check_rotation,
        inverse_legendre=Partial(body_velocity, inertia),
    )
