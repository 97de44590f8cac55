r"""Issue 7: gradients through `integrate`, shooting for landmark matching, parameter identification.

References are independent of the code under test: central finite differences of the same
objective, forward mode against reverse mode, known momenta that generated the matching
problem, and a rigid-body trajectory from SciPy's DOP853 (not from our integrator) with
Gaussian noise of known σ.

Compile time dominates (one gradient program of the landmark full march costs ~15 s on an idle
core), so the tests share four programs: `LANDMARK_VALUE_AND_GRAD` (the endpoint loss and its
gradient with respect to P0 and the kernel width; it also generates the matching problem),
its forward-mode twin, `shoot`'s cached gradient program for one landmark system (every
optimiser run reuses it), and `fit_parameters`' program for the rigid body at order 4 (the
order-4 finite-difference check and the identification share it).
"""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import clebsch_jax as cj
from clebsch_jax import control
from clebsch_jax.models import landmarks, rigid_body

from .helpers import rigid_body_reference

# --------------------------------------------------------------------------------------------
# The landmark problem: five landmarks on the unit circle, Gaussian kernel of width 0.8, flowed
# for T = 1 by the midpoint principle (second order) in 10 steps.

N_LANDMARKS, WIDTH, DT, N_STEPS = 5, 0.8, 0.1, 10
_ANGLES = 2 * np.pi * np.arange(N_LANDMARKS) / N_LANDMARKS
Q_SOURCE = np.stack([np.cos(_ANGLES), np.sin(_ANGLES)], axis=-1)
P_TRUE = 0.6 * np.random.default_rng(0).normal(size=(N_LANDMARKS, 2))  # moves the landmarks up to 0.66
Y_FIXED = Q_SOURCE[::-1] + 0.3  # an arbitrary fixed target for the gradient checks


def _landmark_endpoint(P0, width, order=None):
    sol = cj.integrate(
        landmarks(width),
        Q_SOURCE,
        jnp.zeros_like(P0),
        P0=P0,
        dt=DT,
        n_steps=N_STEPS,
        scheme="midpoint",
        order=order,
        throw=False,
    )
    return sol.Q[-1]


def _landmark_loss(P0, width):
    """A scalar of the endpoint with no symmetry, and the endpoint itself (aux)."""
    Q_end = _landmark_endpoint(P0, width)
    return jnp.sum((Q_end - Y_FIXED) ** 2) + jnp.sum(jnp.sin(Q_end) * Y_FIXED), Q_end


LANDMARK_VALUE_AND_GRAD = jax.jit(jax.value_and_grad(_landmark_loss, argnums=(0, 1), has_aux=True))


def _landmark_target():
    (_, Q_end), _ = LANDMARK_VALUE_AND_GRAD(P_TRUE, WIDTH)
    return np.asarray(Q_end)


def central_differences(f, x, h):
    """∂f/∂x by central differences, component by component (x any array shape)."""
    x = np.asarray(x, float)
    out = np.zeros_like(x)
    for i in np.ndindex(x.shape):
        e = np.zeros_like(x)
        e[i] = h
        out[i] = (f(x + e) - f(x - e)) / (2 * h)
    return out


# --------------------------------------------------------------------------------------------
# Gradients through the full march and through a composition.


@pytest.mark.slow  # landmark gradients by autodiff and central differences
def test_landmark_gradients_wrt_momenta_and_width_match_central_differences():
    """jit(grad) through the full march (Newton solves differentiated implicitly) against central
    differences, with respect to the initial momenta P0 (10 numbers) and the kernel width."""
    P0 = P_TRUE + 0.1
    (value, _), (g_P, g_w) = LANDMARK_VALUE_AND_GRAD(P0, WIDTH)
    loss_of_P = lambda P: float(LANDMARK_VALUE_AND_GRAD(P, WIDTH)[0][0])
    loss_of_w = lambda w: float(LANDMARK_VALUE_AND_GRAD(P0, w)[0][0])
    h = 1e-5
    fd_P = central_differences(loss_of_P, P0, h)
    fd_w = central_differences(loss_of_w, WIDTH, h)
    print(
        f"loss {float(value):.6f}, |grad_P| {np.max(np.abs(g_P)):.3f}, grad_w {float(g_w):.6f}, "
        f"fd errors {np.max(np.abs(np.asarray(g_P) - fd_P)):.1e}, {abs(float(g_w) - float(fd_w)):.1e}"
    )
    # Central differences: truncation h²/6·|f'''| ~ 1e-10 and round-off ~ 1e-16·|f|/h ~ 1e-11
    # (each step is solved to round-off); the gradients are O(1).
    np.testing.assert_allclose(np.asarray(g_P), fd_P, rtol=0, atol=1e-7)
    assert abs(float(g_w) - float(fd_w)) < 1e-7 * max(1.0, abs(float(fd_w)))
    assert np.max(np.abs(fd_P)) > 0.1 and abs(float(fd_w)) > 0.1  # not a vanishing derivative


