r"""Accuracy-driven choice of method and step: `choose_step`, and the `AccuracyPlan` it returns,
which `integrate(..., t_final=T, accuracy=tol)` runs; `plan_members`, the same plan made on
several trajectories at once, which `sweep(..., t_final=T, accuracy=tol)` runs on a sample of its
members (`clebsch_jax.choose_sweep_step`, `clebsch_jax.batching.ensemble_plan`).

**What `accuracy` means.** The relative max-norm error of the state at `t_final`,
$$\max\Big(\frac{\|Q_h(T) - Q(T)\|_\infty}{\|Q^0\|_\infty},
\frac{\|\mu_h(T) - \mu(T)\|_\infty}{\|\mu^0\|_\infty}\Big) \le \texttt{accuracy},$$
of the configuration Q and the momentum map μ (`Solution.momentum`; $\mu = \delta l/\delta\xi$),
each relative to its size at the start (absolute where that is 0; μ alone without Q). The model
predicts an envelope growing at least linearly, so the bound holds before `t_final` too. The
energy is no separate target: the candidates are symplectic and symmetric, their energy error
bounded at $O(h^p)$, far below the global error of long runs (benchmarks/README.md).

**How the plan is made** (`clebsch_jax.march.pilot` has the model and the measurement):

1. A pilot horizon $T_p = \min(T - t_0, \texttt{PILOT\_TIME\_SCALES}\,\tau)$, with τ the time in
   which the configuration moves by its own size at the initial velocity (`time_scale`; or
   `time_scale=`).
2. Each candidate is marched over $T_p$ at the steps $h_0 = \texttt{PILOT\_FIRST\_STEP}\,\tau$,
   $h_0/2$, $h_0/4$, … until two successive differences of its runs show its order (the
   asymptotic regime) or reach round-off; its error constant C of the model
   $e(t) \approx C (t - t_0) h^p$ (global error growing linearly in time: symmetric or
   symplectic methods on integrable motion) is measured there, with its iterations per step.
3. Each candidate's step is the largest that predicts `accuracy` at T, $h = (\texttt{accuracy}
   / (C (T - t_0)))^{1/p}$, never larger than the largest step of its asymptotic regime, rounded
   down so that a whole number of steps ends at `t_final`. When that cap binds at the pilot's
   first step, the pilot is run again from twice that step (at most `PILOT_DOUBLINGS` times,
   while at least `PILOT_MIN_STEPS` steps cover $T_p$).
4. The plan is the candidate of least **predicted work**: steps × its measured iterations per
   step × their cost (`work_per_step`), in sweeps of one Gauss–Legendre stage — a count, not a
   time: two calls give the same plan, whatever the machine's load.
5. Its step is **checked** (`clebsch_jax.march.check`: at h and h/2 over $T_p$, the growth
   $e \propto (t - t_0)^q$ measured and extrapolated to T) and reduced while it misses `accuracy`
   (near a step-size resonance); `AccuracyPlan.check` and `growth` record what was found.

**Candidates** (`DEFAULT_CANDIDATES`): the system's second-order default (loose accuracies, short
runs) and Gauss–Legendre of orders 4, 6, 8, 12 and 16 (12 and 16 the fastest of ours at the
tightest errors of both ensembles of `benchmarks/results/work_precision_ensembles.json`;
compositions of orders 4–8 never were). A Gauss–Legendre plan keeps its stage sweeps'
contraction factor, estimated from the pilot's sweep counts (the worst piloted member's), at most
`clebsch_jax.march.pilot.MAX_CONTRACTION` (`contraction_step`), so that faster members and later
parts of the run still converge. The relative costs of a stage-sweep, a Newton solve, a Newton
update and a step's other work are a fit to that file's native rigid-body points
(`clebsch_jax.march.pilot`: `STEP_COST`, …): on other systems they are a guide.

**Cost of the pilot.** Each candidate compiles one program (every step size reuses it) and
marches $T_p$ at least three times (7 $T_p / h_0$ = 7 × 64 steps with the defaults; each further
halving doubles the last); the check adds $3 T_p / h$ steps per step checked. The plan records
this work (`pilot_work`) beside the run's: for runs much longer than $T_p$ a small fraction of
it; for a run as short as $T_p$ more than the run: make the plan once and reuse it.

**Several members** (`plan_members`): τ is the smallest of theirs; at each step of the pilot
and the check the worst member decides (`clebsch_jax.march.pilot.run_pilot`). They are marched
together (`clebsch_jax.march.members.MemberMarch`: each member's run the one `integrate` makes,
to the bit; one call of a native kernel with the members in its lanes where they share it).

**Limits.** The linear growth holds for integrable and near-integrable motion (rigid bodies,
Kepler, regular vortex motion) up to $t \sim h^{-p}$; the check measures growth up to quadratic,
on $T_p$ only. In chaotic motion errors grow exponentially: the plan is then too optimistic
beyond the Lyapunov time (no method reaches a fixed accuracy there for long). Close encounters
and events after $T_p$ (a vortex pair meeting late, a body passing near a separatrix) are not
seen. τ is a guess from the initial state; a configuration far from the origin of a vector space
makes it too large (give `time_scale=`). `accuracy` below `MIN_ACCURACY` is refused (round-off).
"""

