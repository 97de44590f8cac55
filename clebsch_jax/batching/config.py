r"""A sweep's inputs checked and its static configuration: the first layer of `cj.sweep`.

The options that need no tracing (`check_run` → `Run`), the members — which parameter row,
initial condition and step each uses (`make_members` → `Members`) — and the static part of a
chunk, which `jax.jit` hashes (`chunk_config` → `Config`). Nothing here is traced or compiled;
every other module of the sweep reads these three.
"""

from __future__ import annotations

import dataclasses
import numbers
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import diagnostics as _diagnostics
from ..core.isotropy import gauge_weight as _gauge_weight
from ..core.isotropy import gauged as _gauged
from ..core.isotropy import physical_part as _physical_part
from ..core.system import ClebschSystem
from ..core.validation import check_memory as _check_memory
from ..core.validation import host_float_array as _float_array
from ..core.validation import is_array as _is_array
from ..core.validation import positive_int
from ..march.energy_check import energy_rtol
from ..march.integrate import integrate

_RESERVED = ("P0", "t0", "throw", "dt", "n_steps")
_DEFAULT_CHUNK = 100


def _leading(arr, name, what):
    if arr.ndim < 1:
        raise ValueError(
            f"{name}: expected a leading member axis ({what}), got a scalar. "
            f"For a single initial condition use {name}[None]."
        )
    return arr.shape[0]


def _devices(devices) -> list:
    """The devices batches are dealt to: [None] (JAX's default placement) when not sharding."""
    if devices is None or devices is False:
        return [None]
    if devices is True or (isinstance(devices, str) and devices == "all"):
        return list(jax.devices())
    if isinstance(devices, numbers.Integral) and not isinstance(devices, bool):
        if not 1 <= devices <= len(jax.devices()):
            raise ValueError(f"devices: asked for {devices} devices, {len(jax.devices())} are available.")
        return list(jax.devices()[:devices])
    try:
        devs = list(devices)
    except TypeError:
        raise ValueError(
            f"devices: expected None, True, 'all', an int or a list of devices, got {devices!r}."
        ) from None
    if not devs or not all(isinstance(d, jax.Device) for d in devs) or len(set(devs)) != len(devs):
        raise ValueError(f"devices: expected a non-empty list of distinct jax devices, got {devices!r}.")
    return devs


def member_slices(tree, idx):
    return jax.tree_util.tree_map(lambda a: a[idx], tree)


class Run(NamedTuple):
    """The checked options of a run."""

    n_steps: int
    chunk_steps: int
    save_every: int | None
    member_chunk: int | None
    invariants: dict  # {"energy": diagnostics.energy, **the caller's}
    progress: bool | Callable
    devices: list  # the devices batches are dealt to ([None]: JAX's default placement)
    threads: int = 1  # batches run side by side on each device, each from a host thread of its own
    chunk_default: bool = False  # chunk_steps not given: the default chose it (`whole_run_chunks`)

    @property
    def slots(self) -> list:
        """The device of each batch of a group: every device `threads` times."""
        return list(self.devices) * self.threads

    @property
    def chunks(self) -> list:
        """(first step, number of steps) of each chunk."""
        return [(st, min(self.chunk_steps, self.n_steps - st)) for st in range(0, self.n_steps, self.chunk_steps)]


def check_run(n_steps, grid, options, chunk_steps, save_every, member_chunk, invariants, progress, devices) -> Run:
    """The arguments that need no tracing, checked; the default chunk size chosen."""
    n_steps = positive_int(n_steps, "n_steps")
    if not isinstance(grid, bool):
        raise ValueError(f"grid: expected True or False, got {grid!r}.")
    for key in options:
        if key in _RESERVED:
            raise ValueError(
                f"{key}: set by sweep itself (it hands the state from chunk to chunk); "
                "pass P0 and dt to sweep, not as integrate options."
            )
    save_every = positive_int(save_every, "save_every", allow_none=True)
    member_chunk = positive_int(member_chunk, "member_chunk", allow_none=True)
    chunk_steps = positive_int(chunk_steps, "chunk_steps", allow_none=True)
    chunk_default = chunk_steps is None
    if chunk_steps is None:
        chunk_steps = _DEFAULT_CHUNK
        if save_every is not None:
            chunk_steps = max(save_every, chunk_steps - chunk_steps % save_every)
    elif save_every is not None and chunk_steps < n_steps and chunk_steps % save_every:
        # chunks start at saved nodes (one chunk needs no alignment)
        raise ValueError(f"chunk_steps: must be a multiple of save_every={save_every}, got {chunk_steps}.")
    if invariants is None:
        invariants = {}
    if not isinstance(invariants, dict) or not all(isinstance(k, str) and callable(f) for k, f in invariants.items()):
        raise ValueError("invariants: expected a dict {name: f(system, sol)} of callables.")
    if not (progress is True or progress is False or callable(progress)):
        raise ValueError(f"progress: expected True, False or a callable, got {progress!r}.")
    return Run(
        n_steps,
        min(chunk_steps, n_steps),
        save_every,
        member_chunk,
        {"energy": _diagnostics.energy, **invariants},
        progress,
        _devices(devices),
        chunk_default=chunk_default,
    )


