"""Cheaper forms in the sweep's per-member program and in its native translation: the same
values as the forms they replace."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from clebsch_jax.native import compile_member

pytest.importorskip("llvmlite")

# every class of double: signed zeros, subnormals, normals of both signs, infinities, NaNs of
# both signs (the hardware's own NaN has the sign bit set); 11 × 11 pairs, in lanes
_SPECIAL = np.array([0.0, -0.0, 5e-324, -5e-324, 1.5, -1.5, 2.0, np.inf, -np.inf, np.nan, -np.nan], dtype=np.float64)


def _max_of_sizes(xp, a, b):
    """Maxima whose operands have a clear sign bit: |·|, their maxima, selects of them and
    positive constants (`xp`: jax.numpy, or NumPy for the reference)."""
    m = xp.maximum(xp.abs(a), xp.abs(b))
    return m, xp.maximum(m, 1.0), xp.maximum(xp.where(xp.isnan(b), 0.0, xp.abs(b)), m)


def test_maxima_of_sizes_are_exact_for_every_class_of_double():
    """NumPy's maxima as the reference (XLA's CPU flushes subnormals to zero, the kernels do
    not, with or without this form): the same numbers bit for bit, NaN where NumPy's is."""
    a, b = (g.ravel() for g in np.meshgrid(_SPECIAL, _SPECIAL))
    native = compile_member(lambda a, b: _max_of_sizes(jnp, a, b), a[0], b[0], use_cache=False)(a, b)
    with np.errstate(invalid="ignore"):
        exact = _max_of_sizes(np, a, b)
    for k, (n, x) in enumerate(zip(native, exact)):
        nan = np.isnan(x)
        assert np.array_equal(np.isnan(n), nan), k
        assert np.array_equal(np.asarray(n).view(np.uint64)[~nan], x.view(np.uint64)[~nan]), k


def test_a_maximum_of_sizes_is_an_integer_maximum_in_the_kernel():
    from clebsch_jax.native.kernel import build_ir

    closed = jax.make_jaxpr(lambda a, b: jnp.maximum(jnp.maximum(jnp.abs(a), jnp.abs(b)), 1.0))(1.0, 2.0)
    text = build_ir(closed, 4)
    assert "llvm.maximum" not in text and "icmp sgt <4 x i64>" in text
    general = build_ir(jax.make_jaxpr(lambda a, b: jnp.maximum(jnp.abs(a), b))(1.0, 2.0), 4)
    assert "llvm.maximum" in general


def test_a_failed_step_discards_what_it_computed_and_keeps_what_it_handed_on():
    """The state after a failed step is NaN wherever the step computed it; a leaf the step
    handed on unchanged (the reduced step's identity Q when Q is not carried) stays itself."""
    from clebsch_jax.batching.member import _nan_unless_made

    def step(ok, state):
        mu, Q, n = state
        return _nan_unless_made(ok, (2.0 * mu, Q, n + 1), state)

    state = (jnp.ones(3), jnp.eye(3), jnp.asarray(4))
    mu, Q, n = jax.jit(step)(False, state)
    assert np.all(np.isnan(mu)) and np.array_equal(Q, np.eye(3)) and n == 5
    mu, Q, n = jax.jit(step)(True, state)
    assert np.array_equal(mu, [2.0, 2.0, 2.0]) and np.array_equal(Q, np.eye(3))
