r"""Whether the reduced march applies (Theorem 27's hypotheses), read off the two maps: the
derivative map of Definition 25's form, and the velocity map right multiplication on a matrix
group, $\mathcal L_\xi Q = Q\,X(\xi)$, linear, injective and closed (Theorem 12). `find_reduction`
gives the verdict and, where it applies, what the reduced march needs: the algebra's basis and
its pseudo-inverse (`MatrixGroupReduction`), or nothing at all when ξ is itself the matrix
(`MatrixAlgebraReduction`); `matrix_group_basis` gives the basis alone (the model checks read
the group from it). The inspections are cached per map and shapes.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ..core import linalg as _linalg
from ..core.derivative_maps import CayleyDifference, MatrixGroupDifference
from ..core.jit import evaluate_now, memo
from ..core.representation import MatrixRepresentation, RealMatrices
from ..core.system import ClebschSystem
from ..core.validation import any_traced
from ..discrete.closure import CLOSURE_TOLERANCE

__all__ = ["MatrixGroupReduction", "MatrixAlgebraReduction", "find_reduction", "matrix_group_basis"]


@dataclasses.dataclass(frozen=True)
class MatrixGroupReduction(RealMatrices):
    """What the reduced march needs: the basis X(e_k) of the algebra and its pseudo-inverse.

    `basis` (m, n, n) and `pinv` (m, n·n) are NumPy constants (static: found once per system)."""

    basis: np.ndarray
    pinv: np.ndarray
    xi_shape: tuple

    def X(self, xi):
        return _constant_map(self.basis.reshape(self.basis.shape[0], -1).T, xi, self.basis.shape[1:])

    def X_inv(self, Y):
        return _constant_map(self.pinv, Y, self.xi_shape)

    def X_inv_adjoint(self, g):
        r"""The n×n matrix $P$ with $\langle P, M\rangle = g \cdot X^{-1}(M)$ for every M."""
        return _constant_map(self.pinv.T, g, self.basis.shape[1:])

    def X_adjoint(self, M):
        r"""$X^T$: the vector $(\langle X(e_k), M\rangle)_k$ (Frobenius pairing), of ξ's shape."""
        return _constant_map(self.basis.reshape(self.basis.shape[0], -1), M, self.xi_shape)

    def __hash__(self):
        return hash((self.basis.tobytes(), self.xi_shape))

    def __eq__(self, other):
        return (
            isinstance(other, MatrixGroupReduction)
            and self.xi_shape == other.xi_shape
            and np.array_equal(self.basis, other.basis)
        )


@dataclasses.dataclass(frozen=True)
class MatrixAlgebraReduction(RealMatrices):
    r"""The reduction when ξ *is* the matrix: $\mathcal L_\xi Q = Q\xi$ with ξ of Q's shape
    (n, n), so $X$ is the identity and the algebra is all of $\mathfrak{gl}(n)$ — closed with
    no check (Theorem 12). Nothing of size $(\dim V)^2$ is formed: $X$, $X^{-1}$ and their
    adjoints are the identity, and the Cayley step is written with n×n products
    (`_cayley_step`). A system whose data lie in a subalgebra (the Euler–Zeitlin fluid on
    $\mathfrak u(N)$) stays in it when its Lagrangian's gradient maps the subalgebra to itself."""

    n: int

    @property
    def xi_shape(self):
        return (self.n, self.n)

    def X(self, xi):
        return xi

    X_inv = X_adjoint = X_inv_adjoint = X


MATRIX_ALGEBRA_POINTS = 2
r"""Random (ξ, G) pairs at which `_matrix_algebra` checks $\mathcal L_\xi G = G\xi$."""


def _matrix_algebra(system: ClebschSystem, Q0, xi0) -> MatrixAlgebraReduction | None:
    r"""A `MatrixAlgebraReduction` when ξ and Q are n×n and the velocity map is $Q\xi$ at
    `MATRIX_ALGEBRA_POINTS` random pairs (ξ, G) (a map linear in ξ that is right
    multiplication by ξ itself there is so everywhere but on a set of measure zero, and
    `integrate`'s model checks test the linearity); None otherwise. O(n³) work: no basis."""
    shape = tuple(np.shape(Q0))
    if len(shape) != 2 or shape[0] != shape[1] or tuple(np.shape(xi0)) != shape:
        return None
    n = shape[0]
    rng = np.random.default_rng(11)
    xis = rng.normal(size=(MATRIX_ALGEBRA_POINTS, n, n))
    Gs = np.eye(n) + 0.3 * rng.normal(size=(MATRIX_ALGEBRA_POINTS, n, n))
    values = evaluate_now(jax.vmap(system.velocity_map), xis, Gs)
    if values is None:
        return None
    values = np.asarray(values)
    expected = Gs @ xis
    if np.max(np.abs(values - expected)) > 1e-12 * max(float(np.max(np.abs(expected))), 1.0):
        return None
    return MatrixAlgebraReduction(n=n)


