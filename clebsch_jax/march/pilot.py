r"""The pilot of an accuracy plan (`clebsch_jax.choose_step`): one candidate method marched over a
short horizon at halved steps, and what those runs measure — its error constant under the
linear error-growth model, its order as observed, the largest step at which the model held and
its iterations per step.

**The error measure.** The error of a run at a node is the max-norm error of its configuration
and of its momentum map, each relative to its size at the start (`state_error`):
$$e(t) = \max\Big(\frac{\|Q_h(t) - Q(t)\|_\infty}{\|Q^0\|_\infty},
\frac{\|\mu_h(t) - \mu(t)\|_\infty}{\|\mu^0\|_\infty}\Big),$$
(a size of zero is replaced by 1: the error is then absolute; without Q, with
`reconstruct=False`, the momentum alone).

**The model** (Hairer, Lubich & Wanner, *Geometric Numerical Integration*, §X.3): a symmetric or
symplectic method of order p applied to integrable (or near-integrable) motion makes a global
error that grows linearly in time, $e(t) \approx C\,(t - t_0)\,h^p$, for $t \lesssim h^{-p}$: the
error of the frequencies, $O(h^p)$, accumulates as a phase error while the actions stay
$O(h^p)$ close. The pilot measures $C$ on the second half of its horizon as
$\max_t e(t) / ((t - t_0) h^p)$ (an envelope: a phase error oscillating along an orbit is
bounded by it).

**Richardson's estimate.** No exact solution is at hand: runs at $h, h/2, h/4, \dots$ are compared
pairwise, $d_k(t) = e(y_{h_k}(t), y_{h_{k+1}}(t))$, and in the asymptotic regime
$d_k \approx (1 - 2^{-p})\,e_{h_k}$, the ratio $d_k / d_{k+1} \approx 2^p$ showing that it holds.
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np

from ..roots.status import Status
from ..steppers.gauss import GaussLegendre

__all__ = [
    "PILOT_TIME_SCALES",
    "PILOT_FIRST_STEP",
    "PILOT_HALVINGS",
    "PILOT_MIN_STEPS",
    "PILOT_DOUBLINGS",
    "ORDER_SLACK",
    "ROUNDOFF_FLOOR",
    "GAUSS_STAGE_SWEEP_COST",
    "STEP_COST",
    "NEWTON_SOLVE_COST",
    "NEWTON_UPDATE_COST",
    "MAX_CONTRACTION",
    "Measured",
    "contraction_step",
    "motion",
    "time_scale",
    "nodes",
    "sizes",
    "run_record",
    "state_error",
    "work_per_step",
    "run_pilot",
]

PILOT_TIME_SCALES = 32
"""The pilot's horizon, in time scales τ (`time_scale`), when the run is longer."""

PILOT_FIRST_STEP = 0.5
"""The pilot's first (largest) step, in time scales τ."""

PILOT_MIN_STEPS = 8
"""The fewest steps a pilot run makes over the pilot's horizon."""

PILOT_DOUBLINGS = 2
"""At most this many pilots again from twice the first step, when the step the accuracy allows is
above the largest the pilot tried (`clebsch_jax.march.accuracy`)."""

MAX_CONTRACTION = 0.25
"""The largest contraction factor of a Gauss–Legendre step's stage sweeps that a plan steps at
(`contraction_step`). The factor grows like the step times how fast the state moves, and the
sweeps diverge from 1: a quarter leaves room for members of an ensemble, or later parts of the
run, that move up to four times faster than the pilot's trajectory."""

PILOT_HALVINGS = 5
"""At most this many halvings of the pilot's step per candidate beyond the first three runs."""

ORDER_SLACK = 1.0
"""The asymptotic regime is taken to hold when the observed order is at least p − ORDER_SLACK."""

ROUNDOFF_FLOOR = 100.0
"""A difference below ROUNDOFF_FLOOR × ε × √(steps) is round-off: it resolves no order and bounds
the error constant from above."""

GAUSS_STAGE_SWEEP_COST = 1.0
"""The unit of predicted work: one fixed-point sweep of one Gauss–Legendre stage."""

STEP_COST = 0.25
"""The cost of a step apart from its solves (its nodal velocity, the energy check), in Gauss
stage-sweeps. This and the two below are a least-squares fit, relative to each point's, of the
CPU time per step of the native rigid-body points, Gauss–Legendre and compositions, of
`benchmarks/results/work_precision_ensembles.json` (scene `rigid_body`) against (stage-sweeps,
solves, updates, 1); `tests/test_accuracy.py` refits them from that file."""

NEWTON_SOLVE_COST = 1.24
"""A Newton solve of a (sub-)step, before its updates, in Gauss stage-sweeps (as `STEP_COST`)."""

