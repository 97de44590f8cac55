r"""`continue_from`: a run continued from the last node's canonical state $(Q^n, p^n)$ is the same
trajectory as one long run, to round-off, in each march: the reduced rigid body (where $p^n$
is rebuilt from $\mu^n$ as the minimum-norm cotangent), the full march of the heavy top with
the midpoint principle, and the degenerate point vortices (no nodal velocity: the last step's
velocity seeds the next chunk).

Compile time dominates, so each case compiles one program, a run of 2N steps, and calls it
twice: once from the initial state, once continued from node N of that run (the run cut after N
steps, `_head`: nodes 0..N of a march do not depend on the steps after them). The continued
run's first N steps must then be the long run's last N.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import clebsch_jax as cj
from clebsch_jax import lie, models

N = 8  # steps per chunk; the long run has 2N

QUICK = {"xla_backend_optimization_level": 0}  # short runs: compilation dominates


def _head(sol: cj.Solution, n: int) -> cj.Solution:
    """The first `n` steps of a single run: its nodes 0..n and steps 0..n-1."""
    node = lambda a: None if a is None else a[: n + 1]
    step = lambda a: None if a is None else a[:n]
    return dataclasses.replace(
        sol,
        ts=node(sol.ts),
        Q=node(sol.Q),
        p=node(sol.p),
        xi=node(sol.xi),
        momentum=node(sol.momentum),
        valid=node(sol.valid),
        nodal_stats=jax.tree.map(node, sol.nodal_stats),
        xi_step=step(sol.xi_step),
        P=step(sol.P),
        stats=jax.tree.map(step, sol.stats),
        march_state=None,  # the march's state belongs to the last node: cut, it is not handed over
    )


def _long_and_continued(system, Q0, xi0, dt, **options):
    """A run of 2N steps, and the same program's run continued (`continue_from`) from its node N.
    (The initial multiplier and the hand-over are jitted too: op by op their small linear
    algebra compiles slower.)"""
    run = jax.jit(
        lambda start: cj.integrate(system, **start._asdict(), dt=dt, n_steps=2 * N, **options), compiler_options=QUICK
    )
    initial = jax.jit(
        lambda Q, xi: cj.Start(Q0=Q, xi0=xi, P0=cj.initial_multiplier(system, Q, xi), t0=jnp.zeros((), Q.dtype)),
        compiler_options=QUICK,
    )
    hand_over = jax.jit(lambda sol, Q: cj.continue_from(system, _head(sol, N), Q=Q), compiler_options=QUICK)
    Q0, xi0 = jnp.asarray(Q0, jnp.float64), jnp.asarray(xi0, jnp.float64)
    long = run(initial(Q0, xi0))
    continued = run(hand_over(long, Q0))
    assert run._cache_size() == 1  # the continued run reused the compiled program
    return long, continued


def _assert_continues(long, continued, tol=1e-13):
    r"""Nodes 0..N and steps 0..N-1 of `continued` are nodes N..2N and steps N..2N-1 of `long`, to
    `tol` relative to each field's size; a step's velocity is a difference quotient of the nodes
    ($\phi_{\Delta t}(Q^{n+1}, Q^n) = \mathcal L_{\xi^n}Q^n$), so its round-off is theirs over Δt."""
    assert long.result == continued.result == cj.Status.SUCCESS
    np.testing.assert_allclose(continued.ts[: N + 1], long.ts[N:], rtol=0, atol=1e-15)
    dt = float(long.ts[1] - long.ts[0])
    for field in ("Q", "p", "xi", "momentum", "xi_step"):
        whole = getattr(long, field)
        if whole is None:
            assert getattr(continued, field) is None, field
            continue
        part = getattr(continued, field)[: len(whole) - N]
        atol = tol * np.max(np.abs(whole)) / (dt if field == "xi_step" else 1.0)
        np.testing.assert_allclose(part, whole[N:], rtol=0, atol=atol, err_msg=field)


@pytest.mark.parametrize("reconstruct", [True, False])
def test_reduced_rigid_body(reconstruct):
    """The reduced march carries μⁿ; the hand-over rebuilds pⁿ from it. Without Q
    (`reconstruct=False`) the caller passes a configuration: the free body's step does not
    depend on Q."""
    system = models.rigid_body(jnp.array([2.0, 1.0, 2.0 / 3.0]))
    m0 = np.array([np.cos(1.1), 0.0, np.sin(1.1)])
    long, continued = _long_and_continued(
        system, np.eye(3), m0 / np.array([2.0, 1.0, 2.0 / 3.0]), 0.1, reconstruct=reconstruct
    )
    assert long.form == "reduced" and long.p is None and (long.Q is None) == (not reconstruct)
    _assert_continues(long, continued)


@pytest.mark.slow  # CI runs it; continuation of the full march is checked in the default run on point vortices
def test_full_march_heavy_top_midpoint():
    system = models.heavy_top(jnp.array([1.0, 1.0, 0.4]), 1.5)
    Q0 = lie.so3_exp(jnp.array([0.5, 0.0, 0.0]))
    long, continued = _long_and_continued(system, Q0, np.array([0.3, -0.2, 6.0]), 0.02, scheme="midpoint")
    assert long.form == "full" and long.p is not None
    _assert_continues(long, continued)


def test_degenerate_point_vortices():
    gamma = jnp.array([1.0, -1.0, 1.0, -1.0])
    Q0 = jnp.array([[0.0, 1.0], [0.0, -1.0], [0.0, 0.5], [0.0, -0.5]])
    system = models.point_vortices(gamma)
    long, continued = _long_and_continued(system, Q0, models.vortex_velocity(gamma, Q0), 0.02)
    assert long.xi is None and long.scheme == "midpoint"
    _assert_continues(long, continued)


def test_refuses_a_batch_and_a_missing_configuration():
    """Shapes only (nothing is compiled)."""
    system = models.rigid_body(jnp.array([2.0, 1.0, 2.0 / 3.0]))
    xi0 = jnp.array([[0.5, 0.1, 0.8], [0.1, 0.2, 0.3]])
    march = lambda x, **kw: cj.integrate(system, jnp.eye(3), x, dt=0.1, n_steps=2, throw=False, **kw)
    batched = jax.eval_shape(jax.vmap(march), xi0)
    with pytest.raises(ValueError, match="jax.vmap"):
        cj.continue_from(system, batched)
    start = jax.eval_shape(jax.vmap(lambda s: cj.continue_from(system, s)), batched)
    assert start.Q0.shape == (2, 3, 3) and start.P0.shape == (2, 3, 3) and start.t0.shape == (2,)
    no_Q = jax.eval_shape(lambda x: march(x, reconstruct=False), xi0[0])
    with pytest.raises(ValueError, match="pass the last configuration"):
        cj.continue_from(system, no_Q)


def _split_run(system, Q0, xi0, P0, n_first, n_rest, **options):
    """One run of n_first + n_rest steps, and the same run made as two `integrate` calls, the second
    continued by `continue_from` from the first's last node; also continued without the march state
    (the guesses restarted)."""
    whole = cj.integrate(system, Q0, xi0, P0=P0, n_steps=n_first + n_rest, **options)
    head = cj.integrate(system, Q0, xi0, P0=P0, n_steps=n_first, **options)
    start = cj.continue_from(system, head)
    tail = cj.integrate(system, **start._asdict(), n_steps=n_rest, **options)
    restarted = cj.integrate(system, **start._replace(march_state=None)._asdict(), n_steps=n_rest, **options)
    return whole, tail, restarted


@pytest.mark.parametrize(
    "options",
    [dict(dt=0.1, order=4), dict(dt=0.5, scheme="gauss", order=4)],
    ids=["reduced-composition", "gauss"],
)
def test_march_state_continues_the_very_steps(options):
    """With `Solution.march_state` (which `continue_from` hands over) the continued run makes the
    steps of the unbroken run: the same Newton updates from the same guesses, so the same nodes
    to the bit. Without it the guesses restart (the predictor's history, the Gauss–Legendre
    stage guess from substeps): other updates, nodes equal only to round-off."""
    inertia = jnp.array([2.0, 1.0, 2.0 / 3.0])
    if options.get("scheme") == "gauss":  # the body in Clebsch variables on R³ (a vector space)
        Pi0 = jnp.array([0.3, -0.8, 0.5])
        system = models.rigid_body_vector(inertia)
        Q0, P0 = models.rigid_body_vector_start(Pi0)
        xi0, field = Pi0 / inertia, "Q"
    else:  # the reduced march (Cayley), order 4 by composition: μ carried
        system, Q0, xi0, field = models.rigid_body(inertia), jnp.eye(3), jnp.array([0.4, 1.1, -0.7]), "momentum"
        P0 = None
    n_first, n_rest = 17, 23
    whole, tail, restarted = _split_run(system, Q0, xi0, P0, n_first, n_rest, **options)
    np.testing.assert_array_equal(getattr(tail, field), getattr(whole, field)[n_first:])
    np.testing.assert_array_equal(tail.stats.iterations, whole.stats.iterations[n_first:])
    # the restarted guesses: the same trajectory to round-off, but other Newton updates
    np.testing.assert_allclose(getattr(restarted, field), getattr(whole, field)[n_first:], rtol=0, atol=1e-13)
    assert not np.array_equal(restarted.stats.iterations, whole.stats.iterations[n_first:])


def test_march_state_is_checked():
    """A march state of another method, or of another node than Q0, is refused, naming it."""
    inertia = jnp.array([2.0, 1.0, 2.0 / 3.0])
    system, xi0 = models.rigid_body(inertia), jnp.array([0.4, 1.1, -0.7])
    sol = cj.integrate(system, jnp.eye(3), xi0, dt=0.1, n_steps=4, order=4)
    start = cj.continue_from(system, sol)
    with pytest.raises(ValueError, match="march_state: expected"):
        cj.integrate(system, **start._asdict(), dt=0.1, n_steps=4)  # order 2: another method
    with pytest.raises(ValueError, match="march_state: it is the march's state at another node"):
        cj.integrate(system, **start._replace(Q0=jnp.eye(3))._asdict(), dt=0.1, n_steps=4, order=4)
