"""Failure as a value: the status codes and statistics every root finder returns, and how the
statistics of several solves (a composed step) or of solves not attempted combine."""

from __future__ import annotations

import enum
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..core.validation import is_traced

__all__ = ["Status", "NewtonStats", "combine_stats", "stack_stats", "skip_stats"]


class Status(enum.IntEnum):
    """Per-step status codes carried through the march (failure is a value).

    An `IntEnum`: a member is the integer stored in the arrays, so `sol.stats.status ==
    cj.Status.SINGULAR` and `jnp.where(status == cj.Status.SUCCESS, ...)` work, and
    `cj.Status(int(code))` names a stored code. `Status.MESSAGES[code]` (or `.message`) says
    what a code means."""

    SUCCESS = 0
    MAX_ITERATIONS = 1
    NONFINITE = 2
    SINGULAR = 3
    SKIPPED = 4  # not attempted: an earlier step of this batch member failed
    LEGENDRE = 5  # the nodal velocity could not be recovered from (Q, p)
    DIVERGED = 6  # a fixed-point iteration (Gauss-Legendre step) stopped contracting
    ENERGY_JUMP = 7  # the step changed the energy by more than a tenth of its size so far
    INVALID_INPUT = 8  # under jit/vmap: this member's arguments or model parameters are invalid
    NOT_RUN = -1  # a sweep store's member whose batch is not written yet (never produced by a march)
    FIRST_STEP = 9  # the first step converged far from where two half steps arrive (a spurious root)
    OFF_MANIFOLD = 10  # under jit/vmap: the first step left the configuration manifold (the derivative map)

    @property
    def message(self) -> str:
        """What the code means, in a sentence."""
        return _MESSAGES[self]


_MESSAGES = {
    Status.SUCCESS: "converged",
    Status.MAX_ITERATIONS: "Newton's method reached the maximum number of iterations",
    Status.NONFINITE: "the residual or the Newton iterate became non-finite (NaN/inf)",
    Status.SINGULAR: "the Newton Jacobian is singular",
    Status.SKIPPED: "not attempted because an earlier step failed",
    Status.LEGENDRE: "the nodal velocity could not be recovered from (Q, p) by Lemma 7's "
    "relation dl/dxi(xi, Q) = -p<>Q",
    Status.DIVERGED: "the fixed-point iteration of a Gauss-Legendre step stopped contracting or overflowed "
    "(dt too large for it, or the model is not finite at the stage values)",
    Status.ENERGY_JUMP: "the step converged, but the energy changed in it by more than the energy check's tolerance (by default a tenth) of "
    "the size of its terms so far: it does not resolve the motion (a step across a singularity of the model, "
    "where the solve found a root on the far side, or a step far too large for the motion there)",
    Status.FIRST_STEP: "the first step converged, but far from the node two half steps reach: a root of the "
    "step equations that is not the step of the motion (a spurious root), or a step too large for the motion "
    "at the start",
    Status.OFF_MANIFOLD: "the first step left the configuration manifold, found under jit/vmap where it could "
    "not be refused: the derivative map's step with this principle does not keep Q on M (check_Q's manifold, "
    "or the matrix group the velocity map moves Q in), as the forward difference with the left or right "
    "principle on SO(3)",
    Status.INVALID_INPUT: "this member's input is invalid, found under jit/vmap where it could not be refused "
    "before compiling: dt not finite and positive, Q0/xi0/P0 not finite, Q0 off the configuration manifold "
    "(check_Q), the Lagrangian or velocity map not finite at (xi0, Q0) (a model parameter out of range, "
    "e.g. a non-positive inertia, makes the built-in models' Lagrangian NaN), or a velocity map not linear in xi "
    "at Q0 (Definition 1)",
    Status.NOT_RUN: "not run yet: this member's batch is not written in the sweep's store (an interrupted "
    "sweep; run it again with the same store to finish it)",
}
Status.MESSAGES = _MESSAGES
"""`Status.MESSAGES`: code → sentence (integer codes look up the same entries)."""


