r"""The scenes `vortices`, `peakons` and `landmarks`: their initial data, invariants, trajectories,
plots, and the exact two-peakon solution the `peakons` scene is checked against."""

from __future__ import annotations


import jax.numpy as jnp
import numpy as np

from clebsch_jax.models import (
    landmark_angular_momentum,
    landmark_velocity,
    landmarks,
    peakon_velocity,
    peakons,
    point_vortices,
    vortex_angular_impulse,
    vortex_linear_impulse,
    vortex_velocity,
)

from ._scene_types import Invariant, Scene, Setup

__all__ = ["VORTICES", "PEAKONS", "LANDMARKS", "VORTEX_CIRCULATIONS", "two_peakons"]


# --------------------------------------------------------------------------------------------
# vortices: four point vortices, two leapfrogging pairs (degenerate: midpoint principle).

VORTEX_CIRCULATIONS = (1.0, -1.0, 1.0, -1.0)
VORTEX_Q0 = ((0.0, 1.0), (0.0, -1.0), (0.0, 0.5), (0.0, -0.5))


def _vortex_system():
    return point_vortices(jnp.asarray(VORTEX_CIRCULATIONS))


def _vortex_setup(batch, rng):
    Q0 = np.asarray(VORTEX_Q0)[None] + 0.03 * rng.normal(size=(batch, 4, 2))
    Q0[0] = VORTEX_Q0
    xi0 = np.asarray(vortex_velocity(jnp.asarray(VORTEX_CIRCULATIONS), jnp.asarray(Q0)))
    return Setup(Q0=Q0, xi0=xi0, P0=None, members={"Q0": Q0.tolist()})


def _linear_impulse(system, sol):
    return vortex_linear_impulse(jnp.asarray(VORTEX_CIRCULATIONS), sol.Q)


def _linear_impulse_scale(system, sol):  # Σ|Γ_a||Q_a| at node 0: the size of the terms summed
    return jnp.sum(jnp.abs(jnp.asarray(VORTEX_CIRCULATIONS)) * jnp.linalg.norm(sol.Q[0], axis=-1))


def _angular_impulse(system, sol):
    return vortex_angular_impulse(jnp.asarray(VORTEX_CIRCULATIONS), sol.Q)


def _angular_impulse_scale(system, sol):  # Σ|Γ_a||Q_a|² at node 0
    return jnp.sum(jnp.abs(jnp.asarray(VORTEX_CIRCULATIONS)) * jnp.sum(sol.Q[0] ** 2, axis=-1))


def _vortex_trajectory(system, sol):
    return sol.Q


def _vortex_plot(ax, ts, traj, setup, colors):
    for m, (curves, col) in enumerate(zip(traj, colors)):
        for a, g in enumerate(VORTEX_CIRCULATIONS):
            ax.plot(curves[:, a, 0], curves[:, a, 1], color=col, lw=0.7, ls="-" if g > 0 else "--")
            ax.plot(curves[:1, a, 0], curves[:1, a, 1], "o" if g > 0 else "s", color=col, ms=3)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.set_title("vortex paths (solid: $\\Gamma = +1$, dashed: $\\Gamma = -1$)", fontsize=10)


# --------------------------------------------------------------------------------------------
# peakons: two Camassa-Holm peakons overtaking, against the exact solution.

PEAKON_WIDTH = 1.0
PEAKON_OVERTAKE = (2.0, 1.0, 3.0, 0.0)  # (c1, c2, t0, X0): speeds 2 and 1, interaction at t = 3


