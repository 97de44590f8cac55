r"""The fast path of `sweep` (`clebsch_jax.batching.fast`): fixed Newton updates with a check per
member and step, the chunk rerun with the general loop when a check fails, and the scalarising
evaluator (`clebsch_jax.batching.scalarise`) that runs its loop with one row per component.

The references are independent runs of `integrate` (the general Newton loop) per member, not
the fast path. Compile time dominates: the rigid-body sweeps share one program (`RB`: batches
of 4, 2 chunks of 20 steps), and only array values (inertias, initial data, dt) change.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import clebsch_jax as cj
from clebsch_jax import Status
from clebsch_jax.batching.fast import fast_method
from clebsch_jax.batching.scalarise import scalarise
from clebsch_jax.models import heavy_top, point_vortices, rigid_body
from clebsch_jax.roots.newton import fixed_newton_solve, newton_solve
from clebsch_jax.roots.solvers import FixedNewton

from .helpers import compiles_recorded

N_STEPS = 40
RB = dict(
    n_steps=N_STEPS,
    chunk_steps=20,
    batch_size=4,
    reconstruct=False,
    fast=True,
    invariants={"casimir": lambda system, sol: jnp.sum(sol.momentum**2, axis=-1)},
)
INERTIAS = np.array([[2.0, 1.0, 2.0 / 3.0], [1.0, 1.5, 0.5], [0.5, 0.6, 1.0], [1.2, 1.1, 0.7]])
OMEGAS = np.array([[1.3, 0.8, -0.4], [0.2, 1.0, 0.3], [-0.5, 0.1, 0.9], [0.3, -0.7, 0.3]])
EYES = np.broadcast_to(np.eye(3), (4, 3, 3))


def reference(system, Q0, xi0, dt, n_steps, **options):
    """One member by `integrate` with the general Newton loop: final momentum and energy error."""
    sol = cj.integrate(system, jnp.asarray(Q0), jnp.asarray(xi0), dt=dt, n_steps=n_steps, **options)
    E = np.asarray(cj.diagnostics.energy(system, sol))
    return np.asarray(sol.momentum[-1]), float(np.max(np.abs(E - E[0])))


@pytest.mark.slow  # the fast path, the general path and integrate, each compiled
def test_rigid_bodies_agree_with_integrate_and_keep_invariants():
    res = cj.sweep(rigid_body, INERTIAS, EYES, OMEGAS, dt=0.05, **RB)
    assert res.fast_chunks == 2 and res.fallback_chunks == 0  # one batch, two chunks, all checks passed
    assert np.all(res.succeeded)
    for m in range(4):
        mu, energy_error = reference(rigid_body(INERTIAS[m]), np.eye(3), OMEGAS[m], 0.05, N_STEPS, reconstruct=False)
        np.testing.assert_allclose(res.final_momentum[m], mu, rtol=0, atol=1e-13)
        # the same scheme to round-off: the same energy error (it is O(dt²), far above round-off)
        assert abs(res.energy_error[m] - energy_error) <= 1e-13
    # the Casimir |μ|² of the reduced CAY march is conserved to round-off
    assert np.max(res.drift["casimir"]) < 1e-13


@pytest.mark.slow  # the fast and the general path both compiled
def test_forced_fallback_large_dt_gives_the_general_answer(monkeypatch):
    # Δt = 0.6 with |ω| ~ 3: the predictor is poor, K fixed updates do not reach round-off,
    # every chunk is rerun with the general loop; the answers are the general loop's
    from clebsch_jax.batching import schedule

    omegas = 3.0 * OMEGAS
    res = cj.sweep(rigid_body, INERTIAS, EYES, omegas, dt=0.6, **RB)
    assert res.fallback_chunks >= 1 and res.fast_chunks == 2
    # fast=False runs each batch whole: no member is gathered into rerun groups
    monkeypatch.setattr(schedule, "FALLBACK_BATCH", 2)
    monkeypatch.setattr(schedule, "_take_members", lambda *a: pytest.fail("fast=False gathered members"))
    general = cj.sweep(rigid_body, INERTIAS, EYES, omegas, dt=0.6, **{**RB, "fast": False})
    assert general.fast_chunks == 0 and general.fallback_chunks == 0
    np.testing.assert_array_equal(res.status, general.status)
    np.testing.assert_allclose(res.final_momentum, general.final_momentum, rtol=0, atol=1e-12)
    for m in range(4):
        mu, _ = reference(rigid_body(INERTIAS[m]), np.eye(3), omegas[m], 0.6, N_STEPS, reconstruct=False, throw=False)
        np.testing.assert_allclose(res.final_momentum[m], mu, rtol=0, atol=1e-12)


@pytest.mark.slow  # the fast path's failure report, compiled apart (the sweep's failure reports stay in test_sweep_checks)
def test_failing_member_reported_with_step_and_member():
    omegas = OMEGAS.copy()
    omegas[2] = np.nan  # member 2 is invalid input, reported at step 0; the others are unaffected
    res = cj.sweep(rigid_body, INERTIAS, EYES, omegas, dt=0.05, **RB)
    assert list(res.failed_members) == [2]
    assert res.status[2] == Status.INVALID_INPUT and res.failed_step[2] == 0
    assert res.fallback_chunks >= 1  # the chunk with the failure ran on the general path
    ok = cj.sweep(rigid_body, INERTIAS, EYES, OMEGAS, dt=0.05, **RB)
    np.testing.assert_allclose(res.final_momentum[[0, 1, 3]], ok.final_momentum[[0, 1, 3]], rtol=0, atol=1e-13)


@pytest.mark.slow  # compiles the recording fast chunk and the general chunk of a rerun group
def test_only_the_members_whose_check_failed_run_again(monkeypatch):
    # Members 1, 4 and 6 take steps of 0.6 with |ω| ~ 3 (the fixed updates do not reach
    # round-off); the others are easy. Only those three run again on the general path, in groups
    # of FALLBACK_BATCH = 2 members (the last group padded with a copy of its member), every
    # chunk; the table (saved nodes included) is the general path's.
    from clebsch_jax.batching import schedule

    monkeypatch.setattr(schedule, "FALLBACK_BATCH", 2)
    inertias, eyes = np.concatenate([INERTIAS, INERTIAS]), np.concatenate([EYES, EYES])
    omegas, dts = np.concatenate([OMEGAS, OMEGAS]), np.full(8, 0.05)
    hard = np.array([1, 4, 6])
    omegas[hard] *= 3.0
    dts[hard] = 0.6
    run = {**RB, "batch_size": 8, "save_every": 10}
    res = cj.sweep(rigid_body, inertias, eyes, omegas, dt=dts, **run)
    ref = cj.sweep(rigid_body, inertias, eyes, omegas, dt=dts, **{**run, "fast": False})
    assert res.fast_chunks == res.fallback_chunks == 2
    assert res.fallback_member_chunks == len(hard) * 2
    np.testing.assert_array_equal(res.status, ref.status)
    np.testing.assert_array_equal(res.failed_step, ref.failed_step)
    for key in ("final_momentum", "final_xi", "final_p", "energy_error"):
        np.testing.assert_allclose(getattr(res, key), getattr(ref, key), rtol=0, atol=1e-12, err_msg=key)
    np.testing.assert_allclose(res.drift["casimir"], ref.drift["casimir"], rtol=0, atol=1e-12)
    for key in ("t", "momentum", "xi"):
        np.testing.assert_allclose(res.saved[key], ref.saved[key], rtol=0, atol=1e-12, err_msg=key)
    # a hard member's Newton iterations are the general loop's; an easy member's, the fixed updates'
    np.testing.assert_array_equal(res.newton_iterations[hard], ref.newton_iterations[hard])
    easy = np.setdiff1d(np.arange(8), hard)
    assert np.all(res.newton_iterations[easy] != ref.newton_iterations[easy])


def _assert_same_table(a, b):
    for key in (
        "status",
        "failed_step",
        "newton_iterations",
        "max_residual",
        "final_t",
        "final_momentum",
        "final_xi",
        "final_p",
        "energy_error",
        "fast_chunks",
        "fallback_chunks",
        "fallback_member_chunks",
    ):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key), err_msg=key)
    for name in a.drift:
        np.testing.assert_array_equal(a.drift[name], b.drift[name], err_msg=name)
    for key in ("t", "momentum", "xi"):
        np.testing.assert_array_equal(a.saved[key], b.saved[key], err_msg=key)


@pytest.mark.slow  # a threaded sweep beside a plain one, each compiled
def test_threads_run_batches_side_by_side_with_the_same_table(monkeypatch):
    # batches of 2 members, three at a time from host threads (sweep's threads), with hard
    # members rerun on the general path and saved nodes written from those threads: the table
    # is threads=1's to the bit
    from clebsch_jax.batching import schedule

    monkeypatch.setattr(schedule, "FALLBACK_BATCH", 2)
    inertias, eyes = np.concatenate([INERTIAS, INERTIAS]), np.concatenate([EYES, EYES])
    omegas, dts = np.concatenate([OMEGAS, OMEGAS]), np.full(8, 0.05)
    omegas[[1, 4, 6]] *= 3.0
    dts[[1, 4, 6]] = 0.6
    run = {**RB, "batch_size": 2, "save_every": 10}
    one = cj.sweep(rigid_body, inertias, eyes, omegas, dt=dts, **run, threads=1)
    three = cj.sweep(rigid_body, inertias, eyes, omegas, dt=dts, **run, threads=3)
    assert one.fallback_member_chunks == 6 and one.batch_size == three.batch_size == 2
    _assert_same_table(one, three)
    general = {**run, "fast": False}
    _assert_same_table(
        cj.sweep(rigid_body, inertias, eyes, omegas, dt=dts, **general, threads=1),
        cj.sweep(rigid_body, inertias, eyes, omegas, dt=dts, **general, threads=4),
    )


def test_integrate_traced_without_derivative_rules_is_still_differentiable():
    # a sweep traces integrate's march without the solves' derivative rules (undifferentiated);
    # integrate's programs are keyed by that context, so the same call outside it is traced
    # again with its rules (reusing the first trace, grad would meet the Newton while loop)
    from clebsch_jax.roots.implicit import undifferentiated

    system, w0 = rigid_body(INERTIAS[0]), jnp.asarray(OMEGAS[0])

    def final(w):
        return cj.integrate(system, jnp.eye(3), w, dt=0.05, n_steps=7, reconstruct=False).momentum[-1, 0]

    with undifferentiated():
        jax.eval_shape(final, w0)
    g = np.asarray(jax.grad(final)(w0))
    h = 1e-6
    fd = [(final(w0.at[k].add(h)) - final(w0.at[k].add(-h))) / (2 * h) for k in range(3)]
    np.testing.assert_allclose(g, fd, rtol=0, atol=1e-8)  # central differences: O(h²) + round-off/h


def test_trace_contexts_are_each_threads_own():
    # the lean chunk traces its solves without derivative rules (undifferentiated); a sweep's
    # threads trace at once, and another thread's trace keeps its rules
    import threading

    from clebsch_jax.roots.implicit import in_undifferentiated, undifferentiated

    inside, release, seen = threading.Event(), threading.Event(), []

    def lean_trace():
        with undifferentiated():
            seen.append(in_undifferentiated())
            inside.set()
            release.wait(10)

    t = threading.Thread(target=lean_trace)
    t.start()
    assert inside.wait(10)
    seen.append(in_undifferentiated())  # this thread, while the other is inside
    release.set()
    t.join()
    assert seen == [True, False] and not in_undifferentiated()
    with undifferentiated():
        with undifferentiated():
            assert in_undifferentiated()
        assert in_undifferentiated()
    assert not in_undifferentiated()
    # scalarise's state while it traces (loop depth, rows or stacked) is its layout's, one per
    # call: a layout inside a loop body leaves another (another thread's trace) as it was
    from clebsch_jax.batching.scalarise import RowsLayout

    inside, other = RowsLayout(4), RowsLayout(4)
    with inside.loop_body(scan=True):
        assert (inside.depth, inside.in_loop) == (1, [False, True])
        assert (other.depth, other.in_loop) == (0, [False])
    assert (inside.depth, inside.in_loop) == (0, [False])


def test_default_threads_follow_the_cores_and_the_batch(monkeypatch):
    from clebsch_jax.batching import schedule

    cpu = jax.devices("cpu")[0]
    monkeypatch.setattr(schedule.os, "sched_getaffinity", lambda pid: set(range(8)), raising=False)
    assert schedule.thread_count(None, [None], 10**4) == schedule.THREADS_MAX == 2  # at most THREADS_MAX
    assert schedule.thread_count(None, [cpu, cpu], 10**4) == 1  # the cores shared by the devices
    assert schedule.thread_count(None, [None], 2 * schedule.THREAD_MIN_MEMBERS - 1) == 1  # each thread a batch of 256
    assert schedule.thread_count(3, [None], 10) == 3  # the caller's choice
    monkeypatch.setattr(schedule.os, "sched_getaffinity", lambda pid: {0}, raising=False)
    assert schedule.thread_count(None, [None], 10**4) == 1  # one core
    with pytest.raises(ValueError, match="threads"):
        schedule.thread_count(0, [None], 10)


class _Probed(Exception):
    pass


@pytest.mark.parametrize("case", ["reduced", "reconstructed", "composition", "potential"])
def test_the_lean_probe_gives_the_shapes_of_a_traced_march(monkeypatch, case):
    # the lean path checks a member without tracing its march (probe._check_member); the shapes and
    # facts it finds are those the traced march gives. The sweep stops after the probes: no compile.
    from clebsch_jax.batching import probe

    real, seen = probe.member_shapes, []

    def spy(cfg, members, lean=False):
        shapes = real(cfg, members, lean=lean)
        if lean:
            seen.append(shapes)
            traced = real(cfg, members)
            # (the march state is the general chunk's, which the lean path does not carry)
            assert shapes._replace(invariants=None, march=None) == traced._replace(invariants=None, march=None)
            assert list(shapes.invariants) == list(traced.invariants) == ["energy"]
            for a, b in zip(shapes.invariants.values(), traced.invariants.values()):
                assert (a.shape, a.dtype) == (b.shape, b.dtype)
            raise _Probed
        return shapes

    monkeypatch.setattr(probe, "member_shapes", spy)
    if case == "potential":
        args = (_top, np.array([[1.0, 1.0, 0.4, 1.5]]), np.eye(3)[None], np.array([[0.1, 0.2, 5.0]]))
        options = {}
    else:
        args = (rigid_body, INERTIAS, EYES, OMEGAS)
        options = {"reduced": dict(reconstruct=False), "reconstructed": {}, "composition": dict(order=4)}[case]
    with pytest.raises(_Probed):
        cj.sweep(*args, dt=0.05, n_steps=N_STEPS, chunk_steps=20, fast=True, **options)
    assert seen[0].has_Q == (case != "reduced") and seen[0].facts["order"] == (4 if case == "composition" else 2)


def _top(params):
    return heavy_top(params[:3], params[3])


@pytest.mark.slow  # compiles a lean heavy-top chunk (potential, Q reconstructed): most of a minute
def test_heavy_tops_agree_with_integrate():
    params = np.array([[1.0, 1.0, 0.4, 1.5], [1.0, 1.2, 0.5, 0.8]])
    Q0 = np.stack(
        [np.asarray(cj.lie.so3_exp(jnp.array([0.5, 0.0, 0.0]))), np.asarray(cj.lie.so3_exp(jnp.array([0.2, 0.3, 0.0])))]
    )
    omegas = np.array([[0.1, 0.2, 5.0], [0.3, -0.2, 3.0]])
    res = cj.sweep(_top, params, Q0, omegas, dt=0.01, n_steps=30, chunk_steps=15, fast=True)
    assert res.form == "reduced" and res.fast_chunks == 2 and res.fallback_chunks == 0
    for m in range(2):
        system = _top(params[m])
        sol = cj.integrate(system, jnp.asarray(Q0[m]), jnp.asarray(omegas[m]), dt=0.01, n_steps=30)
        np.testing.assert_allclose(res.final_momentum[m], np.asarray(sol.momentum[-1]), rtol=0, atol=1e-13)
        np.testing.assert_allclose(res.final_Q[m], np.asarray(sol.Q[-1]), rtol=0, atol=1e-13)
        E = np.asarray(cj.diagnostics.energy(system, sol))
        # a difference of energies of size ~10: their round-off (~1e-15) is the tolerance's scale
        np.testing.assert_allclose(res.energy_error[m], np.max(np.abs(E - E[0])), rtol=0, atol=1e-13)


@pytest.mark.slow  # cluster programs on two paths
def test_vortex_cluster_has_no_fast_path_and_agrees():
    # the midpoint full step of point vortices has no fixed-update form yet: the sweep runs the
    # general path (fast_chunks 0) and its answers are integrate's
    G = np.array([1.0, 1.0, -0.5])
    Q0 = np.array([[[1.0, 0.0], [-0.5, 0.8], [-0.4, -0.9]]])
    xi0 = np.zeros_like(Q0)
    assert fast_method(point_vortices(jnp.asarray(G)), jnp.asarray(Q0[0]), jnp.asarray(xi0[0]), {}) is None
    res = cj.sweep(point_vortices, G[None], Q0, xi0, dt=0.05, n_steps=10, fast=True)
    assert res.fast_chunks == 0
    sol = cj.integrate(point_vortices(jnp.asarray(G)), jnp.asarray(Q0[0]), jnp.asarray(xi0[0]), dt=0.05, n_steps=10)
    np.testing.assert_allclose(res.final_p[0], np.asarray(sol.p[-1]), rtol=0, atol=1e-13)


def test_fixed_newton_solve_checks_its_answer():
    # F(z) = z³ + z - c: from a close guess 3 chord updates reach round-off; from a far one they
    # do not, and the status says so (a caller then solves with the general loop)
    c = jnp.array([2.0, 10.0])
    F = lambda z: z**3 + z - c
    root, _ = newton_solve(F, jnp.array([1.0, 2.0]), rtol=0.0, atol=0.0, max_iterations=20)
    near, st, _, _ = fixed_newton_solve(F, root + 1e-5, updates=3, rtol=0.0, atol=0.0)
    assert st.status == Status.SUCCESS
    np.testing.assert_allclose(near, root, rtol=0, atol=1e-14)
    _, st_far, _, _ = fixed_newton_solve(F, root + 0.5, updates=3, rtol=0.0, atol=0.0)
    assert st_far.status == Status.MAX_ITERATIONS
    # derivatives of the root by the implicit function theorem: dz/dc = 1 / (3z² + 1)
    g = jax.grad(
        lambda cc: jnp.sum(fixed_newton_solve(lambda z: z**3 + z - cc, root + 1e-6, updates=3, rtol=0.0, atol=0.0)[0])
    )(c)
    np.testing.assert_allclose(g, 1.0 / (3.0 * root**2 + 1.0), rtol=1e-12)


def test_the_round_off_rule_leaves_out_the_tests_a_zero_tolerance_cannot_pass():
    """`tolerance` of the Python zeros is the Python 0.0, and `converged` then leaves its two
    tests on tol out of the program (fewer operations in every check of a fast step): the same
    verdict as with a traced zero tolerance, on sizes from 0 to overflow, a NaN update included.
    Not compared: max|z| NaN (every caller has stopped as non-finite then), and a previous update
    larger than max(1, max|z|) (after an update of that size the iterate has it), where θ·η can
    underflow and the old estimate accepted an update above round-off."""
    from clebsch_jax.roots.newton import converged, tolerance

    z = jnp.zeros(3)
    assert tolerance(z, 0.0, 0.0) == 0.0 and isinstance(tolerance(z, 0.0, 0.0), float)
    assert not isinstance(tolerance(z, 1e-12, 0.0), float)  # a real tolerance stays an array
    eps = np.finfo(float).eps
    sizes = np.array(
        [0.0, 1e-300, eps, 4 * eps, 8 * eps, 9 * eps, 1e-12, 1e3 * eps, 2e4 * eps, 0.5, 1.0, 3.0, 1e300, np.inf, np.nan]
    )
    eta, prev, zmax = (a.ravel() for a in np.meshgrid(sizes, sizes[:-2], sizes[:-1], indexing="ij"))
    verdict = jax.jit(
        lambda e, p, k, zm, static_zero: converged(e, p, k, 0.0 if static_zero else jnp.zeros(()), z, zm),
        static_argnums=4,
    )
    real = prev <= np.maximum(1.0, zmax)
    eta, prev, zmax = eta[real], prev[real], zmax[real]
    for k in (0, 1, 3):
        kk = jnp.asarray(k, jnp.int32)
        np.testing.assert_array_equal(verdict(eta, prev, kk, zmax, True), verdict(eta, prev, kk, zmax, False))


def test_fixed_newton_in_integrate_reports_unconverged_steps():
    body = rigid_body(jnp.array([0.5, 0.6, 1.0]))
    method = fast_method(body, jnp.eye(3), jnp.array([3.0, 1.0, -2.0]), {"reconstruct": False})
    assert isinstance(method.root_finder, FixedNewton)
    sol = cj.integrate(body, jnp.eye(3), jnp.array([3.0, 1.0, -2.0]), dt=0.6, n_steps=12, method=method, throw=False)
    status = np.asarray(sol.stats.status)
    # the warm-up steps use the general loop and succeed; a later step's check fails
    assert np.all(status[: method.root_finder.warmup] == Status.SUCCESS)
    assert Status.MAX_ITERATIONS in status


def _scalarise_case(x, A):
    M = A @ jnp.outer(x, x) + jnp.eye(3) * x[0]  # dot_general, broadcast, a constant eye

    def body(c, _):
        y = jnp.cross(c, M @ c) * 0.1 + c
        k = jnp.argmax(jnp.abs(y))  # a batched index: handled stacked
        return y / jnp.linalg.norm(y), y[k] + jax.lax.dynamic_slice(y, (jnp.asarray(1),), (1,))[0]

    c, ys = jax.lax.scan(body, x, None, length=5)
    n = jax.lax.while_loop(
        lambda s: s[0] < jnp.abs(c[0]) * 10 + 1, lambda s: (s[0] + 1.0, s[1] * 0.5), (0.0, jnp.sum(c))
    )
    r = jax.lax.cond(x[1] > 0, lambda v: v[::-1], lambda v: -v, c)
    return r, ys, n[1], jnp.sum(M, axis=0)


@pytest.mark.parametrize("loops_only", [True, False])
def test_scalarise_matches_vmap(loops_only):
    f = _scalarise_case
    xs = jnp.asarray(np.random.default_rng(0).normal(size=(7, 3)))
    A = jnp.asarray(np.random.default_rng(1).normal(size=(3, 3)))
    want = jax.vmap(f, in_axes=(0, None))(xs, A)
    run = scalarise(f, in_axes=(0, None), loops_only=loops_only)
    got = jax.jit(run)(xs, A)
    for w, g in zip(jax.tree_util.tree_leaves(want), jax.tree_util.tree_leaves(got)):
        np.testing.assert_allclose(g, w, rtol=1e-14, atol=1e-14)
    # the 3x3 product and the column sums outside the loop: stacked (sums over a member axis),
    # or, rows everywhere, sums of row products
    outside = {e.primitive.name for e in jax.make_jaxpr(run)(xs, A).jaxpr.eqns}
    assert bool(outside & {"dot_general", "reduce_sum"}) == loops_only


# -- the lean chunk (`clebsch_jax.batching.lean`): no invariant but the energy, nothing saved ------

LEAN = dict(n_steps=N_STEPS, chunk_steps=20, batch_size=4, reconstruct=False)


@pytest.mark.slow  # compiles the lean and the general chunk (the lean chunk is opt-in: fast=True)
def test_lean_sweep_agrees_with_the_general_one_and_falls_back_like_it():
    from clebsch_jax.batching import chunks_xla

    general_programs = chunks_xla.run_chunk._cache_size()
    lean = cj.sweep(rigid_body, INERTIAS, EYES, OMEGAS, dt=0.05, fast=True, **LEAN)
    assert lean.fast_chunks == 2 and lean.fallback_chunks == 0
    # no check failed: the general chunk program was not even compiled
    assert chunks_xla.run_chunk._cache_size() == general_programs
    general = cj.sweep(rigid_body, INERTIAS, EYES, OMEGAS, dt=0.05, **LEAN)
    assert np.all(lean.succeeded) and np.all(general.succeeded)
    for key in ("final_momentum", "final_xi", "final_p", "final_t", "energy_error"):
        # the same steps and nodes to round-off (Newton's last updates and the hand-over differ)
        np.testing.assert_allclose(getattr(lean, key), getattr(general, key), rtol=0, atol=1e-13, err_msg=key)
    assert np.max(lean.max_residual) < 1e-14
    for m in range(4):
        mu, energy_error = reference(rigid_body(INERTIAS[m]), np.eye(3), OMEGAS[m], 0.05, N_STEPS, reconstruct=False)
        np.testing.assert_allclose(lean.final_momentum[m], mu, rtol=0, atol=1e-13)
        assert abs(lean.energy_error[m] - energy_error) <= 1e-13

    # failures: a NaN velocity and a negative moment of inertia (invalid input at step 0) and
    # steps too large for the fixed updates; each chunk with a failure runs again on the
    # general path, and the table is the general one
    omegas, dts, inertias = 3.0 * OMEGAS, np.array([0.6, 0.05, 0.05, 0.05]), INERTIAS.copy()
    omegas[1] = np.nan
    inertias[3, 0] = -1.0
    res = cj.sweep(rigid_body, inertias, EYES, omegas, dt=dts, fast=True, **LEAN)
    ref = cj.sweep(rigid_body, inertias, EYES, omegas, dt=dts, **LEAN)
    assert res.fallback_chunks >= 1
    np.testing.assert_array_equal(res.status, ref.status)
    np.testing.assert_array_equal(res.failed_step, ref.failed_step)
    assert res.status[1] == res.status[3] == Status.INVALID_INPUT
    ok = ref.status == Status.SUCCESS
    np.testing.assert_allclose(res.final_momentum[ok], ref.final_momentum[ok], rtol=0, atol=1e-12)


def test_auto_takes_the_lean_chunk_only_for_large_sweeps():
    from clebsch_jax.batching.choose import AUTO_LEAN_MIN_MEMBER_STEPS, AUTO_LEAN_MIN_MEMBERS, auto_lean

    assert not auto_lean(AUTO_LEAN_MIN_MEMBERS - 1, 10**6)  # short rows: the compile is not repaid
    assert not auto_lean(AUTO_LEAN_MIN_MEMBERS, 10)  # long rows, little work: the compile is not repaid
    assert auto_lean(AUTO_LEAN_MIN_MEMBERS, -(-AUTO_LEAN_MIN_MEMBER_STEPS // AUTO_LEAN_MIN_MEMBERS))
    assert auto_lean(10**5, 10**3)


@pytest.mark.slow  # compiles the lean chunk of the other lean tests (the same configuration)
def test_auto_runs_the_lean_chunk_of_a_large_sweep_and_the_general_loop_otherwise(monkeypatch):
    from clebsch_jax.batching import choose

    lean = cj.sweep(rigid_body, INERTIAS, EYES, OMEGAS, dt=0.05, fast=True, **LEAN)
    # fast="auto" chooses among XLA's paths (the native backend, the default, is tests/test_native.py's)
    small = cj.sweep(rigid_body, INERTIAS, EYES, OMEGAS, dt=0.05, backend="xla", **LEAN)
    assert small.fast_chunks == 0
    # the same four members counted as a large sweep: "auto" runs the lean chunk, to the bit
    monkeypatch.setattr(choose, "AUTO_LEAN_MIN_MEMBERS", 4)
    monkeypatch.setattr(choose, "AUTO_LEAN_MIN_MEMBER_STEPS", 4 * N_STEPS)
    auto = cj.sweep(rigid_body, INERTIAS, EYES, OMEGAS, dt=0.05, backend="xla", **LEAN)
    assert auto.fast_chunks == 2 and auto.fallback_chunks == 0
    for key in ("final_momentum", "final_xi", "final_p", "energy_error", "newton_iterations"):
        np.testing.assert_array_equal(getattr(auto, key), getattr(lean, key), err_msg=key)
    # where the lean chunk does not apply (an invariant besides the energy), "auto" keeps the
    # general loop, as fast=False: the recording fast chunk is not faster than it
    inv = {"casimir": lambda system, sol: jnp.sum(sol.momentum**2, axis=-1)}
    assert cj.sweep(rigid_body, INERTIAS, EYES, OMEGAS, dt=0.05, invariants=inv, **LEAN).fast_chunks == 0


@pytest.mark.slow  # the lean chunk of the tests above (the same configuration), written to a Zarr store
def test_a_stored_lean_sweep_gives_the_in_process_table_and_reopens(tmp_path):
    # the path a large stored sweep takes under fast="auto": same program, same rows, to the bit
    pytest.importorskip("zarr")
    kept = cj.sweep(rigid_body, INERTIAS, EYES, OMEGAS, dt=0.05, fast=True, **LEAN)
    store = tmp_path / "lean.zarr"
    written = cj.sweep(rigid_body, INERTIAS, EYES, OMEGAS, dt=0.05, fast=True, store=store, **LEAN)
    reopened = cj.open_sweep(store)
    assert written.fast_chunks == 2
    # resumed by the default "auto" (four members are below its thresholds): the stored path
    resumed = cj.sweep(rigid_body, INERTIAS, EYES, OMEGAS, dt=0.05, store=store, **LEAN)
    for res in (written, reopened, resumed):
        for key in ("status", "final_momentum", "final_xi", "final_p", "energy_error", "newton_iterations"):
            np.testing.assert_array_equal(getattr(res, key), getattr(kept, key), err_msg=key)


@pytest.mark.slow  # two sweeps and eight member chunks evaluated op by op: half a minute
def test_lean_chunk_carries_what_the_general_chunk_carries():
    """One member, no batching: the lean chunk's carry (state, running energy-check maxima,
    drift) against the general chunk's, for a first and a later chunk."""
    import dataclasses

    from clebsch_jax.batching import chunks_xla

    res = {}
    for fast in (False, True):
        cap = {}
        real = chunks_xla.run_fast_chunk if fast else chunks_xla.run_chunk

        def spy(cfg, *args, real=real, cap=cap):
            cap.setdefault("calls", []).append((cfg, args))
            return real(cfg, *args)

        name = "run_fast_chunk" if fast else "run_chunk"
        setattr(chunks_xla, name, spy)
        try:
            cj.sweep(rigid_body, INERTIAS, EYES, OMEGAS, dt=0.05, fast=fast, **LEAN)
        finally:
            setattr(chunks_xla, name, real)
        res[fast] = cap["calls"]
    for (cfg_g, args_g), (cfg_f, args_f) in zip(res[False], res[True]):
        general = dataclasses.replace(cfg_f, fast_method=None, lean=False)
        fast = dataclasses.replace(general, options=(("check_energy", False), ("method", cfg_f.fast_method)))
        params, carry, dt, shared, first, offset = args_g
        one = lambda c, j: jax.tree_util.tree_map(lambda a: a[j], c)
        for j in range(4):
            g, _ = chunks_xla._member_chunk(general, params[j], shared, one(carry, j), dt[j], first, offset)
            f, _ = chunks_xla._lean_member_chunk(fast, params[j], shared, one(carry, j), dt[j], first, offset)
            for name in ("Q", "P", "xi", "t", "momentum", "final_xi", "energy_change", "energy_size", "max_residual"):
                np.testing.assert_allclose(getattr(f, name), getattr(g, name), rtol=1e-12, atol=1e-14, err_msg=name)
            np.testing.assert_allclose(f.drift["energy"], g.drift["energy"], rtol=1e-9, atol=1e-15)
            np.testing.assert_allclose(f.initial["energy"], g.initial["energy"], rtol=0, atol=1e-14)
            assert int(f.status) == int(g.status) == Status.SUCCESS


