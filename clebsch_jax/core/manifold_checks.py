r"""Checks that the configurations stay on their manifold: before marching, $Q^0$ in the matrix
group the velocity map acts on by right multiplication (`check_group_configuration`, a warning);
after it, the first step the march made (`check_first_step`, and `first_step_may_leave`, whether
there is anything for it to check), or, in a traced march, the same test inside the program
(`traced_first_step_check`). Whether a step stays on the manifold depends on the principle as
well as on the derivative map, so the step that ran is looked at, not the map alone.
"""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np

from . import linalg
from .derivative_maps import MatrixGroupDifference
from .validation import any_traced, runnable_check

__all__ = [
    "check_first_step",
    "first_step_may_leave",
    "traced_first_step_check",
    "check_group_configuration",
    "GROUP_RTOL",
    "GROUP_CHECK_MAX_DIM",
]

SQRT_TOL = 0.25
r"""`_log` takes square roots of $g$ until $|g - I| \le$ this, then sums 60 terms of the series."""

GROUP_RTOL = 1e-8
r"""A step leaves the group when the component of $\log((Q^0)^{-1}Q^1)$ outside the algebra $X(V)$
is more than this fraction of it (round-off for a step that stays on the group; of the order of
$\Delta t|\xi|$ for the forward difference with the left principle)."""

GROUP_CHECK_MAX_DIM = 64
"""`check_group_configuration` and the first step's checks look at algebras of at most this many
dimensions (so(n) up to n = 11, se(n) up to n = 10): they form their basis and its commutators.
Above it, the first step is tested by the system's `check_Q` alone."""


def check_first_step(system, method: str, Q0, xi0, Q1) -> None:
    r"""After a march: did its first step, $Q^0 \to Q^1$, stay on the configuration manifold?

    Which principle keeps Q on M depends on the method that ran, not on the derivative map
    alone (the forward difference leaves SO(3) with the left principle, but with the midpoint
    principle the step is a Cayley transform and stays on it), so this looks at the step the
    march actually made:

    - the velocity map is right multiplication on a matrix group, $\mathcal L_\xi Q = Q X(\xi)$
      with $X(V)$ a Lie algebra (`clebsch_jax.discrete.matrix_group.matrix_group_basis`), and the
      derivative map is not of Definition 25's form (which keeps Q on the group by
      construction): $\log((Q^0)^{-1}Q^1)$ must lie in $X(V)$ to `GROUP_RTOL`. This measures the
      step's own defect whatever $Q^0$'s (a $Q^0$ that only just passes `check_Q` is not blamed
      on the step). A defect is a `ValueError` naming `derivative_map` when the system checks
      its configurations (`check_Q`), else a `UserWarning` (its configurations may then be any
      matrices: the step is allowed, but Q drifts off the group);
    - otherwise, when the system has a `check_Q`, it must accept $Q^1$ (`ValueError`).

    Skipped when `Q1` is not finite (a failed step is reported by the march) or traced."""
    if any_traced(Q0, Q1, system) or not np.all(np.isfinite(np.asarray(Q1))):
        return
    Q0, Q1 = np.asarray(Q0), np.asarray(Q1)
    checks = runnable_check(system, Q0) is not None
    test, basis = _first_step_test(system, Q0, xi0, checks)
    if test == GROUP:
        defect = _outside_algebra(np.linalg.solve(Q0, Q1), _off_algebra(basis))
        if not defect > GROUP_RTOL:
            return
        problem = system.check_Q(Q1) if checks else None
        how = (
            f"(Q0^-1 Q1 is not in the group of the algebra X(V) by which velocity_map moves Q: the part of "
            f"its logarithm outside X(V) is {defect:.1e} of it.)"
        )
    elif test == CHECK_Q or (test == STAYS and checks):
        # on a group a Definition 25 map keeps Q there: the system's own check still looks at Q1
        # (a cheap test that blames nothing on a step that stays)
        problem = system.check_Q(Q1)
        if not isinstance(problem, str):
            return
        how = ""
    else:
        return
    name = _name(system.derivative_map)
    fix = (
        f'Use a method whose steps keep Q on M (with {name}, e.g. scheme="midpoint"), or, on a matrix group '
        "with L(xi, Q) = Q X(xi), the derivative map clebsch_jax.cayley or clebsch_jax.exponential, which keep "
        "Q on the group with every principle (Definition 25); forward_difference is for vector spaces."
    )
    where = f"one step of {name} from Q0 ({method}) leaves the configuration manifold"
    if checks:
        found = f"{problem} " if isinstance(problem, str) else ""
        raise ValueError(f"derivative_map: {where}: {found}{how} {fix}".replace("  ", " "))
    warnings.warn(
        f"derivative_map: {where} on which velocity_map acts, a matrix group, so Q drifts off it at "
        f"every step {how} {fix} Give the system a check_Q to make this an error.",
        UserWarning,
        stacklevel=3,
    )  # the caller of integrate


