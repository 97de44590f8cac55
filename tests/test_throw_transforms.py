r"""`integrate(..., throw=True)` under `jax.grad`, `jax.jacfwd`, `jax.vmap`, `cj.batch` and
`jax.jit` (issue 40): a failed step is an `IntegrationError` carrying the member, the step and
the status wherever the values reach Python; inside a compiled program (`jax.jit`) it is JAX's
`JaxRuntimeError` whose message carries them and says how to read the statuses instead.

The failing run (not the issue's): a reduced rigid body whose Lagrangian is undefined past
ξ₃ = 0.35; the fast member reaches it mid-run. The step and status expected are read from a
`throw=False` run, the path that raises nothing.

Cost: each path compiles its own program; the default run keeps one of each kind (eager
`grad`, `cj.batch` in compiled chunks, `jax.jit`), the others are slow-marked.
"""

from __future__ import annotations

import pickle

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import clebsch_jax as cj

INERTIA = jnp.array([2.0, 1.0, 2.0 / 3.0])
SYSTEM = cj.ClebschSystem(
    lagrangian=lambda x: 0.5 * jnp.sum(INERTIA * x * x) + 1e-3 * jnp.sqrt(0.35 - x[2]),
    velocity_map=lambda x, Q: Q @ cj.lie.hat(x),
    derivative_map=cj.cayley,
)
N = 40
OK, BAD = jnp.array([0.05, 0.02, 0.05]), jnp.array([0.2, 1.0, 0.3])
MEMBERS = jnp.stack([OK, OK, OK, BAD, OK])  # member 3 fails


def _run(x, throw=True):
    return cj.integrate(SYSTEM, jnp.eye(3), x, dt=0.1, n_steps=N, reduce=True, throw=throw)


def _loss(x):
    return jnp.sum(_run(x).Q[-1])


@pytest.fixture(scope="module")
def expected():
    """(step, status) of the failing member, from the run that does not raise."""
    sol = _run(BAD, throw=False)
    step, status = int(sol.failed_step), cj.Status(int(sol.result))
    assert status != cj.Status.SUCCESS and 0 < step < N  # it fails mid-run
    assert bool(jax.vmap(lambda x: _run(x, False).succeeded)(jnp.stack([OK]))[0])
    return step, status


def _check(err, member, expected):
    step, status = expected
    assert isinstance(err, cj.IntegrationError)
    assert (err.member, err.step, err.status) == (member, step, status)
    where = f"batch member {member}, " if member is not None else ""
    assert f"{where}step {step} of {N}" in str(err) and f"Status.{status.name}" in str(err)


@pytest.mark.parametrize(
    "name, call, member",
    [
        ("grad", lambda: jax.grad(_loss)(BAD), None),
        pytest.param("jacfwd", lambda: jax.jacfwd(lambda x: _run(x).Q[-1])(BAD), None, marks=pytest.mark.slow),
        pytest.param("vmap", lambda: jax.vmap(lambda x: _run(x).Q[-1])(MEMBERS), 3, marks=pytest.mark.slow),
        pytest.param("vmap of grad", lambda: jax.vmap(jax.grad(_loss))(MEMBERS), 3, marks=pytest.mark.slow),
        # chunks of 2: the failing member is the second of the second chunk, named by its
        # index in the batch; the chunks run compiled (lax.map), and batch re-raises the error
        ("batch in chunks", lambda: cj.batch(lambda x: _run(x).Q[-1], chunk=2)(MEMBERS), 3),
        pytest.param(
            "batch", lambda: cj.batch(lambda x: _run(x).Q[-1], chunk=None)(MEMBERS), 3, marks=pytest.mark.slow
        ),
    ],
)
def test_an_integration_error_with_member_step_and_status(name, call, member, expected):
    with pytest.raises(cj.IntegrationError) as info:
        jax.block_until_ready(call())
    _check(info.value, member, expected)
    assert "JaxRuntimeError" not in str(info.value)  # the values reached Python: no hint needed


@pytest.mark.parametrize(
    "name, call, where",
    [
        ("jit", lambda: jax.jit(lambda x: _run(x).Q[-1])(BAD), ""),
        pytest.param("jit of grad", lambda: jax.jit(jax.grad(_loss))(BAD), "", marks=pytest.mark.slow),
        pytest.param(
            "jit of vmap",
            lambda: jax.jit(jax.vmap(lambda x: _run(x).Q[-1]))(MEMBERS),
            "batch member 3, ",
            marks=pytest.mark.slow,
        ),
        pytest.param(
            "jit of batch",
            lambda: jax.jit(cj.batch(lambda x: _run(x).Q[-1], chunk=2))(MEMBERS),
            "batch member 3, ",
            marks=pytest.mark.slow,
        ),
    ],
)
def test_inside_jit_the_runtime_error_carries_them_and_says_how_to_read_statuses(name, call, where, expected):
    step, status = expected
    with pytest.raises(jax.errors.JaxRuntimeError) as info:
        jax.block_until_ready(call())
    text = str(info.value)
    assert f"IntegrationError: clebsch_jax.integrate: {where}step {step} of {N}" in text
    assert f"Status.{status.name}" in text
    assert "pass throw=False and read Solution.result" in text


def test_the_error_keeps_its_attributes_when_pickled(expected):
    """Dask and process pools pickle exceptions."""
    with pytest.raises(cj.IntegrationError) as info:
        _run(BAD)
    again = pickle.loads(pickle.dumps(info.value))
    _check(again, None, expected)
    assert str(again) == str(info.value)


@pytest.mark.slow
def test_no_error_for_healthy_members_on_any_path():
    """The check does not fire where nothing failed (it is not an error raised always)."""
    healthy = jnp.stack([OK, 0.5 * OK])
    g = jax.grad(_loss)(OK)
    assert np.all(np.isfinite(np.asarray(g)))
    out = cj.batch(lambda x: _run(x).Q[-1], chunk=1)(healthy)
    ref = jax.vmap(lambda x: _run(x).Q[-1])(healthy)
    np.testing.assert_allclose(np.asarray(out), np.asarray(ref), rtol=0, atol=1e-13)
