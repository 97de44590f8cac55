"""Issue 2, check 7: bad input gets a clear error naming the argument, before compiling."""

import contextlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import clebsch_jax as cj
from clebsch_jax.march import integrate as _integrate

from .systems import kinetic as _oscillator
from .systems import translation as _translation
from .systems import unit_vector as _unit_vector

SYSTEM = cj.models.rigid_body(np.array([2.0, 1.0, 2.0 / 3.0]))
Q0, XI0 = np.eye(3), np.array([0.3, 0.1, 1.0])


@pytest.fixture(autouse=True)
def no_compilation(monkeypatch):
    """Every error here must be raised before the march is traced or compiled."""

    def boom(*args, **kwargs):
        raise AssertionError("the march was compiled for invalid input")

    for name in _MARCHES:
        monkeypatch.setattr(_integrate, name, boom)


@pytest.mark.parametrize(
    "error, kwargs, match",
    [
        (ValueError, dict(dt=0.0), r"^dt: must be positive"),
        (ValueError, dict(dt=-0.1), r"^dt: must be positive"),
        (ValueError, dict(dt=float("nan")), r"^dt: contains non-finite"),
        (ValueError, dict(dt=float("inf")), r"^dt: contains non-finite"),
        (ValueError, dict(dt=np.array([0.1, 0.2])), r"^dt: expected a scalar"),
        (ValueError, dict(n_steps=0), r"^n_steps: must be at least 1"),
        (ValueError, dict(n_steps=-5), r"^n_steps: must be at least 1"),
        (ValueError, dict(Q0=np.full((3, 3), np.nan)), r"^Q0: contains non-finite"),
        (ValueError, dict(xi0=np.array([0.0, np.inf, 1.0])), r"^xi0: contains non-finite"),
        (ValueError, dict(xi0=np.zeros(4)), r"^velocity_map: calling it as velocity_map\(xi0, Q0\)|^lagrangian:"),
        (ValueError, dict(Q0=np.eye(4)), r"^velocity_map: calling it"),
        (ValueError, dict(P0=np.zeros((2, 2))), r"^P0: expected Q0's shape"),
        (ValueError, dict(scheme="middle"), r"^scheme: expected one of"),
        (ValueError, dict(t0=float("nan")), r"^t0: contains non-finite"),
        (ValueError, dict(t0=np.zeros(2)), r"^t0: expected a scalar"),
        (ValueError, dict(rtol=-1.0), r"^rtol: expected a finite number >= 0"),
        (ValueError, dict(max_newton_iterations=0), r"^max_newton_iterations: expected an int"),
        (TypeError, dict(n_steps=2.5), r"^n_steps: expected a Python int"),
        (TypeError, dict(n_steps=True), r"^n_steps: expected a Python int"),
        (TypeError, dict(Q0="identity"), r"^Q0: expected an array"),
        (TypeError, dict(xi0=np.array([1 + 1j, 0, 0])), r"^xi0: expected a real floating-point array"),
    ],
)
def test_invalid_arguments_raise_naming_the_argument(error, kwargs, match):
    """ValueError for bad values, TypeError for bad types; the message starts with the name."""
    args = dict(Q0=Q0, xi0=XI0, dt=0.1, n_steps=10)
    args.update(kwargs)
    Q, xi = args.pop("Q0"), args.pop("xi0")
    with pytest.raises(error, match=match):
        cj.integrate(SYSTEM, Q, xi, **args)


def test_maps_returning_the_wrong_shape_are_named():
    good = dict(lagrangian=lambda x: jnp.sum(x**2), velocity_map=lambda x, Q: x, derivative_map=cj.forward_difference)
    bad_l = cj.ClebschSystem(**{**good, "lagrangian": lambda x: x**2})
    with pytest.raises(ValueError, match=r"^lagrangian: must return a scalar"):
        cj.integrate(bad_l, np.zeros(3), np.ones(3), dt=0.1, n_steps=3)
    bad_L = cj.ClebschSystem(**{**good, "velocity_map": lambda x, Q: x[:2]})
    with pytest.raises(ValueError, match=r"^velocity_map: must return an array of Q's shape"):
        cj.integrate(bad_L, np.zeros(3), np.ones(3), dt=0.1, n_steps=3)
    bad_phi = cj.ClebschSystem(**{**good, "derivative_map": lambda Q1, Q, dt: jnp.sum(Q1 - Q) / dt})
    with pytest.raises(ValueError, match=r"^derivative_map: must return an array of Q's shape"):
        cj.integrate(bad_phi, np.zeros(3), np.ones(3), dt=0.1, n_steps=3)


