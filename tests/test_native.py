"""The native translation (`clebsch_jax.native`): jaxprs of one member compiled to SIMD kernels
with LLVM, checked against XLA's `jax.vmap` of the same function — random programs of the
covered primitives, masked loops whose lanes stop at different iterations, branches, shared
inputs, the disk cache, threads — and the sweep's native backend against its XLA backend on
healthy and failing members."""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import clebsch_jax as cj
from clebsch_jax.batching.backends import NativeFallbackWarning
from clebsch_jax.models import peakon_velocity, peakons
from clebsch_jax.native import Unsupported, compile_member
from clebsch_jax.roots.status import Status

from .test_epdiff import COLLISION, OVERTAKE, peakon_antipeakon_exact, two_peakons_exact

pytest.importorskip("llvmlite")

B = 21  # not a multiple of the lanes: the last block is padded


def _agree(native, xla, rtol=1e-13, atol=1e-13):
    for a, b in zip(jax.tree_util.tree_leaves(native), jax.tree_util.tree_leaves(xla)):
        a, b = np.asarray(a), np.asarray(b)
        assert a.shape == b.shape and a.dtype == b.dtype, (a.shape, b.shape, a.dtype, b.dtype)
        if a.dtype.kind == "f":
            np.testing.assert_allclose(a, b, rtol=rtol, atol=atol)
        else:
            np.testing.assert_array_equal(a, b)


# ---------------------------------------------------------------------------------------------
# Random programs of the covered primitives against XLA.

_UNARY = [
    jnp.sin,
    jnp.cos,
    jnp.tanh,
    jnp.abs,
    jnp.negative,
    jnp.square,
    lambda x: jnp.sqrt(jnp.abs(x)),
    lambda x: jnp.exp(-x * x),
    lambda x: jnp.log1p(jnp.abs(x)),
    jnp.arctan,
    lambda x: x**3,
    jnp.floor,
]
_BINARY = [
    jnp.add,
    jnp.subtract,
    jnp.multiply,
    jnp.maximum,
    jnp.minimum,
    lambda a, b: a / (1.0 + b * b),
    jnp.arctan2,
    lambda a, b: jnp.where(a > b, a, b - 1.0),
    lambda a, b: jnp.hypot(a, b),
]


def _structural(k, a, b):
    """Operations that re-index, contract or reduce, on (3,) vectors."""
    if k == 0:
        return jnp.outer(a, b) @ a  # dot_general
    if k == 1:
        return jnp.cumsum(a) - jnp.max(b)  # cumulative, reduction
    if k == 2:
        return jnp.concatenate([a[1:], b[:1]])[::-1]  # slices, concatenation, rev
    if k == 3:
        return jnp.linalg.solve(jnp.eye(3) * 3.0 + jnp.outer(a, a) * 0.1, b)  # LU with pivoting
    if k == 4:
        return jnp.roll(a, 1) * jnp.sum(b)  # gather/slices
    if k == 5:
        return jnp.full(3, jnp.argmax(a)).astype(a.dtype) + b  # argmax, conversion
    if k == 6:
        return jnp.cross(a, b)
    return jnp.where(jnp.all(jnp.isfinite(a)), a, 0.0) + jnp.linalg.norm(b)


def _program(ops):
    def f(x, y, s):
        pool = [x, y, x * s]
        for kind, i, j, k in ops:
            a, b = pool[i % len(pool)], pool[j % len(pool)]
            if kind == 0:
                out = _UNARY[k % len(_UNARY)](a)
            elif kind == 1:
                out = _BINARY[k % len(_BINARY)](a, b)
            elif kind == 2:
                out = _structural(k % 8, a, b)
            elif kind == 3:  # a loop whose trip count differs from lane to lane

                def cond(c):
                    return (c[1] < 30) & (jnp.max(jnp.abs(c[0] - jnp.cos(c[0]))) > 1e-13)

                out = jax.lax.while_loop(cond, lambda c: (jnp.cos(c[0]), c[1] + 1), (jnp.tanh(a), 0))[0]
            elif kind == 4:  # a branch taken per lane
                out = jax.lax.cond(jnp.sum(a) > jnp.sum(b), lambda u, v: u * v, lambda u, v: u - v, a, b)
            else:  # a counted loop
                out = jax.lax.fori_loop(0, 6, lambda n, c: 0.5 * c + jnp.sin(b) / (n + 1.0), a)
            pool.append(jnp.clip(out, -1e3, 1e3))
        return pool[-1], jnp.sum(pool[-1]) > 0, jnp.argmin(pool[-1])

    return f


