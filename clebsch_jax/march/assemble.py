"""The `Solution` from the records of a march's chunks (`assemble`): the chunks joined, the energy
check and the first-step check applied to them (a failed step's later records made NaN and its
later steps `Status.SKIPPED`), the overall result and first failure found — the same code on
NumPy arrays (concrete runs) and traced ones."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..core.isotropy import isotropy_dimension
from ..roots.status import NewtonStats, Status, skip_stats
from .carry import Chunk, failed_to_nan
from .energy_check import ENERGY_STEP_RTOL, energy_jump
from .first_step import FirstStepProbe, first_step_failed
from .solution import Solution

__all__ = ["assemble"]


def _join(xp, chunks, n_steps: int, node: bool):
    """The chunks' records of a field joined: N step entries, or N + 1 node entries."""
    if len(chunks) == 1 and (not node or chunks[0].shape[0] == n_steps + 1):
        return chunks[0][: n_steps + node]  # one chunk of exactly its records (native): no copy
    first = [c[:-1] if node else c for c in chunks]
    joined = xp.concatenate(first)[:n_steps] if len(first) > 1 else first[0][:n_steps]
    return xp.concatenate([joined, chunks[-1][-1:]]) if node else joined


def _fail_from(xp, step, code, stats, nodal, valid, fields):
    """The records with step `step` failed (`code`): later steps SKIPPED, the nodes after it
    invalid, with NaN values (and NaN derivatives: `failed_to_nan`); `fields` are (array,
    node?) pairs. `step` may be len(steps): nothing fails."""
    n_steps = stats.status.shape[0]
    steps, nodes = xp.arange(n_steps), xp.arange(n_steps + 1)
    stats = stats._replace(status=xp.where(steps == step, code, stats.status).astype(stats.status.dtype))
    stats = skip_stats(stats, steps <= step) if xp is jnp else _np_skip(stats, steps <= step)
    keep_node = nodes <= step
    nodal = skip_stats(nodal, keep_node) if xp is jnp else _np_skip(nodal, keep_node)
    valid = valid & keep_node

    def mask(a, keep):
        if a is None:
            return None
        keep = keep.reshape(keep.shape + (1,) * (a.ndim - 1))
        return np.where(keep, a, np.nan) if xp is np else failed_to_nan(a, keep)

    out = [mask(a, keep_node if node else steps < step) for a, node in fields]
    return stats, nodal, valid, out


def _np_skip(stats: NewtonStats, attempted) -> NewtonStats:
    """`skip_stats` on NumPy arrays."""
    return NewtonStats(
        iterations=np.where(attempted, stats.iterations, 0).astype(stats.iterations.dtype),
        residual_norm=np.where(attempted, stats.residual_norm, np.nan),
        status=np.where(attempted, stats.status, Status.SKIPPED).astype(np.int32),
        jacobians=np.where(attempted, stats.jacobians, 0).astype(stats.jacobians.dtype),
    )