def test_system_construction_errors():
    with pytest.raises(TypeError, match=r"^lagrangian: expected l\(xi\) or l\(xi, Q\)"):
        cj.ClebschSystem(
            lagrangian=lambda a, b, c: 0.0, velocity_map=lambda x, Q: x, derivative_map=cj.forward_difference
        )
    with pytest.raises(TypeError, match=r"^velocity_map: expected a callable"):
        cj.ClebschSystem(lagrangian=lambda x: 0.0, velocity_map=3, derivative_map=cj.forward_difference)
    with pytest.raises(TypeError, match=r"^system: expected a clebsch_jax.ClebschSystem"):
        cj.integrate(object(), Q0, XI0, dt=0.1, n_steps=3)
    with pytest.raises(ValueError, match=r"^inertia: expected the three principal moments"):
        cj.models.rigid_body(np.ones(4))


_dims = st.integers(min_value=1, max_value=5)


@settings(max_examples=40, deadline=None)
@given(q_shape=st.lists(_dims, min_size=1, max_size=3), xi_shape=st.lists(_dims, min_size=1, max_size=3))
def test_shape_mismatch_between_Q0_and_xi0_is_caught(q_shape, xi_shape):
    """For the vector-space system L_ξQ = ξ, any Q0/ξ0 shape mismatch is an error before
    compilation; matching shapes are accepted (they reach the march, which is stubbed out)."""
    system = cj.ClebschSystem(
        lagrangian=lambda x: 0.5 * jnp.sum(x**2), velocity_map=lambda x, Q: x, derivative_map=cj.forward_difference
    )
    Q, xi = np.zeros(q_shape), np.ones(xi_shape)
    if tuple(q_shape) == tuple(xi_shape):
        with pytest.raises(AssertionError, match="compiled"):
            cj.integrate(system, Q, xi, dt=0.1, n_steps=2)
    else:
        with pytest.raises(ValueError, match=r"^velocity_map: must return an array of Q's shape"):
            cj.integrate(system, Q, xi, dt=0.1, n_steps=2)


@settings(max_examples=40, deadline=None)
@given(dt=st.one_of(st.floats(max_value=0.0), st.just(float("nan")), st.just(float("inf")), st.just(-float("inf"))))
def test_any_nonpositive_or_nonfinite_dt_is_rejected(dt):
    with pytest.raises(ValueError, match=r"^dt: "):
        cj.integrate(SYSTEM, Q0, XI0, dt=dt, n_steps=3)


# --------------------------------------------------------------------------------------------
# Issue 8: configurations off the manifold, meaningless model parameters, random valid and
# invalid input (hypothesis).

_MARCHES = {name: getattr(_integrate, name) for name in ("_march_jit", "march_chunked")}
ROTATION_TOL = cj.models._rigid_body.ROTATION_TOLERANCE  # √ε ≈ 1.5e-8


@contextlib.contextmanager
def compiling():
    """The real marches back for a test of *valid* input, which must run."""
    stubs = {name: getattr(_integrate, name) for name in _MARCHES}
    for name, fn in _MARCHES.items():
        setattr(_integrate, name, fn)
    try:
        yield
    finally:
        for name, fn in stubs.items():
            setattr(_integrate, name, fn)


def reaches_the_march(system, Q, xi, **kwargs):
    """True when `integrate` accepts the input: it gets as far as the (stubbed) march."""
    with pytest.raises(AssertionError, match="compiled"):
        cj.integrate(system, Q, xi, dt=0.1, n_steps=2, **kwargs)
    return True


def rotation(angles):
    return np.asarray(cj.lie.so3_exp(jnp.asarray(angles, float)))


TOP = cj.models.heavy_top(np.array([1.0, 1.2, 0.5]), 1.7, (0.0, 0.6, 0.8))
R = rotation([0.3, -0.2, 0.5])


