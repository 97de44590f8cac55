r"""Work-precision on long ensembles (issue 41): ours through `cj.sweep` on its native path against
heyoka (Taylor's method, LLVM-compiled, SIMD batch mode) and diffrax, in one process, on the same
initial conditions. Run through `work_precision.py`:

    python benchmarks/work_precision.py --ensembles       # both ensembles, all peers
    python benchmarks/work_precision.py --long-horizon    # energy error over T = 1e5 for a few bodies
    python benchmarks/work_precision.py --long-horizon --horizon 1e6
    python benchmarks/work_precision.py --ensembles --quick   # smoke test (not a measurement)
    python benchmarks/work_precision.py --ensembles --plans-only  # the accuracy plans alone

written as `work_precision_ensembles.{json,png}` and `work_precision_long_horizon.{json,png}`
(`--plans-only`: `work_precision_ensemble_plans.{json,png}`: the reference and, per accuracy,
the ensemble plan beside the plan piloted on the first member alone).

**Scenes** (`work_precision.RigidBody` and `work_precision.VortexClusters`, their initial
conditions and diagnostics):

- `rigid_body`: B free rigid bodies (64; `--batch`), inertia (2, 1, 2/3), the `--long` scene's
  unit body momenta (`rigid_initial`), T = 1e4. Euler's equations $\dot\Pi = \Pi\times\mathbb I^{-1}\Pi$.
- `vortex_clusters`: B leapfrogging clusters of 4 vortices (16; `--clusters-batch`),
  $\Gamma = (1, -1, 1, -1)$, `cluster_initial`, T = 1e3. Biot-Savart:
  $\dot x_a = -\sum_{b\ne a}\Gamma_b (y_a - y_b)/(2\pi r_{ab}^2)$,
  $\dot y_a = \sum_{b\ne a}\Gamma_b (x_a - x_b)/(2\pi r_{ab}^2)$.

**Peers**, each on one thread (so the comparison is per core; the CPU time of the process is
recorded beside the wall time):

- **heyoka** `taylor_adaptive_batch` with `batch_size = heyoka.recommended_simd_size()`, the
  equations above written in heyoka's expression system (independently of `clebsch_jax`), one
  integrator per tolerance (compiled outside the timing: `compile_s`), the ensemble run as
  consecutive groups of `batch_size` members (state and time reset per group), each by
  `propagate_grid` over the `n_samples + 1` sample times. Tolerances 1e-8 ... 1e-16.
- **ours** `cj.sweep(model, params, Q0, xi0, dt=..., n_steps=T/dt, threads=1, backend=...)`:
  `backend="native"` wherever the sweep accepts it (it refuses otherwise, with the reason, which
  is recorded and the point run with `backend="xla"`, labelled so). Rigid body
  (`models.rigid_body`, `reconstruct=False`): the reduced Cayley march (order 2) and its
  compositions (Suzuki 4, Kahan-Li 6 and 8), Gauss-Legendre orders 4, 6, 8; and Gauss-Legendre
  orders 4, 6, 8 on the body in Clebsch variables on R³ (`models.rigid_body_vector`, each body's
  (Q, P) from `rigid_body_vector_start(Π0)`, labelled `vgauss`), with orders 12 and 16 there (native
  too: their programs are within `backend="auto"`'s compile budget). Clusters
  (`models.point_vortices`): the midpoint principle and its compositions, Gauss-Legendre orders 4,
  6, 8, 12 with the constraint matrix as per-vortex blocks (`jacobian="blocks"`, exact for point
  vortices), native when asked for (under `"auto"` their programs, 46 000-127 000 lines of LLVM IR,
  would mostly stay on XLA). A warm-up sweep of one chunk compiles (or loads) the kernel first. Every
  solve to its default stopping rule.
- **diffrax** Dopri8 (rtol 1e-8, 1e-10, 1e-12) and Tsit5 (1e-8, 1e-10): `work_precision.diffrax_program`
  (`PIDController`, atol = rtol * scale, `jit(vmap)` over the members, each its own steps).

**Measures** per point:

- `wall_s`: median of up to `--repeats` (default 3) calls of the whole ensemble; after the first
  sample, more while their total stays below `--point-budget` seconds (default 60), so the
  costliest points have fewer samples (`samples_s` says how many). Every call blocks until its
  result is ready. `load` beside each point: `os.getloadavg()` after it.
- `global_error`: at T, max over members of the distance to the reference (rigid body
  $|\Pi - \Pi_{ref}|$, $|\Pi_0| = 1$; clusters max over vortices of $|Q_a - Q_{a,ref}|$ divided
  by the scene's scale max $|Q_0|$), so relative to the size of the initial state.
- `energy_error`: max over time and members of $|E - E_0|/|E_0|$: ours at every node (the
  sweep's `energy_error` over its `initial["energy"]`, which is checked against this script's own
  energy at node 0), the peers at the `n_samples + 1` sample times (heyoka's grid, diffrax's
  dense output).
- **Reference**: heyoka's scalar `taylor_adaptive` in extended precision (`numpy.longdouble`,
  80-bit on x86-64) at tol 1e-18, member by member; its error is estimated by its distance to a
  second extended-precision run at tol 1e-16 (another Taylor order) on the first members
  (`reference.check`). Without heyoka: diffrax Dopri8 at rtol 1e-14 (the other modes' reference).

**Targets** (issue 41, reported, never asserted): for each heyoka tolerance from 1e-8 to 1e-14, a
point of ours no slower with global error no larger and energy error no larger (or <= 1e-12);
for each diffrax point, a point of ours no slower, global error no larger and energy error >= 100x
smaller (or <= 1e-13). Each row names the fastest qualifying point of ours, else the fastest
point that is accurate enough however slow, with its time ratio to the peer.

**Long horizon** (`--long-horizon`): a few bodies (4, one heyoka batch) of the rigid-body scene
for T = 1e5 (`--horizon`); the relative energy error at 1000 equally spaced times for ours (one
symplectic method, run as 1000 consecutive sweeps each continuing from the last momentum),
heyoka at every tolerance (the one closest to ours in cost is marked) and diffrax Dopri8.
"""

from __future__ import annotations

import math
import os
import statistics
import time
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import _timing as harness
import clebsch_jax as cj
import work_precision as wp
from clebsch_jax import models

OURS, HEYOKA, DIFFRAX = "ours", "heyoka", "diffrax"
REF_TOL = 1e-18  # extended-precision reference (heyoka scalar, long double)
REF_CHECK_TOL = 1e-16
REF_CHECK_MEMBERS = 4
HEYOKA_TARGET_TOLS = (1e-14, 1e-8)  # the issue's range of heyoka tolerances
HEYOKA_ENERGY_FLOOR = 1e-12  # "energy error no larger (or <= 1e-12)"
DIFFRAX_ENERGY_RATIO = 100.0  # "energy error >= 100x smaller ..."
DIFFRAX_ENERGY_FLOOR = 1e-13  # "... or at round-off"
CHUNK = 100  # the sweep's default chunk: T / dt must be a multiple of it