def whole_run_chunks(run: Run) -> Run:
    """`run` as one chunk of `n_steps` where its chunk length is the default and nothing needs a
    chunk's end: for the native per-member program (`clebsch_jax.batching.chunks_native`),
    whose kernel takes the chunk's steps as an argument (one kernel for every length) and
    keeps nothing per step (a chunk's memory does not grow with its length), without
    `progress` (reported at each chunk's end) or `save_every`. Each chunk has its own start and
    end (node 0's velocity and energy, the multiplier, the march's state), so one chunk makes
    the fewest; the boundary's node energy is evaluated again from the handed-over state, which
    moves `drift` in its last bit where it is the maximum (`benchmarks/README.md`)."""
    if run.chunk_default and run.progress is False and run.save_every is None:
        return run._replace(chunk_steps=run.n_steps)
    return run


class Members(NamedTuple):
    """The B members: member m is the system of `params` row `param_index[m]` (or the shared
    system) started from initial condition `ic_index[m]` with step `dt[m]`."""

    builder: Callable | None  # make_system, when every member builds its system from its params
    shared_def: tuple | None  # a shared system's (treedef, static leaves) ...
    shared: list | None  # ... and its array leaves
    params: object  # a pytree of arrays with a leading axis of parameter rows; None when shared
    Q0: np.ndarray
    xi0: np.ndarray
    P0: np.ndarray | None
    n_ic: int
    param_index: np.ndarray
    ic_index: np.ndarray
    dt: np.ndarray  # (B,)

    @property
    def B(self) -> int:
        return len(self.dt)


def _systems(make_system, params):
    """(builder, shared_def, shared): a function of the parameters, or a system shared by all."""
    if isinstance(make_system, ClebschSystem):
        if params is not None:
            raise ValueError("params: must be None when make_system is a ClebschSystem (shared by all members).")
        return (None, *_split_system(make_system))
    if callable(make_system):
        if params is None:
            raise ValueError(
                "params: None, but make_system is a function of the parameters; pass a "
                "ClebschSystem as make_system to share one system."
            )
        return make_system, None, None
    raise TypeError(
        f"make_system: expected a function params -> ClebschSystem or a ClebschSystem, "
        f"got {type(make_system).__name__}."
    )


def _parameter_rows(params):
    """`params` as NumPy float arrays on the host (sliced batch by batch there: no JAX operation
    to compile) and its number of rows (every leaf's leading axis)."""
    if not jax.tree_util.tree_leaves(params):
        raise ValueError("params: has no array leaves.")
    params = jax.tree_util.tree_map(lambda a: _float_array(a, "params"), params)
    sizes = {np.shape(a)[0] if np.ndim(a) else None for a in jax.tree_util.tree_leaves(params)}
    if None in sizes or len(sizes) != 1:
        shapes = [np.shape(a) for a in jax.tree_util.tree_leaves(params)]
        raise ValueError(f"params: every leaf needs the same leading member axis, got shapes {shapes}.")
    return params, sizes.pop()


def make_members(make_system, params, Q0, xi0, P0, dt, grid) -> Members:
    """The members, their inputs checked, and which parameter row and initial condition each uses."""
    builder, shared_def, shared = _systems(make_system, params)
    Q0 = _float_array(Q0, "Q0")
    xi0 = _float_array(xi0, "xi0")
    n_ic = _leading(Q0, "Q0", "one configuration per initial condition")
    if _leading(xi0, "xi0", "one velocity per initial condition") != n_ic:
        raise ValueError(
            f"xi0: {xi0.shape[0]} initial velocities for {n_ic} configurations in Q0 "
            f"(shapes {xi0.shape} and {Q0.shape})."
        )
    if P0 is not None:
        P0 = _float_array(P0, "P0")
        if P0.shape != Q0.shape:
            raise ValueError(f"P0: expected Q0's shape {Q0.shape}, got {P0.shape}.")
    params, n_p = _parameter_rows(params) if builder is not None else (params, 1)
    if grid:
        if builder is None:
            raise ValueError("grid: True needs params (a grid of parameters × initial conditions).")
        B = n_p * n_ic
    else:
        if builder is not None and n_p != n_ic:
            raise ValueError(
                f"params: {n_p} parameter rows for {n_ic} initial conditions; pass as many, or "
                "grid=True for every parameter row with every initial condition."
            )
        B = n_ic
    if B == 0:
        raise ValueError(
            f"sweep: no members to run (Q0 and xi0 have {n_ic} initial conditions"
            + (f", params {n_p} rows" if builder is not None else "")
            + "): the sweep is empty."
        )
    members = np.arange(B)
    param_index = members // n_ic if grid else (members if builder is not None else np.zeros(B, int))
    ic_index = members % n_ic if grid else members
    dt = _float_array(dt, "dt")
    if dt.shape not in ((), (B,)):
        raise ValueError(f"dt: expected a scalar or one step per member, shape ({B},), got {dt.shape}.")
    if not np.all(np.isfinite(dt)) or not np.all(dt > 0):
        raise ValueError("dt: every step must be finite and positive.")
    dt = np.broadcast_to(dt, (B,)).astype(np.float64)
    return Members(builder, shared_def, shared, params, Q0, xi0, P0, n_ic, param_index, ic_index, dt)


