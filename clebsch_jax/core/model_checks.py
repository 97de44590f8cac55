r"""Checks of the model a user wrote: `check_model` before marching, `check_first_step` after.

The shape checks of `integrate` say whether the three maps *run*; these say whether they
describe a Clebsch system the engine can march. Each looks at the concrete initial point
$(\xi^0, Q^0)$ by automatic differentiation and refuses a modelling error with a `ValueError`
naming the culprit, where otherwise it would surface later as a singular Newton Jacobian ("try
a smaller dt") or, worse, as a wrong answer:

- `lagrangian`: the Legendre map $\xi \mapsto \delta l/\delta\xi$ (Lemma 8) must be invertible
  at $(\xi^0, Q^0)$ unless the system is built with `degenerate=True`; a Lagrangian written
  `l(Q, xi)` instead of `l(xi, Q)` is recognised.
- `velocity_map`: $\xi \mapsto \mathcal L_\xi Q^0$ must be linear (Definition 1).
- `derivative_map` (`check_first_step`, on the first step the march made, since whether a step
  stays on the manifold depends on the principle as well as on the derivative map): on a matrix
  group acted on by right multiplication, or when the system checks its configurations
  (`ClebschSystem.check_Q`), the step must stay on the configuration manifold.

The checks of the configurations — `check_first_step`, `first_step_may_leave` and
`check_group_configuration` — are in `clebsch_jax.core.manifold_checks`, and importable from here.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .isotropy import IsotropyGauge, gauge_isotropy, kernel_basis, velocity_jacobian
from .jit import QUICK_COMPILE, filter_jit
from .manifold_checks import check_first_step, check_group_configuration, first_step_may_leave
from .validation import any_traced, is_traced

__all__ = [
    "check_model",
    "check_first_step",
    "first_step_may_leave",
    "check_group_configuration",
    "ModelFacts",
    "traced_isotropy",
]

SINGULAR_RTOL = 1e-14
"""A Hessian is singular when its smallest singular value is at most this times its largest.

Round-off level on purpose: the Hessian of a degenerate Lagrangian, computed by autodiff, has
its null singular values at the level of the float64 epsilon, while regular Lagrangians can be
legitimately ill-conditioned and still march (landmarks close together compared with the
kernel width: $K(Q)^{-1}$ with a large condition number). A looser threshold would refuse those."""

ZERO_RTOL = 1e-10
r"""A singular Hessian counts as zero (l linear in ξ) when its largest singular value is at most
this times $|l|/|\xi|^2 + |\nabla_\xi l|/|\xi|$, the size l's value and gradient at ξ⁰ give it."""

LINEAR_RTOL = 1e-8
r"""A velocity map is linear when $|\mathcal L_\xi Q - J\xi| \le$ this $\times (|\mathcal L_\xi Q| + |J||\xi|)$
at every probe ξ (round-off of a linear map is far below it, any genuine nonlinearity far above)."""


DENSE_CHECK_MAX = 400
r"""Above this many unknowns ξ, `check_model` forms no Hessian and no Jacobian (their size grows
like $(\dim V)^2$, their factorisation like $(\dim V)^3$): `_check_matrix_free` checks the
velocity map's linearity on the probes alone and the Legendre map through the system's
`inverse_legendre`, when it has one (else that check is skipped)."""

INVERSE_RTOL = 1e-8
r"""`inverse_legendre` passes when $|\nabla l(G(\mu)) - \mu| \le$ this $\times|\mu|$ at the probes."""


class ModelFacts(NamedTuple):
    r"""What `check_model` found at $(\xi^0, Q^0)$: `isotropy`, an orthonormal basis (dim V, k) of
    the kernel of $\xi \mapsto \mathcal L_\xi Q^0$ (`clebsch_jax.core.isotropy`), and `gauge`,
    whether l does not see that kernel (its Hessian and gradient in ξ vanish along it), so that
    `integrate` fixes the gauge (`gauge_isotropy`) instead of refusing a singular Hessian."""

    isotropy: np.ndarray
    gauge: bool


