r"""Issue 8: failure as a value. Every failure kind, injected at a known step into one member of
a vmapped batch, for every march: reported with its status, its step and its member, the member's
later states NaN and flagged invalid, and the other members untouched.

**The injected faults.** A "clock" coordinate of the configuration moves at a constant rate and
the Lagrangian is the free kinetic energy $T(\xi)$ until the clock passes a threshold $c$ (the
threshold and the kind of fault are array leaves of the system, so one compiled march serves
every kind and every member). Past $c$ the Lagrangian of a faulty member becomes

- `NONFINITE`: $T + 0\cdot\sqrt{c - \text{clock}}$, i.e. NaN (and exactly $T$ before $c$);
- `SINGULAR`: $0$: its Hessian in $\xi$ vanishes, so the step equations of Lemma 20 lose their
  $\delta l/\delta\xi$ block and the Newton Jacobian is exactly singular (for the full march the
  $\xi$ row reads $-P^n = 0$ while the $Q^n$ row asks $P^n = p^n \ne 0$);
- `MAX_ITERATIONS`: $T + \sum_i \xi_i^4$: the step is still solvable, but its equation turns
  cubic while every march runs with `max_newton_iterations=1` (one Jacobian per solve, enough
  for the linear or gently nonlinear steps before $c$).

A threshold jump through `jnp.where` has a zero derivative in Q, so before $c$ the dynamics are
exactly free: free particles on a line (clock $Q_0$, $Q_0^n = n\Delta t\,v$ for the forward
difference), and the rigid body spinning about its principal axis $e_3$ (clock the rotation
angle: $\approx n\Delta t\,\omega_3$, to $O(\Delta t^3)$ per step for Cayley, far inside the half
step of margin left below).

**The known step.** With the threshold half-way between nodes k and k + 1: the left principle
evaluates l at the first node of a step, so a single-solve march fails at step k + 1; a
composition (`order=4`, Suzuki p4s5 of left∘right half steps) evaluates l also inside a step,
at 0.41, 0.83, 0.17, 0.59 and 1 of it (the particles' sub-steps move them by exactly those
fractions), so it fails at step k itself.

Cost: one compiled march per march kind (the faults and thresholds are traced), 10 steps; the
sweep test (one more compiled chunk program) is marked slow.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.tree_util import Partial

import clebsch_jax as cj
from clebsch_jax import Status

DT, N_STEPS = 0.1, 10
K = 6  # the threshold lies half-way between nodes K and K + 1 of the failing member
HEALTHY = 0  # "kind" of a member without a fault
FAULTS = [Status.NONFINITE, Status.SINGULAR, Status.MAX_ITERATIONS]
INERTIA = (2.0, 1.0, 2.0 / 3.0)


def _faulty(kind, threshold, clock, xi, kinetic):
    """The Lagrangian of the module docstring: `kinetic` before the clock passes `threshold`,
    then the fault `kind` (a `Status` code; 0: none)."""
    past = clock > threshold
    keep = jnp.where((kind == Status.SINGULAR) & past, 0.0, 1.0)
    stiff = jnp.where((kind == Status.MAX_ITERATIONS) & past, 1.0, 0.0) * jnp.sum(xi**4)
    # the NaN branch only for that kind: a where over a NaN would also poison its gradient
    nan = 0.0 * jnp.sqrt(jnp.where(kind == Status.NONFINITE, threshold - clock, 1.0))
    return keep * kinetic + stiff + nan


def _particles_lagrangian(kind, threshold, xi, Q):
    return _faulty(kind, threshold, Q[0], xi, 0.5 * jnp.sum(xi * xi))


def _body_lagrangian(kind, threshold, xi, Q):
    kinetic = 0.5 * jnp.sum(jnp.asarray(INERTIA) * xi * xi)
    return _faulty(kind, threshold, jnp.arctan2(Q[1, 0], Q[0, 0]), xi, kinetic)


def _translation(xi, Q):
    return xi


_RIGHT_MULTIPLICATION = cj.models.rigid_body(INERTIA).velocity_map  # Q ↦ Q hat(ξ), the model's own


def particles(params):
    """Two free particles on a line, Q, ξ of shape (2,); the clock is particle 0."""
    kind, threshold = params
    return cj.ClebschSystem(
        lagrangian=Partial(_particles_lagrangian, kind, threshold),
        velocity_map=_translation,
        derivative_map=cj.forward_difference,
    )


def body(params):
    """The free rigid body on SO(3) (Cayley); the clock is the angle of Q's first column in the xy-plane."""
    kind, threshold = params
    return cj.ClebschSystem(
        lagrangian=Partial(_body_lagrangian, kind, threshold),
        velocity_map=_RIGHT_MULTIPLICATION,
        derivative_map=cj.cayley,
    )


