r"""Issue 22: no silent wrong answers. Each case of the issue, and a variant of it, is refused
with a message naming the argument, or reported with a status, a step and a member — never a
success with wrong numbers.

Cost: the systems are built once at module level and the runs are short (few distinct shapes),
so the compiled programs are shared between the tests.
"""

from __future__ import annotations

import functools
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from jax.tree_util import Partial

import clebsch_jax as cj
from clebsch_jax import Status
from clebsch_jax.batching import batch_last
from clebsch_jax.batching import probe
from clebsch_jax.core import validation
from clebsch_jax.march.scan import energy_jump

I3, W = jnp.eye(3), jnp.array([1.3, 0.8, -0.4])
INERTIA = jnp.array([2.0, 1.0, 2 / 3])
RB = cj.models.rigid_body(INERTIA)


def _wall(strength, xi, Q):
    """The issue's particle: free in the plane, with a potential singular on the line Q_0 = 5."""
    return 0.5 * xi @ xi + strength / jnp.abs(5.0 - Q[0])


WALL = cj.ClebschSystem(
    lagrangian=Partial(_wall, jnp.asarray(1.0)),
    velocity_map=lambda x, Q: x + 0 * Q,
    derivative_map=cj.forward_difference,
)


# -- 1. a nonlinear velocity map --------------------------------------------------------------


@pytest.mark.parametrize(
    "velocity_map",
    [
        lambda x, Q: Q @ cj.lie.se2_hat(x * x),  # the issue's
        lambda x, Q: Q @ cj.lie.hat(x) + 0.1 * Q @ cj.lie.hat(jnp.sin(x)),  # variant: nonlinear in a part
    ],
)
def test_a_nonlinear_velocity_map_is_refused_naming_it(velocity_map):
    Q0 = jnp.eye(3)
    S = cj.ClebschSystem(lagrangian=lambda x: 0.5 * x @ x, velocity_map=velocity_map, derivative_map=cj.cayley)
    with pytest.raises(ValueError, match="velocity_map: must be linear in xi"):
        cj.integrate(S, Q0, jnp.array([0.3, 0.2, 0.1]), dt=0.1, n_steps=5)


# -- 2. a step across a singularity -------------------------------------------------------------


@pytest.mark.parametrize("scheme, step", [("left", 38), ("right", 38)])
def test_a_step_across_a_singularity_fails_with_its_own_status(scheme, step):
    sol = cj.integrate(WALL, jnp.zeros(2), jnp.array([1.0, 0.0]), dt=0.1, n_steps=120, scheme=scheme, throw=False)
    assert int(sol.result) == Status.ENERGY_JUMP and int(sol.failed_step) == step
    assert np.all(np.isfinite(sol.Q[: step + 1])) and np.all(np.isnan(sol.Q[step + 1 :]))
    assert not np.any(sol.valid[step + 1 :]) and np.all(sol.stats.status[step + 1 :] == Status.SKIPPED)
    # the particle stopped short of the wall at x = 5, not at x = 833 beyond it
    assert float(sol.Q[step, 0]) < 5.0
    with pytest.raises(cj.IntegrationError, match=f"step {step} of 120.*energy changed"):
        cj.integrate(WALL, jnp.zeros(2), jnp.array([1.0, 0.0]), dt=0.1, n_steps=120, scheme=scheme)
    # the check can be switched off: the same run then reports success, as before
    off = cj.integrate(
        WALL, jnp.zeros(2), jnp.array([1.0, 0.0]), dt=0.1, n_steps=120, scheme=scheme, check_energy=False
    )
    assert int(off.result) == Status.SUCCESS and float(off.Q[-1, 0]) > 5.0


