r"""Sweeps (`clebsch_jax.sweep`): chunked reductions equal those of a stored trajectory, the
rigid body's Casimir over a grid of inertias, failures reported per member with their global
step, devices splitting the members with identical results, bad input rejected before compiling.

Compile time dominates, so the rigid-body tests share one compiled chunk program: every
rigid-body sweep uses `RB` (the same invariants, 20-step chunks, batches of 4, every 10th node
saved); only array values change between them. The peakon test compiles one more program, and
the device test runs in a subprocess (two more: one per device).
"""

import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import clebsch_jax as cj
from clebsch_jax import Status
from clebsch_jax.models import peakon_hamiltonian, peakon_velocity, peakons, rigid_body
from .helpers import cay_velocity, compiles_recorded, hat
from .test_epdiff import COLLISION, OVERTAKE, peakon_antipeakon_exact, two_peakons_exact


def casimir(system, sol):
    """|μ|² at every node: the Casimir of the rigid body's Lie–Poisson bracket."""
    return jnp.sum(sol.momentum**2, axis=-1)


RB = dict(dt=0.05, n_steps=60, chunk_steps=20, batch_size=4, save_every=10, invariants={"casimir": casimir})
INERTIAS = np.array([[2.0, 1.0, 2.0 / 3.0], [1.0, 1.5, 0.5], [3.0, 2.0, 1.0], [1.2, 1.1, 0.7]])
OMEGAS = np.array([[1.3, 0.8, -0.4], [0.2, 1.0, 0.3], [-0.5, 0.1, 0.9], [0.3, -0.7, 0.3]])


def eyes(n):
    return np.broadcast_to(np.eye(3), (n, 3, 3))


def cay_march(inertia, omega0, dt, n):
    r"""Example 30's reduced CAY method as a NumPy recursion on the body momentum, independent
    of the engine (it reproduces `integrate` to 4e-15 over these runs). Step n solves
    $\mu^n = m + \tfrac h2\,\omega\times m + \tfrac{h^2}4(\omega\cdot m)\,\omega$, $m = \mathbb I\omega$, by
    Newton's method, then $\mu^{n+1} = m - \tfrac h2\,\omega\times m + \tfrac{h^2}4(\omega\cdot m)\,\omega$
    and $Q^{n+1} = Q^n\,\mathrm{cay}(h\hat\omega)$. Returns the nodal (μ, ξ = μ/𝕀, Q)."""
    inertia, h = np.asarray(inertia, float), dt
    w = np.asarray(omega0, float).copy()
    mu, Q = inertia * w, np.eye(3)
    mus, Qs = [mu], [Q]
    for _ in range(n):
        w = cay_velocity(inertia, h, mu, w)
        m = inertia * w
        mu = m - 0.5 * h * np.cross(w, m) + 0.25 * h * h * np.dot(w, m) * w
        Y = h * hat(w)
        Q = Q @ np.linalg.solve(np.eye(3) - Y / 2, np.eye(3) + Y / 2)
        mus.append(mu)
        Qs.append(Q)
    mus = np.array(mus)
    return mus, mus / inertia, np.array(Qs)


