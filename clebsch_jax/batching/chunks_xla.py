r"""A chunk of a batch as XLA programs: the general path, the fast path and the lean chunk.

One chunk of one member is an `integrate` call of `Config.n` steps from the carry the chunk
before handed on (`Carry`: the canonical state and the running reductions); a batch runs it
through `cj.batch` (`run_chunk`, the general Newton loop) or, on the fast path, through the
scalarising evaluator (`run_fast_chunk`: `clebsch_jax.batching.fast`'s fixed updates, or the
lean chunk of `clebsch_jax.batching.lean`), which says per member whether its check failed.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp

from .. import diagnostics as _diagnostics
from ..core.jit import LEAN_COMPILE, QUICK_COMPILE, jit_with_options, undifferentiated
from ..discrete.legendre import initial_multiplier
from ..march.carry import start as march_start
from ..march.continuation import continue_from
from ..march.energy_check import energy_jump, energy_rtol, node_energies
from ..march.first_step import first_step_failed, half_steps
from ..march.arguments import prepared_method
from ..roots.status import Status
from .batch_last import batch
from .config import Carry, Config, chunk_integrate, member_system
from .lean import lean_chunk
from .scalarise import scalarise


def _deviation(values, ref):
    """max-norm over a value's own axes of |values[n] - ref|, one number per node."""
    d = jnp.abs(values - ref[None])
    return jnp.max(d.reshape(d.shape[0], -1), axis=1) if d.ndim > 1 else d


def _node_Q(cfg: Config, sol, carry: Carry):
    """The configurations at the chunk's nodes: the chunk's start where Q is not reconstructed
    (the reduced march: the Lagrangian does not depend on Q)."""
    return sol.Q if sol.Q is not None else jnp.broadcast_to(carry.Q, (cfg.n + 1,) + carry.Q.shape)


def _energy_check(cfg: Config, system, sol, carry: Carry):
    """`integrate`'s energy check (`check_energy`) over the whole run, made chunk by chunk: the
    chunks run unchecked and the sweep compares each step's energy change with the running
    maxima of the steps before it, carried from chunk to chunk. Returns (jumped, step, the
    running maxima after the chunk, the nodes' energies or None)."""
    if not cfg.check_energy or sol.xi is None:  # degenerate systems are not checked (as in integrate)
        return jnp.asarray(False), jnp.asarray(cfg.n), carry.energy_change, carry.energy_size, None
    E, size = node_energies(system, _node_Q(cfg, sol, carry), sol.xi)
    rtol = energy_rtol(cfg.check_energy)
    return (*energy_jump(jnp, E, size, sol.stats.status, carry.energy_change, carry.energy_size, rtol), E)


def _with_start_P(cfg: Config, system, carry: Carry, first) -> Carry:
    """`carry` with the minimum-norm initial multiplier P⁰ from (Q⁰, ξ⁰) (Lemma 7,
    `initial_multiplier`) in the run's first chunk, when the sweep was given no P0: the batch
    starts with a placeholder there, and every chunk program derives it (the lean chunk its
    momentum, `lean_chunk`'s `derive_momentum`), instead of a program of its own compiled for it."""
    if not cfg.derive_P:
        return carry
    return carry._replace(P=jnp.where(first, initial_multiplier(system, carry.Q, carry.xi), carry.P))


def _march_state(cfg: Config, system, carry: Carry, dt, first, alive):
    """The march state a general chunk starts from, and the start-up iterations it counts: the
    carried one (the last chunk's `Solution.march_state`), or in the run's first chunk — and
    after a chunk of the fast or lean path — the state `integrate` starts from
    (`clebsch_jax.march.carry.start`). Both are computed (a member's choice is a value); a
    failed member makes no step."""
    stepper, _, _ = prepared_method(
        system, carry.Q, carry.xi, dt=dt, n_steps=cfg.n, P0=carry.P, t0=carry.t, **dict(cfg.options)
    )
    fresh, startup = march_start(stepper, system, carry.Q, carry.xi, carry.P, dt, check_inputs=True)
    use = ~first & carry.march_ok
    state = jax.tree_util.tree_map(lambda c, f: jnp.where(use, c, f), carry.march, fresh)
    return state._replace(alive=state.alive & alive), jnp.where(use, 0, startup)


