r"""Isotropy: the directions of V that move nothing, $\ker(\xi \mapsto \mathcal L_\xi Q)$.

On a sphere acted on by cross products, $\mathcal L_\xi q = \xi \times q$ vanishes for
$\xi \parallel q$: the velocity map has a kernel (the Lie algebra of the isotropy group of q).
Two consequences for a Clebsch system, both handled here and applied by `integrate`:

- **Lagrangians written with physical velocities.** A Lagrangian that sees ξ only through the
  tangent vector $\mathcal L_\xi Q$ (the double spherical pendulum with $v_a = \xi_a \times q_a$)
  is degenerate exactly along the isotropy: its Hessian in ξ has that kernel as null space.
  The step equations then leave the kernel component of ξ undetermined (it appears nowhere),
  and Newton's matrix is singular. `IsotropyGauge` fixes the gauge by adding

  $$ \tfrac{w}{2}\,|\Pi_{\ker}(Q)\,\xi|^2 , $$

  $\Pi_{\ker}(Q)$ the orthogonal projector onto the kernel at Q (computed at every Q from the
  velocity map's Jacobian, `row_space_basis`). Along solutions this term and its derivatives
  vanish: Lemma 7 puts $\delta l/\delta\xi$ in the range of $A^T$, $A = \partial_\xi\mathcal L_\xi Q$,
  which is orthogonal to the kernel, so the gauged Legendre relation forces $\Pi_{\ker}\xi = 0$,
  and the term is quadratic in $\Pi_{\ker}\xi$. The motion is that of the Lagrangian as
  written; the velocities have no kernel component.
- **Initial velocities.** ξ⁰ and ξ⁰ + k (k in the kernel) are the same physical velocity
  $\mathcal L_{\xi^0}Q^0$. `physical_velocity` replaces ξ⁰ by the ξ with that tangent vector
  whose momentum $\delta l/\delta\xi$ has a multiplier (Lemma 7 needs it in the range of $A^T$).
  Where ξ⁰ is marched as given (a sweep, a batch) the momentum's component along the kernel has
  no multiplier and is dropped; `check_initial_momentum` says so, with its size.

The kernel's dimension is constant along an orbit of the action (isotropy groups along an orbit
are conjugate), and a Clebsch trajectory stays on the orbit of $Q^0$: the rank found at $Q^0$ is
the rank everywhere the march goes.
"""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np

from .jit import QUICK_COMPILE, filter_jit
from .system import ClebschSystem

__all__ = [
    "ISOTROPY_RTOL",
    "kernel_basis",
    "row_space_basis",
    "IsotropyGauge",
    "gauge_isotropy",
    "gauged",
    "gauge_weight",
    "physical_part",
    "rank_holds",
    "physical_velocity",
    "isotropy_dimension",
    "MULTIPLIER_RTOL",
    "MULTIPLIER_CHECK_MAX_DIM",
    "momentum_defect",
    "check_initial_momentum",
]

ISOTROPY_RTOL = 1e-10
r"""A direction of V is in the isotropy at Q when the velocity map's Jacobian
$A = \partial_\xi \mathcal L_\xi Q$ has a singular value at most this times its largest along it
(round-off for an exact kernel; far below any genuine motion)."""


def velocity_jacobian(velocity_map, Q, xi_shape) -> jax.Array:
    r"""$A = \partial_\xi \mathcal L_\xi Q$ flattened to (Q.size, prod(xi_shape)): the velocity map on
    the basis of V."""
    n = int(np.prod(xi_shape)) if xi_shape else 1
    # the map is linear in ξ (Definition 1): its columns are its values on the basis, no derivative
    basis = jnp.eye(n, dtype=Q.dtype).reshape((n,) + tuple(xi_shape))
    return jax.vmap(lambda e: velocity_map(e, Q).reshape(-1), out_axes=1)(basis)


def kernel_basis(A, rtol: float = ISOTROPY_RTOL) -> np.ndarray:
    """An orthonormal basis (n, k) of the kernel of the (m, n) matrix `A` (NumPy, by SVD): the
    right singular vectors whose singular values are at most `rtol` times the largest."""
    A = np.asarray(A)
    n = A.shape[1]
    if A.size == 0:
        return np.eye(n)
    _, s, vt = np.linalg.svd(A)
    if not s.size or not s[0] > 0:
        return np.eye(n)
    rank = int(np.sum(s > rtol * s[0]))
    return vt[rank:].T.copy()


