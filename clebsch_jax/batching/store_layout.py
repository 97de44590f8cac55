r"""What a sweep store holds: its arrays and their dimension names, and the configuration it
belongs to (`configuration`, with the digests of the inputs and of one member's traced program).

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

Creating, checking, resuming and writing a store: `clebsch_jax.batching.store`; reading it back:
`clebsch_jax.batching.store_read`.
"""

from __future__ import annotations

import hashlib
import re

import numpy as np

from ..roots.status import Status

ATTR = "clebsch_jax_sweep"
OWNER, OWNER_VALUE = "written_by", "clebsch_jax.sweep"  # the first attribute a new store gets: it is ours
FORMAT = 2  # the layout's version, part of the configuration

COLUMNS = (
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
SAVED = ("t", "Q", "xi", "momentum")


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
    from .config import first_row, system_of

    cfg, members = plan.cfg, plan.members
    j = int(members.ic_index[0])
    options = {k: v for k, v in cfg.options if k != "check_energy"}

    def member(p, s, q, x, d):
        system = system_of(cfg, p, s)
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
            backend="xla",  # traced (shapes only)
            **options,
        )
        return sol, [fn(system, sol) for _, fn in cfg.invariants]

    with undifferentiated():  # as the sweep's chunks are traced
        closed = jax.make_jaxpr(member)(
            first_row(members),
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


def variables(plan) -> dict:
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


def invariant_keys(shapes) -> dict:
    """{invariant name: the suffix of its arrays}: its position, since a name may hold any character."""
    return {name: ("energy" if name == "energy" else str(k)) for k, name in enumerate(shapes.invariants)}


def fill(root, plan, config: dict):
    from zarr.codecs import Crc32cCodec, ZstdCodec

    for name, (dims, shape, dtype, chunk) in variables(plan).items():
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
    write_inputs(root, plan)
    keys = invariant_keys(plan.shapes)
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


def inputs(plan) -> dict:
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


def write_inputs(root, plan, names=None):
    for name, data in inputs(plan).items():
        if names is None or name in names:
            root[name][:] = data


def written_by_batches(root) -> list:
    """The arrays written batch by batch (`store.write_rows`): those over `member`, less the inputs'
    rows written when the store was created."""
    created = {"member", "param_index", "ic_index", "dt"}
    return [
        k
        for k in sorted(root.array_keys())
        if k not in created and (root[k].metadata.dimension_names or (None,))[0] == "member"
    ]


def chunk_problem(root, var: str, b: int, bs: int):
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
