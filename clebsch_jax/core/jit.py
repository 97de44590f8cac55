"""`filter_jit`: `jax.jit` with every array leaf of the arguments traced and every other leaf
(user functions, steppers, options) static, so that user closures can be passed."""

from __future__ import annotations

import contextlib
import functools
import threading

import jax

from .validation import is_array

__all__ = [
    "filter_jit",
    "jit_with_options",
    "evaluate_now",
    "memo",
    "undifferentiated",
    "in_undifferentiated",
    "QUICK_COMPILE",
    "LEAN_COMPILE",
]

QUICK_COMPILE = {"xla_cpu_use_fusion_emitters": False}
"""XLA options (`jit_with_options(fun, QUICK_COMPILE)`) for programs whose compile time
matters more than the last bit of their speed: inspections run once, the sweep's general
chunk, and `integrate`'s march for every stepper whose `quick_compile` is True. XLA's CPU
compiler then emits fused loops with its older emitters, which compile faster; those
programs ran at the same rate (within a few per cent), while the lean chunk and the
Gauss–Legendre march ran slower, so they keep the default (`benchmarks/README.md`,
"Measurements behind the engine's choices"). A field of XLA's debug options, read by its CPU
compiler (other backends were not available to test it on)."""

LEAN_COMPILE = {"xla_cpu_opt_preset": "CPU_OPT_PRESET_FAST_COMPILE"}
"""XLA options of the sweep's lean chunk (`clebsch_jax.batching.lean`): XLA's CPU preset for a
fast compile. On that program of long rows it compiled faster and ran faster, with bitwise the
same results; on `integrate`'s programs it compiled slower and ran slower, so nothing else uses
it (`benchmarks/README.md`, "Measurements behind the engine's choices"). A field of XLA's debug
options, read by its CPU compiler (other backends were not available to test it on)."""


class _Dynamic:
    def __repr__(self):
        return "<dynamic>"


_DYNAMIC = _Dynamic()


_NESTED = "can only be passed to top-level `jax.jit`"
"""The start of JAX's error for compiler options on a jit staged into another trace."""


def jit_with_options(fun, compiler_options: dict | None, **jit_kwargs):
    """`jax.jit(fun, **jit_kwargs)` whose calls compile with `compiler_options` (e.g.
    `QUICK_COMPILE`) where they are programs of their own. JAX refuses compiler options on a
    jit called inside another trace (the caller's `jit`, or a `grad` that stages the call): that
    call runs the same function through a jit without them, as part of the caller's program.
    `_cache_size()` counts the programs of both."""
    if not compiler_options:
        return jax.jit(fun, **jit_kwargs)
    with_options = jax.jit(fun, compiler_options=compiler_options, **jit_kwargs)
    plain = jax.jit(fun, **jit_kwargs)

    @functools.wraps(fun)
    def call(*args, **kwargs):
        try:
            return with_options(*args, **kwargs)
        except ValueError as err:
            if _NESTED not in str(err):
                raise
        return plain(*args, **kwargs)

    call._cache_size = lambda: with_options._cache_size() + plain._cache_size()
    return call


def evaluate_now(fun, *args, compiler_options: dict | None = QUICK_COMPILE):
    """`fun(*args)` on concrete arrays, computed now as one compiled program, also where the
    caller is inside a trace (its `jit`): traced, lowered and compiled ahead of time, whose call
    runs the program rather than staging it into the caller's. Unlike a call inside
    `jax.ensure_compile_time_eval`, the constants in `fun` (e.g. `lie.hat`'s zeros) are traced
    into that program, not evaluated one operation at a time, each a compile of its own. None
    when `fun` closes over a traced value (the trace then has inputs besides `args`)."""
    traced = jax.jit(fun).trace(*args)
    if len(traced.jaxpr.in_avals) != len(jax.tree_util.tree_leaves(args)):
        return None
    return traced.lower().compile(compiler_options)(*args)


class _Contexts(threading.local):
    """The open `undifferentiated` contexts of the calling thread (`depth`)."""

    def __init__(self):
        self.depth = 0


_UNDIFFERENTIATED = _Contexts()


def in_undifferentiated() -> bool:
    """Whether this thread is inside `undifferentiated`."""
    return _UNDIFFERENTIATED.depth > 0


@contextlib.contextmanager
def undifferentiated():
    """Within this context the roots of the engine's solves are traced without their implicit
    derivative rules (`clebsch_jax.roots.implicit.implicit_root` calls its loop directly), for
    a program that no derivative is ever taken of (a sweep's chunks): the rule's closure
    conversion traces every solve a second time.

    `filter_jit` keys its programs by this context, so a function it compiles (`integrate`'s
    march) traced inside the context is traced again, with its rules, outside it. A plain
    `jax.jit` function with a root inside must not be traced inside the context: JAX would
    reuse that trace, without the rule, in a later differentiated call. The context is the
    calling thread's own: a sweep traces its batches' programs from several threads at once
    (`clebsch_jax.sweep`'s `threads`), and another thread's trace keeps its rules."""
    _UNDIFFERENTIATED.depth += 1
    try:
        yield
    finally:
        _UNDIFFERENTIATED.depth -= 1


def filter_jit(fun, compiler_options: dict | None = None):
    """`fun` compiled with its array leaves traced and its other leaves static (hashed); one
    program per distinct static part and array shapes, and per `undifferentiated` context;
    `compiler_options` as in `jit_with_options`."""

    def jitted(treedef, static, plain, dynamic):
        leaves = [d if s is _DYNAMIC else s for s, d in zip(static, dynamic)]
        args, kwargs = jax.tree_util.tree_unflatten(treedef, leaves)
        if not plain:
            return fun(*args, **kwargs)
        with undifferentiated():
            return fun(*args, **kwargs)

    jitted.__name__ = jitted.__qualname__ = getattr(fun, "__name__", "jitted")  # names the program in JAX's logs
    jitted = jit_with_options(jitted, compiler_options, static_argnums=(0, 1, 2))

    @functools.wraps(fun)
    def wrapper(*args, **kwargs):
        leaves, treedef = jax.tree_util.tree_flatten((args, kwargs))
        static = tuple(_DYNAMIC if is_array(x) else x for x in leaves)
        dynamic = [x if is_array(x) else None for x in leaves]
        return jitted(treedef, static, in_undifferentiated(), dynamic)

    return wrapper


def memo(cache: dict, key, compute, limit: int):
    """`compute()`, kept in `cache` under `key` (the cache is cleared when it holds `limit`
    entries); computed every time when the key cannot be hashed (e.g. an unhashable map). For
    results of Python-level work on static facts (a trace, an inspection of a map) that every
    call would otherwise repeat."""
    try:
        hashable = True
        if key in cache:
            return cache[key]
    except TypeError:
        hashable = False
    value = compute()  # outside the handler: its own errors are not chained to the TypeError
    if hashable:
        if len(cache) >= limit:
            cache.clear()
        cache[key] = value
    return value
