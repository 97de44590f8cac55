"""Native kernels: a jaxpr of one batch member compiled to SIMD machine code with LLVM.

`compile_member(fun, *member_args)` traces `fun` on one member's arguments and compiles its
jaxpr (`clebsch_jax.native.kernel.Kernel`); the result runs a batch (arrays with a leading
member axis) with `W` members per vector, every member's loops masked per lane as under
`jax.vmap`. `compile_loop(body, *member_args)` compiles the body of a loop instead: its
kernel runs the body a given number of times and writes each iteration's records (a march's
steps, `clebsch_jax.march.native_chunk`). `available()` says whether llvmlite can be
imported; `Unsupported` is raised for programs the translation does not cover (its message
names the primitive).
"""

from __future__ import annotations

import copy
import threading
import warnings

__all__ = [
    "available",
    "compile_member",
    "compile_loop",
    "Unsupported",
    "TooLarge",
    "NativeFunction",
    "NativeLoop",
    "BACKENDS",
    "AUTO_MAX_IR_LINES",
    "check_backend",
    "native_unavailable",
    "warn_once",
    "NativeFallbackWarning",
    "compiled_once",
]

BACKENDS = ("auto", "native", "xla")
"""The values of `backend=` (`clebsch_jax.sweep`, `clebsch_jax.integrate`, `clebsch_jax.batch`):
"native" runs the native kernel (an error where it cannot), "xla" XLA's program, "auto" the
native kernel wherever it applies and XLA elsewhere, saying once why (`warn_once`)."""

AUTO_MAX_IR_LINES = 50_000
"""`backend="auto"` compiles a native kernel whose LLVM IR has at most this many lines (a kernel
in the disk cache is always used): LLVM's time grows with the IR, to tens of seconds for the
largest programs the translation covers, where XLA compiles in a few. Larger kernels run on
XLA, with the reason said once; `backend="native"` compiles them.
(`benchmarks/README.md`, `native.py`, records the sizes and times behind the value.)"""


class NativeFallbackWarning(UserWarning):
    """`backend="auto"` ran XLA where a native kernel was wanted; the message says why."""


def check_backend(backend) -> str:
    """`backend` if it is one of `BACKENDS` (a `ValueError` naming `backend` otherwise)."""
    if not (isinstance(backend, str) and backend in BACKENDS):
        raise ValueError(f"backend: expected one of {BACKENDS}, got {backend!r}.")
    return backend


def native_unavailable(devices=(None,)) -> str | None:
    """Why native kernels cannot run here (None: they can): llvmlite missing, or a device that
    is not the host CPU (the native kernels are for CPUs; an accelerator keeps XLA)."""
    if not available():
        return "llvmlite cannot be imported (pip install llvmlite)"
    import jax

    for d in devices:
        device = d if d is not None else jax.devices()[0]
        if getattr(device, "platform", "cpu") != "cpu":
            return f"the device {device} is not the host CPU"
    return None


_WARNED: set = set()
_WARN_LOCK = threading.Lock()


def warn_once(reason: str, what: str = "the batch", stacklevel: int = 3) -> None:
    """Say once per process, `what` and reason that XLA runs where a native kernel was wanted."""
    with _WARN_LOCK:
        if (what, reason) in _WARNED:
            return
        _WARNED.add((what, reason))
    warnings.warn(
        f"clebsch_jax: running {what} with XLA, not a native kernel: {reason}.",
        NativeFallbackWarning,
        stacklevel=stacklevel,
    )


class Unsupported(NotImplementedError):
    """The program uses a primitive (or a form of one) that the native translation does not
    cover; its message names it. The callers then run the program with XLA. (Defined here, not
    beside the translation, so that it can be named where llvmlite cannot be imported.)"""


class TooLarge(Unsupported):
    """A program refused for its size: past the translation's limit of `entries`
    (`values.entries_limit`) or a kernel of `lines` lines of LLVM IR, past the budget it was
    built under. Recorded on disk under the program's record key (`refused`,
    `remember_refusal`), so that a new process falls back without tracing and translating it."""

    def __init__(self, message: str, lines: int | None = None, entries: int | None = None):
        super().__init__(message)
        self.lines, self.entries = lines, entries


