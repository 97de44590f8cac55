r"""The scenes of the command line (`clebsch-jax run SCENE`, `clebsch-jax demo`), as data.

A `Scene` is a built-in model with initial data, default step, number of steps and order, the
invariants to report and a plot: nothing here is special code for the engine, every scene is
`cj.integrate(system, Q0, xi0, P0=..., dt=..., n_steps=..., order=..., throw=False)` under
`jax.vmap` over a batch of initial data, through the public API only.

| scene | model | member 0 | other members (`--batch B`) | conserved (discrete Noether) |
| --- | --- | --- | --- | --- |
| `rigid-body` | `rigid_body((2, 1, 2/3))` | $\Pi^0 = (\cos 1.1, 0, \sin 1.1)$ | random unit momenta | Casimir $|\Pi|^2$, spatial $\pi$ |
| `heavy-top` | `heavy_top((1, 1, 0.4), 1.5)` | a fast top tilted by 0.5 rad | jittered tilt and spin | vertical $\langle p, \hat e_3 Q\rangle$ |
| `vortices` | `point_vortices((1, -1, 1, -1))` | two leapfrogging pairs | jittered copies | linear, angular impulse |
| `peakons` | `peakons(1)` | two peakons overtaking (speeds 2, 1) | random overtaking pairs | $\sum_a p_a$ |
| `landmarks` | `landmarks(0.8)` | three swirling landmarks | jittered copies | $\sum_a p_a$, $\sum_a q_a\times p_a$ |
| `euler-sphere` | `euler_sphere(32)` | a random vorticity, energy spectrum peaked near l = 10 | other random draws | Casimirs $\mathrm{tr}\,W^2, W^3, W^4$, angular momentum |

**The run** (`run_scene`): the march goes in chunks of steps, each one call of the same
compiled, vmapped program, continued from the last node's canonical state $(Q^n, p^n)$
(`clebsch_jax.continue_from`: the step is the symplectic map $(Q^n, p^n)\mapsto(Q^{n+1}, p^{n+1})$
of Lemma 20, so the continuation is the same trajectory up to round-off; in the reduced march
$p^n$ is the minimum-norm cotangent with momentum map $\mu^n$).
After every chunk the host keeps, per member, the worst error of every invariant over the
nodes known so far, and, for the plot, the first `PLOT_MEMBERS` members' trajectories and
errors on at most `PLOT_POINTS` nodes; so memory is one chunk, whatever the number of steps.
A failing member is a value: its later nodes are NaN and not counted, its status and first
failing step are reported, the other members run on.

**Errors reported** (max over members and over known nodes $n$, i.e. before any failure):
for a conserved quantity $f$ (`Invariant.kind == "drift"`), $\max_n\|f^n - f^0\|_\infty / s$
with $s$ the invariant's scale at node 0 ($|f^0|$ unless stated, e.g. $\sum_a|p_a|$ for a total
momentum that may vanish); for a quantity that is itself an error (`kind == "error"`, e.g.
$\max|Q^TQ - I|$) its largest value. The energy error is $\max_n |E^n - E^0| / |E^0|$ with
$E$ = `clebsch_jax.diagnostics.energy`.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

import clebsch_jax as cj
from clebsch_jax import diagnostics, lie
from clebsch_jax.models import (
    euler_sphere,
    euler_sphere_angular_momentum,
    euler_sphere_casimirs,
    euler_sphere_orthographic,
    euler_sphere_quantise,
    euler_sphere_start,
    euler_sphere_vorticity,
    heavy_top,
    landmark_angular_momentum,
    landmark_velocity,
    landmarks,
    peakon_velocity,
    peakons,
    point_vortices,
    rigid_body,
    vortex_angular_impulse,
    vortex_linear_impulse,
    vortex_velocity,
)

__all__ = [
    "Scene",
    "Invariant",
    "Setup",
    "SCENES",
    "run_scene",
    "solve",
    "program",
    "chunk_steps_for",
    "QUICK_COMPILER_OPTIONS",
    "compiler_options_for",
]

PLOT_MEMBERS = 8
"""Members drawn in a scene's plot (the first ones)."""

PLOT_POINTS = 2000
"""At most this many nodes per member are kept for the plots (error envelopes: block maxima)."""

MAX_CHUNKS = 50
"""A long run is cut into at most about this many chunks (progress updates)."""

WORK_PER_CHUNK = 20_000
"""Member-steps per chunk at least (a call's fixed cost is then negligible)."""

NODE_BUDGET = 200_000
"""Member-nodes per chunk at most (bounds the memory of one chunk's `Solution`)."""

QUICK_WORK = 20_000
"""Runs of at most this many member-steps are compiled with XLA's backend optimisation off."""

QUICK_COMPILER_OPTIONS = {"xla_backend_optimization_level": 0}
"""Short runs are dominated by compilation: this shortens it (and slows the steps)."""


