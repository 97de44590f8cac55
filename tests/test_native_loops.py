"""The native translation's looped linear algebra (`clebsch_jax.native.loops`): factorisations,
solves and contractions of matrices past `LOOP_MIN_SIZE` run as loops over stack arrays and
give XLA's values to round-off, and the unrolled form's bit for bit."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import clebsch_jax as cj
from clebsch_jax.native import compile_member, loops

B = 6  # two blocks of lanes, the second padded
SMALL = 6  # the threshold the default tests set (small programs compile fast); slow ones use the real one


def _program(a, b):
    """LU with its pivots and permutation, a general solve (custom_linear_solve over lu and two
    triangular solves), a Cholesky factor and solves with it (lower, transposed upper, unit
    diagonal, right side), and a matrix product."""
    lu, piv, perm = jax.lax.linalg.lu(a)
    spd = a @ a.T + jnp.eye(a.shape[0])
    c = jnp.linalg.cholesky(spd)
    return (
        lu,
        piv,
        perm,
        jnp.linalg.solve(a, b),
        c,
        jsl.solve_triangular(c, b, lower=True),
        jsl.solve_triangular(c, b, lower=True, trans=1),
        jsl.solve_triangular(a, b, lower=False, unit_diagonal=True),
        jax.lax.linalg.triangular_solve(c, b.T, left_side=False, lower=True),
        a @ a,
    )


_KERNELS: dict = {}


def _kernel(n: int, looped_from: int):
    """`_program`'s kernel for n×n matrices, with loops from order `looped_from` (products: its cube)."""
    key = (n, looped_from)
    if key not in _KERNELS:
        a, b = np.eye(n), np.ones((n, 2))
        saved = loops.LOOP_MIN_SIZE, loops.DOT_LOOP_PRODUCTS
        loops.LOOP_MIN_SIZE, loops.DOT_LOOP_PRODUCTS = looped_from, looped_from**3
        try:
            _KERNELS[key] = compile_member(_program, a, b, use_cache=False)
        finally:
            loops.LOOP_MIN_SIZE, loops.DOT_LOOP_PRODUCTS = saved
    return _KERNELS[key]


def test_which_forms_loop_is_a_function_of_the_shapes():
    n = loops.LOOP_MIN_SIZE
    for size, want in ((n - 1, False), (n, True)):
        eqns = jax.make_jaxpr(_program)(np.eye(size), np.ones((size, 2))).jaxpr.eqns
        lus = [e for e in eqns if e.primitive.name in ("lu", "cholesky", "triangular_solve")]
        assert lus and all(loops.looped(e) == want for e in lus)
        assert all(loops.extra_entries(e) == 0 for e in lus) != want


_CASES = dict(
    side=st.sampled_from(["below", "at"]),
    seed=st.integers(0, 2**31 - 1),
    scale=st.floats(1e-3, 1e3),
    ties=st.booleans(),
)


@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(**_CASES)
def test_looped_and_unrolled_linear_algebra_agree_with_xla(side, seed, scale, ties):
    """Random matrices on both sides of a threshold (`SMALL`): see `_agrees`."""
    _agrees(SMALL, side, seed, scale, ties)


@pytest.mark.slow
@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(**_CASES)
def test_linear_algebra_on_both_sides_of_the_real_threshold_agrees_with_xla(side, seed, scale, ties):
    _agrees(loops.LOOP_MIN_SIZE, side, seed, scale, ties)


