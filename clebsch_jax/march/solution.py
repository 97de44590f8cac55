"""The result of `integrate`: trajectory, per-step Newton statistics and an overall result."""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import logging
import threading
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..roots.newton import NewtonStats, Status

__all__ = ["Solution", "IntegrationError"]


class IntegrationError(RuntimeError):
    """Raised (once, at the end) when a step of the march fails.

    Besides its message it carries where and why as attributes: `member` (the failing batch
    member's index, a tuple of ints under nested `vmap`, None for a single run), `step` (the
    failing step, or node for `Status.LEGENDRE`) and `status` (a `Status`; None when raised
    without one, as by `SweepResult.raise_if_failed`, whose message names every failed member).
    """

    def __init__(self, message: str, *, member=None, step=None, status=None):
        super().__init__(message)
        self.member, self.step, self.status = member, step, status

    def __reduce__(self):  # pickled (Dask, processes) with its attributes
        return (type(self), (self.args[0],), dict(self.__dict__))


@dataclasses.dataclass(frozen=True)
class Solution:
    r"""A discrete Clebsch trajectory.

    **Fields** (N = `n_steps`; every array gains leading batch axes under `jax.vmap`):

    - `ts` (N+1,): times $t_n = t_0 + n\Delta t$.
    - `Q` (N+1, *Q.shape): the nodes $Q^n$.
    - `p` (N+1, *Q.shape): the discrete momenta $p^n \in T^*_{Q^n}M$ (discrete Legendre
      transform; `p[0]` is the initial multiplier $P^0$).
    - `xi` (N+1, *xi.shape): nodal velocities, the root of Lemma 7's
      $\delta l/\delta\xi(\xi, Q^n) = -p^n \diamond Q^n$ (so `xi[0]` is the given `xi0`).
      None for a degenerate system (`ClebschSystem(..., degenerate=True)`), where that relation
      does not determine ξ.
    - `xi_step` (N, *xi.shape): the velocity $\xi^n$ of step n, with
      $\phi_{\Delta t}(Q^{n+1}, Q^n) = \mathcal L_{\xi^n} Q^n$ (Lemma 20). For symmetric
      derivative maps and the midpoint scheme it approximates $\xi(t_n + \Delta t/2)$.
    - `P` (N, *Q.shape): the multipliers $P^n$ of Lemma 20, one per step.
    - `momentum` (N+1, *xi.shape): the momentum map $\mu^n = -p^n \diamond Q^n$ at every node
      (Theorem 12; the body momentum for a matrix group), which equals $\delta l/\delta\xi$.

    The reduced march (`form="reduced"`, issue of Theorem 12 / Corollary 29) carries $\mu^n$
    instead of $(Q^n, p^n)$: there `p` is None, `Q` is None unless it was reconstructed, and
    `P` is None unless it was asked for (then it is the minimum-norm multiplier of each step,
    which differs from the full march's $P^n$ only in components the velocity map cannot see).
    - `stats`: `NewtonStats` of the step solves, each (N,): `iterations`,
      `residual_norm` (max-norm of the final Lemma 20 residual), `status` (`Status` codes),
      `jacobians`. Steps after a failure are `Status.SKIPPED` with 0 iterations, 0 Jacobians
      and a NaN residual.
    - `nodal_stats`: `NewtonStats` of the nodal-velocity solves, each (N+1,) (zero iterations
      for a degenerate system, where none are made; skipped nodes as above).
    - `result`: overall `Status` code (0 = success). `failed_step`: index of the first failing
      step (or node, for a nodal failure), -1 if none.
    - `valid` (N+1,): False at nodes after a failure. Their values are NaN on purpose, never
      plausible-looking numbers.
    - Static facts: `scheme`, `form` ("full" or "reduced"), `order` (nominal order of the method),
      `method` (what a step is made of, e.g. "Kahan-Li p8s17 of left principle"),
      `derivative_map` (its name; "none (collocation)" for `scheme="gauss"`, which does not use
      it), `q_ndim` and `xi_ndim` (ranks of one Q and one ξ), `isotropy` (the dimension of the
      isotropy of $Q^0$ whose gauge the engine fixed because l does not see it — a Lagrangian
      written with the physical velocities $\mathcal L_\xi Q$, `clebsch_jax.core.isotropy`; 0 when
      the system ran as written).

    - `march_state`: what the march hands to a continuation at its last node — the stepper's
      state (with its guess of the next step), its predictor history, the number of steps
      made, whether no step failed, and the last step's velocity. `continue_from` passes it on,
      and `integrate(..., march_state=...)` then makes exactly the steps the unbroken march
      would have made (`clebsch_jax.march.carry.resume`). A pytree of arrays whose structure
      depends on the method.
    - `accuracy_plan`: the `AccuracyPlan` of a run made with `accuracy=` (`clebsch_jax.choose_step`:
      the method, step, predicted error and work, and every candidate compared); None otherwise.

    With a composition (`integrate(..., order=k)`) the nodes are those of the whole steps;
    `xi_step` and `P` are those of each step's first sub-step, and `stats` combine the
    sub-steps' solves (updates and Jacobians summed, the worst residual, the first failure).
    """

    ts: jax.Array
    Q: jax.Array | None
    p: jax.Array | None
    xi: jax.Array | None
    xi_step: jax.Array
    P: jax.Array | None
    momentum: jax.Array
    stats: NewtonStats
    nodal_stats: NewtonStats
    result: jax.Array
    failed_step: jax.Array
    valid: jax.Array
    scheme: str = "left"
    form: str = "full"
    order: int = 1
    method: str = ""
    derivative_map: str = ""
    q_ndim: int = 0
    xi_ndim: int = 0
    solves_per_step: int = 1
    isotropy: int = 0
    march_state: Any = None
    accuracy_plan: Any = None

    @property
    def batch_ndim(self) -> int:
        """Number of leading batch axes (0 for a single trajectory)."""
        return self.momentum.ndim - 1 - self.xi_ndim

    @property
    def succeeded(self) -> jax.Array:
        """True where the whole march succeeded (an array under vmap)."""
        return self.result == Status.SUCCESS

    def raise_if_failed(self) -> "Solution":
        """Raise `IntegrationError` naming the first failing batch member and step.

        Works on concrete (not traced) solutions, batched or not: the recipe for a vmapped
        batch is `integrate(..., throw=False)` inside `vmap`, then `raise_if_failed()`
        outside it. Returns `self` when everything succeeded.
        """
        result = np.asarray(self.result)
        if not np.any(result != Status.SUCCESS):
            return self
        failed = np.argwhere(result != Status.SUCCESS)
        member = tuple(int(i) for i in failed[0])
        pick = (lambda a: np.asarray(a)[member]) if member else np.asarray
        step = int(pick(self.failed_step))
        code = int(pick(self.result))
        n_steps = np.asarray(self.ts).shape[-1] - 1
        stats = self.nodal_stats if code == Status.LEGENDRE else self.stats
        iters = pick(stats.iterations)[..., step]
        res = pick(stats.residual_norm)[..., step]
        matrices = pick(stats.jacobians)[..., step]
        t = pick(self.ts)[..., step]
        msg = failure_message(
            code,
            step,
            n_steps,
            float(t),
            int(iters),
            float(res),
            member or None,
            self.scheme,
            1 if code == Status.LEGENDRE else self.solves_per_step,
            int(matrices),
        )
        if len(failed) > 1:
            msg += f" ({len(failed)} batch members failed in all.)"
        raise IntegrationError(msg, member=_member_of(member), step=step, status=Status(code))