# --------------------------------------------------------------------------------------------
# Scenes as data.


@dataclasses.dataclass(frozen=True)
class Invariant:
    r"""A quantity reported for every member.

    - `name`: key in the JSON summary; `label`: for tables and plots (ASCII: any terminal).
    - `values(system, sol)` → per-node values, shape (N+1, …), for one member's `Solution`.
    - `kind`: `"drift"` for a conserved quantity (reported: $\max_n\|f^n - f^0\|_\infty / s$),
      `"error"` for a quantity that is itself an error (reported: its max).
    - `scale(system, sol)` → $s$, a scalar from node 0 (default $\|f^0\|_\infty$).
    - `roundoff`: True when the discrete flow conserves it exactly (shown on a log axis with
      machine epsilon); False when it is only bounded (the energy).
    """

    name: str
    label: str
    values: Callable
    kind: str = "drift"
    scale: Callable | None = None
    roundoff: bool = True


@dataclasses.dataclass(frozen=True)
class Setup:
    """A scene's batch: initial data with a leading member axis B, and what the JSON records.

    - `Q0` (B, …), `xi0` (B, …): `integrate`'s initial data per member.
    - `P0` (B, …) or None: the canonical momenta when the scene knows them (peakons, landmarks);
      None derives them from `xi0` (`clebsch_jax.initial_multiplier`).
    - `members`: per-member data for the JSON (lists) and for `Scene.reference`.
    """

    Q0: np.ndarray
    xi0: np.ndarray
    P0: np.ndarray | None
    members: dict


@dataclasses.dataclass(frozen=True)
class Scene:
    r"""A built-in scene of the command line.

    - `name`, `description` (one line), `details` (for `--help`), `model` (the constructor
      call, for the JSON).
    - `system()` → the `ClebschSystem` (shared by all members).
    - `setup(batch, rng)` → `Setup`: member 0 is the scene's canonical initial condition, the
      others are drawn with `rng` (a `numpy.random.Generator`).
    - `dt`, `steps`, `order`: defaults of `clebsch-jax run`; `quick_steps`, `quick_batch`:
      the demo's short run.
    - `options`: further `integrate` options, a tuple of (key, value) pairs.
    - `invariants`: `Invariant`s besides the energy (always reported).
    - `trajectory(system, sol)` → per-node values for the plot, shape (N+1, …).
    - `plot(ax, ts, traj, setup, members)`: draws the trajectories of the plotted members
      (`traj` (M, S, …) at times `ts` (S,)) on a matplotlib `Axes`.
    - `reference`: None, or `(members, ts, traj)` → (B, S) error against an exact solution
      at each node (computed on the host for every member from `trajectory`).
    """

    name: str
    description: str
    details: str
    model: str
    system: Callable[[], cj.ClebschSystem]
    setup: Callable[[int, np.random.Generator], Setup]
    dt: float
    steps: int
    quick_steps: int
    quick_batch: int
    invariants: tuple
    trajectory: Callable
    plot: Callable
    order: int = 2
    options: tuple = ()
    reference: Callable | None = None
    reference_label: str = ""


# --------------------------------------------------------------------------------------------
# Scale helpers (node 0 of one member's Solution).


def _energy_values(system, sol):
    return diagnostics.energy(system, sol)


ENERGY = Invariant("energy", "energy", _energy_values, kind="drift", roundoff=False)
"""The energy $E = \\langle\\delta l/\\delta\\xi, \\xi\\rangle - l$ (`diagnostics.energy`), reported for every scene."""


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


def _orthogonality(system, sol):
    return diagnostics.orthogonality_error(sol.Q)


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
# euler-sphere: incompressible Euler on the sphere, quantised (Euler–Zeitlin), reduced march.

SPHERE_N = 32
SPHERE_PEAK = 10
"""The scene's matrix size and the degree near which its initial energy spectrum peaks."""


def _sphere_system():
    return euler_sphere(SPHERE_N)


def sphere_random_coefficients(N: int, peak: float, rng: np.random.Generator) -> np.ndarray:
    r"""Spherical-harmonic coefficients c[l, m] of a random real vorticity whose energy spectrum
    $E_l \propto \sum_m |c_{lm}|^2 / (l(l+1))$ is $\propto l^3 e^{-2(l/l_p)^2}$-shaped, peaked near
    $l_p$ = `peak` (random phases; zero mean, $c_{00} = 0$), scaled to a root-mean-square
    vorticity of 1 ($\int\omega^2 dA = 4\pi$: a turnover time of order 1)."""
    l = np.arange(N, dtype=float)
    amplitude = np.sqrt(l * (l + 1) * l**3 * np.exp(-2 * (l / peak) ** 2) / np.maximum(2 * l + 1, 1))
    c = rng.normal(size=(N, N)) + 1j * rng.normal(size=(N, N))
    c = np.tril(c) * amplitude[:, None]
    c[:, 0] = c[:, 0].real * np.sqrt(2)
    c[0, 0] = 0.0
    enstrophy = np.sum(np.abs(c[:, 0]) ** 2) + 2 * np.sum(np.abs(c[:, 1:]) ** 2)  # ∫ω² dA
    return c * np.sqrt(4 * np.pi / enstrophy)