def assemble(
    xp,
    stepper,
    system,
    chunks: list[Chunk],
    n_steps: int,
    startup,
    dt,
    t0,
    Q0,
    xi0,
    input_ok=None,
    probe: FirstStepProbe | None = None,
    energy_rtol: float | None = None,
    off_manifold=None,
) -> Solution:
    """The `Solution` from the chunks' records (`xp`: `numpy` or `jax.numpy`, as they are).
    `input_ok` (traced runs with `check_inputs`): False makes step 0 `Status.INVALID_INPUT`.
    `probe` (runs with the energy check): step 0, unless the energy check failed it, checked
    against two half steps (`first_step_failed`). `off_manifold` (traced runs whose first step
    could leave the manifold: `clebsch_jax.core.manifold_checks.traced_first_step_check`): True
    makes a step 0 that no other check failed `Status.OFF_MANIFOLD`. `energy_rtol`: the energy
    check's tolerance, for chunks that recorded their energies (default `ENERGY_STEP_RTOL`)."""

    def join(get, node):
        fields = [get(c) for c in chunks]
        if fields[0] is None:
            return None
        return jax.tree_util.tree_map(lambda *a: _join(xp, list(a), n_steps, node), *fields)

    nodes = join(lambda c: c.nodes._replace(P=None, xi_step=None, xi_seed=None), True)
    stats = join(lambda c: c.stats, False)
    stats = stats._replace(
        iterations=stats.iterations + xp.where(xp.arange(n_steps) == 0, startup, 0).astype(stats.iterations.dtype)
    )  # start-up work belongs to step 0
    P, xi_step = join(lambda c: c.nodes.P, False), join(lambda c: c.nodes.xi_step, False)
    xin, nodal, valid = join(lambda c: c.xi, True), join(lambda c: c.nodal_stats, True), join(lambda c: c.valid, True)
    if input_ok is not None:  # an invalid member made no step: its step 0 says why
        stats = stats._replace(
            status=xp.where((xp.arange(n_steps) == 0) & ~input_ok, Status.INVALID_INPUT, stats.status).astype(
                stats.status.dtype
            )
        )
    fields_of = lambda: [
        (nodes.Q, True),
        (nodes.p, True),
        (nodes.momentum, True),
        (xin, True),
        (xi_step, False),
        (P, False),
    ]
    energy = join(lambda c: c.energy, True)
    rtol = ENERGY_STEP_RTOL if energy_rtol is None else energy_rtol
    jumped, step = energy_jump(xp, *energy, stats.status, rtol=rtol)[:2] if energy is not None else (False, None)
    first = off = False
    # after the energy check, which every path makes: a step 0 it fails keeps its status
    kept = ~(jumped & (step == 0)) if energy is not None else True
    if probe is not None:
        first = first_step_failed(xp, probe, nodes.nodal_Q[:2], nodes.momentum[:2], stats.status[0]) & kept
    if off_manifold is not None:
        off = off_manifold & (stats.status[0] == Status.SUCCESS) & kept & ~first
    # one pass for the checks: a first step failed by its check fails the run from step 0, which
    # covers a later jump (the energy check's nodes up to step 0 are the ones the check reads)
    checked = energy is not None or probe is not None or off_manifold is not None
    if checked and (xp is jnp or bool(jumped) or bool(first)):
        fail = xp.where(first | off, 0, xp.where(jumped, step, n_steps) if energy is not None else n_steps)
        code = xp.where(first, Status.FIRST_STEP, xp.where(off, Status.OFF_MANIFOLD, Status.ENERGY_JUMP))
        stats, nodal, valid, out = _fail_from(xp, fail, code, stats, nodal, valid, fields_of())
        Qn, pn, mun, xin, xi_step, P = out
        nodes = nodes._replace(Q=Qn, p=pn, momentum=mun)
    facts = stepper.facts(system)
    failed = stats.status != Status.SUCCESS
    any_step, first_step = xp.any(failed), xp.argmax(failed)
    nodal_failed = valid & (nodal.status != Status.SUCCESS)
    any_nodal, first_node = xp.any(nodal_failed), xp.argmax(nodal_failed)
    result = xp.where(any_step, stats.status[first_step], xp.where(any_nodal, Status.LEGENDRE, Status.SUCCESS)).astype(
        xp.int32
    )
    failed_step = xp.where(any_step, first_step, xp.where(any_nodal, first_node, -1)).astype(xp.int32)
    # Gauss–Legendre takes Q̇ from its collocation polynomial, not from the derivative map
    derivative_map = (
        "none (collocation)"
        if facts.scheme == "gauss"
        else getattr(system.derivative_map, "name", repr(system.derivative_map))
    )
    return Solution(
        ts=t0 + dt * xp.arange(n_steps + 1, dtype=dt.dtype),
        Q=nodes.Q,
        p=nodes.p,
        xi=xin,
        xi_step=xi_step,
        P=P,
        momentum=nodes.momentum,
        stats=stats,
        nodal_stats=nodal,
        result=result,
        failed_step=failed_step,
        valid=valid,
        scheme=facts.scheme,
        form=facts.form,
        order=facts.order,
        method=facts.name,
        derivative_map=derivative_map,
        q_ndim=Q0.ndim,
        xi_ndim=xi0.ndim,
        solves_per_step=facts.solves_per_step,
        isotropy=isotropy_dimension(system),
    )
