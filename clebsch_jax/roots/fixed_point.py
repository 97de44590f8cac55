r"""Fixed-point iteration $z \leftarrow G(z)$ for contractions with a good guess (the stage
equations of a Gauss–Legendre step), with the same stopping rule and statuses as Newton's
method and derivatives by the implicit function theorem."""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

from .implicit import dense_tangent_solve, implicit_root
from .newton import converged as is_converged
from .newton import tolerance
from .status import NewtonStats, Status

__all__ = ["fixed_point_solve", "STALLED", "SWEEPS_PER_TEST", "stall_pairs"]


STALLED = ((0.5, 1e2), (0.9, 1e4))
r"""When `fixed_point_solve` takes an update that stopped shrinking as its noise floor (the
`stalled` pairs of `converged`): θ ≥ 1/2 over a test within 100ε of the size, as in Newton,
but further out (up to 10⁴ε) only θ ≥ 0.9. Near its limit a sweep contracts slowly (θ above
1/2 over a test of two sweeps: a large step of a high order), and Newton's rule would stop it
at updates far above round-off, which quadratic invariants then show as drift. The sweeps of
a degenerate system stall a little above round-off (the step divides by h), where θ ≥ 1/2
still stops them. The history of these choices is in `benchmarks/README.md`.

The ratios θ are those of a test of `SWEEPS_PER_TEST` sweeps; a test of `per_test` sweeps
compares its θ with $\theta_0^{\,\texttt{per\_test}/\texttt{SWEEPS\_PER\_TEST}}$, the same
contraction per sweep (`stall_pairs`)."""

SWEEPS_PER_TEST = 2
"""Sweeps of `fixed_point_solve` between two convergence tests, by default (`per_test`). Two:
the updates of a Gauss sweep alternate in size, so pairs of sweeps contract steadily, and a
test costs about as much as a sweep on the CPU (see `benchmarks/README.md` for the runs behind
this choice). A sweep that costs far more than a test (matrix products of n² unknowns, against
one reduction over them) is better tested after every sweep: `per_test=1`."""


def stall_pairs(per_test: int) -> tuple:
    """`STALLED` for tests of `per_test` sweeps: each θ₀ raised to per_test / SWEEPS_PER_TEST
    (the same pairs at the default interval)."""
    if per_test == SWEEPS_PER_TEST:
        return STALLED
    return tuple((theta ** (per_test / SWEEPS_PER_TEST), m) for theta, m in STALLED)