_OPS = st.lists(
    st.tuples(st.integers(0, 5), st.integers(0, 9), st.integers(0, 9), st.integers(0, 20)), min_size=1, max_size=6
)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(ops=_OPS, seed=st.integers(0, 2**31 - 1))
def test_random_programs_agree_with_xla(ops, seed):
    """Every program of the covered primitives gives XLA's values to round-off (libm and XLA's
    own transcendental functions differ in the last bits; 1e-12 leaves room for their
    propagation through a few operations), the same booleans and indices, in each lane."""
    f = _program(ops)
    rng = np.random.default_rng(seed)
    x, y, s = rng.standard_normal((B, 3)), rng.standard_normal((B, 3)), rng.standard_normal(B)
    native = compile_member(f, x[0], y[0], s[0], use_cache=False)(x, y, s)
    xla = jax.vmap(f)(x, y, s)
    np.testing.assert_allclose(native[0], xla[0], rtol=1e-12, atol=1e-12)
    # a boolean or an index read off a value within round-off of a tie may differ: compare
    # only where the value is not at such a tie
    far = np.abs(np.asarray(jnp.sum(xla[0], axis=1))) > 1e-9
    np.testing.assert_array_equal(native[1][far], np.asarray(xla[1])[far])


def test_lanes_stop_their_loops_independently_and_inactive_lanes_keep_their_values():
    """A Newton iteration for x = cos(a x) per member: the members converge after different
    numbers of iterations; each keeps its own count and value, as under `jax.vmap`."""

    def newton(a):
        def cond(c):
            x, n = c
            return (n < 50) & (jnp.abs(x - jnp.cos(a * x)) > 1e-15)

        def body(c):
            x, n = c
            g = x - jnp.cos(a * x)
            return x - g / (1.0 + a * jnp.sin(a * x)), n + 1

        return jax.lax.while_loop(cond, body, (jnp.asarray(1.0), 0))

    a = np.linspace(0.1, 3.0, B)
    native = compile_member(newton, a[0], use_cache=False)(a)
    xla = jax.vmap(newton)(a)
    _agree(native, xla, rtol=0, atol=1e-15)
    assert len(set(np.asarray(native[1]).tolist())) > 2  # the lanes did stop at different counts


def test_a_vmapped_loop_inside_the_member_stops_each_element_on_its_own():
    """`jax.vmap` of a while loop inside the member's program (integrate's nodal solves over
    the nodes): its condition has an entry per element, the loop runs while any holds, and an
    element whose entry is false keeps its value, as XLA's loop does."""

    def count(a):
        def one(x):
            return jax.lax.while_loop(lambda c: (c[1] < 40) & (c[0] > 1e-3), lambda c: (0.5 * c[0], c[1] + 1), (x, 0))

        return jax.vmap(one)(a * jnp.asarray([1.0, 10.0, 1e3]))

    a = np.linspace(0.5, 4.0, B)
    native = compile_member(count, a[0], use_cache=False)(a)
    xla = jax.vmap(count)(a)
    _agree(native, xla, rtol=0, atol=0)
    assert len(set(np.asarray(native[1])[0].tolist())) == 3  # the elements stopped at different counts


@pytest.mark.slow  # a long scan's kernel; shorter scans stay in the default run
def test_a_long_scan_with_inputs_and_outputs_agrees_with_xla():
    """A scan too long to unroll, with per-iteration inputs and outputs (held in arrays on the
    stack, indexed by the counter), forwards and in reverse."""

    def f(x, y):
        xs = jnp.outer(jnp.linspace(0.0, 1.0, 700), y)
        c, ys = jax.lax.scan(lambda c, v: (jnp.tanh(0.5 * c + v), c * v[0]), x, xs)
        d, zs = jax.lax.scan(lambda c, v: (c * 0.9 + v, c), x, xs, reverse=True)
        return c, ys[::97], d, zs[-3:]

    rng = np.random.default_rng(5)
    x, y = rng.standard_normal((B, 3)), rng.standard_normal((B, 3))
    _agree(compile_member(f, x[0], y[0], use_cache=False)(x, y), jax.vmap(f)(x, y), rtol=1e-12, atol=1e-12)


def test_a_heap_buffer_that_cannot_be_allocated_raises_memory_error_naming_its_size(monkeypatch):
    """A kernel holding a scan's records as rows (`native.rows`) allocates one heap buffer per
    call; when that allocation fails, the kernel runs nothing and returns the buffer's size,
    and the call raises `MemoryError` naming it, with one thread or several. The failure is
    injected by asking malloc for 2**62 bytes (more than any address space: malloc returns
    NULL without touching memory); the same program's kernel as built runs and agrees with XLA."""
    import re

    from clebsch_jax.native import kernel, rows

    def f(x):
        c, ys = jax.lax.scan(lambda c, v: (0.5 * c + v, c * v), x, jnp.linspace(0.0, 1.0, rows.ROWS_MIN))
        return c, ys[::7]

    x = np.random.default_rng(3).standard_normal(B)
    _agree(compile_member(f, x[0], use_cache=False)(x), jax.vmap(f)(x))
    build, huge = kernel.build_ir, 1 << 62

    def inflated(*args, **kwargs):
        text = build(*args, **kwargs)
        (size,) = re.findall(r'@"malloc"\(i64 (\d+)\)', text)  # the buffer, also the failed call's return
        return text.replace(f'@"malloc"(i64 {size})', f'@"malloc"(i64 {huge})').replace(
            f"ret i64 {size}", f"ret i64 {huge}"
        )

    monkeypatch.setattr(kernel, "build_ir", inflated)
    failing = compile_member(f, x[0], use_cache=False)
    for threads in (1, 2):
        with pytest.raises(MemoryError, match=f"could not allocate its heap buffer of {huge} bytes"):
            failing(x, threads=threads)