from __future__ import annotations

import dataclasses
import math
import numbers

import numpy as np

from ..core.system import ClebschSystem
from ..core.validation import any_traced, float_array
from ..steppers.base import AbstractStepper
from ..steppers.choose import choose_method
from .check import check_plan
from .members import MemberMarch
from .pilot import (
    PILOT_DOUBLINGS,
    PILOT_FIRST_STEP,
    PILOT_MIN_STEPS,
    PILOT_TIME_SCALES,
    contraction_step,
    run_pilot,
    time_scale,
    work_per_step,
)

__all__ = [
    "AccuracyPlan",
    "Candidate",
    "choose_step",
    "plan_for_call",
    "plan_members",
    "require_step",
    "DEFAULT_CANDIDATES",
    "MIN_ACCURACY",
]

DEFAULT_CANDIDATES = (
    {},
    {"scheme": "gauss", "order": 4},
    {"scheme": "gauss", "order": 6},
    {"scheme": "gauss", "order": 8},
    {"scheme": "gauss", "order": 12},
    {"scheme": "gauss", "order": 16},
)
"""The methods `choose_step` compares by default, as `integrate`'s options (module docstring)."""

MIN_ACCURACY = 1e-13
"""The smallest `accuracy` accepted: a few hundred ulps, what round-off leaves of a short run."""

MAX_STEPS = 10**9
"""A candidate that needs more steps than this is not considered."""

METHOD_OPTIONS = dict(
    reduce="auto", need_P=False, reconstruct=True, rtol=0.0, atol=0.0, max_newton_iterations=20, jacobian="dense"
)
"""`integrate`'s options that shape every candidate's stepper, with their defaults (the others,
`method`, `scheme`, `order`, `composition`, name the method)."""

_NAMING = ("method", "scheme", "order", "composition")


@dataclasses.dataclass(frozen=True)
class Candidate:
    """One candidate as the pilot measured it and the plan would run it: `name`, `order`,
    `options` (as `integrate`'s, sorted pairs), `constant` (C of $e \\approx C(t-t_0)h^p$, None
    when the pilot resolved none: `reason` says why), `observed_order`, `max_step`; for the run
    `dt`, `n_steps`, `predicted_error`, `iterations_per_step`, `predicted_work` (None when not
    planned); `pilot_work` (the pilot's, and the check's for the one chosen)."""

    name: str
    order: int
    options: tuple
    constant: float | None
    observed_order: float | None
    max_step: float | None
    dt: float | None
    n_steps: int | None
    predicted_error: float | None
    iterations_per_step: float | None
    predicted_work: float | None
    pilot_work: float
    reason: str = ""


