r"""`clebsch_jax.batch` on a native kernel: the program of one member compiled with LLVM
(`clebsch_jax.native.compile_member`) and run for every member in one call, members in the
SIMD lanes of the host CPU (the kernel loops over the lanes itself; no chunks).

`batch` asks `wants_native` whether a call runs here (`backend=` "auto" or "native", concrete
arguments, llvmlite importable), makes its checks (the memory of the outputs, `integrate`'s
checks of the first member), then asks `native_program` for the kernel of its function on
these member shapes — compiled once per process and kept (`compiled_once`) under the
function's fingerprint (`clebsch_jax.native.fingerprint`: its code, closures and globals), or,
where that cannot be read, under the function object itself, which the cache then holds (so
that its id is not reused by another function while the kernel is kept).

`integrate(..., throw=True)` inside the function would check its `Solution` in a host
callback, which a kernel cannot make: the member's program is traced inside
`clebsch_jax.march.solution.collecting_checks`, the checks' arguments become extra outputs of
the kernel, and `NativeBatch.__call__` raises the `IntegrationError` that `jax.vmap` would,
naming the first failed member, after the run. Where that is not possible (the call is inside
a trace of the function's own, a `jax.jit`, `vmap` or loop, whose values cannot be outputs) or
the function makes host callbacks of its own (`jax.debug.print`), the translation is refused
(`Unsupported`, with the reason) and the batch-last interpreter runs it.

The kernel is compiled from the member's program without the equations its outputs do not
need (`clebsch_jax.batching.prune`): a function that returns part of a `Solution` does not
translate the rest of the march's work.
"""

from __future__ import annotations

import threading

import jax
import jax.numpy as jnp
import numpy as np

from ..march.integrate import caller_backend
from ..march.solution import collecting_checks, raise_collected
from ..native import (
    AUTO_MAX_IR_LINES,
    Unsupported,
    compiled_once,
    native_unavailable,
    warn_once,
)
from .prune import pruned

__all__ = ["wants_native", "native_program", "NativeBatch", "CALLBACKS", "member_key", "traced_once"]

WHAT = "cj.batch"
"""How the fallback warnings name the caller (`clebsch_jax.native.warn_once`)."""

CALLBACKS = ("debug_callback", "debug_print", "io_callback", "pure_callback")
"""Host callbacks: a native kernel cannot make them (the translation drops `debug_callback`),
so a function that makes one keeps the interpreter."""

_KERNELS: dict = {}
_KERNELS_LOCK = threading.Lock()
_KERNELS_MAX = 32


def wants_native(backend: str, traced: bool) -> bool:
    """Whether a call of `batch` with `backend` runs a native kernel: "xla" never; "auto" and
    "native" on concrete arguments where llvmlite imports. Elsewhere "native" raises a
    `ValueError` with the reason, and "auto" says it once (`warn_once`) and runs XLA."""
    if backend == "xla":
        return False
    if traced:
        why = "its arguments are traced (inside jit, vmap or grad)"
        if backend == "native":
            raise ValueError(f"backend='native': {why}; the native kernel runs concrete calls only.")
    else:
        why = native_unavailable()
    if why is None:
        return True
    refuse(backend, why)
    return False


def refuse(backend: str, why: str) -> None:
    """ "native": a `ValueError` saying `why`; "auto": a warning saying it, once per process
    (pointing at the call of the batched function: `refuse` is called by the functions `batch`
    calls)."""
    if backend == "native":
        raise ValueError(f"backend='native': {why}.")
    warn_once(why, what=WHAT, stacklevel=5)


class NativeBatch:
    """The kernel of a batch's member function (`native_program`) and the end-of-run checks of
    the `integrate(..., throw=True)` calls in it (`checks`, whose arguments the kernel outputs
    after the function's own `n_out` outputs)."""

    def __init__(self, program, checks: list):
        self.program, self.checks = program, checks

    def __call__(self, leaves: list) -> list:
        """The function's flat outputs for all members (batched leaves with a leading member
        axis, shared ones without), as JAX arrays; raises the first failed member's
        `IntegrationError` of a `throw=True` check."""
        outs, values = self.program(*[np.asarray(x) for x in leaves])
        raise_collected(self.checks, values)
        return [jnp.asarray(o) for o in outs]


