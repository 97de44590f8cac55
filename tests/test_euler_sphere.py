"""The Euler–Zeitlin fluid on the sphere (`cj.models.euler_sphere`): its Laplacian and
quantisation against their definitions and SciPy's spherical harmonics, the engine's reduced
march (closure check, matrix-free sweeps), and the mathematics of the runs: Casimirs, energy,
angular momentum, steady states, order 2 against an independent tight solve.

One matrix size (N = 10: 100 unknowns in the default unitary form, above the dense Newton limit
`DENSE_NEWTON_MAX`, so that the default march sweeps) for the marches, so that one compiled
program serves them all."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.special import sph_harm_y

import clebsch_jax as cj
from clebsch_jax.core import model_checks
from clebsch_jax.core.model_checks import check_model
from clebsch_jax.discrete.reduction import MatrixAlgebraReduction, find_reduction
from clebsch_jax.steppers.choose import choose_method

models = cj.models
N = 10


def spin_matrices(N):
    """J1, J2, J3 of spin s = (N − 1)/2, row 0 the state m = s (an independent construction)."""
    s = 0.5 * (N - 1)
    m = s - np.arange(N)
    Jp = np.zeros((N, N))
    for i in range(1, N):
        Jp[i - 1, i] = np.sqrt(s * (s + 1) - m[i] * (m[i] + 1))
    return 0.5 * (Jp + Jp.T), (Jp - Jp.T) / 2j, np.diag(m)


def dense_laplacian(N):
    """Δ_N = −Σ ad(J_a)² as a dense N²×N² matrix acting on row-major vec(P) (reference only)."""
    eye = np.eye(N)
    ad = [np.kron(J, eye) - np.kron(eye, J.T) for J in spin_matrices(N)]
    return -sum(A @ A for A in ad)


def random_coefficients(N, seed, decay=1.0):
    """c[l, m] (0 ≤ m ≤ l < N) of a real trace-free field, amplitude ~ (1 + l)^-decay."""
    rng = np.random.default_rng(seed)
    c = rng.normal(size=(N, N)) + 1j * rng.normal(size=(N, N))
    c = np.tril(c) * (1.0 + np.arange(N))[:, None] ** -decay
    c[:, 0] = c[:, 0].real
    c[0, 0] = 0.0
    return c


def run(W, dt, n_steps, **kw):
    """The default march of the model from the vorticity matrix W; the vorticity at every node."""
    Q0, xi0 = models.euler_sphere_start(W)
    sol = cj.integrate(models.euler_sphere(W.shape[0]), Q0, xi0, dt=dt, n_steps=n_steps, reconstruct=False, **kw)
    return sol, np.asarray(models.euler_sphere_vorticity(sol.momentum))


# --- the Laplacian and the quantisation ------------------------------------------------------


def test_laplacian_is_hoppe_yau_and_its_inverse_solves_it():
    L = dense_laplacian(N)
    rng = np.random.default_rng(0)
    P = rng.normal(size=(N, N)) + 1j * rng.normal(size=(N, N))
    assert np.allclose(np.asarray(models.euler_sphere_laplacian(P)).ravel(), L @ P.ravel(), atol=1e-12)
    assert np.allclose(
        np.sort(np.linalg.eigvalsh(L.real)),
        np.sort(np.concatenate([[-l * (l + 1)] * (2 * l + 1) for l in range(N)])),
        atol=1e-10,
    )
    W = P - np.trace(P) / N * np.eye(N)
    X = np.asarray(models.euler_sphere_inverse_laplacian(W))
    assert abs(np.trace(X)) < 1e-13
    assert np.max(np.abs(L @ X.ravel() - W.ravel())) < 1e-12
    # n = 3, the smallest size with every kind of column in the packed solves (diagonal k above
    # diagonal −(n + 1 − k), the padding an identity row)
    W3 = P[:3, :3] - np.trace(P[:3, :3]) / 3 * np.eye(3)
    X3 = np.asarray(models.euler_sphere_inverse_laplacian(W3))
    assert np.max(np.abs(dense_laplacian(3) @ X3.ravel() - W3.ravel())) < 1e-13


def test_basis_is_orthogonal_eigenvectors_with_spherical_harmonic_phases():
    L = dense_laplacian(N)
    bases = models.euler_sphere_basis(N)
    J1, J2, _ = spin_matrices(N)
    Jm = J1 - 1j * J2
    T = {}
    for m, V in enumerate(bases):
        for l in range(m, N):
            c = np.zeros((N, N), complex)
            c[l, m] = 1.0
            T[l, m] = 1j * np.asarray(models.euler_sphere_quantise(c))  # the upper part is T_lm
            T[l, m] = np.triu(T[l, m], m) if m else T[l, m]
            assert np.allclose(L @ T[l, m].ravel(), -l * (l + 1) * T[l, m].ravel(), atol=1e-11)
            assert np.isclose(np.vdot(T[l, m], T[l, m]).real, N / (4 * np.pi))
    # Condon–Shortley: T_l0 positive at the north pole, J- lowers with +sqrt((l+m)(l-m+1))
    for l in range(N):
        assert T[l, 0][0, 0] > 0
        for m in range(1, l + 1):
            lowered = Jm @ T[l, m] - T[l, m] @ Jm
            assert np.allclose(lowered, np.sqrt((l + m) * (l - m + 1)) * T[l, m - 1], atol=1e-11)


def test_quantisation_round_trip_and_field_against_scipy():
    c = random_coefficients(N, 1)
    W = np.asarray(models.euler_sphere_quantise(c))
    assert np.max(np.abs(W + W.conj().T)) == 0.0  # skew-Hermitian by construction
    assert abs(np.trace(W)) < 1e-14  # c00 = 0: zero mean
    assert np.max(np.abs(np.asarray(models.euler_sphere_coefficients(W)) - c)) < 1e-13
    theta, phi = np.linspace(0.05, 3.1, 9), np.linspace(0.0, 6.2, 7)
    T, P = np.meshgrid(theta, phi, indexing="ij")
    reference = sum(
        c[l, 0].real * sph_harm_y(l, 0, T, P).real
        + sum(2 * np.real(c[l, m] * sph_harm_y(l, m, T, P)) for m in range(1, l + 1))
        for l in range(N)
    )
    assert np.max(np.abs(models.euler_sphere_field(W, theta, phi) - reference)) < 1e-12


def test_quantisation_is_the_sum_over_the_basis_beyond_one_block_of_diagonals():
    """Past one batched product (`DIAGONALS_PER_PRODUCT` diagonals): W = −i Σ c_lm T_lm with
    the T_lm written out entry by entry from `euler_sphere_basis` (T_l,−m = (−1)^m T_lmᴴ), and
    the coefficients back from W, to round-off."""
    from clebsch_jax.models._euler_sphere_quantisation import DIAGONALS_PER_PRODUCT

    Nb = 2 * DIAGONALS_PER_PRODUCT + 3
    c = random_coefficients(Nb, 7)
    bases = models.euler_sphere_basis(Nb)
    H = np.zeros((Nb, Nb), complex)
    for m, V in enumerate(bases):
        for l in range(m, Nb):
            T = np.zeros((Nb, Nb))
            T[np.arange(Nb - m), np.arange(m, Nb)] = np.sqrt(Nb / (4 * np.pi)) * V[:, l - m]
            H += c[l, m] * T if m == 0 else c[l, m] * T + np.conj(c[l, m]) * T.T
    W = np.asarray(models.euler_sphere_quantise(c))
    assert np.max(np.abs(W - (-1j * H))) < 1e-13 * np.max(np.abs(H))
    assert np.max(np.abs(np.asarray(models.euler_sphere_coefficients(W)) - c)) < 1e-13 * np.max(np.abs(c))


def test_commutator_quantises_the_poisson_bracket():
    """(1/ħ)[Ŵ(z), Ŵ(x)] = Ŵ({z, x}) = Ŵ(y) with {f, g} = n·(∇f × ∇g): the model's
    Ẇ = [P, W]/ħ is Euler's ω̇ = {ψ, ω} (exact for degree 1, the spin matrices)."""
    Nq = 9

    def field(l, m, value):
        c = np.zeros((Nq, Nq), complex)
        c[l, m] = value
        return np.asarray(models.euler_sphere_quantise(c))

    a = np.sqrt(2 * np.pi / 3)
    Wz, Wx, Wy = field(1, 0, np.sqrt(4 * np.pi / 3)), field(1, 1, -a), field(1, 1, 1j * a)
    theta, phi = np.array([0.3, 1.9]), np.array([0.4, 4.0])
    T, P = np.meshgrid(theta, phi, indexing="ij")
    assert np.allclose(models.euler_sphere_field(Wx, theta, phi), np.sin(T) * np.cos(P), atol=1e-13)
    bracket = (Wz @ Wx - Wx @ Wz) / models.euler_sphere_hbar(Nq)
    assert np.max(np.abs(bracket - Wy)) < 1e-13