jax.tree_util.register_dataclass(
    Solution,
    data_fields=[
        "ts",
        "Q",
        "p",
        "xi",
        "xi_step",
        "P",
        "momentum",
        "stats",
        "nodal_stats",
        "result",
        "failed_step",
        "valid",
        "march_state",
    ],
    meta_fields=[
        "scheme",
        "form",
        "order",
        "method",
        "derivative_map",
        "q_ndim",
        "xi_ndim",
        "solves_per_step",
        "isotropy",
        "accuracy_plan",
    ],
)


def failure_message(
    code, step, n_steps, t, iterations, residual, member=None, scheme=None, solves=1, jacobians=None
) -> str:
    """A readable failure message: what failed, where, and what to try. `iterations` is what
    the step's solves made in all (`solves` of them; `scheme="gauss"` counts fixed-point sweeps);
    `jacobians` the Newton matrices they formed, the unit of `max_newton_iterations` (None:
    not known)."""
    where = f"batch member {member if len(member) > 1 else member[0]}, " if member else ""
    what = f"{Status.MESSAGES[code]} (Status.{Status(code).name})" if code in Status.MESSAGES else f"status {code}"
    if code == Status.LEGENDRE:
        return (
            f"clebsch_jax.integrate: {where}node {step} (t = {t:.6g}): {what} "
            f"(residual {residual:.3e} after {iterations} iterations). The step solves succeeded; "
            "the Lagrangian may be degenerate in xi: if it sees xi only through L_xi Q (physical velocities on "
            "a sphere), build the system with clebsch_jax.gauge_isotropy (integrate does so itself outside "
            "jit/vmap); if it is linear in xi, with degenerate=True, which uses the midpoint principle. Use "
            "throw=False to inspect the solution."
        )
    if code == Status.INVALID_INPUT:
        return (
            f"clebsch_jax.integrate: {where}step 0 of {n_steps}: {what}. The member made no step (its states are "
            "NaN). "
            "Run integrate on this member's values outside jit/vmap to have the argument at fault named."
        )
    if code == Status.ENERGY_JUMP:
        return (
            f"clebsch_jax.integrate: {where}step {step} of {n_steps} (t = {t:.6g}): {what} (residual "
            f"{residual:.3e}). Later states are marked invalid (NaN). Check the model for a singularity "
            "near the state before this step, or try a smaller dt (one that resolves the motion there); "
            "integrate(..., check_energy=False) accepts the step."
        )
    if code == Status.OFF_MANIFOLD:
        return (
            f"clebsch_jax.integrate: {where}step 0 of {n_steps} (t = {t:.6g}): {what}. Later states are marked "
            'invalid (NaN). Use a method whose steps keep Q on M (e.g. scheme="midpoint"), or, on a matrix group '
            "with L(xi, Q) = Q X(xi), the derivative map clebsch_jax.cayley or clebsch_jax.exponential; run "
            "integrate on this member's values outside jit/vmap to have it explained."
        )
    if code == Status.FIRST_STEP:
        return (
            f"clebsch_jax.integrate: {where}step 0 of {n_steps} (t = {t:.6g}): {what} (residual {residual:.3e}). "
            "Later states are marked invalid (NaN). Try a smaller dt; integrate(..., check_energy=False) "
            "accepts the step."
        )
    if scheme == "gauss":
        made = f"{iterations} fixed-point sweeps; the cap is 5 x max_newton_iterations sweeps per step"
    elif jacobians is None:
        made = f"{iterations} Newton updates" + (
            f" in all over the step's {solves} sub-step solves" if solves > 1 else ""
        )
    else:
        # max_newton_iterations counts Newton iterations with a fresh Jacobian; each is followed by
        # chord updates with it, so the updates can be many more
        over = f" in all over the step's {solves} sub-step solves" if solves > 1 else ""
        made = (
            f"{jacobians} Newton iterations{over} (max_newton_iterations counts these: Jacobians formed"
            f"{', per solve' if solves > 1 else ''}), with {iterations} updates"
        )
    singular = (
        " A Jacobian singular from the start may be a Lagrangian degenerate in xi, which integrate refuses "
        "or gauges before compiling but not under jit/vmap: for one that sees xi only through L_xi Q, build "
        "the system with clebsch_jax.gauge_isotropy."
        if code == Status.SINGULAR
        else ""
    )
    return (
        f"clebsch_jax.integrate: {where}step {step} of {n_steps} (t = {t:.6g}): {what} "
        f"(residual {residual:.3e} after {made}). Later states are "
        "marked invalid (NaN). Try a smaller dt, a larger max_newton_iterations, or "
        f"throw=False to inspect the partial solution.{singular}"
    )