@pytest.mark.slow  # landmark derivatives in both modes; the default run keeps test_reverse_mode_does_not_unroll_the_newton_iterations
def test_forward_and_reverse_mode_agree_on_landmarks():
    """jvp (forward mode through custom_root) equals the reverse-mode gradient · tangent."""
    rng = np.random.default_rng(3)
    P0, dP, dw = P_TRUE - 0.1, rng.normal(size=P_TRUE.shape), 0.7
    jvp = jax.jit(lambda P, w, tP, tw: jax.jvp(lambda P, w: _landmark_loss(P, w)[0], (P, w), (tP, tw)))
    value, tangent = jvp(P0, WIDTH, dP, dw)
    (value_r, _), (g_P, g_w) = LANDMARK_VALUE_AND_GRAD(P0, WIDTH)
    reverse = float(np.sum(np.asarray(g_P) * dP) + float(g_w) * dw)
    print(f"forward {float(tangent):.15f}, reverse {reverse:.15f}")
    assert abs(float(value) - float(value_r)) < 1e-13
    # Both solve the same linear systems (transposed), each to round-off.
    assert abs(float(tangent) - reverse) < 1e-11 * max(1.0, abs(reverse))


def _all_equations(jaxpr):
    """Every equation of a jaxpr and of the jaxprs nested in its equations (scan, while, pjit,
    custom_root bodies)."""
    for eqn in jaxpr.eqns:
        yield eqn
        for param in eqn.params.values():
            for sub in param if isinstance(param, (tuple, list)) else (param,):
                inner = getattr(sub, "jaxpr", sub)  # ClosedJaxpr -> Jaxpr
                if hasattr(inner, "eqns"):
                    yield from _all_equations(inner)


def test_reverse_mode_does_not_unroll_the_newton_iterations():
    """The gradient's program is the same whatever the iteration cap: reverse mode goes through
    the implicit function theorem at the root, so nothing of the iterations is stored for the
    backward pass. An unrolled Newton (a Python loop, or a fixed-count loop that JAX turns into a
    differentiable scan) would add equations, or arrays with an axis of length
    `max_newton_iterations`, growing with the cap."""
    cap = 97  # no array of this problem has an axis of this length

    def loss(P0, iterations):
        sol = cj.integrate(
            landmarks(WIDTH),
            Q_SOURCE,
            jnp.zeros_like(P0),
            P0=P0,
            dt=DT,
            n_steps=N_STEPS,
            scheme="midpoint",
            max_newton_iterations=iterations,
            throw=False,
        )
        return jnp.sum(sol.Q[-1] ** 2)

    programs = {k: jax.make_jaxpr(jax.grad(lambda P: loss(P, k)))(P_TRUE).jaxpr for k in (5, cap)}
    equations = {k: list(_all_equations(j)) for k, j in programs.items()}
    assert len(equations[5]) == len(equations[cap])
    assert [e.primitive.name for e in equations[5]] == [e.primitive.name for e in equations[cap]]
    shapes = {
        tuple(v.aval.shape)
        for e in equations[cap]
        for v in (*e.invars, *e.outvars)
        if hasattr(getattr(v, "aval", None), "shape")
    }
    assert not any(cap in s for s in shapes), sorted(s for s in shapes if cap in s)


# The rigid body for the order-4 check and the identification (module-level functions: the
# program fit_parameters compiles is cached on these objects).
INERTIA, OMEGA0, RB_DT, RB_STEPS, RB_ORDER = np.array([2.0, 1.0, 2.0 / 3.0]), np.array([0.3, 1.0, 0.4]), 0.1, 100, 4


def make_rigid_body(log_inertia):
    return rigid_body(jnp.exp(log_inertia))