# --- the engine takes the model to its reduced march -------------------------------------------


@pytest.mark.parametrize("form", models.EULER_SPHERE_FORMS)
def test_engine_closure_check_reduces_without_a_basis(form):
    system = models.euler_sphere(N, form=form)
    W = models.euler_sphere_quantise(random_coefficients(N, 2))
    Q0, xi0 = models.euler_sphere_start(W, form)
    red, reason = find_reduction(system, Q0, xi0)
    # the unitary form declares its group (its velocity map is the representation); the real
    # form's right multiplication by ξ is found by the engine, with no basis either way
    expected = cj.UnitaryAlgebra if form == "unitary" else MatrixAlgebraReduction
    assert isinstance(red, expected) and reason == "applies"
    method = choose_method(system, Q0, xi0)
    assert isinstance(method, cj.ReducedStep) and isinstance(method.root_finder, cj.FixedPoint)
    # the Legendre map inverts: the momentum of ξ0 is twice the coordinates of W (unitary:
    # Re W + Im W) or its real form
    mu0 = jax.grad(system.lagrangian)(xi0)
    W = np.asarray(W)
    expected_mu0 = 2 * (W.real + W.imag) if form == "unitary" else models.euler_sphere_real_form(W)
    assert np.max(np.abs(mu0 - expected_mu0)) < 1e-13
    assert np.max(np.abs(models.euler_sphere_vorticity(mu0, form) - W)) < 1e-13


