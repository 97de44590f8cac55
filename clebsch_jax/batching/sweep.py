r"""`sweep`: many members (parameters × initial conditions) through `integrate`, reduced to a table.

A sweep member $m$ is one trajectory: a system built from its parameters, initial data
$(Q^0_m, \xi^0_m)$ and a step $\Delta t_m$. The sweep keeps no trajectory. The run is cut into
**chunks** of `chunk_steps` steps; each chunk is one `integrate` call that starts from the last
node of the chunk before, handing over the canonical state $(Q^n, p^n)$ (`P0=`), and each chunk
updates per-member running reductions (maximum energy error, maximum drift of each invariant,
first failure, Newton statistics). Members run in **batches** of `batch_size` (`jax.vmap`
inside, a Python loop outside), so memory is bounded by one batch × one chunk of trajectory,
whatever the number of members and steps. The member axis can be split across devices: whole
batches are dealt to the devices and run side by side (asynchronous dispatch), each device
running the same compiled program as an unsharded sweep, so the results are identical to the
bit. (One SPMD program over a `Mesh` — `jax.shard_map` or `jit` with a `NamedSharding` —
would compile once, but XLA optimises the partitioned module differently: e.g. a division by
a determinant becomes a multiplication by its reciprocal in one program and not in the other,
so results differ in the last bits.)

**Continuation is the same map.** A step of the march is the symplectic map
$(Q^n, p^n) \mapsto (Q^{n+1}, p^{n+1})$ (Lemma 20), so restarting from the last node's
$(Q^n, p^n)$ (`continue_from`) continues the same trajectory. Only round-off differs: each chunk
restarts the Newton initial guesses (the predictor's history, the carried inverse Jacobian)
and, in the reduced march (Theorem 27), the state $\mu^n = -p^n\diamond Q^n$ makes the round
trip $\mu \to p \to \mu$ through the minimum-norm cotangent (`cotangent_from_momentum`, a
least-squares solve). Newton iterates every step to round-off (the default `rtol = atol = 0`),
so a chunked run reproduces the unchunked trajectory to a few ulps per chunk
(`tests/test_sweep.py` bounds it by 1e-12), not bit for bit. Chunks of tens of steps or more
keep the cost of the restarts and of a call small against the steps; the measurements behind
the default chunk size are in `benchmarks/README.md` ("Measurements behind the engine's
choices").
"""

from __future__ import annotations

import dataclasses
import functools
import numbers
import os
import sys
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import diagnostics as _diagnostics
from ..core.jit import LEAN_COMPILE, QUICK_COMPILE, jit_with_options, memo, undifferentiated
from ..core.system import ClebschSystem
from ..core.validation import check_configuration as _check_configuration
from ..core.validation import check_memory as _check_memory
from ..core.validation import host_float_array as _float_array
from ..core.validation import is_array as _is_array
from ..core.validation import positive_int as _positive_int_checked
from ..core.validation import runnable_check as _runnable_check
from ..discrete.legendre import initial_multiplier
from ..march.continuation import continue_from
from ..march.integrate import check_member as _check_member_eagerly
from ..march.integrate import integrate, prepared_method
from ..march.scan import energy_jump, node_energies, node_energy
from ..march.solution import IntegrationError
from ..roots.solvers import Newton
from ..roots.status import Status
from ..steppers.base import AbstractWrapper
from ..steppers.choose import choose_method as _choose_method
from ..steppers.full import FullStep
from .backends import NativeProgram, check_backend as _check_backend, native_unavailable as _native_unavailable
from .backends import warn_once as _warn_once
from .batch_last import batch
from .fast import fast_method as _fast_method
from .lean import carries_Q as _lean_carries_Q, lean_chunk, supports as _lean_supports
from .member import MemberCarry, member_chunk
from .scalarise import scalarise

__all__ = ["sweep", "SweepResult", "SweepProgress"]

_RESERVED = ("P0", "t0", "throw", "dt", "n_steps")
_DEFAULT_CHUNK = 100
_DEFAULT_BATCH = 1024
_DEFAULT_BATCH_LEAN = 16_384
"""Members per compiled call of the lean chunk (`fast=True`): it records nothing, and its rows
of many members share XLA's per-operation cost (`benchmarks/throughput.py --sweep-only`)."""

FAST_GIVE_UP = 2
"""A batch in which at least half the members' checks failed in this many fast-path calls in a
row (a call covers a chunk, or `LEAN_CHUNKS` for the lean chunk) runs its remaining chunks on
the general path directly (the table is the same: a member whose check failed is run again by
the general path anyway): the fast path does not suit its march — e.g. a Lagrangian that is not
quadratic in ξ, whose nodal relation the lean chunk's two fixed updates do not solve to
round-off, or steps too large for them — and trying each chunk twice would make the sweep
slower than `fast=False`. A call in which fewer members failed reruns only those
(`FALLBACK_BATCH`) and keeps the fast path."""

FALLBACK_BATCH = 256
"""Members per call of the general path where it reruns the members whose fast-path check
failed in a call (gathered from the batch, the last group padded with copies of its last
member; at most the batch size): a few hard members — fast rotations, steps too large for the
fixed updates — then cost the general path's time for themselves only, not for their whole
batch, and every rerun compiles the same program. General batches of this size run at the
general path's full rate (`benchmarks/throughput.py --sweep-only`)."""

LEAN_CHUNKS = 4
"""Chunks of `chunk_steps` steps per call of the lean chunk, at most (`_calls`): its start and
end (the momentum map, node 0's velocity, the warm-up steps, the cotangent P of the last node)
are then paid once per that many chunks."""

THREADS_MAX = 2
"""`sweep`'s default `threads`: the CPU cores the process may use, at most this many (measured
on a 2-core host, `benchmarks/README.md`; more threads on more cores are the caller's choice)."""

THREAD_MIN_MEMBERS = 256
"""... and only as many threads as give each a batch of at least this many members (a smaller
sweep runs as before: its batches gain little from running side by side)."""

