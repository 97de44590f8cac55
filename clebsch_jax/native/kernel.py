r"""A jaxpr of one member compiled to a SIMD kernel over a batch, with LLVM (llvmlite).

The kernel is one function

    int64 kernel(void **arrays, int64 stride, int64 first_block, int64 end_block)

that runs the member's program for the lane blocks `first_block … end_block - 1`: block `k`
holds members `k·W … k·W + W - 1` in the `W` lanes of each vector. It returns 0, or the
bytes of the heap buffer it could not allocate (long arrays held as rows,
`clebsch_jax.native.rows`), having run nothing: the call raises `MemoryError`. Every array (inputs, then
outputs) is stored batch-last, one row of `stride` members per entry of the member's shape,
so that an entry of a block is one vector load or store. Booleans are stored as bytes.

The IR is optimised by LLVM's default pipeline (O2, no fast-math: every floating-point
operation is the one the jaxpr names, in its order) and compiled to machine code at
`CODEGEN_OPT` for the host's CPU and features, and the
object code is cached on disk under the hash of the jaxpr (its text and constants), the
lanes, the CPU, its features, the llvmlite version and the translation's own source
(`cache_dir`): a program found there is neither translated nor compiled again, and a program
refused for its size (`TooLarge`) is recorded under the same key and not translated again. A call of
the kernel from ctypes releases the GIL, so threads run blocks side by side.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from . import TooLarge, refused, remember_refusal
from .fingerprint import cache_dir
from .fingerprint import read as _read
from .fingerprint import write as _write
from .layout import input_rows, output_rows, prefetch_next_block, results

__all__ = ["Kernel", "build_ir", "compile_ir", "host_lanes", "cache_dir", "cache_key"]

_LOCK = threading.Lock()
_LLVM: dict = {}

CODEGEN_OPT = 2
"""LLVM's optimisation level of code generation (instruction selection, scheduling, register
allocation; the IR's own pipeline is O2 whatever this is). Level 1 emits a kernel a little
faster, but its machine code differs and its speed was measured only on a loaded machine
(`benchmarks/README.md`, native section): level 2 stays until a quiet comparison says
otherwise. Level 0 needs LLVM's fast register allocator, whose spills slowed the kernels."""


def _binding():
    """llvmlite's binding, initialised once for the host."""
    with _LOCK:
        if not _LLVM:
            import llvmlite
            import llvmlite.binding as llvm

            llvm.initialize_native_target()
            llvm.initialize_native_asmprinter()
            cpu, features = llvm.get_host_cpu_name(), llvm.get_host_cpu_features().flatten()
            target = llvm.Target.from_triple(llvm.get_process_triple())
            tm = target.create_target_machine(
                cpu=cpu, features=features, opt=CODEGEN_OPT, codemodel="jitdefault", jit=True
            )
            _LLVM.update(
                llvm=llvm,
                tm=tm,
                target=target,
                cpu=cpu,
                features=features,
                version=llvmlite.__version__,
                triple=llvm.get_process_triple(),
            )
        return _LLVM


