r"""Loops, solves and short scans `jax.vmap`ped over the nodes of a long march, in a native
kernel (issue "Native kernels": every built-in model runs natively, peakons and landmarks
past 50 steps included).

The nodal velocities of a march (Lemma 7) are a Newton loop and a linear solve per node,
`vmap`ped over the nodes of the trajectory: a `while` whose predicate has an entry per node.
The translation runs such an equation as a loop over the nodes, each node's program (its own
loop with its own predicate) emitted once (`clebsch_jax.native.row_program`), so the kernel
does not grow with the number of steps. The references are NumPy's (node after node), XLA's
`cj.batch` of the same march (an independent evaluator of the same program) and the kernel's
own IR at another number of steps.
"""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import clebsch_jax as cj
from clebsch_jax import native
from clebsch_jax.native import NativeFallbackWarning

from .helpers import assert_same_solution, solution_leaves

pytestmark = pytest.mark.skipif(not native.available(), reason="llvmlite cannot be imported")


def _no_fallback(call):
    with warnings.catch_warnings():
        warnings.simplefilter("error", NativeFallbackWarning)
        return call()


def _residual(z, target, xp):
    return z * z * z + 0.1 * xp.sum(z) - target


def _node_newton(y):
    """Newton's method for z³ + 0.1 Σz = |y| + 1 (componentwise cubes, coupled by the sum),
    each update a dense solve (`jnp.linalg.solve`: LU and a `custom_linear_solve`); the loop
    stops at round-off, after a number of updates that depends on the node."""
    target = jnp.abs(y) + 1.0

    def update(state):
        z, k = state
        jac = jnp.diag(3.0 * z * z) + 0.1
        return z - jnp.linalg.solve(jac, _residual(z, target, jnp)), k + 1

    def going(state):
        z, k = state
        return (jnp.max(jnp.abs(_residual(z, target, jnp))) > 1e-14 * jnp.max(target)) & (k < 40)

    return jax.lax.while_loop(going, update, (jnp.ones_like(y), jnp.asarray(0, jnp.int32)))


def _nodes_program(x, n=40):
    """A scan of n steps (its records the nodes), then a Newton loop per node (vmapped)."""
    ys = jax.lax.scan(lambda c, _: (1.05 * c + jnp.sin(c[::-1]), c), x, None, length=n)[1]
    z, iterations = jax.vmap(_node_newton)(ys)
    return z, iterations, jnp.sum(iterations)


def _nodes_reference(x, n=40):
    """`_nodes_program` in NumPy, node after node (LAPACK's solve)."""
    c, zs, ks = np.asarray(x, float), [], []
    for _ in range(n):
        y, c = c, 1.05 * c + np.sin(c[::-1])
        target, z, k = np.abs(y) + 1.0, np.ones_like(y), 0
        while np.max(np.abs(_residual(z, target, np))) > 1e-14 * np.max(target) and k < 40:
            z, k = z - np.linalg.solve(np.diag(3.0 * z * z) + 0.1, _residual(z, target, np)), k + 1
        zs.append(z)
        ks.append(k)
    return np.array(zs), np.array(ks)


def test_a_loop_per_node_runs_as_a_loop_over_the_nodes():
    x = np.random.default_rng(4).normal(size=(5, 3))
    z, iterations, total = _no_fallback(lambda: cj.batch(_nodes_program, backend="native")(x))
    for m in range(len(x)):
        rz, riterations = _nodes_reference(x[m])
        # each node's own updates: iteration counts exactly (a quadratically converging loop stops
        # at the same update whatever the last bits), roots to round-off of the solves
        np.testing.assert_array_equal(np.asarray(iterations)[m], riterations)
        assert int(total[m]) == int(riterations.sum())
        np.testing.assert_allclose(np.asarray(z)[m], rz, rtol=1e-14)
    assert len(np.unique(np.asarray(iterations))) > 1  # the nodes' loops stop at different updates
    from clebsch_jax.native.kernel import build_ir

    lines = lambda n: build_ir(jax.make_jaxpr(lambda a: _nodes_program(a, n))(x[0]), 4).count("\n")
    assert lines(40) == lines(400)  # each node's loop emitted once: nothing written out per node


# Peakons and landmarks past 50 steps: their nodal velocities are the loop above, a Newton loop
# per node on Lemma 7's relation, with the kernel matrix's solve.

N_LONG = 100


