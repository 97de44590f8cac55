"""The engine: Lemma 20 from the whole discrete action, Remarks 21-22, transforms, maps."""

import functools
import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import clebsch_jax as cj
from clebsch_jax import diagnostics as dg

INERTIA = np.array([2.0, 1.0, 2.0 / 3.0])


@pytest.mark.parametrize(
    # the default run checks the midpoint principle; the one-sided ones, each its own program, are slow
    "scheme",
    [pytest.param(s, marks=pytest.mark.slow) if s != "midpoint" else s for s in cj.SCHEMES],
)
def test_trajectory_is_stationary_for_the_whole_discrete_action(scheme):
    """Lemma 20 checked without the step assembly: the gradient of Σₙ L_d(ξⁿ, Pⁿ, Qⁿ, Qⁿ⁺¹)
    with respect to every ξⁿ, every Pⁿ and every interior Qⁿ vanishes on the trajectory."""
    system = cj.models.rigid_body(INERTIA)
    dt = 0.1
    # XLA by name: the full march's program is past the native translation's size limit, and
    # "auto" would trace it for the translation before falling back (the backends' agreement
    # is test_native_integrate's). The action's gradient is jitted: one compile, not op by op.
    sol = cj.integrate(
        system, jnp.eye(3), jnp.array([0.4, -1.0, 0.7]), dt=dt, n_steps=40, scheme=scheme, reduce=False, backend="xla"
    )
    action = lambda x, P, Q: cj.discrete_action(system, scheme, dt, x, P, Q)  # noqa: E731
    g_xi, g_P, g_Q = jax.jit(jax.grad(action, argnums=(0, 1, 2)))(sol.xi_step, sol.P, sol.Q)
    assert float(jnp.max(jnp.abs(g_xi))) < 1e-13
    assert float(jnp.max(jnp.abs(g_P))) < 1e-13
    assert float(jnp.max(jnp.abs(g_Q[1:-1]))) < 1e-13
    # and the end momenta are the discrete Legendre transforms ∓∂S/∂Q at the ends
    np.testing.assert_allclose(np.asarray(g_Q[-1]), np.asarray(sol.p[-1]), atol=1e-13)
    np.testing.assert_allclose(np.asarray(-g_Q[0]), np.asarray(sol.p[0]), atol=1e-13)


def _oscillator_lagrangian(xi, Q):
    return 0.5 * jnp.sum(xi**2) - 0.5 * jnp.sum(Q**2)


def _translation(xi, Q):
    return xi


# A particle in a potential: V = ℝ, M = ℝ, L_ξQ = ξ, l(ξ, Q) = ξ²/2 - Q²/2 (Def. 14). Built once
# from module-level functions, so the tests below that march it with the same scheme and shapes
# reuse one compiled program (a system rebuilt from fresh lambdas compiles again).
OSCILLATOR = cj.ClebschSystem(
    lagrangian=_oscillator_lagrangian, velocity_map=_translation, derivative_map=cj.forward_difference
)


def test_remarks_21_22_are_symplectic_euler_A_and_B():
    """Forward difference + Definition 19 = symplectic Euler-A; the Remark 22 adjoint = Euler-B.
    With H = p²/2 + q²/2 they are explicit, so compare with the textbook updates exactly."""
    dt, n = 0.1, 50
    q0, p0 = np.array([1.0]), np.array([0.3])
    system = OSCILLATOR
    A = cj.integrate(system, q0, p0, dt=dt, n_steps=n, scheme="left")
    B = cj.integrate(system, q0, p0, dt=dt, n_steps=n, scheme="right")
    qa, pa, qb, pb = [q0.copy()], [p0.copy()], [q0.copy()], [p0.copy()]
    for _ in range(n):
        p_new = pa[-1] - dt * qa[-1]  # Euler-A: p⁺ = p - Δt V'(q), q⁺ = q + Δt p⁺
        qa.append(qa[-1] + dt * p_new)
        pa.append(p_new)
        q_new = qb[-1] + dt * pb[-1]  # Euler-B: q⁺ = q + Δt p, p⁺ = p - Δt V'(q⁺)
        qb.append(q_new)
        pb.append(pb[-1] - dt * q_new)
    np.testing.assert_allclose(np.asarray(A.Q), np.array(qa), atol=1e-13)
    np.testing.assert_allclose(np.asarray(A.p), np.array(pa), atol=1e-13)
    np.testing.assert_allclose(np.asarray(B.Q), np.array(qb), atol=1e-13)
    np.testing.assert_allclose(np.asarray(B.p), np.array(pb), atol=1e-13)


