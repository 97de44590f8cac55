"""Arithmetic from first principles for `work_precision_ceiling.py`: floating-point operations
per member of a Taylor step of heyoka's and of one sweep (and the rest of a step) of ours."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

import clebsch_jax as cj
from clebsch_jax.discrete import collocation


def taylor_flops(ta, n_state: int) -> dict:
    """Floating-point operations per member of one Taylor step of `ta`, from heyoka's decomposition
    of the right-hand side: a product or quotient of two series costs sum_{n<p} (2n+1) = p^2 over
    the p orders, a sum, difference or product with a constant p; each state variable p for
    x_{n+1} = f_n/(n+1), 2p for the Horner update and 4 for the step size's norms."""
    p, series, linear = ta.order, 0, 0
    for expr, _ in ta.decomposition[n_state:-n_state]:
        s = str(expr)
        if s.startswith("div(") or (s.count("u_") == 2 and " * " in s):
            series += 1  # a product or a quotient of two series (or a constant over a series)
        elif s.startswith(("sub(", "(-", "-")) or " + " in s or " * " in s:
            linear += 1
        else:
            raise ValueError(f"no operation count for heyoka's {s}")
    flops = series * p * p + (linear + 3 * n_state) * p + 4 * n_state
    return {"order": p, "series_ops": series, "linear_ops": linear, "flops_per_step": flops}


_ELEMENTWISE = {"add", "sub", "mul", "div", "neg", "max", "min", "abs", "sqrt", "rsqrt", "exp", "log", "sign"}


def jaxpr_flops(jaxpr) -> int:
    """Floating-point operations of a jaxpr: elementwise arithmetic one per output entry,
    `integer_pow` y - 1, `dot_general` (2k - 1) per output entry, `reduce_sum` inputs - outputs;
    sub-jaxprs (pjit, custom derivatives, loops) counted once, scans times their length, cond
    its costliest branch."""
    total = 0
    for eqn in jaxpr.eqns:
        out = eqn.outvars[0].aval
        name = eqn.primitive.name
        subs = [v for x in eqn.params.values() for v in (x if isinstance(x, tuple) else (x,)) if hasattr(v, "eqns")]
        if subs:
            inner = [jaxpr_flops(getattr(j, "jaxpr", j)) for j in subs]
            total += max(inner) if name == "cond" else sum(inner) * eqn.params.get("length", 1)
            continue
        if not jnp.issubdtype(getattr(out, "dtype", jnp.int32), jnp.floating):
            continue
        size = math.prod(out.shape)
        if name in _ELEMENTWISE:
            total += size
        elif name == "integer_pow":
            total += size * (abs(eqn.params["y"]) - 1)
        elif name == "dot_general":
            (contract, _), _ = eqn.params["dimension_numbers"]
            k = math.prod(eqn.invars[0].aval.shape[d] for d in contract)
            total += size * (2 * k - 1)
        elif name == "reduce_sum":
            total += math.prod(eqn.invars[0].aval.shape) - size
    return total


def sweep_flops(scene, options: dict, dt: float) -> dict:
    """Floating-point operations of one member's sweep (`GaussLegendre._sweep`: stage values,
    velocities, increments) and, per step, of the matrices formed once per step, the compensated
    update and the extrapolated guess."""
    options = dict(options)
    make_system, params, Q0, xi0, extra = scene.sweep_args(options.pop("model", None))
    system = make_system(params[0])
    Q = jnp.asarray(Q0[0])
    P = jnp.asarray(extra["P0"][0]) if "P0" in extra else jnp.zeros_like(Q)
    stepper = cj.GaussLegendre(order=options["order"], constraint_blocks=options.get("jacobian") == "blocks")
    tab = collocation.gauss_legendre(stepper.stages)
    s = stepper.stages
    z = collocation.GaussUnknowns(
        xi=jnp.broadcast_to(jnp.asarray(xi0[0]), (s,) + xi0[0].shape), dQ=jnp.zeros((s,) + Q.shape),
        dP=jnp.zeros((s,) + P.shape),
    )  # fmt: skip
    mats = stepper._matrices(system, tab, Q, P, z)
    sweep = jax.make_jaxpr(lambda z: stepper._sweep(system, tab, dt, Q, P, z, mats))(z).jaxpr
    comp = (jnp.zeros_like(Q), jnp.zeros_like(P))

    def per_step(z):
        return (
            stepper._matrices(system, tab, Q, P, z),
            collocation.gauss_update(Q, P, z, comp),
            collocation.extrapolate(tab, z),
        )

    return {"stages": s, "sweep": jaxpr_flops(sweep), "per_step": jaxpr_flops(jax.make_jaxpr(per_step)(z).jaxpr)}
