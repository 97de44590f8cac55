r"""`integrate` on the native backend (issue "Native kernels", item 3): the chunk's steps, the
nodes they leave, their nodal velocities and energies made by one native loop kernel
(`clebsch_jax.march.native_chunk`), the rest of the march unchanged.

The XLA chunk (`backend="xla"`) is an independent evaluator of the same program: the two must
give the same `Solution` — values to 1e-12 relative, the same statuses, failed steps, valid
nodes and NaN after a failure — and the native one the same bits from run to run. Newton
updates are compared with a tolerance: both iterate to round-off (rtol = atol = 0), and where
the two evaluators' last bits differ (XLA's own contractions and transcendental functions), a
solve can stop one update earlier or later.
"""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import clebsch_jax as cj
from clebsch_jax import models, native
from clebsch_jax.native import NativeFallbackWarning

from .systems import kepler, translation

pytestmark = pytest.mark.skipif(not native.available(), reason="llvmlite cannot be imported")

FIELDS = ("Q", "p", "xi", "xi_step", "momentum", "P")
INERTIA = jnp.array([2.0, 1.0, 2.0 / 3.0])
XI0 = jnp.array([1.3, 0.8, -0.4])
TOP = models.heavy_top(jnp.array([1.0, 1.0, 0.4]), 1.5)
TOP_Q0, TOP_XI0 = cj.lie.so3_exp(jnp.array([0.5, 0.0, 0.0])), jnp.array([0.3, -0.2, 2.0])
GAMMA = jnp.array([1.0, 0.5])  # two vortices: a small full step (the compile is what costs)
VORTEX_Q0 = jnp.array([[0.0, 1.0], [0.0, -1.0]])


def _both(*args, **options):
    """The run on each backend, no fallback warning on the native one."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", NativeFallbackWarning)
        fast = cj.integrate(*args, backend="native", throw=False, **options)
    return fast, cj.integrate(*args, backend="xla", throw=False, **options)


def _same_solution(fast, xla, rtol=1e-12, update_slack=0.05):
    """The two runs' `Solution`s agree: facts, statuses, failed step, valid nodes, NaN where
    XLA's is NaN, values to `rtol` relative to each field's size, and Newton updates within
    `update_slack` of XLA's in total (module docstring)."""
    assert (fast.form, fast.method, fast.order) == (xla.form, xla.method, xla.order)
    assert int(fast.result) == int(xla.result) and int(fast.failed_step) == int(xla.failed_step)
    for stats in ("stats", "nodal_stats"):
        np.testing.assert_array_equal(getattr(fast, stats).status, getattr(xla, stats).status)
        a, b = (np.asarray(getattr(s, stats).iterations).sum() for s in (fast, xla))
        assert abs(int(a) - int(b)) <= update_slack * max(int(b), 1), (stats, a, b)
    np.testing.assert_array_equal(fast.valid, xla.valid)
    np.testing.assert_array_equal(fast.ts, xla.ts)
    for name in FIELDS:
        a, b = getattr(fast, name), getattr(xla, name)
        assert (a is None) == (b is None), name
        if b is None:
            continue
        a, b = np.asarray(a), np.asarray(b)
        np.testing.assert_array_equal(np.isnan(a), np.isnan(b), err_msg=name)
        if np.all(np.isnan(b)):
            continue
        size = np.nanmax(np.abs(b))
        np.testing.assert_allclose(a, b, rtol=0, atol=rtol * size, equal_nan=True, err_msg=name)