def _member_of(index: tuple):
    """A failing member's index as `IntegrationError.member` gives it: None for a single run, an
    int for one batch axis, a tuple under nested `vmap`."""
    if not index:
        return None
    return index[0] if len(index) == 1 else index


_MEMBER_OFFSET = contextvars.ContextVar("clebsch_jax_member_offset", default=None)


@contextlib.contextmanager
def member_offset(offset):
    """While tracing inside this context, a failure found by `integrate(..., throw=True)` under
    `jax.vmap` names its member plus `offset` (an int or a traced integer): for an evaluator that
    batches members in chunks (`clebsch_jax.batch`), whose `vmap` sees one chunk at a time."""
    token = _MEMBER_OFFSET.set(offset)
    try:
        yield
    finally:
        _MEMBER_OFFSET.reset(token)


_RAISED = threading.local()
_RAISED_ANYWHERE: list = [None]  # XLA may run a host callback on a thread of its own


COMPILED_HINT = (
    " (Raised inside a compiled program, where JAX reports it as jax.errors.JaxRuntimeError with this "
    "message. To read the statuses instead, pass throw=False and read Solution.result, .failed_step and "
    ".stats.status, or call Solution.raise_if_failed() outside jax.jit; clebsch_jax.batch called outside "
    "jax.jit raises the IntegrationError itself.)"
)


