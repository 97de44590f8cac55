r"""The fast path of `sweep`: each step solved by a fixed number of Newton updates, every member
checked, and the general loop where the check fails.

A sweep's members are many similar trajectories marched side by side. The general Newton loop
(`clebsch_jax.roots.newton.newton_loop`) is a `while_loop` whose trip count depends on the
data: batched, it tests "is any member still running" after every update and pays for the
slowest member. With a good predictor every member of a well-resolved march is at round-off
after the same small number K of updates, so the sweep first runs a chunk of steps with
`FixedNewton` (K chord updates as straight-line code, then one check per member and step), and
reruns the chunk from the same start with the general loop for the members whose check failed
(gathered from the batch: the few hard members of a batch cost the general path's time for
themselves only; `clebsch_jax.batching.schedule.FALLBACK_BATCH`). A rerun chunk is the general
path's chunk, so statuses and failures (step and member) are the general path's; the fast chunk
that is kept has every member and step solved to round-off, as the general loop solves it: the
two agree to round-off (`tests/test_fast_path.py`).

The fast method is derived from the method `integrate` would choose (`fast_method`): each
`ReducedStep` with a `Newton` root finder gets a `FixedNewton` with the same stopping rule;
nothing depends on the model.
"""

from __future__ import annotations

import dataclasses

from ..roots.solvers import FixedNewton, Newton
from ..steppers.base import AbstractWrapper
from ..steppers.choose import choose_method
from ..steppers.reduced import ReducedStep

__all__ = ["fast_method", "FAST_UPDATES"]

FAST_UPDATES = FixedNewton.updates
"""Chord updates per solve on the fast path (K)."""


def _with_fixed_updates(stepper, updates: int):
    """`stepper` with every reduced step's Newton made a `FixedNewton`; None if it has none."""
    if isinstance(stepper, AbstractWrapper):
        base = _with_fixed_updates(stepper.base, updates)
        return None if base is None else dataclasses.replace(stepper, base=base)
    if isinstance(stepper, ReducedStep) and type(stepper.root_finder) is Newton:
        r = stepper.root_finder
        finder = FixedNewton(rtol=r.rtol, atol=r.atol, max_iterations=r.max_iterations, updates=updates)
        return dataclasses.replace(stepper, root_finder=finder)
    return None


def fast_method(system, Q0, xi0, options: dict, updates: int = FAST_UPDATES):
    """The fast path's method for `integrate(system, Q0, xi0, **options)` (one member's
    concrete arrays), or None where it has none: the method those options choose (or
    `options["method"]`), its reduced steps solved by `updates` fixed updates. Only the
    reduced march has one for now (its steps solve dim V unknowns from a closed-form residual)."""
    method = options.get("method")
    if method is None:  # the options that choose the method (not those of the march: check_energy)
        method = choose_method(system, Q0, xi0, **{k: v for k, v in options.items() if k != "check_energy"})
    return _with_fixed_updates(method, updates)