def _bitwise(a, b):
    for name in FIELDS + ("valid",):
        x, y = getattr(a, name), getattr(b, name)
        if x is not None:
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y), err_msg=name)
    for x, y in zip(jax.tree_util.tree_leaves(a.stats), jax.tree_util.tree_leaves(b.stats)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_heavy_top_default_is_xlas_solution_and_repeats_bit_for_bit():
    """The heavy top's default (the reduced left step paired with its adjoint), over more steps
    than one native chunk holds (several kernel calls, the carry handed over between them)."""
    n = 3 * 1024 + 17
    fast, xla = _both(TOP, TOP_Q0, TOP_XI0, dt=0.01, n_steps=n)
    assert fast.form == "reduced" and int(fast.result) == cj.Status.SUCCESS
    assert np.asarray(fast.Q).shape == (n + 1, 3, 3)
    _same_solution(fast, xla)
    again = cj.integrate(TOP, TOP_Q0, TOP_XI0, dt=0.01, n_steps=n, backend="native")
    _bitwise(fast, again)
    # the march the Solution records conserves what the method conserves: |μ|² (a Casimir of the
    # heavy top's reduced equations is |Γ|², here Γ = Qᵀe₃ with Q orthogonal) to round-off
    Q = np.asarray(fast.Q)
    np.testing.assert_allclose(np.einsum("nij,nik->njk", Q, Q), np.broadcast_to(np.eye(3), Q.shape), atol=1e-12)


def test_a_run_of_several_native_chunks_is_xlas(monkeypatch):
    """More steps than two native chunks hold: full chunks and a short last one, whose records
    are those of its steps alone, joined into the Solution as XLA's chunks are. (Native chunks
    of 8 XLA chunks here, not the default's: the same joins, over a run XLA makes quickly.)"""
    from clebsch_jax.march import scan
    from clebsch_jax.march.scan import chunk_length

    monkeypatch.setattr(scan, "NATIVE_CHUNK_FACTOR", 8)
    chunk = chunk_length(TOP_Q0, TOP_XI0) * 8
    n = 2 * chunk + 3
    fast, xla = _both(TOP, TOP_Q0, TOP_XI0, dt=0.01, n_steps=n)
    assert np.asarray(fast.Q).shape == (n + 1, 3, 3) and np.asarray(fast.stats.status).shape == (n,)
    _same_solution(fast, xla, rtol=1e-9)  # the two evaluators' last bits drift apart over 16 000 steps
    shorter = cj.integrate(TOP, TOP_Q0, TOP_XI0, dt=0.01, n_steps=chunk + 5, backend="native")
    for name in ("Q", "xi", "momentum", "valid"):  # its first chunk and node are the longer run's, bit for bit
        np.testing.assert_array_equal(np.asarray(getattr(shorter, name)), np.asarray(getattr(fast, name))[: chunk + 6])
    np.testing.assert_array_equal(np.asarray(shorter.stats.iterations), np.asarray(fast.stats.iterations)[: chunk + 5])


def _kepler_of(k):
    """Kepler's problem with the constant `k` held in the Lagrangian's closure (a Python number)."""
    return cj.ClebschSystem(
        lagrangian=lambda xi, q: 0.5 * jnp.sum(xi**2) + k / jnp.sqrt(jnp.sum(q**2)),
        velocity_map=translation,
        derivative_map=cj.forward_difference,
    )


def test_nothing_found_for_one_system_is_used_for_another_of_the_same_shapes():
    """What a call finds once (the march's kernel, the map checks) is not handed to another
    system of the same shapes: another heavy top, and a Lagrangian whose closure holds another
    number, each give their own XLA Solution; and the value checks still refuse bad values
    after those calls."""
    other = models.heavy_top(jnp.array([1.0, 2.0, 0.5]), 0.7)
    first, _ = _both(TOP, TOP_Q0, TOP_XI0, dt=0.01, n_steps=50)
    fast, xla = _both(other, TOP_Q0, TOP_XI0, dt=0.01, n_steps=50)
    assert not np.allclose(np.asarray(first.Q), np.asarray(fast.Q))
    _same_solution(fast, xla)
    q0, v0 = np.array([1.0, 0.0]), np.array([0.0, 1.1])
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="lagrangian: a function with the code")  # remade: compiled again
        weak, _ = _both(_kepler_of(1.0), q0, v0, dt=0.05, n_steps=40)
        strong, strong_xla = _both(_kepler_of(2.0), q0, v0, dt=0.05, n_steps=40)
    assert not np.allclose(np.asarray(weak.Q), np.asarray(strong.Q))
    _same_solution(strong, strong_xla)
    with pytest.raises(ValueError, match="dt: must be positive"):
        cj.integrate(other, TOP_Q0, TOP_XI0, dt=-0.01, n_steps=50)
    with pytest.raises(ValueError, match="xi0: contains non-finite"):
        cj.integrate(other, TOP_Q0, TOP_XI0.at[0].set(jnp.nan), dt=0.01, n_steps=50)
    with pytest.raises(ValueError, match="Q0"):
        cj.integrate(other, 2.0 * TOP_Q0, TOP_XI0, dt=0.01, n_steps=50)


