r"""Optimal control and parameter identification through `integrate` (gradients by the IFT).

Every step of `integrate` is a Newton solve of Lemma 20; its derivatives with respect to
anything the residual depends on — the initial data $(Q^0, P^0)$, model parameters — come
from the implicit function theorem (`clebsch_jax.roots.implicit`): for a step
$F(z; \theta) = 0$, $\partial z/\partial\theta = -(\partial_z F)^{-1}\partial_\theta F$, one
linear solve with the Jacobian at the root, never a derivative of the iterations. So
`jax.grad` of any scalar function of a `Solution` is the exact gradient of the discrete
flow map, reverse mode costs a few forward solves, and nothing here is model-specific.

**Shooting (the paper's optimal-control reading of the Clebsch principle).** In the
optimal-control context of Cotter & Holm's introduction, $\xi$ is a control that steers $Q$ by
$\dot Q = \mathcal L_\xi Q$ at cost $\int l(\xi)\,dt$, and the Clebsch multiplier $P$ is the
costate: a stationary trajectory is determined by its initial momentum $P^0$, and
$\delta l/\delta\xi = -P\diamond Q$ gives the control (for EPDiff's singular solutions,
Section 3.1, $P$ are the landmark momenta). `shoot` finds the
$P^0$ whose discrete flow carries $Q^0$ onto a target, by minimising

$$ J(P^0) = \mathrm{loss}\big(Q^N(P^0),\ Q_{\rm target}\big) + \lambda\,E(Q^0, P^0), $$

where $Q^N(P^0)$ is the last node of `integrate(system, Q0, xi0, P0=P0, ...)` and $E$ the
energy at node 0 (`clebsch_jax.diagnostics.energy`). For EPDiff landmarks
(`clebsch_jax.models.landmarks`) $E = \tfrac12 P\cdot K(Q)P$ is conserved along the geodesic,
so $\lambda E = (\lambda/T)\int_0^T l\,dt$ is the usual LDDMM kinetic-energy penalty and
$\lambda = 0$ is exact matching.

**Identification.** `fit_parameters` minimises the mean squared misfit between observations
and `observe(integrate(make_system(theta), Q0, xi0, ...))` over parameters $\theta$ (any
pytree of arrays).

**How the optimisation runs.** The gradient of the objective is one jitted program, cached
across calls (compiled again only when the system's functions, the shapes or the static
options change: rerunning with another optimiser or learning rate costs no compilation); the
optimiser's update is a second, small jitted step; a Python loop alternates them and stops
early. Any optax `GradientTransformation` works; line-search methods
(`optax.lbfgs`, `GradientTransformationExtraArgs`) get the objective as `value_fn`, which puts
a copy of the integration into their update program (one more compilation).
"""

from __future__ import annotations

import dataclasses
import numbers
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from .core.validation import float_array, nonnegative, positive_scalar
from .core.system import ClebschSystem
from ._optimisation import fit_terms, fit_value_and_grad, minimize, shooting_terms, shooting_value_and_grad

__all__ = ["shoot", "fit_parameters", "ShootingResult", "FitResult", "squared_distance", "mean_squared_error"]

_RESERVED = ("P0", "throw", "dt", "n_steps")


# --------------------------------------------------------------------------------------------
# Losses.


def squared_distance(Q_end: jax.Array, target: jax.Array) -> jax.Array:
    r"""$\|Q^N - Q_{\rm target}\|^2$, the sum of squares over every axis (shapes of Q); a scalar.
    `shoot`'s default endpoint loss (for landmarks: the sum over landmarks of their squared
    Euclidean distances to the targets)."""
    return jnp.sum((Q_end - target) ** 2)


def mean_squared_error(predicted: jax.Array, observed: jax.Array) -> jax.Array:
    r"""$\frac1m\sum_i (y_i - \hat y_i)^2$ over the m entries of the observations; a scalar.
    `fit_parameters`' default loss: for independent Gaussian noise of standard deviation
    $\sigma$ it tends to $\sigma^2$ at the true parameters."""
    return jnp.mean((predicted - observed) ** 2)