def _quartic_body(inertia):
    """A rigid body whose kinetic energy has a quartic term: l = ½ξ·𝕀ξ + (ξ·ξ)²/8, so that the
    nodal relation is nonlinear (its Hessian depends on ξ)."""
    return cj.ClebschSystem(
        lagrangian=lambda xi, Q: 0.5 * jnp.sum(inertia * xi * xi) + 0.125 * jnp.sum(xi * xi) ** 2,
        velocity_map=lambda xi, Q: Q @ cj.lie.hat(xi),
        derivative_map=cj.cayley,
    )


@pytest.mark.slow  # compiles the lean and the general chunk of a new system
def test_lean_sweep_of_a_nonlinear_nodal_relation_falls_back_then_gives_up():
    # the lean chunk's nodal solves (two chord updates) reach round-off where l is quadratic in
    # ξ (the rigid body, the heavy top); here it is not, every check fails, and after
    # FAST_GIVE_UP rejected calls in a row the batch runs the general path only: the third
    # call (of LEAN_CHUNKS chunks) is not tried. A rejected call's chunks are rerun one by one,
    # so the table is the general path's to the bit.
    from clebsch_jax.batching.schedule import FAST_GIVE_UP, LEAN_CHUNKS

    run = {**LEAN, "chunk_steps": 5, "n_steps": 3 * LEAN_CHUNKS * 5}
    lean = cj.sweep(_quartic_body, INERTIAS, EYES, OMEGAS, dt=0.05, fast=True, **run)
    general = cj.sweep(_quartic_body, INERTIAS, EYES, OMEGAS, dt=0.05, backend="xla", **run)
    assert FAST_GIVE_UP == 2 and lean.fast_chunks == lean.fallback_chunks == 2 * LEAN_CHUNKS
    assert np.all(lean.succeeded) and np.all(general.succeeded)
    for key in ("final_momentum", "final_xi", "final_p", "energy_error", "newton_iterations"):
        np.testing.assert_array_equal(getattr(lean, key), getattr(general, key), err_msg=key)


