"""Methods as data: the stepper objects behind `integrate`, their facts, the rule that picks one,
and `method=` — the same march whichever way the method is named."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import clebsch_jax as cj

RIGID = cj.models.rigid_body(jnp.array([2.0, 1.0, 2.0 / 3.0]))
TOP = cj.models.heavy_top(jnp.array([1.0, 1.0, 0.4]), 1.5)
TOP_Q0 = cj.lie.so3_exp(jnp.array([0.5, 0.0, 0.0]))
EYE, XI0, OMEGA0 = jnp.eye(3), jnp.array([1.3, 0.8, -0.4]), jnp.array([0.1, 0.2, 5.0])


def _same(a, b):
    for f in ("Q", "p", "xi", "xi_step", "P", "momentum"):
        x, y = getattr(a, f), getattr(b, f)
        assert (x is None) == (y is None), f
        if x is not None:
            np.testing.assert_array_equal(x, y, err_msg=f)
    np.testing.assert_array_equal(a.stats.iterations, b.stats.iterations)
    assert (a.form, a.scheme, a.order, a.method) == (b.form, b.scheme, b.order, b.method)


@pytest.mark.slow  # a march per method; the defaults' choice is checked by test_defaults
@pytest.mark.parametrize(
    "options, method",
    [
        (dict(), cj.ReducedStep()),
        (dict(reduce=False, order=4), cj.Composed(cj.FullStep(), cj.SUZUKI_4)),
        (dict(reduce=False, scheme="midpoint"), cj.FullStep(cj.Principle.MIDPOINT)),
    ],
)
def test_method_objects_run_the_march_the_options_choose(options, method):
    """`method=` and the equivalent options are one program: bit-identical solutions."""
    by_options = cj.integrate(RIGID, EYE, XI0, dt=0.1, n_steps=12, **options)
    by_method = cj.integrate(RIGID, EYE, XI0, dt=0.1, n_steps=12, method=method)
    _same(by_options, by_method)


def test_left_right_pair_is_the_documented_second_order_step():
    """With a potential the left principle is first order; order=2 is right(h/2) ∘ left(h/2)."""
    sol = cj.integrate(TOP, TOP_Q0, OMEGA0, dt=0.02, n_steps=10, method=cj.SymmetricPair(cj.ReducedStep()))
    assert (sol.form, sol.order, sol.method) == ("reduced", 2, "right(h/2) o left(h/2)")
    _same(sol, cj.integrate(TOP, TOP_Q0, OMEGA0, dt=0.02, n_steps=10, order=2))


def test_facts_are_data_that_depend_on_the_system():
    left, mid = cj.FullStep(), cj.FullStep("midpoint")
    assert left.facts(RIGID).order == 2 and left.facts(RIGID).symmetric  # Cayley, no potential: Example 30
    assert left.facts(TOP).order == 1 and not left.facts(TOP).symmetric  # l(ξ, Qⁿ) at one end
    assert mid.facts(TOP)[2:4] == (2, True)
    pair = cj.SymmetricPair(cj.FullStep())
    assert pair.facts(TOP).solves_per_step == 2 and pair.facts(TOP).order == 2
    k8 = cj.Composed(pair, "Kahan-Li p8s17")
    assert k8.facts(TOP).order == 8 and k8.facts(TOP).solves_per_step == 34
    assert cj.GaussLegendre(order=12).facts(TOP)[:4] == ("full", "gauss", 12, True)
    assert cj.step_plan(TOP, "left", 8).solves_per_step == k8.facts(TOP).solves_per_step


def test_steppers_are_hashable_values():
    """Static under jit: equal steppers are one cache entry."""
    assert cj.FullStep() == cj.FullStep("left") and hash(cj.FullStep()) == hash(cj.FullStep("left"))
    assert cj.GaussLegendre(order=4) != cj.GaussLegendre(order=6)
    assert len({cj.Newton(), cj.Newton(rtol=0.0), cj.BlockNewton()}) == 2


def test_quick_compile_is_a_fact_of_the_base_stepper():
    """`integrate` compiles a march with `QUICK_COMPILE` unless its stepper says otherwise: the
    Gauss–Legendre step does (its sweeps ran slower so); wrappers ask their base."""
    from clebsch_jax.march.scan import _PROGRAMS

    assert cj.FullStep().quick_compile and cj.ReducedStep().quick_compile
    assert cj.Composed(cj.SymmetricPair(cj.FullStep()), cj.SUZUKI_4).quick_compile
    assert not cj.GaussLegendre(order=8).quick_compile
    assert set(_PROGRAMS) == {True, False}


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: cj.FullStep("sideways"), r"^principle: expected one of"),
        (lambda: cj.FullStep(root_finder=cj.FixedPoint()), r"^root_finder: expected"),
        (lambda: cj.ReducedStep(root_finder=cj.BlockNewton()), r"^root_finder: the reduced step"),
        (lambda: cj.GaussLegendre(order=3), r"^order: Gauss-Legendre expects an even order"),
        (lambda: cj.Composed(cj.FullStep(), "no such coefficients"), r"^composition: unknown name"),
        (lambda: cj.Composed(cj.GaussLegendre(order=4), cj.SUZUKI_4), r"^base: compose"),
        (lambda: cj.Newton(rtol=-1.0), r"^rtol: expected a finite number >= 0"),
        (lambda: cj.FixedPoint(max_iterations=0), r"^max_iterations: expected an int >= 1"),
        (lambda: cj.FixedPoint(per_test=0), r"^per_test: expected an int >= 1"),
    ],
)
def test_bad_steppers_are_refused_when_built(make, match):
    with pytest.raises((ValueError, TypeError), match=match):
        make()


DOTTIE = 0.739085133215160641655312087673873404  # the root of z = cos z (Dottie's number)


@pytest.mark.parametrize("untested, per_test", [(4, 2), (0, 1), (1, 3)])
def test_fixed_point_sweeps_stop_at_the_first_test_at_round_off(untested, per_test):
    """`FixedPoint(untested, per_test)` on z = cos z (contraction factor sin z* = 0.67): the
    root to round-off against its known value, with the sweeps counted as the options say (the
    untested ones, then whole tests of `per_test` sweeps), and testing after each sweep stops
    no later than any other interval does."""
    z0 = jnp.full(3, 1.0)
    finder = cj.FixedPoint(untested=untested, per_test=per_test)
    z, stats = finder.solve(jnp.cos, z0)
    assert stats.status == cj.Status.SUCCESS
    # stopped at an update η ≤ 8ε (round-off): the error left is θ/(1 − θ)·η, θ = sin z* the
    # contraction per sweep, plus the rounding of cos itself
    theta = np.sin(DOTTIE)
    assert np.max(np.abs(np.asarray(z) - DOTTIE)) < (theta / (1 - theta) * 8 + 2) * np.finfo(float).eps
    assert (int(stats.iterations) - untested) % per_test == 0
    _, each = cj.FixedPoint(untested=0, per_test=1).solve(jnp.cos, z0)
    assert int(each.iterations) <= int(stats.iterations)


def test_fixed_point_sweeps_from_the_previous_count():
    """`FixedPoint.solve(..., previous=n)` on z = cos z: the sweeps before the first test come
    from each member's own n under `vmap` (`tests_ahead` tests before it, at least `untested`),
    the root is the same to round-off, the tests then stop at the same η rule (the count is
    the untested sweeps and whole tests), a count past `max_iterations` still leaves one test
    (MAX_ITERATIONS, not a silent stop), and the derivative is the implicit one."""
    z0 = jnp.full(3, 1.0)
    finder = cj.FixedPoint(untested=2, per_test=2, tests_ahead=1, max_iterations=120)
    _, alone = finder.solve(jnp.cos, z0)  # about 90 sweeps: θ = 0.67
    previous = jnp.array([0, 60, 100, 101], jnp.int32)  # below, and past, what the solve needs
    zs, stats = jax.vmap(lambda n: finder.solve(jnp.cos, z0, previous=n))(previous)
    theta = np.sin(DOTTIE)
    assert np.all(np.asarray(stats.status) == cj.Status.SUCCESS)
    assert np.max(np.abs(np.asarray(zs) - DOTTIE)) < (theta / (1 - theta) * 8 + 2) * np.finfo(float).eps
    before = np.maximum(2, np.asarray(previous) - 4)  # n − (tests_ahead + 1)·per_test
    its = np.asarray(stats.iterations)
    # below the need the tests fall on the same sweeps as without a count; past it, one test
    assert its[0] == its[1] == int(alone.iterations) < before[2]
    assert list(its[2:]) == list(before[2:] + 2)

    capped = cj.FixedPoint(untested=2, per_test=2, max_iterations=12)
    _, stats = capped.solve(jnp.cos, z0, previous=jnp.asarray(1000, jnp.int32))
    assert int(stats.status) == cj.Status.MAX_ITERATIONS and int(stats.iterations) == 12

    # d z*/d a for z = a·cos z at a = 1: cos z*/(1 + sin z*)
    dz = jax.grad(lambda a: finder.solve(lambda z: a * jnp.cos(z), z0, previous=jnp.asarray(9))[0][0])(1.0)
    assert abs(float(dz) - np.cos(DOTTIE) / (1 + np.sin(DOTTIE))) < 1e-13


def test_a_method_that_cannot_run_the_system_is_refused_before_compiling():
    with pytest.raises(ValueError, match=r"^method: a composition needs a symmetric second-order step"):
        cj.integrate(TOP, TOP_Q0, OMEGA0, dt=0.02, n_steps=3, method=cj.Composed(cj.FullStep(), cj.SUZUKI_4))
    with pytest.raises(ValueError, match=r"^reduce: the reduced march does not apply.*not a matrix-group map"):
        lamp = cj.ClebschSystem(
            lagrangian=lambda x: 0.5 * x @ x, velocity_map=lambda x, Q: x * Q, derivative_map=cj.forward_difference
        )
        cj.integrate(lamp, jnp.ones(2), jnp.ones(2), dt=0.1, n_steps=3, method=cj.ReducedStep())
    vortices = cj.models.point_vortices(jnp.array([1.0, -1.0]))
    with pytest.raises(ValueError, match=r"^scheme: 'left' is inconsistent for a degenerate Lagrangian"):
        cj.integrate(vortices, jnp.eye(2), jnp.zeros((2, 2)), dt=0.1, n_steps=3, method=cj.FullStep())


def test_method_options_belong_to_the_stepper():
    """With `method=`, an option that describes the method is refused instead of silently ignored."""
    with pytest.raises(ValueError, match=r"^order: with method= the method's options are the stepper's own"):
        cj.integrate(RIGID, EYE, XI0, dt=0.1, n_steps=3, method=cj.FullStep(), order=4)
    with pytest.raises(ValueError, match=r"^rtol: with method="):
        cj.integrate(RIGID, EYE, XI0, dt=0.1, n_steps=3, method=cj.FullStep(), rtol=1e-8)
    with pytest.raises(TypeError, match=r"^method: expected a stepper"):
        cj.integrate(RIGID, EYE, XI0, dt=0.1, n_steps=3, method="gauss")


@pytest.mark.slow  # CI runs it; vmap and grad through integrate are checked by default in tests/test_engine.py
def test_a_stepper_runs_under_vmap_and_grad():
    """A method object is static data: vmapped over initial data and differentiated through."""
    method = cj.SymmetricPair(cj.ReducedStep())

    def final_energy(omega):
        sol = cj.integrate(TOP, TOP_Q0, omega, dt=0.02, n_steps=10, method=method)
        return cj.diagnostics.energy(TOP, sol)[-1]

    omegas = jnp.stack([OMEGA0, OMEGA0 * 1.01])
    batched = jax.vmap(final_energy)(omegas)
    np.testing.assert_allclose(batched[0], final_energy(OMEGA0), rtol=1e-14)
    g = jax.grad(final_energy)(OMEGA0)
    e = jnp.eye(3)[2] * 1e-6
    fd = (final_energy(OMEGA0 + e) - final_energy(OMEGA0 - e)) / 2e-6
    np.testing.assert_allclose(g[2], fd, rtol=1e-6)
