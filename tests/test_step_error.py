r"""Issue 40, item 4: two classes `integrate` itself missed.

- **A gradual fall into a singularity.** A particle falling nearly radially into a $1/r$
  potential with the first-order left or right principle: each step changes the energy a little
  more than the one before, so the old rule (a change 100× the largest earlier one) never fired,
  and the run crossed the singularity and reported success with the energy many times its size.
  The per-step error indicator (`clebsch_jax.march.scan.ENERGY_STEP_RTOL`: the step's energy
  change over the energy's size so far) fails the step that leaves the motion, on `integrate` and
  on `cj.sweep` with both backends, at the same step. It stays far below its tolerance on runs
  that resolve their motion, even coarsely.
- **An initial velocity whose momentum has no multiplier** at Q0 (Lemma 7): a sweep or batch
  derives P0 from xi0 as given, and the minimum-norm multiplier dropped the rest silently; now a
  warning names xi0, the relative size and what was used instead.

The energies in the assertions are computed here from the unchecked runs' nodes, by
`clebsch_jax.march.scan.energy_terms` (the definition), not read from the check.
"""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import clebsch_jax as cj
from clebsch_jax import Status
from clebsch_jax.march.integrate import check_member
from clebsch_jax.march.scan import ENERGY_STEP_RTOL, energy_terms

from .systems import kepler, translation

KEPLER = cj.ClebschSystem(lagrangian=kepler, velocity_map=translation, derivative_map=cj.forward_difference)
Q0 = np.array([2.0, 0.0])
DT, N = 0.1, 60
FALLING = np.array([0.0, 0.1])  # nearly radial: the orbit's perihelion is far inside one step's reach
RESOLVED = np.array([0.0, 0.3])  # with the right principle this one stays resolved at DT


def _energies(system, sol):
    """(E, size) at the nodes: E = <dl/dxi, xi> - l and |<dl/dxi, xi>| + |l| (NaN after a failure)."""
    pairing, lagrangian = jax.vmap(lambda q, x: energy_terms(system, q, x))(sol.Q, sol.xi)
    pairing, lagrangian = np.asarray(pairing), np.asarray(lagrangian)
    return pairing - lagrangian, np.abs(pairing) + np.abs(lagrangian)


def _relative_changes(E, size):
    """Each step's |E^{n+1} - E^n| over the largest size of the nodes up to the one it leaves."""
    return np.abs(np.diff(E)) / np.maximum.accumulate(size)[:-1]


# -- a gradual fall into a 1/r singularity ----------------------------------------------------


@pytest.mark.parametrize("scheme, step", [("left", 30), ("right", 31)])
def test_a_gradual_fall_into_a_singularity_fails_at_the_step_that_leaves_the_motion(scheme, step):
    unchecked = cj.integrate(KEPLER, Q0, FALLING, dt=DT, n_steps=N, scheme=scheme, check_energy=False)
    E, size = _energies(KEPLER, unchecked)
    # what was reported before: success, with the bound orbit (E < 0) ending far above its own energy
    assert int(unchecked.result) == Status.SUCCESS and E[0] < 0 and E[-1] > 5 * abs(E[0])
    changes = np.abs(np.diff(E))
    # ... reached by steady growth: no step changed E by 100x the largest change before it
    assert np.all(changes[1 : step + 1] < 100 * np.maximum.accumulate(changes)[:step])
    relative = _relative_changes(E, size)
    assert np.argmax(relative > ENERGY_STEP_RTOL) == step  # the first step over the tolerance
    sol = cj.integrate(KEPLER, Q0, FALLING, dt=DT, n_steps=N, scheme=scheme, throw=False)
    assert int(sol.result) == Status.ENERGY_JUMP and int(sol.failed_step) == step
    Q = np.asarray(sol.Q)
    assert np.all(np.isfinite(Q[: step + 1])) and np.all(np.isnan(Q[step + 1 :]))
    assert np.all(np.asarray(sol.stats.status)[step + 1 :] == Status.SKIPPED)
    np.testing.assert_array_equal(Q[: step + 1], np.asarray(unchecked.Q)[: step + 1])
    with pytest.raises(cj.IntegrationError, match=rf"step {step} of {N} .*energy changed.*smaller dt"):
        cj.integrate(KEPLER, Q0, FALLING, dt=DT, n_steps=N, scheme=scheme)