def test_each_calls_dt_and_t0_are_its_own():
    """dt and t0 given as Python numbers (kept on the device by value, `float_array`): each call
    marches with its own, on both backends."""
    for dt, t0 in ((0.01, 0.0), (0.02, 1.0), (0.01, -0.0), (0.02, 1.0)):
        fast, xla = _both(TOP, TOP_Q0, TOP_XI0, dt=dt, t0=t0, n_steps=20)
        np.testing.assert_allclose(np.asarray(fast.ts), t0 + dt * np.arange(21), rtol=1e-15)
        _same_solution(fast, xla)
    slower, _ = _both(TOP, TOP_Q0, TOP_XI0, dt=0.01, n_steps=20)
    assert not np.allclose(np.asarray(slower.Q)[-1], np.asarray(fast.Q)[-1])


def test_rigid_body_reduced_step_matches_xla():
    fast, xla = _both(models.rigid_body(INERTIA), jnp.eye(3), XI0, dt=0.1, n_steps=200)
    assert fast.form == "reduced"
    _same_solution(fast, xla)


@pytest.mark.slow  # the full march's native loop kernel; the rigid body's stays in the default run
def test_point_vortices_full_midpoint_step_matches_xla():
    """A degenerate Lagrangian (no nodal velocities solved) with the full midpoint step."""
    system = models.point_vortices(GAMMA)
    fast, xla = _both(system, VORTEX_Q0, models.vortex_velocity(GAMMA, VORTEX_Q0), dt=0.05, n_steps=60)
    assert fast.form == "full" and fast.xi is None  # degenerate: Lemma 7 gives no nodal velocity
    _same_solution(fast, xla)


@pytest.mark.slow  # the Gauss-Legendre step compiled on both backends; CI runs it
def test_gauss_legendre_matches_xla():
    fast, xla = _both(models.rigid_body(INERTIA), jnp.eye(3), XI0, dt=0.1, n_steps=60, scheme="gauss", order=4)
    assert fast.scheme == "gauss"
    _same_solution(fast, xla)


@pytest.mark.slow  # a Gauss-Legendre step compiled on both backends; the energy check's failure is in the default run
def test_a_solve_that_fails_mid_run_fails_at_the_same_step():
    """Gauss–Legendre order 4 near its stage iteration's limit (tests/test_sweep_agreement.py's
    scene, member 13): the stage iteration does not converge at step 2 on either backend; the
    later steps are SKIPPED and the nodes after it NaN."""
    Pi = np.random.default_rng(1).normal(size=(16, 3))
    Pi = jnp.asarray(Pi[13] / np.linalg.norm(Pi[13]))
    Q0, P0 = models.rigid_body_vector_start(Pi)
    system = models.rigid_body_vector(INERTIA)
    fast, xla = _both(system, Q0, Pi / INERTIA, P0=P0, dt=1.0, n_steps=12, scheme="gauss", order=4)
    step = int(xla.failed_step)
    assert int(xla.result) not in (cj.Status.SUCCESS, cj.Status.ENERGY_JUMP) and step > 0
    _same_solution(fast, xla)
    assert np.all(np.isnan(np.asarray(fast.Q)[step + 1 :]))
    assert np.all(np.asarray(fast.stats.status)[step + 1 :] == cj.Status.SKIPPED)


def test_the_energy_check_fails_the_same_step():
    """A particle falling into a 1/r singularity with the left principle (tests/test_step_error.py):
    ENERGY_JUMP at the step that leaves the motion, on both backends."""
    system = cj.ClebschSystem(lagrangian=kepler, velocity_map=translation, derivative_map=cj.forward_difference)
    fast, xla = _both(system, np.array([2.0, 0.0]), np.array([0.0, 0.1]), dt=0.1, n_steps=60, scheme="left")
    assert int(xla.result) == cj.Status.ENERGY_JUMP and int(xla.failed_step) == 30
    _same_solution(fast, xla)