def test_lean_calls_cover_several_chunks_of_one_length():
    # the lean chunk covers up to LEAN_CHUNKS chunks per call, as many as divide the number of
    # full chunks (one compiled length), and a short last chunk alone; other paths one each
    from clebsch_jax.batching.config import Run
    from clebsch_jax.batching.schedule import LEAN_CHUNKS, _calls

    def lengths(n_steps, chunk_steps, lean=True):
        run = Run(n_steps, chunk_steps, None, None, {}, False, [None])
        calls = _calls(run, lean)
        assert [c for call in calls for c in call] == run.chunks  # every chunk once, in order
        return [sum(n for _, n in call) for call in calls]

    assert LEAN_CHUNKS == 4
    assert lengths(800, 100) == [400, 400]
    assert lengths(1000, 100) == [200] * 5
    assert lengths(250, 100) == [200, 50]
    assert lengths(700, 100) == [100] * 7
    assert lengths(800, 100, lean=False) == [100] * 8


@pytest.mark.slow  # compiles the lean and the general chunk of an order-4 composition
def test_lean_sweep_of_a_composition_agrees_with_the_general_one():
    # the lean chunk steps through wrappers (Composed of the reduced step): same answers
    lean = cj.sweep(rigid_body, INERTIAS, EYES, OMEGAS, dt=0.05, fast=True, order=4, **{**LEAN, "reconstruct": True})
    general = cj.sweep(rigid_body, INERTIAS, EYES, OMEGAS, dt=0.05, order=4, **{**LEAN, "reconstruct": True})
    assert lean.order == 4 and lean.fast_chunks == 2 and lean.fallback_chunks == 0
    for key in ("final_momentum", "final_Q", "final_xi", "energy_error"):
        np.testing.assert_allclose(getattr(lean, key), getattr(general, key), rtol=0, atol=1e-13, err_msg=key)


