"""A derivative map whose steps leave the configuration manifold is caught on the first step the
march made (`core.model_checks.check_first_step`): whether a step stays on M depends on the
principle as well as on the derivative map (the forward difference leaves SO(3) with the left
principle, while with the midpoint principle its step is a Cayley transform), so the check looks
at what actually ran. Runs are two steps long, on systems shared by the tests."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import clebsch_jax as cj
from clebsch_jax.batching import batch_last as _batch_last
from clebsch_jax.batching import choose as _choose
from clebsch_jax.batching import probe as _probe
from clebsch_jax.core.manifold_checks import traced_first_step_check

from .systems import kinetic, translation, unit_vector

INERTIA = jnp.array([2.0, 1.0, 2.0 / 3.0])
XI0 = jnp.array([1.3, 0.8, -0.4])
FORWARD = cj.models.rigid_body(INERTIA, derivative_map=cj.forward_difference)  # checks Q is a rotation


def _se3_hat(x):
    return jnp.block([[cj.lie.hat(x[:3]), x[3:, None]], [jnp.zeros((1, 4))]])


def _se3_body(xi, Q):
    return Q @ _se3_hat(xi)


def _se3_kinetic(xi):
    return 0.5 * jnp.sum(jnp.array([1.0, 2.0, 3.0, 1.0, 1.0, 1.0]) * xi**2)


SE3 = cj.ClebschSystem(lagrangian=_se3_kinetic, velocity_map=_se3_body, derivative_map=cj.forward_difference)
SE3_Q0 = jnp.eye(4).at[:3, 3].set(jnp.array([5.0, -2.0, 1.0]))  # far from the identity: the step is what counts
SE3_XI0 = jnp.array([0.3, 0.2, -0.5, 1.0, 0.0, 0.2])


@pytest.mark.parametrize("scheme", ["left", "right"])
def test_the_forward_difference_with_a_one_sided_principle_leaves_the_rotations(scheme):
    """Left: Q1 = Q0 (I + h ξ̂), with Q1ᵀQ1 = I + h² ξ̂ᵀξ̂: refused, naming the derivative map,
    what check_Q says, and the two ways out."""
    with pytest.raises(
        ValueError,
        match=r"^derivative_map: one step of forward difference from Q0 "
        rf"\({scheme} principle\) leaves the configuration manifold: "
        r"not a rotation matrix",
    ) as info:
        cj.integrate(FORWARD, jnp.eye(3), XI0, dt=0.1, n_steps=2, scheme=scheme)
    assert "clebsch_jax.cayley" in str(info.value) and 'scheme="midpoint"' in str(info.value)


def test_the_forward_difference_with_the_midpoint_principle_stays_on_the_rotations():
    """The default for this system is the midpoint principle: (Q1 − Q0)/h = ½(Q0 + Q1) ξ̂ makes
    Q1 = Q0 cay(h ξ̂), a rotation. Accepted, and the rotations are kept to round-off."""
    sol = cj.integrate(FORWARD, jnp.eye(3), XI0, dt=0.1, n_steps=2)
    assert sol.scheme == "midpoint"
    Q = np.asarray(sol.Q)
    assert np.max(np.abs(np.einsum("nji,njk->nik", Q, Q) - np.eye(3))) < 1e-14


def test_a_body_at_rest_is_not_blamed():
    """At rest no step moves Q, so none leaves SO(3): the run is exact and accepted."""
    sol = cj.integrate(FORWARD, jnp.eye(3), jnp.zeros(3), dt=0.1, n_steps=2, scheme="left")
    np.testing.assert_array_equal(np.asarray(sol.Q[-1]), np.eye(3))


@pytest.mark.slow  # CI runs it; two SE(3) marches compiled for one warning
def test_se3_without_a_check_warns_with_the_left_principle_and_not_with_the_midpoint():
    """SE(3) written by hand, with no check_Q: the matrix group is read off the velocity map
    (right multiplication by a closed algebra). The left principle's step leaves it (a warning:
    without check_Q the configurations may be any 4×4 matrices); the midpoint's does not."""
    with pytest.warns(
        UserWarning,
        match=r"^derivative_map: one step of forward difference from Q0 \(left "
        r"principle\) leaves the configuration manifold on which velocity_map "
        r"acts, a matrix group",
    ) as record:
        sol = cj.integrate(SE3, SE3_Q0, SE3_XI0, dt=0.1, n_steps=2, scheme="left")
    # the warning points at the caller's line (other warnings can land in the record too: a
    # ResourceWarning for a file an earlier test left open, when the collector closes it here)
    ours = [w for w in record if str(w.message).startswith("derivative_map:")]
    assert len(ours) == 1 and ours[0].filename == __file__
    R = np.asarray(sol.Q[1, :3, :3])
    assert np.max(np.abs(R.T @ R - np.eye(3))) > 1e-4  # it did leave: the warning is not a false alarm
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sol = cj.integrate(SE3, SE3_Q0, SE3_XI0, dt=0.1, n_steps=2)
    R = np.asarray(sol.Q[-1, :3, :3])
    assert np.max(np.abs(R.T @ R - np.eye(3))) < 1e-14