@dataclasses.dataclass(frozen=True)
class AccuracyPlan:
    """The method and step `choose_step` chose, and why.

    - `method`: the stepper to run (`integrate(..., method=plan.method)`), `name`, `order`;
    - `dt`, `n_steps`: the step and how many end at `t_final` (`t0 + n_steps · dt`);
    - `t0`, `t_final`, `accuracy`: what was asked;
    - `predicted_error`: the error at `t_final` the check predicts (≤ `accuracy` unless `check`
      says "not met"; the pilot's model's where the check resolved nothing);
    - `predicted_work`: the run's work in Gauss stage-sweeps (`clebsch_jax.march.pilot`);
      `pilot_work`: the pilot's and the check's, in the same unit;
    - `time_scale`, `pilot_horizon`: τ and the pilot's horizon;
    - `candidates`: every `Candidate`, in the order compared;
    - `piloted`: the members of an ensemble the pilot marched (`clebsch_jax.choose_sweep_step`:
      their indices in the sweep, the first member first), None for one trajectory;
    - `growth`, `check`: the error's growth exponent q measured at the planned step and what the
      check there found (`clebsch_jax.march.check`: "met", "at round-off", "not met", "not run: …").

    `plan.integrate_options()` gives `method`, `dt` and `n_steps` for `integrate` or `sweep`."""

    method: AbstractStepper
    name: str
    order: int
    dt: float
    n_steps: int
    t0: float
    t_final: float
    accuracy: float
    predicted_error: float
    predicted_work: float
    pilot_work: float
    time_scale: float
    pilot_horizon: float
    candidates: tuple
    piloted: tuple | None = None
    growth: float | None = None
    check: str = ""

    def integrate_options(self) -> dict:
        """`method`, `dt` and `n_steps`, to pass to `integrate` or `sweep`."""
        return {"method": self.method, "dt": self.dt, "n_steps": self.n_steps}

    def summary(self) -> str:
        """A table of the candidates: order, constant, step, steps, predicted error and work (and
        the members piloted, for an ensemble's plan)."""
        rows = [f"{'candidate':<34} {'p':>2} {'C':>9} {'dt':>9} {'steps':>9} {'error':>9} {'work':>10}"]
        for c in self.candidates:
            if c.predicted_work is None:
                rows.append(f"{c.name:<34} {c.order:>2} ({c.reason})")
                continue
            mark = " *" if c.name == self.name else ""
            rows.append(
                f"{c.name:<34} {c.order:>2} {c.constant:9.2e} {c.dt:9.3g} {c.n_steps:9d} "
                f"{c.predicted_error:9.2e} {c.predicted_work:10.4g}{mark}"
            )
        if self.piloted is not None:
            rows.append(f"piloted members: {', '.join(map(str, self.piloted))}")
        growth = f", growth t^{self.growth:.2f}" if self.growth else ""
        return "\n".join([*rows, f"checked at dt {self.dt:.4g}: {self.check}{growth}"])


def check_accuracy(accuracy, t_final, t0=0.0) -> tuple[float, float]:
    """(accuracy, horizon t_final − t0) as floats, or a `ValueError`/`TypeError` naming the
    argument: `accuracy` a real number in [`MIN_ACCURACY`, 1), `t_final` a real number > t0."""
    if accuracy is None:
        raise ValueError("accuracy: required with t_final= (a relative error at t_final, e.g. 1e-8).")
    if isinstance(accuracy, (bool, str)) or not isinstance(accuracy, numbers.Real):
        raise TypeError(f"accuracy: expected a real number in [{MIN_ACCURACY:g}, 1), got {accuracy!r}.")
    accuracy = float(accuracy)
    if not (MIN_ACCURACY <= accuracy < 1):
        hint = " (below it round-off decides, not the method and step)" if 0 < accuracy < MIN_ACCURACY else ""
        raise ValueError(f"accuracy: expected a relative error in [{MIN_ACCURACY:g}, 1), got {accuracy!r}{hint}.")
    if t_final is None:
        raise ValueError("t_final: required with accuracy= (the time the run ends at, where the error is measured).")
    if isinstance(t_final, (bool, str)) or not isinstance(t_final, numbers.Real) or not math.isfinite(t_final):
        raise TypeError(f"t_final: expected a finite real number, got {t_final!r}.")
    try:
        t0 = float(np.asarray(t0, dtype=float))
    except (TypeError, ValueError):
        raise ValueError(f"t0: expected a real scalar, got {t0!r}.") from None
    if not float(t_final) > t0:
        raise ValueError(f"t_final: must be after t0 = {t0:g}, got {t_final!r}.")
    return accuracy, float(t_final) - t0


def require_step(dt, n_steps) -> None:
    """`integrate`'s and `sweep`'s refusal of a call with neither a step (`dt` and `n_steps`)
    nor a plan (`accuracy=` and `t_final=`), naming what is missing."""
    if dt is None or n_steps is None:
        missing = " and ".join(name for name, v in (("dt", dt), ("n_steps", n_steps)) if v is None)
        raise ValueError(f"{missing}: required, unless accuracy= and t_final= choose the step.")