# ours: (method label, sweep options, dts). The backend is native where the sweep takes it.
ENSEMBLES = {
    "rigid_body": {
        "batch": 64,
        "T": 1e4,
        "n_samples": 100,
        "ours": [
            ("order2", {"order": 2}, (0.1,)),
            ("order4", {"order": 4}, (0.2, 0.1)),
            ("order6", {"order": 6}, (0.25, 0.125)),
            ("order8", {"order": 8}, (0.5, 0.25, 0.125)),
            ("gauss4", {"scheme": "gauss", "order": 4}, (0.2, 0.1)),
            ("gauss6", {"scheme": "gauss", "order": 6}, (0.5, 0.25)),
            ("gauss8", {"scheme": "gauss", "order": 8}, (1.0, 0.5, 0.25, 0.125)),
            ("vgauss4", {"model": "vector", "scheme": "gauss", "order": 4}, (0.1,)),
            ("vgauss6", {"model": "vector", "scheme": "gauss", "order": 6}, (0.25,)),
            ("vgauss8", {"model": "vector", "scheme": "gauss", "order": 8}, (0.5, 0.25, 0.125)),
            ("vgauss12", {"model": "vector", "scheme": "gauss", "order": 12}, (0.5,)),
            ("vgauss16", {"model": "vector", "scheme": "gauss", "order": 16}, (1.0,)),
        ],
        "plans": (1e-4, 1e-6, 1e-8),  # cj.choose_step's method and step for these accuracies
        "heyoka": (1e-8, 1e-10, 1e-12, 1e-14, 1e-16),
        "tsit5": (1e-8, 1e-10),
        "dopri8": (1e-8, 1e-10, 1e-12),
    },
    "vortex_clusters": {
        "batch": 16,
        "T": 1e3,
        "n_samples": 100,
        "ours": [
            ("order2", {"order": 2}, (0.05, 0.025)),
            ("order4", {"order": 4}, (0.1, 0.05)),
            ("order6", {"order": 6}, (0.2, 0.1)),
            ("order8", {"order": 8}, (0.25, 0.125)),
            # the constraint matrix as per-vortex blocks: exact for point vortices (the same steps
            # bit for bit), a smaller program and a cheaper step than the dense 8 x 8 matrix
            ("gauss4", {"scheme": "gauss", "order": 4, "jacobian": "blocks"}, (0.1, 0.05)),
            ("gauss6", {"scheme": "gauss", "order": 6, "jacobian": "blocks"}, (0.25, 0.125)),
            ("gauss8", {"scheme": "gauss", "order": 8, "jacobian": "blocks"}, (0.5, 0.25, 0.125)),
            ("gauss12", {"scheme": "gauss", "order": 12, "jacobian": "blocks"}, (0.5, 0.25)),
        ],
        "plans": (1e-4, 1e-6, 1e-8),
        "heyoka": (1e-8, 1e-10, 1e-12, 1e-14, 1e-16),
        "tsit5": (1e-8, 1e-10),
        "dopri8": (1e-8, 1e-10, 1e-12),
    },
}
QUICK_ENSEMBLES = {
    "rigid_body": {
        "batch": 8,
        "T": 20.0,
        "n_samples": 10,
        "ours": [
            ("order4", {"order": 4}, (0.1,)),
            ("gauss8", {"scheme": "gauss", "order": 8}, (0.2,)),
            ("vgauss8", {"model": "vector", "scheme": "gauss", "order": 8}, (0.2,)),
        ],
        "plans": (1e-6,),
        "heyoka": (1e-10, 1e-14),
        "tsit5": (1e-8,),
        "dopri8": (1e-10,),
    },
    "vortex_clusters": {
        "batch": 4,
        "T": 2.0,
        "n_samples": 4,
        "ours": [
            ("order2", {"order": 2}, (0.02,)),
            ("gauss8", {"scheme": "gauss", "order": 8, "jacobian": "blocks"}, (0.2,)),
        ],
        "plans": (1e-6,),
        "heyoka": (1e-10, 1e-14),
        "tsit5": (),
        "dopri8": (1e-10,),
    },
}
DEFAULT_HORIZON = 1e5
LONG_HORIZON = {
    "batch": 4,
    "n_samples": 1000,
    "ours": ("gauss8", {"scheme": "gauss", "order": 8}, 0.25),
    "heyoka": (1e-10, 1e-12, 1e-14, 1e-16),
    "dopri8": (1e-10, 1e-12),
}
QUICK_LONG_HORIZON = {
    "batch": 4,
    "n_samples": 10,
    "ours": ("gauss8", {"scheme": "gauss", "order": 8}, 0.25),
    "heyoka": (1e-12,),
    "dopri8": (1e-10,),
}


def heyoka_module():
    """heyoka, or None when it is not installed (it is in the `bench` extra only)."""
    try:
        import heyoka
    except ImportError:
        return None
    return heyoka


def load3() -> list | None:
    """The 1-, 5- and 15-minute load averages (`uptime`'s)."""
    return list(os.getloadavg()) if hasattr(os, "getloadavg") else None


# --------------------------------------------------------------------------------------------
# Scenes: the equations for heyoka, ours' sweep arguments, the energy.


class RigidEnsemble(wp.RigidBody):
    """`work_precision.RigidBody` with heyoka's equations and ours' sweep arguments."""

    def heyoka_system(self, hy):
        """Euler's equations $\\dot\\Pi = \\Pi\\times\\mathbb I^{-1}\\Pi$ (state (Π1, Π2, Π3))."""
        x, y, z = hy.make_vars("x", "y", "z")
        w = [v / float(i) for v, i in zip((x, y, z), self.inertia)]
        return [(x, y * w[2] - z * w[1]), (y, z * w[0] - x * w[2]), (z, x * w[1] - y * w[0])]

    def flat(self, y):  # (B, 3) <-> (B, n_eq)
        return np.asarray(y).reshape(len(y), -1)

    def unflat(self, y):
        return np.asarray(y).reshape(len(y), 3)

    def energy(self, ys):
        """E = ½ Σ Π²/I of states (..., 3)."""
        return 0.5 * np.sum(np.asarray(ys) ** 2 / self.inertia, -1)

    def sweep_args(self, model=None):
        """(make_system, params, Q0, xi0, options) of `cj.sweep`: `models.rigid_body` (the reduced
        march, Q not reconstructed), or with `model="vector"` `models.rigid_body_vector` (each
        body's (Q, P) from `rigid_body_vector_start(Π0)`)."""
        inertia, m = jnp.asarray(self.inertia), jnp.asarray(self.y0)
        if model == "vector":
            Q0, P0 = jax.vmap(models.rigid_body_vector_start)(m)
            return models.rigid_body_vector, inertia[None], Q0, m / inertia, {"P0": P0}
        Q0 = jnp.broadcast_to(jnp.eye(3), (self.members, 3, 3))
        return models.rigid_body, inertia[None], Q0, m / inertia, {"reconstruct": False}

    def sweep_final(self, res):
        return np.asarray(res.final_momentum)


