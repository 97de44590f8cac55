r"""The one march: steps of a stepper in `jax.lax.scan`, then the `Solution`.

A step whose solve fails makes the member's state NaN from then on and marks the later steps
`Status.SKIPPED` (`gate`): never plausible-looking numbers. After the steps the stepper says
what the nodes are (`AbstractStepper.nodes`), the nodal velocities are recovered from
Lemma 7's relation at every node (except for degenerate systems), and the overall result and
first failure are found.

The march is cut into **chunks** (`run_chunk`): a scan of a fixed number of steps that hands
its carry — the stepper's state and memory, the step number, the failure flag and the last
step velocity — to the next chunk. Called with concrete arguments, `integrate` runs the march
as `march_chunked`: one compiled program for the start and one for a chunk of `CHUNK_STEPS`
steps, whose trip count is an argument (`n_total`: steps from `n_total` on leave the carry
unchanged), so a new `n_steps` or `dt` reuses both programs. Under a JAX transformation
(`jit`, `vmap`, `grad`) the march is one chunk of exactly `n_steps` steps (`march`), traced
into the caller's program. Both assemble the `Solution` with the same code, on NumPy arrays
or traced ones, and the carry is handed over exactly: the chunked march is the same
arithmetic as the single scan.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..core.jit import filter_jit
from ..core.validation import any_traced
from ..discrete.residual import nodal_residual
from ..roots.status import NewtonStats, Status, skip_stats
from ..steppers.base import AbstractStepper, Nodes
from .solution import Solution

__all__ = ["march", "march_chunked", "run_chunk", "start", "gate", "nodal_velocities", "CHUNK_STEPS", "NODAL_BLOCK"]

CHUNK_STEPS = 1024
"""Steps per compiled chunk of `march_chunked` (the last chunk runs idle past `n_steps`)."""


NODAL_BLOCK = 128
"""Steps, and nodes per vmapped block of nodal solves, per block of a chunk longer than this:
blocks holding only steps or nodes past the run's last step (or a failure) are skipped."""


class Carry(NamedTuple):
    """What one chunk hands to the next: the stepper's `state` and `memory`, the number `n`
    of the next step, `alive` (no step failed yet) and `xi_last`, the velocity of the last
    step made (the seed of the nodal solve at the node it arrives at)."""

    state: Any
    memory: Any
    n: jax.Array
    alive: jax.Array
    xi_last: jax.Array


class Chunk(NamedTuple):
    """The record of a chunk of C steps starting at step n₀: the nodes n₀ … n₀ + C (node
    fields have C + 1 entries; the last is the node after the last step actually made), the
    step fields (C entries), the nodal velocities and their statistics, and `valid` per node."""

    nodes: Nodes
    stats: NewtonStats
    xi: Any
    nodal_stats: NewtonStats
    valid: jax.Array


def gate(alive, stats: NewtonStats, values):
    """After a failed step a member's values become NaN and later steps are marked SKIPPED,
    with no Newton updates or Jacobians counted (the loop only ran over NaNs beside the live
    members) and a NaN residual. Returns (ok, stats with statuses, gated values)."""
    ok = alive & (stats.status == Status.SUCCESS)
    values = jax.tree_util.tree_map(lambda a: jnp.where(ok, a, jnp.nan), values)
    return ok, skip_stats(stats, alive), values


def start(stepper: AbstractStepper, system, Q0, xi0, P0, dt):
    """The stepper's initial state as a `Carry`, and the iterations its start-up took."""
    state0, startup_iterations = stepper.init(system, Q0, xi0, P0, dt)
    carry = Carry(state0, stepper.init_memory(system, state0), jnp.asarray(0, jnp.int32), jnp.asarray(True),
                  jnp.zeros_like(xi0))
    return carry, jnp.asarray(startup_iterations, jnp.int32)


