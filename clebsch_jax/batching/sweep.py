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
$(Q^n, p^n)$ (`continue_from`) continues the same trajectory, and each chunk also continues the
last one's march state (`Solution.march_state`: the stepper's guesses, the predictor's history),
so its steps are solved from the guesses of the unbroken run: a member's steps, updates and
statuses do not depend on `chunk_steps` (`tests/test_sweep_agreement.py`). The fast and lean
paths restart their guesses at each chunk (only round-off differs there). Chunks of tens of
steps or more keep the cost of a call small against the steps; the measurements behind
the default chunk size are in `benchmarks/README.md` ("Measurements behind the engine's
choices").

This module is the entry point: `sweep` checks its arguments in order and runs the plan. The
layers below it (`docs/architecture.md`): `config` (options, members, the static configuration),
`probe` (the first member checked and traced), `choose` (the path: backend, fast path, batch
size, with `AUTO_MAX_IR_LINES`, `AUTO_LEAN_MIN_MEMBERS`, `AUTO_LEAN_MIN_MEMBER_STEPS`),
`chunks_xla` and `chunks_native` (a chunk of a batch), `schedule` (batches on devices and
threads, reruns, progress, with `LEAN_CHUNKS`, `FALLBACK_BATCH`, `FAST_GIVE_UP`, `THREADS_MAX`,
`THREAD_MIN_MEMBERS`), `tables` (`SweepResult`), `store` and `distributed`.
"""

from __future__ import annotations

import dataclasses
import sys
import warnings

import numpy as np

from ..core.validation import positive_int
from . import choose, probe, schedule
from .backends import check_backend
from ..march.accuracy import METHOD_OPTIONS, require_step
from .config import chunk_config, check_run, check_size, make_members, whole_run_chunks
from .ensemble_plan import plan_for_sweep
from .schedule import Plan, run_batches
from .tables import SweepProgress, SweepResult, allocate_tables, place, result

__all__ = ["sweep", "SweepResult", "SweepProgress"]


def sweep(
    make_system,
    params,
    Q0,
    xi0,
    *,
    dt=None,
    n_steps: int | None = None,
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
    t_final=None,
    accuracy=None,
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
      `clebsch_jax.march.carry.input_ok`).
    - `dt`: the time step, a positive scalar or one per member, shape (B,).
    - `n_steps`: steps per member (an int >= 1).
    - `t_final`, `accuracy`: instead of `dt` and `n_steps` (and the method options): one
      plan (`clebsch_jax.choose_sweep_step`), its pilot run on the first member and the
      `PILOT_MEMBERS` − 1 others that move fastest relative to their size, its step the one the
      worst of them allows, run by every member; `SweepResult.accuracy_plan` records it and
      which members were piloted (`piloted`). The other members' errors are not measured
      (`clebsch_jax.batching.ensemble_plan` says what the sample sees and what not).
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
      `save_every`; on the native backend without `progress`, `store` or `client`: n_steps,
      one kernel call per batch, `config.whole_run_chunks`). Memory is about
      `batch_size · chunk_steps` nodes on XLA's general path; a chunk size that divides
      `n_steps` compiles one program there (otherwise a second one for the last chunk). The
      native kernel takes a chunk's steps as an argument: one kernel for every `chunk_steps`
      and `n_steps`. Chunks of tens of steps cost little over one unchunked run (see
      `clebsch_jax.batching.sweep`).
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
      the bit. A store written by another configuration is refused (`clebsch_jax.batching.store`),
      and so is a local store another live process is writing (its writer lock names it:
      `clebsch_jax.batching.store_lock`). Needs the optional extra `pip install "clebsch-jax[sweep]"`.
    - `client`: None, or a `dask.distributed.Client`: batches run as Dask tasks on its workers
      (a `LocalCluster` of processes, or any cluster with a scheduler address), each worker
      compiling the batch program once; with `store`, workers write their batches to it (it must
      be reachable from every worker). A task whose worker dies is rerun by Dask elsewhere.
      The table is identical to the bit to the in-process one (`clebsch_jax.batching.distributed`).
      A client closed during the run stops it with a `RuntimeError` that says whether and how it
      can be resumed (with `store`: run the same sweep again).
    - `overwrite`: with `store`, replace a store written by another configuration instead of
      refusing it (never one that another live process is writing).
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
      one. `check_energy` (default True; or a positive tolerance, as in `integrate`) is
      `integrate`'s energy check made over the
      whole run rather than per chunk: the sweep carries its running maxima from chunk to
      chunk, so a member fails with `Status.ENERGY_JUMP` at the step `integrate` would report;
      with it, the first chunk makes `integrate`'s first-step check (two half steps from the
      start: `Status.FIRST_STEP` at step 0 for a spurious root), on both backends.
      A system whose Lagrangian does not see the isotropy of its velocity map (`integrate`
      fixes its gauge, `clebsch_jax.gauge_isotropy`) is gauged for every member as `integrate`
      gauges it: the rank found on the first member checked, each member's weight at its own
      (Q0, xi0), and, without `P0`, xi0 taken as its physical velocity; a member whose Q0 has
      another isotropy reports `Status.INVALID_INPUT`.

    **Returns:** a `SweepResult`.

    What is batched (by `clebsch_jax.batch`, with `jax.vmap`'s meaning): `params` rows (so the
    system's array leaves — inertias, circulations, widths — are traced), `Q0`, `xi0`, `P0` and
    `dt`. What is static: `make_system` itself, the Python callables inside the system,
    `invariants`, `options`, `n_steps`, `chunk_steps`, `save_every`: changing them recompiles
    XLA's programs (not the native kernel, which takes the steps as an argument), changing
    array values does not.
    """
    if accuracy is not None or t_final is not None:  # one plan for all members, piloted on a sample of them
        given = dict(options, dt=dt, n_steps=n_steps)
        arguments = dict(t_final=t_final, accuracy=accuracy, check_energy=options.get("check_energy", True))
        plan = plan_for_sweep(make_system, params, Q0, xi0, P0, grid, given, **arguments, backend=backend)
        kept = {k: v for k, v in options.items() if k not in METHOD_OPTIONS}  # the stepper's fields now
        arguments = dict(grid=grid, invariants=invariants, chunk_steps=chunk_steps, batch_size=batch_size)
        arguments.update(save_every=save_every, member_chunk=member_chunk, devices=devices, progress=progress)
        arguments.update(store=store, client=client, overwrite=overwrite, fast=fast, threads=threads, backend=backend)
        res = sweep(make_system, params, Q0, xi0, P0=P0, **arguments, **kept, **plan.integrate_options())
        return dataclasses.replace(res, accuracy_plan=plan)
    require_step(dt, n_steps)
    run = check_run(n_steps, grid, options, chunk_steps, save_every, member_chunk, invariants, progress, devices)
    if store is not None or client is not None or overwrite is not False:
        from .store import check_arguments

        check_arguments(store, overwrite)
        if client is not None:
            from .distributed import check_client

            check_client(client)
    if not (isinstance(fast, bool) or (isinstance(fast, str) and fast == "auto")):
        raise ValueError(f"fast: expected True, False or 'auto', got {fast!r}.")
    backend = check_backend(backend)
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
    members = make_members(make_system, params, Q0, xi0, P0, dt, grid)
    check_size(run, members)
    B = members.B
    n_threads = schedule.thread_count(threads, run.devices, B)  # checked also where a Dask client's tasks take 1
    run = run._replace(threads=n_threads if client is None else 1)
    cfg = choose.particle_defaults(chunk_config(run, members, options), members)
    # integrate's checks that need values, before any trace; the isotropy gauge integrate fixes
    cfg = dataclasses.replace(cfg, isotropy=probe.check_first_member(cfg, members))
    probe.warn_isotropic_xi0(cfg, members)
    fast, batch_size, backend = choose.resumed(fast, batch_size, store, overwrite, backend)
    if batch_size is not None:
        batch_size = positive_int(batch_size, "batch_size")
    shapes, general = None, cfg
    if backend != "xla":
        cfg, shapes = choose.native_config(cfg, run, members, backend)
    if cfg.native and store is None and client is None:  # a store keeps the length it records
        run = whole_run_chunks(run)
        cfg = dataclasses.replace(cfg, n=run.chunk_steps)
    if not cfg.native and (fast is True or (fast == "auto" and choose.auto_lean(B, run.n_steps))):
        shapes = probe.member_shapes(cfg, members, lean=True)  # the member checked before a method is chosen on it
        method = choose.fast_method_of(cfg, members)
        lean = choose.lean_applies(cfg, members, method)
        if fast is True or lean:  # "auto" takes the fast path only as the lean chunk
            cfg = dataclasses.replace(cfg, fast_method=method, lean=lean)
    if not (cfg.lean or cfg.native):  # the general chunk's shapes, from a trace of its march (cached by `general`)
        shapes = probe.member_shapes(general, members)
    batch_size = choose.batch_size(batch_size, B, run, cfg)
    tables = allocate_tables(B, shapes, run)

    # groups of batches (one batch per device and thread) × chunks
    n_batches = -(-B // batch_size)
    report = schedule.reporter(run.progress, n_batches, run.n_steps, B, batch_size)
    plan = Plan(cfg, members, shapes, run._replace(progress=False, devices=[None]), batch_size)
    if store is not None or client is not None:
        return _run_stored(plan, run, tables, store=store, client=client, overwrite=overwrite, report=report)
    rows = run_batches(plan, list(range(n_batches)), run.slots, report, table=tables)
    if run.progress is True:
        print(file=sys.stderr, flush=True)
    return result(plan, tables, len(rows.devices), rows.fast_chunks)


def _run_stored(plan: Plan, run, tables, *, store, client, overwrite: bool, report) -> SweepResult:
    """`sweep` with `store=` and/or `client=`: the batches a store holds are skipped, the others
    run here (each group's rows written to the store from a writer thread while the next group
    computes) or as Dask tasks (`clebsch_jax.batching.distributed`), which write their own."""
    from . import store as stores  # zarr, dask: the optional extra [sweep]
    from .distributed import run_on_client

    n_batches = plan.n_batches
    if store is None:  # a Dask cluster, the table kept in memory
        chunks = np.zeros(3, int)
        for rows in run_on_client(client, plan, list(range(n_batches)), None, 0, run.progress):
            place(tables, rows.tables, rows.rows)
            chunks += rows.fast_chunks
        return result(plan, tables, 1, chunks)
    with stores.locked(store):  # one writer at a time (local folders), named to the others
        return _run_in_store(plan, run, tables, store, client, overwrite, report)


def _run_in_store(plan: Plan, run, tables, store, client, overwrite: bool, report) -> SweepResult:
    """`_run_stored`'s run, under the store's writer lock."""
    from concurrent.futures import ThreadPoolExecutor

    from . import store as stores
    from .distributed import run_on_client
    from .store_read import open_sweep

    n_batches = plan.n_batches
    name = stores.store_name(store)
    root = stores.open_for_run(store, plan, overwrite)
    done = stores.done_batches(root, name)
    if done.any():  # reopened: every chunk of the finished batches is read back (checksums)
        done = stores.repair(root, plan, done, name)
    pending = [b for b in range(n_batches) if not done[b]]
    if len(pending) < n_batches:
        skipped = plan.members.B - sum(plan.size(b) for b in pending)
        print(
            f"sweep: store {name!r}: skipped {skipped} of {plan.members.B} members already written "
            f"({n_batches - len(pending)} of {n_batches} batches); computing the other {len(pending)} batches.",
            file=sys.stderr,
            flush=True,
        )
    run_id = stores.start_run(root, store)
    if client is not None:
        for _ in run_on_client(client, plan, pending, store, run_id, run.progress):
            pass
        return open_sweep(store)
    # The table is kept in memory too. Leaving the `with` (also on Ctrl-C) waits for the writes under way.
    slots, used, chunks = run.slots, set(), np.zeros(3, int)
    with ThreadPoolExecutor(1, thread_name_prefix="clebsch-jax-sweep-store") as writer:
        writes = []
        for g in range(0, len(pending), len(slots)):
            rows = run_batches(plan, pending[g : g + len(slots)], slots, report)
            used.update(rows.devices)
            chunks += rows.fast_chunks
            place(tables, rows.tables, rows.rows)
            writes.append(writer.submit(stores.write_rows, root, plan, rows, run_id))
            for w in writes:
                if w.done():
                    w.result()  # a failed write stops the sweep now
        for w in writes:
            w.result()
    if run.progress is True:
        print(file=sys.stderr, flush=True)
    if len(pending) < n_batches:  # resumed: the skipped batches' rows are in the store only
        return open_sweep(store)
    return result(plan, tables, len(used), chunks)