NEWTON_UPDATE_COST = 0.42
"""A Newton update, in Gauss stage-sweeps (as `STEP_COST`)."""


@dataclasses.dataclass(frozen=True)
class Measured:
    """What the pilot measured of one candidate.

    - `constant`: C of the model $e(t) \\approx C (t - t_0) h^p$ (None: nothing resolved);
    - `observed_order`: $\\log_2(d_k / d_{k+1})$ of the pair that settled the regime (None: the
      finer pair at round-off, so that the coarser run's error was measured against a run exact
      to round-off, or, for the first pair, bounded by the floor);
    - `max_step`: the largest step of the asymptotic regime (the model is not used beyond it);
    - `steps`, `iterations`: each pilot run's step and its iterations per step (`stats.iterations`,
      mean over steps), largest step first;
    - `work`: the pilot's work on this candidate, in stage-sweeps; `reason`: why no constant."""

    constant: float | None
    observed_order: float | None
    max_step: float | None
    steps: tuple
    iterations: tuple
    work: float
    reason: str = ""

    def iterations_at(self, h: float) -> float:
        """Iterations per step at step h: interpolated in log h between the pilot's runs; the
        smallest step's count below them, the largest's above them (sweeps per step fall as
        the step shrinks, so smaller steps are charged no less than they need)."""
        hs, its = np.log(np.asarray(self.steps[::-1])), np.asarray(self.iterations[::-1])
        return float(np.interp(math.log(h), hs, its))


def contraction_step(measured: "Measured") -> float:
    r"""The step at which the stage sweeps' contraction factor ρ reaches `MAX_CONTRACTION`, read
    from the pilot's sweeps per step at its largest step h and at h/2 (∞ without such a pair, or
    where the counts do not fall). A fixed-point iteration contracting by ρ(h) = κh needs about
    N(h) = a / (−log ρ(h)) sweeps to reach a given tolerance, so N(h) / N(h/2) = R gives
    ρ(h) = 2^{−1/(R−1)}, and ρ reaches ρ_max at h ρ_max / ρ(h). The predictor's error also falls
    with the step, which makes R larger and the step returned smaller: on the safe side."""
    if len(measured.steps) < 2 or not measured.iterations[1] > 0:
        return math.inf
    ratio = measured.iterations[0] / measured.iterations[1]
    if not ratio > 1.0:
        return math.inf
    rho = 2.0 ** (-1.0 / (ratio - 1.0))
    return measured.steps[0] * MAX_CONTRACTION / rho


def motion(system, Q0, xi0):
    r"""(‖L_{ξ⁰}Q⁰‖∞, ‖Q⁰‖∞ or 1 where it is 0): the speed and the size `time_scale` compares,
    as JAX scalars (so that `jax.vmap` gives them for many members at once)."""
    size = jnp.max(jnp.abs(jnp.asarray(Q0)))
    return jnp.max(jnp.abs(system.velocity_map(xi0, Q0))), jnp.where(size > 0, size, 1.0)


def time_scale(system, Q0, xi0) -> float:
    r"""τ = ‖Q⁰‖∞ / ‖L_{ξ⁰}Q⁰‖∞ (`motion`): the time in which the configuration moves by its own
    size at the initial velocity (∞ at rest, 1 for a configuration at the origin)."""
    speed, size = (float(x) for x in motion(system, Q0, xi0))
    return size / speed if speed > 0 else math.inf


def _scale(x) -> float:
    return float(np.max(np.abs(x))) or 1.0


def nodes(sol) -> tuple:
    """(Q or None, momentum) of a `Solution`'s nodes, as arrays: what `state_error` compares."""
    return None if sol.Q is None else np.asarray(sol.Q), np.asarray(sol.momentum)


def sizes(node) -> tuple:
    """(size of Q⁰, size of μ⁰) of a `nodes` pair: the scales of `state_error` (1 for Q without Q
    or for a size of 0)."""
    Q, m = node
    return 1.0 if Q is None else _scale(Q[0]), _scale(m[0])


def run_record(stepper, system, sols, n_steps: int) -> tuple:
    """(each member's mean iterations per step, the work of the run, whether a member failed) of
    one pilot run of `n_steps` steps, `sols` its members' `Solution`s."""
    its = [float(np.mean(np.asarray(sol.stats.iterations))) for sol in sols]
    work = sum(n_steps * work_per_step(stepper, system, i) for i in its)
    return its, work, any(int(np.asarray(sol.result)) != Status.SUCCESS for sol in sols)


