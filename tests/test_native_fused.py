"""Sums over an axis of elementwise expressions as loops (`clebsch_jax.native.fused`): random
pairwise expressions over particles (broadcasts of vectors, elementwise arithmetic on the (N, N)
arrays, sums over one axis or both, contractions, and their gradients by `jax.grad`) give XLA's
values to 1e-12 and the entries written out bit for bit, in fewer lines of IR."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from clebsch_jax.native import compile_member, fused, kernel

B = 6  # two blocks of lanes, the second padded

_PAIRWISE = [
    lambda x, y: x[:, None] - y[None, :],
    lambda x, y: x[None, :] * y[:, None],
    lambda x, y: jnp.exp(-((x[:, None] - x[None, :]) ** 2)),
    lambda x, y: jnp.log(1.0 + (x[:, None] - y[None, :]) ** 2 + jnp.eye(x.shape[0])),
    lambda x, y: jnp.where(x[:, None] > y[None, :], x[:, None], -y[None, :]),
    lambda x, y: jnp.sqrt(1.0 + x[:, None] ** 2 * y[None, :] ** 2) / (2.0 + jnp.cos(y[None, :])),
]
_COMBINE = [jnp.add, jnp.multiply, lambda a, b: a / (1.0 + b * b), lambda a, b: jnp.maximum(a, b) - b]


def _sums(a, w):
    """Every reduction of an (N, N) array the loops cover: over one axis, both, and contractions."""
    return jnp.sum(a, axis=0), jnp.sum(a, axis=1), jnp.sum(a), a @ w, w @ a


def _program(terms):
    def energy(x, y, w):
        a = _PAIRWISE[terms[0][0] % len(_PAIRWISE)](x, y)
        for op, k in terms[1:]:
            a = _COMBINE[op % len(_COMBINE)](a, _PAIRWISE[k % len(_PAIRWISE)](x, y))
        return a

    def f(x, y, w):
        a = energy(x, y, w)
        grad = jax.grad(lambda x, y: jnp.sum(energy(x, y, w) * w[None, :]), argnums=(0, 1))(x, y)
        return (*_sums(a, w), *grad)

    return f


_TERMS = st.lists(st.tuples(st.integers(0, 9), st.integers(0, 9)), min_size=1, max_size=3)


def _unrolled(f, *args):
    """`f`'s kernel with no expression deferred: every entry written out."""
    saved = fused.MIN_ENTRIES
    fused.MIN_ENTRIES = 10**9
    try:
        return compile_member(f, *args, use_cache=False)
    finally:
        fused.MIN_ENTRIES = saved


@settings(max_examples=3, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(terms=_TERMS, n=st.sampled_from([8, 9]), seed=st.integers(0, 2**31 - 1))
def test_random_pairwise_sums_agree_with_xla_and_the_unrolled_code(terms, n, seed):
    """XLA's values to 1e-12 of each output's size (its sums run in another order), and the
    unrolled kernel's bit for bit (the loops sum in the same order from -0.0)."""
    f = _program(terms)
    rng = np.random.default_rng(seed)
    x, y, w = (rng.standard_normal((B, n)) for _ in range(3))
    looped = compile_member(f, x[0], y[0], w[0], use_cache=False)(x, y, w)
    xla = jax.vmap(f)(x, y, w)
    for a, b in zip(looped, xla):
        a, b = np.asarray(a), np.asarray(b)
        size = np.max(np.abs(b), axis=tuple(range(1, b.ndim)), keepdims=True) if b.ndim > 1 else np.abs(b)
        assert np.all(np.abs(a - b) <= 1e-12 * np.maximum(size, 1e-300)), np.max(np.abs(a - b) / size)
    unrolled = _unrolled(f, x[0], y[0], w[0])(x, y, w)
    for a, b in zip(looped, unrolled):
        np.testing.assert_array_equal(np.asarray(a).view(np.int64), np.asarray(b).view(np.int64))


def test_a_pairwise_sum_is_a_loop_whose_code_does_not_grow_with_the_particles():
    """The point-vortex Hamiltonian's gradient (pairwise (N, N) arithmetic, sums over each axis):
    the loops' kernel is the same size for 10 and 20 particles but for the entries read and
    written, where the entries written out grow as N²."""
    from clebsch_jax.models._point_vortices import _hamiltonian

    def lines(n, unroll):
        closed = jax.make_jaxpr(jax.grad(_hamiltonian, 1))(np.ones(n), np.ones((n, 2)))
        saved = fused.MIN_ENTRIES
        fused.MIN_ENTRIES = 10**9 if unroll else saved
        try:
            return kernel.build_ir(closed, 4).count("\n")
        finally:
            fused.MIN_ENTRIES = saved

    looped = {n: lines(n, False) for n in (10, 20)}
    unrolled = {n: lines(n, True) for n in (10, 20)}
    assert unrolled[20] > 3.5 * unrolled[10]  # written out: N² entries
    assert looped[20] < 2.2 * looped[10]  # looped: the entries of the inputs and outputs, N
    assert looped[10] < unrolled[10] / 3


def test_a_sum_of_known_entries_stays_written_out_and_folded():
    """A sum whose operands are known while translating is known (folded), not a loop: the
    code after it folds too."""

    def f(x):
        k = jnp.arange(10.0)
        return x * jnp.sum(k[:, None] * k[None, :] + jnp.eye(10), axis=0)

    x = np.random.default_rng(0).standard_normal((B, 10))
    native = compile_member(f, x[0], use_cache=False)(x)
    np.testing.assert_array_equal(np.asarray(native), np.asarray(jax.vmap(f)(x)))
    text = kernel.build_ir(jax.make_jaxpr(f)(x[0]), 4)
    assert "sum.head" not in text


@pytest.mark.parametrize("axes", [(0,), (0, 2), (1, 2)])
def test_sums_over_axes_of_a_three_dimensional_expression(axes):
    """A (N, N, 3) expression summed over any of its axes: the loops over the first reduced axis
    and the large kept ones, the rest in the body, in the unrolled order."""

    def f(x, v):
        d = x[:, None, :] - x[None, :, :]
        return jnp.sum(jnp.tanh(d) * v[None, :, None] + d * d, axis=axes)

    rng = np.random.default_rng(4)
    x, v = rng.standard_normal((B, 9, 3)), rng.standard_normal((B, 9))
    looped = compile_member(f, x[0], v[0], use_cache=False)(x, v)
    np.testing.assert_allclose(np.asarray(looped), np.asarray(jax.vmap(f)(x, v)), rtol=1e-12, atol=1e-12)
    unrolled = _unrolled(f, x[0], v[0])(x, v)
    np.testing.assert_array_equal(np.asarray(looped).view(np.int64), np.asarray(unrolled).view(np.int64))
