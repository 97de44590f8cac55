"""Instructions per step of the rigid-body sweep's native kernel, counted as it runs.

Run: `python benchmarks/native_instructions.py` (`--profile` adds the hot blocks). The count
does not move with the machine's load, unlike the timings of `native.py`.

The sweep of `native.py` (`cj.sweep(rigid_body, …, reconstruct=False, backend="native")`, the
default reduced CAY march) is compiled as usual, except that its optimised LLVM IR gets a
counter per basic block before code generation (the kernel module's `compile_ir` and `_load`
are replaced for this process, with an empty kernel cache). Two sweeps, of n₁ and n₂ steps in
one chunk each, give the instructions of the optimised IR executed per step and per block of
W members, (count₂ − count₁) / ((n₂ − n₁) · blocks), which leaves out the chunk's entry and
exit; phi nodes are not counted. Floating-point instructions (arithmetic, comparisons,
conversions and the fabs/maximum/sqrt intrinsics) are counted apart. The same counters give
the machine instructions per step: each block's instructions in the object's assembly (from
its counter's increment to the next one's; the increments left out), weighted by the block's
executions — what the IR's instructions become, with the register allocator's spills and
reloads and the expansions of selects and NaN-propagating maxima. `--profile` lists the blocks
by their instructions per step. Nothing is written; the numbers go to `benchmarks/README.md` by
hand.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import re
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import rigid_body_step_cost as rigid  # noqa: E402
import throughput  # noqa: E402

import clebsch_jax as cj  # noqa: E402
from clebsch_jax.native import kernel as K  # noqa: E402

FLOATING = re.compile(
    r"=\s*(fadd|fsub|fmul|fdiv|fneg|fcmp|frem|sitofp|uitofp|fptosi|fptoui|fpext|fptrunc)\b"
    r"|@llvm\.(fma|fmuladd|sqrt|fabs|maxnum|minnum|maximum|minimum|copysign|floor|ceil|round|rint|trunc)\."
)
_BLOCKS: list = []  # (label, instructions, floating-point instructions) of the last kernel compiled
_MACHINE: dict = {}  # block -> machine instructions, of the last kernel compiled
_COUNTER: list = []  # the per-block execution counters of the last kernel loaded


def _instrument(text: str) -> str:
    """`text` (optimised IR) with a counter per basic block of each function, in `@__blocks`."""
    out, block, in_function = [], None, False
    _BLOCKS.clear()

    def flush():
        label = [x for x in block if not x.startswith("  ")]
        phis = [x for x in block if x.startswith("  ") and " = phi " in x]
        body = [x for x in block if x.startswith("  ") and " = phi " not in x and not x.strip().startswith(";")]
        k = len(_BLOCKS)
        _BLOCKS.append(
            (label[0].split(":")[0] if label else "entry", len(body), sum(bool(FLOATING.search(x)) for x in body))
        )
        count = [
            f"  %__p{k} = getelementptr [NBLOCKS x i64], ptr @__blocks, i64 0, i64 {k}",
            f"  %__c{k} = load i64, ptr %__p{k}",
            f"  %__a{k} = add i64 %__c{k}, 1",
            f"  store i64 %__a{k}, ptr %__p{k}",
        ]
        out.extend(label + phis + count + body)

    for line in text.split("\n"):
        if line.startswith("define "):
            in_function, block = True, []
            out.append(line)
        elif in_function and line == "}":
            if block:
                flush()
            in_function = False
            out.append(line)
        elif in_function and line and not line.startswith((" ", ";")):
            if block:
                flush()
            block = [line]
        elif in_function and line.strip():
            block.append(line)
        elif not in_function:
            out.append(line)
    out.append(f"@__blocks = global [{len(_BLOCKS)} x i64] zeroinitializer")
    return "\n".join(out).replace("NBLOCKS", str(len(_BLOCKS))) + "\n"


def _compile_counted(text: str) -> bytes:
    """`clebsch_jax.native.kernel.compile_ir`, with the counters added after the optimisation."""
    L = K._binding()
    llvm = L["llvm"]
    with K._LOCK:
        mod = llvm.parse_assembly(text)
        K.optimise(mod)
        counted = llvm.parse_assembly(_instrument(str(mod)))
        counted.verify()
        _MACHINE.clear()
        _MACHINE.update(_machine(L["tm"].emit_assembly(counted)))
        return L["tm"].emit_object(counted)


def _machine(assembly: str) -> dict:
    """Machine instructions per block of the instrumented kernel's `assembly`: those after the
    increment of block k's counter (`incq 8k(%reg)`) and before the next increment."""
    per, block = {}, None
    for line in assembly.split("\n"):
        if not line.startswith("\t") or line.startswith("\t."):
            continue
        found = re.match(r"\tincq\t(\d*)\(%r\w+\)", line)
        if found:
            block = int(found.group(1) or 0) // 8
        elif block is not None:
            per[block] = per.get(block, 0) + 1
    return per