def test_shared_inputs_threads_and_the_disk_cache(tmp_path, monkeypatch):
    """An input shared by all members (in_axes None) is broadcast to the lanes; two threads
    give the table of one, bit for bit; a second compile of the same program comes from the
    disk cache and gives the same bits."""
    monkeypatch.setenv("CLEBSCH_JAX_NATIVE_CACHE", str(tmp_path))

    def f(x, M):
        return jnp.tanh(M @ x), jnp.sum(x * x)

    M = np.array([[1.0, 2.0, 0.5], [0.0, -1.0, 3.0], [0.2, 0.1, 0.3]])
    x = np.random.default_rng(0).standard_normal((1000, 3))
    first = compile_member(f, x[0], M, in_axes=(0, None))
    assert not first.kernel.from_cache
    again = compile_member(f, x[0], M, in_axes=(0, None))
    assert again.kernel.from_cache and any(tmp_path.rglob("*.o"))
    one, two, cached = first(x, M), first(x, M, threads=2), again(x, M)
    for a, b, c in zip(one, two, cached):
        assert np.array_equal(a, b) and np.array_equal(a, c)
    _agree(one, jax.vmap(f, in_axes=(0, None))(x, M))


def test_a_workspace_reuses_rows_and_reads_the_last_calls_outputs_in_place():
    """With a `Workspace` a kernel's calls reuse rows, and an input that is an output of the
    last call (a view of its rows) is passed in place, without a copy: a loop of calls feeding
    each call's outputs to the next, and a batch that is not a whole number of blocks (its
    padding lanes), give the bits of the calls without a workspace; a call's outputs stay
    valid through the next call."""
    from clebsch_jax.native.layout import Workspace

    def f(x, y):
        return jnp.tanh(x) + 0.5 * y, x * y

    x, y = np.random.default_rng(2).standard_normal((2, 1001, 3))
    g = compile_member(f, x[0], y[0], use_cache=False)
    ws, taken = Workspace(), []
    rows = ws.rows
    ws.rows = lambda key, shape, dtype: taken.append(key[0]) or rows(key, shape, dtype)
    plain, reused = (x, y), (x, y)
    for k in range(4):
        before, plain_before = reused, plain
        plain, reused = g(*plain), g(*reused, workspace=ws)
        for a, b in zip(plain, reused):
            assert np.array_equal(a, b)
        # the first call copies x and y into input rows, the others read the last outputs in place
        assert taken == (["in", "in"] if k == 0 else []) + ["out", "out"]
        taken.clear()
    for a, b in zip(before, plain_before):  # the outputs of the call before the last one, still valid
        assert np.array_equal(a, b)


def test_a_workspace_writes_a_repeated_member_again_only_when_it_changed():
    """An input that repeats one member (a broadcast view, as a sweep's zeros and shared Q0) is
    not copied again into rows that hold it already: calls with a workspace on a sequence of
    broadcast members — the same one again, another value, 0.0 after -0.0, another batch size,
    an array that is not a broadcast, then the first member again — give the bits of the same
    calls without a workspace (1/x tells -0.0 from 0.0)."""
    from clebsch_jax.native.layout import Workspace

    def f(x, y):
        return 1.0 / x + y, x * y

    y = np.random.default_rng(3).standard_normal((1001, 3))
    u, v = np.array([0.5, -2.0, 3.0]), np.array([0.5, -2.0, 3.5])
    g = compile_member(f, u, y[0], use_cache=False)
    ws = Workspace()
    wide = lambda m, n=1001: np.broadcast_to(m, (n, 3))  # noqa: E731
    calls = [wide(u), wide(u), wide(v), wide(-0.0 * u), wide(0.0 * u), wide(u, 999), y + 1.0, wide(u)]
    for x in calls:
        n = len(x)
        plain, reused = g(x, y[:n]), g(x, y[:n], workspace=ws)
        for a, b in zip(plain, reused):
            assert np.array_equal(a, b, equal_nan=True)
            assert np.array_equal(np.signbit(a), np.signbit(b))


def test_indexing_by_values_agrees_with_xla():
    """Indices known while translating and indices that differ from lane to lane, in range and
    out of it (clamped or filled as XLA does), by selects (few places) and by lane loads
    (many places): slices, updates, gathers and scatters."""
    big = np.arange(120.0).reshape(12, 10)

    def f(x, i, j, M):
        return (
            x[i % 3],
            jnp.take(M, jnp.array([2, 0, 1]), axis=0),
            M[i % 3, j % 3],
            x.at[j % 3].set(7.0),
            x.at[jnp.array([0, 2])].add(jnp.array([1.0, 2.0])),
            jax.lax.dynamic_slice(M, (i, j), (2, 2)),
            jax.lax.dynamic_update_slice(M, x[:2, None] * jnp.ones((2, 2)), (j, i)),
            jax.lax.dynamic_slice(big * x[0], (3 * i, j), (3, 2)),
            jax.lax.dynamic_update_slice(big, M, (4 * j, i)) * x[1],
            jnp.take(big[0] * x[2], i + 6, mode="fill", fill_value=-1.0),
            jnp.take_along_axis(M, jnp.argmax(M, axis=0, keepdims=True), axis=0),
        )

    rng = np.random.default_rng(4)
    x, M = rng.standard_normal((B, 3)), rng.standard_normal((B, 3, 3))
    i, j = rng.integers(-4, 6, B).astype(np.int32), rng.integers(-2, 5, B).astype(np.int32)
    native = compile_member(f, x[0], i[0], j[0], M[0], use_cache=False)(x, i, j, M)
    _agree(native, jax.vmap(f)(x, i, j, M), rtol=0, atol=0)