def run_chunk(stepper: AbstractStepper, system, carry: Carry, dt, length: int, n_total) -> tuple[Carry, Chunk]:
    """`length` steps from `carry`, their nodes and nodal velocities; the steps numbered
    `n_total` (an int32 array: the run's number of steps) and later leave the carry unchanged."""

    def advance(c: Carry):
        state, memory, out, stats = stepper.step(system, c.state, c.memory, dt, c.n, c.alive)
        ok, stats, (state, out) = gate(c.alive, stats, (state, out))
        return c._replace(state=state, memory=memory, n=c.n + 1, alive=ok), (state, out, stats, c.alive)

    blank = jax.eval_shape(lambda c: advance(c)[1], carry)

    def idle(c: Carry):
        _, out, stats, _ = jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), blank)
        return c, (c.state, out, stats, jnp.asarray(False))

    def body(c: Carry, _):
        return jax.lax.cond(c.n < n_total, advance, idle, c)

    if length > NODAL_BLOCK and length % NODAL_BLOCK == 0:
        # blocks of steps, a block wholly past the end skipped: a chunk running idle past the
        # end of a run costs almost nothing for its idle steps
        def block(c: Carry, _):
            run = lambda c: jax.lax.scan(body, c, None, length=NODAL_BLOCK)
            skip = lambda c: (c, jax.tree_util.tree_map(
                lambda a: jnp.broadcast_to(a, (NODAL_BLOCK,) + a.shape), idle(c)[1]))  # idle steps
            return jax.lax.cond(c.n < n_total, run, skip, c)

        last, ys = jax.lax.scan(block, carry, None, length=length // NODAL_BLOCK)
        states, outs, stats, valid = jax.tree_util.tree_map(lambda a: a.reshape((length,) + a.shape[2:]), ys)
    else:
        last, (states, outs, stats, valid) = jax.lax.scan(body, carry, None, length=length)
    nodes = stepper.nodes(system, carry.state, states, outs)
    made = jnp.clip(n_total - carry.n, 0, length)
    xi_last = jnp.where(made > 0, nodes.xi_step[jnp.maximum(made - 1, 0)], carry.xi_last)
    valid = jnp.concatenate([valid, last.alive[None]])
    # seeds of the nodal solves: the velocity of the step leaving the node (the given ξ⁰ at
    # node 0), or, where that step failed or at the last node, of the step arriving at it
    leaving = jnp.concatenate([jnp.where(carry.n == 0, nodes.xi_seed, nodes.xi_step[0])[None],
                               nodes.xi_step[1:], xi_last[None]])
    first = jnp.where(carry.n == 0, nodes.xi_seed, carry.xi_last)
    arriving = jnp.concatenate([first[None], nodes.xi_step[:-1], xi_last[None]])
    guesses = jnp.where(_finite_rows(leaving), leaving, arriving)
    if system.degenerate:  # Lemma 7 does not determine nodal velocities: none are solved for
        zero = jnp.zeros(length + 1, jnp.int32)
        xi = None
        nodal = skip_stats(NewtonStats(iterations=zero, residual_norm=jnp.zeros(length + 1, dt.dtype),
                                       status=jnp.full(length + 1, Status.SUCCESS, jnp.int32), jacobians=zero), valid)
    else:
        xi, nodal = nodal_velocities(system, stepper.nodal_solver, nodes.nodal_Q, nodes.momentum, guesses, valid)
    return last._replace(xi_last=xi_last), Chunk(nodes, stats, xi, nodal, valid)


def _finite_rows(a):
    finite = jnp.isfinite(a).reshape(a.shape[0], -1).all(axis=1)
    return finite.reshape((-1,) + (1,) * (a.ndim - 1))


def nodal_velocities(system, finder, Qs, mus, guesses, valid, block: int = NODAL_BLOCK):
    """Solve Lemma 7's relation for ξ at every node (vmapped `finder.solve`), gated by `valid`.

    More than `block` nodes are solved in blocks of `block` (a scan whose blocks past the last
    valid node are skipped by `lax.cond`), so a chunk that runs idle past the end of a run
    costs nothing for its idle nodes; the arithmetic of each node's solve is the same."""
    expand = lambda v, a: v.reshape(v.shape + (1,) * (a.ndim - 1))
    seeds = jnp.where(expand(valid, guesses), guesses, jnp.nan)
    solve = jax.vmap(lambda q, mu, g: finder.solve(lambda x: nodal_residual(system, q, mu, x), g))
    n = valid.shape[0]
    if n <= block:
        xin, st = solve(Qs, mus, seeds)
    else:
        xin, st = _blocked(solve, (Qs, mus, seeds), valid, block)
    ok = valid & (st.status == Status.SUCCESS)  # a failed nodal solve leaves no plausible-looking ξ
    return jnp.where(expand(ok, xin), xin, jnp.nan), skip_stats(st, valid)


def _blocked(solve, args, valid, block: int):
    """`solve(*args)` (vmapped over the leading axis of `args`) in blocks of `block` entries,
    skipping the blocks after the last `valid` entry; their outputs are zeros."""
    n = valid.shape[0]
    n_blocks = -(-n // block)
    pad = lambda a: jnp.concatenate([a, jnp.repeat(a[-1:], n_blocks * block - n, axis=0)])
    blocks = jax.tree_util.tree_map(lambda a: pad(a).reshape((n_blocks, block) + a.shape[1:]), args)
    needed = (jnp.max(jnp.where(valid, jnp.arange(n), -1)) + block) // block  # blocks up to the last valid entry
    blank = jax.eval_shape(solve, *jax.tree_util.tree_map(lambda a: a[0], blocks))

    def one(b, xs):
        return b + 1, jax.lax.cond(b < needed, lambda: solve(*xs),
                                   lambda: jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), blank))

    _, out = jax.lax.scan(one, jnp.asarray(0, needed.dtype), blocks)
    return jax.tree_util.tree_map(lambda a: a.reshape((n_blocks * block,) + a.shape[2:])[:n], out)


