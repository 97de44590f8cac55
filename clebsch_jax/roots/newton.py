r"""Newton's method for the small systems of one step, with failure as a value: one loop for
every Newton matrix.

The loop (`newton_loop`) first tries the inverse of a matrix carried from an earlier solve (a
time march: the Jacobian changes by O(Δt) from step to step), then forms fresh matrices at the
iterate, each followed by chord (simplified Newton) updates while they contract. A *matrix*
(`Matrix`) says how a Newton matrix is formed and applied:

- `dense_matrix(n)`: the exact Jacobian by forward mode, inverted explicitly for a few unknowns
  (where XLA's fixed cost per operation, not arithmetic, is the price of an update) and
  LU-factored otherwise;
- `clebsch_jax.roots.blocks`: the lumped block-diagonal Jacobian of many interacting particles.

Under `jax.vmap` the `while_loop`s run until every member has stopped; each member keeps its
own status. The solve is wrapped in `implicit_root` (the rule of `jax.lax.custom_root`), so derivatives of
the root with respect to what the residual closes over come from the implicit function
theorem, never from differentiating the iterations.
"""

from __future__ import annotations

import functools
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

from ..core import linalg
from .implicit import dense_tangent_solve, implicit_root
from .status import NewtonStats, Status

__all__ = [
    "Matrix",
    "dense_matrix",
    "newton_loop",
    "newton_solve",
    "newton_solve_reusing",
    "fixed_newton_solve",
    "jacobian",
    "max_abs",
    "converged",
    "tolerance",
    "MAX_CHORD_ITERATIONS",
    "REUSE_MAX_CONTRACTION",
    "SMALL_SYSTEM",
]


MAX_CHORD_ITERATIONS = 8
"""Chord (simplified Newton) updates per Jacobian before the Jacobian is refreshed."""

SMALL_SYSTEM = 4
"""Systems of at most this many unknowns invert their dense Jacobian explicitly."""

MAX_ABS_UNROLL = 8
"""`max_abs` of vectors up to this length is written as elementwise maxima."""

REUSE_MAX_CONTRACTION = 0.1
"""`newton_solve_reusing`: a carried Jacobian is replaced by a fresh one as soon as its chord
updates contract by less than this factor per update (θ = |Δz_k|/|Δz_k-1| above it)."""


def jacobian(F: Callable, z: jax.Array, unroll: bool = False):
    """F(z) and its Jacobian by forward mode: one linearisation, its JVP batched over columns
    (`unroll`: one JVP per column, which XLA compiles to cheaper code for a few columns under
    an outer `vmap`)."""
    Fz, lin = jax.linearize(F, z)
    eye = jnp.eye(z.shape[0], dtype=z.dtype)
    if unroll:
        return Fz, jnp.stack([lin(e) for e in eye], axis=-1)
    return Fz, jax.vmap(lin, out_axes=-1)(eye)


def max_abs(v: jax.Array) -> jax.Array:
    """max|v| over the last axis (NaN where v has one), as elementwise maxima when it is short:
    XLA on CPU runs a reduction as an operation of its own (slow under `vmap`), elementwise code
    fuses with its neighbours."""
    if v.ndim == 0:
        return jnp.abs(v)
    if v.shape[-1] > MAX_ABS_UNROLL:
        return jnp.max(jnp.abs(v), axis=-1)
    return functools.reduce(jnp.maximum, [jnp.abs(v[..., i]) for i in range(v.shape[-1])])


def tolerance(z, rtol, atol, zmax=None):
    """atol + rtol·max|z| (`zmax`: max|z| when the caller has it); the Python float 0.0 when
    `rtol` and `atol` are both Python zeros (to round-off, the default), so that `converged`
    leaves out the tests that such a tolerance cannot pass."""
    if _static_zero(rtol) and _static_zero(atol):
        return 0.0
    return atol + rtol * (jnp.max(jnp.abs(z)) if zmax is None else zmax)