def _agrees(threshold, side, seed, scale, ties):
    """Random matrices on both sides of `threshold` (with ties of magnitude in a column, so
    that the first of equal pivots must win, and each lane its own pivots): XLA's values to
    round-off relative to the solution's size, the same pivots and permutations."""
    n = threshold - 1 if side == "below" else threshold
    rng = np.random.default_rng(seed)
    a = rng.standard_normal((B, n, n)) * scale
    if ties:  # the first column's entries of equal magnitude: the first row of them is the pivot
        a[:, :, 0] = scale * rng.choice([-1.0, 1.0], (B, n))
    b = rng.standard_normal((B, n, 2))
    native = _kernel(n, looped_from=threshold)(a, b)
    xla = jax.vmap(_program)(a, b)
    for k, (x, y) in enumerate(zip(native, xla)):
        x, y = np.asarray(x), np.asarray(y)
        if k in (1, 2):  # pivots and permutation
            np.testing.assert_array_equal(x, y)
            continue
        size = np.max(np.abs(y), axis=tuple(range(1, y.ndim)), keepdims=True)
        # XLA's to round-off times the condition number of the matrix (the Cholesky factor's
        # values carry its product a aᵀ + 1, summed in XLA's order, not ours)
        spd = a @ np.swapaxes(a, 1, 2) + np.eye(n)
        matrix = a if k in (3, 7) else spd if k in (4, 5, 6, 8) else None
        cond = 1.0 if matrix is None else np.linalg.cond(matrix)
        tol = np.maximum(1e-12, 1e-15 * np.reshape(cond, (-1,) + (1,) * (y.ndim - 1)))
        assert np.all(np.abs(x - y) <= tol * size), (k, np.max(np.abs(x - y) / size))


def test_the_looped_forms_are_the_unrolled_ones_bit_for_bit():
    n = SMALL
    rng = np.random.default_rng(1)
    a, b = rng.standard_normal((B, n, n)), rng.standard_normal((B, n, 2))
    looped, unrolled = _kernel(n, looped_from=SMALL)(a, b), _kernel(n, looped_from=10**6)(a, b)
    for x, y in zip(looped, unrolled):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_a_looped_lu_of_a_rectangular_matrix_is_the_unrolled_one_and_xlas():
    rng = np.random.default_rng(2)
    lu = lambda x: jax.lax.linalg.lu(x)
    saved = loops.LOOP_MIN_SIZE
    for shape in ((SMALL + 1, SMALL + 3), (SMALL + 3, SMALL + 1)):
        a = rng.standard_normal((B,) + shape)
        outs = []
        for looped_from in (SMALL, 10**6):
            loops.LOOP_MIN_SIZE = looped_from
            try:
                outs.append(compile_member(lu, a[0], use_cache=False)(a))
            finally:
                loops.LOOP_MIN_SIZE = saved
        xla = jax.vmap(lu)(a)
        for x, y, z in zip(*outs, xla):
            np.testing.assert_array_equal(x, y)
            np.testing.assert_allclose(x, np.asarray(z), rtol=0, atol=1e-13)


@pytest.mark.parametrize("n", [loops.LOOP_MIN_SIZE + 4])
def test_a_looped_factorisation_counts_fewer_lines_than_unrolled(n):
    """The point of the loops: the code of a large factorisation does not grow as n³."""
    from clebsch_jax.native.kernel import build_ir

    closed = jax.make_jaxpr(lambda a: jax.lax.linalg.lu(a)[0])(np.eye(n))
    looped = build_ir(closed, 4).count("\n")
    saved = loops.LOOP_MIN_SIZE
    loops.LOOP_MIN_SIZE = 10**6
    try:
        unrolled = build_ir(closed, 4).count("\n")
    finally:
        loops.LOOP_MIN_SIZE = saved
    assert looped < 0.6 * unrolled, (looped, unrolled)


# ---------------------------------------------------------------------------------------------
# Refusals for size, remembered on disk.


def _wide(x):
    """70 000 entries counted (a broadcast: entries, no code), three of them returned."""
    return jnp.broadcast_to(x, (70_000,))[:3] * 2.0