# --------------------------------------------------------------------------------------------
# Results.


@dataclasses.dataclass(frozen=True)
class ShootingResult:
    r"""What `shoot` found (NumPy arrays; shapes for Q of shape `Q.shape`, K = `iterations`).

    **Fields:**

    - `P0` (Q.shape): the last iterate (the last one whose integration succeeded, if one
      failed).
    - `path` (n_steps + 1, *Q.shape): the nodes $Q^0, \dots, Q^N$ of the flow from `P0`;
      `endpoint` = `path[-1]`, where the flow arrives.
    - `momentum` (n_steps + 1, *ξ.shape): the momentum map $\mu^n = -p^n\diamond Q^n$ along
      that flow (for landmarks the momenta $p^n$ themselves: `momentum[-1]` is the costate
      at $T$ of Pontryagin's principle).
    - `mismatch`: the endpoint loss (without the regulariser) at `P0`.
    - `objective`: $J$ at `P0` (mismatch + λ·energy); `gradient` (Q.shape): $\nabla_{P^0}J$ there.
    - `losses` (n_iterations + 1,): $J$ at every iterate, starting with `P0_init`; NaN after
      the loop stopped.
    - `mismatches` (n_iterations + 1,): the endpoint loss at every iterate, NaN after the stop.
    - `iterations`: optimiser updates made (K).
    - `converged`: the mismatch reached `tol` or the gradient's max-norm reached `gtol`.
    - `message`: why the loop stopped.
    """

    P0: np.ndarray
    path: np.ndarray
    momentum: np.ndarray
    mismatch: float
    objective: float
    gradient: np.ndarray
    losses: np.ndarray
    mismatches: np.ndarray
    iterations: int
    converged: bool
    message: str

    @property
    def endpoint(self) -> np.ndarray:
        return self.path[-1]


@dataclasses.dataclass(frozen=True)
class FitResult:
    r"""What `fit_parameters` found.

    **Fields:**

    - `params`: the last iterate (the last one whose integration succeeded, if one failed), with
      the pytree structure of `params0` and NumPy leaves.
    - `loss`: the loss at `params`; `gradient`: its gradient there (the structure of `params`).
    - `predicted`: `observe(solution)` at `params` (the shape of the observations), e.g. for
      residual plots; with `n_iterations=0` this simply evaluates the model at `params0`.
    - `losses` (n_iterations + 1,): the loss at every iterate, starting with `params0`; NaN after
      the loop stopped.
    - `iterations`: optimiser updates made.
    - `converged`: the loss reached `tol` or the gradient's max-norm reached `gtol`.
    - `message`: why the loop stopped.
    """

    params: Any
    loss: float
    gradient: Any
    predicted: np.ndarray
    losses: np.ndarray
    iterations: int
    converged: bool
    message: str


# --------------------------------------------------------------------------------------------
# Validation: clear errors before compiling.


def _float_array(x, name: str) -> jax.Array:
    """`integrate`'s own conversion and checks, and no booleans: a mask is not data to fit or
    shoot from."""
    return float_array(x, name, allow_bool=False)


def _check_common(dt, n_steps, optimizer, n_iterations, tol, gtol, options):
    if isinstance(n_steps, bool) or not isinstance(n_steps, numbers.Integral) or n_steps < 1:
        raise ValueError(f"n_steps: expected a Python int >= 1, got {n_steps!r}.")
    dt = positive_scalar(dt, "dt", allow_bool=False)
    if not (callable(getattr(optimizer, "init", None)) and callable(getattr(optimizer, "update", None))):
        raise TypeError(
            "optimizer: expected an optax GradientTransformation (e.g. optax.adam(1e-2)), "
            f"got {type(optimizer).__name__}."
        )
    if isinstance(n_iterations, bool) or not isinstance(n_iterations, numbers.Integral) or n_iterations < 0:
        raise ValueError(f"n_iterations: expected a Python int >= 0, got {n_iterations!r}.")
    tol, gtol = nonnegative(tol, "tol"), nonnegative(gtol, "gtol")
    for name in _RESERVED:
        if name in options:
            raise ValueError(f"{name}: set by this function; it cannot be passed as an integrate option.")
    return dt, tol, gtol