@pytest.mark.slow  # reverse-mode gradients and forward-over-reverse Hessians of the fluid's Lagrangian, each compiled
def test_lagrangian_gradient_is_the_symmetric_operator_and_agrees_with_autodiff():
    """l's derivative is stated (∇l = ħKξ, K symmetric): it agrees to round-off with reverse
    mode through the quadratic form ½ħ⟨ξ, Kξ⟩ written out here, and its Hessian (forward over
    reverse, as the model checks and Newton form it) with that of the quadratic form."""
    from clebsch_jax.models._euler_sphere import _apply_K

    Ns = 3
    l = models.euler_sphere(Ns, form="real").lagrangian
    hbar = models.euler_sphere_hbar(Ns)
    quadratic = lambda x: 0.5 * hbar * jnp.sum(x * _apply_K(x, inverse=False))
    xi = jnp.asarray(np.random.default_rng(3).normal(size=(2 * Ns, 2 * Ns)))
    scale = np.max(np.abs(jax.grad(quadratic)(xi)))
    assert np.max(np.abs(jax.grad(l)(xi) - jax.grad(quadratic)(xi))) < 1e-14 * scale
    flat = lambda f: lambda y: f(y.reshape(xi.shape))
    H, H_ref = jax.hessian(flat(l))(xi.ravel()), jax.hessian(flat(quadratic))(xi.ravel())
    assert np.max(np.abs(H - H_ref)) < 1e-14 * np.max(np.abs(H_ref))
    assert np.max(np.abs(H - H.T)) < 1e-14 * np.max(np.abs(H))
    # the unitary form: l(S) = ħ⟨S, −Δ̂S⟩ with −Δ̂ written out here as the dense Hoppe–Yau
    # matrix (tests' own construction) plus the centre's weight κ = N² on the trace
    lu = models.euler_sphere(Ns).lagrangian
    K = -np.real(dense_laplacian(Ns)) + Ns**2 * np.outer(np.eye(Ns).ravel(), np.eye(Ns).ravel()) / Ns
    S = np.random.default_rng(4).normal(size=(Ns, Ns))
    assert float(lu(jnp.asarray(S))) == pytest.approx(hbar * S.ravel() @ K @ S.ravel(), rel=1e-14)
    Hu = jax.hessian(lambda y: lu(y.reshape(S.shape)))(jnp.asarray(S).ravel())
    assert np.max(np.abs(Hu - 2 * hbar * K)) < 1e-13 * np.max(np.abs(K))


