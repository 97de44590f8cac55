"""Issue 2, check 6: a system written from scratch here, not among the models, goes through
the same API and passes order and momentum checks. A free planar body on SE(2)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import clebsch_jax as cj
from clebsch_jax import diagnostics as dg

INERTIA, MASS = 0.7, 1.3


def se2_system(derivative_map=cj.cayley):
    """ξ = (ω, v₁, v₂) body velocities, Q ∈ SE(2) as a 3×3 homogeneous matrix, L_ξQ = Q ξ̂."""
    return cj.ClebschSystem(
        lagrangian=lambda xi: 0.5 * INERTIA * xi[0] ** 2 + 0.5 * MASS * (xi[1] ** 2 + xi[2] ** 2),
        velocity_map=lambda xi, Q: Q @ cj.lie.se2_hat(xi),
        derivative_map=derivative_map,
    )


def se2(theta, x, y):
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


def exact(t, theta0, x0, xi0):
    """A free body spins at constant ω while its centre moves at constant spatial velocity."""
    w, v = xi0[0], np.asarray(xi0[1:])
    R0 = se2(theta0, 0, 0)[:2, :2]
    pos = np.array([x0[0], x0[1]]) + R0 @ v * t
    return se2(theta0 + w * t, pos[0], pos[1])


def test_se2_body_converges_at_order_two_to_the_exact_solution():
    theta0, x0, xi0 = 0.4, (1.0, -0.5), np.array([1.3, 0.8, -0.4])
    system = se2_system()
    T, dts = 3.0, np.array([0.2, 0.1, 0.05, 0.025])
    n = int(round(T / dts[-1]))
    run = jax.jit(lambda dt: cj.integrate(system, se2(theta0, *x0), xi0, dt=dt, n_steps=n, reduce=False))
    errs = []
    for dt in dts:
        sol = run(dt)
        k = int(round(T / dt))
        errs.append(np.max(np.abs(np.asarray(sol.Q[k]) - exact(T, theta0, x0, xi0))))
    assert sol.order == 2
    assert abs(dg.fit_order(dts, errs) - sol.order) < 0.15, errs


@pytest.mark.slow  # its own long run; the SE(2) body's order-two convergence runs by default
def test_se2_noether_momentum_and_group_structure_are_preserved():
    """l is left-invariant, so the momentum of the left SE(2) action is conserved exactly."""
    system = se2_system()
    sol = cj.integrate(system, se2(0.4, 1.0, -0.5), jnp.array([1.3, 0.8, -0.4]), dt=0.1, n_steps=5000, reduce=False)
    gens = lambda Q: jnp.stack([cj.lie.se2_hat(e) @ Q for e in jnp.eye(3)])
    J = np.asarray(dg.noether_momentum(sol, gens))
    # The pairing <p, Y(Q)> sums terms of size |x||p| that grow as the body translates
    # (|x| reaches ~500 here), so round-off is relative to those terms, not to |J|.
    terms = np.asarray(jax.vmap(lambda q, p: jnp.sum(jnp.abs(gens(q) * p[None])))(sol.Q, sol.p))
    assert np.max(np.abs(J - J[0])) < 1e-12 * np.max(terms)
    Q = np.asarray(sol.Q)
    np.testing.assert_allclose(Q[:, 2, :], np.tile([0.0, 0.0, 1.0], (len(Q), 1)), atol=1e-14)
    assert float(jnp.max(dg.orthogonality_error(jnp.asarray(Q[:, :2, :2])))) < 1e-12
    E = np.asarray(dg.energy(system, sol))
    # For the free SE(2) body ω and |v| are invariants of the discrete flow too (the CAY map
    # preserves them), so the energy is conserved to accumulated round-off, not just bounded.
    assert np.max(np.abs(E - E[0])) / E[0] < 1e-10