def _scalar_output(fn, name: str, *args):
    try:
        out = jax.eval_shape(fn, *args)
    except Exception as err:  # the user's function could not run on these shapes
        raise ValueError(f"{name}: calling it failed: {type(err).__name__}: {err}") from None
    if getattr(out, "shape", None) != ():
        raise ValueError(f"{name}: must return a scalar, returned {getattr(out, 'shape', type(out).__name__)}.")


# --------------------------------------------------------------------------------------------
# Public entry points.


def shoot(
    system: ClebschSystem,
    Q0,
    target,
    P0_init,
    *,
    dt,
    n_steps: int,
    optimizer,
    n_iterations: int,
    loss: Callable | None = None,
    regularization: float = 0.0,
    xi0=None,
    tol: float = 0.0,
    gtol: float = 0.0,
    **integrate_options,
) -> ShootingResult:
    r"""Find the initial momentum $P^0$ whose discrete flow carries $Q^0$ to `target` (shooting).

    Minimises, with the optax `optimizer` from `P0_init`,

    $$ J(P^0) = \mathrm{loss}(Q^N(P^0), Q_{\rm target}) + \lambda\,E(Q^0, P^0), $$

    $Q^N(P^0)$ the last node of `integrate(system, Q0, xi0, P0=P0, dt=dt, n_steps=n_steps,
    **integrate_options)` and $E = \langle\delta l/\delta\xi, \xi^0\rangle - l(\xi^0, Q^0)$ the
    energy at node 0 ($\xi^0$ solved from $P^0$ by Lemma 7). The gradient
    $\nabla_{P^0}J$ is exact for the discrete flow (reverse mode, Newton solves differentiated
    implicitly). The loop stops when the mismatch (the loss term) is at most `tol`, when the
    gradient's max-norm is at most `gtol`, when an integration fails (the iterate before is
    returned, with a message saying which step failed), or after `n_iterations` updates.

    **Arguments:**

    - `system`: a `ClebschSystem` with a velocity map that can reach the target (e.g.
      `clebsch_jax.models.landmarks(width)`, where $Q$ and $P$ have shape (N, d)).
    - `Q0`, `target`, `P0_init`: arrays of Q's shape: the start, where $Q^N$ should arrive, and
      the first guess of $P^0$ (zeros is a fine start for landmarks: it is the identity flow).
    - `dt`, `n_steps`: the time grid, $T$ = `n_steps · dt`.
    - `optimizer`: an optax `GradientTransformation` (`optax.adam(1e-2)`, `optax.sgd(...)`,
      `optax.lbfgs()`; line-search methods receive `value`, `grad` and `value_fn`).
    - `n_iterations`: the maximum number of optimiser updates (a Python int >= 0).
    - `loss`: `loss(Q_end, target) -> scalar` (default `squared_distance`, the sum of squares).
    - `regularization`: $\lambda \ge 0$ (default 0: exact matching).
    - `xi0`: a velocity of V's shape; with `P0` given it only fixes V's shape and seeds the
      nodal-velocity solve (`integrate`). Default: zeros of Q's shape (V = the tangent space at
      the particles, as for landmarks); pass it when V differs (e.g. a matrix group).
    - `tol`, `gtol`: stopping thresholds (>= 0; default 0: run `n_iterations` updates).
    - `**integrate_options`: passed to `integrate` (`scheme`, `order`, `jacobian`, `rtol`, ...;
      not `P0`, `dt`, `n_steps`, `throw`). For landmarks use `scheme="midpoint"` (second order).

    **Returns:** a `ShootingResult`.

    Transformations: `shoot` runs a Python loop (not traceable: call it outside `jax.jit`/
    `jax.vmap`). The gradient program is compiled once per system (its functions, compared as
    objects: the built-in models' are module-level; array parameters may change), shapes, `loss`
    and static options, and reused by later calls (another optimiser, target or width: no
    recompilation).
    For batches of problems or nested differentiation, `jax.vmap`/`jax.grad` the objective
    itself (`integrate` supports both).
    """
    if not isinstance(system, ClebschSystem):
        raise TypeError(f"system: expected a clebsch_jax.ClebschSystem, got {type(system).__name__}.")
    dt, tol, gtol = _check_common(dt, n_steps, optimizer, n_iterations, tol, gtol, integrate_options)
    Q0 = _float_array(Q0, "Q0")
    target = _float_array(target, "target")
    P0_init = _float_array(P0_init, "P0_init")
    if target.shape != Q0.shape:
        raise ValueError(f"target: expected Q0's shape {Q0.shape}, got {target.shape}.")
    if P0_init.shape != Q0.shape:
        raise ValueError(f"P0_init: expected Q0's shape {Q0.shape}, got {P0_init.shape}.")
    if xi0 is None:
        try:
            fits = (
                jax.eval_shape(system.velocity_map, Q0, Q0).shape == Q0.shape
                and jax.eval_shape(system.l, Q0, Q0).shape == ()
            )
        except Exception:
            fits = False
        if not fits:
            raise ValueError(
                f"xi0: the system's maps do not accept a velocity of Q's shape {Q0.shape}; pass xi0 "
                "(any velocity of V's shape, e.g. zeros)."
            )
        xi0 = jnp.zeros_like(Q0)
    xi0 = _float_array(xi0, "xi0")
    loss = squared_distance if loss is None else loss
    if not callable(loss):
        raise TypeError(f"loss: expected a function loss(Q_end, target) -> scalar, got {type(loss).__name__}.")
    _scalar_output(loss, "loss", Q0, target)
    weight = nonnegative(regularization, "regularization")
    regularize = weight > 0
    if regularize and system.degenerate:
        raise ValueError(
            "regularization: needs the energy of the nodal velocity, which a degenerate system "
            "(degenerate=True) does not determine; use regularization=0."
        )

    options = dict(integrate_options)
    weight = jnp.asarray(weight, Q0.dtype)

    def value_and_grad(P):
        return shooting_value_and_grad(P, system, Q0, target, xi0, dt, weight, n_steps, loss, regularize, options)

    def value_fn(P):  # for line searches, traced into the optimiser's update
        return shooting_terms(
            P, system, Q0, target, xi0, dt, weight, n_steps=n_steps, loss=loss, regularize=regularize, options=options
        )[0]

    last, losses, datas, k, converged, message = minimize(
        value_and_grad, value_fn, P0_init, optimizer, n_iterations, tol, gtol, "mismatch"
    )
    P0, (data, (path, momentum), _, _), value, grad = last
    return ShootingResult(
        P0=np.asarray(P0),
        path=np.asarray(path),
        momentum=np.asarray(momentum),
        mismatch=float(data),
        objective=float(value),
        gradient=np.asarray(grad),
        losses=losses,
        mismatches=datas,
        iterations=int(k),
        converged=bool(converged),
        message=message,
    )


