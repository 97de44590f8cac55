r"""`cj.batch`: `jax.vmap`'s meaning, evaluated batch-last and in chunks (issue 6).

The reference is `jax.vmap` of the same function: an independent evaluation of the same
program by JAX's own batching rules. `batch` evaluates the program primitive by primitive with
the batch axis last, so it performs the same floating-point operations on the same numbers;
the tests assert equality to the bit where XLA compiles both layouts to the same scalar code
(elementwise programs, the reduced march) and to a few ulps where it may sum in another order
(reductions, contractions).

These are tests of the interpreter: concrete calls ask for it with `backend="xla"` (by default
they run a native kernel, `tests/test_batch_native.py`); calls inside `jax.jit` always run it.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import clebsch_jax as cj
from clebsch_jax import models
from clebsch_jax.batching.rules import RULES
from clebsch_jax.batching.walk import CALLS, CONTROL

EPS = np.finfo(float).eps
RNG = np.random.default_rng(6)


def assert_trees_close(a, b, atol=0.0):
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        x, y = np.asarray(x), np.asarray(y)
        assert x.shape == y.shape and x.dtype == y.dtype
        if atol == 0.0:
            np.testing.assert_array_equal(x, y)
        else:
            np.testing.assert_allclose(x, y, rtol=0, atol=atol)


def newton_sqrt(a, x0):
    """A per-member while loop (its length depends on the member), a cond, a scan, a matmul,
    reductions, a dynamic index (no batch-last rule: falls back on vmap) and a linear solve."""

    def body(state):
        x, k = state
        return 0.5 * (x + a / x), k + 1

    x, k = jax.lax.while_loop(
        lambda s: (jnp.max(jnp.abs(s[0] * s[0] - a)) > 1e-14 * jnp.max(a)) & (s[1] < 50), body, (x0, 0)
    )
    y = jax.lax.cond(k > 5, lambda v: jnp.sin(v), lambda v: jnp.cos(v), x)
    csum, ys = jax.lax.scan(lambda c, v: (c + v * v, c), jnp.zeros(()), x)
    M = jnp.outer(x, a) + jnp.eye(a.shape[0]) * 3.0
    z = M @ y + jnp.einsum("ij,jk,k->i", M, M, a)
    w = jnp.linalg.solve(M, z)
    pick = x[jnp.argmax(a)]
    return {
        "x": x,
        "k": k,
        "y": y,
        "csum": csum,
        "ys": ys,
        "z": z,
        "w": w,
        "pick": pick,
        "cum": jnp.cumsum(x),
        "stack": jnp.stack([x, a[::-1]], axis=1).reshape(-1)[1:5],
    }


def test_agrees_with_vmap_on_control_flow_and_fallbacks():
    a = jnp.asarray(RNG.uniform(0.1, 50.0, (37, 3)))  # iteration counts differ between members
    x0 = jnp.ones(3)
    ref = jax.jit(jax.vmap(newton_sqrt, in_axes=(0, None)))(a, x0)
    out = jax.jit(cj.batch(newton_sqrt, in_axes=(0, None), chunk=8))(a, x0)
    assert len(set(np.asarray(ref["k"]).tolist())) > 1  # the while loop did differ per member
    # element-wise work to the bit; contractions and the LU solve may sum in another order
    for key in ("x", "k", "y", "ys", "pick", "cum", "stack"):
        assert_trees_close(out[key], ref[key])
    for key in ("csum", "z", "w"):
        scale = np.max(np.abs(np.asarray(ref[key])))
        assert_trees_close(out[key], ref[key], atol=16 * EPS * scale)


def test_predicate_and_index_batched_or_shared():
    """A while loop and a cond whose predicate is shared by the batch take the unbatched path;
    a cond with a per-member index selects per member."""

    def f(n, v):
        total = jax.lax.fori_loop(0, n, lambda i, c: c + v * i, jnp.zeros_like(v))
        branch = jax.lax.switch(jnp.clip(n - 2, 0, 2), [jnp.sin, jnp.cos, jnp.tanh], v)
        return total, branch

    v = jnp.asarray(RNG.normal(size=(6, 2)))
    for n in (jnp.int32(3), jnp.arange(6, dtype=jnp.int32)):
        in_axes = (None if n.ndim == 0 else 0, 0)
        ref = jax.vmap(f, in_axes=in_axes)(n, v)
        out = cj.batch(f, in_axes=in_axes, backend="xla")(n, v)
        assert_trees_close(out, ref)


@pytest.mark.parametrize("B, chunk", [(1, 4), (5, 2), (9, 4), (12, 12), (7, None)])
def test_chunks_and_padding_change_nothing(B, chunk):
    x = jnp.asarray(RNG.normal(size=(B, 3)))

    def f(v):
        return jnp.tanh(v) * jnp.sum(v * v), jnp.linalg.norm(v)

    assert_trees_close(cj.batch(f, chunk=chunk, backend="xla")(x), jax.vmap(f)(x), atol=4 * EPS)


@settings(max_examples=8, deadline=None)  # each example compiles a program
@given(st.integers(1, 40), st.integers(1, 16), st.integers(0, 2**31 - 1))
def test_each_member_independent_of_batch_and_chunk(B, chunk, seed):
    """A member's result does not depend on the other members or on the chunking."""
    x = jnp.asarray(np.random.default_rng(seed).normal(size=(B, 2, 2)))

    def f(m):
        return jax.lax.while_loop(
            lambda s: s[1] < 3 + (s[0][0, 0] > 0), lambda s: (s[0] @ s[0] * 0.5, s[1] + 1), (m, 0)
        )[0]

    out = np.asarray(cj.batch(f, chunk=chunk, backend="xla")(x))
    alone = np.stack([np.asarray(cj.batch(f, backend="xla")(x[i : i + 1]))[0] for i in range(min(B, 3))])
    np.testing.assert_array_equal(out[: len(alone)], alone)