def row_space_basis(A: jax.Array, rank: int) -> jax.Array:
    r"""An orthonormal basis (n, rank) of the row space of the (m, n) matrix `A` of that rank:
    Gram–Schmidt on the rows with column pivoting (the largest remaining row first, each
    projection made twice), smooth in A where the rank is constant. Plain XLA operations,
    jit-, vmap- and differentiable to any order."""
    W = A.T  # (n, m): the rows of A as columns
    basis = []
    for _ in range(rank):
        norms = jnp.sum(W * W, axis=0)
        pick = jax.nn.one_hot(jnp.argmax(norms), W.shape[1], dtype=W.dtype)
        u = (W @ pick) / jnp.sqrt(norms @ pick)
        for _ in range(2):  # "twice is enough"
            W = W - jnp.outer(u, u @ W)
        basis.append(u)
    return jnp.stack(basis, axis=1) if basis else jnp.zeros((A.shape[1], 0), A.dtype)


class IsotropyGauge:
    r"""A Lagrangian with its isotropy gauge fixed: $l(\xi, Q) + \frac{w}{2}|\Pi_{\ker}(Q)\xi|^2$
    (module docstring), with $|\Pi_{\ker}\xi|^2 = |\xi|^2 - |U^T\xi|^2$, U the `row_space_basis`
    of $A(Q)$.

    **Arguments:** `lagrangian` (the user's, `l(xi)` or `l(xi, Q)`), `velocity_map`,
    `has_potential` (which of the two forms `lagrangian` is), `rank` (of $A$ on the orbit of
    $Q^0$, a Python int), `kernel_dim` (the isotropy's dimension, dim V − rank), `weight` (w, an array: the size of l's Hessian, so the gauged Hessian
    is as well conditioned as the physical one). A pytree: the user's functions and the weight
    are its children."""

    def __init__(self, lagrangian, velocity_map, has_potential: bool, rank: int, kernel_dim: int, weight):
        self.lagrangian, self.velocity_map, self.weight = lagrangian, velocity_map, weight
        self.has_potential, self.rank, self.kernel_dim = bool(has_potential), int(rank), int(kernel_dim)

    def user_l(self, xi, Q):
        return self.lagrangian(xi, Q) if self.has_potential else self.lagrangian(xi)

    def gauge(self, xi, Q):
        r"""$\frac{w}{2}|\Pi_{\ker}(Q)\xi|^2$, with the projector's dependence on Q not differentiated
        (`stop_gradient`): the term is quadratic in $\Pi_{\ker}\xi$, so what that leaves out of the
        step equations is proportional to $\Pi_{\ker}\xi$, which their ξ-block makes zero. The
        roots (and so the root's derivatives by the implicit function theorem) are the same, and
        the residual and its Jacobian need no derivatives of the Gram–Schmidt basis."""
        U = jax.lax.stop_gradient(row_space_basis(velocity_jacobian(self.velocity_map, Q, xi.shape), self.rank))
        flat = xi.reshape(-1)
        seen = U.T @ flat
        return 0.5 * self.weight * (jnp.sum(flat * flat) - jnp.sum(seen * seen))

    def __call__(self, xi, Q):
        return self.user_l(xi, Q) + self.gauge(xi, Q)

    def __repr__(self):
        return f"IsotropyGauge({self.lagrangian!r}, rank={self.rank})"


jax.tree_util.register_pytree_node(
    IsotropyGauge,
    lambda g: ((g.lagrangian, g.velocity_map, g.weight), (g.has_potential, g.rank, g.kernel_dim)),
    lambda aux, ch: IsotropyGauge(ch[0], ch[1], *aux, ch[2]),
)


def gauge_weight(system, Q, xi) -> jax.Array:
    r"""The gauge term's weight w at $(\xi, Q)$: the size of l's Hessian in ξ there (its Frobenius
    norm), 1 where that is zero or not finite. Plain XLA operations (traced or not: `integrate`
    evaluates it on concrete values, a sweep in its members' programs, a traced `integrate`
    in the caller's), so that every path gauges a member with the same weight."""
    return _weight_of(_lagrangian_hessian(system, Q, jnp.asarray(xi)))


def _lagrangian_hessian(system, Q, xi) -> jax.Array:
    """l's Hessian in ξ at (ξ, Q), flattened to (ξ.size, ξ.size)."""
    return jax.hessian(lambda x: system.l(x.reshape(xi.shape), Q))(xi.reshape(-1))


def _weight_of(H) -> jax.Array:
    """`gauge_weight` from l's Hessian `H`: its Frobenius norm, 1 where that is zero or not finite."""
    size = jnp.sqrt(jnp.sum(H * H))
    return jnp.where(jnp.isfinite(size) & (size > 0), size, 1.0)