class NewtonStats(NamedTuple):
    """Statistics of one solve: updates made (`iterations`), final residual max-norm, status,
    and the number of Jacobians formed (`jacobians`)."""

    iterations: jax.Array
    residual_norm: jax.Array
    status: jax.Array
    jacobians: jax.Array

    def summary(self) -> str:
        """A few lines on these solves (concrete arrays, any batch shape): how many, how many
        converged and what stopped the others, the Newton updates per solve (mean, max, total),
        the Jacobians formed and the worst final residual."""
        if any(is_traced(a) for a in self):
            return "NewtonStats(<traced>)"
        status = np.asarray(self.status).ravel()
        iterations = np.asarray(self.iterations).ravel()
        attempted = status != Status.SKIPPED
        counts = {Status(int(c)): int(n) for c, n in zip(*np.unique(status, return_counts=True))}
        failed = ", ".join(f"{n} {code.name.lower()}" for code, n in counts.items() if code != Status.SUCCESS)
        residual = np.asarray(self.residual_norm, dtype=float).ravel()[attempted]
        worst = float(np.nanmax(residual)) if residual.size and not np.all(np.isnan(residual)) else float("nan")
        done = iterations[attempted]
        lines = [
            f"{status.size} solves: {counts.get(Status.SUCCESS, 0)} converged" + (f", {failed}" if failed else ""),
            (
                f"Newton updates per solve: mean {done.mean():.2f}, max {done.max()}, total {done.sum()}"
                if done.size
                else "Newton updates per solve: none attempted"
            ),
            f"Jacobians formed: {int(np.asarray(self.jacobians).sum())}; worst final residual: {worst:.2e}",
        ]
        return "\n".join(lines)

    def __repr__(self) -> str:
        if any(is_traced(a) for a in self) or np.ndim(self.status) == 0:
            return (
                f"NewtonStats(iterations={self.iterations!r}, residual_norm={self.residual_norm!r}, "
                f"status={self.status!r}, jacobians={self.jacobians!r})"
            )
        return "NewtonStats(\n  " + self.summary().replace("\n", "\n  ") + "\n)"

    @staticmethod
    def combine(solves) -> "NewtonStats":
        """The statistics of a step made of several solves (a sequence of `NewtonStats`, or one
        stacked along leading axes): updates and Jacobians add up, the residual is the worst,
        the status the first failure."""
        return combine_stats(stack_stats(solves))


def _first_failure(status):
    """The first status that is not SUCCESS along the last axis (SUCCESS if none)."""
    failed = status != Status.SUCCESS
    return jnp.where(
        jnp.any(failed, axis=-1),
        jnp.take_along_axis(status, jnp.argmax(failed, axis=-1)[..., None], axis=-1)[..., 0],
        Status.SUCCESS,
    ).astype(jnp.int32)


def combine_stats(stats: NewtonStats) -> NewtonStats:
    """One `NewtonStats` for a step made of several solves (stacked along the last axis): the
    updates and Jacobians add up, the residual is the worst, the status the first failure."""
    return NewtonStats(
        iterations=jnp.sum(stats.iterations, axis=-1).astype(jnp.int32),
        residual_norm=jnp.max(stats.residual_norm, axis=-1),
        status=_first_failure(stats.status),
        jacobians=jnp.sum(stats.jacobians, axis=-1).astype(jnp.int32),
    )


def stack_stats(stats) -> NewtonStats:
    """`NewtonStats` of several solves (a sequence, or stacked along leading axes) as one
    `NewtonStats` with the solves along the last axis, in order, for `combine_stats`."""
    if isinstance(stats, NewtonStats):
        return jax.tree_util.tree_map(lambda a: a.reshape(-1), stats)
    return jax.tree_util.tree_map(lambda *a: jnp.stack(a), *stats)


def skip_stats(stats: NewtonStats, attempted) -> NewtonStats:
    """`stats` with the solves that were not `attempted` marked SKIPPED, counting nothing."""
    return NewtonStats(
        iterations=jnp.where(attempted, stats.iterations, 0).astype(stats.iterations.dtype),
        residual_norm=jnp.where(attempted, stats.residual_norm, jnp.nan),
        status=jnp.where(attempted, stats.status, Status.SKIPPED).astype(jnp.int32),
        jacobians=jnp.where(attempted, stats.jacobians, 0).astype(stats.jacobians.dtype),
    )