def test_reduced_rigid_body_march_is_bit_identical_to_vmap():
    """The library's reduced march (Cayley, order 4): every field of the Solution, every
    statistic, to the bit, but the residual norms (to round-off); 13 bodies in chunks of 5
    (the last one padded)."""
    system = models.rigid_body(jnp.array([2.0, 1.0, 2.0 / 3.0]))
    omegas = jnp.asarray(RNG.normal(size=(13, 3)))
    Q0 = jnp.asarray(np.stack([np.asarray(cj.lie.so3_exp(jnp.asarray(v))) for v in RNG.normal(size=(13, 3))]))

    def run(q, x):
        return cj.integrate(system, q, x, dt=0.1, n_steps=30, order=4, throw=False)

    ref = jax.jit(jax.vmap(run))(Q0, omegas)
    out = jax.jit(cj.batch(run, chunk=5))(Q0, omegas)
    assert out.form == ref.form == "reduced"
    # The residual left at each root is a difference of nearly equal numbers, ~1e-16: XLA may
    # fuse (and contract into FMAs) the residual's multiply-adds differently in the two layouts,
    # so its last bits may differ (seen: 3 of 390 values, by 1.2e-16). Everything else is
    # bitwise equal.
    scale = float(np.max(np.abs(np.asarray(ref.momentum))))
    for field in ("stats", "nodal_stats"):
        np.testing.assert_allclose(
            getattr(out, field).residual_norm, getattr(ref, field).residual_norm, rtol=0, atol=4 * EPS * scale
        )
    strip = lambda sol: dataclasses.replace(
        sol, stats=sol.stats._replace(residual_norm=None), nodal_stats=sol.nodal_stats._replace(residual_norm=None)
    )
    assert_trees_close(strip(out), strip(ref))
    # and the physics holds: Casimir at round-off
    C = np.sum(np.asarray(out.momentum) ** 2, axis=-1)
    assert np.max(np.abs(C - C[:, :1])) < 50 * EPS * np.max(C)


@pytest.mark.slow  # the heavy top's march under vmap, cj.batch and alone; the rigid body's test runs by default
def test_heavy_top_march_is_bit_identical_to_vmap_and_alone():
    """The heavy top forms Q¹ in every residual (its potential is evaluated at Q¹) with the so(3)
    update of `reduction._cayley_update`, written so that XLA's FMA contraction is the same in
    every layout: cj.batch, jax.vmap and a member run alone give the same bits (with the
    refined 3×3 solve they did not: Q differed in its last bit)."""
    rng = np.random.default_rng(5)
    Q0 = jnp.asarray(np.stack([np.asarray(cj.lie.so3_exp(jnp.asarray(v))) for v in rng.normal(size=(6, 3))]))
    omegas = jnp.asarray(rng.normal(size=(6, 3)))
    top = models.heavy_top(np.array([1.0, 1.2, 0.5]), 1.7, (0.0, 0.6, 0.8))

    def run(q, x):
        return cj.integrate(top, q, x, dt=np.float64(0.02), n_steps=150, throw=False, backend="xla")

    ref = jax.jit(jax.vmap(run))(Q0, omegas)
    out = jax.jit(cj.batch(run, chunk=4))(Q0, omegas)
    alone = run(Q0[0], omegas[0])
    assert int(alone.result) == cj.Status.SUCCESS
    for name in ("Q", "xi", "xi_step", "momentum"):
        np.testing.assert_array_equal(np.asarray(getattr(out, name)), np.asarray(getattr(ref, name)), err_msg=name)
        np.testing.assert_array_equal(np.asarray(getattr(alone, name)), np.asarray(getattr(ref, name))[0], err_msg=name)
    np.testing.assert_array_equal(np.asarray(out.stats.iterations), np.asarray(ref.stats.iterations))