@pytest.mark.parametrize("scheme", cj.SCHEMES)
def test_schemes_converge_at_their_nominal_order(scheme):
    """Exact solution of the oscillator: q = cos t·q0 + sin t·p0. With a potential the left
    and right principles are first order; the midpoint principle is second order."""
    T, dts = 2.0, np.array([0.1, 0.05, 0.025, 0.0125])
    errs = []
    for dt in dts:
        # concrete calls: every dt and run length uses the compiled chunk program of this scheme,
        # the one the other tests of OSCILLATOR (left, right) compile as well
        sol = cj.integrate(
            OSCILLATOR, jnp.array([1.0]), jnp.array([0.3]), dt=dt, n_steps=int(round(T / dt)), scheme=scheme
        )
        assert float(sol.ts[-1]) == pytest.approx(T)
        errs.append(abs(float(sol.Q[-1, 0]) - (np.cos(T) + 0.3 * np.sin(T))))
    assert sol.order == (2 if scheme == "midpoint" else 1)
    assert abs(dg.fit_order(dts, errs) - sol.order) < 0.15


def test_energy_of_symplectic_euler_is_bounded():
    """Backward error analysis: no drift over 10⁴ steps (envelope ratio, last vs first tenth)."""
    system = OSCILLATOR
    sol = cj.integrate(system, jnp.array([1.0]), jnp.array([0.0]), dt=0.05, n_steps=10_000, scheme="left")
    E = np.asarray(dg.energy(system, sol))
    err = E - E[0]
    assert np.max(np.abs(err)) < 0.05 * E[0]
    assert dg.envelope_ratio(err) < 1.2


def test_diamond_is_minus_the_pairing_with_the_velocity_map():
    """Definition 4: <P⋄Q, ξ> = -<P, L_ξ Q> for random P, Q, ξ (SO(3) right multiplication)."""
    system = cj.models.rigid_body(INERTIA)
    rng = np.random.default_rng(0)
    P, Q, xi = rng.normal(size=(3, 3)), rng.normal(size=(3, 3)), rng.normal(size=3)
    lhs = float(jnp.dot(cj.diamond(system, P, Q, xi), xi))
    rhs = -float(jnp.sum(P * (Q @ cj.lie.hat(xi))))
    assert abs(lhs - rhs) < 1e-13
    np.testing.assert_allclose(cj.momentum_map(system, P, Q, xi), -cj.diamond(system, P, Q, xi))


def test_matrix_maps_are_inverse_pairs():
    rng = np.random.default_rng(1)
    for scale in (0.1, 0.5, 1.5):
        X = scale * rng.normal(size=(3, 3)) / np.sqrt(3)
        np.testing.assert_allclose(cj.lie.cayley_log(cj.lie.cayley_exp(X)), X, atol=1e-13)
        np.testing.assert_allclose(cj.lie.logm(cj.lie.expm(X)), X, atol=1e-12)
        w = rng.normal(size=3)
        w = 2.0 * scale * w / np.linalg.norm(w)  # rotation angle 2·scale < π: so3_log's domain
        np.testing.assert_allclose(cj.lie.so3_exp(w), cj.lie.expm(cj.lie.hat(w)), atol=1e-13)
        np.testing.assert_allclose(cj.lie.so3_log(cj.lie.so3_exp(w)), w, atol=1e-12)
    # Cayley is second-order accurate for exp
    X = 1e-2 * rng.normal(size=(3, 3))
    assert np.max(np.abs(cj.lie.cayley_exp(X) - cj.lie.expm(X))) < 1e-6 * 1.0


