r"""A sweep's table in a Zarr (v3) store, written batch by batch: resumable, readable by xarray.

`cj.sweep(..., store=path)` creates the store (or reopens it), then writes each batch's rows
as soon as the batch is finished. The arrays and the configuration it holds are
`clebsch_jax.batching.store_layout`'s. `xarray.open_zarr(path)` is the analysis entry point and
`cj.open_sweep(path)` gives the `SweepResult` back (`clebsch_jax.batching.store_read`).

**Resume.** The attribute `clebsch_jax_sweep` holds the sweep's configuration: the method and
its options (`check_energy` as asked), `n_steps`, `batch_size`, `chunk_steps`, `save_every`, the
invariants' names, the model, the number of members, a SHA-256 of every input array
(parameters, `Q0`, `xi0`, `P0`, `dt`), a SHA-256 of one member's traced program
(`program_digest`: the bodies of the model and the invariants, every option), and the package
and JAX versions. Running a sweep with an existing store compares them:
a difference is refused (`SweepStoreError` naming the store and the differing entries) unless
`overwrite=True`, which starts the store afresh. With the same configuration, every batch whose
`batch_done` flag is set is skipped. The flag is written after the batch's data, so a process
killed at any instant leaves either a batch marked done with all its data, or one not marked
done, which the next run computes again.

**Nothing we did not write is removed.** A new store gets the attribute `written_by` first;
a store is recognised as a sweep's by it or by its configuration. A path that exists and is not
one — a file, a folder of other files (`.` included), a Zarr group of other data — is refused
naming it, with or without `overwrite`; so is a store whose root metadata cannot be read (it is
reported as damaged, and left as it is). An empty folder, an empty group, and a store of ours
whose creation was interrupted (no configuration yet, hence no result) are (re)created — unless
the process creating it (`created_by`: host and process id) may still be running, which is
refused naming it. One process writes a store at a time (`locked`: the writer lock of
`clebsch_jax.batching.store_lock`, on local folders); a second is refused naming the first.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import sys
import warnings

import numpy as np

from .store_layout import (
    ATTR,
    COLUMNS,
    OWNER,
    OWNER_VALUE,
    SAVED,
    chunk_problem,
    configuration,
    fill,
    inputs,
    invariant_keys,
    variables,
    write_inputs,
    written_by_batches,
)
from .store_lock import LOCK_NAME, SweepStoreError, may_run, writer_lock

__all__ = ["SweepStoreError"]

_EXTRA = 'pip install "clebsch-jax[sweep]"'


def zarr_module():
    """The `zarr` package (v3), or an ImportError naming the extra that installs it."""
    try:
        import zarr
    except ImportError:
        raise ImportError(f"store=: writing a sweep to Zarr needs the zarr package (v3): {_EXTRA}") from None
    if int(zarr.__version__.split(".")[0]) < 3:
        raise ImportError(f"store=: needs zarr >= 3 (found {zarr.__version__}): {_EXTRA}")
    return zarr


def store_name(store) -> str:
    """How errors name a store: its path, or its repr."""
    if isinstance(store, str):
        return store
    try:
        return os.fspath(store)
    except TypeError:
        return repr(store)


def _plain(store):
    """A path-like store as a str (what zarr accepts); other stores unchanged."""
    return os.fspath(store) if isinstance(store, os.PathLike) else store


def _create(zarr, store, plan, config: dict):
    path, mode = _local_path(store), "w"
    if path is not None and os.path.isdir(path):  # new or ours (`_inspect`): emptied but for the writer lock
        for entry in os.listdir(path):
            full = os.path.join(path, entry)
            if entry != LOCK_NAME:
                shutil.rmtree(full) if os.path.isdir(full) and not os.path.islink(full) else os.remove(full)
        mode = "a"
    with zarr.config.set({"array.write_empty_chunks": True}):
        # the owner first, in the group's own metadata: a store whose creation is interrupted is ours
        return fill(
            zarr.open_group(_plain(store), mode=mode, attributes={OWNER: OWNER_VALUE, "created_by": _creator()}),
            plan,
            config,
        )


def open_group(zarr, store, mode: str):
    """The store's root group, opened as it is; a `SweepStoreError` naming the store if it cannot be."""
    try:
        # the arrays as they are (a consolidated copy of their metadata would hide a missing one)
        return zarr.open_group(_plain(store), mode=mode, use_consolidated=False)
    except Exception as err:  # zarr raises several kinds for a missing or unreadable group
        raise SweepStoreError(
            f"store {store_name(store)!r}: not a readable Zarr group ({type(err).__name__}: {err})."
        ) from err