@pytest.mark.parametrize("system", [SYSTEM, TOP], ids=["rigid_body", "heavy_top"])
@pytest.mark.parametrize(
    "Q, match",
    [
        (R @ np.diag([1.0, 1.0, -1.0]), r"^Q0: det Q = -1: .*reflection"),  # orthogonal, det −1
        (-np.eye(3), r"^Q0: det Q = -1: .*reflection"),
        (1.01 * R, r"^Q0: not a rotation matrix: max\|Q\^T Q - I\| = 2\.01e-02"),
        (R + 1e-6 * np.triu(np.ones((3, 3))), r"^Q0: not a rotation matrix"),
        (np.zeros((3, 3)), r"^Q0: not a rotation matrix"),
        (np.array([[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), r"^Q0: not a rotation matrix"),  # a shear
    ],
)
def test_SO3_models_reject_a_Q0_that_is_not_a_rotation(system, Q, match):
    with pytest.raises(ValueError, match=match):
        cj.integrate(system, Q, XI0, dt=0.1, n_steps=3)


def test_the_rotation_check_tolerates_round_off_and_is_skipped_when_Q0_is_traced():
    # a rotation off by 1e-12 (a long run's last node, say) is a rotation; 1e-7 is not
    assert reaches_the_march(SYSTEM, R + 1e-12 * np.ones((3, 3)), XI0)
    assert reaches_the_march(TOP, R @ rotation([1e-3, 0.0, 0.0]), XI0)
    with pytest.raises(ValueError, match=r"^Q0: not a rotation"):
        cj.integrate(SYSTEM, R + 1e-7 * np.eye(3), XI0, dt=0.1, n_steps=3)
    # under jit the values of Q0 are unknown: no check, the (stubbed) march is reached
    with pytest.raises(AssertionError, match="compiled"):
        jax.jit(lambda Q: cj.integrate(SYSTEM, Q, XI0, dt=0.1, n_steps=3).Q)(2.0 * np.eye(3))


def _vector_system(**kwargs):
    return cj.ClebschSystem(
        lagrangian=_oscillator, velocity_map=_translation, derivative_map=cj.forward_difference, **kwargs
    )


def test_a_user_configuration_check_is_data_of_the_system():
    """`check_Q` on a user system: its sentence becomes the ValueError naming Q0; it is kept by
    the pytree round trip (jit, vmap) and validated itself."""
    unit = _vector_system(check_Q=_unit_vector)
    with pytest.raises(ValueError, match=r"^Q0: not a unit vector \(\|Q\| = 2\)"):
        cj.integrate(unit, np.array([2.0, 0.0]), np.ones(2), dt=0.1, n_steps=2)
    # (a unit Q0 passes; that translations then leave the circle is found on the march's first
    # step: tests/test_first_step_check.py)
    leaves, treedef = jax.tree_util.tree_flatten(unit)
    assert jax.tree_util.tree_unflatten(treedef, leaves).check_Q is _unit_vector
    assert jax.tree_util.tree_unflatten(*reversed(jax.tree_util.tree_flatten(_vector_system()))).check_Q is None
    with pytest.raises(TypeError, match=r"^check_Q: expected None or a callable"):
        _vector_system(check_Q="unit")
    with pytest.raises(TypeError, match=r"^check_Q: must return None or a string"):
        cj.integrate(_vector_system(check_Q=lambda Q: False), np.zeros(2), np.ones(2), dt=0.1, n_steps=2)


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: cj.models.rigid_body([2.0, 0.0, 1.0]), r"^inertia: the principal moments must be finite and positive"),
        (
            lambda: cj.models.rigid_body([2.0, 1.0, -0.5]),
            r"^inertia: the principal moments must be finite and positive",
        ),
        (
            lambda: cj.models.rigid_body([np.nan, 1.0, 1.0]),
            r"^inertia: the principal moments must be finite and positive",
        ),
        (
            lambda: cj.models.rigid_body([np.inf, 1.0, 1.0]),
            r"^inertia: the principal moments must be finite and positive",
        ),
        (
            lambda: cj.models.rigid_body(np.array([2.0, 1.0, 1.0]) + 0.5j),
            r"^inertia: the principal moments must be real",
        ),
        (lambda: cj.models.heavy_top([1.0, -1.0, 1.0], 1.0), r"^inertia: the principal moments must be finite"),
        (lambda: cj.models.heavy_top([1.0, 1.0, 1.0], np.nan), r"^mass_gravity_length: must be finite"),
        (lambda: cj.models.heavy_top([1.0, 1.0, 1.0], [1.0, 2.0]), r"^mass_gravity_length: expected a scalar"),
        (
            lambda: cj.models.heavy_top([1.0, 1.0, 1.0], 1.0, (0.0, 0.0, 0.0)),
            r"^center_of_mass: must be a finite, nonzero",
        ),
        (lambda: cj.models.heavy_top([1.0, 1.0, 1.0], 1.0, (0.0, np.inf, 1.0)), r"^center_of_mass: must be a finite"),
        (lambda: cj.models.point_vortices([1.0, 0.0, -1.0]), r"^circulations: must be nonzero: vortex 1"),
        (lambda: cj.models.point_vortices([1.0, np.nan]), r"^circulations: must be finite"),
        (lambda: cj.models.point_vortices(np.ones((2, 2))), r"^circulations: expected a 1-D array"),
        (lambda: cj.models.peakons(0.0), r"^width: must be finite and positive"),
        (lambda: cj.models.peakons(-1.0), r"^width: must be finite and positive"),
        (lambda: cj.models.landmarks(np.inf), r"^width: must be finite and positive"),
        (lambda: cj.models.landmarks(np.nan), r"^width: must be finite and positive"),
    ],
)
def test_meaningless_model_parameters_raise_naming_the_parameter(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_parameter_checks_are_skipped_when_traced_and_meaningful_signs_are_kept():
    """Under jit/vmap the values are unknown: the constructors build the system without looking
    (no concretization error); negative circulations and mgl are meaningful and accepted."""
    assert cj.models.point_vortices([1.0, -2.5]).degenerate
    cj.models.heavy_top([1.0, 1.0, 1.0], -1.5)
    cj.models.heavy_top([1.0, 1.0, 1.0], 0.0)
    xi, Q = jnp.ones(3), jnp.eye(3)
    bad_inertias = jnp.array([[1.0, 2.0, 3.0], [-1.0, 0.0, np.nan]])
    for make in (cj.models.rigid_body, lambda I: cj.models.heavy_top(I, 1.0)):  # traced, not compiled
        assert jax.eval_shape(jax.vmap(lambda I: make(I).l(xi, Q)), bad_inertias).shape == (2,)
    assert jax.eval_shape(
        jax.vmap(lambda g: cj.models.point_vortices(g).l(jnp.ones((3, 2)), jnp.eye(3, 2))), jnp.zeros((2, 3))
    ).shape == (2,)
    assert (
        jax.eval_shape(jax.jit(lambda w: cj.models.peakons(w).l(jnp.ones(2), jnp.array([0.0, 1.0]))), -1.0).shape == ()
    )


# ---- hypothesis: random valid and invalid input

_finite = st.floats(min_value=-3.0, max_value=3.0, allow_nan=False, allow_infinity=False)
_nonfinite = st.sampled_from([np.nan, np.inf, -np.inf])
_shapes = st.lists(st.integers(min_value=1, max_value=4), min_size=1, max_size=3).map(tuple)


def _array(shape):
    return st.lists(_finite, min_size=int(np.prod(shape)), max_size=int(np.prod(shape))).map(
        lambda v: np.array(v).reshape(shape)
    )


def _spring(xi, Q):
    return 0.5 * jnp.sum(xi**2) - 0.5 * jnp.sum(Q**2)


SPRING = cj.ClebschSystem(lagrangian=_spring, velocity_map=_translation, derivative_map=cj.forward_difference)


@settings(max_examples=30, deadline=None)
@given(data=st.data(), shape=_shapes, which=st.sampled_from(["Q0", "xi0", "P0"]))
def test_a_nonfinite_entry_anywhere_is_rejected_naming_the_argument(data, shape, which):
    """A random finite input of a random shape with one NaN/inf at a random position."""
    args = {name: data.draw(_array(shape)) for name in ("Q0", "xi0", "P0")}
    bad = args[which]
    bad[np.unravel_index(data.draw(st.integers(0, bad.size - 1)), shape)] = data.draw(_nonfinite)
    with pytest.raises(ValueError, match=rf"^{which}: contains non-finite"):
        cj.integrate(SPRING, args["Q0"], args["xi0"], P0=args["P0"], dt=0.1, n_steps=2)


def _random_rotation(entries):
    """A rotation from 9 numbers by QR (Q's columns fixed by the sign of R's diagonal, det +1)."""
    q, r = np.linalg.qr(np.reshape(entries, (3, 3)))
    q = q * np.sign(np.where(np.diag(r) == 0, 1.0, np.diag(r)))
    return q * np.array([1.0, 1.0, np.sign(np.linalg.det(q))])


_rotations = (
    st.lists(st.floats(-1.0, 1.0), min_size=9, max_size=9)
    .filter(lambda v: np.linalg.cond(np.reshape(v, (3, 3))) < 1e6)
    .map(_random_rotation)
)


@settings(max_examples=30, deadline=None)
@given(Q=_rotations, kind=st.sampled_from(["reflect", "scale", "perturb"]), data=st.data())
def test_random_non_rotations_are_rejected(Q, kind, data):
    assert cj.models._rigid_body.check_rotation(Q) is None  # the QR rotation itself is accepted
    if kind == "reflect":  # orthogonal with det −1: one column flipped
        j = data.draw(st.integers(0, 2))
        bad, match = Q * np.where(np.arange(3) == j, -1.0, 1.0), r"^Q0: det Q = -1"
    elif kind == "scale":
        s = data.draw(st.floats(0.0, 2.0).filter(lambda s: abs(s - 1.0) > 1e-6))
        bad, match = s * Q, r"^Q0: not a rotation matrix"
    else:  # one entry moved by at least 1e-6 ≫ √ε
        i, j = data.draw(st.integers(0, 2)), data.draw(st.integers(0, 2))
        d = data.draw(st.floats(1e-6, 1.0)) * data.draw(st.sampled_from([-1.0, 1.0]))
        bad, match = Q + d * np.outer(np.eye(3)[i], np.eye(3)[j]), r"^Q0: not a rotation matrix"
    with pytest.raises(ValueError, match=match):
        cj.integrate(data.draw(st.sampled_from([SYSTEM, TOP])), bad, XI0, dt=0.1, n_steps=3)


_bad_value = st.one_of(st.floats(max_value=0.0), _nonfinite)


@settings(max_examples=30, deadline=None)
@given(data=st.data(), model=st.sampled_from(["rigid_body", "heavy_top", "point_vortices", "peakons", "landmarks"]))
def test_random_meaningless_parameters_are_rejected(data, model):
    """One entry of otherwise valid parameters made non-positive (zero for circulations, whose
    sign is free) or non-finite, at a random position."""
    if model in ("rigid_body", "heavy_top"):
        inertia = np.array(data.draw(st.lists(st.floats(0.1, 10.0), min_size=3, max_size=3)))
        inertia[data.draw(st.integers(0, 2))] = data.draw(_bad_value)
        with pytest.raises(ValueError, match=r"^inertia: "):
            cj.models.rigid_body(inertia) if model == "rigid_body" else cj.models.heavy_top(inertia, 1.0)
    elif model == "point_vortices":
        n = data.draw(st.integers(1, 6))
        gamma = np.array(data.draw(st.lists(st.floats(0.1, 5.0), min_size=n, max_size=n)))
        gamma *= data.draw(st.sampled_from([-1.0, 1.0]))
        gamma[data.draw(st.integers(0, n - 1))] = data.draw(st.one_of(st.just(0.0), st.just(-0.0), _nonfinite))
        with pytest.raises(ValueError, match=r"^circulations: "):
            cj.models.point_vortices(gamma)
    else:
        with pytest.raises(ValueError, match=r"^width: "):
            getattr(cj.models, model)(data.draw(_bad_value))


@settings(max_examples=12, deadline=None)
@given(
    Q=_rotations,
    inertia=st.lists(st.floats(0.2, 5.0), min_size=3, max_size=3),
    xi=st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3),
)
def test_random_valid_rigid_bodies_are_accepted_and_run(Q, inertia, xi):
    """Random rotations (QR), positive inertias and velocities: a finite, successful solution
    that stays on SO(3) (3 steps; one compiled march for every example)."""
    with compiling():
        sol = cj.integrate(cj.models.rigid_body(np.array(inertia)), Q, np.array(xi), dt=0.1, n_steps=3)
    assert int(sol.result) == cj.Status.SUCCESS and bool(np.all(sol.valid))
    assert np.all(np.isfinite(sol.Q)) and np.all(np.isfinite(sol.xi))
    assert float(jnp.max(cj.diagnostics.orthogonality_error(sol.Q))) < 1e-13