def test_closure_check_of_the_velocity_map():
    """The general (dense) closure check agrees: right multiplication by ξ is closed."""
    Ns = 2
    system = models.euler_sphere(Ns, form="real")
    assert cj.check_closure(system, jnp.eye(2 * Ns), jnp.zeros((2 * Ns, 2 * Ns))).closed
    # the unitary form's velocity map, Q·R(Z(S)), spans R(u(N)): closed too
    assert cj.check_closure(models.euler_sphere(Ns), jnp.eye(2 * Ns), jnp.zeros((Ns, Ns))).closed


def test_matrix_free_model_checks_refuse_a_wrong_inverse_legendre_map(monkeypatch):
    # the checks that form no Hessian, which run above DENSE_CHECK_MAX unknowns, here at N = 10
    monkeypatch.setattr(model_checks, "DENSE_CHECK_MAX", 0)
    Nl = N
    good = models.euler_sphere(Nl)
    W = models.euler_sphere_quantise(random_coefficients(Nl, 3))
    Q0, xi0 = models.euler_sphere_start(W)
    check_model(good, Q0, xi0, 0.1)  # passes
    bad = cj.ClebschSystem(
        lagrangian=good.lagrangian,
        velocity_map=good.velocity_map,
        derivative_map=good.derivative_map,
        inverse_legendre=lambda mu, Q: 2.0 * good.inverse_legendre(mu, Q),
    )
    with pytest.raises(ValueError, match="inverse_legendre"):
        check_model(bad, Q0, xi0, 0.1)
    affine = cj.ClebschSystem(
        lagrangian=good.lagrangian,
        velocity_map=lambda xi, Q: good.velocity_map(xi, Q) + Q,
        derivative_map=good.derivative_map,
        inverse_legendre=good.inverse_legendre,
    )
    with pytest.raises(ValueError, match="velocity_map"):
        check_model(affine, Q0, xi0, 0.1)


@pytest.mark.slow  # N = 16 fluid sweeps on both solvers: the default run's costliest test
def test_sweeps_and_newton_give_the_same_steps():
    """The matrix-free sweeps solve the same equations as dense Newton (N = 4: 64 unknowns)."""
    Ns = 4
    W = models.euler_sphere_quantise(random_coefficients(Ns, 4))
    Q0, xi0 = models.euler_sphere_start(W)
    system = models.euler_sphere(Ns)
    runs = [
        cj.integrate(system, Q0, xi0, dt=0.05, n_steps=20, method=cj.ReducedStep(root_finder=finder, reconstruct=False))
        for finder in (cj.Newton(), cj.FixedPoint())
    ]
    assert np.max(np.abs(runs[0].momentum - runs[1].momentum)) < 1e-12
    assert np.all(runs[1].stats.jacobians == 0)


# --- the runs ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def long_run():
    W = models.euler_sphere_quantise(random_coefficients(N, 5))
    sol, Ws = run(W, 0.05, 4000)  # t = 200: a few hundred turnover times of the largest eddies
    return W, sol, Ws