def test_a_jump_is_reported_with_its_member_under_vmap():
    """Variant: the wall's strength is a batched parameter; only the member whose particle
    reaches the attractive wall (strength > 0: potential -strength/|5 - x|) fails; one bounces
    off a repulsive wall and one moves along it, both successes, untouched by the failure."""

    def run(strength, v):
        # XLA alone too: the claim is that vmap's members equal XLA's single runs bit for bit
        # (a concrete call would otherwise run the native kernel, equal only to round-off)
        return cj.integrate(
            _wall_system(strength), jnp.zeros(2), v, dt=0.1, n_steps=120, scheme="left", throw=False, backend="xla"
        )

    strengths = jnp.array([-1.0, 1.0, 1.0])
    vs = jnp.array([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    sol = jax.vmap(run)(strengths, vs)
    np.testing.assert_array_equal(sol.result, [Status.SUCCESS, Status.ENERGY_JUMP, Status.SUCCESS])
    alone = run(strengths[0], vs[0])
    np.testing.assert_array_equal(sol.Q[0], alone.Q)
    with pytest.raises(cj.IntegrationError, match="batch member 1, step"):
        sol.raise_if_failed()


def _wall_system(strength):
    return cj.ClebschSystem(
        lagrangian=Partial(_wall, strength), velocity_map=WALL.velocity_map, derivative_map=cj.forward_difference
    )


@pytest.mark.slow  # sweep programs of their own
def test_a_sweep_finds_the_same_jump_across_its_chunks():
    """Variant: a sweep checks the energy over the whole run, chunk by chunk (its running
    maxima carried from chunk to chunk), and finds the jump at the step `integrate` finds, in
    the middle of a chunk; the failed member's later nodes and final state are NaN, its energy
    error covers the nodes before the jump, and the other members are untouched."""
    strengths = jnp.array([1.0, -1.0])
    Q0, v = jnp.zeros((1, 2)), jnp.array([[1.0, 0.0]])
    res = cj.sweep(
        _wall_system, strengths, Q0, v, dt=0.1, n_steps=120, grid=True, chunk_steps=16, save_every=4, scheme="left"
    )
    ref = [
        cj.integrate(_wall_system(s), Q0[0], v[0], dt=0.1, n_steps=120, scheme="left", throw=False) for s in strengths
    ]
    step = int(ref[0].failed_step)
    assert int(ref[0].result) == Status.ENERGY_JUMP and step % 16 not in (0, 15)  # inside a chunk
    np.testing.assert_array_equal(res.status, [Status.ENERGY_JUMP, Status.SUCCESS])
    np.testing.assert_array_equal(res.failed_step, [step, -1])
    assert np.all(np.isnan(res.final_Q[0])) and np.all(np.isnan(res.final_momentum[0]))
    np.testing.assert_allclose(res.final_Q[1], ref[1].Q[-1], rtol=1e-12, atol=1e-12)
    saved = res.saved["step"]
    assert np.all(np.isfinite(res.saved["Q"][0, saved <= step])) and np.all(np.isnan(res.saved["Q"][0, saved > step]))
    energy = np.asarray(cj.diagnostics.energy(_wall_system(strengths[0]), ref[0]))
    np.testing.assert_allclose(res.energy_error[0], np.max(np.abs(energy[: step + 1] - energy[0])), rtol=1e-9)
    off = cj.sweep(
        _wall_system,
        strengths,
        Q0,
        v,
        dt=0.1,
        n_steps=120,
        grid=True,
        chunk_steps=16,
        scheme="left",
        check_energy=False,
    )
    np.testing.assert_array_equal(off.status, [Status.SUCCESS, Status.SUCCESS])


_JUMP_N = 24
_jump_traced = jax.jit(lambda E, size, status, largest, size_max: energy_jump(jnp, E, size, status, largest, size_max))


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.floats(-1.0, 1.0), min_size=_JUMP_N + 1, max_size=_JUMP_N + 1),
    st.lists(st.sampled_from([1e-3, 1e-1, 10.0]), min_size=_JUMP_N + 1, max_size=_JUMP_N + 1),
    st.lists(st.integers(0, 2), min_size=_JUMP_N + 1, max_size=_JUMP_N + 1),
    st.sampled_from([(1e-4, 1e-2, 1.0), (1e-2, 1.0, 1e2)]),
    st.integers(0, _JUMP_N),
)
def test_the_energy_check_made_in_pieces_is_the_check_of_the_whole_run(noise, scale, level, sizes, failure):
    """The sweep checks a run chunk by chunk, carrying the running maxima: on any energy
    sequence (changes of scales 1e-3 to 10, energy sizes of 1e-4 to 1e2, so that some changes
    are jumps and some are not only because of the maxima carried; a failed step at `failure`
    or none) the pieces, split at every step, find the jump the whole run has, at the same step,
    and hand on the same maxima; the traced check (a scan) agrees with the NumPy one."""
    E = np.cumsum(np.asarray(noise) * np.asarray(scale))
    sizes = np.asarray(sizes)[np.asarray(level)]
    status = np.where(np.arange(_JUMP_N) == failure, Status.MAX_ITERATIONS, Status.SUCCESS).astype(np.int32)
    whole = energy_jump(np, E, sizes, status)
    traced = _jump_traced(E, sizes, status, 0.0, 0.0)
    assert bool(traced[0]) == bool(whole[0]) and (not whole[0] or int(traced[1]) == int(whole[1]))
    np.testing.assert_array_equal(np.asarray(traced[2:]), np.asarray(whole[2:]))
    for split in range(1, _JUMP_N):
        first = energy_jump(np, E[: split + 1], sizes[: split + 1], status[:split])
        if first[0] or failure < split:  # the sweep stops checking a member at its first failure
            assert bool(first[0]) == bool(whole[0] and whole[1] < split)
            assert not first[0] or int(first[1]) == int(whole[1])
            continue
        second = energy_jump(np, E[split:], sizes[split:], status[split:], first[2], first[3])
        assert bool(second[0]) == bool(whole[0])
        assert not whole[0] or split + int(second[1]) == int(whole[1])
        np.testing.assert_array_equal(second[2:], whole[2:])


