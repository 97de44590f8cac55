"""`integrate`, the single entry point: validate → choose a stepper → march.

Its arguments are checked and the stepper chosen by `clebsch_jax.march.arguments` (`prepare`);
here the march is run (`scan.march` traced, `scan.march_chunked` on concrete values), continued
from a `march_state`, checked after it (the first step on the manifold) and its failures raised.
`check_member` and `recording_calls` serve the batch callers that march members traced."""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..core.isotropy import check_initial_momentum
from ..core.jit import filter_jit
from ..core.manifold_checks import check_first_step, first_step_may_leave
from ..core.system import ClebschSystem
from ..core.validation import any_traced, float_array
from ..steppers.base import AbstractStepper
from ..steppers.choose import choose_method
from ..steppers.composition import StepPlan, plan_of
from .accuracy import plan_for_call, require_step
from .arguments import prepare, warn_if_remade
from .arguments import prepared_method, solution_bytes_per_step  # noqa: F401  (importable from here as before)
from .carry import start
from .scan import march, march_chunked
from .solution import Solution, check_traced

__all__ = ["integrate", "step_plan"]


def step_plan(
    system: ClebschSystem, scheme: str | None = None, order=None, composition=None, *, Q0=None, xi0=None
) -> StepPlan:
    """The `StepPlan` `integrate` runs for these arguments: its sub-steps and its facts
    (`order`, `symmetric`, `symplectic`, `name`, `solves_per_step`). Given `Q0` and `xi0` it
    is the plan of `integrate(system, Q0, xi0, ...)`, reduced march included; without them,
    of the full march (the default can then differ: a system with a potential whose reduced
    march applies runs the reduced left step paired with its adjoint, not the midpoint
    principle)."""
    if Q0 is not None:
        Q0, xi0 = float_array(Q0, "Q0"), float_array(xi0, "xi0")
    return plan_of(choose_method(system, Q0, xi0, scheme=scheme, order=order, composition=composition), system)


_march_jit = filter_jit(march)