@pytest.mark.slow  # op-by-op derivatives of expm; the marches that use it are checked by default
def test_expm_matches_scipy_and_jax_scipy_derivatives():
    """`lie.expm` (Padé 13 with scaling and squaring in XLA operations) against SciPy's expm over
    sizes 3-9 and 1-norms from 1e-3 to ~50 (0 to 4 squarings), in a batch; its first and
    reverse-mode derivatives against those through `jax.scipy.linalg.expm` (LAPACK)."""
    import scipy.linalg

    rng = np.random.default_rng(7)
    expm = jax.jit(cj.lie.expm)  # op by op, the scan of squarings dispatches every operation
    for n in (3, 5, 9):  # the denominator solved by the adjugate, by elimination, by the LU loop
        X = rng.normal(size=(5, n, n)) * np.array([1e-3, 0.5, 3.0, 15.0, 40.0])[:, None, None] / np.sqrt(n)
        got = np.asarray(expm(X))
        for x, g in zip(X, got):
            ref = scipy.linalg.expm(x)
            # loosened from ε: the squarings (up to 4 here) amplify each method's round-off
            np.testing.assert_allclose(g, ref, rtol=0, atol=1e-12 * np.max(np.abs(ref)))
    X = jnp.asarray(0.4 * rng.normal(size=(3, 3)))
    for d in (jax.jacfwd, jax.jacrev):
        np.testing.assert_allclose(jax.jit(d(cj.lie.expm))(X), jax.jit(d(jax.scipy.linalg.expm))(X), rtol=0, atol=1e-14)


@pytest.mark.slow  # vmap over parameters, compiled per case; vmap of integrate is covered by test_batch and test_silent_failures
@pytest.mark.parametrize("reduce", [False, True])
def test_vmap_over_parameters_and_initial_data_matches_single_runs(reduce):
    """A member's trajectory is the same whether run alone or inside a vmapped batch."""
    inertias = jnp.array([[2.0, 1.0, 2 / 3], [0.5, 0.6, 1.0], [1.0, 2.0, 3.0]])
    xi0s = jnp.array([[0.3, 0.1, 1.0], [1.0, -0.2, 0.1], [0.0, 1.0, 0.5]])
    run = lambda I, x: cj.integrate(cj.models.rigid_body(I), jnp.eye(3), x, dt=0.1, n_steps=30, reduce=reduce)
    batch = jax.vmap(run)(inertias, xi0s)
    assert batch.Q.shape == (3, 31, 3, 3) and batch.xi.shape == (3, 31, 3)
    if not reduce:
        assert batch.P.shape == (3, 30, 3, 3) and batch.p.shape == (3, 31, 3, 3)
    for i in range(3):
        single = run(inertias[i], xi0s[i])
        np.testing.assert_allclose(np.asarray(batch.Q[i]), np.asarray(single.Q), rtol=0, atol=1e-14)
        np.testing.assert_allclose(np.asarray(batch.xi[i]), np.asarray(single.xi), rtol=0, atol=1e-14)


def test_jit_and_closures():
    """A user closure over a traced parameter works under vmap; integrate works inside jit."""

    def with_closure(I):
        system = cj.ClebschSystem(
            lagrangian=lambda x: 0.5 * jnp.sum(I * x * x),
            velocity_map=lambda x, Q: Q @ cj.lie.hat(x),
            derivative_map=cj.cayley,
        )
        return cj.integrate(system, jnp.eye(3), jnp.array([0.2, 1.0, 0.3]), dt=0.1, n_steps=20).Q[-1]

    I = jnp.array([[2.0, 1.0, 2 / 3], [1.0, 2.0, 3.0]])
    a = jax.vmap(with_closure)(I)
    b = jax.jit(
        jax.vmap(
            lambda I: cj.integrate(
                cj.models.rigid_body(I), jnp.eye(3), jnp.array([0.2, 1.0, 0.3]), dt=0.1, n_steps=20
            ).Q[-1]
        )
    )(I)
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-14)


def test_programs_with_compiler_options_run_inside_a_callers_trace():
    """The engine compiles some programs with XLA options (`QUICK_COMPILE`), which JAX refuses
    on a jit staged into another trace; `jit_with_options` then runs the same function without
    them, so `integrate`'s checks and marches stay jit-, grad- and vmap-compatible."""
    from clebsch_jax.core.jit import QUICK_COMPILE, jit_with_options

    fun = lambda x: jnp.sin(x) * x
    with pytest.raises(ValueError, match="top-level"):  # what a plain jit with options does
        jax.jit(lambda x: jax.jit(fun, compiler_options=QUICK_COMPILE)(x))(1.0)
    f = jit_with_options(fun, QUICK_COMPILE)
    assert float(f(1.0)) == float(fun(1.0)) and float(jax.jit(f)(1.0)) == float(jax.jit(fun)(1.0))
    np.testing.assert_allclose(float(jax.grad(f)(1.0)), np.cos(1.0) + np.sin(1.0), rtol=1e-15)
    np.testing.assert_allclose(np.asarray(jax.vmap(f)(jnp.arange(3.0))), np.sin(np.arange(3.0)) * np.arange(3.0))


