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
    leading member axis; it returns the outputs' pytree with the same leading axis."""

    def __init__(self, fun, *member_args, width=None, use_cache=True, in_axes=0, max_lines=None):
        import jax

        from .kernel import Kernel

        closed, out_shape = jax.make_jaxpr(fun, return_shape=True)(*member_args)
        self._in_tree = jax.tree_util.tree_structure(member_args)
        self._out_tree = jax.tree_util.tree_structure(out_shape)
        if not isinstance(in_axes, (tuple, list)):
            in_axes = (in_axes,) * len(member_args)
        flags = [jax.tree_util.tree_map(lambda _: ax is not None, arg) for ax, arg in zip(in_axes, member_args)]
        batched = jax.tree_util.tree_leaves(flags)
        self.kernel = Kernel(closed, width=width, use_cache=use_cache, batched=batched, max_lines=max_lines)

    def __call__(self, *args, threads: int = 1):
        import jax
        import numpy as np

        leaves, tree = jax.tree_util.tree_flatten(args)
        if tree != self._in_tree:
            raise TypeError(f"arguments of structure {tree}, expected {self._in_tree}")
        outs = self.kernel(*[np.asarray(x) for x in leaves], threads=threads)
        return jax.tree_util.tree_unflatten(self._out_tree, outs)


def compile_member(fun, *member_args, width=None, use_cache=True, in_axes=0, max_lines=None) -> NativeFunction:
    """`NativeFunction(fun, *member_args)`: `fun` traced on one member's arguments and compiled.
    `in_axes` (0 or None per argument, as `jax.vmap`'s): an argument with None is shared by
    all members (passed without the member axis). `max_lines`: a kernel not in the disk cache
    whose LLVM IR has more lines than this is refused (`Unsupported`) before LLVM compiles it
    (`clebsch_jax.native.kernel.Kernel`)."""
    return NativeFunction(fun, *member_args, width=width, use_cache=use_cache, in_axes=in_axes, max_lines=max_lines)