def gauged(system: ClebschSystem, rank: int, kernel_dim: int, weight, degenerate: bool) -> ClebschSystem:
    """`system` with its isotropy gauge fixed (`IsotropyGauge`), the velocity map's `rank` (a
    Python int) decided before, e.g. on a concrete member (`gauge_isotropy`), and `weight` an
    array (traced or not: `gauge_weight`). `degenerate`: whether the gauged system is still
    degenerate in ξ."""
    if isinstance(system.lagrangian, IsotropyGauge):
        return system
    lag = IsotropyGauge(system.lagrangian, system.velocity_map, system.has_potential, rank, kernel_dim, weight)
    return _rebuilt(system, lag, degenerate=degenerate)


def physical_part(velocity_map, Q, xi, rank: int) -> jax.Array:
    r"""ξ with its isotropy component at Q dropped: its orthogonal projection $UU^T\xi$ onto the
    row space of $A = \partial_\xi\mathcal L_\xi Q$ (`row_space_basis`, of the given rank), the
    same physical velocity $\mathcal L_\xi Q$. For a system whose gauge is fixed this is the ξ
    `physical_velocity` starts from (the gauge term makes the momentum's kernel component
    $wK^T\xi$), here in plain XLA operations, traced or not."""
    U = row_space_basis(velocity_jacobian(velocity_map, Q, xi.shape), rank)
    flat = xi.reshape(-1)
    return (U @ (U.T @ flat)).reshape(xi.shape)


def rank_holds(velocity_map, Q, xi_shape, rank: int, rtol: float = ISOTROPY_RTOL) -> jax.Array:
    """Whether the velocity map's Jacobian at Q has the given rank (to `rtol`, as `kernel_basis`
    counts it), as a traced boolean: Gram–Schmidt with column pivoting (`row_space_basis`) finds
    `rank` rows each above `rtol` times the largest, and nothing above that left. A member whose
    isotropy differs from the one its gauge was built for (another orbit type) is then refused
    as an invalid input instead of marching a wrong gauge."""
    W = velocity_jacobian(velocity_map, Q, xi_shape).T
    norms = jnp.sum(W * W, axis=0)
    top = jnp.max(norms)
    ok = jnp.isfinite(top) & (top > 0) if rank > 0 else jnp.asarray(True)
    for _ in range(rank):
        norms = jnp.sum(W * W, axis=0)
        pick = jax.nn.one_hot(jnp.argmax(norms), W.shape[1], dtype=W.dtype)
        largest = norms @ pick
        ok = ok & (largest > rtol**2 * top)
        u = (W @ pick) / jnp.sqrt(largest)
        for _ in range(2):
            W = W - jnp.outer(u, u @ W)
    if W.size:
        ok = ok & (jnp.max(jnp.sum(W * W, axis=0)) <= rtol**2 * jnp.maximum(top, jnp.finfo(W.dtype).tiny))
    return ok


def isotropy_dimension(system) -> int:
    """The dimension of the isotropy whose gauge `system` fixes (0: none, the system as written)."""
    lag = system.lagrangian
    return lag.kernel_dim if isinstance(lag, IsotropyGauge) else 0


def gauge_isotropy(system: ClebschSystem, Q0, xi0, *, weight=None, regular=None) -> ClebschSystem:
    r"""`system` with its isotropy gauge fixed (`IsotropyGauge`), for a Lagrangian that sees ξ
    only through $\mathcal L_\xi Q$ (degenerate exactly along the isotropy).

    `integrate` does this itself when it finds such a Lagrangian at a concrete $(\xi^0, Q^0)$
    (and reports it in `Solution.isotropy`); call it to build the gauged system once, e.g.
    to integrate under `jax.jit`/`jax.vmap` over `Q0`, where the engine cannot inspect values.

    **Arguments:** `system`, a concrete `Q0` and `xi0` (the rank of the velocity map is read
    there); `weight` (default: `gauge_weight`, the size — Frobenius norm — of l's Hessian in ξ
    at $(\xi^0, Q^0)$, 1 if it is zero); `regular` (default: True unless `system.degenerate` and the gauged Hessian
    is still singular): whether the gauged system is regular in ξ — a system built with
    `degenerate=True` whose only degeneracy was the isotropy becomes regular.

    **Returns:** a `ClebschSystem` with `lagrangian` an `IsotropyGauge` (of the potential form).
    """
    if isinstance(system.lagrangian, IsotropyGauge):
        return system
    Q0, xi0 = jnp.asarray(Q0, float), jnp.asarray(xi0, float)
    A, H, found = _gauge_values(system, Q0, xi0)
    A, H = np.asarray(A), np.asarray(H)
    K = kernel_basis(A)
    if weight is None:  # the weight every path computes (`gauge_weight`), here on concrete values
        weight = found
    if regular is None:
        fixed = H + float(weight) * K @ K.T
        s = np.linalg.svd(fixed, compute_uv=False)
        regular = (not system.degenerate) or bool(s.size and s[-1] > 1e-14 * s[0])
    rank, kernel_dim = xi0.size - K.shape[1], K.shape[1]
    return gauged(system, rank, kernel_dim, jnp.asarray(weight, float), system.degenerate and not regular)


