r"""A Newton-type solver for many interacting particles: block-diagonal chord iterations.

For systems of N particles — every unknown has a leading axis of length N, as the positions
(N, 2) of point vortices — a dense Newton Jacobian costs (N·b)² entries and N·b residual
linearisations per step (b unknowns per particle), and its factorisation (N·b)³: impossible at
N = 1000. Here the chord matrix is the block-diagonal *lumped* Jacobian

$$ M_a = \sum_b \frac{\partial F_a}{\partial z_b} \quad (a b\times b\text{ block per particle}), $$

which b Jacobian-vector products give for all particles at once (the tangent $e_k$ on component
k of every particle). The updates $z \leftarrow z - M^{-1}F(z)$ drive the *full* residual to
round-off, so the converged step is the same as with exact Newton; only the contraction rate
depends on how well $M$ approximates the Jacobian. Interactions enter the Jacobian through the
Hessian of the potential, times Δt; for a potential invariant under a common translation of the
particles (point vortices, gravitation, EPDiff kernels) the lumped sum even cancels the
diagonal Hessian blocks, leaving the interaction-free part. Each iteration costs one residual
evaluation, like a fixed-point iteration, but with the fast, stiff single-particle part solved
exactly. When the updates stop contracting the matrix is refreshed; a step that still does not
converge is reported (`MAX_ITERATIONS`), never accepted.

Derivatives through the solve use the implicit function theorem (`clebsch_jax.roots.implicit`), with
the tangent systems solved by `TANGENT_SWEEPS` sweeps of the same block-preconditioned iteration.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp

from ..core import linalg
from .newton import Matrix, newton_solve_reusing

__all__ = ["block_newton_solve", "block_newton_solve_reusing", "identity_blocks", "lumped_matrix"]

MAX_CHORD_ITERATIONS = 40
"""Chord updates per block matrix. The lumped matrix is an approximation wherever it is formed,
so refreshing it while the updates still contract buys little: it is refreshed only when they
stop contracting (or after this many updates)."""


TANGENT_SWEEPS = 30
"""Sweeps of the preconditioned tangent iteration: with the contraction of a resolved step
(well below 1/2) 30 sweeps reach round-off."""


def _blocks(tree, n):
    """Leaves (n, ...) → one (n, b) array: the unknowns of particle a in row a."""
    return jnp.concatenate([leaf.reshape(n, -1) for leaf in jax.tree_util.tree_leaves(tree)], axis=1)


def _unblocks(Z, template):
    leaves, treedef = jax.tree_util.tree_flatten(template)
    out, start = [], 0
    for leaf in leaves:
        width = leaf.size // leaf.shape[0]
        out.append(Z[:, start : start + width].reshape(leaf.shape))
        start += width
    return jax.tree_util.tree_unflatten(treedef, out)


def lumped_blocks(lin: Callable, Z: jax.Array) -> jax.Array:
    """(N, b, b) blocks M_a[i, k] = Σ_b ∂F_{a,i}/∂Z_{b,k}, from b products of the linear map `lin`."""
    b = Z.shape[1]
    tangents = jnp.broadcast_to(jnp.eye(b, dtype=Z.dtype)[:, None, :], (b,) + Z.shape)
    # one call of `lin` vmapped over the tangents (a `jit` inside the `vmap`): the same program
    # for XLA, which inlines it, and for the native translation one column's program, which it
    # can emit once in a loop over the columns (`clebsch_jax.native.row_calls`)
    cols = jax.vmap(jax.jit(lin))(tangents)  # (k, N, i)
    return jnp.transpose(cols, (1, 2, 0))


def inverse_blocks(M: jax.Array):
    """The inverses of the (N, b, b) blocks `M` and their singularity flags (N,): one call of
    `linalg.inverse` vmapped over the particles (a loop over them in a native kernel, as the
    columns of `lumped_blocks`)."""
    return jax.vmap(jax.jit(linalg.inverse))(M)


def _block_tangent_solve(g, y):
    """The linear tangent system g(x) = y (g the Jacobian at the root) by the same
    preconditioned iteration as the forward solve, x ← x + M⁻¹(y − g(x)), which contracts where
    the forward chord iterations did. A fixed number of sweeps: JAX transposes this map for
    reverse mode, which a data-dependent while loop would not allow."""
    inv, _ = inverse_blocks(lumped_blocks(g, y))
    apply = lambda r: jnp.einsum("nij,nj->ni", inv, r)
    return jax.lax.fori_loop(0, TANGENT_SWEEPS, lambda _, x: x + apply(y - g(x)), apply(y))


def lumped_matrix(shape) -> Matrix:
    """The Newton `Matrix` of the lumped block-diagonal Jacobian, for flat unknowns that are
    `shape` = (N, b) particle-major: its inverse blocks, applied particle by particle."""

    def invert(f, z):
        Fz, lin = jax.linearize(f, z)
        M = lumped_blocks(lambda t: lin(t.reshape(-1)).reshape(shape), z.reshape(shape))
        inv, singular = inverse_blocks(M)
        return Fz, inv, jnp.any(singular)

    def apply(Hb, r):
        return jnp.einsum("nij,nj->ni", Hb, r.reshape(shape)).reshape(-1)

    def tangent_solve(g, y):
        return _block_tangent_solve(lambda x: g(x.reshape(-1)).reshape(shape), y.reshape(shape)).reshape(-1)

    return Matrix(invert, apply, tangent_solve, MAX_CHORD_ITERATIONS)


def identity_blocks(guess):
    """An (N, b, b) stack of identities: the placeholder inverse blocks for the first solve."""
    leaf = jax.tree_util.tree_leaves(guess)[0]
    n, b = _blocks(guess, leaf.shape[0]).shape
    return jnp.broadcast_to(jnp.eye(b, dtype=leaf.dtype), (n, b, b))


def block_newton_solve_reusing(F: Callable, guess, H, reuse, *, rtol: float, atol: float, max_iterations: int):
    r"""Solve $F(z) = 0$ for a pytree z whose leaves share a leading particle axis, by chord
    iterations with the lumped block-diagonal Jacobian (module docstring), carrying its inverse
    blocks `H` (N, b, b) from the previous solve of a march (`newton_solve_reusing`'s
    contract). Forming the lumped matrix costs b linearised residuals — more than the chord
    updates of a well-predicted step — while the matrix changes by O(Δt) from step to step;
    it is refreshed only when the carried one stops contracting.
    **Returns:** `(z, NewtonStats, H)`."""
    n = jax.tree_util.tree_leaves(guess)[0].shape[0]
    Z0 = _blocks(guess, n)

    def Fb(Z):
        return _blocks(F(_unblocks(Z, guess)), n)

    Z, stats, H, _ = newton_solve_reusing(
        Fb,
        Z0,
        H,
        reuse,
        rtol=rtol,
        atol=atol,
        max_iterations=max_iterations,
        max_contraction=1.0,
        matrix=lumped_matrix(Z0.shape),
    )
    return _unblocks(Z, guess), stats, H


def block_newton_solve(F: Callable, guess, *, rtol: float, atol: float, max_iterations: int):
    r"""Solve $F(z) = 0$ for a pytree $z$ whose leaves share a leading particle axis, by chord
    iterations with the lumped block-diagonal Jacobian (module docstring). Same contract as
    `newton_solve`: returns `(z, NewtonStats)`, stops at round-off by default, and
    `max_iterations` caps the number of block matrices formed."""
    z, stats, _ = block_newton_solve_reusing(F, guess, None, False, rtol=rtol, atol=atol, max_iterations=max_iterations)
    return z, stats