def test_the_group_inspection_is_one_program_also_inside_a_callers_jit():
    """The velocity map's group is read by one compiled program (`evaluate_now`), run at once
    also inside the caller's jit; the constants in the map (`lie.hat`'s zeros) are traced into
    it, not evaluated one operation at a time (each an XLA compile of its own). Inside and
    outside the jit, the basis is bit for bit the same, and a map that closes over a traced
    value is not inspected."""
    from clebsch_jax.core.jit import evaluate_now
    from clebsch_jax.discrete.matrix_group import matrix_group_basis

    from .helpers import compiles_recorded

    system = cj.ClebschSystem(  # fresh functions: no program of theirs is compiled yet
        lagrangian=lambda x: 0.5 * jnp.sum(x * x), velocity_map=lambda x, Q: Q @ cj.lie.hat(x), derivative_map=cj.cayley
    )
    seen = {}

    def f(x0):
        seen["jit"] = matrix_group_basis(system, jnp.eye(3), x0)
        seen["closure"] = evaluate_now(lambda y: y * x0, np.ones(3))
        return x0

    with compiles_recorded(where=("jit.py", "lie.py")) as compiled:
        jax.jit(f)(jnp.ones(3))
    assert len(compiled) == 1, compiled  # the inspection (the caller's jit is compiled from jax's frames)
    outside = matrix_group_basis(system, np.eye(3), np.ones(3))
    assert seen["jit"].tobytes() == outside.tobytes() and seen["closure"] is None
    np.testing.assert_array_equal(outside, np.asarray(jax.vmap(cj.lie.hat)(jnp.eye(3))))


FIRST_CALLS = r"""
import json, traceback
import jax
import numpy as np
import clebsch_jax as cj
where = []
def listen(event, secs, **kw):
    if "backend_compile" in event:
        frames = [f for f in traceback.extract_stack() if "clebsch_jax" in f.filename]
        where.append(frames[-1].filename.rsplit("clebsch_jax", 1)[-1] if frames else "?")
jax.monitoring.register_event_duration_secs_listener(listen)
counts = {}
for name, make, xi0 in [
    ("rigid body", lambda: cj.models.rigid_body(np.array([2.0, 1.0, 2.0 / 3.0])), [1.3, 0.8, -0.4]),
    ("heavy top", lambda: cj.models.heavy_top(np.array([1.0, 1.0, 0.4]), 1.5), [0.3, -0.2, 6.0]),
]:
    system = make()
    where.clear()
    cj.integrate(system, np.eye(3), np.array(xi0), dt=0.05, n_steps=20, backend="xla")
    counts[name] = list(where)
print(json.dumps(counts))
"""


@pytest.mark.slow  # a fresh process (JAX caches its eager operations' programs process-wide) compiling two marches
def test_the_first_calls_of_a_rigid_body_and_a_heavy_top_compile_their_programs_only():
    """In a fresh process, the first `integrate` of the rigid body compiles five programs (the
    model check, the momentum check, the group inspection, the march's start and chunk), and a
    heavy top after it three (its group and momentum check are the rigid body's): no operation
    run on its own, as `lie.hat`'s constants in the group inspection were (two more programs)."""
    import json
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-c", FIRST_CALLS], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    counts = json.loads(proc.stdout.strip().splitlines()[-1])
    assert len(counts["rigid body"]) == 5 and len(counts["heavy top"]) == 3, counts
    assert not any(f.endswith("lie.py") for f in counts["rigid body"] + counts["heavy top"]), counts


@pytest.mark.slow  # CI runs it; reverse mode through the march is checked in the default run by test_gradients_through_the_march_match_finite_differences
def test_reverse_mode_through_a_system_built_inside_grad():
    """A Lagrangian that closes over the differentiated parameter: integrate sees the closure
    (the maps' traced constants) and runs the single scan, which reverse mode can transpose
    (the chunked march's loops stop at n_steps and cannot be); the gradient is the built-in
    model's, whose parameter is an array leaf."""

    def final(I1, closure):
        I = jnp.stack([I1, 1.0, 2 / 3])
        system = (
            cj.ClebschSystem(
                lagrangian=lambda x: 0.5 * jnp.sum(I * x * x),
                velocity_map=lambda x, Q: Q @ cj.lie.hat(x),
                derivative_map=cj.cayley,
            )
            if closure
            else cj.models.rigid_body(I)
        )
        sol = cj.integrate(system, jnp.eye(3), jnp.array([0.2, 1.0, 0.3]), dt=0.1, n_steps=20)
        return sol.Q[-1, 0, 1] + sol.xi[-1, 2]

    g_closure = jax.grad(functools.partial(final, closure=True))(2.0)
    g_leaf = jax.grad(functools.partial(final, closure=False))(2.0)
    assert abs(float(g_closure) - float(g_leaf)) < 1e-12


