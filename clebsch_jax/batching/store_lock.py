r"""The writer lock of a sweep store on a local folder: one process writes a store at a time.

A sweep holds the file `LOCK_NAME` in the store's folder while it creates, checks and writes
the store (Dask workers write the batches of the process that holds it). The file names the
writer — host, process id, start time — and is created atomically (`O_CREAT | O_EXCL`), so of
two processes starting at once exactly one gets it. The other is refused with a
`SweepStoreError` naming the writer and the way out: wait for it (then run the same sweep again
to resume), give another path, or, for a writer on another host that is gone, delete the file.
A lock left by a process that no longer runs on this host (killed, say) is stale: the next sweep
takes it over, and resumes the store. Stores that are not local folders (a `zarr` store object,
a URL) are not locked.
"""

from __future__ import annotations

import contextlib
import datetime
import json
import os
import socket
import time
import warnings

__all__ = ["LOCK_NAME", "SweepStoreError", "may_run", "writer_lock", "writer_of"]

LOCK_NAME = "clebsch_jax_writer.lock"
"""The lock file, in the store's folder."""

UNREADABLE_WAIT = 0.2
"""Seconds to wait for a lock file that cannot be read as a writer (another process may be
writing it this instant) before taking it as damaged, hence stale."""


def _quiet_zarr() -> None:
    """zarr lists a folder's entries to find its members and warns about a file that is none:
    not about the lock (set where the lock is taken: a test runner resets the filters)."""
    warnings.filterwarnings("ignore", message=f"Object at {LOCK_NAME} is not recognized", category=UserWarning)


class SweepStoreError(ValueError):
    """A sweep store that cannot be used: another configuration, unfinished, truncated or
    corrupted, or written by another process now."""


def _me() -> dict:
    now = datetime.datetime.now(datetime.timezone.utc)
    return {"host": socket.gethostname(), "pid": os.getpid(), "started": now.isoformat(timespec="seconds")}


def _read(path: str) -> dict | None:
    try:
        with open(path) as f:
            found = json.load(f)
    except FileNotFoundError:
        return None
    except (OSError, ValueError):
        return {}
    return found if isinstance(found, dict) else {}


def writer_of(folder: str) -> dict | None:
    """The writer named by the lock file in `folder` (host, pid, started), {} for a file that
    cannot be read as one (being written, or damaged), None when there is no lock file."""
    return _read(os.path.join(folder, LOCK_NAME))


def may_run(writer: dict) -> bool:
    """Whether the writer (a dict with `host` and `pid`) may still run: True unless it is a
    process of this host that is gone (another host's processes cannot be checked)."""
    if writer.get("host") != socket.gethostname():
        return True
    pid = writer.get("pid")
    if not isinstance(pid, int) or pid <= 0:
        return False
    try:
        os.kill(pid, 0)  # signal 0: only whether the process exists
    except ProcessLookupError:
        return False
    except PermissionError:  # it exists, under another user
        return True
    return True


def describe(writer: dict) -> str:
    """'process 123 on host h (writing since 2026-…)'."""
    since = f" (writing since {writer['started']})" if writer.get("started") else ""
    return f"process {writer.get('pid')} on host {writer.get('host')}{since}"


def _try_create(path: str, me: dict) -> bool:
    try:
        fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
    except FileExistsError:
        return False
    with os.fdopen(fd, "w") as f:
        json.dump(me, f)
    return True


def acquire(folder: str, name: str) -> dict:
    """Take the lock of the store folder `folder` (created if missing) for this process, taking
    over a stale one; a `SweepStoreError` naming the live writer otherwise. Returns what the
    lock file holds."""
    _quiet_zarr()
    os.makedirs(folder, exist_ok=True)
    path, me = os.path.join(folder, LOCK_NAME), _me()
    for _ in range(3):  # a stale lock taken over by another process meanwhile: look again
        if _try_create(path, me):
            return me
        writer = writer_of(folder)
        if writer is None:
            continue  # released meanwhile
        if writer.get("host") == me["host"] and writer.get("pid") == me["pid"]:
            raise SweepStoreError(
                f"store {name!r}: this process is writing it already (a sweep of the same store inside "
                "another's progress callback, or from another thread); give another path."
            )
        if writer and may_run(writer):
            raise SweepStoreError(
                f"store {name!r}: is being written by {describe(writer)}. Two processes must not write one "
                "store: wait for that run to finish (or stop it), then run this sweep again, which resumes "
                "the store; or give another path. If that process is gone (on another host, which cannot "
                f"be checked from here), delete the file {LOCK_NAME!r} in the store, then run again."
            )
        if not writer:  # unreadable: being written this instant by a process taking the lock?
            time.sleep(UNREADABLE_WAIT)
            if writer_of(folder) != {}:
                continue
            # still unreadable: damaged (a writer killed between creating and filling it), so stale
        # stale: its process is gone. Moved aside first (atomic), so that of two processes taking
        # it over at once only one succeeds; the other finds the new lock and is refused.
        aside = f"{path}.stale-{me['pid']}"
        try:
            os.replace(path, aside)
        except FileNotFoundError:
            continue
        if _read(aside) != writer:  # it was replaced by a live writer meanwhile: give it back
            with contextlib.suppress(OSError):
                os.link(aside, path)
            os.remove(aside)
            continue
        os.remove(aside)
    if _try_create(path, me):
        return me
    writer = writer_of(folder) or {}
    raise SweepStoreError(f"store {name!r}: another process took its writer lock meanwhile: {describe(writer)}.")


def release(folder: str, me: dict) -> None:
    """Remove the lock if it is still this process's (a store replaced meanwhile by hand has
    none)."""
    if writer_of(folder) == me:
        with contextlib.suppress(FileNotFoundError):
            os.remove(os.path.join(folder, LOCK_NAME))


@contextlib.contextmanager
def writer_lock(folder: str | None, name: str):
    """Hold the writer lock of the local store folder `folder` (None: not a local folder, no
    lock) for the `with` block."""
    if folder is None:
        yield None
        return
    try:
        me = acquire(folder, name)
    except OSError as err:  # e.g. a read-only file system, no permission
        raise SweepStoreError(f"store {name!r}: cannot be written ({err.strerror or err}).") from err
    try:
        yield me
    finally:
        release(folder, me)
