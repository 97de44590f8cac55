r"""Higher order by composition: which one-step maps a step of `integrate` is made of.

A step of size $\Delta t$ is the composition $S_{\gamma_s\Delta t}\circ\dots\circ S_{\gamma_1\Delta t}$
of a **symmetric second-order** step $S_h$ (Hairer, Lubich & Wanner, *Geometric Numerical
Integration*, §V.3). $S_h$ is

- the principle itself when it is already symmetric: the midpoint principle, or the left/right
  principle with a symmetric derivative map (Cayley, exact exponential: Example 30) and no
  potential;
- otherwise the first-order left principle composed with its adjoint, the right principle
  (Remarks 21–22): $S_h = \Phi^{\rm right}_{h/2}\circ\Phi^{\rm left}_{h/2}$. Composing the
  first-order map with its adjoint, rather than composing it with itself, is what makes the
  composition symmetric (McLachlan 1995).

Each member of the composition is a discrete Clebsch step (a symplectic map of $(Q, p)$ that
conserves the momentum map of every symmetry of l), so compositions keep both properties.
`Composition` holds the coefficient sets and their facts; `SymmetricPair` and `Composed` are
the steppers that wrap a stepper; `StepPlan` describes what a step is made of.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ..roots.solvers import Newton
from ..roots.status import NewtonStats
from .base import AbstractStepper, AbstractWrapper, Facts
from .reduced import ReducedStep

__all__ = [
    "Composition",
    "StepPlan",
    "COMPOSITIONS",
    "DEFAULT_COMPOSITIONS",
    "SymmetricPair",
    "Composed",
    "plan_of",
    "SUZUKI_4",
    "TRIPLE_JUMP_4",
    "YOSHIDA_6",
    "KAHAN_LI_6",
    "SUZUKI_UMENO_8",
    "KAHAN_LI_8",
]


@dataclasses.dataclass(frozen=True)
class Composition:
    """Coefficients $\\gamma_1, \\dots, \\gamma_s$ (Σγ = 1, palindromic) of a symmetric composition
    of a symmetric second-order step, with its facts: `order`, `name`, `reference`."""

    name: str
    order: int
    gammas: tuple
    reference: str

    def __post_init__(self):
        g = np.asarray(self.gammas, dtype=float)
        if abs(g.sum() - 1.0) > 1e-14 or not np.allclose(g, g[::-1], rtol=0, atol=1e-15):
            raise ValueError(f"{self.name}: coefficients must sum to 1 and be palindromic.")

    @property
    def stages(self) -> int:
        return len(self.gammas)

    @property
    def symmetric(self) -> bool:
        return True  # palindromic coefficients of a symmetric step (checked above)


def _palindrome(half):
    half = tuple(float(x) for x in half)
    return half + half[-2::-1]


_SUZUKI_A = 1.0 / (4.0 - 4.0 ** (1.0 / 3.0))
_TRIPLE_A = 1.0 / (2.0 - 2.0 ** (1.0 / 3.0))

SUZUKI_4 = Composition(
    "Suzuki p4s5",
    4,
    (_SUZUKI_A, _SUZUKI_A, 1.0 - 4.0 * _SUZUKI_A, _SUZUKI_A, _SUZUKI_A),
    "M. Suzuki, Phys. Lett. A 146 (1990) 319",
)
TRIPLE_JUMP_4 = Composition(
    "triple jump p4s3",
    4,
    (_TRIPLE_A, 1.0 - 2.0 * _TRIPLE_A, _TRIPLE_A),
    "H. Yoshida, Phys. Lett. A 150 (1990) 262 (large error constant; for comparison)",
)
YOSHIDA_6 = Composition(
    "Yoshida p6s7",
    6,
    _palindrome(
        [
            0.78451361047755726381949763,
            0.23557321335935813368479318,
            -1.17767998417887100694641568,
            1.31518632068391121888424973,
        ]
    ),
    "H. Yoshida, Phys. Lett. A 150 (1990) 262, solution A",
)
KAHAN_LI_6 = Composition(
    "Kahan-Li p6s9",
    6,
    _palindrome(
        [
            0.39216144400731413927925056,
            0.33259913678935943859974864,
            -0.70624617255763935980996482,
            0.08221359629355080023149045,
            0.79854399093482996339895035,
        ]
    ),
    "W. Kahan & R.-C. Li, Math. Comp. 66 (1997) 1089; Hairer-Lubich-Wanner (V.3.12)",
)
SUZUKI_UMENO_8 = Composition(
    "Suzuki-Umeno p8s15",
    8,
    _palindrome(
        [
            0.74167036435061295344822780,
            -0.40910082580003159399730010,
            0.19075471029623837995387626,
            -0.57386247111608226665638773,
            0.29906418130365592384446354,
            0.33462491824529818378495798,
            0.31529309239676659663205666,
            -0.79688793935291635401978884,
        ]
    ),
    "M. Suzuki & K. Umeno (1993); McLachlan, SIAM J. Sci. Comput. 16 (1995) 151",
)
KAHAN_LI_8 = Composition(
    "Kahan-Li p8s17",
    8,
    _palindrome(
        [
            0.13020248308889008087881763,
            0.56116298177510838456196441,
            -0.38947496264484728640807860,
            0.15884190655515560089621075,
            -0.39590389413323757733623154,
            0.18453964097831570709183254,
            0.25837438768632204729397911,
            0.29501172360931029887096624,
            -0.60550853383003451169892108,
        ]
    ),
    "W. Kahan & R.-C. Li, Math. Comp. 66 (1997) 1089; Hairer-Lubich-Wanner (V.3.14)",
)

COMPOSITIONS = {c.name: c for c in (SUZUKI_4, TRIPLE_JUMP_4, YOSHIDA_6, KAHAN_LI_6, SUZUKI_UMENO_8, KAHAN_LI_8)}
"""Every built-in coefficient set, by name."""

DEFAULT_COMPOSITIONS = {4: SUZUKI_4, 6: KAHAN_LI_6, 8: KAHAN_LI_8}
"""The set `integrate(..., order=k)` uses: small error constants among those of modest stage count."""


@dataclasses.dataclass(frozen=True)
class StepPlan:
    """What one step is made of (`clebsch_jax.step_plan`).

    - `gammas`: the composition coefficients (``(1.0,)`` without composition);
    - `substeps`: the members of the base step $S_h$, ``(scheme, fraction of h)`` each;
    - facts: `order`, `symmetric`, `symplectic`, `name`.
    """

    gammas: tuple
    substeps: tuple
    order: int
    symmetric: bool
    symplectic: bool
    name: str

    @property
    def solves_per_step(self) -> int:
        """Root-finder solves per step (stages × members of the base step)."""
        return len(self.gammas) * len(self.substeps)

    @property
    def schemes(self) -> tuple:
        return tuple(s for s, _ in self.substeps)


def _first(tree):
    return jax.tree_util.tree_map(lambda a: a[0], tree)


@dataclasses.dataclass(frozen=True)
class SymmetricPair(AbstractWrapper):
    r"""The symmetric second-order step $S_h = \Phi^*_{h/2}\circ\Phi_{h/2}$ of a stepper Φ and
    its adjoint $\Phi^*$ (`base.adjoint()`: the left principle's is the right principle,
    Remarks 21–22). Composing a first-order map with its adjoint, rather than with itself, is
    what makes the step symmetric (McLachlan 1995).

    **Arguments:**

    - `base`: a `FullStep` or `ReducedStep`.
    - `shared_jacobian`: the second half step's solve starts from the inverse Jacobian the
      first half step's solve ended with, by chord updates, and forms a fresh one only when
      they contract by less than `REUSE_MAX_CONTRACTION` per update (True), or each half step
      solves as `base` alone would (False: with the Cayley map, a fresh Jacobian at each half
      step's guess). The two half steps' Jacobians at one state differ by O(Δt), so with a
      good guess the chord updates reach round-off in about as many updates as Newton from a
      fresh Jacobian: one Jacobian per step instead of two. None (default) is True for a
      `ReducedStep` solved by `Newton()`, False otherwise; True needs such a base.

    Each half step keeps its own memory (predictor history, carried matrix); the step's
    statistics add up those of both solves, and its output is that of the first half step."""

    shared_jacobian: bool | None = None

    def __post_init__(self):
        if not callable(getattr(self.base, "adjoint", None)):
            raise TypeError(f"base: expected a stepper with an adjoint (FullStep, ReducedStep), got {self.base!r}.")
        if self.shared_jacobian and not _shares(self.base):
            raise TypeError(
                f"shared_jacobian: only a ReducedStep solved by clebsch_jax.Newton() hands its Jacobian "
                f"to its adjoint's half step, got {self.base!r}."
            )

    @property
    def _shared(self) -> bool:
        return _shares(self.base) if self.shared_jacobian is None else bool(self.shared_jacobian)

    @property
    def members(self) -> tuple:
        return self.base, self.base.adjoint()

    def facts(self, system) -> Facts:
        first, second = (m.facts(system) for m in self.members)
        return Facts(
            first.form,
            f"{second.scheme} o {first.scheme}",
            max(2, first.order),
            True,
            first.symplectic,
            f"{second.scheme}(h/2) o {first.scheme}(h/2)",
            first.solves_per_step + second.solves_per_step,
        )

    def init_memory(self, system, state):
        return tuple(m.init_memory(system, state) for m in self.members)

    def step(self, system, state, memory, h, n, alive):
        memories, stats, outs = [], [], []
        H = None
        for member, mem in zip(self.members, memory):
            if self._shared:
                state, mem, out, st, H = member.step_sharing(system, state, mem, 0.5 * h, n, alive, H)
            else:
                state, mem, out, st = member.step(system, state, mem, 0.5 * h, n, alive)
            memories.append(mem), stats.append(st), outs.append(out)
        return state, tuple(memories), outs[0], NewtonStats.combine(stats)


def _shares(base) -> bool:
    """Whether `base`'s half steps can share their Jacobian (`SymmetricPair.shared_jacobian`)."""
    return isinstance(base, ReducedStep) and type(base.root_finder) is Newton


@dataclasses.dataclass(frozen=True)
class Composed(AbstractWrapper):
    r"""A symmetric composition $S_{\gamma_s h}\circ\dots\circ S_{\gamma_1 h}$ of a symmetric
    second-order step S (Hairer, Lubich & Wanner, §V.3): order `composition.order`,
    symmetric, symplectic, and it conserves the momentum maps S conserves.

    **Arguments:**

    - `base`: a symmetric second-order stepper: `FullStep`/`ReducedStep` with a symmetric
      principle (midpoint; Cayley or exponential without potential), or a `SymmetricPair`.
    - `composition`: a `Composition` (e.g. `clebsch_jax.KAHAN_LI_8`) or the name of one in
      `clebsch_jax.COMPOSITIONS`.

    The stages run in a `jax.lax.scan`, each with its own memory, so that each stage
    extrapolates from the same stage of earlier steps (same h, smooth in n)."""

    composition: Composition

    def __post_init__(self):
        composition = self.composition
        if isinstance(composition, str):
            if composition not in COMPOSITIONS:
                raise ValueError(
                    f"composition: unknown name {composition!r}; expected one of "
                    f"{sorted(COMPOSITIONS)} or a Composition."
                )
            object.__setattr__(self, "composition", COMPOSITIONS[composition])
        elif not isinstance(composition, Composition):
            raise ValueError(f"composition: expected a Composition or its name, got {composition!r}.")
        if not isinstance(self.base, AbstractStepper) or getattr(self.base, "stages", None) is not None:
            raise ValueError(
                "base: compose a FullStep, ReducedStep or SymmetricPair; Gauss-Legendre reaches its "
                "order with stages, not by composition."
            )

    def facts(self, system) -> Facts:
        base = self.base.facts(system)
        return Facts(
            base.form,
            base.scheme,
            self.composition.order,
            True,
            base.symplectic,
            f"{self.composition.name} of {base.name}",
            len(self.composition.gammas) * base.solves_per_step,
        )

    def prepare(self, system, Q0, xi0) -> "Composed":
        prepared = super().prepare(system, Q0, xi0)
        facts = prepared.base.facts(system)
        if not (facts.symmetric and facts.order == 2):
            raise ValueError(
                f"method: a composition needs a symmetric second-order step, and {facts.name} is of "
                f"order {facts.order}{'' if facts.symmetric else ' and not symmetric'}; wrap it in "
                "SymmetricPair."
            )
        return prepared

    def init_memory(self, system, state):
        memory = self.base.init_memory(system, state)
        stages = len(self.composition.gammas)
        return jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (stages,) + a.shape), memory)

    def step(self, system, state, memory, h, n, alive):
        def stage(state, xs):
            gamma, mem = xs
            state, mem, out, stats = self.base.step(system, state, mem, gamma * h, n, alive)
            return state, (mem, out, stats)

        gammas = jnp.asarray(self.composition.gammas, dtype=h.dtype)
        state, (memory, outs, stats) = jax.lax.scan(stage, state, (gammas, memory))
        return state, memory, _first(outs), NewtonStats.combine(stats)


def plan_of(stepper, system) -> StepPlan:
    """The `StepPlan` of a stepper: its composition coefficients, the members of its base step
    and its facts."""
    facts = stepper.facts(system)
    gammas = (1.0,)
    if isinstance(stepper, Composed):
        gammas, stepper = tuple(stepper.composition.gammas), stepper.base
    if isinstance(stepper, SymmetricPair):
        substeps = tuple((m.facts(system).scheme, 0.5) for m in stepper.members)
    else:
        substeps = ((facts.scheme, 1.0),)
    return StepPlan(gammas, substeps, facts.order, facts.symmetric, facts.symplectic, facts.name)


def check_coefficients(composition: Composition) -> float:
    """max over the necessary order conditions Σγ^(2j+1) = 0, 2j+1 < order, of |Σγ^(2j+1)|
    (a test of the stored digits; the full conditions are checked by measured orders)."""
    g = np.asarray(composition.gammas, dtype=float)
    return max([abs(np.sum(g**k)) for k in range(3, composition.order, 2)] + [abs(g.sum() - 1.0)])
