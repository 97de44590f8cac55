r"""The discrete Clebsch action (Definition 19 and its adjoint, Remark 22).

One step of the discrete action is the discrete Lagrangian

$$ L_d(\xi, P, Q^n, Q^{n+1}) = \Delta t\,\Big[\, l(\xi, Q^a) + \big\langle P,\ \phi^a - \mathcal L_\xi Q^a \big\rangle \Big], $$

anchored at $Q^a$:

- `scheme="left"` (Definition 19): $Q^a = Q^n$, $\phi^a = \phi_{\Delta t}(Q^{n+1}, Q^n)$;
- `scheme="right"` (Remark 22, the adjoint): $Q^a = Q^{n+1}$,
  $\phi^a = -\phi_{\Delta t}(Q^n, Q^{n+1})$, the same derivative map read backwards;
- `scheme="midpoint"`: $Q^a = \bar Q$, a midpoint of $Q^n$ and $Q^{n+1}$, and $\phi^a$ the
  derivative map's approximation of $\dot Q$ there (`at_midpoint` of the derivative map). Both
  $l$ and $\mathcal L_\xi Q$ are evaluated at the midpoint: a symmetric, second-order principle
  also when $l$ has a potential. It is the one-step scheme for Lagrangians that are
  degenerate in $\xi$ (linear in the velocity, like point vortices): the left and right
  principles are then inconsistent two-step schemes with parasitic modes (Rowley & Marsden
  2002), while the midpoint principle is the implicit midpoint rule when the velocity map is a
  translation and $\delta l/\delta\xi$ is affine in $Q$.

The factor $\Delta t$ (absent in the paper, where it is a constant factor that does not change
the equations) makes the discrete momenta $p^n$ approximate the continuous multiplier $P(t_n)$.
The whole action is $\sum_n L_d(\xi^n, P^n, Q^n, Q^{n+1})$; everything downstream is
`jax.grad` of it.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..core.system import ClebschSystem

__all__ = ["SCHEMES", "discrete_lagrangian", "discrete_action"]

SCHEMES = ("left", "right", "midpoint")


def discrete_lagrangian(
    system: ClebschSystem,
    scheme: str,
    dt: jax.Array,
    xi: jax.Array,
    P: jax.Array,
    Q0: jax.Array,
    Q1: jax.Array,
) -> jax.Array:
    """One term of the discrete Clebsch action (see the module docstring)."""
    if scheme == "left":
        Qa = Q0
        phi = system.derivative_map(Q1, Q0, dt)
    elif scheme == "right":
        Qa = Q1
        phi = -system.derivative_map(Q0, Q1, dt)
    elif scheme == "midpoint":
        Qa, phi = system.derivative_map.at_midpoint(Q1, Q0, dt)
    else:
        raise ValueError(f"scheme: expected one of {SCHEMES}, got {scheme!r}.")
    constraint = phi - system.velocity_map(xi, Qa)
    return dt * (system.l(xi, Qa) + jnp.sum(P * constraint))


def discrete_action(
    system: ClebschSystem,
    scheme: str,
    dt: jax.Array,
    xis: jax.Array,
    Ps: jax.Array,
    Qs: jax.Array,
) -> jax.Array:
    r"""The discrete Clebsch action $\sum_{n=0}^{N-1} L_d(\xi^n, P^n, Q^n, Q^{n+1})$.

    `xis` and `Ps` have a leading axis of length N, `Qs` of length N+1. Its gradient with
    respect to `xis`, `Ps` and the interior `Qs[1:-1]` vanishes on a discrete solution
    (Lemma 20); the tests use this to check the marched trajectory independently of how the
    march assembles its step equations.
    """
    terms = jax.vmap(lambda x, P, q0, q1: discrete_lagrangian(system, scheme, dt, x, P, q0, q1))(
        xis, Ps, Qs[:-1], Qs[1:]
    )
    return jnp.sum(terms)
