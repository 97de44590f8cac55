"""Checks of user input, one of each, shared by `integrate`, `sweep`, `control` and the
steppers: a bad argument is refused before compiling, with a message that names it and says
what was expected. Values are checked only where they are concrete (not traced by `jit` or
`vmap`); under tracing a bad value shows up as a reported failure instead."""

from __future__ import annotations

import numbers
import os

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "is_traced",
    "any_traced",
    "is_array",
    "float_array",
    "host_float_array",
    "positive_int",
    "nonnegative",
    "positive_scalar",
    "output_shape",
    "check_configuration",
    "runnable_check",
    "nan_unless",
    "memory_limit",
    "check_memory",
]


def is_traced(x) -> bool:
    """Whether x is a tracer (its value unknown: inside `jit`, `vmap`, `grad`)."""
    return isinstance(x, jax.core.Tracer)


def any_traced(*trees) -> bool:
    """Whether any array leaf of the pytrees `trees` is a tracer."""
    return any(is_traced(x) for x in jax.tree_util.tree_leaves(trees))


@jax.custom_jvp
def nan_unless(x, ok) -> jax.Array:
    """A traced model parameter `x` made NaN where the traced condition `ok` fails: the value
    check a model makes on concrete parameters, for parameters known only inside jit/vmap.
    The Lagrangian is then NaN at the initial point, and `integrate` reports the member with
    `Status.INVALID_INPUT` at step 0 instead of marching a meaningless model.

    Its derivative is NaN where `ok` fails too (a plain `where` would give the NaN a zero
    derivative): the gradient of a member with invalid input is NaN, never zero, so an optimiser
    sees that its step left the model's domain."""
    return jnp.where(ok, x, jnp.nan)


@nan_unless.defjvp
def _nan_unless_jvp(primals, tangents):
    x, ok = primals
    return nan_unless(x, ok), tangents[0] * jnp.where(ok, 1.0, jnp.nan).astype(jnp.result_type(x))


def is_array(x) -> bool:
    """Whether x is an array (a JAX or NumPy array or scalar), as opposed to static data."""
    return isinstance(x, (jax.Array, np.ndarray, np.generic))


def _real_dtype(dtype, name: str, allow_bool: bool):
    if dtype == np.dtype(object) or not (np.issubdtype(dtype, np.number) or dtype == np.dtype(bool)):
        raise TypeError(f"{name}: expected a real array of numbers, got dtype {dtype}.")
    if np.issubdtype(dtype, np.complexfloating):
        raise TypeError(f"{name}: expected a real floating-point array, got dtype {dtype}.")
    if dtype == np.dtype(bool) and not allow_bool:
        raise TypeError(f"{name}: expected a real array, got dtype {dtype}.")


def float_array(x, name: str, *, allow_bool: bool = True) -> jax.Array:
    """x as a JAX float64 array: refused (naming `name`) if it is not an array of real numbers
    or, when concrete, not finite. Integers (and booleans, if `allow_bool`) become float64, and
    so do floats of lower precision (float32, float16, bfloat16: e.g. arrays made before the
    package enabled float64): the engine computes in float64 only, whose round-off its
    conservation properties and default tolerances assume. A Python float becomes a strongly
    typed array, so that it and a NumPy float compile to one program."""
    return _float_array(x, name, allow_bool)[0]


def _float_array(x, name: str, allow_bool: bool):
    """`float_array`, and its values on the host (None when traced). Concrete input is checked
    and converted with NumPy and moved to the device once: each JAX operation on a small array
    costs a dispatch, which a short call would pay several times per argument."""
    if isinstance(x, (str, bytes)) or x is None:
        raise TypeError(f"{name}: expected an array of numbers, got {type(x).__name__}.")
    f64 = jnp.result_type(float)
    if is_traced(x):
        _real_dtype(np.dtype(x.dtype), name, allow_bool)
        if x.dtype != f64 or getattr(x, "weak_type", False):
            x = jnp.asarray(x, dtype=f64)  # integers, booleans and lower precisions; weak types made strong
        return x, None
    try:
        host = np.asarray(x)
    except (TypeError, ValueError) as err:
        raise TypeError(f"{name}: expected an array of numbers, got {type(x).__name__}.") from err
    _real_dtype(host.dtype, name, allow_bool)
    if isinstance(x, jax.Array) and x.dtype == f64 and not getattr(x, "weak_type", False):
        arr = x
    else:
        host = host.astype(f64)
        arr = None
    if not np.all(np.isfinite(host)):
        raise ValueError(f"{name}: contains non-finite values (NaN or inf).")
    if arr is None:
        # strongly typed; a transfer (`jnp.asarray` of a NumPy array compiles a program per shape)
        arr = _device_scalar(x, f64, host) if type(x) in (float, int) else jax.device_put(host)
    return arr, host


_SCALARS: dict = {}
"""Device arrays of Python numbers given to `float_array` (a run's dt and t0, the same from call
to call), by type, exact value and dtype: a JAX array is immutable, and each conversion is a
transfer of its own."""

_SCALARS_MAX = 64