def first_step_may_leave(system, Q0, xi0) -> bool:
    r"""Whether `check_first_step` has anything to look at for a march from $Q^0$ that a caller
    would have to make first (`sweep` and `batch` march their first member one step for it):
    False when there is nothing to check (no `check_Q` and no matrix group read off the velocity
    map), and False when the derivative map is of Definition 25's form (`MatrixGroupDifference`)
    on the group of a velocity map that is right multiplication by a closed algebra, whose steps
    $Q^0 \to Q^0\,\overline{\exp}(\Delta t\,X(\xi))$ stay in $Q^0 G$ by construction (the built-in
    SO(3) models with `cayley` or `exponential`). True otherwise, and False for traced values."""
    if any_traced(Q0, xi0, system):
        return False
    checks = runnable_check(system, Q0) is not None
    return _first_step_test(system, Q0, xi0, checks)[0] in (GROUP, CHECK_Q)


def traced_first_step_check(system, Q0, xi0):
    r"""`check_first_step` for a march whose values are traced (under the caller's `jax.jit` or
    `jax.vmap`, where it cannot raise): a function `(Q0, Q1) -> traced bool`, True where the
    first step left the manifold (`Status.OFF_MANIFOLD`), or None when there is nothing a
    traced test can find, so that the program does not grow. Decided at trace time from the
    maps and the shapes, as `first_step_may_leave` decides:

    - the velocity map is right multiplication by a closed algebra X(V) (at most
      `GROUP_CHECK_MAX_DIM` dimensions, not all of $\mathfrak{gl}(n)$) and the derivative map is
      not of Definition 25's form: `check_first_step`'s criterion, the part of
      $\log((Q^0)^{-1}Q^1)$ outside X(V) more than `GROUP_RTOL` of it, computed in the
      program (`_traced_log`) — when the system has a `check_Q`; without one
      `check_first_step` only warns, and nothing is checked here;
    - a derivative map of Definition 25's form on such a group keeps Q there: None;
    - otherwise the system's `check_Q` at $Q^1$ through its traced form `check_Q.traced(Q) ->
      bool` (as `models.check_rotation` has); a `check_Q` without one (NumPy on concrete
      values) cannot run in the program: None, the step is not checked.

    The test sees no derivatives (`jax.lax.stop_gradient`): it gates a status."""
    if system.check_Q is None:  # check_first_step would warn at most
        return None
    test, basis = _first_step_test(system, Q0, xi0, True)
    if test == GROUP:
        outside = _off_algebra(basis)
        if not np.max(np.abs(outside)) > 1e-12:  # X(V) is every matrix: no step leaves it
            return None
        return lambda Q0, Q1: _leaves_group(outside, *jax.lax.stop_gradient((Q0, Q1)))
    traced = getattr(system.check_Q, "traced", None)
    if test != CHECK_Q or traced is None:
        return None
    return lambda Q0, Q1: ~jnp.asarray(traced(jax.lax.stop_gradient(Q1)), bool)