def test_a_refusal_for_size_is_recorded_and_a_new_process_does_not_trace_again(tmp_path, monkeypatch):
    """Past the entries of a kernel not asked for (a budget of IR lines: backend="auto") the
    program is refused and the refusal kept under its key; a fresh `NativeFunction` (as a new
    process makes it) with that key and those shapes refuses without tracing. Asked for
    (`max_lines=None`, backend="native"), the same program translates. Another key (another
    program) or other shapes do not hit the record."""
    from clebsch_jax.native import AUTO_MAX_IR_LINES, TooLarge

    monkeypatch.setenv("CLEBSCH_JAX_NATIVE_CACHE", str(tmp_path))
    traced = []

    def compile(x, key, **options):  # a new function each time: JAX keeps the traces of one
        def fun(x):
            traced.append(np.shape(x))
            return _wide(x)

        return compile_member(fun, x, key=key, **options)

    x = np.ones(B)
    with pytest.raises(TooLarge, match="more than 60000 entries"):
        compile(x[0], "wide", max_lines=AUTO_MAX_IR_LINES)
    assert traced == [()] and list(tmp_path.rglob("*.refused"))
    with pytest.raises(TooLarge, match="more than 60000 entries"):
        compile(x[0], "wide", max_lines=AUTO_MAX_IR_LINES)
    assert traced == [()]  # not traced again
    with pytest.raises(TooLarge):
        compile(x[0], "another program", max_lines=AUTO_MAX_IR_LINES)
    with pytest.raises(TooLarge):
        compile(np.float32(1.0), "wide", max_lines=AUTO_MAX_IR_LINES)
    assert traced == [(), (), ()]  # another key, another dtype: traced
    asked = compile(x[0], "wide")  # asked for: translated
    np.testing.assert_array_equal(asked(x), np.asarray(jax.vmap(_wide)(x)))


def test_a_traced_program_refused_for_its_size_is_not_translated_again(tmp_path, monkeypatch):
    """Without a key (cj.batch's kernels), the refusal is kept under the jaxpr's key: traced
    again, the program is not translated again."""
    from clebsch_jax.native import AUTO_MAX_IR_LINES, TooLarge, kernel

    monkeypatch.setenv("CLEBSCH_JAX_NATIVE_CACHE", str(tmp_path))
    with pytest.raises(TooLarge):
        compile_member(_wide, 1.0, max_lines=AUTO_MAX_IR_LINES)
    monkeypatch.setattr(kernel, "build_ir", lambda *a, **k: pytest.fail("translated"))
    with pytest.raises(TooLarge, match="more than 60000 entries"):
        compile_member(_wide, 1.0, max_lines=AUTO_MAX_IR_LINES)


def test_integrate_remembers_a_march_refused_for_its_size_on_disk(tmp_path, monkeypatch):
    """`integrate`'s native loop kernel refused for its size under "auto" is recorded under the
    fingerprint of the stepper and the system's structure: with the process's own caches
    cleared (as in a new process), the step is neither traced nor translated again, and XLA
    runs with the same warning."""
    from clebsch_jax.march import native_chunk
    from clebsch_jax.native import NativeFallbackWarning, kernel, values

    monkeypatch.setenv("CLEBSCH_JAX_NATIVE_CACHE", str(tmp_path))
    monkeypatch.setattr(values, "MAX_ENTRIES", 500)  # the rigid body's step is past it
    monkeypatch.setattr(native_chunk, "_LOOPS", {})
    monkeypatch.setattr("clebsch_jax.native._WARNED", set())
    system = cj.models.rigid_body(jnp.array([2.0, 1.0, 2 / 3]))
    run = lambda: cj.integrate(system, jnp.eye(3), jnp.array([0.4, -1.0, 0.7]), dt=0.1, n_steps=4)
    with pytest.warns(NativeFallbackWarning, match="more than 500 entries"):
        first = run()
    assert len(list(tmp_path.rglob("*.refused"))) == 2  # under the fingerprint and under the jaxpr
    monkeypatch.setattr(native_chunk, "_LOOPS", {})
    monkeypatch.setattr("clebsch_jax.native._WARNED", set())
    traced = []
    body = native_chunk._stream_body
    monkeypatch.setattr(native_chunk, "_stream_body", lambda *a: traced.append(1) or body(*a))
    monkeypatch.setattr(kernel, "build_ir", lambda *a, **k: pytest.fail("translated"))
    with pytest.warns(NativeFallbackWarning, match="more than 500 entries"):
        second = run()
    assert not traced
    np.testing.assert_array_equal(np.asarray(first.Q), np.asarray(second.Q))


