r"""The root finders a stepper can use, as small frozen objects (hashable, so static under
`jax.jit`): each holds its stopping rule and solves through the one Newton loop of
`clebsch_jax.roots.newton` or the fixed-point loop of `clebsch_jax.roots.fixed_point`.

With `rtol = atol = 0` (the default) every solve iterates to round-off: a variational
integrator conserves momenta only as well as each step is solved."""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import jax.numpy as jnp

from ..core.validation import nonnegative, positive_int
from .blocks import block_newton_solve, block_newton_solve_reusing, identity_blocks
from .fixed_point import SWEEPS_PER_TEST, fixed_point_solve
import jax

from .newton import fixed_newton_solve, newton_solve, newton_solve_reusing

__all__ = ["Newton", "FixedNewton", "BlockNewton", "FixedPoint"]


@dataclasses.dataclass(frozen=True)
class Newton:
    r"""Newton's method with the exact (forward-mode) Jacobian, kept while chord updates
    contract (`clebsch_jax.newton_solve`).

    **Arguments:**

    - `rtol`, `atol`: stop when the estimated error $\theta\|\Delta z\|/(1-\theta)$ is below
      $\text{atol} + \text{rtol}\,\|z\|_\infty$; 0, 0 (default) iterates to round-off.
    - `max_iterations`: the most Jacobians formed per solve (default 20).
    """

    rtol: float = 0.0
    atol: float = 0.0
    max_iterations: int = 20

    carries_matrix: ClassVar[bool] = False
    """Whether a full march carries this finder's matrix from step to step (`solve_reusing`)
    rather than forming a fresh one per solve: a dense Jacobian is formed fresh at the good
    guess of each step."""

    def __post_init__(self):
        object.__setattr__(self, "rtol", nonnegative(self.rtol, "rtol"))
        object.__setattr__(self, "atol", nonnegative(self.atol, "atol"))
        object.__setattr__(self, "max_iterations", positive_int(self.max_iterations, "max_iterations"))

    @property
    def _options(self):
        return dict(rtol=self.rtol, atol=self.atol, max_iterations=self.max_iterations)

    def solve(self, F, guess):
        """Solve F(z) = 0 from `guess`. **Returns:** `(z, NewtonStats)`."""
        return newton_solve(F, guess, **self._options)

    def solve_reusing(self, F, guess, H, reuse, finish=None, step=None):
        """Solve F(z) = 0 first with the carried inverse Jacobian `H` (if `reuse`; `step`, the
        step's number in a march, is not used).
        **Returns:** `(z, NewtonStats, H, extra)` (see `newton_solve_reusing`)."""
        return newton_solve_reusing(F, guess, H, reuse, finish=finish, **self._options)

    def initial_matrix(self, guess):
        """A placeholder carried matrix for the first solve of a march."""
        return jnp.eye(guess.size, dtype=guess.dtype)


@dataclasses.dataclass(frozen=True)
class FixedNewton(Newton):
    r"""A fixed number of chord updates from the step's prediction, then a check
    (`clebsch_jax.roots.newton.fixed_newton_solve`): straight-line code, with no loop whose
    trip count depends on the data, for batches of many members that all converge alike.

    A solve the check does not accept has status MAX_ITERATIONS: it is not at round-off, and
    the caller solves again with `Newton` (`clebsch_jax.sweep` reruns the chunk of steps with
    the general loop, so every member and step it reports is solved as `Newton` solves it).

    **Arguments:** those of `Newton` (the stopping rule of the check, the general loop of the
    start-up steps and of one-off solves), and

    - `updates`: chord updates per solve (default 3: with a good guess the last update is
      already at round-off, so the check sees two updates at the noise floor and tells a
      converged solve from one still contracting, as the general loop's stagnation rule does).

    `solve` (a one-off solve, e.g. of a nodal velocity, whose guess may be poor) is `Newton`'s.
    - `warmup`: the first steps of a march (counted by the caller's `step`) solve with the
      general loop (default 4), while the predictor has too few earlier steps to be accurate.
    - `refresh`: form a fresh Jacobian at every update (full Newton updates, which converge
      quadratically from a poorer guess) instead of once per solve (default False).
    - `warmup_rounds`: 0 (default) solves the warm-up steps with the general loop; r > 0 solves
      them by r rounds of a fresh matrix and `updates` chord updates, the later steps by one
      round, in one loop over the rounds (`fixed_newton_solve`'s `rounds`): the solve is
      compiled once instead of twice, for a longer running step (a loop around every solve).
      The sweep's lean chunk uses it (`clebsch_jax.batching.lean.WARMUP_ROUNDS`).
    """

    updates: int = 3
    warmup: int = 4
    refresh: bool = False
    warmup_rounds: int = 0

    def __post_init__(self):
        super().__post_init__()
        object.__setattr__(self, "updates", positive_int(self.updates, "updates"))
        object.__setattr__(self, "warmup", positive_int(self.warmup, "warmup", minimum=0))
        object.__setattr__(self, "warmup_rounds", positive_int(self.warmup_rounds, "warmup_rounds", minimum=0))

    def solve_reusing(self, F, guess, H, reuse, finish=None, step=None):
        """`updates` chord updates and a check; the general loop for steps before `warmup`
        (`step`: the step's number, None: treated as past the warm-up).
        **Returns:** `(z, NewtonStats, H, extra)` as `Newton.solve_reusing`."""

        def fixed(_, rounds=1):
            return fixed_newton_solve(
                F,
                guess,
                updates=self.updates,
                rtol=self.rtol,
                atol=self.atol,
                finish=finish,
                refresh=self.refresh,
                rounds=rounds,
            )

        if step is None or self.warmup == 0:
            return fixed(None)
        if self.warmup_rounds:
            return fixed(None, jnp.where(step < self.warmup, self.warmup_rounds, 1))

        def general(_):
            return newton_solve_reusing(F, guess, H, reuse, finish=finish, **self._options)

        return jax.lax.cond(step < self.warmup, general, fixed, None)