def stored_configuration(store) -> dict | None:
    """The configuration of the sweep stored in `store` (`configuration`, as read back); None
    where there is none (nothing yet, or not a sweep's store)."""
    try:
        stored = zarr_module().open_group(_plain(store), mode="r").attrs.get(ATTR)
    except Exception:  # nothing there: the sweep creates it (open_for_run reports other problems)
        return None
    return stored if isinstance(stored, dict) else None


def _local_path(store) -> str | None:
    """The local directory of a path-like store; None for a `zarr` store object or a URL."""
    if isinstance(store, os.PathLike) or (isinstance(store, str) and "://" not in store):
        return os.fspath(store)
    return None


def _is_empty(zarr, store) -> bool:
    """Whether a `zarr` store object (or URL) holds no key at all."""
    from zarr.core.sync import sync

    if isinstance(store, str):
        store = zarr.storage.FsspecStore.from_url(store, read_only=True)
    return sync(store.is_empty(""))


def _inspect(zarr, store):
    """What `store` holds: ("new", None) when there is nothing to keep (no such path, an empty
    folder or store, an empty group), ("ours", root) for a sweep store, ("unfinished", root)
    for one whose creation was interrupted (it holds no result yet). Anything else is refused
    with a `SweepStoreError` naming it, and nothing is written or removed: a file, a folder or
    store that is not a Zarr group, a Zarr group written by something else, a store whose root
    metadata cannot be read."""
    name = store_name(store)
    path = _local_path(store)
    keep = "Nothing was written or removed; give a new path (or an empty folder)."
    if path is not None:
        if os.path.lexists(path) and not os.path.isdir(path):
            raise SweepStoreError(f"store {name!r}: is a file, not a folder: a sweep store is a Zarr folder. {keep}")
        if not os.path.isdir(path):
            return "new", None
        entries = sorted(e for e in os.listdir(path) if e != LOCK_NAME)  # the lock: `locked`
        if not entries:
            return "new", None
        if "zarr.json" not in entries:
            shown = ", ".join(entries[:5]) + (f" and {len(entries) - 5} more" if len(entries) > 5 else "")
            raise SweepStoreError(f"store {name!r}: is a folder that is not a Zarr store (it holds {shown}). {keep}")
    else:
        try:
            empty = _is_empty(zarr, store)
        except Exception:  # a store that cannot be listed: opening it below says what is wrong
            empty = False
        if empty:
            return "new", None
    try:
        root = zarr.open_group(_plain(store), mode="r", use_consolidated=False)
        attrs = root.attrs.asdict()
    except Exception as err:  # zarr raises several kinds for unreadable metadata
        raise SweepStoreError(
            f"store {name!r}: damaged or not a Zarr group: its root metadata (zarr.json) cannot be read "
            f"({type(err).__name__}: {err}). Nothing was removed, also not with overwrite=True (a store whose "
            "metadata cannot be read is not recognised as a sweep's); move or delete it yourself, or give "
            "another path."
        ) from err
    if ATTR in attrs:
        if not isinstance(attrs[ATTR], dict):
            raise SweepStoreError(
                f"store {name!r}: damaged: its attribute {ATTR!r} is not a configuration "
                f"(got {type(attrs[ATTR]).__name__}). Nothing was removed."
            )
        return "ours", root
    if attrs.get(OWNER) == OWNER_VALUE:
        creator = _live_creator(attrs.get("created_by"))
        if creator is not None:  # another process is creating it now: recreating it would wipe its work
            raise SweepStoreError(
                f"store {name!r}: is being created by {creator}. Wait for it to finish, then run "
                "the same sweep again to resume the store, or give another path. "
                "If that process is gone, delete the store yourself."
            )
        return "unfinished", root
    if not attrs and not list(root.keys()) and (path is None or entries == ["zarr.json"]):
        return "new", None  # an empty group: nothing to keep
    raise SweepStoreError(
        f"store {name!r}: is a Zarr group not written by clebsch_jax.sweep (no attribute {ATTR!r}). {keep}"
    )


