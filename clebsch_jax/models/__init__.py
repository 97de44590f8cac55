"""Built-in models. Each is a constructor returning a `ClebschSystem`: models are data.

Parameters are array leaves (held by `jax.tree_util.Partial`), so a parameter sweep is a
`jax.vmap` over the constructor's arguments.
"""

from ._heavy_top import heavy_top as heavy_top
from ._point_vortices import point_vortices as point_vortices
from ._point_vortices import vortex_angular_impulse as vortex_angular_impulse
from ._point_vortices import vortex_hamiltonian as vortex_hamiltonian
from ._point_vortices import vortex_linear_impulse as vortex_linear_impulse
from ._point_vortices import vortex_velocity as vortex_velocity
from ._rigid_body import rigid_body as rigid_body

__all__ = [
    "rigid_body",
    "heavy_top",
    "point_vortices",
    "vortex_hamiltonian",
    "vortex_velocity",
    "vortex_linear_impulse",
    "vortex_angular_impulse",
]
