r"""Accuracy plans for an ensemble: `choose_sweep_step`, the plan `sweep(..., t_final=T,
accuracy=tol)` runs. `clebsch_jax.choose_step` pilots one trajectory; a sweep runs one method and
step for all its members, and a member that moves faster than the piloted one makes a larger
error at that step (and its stage sweeps may stop contracting). So the pilot is run on a
**sample** of the members, and the plan's step is the one the worst of them allows.

**The sample** (`pilot_members`): the first member, and the `PILOT_MEMBERS` − 1 others of largest
**rate**
$$r_m = \frac{1}{\tau_m} = \frac{\|\mathcal L_{\xi^0_m} Q^0_m\|_\infty}{\|Q^0_m\|_\infty},$$
how fast member m's configuration moves at the start relative to its size
(`clebsch_jax.march.pilot.time_scale`), each with its own system from `params`: one vectorised
evaluation of the velocity map for every member (`member_rates`), before any march. A member
moving k times faster along a similar trajectory is the same motion at k times the step, so
its error constant is $k^{p+1}$ times larger: the rate orders the members by the error a common
step makes, as far as their trajectories are alike.

**The plan** (`clebsch_jax.march.accuracy.plan_members`): the pilot's horizon and steps come from
the smallest τ of the sample; at each pilot step every sampled member is marched with the
candidate's stepper — one compiled program, and where it is a native kernel one call of it with
the members in its lanes (`clebsch_jax.march.members.MemberMarch`) — and the worst member decides: the largest difference at each node (each member relative to its own
sizes), the most iterations per step (and so the stage sweeps' contraction margin), any
member's failure; the check of the chosen step (`clebsch_jax.march.check`) runs on them too.
`AccuracyPlan.piloted` records the members piloted, by their index in the sweep.

**Limits.** Members outside the sample are not measured: the rate is a guess from the initial
state, and a member whose motion is harder in another way (nearer a separatrix, a close
encounter later in the run) is not seen unless it is sampled; name the members to pilot with
`members=`. The module docstring of `clebsch_jax.march.accuracy` states the model's own limits.
"""

from __future__ import annotations

import jax
import numpy as np

from ..march.accuracy import AccuracyPlan, method_options, plan_members
from ..march.pilot import motion
from .config import make_members, member_row

__all__ = ["PILOT_MEMBERS", "choose_sweep_step", "member_rates", "pilot_members", "plan_for_sweep"]

PILOT_MEMBERS = 8
"""The most members an ensemble's pilot marches: the first and the fastest others
(`pilot_members`)."""


def choose_sweep_step(
    make_system,
    params,
    Q0,
    xi0,
    *,
    t_final,
    accuracy,
    grid: bool = False,
    P0=None,
    members=None,
    candidates=None,
    time_scale: float | None = None,
    check_energy=True,
    backend: str = "auto",
    **options,
) -> AccuracyPlan:
    r"""The method and step that reach `accuracy` at `t_final` on every member of a sweep, as far
    as a pilot on a sample of them shows: `clebsch_jax.choose_step`'s plan, made on the first
    member and the `PILOT_MEMBERS` − 1 fastest others (`clebsch_jax.batching.ensemble_plan`).

    ```python
    plan = cj.choose_sweep_step(cj.models.rigid_body, inertias, Q0s, omegas, t_final=1e3, accuracy=1e-8)
    plan.piloted                  # the members the pilot marched
    res = cj.sweep(cj.models.rigid_body, inertias, Q0s, omegas, **plan.integrate_options())
    ```

    **Arguments:**

    - `make_system`, `params`, `Q0`, `xi0`, `grid`, `P0`: as for `clebsch_jax.sweep`.
    - `t_final`, `accuracy`, `candidates`, `time_scale`, `check_energy`, `backend`, `**options`:
      as for `clebsch_jax.choose_step` (`time_scale` then applies to every member piloted).
    - `members`: None (default: the sample above), or the indices of the sweep's members to
      pilot (the first one given resolves the candidates).

    **Returns:** an `AccuracyPlan` whose `piloted` names the members piloted; `sweep(...,
    t_final=T, accuracy=tol)` makes this plan and records it as `SweepResult.accuracy_plan`."""
    ensemble = make_members(make_system, params, Q0, xi0, P0, 1.0, grid)  # the step is the plan's
    if members is None:
        chosen = pilot_members(member_rates(make_system, ensemble))
    else:
        chosen = tuple(int(m) for m in np.atleast_1d(np.asarray(members)))
        if not chosen or any(not 0 <= m < ensemble.B for m in chosen):
            raise ValueError(f"members: expected indices of the sweep's {ensemble.B} members, got {members!r}.")
    trajectories = [_member(make_system, ensemble, m) for m in chosen]
    arguments = dict(t_final=t_final, accuracy=accuracy, candidates=candidates, time_scale=time_scale)
    arguments.update(check_energy=check_energy, backend=backend)
    return plan_members(trajectories, **arguments, piloted=chosen, **options)


def plan_for_sweep(make_system, params, Q0, xi0, P0, grid, given: dict, **arguments) -> AccuracyPlan:
    """`sweep`'s plan: `given` (its options) checked against `accuracy=`, the method options not
    at their defaults passed on to `choose_sweep_step` with `arguments`."""
    options = method_options(given, arguments)
    return choose_sweep_step(make_system, params, Q0, xi0, grid=grid, P0=P0, **arguments, **options)


def member_rates(make_system, ensemble) -> np.ndarray:
    r"""(B,) each member's rate $1/\tau_m$ (module docstring), from its own system: the velocity
    map of every member in one `jax.vmap`; 0 for a member at rest, NaN for one whose data are
    not finite (such a member fails in the sweep, and is not piloted)."""
    Q0 = ensemble.Q0[ensemble.ic_index]
    xi0 = ensemble.xi0[ensemble.ic_index]
    if ensemble.builder is None:
        speed, size = jax.vmap(lambda q, x: motion(make_system, q, x))(Q0, xi0)
    else:
        rows = jax.tree_util.tree_map(lambda a: a[ensemble.param_index], ensemble.params)
        speed, size = jax.vmap(lambda p, q, x: motion(ensemble.builder(p), q, x))(rows, Q0, xi0)
    return np.asarray(speed) / np.asarray(size)


def pilot_members(rates, k: int = PILOT_MEMBERS) -> tuple:
    """The members to pilot: the first, then the k − 1 others of largest finite rate (the
    earlier one first among equal rates), as indices in the sweep."""
    rates = np.asarray(rates, dtype=float)
    others = np.flatnonzero(np.isfinite(rates[1:])) + 1
    others = others[np.argsort(-rates[others], kind="stable")][: max(0, k - 1)]
    return (0, *(int(m) for m in others))


def _member(make_system, ensemble, m: int) -> tuple:
    """(system, Q0, xi0, P0) of member m, as `integrate` takes them."""
    j, row = int(ensemble.ic_index[m]), member_row(ensemble, m)
    system = make_system if row is None else ensemble.builder(row)
    P0 = None if ensemble.P0 is None else ensemble.P0[j]
    return system, ensemble.Q0[j], ensemble.xi0[j], P0