def test_lane_gathers_read_one_stored_copy_per_block_and_agree_with_xla():
    """Indices reaching more places than `SELECT_STARTS` are lane gathers from one stored copy
    of the operand (the row swap and pivot rows of an LU step at run-time rows): XLA's values
    bit for bit, clamped as XLA clamps, floats and integers; three slices of one matrix in one
    block store it once."""
    from clebsch_jax.native.indexing import SELECT_STARTS
    from clebsch_jax.native.kernel import build_ir

    n = 16
    assert n > SELECT_STARTS

    def step(M, perm, p, k):
        swap = jnp.where(jnp.arange(n) == k, p, jnp.where(jnp.arange(n) == p, k, jnp.arange(n)))
        return M[swap], perm[swap], M[p], M[:, k], M[(p + 1) % n, k]

    rng = np.random.default_rng(9)
    M = rng.standard_normal((B, n, n))
    perm = np.stack([rng.permutation(n) for _ in range(B)]).astype(np.int32)
    p, k = rng.integers(-2, n + 2, B).astype(np.int32), rng.integers(0, n, B).astype(np.int32)
    native = compile_member(step, M[0], perm[0], p[0], k[0], use_cache=False)(M, perm, p, k)
    _agree(native, jax.vmap(step)(M, perm, p, k), rtol=0, atol=0)

    lines = lambda f: build_ir(jax.make_jaxpr(f)(M[0], p[0]), 4).count("\n")
    one = lines(lambda M, p: M[p])
    three = lines(lambda M, p: (M[p], M[:, p], M[(p + 1) % n]))
    assert "llvm.masked.gather" in build_ir(jax.make_jaxpr(lambda M, p: M[p])(M[0], p[0]), 4)
    # each more copy would store n² entries (a few lines each); loads from the first copy cost
    # lines per entry read, n of them per slice
    assert three - one < 2 * n * n


def test_a_loops_invariant_operand_is_stored_once_before_the_loop_and_agrees_with_xla():
    """Rows of a matrix computed before a `while` loop, read in its body at run-time rows that
    differ from lane to lane, for a number of iterations that differs too (a triangular solve's
    rows against its fixed matrix): the matrix is stored for the lanes' gathers before the loop,
    not in every iteration, and the values are XLA's bit for bit."""
    from clebsch_jax.native.kernel import build_ir

    n = 12

    def f(M, x, start, count):
        A = M * 2.0  # computed before the loop

        def body(c):
            i, y = c
            return i + 1, y * 0.5 + A[(start + 5 * i) % n]

        return jax.lax.while_loop(lambda c: c[0] < count, body, (jnp.int32(0), x))[1]

    rng = np.random.default_rng(8)
    M, x = rng.standard_normal((B, n, n)), rng.standard_normal((B, n))
    start, count = rng.integers(0, n, B).astype(np.int32), rng.integers(0, 9, B).astype(np.int32)
    native = compile_member(f, M[0], x[0], start[0], count[0], use_cache=False)(M, x, start, count)
    _agree(native, jax.vmap(f)(M, x, start, count), rtol=0, atol=0)
    text = build_ir(jax.make_jaxpr(f)(M[0], x[0], start[0], count[0]), 4)
    before, loop = text.split("while.head:", 1)
    assert before.count(" store ") >= n * n and loop.count(" store ") < n * n  # the carries: a few


def test_a_power_with_an_integer_exponent_agrees_with_xla():
    """`x ** n` with a float base and an integer exponent that differs from lane to lane (JAX's
    `pow` with operands of two types): the exponent is converted to the base's type and the
    power taken, as XLA does, instead of crashing the translation."""

    def f(x, n):
        return x**n, 2.0**n, (-x) ** (n + 1)

    rng = np.random.default_rng(6)
    x, n = rng.uniform(0.5, 2.0, B), rng.integers(-3, 4, B).astype(np.int32)
    native = compile_member(f, x[0], n[0], use_cache=False)(x, n)
    _agree(native, jax.vmap(f)(x, n), rtol=1e-15, atol=0)  # libm's pow against XLA's: the last bit


def test_a_primitive_without_a_rule_is_named():
    with pytest.raises(Unsupported, match="sort"):
        compile_member(lambda x: jnp.sort(x), np.zeros(3), use_cache=False)


# ---------------------------------------------------------------------------------------------
# The sweep's native backend against its XLA backend.

RB = dict(dt=0.05, n_steps=60, chunk_steps=20)


