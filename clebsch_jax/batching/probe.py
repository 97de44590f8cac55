r"""One member checked and traced before anything is compiled.

`check_first_member` makes `integrate`'s checks that need values on the first member that can
run (concrete values: the model by autodiff, the configuration, the first step);
`member_shapes` traces one member's chunk (or, for a sweep that keeps the energy only, its
choice of method alone) for the shapes of the table and the facts of the march. Traces are
cached by the configuration and the member's shapes (`trace_key`).
"""

from __future__ import annotations

import dataclasses
import json
import pickle
import warnings
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..core.isotropy import IsotropyGauge as _IsotropyGauge
from ..core.isotropy import physical_part as _physical_part
from ..core.isotropy import rank_holds as _rank_holds
from ..core.jit import memo, undifferentiated
from ..core.validation import check_configuration as _check_configuration
from ..core.validation import runnable_check as _runnable_check
from ..march.carry import start as march_start
from ..march.energy_check import node_energy
from ..march.integrate import check_member as _check_member_eagerly
from ..march.arguments import prepared_method
from ..native.fingerprint import fingerprint, stored_entries, values_digest
from .config import Config, Members, chunk_integrate, first_row, member_slices, system_of
from .lean import carries_Q as _lean_carries_Q
from .member import march_start_values


def _check_configurations(system, Q0, n_ic):
    """The system's `check_Q` of every concrete Q0[j]: at once when the check has a vectorised
    form (`check_Q.batched(stack) -> None | (j, sentence)`, as the SO(n) models' rotation check
    has; called row by row from Python, it took a large part of a million-member sweep's time),
    else one call per row."""
    check = _runnable_check(system, Q0)
    if check is None:
        return
    batched = getattr(check, "batched", None)
    if batched is not None:
        found = batched(np.asarray(Q0))
        if found is not None:
            j, problem = found
            raise ValueError(f"Q0[{j}]: {problem}")
        return
    for j in range(n_ic):
        try:
            _check_configuration(system, Q0[j])
        except ValueError as err:
            raise ValueError(f"Q0[{j}]: {str(err).removeprefix('Q0: ')}") from None


FIRST_MEMBER_TRIES = 8
"""`check_first_member` checks the first member whose inputs are finite and whose system
`make_system` builds from its concrete parameter row, among the first this many such members."""


def check_first_member(cfg: Config, members: Members) -> tuple | None:
    """`integrate`'s checks of a member, with its concrete values, before any batch is traced or
    compiled (`clebsch_jax.march.integrate.check_member`): the batches march traced members, on
    which `integrate` skips the checks that need values — the model by autodiff (`check_model`),
    Q0 in the velocity map's group (`check_group_configuration`) and the first step on the
    configuration manifold (`check_first_step`). One member: the checks look at the model (its
    functions), which the members share. It is the first member that can run: one with
    non-finite inputs, or whose parameter row the model's constructor refuses, is reported in
    the table instead (`Status.INVALID_INPUT`), as before. The system's own check of its
    configurations (`check_Q`) runs on every Q0[j], first (`_check_configurations`).

    Returns the isotropy gauge `integrate` fixes for that member, `(rank, kernel dimension,
    degenerate)` (`Config.isotropy`: every member's system gets it, with its own weight), or
    None (no gauge, or no member checked)."""
    # a pass is kept per fingerprint and digest of the values checked (a failure raises: checked again)
    check = lambda: _check_configurations(_first_system(cfg, members), members.Q0, members.n_ic)  # noqa: E731
    key = _record("configurations", cfg, values_digest((first_row(members), members.shared, members.Q0)))
    check() if key is None else memo(_SYSTEMS, key, check, _TRACES_MAX)
    ok_ic = _finite_rows(members.Q0) & _finite_rows(members.xi0)
    ok_ic &= True if members.P0 is None else _finite_rows(members.P0)
    ok = ok_ic[members.ic_index]
    if members.builder is not None:
        rows = np.all([_finite_rows(leaf) for leaf in jax.tree_util.tree_leaves(members.params)], axis=0)
        ok &= rows[members.param_index]
    options = {k: v for k, v in cfg.options if k != "check_energy"}
    for m in np.flatnonzero(ok)[:FIRST_MEMBER_TRIES]:
        i, j = int(members.param_index[m]), int(members.ic_index[m])
        row = None if members.builder is None else member_slices(members.params, i)
        P0 = None if members.P0 is None else members.P0[j]
        values = (row, members.shared, members.Q0[j], members.xi0[j], members.dt[m], P0)
        key = _record("first member", cfg, values_digest(values))
        found = _found(key, load=_load_gauge)
        if found is not None:  # this member passed before (so its system was built)
            return found[0]
        try:
            system = system_of(cfg, row, members.shared)
        except (ValueError, TypeError):  # a row the constructor refuses: that member reports it
            continue

        def check():
            checked = _check_member_eagerly(
                system, members.Q0[j], members.xi0[j], dt=members.dt[m], P0=P0, configuration=False, **options
            )
            gauge = checked.lagrangian
            if not isinstance(gauge, _IsotropyGauge):
                return None
            return int(gauge.rank), int(gauge.kernel_dim), bool(checked.degenerate)

        try:
            return once(key, check, load=_load_gauge, dump=_dump_gauge)
        except (ValueError, TypeError) as err:
            where = (f"make_system(params[{i}]), " if members.builder is not None else "") + f"Q0[{j}], xi0[{j}]"
            raise type(err)(f"sweep: member {m} ({where}) is rejected by integrate's checks: {err}") from err
    return None