class ClusterEnsemble(wp.VortexClusters):
    """`work_precision.VortexClusters` with heyoka's equations and ours' sweep arguments."""

    def heyoka_system(self, hy):
        r"""Biot-Savart for 4 vortices, state (x_1, y_1, ..., x_4, y_4)."""
        n = len(self.gamma)
        xs = hy.make_vars(*[f"x{a}" for a in range(n)])
        ys = hy.make_vars(*[f"y{a}" for a in range(n)])
        eqs = []
        for a in range(n):
            u, v = 0.0 * xs[a], 0.0 * xs[a]
            for b in range(n):
                if b == a:
                    continue
                dx, dy = xs[a] - xs[b], ys[a] - ys[b]
                w = float(self.gamma[b]) / (2.0 * math.pi) / (dx * dx + dy * dy)
                u, v = u - w * dy, v + w * dx
            eqs += [(xs[a], u), (ys[a], v)]
        return eqs

    def flat(self, y):
        return np.asarray(y).reshape(len(y), -1)

    def unflat(self, y):
        return np.asarray(y).reshape(len(y), 4, 2)

    def energy(self, ys):
        r"""$H = -\frac{1}{4\pi}\sum_{a<b}\Gamma_a\Gamma_b\log r_{ab}^2$ of states (..., 4, 2)."""
        ys = np.asarray(ys)
        H = 0.0
        for a in range(4):
            for b in range(a + 1, 4):
                r2 = np.sum((ys[..., a, :] - ys[..., b, :]) ** 2, -1)
                H = H - self.gamma[a] * self.gamma[b] * np.log(r2) / (4.0 * math.pi)
        return H

    def sweep_args(self, model=None):
        G = jnp.asarray(self.gamma)
        Q0 = jnp.asarray(self.y0)
        xi0 = jax.vmap(lambda q: models.vortex_velocity(G, q))(Q0)
        return models.point_vortices, G[None], Q0, xi0, {}

    def sweep_final(self, res):
        return np.asarray(res.final_Q)


def relative_energy_error(scene, ys) -> float:
    """max over samples and members of |E - E0| / |E0|, ys (n, B, ...)."""
    E = scene.energy(ys)
    return float(np.max(np.abs(E - E[:1]) / np.abs(E[:1])))


def global_error(scene, y, ref) -> dict:
    """max (and median) over members of the final-state distance, over the scene's scale."""
    d = np.linalg.norm(scene.unflat(y) - scene.unflat(ref), axis=-1).reshape(len(ref), -1).max(-1) / scene.scale
    return {"global_error": float(np.max(d)), "global_error_median": float(np.median(d))}


# --------------------------------------------------------------------------------------------
# Timing.


def time_calls(run, call, what: str, budget_s: float) -> tuple[dict, object]:
    """The first call is a sample (its output kept); more while their total stays below
    `budget_s`, at most `run.repeats`; median."""
    walls, cpus = [], []
    with run.guard(what):
        out = None
        while len(walls) < run.repeats and (not walls or sum(walls) + statistics.median(walls) <= budget_s):
            tic, cpu = time.perf_counter(), time.process_time()
            res = call()
            walls.append(time.perf_counter() - tic)
            cpus.append(time.process_time() - cpu)
            out = res if out is None else out
    return {
        "wall_s": statistics.median(walls),
        "samples_s": walls,
        "cpu_s": statistics.median(cpus),
        "load": load3(),
    }, out


# --------------------------------------------------------------------------------------------
# heyoka.


class HeyokaEnsemble:
    """One `taylor_adaptive_batch` per tolerance; `run(tol)` propagates the ensemble group by group
    over the sample times and returns the samples (n_samples + 1, B, n_eq). Groups of
    `batch_size` members (default `recommended_simd_size()`)."""

    def __init__(self, hy, scene, ts, batch_size=None):
        self.hy, self.scene, self.ts = hy, scene, np.asarray(ts)
        self.bs = int(batch_size or hy.recommended_simd_size())
        self.sys = scene.heyoka_system(hy)
        y0 = scene.flat(scene.y0)
        pad = (-len(y0)) % self.bs  # the last group padded with copies of the last member
        self.y0 = np.concatenate([y0, np.repeat(y0[-1:], pad, 0)]) if pad else y0
        self.grid = np.repeat(self.ts[:, None], self.bs, axis=1)
        self.integrators, self.compile_s = {}, {}

    def compile(self, tol):
        tic = time.perf_counter()
        ta = self.hy.taylor_adaptive_batch(self.sys, np.ascontiguousarray(self.y0[: self.bs].T), tol=tol)
        self.compile_s[tol] = time.perf_counter() - tic
        self.integrators[tol] = ta
        return ta

    def run(self, tol):
        ta = self.integrators[tol]
        n = len(self.scene.y0)
        out = np.empty((len(self.ts), len(self.y0), self.y0.shape[1]))
        ok, steps = True, 0
        for g in range(0, len(self.y0), self.bs):
            ta.set_time(0.0)
            ta.state[:] = self.y0[g : g + self.bs].T
            _, ys = ta.propagate_grid(self.grid)  # (n_samples + 1, n_eq, bs)
            out[:, g : g + self.bs] = np.moveaxis(ys, 2, 1)
            for outcome, _, _, nsteps in ta.propagate_res:
                ok &= outcome == self.hy.taylor_outcome.time_limit
                steps = max(steps, int(nsteps))
        return {"ys": out[:, :n], "valid": bool(ok and np.all(np.isfinite(out))), "steps": steps, "order": ta.order}


def heyoka_reference(hy, scene, tol, members=None) -> np.ndarray:
    """Final states (B, n_eq) from heyoka's scalar integrator in extended precision."""
    ld = np.longdouble
    n_eq = scene.flat(scene.y0).shape[1]
    ta = hy.taylor_adaptive(scene.heyoka_system(hy), np.zeros(n_eq, ld), tol=ld(tol), fp_type=ld)
    y0 = scene.flat(scene.y0)[:members]
    out = np.empty(y0.shape)
    for m, y in enumerate(y0):
        ta.time = ld(0.0)
        ta.state[:] = y.astype(ld)
        outcome = ta.propagate_until(ld(scene.T))[0]
        if outcome != hy.taylor_outcome.time_limit:
            raise RuntimeError(f"{scene.name}: the extended-precision reference failed on member {m} ({outcome})")
        out[m] = ta.state.astype(float)
    return out


