"""The Gauss–Legendre discretisation of the Clebsch principle (`scheme="gauss"`): its tableau,
its order against an independent solve, the structure it keeps, and how it fails."""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import clebsch_jax as cj
from clebsch_jax import diagnostics as dg
from clebsch_jax.discrete.collocation import gauss_legendre

from .helpers import rigid_body_reference

TEST_INERTIA = np.array([2.0, 1.0, 2.0 / 3.0])
PI0 = np.array([np.cos(1.1), 0.0, np.sin(1.1)])


@pytest.mark.parametrize("stages", [1, 2, 3, 4, 5, 6, 7, 8])
def test_tableau_order_conditions_and_exact_symplecticity(stages):
    """B(2s), C(s) and D(s) to round-off, which give order 2s (Butcher); μᵢⱼ + μⱼᵢ = 1 exactly
    in floating point (no drift of quadratic invariants); the extrapolation keeps constants."""
    tab = gauss_legendre(stages)
    b, c, a = tab.b, tab.c, tab.a
    for k in range(1, 2 * stages + 1):
        assert abs(np.sum(b * c ** (k - 1)) - 1.0 / k) < 1e-15
    for k in range(1, stages + 1):
        assert np.max(np.abs(a @ c ** (k - 1) - c**k / k)) < 1e-15
        assert np.max(np.abs((b * c ** (k - 1)) @ a - b * (1.0 - c**k) / k)) < 1e-15
    assert np.array_equal(tab.mu + tab.mu.T, np.ones((stages, stages)))
    assert np.max(np.abs(tab.mu * b[None, :] - a)) < 1e-15
    # its entries grow with s (3.6e4 at 8 stages: a polynomial continued past its nodes), so
    # the row sums are exact to round-off of that size, not of 1
    E = tab.extrapolation
    assert np.max(np.abs(E.sum(axis=1) - 1.0)) < 1e-15 * np.max(np.abs(E).sum(axis=1))


def test_plan_facts_and_refusals_before_compiling():
    system = cj.models.rigid_body_vector(TEST_INERTIA)
    plan = cj.step_plan(system, scheme="gauss", order=8)
    assert (plan.order, plan.symmetric, plan.symplectic, plan.solves_per_step) == (8, True, True, 1)
    assert cj.step_plan(system, scheme="gauss").order == 2
    Q0, P0 = cj.models.rigid_body_vector_start(PI0)
    bad = [
        (dict(order=3), r"^order: scheme=.gauss. expects None or an even order from 2 to 16"),
        (dict(order=8, composition="Kahan-Li p8s17"), r"^composition: scheme='gauss'"),
        (dict(order=4, reduce=True), r"^reduce: the reduced march implements"),
        (dict(order=4, jacobian="blocks"), r"^jacobian: scheme='gauss'"),
    ]
    for kwargs, match in bad:
        with pytest.raises(ValueError, match=match):
            cj.integrate(system, Q0, PI0 / TEST_INERTIA, P0=P0, dt=0.1, n_steps=2, scheme="gauss", **kwargs)
    with pytest.raises(ValueError, match=r"^Pi0: the zero momentum has no Clebsch pair"):
        cj.models.rigid_body_vector_start(np.zeros(3))
    with pytest.raises(ValueError, match=r"^Pi0: expected a body momentum of shape \(3,\)"):
        cj.models.rigid_body_vector_start(np.ones(4))


# Δt ranges in each order's asymptotic regime, above the reference's floor and below the
# fixed-point iteration's limit (order 8 diverges at Δt = 1 here); T/Δt an integer (measured).
# Order 12's smallest error is 6e-13: its reference is DOP853 at rtol 2.5e-14 (at 1e-13 the
# reference moved that point by 2e-13 and the fit to 12.5). Orders 14 and 16 leave nothing to
# measure in double precision: their error constants are so small that their steps are exact
# to round-off wherever the iteration contracts (order 16 at Δt = 1: 8e-14 here).
GAUSS_DTS = {
    2: [0.2, 0.1, 0.05],
    4: [0.4, 0.2, 0.1],
    6: [0.5, 0.4, 0.25, 0.2],
    8: [0.8, 0.5, 0.4, 0.32],
    12: [1.0, 0.8, 0.5],
}
REFERENCE_RTOL = {12: 2.5e-14}