def _evaluate_gauge(system, Q0, xi0):
    """What `gauge_isotropy` reads at (ξ⁰, Q⁰): the velocity map's Jacobian, l's Hessian in ξ and
    the gauge's weight computed from it as `gauge_weight` computes it."""
    H = _lagrangian_hessian(system, Q0, xi0)
    return velocity_jacobian(system.velocity_map, Q0, xi0.shape), H, _weight_of(H)


_gauge_values = filter_jit(_evaluate_gauge, QUICK_COMPILE)
"""`_evaluate_gauge` as one compiled program per system and shapes (a check before marching: one
compile, not one per operation of the user's maps and their derivatives run eagerly)."""


def _rebuilt(system, lagrangian, degenerate):
    return ClebschSystem(
        lagrangian=lagrangian,
        velocity_map=system.velocity_map,
        derivative_map=system.derivative_map,
        degenerate=degenerate,
        check_Q=system.check_Q,
    )


def physical_velocity(system, Q0, xi0, K: np.ndarray, *, warn: bool = True, stacklevel: int = 2):
    r"""ξ⁰ taken as the physical velocity $\mathcal L_{\xi^0}Q^0$: the ξ = ξ⁰ + Kc (the same tangent
    vector, K an orthonormal basis of the isotropy at $Q^0$) whose momentum $\delta l/\delta\xi$
    has no component along the isotropy, $K^T\nabla_\xi l(\xi, Q^0) = 0$, so that Lemma 7's
    multiplier exists. Found by Newton's method on c from $c = -K^T\xi^0$ (the kernel component
    dropped; that is the answer when l does not see the kernel, and one update more when l is
    quadratic in it). With `warn`, a `UserWarning` says so once when ξ⁰ changed.

    Returns ξ (an array of `xi0`'s shape)."""
    if K.shape[1] == 0:
        return xi0
    x0 = np.asarray(xi0, float).reshape(-1)
    shape = tuple(np.shape(xi0))
    c = -K.T @ x0
    for _ in range(3):
        gradient, hessian = _gradient_and_hessian(system, Q0, x0 + K @ c, shape)
        g = K.T @ np.asarray(gradient)
        Hk = K.T @ np.asarray(hessian) @ K
        scale = max(1.0, float(np.linalg.norm(Hk)))
        if not np.all(np.isfinite(g)) or not np.linalg.norm(g) > 1e-14 * scale:
            break
        c = c - np.linalg.lstsq(Hk, g, rcond=1e-12)[0]
    x = x0 + K @ c
    change = float(np.linalg.norm(x - x0))
    if warn and change > 1e-12 * max(float(np.linalg.norm(x0)), np.finfo(float).tiny):
        warnings.warn(
            f"xi0: has a component along the isotropy of Q0 (the {K.shape[1]}-dimensional kernel of "
            "xi -> L_xi Q0, directions that move Q0 not at all). The engine takes xi0 as the physical velocity "
            f"L_xi0 Q0 and starts from the xi with that tangent vector whose momentum has a multiplier "
            f"(Lemma 7): xi0 changed by {change:.3g} (Solution.xi[0] is the velocity used).",
            UserWarning,
            stacklevel=stacklevel,
        )
    return jax.device_put(x.reshape(shape))  # a transfer: `jnp.asarray` would compile a program


def _evaluate_gradient_and_hessian(system, Q0, x, shape):
    """l's gradient and Hessian in ξ at (ξ, Q⁰), ξ = x (flat) of shape `shape`, both flat."""
    grad = jax.grad(lambda y: system.l(y.reshape(shape), Q0))
    return grad(x), jax.jacfwd(grad)(x)


_gradient_and_hessian = filter_jit(_evaluate_gradient_and_hessian, QUICK_COMPILE)
"""`physical_velocity`'s derivatives, one compiled program per system and shapes for its
Newton updates (each an evaluation of this program on the host's iterate)."""


