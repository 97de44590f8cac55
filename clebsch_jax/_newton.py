"""Newton's method for the small dense systems of one step, with failure as a value.

One generic driver serves every residual (full march, nodal Legendre solve, later the reduced
march): the method supplies only the residual and the initial guess. Under `jax.vmap` the
`while_loop` runs until every batch member has stopped; each member keeps its own status.

The solve is wrapped in `jax.lax.custom_root`, so derivatives of the solution with respect to
anything the residual closes over (initial data, model parameters) come from the implicit
function theorem, never from differentiating the iterations.

`newton_solve_reusing` is the variant for a march of similar solves: it carries the inverse
Jacobian from one solve to the next. Systems of at most `SMALL_SYSTEM` unknowns run a leaner
loop (`_chord_lean`) with the same decisions: for them XLA's fixed cost per operation, not the
arithmetic, is the price of an update.
"""

from __future__ import annotations

import functools
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

from . import _linalg

__all__ = ["NewtonStats", "Status", "newton_solve", "newton_solve_reusing", "fixed_point_solve"]


class Status:
    """Per-step status codes carried through the march (failure is a value)."""

    SUCCESS = 0
    MAX_ITERATIONS = 1
    NONFINITE = 2
    SINGULAR = 3
    SKIPPED = 4  # not attempted: an earlier step of this batch member failed
    LEGENDRE = 5  # the nodal velocity could not be recovered from (Q, p)
    DIVERGED = 6  # a fixed-point iteration (Gauss-Legendre step) stopped contracting

    MESSAGES = {
        SUCCESS: "converged",
        MAX_ITERATIONS: "Newton's method reached the maximum number of iterations",
        NONFINITE: "the residual or the Newton iterate became non-finite (NaN/inf)",
        SINGULAR: "the Newton Jacobian is singular",
        SKIPPED: "not attempted because an earlier step failed",
        LEGENDRE: "the nodal velocity could not be recovered from (Q, p) by Lemma 7's "
        "relation dl/dxi(xi, Q) = -p<>Q",
        DIVERGED: "the fixed-point iteration of a Gauss-Legendre step stopped contracting or overflowed "
        "(dt too large for it, or the model is not finite at the stage values)",
    }


class NewtonStats(NamedTuple):
    """Statistics of one solve: updates made (`iterations`), final residual max-norm, status,
    and the number of Jacobians formed (`jacobians`)."""

    iterations: jax.Array
    residual_norm: jax.Array
    status: jax.Array
    jacobians: jax.Array


MAX_CHORD_ITERATIONS = 8
"""Chord (simplified Newton) updates per Jacobian before the Jacobian is refreshed."""


def jacobian(F: Callable, z: jax.Array, unroll: bool = False):
    """F(z) and its Jacobian by forward mode: one linearisation, its JVP batched over columns
    (`unroll`: one JVP per column, which XLA compiles to cheaper code for a few columns under
    an outer `vmap`)."""
    Fz, lin = jax.linearize(F, z)
    eye = jnp.eye(z.shape[0], dtype=z.dtype)
    if unroll:
        return Fz, jnp.stack([lin(e) for e in eye], axis=-1)
    return Fz, jax.vmap(lin, out_axes=-1)(eye)


SMALL_SYSTEM = 4
"""Systems of at most this many unknowns use the leaner loop of `_newton_loop_reusing`."""

MAX_ABS_UNROLL = 8
"""`max_abs` of vectors up to this length is written as elementwise maxima."""


def max_abs(v: jax.Array) -> jax.Array:
    """max|v| over the last axis (NaN where v has one), as elementwise maxima when it is short:
    XLA on CPU runs a reduction as an operation of its own (slow under `vmap`), elementwise code
    fuses with its neighbours."""
    if v.ndim == 0:
        return jnp.abs(v)
    if v.shape[-1] > MAX_ABS_UNROLL:
        return jnp.max(jnp.abs(v), axis=-1)
    return functools.reduce(jnp.maximum, [jnp.abs(v[..., i]) for i in range(v.shape[-1])])


def _tolerance(z, rtol, atol, zmax=None):
    return atol + rtol * (jnp.max(jnp.abs(z)) if zmax is None else zmax)


