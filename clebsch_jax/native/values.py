"""Values of the native translation: one member's arrays as NumPy arrays of lane vectors.

The translation (`clebsch_jax.native.lower`) evaluates a jaxpr of one batch member with every
array entry held separately: an array of shape `s` is a NumPy object array of shape `s` whose
entries are either an LLVM value of type `<W x T>` (the entry in the `W` members of the SIMD
lanes) or a NumPy scalar, the same in every lane (known while translating: constants, shapes,
loop trip counts). Known entries are folded in NumPy where the operation is exactly rounded;
every other operation is emitted as one vector instruction per entry. Shapes are static, so
re-indexing (reshape, transpose, slices, broadcasts) costs nothing in the machine code.
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir

from . import TooLarge, Unsupported

__all__ = [
    "Unsupported",
    "MAX_ENTRIES",
    "ASKED_MAX_ENTRIES",
    "entries_limit",
    "Emitter",
    "llvm_type",
    "is_known",
    "known_array",
    "FLOATS",
    "INTS",
]


FLOATS = {np.dtype(np.float64): ir.DoubleType(), np.dtype(np.float32): ir.FloatType()}
INTS = {
    np.dtype(t): ir.IntType(8 * np.dtype(t).itemsize)
    for t in (np.int8, np.int16, np.int32, np.int64, np.uint8, np.uint16, np.uint32, np.uint64)
}
BOOL = ir.IntType(1)


class _Splat(ir.Constant):
    """A vector constant with every lane equal, written `splat (T c)`: one scalar in the IR
    text instead of one per lane (the text's size and its printing time follow)."""

    def __init__(self, vector_type: ir.VectorType, scalar: ir.Constant):
        super().__init__(vector_type, [scalar] * vector_type.count)
        self._ref = f"splat ({scalar.type} {scalar.get_reference()})"

    def get_reference(self):
        return self._ref

    def _to_string(self):
        return self._ref


def llvm_type(dtype) -> ir.Type:
    """The LLVM scalar type of a NumPy dtype (bool is i1)."""
    dtype = np.dtype(dtype)
    if dtype == np.bool_:
        return BOOL
    if dtype in FLOATS:
        return FLOATS[dtype]
    if dtype in INTS:
        return INTS[dtype]
    raise Unsupported(f"dtype {dtype}")


def is_known(e) -> bool:
    """Whether an entry is known while translating (a NumPy scalar, the same in every lane)."""
    return not isinstance(e, ir.Value)


def known_array(a) -> np.ndarray:
    """A concrete array as an array of known entries."""
    a = np.asarray(a)
    out = np.empty(a.shape, object)
    for idx in np.ndindex(a.shape):
        out[idx] = a[idx]
    return out


MAX_ENTRIES = 60_000
"""The most entries (values of one member, each an instruction or a known number) a program
compiled without being asked for may translate to (`backend="auto"`: a kernel with a budget of
IR lines): beyond it the code, unrolled entry by entry, compiles too slowly to pay. The unroll
policy (`control.unroll_policy`) is chosen against it, whatever the limit."""

ASKED_MAX_ENTRIES = 250_000
"""The limit where the native kernel was asked for (`backend="native"`: no budget of IR
lines): members with many components (clusters of ten vortices) translate, and LLVM compiles
them in tens of seconds; past it the program is refused even so."""


def entries_limit(max_lines) -> int:
    """The entries a program may translate to under a budget of `max_lines` lines of IR (None:
    the kernel was asked for)."""
    return ASKED_MAX_ENTRIES if max_lines is None else MAX_ENTRIES


class Emitter:
    """The IR builder of one kernel with its lane width `W`: constants as vectors, selects,
    allocas in the entry block, intrinsics and libm calls, and the mask of the lanes that the
    code being emitted computes for (`mask`: None for every lane; a while loop's body is
    emitted under the mask of the lanes still iterating, so that loops nested in it stop when
    those lanes have stopped)."""

    def __init__(self, module: ir.Module, builder: ir.IRBuilder, width: int, entry: ir.Block, limit=MAX_ENTRIES):
        self.module, self.b, self.W, self.entry = module, builder, width, entry
        self.limit = limit  # the most entries translated (`entries_limit`)
        self.mask = None
        self.unroll = None  # which scans are unrolled (`control.unroll_policy`; None: the first)
        self.uniform = frozenset()  # ids of the while loops every lane runs alike (`uniform.uniform_loops`)
        self._decls: dict = {}
        self._consts: dict = {}
        self.entries = 0
        self.rows = False  # whether long arrays are held as `clebsch_jax.native.rows.Rows`
        self._arena = None  # (pointer, size constant patched by `finish`, bytes used)
        self.stored: dict = {}  # arrays stored for lane loads, by block and entries (`indexing.stored`)
        self.loops: list = []  # the loops being emitted, outermost first (`enter_loop`)

    def enter_loop(self, pre: ir.Block):
        """Say that a loop is emitted next (its head is the next block), entered from `pre`, and
        until `exit_loop`: a value of a block made before is computed outside the loop
        (`outside`), where what only reads it may be done once (`indexing.stored`)."""
        self.loops.append((pre, {id(block) for block in self.b.function.blocks}))

    def exit_loop(self) -> None:
        self.loops.pop()

    def count(self, entries: int) -> None:
        """Entries translated so far: a program past `limit` is refused (`TooLarge`)."""
        self.entries += entries
        if self.entries > self.limit:
            raise TooLarge(
                f"a program of more than {self.limit} entries (members with many components: "
                "their arrays unrolled entry by entry outgrow a kernel)",
                entries=self.limit,
            )

    # -- types and constants -------------------------------------------------------------
    def vtype(self, dtype) -> ir.VectorType:
        return ir.VectorType(llvm_type(dtype), self.W)

    def const(self, value, dtype) -> ir.Constant:
        dtype = np.dtype(dtype)
        if dtype == np.bool_:
            value = bool(value)
        elif dtype in FLOATS:
            value = float(value)
        else:
            value = int(value)
        key = (
            dtype,
            value if not (dtype in FLOATS and value != value) else "nan",
            np.copysign(1.0, value) if dtype in FLOATS else 0,
        )
        found = self._consts.get(key)
        if found is None:
            t = llvm_type(dtype)
            found = self._consts[key] = _Splat(
                ir.VectorType(t, self.W), ir.Constant(t, int(value) if dtype == np.bool_ else value)
            )
        return found

    def vec(self, e, dtype):
        """An entry as a vector value of `dtype` (a known entry becomes a constant vector)."""
        return self.const(e, dtype) if is_known(e) else e

    # -- memory ---------------------------------------------------------------------------
    def alloca(self, ty: ir.Type, name: str = ""):
        """An alloca in the entry block (where LLVM's mem2reg turns it into registers)."""
        b = self.b
        block = b.block
        b.position_at_start(self.entry)
        ptr = b.alloca(ty, name=name)
        b.position_at_end(block)
        return ptr

    def arena(self, n: int):
        """A pointer to room for `n` vectors in the kernel call's heap buffer (allocated in the
        entry block, its size fixed by `finish`; `Rows` in memory)."""
        i64, i8 = ir.IntType(64), ir.IntType(8)
        if self._arena is None:
            malloc = ir.Function(self.module, ir.FunctionType(ir.PointerType(), [i64]), "malloc")
            size = ir.Constant(i64, 0)
            block = self.b.block
            self.b.position_at_start(self.entry)
            self._arena = [self.b.call(malloc, [size]), size, 0]
            self.b.position_at_end(block)
        ptr, _, used = self._arena
        self._arena[2] = used + n * 8 * self.W  # room for a vector of any type
        return self.b.gep(ptr, [ir.Constant(i64, used)], source_etype=i8)

    def finish(self) -> None:
        """At the kernel's return: free the buffer of `arena`, whose size is now known."""
        if self._arena is not None:
            ptr, size, used = self._arena
            size.constant = max(used, 1)
            free = ir.Function(self.module, ir.FunctionType(ir.VoidType(), [ir.PointerType()]), "free")
            self.b.call(free, [ptr])

    def close_entry(self, first: ir.Block) -> None:
        """End the entry block (left open while the kernel is emitted): on to `first`, or, when
        the buffer of `arena` could not be allocated, return its size in bytes at once (the
        kernel's status: 0 is success; `Kernel` raises `MemoryError` with it)."""
        b = self.b
        b.position_at_end(self.entry)
        if self._arena is None:
            b.branch(first)
            return
        ptr, size, _ = self._arena
        failed = self.entry.parent.append_basic_block("arena.failed")
        b.cbranch(b.icmp_unsigned("==", b.ptrtoint(ptr, ir.IntType(64)), ir.Constant(ir.IntType(64), 0)), failed, first)
        b.position_at_end(failed)
        b.ret(size)

    # -- lane operations --------------------------------------------------------------------
    def select(self, cond, a, b, dtype):
        """Entry-wise `cond ? a : b` (cond an i1 entry); folded when cond is known."""
        if is_known(cond):
            return a if bool(cond) else b
        if is_known(a) and is_known(b) and np.asarray(a) == np.asarray(b) and np.dtype(dtype).kind != "f":
            return a
        return self.b.select(cond, self.vec(a, dtype), self.vec(b, dtype))

    def any_lane(self, cond) -> ir.Value:
        """An i1 scalar: whether any lane of the i1 vector `cond` is set."""
        bits = self.b.bitcast(cond, ir.IntType(self.W))
        return self.b.icmp_unsigned("!=", bits, ir.Constant(ir.IntType(self.W), 0))

    def mask_and(self, cond):
        """`cond` restricted to the lanes of the current mask."""
        if self.mask is None:
            return cond
        if is_known(cond):
            return self.mask if bool(cond) else cond
        return self.b.and_(cond, self.mask)

    # -- functions ----------------------------------------------------------------------------
    def intrinsic(self, name: str, dtype, n_args: int = 1):
        """The vector form of an LLVM intrinsic (e.g. "llvm.sqrt")."""
        vt = self.vtype(dtype)
        key = (name, vt)
        if key not in self._decls:
            fname = f"{name}.v{self.W}{'f64' if np.dtype(dtype) == np.float64 else 'f32'}"
            self._decls[key] = ir.Function(self.module, ir.FunctionType(vt, [vt] * n_args), fname)
        return self._decls[key]

    def call_intrinsic(self, name: str, dtype, *args):
        return self.b.call(self.intrinsic(name, dtype, len(args)), [self.vec(a, dtype) for a in args])

    def libm(self, name: str, dtype, *args):
        """A scalar libm function (`sin`, `atan2`, …) applied lane by lane."""
        dtype = np.dtype(dtype)
        t = llvm_type(dtype)
        fname = name if dtype == np.float64 else name + "f"
        key = ("libm", fname)
        if key not in self._decls:
            fn = self.module.globals.get(fname) or ir.Function(self.module, ir.FunctionType(t, [t] * len(args)), fname)
            self._decls[key] = fn
        fn = self._decls[key]
        vecs = [self.vec(a, dtype) for a in args]
        out = ir.Constant(self.vtype(dtype), ir.Undefined)
        for lane in range(self.W):
            i = ir.Constant(ir.IntType(32), lane)
            r = self.b.call(fn, [self.b.extract_element(v, i) for v in vecs])
            out = self.b.insert_element(out, r, i)
        return out