@pytest.mark.parametrize(
    "order",
    [
        pytest.param(2, marks=pytest.mark.slow),
        4,
        pytest.param(6, marks=pytest.mark.slow),
        8,
        pytest.param(12, marks=pytest.mark.slow),
    ],
)  # 2, 6, 12: ~5 s each, in CI's slow run
def test_rigid_body_orders_against_dop853(order):
    """Gauss–Legendre with order/2 stages on the rigid body on SO(3): Q(T) against SciPy DOP853
    at rtol 1e-13 (2.5e-14 for order 12); log-log fit within 0.15 of the order."""
    system = cj.models.rigid_body(TEST_INERTIA)
    T, dts = 8.0, np.array(GAUSS_DTS[order])
    Q0 = np.asarray(cj.lie.so3_exp(jnp.array([0.3, -0.2, 0.5])))
    rtol = REFERENCE_RTOL.get(order, 1e-13)
    Qref, _ = rigid_body_reference(TEST_INERTIA, Q0, PI0 / TEST_INERTIA, np.array([0.0, T]), rtol=rtol, atol=rtol)
    errs = []
    for dt in dts:
        # concrete calls: one compiled chunk program for every dt and run length, the one
        # test_invariants_rigid_body uses for order 8 as well
        sol = cj.integrate(
            system, Q0, PI0 / TEST_INERTIA, dt=dt, n_steps=int(round(T / dt)), scheme="gauss", order=order
        )
        assert np.isclose(float(sol.ts[-1]), T)
        errs.append(np.max(np.abs(np.asarray(sol.Q[-1]) - Qref[-1])))
    assert sol.form == "full" and sol.order == order and sol.scheme == "gauss"
    assert abs(dg.fit_order(dts, errs) - order) < 0.15, errs


@pytest.mark.slow  # ~15 s (three orders compiled); in CI's slow run
def test_high_orders_with_large_steps():
    """Orders 12, 14 and 16 at Δt = 1 on R³ over T = 200, against SciPy DOP853 (rtol 2.5e-14) for
    the body momentum: each 2 more orders gain over 30× (measured 6.5e-9, 1.8e-11, 2.0e-13);
    order 16 is at the reference's level, where order 8 at half the step is 1e-6 off; the
    quadratic invariants stay at round-off with these large steps."""
    T = 200.0
    _, w = rigid_body_reference(
        TEST_INERTIA, np.eye(3), PI0 / TEST_INERTIA, np.array([0.0, T]), rtol=2.5e-14, atol=2.5e-14
    )
    Pi_ref = w[-1] * TEST_INERTIA
    vec = cj.models.rigid_body_vector(TEST_INERTIA)
    Q0, P0 = cj.models.rigid_body_vector_start(PI0)
    errs = []
    for order in (12, 14, 16):
        sol = cj.integrate(vec, Q0, PI0 / TEST_INERTIA, P0=P0, dt=1.0, n_steps=int(T), scheme="gauss", order=order)
        Q, P, mu = np.asarray(sol.Q), np.asarray(sol.p), np.asarray(sol.momentum)
        for inv in (np.sum(Q * Q, -1), np.sum(P * P, -1), np.sum(Q * P, -1), np.sum(mu * mu, -1)):
            assert np.max(np.abs(inv - inv[0])) < 1e-13  # measured ≤ 3e-14
        errs.append(np.max(np.abs(mu[-1] - Pi_ref)))
    assert errs[0] > 30 * errs[1] > 900 * errs[2], errs
    assert errs[2] < 1e-11, errs
    low = cj.integrate(vec, Q0, PI0 / TEST_INERTIA, P0=P0, dt=0.5, n_steps=int(2 * T), scheme="gauss", order=8)
    assert np.max(np.abs(np.asarray(low.momentum[-1]) - Pi_ref)) > 1e4 * errs[2]


