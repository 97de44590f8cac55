"""Point vortices on the sphere (`cj.models.point_vortices_sphere`): exact solutions (two vortices
about their centre of vorticity, a ring at a latitude), the moment Σ Γ_a x_a to round-off, the
energy bounded, and an independent DOP853 solve of the vortex equations."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation

import clebsch_jax as cj
from clebsch_jax.models import (
    point_vortices_sphere,
    sphere_vortex_hamiltonian,
    sphere_vortex_lift,
    sphere_vortex_moment,
    sphere_vortex_positions,
    sphere_vortex_velocity,
    sphere_vortex_xi,
)


def _unit(theta, phi):
    return np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])


def _run(gamma, x0, dt, n):
    sol = cj.integrate(
        point_vortices_sphere(gamma), sphere_vortex_lift(x0), sphere_vortex_xi(gamma, x0), dt=dt, n_steps=n
    )
    assert sol.scheme == "midpoint" and sol.order == 2
    return np.asarray(sphere_vortex_positions(sol.Q))


def test_the_hopf_lift_is_a_section_on_both_hemispheres():
    x = np.stack([_unit(t, p) for t, p in [(0.0, 0.0), (0.7, 1.0), (np.pi / 2, 2.0), (2.5, -1.0), (np.pi, 0.3)]])
    z = np.asarray(sphere_vortex_lift(x))
    np.testing.assert_allclose(np.linalg.norm(z, axis=-1), 1.0, atol=1e-15)
    np.testing.assert_allclose(np.asarray(sphere_vortex_positions(z)), x, atol=1e-15)


def test_two_vortices_rotate_about_their_centre_of_vorticity():
    """Exact: both turn rigidly about M = Γ₁x₁ + Γ₂x₂ at the angular velocity M / (4π(1 - x₁·x₂))."""
    gamma = jnp.array([1.0, 0.5])
    x0 = np.stack([_unit(0.5, 0.0), _unit(1.0, np.pi / 2)])
    T = 1.0
    M = gamma[0] * x0[0] + gamma[1] * x0[1]
    exact = x0 @ Rotation.from_rotvec(np.asarray(M) * T / (4 * np.pi * (1 - x0[0] @ x0[1]))).as_matrix().T
    errors, dts = [], [0.1, 0.05]
    for dt in dts:
        x = _run(gamma, x0, dt, round(T / dt))
        errors.append(np.max(np.abs(x[-1] - exact)))
        np.testing.assert_allclose(np.linalg.norm(x, axis=-1), 1.0, atol=1e-13)
        moment = np.asarray(sphere_vortex_moment(gamma, x))
        assert np.max(np.abs(moment - np.asarray(M))) < 1e-13
    assert np.log2(errors[0] / errors[1]) > 1.8, errors  # second order
    assert errors[-1] < 1e-5


def test_a_ring_of_equal_vortices_rotates_rigidly_at_its_known_rate():
    """N equal vortices evenly spaced on the latitude z = z0 turn about the pole at
    Ω = Γ(N - 1) z0 / (4π(1 - z0²)) (the vortex equations at the ring give it too)."""
    n, g, theta = 4, 1.0, 0.9  # four vortices: the program of the four-vortex test below
    gamma = jnp.full(n, g)
    x0 = np.stack([_unit(theta, 2 * np.pi * k / n) for k in range(n)])
    z0 = np.cos(theta)
    omega = g * (n - 1) * z0 / (4 * np.pi * (1 - z0**2))
    v = np.asarray(sphere_vortex_velocity(gamma, x0))
    np.testing.assert_allclose(v, omega * np.cross([0.0, 0.0, 1.0], x0), atol=1e-14)  # the formula, independently
    T, dt = 2.0, 0.05
    x = _run(gamma, x0, dt, round(T / dt))
    exact = x0 @ Rotation.from_rotvec([0.0, 0.0, omega * T]).as_matrix().T
    assert np.max(np.abs(x[-1] - exact)) < 1e-4
    assert np.max(np.abs(x[:, :, 2] - z0)) < 1e-12  # the ring keeps its latitude: a rotation about e₃


def test_four_vortices_against_an_independent_solve_with_the_moment_to_round_off():
    gamma = jnp.array([1.0, -0.7, 0.6, 1.3])
    x0 = np.stack([_unit(0.6, 0.0), _unit(1.2, 1.5), _unit(2.0, 3.0), _unit(1.6, -1.8)])
    T, dt = 2.0, 0.02
    x = _run(gamma, x0, dt, round(T / dt))

    def rhs(t, y):
        return np.asarray(sphere_vortex_velocity(gamma, y.reshape(-1, 3))).ravel()

    ref = solve_ivp(rhs, (0.0, T), x0.ravel(), method="DOP853", rtol=1e-12, atol=1e-12)
    assert ref.success
    assert np.max(np.abs(x[-1] - ref.y[:, -1].reshape(-1, 3))) < 1e-3  # O(dt²) of a second-order method
    moment = np.asarray(sphere_vortex_moment(gamma, x))
    assert np.max(np.abs(moment - moment[0])) < 1e-13
    energy = np.asarray(sphere_vortex_hamiltonian(gamma, x))
    assert np.max(np.abs(energy - energy[0])) < 1e-3 * max(1.0, abs(energy[0]))


@pytest.mark.parametrize("bad", [[1.0, 0.0], [1.0, np.nan]])
def test_bad_circulations_are_refused(bad):
    with pytest.raises(ValueError, match="circulations"):
        point_vortices_sphere(bad)