def test_a_rotation_that_only_just_passes_is_not_blamed_on_a_correct_step():
    """Q0 with |Q0ᵀQ0 − I| = 1.4e-8, just inside the rotation check's 1.5e-8: a Cayley step
    keeps that defect (it may even grow past the tolerance by round-off), and the check measures
    the step itself, Q0⁻¹Q1, so the run is accepted."""
    Q0 = np.asarray(cj.lie.so3_exp(jnp.array([0.3, 0.1, 0.2]))) * (1 + 0.7e-8)
    assert 1.3e-8 < np.max(np.abs(Q0.T @ Q0 - np.eye(3))) < 1.5e-8
    sol = cj.integrate(cj.models.rigid_body(INERTIA), Q0, XI0, dt=0.1, n_steps=2, scheme="left")
    assert int(sol.result) == cj.Status.SUCCESS


def test_a_velocity_map_not_tangent_to_the_manifold_is_refused_after_its_first_step():
    """Translations of the plane are not tangent to the unit circle that check_Q declares: every
    principle leaves it, and the first step's Q1 fails check_Q (no matrix group here)."""
    circle = cj.ClebschSystem(
        lagrangian=kinetic, velocity_map=translation, derivative_map=cj.forward_difference, check_Q=unit_vector
    )
    with pytest.raises(
        ValueError,
        match=r"^derivative_map: one step of forward difference from Q0 \(midpoint "
        r"principle\) leaves the configuration manifold: not a unit vector",
    ):
        cj.integrate(circle, np.array([0.6, 0.8]), np.ones(2), dt=0.1, n_steps=2)


# --------------------------------------------------------------------------------------------
# sweeps and batches march traced members: they make this check on their first member, one
# step marched alone, before any batch is traced or compiled. A variant of the example
# (the rigid body): the heavy top with the forward difference and the left principle.

TOP = cj.models.heavy_top(jnp.array([1.0, 1.0, 0.4]), 1.5, derivative_map=cj.forward_difference)
TOP_XI0 = np.array([0.3, -0.2, 6.0])
LEAVES = r"derivative_map: one step of forward difference from Q0 \(left principle\) leaves the configuration manifold"


class _Reached(Exception):
    """The batch was about to be traced or evaluated: the check came too late."""


def _reached(*args, **kwargs):
    raise _Reached


def test_integrate_refuses_the_forward_difference_on_the_heavy_top_with_the_left_principle():
    with pytest.raises(ValueError, match=rf"^{LEAVES}: not a rotation matrix"):
        cj.integrate(TOP, np.eye(3), TOP_XI0, dt=0.05, n_steps=2, scheme="left")


@pytest.mark.parametrize("backend", ["xla", "native"])
def test_a_sweep_refuses_it_before_tracing_a_batch(backend, monkeypatch):
    """Before, a sweep reported success with |QᵀQ − I| of order one. The native backend does not
    apply to this program (backend="native" would be refused for it): the check comes first."""
    monkeypatch.setattr(_probe, "member_shapes", _reached)
    monkeypatch.setattr(_choose, "native_config", _reached)
    Q0, xi0 = np.broadcast_to(np.eye(3), (2, 3, 3)), np.tile(TOP_XI0, (2, 1))
    with pytest.raises(
        ValueError, match=rf"^sweep: member 0 \(Q0\[0\], xi0\[0\]\) is rejected by integrate's checks: {LEAVES}"
    ):
        cj.sweep(TOP, None, Q0, xi0, dt=0.05, n_steps=4, scheme="left", backend=backend)
    with pytest.raises(_Reached):  # the default (midpoint) principle keeps Q on SO(3): accepted
        cj.sweep(TOP, None, Q0, xi0, dt=0.05, n_steps=4, backend=backend)