GROUP, CHECK_Q, STAYS = "group", "check_Q", "stays"


def _first_step_test(system, Q0, xi0, checks: bool):
    r"""What the first step is tested by — one decision for `check_first_step`,
    `first_step_may_leave` and `traced_first_step_check`, from the maps and the shapes:
    (`GROUP`, basis) when the velocity map is right multiplication by a closed algebra X(V) (Q
    square, at most `GROUP_CHECK_MAX_DIM` dimensions) and the derivative map is not of
    Definition 25's form; (`STAYS`, basis) when it is (its steps stay in $Q^0 G$ by
    construction); (`CHECK_Q`, None) otherwise when the system checks its configurations
    (`checks`); (None, None) when there is nothing to test."""
    square = np.ndim(Q0) == 2 and np.shape(Q0)[0] == np.shape(Q0)[1]
    small = np.size(xi0) <= GROUP_CHECK_MAX_DIM
    basis = _group_basis(system, Q0, xi0) if square and small else None
    if basis is not None:
        return (STAYS if isinstance(system.derivative_map, MatrixGroupDifference) else GROUP), basis
    return (CHECK_Q, None) if checks else (None, None)


def _off_algebra(basis: np.ndarray) -> np.ndarray:
    """The orthogonal projector off span X(V) (the basis's matrices flattened)."""
    B = basis.reshape(basis.shape[0], -1).T
    return np.eye(B.shape[0]) - B @ np.linalg.pinv(B)


def _leaves_group(outside: np.ndarray, Q0, Q1):
    """`_outside_algebra(Q0⁻¹Q1) > GROUP_RTOL` in the program (`outside`: the projector off the
    algebra); False where Q1 is not finite (a failed step, reported as such)."""
    log = _traced_log(linalg.inv(Q0) @ Q1).reshape(-1)
    size = jnp.sqrt(jnp.sum(log**2))
    off = outside @ log
    return jnp.sqrt(jnp.sum(off**2)) > GROUP_RTOL * size


def check_group_configuration(system, Q0, xi0) -> None:
    r"""For a system without `check_Q` whose velocity map is right multiplication on a matrix
    group, $\mathcal L_\xi Q = Q X(\xi)$: warn when $Q^0$ is not in the group the engine reads off
    $X(V)$ (`clebsch_jax.discrete.matrix_group.matrix_group_basis`). Recognised: $X(V) \subset so(n)$
    (the group is in SO(n): $Q^0$ must be a rotation) and $X(V) \subset se(n-1)$ (last row zero,
    antisymmetric block: $Q^0$ a rigid motion, last row $(0, \dots, 0, 1)$). A `UserWarning`, not
    an error: the march is well defined on the orbit $Q^0 G$ of any invertible $Q^0$, but a user
    who wrote SO(3) meant a rotation. Skipped for traced values."""
    if system.check_Q is not None or any_traced(Q0, xi0, system.velocity_map):
        return
    Q = np.asarray(Q0)
    if Q.ndim != 2 or Q.shape[0] != Q.shape[1] or not np.all(np.isfinite(Q)):
        return
    if np.size(xi0) > GROUP_CHECK_MAX_DIM or np.shape(xi0) == Q.shape:
        # a large algebra (the fluid's gl(2N), whose basis and commutators would take gigabytes)
        # or ξ the matrix itself: not the small SO(n) or SE(n) this check is for
        return
    basis = _group_basis(system, Q0, xi0)
    if basis is None:
        return
    from ..models._rigid_body import check_rotation  # the models' rotation test (a layer above)

    size = max(float(np.max(np.abs(basis))), np.finfo(float).tiny)
    antisymmetric = lambda X: float(np.max(np.abs(X + np.swapaxes(X, -1, -2)))) <= 1e-12 * size
    n = Q.shape[0]
    if antisymmetric(basis):
        group, problem = f"SO({n})", check_rotation(Q)
    elif n > 1 and not np.any(basis[:, -1, :]) and antisymmetric(basis[:, :-1, :-1]):
        group = f"SE({n - 1})"
        last = np.zeros(n)
        last[-1] = 1.0
        problem = (
            f"its last row is {np.array2string(Q[-1], precision=4)}, not {np.array2string(last)}."
            if np.max(np.abs(Q[-1] - last)) > 1e-8
            else check_rotation(Q[:-1, :-1])
        )
    else:
        return
    if problem is None:
        return
    warnings.warn(
        f"Q0: velocity_map moves Q by right multiplication with the Lie algebra of {group}, but Q0 is "
        f"not in {group}: {problem} The march keeps Q in Q0 {group}. Give the system a check_Q (e.g. "
        "clebsch_jax.models.check_rotation) to make this an error.",
        UserWarning,
        stacklevel=5,
    )


