r"""A sweep's member is checked as `integrate` checks it (issues 40 and 44).

- **The first step.** `integrate` compares step 0 with two half steps from the start
  (`clebsch_jax.march.scan.first_step_probe`): a spurious root of the first step's equations can
  change the energy by little next to its terms (at the perihelion of an eccentric orbit), so
  the per-step energy check does not see it. A sweep makes the same check in its first chunk, on
  both backends, and reports the same status at the same step; the members that pass it are
  untouched (their finals are `integrate`'s, to the bit on XLA, to round-off natively).
- **The isotropy gauge.** A Lagrangian written with the physical velocity ξ × q does not see the
  isotropy ξ ∥ q: `integrate` fixes its gauge, with a weight found at the member's (Q⁰, ξ⁰), and
  takes ξ⁰ as its physical velocity. A sweep does the same for every member (the gauge's rank
  found on the first, checked on each), so its members are `integrate`'s runs. So does
  `integrate` under `jax.jit`/`jax.vmap`, the rank decided at trace time on a concrete example.
"""

import warnings

import jax.numpy as jnp
import numpy as np
import pytest

import clebsch_jax as cj


def _planar(potential):
    """A particle in the plane (or space) with the central potential V(r): l = ½|ξ|² − V(|q|)."""

    def lagrangian(xi, q):
        return 0.5 * jnp.sum(xi**2) - potential(jnp.sqrt(jnp.sum(q**2)))

    return cj.ClebschSystem(lagrangian=lagrangian, velocity_map=lambda xi, q: xi, derivative_map=cj.forward_difference)


KEPLER = _planar(lambda r: -1.0 / r)
YUKAWA = _planar(lambda r: -jnp.exp(-0.5 * r) / r)  # a screened attraction: another system, another root


def _perihelion(e, dim=2):
    """The perihelion of the Kepler orbit of eccentricity e and semi-major axis 1."""
    q, v = np.zeros(dim), np.zeros(dim)
    q[0], v[1] = 1.0 - e, np.sqrt((1.0 + e) / (1.0 - e))
    return q, v


# (system, eccentricities, dt per member): the case (e = 0.95, dt = 0.05: FIRST_STEP),
# resolved orbits (SUCCESS), a first step the energy check fails (ENERGY_JUMP) and one that does
# not converge (MAX_ITERATIONS); with the screened potential, e = 0.9 at dt = 0.2 is spurious
CASES = {
    "kepler": (KEPLER, [0.95, 0.5, 0.95, 0.9, 0.3], [0.05, 0.05, 0.1, 0.05, 0.02]),
    "yukawa": (YUKAWA, [0.9, 0.5, 0.95, 0.9, 0.3], [0.2, 0.05, 0.1, 0.05, 0.02]),
}
N_STEPS, CHUNK = 10, 4  # three chunks: the check belongs to the first only


@pytest.mark.parametrize(
    "case, backend",
    [
        ("kepler", "native"),
        pytest.param("kepler", "xla", marks=pytest.mark.slow),  # a second sweep program compiled
        pytest.param("yukawa", "native", marks=pytest.mark.slow),
        pytest.param("yukawa", "xla", marks=pytest.mark.slow),
    ],
)
def test_a_sweep_checks_the_first_step_as_integrate_does(case, backend):
    system, es, dts = CASES[case]
    Q0, xi0 = map(np.stack, zip(*[_perihelion(e) for e in es]))
    dts = np.asarray(dts)
    sols = [
        cj.integrate(system, Q0[m], xi0[m], dt=dts[m], n_steps=N_STEPS, throw=False, backend=backend)
        for m in range(len(es))
    ]
    status = np.array([int(s.result) for s in sols])
    failed_step = np.array([int(s.failed_step) for s in sols])
    assert status[0] == cj.Status.FIRST_STEP and failed_step[0] == 0  # the case the sweep missed
    assert {cj.Status.SUCCESS, cj.Status.ENERGY_JUMP} <= set(status.tolist())
    res = cj.sweep(system, None, Q0, xi0, dt=dts, n_steps=N_STEPS, chunk_steps=CHUNK, backend=backend)
    np.testing.assert_array_equal(res.status, status)
    np.testing.assert_array_equal(res.failed_step, failed_step)
    ok = status == cj.Status.SUCCESS
    assert np.all(np.isnan(res.final_Q[~ok]))
    # integrate on the same backend: XLA's sweep runs integrate's own program chunk after chunk
    # (the same numbers); the native sweep's kernel is another program than integrate's native
    # loop kernel, with the same steps in another order of (correctly rounded) operations
    tol = 0.0 if backend == "xla" else 1e-12
    final_Q = np.array([np.asarray(s.Q[-1]) for s in sols])
    np.testing.assert_allclose(res.final_Q[ok], final_Q[ok], rtol=0, atol=tol)


# --------------------------------------------------------------------------------------------
# the isotropy gauge: the conical pendulum written with its physical velocity (issue 44)

CONICAL = cj.ClebschSystem(
    lagrangian=lambda xi, q: 0.5 * jnp.sum(jnp.cross(xi, q) ** 2) - 0.8 * q[2],
    velocity_map=lambda xi, q: jnp.cross(xi, q),
    derivative_map=cj.forward_difference,
)