def test_gradients_through_the_march_match_finite_differences():
    """Reverse and forward mode through the Newton solves (implicit differentiation)."""

    def final_angle(I1, x0):
        sol = cj.integrate(cj.models.rigid_body(jnp.stack([I1, 1.0, 2 / 3])), jnp.eye(3), x0, dt=0.1, n_steps=20)
        return sol.Q[-1, 0, 1] + sol.xi[-1, 2]

    I1, x0 = 2.0, jnp.array([0.2, 1.0, 0.3])
    gI, gx = jax.grad(final_angle, argnums=(0, 1))(I1, x0)
    h = 1e-6
    fd_I = (final_angle(I1 + h, x0) - final_angle(I1 - h, x0)) / (2 * h)
    fd_x = np.array([(final_angle(I1, x0 + h * e) - final_angle(I1, x0 - h * e)) / (2 * h) for e in jnp.eye(3)])
    # central differences with h = 1e-6 are accurate to ~1e-9 here
    assert abs(float(gI) - float(fd_I)) < 1e-7
    np.testing.assert_allclose(np.asarray(gx), fd_x, atol=1e-7)
    jI = jax.jacfwd(final_angle)(I1, x0)
    assert abs(float(jI) - float(gI)) < 1e-10


def _breaks_above(c):
    """A rigid body whose Lagrangian has a NaN gradient once ξ₁ exceeds c: ε·√(c − ξ₁) barely
    changes the dynamics below c and injects a NaN into the Newton residual above it."""
    I = jnp.asarray(INERTIA)
    return cj.ClebschSystem(
        lagrangian=lambda x: 0.5 * jnp.sum(I * x * x) + 1e-3 * jnp.sqrt(c - x[0]),
        velocity_map=lambda x, Q: Q @ cj.lie.hat(x),
        derivative_map=cj.cayley,
    )


# the full march (False) is slow-marked, CI runs it; a full march failing mid-run is reported in the
# default run by tests/test_sweep.py (test_a_member_failing_mid_run_is_reported_at_its_global_step_full_march)
@pytest.mark.parametrize("reduce", [pytest.param(False, marks=pytest.mark.slow), True])
def test_failure_is_reported_with_step_and_member_and_never_as_silent_nan(reduce):
    """ξ₁ of the second member reaches 0.46 and first exceeds 0.4 after some steps; the first
    member stays near 0.05. Both marches must report the step and the member."""
    system = _breaks_above(0.4)
    x_ok, x_bad = jnp.array([0.05, 0.0, 0.05]), jnp.array([0.3, 1.0, 0.2])
    run = lambda x, throw: cj.integrate(system, jnp.eye(3), x, dt=0.1, n_steps=60, reduce=reduce, throw=throw)
    with pytest.raises(cj.IntegrationError, match=r"step \d+ of 60"):
        run(x_bad, True)
    sols = jax.vmap(lambda x: run(x, False))(jnp.stack([x_ok, x_bad]))
    assert sols.form == ("reduced" if reduce else "full")
    assert int(sols.result[0]) == cj.Status.SUCCESS and int(sols.result[1]) != cj.Status.SUCCESS
    k = int(sols.failed_step[1])
    assert k > 0  # it fails mid-run, where ξ₁ first crosses 0.4
    assert float(sols.xi[1, k - 1, 0]) < 0.4 and np.all(np.isfinite(np.asarray(sols.xi[1, :k])))
    # node k itself is reached (Q, momentum valid); its nodal velocity lies past the threshold,
    # where l is undefined: that is recorded, not hidden
    assert bool(jnp.isfinite(sols.xi[1, k, 0])) or int(sols.nodal_stats.status[1, k]) == cj.Status.NONFINITE
    assert not bool(sols.valid[1, k + 1]) and bool(sols.valid[1, k])
    # after the failure: flagged invalid, later steps marked skipped, no finite-looking values
    assert np.all(np.asarray(sols.stats.status[1, k + 1 :]) == cj.Status.SKIPPED)
    assert np.all(np.isnan(np.asarray(sols.Q[1, k + 1 :])))
    assert np.all(np.isnan(np.asarray(sols.xi[1, k + 1 :])))
    assert np.all(np.isfinite(np.asarray(sols.Q[1, : k + 1])))
    assert np.all(np.isfinite(np.asarray(sols.Q[0])))
    with pytest.raises(cj.IntegrationError, match=r"batch member 1, step"):
        sols.raise_if_failed()
    # with throw=True under vmap the host check names the member too
    with pytest.raises(Exception, match=r"batch member 1, step"):
        jax.vmap(lambda x: run(x, True))(jnp.stack([x_ok, x_bad]))


