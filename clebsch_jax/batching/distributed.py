r"""A sweep's batches as Dask tasks: `cj.sweep(..., client=distributed.Client(...))`.

The sweep is planned where `sweep` is called (inputs checked, one member's shapes probed, the
store created), then every batch still to do becomes one task on the client's cluster — a
`LocalCluster` of processes on one machine, or any cluster with a scheduler address (SLURM or
PBS through dask-jobqueue, Kubernetes, cloud). A task runs the very function an in-process
sweep runs for a batch (`clebsch_jax.batching.schedule.run_batches`: the same compiled program on
the same padded inputs), so the table is identical to the bit.

**Compile once per worker.** The static part of the plan (configuration, shapes, options) is
scattered to the workers once; a worker keeps the first copy it sees in `_PLANS`, keyed by the
sweep's token, so every task on it passes the same static configuration to `jax.jit`, which
then reuses the program compiled by the worker's first task. A task carries only its own
batch's inputs (`_batch_members`), so the sweep's whole input is never sent to every worker. `make_system` should be a module-level function
(pickled by reference); the plan must be picklable by cloudpickle.

**Workers that die.** With a store, a task writes its batch to the store (data, then the
batch's done flag) and returns its index; without one, it returns the rows. Dask reruns the
task of a worker that died on another worker (up to the scheduler's `allowed-failures`), and
rewriting a batch writes the same bytes, so nothing is lost or doubled. If the whole sweep is
stopped, a stored sweep resumes from its store.
"""

from __future__ import annotations

import sys
import time
import uuid

import numpy as np

from .schedule import Plan, batch_rows, run_batches
from .store import open_group, store_name, write_rows, zarr_module
from .tables import SweepProgress

__all__ = ["run_on_client", "check_client", "worker_environment", "SINGLE_THREAD_XLA_FLAGS"]

_PLANS: dict = {}  # token -> (cfg, shapes, run, batch_size), per worker: one static configuration per sweep


SINGLE_THREAD_XLA_FLAGS = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
"""XLA's CPU flags for one intra-op thread: a sweep's task runs its batch on one host thread
(`threads=1`), so a worker with one Dask thread should not start XLA threads on other cores."""


def worker_environment(environ=None) -> dict:
    """The environment of a single-threaded sweep worker: `environ` (default `os.environ`) with
    XLA's CPU work on one thread (`SINGLE_THREAD_XLA_FLAGS` added to `XLA_FLAGS`) and one
    OpenMP/BLAS thread. `clebsch-jax sweep --workers N` starts its local workers with it; for a
    deployment of your own, start each `dask worker --nthreads 1` in it (the sweeps how-to)."""
    import os

    env = dict(os.environ if environ is None else environ)
    flags = env.get("XLA_FLAGS", "")
    if "intra_op_parallelism_threads" not in flags:
        env["XLA_FLAGS"] = f"{flags} {SINGLE_THREAD_XLA_FLAGS}".strip()
    for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        env.setdefault(name, "1")
    return env


def _batch_members(members, b: int, batch_size: int):
    """Batch b's members alone, as members 0, 1, … of their own: the rows of `params`, `Q0`,
    `xi0`, `P0` and `dt` they use. Run as batch 0 they give the very inputs batch b gets in the
    whole sweep (the last batch is padded with copies of its last member, the sweep's last), so
    a task carries its batch's inputs only, not the whole sweep's."""
    import jax

    idx = np.arange(members.B)[batch_rows(b, batch_size, members.B)]
    ic, n = members.ic_index[idx], len(idx)
    params = members.params
    if members.builder is not None:
        params = jax.tree_util.tree_map(lambda a: a[members.param_index[idx]], params)
    return members._replace(
        params=params,
        Q0=members.Q0[ic],
        xi0=members.xi0[ic],
        P0=None if members.P0 is None else members.P0[ic],
        n_ic=n,
        param_index=np.arange(n) if members.builder is not None else np.zeros(n, int),
        ic_index=np.arange(n),
        dt=members.dt[idx],
    )