def test_the_energy_check_passes_a_long_smooth_run():
    """No false alarm: the rigid body's energy oscillates at O(dt²) for thousands of steps,
    across chunk boundaries, and a large step (dt = 0.5) is still a success."""
    for dt, n in ((0.1, 3000), (0.5, 400)):
        sol = cj.integrate(RB, I3, W, dt=dt, n_steps=n)
        assert int(sol.result) == Status.SUCCESS


# -- 3. the gradient of a failed march ----------------------------------------------------------


@pytest.mark.slow  # a gradient program of the march per case; test_engine's gradient tests stay in the default run
@pytest.mark.parametrize("reduce", [False, True])
def test_the_gradient_of_a_failed_march_is_nan_not_zero(reduce):
    def final(x):
        sol = cj.integrate(RB, I3, x, dt=5.0, n_steps=10, throw=False, reduce=reduce, max_newton_iterations=2)
        return sol.momentum[-1].sum(), sol.result

    (value, result), grad = jax.value_and_grad(final, has_aux=True)(W)
    assert int(result) != Status.SUCCESS and np.isnan(value)
    assert np.all(np.isnan(grad))


def test_the_gradient_of_a_member_with_invalid_input_is_nan():
    # a model parameter out of range (zero circulation of a point vortex, made NaN by the model
    # under tracing) gives a NaN value and a NaN gradient, never a zero one; the valid
    # circulations' gradient is finite
    Q0 = jnp.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])

    def final_x(gamma):
        sol = cj.integrate(cj.models.point_vortices(gamma), Q0, jnp.zeros((3, 2)), dt=0.01, n_steps=2, throw=False)
        return sol.Q[-1, :, 0].sum(), sol.result

    (value, result), grad = jax.value_and_grad(final_x, has_aux=True)(jnp.array([1.0, 0.0, 1.0]))
    assert int(result) == cj.Status.INVALID_INPUT and np.isnan(value) and np.all(np.isnan(grad))
    (value, result), grad = jax.value_and_grad(final_x, has_aux=True)(jnp.array([1.0, 0.5, 1.0]))
    assert int(result) == cj.Status.SUCCESS and np.all(np.isfinite(grad))


