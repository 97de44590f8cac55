"""Loops over the axes of an array, for `clebsch_jax.native.fused`: a counted loop whose counter
and carried vectors are phis (`loop`), an array's entries in an alloca indexed by loop counters
(`Buffer`), loops that store an array's entries (`fill`), and the scopes in which a buffer is
known stored (`scopes`, `enter`)."""

from __future__ import annotations

import math

import numpy as np
from llvmlite import ir

from .values import Emitter

__all__ = ["scopes", "enter", "Buffer", "loop", "fill", "as_array", "splat"]

_I64 = ir.IntType(64)


def scopes(em: Emitter) -> list:
    """The buffers stored by each jaxpr being translated, outermost first (`enter`)."""
    if not hasattr(em, "fused_scopes"):
        em.fused_scopes = [{}]
    return em.fused_scopes


class enter:
    """`with enter(em):` around the translation of a jaxpr: the buffers it stores are found by
    the equations after them and by the jaxprs nested in it, not after it (where its code may
    not have run: a branch, a loop's body)."""

    def __init__(self, em: Emitter):
        self.em = em

    def __enter__(self):
        scopes(self.em).append({})

    def __exit__(self, *exc):
        scopes(self.em).pop()


class Buffer:
    """An array's entries in an alloca of vectors (C order), loaded at indices that are Python
    ints or loop counters."""

    def __init__(self, em: Emitter, shape, dtype, entries=None):
        self.em, self.shape, self.dtype = em, tuple(shape), np.dtype(dtype)
        self.vt = em.vtype(dtype)
        array = em.alloca(ir.ArrayType(self.vt, max(1, math.prod(self.shape))))
        self.ptr = em.b.bitcast(array, self.vt.as_pointer())  # a pointer to its first vector
        self.strides = [math.prod(self.shape[d + 1 :]) for d in range(len(self.shape))]
        if entries is not None:
            for idx in np.ndindex(self.shape):
                self.store(em.vec(entries[idx], dtype), idx)

    def reshaped(self, shape) -> "Buffer":
        """The same memory as an array of `shape` (as many entries, C order)."""
        view = object.__new__(Buffer)
        view.em, view.shape, view.dtype, view.vt, view.ptr = self.em, tuple(shape), self.dtype, self.vt, self.ptr
        view.strides = [math.prod(view.shape[d + 1 :]) for d in range(len(view.shape))]
        return view

    def _at(self, idx):
        b = self.em.b
        static = sum(i * s for i, s in zip(idx, self.strides) if isinstance(i, int))
        flat = None
        for i, s in zip(idx, self.strides):
            if not isinstance(i, int):
                term = i if s == 1 else b.mul(i, ir.Constant(_I64, s))
                flat = term if flat is None else b.add(flat, term)
        if flat is None:
            flat = ir.Constant(_I64, static)
        elif static:
            flat = b.add(flat, ir.Constant(_I64, static))
        return b.gep(self.ptr, [flat], source_etype=self.vt)

    def load(self, idx):
        return self.em.b.load(self._at(idx), typ=self.vt)

    def store(self, value, idx) -> None:
        self.em.b.store(value, self._at(idx))


def loop(em: Emitter, n: int, init: list, body) -> list:
    """`carried = body(i, carried)` for i = 0 … n - 1, the counter and the carried vectors
    phis of the loop's head; the carried values after the last iteration."""
    b = em.b
    fn, pre = b.function, b.block
    head, block, done = (fn.append_basic_block(f"sum.{s}") for s in ("head", "body", "done"))
    b.branch(head)
    b.position_at_end(head)
    i = b.phi(_I64)
    i.add_incoming(ir.Constant(_I64, 0), pre)
    phis = []
    for v in init:
        phis.append(b.phi(v.type))
        phis[-1].add_incoming(v, pre)
    b.cbranch(b.icmp_signed("<", i, ir.Constant(_I64, n)), block, done)
    b.position_at_end(block)
    new = body(i, phis)
    latch = b.block
    i.add_incoming(b.add(i, ir.Constant(_I64, 1)), latch)
    for p, v in zip(phis, new):
        p.add_incoming(v, latch)
    b.branch(head)
    b.position_at_end(done)
    return phis


def fill(em: Emitter, result: Buffer, loops: list, values) -> None:
    """Store into `result` in loops over its axes `loops` (`(axis, size)`): `values(fixes)`
    gives the entries of its other axes (C order) at the loops' indices `fixes` (by axis)."""
    looped = [d for d, _ in loops]

    def outer(level, fixes):
        if level == len(loops):
            rest = [n for d, n in enumerate(result.shape) if d not in looped]
            for kidx, v in zip(np.ndindex(*rest), values(fixes)):
                it = iter(kidx)
                at = tuple(fixes[d] if d in fixes else next(it) for d in range(len(result.shape)))
                result.store(em.vec(v, result.dtype), at)
            return
        d, n = loops[level]
        loop(em, n, [], lambda i, _: outer(level + 1, {**fixes, d: i}) or [])

    outer(0, {})


def as_array(a) -> np.ndarray:
    out = np.empty(np.shape(a), object)
    out[...] = a
    return out


def splat(em: Emitter, i, dtype):
    """The i64 counter `i` as a vector of `dtype` in every lane."""
    b, vt = em.b, em.vtype(dtype)
    if dtype.kind == "f":
        x = b.sitofp(i, vt.element)
    elif vt.element.width < 64:
        x = b.trunc(i, vt.element)
    else:
        x = i
    one = b.insert_element(ir.Constant(vt, ir.Undefined), x, ir.Constant(ir.IntType(32), 0))
    return b.shuffle_vector(
        one, ir.Constant(vt, ir.Undefined), ir.Constant(ir.VectorType(ir.IntType(32), em.W), [0] * em.W)
    )