def _first_step(cfg: Config, system, carry: Carry, dt, first, sol, jumped, jump_step):
    """`integrate`'s first-step check (`clebsch_jax.march.first_step.first_step_probe`) in the run's
    first chunk: whether step 0 converged, was not failed by the energy check, and lies far from
    the node two half steps from the start reach (`first_step_failed`). The half steps run in a
    loop of two iterations in the first chunk and none in the others (`half_steps`)."""
    stepper, _, _ = prepared_method(
        system, carry.Q, carry.xi, dt=dt, n_steps=cfg.n, P0=carry.P, t0=carry.t, **dict(cfg.options)
    )
    fresh, _ = march_start(stepper, system, carry.Q, carry.xi, carry.P, dt, check_inputs=True)
    probe = half_steps(stepper, system, fresh.state, fresh.memory, fresh.alive, dt, jnp.where(first, 2, 0))
    step0 = jnp.where(jumped & (jump_step == 0), Status.ENERGY_JUMP, sol.stats.status[0])
    return first & first_step_failed(jnp, probe, _node_Q(cfg, sol, carry)[:2], sol.momentum[:2], step0)


def _member_chunk(cfg: Config, params, shared, carry: Carry, dt, first, offset):
    system, xi, gauge = member_system(cfg, params, shared, carry.Q, carry.xi, carry.gauge, first)
    carry = _with_start_P(cfg, system, carry._replace(xi=xi, gauge=gauge), first)
    # A member that failed before starts the chunk failed (a NaN state): a failed step made its
    # state NaN already, a jump found by the energy check did not. (Masking the state handed on
    # by the chunk that found the jump instead, on a value computed in that chunk, makes XLA's
    # program several times slower; `tables.collect` masks the final state of a failed member.)
    alive = carry.status == Status.SUCCESS
    carry = carry._replace(**{k: jnp.where(alive, getattr(carry, k), jnp.nan) for k in ("Q", "xi", "P")})
    march_state, startup = None, 0
    if carry.march is not None and cfg.carry_march:  # continue the last chunk's steps exactly
        march_state, startup = _march_state(cfg, system, carry, dt, first, alive)
    sol = chunk_integrate(cfg, system, carry.Q, carry.xi, carry.P, carry.t, dt, cfg.n, march_state)
    jumped, jump_step, energy_change, energy_size, E = _energy_check(cfg, system, sol, carry)
    spurious = _first_step(cfg, system, carry, dt, first, sol, jumped, jump_step) if cfg.check_energy else False
    # a spurious step 0 fails as a jump there does (integrate checks it after the energy)
    jumped, jump_step = jumped | spurious, jnp.where(spurious, 0, jump_step)
    end = jnp.where(jumped, jump_step, cfg.n)  # a jump fails its step: the nodes after it are unknown
    steps, nodes = jnp.arange(cfg.n), jnp.arange(cfg.n + 1)
    # Nodes whose state is known: before any failure, with the nodal velocity recovered.
    known = sol.valid & (sol.nodal_stats.status == Status.SUCCESS) & (nodes <= end)
    initial, drift = {}, {}
    for name, fn in cfg.invariants:
        # the energy invariant is the energy the check computed (the same function of the nodes)
        v = E if (fn is _diagnostics.energy and E is not None) else jnp.asarray(fn(system, sol))
        ref = jnp.where(first, v[0], carry.initial[name])
        dev = jnp.where(known, _deviation(v, ref), -jnp.inf)
        d = jnp.maximum(carry.drift[name], jnp.max(dev))
        initial[name], drift[name] = ref, jnp.where(jnp.all(jnp.isfinite(ref)), d, jnp.nan)
    result = jnp.where(jumped, jnp.where(spurious, Status.FIRST_STEP, Status.ENERGY_JUMP), sol.result)
    new_failure = (carry.status == Status.SUCCESS) & (result != Status.SUCCESS)
    status = jnp.where(new_failure, result, carry.status).astype(jnp.int32)
    failed_step = jnp.where(
        new_failure, offset + jnp.where(jumped, jump_step, sol.failed_step), carry.failed_step
    ).astype(jnp.int32)
    attempted = (sol.stats.status != Status.SKIPPED) & (steps <= end)
    iterations = carry.iterations + jnp.sum(jnp.where(attempted, sol.stats.iterations, 0)) + startup
    good = (sol.stats.status == Status.SUCCESS) & (steps < end)
    max_residual = jnp.maximum(carry.max_residual, jnp.max(jnp.where(good, sol.stats.residual_norm, 0.0)))
    # The hand-over: the canonical state (Qⁿ, pⁿ) at the chunk's last node.
    start = continue_from(system, sol, Q=carry.Q)
    new = Carry(
        Q=start.Q0,
        P=start.P0,
        xi=start.xi0,
        t=start.t0,
        status=status,
        failed_step=failed_step,
        iterations=iterations,
        max_residual=max_residual,
        initial=initial,
        drift=drift,
        momentum=sol.momentum[-1],
        final_xi=None if sol.xi is None else sol.xi[-1],
        energy_change=energy_change,
        energy_size=energy_size,
        march=carry.march if march_state is None else sol.march_state,
        march_ok=None if carry.march is None else jnp.asarray(march_state is not None),
        gauge=carry.gauge,
    )
    saved = None
    if cfg.save_every is not None:
        pick = slice(0, cfg.n, cfg.save_every)  # nodes 0, k, … of the chunk; its end is the next chunk's 0
        # (nodes after an energy jump are made NaN on the host: `tables.collect`)
        saved = {
            "t": sol.ts[pick],
            "Q": None if sol.Q is None else sol.Q[pick],
            "xi": None if sol.xi is None else sol.xi[pick],
            "momentum": sol.momentum[pick],
        }
    return new, saved