def test_chunked_diagnostics_equal_those_of_the_stored_trajectory():
    """Three 20-step chunks, reduced on the fly, against the whole stored trajectory."""
    res = cj.sweep(rigid_body, INERTIAS, eyes(4), OMEGAS, **RB)
    assert res.form == "reduced" and res.n_devices == 1 and res.order == 2
    assert np.all(res.status == Status.SUCCESS) and np.all(res.failed_step == -1)
    n = RB["n_steps"]
    ref = [cay_march(inertia, omega, RB["dt"], n) for inertia, omega in zip(INERTIAS, OMEGAS)]
    mu, xi, Q = (np.array(r) for r in zip(*ref))
    # Each chunk restarts Newton's guesses and, in the reduced march, hands μ over through the
    # minimum-norm cotangent: the same trajectory up to round-off (measured 5e-15), not bit for bit.
    tol = 1e-12
    E = 0.5 * np.sum(mu * xi, axis=-1)  # ½ ξ·𝕀ξ
    np.testing.assert_allclose(res.initial["energy"], E[:, 0], rtol=1e-14)
    np.testing.assert_allclose(res.energy_error, np.max(np.abs(E - E[:, :1]), axis=1), rtol=0, atol=tol)
    np.testing.assert_array_equal(res.drift["energy"], res.energy_error)
    C = np.sum(mu**2, axis=-1)
    np.testing.assert_allclose(res.initial["casimir"], C[:, 0], rtol=1e-14)
    np.testing.assert_allclose(res.drift["casimir"], np.max(np.abs(C - C[:, :1]), axis=1), rtol=0, atol=tol)
    # every 10th node, including the last, and the final state
    assert list(res.saved["step"]) == [0, 10, 20, 30, 40, 50, 60]
    for key, r in (("Q", Q), ("xi", xi), ("momentum", mu)):
        np.testing.assert_allclose(res.saved[key], r[:, ::10], rtol=0, atol=tol)
    np.testing.assert_allclose(res.saved["t"], np.broadcast_to(np.arange(7) * 0.5, (4, 7)), rtol=1e-14)
    np.testing.assert_allclose(res.final_t, n * RB["dt"], rtol=1e-14)
    np.testing.assert_allclose(res.final_Q, Q[:, -1], rtol=0, atol=tol)
    np.testing.assert_allclose(res.final_xi, xi[:, -1], rtol=0, atol=tol)
    np.testing.assert_allclose(res.final_momentum, mu[:, -1], rtol=0, atol=tol)
    # final_p is a canonical momentum at final_Q whose momentum map is the final body momentum,
    # so (final_Q, final_p) continues the run.
    mom = jax.vmap(lambda p, q, x: cj.momentum_map(rigid_body(np.ones(3)), p, q, x))(
        res.final_p, res.final_Q, res.final_xi
    )
    np.testing.assert_allclose(np.asarray(mom), res.final_momentum, rtol=0, atol=1e-14)
    assert np.all(res.newton_iterations >= n) and np.all(res.max_residual < 1e-14)


@pytest.mark.slow  # a sweep program of its own
def test_without_P0_the_first_chunk_derives_the_minimum_norm_multiplier():
    """Without P0 the batch starts from a placeholder and the first chunk's program derives P⁰
    (`_with_start_P`); given P0 it is used as it is. The minimum-norm multipliers passed as
    P0, and another cotangent with the same momentum (a part the velocity map does not see
    added: Q(S) with S symmetric), give the table of the sweep without P0."""
    system = rigid_body(np.ones(3))
    options = {**RB, "save_every": None}
    derived = cj.sweep(rigid_body, INERTIAS, eyes(4), OMEGAS, **options)
    P0 = np.stack(
        [np.asarray(cj.initial_multiplier(rigid_body(i), jnp.eye(3), jnp.asarray(w))) for i, w in zip(INERTIAS, OMEGAS)]
    )
    S = np.array([[0.3, 0.1, 0.0], [0.1, -0.2, 0.4], [0.0, 0.4, 0.5]])
    for given in (P0, P0 + S):
        np.testing.assert_allclose(
            cj.momentum_map(system, jnp.asarray(given[0]), jnp.eye(3), jnp.zeros(3)),
            INERTIAS[0] * OMEGAS[0],
            rtol=0,
            atol=1e-14,
        )
        res = cj.sweep(rigid_body, INERTIAS, eyes(4), OMEGAS, P0=given, **options)
        assert np.all(res.succeeded)
        for key in ("final_momentum", "final_xi", "final_Q", "final_p", "energy_error"):
            # the same march from the same momentum: round-off apart (P⁰ enters through −P⋄Q)
            np.testing.assert_allclose(getattr(res, key), getattr(derived, key), rtol=0, atol=1e-13, err_msg=key)


