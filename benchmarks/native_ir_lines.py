"""Lines of LLVM IR of a sweep's native kernel, and where they come from in its jaxpr.

Run: `python benchmarks/native_ir_lines.py [landmarks rigid vortices4 vortices10] [--top 30]`.

Each case is a small `cj.sweep(..., backend="native")` whose kernel is translated but not
compiled (`kernel.build_ir` is replaced for the call: the member's closed jaxpr is kept and the
sweep stopped), then translated again with every instruction the translation inserts counted
(llvmlite's `IRBuilder._insert`) and attributed to the equation whose rule inserted it, nested
rules apart: by primitive, by (primitive, source line) and, for loops, branches and calls, the
total of the program they hold. The total is the kernel's lines of IR, which `backend="auto"`
compares with `clebsch_jax.native.AUTO_MAX_IR_LINES`; what counts the lines is the kernel's
own translation, so the figures do not move with the machine's load. Nothing is written; the
numbers go to `benchmarks/README.md` by hand.
"""

from __future__ import annotations

import argparse
import collections
import os
import sys
import tempfile
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
os.environ.setdefault("CLEBSCH_JAX_NATIVE_CACHE", tempfile.mkdtemp())  # no kernel found on disk

import clebsch_jax as cj  # noqa: E402
from clebsch_jax import models  # noqa: E402
from clebsch_jax.native import control, indexing, kernel, linalg, lower  # noqa: E402, F401  (their rules)

ROOT = str(Path(__file__).resolve().parents[1]) + os.sep  # source lines printed relative to it
CONTROL = ("while", "scan", "cond", "pjit", "jit", "closed_call", "custom_linear_solve", "custom_jvp_call")


def _landmarks():  # the sweep of tests/test_native.py's landmarks test
    rng = np.random.default_rng(1)
    q0 = rng.standard_normal((3, 3, 2))
    xi0 = np.asarray(jax.vmap(models.landmark_velocity)(q0, 0.3 * rng.standard_normal((3, 3, 2))))
    cj.sweep(models.landmarks, np.ones(3), q0, xi0, backend="native", dt=0.02, n_steps=20, chunk_steps=10)


def _rigid():  # the sweep of native_instructions.py
    import rigid_body_step_cost as rigid
    import throughput

    omega0 = rigid.initial_conditions(64)[1]
    inertias = np.broadcast_to(np.asarray(throughput.SWEEP_INERTIA), (64, 3))
    Q0 = np.broadcast_to(np.eye(3), (64, 3, 3))
    options = dict(dt=rigid.DT, n_steps=20, chunk_steps=20, reconstruct=False, backend="native")
    cj.sweep(models.rigid_body, inertias, Q0, omega0, **options)


def _vortices(n: int):
    import vortex_step_cost as vortex

    G, Q0 = vortex.initial_conditions(n, 16)
    xi0 = np.asarray(jax.vmap(models.vortex_velocity)(jnp.asarray(G), jnp.asarray(Q0)))
    cj.sweep(models.point_vortices, G, Q0, xi0, dt=vortex.DT, n_steps=20, backend="native")


CASES = {
    "landmarks": _landmarks,
    "rigid": _rigid,
    "vortices4": lambda: _vortices(4),
    "vortices10": lambda: _vortices(10),
}


class _Captured(Exception):
    pass


def member_program(case: str):
    """(closed jaxpr, lanes, batched flags) of the kernel the sweep of `case` asks for."""
    found, build = {}, kernel.build_ir

    def capture(closed, width, batched=None, carries=None, limit=None):
        found.update(closed=closed, width=width, batched=batched)
        raise _Captured

    kernel.build_ir = capture
    try:
        CASES[case]()
    except _Captured:
        pass
    finally:
        kernel.build_ir = build
    return found["closed"], found["width"], found["batched"]


def attribute(closed, width, batched) -> dict:
    """The kernel's lines of IR and the instructions each rule inserted (nested rules apart)."""
    from jax._src import source_info_util
    from llvmlite import ir

    inserted, stack = [0], []
    own, held = collections.Counter(), collections.Counter()
    insert, rules = ir.IRBuilder._insert, dict(lower.RULES)

    def counted(builder, instruction):
        inserted[0] += 1
        return insert(builder, instruction)

    def wrap(name, rule):
        def wrapped(em, eqn, args):
            start = inserted[0]
            stack.append(0)
            try:
                return rule(em, eqn, args)
            finally:
                total, inner = inserted[0] - start, stack.pop()
                if stack:
                    stack[-1] += total
                info = getattr(eqn, "source_info", None)  # a fused loop's row equation has none
                where = (name, "" if info is None else source_info_util.summarize(info).replace(ROOT, ""))
                own[where] += total - inner
                held[where] += total

        return wrapped

    ir.IRBuilder._insert = counted
    lower.RULES.update({name: wrap(name, rule) for name, rule in rules.items()})
    try:
        text = kernel.build_ir(closed, width, batched, None, None)
    finally:
        ir.IRBuilder._insert = insert
        lower.RULES.update(rules)
    by_primitive = collections.Counter()
    for (name, _), n in own.items():
        by_primitive[name] += n
    return {"lines": text.count("\n"), "own": own, "held": held, "by_primitive": by_primitive}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("cases", nargs="*", help=f"some of {', '.join(CASES)} (default: all)")
    parser.add_argument("--top", type=int, default=25, help="rows of each table")
    args = parser.parse_args(argv)
    unknown = [c for c in args.cases if c not in CASES]
    if unknown:
        parser.error(f"unknown cases {unknown}: choose from {list(CASES)}")
    found = {}
    for case in args.cases or list(CASES):
        closed, width, batched = member_program(case)
        r = found[case] = attribute(closed, width, batched)
        print(f"\n== {case}: {r['lines']} lines of IR ({width} lanes)")
        print("-- by primitive")
        for name, n in r["by_primitive"].most_common(args.top):
            print(f"{n:8d}  {name}")
        print("-- by equation (its own instructions)")
        for (name, where), n in r["own"].most_common(args.top):
            print(f"{n:8d}  {name}  {where}")
        print("-- loops, branches and calls (with what they hold)")
        rows = [(k, n) for k, n in r["held"].most_common() if k[0] in CONTROL][: args.top]
        for (name, where), n in rows:
            print(f"{n:8d}  {name}  {where}")
    return found


if __name__ == "__main__":
    main()
