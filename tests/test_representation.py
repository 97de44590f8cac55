"""A matrix representation declared by the velocity map (`cj.UnitaryAlgebra`): its algebra
against its definition (skew-Hermitian, isometric, closed, adjoint of the pairings), JAX's
conjugate convention for gradients of real functions of complex arrays, and the reduced march
computed in it against the same system in the real form (`euler_sphere(N, form="real")`):
the same steps, configurations and gradients to round-off, and the full march agreeing."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import clebsch_jax as cj
from clebsch_jax.discrete.matrix_group import find_reduction
from clebsch_jax.march.carry import input_ok, velocity_map_linear

models = cj.models
N = 4  # the euler_sphere tests' vmap/grad size: programs shared where the shapes agree


def random_complex(rng, *shape):
    return rng.normal(size=shape) + 1j * rng.normal(size=shape)


def real_inner(A, B):
    """⟨A, B⟩ = Re tr(Aᴴ B), computed in NumPy."""
    return float(np.real(np.sum(np.conj(A) * B)))


def test_unitary_algebra_is_an_isometry_onto_a_closed_skew_hermitian_algebra():
    rep = cj.UnitaryAlgebra(N)
    rng = np.random.default_rng(0)
    S1, S2 = rng.normal(size=(2, N, N))
    Z1, Z2 = np.asarray(rep.X(S1)), np.asarray(rep.X(S2))
    assert np.max(np.abs(Z1 + Z1.conj().T)) == 0.0  # skew-Hermitian, exactly
    assert real_inner(Z1, Z2) == pytest.approx(float(np.sum(S1 * S2)), rel=1e-14)
    # X⁻¹ = Xᵀ on the algebra, and the commutator stays in it
    assert np.max(np.abs(rep.X_inv(Z1) - S1)) < 1e-15
    C = Z1 @ Z2 - Z2 @ Z1
    assert np.max(np.abs(np.asarray(rep.X(rep.X_adjoint(C))) - C)) < 1e-14 * np.max(np.abs(C))
    # X_adjoint is X's adjoint for the pairings ⟨X(η), M⟩ = η · Xᵀ(M), M any complex matrix
    M = random_complex(rng, N, N)
    assert real_inner(M, np.asarray(rep.X(S1))) == pytest.approx(float(np.sum(S1 * rep.X_adjoint(M))), rel=1e-14)
    # the real form: R(Z₁Z₂) = R(Z₁)R(Z₂), and to_ambient inverts it
    R1, R2 = rep.from_ambient(Z1), rep.from_ambient(Z2)
    assert np.max(np.abs(rep.from_ambient(Z1 @ Z2) - R1 @ R2)) < 1e-14
    assert np.max(np.abs(rep.to_ambient(R1) - Z1)) == 0.0
    # as the velocity map: right multiplication by R(X(S)) of any real 2N×2N Q
    Q = rng.normal(size=(2 * N, 2 * N))
    assert np.max(np.abs(rep(S1, Q) - Q @ R1)) < 1e-14


def test_jax_gradient_of_a_real_function_of_a_complex_matrix_is_the_conjugate():
    """JAX's convention, which `core.representation` states: for f(Z) = Re tr(Mᴴ Z) (Riesz
    gradient M for the pairing Re tr(AᴴB)), `jax.grad(f)(Z)` is conj(M). Through the real
    coordinates of the representation no conjugate appears: the gradient of S ↦ f(X(S)) is
    Xᵀ(M), as the reduced step uses it."""
    rep = cj.UnitaryAlgebra(N)
    rng = np.random.default_rng(1)
    M, Z = random_complex(rng, N, N), random_complex(rng, N, N)
    f = lambda Z: jnp.real(jnp.sum(jnp.conj(M) * Z))
    assert np.max(np.abs(jax.grad(f)(jnp.asarray(Z)) - np.conj(M))) < 1e-15
    S = rng.normal(size=(N, N))
    assert np.max(np.abs(jax.grad(lambda S: f(rep.X(S)))(S) - rep.X_adjoint(M))) < 1e-15


def start(seed, form, n=N):
    """(Q0, xi0) of a random vorticity of size n (amplitude ~ 1/(1 + l)) in the given form."""
    rng = np.random.default_rng(seed)
    c = np.tril(random_complex(rng, n, n)) * (1.0 + np.arange(n))[:, None] ** -1.0
    c[:, 0], c[0, 0] = c[:, 0].real, 0.0
    return models.euler_sphere_start(models.euler_sphere_quantise(c), form)


def test_unitary_form_steps_as_the_real_form():
    """The same vorticity, spectrum and configuration at every node (reconstruct=True: Q from
    the complex solve of the Cayley map, stored in its real form) as the real 2N×2N form,
    to round-off; the unitary form's configurations stay unitary."""
    sols, Ws, n = {}, {}, 3  # the smallest size with all three kinds of diagonals
    for form in models.EULER_SPHERE_FORMS:
        Q0, xi0 = start(12, form, n)
        sols[form] = cj.integrate(models.euler_sphere(n, form=form), Q0, xi0, dt=0.1, n_steps=40, backend="xla")
        Ws[form] = np.asarray(models.euler_sphere_vorticity(sols[form].momentum, form))
    scale = np.max(np.abs(Ws["real"]))
    assert np.max(np.abs(Ws["unitary"] - Ws["real"])) < 1e-13 * scale
    assert np.max(np.abs(Ws["unitary"][-1] - Ws["unitary"][0])) > 1e-2 * scale  # it moved
    assert np.max(np.abs(sols["unitary"].Q - sols["real"].Q)) < 1e-13
    U = np.asarray(cj.UnitaryAlgebra(n).to_ambient(sols["unitary"].Q[-1]))
    assert np.max(np.abs(U.conj().T @ U - np.eye(n))) < 1e-13