def test_nan_initial_data_under_jit_is_reported_not_returned():
    """Under jit the values are unknown when validating, so a NaN initial state reaches the
    march; the first step then fails and the run raises instead of returning NaNs."""
    system = cj.models.rigid_body(INERTIA)
    run = jax.jit(lambda x: cj.integrate(system, jnp.eye(3), x, dt=0.1, n_steps=5).Q)
    with pytest.raises(Exception, match=r"step 0 of 5"):
        jax.block_until_ready(run(jnp.array([jnp.nan, 0.0, 1.0])))


def test_drift_diagnostics_are_per_member_and_rank_strict():
    v = jnp.array([[[1.0, 2.0], [1.0, 2.1]], [[3.0, 1.0], [3.3, 1.0]]])  # (batch, time, feature)
    np.testing.assert_allclose(dg.relative_drift(v, axis=1, feature_ndim=1), [0.05, 0.1])
    with jax.numpy_rank_promotion("raise"):
        assert float(jnp.max(dg.orthogonality_error(jnp.stack([jnp.eye(3)] * 4)))) == 0.0


@pytest.mark.parametrize("spread", [1.0, 1e-7])
def test_minimum_norm_cotangent_of_forty_components_is_the_exact_solution(spread):
    """Above `_DIRECT_MAX` components the cotangent is found by conjugate gradients and checked;
    where CG cannot reach round-off (a velocity map whose scales span 1e-7..1: A^T A has
    condition 1e14) the dense solve is made instead. Either way it is the minimum-norm solution,
    here known exactly (A = mix·diag(s), mix with orthonormal columns: p = mix·(μ/s)); also under
    vmap (the check becomes a select)."""
    from clebsch_jax.discrete.legendre import _DIRECT_MAX

    n = 40
    assert _DIRECT_MAX < n
    rng = np.random.default_rng(3)
    scales = np.geomspace(spread, 1.0, n)
    mix = np.linalg.qr(rng.normal(size=(n + 4, n)))[0]  # orthonormal columns: A = mix·diag(s)
    system = cj.ClebschSystem(
        lagrangian=lambda x, Q: 0.5 * jnp.sum(x * x) - 0.5 * jnp.sum(Q * Q),
        velocity_map=lambda x, Q: jnp.asarray(mix) @ (jnp.asarray(scales) * x),
        derivative_map=cj.forward_difference,
    )
    Q, mu = jnp.asarray(rng.normal(size=n + 4)), rng.normal(size=n)
    expected = mix @ (mu / scales)
    p = cj.cotangent_from_momentum(system, Q, jnp.asarray(mu))
    # round-off relative to |p| ~ 1/spread (Gram–Schmidt on these nearly orthogonal columns
    # keeps it near ε, closer than an SVD least-squares solve gets)
    tol = 1e-14 / spread
    np.testing.assert_allclose(np.asarray(p), expected, rtol=0, atol=tol)
    batched = jax.vmap(lambda m: cj.cotangent_from_momentum(system, Q, m))(jnp.stack([jnp.asarray(mu), 2.0 * mu]))
    np.testing.assert_allclose(np.asarray(batched[1]), 2.0 * expected, rtol=0, atol=2 * tol)