def plan_for_call(system, Q0, xi0, given: dict, **arguments) -> AccuracyPlan:
    """`integrate`'s or `sweep`'s plan: `given` (their options) checked against `accuracy=`
    (`check_replaced`), those of `METHOD_OPTIONS` not at their defaults passed on to
    `choose_step` with `arguments`."""
    return choose_step(system, Q0, xi0, **arguments, **method_options(given, arguments))


def method_options(given: dict, arguments: dict) -> dict:
    """The accuracy arguments checked, `given` (`integrate`'s or `sweep`'s options) checked
    against `accuracy=` (`check_replaced`), and those of `METHOD_OPTIONS` not at their defaults:
    what the plan passes on to the candidates."""
    check_accuracy(arguments.get("accuracy"), arguments.get("t_final"), arguments.get("t0", 0.0))
    check_replaced(given)
    return {k: v for k, v in given.items() if k in METHOD_OPTIONS and not _is_default(v, METHOD_OPTIONS[k])}


def _is_default(value, default) -> bool:
    return value is default or (type(value) is type(default) and value == default)


def check_replaced(given: dict) -> None:
    """Refuse, naming it, an option that `accuracy=` replaces: `dt`, `n_steps`, and the method
    (`method`, `scheme`, `order`, `composition`: choose among them with `candidates=`)."""
    for name in ("dt", "n_steps"):
        if given.get(name) is not None:
            raise ValueError(
                f"{name}: accuracy= chooses the step and the number of steps; pass either accuracy= "
                "and t_final=, or dt= and n_steps=."
            )
    for name in _NAMING:
        if given.get(name) is not None:
            raise ValueError(
                f"{name}: accuracy= chooses the method; leave {name} unset (clebsch_jax.choose_step(..., "
                "candidates=...) sets the methods compared), or pass method=, dt= and n_steps=."
            )
    if given.get("march_state") is not None:
        raise ValueError(
            "march_state: a continued run keeps its method and step; continue with "
            "method=sol.accuracy_plan.method, dt=sol.accuracy_plan.dt and n_steps=, not accuracy=."
        )


def _candidates(candidates) -> tuple:
    if candidates is None:
        return DEFAULT_CANDIDATES
    if isinstance(candidates, (dict, AbstractStepper, str)) or not hasattr(candidates, "__iter__"):
        raise TypeError(
            "candidates: expected a sequence of methods, each a stepper or a dict of integrate's "
            f"method options (scheme, order, composition), got {candidates!r}."
        )
    candidates = tuple(candidates)
    if not candidates:
        raise ValueError("candidates: expected at least one method, got none.")
    for c in candidates:
        if isinstance(c, dict):
            extra = sorted(set(c) - {"scheme", "order", "composition"})
            if extra:
                raise ValueError(f"candidates: {extra[0]!r} is not a method option (scheme, order, composition).")
        elif not isinstance(c, AbstractStepper):
            raise TypeError(f"candidates: expected a stepper or a dict of method options, got {c!r}.")
    return candidates


def choose_step(
    system: ClebschSystem,
    Q0,
    xi0,
    *,
    t_final,
    accuracy,
    t0=0.0,
    P0=None,
    candidates=None,
    time_scale: float | None = None,
    check_energy=True,
    backend: str = "auto",
    **options,
) -> AccuracyPlan:
    r"""The method and step that reach `accuracy` at `t_final` with the least predicted work,
    chosen by a pilot on this system and initial state (the module docstring of
    `clebsch_jax.march.accuracy` states the error measure, the model and its limits).

    **Arguments:**

    - `system`, `Q0`, `xi0`, `P0`, `t0`: as for `integrate` (concrete arrays: the pilot runs).
    - `t_final`: the time the run ends at (> t0). `accuracy`: the relative error allowed there,
      in [`MIN_ACCURACY`, 1).
    - `candidates`: the methods compared (default `DEFAULT_CANDIDATES`): steppers, or dicts of
      `integrate`'s `scheme`, `order`, `composition` (`{}`: the system's default).
    - `time_scale`: τ, the pilot's unit of time (default: `‖Q⁰‖∞ / ‖L_{ξ⁰}Q⁰‖∞`).
    - `check_energy`, `backend`: as for `integrate`, for the pilot's runs.
    - `**options`: `integrate`'s options that shape every candidate's stepper (`reduce`,
      `need_P`, `reconstruct`, `rtol`, `atol`, `max_newton_iterations`, `jacobian`).

    **Returns:** an `AccuracyPlan`. Raises a `ValueError` when no candidate's pilot resolved an
    error constant (each one's reason is in the message). For an ensemble, plan on a sample of
    its members with `clebsch_jax.choose_sweep_step`."""
    return plan_members(
        [(system, Q0, xi0, P0)], t_final=t_final, accuracy=accuracy, t0=t0, candidates=candidates,
        time_scale=time_scale, check_energy=check_energy, backend=backend, **options,
    )  # fmt: skip


