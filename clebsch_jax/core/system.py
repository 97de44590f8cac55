"""The user's system: a reduced Lagrangian, a velocity map and a derivative map.

This is the first stage of the data path
system → discrete action → residual → Newton → scan → Solution → diagnostics.
"""

from __future__ import annotations

import inspect
from typing import Any, Callable

import jax
import jax.numpy as jnp

__all__ = ["ClebschSystem", "diamond", "momentum_map"]


def _positional_arity(fn: Callable, name: str) -> int:
    """Number of required positional parameters of ``fn`` (1 or 2 for a Lagrangian)."""
    try:
        sig = inspect.signature(fn)
    except (TypeError, ValueError) as err:  # builtins, some C callables
        raise TypeError(
            f"{name}: could not read the signature of {fn!r}; wrap it in a Python "
            f"function `def {name}(xi)` or `def {name}(xi, Q)`."
        ) from err
    params = list(sig.parameters.values())
    if any(p.kind is p.VAR_POSITIONAL for p in params):
        raise TypeError(
            f"{name}: takes *args, so it is ambiguous whether it is l(xi) or l(xi, Q); give it explicit parameters."
        )
    required = [p for p in params if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD) and p.default is p.empty]
    return len(required)


class ClebschSystem:
    r"""A Clebsch system: the three things a user writes (Definitions 1, 2, 14, 18).

    The continuous Clebsch action (Definition 2, with potential energy Definition 14) is

    $$ S = \int l(\xi, Q) + \langle P, \dot Q - \mathcal L_\xi Q \rangle \, dt , $$

    and its discrete version (Definition 19) replaces $\dot Q$ by the derivative map
    $\phi_{\Delta t}(Q^{n+1}, Q^n)$.

    **Arguments** (keyword-only):

    - `lagrangian`: `l(xi)` or `l(xi, Q)` → scalar. The second form is Definition 14's
      Lagrangian with potential energy. The form is read from the number of required
      positional parameters.
    - `velocity_map`: `L(xi, Q)` → array of `Q`'s shape, the tangent vector
      $\mathcal L_\xi Q$ by which $\xi$ moves $Q$ (Definition 1). It must be linear in `xi`.
    - `derivative_map`: `phi(Q_next, Q, dt)` → array of `Q`'s shape, the approximation
      $\phi_{\Delta t}(Q^{n+1}, Q^n)$ of $\dot Q$ at $Q^n$ (Definitions 18, 25). See
      `clebsch_jax.forward_difference`, `clebsch_jax.cayley`, `clebsch_jax.exponential`.

    - `degenerate` (default False): set True when $l$ is degenerate in $\xi$ — Lemma 8's
      Legendre map $\xi \mapsto \delta l/\delta\xi$ is not invertible, as for Lagrangians
      linear in the velocity (point vortices). Velocities at the nodes are then not determined
      by $(Q^n, p^n)$ (Lemma 7), so `Solution.xi` is None (the step velocities `xi_step` are
      the velocities), and only the one-step midpoint principle (`scheme="midpoint"`) is
      accepted: the left/right principles give inconsistent two-step schemes here.
    - `check_Q` (default None): a check that a configuration lies on $M$, when $M$ is a
      submanifold of the array space (e.g. $SO(3)$ in the 3×3 matrices): `check_Q(Q)` gets a
      NumPy array of `Q0`'s shape and returns None if it is acceptable, else a sentence saying
      what is wrong (`clebsch_jax.integrate` raises `ValueError("Q0: " + sentence)`). It runs
      on concrete `Q0` only, before compiling. When `Q0` is traced (under `jax.jit`/`jax.vmap`
      over `Q0`) a check with an attribute `traced(Q) -> bool array` (True: on $M$) runs inside
      the program instead, and a member off $M$ reports `Status.INVALID_INPUT` at step 0
      (`models.check_rotation.traced` is `models.rotation_ok`); without one it is skipped. `integrate`
      also runs it on one step of the derivative map from `Q0` and refuses a derivative map
      that leaves $M$ (`clebsch_jax.core.model_checks.check_first_step`; under `jax.jit`/`jax.vmap`
      the traced form runs on that step inside the program, and a member whose step left $M$
      reports `Status.OFF_MANIFOLD`). The models
      `rigid_body` and `heavy_top` set it to a rotation check ($Q^TQ = I$ to $\sqrt\varepsilon$,
      $\det Q = +1$). `cj.sweep` calls it on every row of its `Q0`; a check with an attribute
      `batched(stack) -> None | (row, sentence)` is called once on the whole stack instead
      (`models.check_rotation` has one: 10⁶ rotations in about a second).
    - `inverse_legendre` (default None): Lemma 8's inverse Legendre map, `G(mu, Q)` → the ξ
      with $\delta l/\delta\xi(\xi, Q) = \mu$, when the model knows it in closed form or by a
      structured solve (the Euler–Zeitlin fluid: tridiagonal solves). Nodal velocities are then
      evaluated rather than solved for, the reduced march can solve its steps by fixed-point
      sweeps preconditioned with it (`ReducedStep(root_finder=FixedPoint())`, no Jacobian), and
      `integrate`'s model checks use it instead of a dense Hessian on large systems.

    `xi` and `Q` are arrays of any shape. The system is a pytree: array leaves inside the
    three callables (for instance model parameters held by a `jax.tree_util.Partial`) are
    traced, so `jax.vmap(lambda I: integrate(rigid_body(I), ...))` sweeps parameters
    without recompiling. Plain Python functions are static (hashed by identity).
    """

    lagrangian: Callable
    velocity_map: Callable
    derivative_map: Callable
    has_potential: bool
    degenerate: bool
    check_Q: Callable | None
    inverse_legendre: Callable | None

    def __init__(
        self,
        *,
        lagrangian: Callable,
        velocity_map: Callable,
        derivative_map: Callable,
        degenerate: bool = False,
        check_Q: Callable | None = None,
        inverse_legendre: Callable | None = None,
    ):
        for name, fn in (
            ("lagrangian", lagrangian),
            ("velocity_map", velocity_map),
            ("derivative_map", derivative_map),
        ):
            if not callable(fn):
                raise TypeError(f"{name}: expected a callable, got {type(fn).__name__}.")
        arity = _positional_arity(lagrangian, "lagrangian")
        if arity not in (1, 2):
            raise TypeError(
                f"lagrangian: expected l(xi) or l(xi, Q) (1 or 2 required positional parameters), got {arity}."
            )
        self.lagrangian = lagrangian
        self.velocity_map = velocity_map
        self.derivative_map = derivative_map
        self.has_potential = arity == 2
        if not isinstance(degenerate, bool):
            raise TypeError(f"degenerate: expected True or False, got {degenerate!r}.")
        self.degenerate = degenerate
        if check_Q is not None and not callable(check_Q):
            raise TypeError(f"check_Q: expected None or a callable Q -> None | str, got {type(check_Q).__name__}.")
        self.check_Q = check_Q
        if inverse_legendre is not None and not callable(inverse_legendre):
            raise TypeError(
                f"inverse_legendre: expected None or a callable (mu, Q) -> xi, got {type(inverse_legendre).__name__}."
            )
        if inverse_legendre is not None and degenerate:
            raise ValueError("inverse_legendre: a degenerate Lagrangian has no inverse Legendre map.")
        self.inverse_legendre = inverse_legendre

    def l(self, xi: jax.Array, Q: jax.Array) -> jax.Array:
        """The reduced Lagrangian l(ξ, Q), whichever form the user wrote."""
        return self.lagrangian(xi, Q) if self.has_potential else self.lagrangian(xi)

    def __repr__(self) -> str:
        form = "l(xi, Q)" if self.has_potential else "l(xi)"
        extra = ", degenerate=True" if self.degenerate else ""
        extra += f", check_Q={self.check_Q!r}" if self.check_Q is not None else ""
        extra += f", inverse_legendre={self.inverse_legendre!r}" if self.inverse_legendre is not None else ""
        return (
            f"ClebschSystem(lagrangian={form}, velocity_map={self.velocity_map!r}, "
            f"derivative_map={self.derivative_map!r}{extra})"
        )


