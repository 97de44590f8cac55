r"""Planar point vortices: a Clebsch system with a Lagrangian linear in the velocities.

N vortices of circulations $\Gamma_a$ at $Q_a = (x_a, y_a)$ have the Hamiltonian

$$ H(Q) = -\frac{1}{4\pi} \sum_{a<b} \Gamma_a\Gamma_b \log |Q_a - Q_b|^2 $$

and move by $\Gamma_a \dot x_a = \partial H/\partial y_a$, $\Gamma_a \dot y_a = -\partial H/\partial x_a$
(a positive circulation turns its neighbours counter-clockwise). These are the Euler–Lagrange
equations of the phase-space Lagrangian

$$ l(\xi, Q) = \tfrac12 \sum_a \Gamma_a\, \xi_a \times Q_a - H(Q), \qquad \xi_a \times Q_a = \xi_{a,x} y_a - \xi_{a,y} x_a , $$

with $\xi$ the (N, 2) array of velocities, the velocity map $\mathcal L_\xi Q = \xi$ (translations)
and the vector-space derivative map. $l$ is linear in $\xi$, so the system is degenerate
(`ClebschSystem(..., degenerate=True)`) and `integrate` uses the midpoint principle, which here is
the implicit midpoint rule. Nothing about the update is written by hand: the engine
differentiates $l$.

The companion functions take `(circulations, Q)` with `Q` of shape (..., N, 2) (any leading axes,
e.g. time and batch) and are differentiable and vmappable.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.tree_util import Partial

from ..core.derivative_maps import DerivativeMap, forward_difference
from ..core.system import ClebschSystem
from ..core.validation import is_traced, nan_unless

__all__ = [
    "point_vortices",
    "vortex_hamiltonian",
    "vortex_velocity",
    "vortex_linear_impulse",
    "vortex_angular_impulse",
    "checked_circulations",
    "on_configurations",
]


def _hamiltonian(gamma: jax.Array, Q: jax.Array) -> jax.Array:
    """H for one configuration (N, 2); pairwise terms vectorised, no loop over vortices.

    Written with the coordinates apart, (N, N) arrays only: XLA on the CPU runs its gradient
    (the vortex velocities, what every step evaluates) much faster this way than with the
    (N, N, 2) differences summed over their last axis (the measurement: `benchmarks/README.md`,
    "Measurements behind the engine's choices")."""
    x, y = Q[:, 0], Q[:, 1]
    dx, dy = x[:, None] - x[None, :], y[:, None] - y[None, :]
    r2 = dx * dx + dy * dy + jnp.eye(Q.shape[0], dtype=Q.dtype)  # the diagonal is log 1 = 0, zero gradient
    pair = gamma[:, None] * gamma[None, :] * jnp.log(r2)
    return -jnp.sum(pair) / (8.0 * jnp.pi)  # each pair a<b appears twice


def _lagrangian(gamma: jax.Array, xi: jax.Array, Q: jax.Array) -> jax.Array:
    cross = xi[:, 0] * Q[:, 1] - xi[:, 1] * Q[:, 0]
    return 0.5 * jnp.sum(gamma * cross) - _hamiltonian(gamma, Q)


def _translation(xi: jax.Array, Q: jax.Array) -> jax.Array:
    del Q
    return xi


def checked_circulations(circulations, *, nonzero: bool = False) -> jax.Array:
    """`circulations` as a float array (N,), checked when concrete: finite, and with `nonzero`
    no zero entry (a vortex of zero circulation drops out of l: its velocity is not determined
    and the step's Newton matrix is singular). Negative circulations are meaningful (opposite
    spin). When traced (under `jax.jit`/`jax.vmap`, in `cj.sweep`) circulations with a zero entry
    are made NaN, which `integrate` reports as `Status.INVALID_INPUT` at step 0."""
    gamma = jnp.asarray(circulations, dtype=jnp.result_type(float))
    if gamma.ndim != 1 or gamma.shape[0] < 1:
        raise ValueError(f"circulations: expected a 1-D array of N >= 1 circulations, got shape {gamma.shape}.")
    if not is_traced(gamma):
        values = np.asarray(gamma)
        if not np.all(np.isfinite(values)):
            raise ValueError(f"circulations: must be finite, got {values.tolist()}.")
        if nonzero and np.any(values == 0):
            raise ValueError(
                f"circulations: must be nonzero: vortex {int(np.argmax(values == 0))} has zero "
                "circulation, which leaves its motion undetermined by the Lagrangian (a passive "
                "tracer is not a point vortex); negative circulations are fine."
            )
    elif nonzero:
        gamma = nan_unless(gamma, jnp.all(gamma != 0))  # reported by integrate as Status.INVALID_INPUT
    return gamma


COINCIDENT_RTOL = float(np.finfo(np.float64).eps)
"""Two vortices coincide when their positions differ by at most this times the configuration's
size (the largest coordinate, at least 1) in every coordinate: equal to round-off."""


def coincident_pairs(xs, block: int = 4096) -> tuple[int, int, int] | None:
    """The first (configuration, a, b), a < b, of a stack `xs` (B, N, d) of vortex positions
    whose vortices a and b coincide (`COINCIDENT_RTOL`), or None. NaN never coincides. Checked
    `block` configurations at a time (the pairwise gaps of a whole sweep's stack could be large)."""
    xs = np.asarray(xs, dtype=np.float64)
    if xs.ndim != 3 or xs.shape[1] < 2:
        return None
    for start in range(0, xs.shape[0], block):
        x = xs[start : start + block]
        with np.errstate(invalid="ignore"):
            gap = np.max(np.abs(x[:, :, None, :] - x[:, None, :, :]), axis=-1)  # (block, N, N)
            scale = np.maximum(1.0, np.max(np.abs(x), axis=(1, 2)))[:, None, None]
            same = np.triu(gap <= COINCIDENT_RTOL * scale, k=1)
        if np.any(same):
            j, a, b = (int(i) for i in np.argwhere(same)[0])
            return start + j, a, b
    return None


def _coincident_sentence(x, a: int, b: int) -> str:
    where = ", ".join(f"{v:.6g}" for v in np.asarray(x, np.float64))
    return (
        f"vortices {a} and {b} coincide (both at ({where})): the configuration is singular (the "
        "Hamiltonian's log|x_a - x_b| and the velocities are infinite there), so no time step can march "
        "it. Give distinct positions."
    )


def distinct_check(positions=None):
    """A `check_Q` (with its `batched` and `traced` forms) refusing coincident vortices; the
    configuration's positions are `positions(Q)` ((…, N, d); None: Q itself)."""
    at = (lambda Q: Q) if positions is None else positions

    def check_distinct(Q) -> str | None:
        found = check_distinct.batched(np.asarray(Q)[None])
        return None if found is None else found[1]

    def batched(Qs) -> tuple[int, str] | None:
        x = np.asarray(Qs if positions is None else positions(jnp.asarray(Qs)), dtype=np.float64)
        found = coincident_pairs(x)
        if found is None:
            return None
        j, a, b = found
        return j, _coincident_sentence(x[j, a], a, b)

    def traced(Q) -> jax.Array:
        x = at(jnp.asarray(Q))
        gap = jnp.max(jnp.abs(x[:, None, :] - x[None, :, :]), axis=-1)
        scale = jnp.maximum(1.0, jnp.max(jnp.abs(x)))
        off_diagonal = ~jnp.eye(x.shape[0], dtype=bool)
        return ~jnp.any(off_diagonal & (gap <= COINCIDENT_RTOL * scale))

    check_distinct.batched, check_distinct.traced = batched, traced
    return check_distinct


check_distinct_vortices = distinct_check()
"""`point_vortices`' `check_Q`: None unless two vortices coincide (`COINCIDENT_RTOL`), else a
sentence naming the pair; `.batched` checks a stack for `cj.sweep`, `.traced` a member under
`jax.jit`/`jax.vmap` (`Status.INVALID_INPUT`)."""


def point_vortices(circulations, derivative_map: DerivativeMap = forward_difference) -> ClebschSystem:
    r"""N planar point vortices as a degenerate Clebsch system (see the module docstring).

    - `circulations`: shape (N,), finite and nonzero, of either sign (an array leaf: `vmap`
      over it to sweep; a concrete value is checked, a `ValueError` naming `circulations`,
      while under `jax.jit`/`jax.vmap` a bad one is reported as `Status.INVALID_INPUT`);
    - Q: positions, shape (N, 2); ξ: velocities, shape (N, 2);
    - `derivative_map`: a vector-space map with a midpoint (default
      `clebsch_jax.forward_difference`).

    `integrate(point_vortices(G), Q0, vortex_velocity(G, Q0), dt=..., n_steps=...)` runs the
    midpoint principle: one step is the implicit midpoint rule, which conserves the linear and
    angular impulses (`vortex_linear_impulse`, `vortex_angular_impulse`) to round-off and keeps
    H (`vortex_hamiltonian`) bounded. `Solution.xi` is None (the Legendre map is degenerate);
    `Solution.xi_step` are the velocities at the step midpoints.

    Coincident vortices (a singular configuration) are refused before compiling, naming the pair
    (`check_distinct_vortices`, the system's `check_Q`; under `jax.jit`/`jax.vmap`
    `Status.INVALID_INPUT`).
    """
    gamma = checked_circulations(circulations, nonzero=True)
    return ClebschSystem(
        lagrangian=Partial(_lagrangian, gamma),
        velocity_map=_translation,
        derivative_map=derivative_map,
        degenerate=True,
        check_Q=check_distinct_vortices,
    )


def on_configurations(fn, circulations, Q, dim: int = 2, name: str = "Q", distinct: bool = False):
    """`fn(circulations, q)` on every configuration q (N, `dim`) of `Q` (..., N, `dim`), vmapped.
    With `distinct`, a concrete `Q` with coincident vortices (where `fn` is infinite) is refused."""
    gamma = checked_circulations(circulations)
    Q = jnp.asarray(Q, dtype=jnp.result_type(float))
    if Q.ndim < 2 or Q.shape[-2:] != (gamma.shape[0], dim):
        raise ValueError(
            f"{name}: expected shape (..., {gamma.shape[0]}, {dim}) for {gamma.shape[0]} vortices, got {Q.shape}."
        )
    flat = Q.reshape((-1,) + Q.shape[-2:])
    found = None if is_traced(flat) or not distinct else coincident_pairs(flat)
    if found is not None:
        j, a, b = found
        at = f"[{', '.join(str(int(i)) for i in np.unravel_index(j, Q.shape[:-2]))}]" if Q.ndim > 2 else ""
        raise ValueError(f"{name}{at}: " + _coincident_sentence(np.asarray(flat[j, a]), a, b))
    out = jax.vmap(lambda q: fn(gamma, q))(flat)
    return out.reshape(Q.shape[:-2] + out.shape[1:])


def vortex_hamiltonian(circulations, Q) -> jax.Array:
    r"""$H(Q) = -\frac{1}{4\pi}\sum_{a<b}\Gamma_a\Gamma_b\log|Q_a - Q_b|^2$; shape of Q's leading axes."""
    return on_configurations(_hamiltonian, circulations, Q)


def _velocity(gamma, Q):
    g = jax.grad(_hamiltonian, argnums=1)(gamma, Q)
    return jnp.stack([g[:, 1], -g[:, 0]], axis=-1) / gamma[:, None]


def vortex_velocity(circulations, Q) -> jax.Array:
    r"""The velocities $\dot Q_a = (\partial H/\partial y_a, -\partial H/\partial x_a)/\Gamma_a$ at
    positions Q (by autodiff of H): the consistent initial `xi0` for `integrate`, and the
    right-hand side for a reference ODE solve. Shape of Q. Coincident vortices are refused (a
    `ValueError` naming the pair)."""
    return on_configurations(_velocity, circulations, Q, distinct=True)


def vortex_linear_impulse(circulations, Q) -> jax.Array:
    r"""$\sum_a \Gamma_a Q_a$, shape (..., 2). Conserved (translation invariance of H)."""
    return on_configurations(lambda g, q: jnp.sum(g[:, None] * q, axis=0), circulations, Q)


def vortex_angular_impulse(circulations, Q) -> jax.Array:
    r"""$\sum_a \Gamma_a |Q_a|^2$. Conserved (rotation invariance of H)."""
    return on_configurations(lambda g, q: jnp.sum(g * jnp.sum(q * q, axis=-1)), circulations, Q)