def _creator() -> dict:
    """Who creates a store (its attribute `created_by`): host and process."""
    import socket

    return {"host": socket.gethostname(), "pid": os.getpid()}


def _live_creator(created_by) -> str | None:
    """'process N on host H' when the process that began creating a store may still be running
    (alive on this host, or on another host, where that cannot be checked); None when it is
    this process or gone."""
    if not isinstance(created_by, dict):
        return None
    me = _creator()
    host, pid = created_by.get("host"), created_by.get("pid")
    if host == me["host"] and (pid == me["pid"] or not may_run(created_by)):
        return None
    return f"process {pid} on host {host}"


@contextlib.contextmanager
def locked(store):
    """Hold the store's writer lock (`clebsch_jax.batching.store_lock`; local folders only) for
    the `with` block, after refusing a path that is not a sweep's store (nothing is written into
    it, not even the lock)."""
    _inspect(zarr_module(), store)
    with writer_lock(_local_path(store), store_name(store)) as me:
        yield me


def open_for_run(store, plan, overwrite: bool):
    """The store of this sweep: created, or reopened after checking its configuration. Only a
    store recognised as a sweep's (`_inspect`) is ever replaced, and only with `overwrite`."""
    zarr = zarr_module()
    config = json.loads(json.dumps(configuration(plan)))  # as it reads back (tuples become lists)
    name = store_name(store)
    state, root = _inspect(zarr, store)
    if state == "ours" and not overwrite:
        stored = root.attrs[ATTR]
        diff = sorted(k for k in set(stored) | set(config) if stored.get(k) != config.get(k))
        if diff:
            shown = "; ".join(f"{k}: stored {stored.get(k)!r}, this sweep {config.get(k)!r}" for k in diff[:4])
            why = (
                " One member's traced program differs: the body of make_system, of the system's maps or of an "
                "invariant, an integrate option, or the engine or JAX version."
                if "program_sha256" in diff
                else ""
            )
            raise SweepStoreError(
                f"store {name!r} was written by another sweep configuration ({shown}).{why} Use "
                "another store, or overwrite=True to replace it."
            )
        root = open_group(zarr, store, "r+")
        _check_layout(root, plan, name)
        return root
    try:
        return _create(zarr, store, plan, config)
    except OSError as err:  # e.g. a read-only file system, no permission
        raise SweepStoreError(f"store {name!r}: cannot be written ({err.strerror or err}).") from err


def _check_layout(root, plan, name: str):
    """Every array the configuration implies is there with its shape: else a clear error."""
    have = set(root.array_keys())
    for var, (_, shape, _, _) in variables(plan).items():
        if var not in have:
            raise SweepStoreError(
                f"store {name!r}: the array {var!r} is missing (a truncated or corrupted store); "
                "pass overwrite=True to start it afresh."
            )
        if tuple(root[var].shape) != tuple(shape):
            raise SweepStoreError(
                f"store {name!r}: the array {var!r} has shape {tuple(root[var].shape)}, expected "
                f"{tuple(shape)} (a corrupted store); pass overwrite=True to start it afresh."
            )


def done_batches(root, name: str) -> np.ndarray:
    """Which batches the store marks done; a flag that cannot be read (a damaged chunk) counts
    as not done, so its batch is computed again."""
    flags = root["batch_done"]
    try:
        return np.asarray(flags[:], bool)
    except Exception:  # a damaged flag: read them one by one (each is a chunk of its own)
        done = np.zeros(flags.shape, bool)
        for b in range(flags.shape[0]):
            try:
                done[b] = bool(flags[b])
            except Exception:  # codecs raise many kinds
                print(
                    f"sweep: store {name!r}: the done flag of batch {b} is damaged: computing the batch again.",
                    file=sys.stderr,
                    flush=True,
                )
        return done