def _rigid_body_members(n=6):
    rng = np.random.default_rng(7)
    inertias = rng.uniform(0.5, 3.0, size=(n, 3))
    omegas = rng.standard_normal((n, 3))
    return inertias, np.broadcast_to(np.eye(3), (n, 3, 3)), omegas


def _compare(native, xla, atol=1e-12):
    np.testing.assert_array_equal(native.status, xla.status)
    np.testing.assert_array_equal(native.failed_step, xla.failed_step)
    for key in ("final_Q", "final_p", "final_xi", "final_momentum", "energy_error", "final_t"):
        a, b = getattr(native, key), getattr(xla, key)
        if a is None:
            assert b is None
            continue
        # a chunked run's round-off: the nodal solves start from other seeds (measured 1e-14)
        np.testing.assert_allclose(a, b, rtol=0, atol=atol, err_msg=key)
    assert (native.form, native.scheme, native.order, native.method) == (xla.form, xla.scheme, xla.order, xla.method)


def test_native_sweep_of_rigid_bodies_equals_the_xla_sweep_with_failures_reported():
    """Healthy members, a NaN initial velocity (INVALID_INPUT at step 0) and a negative inertia
    (an invalid parameter row): the same statuses, steps and finals on both backends; the
    native table is the same bit for bit from run to run."""
    inertias, Q0, omegas = _rigid_body_members()
    omegas = omegas.copy()
    omegas[2, 0] = np.nan
    inertias = inertias.copy()
    inertias[4, 1] = -1.0
    Q0 = Q0.copy()  # writable, like every input here: the sweep must write none of them
    given = [a.copy() for a in (inertias, Q0, omegas)]
    native = cj.sweep(cj.models.rigid_body, inertias, Q0, omegas, backend="native", **RB)
    xla = cj.sweep(cj.models.rigid_body, inertias, Q0, omegas, backend="xla", **RB)
    _compare(native, xla)
    assert list(native.failed_members) == [2, 4]
    assert np.all(native.status[[2, 4]] == Status.INVALID_INPUT)
    assert np.all(np.isnan(native.final_momentum[[2, 4]])) and np.all(np.isfinite(native.final_momentum[[0, 1, 3, 5]]))
    again = cj.sweep(cj.models.rigid_body, inertias, Q0, omegas, backend="native", **RB)
    for a, b in zip(jax.tree_util.tree_leaves(native), jax.tree_util.tree_leaves(again)):
        assert np.array_equal(a, b, equal_nan=True)
    # batches of 3 from two threads, each marching its batch through the chunks on its own;
    # batches of 1 and 4 taken one after the other by two and three threads (each thread's rows
    # reused from batch to batch); batches of 2 in groups, reporting progress after each chunk
    sweep = lambda **kw: cj.sweep(cj.models.rigid_body, inertias, Q0, omegas, backend="native", **RB, **kw)  # noqa: E731
    tables = [sweep(batch_size=3, threads=1), sweep(batch_size=3, threads=2), sweep(batch_size=1, threads=2)]
    tables += [sweep(batch_size=4, threads=3), sweep(batch_size=2, threads=2, progress=lambda info: None)]
    for other in tables:
        for a, b in zip(jax.tree_util.tree_leaves(native), jax.tree_util.tree_leaves(other)):
            assert np.array_equal(a, b, equal_nan=True)
    # a native batch of consecutive members reads their inputs as views (`start_batch`)
    for before, after in zip(given, (inertias, Q0, omegas)):
        assert np.array_equal(before, after, equal_nan=True)


def test_kept_kernel_rows_give_the_fresh_rows_table_and_large_ones_are_let_go(monkeypatch):
    """The sweep's threads keep their kernel rows from sweep to sweep (`schedule.workers`,
    `WORKSPACE_KEEP_BYTES`): a sweep whose rows hold another sweep's values (other members, a
    batch of another size) gives, to the bit, the table of threads with fresh rows; rows past
    the limit are let go when the sweep ends."""
    import threading

    from clebsch_jax.batching import schedule

    inertias, Q0, omegas = _rigid_body_members(9)
    sweep = (
        lambda n, **kw: cj.sweep(  # noqa: E731
            cj.models.rigid_body, inertias[:n], Q0[:n], omegas[:n] * 0.5, backend="native", threads=2, **RB, **kw
        )
    )
    cj.sweep(cj.models.rigid_body, inertias, Q0, omegas, backend="native", threads=2, **RB)
    assert schedule._workspace()._rows  # the calling thread's rows, kept
    kept = sweep(7, batch_size=3)
    monkeypatch.setattr(schedule, "_ROWS", threading.local())
    monkeypatch.setattr(schedule, "_WORKERS", [])
    fresh = sweep(7, batch_size=3)
    for a, b in zip(jax.tree_util.tree_leaves(kept), jax.tree_util.tree_leaves(fresh)):
        assert np.array_equal(a, b, equal_nan=True)
    monkeypatch.setattr(schedule, "WORKSPACE_KEEP_BYTES", 0)
    sweep(7)
    assert not schedule._workspace()._rows


