"""Modelling errors are refused before marching, naming the culprit (`core.model_checks`).

Each test writes one mistake a user can make — a degenerate or linear Lagrangian without
`degenerate=True`, a velocity map that is not linear in ξ (Definition 1), a Lagrangian written
`l(Q, xi)`, a Lagrangian that is not a real scalar, a derivative map that leaves the
configuration manifold (after the march: `tests/test_first_step_check.py`) — and checks that `integrate` raises a `ValueError` whose message starts
with the argument at fault and says what is wrong. The march is stubbed (as in
`test_bad_input.py`), so a refusal that came too late fails the test and nothing here compiles a
march; the checks' own small programs are shared by the tests with the same maps and shapes.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import clebsch_jax as cj
from clebsch_jax.batching import batch_last as _batch_last
from clebsch_jax.batching import choose as _choose
from clebsch_jax.batching import probe as _probe
from clebsch_jax.march import arguments as _arguments
from clebsch_jax.march import integrate as _integrate

XI0 = jnp.array([1.3, 0.8, -0.4])
E3 = jnp.array([0.0, 0.0, 1.0])
INERTIA = jnp.array([2.0, 1.0, 2.0 / 3.0])


_TRACED_MARCH = _integrate._march_jit  # the real one, for the test that traces a batch


class _Marched(Exception):
    """Raised by the stubbed march: `integrate` accepted the input."""


@pytest.fixture(autouse=True)
def no_march(monkeypatch):
    def stub(*args, **kwargs):
        raise _Marched

    for march in ("_march_jit", "march_chunked"):  # traced and concrete calls
        monkeypatch.setattr(_integrate, march, stub)


def accepted(system, Q0, xi0, **kwargs):
    """True when `integrate` gets past every check to the (stubbed) march."""
    with pytest.raises(_Marched):
        cj.integrate(system, Q0, xi0, dt=0.1, n_steps=2, **kwargs)
    return True


def refused(system, Q0, xi0, match):
    with pytest.raises(ValueError, match=match) as info:
        cj.integrate(system, Q0, xi0, dt=0.1, n_steps=2)
    return str(info.value)


def _cross(xi, Q):
    return jnp.cross(xi, Q)


def _on_r3(lagrangian, velocity_map=_cross, **kwargs):
    return cj.ClebschSystem(
        lagrangian=lagrangian, velocity_map=velocity_map, derivative_map=cj.forward_difference, **kwargs
    )


# --------------------------------------------------------------------------------------------
# lagrangian


def test_a_degenerate_lagrangian_is_refused_with_its_rank_and_null_direction():
    """l = ½(ξ₁² + ξ₂²) on R³ moved by ξ×Q, at Q0 = e₁: null direction e₃, which moves Q0 (the
    isotropy is e₁), so degenerate=True is a way out and the message says so."""
    system = _on_r3(lambda xi, Q: 0.5 * (xi[0] ** 2 + xi[1] ** 2))
    message = refused(system, jnp.array([1.0, 0.0, 0.0]), XI0, r"^lagrangian: degenerate in xi at \(xi0, Q0\)")
    assert "rank 2 of 3" in message and "[0., 0., 1.]" in message and "degenerate=True" in message


def test_a_lagrangian_of_the_physical_velocity_is_accepted_with_its_isotropy_gauged(monkeypatch):
    """l = ½|ξ×Q|² does not see the component of ξ along Q (the isotropy of Q): accepted as written,
    the gauge fixed by the engine."""
    seen = {}
    original = _arguments.gauge_isotropy
    monkeypatch.setattr(_arguments, "gauge_isotropy", lambda *a, **k: seen.setdefault("gauged", original(*a, **k)))
    system = _on_r3(lambda xi, Q: 0.5 * jnp.sum(jnp.cross(xi, Q) ** 2))
    assert accepted(system, E3, jnp.array([1.3, 0.8, 0.0]))
    assert seen["gauged"].lagrangian.kernel_dim == 1


def test_a_lagrangian_degenerate_along_the_isotropy_of_q0_only_is_refused():
    """l = ½(ξ₁² + ξ₂²) at Q0 = e₃: its null direction is the isotropy of Q0, but not of the points
    Q0 moves to; the gauge would change the motion there. Refused, naming the isotropy, and
    degenerate=True (no help for a direction that moves nothing) is not suggested."""
    system = _on_r3(lambda xi, Q: 0.5 * (xi[0] ** 2 + xi[1] ** 2))
    message = refused(system, E3, XI0, r"^lagrangian: degenerate in xi at \(xi0, Q0\)")
    assert "1-dimensional isotropy" in message and "degenerate=True" not in message


@pytest.mark.parametrize(
    "lagrangian", [lambda xi: jnp.sum(xi), lambda xi, Q: jnp.dot(xi, Q) - Q[2]], ids=["l(xi)", "l(xi, Q)"]
)
def test_a_lagrangian_linear_in_xi_needs_degenerate_true(lagrangian):
    message = refused(_on_r3(lagrangian), E3, XI0, r"^lagrangian: l is linear in xi")
    assert "ClebschSystem(..., degenerate=True)" in message and "midpoint" in message
    # declared degenerate it is accepted (the midpoint principle is chosen)
    assert accepted(_on_r3(lagrangian, degenerate=True), E3, XI0)


def test_a_lagrangian_written_l_of_Q_xi_is_recognised():
    """The R³ pendulum l(ξ, q) = ½|ξ|² − g q₃ with the parameter names swapped: the engine
    calls it as l(xi, Q), so it reads ½|Q|² − g ξ₃, linear in ξ and regular in Q."""

    def swapped(Q, xi):
        return 0.5 * jnp.sum(xi**2) - 9.81 * Q[2]

    message = refused(_on_r3(swapped), E3, XI0, r"^lagrangian: it looks like it was written l\(Q, xi\)")
    assert "write it as l(xi, Q)" in message

    def pendulum(xi, Q):
        return 0.5 * jnp.sum(xi**2) - 9.81 * Q[2]

    assert accepted(_on_r3(pendulum), E3, XI0)


@pytest.mark.parametrize(
    "lagrangian, returned",
    [
        (lambda xi: (0.5 * jnp.sum(xi**2), 0.0), "returned a tuple of 2 values"),
        (lambda xi: jnp.sum(xi > 0), "returned dtype int"),
        (lambda xi: 0.5 * jnp.sum(xi**2) + 1j, "returned dtype complex128"),
    ],
    ids=["tuple", "int", "complex"],
)
def test_a_lagrangian_must_return_a_real_floating_point_scalar(lagrangian, returned):
    message = refused(_on_r3(lagrangian), E3, XI0, r"^lagrangian: must return a real floating-point scalar, returned")
    assert returned in message


def test_the_maps_must_return_real_floating_point_arrays():
    good = lambda xi: 0.5 * jnp.sum(xi**2)  # noqa: E731
    refused(
        _on_r3(good, lambda xi, Q: jnp.cross(xi, Q) * (1 + 0j)),
        E3,
        XI0,
        r"^velocity_map: must return a real floating-point array of Q's shape, returned dtype complex128",
    )
    integer = cj.ClebschSystem(
        lagrangian=good, velocity_map=_cross, derivative_map=lambda Q1, Q, dt: jnp.round(Q1 - Q).astype(int)
    )
    refused(
        integer, E3, XI0, r"^derivative_map: must return a real floating-point array of Q's shape, returned dtype int"
    )


# --------------------------------------------------------------------------------------------
# velocity_map


def test_a_velocity_map_not_linear_in_xi_is_refused():
    """The README's SE(2) body with ξ̂ replaced by (ξ∘ξ)^: quadratic in ξ."""
    system = cj.ClebschSystem(
        lagrangian=lambda x: 0.5 * x @ x, velocity_map=lambda x, Q: Q @ cj.lie.se2_hat(x * x), derivative_map=cj.cayley
    )
    message = refused(system, jnp.eye(3), XI0, r"^velocity_map: must be linear in xi \(Definition 1\)")
    assert "differs from J xi" in message