def _constant_map(C: np.ndarray, x, shape):
    """C @ ravel(x) reshaped to `shape`, for a constant (NumPy) matrix C.

    The maps X, X⁻¹ and their adjoints are such constants, and sparse (so(3): two nonzeros per
    row). Written as the sums over C's nonzero entries, they are a few scalar multiply-adds
    that XLA fuses with their neighbours, instead of an unfused matrix-vector product (entries
    below 1e-14·max|C|, the round-off of a pseudo-inverse, count as zero). (Written instead as
    Σⱼ xⱼ·C[:, j], dense, XLA fuses the result into every product that uses it and recomputes
    it there, which costs more under `vmap` than it saves: `benchmarks/README.md`, "Notes:
    making the reduced step cheap".)"""
    v = jnp.ravel(x)
    cut = 1e-14 * np.max(np.abs(C))
    rows = [_linalg.weighted_sum(((float(c), v[j]) for j, c in enumerate(row) if abs(c) > cut), v.dtype) for row in C]
    return jnp.stack(rows).reshape(shape)


_CACHE: dict = {}
"""The reduction's inspections of a map (`clebsch_jax.core.jit.memo`, at most 256)."""


def _memo(key, compute):
    return memo(_CACHE, key, compute, 256)


def find_reduction(
    system: ClebschSystem, Q0, xi0
) -> tuple[MatrixGroupReduction | MatrixAlgebraReduction | MatrixRepresentation | None, str]:
    """`_find_reduction`, cached: the verdict depends only on the two maps and the shapes."""
    if any_traced(system.velocity_map):
        return _find_reduction(system, Q0, xi0)
    key = (
        "reduction",
        system.velocity_map,
        system.derivative_map,
        system.has_potential,
        tuple(np.shape(Q0)),
        tuple(np.shape(xi0)),
    )
    return _memo(key, lambda: _find_reduction(system, Q0, xi0))


def _find_reduction(system: ClebschSystem, Q0, xi0) -> tuple[MatrixGroupReduction | None, str]:
    # evaluated now even inside a user's jit (`evaluate_now`): only the maps and the shapes matter here
    return _inspect(system, Q0, xi0)


def _inspect(system: ClebschSystem, Q0, xi0) -> tuple[MatrixGroupReduction | None, str]:
    r"""Decide whether the reduced march applies; returns `(reduction or None, reason)`.

    It applies when (1) the derivative map is a `MatrixGroupDifference` (Definition 25),
    (2) Q is a square matrix and the velocity map is right multiplication, linear in ξ,
    $\mathcal L_\xi G = G\,\mathcal L_\xi I$ (checked at fixed random matrices G and a random ξ,
    `_group_basis`), and (3) the velocity map is closed (Theorem 12: the commutators of its
    basis in its span), so that $X(V)$ is a Lie algebra. When ξ is itself the n×n matrix
    ($\mathcal L_\xi Q = Q\xi$, `_matrix_algebra`) (2) and (3) hold with $X$ the identity and no
    basis is formed: a `MatrixAlgebraReduction`, which scales to $\dim V = n^2$ in the
    thousands. A velocity map that is a `MatrixRepresentation` is not inspected: it states
    (2) and (3) and is its own reduction (`_declared`).
    """
    if not isinstance(system.derivative_map, MatrixGroupDifference):
        return None, "the derivative map is not a matrix-group map (Definition 25)"
    if isinstance(system.velocity_map, MatrixRepresentation):
        return _declared(system, Q0, xi0)
    algebra = _matrix_algebra(system, Q0, xi0)
    if algebra is not None:
        return algebra, "applies"
    basis, reason = _cached_group_basis(system, Q0, xi0)
    if basis is None:
        return None, reason
    m = basis.shape[0]
    B = basis.reshape(m, -1).T
    return MatrixGroupReduction(basis=basis, pinv=np.linalg.pinv(B), xi_shape=tuple(np.shape(xi0))), "applies"


def _declared(system: ClebschSystem, Q0, xi0) -> tuple[MatrixRepresentation | None, str]:
    r"""A velocity map that is a `MatrixRepresentation` declares its group and how the reduced
    step computes with it (closure is its own statement): checked here are only what the
    reduced step written with it covers — the Cayley map for a representation in another form
    than the real one (the other maps' logarithms are real), a Lagrangian without potential,
    and ξ of the representation's shape."""
    rep = system.velocity_map
    if tuple(np.shape(xi0)) != tuple(rep.xi_shape):
        return None, f"xi has shape {tuple(np.shape(xi0))}, the representation {rep!r} takes {tuple(rep.xi_shape)}"
    if rep.ambient_complex and not isinstance(system.derivative_map, CayleyDifference):
        return None, f"the representation {rep!r} computes in complex matrices, for the Cayley map only"
    if system.has_potential:
        return None, f"the representation {rep!r} takes a Lagrangian without potential, l(xi)"
    return rep, "applies"


