r"""The reduced step (Theorem 27, Corollary 29): dim V unknowns per step instead of
dim V + 2 dim M. The state is the body momentum $\mu^n = -p^n\diamond Q^n$; Q is carried only
when l depends on it (Definition 14) or the caller asks for it, and updated explicitly,
$Q^{n+1} = Q^n\,\overline{\exp}(\Delta t X(\xi^n))$.

Each step is small (a few hundred flops for the rigid body), so its cost is the number of
operations XLA runs (each with a fixed cost on the CPU) and the number of Newton updates:

- the residual and the outgoing momentum come from one evaluation (`reduced_step`), in closed
  form for the Cayley map;
- the guess is the last velocity plus a polynomial extrapolation of the increments this
  sub-step made in earlier steps (`predictor`);
- for the Cayley map every solve forms the exact Jacobian at that guess, from the cheap
  closed-form residual: Newton converges quadratically from the good guess, so one update
  reaches round-off and a second confirms it, and a batch pays its slowest member's updates
  (the second half step of a `SymmetricPair` starts from the first one's instead:
  `step_sharing`);
- for other maps, whose residual costs more (the exponential pair: the derivative of the
  logarithm as φ₁(ad)⁻¹ from a matrix exponential; any other pair: autodiff of exp̄ and loḡ)
  and makes a Jacobian expensive, the inverse Jacobian is carried from step to step: formed
  at step 0 and again only when its chord updates stop contracting well.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from ..core.derivative_maps import CayleyDifference
from ..core.system import momentum_map
from ..discrete.legendre import initial_multiplier
from ..discrete.matrix_group import MatrixAlgebraReduction, MatrixGroupReduction, find_reduction
from ..discrete.reduction import reduced_step
from ..roots.solvers import FixedNewton, FixedPoint, Newton
from .base import Nodes, Principle
from .full import seed_velocity
from .predictor import degree, empty_history, predict, push
from .principles import PrincipleStep

__all__ = ["ReducedStep"]


@dataclasses.dataclass(frozen=True)
class ReducedStep(PrincipleStep):
    r"""One step of the reduced discrete Euler–Poincaré equation (Theorem 27, Corollary 29),
    for a velocity map that is right multiplication on a matrix group, closed (Theorem 12),
    with a derivative map of Definition 25's form: P and Q are eliminated and each step solves
    dim V equations for $\xi^n$ from the body momentum. Same trajectory as `FullStep` with the
    same principle.

    **Arguments:**

    - `principle`: `Principle.LEFT` (default) or `RIGHT`.
    - `root_finder`: a `Newton()` (or a `FixedNewton()`, which `clebsch_jax.sweep` uses), or
      `FixedPoint()` for a system that gives its inverse Legendre map G
      (`ClebschSystem(inverse_legendre=...)`): matrix-free sweeps
      $\xi \leftarrow G(\nabla l(\xi) + r(\xi))$ (made on $\nabla l(\xi)$: `_sweep`), r the
      step's residual, whose leading part is
      $\mu^n - \nabla l(\xi)$ — Newton's update with the Jacobian $-\nabla^2 l$ of $\Delta t = 0$,
      contracting like $O(\Delta t\,|\xi|)$. For the Euler–Zeitlin fluid this is the isospectral
      midpoint method's own iteration, with O(n³) work per sweep and no Jacobian.
    - `reconstruct`: carry and return $Q^n$ (default True). With False and an l without
      potential, `Solution.Q` is None and Q is never computed.
    - `need_P`: also return the minimum-norm multiplier $P^n$ of each step.
    - `fresh_jacobian`: form a fresh Jacobian at every solve (True) or carry the inverse
      Jacobian from step to step (False); None (default) chooses fresh for the Cayley map,
      whose residual is in closed form, carried otherwise.

    `prepare` finds the matrix-group structure (`find_reduction`) or says why it does not
    apply.
    """

    reconstruct: bool = True
    need_P: bool = False
    fresh_jacobian: bool | None = None
    reduction: MatrixGroupReduction | MatrixAlgebraReduction | None = None

    form = "reduced"

    def __post_init__(self):
        super().__post_init__()
        if type(self.root_finder) not in (Newton, FixedNewton, FixedPoint):
            raise TypeError(
                f"root_finder: the reduced step solves dim V equations with clebsch_jax.Newton() (or "
                f"its fixed-update form, clebsch_jax.roots.solvers.FixedNewton), or by sweeps with "
                f"clebsch_jax.FixedPoint() for a system with an inverse_legendre map, got "
                f"{self.root_finder!r}."
            )

    def prepare(self, system, Q0, xi0) -> "ReducedStep":
        if self.principle == Principle.MIDPOINT:
            raise ValueError(
                "reduce: the reduced march does not apply to this system: the reduced march "
                "implements the left and right principles only."
            )
        if self._sweeps and system.inverse_legendre is None:
            raise ValueError(
                "root_finder: FixedPoint() sweeps of the reduced step are preconditioned with the "
                "system's inverse Legendre map; build the system with ClebschSystem(..., "
                "inverse_legendre=...) or use clebsch_jax.Newton()."
            )
        red, reason = find_reduction(system, Q0, xi0)
        if red is None:
            raise ValueError(f"reduce: the reduced march does not apply to this system: {reason}.")
        return dataclasses.replace(self, reduction=red)

    @property
    def _sweeps(self) -> bool:
        return isinstance(self.root_finder, FixedPoint)

    def _carry_Q(self, system) -> bool:
        return bool(self.reconstruct or system.has_potential or self.need_P)

    def _fresh(self, system) -> bool:
        if self.fresh_jacobian is None:
            return isinstance(system.derivative_map, CayleyDifference)
        return bool(self.fresh_jacobian)

    def init(self, system, Q0, xi0, P0, dt):
        if P0 is not None:
            mu0 = momentum_map(system, P0, Q0, xi0)
            xi0 = seed_velocity(system, self.root_finder, Q0, P0, xi0)
        else:
            mu0 = jax.grad(lambda x: system.l(x, Q0))(xi0)
        # Without a potential the reduced Lagrangian is left-invariant: evaluate at the identity.
        Qc0 = Q0 if self._carry_Q(system) else jnp.eye(Q0.shape[0], dtype=Q0.dtype)
        return (mu0, Qc0, xi0), 0

    def init_memory(self, system, state):
        _, _, xi = state
        history = empty_history(xi.shape, xi.dtype)
        # sweeps carry no matrix (a placeholder scalar): dim V may be in the thousands
        H = jnp.zeros((), xi.dtype) if self._sweeps else jnp.eye(xi.size, dtype=xi.dtype)
        return history, H, degree(0, history)

    def step(self, system, state, memory, h, n, alive):
        return self.step_sharing(system, state, memory, h, n, alive)[:4]

    def step_sharing(self, system, state, memory, h, n, alive, shared=None):
        """`step`, and the inverse Jacobian its solve ended with (for the next solve of the same
        step: `SymmetricPair`'s second half step). With `shared`, such a matrix from the step's
        previous solve, the solve starts with chord updates on it instead of this slot's own
        (a fresh one only when they stop contracting, as for a carried matrix); the slot's
        memory is handed on as `step` would. **Returns:** `step`'s four values and the matrix."""
        mu, Q, xi_last = state
        history, H, deg = memory
        red, principle = self.reduction, self.principle
        carry_Q = self._carry_Q(system)

        def residual(x):
            return reduced_step(system, red, principle, h, mu, Q, x, outgoing=False)[0]

        def finish(x):  # the residual at the solution and the outgoing μⁿ⁺¹, Qⁿ⁺¹, sharing work
            r, mu1, Q1 = reduced_step(system, red, principle, h, mu, Q, x, need_Q1=carry_Q)
            return r, (mu1, Q1)

        # A fresh Jacobian at the guess, or the inverse Jacobian of this slot's last solve
        # (refreshed when it stops contracting, formed at step 0); a member that has failed
        # iterates on NaNs without forming any.
        guess = xi_last + predict(n, jnp.zeros_like(xi_last), history, deg)
        if self._sweeps:
            reuse = False
            xi, g, stats = self._sweep(system, red, principle, h, mu, Q, guess)
            _, mu1, Q1 = reduced_step(system, red, principle, h, mu, Q, xi, need_Q1=carry_Q, gradient=g)
        else:
            reuse = False if self._fresh(system) else (n > 0) | ~alive
            start, use = (H, reuse) if shared is None else (shared, True)
            xi, stats, H_new, (mu1, Q1) = self.root_finder.solve_reusing(
                residual, guess, start, use, finish=finish, step=n
            )
        # a fresh Jacobian every solve: the carried matrix is never read, so it is handed on
        # unchanged (a loop-invariant placeholder rather than a new value per step)
        H_out = H_new if not self._sweeps else H
        H = H if reuse is False else H_new
        history = push(history, xi - xi_last)
        # the next step's choice of differences, carried (`degree`)
        memory = (history, H, degree(n + 1, history))
        return (mu1, Q1 if carry_Q else Q, xi), memory, (xi, Q1), stats, H_out

    def _sweep(self, system, red, principle, h, mu, Q, guess):
        r"""The step's root by sweeps (`FixedPoint`'s stopping rule and statuses), made on the
        momentum $g = \nabla l(\xi)$ rather than on ξ: $g \leftarrow g + r(G(g))$, then
        $\xi = G(g)$. The same iterates as $\xi \leftarrow G(\nabla l(\xi) + r(\xi))$, but the
        sizes the stopping rule judges are those of the momentum, whose round-off is that of
        the residual's terms; G (a solve with $\nabla^2 l$, e.g. an inverse Laplacian) would
        amplify it unevenly across the components of ξ. Without a potential, the residual at
        $\xi = G(g)$ takes g itself as $\nabla l(\xi)$ (equal up to the round-off of G and
        ∇l): a sweep applies G once and not ∇l, and the outgoing momentum is formed from the
        same g. **Returns:** `(xi, g, stats)`."""
        G = system.inverse_legendre
        given = not system.has_potential

        def sweep(g):
            xi = G(g, Q)
            r, _, _ = reduced_step(system, red, principle, h, mu, Q, xi, outgoing=False, gradient=g if given else None)
            return g + r

        g0 = jax.grad(lambda y: system.l(y, Q))(guess)
        g, stats = self.root_finder.solve(sweep, g0)
        return G(g, Q), (g if given else None), stats

    def nodes(self, system, state0, states, outs) -> Nodes:
        mu0, Qc0, xi0 = state0
        (mus, Qs_after, _), (xis, Q_first) = states, outs
        n_steps = xis.shape[0]
        mus = jnp.concatenate([mu0[None], mus])
        if self._carry_Q(system):
            Qs = nodal_Q = jnp.concatenate([Qc0[None], Qs_after])
        else:
            Qs, nodal_Q = None, jnp.broadcast_to(Qc0, (n_steps + 1,) + Qc0.shape)
        Ps = None
        if self.need_P:  # the multiplier of each step's first sub-step, at that sub-step's anchor
            anchors = Qs[:-1] if self.principle == Principle.LEFT else Q_first
            Ps = jax.vmap(lambda q, x: initial_multiplier(system, q, x))(anchors, xis)
        return Nodes(Q=Qs, p=None, P=Ps, momentum=mus, xi_step=xis, nodal_Q=nodal_Q, xi_seed=xi0)