@pytest.mark.slow  # a compiled gradient program of the vortices' march; the eager gradient above runs by default
def test_under_jit_and_vmap_the_gradient_of_an_invalid_member_is_nan_and_the_others_are_their_own():
    """Variant of the issue's case (value_and_grad of one member with a negative inertia) on the
    other paths: jit of vmap of the gradient, over members of which one has a zero circulation.
    Its value and gradient are NaN; the valid member's gradient is the one it has alone."""
    Q0 = jnp.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])

    def final_x(gamma):
        sol = cj.integrate(cj.models.point_vortices(gamma), Q0, jnp.zeros((3, 2)), dt=0.01, n_steps=2, throw=False)
        return sol.Q[-1, :, 0].sum()

    gammas = jnp.array([[1.0, 0.5, 1.0], [1.0, 0.0, 1.0]])
    values, grads = jax.jit(jax.vmap(jax.value_and_grad(final_x)))(gammas)
    assert np.isnan(values[1]) and np.all(np.isnan(grads[1]))
    alone = jax.grad(final_x)(gammas[0])
    assert np.all(np.isfinite(grads[0]))
    np.testing.assert_allclose(grads[0], alone, rtol=1e-12, atol=1e-14)


@pytest.mark.slow  # a second compiled gradient program (vmapped)
def test_a_failed_member_does_not_poison_the_others_gradients():
    """Variant: a vmapped batch with one failing member: its gradient is NaN, the healthy
    member's is the one it has alone (with respect to its own initial velocity)."""

    def loss(xs, dts):
        sol = jax.vmap(lambda x, d: cj.integrate(RB, I3, x, dt=d, n_steps=10, throw=False, max_newton_iterations=2))(
            xs, dts
        )
        return jnp.sum(jnp.where(sol.succeeded, sol.momentum[:, -1].sum(-1), 0.0))

    xs, dts = jnp.stack([W, W]), jnp.array([0.1, 5.0])
    g = jax.grad(loss)(xs, dts)
    alone = jax.grad(
        lambda x: cj.integrate(RB, I3, x, dt=0.1, n_steps=10, throw=False, max_newton_iterations=2).momentum[-1].sum()
    )(W)
    np.testing.assert_allclose(g[0], alone, rtol=1e-12)
    assert np.all(np.isnan(g[1]))


# -- 4. bad values under vmap, cj.batch and in sweeps ----------------------------------------------


def _with_inertia(inertia):
    return cj.integrate(cj.models.rigid_body(inertia), I3, W, dt=0.1, n_steps=5, throw=False)


def _with_dt(dt):
    return cj.integrate(RB, I3, W, dt=dt, n_steps=5, throw=False)


def _with_Q0(Q0):
    return cj.integrate(RB, Q0, W, dt=0.1, n_steps=5, throw=False)


BAD_ROWS = [
    (_with_inertia, jnp.array([[2.0, 1.0, 2 / 3], [-2.0, 1.0, 2 / 3]])),  # a negative inertia
    (_with_dt, jnp.array([0.1, -0.1])),  # a negative dt
    (_with_Q0, jnp.stack([I3, 2 * I3])),  # |QᵀQ - I| = 3
    (_with_Q0, jnp.stack([I3, jnp.diag(jnp.array([1.0, 1.0, -1.0]))])),  # variant: a reflection
    (_with_dt, jnp.array([0.1, jnp.nan])),  # variant: a NaN dt
]