def refused(record: str | None, max_lines) -> None:
    """Raise the `TooLarge` recorded under `record` (a program's record key) if it applies
    under the budget of `max_lines` lines of IR (None: the kernel was asked for): a refusal
    for the entries where this budget's limit of entries is at most the one refused, one for
    the lines of IR where `max_lines` is below those lines."""
    if record is None:
        return
    import json

    from .fingerprint import read
    from .values import entries_limit

    data = read(record, ".refused")
    if data is None:
        return
    try:
        found = json.loads(data)
        reason, lines, entries = str(found["reason"]), found["lines"], found["entries"]
    except Exception:  # a damaged record: translate again
        return
    if entries is not None and entries_limit(max_lines) <= int(entries):
        raise TooLarge(reason, entries=entries)
    if lines is not None and max_lines is not None and int(lines) > max_lines:
        raise TooLarge(reason, lines=lines)


def _kernel(record: str | None, closed, **options):
    """`Kernel(closed, **options)`; a refusal for its size is first recorded under `record`."""
    from .kernel import Kernel

    try:
        return Kernel(closed, **options)
    except TooLarge as err:
        remember_refusal(record, err)
        raise


def remember_refusal(record: str | None, err: Exception) -> None:
    """Keep a `TooLarge` refusal under `record` (other exceptions are not recorded)."""
    if record is None or not isinstance(err, TooLarge):
        return
    import json

    from .fingerprint import write

    write(record, ".refused", json.dumps({"reason": str(err), "lines": err.lines, "entries": err.entries}).encode())


def available() -> bool:
    """Whether native kernels can be built here (llvmlite imports)."""
    try:
        import llvmlite.binding  # noqa: F401
    except ImportError:
        return False
    return True


class NativeFunction:
    """`fun` of one member compiled for batches: call it with pytrees whose leaves have a
    leading member axis; it returns the outputs' pytree with the same leading axis.

    `key` (optional): a digest of everything `fun`'s trace depends on besides its arguments'
    structure, shapes and dtypes (`clebsch_jax.native.fingerprint.fingerprint` of the
    configuration `fun` is made from). A kernel compiled before under the same key, the same
    arguments' signature and the same environment (`fingerprint.environment`: this package's
    source, the versions, JAX's options) is then loaded from the disk cache without tracing
    `fun` (`from_record` is True); without a key `fun` is traced, and its jaxpr names the kernel.
    A program refused for its size (`TooLarge`) is recorded under the same key, and refused
    again without tracing (`refused`)."""

    def __init__(self, fun, *member_args, width=None, use_cache=True, in_axes=0, max_lines=None, key=None):
        import jax

        from .kernel import host_lanes

        self._in_tree = jax.tree_util.tree_structure(member_args)
        if not isinstance(in_axes, (tuple, list)):
            in_axes = (in_axes,) * len(member_args)
        flags = [jax.tree_util.tree_map(lambda _: ax is not None, arg) for ax, arg in zip(in_axes, member_args)]
        batched = jax.tree_util.tree_leaves(flags)
        width = width or host_lanes()
        record = _record_key(key, member_args, batched, width) if key is not None and use_cache else None
        self.from_record = record is not None and self._load(record)
        if self.from_record:
            return
        refused(record, max_lines)  # a program refused for its size before: not traced again
        closed, out_shape = jax.make_jaxpr(fun, return_shape=True)(*member_args)
        self._out_tree = jax.tree_util.tree_structure(out_shape)
        self.kernel = _kernel(
            record, closed, width=width, use_cache=use_cache, batched=batched, max_lines=max_lines, key=record
        )
        if record is not None:
            self._save(record)

    def _load(self, record: str) -> bool:
        import pickle

        from .fingerprint import read
        from .kernel import Kernel

        data = read(record, ".member")
        if data is None:
            return False
        try:
            found = pickle.loads(data)
            kernel = Kernel.from_record(found["kernel"])
        except Exception:  # a record of another version, or damaged: trace and write it again
            return False
        if kernel is None:
            return False
        self.kernel, self._out_tree = kernel, found["out_tree"]
        return True

    def _save(self, record: str) -> None:
        import pickle

        from .fingerprint import write

        try:
            data = pickle.dumps({"kernel": self.kernel.record(), "out_tree": self._out_tree})
        except Exception:  # an output tree with a node type pickle cannot name: traced next time
            return
        write(record, ".member", data)

    def __call__(self, *args, threads: int = 1, workspace=None):
        """`fun` for every member; `workspace`: see `clebsch_jax.native.kernel.Kernel`."""
        import jax
        import numpy as np

        leaves, tree = jax.tree_util.tree_flatten(args)
        if tree != self._in_tree:
            raise TypeError(f"arguments of structure {tree}, expected {self._in_tree}")
        outs = self.kernel(*[np.asarray(x) for x in leaves], threads=threads, workspace=workspace)
        return jax.tree_util.tree_unflatten(self._out_tree, outs)