def test_batch_refuses_it_before_evaluating_the_batch(monkeypatch):
    monkeypatch.setattr(_batch_last, "eval_closed", _reached)
    march = cj.batch(lambda x: cj.integrate(TOP, jnp.eye(3), x, dt=0.05, n_steps=2, scheme="left", throw=False).Q[-1])
    with pytest.raises(ValueError, match=rf"^batch: member 0 is rejected by integrate's checks: {LEAVES}"):
        march(np.tile(TOP_XI0, (2, 1)))


# --------------------------------------------------------------------------------------------
# Under the caller's own jax.jit / jax.vmap of integrate the values are traced: the same test of
# the first step runs inside the program (`traced_first_step_check`), and a member whose step
# left the manifold reports Status.OFF_MANIFOLD at step 0 (NaN after it); the others run on.


def unit_circle(Q):
    """`unit_vector` with a traced form, which the program can run."""
    return unit_vector(np.asarray(Q))


unit_circle.traced = lambda Q: jnp.abs(jnp.sqrt(jnp.sum(Q**2)) - 1.0) <= 1e-12
CIRCLE = cj.ClebschSystem(
    lagrangian=kinetic, velocity_map=translation, derivative_map=cj.forward_difference, check_Q=unit_circle
)
NUMPY_CIRCLE = cj.ClebschSystem(
    lagrangian=kinetic, velocity_map=translation, derivative_map=cj.forward_difference, check_Q=unit_vector
)


def _statuses(sol):
    return [cj.Status(int(r)) for r in np.asarray(sol.result)]


def test_under_vmap_the_member_whose_first_step_leaves_the_circle_reports_it():
    """check_Q with a traced form (`check_Q.traced`): the circle's translations leave it; one
    member moving and one at rest give [OFF_MANIFOLD, SUCCESS], the first NaN after step 0."""
    run = jax.vmap(lambda q, x: cj.integrate(CIRCLE, q, x, dt=0.1, n_steps=2, throw=False))
    sol = run(np.array([[0.0, 1.0], [0.6, 0.8]]), np.array([[1.0, -0.5], [0.0, 0.0]]))
    assert _statuses(sol) == [cj.Status.OFF_MANIFOLD, cj.Status.SUCCESS]
    assert np.asarray(sol.failed_step).tolist() == [0, -1]
    Q = np.asarray(sol.Q)
    assert np.all(np.isnan(Q[0, 1:])) and np.all(Q[1] == [0.6, 0.8])
    with pytest.raises(cj.IntegrationError, match=r"member 0, step 0 of 2 .*left the configuration manifold.*") as info:
        sol.raise_if_failed()  # what throw=True raises: the status and the ways out
    assert info.value.status == cj.Status.OFF_MANIFOLD and 'scheme="midpoint"' in str(info.value)


@pytest.mark.slow  # compiles the heavy top's traced march; the circle's above is the default test of the traced check
def test_under_vmap_the_member_whose_first_step_leaves_the_rotations_reports_it():
    """The heavy top with the forward difference and the left principle, one member spinning and
    one at rest: [OFF_MANIFOLD, SUCCESS], the first member NaN after step 0 and the second exact."""
    run = jax.vmap(lambda x: cj.integrate(TOP, jnp.eye(3), x, dt=0.05, n_steps=2, scheme="left", throw=False))
    sol = run(np.stack([TOP_XI0, np.zeros(3)]))
    assert _statuses(sol) == [cj.Status.OFF_MANIFOLD, cj.Status.SUCCESS]
    assert np.asarray(sol.failed_step).tolist() == [0, -1]
    Q = np.asarray(sol.Q)
    assert np.all(np.isfinite(Q[0, 0])) and np.all(np.isnan(Q[0, 1:]))
    np.testing.assert_array_equal(Q[1], np.broadcast_to(np.eye(3), (3, 3, 3)))