def test_an_affine_velocity_map_is_refused():
    system = _on_r3(lambda xi: 0.5 * jnp.sum(xi**2), lambda xi, Q: jnp.cross(xi, Q) + jnp.array([0.0, 0.5, 0.0]))
    message = refused(system, E3, XI0, r"^velocity_map: must be linear in xi \(Definition 1\)")
    assert "affine" in message and "L(0, Q0) != 0" in message


# --------------------------------------------------------------------------------------------
# derivative_map: checked after the march, on its first step (tests/test_first_step_check.py)


# --------------------------------------------------------------------------------------------
# silent where they should be


def _se2_body():
    return cj.ClebschSystem(
        lagrangian=lambda xi: 0.5 * 0.7 * xi[0] ** 2 + 0.5 * 1.3 * (xi[1] ** 2 + xi[2] ** 2),
        velocity_map=lambda xi, Q: Q @ cj.lie.se2_hat(xi),
        derivative_map=cj.cayley,
    )


def test_the_checks_accept_the_built_in_models():
    top_Q0 = cj.lie.so3_exp(jnp.array([0.5, 0.0, 0.0]))
    circulations = jnp.array([1.0, -1.0, 2.0])
    vortex_Q0 = jnp.array([[0.0, 1.0], [0.0, -1.0], [1.0, 0.0]])
    peakon_Q0 = jnp.array([-3.0, 0.0])
    vector_Q0, _ = cj.models.rigid_body_vector_start(INERTIA * XI0)
    cases = [
        (cj.models.rigid_body(INERTIA), top_Q0, XI0),
        (cj.models.rigid_body(INERTIA), jnp.eye(3), jnp.zeros(3)),
        (cj.models.heavy_top(jnp.array([1.0, 1.0, 0.4]), 1.5), top_Q0, jnp.array([0.3, -0.2, 6.0])),
        (cj.models.point_vortices(circulations), vortex_Q0, cj.models.vortex_velocity(circulations, vortex_Q0)),
        (cj.models.rigid_body_vector(INERTIA), vector_Q0, XI0),
        (cj.models.peakons(1.0), peakon_Q0, cj.models.peakon_velocity(peakon_Q0, jnp.array([2.0, 1.0]))),
        (cj.models.landmarks(1.0), jnp.array([[0.0, 0.0], [1.0, 0.5]]), jnp.array([[1.0, 0.0], [0.0, 1.0]])),
        # regular but ill-conditioned: eight landmarks a fifth of the kernel width apart (K(Q) has a
        # condition number above 1e10, and the march runs): not taken for a degenerate Lagrangian
        (cj.models.landmarks(1.0), jnp.stack([0.2 * jnp.arange(8.0), jnp.zeros(8)], axis=-1), jnp.ones((8, 2))),
        (_se2_body(), jnp.eye(3), XI0),
    ]
    for system, Q0, xi0 in cases:
        assert accepted(system, Q0, xi0)