def _finite_rows(a) -> np.ndarray:
    """Whether each row of `a` (its leading axis) is finite: the whole array at once first (the
    usual case, without a reduction per row; a broadcast view by the entries it stores), row by
    row only when that finds a non-finite value."""
    a = np.asarray(a)
    if np.isfinite(stored_entries(a)[1]).all():
        return np.ones(len(a), bool)
    return np.all(np.isfinite(np.reshape(a, (len(a), -1))), axis=1)


def _first_system(cfg: Config, members: Members):
    """`system_of` the first parameter row, whose configuration check every Q0 gets: built once
    per fingerprint of the configuration's code and digest of the row's and shared values
    (`_record`: a changed function, closure or global builds it again), else every call."""
    row = first_row(members)
    build = lambda: system_of(cfg, row, members.shared)  # noqa: E731
    key = _record("first system", cfg, values_digest((row, members.shared)))
    return build() if key is None else memo(_SYSTEMS, key, build, _TRACES_MAX)


_SYSTEMS: dict = {}


def _dump_gauge(gauge: tuple | None) -> bytes:
    """The first member's isotropy gauge (`check_first_member`'s result) as a passed check keeps it."""
    return json.dumps(None if gauge is None else list(gauge)).encode()


def _load_gauge(data: bytes) -> tuple | None:
    gauge = json.loads(data.decode())
    return None if gauge is None else (int(gauge[0]), int(gauge[1]), bool(gauge[2]))


_PASSED: dict = {}
"""{key: (result,)} of the checks that passed in this process (`once`), so that a call finds its
pass without reading the disk record."""
_PASSED_MAX = 1024


def _record(kind: str, cfg: Config, digest: str | None) -> str | None:
    """The key of a check of `cfg`'s member on what `digest` names (values' bytes, or shapes),
    or None when `cfg` cannot be fingerprinted (`clebsch_jax.native.fingerprint`): such checks
    always run."""
    from ..native.fingerprint import record_key

    # per configuration in a process, as the traces and compiled programs are (`trace_key`)
    found = memo(_FINGERPRINTS, (kind, cfg), lambda: fingerprint((kind, cfg)), _TRACES_MAX)
    return None if found is None or digest is None else record_key(kind, found, digest)


_FINGERPRINTS: dict = {}


def _found(key: str | None, load=None) -> tuple | None:
    """`(result,)` of a check that passed under `key` before (`once`), or None."""
    from ..native.fingerprint import read

    if key is None:
        return None
    found = _PASSED.get(key)
    if found is not None:
        return found
    data = read(key, ".passed")
    if data is None:
        return None
    try:
        result = None if load is None else load(data)
    except Exception:  # a record of another version: check again
        return None
    _passed(key, result)
    return (result,)


def _passed(key: str, result) -> None:
    if len(_PASSED) >= _PASSED_MAX:
        _PASSED.clear()
    _PASSED[key] = (result,)


def once(key: str | None, check, load=None, dump=None):
    """`check()` (a check that raises, warns or returns a result), unless it passed under `key`
    before, in this process or (a record on disk, `clebsch_jax.native.fingerprint`) in another:
    the checks a sweep makes before it runs depend only on what `key` names (the code of the
    member's functions, the configuration, the values checked), so a pass stays a pass. Only
    a clean pass is kept: a check that raised or warned runs again next time (its warnings
    are recorded, then given to the caller's filters again, as if not recorded). With `load`
    and `dump`, the check's result is kept too (`dump(result) -> bytes`, `load(bytes)`)."""
    from ..native.fingerprint import write

    found = _found(key, load)
    if found is not None:
        return found[0]
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")  # every warning recorded, whatever was shown before
            result = check()
    finally:
        # to the caller's filters again, outside the recording (re-emitted inside it, each
        # would be recorded again while the list is read: a loop that never ends)
        for w in caught:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno, source=w.source)
    if key is not None and not caught:
        try:
            data = b"" if dump is None else dump(result)
        except Exception:  # a result that cannot be kept: checked again next time
            return result
        write(key, ".passed", data)
        _passed(key, result)
    return result