def test_full_newton_updates_converge_from_a_far_guess():
    # refresh: a fresh Jacobian at every update (FixedNewton(refresh=True)), quadratic convergence
    c = jnp.array([2.0, 10.0])
    F = lambda z: z**3 + z - c
    root, _ = newton_solve(F, jnp.array([1.0, 2.0]), rtol=0.0, atol=0.0, max_iterations=20)
    _, chord, _, _ = fixed_newton_solve(F, root + 0.5, updates=6, rtol=0.0, atol=0.0)
    z, full, _, _ = fixed_newton_solve(F, root + 0.5, updates=6, rtol=0.0, atol=0.0, refresh=True)
    assert chord.status == Status.MAX_ITERATIONS and full.status == Status.SUCCESS
    np.testing.assert_allclose(z, root, rtol=0, atol=1e-14)


def test_rounds_of_chord_updates_converge_where_one_round_does_not():
    # rounds: a fresh Jacobian and `updates` chord updates per round, in one loop whose trip
    # count may be traced (FixedNewton.warmup_rounds: more rounds on the warm-up steps only)
    c = jnp.array([2.0, 10.0])
    F = lambda z: z**3 + z - c
    root, _ = newton_solve(F, jnp.array([1.0, 2.0]), rtol=0.0, atol=0.0, max_iterations=20)
    _, one, _, _ = fixed_newton_solve(F, root + 0.5, updates=2, rtol=0.0, atol=0.0)
    assert one.status == Status.MAX_ITERATIONS

    @jax.jit
    def solve(rounds):
        return fixed_newton_solve(F, root + 0.5, updates=2, rtol=0.0, atol=0.0, rounds=rounds)[:2]

    z, st = solve(5)
    assert st.status == Status.SUCCESS and st.iterations == 10 and st.jacobians == 5
    np.testing.assert_allclose(z, root, rtol=0, atol=1e-14)
    assert solve(1)[1].status == Status.MAX_ITERATIONS  # the same program, one round: not converged
    # under vmap with a batched guess and grad through the implicit rule
    z = jax.vmap(lambda g: fixed_newton_solve(F, g, updates=2, rtol=0.0, atol=0.0, rounds=5)[0])(
        jnp.stack([root + 0.5, root - 0.3])
    )
    np.testing.assert_allclose(z, jnp.stack([root, root]), rtol=0, atol=1e-14)
    dz = jax.grad(
        lambda s: fixed_newton_solve(
            lambda z: z**3 + z - s * c, root, updates=2, rtol=0.0, atol=0.0, rounds=jnp.asarray(2)
        )[0][0]
    )(1.0)
    np.testing.assert_allclose(dz, c[0] / (3 * root[0] ** 2 + 1), rtol=1e-12)

    # FixedNewton: warm-up steps by rounds, later steps by one round, one solve compiled
    finder = FixedNewton(updates=2, warmup=3, warmup_rounds=5)
    step = jax.jit(lambda n: finder.solve_reusing(F, root + 0.5, None, False, step=n)[1].status)
    assert step(2) == Status.SUCCESS and step(3) == Status.MAX_ITERATIONS
    with pytest.raises(ValueError, match="warmup_rounds"):
        FixedNewton(warmup_rounds=-1)