_LOAD = K._load  # the kernel module's loader, which `_load_counted` stands in for while counting


def _load_counted(obj: bytes) -> int:
    """`clebsch_jax.native.kernel._load`, keeping the address of the counters."""
    address, found = _LOAD(obj, ("__blocks",))
    _COUNTER[:] = [(ctypes.c_int64 * len(_BLOCKS)).from_address(found["__blocks"])]
    return address


def counted_sweep(batch: int, n_steps: int):
    """One sweep of `batch` rigid bodies and `n_steps` steps in one chunk (compiled by a first
    call): (executions per block, the blocks, the sweep's result)."""
    omega0 = rigid.initial_conditions(batch)[1]
    inertias = np.broadcast_to(np.asarray(throughput.SWEEP_INERTIA), (batch, 3))
    Q0 = np.broadcast_to(np.eye(3), (batch, 3, 3))
    args = (cj.models.rigid_body, inertias, Q0, omega0)
    options = dict(dt=rigid.DT, n_steps=n_steps, chunk_steps=n_steps, reconstruct=False, backend="native")
    cj.sweep(*args, **options)
    counter, blocks = _COUNTER[0], [b + (_MACHINE.get(i, 0),) for i, b in enumerate(_BLOCKS)]
    for i in range(len(blocks)):
        counter[i] = 0
    result = cj.sweep(*args, **options)
    return np.array(counter[:], dtype=float), blocks, result


def counted_integrate(n_steps: int):
    """One `integrate(backend="native")` of the heavy top of `native_integrate.py` (its default
    method, one chunk, compiled by a first call): (executions per block, the blocks, the
    Solution). The first-step check's call and the chunk's are counted together."""
    import native_integrate as top

    call = lambda: cj.integrate(top.TOP, top.Q0, top.XI0, dt=top.DT, n_steps=n_steps, backend="native")  # noqa: E731
    call()
    counter, blocks = _COUNTER[0], [b + (_MACHINE.get(i, 0),) for i, b in enumerate(_BLOCKS)]
    for i in range(len(blocks)):
        counter[i] = 0
    sol = call()
    return np.array(counter[:], dtype=float), blocks, sol


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--steps", type=int, nargs=2, default=(40, 240), metavar=("N1", "N2"))
    parser.add_argument("--profile", action="store_true", help="list the blocks by instructions per step")
    parser.add_argument(
        "--integrate",
        action="store_true",
        help="the heavy top's integrate(backend='native') of native_integrate.py instead (one lane)",
    )
    args = parser.parse_args(argv)
    os.environ["CLEBSCH_JAX_NATIVE_CACHE"] = tempfile.mkdtemp()  # compiled here, with the counters
    K.compile_ir, K._load = _compile_counted, _load_counted
    width = 1 if args.integrate else K.host_lanes()
    blocks = 1 if args.integrate else -(-args.batch // width)
    n1, n2 = args.steps
    count = (lambda n: counted_integrate(n)) if args.integrate else (lambda n: counted_sweep(args.batch, n))
    c1, b1, _ = count(n1)
    c2, b2, result = count(n2)
    size = lambda bs, i: np.array([b[i] for b in bs], float)
    per_step = lambda i: float((c2 @ size(b2, i) - c1 @ size(b1, i)) / ((n2 - n1) * blocks))
    row = {
        "lanes": width,
        "cpu": K._binding()["cpu"],
        "instructions_per_step_and_block": round(per_step(1), 1),
        "floating_point": round(per_step(2), 1),
        "machine_instructions": round(per_step(3), 1),
        "newton_updates_per_step": (
            float(np.sum(result.stats.iterations)) / n2
            if args.integrate
            else float(np.mean(result.newton_iterations)) / n2
        ),
    }
    print(json.dumps(row))
    if args.profile:
        each = c2 / (n2 * blocks)
        for cost, count, (label, n, _, machine) in sorted(
            ((each[i] * b[1], each[i], b) for i, b in enumerate(b2)), reverse=True
        ):
            if cost >= 1:
                print(f"{cost:8.1f}  {count:6.3f} x {n:5d} (machine {machine:5d})  {label}")
    return row


if __name__ == "__main__":
    main()
