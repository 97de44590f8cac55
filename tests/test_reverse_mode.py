r"""Reverse-mode derivatives through `integrate`, checked against central finite differences
of the march itself (an independent route: no derivative rule of the engine is used), on
vector-space systems (an oscillator and a free particle with configurations of shape (2,),
(1, 2) and (2, 1), Kepler in the plane) and on group systems (the rigid body and the heavy top
on SO(3)), for every derivative map (forward difference, Cayley, exponential), principle and stepper.

The reverse-mode derivative of a step is the implicit one (`clebsch_jax.roots.implicit`): its
tangent solve with the step's Jacobian must be linear in the tangent as JAX sees it, or reverse
mode cannot transpose it ("nonlinear div can't be transposed": the small-system elimination
once divided by pivots read from rows that held the tangent). Each gradient program takes
seconds to compile, so the default run checks the elimination directly for every size and one
march of each kind of system; the matrix of systems × maps × principles × steppers is slow.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import clebsch_jax as cj
from clebsch_jax.roots.implicit import dense_tangent_solve

from .systems import translation


def oscillator(xi, Q):
    """l(ξ, Q) = |ξ|²/2 − |Q|²/2: a harmonic oscillator on a vector space."""
    return 0.5 * jnp.sum(xi**2) - 0.5 * jnp.sum(Q**2)


def free(xi, Q):
    """l(ξ) = |ξ|²/2 written with Q (a free particle: no potential)."""
    return 0.5 * jnp.sum(xi**2)


def kepler(xi, Q):
    """l(ξ, Q) = |ξ|²/2 + 1/|Q|: Kepler's problem in the plane."""
    return 0.5 * jnp.sum(xi**2) + 1.0 / jnp.sqrt(jnp.sum(Q**2))


def vector_system(lagrangian, derivative_map=cj.forward_difference):
    return cj.ClebschSystem(lagrangian=lagrangian, velocity_map=translation, derivative_map=derivative_map)


W = np.array([1.3, 0.8, -0.4])
INERTIA = np.array([2.0, 1.0, 2.0 / 3.0])
VECTOR = {  # name: (system, Q0, ξ0)
    "oscillator (2,)": (vector_system(oscillator), np.array([0.3, -0.2]), np.array([0.7, 0.1])),
    "oscillator (1, 2)": (vector_system(oscillator), np.array([[0.3, -0.2]]), np.array([[0.7, 0.1]])),
    "oscillator (2, 1)": (vector_system(oscillator), np.array([[0.3], [-0.2]]), np.array([[0.7], [0.1]])),
    "free particle (2,)": (vector_system(free), np.array([0.3, -0.2]), np.array([0.7, 0.1])),
    "kepler (2,)": (vector_system(kepler), np.array([1.0, 0.0]), np.array([0.1, 1.1])),
}
GROUP = {
    "rigid body, cayley": (cj.models.rigid_body(INERTIA), np.eye(3), W),
    "rigid body, forward difference": (cj.models.rigid_body(INERTIA, cj.forward_difference), np.eye(3), W),
    "heavy top, cayley": (cj.models.heavy_top(INERTIA, 0.7), np.eye(3), W),
    "rigid body, exponential": (cj.models.rigid_body(INERTIA, cj.exponential), np.eye(3), W),
}
STEPPERS = {  # integrate options: the principles (full and reduced marches as chosen), and the other steppers
    "default": {},
    "left": {"scheme": "left"},
    "right": {"scheme": "right"},
    "midpoint": {"scheme": "midpoint"},
    "left, full march": {"scheme": "left", "reduce": False},
    "gauss 4": {"scheme": "gauss", "order": 4},
    "composition 4": {"order": 4},
}
DT, N_STEPS = 0.1, 3
WEIGHTS = (0.7, -1.3, 0.4, 1.1, -0.5, 0.9, 0.2, -0.8, 0.6)