def _static_zero(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and x == 0


def converged(eta, eta_prev, k, tol, z, zmax=None, stalled=((0.5, 1e4),), roundoff_floor=8.0):
    """Whether the iterate after an update of size η is final.

    - the update is at round-off size, η ≤ 8ε·max(1, |z|) (`roundoff_floor` = 8): nothing left
      to gain at the size of |z|; with `roundoff_floor` = 0 only a zero update, so that an
      iterate whose parts are smaller than |z| converges to their own round-off, which the
      stall rule below then recognises;
    - the estimated remaining error is below tol: with θ = η/η_prev, θ/(1-θ)·η ≤ tol (with
      tol = 0, the default, this never triggers before round-off);
    - a first update below tol/100;
    - stagnation at the noise floor of an ill-conditioned system: the update stopped
      shrinking while already tiny; continuing would only report a false failure. `stalled`
      lists the pairs (θ₀, m) for which θ ≥ θ₀ and η ≤ m·ε·max(1, |z|) count as stalled
      (Newton: θ ≥ 1/2 and η ≤ 10⁴ε·max(1, |z|)).

    `zmax`, if given, is max|z| (already computed by the caller). With `tol` the Python 0.0
    (`tolerance` of zero rtol and atol) the two tests on tol are left out of the program: all
    they accept then is an update of size 0 (or one that underflows against θ), which the
    round-off test accepts too — unless max|z| is NaN, and every caller stops a NaN iterate as
    non-finite first. The same verdict in fewer operations, which in the straight-line solves
    of a sweep's fast path are a good part of a step's check.
    """
    eps = jnp.finfo(z.dtype).eps
    scale = jnp.maximum(1.0, jnp.max(jnp.abs(z)) if zmax is None else zmax)
    theta = jnp.where(k == 0, jnp.inf, eta / eta_prev)
    roundoff = eta <= roundoff_floor * eps * scale
    stalls = [(theta >= t) & (eta <= m * eps * scale) for t, m in stalled]
    stagnant = (k > 0) & functools.reduce(jnp.logical_or, stalls)
    if _static_zero(tol):
        return roundoff | stagnant
    estimate = (theta < 1.0) & (theta * eta <= (1.0 - theta) * tol)
    return roundoff | estimate | (eta <= 0.01 * tol) | stagnant


class Matrix(NamedTuple):
    """How a Newton matrix is formed and used: `invert(F, z) -> (F(z), M, singular)` forms it
    at z (M: whatever `apply` needs, an inverse or a factorisation), `apply(M, r)` returns
    M⁻¹r, `tangent_solve` solves the tangent systems of the implicit derivative, and
    `max_updates` caps the chord updates per matrix."""

    invert: Callable
    apply: Callable
    tangent_solve: Callable = dense_tangent_solve
    max_updates: int = MAX_CHORD_ITERATIONS


def fence(values):
    """`values` behind an `optimization_barrier`: XLA fuses on neither side of it. A fixed solve
    is long straight-line code; fenced between its phases (the Jacobian, its inverse, each
    update) it is fused phase by phase, where unfenced XLA makes fusions that each recompute
    the terms they share with others (every entry of an inverse its own Jacobian)."""
    return jax.lax.optimization_barrier(values)


def _dense_inverse(F: Callable, z: jax.Array):
    """F(z), the explicit inverse of the exact Jacobian at z and whether it is singular."""
    Fz, J = jacobian(F, z, unroll=z.shape[0] <= linalg.UNROLL_MAX)
    H, singular = linalg.inverse(J)
    return Fz, H, singular


def _fenced_inverse(F: Callable, z: jax.Array):
    """`_dense_inverse` with the Jacobian and the adjugate and determinant fenced (`fence`)."""
    Fz, J = fence(jacobian(F, z, unroll=z.shape[0] <= linalg.UNROLL_MAX))
    H, singular = linalg.inverse(J, fence=True)
    return Fz, H, singular


def _dense_factor(F: Callable, z: jax.Array):
    """F(z), the factored exact Jacobian at z and whether it is singular."""
    Fz, J = jacobian(F, z)
    fac, singular = linalg.factor(J)
    return Fz, fac, singular


DENSE_INVERSE = Matrix(_dense_inverse, linalg.matvec)
"""The exact Jacobian, inverted explicitly: the matrix a march carries from solve to solve."""

FENCED_INVERSE = Matrix(_fenced_inverse, linalg.matvec)
"""`DENSE_INVERSE` fenced between its phases: the matrix of the fixed solves (`fixed_newton_solve`)."""

DENSE_FACTOR = Matrix(_dense_factor, linalg.solve_factored)
"""The exact Jacobian, factored (LU above three unknowns): for one-off solves of more unknowns."""


def dense_matrix(n: int) -> Matrix:
    """The exact Jacobian for a one-off solve of n unknowns: explicit inverse up to
    `SMALL_SYSTEM` unknowns, else factored."""
    return DENSE_INVERSE if n <= SMALL_SYSTEM else DENSE_FACTOR


_RUNNING, _CONVERGED, _NONFINITE, _STOPPED = 0, 1, 2, 3


def _chord(
    F,
    z0,
    H,
    rtol,
    atol,
    *,
    F0=None,
    max_contraction=1.0,
    active=True,
    apply=linalg.matvec,
    max_updates=MAX_CHORD_ITERATIONS,
):
    """Chord updates z ← z − M⁻¹F(z) with one matrix (`apply(H, r)` = M⁻¹r) until `converged`,
    until they contract by less than `max_contraction` per update (time for a fresh matrix),
    an iterate is non-finite, or `max_updates`. Each update computes max|Δz| and max|z| once
    each (a NaN or inf in F or z shows in them), and the loop carries one outcome code: under
    `vmap` on CPU the fixed cost of every operation of the loop body is paid per update, and
    for small systems the bookkeeping is most of the body. `F0`, if given, is F(z0) (known
    from forming the matrix). `active=False` makes no update.
    Returns (z, updates, converged, nonfinite)."""

    def update(state, Fz):
        k, z, eta_prev, _ = state
        dz = apply(H, Fz)
        z_new = z - dz
        eta, zmax = max_abs(jnp.stack([dz, z_new]))  # one fused computation for both
        nonfinite = ~(jnp.isfinite(eta) & jnp.isfinite(zmax))
        done = converged(eta, eta_prev, k, tolerance(z_new, rtol, atol, zmax), z_new, zmax)
        stopped = ((k > 0) & (eta >= max_contraction * eta_prev)) | (k + 1 >= max_updates)
        code = jnp.where(nonfinite, _NONFINITE, jnp.where(done, _CONVERGED, jnp.where(stopped, _STOPPED, _RUNNING)))
        return k + 1, jnp.where(nonfinite, z, z_new), eta, code.astype(jnp.int32)

    code0 = jnp.where(active, _RUNNING, _STOPPED).astype(jnp.int32)
    state = (jnp.asarray(0, jnp.int32), z0, jnp.asarray(jnp.inf, z0.dtype), code0)
    if F0 is not None:
        state = update(state, F0)
    k, z, _, code = jax.lax.while_loop(lambda st: st[3] == _RUNNING, lambda st: update(st, F(st[1])), state)
    return z, k, code == _CONVERGED, code == _NONFINITE


def newton_loop(
    F: Callable, z0, H0, reuse, rtol, atol, max_iterations: int, max_contraction=1.0, *, matrix: Matrix = DENSE_INVERSE
):
    """Newton's method on flat unknowns, first with a carried matrix, then with fresh ones.

    First chord updates with the carried `H0` (if `reuse`; `reuse=False`, a Python bool, leaves
    them out of the program) while they contract by at least `max_contraction` per update;
    then, if not converged, at most `max_iterations` fresh matrices formed at the iterate
    (`matrix.invert`), each followed by chord updates, its first update using the residual
    that forming it gave. With a good guess one matrix per solve suffices; a hard step gets
    fresh ones, i.e. full Newton. Under `vmap` the outer loop runs only as often as the
    slowest member needs.

    Returns (z, NewtonStats, H), H the matrix to carry to the next solve (None when `H0` is
    None: a one-off solve carries no matrix through its loop); the stats' `residual_norm` is
    left NaN for the caller, who evaluates F at the root anyway."""
    if reuse is False:
        z1, k0, converged0, nonfinite0 = z0, jnp.asarray(0, jnp.int32), jnp.asarray(False), jnp.asarray(False)
    else:
        z1, k0, converged0, nonfinite0 = _chord(
            F,
            z0,
            H0,
            rtol,
            atol,
            max_contraction=max_contraction,
            active=reuse,
            apply=matrix.apply,
            max_updates=matrix.max_updates,
        )

    def cond(state):
        j, _, _, _, done, _ = state
        return (~done) & (j < max_iterations)

    def body(state):
        j, z, H_old, _, _, updates = state
        Fz, H, singular = matrix.invert(F, z)
        z1, k, conv, nonfinite = _chord(F, z, H, rtol, atol, F0=Fz, apply=matrix.apply, max_updates=matrix.max_updates)
        status = jnp.where(singular, Status.SINGULAR, jnp.where(nonfinite, Status.NONFINITE, Status.SUCCESS)).astype(
            jnp.int32
        )
        done = conv | singular | nonfinite
        H = None if H_old is None else jax.tree_util.tree_map(lambda old, new: jnp.where(singular, old, new), H_old, H)
        return j + 1, jnp.where(singular, z, z1), H, status, done, updates + jnp.where(singular, 0, k)

    status0 = jnp.where(nonfinite0, Status.NONFINITE, Status.SUCCESS).astype(jnp.int32)
    init = (jnp.asarray(0, jnp.int32), z1, H0, status0, converged0 | nonfinite0, k0)
    j, z, H, status, done, updates = jax.lax.while_loop(cond, body, init)
    status = jnp.where(done, status, Status.MAX_ITERATIONS).astype(jnp.int32)
    return (
        z,
        NewtonStats(iterations=updates, residual_norm=jnp.asarray(jnp.nan, z.dtype), status=status, jacobians=j),
        H,
    )


def with_residual(stats: NewtonStats, residual) -> NewtonStats:
    """`stats` with the final residual's max-norm; a SUCCESS whose residual is not finite
    becomes NONFINITE."""
    res_norm = max_abs(ravel_pytree(residual)[0])
    status = jnp.where((stats.status == Status.SUCCESS) & ~jnp.isfinite(res_norm), Status.NONFINITE, stats.status)
    return stats._replace(residual_norm=res_norm, status=status.astype(jnp.int32))


def newton_solve_reusing(
    F: Callable,
    guess,
    H,
    reuse,
    *,
    rtol: float,
    atol: float,
    max_iterations: int,
    finish: Callable | None = None,
    max_contraction: float | None = None,
    matrix: Matrix = DENSE_INVERSE,
):
    r"""Solve $F(z) = 0$ for a pytree z by Newton's method, carrying the matrix between solves.

    `H` is the matrix returned by the previous solve (any array of the right structure when
    `reuse` is False). With `reuse` the solve starts with chord updates $z \leftarrow z - H F(z)$
    and forms a fresh Jacobian only when they contract by less than `max_contraction` (default
    `REUSE_MAX_CONTRACTION`) per update or do not converge within the matrix's `max_updates`;
    then it continues with fresh matrices (`newton_loop`), and the last one is returned for the
    next solve. The stopping rule (`converged`, to round-off with `rtol = atol = 0`), the
    statuses and `max_iterations` (the cap on fresh matrices per solve) are those of
    `newton_solve`.

    `finish(z) -> (F(z), extra)`, if given, evaluates the residual at the solution together
    with whatever else the caller needs there (sharing their work); it runs outside the
    implicitly differentiated solve, so `extra` is differentiable as usual. Without it F(z)
    is evaluated once more and `extra` is None. `stats.residual_norm` is max|F(z)| either way.

    **Returns:** `(z, NewtonStats, H, extra)`; `stats.jacobians` counts the fresh matrices
    (0 when the carried one sufficed). `H` carries no derivatives.
    """
    if max_contraction is None:
        max_contraction = REUSE_MAX_CONTRACTION
    flat0, unravel = ravel_pytree(guess)

    def F_flat(x):
        return ravel_pytree(F(unravel(x)))[0]

    def loop(f, x0):
        return newton_loop(f, x0, H, reuse, rtol, atol, max_iterations, max_contraction, matrix=matrix)

    flat, stats, H_new = implicit_root(F_flat, flat0, loop, matrix.tangent_solve)
    z = unravel(flat)
    residual, extra = (F(z), None) if finish is None else finish(z)
    return z, with_residual(stats, residual), H_new, extra


def newton_solve(F: Callable, guess, *, rtol: float, atol: float, max_iterations: int, matrix: Matrix | None = None):
    r"""Solve $F(z) = 0$ for a pytree $z$ by Newton's method with an exact (forward-mode) Jacobian.

    The Jacobian is formed at the initial guess and kept while the updates contract (chord,
    or simplified Newton, iterations), and refreshed when they stop contracting — one
    Jacobian per solve when the guess is good, full Newton on hard steps; `max_iterations`
    caps the number of Jacobians. It stops when the error left after an update, estimated from
    the contraction $\theta = \|\Delta z_k\|/\|\Delta z_{k-1}\|$ as $\theta\|\Delta z_k\|/(1-\theta)$,
    is below $\text{atol} + \text{rtol}\,\|z\|_\infty$, or when the update is at round-off (see
    `converged`), or with status `SINGULAR` / `NONFINITE` / `MAX_ITERATIONS`. Variational
    integrators conserve momenta only as well as each step is solved, and errors of 1e-15 per
    step add up over 10⁴ steps, so the march's default is `rtol = atol = 0`: iterate to
    round-off. `matrix` replaces the exact dense Jacobian (`dense_matrix`) by another one.

    **Returns:** `(z, NewtonStats)`. On failure `z` is the last finite iterate.
    """
    flat0, unravel = ravel_pytree(guess)
    matrix = dense_matrix(flat0.shape[0]) if matrix is None else matrix
    z, stats, _, _ = newton_solve_reusing(
        F, guess, None, False, rtol=rtol, atol=atol, max_iterations=max_iterations, matrix=matrix
    )
    return z, stats


def fixed_newton_solve(
    F: Callable,
    guess,
    *,
    updates: int,
    rtol: float,
    atol: float,
    finish: Callable | None = None,
    matrix: Matrix = FENCED_INVERSE,
    refresh: bool = False,
    rounds=1,
):
    r"""Solve $F(z) = 0$ by a fixed number of chord updates with one matrix formed at the guess,
    as straight-line code (no loop, no test between updates), then check the result.

    Updates $z_{k+1} = z_k - J(z_0)^{-1}F(z_k)$, k < `updates` (with `refresh`, full Newton
    updates $z_{k+1} = z_k - J(z_k)^{-1}F(z_k)$; the check then uses the last matrix). The
    check is the size of the update the residual at the result would make,
    $\eta = \|J(z_0)^{-1}F(z_K)\|_\infty$: the
    solve has status SUCCESS when `converged` (the general loop's stopping rule) accepts it —
    an update at round-off size, or a stalled one at the noise floor — and MAX_ITERATIONS
    otherwise (SINGULAR or NONFINITE when those stopped it). The caller that gets a failure
    solves again with the general loop (`newton_solve_reusing`): a chunk of a `sweep` does.
    With a predictor of order p from earlier steps ($\|z_0 - z^*\| = O(\Delta t^{p+1})$) the
    chord error after K updates is $O(\Delta t^{(K+1)(p+1)})$: at round-off after two updates
    in a well-resolved march, so that with K = 3 the check meets an update at the noise floor.

    `rounds` (an int, or a traced integer shared by every member of a batch): that many
    rounds, each a matrix formed at the current iterate and `updates` chord updates, in one
    loop whose body is the single copy of the solve's code — a march that needs more rounds
    on a few steps (a predictor still short of history) and one on the others compiles the
    solve once (`FixedNewton.warmup_rounds`). The check then uses the last round's matrix.
    A Python 1 (default) is straight-line code, no loop.

    Derivatives of the root come from the implicit function theorem, as for `newton_solve`.
    `finish(z) -> (F(z), extra)` as in `newton_solve_reusing`; its residual is the check's.

    **Returns:** `(z, NewtonStats, M, extra)`, M the matrix of the last round (no derivatives).
    """
    flat0, unravel = ravel_pytree(guess)

    def F_flat(x):
        return ravel_pytree(F(unravel(x)))[0]

    def one_round(f, x):
        Fz, M, singular = fence(matrix.invert(f, x))
        eta = jnp.asarray(jnp.inf, x.dtype)
        for k in range(updates):
            dz = matrix.apply(M, Fz)
            x, eta = fence((x - dz, max_abs(dz)))
            if k + 1 < updates and refresh:
                Fz, M, singular_k = fence(matrix.invert(f, x))
                singular = singular | singular_k
            elif k + 1 < updates:
                Fz = fence(f(x))
        return x, M, eta, singular

    def loop(f, x0):
        if isinstance(rounds, int) and rounds == 1:
            x, M, eta, singular = one_round(f, x0)
        else:  # the rounds in a loop: the round's code once (the matrix's shape from a trace of it)
            M0 = jax.tree_util.tree_map(
                lambda a: jnp.zeros(a.shape, a.dtype), jax.eval_shape(lambda x: matrix.invert(f, x)[1], x0)
            )

            def body(_, c):
                x, M, eta, singular = c
                x, M, eta, singular_k = one_round(f, x)
                return x, M, eta, singular | singular_k

            x, M, eta, singular = jax.lax.fori_loop(
                0, rounds, body, (x0, M0, jnp.asarray(jnp.inf, x0.dtype), jnp.asarray(False))
            )
        n_rounds = jnp.asarray(rounds, jnp.int32)
        stats = NewtonStats(
            iterations=n_rounds * updates,
            residual_norm=jnp.asarray(jnp.nan, x.dtype),
            status=jnp.where(singular, Status.SINGULAR, Status.SUCCESS).astype(jnp.int32),
            jacobians=n_rounds * (updates if refresh else 1),
        )
        return x, stats, (M, eta)

    flat, stats, (M, eta_last) = implicit_root(F_flat, flat0, loop, matrix.tangent_solve)
    z = unravel(flat)
    residual, extra = fence((F(z), None) if finish is None else finish(z))
    # the check: the update the residual at z would make, judged by the general loop's rule
    dz = matrix.apply(jax.lax.stop_gradient(M), ravel_pytree(residual)[0])
    eta, zmax = max_abs(jnp.stack([dz, flat]))
    done = converged(
        eta,
        jax.lax.stop_gradient(eta_last),
        jnp.asarray(updates, jnp.int32),
        tolerance(flat, rtol, atol, zmax),
        flat,
        zmax,
    )
    status = jnp.where(
        ~(jnp.isfinite(eta) & jnp.isfinite(zmax)),
        Status.NONFINITE,
        jnp.where(stats.status != Status.SUCCESS, stats.status, jnp.where(done, Status.SUCCESS, Status.MAX_ITERATIONS)),
    )
    stats = fence(with_residual(stats._replace(status=status.astype(jnp.int32)), residual))
    return z, stats, jax.lax.stop_gradient(M), extra