def plan_members(
    members,
    *,
    t_final,
    accuracy,
    t0=0.0,
    candidates=None,
    time_scale: float | None = None,
    check_energy=True,
    backend: str = "auto",
    piloted: tuple | None = None,
    **options,
) -> AccuracyPlan:
    """`choose_step`'s plan made on several trajectories at once (`members`, a sequence of
    (system, Q0, xi0, P0)), its step to hold for each (module docstring); the candidates resolved
    on the first; `piloted` recorded on the plan."""
    accuracy, horizon = check_accuracy(accuracy, t_final, t0)
    candidates = _candidates(candidates)
    for name in options:
        if name in _NAMING or name in ("dt", "n_steps", "march_state"):
            check_replaced({name: options[name]})
        if name not in METHOD_OPTIONS:
            raise TypeError(f"{name}: not an option of choose_step (method options: {', '.join(METHOD_OPTIONS)}).")
        if options[name] is None:
            raise ValueError(f"{name}: expected a value (default {METHOD_OPTIONS[name]!r}), got None.")
    if time_scale is not None and (
        isinstance(time_scale, bool) or not isinstance(time_scale, numbers.Real) or not time_scale > 0
    ):
        raise ValueError(f"time_scale: expected a positive number, got {time_scale!r}.")
    checked = []
    for system, Q0, xi0, P0 in members:
        if not isinstance(system, ClebschSystem):
            raise TypeError(f"system: expected a clebsch_jax.ClebschSystem, got {type(system).__name__}.")
        if any_traced(system, Q0, xi0, P0):
            raise ValueError(
                "accuracy: the plan runs a pilot and needs concrete Q0, xi0 and system (not inside jit, vmap "
                "or grad); call clebsch_jax.choose_step outside and pass method=, dt= and n_steps= inside."
            )
        checked.append((system, float_array(Q0, "Q0"), float_array(xi0, "xi0"), P0))
    system, Q0, xi0, _ = checked[0]
    resolved = [_resolve(system, Q0, xi0, spec, options) for spec in candidates]
    if all(stepper is None for stepper, _ in resolved):  # refused before anything is evaluated
        why = "; ".join(f"{r.name}: {r.reason}" for _, r in resolved)
        raise ValueError(f"accuracy: no candidate method's pilot resolved its error ({why}).")
    tau = float(time_scale) if time_scale is not None else _time_scale(checked)
    pilot_horizon = min(horizon, PILOT_TIME_SCALES * tau)
    h0 = pilot_horizon / max(PILOT_MIN_STEPS, math.ceil(pilot_horizon / (PILOT_FIRST_STEP * tau)))
    t0 = float(np.asarray(t0))

    march = MemberMarch(checked, t0, check_energy, backend)  # every member's pilot run, together

    rows, best = [], None
    for spec, (stepper, refused) in zip(candidates, resolved):
        if stepper is None:
            rows.append(refused)
            continue
        row, stepper = _plan_candidate(march, system, spec, stepper, t0, horizon, pilot_horizon, h0, accuracy)
        rows.append(row)
        if row.predicted_work is not None and (best is None or row.predicted_work < best[0].predicted_work):
            best = (row, stepper)
    if best is None:
        why = "; ".join(f"{r.name}: {r.reason}" for r in rows)
        raise ValueError(f"accuracy: no candidate method's pilot resolved its error ({why}).")
    row, stepper = best
    checked, growth, check = check_plan(march, stepper, system, row, t0, horizon, pilot_horizon, accuracy)
    rows = [checked if r is row else r for r in rows]
    return AccuracyPlan(
        stepper, checked.name, checked.order, checked.dt, checked.n_steps, t0, t0 + horizon, accuracy,
        checked.predicted_error, checked.predicted_work, sum(r.pilot_work for r in rows), tau, pilot_horizon,
        tuple(rows), piloted, growth, check,
    )  # fmt: skip