@pytest.mark.slow  # two differentiated marches (both forms) compiled; the default run's
# test_euler_sphere.py::test_vmap_and_grad_through_the_sweeps differentiates the unitary form
def test_gradient_through_the_unitary_form_equals_the_real_forms():
    """d/da of the final energy from ξ0 + a·δξ, by the sweeps' implicit derivative through the
    complex products, equals the real form's derivative (same function of a) to round-off of
    the two routes."""

    def derivative(form):
        (Q0, xi0), (_, direction) = start(13, form), start(14, form)
        system = models.euler_sphere(N, form=form)
        method = cj.ReducedStep(root_finder=cj.FixedPoint(), reconstruct=False)

        def energy(a):
            sol = cj.integrate(system, Q0, xi0 + a * direction, dt=0.05, n_steps=10, method=method, throw=False)
            return models.euler_sphere_energy(models.euler_sphere_vorticity(sol.momentum[-1], form))

        return float(jax.grad(energy)(0.0))

    unitary, real = derivative("unitary"), derivative("real")
    assert abs(unitary) > 1e-6
    assert unitary == pytest.approx(real, rel=1e-10)


@pytest.mark.slow  # dense Newton of the full march (dim V + 2 dim M = 36 unknowns, N = 2) compiled
def test_full_march_on_the_representation_agrees_with_the_reduced_march():
    """The velocity map called as a map (Q·R(X(S))) gives the full march of the same system,
    which the reduced march computed in complex matrices reproduces."""
    Nf = 2
    W = models.euler_sphere_quantise(np.array([[0.0, 0.0], [0.7, 0.4 + 0.3j]]))
    Q0, xi0 = models.euler_sphere_start(W)
    system = models.euler_sphere(Nf)
    reduced = cj.integrate(system, Q0, xi0, dt=0.1, n_steps=10, method=cj.ReducedStep(root_finder=cj.Newton()))
    full = cj.integrate(system, Q0, xi0, dt=0.1, n_steps=10, method=cj.FullStep(cj.Principle.LEFT))
    assert np.max(np.abs(full.Q - reduced.Q)) < 1e-12
    assert np.max(np.abs(full.momentum - reduced.momentum)) < 1e-12


def test_declared_representation_refusals():
    rep = cj.UnitaryAlgebra(N)
    with pytest.raises(ValueError, match="n: expected a positive integer"):
        cj.UnitaryAlgebra(0)
    with pytest.raises(ValueError, match="derivative_map: the unitary form"):
        models.euler_sphere(N, cj.exponential)
    Q0, xi0 = jnp.eye(2 * N), jnp.zeros((N, N))
    potential = cj.ClebschSystem(
        lagrangian=lambda xi, Q: 0.5 * jnp.sum(xi**2) + jnp.sum(Q), velocity_map=rep, derivative_map=cj.cayley
    )
    assert "without potential" in find_reduction(potential, Q0, xi0)[1]
    plain = cj.ClebschSystem(lagrangian=lambda xi: 0.5 * jnp.sum(xi**2), velocity_map=rep, derivative_map=cj.cayley)
    assert find_reduction(plain, Q0, jnp.zeros((N + 1, N + 1)))[0] is None
    exp_system = cj.ClebschSystem(
        lagrangian=lambda xi: 0.5 * jnp.sum(xi**2), velocity_map=rep, derivative_map=cj.exponential
    )
    with pytest.raises(ValueError, match="Cayley map only"):
        cj.ReducedStep().prepare(exp_system, Q0, xi0)


class _BentUnitary(cj.UnitaryAlgebra):
    """UnitaryAlgebra with a term quadratic in ξ in X: not a velocity map (Definition 1)."""

    def X(self, xi):
        return super().X(xi + 0.1 * xi * xi)


@pytest.mark.slow  # ~1.5 s of compiling the traced checks; the default run covers input_ok and
# velocity_map_linear on undeclared velocity maps (test_model_checks)
def test_traced_checks_read_a_declared_representation_through_X():
    """The checks a traced march makes at its start (`march.carry.input_ok`,
    `velocity_map_linear`) evaluate a declared representation's factor X(ξ) instead of the
    product Q⁰·R(X(ξ)) of the ambient size 2n: a nonlinear X still fails them, a NaN in ξ⁰ too,
    and the linear UnitaryAlgebra passes."""
    n = 3
    Q0, xi0 = start(15, "unitary", n)
    model = models.euler_sphere(n)

    def system(velocity_map):
        return cj.ClebschSystem(lagrangian=model.lagrangian, velocity_map=velocity_map, derivative_map=cj.cayley)

    @jax.jit
    def checks(xi):  # one program for the three systems' checks (not op by op)
        good, bent = system(cj.UnitaryAlgebra(n)), system(_BentUnitary(n))
        ok = lambda x: input_ok(good, Q0, x, None, 0.1)
        return (
            ok(xi),
            velocity_map_linear(good, Q0, xi),
            velocity_map_linear(bent, Q0, xi),
            ok(xi.at[0, 0].set(jnp.nan)),
        )

    assert [bool(b) for b in checks(xi0)] == [True, True, False, False]