def test_scalarise_unrolls_loops_inside_loops_but_not_a_short_loop_outside():
    # a short scan outside every loop (once per call) stays a loop: unrolled, XLA would compile
    # every copy; the same scan inside a loop body (once per step) is unrolled, which keeps its
    # rows in place
    from clebsch_jax.batching.scalarise import SCAN_UNROLL, SHORT_SCAN

    def short(x):
        return jax.lax.fori_loop(0, 3, lambda i, c: c * 0.5 + x, x)

    def f(x):
        return short(x) + jax.lax.fori_loop(0, 10, lambda i, c: short(c) * 0.1, x)

    xs = jnp.arange(12.0).reshape(4, 3)
    np.testing.assert_allclose(jax.jit(scalarise(f, loops_only=False))(xs), jax.vmap(f)(xs), rtol=1e-15)
    jaxpr = jax.make_jaxpr(scalarise(f, loops_only=False))(xs).jaxpr
    outer = [e for e in jaxpr.eqns if e.primitive.name == "scan"]
    assert sorted((e.params["length"], e.params["unroll"]) for e in outer) == [(3, 1), (10, SCAN_UNROLL)]
    assert 3 <= SHORT_SCAN < 10
    long_loop = next(e for e in outer if e.params["length"] == 10)
    inner = [e for e in long_loop.params["jaxpr"].jaxpr.eqns if e.primitive.name == "scan"]
    assert [e.params["unroll"] for e in inner] == [3]


