r"""A sweep's table: `SweepResult`, one row per member, filled in on the host batch by batch.

`Tables` holds the columns while the sweep runs (`allocate_tables`); `collect` copies a
finished batch's carry into its rows, `place` a group's rows into the sweep's, and `result`
makes the `SweepResult`. `SweepProgress` is what a `progress` callback receives.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import numpy as np

from ..march.solution import IntegrationError
from ..roots.status import Status
from .config import Run
from .probe import Shapes


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
    - `accuracy_plan`: the `AccuracyPlan` of a sweep run with `accuracy=` (piloted on a sample
      of its members, `accuracy_plan.piloted`: `clebsch_jax.choose_sweep_step`); None otherwise.
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
    accuracy_plan: object = None

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
        "accuracy_plan",
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


@dataclasses.dataclass(frozen=True)
class Tables:
    """The sweep's table on the host, filled in group by group of batches."""

    columns: dict  # SweepResult's per-member fields, from status to final_momentum (None: not produced)
    initial: dict  # {invariant: (B, …)}
    drift: dict  # {invariant: (B,)}
    saved: dict | None  # SweepResult.saved


def allocate_tables(B: int, shapes: Shapes, run: Run) -> Tables:
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
    return Tables(columns, initial, drift, saved)


_STATE = ("final_Q", "final_p", "final_xi", "final_momentum")
"""The columns of a member's final state, NaN for a failed member."""


def collect(tables: Tables, one, run: Run):
    """A finished batch's carry into its rows of the host tables."""
    host = jax.device_get(one.carry)
    take = lambda a: np.asarray(a)[: one.n_real]
    failed = np.asarray(host.status) != Status.SUCCESS
    # a failed member's final state is NaN (after a jump the chunk's march ran on): written over
    # its copied row, not through a NaN-filled copy of the whole batch
    lost = np.flatnonzero(take(failed)) + one.rows.start if failed.any() else None
    final = {
        "status": host.status,
        "failed_step": host.failed_step,
        "newton_iterations": host.iterations,
        "max_residual": host.max_residual,
        "final_t": host.t,
        "final_Q": host.Q,
        "final_p": host.P,
        "final_xi": host.final_xi,
        "final_momentum": host.momentum,
    }
    for key, column in tables.columns.items():
        if column is not None:
            column[one.rows] = take(final[key])
            if lost is not None and key in _STATE:
                column[lost] = np.nan
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


def place(tables: Tables, part: Tables, rows: list):
    """Copy a `Rows` table `part` (its batches' rows one after the other) into `tables`."""

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


def result(plan, tables: Tables, n_devices: int, chunks=(0, 0, 0)) -> SweepResult:
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