def _converged(eta, eta_prev, k, tol, z, zmax=None, stalled=((0.5, 1e4),)):
    """Whether the iterate after an update of size η is final.

    - the update is at round-off size, η ≤ 8ε·max(1, |z|): nothing left to gain;
    - the estimated remaining error is below tol: with θ = η/η_prev, θ/(1-θ)·η ≤ tol (with
      tol = 0, the default, this never triggers before round-off);
    - a first update below tol/100;
    - stagnation at the noise floor of an ill-conditioned system: the update stopped
      shrinking while already tiny; continuing would only report a false failure. `stalled`
      lists the pairs (θ₀, m) for which θ ≥ θ₀ and η ≤ m·ε·max(1, |z|) count as stalled
      (Newton: θ ≥ 1/2 and η ≤ 10⁴ε·max(1, |z|)).

    `zmax`, if given, is max|z| (already computed by the caller).
    """
    eps = jnp.finfo(z.dtype).eps
    scale = jnp.maximum(1.0, jnp.max(jnp.abs(z)) if zmax is None else zmax)
    theta = jnp.where(k == 0, jnp.inf, eta / eta_prev)
    roundoff = eta <= 8.0 * eps * scale
    estimate = (theta < 1.0) & (theta * eta <= (1.0 - theta) * tol)
    stalls = [(theta >= t) & (eta <= m * eps * scale) for t, m in stalled]
    stagnant = (k > 0) & functools.reduce(jnp.logical_or, stalls)
    return roundoff | estimate | (eta <= 0.01 * tol) | stagnant


def _dense_factor(F: Callable, z: jax.Array):
    """The exact Jacobian at z, factored: `(factor, singular)`."""
    _, J = jacobian(F, z)
    return _linalg.factor(J)


def _chord(F, z0, fac, rtol, atol, solve=_linalg.solve_factored, max_updates=MAX_CHORD_ITERATIONS):
    """Updates with one factored matrix until `_converged`, until they stop contracting
    (θ ≥ 1: time for a fresh matrix), an iterate is non-finite, or `max_updates`.
    Returns (z, updates, converged, nonfinite)."""

    def cond(state):
        k, _, _, stop, _, _ = state
        return (~stop) & (k < max_updates)

    def body(state):
        k, z, eta_prev, _, _, _ = state
        Fz = F(z)
        dz = solve(fac, Fz)
        z_new = z - dz
        eta = jnp.max(jnp.abs(dz))
        nonfinite = ~(jnp.all(jnp.isfinite(z_new)) & jnp.all(jnp.isfinite(Fz)))
        converged = ~nonfinite & _converged(eta, eta_prev, k, _tolerance(z_new, rtol, atol), z_new)
        stop = converged | nonfinite | ((k > 0) & (eta >= eta_prev))
        return k + 1, jnp.where(nonfinite, z, z_new), eta, stop, converged, nonfinite

    false = jnp.asarray(False)
    init = (jnp.asarray(0, jnp.int32), z0, jnp.asarray(jnp.inf, z0.dtype), false, false, false)
    k, z, _, _, converged, nonfinite = jax.lax.while_loop(cond, body, init)
    return z, k, converged, nonfinite


def _newton_loop(F: Callable, z0: jax.Array, rtol, atol, max_iterations: int, *, factorize=_dense_factor,
                 solve=_linalg.solve_factored, max_updates=MAX_CHORD_ITERATIONS):
    """Newton's method with the Jacobian refreshed only when chord updates stop contracting.

    Outer loop: form and factor the Jacobian (at most `max_iterations` times); inner loop:
    chord updates with it. With a good guess — a time march with extrapolated guesses — one
    Jacobian per solve suffices; a hard step gets fresh Jacobians, i.e. full Newton. The
    Jacobian appears once in the program, and under `vmap` the outer loop runs only as often
    as the slowest member needs.

    `factorize(F, z) -> (factor, singular)` and `solve(factor, r)` choose the matrix: the exact
    dense Jacobian by default; `clebsch_jax._block_newton` passes its block-diagonal one. Dense
    systems of at most `SMALL_SYSTEM` unknowns take the same decisions in the leaner loop of
    `_newton_loop_reusing` (without a carried Jacobian)."""
    if factorize is _dense_factor and z0.shape[0] <= SMALL_SYSTEM:
        z, stats, _ = _newton_loop_reusing(F, z0, None, False, rtol, atol, max_iterations)
        return z, _with_residual(stats, F(z))

    def cond(state):
        j, _, _, done, _ = state
        return (~done) & (j < max_iterations)

    def body(state):
        j, z, _, _, updates = state
        fac, singular = factorize(F, z)
        z1, k, converged, nonfinite = _chord(F, z, fac, rtol, atol, solve, max_updates)
        status = jnp.where(singular, Status.SINGULAR,
                           jnp.where(nonfinite, Status.NONFINITE, Status.SUCCESS)).astype(jnp.int32)
        done = converged | singular | nonfinite
        return j + 1, jnp.where(singular, z, z1), status, done, updates + jnp.where(singular, 0, k)

    init = (jnp.asarray(0, jnp.int32), z0, jnp.asarray(Status.SUCCESS, jnp.int32), jnp.asarray(False),
            jnp.asarray(0, jnp.int32))
    j, z, status, done, updates = jax.lax.while_loop(cond, body, init)
    status = jnp.where(done, status, Status.MAX_ITERATIONS).astype(jnp.int32)
    stats = NewtonStats(iterations=updates, residual_norm=jnp.asarray(jnp.nan, z.dtype), status=status, jacobians=j)
    return z, _with_residual(stats, F(z))


