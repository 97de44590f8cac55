"""`integrate`'s arguments, before anything is compiled: each checked (types, values, the three
maps called on their shapes, the configuration, the model, the memory of the `Solution`), the
system to march (its isotropy's gauge fixed where the Lagrangian does not see it) and the stepper
chosen and prepared for it (`prepare`, `prepared_method`); and the warning for a map remade with
other Python numbers in its closure (`warn_if_remade`)."""

from __future__ import annotations

import collections
import numbers
import types
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from ..core.isotropy import (
    check_initial_momentum,
    gauge_isotropy,
    gauge_weight,
    gauged,
    physical_part,
    physical_velocity,
)
from ..core.manifold_checks import check_group_configuration
from ..core.model_checks import check_model, traced_isotropy
from ..core.system import ClebschSystem
from ..core import validation
from ..core.validation import (
    any_traced,
    check_configuration,
    check_memory,
    float_array,
    is_array,
    is_traced,
    nonnegative,
    output_shape,
    positive_int,
    positive_scalar,
)
from ..steppers.base import AbstractStepper
from .energy_check import energy_rtol
from ..steppers.choose import check_scheme, choose_method
from ..steppers.principles import check_particle_axis

__all__ = ["prepare", "prepared_method", "solution_bytes_per_step", "vmapped_members", "warn_if_remade"]

_LEGACY_DEFAULTS = dict(
    scheme=None,
    reduce="auto",
    need_P=False,
    reconstruct=True,
    rtol=0.0,
    atol=0.0,
    max_newton_iterations=20,
    jacobian="dense",
    order=None,
    composition=None,
)
"""`integrate`'s options that describe the method; with `method=` they belong to the stepper."""


def _check_options(system, n_steps, rtol, atol, max_newton_iterations):
    if not isinstance(system, ClebschSystem):
        raise TypeError(f"system: expected a clebsch_jax.ClebschSystem, got {type(system).__name__}.")
    if isinstance(n_steps, bool) or not isinstance(n_steps, numbers.Integral):
        raise TypeError(f"n_steps: expected a Python int, got {type(n_steps).__name__}.")
    if n_steps < 1:
        raise ValueError(f"n_steps: must be at least 1, got {n_steps}.")
    positive_int(max_newton_iterations, "max_newton_iterations")
    nonnegative(rtol, "rtol"), nonnegative(atol, "atol")


def _real_output(name: str, out, expected: str):
    """Refuse (naming `name`) a map's output `out` (from `output_shape`) that is not one array
    of real floating-point numbers: a tuple, an integer or a complex result."""
    if not isinstance(out, jax.ShapeDtypeStruct):
        got = f"a {type(out).__name__} of {len(out)} values" if isinstance(out, (tuple, list)) else type(out).__name__
        raise ValueError(f"{name}: must return {expected}, returned {got}.")
    if not jnp.issubdtype(out.dtype, jnp.floating):
        hint = (
            "take the real part or write it in real arithmetic"
            if jnp.issubdtype(out.dtype, jnp.complexfloating)
            else "compute it in floating point, e.g. with float constants"
        )
        raise ValueError(f"{name}: must return {expected}, returned dtype {out.dtype} ({hint}).")


