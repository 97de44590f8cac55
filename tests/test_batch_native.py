r"""`cj.batch` on native kernels (issue "Native kernels": `cj.batch` runs the native kernel on
concrete calls wherever the compiler covers the program, XLA elsewhere, saying once why).

The reference is `backend="xla"`, the batch-last interpreter: an independent evaluator of the
same member program. The two must give the same `Solution` — every leaf: statuses, failed
steps, valid nodes and NaN after a failure exactly, values to 1e-12 relative to each leaf's
size — and the native one the same bits from run to run. Newton's residual norms are
round-off (about 1e-16 on these unit-sized states), compared to 1e-12 absolute.

Cost: a native kernel of the rigid body's march compiles in seconds; the other cases use
small functions, whose kernels compile at once. Each distinct function or shape compiles.
"""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import clebsch_jax as cj
from clebsch_jax import models, native
from clebsch_jax.batching import batch_last, batch_native, prune
from clebsch_jax.native import NativeFallbackWarning

from .helpers import assert_same_solution, solution_leaves

pytestmark = pytest.mark.skipif(not native.available(), reason="llvmlite cannot be imported")

BODY = models.rigid_body(jnp.array([2.0, 1.0, 2.0 / 3.0]))
N = 20
B = 5
XI0 = jnp.asarray(np.random.default_rng(11).normal(size=(B, 3))).at[2, 1].set(jnp.nan)  # member 2: NaN
DTS = jnp.asarray([0.05, 0.1, 0.05, -0.05, 0.2])  # member 3: dt <= 0
Q0 = jnp.stack([cj.lie.so3_exp(jnp.array([0.1 * k, 0.2, -0.1])) for k in range(B)])


def _march(Q0, xi0, dt):
    return cj.integrate(BODY, Q0, xi0, dt=dt, n_steps=N, throw=False)


def _no_fallback(call):
    with warnings.catch_warnings():
        warnings.simplefilter("error", NativeFallbackWarning)
        return call()


@pytest.fixture(scope="module")
def fast_runs():
    """Two native runs of the rigid bodies' marches, two members failing."""
    run = lambda: _no_fallback(lambda: cj.batch(_march, backend="native")(Q0, XI0, DTS))
    return run(), run()


def test_two_native_runs_are_bitwise_equal_and_conserve_the_casimir(fast_runs):
    first, again = fast_runs
    for (name, a), (_, b) in zip(solution_leaves(first), solution_leaves(again)):
        np.testing.assert_array_equal(a, b, err_msg=name)
    result = np.asarray(first.result)
    assert result[2] == cj.Status.INVALID_INPUT and result[3] == cj.Status.INVALID_INPUT  # NaN ξ⁰, dt <= 0
    assert np.all(result[[0, 1, 4]] == cj.Status.SUCCESS)
    np.testing.assert_array_equal(np.asarray(first.failed_step)[[2, 3]], [0, 0])
    C = np.sum(np.asarray(first.momentum)[[0, 1, 4]] ** 2, axis=-1)  # |μ|² of the rigid body
    assert np.max(np.abs(C - C[:, :1])) < 1e-13 * np.max(C)


@pytest.fixture(scope="module")
def xla_run():
    """The interpreter's run; integrate's calls inside run on batch's backend: no warning of
    their own that their march runs with XLA."""
    return _no_fallback(lambda: cj.batch(_march, backend="xla")(Q0, XI0, DTS))


@pytest.mark.slow  # the interpreter's program of the march compiles in XLA for over 10 s
def test_the_native_batch_equals_xla_on_every_leaf_of_the_solution(fast_runs, xla_run):
    fast, xla = fast_runs[0], xla_run
    assert (fast.form, fast.method, fast.order, fast.scheme) == (xla.form, xla.method, xla.order, xla.scheme)
    assert jax.tree_util.tree_structure(fast) == jax.tree_util.tree_structure(xla)
    assert_same_solution(fast, xla)
    # the failing members: the same statuses and steps
    np.testing.assert_array_equal(np.asarray(fast.result), np.asarray(xla.result))
    np.testing.assert_array_equal(np.asarray(fast.failed_step), np.asarray(xla.failed_step))