def fixed_point_solve(
    G: Callable,
    guess,
    *,
    rtol: float,
    atol: float,
    max_iterations: int,
    size=None,
    untested: int = 0,
    per_test: int = SWEEPS_PER_TEST,
    until_stalled: bool = False,
    extra=None,
):
    r"""Solve $z = G(z)$ for a pytree z by the iteration $z \leftarrow G(z)$ (sweeps), for a
    contraction G with a good guess (a Gauss–Legendre step, `clebsch_jax.discrete.collocation`).

    Runs `untested` sweeps (a static count), then `extra` more (None: none; a traced count, so
    under `jax.vmap` each member runs its own: a march's estimate from the solve of its previous
    step, `FixedPoint.solve`'s `previous`), then tests convergence after every
    `per_test` sweeps (default `SWEEPS_PER_TEST`), on the size η of the last update, by `_converged` with the
    previous test's η and the stall rule `STALLED` (per sweep: `stall_pairs`) (with `rtol = atol = 0`: at round-off). Sizes are judged against `size`,
    the magnitude of the values the iterate is part of or added to (default: max|guess|),
    fixed for the solve: its round-off floor is 8ε·max(1, size) and a positive rtol is
    relative to it. Fails with `Status.DIVERGED` when, from the third test on, η grew since the
    last test while not at round-off (the map is not contracting: Δt too large), or when the
    iterate became non-finite although `size` is finite (the untested sweeps can overflow
    before a test sees η grow); with `Status.NONFINITE` when it became non-finite from a
    non-finite start; and with `Status.MAX_ITERATIONS` after `max_iterations` sweeps.
    `stats.iterations` counts sweeps, `stats.jacobians` is 0, `stats.residual_norm` is η
    (max|G(z) − z| at the iterate before the last: the residual the loop already has, not one
    more evaluation). Derivatives by the implicit function theorem on $F(z) = z - G(z)$ with a
    dense tangent solve.

    With `until_stalled` an update at round-off of `size` does not stop the sweeps: they go on
    until the update is zero or stops shrinking (the stall rule), i.e. to the round-off of the
    iterate's own entries — the rule of Hairer, McLachlan & Razakarivony (BIT 48 (2008) 231).
    An iterate of increments much smaller than the state they are added to (a Gauss–Legendre
    step) otherwise keeps an error of ~ε·size per step, a smooth function of the state, which
    a compensated update does not round away and which drifts the energy linearly.

    A test costs about as much as a sweep on the CPU (a reduction over the unknowns and the
    bookkeeping of a batched loop), so there is one reduction per test and none for the size.
    **Returns:** `(z, NewtonStats)`."""
    flat0, unravel = ravel_pytree(guess)
    per_test = int(per_test)
    stalled = stall_pairs(per_test)
    untested = max(0, min(int(untested), max_iterations - per_test))

    def F_flat(x):
        return x - ravel_pytree(G(unravel(x)))[0]

    def loop(f, x0):
        g = lambda x: x - f(x)  # G itself, from the residual implicit_root passes in
        zmax = jnp.max(jnp.abs(x0)) if size is None else jnp.asarray(size, x0.dtype)
        tol = tolerance(x0, rtol, atol, zmax)
        scale = jnp.maximum(1.0, zmax)
        start_finite = jnp.isfinite(zmax)

        if extra is None:
            before = untested
        else:  # every member keeps at least one test
            more = jnp.clip(jnp.asarray(extra, jnp.int32), 0, max_iterations - per_test - untested)
            before = untested + more

        def cond(state):
            return (~state[3]) & (state[0] + before < max_iterations)

        def body(state):
            k, z, previous, _, _ = state  # k: sweeps since the untested ones
            z_mid = z
            for _ in range(per_test - 1):
                z_mid = g(z_mid)
            z_new = g(z_mid)
            eta = jnp.max(jnp.abs(z_new - z_mid))
            nonfinite = ~jnp.isfinite(eta)  # a NaN or inf in z_new makes η one
            converged = ~nonfinite & is_converged(
                eta, previous, k, tol, z_new, zmax, stalled=stalled, roundoff_floor=0.0 if until_stalled else 8.0
            )
            diverged = (k >= 2 * per_test) & (eta > previous) & (eta > 1e4 * jnp.finfo(z.dtype).eps * scale)
            # sweeps that overflow from a finite start did not contract: DIVERGED too
            status = jnp.where(
                nonfinite & ~start_finite,
                Status.NONFINITE,
                jnp.where((diverged & ~converged) | nonfinite, Status.DIVERGED, Status.SUCCESS),
            ).astype(jnp.int32)
            done = converged | nonfinite | diverged
            return k + per_test, jnp.where(nonfinite, z, z_new), eta, done, status

        x0 = jax.lax.fori_loop(0, untested, lambda _, x: g(x), x0)
        if extra is not None:
            x0 = jax.lax.while_loop(
                lambda c: c[0] < more, lambda c: (c[0] + 1, g(c[1])), (jnp.asarray(0, jnp.int32), x0)
            )[1]
        init = (
            jnp.asarray(0, jnp.int32),
            x0,
            jnp.asarray(jnp.inf, x0.dtype),
            jnp.asarray(False),
            jnp.asarray(Status.SUCCESS, jnp.int32),
        )
        k, z, eta, done, status = jax.lax.while_loop(cond, body, init)
        status = jnp.where(done, status, Status.MAX_ITERATIONS).astype(jnp.int32)
        return (
            z,
            NewtonStats(iterations=k + before, residual_norm=eta, status=status, jacobians=jnp.asarray(0, jnp.int32)),
            None,
        )

    flat, stats, _ = implicit_root(F_flat, flat0, loop, dense_tangent_solve)
    return unravel(flat), stats