def _sphere_setup(batch, rng):
    starts = [
        euler_sphere_start(euler_sphere_quantise(sphere_random_coefficients(SPHERE_N, SPHERE_PEAK, rng)))
        for _ in range(batch)
    ]
    Q0 = np.stack([np.asarray(q) for q, _ in starts])
    xi0 = np.stack([np.asarray(x) for _, x in starts])
    return Setup(Q0=Q0, xi0=xi0, P0=None, members={"N": SPHERE_N, "peak_degree": SPHERE_PEAK})


def _sphere_casimir(k):
    def values(system, sol):
        return euler_sphere_casimirs(euler_sphere_vorticity(sol.momentum), powers=(k,))

    return values


def _sphere_casimir_scale(k):
    def scale(system, sol):  # Σ|λ|^k over W's eigenvalues: tr W³ of a random field is near 0
        H = 1j * euler_sphere_vorticity(sol.momentum[0])
        return jnp.sum(jnp.abs(jnp.linalg.eigvalsh(H)) ** k)

    return scale


def _sphere_angular_momentum(system, sol):
    return euler_sphere_angular_momentum(euler_sphere_vorticity(sol.momentum))


def _sphere_angular_scale(system, sol):  # |∫ω n| ≤ ∫|ω|: the size of ω at node 0 (Frobenius)
    W = euler_sphere_vorticity(sol.momentum[0])
    return jnp.sqrt(jnp.real(jnp.sum(jnp.conj(W) * W)) * 4 * np.pi / W.shape[-1])


def _sphere_trajectory(system, sol):
    return sol.momentum


def _sphere_plot(ax, ts, traj, setup, colors):
    """Member 0's vorticity at the last known node, orthographic view from above the equator."""
    known = np.flatnonzero(np.all(np.isfinite(traj[0].reshape(traj.shape[1], -1)), axis=-1))
    k = known[-1] if known.size else 0
    W = np.asarray(euler_sphere_vorticity(traj[0, k]))
    _orthographic(ax, W)
    ax.set_title(f"vorticity at t = {ts[k]:.3g} (orthographic, member 0)", fontsize=10)


def _orthographic(ax, W):
    """The field of W on the hemisphere seen from above the equator (`euler_sphere_orthographic`)."""
    values = euler_sphere_orthographic(W, colatitude=0.35, longitude=0.4)
    r = np.nanmax(np.abs(values))
    ax.imshow(values, origin="lower", extent=(-1, 1, -1, 1), cmap="RdBu_r", vmin=-r, vmax=r)
    ax.set_aspect("equal")
    ax.set_axis_off()


# --------------------------------------------------------------------------------------------
# The table of scenes.

SCENES: dict[str, Scene] = {
    s.name: s
    for s in (
        Scene(
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
                Invariant("orthogonality", "|Q^T Q - I|", _orthogonality, kind="error"),
            ),
            trajectory=_rigid_trajectory,
            plot=_rigid_plot,
        ),
        Scene(
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
                Invariant(
                    "vertical_momentum", "vertical ang. momentum", _vertical_momentum, scale=_body_momentum_scale
                ),
                Invariant("gamma_norm", "||Gamma| - 1|", _gamma_norm_error, kind="error"),
                Invariant("orthogonality", "|Q^T Q - I|", _orthogonality, kind="error"),
            ),
            trajectory=_top_trajectory,
            plot=_top_plot,
        ),
        Scene(
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
        ),
        Scene(
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
            invariants=(
                Invariant("total_momentum", "total momentum", _total_momentum_1d, scale=_abs_momentum_scale_1d),
            ),
            trajectory=_peakon_trajectory,
            plot=_peakon_plot,
            reference=_peakon_reference,
            reference_label="|q - q_exact|",
        ),
        Scene(
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
        ),
        Scene(
            name="euler-sphere",
            description="incompressible Euler on the sphere, quantised at N = 32 (Euler-Zeitlin)",
            details="The paper's fluid: vorticity as a skew-Hermitian 32 x 32 matrix, the reduced Cayley "
            "march (the isospectral midpoint method) solved by matrix-free sweeps. Member 0 and, "
            "with --batch B, the others are random vorticities with an energy spectrum peaked "
            "near degree 10. Reports the Casimirs tr W^2, tr W^3, tr W^4 (relative to sum "
            "|lambda|^k) and the total angular momentum (relative to |omega|).",
            model=f"euler_sphere(N={SPHERE_N})",
            system=_sphere_system,
            setup=_sphere_setup,
            dt=0.01,
            steps=2000,
            quick_steps=100,
            quick_batch=1,
            invariants=(
                Invariant("casimir_2", "Casimir tr W^2", _sphere_casimir(2), scale=_sphere_casimir_scale(2)),
                Invariant("casimir_3", "Casimir tr W^3", _sphere_casimir(3), scale=_sphere_casimir_scale(3)),
                Invariant("casimir_4", "Casimir tr W^4", _sphere_casimir(4), scale=_sphere_casimir_scale(4)),
                Invariant(
                    "angular_momentum", "angular momentum", _sphere_angular_momentum, scale=_sphere_angular_scale
                ),
                Invariant("orthogonality", "|Q^T Q - I|", _orthogonality, kind="error"),
            ),
            trajectory=_sphere_trajectory,
            plot=_sphere_plot,
        ),
    )
}


