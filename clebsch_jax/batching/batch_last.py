r"""`batch`: `jax.vmap` for many small independent systems on the CPU, with the batch axis last.

`jax.vmap` puts the batch axis first: a batch of B rigid bodies holds its velocities as a
(B, 3) array, and every component a step touches, ξ₁ say, is a strided column of it. On the
CPU XLA then vectorises across the three components of one body, not across bodies, and a
step of a few hundred flops runs far below the machine's speed; the same straight-line step
written with the bodies along the last axis runs much faster.

`batch(fun)` has `jax.vmap`'s meaning (in_axes 0 or None, out_axes 0) but evaluates `fun`
differently: it traces `fun` once for one member (`jax.make_jaxpr`) and evaluates that program
with every batched value stored *batch-last*, shape (…member shape, B): each component of a
member is a contiguous row of B numbers, which XLA vectorises across members. The program is
walked by `clebsch_jax.batching.walk` with the stacked layout: each primitive is applied by a
rule (`clebsch_jax.batching.rules`) that knows where the batch axis is — elementwise
operations, broadcasts, reshapes, slices, reductions and small `dot_general`s keep it last at
no cost; `scan`, `while` and `cond` are evaluated with batch-last bodies (a `while` whose predicate
differs between members runs until the last member stops, the others held by a select, as
under `jax.vmap`); calls (`jit`, `custom_jvp_call`, …) are entered. Any other primitive (a
gather, a callback, a large dot) falls back on `jax.vmap` of that one primitive with the batch
axis moved last around it: slower, never wrong.

The batch is also cut into chunks of `chunk` members, marched to the end one chunk after the
other (`jax.lax.map`): the arrays of one chunk stay in cache, so the rate falls less as B
grows. (The measurements behind the layout and the chunks: `benchmarks/README.md`,
"Measurements behind the engine's choices".)

The result is `jax.vmap`'s up to round-off: the same operations on the same numbers; XLA may
fuse them differently for another layout. Each member's result does not depend on the other
members (padding members of the last chunk are copies of the last member, dropped).

That is the evaluation under tracing (inside `jax.jit`) and with `backend="xla"`. Called on
concrete arrays, `batch` compiles the member's program to a native kernel instead
(`clebsch_jax.batching.batch_native`, `clebsch_jax.native`) and runs all members through it
in one call, where the translation covers the program.
"""

from __future__ import annotations

import functools
from typing import Callable

import jax
import jax.extend.core as jex
import jax.numpy as jnp
import numpy as np
from jax import lax

from ..core.validation import check_memory, is_traced
from ..march.integrate import caller_backend, check_member, recording_calls
from ..march.solution import member_offset, raised_in_callback
from ..native import check_backend
from .batch_native import member_key, native_program, traced_once, wants_native
from .rules import batch_members, eval_closed, flat_axes, to_batched
from .walk import bind

__all__ = ["batch"]

DEFAULT_CHUNK = 1024
"""Members per chunk: the working set of the built-in models' steps stays in the L2 cache."""


