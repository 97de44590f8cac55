r"""Derivative maps $\phi_{\Delta t}(Q^{n+1}, Q^n)$ (Definitions 18 and 25).

A derivative map approximates $\dot Q$ at $Q^n$ from two successive points. Each map carries
its facts as data: `symmetric` (the map is self-adjoint, $-\phi_{\Delta t}(Q^n, Q^{n+1})$
equals the same map anchored at $Q^{n+1}$; this is what makes Example 30's integrator
second order) and, for matrix groups, the pair $(\overline{\log}, \overline{\exp})$.

The built-in maps also know the midpoint of a step, `at_midpoint(Q_next, Q, dt)` →
$(\bar Q, \bar\phi)$: a point halfway between $Q^n$ and $Q^{n+1}$ and the approximation of
$\dot Q$ there, which the midpoint principle (`scheme="midpoint"`) anchors the step at.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import jax

from . import linalg as _linalg
from .. import lie

__all__ = [
    "DerivativeMap",
    "VectorSpaceDifference",
    "MatrixGroupDifference",
    "CayleyDifference",
    "forward_difference",
    "cayley",
    "exponential",
    "so3_exponential",
]


class DerivativeMap:
    """Base class of the built-in derivative maps: a callable `phi(Q_next, Q, dt)`.

    Any Python callable with that signature is accepted by `ClebschSystem`; this class only
    adds facts that the engine and the tests read (`name`, `symmetric`).
    """

    name: str = "derivative map"
    symmetric: bool = False

    def __call__(self, Q_next: jax.Array, Q: jax.Array, dt: jax.Array) -> jax.Array:
        raise NotImplementedError

    # Subclasses that support `scheme="midpoint"` define
    # `at_midpoint(Q_next, Q, dt) -> (Q_mid, phi_mid)`, symmetric under swapping the two
    # points and negating dt: Q_mid unchanged, phi_mid unchanged.


@dataclasses.dataclass(frozen=True)
class VectorSpaceDifference(DerivativeMap):
    r"""Remark 21: $\phi_{\Delta t}(Q^{n+1}, Q^n) = (Q^{n+1} - Q^n)/\Delta t$ on a vector space.

    With the Definition 19 principle (`scheme="left"`) this gives symplectic Euler-A; with
    its adjoint, Remark 22 (`scheme="right"`), symplectic Euler-B.
    """

    name: str = "forward difference"
    symmetric: bool = False

    def __call__(self, Q_next, Q, dt):
        return (Q_next - Q) / dt

    def at_midpoint(self, Q_next, Q, dt):
        r"""The arithmetic midpoint and the difference quotient, $\dot Q$ there to O(Δt²)."""
        return 0.5 * (Q + Q_next), (Q_next - Q) / dt


@dataclasses.dataclass(frozen=True)
class MatrixGroupDifference(DerivativeMap):
    r"""Definition 25: $\phi_{\Delta t}(Q^{n+1}, Q^n) = Q^n\, \overline{\log}\big((Q^n)^{-1} Q^{n+1}\big) / \Delta t$.

    For velocity maps $\mathcal L_X Q = Q X$ (right multiplication). `log` and `exp` are an
    inverse pair $\overline{\log} = \overline{\exp}^{-1}$ approximating the matrix
    logarithm and exponential. $(Q^n)^{-1}$ is the group inverse computed by a linear solve,
    so the map is a smooth local diffeomorphism of $GL(n)$ in $Q^{n+1}$: the full march
    solves in ambient matrix coordinates, as in Section 4.1 of the paper.
    """

    log: Callable[[jax.Array], jax.Array]
    exp: Callable[[jax.Array], jax.Array]
    name: str = "matrix group"
    symmetric: bool = True
    exponential_pair: bool = False
    """Whether `log` is the principal matrix logarithm and `exp` the matrix exponential (on the
    group): the reduced march then evaluates its step with the closed form of the derivative
    of the logarithm (`clebsch_jax.discrete.reduction`) instead of differentiating `log`."""

    def __call__(self, Q_next, Q, dt):
        return Q @ self.log(_linalg.solve(Q, Q_next)) / dt

    def at_midpoint(self, Q_next, Q, dt):
        r"""$\bar Q = Q^n G^{1/2}$ with $G = (Q^n)^{-1}Q^{n+1}$ (the point halfway along the
        one-parameter subgroup from $Q^n$ to $Q^{n+1}$, principal square root) and
        $\bar\phi = \bar Q\,\overline{\log}(G)/\Delta t$: the same body velocity as
        `__call__`, transported to $\bar Q$."""
        G = _linalg.solve(Q, Q_next)
        Q_mid = Q @ lie.sqrtm(G)
        return Q_mid, Q_mid @ self.log(G) / dt


forward_difference = VectorSpaceDifference()
"""The vector-space forward difference of Remark 21."""


@dataclasses.dataclass(frozen=True)
class CayleyDifference(MatrixGroupDifference):
    r"""Definition 25 with the Cayley pair $\overline{\exp}(Y) = (I - Y/2)^{-1}(I + Y/2)$,
    $\overline{\log}(A) = 2(A + I)^{-1}(A - I)$ (Example 30). A type of its own because its
    logarithm has an explicit derivative: the reduced march evaluates its step in closed form
    (`clebsch_jax.discrete.reduction`) and forms a fresh Newton Jacobian at every solve."""

    log: Callable[[jax.Array], jax.Array] = lie.cayley_log
    exp: Callable[[jax.Array], jax.Array] = lie.cayley_exp
    name: str = "cayley"


cayley = CayleyDifference()
"""Definition 25 with the Cayley transform of Example 30 (the CAY integrator)."""

exponential = MatrixGroupDifference(log=lie.logm, exp=lie.expm, name="exponential", exponential_pair=True)
"""Definition 25 with the exact matrix logarithm/exponential (Definitions 23-24)."""

so3_exponential = MatrixGroupDifference(
    log=lie.logm, exp=lambda X: lie.so3_exp(lie.vee(X)), name="so3 exponential", exponential_pair=True
)
"""Definition 25 with the exact exponential on SO(3): Rodrigues' formula for exp (used by the
reduced march to reconstruct Q), the matrix logarithm for log (the full march solves in ambient
GL(3) coordinates, where log must be a local diffeomorphism, which a Rodrigues inverse is not).
Its X must lie in so(3)."""