def two_peakons(t, c1, c2, t0, X0):
    r"""Exact positions and momenta of two overtaking Camassa–Holm peakons (width 1).

    For $H = \tfrac12\sum_{a,b}p_ap_be^{-|q_a-q_b|}$ with $q_1 < q_2$ and asymptotic speeds
    $c_1 > c_2 > 0$: $\Sigma = c_1 + c_2 = p_1 + p_2$ and $\Delta = c_1 - c_2$ are conserved;
    with $\tau = t - t_0$, $r = q_2 - q_1 = \log\big((c_1^2 + c_2^2 + 2c_1c_2\cosh\Delta\tau)/\Delta^2\big)$,
    $q_1 + q_2 = X_0 + \Sigma\tau + 2\,\mathrm{artanh}\big((\Delta/\Sigma)\tanh(\Delta\tau/2)\big)$ and
    $p_1 - p_2 = -\Delta\tanh(\Delta\tau/2)$. The faster peakon starts behind; at $t_0$ the
    momenta are equal; afterwards they are exchanged.

    **Arguments:** `t` (any shape); scalars or arrays broadcasting with `t`.
    **Returns:** `(q, p)`, each of shape `broadcast(t).shape + (2,)`.
    """
    t = np.asarray(t, float)
    D, S = c1 - c2, c1 + c2
    tau = t - t0
    r = np.log((c1**2 + c2**2 + 2 * c1 * c2 * np.cosh(D * tau)) / D**2)
    X = X0 + S * tau + 2 * np.arctanh((D / S) * np.tanh(D * tau / 2))
    s = -D * np.tanh(D * tau / 2)
    return np.stack([(X - r) / 2, (X + r) / 2], -1), np.stack([(S + s) / 2, (S - s) / 2], -1)


def _peakon_system():
    return peakons(PEAKON_WIDTH)


def _peakon_setup(batch, rng):
    c1 = rng.uniform(1.6, 2.4, batch)
    c2 = rng.uniform(0.6, 1.2, batch)
    t0 = rng.uniform(2.0, 4.0, batch)
    X0 = rng.uniform(-1.0, 1.0, batch)
    c1[0], c2[0], t0[0], X0[0] = PEAKON_OVERTAKE
    q0, p0 = two_peakons(0.0, c1, c2, t0, X0)
    xi0 = np.asarray(peakon_velocity(jnp.asarray(q0), jnp.asarray(p0), PEAKON_WIDTH))
    members = {"c1": c1.tolist(), "c2": c2.tolist(), "t0": t0.tolist(), "X0": X0.tolist()}
    return Setup(Q0=q0, xi0=xi0, P0=p0, members=members)


def _total_momentum_1d(system, sol):
    return jnp.sum(sol.momentum, axis=-1)  # Solution.momentum is pⁿ itself (translations)


def _abs_momentum_scale_1d(system, sol):
    return jnp.sum(jnp.abs(sol.momentum[0]))


def _peakon_trajectory(system, sol):
    return jnp.stack([sol.Q, sol.momentum], axis=-2)  # (N+1, 2, n_peakons): positions, momenta


def _peakon_reference(members, ts, traj):
    """max_a |q_a − q_a^exact| at every node, (B, S)."""
    c1, c2, t0, X0 = (np.asarray(members[k])[:, None] for k in ("c1", "c2", "t0", "X0"))
    q, _ = two_peakons(np.asarray(ts)[None, :], c1, c2, t0, X0)
    return np.max(np.abs(traj[:, :, 0, :] - q), axis=-1)


def _peakon_plot(ax, ts, traj, setup, colors):
    members = setup.members
    for m, (curves, col) in enumerate(zip(traj, colors)):
        q_ex, _ = two_peakons(ts, members["c1"][m], members["c2"][m], members["t0"][m], members["X0"][m])
        for a in range(curves.shape[-1]):
            ax.plot(curves[:, 0, a], ts, color=col, lw=1.0 if a == 0 else 0.7)
            ax.plot(q_ex[:, a], ts, color="k", lw=0.6, ls=":")
    ax.set_xlabel("position q")
    ax.set_ylabel("t")
    ax.set_title("peak positions (dotted: exact solution)", fontsize=10)


# --------------------------------------------------------------------------------------------
# landmarks: three Gaussian landmarks in the plane.

LANDMARK_WIDTH = 0.8
LANDMARK_Q0 = ((-1.0, 0.2), (0.9, -0.1), (0.1, 1.1))
LANDMARK_P0 = ((0.46, -0.76), (0.22, 0.92), (-0.68, -0.16))  # swirling, slightly inward


def _landmark_system():
    return landmarks(LANDMARK_WIDTH)


def _landmark_setup(batch, rng):
    Q0 = np.asarray(LANDMARK_Q0)[None] + 0.1 * rng.normal(size=(batch, 3, 2))
    P0 = np.asarray(LANDMARK_P0)[None] + 0.1 * rng.normal(size=(batch, 3, 2))
    Q0[0], P0[0] = LANDMARK_Q0, LANDMARK_P0
    xi0 = np.asarray(landmark_velocity(jnp.asarray(Q0), jnp.asarray(P0), LANDMARK_WIDTH))
    return Setup(Q0=Q0, xi0=xi0, P0=P0, members={"Q0": Q0.tolist(), "P0": P0.tolist()})