def raised_in_callback(err: BaseException) -> "IntegrationError | None":
    """The `IntegrationError` that a host callback of `integrate(..., throw=True)` raised inside a
    compiled program, if `err` (JAX's `JaxRuntimeError`) reports it; else None. An evaluator that
    calls the compiled program itself (`clebsch_jax.batch`) re-raises it, with its member,
    step and status, in place of JAX's error."""
    found = getattr(_RAISED, "error", None) or _RAISED_ANYWHERE[0]
    if found is not None and str(found) + COMPILED_HINT in str(err):
        return found
    return None


class _HideOurCallbackErrors(logging.Filter):
    """JAX logs an exception raised in a host callback, with its traceback, before it re-raises
    it: for an `IntegrationError` that is the error twice (its message is in what is raised)."""

    def filter(self, record):
        return not (record.exc_info and isinstance(record.exc_info[1], IntegrationError))


for _name in ("jax._src.debugging", "jax._src.callback"):
    logging.getLogger(_name).addFilter(_HideOurCallbackErrors())


def _host_check(
    result, failed_step, iterations, residual, t, n_steps, jacobians, offset, batched, compiled, scheme=None, solves=1
):
    result = np.asarray(result)
    if not np.any(result != Status.SUCCESS):
        return
    if batched:
        member = tuple(int(i) for i in np.argwhere(result != Status.SUCCESS)[0])
    else:
        member = ()
    pick = (lambda a: np.asarray(a)[member]) if member else np.asarray
    code, step = int(pick(result)), int(pick(failed_step))
    named = (member[0] + int(np.asarray(offset)),) + member[1:] if member else member
    msg = failure_message(
        code,
        step,
        int(np.asarray(n_steps).ravel()[0]),
        float(pick(t)),
        int(pick(iterations)),
        float(pick(residual)),
        named or None,
        scheme,
        1 if code == Status.LEGENDRE else solves,
        int(pick(jacobians)),
    )
    error = IntegrationError(msg, member=_member_of(named), step=step, status=Status(code))
    if not compiled:
        raise error
    _RAISED.error = _RAISED_ANYWHERE[0] = error
    raise IntegrationError(msg + COMPILED_HINT, member=error.member, step=step, status=error.status)


