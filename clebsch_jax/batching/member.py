r"""The per-member program of a sweep: one member's chunk of steps with its reductions in the loop.

A sweep keeps per-member reductions, not trajectories. `member_chunk` makes `n` steps of one
member from the sweep's carry with the stepper `integrate` chooses — its solves iterate to
their own stopping rule, as in `integrate` — and at each new node, in the same loop body:

- the nodal velocity (Lemma 7: $\delta l/\delta\xi(\xi, Q) = \mu$), solved by the stepper's
  nodal solver from the velocity of the step arriving at the node;
- the energy $E = \langle\delta l/\delta\xi, \xi\rangle - l$, its drift from the run's first
  node, and `integrate`'s energy check (`clebsch_jax.march.energy_check.jump_step`);
- the member's status: the status and step of its first failure (a step's solve, a node's
  velocity, an energy jump, an invalid input), after which its values are NaN.

Nothing is stored per step, so the program of a chunk is one loop whose body is a step: its
size does not grow with the chunk's length. It is the program both batch backends evaluate
(`clebsch_jax.batching.backends`): XLA under `jax.vmap`, or the native kernel
(`clebsch_jax.native`) with members in SIMD lanes. Its statuses and reductions are those of
`integrate` over the same steps (the sweep's tests compare them): the only differences are
round-off, from the nodal solves' seeds and the hand-over between chunks.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ..core.system import momentum_map
from ..discrete.legendre import cotangent_from_momentum, explicit_nodal_velocity, initial_multiplier
from ..discrete.residual import nodal_residual
from ..march.carry import input_ok
from ..march.energy_check import energy_rtol, jump_step, node_energy, zero_nan
from ..march.first_step import FirstStepProbe, first_step_failed
from ..roots.status import Status
from ..steppers.base import innermost
from ..steppers.reduced import ReducedStep

__all__ = ["MemberCarry", "march_start_values", "member_chunk"]


class MemberCarry(NamedTuple):
    """What a member hands from one chunk to the next (and, at the end, the sweep's table)."""

    Q: jax.Array
    P: jax.Array
    xi: jax.Array
    t: jax.Array
    status: jax.Array  # int32: the first failure's status (Status.SUCCESS while none)
    failed_step: jax.Array  # int32: its step (-1 while none)
    iterations: jax.Array  # int64: Newton iterations of the steps made
    max_residual: jax.Array
    energy0: jax.Array  # the energy at the run's first node
    drift: jax.Array  # max |E - E⁰| over the nodes made
    momentum: jax.Array  # the momentum map at the last node
    energy_change: jax.Array  # the energy check's running maxima (`clebsch_jax.march.energy_check.jump_step`)
    energy_size: jax.Array
    # (stepper state, memory, steps made) at the last node: the next chunk continues from it,
    # with the stepper's guesses and predictor history, the steps of one unbroken run
    # (`march_start_values`); None: every chunk starts the stepper afresh
    march: tuple | None = None
    gauge: jax.Array | None = None  # the weight of the member's isotropy gauge (`config.Carry.gauge`)


def march_start_values(stepper, system, Q0, xi0, P0, dt) -> tuple:
    """`MemberCarry.march` at the start of a run: (the stepper's initial state, its memory, 0)."""
    state, _ = stepper.init(system, Q0, xi0, P0, dt)
    return state, stepper.init_memory(system, state), jnp.zeros((), jnp.int32)


def _one(tree):
    return jax.tree_util.tree_map(lambda a: a[None], tree)


def _nan_unless(ok, tree):
    return jax.tree_util.tree_map(
        lambda a: jnp.where(ok, a, jnp.nan) if jnp.issubdtype(a.dtype, jnp.inexact) else a, tree
    )


def _nan_unless_made(ok, new, old):
    """`_nan_unless(ok, new)` for a state `new` that a step made from `old`, except the leaves
    it handed on unchanged (the very values of `old`: the reduced step's identity Q where it
    does not carry Q): the step computed nothing there to discard, and a select would make
    such a leaf a value of the loop's carry, a register or a spill slot in every step."""
    return jax.tree_util.tree_map(lambda a, b: a if a is b else _nan_unless(ok, a), new, old)


def _where(cond, a, b):
    """`jnp.where(cond, a, b)` leaf by leaf over two pytrees of one structure."""
    return jax.tree_util.tree_map(lambda x, y: jnp.where(cond, x, y), a, b)


def _node(system, finder, Q, mu, seed, ok):
    """A node's velocity, whether it is known, its energy and the energy's size: the velocity
    solved from Lemma 7's relation from `seed` (NaN where not `ok`), or evaluated by the
    system's inverse Legendre map (Lemma 8) when it gives one, as `integrate` does; for a
    degenerate system the seed itself, and the energy read at ξ = 0
    (`clebsch_jax.diagnostics.energy`)."""
    if system.degenerate:
        E, size = node_energy(system, Q, jnp.zeros_like(seed))
        return seed, ok, E, size
    if system.inverse_legendre is not None:
        xi, st = explicit_nodal_velocity(system, Q, jnp.where(ok, mu, jnp.nan))
    else:
        xi, st = finder.solve(lambda x: nodal_residual(system, Q, mu, x), jnp.where(ok, seed, jnp.nan))
    known = ok & (st.status == Status.SUCCESS)
    # the energy of the velocity as found, made NaN with it where it is not known (what the
    # energy of the NaN velocity is): its terms then share the check's evaluation of δl/δξ
    E, size = node_energy(system, Q, xi)
    unknown = lambda a: jnp.where(known, a, jnp.nan)
    return unknown(xi), known, unknown(E), unknown(size)


def _phases(stepper, system, reduce, dt, n, probes, steps0, state0, memory0, red0):
    """The chunk's loop with `integrate`'s first-step probe (`probes`: 2 in the run's first
    chunk, else 0): three phases of one loop over the step (`reduce` of `stepper.step`), the
    program's single copy of it — the probe's half steps from the start (their last node is the
    probe), step 0 from the start again (its node and outcome kept for the first-step check),
    then steps 1 … n - 1. A phase's time step, step numbers and start are set between phases,
    so that a step carries no select of them: every member runs the same phases (`first` is
    the batch's), so that the inner loop is the same in every lane of a native kernel.

    Returns (state, memory, reductions, the probe's `FirstStepProbe`, step 0's {Q, mu, ok,
    iterations}); a half step's reductions are dropped, as are those of a phase of no steps."""
    nan = lambda a: jnp.full_like(a, jnp.nan)  # noqa: E731
    Q0, mu0, alive0 = red0["Q"], red0["mu"], red0["alive"]
    counts = jnp.stack([probes, jnp.minimum(n, 1), jnp.maximum(n - 1, 0)]).astype(jnp.int32)

    def steps(c):
        """The phase's steps: each from the last (the first from c's state) with the phase's
        `dt`, numbers `index0 + i` (stepper) and `k0 + i` (reductions); `alive` the last
        step's outcome, its node's in the probe."""
        phase, state, memory, red, node, alive = c[:6]
        in_probe = phase == 0
        step_dt = jnp.where(in_probe, dt / 2, dt)
        index0 = jnp.where(in_probe, 0, steps0 + phase - 1).astype(jnp.int32)
        k0 = (phase - 1).astype(jnp.int32)

        def one(i, s):
            state_prev, memory, red, _, alive = s
            stepped = stepper.step(system, state_prev, memory, step_dt, index0 + i, alive)
            state, memory, red, node = reduce(k0 + i, state_prev, red, alive, stepped)
            return state, memory, red, node, jnp.where(in_probe, node[2], red["alive"])

        return jax.lax.fori_loop(0, counts[phase], one, (state, memory, red, node, alive))

    def phase_body(c):
        phase, _, _, _, _, _, probe, at0 = c
        # the probe's half steps and step 0 start from the chunk's start, the reductions from red0
        restart = phase < 2
        start = jax.tree_util.tree_map(lambda a, b: jnp.where(restart, a, b), (state0, memory0, red0), c[1:4])
        alive = jnp.where(phase == 0, probe[2], jnp.where(restart, alive0, c[5]))
        state, memory, red, node, alive = steps((phase,) + start + (c[4], alive))
        probe = _where(phase == 0, node, probe)
        step0 = dict(Q=node[0], mu=node[1], ok=node[2] & ~red["jumped"], iterations=red["iterations"])
        at0 = _where((phase == 1) & (counts[1] > 0), step0, at0)
        return phase + 1, state, memory, red, node, alive, probe, at0

    probe0 = (nan(Q0), nan(mu0), jnp.asarray(alive0))
    at00 = dict(Q=nan(Q0), mu=nan(mu0), ok=jnp.asarray(False), iterations=red0["iterations"])
    start = (jnp.zeros((), jnp.int32), state0, memory0, red0, probe0, alive0, probe0, at00)
    _, state, memory, red, _, _, probe, at0 = jax.lax.while_loop(lambda c: c[0] < 3, phase_body, start)
    return state, memory, red, FirstStepProbe(probe[0], probe[1], probe[2] & (probes > 0)), at0


def member_chunk(
    stepper,
    system,
    carry: MemberCarry,
    dt,
    n,
    first,
    offset,
    *,
    check_energy: bool | float = True,
    derive_P: bool = False,
) -> MemberCarry:
    r"""`n` steps of one member from `carry`, with the sweep's reductions made in the loop.

    **Arguments:** `stepper`, prepared for `system` (`integrate`'s choice: `prepared_method`);
    `carry` the member's `MemberCarry`; `dt`; `n` the chunk's steps (static, or an int32
    scalar ≥ 1 of the program: one program for every chunk length); `first` (bool)
    whether this is the run's first chunk; `offset` (int) the run's step number of the chunk's
    first step; `check_energy` `integrate`'s energy check (True, False or its tolerance); `derive_P` whether the carry's P is
    a placeholder to be replaced, in the first chunk, by the minimum-norm multiplier of
    $(Q^0, \xi^0)$ (Lemma 7, `initial_multiplier`).

    **Returns:** the carry after the chunk. A member that had failed before keeps its status
    and step; one that fails in the chunk gets the status and the run's step of its first
    failure, and NaN state."""
    alive0 = carry.status == Status.SUCCESS
    Q0, xi0 = jnp.where(alive0, carry.Q, jnp.nan), jnp.where(alive0, carry.xi, jnp.nan)
    P0 = carry.P
    if derive_P:
        P0 = jnp.where(first, initial_multiplier(system, Q0, xi0), P0)
    P0 = jnp.where(alive0, P0, jnp.nan)
    degenerate = system.degenerate
    rtol = energy_rtol(check_energy)
    energy_on = rtol is not None and not degenerate  # as integrate: no energy check without nodal velocities
    ok_in = input_ok(system, Q0, xi0, P0, dt)

    def fresh():
        state, startup = stepper.init(system, Q0, xi0, P0, dt)
        memory = stepper.init_memory(system, state)
        return (state, memory, jnp.zeros((), jnp.int32)), jnp.asarray(startup, carry.iterations.dtype)

    if carry.march is None:
        (state0, memory0, steps0), startup = fresh()
    else:  # the run's first chunk starts the stepper; a later one continues the last one's march
        carried = lambda: (carry.march, jnp.zeros((), carry.iterations.dtype))
        (state0, memory0, steps0), startup = jax.lax.cond(first, fresh, carried)
    # integrate's first-step check (`clebsch_jax.march.first_step.first_step_probe`): two half steps
    # from the start, in the run's first chunk only. They are the loop's first two iterations
    # (`probes` of them: 2 or 0), made by the loop's own step, so that the program holds one
    # copy of the step (a second would double the native kernel, and its compile time)
    probes = jnp.where(first, 2, 0).astype(jnp.int32) if check_energy else None
    mu0 = momentum_map(system, P0, Q0, xi0)
    finder = stepper.nodal_solver
    xin0, ok0, E0, size0 = _node(system, finder, Q0, mu0, xi0, ok_in)
    ref = jnp.where(first, E0, carry.energy0)
    # the status of the chunk's start: an invalid input fails step 0, a node 0 whose velocity
    # is not recovered is a LEGENDRE failure at step 0
    status0 = jnp.where(ok_in, jnp.where(ok0, Status.SUCCESS, Status.LEGENDRE), Status.INVALID_INPUT)
    status0 = status0.astype(jnp.int32)
    int_dtype = carry.iterations.dtype
    size_max0 = jnp.maximum(carry.energy_size, zero_nan(size0)) if energy_on else carry.energy_size
    red0 = dict(
        alive=ok_in,
        status=status0,
        step=jnp.where(ok_in & ok0, -1, 0).astype(jnp.int32),
        iterations=jnp.where(ok_in, jnp.asarray(startup, int_dtype), 0),
        residual=jnp.zeros((), dt.dtype),
        change=carry.energy_change,
        size=size_max0 if energy_on else carry.energy_size,
        E=E0,
        drift=jnp.where(ok0, jnp.abs(E0 - ref), 0.0),
        Q=Q0,
        mu=mu0,
        xin=xin0,
        xstep=xi0,
        jumped=jnp.asarray(False),
        p=jnp.full_like(Q0, jnp.nan),
    )

    def reduce(k, state_prev, red, alive, stepped):
        """Step k of the chunk (`stepped`: the stepper's step from `state_prev`) and the
        reductions after it: (the state, the memory, the new reductions, and the node the step
        reaches with its outcome: (Q, momentum, ok))."""
        state, memory, out, stats = stepped
        ok = alive & (stats.status == Status.SUCCESS)
        state, out = _nan_unless_made(ok, state, state_prev), _nan_unless(ok, out)
        nodes = stepper.nodes(system, state_prev, _one(state), _one(out))
        Qn = nodes.nodal_Q[1]
        mun, xi_step = nodes.momentum[1], nodes.xi_step[0]
        xin, nodal_ok, E, size = _node(system, finder, Qn, mun, xi_step, ok)
        counted = alive & ~red["jumped"]  # the steps up to the first failure or jump
        iterations = red["iterations"] + jnp.where(counted, stats.iterations, 0).astype(int_dtype)
        if energy_on:
            # the step leaves the node whose size red["size"] already holds (`jump_step`)
            change, size_max, jump = jump_step(red["change"], red["size"], jnp.abs(E - red["E"]), rtol=rtol)
            size_max = jnp.maximum(size_max, zero_nan(size))
            # checked up to the first failed step, as integrate does: a node's failure does not stop it
            jumped = red["jumped"] | (jump & ok)
            new_jump = jumped & ~red["jumped"]
        else:
            change, size_max, jumped, new_jump = red["change"], red["size"], red["jumped"], jnp.asarray(False)
        still = red["status"] == Status.SUCCESS
        step_failed = alive & ~ok
        code = jnp.where(
            new_jump,
            Status.ENERGY_JUMP,
            jnp.where(step_failed, stats.status, jnp.where(ok & ~nodal_ok, Status.LEGENDRE, Status.SUCCESS)),
        )
        # a step's failure or a jump outranks an earlier node's (LEGENDRE), as integrate ranks them
        fails = (still & (code != Status.SUCCESS)) | ((red["status"] == Status.LEGENDRE) & (step_failed | new_jump))
        status = jnp.where(fails, code, red["status"]).astype(jnp.int32)
        # a step's failure is reported at the step, a node's at the node (k + 1: the one step k reaches)
        step = jnp.where(fails, jnp.where(code == Status.LEGENDRE, k + 1, k), red["step"]).astype(jnp.int32)
        good = ok & ~jumped
        residual = jnp.maximum(red["residual"], jnp.where(good, stats.residual_norm, 0.0))
        known = good & nodal_ok
        drift = jnp.maximum(red["drift"], jnp.where(known, jnp.abs(E - ref), 0.0))
        # the state handed on, as found: each step overwrites it, and it is made NaN after the
        # loop where the last step did not keep it (a failure or a jump: `alive` is then False)
        Qh = nodes.Q[1] if nodes.Q is not None else red["Q"]
        p = nodes.p[1] if nodes.p is not None else red["p"]
        red = dict(
            alive=ok & ~jumped,
            status=status,
            step=step,
            iterations=iterations,
            residual=residual,
            change=change,
            size=size_max,
            E=E,
            drift=drift,
            Q=Qh,
            mu=mun,
            xin=xin,
            xstep=xi_step,
            jumped=jumped,
            p=p,
        )
        return state, memory, red, (Qn, mun, ok)

    def body(k, c):
        state_prev, memory, red = c
        alive = red["alive"]
        stepped = stepper.step(system, state_prev, memory, dt, steps0 + k, alive)
        state, memory, red, _ = reduce(k, state_prev, red, alive, stepped)
        return state, memory, red

    if probes is None:
        state, memory, red = jax.lax.fori_loop(0, n, body, (state0, memory0, red0))
    else:
        state, memory, red, probe, at0 = _phases(stepper, system, reduce, dt, n, probes, steps0, state0, memory0, red0)
    made = not isinstance(n, int) or n > 0  # a chunk of steps (a traced n is at least 1)
    if probes is not None and made:
        # integrate's first-step check (after its energy check): step 0 converged, was not failed
        # by the energy check, and lies far from the half steps' node. It fails the member at
        # step 0 as a jump there would: what the loop reduced after step 0 is dropped. (Made
        # here, on the node recorded at step 0, rather than in every step of the loop.)
        nodes0 = (jnp.stack([red0["Q"], at0["Q"]]), jnp.stack([mu0, at0["mu"]]))
        spurious = first & at0["ok"] & first_step_failed(jnp, probe, *nodes0, Status.SUCCESS)
        red.update(
            status=jnp.where(spurious, Status.FIRST_STEP, red["status"]).astype(jnp.int32),
            step=jnp.where(spurious, 0, red["step"]).astype(jnp.int32),
            iterations=jnp.where(spurious, at0["iterations"], red["iterations"]),
            residual=jnp.where(spurious, red0["residual"], red["residual"]),
            drift=jnp.where(spurious, red0["drift"], red["drift"]),
            alive=red["alive"] & ~spurious,
        )
    if made:  # the state the last step kept (`alive`: no failure or jump up to it), else NaN
        red.update(_nan_unless(red["alive"], {k: red[k] for k in ("Q", "mu", "xin", "p")}))
    Qn, mun = red["Q"], red["mu"]
    # the reduced march carries μ, not p: the minimum-norm cotangent with that momentum map
    # (as `continue_from` hands it over)
    reduced = isinstance(innermost(stepper), ReducedStep)
    Pn = cotangent_from_momentum(system, Qn, mun, unroll=True) if reduced else red["p"]
    xin = red["xstep"] if degenerate else red["xin"]
    newly = alive0 & (red["status"] != Status.SUCCESS)
    status = jnp.where(newly, red["status"], carry.status).astype(jnp.int32)
    failed_step = jnp.where(newly, offset + red["step"], carry.failed_step).astype(jnp.int32)
    drift = jnp.where(jnp.isfinite(ref), jnp.maximum(carry.drift, red["drift"]), jnp.nan)
    return MemberCarry(
        Q=jnp.where(alive0, Qn, jnp.nan),
        P=jnp.where(alive0, Pn, jnp.nan),
        xi=jnp.where(alive0, xin, jnp.nan),
        t=carry.t + dt * jnp.asarray(n, dt.dtype),
        status=status,
        failed_step=failed_step,
        iterations=carry.iterations + jnp.where(alive0, red["iterations"], 0),
        max_residual=jnp.maximum(carry.max_residual, red["residual"]),
        energy0=ref,
        drift=drift,
        momentum=jnp.where(alive0, mun, jnp.nan),
        energy_change=red["change"],
        energy_size=red["size"],
        march=None if carry.march is None else (state, memory, steps0 + n),
        gauge=carry.gauge,
    )
