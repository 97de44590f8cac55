r"""Stationarity conditions of the discrete action, by `jax.grad` (Lemma 20).

Write $p^n$ for the discrete momentum arriving at $Q^n$ from the previous step (the discrete
Legendre transform $p^n = \partial L_d(\xi^{n-1}, P^{n-1}, Q^{n-1}, Q^n)/\partial Q^n$, which for
the left scheme is $\Delta t\,(D_1\phi_{\Delta t}(Q^n, Q^{n-1}))^T P^{n-1}$). A step solves for
$z = (\xi^n, P^n, Q^{n+1})$ the three blocks of Lemma 20:

$$ \frac{1}{\Delta t}\frac{\partial L_d}{\partial \xi} = \frac{\delta l}{\delta \xi} + P^n \diamond Q^n = 0,\qquad
   \frac{\partial L_d}{\partial P} = \Delta t\,\big(\phi_{\Delta t}(Q^{n+1},Q^n) - \mathcal L_{\xi^n} Q^n\big) = 0, $$
$$ p^n + \frac{\partial L_d}{\partial Q^n} = 0, $$

and then sends $p^{n+1} = \partial L_d / \partial Q^{n+1}$ on. This is a symplectic one-step map
$(Q^n, p^n) \mapsto (Q^{n+1}, p^{n+1})$. Nothing is derived by hand: every block is a gradient
of `discrete_lagrangian`.
"""

from __future__ import annotations

from typing import NamedTuple

import jax

from ..discrete.action import discrete_lagrangian
from ..core.system import ClebschSystem, diamond

__all__ = ["StepUnknowns", "step_residual", "outgoing_momentum", "nodal_residual", "legendre_residual"]


class StepUnknowns(NamedTuple):
    """The unknowns of one step: (ξⁿ, Pⁿ, Qⁿ⁺¹)."""

    xi: jax.Array
    P: jax.Array
    Q1: jax.Array


def step_residual(
    system: ClebschSystem,
    scheme: str,
    dt: jax.Array,
    Q0: jax.Array,
    p0: jax.Array,
    z: StepUnknowns,
) -> StepUnknowns:
    """The Lemma 20 residual of one step, block by block (see the module docstring)."""
    g_xi, g_P, g_Q0 = jax.grad(
        lambda xi, P, q0: discrete_lagrangian(system, scheme, dt, xi, P, q0, z.Q1),
        argnums=(0, 1, 2),
    )(z.xi, z.P, Q0)
    return StepUnknowns(xi=g_xi / dt, P=g_P, Q1=p0 + g_Q0)


def outgoing_momentum(system: ClebschSystem, scheme: str, dt: jax.Array, Q0: jax.Array, z: StepUnknowns) -> jax.Array:
    r"""The discrete Legendre transform $p^{n+1} = \partial L_d / \partial Q^{n+1}$."""
    return jax.grad(lambda q1: discrete_lagrangian(system, scheme, dt, z.xi, z.P, Q0, q1))(z.Q1)


def nodal_residual(system: ClebschSystem, Q: jax.Array, mu: jax.Array, xi: jax.Array) -> jax.Array:
    r"""Lemma 7's first equation at a node, in momentum form: $\delta l/\delta\xi(\xi, Q) - \mu$,
    with $\mu = -p \diamond Q$ the momentum map. Its root is the nodal velocity when $l$ is regular
    in $\xi$ (Lemma 8's operator $G$ exists)."""
    return jax.grad(lambda x: system.l(x, Q))(xi) - mu


def legendre_residual(system: ClebschSystem, Q: jax.Array, p: jax.Array, xi: jax.Array) -> jax.Array:
    r"""Lemma 7's first equation at a node: $\delta l/\delta \xi(\xi, Q) + p \diamond Q$
    (`nodal_residual` with $\mu = -p\diamond Q$)."""
    return nodal_residual(system, Q, -diamond(system, p, Q, xi), xi)