def integrate(
    system: ClebschSystem,
    Q0,
    xi0,
    *,
    dt=None,
    n_steps: int | None = None,
    P0=None,
    t0=0.0,
    method: AbstractStepper | None = None,
    scheme: str | None = None,
    reduce="auto",
    need_P: bool = False,
    reconstruct: bool = True,
    rtol: float = 0.0,
    atol: float = 0.0,
    max_newton_iterations: int = 20,
    jacobian: str = "dense",
    order: int | None = None,
    composition=None,
    throw: bool = True,
    check_energy: bool = True,
    march_state=None,
    backend: str = "auto",
    t_final=None,
    accuracy=None,
) -> Solution:
    r"""March the discrete Clebsch equations (Lemma 20) of `system` from $(Q^0, \xi^0)$.

    The method is a stepper (`clebsch_jax.steppers`): pass one as `method=`, or let the
    options below choose it (`clebsch_jax.steppers.choose`: the rules are written there once).

    - **Full step** (`FullStep`, `form="full"`): each step solves, by Newton's method with a
      forward-mode Jacobian, the stationarity conditions of the discrete action
      (`clebsch_jax.discrete_action`) for $(\xi^n, P^n, Q^{n+1})$ — obtained with `jax.grad`,
      nothing model-specific written by hand — as a symplectic map
      $(Q^n, p^n) \mapsto (Q^{n+1}, p^{n+1})$.
    - **Reduced step** (`ReducedStep`, `form="reduced"`, Theorem 27 / Corollary 29): when the
      velocity map is right multiplication on a matrix group, closed (Theorem 12), and the
      derivative map is of Definition 25's form, Q and P are eliminated and each step solves
      only for $\xi^n$ (dim V unknowns) from the body momentum $\mu^n$. Same trajectory, far
      fewer unknowns.
    - **Gauss–Legendre** (`GaussLegendre`): the s-stage partitioned Runge–Kutta discretisation
      of the Clebsch principle, order 2s up to 16, solved by fixed-point sweeps.
    - **Compositions** (`SymmetricPair`, `Composed`) of the first two.

    **Arguments:**

    - `system`: a `ClebschSystem`.
    - `Q0`: initial configuration $Q^0$, any shape the system's maps accept.
    - `xi0`: initial velocity $\xi^0$. Unless `P0` is given, the initial multiplier is the
      minimum-norm solution of $\delta l/\delta\xi(\xi^0, Q^0) = -P^0 \diamond Q^0$
      (`initial_multiplier`). With `P0`, `xi0` only fixes the shape of $V$ and seeds the
      nodal-velocity solve. Without it, `xi0` is taken as the physical velocity
      $\mathcal L_{\xi^0}Q^0$: where the velocity map has an isotropy at $Q^0$ (directions k with
      $\mathcal L_k Q^0 = 0$, as ξ ∥ q on a sphere moved by ξ × q), its component there is
      replaced by the one whose momentum has a multiplier (dropped, for $l = \frac12|\xi|^2$ or a
      Lagrangian of $\mathcal L_\xi Q$ alone), with a warning; `Solution.xi[0]` is the velocity
      used (`clebsch_jax.core.isotropy.physical_velocity`). A Lagrangian that does not see the
      isotropy (written with the physical velocities $\mathcal L_\xi Q$) is accepted as written:
      the engine adds the gauge term $\frac w2|\Pi_{\ker}\xi|^2$, which vanishes along solutions
      (`clebsch_jax.gauge_isotropy`), and `Solution.isotropy` says so. Under `jit`/`vmap` over
      `Q0`/`xi0` too: the gauge's rank is then decided at trace time on a concrete example
      (`clebsch_jax.core.model_checks.traced_isotropy`), the weight and ξ⁰'s physical part
      (`clebsch_jax.core.isotropy.physical_part`, no warning) computed in the program, and a
      member of another isotropy reports `Status.INVALID_INPUT`; not for systems whose own arrays
      are traced.
    - `dt`: time step (> 0). `n_steps`: number of steps (a Python int >= 1). Both required,
      unless `t_final` and `accuracy` choose them.
    - `t_final`, `accuracy`: instead of `dt`, `n_steps` and the method (`method`, `scheme`,
      `order`, `composition`, each refused with them): the run ends at `t_final` with a relative
      error of at most `accuracy` there, by the plan of `clebsch_jax.choose_step` (a short pilot on
      this system and state picks the method and step of least predicted work; the error measure,
      the model and its limits are in `clebsch_jax.march.accuracy`). `Solution.accuracy_plan`
      records the plan. Concrete arguments only (the pilot runs).
    - `P0`: optional initial multiplier (the canonical momentum at $Q^0$), shape of `Q0`.
    - `t0`: initial time (only used for `Solution.ts`).
    - `method`: a stepper, e.g. `clebsch_jax.Composed(clebsch_jax.SymmetricPair(
      clebsch_jax.FullStep()), clebsch_jax.KAHAN_LI_8)`. With it the options below, which
      describe a method, must stay at their defaults (they are the stepper's fields).
    - `scheme`: None (default): a symmetric second-order method chosen for the system
      (`clebsch_jax.steppers.choose`, rule 0: the left principle where it is symmetric already,
      as for the rigid body with Cayley; the reduced left step paired with its adjoint when the
      system has a potential and reduces, as the heavy top; else the midpoint principle).
      `"left"` (Definition 19), `"right"` (the adjoint principle of
      Remark 22), `"midpoint"` (l and the velocity map evaluated at the midpoint of each step:
      symmetric and second order also with a potential; full march only; the default for
      systems built with `degenerate=True`), or `"gauss"` (Gauss–Legendre of `order`, default
      2; each step is one fixed-point solve of its stages, `stats.iterations` counts sweeps, at
      most 5 × `max_newton_iterations`; a step too large for the iteration fails with
      `Status.DIVERGED`. For a degenerate l it must be affine in ξ, as for point vortices).
    - `reduce`: `"auto"` (default) uses the reduced step when it applies and `need_P` is
      False; `True` forces it (a `ValueError` says why when it does not apply); `False`
      forces the full step. `Solution.form` says which ran.
    - `need_P`: the caller needs the multipliers $P^n$. With `reduce="auto"` this selects the
      full step; with `reduce=True` the reduced step reconstructs the minimum-norm $P^n$.
    - `reconstruct`: reduced step only: reconstruct $Q^n$ (default). With False and an l that
      does not depend on Q, `Solution.Q` is None and Q is never computed.
    - `rtol`, `atol`, `max_newton_iterations`: the root finder's stopping rule (`Newton`). The
      default 0, 0 iterates to round-off, which exact conservation of momenta needs.
    - `jacobian`: `"dense"` (default): `Newton` with the exact Jacobian. `"blocks"`: for N
      interacting particles — `Q0` and `xi0` have a leading axis of length N — `BlockNewton`,
      chord iterations with the lumped block-diagonal Jacobian, converged to the same
      round-off. With `scheme="gauss"` and a degenerate l: the constraint bracket matrix whole
      or lumped per particle (exact for point vortices).
    - `order`: None (default) runs the default method (order 2), or the named `scheme` as it
      is (order 1, or 2 when it is symmetric: midpoint, or left/right with a symmetric
      derivative map and no potential). 2, 4, 6 or 8
      makes each step a symmetric composition of sub-steps (`SymmetricPair`, `Composed`). With
      `scheme="gauss"`: any even order up to 16.
    - `composition`: a `Composition` (or the name of one in `clebsch_jax.COMPOSITIONS`)
      instead of the default coefficients of its order.
    - `throw`: if True (default) a failed step raises `IntegrationError` once, at the end,
      naming the step (and batch member under `jax.vmap`), the reason, its `Status` and what to
      try; the error carries them as `member`, `step` and `status`. So it does under `jax.grad`,
      `jax.jacfwd`, `jax.vmap` and `clebsch_jax.batch` (whose members are named by their index
      in the batch, whatever its chunks). Inside a program compiled by `jax.jit` it is raised
      from a host callback, and JAX reports it as `jax.errors.JaxRuntimeError`, whose message
      holds the `IntegrationError`'s and says how to read the statuses instead. If False,
      failures are only recorded in the `Solution` (`result`, `failed_step`, per-step
      `stats.status`, `valid`); call `Solution.raise_if_failed()` later.
    - `check_energy`: if True (default) every step is checked by a per-step error indicator, its
      relative energy change: step n fails with `Status.ENERGY_JUMP` when
      $|E^{n+1} - E^n|$ exceeds `ENERGY_STEP_RTOL` (0.1) — or, when `check_energy` is a positive
      number, that number — times the energy's size so far,
      $\max_{k \le n} |\langle\delta l/\delta\xi, \xi^k\rangle| + |l(\xi^k, Q^k)|$
      (`clebsch_jax.march.scan`): a converged step across a singularity of the model, or one far
      too large for the motion there, which would otherwise pass as a success. It costs one
      evaluation of l and its gradient per node; False switches it off.
      Step 0, whose energy change can be small next to the terms at the start, is also checked
      against two half steps made once at the start
      (by the march's own loop and step, before its steps, or on the native backend by a call
      of its compiled chunk with Δt/2. So on concrete runs, under `jit`/`vmap`, where a failure
      is reported as any traced failure is, and in `clebsch_jax.sweep`'s first chunk; not when
      continuing from `march_state`):
      it fails with `Status.FIRST_STEP` when they do not converge, or when their node differs
      from step 0's by more than `FIRST_STEP_RTOL` (0.5) of their own displacement in both Q and
      the momentum map (a spurious root of the step equations).
      Not made for degenerate systems (no nodal velocities).

    - `march_state`: None (default), or the `Solution.march_state` of an earlier run of the same
      system with the same method, options and shapes, to continue that run: the steps then start
      from its stepper state, guesses and predictor history, so that chunks of a long run make
      exactly the steps of one unbroken run (without it a continued run restarts its guesses,
      which changes the round-off and the Newton updates, and near a method's step-size limit
      can change whether a step converges). `continue_from` passes it. `Q0`, `xi0` and `P0` are
      still required (they are node 0 of this `Solution`; pass `continue_from`'s), and the
      energy check's history and the first-step check start afresh.

    - `backend`: `"auto"` (default), `"native"` or `"xla"`: what makes the steps of a concrete
      call (`clebsch_jax.march.native_chunk`). `"native"`: a kernel compiled from the step's
      program by LLVM (`clebsch_jax.native`), which runs the chunk's steps without XLA's cost
      per operation; `"xla"`: XLA's compiled chunk. They make the same steps and give the same
      `Solution`, up to round-off where XLA's transcendental functions differ from libm's.
      `"auto"` runs the native kernel wherever it applies (on the CPU, with concrete arguments,
      for a step the translation covers) and XLA elsewhere — under `jit`, `vmap` or `grad`, for
      a primitive the translation does not cover, without llvmlite — saying once why (a
      `clebsch_jax.native.NativeFallbackWarning`); `"native"` raises a `ValueError` with the
      reason there. Inside `clebsch_jax.batch`, `batch`'s own `backend` decides for the whole
      batched function, this call included: this one is not consulted.

    **Returns:** a `Solution`, with the method's facts (`form`, `scheme`, `order`, `method`).

    Compilation: with concrete arguments the march runs as compiled chunks of steps
    (`clebsch_jax.march.scan.march_chunked`): a later call on the same system and shapes
    compiles nothing for a new `n_steps`, `dt` or parameter values held as array leaves (the
    built-in models'). Before compiling, the model is checked at the initial point, and after
    the march its first step is checked to stay on the configuration manifold
    (`clebsch_jax.core.model_checks`).

    Transformations: works under `jax.jit` (`n_steps`, `method` and the options are static)
    and `jax.vmap` over `Q0`, `xi0`, `P0`, `dt` and array parameters inside the system.
    There the values are unknown before compiling: the shapes and the maps' output types are
    checked as above, and each member's values at step 0 inside the program (`dt`, `Q0`,
    `xi0`, `P0` and the parameters finite, `Q0` on the manifold through `check_Q.traced`, l
    and the velocity map finite and linear in ξ, `march.carry.velocity_map_linear`; a failing
    member reports `Status.INVALID_INPUT`), and the first step on the manifold where a step can
    leave it (`traced_first_step_check`: `check_first_step`'s test in the program, for a system
    with a `check_Q`; on a matrix group read off the velocity map the step's $Q_0^{-1}Q_1$
    against the group, elsewhere `check_Q.traced` at $Q_1$, and nothing for a `check_Q`
    without a traced form; a failing member reports `Status.OFF_MANIFOLD` at step 0). What
    needs values is not checked: the Lagrangian by autodiff (`check_model`: a singular
    Hessian), `Q0` against `check_Q` and the velocity map's group. The memory the `Solution`s of
    all members of the caller's `vmap` need is estimated (`arguments.vmapped_members`) and,
    beyond the machine's, said in a warning, not refused: XLA keeps only what the caller's
    program uses. `clebsch_jax.sweep`, and
    `clebsch_jax.batch` called on concrete arrays, make those checks on their first member
    before compiling (`check_member`), and estimate their memory.
    Derivatives (forward and reverse mode) flow through the root finders by implicit
    differentiation (`clebsch_jax.roots.implicit`).
    """
    from ..native import check_backend, warn_once

    backend = check_backend(backend)
    if accuracy is not None or t_final is not None:  # the method and step chosen by a pilot
        given = dict(dt=dt, n_steps=n_steps, method=method, scheme=scheme, order=order, composition=composition)
        given.update(march_state=march_state, reduce=reduce, need_P=need_P, reconstruct=reconstruct, rtol=rtol)
        given.update(atol=atol, max_newton_iterations=max_newton_iterations, jacobian=jacobian)
        plan = plan_for_call(
            system, Q0, xi0, given, t_final=t_final, accuracy=accuracy, t0=t0, P0=P0, check_energy=check_energy,
            backend=backend,
        )  # fmt: skip
        sol = integrate(
            system, Q0, xi0, P0=P0, t0=t0, throw=throw, check_energy=check_energy, backend=backend,
            **plan.integrate_options(),
        )  # fmt: skip
        return dataclasses.replace(sol, accuracy_plan=plan)
    require_step(dt, n_steps)
    user_system = system
    given = (system, Q0, xi0, P0, dt, t0)
    stepper, (Q0, xi0, P0, dt, t0, closes), n_steps, system = prepare(
        system,
        Q0,
        xi0,
        dt=dt,
        n_steps=n_steps,
        P0=P0,
        t0=t0,
        method=method,
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
        check_energy=check_energy,
    )
    state = None if march_state is None else _checked_march_state(stepper, system, Q0, xi0, P0, dt, march_state)
    if closes or any_traced(system, Q0, xi0, P0, dt, t0):
        # one scan, in the caller's program (differentiable by it); values unknown until now
        # are checked per member
        if backend != "xla" and not _CALLER_BACKEND.get():
            why = (
                "its arguments are traced (inside jit, vmap or grad)"
                if not closes
                else "a map closes over a traced value"
            )
            if backend == "native":
                raise ValueError(f"backend='native': {why}; the native kernel runs concrete calls only.")
            warn_once(why, what="integrate's march", stacklevel=3)
        calls = _RECORDED.get()
        if calls is not None and not closes:
            options = dict(method=method, scheme=scheme, reduce=reduce, need_P=need_P, reconstruct=reconstruct)
            options.update(rtol=rtol, atol=atol, max_newton_iterations=max_newton_iterations, jacobian=jacobian)
            calls.append(RecordedCall(given, dict(options, order=order, composition=composition)))
        sol = _march_jit(
            stepper,
            system,
            Q0,
            xi0,
            P0,
            dt,
            t0,
            n_steps,
            check_energy=check_energy,
            check_inputs=True,
            march_state=state,
        )
    else:  # programs reused for any n_steps
        warn_if_remade(user_system)
        sol = march_chunked(
            stepper, system, Q0, xi0, P0, dt, t0, n_steps, check_energy=check_energy, march_state=state, backend=backend
        )
        if state is not None:
            _check_continues(sol, Q0)
        if sol.Q is not None and not any_traced(sol.Q):  # traced when the maps close over tracers
            # on the host: indexing the device array would compile a slice for each n_steps
            check_first_step(system, sol.method, Q0, xi0, np.asarray(sol.Q)[1])
    if throw:
        seen = {name: getattr(sol, name) for name in _CHECKED}
        if not any_traced(seen):  # concrete: read as they are (stop_gradient would dispatch per field)
            sol.raise_if_failed()
            return sol
        # under an eager jax.grad/jacfwd the values are known: stop_gradient gives them
        seen = jax.lax.stop_gradient(seen)
        if any_traced(seen):
            sol = dataclasses.replace(sol, result=check_traced(sol))
        else:
            dataclasses.replace(sol, **seen).raise_if_failed()
    return sol