@settings(max_examples=12, deadline=None)
@given(data=st.data(), shape=st.sampled_from([(2,), (2, 3)]))
def test_random_valid_vector_space_input_is_accepted_and_runs(data, shape):
    """Random finite Q0, ξ0 (and sometimes P0) for a harmonic oscillator on R^shape: accepted
    and marched to a finite solution by the default (the midpoint principle, which for this
    quadratic Lagrangian is the implicit midpoint rule), with its energy ½(p² + q²) conserved
    exactly (two shapes: at most two compiled marches)."""
    Q, xi = data.draw(_array(shape)), data.draw(_array(shape))
    P = data.draw(st.one_of(st.none(), _array(shape)))
    with compiling():
        sol = cj.integrate(SPRING, Q, xi, P0=P, dt=0.1, n_steps=3)
    assert int(sol.result) == cj.Status.SUCCESS
    assert all(np.all(np.isfinite(a)) for a in (sol.Q, sol.p, sol.xi, sol.momentum))
    # the implicit midpoint rule keeps the quadratic H = ½(p² + q²) exactly
    assert sol.scheme == "midpoint"
    p, q = np.asarray(sol.p), np.asarray(sol.Q)
    H = 0.5 * np.sum((p**2 + q**2).reshape(4, -1), axis=1)
    np.testing.assert_allclose(H, H[0], rtol=1e-13, atol=1e-13)