@pytest.mark.parametrize("batching", ["vmap", pytest.param("batch", marks=pytest.mark.slow)])
@pytest.mark.parametrize("run, rows", BAD_ROWS)
def test_bad_values_under_transformations_fail_at_step_zero(batching, run, rows):
    """The issue's three cases and two variants, under jax.vmap (cj.batch: slow, it compiles
    each program again batch-last)."""
    transform = jax.vmap if batching == "vmap" else cj.batch
    sol = transform(run)(rows)
    np.testing.assert_array_equal(sol.result, [Status.SUCCESS, Status.INVALID_INPUT])
    np.testing.assert_array_equal(sol.failed_step, [-1, 0])
    assert np.all(np.isnan(sol.momentum[1, 1:])) and not np.any(sol.valid[1])
    with pytest.raises(cj.IntegrationError, match="batch member 1, step 0 of 5: this member's input is invalid"):
        sol.raise_if_failed()


def test_a_zero_circulation_under_vmap_is_invalid_input():
    """Variant on another model: point vortices with a zero circulation (their constructor
    refuses it when concrete)."""
    Q0 = jnp.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0]])

    def run(gamma):
        return cj.integrate(cj.models.point_vortices(gamma), Q0, jnp.zeros_like(Q0), dt=0.05, n_steps=3, throw=False)

    sol = jax.vmap(run)(jnp.array([[1.0, 1.0, -0.5], [1.0, 0.0, -0.5]]))
    np.testing.assert_array_equal(sol.result, [Status.SUCCESS, Status.INVALID_INPUT])


def test_a_sweep_checks_every_parameter_row():
    inertias = jnp.array([[2.0, 1.0, 2 / 3], [1.0, 1.0, 0.5], [-1.0, 1.0, 0.5], [3.0, 0.0, 1.0]])
    res = cj.sweep(
        cj.models.rigid_body, inertias, jnp.broadcast_to(I3, (4, 3, 3)), jnp.broadcast_to(W, (4, 3)), dt=0.1, n_steps=5
    )
    np.testing.assert_array_equal(
        res.status, [Status.SUCCESS, Status.SUCCESS, Status.INVALID_INPUT, Status.INVALID_INPUT]
    )
    np.testing.assert_array_equal(res.failed_step, [-1, -1, 0, 0])
    with pytest.raises(cj.IntegrationError, match="member 2"):
        res.raise_if_failed()


# -- 5. float32 input ----------------------------------------------------------------------------


@pytest.mark.parametrize("which", ["Q0", "xi0", "dt", "all"])
def test_float32_input_is_promoted_to_float64(which):
    args = dict(Q0=I3, xi0=W, dt=jnp.asarray(0.1))
    expect = cj.integrate(RB, args["Q0"], args["xi0"], dt=args["dt"], n_steps=5)
    for name in args if which == "all" else [which]:
        args[name] = np.asarray(args[name], np.float32)
    sol = cj.integrate(RB, args["Q0"], args["xi0"], dt=args["dt"], n_steps=5)
    assert sol.momentum.dtype == jnp.float64
    # float32 input rounds the data (0.8 and 0.1 are not float32 numbers): the runs agree to
    # float32's epsilon, not bit for bit
    np.testing.assert_allclose(sol.momentum, expect.momentum, rtol=1e-6, atol=1e-6)


def test_float32_batches_run_under_vmap_and_in_sweeps():
    """Variant: a float32 batch under vmap, and a float32 sweep."""
    xs = np.stack([np.asarray(W, np.float32)] * 2)
    assert list(jax.vmap(lambda x: cj.integrate(RB, I3, x, dt=0.1, n_steps=5).result)(xs)) == [0, 0]
    res = cj.sweep(RB, None, np.eye(3, dtype=np.float32)[None], xs[:1], dt=np.float32(0.1), n_steps=5)
    assert int(res.status[0]) == Status.SUCCESS


# -- 6. internal errors become named ones ------------------------------------------------------------


