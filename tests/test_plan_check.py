"""The check of an accuracy plan at its own step (`clebsch_jax.march.check`): the growth exponent
of an error envelope of known growth, and the check's prediction and step reduction on runs
whose error is known exactly, C(h) (t − t₀)^q hᵖ, with a step-size resonance in C(h)."""

from __future__ import annotations

import math
import types

import numpy as np
import pytest

from clebsch_jax.march import check as check_module
from clebsch_jax.march import pilot as pilot_module
from clebsch_jax.march.check import CHECK_TRIES, GROWTH_CAP, check_plan, growth_exponent
from clebsch_jax.march.accuracy import Candidate
from clebsch_jax.roots.status import Status


@pytest.mark.parametrize("q", [1.0, 1.3, 1.7, 2.0])
def test_the_growth_exponent_of_an_oscillating_envelope(q):
    """e(t) = tᵠ |sin 5t|: a phase error oscillating along an orbit under an envelope tᵠ. The
    running maximum touches tᵠ once per half period, so the fit over the second half recovers
    q to the envelope's ripple (a half period is 0.3 of t = 20..40)."""
    ts = np.linspace(0.0, 40.0, 4001)
    q_fit = growth_exponent(ts, ts**q * np.abs(np.sin(5 * ts)), 0.0)
    assert q_fit == pytest.approx(q, abs=0.03)


def test_the_growth_exponent_is_held_between_linear_and_the_cap():
    ts = np.linspace(1.0, 41.0, 401)  # t0 = 1: the span is t − 1
    span = ts - 1.0
    assert growth_exponent(ts, span**0.5, 1.0) == 1.0  # bounded (e.g. an action error): linear at least
    assert growth_exponent(ts, np.exp(span), 1.0) == GROWTH_CAP  # exponential: the cap
    assert growth_exponent(ts, span**1.5, 1.0) == pytest.approx(1.5, rel=1e-12)
    assert growth_exponent(ts, np.zeros_like(ts), 1.0) == 1.0  # nothing measured


P, Q_GROWTH, T, ACCURACY = 8, 1.5, 1000.0, 1e-8


def _constant(h):
    """C(h): 1e-5, and 100 times that in a step-size resonance at h in (0.29, 0.31)."""
    return 1e-5 * (100.0 if 0.29 < h < 0.31 else 1.0)


def _march(stepper, dt, n):
    """One member's run at step dt: the exact momentum (0: the error measure is then absolute)
    plus the known error C(dt) t^q dtᵖ."""
    t = np.arange(n + 1) * dt
    m = _constant(dt) * t**Q_GROWTH * dt**P
    sol = types.SimpleNamespace(
        Q=None, momentum=m[:, None], result=np.int32(Status.SUCCESS), stats=types.SimpleNamespace(iterations=np.ones(n))
    )
    return [sol]


def _row(dt):
    n = math.ceil(T / dt)
    return Candidate(
        "known", P, (), 1e-5, 8.0, 1.0, T / n, n, ACCURACY / 2, 1.0, n * 2.0, 0.0
    )  # the pilot's (wrong) prediction


def test_the_check_predicts_the_known_error_and_steps_out_of_a_resonance(monkeypatch):
    """The error C(h) t^1.5 hᵖ at T = 1000 from a check over 40: Richardson's estimate at h and
    h/2 is exact for this error, so the check recovers q = 1.5 and predicts C(h) T^1.5 hᵖ at the
    step it keeps. Planned at h = 0.3, inside the resonance, the check reduces the step until the
    known error at T is within the accuracy; planned outside, it keeps the step when the known
    error is within it."""
    for module in (check_module, pilot_module):  # the check's runs are counted by the pilot's `run_record`
        monkeypatch.setattr(module, "work_per_step", lambda stepper, system, its: 1.0)
    pilot_horizon = 40.0
    for h, kept in ((0.3, False), (0.1, True)):
        row = _row(h)
        checked, growth, found = check_plan(_march, None, None, row, 0.0, T, pilot_horizon, ACCURACY)
        assert found == "met" and growth == pytest.approx(Q_GROWTH, rel=1e-6)
        exact = _constant(checked.dt) * T**Q_GROWTH * checked.dt**P
        assert checked.predicted_error == pytest.approx(exact, rel=1e-6)
        assert exact <= ACCURACY
        assert (checked.dt == row.dt) == kept
        assert checked.n_steps * checked.dt == pytest.approx(T, rel=1e-12)
        assert checked.pilot_work > row.pilot_work  # the check's runs counted
    # the plan's step missed by the resonance's factor and the growth's: the check saw it
    assert _constant(_row(0.3).dt) * T**Q_GROWTH * _row(0.3).dt ** P > 100 * ACCURACY


def test_a_check_that_cannot_meet_the_accuracy_says_so(monkeypatch):
    """An error that no step of the tries reaches (C = 1e10): the plan keeps the last step it
    checked, predicts its error above the accuracy and says "not met"."""
    for module in (check_module, pilot_module):  # the check's runs are counted by the pilot's `run_record`
        monkeypatch.setattr(module, "work_per_step", lambda stepper, system, its: 1.0)
    monkeypatch.setattr(check_module, "ROUNDOFF_FLOOR", 0.0)
    calls = []

    def march(stepper, dt, n):
        calls.append(dt)
        t = np.arange(n + 1) * dt
        sol = _march(stepper, dt, n)[0]
        sol.momentum = 1e10 * np.exp(t / 10)[:, None] * dt**P
        return [sol]

    checked, growth, found = check_plan(march, None, None, _row(0.1), 0.0, T, 40.0, ACCURACY)
    assert found == "not met" and checked.predicted_error > ACCURACY and growth == GROWTH_CAP
    assert len(calls) == 2 * CHECK_TRIES and checked.dt == calls[-2]