def test_casimirs_conserved_to_round_off(long_run):
    _, sol, Ws = long_run
    assert sol.result == cj.Status.SUCCESS and sol.form == "reduced"
    C = np.asarray(models.euler_sphere_casimirs(Ws))
    # tr(W³) of a random field is near zero: judge it against |W|³ (tr|W|³)
    size = np.array([1.0, np.sum(np.abs(np.linalg.eigvalsh(1j * Ws[0])) ** 3), 1.0])
    scale = np.where(size == 1.0, np.abs(C[0]), size)
    assert np.max(np.abs(C - C[0]) / scale) < 1e-12
    # the spectrum itself (all Casimirs)
    spectra = np.linalg.eigvalsh(1j * Ws)
    assert np.max(np.abs(spectra - spectra[0])) < 1e-12 * np.max(np.abs(spectra[0]))


def test_default_sweeps_are_tested_after_each_and_solve_the_same_steps(long_run):
    """The default sweeps (`MATRIX_FREE_SWEEPS`: a test after every sweep) solve the same
    steps as `FixedPoint()`'s defaults (4 untested sweeps, then tests of 2) to round-off, in
    fewer sweeps: counts that are not all of the defaults' parity, and fewer in total."""
    W, sol, _ = long_run
    Q0, xi0 = models.euler_sphere_start(W)
    n = 400
    paired = cj.integrate(
        models.euler_sphere(N),
        Q0,
        xi0,
        dt=0.05,
        n_steps=n,
        method=cj.ReducedStep(root_finder=cj.FixedPoint(), reconstruct=False),
    )
    assert np.max(np.abs(paired.momentum - sol.momentum[: n + 1])) < 1e-13 * np.max(np.abs(sol.momentum[0]))
    each, pairs = np.asarray(sol.stats.iterations[:n]), np.asarray(paired.stats.iterations)
    assert np.all(pairs % 2 == 0) and np.any(each % 2 == 1)
    assert each.sum() < pairs.sum()


def test_energy_bounded_without_drift(long_run):
    _, _, Ws = long_run
    E = np.asarray(models.euler_sphere_energy(Ws))
    error = E / E[0] - 1
    assert np.max(np.abs(error)) < 1e-3
    # bounded: the envelope of the error over the last quarter of the run is not above that
    # over the first (it oscillates with the flow; a drift would grow it fourfold)
    assert cj.diagnostics.envelope_ratio(error, fraction=0.25) < 2.0


def test_angular_momentum_conserved(long_run):
    """The degree-1 part of W (the total angular momentum) is a Noether momentum of the
    rotations: conserved to round-off (while the higher degrees change at O(1))."""
    _, _, Ws = long_run
    c = np.stack([np.asarray(models.euler_sphere_coefficients(W)) for W in Ws[::400]])
    assert np.max(np.abs(c[:, 1, :2] - c[0, 1, :2])) < 1e-12 * np.max(np.abs(c[0]))
    assert np.max(np.abs(c[:, 3, :4] - c[0, 3, :4])) > 1e-2 * np.max(np.abs(c[0]))
    L = np.asarray(models.euler_sphere_angular_momentum(Ws))
    assert np.max(np.abs(L - L[0])) < 1e-12 * np.max(np.abs(c[0]))


def test_angular_momentum_is_the_integral_of_vorticity_times_position():
    """∫ω n dA from the degree-1 coefficients: for ω = a z + b x, (4π/3)(b, 0, a)."""
    c = random_coefficients(N, 9)
    a, b = 0.7, -1.3
    c[1, 0] = a * np.sqrt(4 * np.pi / 3)
    c[1, 1] = -b * np.sqrt(2 * np.pi / 3)
    L = np.asarray(models.euler_sphere_angular_momentum(models.euler_sphere_quantise(c)))
    assert np.allclose(L, 4 * np.pi / 3 * np.array([b, 0.0, a]), atol=1e-13)


def test_zonal_and_degree_one_states_are_steady():
    rng = np.random.default_rng(6)
    c = np.zeros((N, N), complex)
    c[1:, 0] = rng.normal(size=N - 1)  # zonal: T_l0 only
    _, Ws = run(models.euler_sphere_quantise(c), 0.05, 400)
    assert np.max(np.abs(Ws - Ws[0])) < 1e-13 * np.max(np.abs(Ws[0]))
    c = np.zeros((N, N), complex)
    c[1, :2] = [0.7, 0.4 - 0.9j]  # degree 1: a rotated zonal state
    _, Ws = run(models.euler_sphere_quantise(c), 0.05, 400)
    assert np.max(np.abs(Ws - Ws[0])) < 1e-13 * np.max(np.abs(Ws[0]))