AUTO_MAX_IR_LINES = 50_000
"""`backend="auto"` compiles a native kernel whose LLVM IR has at most this many lines (a kernel
in the disk cache is always used): LLVM's time grows with the IR, to tens of seconds for the
largest programs the translation covers, where XLA compiles in a few. Larger kernels run on
XLA, with the reason said once; `backend="native"` compiles them.
(`benchmarks/README.md`, `native.py`, records the sizes and times behind the value.)"""

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
(`_resumed`)."""


def _auto_lean(B: int, n_steps: int) -> bool:
    """Whether `fast="auto"` tries the lean chunk for a sweep of B members and `n_steps` steps."""
    return B >= AUTO_LEAN_MIN_MEMBERS and B * n_steps >= AUTO_LEAN_MIN_MEMBER_STEPS


def _resumed(fast, batch_size, store, overwrite: bool, backend: str = "xla"):
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


# --------------------------------------------------------------------------------------------
# The result: one row per member.


@dataclasses.dataclass(frozen=True)
class SweepResult:
    r"""Per-member diagnostics of a `sweep` (B members; a pytree of NumPy arrays).

    **Fields:**

    - `param_index`, `ic_index` (B,): which row of `params` and of `Q0`/`xi0` member m used
      (with `grid=True`, m = `param_index` · n_ic + `ic_index`; otherwise both equal m).
    - `status` (B,): the first failure's `clebsch_jax.Status` code (0 = success).
      `failed_step` (B,): its step, counted from the start of the run (for
      `Status.LEGENDRE`, the node), −1 if none.
    - `energy_error` (B,): $\max_n |E^n - E^0|$ over the known nodes, $E$ =
      `clebsch_jax.diagnostics.energy`. Known nodes: those before a failure whose nodal velocity
      was recovered (`Solution.valid` and `nodal_stats.status` SUCCESS; the node a failed step
      starts from is valid, but its velocity is NaN). NaN when the values at node 0 are not
      finite (e.g. NaN initial data).
    - `drift` {name: (B,)}: for each invariant f, $\max_n \|f^n - f^0\|_\infty$ over the known
      nodes (absolute; divide by `initial[name]` for a relative drift), NaN as `energy_error`.
      Always has "energy" (equal to `energy_error`).
    - `initial` {name: (B, …)}: each invariant at node 0.
    - `newton_iterations` (B,): Newton updates summed over all steps attempted.
      `max_residual` (B,): worst final residual max-norm of a successful step.
    - `final_t` (B,), `final_Q` (B, *Q.shape) (None when the reduced march ran without
      reconstructing Q), `final_p` (B, *Q.shape) the canonical momentum at `final_Q` (passing
      `final_Q`, `final_p` as `Q0`, `P0` continues the run), `final_xi` (B, *ξ.shape) the nodal
      velocity (None for a degenerate system), `final_momentum` (B, *ξ.shape) the momentum
      map $-p\diamond Q$. NaN for members that failed.
    - `saved`: None, or (with `save_every=k`) a dict with `"step"` (S,) the saved nodes
      0, k, 2k, … ≤ n_steps, `"t"` (B, S), `"Q"` (B, S, *Q.shape) (None as `final_Q`),
      `"xi"` (B, S, *ξ.shape) (None as `final_xi`) and `"momentum"` (B, S, *ξ.shape).
    - Static facts: `n_steps`, `chunk_steps`, `batch_size`, `n_devices` (the number of devices
      the members' results were computed on, read back from the output arrays), `form` ("full" or
      "reduced"), `scheme`, `order`, `method` (of the `integrate` run).
    - `fast_chunks`: the chunks (of steps, of one batch) run on the fast path
      (`clebsch_jax.batching.fast`; 0 when it does not apply or `fast=False`);
      `fallback_chunks`: how many of them some member's check rejected, so that the member's
      chunk ran again with the general Newton loop (a lean call covers several chunks: they
      count together); `fallback_member_chunks`: the (member, chunk) pairs run again so —
      divided by `fast_chunks` × members per batch, the share of the work the general path
      redid. A table read from a store (`open_sweep`, also the result of a resumed or
      Dask-written stored sweep) does not keep these counts: 0.
    """

    param_index: np.ndarray
    ic_index: np.ndarray
    status: np.ndarray
    failed_step: np.ndarray
    energy_error: np.ndarray
    drift: dict
    initial: dict
    newton_iterations: np.ndarray
    max_residual: np.ndarray
    final_t: np.ndarray
    final_Q: np.ndarray | None
    final_p: np.ndarray
    final_xi: np.ndarray | None
    final_momentum: np.ndarray
    saved: dict | None
    n_steps: int = 0
    chunk_steps: int = 0
    batch_size: int = 0
    n_devices: int = 1
    form: str = ""
    scheme: str = ""
    order: int = 0
    method: str = ""
    fast_chunks: int = 0
    fallback_chunks: int = 0
    fallback_member_chunks: int = 0

    def __len__(self) -> int:
        return int(self.status.shape[0])

    @property
    def succeeded(self) -> np.ndarray:
        """(B,) True for members whose whole run succeeded."""
        return self.status == Status.SUCCESS

    @property
    def failed_members(self) -> np.ndarray:
        """Indices of the members that failed."""
        return np.flatnonzero(self.status != Status.SUCCESS)

    def to_dict(self, state: bool = False) -> dict:
        """The table as a dict of equal-length 1-D NumPy columns (`pandas.DataFrame(result.to_dict())`).

        Columns: `member`, `param_index`, `ic_index`, `status`, `failed_step`, `energy_error`,
        `drift_<name>` for every other invariant, `newton_iterations`, `max_residual`, `final_t`
        and, with `state=True`, one column per component of the final state (`final_Q[0,1]`, …).
        """
        cols = {
            "member": np.arange(len(self)),
            "param_index": self.param_index,
            "ic_index": self.ic_index,
            "status": self.status,
            "failed_step": self.failed_step,
            "energy_error": self.energy_error,
        }
        cols.update({f"drift_{k}": v for k, v in self.drift.items() if k != "energy"})
        cols.update(newton_iterations=self.newton_iterations, max_residual=self.max_residual, final_t=self.final_t)
        if state:
            for name in ("final_Q", "final_p", "final_xi", "final_momentum"):
                arr = getattr(self, name)
                if arr is None:
                    continue
                for idx in np.ndindex(arr.shape[1:]):
                    cols[f"{name}[{','.join(map(str, idx))}]"] = arr[(slice(None),) + idx]
        return cols

    def summary(self) -> str:
        """A few lines: members, failures (first few with their steps), worst errors and drifts."""
        fails = self.failed_members
        lines = [
            f"sweep: {len(self)} members × {self.n_steps} steps ({self.form} march, {self.method or self.scheme}, "
            f"order {self.order}), {len(fails)} failed"
        ]
        for m in fails[:5]:
            code = int(self.status[m])
            lines.append(f"  member {m}: step {int(self.failed_step[m])}: {Status.MESSAGES.get(code, code)}")
        ok = self.succeeded
        if ok.any():
            for name, v in self.drift.items():
                lines.append(f"  max drift of {name} over successful members: {np.max(v[ok]):.3e}")
        return "\n".join(lines)

    def __repr__(self) -> str:
        return self.summary()

    def raise_if_failed(self) -> "SweepResult":
        """Raise `IntegrationError` naming the failed members and their steps; else return self."""
        fails = self.failed_members
        if len(fails):
            first = ", ".join(
                f"member {m} at step {int(self.failed_step[m])} "
                f"({Status.MESSAGES.get(int(self.status[m]), int(self.status[m]))})"
                for m in fails[:3]
            )
            raise IntegrationError(
                f"clebsch_jax.sweep: {len(fails)} of {len(self)} members failed: {first}"
                + (", …" if len(fails) > 3 else "")
                + ". Try a smaller dt for them."
            )
        return self


jax.tree_util.register_dataclass(
    SweepResult,
    data_fields=[
        "param_index",
        "ic_index",
        "status",
        "failed_step",
        "energy_error",
        "drift",
        "initial",
        "newton_iterations",
        "max_residual",
        "final_t",
        "final_Q",
        "final_p",
        "final_xi",
        "final_momentum",
        "saved",
    ],
    meta_fields=[
        "n_steps",
        "chunk_steps",
        "batch_size",
        "n_devices",
        "form",
        "scheme",
        "order",
        "method",
        "fast_chunks",
        "fallback_chunks",
        "fallback_member_chunks",
    ],
)


class SweepProgress(NamedTuple):
    """What a `progress` callback receives after every chunk (every call of the lean chunk,
    which covers several)."""

    batch: int  # 0-based index of the current batch
    n_batches: int
    step: int  # steps done in this batch
    n_steps: int
    members_done: int  # members whose whole run is finished
    n_members: int
    elapsed: float  # seconds since the sweep started


# --------------------------------------------------------------------------------------------
# One chunk of one member (vmapped over a batch, jitted; compiled once per device).


class _Carry(NamedTuple):
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
    energy_change: jax.Array  # the energy check's running maxima (`clebsch_jax.march.scan.energy_jump`)
    energy_size: jax.Array


@dataclasses.dataclass(frozen=True)
class _Config:
    """Everything static about a chunk: hashed by jit (callables by identity)."""

    make_system: Callable | None
    invariants: tuple  # ((name, fn), ...)
    options: tuple  # sorted ((key, value), ...) passed to integrate
    n: int  # steps in this chunk
    save_every: int | None
    shared_def: tuple | None = None  # (treedef, leaves with None for arrays) of a shared system
    member_chunk: int | None = None  # members per cj.batch chunk inside a batch (None: one)
    fast_method: object = None  # the fast path's stepper (clebsch_jax.batching.fast), None: none
    check_energy: bool = True  # the energy check, made by the sweep over the whole run (`_energy_check`)
    lean: bool = False  # the fast path runs the lean chunk (`clebsch_jax.batching.lean`)
    derive_P: bool = False  # the run's first chunk derives the initial multiplier (`_with_start_P`)
    native: bool = False  # the batches run the per-member program as native kernels (`_native_call`)
    native_max_lines: int | None = None  # a kernel of more IR lines is not compiled (backend="auto")


def _integrate(cfg: _Config, system, Q, xi, P, t, dt, n):
    return integrate(system, Q, xi, dt=dt, n_steps=n, P0=P, t0=t, throw=False, **dict(cfg.options))


def _system_of(cfg: _Config, params, shared):
    """Member's system: `make_system(params)`, or the shared system rebuilt from its array
    leaves `shared` (traced) and its other leaves (static, in `cfg`)."""
    if cfg.make_system is not None:
        return cfg.make_system(params)
    treedef, static = cfg.shared_def
    it = iter(shared)
    return jax.tree_util.tree_unflatten(treedef, [next(it) if x is None else x for x in static])


def _split_system(system: ClebschSystem):
    """A shared system as (treedef, static leaves) and its array leaves: plain functions in a
    system are leaves too, and jit only takes arrays."""
    leaves, treedef = jax.tree_util.tree_flatten(system)
    is_array = [_is_array(x) for x in leaves]
    static = tuple(None if a else x for x, a in zip(leaves, is_array))
    return (treedef, static), [x for x, a in zip(leaves, is_array) if a]


def _deviation(values, ref):
    """max-norm over a value's own axes of |values[n] - ref|, one number per node."""
    d = jnp.abs(values - ref[None])
    return jnp.max(d.reshape(d.shape[0], -1), axis=1) if d.ndim > 1 else d


def _node_Q(cfg: _Config, sol, carry: _Carry):
    """The configurations at the chunk's nodes: the chunk's start where Q is not reconstructed
    (the reduced march: the Lagrangian does not depend on Q)."""
    return sol.Q if sol.Q is not None else jnp.broadcast_to(carry.Q, (cfg.n + 1,) + carry.Q.shape)


def _energy_check(cfg: _Config, system, sol, carry: _Carry):
    """`integrate`'s energy check (`check_energy`) over the whole run, made chunk by chunk: the
    chunks run unchecked and the sweep compares each step's energy change with the running
    maxima of the steps before it, carried from chunk to chunk. Returns (jumped, step, the
    running maxima after the chunk, the nodes' energies or None)."""
    if not cfg.check_energy or sol.xi is None:  # degenerate systems are not checked (as in integrate)
        return jnp.asarray(False), jnp.asarray(cfg.n), carry.energy_change, carry.energy_size, None
    E, size = node_energies(system, _node_Q(cfg, sol, carry), sol.xi)
    return (*energy_jump(jnp, E, size, sol.stats.status, carry.energy_change, carry.energy_size), E)


def _with_start_P(cfg: _Config, system, carry: _Carry, first) -> _Carry:
    """`carry` with the minimum-norm initial multiplier P⁰ from (Q⁰, ξ⁰) (Lemma 7,
    `initial_multiplier`) in the run's first chunk, when the sweep was given no P0: the batch
    starts with a placeholder there, and every chunk program derives it (the lean chunk its
    momentum, `lean_chunk`'s `derive_momentum`), instead of a program of its own compiled for it."""
    if not cfg.derive_P:
        return carry
    return carry._replace(P=jnp.where(first, initial_multiplier(system, carry.Q, carry.xi), carry.P))