def test_one_kernel_serves_every_n_steps(tmp_path, monkeypatch):
    """The loop kernel takes its iterations as an argument and is keyed without the number of
    steps (`native_chunk.native_loop`): runs of 20, 45 and 60 steps (native chunks of 16, so
    short last chunks of 4, 13 and 12 steps) trace and compile one kernel. The shorter run is
    the longer one's beginning to the bit, and the two runs past the energy check's failure at
    step 30 report it alike (the falling particle of
    `test_the_energy_check_fails_the_same_step`), as XLA does."""
    from clebsch_jax.march import native_chunk, scan
    from clebsch_jax.native import kernel

    monkeypatch.setenv("CLEBSCH_JAX_NATIVE_CACHE", str(tmp_path))
    monkeypatch.setattr(native_chunk, "_LOOPS", {})
    monkeypatch.setattr(scan, "CHUNK_STEPS", 16)
    monkeypatch.setattr(scan, "NATIVE_CHUNK_FACTOR", 1)
    compiled, traced = [], []
    real, body = kernel.compile_ir, native_chunk._stream_body
    monkeypatch.setattr(kernel, "compile_ir", lambda text: compiled.append(1) or real(text))
    monkeypatch.setattr(native_chunk, "_stream_body", lambda *a: traced.append(1) or body(*a))
    system = cj.ClebschSystem(lagrangian=kepler, velocity_map=translation, derivative_map=cj.forward_difference)
    args = (system, np.array([2.0, 0.0]), np.array([0.0, 0.1]))
    run = lambda n: cj.integrate(*args, dt=0.1, n_steps=n, scheme="left", backend="native", throw=False)  # noqa: E731
    short, failed, longer = run(20), run(45), run(60)
    assert len(compiled) == 1 and len(traced) == 1 and len(native_chunk._LOOPS) == 1
    assert int(short.result) == cj.Status.SUCCESS
    assert (int(failed.result), int(failed.failed_step)) == (int(longer.result), int(longer.failed_step))
    _same_solution(failed, cj.integrate(*args, dt=0.1, n_steps=45, scheme="left", backend="xla", throw=False))
    for name in ("Q", "p", "xi", "momentum", "valid"):
        np.testing.assert_array_equal(np.asarray(getattr(short, name)), np.asarray(getattr(longer, name))[:21])
    for name in ("xi_step", "P"):
        np.testing.assert_array_equal(np.asarray(getattr(short, name)), np.asarray(getattr(longer, name))[:20])
    for a, b in zip(jax.tree_util.tree_leaves(short.stats), jax.tree_util.tree_leaves(longer.stats)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b)[:20])
    for name in FIELDS + ("valid", "ts"):  # past the failure the two failed runs agree too
        a, b = getattr(failed, name), getattr(longer, name)
        if a is not None:
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b)[: np.shape(a)[0]], err_msg=name)


def test_the_first_step_probe_runs_on_the_native_chunk():
    """Kepler at the perihelion of e = 0.95 with a step far longer than the passage: step 0
    converges to a spurious root that only the two half steps reveal (tests/test_spheres.py)."""
    system = cj.ClebschSystem(lagrangian=kepler, velocity_map=translation, derivative_map=cj.forward_difference)
    e = 0.95
    q0, v0 = np.array([1.0 - e, 0.0]), np.array([0.0, np.sqrt((1.0 + e) / (1.0 - e))])
    fast, xla = _both(system, q0, v0, dt=0.05, n_steps=3)
    assert int(fast.result) == cj.Status.FIRST_STEP and int(fast.failed_step) == 0
    _same_solution(fast, xla)


def test_continuation_equals_the_unbroken_native_run():
    """`continue_from` hands the march state over: two native calls make the steps of one."""
    whole = cj.integrate(TOP, TOP_Q0, TOP_XI0, dt=0.05, n_steps=80, backend="native")
    first = cj.integrate(TOP, TOP_Q0, TOP_XI0, dt=0.05, n_steps=30, backend="native")
    start = cj.continue_from(TOP, first)
    continued = lambda backend: cj.integrate(
        TOP, start.Q0, start.xi0, P0=start.P0, t0=start.t0, dt=0.05, n_steps=50,
        march_state=start.march_state, backend=backend,
    )  # fmt: skip
    second, xla = continued("native"), continued("xla")
    np.testing.assert_array_equal(np.asarray(second.Q), np.asarray(whole.Q)[30:])
    np.testing.assert_array_equal(np.asarray(second.stats.iterations), np.asarray(whole.stats.iterations)[30:])
    _same_solution(second, xla)


