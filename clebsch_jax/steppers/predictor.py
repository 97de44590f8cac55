"""The initial guess of a step's unknowns: polynomial extrapolation of the solutions of the
same sub-step in earlier steps."""

from __future__ import annotations

import functools
import math

import jax.numpy as jnp
import numpy as np

from ..roots.newton import max_abs

__all__ = ["PREDICTOR_ORDER", "predict", "degree", "push", "empty_history"]


PREDICTOR_ORDER = 5
"""Highest degree of the polynomial through the last solutions that predicts the next one
(`predict`)."""


def predict(n, first, history, degree=None):
    """Initial guess of step n's unknowns: `first` at n = 0, then the polynomial extrapolation
    of the solutions of the last steps, `history` (newest first, leading axis p + 1), in
    Newton's backward-difference form zⁿ ≈ Σⱼ ∇ʲzⁿ⁻¹, j = 0 … p.

    The degree p is at most min(n − 1, PREDICTOR_ORDER) (the differences the steps made so far
    support) and, beyond 1, a difference is used only while the differences decrease by at
    least half each (max-norm): over a smooth, well-resolved trajectory the predictor is then
    of high order (error O(Δtᵖ⁺¹), which saves Newton updates), while an under-resolved or
    rough one (where high-degree extrapolation amplifies) falls back to low degree.

    `degree`, if given, is that choice made beforehand (the function `degree(n, history)`)."""
    D = _differences(history)
    if degree is None:
        degree = _degree(n, D)
    total = D[0]
    for j in range(1, D.shape[0]):
        total = total + jnp.where(j <= degree, D[j], 0.0)
    return jnp.where(n == 0, first, total.reshape(first.shape))


def degree(n, history):
    """How many differences `predict(n, ·, history)` uses beyond the first: an int32 from 0 to
    p. A march computes it at the end of the step before (its history is then complete) and
    carries it: each component's prediction then reads it instead of recomputing the max-norm
    sizes of every component's differences (which XLA does in each component's computation
    when the components are rows of their own, `clebsch_jax.batching.scalarise`). One number
    rather than a flag per difference: XLA computes each flag, with the chain of tests before
    it, in a computation of its own."""
    return _degree(n, _differences(history))


def _differences(history):
    """The backward differences ∇ʲzⁿ⁻¹ = Σᵢ (-1)ⁱ C(j, i) zⁿ⁻¹⁻ⁱ, j = 0 … p, as rows (p + 1, size),
    each computed in one piece (elementwise, which XLA fuses into one operation)."""
    p = history.shape[0] - 1
    H = history.reshape(p + 1, -1)
    C = np.array([[(-1) ** i * math.comb(j, i) for i in range(p + 1)] for j in range(p + 1)], dtype=float)
    return functools.reduce(jnp.add, [jnp.asarray(C[:, i : i + 1], H.dtype) * H[i] for i in range(p + 1)])


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
    """`history` with z in front and the oldest entry dropped."""
    return jnp.concatenate([z[None], history[:-1]])


def empty_history(shape, dtype):
    """The history `predict` extrapolates from before any step was made (not read at step 0)."""
    return jnp.zeros((PREDICTOR_ORDER + 1,) + tuple(shape), dtype)