def test_rigid_body_grid_conserves_the_casimir_for_every_member_and_reports_failures():
    """3 inertias × 4 initial momenta (one of them NaN): the Casimir |Π|² is conserved to
    round-off by every member that runs; the NaN members are reported with their indices."""
    rng = np.random.default_rng(3)
    inertias = rng.uniform(0.5, 3.0, size=(3, 3))
    omegas = OMEGAS.copy()
    omegas[2, 1] = np.nan
    res = cj.sweep(rigid_body, inertias, eyes(4), omegas, grid=True, **RB)
    assert len(res) == 12
    np.testing.assert_array_equal(res.param_index, np.repeat(np.arange(3), 4))
    np.testing.assert_array_equal(res.ic_index, np.tile(np.arange(4), 3))
    bad = res.ic_index == 2
    np.testing.assert_array_equal(res.failed_members, np.flatnonzero(bad))  # members 2, 6, 10
    assert np.all(res.status[bad] == Status.INVALID_INPUT) and np.all(res.failed_step[bad] == 0)
    assert np.all(np.isnan(res.final_momentum[bad])) and np.all(np.isnan(res.final_Q[bad]))
    ok = ~bad
    assert np.all(res.status[ok] == Status.SUCCESS) and np.all(res.failed_step[ok] == -1)
    # the grid pairs parameter row i with initial condition j: |I_i ω_j|², computed here
    C0 = np.sum((inertias[res.param_index] * omegas[res.ic_index]) ** 2, axis=1)
    np.testing.assert_allclose(res.initial["casimir"][ok], C0[ok], rtol=1e-14)
    # 60 steps of round-off: relative 1e-13 leaves a factor ~10 over the measured 1e-14
    assert np.all(res.drift["casimir"][ok] <= 1e-13 * C0[ok]), res.drift["casimir"][ok] / C0[ok]
    assert np.all(cj.diagnostics.orthogonality_error(res.final_Q[ok]) < 1e-13)
    # the table
    table = res.to_dict(state=True)
    assert {len(v) for v in table.values()} == {12}
    assert "drift_casimir" in table and "final_Q[2,2]" in table and "final_xi[0]" in table
    assert "3 failed" in res.summary()
    with pytest.raises(cj.IntegrationError, match="member 2 at step 0"):
        res.raise_if_failed()


def test_a_batch_size_above_the_member_count_is_clamped_to_it():
    # 4 members in a batch of 10⁹ would run 10⁹ − 4 padded copies: the batch is 4 members, the
    # program and the table those of batch_size=4 (RB's)
    res = cj.sweep(rigid_body, INERTIAS, eyes(4), OMEGAS, **{**RB, "batch_size": 10**9})
    assert res.batch_size == 4 and len(res) == 4
    four = cj.sweep(rigid_body, INERTIAS, eyes(4), OMEGAS, **RB)
    np.testing.assert_array_equal(res.final_momentum, four.final_momentum)
    np.testing.assert_array_equal(res.drift["casimir"], four.drift["casimir"])


def test_member_chunks_give_the_same_table():
    """`member_chunk` splits a batch into chunks of `cj.batch`: each member's run does not
    depend on the others, so the table is the same, to the bit, for chunks of 3 (the last
    padded) and one chunk of 4; a NaN member fails in both."""
    omegas = OMEGAS.copy()
    omegas[1, 2] = np.nan
    one = cj.sweep(rigid_body, INERTIAS, eyes(4), omegas, **RB)
    split = cj.sweep(rigid_body, INERTIAS, eyes(4), omegas, member_chunk=3, **RB)
    assert list(one.failed_members) == list(split.failed_members) == [1]
    for a, b in zip(jax.tree_util.tree_leaves(one), jax.tree_util.tree_leaves(split)):
        assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True), (a, b)


def total_momentum(system, sol):
    """Σ_a p_a: the Noether momentum of translations (the momentum map of the peakons)."""
    return jnp.sum(sol.momentum, axis=-1)


