r"""Point vortices on the unit sphere, as a collective Clebsch system on $\mathbb C^2$ per vortex.

N vortices of circulations $\Gamma_a$ at $x_a \in S^2$ have the Hamiltonian (the sphere's
Green's function)

$$ H(x) = -\frac{1}{4\pi} \sum_{a<b} \Gamma_a\Gamma_b \log\big(1 - x_a\cdot x_b\big) $$

and move by $\Gamma_a \dot x_a = \nabla_a H \times x_a$, i.e.
$\dot x_a = \frac{1}{4\pi}\sum_{b\ne a}\Gamma_b\, \frac{x_b \times x_a}{1 - x_a\cdot x_b}$: a
Lie–Poisson system on $so(3)^{*N}$, so(3) acting on each $x_a$ by cross products.

The sphere carries no global phase-space Lagrangian (its area form is not exact), so, as in
Vankerschaver & Leok's collective Lie–Poisson integrators, each vortex is lifted to
$z_a \in \mathbb C^2 \cong \mathbb R^4$ by the Hopf map $x = \pi(z) = z^\dagger\sigma z$ (σ the Pauli
matrices), where the canonical symplectic form is exact. The Clebsch system (`Q` of shape
(N, 4): $(\mathrm{Re}\,z_1, \mathrm{Im}\,z_1, \mathrm{Re}\,z_2, \mathrm{Im}\,z_2)$ per vortex):

- velocity map $\mathcal L_\xi z_a = -\tfrac i2(\omega_a\cdot\sigma)\,z_a + s_a z_a$, $\xi_a = (\omega_a, s_a)
  \in \mathbb R^4$: so(3) ≅ su(2) acting on $\mathbb C^2$ (its image under π is $\omega_a \times x_a$:
  the cross products) and the scalings, which together move z in every direction of $\mathbb C^2$;
- Lagrangian $l(\xi, z) = \sum_a \Gamma_a\, \omega_a\cdot\pi(z_a) - H(\pi(z))$, linear in ξ
  (`degenerate=True`: the midpoint principle, here a Cayley step of each $z_a$ when $s_a = 0$).

Along solutions $s_a = 0$, $|z_a|$ stays 1 and $x_a = \pi(z_a)$ follows the vortex equations: the
Clebsch momentum map is the collective momentum $\Gamma_a x_a$, and the total
$\sum_a\Gamma_a x_a$ (rotations of the sphere) is conserved to round-off.

The companion functions take `(circulations, x)` with `x` of shape (..., N, 3), or lift and
project configurations (`sphere_vortex_lift`, `sphere_vortex_positions`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.tree_util import Partial

from ..core.derivative_maps import DerivativeMap, forward_difference
from ..core.system import ClebschSystem
from ._point_vortices import checked_circulations, distinct_check, on_configurations

__all__ = [
    "point_vortices_sphere",
    "sphere_vortex_lift",
    "sphere_vortex_positions",
    "sphere_vortex_hamiltonian",
    "sphere_vortex_velocity",
    "sphere_vortex_xi",
    "sphere_vortex_moment",
]


def _su2_generators() -> np.ndarray:
    r"""$-\frac i2\sigma_k$ as real 4×4 matrices on $(\mathrm{Re}\,z_1, \mathrm{Im}\,z_1, \mathrm{Re}\,z_2,
    \mathrm{Im}\,z_2)$, shape (3, 4, 4)."""
    sigma = [np.array([[0, 1], [1, 0]], complex), np.array([[0, -1j], [1j, 0]]), np.array([[1, 0], [0, -1]], complex)]
    out = np.zeros((3, 4, 4))
    for k, s in enumerate(sigma):
        for col in range(4):
            z = np.zeros(2, complex)
            z[col // 2] = 1.0 if col % 2 == 0 else 1j
            w = -0.5j * s @ z
            out[k, :, col] = [w[0].real, w[0].imag, w[1].real, w[1].imag]
    return out


_GENERATORS = _su2_generators()


def _hopf(z: jax.Array) -> jax.Array:
    r"""$\pi(z) = z^\dagger\sigma z$ for z of shape (..., 4) → (..., 3)."""
    a, b, c, d = z[..., 0], z[..., 1], z[..., 2], z[..., 3]
    # z̄₁ z₂ = (a - ib)(c + id) = (ac + bd) + i(ad - bc)
    return jnp.stack([2.0 * (a * c + b * d), 2.0 * (a * d - b * c), a * a + b * b - c * c - d * d], axis=-1)


def _velocity_map(xi: jax.Array, Z: jax.Array) -> jax.Array:
    G = jnp.asarray(_GENERATORS, Z.dtype)
    return jnp.einsum("nk,kij,nj->ni", xi[:, :3], G, Z) + xi[:, 3:] * Z


def _hamiltonian(gamma: jax.Array, x: jax.Array) -> jax.Array:
    """H for one configuration x (N, 3) on the unit sphere; pairwise terms vectorised."""
    n = x.shape[0]
    gap = 1.0 - x @ x.T + jnp.eye(n, dtype=x.dtype)  # the diagonal is log 1 = 0, zero gradient
    return -jnp.sum(gamma[:, None] * gamma[None, :] * jnp.log(gap)) / (8.0 * jnp.pi)  # each pair twice


def _lagrangian(gamma: jax.Array, xi: jax.Array, Z: jax.Array) -> jax.Array:
    x = _hopf(Z)
    return jnp.sum(gamma[:, None] * xi[:, :3] * x) - _hamiltonian(gamma, x)


def point_vortices_sphere(circulations, derivative_map: DerivativeMap = forward_difference) -> ClebschSystem:
    r"""N point vortices on the unit sphere as a degenerate Clebsch system on $\mathbb C^{2N}$ (see the
    module docstring).

    - `circulations`: shape (N,), finite and nonzero, of either sign (an array leaf: `vmap`
      over it to sweep; checked like `point_vortices`'s);
    - Q: the lifted positions, shape (N, 4) (`sphere_vortex_lift(x)`); ξ: shape (N, 4), the
      angular velocity $\omega_a$ of each vortex and a scaling rate $s_a$ (zero along solutions);
      a consistent seed is `sphere_vortex_xi(circulations, x)`;
    - `derivative_map`: a vector-space map with a midpoint (default `forward_difference`).

    `integrate` runs the midpoint principle. The positions are `sphere_vortex_positions(sol.Q)`;
    $\sum_a \Gamma_a x_a$ (`sphere_vortex_moment`) is conserved to round-off and H
    (`sphere_vortex_hamiltonian`) stays bounded. Coincident vortices (a singular configuration)
    are refused before compiling, naming the pair, as by `point_vortices`.
    """
    gamma = checked_circulations(circulations, nonzero=True)
    return ClebschSystem(
        lagrangian=Partial(_lagrangian, gamma),
        velocity_map=_velocity_map,
        derivative_map=derivative_map,
        degenerate=True,
        check_Q=_CHECK_DISTINCT,
    )


_CHECK_DISTINCT = distinct_check(_hopf)
"""`point_vortices_sphere`'s `check_Q`: no two vortices at one point of the sphere."""


def sphere_vortex_lift(x) -> jax.Array:
    r"""A point z on the Hopf fibre over each unit vector x: $\pi(z) = x$, $|z| = 1$. Shape (..., N, 3)
    → (..., N, 4). Smooth away from the south pole on the northern chart ($z_1$ real and positive)
    and away from the north pole on the southern one ($z_2$ real and positive), each used on its
    hemisphere."""
    x = jnp.asarray(x, dtype=jnp.result_type(float))
    if x.ndim < 1 or x.shape[-1] != 3:
        raise ValueError(f"x: expected unit vectors of shape (..., 3), got {x.shape}.")
    x1, x2, x3 = x[..., 0], x[..., 1], x[..., 2]
    north = x3 >= 0
    r1 = jnp.sqrt(jnp.maximum((1.0 + x3) / 2.0, 0.0))  # z₁ = r1, z₂ = (x1 + i x2) / (2 r1)
    r2 = jnp.sqrt(jnp.maximum((1.0 - x3) / 2.0, 0.0))  # z₂ = r2, z₁ = (x1 - i x2) / (2 r2)
    s1, s2 = jnp.where(north, r1, 1.0), jnp.where(north, 1.0, r2)
    zn = jnp.stack([r1, jnp.zeros_like(r1), x1 / (2 * s1), x2 / (2 * s1)], axis=-1)
    zs = jnp.stack([x1 / (2 * s2), -x2 / (2 * s2), r2, jnp.zeros_like(r2)], axis=-1)
    return jnp.where(north[..., None], zn, zs)


def sphere_vortex_positions(Z) -> jax.Array:
    r"""The vortex positions $x = \pi(z)$, shape (..., N, 4) → (..., N, 3)."""
    Z = jnp.asarray(Z, dtype=jnp.result_type(float))
    if Z.ndim < 1 or Z.shape[-1] != 4:
        raise ValueError(f"Z: expected lifted positions of shape (..., 4), got {Z.shape}.")
    return _hopf(Z)


def _on_positions(fn, circulations, x, distinct: bool = False):
    return on_configurations(fn, circulations, x, dim=3, name="x", distinct=distinct)


def sphere_vortex_hamiltonian(circulations, x) -> jax.Array:
    r"""$H(x) = -\frac1{4\pi}\sum_{a<b}\Gamma_a\Gamma_b\log(1 - x_a\cdot x_b)$; shape of x's leading axes."""
    return _on_positions(_hamiltonian, circulations, x)


def sphere_vortex_velocity(circulations, x) -> jax.Array:
    r"""$\dot x_a = \nabla_a H \times x_a / \Gamma_a$ (by autodiff of H): the right-hand side for a
    reference ODE solve. Shape of x. Coincident vortices are refused (a `ValueError` naming the pair)."""

    def velocity(gamma, q):
        return jnp.cross(jax.grad(_hamiltonian, argnums=1)(gamma, q) / gamma[:, None], q)

    return _on_positions(velocity, circulations, x, distinct=True)


def sphere_vortex_xi(circulations, x) -> jax.Array:
    r"""The consistent ξ at positions x: $\omega_a = \nabla_a H / \Gamma_a$ (the collective velocity),
    $s_a = 0$; shape (..., N, 4). The seed `xi0` for `integrate`. Coincident vortices are refused."""

    def xi(gamma, q):
        omega = jax.grad(_hamiltonian, argnums=1)(gamma, q) / gamma[:, None]
        return jnp.concatenate([omega, jnp.zeros_like(omega[:, :1])], axis=-1)

    return _on_positions(xi, circulations, x, distinct=True)


def sphere_vortex_moment(circulations, x) -> jax.Array:
    r"""$\sum_a \Gamma_a x_a$, shape (..., 3). Conserved (rotation invariance of H)."""
    return _on_positions(lambda g, q: jnp.sum(g[:, None] * q, axis=0), circulations, x)
