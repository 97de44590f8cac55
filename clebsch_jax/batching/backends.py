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
import warnings

__all__ = ["BACKENDS", "check_backend", "native_unavailable", "warn_once", "NativeProgram", "NativeFallbackWarning"]

BACKENDS = ("auto", "native", "xla")


class NativeFallbackWarning(UserWarning):
    """`backend="auto"` ran XLA where a native kernel was wanted; the message says why."""


def check_backend(backend) -> str:
    if not (isinstance(backend, str) and backend in BACKENDS):
        raise ValueError(f"backend: expected one of {BACKENDS}, got {backend!r}.")
    return backend


def native_unavailable(devices) -> str | None:
    """Why native kernels cannot run here (None: they can): llvmlite missing, or a device that
    is not the host CPU (the native kernels are for CPUs; an accelerator keeps XLA)."""
    from ..native import available

    if not available():
        return "llvmlite cannot be imported (pip install llvmlite)"
    import jax

    for d in devices:
        device = d if d is not None else jax.devices()[0]
        if getattr(device, "platform", "cpu") != "cpu":
            return f"the device {device} is not the host CPU"
    return None


_WARNED: set = set()
_WARN_LOCK = threading.Lock()


def warn_once(reason: str) -> None:
    """Say once per process and reason that XLA runs where a native kernel was wanted."""
    with _WARN_LOCK:
        if reason in _WARNED:
            return
        _WARNED.add(reason)
    warnings.warn(
        f"clebsch_jax: running the batch with XLA, not a native kernel: {reason}.", NativeFallbackWarning, stacklevel=3
    )


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
        with _PROGRAMS_LOCK:
            found = _PROGRAMS.get(key)
        if found is None:
            from ..native import Unsupported, compile_member

            try:
                found = compile_member(fun, *member_args, in_axes=in_axes, max_lines=max_lines, key=disk_key)
            except Unsupported as err:
                found = err
            with _PROGRAMS_LOCK:
                if len(_PROGRAMS) >= _PROGRAMS_MAX:
                    _PROGRAMS.clear()
                _PROGRAMS[key] = found
        if isinstance(found, Exception):
            raise found
        return found
