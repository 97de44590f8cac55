r"""Closure of the velocity map (Definition 10), the induced bracket, ad and ad* (Definition 11),
and the continuous Euler–Poincaré field (Theorems 12 and 16), all derived from l and L.

Closure means that for every pair u, v ∈ V there is **one** w ∈ V with

$$ \mathcal L_w Q = \big((T_Q\mathcal L_v)\mathcal L_u - (T_Q\mathcal L_u)\mathcal L_v\big) Q \quad\text{for every } Q . $$

The bracket vector field on the right is computed with jvps; w is fitted by least squares jointly
over several points Q (at a single point where L is onto, every map looks closed).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from ..core.jit import QUICK_COMPILE, jit_with_options
from ..core.system import ClebschSystem, momentum_map

__all__ = ["ClosureResult", "check_closure", "euler_poincare_field", "sample_points"]


@dataclasses.dataclass(frozen=True)
class ClosureResult:
    r"""Verdict of `check_closure`.

    - `closed`: True when one w per basis pair fits the bracket field at every sample point
      with relative residual ≤ `tolerance`, and the fitted bracket satisfies Jacobi.
    - `worst_residual`: the largest relative least-squares residual over basis pairs.
    - `structure_constants` (m, m, m): $[e_i, e_j] = \sum_k c_{ijk} e_k$ for the flattened
      basis $e_i$ of V (meaningful only when `closed`).
    - `jacobi_error`: max over basis triples of $|[[a,b],c] + [[b,c],a] + [[c,a],b]|$, relative
      to the size of the constants; `satisfies_jacobi` compares it with `tolerance`.
    - `rank`: rank of $\xi \mapsto \mathcal L_\xi Q$ stacked over the sample points (if it is
      below m, w is not unique and the minimum-norm fit is reported).
    - `n_points`, `tolerance`, `xi_shape`.
    """

    closed: bool
    worst_residual: float
    structure_constants: np.ndarray
    jacobi_error: float
    satisfies_jacobi: bool
    rank: int
    n_points: int
    tolerance: float
    xi_shape: tuple

    def bracket(self, u: jax.Array, v: jax.Array) -> jax.Array:
        """The induced bracket [u, v] of Definition 10 (arrays of ξ's shape)."""
        c = jnp.asarray(self.structure_constants)
        w = jnp.einsum("i,j,ijk->k", jnp.ravel(u), jnp.ravel(v), c)
        return w.reshape(self.xi_shape)

    def ad(self, u: jax.Array, v: jax.Array) -> jax.Array:
        r"""$\mathrm{ad}_u v = -[u, v]$ (Definition 11)."""
        return -self.bracket(u, v)

    def ad_star(self, u: jax.Array, m: jax.Array) -> jax.Array:
        r"""$\langle \mathrm{ad}^*_u m, v\rangle = \langle m, \mathrm{ad}_u v\rangle$ (Definition 11)."""
        c = jnp.asarray(self.structure_constants)
        out = -jnp.einsum("i,ijk,k->j", jnp.ravel(u), c, jnp.ravel(m))
        return out.reshape(self.xi_shape)


def _basis(xi_shape, dtype):
    m = int(np.prod(xi_shape)) if xi_shape else 1
    return np.eye(m, dtype=dtype).reshape((m,) + tuple(xi_shape))


def _directions(xi, n_points: int, seed: int, dtype):
    """`n_points` random unit directions of ξ's shape (the flows of `sample_points`)."""
    rng = np.random.default_rng(seed)
    etas = rng.normal(size=(n_points,) + tuple(np.shape(xi)))
    etas = etas / np.linalg.norm(etas.reshape(n_points, -1), axis=1).reshape((-1,) + (1,) * np.ndim(xi))
    return etas.astype(dtype)


def sample_points(
    system: ClebschSystem, Q: jax.Array, xi: jax.Array, n_points: int, spread: float, seed: int = 0
) -> jax.Array:
    r"""Points near Q reached by following the velocity map: $\dot Q = \mathcal L_\eta Q$ for a
    random unit $\eta$ (RK4, 16 substeps, time `spread`). They stay on the orbit of Q, so a
    model defined only on a submanifold (rotations, a sphere) is evaluated where it is valid.
    Returns shape (n_points + 1, *Q.shape), Q first."""
    return _flow_jit(system.velocity_map, Q, _directions(xi, n_points, seed, jnp.result_type(Q)), spread)


def _flow(velocity_map, Q, etas, spread):
    substeps = 16
    h = spread / substeps

    def one(eta):
        f = lambda q: velocity_map(eta, q)

        def rk4(_, q):
            k1 = f(q)
            k2 = f(q + 0.5 * h * k1)
            k3 = f(q + 0.5 * h * k2)
            k4 = f(q + h * k3)
            return q + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)

        return jax.lax.fori_loop(0, substeps, rk4, Q)

    return jnp.concatenate([Q[None], jax.vmap(one)(etas)])