# march → (system, Q0, the members' ξ0 (member 1 is the one that reaches the threshold), its
# clock rate, integrate options). Members 0 and 2 move generically and slower: their clocks
# stay below 0.5 < c over the run (checked: they succeed).
_XI_PARTICLES = np.array([[0.3, -0.2], [1.0, 0.4], [0.4, 0.7]])
MARCHES = {
    "full": (particles, np.zeros(2), _XI_PARTICLES, 1.0, {"scheme": "left"}),
    "blocks": (particles, np.zeros(2), _XI_PARTICLES, 1.0, {"scheme": "left", "jacobian": "blocks"}),
    "order4": (particles, np.zeros(2), _XI_PARTICLES, 1.0, {"order": 4}),
    "reduced": (
        body,
        np.eye(3),
        np.array([[0.3, 0.1, 0.2], [0.0, 0.0, 1.0], [-0.2, 0.3, 0.4]]),
        1.0,
        {"scheme": "left"},
    ),
}
FORMS = {"full": "full", "blocks": "full", "order4": "full", "reduced": "reduced"}


def threshold_of(march):
    return (K + 0.5) * DT * MARCHES[march][3]


def expected_step(march):
    """The first failing step (module docstring): K + 1 for one left solve per step, K for a
    composition, which evaluates l inside the step that crosses the threshold."""
    return K if MARCHES[march][4].get("order") else K + 1


def run(march, kinds, throw=False):
    """The three members of `march` under `jax.vmap`, with fault kinds `kinds` (3,)."""
    make, Q0, xi0s, _, options = MARCHES[march]
    thresholds = jnp.full(3, threshold_of(march))

    def member(xi0, kind, threshold):
        return cj.integrate(
            make((kind, threshold)), Q0, xi0, dt=DT, n_steps=N_STEPS, max_newton_iterations=1, throw=throw, **options
        )

    return jax.vmap(member)(jnp.asarray(xi0s), jnp.asarray(kinds), thresholds)


@functools.lru_cache(maxsize=None)
def healthy_batch(march):
    """The same batch without the faulty member (its fault removed: same shapes, same program)."""
    sol = run(march, [HEALTHY, HEALTHY, HEALTHY])
    np.testing.assert_array_equal(np.asarray(sol.result), Status.SUCCESS)
    return sol


def _member(tree, i):
    return jax.tree_util.tree_map(lambda a: np.asarray(a)[i], tree)


@pytest.mark.parametrize("kind", FAULTS, ids=["nonfinite", "singular", "max_iterations"])
@pytest.mark.parametrize("march", list(MARCHES))
def test_an_injected_failure_is_reported_at_its_step_and_member(march, kind):
    """Member 1 of 3 fails with status `kind` at the known step: the code, `failed_step`, the
    statuses, `valid`, NaN exactly at the invalid nodes, the message of `raise_if_failed()` and
    of `throw=True` under vmap, and members 0 and 2 bit for bit as without the fault."""
    sol = run(march, [HEALTHY, kind, HEALTHY])
    k = expected_step(march)
    # l depends on Q (the clock), so the left principle is of order 1; the composition of order 4
    assert sol.form == FORMS[march] and sol.order == (4 if march == "order4" else 1)

    # status, step and member
    np.testing.assert_array_equal(np.asarray(sol.result), [Status.SUCCESS, kind, Status.SUCCESS])
    np.testing.assert_array_equal(np.asarray(sol.failed_step), [-1, k, -1])
    bad = _member(sol, 1)
    np.testing.assert_array_equal(bad.stats.status[:k], Status.SUCCESS)
    assert bad.stats.status[k] == kind
    np.testing.assert_array_equal(bad.stats.status[k + 1 :], Status.SKIPPED)
    # skipped steps and nodes count no work and report no residual
    for stats in (bad.stats, bad.nodal_stats):
        skipped = np.asarray(stats.status) == Status.SKIPPED
        assert np.all(np.asarray(stats.iterations)[skipped] == 0) and np.all(np.asarray(stats.jacobians)[skipped] == 0)
        assert np.all(np.isnan(np.asarray(stats.residual_norm)[skipped]))
    assert np.all(np.asarray(bad.stats.iterations)[:k] > 0)

    # valid exactly up to node k, the node the failed step leaves from
    np.testing.assert_array_equal(bad.valid, np.arange(N_STEPS + 1) <= k)
    nodes = [a for a in (bad.Q, bad.p, bad.momentum) if a is not None]
    for a in nodes:
        assert np.all(np.isfinite(a[: k + 1])) and np.all(np.isnan(a[k + 1 :]))
    for a in (bad.xi_step, bad.P):  # per step: NaN from the failed step on
        if a is not None:
            assert np.all(np.isfinite(a[:k])) and np.all(np.isnan(a[k:]))
    # nodal velocities: NaN at every invalid node, finite at every valid node whose own solve
    # (Lemma 7) succeeded; only node k may report a failed nodal solve, and only when it is
    # already past the threshold (the single-solve marches)
    assert np.all(np.isnan(bad.xi[k + 1 :]))
    solved = bad.nodal_stats.status[: k + 1] == Status.SUCCESS
    np.testing.assert_array_equal(np.isfinite(bad.xi[: k + 1]).all(-1), solved)
    assert np.all(solved[:k])
    assert solved[k] or k == K + 1

    # the message: which member, which step, what happened, what to try
    message = Status.MESSAGES[kind]
    with pytest.raises(cj.IntegrationError) as info:
        sol.raise_if_failed()
    text = str(info.value)
    assert f"batch member 1, step {k} of {N_STEPS}" in text and message in text
    assert "smaller dt" in text and "max_newton_iterations" in text and "throw=False" in text
    with pytest.raises(Exception, match=rf"batch member 1, step {k} of {N_STEPS}") as info:
        jax.block_until_ready(run(march, [HEALTHY, kind, HEALTHY], throw=True))
    assert message in str(info.value)

    # the other members: bit for bit as in the batch without the faulty member (the same
    # compiled program; a vmapped while loop freezes members that have stopped, so a member's
    # arithmetic does not depend on how long the others iterate)
    ref = healthy_batch(march)
    for i in (0, 2):
        jax.tree_util.tree_map(np.testing.assert_array_equal, _member(sol, i), _member(ref, i))