def host_lanes(dtype=np.float64) -> int:
    """Members per vector on this CPU for `dtype`: the widest vector register's lanes."""
    features = _binding()["features"]
    bits = 512 if "+avx512f" in features else 256 if "+avx" in features else 128
    return max(2, bits // (8 * np.dtype(dtype).itemsize))


def _storage(dtype) -> np.dtype:
    dtype = np.dtype(dtype)
    return np.dtype(np.uint8) if dtype == np.bool_ else dtype


def build_ir(closed, width: int, batched=None, carries: int | None = None, limit: int | None = None) -> str:
    """The LLVM IR (text) of the kernel of `closed` (a closed jaxpr of one member). `batched`
    (one flag per input, default all True): an input that is not batched is one value shared
    by every member, stored as its entries alone and broadcast to the lanes.

    `carries` (a loop kernel): `closed` is the body of a loop whose last `carries` inputs are
    its carry and whose outputs are the new carry, then the iteration's records. The kernel
    takes a fifth argument, the number of iterations `steps` (the same for every member), runs
    the body that many times (`_loop`) and writes the final carry, then every iteration's
    records: record `j` of an entry `e` of a record of `size` entries goes to row
    `j·size + e` of its array (rows of `stride` members, as every array).

    `limit`: the most entries translated (default `values.MAX_ENTRIES`; past it `TooLarge`)."""
    # the translation, imported here: a kernel loaded from the disk cache needs none of it
    from llvmlite import ir

    from . import control as _control  # registers the loop and branch rules
    from . import indexing as _indexing  # noqa: F401  (registers the indexing rules)
    from . import linalg as _linalg  # noqa: F401  (registers the linear algebra rules)
    from . import rows as _rows
    from .loop_kernel import loop_iterations
    from .lower import eval_closed
    from .uniform import uniform_loops
    from .values import MAX_ENTRIES, Emitter, llvm_type

    module = ir.Module(name="clebsch_jax_native")
    module.triple = _binding()["triple"]
    ptr, i64 = ir.PointerType(), ir.IntType(64)
    params = [ptr, i64, i64, i64] + ([i64] if carries is not None else [])
    fn = ir.Function(module, ir.FunctionType(i64, params), "kernel")
    arrays, stride, first, end = fn.args[:4]
    entry = fn.append_basic_block("entry")
    b = ir.IRBuilder(entry)
    em = Emitter(module, b, width, entry, MAX_ENTRIES if limit is None else limit)
    em.rows = carries is None and _rows.wants_rows(closed.jaxpr)  # long arrays as rows in memory
    em.unroll = _control.unroll_policy(closed.jaxpr, em.rows)
    em.uniform = uniform_loops(closed, [True] * len(closed.jaxpr.invars) if batched is None else batched)
    counter = b.alloca(i64)
    b.store(first, counter)
    head, body, done = (
        fn.append_basic_block("block.head"),
        fn.append_basic_block("block.body"),
        fn.append_basic_block("block.done"),
    )
    b.position_at_end(head)  # the entry block is ended last (`close_entry`): the heap buffer's check
    k = b.load(counter, typ=i64)
    b.cbranch(b.icmp_signed("<", k, end), body, done)
    b.position_at_end(body)
    offset = b.mul(k, ir.Constant(i64, width))

    bases: dict = {}

    def base(j: int):
        """Array j's data pointer. A loop kernel reads it once, in the entry block (LLVM would read
        it again after each store, which may for all it knows change `arrays`); other kernels
        where it is used (held through the block, it would be spilled)."""
        read = lambda: b.load(b.gep(arrays, [ir.Constant(i64, j)], source_etype=ptr), typ=ptr)  # noqa: E731
        if carries is not None and j not in bases:
            block = b.block
            b.position_at_end(entry)
            bases[j] = read()
            b.position_at_end(block)
        return bases[j] if carries is not None else read()

    def row(j: int, e: int, dtype):
        at = b.add(b.mul(ir.Constant(i64, e), stride), offset)
        return b.gep(base(j), [at], source_etype=llvm_type(_storage(dtype)) if dtype != np.bool_ else ir.IntType(8))

    def shared(j: int, e: int, dtype):
        st = llvm_type(_storage(dtype)) if dtype != np.bool_ else ir.IntType(8)
        x = b.load(b.gep(base(j), [ir.Constant(i64, e)], source_etype=st), typ=st)
        if dtype == np.bool_:
            x = b.icmp_unsigned("!=", x, ir.Constant(st, 0))
        vt = ir.VectorType(x.type, width)
        one = b.insert_element(ir.Constant(vt, ir.Undefined), x, ir.Constant(ir.IntType(32), 0))
        return b.shuffle_vector(
            one, ir.Constant(vt, ir.Undefined), ir.Constant(ir.VectorType(ir.IntType(32), width), [0] * width)
        )

    batched = [True] * len(closed.jaxpr.invars) if batched is None else list(batched)
    if carries is None and width > 1:  # the next block's rows, asked for while this block runs
        n_in = len(closed.jaxpr.invars)
        spec = lambda j, v: (j, int(np.prod(v.aval.shape, dtype=int)), _storage(v.aval.dtype).itemsize)  # noqa: E731
        ins = [spec(j, v) for j, v in enumerate(closed.jaxpr.invars) if batched[j]]
        outs = [] if em.rows else [spec(n_in + j, v) for j, v in enumerate(closed.jaxpr.outvars)]  # not `Rows`
        prefetch_next_block(b, entry, arrays, stride, b.add(offset, ir.Constant(i64, width)), ins, outs)
    args = []
    for j, v in enumerate(closed.jaxpr.invars):
        dtype = np.dtype(v.aval.dtype)
        arr = np.empty(v.aval.shape, object)
        for e, idx in enumerate(np.ndindex(v.aval.shape)):
            if not batched[j]:
                arr[idx] = shared(j, e, dtype)
            elif dtype == np.bool_:
                raw = b.load(row(j, e, dtype), typ=ir.VectorType(ir.IntType(8), width), align=1)
                arr[idx] = b.icmp_unsigned("!=", raw, ir.Constant(raw.type, [ir.Constant(ir.IntType(8), 0)] * width))
            else:
                arr[idx] = b.load(row(j, e, dtype), typ=em.vtype(dtype), align=np.dtype(dtype).itemsize)
        args.append(arr)
    n_in = len(closed.jaxpr.invars)
    if carries is None:
        outs = eval_closed(em, closed, args)
    else:  # the carry after the loop; the records are written in it
        outs = loop_iterations(em, closed, args, carries, fn.args[4], lambda j, e, dt: row(n_in + j, e, dt))

    def write(j, e, value, dtype, shift=None):
        value = em.vec(value, dtype)
        if dtype == np.bool_:
            value = b.zext(value, ir.VectorType(ir.IntType(8), width))
        at = row(n_in + j, e, dtype)
        if shift is not None:  # entry e of a later row of a `Rows` output
            at = b.gep(at, [shift], source_etype=value.type.element)
        b.store(value, at, align=_storage(dtype).itemsize)

    for j, (v, out) in enumerate(zip(closed.jaxpr.outvars[: len(outs)], outs)):
        dtype = np.dtype(v.aval.dtype)
        if isinstance(out, _rows.Rows):  # written row by row, in a loop
            size = int(np.prod(out.row, dtype=int))

            def put(i, j=j, out=out, size=size, dtype=dtype):
                shift = b.mul(b.mul(i, ir.Constant(i64, size)), stride)
                for e, value in enumerate(_rows.row_at(em, out, i).reshape(-1)):
                    write(j, e, value, dtype, shift)

            _rows.loop(em, out.n, put)
            continue
        for e, idx in enumerate(np.ndindex(v.aval.shape)):
            write(j, e, out[idx], dtype)
    b.store(b.add(b.load(counter, typ=i64), ir.Constant(i64, 1)), counter)
    b.branch(head)
    b.position_at_end(done)
    em.finish()
    b.ret(ir.Constant(i64, 0))
    em.close_entry(head)
    return str(module)


_SOURCE: list = []


def _translator_digest() -> str:
    """A hash of the translation's own source: a change of it invalidates the cached kernels."""
    if not _SOURCE:
        h = hashlib.sha256()
        folder = os.path.dirname(__file__)
        for name in sorted(os.listdir(folder)):
            if name.endswith(".py"):
                with open(os.path.join(folder, name), "rb") as f:
                    h.update(f.read())
        _SOURCE.append(h.hexdigest())
    return _SOURCE[0]


def _program_text(closed, width: int, batched, carries=None) -> str:
    """What determines a kernel: the jaxpr (its text and its constants' bytes), the lanes,
    which inputs are batched and, for a loop kernel, its carries."""
    consts = hashlib.sha256()
    for c in closed.consts:
        c = np.asarray(c)
        consts.update(f"{c.dtype}{c.shape}".encode())
        consts.update(np.ascontiguousarray(c).tobytes())
    loop = "" if carries is None else f"\nloop of {carries} carries"
    return f"{closed.jaxpr}\n{consts.hexdigest()}\n{width}\n{list(batched)}{loop}"


def cache_key(text: str) -> str:
    """The disk cache's key of `text` on this host: its hash with llvmlite's version, the
    target, the CPU and its features, and the translation's source."""
    L = _binding()
    h = hashlib.sha256()
    for part in (L["version"], L["triple"], L["cpu"], L["features"], _translator_digest(), text):
        h.update(part.encode())
        h.update(b"\0")
    return h.hexdigest()


LARGE_IR_LINES = 15_000
"""IR of more lines than this is given LLVM's basic register allocator instead of the greedy
one: the greedy allocator's time grows steeply with the long straight-line blocks of a large
member (clusters of vortices) and dominated its compile, for a kernel only slightly faster
(`benchmarks/README.md`)."""


def optimise(mod) -> None:
    """Optimise the parsed module `mod` in place, for the host (`compile_ir`'s pipeline; called
    with `_LOCK` held, so it reads the initialised binding without `_binding()`)."""
    L = _LLVM
    llvm = L["llvm"]
    pb = llvm.create_pass_builder(L["tm"], llvm.create_pipeline_tuning_options(speed_level=2))
    pb.getModulePassManager().run(mod, pb)


def compile_ir(text: str) -> bytes:
    """Object code of the IR `text` for the host: LLVM's O2 pipeline (`optimise`), code generation
    at `CODEGEN_OPT`."""
    L = _binding()
    llvm = L["llvm"]
    with _LOCK:  # the register allocator is a process-wide LLVM option
        llvm.set_option("", "--regalloc=" + ("basic" if text.count("\n") > LARGE_IR_LINES else "greedy"))
        try:
            mod = llvm.parse_assembly(text)
            mod.verify()
            optimise(mod)
            return L["tm"].emit_object(mod)
        finally:
            llvm.set_option("", "--regalloc=greedy")  # LLVM's default, which unoptimised code generation needs


_ENGINES: list = []


def _load(obj: bytes, globals_: tuple = ()) -> int | tuple:
    """The address of `kernel` in the object code `obj`, loaded by an MCJIT engine of its own
    (with `globals_`, names of global values: `(address, {name: its address})`).
    The engine and the object are kept for the life of the process and never disposed by
    llvmlite (`detach`): an engine given an object file owns it, and disposing both (as their
    finalisers would, in either order) frees it twice. A process compiles a kernel once per
    program (the callers keep them), so what is kept is bounded by the programs it runs."""
    L = _binding()
    llvm = L["llvm"]
    with _LOCK:
        # an engine owns the target machine it is given: each gets one of its own, never the
        # one `compile_ir` emits objects with
        tm = L["target"].create_target_machine(
            cpu=L["cpu"], features=L["features"], opt=2, codemodel="jitdefault", jit=True
        )
        engine = llvm.create_mcjit_compiler(llvm.parse_assembly(""), tm)
        ref = llvm.ObjectFileRef.from_data(obj)
        engine.add_object_file(ref)
        engine.finalize_object()
        address = engine.get_function_address("kernel")
        found = {name: engine.get_global_value_address(name) for name in globals_}
        ref.detach()
        engine.detach()
        _ENGINES.append((engine, ref, obj, tm))
    return (address, found) if globals_ else address


_SIGNATURE = ctypes.CFUNCTYPE(ctypes.c_int64, ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64, ctypes.c_int64)
_LOOP_SIGNATURE = ctypes.CFUNCTYPE(
    ctypes.c_int64, ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64, ctypes.c_int64, ctypes.c_int64
)


class Kernel:
    """The compiled kernel of a closed jaxpr of one member. Call it with the batch's arrays,
    each of shape (B, *the member's shape), in the order of the jaxpr's inputs; it returns the
    outputs, each (B, *shape).

    A loop kernel (`carries`, `build_ir`) is called with `steps` (its iterations) and
    `capacity` (the records kept, at least `steps`): it returns the carry's arrays, each
    (B, *shape), then the records', each (B, capacity, *shape), zero after the `steps` made."""

    def __init__(
        self,
        closed,
        width: int | None = None,
        use_cache: bool = True,
        batched=None,
        max_lines=None,
        key=None,
        carries=None,
    ):
        width = width or host_lanes()
        ins = [(tuple(v.aval.shape), np.dtype(v.aval.dtype)) for v in closed.jaxpr.invars]
        outs = [(tuple(v.aval.shape), np.dtype(v.aval.dtype)) for v in closed.jaxpr.outvars]
        batched = [True] * len(ins) if batched is None else [bool(x) for x in batched]
        # `key`: a key that determines the jaxpr (`NativeFunction`'s record key), which spares
        # printing a large jaxpr to hash it
        self.key = key or cache_key(_program_text(closed, width, batched, carries))
        obj = _read(self.key, ".o") if use_cache else None
        self.from_cache = obj is not None
        if obj is None:
            from .values import entries_limit

            # a program refused for its size before, in any process: not translated again
            refused(self.key if use_cache else None, max_lines)
            try:
                text = build_ir(closed, width, batched, carries, entries_limit(max_lines))
                lines = text.count("\n")
                if max_lines is not None and lines > max_lines:
                    raise TooLarge(
                        f"a kernel of {lines} lines of LLVM IR, more than the {max_lines} compiled without being "
                        "asked (LLVM's time grows with them; backend='native' compiles it)",
                        lines,
                    )
            except TooLarge as err:
                if use_cache:
                    remember_refusal(self.key, err)
                raise
            obj = compile_ir(text)
            if use_cache:
                _write(self.key, ".o", obj)
        self._setup(width, ins, outs, batched, obj, carries)

    def _setup(self, width: int, ins: list, outs: list, batched: list, obj: bytes, carries=None) -> None:
        self.width, self.batched, self.carries = width, batched, carries
        self.in_dtypes, self.out_dtypes = [d for _, d in ins], [d for _, d in outs]
        layout = lambda shape, dtype: (shape, int(np.prod(shape, dtype=int)), _storage(dtype))
        self._ins, self._outs = [layout(*a) for a in ins], [layout(*a) for a in outs]
        self._fn = (_SIGNATURE if carries is None else _LOOP_SIGNATURE)(_load(obj))

    def record(self) -> dict:
        """What `from_record` needs to load this kernel again without its jaxpr."""
        layout = lambda x, dtypes: [(list(shape), str(d)) for (shape, _, _), d in zip(x, dtypes)]
        return {
            "key": self.key,
            "width": self.width,
            "batched": self.batched,
            "ins": layout(self._ins, self.in_dtypes),
            "outs": layout(self._outs, self.out_dtypes),
            "carries": self.carries,
        }

    @classmethod
    def from_record(cls, record: dict):
        """The kernel a `record` names, loaded from the disk cache (no jaxpr, no translation), or
        None when its object code is not there."""
        obj = _read(record["key"], ".o")  # the object code, or None
        if obj is None:
            return None
        k = cls.__new__(cls)
        k.key, k.from_cache = record["key"], True
        avals = lambda x: [(tuple(shape), np.dtype(d)) for shape, d in x]
        k._setup(
            record["width"],
            avals(record["ins"]),
            avals(record["outs"]),
            list(record["batched"]),
            obj,
            record.get("carries"),
        )
        return k

    def record_layout(self) -> list:
        """(shape, entries, storage dtype, dtype) of each record output of a loop kernel."""
        if self.carries is None:
            return []
        return [(*layout, d) for layout, d in zip(self._outs[self.carries :], self.out_dtypes[self.carries :])]

    def __call__(self, *arrays, threads: int = 1, steps: int = 0, capacity: int = 0, workspace=None, records=None):
        """`workspace` (`clebsch_jax.native.layout.Workspace`, optional): rows kept for this
        thread's next calls; the outputs are then valid until its second call after this one.
        `records` (a loop kernel's): the rows its records are written to (`output_rows`)."""
        if len(arrays) != len(self._ins):
            raise TypeError(f"expected {len(self._ins)} arrays, got {len(arrays)}")
        B = next(int(np.shape(a)[0]) for a, bat in zip(arrays, self.batched) if bat)
        blocks = -(-B // self.width)
        stride = blocks * self.width
        buffers = input_rows(arrays, self._ins, self.batched, B, stride, workspace)
        n_carry = len(self._outs) if self.carries is None else self.carries
        if self.carries is not None and not 0 <= steps <= capacity:
            raise ValueError(f"a loop kernel of {steps} steps with records for {capacity}")
        outs = output_rows(self._outs, n_carry, stride, steps, capacity, workspace, records)
        address = (lambda x: x.ctypes.data) if workspace is None else workspace.address
        pointers = (ctypes.c_void_p * (len(buffers) + len(outs)))(*[address(x) for x in buffers + outs])
        address = ctypes.addressof(pointers)
        loop = () if self.carries is None else (int(steps),)
        threads = max(1, min(int(threads), blocks))
        if threads == 1:
            status = [self._fn(address, stride, 0, blocks, *loop)]
        else:
            cuts = np.linspace(0, blocks, threads + 1).astype(int)
            with ThreadPoolExecutor(threads) as pool:
                call = lambda i: self._fn(address, stride, int(cuts[i]), int(cuts[i + 1]), *loop)
                status = list(pool.map(call, range(threads)))
        if max(status):  # the heap buffer's size: it could not be allocated (`Emitter.close_entry`)
            raise MemoryError(
                f"a native kernel could not allocate its heap buffer of {max(status)} bytes (a long scan's arrays "
                "held as rows, a buffer per thread): run fewer steps per call, fewer threads, or backend='xla'"
            )
        found = results(outs, self._outs, self.out_dtypes, n_carry, B, stride, capacity)
        if workspace is not None:
            workspace.returned(found[:n_carry], outs[:n_carry])
        return found
