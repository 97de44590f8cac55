"""`integrate`: the single entry point. Validation → initial multiplier → scan of Newton steps."""

from __future__ import annotations

import dataclasses
import functools
import numbers

import jax
import jax.numpy as jnp
import numpy as np

from ._discrete_action import SCHEMES
from ._newton import NewtonStats, Status, newton_solve
from ._residual import StepUnknowns, legendre_residual, outgoing_momentum, step_residual
from ._solution import Solution, check_traced
from ._system import ClebschSystem

__all__ = ["integrate", "initial_multiplier", "nodal_velocity"]


# --------------------------------------------------------------------------------------------
# jit with array leaves traced and everything else static (so user closures can be passed).


def _is_array(x) -> bool:
    return isinstance(x, (jax.Array, np.ndarray, np.generic))


def _filter_jit(fun):
    @functools.partial(jax.jit, static_argnums=(0, 1))
    def jitted(treedef, static, dynamic):
        leaves = [d if s is _DYNAMIC else s for s, d in zip(static, dynamic)]
        args, kwargs = jax.tree_util.tree_unflatten(treedef, leaves)
        return fun(*args, **kwargs)

    @functools.wraps(fun)
    def wrapper(*args, **kwargs):
        leaves, treedef = jax.tree_util.tree_flatten((args, kwargs))
        static = tuple(_DYNAMIC if _is_array(x) else x for x in leaves)
        dynamic = [x if _is_array(x) else None for x in leaves]
        return jitted(treedef, static, dynamic)

    return wrapper


class _Dynamic:
    def __repr__(self):
        return "<dynamic>"


_DYNAMIC = _Dynamic()


# --------------------------------------------------------------------------------------------
# Validation: clear errors before compiling.


def _is_traced(x) -> bool:
    return isinstance(x, jax.core.Tracer)


def _as_float_array(x, name: str) -> jax.Array:
    if isinstance(x, (str, bytes)) or x is None:
        raise TypeError(f"{name}: expected an array of numbers, got {type(x).__name__}.")
    try:
        arr = jnp.asarray(x)
    except TypeError as err:
        raise TypeError(f"{name}: expected an array of numbers, got {type(x).__name__}.") from err
    if not (jnp.issubdtype(arr.dtype, jnp.floating) or jnp.issubdtype(arr.dtype, jnp.integer)
            or jnp.issubdtype(arr.dtype, jnp.bool_)):
        raise TypeError(f"{name}: expected a real floating-point array, got dtype {arr.dtype}.")
    if not jnp.issubdtype(arr.dtype, jnp.floating):
        arr = arr.astype(jnp.result_type(float))
    if not _is_traced(x) and not _is_traced(arr) and not np.all(np.isfinite(np.asarray(arr))):
        raise ValueError(f"{name}: contains non-finite values (NaN or inf).")
    return arr


def _shape_of(fn_name: str, fn, args, describe: str):
    try:
        out = jax.eval_shape(fn, *args)
    except Exception as err:  # the user's function could not even run on these shapes
        raise ValueError(
            f"{fn_name}: calling it as {describe} failed: {type(err).__name__}: {err}"
        ) from None
    return out