# --------------------------------------------------------------------------------------------
# The compiled chunk: integrate under vmap, with the scene's per-node invariants.


def _options_key(options) -> tuple:
    return tuple(sorted((options or {}).items()))


@functools.lru_cache(maxsize=None)
def program(name: str, order: int, n_steps: int, compiler_options: tuple = (), scheme: str | None = None):
    r"""The jitted, vmapped march of `n_steps` steps of scene `name` (cached: one per arguments).

    `program(...)(Q0, xi0, P0, derive_P0, t0, dt)` with a leading member axis on `Q0`, `xi0`,
    `P0` runs `integrate(system, Q0, xi0, P0=P0, t0=t0, dt=dt, n_steps=n_steps, order=order,
    throw=False, **scene.options)` for every member (`scheme`, if given, in place of the
    scene's), with $P^0$ replaced by `initial_multiplier(system, Q0, xi0)` where `derive_P0` (a
    traced bool) is True.

    **Returns** a dict: `sol` (the batched `Solution`), `values` {name: (B, N+1, k)} and
    `scales` {name: (B,)} of the energy and the scene's invariants, `trajectory` (B, N+1, …),
    `known` (B, N+1) (valid nodes with a recovered nodal velocity), and `start`, the
    `clebsch_jax.Start` at the last node to continue from (fields (B, …)).
    """
    scene = SCENES[name]
    system = scene.system()
    invariants = (ENERGY,) + scene.invariants
    options = dict(scene.options)
    if scheme is not None:
        options["scheme"] = scheme

    def one(Q0, xi0, P0, derive_P0, t0, dt):
        P0 = jnp.where(derive_P0, cj.initial_multiplier(system, Q0, xi0), P0)
        sol = cj.integrate(system, Q0, xi0, P0=P0, t0=t0, dt=dt, n_steps=n_steps, order=order, throw=False, **options)
        values, scales = {}, {}
        for inv in invariants:
            v = jnp.asarray(inv.values(system, sol))
            values[inv.name] = v = v.reshape(v.shape[0], -1)
            scales[inv.name] = (
                jnp.ones((), v.dtype)
                if inv.kind != "drift"
                else inv.scale(system, sol)
                if inv.scale is not None
                else jnp.max(jnp.abs(v[0]))
            )
        known = sol.valid & (sol.nodal_stats.status == cj.Status.SUCCESS)
        return dict(
            sol=sol,
            values=values,
            scales=scales,
            trajectory=scene.trajectory(system, sol),
            known=known,
            start=cj.continue_from(system, sol)._replace(march_state=None),  # one program for every chunk
        )

    mapped = jax.vmap(one, in_axes=(0, 0, 0, 0, None, None))
    return jax.jit(mapped, compiler_options=dict(compiler_options) or None)


def compiler_options_for(batch: int, n_steps: int) -> dict:
    """XLA options of a run: `QUICK_COMPILER_OPTIONS` when it is short (compile-dominated)."""
    return dict(QUICK_COMPILER_OPTIONS) if batch * n_steps <= QUICK_WORK else {}


