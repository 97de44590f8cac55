"""The one place where `integrate`'s options become a stepper: which method runs for which
system when the caller does not pass `method=`.

The rules, in order:

0. **The default** (no `scheme`, `order` or `composition`) is symmetric and of order 2 for
   every system (`default_method`): the left principle where it is symmetric already (a
   symmetric derivative map and no potential: the rigid body's CAY march); else, when the
   reduced march applies, the reduced left step composed with its adjoint over half steps
   (`SymmetricPair`: the heavy top keeps its ξ-only unknowns); else the midpoint principle
   (also for degenerate systems). First-order principles run only when asked for by name.
1. `scheme` (default: "midpoint" for a degenerate system, else "left") picks the principle, or
   "gauss" the Gauss–Legendre method of `order` (default 2), solved by fixed-point sweeps.
2. `jacobian` picks the root finder: "dense" `Newton`, "blocks" `BlockNewton` (N particles).
   The reduced march of a system that gives its inverse Legendre map
   (`ClebschSystem(inverse_legendre=...)`) with more than `DENSE_NEWTON_MAX` unknowns solves
   by matrix-free sweeps preconditioned with it (`FixedPoint`) instead: a dense Jacobian of
   dim V = n² unknowns (the Euler–Zeitlin fluid) costs n⁶. Those sweeps are tested after
   each one (`MATRIX_FREE_SWEEPS`).
3. The reduced march (`ReducedStep`) runs when `reduce=True`, or with `reduce="auto"` when the
   caller does not need the multipliers and the velocity map is right multiplication on a
   matrix group with a Definition 25 derivative map (`find_reduction`); else `FullStep`.
4. `order` None runs the principle as it is; 2 makes it symmetric (`SymmetricPair` unless it
   is symmetric already); 4, 6, 8 compose that symmetric step (`Composed`, coefficients
   `composition` or `DEFAULT_COMPOSITIONS[order]`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..discrete.collocation import GAUSS_ORDERS
from ..discrete.matrix_group import find_reduction
from ..roots.solvers import BlockNewton, FixedPoint, Newton
from .base import Principle
from .composition import COMPOSITIONS, DEFAULT_COMPOSITIONS, Composed, Composition, SymmetricPair
from .full import FullStep
from .gauss import SWEEPS_PER_NEWTON_ITERATION, UNTESTED_SWEEPS, GaussLegendre
from .principles import check_principle, principle_facts
from .reduced import ReducedStep

__all__ = [
    "DENSE_NEWTON_MAX",
    "MATRIX_FREE_SWEEPS",
    "default_scheme",
    "default_method",
    "choose_method",
    "check_scheme",
    "COMPOSITION_ORDERS",
]

DENSE_NEWTON_MAX = 64
"""Above this many unknowns per step, the reduced march of a system with an inverse Legendre map
solves by sweeps (rule 2): forming and factorising a dense Jacobian costs more than the sweeps."""

MATRIX_FREE_SWEEPS = {"untested": 0, "per_test": 1}
"""The `FixedPoint` options of rule 2's matrix-free sweeps: a convergence test after every
sweep, from the first. Such a sweep costs matrix products over its unknowns (O(n³) for n²
unknowns) where a test is one reduction over them (O(n²)), and the reduced step's guess (the
predictor's extrapolation of earlier steps) is good enough that a few sweeps reach round-off:
the defaults' untested sweeps and pairs of sweeps per test would only add sweeps."""

COMPOSITION_ORDERS = (2, 4, 6, 8)
"""The orders `integrate(..., order=k)` reaches by composing a principle."""


def default_scheme(system, scheme):
    """The scheme `integrate` runs when the caller gives none."""
    if scheme is None:
        return "midpoint" if system.degenerate else "left"
    return scheme


def check_scheme(system, scheme) -> str:
    """`scheme` (None: the default) checked against the system: "gauss" or a `Principle`'s name."""
    scheme = default_scheme(system, scheme)
    if isinstance(scheme, str) and scheme == "gauss":
        return "gauss"
    return check_principle(system, scheme).value


def _composition(order, composition):
    """(order, Composition or None) from `integrate`'s `order` and `composition`."""
    if composition is not None:
        if isinstance(composition, str):
            if composition not in COMPOSITIONS:
                raise ValueError(
                    f"composition: unknown name {composition!r}; expected one of "
                    f"{sorted(COMPOSITIONS)} or a Composition."
                )
            composition = COMPOSITIONS[composition]
        if not isinstance(composition, Composition):
            raise ValueError(f"composition: expected a Composition or its name, got {composition!r}.")
        if order is not None and order != composition.order:
            raise ValueError(
                f"order: {order} disagrees with composition {composition.name!r} "
                f"of order {composition.order}; pass one of them."
            )
        order = composition.order
    if order is not None and order not in COMPOSITION_ORDERS:
        raise ValueError(f"order: expected None, 2, 4, 6 or 8, got {order!r}.")
    if order is not None and order > 2 and composition is None:
        composition = DEFAULT_COMPOSITIONS[order]
    return order, composition