def _validate(system, Q0, xi0, P0, dt, n_steps, scheme, rtol, atol, max_newton_iterations):
    if not isinstance(system, ClebschSystem):
        raise TypeError(f"system: expected a clebsch_jax.ClebschSystem, got {type(system).__name__}.")
    if isinstance(n_steps, bool) or not isinstance(n_steps, numbers.Integral):
        raise TypeError(f"n_steps: expected a Python int, got {type(n_steps).__name__}.")
    if n_steps < 1:
        raise ValueError(f"n_steps: must be at least 1, got {n_steps}.")
    if isinstance(max_newton_iterations, bool) or not isinstance(max_newton_iterations, numbers.Integral) \
            or max_newton_iterations < 1:
        raise ValueError(f"max_newton_iterations: expected an int >= 1, got {max_newton_iterations!r}.")
    for name, tol in (("rtol", rtol), ("atol", atol)):
        if not isinstance(tol, numbers.Real) or not (tol >= 0) or not np.isfinite(tol):
            raise ValueError(f"{name}: expected a finite float >= 0, got {tol!r}.")
    if scheme not in SCHEMES:
        raise ValueError(f"scheme: expected one of {SCHEMES}, got {scheme!r}.")

    Q0 = _as_float_array(Q0, "Q0")
    xi0 = _as_float_array(xi0, "xi0")
    dt = _as_float_array(dt, "dt")
    if dt.shape != ():
        raise ValueError(f"dt: expected a scalar, got an array of shape {dt.shape}.")
    if not _is_traced(dt) and not float(np.asarray(dt)) > 0:
        raise ValueError(f"dt: must be positive, got {float(dt)}.")
    if P0 is not None:
        P0 = _as_float_array(P0, "P0")
        if P0.shape != Q0.shape:
            raise ValueError(f"P0: expected Q0's shape {Q0.shape}, got {P0.shape}.")

    sx, sq = jax.ShapeDtypeStruct(xi0.shape, xi0.dtype), jax.ShapeDtypeStruct(Q0.shape, Q0.dtype)
    shapes = f"xi0 of shape {xi0.shape} and Q0 of shape {Q0.shape}"
    lag = _shape_of("lagrangian", system.l, (sx, sq),
                    ("lagrangian(xi0, Q0)" if system.has_potential else "lagrangian(xi0)") + f" with {shapes}")
    if lag.shape != ():
        raise ValueError(f"lagrangian: must return a scalar, returned shape {lag.shape} for {shapes}.")
    vel = _shape_of("velocity_map", system.velocity_map, (sx, sq), f"velocity_map(xi0, Q0) with {shapes}")
    if vel.shape != Q0.shape:
        raise ValueError(
            f"velocity_map: must return an array of Q's shape {Q0.shape}, returned {vel.shape} for {shapes}."
        )
    sdt = jax.ShapeDtypeStruct((), dt.dtype)
    der = _shape_of("derivative_map", system.derivative_map, (sq, sq, sdt),
                    f"derivative_map(Q_next, Q, dt) with Q of shape {Q0.shape}")
    if der.shape != Q0.shape:
        raise ValueError(
            f"derivative_map: must return an array of Q's shape {Q0.shape}, returned {der.shape}."
        )
    return Q0, xi0, P0, dt


def _nominal_order(system: ClebschSystem) -> int:
    """Order of the one-step principles: 2 when the derivative map is symmetric (Example 30)
    and l has no potential (l(ξ, Qⁿ) at one end of the step is a first-order quadrature)."""
    symmetric = bool(getattr(system.derivative_map, "symmetric", False))
    return 2 if symmetric and not system.has_potential else 1


# --------------------------------------------------------------------------------------------
# The parts of the march.


def initial_multiplier(system: ClebschSystem, Q0: jax.Array, xi0: jax.Array) -> jax.Array:
    r"""The minimum-norm $P^0$ with $\delta l/\delta\xi(\xi^0, Q^0) = -P^0 \diamond Q^0$ (Lemma 7).

    With $A = \partial_\xi \mathcal L_\xi Q^0$ (a matrix from $V$ to $T_{Q^0}M$, by forward-mode
    autodiff) the condition is $A^T P^0 = \delta l/\delta \xi$; among its solutions we take the
    one of least Euclidean norm, $P^0 = (A^T)^+ \,\delta l/\delta\xi$. Components of $P^0$
    that the velocity map cannot see (e.g. the symmetric part of $Q^T P$ on $SO(3)$) are zero.
    """
    g = jax.grad(lambda x: system.l(x, Q0))(xi0).ravel()
    A = jax.jacfwd(lambda x: system.velocity_map(x.reshape(xi0.shape), Q0).ravel())(xi0.ravel())
    P0 = jnp.linalg.lstsq(A.T, g)[0]
    return P0.reshape(Q0.shape)


