"""The rigid body (Examples 9 and 30): the full (ξ, P, Q) march against independent references."""

import jax.numpy as jnp
import numpy as np
import pytest

import clebsch_jax as cj
from clebsch_jax import diagnostics as dg

from .helpers import cay_compact_residual, cay_recursion, rigid_body_reference

FIG1_INERTIA = np.array([0.5, 0.6, 1.0])
TEST_INERTIA = np.array([2.0, 1.0, 2.0 / 3.0])


def spatial_generators(Q):
    """Generators ê_k Q of the left SO(3) action (a symmetry of the discrete action)."""
    return jnp.stack([cj.lie.hat(e) @ Q for e in jnp.eye(3)])


def test_full_march_reproduces_cay_recursion():
    """Issue 2, check 1: Example 30's compact reduced equation, 2000 steps at Δt = 0.1."""
    dt, n = 0.1, 2000
    m0 = np.array([np.cos(1.1), 0.0, np.sin(1.1)])
    sol = cj.integrate(
        cj.models.rigid_body(TEST_INERTIA), jnp.eye(3), m0 / TEST_INERTIA, dt=dt, n_steps=n, reduce=False
    )
    X = np.asarray(sol.xi_step)
    # The compact matrix form holds along the computed step velocities ...
    assert cay_compact_residual(TEST_INERTIA, X, dt) <= 1e-12
    # ... and an independent NumPy solve of the recursion from the same first step agrees.
    ref = cay_recursion(TEST_INERTIA, X[0], dt, n)
    assert np.max(np.abs(ref - X)) <= 1e-10


@pytest.mark.parametrize(
    "dmap",
    [cj.cayley, pytest.param(cj.exponential, marks=pytest.mark.slow)],  # exp: ~20 s
    ids=["cayley", "exponential"],
)
def test_order_two_against_tight_reference(dmap):
    """Issue 2, check 2: measured order from a log-log fit against SciPy DOP853 at rtol 1e-13.

    Concrete calls: every Δt and run length uses the compiled chunk program of the full march
    on this system, the one the other tests of this file compile as well (no program of its own).
    """
    system = cj.models.rigid_body(TEST_INERTIA, derivative_map=dmap)
    T = 4.0
    dts = np.array([0.2, 0.1, 0.05, 0.025])
    m0 = np.array([np.cos(1.1), 0.0, np.sin(1.1)])
    Q0 = np.asarray(cj.lie.so3_exp(jnp.array([0.3, -0.2, 0.5])))
    Qref, wref = rigid_body_reference(TEST_INERTIA, Q0, m0 / TEST_INERTIA, np.array([0.0, T]))
    errors_Q, errors_w = [], []
    for dt in dts:
        sol = cj.integrate(system, Q0, m0 / TEST_INERTIA, dt=dt, n_steps=int(round(T / dt)), reduce=False)
        assert np.isclose(float(sol.ts[-1]), T)
        errors_Q.append(np.max(np.abs(np.asarray(sol.Q[-1]) - Qref[-1])))
        errors_w.append(np.max(np.abs(np.asarray(sol.xi[-1]) - wref[-1])))
    order = sol.order
    assert order == 2
    assert abs(dg.fit_order(dts, errors_Q) - order) < 0.15, errors_Q
    assert abs(dg.fit_order(dts, errors_w) - order) < 0.15, errors_w


@pytest.fixture(scope="module")
def figure1_run():
    """The paper's Figure 1 scene: inertia (0.5, 0.6, 1), Δt = 0.1, 2·10⁴ steps (> 100 periods),
    with the full (ξ, P, Q) march (the reduced one is checked against it in test_reduction)."""
    dt, n = 0.1, 20_000
    m0 = np.array([0.6, 0.1, 0.79])
    m0 = m0 / np.linalg.norm(m0)
    system = cj.models.rigid_body(FIG1_INERTIA)
    sol = cj.integrate(system, jnp.eye(3), m0 / FIG1_INERTIA, dt=dt, n_steps=n, reduce=False)
    return system, sol


def test_noether_momentum_conserved_to_round_off(figure1_run):
    """Issue 2, check 3: spatial angular momentum pⁿ paired with the left generators."""
    _, sol = figure1_run
    pi = np.asarray(dg.noether_momentum(sol, spatial_generators))[:10_001]
    rel = np.max(np.abs(pi - pi[0])) / np.max(np.abs(pi[0]))
    assert rel <= 1e-12


def test_rotation_stays_orthogonal(figure1_run):
    """Issue 2, check 4: |QᵀQ - I| ≤ 1e-12 over 10⁴ steps (and beyond)."""
    _, sol = figure1_run
    assert float(jnp.max(dg.orthogonality_error(sol.Q))) <= 1e-12


