"""The optimisation behind `clebsch_jax.control`'s `shoot` and `fit_parameters`: their objectives,
each one jitted value-and-gradient program through `integrate` (cached across calls), and the
loop that alternates it with the optimiser's jitted update and stops early (`minimize`)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax

from .core.jit import filter_jit
from .diagnostics import node_energy
from .march.integrate import integrate
from .roots.status import Status

__all__ = ["shooting_terms", "shooting_value_and_grad", "fit_terms", "fit_value_and_grad", "minimize"]


# --------------------------------------------------------------------------------------------
# The objectives (one jitted value-and-gradient program each, cached across calls).


def shooting_terms(P0, system, Q0, target, xi0, dt, weight, *, n_steps, loss, regularize, options):
    sol = integrate(
        system, Q0, xi0, P0=P0, dt=dt, n_steps=n_steps, throw=False, backend="xla", **options
    )  # differentiated
    data = loss(sol.Q[-1], target)
    value = data + weight * node_energy(system, Q0, sol.xi[0]) if regularize else data
    ok = sol.result == Status.SUCCESS
    nan = jnp.asarray(jnp.nan, value.dtype)
    return jnp.where(ok, value, nan), (jnp.where(ok, data, nan), (sol.Q, sol.momentum), sol.result, sol.failed_step)


@filter_jit
def shooting_value_and_grad(P0, system, Q0, target, xi0, dt, weight, n_steps, loss, regularize, options):
    terms = lambda P: shooting_terms(
        P, system, Q0, target, xi0, dt, weight, n_steps=n_steps, loss=loss, regularize=regularize, options=options
    )
    return jax.value_and_grad(terms, has_aux=True)(P0)


def fit_terms(params, make_system, Q0, xi0, observations, dt, *, n_steps, observe, loss, options):
    sol = integrate(
        make_system(params), Q0, xi0, dt=dt, n_steps=n_steps, throw=False, backend="xla", **options
    )  # differentiated
    predicted = observe(sol)
    if jnp.shape(predicted) != observations.shape:
        raise ValueError(
            f"observe: returned shape {jnp.shape(predicted)}, but observations have shape {observations.shape}."
        )
    value = loss(predicted, observations)
    if jnp.shape(value) != ():
        raise ValueError(f"loss: must return a scalar, returned shape {jnp.shape(value)}.")
    ok = sol.result == Status.SUCCESS
    return jnp.where(ok, value, jnp.nan), (value, predicted, sol.result, sol.failed_step)


@filter_jit
def fit_value_and_grad(params, make_system, Q0, xi0, observations, dt, n_steps, observe, loss, options):
    terms = lambda p: fit_terms(
        p, make_system, Q0, xi0, observations, dt, n_steps=n_steps, observe=observe, loss=loss, options=options
    )
    return jax.value_and_grad(terms, has_aux=True)(params)


# --------------------------------------------------------------------------------------------
# The optimisation loop: jitted gradient, jitted update, Python loop with early stopping.


def _update_step(optimizer, value_fn):
    extra = isinstance(optimizer, optax.GradientTransformationExtraArgs)

    @jax.jit
    def step(params, state, value, grad):
        if extra:
            updates, state = optimizer.update(grad, state, params, value=value, grad=grad, value_fn=value_fn)
        else:
            updates, state = optimizer.update(grad, state, params)
        return optax.apply_updates(params, updates), state

    return step


def _max_norm(tree) -> float:
    leaves = jax.tree_util.tree_leaves(tree)
    return max((float(jnp.max(jnp.abs(x))) for x in leaves), default=0.0)


def minimize(value_and_grad, value_fn, params, optimizer, n_iterations, tol, gtol, what):
    """Python loop of (jitted) gradient evaluations and optimiser updates.

    `value_and_grad(params) -> ((value, (data, extra, result, failed_step)), grad)`.
    Returns ((params, aux, value, grad) of the last iterate whose integration succeeded, losses,
    datas, iterations, converged, message)."""
    state = optimizer.init(params)
    step = _update_step(optimizer, value_fn)
    losses = np.full(n_iterations + 1, np.nan)
    datas = np.full(n_iterations + 1, np.nan)
    last = None
    converged, message, k = False, f"reached n_iterations = {n_iterations}", 0
    for k in range(n_iterations + 1):
        (value, aux), grad = value_and_grad(params)
        value, data = float(value), float(aux[0])
        if not np.isfinite(value) or not all(bool(jnp.all(jnp.isfinite(g))) for g in jax.tree_util.tree_leaves(grad)):
            result, failed = int(aux[2]), int(aux[3])
            if result != Status.SUCCESS:
                what_failed = f"the integration failed at step {failed} ({Status.MESSAGES.get(result, result)})"
            else:
                what_failed = "the objective or its gradient is not finite"
            message = (
                f"stopped at iteration {k}: {what_failed}; returning the iterate before. "
                "Try a smaller learning rate or time step."
            )
            break
        losses[k], datas[k] = value, data
        last = (params, aux, value, grad)
        if data <= tol:
            converged, message = True, f"converged: {what} {data:.3e} <= tol = {tol:.3e} after {k} iterations"
            break
        gnorm = _max_norm(grad)
        if gnorm <= gtol:
            converged = True
            message = f"converged: gradient max-norm {gnorm:.3e} <= gtol = {gtol:.3e} after {k} iterations"
            break
        if k == n_iterations:
            break
        params, state = step(params, state, value, grad)
    if last is None:
        raise ValueError(f"the initial guess already fails: {message}")
    return last, losses, datas, k, converged, message