@pytest.mark.slow  # compiles the native kernel of an 8-stage step (LLVM, tens of seconds); native Gauss
# stays in the default run through test_native_integrate's order 4
def test_order_16_sweep_runs_natively_under_auto(tmp_path, monkeypatch):
    """Gauss–Legendre 16 on R³: the sweep's per-member program is within `backend="auto"`'s
    compile budget (`native.AUTO_MAX_IR_LINES`), so the sweep compiles its native kernel (an
    object file in the disk cache, no fallback warning), and its bodies' momenta after 20 steps
    of Δt = 1 match DOP853 (measured ≤ 2.7e-14; the bound leaves room for the reference's own
    error, rtol 2.5e-14 over 20 time units), with |Π|² kept to round-off (measured ≤ 9e-16)."""
    pytest.importorskip("llvmlite")
    from clebsch_jax.batching.backends import NativeFallbackWarning

    monkeypatch.setenv("CLEBSCH_JAX_NATIVE_CACHE", str(tmp_path))
    T = 20.0
    Pis = np.array([PI0, [0.6, 0.8, 0.0], [0.0, -0.28, 0.96]])
    Q0, P0 = jax.vmap(cj.models.rigid_body_vector_start)(jnp.asarray(Pis))
    with warnings.catch_warnings():
        warnings.simplefilter("error", NativeFallbackWarning)
        res = cj.sweep(
            cj.models.rigid_body_vector,
            TEST_INERTIA[None],
            Q0,
            Pis / TEST_INERTIA,
            P0=P0,
            grid=True,
            dt=1.0,
            n_steps=int(T),
            scheme="gauss",
            order=16,
        )
    assert list(tmp_path.rglob("*.o"))  # the native kernel was compiled
    assert len(res.failed_members) == 0
    for Pi, final in zip(Pis, np.asarray(res.final_momentum)):
        _, w = rigid_body_reference(
            TEST_INERTIA, np.eye(3), Pi / TEST_INERTIA, np.array([0.0, T]), rtol=2.5e-14, atol=2.5e-14
        )
        assert np.max(np.abs(final - w[-1] * TEST_INERTIA)) < 1e-12
        assert abs(final @ final - Pi @ Pi) < 1e-14


def test_first_step_from_substeps_and_steps_near_the_limit():
    """Step 0 has no previous step to extrapolate. From constant slopes alone its sweeps
    diverged for this body with order 16 at Δt = 1.25 (measured), though every later step
    converges from its extrapolated guess: its guess now comes from four solved quarter steps.
    Near the limit a sweep contracts slowly (~0.75), and each step is still solved to round-off:
    the quadratic invariants stay at round-off (measured 4e-15 where a looser stop left 3e-12),
    and Π(T) is within 1e-9 of DOP853 (measured 4e-11)."""
    T = 100.0
    _, w = rigid_body_reference(
        TEST_INERTIA, np.eye(3), PI0 / TEST_INERTIA, np.array([0.0, T]), rtol=2.5e-14, atol=2.5e-14
    )
    vec = cj.models.rigid_body_vector(TEST_INERTIA)
    Q0, P0 = cj.models.rigid_body_vector_start(PI0)
    sol = cj.integrate(vec, Q0, PI0 / TEST_INERTIA, P0=P0, dt=1.25, n_steps=80, scheme="gauss", order=16)
    Q, P, mu = np.asarray(sol.Q), np.asarray(sol.p), np.asarray(sol.momentum)
    for inv in (np.sum(Q * Q, -1), np.sum(P * P, -1), np.sum(Q * P, -1), np.sum(mu * mu, -1)):
        assert np.max(np.abs(inv - inv[0])) < 1e-13
    assert np.max(np.abs(mu[-1] - w[-1] * TEST_INERTIA)) < 1e-9
    it = np.asarray(sol.stats.iterations)
    assert it[0] > it[1]  # step 0 counts its substeps' sweeps too


def test_one_stage_is_the_midpoint_principle():
    """One Gauss stage is the implicit midpoint rule: the same (Q, p) as the midpoint principle
    with the forward difference (the full march, Newton), to round-off."""
    system = cj.models.rigid_body_vector(TEST_INERTIA)
    Q0, P0 = cj.models.rigid_body_vector_start(PI0)
    kw = dict(P0=P0, dt=0.1, n_steps=200)
    gauss = cj.integrate(system, Q0, PI0 / TEST_INERTIA, scheme="gauss", order=2, **kw)
    mid = cj.integrate(system, Q0, PI0 / TEST_INERTIA, scheme="midpoint", **kw)
    assert np.max(np.abs(np.asarray(gauss.Q) - np.asarray(mid.Q))) < 1e-13
    assert np.max(np.abs(np.asarray(gauss.p) - np.asarray(mid.p))) < 1e-13