_CHECKED = ("result", "failed_step", "ts", "stats", "nodal_stats")
"""The fields of a `Solution` that `Solution.raise_if_failed` reads."""


def _checked_march_state(stepper, system, Q0, xi0, P0, dt, march_state):
    """`march_state`, after checking that it is one of this method on
    these shapes (the carry `start` would make, by `jax.eval_shape`: nothing is computed)."""
    expected = jax.eval_shape(lambda: start(stepper, system, Q0, xi0, P0, dt)[0])
    leaves, tree = jax.tree_util.tree_flatten(march_state)
    want, want_tree = jax.tree_util.tree_flatten(expected)
    describe = lambda xs: [(tuple(np.shape(x)), str(jnp.result_type(x))) for x in xs]
    if tree != want_tree or describe(leaves) != describe(want):
        raise ValueError(
            "march_state: expected the Solution.march_state of a run of this system with the same "
            f"method, options and shapes ({stepper.facts(system).name}); got one of another structure "
            "or shapes. Pass the march_state of the run being continued (cj.continue_from does), "
            "or leave it None to start afresh."
        )
    return march_state


def _check_continues(sol: Solution, Q0) -> None:
    """On concrete values: the march continued from `march_state` started at `Q0` (its node 0 is
    read off the state; a state taken from another node, e.g. of a `Solution` cut by hand, would
    continue from there)."""
    if sol.Q is None or any_traced(sol.Q, Q0):
        return
    start, given = np.asarray(sol.Q)[0], np.asarray(Q0)
    gap = float(np.max(np.abs(start - given)))
    if not gap <= 1e-12 * (1.0 + float(np.max(np.abs(given)))):
        raise ValueError(
            f"march_state: it is the march's state at another node than Q0 (they differ by {gap:.3g}); "
            "pass the march_state of the Solution whose last node is Q0 (cj.continue_from(system, sol) "
            "does), or march_state=None to start from Q0 afresh."
        )


