"""`scheme="gauss"` on a degenerate Lagrangian (l affine in ξ): point vortices. The stage
Clebsch relations are constraints there, enforced by ξ (`clebsch_jax.discrete.collocation.degenerate_sweep`);
nothing vortex-specific is written in the engine."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import clebsch_jax as cj
from clebsch_jax import diagnostics as dg
from clebsch_jax import models

from .helpers import vortex_reference

LEAPFROG_GAMMA = np.array([1.0, -1.0, 1.0, -1.0])
LEAPFROG_Q0 = np.array([[0.0, 1.0], [0.0, -1.0], [0.0, 0.5], [0.0, -0.5]])
MIXED_GAMMA = np.array([1.0, -0.5, 0.7, 0.4])  # the scene of test_composition's vortex orders


def _mixed_q0():
    return np.random.default_rng(3).uniform(-1.0, 1.0, (4, 2))


def _random_vortices(n, seed):
    rng = np.random.default_rng(seed)
    gamma = rng.uniform(0.5, 1.5, n) * rng.choice([-1.0, 1.0], n)
    return gamma, rng.normal(size=(n, 2)) * np.sqrt(n)


def _run(gamma, Q0, dt, n_steps, **kw):
    return cj.integrate(
        models.point_vortices(gamma),
        Q0,
        models.vortex_velocity(gamma, Q0),
        dt=dt,
        n_steps=n_steps,
        scheme="gauss",
        **kw,
    )


@pytest.mark.slow  # two vortex programs of their own; the orders against DOP853 run by default
def test_one_stage_is_the_midpoint_principle():
    """One stage: the implicit midpoint rule, as the midpoint principle's Newton solve gives it
    (measured 2e-15 apart after 80 steps)."""
    gamma, Q0 = MIXED_GAMMA, _mixed_q0()
    gauss = _run(gamma, Q0, 0.05, 80, order=2)
    mid = cj.integrate(models.point_vortices(gamma), Q0, models.vortex_velocity(gamma, Q0), dt=0.05, n_steps=80)
    assert gauss.scheme == "gauss" and gauss.order == 2 and gauss.xi is None and mid.scheme == "midpoint"
    assert np.max(np.abs(np.asarray(gauss.Q) - np.asarray(mid.Q))) < 1e-13


# Δt in each order's asymptotic regime and above the reference's floor (measured fits 3.99,
# 5.99, 7.92); T/Δt an integer.
VORTEX_DTS = {4: [0.2, 0.1, 0.05], 6: [0.4, 0.2, 0.1], 8: [0.5, 0.4, 0.25, 0.2]}


@pytest.mark.parametrize(
    "order", [4, *(pytest.param(k, marks=pytest.mark.slow) for k in (6, 8))]
)  # 6, 8: in CI's slow run
def test_point_vortex_orders_against_dop853(order):
    """Four vortices of mixed sign, Q(T) against SciPy DOP853 at rtol 1e-13; log-log fit within
    0.15 of the order."""
    gamma, Q0 = MIXED_GAMMA, _mixed_q0()
    T, dts = 4.0, np.array(VORTEX_DTS[order])
    ref = vortex_reference(gamma, Q0, np.array([0.0, T]))[-1]
    system = models.point_vortices(gamma)
    xi0 = models.vortex_velocity(gamma, Q0)
    errs = []
    for dt in dts:
        # concrete calls: one compiled chunk program for every dt and run length, the one the
        # leapfrogging test below uses for order 8 as well
        sol = cj.integrate(system, Q0, xi0, dt=dt, n_steps=int(round(T / dt)), scheme="gauss", order=order)
        assert np.isclose(float(sol.ts[-1]), T)
        errs.append(np.max(np.abs(np.asarray(sol.Q[-1]) - ref)))
    assert sol.form == "full" and sol.order == order and sol.scheme == "gauss"
    assert abs(dg.fit_order(dts, errs) - order) < 0.15, errs


@pytest.mark.slow  # compiles a Gauss march of two vortex pairs; test_point_vortex_orders_against_dop853[4] keeps
# Gauss on vortices in the default run, and tests/test_vortices.py the impulses of the midpoint march
def test_leapfrogging_keeps_impulses_to_roundoff_and_bounds_H():
    """Order 8 at Δt = 0.2 over T = 400 (about 70 leapfrogging cycles): the linear impulse
    (linear) and the angular impulse (quadratic) are kept to round-off, H stays bounded with no
    drift; the pairs keep their widths (|y| ≤ 1) and travel on along x."""
    sol = _run(LEAPFROG_GAMMA, LEAPFROG_Q0, 0.2, 2000, order=8)
    Q = np.asarray(sol.Q)
    lin = np.asarray(models.vortex_linear_impulse(LEAPFROG_GAMMA, Q))
    ang = np.asarray(models.vortex_angular_impulse(LEAPFROG_GAMMA, Q))
    # the pairs travel ~85 along x: round-off is relative to the sizes the sums are made of,
    # Σ|Γ||Q| and Σ|Γ||Q|² over the run (measured 1e-15 and 2e-15 of them)
    size = np.abs(LEAPFROG_GAMMA) * np.linalg.norm(Q, axis=-1)
    assert np.max(np.abs(lin - lin[0])) < 1e-13 * np.max(np.sum(size, -1))
    assert np.max(np.abs(ang - ang[0])) < 1e-13 * np.max(np.sum(size * np.linalg.norm(Q, axis=-1), -1))
    H = np.asarray(models.vortex_hamiltonian(LEAPFROG_GAMMA, Q))
    assert np.max(np.abs(H - H[0])) < 1e-9 * abs(H[0])  # measured 5e-12 (order 8, Δt = 0.2)
    assert dg.envelope_ratio(H - H[0]) < 1.5
    assert np.max(np.abs(Q[:, :, 1])) < 1.1 and np.min(Q[-1, :, 0]) > 50  # bounded widths, travelled


@pytest.mark.slow  # ~12 s (four programs); in CI's slow run
def test_blocks_give_the_dense_steps_and_vmap_and_batch_agree():
    """The constraint matrix lumped per particle (`jacobian="blocks"`, exact for vortices) gives
    the steps of the whole matrix; `jax.vmap` and `cj.batch` over clusters give each member's
    own run."""
    gamma, Q0 = _random_vortices(8, 11)
    dense = _run(gamma, Q0, 0.05, 40, order=8)
    blocks = _run(gamma, Q0, 0.05, 40, order=8, jacobian="blocks")
    assert np.max(np.abs(np.asarray(blocks.Q) - np.asarray(dense.Q))) < 1e-12 * np.max(np.abs(Q0))

    rng = np.random.default_rng(5)
    gammas = rng.uniform(0.5, 1.5, (3, 4)) * np.array([1.0, -1.0, 1.0, 1.0])
    Q0s = rng.normal(size=(3, 4, 2))

    def run(g, q):
        return cj.integrate(
            models.point_vortices(g),
            q,
            models.vortex_velocity(g, q),
            dt=0.05,
            n_steps=40,
            scheme="gauss",
            order=6,
            throw=False,
        )

    vm = jax.jit(jax.vmap(run))(gammas, Q0s)
    bt = jax.jit(cj.batch(run))(gammas, Q0s)
    assert np.all(np.asarray(vm.valid)) and np.all(np.asarray(bt.valid))
    for i in range(3):
        one = run(gammas[i], Q0s[i])
        np.testing.assert_allclose(vm.Q[i], one.Q, rtol=0, atol=1e-13)
        np.testing.assert_allclose(bt.Q[i], one.Q, rtol=0, atol=1e-13)


@pytest.mark.slow  # ~10 s (compiles derivatives through the solve); in CI's slow run
def test_gradients_match_finite_differences_and_the_step_is_symplectic():
    """Reverse mode through the degenerate fixed-point solve (implicit function theorem) against
    central differences; the one-step map of the positions preserves the vortex symplectic form
    Σ Γₐ dxₐ ∧ dyₐ (JᵀΩJ = Ω)."""
    gamma, Q0 = _random_vortices(5, 2)

    def final_x(scale):
        Q = Q0 * scale
        return _run(gamma, Q, 0.1, 10, order=8).Q[-1, 0, 0]

    g = float(jax.grad(final_x)(1.0))
    h = 1e-5
    fd = (float(final_x(1.0 + h)) - float(final_x(1.0 - h))) / (2 * h)
    assert abs(g - fd) < 1e-6 * max(1.0, abs(fd))  # central difference error O(h²)

    def step(q):
        q = q.reshape(Q0.shape)
        return _run(gamma, q, 0.2, 1, order=8).Q[-1].ravel()

    J = np.asarray(jax.jacfwd(step)(jnp.asarray(Q0).ravel()))
    Omega = np.kron(np.diag(gamma), np.array([[0.0, 1.0], [-1.0, 0.0]]))
    assert np.max(np.abs(J.T @ Omega @ J - Omega)) < 1e-11 * np.max(np.abs(J)) ** 2