@pytest.mark.slow  # a full-march sweep program of its own; the reduced march's case stays in the default run
def test_a_member_failing_mid_run_is_reported_at_its_global_step_full_march():
    """Peakons (full march, midpoint scheme, 20-step chunks): a symmetric peakon–antipeakon
    pair collides at t* = 3, where the step fails (a later chunk: the failing step is counted
    from the start of the run); an overtaking pair runs through, second-order accurate; a NaN
    member fails at step 0. References: the exact solutions of `tests.test_epdiff`."""
    dt, n = 0.05, 80
    qc, pc = peakon_antipeakon_exact(0.0, **COLLISION)
    qo, po = two_peakons_exact(0.0, **OVERTAKE)
    q0s, p0s = np.array([qc, qo, [np.nan, 1.0]]), np.array([pc, po, [1.0, 1.0]])
    xi0s = np.asarray(jax.vmap(peakon_velocity)(q0s, p0s))
    res = cj.sweep(
        peakons,
        np.ones(3),
        q0s,
        xi0s,
        dt=dt,
        n_steps=n,
        chunk_steps=20,
        scheme="midpoint",
        invariants={"total_momentum": total_momentum},
    )
    assert res.form == "full" and res.order == 2
    np.testing.assert_array_equal(res.failed_members, [0, 2])
    # the collision: as for one integrate call (tests/test_epdiff.py), within 3 steps before t*
    t_star = COLLISION["t_star"]
    assert res.status[0] in (Status.NONFINITE, Status.MAX_ITERATIONS)
    assert t_star - 3 * dt <= res.failed_step[0] * dt < t_star, res.failed_step[0]
    assert res.failed_step[0] >= 40  # in the third chunk
    assert np.all(np.isnan(res.final_Q[0])) and np.isfinite(res.energy_error[0])
    assert res.drift["total_momentum"][0] < 1e-13  # up to the failure, Σp = 0 is kept
    # the NaN member
    assert res.status[2] == Status.INVALID_INPUT and res.failed_step[2] == 0 and np.isnan(res.energy_error[2])
    # the overtaking pair through four chunk hand-overs of (Q, p): Σp to round-off, the energy
    # bounded, and the exact solution at t = 4 to the method's O(Δt²) (1e-4 here, measured)
    assert res.status[1] == Status.SUCCESS and res.failed_step[1] == -1
    assert res.drift["total_momentum"][1] < 1e-13
    q_ex, p_ex = two_peakons_exact(n * dt, **OVERTAKE)
    err = max(np.max(np.abs(res.final_Q[1] - q_ex)), np.max(np.abs(res.final_p[1] - p_ex)))
    assert err < 1e-3, err
    H = float(peakon_hamiltonian(res.final_Q[1], res.final_p[1]))
    # H of the final state (its own formula) is within the sweep's energy error (measured 8e-6)
    assert abs(H - res.initial["energy"][1]) <= res.energy_error[1] + 1e-14 and res.energy_error[1] < 1e-4


def test_progress_is_reported_after_every_chunk(capsys):
    seen = []
    res = cj.sweep(rigid_body, INERTIAS[:2], eyes(2), OMEGAS[:2], progress=seen.append, **RB)
    assert [(p.step, p.members_done) for p in seen] == [(20, 0), (40, 0), (60, 2)]
    assert all(p.n_batches == 1 and p.n_members == 2 for p in seen)
    assert [p.elapsed for p in seen] == sorted(p.elapsed for p in seen)
    cj.sweep(rigid_body, INERTIAS[:2], eyes(2), OMEGAS[:2], progress=True, **RB)
    err = capsys.readouterr().err
    assert "step 20/60" in err and "2/2 members done" in err
    assert np.all(res.succeeded)


