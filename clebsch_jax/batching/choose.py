r"""The one place where a sweep's path is chosen, from the options and the first member's facts.

The backend (`native_config`: a native kernel where the per-member program translates, else
XLA), on XLA the fast path and its lean chunk (`fast_method_of`, `lean_applies`, `auto_lean`),
the defaults of degenerate particle systems (`particle_defaults`), the batch size
(`batch_size`), and, for a sweep resumed from a store, the path and batch size it was written
with (`resumed`). Every member shares the system's facts, so the choices are made on one.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from .. import diagnostics as _diagnostics
from ..core.jit import memo
from ..core.validation import positive_int
from ..roots.solvers import Newton
from ..steppers.base import AbstractWrapper
from ..steppers.choose import choose_method as _choose_method
from ..steppers.full import FullStep
from . import chunks_native, probe
from ..native import AUTO_MAX_IR_LINES
from .backends import native_unavailable as _native_unavailable
from .backends import warn_once as _warn_once
from .config import Config, Members, Run, first_row, system_of
from .fast import fast_method as _fast_method
from .lean import supports as _lean_supports
from .schedule import start_batch


DEFAULT_BATCH = 1024
"""Members per compiled call of the general chunk, at most (`batch_size`)."""

DEFAULT_BATCH_LEAN = 16_384
"""Members per compiled call of the lean chunk (`fast=True`): it records nothing, and its rows
of many members share XLA's per-operation cost (`benchmarks/throughput.py --sweep-only`)."""

AUTO_LEAN_MIN_MEMBERS = 1000
"""`fast="auto"` runs the lean chunk only for sweeps of at least this many members: on shorter
rows its steps gain too little over the general chunk's to repay its compile
(`benchmarks/README.md`, "Measurements behind the engine's choices")."""

AUTO_LEAN_MIN_MEMBER_STEPS = 1_000_000
"""... and of at least this many member-steps (members × `n_steps`): the lean chunk takes
longer to compile than the general one, which its faster steps repay from here on (the largest
break-even of the first calls measured in `benchmarks/README.md`; every later call of the same
shapes is faster from the first step). A sweep with members that fail its check compiles the
general chunk too, for their reruns, which the first call of a sweep this short does not repay.
A stored sweep resumes on the path it was written with, whatever these thresholds are now
(`resumed`)."""


def auto_lean(B: int, n_steps: int) -> bool:
    """Whether `fast="auto"` tries the lean chunk for a sweep of B members and `n_steps` steps."""
    return B >= AUTO_LEAN_MIN_MEMBERS and B * n_steps >= AUTO_LEAN_MIN_MEMBER_STEPS


def resumed(fast, batch_size, store, overwrite: bool, backend: str = "xla"):
    """`(fast, batch_size, backend)`, except that with a `store` that holds a sweep (and no
    `overwrite`) "auto" is the path and the backend that sweep ran (a store written before the
    native backend ran XLA) and None the batch size it ran with, so that it resumes (the store
    refuses another path, backend or batch size) whatever the defaults are now."""
    if store is None or overwrite or (fast != "auto" and batch_size is not None and backend != "auto"):
        return fast, batch_size, backend
    from .store import stored_configuration

    stored = stored_configuration(store) or {}
    if stored and backend == "auto":
        backend = stored.get("backend", "xla")
    if fast == "auto" and "fast" in stored:
        fast = bool(stored["fast"])
    if batch_size is None and isinstance(stored.get("batch_size"), int):
        batch_size = stored["batch_size"]
    return fast, batch_size, backend


_PARTICLE_MEMBER_CHUNK = 16
"""`member_chunk` of a sweep of degenerate particle systems (`particle_defaults`): small
chunks of block Newton loops, each running until its slowest member stops
(`benchmarks/throughput.py` measures clusters of point vortices)."""


def particle_defaults(cfg: Config, members: Members) -> Config:
    """`cfg` with the block Newton matrix (`jacobian="blocks"`) and `_PARTICLE_MEMBER_CHUNK` when
    the user chose neither the Jacobian nor the method and the first member (all share the
    system's facts and shapes) is a degenerate system of N >= 2 particles marched by a full
    step with a dense Newton matrix."""
    options = dict(cfg.options)
    if "jacobian" in options or "method" in options:
        return cfg
    j = members.ic_index[0]
    Q0, xi0 = np.shape(members.Q0[j]), np.shape(members.xi0[j])
    if len(Q0) < 2 or len(xi0) < 2 or Q0[0] != xi0[0] or Q0[0] < 2:
        return cfg
    system = system_of(cfg, first_row(members), members.shared)
    if not getattr(system, "degenerate", False):
        return cfg
    try:
        method = _choose_method(
            system,
            jnp.asarray(members.Q0[j]),
            jnp.asarray(members.xi0[j]),
            **{k: v for k, v in options.items() if k != "check_energy"},
        )
    except (TypeError, ValueError):  # the probe reports bad options with the member named
        return cfg
    while isinstance(method, AbstractWrapper):
        method = method.base
    if not (isinstance(method, FullStep) and type(method.root_finder) is Newton):
        return cfg
    return dataclasses.replace(
        cfg,
        options=tuple(sorted({**options, "jacobian": "blocks"}.items())),
        member_chunk=cfg.member_chunk or _PARTICLE_MEMBER_CHUNK,
    )