def test_single_degree_state_steady_to_the_order_of_the_method():
    """A state of one degree l ≥ 2 that is not a rotated zonal one has P ∝ W and is steady for
    Euler's equation, but not for the isospectral midpoint step: its step velocity solves
    W = (I + A)g(I − A), whose solution g has other degrees at O(Δt²). The departure is the
    method's error, second order in Δt."""
    rng = np.random.default_rng(7)
    c = np.zeros((N, N), complex)
    c[3, :4] = rng.normal(size=4) + 1j * rng.normal(size=4)
    c[3, 0] = c[3, 0].real
    W = models.euler_sphere_quantise(c)
    P = np.asarray(models.euler_sphere_inverse_laplacian(W))
    assert np.max(np.abs(P + np.asarray(W) / 12)) < 1e-13  # P = −W / l(l+1)
    departures = []
    for dt in (0.1, 0.05):
        _, Ws = run(W, dt, round(2.0 / dt))
        departures.append(np.max(np.abs(Ws[-1] - Ws[0])))
    assert np.log2(departures[0] / departures[1]) == pytest.approx(2.0, abs=0.15)


def zeitlin_reference(W0, ts):
    """Ẇ = [P, W]/ħ with Δ_N P = W (dense Laplacian from the spin matrices), by SciPy's DOP853
    at tolerance 1e-13: independent of the model's code and of the march."""
    n = W0.shape[0]
    L = dense_laplacian(n)
    Lp = np.linalg.pinv(L)
    hbar = 2.0 / np.sqrt(n * n - 1.0)

    def rhs(t, y):
        W = (y[: n * n] + 1j * y[n * n :]).reshape(n, n)
        P = (Lp @ W.ravel()).reshape(n, n)
        dW = (P @ W - W @ P) / hbar
        return np.concatenate([dW.real.ravel(), dW.imag.ravel()])

    W0 = np.asarray(W0)
    y = solve_ivp(
        rhs,
        (ts[0], ts[-1]),
        np.concatenate([W0.real.ravel(), W0.imag.ravel()]),
        method="DOP853",
        t_eval=ts,
        rtol=1e-13,
        atol=1e-13,
    ).y
    return (y[: n * n] + 1j * y[n * n :]).T.reshape(len(ts), n, n)


def test_order_two_against_a_tight_reference():
    W = models.euler_sphere_quantise(random_coefficients(N, 8, decay=2.0))
    T = 1.0
    reference = zeitlin_reference(W, np.array([0.0, T]))[-1]
    dts = np.array([0.1, 0.05, 0.025, 0.0125])
    errors = [np.max(np.abs(run(W, dt, round(T / dt))[1][-1] - reference)) for dt in dts]
    order = cj.diagnostics.fit_order(dts, errors)
    assert order == pytest.approx(2.0, abs=0.1)
    assert run(W, 0.1, 1)[0].order == 2  # the order the default method records


def test_orthographic_image_of_the_height_function():
    """ω = z seen from colatitude t: the image's value at screen (x, y) is the height of the
    visible point, y sin t + √(1 − x² − y²) cos t (nearest grid point: to 1/180 of π)."""
    c = np.zeros((N, N), complex)
    c[1, 0] = np.sqrt(4 * np.pi / 3)
    t = 0.9
    image = models.euler_sphere_orthographic(models.euler_sphere_quantise(c), colatitude=t, resolution=41)
    x, y = np.meshgrid(np.linspace(-1, 1, 41), np.linspace(-1, 1, 41))
    inside = x**2 + y**2 <= 1
    height = y * np.sin(t) + np.sqrt(np.clip(1 - x**2 - y**2, 0, None)) * np.cos(t)
    assert np.all(np.isnan(image[~inside]))
    assert np.max(np.abs(image[inside] - height[inside])) < 2 * np.pi / 180