def check_model(system, Q0, xi0, dt) -> ModelFacts | None:
    r"""Refuse modelling errors of `system` at the initial point $(\xi^0, Q^0)$, before marching.

    Each refusal is a `ValueError` whose message starts with the argument at fault and says
    what is wrong and what to do:

    1. `lagrangian`: the Hessian $H$ of $\xi \mapsto l(\xi, Q^0)$ at $\xi^0$ must be nonsingular
       (smallest singular value above `SINGULAR_RTOL` times the largest), or the Legendre map of
       Lemma 8 is not invertible and the step equations have no unique solution — except along
       the **isotropy** K, the kernel of $\xi \mapsto \mathcal L_\xi Q^0$: when l does not see it
       ($HK = 0$ and $K^T\nabla_\xi l = 0$ to `ISOTROPY_LAG_RTOL`, as for a Lagrangian written with
       the physical velocities $\mathcal L_\xi Q$), at $Q^0$ and at a point moved from it along
       the velocity map (where the isotropy has moved too; looked for up to `ISOTROPY_MAX_DIM`
       components of ξ) the answer says `gauge` and `integrate` fixes
       the gauge (`clebsch_jax.core.isotropy`); then $H + wKK^T$ must be nonsingular. Skipped for
       `degenerate=True` (beyond the isotropy test). When $H = 0$ (to `ZERO_RTOL`) the message says
       l is linear in ξ (point vortices need `degenerate=True`); when l has a potential, ξ and Q
       have the same shape and l's Hessian in its *second* argument is nonsingular, it says l looks
       written as `l(Q, xi)`; otherwise it gives the rank of $H$ and a null direction.
    2. `velocity_map`: it must be finite at the probes below and its Jacobian at ξ⁰ too
       (NaN or inf there is refused); with $J$ the Jacobian of $\xi \mapsto \mathcal L_\xi Q^0$ at $\xi^0$,
       $\mathcal L_\xi Q^0 = J\xi$ to `LINEAR_RTOL` at $\xi^0$, at a fixed pseudo-random
       direction $d$ of $\xi^0$'s size (unit size if $\xi^0 = 0$) and at $2\xi^0 + d$: a map
       linear in ξ (Definition 1) passes, a nonlinear or affine one does not.
    (The derivative map is checked after the march, on its first step: `check_first_step`.)

    The derivatives are evaluated by one compiled program per system and shapes (`filter_jit`),
    the decisions made with NumPy on its results. The checks run only when `Q0`, `xi0`, `dt` and
    every array leaf of `system` are concrete: under `jax.jit` or `jax.vmap` they are skipped
    (as are the value checks of `clebsch_jax.core.validation`), and also when the user's
    functions close over traced values.

    **Arguments:** the system and the initial point as `integrate` validated them (`Q0`, `xi0`
    float arrays of shapes the maps accept, `dt` a positive scalar: only its being concrete
    matters).

    **Returns:** `ModelFacts` (None when the checks were skipped).
    """
    if any_traced(Q0, xi0, dt, system):
        return None
    direction = _direction(xi0)
    if np.size(xi0) > DENSE_CHECK_MAX:
        return _check_matrix_free(system, Q0, xi0, direction)
    found = _derivatives(system, Q0, xi0, direction)
    if any(is_traced(x) for x in found.values()):
        return None  # the user's functions close over traced values
    found = {key: np.asarray(value) for key, value in found.items()}
    xi = np.asarray(xi0)
    found["probes"] = np.stack([x.reshape(-1) for x in (xi, direction, 2.0 * xi + direction)])
    J = found["jacobian"]
    K = _isotropy(J, xi.size)
    # blind to the isotropy at Q0 and at a second point of its orbit: a Lagrangian degenerate along
    # a fixed direction that happens to be the isotropy of Q0 is not blind to it elsewhere
    gauge = _blind_to(K, found["hessian"], found["gradient"], xi)
    if gauge:
        moved = {key: np.asarray(value) for key, value in _moved_derivatives(system, Q0, xi0, direction).items()}
        moved_K = _isotropy(moved["jacobian"], xi.size)
        gauge = moved_K.shape[1] == K.shape[1] and _blind_to(moved_K, moved["hessian"], moved["gradient"], xi)
    try:
        if not system.degenerate:
            H = found["hessian"]
            if gauge:
                H = H + np.linalg.norm(H, 2) * K @ K.T
            _check_legendre_map(system, Q0, xi0, H, K, J)
        _check_linear(xi0, found)
    except _Traced:
        return None
    return ModelFacts(K, gauge)