def _with_residual(stats: NewtonStats, residual) -> NewtonStats:
    """`stats` with the final residual's max-norm; a SUCCESS whose residual is not finite
    becomes NONFINITE."""
    res_norm = max_abs(ravel_pytree(residual)[0])
    status = jnp.where((stats.status == Status.SUCCESS) & ~jnp.isfinite(res_norm), Status.NONFINITE, stats.status)
    return stats._replace(residual_norm=res_norm, status=status.astype(jnp.int32))


_RUNNING, _CONVERGED, _NONFINITE, _STOPPED = 0, 1, 2, 3


def _chord_lean(F, z0, H, rtol, atol, *, F0=None, max_contraction=1.0, active=True, apply=_linalg.matvec,
                max_updates=MAX_CHORD_ITERATIONS):
    """`_chord` with an explicit inverse Jacobian H, written for small systems: its decisions
    are those of `_chord` (with θ ≥ `max_contraction` ending it), but each update computes
    max|Δz| and max|z| once each, by `max_abs` (a NaN or inf in F or z shows in them), and the
    loop carries one outcome code instead of three flags. Under `vmap` on CPU the fixed cost of
    every operation of the loop body is paid per update, and here the bookkeeping is most of
    the body. `F0`, if given, is F(z0) (known from forming the Jacobian): the first update
    uses it instead of evaluating F again. `active=False` makes no update. Returns (z,
    updates, converged, nonfinite). `apply(H, r)` applies the inverse (default: a dense matrix)."""

    def update(state, Fz):
        k, z, eta_prev, _ = state
        dz = apply(H, Fz)
        z_new = z - dz
        eta, zmax = max_abs(jnp.stack([dz, z_new]))  # one fused computation for both
        nonfinite = ~(jnp.isfinite(eta) & jnp.isfinite(zmax))
        converged = _converged(eta, eta_prev, k, _tolerance(z_new, rtol, atol, zmax), z_new, zmax)
        stopped = ((k > 0) & (eta >= max_contraction * eta_prev)) | (k + 1 >= max_updates)
        code = jnp.where(nonfinite, _NONFINITE,
                         jnp.where(converged, _CONVERGED, jnp.where(stopped, _STOPPED, _RUNNING)))
        return k + 1, jnp.where(nonfinite, z, z_new), eta, code.astype(jnp.int32)

    code0 = jnp.where(active, _RUNNING, _STOPPED).astype(jnp.int32)
    state = (jnp.asarray(0, jnp.int32), z0, jnp.asarray(jnp.inf, z0.dtype), code0)
    if F0 is not None:
        state = update(state, F0)
    k, z, _, code = jax.lax.while_loop(lambda st: st[3] == _RUNNING, lambda st: update(st, F(st[1])), state)
    return z, k, code == _CONVERGED, code == _NONFINITE


REUSE_MAX_CONTRACTION = 0.1
"""`newton_solve_reusing`: a carried Jacobian is replaced by a fresh one as soon as its chord
updates contract by less than this factor per update (θ = |Δz_k|/|Δz_k-1| above it)."""


def _dense_inverse(F: Callable, z: jax.Array):
    """F(z), the explicit inverse of the exact Jacobian at z and whether it is singular."""
    Fz, J = jacobian(F, z, unroll=z.shape[0] <= _linalg.UNROLL_MAX)
    H, singular = _linalg.inverse(J)
    return Fz, H, singular


