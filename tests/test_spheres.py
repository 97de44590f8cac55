"""Systems on spheres: the isotropy of ξ ↦ ξ × q (issue 44).

The velocity map of a sphere, L_ξ q = ξ × q, has a kernel (ξ ∥ q). A Lagrangian written with the
physical velocities ξ × q is degenerate exactly along it and runs as written (the engine fixes the
gauge); an initial ξ0 is its physical velocity ξ0 × q0, whatever its component along q0.
References are independent: exact solutions, or SciPy's DOP853 on the Cartesian equations with
constraint forces.
"""

from __future__ import annotations

import warnings

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import clebsch_jax as cj
from clebsch_jax.core.isotropy import kernel_basis, row_space_basis

G = 1.0


def _cross(xi, Q):
    return jnp.cross(xi, Q)


def _double_pendulum_lagrangian(xi, Q):
    """Two unit masses on unit rods, written with the physical velocities v_a = ξ_a × q_a."""
    v = jnp.cross(xi, Q)
    v1, v2 = v[0], v[0] + v[1]
    return 0.5 * jnp.sum(v1**2) + 0.5 * jnp.sum(v2**2) - G * (2.0 * Q[0, 2] + Q[1, 2])


DOUBLE = cj.ClebschSystem(
    lagrangian=_double_pendulum_lagrangian, velocity_map=_cross, derivative_map=cj.forward_difference
)
Q0_DOUBLE = np.array([[0.6, 0.0, -0.8], [0.0, 0.6, -0.8]])
XI0_DOUBLE = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])  # the first row has a component along q1


def _double_reference(Q0, V0, ts):
    """The double spherical pendulum in Cartesian coordinates r1 = q1, r2 = q1 + q2 with the rod
    constraints' forces solved at every evaluation (DOP853, tight tolerances)."""

    def rhs(t, y):
        r1, r2, v1, v2 = y[:3], y[3:6], y[6:9], y[9:]
        d, w = r2 - r1, v2 - v1
        F = np.array([0.0, 0.0, -G, 0.0, 0.0, -G])  # V = G (2 q1z + q2z) = G (r1z + r2z), unit masses
        # constraint gradients (rows) of ½|r1|² and ½|r2 - r1|², acceleration-level right-hand sides
        C = np.array([np.concatenate([r1, np.zeros(3)]), np.concatenate([-d, d])])
        b = -np.array([v1 @ v1, w @ w]) - C @ F
        lam = np.linalg.solve(C @ C.T, b)
        a = F + C.T @ lam
        return np.concatenate([v1, v2, a[:3], a[3:]])

    r1, r2 = Q0[0], Q0[0] + Q0[1]
    y0 = np.concatenate([r1, r2, V0[0], V0[0] + V0[1]])
    out = solve_ivp(rhs, (ts[0], ts[-1]), y0, method="DOP853", t_eval=ts, rtol=1e-13, atol=1e-13)
    assert out.success
    Y = out.y.T
    return np.stack([Y[:, :3], Y[:, 3:6] - Y[:, :3]], axis=1)


