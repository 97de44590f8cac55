r"""A loop kernel's iterations (`clebsch_jax.native.kernel.build_ir` with `carries`): a loop body of
one member — one step of `integrate`'s march and the node it leaves — run a given number of
times with its carry in registers, each iteration's records stored at the iteration's rows.
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir

from .loops import for_range

__all__ = ["loop_iterations"]


def loop_iterations(em, closed, args, carries: int, steps, row) -> list:
    """`steps` iterations of the loop body `closed` (`build_ir`'s `carries`) from the carry in
    the last `carries` entries of `args`: the carry lives in allocas (registers, after LLVM's
    mem2reg), and each iteration's records are stored to their output arrays (`row(j, e,
    dtype)`: a pointer to entry `e` of output `j`, for the block being run) at the iteration's
    rows. Returns the carry after the last iteration."""
    from .lower import eval_closed  # the translation, which imports this module's neighbours

    b, i64 = em.b, ir.IntType(64)
    consts, init = list(args[: len(args) - carries]), list(args[len(args) - carries :])
    dtypes = [np.dtype(v.aval.dtype) for v in closed.jaxpr.invars[len(consts) :]]
    slots = []
    for x, dtype in zip(init, dtypes):
        arr = np.empty(x.shape, object)
        for idx in np.ndindex(x.shape):
            arr[idx] = em.alloca(em.vtype(dtype))
            b.store(em.vec(x[idx], dtype), arr[idx])
        slots.append(arr)

    def load():
        out = []
        for s, dtype in zip(slots, dtypes):
            arr = np.empty(s.shape, object)
            for idx in np.ndindex(s.shape):
                arr[idx] = b.load(s[idx], typ=em.vtype(dtype))
            out.append(arr)
        return out

    def iteration(k):
        outs = eval_closed(em, closed, consts + load())
        for s, new, dtype in zip(slots, outs[:carries], dtypes):
            for idx in np.ndindex(s.shape):
                b.store(em.vec(new[idx], dtype), s[idx])
        for j, (v, rec) in enumerate(zip(closed.jaxpr.outvars[carries:], outs[carries:])):
            dtype, size = np.dtype(v.aval.dtype), int(np.prod(v.aval.shape, dtype=int))
            for e, idx in enumerate(np.ndindex(v.aval.shape)):
                value = em.vec(rec[idx], dtype)
                if dtype == np.bool_:
                    value = b.zext(value, ir.VectorType(ir.IntType(8), em.W))
                # row k·size + e of record j: `row` of entry e, moved on by k·size rows
                at = row(carries + j, e, dtype)
                shift = b.mul(b.mul(k, ir.Constant(i64, size)), b.function.args[1])
                b.store(
                    value,
                    b.gep(at, [shift], source_etype=value.type.element),
                    align=1 if dtype == np.bool_ else dtype.itemsize,
                )

    for_range(em, 0, steps, iteration)
    return load()