@pytest.mark.slow  # three matrix sizes (three compiled marches) and 400 steps each: ~1.5 min on 2 cores
def test_converges_in_N_to_a_spectral_solve_of_eulers_equation():
    """From a smooth vorticity (degrees ≤ 4), the Zeitlin solution at t = 1 approaches an
    independent pseudo-spectral Galerkin solve of the continuous Euler equation (degree 24,
    DOP853 at 1e-12) as N grows: errors of the coefficients of degree ≤ 8 fall like N⁻²
    (the commutator quantises the Poisson bracket up to O(ħ²), ħ ~ 2/N)."""
    from .helpers import sphere_euler_spectral

    rng = np.random.default_rng(0)
    L0 = 4
    c0 = np.tril(rng.normal(size=(L0 + 1, L0 + 1)) + 1j * rng.normal(size=(L0 + 1, L0 + 1)))
    c0[:, 0] = c0[:, 0].real
    c0[0, 0] = 0.0
    c0 *= np.sqrt(4 * np.pi / (np.sum(np.abs(c0[:, 0]) ** 2) + 2 * np.sum(np.abs(c0[:, 1:]) ** 2)))
    T, dt = 1.0, 0.0025  # the time error (order 2) far below the space error at these N
    reference = sphere_euler_spectral(c0, T, 24)
    assert np.max(np.abs(reference[: L0 + 1, : L0 + 1] - c0)) > 0.3  # the flow moves the field at O(1)
    Ns, errors = np.array([16, 32, 64]), []
    for n in Ns:
        c = np.zeros((n, n), complex)
        c[: L0 + 1, : L0 + 1] = c0
        _, Ws = run(models.euler_sphere_quantise(c), dt, round(T / dt))
        cT = np.asarray(models.euler_sphere_coefficients(Ws[-1]))
        errors.append(np.max(np.abs(cT[:9, :9] - reference[:9, :9])))
    rate = -np.polyfit(np.log(Ns), np.log(errors), 1)[0]
    assert rate == pytest.approx(2.0, abs=0.2), (errors, rate)


def test_bad_input_is_refused_before_compiling():
    for bad in (1, 2.5, True, "8"):
        with pytest.raises(ValueError, match="N: expected an integer"):
            models.euler_sphere(bad)
    with pytest.raises(ValueError, match="coeffs: expected an"):
        models.euler_sphere_quantise(np.zeros((4, 5)))
    with pytest.raises(ValueError, match="W: expected a square"):
        models.euler_sphere_start(np.zeros((4, 5)))
    with pytest.raises(ValueError, match="W: expected a square"):
        models.euler_sphere_coefficients(np.zeros(4))


@pytest.mark.slow  # compiles a vmapped and a differentiated march: ~80 s on a loaded 2-core host
def test_vmap_and_grad_through_the_sweeps():
    """A batch of vorticities under jax.vmap equals the single runs; the gradient of the final
    energy of one mode's amplitude through the sweeps' implicit derivative matches a centred
    difference."""
    Ns = 4
    system = models.euler_sphere(Ns)
    method = cj.ReducedStep(root_finder=cj.FixedPoint(), reconstruct=False)
    Ws = [models.euler_sphere_quantise(random_coefficients(Ns, s)) for s in (10, 11)]
    starts = [models.euler_sphere_start(W) for W in Ws]
    Q0 = starts[0][0]

    def final_momentum(xi0):
        return cj.integrate(system, Q0, xi0, dt=0.05, n_steps=20, method=method, throw=False).momentum[-1]

    batch = jax.vmap(final_momentum)(jnp.stack([x for _, x in starts]))
    for k, (_, xi0) in enumerate(starts):
        assert np.max(np.abs(batch[k] - final_momentum(xi0))) < 1e-13

    direction = starts[1][1]

    def energy(a):
        mu = final_momentum(starts[0][1] + a * direction)
        return models.euler_sphere_energy(models.euler_sphere_vorticity(mu))

    h = 1e-5
    fd = (energy(h) - energy(-h)) / (2 * h)
    assert float(jax.grad(energy)(0.0)) == pytest.approx(float(fd), rel=1e-6)