def test_a_second_call_traces_nothing_and_checks_new_values(monkeypatch):
    traces = []
    trace = batch_last._trace
    monkeypatch.setattr(batch_last, "_trace", lambda *a, **k: traces.append(1) or trace(*a, **k))
    march = cj.batch(_march, backend="native")
    march(Q0, XI0, DTS)
    march(Q0, 1.1 * XI0, DTS)  # new values: the kept trace
    assert len(traces) <= 1
    with pytest.raises(ValueError, match="member 0 is rejected by integrate's checks"):
        march(Q0.at[0].multiply(2.0), XI0, DTS)  # not a rotation: checked, not taken as seen


def _throwing(xi0, dt):
    return cj.integrate(BODY, jnp.eye(3), xi0, dt=dt, n_steps=4).Q[-1]


def _error(backend):
    with pytest.raises(cj.IntegrationError) as info:
        cj.batch(_throwing, backend=backend)(XI0, DTS)
    return info.value


def test_throw_raises_the_first_failed_members_error():
    """`integrate(throw=True)` in the batched function: its check is the kernel's output, and
    the error names the first failed member, its step and status."""
    err = _error("native")
    assert (err.member, err.step, err.status) == (2, 0, cj.Status.INVALID_INPUT)
    assert "batch member 2, step 0 of 4" in str(err) and "Status.INVALID_INPUT" in str(err)


@pytest.mark.slow  # the interpreter's program compiles in XLA for about 10 s
def test_throw_raises_what_the_interpreter_raises():
    fast, xla = _error("native"), _error("xla")
    assert (fast.member, fast.step, fast.status) == (xla.member, xla.step, xla.status)
    assert str(fast) == str(xla)


class _Scale:
    """A callable whose fingerprint cannot be read (a class of the tests): the kernel cache
    keys it by the object itself."""

    def __init__(self, k):
        self.k = k

    def __call__(self, x):
        return jnp.sin(x) * self.k


def test_a_second_call_compiles_nothing_and_functions_are_told_apart(monkeypatch):
    monkeypatch.setattr(batch_native, "_KERNELS", {})
    compiled = []
    real = native.compile_member
    monkeypatch.setattr(native, "compile_member", lambda *a, **k: compiled.append(1) or real(*a, **k))
    x = jnp.linspace(-1.0, 1.0, 12).reshape(4, 3)
    k = 2.0
    run = lambda f, x=x: np.asarray(_no_fallback(lambda: cj.batch(f)(x)))
    np.testing.assert_allclose(run(lambda v: jnp.sin(v) * k), np.sin(x) * 2.0, rtol=1e-15)
    np.testing.assert_allclose(run(lambda v: jnp.sin(v) * k), np.sin(x) * 2.0, rtol=1e-15)  # same fingerprint
    assert len(compiled) == 1
    np.testing.assert_allclose(run(lambda v: jnp.sin(v) * k, x[:2]), np.sin(x[:2]) * 2.0, rtol=1e-15)  # another B
    assert len(compiled) == 1
    k = 3.0  # the closure's value changed: another program
    np.testing.assert_allclose(run(lambda v: jnp.sin(v) * k), np.sin(x) * 3.0, rtol=1e-15)
    assert len(compiled) == 2
    # functions the fingerprint cannot read are kept by the cache: a new one never finds a
    # kernel of another that happened to have its id
    for k in (4.0, 5.0, 6.0):
        np.testing.assert_allclose(run(_Scale(k)), np.sin(x) * k, rtol=1e-15)
    assert len(compiled) == 5


def test_shared_arguments_and_pytrees():
    x = jnp.asarray(np.random.default_rng(3).normal(size=(7, 2)))
    fun = lambda d, c: {"a": d["u"] * c, "b": (jnp.sum(d["u"] ** 2), d["v"] + 1)}
    args = ({"u": x, "v": jnp.arange(7)}, jnp.asarray([2.0, -1.0]))
    out = _no_fallback(lambda: cj.batch(fun, in_axes=(0, None), backend="native")(*args))
    ref = jax.vmap(fun, in_axes=(0, None))(*args)
    assert jax.tree_util.tree_structure(out) == jax.tree_util.tree_structure(ref)
    for a, b in zip(jax.tree_util.tree_leaves(out), jax.tree_util.tree_leaves(ref)):
        assert a.dtype == b.dtype
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-15)


def _erf_inv(x):
    return jax.lax.erf_inv(0.3 * jnp.tanh(x))  # a primitive the translation does not cover


def _printing(x):
    jax.debug.print("{}", x[0])
    return 2.0 * x


