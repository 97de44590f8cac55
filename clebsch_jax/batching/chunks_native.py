r"""A chunk of a batch as one call of a native kernel (`clebsch_jax.native`).

The per-member program (`clebsch_jax.batching.member`) of a sweep's configuration, compiled
once per process (`native_program`, from the disk cache when another process compiled it),
and called on a batch's host arrays (`native_call`), with the sweep's carry converted to the
program's and back. The chunk's number of steps is an argument of the kernel, not part of
its program: one kernel serves every chunk length and every `n_steps`.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import numpy as np

from ..core.jit import memo, undifferentiated
from ..march.arguments import prepared_method
from .backends import NativeProgram
from .config import Carry, Config, member_system
from .member import MemberCarry, member_chunk
from .probe import trace_key


def _native_member(cfg: Config, params, shared, carry: MemberCarry, dt, first, offset, n) -> MemberCarry:
    """One member's chunk of `n` steps (an int32 of the program) as the per-member program
    (`clebsch_jax.batching.member`): the method `integrate` chooses for it, its solves to their
    own stopping rule, the reductions in the loop."""
    system, xi, gauge = member_system(cfg, params, shared, carry.Q, carry.xi, carry.gauge, first)
    carry = carry._replace(xi=xi, gauge=gauge)
    # the method does not depend on the number of steps (`integrate` checks it, and the memory
    # of a stored trajectory, which this program does not keep): one step stands for any
    stepper, _, _ = prepared_method(
        system, carry.Q, carry.xi, dt=dt, n_steps=1, P0=carry.P, t0=carry.t, **dict(cfg.options)
    )
    return member_chunk(
        stepper, system, carry, dt, n, first, offset, check_energy=cfg.check_energy, derive_P=cfg.derive_P
    )


def as_member(carry: Carry) -> MemberCarry:
    """The sweep's carry (energy the only invariant) as the per-member program's, on the host."""
    h = lambda a: np.asarray(a)
    return MemberCarry(
        Q=h(carry.Q),
        P=h(carry.P),
        xi=h(carry.xi),
        t=h(carry.t),
        status=h(carry.status),
        failed_step=h(carry.failed_step),
        iterations=h(carry.iterations),
        max_residual=h(carry.max_residual),
        energy0=h(carry.initial["energy"]),
        drift=h(carry.drift["energy"]),
        momentum=h(carry.momentum),
        energy_change=h(carry.energy_change),
        energy_size=h(carry.energy_size),
        march=None if carry.march is None else jax.tree_util.tree_map(h, carry.march),
        gauge=None if carry.gauge is None else h(carry.gauge),
    )


def _from_member(m: MemberCarry, has_xi: bool) -> Carry:
    return Carry(
        Q=m.Q,
        P=m.P,
        xi=m.xi,
        t=m.t,
        status=m.status,
        failed_step=m.failed_step,
        iterations=m.iterations,
        max_residual=m.max_residual,
        initial={"energy": m.energy0},
        drift={"energy": m.drift},
        momentum=m.momentum,
        final_xi=m.xi if has_xi else None,
        energy_change=m.energy_change,
        energy_size=m.energy_size,
        march=m.march,
        gauge=m.gauge,
    )


_NATIVE_AXES = (0, None, 0, 0, None, None, None)


def native_program(cfg: Config, params, shared, carry: MemberCarry, dt):
    """The native kernel of `_native_member` for this configuration and these shapes (compiled
    once per process; from the disk cache when another process compiled it), for every chunk
    length (`cfg.n` is not read: the kernel's last argument)."""
    cfg = any_length(cfg)
    row = lambda tree: jax.tree_util.tree_map(lambda a: np.asarray(a)[0], tree)
    args = (
        row(params),
        None if shared is None else [np.asarray(x) for x in shared],
        row(carry),
        row(dt),
        np.asarray(True),
        np.asarray(0, np.int32),
        np.asarray(1, np.int32),
    )
    fun = functools.partial(_native_member, cfg)

    def traced(*a):
        with undifferentiated():  # a sweep is never differentiated: no derivative rules traced
            return fun(*a)

    key = ("sweep", trace_key(cfg, args))
    return NativeProgram.get(key, traced, args, _NATIVE_AXES, cfg.native_max_lines, disk_key=_disk_key(cfg))


def any_length(cfg: Config) -> Config:
    """`cfg` without its chunk length: what the native kernel of a chunk is made from."""
    return dataclasses.replace(cfg, n=0)


_DISK_KEYS: dict = {}


def _disk_key(cfg: Config) -> str | None:
    """The fingerprint of the per-member program of `cfg` (`clebsch_jax.native.fingerprint`):
    `make_system`, the options, the energy check (not the steps of a chunk: `any_length`); None
    where it cannot be read (the kernel is then found by its jaxpr, traced). Kept per
    configuration in a process."""
    from ..native.fingerprint import fingerprint

    return memo(_DISK_KEYS, cfg, lambda: fingerprint(("sweep-member", cfg)), 64)


def native_program_of(c: Config, one):
    """`native_program` of a batch (`schedule.Batch`) for the chunk configuration `c`: the same
    for every batch and chunk of a run with `c` (their members' shapes are the same)."""
    return native_program(c, one.params, one.shared, as_member(one.carry), one.dt)


def native_call(c: Config, one, st: int, workspace=None, program=None) -> Carry:
    """One chunk of `c.n` steps of a batch (`schedule.Batch`) by its native kernel: the batch's
    carry after it (host arrays; with a `workspace` of the calling thread,
    `clebsch_jax.native.layout`, views of its rows, valid until its second call after this
    one). `program`: `native_program_of(c, one)`, found before (else looked up)."""
    carry = as_member(one.carry)
    if program is None:
        program = native_program(c, one.params, one.shared, carry, one.dt)
    shared = None if one.shared is None else [np.asarray(x) for x in one.shared]
    params = jax.tree_util.tree_map(np.asarray, one.params)
    new = program(
        params,
        shared,
        carry,
        np.asarray(one.dt),
        np.asarray(st == 0),
        np.asarray(st, np.int32),
        np.asarray(c.n, np.int32),
        workspace=workspace,
    )
    return _from_member(new, one.carry.final_xi is not None)