def test_a_native_batch_that_raises_stops_the_threads_and_its_error_is_raised(monkeypatch):
    """A batch's error (here the table's writing of the second batch done) is raised by the
    sweep once the threads stopped; no thread takes a batch after it (at most the one batch
    another thread had started runs on)."""
    from clebsch_jax.batching import tables

    done, collect = [], tables.collect

    def collect_or_fail(table, one, run):
        done.append(one.rows.start)
        if len(done) == 2:
            raise RuntimeError("the second batch failed")
        return collect(table, one, run)

    monkeypatch.setattr(tables, "collect", collect_or_fail)
    inertias, Q0, omegas = _rigid_body_members(8)
    with pytest.raises(RuntimeError, match="the second batch failed"):
        cj.sweep(cj.models.rigid_body, inertias, Q0, omegas, backend="native", batch_size=1, threads=2, **RB)
    assert len(done) <= 3


@pytest.mark.slow  # two sweep programs compiled; the default run checks native statuses in test_sweep_checks
def test_native_sweep_reports_a_failure_in_a_later_chunk_at_the_step_xla_reports():
    """Peakons (the full march, midpoint scheme): a peakon–antipeakon pair collides at t* = 3,
    where the step fails in the third chunk; an overtaking pair runs through; a NaN member
    fails at step 0. Statuses, the run's failing steps and the finals equal the XLA backend's."""
    qc, pc = peakon_antipeakon_exact(0.0, **COLLISION)
    qo, po = two_peakons_exact(0.0, **OVERTAKE)
    q0s, p0s = np.array([qc, qo, [np.nan, 1.0]]), np.array([pc, po, [1.0, 1.0]])
    xi0s = np.asarray(jax.vmap(peakon_velocity)(q0s, p0s))
    kw = dict(dt=0.05, n_steps=80, chunk_steps=20, scheme="midpoint")
    native = cj.sweep(peakons, np.ones(3), q0s, xi0s, backend="native", **kw)
    xla = cj.sweep(peakons, np.ones(3), q0s, xi0s, backend="xla", **kw)
    _compare(native, xla, atol=1e-11)  # round-off of 80 steps near a collision, both ways
    assert list(native.failed_members) == [0, 2] and native.failed_step[0] >= 40
    assert native.status[2] == Status.INVALID_INPUT


@pytest.mark.slow  # the heavy top's full-march kernel and XLA's sweep, both compiled
def test_native_sweep_of_heavy_tops_equals_the_xla_sweep():
    """A potential (the heavy top: the reduced march with Q reconstructed, composed as a
    symmetric pair) on both backends."""
    n = 4
    rng = np.random.default_rng(2)
    Q0 = np.stack([np.asarray(cj.lie.so3_exp(jnp.asarray(v))) for v in 0.5 * rng.standard_normal((n, 3))])
    omegas = np.array([0.1, 0.2, 5.0]) + 0.3 * rng.standard_normal((n, 3))

    def make(m):
        return cj.models.heavy_top(jnp.array([1.0, 1.0, 0.4]), m)

    masses = np.array([1.5, 1.0, 2.0, 0.5])
    kw = dict(dt=0.01, n_steps=40, chunk_steps=20)
    native = cj.sweep(make, masses, Q0, omegas, backend="native", **kw)
    xla = cj.sweep(make, masses, Q0, omegas, backend="xla", **kw)
    _compare(native, xla)
    assert np.all(native.succeeded)


def test_backend_choice_and_fallback():
    """ "auto" runs native where it applies and says once why not elsewhere (here: saved
    nodes); "native" where it cannot apply is refused with the reason; a bad name is refused."""
    inertias, Q0, omegas = _rigid_body_members(3)
    with pytest.raises(ValueError, match="save_every"):
        cj.sweep(cj.models.rigid_body, inertias, Q0, omegas, backend="native", save_every=10, **RB)
    with pytest.raises(ValueError, match="backend"):
        cj.sweep(cj.models.rigid_body, inertias, Q0, omegas, backend="llvm", **RB)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = cj.sweep(cj.models.rigid_body, inertias, Q0, omegas, save_every=10, **RB)
    assert res.saved is not None
    assert not any(issubclass(w.category, NativeFallbackWarning) for w in caught) or any(
        "save_every" in str(w.message) for w in caught
    )
    with pytest.warns(DeprecationWarning, match="fast="):
        cj.sweep(cj.models.rigid_body, inertias, Q0, omegas, fast=False, **RB)


def test_without_llvmlite_the_sweep_runs_xla_and_says_so_once(monkeypatch):
    """Where llvmlite cannot be imported, "auto" runs XLA and warns once, naming the reason;
    "native" is refused with it."""
    from clebsch_jax import native

    monkeypatch.setattr(native, "available", lambda: False)
    monkeypatch.setattr(native, "_WARNED", set())
    inertias, Q0, omegas = _rigid_body_members(3)
    with pytest.warns(NativeFallbackWarning, match="llvmlite"):
        res = cj.sweep(cj.models.rigid_body, inertias, Q0, omegas, **RB)
    assert np.all(res.succeeded)
    with warnings.catch_warnings():
        warnings.simplefilter("error", NativeFallbackWarning)  # said once
        cj.sweep(cj.models.rigid_body, inertias, Q0, omegas, **RB)
    with pytest.raises(ValueError, match="llvmlite"):
        cj.sweep(cj.models.rigid_body, inertias, Q0, omegas, backend="native", **RB)