@pytest.mark.parametrize("fun, reason", [(_erf_inv, "primitive 'erf_inv'"), (_printing, "host callbacks")])
def test_an_uncovered_function_runs_the_interpreter_and_says_why_once(monkeypatch, fun, reason):
    monkeypatch.setattr(native, "_WARNED", set())
    x = jnp.linspace(-1.0, 1.0, 6).reshape(3, 2)
    with pytest.warns(NativeFallbackWarning, match=f"cj.batch with XLA.*does not cover fun: {reason}"):
        auto = cj.batch(fun)(x)
    with warnings.catch_warnings():
        warnings.simplefilter("error", NativeFallbackWarning)  # said once
        again = cj.batch(fun)(x)
    xla = cj.batch(fun, backend="xla")(x)
    np.testing.assert_array_equal(np.asarray(auto), np.asarray(xla))
    np.testing.assert_array_equal(np.asarray(again), np.asarray(xla))
    with pytest.raises(ValueError, match=f"backend='native'.*{reason}"):
        cj.batch(fun, backend="native")(x)


def test_under_jit_the_interpreter_runs(monkeypatch):
    monkeypatch.setattr(native, "_WARNED", set())
    x = jnp.linspace(-1.0, 1.0, 6).reshape(3, 2)
    f = lambda v: jnp.tanh(v) * jnp.sum(v)
    with pytest.warns(NativeFallbackWarning, match="cj.batch with XLA.*traced"):
        inside = jax.jit(cj.batch(f))(x)
    np.testing.assert_allclose(np.asarray(inside), np.asarray(jax.vmap(f)(x)), rtol=1e-15)
    with warnings.catch_warnings():
        warnings.simplefilter("error", NativeFallbackWarning)  # said once; "xla" says nothing
        jax.jit(cj.batch(lambda v: f(v) + 1.0))(x)
        jax.jit(cj.batch(f, backend="xla"))(x)
    with pytest.raises(ValueError, match="backend='native'.*traced.*concrete calls only"):
        jax.jit(cj.batch(f, backend="native"))(x)


def test_without_llvmlite_the_interpreter_runs(monkeypatch):
    monkeypatch.setattr(native, "available", lambda: False)
    monkeypatch.setattr(native, "_WARNED", set())
    x = jnp.ones((2, 3))
    with pytest.warns(NativeFallbackWarning, match="llvmlite"):
        out = cj.batch(jnp.sin)(x)
    np.testing.assert_array_equal(np.asarray(out), np.asarray(cj.batch(jnp.sin, backend="xla")(x)))
    with pytest.raises(ValueError, match="backend='native'.*llvmlite"):
        cj.batch(jnp.sin, backend="native")(x)


@pytest.mark.parametrize("backend", ["gpu", None, "NATIVE"])
def test_a_bad_backend_is_refused_before_anything_is_traced(monkeypatch, backend):
    monkeypatch.setattr(native, "compile_member", lambda *a, **k: pytest.fail("compiled"))
    traced = []
    with pytest.raises(ValueError, match="backend: expected one of"):
        cj.batch(lambda x: traced.append(1) or x, backend=backend)
    assert not traced


def _partly_used(x):
    """A call whose second output, of 250 000 entries (past the translation's limit), is not used."""

    @jax.jit
    def both(v):
        grid = jnp.outer(jnp.tile(v, 100), jnp.tile(v, 100)) ** 2
        return jnp.sum(jax.nn.softplus(v)), jnp.tanh(grid)

    return both(x)[0] * 2.0


def test_the_kernel_is_compiled_without_what_the_outputs_do_not_need():
    x = jnp.asarray(np.random.default_rng(5).normal(size=(6, 5)))
    closed = jax.make_jaxpr(_partly_used)(x[0])
    kept = jax.make_jaxpr(prune.pruned(closed))(x[0])
    names = lambda j: {e.primitive.name for e in j.jaxpr.eqns}
    assert "tanh" not in names(kept) and "jit" not in names(kept)  # entered, the unused output dropped
    out = _no_fallback(lambda: cj.batch(_partly_used, backend="native")(x))  # within the limits
    np.testing.assert_allclose(np.asarray(out), np.asarray(jax.vmap(_partly_used)(x)), rtol=1e-14)


# Long marches: the records of the march's scan and what the Solution computes from them are
# held as rows in memory and computed in loops (`clebsch_jax.native.rows`): the kernel's size
# does not depend on n_steps.