class Shapes(NamedTuple):
    """One member's shapes and the facts of its march."""

    q: tuple  # Q's shape
    xi: tuple  # ξ's shape
    has_Q: bool  # False: the reduced march ran without reconstructing Q
    has_xi: bool  # False: a degenerate system (no nodal velocity)
    invariants: dict  # {name: shape and dtype of its values on a 1-step solution, (2, …)}
    facts: dict  # form, scheme, order, method
    march: object = None  # shapes and dtypes of the march state a chunk hands on (`Carry.march`)


def _trace_member(cfg: Config, *args):
    """`jax.eval_shape` of one member's chunk (its `Solution` and invariants), cached by the
    arguments' shapes and dtypes: the trace reads nothing else, and repeating it cost a sweep of
    a thousand members a third of its time."""

    def probe(p, s, q, x, d):
        system = system_of(cfg, p, s)
        sol = chunk_integrate(cfg, system, q, x, jnp.zeros_like(q), jnp.zeros((), q.dtype), d, cfg.n)
        return sol, {name: jnp.asarray(fn(system, sol)) for name, fn in cfg.invariants}

    def trace():  # as the chunk programs trace the march (`chunks_xla._batched_chunk`), whose traces it shares
        with undifferentiated():
            return jax.eval_shape(probe, *args)

    return memo(_TRACES, trace_key(cfg, args), trace, _TRACES_MAX)


def trace_key(cfg: Config, args) -> tuple:
    """The cache key of a trace of one member's `args`: the configuration, the arguments' tree,
    shapes and dtypes (a trace reads nothing else)."""
    leaves, tree = jax.tree_util.tree_flatten(args)
    dtype = lambda x: x.dtype if hasattr(x, "dtype") else np.result_type(x)  # not an array as a dtype (deprecated)
    return (cfg, tree, tuple((np.shape(x), dtype(x), getattr(x, "weak_type", False)) for x in leaves))


_TRACES: dict = {}
_TRACES_MAX = 64
"""`_trace_member`'s cache (`clebsch_jax.core.jit.memo`): cleared when it holds this many."""


def _check_member(cfg: Config, *args):
    """`integrate`'s checks of one member's arguments and its choice of method, traced
    (`prepared_method` under `jax.eval_shape`: no march is traced, nothing compiled):
    (the prepared method's facts, whether the lean chunk carries Q, the energy's dtype, and the
    shapes of the march state: the per-member program's (`MemberCarry.march`) for the native
    backend, else the general chunk's, which the reruns of a lean sweep carry)."""
    found = {}

    def check(p, s, q, x, d):
        system = system_of(cfg, p, s)
        stepper, _, _ = prepared_method(
            system, q, x, dt=d, n_steps=cfg.n, P0=jnp.zeros_like(q), t0=jnp.zeros((), q.dtype), **dict(cfg.options)
        )
        found["facts"], found["has_Q"] = stepper.facts(system), _lean_carries_Q(stepper, system)
        P = jnp.zeros_like(q)
        if cfg.native:  # the per-member program's march state
            march = march_start_values(stepper, system, q, x, P, d)
        else:  # the general chunk's, which a lean sweep's reruns carry (`chunks_xla._march_state`)
            march = march_start(stepper, system, q, x, P, d, check_inputs=True)[0]
        found["march"] = jax.tree_util.tree_map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype), march)
        return node_energy(system, q, x)[0]

    def run():
        energy = jax.eval_shape(check, *args)
        return found["facts"], found["has_Q"], energy.dtype, found["march"]

    def checked():  # a fresh process finds a pass of the same configuration and shapes on disk
        leaves, tree = jax.tree_util.tree_flatten(args)
        signature = [(np.shape(x), str(_dtype(x)), getattr(x, "weak_type", False)) for x in leaves]
        key = _record("member", cfg, fingerprint((tree, signature)))
        return once(key, run, load=pickle.loads, dump=pickle.dumps)

    return memo(_TRACES, ("check",) + trace_key(cfg, args), checked, _TRACES_MAX)


def _dtype(x):
    """A leaf's dtype: its own for an array (NumPy's `result_type` of a JAX array is deprecated)."""
    return x.dtype if hasattr(x, "dtype") else np.result_type(x)