def _check_arrays(system, Q0, xi0, P0, dt, t0, configuration: bool = True):
    """The arrays as float arrays, and the three maps called on their shapes (`ValueError`
    naming the map that cannot run on them or returns the wrong shape or dtype); then, on
    concrete values, the configuration (`check_configuration`) and the model (`check_model`).
    Returns them, whether a map closes over a traced value (`_check_maps`) and the system to
    march: `system`, or, when l does not see the isotropy of Q0, `system` with that gauge fixed
    (`clebsch_jax.gauge_isotropy`). Without `P0`, ξ⁰ is taken as the physical
    velocity L_ξ⁰ Q⁰ (`physical_velocity`: its isotropy component dropped, with a
    warning), and a momentum still without a multiplier is reported (`check_initial_momentum`)."""
    Q0, xi0 = float_array(Q0, "Q0"), float_array(xi0, "xi0")
    dt = positive_scalar(dt, "dt")
    if P0 is not None:
        P0 = float_array(P0, "P0")
        if P0.shape != Q0.shape:
            raise ValueError(f"P0: expected Q0's shape {Q0.shape}, got {P0.shape}.")
    t0 = float_array(t0, "t0")
    if t0.shape != ():
        raise ValueError(f"t0: expected a scalar, got an array of shape {t0.shape}.")
    closes = _check_maps_once(system, Q0, xi0, dt)
    if configuration:  # False: the caller checked it (`check_member`)
        check_configuration(system, Q0)
    facts = check_model(system, Q0, xi0, dt)
    check_group_configuration(system, Q0, xi0)  # after check_model: the velocity map is finite at Q0
    if facts is not None:
        if facts.gauge:
            system = gauge_isotropy(system, Q0, xi0)
        if P0 is None:
            xi0 = physical_velocity(system, Q0, xi0, facts.isotropy, stacklevel=5)
            check_initial_momentum(system, Q0, xi0, as_given=False, stacklevel=5)
    elif not closes and any_traced(Q0, xi0):
        # values known only in the program: the gauge's rank decided on a concrete example, its
        # weight and ξ⁰'s physical part computed in the program (the same functions as above)
        found = traced_isotropy(system, Q0.shape, xi0.shape)
        if found is not None:
            rank, kernel_dim, degenerate = found
            base = system
            system = gauged(base, rank, kernel_dim, gauge_weight(base, Q0, xi0), degenerate)
            if P0 is None:
                xi0 = physical_part(base.velocity_map, Q0, xi0, rank)
    return Q0, xi0, P0, dt, t0 if t0.dtype == dt.dtype else t0.astype(dt.dtype), closes, system


def _check_maps(system, Q0, xi0, dt) -> bool:
    """The three maps called on the shapes of Q0, xi0 and dt (`ValueError` naming the map
    that cannot run on them or returns the wrong shape or dtype). Returns whether a map closes
    over a traced value (a system built inside the caller's `jit`/`vmap`/`grad`)."""
    sx, sq = jax.ShapeDtypeStruct(xi0.shape, xi0.dtype), jax.ShapeDtypeStruct(Q0.shape, Q0.dtype)
    shapes = f"xi0 of shape {xi0.shape} and Q0 of shape {Q0.shape}"
    call = ("lagrangian(xi0, Q0)" if system.has_potential else "lagrangian(xi0)") + f" with {shapes}"
    lag, closes_l = output_shape("lagrangian", system.l, (sx, sq), call)
    _real_output("lagrangian", lag, "a real floating-point scalar")
    if lag.shape != ():
        raise ValueError(f"lagrangian: must return a scalar, returned shape {lag.shape} for {shapes}.")
    vel, closes_v = output_shape("velocity_map", system.velocity_map, (sx, sq), f"velocity_map(xi0, Q0) with {shapes}")
    _real_output("velocity_map", vel, "a real floating-point array of Q's shape")
    if vel.shape != Q0.shape:
        raise ValueError(
            f"velocity_map: must return an array of Q's shape {Q0.shape}, returned {vel.shape} for {shapes}."
        )
    der, closes_d = output_shape(
        "derivative_map",
        system.derivative_map,
        (sq, sq, jax.ShapeDtypeStruct((), dt.dtype)),
        f"derivative_map(Q_next, Q, dt) with Q of shape {Q0.shape}",
    )
    _real_output("derivative_map", der, "a real floating-point array of Q's shape")
    if der.shape != Q0.shape:
        raise ValueError(f"derivative_map: must return an array of Q's shape {Q0.shape}, returned {der.shape}.")
    return closes_l or closes_v or closes_d


_MAPS_CHECKED: collections.OrderedDict = collections.OrderedDict()


_MAPS_CHECKED_SIZE = 256


