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

The scenes are defined by family in `_scenes_bodies`, `_scenes_particles` and `_scenes_fluid`
(on the types of `_scene_types`); the run that reduces a scene's batch to a summary and a plot
is in `_scene_run`.
"""

from __future__ import annotations

from ._scene_types import ENERGY, Invariant, Scene, Setup
from ._scenes_bodies import HEAVY_TOP, RIGID_BODY
from ._scenes_fluid import EULER_SPHERE
from ._scenes_particles import LANDMARKS, PEAKONS, VORTEX_CIRCULATIONS, VORTICES

__all__ = ["Scene", "Invariant", "Setup", "ENERGY", "SCENES", "VORTEX_CIRCULATIONS"]

SCENES: dict[str, Scene] = {s.name: s for s in (RIGID_BODY, HEAVY_TOP, VORTICES, PEAKONS, LANDMARKS, EULER_SPHERE)}
"""The built-in scenes by name, in the order `clebsch-jax run --help` lists them."""