def _member_chunk(cfg: _Config, params, shared, carry: _Carry, dt, first, offset):
    system = _system_of(cfg, params, shared)
    carry = _with_start_P(cfg, system, carry, first)
    # A member that failed before starts the chunk failed (a NaN state): a failed step made its
    # state NaN already, a jump found by the energy check did not. (Masking the state handed on
    # by the chunk that found the jump instead, on a value computed in that chunk, makes XLA's
    # program several times slower; `_collect` masks the final state of a failed member.)
    alive = carry.status == Status.SUCCESS
    carry = carry._replace(**{k: jnp.where(alive, getattr(carry, k), jnp.nan) for k in ("Q", "xi", "P")})
    sol = _integrate(cfg, system, carry.Q, carry.xi, carry.P, carry.t, dt, cfg.n)
    jumped, jump_step, energy_change, energy_size, E = _energy_check(cfg, system, sol, carry)
    end = jnp.where(jumped, jump_step, cfg.n)  # a jump fails its step: the nodes after it are unknown
    steps, nodes = jnp.arange(cfg.n), jnp.arange(cfg.n + 1)
    # Nodes whose state is known: before any failure, with the nodal velocity recovered.
    known = sol.valid & (sol.nodal_stats.status == Status.SUCCESS) & (nodes <= end)
    initial, drift = {}, {}
    for name, fn in cfg.invariants:
        # the energy invariant is the energy the check computed (the same function of the nodes)
        v = E if (fn is _diagnostics.energy and E is not None) else jnp.asarray(fn(system, sol))
        ref = jnp.where(first, v[0], carry.initial[name])
        dev = jnp.where(known, _deviation(v, ref), -jnp.inf)
        d = jnp.maximum(carry.drift[name], jnp.max(dev))
        initial[name], drift[name] = ref, jnp.where(jnp.all(jnp.isfinite(ref)), d, jnp.nan)
    result = jnp.where(jumped, Status.ENERGY_JUMP, sol.result)
    new_failure = (carry.status == Status.SUCCESS) & (result != Status.SUCCESS)
    status = jnp.where(new_failure, result, carry.status).astype(jnp.int32)
    failed_step = jnp.where(
        new_failure, offset + jnp.where(jumped, jump_step, sol.failed_step), carry.failed_step
    ).astype(jnp.int32)
    attempted = (sol.stats.status != Status.SKIPPED) & (steps <= end)
    iterations = carry.iterations + jnp.sum(jnp.where(attempted, sol.stats.iterations, 0))
    good = (sol.stats.status == Status.SUCCESS) & (steps < end)
    max_residual = jnp.maximum(carry.max_residual, jnp.max(jnp.where(good, sol.stats.residual_norm, 0.0)))
    # The hand-over: the canonical state (Qⁿ, pⁿ) at the chunk's last node.
    start = continue_from(system, sol, Q=carry.Q)
    new = _Carry(
        Q=start.Q0,
        P=start.P0,
        xi=start.xi0,
        t=start.t0,
        status=status,
        failed_step=failed_step,
        iterations=iterations,
        max_residual=max_residual,
        initial=initial,
        drift=drift,
        momentum=sol.momentum[-1],
        final_xi=None if sol.xi is None else sol.xi[-1],
        energy_change=energy_change,
        energy_size=energy_size,
    )
    saved = None
    if cfg.save_every is not None:
        pick = slice(0, cfg.n, cfg.save_every)  # nodes 0, k, … of the chunk; its end is the next chunk's 0
        # (nodes after an energy jump are made NaN on the host: `_collect`)
        saved = {
            "t": sol.ts[pick],
            "Q": None if sol.Q is None else sol.Q[pick],
            "xi": None if sol.xi is None else sol.xi[pick],
            "momentum": sol.momentum[pick],
        }
    return new, saved


def _lean_member_chunk(cfg: _Config, params, shared, carry: _Carry, dt, first, offset):
    """A member's chunk on the lean path (`clebsch_jax.batching.lean`): the fast method's steps
    with the sweep's reductions in the loop, no records."""
    system = _system_of(cfg, params, shared)
    stepper = dict(cfg.options)["method"].prepare(system, carry.Q, carry.xi)  # the fast method: `_run_fast_chunk`
    # the lean chunk uses P⁰ only for its momentum μ⁰ = δl/δξ(ξ⁰, Q⁰) (Lemma 7): derived directly
    new, _ = lean_chunk(stepper, system, carry, dt, cfg.n, first, derive_momentum=first if cfg.derive_P else False)
    return new, None


def _batched_chunk(cfg: _Config, params, carry, dt, shared, first, offset, rows: bool = False):
    """The chunk of every member of a batch: `cj.batch` (in chunks of `member_chunk`), or with
    `rows` the scalarising evaluation (`clebsch_jax.batching.scalarise`, the whole batch)."""

    def one(p, c, d, s, f, o):
        if cfg.lean:
            return _lean_member_chunk(cfg, p, s, c, d, f, o)
        return _member_chunk(cfg, p, s, c, d, f, o)

    axes = (0, 0, 0, None, None, None)
    # a sweep is never differentiated: its solves are traced without their derivative rules
    # (`undifferentiated`: `integrate`'s programs are keyed by it, so this is safe for them)
    if rows:  # the lean chunk's start and end compute on small values only (one node each)
        run = scalarise(one, in_axes=axes, loops_only=not cfg.lean)
    else:
        run = batch(one, in_axes=axes, chunk=cfg.member_chunk)
    with undifferentiated():
        return run(params, carry, dt, shared, first, offset)


@functools.partial(jit_with_options, compiler_options=QUICK_COMPILE, static_argnums=0)
def _run_chunk(cfg: _Config, params, carry, dt, shared, first, offset):
    """One chunk of a batch by the general path: (carry, saved)."""
    return _batched_chunk(
        dataclasses.replace(cfg, fast_method=None, lean=False), params, carry, dt, shared, first, offset
    )


def _run_fast_chunk(cfg: _Config, params, carry, dt, shared, first, offset):
    """One chunk of a batch by the fast path (`clebsch_jax.batching.fast`; the lean chunk,
    `clebsch_jax.batching.lean`, where `cfg.lean`): (carry, saved, ok), `ok` (B,) False for a
    member that was alive and failed in it — the caller then runs that member's chunk again
    from the same carry with `_run_chunk` (`_rerun`), which reports the failure. A separate
    program, so that the general one is compiled only for a sweep that needs it; the lean
    chunk's is compiled with `LEAN_COMPILE`."""
    return (_lean_program if cfg.lean else _fast_program)(cfg, params, carry, dt, shared, first, offset)


def _fast_chunk(cfg: _Config, params, carry, dt, shared, first, offset):
    general = dataclasses.replace(cfg, fast_method=None)
    fast = dataclasses.replace(general, options=(("check_energy", False), ("method", cfg.fast_method)))
    new, saved = _batched_chunk(fast, params, carry, dt, shared, first, offset, rows=True)
    ok = (new.status == Status.SUCCESS) | (carry.status != Status.SUCCESS)
    return new, saved, ok


_fast_program = jax.jit(_fast_chunk, static_argnums=0)
_lean_program = jit_with_options(_fast_chunk, LEAN_COMPILE, static_argnums=0)


def _native_member(cfg: _Config, params, shared, carry: MemberCarry, dt, first, offset) -> MemberCarry:
    """One member's chunk as the per-member program (`clebsch_jax.batching.member`): the method
    `integrate` chooses for it, its solves to their own stopping rule, the reductions in the loop."""
    system = _system_of(cfg, params, shared)
    stepper, _, _ = prepared_method(
        system, carry.Q, carry.xi, dt=dt, n_steps=cfg.n, P0=carry.P, t0=carry.t, **dict(cfg.options)
    )
    return member_chunk(
        stepper, system, carry, dt, cfg.n, first, offset, check_energy=cfg.check_energy, derive_P=cfg.derive_P
    )


def _as_member(carry: _Carry) -> MemberCarry:
    """The sweep's carry (energy the only invariant) as the per-member program's, on the host."""
    h = lambda a: np.asarray(a)
    return MemberCarry(
        Q=h(carry.Q),
        P=h(carry.P),
        xi=h(carry.xi),
        t=h(carry.t),
        status=h(carry.status),
        failed_step=h(carry.failed_step),
        iterations=h(carry.iterations),
        max_residual=h(carry.max_residual),
        energy0=h(carry.initial["energy"]),
        drift=h(carry.drift["energy"]),
        momentum=h(carry.momentum),
        energy_change=h(carry.energy_change),
        energy_size=h(carry.energy_size),
    )


def _from_member(m: MemberCarry, has_xi: bool) -> _Carry:
    return _Carry(
        Q=m.Q,
        P=m.P,
        xi=m.xi,
        t=m.t,
        status=m.status,
        failed_step=m.failed_step,
        iterations=m.iterations,
        max_residual=m.max_residual,
        initial={"energy": m.energy0},
        drift={"energy": m.drift},
        momentum=m.momentum,
        final_xi=m.xi if has_xi else None,
        energy_change=m.energy_change,
        energy_size=m.energy_size,
    )


_NATIVE_AXES = (0, None, 0, 0, None, None)


def _native_program(cfg: _Config, params, shared, carry: MemberCarry, dt):
    """The native kernel of `_native_member` for this configuration and these shapes (compiled
    once per process; from the disk cache when another process compiled it)."""
    row = lambda tree: jax.tree_util.tree_map(lambda a: np.asarray(a)[0], tree)
    args = (
        row(params),
        None if shared is None else [np.asarray(x) for x in shared],
        row(carry),
        row(dt),
        np.asarray(True),
        np.asarray(0, np.int32),
    )
    fun = functools.partial(_native_member, cfg)

    def traced(*a):
        with undifferentiated():  # a sweep is never differentiated: no derivative rules traced
            return fun(*a)

    return NativeProgram.get(("sweep", _trace_key(cfg, args)), traced, args, _NATIVE_AXES, cfg.native_max_lines)


