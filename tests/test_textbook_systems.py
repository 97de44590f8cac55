"""Two of issue 44's five textbook systems, written from the README alone (the spherical and
double spherical pendulums and Kepler in the plane are in `test_spheres.py`): a gravity-gradient
satellite on SO(3) and a charged particle in a magnetic field. Each against an independent DOP853
solve of its equations of motion, order 2 by a log-log fit, its momentum to round-off."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from scipy.integrate import solve_ivp

import clebsch_jax as cj
from tests.helpers import hat

INERTIA = np.array([1.0, 1.6, 2.3])
K = 0.8  # gravity-gradient strength 3μ/(2R³)


def _satellite_lagrangian(xi, Q):
    """½ ξ·Iξ - K γ·Iγ, γ = Qᵀe₃ the local vertical in the body frame."""
    gamma = Q[2]  # Qᵀ e₃ is the third row of Q
    return 0.5 * jnp.sum(INERTIA * xi**2) - K * jnp.sum(INERTIA * gamma**2)


SATELLITE = cj.ClebschSystem(
    lagrangian=_satellite_lagrangian,
    velocity_map=lambda xi, Q: Q @ cj.lie.hat(xi),
    derivative_map=cj.cayley,
    check_Q=cj.models.check_rotation,
)


def _satellite_reference(Q0, w0, T):
    """Euler's equations with the gravity-gradient torque, I ω̇ = Iω × ω + γ × ∂V/∂γ (V = K γ·Iγ),
    and Q̇ = Q ω^."""

    def rhs(t, y):
        Q, w = y[:9].reshape(3, 3), y[9:]
        gamma = Q[2]
        torque = np.cross(gamma, 2 * K * INERTIA * gamma)
        return np.concatenate([(Q @ hat(w)).ravel(), (np.cross(INERTIA * w, w) + torque) / INERTIA])

    out = solve_ivp(rhs, (0.0, T), np.concatenate([Q0.ravel(), w0]), method="DOP853", rtol=1e-13, atol=1e-13)
    assert out.success
    return out.y[:9, -1].reshape(3, 3)


def _order(errors, dts):
    return np.polyfit(np.log(dts), np.log(errors), 1)[0]


def test_a_gravity_gradient_satellite():
    """Q on SO(3) to round-off, the vertical spatial angular momentum (Q μ)₃ to round-off (the
    potential is invariant under rotations about e₃), second order against DOP853."""
    Q0 = np.asarray(cj.lie.expm(cj.lie.hat(jnp.array([0.3, -0.5, 0.2]))))
    w0 = np.array([0.4, -0.9, 0.6])
    T = 2.0
    ref = _satellite_reference(Q0, w0, T)
    errors, dts = [], [0.1, 0.05, 0.025]
    for dt in dts:
        sol = cj.integrate(SATELLITE, Q0, w0, dt=dt, n_steps=round(T / dt))
        Q = np.asarray(sol.Q)
        errors.append(np.max(np.abs(Q[-1] - ref)))
        np.testing.assert_allclose(np.swapaxes(Q, 1, 2) @ Q, np.broadcast_to(np.eye(3), Q.shape), atol=1e-13)
        Lz = np.einsum("nij,nj->ni", Q, np.asarray(sol.momentum))[:, 2]
        assert np.ptp(Lz) < 1e-13
    assert abs(_order(errors, dts) - sol.order) < 0.15, errors


B = np.array([0.0, 0.0, 1.5])
TRAP = 0.7


def _particle_lagrangian(xi, x):
    """½|ẋ|² + ẋ·A(x) - φ(x): unit mass and charge, A = ½ B × x (uniform field), φ a trap about e₃."""
    A = 0.5 * jnp.cross(jnp.asarray(B), x)
    return 0.5 * jnp.sum(xi**2) + jnp.sum(xi * A) - 0.5 * TRAP * (x[0] ** 2 + x[1] ** 2)


PARTICLE = cj.ClebschSystem(
    lagrangian=_particle_lagrangian, velocity_map=lambda xi, x: xi, derivative_map=cj.forward_difference
)


def test_a_charged_particle_in_a_magnetic_field():
    """ẍ = ẋ × B - ∇φ. The canonical momentum p (the march's own) has p₃ and the canonical angular
    momentum x₁p₂ - x₂p₁ conserved to round-off (translations along e₃, rotations about it)."""
    x0, v0 = np.array([1.0, 0.0, 0.2]), np.array([0.1, 0.8, 0.3])
    T = 3.0

    def rhs(t, y):
        x, v = y[:3], y[3:]
        return np.concatenate([v, np.cross(v, B) - TRAP * np.array([x[0], x[1], 0.0])])

    out = solve_ivp(rhs, (0.0, T), np.concatenate([x0, v0]), method="DOP853", rtol=1e-13, atol=1e-13)
    ref = out.y[:3, -1]
    errors, dts = [], [0.1, 0.05, 0.025]
    for dt in dts:
        sol = cj.integrate(PARTICLE, x0, v0, dt=dt, n_steps=round(T / dt))
        x, p = np.asarray(sol.Q), np.asarray(sol.p)
        errors.append(np.max(np.abs(x[-1] - ref)))
        assert np.ptp(p[:, 2]) < 1e-13
        assert np.ptp(x[:, 0] * p[:, 1] - x[:, 1] * p[:, 0]) < 1e-13
    assert abs(_order(errors, dts) - sol.order) < 0.15, errors