def test_bad_input_is_rejected_before_compiling(monkeypatch):
    from clebsch_jax.batching import chunks_native, chunks_xla

    def compiled(*args, **kwargs):
        raise AssertionError("compiled a chunk for bad input")

    monkeypatch.setattr(chunks_xla, "run_chunk", compiled)
    monkeypatch.setattr(chunks_xla, "run_fast_chunk", compiled)
    monkeypatch.setattr(chunks_native, "native_program", compiled)
    good = dict(make_system=rigid_body, params=INERTIAS, Q0=eyes(4), xi0=OMEGAS, dt=0.05, n_steps=10)
    cases = [
        (dict(chunk_steps=0), "chunk_steps"),
        (dict(chunk_steps=2.5), "chunk_steps"),
        (dict(batch_size=-3), "batch_size"),
        (dict(n_steps=0), "n_steps"),
        (dict(save_every=0), "save_every"),
        (dict(member_chunk=0), "member_chunk"),
        (dict(chunk_steps=5, save_every=4), "chunk_steps: must be a multiple of save_every"),
        (dict(params=INERTIAS[:3]), "params: 3 parameter rows for 4 initial conditions"),
        (dict(xi0=OMEGAS[:3]), "xi0: 3 initial velocities for 4 configurations"),
        (dict(params={"a": INERTIAS, "b": INERTIAS[:2]}), "params: every leaf needs the same leading"),
        (dict(Q0=np.zeros((4, 3))), "Q0"),  # members with Q of shape (3,): the velocity map says why
        (dict(xi0=OMEGAS[:, :2]), "xi0"),
        (dict(dt=np.array([0.1, 0.1])), "dt: expected a scalar or one step per member"),
        (dict(dt=-0.1), "dt: every step must be finite and positive"),
        (dict(P0=np.zeros((4, 3))), "P0: expected Q0's shape"),
        (dict(grid=True, make_system=rigid_body(INERTIAS[0]), params=None), "grid"),
        (dict(make_system=rigid_body(INERTIAS[0])), "params: must be None"),
        (dict(t0=1.0), "t0: set by sweep itself"),
        (dict(devices=0), "devices"),
        (dict(fast="yes"), "fast: expected True, False or 'auto'"),
        (dict(threads=0), "threads"),
        (dict(invariants={"scalar": lambda s, sol: jnp.sum(sol.momentum)}), "invariants: 'scalar'"),
        (
            dict(invariants={"short": lambda s, sol: sol.momentum[1:]}),
            "invariants: 'short' must return one value per node",
        ),
        (dict(scheme="sideways"), "scheme"),
        (dict(Q0=np.concatenate([eyes(3), np.diag([1.0, 1.0, -1.0])[None]])), r"Q0\[3\]: det Q = -1"),
        (
            dict(Q0=np.concatenate([eyes(2), 1.01 * eyes(1), np.diag([1.0, 1.0, -1.0])[None]])),
            r"Q0\[2\]: not a rotation matrix",
        ),  # the first bad row is named
        (dict(params=-INERTIAS), "inertia"),  # the constructor's own check, on the concrete first row
    ]
    for change, message in cases:
        with pytest.raises((ValueError, TypeError), match=message):
            cj.sweep(**{**good, **change})
    # the same on the fast path, whose lean chunk checks the member without tracing its march
    monkeypatch.setattr(chunks_xla, "_lean_program", compiled)
    monkeypatch.setattr(chunks_xla, "_fast_program", compiled)
    for change, message in cases:
        if "fast" not in change:
            with pytest.raises((ValueError, TypeError), match=message):
                cj.sweep(**{**good, **change, "fast": True})


SHARDED = r"""
import os
os.environ["XLA_FLAGS"] = "--xla_force_host_platform_device_count=2"
import jax, numpy as np
import clebsch_jax as cj
assert len(jax.devices()) == 2, jax.devices()
from tests.test_sweep import RB, INERTIAS, OMEGAS, eyes
rng = np.random.default_rng(7)
inertias = np.concatenate([INERTIAS, rng.uniform(0.5, 3.0, size=(3, 3))])
omegas = np.concatenate([OMEGAS, rng.normal(size=(3, 3))])
omegas[5, 0] = np.nan
args = (cj.models.rigid_body, inertias, eyes(7), omegas)
one = cj.sweep(*args, **RB)
two = cj.sweep(*args, devices=2, **RB)  # batch 0 on device 0, batch 1 on device 1
assert (one.n_devices, two.n_devices) == (1, 2), (one.n_devices, two.n_devices)
la, lb = jax.tree_util.tree_leaves(one), jax.tree_util.tree_leaves(two)
assert len(la) == len(lb) == 21
for a, b in zip(la, lb):
    assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True), (a, b)
assert list(one.failed_members) == [5] and np.any(one.drift["casimir"][:5] > 0)
print("identical", len(la))
# two batches side by side from two threads under the caller's default device: they run there
from clebsch_jax.batching import tables as tb
seen, collect = set(), tb.collect
tb.collect = lambda tables, one, run: (seen.update(one.carry.status.devices()), collect(tables, one, run))[1]
with jax.default_device(jax.devices()[1]):
    there = cj.sweep(*args, threads=2, **RB)
tb.collect = collect
assert seen == {jax.devices()[1]}, seen
for a, b in zip(la, jax.tree_util.tree_leaves(there)):
    assert np.array_equal(a, b, equal_nan=True)
print("default device", seen)
# many members, chunks handing over (Q, p), the lean chunk too, each sweep made twice: batched
# LAPACK kernels (the least squares of the hand-over) deadlocked here on the second sweep
B = 2048
many = (cj.models.rigid_body, np.broadcast_to(INERTIAS[0], (B, 3)), eyes(B), rng.normal(size=(B, 3)))
for fast in (False, True):
    runs = [cj.sweep(*many, dt=0.05, n_steps=20, chunk_steps=10, batch_size=B // 2, devices=2, fast=fast)
            for _ in range(2)]
    assert runs[0].n_devices == 2 and len(runs[0].failed_members) == 0
    assert np.array_equal(runs[0].final_momentum, runs[1].final_momentum)
print("many members twice")
"""


