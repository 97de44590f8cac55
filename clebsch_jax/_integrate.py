"""`integrate`: the single entry point. Validation → initial multiplier → scan of Newton steps."""

from __future__ import annotations

import dataclasses
import functools
import numbers

import jax
import jax.numpy as jnp
import numpy as np

from ._composition import plan_steps
from ._discrete_action import SCHEMES
from ._march_full import march_full
from ._march_gauss import march_gauss
from ._march_reduced import march_reduced
from ._reduction import find_reduction
from ._solution import Solution, check_traced
from ._system import ClebschSystem

__all__ = ["integrate"]


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
    if getattr(arr, "weak_type", False):  # a Python float: one compiled program with np.float64 input
        arr = jnp.asarray(arr, dtype=arr.dtype)
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


def _default_scheme(system, scheme):
    if scheme is None:
        return "midpoint" if system.degenerate else "left"
    return scheme


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
    scheme = _default_scheme(system, scheme)
    if scheme not in SCHEMES + ("gauss",):
        raise ValueError(f"scheme: expected one of {SCHEMES + ('gauss',)}, got {scheme!r}.")
    if scheme == "midpoint" and not callable(getattr(system.derivative_map, "at_midpoint", None)):
        raise ValueError(
            "scheme: 'midpoint' needs a derivative map that knows the midpoint of a step "
            "(an `at_midpoint(Q_next, Q, dt)` method, as clebsch_jax.forward_difference, cayley and "
            f"exponential have); {system.derivative_map!r} has none."
        )
    if system.degenerate and scheme not in ("midpoint", "gauss"):
        raise ValueError(
            f"scheme: {scheme!r} is inconsistent for a degenerate Lagrangian (system built with "
            "degenerate=True): the left/right principles become two-step schemes with parasitic "
            "modes. Use scheme='midpoint' or 'gauss'."
        )

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
    _check_configuration(system, Q0)
    return Q0, xi0, P0, dt, scheme


def _runnable_check(system, Q0):
    """`system.check_Q` when it can run on Q0, else None: values are known only when neither Q0
    nor the check's array leaves are traced (jit/vmap)."""
    check = system.check_Q
    if check is None or _is_traced(Q0) or any(_is_traced(x) for x in jax.tree_util.tree_leaves(check)):
        return None
    return check


def _check_configuration(system, Q0):
    """The system's own check that Q0 lies on its configuration manifold (`ClebschSystem.check_Q`,
    e.g. a rotation for SO(3) models): on concrete values only (`_runnable_check`)."""
    check = _runnable_check(system, Q0)
    if check is None:
        return
    problem = check(np.asarray(Q0))
    if problem is None:
        return
    if not isinstance(problem, str):
        raise TypeError(f"check_Q: must return None or a string saying what is wrong, returned "
                        f"{type(problem).__name__}.")
    raise ValueError(f"Q0: {problem}")


def _base_facts(system: ClebschSystem, scheme: str):
    """(order, symmetric) of the one-step principle: the midpoint principle is symmetric, of
    order 2; left/right are when the derivative map is symmetric (Example 30) and l has no
    potential (l(ξ, Qⁿ) at one end of the step is a first-order quadrature); else order 1."""
    if scheme == "midpoint":
        return 2, True
    symmetric = bool(getattr(system.derivative_map, "symmetric", False)) and not system.has_potential
    return (2 if symmetric else 1), symmetric


def step_plan(system: ClebschSystem, scheme: str | None = None, order=None, composition=None):
    """The `StepPlan` `integrate` runs for these arguments: its sub-steps and its facts
    (`order`, `symmetric`, `symplectic`, `name`, `solves_per_step`)."""
    scheme = _default_scheme(system, scheme)
    return plan_steps(scheme, *_base_facts(system, scheme), order, composition)


_march_full_jit = _filter_jit(march_full)
_march_reduced_jit = _filter_jit(march_reduced)
_march_gauss_jit = _filter_jit(march_gauss)