@pytest.mark.parametrize("n", [4, 6, 9])
def test_dense_solves_above_three_unknowns_match_numpy(n):
    """`linalg.solve` and `inv` above the closed form (n > 3): straight-line elimination up to
    `ELIMINATION_MAX`, the `lu_factor` loop above it; against NumPy's LAPACK on random and
    pivot-needing matrices, vector and matrix right-hand sides, with leading axes."""
    from clebsch_jax.core import linalg

    assert 4 <= linalg.ELIMINATION_MAX < 9
    rng = np.random.default_rng(n)
    A = rng.normal(size=(3, n, n)) + 2.0 * np.eye(n)
    A[1] = np.eye(n)[rng.permutation(n)] * rng.uniform(1.0, 2.0, n)  # a zero diagonal: the pivots swap rows
    A[2, 0, 0] = 0.0
    b, B = rng.normal(size=(3, n)), rng.normal(size=(3, n, 2))
    for got, ref in [
        (linalg.solve(A, b), np.linalg.solve(A, b[..., None])[..., 0]),
        (linalg.solve(A, B), np.linalg.solve(A, B)),
        (linalg.inv(A), np.linalg.inv(A)),
        (linalg.solve(A[0], B), np.linalg.solve(A[0], B)),
    ]:
        # round-off of well-conditioned solves (condition numbers below 1e3 here)
        np.testing.assert_allclose(np.asarray(got), ref, rtol=0, atol=1e-12 * np.max(np.abs(ref)))


@pytest.mark.parametrize("n", [3, 12])
def test_positive_definite_solves_match_numpy_batched_or_not_and_are_nan_otherwise(n):
    """`linalg.spd_solve`: one matrix by LAPACK, a vmapped batch by Cholesky in XLA operations;
    both against NumPy, and NaN for a matrix that is not positive definite (derivatives:
    `test_positive_definite_solve_derivatives_up_to_third_order_match_jax_scipy`)."""
    from clebsch_jax.core import linalg

    rng = np.random.default_rng(n)
    A = rng.normal(size=(2, n, n))
    K = A @ np.swapaxes(A, 1, 2) + n * np.eye(n)
    b = rng.normal(size=(2, n))
    ref = np.linalg.solve(K, b[..., None])[..., 0]
    batched = jax.vmap(linalg.spd_solve)(jnp.asarray(K), jnp.asarray(b))
    single = [linalg.spd_solve(K[i], b[i]) for i in range(2)]
    for got in (batched, np.stack(single)):
        np.testing.assert_allclose(np.asarray(got), ref, rtol=0, atol=1e-13 * np.max(np.abs(ref)))  # round-off
    indefinite = jnp.asarray(np.eye(n) - 2.0 * np.outer(np.eye(n)[0], np.eye(n)[0]))  # diag(-1, 1, ..., 1)
    assert np.all(np.isnan(np.asarray(linalg.spd_solve(indefinite, jnp.ones(n)))))
    assert np.all(np.isnan(np.asarray(jax.vmap(linalg.spd_solve)(jnp.stack([indefinite] * 2), jnp.ones((2, n))))))


@pytest.mark.slow  # ~5 s of compile; the landmark gradient tests (test_control.py) differentiate it too
def test_positive_definite_solve_derivatives_up_to_third_order_match_jax_scipy():
    """Derivatives of ½xᵀK(q)⁻¹x (the peakon kernel) up to third order through `linalg.spd_solve`
    (implicit, `custom_linear_solve`; batched: the XLA-operations Cholesky) equal those through
    `jax.scipy`'s Cholesky."""
    from clebsch_jax.core import linalg

    kernel = lambda q: jnp.exp(-jnp.abs(q[:, None] - q[None, :]))  # SPD for distinct q
    energy = lambda solve: lambda q, x: 0.5 * x @ solve(kernel(q), x)
    ours = energy(linalg.spd_solve)
    scipy = energy(lambda K, x: jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(K, lower=True), x))
    third = lambda f: jax.jacfwd(jax.hessian(f, (0, 1)), (0, 1))
    q, x = np.random.default_rng(3).normal(size=(2, 3))
    want = jax.jit(third(scipy))(q, x)
    got = jax.jit(jax.vmap(third(ours)))(jnp.stack([q, q]), jnp.stack([x, x]))
    for w, g in zip(jax.tree_util.tree_leaves(want), jax.tree_util.tree_leaves(got)):
        scale = max(1.0, float(np.max(np.abs(w))))
        # Round-off of a few hundred flops of O(1) terms.
        np.testing.assert_allclose(np.asarray(g), np.stack([w, w]), rtol=0, atol=1e-13 * scale)