def member_shapes(cfg: Config, members: Members, lean: bool = False) -> Shapes:
    """One member's shapes, by tracing integrate (its own checks name Q0, xi0, ...): no compile.

    With `lean` (the sweep runs the lean chunk, `clebsch_jax.batching.lean`, which keeps the
    energy only): the same checks and shapes without tracing the march, which nothing else
    of such a sweep would reuse (`_check_member`). The configurations and the checks that need
    values were made before, on concrete values (`check_first_member`)."""
    p_row = first_row(members)
    j = members.ic_index[0]
    # host arrays: traced as JAX's would be (same dtypes, not weak), with no program compiled to convert them
    q_row, x_row = np.asarray(members.Q0[j]), np.asarray(members.xi0[j])

    args = (p_row, members.shared, q_row, x_row, np.asarray(members.dt[0]))
    try:
        if lean:
            facts, has_Q, energy_dtype, march = _check_member(cfg, *args)
        else:
            sol_shape, inv_shape = _trace_member(cfg, *args)
    except (ValueError, TypeError) as err:
        where = (
            "make_system(params[i]), " if members.builder is not None else ""
        ) + f"Q0[j] of shape {q_row.shape}, xi0[j] of shape {x_row.shape}"
        kind = ValueError if isinstance(err, ValueError) else TypeError
        raise kind(f"sweep: one member ({where}) is rejected: {err}") from err
    if lean:  # a regular system (nodal velocities), the energy its only invariant (`lean_applies`)
        invariants = {"energy": jax.ShapeDtypeStruct((cfg.n + 1,), energy_dtype)}
        facts = dict(form=facts.form, scheme=facts.scheme, order=int(facts.order), method=str(facts.name))
        return Shapes(q_row.shape, x_row.shape, has_Q, True, invariants, facts, march)
    for name, v in inv_shape.items():
        if v.ndim < 1 or v.shape[0] != cfg.n + 1:
            raise ValueError(
                f"invariants: {name!r} must return one value per node (leading axis n+1 = "
                f"{cfg.n + 1} for a {cfg.n}-step solution), returned shape {v.shape}."
            )
    facts = dict(
        form=sol_shape.form,
        scheme=sol_shape.scheme,
        order=int(sol_shape.order),
        method=str(getattr(sol_shape, "method", "")),
    )
    has_Q, has_xi = sol_shape.Q is not None, sol_shape.xi is not None
    return Shapes(q_row.shape, x_row.shape, has_Q, has_xi, inv_shape, facts, sol_shape.march_state)


def warn_isotropic_xi0(cfg: Config, members: Members, stacklevel: int = 3) -> None:
    """Say once, as `integrate` says for its one ξ⁰ (`clebsch_jax.core.isotropy.physical_velocity`),
    when members' ξ⁰ have a component along the isotropy of their Q⁰ (`cfg.isotropy`): a run
    given no P0 starts each member from its physical part, which moves Q⁰ as ξ⁰ does
    (`config.member_system`). Every member is looked at, in one program over all of them;
    non-finite ones are reported in the table instead."""
    if cfg.isotropy is None or not cfg.derive_P:
        return
    rank = cfg.isotropy[0]
    plain = dataclasses.replace(cfg, isotropy=None)

    def moved(row, Q, xi):
        velocity_map = system_of(plain, row, members.shared).velocity_map
        change = jnp.linalg.norm((_physical_part(velocity_map, Q, xi, rank) - xi).reshape(-1))
        big = change > 1e-12 * jnp.maximum(jnp.linalg.norm(xi.reshape(-1)), jnp.finfo(xi.dtype).tiny)
        return big & _rank_holds(velocity_map, Q, xi.shape, rank)  # another orbit type is refused instead

    ic = members.ic_index
    rows = None if members.builder is None else member_slices(members.params, members.param_index)
    axes = (None if rows is None else 0, 0, 0)
    found = np.asarray(jax.jit(jax.vmap(moved, in_axes=axes))(rows, members.Q0[ic], members.xi0[ic]))
    if found.any():
        first = int(np.argmax(found))
        warnings.warn(
            f"xi0: {int(found.sum())} of {members.B} members (the first: member {first}) have a component "
            f"along the isotropy of their Q0 (the {cfg.isotropy[1]}-dimensional kernel of xi -> L_xi Q0, "
            "directions that move Q0 not at all). The sweep takes each xi0 as the physical velocity L_xi0 Q0, "
            "as integrate does, and starts from xi0 with that component dropped.",
            UserWarning,
            stacklevel=stacklevel,
        )
