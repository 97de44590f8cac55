"""The midpoint discrete Clebsch principle (`scheme="midpoint"`) on systems other than vortices:
a symmetric, second-order method for every system, also with a potential."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import clebsch_jax as cj
from clebsch_jax import diagnostics as dg

from .test_reduction import _vertical, heavy_top_rhs


@pytest.mark.slow  # CI runs it; the default methods' second order (the midpoint principle among them) is measured in the default run by tests/test_defaults.py
def test_heavy_top_midpoint_is_second_order_and_conservative():
    """With a potential the left/right principles are first order (l at one end of the step);
    the midpoint principle evaluates l and the velocity map at Qⁿ·(Qⁿ⁻¹Qⁿ⁺¹)^½ and is second
    order. Reference: Euler–Poisson equations written by hand, DOP853 at 1e-13."""
    I, mgl, chi = np.array([1.0, 1.0, 0.4]), 1.5, np.array([0.0, 0.0, 1.0])
    Q0, w0 = np.asarray(cj.lie.so3_exp(jnp.array([0.5, 0.0, 0.0]))), np.array([0.3, -0.2, 6.0])
    system = cj.models.heavy_top(I, mgl, chi)
    T, dts = 1.0, np.array([0.04, 0.02, 0.01, 0.005])
    y = solve_ivp(
        heavy_top_rhs(I, mgl, chi), (0, T), np.concatenate([Q0.ravel(), w0]), method="DOP853", rtol=1e-13, atol=1e-13
    ).y[:, -1]
    # one program for every run (dt traced): compiling the full march dominates this test
    run = jax.jit(lambda dt: cj.integrate(system, Q0, w0, dt=dt, n_steps=1000, scheme="midpoint"))
    errs = []
    for dt in dts[::-1]:  # the last run, Δt = 0.04 over T = 40, is also the long run below
        sol = run(dt)
        assert sol.form == "full" and sol.order == 2
        errs.append(np.max(np.abs(np.asarray(sol.Q[int(round(T / dt))]).ravel() - y[:9])))
    assert abs(dg.fit_order(dts[::-1], errs) - 2.0) < 0.15, errs
    # long run: Noether momentum about the vertical to round-off, energy bounded
    Jz = np.asarray(dg.noether_momentum(sol, _vertical))[:, 0]
    assert np.max(np.abs(Jz - Jz[0])) < 1e-12 * np.max(np.abs(sol.momentum[0]))
    assert float(jnp.max(dg.orthogonality_error(sol.Q))) < 1e-12
    E = np.asarray(dg.energy(system, sol))
    # O(Δt²) energy oscillation at |ω|Δt ≈ 0.24 (measured 1.8e-3 relative): bounded, not drifting
    assert np.max(np.abs(E - E[0])) < 5e-3 * abs(E[0])
    assert dg.envelope_ratio(E - E[0]) < 1.5


def test_midpoint_needs_a_derivative_map_with_a_midpoint():
    system = cj.ClebschSystem(
        lagrangian=lambda xi: 0.5 * jnp.sum(xi**2),
        velocity_map=lambda xi, Q: xi,
        derivative_map=lambda Q1, Q0, dt: (Q1 - Q0) / dt,
    )
    with pytest.raises(ValueError, match="midpoint"):
        cj.integrate(system, np.zeros(2), np.ones(2), dt=0.1, n_steps=3, scheme="midpoint")
    with pytest.raises(ValueError, match="reduce"):
        cj.integrate(
            cj.models.rigid_body((1.0, 2.0, 3.0)),
            np.eye(3),
            np.ones(3),
            dt=0.1,
            n_steps=3,
            scheme="midpoint",
            reduce=True,
        )