def _lean_member_chunk(cfg: Config, params, shared, carry: Carry, dt, first, offset):
    """A member's chunk on the lean path (`clebsch_jax.batching.lean`): the fast method's steps
    with the sweep's reductions in the loop, no records."""
    system, xi, gauge = member_system(cfg, params, shared, carry.Q, carry.xi, carry.gauge, first)
    carry = carry._replace(xi=xi, gauge=gauge)
    stepper = dict(cfg.options)["method"].prepare(system, carry.Q, carry.xi)  # the fast method: `run_fast_chunk`
    # the lean chunk uses P⁰ only for its momentum μ⁰ = δl/δξ(ξ⁰, Q⁰) (Lemma 7): derived directly
    new, _ = lean_chunk(stepper, system, carry, dt, cfg.n, first, derive_momentum=first if cfg.derive_P else False)
    return new, None


def _batched_chunk(cfg: Config, params, carry, dt, shared, first, offset, rows: bool = False):
    """The chunk of every member of a batch: `cj.batch` (in chunks of `member_chunk`), or with
    `rows` the scalarising evaluation (`clebsch_jax.batching.scalarise`, the whole batch)."""

    def one(p, c, d, s, f, o):
        if cfg.lean:
            return _lean_member_chunk(cfg, p, s, c, d, f, o)
        return _member_chunk(cfg, p, s, c, d, f, o)

    axes = (0, 0, 0, None, None, None)
    # a sweep is never differentiated: its solves are traced without their derivative rules
    # (`undifferentiated`: `integrate`'s programs are keyed by it, so this is safe for them)
    if rows:  # the lean chunk's start and end compute on small values only (one node each)
        run = scalarise(one, in_axes=axes, loops_only=not cfg.lean)
    else:
        run = batch(one, in_axes=axes, chunk=cfg.member_chunk, backend="xla")  # the sweep chose XLA
    with undifferentiated():
        return run(params, carry, dt, shared, first, offset)


@functools.partial(jit_with_options, compiler_options=QUICK_COMPILE, static_argnums=0)
def run_chunk(cfg: Config, params, carry, dt, shared, first, offset):
    """One chunk of a batch by the general path: (carry, saved)."""
    return _batched_chunk(
        dataclasses.replace(cfg, fast_method=None, lean=False), params, carry, dt, shared, first, offset
    )


def run_fast_chunk(cfg: Config, params, carry, dt, shared, first, offset):
    """One chunk of a batch by the fast path (`clebsch_jax.batching.fast`; the lean chunk,
    `clebsch_jax.batching.lean`, where `cfg.lean`): (carry, saved, ok), `ok` (B,) False for a
    member that was alive and failed in it — the caller then runs that member's chunk again
    from the same carry with `run_chunk` (`schedule._rerun`), which reports the failure. A separate
    program, so that the general one is compiled only for a sweep that needs it; the lean
    chunk's is compiled with `LEAN_COMPILE`."""
    return (_lean_program if cfg.lean else _fast_program)(cfg, params, carry, dt, shared, first, offset)


def _fast_chunk(cfg: Config, params, carry, dt, shared, first, offset):
    general = dataclasses.replace(cfg, fast_method=None)
    fast = dataclasses.replace(
        general, options=(("check_energy", False), ("method", cfg.fast_method)), carry_march=False
    )
    new, saved = _batched_chunk(fast, params, carry, dt, shared, first, offset, rows=True)
    ok = (new.status == Status.SUCCESS) | (carry.status != Status.SUCCESS)
    return new, saved, ok


_fast_program = jax.jit(_fast_chunk, static_argnums=0)
_lean_program = jit_with_options(_fast_chunk, LEAN_COMPILE, static_argnums=0)