def traced_isotropy(system, q_shape, xi_shape) -> tuple | None:
    r"""The isotropy gauge `integrate` fixes for `system` when its `Q0` and `xi0` are traced
    (under `jax.jit`/`jax.vmap`), decided at trace time from a concrete example: a fixed
    pseudo-random point $(\xi, Q)$ of those shapes, where `check_model` answers whether l does
    not see the isotropy of the velocity map (`ModelFacts.gauge`) and `gauge_isotropy` finds the
    rank. Returns `(rank, kernel dimension, degenerate)` (the arguments of
    `clebsch_jax.core.isotropy.gauged`), or None: no isotropy at the example, l sees it, the
    system's own arrays are traced (parameters under `vmap`: no concrete example), ξ has more
    than `ISOTROPY_MAX_DIM` components, or its maps fail there.

    The example has the generic rank of the velocity map; a member whose $Q^0$ is of another
    orbit type (a larger isotropy, e.g. q = 0 for ξ × q) is refused in the program itself as an
    invalid input (`clebsch_jax.march.carry.input_ok`, `rank_holds`), never marched with a wrong
    gauge."""
    size = int(np.prod(xi_shape))
    if any_traced(system) or isinstance(system.lagrangian, IsotropyGauge) or size > ISOTROPY_MAX_DIM:
        return None  # (as on concrete values, no isotropy is looked for above ISOTROPY_MAX_DIM)
    rng = np.random.default_rng(0)
    Q, xi = rng.normal(size=q_shape), rng.normal(size=xi_shape)
    try:
        with jax.ensure_compile_time_eval():  # evaluated now, not staged into the caller's trace
            A = np.asarray(velocity_jacobian(system.velocity_map, jnp.asarray(Q), xi.shape))
            if _isotropy(A, xi.size).shape[1] == 0:
                return None
            facts = check_model(system, jnp.asarray(Q), jnp.asarray(xi), jnp.asarray(1.0))
            if facts is None or not facts.gauge:
                return None
            fixed = gauge_isotropy(system, Q, xi)
    except (ValueError, TypeError, ArithmeticError, np.linalg.LinAlgError):
        return None  # the maps do not run at the example: no decision, the system as written
    lag = fixed.lagrangian
    return lag.rank, lag.kernel_dim, bool(fixed.degenerate)


ISOTROPY_MAX_DIM = 256
"""The isotropy is looked for (a dense SVD of the velocity map's Jacobian) up to this dim V; above
it, systems of many particles, it is not (`cj.gauge_isotropy` gauges one by hand)."""


def _isotropy(J, n) -> np.ndarray:
    """`kernel_basis` of the velocity map's Jacobian J (dim M, n), or an empty basis when J is not
    finite or n > `ISOTROPY_MAX_DIM`."""
    if n > ISOTROPY_MAX_DIM or not np.all(np.isfinite(J)):
        return np.zeros((n, 0))
    return kernel_basis(J)


ISOTROPY_LAG_RTOL = 1e-8
r"""l does not see the isotropy K when $|HK| \le$ this $\times |H|$ and
$|K^T\nabla_\xi l| \le$ this $\times (|\nabla_\xi l| + |H||\xi^0|)$ (round-off for a Lagrangian of
$\mathcal L_\xi Q$ alone)."""


def _blind_to(K, H, g, xi) -> bool:
    """Whether l's Hessian `H` and gradient `g` in ξ vanish along the isotropy `K` (and that is
    not empty), to `ISOTROPY_LAG_RTOL`."""
    if K.shape[1] == 0 or not (np.all(np.isfinite(H)) and np.all(np.isfinite(g))):
        return False
    size = float(np.linalg.norm(H, 2)) if H.size else 0.0
    if size == 0.0 and not np.any(g):
        return True
    hk = float(np.linalg.norm(H @ K))
    gk = float(np.linalg.norm(K.T @ g.reshape(-1)))
    return hk <= ISOTROPY_LAG_RTOL * size and gk <= ISOTROPY_LAG_RTOL * (np.linalg.norm(g) + size * np.linalg.norm(xi))


