"""The free rigid body on SO(3) (Example 9 and Example 30)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.tree_util import Partial

from .. import lie
from .._derivative_maps import DerivativeMap, cayley
from .._system import ClebschSystem

__all__ = ["rigid_body"]


def _kinetic_energy(inertia: jax.Array, xi: jax.Array) -> jax.Array:
    return 0.5 * jnp.sum(inertia * xi * xi)


def _right_multiplication(xi: jax.Array, Q: jax.Array) -> jax.Array:
    return Q @ lie.hat(xi)


def rigid_body(inertia, derivative_map: DerivativeMap = cayley) -> ClebschSystem:
    r"""The free rigid body as a Clebsch system on $SO(3)$ (Example 9).

    - $\xi = \Omega \in \mathbb R^3$, the body angular velocity;
    - $l(\Omega) = \tfrac12 \Omega \cdot \mathbb I \Omega$ with principal moments `inertia`
      (shape (3,), an array leaf: `vmap` over it to sweep);
    - $Q \in SO(3)$ a 3×3 rotation, velocity map $\mathcal L_\Omega Q = Q\hat\Omega$;
    - derivative map: `clebsch_jax.cayley` (Example 30, the CAY integrator) by default, or
      `clebsch_jax.exponential`.

    Its momentum map $-P \diamond Q$ (`clebsch_jax.momentum_map`, by autodiff) is the body
    angular momentum, equal to $\mathbb I\Omega$ on solutions (Lemma 7).
    """
    inertia = jnp.asarray(inertia, dtype=jnp.result_type(float))
    if inertia.shape != (3,):
        raise ValueError(f"inertia: expected the three principal moments, shape (3,), got {inertia.shape}.")
    return ClebschSystem(
        lagrangian=Partial(_kinetic_energy, inertia),
        velocity_map=_right_multiplication,
        derivative_map=derivative_map,
    )

