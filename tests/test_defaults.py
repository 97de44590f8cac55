"""Right by default: with no method options every system gets a symmetric, second-order method.

The measured order of the default, from a log-log fit of the error at the final time against the
step size, on every built-in model and on two systems with a potential written by a user (a
spherical pendulum on R³ and a heavy top on SO(3)); and the pendulum's invariants over a long run.
Each model runs at four step sizes with the same shapes, so `integrate` compiles once per model.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import clebsch_jax as cj
from clebsch_jax.march.scan import CHUNK_STEPS

GRAVITY = 9.81


def pendulum():
    """A spherical pendulum written on R³ as a new user would: so(3) acts by the cross product,
    the forward difference, l = ½|ξ×Q|² + ½(ξ·Q)² − g Q_z (the issue's example)."""
    return cj.ClebschSystem(
        lagrangian=lambda xi, Q: 0.5 * jnp.sum(jnp.cross(xi, Q) ** 2) + 0.5 * jnp.dot(xi, Q) ** 2 - GRAVITY * Q[2],
        velocity_map=lambda xi, Q: jnp.cross(xi, Q),
        derivative_map=cj.forward_difference,
    )


PENDULUM = pendulum()
PENDULUM_Q0 = jnp.array([np.sin(1.0), 0.0, -np.cos(1.0)])
PENDULUM_XI0 = jnp.array([0.0, 0.3, 1.2])

TOP_INERTIA = jnp.array([1.0, 1.0, 0.4])


def user_heavy_top():
    """A heavy top written by a user on SO(3) with the Cayley map: l = ½ξ·𝕀ξ − mgl (Qχ)·e₃."""
    return cj.ClebschSystem(
        lagrangian=lambda xi, Q: 0.5 * jnp.sum(TOP_INERTIA * xi * xi) - 1.5 * (Q @ jnp.array([0.0, 0.0, 1.0]))[2],
        velocity_map=lambda xi, Q: Q @ cj.lie.hat(xi),
        derivative_map=cj.cayley,
    )


TOP_Q0 = cj.lie.so3_exp(jnp.array([0.5, 0.0, 0.0]))
TOP_XI0 = jnp.array([0.3, -0.2, 2.0])
INERTIA = jnp.array([2.0, 1.0, 2.0 / 3.0])
XI0 = jnp.array([1.3, 0.8, -0.4])
CIRCULATIONS = jnp.array([1.0, -1.0, 1.0, -1.0])
VORTEX_Q0 = jnp.array([[0.0, 1.0], [0.0, -1.0], [0.0, 0.5], [0.0, -0.5]])
PEAKON_Q0, PEAKON_P0 = jnp.array([-3.0, 0.0]), jnp.array([2.0, 1.0])
LANDMARK_Q0 = jnp.array([[0.0, 0.0], [1.0, 0.3]])
LANDMARK_P0 = jnp.array([[1.0, 0.0], [-0.5, 0.5]])


def _cases():
    """name → (system, Q0, xi0, P0, final time, coarsest step)."""
    vector_Q0, vector_P0 = cj.models.rigid_body_vector_start(INERTIA * XI0)
    return {
        "rigid_body": (cj.models.rigid_body(INERTIA), jnp.eye(3), XI0, None, 2.0, 0.1),
        "rigid_body_vector": (cj.models.rigid_body_vector(INERTIA), vector_Q0, XI0, vector_P0, 2.0, 0.1),
        "heavy_top": (cj.models.heavy_top(TOP_INERTIA, 1.5), TOP_Q0, TOP_XI0, None, 1.0, 0.05),
        "point_vortices": (
            cj.models.point_vortices(CIRCULATIONS),
            VORTEX_Q0,
            cj.models.vortex_velocity(CIRCULATIONS, VORTEX_Q0),
            None,
            1.0,
            0.05,
        ),
        "peakons": (
            cj.models.peakons(1.0),
            PEAKON_Q0,
            cj.models.peakon_velocity(PEAKON_Q0, PEAKON_P0, 1.0),
            PEAKON_P0,
            2.0,
            0.1,
        ),
        "landmarks": (
            cj.models.landmarks(1.0),
            LANDMARK_Q0,
            cj.models.landmark_velocity(LANDMARK_Q0, LANDMARK_P0, 1.0),
            LANDMARK_P0,
            1.0,
            0.05,
        ),
        "user_pendulum": (PENDULUM, PENDULUM_Q0, PENDULUM_XI0, None, 1.0, 0.05),
        "user_heavy_top": (user_heavy_top(), TOP_Q0, TOP_XI0, None, 1.0, 0.05),
    }


CASES = _cases()


def _final_state(sol):
    """Momentum map and (when carried) configuration at the last node, as one vector."""
    parts = [sol.momentum[-1].ravel()] + ([sol.Q[-1].ravel()] if sol.Q is not None else [])
    return np.concatenate([np.asarray(p) for p in parts])


@pytest.mark.parametrize("name", list(CASES))
def test_the_default_is_symmetric_second_order_and_measures_so(name):
    system, Q0, xi0, P0, T, h0 = CASES[name]
    plan = cj.step_plan(system, Q0=Q0, xi0=xi0)
    assert plan.order == 2 and plan.symmetric, (name, plan.name)
    runs = {}
    for k in (1, 2, 4, 64):  # the finest run is the reference: its error is (1/16)² of the finest fitted
        n = round(T / h0) * k
        sol = cj.integrate(system, Q0, xi0, P0=P0, dt=h0 / k, n_steps=n)
        assert sol.order == 2 and sol.method == plan.name, (name, sol.method)
        runs[k] = _final_state(sol)
    hs = np.array([h0, h0 / 2, h0 / 4])
    errors = np.array([np.max(np.abs(runs[k] - runs[64])) for k in (1, 2, 4)])
    slope = np.polyfit(np.log(hs), np.log(errors), 1)[0]
    assert slope >= 1.9, f"{name}: measured order {slope:.2f} (errors {errors})"


def test_first_order_principles_stay_available_by_name():
    system, Q0, xi0, _, _, _ = CASES["user_heavy_top"]
    sol = cj.integrate(system, Q0, xi0, dt=0.05, n_steps=4, scheme="left")
    assert sol.order == 1 and sol.method == "left principle"


def test_the_default_with_a_potential_keeps_the_reduced_march():
    system, Q0, xi0, _, _, _ = CASES["heavy_top"]
    sol = cj.integrate(system, Q0, xi0, dt=0.05, n_steps=4)
    assert sol.form == "reduced" and sol.order == 2
    assert sol.method == "right(h/2) o left(h/2)"


def test_the_rigid_body_default_is_the_reduced_cayley_march_unchanged():
    system, Q0, xi0, _, _, _ = CASES["rigid_body"]
    default = cj.integrate(system, Q0, xi0, dt=0.1, n_steps=20)
    named = cj.integrate(system, Q0, xi0, dt=0.1, n_steps=20, scheme="left")
    assert default.form == "reduced" and default.method == "left principle"
    np.testing.assert_array_equal(np.asarray(default.momentum), np.asarray(named.momentum))


def test_the_user_pendulum_stays_on_the_sphere_and_keeps_its_vertical_angular_momentum():
    """10⁴ default steps: |Q| = 1 to 1e-10 and Q × Q̇ · e₃ to 1e-11 (midpoint principle). The
    same system object and shapes as the order test: no new compilation."""
    sol = cj.integrate(PENDULUM, PENDULUM_Q0, PENDULUM_XI0, dt=0.01, n_steps=10_000)
    Q, xi = np.asarray(sol.Q), np.asarray(sol.xi)
    assert np.max(np.abs(np.linalg.norm(Q, axis=1) - 1.0)) < 1e-10
    vertical = np.cross(Q, np.cross(xi, Q))[:, 2]
    assert np.max(np.abs(vertical - vertical[0])) < 1e-11


# --------------------------------------------------------------------------------------------
# Compile once per system and shapes


class _Compilations:
    """Counts the programs JAX lowers and compiles while the block runs (JAX's own monitoring
    events, emitted for every program not already in its in-memory cache)."""

    EVENTS = ("/jax/core/compile/jaxpr_to_mlir_module_duration", "/jax/core/compile/backend_compile_duration")

    def __init__(self):
        self.count = 0

    def _listen(self, event, duration, **kwargs):
        self.count += event in self.EVENTS

    def __enter__(self):
        jax.monitoring.register_event_duration_secs_listener(self._listen)
        return self

    def __exit__(self, *exc):
        jax.monitoring.unregister_event_duration_listener(self._listen)


def test_a_new_run_length_step_or_parameter_value_compiles_nothing():
    """After one call, a new `n_steps` (also across the chunk length), a new `dt` and a built-in
    model built again with new parameter values reuse the compiled programs; so does a second
    user system call with new `n_steps`."""
    first = cj.integrate(cj.models.rigid_body(INERTIA), jnp.eye(3), XI0, dt=0.05, n_steps=30)
    calls = {
        "new n_steps": lambda: cj.integrate(cj.models.rigid_body(INERTIA), jnp.eye(3), XI0, dt=0.05, n_steps=45),
        "beyond one chunk": lambda: cj.integrate(
            cj.models.rigid_body(INERTIA), jnp.eye(3), XI0, dt=0.05, n_steps=CHUNK_STEPS + 3
        ),
        "new dt": lambda: cj.integrate(cj.models.rigid_body(INERTIA), jnp.eye(3), XI0, dt=0.02, n_steps=30),
        "new inertia": lambda: cj.integrate(
            cj.models.rigid_body(jnp.array([1.0, 2.0, 3.0])), jnp.eye(3), XI0, dt=0.05, n_steps=30
        ),
    }
    for what, call in calls.items():
        with _Compilations() as compiled:
            sol = call()
        assert compiled.count == 0, f"{what}: {compiled.count} programs compiled"
        assert sol.succeeded
    again = cj.integrate(cj.models.rigid_body(INERTIA), jnp.eye(3), XI0, dt=0.05, n_steps=CHUNK_STEPS + 3)
    np.testing.assert_array_equal(np.asarray(again.momentum[:31]), np.asarray(first.momentum))
    cj.integrate(PENDULUM, PENDULUM_Q0, PENDULUM_XI0, dt=0.05, n_steps=20)
    with _Compilations() as compiled:
        cj.integrate(PENDULUM, PENDULUM_Q0, PENDULUM_XI0, dt=0.03, n_steps=33)
    assert compiled.count == 0


def test_a_numpy_integer_run_length_is_accepted_plain_and_under_vmap():
    """`n_steps=np.int64(k)` is the static int k (it used to fail inside `lax.scan` under vmap)."""
    plain = cj.integrate(cj.models.rigid_body(INERTIA), jnp.eye(3), XI0, dt=0.05, n_steps=np.int64(7))
    assert plain.xi.shape == (8, 3)
    batched = jax.vmap(
        lambda xi: cj.integrate(cj.models.rigid_body(INERTIA), jnp.eye(3), xi, dt=0.05, n_steps=np.int64(3)).momentum
    )(jnp.stack([XI0, -XI0]))
    assert batched.shape == (2, 4, 3) and np.all(np.isfinite(np.asarray(batched)))
