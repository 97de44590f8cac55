r"""Sweeps written to a Zarr store (`cj.sweep(store=)`, `cj.open_sweep`) and run on Dask
(`cj.sweep(client=)`): the stored table equals the in-memory one to the bit and reads back with
xarray; a sweep killed (SIGKILL) after some batches resumes and recomputes only the rest; a
store of another configuration is refused; a truncated or corrupted store is a clear error; a
`LocalCluster` of two processes gives the in-process table to the bit, even when a worker dies
in the middle of a batch.

Compilation dominates: the in-process tests share one compiled chunk program (every sweep
here uses `KW`, only array values change). The subprocess and cluster tests compile again in
each process and are marked slow.
"""

import os
import signal
import subprocess
import sys
import textwrap
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import clebsch_jax as cj
from clebsch_jax.models import rigid_body

zarr = pytest.importorskip("zarr")
xarray = pytest.importorskip("xarray")


def casimir(system, sol):
    """|μ|² at every node: the Casimir of the rigid body's Lie–Poisson bracket."""
    return jnp.sum(sol.momentum**2, axis=-1)


KW = dict(dt=0.05, n_steps=16, chunk_steps=8, batch_size=2, save_every=4, grid=True)
INERTIAS = np.array([[2.0, 1.0, 2.0 / 3.0], [1.0, 1.5, 0.5], [3.0, 2.0, 1.0]])
OMEGAS = np.array([[1.3, 0.8, -0.4], [0.2, 1.0, 0.3], [-0.5, 0.1, 0.9]])
EYES = np.broadcast_to(np.eye(3), (3, 3, 3))
N_MEMBERS, N_BATCHES = 9, 5  # 3 inertias × 3 momenta in batches of 2: the last one padded


def assert_same_table(a, b):
    """Every per-member array equal to the bit (NaN where NaN), and the same static facts."""
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    assert ta == tb
    for x, y in zip(la, lb):
        x, y = np.asarray(x), np.asarray(y)
        assert x.dtype == y.dtype and x.shape == y.shape
        assert np.array_equal(x, y, equal_nan=True)


@pytest.fixture(scope="module")
def reference():
    return cj.sweep(rigid_body, INERTIAS, EYES, OMEGAS, invariants={"casimir": casimir}, **KW)


def stored(path, **change):
    return cj.sweep(
        rigid_body, INERTIAS, EYES, OMEGAS, invariants={"casimir": casimir}, store=str(path), **{**KW, **change}
    )


def test_store_round_trip_with_xarray_and_open_sweep(reference, tmp_path):
    path = tmp_path / "sweep.zarr"
    res = stored(path)
    assert_same_table(res, reference)
    assert_same_table(cj.open_sweep(path), reference)

    ds = xarray.open_zarr(path)
    assert ds.sizes["member"] == N_MEMBERS and ds.sizes["batch"] == N_BATCHES
    assert ds["final_Q"].dims == ("member", "Q_axis0", "Q_axis1")
    assert ds["saved_momentum"].dims == ("member", "node", "component")
    assert ds["params_0"].dims == ("param", "params_0_axis0") and ds["Q0"].dims[0] == "ic"
    np.testing.assert_array_equal(ds["params_0"].values[ds["param_index"].values], INERTIAS[reference.param_index])
    np.testing.assert_array_equal(ds["status"].values, reference.status)
    key = ds.attrs["invariant_arrays"]["casimir"]
    np.testing.assert_array_equal(ds[f"drift_{key}"].values, reference.drift["casimir"])
    assert ds.attrs["method"] == reference.method and ds.attrs["dt"] == KW["dt"]
    assert ds.attrs["package_version"] == cj.__version__
    assert ds["batch_done"].values.all() and (ds["batch_run"].values == 1).all()


def test_a_store_of_another_configuration_is_refused(reference, tmp_path):
    path = tmp_path / "sweep.zarr"
    stored(path)
    for change in ({"dt": 0.04}, {"n_steps": 24}, {"batch_size": 3}):
        with pytest.raises(cj.SweepStoreError, match=f"store '{path}'.*another sweep configuration"):
            stored(path, **change)
    with pytest.raises(cj.SweepStoreError, match="another sweep configuration.*inputs_sha256"):
        cj.sweep(rigid_body, INERTIAS, EYES, OMEGAS + 0.125, invariants={"casimir": casimir}, store=str(path), **KW)
    res = stored(path, dt=0.04, overwrite=True)
    assert_same_table(
        res, cj.sweep(rigid_body, INERTIAS, EYES, OMEGAS, invariants={"casimir": casimir}, **{**KW, "dt": 0.04})
    )
    assert xarray.open_zarr(path, consolidated=False).attrs["dt"] == 0.04


def quartic(system, sol):
    """|μ|⁴ at every node: another body under the invariant's name."""
    return jnp.sum(sol.momentum**2, axis=-1) ** 2