# --------------------------------------------------------------------------------------------
# Ours.


def ours_sweep(scene, options, dt, n_steps, backend):
    """`cj.sweep` of the scene's ensemble: (result, warnings' messages). `options["model"]`, if
    given, chooses the scene's model (`sweep_args`); the others go to the sweep."""
    options = dict(options)
    make_system, params, Q0, xi0, extra = scene.sweep_args(options.pop("model", None))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = cj.sweep(
            make_system,
            params,
            Q0,
            xi0,
            grid=True,
            dt=dt,
            n_steps=n_steps,
            threads=1,
            backend=backend,
            **extra,
            **options,
        )
    return res, [str(w.message) for w in caught]


def ours_backend(scene, options, dt, n_steps) -> tuple[str, str | None, float, list]:
    """(backend, why not native, warm-up seconds, warnings): a one-chunk sweep with
    `backend="native"` (compiles or loads the kernel); where the sweep refuses it, with "xla".
    `options["backend"]`, if given, is taken as it is (for XLA-only points)."""
    options = dict(options)
    if "backend" in options:
        backend = options.pop("backend")
        tic = time.perf_counter()
        _, msgs = ours_sweep(scene, options, dt, min(n_steps, CHUNK), backend)
        return backend, "chosen", time.perf_counter() - tic, msgs
    tic = time.perf_counter()
    try:
        _, msgs = ours_sweep(scene, options, dt, min(n_steps, CHUNK), "native")
        return "native", None, time.perf_counter() - tic, msgs
    except ValueError as err:
        why = str(err)
    tic = time.perf_counter()
    _, msgs = ours_sweep(scene, options, dt, min(n_steps, CHUNK), "xla")
    return "xla", why, time.perf_counter() - tic, msgs


def _steps(T, dt) -> int:
    n = round(T / dt)
    if abs(n * dt - T) > 1e-9 * T or (n > CHUNK and n % CHUNK):
        raise ValueError(f"T / dt = {T / dt} is not a multiple of {CHUNK}")
    return n


# --------------------------------------------------------------------------------------------
# One ensemble.


def run_ensemble(scene, cfg, run, hy) -> dict:
    T, budget = scene.T, run.args.point_budget
    ts = np.linspace(0.0, T, cfg["n_samples"] + 1)
    out = {"scene": scene.name, "label": scene.label, "T": T, "members": scene.members, "scale": scene.scale}
    points = []
    E0 = scene.energy(scene.y0)

    with run.case(f"{scene.name}: reference"):
        tic = time.perf_counter()
        if hy is not None:
            y_ref = heyoka_reference(hy, scene, REF_TOL)
            check = heyoka_reference(hy, scene, REF_CHECK_TOL, REF_CHECK_MEMBERS)
            d = np.linalg.norm(scene.unflat(check) - scene.unflat(y_ref[:REF_CHECK_MEMBERS]), axis=-1)
            out["reference"] = {
                "method": f"heyoka taylor_adaptive, long double, tol {REF_TOL:g}, member by member",
                "check": f"distance to tol {REF_CHECK_TOL:g} on the first {REF_CHECK_MEMBERS} members",
                "floor": float(np.max(d)) / scene.scale,
            }
        else:
            print("heyoka is not installed (pip install -e '.[bench]'): no heyoka points; reference by diffrax")
            call = wp.diffrax_program(scene, "dopri8", run.compiler_options)
            res = call(wp.REFERENCE_RTOL)
            y_ref = scene.flat(res["ys"][-1])
            out["reference"] = {"method": f"diffrax Dopri8, rtol {wp.REFERENCE_RTOL:g}", "floor": None}
        out["reference"]["wall_s"] = time.perf_counter() - tic

    if run.args.plans_only:
        out["points"] = ours_plans(scene, cfg, run, y_ref, E0, budget)
        return out

    if hy is not None:
        ens = HeyokaEnsemble(hy, scene, ts)
        out["heyoka_batch_size"] = ens.bs
        with run.case(f"{scene.name}: heyoka batch (simd {ens.bs}), tol {list(cfg['heyoka'])}"):
            for tol in cfg["heyoka"]:
                ens.compile(tol)
                timing, res = time_calls(run, lambda t=tol: ens.run(t), f"heyoka tol {tol:g}", budget)
                points.append(
                    _point(scene, HEYOKA, "heyoka", "tol", tol, timing, res, y_ref, E0)
                    | {"compile_s": ens.compile_s[tol], "taylor_order": res["order"], "steps": res["steps"]}
                )

    with run.case(f"{scene.name}: diffrax Tsit5 {list(cfg['tsit5'])}, Dopri8 {list(cfg['dopri8'])}"):
        for solver in ("tsit5", "dopri8"):
            if not cfg[solver]:
                continue
            call = wp.diffrax_program(scene, solver, run.compiler_options)
            warm = _wall(lambda c=call: c(cfg[solver][0]))
            for rtol in cfg[solver]:
                timing, res = time_calls(run, lambda c=call, r=rtol: c(r), f"{solver} rtol {rtol:g}", budget)
                res = dict(res, ys=res["ys"].reshape(res["ys"].shape[:2] + (-1,)))
                points.append(
                    _point(scene, DIFFRAX, solver, "rtol", rtol, timing, res, y_ref, E0)
                    | {"warm_up_s": warm, "steps": res["steps"]}
                )

    for method, options, dts in cfg["ours"]:
        with run.case(f"{scene.name}: ours {method}, dt {list(dts)}"):
            with run.guard(f"warm-up {method}"):
                backend, why, warm, msgs = ours_backend(scene, options, dts[0], _steps(T, dts[0]))
            options = {k: v for k, v in options.items() if k != "backend"}
            for dt in dts:
                n_steps = _steps(T, dt)
                timing, (res, _) = time_calls(
                    run,
                    lambda d=dt, n=n_steps: ours_sweep(scene, options, d, n, backend),
                    f"{method} dt {dt:g}",
                    budget,
                )
                e0 = np.asarray(res.initial["energy"])
                ok = bool(np.all(res.succeeded))
                p = {
                    "family": OURS,
                    "method": method,
                    "backend": backend,
                    "not_native_because": why,
                    "warnings": msgs,
                    "sweep_method": res.method,
                    "form": res.form,
                    "param_name": "dt",
                    "param": dt,
                    "steps": n_steps,
                    "valid": ok,
                    "warm_up_s": warm,
                    "newton_per_step": float(np.mean(res.newton_iterations)) / n_steps,
                    # the sweep's energy at node 0 against this script's (the same function?)
                    "energy0_mismatch": float(np.max(np.abs(e0 - E0) / np.abs(E0))),
                    **timing,
                }
                if ok:
                    p.update(global_error(scene, scene.flat(scene.sweep_final(res)), y_ref))
                    p["energy_error"] = float(np.max(np.asarray(res.energy_error) / np.abs(e0)))
                points.append(p)
    points += ours_plans(scene, cfg, run, y_ref, E0, budget)
    out["points"] = points
    return out


