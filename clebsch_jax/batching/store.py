r"""A sweep's table in a Zarr (v3) store, written batch by batch: resumable, readable by xarray.

`cj.sweep(..., store=path)` creates the store (or reopens it), then writes each batch's rows
as soon as the batch is finished. `xarray.open_zarr(path)` is the analysis entry point and
`cj.open_sweep(path)` gives the `SweepResult` back.

**Layout.** One Zarr group; every array carries its dimension names (Zarr v3
`dimension_names`, which xarray reads):

- `member` (member,) and, per member, `param_index`, `ic_index`, `dt`, `status`, `failed_step`,
  `energy_error`, `newton_iterations`, `max_residual`, `final_t`, `final_Q`, `final_p`,
  `final_xi`, `final_momentum` (the state arrays with one more dimension per axis of Q or ξ:
  `Q_axis0`, … and `component`, …), `initial_<k>` and `drift_<k>` of every invariant but the
  energy (the names in the attribute `invariants`; `drift_energy` is `energy_error`);
- the inputs: `Q0`, `xi0` (`P0` if given) over (ic, …) and every parameter leaf `params_<i>`
  over (param, …); the member's row of them is `ic_index`, `param_index`;
- with `save_every`: `saved_step` (node,) and `saved_t`, `saved_Q`, `saved_xi`,
  `saved_momentum` over (member, node, …);
- `batch_done` (batch,) and `batch_run` (batch,): whether batch b is written, and by which run
  of the sweep (1 for the first, 2 for the first resume, …).

A member not written yet (an interrupted sweep) reads `status` = `Status.NOT_RUN` (-1), never
a success, and NaN in its float arrays; `status` is the last of a batch's arrays written, so a
member with another status has all its data. The metadata are consolidated at the start of
every run, so `xarray.open_zarr(store)` opens it without a warning.

**Checksums.** Every chunk is compressed (zstd), then carries a CRC-32C of its stored bytes
(Zarr's `crc32c` codec): a flipped bit is an error when the chunk is read, never a changed
number. A reopened store is read back chunk by chunk (`repair`): a finished batch with a damaged
or missing chunk is marked not done, with a message, and computed again by this run alone; a
damaged chunk of the inputs is written again. `open_sweep` names the damaged batches.

Per-member arrays are chunked by the sweep's `batch_size` along `member`, so each batch writes
whole chunks of its own and batches written at once by different processes never share one.

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
refused naming it. Two processes running the same sweep on one store share its batches: each
skips the batches written when it starts; a batch both compute holds one run's rows (a chunk
garbled by two writers at once fails its checksum, and is computed again by the next run).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import sys
import warnings
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..roots.status import Status

__all__ = ["open_sweep", "SweepStoreError"]

ATTR = "clebsch_jax_sweep"
OWNER, OWNER_VALUE = "written_by", "clebsch_jax.sweep"  # the first attribute a new store gets: it is ours
FORMAT = 2  # the layout's version, part of the configuration

_EXTRA = 'pip install "clebsch-jax[sweep]"'
_COLUMNS = (
    "status",
    "failed_step",
    "newton_iterations",
    "max_residual",
    "final_t",
    "final_Q",
    "final_p",
    "final_xi",
    "final_momentum",
)
_SAVED = ("t", "Q", "xi", "momentum")


class SweepStoreError(ValueError):
    """A sweep store that cannot be used: another configuration, unfinished, truncated or corrupted."""


def _zarr():
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


# --------------------------------------------------------------------------------------------
# The configuration a store belongs to.


def _digest(arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        if a is None:
            h.update(b"none")
            continue
        a = np.ascontiguousarray(np.asarray(a))
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _describe(obj) -> str:
    """A repr without memory addresses (they change from process to process)."""
    if callable(obj) and hasattr(obj, "__qualname__"):
        return f"{getattr(obj, '__module__', '?')}.{obj.__qualname__}"
    return re.sub(r" at 0x[0-9a-fA-F]+", "", repr(obj))


def program_digest(plan) -> str:
    r"""A SHA-256 of what one member computes: the jaxpr of one chunk of its `integrate` run
    and its invariants (`jax.make_jaxpr` on the first member's shapes, as the sweep traces it),
    with the values of the constants the trace captured. The system's maps and Lagrangian,
    `make_system`'s body, the invariants' bodies and every `integrate` option are in it, so a
    store refuses a sweep that would compute something else under the same names (a lambda with
    another body, a function edited in place); so do another version of the engine or of JAX
    when they trace another program. Array inputs are traced, not in the jaxpr: they have
    their own digest."""
    import jax
    import jax.numpy as jnp

    from ..core.jit import undifferentiated
    from ..march.integrate import integrate
    from .sweep import _first_row, _system_of

    cfg, members = plan.cfg, plan.members
    j = int(members.ic_index[0])
    options = {k: v for k, v in cfg.options if k != "check_energy"}

    def member(p, s, q, x, d):
        system = _system_of(cfg, p, s)
        sol = integrate(
            system,
            q,
            x,
            dt=d,
            n_steps=cfg.n,
            P0=jnp.zeros_like(q),
            t0=jnp.zeros((), q.dtype),
            throw=False,
            check_energy=False,
            **options,
        )
        return sol, [fn(system, sol) for _, fn in cfg.invariants]

    with undifferentiated():  # as the sweep's chunks are traced
        closed = jax.make_jaxpr(member)(
            _first_row(members),
            members.shared,
            jnp.asarray(members.Q0[j]),
            jnp.asarray(members.xi0[j]),
            jnp.asarray(members.dt[0]),
        )
    text = re.sub(r" at 0x[0-9a-fA-F]+", "", str(closed.jaxpr))  # no memory addresses (they change)
    return hashlib.sha256(text.encode() + _digest(closed.consts).encode()).hexdigest()


def configuration(plan) -> dict:
    """The sweep's configuration, as stored in the attribute `clebsch_jax_sweep` (JSON)."""
    from .. import __version__
    import jax

    cfg, members, shapes, run, batch_size = plan
    dts = np.unique(members.dt)
    return {
        "format": FORMAT,
        "package_version": __version__,
        "model": "shared system" if members.builder is None else _describe(members.builder),
        "method": shapes.facts["method"] or shapes.facts["scheme"],
        "scheme": shapes.facts["scheme"],
        "form": shapes.facts["form"],
        "order": shapes.facts["order"],
        # the energy check is the sweep's own (its chunks run without it): recorded as asked
        "options": {**{k: _describe(v) for k, v in cfg.options}, "check_energy": cfg.check_energy},
        "program_sha256": program_digest(plan),
        "jax_version": jax.__version__,
        "fast": cfg.fast_method is not None,  # the fast path agrees with the general one to round-off only
        **({"backend": "native"} if getattr(cfg, "native", False) else {}),  # stores before it ran XLA
        "dt": float(dts[0]) if len(dts) == 1 else "one per member",
        "n_steps": run.n_steps,
        "chunk_steps": run.chunk_steps,
        "save_every": run.save_every,
        "batch_size": batch_size,
        "n_members": members.B,
        "n_batches": -(-members.B // batch_size),
        "invariants": [name for name in run.invariants if name != "energy"],
        "inputs_sha256": _digest(
            [
                *jax.tree_util.tree_leaves(members.params),
                members.Q0,
                members.xi0,
                members.P0,
                members.dt,
                members.param_index,
                members.ic_index,
                *(members.shared or []),
            ]
        ),
    }


# --------------------------------------------------------------------------------------------
# Creating, checking and writing.


def _dims(prefix: str, shape: tuple) -> list:
    return [f"{prefix}{k}" for k in range(len(shape))]


def _xi_dims(shape: tuple) -> list:
    return ["component"] if len(shape) == 1 else _dims("component", shape)


def _variables(plan) -> dict:
    """{name: (dimension names, shape, dtype, chunk along the first axis)} of every array."""
    cfg, members, shapes, run, bs = plan
    import jax

    B, q, x = members.B, shapes.q, shapes.xi
    qd, xd = _dims("Q_axis", q), _xi_dims(x)
    n_batches = -(-B // bs)
    out = {
        "member": (["member"], (B,), np.int64, bs),
        "param_index": (["member"], (B,), np.int64, bs),
        "ic_index": (["member"], (B,), np.int64, bs),
        "dt": (["member"], (B,), np.float64, bs),
        "status": (["member"], (B,), np.int32, bs),
        "failed_step": (["member"], (B,), np.int32, bs),
        "energy_error": (["member"], (B,), np.float64, bs),
        "newton_iterations": (["member"], (B,), np.int64, bs),
        "max_residual": (["member"], (B,), np.float64, bs),
        "final_t": (["member"], (B,), np.float64, bs),
        "final_p": (["member"] + qd, (B,) + q, np.float64, bs),
        "final_momentum": (["member"] + xd, (B,) + x, np.float64, bs),
        "Q0": (["ic"] + qd, members.Q0.shape, np.float64, bs),
        "xi0": (["ic"] + xd, members.xi0.shape, np.float64, bs),
        "batch_done": (["batch"], (n_batches,), np.bool_, 1),
        "batch_run": (["batch"], (n_batches,), np.int32, 1),
    }
    if shapes.has_Q:
        out["final_Q"] = (["member"] + qd, (B,) + q, np.float64, bs)
    if shapes.has_xi:
        out["final_xi"] = (["member"] + xd, (B,) + x, np.float64, bs)
    if members.P0 is not None:
        out["P0"] = (["ic"] + qd, members.P0.shape, np.float64, bs)
    if members.builder is not None:
        for i, leaf in enumerate(jax.tree_util.tree_leaves(members.params)):
            shape = tuple(np.shape(leaf))
            out[f"params_{i}"] = (["param"] + _dims(f"params_{i}_axis", shape[1:]), shape, np.float64, bs)
    for k, (name, v) in enumerate(shapes.invariants.items()):
        if name == "energy":
            continue
        tail = tuple(v.shape[1:])
        out[f"initial_{k}"] = (["member"] + _dims(f"initial_{k}_axis", tail), (B,) + tail, v.dtype, bs)
        out[f"drift_{k}"] = (["member"], (B,), np.float64, bs)
    out["initial_energy"] = (["member"], (B,), shapes.invariants["energy"].dtype, bs)
    if run.save_every is not None:
        S = len(range(0, run.n_steps + 1, run.save_every))
        out["saved_step"] = (["node"], (S,), np.int64, S)
        out["saved_t"] = (["member", "node"], (B, S), np.float64, bs)
        out["saved_momentum"] = (["member", "node"] + xd, (B, S) + x, np.float64, bs)
        if shapes.has_Q:
            out["saved_Q"] = (["member", "node"] + qd, (B, S) + q, np.float64, bs)
        if shapes.has_xi:
            out["saved_xi"] = (["member", "node"] + xd, (B, S) + x, np.float64, bs)
    return out


def _invariant_keys(shapes) -> dict:
    """{invariant name: the suffix of its arrays}: its position, since a name may hold any character."""
    return {name: ("energy" if name == "energy" else str(k)) for k, name in enumerate(shapes.invariants)}


def _create(zarr, store, plan, config: dict):
    with zarr.config.set({"array.write_empty_chunks": True}):
        # the owner first, in the group's own metadata: a store whose creation is interrupted is ours
        return _fill(
            zarr.open_group(_plain(store), mode="w", attributes={OWNER: OWNER_VALUE, "created_by": _creator()}),
            plan,
            config,
        )


def _fill(root, plan, config: dict):
    from zarr.codecs import Crc32cCodec, ZstdCodec

    for name, (dims, shape, dtype, chunk) in _variables(plan).items():
        chunks = (max(1, min(chunk, shape[0])),) + tuple(shape[1:]) if shape else ()
        fill = False if dtype == np.bool_ else (0 if np.issubdtype(dtype, np.integer) else np.nan)
        fill = int(Status.NOT_RUN) if name == "status" else fill  # an unwritten member is no success
        # every chunk compressed, then checksummed (CRC-32C of the stored bytes): a flipped bit is
        # an error when the chunk is read, never a changed number
        root.create_array(
            name,
            shape=shape,
            dtype=dtype,
            chunks=chunks,
            dimension_names=dims,
            fill_value=fill,
            compressors=[ZstdCodec(), Crc32cCodec()],
        )
    _write_inputs(root, plan)
    keys = _invariant_keys(plan.shapes)
    # the configuration last: a store without it was not finished being created
    root.attrs.update(
        {
            "invariant_arrays": keys,
            "runs": 0,
            "description": "clebsch_jax.sweep table",
            **{k: config[k] for k in ("method", "dt", "n_steps", "package_version")},
            ATTR: config,
        }
    )
    return root


def _inputs(plan) -> dict:
    """{array: its data} of the arrays written when the store is created (the inputs, the
    members' rows of them, the saved steps): every other array is written batch by batch."""
    import jax

    members, run = plan.members, plan.run
    out = {
        "member": np.arange(members.B),
        "param_index": members.param_index,
        "ic_index": members.ic_index,
        "dt": members.dt,
        "Q0": members.Q0,
        "xi0": members.xi0,
    }
    if members.P0 is not None:
        out["P0"] = members.P0
    if members.builder is not None:
        for i, leaf in enumerate(jax.tree_util.tree_leaves(members.params)):
            out[f"params_{i}"] = np.asarray(leaf)
    if run.save_every is not None:
        out["saved_step"] = np.arange(0, run.n_steps + 1, run.save_every)
    return out


def _write_inputs(root, plan, names=None):
    for name, data in _inputs(plan).items():
        if names is None or name in names:
            root[name][:] = data


def _open_group(zarr, store, mode: str):
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
        stored = _zarr().open_group(_plain(store), mode="r").attrs.get(ATTR)
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
        entries = sorted(os.listdir(path))
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
                f"store {name!r}: is being created by {creator}. Wait for it to start its "
                "batches and run the same sweep again to share them, or give another path. "
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
    if host == me["host"]:
        if pid == me["pid"] or not isinstance(pid, int):
            return None
        try:
            os.kill(pid, 0)  # signal 0: only whether the process exists
        except ProcessLookupError:
            return None
        except PermissionError:  # it exists, under another user
            pass
    return f"process {pid} on host {host}"


def open_for_run(store, plan, overwrite: bool):
    """The store of this sweep: created, or reopened after checking its configuration. Only a
    store recognised as a sweep's (`_inspect`) is ever replaced, and only with `overwrite`."""
    zarr = _zarr()
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
        root = _open_group(zarr, store, "r+")
        _check_layout(root, plan, name)
        return root
    try:
        return _create(zarr, store, plan, config)
    except OSError as err:  # e.g. a read-only file system, no permission
        raise SweepStoreError(f"store {name!r}: cannot be written ({err.strerror or err}).") from err


def _check_layout(root, plan, name: str):
    """Every array the configuration implies is there with its shape: else a clear error."""
    have = set(root.array_keys())
    for var, (_, shape, _, _) in _variables(plan).items():
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


def _written_by_batches(root) -> list:
    """The arrays written batch by batch (`write_rows`): those over `member`, less the inputs'
    rows written when the store was created."""
    created = {"member", "param_index", "ic_index", "dt"}
    return [
        k
        for k in sorted(root.array_keys())
        if k not in created and (root[k].metadata.dimension_names or (None,))[0] == "member"
    ]


def _chunk_problem(root, var: str, b: int, bs: int):
    """None if batch b's rows of `var` (exactly one chunk: per-member arrays are chunked by the
    batch size) are there and read back; else what is wrong with them."""
    from zarr.core.sync import sync

    arr = root[var]
    key = f"{arr.path}/{arr.metadata.encode_chunk_key((b,) + (0,) * (arr.ndim - 1))}"
    try:
        if not sync(root.store.exists(key)):
            return "a missing chunk"
        arr[b * bs : (b + 1) * bs]
    except Exception as err:  # a checksum mismatch, a truncated chunk: codecs raise many kinds
        return f"{type(err).__name__}: {err}"
    return None


def damaged_batches(root, batches, bs: int) -> dict:
    """{batch: (array, what is wrong)} of the given batches whose data cannot be read back."""
    found = {}
    for var in _written_by_batches(root):
        for b in batches:
            if b not in found:
                problem = _chunk_problem(root, var, b, bs)
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
        print(
            f"sweep: store {name!r}: batch {b} (members {b * bs}-{min((b + 1) * bs, plan.members.B) - 1}) is "
            f"damaged ({var!r}: {problem}): computing it again.",
            file=sys.stderr,
            flush=True,
        )
        root["batch_done"][b] = False
        done[b] = False
    broken = []
    for var in _inputs(plan):
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
        _write_inputs(root, plan, broken)
    return done


def write_rows(root, plan, rows, run_id: int):
    """Write finished batches (a `_Rows`) into the store: data first, then each batch's flags."""
    shapes = plan.shapes
    keys = _invariant_keys(shapes)
    part = rows.tables
    arrays = {k: part.columns[k] for k in _COLUMNS if part.columns[k] is not None and k != "status"}
    for name, key in keys.items():
        arrays[f"initial_{key}"] = part.initial[name]
        if name != "energy":
            arrays[f"drift_{key}"] = part.drift[name]
    arrays["energy_error"] = part.drift["energy"]
    if part.saved is not None:
        arrays.update({f"saved_{k}": part.saved[k] for k in _SAVED if part.saved[k] is not None})
    arrays["status"] = part.columns["status"]  # the last data: a member with a status has all its data
    start = 0
    spans = []
    for r in rows.rows:
        n = r.stop - r.start
        spans.append((r, slice(start, start + n)))
        start += n
    # every chunk written, even one that equals the fill value: a missing chunk means a truncated store
    with _zarr().config.set({"array.write_empty_chunks": True}):
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
        _zarr().consolidate_metadata(_plain(store))
    return run_id


# --------------------------------------------------------------------------------------------
# Reading back.


def open_sweep(store):
    """The `SweepResult` of a finished sweep written to `store` (`cj.sweep(..., store=)`).

    **Arguments:**

    - `store`: the store's path or a `zarr` store.

    **Returns:** a `SweepResult` equal to the bit to the one the sweep returned (its
    `n_devices` is 1).

    Raises `SweepStoreError` naming the store when it is not a sweep store, when some batches
    are not written yet (rerun the sweep with the same store to finish them), or when it is
    truncated or corrupted. For analysis, `xarray.open_zarr(store)` reads the same arrays with
    their dimension names.
    """
    from .sweep import SweepResult

    zarr = _zarr()
    name = store_name(store)
    root = _open_group(zarr, store, "r")
    config = root.attrs.get(ATTR)
    if config is None:
        raise SweepStoreError(f"store {name!r}: holds no clebsch_jax sweep (no attribute {ATTR!r}).")
    done = done_batches(root, name)
    if not done.all():
        raise SweepStoreError(
            f"store {name!r}: {int((~done).sum())} of {len(done)} batches are not written yet "
            "(the sweep was interrupted): run the same sweep with this store to finish it."
        )
    keys = root.attrs.get("invariant_arrays", {})
    per_member = {
        "param_index",
        "ic_index",
        "energy_error",
        *_COLUMNS,
        *(f"{kind}_{key}" for key in keys.values() for kind in ("initial", "drift")),
        *(f"saved_{k}" for k in _SAVED),
    }

    def read(var, required=True):
        if var not in root.array_keys():
            if required:
                raise SweepStoreError(f"store {name!r}: the array {var!r} is missing (a truncated or corrupted store).")
            return None
        try:
            arr = root[var]
            if var in per_member and arr.nchunks_initialized < arr.nchunks:
                raise SweepStoreError(
                    f"store {name!r}: {arr.nchunks - arr.nchunks_initialized} of {arr.nchunks} "
                    f"chunks of {var!r} are missing (a truncated store){_which(var)}"
                )
            return np.asarray(arr[...])
        except SweepStoreError:
            raise
        except Exception as err:  # a checksum mismatch, a truncated chunk: codecs raise many kinds
            raise SweepStoreError(
                f"store {name!r}: cannot read {var!r} ({type(err).__name__}: {err}): a damaged store{_which(var)}"
            ) from err

    def _which(var):
        """Which batches of `var` are damaged, and what a rerun does about them."""
        if var not in _written_by_batches(root):
            return "; run the same sweep with this store: it writes the inputs again."
        bs = config["batch_size"]
        bad = sorted(b for b in range(len(done)) if _chunk_problem(root, var, b, bs) is not None)
        return (
            f": batch{'es' if len(bad) > 1 else ''} {', '.join(map(str, bad))}; run the same sweep with this "
            "store: it computes only the damaged batches again."
        )

    columns = {k: read(k, required=k not in ("final_Q", "final_xi")) for k in _COLUMNS}
    drift = {"energy": read("energy_error")}
    initial = {}
    for inv, key in keys.items():
        initial[inv] = read(f"initial_{key}")
        if inv != "energy":
            drift[inv] = read(f"drift_{key}")
    saved = None
    if config["save_every"] is not None:
        saved = {
            "step": read("saved_step"),
            "t": read("saved_t"),
            "Q": read("saved_Q", False),
            "xi": read("saved_xi", False),
            "momentum": read("saved_momentum"),
        }
    return SweepResult(
        param_index=read("param_index"),
        ic_index=read("ic_index"),
        energy_error=drift["energy"],
        drift=drift,
        initial=initial,
        saved=saved,
        n_steps=config["n_steps"],
        chunk_steps=config["chunk_steps"],
        batch_size=config["batch_size"],
        n_devices=1,
        form=config["form"],
        scheme=config["scheme"],
        order=config["order"],
        method=config["method"],
        **columns,
    )


# --------------------------------------------------------------------------------------------
# A stored sweep: skip what is done, run the rest (here or on a Dask cluster), read it back.


def check_arguments(store, client, overwrite) -> None:
    """`sweep`'s `store`, `client` and `overwrite`, checked before anything is traced or compiled
    (the optional packages they need named with the extra that installs them)."""
    if overwrite not in (True, False):
        raise ValueError(f"overwrite: expected True or False, got {overwrite!r}.")
    if overwrite and store is None:
        raise ValueError("overwrite: True replaces a store, but no store= was given.")
    if store is not None:
        zarr = _zarr()
        if isinstance(store, (str, bytes)) and not store:
            raise ValueError("store: expected a path or a zarr store, got an empty string.")
        _inspect(zarr, store)  # a path that is not a sweep store of ours is refused here already
    if client is not None:
        from .distributed import check_client

        check_client(client)


def run_stored(plan, run, tables, *, store, client, overwrite: bool, report, make_result):
    """`sweep` with `store=` and/or `client=`: called by `sweep` after `check_arguments` and its
    own checks."""
    from .sweep import _place, _run_batches

    B, bs = plan.members.B, plan.batch_size
    n_batches = -(-B // bs)
    if store is None:  # a Dask cluster, the table kept in memory
        from .distributed import run_on_client

        chunks = np.zeros(3, int)
        for rows in run_on_client(client, plan, list(range(n_batches)), None, 0, run.progress):
            _place(tables, rows.tables, rows.rows)
            chunks += rows.fast_chunks
        return make_result(plan, tables, 1, chunks)
    name = store_name(store)
    root = open_for_run(store, plan, overwrite)
    done = done_batches(root, name)
    if done.any():  # reopened: every chunk of the finished batches is read back (checksums)
        done = repair(root, plan, done, name)
    pending = [b for b in range(n_batches) if not done[b]]
    if len(pending) < n_batches:
        skipped = B - sum(min(bs, B - b * bs) for b in pending)
        print(
            f"sweep: store {name!r}: skipped {skipped} of {B} members already written "
            f"({n_batches - len(pending)} of {n_batches} batches); computing the other {len(pending)} batches.",
            file=sys.stderr,
            flush=True,
        )
    run_id = start_run(root, store)
    if client is not None:
        from .distributed import run_on_client

        for _ in run_on_client(client, plan, pending, store, run_id, run.progress):
            pass
        return open_sweep(store)
    # Each group's rows go to the store from a writer thread while the next group computes; the
    # table is kept in memory too. Leaving the `with` (also on Ctrl-C) waits for the writes under way.
    slots, used, chunks = run.slots, set(), np.zeros(3, int)
    with ThreadPoolExecutor(1, thread_name_prefix="clebsch-jax-sweep-store") as writer:
        writes = []
        for g in range(0, len(pending), len(slots)):
            rows = _run_batches(plan, pending[g : g + len(slots)], slots, report)
            used.update(rows.devices)
            chunks += rows.fast_chunks
            _place(tables, rows.tables, rows.rows)
            writes.append(writer.submit(write_rows, root, plan, rows, run_id))
            for w in writes:
                if w.done():
                    w.result()  # a failed write stops the sweep now
        for w in writes:
            w.result()
    if run.progress is True:
        print(file=sys.stderr, flush=True)
    if len(pending) < n_batches:  # resumed: the skipped batches' rows are in the store only
        return open_sweep(store)
    return make_result(plan, tables, len(used), chunks)