def body_momentum(sol):
    return sol.momentum


def _observed_momenta(sigma, seed=1):
    """Body momenta Iω at every node of t = 0, 0.1, ..., 10 from DOP853 (rtol 1e-13), plus noise."""
    ts = RB_DT * np.arange(RB_STEPS + 1)
    _, omega = rigid_body_reference(INERTIA, np.eye(3), OMEGA0, ts)
    clean = INERTIA * omega
    return clean + sigma * np.random.default_rng(seed).normal(size=clean.shape), clean


def _rigid_body_fit(params0, observations, optimizer=None, n_iterations=0, **kwargs):
    return control.fit_parameters(
        make_rigid_body,
        params0,
        observations,
        np.eye(3),
        OMEGA0,
        dt=RB_DT,
        n_steps=RB_STEPS,
        observe=body_momentum,
        order=RB_ORDER,
        optimizer=optimizer or optax.sgd(0.0),
        n_iterations=n_iterations,
        **kwargs,
    )


def test_gradient_through_an_order_4_composition_matches_central_differences():
    """Reverse mode through Suzuki's p4s5 composition (5 sub-steps per step, reduced march) of the
    rigid body, with respect to the log-inertia, against central differences."""
    assert cj.step_plan(make_rigid_body(np.zeros(3)), order=RB_ORDER).order == 4
    observations, _ = _observed_momenta(0.01)
    theta = np.log([1.5, 1.2, 0.8])
    fit = _rigid_body_fit(theta, observations)
    fd = central_differences(lambda t: _rigid_body_fit(t, observations).loss, theta, 1e-5)
    print(f"loss {fit.loss:.6f}, gradient {fit.gradient}, fd error {np.max(np.abs(fit.gradient - fd)):.1e}")
    # truncation ~1e-11 and round-off ~1e-16·|f|/h ~ 1e-11 for a loss of size 0.3
    np.testing.assert_allclose(fit.gradient, fd, rtol=0, atol=1e-8)
    assert np.max(np.abs(fd)) > 0.1


# --------------------------------------------------------------------------------------------
# Landmark matching by shooting.


@pytest.mark.slow  # CI runs it; the shooting gradients are checked in the default run by test_landmark_gradients_wrt_momenta_and_width_match_central_differences
def test_landmark_matching_by_shooting_lbfgs_beats_the_best_gradient_descent():
    """Recover initial momenta that carry the source landmarks onto a target generated by known
    momenta, from P0 = 0 (the identity flow). L-BFGS (optax, unit step, no line search) reaches
    a mismatch Σ|Q^N − target|² ≤ 1e-14 (every landmark within 1e-7 of its target); plain
    gradient descent is still orders of magnitude above it after twice as many iterations at
    every step size that converges at all, and a larger step stalls."""
    system, target, tol = landmarks(WIDTH), _landmark_target(), 1e-14

    def run(optimizer, n_iterations):
        return control.shoot(
            system,
            Q_SOURCE,
            target,
            np.zeros_like(Q_SOURCE),
            dt=DT,
            n_steps=N_STEPS,
            optimizer=optimizer,
            n_iterations=n_iterations,
            tol=tol,
            scheme="midpoint",
        )

    lb = run(optax.lbfgs(learning_rate=1.0, linesearch=None), 60)
    print(lb.message)
    assert lb.converged and lb.mismatch <= tol
    assert np.max(np.linalg.norm(lb.endpoint - target, axis=-1)) < 1e-7
    np.testing.assert_array_equal(lb.path[0], Q_SOURCE)
    # The recovered momenta are the generating ones: near the identity the shooting map
    # P0 -> Q^N is a diffeomorphism with a gain of order 1 (measured |ΔP0|/|ΔQ^N| ≈ 1).
    np.testing.assert_allclose(lb.P0, P_TRUE, rtol=0, atol=1e-5)
    assert lb.losses[0] > 0.5 and lb.losses[lb.iterations] == lb.objective

    k = lb.iterations
    for lr in (0.1, 0.2, 0.3):
        gd = run(optax.sgd(lr), 2 * k)
        print(f"gradient descent, step {lr}: mismatch {gd.mismatch:.2e} after {gd.iterations} iterations")
        assert not gd.converged and gd.iterations == 2 * k
        assert gd.mismatch > 100 * tol
        assert gd.mismatch < 1e-2 * gd.losses[0]  # but it does descend
    # The step cannot be raised to catch up: from 0.35 on, descent stalls far from the target.
    gd = run(optax.sgd(0.4), 2 * k)
    print(f"gradient descent, step 0.4: mismatch {gd.mismatch:.2e}")
    assert gd.mismatch > 0.1 * gd.losses[0]


