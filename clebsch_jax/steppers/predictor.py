"""The initial guess of a step's unknowns: polynomial extrapolation of the solutions of the
same sub-step in earlier steps, carried as their table of backward differences."""

from __future__ import annotations

import jax.numpy as jnp

from ..roots.newton import max_abs

__all__ = ["PREDICTOR_ORDER", "predict", "degree", "push", "empty_history"]


PREDICTOR_ORDER = 5
"""Highest degree of the polynomial through the last solutions that predicts the next one
(`predict`)."""


def predict(n, first, history, degree=None):
    """Initial guess of step n's unknowns: `first` at n = 0, then the polynomial extrapolation
    of the solutions of the last steps in Newton's backward-difference form
    zⁿ ≈ Σⱼ ∇ʲzⁿ⁻¹, j = 0 … p, from `history`, the table of those differences (`push`).

    The degree p is at most min(n − 1, PREDICTOR_ORDER) (the differences the steps made so far
    support) and, beyond 1, a difference is used only while the differences decrease by at
    least half each (max-norm): over a smooth, well-resolved trajectory the predictor is then
    of high order (error O(Δtᵖ⁺¹), which saves Newton updates), while an under-resolved or
    rough one (where high-degree extrapolation amplifies) falls back to low degree.

    `degree`, if given, is that choice made beforehand (the function `degree(n, history)`)."""
    D = _rows(history)
    if degree is None:
        degree = _degree(n, D)
    total = D[0]
    for j in range(1, D.shape[0]):
        total = jnp.where(j <= degree, total + D[j], total)
    return jnp.where(n == 0, first, total.reshape(first.shape))


def degree(n, history):
    """How many differences `predict(n, ·, history)` uses beyond the first: an int32 from 0 to
    p. A march computes it at the end of the step before (its history is then complete) and
    carries it: each component's prediction then reads it instead of recomputing the max-norm
    sizes of every component's differences (which XLA does in each component's computation
    when the components are rows of their own, `clebsch_jax.batching.scalarise`). One number
    rather than a flag per difference: XLA computes each flag, with the chain of tests before
    it, in a computation of its own."""
    return _degree(n, _rows(history))


def _rows(history):
    """The differences ∇ʲzⁿ⁻¹, j = 0 … p, as rows (p + 1, size)."""
    return history.reshape(history.shape[0], -1)


def _degree(n, D):
    """The differences used beyond the first: a difference j ≥ 1 while j < n and, beyond the
    first, while each is at most half the one before (max-norm)."""
    size = max_abs(D)
    count, keep = jnp.zeros((), jnp.int32), jnp.asarray(True)
    for j in range(1, D.shape[0]):
        if j >= 2:
            keep = keep & (size[j] <= 0.5 * size[j - 1])
        keep = keep & (n > j)
        count = count + keep.astype(jnp.int32)
    return count


def push(history, z):
    r"""The difference table after the solution z of a new step: $\nabla^0 = z$ and
    $\nabla^j z^n = \nabla^{j-1}z^n - \nabla^{j-1}z^{n-1}$, j = 1 … p (the oldest difference
    drops out). One subtraction per difference, where forming them from the last p + 1
    solutions with binomial coefficients takes p + 1 products and sums each, in every step."""
    rows = [z]
    for j in range(1, history.shape[0]):
        rows.append(rows[-1] - history[j - 1])
    return jnp.stack(rows)


def empty_history(shape, dtype):
    """The difference table `predict` extrapolates from before any step was made (not read at
    step 0): the differences of solutions that were all zero."""
    return jnp.zeros((PREDICTOR_ORDER + 1,) + tuple(shape), dtype)
