"""Diagnostics of a `Solution`: energy, momentum maps, Noether momenta, drift and order fits.

Quantities come from the trajectory by autodiff of the user's maps; nothing is written per
model. Functions taking a `Solution` map over its time axis and any batch axes.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from .discrete.legendre import cotangent_from_momentum
from .march.scan import energy_terms
from .march.solution import Solution
from .core.system import ClebschSystem

__all__ = [
    "node_energy",
    "energy",
    "body_momentum",
    "noether_momentum",
    "orthogonality_error",
    "relative_drift",
    "envelope_ratio",
    "fit_order",
]


def _over_nodes(fn, sol: Solution, *arrays):
    """vmap `fn` (defined on one node) over the time axis and the batch axes of `sol`."""
    for _ in range(sol.batch_ndim + 1):
        fn = jax.vmap(fn)
    return fn(*arrays)


def node_energy(system: ClebschSystem, Q, xi) -> jax.Array:
    r"""The energy $E = \langle \delta l/\delta\xi, \xi\rangle - l(\xi, Q)$ at one node."""
    pairing, lagrangian = energy_terms(system, Q, xi)
    return pairing - lagrangian


def energy(system: ClebschSystem, sol: Solution) -> jax.Array:
    r"""The energy $E = \langle \delta l/\delta\xi, \xi\rangle - l(\xi, Q)$ at every node.

    On solutions it equals the Hamiltonian of Lemma 8, $H = \langle P, \mathcal L_\xi Q\rangle
    - l$. Shape: batch axes + (N+1,).

    For a degenerate system (`sol.xi is None`) it is evaluated at $\xi = 0$, i.e.
    $E = -l(0, Q)$: exact when $l$ is affine in $\xi$ (Lagrangians linear in the velocity,
    such as point vortices, where $E$ is the Hamiltonian $H(Q)$), and meaningless otherwise.
    """

    def one(q, x):
        return node_energy(system, q, x)

    if sol.xi is None:  # degenerate: E does not depend on xi when l is affine in it
        zeros = jnp.zeros(sol.momentum.shape, sol.momentum.dtype)
        return _over_nodes(one, sol, sol.Q, zeros)
    if sol.Q is None:  # reduced march without reconstruction: l does not depend on Q
        return _over_nodes(lambda x: one(None, x), sol, sol.xi)
    return _over_nodes(one, sol, sol.Q, sol.xi)


def body_momentum(system: ClebschSystem, sol: Solution) -> jax.Array:
    r"""The momentum map $J = -p^n \diamond Q^n$ at every node (Theorem 12).

    For right multiplication on a matrix group this is the body momentum, whose Casimirs
    (e.g. $|J|^2$ on $SO(3)$) the integrator conserves. Shape: batch + (N+1,) + ξ's shape.
    """
    del system  # carried by the march in both forms (`Solution.momentum`)
    return sol.momentum


def noether_momentum(
    sol: Solution, generators: Callable[[jax.Array], jax.Array], system: ClebschSystem | None = None
) -> jax.Array:
    r"""Noether momenta $\langle p^n, Y_k(Q^n)\rangle$ of the discrete flow.

    `generators(Q)` returns shape (K, *Q.shape): K infinitesimal generators of a symmetry of
    the discrete action at one configuration Q. For the left action of $SO(3)$ on the rigid
    body, $Y_k(Q) = \hat e_k Q$ and the result is the spatial angular momentum. When the
    discrete Lagrangian is invariant these are conserved exactly by the discrete flow (discrete
    Noether theorem). Shape: batch + (N+1, K).
    """

    def one(q, p):
        Y = generators(q)
        return jnp.sum(Y * p[None], axis=tuple(range(1, Y.ndim)))

    if sol.Q is None:
        raise ValueError("sol: Noether momenta need the configurations; integrate with reconstruct=True.")
    if sol.p is None:
        if system is None:
            raise ValueError("system: needed to rebuild cotangent momenta from a reduced march.")
        # Reduced march: rebuild the part of pⁿ the velocity map sees, the minimum-norm p
        # with -p⋄Q = μ. Exact for generators tangent to the orbits of the velocity map
        # (e.g. the left action on a group acted on by right multiplication).
        p = _over_nodes(lambda q, mu: cotangent_from_momentum(system, q, mu), sol, sol.Q, sol.momentum)
        return _over_nodes(one, sol, sol.Q, p)
    return _over_nodes(one, sol, sol.Q, sol.p)


def orthogonality_error(Q: jax.Array) -> jax.Array:
    r"""$\max |Q^TQ - I|$ per matrix (for $SO(n)$ configurations); maps over leading axes."""
    eye = jnp.broadcast_to(jnp.eye(Q.shape[-1], dtype=Q.dtype), Q.shape)
    return jnp.max(jnp.abs(jnp.swapaxes(Q, -1, -2) @ Q - eye), axis=(-2, -1))


def relative_drift(values: jax.Array, axis: int = 0, *, feature_ndim: int = 0) -> jax.Array:
    r"""$\max_n \|v^n - v^0\|_\infty / \|v^0\|_\infty$ along the time `axis`.

    The trailing `feature_ndim` axes are one quantity (e.g. 1 for a momentum vector) and are
    reduced with the max-norm; any other axes are batch axes and are kept, so a batch gets
    one drift per member.
    """
    v = jnp.moveaxis(jnp.asarray(values), axis, 0)
    feat = tuple(range(v.ndim - feature_ndim, v.ndim))
    v0 = v[:1]
    scale = jnp.max(jnp.abs(v0), axis=(0,) + feat)
    scale = jnp.maximum(scale, jnp.finfo(v.dtype).tiny)
    dev = jnp.max(jnp.abs(v - v0), axis=(0,) + feat)
    return dev / scale


def envelope_ratio(error, fraction: float = 0.1) -> float:
    """Ratio of the error envelope (max |error|) over the last `fraction` of a run to that over
    the first (excluding the initial node, where the error is zero).

    Close to 1 when the error oscillates without secular drift; grows with the run when it
    drifts.
    """
    e = np.abs(np.asarray(error))
    k = max(1, int(len(e) * fraction))
    return float(np.max(e[-k:]) / max(np.max(e[1 : k + 1]), np.finfo(float).tiny))


def fit_order(dts, errors) -> float:
    """Slope of the least-squares fit of log(error) against log(dt): the measured order."""
    slope, _ = np.polyfit(np.log(np.asarray(dts, float)), np.log(np.asarray(errors, float)), 1)
    return float(slope)