def _newton_loop_reusing(F: Callable, z0, H0, reuse, rtol, atol, max_iterations: int, max_contraction=1.0, *,
                         invert=_dense_inverse, apply=_linalg.matvec, max_updates=MAX_CHORD_ITERATIONS):
    """`_newton_loop` that first tries an inverse Jacobian `H0` carried from an earlier solve.

    First chord updates with `H0` (if `reuse`; `reuse=False`, a Python bool, leaves them out
    of the program) while they contract by at least `max_contraction` per update; then, if not
    converged, the loop of `_newton_loop`: fresh Jacobians (inverted explicitly, to be carried
    on) with chord updates, each fresh Jacobian's first update using the residual that forming
    it gave. Returns (z, NewtonStats, H), H the inverse Jacobian to carry to the next solve;
    the stats' `residual_norm` is left NaN for the caller, who evaluates F at the root anyway. `invert(F, z) -> (F(z), H, singular)` forms the inverse to carry and
    `apply(H, r)` applies it: an exact dense Jacobian by default (`_block_newton` passes its
    block-diagonal one)."""
    if reuse is False:
        z1, k0, converged0, nonfinite0 = z0, jnp.asarray(0, jnp.int32), jnp.asarray(False), jnp.asarray(False)
        if H0 is None:  # a placeholder of the dense inverse's shape for the loop's carry
            H0 = jnp.eye(z0.shape[0], dtype=z0.dtype)
    else:
        z1, k0, converged0, nonfinite0 = _chord_lean(F, z0, H0, rtol, atol, max_contraction=max_contraction,
                                                     active=reuse, apply=apply, max_updates=max_updates)

    def cond(state):
        j, _, _, _, done, _ = state
        return (~done) & (j < max_iterations)

    def body(state):
        j, z, H_old, _, _, updates = state
        Fz, H, singular = invert(F, z)
        z1, k, converged, nonfinite = _chord_lean(F, z, H, rtol, atol, F0=Fz, apply=apply, max_updates=max_updates)
        status = jnp.where(singular, Status.SINGULAR,
                           jnp.where(nonfinite, Status.NONFINITE, Status.SUCCESS)).astype(jnp.int32)
        done = converged | singular | nonfinite
        return (j + 1, jnp.where(singular, z, z1), jnp.where(singular, H_old, H), status, done,
                updates + jnp.where(singular, 0, k))

    status0 = jnp.where(nonfinite0, Status.NONFINITE, Status.SUCCESS).astype(jnp.int32)
    init = (jnp.asarray(0, jnp.int32), z1, H0, status0, converged0 | nonfinite0, k0)
    j, z, H, status, done, updates = jax.lax.while_loop(cond, body, init)
    status = jnp.where(done, status, Status.MAX_ITERATIONS).astype(jnp.int32)
    return z, NewtonStats(iterations=updates, residual_norm=jnp.asarray(jnp.nan, z.dtype), status=status,
                          jacobians=j), H


def newton_solve_reusing(F: Callable, guess, H, reuse, *, rtol: float, atol: float, max_iterations: int,
                         finish: Callable | None = None, max_contraction: float | None = None,
                         invert=_dense_inverse, apply=_linalg.matvec, tangent_solve: Callable | None = None,
                         max_updates: int = MAX_CHORD_ITERATIONS):
    r"""`newton_solve` for a sequence of similar solves (a time march), reusing the Jacobian.

    `H` is the inverse Jacobian returned by the previous solve (any array of the right shape,
    e.g. the identity, when `reuse` is False). With `reuse` the solve starts with chord updates
    $z \leftarrow z - H F(z)$ and forms a fresh Jacobian (forward mode, as `newton_solve`) only
    when they contract by less than `max_contraction` (default `REUSE_MAX_CONTRACTION`) per
    update or do not converge within `MAX_CHORD_ITERATIONS`; then it continues exactly as
    `newton_solve`, and the fresh inverse is returned for the next solve. Along a smooth march
    the Jacobian changes little from step to step, so most solves form none: for the reduced
    rigid body at Δt = 0.05 one Jacobian serves a thousand steps (the reduced Cayley march
    nevertheless passes `reuse=False`, forming one per solve: see
    `_march_reduced._fresh_jacobians`). The stopping rule, the
    statuses and `max_iterations` (the cap on fresh Jacobians per solve) are those of
    `newton_solve`: with `rtol = atol = 0` it iterates to round-off.

    `finish(z) -> (F(z), extra)`, if given, evaluates the residual at the solution together
    with whatever else the caller needs there (sharing their work); it runs outside the
    implicitly differentiated solve, so `extra` is differentiable as usual. Without it F(z)
    is evaluated once more and `extra` is None. `stats.residual_norm` is max|F(z)| either way.

    `invert`, `apply`, `tangent_solve` and `max_updates` replace the dense Jacobian by another
    carried matrix (see `_newton_loop_reusing`; `_block_newton.block_newton_solve_reusing`).

    **Returns:** `(z, NewtonStats, H, extra)`; `stats.jacobians` counts the fresh Jacobians
    (0 when the carried one sufficed). `H` carries no derivatives.
    """
    if max_contraction is None:
        max_contraction = REUSE_MAX_CONTRACTION
    flat0, unravel = ravel_pytree(guess)

    def F_flat(x):
        return ravel_pytree(F(unravel(x)))[0]

    def loop(f, x0):
        return _newton_loop_reusing(f, x0, H, reuse, rtol, atol, max_iterations, max_contraction, invert=invert,
                                    apply=apply, max_updates=max_updates)

    flat, stats, H_new = implicit_root(F_flat, flat0, loop, tangent_solve or _dense_tangent_solve)
    z = unravel(flat)
    residual, extra = (F(z), None) if finish is None else finish(z)
    return z, _with_residual(stats, residual), H_new, extra