# --------------------------------------------------------------------------------------------
# Parameter identification.


def test_inertia_is_identified_from_noisy_body_momenta_within_the_statistical_error():
    r"""The body momenta of a DOP853 trajectory with Gaussian noise σ = 0.01 (303 numbers of size
    ~1) determine the inertia: Adam on the log-inertia (positivity by the parametrisation) from
    I = (1, 1, 1) recovers it within 4 standard errors, the standard errors being the
    Cramér–Rao bound σ²(JᵀJ)⁻¹ = σ²(2/m)H⁻¹ from the loss Hessian H at the estimate (central
    differences of the gradient). Those are ~1e-3 (relative), so the bound is tight; the
    model error of the order-4 method at Δt = 0.1 (rms 1e-5 against DOP853) is far below σ."""
    sigma = 0.01
    observations, clean = _observed_momenta(sigma)
    # The discrete model at the true inertia reproduces the noiseless data far below σ (measured
    # rms 1.0e-5 = σ/1000), so its bias on the estimate is ~1e-3 standard errors.
    assert _rigid_body_fit(np.log(INERTIA), clean).loss < 1e-5 * sigma**2
    fit = _rigid_body_fit(np.zeros(3), observations, optax.adam(0.05), 300)
    theta = np.asarray(fit.params)
    m = observations.size
    H = np.stack(
        [
            (_rigid_body_fit(theta + e, observations).gradient - _rigid_body_fit(theta - e, observations).gradient)
            / 2e-5
            for e in 1e-5 * np.eye(3)
        ]
    )
    H = 0.5 * (H + H.T)
    cov = sigma**2 * (2.0 / m) * np.linalg.inv(H)
    se = np.sqrt(np.diag(cov))
    error = theta - np.log(INERTIA)
    print(
        f"{fit.message}; inertia {np.exp(theta)}, log-errors {error}, standard errors {se}, "
        f"loss/σ² {fit.loss / sigma**2:.3f}"
    )
    assert np.all(se < 3e-3)  # the data pin the inertia down to ~0.1 %
    assert np.all(np.abs(error) < 4 * se), (error, se)
    # Adam ended at the minimum, well inside the statistical error: the Newton step left is tiny.
    assert np.all(np.abs(np.linalg.solve(H, fit.gradient)) < 0.1 * se)
    # At the minimum the mean squared residual is σ²(1 − 3/m) up to the χ² spread √(2/m) = 0.08.
    assert abs(fit.loss / sigma**2 - 1) < 4 * np.sqrt(2 / m)


# --------------------------------------------------------------------------------------------
# Bad input: clear errors naming the argument, before anything is compiled.


@pytest.fixture
def no_compilation(monkeypatch):
    def boom(*args, **kwargs):
        raise AssertionError("the objective was compiled for invalid input")

    monkeypatch.setattr(control, "shooting_value_and_grad", boom)
    monkeypatch.setattr(control, "fit_value_and_grad", boom)


SHOOT_ARGS = dict(
    system=landmarks(WIDTH),
    Q0=Q_SOURCE,
    target=Q_SOURCE + 0.1,
    P0_init=np.zeros((5, 2)),
    dt=DT,
    n_steps=N_STEPS,
    optimizer=optax.adam(0.1),
    n_iterations=10,
)