def batch(fun: Callable, in_axes=0, *, chunk: int | None = DEFAULT_CHUNK, backend: str = "auto") -> Callable:
    r"""`jax.vmap(fun, in_axes)` for many small independent systems on the CPU (a sweep of rigid
    bodies, a batch of vortex clusters): a native kernel on concrete calls, else evaluated
    batch-last and in chunks.

    ```python
    march = cj.batch(lambda Q0, xi0: cj.integrate(body, Q0, xi0, dt=0.05, n_steps=50, throw=False))
    sol = march(Q0s, xi0s)    # the Solution jax.vmap would give, batch axis first
    ```

    **Arguments:**

    - `fun`: a function of arrays (pytrees of arrays) that `jax.vmap` could batch.
    - `in_axes`: 0 (batched along the leading axis) or None (shared), for all positional
      arguments or as a tuple with one entry per positional argument (which applies to every
      array in that argument).
    - `chunk`: members per chunk of the batch-last evaluation (default `DEFAULT_CHUNK`), or
      None for one chunk. Chunks run one after the other; the last is padded with copies of
      the last member. A loop in `fun` (Newton's) runs, in each chunk, until the chunk's
      slowest member stops: members that need very different numbers of iterations (clusters
      of point vortices, where a few members need many times the mean) run faster in small
      chunks (e.g. 64), while uniform ones (rigid bodies) prefer large chunks, where each
      operation's fixed cost is shared by more members (the runs: `benchmarks/README.md`,
      `throughput.py`). It does not apply to the native kernel, which runs a few members at
      a time, one per SIMD lane, each stopping its loops on its own.
    - `backend`: `"auto"` (default), `"native"` or `"xla"` (`clebsch_jax.native.BACKENDS`),
      checked when `batch` is called. A concrete call (no tracers among the arguments) with
      `"auto"` or `"native"` traces `fun` for one member, compiles it to a native kernel with
      LLVM (`clebsch_jax.native.compile_member`) and runs every member through it in one
      call, on the host CPU. `"xla"`, and a call traced by `jax.jit`, `jax.grad` or
      `jax.vmap`, run the batch-last evaluation in chunks, compiled by XLA (under tracing
      `"auto"` says so once, `"native"` raises a `ValueError`). Where the native translation
      does not cover `fun` (a primitive it lacks; a program past its size limits, for
      `"auto"` one of more than `clebsch_jax.native.AUTO_MAX_IR_LINES` lines of LLVM IR; a
      host callback such as `jax.debug.print`) or llvmlite cannot be imported, `"auto"`
      runs the batch-last evaluation and says once why (a
      `clebsch_jax.native.NativeFallbackWarning` naming the reason, e.g. the primitive), and
      `"native"` raises a `ValueError` with the reason.
      The two give the same results up to round-off (libm's transcendental functions and
      XLA's may differ in the last bits), and the native kernel the same bits from run to run.
      `integrate` calls in `fun` run on this backend: their own `backend=` is not consulted.

    **Returns:** a function with `jax.vmap(fun, in_axes)`'s signature and outputs (every output
    batched along axis 0).

    Compilation: the native kernel is kept for the process under `fun`'s fingerprint (its code,
    closures, defaults and globals: `clebsch_jax.native.fingerprint`; a function whose
    fingerprint cannot be read is kept by the cache itself, so another function never finds
    its kernel), the arguments' structure, the member's shapes and dtypes and `in_axes`: a
    later call with new values or another batch size compiles nothing; a function that
    closes over other values, or new member shapes, compiles again. A program the translation
    refused is remembered too. Compiled kernels are also kept on disk by their program
    (`clebsch_jax.native.fingerprint.cache_dir`), so that another process skips LLVM's work.
    The kernel's size, and LLVM's time, grow with the entries the member's program computes
    (the translation writes each out; what the outputs do not need is left out first,
    `clebsch_jax.batching.prune`): `integrate`'s traced march computes its nodes for all steps
    at once, so its kernel grows with `n_steps`, and a long march passes the translation's
    limits (`"auto"` then runs the batch-last evaluation, saying so; `clebsch_jax.sweep`'s
    kernels do not depend on the number of steps).

    Checks, before anything is evaluated or compiled: the outputs of all members, estimated
    from one member's trace, must fit in memory (twice: batch-last and in `jax.vmap`'s layout;
    a `ValueError` naming `batch` gives the estimate). Called on concrete arrays (not inside
    `jax.jit`), each `clebsch_jax.integrate` call in `fun` is also checked on the first
    member's values as `integrate` checks a plain call (`clebsch_jax.march.integrate.
    check_member`: the model by autodiff, the configuration, the first step on the manifold),
    which under tracing it cannot do itself; not when its arguments are computed by a loop or
    inside a transformation of `fun`'s own.

    Failures: `integrate(..., throw=True)` in `fun` raises the `IntegrationError` of the first
    failed member, named by its index in the batch, on both evaluations (the native kernel
    returns the check's values and the error is raised after the run; inside a `jax.jit` or
    loop of `fun`'s own the check stays a host callback, and the batch-last evaluation runs).

    Transformations: jit-compatible (trace it inside `jax.jit`; it is not jitted itself; the
    batch-last evaluation then runs). Not for differentiation: the program is evaluated
    primitive by primitive, so custom derivative rules (`custom_jvp`, the implicit
    differentiation of `integrate`'s Newton solves) are not seen by an outer `jax.grad`,
    which then meets the Newton `while_loop`s themselves and raises JAX's error for reverse
    mode through them; differentiate with `jax.vmap` instead. Not batchable again by
    `jax.vmap` in a useful way (flatten the batch instead).
    """
    if chunk is not None and (not isinstance(chunk, int) or isinstance(chunk, bool) or chunk < 1):
        raise ValueError(f"chunk: expected a whole number >= 1 or None, got {chunk!r}.")
    backend = check_backend(backend)

    @functools.wraps(fun)
    def batched(*args):
        leaves, tree = jax.tree_util.tree_flatten(args)
        axes = flat_axes(in_axes, args)
        B, leaves, member = batch_members(leaves, axes)
        if B == 0:  # an empty batch: jax.vmap's empty outputs (no chunk to run, nothing to say)
            with caller_backend():
                return jax.vmap(fun, in_axes=in_axes)(*args)
        flags = [a == 0 for a in axes]

        def flat_fun(*flat):
            return fun(*jax.tree_util.tree_unflatten(tree, flat))

        traced = any(is_traced(x) for x in leaves)
        native = wants_native(backend, traced)
        trace = lambda: _trace(flat_fun, member, record=not traced)
        checked = None  # first members' check values already checked (concrete calls)
        with caller_backend():  # integrate's calls in fun run on batch's backend: they say nothing of their own
            if traced:
                closed, out_shapes, calls = trace()
            else:  # a concrete call: the trace depends on the function and the shapes alone
                (closed, out_shapes, calls), checked = traced_once(member_key(fun, tree, member, axes), trace)
        out_tree = jax.tree_util.tree_structure(out_shapes)
        n_out = out_tree.num_leaves
        c = B if chunk is None else min(chunk, B)
        n_chunks = -(-B // c)
        pad = n_chunks * c - B
        _check_outputs(out_shapes, B, pad)
        if calls:
            _check_first_member(closed, calls, n_out, leaves, flags, B, checked)
        program = native_program(fun, flat_fun, tree, member, axes, backend) if native else None
        if program is not None:  # all members in one call of the kernel
            return jax.tree_util.tree_unflatten(out_tree, program(leaves))

        def run(chunk_leaves, first=0):  # batched leaves batch-last, (…, c); `first`: its first member
            with member_offset(first):  # a failure under integrate(throw=True) names the batch's member
                outs, out_flags = eval_closed(closed, chunk_leaves, flags, c)
            return [to_batched(o, f, c) for o, f in zip(outs[:n_out], out_flags[:n_out])]

        def split(x, a):  # (B, …) -> (n_chunks, …, c)
            if a != 0:
                return x
            if pad:
                x = jnp.concatenate([x, jnp.broadcast_to(x[-1:], (pad,) + x.shape[1:])])
            return jnp.moveaxis(x.reshape((n_chunks, c) + x.shape[1:]), 1, -1)

        chunked = [split(x, a) for x, a in zip(leaves, axes)]
        try:
            if n_chunks == 1:
                outs = [o[None] for o in run([x[0] if f else x for x, f in zip(chunked, flags)])]
            else:
                dyn = [x for x, f in zip(chunked, flags) if f]

                def one(indexed):
                    index, dyn_chunk = indexed
                    it = iter(dyn_chunk)
                    return run([next(it) if f else x for x, f in zip(chunked, flags)], index * c)

                outs = lax.map(one, (jnp.arange(n_chunks), dyn))
        except jax.errors.JaxRuntimeError as err:  # integrate(throw=True) inside the compiled chunks
            found = raised_in_callback(err)
            if found is None:
                raise
            raise found from None
        outs = [jnp.moveaxis(o, -1, 1).reshape((n_chunks * c,) + o.shape[1:-1])[:B] for o in outs]
        return jax.tree_util.tree_unflatten(out_tree, outs)

    return batched


def _trace(flat_fun, member, record: bool):
    """`jax.make_jaxpr` of one member's `flat_fun`: (closed jaxpr, output shapes, recorded
    `integrate` calls). With `record` (the batch's values are concrete), the traced `integrate`
    calls inside are recorded (`clebsch_jax.march.integrate.recording_calls`) and their array
    arguments added as extra outputs of the jaxpr, after the function's own, so that they can
    be evaluated for the first member (`_check_first_member`). Calls whose arguments belong to
    a trace inside the function (its own `jit`, `vmap`, `scan`) cannot be outputs (JAX raises,
    or keeps them as constants of the jaxpr): the function is then traced again without
    recording (and those calls are not checked)."""
    if record:
        found = []

        def probe(*flat):
            with recording_calls() as calls:
                out = flat_fun(*flat)
            found.extend(calls)
            return out, [[x for x in jax.tree_util.tree_leaves(call.args) if _is_value(x)] for call in calls]

        try:
            closed, (out_shapes, _) = jax.make_jaxpr(probe, return_shape=True)(*member)
            if not any(is_traced(c) for c in closed.consts):  # a leaked inner tracer becomes a constant
                return closed, out_shapes, found
        except jax.errors.UnexpectedTracerError:
            pass
        found.clear()
    closed, out_shapes = jax.make_jaxpr(flat_fun, return_shape=True)(*member)
    return closed, out_shapes, []


def _is_value(x) -> bool:
    """Whether a leaf of `integrate`'s arguments is a value (an array, a tracer, a number),
    which the trace can output, and not a function or other static object."""
    return is_traced(x) or isinstance(x, (jax.Array, np.ndarray, np.generic, int, float, complex))


RESULT_COPIES = 2
"""`_check_outputs` counts the batch's outputs this many times: they are made batch-last, then
moved to `jax.vmap`'s layout (a copy) — a lower bound of what the program needs, whose own
intermediate arrays (a march's stacked steps) come on top."""


def _check_outputs(out_shapes, B: int, pad: int) -> None:
    """Refuse, before compiling, a batch whose outputs alone would not fit in memory
    (`clebsch_jax.core.validation.check_memory`, `integrate`'s guard), e.g. the `Solution`s of
    10⁴ members of thousands of steps each (`pad`: the copies that fill the last chunk): the
    estimate and the ways out."""
    per = sum(int(np.prod(x.shape)) * np.dtype(x.dtype).itemsize for x in jax.tree_util.tree_leaves(out_shapes))
    check_memory(
        "batch",
        f"{B} members",
        RESULT_COPIES * per * (B + pad),
        "Run fewer members per call, return less per member (e.g. sol.Q[-1] or a reduction instead of the "
        "whole Solution), or use clebsch_jax.sweep, which runs members in batches and keeps per-member "
        "reductions and every k-th node (save_every=k) instead of trajectories.",
        detail=f" for the outputs ({per} bytes per member, {RESULT_COPIES} copies: batch-last and batch-first)",
    )


MEMBER_CHECK_MAX_EQNS = 200
"""`_check_first_member` evaluates the operations that compute `integrate`'s arguments from the
batch's for a member, one by one, when there are at most this many and none is a loop:
arguments computed by a long program (another march's result) are not checked."""

MEMBER_CHECK_TRIES = 8
"""`_check_first_member` checks the first member whose arguments are valid (finite, dt > 0)
among the first this many members."""


def _check_first_member(closed, calls: list, n_out: int, leaves: list, flags: list, B: int, checked=None) -> None:
    """`integrate`'s checks that need values (`clebsch_jax.march.integrate.check_member`: the model
    by autodiff, the configuration, Q0 in the velocity map's group, the first step on the
    manifold) of each recorded `integrate` call, for the batch's first member whose arguments are
    valid (a member with non-finite values or dt <= 0 reports `Status.INVALID_INPUT` in the
    batch, as under `jax.vmap`), before the batch is compiled: its arguments are the jaxpr's
    extra outputs (after the `n_out` outputs of the function), evaluated for that member.
    `checked` (a concrete call's, kept with its trace): those arguments' values that passed
    the checks before, which are not checked again."""
    jaxpr = closed.jaxpr
    extras = jaxpr.outvars[n_out:]
    needed = {v for v in extras if not isinstance(v, jex.Literal)}
    kept = []
    for eqn in reversed(jaxpr.eqns):
        if any(v in needed for v in eqn.outvars if not isinstance(v, jex.DropVar)):
            kept.append(eqn)
            needed.update(v for v in eqn.invars if not isinstance(v, jex.Literal))
    if len(kept) > MEMBER_CHECK_MAX_EQNS or any(eqn.primitive.name in ("while", "scan") for eqn in kept):
        return
    kept.reverse()
    host = [np.asarray(x) if f else x for x, f in zip(leaves, flags)]
    for m in range(min(B, MEMBER_CHECK_TRIES)):
        env = dict(zip(jaxpr.constvars, closed.consts))
        env.update(zip(jaxpr.invars, [x[m] if f else x for x, f in zip(host, flags)]))
        for eqn in kept:
            vals = [v.val if isinstance(v, jex.Literal) else env[v] for v in eqn.invars]
            env.update(zip(eqn.outvars, bind(eqn, vals)))
        values = [np.asarray(v.val if isinstance(v, jex.Literal) else env[v]) for v in extras]
        if all(np.all(np.isfinite(v)) for v in values if np.issubdtype(v.dtype, np.inexact)):
            break
    else:
        return
    seen = tuple((v.dtype.str, v.shape, v.tobytes()) for v in values)
    if checked is not None and seen in checked:  # these values passed the checks before
        return
    values = iter(values)
    for call in calls:
        flat, tree = jax.tree_util.tree_flatten(call.args)
        flat = [next(values) if _is_value(x) else x for x in flat]  # functions stay as they are
        system, Q0, xi0, P0, dt, t0 = jax.tree_util.tree_unflatten(tree, flat)
        if not np.all(np.asarray(dt) > 0):
            continue  # reported by the batch (INVALID_INPUT), as under jax.vmap
        try:
            check_member(system, Q0, xi0, dt=dt, P0=P0, t0=t0, **call.options)
        except (ValueError, TypeError) as err:
            raise type(err)(f"batch: member {m} is rejected by integrate's checks: {err}") from err
    if checked is not None:  # a concrete call's cached trace keeps the last few values checked
        if len(checked) >= MEMBER_CHECK_TRIES:
            checked.clear()
        checked.add(seen)