def test_under_jit_integrate_runs_xla_and_says_so_once(monkeypatch):
    monkeypatch.setattr(native, "_WARNED", set())
    body = models.rigid_body(INERTIA)
    march = lambda xi0, backend="auto": cj.integrate(body, jnp.eye(3), xi0, dt=0.1, n_steps=5, backend=backend)
    with pytest.warns(NativeFallbackWarning, match="integrate's march with XLA.*traced"):
        inside = jax.jit(lambda xi0: march(xi0).Q[-1])(XI0)
    np.testing.assert_allclose(inside, march(XI0).Q[-1], rtol=0, atol=1e-13)
    with warnings.catch_warnings():
        warnings.simplefilter("error", NativeFallbackWarning)  # said once
        jax.jit(lambda xi0: march(xi0).Q[-2])(XI0)  # traced again
    with pytest.raises(ValueError, match="backend='native'.*traced"):
        jax.jit(lambda xi0: march(xi0, "native").Q[-1])(XI0)


def _erf_inv_potential(xi, q):
    """A particle in a potential written with `lax.erf_inv`, a primitive the translation lacks."""
    return 0.5 * jnp.sum(xi**2) - 0.1 * jnp.sum(jax.lax.erf_inv(0.3 * jnp.tanh(q)))


def test_an_uncovered_step_runs_xla_and_names_the_primitive(monkeypatch):
    """ "auto" says which primitive the translation does not cover and runs XLA's chunk;
    "native" raises with the reason."""
    monkeypatch.setattr(native, "_WARNED", set())
    system = cj.ClebschSystem(
        lagrangian=_erf_inv_potential, velocity_map=translation, derivative_map=cj.forward_difference
    )
    args = (system, jnp.array([0.5, -0.2]), jnp.array([0.1, 0.3]))
    with pytest.warns(NativeFallbackWarning, match="does not cover the step: primitive 'erf_inv'"):
        auto = cj.integrate(*args, dt=0.1, n_steps=5)
    _bitwise(auto, cj.integrate(*args, dt=0.1, n_steps=5, backend="xla"))
    with pytest.raises(ValueError, match="backend='native'.*'erf_inv'"):
        cj.integrate(*args, dt=0.1, n_steps=5, backend="native")


def test_without_llvmlite_integrate_runs_xla(monkeypatch):
    monkeypatch.setattr(native, "available", lambda: False)
    monkeypatch.setattr(native, "_WARNED", set())
    with pytest.warns(NativeFallbackWarning, match="llvmlite"):
        sol = cj.integrate(models.rigid_body(INERTIA), jnp.eye(3), XI0, dt=0.1, n_steps=5)
    assert int(sol.result) == cj.Status.SUCCESS
    with pytest.raises(ValueError, match="backend='native'.*llvmlite"):
        cj.integrate(models.rigid_body(INERTIA), jnp.eye(3), XI0, dt=0.1, n_steps=5, backend="native")


def test_a_bad_backend_is_refused_before_compiling():
    with pytest.raises(ValueError, match="backend: expected one of"):
        cj.integrate(models.rigid_body(INERTIA), jnp.eye(3), XI0, dt=0.1, n_steps=5, backend="llvm")


@pytest.mark.parametrize("width, members", [(1, 1), (4, 5)])
def test_a_loop_kernel_runs_its_body_and_writes_every_iteration(width, members):
    """`native.compile_loop` against the body run in Python, step by step: the carry after
    `steps` iterations, the records of each (booleans and stacked arrays too), zero records
    after them; with several members in lanes of 4, one block padded."""

    def body(a, c):
        x, n, ok = c
        y = jnp.sin(x) * a + 0.1
        return (y, n + 1, ok & jnp.all(y < 1.5)), (y, n, ok, jnp.stack([x, y]))

    c0 = (jnp.ones(3), jnp.int32(0), jnp.asarray(True))
    loop = native.compile_loop(body, jnp.ones(3), c0, width=width)
    rng = np.random.default_rng(0)
    a = rng.uniform(0.5, 1.5, (members, 3))
    carry = (rng.uniform(size=(members, 3)), np.zeros(members, np.int32), np.ones(members, bool))
    last, records = loop(a, carry, steps=7, capacity=10)
    for m in range(members):
        c, expected = tuple(x[m] for x in carry), []
        for _ in range(7):
            c, r = body(a[m], c)
            expected.append(r)
        for got, want in zip(last, c):
            np.testing.assert_allclose(got[m], want, rtol=1e-15)
        for k, rec in enumerate(records):
            np.testing.assert_allclose(rec[m, :7], np.stack([r[k] for r in expected]), rtol=1e-15)
            assert not np.any(rec[m, 7:])