@pytest.mark.slow  # compiles the clusters' kernel (LLVM, several seconds) and XLA's sweep
def test_a_native_sweep_of_clusters_of_ten_vortices_equals_the_xla_sweep():
    """Clusters of ten point vortices (the block Newton matrix per particle; their pairwise sums
    loops, `native.fused`; the loops' carries phis): within the lines of IR of a kernel not
    asked for, so "auto" compiles it (no fallback warning), and its values are XLA's to 1e-12
    relative and the same, bit for bit, as those of the kernel asked for."""
    import warnings

    from clebsch_jax.native import NativeFallbackWarning

    rng = np.random.default_rng(3)
    n, members = 10, 8
    G = rng.uniform(0.5, 1.5, (members, n)) * rng.choice([-1.0, 1.0], (members, n))
    Q0 = rng.normal(size=(members, n, 2)) * np.sqrt(n)
    xi0 = np.asarray(jax.vmap(cj.models.vortex_velocity)(jnp.asarray(G), jnp.asarray(Q0)))
    run = lambda backend: cj.sweep(cj.models.point_vortices, G, Q0, xi0, dt=0.01, n_steps=6, backend=backend)
    xla = run("xla")
    with warnings.catch_warnings(record=True) as caught:  # first: the kernel is not cached yet
        warnings.simplefilter("always")
        auto = run("auto")
    native = run("native")
    assert not [w for w in caught if issubclass(w.category, NativeFallbackWarning)]
    for a, b in ((auto.final_Q, native.final_Q), (auto.final_p, native.final_p)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_array_equal(native.status, xla.status)
    for a, b in ((native.final_Q, xla.final_Q), (native.final_p, xla.final_p)):
        a, b = np.asarray(a), np.asarray(b)
        scale = np.maximum(np.abs(b), np.max(np.abs(b)))
        assert np.nanmax(np.abs(a - b) / scale) < 1e-12
    # the energy error is a difference of energies of order one: round-off of them, absolutely
    assert np.nanmax(np.abs(np.asarray(native.energy_error) - np.asarray(xla.energy_error))) < 1e-12


def _many_carries(x):
    """A scan and a while loop (its iterations differ from member to member) whose carries
    are a (16, 16) array: `control.PHI_MIN_ENTRIES` entries that change."""
    y = jax.lax.fori_loop(0, 40, lambda i, y: 0.5 * jnp.sin(y) + 0.25 * y[::-1] + i, x)

    def halve(c):
        return 0.5 * c[0] + 1e-4 * jnp.cos(c[0]), c[1] + 1

    z, k = jax.lax.while_loop(lambda c: (jnp.max(jnp.abs(c[0])) > 1.0) & (c[1] < 60), halve, (x, 0))
    return y, z, k


def test_loops_with_many_carries_hold_them_as_phis_with_the_values_of_allocas(monkeypatch):
    """Loops whose changing carries have at least `PHI_MIN_ENTRIES` entries hold them as phis
    in their head, smaller ones in allocas: both forms give the same values bit for bit, and
    XLA's to 1e-12 relative."""
    from clebsch_jax.native import control
    from clebsch_jax.native.kernel import build_ir

    rng = np.random.default_rng(5)
    x = rng.uniform(-1.0, 1.0, (B, 16, 16)) * 10.0 ** rng.uniform(0.5, 4.0, (B, 1, 1))
    closed = jax.make_jaxpr(_many_carries)(x[0])
    phis = compile_member(_many_carries, x[0], use_cache=False)(x)
    assert build_ir(closed, 8).count(" = phi ") >= 2 * 256
    monkeypatch.setattr(control, "PHI_MIN_ENTRIES", 10**6)
    assert " = phi " not in build_ir(closed, 8)
    slots = compile_member(_many_carries, x[0], use_cache=False)(x)
    for a, b in zip(phis, slots):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    xla = jax.vmap(_many_carries)(x)
    assert len(set(np.asarray(xla[2]).tolist())) > 1  # the members' loops end apart (masked lanes)
    np.testing.assert_array_equal(np.asarray(phis[2]), np.asarray(xla[2]))
    for a, b in zip(phis[:2], xla[:2]):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=0)