def test_the_checks_are_skipped_under_vmap():
    """Traced values are unknown: a model the checks would refuse reaches the march under vmap,
    over the initial data or over a parameter its functions close over (no crash either)."""
    linear = _on_r3(lambda xi: jnp.sum(xi))
    with pytest.raises(_Marched):
        jax.vmap(lambda xi0: cj.integrate(linear, E3, xi0, dt=0.1, n_steps=2))(jnp.ones((2, 3)))

    def member(scale):
        closure = _on_r3(lambda xi: scale * jnp.sum(xi))  # Q0, xi0 concrete, l closes over a tracer
        return cj.integrate(closure, E3, XI0, dt=0.1, n_steps=2).Q

    with pytest.raises(_Marched):
        jax.vmap(member)(jnp.ones(2))
    forward = cj.models.rigid_body(INERTIA, derivative_map=cj.forward_difference)
    with pytest.raises(_Marched):
        jax.vmap(lambda Q0: cj.integrate(forward, Q0, XI0, dt=0.1, n_steps=2).Q)(np.broadcast_to(np.eye(3), (2, 3, 3)))


# --------------------------------------------------------------------------------------------
# the same checks in sweeps and batches, which march traced members: made on the first member's
# values before anything of the batch is traced or compiled


def _quadratic_on_r3():
    """A variant of the issue's cubic map: R³ moved by ξ₁ (ξ × Q), quadratic in ξ."""
    return _on_r3(lambda xi: 0.5 * jnp.sum(xi**2), lambda xi, Q: xi[0] * jnp.cross(xi, Q))