def test_a_loop_kernel_writes_its_records_into_a_runs_rows():
    """`records=` views of a run's rows (`NativeLoop.record_rows`, aligned to 64 bytes): two
    calls, the second from the first's carry, fill records 0–2 and 3–6 in place with what one
    call of 7 iterations writes (how `integrate`'s native chunks fill a Solution without a
    join); rows of another shape are refused, naming the record."""

    def body(a, c):
        x, n, ok = c
        y = jnp.sin(x) * a + 0.1
        return (y, n + 1, ok & jnp.all(y < 1.5)), (y, n, ok, jnp.stack([x, y]))

    loop = native.compile_loop(body, jnp.ones(3), (jnp.ones(3), jnp.int32(0), jnp.asarray(True)), width=1)
    a = np.array([[0.7, 1.1, 1.4]])
    carry = (np.array([[0.2, 0.5, 0.9]]), np.zeros(1, np.int32), np.ones(1, bool))
    _, whole = loop(a, carry, steps=7, capacity=7)
    rows = loop.record_rows(7)
    assert all(r.ctypes.data % 64 == 0 for r in rows)
    mid, _ = loop(a, carry, steps=3, capacity=3, records=loop.record_views(rows, 0, 3))
    loop(a, mid, steps=4, capacity=4, records=loop.record_views(rows, 3, 7))
    for got, want in zip(jax.tree_util.tree_leaves(loop.records(rows, 7)), whole):
        assert got.dtype == want.dtype
        np.testing.assert_array_equal(got, want[0])
    with pytest.raises(ValueError, match=r"records\[0\]: expected C-contiguous rows of shape \(9, 1\)"):
        loop(a, carry, steps=3, capacity=3, records=loop.record_views(rows, 0, 2))


def test_a_later_run_writes_into_a_runs_rows_only_once_nothing_holds_them():
    """A run's record rows are taken again by the next run of the same length (their pages
    already faulted in: `layout.SpareRows`), but never while a `Solution`, or a NumPy view of
    one, still holds them: each run's values stay what they were, and a run that does reuse
    rows gives the same bits as on fresh ones."""
    run = lambda xi: cj.integrate(TOP, TOP_Q0, xi, dt=0.01, n_steps=300, backend="native")  # noqa: E731
    first = run(TOP_XI0)
    want = {name: np.array(getattr(first, name)) for name in ("Q", "xi", "momentum")}
    view = np.asarray(first.Q)  # outlives `first`
    held = run(1.1 * TOP_XI0)  # rows of its own: `first` holds the last run's
    held_Q = np.array(held.Q)
    del first
    for scale in (1.2, 1.3, 1.2):  # each run after the first takes the rows of the one before
        other = run(scale * TOP_XI0)
        del other
    np.testing.assert_array_equal(view, want["Q"])
    np.testing.assert_array_equal(np.asarray(held.Q), held_Q)
    again = run(TOP_XI0)
    for name, values in want.items():
        np.testing.assert_array_equal(np.asarray(getattr(again, name)), values, err_msg=name)


def test_a_kernel_of_one_member_in_one_lane_leaves_its_inputs_as_they_were():
    """One member in a kernel of one lane (a single trajectory's layout): its arrays are passed
    as they are, not copied into row buffers; the kernel gives the function's values (booleans
    too) and leaves its inputs unchanged."""

    def f(a, ok):
        return a * 2.0 + 1.0, ok & jnp.all(a > 0), jnp.sum(a, axis=0)

    kernel = native.compile_member(f, jnp.ones((2, 3)), jnp.asarray(True), width=1, use_cache=False)
    a, ok = np.arange(6.0).reshape(1, 2, 3) - 1.0, np.array([True])
    before = a.copy()
    got = kernel(a, ok)
    for x, y in zip(got, f(a[0], ok[0])):
        assert x.shape == (1,) + np.shape(y) and x.dtype == np.asarray(y).dtype
        np.testing.assert_array_equal(x[0], y)
    np.testing.assert_array_equal(a, before)