@pytest.mark.slow  # ~8 s (three marches); in CI's slow run. The default run keeps the 1-stage identity.
def test_descends_to_the_same_map_of_the_body_momentum():
    """The Gauss step commutes with the linear symmetries of the Clebsch variables, so the body
    momentum's map does not depend on which (Q, P) carries it: on SO(3) (3×3 matrices) and on
    R³ from two different starting pairs, the same Π at every node."""
    n, dt = 400, 0.25
    so3 = cj.integrate(
        cj.models.rigid_body(TEST_INERTIA), np.eye(3), PI0 / TEST_INERTIA, dt=dt, n_steps=n, scheme="gauss", order=8
    )
    vec = cj.models.rigid_body_vector(TEST_INERTIA)
    Q0, P0 = cj.models.rigid_body_vector_start(PI0)
    a = cj.integrate(vec, Q0, PI0 / TEST_INERTIA, P0=P0, dt=dt, n_steps=n, scheme="gauss", order=8)
    # another pair for the same Π0: (Q, P) -> (aQ + bP, cQ + dP) with ad - bc = 1 keeps P × Q
    Q1, P1 = np.asarray(2.0 * Q0 + P0), np.asarray(-0.5 * Q0 + 0.25 * P0)
    assert np.max(np.abs(np.cross(P1, Q1) - PI0)) < 1e-15
    b = cj.integrate(vec, Q1, PI0 / TEST_INERTIA, P0=P1, dt=dt, n_steps=n, scheme="gauss", order=8)
    # each march ends its solves at round-off, not at the same digits: agreement to ~1e-13
    assert np.max(np.abs(np.asarray(a.momentum) - np.asarray(so3.momentum))) < 1e-12
    assert np.max(np.abs(np.asarray(a.momentum) - np.asarray(b.momentum))) < 1e-12


def test_invariants_rigid_body():
    """Order 8, 4000 steps of Δt = 0.25 on R³: |Q|², |P|², Q·P and the Casimir |Π|² to round-off
    (a random walk, thanks to the exact μᵢⱼ + μⱼᵢ = 1), the energy bounded without drift; on
    SO(3), QᵀQ = I to round-off."""
    vec = cj.models.rigid_body_vector(TEST_INERTIA)
    Q0, P0 = cj.models.rigid_body_vector_start(PI0)
    sol = cj.integrate(vec, Q0, PI0 / TEST_INERTIA, P0=P0, dt=0.25, n_steps=4000, scheme="gauss", order=8)
    Q, P, mu = np.asarray(sol.Q), np.asarray(sol.p), np.asarray(sol.momentum)
    for inv in (np.sum(Q * Q, -1), np.sum(P * P, -1), np.sum(Q * P, -1), np.sum(mu * mu, -1)):
        assert np.max(np.abs(inv - inv[0])) < 2e-14  # measured ≤ 5e-15 (a drift would be ~1e-12 here)
    E = 0.5 * np.sum(mu**2 / TEST_INERTIA, -1)
    assert np.max(np.abs(E - E[0])) < 1e-10 * E[0]  # measured 2e-11 relative
    assert dg.envelope_ratio(E - E[0]) < 1.5
    assert np.all(np.asarray(sol.stats.jacobians) == 0)

    so3 = cj.integrate(
        cj.models.rigid_body(TEST_INERTIA), np.eye(3), PI0 / TEST_INERTIA, dt=0.25, n_steps=400, scheme="gauss", order=8
    )
    Qs = np.asarray(so3.Q)
    assert np.max(np.abs(np.einsum("nji,njk->nik", Qs, Qs) - np.eye(3))) < 1e-14


