r"""What a stepper is: a one-step method of the discrete Clebsch principle, with its facts as
data and pure functions for the march.

A stepper answers three questions for the march (`clebsch_jax.march`):

- **where to start**: `init(system, Q0, xi0, P0, dt) -> (state, startup_iterations)` and
  `init_memory(system, state) -> memory`. The state is what one step hands to the next (e.g.
  $(Q^n, p^n)$ and the last velocity); the memory is the root finder's own (the history its
  predictor extrapolates, a carried Newton matrix). A composition keeps one memory per
  sub-step, so that each sub-step extrapolates from its own past.
- **how to step**: `step(system, state, memory, h, n, alive) -> (state, memory, out, stats)`,
  pure: one step of size h (step number n; `alive` False once the member has failed, when
  the step only iterates on NaNs), its output for the record (the step velocity, the
  multiplier) and its `NewtonStats`.
- **what the nodes are**: `nodes(system, state0, states, outs) -> Nodes`, the trajectory
  (configurations, momenta, multipliers) from the stacked states and outputs.

Its facts — `facts(system) -> Facts`: form, order, symmetric, symplectic, name, solves per
step — are data that `Solution`, `step_plan` and the tests read. `prepare(system, Q0, xi0)`
checks that the method applies to the system (raising a `ValueError` that says why not) and
returns the stepper with whatever it found out about the system (e.g. the matrix-group
structure of a reduced march) bound to it; it runs before compiling.

Steppers are frozen dataclasses: hashable, so `jax.jit` treats them as static.
"""

from __future__ import annotations

import dataclasses
import enum
from typing import Any, ClassVar, NamedTuple

import jax

__all__ = ["AbstractStepper", "AbstractWrapper", "Facts", "Nodes", "Principle", "innermost"]


class Principle(str, enum.Enum):
    """Where a step of the discrete Clebsch action evaluates l and the velocity map.

    - `LEFT`: at $Q^n$ (Definition 19);
    - `RIGHT`: at $Q^{n+1}$, the adjoint principle (Remark 22);
    - `MIDPOINT`: at the midpoint of the step (the derivative map's `at_midpoint`): symmetric
      and second order also with a potential.

    A `Principle` is also the string of its name (`Principle.LEFT == "left"`)."""

    LEFT = "left"
    RIGHT = "right"
    MIDPOINT = "midpoint"

    def __str__(self) -> str:
        return self.value


class Facts(NamedTuple):
    """What a method is, for a given system: `form` ("full": the march carries $(Q, p)$;
    "reduced": the body momentum), `scheme` (its principle, "right o left" for a principle
    paired with its adjoint — the order `name` writes them in, without the step fractions — or
    "gauss"), `order`, `symmetric`, `symplectic`, `name` (what a step is made of) and
    `solves_per_step` (root-finder solves per step)."""

    form: str
    scheme: str
    order: int
    symmetric: bool
    symplectic: bool
    name: str
    solves_per_step: int


class Nodes(NamedTuple):
    """The trajectory a stepper's states describe, node by node (N steps, N + 1 nodes):
    `Q` (N+1, …) or None when not carried, `p` (N+1, …) or None, `P` (N, …) or None,
    `momentum` (N+1, …) the momentum map, `xi_step` (N, …) the step velocities, `nodal_Q`
    (N+1, …) the configurations the nodal velocities are solved at, and `xi_seed` the first
    velocity (seed of the nodal solves)."""

    Q: Any
    p: Any
    P: Any
    momentum: jax.Array
    xi_step: jax.Array
    nodal_Q: jax.Array
    xi_seed: jax.Array


@dataclasses.dataclass(frozen=True)
class AbstractStepper:
    """Base class of the steppers (see the module docstring for the protocol)."""

    quick_compile: ClassVar[bool] = True
    """Whether `integrate` compiles this stepper's march with `clebsch_jax.core.jit.QUICK_COMPILE`
    (a shorter compile at the same speed); False where the march measured slower with it."""

    def facts(self, system) -> Facts:
        raise NotImplementedError

    def prepare(self, system, Q0, xi0) -> "AbstractStepper":
        return self

    def init(self, system, Q0, xi0, P0, dt):
        raise NotImplementedError

    def init_memory(self, system, state):
        return None

    def step(self, system, state, memory, h, n, alive):
        raise NotImplementedError

    def nodes(self, system, state0, states, outs) -> Nodes:
        raise NotImplementedError

    @property
    def nodal_solver(self):
        """The root finder that recovers nodal velocities (Lemma 7) after the march."""
        return self.root_finder


@dataclasses.dataclass(frozen=True)
class AbstractWrapper(AbstractStepper):
    """A stepper around another (`base`): it starts, prepares and reads its nodes as `base`
    does, with `base`'s root finders; a subclass says how a step is made of `base`'s steps
    (`step`, `init_memory`, `facts`)."""

    base: AbstractStepper

    @property
    def root_finder(self):
        return self.base.root_finder

    @property
    def quick_compile(self) -> bool:
        return self.base.quick_compile

    @property
    def nodal_solver(self):
        return self.base.nodal_solver

    def prepare(self, system, Q0, xi0):
        return dataclasses.replace(self, base=self.base.prepare(system, Q0, xi0))

    def init(self, system, Q0, xi0, P0, dt):
        return self.base.init(system, Q0, xi0, P0, dt)

    def nodes(self, system, state0, states, outs) -> Nodes:
        return self.base.nodes(system, state0, states, outs)


def innermost(stepper):
    """The stepper inside any wrappers (`AbstractWrapper`): the one that makes the solves."""
    while isinstance(stepper, AbstractWrapper):
        stepper = stepper.base
    return stepper