def _evaluate_matrix_free(system, Q0, xi0, direction):
    """The values `_check_matrix_free` needs, in one program: the velocity map at ξ⁰, d and
    2ξ⁰ + d; l's gradient μ at ξ⁰ and d and, with an inverse Legendre map G, ∇l(G(μ))."""
    grad = jax.grad(lambda x: system.l(x, Q0))
    mus = jnp.stack([grad(xi0), grad(direction)])
    found = dict(
        velocities=jnp.stack([system.velocity_map(x, Q0) for x in (xi0, direction, 2.0 * xi0 + direction)]), momenta=mus
    )
    if system.inverse_legendre is not None:
        found["recovered"] = jnp.stack([grad(system.inverse_legendre(mu, Q0)) for mu in mus])
    return found


_matrix_free_values = filter_jit(_evaluate_matrix_free, compiler_options=QUICK_COMPILE)


def _check_matrix_free(system, Q0, xi0, direction) -> None:
    r"""`check_model` for a large ξ (`DENSE_CHECK_MAX`): the velocity map finite and additive on
    the probes, $\mathcal L_{2\xi^0 + d} = 2\mathcal L_{\xi^0} + \mathcal L_d$ to `LINEAR_RTOL`
    (an affine or nonlinear map fails it); and, when the system gives `inverse_legendre` G, G
    inverts the Legendre map at the momenta μ of ξ⁰ and d, $\nabla l(G(\mu)) = \mu$ to
    `INVERSE_RTOL` (the Legendre map is then invertible, Lemma 8)."""
    found = _matrix_free_values(system, Q0, xi0, direction)
    if any(is_traced(x) for x in found.values()):
        return
    found = {key: np.asarray(value) for key, value in found.items()}
    v0, vd, v2 = found["velocities"]
    if not np.all(np.isfinite(found["velocities"])):
        raise ValueError(
            "velocity_map: not finite at the initial configuration Q0 (at xi0 or at a random "
            "direction); start from a Q0 where the map is defined."
        )
    defect = np.linalg.norm(v2 - 2.0 * v0 - vd)
    scale = 2.0 * np.linalg.norm(v0) + np.linalg.norm(vd) + np.linalg.norm(v2)
    if defect > LINEAR_RTOL * scale:
        raise ValueError(
            f"velocity_map: must be linear in xi (Definition 1), but L(2 xi0 + d, Q0) differs from "
            f"2 L(xi0, Q0) + L(d, Q0) by {defect / scale:.1e} of their size (d a random direction): "
            "every term must be linear in xi, with no constant term."
        )
    if "recovered" in found:
        mus, back = found["momenta"], found["recovered"]
        error = max(np.linalg.norm(b - m) / max(np.linalg.norm(m), np.finfo(float).tiny) for m, b in zip(mus, back))
        if not error <= INVERSE_RTOL:
            raise ValueError(
                f"inverse_legendre: G(mu, Q0) does not invert the Legendre map xi -> dl/dxi at Q0: "
                f"dl/dxi(G(mu)) differs from mu by {error:.1e} of its size at the momentum of xi0 or "
                "of a random velocity. It must return the xi whose momentum dl/dxi(xi, Q) is mu."
            )


class _Traced(Exception):
    """A value the checks need depends on a traced value the user's functions close over."""


def _host(x) -> np.ndarray:
    """x as a NumPy array, or `_Traced` when it is a tracer."""
    if is_traced(x):
        raise _Traced
    return np.asarray(x)


def _direction(xi0) -> np.ndarray:
    """A fixed pseudo-random direction of `xi0`'s shape and norm (unit norm if `xi0` = 0)."""
    xi0 = np.asarray(xi0)
    norm = float(np.linalg.norm(xi0))
    return (norm if norm > 0 else 1.0) * _unit_direction(xi0.size).reshape(xi0.shape).astype(xi0.dtype)


@functools.lru_cache(maxsize=None)
def _unit_direction(n: int) -> np.ndarray:
    r = np.random.default_rng(20240531).standard_normal(n)
    return r / np.linalg.norm(r) if n else r


def _hessian_in(fn, x):
    """The Hessian of the scalar function `fn` of an array at `x`, flattened to (x.size, x.size)."""
    return jax.hessian(lambda y: fn(y.reshape(x.shape)))(x.reshape(-1))