def _energy_errors(compensated: bool, momenta, dt: float, n_steps: int):
    """|E − E0|/E0 at every node of order-8 Gauss marches of the rigid body on SO(3) from each
    body momentum in `momenta` (one vmapped program)."""
    system = cj.models.rigid_body(TEST_INERTIA)
    method = cj.GaussLegendre(order=8, compensated=compensated)

    def energy(mu0):
        sol = cj.integrate(system, jnp.eye(3), mu0 / TEST_INERTIA, dt=dt, n_steps=n_steps, method=method, throw=False)
        E = 0.5 * jnp.sum(sol.momentum**2 / TEST_INERTIA, -1)
        return jnp.abs(E - E[0]) / E[0], jnp.all(sol.valid)

    errors, valid = jax.jit(jax.vmap(energy))(jnp.asarray(momenta))
    assert np.all(np.asarray(valid))
    return np.asarray(errors)


@pytest.mark.slow  # ~30 s (two vmapped marches of 2·10⁴ steps); in CI's slow run
def test_compensated_summation_energy_round_off_is_a_small_random_walk():
    """At Δt = 0.05 order 8's energy error is far below round-off, so what the energy shows is
    round-off alone. Rounding the state at ε|Q| each step makes a random walk of ~ε√n; with the
    step's increments added by compensated summation (the default) the state is rounded at the
    size of its increment, ~εΔt|Q̇|, and the walk is Δt smaller (Hairer, McLachlan &
    Razakarivony 2008). Over 8 bodies and 2·10⁴ steps: the compensated error stays within
    ε(1 + Δt√n), which the uncompensated march exceeds, grows no faster than √n (no drift),
    and is several times below the uncompensated march's, same bodies."""
    rng = np.random.default_rng(3)
    momenta = rng.normal(size=(8, 3))
    momenta /= np.linalg.norm(momenta, axis=1, keepdims=True)
    dt, n = 0.05, 20_000
    new, old = (_energy_errors(c, momenta, dt, n) for c in (True, False))
    steps = np.arange(n + 1)
    # rms over the bodies in 8 equal windows of steps, against the window's last step
    edges = np.linspace(n // 8, n + 1, 9).astype(int)
    rms = lambda e: np.array([np.sqrt(np.mean(e[:, a:b] ** 2)) for a, b in zip(edges[:-1], edges[1:])])
    n_mid = np.array([steps[b - 1] for b in edges[1:]])
    eps = np.finfo(float).eps
    # a walk of ε·Δt per step (the increments' round-off) over ε for evaluating E; measured at
    # 0.26 of this bound, the uncompensated march at 4 times it
    assert np.all(rms(new) <= eps * (1 + dt * np.sqrt(n_mid))), rms(new)
    # growth exponent of the rms over the windows: 1/2 for a random walk, 1 for a drift; loose
    # (measured 0.36): the windows sit near the floor of evaluating E
    slope = np.polyfit(np.log(n_mid), np.log(rms(new)), 1)[0]
    assert slope < 0.85, slope
    # the uncompensated march, same bodies: a walk at ε|Q| per step, several times larger
    assert rms(old)[-1] > 3 * rms(new)[-1], (rms(old), rms(new))


@pytest.mark.slow  # ~8 s; in CI's slow run
def test_heavy_top_noether_momentum_and_order():
    """With a potential (the heavy top, l(ξ, Q)): the momentum about the vertical, a linear
    symmetry's momentum map, to round-off; order 4 against the Euler–Poisson equations."""
    from scipy.integrate import solve_ivp

    from .test_reduction import _vertical, heavy_top_rhs

    I, mgl, chi = np.array([1.0, 1.0, 0.4]), 1.5, np.array([0.0, 0.0, 1.0])
    top = cj.models.heavy_top(I, mgl, chi)
    Q0, w0 = np.asarray(cj.lie.so3_exp(jnp.array([0.5, 0.0, 0.0]))), np.array([0.3, -0.2, 6.0])
    sol = cj.integrate(top, Q0, w0, dt=0.02, n_steps=500, scheme="gauss", order=4)
    Jz = np.asarray(dg.noether_momentum(sol, _vertical))[:, 0]
    assert np.max(np.abs(Jz - Jz[0])) < 1e-12 * np.max(np.abs(sol.momentum[0]))
    T, dts = 1.0, np.array([0.1, 0.05, 0.025])
    y = solve_ivp(
        heavy_top_rhs(I, mgl, chi), (0, T), np.concatenate([Q0.ravel(), w0]), method="DOP853", rtol=1e-13, atol=1e-13
    ).y[:9, -1]
    # concrete calls: the chunk program of the run above serves every dt and run length
    errs = [
        np.max(
            np.abs(
                np.asarray(
                    cj.integrate(top, Q0, w0, dt=dt, n_steps=int(round(T / dt)), scheme="gauss", order=4).Q[-1]
                ).ravel()
                - y
            )
        )
        for dt in dts
    ]
    assert abs(dg.fit_order(dts, errs) - 4) < 0.15, errs


@pytest.mark.slow  # ~11 s (compiles forward and reverse derivatives through the solve); in CI's slow run
def test_symplectic_and_differentiable():
    """The one-step map (Q, P) -> (Q¹, P¹), differentiated through the fixed-point solve by
    forward mode (implicit function theorem), is symplectic: JᵀΩJ = Ω; reverse mode agrees."""
    system = cj.models.rigid_body_vector(TEST_INERTIA)
    Q0, P0 = cj.models.rigid_body_vector_start(PI0)

    def step(y):
        sol = cj.integrate(system, y[:3], PI0 / TEST_INERTIA, P0=y[3:], dt=0.3, n_steps=1, scheme="gauss", order=8)
        return jnp.concatenate([sol.Q[-1], sol.p[-1]])

    y0 = jnp.concatenate([Q0, P0])
    J = np.asarray(jax.jacfwd(step)(y0))
    Omega = np.block([[np.zeros((3, 3)), np.eye(3)], [-np.eye(3), np.zeros((3, 3))]])
    assert np.max(np.abs(J.T @ Omega @ J - Omega)) < 1e-12
    Jr = np.asarray(jax.jacrev(step)(y0))
    assert np.max(np.abs(J - Jr)) < 1e-12


@pytest.mark.slow  # Gauss–Legendre under vmap and cj.batch, each compiled
def test_batch_vmap_and_failure_report():
    """cj.batch equals vmap; a step too large for the fixed-point iteration fails with the
    DIVERGED status, named with its step and batch member, never as a silent NaN trajectory."""
    system = cj.models.rigid_body_vector(TEST_INERTIA)
    rng = np.random.default_rng(0)
    Pis = rng.normal(size=(3, 3))
    Q0s, P0s = jax.vmap(cj.models.rigid_body_vector_start)(jnp.asarray(Pis))

    def run(Q, P, Pi, dt):
        return cj.integrate(system, Q, Pi / TEST_INERTIA, P0=P, dt=dt, n_steps=20, scheme="gauss", order=8, throw=False)

    vmapped = jax.jit(jax.vmap(run))  # one program for the healthy and the failing batch
    dts = jnp.array([0.2, 0.2, 0.2])
    a = vmapped(Q0s, P0s, jnp.asarray(Pis), dts)
    b = jax.jit(cj.batch(run))(Q0s, P0s, jnp.asarray(Pis), dts)
    assert np.all(np.asarray(a.valid)) and np.all(np.asarray(b.valid))
    assert np.max(np.abs(np.asarray(a.momentum) - np.asarray(b.momentum))) < 1e-14

    dts = jnp.array([0.2, 3.0, 0.2])  # member 1: far beyond the iteration's limit
    sol = vmapped(Q0s, P0s, jnp.asarray(Pis), dts)
    assert list(np.asarray(sol.result)) == [cj.Status.SUCCESS, cj.Status.DIVERGED, cj.Status.SUCCESS]
    assert int(sol.failed_step[1]) == 0 and np.all(np.isnan(np.asarray(sol.Q[1, 1:])))

    def run_throw(Q, P, Pi, dt):
        return cj.integrate(system, Q, Pi / TEST_INERTIA, P0=P, dt=dt, n_steps=20, scheme="gauss", order=8)

    with pytest.raises(cj.IntegrationError, match=r"batch member 1, step 0 of 20 .*stopped contracting.*sweeps"):
        sol.raise_if_failed()
    # raised from a host callback under jit/vmap: JAX re-raises it wrapped in its runtime error
    with pytest.raises(Exception, match=r"batch member 1, step 0 of 20 .*stopped contracting"):
        jax.block_until_ready(jax.jit(jax.vmap(run_throw))(Q0s, P0s, jnp.asarray(Pis), dts))
