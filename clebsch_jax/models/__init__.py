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
from ._euler_sphere import euler_sphere as euler_sphere
from ._euler_sphere import EULER_SPHERE_FORMS as EULER_SPHERE_FORMS
from ._euler_sphere import euler_sphere_hbar as euler_sphere_hbar
from ._euler_sphere import euler_sphere_laplacian as euler_sphere_laplacian
from ._euler_sphere import euler_sphere_inverse_laplacian as euler_sphere_inverse_laplacian
from ._euler_sphere import euler_sphere_real_form as euler_sphere_real_form
from ._euler_sphere import euler_sphere_complex_form as euler_sphere_complex_form
from ._euler_sphere import euler_sphere_start as euler_sphere_start
from ._euler_sphere import euler_sphere_vorticity as euler_sphere_vorticity
from ._euler_sphere_quantisation import euler_sphere_quantise as euler_sphere_quantise
from ._euler_sphere_quantisation import euler_sphere_coefficients as euler_sphere_coefficients
from ._euler_sphere_quantisation import euler_sphere_field as euler_sphere_field
from ._euler_sphere_quantisation import euler_sphere_basis as euler_sphere_basis
from ._euler_sphere import euler_sphere_casimirs as euler_sphere_casimirs
from ._euler_sphere import euler_sphere_energy as euler_sphere_energy
from ._euler_sphere import euler_sphere_angular_momentum as euler_sphere_angular_momentum
from ._euler_sphere_quantisation import euler_sphere_orthographic as euler_sphere_orthographic
from ._heavy_top import heavy_top as heavy_top
from ._point_vortices import check_distinct_vortices as check_distinct_vortices
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
    "check_distinct_vortices",
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
    "euler_sphere",
    "EULER_SPHERE_FORMS",
    "euler_sphere_hbar",
    "euler_sphere_laplacian",
    "euler_sphere_inverse_laplacian",
    "euler_sphere_real_form",
    "euler_sphere_complex_form",
    "euler_sphere_start",
    "euler_sphere_vorticity",
    "euler_sphere_quantise",
    "euler_sphere_coefficients",
    "euler_sphere_field",
    "euler_sphere_basis",
    "euler_sphere_casimirs",
    "euler_sphere_energy",
    "euler_sphere_angular_momentum",
    "euler_sphere_orthographic",
]