def newton_solve(F: Callable, guess, *, rtol: float, atol: float, max_iterations: int):
    r"""Solve $F(z) = 0$ for a pytree $z$ by Newton's method with an exact (forward-mode) Jacobian.

    The Jacobian is formed at the initial guess and kept while the updates contract (chord,
    or simplified Newton, iterations), and refreshed when they stop contracting — one
    Jacobian per solve when the guess is good, full Newton on hard steps; `max_iterations`
    caps the number of Jacobians. It stops when the error left after an update, estimated from
    the contraction $\theta = \|\Delta z_k\|/\|\Delta z_{k-1}\|$ as $\theta\|\Delta z_k\|/(1-\theta)$,
    is below $\text{atol} + \text{rtol}\,\|z\|_\infty$, or when the update is at round-off (see
    `_converged`), or with status `SINGULAR` / `NONFINITE` / `MAX_ITERATIONS`. Variational
    integrators conserve momenta only as well as each step is solved, and errors of 1e-15 per
    step add up over 10⁴ steps, so the march's default is `rtol = atol = 0`: iterate to
    round-off.

    **Returns:** `(z, NewtonStats)`. On failure `z` is the last finite iterate.
    """
    flat0, unravel = ravel_pytree(guess)

    def F_flat(x):
        return ravel_pytree(F(unravel(x)))[0]

    def loop(f, x0):
        return (*_newton_loop(f, x0, rtol, atol, max_iterations), None)

    flat, stats, _ = implicit_root(F_flat, flat0, loop, _dense_tangent_solve)
    return unravel(flat), stats


def _dense_tangent_solve(g, y):
    """The tangent system of `custom_root` with the dense Jacobian of g."""
    return _linalg.solve(jax.jacfwd(g)(y), y)


def implicit_root(F: Callable, x0: jax.Array, loop: Callable, tangent_solve: Callable):
    """`jax.lax.custom_root` around `loop(F, x0) -> (x, NewtonStats, extra)`: derivatives of the
    root by the implicit function theorem, with `tangent_solve` for the tangent systems. `extra`
    (e.g. a carried inverse Jacobian; None if unused) passes through without derivatives.
    Returns `(x, NewtonStats, extra)`."""

    def solve(f, x):
        x, stats, extra = loop(f, x)
        # custom_root's JVP gives integer aux outputs integer (not float0) tangents, which
        # JAX then rejects; carry the statistics as floats through it and cast back below.
        return x, (jax.tree_util.tree_map(lambda a: a.astype(x.dtype), stats), extra)

    x, (stats, extra) = jax.lax.custom_root(F, x0, solve, tangent_solve, has_aux=True)
    return x, NewtonStats(
        iterations=stats.iterations.astype(jnp.int32),
        residual_norm=stats.residual_norm,
        status=stats.status.astype(jnp.int32),
        jacobians=stats.jacobians.astype(jnp.int32),
    ), extra


STALLED = ((0.5, 1e2), (0.9, 1e4))
"""When `fixed_point_solve` takes an update that stopped shrinking as its noise floor (the
`stalled` pairs of `_converged`): θ ≥ 1/2 over a test within 100ε of the size, as in Newton,
but further out (up to 10⁴ε) only θ ≥ 0.9. Near its limit a sweep contracts by ~0.75 (rigid
body, Δt 1.25, order 16): θ ≈ 0.56 over a test of 2 sweeps, and Newton's rule stopped such
steps at updates of 1e-12 (|Q|² drifted 2.7e-12 over 80 steps; now 4e-15). The sweeps of a
degenerate system stall near 30ε (100 vortices: the step divides by h), where θ ≥ 1/2 still
stops them."""