def _peakon_members():
    """A peakon–antipeakon pair colliding at t* = 3 (its step fails before), an overtaking
    pair, a NaN member (fails at step 0) and a pair running apart."""
    from clebsch_jax.models import peakon_velocity

    from .test_epdiff import COLLISION, OVERTAKE, peakon_antipeakon_exact, two_peakons_exact

    qc, pc = peakon_antipeakon_exact(0.0, **COLLISION)
    qo, po = two_peakons_exact(0.0, **OVERTAKE)
    q0 = np.array([qc, qo, [np.nan, 1.0], [-0.5, 0.7]])
    p0 = np.array([pc, po, [1.0, 1.0], [0.8, 0.3]])
    return q0, np.asarray(jax.vmap(peakon_velocity)(q0, p0)), np.array([0.05, 0.05, 0.05, 0.03])


def _peakon_march(q0, xi0, dt, n_steps=N_LONG):
    return cj.integrate(cj.models.peakons(), q0, xi0, dt=dt, n_steps=n_steps, throw=False)


def _kernel_lines(march, args, n_steps: int) -> int:
    """Lines of LLVM IR of cj.batch's kernel of `march` over `n_steps` steps (its member
    program as `batch_native` prunes it; emitted, not compiled)."""
    from clebsch_jax.batching import prune
    from clebsch_jax.march.integrate import caller_backend
    from clebsch_jax.native.kernel import build_ir

    def member(*a):
        with caller_backend():
            return jax.tree_util.tree_leaves(march(*a, n_steps=n_steps))

    closed = jax.make_jaxpr(member)(*args)
    return build_ir(jax.make_jaxpr(prune.pruned(closed))(*args), 4).count("\n")


@pytest.mark.slow  # compiles the peakons' march twice: XLA's batch and the native kernel; the
# default run covers the nodes' loops with test_a_loop_per_node_runs_as_a_loop_over_the_nodes
def test_peakons_past_50_steps_run_natively_under_auto_and_equal_xla():
    q0, xi0, dts = _peakon_members()
    lines = _kernel_lines(_peakon_march, (q0[0], xi0[0], dts[0]), N_LONG)
    assert lines == _kernel_lines(_peakon_march, (q0[0], xi0[0], dts[0]), 10 * N_LONG)
    assert lines < native.AUTO_MAX_IR_LINES
    run = lambda: _no_fallback(lambda: cj.batch(_peakon_march)(q0, xi0, dts))  # "auto": no fallback
    first, again = run(), run()
    for (name, a), (_, b) in zip(solution_leaves(first), solution_leaves(again)):
        np.testing.assert_array_equal(a, b, err_msg=name)  # the same bits, call after call
    xla = jax.jit(cj.batch(_peakon_march, backend="xla"))(q0, xi0, dts)
    assert_same_solution(first, xla)
    result, failed = np.asarray(first.result), np.asarray(first.failed_step)
    assert result[2] == cj.Status.INVALID_INPUT and failed[2] == 0
    assert result[0] != cj.Status.SUCCESS and 40 <= failed[0] < 60  # the collision, before t* = 3
    assert np.all(result[[1, 3]] == cj.Status.SUCCESS)


def _landmark_march(q0, xi0, dt, n_steps=N_LONG):
    return cj.integrate(cj.models.landmarks(0.8), q0, xi0, dt=dt, n_steps=n_steps, throw=False)


@pytest.mark.slow  # LLVM compiles the landmarks' kernel in tens of seconds, XLA its batch; the
# default run covers the nodes' loops with test_a_loop_per_node_runs_as_a_loop_over_the_nodes
def test_landmarks_past_50_steps_run_natively_and_equal_xla():
    """Three landmarks in the plane: the kernel does not grow with the steps (asked for with
    `backend="native"`; within "auto"'s budget of IR lines too)."""
    from clebsch_jax.models import landmark_velocity

    from .test_epdiff import LANDMARK_P0, LANDMARK_Q0

    rng = np.random.default_rng(1)
    q0 = np.stack([LANDMARK_Q0 + 0.1 * rng.standard_normal((3, 2)) for _ in range(4)])
    q0[2, 0, 0] = np.nan  # fails at step 0
    xi0 = np.asarray(jax.vmap(lambda q, p: landmark_velocity(q, p, 0.8))(q0, np.stack([LANDMARK_P0] * 4)))
    dts = np.array([0.02, 0.03, 0.02, 0.05])
    args = (q0[0], xi0[0], dts[0])
    assert _kernel_lines(_landmark_march, args, N_LONG) == _kernel_lines(_landmark_march, args, 10 * N_LONG)
    native_run = _no_fallback(lambda: cj.batch(_landmark_march, backend="native")(q0, xi0, dts))
    xla = jax.jit(cj.batch(_landmark_march, backend="xla"))(q0, xi0, dts)
    assert_same_solution(native_run, xla)
    result = np.asarray(native_run.result)
    assert result[2] == cj.Status.INVALID_INPUT and np.all(result[[0, 1, 3]] == cj.Status.SUCCESS)
