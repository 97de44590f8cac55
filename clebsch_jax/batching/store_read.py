"""A sweep's Zarr store read back (`cj.open_sweep`): the `SweepResult` of a finished sweep, equal
to the bit to the one the sweep returned; a store that is not a sweep's, not finished, truncated
or damaged is refused naming the store and, where a rerun repairs it, the batches. Creating,
checking, resuming and writing a store: `clebsch_jax.batching.store`."""

from __future__ import annotations

import numpy as np

from .store import done_batches, open_group, store_name, zarr_module
from .store_layout import ATTR, COLUMNS, SAVED, chunk_problem, written_by_batches
from .store_lock import SweepStoreError
from .tables import SweepResult

__all__ = ["open_sweep"]


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
    zarr = zarr_module()
    name = store_name(store)
    root = open_group(zarr, store, "r")
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
        *COLUMNS,
        *(f"{kind}_{key}" for key in keys.values() for kind in ("initial", "drift")),
        *(f"saved_{k}" for k in SAVED),
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
        if var not in written_by_batches(root):
            return "; run the same sweep with this store: it writes the inputs again."
        bs = config["batch_size"]
        bad = sorted(b for b in range(len(done)) if chunk_problem(root, var, b, bs) is not None)
        return (
            f": batch{'es' if len(bad) > 1 else ''} {', '.join(map(str, bad))}; run the same sweep with this "
            "store: it computes only the damaged batches again."
        )

    columns = {k: read(k, required=k not in ("final_Q", "final_xi")) for k in COLUMNS}
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