def _record_key(key: str, member_args, batched: list, width: int) -> str | None:
    """The key of the record that names the kernel of `key`'s function on these arguments: the
    arguments' tree structure, shapes and dtypes, the lanes, the environment and the host
    (`kernel._key`: CPU, features, llvmlite, the translation's source). None when the
    arguments' structure cannot be fingerprinted."""
    import jax
    import numpy as np

    from .fingerprint import environment, fingerprint
    from .kernel import cache_key

    leaves, tree = jax.tree_util.tree_flatten(member_args)
    dtype = lambda x: x.dtype if hasattr(x, "dtype") else np.result_type(x)
    signature = fingerprint(
        (tree, [(np.shape(x), str(dtype(x)), bool(getattr(x, "weak_type", False))) for x in leaves])
    )
    if signature is None:
        return None
    return cache_key(f"member\n{key}\n{signature}\n{list(batched)}\n{width}\n{environment()}")


def compile_member(
    fun, *member_args, width=None, use_cache=True, in_axes=0, max_lines=None, key=None
) -> NativeFunction:
    """`NativeFunction(fun, *member_args)`: `fun` traced on one member's arguments and compiled.
    `in_axes` (0 or None per argument, as `jax.vmap`'s): an argument with None is shared by
    all members (passed without the member axis). `max_lines`: a kernel not in the disk cache
    whose LLVM IR has more lines than this is refused (`TooLarge`) before LLVM compiles it
    (`clebsch_jax.native.kernel.Kernel`); None (the kernel asked for) also lets the program
    translate to more entries (`values.entries_limit`). `key`: see `NativeFunction` (a kernel found by it is
    loaded without tracing `fun`)."""
    return NativeFunction(
        fun, *member_args, width=width, use_cache=use_cache, in_axes=in_axes, max_lines=max_lines, key=key
    )