@pytest.mark.parametrize(
    "error, kwargs, match",
    [
        (TypeError, dict(system="landmarks"), r"^system: expected a clebsch_jax.ClebschSystem"),
        (ValueError, dict(target=np.zeros((4, 2))), r"^target: expected Q0's shape"),
        (ValueError, dict(P0_init=np.zeros(10)), r"^P0_init: expected Q0's shape"),
        (ValueError, dict(target=np.full((5, 2), np.nan)), r"^target: contains non-finite"),
        (TypeError, dict(optimizer=lambda g: g), r"^optimizer: expected an optax GradientTransformation"),
        (ValueError, dict(n_iterations=-1), r"^n_iterations: expected a Python int"),
        (ValueError, dict(n_iterations=2.5), r"^n_iterations: expected a Python int"),
        (ValueError, dict(dt=-0.1), r"^dt: must be positive"),
        (ValueError, dict(n_steps=0), r"^n_steps: expected a Python int >= 1"),
        (ValueError, dict(regularization=-1.0), r"^regularization: expected a finite number >= 0"),
        (ValueError, dict(tol=float("nan")), r"^tol: expected a finite number >= 0"),
        (ValueError, dict(loss=lambda q, y: q - y), r"^loss: must return a scalar"),
        (TypeError, dict(loss="l2"), r"^loss: expected a function"),
        (ValueError, dict(throw=True), r"^throw: set by this function"),
        (
            ValueError,
            dict(system=rigid_body(INERTIA), Q0=np.eye(3), target=np.eye(3), P0_init=np.zeros((3, 3))),
            r"^xi0: the system's maps do not accept a velocity of Q's shape",
        ),
    ],
)
def test_shoot_rejects_bad_input_naming_the_argument(no_compilation, error, kwargs, match):
    args = dict(SHOOT_ARGS, **kwargs)
    with pytest.raises(error, match=match):
        control.shoot(args.pop("system"), args.pop("Q0"), args.pop("target"), args.pop("P0_init"), **args)


FIT_ARGS = dict(
    make_system=make_rigid_body,
    params0=np.zeros(3),
    observations=np.zeros((RB_STEPS + 1, 3)),
    Q0=np.eye(3),
    xi0=OMEGA0,
    dt=RB_DT,
    n_steps=RB_STEPS,
    observe=body_momentum,
    optimizer=optax.adam(0.1),
    n_iterations=10,
)


@pytest.mark.parametrize(
    "error, kwargs, match",
    [
        (TypeError, dict(make_system=None), r"^make_system: expected a function"),
        (TypeError, dict(make_system=lambda p: p), r"^make_system: must return a clebsch_jax.ClebschSystem"),
        (ValueError, dict(params0={}), r"^params0: expected at least one array"),
        (ValueError, dict(params0=np.array([0.0, np.nan, 0.0])), r"^params0: contains non-finite"),
        (TypeError, dict(observations="data"), r"^observations: expected an array"),
        (TypeError, dict(observe=3), r"^observe: expected a function"),
        (ValueError, dict(gtol=-1.0), r"^gtol: expected a finite number >= 0"),
        (ValueError, dict(n_steps=1.5), r"^n_steps: expected a Python int >= 1"),
    ],
)
def test_fit_parameters_rejects_bad_input_naming_the_argument(no_compilation, error, kwargs, match):
    args = dict(FIT_ARGS, **kwargs)
    with pytest.raises(error, match=match):
        control.fit_parameters(
            args.pop("make_system"),
            args.pop("params0"),
            args.pop("observations"),
            args.pop("Q0"),
            args.pop("xi0"),
            **args,
        )


# --------------------------------------------------------------------------------------------
# Heavier checks (each compiles programs of its own).


@pytest.mark.slow
def test_landmark_gradient_through_an_order_4_composition_matches_central_differences():
    """The full march composed to order 4 (Suzuki p4s5 of the midpoint principle): reverse mode
    with respect to P0 and the width against central differences."""

    def loss(P0, width):
        return jnp.sum(jnp.sin(_landmark_endpoint(P0, width, order=4)) * Y_FIXED)

    value_and_grad = jax.jit(jax.value_and_grad(loss, argnums=(0, 1)))
    P0 = P_TRUE + 0.1
    _, (g_P, g_w) = value_and_grad(P0, WIDTH)
    fd_P = central_differences(lambda P: float(value_and_grad(P, WIDTH)[0]), P0, 1e-5)
    fd_w = central_differences(lambda w: float(value_and_grad(P0, w)[0]), WIDTH, 1e-5)
    np.testing.assert_allclose(np.asarray(g_P), fd_P, rtol=0, atol=1e-7)  # as in the order-2 test
    assert abs(float(g_w) - float(fd_w)) < 1e-7 * max(1.0, abs(float(fd_w)))
    assert np.max(np.abs(fd_P)) > 0.1


