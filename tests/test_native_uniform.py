"""Loops whose condition is the same in every lane (`clebsch_jax.native.uniform`): found by
`vmap`'s rule for batched values, and translated without a carry kept per lane."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("llvmlite")

from clebsch_jax.native import compile_member  # noqa: E402
from clebsch_jax.native.kernel import build_ir  # noqa: E402
from clebsch_jax.native.uniform import uniform_loops  # noqa: E402


def _program(x, n):
    """An outer loop of `n` iterations (a counter against n) around an inner loop that stops
    each lane on its own value, and a loop whose counter moves by a value of x."""

    def inner(c):
        return c[0] > 1e-3, None

    def outer_body(i, y):
        z = jax.lax.while_loop(lambda c: (c[0] > 1e-3) & (c[1] < 60), lambda c: (0.5 * c[0], c[1] + 1), (y, 0))
        return jnp.sin(y) + z[0] * i + z[1]

    y = jax.lax.fori_loop(0, n, outer_body, x)
    # the counter starts unbatched but moves by a batched step: batched after one iteration
    k = jax.lax.while_loop(lambda c: c[0] < 5.0, lambda c: (c[0] + jnp.abs(c[1]) + 1.0, c[1]), (0.0, x))[0]
    return y + k


def _whiles(closed) -> list:
    """The program's while equations, in the order `_program` writes them (nested ones after
    their loop's place)."""
    found = []

    def walk(jaxpr):
        for eqn in jaxpr.eqns:
            if eqn.primitive.name == "while":
                found.append(eqn)
            for v in eqn.params.values():
                for x in v if isinstance(v, (tuple, list)) else [v]:
                    if hasattr(getattr(x, "jaxpr", None), "eqns"):
                        walk(x.jaxpr)

    walk(closed.jaxpr)
    return found


def test_a_loop_counted_by_a_shared_bound_is_uniform_and_one_on_a_member_value_is_not():
    closed = jax.make_jaxpr(_program)(1.0, 3)
    outer, inner, moving = _whiles(closed)
    uniform = uniform_loops(closed, [True, False])
    assert id(outer) in uniform
    assert id(inner) not in uniform  # each lane stops on its own value
    assert id(moving) not in uniform  # the counter turns batched through the body (the fixed point)
    assert not uniform_loops(closed, [True, True])  # a bound per member: no loop is uniform


def test_a_uniform_loop_keeps_no_carry_per_lane_and_equals_vmap():
    closed = jax.make_jaxpr(_program)(1.0, 3)
    selects = lambda batched: build_ir(closed, 4, batched).count(" select ")  # noqa: E731
    # the outer loop's carry (y, its counter) kept per lane only when the bound is per member
    assert selects([True, False]) < selects([True, True])
    x = np.linspace(-2.0, 3.0, 11)  # not a multiple of the lanes: padding lanes repeat the last member
    kernel = compile_member(_program, 1.0, np.int32(4), in_axes=(0, None), use_cache=False)
    (got,) = jax.tree_util.tree_leaves(kernel(x, np.int32(4)))
    want = jax.vmap(_program, in_axes=(0, None))(x, 4)
    np.testing.assert_allclose(got, want, rtol=1e-14, atol=0)
