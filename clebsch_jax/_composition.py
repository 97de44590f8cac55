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
`Composition` holds the coefficient sets and their facts; `plan_steps` turns the user's
`scheme` and `order` into the static list of sub-steps the marches run.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ._collocation import GAUSS_ORDERS

__all__ = [
    "Composition", "StepPlan", "COMPOSITIONS", "DEFAULT_COMPOSITIONS", "plan_steps",
    "SUZUKI_4", "TRIPLE_JUMP_4", "YOSHIDA_6", "KAHAN_LI_6", "SUZUKI_UMENO_8", "KAHAN_LI_8",
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
    "Suzuki p4s5", 4, (_SUZUKI_A, _SUZUKI_A, 1.0 - 4.0 * _SUZUKI_A, _SUZUKI_A, _SUZUKI_A),
    "M. Suzuki, Phys. Lett. A 146 (1990) 319",
)
TRIPLE_JUMP_4 = Composition(
    "triple jump p4s3", 4, (_TRIPLE_A, 1.0 - 2.0 * _TRIPLE_A, _TRIPLE_A),
    "H. Yoshida, Phys. Lett. A 150 (1990) 262 (large error constant; for comparison)",
)
YOSHIDA_6 = Composition(
    "Yoshida p6s7", 6,
    _palindrome([0.78451361047755726381949763, 0.23557321335935813368479318, -1.17767998417887100694641568,
                 1.31518632068391121888424973]),
    "H. Yoshida, Phys. Lett. A 150 (1990) 262, solution A",
)
KAHAN_LI_6 = Composition(
    "Kahan-Li p6s9", 6,
    _palindrome([0.39216144400731413927925056, 0.33259913678935943859974864, -0.70624617255763935980996482,
                 0.08221359629355080023149045, 0.79854399093482996339895035]),
    "W. Kahan & R.-C. Li, Math. Comp. 66 (1997) 1089; Hairer-Lubich-Wanner (V.3.12)",
)
SUZUKI_UMENO_8 = Composition(
    "Suzuki-Umeno p8s15", 8,
    _palindrome([0.74167036435061295344822780, -0.40910082580003159399730010, 0.19075471029623837995387626,
                 -0.57386247111608226665638773, 0.29906418130365592384446354, 0.33462491824529818378495798,
                 0.31529309239676659663205666, -0.79688793935291635401978884]),
    "M. Suzuki & K. Umeno (1993); McLachlan, SIAM J. Sci. Comput. 16 (1995) 151",
)
KAHAN_LI_8 = Composition(
    "Kahan-Li p8s17", 8,
    _palindrome([0.13020248308889008087881763, 0.56116298177510838456196441, -0.38947496264484728640807860,
                 0.15884190655515560089621075, -0.39590389413323757733623154, 0.18453964097831570709183254,
                 0.25837438768632204729397911, 0.29501172360931029887096624, -0.60550853383003451169892108]),
    "W. Kahan & R.-C. Li, Math. Comp. 66 (1997) 1089; Hairer-Lubich-Wanner (V.3.14)",
)

COMPOSITIONS = {c.name: c for c in (SUZUKI_4, TRIPLE_JUMP_4, YOSHIDA_6, KAHAN_LI_6, SUZUKI_UMENO_8, KAHAN_LI_8)}
"""Every built-in coefficient set, by name."""

DEFAULT_COMPOSITIONS = {4: SUZUKI_4, 6: KAHAN_LI_6, 8: KAHAN_LI_8}
"""The set `integrate(..., order=k)` uses: small error constants among those of modest stage count."""


@dataclasses.dataclass(frozen=True)
class StepPlan:
    """The static recipe of one step of `integrate`.

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
        """Newton solves per step of `integrate` (stages × members of the base step)."""
        return len(self.gammas) * len(self.substeps)

    @property
    def schemes(self) -> tuple:
        return tuple(s for s, _ in self.substeps)


def plan_steps(scheme: str, base_order: int, base_symmetric: bool, order, composition) -> StepPlan:
    """The `StepPlan` for `integrate`'s `scheme`, `order` (None, 2, 4, 6, 8; Gauss: even orders
    up to 16) and `composition` (None, a `Composition` or the name of one in `COMPOSITIONS`).
    `base_order` and `base_symmetric` describe the principle `scheme` with the system's
    derivative map.

    `scheme="gauss"` is not composed: `order` (None: 2) picks the Gauss–Legendre tableau of
    order/2 stages (`clebsch_jax._collocation`), one solve per step."""
    if scheme == "gauss":
        if composition is not None:
            raise ValueError("composition: scheme='gauss' reaches its order with stages, not by composition; "
                             f"pass order={', '.join(map(str, GAUSS_ORDERS))} and no composition.")
        if order is None:
            order = 2
        if order not in GAUSS_ORDERS:
            raise ValueError(f"order: scheme='gauss' expects None or an even order from 2 to {GAUSS_ORDERS[-1]}, "
                             f"got {order!r}.")
        stages = order // 2
        return StepPlan((1.0,), (("gauss", 1.0),), order, True, True,
                        f"Gauss-Legendre {stages}-stage PRK")
    if composition is not None:
        if isinstance(composition, str):
            if composition not in COMPOSITIONS:
                raise ValueError(f"composition: unknown name {composition!r}; expected one of "
                                 f"{sorted(COMPOSITIONS)} or a Composition.")
            composition = COMPOSITIONS[composition]
        if not isinstance(composition, Composition):
            raise ValueError(f"composition: expected a Composition or its name, got {composition!r}.")
        if order is not None and order != composition.order:
            raise ValueError(f"order: {order} disagrees with composition {composition.name!r} "
                             f"of order {composition.order}; pass one of them.")
        order = composition.order
    if order is not None and order not in (2, 4, 6, 8):
        raise ValueError(f"order: expected None, 2, 4, 6 or 8, got {order!r}.")
    if order is None:  # the principle as it is
        return StepPlan((1.0,), ((scheme, 1.0),), base_order, base_symmetric, True, f"{scheme} principle")
    if base_symmetric:
        base, base_name = ((scheme, 1.0),), f"{scheme} principle"
    else:  # left or right (the midpoint principle is symmetric)
        base, base_name = (("left", 0.5), ("right", 0.5)), "right(h/2) o left(h/2)"
    if order == 2:
        return StepPlan((1.0,), base, 2, True, True, base_name)
    if composition is None:
        composition = DEFAULT_COMPOSITIONS[order]
    return StepPlan(tuple(composition.gammas), base, composition.order, True, True,
                    f"{composition.name} of {base_name}")


def check_coefficients(composition: Composition) -> float:
    """max over the necessary order conditions Σγ^(2j+1) = 0, 2j+1 < order, of |Σγ^(2j+1)|
    (a test of the stored digits; the full conditions are checked by measured orders)."""
    g = np.asarray(composition.gammas, dtype=float)
    return max([abs(np.sum(g ** k)) for k in range(3, composition.order, 2)] + [abs(g.sum() - 1.0)])