@pytest.fixture
def no_batch_trace(monkeypatch):
    """A sweep that gets past its checks of the first member would probe or trace a batch."""

    def stub(*args, **kwargs):
        raise _Marched

    monkeypatch.setattr(_probe, "member_shapes", stub)
    monkeypatch.setattr(_choose, "native_config", stub)


def test_a_velocity_map_not_linear_in_xi_is_refused_by_integrate_on_a_vector_space():
    message = refused(_quadratic_on_r3(), E3, XI0, r"^velocity_map: must be linear in xi \(Definition 1\)")
    assert "differs from J xi" in message


@pytest.mark.parametrize("backend", ["xla", "native"])
def test_a_sweep_refuses_a_velocity_map_not_linear_in_xi_before_tracing_a_batch(backend, no_batch_trace):
    """Before, the sweep ran it and reported success (the body frozen, no energy error)."""
    Q0, xi0 = np.tile(np.asarray(E3), (3, 1)), np.tile(np.asarray(XI0), (3, 1))
    with pytest.raises(
        ValueError, match=r"^sweep: member 0 \(Q0\[0\], xi0\[0\]\) is rejected by integrate's checks: velocity_map: "
    ):
        cj.sweep(_quadratic_on_r3(), None, Q0, xi0, dt=0.1, n_steps=4, backend=backend)
    # the same sweep of a linear map gets past its checks to the (stubbed) batch
    with pytest.raises(_Marched):
        cj.sweep(_on_r3(lambda xi: 0.5 * jnp.sum(xi**2)), None, Q0, xi0, dt=0.1, n_steps=4, backend=backend)


def test_a_sweep_refuses_a_degenerate_lagrangian_of_its_parameters(no_batch_trace):
    """make_system(params[0]) is checked: a rigid body whose first inertia row has a zero moment
    of inertia (the constructor's own check is skipped on the sweep's traced rows)."""
    rows = np.array([[2.0, 1.0, 0.0], [2.0, 1.0, 0.5]])
    Q0 = np.broadcast_to(np.eye(3), (2, 3, 3))
    with pytest.raises(
        ValueError,
        match=r"^sweep: member 0 \(make_system\(params\[0\]\), Q0\[0\], xi0\[0\]\) is rejected by integrate's checks: lagrangian: degenerate",
    ):
        cj.sweep(_zero_moment_body, rows, Q0, np.tile(np.asarray(XI0), (2, 1)), dt=0.1, n_steps=4, backend="xla")


def test_a_sweep_checks_the_first_member_that_can_run(no_batch_trace):
    """A member with non-finite initial data is reported in the table (INVALID_INPUT), not
    refused: the checks take the next member, and name it."""
    Q0, xi0 = np.tile(np.asarray(E3), (3, 1)), np.tile(np.asarray(XI0), (3, 1))
    xi0[0, 1] = np.nan
    with pytest.raises(ValueError, match=r"^sweep: member 1 \(Q0\[1\], xi0\[1\]\) is rejected by integrate's checks: "):
        cj.sweep(_quadratic_on_r3(), None, Q0, xi0, dt=0.1, n_steps=4, backend="xla")


def _zero_moment_body(inertia):
    return cj.ClebschSystem(
        lagrangian=lambda xi: 0.5 * jnp.sum(inertia * xi**2),
        velocity_map=lambda xi, Q: Q @ cj.lie.hat(xi),
        derivative_map=cj.cayley,
    )


