r"""Calls `jax.vmap`ped over a leading axis as loops over their rows in a native kernel
(`clebsch_jax.native.row_calls`): the lumped block Jacobian of a particle system
(`clebsch_jax.roots.blocks`: a Jacobian-vector product per unknown of a particle, vmapped over
the unknowns), its block inverses (vmapped over the particles) and a Gauss–Legendre sweep's
stage evaluations (`clebsch_jax.discrete.collocation`, vmapped over the stages) emitted as one
row's program in a loop, with the unrolled form's numbers bit for bit and XLA's to round-off.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from clebsch_jax import native
from clebsch_jax.roots import blocks

pytestmark = pytest.mark.skipif(not native.available(), reason="llvmlite cannot be imported")

N, b = 5, 4  # particles and unknowns per particle: 4×4 blocks, inverted by LU (gathers at run-time pivots)
MEMBERS = 6  # two blocks of lanes, the second padded


def _residual(Z):
    """A pairwise interaction of the particles' unknowns (N, b), nonlinear in each."""
    d = Z[:, None, :] - Z[None, :, :]
    r2 = jnp.sum(d * d, axis=-1) + 1.0
    return Z + 0.1 * jnp.sum(d / r2[..., None], axis=1) + 0.05 * Z**3


def _program(Z):
    Fz, lin = jax.linearize(_residual, Z)
    M = blocks.lumped_blocks(lin, Z)
    inv, singular = blocks.inverse_blocks(M)
    return Fz, M, inv, singular


def _members():
    return np.random.default_rng(7).normal(size=(MEMBERS, N, b))


def _kernel(monkeypatch, policies):
    """The program's kernel with the unroll policies `policies` (`control.POLICIES`): its IR
    text, its outputs on `_members()` and the kernel."""
    from clebsch_jax.native import control
    from clebsch_jax.native.kernel import build_ir

    monkeypatch.setattr(control, "POLICIES", policies)
    Z = _members()
    text = build_ir(jax.make_jaxpr(_program)(Z[0]), 4)
    kernel = native.compile_member(_program, Z[0], use_cache=False)
    return text, [np.asarray(x) for x in kernel(Z)], kernel


def test_vmapped_calls_run_as_loops_over_their_rows_with_the_unrolled_numbers(monkeypatch):
    looped_text, looped, kernel = _kernel(monkeypatch, ((0, 0),))  # every scan a loop: the calls' rows too
    unrolled_text, unrolled, _ = _kernel(monkeypatch, ((10**9, 10**9),))  # everything unrolled
    loops = lambda text: sum(line.startswith("for.head") for line in text.splitlines())
    assert loops(looped_text) >= 2 and loops(unrolled_text) == 0  # the columns' call and the inverses'
    assert looped_text.count("\n") < unrolled_text.count("\n")
    for a, c in zip(looped, unrolled):
        np.testing.assert_array_equal(a, c)  # the same operations in the same order
    for a, c in zip(looped, kernel(_members())):
        np.testing.assert_array_equal(a, np.asarray(c))  # bit for bit, call to call
    xla = jax.jit(jax.vmap(_program))(_members())
    for a, c in zip(looped[:3], xla[:3]):
        c = np.asarray(c)
        assert np.max(np.abs(a - c)) <= 1e-12 * np.max(np.abs(c))
    np.testing.assert_array_equal(looped[3], np.asarray(xla[3]))
    assert not looped[3].any()  # no block singular: the inverses are the blocks' inverses
    M, inv = looped[1], looped[2]
    np.testing.assert_allclose(M @ inv, np.broadcast_to(np.eye(b), M.shape), atol=1e-12)


def _sweep_program(kind: str, stages: int):
    """One fixed-point sweep of a Gauss–Legendre step (`collocation`), its stage evaluations a
    call vmapped over the stages: point vortices (the degenerate sweep, blocks of the constraint
    matrix) or the rigid body on R³ (the regular one), on one member's (Q, P) and stage unknowns."""
    from clebsch_jax import models
    from clebsch_jax.discrete import collocation as co
    from clebsch_jax.discrete.legendre import initial_multiplier

    tab = co.gauss_legendre(stages)
    if kind == "vortices":
        system = models.point_vortices(jnp.array([1.0, -1.0, 1.0, -0.5]))

        def program(Q, xi, dQ, dP):
            P = initial_multiplier(system, Q, xi[0])
            z = co.GaussUnknowns(xi, dQ, dP)
            inverse = co.constraint_matrix_inverse(system, xi[0], Q, P, blocks=True)[0]
            return co.degenerate_sweep(system, tab, 0.3, Q, P, z, inverse)

        Q = np.array([[1.0, 0.0], [0.0, 1.2], [-1.1, 0.1], [0.2, -0.9]])
    else:
        system = models.rigid_body_vector(jnp.array([2.0, 1.0, 2.0 / 3.0]))

        def program(Q, xi, dQ, dP):
            P = jnp.cross(Q, jnp.array([0.3, -0.2, 0.9]))
            return co.gauss_sweep(system, tab, 0.3, Q, P, co.GaussUnknowns(xi, dQ, dP))

        Q = np.array([0.6, 0.8, 0.0])
    rng = np.random.default_rng(3)
    members = [Q + 0.05 * rng.normal(size=(MEMBERS,) + Q.shape)]
    members += [0.1 * rng.normal(size=(MEMBERS, stages) + Q.shape) for _ in range(3)]
    return program, members


@pytest.mark.parametrize(
    "kind, stages",
    [
        # slow: the vortices' sweep written out entry by entry (the unrolled kernel) takes LLVM
        # about a minute
        pytest.param("vortices", 6, marks=pytest.mark.slow),
        ("body", 8),
    ],
)
def test_gauss_sweep_stages_run_as_a_loop_with_the_unrolled_numbers(monkeypatch, kind, stages):
    from clebsch_jax.native import control
    from clebsch_jax.native.kernel import build_ir

    program, members = _sweep_program(kind, stages)
    one = [m[0] for m in members]
    runs = {}
    for name, policies in (("looped", ((0, 0),)), ("unrolled", ((10**9, 10**9),))):
        monkeypatch.setattr(control, "POLICIES", policies)
        text = build_ir(jax.make_jaxpr(program)(*one), 4)
        kernel = native.compile_member(program, *one, use_cache=False)
        runs[name] = text, [np.asarray(x) for x in jax.tree_util.tree_leaves(kernel(*members))]
    (looped_text, looped), (unrolled_text, unrolled) = runs["looped"], runs["unrolled"]
    assert any(line.startswith("for.head") for line in looped_text.splitlines())  # the stages' loop
    if kind == "body":  # the vortices' pairwise sums are loops either way (`native.fused`), and
        # their written-out sweep is now the shorter text: only the numbers are compared there
        assert looped_text.count("\n") < unrolled_text.count("\n")
    for a, c in zip(looped, unrolled):
        np.testing.assert_array_equal(a, c)  # the same operations in the same order
    xla = jax.tree_util.tree_leaves(jax.jit(jax.vmap(program))(*members))
    for a, c in zip(looped, xla):
        c = np.asarray(c)
        assert np.max(np.abs(a - c)) <= 1e-12 * np.max(np.abs(c))