@pytest.mark.slow  # CI runs it; a second process with two host devices
def test_devices_split_the_members_and_the_results_are_identical():
    """Two CPU devices (XLA_FLAGS must be set before jax is imported: a subprocess). The 7
    members run in two batches of 4 (the last padded), one per device: every field of the
    table, the NaN member included, is bitwise equal to the one-device sweep. Then 2048 members
    in two batches, general and lean chunks, each sweep twice: it finishes (no deadlock) and
    repeats itself to the bit."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = {**os.environ, "PYTHONPATH": root + os.pathsep + os.environ.get("PYTHONPATH", "")}
    out = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(SHARDED)], capture_output=True, text=True, cwd=root, env=env, timeout=300
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert "identical 21" in out.stdout and "many members twice" in out.stdout


def test_a_check_without_a_batched_form_runs_on_every_row():
    """A user's `check_Q` is called once per concrete Q0[j] (the SO(n) models' check is
    vectorised instead: `check_rotation.batched`), and its sentence names the row."""
    seen = []

    def check(Q):
        seen.append(np.asarray(Q).copy())
        return "too far out" if np.asarray(Q)[0, 0] > 1.5 else None

    system = rigid_body(INERTIAS[0])
    system = cj.ClebschSystem(
        lagrangian=system.lagrangian,
        velocity_map=system.velocity_map,
        derivative_map=system.derivative_map,
        check_Q=check,
    )
    Q0 = eyes(3).copy()
    Q0[1, 0, 0] = 2.0
    with pytest.raises(ValueError, match=r"^Q0\[1\]: too far out"):
        cj.sweep(system, None, Q0, OMEGAS[:3], dt=0.05, n_steps=4)
    assert len(seen) == 2 and np.array_equal(seen[1], Q0[1])


@pytest.mark.slow  # block-Newton cluster programs on both paths
def test_a_sweep_of_vortex_clusters_defaults_to_block_newton_and_agrees_with_integrate():
    """Degenerate particle systems (point vortices) sweep with the block Newton matrix by
    default (`jacobian="dense"` keeps the dense one): the same trajectories to round-off as
    `integrate` with its dense default, and as the dense sweep."""
    rng = np.random.default_rng(11)
    G = rng.uniform(0.5, 1.5, (3, 4)) * np.array([1.0, -1.0, 1.0, -1.0])
    Q0 = np.array([[0.0, 1.0], [0.0, -1.0], [0.0, 0.5], [0.0, -0.5]]) + 0.05 * rng.normal(size=(3, 4, 2))
    xi0 = np.asarray(jax.vmap(cj.models.vortex_velocity)(jnp.asarray(G), jnp.asarray(Q0)))
    args = (cj.models.point_vortices, G, Q0, xi0)
    blocks = cj.sweep(*args, dt=0.02, n_steps=30, chunk_steps=15)
    dense = cj.sweep(*args, dt=0.02, n_steps=30, chunk_steps=15, jacobian="dense")
    # block chord updates converge linearly, dense Newton quadratically: the counts tell them apart
    assert np.all(blocks.newton_iterations > dense.newton_iterations)
    for m in range(3):
        sol = cj.integrate(cj.models.point_vortices(G[m]), Q0[m], xi0[m], dt=0.02, n_steps=30)
        # positions of size ~1 after 30 steps solved to round-off by both matrices
        np.testing.assert_allclose(blocks.final_Q[m], np.asarray(sol.Q[-1]), rtol=0, atol=1e-13)
        np.testing.assert_allclose(dense.final_Q[m], np.asarray(sol.Q[-1]), rtol=0, atol=1e-13)


PEAKON_BATCHES = r"""
import numpy as np, jax, jax.numpy as jnp
import clebsch_jax as cj
rng = np.random.default_rng(0)
B = 2048
Q0 = np.sort(2.0 * rng.normal(size=(B, 3)), axis=1)
p0 = np.abs(rng.normal(size=(B, 3))) + 0.5
xi0 = np.asarray(jax.vmap(cj.models.peakon_velocity)(jnp.asarray(Q0), jnp.asarray(p0)))
for _ in range(2):
    res = cj.sweep(cj.models.peakons, np.ones(B), Q0, xi0, dt=0.01, n_steps=20, chunk_steps=10, batch_size=B // 2)
print("finished", len(res.failed_members))
"""


@pytest.mark.slow  # CI runs it; a second process (a hang must not stop the test run)
def test_a_sweep_of_many_peakon_systems_finishes():
    """2048 systems of 3 peakons in batches of 1024, swept twice on one device. With the
    Lagrangian's Cholesky solve a LAPACK kernel, the batched triangular solve deadlocked on
    XLA's thread pool (the script timed out); batched, it is XLA operations now
    (`clebsch_jax.core.linalg.spd_solve`)."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = {**os.environ, "PYTHONPATH": root + os.pathsep + os.environ.get("PYTHONPATH", "")}
    out = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(PEAKON_BATCHES)],
        capture_output=True,
        text=True,
        cwd=root,
        env=env,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert "finished 0" in out.stdout


