"""Planar point vortices through the engine's midpoint principle (degenerate Lagrangian)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import clebsch_jax as cj
from clebsch_jax import diagnostics as dg
from clebsch_jax import models

from .helpers import implicit_midpoint_vortices, vortex_reference, vortex_rhs

LEAPFROG_GAMMA = np.array([1.0, -1.0, 1.0, -1.0])
# Two coaxial pairs, half-widths 1 and 0.5 (ratio 0.5 > 0.382: stable leapfrogging, Acheson 2000).
LEAPFROG_Q0 = np.array([[0.0, 1.0], [0.0, -1.0], [0.0, 0.5], [0.0, -0.5]])


def _run(gamma, Q0, dt, n_steps, **kw):
    system = models.point_vortices(gamma)
    return cj.integrate(system, Q0, models.vortex_velocity(gamma, Q0), dt=dt, n_steps=n_steps, **kw)


def test_the_model_follows_the_vortex_convention_and_is_degenerate():
    gamma = np.array([0.7, -1.3, 2.0])
    Q = np.array([[0.1, 0.2], [1.0, -0.4], [-0.6, 0.9]])
    # velocity from autodiff of H equals the Biot–Savart law written independently
    np.testing.assert_allclose(models.vortex_velocity(gamma, Q), vortex_rhs(gamma, Q), rtol=1e-13, atol=1e-15)
    system = models.point_vortices(gamma)
    assert system.degenerate and system.has_potential
    with pytest.raises(ValueError, match="scheme"):
        cj.integrate(system, Q, models.vortex_velocity(gamma, Q), dt=0.1, n_steps=2, scheme="left")


def test_the_midpoint_principle_is_the_implicit_midpoint_rule():
    """Nothing vortex-specific is written in the engine, yet its steps equal an independent NumPy
    implicit midpoint rule (Rowley & Marsden 2002: the midpoint discretisation of a Lagrangian
    linear in the velocity, started on the constraint p = ∂l/∂ξ, stays on it)."""
    gamma = np.array([1.0, 0.6, -0.4])
    Q0 = np.array([[0.0, 0.0], [1.0, 0.2], [-0.3, 1.1]])
    sol = _run(gamma, Q0, 0.05, 200)
    assert sol.scheme == "midpoint" and sol.order == 2 and sol.xi is None
    ref = implicit_midpoint_vortices(gamma, Q0, 0.05, 200)
    np.testing.assert_allclose(sol.Q, ref, rtol=0, atol=1e-12)
    # xi_step is the velocity at each step's midpoint
    mid = 0.5 * (ref[1:] + ref[:-1])
    np.testing.assert_allclose(sol.xi_step, np.stack([vortex_rhs(gamma, q) for q in mid]), atol=1e-11)


def test_two_vortices_rotate_rigidly_at_the_exact_rate_with_order_two():
    gamma, d = np.array([1.0, 0.5]), 1.0
    Q0 = np.array([[0.0, 0.0], [d, 0.0]])
    omega = gamma.sum() / (2 * np.pi * d**2)
    centre = (gamma[:, None] * Q0).sum(0) / gamma.sum()

    def exact(t):
        c, s = np.cos(omega * t), np.sin(omega * t)
        R = np.array([[c, -s], [s, c]])
        return centre + (Q0 - centre) @ R.T

    T, dts = 4.0, np.array([0.2, 0.1, 0.05, 0.025])
    n = int(round(T / dts[-1]))  # one program for every dt: dt is traced, n_steps is static
    errors = []
    for dt in dts:
        sol = _run(gamma, Q0, dt, n)
        k = int(round(T / dt))
        errors.append(np.max(np.abs(sol.Q[k] - exact(T))))
        # rigid: the distance and the centre of vorticity are invariants of the discrete flow
        dist = np.linalg.norm(sol.Q[:, 0] - sol.Q[:, 1], axis=-1)
        np.testing.assert_allclose(dist, d, rtol=1e-13)
        np.testing.assert_allclose(
            (gamma[None, :, None] * sol.Q).sum(1) / gamma.sum(), centre[None].repeat(n + 1, 0), atol=1e-13
        )
    assert abs(dg.fit_order(dts, errors) - 2.0) < 0.15, errors
    # the measured angular velocity converges to (Γ₁+Γ₂)/(2π d²)
    sol = _run(gamma, Q0, dts[-1], n)
    rel = sol.Q[:, 0] - sol.Q[:, 1]
    angle = np.unwrap(np.arctan2(rel[:, 1], rel[:, 0]))
    omega_num = (angle[-1] - angle[0]) / T
    assert abs(omega_num - omega) < 1e-4 * omega


@pytest.fixture(scope="module")
def leapfrog():
    # 2·10⁴ steps of Δt 0.02: T = 400, about 70 leapfrogging cycles
    return _run(LEAPFROG_GAMMA, LEAPFROG_Q0, 0.02, 20_000)


def test_leapfrogging_pairs_keep_leapfrogging_over_a_long_run(leapfrog):
    Q = np.asarray(leapfrog.Q)
    ts = np.asarray(leapfrog.ts)
    lead = np.sign(Q[:, 0, 0] - Q[:, 2, 0])  # the outer pair's x minus the inner pair's
    passes = np.nonzero(np.diff(lead[1:]))[0]  # node 0: both pairs at x = 0
    assert len(passes) >= 130, len(passes)
    gaps = np.diff(ts[passes])
    # the passes stay periodic: no drift of the leapfrogging period over the run
    assert np.max(np.abs(gaps - np.median(gaps))) <= 2.5 * 0.02, (gaps.min(), gaps.max())
    # the pairs exchange their widths (1 and 0.5) and never separate or merge
    assert 0.49 < Q[:, [0, 2], 1].min() and Q[:, [0, 2], 1].max() < 1.01
    # mirror symmetry about the x axis is kept (it is a symmetry of the midpoint rule); the
    # error grows only from round-off through the 20000 steps
    assert np.max(np.abs(Q[:, 0, 1] + Q[:, 1, 1])) < 1e-9
    # and the first few cycles agree with a tight DOP853 solve
    k = 1000
    ref = vortex_reference(LEAPFROG_GAMMA, LEAPFROG_Q0, ts[: k + 1])
    # second-order method at Δt 0.02 over T = 20: phase error of a few 1e-4
    assert np.max(np.abs(Q[: k + 1] - ref)) < 2e-3


def test_impulses_are_conserved_to_roundoff_and_H_is_bounded(leapfrog):
    Q = leapfrog.Q
    lin = models.vortex_linear_impulse(LEAPFROG_GAMMA, Q)
    ang = models.vortex_angular_impulse(LEAPFROG_GAMMA, Q)
    scale = float(jnp.max(jnp.sum(jnp.abs(LEAPFROG_GAMMA)[:, None] * jnp.sum(Q * Q, -1).T, axis=0)))
    # quadratic invariants of the implicit midpoint rule: conserved up to round-off accumulated
    # over 2·10⁴ steps of an O(1)-sized configuration moving ~100 units (|Q|² ~ 1e4 by the end)
    assert float(jnp.max(jnp.abs(lin - lin[0]))) < 1e-11
    assert float(jnp.max(jnp.abs(ang - ang[0]))) < 1e-14 * scale * 100
    H = np.asarray(models.vortex_hamiltonian(LEAPFROG_GAMMA, Q))
    err = H - H[0]
    assert np.max(np.abs(err)) < 1e-4 * abs(H[0])
    assert dg.envelope_ratio(err) < 1.5  # bounded, no secular drift
    # the engine's energy diagnostic is H for a Lagrangian linear in the velocity
    np.testing.assert_allclose(dg.energy(models.point_vortices(LEAPFROG_GAMMA), leapfrog), H, rtol=1e-13)


def test_a_random_cluster_conserves_impulses_over_1e4_steps():
    rng = np.random.default_rng(3)
    gamma = rng.uniform(0.5, 1.5, 6)  # one sign: no collapse, the cluster stays bounded
    Q0 = rng.normal(size=(6, 2))
    sol = _run(gamma, Q0, 0.01, 10_000)
    lin = models.vortex_linear_impulse(gamma, sol.Q)
    ang = models.vortex_angular_impulse(gamma, sol.Q)
    assert float(dg.relative_drift(lin, feature_ndim=1)) < 1e-12
    assert float(dg.relative_drift(ang)) < 1e-12
    H = np.asarray(models.vortex_hamiltonian(gamma, sol.Q))
    # H is not a quadratic invariant: its error oscillates at O(Δt²) (measured 1.1e-5·|H| here,
    # 2.8e-6 at Δt/2, with pairs as close as 0.25); a factor 3 of margin. The no-drift check
    # on a regular (quasi-periodic) orbit is the leapfrog test's envelope ratio.
    assert np.max(np.abs(H - H[0])) < 3e-5 * np.max(np.abs(H))


COLLAPSE_GAMMA = np.array([2.0, 2.0, -1.0])
# Σ_{a<b} Γ_aΓ_b = 0 and Σ_{a<b} Γ_aΓ_b r_ab² = 4·4 − 2·6 − 2·2 = 0 (Aref's conditions): the
# triangle keeps its shape and shrinks self-similarly, r_ab(t)² = r_ab(0)²(1 − t/τ).
COLLAPSE_Q0 = np.array([[-1.0, 0.0], [1.0, 0.0], [1.0, np.sqrt(2.0)]])


def _collapse_time():
    r2 = np.sum((COLLAPSE_Q0[0] - COLLAPSE_Q0[1]) ** 2)
    v = vortex_rhs(COLLAPSE_GAMMA, COLLAPSE_Q0)
    dr2 = 2 * np.dot(COLLAPSE_Q0[0] - COLLAPSE_Q0[1], v[0] - v[1])
    return -r2 / dr2


def test_three_vortex_collapse_is_followed_then_reported_as_a_failure():
    tau, dt = _collapse_time(), 0.02
    n = int(1.2 * tau / dt)
    sol = _run(COLLAPSE_GAMMA, COLLAPSE_Q0, dt, n, throw=False)
    ts, valid = np.asarray(sol.ts), np.asarray(sol.valid)
    pairs = [(0, 1), (0, 2), (1, 2)]
    r2 = np.stack([np.sum((sol.Q[:, a] - sol.Q[:, b]) ** 2, -1) for a, b in pairs], -1)
    r2_exact = np.sum((COLLAPSE_Q0[[0, 0, 1]] - COLLAPSE_Q0[[1, 2, 2]]) ** 2, -1)[None] * (1 - ts / tau)[:, None]
    well_separated = ts <= 0.9 * tau  # sizes down to √0.1 ≈ 0.32 of the initial triangle
    assert valid[well_separated].all()
    np.testing.assert_allclose(r2[well_separated], r2_exact[well_separated], rtol=1e-9)
    # the run stops at the collapse with a reported failure, not with NaN passed off as data
    assert int(sol.result) != cj.Status.SUCCESS
    step = int(sol.failed_step)
    assert 0.9 * tau < ts[step] <= tau + dt
    assert valid[: step + 1].all() and not valid[step + 1 :].any()
    assert np.isnan(np.asarray(sol.Q[step + 1 :])).all()
    assert np.isfinite(np.asarray(sol.Q[: step + 1])).all()
    with pytest.raises(cj.IntegrationError, match=rf"step {step} of {n} .*Newton"):
        _run(COLLAPSE_GAMMA, COLLAPSE_Q0, dt, n)


def test_vmap_over_circulations_and_initial_positions():
    rng = np.random.default_rng(5)
    gammas = rng.uniform(0.5, 1.5, (3, 4))
    Q0s = rng.normal(size=(3, 4, 2))

    def run(g, q):
        return cj.integrate(models.point_vortices(g), q, models.vortex_velocity(g, q), dt=0.02, n_steps=50, throw=False)

    batch = jax.jit(jax.vmap(run))(gammas, Q0s)
    batch.raise_if_failed()
    for i in range(3):
        one = run(gammas[i], Q0s[i])
        np.testing.assert_allclose(batch.Q[i], one.Q, rtol=0, atol=1e-13)


# ------------------------------------------------------------------------------------------
# Many vortices: the block-chord Newton (jacobian="blocks")


def _random_vortices(n, seed):
    rng = np.random.default_rng(seed)
    gamma = rng.uniform(0.5, 1.5, n) * rng.choice([-1.0, 1.0], n)
    return gamma, rng.normal(size=(n, 2)) * np.sqrt(n)


@pytest.mark.slow  # dense and block Newton marches of a cluster, both compiled
def test_block_jacobian_gives_the_dense_newton_trajectory():
    gamma, Q0 = _random_vortices(8, 11)
    dense = _run(gamma, Q0, 0.01, 100)
    blocks = _run(gamma, Q0, 0.01, 100, jacobian="blocks")
    np.testing.assert_allclose(blocks.Q, dense.Q, rtol=0, atol=1e-12)
    assert float(jnp.max(blocks.stats.residual_norm)) < 1e-13


@pytest.mark.slow  # CI runs it; gradients through the march are checked in the default run by tests/test_engine.py
def test_gradients_through_the_block_solver_match_finite_differences():
    gamma, Q0 = _random_vortices(5, 2)

    def final_x(scale):
        Q = Q0 * scale
        sol = cj.integrate(
            models.point_vortices(gamma), Q, models.vortex_velocity(gamma, Q), dt=0.02, n_steps=20, jacobian="blocks"
        )
        return sol.Q[-1, 0, 0]

    g = float(jax.grad(final_x)(1.0))
    h = 1e-5
    fd = (float(final_x(1.0 + h)) - float(final_x(1.0 - h))) / (2 * h)
    assert abs(g - fd) < 1e-6 * max(1.0, abs(fd))  # central difference error O(h²) ~ 1e-10, GMRES 1e-13


@pytest.mark.slow
def test_a_thousand_vortices_run_and_match_the_implicit_midpoint_rule():
    gamma, Q0 = _random_vortices(1000, 0)
    sol = _run(gamma, Q0, 0.01, 3, jacobian="blocks")
    assert bool(sol.succeeded)
    ref = implicit_midpoint_vortices(gamma, Q0, 0.01, 3)
    # positions of size ~30; the fixed-point reference converges to ~1e-15 relative
    np.testing.assert_allclose(sol.Q, ref, rtol=0, atol=1e-11)
    lin = models.vortex_linear_impulse(gamma, sol.Q)
    assert float(jnp.max(jnp.abs(lin - lin[0]))) < 1e-10 * float(jnp.max(jnp.abs(Q0)))


# ------------------------------------------------------------------------------------------
# Coincident vortices: a singular configuration, refused naming the pair (issue 40)


def test_coincident_vortices_are_refused_naming_the_pair_on_every_path():
    """Vortices 0 and 3 of four at one point: H and the velocities are infinite there, which no
    time step can cure. Refused before compiling by `integrate`, `vortex_velocity` and
    `cj.sweep` (naming the row), on the sphere too; under `jax.vmap` the member reports
    `INVALID_INPUT` at step 0 and the others run. Vortices close but apart are accepted."""
    gamma = np.array([1.0, -0.5, 0.8, 1.2])
    Q = np.array([[0.3, -0.2], [1.0, 0.5], [-0.7, 0.4], [0.3, -0.2]])
    system = models.point_vortices(gamma)
    singular = r"vortices 0 and 3 coincide \(both at \(0\.3, -0\.2\)\): the configuration is singular"
    with pytest.raises(ValueError, match=rf"^Q0: {singular}.*no time step"):
        cj.integrate(system, Q, np.zeros_like(Q), dt=0.01, n_steps=5)
    apart = np.zeros_like(Q)
    apart[3, 0] = 1.0
    assert models.check_distinct_vortices(Q + 1e-6 * apart) is None  # close, yet apart: accepted
    Qs = np.stack([Q + 0.5 * apart, Q])
    with pytest.raises(ValueError, match=rf"^Q\[1\]: {singular}"):
        models.vortex_velocity(gamma, Qs)
    with pytest.raises(ValueError, match=rf"^Q0\[1\]: {singular}"):
        cj.sweep(models.point_vortices, gamma[None], Qs, np.zeros_like(Qs), dt=0.01, n_steps=5, grid=True)

    x = np.array([[0.0, 0.0, 1.0], [0.6, 0.8, 0.0], [0.0, 1.0, 0.0], [0.6, 0.8, 0.0]])  # 1 and 3 on the sphere
    on_sphere = r"vortices 1 and 3 coincide .*: the configuration is singular"
    with pytest.raises(ValueError, match=rf"^Q0: {on_sphere}"):
        cj.integrate(
            models.point_vortices_sphere(gamma), models.sphere_vortex_lift(x), np.zeros((4, 4)), dt=0.01, n_steps=5
        )
    with pytest.raises(ValueError, match=rf"^x: {on_sphere}"):
        models.sphere_vortex_xi(gamma, x)

    run = lambda q: cj.integrate(system, q, jnp.zeros_like(q), dt=0.01, n_steps=5, throw=False)
    sols = jax.vmap(run)(jnp.asarray(Qs))
    assert [cj.Status(int(r)) for r in sols.result] == [cj.Status.SUCCESS, cj.Status.INVALID_INPUT]
    assert int(sols.failed_step[1]) == 0