def fast_method_of(cfg: Config, members: Members):
    """The fast path's method for this sweep (`clebsch_jax.batching.fast`), chosen on the first
    member as `integrate` chooses (the choice depends on the system's facts and the options,
    the same for every member), or None."""
    j = members.ic_index[0]
    return _fast_method(
        system_of(cfg, first_row(members), members.shared),
        jnp.asarray(members.Q0[j]),
        jnp.asarray(members.xi0[j]),
        dict(cfg.options),
    )


def lean_applies(cfg: Config, members: Members, method) -> bool:
    """Whether the fast path can run the lean chunk: a method it supports, no node saved, no
    invariant but the energy (the others are functions of a chunk's `Solution`), the energy
    check on with its default tolerance (the lean chunk always makes it)."""
    if method is None or cfg.save_every is not None or cfg.check_energy is not True:
        return False
    if [name for name, _ in cfg.invariants] != ["energy"] or cfg.invariants[0][1] is not _diagnostics.energy:
        return False
    return _lean_supports(method, system_of(cfg, first_row(members), members.shared))


def _native_why(cfg: Config, run: Run) -> str | None:
    """Why the per-member program cannot run this sweep natively (None: it can)."""
    why = _native_unavailable(run.devices)
    if why is not None:
        return why
    if run.save_every is not None:
        return "the sweep saves nodes (save_every), which the per-member program does not record"
    if [name for name, _ in cfg.invariants] != ["energy"] or cfg.invariants[0][1] is not _diagnostics.energy:
        return "the sweep has invariants besides the energy (functions of a chunk's Solution)"
    return None


def native_config(cfg: Config, run: Run, members: Members, backend: str):
    """`(cfg, shapes)` for the native backend where it applies: the member checked as
    `integrate` checks it, and the program of a chunk compiled (from the disk cache when it is
    there). Where it does not apply: `backend="native"` is refused with the reason, "auto"
    says the reason once and keeps XLA (`(cfg, None)`)."""
    why = _native_why(cfg, run)
    shapes = None
    if why is None:
        from ..native import Unsupported

        limit = AUTO_MAX_IR_LINES if backend == "auto" else None
        native = dataclasses.replace(cfg, native=True, native_max_lines=limit)
        # integrate's checks of a member, no march traced; the per-member program's march state
        shapes = probe.member_shapes(native, members, lean=True)

        def compiled() -> bool:
            one = start_batch(native, members, shapes, 0, 1, None)
            chunks_native.native_program_of(native, one)
            return True

        try:
            # the program of this configuration and these member shapes (`_COMPILED`), compiled
            # or found once per process
            memo(_COMPILED, _member_key(native, members), compiled, 64)
            return native, shapes
        except Unsupported as err:
            why = f"the per-member program uses {err}, which the native translation does not cover"
    if backend == "native":
        raise ValueError(f"backend='native': {why}.")
    _warn_once(why)
    return cfg, shapes


_COMPILED: dict = {}


def _member_key(cfg: Config, members: Members) -> tuple:
    """What a sweep's native program depends on besides `cfg`: the first member's arrays'
    shapes and dtypes (`probe.trace_key`; every member's are the same), and whether P0 is given."""
    j = members.ic_index[0]
    args = (first_row(members), members.shared, members.Q0[j], members.xi0[j], members.dt[0])
    return (probe.trace_key(cfg, args), members.P0 is None)


def batch_size(given, B: int, run: Run, cfg: Config) -> int:
    """Members per batch: the caller's (clamped to B: more would only run padding), or by
    default one batch for every device and every thread of each — at most `DEFAULT_BATCH`
    members, or for the lean chunk and native kernels batches of equal size (no padded
    members) up to `DEFAULT_BATCH_LEAN`."""
    if given is None:
        per_slot = -(-B // (len(run.devices) * run.threads))
        if cfg.lean or cfg.native:
            given = -(-per_slot // -(-per_slot // DEFAULT_BATCH_LEAN))
        else:
            given = min(per_slot, DEFAULT_BATCH)
    return min(positive_int(given, "batch_size"), B)