def test_the_vectorised_rotation_check_agrees_with_the_single_one():
    """`check_rotations` (used by `sweep` for a whole stack) names the first row that
    `check_rotation` rejects, with the same sentence; a stack of rotations passes."""
    from clebsch_jax.models._rigid_body import check_rotation, check_rotations

    rng = np.random.default_rng(3)
    good = np.stack([_random_rotation(rng.uniform(-1, 1, 9)) for _ in range(50)])
    assert check_rotations(good) is None and check_rotation.batched is check_rotations
    for j, bad in ((7, 1.001 * good[7]), (0, good[0] @ np.diag([1.0, -1.0, 1.0])), (49, np.full((3, 3), np.nan))):
        stack = good.copy()
        stack[j] = bad
        if j + 1 < len(stack):
            stack[j + 1] = 2.0 * np.eye(3)  # a later, different fault: the first one is named
        found = check_rotations(stack)
        assert found is not None and found[0] == j, (j, found)
        assert found[1] == check_rotation(stack[j])


def test_python_numbers_kept_on_the_device_are_their_own_values():
    """`float_array` keeps the device arrays of Python numbers it converted (dt and t0 repeat
    from call to call): each value gets its own, -0.0 is not 0.0, an int is its float, and a
    bad value is still refused after good ones (tests/test_native_integrate.py marches with
    several)."""
    from clebsch_jax.core.validation import float_array, positive_scalar

    assert np.signbit(float_array(-0.0, "t0")) and not np.signbit(float_array(0.0, "t0"))
    for x in (0.01, 0.02, 3, 0.01):
        got = float_array(x, "t0")
        assert isinstance(got, jax.Array) and got.dtype == jnp.float64 and float(got) == float(x)
    system = cj.ClebschSystem(lagrangian=_oscillator, velocity_map=_translation, derivative_map=cj.forward_difference)
    run = lambda **kw: cj.integrate(system, jnp.array([1.0, 0.0]), jnp.array([0.0, 1.0]), n_steps=3, **kw)
    with pytest.raises(ValueError, match="dt: must be positive"):
        positive_scalar(-0.1, "dt")
    with pytest.raises(ValueError, match="t0: contains non-finite"):
        run(dt=0.1, t0=float("nan"))


def test_a_python_number_first_converted_inside_a_trace_is_not_kept():
    """A Python number first met inside a trace (a caller's jax.jit closing over dt) becomes a
    tracer there; kept, it would leak into later calls, which would take it for traced input
    and skip the checks made on values (the first-step check, the guidance warnings)."""
    from clebsch_jax.core.validation import float_array, is_traced

    value = 0.012345678901234  # a number no other test converts
    jax.jit(lambda x: x * float_array(value, "dt"))(1.0)
    assert not is_traced(float_array(value, "dt"))