SWEEPS_PER_TEST = 2
"""Sweeps of `fixed_point_solve` between two convergence tests. Two: the updates of a Gauss
sweep alternate in size (measured: ×1.3 then ×0.08, ...), so pairs of sweeps contract
steadily; and a test per pair costs less (rigid-body batch, 200 bodies, order 8, Δt = 0.25:
1.6 s against 2.5 s per 4000 steps for a test per sweep, 1.7-1.9 s for 3 or 4 sweeps; the
sweeps per step rose from 12.0 to 12.6; after 4 untested sweeps, 3 or 4 sweeps per test
still lose: 1.7-1.8 s against 1.3 s)."""


def fixed_point_solve(G: Callable, guess, *, rtol: float, atol: float, max_iterations: int, size=None,
                      untested: int = 0):
    r"""Solve $z = G(z)$ for a pytree z by the iteration $z \leftarrow G(z)$ (sweeps), for a
    contraction G with a good guess (a Gauss–Legendre step, `clebsch_jax._collocation`).

    Runs `untested` sweeps (a static count), then tests convergence after every
    `SWEEPS_PER_TEST` sweeps, on the size η of the last update, by `_converged` with the
    previous test's η and the stall rule `STALLED` (with `rtol = atol = 0`: at round-off). Sizes are judged against `size`,
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

    A test costs about as much as a sweep on the CPU (a reduction over the unknowns and the
    bookkeeping of a batched loop), so there is one reduction per test and none for the size.
    **Returns:** `(z, NewtonStats)`."""
    flat0, unravel = ravel_pytree(guess)
    untested = max(0, min(int(untested), max_iterations - SWEEPS_PER_TEST))

    def F_flat(x):
        return x - ravel_pytree(G(unravel(x)))[0]

    def loop(f, x0):
        g = lambda x: x - f(x)  # G itself, from the residual custom_root passes in
        zmax = jnp.max(jnp.abs(x0)) if size is None else jnp.asarray(size, x0.dtype)
        tol = _tolerance(x0, rtol, atol, zmax)
        scale = jnp.maximum(1.0, zmax)
        start_finite = jnp.isfinite(zmax)

        def cond(state):
            return (~state[3]) & (state[0] + untested < max_iterations)

        def body(state):
            k, z, previous, _, _ = state  # k: sweeps since the untested ones
            z_mid = z
            for _ in range(SWEEPS_PER_TEST - 1):
                z_mid = g(z_mid)
            z_new = g(z_mid)
            eta = jnp.max(jnp.abs(z_new - z_mid))
            nonfinite = ~jnp.isfinite(eta)  # a NaN or inf in z_new makes η one
            converged = ~nonfinite & _converged(eta, previous, k, tol, z_new, zmax, stalled=STALLED)
            diverged = (k >= 2 * SWEEPS_PER_TEST) & (eta > previous) & (eta > 1e4 * jnp.finfo(z.dtype).eps * scale)
            # sweeps that overflow from a finite start did not contract: DIVERGED too
            status = jnp.where(nonfinite & ~start_finite, Status.NONFINITE,
                               jnp.where((diverged & ~converged) | nonfinite, Status.DIVERGED,
                                         Status.SUCCESS)).astype(jnp.int32)
            done = converged | nonfinite | diverged
            return k + SWEEPS_PER_TEST, jnp.where(nonfinite, z, z_new), eta, done, status

        x0 = jax.lax.fori_loop(0, untested, lambda _, x: g(x), x0)
        init = (jnp.asarray(0, jnp.int32), x0, jnp.asarray(jnp.inf, x0.dtype), jnp.asarray(False),
                jnp.asarray(Status.SUCCESS, jnp.int32))
        k, z, eta, done, status = jax.lax.while_loop(cond, body, init)
        status = jnp.where(done, status, Status.MAX_ITERATIONS).astype(jnp.int32)
        return z, NewtonStats(iterations=k + untested, residual_norm=eta, status=status,
                              jacobians=jnp.asarray(0, jnp.int32)), None

    flat, stats, _ = implicit_root(F_flat, flat0, loop, _dense_tangent_solve)
    return unravel(flat), stats