def nodal_velocity(system: ClebschSystem, Q: jax.Array, p: jax.Array, guess: jax.Array, *,
                   rtol: float = 1e-12, atol: float = 1e-12, max_iterations: int = 20):
    r"""Solve Lemma 7's $\delta l/\delta\xi(\xi, Q) = -p \diamond Q$ for $\xi$ by Newton.

    Returns `(xi, NewtonStats)`. Requires $l$ to be regular in $\xi$ (Lemma 8).
    """
    return newton_solve(lambda x: legendre_residual(system, Q, p, x), guess,
                        rtol=rtol, atol=atol, max_iterations=max_iterations)


def _march(system, Q0, xi0, P0, dt, t0, *, n_steps, scheme, rtol, atol, max_newton_iterations,
           P0_given):
    newton = functools.partial(newton_solve, rtol=rtol, atol=atol, max_iterations=max_newton_iterations)
    if not P0_given:
        P0 = initial_multiplier(system, Q0, xi0)
    else:
        # Seeds the first step's guess only; node 0's nodal velocity is solved (and its
        # status checked and reported) with all the other nodes after the march.
        xi0, _ = nodal_velocity(system, Q0, P0, xi0, rtol=rtol, atol=atol,
                                max_iterations=max_newton_iterations)
    z_first = StepUnknowns(xi0, P0, Q0 + dt * system.velocity_map(xi0, Q0))
    z_before = StepUnknowns(xi0, P0, Q0)

    def step(carry, _):
        Q, p, z_prev, z_pp, n, alive = carry
        guess = jax.tree_util.tree_map(
            lambda first, a, b: jnp.where(n == 0, first, 2.0 * a - b), z_first, z_prev, z_pp
        )
        z, stats = newton(lambda z: step_residual(system, scheme, dt, Q, p, z), guess)
        p1 = outgoing_momentum(system, scheme, dt, Q, z)
        ok = alive & (stats.status == Status.SUCCESS)
        status = jnp.where(alive, stats.status, Status.SKIPPED).astype(jnp.int32)
        z = jax.tree_util.tree_map(lambda a: jnp.where(ok, a, jnp.nan), z)
        p1 = jnp.where(ok, p1, jnp.nan)
        out = (z, p1, NewtonStats(stats.iterations, stats.residual_norm, status))
        return (z.Q1, p1, z, z_prev, n + 1, ok), out

    init = (Q0, P0, z_first, z_before, jnp.asarray(0, jnp.int32), jnp.asarray(True))
    _, (zs, ps, stats) = jax.lax.scan(step, init, None, length=n_steps)

    Qs = jnp.concatenate([Q0[None], zs.Q1])
    pn = jnp.concatenate([P0[None], ps])
    failed = stats.status != Status.SUCCESS
    valid = jnp.concatenate([jnp.array([True]), jnp.cumsum(failed) == 0])

    # Nodal velocities: the step velocity leaving each node is the initial guess.
    guesses = jnp.concatenate([xi0[None], zs.xi[1:], zs.xi[-1:]])
    xin, nodal = jax.vmap(
        lambda q, p, g: nodal_velocity(system, q, p, g, rtol=rtol, atol=atol,
                                       max_iterations=max_newton_iterations)
    )(Qs, pn, jnp.where(valid.reshape((-1,) + (1,) * xi0.ndim), guesses, jnp.nan))
    nodal_status = jnp.where(valid, nodal.status, Status.SKIPPED).astype(jnp.int32)
    xin = jnp.where(valid.reshape((-1,) + (1,) * xi0.ndim), xin, jnp.nan)
    nodal = NewtonStats(nodal.iterations, nodal.residual_norm, nodal_status)

    any_step = jnp.any(failed)
    first_step = jnp.argmax(failed)
    nodal_failed = valid & (nodal_status != Status.SUCCESS)
    any_nodal = jnp.any(nodal_failed)
    first_node = jnp.argmax(nodal_failed)
    result = jnp.where(any_step, stats.status[first_step],
                       jnp.where(any_nodal, Status.LEGENDRE, Status.SUCCESS)).astype(jnp.int32)
    failed_step = jnp.where(any_step, first_step, jnp.where(any_nodal, first_node, -1)).astype(jnp.int32)

    ts = t0 + dt * jnp.arange(n_steps + 1, dtype=dt.dtype)
    return Solution(
        ts=ts, Q=Qs, p=pn, xi=xin, xi_step=zs.xi, P=zs.P, stats=stats, nodal_stats=nodal,
        result=result, failed_step=failed_step, valid=valid, scheme=scheme, form="full",
        order=_nominal_order(system), derivative_map=getattr(system.derivative_map, "name", repr(system.derivative_map)),
        q_ndim=Q0.ndim, xi_ndim=xi0.ndim,
    )