class RecordedCall(NamedTuple):
    """A traced `integrate` call seen inside `recording_calls`: its arguments as given, `args` =
    (system, Q0, xi0, P0, dt, t0) (tracers of the caller's trace), and its other `options`."""

    args: tuple
    options: dict


_RECORDED: contextvars.ContextVar = contextvars.ContextVar("clebsch_jax_recorded_calls", default=None)


@contextlib.contextmanager
def recording_calls():
    """Within this context (in this thread), every `integrate` call on traced values whose maps
    close over no traced value is recorded (`RecordedCall`) in the list it yields: a caller
    that traces a function of one member (`clebsch_jax.batch`) can then evaluate those
    arguments for a concrete member and make the checks `integrate` skipped on them
    (`check_member`)."""
    calls: list = []
    token = _RECORDED.set(calls)
    try:
        yield calls
    finally:
        _RECORDED.reset(token)


_CALLER_BACKEND: contextvars.ContextVar = contextvars.ContextVar("clebsch_jax_caller_backend", default=False)


@contextlib.contextmanager
def caller_backend():
    """Within this context (in this thread), `integrate` calls on traced values are traced into a
    program whose backend the caller chose as a whole (`clebsch_jax.batch`: a native kernel
    compiled from the trace, or XLA, having said why where "auto" could not run the kernel):
    they neither warn that their march runs with XLA nor refuse `backend="native"`."""
    token = _CALLER_BACKEND.set(True)
    try:
        yield
    finally:
        _CALLER_BACKEND.reset(token)