def damaged_batches(root, batches, bs: int) -> dict:
    """{batch: (array, what is wrong)} of the given batches whose data cannot be read back."""
    found = {}
    for var in written_by_batches(root):
        for b in batches:
            if b not in found:
                problem = chunk_problem(root, var, b, bs)
                if problem is not None:
                    found[b] = (var, problem)
    return found


def repair(root, plan, done: np.ndarray, name: str) -> np.ndarray:
    """A reopened store checked chunk by chunk: a batch marked done whose data cannot be read
    back (a checksum mismatch, a missing or truncated chunk) is marked not done, with a message,
    so this run computes it again; a damaged chunk of the inputs written at creation is written
    again (the configuration check has shown they are the same). Returns the batches done."""
    bs = plan.batch_size
    damaged = damaged_batches(root, np.flatnonzero(done).tolist(), bs)
    for b, (var, problem) in sorted(damaged.items()):
        rows = plan.rows(b)
        print(
            f"sweep: store {name!r}: batch {b} (members {rows.start}-{rows.stop - 1}) is "
            f"damaged ({var!r}: {problem}): computing it again.",
            file=sys.stderr,
            flush=True,
        )
        root["batch_done"][b] = False
        done[b] = False
    broken = []
    for var in inputs(plan):
        try:
            root[var][...]
        except Exception:  # codecs raise many kinds
            broken.append(var)
    if broken:
        print(
            f"sweep: store {name!r}: the input arrays {', '.join(broken)} are damaged: written again.",
            file=sys.stderr,
            flush=True,
        )
        write_inputs(root, plan, broken)
    return done


def write_rows(root, plan, rows, run_id: int):
    """Write finished batches (a `schedule.Rows`) into the store: data first, then each batch's flags."""
    shapes = plan.shapes
    keys = invariant_keys(shapes)
    part = rows.tables
    arrays = {k: part.columns[k] for k in COLUMNS if part.columns[k] is not None and k != "status"}
    for name, key in keys.items():
        arrays[f"initial_{key}"] = part.initial[name]
        if name != "energy":
            arrays[f"drift_{key}"] = part.drift[name]
    arrays["energy_error"] = part.drift["energy"]
    if part.saved is not None:
        arrays.update({f"saved_{k}": part.saved[k] for k in SAVED if part.saved[k] is not None})
    arrays["status"] = part.columns["status"]  # the last data: a member with a status has all its data
    start = 0
    spans = []
    for r in rows.rows:
        n = r.stop - r.start
        spans.append((r, slice(start, start + n)))
        start += n
    # every chunk written, even one that equals the fill value: a missing chunk means a truncated store
    with zarr_module().config.set({"array.write_empty_chunks": True}):
        for var, data in arrays.items():
            target = root[var]
            for r, local in spans:
                target[r] = data[local]
    for b in rows.batches:
        root["batch_run"][b] = run_id
        root["batch_done"][b] = True  # last: the batch counts as done only with all its data written


def start_run(root, store) -> int:
    """The number of this run of the sweep on the store (1, 2, …), recorded in its attributes.
    Then the metadata are consolidated (every array's in the root's), so that `xarray.open_zarr`
    opens the store without a warning, interrupted or not: nothing changes them later in the run
    (the arrays' metadata never change, the root's attributes only here)."""
    run_id = int(root.attrs.get("runs", 0)) + 1
    root.attrs["runs"] = run_id
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Consolidated metadata is currently not part")
        zarr_module().consolidate_metadata(_plain(store))
    return run_id


def check_arguments(store, overwrite) -> None:
    """`sweep`'s `store` and `overwrite`, checked before anything is traced or compiled (zarr
    named with the extra that installs it)."""
    if overwrite not in (True, False):
        raise ValueError(f"overwrite: expected True or False, got {overwrite!r}.")
    if overwrite and store is None:
        raise ValueError("overwrite: True replaces a store, but no store= was given.")
    if store is not None:
        zarr = zarr_module()
        if isinstance(store, (str, bytes)) and not store:
            raise ValueError("store: expected a path or a zarr store, got an empty string.")
        _inspect(zarr, store)  # a path that is not a sweep store of ours is refused here already