def _check_maps_once(system, Q0, xi0, dt) -> bool:
    """`_check_maps`, skipped when it already passed for the same system structure (its
    functions and static fields) and the same shapes and dtypes: its outcome depends on
    nothing else, and tracing the three maps is most of a short call's fixed cost. Returns
    `_check_maps`'s answer (a map closing over a traced value is checked every time: such a
    function is made anew inside each trace)."""
    leaves, treedef = jax.tree_util.tree_flatten(system)
    # arrays by shape and dtype (weak types included), anything else (functions) as itself
    avals = tuple(
        (np.shape(x), np.dtype(x.dtype), bool(getattr(x, "weak_type", False))) if is_array(x) or is_traced(x) else x
        for x in (*leaves, Q0, xi0, dt)
    )
    try:
        key = (treedef, avals)
        hash(key)
    except TypeError:  # a static field that cannot be hashed: check every time
        return _check_maps(system, Q0, xi0, dt)
    if key in _MAPS_CHECKED:
        _MAPS_CHECKED.move_to_end(key)
        return False
    if _check_maps(system, Q0, xi0, dt):
        return True
    _MAPS_CHECKED[key] = True
    if len(_MAPS_CHECKED) > _MAPS_CHECKED_SIZE:
        _MAPS_CHECKED.popitem(last=False)
    return False


_CLOSED_NUMBERS: dict = {}
"""(role, code object) of a user's function → the Python numbers its closure held when last seen."""


_REMADE_WARNED: set = set()


def warn_if_remade(system) -> None:
    """Warn once per function when one of the system's maps is a function seen before with the
    same code but other Python numbers in its closure (a function made anew for each value, as
    `lambda xi, q: ... - g * q[2]` inside a loop over g): the march is compiled for every such
    function (functions are static, compared by identity), which costs most of a short call.
    Array leaves of a `jax.tree_util.Partial` are traced instead, and reuse one program."""
    for role in ("lagrangian", "velocity_map", "derivative_map"):
        fn = getattr(system, role)
        if not isinstance(fn, types.FunctionType) or not fn.__closure__:
            continue
        values = []
        for cell in fn.__closure__:
            try:
                value = cell.cell_contents
            except ValueError:  # an empty cell
                continue
            if isinstance(value, numbers.Number) and not isinstance(value, bool):
                values.append(value)
        if not values:
            continue
        key = (role, fn.__code__)
        seen = _CLOSED_NUMBERS.get(key)
        _CLOSED_NUMBERS[key] = tuple(values)
        if seen is None or seen == tuple(values) or key in _REMADE_WARNED:
            continue
        _REMADE_WARNED.add(key)
        warnings.warn(
            f"{role}: a function with the code of one integrated before but other Python numbers in its closure "
            f"({', '.join(map(repr, values))}; before: {', '.join(map(repr, seen))}): the march is compiled again "
            "for every new function. Hold such a parameter as an array leaf to compile once, e.g. "
            "jax.tree_util.Partial(fn, jnp.asarray(value)) with fn taking it as its first argument (said once "
            "per function).",
            UserWarning,
            stacklevel=3,
        )


def vmapped_members(*trees) -> int:
    """How many members the caller's `jax.vmap`s (nested ones multiplied) map a call over, read
    off the batch sizes of the traced leaves of `trees`; 1 outside `vmap`. It reads JAX's
    batching tracers (`batch_dim` and `val`); a leaf that does not look like one counts 1."""
    most = 1
    for leaf in jax.tree_util.tree_leaves(trees):
        members, t = 1, leaf
        try:
            while isinstance(getattr(t, "batch_dim", None), int) and hasattr(t, "val"):
                members, t = members * int(t.val.shape[t.batch_dim]), t.val
        except (AttributeError, IndexError, TypeError):
            members = 1
        most = max(most, members)
    return most