def test_scalarise_keeps_optimization_barriers():
    def f(x):
        a, b = jax.lax.optimization_barrier((x * x, jnp.sum(x)))
        return jax.lax.fori_loop(0, 3, lambda i, c: jax.lax.optimization_barrier(c * 0.5 + a * b), x)

    xs = jnp.arange(12.0).reshape(4, 3)
    np.testing.assert_allclose(jax.jit(scalarise(f))(xs), jax.vmap(f)(xs), rtol=1e-15)
    assert "optimization_barrier" in str(jax.make_jaxpr(scalarise(f))(xs))


# Unbatched operations on values known at trace time, one of each kind `scalarise` folds in NumPy
FOLDED = {
    "arithmetic": lambda a, b: (a + b, a - b, a * b, a / b, -a, jnp.maximum(a, b), jnp.minimum(a, b), jnp.abs(b)),
    "comparisons": lambda a, b: (a == b, a != b, a < b, a <= b, a > b, a >= b, (a < b) & (a > 0), (a < b) | ~(b > 0)),
    "select": lambda a, b: (jnp.where(a > b, a, b), jax.lax.select_n(jnp.arange(3) % 2 == 0, a, b)),
    "layout": lambda a, b: (
        jnp.eye(3, dtype=a.dtype),
        jnp.broadcast_to(a[:, None], (3, 4)),
        a.reshape(1, 3),
        jnp.squeeze(a.reshape(1, 3), 0),
        a[1:],
        a[::2],
        jnp.outer(a, b).T,
        a[::-1],
        jnp.concatenate([a, b]),
        jnp.stack([a, b], 1),
        *jnp.split(a, 3),
    ),
    "types": lambda a, b: (a.astype(jnp.int32), jnp.arange(4), (a > 0).astype(a.dtype)),
    "ieee": lambda a, b: (a * jnp.inf * 0.0, a / (b * 0.0), jnp.maximum(a * jnp.nan, b)),  # NaN, ±inf, silently
}