def loss(system, Q0, options, xi0):
    """A weighted sum of the final configuration and momentum (weights without symmetry, so
    that no derivative cancels by accident)."""
    sol = cj.integrate(system, jnp.asarray(Q0), xi0, dt=DT, n_steps=N_STEPS, **options)
    q, m = sol.Q[-1].ravel(), sol.momentum[-1].ravel()
    return jnp.dot(q, jnp.asarray(WEIGHTS[: q.size])) + jnp.dot(m, jnp.asarray(WEIGHTS[::-1][: m.size]))


def central_differences(f, x, h=1e-6):
    """∂f/∂x by central differences of the concrete (eagerly run) march."""
    x = np.asarray(x, float)
    out = np.zeros(x.shape)
    for k in np.ndindex(x.shape):
        e = np.zeros(x.shape)
        e[k] = h
        out[k] = (float(f(jnp.asarray(x + e))) - float(f(jnp.asarray(x - e)))) / (2 * h)
    return out


def check_reverse_mode(system, Q0, xi0, options):
    f = functools.partial(loss, system, Q0, options)
    grad = np.asarray(jax.grad(f)(jnp.asarray(xi0, float)))
    # h = 1e-6: truncation O(h²) and round-off O(ε/h) both ≲ 1e-9 of these O(1) derivatives
    np.testing.assert_allclose(grad, central_differences(f, xi0), rtol=1e-7, atol=1e-8)


def test_the_tangent_solve_is_transposable_for_every_size():
    # the tangent solve of a root's implicit derivative (`dense_tangent_solve`: the Jacobian of
    # the linear map g, then a solve) for the closed form (n ≤ 3), the unrolled elimination
    # (4 ≤ n ≤ 8) and the LU loop (n > 8): reverse mode transposes it, y ↦ J⁻¹y into
    # w ↦ J⁻ᵀw, which NumPy computes here
    rng = np.random.default_rng(0)
    for n in (2, 4, 9):  # one of each: the closed form, the elimination, the LU loop
        J, w = rng.normal(size=(n, n)) + n * np.eye(n), rng.normal(size=n)
        solve = lambda y, J=jnp.asarray(J): dense_tangent_solve(lambda v: J @ v, y)
        (transposed,) = jax.jit(jax.linear_transpose(solve, jnp.zeros(n)))(jnp.asarray(w))
        np.testing.assert_allclose(np.asarray(transposed), np.linalg.solve(J.T, w), rtol=1e-12, atol=1e-13)


def test_reverse_mode_on_a_two_dimensional_vector_space_matches_finite_differences():
    check_reverse_mode(*VECTOR["oscillator (1, 2)"], {})


PRINCIPLES = ("default", "left", "right", "midpoint")
CASES = (  # every stepper on one system of each kind, the principles on the others
    [
        (name, stepper)
        for name in ("oscillator (2,)", "kepler (2,)", "rigid body, cayley", "heavy top, cayley")
        for stepper in STEPPERS
    ]
    + [
        (name, stepper)
        for name in ("oscillator (1, 2)", "oscillator (2, 1)", "free particle (2,)")
        for stepper in PRINCIPLES
    ]
    # the forward difference leaves SO(3) with the left and right principles (refused): the
    # symmetric methods only
    + [("rigid body, forward difference", stepper) for stepper in ("default", "midpoint", "gauss 4")]
    # the exact exponential pair of Definitions 23-24 (matrix log and exp): the reduced and full marches
    + [("rigid body, exponential", stepper) for stepper in ("default", "left", "midpoint", "left, full march")]
)


@pytest.mark.slow
@pytest.mark.parametrize("name, stepper", CASES)
def test_reverse_mode_matches_finite_differences(name, stepper):
    system, Q0, xi0 = {**VECTOR, **GROUP}[name]
    check_reverse_mode(system, Q0, xi0, STEPPERS[stepper])


@pytest.mark.slow
def test_reverse_mode_with_respect_to_the_configuration_on_a_vector_space():
    system, Q0, xi0 = VECTOR["kepler (2,)"]
    f = lambda q: loss(system, q, {}, jnp.asarray(xi0))
    grad = np.asarray(jax.grad(f)(jnp.asarray(Q0)))
    np.testing.assert_allclose(grad, central_differences(f, Q0), rtol=1e-7, atol=1e-8)