CHUNK_BYTES = 200
"""Host memory per chunk of a run's schedule (`Run.chunks` and the calls that hold them: a
(first step, steps) pair and its places in two lists), for `check_size`."""


def check_size(run: Run, members: Members) -> None:
    """Refuse, before anything is traced or allocated, a sweep whose bookkeeping would not fit
    in memory (`clebsch_jax.core.validation.check_memory`, `integrate`'s guard): the schedule of
    ⌈n_steps / chunk_steps⌉ chunks (`CHUNK_BYTES` each), the nodes kept with `save_every` (t,
    Q, ξ and the momentum per member and node) and the table (the final state per member)."""
    n_chunks = -(-run.n_steps // run.chunk_steps)
    q, x = int(np.prod(members.Q0.shape[1:])), int(np.prod(members.xi0.shape[1:]))
    saved = 0 if run.save_every is None else members.B * (run.n_steps // run.save_every + 1) * 8 * (1 + q + 2 * x)
    table = members.B * 8 * (8 + 2 * q + 2 * x)
    what = f"{run.n_steps} steps in {n_chunks} chunks of {run.chunk_steps} (chunk_steps) for {members.B} members"
    _check_memory(
        "n_steps",
        what,
        n_chunks * CHUNK_BYTES + saved + table,
        "Give a larger chunk_steps (fewer chunks), save fewer nodes (a larger save_every, or none), or run "
        "fewer steps per sweep and start the next from this one's final state (Q0=res.final_Q, P0=res.final_p).",
        detail=(
            f" ({n_chunks * CHUNK_BYTES / 1e9:.3g} GB for the schedule of chunks, {saved / 1e9:.3g} GB for the "
            f"saved nodes, {table / 1e9:.3g} GB for the table)"
        ),
    )


class Carry(NamedTuple):
    """What a chunk hands the next, per member (batched): the canonical state (Q, P), the nodal
    velocity, the first failure and the running reductions."""

    Q: jax.Array
    P: jax.Array
    xi: jax.Array
    t: jax.Array
    status: jax.Array
    failed_step: jax.Array
    iterations: jax.Array
    max_residual: jax.Array
    initial: dict
    drift: dict
    momentum: jax.Array
    final_xi: jax.Array | None
    energy_change: jax.Array  # the energy check's running maxima (`clebsch_jax.march.energy_check.energy_jump`)
    energy_size: jax.Array
    # The march state at the chunk's last node, so that the next chunk makes exactly the steps
    # of one unbroken `integrate` run: the general chunk's `Solution.march_state` (the stepper's
    # guesses and predictor history), or the per-member program's `MemberCarry.march` on the
    # native backend; None where nothing carries it. `march_ok`: whether `march` holds this
    # member's state (not after a chunk of the fast or lean path, which march with another method).
    march: object = None
    march_ok: jax.Array | None = None
    # the weight of the member's isotropy gauge (`Config.isotropy`), found in the first chunk at
    # (Q⁰, ξ⁰) as `integrate` finds it (`clebsch_jax.core.isotropy.gauge_weight`); None: no gauge
    gauge: jax.Array | None = None


@dataclasses.dataclass(frozen=True)
class Config:
    """Everything static about a chunk: hashed by jit (callables by identity)."""

    make_system: Callable | None
    invariants: tuple  # ((name, fn), ...)
    options: tuple  # sorted ((key, value), ...) passed to integrate
    n: int  # steps in this chunk
    save_every: int | None
    shared_def: tuple | None = None  # (treedef, leaves with None for arrays) of a shared system
    member_chunk: int | None = None  # members per cj.batch chunk inside a batch (None: one)
    fast_method: object = None  # the fast path's stepper (clebsch_jax.batching.fast), None: none
    # the energy check (True, False or its tolerance, `energy_check.energy_rtol`), made by the
    # sweep over the whole run (`chunks_xla._energy_check`)
    check_energy: bool | float = True
    lean: bool = False  # the fast path runs the lean chunk (`clebsch_jax.batching.lean`)
    derive_P: bool = False  # the run's first chunk derives the initial multiplier (`chunks_xla._with_start_P`)
    native: bool = False  # the batches run the per-member program as native kernels (`native_call`)
    native_max_lines: int | None = None  # a kernel of more IR lines is not compiled (backend="auto")
    carry_march: bool = True  # hand the march state from chunk to chunk (not on the fast path)
    # (rank, kernel dimension, degenerate) of the isotropy gauge `integrate` fixes for the first
    # member (`probe.check_first_member`), which every member's system gets (`member_system`)
    isotropy: tuple | None = None


def chunk_integrate(cfg: Config, system, Q, xi, P, t, dt, n, march_state=None):
    return integrate(
        system,
        Q,
        xi,
        dt=dt,
        n_steps=n,
        P0=P,
        t0=t,
        throw=False,
        march_state=march_state,
        backend="xla",  # traced, in the XLA chunk of a batch
        **dict(cfg.options),
    )


def system_of(cfg: Config, params, shared, weight=None):
    """Member's system: `make_system(params)`, or the shared system rebuilt from its array
    leaves `shared` (traced) and its other leaves (static, in `cfg`); with `cfg.isotropy`, with
    its isotropy gauge fixed as `integrate` fixes it, with `weight` (default 1: for traces that
    need the system's structure, not its values; a chunk's member has its own, `member_system`)."""
    if cfg.make_system is not None:
        system = cfg.make_system(params)
    else:
        treedef, static = cfg.shared_def
        it = iter(shared)
        system = jax.tree_util.tree_unflatten(treedef, [next(it) if x is None else x for x in static])
    if cfg.isotropy is None:
        return system
    rank, kernel_dim, degenerate = cfg.isotropy
    return _gauged(system, rank, kernel_dim, jnp.ones(()) if weight is None else weight, degenerate)


def member_system(cfg: Config, params, shared, Q, xi, weight, first):
    """(system, ξ, gauge weight) of a member in a chunk that starts from (Q, ξ): `system_of`, and
    with `cfg.isotropy` what `integrate` does for a Lagrangian blind to the isotropy — the gauge
    weight found in the run's first chunk at (Q⁰, ξ⁰ as given) and `weight` (the carried one)
    in the others; and, in the first chunk of a run given no P0, ξ⁰ taken as its physical
    velocity (its isotropy component dropped: `clebsch_jax.core.isotropy.physical_part`)."""
    if cfg.isotropy is None:
        return system_of(cfg, params, shared), xi, weight
    rank, kernel_dim, degenerate = cfg.isotropy
    base = system_of(dataclasses.replace(cfg, isotropy=None), params, shared)
    weight = jnp.where(first, _gauge_weight(base, Q, xi), weight)
    if cfg.derive_P:
        xi = jnp.where(first, _physical_part(base.velocity_map, Q, xi, rank), xi)
    return _gauged(base, rank, kernel_dim, weight, degenerate), xi, weight


def _split_system(system: ClebschSystem):
    """A shared system as (treedef, static leaves) and its array leaves: plain functions in a
    system are leaves too, and jit only takes arrays."""
    leaves, treedef = jax.tree_util.tree_flatten(system)
    is_array = [_is_array(x) for x in leaves]
    static = tuple(None if a else x for x, a in zip(leaves, is_array))
    return (treedef, static), [x for x, a in zip(leaves, is_array) if a]


def chunk_config(run: Run, members: Members, options: dict) -> Config:
    """The static part of a chunk, which jit hashes: refused here if it is not hashable. The
    energy check (`check_energy`, on by default as in `integrate`) is the sweep's own, over
    the whole run (`chunks_xla._energy_check`): the chunks' `integrate` calls run without it."""
    check_energy = options.get("check_energy", True)
    rtol = energy_rtol(check_energy)  # refused here if it is not True, False or a tolerance
    check_energy = check_energy if isinstance(check_energy, bool) else rtol
    options = {**options, "check_energy": False}
    cfg = Config(
        members.builder,
        tuple(run.invariants.items()),
        tuple(sorted(options.items())),
        run.chunk_steps,
        run.save_every,
        members.shared_def,
        run.member_chunk,
        check_energy=check_energy,
        derive_P=members.P0 is None,
    )
    try:
        hash(cfg)
    except TypeError as err:
        raise ValueError(
            f"options: integrate options (and the non-array parts of a shared system) must be hashable ({err})."
        ) from None
    return cfg


def first_row(members: Members):
    """The first member's parameter row (None without `make_system`): the choices made on one
    member (method, fast path, defaults) hold for all, which share the system's facts."""
    return member_row(members, 0)


def member_row(members: Members, m: int):
    """Member m's parameter row (None without `make_system`)."""
    return None if members.builder is None else member_slices(members.params, int(members.param_index[m]))