@pytest.mark.parametrize(
    "velocity_map",
    [
        lambda x, Q: Q @ cj.lie.hat(x) / Q[0, 1],  # the kind: NaN (0/0) at Q0 = I
        lambda x, Q: Q @ cj.lie.hat(x) * jnp.log(Q[0, 1]),  # variant: inf at Q0 = I
    ],
)
def test_a_velocity_map_not_finite_at_Q0_is_named(velocity_map):
    S = cj.ClebschSystem(lagrangian=lambda x: 0.5 * x @ x, velocity_map=velocity_map, derivative_map=cj.cayley)
    with pytest.raises(ValueError, match="velocity_map: not finite at the initial configuration Q0"):
        cj.integrate(S, I3, W, dt=0.1, n_steps=5)


def test_numpy_integer_step_counts_run():
    for n in (np.int64(5), np.int32(5)):
        np.testing.assert_array_equal(
            cj.integrate(RB, I3, W, dt=0.1, n_steps=n).momentum, cj.integrate(RB, I3, W, dt=0.1, n_steps=5).momentum
        )


# -- 7. size guard, empty batches ------------------------------------------------------------------


def test_a_run_too_large_for_memory_is_refused_with_the_estimate():
    with pytest.raises(ValueError, match=r"n_steps: 1000000000 steps would need about .* GB.*clebsch_jax.sweep"):
        cj.integrate(RB, I3, W, dt=0.1, n_steps=10**9)


def test_the_size_guard_uses_the_machines_memory(monkeypatch):
    """Variant: on a machine with 1 MB a 10⁴-step run does not fit, a 10-step one does."""
    monkeypatch.setattr(validation, "memory_limit", lambda: 10**6)
    with pytest.raises(ValueError, match="more than this machine's 0.001 GB"):
        cj.integrate(RB, I3, W, dt=0.1, n_steps=10**4)
    assert int(cj.integrate(RB, I3, W, dt=0.1, n_steps=10).result) == Status.SUCCESS


def test_a_sweep_too_long_for_its_schedule_is_refused_with_the_estimate_before_tracing(monkeypatch):
    """10¹² steps in chunks of 100 would be 10¹⁰ chunk descriptors (an empty MemoryError before):
    refused with the estimate and the ways out, before anything is traced."""

    def traced(*args, **kwargs):
        raise AssertionError("the sweep was traced for a run it cannot hold")

    monkeypatch.setattr(probe, "check_first_member", traced)
    with pytest.raises(ValueError, match=r"^n_steps: 1000000000000 steps in 10000000000 chunks of 100 .* GB") as info:
        cj.sweep(RB, None, I3[None], W[None], dt=0.1, n_steps=10**12)
    assert "for the schedule of chunks" in str(info.value) and "larger chunk_steps" in str(info.value)
    # variant: the saved nodes of a run that would fit without them
    monkeypatch.setattr(validation, "memory_limit", lambda: 10**6)
    with pytest.raises(ValueError, match=r"^n_steps: .* GB for the saved nodes.*save_every"):
        cj.sweep(RB, None, I3[None], W[None], dt=0.1, n_steps=10**5, save_every=1)


def test_a_batch_whose_outputs_cannot_fit_is_refused_with_the_estimate_before_evaluating(monkeypatch):
    """cj.batch knows the members' output shapes from one member's trace: 10⁴ members of 2000
    steps on a machine of 1 GB are refused before the program is evaluated or compiled."""

    def evaluated(*args, **kwargs):
        raise AssertionError("the batch was evaluated")

    monkeypatch.setattr(batch_last, "eval_closed", evaluated)
    monkeypatch.setattr(validation, "memory_limit", lambda: 10**9)
    march = cj.batch(lambda x: cj.integrate(RB, I3, x, dt=0.1, n_steps=2000, throw=False))
    with pytest.raises(ValueError, match=r"^batch: 10000 members would need about .* GB for the outputs") as info:
        march(jnp.zeros((10**4, 3)))
    assert "clebsch_jax.sweep" in str(info.value)
    # variant: few members of long runs, on a machine of 100 MB
    monkeypatch.setattr(validation, "memory_limit", lambda: 10**8)
    long = cj.batch(lambda x: cj.integrate(RB, I3, x, dt=0.1, n_steps=10**5, throw=False).momentum)
    with pytest.raises(ValueError, match=r"^batch: 64 members would need about .* GB for the outputs"):
        long(jnp.zeros((64, 3)))