@pytest.mark.slow
def test_lbfgs_with_its_zoom_line_search_matches_the_landmarks():
    """optax.lbfgs() with its default line search gets the objective as `value_fn` (a copy of the
    integration inside its update program) and matches as well as the unit-step variant."""
    target, tol = _landmark_target(), 1e-14
    res = control.shoot(
        landmarks(WIDTH),
        Q_SOURCE,
        target,
        np.zeros_like(Q_SOURCE),
        dt=DT,
        n_steps=N_STEPS,
        optimizer=optax.lbfgs(),
        n_iterations=60,
        tol=tol,
        scheme="midpoint",
    )
    print(res.message)
    assert res.converged and res.mismatch <= tol and res.iterations < 40
    np.testing.assert_allclose(res.P0, P_TRUE, rtol=0, atol=1e-5)
    finite = res.losses[: res.iterations + 1]
    assert np.all(np.diff(finite) <= 0)  # a line search with sufficient decrease never goes up


@pytest.mark.slow
def test_regularised_shooting_satisfies_pontryagins_transversality_to_second_order():
    r"""With the kinetic-energy penalty, J = g(Q^N) + λE(P0) and E conserved along the geodesic,
    J = g + (λ/T)∫l dt, whose minimiser satisfies Pontryagin's transversality condition
    p(T) = −(T/λ)∇g(Q(T)) = −(2T/λ)(Q(T) − target). The discrete flow conserves E only to
    O(Δt²), so the condition holds to O(Δt²): its relative defect drops by ~4 when Δt halves."""
    lam, T = 0.5, 1.0
    target = Q_SOURCE + 0.3 * np.array([[1, 0], [0, 1], [-1, 0], [0, -1], [1, 1.0]])
    defects = []
    for n in (10, 20):
        res = control.shoot(
            landmarks(WIDTH),
            Q_SOURCE,
            target,
            np.zeros_like(Q_SOURCE),
            dt=T / n,
            n_steps=n,
            optimizer=optax.lbfgs(learning_rate=1.0, linesearch=None),
            n_iterations=200,
            regularization=lam,
            gtol=1e-12,
            scheme="midpoint",
        )
        assert res.converged, res.message
        p_T, predicted = res.momentum[-1], -(2 * T / lam) * (res.endpoint - target)
        defects.append(np.max(np.abs(p_T - predicted)) / np.max(np.abs(p_T)))
        # the penalty keeps the landmarks off the target: an honest trade-off, not a match
        assert res.mismatch > 1e-3 and res.objective > res.mismatch
    print(f"transversality defects {defects}, ratio {defects[0] / defects[1]:.2f}")
    assert defects[0] < 1e-2  # measured 4.4e-4 at Δt = 0.1
    assert 3.0 < defects[0] / defects[1] < 5.0  # second order


@pytest.mark.slow
def test_a_failing_integration_stops_the_optimisation_with_a_message():
    """A model whose Lagrangian is NaN once ξ₁ exceeds a parameter c: gradient descent on c with a
    large step pushes c below what the trajectory reaches; the loop stops there, names the
    failure, and returns the last iterate whose integration succeeded."""

    def breaks_above(c):
        I = jnp.asarray(INERTIA)
        return cj.ClebschSystem(
            lagrangian=lambda x: 0.5 * jnp.sum(I * x * x) + 1e-3 * jnp.sqrt(c[0] - x[0]),
            velocity_map=lambda x, Q: Q @ cj.lie.hat(x),
            derivative_map=cj.cayley,
        )

    observations = np.zeros((RB_STEPS + 1, 3))  # pulls the momenta, hence c, down
    fit = control.fit_parameters(
        breaks_above,
        np.array([1.0]),
        observations,
        np.eye(3),
        OMEGA0,
        dt=RB_DT,
        n_steps=RB_STEPS,
        observe=body_momentum,
        optimizer=optax.sgd(1e4),
        n_iterations=50,
    )
    print(fit.message)
    assert not fit.converged and "integration failed" in fit.message
    assert np.isfinite(fit.loss) and fit.iterations < 50
    assert np.isnan(fit.losses[fit.iterations + 1 :]).all()
    with pytest.raises(ValueError, match="the initial guess already fails"):
        control.fit_parameters(
            breaks_above,
            np.array([0.1]),
            observations,
            np.eye(3),
            OMEGA0,
            dt=RB_DT,
            n_steps=RB_STEPS,
            observe=body_momentum,
            optimizer=optax.sgd(1.0),
            n_iterations=5,
        )