def state_error(a, b, scales) -> np.ndarray:
    """The error measure at each node (module docstring) between the nodes `a` and `b`, pairs
    (Q or None, momentum) of arrays with a leading node axis, `scales` = (size of Q⁰, of μ⁰)."""
    (Qa, ma), (Qb, mb) = a, b
    axes = tuple(range(1, ma.ndim))
    err = np.max(np.abs(ma - mb), axis=axes) / scales[1]
    if Qa is not None and Qb is not None:
        err = np.maximum(err, np.max(np.abs(Qa - Qb), axis=tuple(range(1, Qa.ndim))) / scales[0])
    return err


def work_per_step(stepper, system, iterations: float) -> float:
    """Predicted work of one step, in Gauss stage-sweeps: `STEP_COST`, and `iterations` sweeps
    of its stages for Gauss–Legendre; for a Newton-solved step, `NEWTON_SOLVE_COST` per solve
    (its sub-steps) and `NEWTON_UPDATE_COST` per update (`iterations` counts those of all its
    solves)."""
    if isinstance(stepper, GaussLegendre):
        return STEP_COST + iterations * stepper.stages * GAUSS_STAGE_SWEEP_COST
    solves = stepper.facts(system).solves_per_step
    return STEP_COST + solves * NEWTON_SOLVE_COST + iterations * NEWTON_UPDATE_COST


def _envelope(d, ts, t0) -> float:
    """max over the second half of the pilot (the nodes t with t − t0 ≥ half its horizon) of d(t)/(t − t0)."""
    span = ts - t0
    late = span >= 0.5 * span[-1]
    return float(np.max(d[late] / span[late]))


def run_pilot(march, stepper, system, order: int, t0: float, horizon: float, h0: float) -> Measured:
    """March `stepper` over `horizon` at h0, h0/2, h0/4, … (`march(stepper, dt, n_steps)` → one
    `Solution` per member piloted, not raising) until a pair of differences shows the asymptotic
    regime (observed order ≥ `order` − `ORDER_SLACK`) or reaches round-off; a run in which a
    member failed at the largest step is dropped and the next halving taken. With several
    members the worst one decides at every node and step: the differences are the largest of
    the members' (each relative to its own sizes), the iterations per step the largest mean,
    and the work their sum. Returns what it measured (`Measured`)."""
    n0 = max(1, round(horizon / h0))
    runs, steps, iterations, work = [], [], [], 0.0
    envelopes, reason, scales = [], "", None
    for k in range(PILOT_HALVINGS + 3):
        n = n0 * 2**k
        h = horizon / n
        sols = march(stepper, h, n)
        its, cost, failed = run_record(stepper, system, sols, n)
        work += cost
        if failed:
            if runs:  # a failure at a smaller step than one that succeeded: the method breaks down here
                return Measured(None, None, None, tuple(steps), tuple(iterations), work, f"failed at step {h:.3g}")
            continue  # too large a step: halve it
        run = [nodes(sol) for sol in sols]
        stride = n // n0
        if scales is None:  # the sizes of each member's Q⁰ and μ⁰
            scales = [sizes(member) for member in run]
        runs.append([tuple(None if x is None else x[::stride] for x in member) for member in run])
        steps.append(h)
        iterations.append(max(its))
        if len(runs) < 2:
            continue
        ts = t0 + np.arange(n0 + 1) * (horizon / n0)
        d = np.max([state_error(a, b, s) for a, b, s in zip(runs[-2], runs[-1], scales)], axis=0)
        envelopes.append(_envelope(d, ts, t0))
        floor = ROUNDOFF_FLOOR * np.finfo(float).eps * math.sqrt(n) / horizon
        h_coarse = steps[-2]
        if envelopes[-1] <= floor:  # at round-off
            if len(envelopes) >= 2:
                # the pair before was resolved: its coarse run measured against one exact to round-off
                return Measured(
                    envelopes[-2] / steps[-3] ** order, None, steps[-3], tuple(steps), tuple(iterations), work
                )
            # the first pair: the coarse run's error is bounded by the floor
            constant = floor / (h_coarse**order * (1 - 2.0**-order))
            return Measured(constant, None, h_coarse, tuple(steps), tuple(iterations), work)
        if len(envelopes) >= 2:
            observed = math.log2(envelopes[-2] / envelopes[-1])
            if observed >= order - ORDER_SLACK:
                # both pairs in the regime: the larger of their constants (the conservative one)
                c = [e / (s**order * (1 - 2.0**-order)) for e, s in zip(envelopes[-2:], steps[-3:-1])]
                return Measured(max(c), observed, steps[-3], tuple(steps), tuple(iterations), work)
        reason = "no asymptotic regime reached"
    return Measured(None, None, None, tuple(steps), tuple(iterations), work, reason or "every pilot run failed")