def _evaluate(system, Q0, xi0, direction):
    """The derivatives the checks need, in one program: l's Hessian and gradient in ξ at ξ⁰, the
    velocity map's Jacobian in ξ there and its values at the probes ξ⁰, d, 2ξ⁰ + d."""

    def velocity(x):
        return system.velocity_map(x.reshape(xi0.shape), Q0).reshape(-1)

    flat, d = xi0.reshape(-1), direction.reshape(-1)
    return {
        "hessian": _hessian_in(lambda x: system.l(x, Q0), xi0),
        "gradient": jax.grad(lambda x: system.l(x, Q0))(xi0).reshape(-1),
        "jacobian": jax.jacfwd(velocity)(flat),
        "velocities": jnp.stack([velocity(flat), velocity(d), velocity(2.0 * flat + d)]),
    }


def _evaluate_moved(system, Q0, xi0, direction):
    """The same Hessian, gradient and Jacobian at a second point Q⁰ + s L_d Q⁰ (s: a tenth of |Q⁰|
    along the tangent), for the isotropy test (`_blind_to`); evaluated only when l is blind to
    the isotropy at Q⁰."""
    tangent = system.velocity_map(direction, Q0)
    size = jnp.sqrt(jnp.sum(tangent * tangent))
    moved = Q0 + jnp.where(size > 0, 0.1 * jnp.sqrt(jnp.sum(Q0 * Q0)) / jnp.where(size > 0, size, 1.0), 0.0) * tangent
    return {
        "hessian": _hessian_in(lambda x: system.l(x, moved), xi0),
        "gradient": jax.grad(lambda x: system.l(x, moved))(xi0).reshape(-1),
        "jacobian": jax.jacfwd(lambda x: system.velocity_map(x.reshape(xi0.shape), moved).reshape(-1))(xi0.reshape(-1)),
    }


_moved_derivatives = filter_jit(_evaluate_moved, compiler_options=QUICK_COMPILE)


_derivatives = filter_jit(_evaluate, compiler_options=QUICK_COMPILE)  # run once per system: compile time counts
"""The program of the checks, one per system and shapes."""


def _singular(H: np.ndarray):
    """(singular?, singular values) of a square matrix H; not singular when H is not finite
    (a NaN or inf is left for the march to report)."""
    if H.size == 0 or not np.all(np.isfinite(H)):
        return False, None
    s = np.linalg.svd(H, compute_uv=False)
    return bool(s[-1] <= SINGULAR_RTOL * s[0]), s


def _rounded(v: np.ndarray, shape) -> str:
    """A unit null vector for a message: largest entry positive, three decimals, `shape`."""
    v = v / np.linalg.norm(v)
    v = -v if v[np.argmax(np.abs(v))] < 0 else v
    return np.array2string(np.round(v, 3).reshape(shape) + 0.0, separator=", ")


def _check_legendre_map(system, Q0, xi0, H, K, J):
    singular, s = _singular(H)
    if not singular:
        return
    # From here on a refusal follows: the extra derivatives are evaluated eagerly.
    if system.has_potential and xi0.shape == Q0.shape:
        in_Q = _host(_hessian_in(lambda q: system.l(xi0, q), Q0))
        if not _singular(in_Q)[0] and np.all(np.isfinite(in_Q)):
            raise ValueError(
                "lagrangian: it looks like it was written l(Q, xi): its Hessian in its first argument (xi) "
                "is singular at (xi0, Q0) while its Hessian in its second argument (Q) is not. The engine "
                "calls lagrangian(xi, Q): write it as l(xi, Q), velocity first. (If l really is degenerate "
                "in xi, as for point vortices, build the system with ClebschSystem(..., degenerate=True).)"
            )
    if s[0] <= ZERO_RTOL * _hessian_scale(system, Q0, xi0):
        raise ValueError(
            "lagrangian: l is linear in xi (or does not depend on it) at (xi0, Q0): its Hessian in xi is "
            "zero, so the Legendre map xi -> dl/dxi (Lemma 8) is not invertible and the step equations "
            "have no unique solution. If that is the model (a Lagrangian linear in the velocity, as for "
            "point vortices), build it with ClebschSystem(..., degenerate=True) and integrate with "
            'scheme="midpoint" or "gauss"; otherwise make l quadratic in xi (a kinetic energy).'
        )
    rank = int(np.sum(s > SINGULAR_RTOL * s[0]))
    null = np.linalg.svd(H)[2][-1]
    # degenerate=True helps only where the constraint L_xi Q sees the null direction: a direction of
    # the isotropy appears in no step equation
    moves = float(np.linalg.norm(J @ null)) > 1e-8 * max(float(np.linalg.norm(J, 2)), np.finfo(float).tiny)
    if K.shape[1]:
        isotropy = (
            f" The velocity map has a {K.shape[1]}-dimensional isotropy at Q0 (directions of xi that move "
            "Q0 not at all); a Lagrangian that sees xi only through L_xi Q (physical velocities) is "
            "accepted as written, the engine fixing that gauge, but this one depends on the isotropy "
            "directions or is degenerate elsewhere too."
        )
    else:
        isotropy = ""
    fix = "Make l depend quadratically on every component of xi (e.g. a positive moment of inertia for each)" + (
        ", or, if the degeneracy is the model's, build it with ClebschSystem(..., degenerate=True)."
        if moves
        else ", or write it with the physical velocity L_xi Q only."
    )
    raise ValueError(
        f"lagrangian: degenerate in xi at (xi0, Q0): its Hessian in xi has rank {rank} of {H.shape[0]} (smallest "
        f"singular value {s[-1] / s[0]:.1e} of the largest), with null direction {_rounded(null, xi0.shape)}, so "
        "the Legendre map xi -> dl/dxi (Lemma 8) is not invertible and Newton's Jacobian of every step would "
        f"be singular.{isotropy} {fix} (If l is regular but this ill-conditioned, e.g. landmarks much "
        "closer together than the kernel width, the steps cannot be solved in float64 either.)"
    )


