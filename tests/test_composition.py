"""Higher order by composition (`integrate(..., order=k)`): measured orders against tight
references, conservation through composition, and the facts each method carries."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import clebsch_jax as cj
from clebsch_jax import diagnostics as dg
from clebsch_jax.steppers.composition import check_coefficients

from .helpers import rigid_body_reference, vortex_reference
from .test_reduction import _vertical, heavy_top_rhs

TEST_INERTIA = np.array([2.0, 1.0, 2.0 / 3.0])


def test_coefficient_sets_satisfy_their_order_conditions():
    """Σγ = 1 and Σγ^k = 0 for odd 3 ≤ k < order (necessary conditions; the measured orders
    below check the rest), to the rounding of the stored digits."""
    for name, comp in cj.COMPOSITIONS.items():
        assert check_coefficients(comp) < 1e-15, name
        assert comp.symmetric and comp.stages == len(comp.gammas)


def test_step_plans_carry_their_facts():
    rb = cj.models.rigid_body(TEST_INERTIA)  # Cayley, no potential: the principle is symmetric
    top = cj.models.heavy_top(np.array([1.0, 1.0, 0.4]), 1.5, np.array([0.0, 0.0, 1.0]))
    assert cj.step_plan(rb).order == 2 and cj.step_plan(rb).solves_per_step == 1
    assert cj.step_plan(top, "left").order == 1 and not cj.step_plan(top, "left").symmetric
    p = cj.step_plan(top, order=2)  # first order: composed with its adjoint over half steps
    assert p.schemes == ("left", "right") and p.symmetric and p.solves_per_step == 2
    assert cj.step_plan(rb, order=8).solves_per_step == 17 and cj.step_plan(top, order=8).solves_per_step == 34
    assert cj.step_plan(rb, order=6).name.startswith("Kahan-Li p6s9")
    assert cj.step_plan(rb, composition="Suzuki-Umeno p8s15").order == 8
    for p in (cj.step_plan(rb, order=k) for k in (2, 4, 6, 8)):
        assert p.symmetric and p.symplectic


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(order=3), "order"),
        (dict(order=4, composition="Kahan-Li p6s9"), "order"),
        (dict(composition="no such method"), "composition"),
        (dict(composition=(0.5, 0.5)), "composition"),
    ],
)
def test_bad_order_or_composition_is_refused_before_compiling(kwargs, match):
    with pytest.raises(ValueError, match=match):
        cj.integrate(cj.models.rigid_body(TEST_INERTIA), np.eye(3), np.ones(3), dt=0.1, n_steps=2, **kwargs)


# Δt ranges in each method's asymptotic regime and above the reference's 1e-12 floor (measured).
RIGID_BODY_DTS = {2: [0.2, 0.1, 0.05], 4: [0.2, 0.1, 0.05], 6: [0.2, 0.1, 0.05], 8: [0.2, 0.16, 0.125, 0.1]}


@pytest.mark.parametrize("order", [2, 4, 6, 8])
def test_rigid_body_orders_against_dop853(order):
    """Reduced Cayley march composed to order k; Q(T) against SciPy DOP853 at rtol 1e-13.
    Concrete calls: one compiled chunk program per order for every dt and run length (order 8's
    is the one test_conservation_survives_composition_rigid_body uses as well)."""
    system = cj.models.rigid_body(TEST_INERTIA)
    T, dts = 8.0, np.array(RIGID_BODY_DTS[order])
    m0 = np.array([np.cos(1.1), 0.0, np.sin(1.1)])
    Q0 = np.asarray(cj.lie.so3_exp(jnp.array([0.3, -0.2, 0.5])))
    Qref, _ = rigid_body_reference(TEST_INERTIA, Q0, m0 / TEST_INERTIA, np.array([0.0, T]))
    errs = []
    for dt in dts:
        sol = cj.integrate(system, Q0, m0 / TEST_INERTIA, dt=dt, n_steps=int(round(T / dt)), order=order)
        assert np.isclose(float(sol.ts[-1]), T)
        errs.append(np.max(np.abs(np.asarray(sol.Q[-1]) - Qref[-1])))
    assert sol.form == "reduced" and sol.order == order
    assert abs(dg.fit_order(dts, errs) - order) < 0.15, errs


VORTEX_DTS = {2: [0.05, 0.025, 0.0125], 4: [0.1, 0.05, 0.025], 6: [0.2, 0.1, 0.05], 8: [0.25, 0.2, 0.16, 0.125]}


@pytest.fixture(scope="module")
def vortex_scene():
    gamma = np.array([1.0, -0.5, 0.7, 0.4])
    Q0 = np.random.default_rng(3).uniform(-1.0, 1.0, (4, 2))
    return gamma, Q0


@pytest.mark.parametrize("order", [2, 4, 6, 8])
def test_point_vortex_orders_against_dop853(order, vortex_scene):
    """Midpoint principle (full march) composed to order k; four vortices of mixed sign."""
    gamma, Q0 = vortex_scene
    T, dts = 4.0, np.array(VORTEX_DTS[order])
    ref = vortex_reference(gamma, Q0, np.array([0.0, T]))[-1]
    system = cj.models.point_vortices(gamma)
    xi0 = cj.models.vortex_velocity(gamma, Q0)
    run = jax.jit(lambda dt: cj.integrate(system, Q0, xi0, dt=dt, n_steps=int(round(T / dts[-1])), order=order))
    errs = []
    for dt in dts:
        sol = run(dt)
        errs.append(np.max(np.abs(np.asarray(sol.Q[int(round(T / dt))]) - ref)))
    assert sol.form == "full" and sol.order == order
    assert abs(dg.fit_order(dts, errs) - order) < 0.15, errs


def test_heavy_top_composes_first_order_principle_with_its_adjoint():
    """With a potential the left principle is first order; order=2 and 4 compose it with the
    right principle (its adjoint). Measured orders against the Euler–Poisson equations."""
    I, mgl, chi = np.array([1.0, 1.0, 0.4]), 1.5, np.array([0.0, 0.0, 1.0])
    Q0, w0 = np.asarray(cj.lie.so3_exp(jnp.array([0.5, 0.0, 0.0]))), np.array([0.3, -0.2, 6.0])
    system = cj.models.heavy_top(I, mgl, chi)
    T = 1.0
    y = solve_ivp(
        heavy_top_rhs(I, mgl, chi), (0, T), np.concatenate([Q0.ravel(), w0]), method="DOP853", rtol=1e-13, atol=1e-13
    ).y[:9, -1]
    for order, dts in ((2, np.array([0.04, 0.02, 0.01])), (4, np.array([0.1, 0.05, 0.025]))):
        run = jax.jit(lambda dt: cj.integrate(system, Q0, w0, dt=dt, n_steps=int(round(T / dts[-1])), order=order))
        errs = []
        for dt in dts:
            sol = run(dt)
            errs.append(np.max(np.abs(np.asarray(sol.Q[int(round(T / dt))]).ravel() - y)))
        assert sol.order == order and "right(h/2) o left(h/2)" in sol.method
        assert abs(dg.fit_order(dts, errs) - order) < 0.15, (order, errs)


def test_conservation_survives_composition_rigid_body():
    """Order 8 (17 Cayley sub-steps per step), 2000 steps of Δt = 0.4: the Casimir |μ|² to
    round-off and the energy bounded without drift."""
    system = cj.models.rigid_body(TEST_INERTIA)
    m0 = np.array([np.cos(1.1), 0.0, np.sin(1.1)])
    sol = cj.integrate(system, np.eye(3), m0 / TEST_INERTIA, dt=0.4, n_steps=2000, order=8)
    mu = np.asarray(sol.momentum)
    casimir = np.sum(mu**2, axis=-1)
    assert np.max(np.abs(casimir - casimir[0])) < 1e-13
    E = 0.5 * np.sum(mu**2 / TEST_INERTIA, axis=-1)
    assert np.max(np.abs(E - E[0])) < 1e-6 * E[0]  # measured 1.5e-8 relative (order 8 at Δt = 0.4)
    assert dg.envelope_ratio(E - E[0]) < 1.5


@pytest.mark.slow  # ~30 s; the rigid-body conservation test covers compositions by default
def test_conservation_survives_composition_vortices_and_heavy_top(vortex_scene):
    """Order 4 on the vortices: linear and angular impulses to round-off, H bounded. Order 4
    of left/right on the heavy top (full march): the Noether momentum about the vertical to
    round-off, and the reduced march agrees with the full one."""
    gamma, Q0 = vortex_scene
    sol = cj.integrate(
        cj.models.point_vortices(gamma), Q0, cj.models.vortex_velocity(gamma, Q0), dt=0.05, n_steps=2000, order=4
    )
    Q = np.asarray(sol.Q)
    lin = np.asarray(jax.vmap(lambda q: cj.models.vortex_linear_impulse(gamma, q))(Q))
    ang = np.asarray(jax.vmap(lambda q: cj.models.vortex_angular_impulse(gamma, q))(Q))
    # round-off of 10⁴ solves (2000 steps × 5 stages) adds up: measured 3.9e-14 and 1.6e-13 absolute
    assert np.max(np.abs(lin - lin[0])) < 1e-12 * np.max(np.abs(lin[0]))
    assert np.max(np.abs(ang - ang[0])) < 1e-12 * abs(ang[0])
    H = np.asarray(jax.vmap(lambda q: cj.models.vortex_hamiltonian(gamma, q))(Q))
    assert np.max(np.abs(H - H[0])) < 1e-5 * abs(H[0])
    assert dg.envelope_ratio(H - H[0]) < 1.5

    I, mgl, chi = np.array([1.0, 1.0, 0.4]), 1.5, np.array([0.0, 0.0, 1.0])
    top = cj.models.heavy_top(I, mgl, chi)
    Qt, wt = np.asarray(cj.lie.so3_exp(jnp.array([0.5, 0.0, 0.0]))), np.array([0.3, -0.2, 6.0])
    full = cj.integrate(top, Qt, wt, dt=0.02, n_steps=500, order=4, reduce=False)
    Jz = np.asarray(dg.noether_momentum(full, _vertical))[:, 0]
    assert np.max(np.abs(Jz - Jz[0])) < 1e-12 * np.max(np.abs(full.momentum[0]))
    red = cj.integrate(top, Qt, wt, dt=0.02, n_steps=500, order=4, reduce=True)
    assert red.form == "reduced" and full.form == "full"
    np.testing.assert_allclose(np.asarray(red.Q), np.asarray(full.Q), rtol=0, atol=1e-10)


def test_heavy_top_half_steps_share_their_jacobian():
    """The heavy top's default step (the reduced left step and its adjoint over half steps)
    forms one Jacobian per step: the second half step's solve starts from the first half
    step's (`SymmetricPair.shared_jacobian`, chord updates). Against the previous schedule
    (`shared_jacobian=False`, a fresh Jacobian at each half step's guess), on a fast top: one
    Jacobian per step instead of two, about one chord update more, every solve still at
    round-off, the trajectory the same to round-off (both iterate to round-off), and the same
    conservation: the Noether momentum about the vertical and QᵀQ = I to round-off, the energy
    error bounded without drift. (Its order: `test_heavy_top_composes_first_order_principle_with_its_adjoint`.)"""
    I, mgl, chi = np.array([1.0, 1.0, 0.4]), 1.5, np.array([0.0, 0.0, 1.0])
    top = cj.models.heavy_top(I, mgl, chi)
    Q0, w0 = np.asarray(cj.lie.so3_exp(jnp.array([0.5, 0.0, 0.0]))), np.array([0.3, -0.2, 6.0])
    assert cj.step_plan(top, order=2).schemes == ("left", "right")
    pair = cj.SymmetricPair(cj.ReducedStep())
    runs = {
        shared: cj.integrate(
            top, Q0, w0, dt=0.05, n_steps=1000, method=dataclasses.replace(pair, shared_jacobian=shared)
        )
        for shared in (None, False)
    }
    new, old = runs[None], runs[False]
    assert new.method == old.method == "right(h/2) o left(h/2)"
    assert np.all(np.asarray(new.stats.jacobians) == 1) and np.all(np.asarray(old.stats.jacobians) == 2)
    assert float(np.mean(new.stats.iterations)) <= float(np.mean(old.stats.iterations)) + 1.1
    scale = np.max(np.abs(np.asarray(old.momentum)))
    for sol in (new, old):
        assert bool(np.all(sol.valid)) and float(jnp.max(sol.stats.residual_norm)) < 1e-15 * scale
        Jz = np.asarray(dg.noether_momentum(sol, _vertical, top))[:, 0]
        assert np.max(np.abs(Jz - Jz[0])) < 1e-13 * scale
        assert float(jnp.max(dg.orthogonality_error(sol.Q))) < 1e-13
    # the same trajectory to round-off: both schedules iterate every solve to round-off
    np.testing.assert_allclose(np.asarray(new.Q), np.asarray(old.Q), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(new.momentum), np.asarray(old.momentum), rtol=0, atol=1e-12 * scale)
    E_new, E_old = (np.asarray(dg.energy(top, s)) for s in (new, old))
    # O(Δt²) energy oscillation at |ω|Δt ≈ 0.3: bounded, not drifting, the same on both schedules
    assert np.max(np.abs(E_new - E_new[0])) < 1e-3 * abs(E_new[0])
    np.testing.assert_allclose(E_new - E_new[0], E_old - E_old[0], rtol=0, atol=1e-12 * abs(E_old[0]))
    assert dg.envelope_ratio(E_new - E_new[0]) < 1.5


def test_only_a_reduced_newton_step_shares_its_jacobian():
    """`shared_jacobian=True` needs a `ReducedStep` solved by `Newton()`; None means False for
    any other base (the full step keeps its own solves), and True is refused for it."""
    cj.SymmetricPair(cj.FullStep())  # None: each half step solves on its own
    with pytest.raises(TypeError, match="shared_jacobian"):
        cj.SymmetricPair(cj.FullStep(), shared_jacobian=True)
