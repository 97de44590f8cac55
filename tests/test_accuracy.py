"""The accuracy-driven choice of method and step (`clebsch_jax.choose_step`, `integrate(...,
accuracy=)`): the error reached at t_final against independent references (SciPy's DOP853 on
Euler's equations for the rigid body, Kepler's exact solution), the plan's response to the
accuracy asked, its determinism, refusals before compiling, and the cost model against the
committed measurements."""

from __future__ import annotations

import dataclasses
import json
import math
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import clebsch_jax as cj
from clebsch_jax.march import accuracy as accuracy_module
from clebsch_jax.march.pilot import GAUSS_STAGE_SWEEP_COST, NEWTON_SOLVE_COST, NEWTON_UPDATE_COST, STEP_COST

from .helpers import compiles_recorded, rigid_body_reference
from .systems import kepler, translation

INERTIA = np.array([2.0, 1.0, 2.0 / 3.0])
RIGID = cj.models.rigid_body(jnp.asarray(INERTIA))
Q0_BODY = np.eye(3)
OMEGA0 = np.array([np.cos(1.1), 0.0, np.sin(1.1)]) / INERTIA
KEPLER = cj.ClebschSystem(lagrangian=kepler, velocity_map=translation, derivative_map=cj.forward_difference)
Q0_KEPLER, V0_KEPLER = np.array([1.0, 0.0]), np.array([0.0, 1.1])  # eccentricity 0.21

ABOVE = 2.0
"""Allowed factor above the accuracy: the error constant is a Richardson estimate on the pilot's
horizon and the linear growth an envelope of it, so the error at t_final can exceed the
prediction by what the pilot did not see."""

BELOW = 1e-3
"""Not wastefully accurate: at least accuracy × BELOW. The model is an envelope (the error at
t_final may sit in a trough of its oscillation), and a step is never taken beyond the pilot's
largest step of the asymptotic regime, which can leave a loose accuracy far undercut."""


def _rigid_error(sol, T, omega0=OMEGA0):
    """The plan's error measure at t_final against DOP853 (rtol 1e-13) of Euler's equations."""
    Q_ref, omega_ref = rigid_body_reference(INERTIA, Q0_BODY, omega0, np.array([0.0, T]))
    mu, mu_ref = np.asarray(sol.momentum[-1]), INERTIA * omega_ref[-1]
    q_err = np.max(np.abs(np.asarray(sol.Q[-1]) - Q_ref[-1])) / np.max(np.abs(Q0_BODY))
    return max(q_err, np.max(np.abs(mu - mu_ref)) / np.max(np.abs(INERTIA * omega0)))


def _kepler_exact(q0, v0, t):
    """Kepler's problem (GM = 1) in the plane, exactly: Kepler's equation by Newton's method and
    Lagrange's f and g coefficients in the eccentric anomaly."""
    r0 = np.linalg.norm(q0)
    a = 1.0 / (2.0 / r0 - v0 @ v0)
    n = a**-1.5
    e_cos, e_sin = 1.0 - r0 / a, (q0 @ v0) / np.sqrt(a)
    e, E0 = np.hypot(e_cos, e_sin), np.arctan2(e_sin, e_cos)
    M = E0 - e_sin + n * t
    E = M
    for _ in range(60):
        E = E - (E - e * np.sin(E) - M) / (1.0 - e * np.cos(E))
    dE = E - E0
    r = a * (1.0 - e * np.cos(E))
    f, g = 1.0 - a / r0 * (1.0 - np.cos(dE)), t - (dE - np.sin(dE)) / n
    fd, gd = -np.sqrt(a) * np.sin(dE) / (r * r0), 1.0 - a / r * (1.0 - np.cos(dE))
    return f * q0 + g * v0, fd * q0 + gd * v0


def _kepler_error(sol, T):
    """The plan's error measure at t_final against the exact orbit (μ = δl/δξ = the velocity)."""
    q, v = _kepler_exact(Q0_KEPLER, V0_KEPLER, T)
    q_err = np.max(np.abs(np.asarray(sol.Q[-1]) - q)) / np.max(np.abs(Q0_KEPLER))
    return max(q_err, np.max(np.abs(np.asarray(sol.momentum[-1]) - v)) / np.max(np.abs(V0_KEPLER)))


SCENES = {
    "rigid body": (RIGID, Q0_BODY, OMEGA0, _rigid_error),
    "kepler": (KEPLER, Q0_KEPLER, V0_KEPLER, _kepler_error),
}


def _reached(scene, T, accuracy, candidates=None):
    system, Q0, xi0, error = SCENES[scene]
    plan = cj.choose_step(system, Q0, xi0, t_final=T, accuracy=accuracy, candidates=candidates, backend="xla")
    sol = cj.integrate(system, Q0, xi0, backend="xla", **plan.integrate_options())
    assert float(sol.ts[-1]) == pytest.approx(T, rel=1e-12)
    return plan, error(sol, T)