def _on_the_sphere():
    """Four members at other points of the sphere, each with ξ⁰ = e₃ + c q⁰ (c differs: the same
    physical velocity e₃ × q⁰ whatever c), and a fifth at the origin, where ξ ↦ ξ × q has no
    rank at all (another orbit type than the first member's)."""
    theta, phi = np.array([0.3, 0.6, 0.9, 1.2]), np.array([0.0, 1.0, 2.0, 3.0])
    Q0 = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), -np.cos(theta)], -1)
    xi0 = np.array([0.0, 0.0, 1.0]) + np.array([0.0, 1.7, -0.5, 3.0])[:, None] * Q0
    return np.concatenate([Q0, np.zeros((1, 3))]), np.concatenate([xi0, [[0.0, 0.0, 1.0]]])


@pytest.mark.slow  # the gauged step compiled for integrate and a sweep (minutes on a loaded host)
@pytest.mark.parametrize("backend", ["native", "xla"])
def test_a_sweep_gauges_the_isotropy_as_integrate_does(backend):
    Q0, xi0 = _on_the_sphere()
    n, dt = 12, 0.05
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # integrate's "xi0 has a component along the isotropy"
        sols = [cj.integrate(CONICAL, Q0[m], xi0[m], dt=dt, n_steps=n) for m in range(4)]
    # the sweep says once that the four members' ξ⁰ lose their isotropy component (the fifth is refused)
    with pytest.warns(UserWarning, match=r"xi0: 4 of 5 members \(the first: member 0\)"):
        res = cj.sweep(CONICAL, None, Q0, xi0, dt=dt, n_steps=n, chunk_steps=5, backend=backend)
    assert all(s.isotropy == 1 for s in sols)
    # the member at the origin is not of the first member's orbit type: refused, not marched
    np.testing.assert_array_equal(res.status, [cj.Status.SUCCESS] * 4 + [cj.Status.INVALID_INPUT])
    final_Q = np.array([np.asarray(s.Q[-1]) for s in sols])
    final_xi = np.array([np.asarray(s.xi[-1]) for s in sols])
    # the same gauge weight and starting velocity as integrate's, found in the sweep's program:
    # round-off apart (the physical part by Gram-Schmidt there, by an SVD in integrate)
    np.testing.assert_allclose(res.final_Q[:4], final_Q, rtol=0, atol=1e-13)
    np.testing.assert_allclose(res.final_xi[:4], final_xi, rtol=0, atol=1e-13)
    assert np.max(np.abs(np.sum(res.final_xi[:4] * res.final_Q[:4], axis=-1))) < 1e-13  # no isotropy component
    # given their physical parts, the same members start where they did, and nothing is said
    physical = xi0 - np.sum(xi0 * Q0, axis=-1, keepdims=True) * Q0
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        again = cj.sweep(CONICAL, None, Q0, physical, dt=dt, n_steps=n, chunk_steps=5, backend=backend)
    assert not [w for w in said if "isotropy of their Q0" in str(w.message)]
    np.testing.assert_allclose(again.final_Q[:4], res.final_Q[:4], rtol=0, atol=1e-13)


@pytest.mark.slow  # the gauged march compiled under jit and under vmap
def test_integrate_under_jit_and_vmap_gauges_the_isotropy_as_on_concrete_values():
    """Q⁰ traced: the gauge's rank is decided at trace time on a concrete example
    (`traced_isotropy`), its weight and ξ⁰'s physical part in the program; the runs are the
    concrete ones (no `cj.gauge_isotropy` by hand), and the member at the origin (no rank at
    all) is refused as an invalid input, not marched with a wrong gauge."""
    import jax

    Q0, xi0 = _on_the_sphere()
    Q0, xi0 = Q0[[0, 1, 2, 4]], xi0[[0, 1, 2, 4]]
    n, dt = 12, 0.05
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # integrate's "xi0 has a component along the isotropy"
        concrete = [cj.integrate(CONICAL, Q0[m], xi0[m], dt=dt, n_steps=n) for m in range(3)]
    run = lambda q, x: cj.integrate(CONICAL, q, x, dt=dt, n_steps=n, throw=False)  # noqa: E731
    traced = jax.jit(run)(Q0[1], xi0[1])
    assert traced.isotropy == 1 and int(traced.result) == cj.Status.SUCCESS
    np.testing.assert_allclose(np.asarray(traced.Q), np.asarray(concrete[1].Q), rtol=0, atol=1e-14)
    batched = jax.vmap(run)(Q0, xi0)
    np.testing.assert_array_equal(batched.result, [cj.Status.SUCCESS] * 3 + [cj.Status.INVALID_INPUT])
    for m in range(3):
        np.testing.assert_allclose(np.asarray(batched.Q[m]), np.asarray(concrete[m].Q), rtol=0, atol=1e-14)
        np.testing.assert_allclose(np.asarray(batched.xi[m]), np.asarray(concrete[m].xi), rtol=0, atol=1e-13)