def _time_scale(members) -> float:
    tau = min(time_scale(system, Q0, xi0) for system, Q0, xi0, _ in members)  # members at rest: ∞
    if not math.isfinite(tau):
        raise ValueError(
            "time_scale: the initial velocity does not move the configuration (L_xi0 Q0 = 0), so the "
            "pilot has no time scale; pass time_scale= (a time over which the motion changes)."
        )
    return tau


def _step(measured, order, accuracy, horizon) -> float:
    """The step at which the model predicts `accuracy` at the end of `horizon` (∞ for C = 0)."""
    C = measured.constant
    return math.inf if C == 0 else (accuracy / (C * horizon)) ** (1.0 / order)


_NO_FIT = dict(constant=None, observed_order=None, max_step=None)
_NO_RUN = dict(dt=None, n_steps=None, predicted_error=None, iterations_per_step=None, predicted_work=None)


def _key(spec) -> tuple:
    return () if isinstance(spec, AbstractStepper) else tuple(sorted(spec.items()))


def _resolve(system, Q0, xi0, spec, options):
    """(stepper, None) of one candidate, by `choose_method` (the one place options become a
    stepper), or (None, its `Candidate` row saying why it does not apply)."""
    if isinstance(spec, AbstractStepper):
        return spec, None
    try:
        return choose_method(system, Q0, xi0, **options, **spec), None
    except ValueError as err:  # not a method of this system (e.g. Gauss with jacobian="blocks")
        base = dict(name=str(spec), order=int(spec.get("order") or 2), options=_key(spec), pilot_work=0.0)
        return None, Candidate(**base, **_NO_FIT, **_NO_RUN, reason=f"not applicable: {err}")


def _plan_candidate(march, system, spec, stepper, t0, horizon, pilot_horizon, h0, accuracy):
    """(`Candidate`, stepper) of one applicable candidate: its pilot, and its step for `accuracy`."""
    key = _key(spec)
    facts = stepper.facts(system)
    p = facts.order
    try:
        measured = run_pilot(march, stepper, system, p, t0, pilot_horizon, h0)
    except ValueError as err:  # refused by integrate's checks (e.g. a stepper that does not apply)
        base = dict(name=facts.name, order=p, options=key, pilot_work=0.0)
        return Candidate(**base, **_NO_FIT, **_NO_RUN, reason=f"not applicable: {err}"), None
    work = measured.work
    for _ in range(PILOT_DOUBLINGS):  # the step wanted is above the regime's largest, which was the first tried
        if measured.constant is None or measured.max_step < measured.steps[0]:
            break
        if _step(measured, p, accuracy, horizon) <= measured.max_step:
            break
        if 2 * measured.steps[0] > pilot_horizon / PILOT_MIN_STEPS:
            break
        larger = run_pilot(march, stepper, system, p, t0, pilot_horizon, 2 * measured.steps[0])
        work += larger.work
        if larger.constant is None or not larger.max_step > measured.max_step:
            break
        measured = larger
    base = dict(name=facts.name, order=p, options=key, pilot_work=work)
    if measured.constant is None:
        return Candidate(**base, **_NO_FIT, **_NO_RUN, reason=measured.reason), None
    C = measured.constant
    h = min(measured.max_step, _step(measured, p, accuracy, horizon))
    if facts.scheme == "gauss":  # stage sweeps: a margin from where they stop contracting
        h = min(h, contraction_step(measured))
    n_steps = max(1, math.ceil(horizon / h * (1 - 1e-12)))
    fit = dict(constant=C, observed_order=measured.observed_order, max_step=measured.max_step)
    if n_steps > MAX_STEPS:
        return Candidate(**base, **fit, **_NO_RUN, reason=f"needs {n_steps:.3g} steps"), None
    dt = horizon / n_steps
    its = measured.iterations_at(dt)
    work = n_steps * work_per_step(stepper, system, its)
    planned = dict(dt=dt, n_steps=n_steps, predicted_error=C * horizon * dt**p, iterations_per_step=its)
    return Candidate(**base, **fit, **planned, predicted_work=work), stepper
