r"""The scenes `rigid-body` and `heavy-top`: their initial data, invariants, trajectories, plots."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from clebsch_jax import diagnostics, lie
from clebsch_jax.models import (
    heavy_top,
    rigid_body,
)

from ._scene_types import Invariant, Scene, Setup, orthogonality

__all__ = ["RIGID_BODY", "HEAVY_TOP"]


# --------------------------------------------------------------------------------------------
# rigid-body: the free rigid body (Example 30), reduced march.

RIGID_INERTIA = (2.0, 1.0, 2.0 / 3.0)


def _rigid_system():
    return rigid_body(jnp.asarray(RIGID_INERTIA))


def _rigid_setup(batch, rng):
    m = rng.normal(size=(batch, 3))
    m /= np.linalg.norm(m, axis=-1, keepdims=True)
    m[0] = (math.cos(1.1), 0.0, math.sin(1.1))
    xi0 = m / np.asarray(RIGID_INERTIA)  # Lemma 7: Π = I Ω
    Q0 = np.broadcast_to(np.eye(3), (batch, 3, 3)).copy()
    return Setup(Q0=Q0, xi0=xi0, P0=None, members={"Pi0": m.tolist()})


def _casimir(system, sol):
    return jnp.sum(sol.momentum**2, axis=-1)


def _spatial_momentum(system, sol):
    return diagnostics.noether_momentum(sol, lie.so3_left_generators, system)


def _rigid_trajectory(system, sol):
    return sol.momentum


def _sphere_view(ax, traj, colors, axis_names, view=(1.0, 0.8, 0.6)):
    """Curves on the unit sphere (M, S, 3) seen from direction `view` (orthographic): the near
    side solid, the far side faint; the outline and the three axes."""
    v = np.asarray(view, float)
    v /= np.linalg.norm(v)
    e1 = np.cross([0.0, 0.0, 1.0], v)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(v, e1)
    u = np.linspace(0, 2 * np.pi, 200)
    ax.plot(np.cos(u), np.sin(u), color="0.6", lw=0.6)
    for k, name in enumerate(axis_names):
        e = np.eye(3)[k]
        ax.plot([0, e @ e1], [0, e @ e2], color="0.5", lw=0.5, ls=":")
        ax.text(1.12 * (e @ e1), 1.12 * (e @ e2), name, ha="center", va="center", fontsize=9)
    for curve, col in zip(traj, colors):
        x, y, front = curve @ e1, curve @ e2, curve @ v >= 0
        ax.plot(np.where(front, x, np.nan), np.where(front, y, np.nan), color=col, lw=0.8)
        ax.plot(np.where(front, np.nan, x), np.where(front, np.nan, y), color=col, lw=0.6, alpha=0.25)
        ax.plot(x[:1], y[:1], "o", color=col, ms=3)
    ax.set_aspect("equal")
    ax.set_xlim(-1.25, 1.25)
    ax.set_ylim(-1.25, 1.25)
    ax.set_axis_off()


def _rigid_plot(ax, ts, traj, setup, colors):
    norms = np.linalg.norm(traj[:, :1], axis=-1, keepdims=True)
    _sphere_view(ax, traj / norms, colors, ("$\\Pi_1$", "$\\Pi_2$", "$\\Pi_3$"))
    ax.set_title("body angular momentum $\\Pi/|\\Pi|$ on the sphere", fontsize=10)


# --------------------------------------------------------------------------------------------
# heavy-top: a fast symmetric (Lagrange) top, Definition 14's potential.

TOP_INERTIA = (1.0, 1.0, 0.4)
TOP_MGL = 1.5


def _top_system():
    return heavy_top(jnp.asarray(TOP_INERTIA), TOP_MGL, (0.0, 0.0, 1.0))


def _top_setup(batch, rng):
    tilt = np.column_stack([0.5 + 0.15 * rng.uniform(-1, 1, batch), 0.15 * rng.uniform(-1, 1, batch), np.zeros(batch)])
    omega = np.array([0.3, -0.2, 6.0]) + np.column_stack(
        [0.3 * rng.normal(size=(batch, 2)), 0.5 * rng.normal(size=batch)]
    )
    tilt[0], omega[0] = (0.5, 0.0, 0.0), (0.3, -0.2, 6.0)
    Q0 = np.asarray(jax.vmap(lie.so3_exp)(jnp.asarray(tilt)))
    return Setup(Q0=Q0, xi0=omega, P0=None, members={"tilt": tilt.tolist(), "Omega0": omega.tolist()})


def _vertical_generator(Q):
    return jnp.stack([lie.hat(jnp.array([0.0, 0.0, 1.0], Q.dtype)) @ Q])


def _vertical_momentum(system, sol):
    return diagnostics.noether_momentum(sol, _vertical_generator, system)


def _body_momentum_scale(system, sol):
    return jnp.max(jnp.abs(sol.momentum[0]))


def _gamma_norm_error(system, sol):
    return jnp.abs(jnp.linalg.norm(sol.Q[:, 2, :], axis=-1) - 1.0)  # Γ = Qᵀe₃, the third row of Q


def _top_trajectory(system, sol):
    return sol.Q[:, :, 2]  # the symmetry axis Qe₃ in space (the centre of mass direction)


def _top_plot(ax, ts, traj, setup, colors):
    u = np.linspace(0, 2 * np.pi, 200)
    ax.plot(np.cos(u), np.sin(u), color="0.6", lw=0.6)
    for curve, col in zip(traj, colors):
        ax.plot(curve[:, 0], curve[:, 1], color=col, lw=0.7)
        ax.plot(curve[:1, 0], curve[:1, 1], "o", color=col, ms=3)
    ax.set_aspect("equal")
    r = max(1e-3, float(np.nanmax(np.abs(traj[..., :2])))) * 1.1
    ax.set_xlim(-r, r)
    ax.set_ylim(-r, r)
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.set_title("symmetry axis $Qe_3$ seen from above (precession, nutation)", fontsize=10)


# --------------------------------------------------------------------------------------------
# The scenes.

RIGID_BODY = Scene(
    name="rigid-body",
    description="free rigid body, I = (2, 1, 2/3), Cayley (Example 30), reduced march",
    details="Member 0 starts from the body angular momentum Pi0 = (cos 1.1, 0, sin 1.1); "
    "with --batch B the others are random unit momenta. Reports the Casimir |Pi|^2, the "
    "spatial angular momentum (Noether, left SO(3) action) and |Q^T Q - I|.",
    model="rigid_body(inertia=(2, 1, 2/3))",
    system=_rigid_system,
    setup=_rigid_setup,
    dt=0.05,
    steps=4000,
    quick_steps=400,
    quick_batch=4,
    invariants=(
        Invariant("casimir", "Casimir |Pi|^2", _casimir),
        Invariant("spatial_momentum", "spatial ang. momentum", _spatial_momentum),
        Invariant("orthogonality", "|Q^T Q - I|", orthogonality, kind="error"),
    ),
    trajectory=_rigid_trajectory,
    plot=_rigid_plot,
)


HEAVY_TOP = Scene(
    name="heavy-top",
    description="fast symmetric heavy top, I = (1, 1, 0.4), mgl = 1.5, tilted 0.5 rad",
    details="Definition 14's potential; order 2 composes the left principle with its adjoint "
    "over half steps (reduced march). With --batch B the others have jittered tilts and "
    "spins. Reports the vertical angular momentum (Noether, rotations about the "
    "vertical; relative to |Pi0|), ||Gamma| - 1| and |Q^T Q - I|.",
    model="heavy_top(inertia=(1, 1, 0.4), mass_gravity_length=1.5, center_of_mass=(0, 0, 1))",
    system=_top_system,
    setup=_top_setup,
    dt=0.02,
    steps=2500,
    quick_steps=500,
    quick_batch=4,
    invariants=(
        Invariant("vertical_momentum", "vertical ang. momentum", _vertical_momentum, scale=_body_momentum_scale),
        Invariant("gamma_norm", "||Gamma| - 1|", _gamma_norm_error, kind="error"),
        Invariant("orthogonality", "|Q^T Q - I|", orthogonality, kind="error"),
    ),
    trajectory=_top_trajectory,
    plot=_top_plot,
)
