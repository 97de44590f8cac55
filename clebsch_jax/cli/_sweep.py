"""`clebsch-jax sweep CONFIG.toml --store OUT.zarr [--workers N | --scheduler ADDRESS]`.

A parameter sweep described by a TOML file (`FORMAT` below, also the command's help), run by
`clebsch_jax.sweep` into a Zarr store: in this process, on a `LocalCluster` of `--workers`
processes, or on an existing Dask cluster (`--scheduler`). A tqdm bar counts finished batches
with an ETA; the summary table follows. Ctrl-C stops after cancelling the outstanding work:
the batches already written stay in the store and the same command resumes from them.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import time

import numpy as np

import clebsch_jax as cj

FORMAT = """\
CONFIG.toml:

  model = "rigid_body"      # a function of clebsch_jax.models, or "package.module:function"
                            # (importable by the workers): make_system(params_row)
  dt = 0.05                 # time step > 0
  n_steps = 1000            # steps per member
  grid = true               # every parameter row with every initial condition
                            # (false: row m with initial condition m)
  batch_size = 1024         # optional: members per compiled call (default min(members, 1024))
  chunk_steps = 100         # optional: steps per integrate call
  save_every = 10           # optional: keep every 10th node in the store

  [params]                  # the parameter rows, one of:
  values = [[2.0, 1.0, 0.5], [1.0, 1.0, 0.5]]        # explicit rows
  # linspace = [[0.5, 1.5, 9], [0.5, 1.5, 9], [1, 1, 1]]  # every combination of the
                            # columns' numpy.linspace(start, stop, num)

  [initial]
  Q0 = {identity = 3}       # the 3x3 identity for every initial condition; or {value = [...]}
                            # (one shared Q0), or [[...], ...] (one per initial condition)
  xi0 = {normal = [24, 3], seed = 0, scale = 1.0}   # random normal rows; or [[...], ...]

  [options]                 # optional: integrate options (scheme, reduce, order, rtol, ...)
  reduce = true

  [invariants]              # optional: name = "package.module:function" (f(system, sol)),
                            # or the name of a clebsch_jax.diagnostics function
  body_momentum = "body_momentum"