def test_the_step_follows_the_accuracy_asked_for():
    """One candidate (the rigid body's second-order default): the step the pilot chooses reaches
    each accuracy at t_final, within ABOVE and BELOW, and a tighter accuracy takes a smaller
    step, by the method's order. T = 100 is four pilot horizons: the error is extrapolated."""
    plans = []
    for accuracy in (1e-3, 1e-4):
        plan, err = _reached("rigid body", 100.0, accuracy, candidates=({},))
        assert plan.predicted_error <= accuracy * (1 + 1e-12)
        assert accuracy * BELOW <= err <= ABOVE * accuracy, (accuracy, err, plan.summary())
        plans.append(plan)
    assert plans[0].pilot_horizon < 100.0
    # h ∝ accuracy^(1/p): ten times tighter, √10 times smaller for order 2 (up to whole steps)
    assert plans[0].dt / plans[1].dt == pytest.approx(math.sqrt(10.0), rel=1e-3)


def test_the_plan_is_deterministic_and_recorded(monkeypatch):
    """integrate(accuracy=) runs choose_step's plan and records it; two calls give the same plan."""
    monkeypatch.setattr(accuracy_module, "DEFAULT_CANDIDATES", ({},))  # the program of the test above
    run = dict(t_final=100.0, accuracy=1e-3, backend="xla")
    first = cj.integrate(RIGID, Q0_BODY, OMEGA0, **run)
    second = cj.integrate(RIGID, Q0_BODY, OMEGA0, **run)
    assert first.accuracy_plan == second.accuracy_plan
    assert first.accuracy_plan == cj.choose_step(RIGID, Q0_BODY, OMEGA0, **run)
    plan = first.accuracy_plan
    assert first.method == plan.name and len(first.ts) == plan.n_steps + 1
    assert plan.t_final == 100.0 and plan.candidates[0].pilot_work == plan.pilot_work > 0
    assert "left principle" in plan.summary()
    # the planned step was checked (clebsch_jax.march.check) and its growth measured
    assert plan.check == "met" and 1.0 <= plan.growth <= 2.0 and "checked at dt" in plan.summary()


@pytest.mark.slow  # compiles the six default candidates per system, a minute or more under load;
# the default run covers the step's choice with one candidate (test_the_step_follows_the_accuracy_asked_for)
@pytest.mark.parametrize("scene", sorted(SCENES))
def test_the_default_candidates_reach_the_accuracy(scene):
    """The default candidates on two systems with independent references, T = 200 (six pilot
    horizons): each accuracy reached within ABOVE and BELOW; the tighter one runs a method of
    no lower order and a smaller step, or a higher order; the pilot costs less than the run."""
    plans = []
    for accuracy in (1e-6, 1e-9):
        plan, err = _reached(scene, 200.0, accuracy)
        assert accuracy * BELOW <= err <= ABOVE * accuracy, (accuracy, err, plan.summary())
        plans.append(plan)
    loose, tight = plans
    assert tight.order > loose.order or (tight.order == loose.order and tight.dt < loose.dt)
    # the least predicted work among those compared
    assert tight.predicted_work == min(c.predicted_work for c in tight.candidates if c.predicted_work)


@pytest.mark.slow  # compiles the sweep's program; the default run covers the plan through choose_sweep_step
def test_sweep_runs_the_plan_of_its_ensemble(monkeypatch):
    monkeypatch.setattr(accuracy_module, "DEFAULT_CANDIDATES", ({},))
    omegas = np.stack([OMEGA0, [0.3, 0.2, 1.0]])
    Q0s = np.broadcast_to(Q0_BODY, (2, 3, 3))
    res = cj.sweep(RIGID, None, Q0s, omegas, t_final=100.0, accuracy=1e-3)
    plan = res.accuracy_plan
    assert plan == cj.choose_sweep_step(RIGID, None, Q0s, omegas, t_final=100.0, accuracy=1e-3)
    assert plan.piloted == (0, 1)
    assert res.n_steps == plan.n_steps and np.all(res.succeeded)
    np.testing.assert_allclose(res.final_t, 100.0, rtol=1e-12)


