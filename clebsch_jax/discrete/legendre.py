r"""The discrete Legendre side of a node (Lemma 7): from a velocity to the multiplier and back.

At a node, $\delta l/\delta\xi(\xi, Q) = -p\diamond Q = \mu$ ties the velocity ξ to the
canonical momentum p through the momentum map μ. These functions start a march (the initial
multiplier from $(Q^0, \xi^0)$), hand a reduced march's momentum back to a cotangent vector,
and recover nodal velocities."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from ..core.system import ClebschSystem, momentum_map
from ..roots.newton import newton_solve
from ..roots.status import NewtonStats, Status
from .residual import nodal_residual

__all__ = [
    "initial_multiplier",
    "cotangent_from_momentum",
    "min_norm_transpose_solve",
    "nodal_velocity",
    "explicit_nodal_velocity",
]


def initial_multiplier(system: ClebschSystem, Q0: jax.Array, xi0: jax.Array) -> jax.Array:
    r"""The minimum-norm $P^0$ with $\delta l/\delta\xi(\xi^0, Q^0) = -P^0 \diamond Q^0$ (Lemma 7).

    With $A = \partial_\xi \mathcal L_\xi Q^0$ (a matrix from $V$ to $T_{Q^0}M$, by forward-mode
    autodiff) the condition is $A^T P^0 = \delta l/\delta \xi$; among its solutions we take the
    one of least Euclidean norm, $P^0 = (A^T)^+ \,\delta l/\delta\xi$. Components of $P^0$
    that the velocity map cannot see (e.g. the symmetric part of $Q^T P$ on $SO(3)$) are zero.
    """
    return cotangent_from_momentum(system, Q0, jax.grad(lambda x: system.l(x, Q0))(xi0))


_DIRECT_MAX = 32
"""Up to this many components of V the minimum-norm cotangent is a dense solve."""

_DENSE_MAX = 256
"""Above this many components of V it is found matrix-free only (the dense matrix is not formed)."""


def cotangent_from_momentum(system: ClebschSystem, Q: jax.Array, mu: jax.Array, *, unroll: bool = False) -> jax.Array:
    r"""The minimum-norm $p \in T^*_QM$ with momentum map $-p\diamond Q = \mu$.

    Solves $A^T p = \mu$, $A = \partial_\xi \mathcal L_\xi Q$, for the $p$ in the range of $A$
    (`mu` has ξ's shape). Used for the initial multiplier and to rebuild momenta from a reduced
    march.

    - Up to `_DIRECT_MAX` components of V: the dense solve `min_norm_transpose_solve` (an
      orthogonal basis of the range of $A$ by Gram–Schmidt, no LAPACK call).
    - Above: matrix-free first — $p = A y$ with $A^TA\,y = \mu$ by conjugate gradients, products
      by $A$ and $A^T$ only (one iteration when the velocity map is a translation, as for point
      vortices). Up to `_DENSE_MAX` components the result is checked, $|A^Tp - \mu|_\infty \le
      10^3\varepsilon\max(1, |\mu|_\infty)$, and the dense solve is made where it fails.

    No LAPACK call: jaxlib's batched LAPACK kernels share XLA's intra-op thread pool and were
    seen to deadlock when two host devices ran them side by side (a sweep with `devices=2`).
    `unroll`: the dense solve's `unroll` (for a batch of rows).
    """
    lin = lambda x: system.velocity_map(x.reshape(mu.shape), Q)
    if mu.size <= _DIRECT_MAX:
        return _dense_cotangent(lin, Q, mu, unroll)
    _, vjp = jax.vjp(lin, jnp.zeros_like(mu))
    y, _ = jax.scipy.sparse.linalg.cg(lambda v: vjp(lin(v))[0], mu, tol=1e-15, atol=0.0, maxiter=200)
    p = lin(y)
    if mu.size > _DENSE_MAX:
        return p
    scale = jnp.maximum(1.0, jnp.max(jnp.abs(mu)))
    solved = jnp.max(jnp.abs(vjp(p)[0] - mu)) <= 1e3 * jnp.finfo(mu.dtype).eps * scale
    return jax.lax.cond(solved, lambda: p, lambda: _dense_cotangent(lin, Q, mu, unroll))


def _dense_cotangent(lin, Q, mu, unroll=False):
    r"""The minimum-norm solution of $A^T p = \mu$, $A$ formed densely by forward mode."""
    A = jax.jacfwd(lambda x: lin(x).ravel())(jnp.zeros(mu.size, Q.dtype))
    return min_norm_transpose_solve(A, mu.ravel(), unroll=unroll).reshape(Q.shape)


def min_norm_transpose_solve(A: jax.Array, b: jax.Array, *, unroll: bool = False) -> jax.Array:
    r"""The $p$ in the range of `A` (m, n) with $A^T p = b$: the minimum-norm solution.

    Gram–Schmidt with reorthogonalisation (each column projected out twice) gives $A = UR$,
    the columns of $U$ orthonormal and $R$ upper triangular; then $p = Uc$ with $R^T c = b$ by
    forward substitution. A column whose part outside the earlier ones is below
    $\max(m, n)\,\varepsilon$ times the largest column is dependent: its column of $U$ and its
    equation are left out (the system is consistent when $b$ is a momentum $-p\diamond Q$). The
    substitution's row $j$ is solved as column $j$ of $R$ is made, so $R$ is never stored. The
    error is that of a Householder QR, about $\kappa(A)\varepsilon$ (the normal equations would
    square the condition number).

    Plain XLA operations (a `fori_loop` over the n columns), for the reason
    `cotangent_from_momentum` gives; jit-, vmap- and grad-compatible. `unroll`: written out
    column by column up to `STRAIGHT_MAX` columns, for a batch of rows
    (`clebsch_jax.batching.scalarise`), where the loop's masks over every column cannot be
    folded away (a stacked batch compiles the loop's few operations faster)."""
    m, n = A.shape
    eps = jnp.finfo(A.dtype).eps
    cols = jnp.arange(n)
    tol = max(m, n) * eps * jnp.max(jnp.sqrt(jnp.sum(A * A, axis=0)))
    if unroll and n <= STRAIGHT_MAX:
        return _min_norm_straight(A, b, tol)

    def column(j, state):
        U, c = state
        v = A @ (cols == j).astype(A.dtype)
        r = jnp.zeros(n, A.dtype)
        for _ in range(2):  # project out the earlier columns twice ("twice is enough")
            s = U.T @ v  # U's columns j, j+1, ... are still zero
            v, r = v - U @ s, r + s
        norm = jnp.sqrt(jnp.sum(v * v))
        keep = norm > tol
        u = jnp.where(keep, v / jnp.where(keep, norm, 1.0), 0.0)
        U = jnp.where(cols == j, u[:, None], U)
        # R^T c = b, row j, with R's column j (r above the diagonal, d on it) as it is made;
        # c_j = 0 for a dependent column
        d = jnp.where(keep, norm, 0.0)
        cj = (b[j] - jnp.sum(jnp.where(cols < j, r * c, 0.0))) / jnp.where(d != 0, d, 1.0)
        return U, jnp.where(cols == j, jnp.where(d != 0, cj, 0.0), c)

    U, c = jax.lax.fori_loop(0, n, column, (jnp.zeros_like(A), jnp.zeros(n, A.dtype)))
    return U @ c


STRAIGHT_MAX = 4
"""`min_norm_transpose_solve(unroll=True)` with at most this many columns is written out column
by column: the loop's masks over every column go, and the projections are onto the earlier
columns only."""


def _min_norm_straight(A, b, tol):
    """`min_norm_transpose_solve`, unrolled: the same Gram–Schmidt and forward substitution
    without the terms the loop adds as zeros."""
    n = A.shape[1]
    U, R = [], [[None] * n for _ in range(n)]
    for j in range(n):
        v = A[:, j]
        r = [jnp.zeros((), A.dtype)] * j
        for _ in range(2):  # project out the earlier columns twice ("twice is enough")
            if j:
                s = [jnp.sum(U[k] * v) for k in range(j)]
                v = v - functools.reduce(jnp.add, [U[k] * s[k] for k in range(j)])
                r = [r[k] + s[k] for k in range(j)]
        norm = jnp.sqrt(jnp.sum(v * v))
        keep = norm > tol
        U.append(jnp.where(keep, v / jnp.where(keep, norm, 1.0), 0.0))
        R[j][j] = jnp.where(keep, norm, 0.0)
        for k in range(j):
            R[k][j] = r[k]
    c = []
    for j in range(n):  # R^T c = b, row j; c_j = 0 for a dependent column
        d = R[j][j]
        acc = b[j] - functools.reduce(jnp.add, [R[k][j] * c[k] for k in range(j)]) if j else b[j]
        c.append(jnp.where(d != 0, acc / jnp.where(d != 0, d, 1.0), 0.0))
    return functools.reduce(jnp.add, [U[j] * c[j] for j in range(n)])


def nodal_velocity(
    system: ClebschSystem,
    Q: jax.Array,
    p: jax.Array,
    guess: jax.Array,
    *,
    rtol: float = 0.0,
    atol: float = 0.0,
    max_iterations: int = 20,
    solver=None,
):
    r"""Solve Lemma 7's $\delta l/\delta\xi(\xi, Q) = -p \diamond Q$ for $\xi$ by Newton
    (`solver`: `newton_solve`, or `block_newton_solve` for many particles).

    Returns `(xi, NewtonStats)`. Requires $l$ to be regular in $\xi$ (Lemma 8).
    """
    mu = momentum_map(system, p, Q, guess)
    solver = newton_solve if solver is None else solver
    return solver(
        lambda x: nodal_residual(system, Q, mu, x), guess, rtol=rtol, atol=atol, max_iterations=max_iterations
    )


def explicit_nodal_velocity(system: ClebschSystem, Q: jax.Array, mu: jax.Array) -> tuple[jax.Array, NewtonStats]:
    r"""The nodal velocity $\xi = G(\mu, Q)$ from the system's inverse Legendre map
    (`ClebschSystem(inverse_legendre=G)`), with the statistics of a solve that needed no update:
    `residual_norm` is $\max|\delta l/\delta\xi(\xi, Q) - \mu|$, the status `NONFINITE` when ξ
    or that residual is not finite. **Returns:** `(xi, NewtonStats)`."""
    xi = system.inverse_legendre(mu, Q)
    r = jnp.max(jnp.abs(nodal_residual(system, Q, mu, xi)))
    zero = jnp.asarray(0, jnp.int32)
    status = jnp.where(jnp.isfinite(r), Status.SUCCESS, Status.NONFINITE).astype(jnp.int32)
    return xi, NewtonStats(iterations=zero, residual_norm=r, status=status, jacobians=zero)