@pytest.mark.slow  # compiling sweep's chunk program costs ~12 s of the suite's budget
def test_sweep_reports_each_fault_at_its_global_step():
    """`cj.sweep` over faulty particle systems (the full march, chunks of 5 steps, batches of 3):
    every member's status and first failed step, counted from the start of the run, are those of
    `integrate` above, with thresholds that put the failures in different chunks."""
    ks = np.array([0, 6, 2, 8, 6])  # member m's threshold lies between nodes ks[m] and ks[m] + 1
    kinds = np.array([HEALTHY, Status.NONFINITE, Status.SINGULAR, Status.MAX_ITERATIONS, HEALTHY])
    thresholds = (ks + 0.5) * DT
    xi0s = np.array([[1.0, 0.1], [1.0, 0.4], [1.0, -0.3], [1.0, 0.2], [0.5, 0.5]])
    res = cj.sweep(
        particles,
        (kinds, thresholds),
        np.zeros((5, 2)),
        xi0s,
        dt=DT,
        n_steps=N_STEPS,
        chunk_steps=5,
        batch_size=3,
        max_newton_iterations=1,
    )
    failing = kinds != HEALTHY
    np.testing.assert_array_equal(res.failed_members, np.flatnonzero(failing))
    np.testing.assert_array_equal(res.status, kinds)
    np.testing.assert_array_equal(res.failed_step, np.where(failing, ks + 1, -1))
    assert np.all(np.isnan(res.final_Q[failing])) and np.all(np.isfinite(res.final_Q[~failing]))
    # the healthy members: free particles, Q = n Δt ξ0 (forward difference, exact up to round-off)
    np.testing.assert_allclose(res.final_Q[~failing], N_STEPS * DT * xi0s[~failing], rtol=1e-14)
    with pytest.raises(cj.IntegrationError, match=r"3 of 5 members failed: member 1 at step 7 .*smaller dt"):
        res.raise_if_failed()


@pytest.mark.slow  # two more compiled marches (~15 s); the default run checks the pair's schedule in test_composition
def test_a_shared_jacobian_reports_each_fault_as_the_unshared_pair():
    """The reduced left step and its adjoint over half steps (`order=2`), the second half
    step's solve starting from the first one's Jacobian (`SymmetricPair.shared_jacobian`,
    the default) or not: for every fault kind the same status at the same step of the same
    member, the later nodes NaN and invalid, and a message naming member and step."""
    make, Q0, xi0s, _, _ = MARCHES["reduced"]
    thresholds = jnp.full(3, threshold_of("reduced"))

    def batch(shared, kind):
        method = cj.SymmetricPair(cj.ReducedStep(root_finder=cj.Newton(max_iterations=1)), shared_jacobian=shared)
        march = lambda xi0, kind, threshold: cj.integrate(  # noqa: E731
            make((kind, threshold)), Q0, xi0, dt=DT, n_steps=N_STEPS, method=method, throw=False
        )
        return jax.vmap(march)(jnp.asarray(xi0s), jnp.asarray([HEALTHY, kind, HEALTHY]), thresholds)

    for kind in FAULTS:
        shared, alone = batch(None, kind), batch(False, kind)
        assert shared.method == "right(h/2) o left(h/2)"
        np.testing.assert_array_equal(np.asarray(shared.result), [Status.SUCCESS, kind, Status.SUCCESS])
        np.testing.assert_array_equal(np.asarray(shared.failed_step), np.asarray(alone.failed_step))
        np.testing.assert_array_equal(np.asarray(shared.stats.status), np.asarray(alone.stats.status))
        np.testing.assert_array_equal(np.asarray(shared.valid), np.asarray(alone.valid))
        k = int(shared.failed_step[1])
        bad = _member(shared, 1)
        assert 0 < k < N_STEPS and np.all(np.isnan(bad.Q[k + 1 :])) and np.all(np.isfinite(bad.Q[: k + 1]))
        with pytest.raises(cj.IntegrationError, match=rf"batch member 1, step {k} of {N_STEPS}"):
            shared.raise_if_failed()