def test_auto_leaves_a_kernel_past_its_size_budget_to_xla_and_native_compiles_it(tmp_path, monkeypatch):
    """ "auto" does not ask LLVM for a kernel of more IR lines than `AUTO_MAX_IR_LINES` (here
    made small, with an empty disk cache): it runs XLA and says why; "native" compiles it, and
    the two tables agree."""
    import clebsch_jax.batching.backends as backends
    import clebsch_jax.batching.choose as choose
    from clebsch_jax import native

    monkeypatch.setenv("CLEBSCH_JAX_NATIVE_CACHE", str(tmp_path))
    monkeypatch.setattr(choose, "AUTO_MAX_IR_LINES", 100)
    monkeypatch.setattr(native, "_WARNED", set())
    monkeypatch.setattr(backends, "_PROGRAMS", {})  # no kernel kept from an earlier test
    inertias, Q0, omegas = _rigid_body_members(3)
    with pytest.warns(NativeFallbackWarning, match=r"a kernel of \d+ lines of LLVM IR, more than the 100"):
        auto = cj.sweep(cj.models.rigid_body, inertias, Q0, omegas, **RB)
    assert not list(tmp_path.rglob("*.o"))  # nothing compiled
    with warnings.catch_warnings():
        warnings.simplefilter("error", NativeFallbackWarning)
        native = cj.sweep(cj.models.rigid_body, inertias, Q0, omegas, backend="native", **RB)
    assert list(tmp_path.rglob("*.o"))
    _compare(native, auto)


# ---------------------------------------------------------------------------------------------
# Coverage: Gauss–Legendre stages and compositions, and what lets their programs fit a kernel.


def _diverging_rigid_bodies():
    """Rigid bodies (0.5, 1, 3) whose Gauss–Legendre sweeps at Δt = 0.05 contract (members 0,
    1, 3; 1 near the sweeps' limit), stop contracting at a later step (2: |ω| ≈ 21, step 9) or
    at step 0 (4), and a NaN initial velocity (5)."""
    rng = np.random.default_rng(7)
    base = rng.standard_normal((40, 3))
    omegas = base / np.linalg.norm(base, axis=1, keepdims=True) * np.linspace(16.0, 22.0, 40)[:, None]
    omegas = omegas[[0, 14, 35, 5, 8, 1]].copy()
    omegas[5, 1] = np.nan
    inertias = np.broadcast_to(np.array([0.5, 1.0, 3.0]), (6, 3))
    return inertias, np.broadcast_to(np.eye(3), (6, 3, 3)), omegas


@pytest.mark.slow  # Gauss–Legendre's kernel and XLA's sweep, both compiled
def test_native_gauss_legendre_sweep_equals_the_xla_sweep_with_its_failures():
    """Gauss–Legendre of order 6 (three stages, fixed-point sweeps; its first step's substeps
    and untested sweeps would pass the entry limit unrolled, so they run as loops): the same
    statuses — DIVERGED at step 0 and in a later chunk, INVALID_INPUT — failing steps and
    finals on both backends, and the native table bit for bit from run to run."""
    inertias, Q0, omegas = _diverging_rigid_bodies()
    kw = dict(dt=0.05, n_steps=60, chunk_steps=5, scheme="gauss", order=6)
    native = cj.sweep(cj.models.rigid_body, inertias, Q0, omegas, backend="native", **kw)
    xla = cj.sweep(cj.models.rigid_body, inertias, Q0, omegas, backend="xla", **kw)
    # loosened from 1e-12: member 1 runs to the edge of divergence (energy error 0.09, DIVERGED
    # at step >= 40), which amplifies the two backends' round-off (measured 1.0e-12 in its energy error)
    _compare(native, xla, atol=5e-12)
    assert native.method == "Gauss-Legendre 3-stage PRK"
    # integrate's own statuses (member 1 converges throughout: it failed here at step 40 only
    # while each chunk restarted the stage guesses, issue 40 item 11)
    assert list(native.failed_members) == [2, 4, 5]
    assert np.all(native.status[[2, 4]] == Status.DIVERGED) and native.status[5] == Status.INVALID_INPUT
    assert native.failed_step[4] == 0 and native.failed_step[2] == 9  # in the second chunk
    again = cj.sweep(cj.models.rigid_body, inertias, Q0, omegas, backend="native", **kw)
    for a, b in zip(jax.tree_util.tree_leaves(native), jax.tree_util.tree_leaves(again)):
        assert np.array_equal(a, b, equal_nan=True)


def _exponential_rigid_body(inertia):
    return cj.models.rigid_body(inertia, derivative_map=cj.exponential)