@pytest.mark.parametrize("name", sorted(FOLDED))
def test_scalarise_folds_known_values_in_numpy_exactly(name):
    """Every operation of `FOLDED[name]` on known operands gives, folded in NumPy, JAX's own
    result to the bit (the folding rules are exact: rounded IEEE arithmetic and re-indexing)."""
    from clebsch_jax.batching.rules import bind
    from clebsch_jax.batching.rows import numpy_fold

    a, b = np.array([0.3, -1.7, 2.5]), np.array([1.1, -1.7, 1e-3])
    jaxpr = jax.make_jaxpr(FOLDED[name])(a, b).jaxpr
    env = {jaxpr.invars[0]: a, jaxpr.invars[1]: b}
    read = lambda v: np.asarray(v.val) if isinstance(v, jax.extend.core.Literal) else env[v]
    folded = 0
    for eqn in jaxpr.eqns:
        known = [read(v) for v in eqn.invars]
        with jax.ensure_compile_time_eval():
            want = [np.asarray(o) for o in bind(eqn, [jnp.asarray(k) for k in known])]
        got = numpy_fold(eqn, known)
        if got is not None:
            folded += 1
            for g, w in zip(got, want):
                g = np.asarray(g, dtype=w.dtype)
                assert g.shape == w.shape and np.array_equal(g, w, equal_nan=g.dtype.kind == "f"), eqn
        for v, w in zip(eqn.outvars, want):
            env[v] = w
    assert folded >= len(jaxpr.eqns) - 2  # at most the `jit` wrappers of jnp.where and split are not folded


def test_scalarise_traces_known_values_without_compiling():
    """Tracing a member program whose loop builds constants (an identity, slices, a split) runs
    no eager JAX operation: `scalarise` folds them in NumPy, where each would otherwise be
    dispatched and, per new shape, compiled on its own."""

    def f(x):
        def body(c, _):
            e = jnp.eye(3, dtype=c.dtype)
            w = jnp.stack(jnp.split(jnp.arange(3.0), 3))[:, 0]
            return e[:, 1:] @ c[:2] * 0.25 + c * 0.5 + w[::-1] * 1e-3, None

        return jax.lax.scan(body, x, None, length=3)[0]

    xs = jnp.asarray(np.random.default_rng(2).normal(size=(5, 3)))
    with compiles_recorded() as compiles:
        jax.jit(scalarise(f)).lower(xs)
    assert compiles == []
    np.testing.assert_allclose(jax.jit(scalarise(f))(xs), jax.vmap(f)(xs), rtol=1e-15)
