r"""The full step: every step solves Lemma 20 for $(\xi^n, P^n, Q^{n+1})$ (dim V + 2 dim M
unknowns) and hands the symplectic state $(Q^{n+1}, p^{n+1})$ to the next step.

The residual is `jax.grad` of the discrete Lagrangian (`clebsch_jax.discrete.residual`); the
guess is the last step's unknowns plus the polynomial extrapolation of this sub-step's past
increments (`predictor`); the root finder is `Newton` (a fresh dense Jacobian at the guess) or
`BlockNewton` (lumped per-particle blocks, carried from step to step)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

from ..core.system import momentum_map
from ..discrete.legendre import explicit_nodal_velocity, initial_multiplier
from ..discrete.residual import StepUnknowns, nodal_residual, outgoing_momentum, step_residual
from ..roots.solvers import BlockNewton, Newton
from .base import Nodes
from .predictor import empty_history, predict, push
from .principles import PrincipleStep, check_particle_axis, check_principle

__all__ = ["FullStep"]


def seed_velocity(system, finder, Q0, P0, xi0):
    """The nodal velocity at (Q0, P0) from the guess xi0 (Lemma 7), to seed the first step; node
    0's velocity is solved again, and its status reported, with the other nodes after the march.
    A degenerate system has no nodal velocity: xi0 is kept."""
    if system.degenerate:
        return xi0
    mu = momentum_map(system, P0, Q0, xi0)
    if system.inverse_legendre is not None:
        return explicit_nodal_velocity(system, Q0, mu)[0]
    return finder.solve(lambda x: nodal_residual(system, Q0, mu, x), xi0)[0]


@dataclasses.dataclass(frozen=True)
class FullStep(PrincipleStep):
    r"""One step of the discrete Clebsch principle in full (Lemma 20): the unknowns
    $(\xi^n, P^n, Q^{n+1})$, the state $(Q^n, p^n)$. Symplectic; order and symmetry are those
    of the principle with the system's derivative map (`principle_facts`).

    **Arguments:**

    - `principle`: `Principle.LEFT` (Definition 19, default), `RIGHT` (Remark 22) or
      `MIDPOINT`; its string name is accepted too.
    - `root_finder`: `Newton()` (default) or, for N interacting particles (`Q0` and `xi0` with
      a leading particle axis), `BlockNewton()`.
    """

    form = "full"

    def __post_init__(self):
        super().__post_init__()
        if not isinstance(self.root_finder, Newton):
            raise TypeError(f"root_finder: expected clebsch_jax.Newton() or BlockNewton(), got {self.root_finder!r}.")

    def prepare(self, system, Q0, xi0) -> "FullStep":
        check_principle(system, self.principle)
        if isinstance(self.root_finder, BlockNewton):
            check_particle_axis(Q0, xi0)
        return self

    def init(self, system, Q0, xi0, P0, dt):
        if P0 is None:
            P0 = initial_multiplier(system, Q0, xi0)
        else:
            xi0 = seed_velocity(system, self.root_finder, Q0, P0, xi0)
        return (Q0, P0, xi0), 0

    def init_memory(self, system, state):
        Q, p, xi = state
        H = self.root_finder.initial_matrix(StepUnknowns(xi, p, Q)) if self.root_finder.carries_matrix else None
        return empty_history((2 * Q.size + xi.size,), Q.dtype), H

    def step(self, system, state, memory, h, n, alive):
        Q, p, xi_last = state
        history, H = memory
        # The guess is (ξ, P, Q¹) = (ξ_last, p, Q) + the predicted increment: at step 0 the
        # explicit (0, 0, h L_ξ Q), later the extrapolation of this sub-step's past increments.
        base, unravel = ravel_pytree(StepUnknowns(xi_last, p, Q))
        first = ravel_pytree(
            StepUnknowns(jnp.zeros_like(xi_last), jnp.zeros_like(p), h * system.velocity_map(xi_last, Q))
        )[0]
        residual = lambda z: step_residual(system, self.principle, h, Q, p, z)
        guess = unravel(base + predict(n, first, history))
        if self.root_finder.carries_matrix:  # this slot's last matrix, refreshed when it stops contracting
            z, stats, H, _ = self.root_finder.solve_reusing(residual, guess, H, (n > 0) | ~alive)
        else:
            z, stats = self.root_finder.solve(residual, guess)
        p1 = outgoing_momentum(system, self.principle, h, Q, z)
        history = push(history, ravel_pytree(z)[0] - base)
        return (z.Q1, p1, z.xi), (history, H), (z.xi, z.P), stats

    def nodes(self, system, state0, states, outs) -> Nodes:
        Q0, P0, xi0 = state0
        (Qs, ps, _), (xis, Ps) = states, outs
        Qs = jnp.concatenate([Q0[None], Qs])
        pn = jnp.concatenate([P0[None], ps])
        mus = jax.vmap(lambda q, p: momentum_map(system, p, q, xi0))(Qs, pn)
        return Nodes(Q=Qs, p=pn, P=Ps, momentum=mus, xi_step=xis, nodal_Q=Qs, xi_seed=xi0)