def matrix_group_basis(system: ClebschSystem, Q0, xi0) -> np.ndarray | None:
    r"""The basis $X(e_k)$, shape (dim V, n, n), of the Lie algebra by which the velocity map
    moves Q when it is right multiplication on a matrix group, $\mathcal L_\xi Q = Q\,X(\xi)$,
    with $X$ injective and closed (Theorem 12); None otherwise (or when the velocity map depends
    on traced values). Cached like `find_reduction`: it depends only on the map and the shapes."""
    if any_traced(system.velocity_map):
        return None
    return _cached_group_basis(system, Q0, xi0)[0]


def _cached_group_basis(system: ClebschSystem, Q0, xi0) -> tuple[np.ndarray | None, str]:
    """`_group_basis`, cached per velocity map and shapes when the map holds no traced values
    (shared by the reduction's inspection and `matrix_group_basis`: one evaluation each)."""
    if any_traced(system.velocity_map):
        return _group_basis(system, Q0, xi0)
    key = ("basis", system.velocity_map, tuple(np.shape(Q0)), tuple(np.shape(xi0)))
    return _memo(key, lambda: _group_basis(system, Q0, xi0))


def _group_basis(system: ClebschSystem, Q0, xi0) -> tuple[np.ndarray | None, str]:
    r"""Conditions (2) and (3) of `_inspect`: the basis X(e_k), or None and the reason.

    (2) is checked where one program evaluates the map: at the identity on the basis of V (the
    basis $X(e_k) = \mathcal L_{e_k} I$), at `RIGHT_POINTS` random matrices G on that basis
    ($\mathcal L_{e_k} G = G X(e_k)$) and on a random ξ (the map linear in ξ, Definition 1).
    (3) then needs no more evaluations of the map: the vector fields $Q \mapsto Q X$ are
    left-invariant, their bracket is $Q\,[X(e_i), X(e_j)]$, so the velocity map is closed
    (Theorem 12) exactly when every commutator $[X(e_i), X(e_j)]$ lies in the span of the basis:
    a least-squares fit in NumPy, with `check_closure`'s tolerance on its relative residual."""
    shape = tuple(np.shape(Q0))
    if len(shape) != 2 or shape[0] != shape[1]:
        return None, f"Q is not a square matrix (shape {shape})"
    n = shape[0]
    xi_shape = tuple(np.shape(xi0))
    m = int(np.prod(xi_shape)) if xi_shape else 1
    rng = np.random.default_rng(7)
    Gs = np.eye(n) + 0.3 * rng.normal(size=(RIGHT_POINTS, n, n))
    E = np.concatenate([np.eye(m), rng.normal(size=(1, m))]).reshape((m + 1,) + xi_shape)
    # one compiled program for all evaluations (op-by-op evaluation compiles every operation)
    points = np.concatenate([np.eye(n)[None], Gs])
    values = evaluate_now(
        lambda E, Q: jax.vmap(lambda q: jax.vmap(lambda e: system.velocity_map(e, q))(E))(Q), E, points
    )
    if values is None:
        return None, "the velocity map depends on traced values, so it cannot be inspected"
    values = np.asarray(values)  # split on the host (unstacking the device array compiles a program)
    basis, random = values[0, :m], values[:, m]
    scale = max(float(np.max(np.abs(values))), 1.0)
    if np.max(np.abs(values[1:, :m] - Gs[:, None] @ basis)) > 1e-12 * scale:
        return None, "the velocity map is not right multiplication Q·X(xi)"
    if np.max(np.abs(random - points @ np.einsum("k,kij->ij", E[m].ravel(), basis))) > 1e-12 * scale:
        return None, "the velocity map is not linear in xi"
    B = basis.reshape(m, n * n).T
    if np.linalg.matrix_rank(B) < m:
        return None, "xi -> X(xi) is not injective"
    worst = _commutator_residual(basis, B)
    if worst > CLOSURE_TOLERANCE:
        return None, f"the velocity map is not closed (residual {worst:.1e})"
    return basis, "applies"


RIGHT_POINTS = 3
"""Random matrices at which `_group_basis` checks that the velocity map is right multiplication."""


def _commutator_residual(basis: np.ndarray, B: np.ndarray) -> float:
    """The largest relative residual of the least-squares fits of the commutators
    $[X_i, X_j]$ (i < j) in the span of the basis (the columns of `B`)."""
    m = basis.shape[0]
    C = np.stack(
        [(basis[i] @ basis[j] - basis[j] @ basis[i]).ravel() for i in range(m) for j in range(i + 1, m)]
        or [np.zeros(B.shape[0])],
        axis=1,
    )
    fit, *_ = np.linalg.lstsq(B, C, rcond=None)
    size = max(float(np.linalg.norm(C, axis=0).max()), float(np.linalg.norm(B)), np.finfo(float).tiny)
    return float(np.max(np.linalg.norm(B @ fit - C, axis=0)) / size)
