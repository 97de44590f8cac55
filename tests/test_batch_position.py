r"""A member's trajectory does not depend on where it runs: alone, or at any position of a
`jax.vmap`ped batch of other members, or in any batch of `cj.sweep` (issue 8).

What is bit-identical and what is not (measured with jax 0.10 on CPU; the tests assert it):

- Inside one compiled batch, a member's result never depends on its position or on the other
  members: every operation of the march is per member (a batched `while_loop` freezes
  converged members with a select), so the tests assert equality to the bit.
- Alone vs batched: the **reduced march** (rigid body) is bit-identical: its arithmetic is
  written as elementwise multiply-adds (`_linalg.matmul`, `matvec`, closed-form 3×3 solves)
  that compile to the same scalar code per member. XLA contracts a product that feeds an
  addition into a fused multiply-add, and when both operands are products which one depends on
  the layout: the so(3) update of Q (`reduction._cayley_update`) is written without such sums. Its order-4 composition is bit-identical
  between a member traced alone (`jax.jit`) and batched; a plain call runs the chunked march,
  a `while_loop` that stops at n_steps, around the composition's scan over its stages, which
  XLA compiles into other code than the single scan of a traced march: last-bit differences
  (measured 7.8e-16 in Q over 200 steps), bounded like the full march's. The
  **full march** and the **point vortices** are not: their residuals contain reductions — the
  pairing ⟨P, ·⟩ of 3×3 matrices and `jnp.sum` over vortex pairs in the action, small matrix
  products in the Cayley map — which XLA compiles, for one trajectory, as vectorised
  (tree-ordered) sums over contiguous data and, in a batch, as member-by-member sums along
  another axis: a different summation order, so the last bit of a residual can differ
  (`test_the_cause_a_sum_alone_and_in_a_batch`). Newton then stops at a round-off-level root
  that differs by an ulp or two, and the difference propagates like any round-off: measured
  1.3e-14 over 200 rigid-body steps (full march) and 2.2e-15 over 200 vortex steps; the
  number of Newton updates can differ by a few in a thousand. Bounded below with margin.
- `cj.sweep`: batches of size ≥ 2 give identical tables whatever the split; a batch of one
  member compiles as an unbatched program (XLA drops the size-1 axis), so its chunk hand-over
  (a least-squares solve) rounds like a single trajectory: last-bit differences after the
  second hand-over (measured 7.8e-16 over 60 steps; slow test).

Compile time dominates: each family compiles one plain and one batched program (the slow tests
add the full march, the composition and the one-member sweep).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import clebsch_jax as cj
from clebsch_jax import models

B = 5
POSITIONS = (0, 2, 4)
N_STEPS = 200
EPS = np.finfo(float).eps
RNG = np.random.default_rng(8)
INERTIAS = np.concatenate([[[2.0, 1.0, 2.0 / 3.0]], RNG.uniform(0.5, 2.5, (B - 1, 3))])
OMEGAS = RNG.normal(size=(B, 3))
ROTATIONS = np.stack([np.asarray(cj.lie.so3_exp(jnp.asarray(v))) for v in RNG.normal(size=(B, 3))])
# vortices: member 0 is the leapfrogging pairs of test_vortices, the others random clusters
GAMMAS = np.concatenate([[[1.0, -1.0, 1.0, -1.0]], RNG.uniform(0.5, 1.5, (B - 1, 4))])
POSITIONS_Q = np.concatenate([[[[0.0, 1.0], [0.0, -1.0], [0.0, 0.5], [0.0, -0.5]]], RNG.normal(size=(B - 1, 4, 2))])


def placed(arrays, pos):
    """The batch with member 0 moved to position `pos` (the others keep their order)."""
    order = list(range(1, B))
    order.insert(pos, 0)
    return [a[order] for a in arrays]


def member(tree, pos):
    return jax.tree_util.tree_map(lambda x: np.asarray(x)[pos], tree)


def fields(sol):
    """The arrays of a Solution that a user reads (None fields dropped)."""
    names = ("Q", "p", "xi", "xi_step", "momentum", "ts", "valid")
    return {k: np.asarray(getattr(sol, k)) for k in names if getattr(sol, k) is not None}


def rigid_body(inertia, Q0, omega0, **kw):
    # backend="xla": the claim is about XLA's program alone and under vmap (a concrete call
    # would otherwise run the native kernel, which equals it to round-off, not bit for bit)
    return cj.integrate(
        cj.models.rigid_body(inertia),
        Q0,
        omega0,
        dt=np.float64(0.1),
        n_steps=N_STEPS,
        throw=False,
        backend="xla",
        **kw,
    )


def vortices(gamma, Q0):
    return cj.integrate(
        models.point_vortices(gamma),
        Q0,
        models.vortex_velocity(gamma, Q0),
        dt=np.float64(0.02),
        n_steps=N_STEPS,
        jacobian="blocks",
        throw=False,
        backend="xla",
    )


def alone_and_placed(run, arrays):
    """Member 0 run alone (a plain call) and at each of `POSITIONS` of one jit(vmap) batch."""
    alone = run(*(a[0] for a in arrays))
    batched = jax.jit(jax.vmap(run))
    at = {pos: member(batched(*placed(arrays, pos)), pos) for pos in POSITIONS}
    return alone, at


def assert_position_independent(at):
    """Inside a batch: bit-identical at every position, Newton statistics included."""
    first = at[POSITIONS[0]]
    for pos in POSITIONS[1:]:
        for k, v in fields(first).items():
            np.testing.assert_array_equal(fields(at[pos])[k], v, err_msg=f"{k} at position {pos}")
        np.testing.assert_array_equal(at[pos].stats.iterations, first.stats.iterations)


def test_reduced_rigid_body_is_bit_identical_alone_and_at_any_position():
    alone, at = alone_and_placed(rigid_body, [INERTIAS, ROTATIONS, OMEGAS])
    assert alone.form == "reduced" and int(alone.result) == cj.Status.SUCCESS
    assert_position_independent(at)
    for pos, sol in at.items():
        for k, v in fields(alone).items():
            np.testing.assert_array_equal(fields(sol)[k], v, err_msg=f"{k} at position {pos}")
        np.testing.assert_array_equal(sol.stats.iterations, alone.stats.iterations)


@pytest.mark.slow  # a block-Newton vortex batch of its own; the rigid bodies' position test runs by default
def test_vortices_with_blocks_differ_from_alone_only_by_bounded_round_off():
    alone, at = alone_and_placed(vortices, [GAMMAS, POSITIONS_Q])
    assert int(alone.result) == cj.Status.SUCCESS
    assert_position_independent(at)
    sol = at[0]
    # Alone vs batched: summation order (module docstring). Measured 2.2e-15 in Q over 200
    # steps; bound: 2 ulps of |Q| per step, far below the method's own error (~1e-6 here).
    scale = np.max(np.abs(alone.Q))
    assert np.max(np.abs(sol.Q - alone.Q)) <= 2 * N_STEPS * EPS * scale
    # both are the implicit midpoint rule solved to round-off: the impulses agree to round-off
    for impulse in (models.vortex_linear_impulse, models.vortex_angular_impulse):
        a, b = np.asarray(impulse(GAMMAS[0], alone.Q)), np.asarray(impulse(GAMMAS[0], sol.Q))
        assert np.max(np.abs(a - b)) < 1e-12
    # Newton may stop after a different number of updates (measured 1100 vs 1096 in all)
    total, total_alone = int(np.sum(sol.stats.iterations)), int(np.sum(alone.stats.iterations))
    assert abs(total - total_alone) <= 0.02 * total_alone


def test_the_cause_a_sum_alone_and_in_a_batch():
    """A 9-term pairing ⟨A, C⟩ (the shape of ⟨P, L_ξQ⟩ in the action) compiled for one pair
    and in a batch: the results may differ in the last bits (summation order; on this machine
    in most draws), never by more than the rounding bound of a 9-term sum, and within the batch
    they do not depend on the position."""
    rng = np.random.default_rng(0)
    A, C = rng.normal(size=(2, 64, 3, 3))
    pairing = lambda a, c: jnp.sum(a * c)
    alone = np.array([jax.jit(pairing)(a, c) for a, c in zip(A[:8], C[:8])])
    batched = np.asarray(jax.jit(jax.vmap(pairing))(A, C))
    bound = 9 * EPS * np.sum(np.abs(A[:8] * C[:8]), axis=(1, 2))
    assert np.all(np.abs(alone - batched[:8]) <= bound)
    flipped = np.asarray(jax.jit(jax.vmap(pairing))(A[::-1], C[::-1]))[::-1]
    np.testing.assert_array_equal(flipped, batched)


def _casimir(system, sol):
    return jnp.sum(sol.momentum**2, axis=-1)


SWEEP = dict(dt=0.1, n_steps=60, chunk_steps=20, save_every=10, invariants={"casimir": _casimir})


def _sweep(batch_size):
    return cj.sweep(cj.models.rigid_body, INERTIAS, ROTATIONS, OMEGAS, batch_size=batch_size, **SWEEP)


def _assert_same_table(a, b, atol=0.0):
    for name in ("final_momentum", "final_Q", "final_p", "final_xi", "energy_error"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=0, atol=atol, err_msg=name)
    np.testing.assert_allclose(a.saved["momentum"], b.saved["momentum"], rtol=0, atol=atol)
    np.testing.assert_allclose(a.drift["casimir"], b.drift["casimir"], rtol=0, atol=atol)
    np.testing.assert_array_equal(a.status, b.status)


def test_sweep_tables_do_not_depend_on_the_batch_split():
    """5 members in batches of 2 (the last one padded with a copy of member 4) and in one
    batch of 5: every member sits at another position, the tables are equal to the bit."""
    by2, by5 = _sweep(2), _sweep(5)
    assert by2.batch_size == 2 and by5.batch_size == 5
    assert np.all(by5.status == cj.Status.SUCCESS)
    _assert_same_table(by2, by5)
    np.testing.assert_array_equal(by2.newton_iterations, by5.newton_iterations)


# ------------------------------------------------------------------------------------------
# Slow: three more families, two programs each


@pytest.mark.slow
def test_full_rigid_body_differs_from_alone_only_by_bounded_round_off():
    alone, at = alone_and_placed(lambda i, q, w: rigid_body(i, q, w, reduce=False), [INERTIAS, ROTATIONS, OMEGAS])
    assert alone.form == "full" and int(alone.result) == cj.Status.SUCCESS
    assert_position_independent(at)
    sol = at[0]
    # Alone vs batched: summation order (module docstring). The first step already differs by
    # an ulp; measured 1.3e-14 in μ and 1.2e-14 in Q after 200 steps. Bound: 2 ulps per step.
    for k in ("Q", "p", "momentum", "xi"):
        scale = np.max(np.abs(getattr(alone, k)))
        assert np.max(np.abs(getattr(sol, k) - getattr(alone, k))) <= 2 * N_STEPS * EPS * scale, k
    # the invariants agree as well as each run keeps them (round-off)
    C_alone, C = (np.sum(np.asarray(s.momentum) ** 2, -1) for s in (alone, sol))
    assert np.max(np.abs(C - C_alone)) < 1e-13 * C_alone[0]


@pytest.mark.slow
def test_order_four_composition_alone_and_at_any_position():
    """The order-4 composition of the reduced step: one member traced alone (`jax.jit`, the
    single scan) is bit-identical to the same member at any position of the jit(vmap) batch.
    The plain call runs the chunked march, whose steps are a `while_loop` that stops at
    n_steps: XLA compiles the composition's stage scan inside it into different code than
    inside the single scan, so the last bits differ (module docstring): bounded like the full
    march, 2 ulps per step."""
    run = lambda i, q, w: rigid_body(i, q, w, order=4)
    alone, at = alone_and_placed(run, [INERTIAS, ROTATIONS, OMEGAS])
    assert alone.order == 4 and alone.form == "reduced" and int(alone.result) == cj.Status.SUCCESS
    assert_position_independent(at)
    traced = jax.jit(run)(INERTIAS[0], ROTATIONS[0], OMEGAS[0])
    for pos, sol in at.items():
        for k, v in fields(traced).items():
            np.testing.assert_array_equal(fields(sol)[k], v, err_msg=f"{k} at position {pos}")
    for k in ("Q", "momentum", "xi"):
        scale = np.max(np.abs(getattr(alone, k)))
        assert np.max(np.abs(getattr(traced, k) - getattr(alone, k))) <= 2 * N_STEPS * EPS * scale, k


@pytest.mark.slow
def test_sweep_with_one_member_per_batch_differs_only_by_round_off():
    """Batches of one member compile as an unbatched program (the size-1 axis is dropped), so
    the step's small linear solves and the chunk hand-over's least-squares solve round as for a
    single trajectory, not as in a batch of 5: the tables agree to round-off, not to the bit.
    Measured: 7.8e-16 over the whole table. Before the increment-form step (cea7b6e) the first
    chunks were bit-identical; since then two of their 45 entries differ by one ulp (5.6e-17)."""
    by1, by5 = _sweep(1), _sweep(5)
    _assert_same_table(by1, by5, atol=1e-14)
    first = by5.saved["momentum"][:, :3]
    # a few ulps of the momentum scale: no drift can build up over three saved points
    np.testing.assert_allclose(by1.saved["momentum"][:, :3], first, rtol=0, atol=4 * EPS * np.max(np.abs(first)))