def ours_plans(scene, cfg, run, y_ref, E0, budget) -> list:
    """Points of the ensemble plans (`cfg["plans"]`: accuracies at T): `cj.choose_sweep_step` on
    the scene's members with its sweep options (the pilot on the first member and the fastest
    others), then the sweep of every member with the plan's method and step. With
    `--plans-only` also the plan piloted on the first member alone (`members=[0]`, what
    `choose_step` on member 0 gives; method label `plan_first`), for comparison. The pilot's wall
    time, the members piloted and the plan's predicted error and work are recorded beside the
    point, whose `global_error` is the worst member's."""
    points = []
    kinds = (("plan", None), ("plan_first", [0])) if run.args.plans_only else (("plan", None),)
    for accuracy in cfg.get("plans", ()):
        for label, members in kinds:
            with run.case(f"{scene.name}: ours, {label} for accuracy {accuracy:g}"):
                points.append(_plan_point(scene, run, y_ref, E0, budget, accuracy, label, members))
    return points


def _plan_point(scene, run, y_ref, E0, budget, accuracy, label, members) -> dict:
    make_system, params, Q0, xi0, extra = scene.sweep_args()
    P0 = extra.pop("P0", None)
    ensemble = dict(P0=P0, grid=True)
    pilot_s = []  # the first call compiles (or loads) the candidates' kernels, the second finds them
    for _ in range(2):
        tic = time.perf_counter()
        plan = cj.choose_sweep_step(
            make_system, params, Q0, xi0, t_final=scene.T, accuracy=accuracy, members=members, **ensemble, **extra
        )
        pilot_s.append(time.perf_counter() - tic)
    load_after_pilot = load3()
    sweep = dict(threads=1, **ensemble, **plan.integrate_options())
    # native where the sweep takes the plan's method, as for the other points (the warm-up)
    backend, why, tic = "native", None, time.perf_counter()
    try:
        cj.sweep(make_system, params, Q0, xi0, backend="native", **sweep)
    except ValueError as err:
        backend, why = "xla", str(err)
        cj.sweep(make_system, params, Q0, xi0, backend="xla", **sweep)
    warm, sweep["backend"] = time.perf_counter() - tic, backend
    timing, res = time_calls(
        run, lambda: cj.sweep(make_system, params, Q0, xi0, **sweep), f"{label} {accuracy:g}", budget
    )
    e0 = np.asarray(res.initial["energy"])
    p = {
        "family": OURS,
        "method": label,
        "backend": backend,
        "not_native_because": why,
        "sweep_method": res.method,
        "form": res.form,
        "param_name": "accuracy",
        "param": accuracy,
        "planned_dt": plan.dt,
        "steps": plan.n_steps,
        "piloted": list(plan.piloted),
        "predicted_error": plan.predicted_error,
        "plan_check": plan.check,  # what the check at the planned step found, and its growth exponent
        "growth": plan.growth,
        "predicted_work": plan.predicted_work,
        "pilot_work": plan.pilot_work,
        "pilot_s": pilot_s[0],
        "pilot_warm_s": pilot_s[1],
        "load_after_pilot": load_after_pilot,
        "warm_up_s": warm,
        "valid": bool(np.all(res.succeeded)),
        "newton_per_step": float(np.mean(res.newton_iterations)) / plan.n_steps,
        "energy0_mismatch": float(np.max(np.abs(e0 - E0) / np.abs(E0))),
        **timing,
    }
    if p["valid"]:
        p.update(global_error(scene, scene.flat(scene.sweep_final(res)), y_ref))
        p["energy_error"] = float(np.max(np.asarray(res.energy_error) / np.abs(e0)))
    return p


def _wall(call) -> float:
    tic = time.perf_counter()
    call()
    return time.perf_counter() - tic


def _point(scene, family, method, param_name, param, timing, res, y_ref, E0) -> dict:
    p = {"family": family, "method": method, "param_name": param_name, "param": param, "valid": res["valid"], **timing}
    if res["valid"]:
        ys = res["ys"]  # (n, B, n_eq)
        p.update(global_error(scene, ys[-1], y_ref))
        states = scene.unflat(ys.reshape(-1, ys.shape[-1])).reshape(ys.shape[:2] + scene.y0.shape[1:])
        p["energy_error"] = relative_energy_error(scene, states)
        p["energy0_mismatch"] = float(np.max(np.abs(scene.energy(scene.unflat(ys[0])) - E0) / np.abs(E0)))
    return p


# --------------------------------------------------------------------------------------------
# Targets.


def _dominating(ours, peer, energy_ok, key):
    """(fastest point of ours no slower by `key` and as accurate, or None; fastest accurate one)."""
    good = sorted(
        (o for o in ours if o["global_error"] <= peer["global_error"] and energy_ok(o["energy_error"])),
        key=lambda o: o[key],
    )
    met = [o for o in good if o[key] <= peer[key]]
    return (met[0] if met else None), (good[0] if good else None)


def _row(peer, met, best, key):
    o = met or best
    return {
        "peer": f"{peer['method']} {peer['param_name']} {peer['param']:g}",
        "peer_time_s": peer[key],
        "peer_global": peer["global_error"],
        "peer_energy": peer["energy_error"],
        "met": met is not None,
        "ours": None if o is None else f"{o['method']} {o['param_name']} {o['param']:g} ({o['backend']})",
        "ours_time_s": None if o is None else o[key],
        "ours_global": None if o is None else o["global_error"],
        "ours_energy": None if o is None else o["energy_error"],
        "time_ratio_ours_over_peer": None if o is None else o[key] / peer[key],
    }


