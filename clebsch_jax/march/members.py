"""Several trajectories marched together with one stepper, as an accuracy plan's pilot marches
its members (`clebsch_jax.march.accuracy.plan_members`): `MemberMarch`.

Each member's `Solution` is the one `integrate(system, Q0, xi0, P0=P0, t0=t0, dt=dt,
n_steps=n_steps, method=stepper, throw=False, check_energy=..., backend=...)` returns, value for
value: the same checks of the arguments (made once per member and stepper: they do not depend
on the step), the same start, first-step probe, steps and nodes, the same assembly and check
of the first step on the manifold. Where every member runs the same native loop kernel
(`clebsch_jax.march.native_chunk`: the stepper, the system's structure and the shapes alike),
that kernel is compiled with the host's lanes and the members are marched in its lanes by one
call per chunk, instead of a call per member with its host work around it. A lane makes the
operations a one-lane kernel makes, in the same order (a masked loop keeps a finished lane's
carry, as a one-lane loop stops), so each member's numbers are those of its own call, to the
bit (`tests/test_member_march.py`). Elsewhere (XLA's chunk, members of different structures)
each member is marched by `integrate`.
"""

from __future__ import annotations

import jax
import numpy as np

from ..core.manifold_checks import check_first_step
from ..core.validation import positive_scalar
from ..roots.status import Status
from .arguments import prepare, warn_if_remade
from .assemble import assemble
from .energy_check import energy_rtol
from .first_step import FirstStepProbe
from .native_chunk import member_chunks, native_chunk_program, run_members
from .scan import NATIVE_CHUNK_FACTOR, chunk_length, start_program

__all__ = ["MemberMarch"]


class MemberMarch:
    """`march(stepper, dt, n_steps)` → one `Solution` per member (module docstring), for
    `members`, a sequence of (system, Q0, xi0, P0) with concrete values, all from `t0`."""

    def __init__(self, members, t0, check_energy, backend: str):
        self.members, self.t0, self.check_energy, self.backend = list(members), t0, check_energy, backend
        self._ready: dict = {}  # stepper → its members' prepared arguments and the kernel they share

    def __call__(self, stepper, dt, n_steps: int) -> list:
        from .integrate import integrate  # integrate imports the plan, which imports this module

        ready = self._prepared(stepper, dt, n_steps)
        if ready is None:  # XLA's chunk, or members of different programs: each by its own call
            return [
                integrate(
                    system, Q0, xi0, P0=P0, t0=self.t0, dt=dt, n_steps=n_steps, method=stepper, throw=False,
                    check_energy=self.check_energy, backend=self.backend,
                )
                for system, Q0, xi0, P0 in self.members
            ]  # fmt: skip
        return self._march(ready, dt, n_steps)

    def _prepared(self, stepper, dt, n_steps):
        """The members' `prepare`d arguments for `stepper` (`integrate`'s checks, which do not
        depend on the step: made at the stepper's first call), their kernel and its system arrays
        stacked, or None where they do not share a native kernel."""
        if stepper not in self._ready:
            found = []
            for system, Q0, xi0, P0 in self.members:
                warn_if_remade(system)
                method, (Q0, xi0, P0, _, t0, closes), _, system = prepare(
                    system, Q0, xi0, dt=dt, n_steps=n_steps, P0=P0, t0=self.t0, method=stepper,
                    check_energy=self.check_energy,
                )  # fmt: skip
                found.append((method, system, Q0, xi0, P0, t0, closes))
            self._ready[stepper] = self._shared_kernel(found, positive_scalar(dt, "dt"))
        return self._ready[stepper]

    def _shared_kernel(self, found, dt):
        """(prepared members, kernel, stacked system arrays) when every member runs one native
        loop kernel (`native_chunk_program` with the host's lanes: the same compiled object),
        else None."""
        from ..native import native_unavailable
        from ..native.kernel import host_lanes

        if self.backend == "xla" or any(closes for *_, closes in found):
            return None
        # the members in the lanes of the host's vectors (one member: one lane, integrate's kernel)
        width = 1 if len(found) == 1 or native_unavailable() is not None else host_lanes()
        bounds = []
        for method, system, Q0, xi0, P0, _, _ in found:
            carry = start_program(method)(method, system, Q0, xi0, P0, dt)[0]
            check = energy_rtol(self.check_energy) is not None
            native = native_chunk_program(method, system, carry, dt, check, self.backend, width)
            if native is None or (bounds and native.bound.kernel is not bounds[0].kernel):
                return None
            bounds.append(native.bound)
        system_arrays = [np.stack(leaf) for leaf in zip(*(b.arrays[:-1] for b in bounds))]
        return found, bounds[0].kernel, system_arrays

    def _march(self, ready, dt, n_steps: int) -> list:
        """`march_chunked`'s native march of every member, each kernel call for all of them."""
        found, kernel, system_arrays = ready
        dt, rtol = positive_scalar(dt, "dt"), energy_rtol(self.check_energy)
        starts = [start_program(m)(m, s, Q0, xi0, P0, dt) for m, s, Q0, xi0, P0, *_ in found]
        carry = jax.tree_util.tree_map(lambda *a: np.stack([np.asarray(x) for x in a]), *[c for c, _ in starts])
        per_member = lambda a: np.stack([a] * len(found))
        probes = [None] * len(found)
        if rtol is not None:  # the first-step check: two steps of dt/2 from the start (`first_step_probe`)
            half = np.asarray(np.asarray(dt) / 2)
            rec = run_members(kernel, [*system_arrays, per_member(half)], carry, 2)[1]
            for m, chunk in enumerate(member_chunks(rec, 2)):
                ok = np.all(np.asarray(chunk.stats.status)[:2] == Status.SUCCESS)
                probes[m] = FirstStepProbe(chunk.nodes.nodal_Q[2], chunk.nodes.momentum[2], ok)
        arrays = [*system_arrays, per_member(np.asarray(dt))]
        length = chunk_length(*found[0][2:4]) * NATIVE_CHUNK_FACTOR
        chunks = [[] for _ in found]
        for _ in range(-(-n_steps // length)):
            made = int(np.clip(n_steps - int(carry.n[0]), 0, length))
            carry, rec = run_members(kernel, arrays, carry, made)
            for own, chunk in zip(chunks, member_chunks(rec, made)):
                own.append(chunk)
        sols = []
        for (method, system, Q0, xi0, _, t0, _), (_, startup), own, probe in zip(found, starts, chunks, probes):
            sol = assemble(
                np, method, system, own, n_steps, np.asarray(startup), np.asarray(dt), np.asarray(t0), Q0, xi0,
                probe=probe, energy_rtol=rtol,
            )  # fmt: skip
            if sol.Q is not None:
                check_first_step(system, sol.method, Q0, xi0, np.asarray(sol.Q)[1])
            sols.append(sol)
        return sols