_march_jit = _filter_jit(_march)


def integrate(
    system: ClebschSystem,
    Q0,
    xi0,
    *,
    dt,
    n_steps: int,
    P0=None,
    t0=0.0,
    scheme: str = "left",
    rtol: float = 1e-12,
    atol: float = 1e-12,
    max_newton_iterations: int = 20,
    throw: bool = True,
) -> Solution:
    r"""March the discrete Clebsch equations (Lemma 20) of `system` from $(Q^0, \xi^0)$.

    Each step solves, by Newton's method with a forward-mode Jacobian, the stationarity
    conditions of the discrete action (`clebsch_jax.discrete_action`) for
    $(\xi^n, P^n, Q^{n+1})$; the conditions are obtained with `jax.grad`, nothing
    model-specific is written by hand. Steps run in `jax.lax.scan`.

    **Arguments:**

    - `system`: a `ClebschSystem`.
    - `Q0`: initial configuration $Q^0$, any shape the system's maps accept.
    - `xi0`: initial velocity $\xi^0$. Unless `P0` is given, the initial multiplier is the
      minimum-norm solution of $\delta l/\delta\xi(\xi^0, Q^0) = -P^0 \diamond Q^0$
      (`initial_multiplier`). With `P0`, `xi0` only fixes the shape of $V$ and seeds the
      nodal-velocity solve.
    - `dt`: time step (> 0). `n_steps`: number of steps (a Python int >= 1).
    - `P0`: optional initial multiplier (the canonical momentum at $Q^0$), shape of `Q0`.
    - `t0`: initial time (only used for `Solution.ts`).
    - `scheme`: `"left"` (Definition 19) or `"right"` (the adjoint principle of Remark 22).
    - `rtol`, `atol`, `max_newton_iterations`: Newton stopping rule, see `newton_solve`.
    - `throw`: if True (default) a failed step raises `IntegrationError` once, at the end,
      naming the step (and batch member under `jax.vmap`), the reason and what to try. Under
      `jit`/`vmap` the error is raised from a host callback. If False, failures are only
      recorded in the `Solution` (`result`, `failed_step`, per-step `stats.status`, `valid`)
      so one bad member does not stop a batch; call `Solution.raise_if_failed()` later.

    **Returns:** a `Solution`.

    Transformations: works under `jax.jit` (`n_steps`, `scheme` and the tolerances are
    static) and `jax.vmap` over `Q0`, `xi0`, `P0`, `dt` and array parameters inside the
    system. Derivatives (forward and reverse mode) flow through the Newton solves by implicit
    differentiation (`jax.lax.custom_root`).
    """
    Q0, xi0, P0, dt = _validate(system, Q0, xi0, P0, dt, n_steps, scheme, rtol, atol, max_newton_iterations)
    t0 = jnp.asarray(t0, dtype=dt.dtype)
    P0_given = P0 is not None
    sol = _march_jit(system, Q0, xi0, P0 if P0_given else jnp.zeros_like(Q0), dt, t0,
                     n_steps=n_steps, scheme=scheme, rtol=float(rtol), atol=float(atol),
                     max_newton_iterations=int(max_newton_iterations), P0_given=P0_given)
    if throw:
        if _is_traced(sol.result):
            result = check_traced(sol)
            sol = dataclasses.replace(sol, result=result)
        else:
            sol.raise_if_failed()
    return sol