@pytest.mark.slow  # a sweep per changed body; test_a_store_of_another_configuration_is_refused runs by default
def test_a_sweep_that_computes_something_else_under_the_same_names_is_refused(reference, tmp_path, monkeypatch):
    # the store keeps a digest of one member's traced program: same names, other bodies are refused
    path = tmp_path / "sweep.zarr"
    stored(path)
    for change, differs in (
        ({"invariants": {"casimir": quartic}}, r"\(program_sha256: stored"),
        ({"check_energy": False}, r"\(options: stored .*'check_energy': True"),
    ):
        with pytest.raises(cj.SweepStoreError, match=f"another sweep configuration {differs}"):
            cj.sweep(
                rigid_body,
                INERTIAS,
                EYES,
                OMEGAS,
                store=str(path),
                **{"invariants": {"casimir": casimir}, **KW, **change},
            )

    # make_system: a lambda with another body, a module-level function edited in place
    scaled = tmp_path / "scaled.zarr"
    twice = (lambda inertia: rigid_body(inertia),), (lambda inertia: rigid_body(2.0 * inertia),)
    cj.sweep(twice[0][0], INERTIAS, EYES, OMEGAS, store=str(scaled), **KW)
    with pytest.raises(cj.SweepStoreError, match="another sweep configuration.*program_sha256"):
        cj.sweep(twice[1][0], INERTIAS, EYES, OMEGAS, store=str(scaled), **KW)
    assert cj.sweep(twice[0][0], INERTIAS, EYES, OMEGAS, store=str(scaled), **KW).succeeded.all()  # the same: resumed

    module = tmp_path / "edited_model.py"
    module.write_text(
        "from clebsch_jax.models import rigid_body\n\ndef model(inertia):\n    return rigid_body(inertia)\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    import importlib

    import edited_model

    edited = tmp_path / "edited.zarr"
    cj.sweep(edited_model.model, INERTIAS, EYES, OMEGAS, store=str(edited), **KW)
    module.write_text(
        "from clebsch_jax.models import rigid_body\n\ndef model(inertia):\n    return rigid_body(inertia[::-1])\n"
    )
    importlib.reload(edited_model)
    with pytest.raises(cj.SweepStoreError, match="another sweep configuration.*program_sha256"):
        cj.sweep(edited_model.model, INERTIAS, EYES, OMEGAS, store=str(edited), **KW)


DERIVATIVE_MAP = cj.cayley  # read by _configured_body when it is called: a setting changed between runs


def _configured_body(inertia):
    return rigid_body(inertia, derivative_map=DERIVATIVE_MAP)


@pytest.mark.slow  # traces and compiles a sweep of its own make_system; test_a_store_of_another_configuration_is_refused runs by default
def test_a_resume_with_another_setting_of_the_model_or_tolerance_is_refused(reference, tmp_path, monkeypatch):
    """Variants of the issue's cases (not a lambda, an edited body, an invariant or
    check_energy=False): the same make_system whose module-level setting chose another
    derivative map, and check_energy= another tolerance. Refused before anything is computed;
    the store is kept as it was."""
    path = tmp_path / "sweep.zarr"
    first = cj.sweep(_configured_body, INERTIAS, EYES, OMEGAS, invariants={"casimir": casimir}, store=str(path), **KW)
    assert_same_table(first, reference)
    before = _tree(path)
    monkeypatch.setattr(sys.modules[__name__], "DERIVATIVE_MAP", cj.exponential)
    with pytest.raises(cj.SweepStoreError, match=r"another sweep configuration \(program_sha256: stored"):
        cj.sweep(_configured_body, INERTIAS, EYES, OMEGAS, invariants={"casimir": casimir}, store=str(path), **KW)
    monkeypatch.setattr(sys.modules[__name__], "DERIVATIVE_MAP", cj.cayley)
    with pytest.raises(cj.SweepStoreError, match="another sweep configuration.*check_energy"):
        cj.sweep(
            _configured_body, INERTIAS, EYES, OMEGAS, invariants={"casimir": casimir}, store=str(path),
            check_energy=1e-3, **KW,
        )  # fmt: skip
    assert _tree(path) == before


def test_a_stored_sweep_from_three_threads_is_the_same_table(reference, tmp_path):
    # the store's groups are devices × threads batches, run side by side while the writer
    # thread stores the group before; the table and the store are the in-memory table's
    path = tmp_path / "threads.zarr"
    assert_same_table(stored(path, threads=3), reference)
    assert_same_table(cj.open_sweep(path), reference)
    assert xarray.open_zarr(path, consolidated=False)["batch_done"].values.all()


def test_fast_auto_resumes_on_the_path_a_store_was_written_with(reference, tmp_path):
    # "auto" picks its path from B and n_steps, the default batch size follows the threads; a
    # stored sweep keeps the path and batch size it was written with (the store refuses
    # others), so defaults can change without stranding stores
    from clebsch_jax.batching.store import ATTR, stored_configuration
    from clebsch_jax.batching.choose import resumed

    path = tmp_path / "sweep.zarr"
    nothing = resumed("auto", None, path, False, "auto")
    assert stored_configuration(path) is None and nothing == ("auto", None, "auto")  # nothing yet
    stored(path, fast=False)
    assert stored_configuration(path)["fast"] is False
    written = zarr.open_group(str(path), mode="r").attrs[ATTR]["batch_size"]
    # a store written before the native backend (no "backend" recorded) resumes on XLA
    assert resumed("auto", None, path, False, "auto") == (False, written, "xla")
    assert resumed("auto", None, path, True, "auto") == ("auto", None, "auto")  # overwrite: a new sweep
    assert resumed(True, 3, path, False, "xla") == (True, 3, "xla")  # explicit choices stay (and are refused)
    fast_store = zarr.open_group(str(tmp_path / "fast.zarr"), mode="w")
    fast_store.attrs[ATTR] = {"fast": True}
    assert resumed("auto", None, tmp_path / "fast.zarr", False, "auto") == (True, None, "xla")
    native_store = zarr.open_group(str(tmp_path / "native.zarr"), mode="w")
    native_store.attrs[ATTR] = {"fast": False, "backend": "native", "batch_size": 8}
    assert resumed("auto", None, tmp_path / "native.zarr", False, "auto") == (False, 8, "native")
    zarr.open_group(str(tmp_path / "other.zarr"), mode="w").attrs["x"] = 1  # not a sweep's store
    assert stored_configuration(tmp_path / "other.zarr") is None
    assert_same_table(stored(path), reference)  # the default, "auto", reads the stored table back


def test_a_truncated_or_corrupted_store_is_a_clear_error(reference, tmp_path):
    path = tmp_path / "sweep.zarr"
    stored(path)
    chunk = path / "final_p" / "c" / "1" / "0" / "0"
    assert chunk.is_file()
    data = chunk.read_bytes()
    chunk.write_bytes(data[: len(data) // 2])  # a garbled chunk of batch 1
    with pytest.raises(cj.SweepStoreError, match=f"store '{path}': cannot read 'final_p'"):
        cj.open_sweep(path)
    chunk.unlink()  # a missing chunk would read as NaN: it is reported instead
    with pytest.raises(cj.SweepStoreError, match=f"store '{path}': 1 of {N_BATCHES} chunks of 'final_p' are missing"):
        cj.open_sweep(path)
    (path / "status" / "zarr.json").unlink()  # an array gone
    with pytest.raises(cj.SweepStoreError, match=f"store '{path}': the array 'status' is missing"):
        stored(path)
    (path / "zarr.json").unlink()  # not a group any more
    with pytest.raises(cj.SweepStoreError, match=f"store '{path}'"):
        cj.open_sweep(path)


def _tree(path):
    """Every file under `path` with its bytes: what must survive a refused store."""
    return {str(f.relative_to(path)): f.read_bytes() for f in sorted(path.rglob("*")) if f.is_file()}


def test_a_path_that_is_not_our_store_is_refused_and_kept(tmp_path, monkeypatch):
    # nothing we did not write is removed, with or without overwrite: a folder of other files
    # (also the current folder, "."), a file, a Zarr group of other data, in memory too
    folder = tmp_path / "results"
    (folder / "runs").mkdir(parents=True)
    (folder / "runs" / "a.csv").write_text("1,2\n")
    (folder / "notes.txt").write_text("keep me")
    a_file = tmp_path / "table.zarr"
    a_file.write_bytes(b"not a folder")
    other = tmp_path / "other.zarr"
    zarr.open_group(str(other), mode="w", attributes={"source": "a simulation"}).create_array(
        "x", shape=(3,), dtype="f8"
    )
    monkeypatch.chdir(folder)
    cases = [
        (folder, "is a folder that is not a Zarr store \\(it holds notes.txt, runs\\)"),
        (".", "is a folder that is not a Zarr store"),
        (a_file, "is a file, not a folder"),
        (other, "is a Zarr group not written by clebsch_jax.sweep"),
    ]
    before = _tree(tmp_path)
    for path, message in cases:
        for overwrite in (False, True):
            with pytest.raises(cj.SweepStoreError, match=f"store '{path}': {message}.*Nothing was written or removed"):
                stored(path, overwrite=overwrite)
    assert _tree(tmp_path) == before
    memory = zarr.storage.MemoryStore()
    zarr.open_group(memory, mode="w", attributes={"source": "a simulation"})
    with pytest.raises(cj.SweepStoreError, match="is a Zarr group not written by clebsch_jax.sweep"):
        cj.sweep(rigid_body, INERTIAS, EYES, OMEGAS, store=memory, overwrite=True, **KW)
    assert zarr.open_group(memory, mode="r").attrs["source"] == "a simulation"


def test_a_damaged_store_is_an_error_never_wiped(reference, tmp_path):
    path = tmp_path / "sweep.zarr"
    stored(path)
    meta = path / "zarr.json"
    meta.write_bytes(meta.read_bytes()[:-40])  # the root metadata cut short
    before = _tree(path)
    for overwrite in (False, True):
        with pytest.raises(
            cj.SweepStoreError,
            match=f"store '{path}': damaged.*root metadata \\(zarr.json\\) cannot be read.*Nothing was removed",
        ):
            stored(path, overwrite=overwrite)
    assert _tree(path) == before
    # variants: the root metadata gone (a folder of our arrays without it), or readable but with
    # its attributes lost (a Zarr group that does not say it is ours): refused and kept, also
    # with overwrite=True, since nothing says the folder is a sweep's any more
    import json

    meta.unlink()
    bare = _tree(path)
    for overwrite in (False, True):
        with pytest.raises(cj.SweepStoreError, match=f"store '{path}': .*Nothing was (written or )?removed"):
            stored(path, overwrite=overwrite)
    assert _tree(path) == bare
    meta.write_text(json.dumps({"zarr_format": 3, "node_type": "group", "attributes": {}}))
    stripped = _tree(path)
    for overwrite in (False, True):
        with pytest.raises(
            cj.SweepStoreError, match=f"store '{path}': is a Zarr group not written by clebsch_jax.sweep"
        ):
            stored(path, overwrite=overwrite)
    assert _tree(path) == stripped


def test_an_empty_folder_or_an_interrupted_creation_is_used(reference, tmp_path):
    # nothing to keep: an empty folder becomes the store; a store of ours whose creation was
    # interrupted (its owner attribute, no configuration: no batch can have been written) is
    # created again without overwrite; a store of ours is replaced with overwrite
    from clebsch_jax.batching.store import OWNER, OWNER_VALUE

    empty = tmp_path / "empty"
    empty.mkdir()
    assert_same_table(stored(empty), reference)
    interrupted = tmp_path / "interrupted.zarr"
    zarr.open_group(str(interrupted), mode="w", attributes={OWNER: OWNER_VALUE}).create_array(
        "status", shape=(2,), dtype="i4"
    )
    assert_same_table(stored(interrupted), reference)
    (empty / "status" / "c" / "0").unlink()  # ours, truncated: overwrite replaces it
    assert_same_table(stored(empty, overwrite=True), reference)
    assert_same_table(cj.open_sweep(empty), reference)


def _flip_a_bit(chunk):
    data = bytearray(chunk.read_bytes())
    data[len(data) // 2] ^= 0x10
    chunk.write_bytes(bytes(data))


def test_a_flipped_bit_is_found_and_only_its_batch_is_computed_again(reference, tmp_path, capsys):
    # every chunk carries a CRC-32C: a flipped bit in a finished batch's data is an error naming
    # the batch, and a rerun marks that batch not done and computes it alone; a flipped bit in an
    # input array (written at creation) is written again, in a done flag the batch is recomputed
    path = tmp_path / "sweep.zarr"
    stored(path)
    _flip_a_bit(path / "saved_momentum" / "c" / "3" / "0" / "0")  # batch 3's saved nodes
    _flip_a_bit(path / "final_t" / "c" / "1")  # batch 1
    _flip_a_bit(path / "xi0" / "c" / "0" / "0")  # an input
    with pytest.raises(
        cj.SweepStoreError,
        match=f"store '{path}': cannot read 'final_t' .*checksum.*: batch 1; run "
        "the same sweep with this store: it computes only the damaged",
    ):
        cj.open_sweep(path)
    with pytest.raises(Exception, match="(?i)checksum"):  # xarray reads no changed number either
        xarray.open_zarr(path)["final_t"].values
    capsys.readouterr()
    assert_same_table(stored(path), reference)
    err = capsys.readouterr().err
    assert "batch 1 (members 2-3) is damaged ('final_t'" in err and "batch 3 (members 6-7) is damaged" in err
    assert "the input arrays xi0 are damaged: written again" in err
    assert "skipped 5 of 9 members" in err  # batches 0, 2, 4
    runs = np.asarray(zarr.open_group(str(path), mode="r")["batch_run"][:])
    np.testing.assert_array_equal(runs, [1, 2, 1, 2, 1])
    assert_same_table(cj.open_sweep(path), reference)
    np.testing.assert_array_equal(xarray.open_zarr(path)["xi0"].values, OMEGAS)

    _flip_a_bit(path / "batch_done" / "c" / "4")
    assert_same_table(stored(path), reference)
    assert "the done flag of batch 4 is damaged" in capsys.readouterr().err
    np.testing.assert_array_equal(np.asarray(zarr.open_group(str(path), mode="r")["batch_run"][:]), [1, 2, 1, 2, 3])


def test_a_store_another_process_is_creating_is_refused_naming_it(reference, tmp_path):
    # a store of ours without its configuration yet is recreated only when the process that
    # began creating it is gone: recreating it under a live process would wipe its work
    import socket
    import subprocess

    from clebsch_jax.batching.store import OWNER, OWNER_VALUE

    path = tmp_path / "sweep.zarr"
    host = socket.gethostname()
    with subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"]) as alive:
        try:
            zarr.open_group(
                str(path), mode="w", attributes={OWNER: OWNER_VALUE, "created_by": {"host": host, "pid": alive.pid}}
            )
            with pytest.raises(cj.SweepStoreError, match=f"is being created by process {alive.pid} on host {host}"):
                stored(path)
        finally:
            alive.kill()
    # now gone (reaped): the store is created again
    assert_same_table(stored(path), reference)
    elsewhere = tmp_path / "elsewhere.zarr"  # a creator on another host cannot be checked: refused
    zarr.open_group(
        str(elsewhere), mode="w", attributes={OWNER: OWNER_VALUE, "created_by": {"host": "node-17", "pid": 4242}}
    )
    with pytest.raises(cj.SweepStoreError, match="process 4242 on host node-17.*delete the store yourself"):
        stored(elsewhere, overwrite=True)


def _lock(path, host, pid, started="2026-11-28T23:00:00+00:00"):
    import json

    from clebsch_jax.batching.store_lock import LOCK_NAME

    path.mkdir(exist_ok=True)
    (path / LOCK_NAME).write_text(json.dumps({"host": host, "pid": pid, "started": started}))
    return path / LOCK_NAME


def test_a_store_another_live_process_writes_is_refused_naming_it_even_with_overwrite(reference, tmp_path, capsys):
    """The writer lock: a store whose lock names a live process is neither resumed nor replaced
    (overwrite=True would wipe that process's batches); the message names the writer and the
    ways out. A writer on another host cannot be checked: refused too. Nothing is changed."""
    import socket

    path = tmp_path / "sweep.zarr"
    stored(path)
    before = {p: p.read_bytes() for p in path.rglob("*") if p.is_file()}
    host = socket.gethostname()
    with subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"]) as alive:
        try:
            lock = _lock(path, host, alive.pid)
            before[lock] = lock.read_bytes()
            for overwrite in (False, True):
                with pytest.raises(
                    cj.SweepStoreError,
                    match=rf"is being written by process {alive.pid} on host {host} \(writing since "
                    r"2026-11-28T23:00:00\+00:00\)\. .*wait for that run to finish.*resumes",
                ):
                    stored(path, overwrite=overwrite)
                assert {p: p.read_bytes() for p in path.rglob("*") if p.is_file()} == before
            # the command line: one line, exit code 2, the writer named (the message told
            # the second process to pass overwrite=True)
            from clebsch_jax.cli import main

            config = tmp_path / "sweep.toml"
            config.write_text(CONFIG)
            for extra in ([], ["--overwrite"]):
                assert main(["sweep", str(config), "--store", str(path), "--quiet", *extra]) == 2
                err = capsys.readouterr().err
                assert f"is being written by process {alive.pid} on host {host}" in err and err.count("\n") == 1, err
            assert {p: p.read_bytes() for p in path.rglob("*") if p.is_file()} == before
        finally:
            alive.kill()
    _lock(path, "node-17", 4242)
    with pytest.raises(
        cj.SweepStoreError, match="process 4242 on host node-17.*delete the file 'clebsch_jax_writer.lock'"
    ):
        stored(path, overwrite=True)


def test_a_stale_lock_of_a_dead_process_is_taken_over_and_the_store_resumed(reference, tmp_path):
    """A lock left by a process of this host that is gone (killed) is taken over; the store is
    resumed (nothing recomputed), and the lock is released at the end. Also on a new store path
    holding only a stale lock (a writer killed while creating it), and an empty lock file."""
    import socket

    from clebsch_jax.batching.store_lock import LOCK_NAME

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    pid = int(dead.stdout)  # reaped: no process has this id now (ids are not reused this soon)
    path = tmp_path / "sweep.zarr"
    stored(path)
    _lock(path, socket.gethostname(), pid)
    assert_same_table(stored(path), reference)
    np.testing.assert_array_equal(np.asarray(zarr.open_group(str(path), mode="r")["batch_run"][:]), 1)
    assert not (path / LOCK_NAME).exists()
    fresh = _lock(tmp_path / "fresh.zarr", socket.gethostname(), pid).parent
    assert_same_table(stored(fresh), reference)
    assert not (fresh / LOCK_NAME).exists()
    (path / LOCK_NAME).write_text("")  # a writer killed between creating its lock and filling it
    assert_same_table(stored(path), reference)
    assert sorted(p.name for p in path.iterdir() if "lock" in p.name) == []


def test_an_unfinished_store_is_not_read_as_a_result(reference, tmp_path):
    path = tmp_path / "sweep.zarr"
    stored(path)
    root = zarr.open_group(str(path), mode="r+")
    root["batch_done"][3] = False
    with pytest.raises(cj.SweepStoreError, match=f"store '{path}': 1 of {N_BATCHES} batches are not written"):
        cj.open_sweep(path)


class _Stop(Exception):
    pass


def test_an_interrupted_store_reads_its_unwritten_members_as_not_run(reference, tmp_path):
    # xarray on a store whose sweep stopped after two batches: the unwritten members' status is
    # Status.NOT_RUN (never SUCCESS, the integer fill 0), their numbers NaN; the store opens
    # without xarray's warning about consolidated metadata, before and after the sweep finishes
    import warnings

    path = tmp_path / "sweep.zarr"

    def stop_at_batch_2(info):
        if info.batch == 2:
            raise _Stop

    with pytest.raises(_Stop):
        stored(path, progress=stop_at_batch_2)
    written = np.arange(N_MEMBERS) < 2 * KW["batch_size"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ds = xarray.open_zarr(path)
    np.testing.assert_array_equal(ds["batch_done"].values, np.arange(N_BATCHES) < 2)
    status = ds["status"].values
    np.testing.assert_array_equal(status[written], reference.status[written])
    assert (status[~written] == cj.Status.NOT_RUN).all() and cj.Status.NOT_RUN != cj.Status.SUCCESS
    assert np.isnan(ds["energy_error"].values[~written]).all() and np.isnan(ds["final_p"].values[~written]).all()
    assert "not run yet" in cj.Status.NOT_RUN.message
    assert_same_table(stored(path), reference)  # finished by a rerun
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert (xarray.open_zarr(path)["status"].values == reference.status).all()


def test_store_needs_the_optional_extra(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "zarr", None)  # as if not installed
    with pytest.raises(ImportError, match=r"clebsch-jax\[sweep\]"):
        stored(tmp_path / "sweep.zarr")


def test_bad_store_client_and_overwrite_are_refused_before_compiling(tmp_path):
    pytest.importorskip("distributed")
    bad = [
        ({"overwrite": True}, ValueError, "overwrite: True replaces a store, but no store= was given"),
        ({"overwrite": "yes", "store": str(tmp_path / "s.zarr")}, ValueError, "overwrite: expected True or False"),
        ({"client": "tcp://localhost:8786"}, ValueError, "client: expected a dask.distributed.Client, got str"),
        ({"store": ""}, ValueError, "store: expected a path"),
    ]
    for change, kind, message in bad:
        with pytest.raises(kind, match=message):
            cj.sweep(rigid_body, INERTIAS, EYES, OMEGAS, invariants={"casimir": casimir}, **{**KW, **change})
    assert not (tmp_path / "s.zarr").exists()


# --------------------------------------------------------------------------------------------
# Killed and resumed.

SCRIPT = textwrap.dedent("""
    import sys, time
    import jax.numpy as jnp
    import numpy as np
    import clebsch_jax as cj

    def casimir(system, sol):
        return jnp.sum(sol.momentum**2, axis=-1)

    data = np.load(sys.argv[2])
    cj.sweep(cj.models.rigid_body, data["inertias"], data["eyes"], data["omegas"], dt=0.05, n_steps=16,
             chunk_steps=8, batch_size=2, save_every=4, grid=True, invariants={"casimir": casimir},
             store=sys.argv[1], progress=lambda info: time.sleep(1.0))  # slow enough to be met and killed mid-run
""")


@pytest.mark.slow
def test_a_sweep_killed_after_some_batches_resumes_with_the_same_table(reference, tmp_path, capsys):
    path, inputs = tmp_path / "sweep.zarr", tmp_path / "inputs.npz"
    np.savez(inputs, inertias=INERTIAS, eyes=EYES, omegas=OMEGAS)
    (tmp_path / "run.py").write_text(SCRIPT)
    proc = subprocess.Popen(
        [sys.executable, str(tmp_path / "run.py"), str(path), str(inputs)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    done = np.zeros(N_BATCHES, bool)
    deadline = time.monotonic() + 300
    try:
        while time.monotonic() < deadline and proc.poll() is None:
            try:
                done = np.asarray(zarr.open_group(str(path), mode="r")["batch_done"][:])
            except Exception:  # not created yet
                pass
            if done.any():
                break
            time.sleep(0.05)
        assert proc.poll() is None, proc.communicate()[1].decode()[-2000:]
        # a second process on the store while the first writes it: refused, naming the writer,
        # also with overwrite=True (which would wipe the first one's batches)
        for overwrite in (False, True):
            with pytest.raises(cj.SweepStoreError, match=rf"is being written by process {proc.pid} on host .*resumes"):
                stored(path, overwrite=overwrite)
        assert proc.poll() is None  # the writer was not disturbed
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait()
    done = np.asarray(zarr.open_group(str(path), mode="r")["batch_done"][:])
    assert 1 <= done.sum() < N_BATCHES, done
    written_before = done.copy()
    # xarray on the killed sweep's store: its unwritten members read NOT_RUN, never SUCCESS
    written = np.repeat(done, KW["batch_size"])[:N_MEMBERS]
    status = xarray.open_zarr(path)["status"].values
    np.testing.assert_array_equal(status[written], reference.status[written])
    assert (status[~written] == cj.Status.NOT_RUN).all()
    # the killed writer's lock is left behind; its process is gone, so the next run takes it over
    from clebsch_jax.batching.store_lock import LOCK_NAME, writer_of

    assert writer_of(str(path))["pid"] == proc.pid

    capsys.readouterr()
    res = stored(path)
    assert not (path / LOCK_NAME).exists()  # released at the end
    skipped = sum(min(KW["batch_size"], N_MEMBERS - b * KW["batch_size"]) for b in np.flatnonzero(written_before))
    assert f"skipped {skipped} of {N_MEMBERS} members" in capsys.readouterr().err
    assert_same_table(res, reference)
    runs = np.asarray(zarr.open_group(str(path), mode="r")["batch_run"][:])
    np.testing.assert_array_equal(runs, np.where(written_before, 1, 2))  # only the unfinished batches rerun


# --------------------------------------------------------------------------------------------
# Dask.


@pytest.fixture(scope="module")
def client():
    distributed = pytest.importorskip("distributed")
    with (
        distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cl,
        distributed.Client(cl) as c,
    ):
        yield c


def killing_casimir(flag: str, driver: int):
    """`casimir`, but the first worker process that traces it SIGKILLs itself (once, flagged
    by the file `flag`): a worker dying in the middle of its first batch."""

    def f(system, sol):
        if os.getpid() != driver and not os.path.exists(flag):
            open(flag, "w").close()
            os.kill(os.getpid(), signal.SIGKILL)
        return jnp.sum(sol.momentum**2, axis=-1)

    return f


def test_a_client_closed_mid_run_says_the_run_can_be_resumed_and_it_is(reference, tmp_path, capsys):
    """`client.close()` while the tasks run (here from the progress callback, after the first
    batch): an error that says whether the run can be resumed and how; with a store, running the
    same sweep again resumes it to the in-process table. Workers are threads of this process,
    which share its compiled programs."""
    distributed = pytest.importorskip("distributed")
    path = tmp_path / "sweep.zarr"
    for store in (str(path), None):
        with distributed.LocalCluster(
            n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None
        ) as cluster:
            client = distributed.Client(cluster)
            closing = {"progress": lambda info: client.close()}
            if store is None:
                expected = r"client was closed during the run .*lost\). .*pass store=PATH to make a run resumable"
            else:
                expected = rf"store '{path}' holds the batches .* It can be resumed: run the same sweep again"
            with pytest.raises(RuntimeError, match=expected):
                cj.sweep(
                    rigid_body, INERTIAS, EYES, OMEGAS, invariants={"casimir": casimir}, store=store,
                    client=client, **KW, **closing,
                )  # fmt: skip
    done = np.asarray(zarr.open_group(str(path), mode="r")["batch_done"][:])
    assert 1 <= done.sum() < N_BATCHES
    capsys.readouterr()
    assert_same_table(stored(path), reference)
    assert "skipped" in capsys.readouterr().err


@pytest.mark.slow
def test_a_local_cluster_gives_the_in_process_table_even_when_a_worker_dies(reference, client, tmp_path):
    flag = tmp_path / "killed"
    inv = {"casimir": killing_casimir(str(flag), os.getpid())}
    path = tmp_path / "sweep.zarr"
    res = cj.sweep(rigid_body, INERTIAS, EYES, OMEGAS, invariants=inv, store=str(path), client=client, **KW)
    assert flag.exists()  # a worker was killed in the middle of a batch
    assert_same_table(res, reference)
    # every worker compiled the chunk program at most once for its 2-3 batches (16 steps = 2 chunks of 8)
    compiled = client.run(lambda: __import__("clebsch_jax.batching.chunks_xla", fromlist=["_"]).run_chunk._cache_size())
    assert max(compiled.values()) == 1, compiled
    assert np.asarray(zarr.open_group(str(path), mode="r")["batch_done"][:]).all()
    assert_same_table(cj.sweep(rigid_body, INERTIAS, EYES, OMEGAS, invariants=inv, client=client, **KW), reference)


# --------------------------------------------------------------------------------------------
# The command line.

CONFIG = f"""
model = "rigid_body"
dt = {KW["dt"]}
n_steps = {KW["n_steps"]}
chunk_steps = {KW["chunk_steps"]}
batch_size = {KW["batch_size"]}
save_every = {KW["save_every"]}
grid = true

[params]
values = {INERTIAS.tolist()}

[initial]
Q0 = {{identity = 3}}
xi0 = {OMEGAS.tolist()}

[invariants]
casimir = "{__name__}:casimir"
"""


def test_the_command_line_sweeps_into_a_store_and_resumes(reference, tmp_path, capsys):
    from clebsch_jax.cli import main

    config, path = tmp_path / "sweep.toml", tmp_path / "sweep.zarr"
    config.write_text(CONFIG)
    assert main(["sweep", str(config), "--store", str(path), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert f"{N_MEMBERS} members x {KW['n_steps']} steps in {N_BATCHES} batches of {KW['batch_size']}" in out
    assert f"{N_MEMBERS} x {KW['n_steps']} steps" in out and "casimir drift" in out
    assert_same_table(cj.open_sweep(path), reference)
    assert main(["sweep", str(config), "--store", str(path), "--quiet"]) == 0
    captured = capsys.readouterr()
    assert f"skipped {N_MEMBERS} of {N_MEMBERS} members" in captured.err
    assert "0 members computed in this run" in captured.out


def test_the_command_line_clamps_a_batch_size_above_the_member_count(tmp_path, capsys):
    """Two members with batch_size 10^6 (the issue's CLI case: 400 members, still running after
    120 s) run as one batch of 2: the store, the program and the table of batch_size=2."""
    from clebsch_jax.cli import main

    two = CONFIG.replace("grid = true", "grid = false")
    two = two.replace(f"batch_size = {KW['batch_size']}", "batch_size = 1000000")
    two = two.replace(f"values = {INERTIAS.tolist()}", f"values = {INERTIAS[:2].tolist()}")
    two = two.replace(f"xi0 = {OMEGAS.tolist()}", f"xi0 = {OMEGAS[:2].tolist()}")
    config, path = tmp_path / "sweep.toml", tmp_path / "sweep.zarr"
    config.write_text(two)
    assert main(["sweep", str(config), "--store", str(path), "--quiet"]) == 0
    assert f"2 members x {KW['n_steps']} steps in 1 batches of 2," in capsys.readouterr().out
    assert zarr.open_group(str(path), mode="r").attrs["clebsch_jax_sweep"]["batch_size"] == 2
    alone = cj.sweep(
        rigid_body, INERTIAS[:2], EYES[:2], OMEGAS[:2], invariants={"casimir": casimir}, **{**KW, "grid": False}
    )
    assert_same_table(cj.open_sweep(path), alone)


def test_the_command_line_help_documents_the_toml_format(capsys):
    from clebsch_jax.cli import main

    assert main(["--help"]) == 0 and "sweep" in capsys.readouterr().out
    assert main(["sweep", "--help"]) == 0
    out = capsys.readouterr().out
    for text in (
        "--store",
        "--workers",
        "--scheduler",
        "--overwrite",
        "model =",
        "n_steps =",
        "[params]",
        "linspace",
        "[initial]",
        "xi0 =",
        "[options]",
        "[invariants]",
    ):
        assert text in out
    assert main(["sweep", "x.toml", "--store", "s.zarr", "--workers", "2", "--scheduler", "tcp://h:8786"]) == 2


@pytest.mark.parametrize(
    "edit, message",
    [
        (
            lambda c: c.replace('"rigid_body"', '"no_such_model"'),
            "model: clebsch_jax.models has no function 'no_such_model'",
        ),
        (lambda c: "n_step = 3\n" + c, "unknown entry n_step"),
        (
            lambda c: c.replace("[params]\nvalues", "[params]\nlinspace = [[1, 2, 3]]\nvalues"),
            "[params]: give exactly one of values",
        ),
        (lambda c: c.replace("[params]\nvalues", "[params]\nvalue"), "[params]: unknown entry value"),
        (lambda c: c + "[options]\nscheme = 3\n", "sweep.toml: sweep: member 0"),  # refused by cj.sweep
        # misspelled keys inside tables are refused, not ignored
        (
            lambda c: c.replace("[params]\nvalues", "[params]\nvalues = [[1.0, 2.0, 3.0]]\nvaluess"),
            "[params]: unknown entry valuess",
        ),
        (
            lambda c: c.replace("xi0 = [", "xi0 = {normal = [4, 3], seedd = 1}\nunused = ["),
            "[initial]: unknown entry unused",
        ),
        (
            lambda c: c.replace("xi0 = [[", "xi0 = {normal = [4, 3], sede = 1}\n# [["),
            "[initial] xi0: unknown entry sede",
        ),
        (lambda c: c.replace("Q0 = {identity = 3}", "Q0 = {identity = 3, valu = 1}"), "[initial] Q0: expected"),
        (
            lambda c: c.replace("xi0 = [[", "xi0 = {normal = [4, 3], seed = -7}\n# [["),
            "seed must be a whole number >= 0",
        ),
        (lambda c: c.replace("xi0 = [[", "xi0 = {normal = [4, 3], scale = 'big'}\n# [["), "scale must be a finite"),
        # a run the sweep's schedule cannot hold: refused by cj.sweep with the estimate, before
        # the store is created (the case was a Python call of 10^12 steps in chunks of 100)
        (
            lambda c: c.replace(f"n_steps = {KW['n_steps']}", "n_steps = 400000000000"),
            "n_steps: 400000000000 steps in 50000000000 chunks of 8",
        ),
    ],
)
def test_the_command_line_names_a_bad_config_entry(tmp_path, capsys, edit, message):
    from clebsch_jax.cli import main

    config = tmp_path / "sweep.toml"
    config.write_text(edit(CONFIG))
    assert main(["sweep", str(config), "--store", str(tmp_path / "s.zarr"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and err.count("\n") == 1, err
    assert not (tmp_path / "s.zarr").exists()


def test_the_command_line_refuses_a_store_it_cannot_use_in_one_line(tmp_path, capsys, monkeypatch):
    # a file, a folder of other files, a place where nothing can be created: exit code 2, one
    # line, nothing changed
    import errno

    from clebsch_jax.cli import main

    config, a_file, folder = tmp_path / "sweep.toml", tmp_path / "table.csv", tmp_path / "data"
    config.write_text(CONFIG)
    a_file.write_text("1,2")
    folder.mkdir()
    (folder / "x.npy").write_bytes(b"x")
    cases = [(a_file, "is a file, not a folder"), (folder, "is a folder that is not a Zarr store")]
    for store, message in cases:
        for extra in ([], ["--overwrite"]):
            assert main(["sweep", str(config), "--store", str(store), "--quiet", *extra]) == 2
            err = capsys.readouterr().err
            assert f"store '{store}': {message}" in err and err.count("\n") == 1, err
    assert a_file.read_text() == "1,2" and (folder / "x.npy").read_bytes() == b"x"

    def read_only(self, *args, **kwargs):  # as on a read-only file system (root may write anywhere else)
        raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(self))

    monkeypatch.setattr("pathlib.Path.mkdir", read_only)
    assert main(["sweep", str(config), "--store", str(tmp_path / "new.zarr"), "--quiet"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err[-1].endswith(f"store '{tmp_path / 'new.zarr'}': cannot be written (Read-only file system).")


@pytest.mark.slow
def test_the_command_line_on_local_workers_stops_on_ctrl_c_and_resumes(tmp_path):
    config, path = tmp_path / "sweep.toml", tmp_path / "sweep.zarr"
    long = dict(KW, n_steps=2000, chunk_steps=100, batch_size=1, save_every=None)  # batches of ~1 s
    config.write_text(
        CONFIG.replace(f"n_steps = {KW['n_steps']}", f"n_steps = {long['n_steps']}")
        .replace(f"chunk_steps = {KW['chunk_steps']}", f"chunk_steps = {long['chunk_steps']}")
        .replace(f"batch_size = {KW['batch_size']}", "batch_size = 1")
        .replace(f"save_every = {KW['save_every']}\n", "")
        .replace(f'casimir = "{__name__}:casimir"', 'body_momentum = "body_momentum"')
    )
    cmd = [sys.executable, "-m", "clebsch_jax", "sweep", str(config), "--store", str(path), "--quiet"]
    proc = subprocess.Popen(cmd + ["--workers", "2"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and proc.poll() is None:
        try:
            if np.asarray(zarr.open_group(str(path), mode="r")["batch_done"][:]).any():
                break
        except Exception:  # not created yet
            pass
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err[-2000:]
    assert "run the same command to resume" in err
    done = np.asarray(zarr.open_group(str(path), mode="r")["batch_done"][:])
    assert 1 <= done.sum() < N_MEMBERS

    rerun = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert rerun.returncode == 0, rerun.stderr[-2000:]
    assert f"skipped {done.sum()} of {N_MEMBERS} members" in rerun.stderr
    whole = cj.sweep(
        rigid_body, INERTIAS, EYES, OMEGAS, invariants={"body_momentum": cj.diagnostics.body_momentum}, **long
    )
    assert_same_table(cj.open_sweep(path), whole)


def test_sweep_workers_get_one_xla_and_one_blas_thread():
    """`worker_environment`: a one-thread Dask worker's XLA runs on one intra-op thread and BLAS on
    one thread; the user's own XLA flags and thread counts are kept."""
    from clebsch_jax.batching.distributed import SINGLE_THREAD_XLA_FLAGS, worker_environment

    env = worker_environment({"XLA_FLAGS": "--xla_dump_to=somewhere", "OMP_NUM_THREADS": "3", "PATH": "p"})
    assert env["XLA_FLAGS"] == f"--xla_dump_to=somewhere {SINGLE_THREAD_XLA_FLAGS}"
    assert env["OMP_NUM_THREADS"] == "3" and env["OPENBLAS_NUM_THREADS"] == env["MKL_NUM_THREADS"] == "1"
    assert env["PATH"] == "p"
    assert worker_environment(env) == env  # the flags are not added twice
    assert worker_environment({})["XLA_FLAGS"] == SINGLE_THREAD_XLA_FLAGS
