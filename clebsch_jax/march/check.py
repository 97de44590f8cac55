r"""The check of an accuracy plan at its own step (`clebsch_jax.choose_step`): the chosen method
marched over the pilot's horizon at the planned step h and at h/2, the error's growth in time
measured there, and the step reduced while the error predicted at `t_final` exceeds `accuracy`.

**Why.** The pilot (`clebsch_jax.march.pilot`) measures the error constant C at its own steps
h₀, h₀/2, … and the plan extrapolates it to the planned step as C hᵖ. On near-integrable motion
that fails near a **step-size resonance**: when a multiple of h times a frequency of the motion
comes near a multiple of 2π, the error constant of a symmetric or symplectic method jumps
(numerical resonances: the small denominators of the perturbation series behind the modified
equations, Hairer, Lubich & Wanner, *Geometric Numerical Integration*, chapters X and XIII).
A pilot step and the planned one can lie on different sides of a resonance, and C hᵖ is then
short by an order of magnitude or more (benchmarks/README.md: the leapfrogging clusters). The
error's growth in time is measured too, so that growth faster than linear over the window is
extrapolated as such.

**The measurement.** The runs at h and h/2 over $T_c = k h \approx T_p$ give Richardson's
estimate of the error at h, $\hat e(t) = d(t)/(1 - 2^{-p})$, the worst member's at each node
(`clebsch_jax.march.pilot.state_error`). Its running maximum $E(t) = \max_{s \le t}\hat e(s)$ (an
envelope: a phase error oscillates along an orbit) is fitted as $E(t) \approx c\,(t - t_0)^q$ by
least squares in log-log over the second half of $T_c$, with q held in [1, `GROWTH_CAP`]:
linear growth (integrable and near-integrable motion, the model of `clebsch_jax.march.pilot`)
at least, and at most quadratic, the growth of a phase error whose frequency error itself
drifts. The error predicted at T is
$$e(T) \approx E(T_c)\,\Big(\frac{T - t_0}{T_c}\Big)^{q}.$$
If it exceeds `accuracy`, the step is reduced to $h\,(\texttt{accuracy}/e(T))^{1/p}$ (whole
steps ending at T) and checked again, at most `CHECK_TRIES` times in all. Runs at fixed steps
and a fit: two calls give the same plan.

**Limits.** The fit sees only $[t_0, t_0 + T_c]$: growth that starts later (a close encounter,
chaotic divergence beyond the Lyapunov time, where errors grow exponentially) is not seen, and
the cap makes the extrapolation of an exponential growth too optimistic. A plan whose check did
not meet `accuracy` after `CHECK_TRIES` says so (`AccuracyPlan.check`), as does one whose check
failed to run.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .pilot import PILOT_MIN_STEPS, ROUNDOFF_FLOOR, nodes, run_record, sizes, state_error, work_per_step

__all__ = ["CHECK_TRIES", "GROWTH_CAP", "check_plan", "growth_exponent"]

CHECK_TRIES = 3
"""The most steps an accuracy plan checks (the planned one and at most two reductions)."""

GROWTH_CAP = 2.0
"""The largest growth exponent q the check extrapolates with (module docstring)."""


def growth_exponent(ts, err, t0: float) -> float:
    r"""q of $E(t) \approx c\,(t - t_0)^q$, E the running maximum of `err` at the nodes `ts`: the
    least-squares slope of log E against log(t − t0) over the nodes of the second half of the
    span where E > 0, held in [1, `GROWTH_CAP`] (1 when fewer than two such nodes)."""
    span = np.asarray(ts, dtype=float) - t0
    envelope = np.maximum.accumulate(np.asarray(err, dtype=float))
    late = (span >= 0.5 * span[-1]) & (span > 0) & (envelope > 0)
    if np.count_nonzero(late) < 2:
        return 1.0
    slope = np.polyfit(np.log(span[late]), np.log(envelope[late]), 1)[0]
    return float(np.clip(slope, 1.0, GROWTH_CAP))


def check_plan(march, stepper, system, row, t0: float, horizon: float, pilot_horizon: float, accuracy: float):
    """(row, growth, check) for the chosen candidate's `Candidate` `row`: its `dt`, `n_steps`,
    `predicted_error`, `predicted_work` replaced by the checked step's and the check's work added
    to its `pilot_work`; the growth exponent measured at the last step checked (None if no check
    ran); what the check found: "met", "at round-off", "not met" or "not run: ..."."""
    p, dt, n_steps = row.order, row.dt, row.n_steps
    work, growth, found, predicted = 0.0, None, "not run", row.predicted_error
    for attempt in range(CHECK_TRIES):
        if attempt:  # the step the last check predicts `accuracy` at, in whole steps ending at T
            h = dt * (accuracy / predicted) ** (1.0 / p)
            n_steps = max(n_steps + 1, math.ceil(horizon / h * (1 - 1e-12)))
            dt = horizon / n_steps
        k = max(PILOT_MIN_STEPS, round(pilot_horizon / dt))
        coarse, fine = march(stepper, dt, k), march(stepper, dt / 2, 2 * k)
        failed = False
        for sols, n in ((coarse, k), (fine, 2 * k)):
            _, cost, failed_here = run_record(stepper, system, sols, n)
            work, failed = work + cost, failed or failed_here
        if failed:
            found = f"not run: a member failed at step {dt:.3g}"
            break
        d = np.max([_difference(a, b) for a, b in zip(coarse, fine)], axis=0) / (1 - 2.0**-p)
        growth = growth_exponent(t0 + np.arange(k + 1) * dt, d, t0)
        if np.max(d) <= ROUNDOFF_FLOOR * np.finfo(float).eps * math.sqrt(2 * k):
            found = "at round-off"
            break
        predicted = float(np.max(d)) * (horizon / (k * dt)) ** growth
        found = "met" if predicted <= accuracy else "not met"
        if found == "met":
            break
    if n_steps != row.n_steps:
        its = row.iterations_per_step
        row = dataclasses.replace(
            row, dt=dt, n_steps=n_steps, predicted_work=n_steps * work_per_step(stepper, system, its)
        )
    if found in ("met", "not met"):
        row = dataclasses.replace(row, predicted_error=predicted)
    return dataclasses.replace(row, pilot_work=row.pilot_work + work), growth, found


def _difference(a, b) -> np.ndarray:
    """The error measure between a run at h and one at h/2, at the first's nodes."""
    coarse, (Qb, mb) = nodes(a), nodes(b)
    return state_error(coarse, (None if Qb is None else Qb[::2], mb[::2]), sizes(coarse))