@pytest.mark.slow  # an implementation property (which kernels a batched march calls), checked in CI's slow run
def test_batched_marches_call_no_lapack_kernel():
    """Batched marches (the peakons' Cholesky solve included), the exponential map's `expm` and
    the cotangent hand-over compile to XLA operations only: jaxlib's batched LAPACK kernels
    share XLA's intra-op thread pool and deadlocked a sweep on two host devices
    (`tests/test_sweep.py`, `devices=2`) and a sweep of 2048 peakon systems on one."""
    from clebsch_jax.discrete.legendre import cotangent_from_momentum
    from .test_first_step_check import _se3_body, _se3_kinetic

    se3 = cj.ClebschSystem(lagrangian=_se3_kinetic, velocity_map=_se3_body, derivative_map=cj.cayley)
    rigid = cj.models.rigid_body(INERTIA)
    programs = {
        # the exponential derivative map's matrix exponential (its logarithm is Denman–Beavers
        # iterations and `linalg.solve`); a whole march with it takes seconds to lower
        "expm": (cj.lie.expm, 0.1 * jnp.ones((2, 3, 3))),
        "rigid body": (
            lambda x: cj.integrate(rigid, jnp.eye(3), x, dt=0.1, n_steps=3, throw=False).momentum,
            jnp.ones((2, 3)),
        ),
        "SE(3), Cayley": (
            lambda x: cj.integrate(se3, jnp.eye(4), x, dt=0.1, n_steps=3, throw=False).momentum,
            jnp.ones((2, 6)),
        ),
        "hand-over": (lambda m: cotangent_from_momentum(rigid, jnp.eye(3), m), jnp.ones((2, 3))),
        # Q0 batched too: one unbatched Cholesky (a Q0 shared by the members) is LAPACK, and safe.
        "peakons": (
            lambda x: (
                cj.integrate(
                    cj.models.peakons(), x[0] * jnp.array([-1.0, 0.0, 1.5]), x[1], dt=0.01, n_steps=3, throw=False
                ).Q
            ),
            jnp.ones((2, 2, 3)),
        ),
    }
    for name, (fn, x) in programs.items():
        text = jax.jit(jax.vmap(fn)).lower(x).as_text().lower()
        assert "lapack" not in text, name


@pytest.mark.slow  # its own compiled programs; Lemma 7's multiplier is also checked by test_sweep's P0 tests in the slow run
def test_minimum_norm_cotangent_of_a_rank_deficient_map_matches_least_squares():
    """The dense solve (no LAPACK: Gram–Schmidt) against NumPy's least squares: full-rank and
    rank-deficient A (a velocity map with isotropy), written out (up to STRAIGHT_MAX columns) and
    as a loop, under vmap and jit; its gradient is finite. The two forms agree to round-off."""
    from clebsch_jax.discrete.legendre import STRAIGHT_MAX, min_norm_transpose_solve

    rng = np.random.default_rng(5)
    for m, n, rank in [(9, 3, 3), (9, 3, 2), (8, 4, 3), (12, 6, 4)]:
        A = rng.normal(size=(m, rank)) @ rng.normal(size=(rank, n))
        b = jnp.asarray(A.T @ rng.normal(size=m))
        straight = min_norm_transpose_solve(jnp.asarray(A), b, unroll=True)
        loop = min_norm_transpose_solve(jnp.asarray(A), b)
        np.testing.assert_allclose(straight, loop, rtol=0, atol=1e-14 * np.max(np.abs(loop)))
    assert STRAIGHT_MAX >= 4
    for (m, n, rank), unroll in itertools.product([(9, 3, 3), (9, 3, 2), (12, 6, 4)], [False, True]):
        A = rng.normal(size=(m, rank)) @ rng.normal(size=(rank, n))
        bs = A.T @ rng.normal(size=(m, 2))  # consistent right-hand sides (momenta of some p)
        solve = functools.partial(min_norm_transpose_solve, unroll=unroll)
        ps = jax.jit(jax.vmap(solve, in_axes=(None, 1)))(jnp.asarray(A), jnp.asarray(bs))
        for k in range(2):
            ref = np.linalg.lstsq(A.T, bs[:, k], rcond=None)[0]
            np.testing.assert_allclose(np.asarray(ps[k]), ref, rtol=0, atol=1e-13 * np.max(np.abs(ref)))
        g = jax.grad(lambda b: jnp.sum(solve(jnp.asarray(A), b) ** 2))(jnp.asarray(bs[:, 0]))
        assert np.all(np.isfinite(np.asarray(g)))