def _batch_task(static, token: str, b: int, members, store, run_id: int):
    """Batch b on a worker (`members`: its own, `_batch_members`): its rows, written to `store`
    (returns b) or returned."""
    cfg, shapes, run, bs = _PLANS.setdefault(token, static)  # the first copy: one jit cache entry
    plan = Plan(cfg, members, shapes, run, bs)
    rows = run_batches(plan, [0], [None], lambda group, step: None)
    n = members.B
    # its rows of the whole table; devices do not pickle (the result counts one)
    rows = rows._replace(batches=[b], rows=[slice(b * bs, b * bs + n)], devices=set())
    if store is None:
        return rows
    write_rows(open_group(zarr_module(), store, "r+"), plan, rows, run_id)
    return b


class ClientClosedError(RuntimeError):
    """The Dask client of a sweep was closed while the sweep ran (`client.close()`)."""


def _closed_message(store, done: int, B: int) -> str:
    if store is None:
        return (
            f"sweep: the Dask client was closed during the run ({done} of {B} members done, kept in memory "
            "only, and lost). Run the sweep again with an open client; pass store=PATH to make a run "
            "resumable."
        )
    return (
        f"sweep: the Dask client was closed during the run; the store {store_name(store)!r} holds the batches "
        f"finished so far (at least {done} of {B} members). It can be resumed: run the same sweep again with the same "
        "store (with an open client, or none), and the written batches are skipped."
    )


def check_client(client):
    try:
        from distributed import Client
    except ImportError:
        raise ImportError(
            'client=: running a sweep on Dask needs dask.distributed: pip install "clebsch-jax[sweep]"'
        ) from None
    if not isinstance(client, Client):
        raise ValueError(f"client: expected a dask.distributed.Client, got {type(client).__name__}.")


def run_on_client(client, plan, batches: list, store, run_id: int, progress):
    """Submit `batches` as tasks; yield each task's result as it finishes (rows, or the batch
    index when written to `store`). `progress` (as `sweep`'s) hears of each finished batch.
    Stopping the generator (or Ctrl-C) cancels the tasks not yet finished."""
    from distributed import as_completed

    B, bs, n_steps = plan.members.B, plan.batch_size, plan.run.n_steps
    n_batches = plan.n_batches
    token = uuid.uuid4().hex
    # the static part once per worker (broadcast): deserialised once, so its functions keep their
    # identity and jax.jit compiles once per worker; each task carries its own batch's inputs
    [static] = client.scatter([(plan.cfg, plan.shapes, plan.run, bs)], broadcast=True, hash=False)
    futures = [
        client.submit(
            _batch_task,
            static,
            token,
            b,
            _batch_members(plan.members, b, bs),
            store,
            run_id,
            pure=False,
            key=f"clebsch-jax-sweep-{token}-batch-{b}",
        )
        for b in batches
    ]
    start, done = time.perf_counter(), B - sum(plan.size(b) for b in batches)
    try:
        for future in as_completed(futures):
            result = future.result()
            b = result if isinstance(result, int) else result.batches[0]
            done += plan.size(b)
            info = SweepProgress(b, n_batches, n_steps, n_steps, done, B, time.perf_counter() - start)
            if progress is True:
                print(
                    f"\rsweep: batch {b + 1}/{n_batches} done, {done}/{B} members done, {info.elapsed:.1f} s",
                    end="",
                    file=sys.stderr,
                    flush=True,
                )
            elif progress is not False:
                progress(info)
            yield result
    except Exception as err:  # distributed raises ClosedClientError, or CancelledError for the tasks
        if client.status not in ("closing", "closed"):
            raise
        raise ClientClosedError(_closed_message(store, done, B)) from err
    finally:
        if client.status not in ("closing", "closed"):
            client.cancel([f for f in futures if not f.done()])
        if progress is True:
            print(file=sys.stderr, flush=True)
