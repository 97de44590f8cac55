r"""Throughput of the built-in models (issue 6): body-steps and vortex-steps per second against
NumPy RK4s of the same equations, and the first-call compile time of every model.

Run from the repository root:

    python benchmarks/throughput.py            # default run, 7.6 min on 2 idle cores
    python benchmarks/throughput.py --quick    # smoke test, tiny sizes (not a measurement)
    python benchmarks/throughput.py --sweep-only   # part 4 only: the sweep against the hand kernel

Three parts, timed with the harness the benchmarks share (`_timing.py`: a first call compiles,
every call ends in `jax.block_until_ready`, the median of `--repeats` samples, the methods of a
case sampled in turn, load average recorded):

1. **Rigid body, reduced march** (`rigid_body((2, 1, 2/3))`, Cayley, `reduce=True`: Theorem 27
   / Corollary 29, Q reconstructed, dt = 0.05; the bodies and the RK4 of
   `rigid_body_step_cost.py`). Body-steps per second = B * n_steps / (time of one call) for
   batch sizes B = 1, 10^3, 10^4, 10^5, 10^6 (random unit body momenta, Q0 = I), with

   - **vmap**: `jax.jit(jax.vmap(lambda Q0, xi0: integrate(..., throw=False)))` over all B bodies;
   - **chunked** (B > chunk only): `jax.jit(lambda Q0, xi0: jax.lax.map(member, (Q0, xi0),
     batch_size=chunk))`, i.e. a sequential map over chunks of `chunk` bodies, each chunk a
     vmap: the working set of one chunk stays in cache, and each chunk's Newton loops stop with
     the chunk's slowest member instead of the whole batch's;
   - **batch_last**: `jax.jit(cj.batch(member, chunk=chunk))`, the library's batch-last evaluation
     of the same per-member program (`clebsch_jax.batch`: components as rows of `chunk`
     numbers, chunks one after the other; bit-identical to vmap here);
   - **NumPy RK4** of Euler's equations with reconstruction, broadcast over the bodies;
   - **JAX by hand** (`hand_march`): the same discrete equations written by hand for speed
     (batch-last layout, closed-form Jacobian, a fixed 3 chord updates, no checks), jitted: a
     reference for what XLA on this CPU makes of this arithmetic, not a library path.

   Every call keeps the whole trajectory (for B = 10^6 and 10 steps ~2 GB per method; the
   run peaks at ~10 GB resident).
2. **Point vortices** (`point_vortices(G)`, midpoint principle = implicit midpoint rule, solved
   to round-off, `jacobian="blocks"`; the systems and the RK4 of `vortex_step_cost.py`).
   Vortex-steps per second = N * B * n_steps / (time of one call) for one system of N = 4, 100,
   1000 vortices (a plain `integrate` call) and batches of B systems (`jax.jit(jax.vmap(...))`):
   4 x 1000 and 100 x 10; against the NumPy RK4 of the Biot-Savart velocities over all pairs.
3. **Compile time** of each built-in model: rigid body (reduced), heavy top, point vortices,
   peakons, landmarks. Each in a fresh child process (a user's first call), after one tiny
   `jax.jit` that initialises the backend and XLA (reported apart as `process_first_jit_s`):
   compile time = the first `integrate` call minus a second identical call. Each model runs
   in two children that share a fresh directory for `clebsch_jax.enable_compilation_cache`:
   the first compiles and writes the programs (`compile_s`, the cold start the target speaks
   of), the second loads them (`warm`: what a new process pays once the cache holds them,
   e.g. the second `clebsch-jax run` or a restarted notebook kernel).

4. **Sweep** (`--sweep-only`, written to `throughput_sweep.json`/`.png`; issue 20): the
   documented `cj.sweep(rigid_body, …, reconstruct=False)` call with default options
   (`fast="auto"`: the general Newton loop below 10⁶ member-steps or 1000 members, the
   lean chunk from there, so at B = 10⁵ × 200 steps) and with `fast=True` (the lean chunk, `clebsch_jax.batching.lean`,
   in batches of up to 16384 members), `jax.jit(cj.batch(integrate → final momentum, energy
   error))`, the hand-written rows kernel `hand_rows_march` (the yardstick: each component a
   (B,) row, closed-form Jacobian and cofactor inverse, fixed chord updates,
   `fori_loop(unroll=4)`, final state and energy error only), `jax_by_hand_rows_verified`: the
   same kernel with the lean chunk's per-step checks written by hand (the solve's check, the
   node's velocity and its check, the energy at the node and `integrate`'s jump rule, finite
   values; `hand_rows_march(verified=True)`, the yardstick of a step that keeps the sweep's
   promises, with the share of members whose every step passed), NumPy RK4 of Euler's equations on
   (3, B) arrays and, when a C compiler is present, `c_simd`: the hand kernel's step in C
   (`benchmarks/c/rigid_body_cay.c`, bodies in SIMD lanes, one thread; built at run time,
   skipped with the reason otherwise), the hardware reference; M body-steps/s,
   ratios, compile times (first call − second call), energy errors, fallback counts. With
   `--sweep-only` the script asks XLA for two host devices (`XLA_FLAGS`, set before JAX
   starts, unless the caller set a device count) and adds `sweep_fast_2dev`: `fast=True,
   devices=2`, the batches dealt to both cores. Every other row runs on device 0 as before.
   Cores: every JAX row, the hand kernel included, runs with XLA's intra-op threads on every
   core the process may use (`taskset` limits them); NumPy's RK4 uses one.
   A *mixed-momenta* case (`mixed_momenta`: ω ~ N(0, 1), B = 10⁴ × 800 steps) runs the
   default sweep, `fast=True`, `fast=False`, the hand kernel and RK4 on members of which ~1 %
   turn too fast for the fast path's fixed updates: what their reruns on the general path cost
   (`fallback_share`: member-chunks rerun over member-chunks tried).

The issue's targets (reported, never asserted): the reduced rigid body at >= 10^7 body-steps
per second and >= 3x the NumPy RK4 rate, flat from B = 10^3 to 10^6 (here: every rate within
`FLAT_FRACTION` of the best rate over that range); one variational vortex step at N = 1000
costing <= 3x one RK4 step; compile <= 2 s per model.

Outputs (in `--out`, default `benchmarks/results`): `throughput.json` and `throughput.png`
(body-steps per second against batch size; vortex-steps per second; compile times).
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

if "--sweep-only" in sys.argv and "device_count" not in os.environ.get("XLA_FLAGS", ""):
    # two host devices for the sweep's `devices=2` row (before JAX starts: a process-wide flag)
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2").strip()

import jax
import jax.numpy as jnp
import numpy as np

import _timing as harness
import clebsch_jax as cj
from clebsch_jax.march.scan import ENERGY_STEP_RTOL
import rigid_body_step_cost as rigid
import vortex_step_cost as vortex
from clebsch_jax import models

RESULTS_NAME = "throughput"
RK4 = "numpy_rk4"
HAND = "jax_by_hand"  # a reference, not a library path: never "best", not in the verdicts

# Rigid body: (batch size, n_steps). The same n_steps for every B >= 10^3, so that the rates
# are comparable (a call's fixed cost, the first Jacobian and the predictor's start-up are
# shared by the same number of steps); B = 1 runs longer to last more than a few ms.
RIGID_DEFAULT = ((1, 1000), (1_000, 10), (10_000, 10), (100_000, 10), (1_000_000, 10))
RIGID_QUICK = ((8, 5),)
CHUNK, CHUNK_QUICK = 1000, 4  # bodies per chunk of the chunked variant
# calls of >= this many body-steps take several seconds each (B = 10^6): fewer samples
LONG_CALL_BODY_STEPS, LONG_CALL_REPEATS = 5_000_000, 3

# Vortices: (label, N, batch size or None for one plain call, n_steps).
VORTEX_DEFAULT = (
    ("single", 4, None, 1000),
    ("single", 100, None, 20),
    ("single", 1000, None, 4),
    ("vmap", 4, 1000, 20),
    ("vmap", 100, 10, 5),
)
VORTEX_QUICK = (("single", 4, None, 10), ("vmap", 4, 3, 4))

MODELS = ("rigid_body", "heavy_top", "point_vortices", "peakons", "landmarks")
MODELS_QUICK = ("point_vortices", "peakons")
COMPILE_N_STEPS = 100

TARGETS = {
    "rigid_body_steps_per_second": 1e7,
    "rigid_body_over_rk4_rate": 3.0,
    "flat_from_batch": 1000,  # the flat range: every batch size from this one up
    "flat_fraction": 0.8,  # "flat": every rate >= this fraction of the best rate over the range
    "vortex_N": 1000,
    "vortex_ours_over_rk4_time_per_step": 3.0,
    "compile_s": 2.0,
}


# --------------------------------------------------------------------------------------------
# Part 1: the reduced rigid-body march.


def _rates(timing: dict, n_steps: int, units: int, unit: str) -> dict:
    """Time per step and throughput of one method: `units` bodies or vortices per step."""
    per_step = timing["per_call_s"] / n_steps
    return {
        "seconds_per_step": per_step,  # one step of the whole batch
        f"seconds_per_{unit}_step": per_step / units,
        f"{unit}_steps_per_second": units / per_step,
        "cpu_over_wall": timing["cpu_per_call_s"] / timing["per_call_s"],
        **timing,
    }


def chunked_call(system, chunk: int, n_steps: int, Q0, omega0, compiler_options=None):
    """A blocking call of the reduced march over all bodies, `chunk` bodies at a time."""
    Q0_j, xi0_j = jnp.asarray(Q0), jnp.asarray(omega0)

    def member(args):
        return cj.integrate(system, *args, dt=rigid.DT, n_steps=n_steps, reduce=True, throw=False)

    march = jax.jit(lambda q, x: jax.lax.map(member, (q, x), batch_size=chunk), compiler_options=compiler_options)

    def call():
        return jax.block_until_ready(march(Q0_j, xi0_j))

    return call


HAND_UPDATES = 3


def hand_march(inertia, dt, n_steps, updates=HAND_UPDATES):
    """The reduced CAY rigid-body step (Example 30) written by hand in JAX: a reference for what
    XLA makes of this arithmetic, not a library path. The equations are ours (checked against
    `integrate` in every case: `max_abs_momentum_diff_vs_vmap`): find ξ with
    D(Δt ξ, 𝕀ξ) = μⁿ, D(y, M) = M + y×M/2 + y(y·M)/4, then μⁿ⁺¹ = D(−Δt ξ, 𝕀ξ) and
    Qⁿ⁺¹ = Qⁿ cay(Δt ξ̂). Written the way a specialist would for speed: batch-last layout
    (components as rows of B numbers), the Jacobian in closed form at a linear predictor and
    inverted by cofactors, a fixed number of chord updates with no convergence test, no
    failure handling, no statistics; like the other methods it keeps μ, Q and ξ of every step."""
    Iv = jnp.asarray(inertia)[:, None]
    h = dt

    def cross(a, b):
        return jnp.stack([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])

    def D(y, M):  # M + y×M/2 + y (y·M)/4: the CAY momentum map
        return M + 0.5 * cross(y, M) + 0.25 * y * jnp.sum(y * M, 0)

    def hat(x):
        z = jnp.zeros_like(x[0])
        return jnp.stack([jnp.stack([z, -x[2], x[1]]), jnp.stack([x[2], z, -x[0]]), jnp.stack([-x[1], x[0], z])])

    def mm(A, B):  # (3,3,B) @ (3,3,B)
        return jnp.stack([jnp.stack([sum(A[i, k] * B[k, j] for k in range(3)) for j in range(3)]) for i in range(3)])

    def inv3(A):
        c0, c1, c2 = A[:, 0], A[:, 1], A[:, 2]
        r0, r1, r2 = cross(c1, c2), cross(c2, c0), cross(c0, c1)
        return jnp.stack([r0, r1, r2]) / jnp.sum(c0 * r0, 0)

    def jac(x):
        M = Iv * x
        eye = jnp.eye(3)[:, :, None]
        J = eye * Iv[None]  # diag(I): J[i,j] = I_j δ_ij
        J = J + 0.5 * h * (mm(hat(x), eye * Iv[None]) - hat(M))
        J = J + 0.25 * h * h * (eye * jnp.sum(x * M, 0) + 2.0 * x[:, None] * M[None, :])
        return J

    def step(carry, _):
        mu, Q, x1, x2 = carry
        x = 2.0 * x1 - x2
        Jinv = inv3(jac(x))
        for _ in range(updates):
            r = D(h * x, Iv * x) - mu
            x = x - jnp.sum(Jinv * r[None], 1)
        mu1 = D(-h * x, Iv * x)
        y = h * x
        Y = hat(y)
        C = jnp.eye(3)[:, :, None] + (4.0 / (4.0 + jnp.sum(y * y, 0))) * (Y + 0.5 * mm(Y, Y))
        Q1 = mm(Q, C)
        return (mu1, Q1, x, x1), (mu1, Q1, x)

    @jax.jit
    def march(Q0, xi0):  # batch-first in and out, like the other methods
        x0 = xi0.T
        mu0 = Iv * x0
        carry = (mu0, jnp.transpose(Q0, (1, 2, 0)), x0, x0)
        _, (mus, Qs, xs) = jax.lax.scan(step, carry, None, length=n_steps)
        return mus, Qs, xs

    return march


ROWS_UPDATES, ROWS_UNROLL = 3, 4


def hand_rows_march(inertia, dt, n_steps, updates=ROWS_UPDATES, unroll=ROWS_UNROLL, verified=False):
    """The reduced CAY rigid-body step by hand in the fastest shape found for XLA on the CPU (the
    yardstick of the sweep's fast path, not a library path): each component of ξ and μ its own
    (B,) row, the linear predictor 2ξⁿ⁻¹ − ξⁿ⁻², the Jacobian of D(Δt ξ, 𝕀ξ) in closed form at
    the prediction and inverted by cofactors with one division, `updates` chord updates with no
    test, `fori_loop(unroll=unroll)` over the steps, no trajectory: returns the final μ (3, B)
    and the largest |E - E⁰| over the steps (B,), E = ½ Σ μᵢ²/Iᵢ evaluated at each node.
    Same discrete equations as `hand_march` and `integrate` (μⁿ⁺¹ = D(−Δt ξ, 𝕀ξ)).

    `verified=True` adds, by hand, what the sweep's lean chunk promises at every step
    (`clebsch_jax.batching.lean`): the solve's check (the update the residual at the result
    would make, at most `VERIFY_TOLERANCE` times max(1, |ξ|)), the node's velocity from μⁿ⁺¹
    (one update of 𝕀ξ = μ from the step's ξ, and its residual), the energy ⟨μ, ξ⟩ − l(ξ) at
    the node from it, `integrate`'s energy-jump rule and finite values; it returns a third
    output, whether every step of a member passed (a sweep would rerun the others). The
    yardstick of a step that keeps the sweep's promises, written the fast way."""
    I = [float(v) for v in np.asarray(inertia)]
    h = float(dt)

    def D(y, M):  # M + y×M/2 + y (y·M)/4, on rows
        yM = y[0] * M[0] + y[1] * M[1] + y[2] * M[2]
        c = (y[1] * M[2] - y[2] * M[1], y[2] * M[0] - y[0] * M[2], y[0] * M[1] - y[1] * M[0])
        return tuple(M[i] + 0.5 * c[i] + 0.25 * y[i] * yM for i in range(3))

    def energy(mu):
        return 0.5 * (mu[0] * mu[0] / I[0] + mu[1] * mu[1] / I[1] + mu[2] * mu[2] / I[2])

    def jac(x):  # d/dx of D(h x, I x), rows J[i][j]
        M = tuple(I[i] * x[i] for i in range(3))
        xM = x[0] * M[0] + x[1] * M[1] + x[2] * M[2]
        J = [[None] * 3 for _ in range(3)]
        for i in range(3):
            for j in range(3):
                # (h/2)(x × (I e_j) - M × e_j)_i + (h²/4)(δ_ij x·M + 2 x_i M_j)
                e = [0.0, 0.0, 0.0]
                e[j] = 1.0
                Ie = [I[k] * e[k] for k in range(3)]
                k1, k2 = (i + 1) % 3, (i + 2) % 3
                cross_xI = x[k1] * Ie[k2] - x[k2] * Ie[k1]
                cross_Me = M[k1] * e[k2] - M[k2] * e[k1]
                J[i][j] = (
                    (I[i] if i == j else 0.0)
                    + 0.5 * h * (cross_xI - cross_Me)
                    + 0.25 * h * h * ((xM if i == j else 0.0) + 2.0 * x[i] * M[j])
                )
        return J

    def inv3(A):  # cofactors, one division
        c = [
            [
                A[(i + 1) % 3][(j + 1) % 3] * A[(i + 2) % 3][(j + 2) % 3]
                - A[(i + 1) % 3][(j + 2) % 3] * A[(i + 2) % 3][(j + 1) % 3]
                for j in range(3)
            ]
            for i in range(3)
        ]
        r = 1.0 / (A[0][0] * c[0][0] + A[0][1] * c[0][1] + A[0][2] * c[0][2])
        return [[c[j][i] * r for j in range(3)] for i in range(3)]

    def residual(x, mu):
        return tuple(a - b for a, b in zip(D(tuple(h * v for v in x), tuple(I[i] * x[i] for i in range(3))), mu))

    def largest(v):
        return jnp.maximum(jnp.maximum(jnp.abs(v[0]), jnp.abs(v[1])), jnp.abs(v[2]))

    def check(x, H, mu, mu1, E_prev, change_max, size_max):
        """The lean chunk's per-step verification: (passed, E, largest change, largest size)."""
        r = residual(x, mu)
        update = [H[i][0] * r[0] + H[i][1] * r[1] + H[i][2] * r[2] for i in range(3)]
        passed = largest(update) <= VERIFY_TOLERANCE * jnp.maximum(largest(x), 1.0)
        xn = tuple(x[i] - (I[i] * x[i] - mu1[i]) / I[i] for i in range(3))  # the node's velocity
        passed = passed & (
            largest([I[i] * xn[i] - mu1[i] for i in range(3)]) <= VERIFY_TOLERANCE * jnp.maximum(largest(mu1), 1.0)
        )
        pairing = mu1[0] * xn[0] + mu1[1] * xn[1] + mu1[2] * xn[2]
        lagrangian = 0.5 * (I[0] * xn[0] * xn[0] + I[1] * xn[1] * xn[1] + I[2] * xn[2] * xn[2])
        E = pairing - lagrangian
        change = jnp.abs(E - E_prev)  # `integrate`'s rule, against the nodes before this one
        passed = passed & ~(change > ENERGY_STEP_RTOL * size_max) & jnp.isfinite(E)
        return passed, E, jnp.maximum(change_max, change), jnp.maximum(size_max, jnp.abs(pairing) + jnp.abs(lagrangian))

    def step(_, carry):  # the verified kernel carries (passed, E, largest change, largest size) too
        mu, x1, x2, E0, err, *checks = carry
        x = tuple(2.0 * a - b for a, b in zip(x1, x2))
        H = inv3(jac(x))
        for _ in range(updates):
            r = residual(x, mu)
            x = tuple(x[i] - (H[i][0] * r[0] + H[i][1] * r[1] + H[i][2] * r[2]) for i in range(3))
        mu1 = D(tuple(-h * v for v in x), tuple(I[i] * x[i] for i in range(3)))
        if not verified:
            return mu1, x, x1, E0, jnp.maximum(err, jnp.abs(energy(mu1) - E0))
        ok, E_prev, change_max, size_max = checks
        passed, E, change_max, size_max = check(x, H, mu, mu1, E_prev, change_max, size_max)
        return mu1, x, x1, E0, jnp.maximum(err, jnp.abs(E - E0)), ok & passed, E, change_max, size_max

    @jax.jit
    def march(xi0):  # (B, 3) in; final μ (B, 3) and energy error (B,) out (and passed (B,) if verified)
        x0 = tuple(xi0[:, i] for i in range(3))
        mu0 = tuple(I[i] * x0[i] for i in range(3))
        E0 = energy(mu0)
        zero = jnp.zeros_like(E0)
        carry = (mu0, x0, x0, E0, zero)
        if verified:  # |⟨μ, ξ⟩| + |l| = 3E at node 0
            carry += (jnp.ones_like(E0, dtype=bool), E0, zero, 3.0 * E0)
        mu, _, _, _, err, *checks = jax.lax.fori_loop(0, n_steps, step, carry, unroll=unroll)
        return (jnp.stack(mu, axis=1), err) + ((checks[0],) if verified else ())

    return march


VERIFY_TOLERANCE = 64 * float(np.finfo(np.float64).eps)
"""`hand_rows_march(verified=True)`'s bound on its checks, relative to max(1, the value's size):
a fixed bound instead of the engine's stopping rule, the same cost."""


C_SOURCE = Path(__file__).with_name("c") / "rigid_body_cay.c"
C_FLAGS = (["-O3", "-march=native", "-mprefer-vector-width=512"], ["-O3", "-march=native"], ["-O3"])
"""Tried in order until one compiles: AVX-512 lanes where the CPU has them, else the widest the
compiler picks, else portable code."""

_C_KERNEL: dict = {}


def c_kernel():
    """The C kernel `c/rigid_body_cay.c` (`hand_rows_march`'s step, bodies in SIMD lanes, one
    thread), built once per process with the system's C compiler (`cc`, or `$CC`) into a
    temporary directory: `(march, flags)` with `march(inertia, dt, n_steps, xi0 (B, 3)) -> (final
    μ (B, 3), max |E − E⁰| (B,))`, or `(None, reason)` when there is no compiler or no build."""
    if "kernel" in _C_KERNEL:
        return _C_KERNEL["kernel"]
    import ctypes
    import shutil

    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")
    result = (None, "no C compiler (cc, gcc, clang or $CC) found")
    if cc:
        out = Path(tempfile.mkdtemp(prefix="clebsch_c_")) / "rigid_body_cay.so"
        for flags in C_FLAGS:
            cmd = [cc, *flags, f"-DUPDATES={ROWS_UPDATES}", "-shared", "-fPIC", "-o", str(out), str(C_SOURCE), "-lm"]
            if subprocess.run(cmd, capture_output=True).returncode == 0:
                lib = ctypes.CDLL(str(out))
                fn = lib.rigid_body_cay_march
                dp = ctypes.POINTER(ctypes.c_double)
                fn.argtypes = [ctypes.c_long, ctypes.c_long, ctypes.c_double, dp, dp, dp, dp]
                fn.restype = None

                def march(inertia, dt, n_steps, xi0, fn=fn, dp=dp):
                    I = np.ascontiguousarray(inertia, dtype=np.float64)
                    x = np.ascontiguousarray(xi0, dtype=np.float64)
                    mu, err = np.empty_like(x), np.empty(x.shape[0])
                    fn(x.shape[0], n_steps, float(dt), *(a.ctypes.data_as(dp) for a in (I, x, mu, err)))
                    return mu, err

                result = (march, " ".join([os.path.basename(cc), *flags]))
                break
        else:
            result = (None, f"{cc} could not build {C_SOURCE.name}")
    _C_KERNEL["kernel"] = result
    return result


def hand_call(batch: int, n_steps: int, Q0, omega0):
    march = hand_march(rigid.INERTIA, rigid.DT, n_steps)
    Q0_j, xi0_j = jnp.asarray(Q0), jnp.asarray(omega0)
    return lambda: jax.block_until_ready(march(Q0_j, xi0_j))


def rigid_case(batch: int, n_steps: int, chunk: int, run: harness.Run) -> dict:
    system = models.rigid_body(jnp.asarray(rigid.INERTIA))
    inertia = np.asarray(rigid.INERTIA)
    Q0, omega0 = rigid.initial_conditions(batch)
    name = f"rigid body B={batch} n_steps={n_steps}"
    calls = {"vmap": rigid.ours_call(system, batch, n_steps, Q0, omega0, {"reduce": True}, run.compiler_options)}
    if batch > chunk:
        calls["chunked"] = chunked_call(system, chunk, n_steps, Q0, omega0, run.compiler_options)
    if batch > 1:
        calls["batch_last"] = rigid.ours_call(
            system,
            batch,
            n_steps,
            Q0,
            omega0,
            {"reduce": True},
            run.compiler_options,
            functools.partial(cj.batch, chunk=chunk),
        )
    calls[HAND] = hand_call(batch, n_steps, Q0, omega0)
    calls[RK4] = lambda: rigid.rk4_march(inertia, Q0, omega0, rigid.DT, n_steps)
    long_calls = batch * n_steps >= LONG_CALL_BODY_STEPS
    timings, outs = run.time(calls, what=name, repeats=min(run.repeats, LONG_CALL_REPEATS) if long_calls else None)

    row = {
        "part": "rigid_body",
        "case": "vmap",
        "batch": batch,
        "n_steps": n_steps,
        "chunk": chunk if "chunked" in calls else None,
        "methods": list(calls),
    }
    with run.guard(f"diagnostics, {name}"):
        omegas, _ = outs[RK4]
        for m in calls:
            row[m] = _rates(timings[m], n_steps, batch, "body")
        for m in ("vmap", "chunked", "batch_last"):
            if m not in calls:
                continue
            sol = outs[m].raise_if_failed()
            if sol.form != "reduced":
                raise RuntimeError(f"{name}: {m} ran the {sol.form!r} march, not the reduced one.")
            row[m]["compile_s"] = timings[m]["first_call_s"] - timings[m]["second_call_s"]
            # the same equations: final velocities against RK4's (O(dt^2) apart)
            row[m]["max_abs_final_xi_diff_vs_rk4"] = float(np.max(np.abs(np.asarray(sol.xi)[:, -1] - omegas[-1])))
        mus = np.moveaxis(np.asarray(outs[HAND][0]), -1, 0)  # (B, n_steps, 3)
        row[HAND]["max_abs_momentum_diff_vs_vmap"] = float(
            np.max(np.abs(mus - np.asarray(outs["vmap"].momentum)[:, 1:]))
        )
        iters = np.asarray(outs["vmap"].stats.iterations, dtype=float)  # (B, n_steps)
        row["newton_updates_per_step"] = {
            "mean": float(iters.mean()),
            # a batched while_loop runs until its slowest member has converged
            "slowest_of_batch_mean": float(iters.max(axis=0).mean()),
        }
        if "chunked" in calls:
            row["newton_updates_per_step"]["slowest_of_chunk_mean"] = float(
                iters[: batch // chunk * chunk].reshape(batch // chunk, chunk, n_steps).max(axis=1).mean()
            )
            row["max_abs_xi_diff_chunked_vs_vmap"] = float(
                np.max(np.abs(np.asarray(outs["chunked"].xi) - np.asarray(outs["vmap"].xi)))
            )
    rate = {m: row[m]["body_steps_per_second"] for m in calls}
    row["ratios"] = {f"{m}_over_rk4_rate": rate[m] / rate[RK4] for m in calls if m != RK4}
    if "chunked" in calls:
        row["ratios"]["chunked_over_vmap_rate"] = rate["chunked"] / rate["vmap"]
    if "batch_last" in calls:
        row["ratios"]["batch_last_over_vmap_rate"] = rate["batch_last"] / rate["vmap"]
        row["max_abs_xi_diff_batch_last_vs_vmap"] = float(
            np.max(np.abs(np.asarray(outs["batch_last"].xi) - np.asarray(outs["vmap"].xi)))
        )
    row["ratios"]["vmap_over_hand_rate"] = rate["vmap"] / rate[HAND]
    row["best"] = max((m for m in calls if m not in (RK4, HAND)), key=rate.get)
    return row


# --------------------------------------------------------------------------------------------
# Part 4 (`--sweep-only`, its own results file): the documented sweep call against the yardstick
# of issue 20, final state and energy error only (no trajectories kept).

SWEEP_RESULTS_NAME = "throughput_sweep"
TWO_DEVICES = "sweep_fast_2dev"  # sweep(fast=True, devices=2), with --sweep-only (two host devices)
HAND_ROWS = "jax_by_hand_rows"  # hand_rows_march: the yardstick of issue 20, not a library path
HAND_VERIFIED = "jax_by_hand_rows_verified"  # hand_rows_march(verified=True): the same, with the sweep's checks
C_SIMD = "c_simd"  # c/rigid_body_cay.c: the hardware reference of issue 20, when a C compiler is present
SWEEP_DEFAULT = ((1_000, 200), (10_000, 200), (100_000, 200))  # the last at fast="auto"'s threshold: lean chunk
SWEEP_QUICK = ((8, 10),)
SWEEP_MIXED_DEFAULT = ((10_000, 800),)  # mixed_momenta: a few members per batch rerun on the general path
SWEEP_MIXED_QUICK = ((8, 10),)
SWEEP_INERTIA = (0.5, 0.6, 1.0)  # issue 20's table
SWEEP_TARGETS = {
    "over_hand_at_1e3": 0.5,
    "over_hand_from_1e4": 0.75,
    "over_rk4": 2.0,
    "compile_s": 2.0,
    "vortex_clusters_over_rk4_step": 1.0,
}
SWEEP_VORTEX_DEFAULT = ((4, 1000, 100), (10, 1000, 50))  # (N vortices per cluster, clusters, steps)
SWEEP_VORTEX_QUICK = ((4, 8, 5),)


def rk4_euler_final(inertia, omega0, dt, n_steps):
    """NumPy RK4 of Euler's equations 𝕀ω̇ = 𝕀ω × ω on (3, B) arrays, final ω and the largest
    |E − E⁰| over the steps (the peer of issue 20's table: no Q, no trajectory)."""
    I = np.asarray(inertia, float)[:, None]
    w = np.ascontiguousarray(np.asarray(omega0, float).T)

    def f(w):
        m = I * w
        return np.stack([m[1] * w[2] - m[2] * w[1], m[2] * w[0] - m[0] * w[2], m[0] * w[1] - m[1] * w[0]]) / I

    def energy(w):
        return 0.5 * np.sum(I * w * w, axis=0)

    E0, err = energy(w), np.zeros(w.shape[1])
    for _ in range(n_steps):
        k1 = f(w)
        k2 = f(w + 0.5 * dt * k1)
        k3 = f(w + 0.5 * dt * k2)
        k4 = f(w + dt * k3)
        w = w + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        err = np.maximum(err, np.abs(energy(w) - E0))
    return w.T, err


def mixed_momenta(batch: int) -> np.ndarray:
    """Initial angular velocities ω ~ N(0, 1) per component (seed `rigid.SEED`): body momenta
    up to |m| ~ 4, so that ~1 % of the members turn too fast for the fast path's two fixed
    updates at Δt = 0.05 (the sweep reruns those on the general path)."""
    return np.random.default_rng(rigid.SEED).normal(size=(batch, 3))


def sweep_case(batch: int, n_steps: int, run: harness.Run, mixed: bool = False) -> dict:
    """M body-steps/s of the documented sweep call (default options and with `fast=True`),
    `jit(cj.batch(integrate → final))`, the hand-written rows kernel and NumPy RK4. `mixed`:
    on `mixed_momenta`, with `fast=False` in place of `cj.batch` and the second device."""
    omega0 = mixed_momenta(batch) if mixed else rigid.initial_conditions(batch)[1]
    inertia = np.asarray(SWEEP_INERTIA)
    inertias = np.broadcast_to(inertia, (batch, 3))
    Q0 = np.broadcast_to(np.eye(3), (batch, 3, 3))
    system = models.rigid_body(jnp.asarray(inertia))

    def sweep_call(**extra):
        return lambda: cj.sweep(
            models.rigid_body, inertias, Q0, omega0, dt=rigid.DT, n_steps=n_steps, reconstruct=False, **extra
        )

    def member(q, x):
        sol = cj.integrate(system, q, x, dt=rigid.DT, n_steps=n_steps, reconstruct=False, throw=False)
        E = cj.diagnostics.energy(system, sol)
        return sol.momentum[-1], jnp.max(jnp.abs(E - E[0]))

    batched = jax.jit(cj.batch(member, chunk=min(batch, 1024)))
    Q0_j, xi0_j = jnp.asarray(Q0), jnp.asarray(omega0)
    hand = hand_rows_march(inertia, rigid.DT, n_steps)
    hand_verified = hand_rows_march(inertia, rigid.DT, n_steps, verified=True)
    calls = {
        "sweep": sweep_call(),
        "sweep_fast": sweep_call(fast=True),
        "cj_batch": lambda: jax.block_until_ready(batched(Q0_j, xi0_j)),
        HAND_ROWS: lambda: jax.block_until_ready(hand(xi0_j)),
        HAND_VERIFIED: lambda: jax.block_until_ready(hand_verified(xi0_j)),
        RK4: lambda: rk4_euler_final(inertia, omega0, rigid.DT, n_steps),
    }
    c_march, c_flags = c_kernel()
    if c_march is not None and not mixed:
        calls[C_SIMD] = lambda: c_march(inertia, rigid.DT, n_steps, omega0)
    if mixed:
        del calls["cj_batch"]
        calls["sweep_general"] = sweep_call(fast=False)
    elif len(jax.devices()) >= 2:
        calls[TWO_DEVICES] = sweep_call(fast=True, devices=2)  # the default batch size gives each device a batch
    name = f"sweep{' (mixed momenta)' if mixed else ''} B={batch} n_steps={n_steps}"
    timings, outs = run.time(calls, what=name, repeats=run.repeats or 3)
    row = {"part": "sweep_mixed" if mixed else "sweep", "batch": batch, "n_steps": n_steps, "methods": list(calls)}
    for m in calls:
        row[m] = _rates(timings[m], n_steps, batch, "body")
        row[m]["compile_s"] = timings[m]["first_call_s"] - timings[m]["second_call_s"]
    mu_hand, err_hand = (np.asarray(a) for a in outs[HAND_ROWS])
    for m in [m for m in calls if m.startswith("sweep")]:
        res = outs[m].raise_if_failed()
        row[m]["max_abs_final_momentum_diff_vs_hand"] = float(np.max(np.abs(res.final_momentum - mu_hand)))
        row[m]["max_energy_error"] = float(np.max(res.energy_error))
        row[m]["fast_chunks"], row[m]["fallback_chunks"] = res.fast_chunks, res.fallback_chunks
        row[m]["fallback_member_chunks"] = res.fallback_member_chunks
        # the share of member-chunks the general path ran again
        row[m]["fallback_share"] = res.fallback_member_chunks / max(1, res.fast_chunks * min(res.batch_size, batch))
    if mixed:
        fast, general = outs["sweep_fast"], outs["sweep_general"]
        row["sweep_fast"]["max_abs_final_momentum_diff_vs_general"] = float(
            np.max(np.abs(fast.final_momentum - general.final_momentum))
        )
    row[HAND_ROWS]["max_energy_error"] = float(np.max(err_hand))
    mu_v, err_v, passed = (np.asarray(a) for a in outs[HAND_VERIFIED])
    row[HAND_VERIFIED].update(
        max_energy_error=float(np.max(err_v)),
        verified_share=float(np.mean(passed)),
        max_abs_final_momentum_diff_vs_hand=float(np.max(np.abs(mu_v - mu_hand))),
    )
    if "cj_batch" in calls:
        row["cj_batch"]["max_energy_error"] = float(np.max(np.asarray(outs["cj_batch"][1])))
    row[RK4]["max_energy_error"] = float(np.max(outs[RK4][1]))
    if C_SIMD in calls:
        row[C_SIMD]["flags"] = c_flags
        row[C_SIMD]["max_energy_error"] = float(np.max(outs[C_SIMD][1]))
        row[C_SIMD]["max_abs_final_momentum_diff_vs_hand"] = float(np.max(np.abs(outs[C_SIMD][0] - mu_hand)))
    else:
        row["c_simd_skipped"] = c_flags
    rate = {m: row[m]["body_steps_per_second"] for m in calls}
    row["ratios"] = {
        **{f"{m}_over_hand": rate[m] / rate[HAND_ROWS] for m in calls if m != HAND_ROWS},
        **{f"{m}_over_hand_verified": rate[m] / rate[HAND_VERIFIED] for m in calls if m != HAND_VERIFIED},
        **{f"{m}_over_numpy_rk4": rate[m] / rate[RK4] for m in calls if m != RK4},
        **({f"{m}_over_c": rate[m] / rate[C_SIMD] for m in calls if m != C_SIMD} if C_SIMD in calls else {}),
    }
    return row


def sweep_vortex_case(N: int, batch: int, n_steps: int, run: harness.Run) -> dict:
    """Cost per step of the documented sweep of `batch` clusters of N point vortices (default
    options: the midpoint principle, block Newton by default for particle systems) against the
    NumPy RK4 of the same batch (`vortex_step_cost.rk4_march`), same initial conditions and dt."""
    G, Q0 = vortex.initial_conditions(N, batch)
    xi0 = np.asarray(jax.vmap(models.vortex_velocity)(jnp.asarray(G), jnp.asarray(Q0)))
    calls = {
        "sweep": lambda: cj.sweep(models.point_vortices, G, Q0, xi0, dt=vortex.DT, n_steps=n_steps),
        RK4: lambda: vortex.rk4_march(G, Q0, vortex.DT, n_steps),
    }
    timings, outs = run.time(calls, what=f"vortex clusters N={N} B={batch}", repeats=run.repeats or 3)
    row = {"part": "sweep_vortices", "N": N, "batch": batch, "n_steps": n_steps, "methods": list(calls)}
    for m in calls:
        row[m] = _rates(timings[m], n_steps, N * batch, "vortex")
        row[m]["compile_s"] = timings[m]["first_call_s"] - timings[m]["second_call_s"]
    res = outs["sweep"]
    ok = res.status == 0
    rk4_final = outs[RK4][-1]
    row["sweep"].update(
        failed_members=int(np.sum(~ok)),
        max_energy_error=float(np.nanmax(res.energy_error)),
        max_abs_final_Q_diff_vs_rk4=float(np.max(np.abs(res.final_Q[ok] - rk4_final[ok]))),
    )
    row["ratios"] = {"sweep_over_numpy_rk4_step": row["sweep"]["seconds_per_step"] / row[RK4]["seconds_per_step"]}
    return row


def print_sweep_report(summary: dict) -> None:
    harness.print_header(
        summary,
        "Sweep throughput (issue 20)",
        f"Free rigid body {SWEEP_INERTIA}, reduced CAY march (reconstruct=False), dt = {rigid.DT}; "
        "final state and energy error per body, no trajectories kept.",
    )
    rows = [r for r in summary["results"] if r["part"] == "sweep"]
    print("\nM body-steps/s (compile s) and ratios:")
    names = ("sweep", "sweep_fast", "cj_batch", HAND_ROWS, HAND_VERIFIED, RK4)
    names += (TWO_DEVICES,) if all(TWO_DEVICES in r for r in rows) else ()
    names += (C_SIMD,) if rows and all(C_SIMD in r for r in rows) else ()
    width = {m: max(20, len(m) + 1) for m in names}
    harness.print_table(
        f"{'B':>8}{'steps':>6} |" + "".join(f"{m:>{width[m]}}" for m in names) + " |"
        f"{'sweep/hand':>11}{'fast/hand':>10}{'sweep/RK4':>10}{'fast/RK4':>9} | sweep's path | fallbacks",
        (
            f"{r['batch']:>8}{r['n_steps']:>6} |"
            + "".join(
                f"{r[m]['body_steps_per_second'] / 1e6:>{width[m] - 9}.3g} ({r[m]['compile_s']:5.1f})" for m in names
            )
            + f" |{r['ratios']['sweep_over_hand']:>11.3g}{r['ratios']['sweep_fast_over_hand']:>10.3g}"
            f"{r['ratios']['sweep_over_numpy_rk4']:>10.3g}{r['ratios']['sweep_fast_over_numpy_rk4']:>9.3g} | "
            f"{'lean' if r['sweep']['fast_chunks'] else 'general':>12} | "
            f"{r['sweep_fast']['fallback_chunks']}/{r['sweep_fast']['fast_chunks']}"
            for r in rows
        ),
    )
    print(
        "Against the hand kernel with the sweep's per-step checks (hand_rows_march(verified=True); the share of "
        "members whose every step passed): sweep / verified, fast / verified, hand / verified: "
        + "; ".join(
            f"B={r['batch']}: {r['ratios']['sweep_over_hand_verified']:.3g}, "
            f"{r['ratios']['sweep_fast_over_hand_verified']:.3g}, {r['ratios'][HAND_ROWS + '_over_hand_verified']:.3g} "
            f"(passed {r[HAND_VERIFIED]['verified_share']:.1%})"
            for r in rows
        )
    )
    if TWO_DEVICES in names:
        print(
            "sweep_fast_2dev (both cores) over hand / over NumPy RK4: "
            + "; ".join(
                f"B={r['batch']}: {r['ratios'][TWO_DEVICES + '_over_hand']:.3g} / "
                f"{r['ratios'][TWO_DEVICES + '_over_numpy_rk4']:.3g}"
                for r in rows
            )
        )
    if C_SIMD in names:
        print(
            f"C kernel ({rows[0][C_SIMD]['flags']}, one thread): sweep / C, fast / C, hand / C: "
            + "; ".join(
                f"B={r['batch']}: {r['ratios']['sweep_over_c']:.3g}, {r['ratios']['sweep_fast_over_c']:.3g}, "
                f"{r['ratios'][HAND_ROWS + '_over_c']:.3g}"
                for r in rows
            )
        )
    elif rows:
        print(f"C kernel skipped: {rows[0].get('c_simd_skipped')}")
    print(
        "max energy error: "
        + "; ".join(f"B={r['batch']}: " + ", ".join(f"{m} {r[m]['max_energy_error']:.2e}" for m in names) for r in rows)
    )
    mixed = [r for r in summary["results"] if r["part"] == "sweep_mixed"]
    if mixed:
        print(
            "\nMixed momenta (omega ~ N(0, 1)): M body-steps/s (compile s); the share of member-chunks rerun "
            "on the general path:"
        )
        names = ("sweep", "sweep_fast", "sweep_general", HAND_ROWS, RK4)
        harness.print_table(
            f"{'B':>8}{'steps':>6} |" + "".join(f"{m:>20}" for m in names) + " | fast/general | fast/hand | rerun",
            (
                f"{r['batch']:>8}{r['n_steps']:>6} |"
                + "".join(f"{r[m]['body_steps_per_second'] / 1e6:>11.3g} ({r[m]['compile_s']:5.1f})" for m in names)
                + f" | {r['sweep_fast']['body_steps_per_second'] / r['sweep_general']['body_steps_per_second']:>12.3g}"
                f" | {r['ratios']['sweep_fast_over_hand']:>9.3g} | {r['sweep_fast']['fallback_share']:.2%}"
                for r in mixed
            ),
        )
    vortex_rows = [r for r in summary["results"] if r["part"] == "sweep_vortices"]
    if vortex_rows:
        print(
            "\nClusters of point vortices, documented sweep (default options) against NumPy RK4, ms per step "
            "of the whole batch:"
        )
        harness.print_table(
            f"{'N':>4}{'B':>7}{'steps':>6} |{'sweep':>10}{'RK4':>9}{'sweep/RK4':>10} | compile s | failed | "
            "max |Q - Q_RK4|",
            (
                f"{r['N']:>4}{r['batch']:>7}{r['n_steps']:>6} |{r['sweep']['seconds_per_step'] * 1e3:>10.3g}"
                f"{r[RK4]['seconds_per_step'] * 1e3:>9.3g}{r['ratios']['sweep_over_numpy_rk4_step']:>10.3g} | "
                f"{r['sweep']['compile_s']:9.1f} | {r['sweep']['failed_members']:>6} | "
                f"{r['sweep']['max_abs_final_Q_diff_vs_rk4']:.1e}"
                for r in vortex_rows
            ),
        )
    t = SWEEP_TARGETS
    print(
        f"Targets: sweep >= {t['over_hand_at_1e3']}x hand at B=1e3, >= {t['over_hand_from_1e4']}x from 1e4, "
        f">= {t['over_rk4']}x NumPy RK4, compile <= {t['compile_s']} s; vortex clusters <= "
        f"{t['vortex_clusters_over_rk4_step']}x an RK4 step (reported, never asserted)."
    )


def plot_sweep(summary: dict, path: Path) -> None:
    fig, ax = harness.figure((1,), size=(7, 4.6))
    styles = {
        "sweep": ("o", "C2"),
        "sweep_fast": ("*", "C3"),
        "cj_batch": ("D", "C0"),
        HAND_ROWS: ("^", "C7"),
        HAND_VERIFIED: ("v", "C8"),
        RK4: ("s", "C1"),
        TWO_DEVICES: ("P", "C4"),
        C_SIMD: ("x", "k"),
    }
    for m, (marker, color) in styles.items():
        pts = [
            (r["batch"], r[m]["body_steps_per_second"]) for r in summary["results"] if r["part"] == "sweep" and m in r
        ]
        if not pts:
            continue
        ax.loglog(*zip(*pts), marker=marker, color=color, label=m)
    ax.set_xlabel("batch size B (bodies)")
    ax.set_ylabel("body-steps per second")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(harness.plot_title(summary, "sweep vs hand kernel, rigid body"), fontsize=9)
    fig.savefig(path, dpi=120)


# --------------------------------------------------------------------------------------------
# Part 2: point vortices.


VORTEX_CHUNK = 64
"""Systems per chunk of `cj.batch` for the vortex batches: their members need very different
numbers of Newton updates, and a chunk's loops run until its slowest member stops."""


def vortex_case(label: str, N: int, batch: int | None, n_steps: int, run: harness.Run) -> dict:
    B = 1 if batch is None else batch
    gamma, Q0 = vortex.initial_conditions(N, B)
    name = f"vortices {label} N={N} B={B} n_steps={n_steps}"
    calls = {
        "ours": vortex.ours_call(N, batch, n_steps, gamma, Q0, "blocks", run.compiler_options),
        RK4: lambda: vortex.rk4_march(gamma, Q0, vortex.DT, n_steps),
    }
    if batch is not None:
        calls["batch_last"] = vortex.ours_call(
            N,
            batch,
            n_steps,
            gamma,
            Q0,
            "blocks",
            run.compiler_options,
            functools.partial(cj.batch, chunk=min(VORTEX_CHUNK, B)),
        )
    timings, outs = run.time(calls, what=name)
    row = {
        "part": "vortices",
        "case": label,
        "N": N,
        "batch": B,
        "n_steps": n_steps,
        "jacobian": "blocks",
        "ours": _rates(timings["ours"], n_steps, N * B, "vortex"),
        RK4: _rates(timings[RK4], n_steps, N * B, "vortex"),
    }
    with run.guard(f"diagnostics, {name}"):
        sol = outs["ours"].raise_if_failed()
        Q = np.asarray(sol.Q).reshape(B, n_steps + 1, N, 2)
        row["ours"]["compile_s"] = timings["ours"]["first_call_s"] - timings["ours"]["second_call_s"]
        iters = np.asarray(sol.stats.iterations, dtype=float).reshape(B, n_steps)
        row["newton_updates_per_step"] = {
            "mean": float(iters.mean()),
            # a batched while_loop runs until its slowest member has converged
            "slowest_of_batch_mean": float(iters.max(axis=0).mean()),
        }
        # the same equations: final positions against RK4's (O(dt^2) apart)
        row["ours"]["max_abs_final_position_diff_vs_rk4"] = float(np.max(np.abs(Q[:, -1] - outs[RK4][-1])))
        if "batch_last" in calls:
            row["batch_last"] = _rates(timings["batch_last"], n_steps, N * B, "vortex")
            row["batch_last"]["chunk"] = min(VORTEX_CHUNK, B)
            row["batch_last"]["max_abs_position_diff_vs_vmap"] = float(
                np.nanmax(np.abs(np.asarray(outs["batch_last"].raise_if_failed().Q).reshape(Q.shape) - Q))
            )
    row["ratios"] = {
        "ours_over_rk4_time_per_step": row["ours"]["seconds_per_step"] / row[RK4]["seconds_per_step"],
        "ours_over_rk4_rate": row["ours"]["vortex_steps_per_second"] / row[RK4]["vortex_steps_per_second"],
    }
    if "batch_last" in calls:
        row["ratios"]["batch_last_over_rk4_time_per_step"] = (
            row["batch_last"]["seconds_per_step"] / row[RK4]["seconds_per_step"]
        )
    return row


# --------------------------------------------------------------------------------------------
# Part 3: first-call compile time of each model, in child processes.


def compile_problem(model: str):
    """(system, Q0, xi0, dt, keywords of `integrate`) of a small, smooth run of `model`."""
    if model == "rigid_body":
        return models.rigid_body(jnp.asarray(rigid.INERTIA)), jnp.eye(3), jnp.array([0.6, -0.3, 0.9]), 0.05, {}
    if model == "heavy_top":
        system = models.heavy_top(jnp.array([1.0, 1.2, 0.5]), 1.7, (0.0, 0.6, 0.8))
        return system, cj.lie.so3_exp(jnp.array([0.3, 0.2, -0.1])), jnp.array([0.5, -0.4, 3.0]), 0.01, {}
    if model == "point_vortices":  # two leapfrogging pairs (README)
        G, Q0 = jnp.array([1.0, -1.0, 1.0, -1.0]), jnp.array([[0, 1.0], [0, -1.0], [0, 0.5], [0, -0.5]])
        return models.point_vortices(G), Q0, models.vortex_velocity(G, Q0), 0.02, {}
    if model == "peakons":  # a fast peakon overtaking a slow one
        q0, p0 = jnp.array([-3.0, 0.0]), jnp.array([2.0, 1.0])
        return models.peakons(1.0), q0, models.peakon_velocity(q0, p0, 1.0), 0.01, {"scheme": "midpoint"}
    if model == "landmarks":
        Q0 = jnp.array([[0.0, 0.0], [1.0, 0.2], [0.3, 1.1]])
        P0 = jnp.array([[0.5, 0.1], [-0.2, 0.4], [0.1, -0.3]])
        return models.landmarks(1.0), Q0, models.landmark_velocity(Q0, P0, 1.0), 0.05, {"scheme": "midpoint"}
    raise ValueError(f"unknown model {model!r}; one of {MODELS}")


def _compile_events() -> list:
    """JAX's own durations of tracing, lowering and XLA compilation (`jax.monitoring`), as
    (event, seconds, program name) from now on."""
    events = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda event, secs, **kw: events.append((event.rsplit("/", 1)[-1], secs, kw.get("fun_name")))
    )
    return events


def _where_compile_time_goes(events: list) -> dict:
    """Sums of JAX's compile-time events of one call; XLA compilations by program: the largest
    one (the march) and the many small ones (JAX compiles every eager operation outside a
    `jax.jit` as a program of its own)."""
    out = {}
    for event, secs, _ in events:
        entry = out.setdefault(event.removesuffix("_duration"), {"s": 0.0, "count": 0})
        entry["s"] += secs
        entry["count"] += 1
    xla = sorted(((secs, name) for event, secs, name in events if event == "backend_compile_duration"), reverse=True)
    if xla:
        out["largest_backend_compile"] = {"s": xla[0][0], "program": xla[0][1]}
    return out


def first_call_cost(model_names, cache_dir=None) -> list:
    """In this (fresh) process: for each model, the first and a second identical `integrate`
    call; compile time = first - second, with JAX's account of where it went. With `cache_dir`
    the persistent compilation cache is on (`cj.enable_compilation_cache`), and the rows count
    its hits and misses."""
    if cache_dir is not None:
        cj.enable_compilation_cache(cache_dir)
    cache_events = {"hits": 0, "misses": 0}

    def count(event, **kw):
        if event.startswith("/jax/compilation_cache/cache_"):
            key = event.rsplit("_", 1)[-1]
            cache_events[key] = cache_events.get(key, 0) + 1

    jax.monitoring.register_event_listener(count)
    events = _compile_events()
    tic = time.perf_counter()
    jax.block_until_ready(jax.jit(jnp.sin)(jnp.arange(3.0)))  # backend and XLA start-up, not a model's
    first_jit = time.perf_counter() - tic
    rows = []
    for model in model_names:
        system, Q0, xi0, dt, kwargs = compile_problem(model)

        def call():
            return jax.block_until_ready(cj.integrate(system, Q0, xi0, dt=dt, n_steps=COMPILE_N_STEPS, **kwargs))

        load = harness.load_average()
        events.clear()
        cache_events.update(hits=0, misses=0)
        tic = time.perf_counter()
        sol = call()
        first = time.perf_counter() - tic
        first_call_events = list(events)
        tic = time.perf_counter()
        call()
        second = time.perf_counter() - tic
        rows.append(
            {
                "part": "compile",
                "case": model,
                "form": sol.form,
                "scheme": sol.scheme,
                "n_steps": COMPILE_N_STEPS,
                "dt": dt,
                "keywords": kwargs,
                "first_call_s": first,
                "second_call_s": second,
                "compile_s": first - second,
                "process_first_jit_s": first_jit,
                "first_call_jax_events": _where_compile_time_goes(first_call_events),
                "persistent_cache": None if cache_dir is None else dict(cache_events),
                "load_average_1min_at_start": load,
            }
        )
    return rows


def _child(model_names: tuple, run: harness.Run, cache_dir: str) -> list:
    """`first_call_cost(model_names, cache_dir)` in a child process (`--compile-model`)."""
    cmd = [
        sys.executable,
        str(Path(__file__).resolve()),
        "--compile-model",
        ",".join(model_names),
        "--compile-cache",
        cache_dir,
    ]
    if run.quick:
        cmd.append("--quick")
    with run.guard(f"compile time of {', '.join(model_names)}"):
        done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"the compile-time child for {model_names} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def compile_case(model_names: tuple, run: harness.Run) -> list:
    """The cold child, then the warm one on the programs it left in a fresh cache directory."""
    with tempfile.TemporaryDirectory(prefix="clebsch-jax-xla-") as cache_dir:
        cold = _child(model_names, run, cache_dir)
        warm = _child(model_names, run, cache_dir)
    for row, again in zip(cold, warm):
        row["warm"] = {
            k: again[k]
            for k in (
                "first_call_s",
                "second_call_s",
                "compile_s",
                "first_call_jax_events",
                "persistent_cache",
                "load_average_1min_at_start",
            )
        }
    return cold


# --------------------------------------------------------------------------------------------
# Targets.


def _verdicts(rigid_rows: list, vortex_rows: list, compile_rows: list) -> dict:
    t = TARGETS
    # the batches the rate targets speak of: B >= 10^3 (with --quick: every B > 1)
    batched = [r for r in rigid_rows if r["batch"] >= t["flat_from_batch"]] or [r for r in rigid_rows if r["batch"] > 1]
    best = {r["batch"]: r[r["best"]]["body_steps_per_second"] for r in batched}
    over_rk4 = {r["batch"]: r["ratios"][f"{r['best']}_over_rk4_rate"] for r in batched}

    def flatness(rates: dict):
        return None if len(rates) < 2 else min(rates.values()) / max(rates.values())

    flat = {
        m: flatness({r["batch"]: r[m]["body_steps_per_second"] for r in batched if m in r})
        for m in ("vmap", "chunked", "batch_last")
    }
    flat["best"] = flatness(best)
    at_N = [r for r in vortex_rows if r["case"] == "single" and r["N"] == t["vortex_N"]]
    vortex_ratio = at_N[0]["ratios"]["ours_over_rk4_time_per_step"] if at_N else None
    compile_s = {r["case"]: r["compile_s"] for r in compile_rows}
    warm_s = {r["case"]: r["warm"]["compile_s"] for r in compile_rows if "warm" in r}
    return {
        "rigid_body_rate": {
            "min_body_steps_per_second": t["rigid_body_steps_per_second"],
            "best_per_batch": best,
            "met": bool(best) and all(v >= t["rigid_body_steps_per_second"] for v in best.values()),
        },
        "rigid_body_over_rk4": {
            "min_rate_ratio": t["rigid_body_over_rk4_rate"],
            "best_per_batch": over_rk4,
            "met": bool(over_rk4) and all(v >= t["rigid_body_over_rk4_rate"] for v in over_rk4.values()),
        },
        "rigid_body_flat": {
            "batches": sorted(best),
            "min_fraction_of_best": t["flat_fraction"],
            "min_over_max_rate": flat,
            "met": None if flat["best"] is None else bool(flat["best"] >= t["flat_fraction"]),
        },
        "vortex_step_cost": {
            "N": t["vortex_N"],
            "max_ours_over_rk4_time_per_step": t["vortex_ours_over_rk4_time_per_step"],
            "ours_over_rk4_time_per_step": vortex_ratio,
            "met": None if vortex_ratio is None else bool(vortex_ratio <= t["vortex_ours_over_rk4_time_per_step"]),
        },
        "compile": {
            "max_s": t["compile_s"],
            "per_model": compile_s,
            "met": bool(compile_s) and all(v <= t["compile_s"] for v in compile_s.values()),
            "warm_per_model": warm_s,
            "warm_met": bool(warm_s) and all(v <= t["compile_s"] for v in warm_s.values()),
        },
    }


# --------------------------------------------------------------------------------------------
# Printing and plotting.


def _verdict(v: dict) -> str:
    return {True: "met", False: "NOT met", None: "not measured"}[v["met"]]


def _jax_events(e: dict) -> str:
    def s(k):
        return e.get(k, {}).get("s", 0.0)

    xla = f"{s('backend_compile'):.2f} ({e.get('backend_compile', {}).get('count', 0)})"
    return f"{s('jaxpr_trace'):>6.2f}{s('jaxpr_to_mlir_module'):>6.2f}{xla:>16}{s('largest_backend_compile'):>8.2f}"


def print_report(summary: dict) -> None:
    parts = harness.rows_by(summary["results"], "part")
    fmt, v = harness.fmt, summary["targets"]
    harness.print_header(
        summary,
        "Throughput",
        f"Rigid body (2, 1, 2/3), reduced march (Cayley), dt = {rigid.DT}: vmap = jit(vmap(integrate)) over B "
        f"bodies, chunked = jit(lax.map(..., batch_size={summary['config']['chunk']})), batch_last = jit(cj.batch(..., "
        f"chunk={summary['config']['chunk']}));\n  point vortices, "
        f"dt = {vortex.DT}, jacobian='blocks': single = one plain integrate call, vmap = jit(vmap) over B systems; "
        "NumPy RK4s of the same equations.",
    )

    print(
        "\nRigid body: body-steps per second (rate ratios; Newton updates per step of the slowest member of the "
        "batch / of a chunk):"
    )
    harness.print_table(
        f"{'B':>8}{'steps':>6} |{'vmap':>10}{'chunked':>10}{'batch':>10}{'NumPy RK4':>11}{'JAX hand':>10} |"
        f"{'vmap/RK4':>9}{'chunk/RK4':>10}{'batch/RK4':>10}{'chunk/vmap':>11}{'vmap/hand':>10} {'best':<8}|"
        f"{'upd/batch':>10}{'upd/chunk':>10}",
        (
            f"{r['batch']:>8}{r['n_steps']:>6} |{r['vmap']['body_steps_per_second']:>10.3g}"
            f"{fmt(r.get('chunked', {}).get('body_steps_per_second'), '.3g', 10)}"
            f"{fmt(r.get('batch_last', {}).get('body_steps_per_second'), '.3g', 10)}"
            f"{r[RK4]['body_steps_per_second']:>11.3g}{fmt(r.get(HAND, {}).get('body_steps_per_second'), '.3g', 10)} |"
            f"{r['ratios']['vmap_over_rk4_rate']:>9.3g}"
            f"{fmt(r['ratios'].get('chunked_over_rk4_rate'), '.3g', 10)}"
            f"{fmt(r['ratios'].get('batch_last_over_rk4_rate'), '.3g', 10)}"
            f"{fmt(r['ratios'].get('chunked_over_vmap_rate'), '.3g', 11)}"
            f"{fmt(r['ratios'].get('vmap_over_hand_rate'), '.3g', 10)} {r['best']:<8}|"
            f"{r['newton_updates_per_step']['slowest_of_batch_mean']:>10.2f}"
            f"{fmt(r['newton_updates_per_step'].get('slowest_of_chunk_mean'), '.2f', 10)}"
            for r in parts.get("rigid_body", [])
        ),
    )
    rate, over, flat = v["rigid_body_rate"], v["rigid_body_over_rk4"], v["rigid_body_flat"]
    print(
        f"Target >= {rate['min_body_steps_per_second']:.3g} body-steps/s for B in {flat['batches']}: "
        f"{_verdict(rate)} (best per B: {', '.join(f'{x:.3g}' for x in rate['best_per_batch'].values())})."
    )
    print(
        f"Target >= {over['min_rate_ratio']:g}x the NumPy RK4 rate: {_verdict(over)} "
        f"(best per B: {', '.join(f'{x:.3g}x' for x in over['best_per_batch'].values())})."
    )
    print(
        f"Target flat over B in {flat['batches']} (min rate >= {flat['min_fraction_of_best']:g} x max rate): "
        f"{_verdict(flat)} (min/max: "
        + ", ".join(f"{m} {fmt(x, '.2f', 1, 'n/a')}" for m, x in flat["min_over_max_rate"].items())
        + ")."
    )
    hand = [r for r in parts.get("rigid_body", []) if HAND in r]
    if hand:
        print(
            f"Reference, the same step written by hand in JAX ({HAND_UPDATES} chord updates, no checks): "
            + ", ".join(f"B={r['batch']} {r[HAND]['body_steps_per_second']:.3g}/s" for r in hand)
            + f"; its momenta differ from ours by <= "
            f"{max(r[HAND]['max_abs_momentum_diff_vs_vmap'] for r in hand):.1e}."
        )

    print(
        "\nPoint vortices: vortex-steps per second (seconds per step of the whole batch); Newton updates per "
        "step (mean; slowest member of the batch):"
    )
    harness.print_table(
        f"{'case':<7}{'N':>5}{'B':>6}{'steps':>6} |{'ours':>22}{'NumPy RK4':>22} |{'ours/RK4 time per step':>23}"
        f"{'batch/RK4':>12}"
        f" |{'upd mean':>9}{'slowest':>8}",
        (
            f"{r['case']:<7}{r['N']:>5}{r['batch']:>6}{r['n_steps']:>6} |"
            + "".join(
                f"{r[m]['vortex_steps_per_second']:>10.3g} ({r[m]['seconds_per_step']:8.2e})" for m in ("ours", RK4)
            )
            + f" |{r['ratios']['ours_over_rk4_time_per_step']:>23.3g}"
            f"{fmt(r['ratios'].get('batch_last_over_rk4_time_per_step'), '.3g', 12)} |{r['newton_updates_per_step']['mean']:>9.2f}"
            f"{r['newton_updates_per_step']['slowest_of_batch_mean']:>8.2f}"
            for r in parts.get("vortices", [])
        ),
    )
    vx = v["vortex_step_cost"]
    print(
        f"Target one step <= {vx['max_ours_over_rk4_time_per_step']:g}x one RK4 step at N = {vx['N']}: {_verdict(vx)}"
        + ("" if vx["ours_over_rk4_time_per_step"] is None else f" ({vx['ours_over_rk4_time_per_step']:.3g}x)")
        + "."
    )

    print(
        f"\nCompile time of each model's first integrate call ({COMPILE_N_STEPS} steps), in a fresh process: "
        "first call - second call [s]:"
    )
    rows = [
        (label, r, d)
        for r in parts.get("compile", [])
        for label, d in (("cold", r), ("warm", r.get("warm")))
        if d is not None
    ]
    harness.print_table(
        f"{'model':<16}{'form':<9}{'scheme':<10}{'cache':<6}{'first':>8}{'second':>8}{'compile':>9}{'load':>6} | "
        f"{'trace':>6}{'lower':>6}{'XLA (programs)':>16}{'largest':>8}{'hits':>6}",
        (
            f"{r['case']:<16}{r['form']:<9}{r['scheme']:<10}{label:<6}{d['first_call_s']:>8.2f}{d['second_call_s']:>8.3f}"
            f"{d['compile_s']:>9.2f}{d['load_average_1min_at_start']:>6.2f} | {_jax_events(d['first_call_jax_events'])}"
            f"{fmt((d.get('persistent_cache') or {}).get('hits'), 'd', 6)}"
            for label, r, d in rows
        ),
    )
    print(
        "  (JAX's own durations during the first call [s]: tracing to jaxprs, lowering to MLIR, XLA compilation "
        "summed over all programs\n  compiled, with their number, and the largest program; every eager "
        "operation outside a jit is a program of its own.)"
    )
    c = v["compile"]
    print(
        f"Target <= {c['max_s']:g} s per model: {_verdict(c)} (cold: a new cache); with the programs in "
        f"the persistent cache (warm): {_verdict({'met': c.get('warm_met') if c.get('warm_per_model') else None})}."
    )


def plot(summary: dict, path: Path) -> None:
    parts = harness.rows_by(summary["results"], "part")
    fig, (ax, ax_v, ax_c) = harness.figure((3, 2, 1.4), size=(14, 4.8))
    rows = parts.get("rigid_body", [])
    styles = {
        "vmap": ("o", "C2", "ours, jit(vmap)"),
        "chunked": ("D", "C0", "ours, lax.map over chunks of vmap"),
        "batch_last": ("*", "C3", "ours, jit(cj.batch): batch-last, in chunks"),
        RK4: ("s", "C1", "NumPy RK4 (broadcast)"),
        HAND: ("^", "C7", "reference: the same step in JAX by hand"),
    }
    for m, (marker, color, label) in styles.items():
        pts = [(r["batch"], r[m]["body_steps_per_second"]) for r in rows if m in r]
        if pts:
            ax.loglog(*zip(*pts), marker=marker, color=color, label=label)
    t = summary["targets"]["rigid_body_rate"]["min_body_steps_per_second"]
    ax.axhline(t, color="k", ls=":", lw=1.0, label=f"issue target {t:.0e}/s")
    ax.set_xlabel("batch size B (bodies)")
    ax.set_ylabel("body-steps per second")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(harness.plot_title(summary, "Rigid body, reduced march, dt = 0.05"), fontsize=9)

    for r in parts.get("vortices", []):
        for m, (marker, color) in (("ours", ("o", "C0")), (RK4, ("s", "C1")), ("batch_last", ("*", "C3"))):
            if m in r:
                ax_v.loglog(
                    [r["N"] * r["batch"]],
                    [r[m]["vortex_steps_per_second"]],
                    marker=marker,
                    color=color,
                    mfc=color if r["case"] == "single" else "none",
                    ms=8,
                    ls="none",
                )
        ax_v.annotate(
            f"{r['N']}x{r['batch']}",
            (r["N"] * r["batch"], r["ours"]["vortex_steps_per_second"]),
            textcoords="offset points",
            xytext=(5, 4),
            fontsize=7,
        )
    ax_v.plot([], [], "o", color="C0", label="ours, jacobian='blocks'")
    ax_v.plot([], [], "*", color="C3", mfc="none", label=f"ours, cj.batch (chunk {VORTEX_CHUNK})")
    ax_v.plot([], [], "s", color="C1", label="NumPy RK4")
    ax_v.legend(
        handles=ax_v.get_legend_handles_labels()[0] + [harness.hollow_marker("hollow: jit(vmap) batch")], fontsize=8
    )
    ax_v.set_xlabel("vortices per step, N x B")
    ax_v.set_ylabel("vortex-steps per second")
    ax_v.grid(True, which="both", alpha=0.3)
    ax_v.set_title("Point vortices (labels N x B)", fontsize=9)

    rows = parts.get("compile", [])
    y = np.arange(len(rows))
    ax_c.barh(y - 0.2, [r["compile_s"] for r in rows], height=0.4, color="C0", label="cold")
    ax_c.barh(
        y + 0.2,
        [r["warm"]["compile_s"] if "warm" in r else np.nan for r in rows],
        height=0.4,
        color="C2",
        label="warm (persistent cache)",
    )
    ax_c.set_yticks(y, [r["case"] for r in rows])
    ax_c.axvline(TARGETS["compile_s"], color="k", ls=":", lw=1.0, label=f"target {TARGETS['compile_s']:g} s")
    ax_c.set_ylim(len(rows) + 1.0, -0.6)  # top to bottom, an empty row at the bottom for the legend
    ax_c.set_xlabel("first call - second call [s]")
    ax_c.legend(fontsize=8, loc="lower right")
    ax_c.set_title("compile time per model", fontsize=9)
    fig.savefig(path, dpi=120)


# --------------------------------------------------------------------------------------------


def _add_arguments(parser: argparse.ArgumentParser) -> None:
    # the child process of part 3: measure these models (comma-separated) and print JSON
    parser.add_argument("--compile-model", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--compile-cache", default=None, help=argparse.SUPPRESS)
    parser.add_argument(
        "--sweep-only",
        action="store_true",
        help=f"only part 4, the sweep against the hand kernel ({SWEEP_RESULTS_NAME}.json/.png)",
    )


def main(argv=None) -> dict | None:
    """Runs the three parts, prints the report, writes the JSON and the PNG; returns the summary."""
    argv = sys.argv[1:] if argv is None else argv
    run = harness.Run(
        SWEEP_RESULTS_NAME if "--sweep-only" in argv else RESULTS_NAME,
        argv,
        description="Throughput of the built-in models against NumPy RK4s, "
        "and their compile times (see module docstring).",
        add_arguments=_add_arguments,
    )
    if run.args.sweep_only:
        with run:
            rows = run.measure(
                SWEEP_DEFAULT, SWEEP_QUICK, lambda B, n: f"sweep B={B} n_steps={n}", lambda B, n: sweep_case(B, n, run)
            )
            rigid_cases = run.cases
            rows += run.measure(
                SWEEP_MIXED_DEFAULT,
                SWEEP_MIXED_QUICK,
                lambda B, n: f"sweep (mixed momenta) B={B} n_steps={n}",
                lambda B, n: sweep_case(B, n, run, mixed=True),
            )
            mixed_cases = run.cases
            rows += run.measure(
                SWEEP_VORTEX_DEFAULT,
                SWEEP_VORTEX_QUICK,
                lambda N, B, n: f"sweep of {B} clusters of {N} vortices, n_steps={n}",
                lambda N, B, n: sweep_vortex_case(N, B, n, run),
            )
        summary = run.summary(
            config={
                "inertia": list(SWEEP_INERTIA),
                "dt": rigid.DT,
                "seed": rigid.SEED,
                "cases": [{"batch": b, "n_steps": n} for b, n in rigid_cases],
                "mixed_momenta_cases": [{"batch": b, "n_steps": n} for b, n in mixed_cases],
                "vortex_clusters": {
                    "dt": vortex.DT,
                    "seed": vortex.SEED,
                    "cases": [{"N": N, "batch": b, "n_steps": n} for N, b, n in run.cases],
                },
            },
            results=rows,
            targets=SWEEP_TARGETS,
        )
        return run.finish(summary, print_sweep_report, plot_sweep)
    if run.args.compile_model:  # a child of part 3
        with harness.quick_mode(run.quick):
            print(json.dumps(first_call_cost(run.args.compile_model.split(","), run.args.compile_cache)))
        return None
    chunk = CHUNK_QUICK if run.quick else CHUNK
    # a fresh process for each model; --quick: one child for two models (a smoke test)
    compile_groups = ((MODELS_QUICK,),) if run.quick else tuple(((m,),) for m in MODELS)
    with run:
        rigid_rows = run.measure(
            RIGID_DEFAULT,
            RIGID_QUICK,
            lambda B, n: f"rigid body B={B} n_steps={n}",
            lambda B, n: rigid_case(B, n, chunk, run),
        )
        vortex_rows = run.measure(
            VORTEX_DEFAULT,
            VORTEX_QUICK,
            lambda label, N, B, n: f"vortices {label} N={N} B={B or 1} n_steps={n}",
            lambda *case: vortex_case(*case, run),
        )
        compile_rows = run.measure(
            compile_groups,
            compile_groups,
            lambda names: f"compile time of {', '.join(names)} (child process)",
            lambda names: compile_case(names, run),
        )
    compile_rows = [r for rows in compile_rows for r in rows]
    summary = run.summary(
        config={
            "chunk": chunk,
            "rigid_body": {
                "inertia": list(rigid.INERTIA),
                "dt": rigid.DT,
                "march": "reduce=True (Cayley)",
                "cases": [{"batch": b, "n_steps": n} for b, n in (RIGID_QUICK if run.quick else RIGID_DEFAULT)],
                "long_call": {"min_body_steps": LONG_CALL_BODY_STEPS, "repeats": LONG_CALL_REPEATS},
            },
            "vortices": {
                "dt": vortex.DT,
                "jacobian": "blocks",
                "cases": [
                    {"case": c, "N": N, "batch": b or 1, "n_steps": n}
                    for c, N, b, n in (VORTEX_QUICK if run.quick else VORTEX_DEFAULT)
                ],
            },
            "compile": {
                "models": list(MODELS_QUICK if run.quick else MODELS),
                "n_steps": COMPILE_N_STEPS,
                "child_processes": [list(g[0]) for g in compile_groups],
            },
            "seed": rigid.SEED,
        },
        results=rigid_rows + vortex_rows + compile_rows,
        targets=_verdicts(rigid_rows, vortex_rows, compile_rows),
    )
    return run.finish(summary, print_report, plot)


if __name__ == "__main__":
    main()
