r"""The Gauss–Legendre step: the s-stage partitioned Runge–Kutta discretisation of the Clebsch
principle (`clebsch_jax.discrete.collocation`), order 2s, carrying the canonical pair
$(Q^n, P^n)$.

Each step finds its stage velocities and increments by the fixed-point iteration of
`gauss_sweep` (`FixedPoint`), to round-off by default, from the guess of the previous step's
collocation polynomials continued over one step (step 0: of `FIRST_STEP_SUBSTEPS` solved
substeps); the inverse Hessians of l in ξ that the sweeps use are formed once per step, at
that guess (for a degenerate l: the inverse of the constraint bracket matrix,
`degenerate_sweep`). A sweep evaluates the model's gradients once per stage and forms no
Jacobian. The march hands each step the sweep count of the step before (the stepper's
memory), from which the sweeps judge how many to make before their first convergence test
(`FixedPoint`'s `tests_ahead`).
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import jax
import jax.numpy as jnp

from ..core.system import momentum_map
from ..discrete.collocation import (
    GAUSS_ORDERS,
    GaussUnknowns,
    constraint_matrix_inverse,
    degenerate_sweep,
    extrapolate,
    from_substeps,
    gauss_legendre,
    gauss_sweep,
    gauss_update,
    stage_hessians,
)
from ..discrete.legendre import initial_multiplier
from ..roots.solvers import FixedPoint, Newton
from ..roots.status import Status
from .base import AbstractStepper, Facts, Nodes
from .full import seed_velocity
from .principles import check_particle_axis

__all__ = ["GaussLegendre", "FIRST_STEP_SUBSTEPS", "SWEEPS_PER_NEWTON_ITERATION", "UNTESTED_SWEEPS"]

FIRST_STEP_SUBSTEPS = 4
"""The first step has no previous step to extrapolate: its guess comes from this many substeps
of a quarter of its size, each solved from the one before (the first from constant slopes).
From constant slopes alone the sweeps can diverge on large steps where every later step
converges from its extrapolated guess."""

SWEEPS_PER_NEWTON_ITERATION = 5
"""`integrate`'s `max_newton_iterations` read for sweeps: a step may take
`SWEEPS_PER_NEWTON_ITERATION × max_newton_iterations` sweeps (100 by default), a sweep gaining
about one digit where a Newton update gains many."""

UNTESTED_SWEEPS = 6
"""The sweeps of a step before its first convergence test, at least (`FixedPoint`'s
`untested`; the step before can make it more, `tests_ahead`): with tests of two sweeps the
first test comes after the eighth, and no step swept to the increments' round-off from its
extrapolated guess stopped earlier in the runs of `benchmarks/README.md`."""


@dataclasses.dataclass(frozen=True)
class GaussLegendre(AbstractStepper):
    r"""The Gauss–Legendre discretisation of the Clebsch principle in Hamiltonian form,
    $H(\xi, Q, P) = \langle P, \mathcal L_\xi Q\rangle - l(\xi, Q)$, with order/2 stages:
    symmetric, symplectic, exact for quadratic invariants; one stage is the midpoint
    principle. It marches $(Q, P)$ (form "full") and does not use the derivative map.

    **Arguments:**

    - `order`: an even order from 2 to 16 (default 2).
    - `root_finder`: the `FixedPoint` sweeps that solve a step's stages (default
      `FixedPoint(untested=UNTESTED_SWEEPS)`: to round-off, at most 100 sweeps, the first test
      a little before the sweep count of the step before (`tests_ahead`); a step too large for
      the iteration fails with `Status.DIVERGED`).
    - `nodal_solver`: the `Newton` that recovers nodal velocities (default `Newton()`).
    - `constraint_blocks`: for a degenerate l (affine in ξ, as point vortices), lump the
      constraint bracket matrix into per-particle blocks (exact for point vortices) instead of
      forming it whole; needs a leading particle axis.
    - `compensated`: add each step's increments to (Q, P) by compensated (Kahan) summation,
      the rounding error carried in the state to the next step (`gauss_update`), and sweep the
      increments to their own round-off (`until_stalled`, `fixed_point_solve`), not the
      state's (default True): Hairer, McLachlan & Razakarivony's recipe for round-off that
      grows as √n. Without it the iteration's leftover, ~ε|Q| per step and a smooth function
      of the state, drifts the energy linearly over 10⁶ steps (`benchmarks/README.md`, long
      horizon), and the state's rounding makes a random walk of ~ε√n.
    """

    order: int = 2
    root_finder: FixedPoint = FixedPoint(untested=UNTESTED_SWEEPS)
    nodal_solver: Newton = Newton()
    constraint_blocks: bool = False
    compensated: bool = True

    quick_compile: ClassVar[bool] = False  # its sweeps ran slower with QUICK_COMPILE

    def __post_init__(self):
        if isinstance(self.order, bool) or self.order not in GAUSS_ORDERS:
            raise ValueError(
                f"order: Gauss-Legendre expects an even order from 2 to {GAUSS_ORDERS[-1]}, got {self.order!r}."
            )
        if not isinstance(self.root_finder, FixedPoint):
            raise TypeError(f"root_finder: expected clebsch_jax.FixedPoint(), got {self.root_finder!r}.")
        if not isinstance(self.compensated, bool):
            raise TypeError(f"compensated: expected True or False, got {self.compensated!r}.")

    @property
    def stages(self) -> int:
        return self.order // 2

    def facts(self, system) -> Facts:
        return Facts("full", "gauss", self.order, True, True, f"Gauss-Legendre {self.stages}-stage PRK", 1)

    def prepare(self, system, Q0, xi0) -> "GaussLegendre":
        if self.constraint_blocks:
            if not system.degenerate:
                raise ValueError(
                    "jacobian: scheme='gauss' solves the steps of a regular Lagrangian by fixed-point "
                    "sweeps, without a Newton matrix; 'blocks' lumps the constraint matrix of a "
                    "degenerate one. Leave jacobian at 'dense'."
                )
            check_particle_axis(Q0, xi0)
        return self

    def _matrices(self, system, tab, Q, P, z):  # formed once per step, at the guess
        if system.degenerate:
            return constraint_matrix_inverse(system, z.xi[0], Q, P, blocks=self.constraint_blocks)[0]
        return stage_hessians(system, tab, Q, P, z)

    def _sweep(self, system, tab, h, Q, P, z, matrices):
        if system.degenerate:
            return degenerate_sweep(system, tab, h, Q, P, z, matrices)
        return gauss_sweep(system, tab, h, Q, P, z, matrices)

    def init_memory(self, system, state):
        """The sweeps of the step before (none before the first)."""
        return jnp.zeros((), jnp.int32)

    def _advance(self, system, tab, h, state, compensation=None, previous=None):
        """One solved step: the next (Q, P, guess), its unknowns and statistics; with
        `compensation` (`gauss_update`), the next compensation too; `previous`: the sweeps of
        the step before."""
        Q, P, guess = state
        mats = self._matrices(system, tab, Q, P, guess)
        # sizes are judged against the state the increments are added to, and ξ
        size = jnp.max(jnp.abs(jnp.concatenate([Q.ravel(), P.ravel(), guess.xi.ravel()])))
        # compensated: the increments to their own round-off, not the state's (`fixed_point_solve`)
        z, stats = self.root_finder.solve(
            lambda z: self._sweep(system, tab, h, Q, P, z, mats),
            guess,
            size=size,
            until_stalled=compensation is not None,
            previous=previous,
        )
        if compensation is None:
            Q1, P1 = gauss_update(Q, P, z)
            return (Q1, P1, extrapolate(tab, z)), z, stats
        Q1, P1, compensation = gauss_update(Q, P, z, compensation)
        return (Q1, P1, extrapolate(tab, z), compensation), z, stats

    def init(self, system, Q0, xi0, P0, dt):
        tab = gauss_legendre(self.stages)
        if P0 is None:
            P0 = initial_multiplier(system, Q0, xi0)
        else:
            xi0 = seed_velocity(system, self.nodal_solver, Q0, P0, xi0)
        # Step 0's guess: FIRST_STEP_SUBSTEPS solved substeps, the first from constant slopes (one
        # sweep from zero increments at the initial velocity); if one fails, constant slopes, and
        # step 0 reports what its own solve meets. The substeps' sweeps count as step 0's work.
        zero = jnp.zeros((tab.stages,) + Q0.shape, Q0.dtype)
        still = GaussUnknowns(jnp.broadcast_to(xi0, (tab.stages,) + xi0.shape), zero, zero)
        h_sub = dt / FIRST_STEP_SUBSTEPS
        m0 = self._matrices(system, tab, Q0, P0, still)
        crude = self._sweep(system, tab, h_sub, Q0, P0, still, m0)

        def substep(state, _):
            state, z, st = self._advance(system, tab, h_sub, state)
            return state, (z, st.status, st.iterations)

        _, (zs, status, sweeps) = jax.lax.scan(substep, (Q0, P0, crude), None, length=FIRST_STEP_SUBSTEPS)
        ok = jnp.all(status == Status.SUCCESS)
        guess0 = jax.tree_util.tree_map(
            lambda a, b: jnp.where(ok, a, b), from_substeps(tab, zs), self._sweep(system, tab, dt, Q0, P0, still, m0)
        )
        compensation = (jnp.zeros_like(Q0), jnp.zeros_like(P0)) if self.compensated else None
        return (Q0, P0, guess0, xi0, compensation), jnp.sum(sweeps)

    def step(self, system, state, memory, h, n, alive):
        tab = gauss_legendre(self.stages)
        Q, P, guess, xi0, compensation = state
        advanced, z, stats = self._advance(system, tab, h, (Q, P, guess), compensation, memory)
        Q1, P1, guess1 = advanced[:3]
        compensation = advanced[3] if compensation is not None else None
        xi_mean = jnp.tensordot(jnp.asarray(tab.b, z.xi.dtype), z.xi, axes=1)
        return (Q1, P1, guess1, xi0, compensation), stats.iterations, xi_mean, stats

    def nodes(self, system, state0, states, outs) -> Nodes:
        Q0, P0, _, xi0, _ = state0
        Qs, Ps = states[0], states[1]
        Qs = jnp.concatenate([Q0[None], Qs])
        pn = jnp.concatenate([P0[None], Ps])
        mus = jax.vmap(lambda q, p: momentum_map(system, p, q, xi0))(Qs, pn)
        return Nodes(Q=Qs, p=pn, P=pn[:-1], momentum=mus, xi_step=outs, nodal_Q=Qs, xi_seed=xi0)