def targets(scene_result, key="wall_s") -> dict:
    """Issue 41's targets (module docstring) by the time `key`: "wall_s" (the issue's), or
    "cpu_s" (the process's CPU time, less sensitive to other processes on a loaded machine)."""
    pts = [p for p in scene_result["points"] if p["valid"]]
    ours = [p for p in pts if p["family"] == OURS]
    rows_h, rows_d = [], []
    for peer in sorted((p for p in pts if p["family"] == HEYOKA), key=lambda p: -p["param"]):
        met, best = _dominating(ours, peer, lambda e, pe=peer["energy_error"]: e <= pe or e <= HEYOKA_ENERGY_FLOOR, key)
        row = _row(peer, met, best, key)
        lo, hi = HEYOKA_TARGET_TOLS
        row["in_target_range"] = bool(lo * (1 - 1e-9) <= peer["param"] <= hi * (1 + 1e-9))
        # our fastest point at no larger global error (energy not asked), over heyoka's time
        glob = sorted((o for o in ours if o["global_error"] <= peer["global_error"]), key=lambda o: o[key])
        row["global_only_time_ratio"] = glob[0][key] / peer[key] if glob else None
        rows_h.append(row)
    for peer in sorted((p for p in pts if p["family"] == DIFFRAX), key=lambda p: (p["method"], -p["param"])):
        met, best = _dominating(
            ours,
            peer,
            lambda e, pe=peer["energy_error"]: e * DIFFRAX_ENERGY_RATIO <= pe or e <= DIFFRAX_ENERGY_FLOOR,
            key,
        )
        rows_d.append(_row(peer, met, best, key))
    in_range = [r for r in rows_h if r["in_target_range"]]
    return {
        "time": key,
        "heyoka": rows_h,
        "heyoka_met": bool(in_range) and all(r["met"] for r in in_range),
        "diffrax": rows_d,
        "diffrax_met": bool(rows_d) and all(r["met"] for r in rows_d),
    }


# --------------------------------------------------------------------------------------------
# Long horizon.


def run_long_horizon(run, hy, T, cfg) -> dict:
    scene = RigidEnsemble({"batch": cfg["batch"], "T": T, "n_samples": cfg["n_samples"], "chunk": CHUNK})
    ts = np.linspace(0.0, T, cfg["n_samples"] + 1)
    E0 = scene.energy(scene.y0)
    curves = []

    method, options, dt = cfg["ours"]
    seg_steps = _steps(T / cfg["n_samples"], dt)
    with run.case(f"long horizon T = {T:g}: ours {method} dt {dt:g}, {cfg['n_samples']} sweeps of {seg_steps} steps"):
        make_system, params, _, xi0, extra = scene.sweep_args()
        backend, why, warm, _ = ours_backend(scene, options, dt, seg_steps)
        inertia = jnp.asarray(scene.inertia)
        mu = np.asarray(scene.y0)
        E = [scene.energy(mu)]
        e_nodes = 0.0
        tic, cpu = time.perf_counter(), time.process_time()
        with run.guard("long horizon, ours"):
            for _ in range(cfg["n_samples"]):
                res = cj.sweep(
                    make_system, params, jnp.broadcast_to(jnp.eye(3), (len(mu), 3, 3)), jnp.asarray(mu) / inertia,
                    grid=True, dt=dt, n_steps=seg_steps, threads=1, backend=backend, **extra, **options,
                )  # fmt: skip
                mu = np.asarray(res.final_momentum)
                E.append(scene.energy(mu))
                # every node of the segment, against E0: |E - E_start| + |E_start - E0|
                e_nodes = max(e_nodes, float(np.max((np.asarray(res.energy_error) + np.abs(E[-2] - E0)) / E0)))
        wall, cpu = time.perf_counter() - tic, time.process_time() - cpu
        err = np.max(np.abs(np.array(E) - E0) / E0, axis=1)
        curves.append(
            {"family": OURS, "method": method, "param": dt, "backend": backend, "not_native_because": why,
             "wall_s": wall, "cpu_s": cpu, "warm_up_s": warm, "load": load3(), "energy_error_t": err.tolist(),
             "energy_error_every_node_bound": e_nodes}
        )  # fmt: skip

    if hy is not None:
        ens = HeyokaEnsemble(hy, scene, ts)
        with run.case(f"long horizon: heyoka tol {list(cfg['heyoka'])}"):
            for tol in cfg["heyoka"]:
                ens.compile(tol)
                timing, res = time_calls(run, lambda t=tol: ens.run(t), f"long horizon heyoka {tol:g}", 0.0)
                ys = scene.unflat(res["ys"].reshape(-1, 3)).reshape(res["ys"].shape[:2] + (3,))
                Et = scene.energy(ys)
                curves.append(
                    {"family": HEYOKA, "method": "heyoka", "param": tol, "valid": res["valid"], **timing,
                     "energy_error_t": np.max(np.abs(Et - E0) / E0, axis=1).tolist()}
                )  # fmt: skip
    with run.case(f"long horizon: diffrax Dopri8 {list(cfg['dopri8'])}"):
        call = wp.diffrax_program(scene, "dopri8", run.compiler_options)
        _wall(lambda: call(cfg["dopri8"][0]))
        for rtol in cfg["dopri8"]:
            timing, res = time_calls(run, lambda r=rtol: call(r), f"long horizon dopri8 {rtol:g}", 0.0)
            Et = scene.energy(res["ys"])
            curves.append(
                {"family": DIFFRAX, "method": "dopri8", "param": rtol, "valid": res["valid"], **timing,
                 "energy_error_t": np.max(np.abs(Et - E0) / E0, axis=1).tolist()}
            )  # fmt: skip
    ours_wall = curves[0]["wall_s"]
    hy_curves = [c for c in curves if c["family"] == HEYOKA]
    if hy_curves:
        closest = min(hy_curves, key=lambda c: abs(math.log(c["wall_s"] / ours_wall)))
        for c in hy_curves:
            c["closest_in_cost_to_ours"] = c is closest
    for c in curves:
        e = np.asarray(c["energy_error_t"])
        half = len(e) // 2
        # drift: the max over the second half against the first half's
        c["energy_error_max"] = float(np.max(e))
        c["energy_error_second_over_first_half"] = float(np.max(e[half:]) / max(np.max(e[1 : half + 1]), 1e-300))
        c["energy_error_slope_loglog"] = _slope(ts[1:], e[1:])
    return {"scene": "rigid_body_long_horizon", "T": T, "members": scene.members, "ts": ts.tolist(), "curves": curves}


def _slope(t, e):
    """Least-squares slope of log e against log t over the second half of the samples (growth
    exponent: ~0 bounded, ~1 linear drift, ~0.5 random walk)."""
    h = len(t) // 2
    e = np.maximum(np.asarray(e[h:]), 1e-300)
    return float(np.polyfit(np.log(t[h:]), np.log(e), 1)[0])


# --------------------------------------------------------------------------------------------
# Report and plots.


def _e(x, w=9):
    return harness.fmt(x, ".1e", w)