@functools.partial(jit_with_options, compiler_options=QUICK_COMPILE, static_argnums=0)
def _sampled_bracket_data(velocity_map, Q, etas, spread, basis):
    """`_flow` and `_bracket_data` in one program: (points, A, B)."""
    pts = _flow(velocity_map, Q, etas, spread)
    return (pts,) + _bracket_data(velocity_map, pts, basis)


def _bracket_data(velocity_map, pts, basis):
    """At every sample point: A = [L_{e_k} Q] (d, m) and B_ij = (T L_{e_j}) L_{e_i} Q - (T L_{e_i}) L_{e_j} Q.

    All pairs in one batched jvp (compiled once per velocity map, which is static)."""
    m = basis.shape[0]

    def at_point(q):
        Lq = jax.vmap(lambda e: velocity_map(e, q))(basis)  # (m, *Q.shape)
        A = Lq.reshape(m, -1).T
        # T[j, i] = T_Q L_{e_j} · (L_{e_i} Q), a jvp of Q ↦ L_{e_j} Q
        T = jax.vmap(lambda ej: jax.vmap(lambda li: jax.jvp(lambda qq: velocity_map(ej, qq), (q,), (li,))[1])(Lq))(
            basis
        )
        T = T.reshape(m, m, -1)
        B = jnp.swapaxes(T, 0, 1) - T  # B[i, j] = T[j, i] - T[i, j]
        return A, B

    return jax.vmap(at_point)(pts)


_flow_jit = jit_with_options(_flow, QUICK_COMPILE, static_argnums=0)
_bracket_data_jit = jit_with_options(_bracket_data, QUICK_COMPILE, static_argnums=0)


CLOSURE_TOLERANCE = 1e-9
"""`check_closure`'s default tolerance on the relative residual of a bracket's fit (and the
reduction's, `clebsch_jax.discrete.reduction`): far above round-off of exact derivatives
(~1e-15), far below any genuine Q-dependence of the structure constants."""