def integrate(
    system: ClebschSystem,
    Q0,
    xi0,
    *,
    dt,
    n_steps: int,
    P0=None,
    t0=0.0,
    scheme: str | None = None,
    reduce="auto",
    need_P: bool = False,
    reconstruct: bool = True,
    rtol: float = 0.0,
    atol: float = 0.0,
    max_newton_iterations: int = 20,
    jacobian: str = "dense",
    order: int | None = None,
    composition=None,
    throw: bool = True,
) -> Solution:
    r"""March the discrete Clebsch equations (Lemma 20) of `system` from $(Q^0, \xi^0)$.

    **Full march** (`form="full"`): each step solves, by Newton's method with a forward-mode
    Jacobian, the stationarity conditions of the discrete action (`clebsch_jax.discrete_action`)
    for $(\xi^n, P^n, Q^{n+1})$ — obtained with `jax.grad`, nothing model-specific written by
    hand — as a symplectic map $(Q^n, p^n) \mapsto (Q^{n+1}, p^{n+1})$.

    **Reduced march** (`form="reduced"`, Theorem 27 / Corollary 29): when the velocity map is
    right multiplication on a matrix group, closed (Theorem 12), and the derivative map is of
    Definition 25's form, Q and P are eliminated and each step solves only for $\xi^n$ (dim V
    unknowns) from the body momentum $\mu^n$; see `clebsch_jax._reduction`. Same trajectory,
    far fewer unknowns. Steps run in `jax.lax.scan` in both forms.

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
    - `scheme`: `"left"` (Definition 19; the default), `"right"` (the adjoint principle of Remark 22) or
      `"midpoint"` (l and the velocity map evaluated at the midpoint of each step: symmetric
      and second order also with a potential; the only scheme for degenerate Lagrangians; full
      march only; the default for systems built with `degenerate=True`). See
      `clebsch_jax.discrete_lagrangian`. Or `"gauss"`: the Gauss–Legendre partitioned
      Runge–Kutta discretisation of the Clebsch principle (`clebsch_jax._collocation`), with
      order/2 stages (`order` None: 2; any even order up to 16), which marches $(Q, P)$
      (`Solution.form` "full", `p` and `P` the nodal momenta) and does not use the derivative
      map (the collocation polynomial gives $\dot Q$): symmetric, symplectic, exact for
      quadratic invariants; each step is one fixed-point solve of its stages
      (`stats.iterations` counts sweeps, at most 5 × `max_newton_iterations`; a step too large
      for the iteration fails with `Status.DIVERGED`). On the rigid-body batch of
      `benchmarks/work_precision.py` its order 8 is 120–135× more accurate than the order-8
      composition at the same Δt, and faster; orders 12 and 16 take steps of 0.5-1 there. For
      a degenerate l (`degenerate=True`) it must be affine in ξ, as for point vortices: the
      stage Clebsch relations are then constraints that ξ enforces, and a sweep corrects ξ
      with the inverse of the constraints' bracket matrix (`jacobian`); order 2 is the
      midpoint principle again.
    - `reduce`: `"auto"` (default) uses the reduced march when it applies and `need_P` is
      False; `True` forces it (a `ValueError` says why when it does not apply); `False`
      forces the full march. `Solution.form` says which ran.
    - `need_P`: the caller needs the multipliers $P^n$. With `reduce="auto"` this selects the
      full march; with `reduce=True` the reduced march reconstructs the minimum-norm $P^n$.
    - `reconstruct`: reduced march only: reconstruct $Q^n$ (default). With False and an l
      that does not depend on Q, `Solution.Q` is None and Q is never computed.
    - `rtol`, `atol`, `max_newton_iterations`: Newton stopping rule, see `newton_solve`. The
      default 0, 0 iterates to round-off, which exact conservation of momenta needs; a
      positive tolerance bounds the estimated error per step instead (cheaper, but errors add
      up over long runs).
    - `jacobian`: the full march's Newton matrix. `"dense"` (default): the exact Jacobian by
      forward mode, for systems of modest size. `"blocks"`: for N interacting particles — `Q0`
      and `xi0` (and so every unknown) have a leading axis of length N — chord iterations
      with the lumped block-diagonal Jacobian (`clebsch_jax._block_newton`): b Jacobian-vector
      products per matrix instead of N·b and no (N·b)³ factorisation, converged to the same
      round-off; needed for N in the hundreds and more (point vortices, landmarks). With
      `scheme="gauss"` and a degenerate l: the constraint bracket matrix of each step whole
      (`"dense"`) or lumped into per-particle blocks (`"blocks"`, exact for point vortices).
    - `order`: None (default) runs the principle as it is (order 1, or 2 when it is symmetric:
      midpoint, or left/right with a symmetric derivative map and no potential). 2, 4, 6 or 8
      makes each step a symmetric composition of sub-steps (`clebsch_jax._composition`): the
      symmetric second-order step — the principle itself if symmetric, else the left principle
      composed with its adjoint, the right principle, over half steps — at orders 4, 6, 8
      composed with Suzuki's p4s5, Kahan & Li's p6s9 and p8s17 coefficients. Each sub-step is a
      discrete Clebsch step, so the composition is symplectic and conserves the same momentum
      maps; a step costs `step_plan(...).solves_per_step` Newton solves (5, 9, 17, doubled for
      a first-order principle). `Solution.order` and `Solution.method` record what ran.
    - `composition`: a `Composition` (or the name of one in `clebsch_jax.COMPOSITIONS`, e.g.
      "Suzuki-Umeno p8s15") instead of the default coefficients of its order.
    - `throw`: if True (default) a failed step raises `IntegrationError` once, at the end,
      naming the step (and batch member under `jax.vmap`), the reason and what to try. Under
      `jit`/`vmap` the error is raised from a host callback. If False, failures are only
      recorded in the `Solution` (`result`, `failed_step`, per-step `stats.status`, `valid`)
      so one bad member does not stop a batch; call `Solution.raise_if_failed()` later.

    **Returns:** a `Solution`.

    Transformations: works under `jax.jit` (`n_steps`, `scheme`, `reduce`, `order`,
    `composition` and the tolerances are static) and `jax.vmap` over `Q0`, `xi0`, `P0`, `dt` and array parameters inside the
    system. Derivatives (forward and reverse mode) flow through the Newton solves by implicit
    differentiation (`jax.lax.custom_root`).
    """
    Q0, xi0, P0, dt, scheme = _validate(system, Q0, xi0, P0, dt, n_steps, scheme, rtol, atol, max_newton_iterations)
    if reduce not in ("auto", True, False):
        raise ValueError(f"reduce: expected 'auto', True or False, got {reduce!r}.")
    if jacobian not in ("dense", "blocks"):
        raise ValueError(f"jacobian: expected 'dense' or 'blocks', got {jacobian!r}.")
    if jacobian == "blocks" and (Q0.ndim < 1 or xi0.ndim < 1 or Q0.shape[0] != xi0.shape[0]):
        raise ValueError(
            "jacobian: 'blocks' needs a leading particle axis shared by Q0 and xi0, got Q0 of shape "
            f"{Q0.shape} and xi0 of shape {xi0.shape}."
        )
    plan = step_plan(system, scheme, order, composition)
    t0 = _as_float_array(t0, "t0")
    if t0.shape != ():
        raise ValueError(f"t0: expected a scalar, got an array of shape {t0.shape}.")
    t0 = t0.astype(dt.dtype)
    P0_given = P0 is not None
    common = dict(n_steps=n_steps, scheme=scheme, plan=plan, rtol=float(rtol), atol=float(atol),
                  max_newton_iterations=int(max_newton_iterations), P0_given=P0_given)
    P0 = P0 if P0_given else jnp.zeros_like(Q0)
    red = None
    if scheme == "gauss":  # its own march (`_march_gauss`): no reduction, no Newton matrix
        if reduce is True:
            raise ValueError("reduce: the reduced march implements the left and right principles only; "
                             "scheme='gauss' marches (Q, P).")
        if jacobian != "dense" and not system.degenerate:
            raise ValueError("jacobian: scheme='gauss' solves the steps of a regular Lagrangian by fixed-point "
                             "sweeps, without a Newton matrix; 'blocks' lumps the constraint matrix of a degenerate "
                             f"one. Leave jacobian at 'dense', got {jacobian!r}.")
    elif reduce is True or (reduce == "auto" and not need_P):  # "auto" with need_P: full march
        if scheme == "midpoint":
            red, reason = None, "the reduced march implements the left and right principles only"
        else:
            red, reason = find_reduction(system, Q0, xi0)
        if reduce is True and red is None:
            raise ValueError(f"reduce: the reduced march does not apply to this system: {reason}.")
    if scheme == "gauss":
        sol = _march_gauss_jit(system, Q0, xi0, P0, dt, t0, **common, jacobian=jacobian)
    elif red is None:
        sol = _march_full_jit(system, Q0, xi0, P0, dt, t0, **common, jacobian=jacobian)
    else:
        sol = _march_reduced_jit(system, red, Q0, xi0, P0, dt, t0, **common,
                                 carry_Q=bool(reconstruct or system.has_potential or need_P),
                                 need_P=bool(need_P))
    if throw:
        if _is_traced(sol.result):
            sol = dataclasses.replace(sol, result=check_traced(sol))
        else:
            sol.raise_if_failed()
    return sol
