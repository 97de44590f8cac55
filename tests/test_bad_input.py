"""Issue 2, check 7: bad input gets a clear error naming the argument, before compiling."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import clebsch_jax as cj
from clebsch_jax import _integrate

SYSTEM = cj.models.rigid_body(np.array([2.0, 1.0, 2.0 / 3.0]))
Q0, XI0 = np.eye(3), np.array([0.3, 0.1, 1.0])


@pytest.fixture(autouse=True)
def no_compilation(monkeypatch):
    """Every error here must be raised before the march is traced or compiled."""
    def boom(*args, **kwargs):
        raise AssertionError("the march was compiled for invalid input")

    monkeypatch.setattr(_integrate, "_march_full_jit", boom)
    monkeypatch.setattr(_integrate, "_march_reduced_jit", boom)


@pytest.mark.parametrize(
    "error, kwargs, match",
    [
        (ValueError, dict(dt=0.0), r"^dt: must be positive"),
        (ValueError, dict(dt=-0.1), r"^dt: must be positive"),
        (ValueError, dict(dt=float("nan")), r"^dt: contains non-finite"),
        (ValueError, dict(dt=float("inf")), r"^dt: contains non-finite"),
        (ValueError, dict(dt=np.array([0.1, 0.2])), r"^dt: expected a scalar"),
        (ValueError, dict(n_steps=0), r"^n_steps: must be at least 1"),
        (ValueError, dict(n_steps=-5), r"^n_steps: must be at least 1"),
        (ValueError, dict(Q0=np.full((3, 3), np.nan)), r"^Q0: contains non-finite"),
        (ValueError, dict(xi0=np.array([0.0, np.inf, 1.0])), r"^xi0: contains non-finite"),
        (ValueError, dict(xi0=np.zeros(4)), r"^velocity_map: calling it as velocity_map\(xi0, Q0\)|^lagrangian:"),
        (ValueError, dict(Q0=np.eye(4)), r"^velocity_map: calling it"),
        (ValueError, dict(P0=np.zeros((2, 2))), r"^P0: expected Q0's shape"),
        (ValueError, dict(scheme="middle"), r"^scheme: expected one of"),
        (ValueError, dict(rtol=-1.0), r"^rtol: expected a finite float"),
        (ValueError, dict(max_newton_iterations=0), r"^max_newton_iterations: expected an int"),
        (TypeError, dict(n_steps=2.5), r"^n_steps: expected a Python int"),
        (TypeError, dict(n_steps=True), r"^n_steps: expected a Python int"),
        (TypeError, dict(Q0="identity"), r"^Q0: expected an array"),
        (TypeError, dict(xi0=np.array([1 + 1j, 0, 0])), r"^xi0: expected a real floating-point array"),
    ],
)
def test_invalid_arguments_raise_naming_the_argument(error, kwargs, match):
    """ValueError for bad values, TypeError for bad types; the message starts with the name."""
    args = dict(Q0=Q0, xi0=XI0, dt=0.1, n_steps=10)
    args.update(kwargs)
    Q, xi = args.pop("Q0"), args.pop("xi0")
    with pytest.raises(error, match=match):
        cj.integrate(SYSTEM, Q, xi, **args)


def test_maps_returning_the_wrong_shape_are_named():
    good = dict(lagrangian=lambda x: jnp.sum(x**2), velocity_map=lambda x, Q: x, derivative_map=cj.forward_difference)
    bad_l = cj.ClebschSystem(**{**good, "lagrangian": lambda x: x**2})
    with pytest.raises(ValueError, match=r"^lagrangian: must return a scalar"):
        cj.integrate(bad_l, np.zeros(3), np.ones(3), dt=0.1, n_steps=3)
    bad_L = cj.ClebschSystem(**{**good, "velocity_map": lambda x, Q: x[:2]})
    with pytest.raises(ValueError, match=r"^velocity_map: must return an array of Q's shape"):
        cj.integrate(bad_L, np.zeros(3), np.ones(3), dt=0.1, n_steps=3)
    bad_phi = cj.ClebschSystem(**{**good, "derivative_map": lambda Q1, Q, dt: jnp.sum(Q1 - Q) / dt})
    with pytest.raises(ValueError, match=r"^derivative_map: must return an array of Q's shape"):
        cj.integrate(bad_phi, np.zeros(3), np.ones(3), dt=0.1, n_steps=3)


def test_system_construction_errors():
    with pytest.raises(TypeError, match=r"^lagrangian: expected l\(xi\) or l\(xi, Q\)"):
        cj.ClebschSystem(lagrangian=lambda a, b, c: 0.0, velocity_map=lambda x, Q: x, derivative_map=cj.forward_difference)
    with pytest.raises(TypeError, match=r"^velocity_map: expected a callable"):
        cj.ClebschSystem(lagrangian=lambda x: 0.0, velocity_map=3, derivative_map=cj.forward_difference)
    with pytest.raises(TypeError, match=r"^system: expected a clebsch_jax.ClebschSystem"):
        cj.integrate(object(), Q0, XI0, dt=0.1, n_steps=3)
    with pytest.raises(ValueError, match=r"^inertia: expected the three principal moments"):
        cj.models.rigid_body(np.ones(4))


_dims = st.integers(min_value=1, max_value=5)


@settings(max_examples=40, deadline=None)
@given(q_shape=st.lists(_dims, min_size=1, max_size=3), xi_shape=st.lists(_dims, min_size=1, max_size=3))
def test_shape_mismatch_between_Q0_and_xi0_is_caught(q_shape, xi_shape):
    """For the vector-space system L_ξQ = ξ, any Q0/ξ0 shape mismatch is an error before
    compilation; matching shapes are accepted (they reach the march, which is stubbed out)."""
    system = cj.ClebschSystem(
        lagrangian=lambda x: 0.5 * jnp.sum(x**2), velocity_map=lambda x, Q: x, derivative_map=cj.forward_difference
    )
    Q, xi = np.zeros(q_shape), np.ones(xi_shape)
    if tuple(q_shape) == tuple(xi_shape):
        with pytest.raises(AssertionError, match="compiled"):
            cj.integrate(system, Q, xi, dt=0.1, n_steps=2)
    else:
        with pytest.raises(ValueError, match=r"^velocity_map: must return an array of Q's shape"):
            cj.integrate(system, Q, xi, dt=0.1, n_steps=2)


@settings(max_examples=40, deadline=None)
@given(dt=st.one_of(st.floats(max_value=0.0), st.just(float("nan")), st.just(float("inf")), st.just(-float("inf"))))
def test_any_nonpositive_or_nonfinite_dt_is_rejected(dt):
    with pytest.raises(ValueError, match=r"^dt: "):
        cj.integrate(SYSTEM, Q0, XI0, dt=dt, n_steps=3)