def _native_call(c: _Config, one: "_Batch", st: int) -> _Carry:
    """One chunk of a batch by its native kernel: the batch's carry after it (host arrays)."""
    carry = _as_member(one.carry)
    program = _native_program(c, one.params, one.shared, carry, one.dt)
    shared = None if one.shared is None else [np.asarray(x) for x in one.shared]
    params = jax.tree_util.tree_map(np.asarray, one.params)
    new = program(params, shared, carry, np.asarray(one.dt), np.asarray(st == 0), np.asarray(st, np.int32))
    return _from_member(new, one.carry.final_xi is not None)


@functools.partial(jit_with_options, compiler_options=QUICK_COMPILE)
def _take_members(tree, idx):
    """The rows `idx` of every leaf of a batch's pytree (params, dt, carry)."""
    return jax.tree_util.tree_map(lambda a: a[idx], tree)


@functools.partial(jit_with_options, compiler_options=QUICK_COMPILE)
def _put_members(tree, idx, rows):
    """`tree` with its rows `idx` replaced by `rows`; an index past the end (padding) is dropped."""
    return jax.tree_util.tree_map(lambda a, r: a.at[idx].set(r, mode="drop"), tree, rows)


# --------------------------------------------------------------------------------------------
# Validation: clear errors before compiling.


def _positive_int(x, name, allow_none=False):
    return _positive_int_checked(x, name, allow_none=allow_none)


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