def _flatten(sys: ClebschSystem):
    # check_Q is a child like the three maps: a plain function is a static leaf, array leaves
    # of a `Partial` are traced; None is an empty subtree.
    children = (sys.lagrangian, sys.velocity_map, sys.derivative_map, sys.check_Q, sys.inverse_legendre)
    return children, (sys.has_potential, sys.degenerate)


def _unflatten(aux: tuple, children: Any) -> ClebschSystem:
    obj = object.__new__(ClebschSystem)
    obj.lagrangian, obj.velocity_map, obj.derivative_map, obj.check_Q, obj.inverse_legendre = children
    obj.has_potential, obj.degenerate = aux
    return obj


jax.tree_util.register_pytree_node(ClebschSystem, _flatten, _unflatten)


def diamond(system: ClebschSystem, P: jax.Array, Q: jax.Array, xi: jax.Array) -> jax.Array:
    r"""The diamond operator $P \diamond Q \in V^*$ of Definition 4.

    $$ \langle P \diamond Q, \xi \rangle_V = -\langle P, \mathcal L_\xi Q \rangle_{T^*M} , $$

    computed as minus the vjp of $\xi \mapsto \mathcal L_\xi Q$ applied to $P$. The velocity
    map is linear in $\xi$, so `xi` is only a template for the shape of $V$ (any element
    works). Returns an array of `xi`'s shape.
    """
    _, vjp = jax.vjp(lambda x: system.velocity_map(x, Q), jnp.zeros_like(xi))
    (out,) = vjp(P)
    return -out


def momentum_map(system: ClebschSystem, P: jax.Array, Q: jax.Array, xi: jax.Array) -> jax.Array:
    r"""The momentum map $J(Q, P) = -P \diamond Q$ (Remark 6, Theorem 12).

    When the velocity map is a Lie algebra action this is the cotangent-lift momentum map,
    and Lemma 7 says $\delta l / \delta \xi = J$ along solutions. For the rigid body it is
    the body angular momentum.
    """
    return -diamond(system, P, Q, xi)
