"""The backends that evaluate a batch of per-member programs: XLA or native machine code.

A batch runs one program per member (`clebsch_jax.batching.member`). Two evaluators of that
one program stand behind `backend=`:

- `"xla"`: `jax.vmap` of the program, compiled by XLA — for every device and every program,
  and under JAX transformations;
- `"native"`: the program's jaxpr compiled by `clebsch_jax.native` with members in the SIMD
  lanes of the host CPU — for concrete calls on the CPU, where XLA's CPU runtime charges
  microseconds per operation of a loop of small operations.

`"auto"` (the default) takes the native backend wherever it applies (`native_unavailable`
says why not) and XLA elsewhere, saying once why.
"""

from __future__ import annotations

import threading

from ..native import (
    BACKENDS,
    NativeFallbackWarning,
    check_backend,
    native_unavailable,
    warn_once,
)

__all__ = ["BACKENDS", "check_backend", "native_unavailable", "warn_once", "NativeProgram", "NativeFallbackWarning"]

_PROGRAMS: dict = {}
_PROGRAMS_LOCK = threading.Lock()
_PROGRAMS_MAX = 32


class NativeProgram:
    """A per-member function compiled once per key (`get`), called on host arrays."""

    @staticmethod
    def get(key, fun, member_args, in_axes, max_lines=None, disk_key=None):
        """The compiled program of `fun` for `key` (compiled on first use, then kept; a
        `clebsch_jax.native.Unsupported` is raised, and remembered, for a program the
        translation does not cover, or, with `max_lines`, whose kernel would be larger;
        `key` must tell those limits apart). `disk_key`: a fingerprint of what `fun` is made
        from, under which a new process finds the kernel without tracing `fun`
        (`clebsch_jax.native.NativeFunction`)."""
        from ..native import compile_member, compiled_once

        return compiled_once(
            _PROGRAMS,
            _PROGRAMS_LOCK,
            _PROGRAMS_MAX,
            key,
            lambda: compile_member(fun, *member_args, in_axes=in_axes, max_lines=max_lines, key=disk_key),
        )