def _name(fn) -> str:
    return getattr(fn, "name", None) or getattr(fn, "__name__", None) or type(fn).__name__


def _group_basis(system, Q0, xi0):
    """`clebsch_jax.discrete.matrix_group.matrix_group_basis` (imported here: the reduction sits
    above this module on the data path)."""
    from ..discrete.matrix_group import matrix_group_basis

    return matrix_group_basis(system, Q0, xi0)


def _outside_algebra(g: np.ndarray, outside: np.ndarray) -> float:
    """The part of log g off the algebra (`outside`: the projector off it, `_off_algebra`),
    relative to |log g| (0 when g = I): `_leaves_group`'s measure, on concrete values."""
    log = _log(g).reshape(-1)
    size = np.linalg.norm(log)
    return float(np.linalg.norm(outside @ log) / size) if size > 0 else 0.0


def _traced_log(g):
    """`_log` in the program: square roots (a loop of as many as it needs; Denman–Beavers in its
    product form, one inverse per iteration, `clebsch_jax.core.linalg.inv`: no LAPACK call) until
    |g − I| <= `SQRT_TOL`, then the same series (a loop of its terms)."""
    eye = jnp.eye(g.shape[0], dtype=g.dtype)
    big = lambda g: jnp.sqrt(jnp.sum((g - eye) ** 2)) > SQRT_TOL

    def db(_, c):  # M → I, Y → g^(1/2)
        M, Y = c
        M_inv = linalg.inv(M)
        return 0.5 * (eye + 0.5 * (M + M_inv)), 0.5 * Y @ (eye + M_inv)

    def root(c):  # scale: 2 to the number of roots taken (a float: no pow of mixed types)
        g, roots, scale = c
        return jax.lax.fori_loop(0, 30, db, (g, g))[1], roots + 1, 2.0 * scale

    start = (g, jnp.asarray(0, jnp.int32), jnp.asarray(1.0, g.dtype))
    g, _, scale = jax.lax.while_loop(lambda c: big(c[0]) & (c[1] < 30), root, start)
    A = g - eye

    def term(k, c):
        power, log = c
        power = power @ A
        return power, log + jnp.where(k % 2 == 0, -1.0, 1.0) / k * power

    return jax.lax.fori_loop(2, 61, term, (A, A))[1] * scale


def _log(g: np.ndarray) -> np.ndarray:
    """The principal matrix logarithm of g near the identity, by inverse scaling and squaring:
    Denman–Beavers square roots until |g − I| <= `SQRT_TOL`, then 60 terms of the series of
    log(I + A) (far below round-off at that size)."""
    eye = np.eye(g.shape[0])
    roots = 0
    while np.linalg.norm(g - eye) > SQRT_TOL and roots < 30:
        Y, Z = g, eye
        for _ in range(30):
            Y, Z = 0.5 * (Y + np.linalg.inv(Z)), 0.5 * (Z + np.linalg.inv(Y))
        g, roots = Y, roots + 1
    A = g - eye
    power, log = A, A.copy()
    for k in range(2, 61):
        power = power @ A
        log += (-1.0) ** (k + 1) / k * power
    return log * 2.0**roots
