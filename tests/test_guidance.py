"""What `integrate` tells a user about a hand-written system (issue 44's small items): the
method's facts agree with each other, failures are counted in the unit of the option that caps
them, a configuration off the group the velocity map acts by is named, and a function remade
for every value of a Python number is said to recompile."""

from __future__ import annotations

import warnings

import jax.numpy as jnp
import numpy as np
import pytest

import clebsch_jax as cj
from clebsch_jax.march import arguments as _arguments
from clebsch_jax.march import integrate as _integrate
from clebsch_jax.march.solution import failure_message

INERTIA = jnp.array([2.0, 1.0, 2.0 / 3.0])
XI0 = jnp.array([1.3, 0.8, -0.4])


def _body_lagrangian(xi):
    return 0.5 * jnp.sum(INERTIA * xi**2)


def _right_so3(xi, Q):
    return Q @ cj.lie.hat(xi)


SO3 = cj.ClebschSystem(lagrangian=_body_lagrangian, velocity_map=_right_so3, derivative_map=cj.cayley)


def test_the_scheme_of_a_symmetric_pair_names_both_principles_as_the_method_does():
    plan = cj.step_plan(cj.models.heavy_top(INERTIA, 1.0), Q0=jnp.eye(3), xi0=XI0)
    sol_facts = cj.SymmetricPair(cj.FullStep()).facts(SO3)
    assert sol_facts.scheme == "right o left" and sol_facts.name == "right(h/2) o left(h/2)"
    assert plan.name.startswith("right(h/2) o left(h/2)")
    composed = cj.Composed(cj.SymmetricPair(cj.FullStep()), cj.COMPOSITIONS["triple jump p4s3"]).facts(SO3)
    assert composed.scheme == "right o left"


def test_newton_failures_are_counted_in_max_newton_iterations_unit():
    """`max_newton_iterations` caps the Jacobians formed; the message counts those, then updates."""
    message = failure_message(cj.Status.MAX_ITERATIONS, 3, 10, 0.3, 90, 1e-3, None, "left", 1, 20)
    assert "after 20 Newton iterations (max_newton_iterations counts these" in message and "90 updates" in message
    sol = cj.integrate(
        SO3, jnp.eye(3), 40.0 * XI0, dt=1.0, n_steps=2, max_newton_iterations=1, throw=False, scheme="left"
    )
    assert int(sol.result) == cj.Status.MAX_ITERATIONS  # a step this large is not solved with one Jacobian
    updates = int(np.asarray(sol.stats.iterations)[0])
    assert updates > 1  # chord updates: more updates than the cap allows iterations
    with pytest.raises(
        cj.IntegrationError,
        match=rf"after 1 Newton iterations \(max_newton_iterations counts these: "
        rf"Jacobians formed\), with {updates} updates",
    ):
        sol.raise_if_failed()


@pytest.mark.parametrize(
    "Q0, problem",
    [(1.01 * np.eye(3), "max|Q^T Q - I|"), (np.diag([1.0, 1.0, -1.0]), "det Q = -1")],
    ids=["scaled", "reflection"],
)
def test_a_hand_written_so3_system_warns_about_a_q0_off_the_group(Q0, problem, monkeypatch):
    """No check_Q given: the engine reads SO(3) off the velocity map (right multiplication by
    antisymmetric matrices) and names what is wrong with Q0, before marching (stubbed here)."""
    monkeypatch.setattr(_integrate, "march_chunked", lambda *a, **k: (_ for _ in ()).throw(RuntimeError("marched")))
    with pytest.warns(
        UserWarning,
        match=r"Q0: velocity_map moves Q by right multiplication with the Lie algebra "
        r"of SO\(3\), but Q0 is not in SO\(3\)",
    ) as record:
        with pytest.raises(RuntimeError, match="marched"):
            cj.integrate(SO3, Q0, XI0, dt=0.1, n_steps=2)
    assert any(problem in str(w.message) for w in record)
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        with pytest.raises(RuntimeError, match="marched"):
            cj.integrate(SO3, np.eye(3), XI0, dt=0.1, n_steps=2)  # a rotation: silent


def test_a_function_remade_for_each_value_of_a_python_number_is_said_to_recompile(monkeypatch):
    monkeypatch.setattr(_arguments, "_CLOSED_NUMBERS", {})
    monkeypatch.setattr(_arguments, "_REMADE_WARNED", set())
    monkeypatch.setattr(_integrate, "march_chunked", lambda *a, **k: (_ for _ in ()).throw(RuntimeError("marched")))

    def attempt(g):
        system = cj.ClebschSystem(
            lagrangian=lambda xi, q: 0.5 * jnp.sum(xi**2) - g * q[2],
            velocity_map=lambda xi, q: jnp.cross(xi, q),
            derivative_map=cj.forward_difference,
        )
        with warnings.catch_warnings(record=True) as record:
            warnings.simplefilter("always")
            with pytest.raises(RuntimeError, match="marched"):
                cj.integrate(system, jnp.array([0.6, 0.0, -0.8]), jnp.array([0.0, 0.3, 0.0]), dt=0.1, n_steps=2)
        return [str(w.message) for w in record if "compiled again" in str(w.message)]

    assert attempt(1.0) == [] and attempt(1.0) == []  # the same number: nothing to say
    said = attempt(2.0)
    assert len(said) == 1 and said[0].startswith("lagrangian:") and "2.0; before: 1.0" in said[0]
    assert attempt(3.0) == []  # once per function