def test_the_ensemble_plan_holds_for_a_faster_member():
    """Member 1 is member 0's motion three times faster (ω → 3ω: the same orbit in a third of the
    time, and a step h on it is the step 3h on member 0's), so a second-order method's error
    constant is 3³ times member 0's. The plan piloted on the first member alone misses
    `accuracy` on member 1 (against DOP853 at rtol 1e-13); the plan piloted on both meets it
    on both, and the first member alone makes the same plan as `choose_step` on it."""
    T, accuracy = 100.0, 1e-2
    omegas = np.stack([OMEGA0, 3.0 * OMEGA0])
    Q0s = np.broadcast_to(Q0_BODY, (2, 3, 3))
    run = dict(t_final=T, accuracy=accuracy, candidates=({},), backend="xla")
    first = cj.choose_sweep_step(RIGID, None, Q0s, omegas, members=[0], **run)
    assert first == dataclasses.replace(cj.choose_step(RIGID, Q0_BODY, OMEGA0, **run), piloted=(0,))
    ensemble = cj.choose_sweep_step(RIGID, None, Q0s, omegas, **run)
    assert ensemble.piloted == (0, 1) and ensemble.predicted_error <= accuracy * (1 + 1e-12)
    assert "piloted members: 0, 1" in ensemble.summary()

    def error(plan, omega):
        sol = cj.integrate(RIGID, Q0_BODY, omega, backend="xla", **plan.integrate_options())
        return _rigid_error(sol, T, omega)

    assert error(first, omegas[1]) > 5 * accuracy  # 3³ times the constant the plan was made for
    for omega in omegas:
        assert accuracy * BELOW <= error(ensemble, omega) <= accuracy, ensemble.summary()


def test_the_pilot_samples_the_first_member_and_the_fastest():
    """The rate of a body at Q = I is ‖L_ξ Q‖∞ / ‖Q‖∞ = max |ω_i| (L_ξ Q = Q ξ^), each member's
    with its own inertia; the sample is the first member and the fastest others, in order."""
    from clebsch_jax.batching.config import make_members
    from clebsch_jax.batching.ensemble_plan import member_rates, pilot_members

    omegas = np.array([[0.1, 0.2, 0.3], [1.0, 0.0, 0.0], [0.0, -2.0, 0.5], [0.0, 0.0, 0.2], [0.5, 0.5, 0.5]])
    inertias = np.stack([INERTIA * (1 + k) for k in range(5)])
    members = make_members(
        cj.models.rigid_body, inertias, np.broadcast_to(Q0_BODY, (5, 3, 3)), omegas, None, 1.0, False
    )
    rates = member_rates(cj.models.rigid_body, members)
    np.testing.assert_allclose(rates, np.max(np.abs(omegas), axis=1), rtol=1e-15)
    assert pilot_members(rates, 3) == (0, 2, 1)
    assert pilot_members(rates, 1) == (0,)
    assert pilot_members(rates) == (0, 2, 1, 4, 3)
    bad = make_members(
        cj.models.rigid_body, inertias[:2], members.Q0[:2], np.array([[0.1, 0, 0], [np.nan, 1, 0]]), None, 1.0, False
    )
    assert np.isnan(member_rates(cj.models.rigid_body, bad)[1])
    assert pilot_members(np.array([1.0, np.nan, 3.0, 0.0])) == (0, 2, 3)  # non-finite data: not piloted
    with compiles_recorded() as compiled, pytest.raises(ValueError, match="members: expected indices"):
        cj.choose_sweep_step(
            cj.models.rigid_body, inertias, members.Q0, omegas, t_final=10.0, accuracy=1e-6, members=[0, 5]
        )
    assert compiled == []


_BAD = {
    "accuracy zero": (dict(accuracy=0.0, t_final=10.0), ValueError, "accuracy"),
    "accuracy negative": (dict(accuracy=-1e-6, t_final=10.0), ValueError, "accuracy"),
    "accuracy NaN": (dict(accuracy=float("nan"), t_final=10.0), ValueError, "accuracy"),
    "accuracy one": (dict(accuracy=1.0, t_final=10.0), ValueError, "accuracy"),
    "accuracy below round-off": (dict(accuracy=1e-16, t_final=10.0), ValueError, "round-off"),
    "accuracy a string": (dict(accuracy="1e-6", t_final=10.0), TypeError, "accuracy"),
    "accuracy a bool": (dict(accuracy=True, t_final=10.0), TypeError, "accuracy"),
    "accuracy with dt": (dict(accuracy=1e-6, t_final=10.0, dt=0.1), ValueError, "dt: accuracy="),
    "accuracy with n_steps": (dict(accuracy=1e-6, t_final=10.0, n_steps=10), ValueError, "n_steps: accuracy="),
    "accuracy with scheme": (dict(accuracy=1e-6, t_final=10.0, scheme="gauss"), ValueError, "scheme: accuracy="),
    "accuracy with order": (dict(accuracy=1e-6, t_final=10.0, order=4), ValueError, "order: accuracy="),
    "accuracy with method": (dict(accuracy=1e-6, t_final=10.0, method=cj.FullStep()), ValueError, "method:"),
    "accuracy without t_final": (dict(accuracy=1e-6), ValueError, "t_final: required"),
    "t_final without accuracy": (dict(t_final=10.0), ValueError, "accuracy: required"),
    "t_final before t0": (dict(accuracy=1e-6, t_final=1.0, t0=2.0), ValueError, "t_final: must be after"),
    "t_final a string": (dict(accuracy=1e-6, t_final="10"), TypeError, "t_final"),
    "neither dt nor accuracy": (dict(), ValueError, "dt and n_steps: required"),
}