@dataclasses.dataclass(frozen=True)
class BlockNewton(Newton):
    r"""Chord iterations with the lumped block-diagonal Jacobian, one block per particle, for N
    interacting particles (`clebsch_jax.roots.blocks`): every unknown has a leading axis of
    length N. b Jacobian-vector products per matrix instead of N·b, no (N·b)³ factorisation;
    the full residual is still driven to round-off. A march carries the inverse blocks from
    step to step and refreshes them only when they stop contracting. Same arguments as
    `Newton` (`max_iterations` caps the block matrices per solve)."""

    carries_matrix: ClassVar[bool] = True  # forming the lumped matrix costs more than a step's updates

    def solve(self, F, guess):
        return block_newton_solve(F, guess, **self._options)

    def solve_reusing(self, F, guess, H, reuse, finish=None, step=None):
        z, stats, H = block_newton_solve_reusing(F, guess, H, reuse, **self._options)
        return z, stats, H, None

    def initial_matrix(self, guess):
        return identity_blocks(guess)


@dataclasses.dataclass(frozen=True)
class FixedPoint:
    r"""Fixed-point sweeps $z \leftarrow G(z)$ for a contraction with a good guess
    (`clebsch_jax.roots.fixed_point.fixed_point_solve`), to round-off by default.

    **Arguments:**

    - `rtol`, `atol`: as for `Newton`, judged on the size of the last update.
    - `max_iterations`: the most sweeps per solve (default 100; a sweep gains about one digit
      where a Newton update gains many).
    - `untested`: sweeps before the first convergence test (default 4: a test costs about as
      much as a sweep, and a well-predicted step needs more than that).
    - `per_test`: sweeps between two convergence tests (default `SWEEPS_PER_TEST`, 2). Sweeps
      that cost far more than a test (matrix products over n² unknowns) are tested after
      each one, `per_test=1`, with `untested=0`: a well-predicted solve then stops at the
      first sweep that reaches its tolerance, not at the next multiple of the test interval.
    - `tests_ahead`: in a march that hands each solve the sweep count of its previous one
      (`solve`'s `previous`, n; `GaussLegendre` does), sweep untested up to `tests_ahead`
      tests before n — `n − (tests_ahead + 1)·per_test` sweeps, at least `untested` — so that
      a solve needing about as many sweeps as the last makes a few tests, not one every
      `per_test` sweeps from the start, and a count can fall by `tests_ahead` tests from one
      step to the next (default 2; None: `untested` only). On the native backend the sweeps
      of a convergence loop cost more than straight ones, since the loop keeps each lane's
      carry and runs until the slowest lane of the vector is done (`benchmarks/README.md`).
    """

    rtol: float = 0.0
    atol: float = 0.0
    max_iterations: int = 100
    untested: int = 4
    per_test: int = SWEEPS_PER_TEST
    tests_ahead: int | None = 2

    def __post_init__(self):
        object.__setattr__(self, "rtol", nonnegative(self.rtol, "rtol"))
        object.__setattr__(self, "atol", nonnegative(self.atol, "atol"))
        object.__setattr__(self, "max_iterations", positive_int(self.max_iterations, "max_iterations"))
        object.__setattr__(self, "untested", positive_int(self.untested, "untested", minimum=0))
        object.__setattr__(self, "per_test", positive_int(self.per_test, "per_test"))
        if self.tests_ahead is not None:
            object.__setattr__(self, "tests_ahead", positive_int(self.tests_ahead, "tests_ahead", minimum=0))

    def solve(self, G, guess, size=None, until_stalled: bool = False, previous=None):
        """Solve z = G(z) from `guess`, sizes judged against `size`; with `until_stalled`, to the
        round-off of z's own entries (`fixed_point_solve`); `previous`: the sweeps of the solve
        before (an int array; `tests_ahead`). **Returns:** `(z, NewtonStats)`."""
        extra = None
        if previous is not None and self.tests_ahead is not None:
            extra = previous - self.untested - (self.tests_ahead + 1) * self.per_test
        return fixed_point_solve(
            G,
            guess,
            rtol=self.rtol,
            atol=self.atol,
            max_iterations=self.max_iterations,
            size=size,
            untested=self.untested,
            per_test=self.per_test,
            until_stalled=until_stalled,
            extra=extra,
        )
