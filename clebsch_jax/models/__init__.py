"""Built-in models. Each is a constructor returning a `ClebschSystem`: models are data.

Parameters are array leaves (held by `jax.tree_util.Partial`), so a parameter sweep is a
`jax.vmap` over the constructor's arguments.
"""

from ._epdiff import peakons as peakons
from ._epdiff import ordered_difference as ordered_difference
from ._epdiff import OrderedDifference as OrderedDifference
from ._epdiff import peakon_kernel_matrix as peakon_kernel_matrix
from ._epdiff import peakon_hamiltonian as peakon_hamiltonian
from ._epdiff import peakon_velocity as peakon_velocity
from ._epdiff import peakon_momenta as peakon_momenta
from ._epdiff import peakon_field as peakon_field
from ._epdiff import landmarks as landmarks
from ._epdiff import landmark_kernel_matrix as landmark_kernel_matrix
from ._epdiff import landmark_hamiltonian as landmark_hamiltonian
from ._epdiff import landmark_velocity as landmark_velocity
from ._epdiff import landmark_momenta as landmark_momenta
from ._epdiff import landmark_field as landmark_field
from ._epdiff import landmark_angular_momentum as landmark_angular_momentum
from ._heavy_top import heavy_top as heavy_top
from ._point_vortices import point_vortices as point_vortices
from ._point_vortices import vortex_angular_impulse as vortex_angular_impulse
from ._point_vortices import vortex_hamiltonian as vortex_hamiltonian
from ._point_vortices import vortex_linear_impulse as vortex_linear_impulse
from ._point_vortices import vortex_velocity as vortex_velocity
from ._sphere_vortices import point_vortices_sphere as point_vortices_sphere
from ._sphere_vortices import sphere_vortex_hamiltonian as sphere_vortex_hamiltonian
from ._sphere_vortices import sphere_vortex_lift as sphere_vortex_lift
from ._sphere_vortices import sphere_vortex_moment as sphere_vortex_moment
from ._sphere_vortices import sphere_vortex_positions as sphere_vortex_positions
from ._sphere_vortices import sphere_vortex_velocity as sphere_vortex_velocity
from ._sphere_vortices import sphere_vortex_xi as sphere_vortex_xi
from ._rigid_body import ROTATION_TOLERANCE as ROTATION_TOLERANCE
from ._rigid_body import check_rotation as check_rotation
from ._rigid_body import rigid_body as rigid_body
from ._rigid_body import rigid_body_vector as rigid_body_vector
from ._rigid_body import rigid_body_vector_start as rigid_body_vector_start

__all__ = [
    "rigid_body",
    "rigid_body_vector",
    "rigid_body_vector_start",
    "check_rotation",
    "ROTATION_TOLERANCE",
    "heavy_top",
    "point_vortices",
    "vortex_hamiltonian",
    "vortex_velocity",
    "vortex_linear_impulse",
    "vortex_angular_impulse",
    "point_vortices_sphere",
    "sphere_vortex_lift",
    "sphere_vortex_positions",
    "sphere_vortex_hamiltonian",
    "sphere_vortex_velocity",
    "sphere_vortex_xi",
    "sphere_vortex_moment",
    "peakons",
    "ordered_difference",
    "OrderedDifference",
    "peakon_kernel_matrix",
    "peakon_hamiltonian",
    "peakon_velocity",
    "peakon_momenta",
    "peakon_field",
    "landmarks",
    "landmark_kernel_matrix",
    "landmark_hamiltonian",
    "landmark_velocity",
    "landmark_momenta",
    "landmark_field",
    "landmark_angular_momentum",
]