N_LONG = 600
DTS_LONG = jnp.asarray([0.05, 0.03, 0.05, -0.05, 0.04])  # member 2: NaN ξ⁰, member 3: dt <= 0


def _long_march(Q0, xi0, dt):
    return cj.integrate(BODY, Q0, xi0, dt=dt, n_steps=N_LONG, throw=False)


def _kernel_lines(n_steps: int) -> int:
    """Lines of LLVM IR of cj.batch's kernel of the rigid body's march of `n_steps` steps (its
    member program as `batch_native` prunes it; emitted, not compiled)."""
    from clebsch_jax.march.integrate import caller_backend
    from clebsch_jax.native.kernel import build_ir

    def member(Q0, xi0):
        with caller_backend():
            return jax.tree_util.tree_leaves(cj.integrate(BODY, Q0, xi0, dt=0.05, n_steps=n_steps, throw=False))

    closed = jax.make_jaxpr(member)(Q0[0], XI0[0])
    return build_ir(jax.make_jaxpr(prune.pruned(closed))(Q0[0], XI0[0]), 4).count("\n")


def test_the_kernel_of_a_long_march_does_not_grow_with_its_steps():
    lines = _kernel_lines(100)
    assert _kernel_lines(2000) == lines
    assert lines < native.AUTO_MAX_IR_LINES


@pytest.fixture(scope="module")
def long_run():
    """A native run of 600 steps under "auto": no warning, no fallback."""
    return _no_fallback(lambda: cj.batch(_long_march)(Q0, XI0, DTS_LONG))


def test_a_long_march_runs_natively_under_auto(long_run):
    sol = long_run
    assert np.asarray(sol.Q).shape == (B, N_LONG + 1, 3, 3)
    result = np.asarray(sol.result)
    assert result[2] == cj.Status.INVALID_INPUT and result[3] == cj.Status.INVALID_INPUT
    assert np.all(result[[0, 1, 4]] == cj.Status.SUCCESS)
    np.testing.assert_array_equal(np.asarray(sol.ts)[0, [0, -1]], [0.0, 0.05 * N_LONG])
    C = np.sum(np.asarray(sol.momentum)[[0, 1, 4]] ** 2, axis=-1)  # |μ|² of the rigid body
    assert np.max(np.abs(C - C[:, :1])) < 1e-12 * np.max(C)


@pytest.mark.slow  # the interpreter's program of the march compiles in XLA for over 10 s
def test_a_long_native_march_equals_xla(long_run):
    xla = _no_fallback(lambda: cj.batch(_long_march, backend="xla")(Q0, XI0, DTS_LONG))
    assert_same_solution(long_run, xla)


def _rows_program(x, k, n=200):
    """A scan of n steps and what is computed from its records along their long axis: rows
    (elementwise, broadcasts, contractions, slices, concatenations, reductions over and along
    the axis, a row at a run-time index) in loops."""
    ys = jax.lax.scan(lambda c, _: (jnp.sin(c) + 0.1 * c[::-1], (c, jnp.sum(c * c))), x, None, length=n)[1]
    rows, sq = ys
    t = jnp.arange(n + 1.0)[:, None]
    shifted = jnp.concatenate([rows[:1], rows[1:] - rows[:-1], x[None]])  # (201, 3)
    sq1 = jnp.concatenate([sq, sq[-1:]])
    w = jnp.where(sq1[:, None] > 0.5, shifted * t, -shifted) @ jnp.array([1.0, -2.0, 0.5])
    first = jnp.argmax(sq > 1.0)
    return w, jnp.cumsum(rows, axis=1), jnp.max(sq), jnp.sum(w), rows[k], first, jnp.any(jnp.isnan(w))


def test_long_arrays_are_rows_in_loops_and_equal_vmap():
    x = jnp.asarray(np.random.default_rng(3).normal(size=(6, 3)))
    k = jnp.asarray([0, 5, 199, 250, -3, 17])  # out of range: clamped, as XLA does
    out = _no_fallback(lambda: cj.batch(_rows_program, backend="native")(x, k))
    ref = jax.vmap(_rows_program)(x, k)
    for a, b in zip(out, ref):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-13, atol=1e-13)
    from clebsch_jax.native.kernel import build_ir

    lines = lambda n: build_ir(jax.make_jaxpr(lambda a, b: _rows_program(a, b, n))(x[0], k[0]), 4).count("\n")
    assert lines(200) == lines(2000)  # no row written out