def _hessian_scale(system, Q0, xi0) -> float:
    r"""The size a Hessian of l in ξ would have from l's value and gradient at ξ⁰,
    $|l|/|\xi|^2 + |\nabla l|/|\xi|$ (0 when ξ⁰ = 0: only an exactly zero Hessian is "zero")."""
    norm = float(np.linalg.norm(np.asarray(xi0)))
    if norm == 0:
        return 0.0
    value, grad = jax.value_and_grad(lambda x: system.l(x, Q0))(xi0)
    return float(abs(_host(value))) / norm**2 + float(np.linalg.norm(_host(grad))) / norm


def _check_linear(xi0, found):
    J, values = found["jacobian"], found["velocities"]
    labels = ("xi0", "a random direction d", "2 xi0 + d")
    if not (np.all(np.isfinite(J)) and np.all(np.isfinite(values))):
        where = [label for label, v in zip(labels, values) if not np.all(np.isfinite(v))]
        what = (
            f"L(xi, Q0) contains NaN or inf at xi = {', '.join(where)}"
            if where
            else "its Jacobian in xi at xi0 contains NaN or inf"
        )
        raise ValueError(
            f"velocity_map: not finite at the initial configuration Q0: {what}. The tangent vector L(xi, Q0) "
            "must be finite for every xi (a division by, or a log or sqrt of, a component of Q that is 0 at "
            "Q0?); start from a Q0 where the map is defined."
        )
    defects = []
    for label, x, value in zip(labels, found["probes"], values):
        defect = value - J @ x
        scale = np.linalg.norm(value) + np.linalg.norm(J) * np.linalg.norm(x)
        size = float(np.linalg.norm(defect))
        relative = size / scale if scale > 0 else (np.inf if size > 0 else 0.0)
        defects.append((relative, size, label, defect))
    relative, size, label, _ = max(defects, key=lambda item: item[0])
    if not relative > LINEAR_RTOL:
        return
    offset = defects[0][3]
    if all(np.linalg.norm(item[3] - offset) <= 1e-6 * np.linalg.norm(offset) for item in defects):
        what = (
            f"it is affine: L(xi, Q0) - J xi is the same nonzero offset (norm {size:.2e}) at every probe "
            "xi, i.e. L(0, Q0) != 0"
        )
    else:
        what = (
            f"at xi = {label}, L(xi, Q0) differs from J xi, J its Jacobian in xi at xi0, by "
            f"{relative:.1e} of their size"
        )
    raise ValueError(
        f"velocity_map: must be linear in xi (Definition 1), but {what}. L(xi, Q) is the tangent vector by "
        "which xi moves Q: every term must be linear in xi (e.g. Q @ hat(xi), with no products of xi's "
        "components and no constant term); put any nonlinear dependence on xi in the Lagrangian."
    )