@pytest.mark.parametrize("case", sorted(_BAD))
def test_bad_accuracy_arguments_are_refused_before_compiling(case):
    kwargs, error, message = _BAD[case]
    with compiles_recorded() as compiled, pytest.raises(error, match=message):
        cj.integrate(RIGID, Q0_BODY, OMEGA0, **kwargs)
    assert compiled == []


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(candidates=()), "candidates: expected at least one"),
        (dict(candidates=[{"dt": 0.1}]), "candidates: 'dt' is not a method option"),
        (dict(candidates={"order": 4}), "candidates: expected a sequence"),
        (dict(time_scale=-1.0), "time_scale: expected a positive"),
        (dict(scheme="gauss"), "scheme: accuracy= chooses the method"),
        (dict(tolerance=1e-6), "tolerance: not an option"),
        (dict(candidates=[{"scheme": "gauss", "composition": "Suzuki p4s5"}]), "no candidate .*not applicable"),
    ],
)
def test_bad_choose_step_arguments_are_refused_before_compiling(kwargs, message):
    with compiles_recorded() as compiled, pytest.raises((TypeError, ValueError), match=message):
        cj.choose_step(RIGID, Q0_BODY, OMEGA0, t_final=10.0, accuracy=1e-6, **kwargs)
    assert compiled == []


def test_accuracy_inside_jit_is_refused_with_what_to_do():
    with pytest.raises(ValueError, match="concrete .*choose_step outside"):
        jax.jit(lambda w: cj.integrate(RIGID, Q0_BODY, w, t_final=1.0, accuracy=1e-6).Q)(OMEGA0)


def test_the_cost_model_follows_the_committed_measurements():
    """The work per step of `work_per_step` (stage-sweeps, solves, updates, the step) against the
    CPU time per step of every native rigid-body point of the committed ensemble benchmark:
    one common scale (least squares in the logarithm) fits each point within a factor 1.5
    (the run was on a shared machine; its points scatter by about that much). A rerun that
    moves the costs fails here: refit the constants of `clebsch_jax.march.pilot`."""
    path = pathlib.Path(__file__).parents[1] / "benchmarks" / "results" / "work_precision_ensembles.json"
    scene = next(r for r in json.loads(path.read_text())["results"] if r["scene"] == "rigid_body")
    solves = {"order2": 1, "order4": 5, "order6": 9, "order8": 17}
    predicted, measured = [], []
    for p in scene["points"]:
        if p["family"] != "ours" or p.get("backend") != "native":
            continue
        if p["method"].startswith("gauss"):
            stages = int(p["method"][len("gauss") :]) // 2
            work = STEP_COST + p["newton_per_step"] * stages * GAUSS_STAGE_SWEEP_COST
        elif p["method"] in solves:
            work = STEP_COST + solves[p["method"]] * NEWTON_SOLVE_COST + p["newton_per_step"] * NEWTON_UPDATE_COST
        else:
            continue
        predicted.append(work)
        measured.append(p["cpu_s"] / (scene["members"] * p["steps"]))
    assert len(predicted) >= 8  # both families, several steps each
    ratio = np.log(np.asarray(measured) / np.asarray(predicted))
    assert np.max(np.abs(ratio - np.mean(ratio))) <= math.log(1.5)


@pytest.mark.parametrize("kappa", [0.05, 0.3, 0.9])
def test_the_contraction_margin_finds_the_step_of_a_known_contraction(kappa):
    """Sweep counts of a fixed-point iteration contracting by ρ(h) = κh to a tolerance ε,
    N(h) = log ε / log ρ(h), at the pilot's steps h and h/2: the step returned is the one at
    which κh = MAX_CONTRACTION, whichever side of it the pilot's steps lie; counts that do not
    fall with the step give no limit."""
    from clebsch_jax.march.pilot import MAX_CONTRACTION, Measured, contraction_step

    h = 0.6
    counts = tuple(math.log(1e-16) / math.log(kappa * s) for s in (h, h / 2))
    measured = Measured(1.0, 8.0, h, (h, h / 2), counts, 0.0)
    assert contraction_step(measured) == pytest.approx(MAX_CONTRACTION / kappa, rel=1e-12)
    flat = Measured(1.0, 8.0, h, (h, h / 2), (5.0, 5.0), 0.0)
    assert contraction_step(flat) == math.inf
    assert contraction_step(Measured(1.0, 8.0, h, (h,), (5.0,), 0.0)) == math.inf