def _traced_checker(scheme, solves):
    """The end-of-run check as a function of traced values, for a method's `scheme` and
    `solves` per step (what its failure message says). Called with concrete values (the
    batching rule under an eager `jax.vmap`), it raises at once; else from a host callback."""

    def host(*args, batched):
        concrete = not any(isinstance(a, jax.core.Tracer) for a in args)
        if concrete:
            _host_check(*args, batched=batched, compiled=False, scheme=scheme, solves=solves)
        else:
            jax.debug.callback(
                lambda *a: _host_check(*a, batched=batched, compiled=True, scheme=scheme, solves=solves), *args
            )

    @jax.custom_batching.custom_vmap
    def check(result, failed_step, iterations, residual, t, n_steps, jacobians):
        host(result, failed_step, iterations, residual, t, n_steps, jacobians, jnp.asarray(0), batched=False)
        return result

    @check.def_vmap
    def check_vmap(axis_size, in_batched, *args):
        args = [a if b else jnp.broadcast_to(a, (axis_size,) + jnp.shape(a)) for a, b in zip(args, in_batched)]
        offset = _MEMBER_OFFSET.get()
        host(*args, jnp.asarray(0 if offset is None else offset), batched=True)
        return args[0], True

    return check


def check_traced(sol: Solution) -> jax.Array:
    """Insert the end-of-run failure check into a traced computation (jit/vmap).

    A failure raises `IntegrationError` (under `jax.vmap` naming the member); inside a
    compiled program it is raised from a host callback, and JAX reports it as its
    `JaxRuntimeError` with the same message (`COMPILED_HINT` says how to read the statuses).
    Inside `collecting_checks` no check is inserted: its arguments are collected instead.
    """
    stats_at = lambda s: jnp.take(s, jnp.clip(sol.failed_step, 0, s.shape[-1] - 1), axis=-1)
    is_nodal = sol.result == Status.LEGENDRE
    iters = jnp.where(is_nodal, stats_at(sol.nodal_stats.iterations), stats_at(sol.stats.iterations))
    res = jnp.where(is_nodal, stats_at(sol.nodal_stats.residual_norm), stats_at(sol.stats.residual_norm))
    matrices = jnp.where(is_nodal, stats_at(sol.nodal_stats.jacobians), stats_at(sol.stats.jacobians))
    t = stats_at(sol.ts)
    n_steps = jnp.asarray(sol.ts.shape[-1] - 1)
    args = jax.lax.stop_gradient((sol.result, sol.failed_step, iters, res, t, n_steps, matrices))
    collected = _COLLECTED.get()
    if collected is not None and collected[0] == _trace_state():  # the collecting trace, not one inside it
        collected[1].append(CollectedCheck(sol.scheme, sol.solves_per_step, args))
        return sol.result
    return _traced_checker(sol.scheme, sol.solves_per_step)(*args)


class CollectedCheck(NamedTuple):
    """An end-of-run check of `integrate(..., throw=True)` met inside `collecting_checks`: what
    its message says (`scheme`, `solves` per step) and its traced arguments `args` (result,
    failed step, the failed step's iterations, residual norm and time, the number of steps,
    the Jacobians made)."""

    scheme: Any
    solves: int
    args: tuple


_COLLECTED: contextvars.ContextVar = contextvars.ContextVar("clebsch_jax_collected_checks", default=None)


def _trace_state():
    import jax.extend.core as jex

    return jex.get_opaque_trace_state(convention="flax")


@contextlib.contextmanager
def collecting_checks():
    """Within this context (in this thread), `integrate(..., throw=True)` on values of the
    trace the context is entered in does not insert its end-of-run check into the trace (a
    host callback, which a native kernel cannot make): it appends a `CollectedCheck` to the
    list this yields, for a caller that makes the check's arguments outputs of its program and
    checks them on the host after the run (`raise_collected`: `clebsch_jax.batch` on a native
    kernel). Calls inside a trace of their own (a `jax.jit`, `vmap` or `scan` inside the
    traced function) insert their check as always: JAX may keep such a trace and reuse it
    outside the context."""
    found: list = []
    token = _COLLECTED.set((_trace_state(), found))
    try:
        yield found
    finally:
        _COLLECTED.reset(token)


def raise_collected(checks: list, values: list) -> None:
    """Raise the `IntegrationError` that the checks of `collecting_checks` would have raised
    under `jax.vmap`: `values[i]` holds the arguments of `checks[i]` computed for every member
    (a leading member axis); the first check with a failed member names its first failed
    member, its step and status."""
    for check, args in zip(checks, values):
        args = [np.asarray(a) for a in args]
        _host_check(*args, np.asarray(0), batched=True, compiled=False, scheme=check.scheme, solves=check.solves)