@pytest.mark.slow  # compiles the heavy top's traced midpoint march; the left one is checked by default above
def test_under_vmap_the_midpoint_step_and_a_rotation_that_only_just_passes_are_not_blamed():
    """The midpoint principle keeps SO(3) (a Cayley step): not blamed, from the identity nor from
    a Q0 just inside the rotation check's tolerance, whose own defect the step keeps (the test
    measures Q0⁻¹Q1, the step's, not Q1's)."""
    Q0 = np.asarray(cj.lie.so3_exp(jnp.array([0.3, 0.1, 0.2]))) * (1 + 0.7e-8)
    assert 1.3e-8 < np.max(np.abs(Q0.T @ Q0 - np.eye(3))) < 1.5e-8
    run = jax.vmap(lambda q: cj.integrate(TOP, q, TOP_XI0, dt=0.05, n_steps=2, throw=False))
    sol = run(np.stack([np.eye(3), Q0]))
    assert sol.scheme == "midpoint" and _statuses(sol) == [cj.Status.SUCCESS] * 2


@pytest.mark.slow  # compiles the traced march with its error callback; reported under vmap by default above
def test_under_jit_a_first_step_off_the_circle_is_raised():
    """With throw=True the program raises naming the status; a member at rest runs."""
    run = jax.jit(lambda q, x: cj.integrate(CIRCLE, q, x, dt=0.1, n_steps=2).Q)
    with pytest.raises(jax.errors.JaxRuntimeError, match=r"step 0 of 2.*left the configuration.*OFF_MANIFOLD"):
        jax.block_until_ready(run(np.array([0.0, 1.0]), np.array([1.0, -0.5])))
    np.testing.assert_array_equal(run(np.array([0.0, 1.0]), np.zeros(2)), np.tile([0.0, 1.0], (3, 1)))


@pytest.mark.slow  # compiles another traced march; test_the_traced_check_is_added_only_where_a_step_can_leave checks by default that none is added
def test_a_check_q_without_a_traced_form_is_not_run_in_the_program():
    """A check_Q written with NumPy on concrete values cannot run in the program: the traced
    first step is not checked (documented), and the run neither crashes nor fails, where the same
    system with a traced form of the check is reported (`test_under_jit_a_first_step_off_the_circle_is_raised`)."""
    run = jax.vmap(lambda q, x: cj.integrate(NUMPY_CIRCLE, q, x, dt=0.1, n_steps=2, throw=False))
    sol = run(np.array([[0.6, 0.8], [0.0, 1.0]]), np.array([[1.0, 1.0], [0.0, 0.0]]))
    assert _statuses(sol) == [cj.Status.SUCCESS] * 2
    assert abs(np.linalg.norm(np.asarray(sol.Q[0, 1])) - 1) > 1e-3  # it did leave the circle, unchecked


def test_the_traced_check_is_added_only_where_a_step_can_leave():
    """Decided from the maps and shapes at trace time: nothing for a derivative map of Definition
    25's form on the velocity map's group (the built-in models' defaults), for a system with no
    check_Q (SE(3) by hand: a concrete run only warns) or one whose check_Q has no traced form;
    a test for the forward difference on SO(3) and for a traced check_Q."""
    check = lambda system, Q0, xi0: traced_first_step_check(system, jnp.asarray(Q0), jnp.asarray(xi0))
    assert check(cj.models.rigid_body(INERTIA), np.eye(3), XI0) is None
    assert check(cj.models.heavy_top(jnp.array([1.0, 1.0, 0.4]), 1.5), np.eye(3), TOP_XI0) is None
    assert check(SE3, SE3_Q0, SE3_XI0) is None
    assert check(NUMPY_CIRCLE, np.array([0.6, 0.8]), np.ones(2)) is None
    assert check(FORWARD, np.eye(3), XI0) is not None and check(CIRCLE, np.array([0.6, 0.8]), np.ones(2)) is not None


def test_the_programs_logarithm_is_scipys():
    """The traced test's logarithm (square roots, then the series) against SciPy's `logm`, for a
    rotation by 2.9 rad (several square roots) and a rigid motion near the identity (none)."""
    from scipy.linalg import logm

    from clebsch_jax.core import manifold_checks

    log = jax.jit(manifold_checks._traced_log)
    for g in [np.asarray(cj.lie.so3_exp(jnp.array([2.0, -1.5, 1.4]))), np.eye(4) + 0.1 * np.asarray(_se3_hat(SE3_XI0))]:
        np.testing.assert_allclose(np.asarray(log(g)), logm(g).real, rtol=0, atol=1e-12)