SWEEP_HOST = tuple(
    os.path.join("batching", f"{name}.py")
    for name in ("sweep", "config", "probe", "choose", "schedule", "tables", "chunks_xla", "chunks_native")
)
"""The modules of `cj.sweep`'s host code (those `clebsch_jax.batching.sweep` was split into)."""


@pytest.mark.slow  # compiles a sweep's programs for a batch shape of its own
def test_a_sweep_compiles_only_its_programs():
    """The sweep's host code deals the inputs out as NumPy arrays and device transfers: the only
    programs compiled from the sweep's own modules (`SWEEP_HOST`) are its jitted chunks (the initial
    multipliers are derived in the first chunk's program), never an eager JAX operation (a gather, a broadcast, ...), which
    would compile once per new shape on every first call."""
    n = 7  # a batch shape no other test uses
    inertias = np.concatenate([INERTIAS, INERTIAS[:3]])
    omegas = np.concatenate([OMEGAS, -OMEGAS[:3]])
    with compiles_recorded(where=SWEEP_HOST) as compiled:
        res = cj.sweep(rigid_body, inertias, eyes(n), omegas, dt=0.05, n_steps=6, chunk_steps=3)
    assert np.all(res.succeeded)
    assert set(compiled) <= {"jit(run_chunk)", "jit(stage)"}, compiled


@pytest.mark.slow  # two sweeps on XLA's path, compiled for this test
def test_a_repeated_sweep_traces_its_member_once(monkeypatch):
    """The probe of a member's shapes (a trace of `integrate`) depends only on one member's
    shapes and dtypes and the sweep's options: a second sweep reuses it (with other values,
    members or steps), a new chunk length traces again, and the table is the same either way."""
    from clebsch_jax.batching import probe

    monkeypatch.setattr(probe, "_TRACES", {})  # other tests' sweeps of these shapes are cached
    traces = []
    real = jax.eval_shape
    # the member's shape probe (`probe._trace_member`); the traced check and the first-step
    # probe's shapes are other traces, cached on their own
    member = lambda f: getattr(f, "__qualname__", "").startswith("_trace_member")  # noqa: E731
    monkeypatch.setattr(jax, "eval_shape", lambda f, *a, **k: (member(f) and traces.append(1)) or real(f, *a, **k))
    # on XLA: the native backend finds its kernel by a fingerprint, without this trace
    # (tests/test_native_keys.py)
    run = dict(dt=0.05, n_steps=6, chunk_steps=3, backend="xla")
    first = cj.sweep(rigid_body, INERTIAS, eyes(4), OMEGAS, **run)
    again = cj.sweep(rigid_body, INERTIAS, eyes(4), OMEGAS, **run)
    assert len(traces) == 1
    np.testing.assert_array_equal(again.final_momentum, first.final_momentum)
    cj.sweep(rigid_body, INERTIAS[:3], eyes(3), OMEGAS[:3], **{**run, "n_steps": 9})  # the same chunk
    assert len(traces) == 1
    cj.sweep(rigid_body, INERTIAS, eyes(4), OMEGAS, **{**run, "chunk_steps": 2})  # a new chunk: traced
    assert len(traces) == 2
    assert len(probe._TRACES) <= probe._TRACES_MAX