def test_batch_refuses_a_velocity_map_not_linear_in_xi_before_evaluating_the_batch(monkeypatch):
    """cj.batch traces one member (integrate's traced path), then checks the first member's values
    before its program is evaluated (stubbed here: reaching it fails the test)."""
    monkeypatch.setattr(_integrate, "_march_jit", _TRACED_MARCH)  # the trace is needed

    def evaluated(*args, **kwargs):
        raise _Marched

    monkeypatch.setattr(_batch_last, "eval_closed", evaluated)
    Q0s, xi0s = np.tile(np.asarray(E3), (3, 1)), np.tile(np.asarray(XI0), (3, 1))
    march = cj.batch(lambda q, x: cj.integrate(_quadratic_on_r3(), q, x, dt=0.1, n_steps=2, throw=False).Q[-1])
    with pytest.raises(ValueError, match=r"^batch: member 0 is rejected by integrate's checks: velocity_map: "):
        march(Q0s, xi0s)
    xi0s[0, 0] = np.nan  # a member with non-finite data is reported by the batch: the next is checked
    with pytest.raises(ValueError, match=r"^batch: member 1 is rejected by integrate's checks: velocity_map: "):
        march(Q0s, xi0s)
    # under the caller's jit the values are unknown: the batch is traced and evaluated unchecked
    with pytest.raises(_Marched):
        jax.jit(march)(Q0s, xi0s)


def test_the_traced_linearity_check_tells_linear_maps_from_others():
    """`velocity_map_linear`, the per-member check a traced integrate call makes, under vmap:
    linear maps pass (also at ξ⁰ = 0, and with a large ξ⁰), a quadratic, a cubic and an affine
    map fail. The end-to-end march is the slow test below."""
    from clebsch_jax.march.carry import velocity_map_linear

    maps = {
        "linear": (_cross, True),
        "rotation": (lambda xi, Q: jnp.stack([xi[1] * Q[2] - 3.0 * xi[2] * Q[1], xi[0] * Q[0], xi[2]]), True),
        "quadratic": (lambda xi, Q: xi[0] * jnp.cross(xi, Q), False),
        "cubic": (lambda xi, Q: jnp.sum(xi**2) * jnp.cross(xi, Q), False),
        "affine": (lambda xi, Q: jnp.cross(xi, Q) + 1e-3 * Q, False),
    }
    xi0s = jnp.stack([XI0, jnp.zeros(3), 1e6 * XI0])
    for name, (velocity_map, linear) in maps.items():
        system = _on_r3(lambda xi: 0.5 * jnp.sum(xi**2), velocity_map)
        ok = jax.vmap(lambda x: velocity_map_linear(system, E3, x))(xi0s)
        assert bool(ok[0]) is linear, name
        # at rest only a constant term shows; at |ξ⁰| ~ 1e6 the affine map's offset of 1e-3 is
        # round-off next to the velocities (relative to their size, as in the check on values)
        assert bool(ok[1]) is (linear or name != "affine"), name
        assert bool(ok[2]) is (linear or name == "affine"), name


@pytest.mark.slow  # compiles a traced march under jit of vmap; the check itself is tested by default above
def test_under_jit_and_vmap_a_velocity_map_not_linear_in_xi_fails_its_member_at_step_zero(monkeypatch):
    """Under the caller's jit/vmap the check on values cannot run; its traced form
    (`march.carry.velocity_map_linear`) fails a member whose map is not linear at step 0
    (`INVALID_INPUT`) instead of reporting success with the body frozen. Per member: the map
    ξ × Q + a ξ₁ (ξ × Q) is linear for a = 0 only, and a member with a = 0 runs."""
    monkeypatch.setattr(_integrate, "_march_jit", _TRACED_MARCH)

    def run(a, xi0):
        system = _on_r3(lambda xi: 0.5 * jnp.sum(xi**2), lambda xi, Q: (1.0 + a * xi[0]) * jnp.cross(xi, Q))
        sol = cj.integrate(system, E3, xi0, dt=0.1, n_steps=2, throw=False)
        return sol.result, sol.failed_step

    a, xi0 = jnp.array([0.0, 1.0, 1e-3]), jnp.stack([XI0, XI0, 0.5 * XI0])
    result, failed_step = jax.jit(jax.vmap(run))(a, xi0)
    assert [cj.Status(int(r)) for r in result] == [cj.Status.SUCCESS] + 2 * [cj.Status.INVALID_INPUT]
    np.testing.assert_array_equal(failed_step, [-1, 0, 0])
    assert "velocity map not linear in xi" in cj.Status.INVALID_INPUT.message