class NativeLoop:
    """A loop body of one member compiled for batches (`compile_loop`): `body(*args, carry) ->
    (carry, record)`, with the carry the last argument. Call it with pytrees whose leaves have a
    leading member axis, `steps` (the iterations, the same for every member) and `capacity`
    (the records kept): it returns (the carry after `steps` iterations, the records stacked
    with shape (B, capacity, …), zero after the `steps` made)."""

    def __init__(self, body, *member_args, width=None, use_cache=True, in_axes=0, max_lines=None, key=None):
        import jax
        import numpy as np

        from .kernel import host_lanes

        if not isinstance(in_axes, (tuple, list)):
            in_axes = (in_axes,) * len(member_args)
        flags = [jax.tree_util.tree_map(lambda _: ax is not None, arg) for ax, arg in zip(in_axes, member_args)]
        batched = jax.tree_util.tree_leaves(flags)
        width = width or host_lanes()
        record = _record_key("loop\n" + key, member_args, batched, width) if key is not None and use_cache else None
        refused(record, max_lines)  # a body refused for its size before: not traced again
        closed, (carry_shape, record_shape) = jax.make_jaxpr(body, return_shape=True)(*member_args)
        self._in_tree = jax.tree_util.tree_structure(member_args)
        self._carry_tree = jax.tree_util.tree_structure(carry_shape)
        self._record_tree = jax.tree_util.tree_structure(record_shape)
        dtype = lambda x: np.dtype(x.dtype) if hasattr(x, "dtype") else np.result_type(x)
        shapes = lambda tree: [(np.shape(x), dtype(x)) for x in jax.tree_util.tree_leaves(tree)]
        if self._carry_tree != jax.tree_util.tree_structure(member_args[-1]) or shapes(carry_shape) != shapes(
            member_args[-1]
        ):
            raise TypeError("compile_loop: the body must return a carry of its last argument's structure and shapes")
        n = self._carry_tree.num_leaves
        self.kernel = _kernel(
            record, closed, width=width, use_cache=use_cache, batched=batched, max_lines=max_lines, carries=n
        )

    def record_rows(self, capacity: int) -> list:
        """Rows for `capacity` records of one member, one array per record leaf, aligned
        (`layout.aligned_empty`): a run's records, which calls with `records=` views of them
        (`record_views`) fill in place. Those of the last run (`keep_rows`) when they fit and
        its records were let go (`layout.SpareRows`), else new ones."""
        from .layout import SPARE_ROWS, aligned_empty

        specs = [((capacity * size, 1), storage) for _, size, storage, _ in self.kernel.record_layout()]
        found = SPARE_ROWS.take(specs)
        return found if found is not None else [aligned_empty(*spec) for spec in specs]

    def keep_rows(self, rows: list) -> None:
        """`record_rows`' rows, filled: a next run takes them again once nothing else holds them."""
        from .layout import SPARE_ROWS

        SPARE_ROWS.keep(rows)

    def record_views(self, rows: list, start: int, stop: int) -> list:
        """Records `start` to `stop` of `record_rows`' arrays, as the rows of one call's records."""
        return [r[start * size : stop * size] for r, (_, size, _, _) in zip(rows, self.kernel.record_layout())]

    def records(self, rows: list, count: int):
        """The first `count` records of `record_rows`' arrays as the record pytree, (count, …)
        views (a bool record as a bool copy)."""
        import jax

        from .layout import results

        layout = self.kernel.record_layout()
        cut = [r[: count * size] for r, (_, size, _, _) in zip(rows, layout)]
        out = results(cut, [rec[:3] for rec in layout], [rec[3] for rec in layout], 0, 1, 1, count)
        return jax.tree_util.tree_unflatten(self._record_tree, [a[0] for a in out])

    def __call__(self, *args, steps: int, capacity: int, records=None):
        import jax
        import numpy as np

        leaves, tree = jax.tree_util.tree_flatten(args)
        if tree != self._in_tree:
            raise TypeError(f"arguments of structure {tree}, expected {self._in_tree}")
        outs = self.kernel(*[np.asarray(x) for x in leaves], steps=steps, capacity=capacity, records=records)
        n = self._carry_tree.num_leaves
        carry = jax.tree_util.tree_unflatten(self._carry_tree, outs[:n])
        return carry, jax.tree_util.tree_unflatten(self._record_tree, outs[n:])


def compile_loop(body, *member_args, width=None, use_cache=True, in_axes=0, max_lines=None, key=None) -> NativeLoop:
    """`NativeLoop(body, *member_args)`: a loop body traced on one member's arguments (the
    carry last) and compiled to a kernel that runs it a given number of times, writing each
    iteration's records. `width`: members per vector (default the host's widest; 1 for a
    single member, whose other lanes would only repeat it). The other arguments are
    `compile_member`'s; `key` here only names a refusal for the body's size (`TooLarge`),
    recorded on disk so that a new process does not trace the body again."""
    return NativeLoop(
        body, *member_args, width=width, use_cache=use_cache, in_axes=in_axes, max_lines=max_lines, key=key
    )


def compiled_once(cache: dict, lock, limit: int, key, compile):
    """`compile()` (a native program), kept in `cache` under `key` behind `lock` (cleared when it
    holds `limit` entries): an `Unsupported` it raises is kept too (a copy without its
    traceback) and raised again as a new copy, so a program the translation refuses is not
    translated again and no caller's values are kept. A key that cannot be hashed compiles each
    time (the disk cache may still spare LLVM's work)."""
    try:
        with lock:
            found = cache.get(key)
        hashable = True
    except TypeError:
        found, hashable = None, False
    if found is None:
        try:
            found = compile()
        except Unsupported as err:
            # kept without its traceback: the frames of a traceback reach the callers' frames
            # and their values (a march's whole Solution), which the cache would keep alive;
            # cleared after the copy, which keeps them where exceptions pickle their tracebacks
            # (tblib's pickling support, which importing dask.distributed installs)
            found = copy.copy(err)
            found.__traceback__ = found.__cause__ = found.__context__ = None
        if hashable:
            with lock:
                if len(cache) >= limit:
                    cache.clear()
                cache[key] = found
    if isinstance(found, Exception):
        raise copy.copy(found)  # a new one each time: the kept one never holds a traceback
    return found
