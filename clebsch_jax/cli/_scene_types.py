r"""The types of the built-in scenes (`Scene`, `Setup`, `Invariant`) and what every scene shares:
the energy, reported for all, and the orthogonality error of a rotation.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

import clebsch_jax as cj
from clebsch_jax import diagnostics

__all__ = ["Invariant", "Setup", "Scene", "ENERGY", "orthogonality"]


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
def _energy_values(system, sol):
    return diagnostics.energy(system, sol)


ENERGY = Invariant("energy", "energy", _energy_values, kind="drift", roundoff=False)
"""The energy $E = \\langle\\delta l/\\delta\\xi, \\xi\\rangle - l$ (`diagnostics.energy`), reported for every scene."""


def orthogonality(system, sol):
    return diagnostics.orthogonality_error(sol.Q)