"""


class ConfigError(ValueError):
    """A CONFIG.toml that cannot be run: the message names the entry."""


def _toml(path: str) -> dict:
    try:
        import tomllib
    except ImportError:  # Python 3.10
        try:
            import tomli as tomllib
        except ImportError:
            raise ConfigError("reading TOML needs Python >= 3.11 or the tomli package (pip install tomli)") from None
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except OSError as err:
        raise ConfigError(f"cannot read {path!r}: {err.strerror or err}") from None
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{path}: not valid TOML: {err}") from None


def _function(spec, where: str, default_module):
    """`"package.module:function"`, or the name of a function of `default_module`."""
    if not isinstance(spec, str):
        raise ConfigError(f"{where}: expected a function name or 'package.module:function', got {spec!r}")
    if ":" in spec:
        module, _, name = spec.partition(":")
        try:
            fn = getattr(importlib.import_module(module), name)
        except (ImportError, AttributeError) as err:
            raise ConfigError(f"{where}: cannot import {spec!r} ({err})") from None
    else:
        fn = getattr(default_module, spec, None)
        if fn is None or spec.startswith("_"):
            raise ConfigError(
                f"{where}: {default_module.__name__} has no function {spec!r}; use "
                "'package.module:function' for your own"
            )
    if not callable(fn):
        raise ConfigError(f"{where}: {spec!r} is not a function")
    return fn


def _array(value, where: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: expected an array of numbers (equal-length rows), got {value!r}") from None
    if arr.ndim < 1 or arr.shape[0] < 1:
        raise ConfigError(f"{where}: expected at least one row, got {value!r}")
    return arr


def _known(table: dict, known: set, where: str) -> None:
    """Refuse a key of `table` outside `known` (a misspelled one would be ignored silently)."""
    unknown = sorted(set(table) - known)
    if unknown:
        raise ConfigError(
            f"{where}: unknown entr{'ies' if len(unknown) > 1 else 'y'} {', '.join(unknown)} "
            f"(known: {', '.join(sorted(known))})"
        )


def _params(table) -> np.ndarray:
    if isinstance(table, dict):
        _known(table, {"values", "linspace"}, "[params]")
    if not isinstance(table, dict) or len(table.keys() & {"values", "linspace"}) != 1:
        raise ConfigError("[params]: give exactly one of values = [[...], ...] or linspace = [[start, stop, num], ...]")
    if "values" in table:
        return _array(table["values"], "[params] values")
    cols = []
    for i, spec in enumerate(table["linspace"] if isinstance(table["linspace"], list) else [None]):
        if not (isinstance(spec, list) and len(spec) == 3 and isinstance(spec[2], int) and spec[2] >= 1):
            raise ConfigError(
                f"[params] linspace[{i}]: expected [start, stop, num] with num a whole number >= 1, got {spec!r}"
            )
        cols.append(np.linspace(float(spec[0]), float(spec[1]), spec[2]))
    return np.stack([g.ravel() for g in np.meshgrid(*cols, indexing="ij")], axis=-1)


def _initial(table) -> tuple:
    if not isinstance(table, dict) or "xi0" not in table or "Q0" not in table:
        raise ConfigError("[initial]: needs Q0 and xi0")
    _known(table, {"Q0", "xi0"}, "[initial]")
    xi = table["xi0"]
    if isinstance(xi, dict):
        _known(xi, {"normal", "seed", "scale"}, "[initial] xi0")
        shape, seed, scale = xi.get("normal"), xi.get("seed", 0), xi.get("scale", 1.0)
        if not (isinstance(shape, list) and shape and all(isinstance(n, int) and n >= 1 for n in shape)):
            raise ConfigError(f"[initial] xi0: expected {{normal = [n, d, ...], seed = 0, scale = 1.0}}, got {xi!r}")
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise ConfigError(f"[initial] xi0: seed must be a whole number >= 0, got {seed!r}")
        if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not np.isfinite(scale):
            raise ConfigError(f"[initial] xi0: scale must be a finite number, got {scale!r}")
        xi0 = float(scale) * np.random.default_rng(seed).standard_normal(tuple(shape))
    else:
        xi0 = _array(xi, "[initial] xi0")
    q = table["Q0"]
    n = xi0.shape[0]
    if isinstance(q, dict) and len(q) != 1:
        raise ConfigError(f"[initial] Q0: expected {{identity = d}} or {{value = [...]}}, got {q!r}")
    if isinstance(q, dict) and "identity" in q:
        d = q["identity"]
        if not (isinstance(d, int) and d >= 1):
            raise ConfigError(f"[initial] Q0: identity = d needs a whole number d >= 1, got {d!r}")
        Q0 = np.broadcast_to(np.eye(d), (n, d, d))
    elif isinstance(q, dict) and "value" in q:
        one = _array(q["value"], "[initial] Q0 value")
        Q0 = np.broadcast_to(one, (n,) + one.shape)
    elif isinstance(q, dict):
        raise ConfigError(
            f"[initial] Q0: expected {{identity = d}}, {{value = [...]}} or one row per initial condition, got {q!r}"
        )
    else:
        Q0 = _array(q, "[initial] Q0")
    return Q0, xi0


def load(path: str) -> dict:
    """CONFIG.toml as `clebsch_jax.sweep`'s arguments (a dict); ConfigError names a bad entry."""
    cfg = _toml(path)
    known = {
        "model",
        "dt",
        "n_steps",
        "grid",
        "batch_size",
        "chunk_steps",
        "save_every",
        "params",
        "initial",
        "options",
        "invariants",
    }
    unknown = sorted(set(cfg) - known)
    if unknown:
        raise ConfigError(
            f"{path}: unknown entr{'ies' if len(unknown) > 1 else 'y'} {', '.join(unknown)} "
            f"(known: {', '.join(sorted(known))})"
        )
    for key in ("model", "dt", "n_steps", "params", "initial"):
        if key not in cfg:
            raise ConfigError(f"{path}: missing {key!r} (see 'clebsch-jax sweep --help')")
    Q0, xi0 = _initial(cfg["initial"])
    invariants = cfg.get("invariants", {})
    if not isinstance(invariants, dict):
        raise ConfigError('[invariants]: expected a table name = "package.module:function"')
    options = cfg.get("options", {})
    if not isinstance(options, dict):
        raise ConfigError("[options]: expected a table of integrate options")
    args = dict(
        make_system=_function(cfg["model"], "model", cj.models),
        params=_params(cfg["params"]),
        Q0=Q0,
        xi0=xi0,
        dt=cfg["dt"],
        n_steps=cfg["n_steps"],
        grid=cfg.get("grid", False),
        invariants={k: _function(v, f"[invariants] {k}", cj.diagnostics) for k, v in invariants.items()},
        chunk_steps=cfg.get("chunk_steps"),
        save_every=cfg.get("save_every"),
        **options,
    )
    n_members = len(args["params"]) * len(Q0) if args["grid"] is True else len(Q0)
    args["batch_size"] = cfg.get("batch_size", min(n_members, 1024))
    return args