def test_integrate_under_vmap_warns_when_all_members_solutions_would_not_fit(monkeypatch):
    """Under the caller's jit(vmap(...)) integrate sees one member's shapes; the members' count is
    read off the batching tracers (nested vmaps multiply). On a machine of 1 GB, 10⁴ members of
    2000 steps (the issue's jit(vmap)) get a warning with the estimate and the ways out before
    anything compiles; a warning, not a refusal, since XLA keeps only what the program uses
    (here Q[-1]). 10 members, or one vmap of 100 inside another of 100 on 10 MB, are told apart."""
    monkeypatch.setattr(validation, "memory_limit", lambda: 10**9)
    run = lambda x: cj.integrate(RB, I3, x, dt=0.1, n_steps=2000, throw=False).Q[-1]
    with pytest.warns(UserWarning, match=r"^integrate under jax.vmap: the Solutions of 10000 members x 2000 steps"):
        jax.eval_shape(jax.jit(jax.vmap(run)), jnp.zeros((10**4, 3)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        jax.eval_shape(jax.vmap(run), jnp.zeros((10, 3)))
    monkeypatch.setattr(validation, "memory_limit", lambda: 10**7)
    short = lambda x: cj.integrate(RB, I3, x, dt=0.1, n_steps=20, throw=False).Q[-1]
    with pytest.warns(UserWarning, match=r"the Solutions of 10000 members x 20 steps .*clebsch_jax.batch"):
        jax.eval_shape(jax.vmap(jax.vmap(short)), jnp.zeros((100, 100, 3)))


def test_an_empty_batch_gives_an_empty_result_and_an_empty_sweep_says_so():
    out = cj.batch(lambda x: cj.integrate(RB, I3, x, dt=0.1, n_steps=5, throw=False))(jnp.zeros((0, 3)))
    assert out.momentum.shape == (0, 6, 3) and out.result.shape == (0,)
    with pytest.raises(ValueError, match="the sweep is empty"):
        cj.sweep(RB, None, jnp.zeros((0, 3, 3)), jnp.zeros((0, 3)), dt=0.1, n_steps=5)
    with pytest.raises(ValueError, match="the sweep is empty"):  # variant: no parameter rows on a grid
        cj.sweep(cj.models.rigid_body, jnp.zeros((0, 3)), I3[None], W[None], dt=0.1, n_steps=5, grid=True)


# -- the property: every run succeeds within tolerance or reports a failure --------------------------

N_STEPS_PROPERTY, MEMBERS = 40, 4


def _family(params, xi, Q):
    r"""A small family of Lagrangians on the plane: $\tfrac12 (m_0\xi_0^2 + m_1\xi_1^2)$, a
    harmonic potential $-\tfrac k2|Q|^2$ and a term $-c/|a - Q_0|$ singular on the line
    $Q_0 = a$ (c of either sign: repulsive or attractive). k = c = 0 is the free particle."""
    m0, m1, k, c, a = params[0], params[1], params[2], params[3], params[4]
    return 0.5 * (m0 * xi[0] ** 2 + m1 * xi[1] ** 2) - 0.5 * k * Q @ Q - c / jnp.abs(a - Q[0])


def _property_run(scheme, params, Q0, xi0, dt):
    system = cj.ClebschSystem(
        lagrangian=Partial(_family, params), velocity_map=WALL.velocity_map, derivative_map=cj.forward_difference
    )
    return cj.integrate(system, Q0, xi0, dt=dt, n_steps=N_STEPS_PROPERTY, scheme=scheme, throw=False)


_PROPERTY_RUNS = {
    scheme: jax.jit(jax.vmap(functools.partial(_property_run, scheme))) for scheme in ("left", "midpoint")
}

finite = dict(allow_nan=False, allow_infinity=False)
mass = st.one_of(st.floats(0.5, 2.0, **finite), st.floats(-2.0, -0.5, **finite))
good_row = st.tuples(
    mass,
    mass,
    st.sampled_from([0.0, 1.0]).flatmap(lambda on: st.floats(0.0, 2.0 * on, **finite)),
    st.sampled_from([0.0, 1.0]).flatmap(lambda on: st.floats(-1.0 * on, 1.0 * on, **finite)),
    st.floats(2.0, 6.0, **finite),
    st.floats(0.02, 0.2, **finite),
)
bad_value = st.sampled_from([np.nan, np.inf, -0.1, 0.0])


@st.composite
def members(draw):
    """A member: parameters (m0, m1, k, c, a), dt, Q0 and xi0, possibly spoiled by one bad
    value (a non-finite parameter or initial value, or a dt that is not positive)."""
    *params, dt = draw(good_row)
    Q0 = [draw(st.floats(-1.0, 1.0, **finite)), draw(st.floats(-1.0, 1.0, **finite))]
    xi0 = [draw(st.floats(-2.0, 2.0, **finite)), draw(st.floats(-2.0, 2.0, **finite))]
    spoil = draw(st.sampled_from(["none", "none", "param", "dt", "Q0", "xi0"]))
    if spoil == "param":
        params[draw(st.integers(0, 4))] = draw(st.sampled_from([np.nan, np.inf]))
    elif spoil == "dt":
        dt = draw(bad_value)
    elif spoil in ("Q0", "xi0"):
        (Q0 if spoil == "Q0" else xi0)[draw(st.integers(0, 1))] = draw(st.sampled_from([np.nan, np.inf]))
    return params, dt, Q0, xi0, spoil


@pytest.mark.slow  # many marches of distinct shapes
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(members(), min_size=MEMBERS, max_size=MEMBERS), st.sampled_from(sorted(_PROPERTY_RUNS)))
def test_every_run_succeeds_within_tolerance_or_reports_a_failure(rows, scheme):
    params, dt, Q0, xi0, spoiled = (np.array(x, dtype=np.float64) if i < 4 else x for i, x in enumerate(zip(*rows)))
    sol = _PROPERTY_RUNS[scheme](params, Q0, xi0, dt)
    result, failed_step = np.asarray(sol.result), np.asarray(sol.failed_step)
    for m in range(MEMBERS):
        if spoiled[m] != "none":  # refused at step 0
            assert result[m] == Status.INVALID_INPUT and failed_step[m] == 0, (m, rows[m])
            continue
        if result[m] != Status.SUCCESS:  # a failure, reported where it happened
            k = failed_step[m]
            assert 0 <= k < N_STEPS_PROPERTY and not np.any(sol.valid[m, k + 1 :]), (m, rows[m])
            assert np.all(np.isnan(sol.Q[m, k + 1 :])), (m, rows[m])
            continue
        # a success: finite, and the energy within tolerance of its initial value
        assert np.all(np.isfinite(sol.Q[m])) and np.all(np.isfinite(sol.xi[m])), (m, rows[m])
        system = cj.ClebschSystem(
            lagrangian=Partial(_family, params[m]), velocity_map=WALL.velocity_map, derivative_map=cj.forward_difference
        )
        member = jax.tree_util.tree_map(lambda a: a[m], sol)
        energy = np.asarray(cj.diagnostics.energy(system, member))
        pairing = np.sum(np.asarray(member.momentum) * np.asarray(member.xi), axis=-1)
        size = np.max(np.abs(pairing) + np.abs(pairing - energy))
        # A variational step conserves energy to O(dt^p) without drift; near the singular line
        # the local time scale shrinks and the error grows, so the bound is a fraction of the
        # energy's size, not a tolerance on round-off: a crossing changes E by many times it.
        assert np.max(np.abs(energy - energy[0])) <= 0.5 * size, (m, rows[m])