def chunk_steps_for(batch: int, n_steps: int) -> int:
    """Steps per compiled call: at most ~`MAX_CHUNKS` chunks, at least `WORK_PER_CHUNK`
    member-steps each, at most `NODE_BUDGET` member-nodes (memory); `n_steps` if one call does."""
    chunk = max(-(-n_steps // MAX_CHUNKS), -(-WORK_PER_CHUNK // batch))
    chunk = min(chunk, max(10, NODE_BUDGET // batch))
    return min(chunk, n_steps)


# --------------------------------------------------------------------------------------------
# The run: chunks, host-side reductions, summary, plot.


def _initial_state(setup: Setup):
    """(Q0, xi0, P0, derive_P0) as `program` takes them (P0 zeros where it is derived)."""
    Q = jnp.asarray(setup.Q0)
    derive = setup.P0 is None
    P = jnp.zeros_like(Q) if derive else jnp.asarray(setup.P0)
    return Q, jnp.asarray(setup.xi0), P, jnp.full((Q.shape[0],), derive)


def solve(
    scene: Scene,
    setup: Setup,
    *,
    dt: float,
    n_steps: int,
    order: int | None = None,
    compiler_options=None,
    scheme: str | None = None,
) -> dict:
    """One call of `program` from `setup`'s initial data, $t_0 = 0$ (no chunks): what `run_scene`
    computes first, as the dict `program` returns (its `"sol"` is the batched `Solution`).
    `compiler_options` default as in `run_scene` (the same compiled program)."""
    batch = setup.Q0.shape[0]
    copts = compiler_options_for(batch, n_steps) if compiler_options is None else dict(compiler_options)
    run = program(scene.name, scene.order if order is None else int(order), n_steps, _options_key(copts), scheme)
    return run(*_initial_state(setup), jnp.asarray(0.0, jnp.float64), jnp.asarray(dt, jnp.float64))


class _Binned:
    """Per-member maxima of per-node values over bins of `stride` nodes (plot envelopes)."""

    def __init__(self, members: int, n_nodes: int, stride: int):
        self.stride = stride
        self.data = np.full((members, -(-n_nodes // stride)), -np.inf)

    def add(self, nodes: np.ndarray, values: np.ndarray) -> None:
        bins = nodes // self.stride
        for m in range(self.data.shape[0]):
            np.maximum.at(self.data[m], bins, np.where(np.isnan(values[m]), -np.inf, values[m]))

    def result(self) -> np.ndarray:
        return np.where(np.isfinite(self.data), self.data, np.nan)


def run_scene(
    scene: Scene,
    *,
    dt: float | None = None,
    n_steps: int | None = None,
    order: int | None = None,
    batch: int = 1,
    seed: int = 0,
    chunk_steps: int | None = None,
    compiler_options=None,
    progress: Callable | None = None,
    scheme: str | None = None,
) -> dict:
    r"""Integrate a scene's batch and reduce it to a summary (no files written).

    **Arguments:**

    - `scene`: a `Scene` (e.g. `SCENES["rigid-body"]`).
    - `dt`, `n_steps`, `order`: default the scene's; `scheme`: None (the scene's) or a scheme of
      `integrate` (e.g. "gauss", with an even `order` up to 16).
    - `batch`: members B (member 0 is the canonical one); `seed`: of the other members' draw.
    - `chunk_steps`: steps per compiled call (default `chunk_steps_for(batch, n_steps)`).
    - `compiler_options`: XLA options (default `compiler_options_for(batch, n_steps)`).
    - `progress`: None or `progress(steps_done, n_steps, elapsed_s)`, called before the first
      chunk (0 steps done: compiling) and after every chunk.

    **Returns:** the summary, JSON-serialisable but for its private entry `"_plot"` (NumPy
    arrays for `write_plot`, dropped by `write_summary`): `scene` (name, model, members, seed,
    initial data for B <= 64), `run` (dt, steps, t_final, the `Solution`'s `method`, `form`,
    `scheme`, `order`, `derivative_map`, chunks, compiler options), `errors` (`energy_rel_max`,
    `<invariant>_max`, `reference_max`: maxima over members and known nodes, None if no node is
    known), `invariants` {name: label, kind, max, per_member}, `reference`, `newton_iterations`
    (mean and max updates per step), `failures` (count; member, step, t, status, reason of
    each), `per_member` (status, failed_step: -1 if none), `timing` and `versions`.
    """
    plan = _plan(
        scene,
        dt=dt,
        n_steps=n_steps,
        order=order,
        batch=batch,
        seed=seed,
        chunk_steps=chunk_steps,
        compiler_options=compiler_options,
    )
    setup = scene.setup(batch, np.random.default_rng(seed))
    run = program(scene.name, plan.order, plan.chunk, _options_key(plan.compiler_options), scheme)
    tally = _Tally(scene, setup, plan)
    wall, first_s = _march(run, setup, plan, tally, progress)
    summary = _summary(scene, setup, plan, tally, wall, first_s)
    summary["_plot"] = _plot_data(setup, plan, tally)
    return summary


@dataclasses.dataclass(frozen=True)
class _Plan:
    """A run's settings, the scene's defaults filled in."""

    dt: float
    n_steps: int
    order: int  # as requested (the `Solution` says which order ran)
    batch: int
    seed: int
    chunk: int  # steps per compiled call
    n_chunks: int
    compiler_options: dict


def _plan(scene: Scene, *, dt, n_steps, order, batch, seed, chunk_steps, compiler_options) -> _Plan:
    """`run_scene`'s settings: None takes the scene's default, or `chunk_steps_for` and
    `compiler_options_for`; a chunk is at most the whole run."""
    dt = scene.dt if dt is None else float(dt)
    n_steps = scene.steps if n_steps is None else int(n_steps)
    chunk = chunk_steps_for(batch, n_steps) if chunk_steps is None else min(int(chunk_steps), n_steps)
    copts = compiler_options_for(batch, n_steps) if compiler_options is None else dict(compiler_options)
    return _Plan(
        dt=dt,
        n_steps=n_steps,
        order=scene.order if order is None else int(order),
        batch=batch,
        seed=seed,
        chunk=chunk,
        n_chunks=-(-n_steps // chunk),
        compiler_options=copts,
    )


def _march(run, setup: Setup, plan: _Plan, tally: _Tally, progress: Callable | None) -> tuple:
    """Call the compiled chunk `run` `plan.n_chunks` times, each chunk continued from the
    `clebsch_jax.Start` at the last node of the one before, and hand every chunk to `tally`.

    **Returns:** (wall time, time of the first chunk, which includes the compilation), seconds.
    """
    Q, xi, P, derive_P0 = _initial_state(setup)
    t_start = time.perf_counter()
    if progress is not None:
        progress(0, plan.n_steps, 0.0)
    first_s = None
    for c in range(plan.n_chunks):
        offset = c * plan.chunk
        t0 = offset * plan.dt  # on the host, so no round-off accumulates from chunk to chunk
        out = run(Q, xi, P, derive_P0, jnp.asarray(t0, jnp.float64), jnp.asarray(plan.dt, jnp.float64))
        out = jax.block_until_ready(out)
        if first_s is None:
            first_s = time.perf_counter() - t_start
        tally.add(out, offset)
        start = out["start"]
        Q, P, xi = start.Q0, start.P0, start.xi0
        derive_P0 = jnp.zeros((plan.batch,), bool)
        if progress is not None:
            progress(min(offset + plan.chunk, plan.n_steps), plan.n_steps, time.perf_counter() - t_start)
    return time.perf_counter() - t_start, first_s


class _Tally:
    """What the host keeps of a run, chunk after chunk, so that memory is one chunk whatever the
    number of steps: per member the worst error of every invariant and against the reference
    over the known nodes, the first failure, the Newton updates; for the first `PLOT_MEMBERS`
    members the errors' envelopes (`_Binned`) and the trajectory at every `stride`-th node; and
    the facts of the `Solution` (method, form, ...)."""

    def __init__(self, scene: Scene, setup: Setup, plan: _Plan):
        self.scene, self.setup, self.n_steps, self.chunk = scene, setup, plan.n_steps, plan.chunk
        self.invariants = (ENERGY,) + scene.invariants
        batch, n_nodes = plan.batch, plan.n_steps + 1
        self.n_plot = min(batch, PLOT_MEMBERS)
        self.stride = max(1, -(-n_nodes // PLOT_POINTS))
        self.errors_binned = {inv.name: _Binned(self.n_plot, n_nodes, self.stride) for inv in self.invariants}
        self.ref_binned = _Binned(self.n_plot, n_nodes, self.stride) if scene.reference else None
        self.worst = {inv.name: np.full(batch, -np.inf) for inv in self.invariants}
        self.ref_worst = np.full(batch, -np.inf)
        self.traj_nodes, self.traj_pieces = [], []
        self.status = np.zeros(batch, np.int64)
        self.failed_step = np.full(batch, -1, np.int64)
        self.iter_sum, self.iter_count, self.iter_max = 0, 0, 0
        self.ref0 = self.scale0 = self.facts = None

    def add(self, out: dict, offset: int) -> None:
        """Take in one chunk (what `program` returns) whose node 0 is the run's node `offset`."""
        sol = out["sol"]
        if self.facts is None:
            self.facts = dict(
                method=sol.method,
                form=sol.form,
                scheme=sol.scheme,
                order=int(sol.order),
                derivative_map=sol.derivative_map,
            )
        # nodes of this chunk kept: 0 only in the first chunk (later it is the previous end), and
        # none past n_steps (the last chunk may run over)
        lo, hi = (0 if offset == 0 else 1), min(self.chunk, self.n_steps - offset)
        keep = slice(lo, hi + 1)
        nodes = offset + np.arange(lo, hi + 1)
        known = np.asarray(out["known"])[:, keep]
        self._add_invariants(out, nodes, known, keep)
        traj = np.asarray(out["trajectory"][: None if self.scene.reference is not None else self.n_plot])[:, keep]
        if self.scene.reference is not None:
            self._add_reference(np.asarray(sol.ts)[0, keep], traj, nodes, known)
        self._add_trajectory(traj, nodes, known)
        self._add_newton(sol, hi)
        self._add_failures(sol, offset)

    def _add_invariants(self, out: dict, nodes, known, keep: slice) -> None:
        """Per node the drift of each conserved quantity from node 0 of the run, relative to its
        scale there (or the value of an error quantity): worst per member, and plot envelopes."""
        values = {k: np.asarray(v)[:, keep] for k, v in out["values"].items()}
        if self.ref0 is None:  # the first chunk: its node 0 is the run's
            self.ref0 = {k: v[:, 0] for k, v in values.items()}
            self.scale0 = {k: np.asarray(v) for k, v in out["scales"].items()}
        for inv in self.invariants:
            v = values[inv.name]
            if inv.kind == "drift":
                err = np.max(np.abs(v - self.ref0[inv.name][:, None]), axis=-1)
                err = err / np.maximum(np.abs(self.scale0[inv.name]), np.finfo(float).tiny)[:, None]
            else:
                err = np.max(v, axis=-1)
            err = np.where(known, err, np.nan)
            worst = np.nanmax(np.where(known, err, -np.inf), axis=-1)
            self.worst[inv.name] = np.fmax(self.worst[inv.name], worst)
            self.errors_binned[inv.name].add(nodes, err[: self.n_plot])

    def _add_reference(self, ts, traj, nodes, known) -> None:
        """Every member's error against the scene's exact solution at the known nodes."""
        rerr = np.where(known, self.scene.reference(self.setup.members, ts, traj), np.nan)
        self.ref_worst = np.fmax(self.ref_worst, np.max(np.where(known, rerr, -np.inf), axis=-1))
        self.ref_binned.add(nodes, rerr[: self.n_plot])

    def _add_trajectory(self, traj, nodes, known) -> None:
        """The plotted members' trajectories at every `stride`-th node and the last (NaN where
        not known)."""
        pick = (nodes % self.stride == 0) | (nodes == self.n_steps)
        self.traj_nodes.append(nodes[pick])
        mask = known[: self.n_plot, pick]
        mask = mask.reshape(mask.shape + (1,) * (traj.ndim - 2))
        self.traj_pieces.append(np.where(mask, traj[: self.n_plot][:, pick], np.nan))

    def _add_newton(self, sol, n: int) -> None:
        """Newton updates per step (summed over a composition's sub-steps) of the chunk's first
        `n` steps, attempted steps only."""
        st = np.asarray(sol.stats.status)[:, :n]
        it = np.asarray(sol.stats.iterations)[:, :n]
        tried = st != cj.Status.SKIPPED
        self.iter_sum += int(np.sum(it[tried]))
        self.iter_count += int(np.sum(tried))
        self.iter_max = max(self.iter_max, int(np.max(it[tried], initial=0)))

    def _add_failures(self, sol, offset: int) -> None:
        """The first failure of each member, in the run's steps (a failure past n_steps does not
        count)."""
        result = np.asarray(sol.result)
        local = np.asarray(sol.failed_step)
        last = self.n_steps - offset + (result == cj.Status.LEGENDRE)  # a node failure may be at node n_steps
        new = (self.status == cj.Status.SUCCESS) & (result != cj.Status.SUCCESS) & (local < last)
        self.status = np.where(new, result, self.status)
        self.failed_step = np.where(new, offset + local, self.failed_step)


def _finite_max(a) -> float | None:
    """The largest finite entry of `a`, None if there is none."""
    a = np.asarray(a, float)
    a = a[np.isfinite(a)]
    return float(np.max(a)) if a.size else None


def _finite_list(a) -> list:
    return [None if not np.isfinite(x) else float(x) for x in a]


def _failures(tally: _Tally, dt: float) -> list:
    """One entry per failed member: its index, step, time, status code and the reason."""
    return [
        {
            "member": int(m),
            "step": int(tally.failed_step[m]),
            "t": float(tally.failed_step[m] * dt),
            "status": int(tally.status[m]),
            "reason": cj.Status.MESSAGES.get(int(tally.status[m]), f"status {int(tally.status[m])}"),
        }
        for m in np.flatnonzero(tally.status != cj.Status.SUCCESS)
    ]


def _summary(scene: Scene, setup: Setup, plan: _Plan, tally: _Tally, wall: float, first_s: float) -> dict:
    """`run_scene`'s summary (without the plot data) from the tally of its chunks."""
    facts, worst = tally.facts, tally.worst
    failures = _failures(tally, plan.dt)
    errors = {"energy_rel_max": _finite_max(worst["energy"])}
    errors.update({f"{inv.name}_max": _finite_max(worst[inv.name]) for inv in scene.invariants})
    if scene.reference is not None:
        errors["reference_max"] = _finite_max(tally.ref_worst)
    compiled_steps = (plan.n_chunks - 1) * plan.chunk
    return {
        "scene": {
            "name": scene.name,
            "description": scene.description,
            "model": scene.model,
            "options": dict(scene.options),
            "members": plan.batch,
            "seed": plan.seed,
            "initial": setup.members if plan.batch <= 64 else None,
        },
        "run": {
            "dt": plan.dt,
            "n_steps": plan.n_steps,
            "t_final": plan.n_steps * plan.dt,
            "order": facts["order"],
            "order_requested": plan.order,
            "method": facts["method"],
            "form": facts["form"],
            "scheme": facts["scheme"],
            "derivative_map": facts["derivative_map"],
            "chunks": plan.n_chunks,
            "steps_per_chunk": plan.chunk,
            "compiler_options": plan.compiler_options,
        },
        "errors": errors,
        "invariants": {
            inv.name: {
                "label": inv.label,
                "kind": inv.kind,
                "conserved_exactly": inv.roundoff,
                "max": _finite_max(worst[inv.name]),
                "per_member": _finite_list(worst[inv.name]),
            }
            for inv in tally.invariants
        },
        "reference": None
        if scene.reference is None
        else {
            "label": scene.reference_label,
            "max": _finite_max(tally.ref_worst),
            "per_member": _finite_list(tally.ref_worst),
        },
        "newton_iterations": {
            "mean": tally.iter_sum / tally.iter_count if tally.iter_count else None,
            "max": tally.iter_max,
            "per": "step (updates summed over the sub-steps of a composition)",
        },
        "failures": {"count": len(failures), "members": failures[:100]},
        "per_member": {"status": tally.status.tolist(), "failed_step": tally.failed_step.tolist()},
        "timing": {
            "wall_s": wall,
            "first_chunk_s": first_s,
            "steps_per_s_compiled": (compiled_steps / (wall - first_s) if compiled_steps and wall > first_s else None),
        },
        "versions": {"jax": jax.__version__, "numpy": np.__version__},
    }


def _plot_data(setup: Setup, plan: _Plan, tally: _Tally) -> dict:
    """What `write_plot` draws: the plotted members' trajectories and their errors' envelopes,
    with their times."""
    stride, n_bins = tally.stride, tally.errors_binned["energy"].data.shape[1]
    return {
        "setup": setup,
        "t_traj": np.concatenate(tally.traj_nodes) * plan.dt,
        "trajectory": np.concatenate(tally.traj_pieces, axis=1),
        "t_err": np.minimum(np.arange(n_bins) * stride + stride - 1, plan.n_steps) * plan.dt,
        "errors": {inv.name: tally.errors_binned[inv.name].result() for inv in tally.invariants},
        "reference": None if tally.ref_binned is None else tally.ref_binned.result(),
    }


def write_summary(summary: dict, out_dir: str, files: list) -> str:
    """Write `summary.json` (without the private plot data) into `out_dir`; returns its path."""
    path = os.path.join(out_dir, "summary.json")
    public = {k: v for k, v in summary.items() if not k.startswith("_")} | {"files": files}
    with open(path, "w") as fh:
        json.dump(public, fh, indent=2)
        fh.write("\n")
    return path


def write_plot(scene: Scene, summary: dict, path: str) -> None:
    """One PNG: the plotted members' trajectories (left) and the invariants' errors against
    time (right, log scale; conserved quantities with machine epsilon)."""
    from matplotlib import colormaps
    from matplotlib.figure import Figure

    data = summary["_plot"]
    invariants = (ENERGY,) + scene.invariants
    panels = [(inv.label, inv, data["errors"][inv.name]) for inv in invariants]
    if data["reference"] is not None:
        panels.append((scene.reference_label, None, data["reference"]))
    n_members = data["trajectory"].shape[0]
    colors = [colormaps["tab10"](k % 10) for k in range(n_members)]
    run = summary["run"]
    fig = Figure(figsize=(12, 6.5), dpi=90)
    fig.suptitle(
        f"{scene.name}: {scene.description}\n{run['method']} ({run['form']} march), order "
        f"{run['order']}, dt = {run['dt']:g}, {run['n_steps']} steps, "
        f"{summary['scene']['members']} member(s), first {n_members} shown",
        fontsize=10,
    )
    grid = fig.add_gridspec(
        len(panels), 2, width_ratios=(1.1, 1.0), left=0.06, right=0.97, bottom=0.08, top=0.86, hspace=0.35, wspace=0.22
    )
    scene.plot(fig.add_subplot(grid[:, 0]), data["t_traj"], data["trajectory"], data["setup"], colors)
    eps = float(np.finfo(float).eps)
    floor = 1e-17
    axes = []
    for row, (label, inv, err) in enumerate(panels):
        ax = fig.add_subplot(grid[row, 1], sharex=axes[0] if axes else None)
        axes.append(ax)
        t = data["t_err"][: err.shape[1]]
        for y, col in zip(err, colors):
            ax.plot(t, np.maximum(y, floor), color=col, lw=0.7)
        ax.set_yscale("log")
        if inv is not None and inv.roundoff:
            ax.axhline(eps, color="k", lw=0.6, ls=":")
        kind = "" if inv is None else (" (rel. drift)" if inv.kind == "drift" else "")
        worst = np.nanmax(err) if np.any(np.isfinite(err)) else math.nan
        ax.set_title(f"{label}{kind}: max {worst:.2e}", fontsize=9, pad=2)
        ax.tick_params(labelsize=8)
        ax.grid(True, lw=0.3, alpha=0.5)
        if row < len(panels) - 1:
            ax.tick_params(labelbottom=False)
    axes[-1].set_xlabel("t")
    fig.savefig(path)