def _n_members(args) -> int:
    return len(args["params"]) * len(args["Q0"]) if args["grid"] is True else len(args["Q0"])


def _already_done(store: str, n_batches: int) -> np.ndarray:
    """Which batches an existing store marks done (none if it has no such flags: sweep decides)."""
    try:
        import zarr

        done = np.asarray(zarr.open_group(store, mode="r")["batch_done"][:], bool)
    except Exception:  # no store yet, or one sweep will refuse with its own message
        return np.zeros(n_batches, bool)
    return done if done.shape == (n_batches,) else np.zeros(n_batches, bool)


def _summary(res, store: str, wall: float, members_run: int) -> str:
    ok = res.succeeded
    steps = res.n_steps
    rows = [
        (
            "members",
            f"{len(res):,} x {steps:,} steps ({res.form} march, {res.method or res.scheme}, order {res.order})",
        ),
        (
            "failed",
            f"{len(res.failed_members):,}"
            + (
                f" (first: member {res.failed_members[0]} at step {int(res.failed_step[res.failed_members[0]])})"
                if len(res.failed_members)
                else ""
            ),
        ),
        (
            "wall time",
            f"{wall:.1f} s for {members_run:,} members computed in this run"
            + (f" ({members_run * steps / wall:,.0f} member-steps/s)" if members_run and wall > 0 else ""),
        ),
        ("Newton iterations/step", f"{np.mean(res.newton_iterations) / steps:.2f} mean"),
    ]
    for name, v in res.drift.items():
        label = "energy error (max abs.)" if name == "energy" else f"{name} drift (max abs.)"
        rows.append((label, f"{np.max(v[ok]):.3e}" if ok.any() else "n/a"))
    rows.append(("store", f"{store} (xarray.open_zarr / clebsch_jax.open_sweep)"))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"  {k:<{width}}  {v}" for k, v in rows)