@pytest.mark.slow  # an order-8 composition's kernel and XLA's sweep, both compiled
def test_native_composition_sweep_equals_the_xla_sweep():
    """The triple jump (a composition of the reduced step of the exponential map, three stages;
    unrolled, its stages would pass the entry limit) with a negative inertia (INVALID_INPUT):
    the same table on both backends."""
    inertias, Q0, omegas = _rigid_body_members(5)
    inertias = inertias.copy()
    inertias[3, 0] = -1.0
    kw = dict(dt=0.05, n_steps=40, chunk_steps=20, composition="triple jump p4s3")
    native = cj.sweep(_exponential_rigid_body, inertias, Q0, omegas, backend="native", **kw)
    xla = cj.sweep(_exponential_rigid_body, inertias, Q0, omegas, backend="xla", **kw)
    _compare(native, xla)
    assert native.method == "triple jump p4s3 of left principle" and native.order == 4
    assert list(native.failed_members) == [3] and native.status[3] == Status.INVALID_INPUT


def test_a_scan_that_fits_only_as_a_loop_is_translated_as_one():
    """A short scan whose body counts many entries (a broadcast: no code, but entries): unrolled
    it would pass the entry limit, so `unroll_policy` keeps it a loop; the values are XLA's."""
    from clebsch_jax.native import control
    from clebsch_jax.native.values import MAX_ENTRIES

    def f(x):
        def body(c, _):
            wide = jnp.broadcast_to(c, (MAX_ENTRIES // 6, 3))
            return jnp.sin(c) * 0.5 + wide[7], jnp.sum(c)

        return jax.lax.scan(body, x, None, length=4)

    x = np.random.default_rng(3).standard_normal((B, 3))
    closed = jax.make_jaxpr(f)(x[0])
    assert control.entries(closed.jaxpr, control.POLICIES[0]) > MAX_ENTRIES
    assert control.unroll_policy(closed.jaxpr) != control.POLICIES[0]
    _agree(compile_member(f, x[0], use_cache=False)(x), jax.vmap(f)(x), rtol=1e-14, atol=1e-14)


def test_a_scatter_at_a_run_time_column_agrees_with_xla():
    """`M.at[:, k].set(v)` with k differing from lane to lane over more places than
    `SELECT_STARTS` (the column update of an LU factorisation run as a loop): one select per
    place and entry, XLA's values, an index out of range dropped as XLA drops it."""

    def f(M, v, k):
        return M.at[:, k].set(v), M.at[k].add(v[0])

    rng = np.random.default_rng(6)
    M, v = rng.standard_normal((B, 12, 12)), rng.standard_normal((B, 12))
    k = rng.integers(-2, 14, B).astype(np.int32)
    native = compile_member(f, M[0], v[0], k[0], use_cache=False)(M, v, k)
    _agree(native, jax.vmap(f)(M, v, k), rtol=0, atol=0)


@pytest.mark.slow  # XLA compiles the landmarks' sweep in about ten seconds; the default run covers
# the looped LU's lane gathers and run-time scatters with test_lane_gathers_read_one_stored_copy_per_block_and_agree_with_xla
# and test_a_scatter_at_a_run_time_column_agrees_with_xla
def test_landmarks_sweep_runs_natively_under_auto_and_equals_the_xla_sweep():
    """Three landmarks in the plane (the full march, 18 unknowns: its LU factorisations run as
    loops with row swaps by lane gathers and column updates at run-time indices): "auto"
    compiles the kernel (within `AUTO_MAX_IR_LINES`, no fallback), the same table bit for bit
    as `backend="native"`, and XLA's to 1e-12 relative with the same statuses."""
    from clebsch_jax.models import landmark_velocity

    rng = np.random.default_rng(1)
    q0 = rng.standard_normal((3, 3, 2))
    xi0 = np.asarray(jax.vmap(landmark_velocity)(q0, 0.3 * rng.standard_normal((3, 3, 2))))
    kw = dict(dt=0.02, n_steps=20, chunk_steps=10)
    with warnings.catch_warnings():
        warnings.simplefilter("error", NativeFallbackWarning)
        auto = cj.sweep(cj.models.landmarks, np.ones(3), q0, xi0, backend="auto", **kw)
    native = cj.sweep(cj.models.landmarks, np.ones(3), q0, xi0, backend="native", **kw)
    for key in ("final_Q", "final_p", "final_xi", "energy_error", "newton_iterations", "status"):
        assert np.asarray(getattr(auto, key)).tobytes() == np.asarray(getattr(native, key)).tobytes(), key
    xla = cj.sweep(cj.models.landmarks, np.ones(3), q0, xi0, backend="xla", **kw)
    _compare(auto, xla)
    for key in ("final_Q", "final_p", "final_xi"):
        a, b = np.asarray(getattr(auto, key)), np.asarray(getattr(xla, key))
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * np.max(np.abs(b)), err_msg=key)
    assert np.all(auto.succeeded)


def test_a_placement_inside_the_program_is_the_identity():
    """`device_put` (a placement, e.g. of a model's constant) changes no value."""

    def f(x):
        return jax.device_put(x) * 2.0, jax.device_put(jnp.arange(3.0))

    x = np.random.default_rng(2).standard_normal((B, 3))
    _agree(compile_member(f, x[0], use_cache=False)(x), jax.vmap(f)(x))