@pytest.mark.slow  # vortex programs under vmap and cj.batch
def test_point_vortex_batch_agrees_with_vmap():
    """The full march with block Newton (midpoint principle) over 6 clusters of 4 vortices:
    reductions over vortex pairs may round differently in the two layouts (see
    test_batch_position), so positions agree to round-off, not to the bit."""
    rng = np.random.default_rng(11)
    G = jnp.asarray(rng.uniform(0.5, 1.5, (6, 4)))
    Q0 = jnp.asarray(rng.normal(size=(6, 4, 2)))

    def run(g, q):
        return cj.integrate(
            models.point_vortices(g),
            q,
            models.vortex_velocity(g, q),
            dt=0.01,
            n_steps=20,
            jacobian="blocks",
            throw=False,
        )

    ref = jax.jit(jax.vmap(run))(G, Q0)
    out = jax.jit(cj.batch(run, chunk=4))(G, Q0)
    np.testing.assert_array_equal(np.asarray(out.result), np.asarray(ref.result))
    assert np.sum(np.asarray(out.valid)) > 0.8 * out.valid.size
    # round-off of the pair sums, propagated over 20 steps (failed members NaN in both)
    np.testing.assert_allclose(np.asarray(out.Q), np.asarray(ref.Q), rtol=0, atol=1e-13, equal_nan=True)


def test_failure_is_reported_per_member():
    """A member whose step fails (non-finite initial velocity) is reported as under vmap; the
    others are untouched."""
    system = models.rigid_body(jnp.array([2.0, 1.0, 2.0 / 3.0]))
    omegas = jnp.asarray(RNG.normal(size=(4, 3))).at[2, 0].set(jnp.nan)
    Q0 = jnp.broadcast_to(jnp.eye(3), (4, 3, 3))

    def run(q, x):
        return cj.integrate(system, q, x, dt=0.1, n_steps=10, throw=False)

    ref = jax.jit(jax.vmap(run))(Q0, omegas)  # jitted: op by op (one dispatch per operation) it is slow
    out = jax.jit(cj.batch(run))(Q0, omegas)
    np.testing.assert_array_equal(np.asarray(out.result), np.asarray(ref.result))
    np.testing.assert_array_equal(np.asarray(out.failed_step), np.asarray(ref.failed_step))
    assert np.asarray(out.result)[2] != cj.Status.SUCCESS
    assert np.all(np.asarray(out.result)[[0, 1, 3]] == cj.Status.SUCCESS)
    with pytest.raises(cj.IntegrationError, match="member 2"):
        out.raise_if_failed()


@pytest.mark.parametrize(
    "in_axes, args, match",
    [
        ((0, 1), (np.ones((3, 2)), np.ones((3, 2))), "expected 0 or None"),
        ((0,), (np.ones((3, 2)), np.ones((3, 2))), "one entry per argument"),
        (0, (np.ones((3, 2)), np.ones((4, 2))), "share one leading axis size"),
        (None, (np.ones((3, 2)),), "no batched argument"),
        (0, (np.float64(1.0),), "is a scalar"),
    ],
)
def test_bad_arguments_are_refused(in_axes, args, match):
    with pytest.raises(ValueError, match=match):
        cj.batch(lambda *a: a[0], in_axes=in_axes)(*args)


@pytest.mark.parametrize("chunk", [0, -3, 2.5, True])
def test_bad_chunk_is_refused(chunk):
    with pytest.raises(ValueError, match="chunk"):
        cj.batch(jnp.sin, chunk=chunk)


def test_rules_cover_the_reduced_march():
    """Every primitive of the reduced rigid-body march has a batch-last rule, except the few
    gathers of the statistics (which fall back on vmap): the hot loop never leaves the layout."""
    system = models.rigid_body(jnp.array([2.0, 1.0, 2.0 / 3.0]))
    jaxpr = jax.make_jaxpr(lambda q, x: cj.integrate(system, q, x, dt=0.1, n_steps=5, order=4, throw=False))(
        jnp.eye(3), jnp.ones(3)
    )
    import jax.extend.core as jex

    names = set()

    def walk(j):
        for e in j.eqns:
            names.add(e.primitive.name)
            for sub in jex.jaxprs_in_params(e.params):
                walk(sub)

    walk(jaxpr.jaxpr)
    missing = {n for n in names if n not in RULES and n not in CONTROL and n not in CALLS} - {"iota"}
    assert missing <= {"gather", "dynamic_slice"}, missing


@pytest.mark.slow  # the march's programs (the batch's and vmap's reference) compile for over 10 s
def test_an_integrate_call_inside_a_jit_of_the_function_is_not_checked_and_runs():
    """`integrate` inside a `jax.jit` of the batched function's own: its arguments are values of
    that inner trace, which the first-member check cannot evaluate (JAX kept the one made inside
    the jit, the identity matrix, as a constant of the outer program); the batch runs unchecked."""
    system = models.rigid_body(jnp.array([2.0, 1.0, 2.0 / 3.0]))
    run = jax.jit(lambda x: cj.integrate(system, jnp.eye(3), x, dt=0.1, n_steps=5, throw=False).momentum[-1])
    omegas = jnp.asarray(RNG.normal(size=(3, 3)))
    out = cj.batch(lambda x: run(x))(omegas)
    np.testing.assert_allclose(np.asarray(out), np.asarray(jax.vmap(run)(omegas)), rtol=0, atol=1e-13)