def _check_size(Q0, xi0, n_steps: int, members: int = 1):
    """Refuse a run whose `Solution` could not fit in memory, before allocating it: every node
    keeps Q, p, the momentum and ξ, every step P, ξ and four statistics (float64). Under the
    caller's `vmap` of `members` members: a warning when all their `Solution`s would not fit
    (not a refusal: XLA keeps only what the caller's program uses, which may be far less)."""
    per_step = solution_bytes_per_step(Q0, xi0)
    need, limit = per_step * (n_steps + 1) * members, validation.memory_limit()
    if members > 1 and limit and need > limit:
        warnings.warn(
            f"integrate under jax.vmap: the Solutions of {members} members x {n_steps} steps would need about "
            f"{need / 1e9:.3g} GB ({per_step} bytes per step and member), more than this machine's "
            f"{limit / 1e9:.3g} GB of memory; XLA runs out of memory if the program keeps them all. "
            "clebsch_jax.batch(fun) keeps only what fun returns and refuses a batch that would not fit; "
            "clebsch_jax.sweep keeps per-member reductions and every k-th node (save_every=k).",
            UserWarning,
            stacklevel=4,
        )
    check_memory(
        "n_steps",
        f"{n_steps} steps",
        per_step * (n_steps + 1),
        "Run it in pieces (clebsch_jax.continue_from), or with clebsch_jax.sweep, which keeps per-member "
        "reductions and every k-th node (save_every=k) instead of the whole trajectory.",
        detail=f" for the Solution ({per_step} bytes per step)",
    )


def solution_bytes_per_step(Q0, xi0) -> int:
    """Bytes a `Solution` keeps per step of a member with these shapes (float64): every node
    Q, p, the momentum and ξ, every step P, ξ and four statistics."""
    return 8 * (3 * int(np.size(Q0)) + 3 * int(np.size(xi0)) + 8)


def prepared_method(system, Q0, xi0, **options):
    """`integrate`'s checks of its arguments and its choice of method, without the march:
    `(stepper prepared for the system, (Q0, xi0, P0, dt, t0, closes) as arrays, n_steps)`.
    Raises what `integrate` raises for bad arguments; works on traced arguments
    (`clebsch_jax.sweep` checks one member this way, under `jax.eval_shape`). The keyword
    options are `integrate`'s."""
    return prepare(system, Q0, xi0, **options)[:3]


def prepare(
    system,
    Q0,
    xi0,
    *,
    dt,
    n_steps,
    P0=None,
    t0=0.0,
    method=None,
    scheme=None,
    reduce="auto",
    need_P=False,
    reconstruct=True,
    rtol=0.0,
    atol=0.0,
    max_newton_iterations=20,
    jacobian="dense",
    order=None,
    composition=None,
    check_energy=True,
    configuration=True,
):
    """`prepared_method`, and the system to march (the gauged one, when `_check_arrays` fixed
    the isotropy's gauge)."""
    _check_options(system, n_steps, rtol, atol, max_newton_iterations)
    energy_rtol(check_energy)  # True, False or a positive tolerance
    n_steps = int(n_steps)  # a NumPy integer is accepted and becomes the static Python int
    if method is None:
        check_scheme(system, scheme)
    else:
        _check_method(method, locals())
    Q0, xi0, P0, dt, t0, closes, system = _check_arrays(system, Q0, xi0, P0, dt, t0, configuration)
    _check_size(Q0, xi0, n_steps, vmapped_members(system, Q0, xi0, P0, dt))
    if method is None:
        if jacobian == "blocks":
            check_particle_axis(Q0, xi0)
        method = choose_method(
            system,
            Q0,
            xi0,
            scheme=scheme,
            reduce=reduce,
            need_P=need_P,
            reconstruct=reconstruct,
            rtol=rtol,
            atol=atol,
            max_newton_iterations=max_newton_iterations,
            jacobian=jacobian,
            order=order,
            composition=composition,
        )
    return method.prepare(system, Q0, xi0), (Q0, xi0, P0, dt, t0, closes), n_steps, system


def _check_method(method, options):
    if not isinstance(method, AbstractStepper):
        raise TypeError(
            "method: expected a stepper (e.g. clebsch_jax.FullStep(), ReducedStep(), "
            f"GaussLegendre(order=8)), got {type(method).__name__}."
        )
    for name, default in _LEGACY_DEFAULTS.items():
        value = options[name]
        if value is not default and value != default:
            raise ValueError(
                f"{name}: with method= the method's options are the stepper's own; pass "
                f"{name}={value!r} to the stepper instead (or leave method unset)."
            )