def _total_momentum_2d(system, sol):
    return jnp.sum(sol.momentum, axis=-2)


def _abs_momentum_scale_2d(system, sol):
    return jnp.sum(jnp.linalg.norm(sol.momentum[0], axis=-1))


def _landmark_angular(system, sol):
    return landmark_angular_momentum(sol.Q, sol.momentum)


def _landmark_angular_scale(system, sol):  # Σ|q_a||p_a| at node 0
    return jnp.sum(jnp.linalg.norm(sol.Q[0], axis=-1) * jnp.linalg.norm(sol.momentum[0], axis=-1))


def _landmark_trajectory(system, sol):
    return sol.Q


def _landmark_plot(ax, ts, traj, setup, colors):
    for curves, col in zip(traj, colors):
        for a in range(curves.shape[1]):
            ax.plot(curves[:, a, 0], curves[:, a, 1], color=col, lw=0.8)
            ax.plot(curves[:1, a, 0], curves[:1, a, 1], "o", color=col, ms=3)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.set_title("landmark paths (dots: start)", fontsize=10)


# --------------------------------------------------------------------------------------------
# The scenes.

VORTICES = Scene(
    name="vortices",
    description="four point vortices, two leapfrogging pairs (midpoint principle)",
    details="Circulations (1, -1, 1, -1) at (0, +-1), (0, +-0.5): a degenerate Lagrangian, so "
    "the midpoint principle (the implicit midpoint rule). With --batch B the others "
    "are jittered copies (positions + 0.03 N(0, 1)). Reports the linear and angular "
    "impulses (relative to the sums of |terms|) and H as the energy.",
    model="point_vortices(circulations=(1, -1, 1, -1))",
    system=_vortex_system,
    setup=_vortex_setup,
    dt=0.02,
    steps=3000,
    quick_steps=400,
    quick_batch=4,
    invariants=(
        Invariant("linear_impulse", "linear impulse", _linear_impulse, scale=_linear_impulse_scale),
        Invariant("angular_impulse", "angular impulse", _angular_impulse, scale=_angular_impulse_scale),
    ),
    trajectory=_vortex_trajectory,
    plot=_vortex_plot,
)


PEAKONS = Scene(
    name="peakons",
    description="two Camassa-Holm peakons overtaking (speeds 2, 1), against the exact solution",
    details="Width 1, midpoint principle, the order-keeping forward difference. Every member "
    "is an exact two-peakon solution (the others: random speeds c1 in [1.6, 2.4], c2 in "
    "[0.6, 1.2], interaction time in [2, 4]); reports the total momentum and the largest "
    "position error against the closed-form solution.",
    model="peakons(width=1)",
    system=_peakon_system,
    setup=_peakon_setup,
    dt=0.02,
    steps=600,
    quick_steps=300,
    quick_batch=4,
    options=(("scheme", "midpoint"),),
    invariants=(Invariant("total_momentum", "total momentum", _total_momentum_1d, scale=_abs_momentum_scale_1d),),
    trajectory=_peakon_trajectory,
    plot=_peakon_plot,
    reference=_peakon_reference,
    reference_label="|q - q_exact|",
)


LANDMARKS = Scene(
    name="landmarks",
    description="three Gaussian landmarks in the plane (width 0.8), midpoint principle",
    details="EPDiff singular solutions with a Gaussian kernel. With --batch B the others are "
    "jittered copies (positions and momenta + 0.1 N(0, 1)). Reports the total linear "
    "momentum (relative to sum |p_a|) and the angular momentum sum q_a x p_a "
    "(relative to sum |q_a||p_a|).",
    model="landmarks(width=0.8)",
    system=_landmark_system,
    setup=_landmark_setup,
    dt=0.0125,
    steps=480,
    quick_steps=240,
    quick_batch=4,
    options=(("scheme", "midpoint"),),
    invariants=(
        Invariant("linear_momentum", "linear momentum", _total_momentum_2d, scale=_abs_momentum_scale_2d),
        Invariant("angular_momentum", "angular momentum", _landmark_angular, scale=_landmark_angular_scale),
    ),
    trajectory=_landmark_trajectory,
    plot=_landmark_plot,
)