def _quiet(fn, *args, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return fn(*args, **kwargs)


def test_row_space_basis_is_orthonormal_and_spans_the_rows():
    A = np.cross(np.eye(3), np.array([0.6, 0.0, -0.8])).T  # ξ ↦ ξ × q, rank 2
    U = np.asarray(row_space_basis(jnp.asarray(A), 2))
    K = kernel_basis(A)
    assert K.shape == (3, 1) and np.allclose(np.abs(K[:, 0]), [0.6, 0.0, 0.8], atol=1e-15)
    np.testing.assert_allclose(U.T @ U, np.eye(2), atol=1e-15)
    np.testing.assert_allclose(U.T @ K, 0.0, atol=1e-15)


def test_the_double_spherical_pendulum_runs_as_written_with_default_options():
    """Natural Lagrangian (Hessian rank 4 of 6): accepted, the gauge reported in `Solution.isotropy`,
    the velocities without a component along q, |q_a| = 1 and the vertical angular momentum to
    round-off, second order against an independent solve."""
    T = 1.0
    with pytest.warns(UserWarning, match="isotropy of Q0"):
        sol = cj.integrate(DOUBLE, Q0_DOUBLE, XI0_DOUBLE, dt=0.05, n_steps=20)
    assert sol.isotropy == 2 and sol.order == 2
    Q, xi = np.asarray(sol.Q), np.asarray(sol.xi)
    np.testing.assert_allclose(np.linalg.norm(Q, axis=-1), 1.0, atol=1e-13)
    assert np.max(np.abs(np.sum(xi * Q, axis=-1))) < 1e-13  # no isotropy component
    # the physical initial velocity is kept: xi[0] x q0 = xi0 x q0
    V0 = np.cross(XI0_DOUBLE, Q0_DOUBLE)
    np.testing.assert_allclose(np.cross(xi[0], Q0_DOUBLE), V0, atol=1e-14)
    # rotations about the vertical: J_z = Σ_a (q_a × p_a)_z = Σ_a μ_a,z (momentum map of ξ ↦ ξ × q)
    Jz = np.asarray(sol.momentum)[:, :, 2].sum(axis=1)
    assert np.ptp(Jz) < 1e-13
    errors, dts = [], [0.05, 0.025, 0.0125]
    ref = _double_reference(Q0_DOUBLE, V0, np.array([0.0, T]))[-1]
    for dt in dts:
        s = _quiet(cj.integrate, DOUBLE, Q0_DOUBLE, XI0_DOUBLE, dt=dt, n_steps=round(T / dt))
        errors.append(np.max(np.abs(np.asarray(s.Q)[-1] - ref)))
    slope = np.polyfit(np.log(dts), np.log(errors), 1)[0]
    assert abs(slope - sol.order) < 0.15, (errors, slope)


def test_degenerate_true_is_no_longer_a_dead_end_for_the_natural_lagrangian():
    """`degenerate=True`, which an older message suggested: the gauge makes the system regular
    again (nodal velocities recovered), the same trajectory as the default."""
    system = cj.ClebschSystem(
        lagrangian=_double_pendulum_lagrangian,
        velocity_map=_cross,
        derivative_map=cj.forward_difference,
        degenerate=True,
    )
    a = _quiet(cj.integrate, system, Q0_DOUBLE, XI0_DOUBLE, dt=0.05, n_steps=5)
    b = _quiet(cj.integrate, DOUBLE, Q0_DOUBLE, XI0_DOUBLE, dt=0.05, n_steps=5)
    assert a.isotropy == 2 and a.xi is not None
    np.testing.assert_allclose(np.asarray(a.Q), np.asarray(b.Q), atol=1e-14)


def _spherical_pendulum(lagrangian):
    return cj.ClebschSystem(lagrangian=lagrangian, velocity_map=_cross, derivative_map=cj.forward_difference)


CONICAL_G = 0.8  # ω = 1 at cos θ = 0.8: q(t) = (0.6 cos t, 0.6 sin t, -0.8)
Q0_CONICAL = np.array([0.6, 0.0, -0.8])


@pytest.mark.parametrize(
    "natural", [False, pytest.param(True, marks=pytest.mark.slow)], ids=["l=|xi|^2/2", "l=|xi x q|^2/2"]
)  # the double pendulum covers the gauge by default
def test_the_conical_pendulum_keeps_its_physical_initial_velocity(natural):
    """ξ0 = e₃ + c q0 is the physical velocity (0, 0.6, 0) for every c: the run is the conical orbit
    whatever c, with one warning that ξ0 was changed (none when it has no isotropy component),
    second order, with the vertical angular momentum to round-off."""
    if natural:
        system = _spherical_pendulum(lambda xi, q: 0.5 * jnp.sum(jnp.cross(xi, q) ** 2) - CONICAL_G * q[2])
    else:
        system = _spherical_pendulum(lambda xi, q: 0.5 * jnp.sum(xi**2) - CONICAL_G * q[2])
    dt, n = 0.01, 100
    exact = np.array([0.6 * np.cos(1.0), 0.6 * np.sin(1.0), -0.8])
    finals = []
    for c in (0.0, 1.7):
        xi0 = np.array([0.0, 0.0, 1.0]) + c * Q0_CONICAL
        with pytest.warns(UserWarning, match="xi0: has a component along the isotropy") as record:
            sol = cj.integrate(system, Q0_CONICAL, xi0, dt=dt, n_steps=n)
        assert len([w for w in record if "isotropy" in str(w.message)]) == 1
        np.testing.assert_allclose(np.cross(np.asarray(sol.xi)[0], Q0_CONICAL), [0.0, 0.6, 0.0], atol=1e-14)
        assert sol.isotropy == (1 if natural else 0)
        finals.append(np.asarray(sol.Q)[-1])
        assert np.max(np.abs(np.asarray(sol.Q)[:, 2] + 0.8)) < 1e-3  # stays on its circle, O(dt²)
        assert np.max(np.abs(finals[-1] - exact)) < 1e-3  # the exact orbit, to O(dt²)
    np.testing.assert_allclose(finals[0], finals[1], atol=1e-13)  # c changes nothing
    # the vertical angular momentum (μ_z: the momentum map of rotations about e₃) to round-off
    assert np.ptp(np.asarray(sol.momentum)[:, 2]) < 1e-13
    # second order against the exact orbit (the same compiled programs for the other dt)
    coarse = _quiet(cj.integrate, system, Q0_CONICAL, xi0, dt=2 * dt, n_steps=n // 2)
    slope = np.log2(np.max(np.abs(np.asarray(coarse.Q)[-1] - exact)) / np.max(np.abs(finals[-1] - exact)))
    assert sol.order == 2 and abs(slope - 2) < 0.15, slope
    physical = np.array([0.48, 0.0, 0.36])  # already ⊥ q0: accepted silently
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        cj.integrate(system, Q0_CONICAL, physical, dt=dt, n_steps=2)


# --------------------------------------------------------------------------------------------
# the first step is checked like every other (Kepler in the plane)


def _kepler_lagrangian(xi, q):
    return 0.5 * jnp.sum(xi**2) + 1.0 / jnp.sqrt(jnp.sum(q**2))


KEPLER = cj.ClebschSystem(
    lagrangian=_kepler_lagrangian, velocity_map=lambda xi, q: xi, derivative_map=cj.forward_difference
)


def _perihelion(e):
    """Perihelion of the orbit of eccentricity e and semi-major axis 1 (energy -1/2)."""
    return np.array([1.0 - e, 0.0]), np.array([0.0, np.sqrt((1.0 + e) / (1.0 - e))])


@pytest.mark.parametrize(
    "dt, status, message",
    [
        (0.05, cj.Status.FIRST_STEP, "two half steps"),
        (0.1, cj.Status.ENERGY_JUMP, "energy changed"),
    ],
    ids=["half steps fail", "energy check"],
)
def test_a_spurious_first_step_is_reported(dt, status, message):
    """e = 0.95 at perihelion (r = 0.05, |v| ≈ 6.2) with steps far longer than the passage: step 0
    converges to a root with a positive energy (the body would escape). With dt = 0.05 its energy
    change is small next to the terms at perihelion, and the two half steps, which do not
    converge, report it; with dt = 0.1 it changes the energy by more than a tenth of their size,
    and the per-step energy check (`ENERGY_STEP_RTOL`), which sweeps make too, reports it first."""
    q0, v0 = _perihelion(0.95)
    unchecked = cj.integrate(KEPLER, q0, v0, dt=dt, n_steps=3, check_energy=False)
    energy = 0.5 * np.sum(np.asarray(unchecked.xi) ** 2, -1) - 1.0 / np.linalg.norm(np.asarray(unchecked.Q), axis=-1)
    assert energy[1] > 0  # the spurious root: the orbit was bound (energy -1/2)
    sol = cj.integrate(KEPLER, q0, v0, dt=dt, n_steps=3, throw=False)
    assert int(sol.result) == status and int(sol.failed_step) == 0
    assert np.all(np.isnan(np.asarray(sol.Q)[1:]))
    with pytest.raises(cj.IntegrationError, match=f"step 0 of 3.*{message}.*smaller dt"):
        cj.integrate(KEPLER, q0, v0, dt=dt, n_steps=3)


def test_a_spurious_first_step_is_reported_under_vmap():
    """Under `jax.vmap` the march is traced: its first-step check's two half steps are the first
    iterations of the traced scan, and the member whose step 0 is the spurious root reports
    `Status.FIRST_STEP` in its `Solution` (with NaN after step 0); its neighbour runs."""
    import jax

    (q_bad, v_bad), (q_ok, v_ok) = _perihelion(0.95), _perihelion(0.5)
    run = jax.vmap(lambda q, v: cj.integrate(KEPLER, q, v, dt=0.05, n_steps=3, throw=False))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", cj.native.NativeFallbackWarning)
        sol = run(np.stack([q_bad, q_ok]), np.stack([v_bad, v_ok]))
    assert np.asarray(sol.result).tolist() == [cj.Status.FIRST_STEP, cj.Status.SUCCESS]
    assert np.asarray(sol.failed_step).tolist() == [0, -1]
    Q = np.asarray(sol.Q)
    assert np.all(np.isnan(Q[0, 1:])) and np.all(np.isfinite(Q[1]))


@pytest.mark.slow  # compiles the traced march with its error callback
def test_a_spurious_first_step_is_raised_under_jit():
    """Under `jax.jit` with `throw=True` the first-step check's failure is raised from the
    program, as any traced failure is (`jax.errors.JaxRuntimeError` holding the
    `IntegrationError`'s message)."""
    import jax

    q0, v0 = _perihelion(0.95)
    run = jax.jit(lambda q, v: cj.integrate(KEPLER, q, v, dt=0.05, n_steps=3).Q)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", cj.native.NativeFallbackWarning)
        with pytest.raises(jax.errors.JaxRuntimeError, match="step 0 of 3.*two half steps.*FIRST_STEP"):
            jax.block_until_ready(run(q0, v0))


def test_kepler_in_the_plane_is_second_order_with_its_angular_momentum_to_round_off():
    """A resolved run passes the first-step check; against the exact Kepler orbit (e = 0.5, one
    period from perihelion), order 2, and the angular momentum q × ξ to round-off."""
    q0, v0 = _perihelion(0.5)
    T = 2 * np.pi
    errors, dts = [], [T / 400, T / 800, T / 1600]
    for dt in dts:
        sol = cj.integrate(KEPLER, q0, v0, dt=dt, n_steps=round(T / dt))
        Q, xi = np.asarray(sol.Q), np.asarray(sol.xi)
        errors.append(np.max(np.abs(Q[-1] - q0)))  # periodic: back at perihelion
        L = Q[:, 0] * xi[:, 1] - Q[:, 1] * xi[:, 0]
        assert np.ptp(L) < 1e-12
    slope = np.polyfit(np.log(dts), np.log(errors), 1)[0]
    assert abs(slope - sol.order) < 0.15, (errors, slope)


@pytest.mark.slow  # compiles the gauged march once more, traced into a jit
def test_a_hand_gauged_system_runs_under_jit_as_integrate_runs_it():
    """Under jit the engine cannot inspect values: `cj.gauge_isotropy` builds the gauged system
    once, from concrete values, and the traced march gives integrate's nodes."""
    import jax

    xi0 = np.cross(Q0_DOUBLE, np.cross(XI0_DOUBLE, Q0_DOUBLE))  # the physical velocity's xi, ⊥ q_a
    gauged = cj.gauge_isotropy(DOUBLE, Q0_DOUBLE, xi0)
    traced = jax.jit(lambda q, x: cj.integrate(gauged, q, x, dt=0.05, n_steps=5).Q)(Q0_DOUBLE, xi0)
    concrete = cj.integrate(DOUBLE, Q0_DOUBLE, xi0, dt=0.05, n_steps=5)
    assert concrete.isotropy == 2
    np.testing.assert_allclose(np.asarray(traced), np.asarray(concrete.Q), atol=1e-13)


def _fresh_single_pendulum():
    """A spherical pendulum written with its physical velocity, made of functions no other test
    has compiled (each call makes new ones): its checks and march are compiled afresh."""

    def lagrangian(xi, q):
        v = jnp.cross(xi, q)
        return 0.5 * jnp.sum(v * v) - G * q[2]

    return cj.ClebschSystem(
        lagrangian=lagrangian, velocity_map=lambda xi, q: jnp.cross(xi, q), derivative_map=cj.forward_difference
    )


SINGLE_Q0, SINGLE_XI0 = np.array([0.6, 0.0, -0.8]), np.array([0.3, 1.0, 0.2])  # ξ0 has a component along q0


def test_the_checks_of_a_sphere_system_compile_a_few_programs():
    """The value checks and the isotropy gauge of a new sphere system (the model checks, the
    gauge's values, the physical velocity's derivatives) are one compiled program each, not an
    XLA compile per operation run eagerly (issue 44: about 160 programs before)."""
    from clebsch_jax.march.arguments import prepared_method

    from .helpers import compiles_recorded

    with compiles_recorded() as compiled, pytest.warns(UserWarning, match="isotropy of Q0"):
        prepared_method(_fresh_single_pendulum(), SINGLE_Q0, SINGLE_XI0, dt=0.05, n_steps=4)
    assert len(compiled) <= 4, compiled


@pytest.mark.slow  # compiles a new march
def test_the_first_call_of_a_sphere_system_compiles_a_few_programs():
    """A new sphere system's first `integrate` call: its checks and the march's start and chunk
    (the first-step probe is that chunk); a second call compiles nothing."""
    from .helpers import compiles_recorded

    system = _fresh_single_pendulum()
    with compiles_recorded() as compiled:
        sol = _quiet(cj.integrate, system, SINGLE_Q0, SINGLE_XI0, dt=0.05, n_steps=4, backend="xla")
    assert sol.isotropy == 1 and len(compiled) <= 6, compiled
    with compiles_recorded() as again:
        _quiet(cj.integrate, system, SINGLE_Q0, SINGLE_XI0, dt=0.05, n_steps=7, backend="xla")
    assert again == []