def run(args) -> int:
    from ._arguments import PROG
    from ._setup import fail

    prog = f"{PROG} sweep"
    try:
        kwargs = load(args.config)
    except (ValueError, TypeError) as err:  # ConfigError names the entry; anything else, the file
        return fail(str(err) if isinstance(err, ConfigError) else f"{args.config}: {err}", code=2, prog=prog)
    try:
        from tqdm import tqdm
    except ImportError:
        return fail('the progress bar needs tqdm: pip install "clebsch-jax[sweep]"', prog=prog)
    B = _n_members(kwargs)
    bs = kwargs["batch_size"]
    if isinstance(bs, int) and bs > B > 0:  # clamped by cj.sweep: the batches it runs
        bs = B
    n_batches = -(-B // bs) if isinstance(bs, int) and bs > 0 else 0
    done = _already_done(args.store, n_batches) if not args.overwrite else np.zeros(n_batches, bool)
    before = int(done.sum())
    members_run = B - sum(min(bs, B - b * bs) for b in np.flatnonzero(done))
    client = cluster = None
    try:
        if args.workers or args.scheduler:
            try:
                import distributed
            except ImportError:
                return fail('--workers/--scheduler need dask.distributed: pip install "clebsch-jax[sweep]"', prog=prog)
            if args.scheduler:
                client = distributed.Client(args.scheduler)
            else:
                from ..batching.distributed import worker_environment

                # one XLA and BLAS thread per one-thread worker (the user's own XLA_FLAGS kept)
                single = {k: v for k, v in worker_environment().items() if os.environ.get(k) != v}
                cluster = distributed.LocalCluster(
                    n_workers=args.workers, threads_per_worker=1, processes=True, dashboard_address=None, env=single
                )
                client = distributed.Client(cluster)
        where = (
            f"on the Dask cluster at {args.scheduler}"
            if args.scheduler
            else f"on {args.workers} local worker processes"
            if args.workers
            else "in this process"
        )
        print(
            f"{prog}: {B:,} members x {kwargs['n_steps']:,} steps in {n_batches} batches of {bs}, {where}, "
            f"into {args.store}",
            flush=True,
        )
        bar = tqdm(
            total=n_batches,
            initial=before,
            unit="batch",
            desc="sweep",
            disable=args.quiet,
            dynamic_ncols=True,
            file=sys.stderr,
        )

        def progress(info):
            if info.step == info.n_steps:
                bar.update(1)

        tic = time.perf_counter()
        try:
            res = cj.sweep(**kwargs, store=args.store, client=client, overwrite=args.overwrite, progress=progress)
        finally:
            bar.close()
        wall = time.perf_counter() - tic
    except KeyboardInterrupt:
        print(
            f"{prog}: stopped; the finished batches are in {args.store}: run the same command to resume",
            file=sys.stderr,
        )
        return 130
    except cj.SweepStoreError as err:  # the store cannot be used (a file, another's data, read-only, ...)
        return fail(str(err), code=2, prog=prog)
    except (ValueError, TypeError) as err:  # the sweep refused its arguments, before compiling
        return fail(f"{args.config}: {err}", code=2, prog=prog)
    except OSError as err:  # writing failed under way (a full disk, a lost mount)
        return fail(
            f"store {args.store!r}: {err}; the batches written before are kept: run the same command to resume",
            prog=prog,
        )
    finally:
        if client is not None:
            client.close()
        if cluster is not None:
            cluster.close()
    print(_summary(res, args.store, wall, members_run))
    return 0


def add(subparsers) -> None:
    from ._arguments import paragraphs

    p = subparsers.add_parser(
        "sweep",
        help="a parameter sweep from a TOML file into a Zarr store (resumable; local or Dask workers)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=paragraphs(
            "Run the parameter sweep CONFIG.toml describes (clebsch_jax.sweep: every member's "
            "status, energy error, invariant drifts, Newton statistics and final state) and write "
            "each finished batch to the Zarr store --store. Read it with xarray.open_zarr(STORE) or "
            "clebsch_jax.open_sweep(STORE). Running the same command again resumes: the batches "
            "already in the store are skipped. A store written by another configuration is refused "
            "(--overwrite replaces it). Ctrl-C stops cleanly.",
            "Where the batches run: in this process (default), on --workers N local worker "
            "processes (a dask LocalCluster, one thread each), or on an existing Dask cluster "
            "(--scheduler ADDRESS, e.g. tcp://host:8786; the store must be reachable from every "
            "worker).",
            FORMAT,
        ),
        epilog="example: clebsch-jax sweep sweep.toml --store sweep.zarr --workers 2",
    )
    p.add_argument("config", metavar="CONFIG.toml", help="the sweep's configuration (format above)")
    p.add_argument("--store", required=True, metavar="OUT.zarr", help="the Zarr store (created, or resumed)")
    where = p.add_mutually_exclusive_group()
    where.add_argument(
        "--workers",
        type=_workers,
        default=None,
        metavar="N",
        help="run on a LocalCluster of N worker processes (one thread each)",
    )
    where.add_argument(
        "--scheduler", default=None, metavar="ADDRESS", help="run on the Dask cluster whose scheduler is at ADDRESS"
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace a store written by another configuration instead of refusing it",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar (the summary is still printed)")
    p.set_defaults(handler=run)


def _workers(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1 or n > (os.cpu_count() or 1) * 4:
        raise argparse.ArgumentTypeError(
            f"expected a whole number of worker processes from 1 to {(os.cpu_count() or 1) * 4}, got {text!r}"
        )
    return n