def test_casimir_conserved(figure1_run):
    """|J|² of the body momentum J = -p⋄Q (Theorem 12's momentum map) is a Casimir."""
    system, sol = figure1_run
    J = np.asarray(dg.body_momentum(system, sol))
    C = np.sum(J * J, axis=-1)
    assert np.max(np.abs(C - C[0])) / C[0] <= 1e-12
    # and the momentum map equals δl/δξ = 𝕀ξ at the nodes (Lemma 7)
    np.testing.assert_allclose(J, FIG1_INERTIA * np.asarray(sol.xi), rtol=0, atol=1e-12)


def test_figure1_energy_bounded_and_orbit_persists(figure1_run):
    """Issue 2, check 5: over 100+ periodic orbits the energy error is bounded with no secular
    drift (envelope of the last tenth vs the first tenth) and the orbit stays closed."""
    system, sol = figure1_run
    J = np.asarray(dg.body_momentum(system, sol))
    # count periods: m_1 changes sign twice per period on this orbit (it circles the e3 axis)
    crossings = np.count_nonzero(np.diff(np.sign(J[:, 0])) != 0)
    assert crossings / 2 >= 100
    E = np.asarray(dg.energy(system, sol))
    err = (E - E[0]) / E[0]
    assert np.max(np.abs(err)) < 1e-2  # O(Δt²) oscillation, Δt = 0.1
    # No drift: a drifting error would grow ~10× from the first tenth to the last tenth.
    assert dg.envelope_ratio(err) < 1.3
    # Orbit persistence: in the last period the body momentum revisits its starting point
    # (the orbit is a closed curve near the exact one, not a spiral).
    last = J[-len(J) // 100 :]
    assert np.min(np.linalg.norm(last - J[0], axis=1)) < 0.05 * np.linalg.norm(J[0])


def test_xi0_is_reproduced_and_P0_is_minimum_norm():
    system = cj.models.rigid_body(TEST_INERTIA)
    Q0 = np.asarray(cj.lie.so3_exp(jnp.array([0.1, 0.7, -0.4])))
    xi0 = np.array([0.3, -1.2, 0.8])
    P0 = np.asarray(cj.initial_multiplier(system, Q0, xi0))
    # δl/δξ = -P⋄Q  with P⋄Q computed independently: <P⋄Q, ξ> = -Tr(Pᵀ Q hat ξ)
    A = np.stack([(Q0 @ np.asarray(cj.lie.hat(e))).ravel() for e in np.eye(3)], axis=1)
    np.testing.assert_allclose(A.T @ P0.ravel(), TEST_INERTIA * xi0, atol=1e-13)
    np.testing.assert_allclose(P0.ravel(), np.linalg.pinv(A.T) @ (TEST_INERTIA * xi0), atol=1e-13)
    sol = cj.integrate(system, Q0, xi0, dt=0.1, n_steps=3, reduce=False)
    np.testing.assert_allclose(np.asarray(sol.xi[0]), xi0, atol=1e-13)
    np.testing.assert_allclose(np.asarray(sol.p[0]), P0, atol=1e-13)
    # P0 given directly gives the same run
    sol2 = cj.integrate(system, Q0, np.zeros(3), P0=P0, dt=0.1, n_steps=3, reduce=False)
    np.testing.assert_allclose(np.asarray(sol2.Q), np.asarray(sol.Q), atol=1e-13)


@pytest.mark.parametrize(
    "make, Q",
    [
        (lambda I: cj.models.rigid_body(I), cj.lie.so3_exp(jnp.array([0.3, -0.7, 1.1]))),
        (lambda I: cj.models.rigid_body_vector(I), jnp.array([0.2, -1.0, 0.4])),
        (lambda I: cj.models.heavy_top(I, 2.5, (0.3, 0.1, 1.0)), cj.lie.so3_exp(jnp.array([0.3, -0.7, 1.1]))),
    ],
    ids=["rigid_body", "rigid_body_vector", "heavy_top"],
)
def test_inverse_legendre_map_solves_the_legendre_relation(make, Q):
    """The models' inverse Legendre map (Lemma 8, ξ = 𝕀⁻¹μ) against Newton's solve of Lemma 7's
    relation δl/δξ(ξ, Q) = μ from a poor guess, for random momenta; the heavy top's potential
    depends on Q only, so its map is the free body's."""
    from clebsch_jax.discrete.residual import nodal_residual
    from clebsch_jax.roots.newton import newton_solve

    system = make(TEST_INERTIA)
    for mu in np.random.default_rng(3).standard_normal((4, 3)):
        mu = jnp.asarray(mu)
        solved, st = newton_solve(
            lambda x: nodal_residual(system, Q, mu, x), jnp.zeros(3), rtol=0.0, atol=0.0, max_iterations=20
        )
        assert int(st.status) == cj.Status.SUCCESS
        np.testing.assert_allclose(system.inverse_legendre(mu, Q), solved, rtol=1e-15, atol=1e-15)
