"""Facts and checks of the three principles (`Principle`) that both the full and the reduced
step share: which order and symmetry a principle has with a system's derivative map and
Lagrangian, and which systems it can run."""

from __future__ import annotations

import dataclasses
from typing import ClassVar

from ..roots.solvers import Newton
from .base import AbstractStepper, Facts, Principle

__all__ = ["PrincipleStep", "principle_facts", "check_principle", "check_particle_axis", "ADJOINT"]

ADJOINT = {Principle.LEFT: Principle.RIGHT, Principle.RIGHT: Principle.LEFT, Principle.MIDPOINT: Principle.MIDPOINT}
"""The adjoint of each principle (Remark 22): the method run backwards in time."""


def principle_facts(system, principle: Principle) -> tuple[int, bool]:
    """(order, symmetric) of the one-step principle: the midpoint principle is symmetric, of
    order 2; left/right are when the derivative map is symmetric (Example 30) and l has no
    potential (l(ξ, Qⁿ) at one end of the step is a first-order quadrature); else order 1."""
    if principle == Principle.MIDPOINT:
        return 2, True
    symmetric = bool(getattr(system.derivative_map, "symmetric", False)) and not system.has_potential
    return (2 if symmetric else 1), symmetric


def check_principle(system, principle) -> Principle:
    """`principle` as a `Principle`, refused (naming `scheme`) where it cannot run `system`."""
    try:
        principle = Principle(principle)
    except ValueError:
        raise ValueError(
            f"scheme: expected one of {tuple(p.value for p in Principle) + ('gauss',)}, got {principle!r}."
        ) from None
    if principle == Principle.MIDPOINT and not callable(getattr(system.derivative_map, "at_midpoint", None)):
        raise ValueError(
            "scheme: 'midpoint' needs a derivative map that knows the midpoint of a step "
            "(an `at_midpoint(Q_next, Q, dt)` method, as clebsch_jax.forward_difference, cayley and "
            f"exponential have); {system.derivative_map!r} has none."
        )
    if system.degenerate and principle != Principle.MIDPOINT:
        raise ValueError(
            f"scheme: {principle.value!r} is inconsistent for a degenerate Lagrangian (system built with "
            "degenerate=True): the left/right principles become two-step schemes with parasitic "
            "modes. Use scheme='midpoint' or 'gauss'."
        )
    return principle


def check_particle_axis(Q0, xi0, name: str = "jacobian"):
    """Block Newton matrices need a leading particle axis shared by Q0 and xi0."""
    if Q0.ndim < 1 or xi0.ndim < 1 or Q0.shape[0] != xi0.shape[0]:
        raise ValueError(
            f"{name}: 'blocks' needs a leading particle axis shared by Q0 and xi0, got Q0 of shape "
            f"{Q0.shape} and xi0 of shape {xi0.shape}."
        )


@dataclasses.dataclass(frozen=True)
class PrincipleStep(AbstractStepper):
    """What the full and the reduced step share: a `principle` (its string name is accepted
    too), a `Newton` root finder, the facts of the principle with the system, and the adjoint
    step (Remark 22)."""

    principle: Principle = Principle.LEFT
    root_finder: Newton = Newton()

    form: ClassVar[str]

    def __post_init__(self):
        try:
            object.__setattr__(self, "principle", Principle(self.principle))
        except ValueError:
            raise ValueError(
                f"principle: expected one of {[p.value for p in Principle]}, got {self.principle!r}."
            ) from None

    def facts(self, system) -> Facts:
        order, symmetric = principle_facts(system, self.principle)
        return Facts(self.form, self.principle.value, order, symmetric, True, f"{self.principle.value} principle", 1)

    def adjoint(self):
        """The same step with the adjoint principle (Remark 22)."""
        return dataclasses.replace(self, principle=ADJOINT[self.principle])