def _gauss(system, order, composition, rtol, atol, max_newton_iterations, jacobian):
    if composition is not None:
        raise ValueError(
            "composition: scheme='gauss' reaches its order with stages, not by composition; "
            f"pass order={', '.join(map(str, GAUSS_ORDERS))} and no composition."
        )
    order = 2 if order is None else order
    if isinstance(order, bool) or order not in GAUSS_ORDERS:
        raise ValueError(
            f"order: scheme='gauss' expects None or an even order from 2 to {GAUSS_ORDERS[-1]}, got {order!r}."
        )
    if jacobian != "dense" and not system.degenerate:
        raise ValueError(
            "jacobian: scheme='gauss' solves the steps of a regular Lagrangian by fixed-point "
            "sweeps, without a Newton matrix; 'blocks' lumps the constraint matrix of a degenerate "
            f"one. Leave jacobian at 'dense', got {jacobian!r}."
        )
    sweeps = FixedPoint(
        rtol=rtol,
        atol=atol,
        max_iterations=SWEEPS_PER_NEWTON_ITERATION * max_newton_iterations,
        untested=UNTESTED_SWEEPS,
    )
    return GaussLegendre(
        order=order,
        root_finder=sweeps,
        nodal_solver=Newton(rtol=rtol, atol=atol, max_iterations=max_newton_iterations),
        constraint_blocks=jacobian == "blocks",
    )


def symmetric_step(system, base, order, composition):
    """`base` raised to `order` (None: as it is): made symmetric of order 2 (`SymmetricPair`
    unless it is already), then composed."""
    if order is None:
        return base
    if not principle_facts(system, base.principle)[1]:
        base = SymmetricPair(base)
    return base if order == 2 else Composed(base, composition)


def _size(x) -> int:
    """The number of entries of an array, or of an array of shape `x` (a tuple)."""
    return int(np.prod(x)) if isinstance(x, tuple) else int(np.size(x))


def choose_method(
    system,
    Q0,
    xi0,
    *,
    scheme=None,
    reduce="auto",
    need_P=False,
    reconstruct=True,
    rtol=0.0,
    atol=0.0,
    max_newton_iterations=20,
    jacobian="dense",
    order=None,
    composition=None,
):
    """The stepper `integrate` runs for these options (the rules of the module docstring).
    `Q0` and `xi0` (arrays or shapes) serve the reduction test; None skips it (full step)."""
    scheme_given, scheme = scheme, check_scheme(system, scheme)
    if reduce not in ("auto", True, False):
        raise ValueError(f"reduce: expected 'auto', True or False, got {reduce!r}.")
    if jacobian not in ("dense", "blocks"):
        raise ValueError(f"jacobian: expected 'dense' or 'blocks', got {jacobian!r}.")
    if scheme == "gauss":
        if reduce is True:
            raise ValueError(
                "reduce: the reduced march implements the left and right principles only; "
                "scheme='gauss' marches (Q, P)."
            )
        return _gauss(system, order, composition, rtol, atol, max_newton_iterations, jacobian)
    by_default = scheme_given is None and order is None and composition is None
    order, composition = _composition(order, composition)
    newton = Newton(rtol=rtol, atol=atol, max_iterations=max_newton_iterations)
    finder = BlockNewton(rtol=rtol, atol=atol, max_iterations=max_newton_iterations) if jacobian == "blocks" else newton
    principle = Principle(scheme)
    base = FullStep(principle=principle, root_finder=finder)
    if Q0 is not None and (reduce is True or (reduce == "auto" and not need_P)):
        reduced_finder = newton
        if system.inverse_legendre is not None and _size(xi0) > DENSE_NEWTON_MAX and jacobian == "dense":
            reduced_finder = FixedPoint(
                rtol=rtol,
                atol=atol,
                max_iterations=SWEEPS_PER_NEWTON_ITERATION * max_newton_iterations,
                **MATRIX_FREE_SWEEPS,
            )
        reduced = ReducedStep(
            principle=principle, root_finder=reduced_finder, reconstruct=bool(reconstruct), need_P=bool(need_P)
        )
        if reduce is True:
            base = reduced.prepare(system, Q0, xi0)  # says why, when it does not apply
        elif principle != Principle.MIDPOINT and find_reduction(system, Q0, xi0)[0] is not None:
            base = reduced
    if by_default:
        return default_method(system, base)
    return symmetric_step(system, base, order, composition)


def default_method(system, base):
    """The default method (rule 0) from `base`, the left-principle step (full or reduced) that
    the options chose: `base` if it is symmetric already; the reduced step paired with its
    adjoint; else the full step of the midpoint principle (of the left one paired with its
    adjoint, for a derivative map without a midpoint)."""
    if principle_facts(system, base.principle)[1]:
        return base
    if isinstance(base, ReducedStep):
        return SymmetricPair(base)
    if callable(getattr(system.derivative_map, "at_midpoint", None)):
        return dataclasses.replace(base, principle=Principle.MIDPOINT)
    return SymmetricPair(base)