def native_program(fun, flat_fun, tree, member: list, axes: list, backend: str):
    """The `NativeBatch` of `flat_fun` (`fun` on the flat leaves of arguments of structure
    `tree`) for one member's leaves `member` (shapes and dtypes) and `axes` (0: batched, None:
    shared), compiled on first use and kept; None where the translation refuses the program
    ("auto": said once, then the interpreter runs; "native": a `ValueError` with the reason).
    "auto" compiles kernels of at most `AUTO_MAX_IR_LINES` lines of LLVM IR."""
    limit = AUTO_MAX_IR_LINES if backend == "auto" else None
    key = _key(fun, tree, member, axes, limit)
    try:
        return compiled_once(
            _KERNELS, _KERNELS_LOCK, _KERNELS_MAX, key, lambda: _compile(flat_fun, member, axes, limit)
        )
    except Unsupported as err:
        why = f"the native translation does not cover fun: {err}"
    refuse(backend, why)
    return None


def _key(fun, tree, member: list, axes: list, limit):
    """The cache key of `fun`'s kernel: `member_key` and the IR limit."""
    return member_key(fun, tree, member, axes) + (limit,)


def member_key(fun, tree, member: list, axes: list) -> tuple:
    """What determines `fun`'s program of one member: its fingerprint, or (where the
    fingerprint cannot be read) the function itself, held by the caches; the arguments'
    structure, the member's shapes and dtypes, the axes and the environment (JAX's options)."""
    from ..native.fingerprint import environment, fingerprint

    found = fingerprint(fun)
    who = ("fingerprint", found) if found is not None else ("function", fun)
    shapes = tuple((tuple(x.shape), str(np.dtype(x.dtype))) for x in member)
    return (who, tree, shapes, tuple(axes), environment())


_TRACES: dict = {}
_TRACES_LOCK = threading.Lock()


def traced_once(key, trace):
    """`trace()` (a concrete call's trace of one member, with what its checks need) computed
    once per `key` (`member_key`) and kept: a concrete call of a batch again with new values
    traces nothing. The value is a list, to which the caller may add (the first members
    already checked). A trace holding a value traced by an enclosing transformation (a
    function that closes over one) is not kept."""
    from ..core.validation import is_traced

    found = compiled_once(_TRACES, _TRACES_LOCK, _KERNELS_MAX, key, lambda: [trace(), set()])
    if any(is_traced(c) for c in found[0][0].consts):
        with _TRACES_LOCK:
            _TRACES.pop(key, None)
    return found


def _compile(flat_fun, member: list, axes: list, limit) -> NativeBatch:
    """`flat_fun`'s member program, its `integrate` checks made outputs, compiled
    (`compile_member`); `Unsupported` where that cannot be done faithfully."""
    from ..native import compile_member

    checks: list = []

    def member_fun(*flat):
        with caller_backend(), collecting_checks() as found:
            out = flat_fun(*flat)
        checks[:] = [c._replace(args=None) for c in found]
        return jax.tree_util.tree_leaves(out), [c.args for c in found]

    closed, shape = jax.make_jaxpr(member_fun, return_shape=True)(*member)
    called = sorted(_primitives(closed.jaxpr) & set(CALLBACKS))
    if called:
        raise Unsupported(
            f"host callbacks ({', '.join(called)}), which a native kernel cannot make: jax.debug.print or "
            "callbacks, or integrate(throw=True) inside a jit, vmap or loop of fun's own (pass throw=False "
            "and read Solution.result there)"
        )
    # only what the outputs need: the translation writes out every entry it is given
    needed, tree = pruned(closed), jax.tree_util.tree_structure(shape)
    program = compile_member(
        lambda *a: jax.tree_util.tree_unflatten(tree, needed(*a)), *member, in_axes=tuple(axes), max_lines=limit
    )
    return NativeBatch(program, list(checks))


def _primitives(jaxpr) -> set:
    """The names of the primitives of `jaxpr` and of the programs nested in its equations."""
    found = set()
    for eqn in jaxpr.eqns:
        found.add(eqn.primitive.name)
        for value in eqn.params.values():
            for sub in value if isinstance(value, (tuple, list)) else (value,):
                inner = getattr(sub, "jaxpr", sub)  # a ClosedJaxpr's, or a Jaxpr
                if hasattr(inner, "eqns"):
                    found |= _primitives(inner)
    return found