@pytest.mark.parametrize("backend", ["xla", "native"])
def test_a_sweep_fails_the_same_member_at_the_same_step(backend):
    """The per-member program applies the same rule in its loop (`jump_step`), chunk by chunk:
    the falling member fails at integrate's step, inside a chunk; the resolved one succeeds."""
    if backend == "native":
        pytest.importorskip("llvmlite")
    xi0 = np.stack([FALLING, RESOLVED])
    ref = [cj.integrate(KEPLER, Q0, x, dt=DT, n_steps=N, scheme="right", throw=False) for x in xi0]
    assert [int(r.result) for r in ref] == [Status.ENERGY_JUMP, Status.SUCCESS]
    step = int(ref[0].failed_step)
    assert step % 10 not in (0, 9)  # inside a chunk of 10 steps
    res = cj.sweep(
        KEPLER, None, np.stack([Q0, Q0]), xi0, dt=DT, n_steps=N, scheme="right", chunk_steps=10, backend=backend
    )
    np.testing.assert_array_equal(res.status, [Status.ENERGY_JUMP, Status.SUCCESS])
    np.testing.assert_array_equal(res.failed_step, [step, -1])
    assert np.all(np.isnan(res.final_Q[0]))
    np.testing.assert_allclose(res.final_Q[1], np.asarray(ref[1].Q)[-1], rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("backend", ["xla", "native"])
def test_a_tolerance_of_ones_own_fails_the_first_step_above_it_on_every_path(backend):
    """`check_energy=` a number is the check's tolerance: the falling particle fails at the first
    step whose relative change passes it (here some steps before the default's), in `integrate`
    and in a sweep alike (each member as its own `integrate` run)."""
    if backend == "native":
        pytest.importorskip("llvmlite")
    unchecked = cj.integrate(KEPLER, Q0, FALLING, dt=DT, n_steps=N, scheme="right", check_energy=False)
    relative = _relative_changes(*_energies(KEPLER, unchecked))
    tol = 1e-2
    step = int(np.argmax(relative > tol))
    assert 0 < step < int(np.argmax(relative > ENERGY_STEP_RTOL))  # earlier than the default's
    assert np.min(np.abs(relative[: step + 1] - tol)) > 1e-3 * tol  # not decided by round-off
    xi0 = np.stack([FALLING, RESOLVED])
    runs = [
        cj.integrate(KEPLER, Q0, x, dt=DT, n_steps=N, scheme="right", check_energy=tol, backend=backend, throw=False)
        for x in xi0
    ]
    assert int(runs[0].result) == Status.ENERGY_JUMP and int(runs[0].failed_step) == step
    res = cj.sweep(
        KEPLER,
        None,
        np.stack([Q0, Q0]),
        xi0,
        dt=DT,
        n_steps=N,
        scheme="right",
        chunk_steps=10,
        backend=backend,
        check_energy=tol,
    )
    np.testing.assert_array_equal(res.status, [int(r.result) for r in runs])
    np.testing.assert_array_equal(res.failed_step, [int(r.failed_step) for r in runs])


@pytest.mark.parametrize(
    "bad, error", [(0.0, ValueError), (-0.1, ValueError), (np.nan, ValueError), ("yes", TypeError)]
)
def test_a_bad_energy_tolerance_is_refused_naming_it(bad, error):
    with pytest.raises(error, match="check_energy"):
        cj.integrate(KEPLER, Q0, RESOLVED, dt=DT, n_steps=3, check_energy=bad)
    with pytest.raises(error, match="check_energy"):
        cj.sweep(KEPLER, None, Q0[None], RESOLVED[None], dt=DT, n_steps=3, check_energy=bad)


def test_a_jump_from_rest_is_caught_too():
    """Variant: the particle starts at rest beside a line singularity (potential -1/|5 - x|) and
    falls into it; the changes grow steadily over a hundred steps until it crosses."""

    def wall(xi, q):
        return 0.5 * jnp.sum(xi**2) + 1.0 / jnp.abs(5.0 - q[0])

    system = cj.ClebschSystem(lagrangian=wall, velocity_map=translation, derivative_map=cj.forward_difference)
    unchecked = cj.integrate(system, np.zeros(2), np.zeros(2), dt=0.2, n_steps=80, scheme="left", check_energy=False)
    E, size = _energies(system, unchecked)
    assert int(unchecked.result) == Status.SUCCESS and np.max(np.abs(E - E[0])) > 10 * abs(E[0])
    step = int(np.argmax(_relative_changes(E, size) > ENERGY_STEP_RTOL))
    sol = cj.integrate(system, np.zeros(2), np.zeros(2), dt=0.2, n_steps=80, scheme="left", throw=False)
    assert int(sol.result) == Status.ENERGY_JUMP and int(sol.failed_step) == step
    assert float(np.asarray(sol.Q)[step, 0]) < 5.0  # stopped on the near side of the wall


# -- no false alarms ----------------------------------------------------------------------------

INERTIA = np.array([2.0, 1.0, 2.0 / 3.0])
M_LARGE = np.array([np.cos(1.1), 0.0, np.sin(1.1)])  # |omega| ~ 1.4: dt = 1 turns the body ~80 degrees
TOP_Q0 = np.asarray(cj.lie.so3_exp(jnp.array([0.5, 0.0, 0.0])))
PEAKON_Q0, PEAKON_P0 = np.array([-3.0, 0.0]), np.array([2.0, 1.0])
VECTOR_Q0, VECTOR_P0 = (np.asarray(a) for a in cj.models.rigid_body_vector_start(INERTIA * np.array([1.3, 0.8, -0.4])))


def _perihelion(e):
    return np.array([1.0 - e, 0.0]), np.array([0.0, np.sqrt((1.0 + e) / (1.0 - e))])


RESOLVED_RUNS = {
    # name: (system, Q0, xi0, options)
    "rigid body, reduced, dt = 1": (cj.models.rigid_body(INERTIA), np.eye(3), M_LARGE / INERTIA, dict(dt=1.0)),
    "heavy top": (
        cj.models.heavy_top(np.array([1.0, 1.0, 0.4]), 1.5),
        TOP_Q0,
        np.array([0.3, -0.2, 2.0]),
        dict(dt=0.05),
    ),
    "peakons": (
        cj.models.peakons(1.0),
        PEAKON_Q0,
        np.asarray(cj.models.peakon_velocity(PEAKON_Q0, PEAKON_P0, 1.0)),
        dict(dt=0.1, P0=PEAKON_P0),
    ),
    "rigid body vector, Gauss order 8": (
        cj.models.rigid_body_vector(INERTIA),
        VECTOR_Q0,
        np.array([1.3, 0.8, -0.4]),
        dict(dt=0.5, P0=VECTOR_P0, scheme="gauss", order=8),
    ),
    "Kepler e = 0.9, left principle (first order), T/400": (
        KEPLER,
        *_perihelion(0.9),
        dict(dt=2 * np.pi / 400, scheme="left"),
    ),
}


SLOW_RUNS = ("peakons", "rigid body vector, Gauss order 8")  # a compile each, beyond the default run's budget


@pytest.mark.parametrize(
    "name", [pytest.param(name, marks=pytest.mark.slow) if name in SLOW_RUNS else name for name in RESOLVED_RUNS]
)
def test_runs_that_resolve_their_motion_stay_far_below_the_tolerance(name):
    """Over 400 steps (a Kepler period; several turns of the bodies) the largest relative change
    is a small fraction of the tolerance, also for a coarse or first-order run."""
    system, Q0_, xi0, options = RESOLVED_RUNS[name]
    sol = cj.integrate(system, Q0_, xi0, n_steps=400, **options)
    assert int(sol.result) == Status.SUCCESS
    E, size = _energies(system, sol)
    assert np.max(_relative_changes(E, size)) < 0.5 * ENERGY_STEP_RTOL


# -- xi0 whose momentum has no multiplier ------------------------------------------------------

VECTOR = cj.models.rigid_body_vector(INERTIA)
E1 = np.array([1.0, 0.0, 0.0])
SKEW_XI0 = np.array([0.5, 0.8, -0.4])  # I xi0 has a component 1.0 along Q0 = e1, of |I xi0| ~ 1.31
NO_MULTIPLIER = r"^xi0: its momentum dl/dxi\(xi0, Q0\) has a component along the isotropy of Q0 .* 0\.764 of its size"


def _xi0_warnings(record):
    return [w for w in record if str(w.message).startswith("xi0:")]


def test_a_sweep_warns_that_xi0_has_no_multiplier_naming_its_size():
    """rigid_body_vector: the velocity map Q x xi has the isotropy xi || Q; a momentum I xi0
    with a component along Q0 has no multiplier, and the sweep starts from it projected."""
    with pytest.warns(UserWarning, match=NO_MULTIPLIER) as record:
        res = cj.sweep(VECTOR, None, E1[None], SKEW_XI0[None], dt=0.1, n_steps=4, scheme="midpoint", backend="xla")
    assert "minimum-norm P0" in str(_xi0_warnings(record)[0].message)
    # what it used instead: the momentum without its component along Q0, i.e. the run from the
    # multiplier P0 = Q0 x m of that momentum m
    m = INERTIA * SKEW_XI0 - E1 * (INERTIA * SKEW_XI0)[0]
    ref = cj.integrate(VECTOR, E1, SKEW_XI0, P0=np.cross(E1, m), dt=0.1, n_steps=4, scheme="midpoint")
    np.testing.assert_allclose(np.asarray(ref.momentum)[0], m, atol=1e-14)
    np.testing.assert_allclose(res.final_momentum[0], np.asarray(ref.momentum)[-1], rtol=1e-12, atol=1e-14)


@pytest.mark.slow  # compiles a batch; the sweep's test covers the first-member check by default
def test_batch_warns_too_and_a_consistent_xi0_is_silent():
    march = cj.batch(lambda x: cj.integrate(VECTOR, jnp.asarray(E1), x, dt=0.1, n_steps=2, throw=False).Q[-1])
    with pytest.warns(UserWarning, match=NO_MULTIPLIER):
        march(SKEW_XI0[None])
    consistent = SKEW_XI0 - E1 * (INERTIA * SKEW_XI0)[0] / INERTIA[0]  # I xi0 perpendicular to Q0
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        march(consistent[None])
    assert not _xi0_warnings(record)


def test_integrate_takes_xi0_as_its_physical_velocity_with_one_warning():
    """integrate alone moves xi0 along the isotropy until its momentum has a multiplier
    (`physical_velocity`, which warns); nothing is left for the multiplier to drop."""
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        sol = cj.integrate(VECTOR, E1, SKEW_XI0, dt=0.1, n_steps=2)
    messages = [str(w.message) for w in _xi0_warnings(record)]
    assert len(messages) == 1 and "xi0: has a component along the isotropy" in messages[0]
    np.testing.assert_allclose(np.asarray(sol.momentum)[0], INERTIA * np.asarray(sol.xi)[0], atol=1e-14)


def test_a_gauge_fixed_lagrangian_is_not_blamed_for_an_isotropy_component():
    """A spherical pendulum written with the physical velocity xi x q: l does not see xi || q,
    the engine fixes the gauge, and the momentum of any xi0 has a multiplier."""

    def natural(xi, q):
        return 0.5 * jnp.sum(jnp.cross(xi, q) ** 2) - 0.8 * q[2]

    system = cj.ClebschSystem(
        lagrangian=natural, velocity_map=lambda x, q: jnp.cross(x, q), derivative_map=cj.forward_difference
    )
    q0 = np.array([0.6, 0.0, -0.8])
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        check_member(system, q0, np.array([0.0, 0.0, 1.0]) + 1.7 * q0, dt=0.01)
    assert not [w for w in _xi0_warnings(record) if "no initial multiplier" in str(w.message)]


# a variant of the case on another system: a body on the unit sphere moved by ξ × q,
# with an anisotropic kinetic energy (not diagonal) and gravity, at a Q0 off the axes; its
# momentum A ξ0 has a component along q0, which no multiplier gives

A_SPHERE = np.array([[2.0, 0.3, 0.0], [0.3, 1.0, 0.2], [0.0, 0.2, 0.7]])
Q0_SPHERE = np.array([0.6, 0.0, -0.8])
XI0_SPHERE = np.array([1.0, 0.3, -0.6])


def _sphere_body(xi, q):
    return 0.5 * xi @ A_SPHERE @ xi + 0.9 * q[2]


SPHERE_BODY = cj.ClebschSystem(
    lagrangian=_sphere_body, velocity_map=lambda xi, q: jnp.cross(xi, q), derivative_map=cj.forward_difference
)


class _Reached(Exception):
    """The batch was about to be traced or evaluated: the checks were made before it."""


def _reached(*args, **kwargs):
    raise _Reached


@pytest.mark.slow  # a batch and integrate of a new system compiled; the rigid_body_vector case runs by default
def test_sweeps_and_batches_warn_for_another_system_naming_the_size(monkeypatch):
    """The sweep's check of its first member (both backends; the batch itself stubbed) and
    cj.batch's (one member, two steps) warn, naming xi0 and the relative size."""
    from clebsch_jax.batching import choose, probe

    m = A_SPHERE @ XI0_SPHERE
    defect = abs(m @ Q0_SPHERE) / np.linalg.norm(m)  # |q0| = 1: the isotropy is the line of q0
    assert defect > 0.1
    message = (
        rf"^xi0: its momentum dl/dxi\(xi0, Q0\) has a component along the isotropy of Q0 .* {defect:.3g} of its size"
    )
    monkeypatch.setattr(probe, "member_shapes", _reached)
    monkeypatch.setattr(choose, "native_config", _reached)
    for backend in ("xla", "native"):
        with pytest.warns(UserWarning, match=message), pytest.raises(_Reached):
            cj.sweep(SPHERE_BODY, None, Q0_SPHERE[None], XI0_SPHERE[None], dt=0.05, n_steps=4, backend=backend)
    march = cj.batch(lambda x: cj.integrate(SPHERE_BODY, Q0_SPHERE, x, dt=0.05, n_steps=2, throw=False).result)
    with pytest.warns(UserWarning, match=message):
        march(XI0_SPHERE[None])
    # integrate takes xi0 as its physical velocity, whose momentum has a multiplier (one warning)
    with pytest.warns(UserWarning, match="xi0: has a component along the isotropy"):
        sol = cj.integrate(SPHERE_BODY, Q0_SPHERE, XI0_SPHERE, dt=0.05, n_steps=2, backend="xla")
    assert abs(float(np.asarray(sol.momentum)[0] @ Q0_SPHERE)) < 1e-14
    np.testing.assert_allclose(np.cross(np.asarray(sol.xi)[0], Q0_SPHERE), np.cross(XI0_SPHERE, Q0_SPHERE), atol=1e-14)


def _wall(xi, q):
    """A particle beside the line singularity q₀ = 5 (potential −1/|5 − q₀|)."""
    return 0.5 * jnp.sum(xi**2) + 1.0 / jnp.abs(5.0 - q[0])


WALL = cj.ClebschSystem(lagrangian=_wall, velocity_map=translation, derivative_map=cj.forward_difference)


@pytest.mark.slow  # a sweep program per backend compiled; test_a_sweep_fails_the_same_member_at_the_same_step runs by default
@pytest.mark.parametrize("backend", ["xla", "native"])
def test_a_sweep_fails_a_gradual_fall_at_integrates_step_on_another_singularity(backend):
    """The variant above (from rest into a line singularity, left principle) in a sweep: the
    falling member fails with integrate's status at integrate's step, inside a chunk; the member
    moving away from the wall succeeds with integrate's final state."""
    if backend == "native":
        pytest.importorskip("llvmlite")
    Q0s, xi0s = np.zeros((2, 2)), np.array([[0.0, 0.0], [-3.0, 0.5]])
    options = dict(dt=0.2, n_steps=80, scheme="left")
    ref = [cj.integrate(WALL, q, x, throw=False, backend="xla", **options) for q, x in zip(Q0s, xi0s)]
    assert [int(r.result) for r in ref] == [Status.ENERGY_JUMP, Status.SUCCESS]
    res = cj.sweep(WALL, None, Q0s, xi0s, chunk_steps=7, backend=backend, **options)
    np.testing.assert_array_equal(res.status, [int(r.result) for r in ref])
    np.testing.assert_array_equal(res.failed_step, [int(r.failed_step) for r in ref])
    assert int(ref[0].failed_step) % 7 not in (0, 6)  # inside a chunk
    np.testing.assert_allclose(res.final_Q[1], np.asarray(ref[1].Q)[-1], rtol=1e-10, atol=1e-12)
