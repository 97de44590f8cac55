"""Native kernels: a jaxpr of one batch member compiled to SIMD machine code with LLVM.

`compile_member(fun, *member_args)` traces `fun` on one member's arguments and compiles its
jaxpr (`clebsch_jax.native.kernel.Kernel`); the result runs a batch (arrays with a leading
member axis) with `W` members per vector, every member's loops masked per lane as under
`jax.vmap`. `available()` says whether llvmlite can be imported; `Unsupported` is raised for
programs the translation does not cover (its message names the primitive).
"""

from __future__ import annotations

__all__ = ["available", "compile_member", "Unsupported", "NativeFunction"]


class Unsupported(NotImplementedError):
    """The program uses a primitive (or a form of one) that the native translation does not
    cover; its message names it. The callers then run the program with XLA. (Defined here, not
    beside the translation, so that it can be named where llvmlite cannot be imported.)"""


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
    `fun` (`from_record` is True); without a key `fun` is traced, and its jaxpr names the kernel."""

    def __init__(self, fun, *member_args, width=None, use_cache=True, in_axes=0, max_lines=None, key=None):
        import jax

        from .kernel import Kernel, host_lanes

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
        closed, out_shape = jax.make_jaxpr(fun, return_shape=True)(*member_args)
        self._out_tree = jax.tree_util.tree_structure(out_shape)
        self.kernel = Kernel(closed, width=width, use_cache=use_cache, batched=batched, max_lines=max_lines, key=record)
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

    def __call__(self, *args, threads: int = 1):
        import jax
        import numpy as np

        leaves, tree = jax.tree_util.tree_flatten(args)
        if tree != self._in_tree:
            raise TypeError(f"arguments of structure {tree}, expected {self._in_tree}")
        outs = self.kernel(*[np.asarray(x) for x in leaves], threads=threads)
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
    whose LLVM IR has more lines than this is refused (`Unsupported`) before LLVM compiles it
    (`clebsch_jax.native.kernel.Kernel`). `key`: see `NativeFunction` (a kernel found by it is
    loaded without tracing `fun`)."""
    return NativeFunction(
        fun, *member_args, width=width, use_cache=use_cache, in_axes=in_axes, max_lines=max_lines, key=key
    )