def print_report(summary) -> None:
    quick = summary["config"]["quick"]
    if summary["config"]["mode"].endswith("long horizon"):
        lh = summary["results"][0]
        print(f"\nLong horizon, {lh['members']} rigid bodies, T = {lh['T']:g}: relative energy error at sample times")
        harness.print_table(
            f"{'method':<10}{'param':>8}{'wall [s]':>10} |{'max':>9}{'2nd/1st half':>13}{'slope':>7}",
            (
                f"{c['method']:<10}{c['param']:>8.3g}{c['wall_s']:>10.3g} |{_e(c['energy_error_max'])}"
                f"{c['energy_error_second_over_first_half']:>13.3g}{c['energy_error_slope_loglog']:>7.2f}"
                + ("  (closest to ours in cost)" if c.get("closest_in_cost_to_ours") else "")
                for c in lh["curves"]
            ),
        )
        return
    print(
        f"\nWork-precision on ensembles ({'--quick: not a measurement' if quick else 'measured'}); "
        "wall = median of the samples (n given), one thread per peer; load = 1-min average after the point."
    )
    for sc in summary["results"]:
        ref = sc["reference"]
        print(f"\n{sc['label']}: reference {ref['method']} (check {_e(ref.get('floor')).strip()})")
        harness.print_table(
            f"{'peer':<8}{'method':<8}{'param':>8}{'backend':>8}{'wall [s]':>10}{'cpu [s]':>9}{'n':>3}{'load':>6} |"
            f"{'global':>9}{'energy':>9}",
            (
                f"{p['family']:<8}{p['method']:<8}{p['param']:>8.3g}{p.get('backend', ''):>8}{p['wall_s']:>10.3g}"
                f"{p['cpu_s']:>9.3g}"
                f"{len(p['samples_s']):>3}{p['load'][0]:>6.2f} |{_e(p.get('global_error'))}{_e(p.get('energy_error'))}"
                + ("" if p["valid"] else "  FAILED")
                for p in sc["points"]
            ),
        )
        plans = [p for p in sc["points"] if "piloted" in p]
        if plans:
            harness.print_table(
                f"{'plan':<11}{'accuracy':>9}{'method':>26}{'dt':>8}{'predicted':>10}{'worst':>9}{'pilot [s]':>10}"
                f"{'warm [s]':>10}  piloted",
                (
                    f"{p['method']:<11}{p['param']:>9.0e}{p['sweep_method'][:25]:>26}{p['planned_dt']:>8.3g}"
                    f"{_e(p['predicted_error'], 10)}{_e(p.get('global_error'))}{p['pilot_s']:>10.3g}"
                    f"{p['pilot_warm_s']:>10.3g}  {p['piloted']}"
                    for p in plans
                ),
            )
        if summary["config"].get("plans_only"):
            continue  # no peers: no targets
        for tg in (summary["targets"][sc["scene"]], summary["targets_cpu"][sc["scene"]]):
            _print_targets(sc["scene"], tg)


def _print_targets(scene, tg) -> None:
    what = "wall time" if tg["time"] == "wall_s" else "CPU time of the process"
    print(
        f"Issue 41 targets, {scene}, by {what}: heyoka 1e-8..1e-14 "
        f"{'MET' if tg['heyoka_met'] else 'NOT MET' if tg['heyoka'] else 'n/a (no heyoka points)'}; "
        f"diffrax dominated {'MET' if tg['diffrax_met'] else 'NOT MET'}"
    )
    for r in tg["heyoka"] + tg["diffrax"]:
        ours = (
            "no point of ours is as accurate"
            if r["ours"] is None
            else f"{'met by' if r['met'] else 'closest:'} {r['ours']} {r['ours_time_s']:.3g} s "
            f"({r['time_ratio_ours_over_peer']:.3g}x), global {r['ours_global']:.1e}, energy {r['ours_energy']:.1e}"
        )
        extra = (
            f"; global only: {r['global_only_time_ratio']:.3g}x" if r.get("global_only_time_ratio") is not None else ""
        )
        print(
            f"  {r['peer']:<18} {r['peer_time_s']:8.3g} s, global {r['peer_global']:.1e}, energy "
            f"{r['peer_energy']:.1e}: {ours}{extra}"
        )


_STYLE = {
    "order2": ("o", "#9ecae1"),
    "order4": ("o", "#4292c6"),
    "order6": ("o", "#2171b5"),
    "order8": ("o", "#08306b"),
    "gauss4": ("*", "#74c476"),
    "gauss6": ("*", "#41ab5d"),
    "gauss8": ("*", "#006d2c"),
    "gauss12": ("P", "#e7298a"),
    "vgauss4": ("D", "#fdae6b"),
    "vgauss6": ("D", "#f16913"),
    "vgauss8": ("D", "#a63603"),
    "vgauss12": ("P", "#54278f"),
    "vgauss16": ("X", "#7a0177"),
    "heyoka": ("s", "C3"),
    "tsit5": ("^", "C1"),
    "dopri8": ("v", "C5"),
}


def plot(summary, path: Path) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    if summary["config"]["mode"].endswith("long horizon"):
        return plot_long_horizon(summary, path)
    scenes, quick = summary["results"], summary["config"]["quick"]
    fig = Figure(figsize=(12, 4.4 * len(scenes) + 0.8), layout="constrained")
    FigureCanvasAgg(fig)
    axes = np.atleast_2d(fig.subplots(len(scenes), 2))
    for row, sc in zip(axes, scenes):
        for ax, measure in zip(row, ("global_error", "energy_error")):
            groups = {}
            for p in sc["points"]:
                if p["valid"] and p.get(measure) is not None:
                    key = (p["family"], p["method"], p.get("backend"))
                    groups.setdefault(key, []).append((-p["param"], p["wall_s"], max(p[measure], 1e-17)))
            for (family, method, backend), pts in groups.items():
                pts = [(t, e) for _, t, e in sorted(pts)]  # from the loosest setting to the tightest
                marker, color = _STYLE.get(method, ("x", "k"))
                label = (
                    f"ours {method} ({backend})"
                    if family == OURS
                    else "heyoka (batch)"
                    if family == HEYOKA
                    else f"diffrax {method}"
                )
                ax.loglog(
                    *zip(*pts),
                    marker=marker,
                    color=color,
                    ls="-" if backend != "xla" else "--",
                    mfc=color if backend != "xla" else "none",
                    label=label,
                )
            if measure == "global_error" and sc["reference"].get("floor"):
                ax.axhline(sc["reference"]["floor"], color="0.5", ls=":", lw=1, label="reference check")
            ax.set_xlabel("wall time of the ensemble [s]")
            ax.set_ylabel(
                "global error at T (max over members)" if measure == "global_error" else "max relative energy error"
            )
            ax.set_title(f"{sc['label']}", fontsize=9)
            ax.grid(True, which="both", alpha=0.3)
        row[1].legend(fontsize=6, ncol=2, loc="upper right")  # the energy panel's upper right is empty
    mach = summary["machine"]
    loads = [p["load"][0] for sc in scenes for p in sc["points"] if p.get("load")]
    fig.suptitle(
        f"Work-precision on ensembles (issue 41){'; --quick: not a measurement' if quick else ''}: "
        f"one thread per peer, {mach['cpu_count']} CPUs, 1-min load {min(loads):.1f}-{max(loads):.1f}.\n"
        "Ours: cj.sweep, energy at every node; heyoka and diffrax: energy at the sample times.",
        fontsize=10,
    )
    fig.savefig(path, dpi=110)