MULTIPLIER_RTOL = 1e-8
r"""`check_initial_momentum` warns when the part of $\delta l/\delta\xi(\xi^0, Q^0)$ that no multiplier
gives is more than this fraction of it (round-off for a momentum that has one; any genuine
component along the isotropy far above)."""

MULTIPLIER_CHECK_MAX_DIM = 256
"""`momentum_defect` is measured up to this dim V (a dense SVD of the velocity map's Jacobian,
as the isotropy is found: `clebsch_jax.core.model_checks.ISOTROPY_MAX_DIM`)."""


def momentum_defect(system, Q0, xi0) -> tuple[float, int]:
    r"""How far the momentum of ξ⁰ is from having a multiplier: Lemma 7 starts the march from a
    $P^0$ with $\delta l/\delta\xi(\xi^0, Q^0) = A^T P^0$, $A = \partial_\xi\mathcal L_\xi Q^0$, which exists
    exactly when $K^T\nabla_\xi l = 0$, K an orthonormal basis of the isotropy $\ker A$
    (`kernel_basis`). Without it the minimum-norm $P^0$ (`initial_multiplier`) solves the
    least-squares problem: its momentum is $\nabla_\xi l$ with that component removed.

    **Returns:** (relative defect $|K^T\nabla_\xi l| / |\nabla_\xi l|$, dimension of the isotropy); (0, 0)
    for a system whose gauge is fixed (`IsotropyGauge`: l does not see the isotropy, the gauge
    term's part is the one the multiplier drops, and the motion is that of the physical velocity)
    or when not measured (dim V above `MULTIPLIER_CHECK_MAX_DIM`, or values not finite)."""
    if isinstance(system.lagrangian, IsotropyGauge) or np.size(xi0) > MULTIPLIER_CHECK_MAX_DIM:
        return 0.0, 0
    # one compiled program each (concrete values: a check before marching), not an XLA compile
    # per operation of the velocity map and of l's gradient run eagerly
    Q0, xi0 = np.asarray(Q0), np.asarray(xi0)
    A = np.asarray(_velocity_jacobian_compiled(system.velocity_map, Q0, xi0.shape))
    if not np.all(np.isfinite(A)):
        return 0.0, 0
    K = kernel_basis(A)
    if K.shape[1] == 0:
        return 0.0, 0
    g = np.asarray(_lagrangian_gradient(system, xi0, Q0)).reshape(-1)
    size = float(np.linalg.norm(g))
    if not np.all(np.isfinite(g)) or size == 0.0:
        return 0.0, K.shape[1]
    return float(np.linalg.norm(K.T @ g)) / size, K.shape[1]


_velocity_jacobian_compiled = filter_jit(velocity_jacobian, QUICK_COMPILE)
_lagrangian_gradient = filter_jit(lambda system, xi, Q: jax.grad(lambda x: system.l(x, Q))(xi), QUICK_COMPILE)


def check_initial_momentum(system, Q0, xi0, *, as_given: bool, stacklevel: int = 2) -> float:
    r"""Warn (`UserWarning`, naming `xi0`) when the momentum $\delta l/\delta\xi(\xi^0, Q^0)$ has a
    component that no multiplier gives (`momentum_defect` above `MULTIPLIER_RTOL`): the march
    would start from that momentum with the component removed, not from the one given.
    `as_given`: ξ⁰ is marched as given (a sweep or batch member), not first taken as its physical
    velocity (`physical_velocity`, which `integrate` does). Returns the relative defect."""
    defect, k = momentum_defect(system, Q0, xi0)
    if defect <= MULTIPLIER_RTOL:
        return defect
    if as_given:
        why = (
            "A sweep or batch marches xi0 as given; integrate alone takes it as the physical velocity L_xi0 Q0 "
            "(whose momentum has a multiplier) and can start elsewhere. Pass an xi0 without that component "
            "(e.g. integrate's Solution.xi[0]), or P0."
        )
    else:
        why = "Taking xi0 as its physical velocity L_xi0 Q0 did not remove it. Pass P0, or another xi0."
    warnings.warn(
        f"xi0: its momentum dl/dxi(xi0, Q0) has a component along the isotropy of Q0 (the {k}-dimensional "
        "kernel of xi -> L_xi Q0) that no initial multiplier gives (Lemma 7: dl/dxi = -P0<>Q0 is orthogonal "
        f"to that kernel), {defect:.3g} of its size. The run starts from the momentum of the minimum-norm "
        f"P0, which drops that component, not from the momentum of xi0. {why}",
        UserWarning,
        stacklevel=stacklevel,
    )
    return defect