def fit_parameters(
    make_system: Callable,
    params0,
    observations,
    Q0,
    xi0,
    *,
    dt,
    n_steps: int,
    observe: Callable | None = None,
    optimizer,
    n_iterations: int,
    loss: Callable | None = None,
    tol: float = 0.0,
    gtol: float = 0.0,
    **integrate_options,
) -> FitResult:
    r"""Identify model parameters from an observed trajectory (least squares through `integrate`).

    Minimises over $\theta$, with the optax `optimizer` from `params0`,

    $$ J(\theta) = \mathrm{loss}\big(\hat y(\theta),\ y\big), \qquad
       \hat y(\theta) = \mathrm{observe}\big(\mathrm{integrate}(\mathrm{make\_system}(\theta), \dots)\big), $$

    by default the mean squared error $\frac1m\sum_i(\hat y_i(\theta) - y_i)^2$ over the m
    entries of `observations` $y$ (for independent Gaussian noise of standard deviation
    $\sigma$, $J \approx \sigma^2$ at the true parameters). The gradient is exact for the
    discrete flow (Newton solves differentiated implicitly). Constraints are the caller's
    parametrisation: e.g. positive moments of inertia as `make_system = lambda log_I:
    rigid_body(jnp.exp(log_I))`. The loop stops when $J \le$ `tol`, when the gradient's
    max-norm is at most `gtol`, when an integration fails (the iterate before is returned,
    with a message), or after `n_iterations` updates.

    **Arguments:**

    - `make_system`: `make_system(params) -> ClebschSystem`, traceable in `params`.
    - `params0`: the first guess, a pytree of float arrays (e.g. one array).
    - `observations`: an array of the shape `observe` returns.
    - `Q0`, `xi0`: the (known) initial data of the observed trajectory.
    - `dt`, `n_steps`: the time grid of the simulation.
    - `observe`: `observe(solution) -> array` (default: `solution.Q`, shape (n_steps+1, *Q.shape)),
      e.g. `lambda s: s.momentum[::10]` for every tenth body momentum.
    - `optimizer`, `n_iterations`, `tol`, `gtol`: as in `shoot`.
    - `loss`: `loss(predicted, observations) -> scalar` (default `mean_squared_error`).
    - `**integrate_options`: passed to `integrate` (`scheme`, `order`, `P0`, ...; not `dt`,
      `n_steps`, `throw`).

    **Returns:** a `FitResult`.

    Transformations: a Python loop of jitted steps, as `shoot` (call it outside `jax.jit`).
    The gradient program is cached on `make_system`, `observe` and `loss` (the same function
    objects) and the shapes: a second fit with other data or another optimiser reuses it.
    """
    if not callable(make_system):
        raise TypeError(f"make_system: expected a function params -> ClebschSystem, got {type(make_system).__name__}.")
    dt, tol, gtol = _check_common(
        dt, n_steps, optimizer, n_iterations, tol, gtol, {k: v for k, v in integrate_options.items() if k != "P0"}
    )
    leaves, treedef = jax.tree_util.tree_flatten(params0)
    if not leaves:
        raise ValueError("params0: expected at least one array of parameters, got an empty pytree.")
    params0 = jax.tree_util.tree_unflatten(treedef, [_float_array(x, "params0") for x in leaves])
    system = make_system(params0)
    if not isinstance(system, ClebschSystem):
        raise TypeError(f"make_system: must return a clebsch_jax.ClebschSystem, returned {type(system).__name__}.")
    observations = _float_array(observations, "observations")
    Q0, xi0 = _float_array(Q0, "Q0"), _float_array(xi0, "xi0")
    observe = _observe_Q if observe is None else observe
    if not callable(observe):
        raise TypeError(f"observe: expected a function solution -> array, got {type(observe).__name__}.")
    loss = mean_squared_error if loss is None else loss
    if not callable(loss):
        raise TypeError(
            f"loss: expected a function loss(predicted, observations) -> scalar, got {type(loss).__name__}."
        )
    if "P0" in integrate_options:
        integrate_options = dict(integrate_options, P0=_float_array(integrate_options["P0"], "P0"))
    options = dict(integrate_options)

    def value_and_grad(p):
        return fit_value_and_grad(p, make_system, Q0, xi0, observations, dt, n_steps, observe, loss, options)

    def value_fn(p):
        return fit_terms(
            p, make_system, Q0, xi0, observations, dt, n_steps=n_steps, observe=observe, loss=loss, options=options
        )[0]

    last, losses, _, k, converged, message = minimize(
        value_and_grad, value_fn, params0, optimizer, n_iterations, tol, gtol, "loss"
    )
    params, (_, predicted, _, _), value, grad = last
    to_numpy = lambda tree: jax.tree_util.tree_map(np.asarray, tree)
    return FitResult(
        params=to_numpy(params),
        loss=float(value),
        gradient=to_numpy(grad),
        predicted=np.asarray(predicted),
        losses=losses,
        iterations=int(k),
        converged=bool(converged),
        message=message,
    )


def _observe_Q(sol):
    return sol.Q