def march(stepper: AbstractStepper, system, Q0, xi0, P0, dt, t0, n_steps: int) -> Solution:
    """Run `stepper` (prepared for `system`) for `n_steps` steps of size `dt` from
    $(Q^0, \\xi^0)$ (and $P^0$, if not None) in one scan and assemble the `Solution`."""
    carry, startup = start(stepper, system, Q0, xi0, P0, dt)
    # with the trip count as in `march_chunked` (every step taken): the same step program
    _, chunk = run_chunk(stepper, system, carry, dt, n_steps, jnp.asarray(n_steps, jnp.int32))
    return _assemble(jnp, stepper, system, [chunk], n_steps, startup, dt, t0, Q0, xi0)


_start_jit = filter_jit(start)
_chunk_jit = filter_jit(run_chunk)


def march_chunked(stepper: AbstractStepper, system, Q0, xi0, P0, dt, t0, n_steps: int,
                  chunk_steps: int = CHUNK_STEPS) -> Solution:
    """`march` with concrete arguments, as compiled chunks of `chunk_steps` steps: the
    programs depend on the stepper, the system and the shapes, not on `n_steps` or `dt`."""
    carry, startup = _start_jit(stepper, system, Q0, xi0, P0, dt)
    total = jnp.asarray(n_steps, jnp.int32)
    chunks = []
    for _ in range(-(-n_steps // chunk_steps)):
        carry, chunk = _chunk_jit(stepper, system, carry, dt, chunk_steps, total)
        chunks.append(chunk)
    if any_traced(chunks, startup):
        # a user function closed over a traced value (the caller is inside jit/vmap/grad)
        return _assemble(jnp, stepper, system, chunks, n_steps, startup, dt, t0, Q0, xi0)
    chunks, startup, dt, t0 = jax.tree_util.tree_map(np.asarray, (chunks, startup, dt, t0))
    return jax.device_put(_assemble(np, stepper, system, chunks, n_steps, startup, dt, t0, Q0, xi0))


def _join(xp, chunks, n_steps: int, node: bool):
    """The chunks' records of a field joined: N step entries, or N + 1 node entries."""
    first = [c[:-1] if node else c for c in chunks]
    joined = xp.concatenate(first)[:n_steps] if len(first) > 1 else first[0][:n_steps]
    return xp.concatenate([joined, chunks[-1][-1:]]) if node else joined


def _assemble(xp, stepper, system, chunks: list[Chunk], n_steps: int, startup, dt, t0, Q0, xi0) -> Solution:
    """The `Solution` from the chunks' records (`xp`: `numpy` or `jax.numpy`, as they are)."""
    def join(get, node):
        fields = [get(c) for c in chunks]
        if fields[0] is None:
            return None
        return jax.tree_util.tree_map(lambda *a: _join(xp, list(a), n_steps, node), *fields)

    nodes = join(lambda c: c.nodes._replace(P=None, xi_step=None, xi_seed=None), True)
    stats = join(lambda c: c.stats, False)
    stats = stats._replace(iterations=stats.iterations + xp.where(xp.arange(n_steps) == 0, startup, 0)
                           .astype(stats.iterations.dtype))  # start-up work belongs to step 0
    P, xi_step = join(lambda c: c.nodes.P, False), join(lambda c: c.nodes.xi_step, False)
    xin, nodal, valid = join(lambda c: c.xi, True), join(lambda c: c.nodal_stats, True), join(lambda c: c.valid, True)
    facts = stepper.facts(system)
    failed = stats.status != Status.SUCCESS
    any_step, first_step = xp.any(failed), xp.argmax(failed)
    nodal_failed = valid & (nodal.status != Status.SUCCESS)
    any_nodal, first_node = xp.any(nodal_failed), xp.argmax(nodal_failed)
    result = xp.where(any_step, stats.status[first_step],
                      xp.where(any_nodal, Status.LEGENDRE, Status.SUCCESS)).astype(xp.int32)
    failed_step = xp.where(any_step, first_step, xp.where(any_nodal, first_node, -1)).astype(xp.int32)
    # Gauss–Legendre takes Q̇ from its collocation polynomial, not from the derivative map
    derivative_map = ("none (collocation)" if facts.scheme == "gauss"
                      else getattr(system.derivative_map, "name", repr(system.derivative_map)))
    return Solution(
        ts=t0 + dt * xp.arange(n_steps + 1, dtype=dt.dtype), Q=nodes.Q, p=nodes.p, xi=xin, xi_step=xi_step,
        P=P, momentum=nodes.momentum, stats=stats, nodal_stats=nodal, result=result, failed_step=failed_step,
        valid=valid, scheme=facts.scheme, form=facts.form, order=facts.order, method=facts.name,
        derivative_map=derivative_map, q_ndim=Q0.ndim, xi_ndim=xi0.ndim,
        solves_per_step=facts.solves_per_step,
    )