def plot_long_horizon(summary, path: Path) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    lh = summary["results"][0]
    ts = np.asarray(lh["ts"])
    fig = Figure(figsize=(9, 5.2), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    for c in lh["curves"]:
        marker, color = _STYLE.get(c["method"], ("x", "k"))
        if c["family"] == HEYOKA:
            alpha = 1.0 if c.get("closest_in_cost_to_ours") else 0.35
            label = f"heyoka tol {c['param']:g} ({c['wall_s']:.3g} s)"
            label += ", the closest to ours in cost" if c.get("closest_in_cost_to_ours") else ""
        else:
            alpha = 1.0
            what = f"ours {c['method']} dt" if c["family"] == OURS else "diffrax Dopri8 rtol"
            label = f"{what} {c['param']:g} ({c['wall_s']:.3g} s)"
        ax.loglog(ts[1:], np.maximum(c["energy_error_t"][1:], 1e-18), color=color, alpha=alpha, lw=1, label=label)
    ax.set_xlabel("t")
    ax.set_ylabel("max over bodies of |E(t) - E0| / E0")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    mach = summary["machine"]
    ax.set_title(
        f"{lh['members']} rigid bodies, T = {lh['T']:g}: energy error over time "
        "(wall time of the whole run in the legend)"
        f"{'; --quick' if summary['config']['quick'] else ''}\n{mach['cpu_count']} CPUs, load "
        f"{mach['load_average_1min_at_start']:.1f} at start",
        fontsize=9,
    )
    fig.savefig(path, dpi=110)


# --------------------------------------------------------------------------------------------


def add_arguments(parser) -> None:
    parser.add_argument("--ensembles", action="store_true", help="the long ensembles against heyoka and diffrax")
    parser.add_argument(
        "--long-horizon", action="store_true", dest="long_horizon", help="energy error over T = --horizon"
    )
    parser.add_argument(
        "--horizon",
        type=float,
        default=DEFAULT_HORIZON,
        help="T of --long-horizon (default 1e5; another T writes work_precision_long_horizon_T<T>.{json,png})",
    )
    parser.add_argument("--batch", type=int, default=None, help="rigid bodies in the ensemble (default 64)")
    parser.add_argument("--clusters-batch", type=int, default=None, dest="clusters_batch", help="clusters (default 16)")
    parser.add_argument(
        "--scenes", nargs="+", choices=list(ENSEMBLES), default=None, help="run only these ensembles (default: both)"
    )
    parser.add_argument(
        "--plans-only",
        action="store_true",
        dest="plans_only",
        help="the reference and ours' accuracy plans only, each ensemble plan beside the plan piloted on "
        "the first member (written as work_precision_ensemble_plans.{json,png})",
    )
    parser.add_argument(
        "--point-budget",
        type=float,
        default=None,
        dest="point_budget",
        help="seconds of samples per point before stopping at fewer than --repeats (default 60; 0.05 with --quick)",
    )


def _horizon(argv) -> float:
    """The value of `--horizon` in argv (before the parser runs: it names the output files)."""
    for k, a in enumerate(argv):
        if a.startswith("--horizon="):
            return float(a.split("=", 1)[1])
        if a == "--horizon" and k + 1 < len(argv):
            return float(argv[k + 1])
    return DEFAULT_HORIZON


def main(argv) -> dict:
    long_horizon = "--long-horizon" in argv
    name = "work_precision_long_horizon" if long_horizon else "work_precision_ensembles"
    if "--plans-only" in argv and not long_horizon:  # not the full run's files
        name = "work_precision_ensemble_plans"
    horizon = _horizon(argv)
    if long_horizon and horizon != DEFAULT_HORIZON:  # another horizon does not replace the default's files
        name += f"_T{horizon:g}"
    if not any(a.startswith("--repeats") for a in argv):
        argv = [*argv, "--repeats", "3"]
    with harness.Run(
        name,
        argv,
        description="Work-precision on long ensembles: ours (cj.sweep, native) against heyoka and diffrax.",
        add_arguments=add_arguments,
    ) as run:
        args = run.args
        if args.point_budget is None:
            args.point_budget = 0.05 if run.quick else 60.0
        hy = heyoka_module()
        if hy is None:
            print("heyoka is not installed (it is in the bench extra: pip install -e '.[bench]'): skipping heyoka")
        machine_extra = {
            "heyoka": None if hy is None else hy.__version__,
            "heyoka_simd_size": None if hy is None else int(hy.recommended_simd_size()),
            "uptime_load_at_start": load3(),
        }
        if long_horizon:
            cfg = QUICK_LONG_HORIZON if run.quick else LONG_HORIZON
            T = 20.0 if run.quick else args.horizon
            results = [run_long_horizon(run, hy, T, cfg)]
            config = {"mode": "quick long horizon" if run.quick else "long horizon", "T": T, **cfg}
            tg = tg_cpu = {}
        else:
            config = {k: dict(v) for k, v in (QUICK_ENSEMBLES if run.quick else ENSEMBLES).items()}
            if args.batch:
                config["rigid_body"]["batch"] = args.batch
            if args.clusters_batch:
                config["vortex_clusters"]["batch"] = args.clusters_batch
            results = []
            for s in args.scenes or list(config):
                cfg = dict(config[s], chunk=CHUNK)
                scene = RigidEnsemble(cfg) if s == "rigid_body" else ClusterEnsemble(cfg)
                results.append(run_ensemble(scene, cfg, run, hy))
            tg = {r["scene"]: targets(r) for r in results}
            tg_cpu = {r["scene"]: targets(r, "cpu_s") for r in results}
            config = {"mode": "quick ensembles" if run.quick else "ensembles", "scenes": config}
            config["plans_only"] = args.plans_only
    summary = run.summary(
        config={
            **config,
            "point_budget_s": args.point_budget,
            "threads": "one per peer: ours threads=1, heyoka one batch integrator, diffrax one jit(vmap) program",
            "inertia": list(wp.INERTIA),
            "seed": wp.SEED,
            "reference_tol": REF_TOL,
            "targets": {
                "heyoka_tols": list(HEYOKA_TARGET_TOLS),
                "heyoka_energy_floor": HEYOKA_ENERGY_FLOOR,
                "diffrax_energy_ratio": DIFFRAX_ENERGY_RATIO,
                "diffrax_energy_floor": DIFFRAX_ENERGY_FLOOR,
            },
        },
        results=results,
        targets=tg,
        targets_cpu=tg_cpu,
        peers=machine_extra,
    )
    summary["uptime_load_at_end"] = load3()
    return run.finish(summary, print_report, plot)