def _threads(threads, devices: list, B: int) -> int:
    """Host threads per device (`sweep`'s `threads`): the given number, or by default the CPU
    cores this process may use, at most `THREADS_MAX`, shared by the devices, for CPU devices
    (1 for others: an accelerator runs its queue in order) — and never more than give each
    thread a batch of `THREAD_MIN_MEMBERS` members."""
    if threads is not None:
        return _positive_int(threads, "threads")
    if any(d is not None and d.platform != "cpu" for d in devices) or (
        devices == [None] and jax.default_backend() != "cpu"
    ):
        return 1
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on every platform
        cores = os.cpu_count() or 1
    per_device = max(1, min(THREADS_MAX, cores) // len(devices))
    return max(1, min(per_device, B // (len(devices) * THREAD_MIN_MEMBERS)))


def _check_configurations(system, Q0, n_ic):
    """The system's `check_Q` of every concrete Q0[j]: at once when the check has a vectorised
    form (`check_Q.batched(stack) -> None | (j, sentence)`, as the SO(n) models' rotation check
    has; called row by row from Python, it took a large part of a million-member sweep's time),
    else one call per row."""
    check = _runnable_check(system, Q0)
    if check is None:
        return
    batched = getattr(check, "batched", None)
    if batched is not None:
        found = batched(np.asarray(Q0))
        if found is not None:
            j, problem = found
            raise ValueError(f"Q0[{j}]: {problem}")
        return
    for j in range(n_ic):
        try:
            _check_configuration(system, Q0[j])
        except ValueError as err:
            raise ValueError(f"Q0[{j}]: {str(err).removeprefix('Q0: ')}") from None


def _member_slices(tree, idx):
    return jax.tree_util.tree_map(lambda a: a[idx], tree)


# --------------------------------------------------------------------------------------------
# The steps of a sweep: check the options, build the members, probe one member's shapes,
# allocate the table, then for each group of batches (one per device): start, march, collect.


class _Run(NamedTuple):
    """The checked options of a run."""

    n_steps: int
    chunk_steps: int
    save_every: int | None
    member_chunk: int | None
    invariants: dict  # {"energy": diagnostics.energy, **the caller's}
    progress: bool | Callable
    devices: list  # the devices batches are dealt to ([None]: JAX's default placement)
    threads: int = 1  # batches run side by side on each device, each from a host thread of its own

    @property
    def slots(self) -> list:
        """The device of each batch of a group: every device `threads` times."""
        return list(self.devices) * self.threads

    @property
    def chunks(self) -> list:
        """(first step, number of steps) of each chunk."""
        return [(st, min(self.chunk_steps, self.n_steps - st)) for st in range(0, self.n_steps, self.chunk_steps)]


def _check_run(n_steps, grid, options, chunk_steps, save_every, member_chunk, invariants, progress, devices) -> _Run:
    """The arguments that need no tracing, checked; the default chunk size chosen."""
    n_steps = _positive_int(n_steps, "n_steps")
    if not isinstance(grid, bool):
        raise ValueError(f"grid: expected True or False, got {grid!r}.")
    for key in options:
        if key in _RESERVED:
            raise ValueError(
                f"{key}: set by sweep itself (it hands the state from chunk to chunk); "
                "pass P0 and dt to sweep, not as integrate options."
            )
    save_every = _positive_int(save_every, "save_every", allow_none=True)
    member_chunk = _positive_int(member_chunk, "member_chunk", allow_none=True)
    chunk_steps = _positive_int(chunk_steps, "chunk_steps", allow_none=True)
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
    return _Run(
        n_steps,
        min(chunk_steps, n_steps),
        save_every,
        member_chunk,
        {"energy": _diagnostics.energy, **invariants},
        progress,
        _devices(devices),
    )


class _Members(NamedTuple):
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


def _members(make_system, params, Q0, xi0, P0, dt, grid) -> _Members:
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
    return _Members(builder, shared_def, shared, params, Q0, xi0, P0, n_ic, param_index, ic_index, dt)


CHUNK_BYTES = 200
"""Host memory per chunk of a run's schedule (`_Run.chunks` and the calls that hold them: a
(first step, steps) pair and its places in two lists), for `_check_size`."""


def _check_size(run: _Run, members: _Members) -> None:
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


FIRST_MEMBER_TRIES = 8
"""`_check_first_member` checks the first member whose inputs are finite and whose system
`make_system` builds from its concrete parameter row, among the first this many such members."""


def _check_first_member(cfg: _Config, members: _Members) -> None:
    """`integrate`'s checks of a member, with its concrete values, before any batch is traced or
    compiled (`clebsch_jax.march.integrate.check_member`): the batches march traced members, on
    which `integrate` skips the checks that need values — the model by autodiff (`check_model`),
    Q0 in the velocity map's group (`check_group_configuration`) and the first step on the
    configuration manifold (`check_first_step`). One member: the checks look at the model (its
    functions), which the members share. It is the first member that can run: one with
    non-finite inputs, or whose parameter row the model's constructor refuses, is reported in
    the table instead (`Status.INVALID_INPUT`), as before. The system's own check of its
    configurations (`check_Q`) runs on every Q0[j], first (`_check_configurations`)."""
    _check_configurations(_system_of(cfg, _first_row(members), members.shared), members.Q0, members.n_ic)
    finite = lambda a: np.all(np.isfinite(np.reshape(a, (len(a), -1))), axis=1)  # noqa: E731
    ok_ic = finite(members.Q0) & finite(members.xi0) & (True if members.P0 is None else finite(members.P0))
    ok = ok_ic[members.ic_index]
    if members.builder is not None:
        rows = np.all([finite(leaf) for leaf in jax.tree_util.tree_leaves(members.params)], axis=0)
        ok &= rows[members.param_index]
    options = {k: v for k, v in cfg.options if k != "check_energy"}
    for m in np.flatnonzero(ok)[:FIRST_MEMBER_TRIES]:
        i, j = int(members.param_index[m]), int(members.ic_index[m])
        try:
            row = None if members.builder is None else _member_slices(members.params, i)
            system = _system_of(cfg, row, members.shared)
        except (ValueError, TypeError):  # a row the constructor refuses: that member reports it
            continue
        P0 = None if members.P0 is None else members.P0[j]
        try:
            _check_member_eagerly(
                system, members.Q0[j], members.xi0[j], dt=members.dt[m], P0=P0, configuration=False, **options
            )
        except (ValueError, TypeError) as err:
            where = (f"make_system(params[{i}]), " if members.builder is not None else "") + f"Q0[{j}], xi0[{j}]"
            raise type(err)(f"sweep: member {m} ({where}) is rejected by integrate's checks: {err}") from err
        return


def _chunk_config(run: _Run, members: _Members, options: dict) -> _Config:
    """The static part of a chunk, which jit hashes: refused here if it is not hashable. The
    energy check (`check_energy`, on by default as in `integrate`) is the sweep's own, over
    the whole run (`_energy_check`): the chunks' `integrate` calls run without it."""
    check_energy = options.get("check_energy", True)
    if not isinstance(check_energy, bool):
        raise TypeError(f"check_energy: expected True or False, got {check_energy!r}.")
    options = {**options, "check_energy": False}
    cfg = _Config(
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


def _first_row(members: _Members):
    """The first member's parameter row (None without `make_system`): the choices made on one
    member (method, fast path, defaults) hold for all, which share the system's facts."""
    return None if members.builder is None else _member_slices(members.params, int(members.param_index[0]))


_PARTICLE_MEMBER_CHUNK = 16
"""`member_chunk` of a sweep of degenerate particle systems (`_particle_defaults`): small
chunks of block Newton loops, each running until its slowest member stops
(`benchmarks/throughput.py` measures clusters of point vortices)."""


def _particle_defaults(cfg: _Config, members: _Members) -> _Config:
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
    system = _system_of(cfg, _first_row(members), members.shared)
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


def _fast_method_of(cfg: _Config, members: _Members):
    """The fast path's method for this sweep (`clebsch_jax.batching.fast`), chosen on the first
    member as `integrate` chooses (the choice depends on the system's facts and the options,
    the same for every member), or None."""
    j = members.ic_index[0]
    return _fast_method(
        _system_of(cfg, _first_row(members), members.shared),
        jnp.asarray(members.Q0[j]),
        jnp.asarray(members.xi0[j]),
        dict(cfg.options),
    )


def _lean_applies(cfg: _Config, members: _Members, method) -> bool:
    """Whether the fast path can run the lean chunk: a method it supports, no node saved, no
    invariant but the energy (the others are functions of a chunk's `Solution`), the energy
    check on (the lean chunk always makes it)."""
    if method is None or cfg.save_every is not None or not cfg.check_energy:
        return False
    if [name for name, _ in cfg.invariants] != ["energy"] or cfg.invariants[0][1] is not _diagnostics.energy:
        return False
    return _lean_supports(method, _system_of(cfg, _first_row(members), members.shared))


def _native_why(cfg: _Config, run: _Run) -> str | None:
    """Why the per-member program cannot run this sweep natively (None: it can)."""
    why = _native_unavailable(run.devices)
    if why is not None:
        return why
    if run.save_every is not None:
        return "the sweep saves nodes (save_every), which the per-member program does not record"
    if [name for name, _ in cfg.invariants] != ["energy"] or cfg.invariants[0][1] is not _diagnostics.energy:
        return "the sweep has invariants besides the energy (functions of a chunk's Solution)"
    return None


def _native_config(cfg: _Config, run: _Run, members: _Members, backend: str):
    """`(cfg, shapes)` for the native backend where it applies: the member checked as
    `integrate` checks it, and the program of a chunk compiled (from the disk cache when it is
    there). Where it does not apply: `backend="native"` is refused with the reason, "auto"
    says the reason once and keeps XLA (`(cfg, None)`)."""
    why = _native_why(cfg, run)
    shapes = None
    if why is None:
        from ..native import Unsupported

        shapes = _probe(cfg, members, lean=True)  # integrate's checks of a member, no march traced
        limit = AUTO_MAX_IR_LINES if backend == "auto" else None
        native = dataclasses.replace(cfg, native=True, native_max_lines=limit)
        one = _start_batch(native, members, shapes, 0, 1, None)
        try:
            _native_program(native, one.params, one.shared, _as_member(one.carry), one.dt)
            return native, shapes
        except Unsupported as err:
            why = f"the per-member program uses {err}, which the native translation does not cover"
    if backend == "native":
        raise ValueError(f"backend='native': {why}.")
    _warn_once(why)
    return cfg, shapes


class _Shapes(NamedTuple):
    """One member's shapes and the facts of its march."""

    q: tuple  # Q's shape
    xi: tuple  # ξ's shape
    has_Q: bool  # False: the reduced march ran without reconstructing Q
    has_xi: bool  # False: a degenerate system (no nodal velocity)
    invariants: dict  # {name: shape and dtype of its values on a 1-step solution, (2, …)}
    facts: dict  # form, scheme, order, method


def _trace_member(cfg: _Config, *args):
    """`jax.eval_shape` of one member's chunk (its `Solution` and invariants), cached by the
    arguments' shapes and dtypes: the trace reads nothing else, and repeating it cost a sweep of
    a thousand members a third of its time."""

    def probe(p, s, q, x, d):
        system = _system_of(cfg, p, s)
        sol = _integrate(cfg, system, q, x, jnp.zeros_like(q), jnp.zeros((), q.dtype), d, cfg.n)
        return sol, {name: jnp.asarray(fn(system, sol)) for name, fn in cfg.invariants}

    def trace():  # as the chunk programs trace the march (`_batched_chunk`), whose traces it shares
        with undifferentiated():
            return jax.eval_shape(probe, *args)

    return memo(_TRACES, _trace_key(cfg, args), trace, _TRACES_MAX)


def _trace_key(cfg: _Config, args) -> tuple:
    """The cache key of a trace of one member's `args`: the configuration, the arguments' tree,
    shapes and dtypes (a trace reads nothing else)."""
    leaves, tree = jax.tree_util.tree_flatten(args)
    dtype = lambda x: x.dtype if hasattr(x, "dtype") else np.result_type(x)  # not an array as a dtype (deprecated)
    return (cfg, tree, tuple((np.shape(x), dtype(x), getattr(x, "weak_type", False)) for x in leaves))


_TRACES: dict = {}
_TRACES_MAX = 64
"""`_trace_member`'s cache (`clebsch_jax.core.jit.memo`): cleared when it holds this many."""


def _check_member(cfg: _Config, *args):
    """`integrate`'s checks of one member's arguments and its choice of method, traced
    (`prepared_method` under `jax.eval_shape`: no march is traced, nothing compiled):
    (the prepared method's facts, whether the lean chunk carries Q, the energy's dtype)."""
    found = {}

    def check(p, s, q, x, d):
        system = _system_of(cfg, p, s)
        stepper, _, _ = prepared_method(
            system, q, x, dt=d, n_steps=cfg.n, P0=jnp.zeros_like(q), t0=jnp.zeros((), q.dtype), **dict(cfg.options)
        )
        found["facts"], found["has_Q"] = stepper.facts(system), _lean_carries_Q(stepper, system)
        return node_energy(system, q, x)[0]

    def run():
        energy = jax.eval_shape(check, *args)
        return found["facts"], found["has_Q"], energy.dtype

    return memo(_TRACES, ("check",) + _trace_key(cfg, args), run, _TRACES_MAX)


def _probe(cfg: _Config, members: _Members, lean: bool = False) -> _Shapes:
    """One member's shapes, by tracing integrate (its own checks name Q0, xi0, ...): no compile.

    With `lean` (the sweep runs the lean chunk, `clebsch_jax.batching.lean`, which keeps the
    energy only): the same checks and shapes without tracing the march, which nothing else
    of such a sweep would reuse (`_check_member`). The configurations and the checks that need
    values were made before, on concrete values (`_check_first_member`)."""
    p_row = _first_row(members)
    j = members.ic_index[0]
    q_row, x_row = jnp.asarray(members.Q0[j]), jnp.asarray(members.xi0[j])

    args = (p_row, members.shared, q_row, x_row, jnp.asarray(members.dt[0]))
    try:
        if lean:
            facts, has_Q, energy_dtype = _check_member(cfg, *args)
        else:
            sol_shape, inv_shape = _trace_member(cfg, *args)
    except (ValueError, TypeError) as err:
        where = (
            "make_system(params[i]), " if members.builder is not None else ""
        ) + f"Q0[j] of shape {q_row.shape}, xi0[j] of shape {x_row.shape}"
        kind = ValueError if isinstance(err, ValueError) else TypeError
        raise kind(f"sweep: one member ({where}) is rejected: {err}") from err
    if lean:  # a regular system (nodal velocities), the energy its only invariant (`_lean_applies`)
        invariants = {"energy": jax.ShapeDtypeStruct((cfg.n + 1,), energy_dtype)}
        facts = dict(form=facts.form, scheme=facts.scheme, order=int(facts.order), method=str(facts.name))
        return _Shapes(q_row.shape, x_row.shape, has_Q, True, invariants, facts)
    for name, v in inv_shape.items():
        if v.ndim < 1 or v.shape[0] != cfg.n + 1:
            raise ValueError(
                f"invariants: {name!r} must return one value per node (leading axis n+1 = "
                f"{cfg.n + 1} for a {cfg.n}-step solution), returned shape {v.shape}."
            )
    facts = dict(
        form=sol_shape.form,
        scheme=sol_shape.scheme,
        order=int(sol_shape.order),
        method=str(getattr(sol_shape, "method", "")),
    )
    return _Shapes(q_row.shape, x_row.shape, sol_shape.Q is not None, sol_shape.xi is not None, inv_shape, facts)


@dataclasses.dataclass(frozen=True)
class _Tables:
    """The sweep's table on the host, filled in group by group of batches."""

    columns: dict  # SweepResult's per-member fields, from status to final_momentum (None: not produced)
    initial: dict  # {invariant: (B, …)}
    drift: dict  # {invariant: (B,)}
    saved: dict | None  # SweepResult.saved


def _allocate_tables(B: int, shapes: _Shapes, run: _Run) -> _Tables:
    q, x = shapes.q, shapes.xi
    columns = dict(
        status=np.zeros(B, np.int32),
        failed_step=np.full(B, -1, np.int32),
        newton_iterations=np.zeros(B, np.int64),
        max_residual=np.zeros(B),
        final_t=np.zeros(B),
        final_Q=np.zeros((B,) + q) if shapes.has_Q else None,
        final_p=np.zeros((B,) + q),
        final_xi=np.zeros((B,) + x) if shapes.has_xi else None,
        final_momentum=np.zeros((B,) + x),
    )
    initial = {k: np.zeros((B,) + v.shape[1:], v.dtype) for k, v in shapes.invariants.items()}
    drift = {k: np.zeros(B) for k in shapes.invariants}
    saved = None
    if run.save_every is not None:
        steps = np.arange(0, run.n_steps + 1, run.save_every)
        S = len(steps)
        saved = {
            "step": steps,
            "t": np.zeros((B, S)),
            "Q": np.zeros((B, S) + q) if shapes.has_Q else None,
            "xi": np.zeros((B, S) + x) if shapes.has_xi else None,
            "momentum": np.zeros((B, S) + x),
        }
    return _Tables(columns, initial, drift, saved)


@dataclasses.dataclass
class _Batch:
    """One batch on its device: its members' inputs and the carry handed from chunk to chunk."""

    index: int
    rows: slice  # its members' rows of the table (without the padding)
    n_real: int  # members that are not padding
    params: object
    dt: jax.Array
    shared: list | None
    carry: _Carry
    fallbacks_in_a_row: int = 0  # fast chunks of this batch rerun by the general path, the last ones


def _start_batch(cfg: _Config, members: _Members, shapes: _Shapes, b: int, batch_size: int, device) -> _Batch:
    """Batch b on `device` (None: JAX's default placement); the last batch is padded with copies
    of the last member."""
    member = np.minimum(np.arange(b * batch_size, (b + 1) * batch_size), members.B - 1)
    n_real = min(batch_size, members.B - b * batch_size)
    ic = members.ic_index[member]
    # host arrays moved to the device as they are: a transfer each, no JAX operation to compile
    put = functools.partial(jax.device_put, device=device)
    params = None if members.builder is None else put(_member_slices(members.params, members.param_index[member]))
    Q, xi = put(members.Q0[ic]), put(members.xi0[ic])
    shared = None if members.shared is None else put(members.shared)
    # without P0, a placeholder that the first chunk's program replaces (`_with_start_P`)
    P = put(np.zeros((len(ic),) + members.Q0.shape[1:], members.Q0.dtype) if members.P0 is None else members.P0[ic])
    zeros = lambda shape, dtype=np.float64: put(np.zeros((batch_size,) + shape, dtype))
    carry = _Carry(
        Q=Q,
        P=P,
        xi=xi,
        t=zeros(()),
        status=zeros((), np.int32),
        failed_step=put(np.full((batch_size,), -1, np.int32)),
        iterations=zeros((), np.int64),
        max_residual=zeros(()),
        initial={k: zeros(v.shape[1:], v.dtype) for k, v in shapes.invariants.items()},
        drift={k: zeros(()) for k in shapes.invariants},
        momentum=zeros(shapes.xi),
        final_xi=zeros(shapes.xi) if shapes.has_xi else None,
        energy_change=zeros(()),
        energy_size=zeros(()),
    )
    rows = slice(b * batch_size, b * batch_size + n_real)
    return _Batch(b, rows, n_real, params, put(members.dt[member]), shared, carry)


def _calls(run: _Run, lean: bool) -> list:
    """The chunks of `run.chunks` that each call of the fast path covers: one each, or for the
    lean chunk up to `LEAN_CHUNKS` consecutive full chunks — as many as divide their number, so
    that every call but a short last chunk's has the same length (one compiled program)."""
    full = [c for c in run.chunks if c[1] == run.chunk_steps]
    rest = [[c] for c in run.chunks[len(full) :]]
    per = max(d for d in range(1, LEAN_CHUNKS + 1) if len(full) % d == 0) if lean else 1
    return [full[i : i + per] for i in range(0, len(full), per)] + rest


def _general_chunks(cfg: _Config, run: _Run, one: _Batch, chunks: list, saved: dict | None):
    """The general path over `chunks` from the batch's carry (dispatched, not waited for): the
    new carry; each chunk's saved nodes go to `saved`."""
    carry = one.carry
    for st, n in chunks:
        carry, chunk_saved = _run_chunk(_steps(cfg, run, n), one.params, carry, one.dt, one.shared, *_at(st))
        _save(saved, run, one, st, n, chunk_saved)
    return carry


def _rerun(cfg: _Config, run: _Run, one: _Batch, chunks: list, saved: dict | None, members: np.ndarray, carry):
    """The general path over `chunks` from the batch's carry for its `members` (indices of real
    members), in groups of `FALLBACK_BATCH`: `carry` (the fast path's new carry) with those
    members' rows replaced by the general path's; their saved nodes go to `saved`. All the
    batch's members in one group: the batch itself, as `_general_chunks`."""
    size = min(FALLBACK_BATCH, len(one.dt))
    if len(members) == one.n_real and size == len(one.dt):
        return _general_chunks(cfg, run, one, chunks, saved)
    table_rows = np.arange(one.rows.start, one.rows.stop)
    for g in range(0, len(members), size):
        part = members[g : g + size]
        pad = size - len(part)
        take = np.concatenate([part, np.full(pad, part[-1])]).astype(np.int32)
        params, dt, start = _take_members((one.params, one.dt, one.carry), take)
        sub = _Batch(one.index, table_rows[part], len(part), params, dt, one.shared, start)
        new = _general_chunks(cfg, run, sub, chunks, saved)
        put = np.concatenate([part, np.full(pad, len(one.dt))]).astype(np.int32)  # padding: dropped
        carry = _put_members(carry, put, new)
    return carry


def _steps(cfg: _Config, run: _Run, n: int) -> _Config:
    """`cfg` for a call of n steps (the same object for the run's chunk length)."""
    return cfg if n == run.chunk_steps else dataclasses.replace(cfg, n=n)


def _at(st: int):
    """A chunk's (first, offset) arguments: host values, so no eager JAX operation."""
    return np.asarray(st == 0), np.asarray(st, np.int32)


def _save(saved: dict | None, run: _Run, one: _Batch, st: int, n: int, chunk_saved):
    """A chunk's saved nodes into the batch's rows of `saved` (`one.rows`: a slice, or the
    table rows of a rerun's members)."""
    if saved is None:
        return
    k0, kn = st // run.save_every, len(range(0, n, run.save_every))
    for key in ("t", "Q", "xi", "momentum"):
        if saved[key] is not None:
            saved[key][one.rows, k0 : k0 + kn] = np.asarray(chunk_saved[key])[: one.n_real]


def _run_chunks(cfg: _Config, group: list, run: _Run, saved: dict | None, report: Callable, fell_back: list):
    """March a group of batches (one per device and thread, side by side) through every chunk:
    each batch's carry moves on, the chunks' saved nodes go to `saved`, each fast-path call's
    (chunks, members rerun) to `fell_back`, `report(group, step)` follows each call.

    A call of the fast path covers one chunk, or `LEAN_CHUNKS` for the lean chunk (which
    records nothing, so its length costs no memory, and its work at the start and end of a call
    is then shared by more steps); the members whose check failed in it are run again by the
    general path, chunk by chunk from the call's start (`_rerun`). Each batch of a group is
    called from a host thread of its own (`sweep`'s `threads`): one thread would run the
    programs it gives one device one after the other."""
    pool = ThreadPoolExecutor(len(group), thread_name_prefix="clebsch-jax-sweep") if len(group) > 1 else None
    # the caller's default device (`jax.default_device`, a context of the calling thread) holds
    # in the pool's threads too: the batches were placed there
    default = jax.config.jax_default_device

    def in_context(call, one):
        if default is None:
            return call(one)
        with jax.default_device(default):
            return call(one)

    try:
        for chunks in _calls(run, cfg.lean):
            st, n = chunks[0][0], sum(k for _, k in chunks)
            c = _steps(cfg, run, n)
            call = functools.partial(_call, cfg, c, run, chunks, st, n, saved, pool is not None)
            done = list(pool.map(functools.partial(in_context, call), group)) if pool is not None else [call(group[0])]
            fell_back.extend(d for d in done if d is not None)
            report(group, st + n)
    finally:
        if pool is not None:
            pool.shutdown()


def _call(
    cfg: _Config, c: _Config, run: _Run, chunks: list, st: int, n: int, saved: dict | None, wait: bool, one: _Batch
):
    """One call of `_run_chunks` for one batch: the fast call (`c`: its chunk's configuration),
    then the general path for the members whose check failed; a batch in which most members
    failed `FAST_GIVE_UP` times in a row runs the general chunks directly. `wait`: return only
    when the general path's programs have run (called from a thread of a group: the group's
    batches then run side by side; a batch alone dispatches them and goes on). Returns the
    fast call's (chunks, members rerun), or None without one."""
    if cfg.native:
        one.carry = _native_call(c, one, st)
        return None
    if cfg.fast_method is None or one.fallbacks_in_a_row >= FAST_GIVE_UP:
        # the general path: for every batch without a fast method, or given up
        one.carry = (
            _general_chunks(cfg, run, one, chunks, saved)
            if cfg.fast_method is None
            else _rerun(cfg, run, one, chunks, saved, np.arange(one.n_real), one.carry)
        )
        if wait:
            jax.block_until_ready(one.carry)
        return None
    f = _run_fast_chunk(c, one.params, one.carry, one.dt, one.shared, *_at(st))
    failed = np.flatnonzero(~np.asarray(jax.device_get(f[2]))[: one.n_real])
    _save(saved, run, one, st, n, f[1])  # a rerun member's rows are written again by `_rerun`
    one.carry = _rerun(cfg, run, one, chunks, saved, failed, f[0]) if failed.size else f[0]
    one.fallbacks_in_a_row = one.fallbacks_in_a_row + 1 if 2 * failed.size >= one.n_real else 0
    return len(chunks), failed.size


def _reporter(progress, n_batches: int, n_steps: int, B: int, batch_size: int) -> Callable:
    """`report(group, step)` after each chunk: nothing (progress False), a line on stderr (True),
    or a `SweepProgress` to the callable. Reporting waits for the chunk to finish."""
    start_time = time.perf_counter()

    def report(group, step):
        if progress is False:
            return
        jax.block_until_ready([one.carry for one in group])
        done = group[0].index * batch_size + (sum(one.n_real for one in group) if step == n_steps else 0)
        info = SweepProgress(
            group[-1].index, n_batches, step, n_steps, min(done, B), B, time.perf_counter() - start_time
        )
        if progress is True:
            print(
                f"\rsweep: batch {info.batch + 1}/{n_batches}, step {step}/{n_steps}, "
                f"{info.members_done}/{B} members done, {info.elapsed:.1f} s",
                end="",
                file=sys.stderr,
                flush=True,
            )
        else:
            progress(info)

    return report


def _collect(tables: _Tables, one: _Batch, run: _Run):
    """A finished batch's carry into its rows of the host tables."""
    host = jax.device_get(one.carry)
    take = lambda a: np.asarray(a)[: one.n_real]
    failed = np.asarray(host.status) != Status.SUCCESS

    def state(a):  # a failed member's final state is NaN (after a jump the chunk's march ran on)
        return None if a is None else np.where(failed.reshape((-1,) + (1,) * (np.ndim(a) - 1)), np.nan, a)

    final = {
        "status": host.status,
        "failed_step": host.failed_step,
        "newton_iterations": host.iterations,
        "max_residual": host.max_residual,
        "final_t": host.t,
        "final_Q": state(host.Q),
        "final_p": state(host.P),
        "final_xi": state(host.final_xi),
        "final_momentum": state(host.momentum),
    }
    for key, column in tables.columns.items():
        if column is not None:
            column[one.rows] = take(final[key])
    for k in tables.drift:
        tables.initial[k][one.rows], tables.drift[k][one.rows] = take(host.initial[k]), take(host.drift[k])
    if tables.saved is None:
        return
    if run.n_steps % run.save_every == 0:  # the last node closes the saved series
        last = {"t": host.t, "Q": host.Q, "xi": host.final_xi, "momentum": host.momentum}
        for key, value in last.items():
            if tables.saved[key] is not None:
                tables.saved[key][one.rows, -1] = take(value)
    # a failed member's nodes after its failed step are NaN (after a jump the march ran on)
    after = take(failed)[:, None] & (tables.saved["step"][None, :] > take(host.failed_step)[:, None])
    for key in ("Q", "xi", "momentum"):
        if tables.saved[key] is not None:
            block = tables.saved[key][one.rows]
            block[after] = np.nan
            tables.saved[key][one.rows] = block


class _Plan(NamedTuple):
    """Everything a batch needs, built once by `sweep` (and sent once to each Dask worker)."""

    cfg: _Config
    members: _Members
    shapes: _Shapes
    run: _Run  # with progress False and devices [None]
    batch_size: int


class _Rows(NamedTuple):
    """The table rows of some batches: `tables` holds them one after the other."""

    batches: list  # batch indices
    rows: list  # each batch's rows of the sweep's table (slices)
    tables: _Tables
    devices: set  # the devices they ran on
    fast_chunks: tuple = (0, 0, 0)  # chunks run by the fast path, those with members rerun by the
    # general one, and the (member, chunk) pairs rerun


def _run_batches(plan: _Plan, batches: list, devices: list, report: Callable) -> _Rows:
    """Run batches side by side (batch i on `devices[i]`; None: JAX's default placement) → their
    table rows. The one function behind an in-process sweep, a stored one and a Dask task: the
    same program on the same padded inputs, so the rows are the same to the bit wherever they
    are computed."""
    cfg, members, shapes, run, bs = plan
    group = [_start_batch(cfg, members, shapes, b, bs, dev) for b, dev in zip(batches, devices)]
    rows, at = [], 0
    for one in group:  # each batch's rows in the group's own table
        rows.append(one.rows)
        one.rows = slice(at, at + one.n_real)
        at += one.n_real
    tables = _allocate_tables(at, shapes, run)
    fell_back = []
    _run_chunks(cfg, group, run, tables.saved, report, fell_back)
    used = set()
    for one in group:
        used.update(one.carry.status.devices() if hasattr(one.carry.status, "devices") else ["native"])
        _collect(tables, one, run)
    fast = (sum(k for k, _ in fell_back), sum(k for k, m in fell_back if m), sum(k * m for k, m in fell_back))
    return _Rows(list(batches), rows, tables, used, fast)


def _place(tables: _Tables, part: _Tables, rows: list):
    """Copy a `_Rows` table `part` (its batches' rows one after the other) into `tables`."""

    def put(dst, src):
        if dst is None:
            return
        start = 0
        for r in rows:
            n = r.stop - r.start
            dst[r] = src[start : start + n]
            start += n

    for key, column in tables.columns.items():
        put(column, part.columns[key])
    for k in tables.drift:
        put(tables.initial[k], part.initial[k])
        put(tables.drift[k], part.drift[k])
    if tables.saved is not None:
        for key in ("t", "Q", "xi", "momentum"):
            put(tables.saved[key], part.saved[key])


# --------------------------------------------------------------------------------------------
# The entry point.


def sweep(
    make_system,
    params,
    Q0,
    xi0,
    *,
    dt,
    n_steps: int,
    P0=None,
    grid: bool = False,
    invariants: dict | None = None,
    chunk_steps: int | None = None,
    batch_size: int | None = None,
    save_every: int | None = None,
    member_chunk: int | None = None,
    devices=None,
    progress=False,
    store=None,
    client=None,
    overwrite: bool = False,
    fast: bool | str = "auto",
    threads: int | None = None,
    backend: str = "auto",
    **options,
) -> SweepResult:
    r"""Run many members — parameters × initial conditions — through `integrate`; keep a table.

    Each member is one `integrate` run; the sweep stores no trajectory, only per-member
    reductions (`SweepResult`): for the energy $E$ and every invariant $f$ you pass,
    $\max_n \|f(\text{node } n) - f(\text{node } 0)\|_\infty$ over the nodes before a failure, the first
    failure (status and step), Newton statistics and the final state; optionally every k-th
    node. Failure is a value: a failing member is reported in the table (its later states NaN)
    and the others are unaffected; nothing is raised (call `raise_if_failed()` for that).

    ```python
    inertias = jnp.array([[2.0, 1.0, 2 / 3], [1.0, 1.0, 0.5], [3.0, 2.0, 1.0]])
    omegas = jax.random.normal(jax.random.key(0), (1000, 3))
    res = cj.sweep(cj.models.rigid_body, inertias, jnp.broadcast_to(jnp.eye(3), (1000, 3, 3)), omegas,
                   dt=0.05, n_steps=10_000, grid=True,        # 3 inertias × 1000 momenta = 3000 members
                   invariants={"casimir": lambda system, sol: jnp.sum(sol.momentum**2, axis=-1)})
    res.drift["casimir"]        # (3000,) max |‖μⁿ‖² − ‖μ⁰‖²|, round-off for every member
    pandas.DataFrame(res.to_dict())
    ```

    **Arguments:**

    - `make_system`: `make_system(params_m)` → the `ClebschSystem` of member m, e.g.
      `cj.models.rigid_body` or `lambda g: cj.models.point_vortices(g)`. It is called inside
      `jax.vmap` (and `jit`) with one member's slice of `params`, so it must build the system
      from those arrays without Python control flow on their values; value checks of the
      built-in models that need concrete numbers (e.g. a positive width) are skipped there.
      Pass a module-level function (not a fresh lambda per call) to reuse compiled code across
      sweeps. Or a `ClebschSystem`, shared by all members (then `params` must be None).
    - `params`: a pytree of arrays (an array, a tuple, a dict) whose leaves all have a leading
      axis of length n_p: row i are the parameters of `make_system`. None with a shared system.
    - `Q0`, `xi0`: initial configurations and velocities with a leading axis of length n_ic
      (`Q0[j]` and `xi0[j]` are one member's `integrate` arguments; use `Q0[None]` for a single
      one, `jnp.broadcast_to` to share one). Non-finite rows are *not* rejected: such members
      fail (status `INVALID_INPUT` at step 0) and are reported, so random samples need no cleaning;
      so do members whose parameter row is invalid (each row is checked in the member's program:
      `clebsch_jax.march.scan.input_ok`).
    - `dt`: the time step, a positive scalar or one per member, shape (B,).
    - `n_steps`: steps per member (an int >= 1).
    - `P0`: optional initial multipliers, shape of `Q0`. Default: `initial_multiplier` of each
      member, as `integrate` does.
    - `grid`: False (default): member m uses row m of `params` and of the initial data (n_p =
      n_ic = B). True: every parameter row with every initial condition, B = n_p · n_ic, member
      m = i · n_ic + j for parameter row i and initial condition j.
    - `invariants`: {name: f} with `f(system, sol)` → per-node values, shape (n+1, …), of a
      `Solution` `sol` of one member over one chunk (the functions of `clebsch_jax.diagnostics`
      have this form: `"energy": cj.diagnostics.energy` is always included). For a function of
      one node, `lambda s, sol: jax.vmap(g)(sol.Q, sol.momentum)`.
    - `chunk_steps`: steps per `integrate` call (default min(n_steps, 100), a multiple of
      `save_every`). Memory is about `batch_size · chunk_steps` nodes; a chunk size that divides
      `n_steps` compiles one program (otherwise a second one for the last chunk). Chunks of
      tens of steps cost little over one unchunked run (see `clebsch_jax.batching.sweep`).
      The lean chunk of `fast` records nothing and runs up to `LEAN_CHUNKS` chunks per call
      (as many as divide the number of chunks); a rerun is made chunk by chunk.
    - `batch_size`: members per compiled call (default min(⌈B / (devices × threads)⌉, 1024); for
      the lean chunk of `fast=True`, batches of equal size up to 16384); at most the number of
      members (a larger one is clamped to it); the last batch is padded with copies of the last
      member. A sweep resumed from a `store` keeps the stored
      batch size.
    - `save_every`: keep every k-th node (`SweepResult.saved`); `chunk_steps` must be a multiple of
      k when the run has more than one chunk.
    - `member_chunk`: a batch runs through `clebsch_jax.batch` (batch-last, the batch's members
      in chunks of `member_chunk` one after the other; default None: one chunk, or 32 for
      degenerate particle systems, see `**options`). A chunk's
      Newton loops run until its slowest member stops, so members whose iteration counts
      differ widely (clusters of point vortices) run faster in small chunks (e.g. 64).
    - `devices`: None (default: JAX's default device); True or "all" (every `jax.devices()`),
      an int n (the first n) or a list of devices: the member axis is split across them batch by
      batch — batch b runs on device b mod n, the batches of a group run side by side
      (asynchronous dispatch) with no communication. Each device runs the very program an
      unsharded sweep runs (same shapes), compiled once per device, so the table is identical
      to the bit (why not one SPMD program: `clebsch_jax.batching.sweep`). The default
      `batch_size` gives every device a batch.
    - `threads`: batches run side by side on each device, each called from a host thread of
      its own (JAX runs the programs one device is given from one thread one after the other;
      from several threads they run at once, and XLA's CPU programs of a sweep — many small
      operations — leave cores idle when run alone). Default: the CPU cores this process may
      use, at most `THREADS_MAX`, shared by the devices, and no more than give each thread
      `THREAD_MIN_MEMBERS` members; 1 on accelerators and for a Dask `client`'s tasks (whose
      workers are the parallelism). The same program per batch: the table is the same to the
      bit for any number of threads (for the same `batch_size`). The caller's
      `jax.default_device` holds in the threads; JAX's other contexts of the calling thread
      (`jax.disable_jit`, `jax.debug_nans`, …) do not reach them: pass `threads=1` under those.
    - `progress`: False (default); True prints one updating line per chunk to stderr; or a
      callable receiving a `SweepProgress` after every chunk. Progress waits for each chunk to
      finish (otherwise chunks are dispatched asynchronously).
    - `store`: None (default: the table is kept in memory only), or a Zarr v3 store (a path or a
      `zarr` store): every finished batch is written to it, with named dimensions and the
      sweep's configuration as attributes, so `xarray.open_zarr(store)` reads it and
      `clebsch_jax.open_sweep(store)` gives the `SweepResult` back. Running the same sweep with
      the same store again skips the batches already written (and says how many members it
      skipped): a sweep killed at any moment resumes where it stopped, with the same table to
      the bit. A store written by another configuration is refused (`clebsch_jax.batching.store`).
      Needs the optional extra `pip install "clebsch-jax[sweep]"`.
    - `client`: None, or a `dask.distributed.Client`: batches run as Dask tasks on its workers
      (a `LocalCluster` of processes, or any cluster with a scheduler address), each worker
      compiling the batch program once; with `store`, workers write their batches to it (it must
      be reachable from every worker). A task whose worker dies is rerun by Dask elsewhere.
      The table is identical to the bit to the in-process one (`clebsch_jax.batching.distributed`).
    - `overwrite`: with `store`, replace a store written by another configuration instead of
      refusing it.
    - `fast`: "auto" (default), True or False. False: the general Newton loop. True: where the
      method has a fast path (`clebsch_jax.batching.fast`: the reduced march, possibly composed), each chunk
      first solves every step by a fixed number of Newton updates with a check per member and
      step, each component of a member its own row (`clebsch_jax.batching.scalarise`). When
      the sweep keeps no node and no invariant but the energy, the chunk is the lean one
      (`clebsch_jax.batching.lean`): the nodal velocities and the energy check are made in the
      same loop and nothing is recorded; otherwise the chunk records its steps as `integrate`
      does. A member whose check fails in a chunk (in a call of the lean chunk: in any of its
      chunks) runs that call's chunks again from the same start with the general loop, which
      reports a failure (status and step) as `fast=False` would; only such members run again
      (gathered in groups of `FALLBACK_BATCH`), the others keep the fast path's results.
      Reruns are counted in `SweepResult.fallback_chunks` and `fallback_member_chunks`, and
      the general program is compiled only when a rerun needs it; after `FAST_GIVE_UP` calls
      in a row in which at least half a batch's members failed, the batch runs its remaining
      chunks on the general path only. The table agrees with
      `fast=False` to round-off (Newton iteration counts are those of the path that ran).
      "auto": the lean chunk where it applies and the sweep is large — at least
      `AUTO_LEAN_MIN_MEMBERS` members and `AUTO_LEAN_MIN_MEMBER_STEPS` member-steps — else the
      general loop: the lean chunk compiles longer than the general one, which a short sweep
      does not repay, and its speed needs long rows (its default `batch_size` is larger;
      `benchmarks/throughput.py --sweep-only` measures both paths). The choice depends on B
      and `n_steps` only — except that a sweep resumed from a `store` takes the path the store
      was written with (the store refuses a run on the other path, so a store written before
      a change of these thresholds, or with `fast=False`, still resumes).
    - `**options`: passed to every `integrate` call (`scheme`, `reduce`, `reconstruct`, `order`,
      `rtol`, `atol`, `max_newton_iterations`, `jacobian`, …); `P0`, `t0`, `throw` are the
      sweep's own. One default differs from `integrate`'s: members that are degenerate
      particle systems (point vortices: `Q0` and `xi0` of shape (N, d), N >= 2) marched by the
      full step get `jacobian="blocks"` and, unless given, `member_chunk=16`. A dense Jacobian of
      3·N·d unknowns factored per member and step costs tens of times a batch's RK4 step; the
      block Newton loop solves to the same round-off. Pass `jacobian="dense"` for the dense
      one. `check_energy` (default True) is `integrate`'s energy check made over the
      whole run rather than per chunk: the sweep carries its running maxima from chunk to
      chunk, so a member fails with `Status.ENERGY_JUMP` at the step `integrate` would report.

    **Returns:** a `SweepResult`.

    What is batched (by `clebsch_jax.batch`, with `jax.vmap`'s meaning): `params` rows (so the
    system's array leaves — inertias, circulations, widths — are traced), `Q0`, `xi0`, `P0` and
    `dt`. What is static: `make_system` itself, the Python callables inside the system,
    `invariants`, `options`, `n_steps`, `chunk_steps`, `save_every`: changing them recompiles,
    changing array values does not.
    """
    run = _check_run(n_steps, grid, options, chunk_steps, save_every, member_chunk, invariants, progress, devices)
    if store is not None or client is not None or overwrite is not False:
        from .store import check_arguments

        check_arguments(store, client, overwrite)
    if not (isinstance(fast, bool) or (isinstance(fast, str) and fast == "auto")):
        raise ValueError(f"fast: expected True, False or 'auto', got {fast!r}.")
    backend = _check_backend(backend)
    if fast != "auto":
        warnings.warn(
            "sweep: fast= is deprecated; it chooses among XLA's paths, and implies backend='xla' "
            "(the default backend='auto' runs native kernels where they apply).",
            DeprecationWarning,
            stacklevel=2,
        )
        if backend == "native":
            raise ValueError("fast: chooses among XLA's paths; it cannot be combined with backend='native'.")
        backend = "xla"
    members = _members(make_system, params, Q0, xi0, P0, dt, grid)
    _check_size(run, members)
    B, n_dev = members.B, len(run.devices)
    n_threads = _threads(threads, run.devices, B)  # checked also where a Dask client's tasks take 1
    run = run._replace(threads=n_threads if client is None else 1)
    cfg = _particle_defaults(_chunk_config(run, members, options), members)
    _check_first_member(cfg, members)  # integrate's checks that need values, before any trace
    fast, batch_size, backend = _resumed(fast, batch_size, store, overwrite, backend)
    if batch_size is not None:
        batch_size = _positive_int(batch_size, "batch_size")
    shapes, general = None, cfg
    if backend != "xla":
        cfg, shapes = _native_config(cfg, run, members, backend)
    if not cfg.native and (fast is True or (fast == "auto" and _auto_lean(B, run.n_steps))):
        shapes = _probe(cfg, members, lean=True)  # the member checked before a method is chosen on it
        method = _fast_method_of(cfg, members)
        lean = _lean_applies(cfg, members, method)
        if fast is True or lean:  # "auto" takes the fast path only as the lean chunk
            cfg = dataclasses.replace(cfg, fast_method=method, lean=lean)
    if not (cfg.lean or cfg.native):  # the general chunk's shapes, from a trace of its march (cached by `general`)
        shapes = _probe(general, members)
    if batch_size is None:  # every device, and every thread of each, gets a batch
        per_slot = -(-B // (n_dev * run.threads))
        if cfg.lean or cfg.native:  # batches of equal size (no padded members), at most _DEFAULT_BATCH_LEAN
            batch_size = -(-per_slot // -(-per_slot // _DEFAULT_BATCH_LEAN))
        else:
            batch_size = min(per_slot, _DEFAULT_BATCH)
    batch_size = min(_positive_int(batch_size, "batch_size"), B)  # more would only run padding
    tables = _allocate_tables(B, shapes, run)

    # groups of batches (one batch per device and thread) × chunks
    n_batches = -(-B // batch_size)
    report = _reporter(run.progress, n_batches, run.n_steps, B, batch_size)
    plan = _Plan(cfg, members, shapes, run._replace(progress=False, devices=[None]), batch_size)
    if store is not None or client is not None:
        from . import store as _store  # zarr, dask: the optional extra [sweep]

        return _store.run_stored(
            plan, run, tables, store=store, client=client, overwrite=overwrite, report=report, make_result=_result
        )
    used, chunks, slots = set(), np.zeros(3, int), run.slots
    for g in range(0, n_batches, len(slots)):
        rows = _run_batches(plan, list(range(g, min(g + len(slots), n_batches))), slots, report)
        used.update(rows.devices)
        chunks += rows.fast_chunks
        _place(tables, rows.tables, rows.rows)
    if run.progress is True:
        print(file=sys.stderr, flush=True)
    return _result(plan, tables, len(used), chunks)


def _result(plan: "_Plan", tables: _Tables, n_devices: int, chunks=(0, 0, 0)) -> SweepResult:
    """The `SweepResult` of a plan's filled-in tables; `chunks`: (fast chunks, fallback chunks,
    fallback member-chunks) of the fast path in this process (zeros for a stored or Dask run,
    which do not count them)."""
    members, run = plan.members, plan.run
    return SweepResult(
        param_index=members.param_index,
        ic_index=members.ic_index,
        energy_error=tables.drift["energy"],
        drift=tables.drift,
        initial=tables.initial,
        saved=tables.saved,
        n_steps=run.n_steps,
        chunk_steps=run.chunk_steps,
        batch_size=plan.batch_size,
        n_devices=n_devices,
        **tables.columns,
        **plan.shapes.facts,
        fast_chunks=int(chunks[0]),
        fallback_chunks=int(chunks[1]),
        fallback_member_chunks=int(chunks[2]),
    )