def _device_scalar(x, dtype, host: np.ndarray) -> jax.Array:
    """`jnp.asarray(host)` for the Python number `x` (`host`: it as a NumPy array of `dtype`), kept
    in `_SCALARS` under its exact value (`float.hex`: -0.0 is not 0.0), unless it was made inside a
    trace: a tracer kept would leak into later calls, which would then take it for traced input."""
    key = (type(x), x.hex() if isinstance(x, float) else x, np.dtype(dtype))
    found = _SCALARS.get(key)
    if found is None:
        found = jax.device_put(host)
        if is_traced(found):  # made inside a trace (a jit of the caller's): a tracer, never kept
            return found
        if len(_SCALARS) >= _SCALARS_MAX:
            _SCALARS.clear()
        _SCALARS[key] = found
    return found


def host_float_array(x, name: str) -> np.ndarray:
    """x as a NumPy float array kept on the host (large sweep inputs, dealt out batch by batch),
    refused like `float_array` if it is not an array of real numbers."""
    if x is None or isinstance(x, (str, bytes)):
        raise TypeError(f"{name}: expected an array of numbers, got {type(x).__name__}.")
    try:
        arr = np.asarray(x)
    except Exception as err:  # e.g. ragged lists
        raise TypeError(f"{name}: expected an array of numbers ({err}).") from None
    _real_dtype(arr.dtype, name, allow_bool=True)
    return arr.astype(np.float64) if arr.dtype != np.float64 else arr  # float32/16 promoted too


def positive_int(x, name: str, *, allow_none: bool = False, minimum: int = 1):
    """x as a Python int >= `minimum` (None passes when `allow_none`)."""
    if x is None and allow_none:
        return None
    if isinstance(x, bool) or not isinstance(x, numbers.Integral) or x < minimum:
        raise ValueError(f"{name}: expected an int >= {minimum}, got {x!r}.")
    return int(x)


def nonnegative(x, name: str) -> float:
    """x as a finite Python float >= 0."""
    if isinstance(x, bool) or not isinstance(x, numbers.Real) or not np.isfinite(x) or x < 0:
        raise ValueError(f"{name}: expected a finite number >= 0, got {x!r}.")
    return float(x)


def positive_scalar(x, name: str, *, allow_bool: bool = True) -> jax.Array:
    """A scalar float array, positive when concrete (a time step)."""
    arr, host = _float_array(x, name, allow_bool)
    if arr.shape != ():
        raise ValueError(f"{name}: expected a scalar, got an array of shape {arr.shape}.")
    if host is not None and not float(host) > 0:
        raise ValueError(f"{name}: must be positive, got {float(host)}.")
    return arr


def output_shape(fn_name: str, fn, args, describe: str):
    """(the shape and dtype `fn(*args)` returns, whether `fn` closes over a traced value), args
    may be `ShapeDtypeStruct`s; or a `ValueError` naming `fn_name` and the call `describe` when
    it cannot run on them. A function built inside a caller's `jit`/`vmap`/`grad` may close
    over the caller's tracers: they are the traced constants of its jaxpr."""
    try:
        closed, shape = jax.make_jaxpr(fn, return_shape=True)(*args)
    except Exception as err:  # the user's function could not even run on these shapes
        raise ValueError(f"{fn_name}: calling it as {describe} failed: {type(err).__name__}: {err}") from None
    return shape, any(is_traced(c) for c in closed.consts)


def runnable_check(system, Q0):
    """`system.check_Q` when it can run on Q0, else None: values are known only when neither Q0
    nor the check's array leaves are traced (jit/vmap)."""
    check = system.check_Q
    if check is None or any_traced(Q0, check):
        return None
    return check


def check_configuration(system, Q0, name: str = "Q0"):
    """The system's own check that Q0 lies on its configuration manifold (`ClebschSystem.check_Q`,
    e.g. a rotation for SO(3) models): on concrete values only (`runnable_check`)."""
    check = runnable_check(system, Q0)
    if check is None:
        return
    problem = check(np.asarray(Q0))
    if problem is None:
        return
    if not isinstance(problem, str):
        raise TypeError(
            f"check_Q: must return None or a string saying what is wrong, returned {type(problem).__name__}."
        )
    raise ValueError(f"{name}: {problem}")


def memory_limit() -> int:
    """The machine's physical memory in bytes (0 if unknown: no limit)."""
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return 0


def check_memory(name: str, what: str, need: float, fix: str, detail: str = "") -> None:
    """Refuse, before allocating anything, a run whose arrays would not fit in the machine's
    memory (`memory_limit`): a `ValueError` naming the argument `name`, saying that `what`
    (e.g. "1000000000 steps") would need about `need` bytes (`detail`: for what, e.g. " for
    the Solution (128 bytes per step)"), the machine's memory, and `fix`, the way out. Shared by `integrate`, `sweep`
    and `batch`, which each estimate `need` from shapes known before compiling."""
    limit = memory_limit()
    if limit and need > limit:
        raise ValueError(
            f"{name}: {what} would need about {need / 1e9:.3g} GB{detail}, more than this machine's "
            f"{limit / 1e9:.3g} GB of memory. {fix}"
        )
