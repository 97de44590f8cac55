"""The ensemble pilot's members marched together (`clebsch_jax.march.members.MemberMarch`): each
member's run the one `integrate` makes alone, to the bit, a failing member's failure included,
and the plan the same as the plan piloted member by member (each by its own `integrate`)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

import clebsch_jax as cj
from clebsch_jax.march.members import MemberMarch
from clebsch_jax.roots.status import Status

INERTIAS = np.array([[2.0, 1.0, 2.0 / 3.0], [1.5, 1.0, 0.5], [2.0, 1.2, 0.9]])
OMEGAS = np.array([[0.4, 0.0, 1.3], [1.0, -0.3, 0.8], [-0.5, 0.9, 1.6]])
Q0S = np.broadcast_to(np.eye(3), (3, 3, 3))


def _members(omegas=OMEGAS):
    """A member per inertia and ω: systems whose arrays differ, of one structure."""
    return [(cj.models.rigid_body(jnp.asarray(i)), q, w, None) for i, q, w in zip(INERTIAS, Q0S, omegas)]


def _same(a, b):
    for name in ("Q", "momentum", "xi", "result", "failed_step", "valid"):
        np.testing.assert_array_equal(np.asarray(getattr(a, name)), np.asarray(getattr(b, name)), err_msg=name)
    for x, y in zip(a.stats, b.stats):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_members_marched_together_are_each_members_own_run():
    """One kernel call per chunk for every member gives each the `integrate` run it gets alone, to
    the bit; a member whose step is too large for the stage sweeps fails as it does alone."""
    method = cj.GaussLegendre(order=4)
    members = _members(np.concatenate([OMEGAS[:2], 40.0 * OMEGAS[2:]]))  # the last far too fast for dt
    march = MemberMarch(members, 0.0, True, "native")
    sols = march(method, 0.3, 40)
    assert march._ready[method] is not None  # one kernel for all: the path under test
    for sol, (system, Q0, xi0, _) in zip(sols, members):
        alone = cj.integrate(system, Q0, xi0, dt=0.3, n_steps=40, method=method, throw=False, backend="native")
        _same(sol, alone)
    assert [int(s.result) == Status.SUCCESS for s in sols] == [True, True, False]


def test_the_batched_pilot_makes_the_member_by_member_plan(monkeypatch):
    """The plan piloted with the members together equals the plan piloted by each member's own
    `integrate` calls: method, step, predicted error, every candidate's measurements, the check."""
    run = dict(t_final=60.0, accuracy=1e-6, candidates=({}, {"scheme": "gauss", "order": 4}), backend="native")
    together = cj.choose_sweep_step(cj.models.rigid_body, INERTIAS, Q0S, OMEGAS, **run)
    monkeypatch.setattr(MemberMarch, "_prepared", lambda self, *args: None)  # each member by integrate
    alone = cj.choose_sweep_step(cj.models.rigid_body, INERTIAS, Q0S, OMEGAS, **run)
    assert together == alone
    assert sorted(together.piloted) == [0, 1, 2]
    assert together.check in ("met", "at round-off")