def check_member(system, Q0, xi0, *, configuration: bool = True, **options) -> ClebschSystem:
    """`integrate`'s checks of one member with concrete values, for callers that march it
    traced, where `integrate` itself cannot make them (`clebsch_jax.sweep` and
    `clebsch_jax.batch` call it on their first member before compiling the batch). Raises the
    errors and emits the warnings `integrate` would for the same call: everything checked
    before the march (`prepared_method`: the arguments, the maps' shapes, `check_configuration`,
    `check_model`, `check_group_configuration`), and, when the first step could leave the
    configuration manifold (`first_step_may_leave`: not for the built-in models with their
    default derivative maps), `check_first_step` on one step of this member, marched alone
    (one compiled step). Without `P0` the member starts from the multiplier of `xi0` as given:
    a momentum with no multiplier is reported (`check_initial_momentum`). The keyword options
    are `integrate`'s; `n_steps` is not used (the caller checks the size of its own run). Skipped where a value is traced or a map closes
    over a traced value. `configuration=False` leaves out `check_configuration` (a sweep checks
    every member's Q0 at once). Returns the system `integrate` would march: `system`, or with
    its isotropy gauge fixed (`clebsch_jax.gauge_isotropy`; a sweep gives every member that gauge)."""
    options = {key: value for key, value in options.items() if key not in ("n_steps", "throw")}
    P0 = options.pop("P0", None)
    # the isotropy's adjustment of xi0 (and its warning) is integrate's, when P0 is not given:
    # a batch marches xi0 as given, so the checks see it as given
    # zeros made on the host: `jnp.zeros` would compile two XLA programs on a process's first call
    given = P0 if P0 is not None else np.zeros(np.shape(Q0))
    stepper, (Q0, xi0, _, dt, t0, closes), _, system = prepare(
        system, Q0, xi0, n_steps=1, P0=given, configuration=configuration, **options
    )
    if closes or any_traced(system, Q0, xi0, dt, t0, P0):
        return system
    if P0 is None:  # the member's P0 is derived from xi0 as given: say if its momentum has none
        check_initial_momentum(system, Q0, xi0, as_given=True, stacklevel=3)
    if not first_step_may_leave(system, Q0, xi0):
        return system
    P0 = None if P0 is None else float_array(P0, "P0")
    sol = march_chunked(stepper, system, Q0, xi0, P0, dt, t0, 1, check_energy=False)
    if sol.Q is not None and not any_traced(sol.Q):
        check_first_step(system, sol.method, Q0, xi0, np.asarray(sol.Q)[1])
    return system