def check_closure(
    system: ClebschSystem,
    Q: jax.Array,
    xi: jax.Array,
    *,
    points: jax.Array | None = None,
    n_points: int = 6,
    spread: float = 0.5,
    tolerance: float = CLOSURE_TOLERANCE,
    seed: int = 0,
) -> ClosureResult:
    r"""Decide numerically whether the velocity map is closed (Definition 10, Theorem 12).

    For every basis pair $(e_i, e_j)$ of V the bracket vector field
    $B_{ij}(Q) = (T_Q\mathcal L_{e_j})\mathcal L_{e_i}Q - (T_Q\mathcal L_{e_i})\mathcal L_{e_j}Q$ is
    computed with jvps at each sample point, and one $w_{ij}$ is fitted by least squares to
    $\mathcal L_{w_{ij}} Q_s = B_{ij}(Q_s)$ jointly over all points $Q_s$. The relative residual
    $\|A w - B\| / \max(\|B\|, \|A\|_F)$ (A stacks $\xi\mapsto\mathcal L_\xi Q_s$) must be below
    `tolerance` for every pair; the default 1e-9 sits far above round-off of exact jvps
    (~1e-15) and far below any genuine Q-dependence of the structure constants.

    **Arguments:**

    - `system`: the Clebsch system. `Q`: a point of M. `xi`: any element of V (its shape).
    - `points`: optional sample points, shape (S, *Q.shape); by default `n_points` points are
      drawn near Q along the flows of the velocity map (`sample_points`, time `spread`).
    - `tolerance`, `seed`: see above.

    **Returns:** a `ClosureResult` (`closed`, `worst_residual`, `structure_constants`,
    `jacobi_error`, `satisfies_jacobi`, ...).

    Not jit/vmap/grad-compatible by design: it returns a Python verdict used to choose a
    method, from concrete sample points.
    """
    Q = jnp.asarray(Q, dtype=jnp.result_type(float))
    xi = jnp.asarray(xi, dtype=Q.dtype)
    basis = _basis(xi.shape, Q.dtype)
    m = basis.shape[0]
    if points is None:  # one program: the sample points and the brackets there
        etas = _directions(xi, n_points, seed, Q.dtype)
        pts, As, Bs = _sampled_bracket_data(system.velocity_map, Q, etas, spread, basis)
    else:
        pts = jnp.asarray(points, dtype=Q.dtype)
        As, Bs = _bracket_data_jit(system.velocity_map, pts, basis)  # (S, d, m), (S, m, m, d)
    A = np.asarray(As).reshape(-1, m)
    B = np.moveaxis(np.asarray(Bs), 0, 2).reshape(m, m, -1)  # (m, m, S*d)
    c = np.zeros((m, m, m))
    worst = 0.0
    A_norm = np.linalg.norm(A)
    rank = int(np.linalg.matrix_rank(A))
    pinv = np.linalg.pinv(A)
    for i in range(m):
        for j in range(i + 1, m):
            b = B[i, j]
            w = pinv @ b
            res = np.linalg.norm(A @ w - b) / max(np.linalg.norm(b), A_norm, np.finfo(float).tiny)
            worst = max(worst, float(res))
            c[i, j] = w
            c[j, i] = -w
    # Jacobi identity on basis triples: [[a,b],c] + [[b,c],a] + [[c,a],b] = 0
    br = lambda u, v: np.einsum("i,j,ijk->k", u, v, c)
    E = np.eye(m)
    jac = 0.0
    for a in range(m):
        for b_ in range(m):
            for cc in range(m):
                x, y, z = E[a], E[b_], E[cc]
                jac = max(jac, float(np.max(np.abs(br(br(x, y), z) + br(br(y, z), x) + br(br(z, x), y)))))
    scale = max(1.0, float(np.max(np.abs(c))) ** 2)
    jacobi_error = jac / scale
    satisfies = jacobi_error <= tolerance
    return ClosureResult(
        closed=bool(worst <= tolerance and satisfies),
        worst_residual=worst,
        structure_constants=c,
        jacobi_error=jacobi_error,
        satisfies_jacobi=bool(satisfies),
        rank=rank,
        n_points=int(pts.shape[0]),
        tolerance=float(tolerance),
        xi_shape=tuple(xi.shape),
    )


def euler_poincare_field(system: ClebschSystem, closure: ClosureResult) -> Callable:
    r"""The continuous Euler–Poincaré vector field, derived from l and the induced bracket.

    Theorem 16 (Theorem 12 when l does not depend on Q):

    $$ \frac{d}{dt}\frac{\delta l}{\delta \xi} = -\mathrm{ad}^*_\xi \frac{\delta l}{\delta \xi}
       - \frac{\delta l}{\delta Q}\diamond Q, \qquad \dot Q = \mathcal L_\xi Q . $$

    With $m = \delta l/\delta\xi(\xi, Q)$, $\dot m = H_{\xi\xi}\dot\xi + H_{\xi Q}\dot Q$, so
    $\dot\xi$ is found by a dense solve with the Hessian $H_{\xi\xi}$ (l must be regular in ξ).

    **Returns:** `rhs(xi, Q) -> (xi_dot, Q_dot)`, a pure function (jit/vmap/grad-compatible),
    usable as the right-hand side of an ODE solver for reference solutions. For the rigid body
    it is Euler's equations with reconstruction $\dot Q = Q\hat\Omega$.
    """
    if not closure.closed:
        raise ValueError(
            "closure: the velocity map is not closed (Definition 10), so Q and P cannot be "
            f"eliminated (Theorem 12); worst residual {closure.worst_residual:.2e}."
        )

    def rhs(xi, Q):
        Qdot = system.velocity_map(xi, Q)
        grad_xi = lambda x, q: jax.grad(lambda y: system.l(y, q))(x)
        dl_dQ = jax.grad(lambda q: system.l(xi, q))(Q)
        mdot = -closure.ad_star(xi, grad_xi(xi, Q)) + momentum_map(system, dl_dQ, Q, xi)
        # m(ξ, Q) = δl/δξ: dm/dt = H_ξξ ξ' + H_ξQ Q'
        _, mQ = jax.jvp(lambda q: grad_xi(xi, q), (Q,), (Qdot,))
        H = jax.jacfwd(lambda x: grad_xi(x.reshape(xi.shape), Q).ravel())(xi.ravel())
        xidot = jnp.linalg.solve(H, (mdot - mQ).ravel()).reshape(xi.shape)
        return xidot, Qdot

    return rhs
