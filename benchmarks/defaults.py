r"""The defaults of issue 23: compile once per system and shapes, the cost of the heavy top's new
second-order default, and the measured order of the default method.

Run from the repository root:

    python benchmarks/defaults.py            # default run
    python benchmarks/defaults.py --quick    # smoke test, XLA optimisation off (not a measurement)

Three parts:

1. **Compile once per system and shapes.** `integrate` with concrete arguments marches in
   compiled chunks (`clebsch_jax.march.scan.march_chunked`): one program for the start, one for
   a chunk, neither depending on `n_steps` or `dt`; the built-in models hold their parameters
   as array leaves. Three scenes — `rigid_body` (built-in, the reduced CAY left principle),
   `heavy_top` (built-in, the reduced left step paired with its adjoint over half steps) and
   `user_pendulum` (a spherical pendulum on R³ written as a user would, the midpoint
   principle) — each run in a *fresh child process* with no persistent compilation cache
   (`JAX_COMPILATION_CACHE_DIR` and `CLEBSCH_JAX_CACHE_DIR` removed from its environment;
   the child checks that JAX's cache directory is unset). After one tiny `jax.jit` that starts
   the backend (reported apart), the child makes five calls with default options:

   1. `first`: `n_steps = 1000`, `dt = 0.01`;
   2. `new_n_steps`: `n_steps = 1500`;
   3. `new_dt`: `dt = 0.02`, `n_steps = 1000`;
   4. `new_parameters` (built-in models only): the model constructed again with other
      parameter values (inertia; inertia and m g l), `n_steps = 1000`, `dt = 0.01`;
   5. `first_again`: the first call again (same system object).

   Each call's wall time ends in `jax.block_until_ready` on the `Solution`; the XLA
   compilations during it are counted with `jax.monitoring` (the event
   `/jax/core/compile/backend_compile_duration`, with the name of each program compiled), and
   the tracings and lowerings beside them. Every scene runs in `CHILD_REPEATS` children, the
   scenes interleaved round by round; reported: the median time of each call over the
   children, its ratio to the median first call, and the compilations of every call (the
   issue's target: a new `n_steps` costs at most 0.2 of the first call, and calls 2-5 compile
   nothing).

2. **What the heavy top's default costs.** `heavy_top((1, 1, 0.4), 1.5)`, Q0 = exp(0.5 ê₁),
   ξ0 = (0.3, −0.2, 2), dt = 0.01, 2000 steps, one trajectory, plain `integrate` calls timed
   with the shared harness (`_timing.py`: a first call compiles, the median of `--repeats`
   samples, the methods sampled in turn, every call ending in `jax.block_until_ready`):
   `default` (no method options: "right(h/2) o left(h/2)", order 2), `left`
   (`scheme="left"`, the reduced left step alone, order 1: the default before issue 23) and
   `midpoint` (`scheme="midpoint"`, the full march, order 2). Reported: time per step,
   default/left (target <= 2.5), midpoint/default, and each method's error at the final time
   against a reference run of the default at dt/16 (max |·| over the final body momentum and
   Q), so that speed stands next to accuracy. The default at dt/8 against the reference bounds
   the reference's own error.

3. **Measured order of the default**, on the setups of `tests/test_defaults.py` (replicated
   here, not imported): every built-in model and two user systems with a potential (the
   spherical pendulum above; a heavy top written on SO(3) with the Cayley map). Each runs the
   default at h0, h0/2, h0/4, h0/8 and h0/64 to the same final time; the error of each of the
   first four against the h0/64 run (max |·| over the final momentum map and, where carried,
   Q) and the slope of a least-squares fit of log error against log h. The XLA compilations
   of every run are counted too: only the first step size of a model may compile.

Outputs (in `--out`, default `benchmarks/results`): `defaults.json` and `defaults.png` (call
times per scene on a log axis; heavy-top time per step against error; error against step size
per model with a slope-2 guide). Nothing here asserts a time.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import _timing as harness
import clebsch_jax as cj
from clebsch_jax.march.scan import CHUNK_STEPS

RESULTS_NAME = "defaults"
BACKEND_COMPILE = "/jax/core/compile/backend_compile_duration"  # jax._src.dispatch.BACKEND_COMPILE_EVENT
CACHE_VARIABLES = ("JAX_COMPILATION_CACHE_DIR", "CLEBSCH_JAX_CACHE_DIR")
GRAVITY = 9.81

# The targets (reported, never asserted).
TARGETS = {
    "new_n_steps_over_first": 0.2,  # a second call with a new n_steps, relative to the first call
    "compilations_calls_2_to_5": 0,  # XLA compilations during calls 2-5
    "heavy_top_default_over_left": 2.5,  # time per step of the new default against the reduced left step
    "min_order_slope": 1.9,  # the measured order of the default (as tests/test_defaults.py)
}

# --------------------------------------------------------------------------------------------
# The systems (the setups of tests/test_defaults.py, written again here).

TOP_INERTIA = (1.0, 1.0, 0.4)
TOP_MGL = 1.5


def user_pendulum() -> cj.ClebschSystem:
    """A spherical pendulum on R³ as a new user would write it: so(3) acting by the cross
    product, the forward difference, l = ½|ξ×Q|² + ½(ξ·Q)² − g Q_z."""
    return cj.ClebschSystem(
        lagrangian=lambda xi, Q: 0.5 * jnp.sum(jnp.cross(xi, Q) ** 2) + 0.5 * jnp.dot(xi, Q) ** 2 - GRAVITY * Q[2],
        velocity_map=lambda xi, Q: jnp.cross(xi, Q),
        derivative_map=cj.forward_difference,
    )


def user_heavy_top() -> cj.ClebschSystem:
    """A heavy top written by a user on SO(3) with the Cayley map: l = ½ξ·𝕀ξ − mgl (Qχ)·e₃."""
    inertia = jnp.array(TOP_INERTIA)
    return cj.ClebschSystem(
        lagrangian=lambda xi, Q: 0.5 * jnp.sum(inertia * xi * xi) - TOP_MGL * (Q @ jnp.array([0.0, 0.0, 1.0]))[2],
        velocity_map=lambda xi, Q: Q @ cj.lie.hat(xi),
        derivative_map=cj.cayley,
    )


def pendulum_start():
    return jnp.array([np.sin(1.0), 0.0, -np.cos(1.0)]), jnp.array([0.0, 0.3, 1.2])


def top_start():
    return cj.lie.so3_exp(jnp.array([0.5, 0.0, 0.0])), jnp.array([0.3, -0.2, 2.0])


RIGID_INERTIA = (2.0, 1.0, 2.0 / 3.0)
RIGID_XI0 = (1.3, 0.8, -0.4)


def rigid_body_vector(inertia, xi0):
    vector_Q0, vector_P0 = cj.models.rigid_body_vector_start(inertia * xi0)
    return cj.models.rigid_body_vector(inertia), vector_Q0, xi0, vector_P0, 2.0, 0.1


def order_cases(names) -> dict:
    """name -> (system, Q0, xi0, P0, final time, coarsest step): tests/test_defaults.py's cases."""
    inertia, xi0 = jnp.array(RIGID_INERTIA), jnp.array(RIGID_XI0)
    top_Q0, top_xi0 = top_start()
    G = jnp.array([1.0, -1.0, 1.0, -1.0])
    vortex_Q0 = jnp.array([[0.0, 1.0], [0.0, -1.0], [0.0, 0.5], [0.0, -0.5]])
    peakon_Q0, peakon_P0 = jnp.array([-3.0, 0.0]), jnp.array([2.0, 1.0])
    landmark_Q0 = jnp.array([[0.0, 0.0], [1.0, 0.3]])
    landmark_P0 = jnp.array([[1.0, 0.0], [-0.5, 0.5]])
    make = {
        "rigid_body": lambda: (cj.models.rigid_body(inertia), jnp.eye(3), xi0, None, 2.0, 0.1),
        "rigid_body_vector": lambda: rigid_body_vector(inertia, xi0),
        "heavy_top": lambda: (cj.models.heavy_top(jnp.array(TOP_INERTIA), TOP_MGL), top_Q0, top_xi0, None, 1.0, 0.05),
        "point_vortices": lambda: (
            cj.models.point_vortices(G),
            vortex_Q0,
            cj.models.vortex_velocity(G, vortex_Q0),
            None,
            1.0,
            0.05,
        ),
        "peakons": lambda: (
            cj.models.peakons(1.0),
            peakon_Q0,
            cj.models.peakon_velocity(peakon_Q0, peakon_P0, 1.0),
            peakon_P0,
            2.0,
            0.1,
        ),
        "landmarks": lambda: (
            cj.models.landmarks(1.0),
            landmark_Q0,
            cj.models.landmark_velocity(landmark_Q0, landmark_P0, 1.0),
            landmark_P0,
            1.0,
            0.05,
        ),
        "user_pendulum": lambda: (user_pendulum(), *pendulum_start(), None, 1.0, 0.05),
        "user_heavy_top": lambda: (user_heavy_top(), *top_start(), None, 1.0, 0.05),
    }
    return {name: make[name]() for name in names}


ORDER_MODELS = (
    "rigid_body",
    "rigid_body_vector",
    "heavy_top",
    "point_vortices",
    "peakons",
    "landmarks",
    "user_pendulum",
    "user_heavy_top",
)
ORDER_MODELS_QUICK = ("rigid_body", "heavy_top", "user_pendulum")
ORDER_DIVISORS = (1, 2, 4, 8)  # the fitted step sizes h0 / k
ORDER_REFERENCE = 64  # the reference run: step h0 / 64


def final_state(sol) -> np.ndarray:
    """Momentum map and (when carried) configuration at the last node, as one vector."""
    parts = [sol.momentum[-1].ravel()] + ([sol.Q[-1].ravel()] if sol.Q is not None else [])
    return np.concatenate([np.asarray(p) for p in parts])


class CompileLog:
    """JAX's compile-time events (`jax.monitoring`) from its creation on: XLA compilations with
    the name of each program, tracings and lowerings to MLIR."""

    def __init__(self):
        self.events = []
        jax.monitoring.register_event_duration_secs_listener(
            lambda event, secs, **kw: self.events.append((event, secs, kw.get("fun_name")))
        )

    def mark(self) -> int:
        return len(self.events)

    def since(self, mark: int) -> dict:
        events = self.events[mark:]
        xla = [(name, secs) for event, secs, name in events if event == BACKEND_COMPILE]
        return {
            "compilations": len(xla),
            "compile_s": sum(s for _, s in xla),
            "programs": [{"program": name, "s": secs} for name, secs in xla],
            "tracings": sum(1 for e, _, _ in events if e.endswith("jaxpr_trace_duration")),
            "lowerings": sum(1 for e, _, _ in events if e.endswith("jaxpr_to_mlir_module_duration")),
        }


# --------------------------------------------------------------------------------------------
# Part 1: compile once per system and shapes, in fresh child processes.

SCENES = ("rigid_body", "heavy_top", "user_pendulum")
CHILD_REPEATS = 3
CHILD_REPEATS_QUICK = 1
SCENE_N, SCENE_DT = 1000, 0.01
# (call, n_steps, dt, parameters: "first" or "new"); new_parameters is left out for user systems
CALLS = (
    ("first", SCENE_N, SCENE_DT, "first"),
    ("new_n_steps", 1500, SCENE_DT, "first"),
    ("new_dt", SCENE_N, 0.02, "first"),
    ("new_parameters", SCENE_N, SCENE_DT, "new"),
    ("first_again", SCENE_N, SCENE_DT, "first"),
)
CALL_NAMES = tuple(c[0] for c in CALLS)


def scene(name: str):
    """(make(params) -> system, first params, new params or None, Q0, xi0, what the parameters are)."""
    if name == "rigid_body":
        return (
            lambda p: cj.models.rigid_body(p[0]),
            (jnp.array(RIGID_INERTIA),),
            (jnp.array([1.5, 1.2, 0.7]),),
            jnp.eye(3),
            jnp.array(RIGID_XI0),
            "inertia (2, 1, 2/3), then (1.5, 1.2, 0.7)",
        )
    if name == "heavy_top":
        return (
            lambda p: cj.models.heavy_top(p[0], p[1]),
            (jnp.array(TOP_INERTIA), TOP_MGL),
            (jnp.array([1.2, 1.1, 0.5]), 2.0),
            *top_start(),
            "inertia (1, 1, 0.4), m g l 1.5, then (1.2, 1.1, 0.5), 2.0",
        )
    if name == "user_pendulum":
        system = user_pendulum()  # written once, by the user; no parameters to change
        return (lambda p: system, (), None, *pendulum_start(), None)
    raise ValueError(f"unknown scene {name!r}; one of {SCENES}")


def child_calls(name: str) -> dict:
    """In this (fresh) process: the five calls of part 1 on scene `name`; what each cost."""
    cache_dir = jax.config.values.get("jax_compilation_cache_dir")
    if cache_dir:
        raise RuntimeError("a persistent compilation cache is on in the child; part 1 needs cold compiles")
    log = CompileLog()
    tic = time.perf_counter()
    jax.block_until_ready(jax.jit(jnp.sin)(jnp.arange(3.0)))  # backend and XLA start-up, not the scene's
    first_jit = time.perf_counter() - tic
    make, params, new_params, Q0, xi0, _ = scene(name)
    system = make(params)
    out = {
        "scene": name,
        "process_first_jit_s": first_jit,
        "load_average_1min_at_start": harness.load_average(),
        "source_sha256": harness.source_digest(),
        "calls": {},
    }
    first_state = None
    for call, n, dt, which in CALLS:
        entry = {"n_steps": n, "dt": dt}
        sys_call = system
        if which == "new":
            if new_params is None:
                continue
            mark = log.mark()
            sys_call = make(new_params)  # the model constructed again with other values
            entry["construct"] = log.since(mark)
        mark = log.mark()
        tic = time.perf_counter()
        sol = jax.block_until_ready(cj.integrate(sys_call, Q0, xi0, dt=dt, n_steps=n))
        entry["wall_s"] = time.perf_counter() - tic
        entry.update(log.since(mark))
        entry["method"], entry["form"], entry["order"] = sol.method, sol.form, sol.order
        state = final_state(sol)
        if call == "first":
            first_state = state
        if call == "first_again":  # the same programs on the same input: the same numbers
            entry["max_abs_final_diff_vs_first"] = float(np.max(np.abs(state - first_state)))
        out["calls"][call] = entry
    return out


def child_env() -> dict:
    """The environment of a child: this one without a persistent compilation cache."""
    env = dict(os.environ)
    for key in CACHE_VARIABLES:
        env.pop(key, None)
    return env


def run_child(name: str, run: harness.Run) -> dict:
    cmd = [sys.executable, str(Path(__file__).resolve()), "--scene", name] + (["--quick"] if run.quick else [])
    with run.guard(f"child process, scene {name}"):
        done = subprocess.run(cmd, capture_output=True, text=True, check=False, env=child_env())
    if done.returncode != 0:
        raise RuntimeError(f"the child for scene {name} failed:\n{done.stderr[-3000:]}")
    out = json.loads(done.stdout.strip().splitlines()[-1])
    if out["source_sha256"] != harness.source_digest():
        raise RuntimeError(
            f"the child for scene {name} imported other clebsch_jax sources than this process (check PYTHONPATH)"
        )
    return out


def compile_once(run: harness.Run) -> list:
    """Part 1: every scene in `repeats` fresh children, the scenes interleaved round by round."""
    repeats = CHILD_REPEATS_QUICK if run.quick else CHILD_REPEATS
    children = {name: [] for name in SCENES}
    for r in range(repeats):
        for name in SCENES:
            with run.case(f"part 1, scene {name}, child {r + 1} of {repeats}"):
                children[name].append(run_child(name, run))
    rows = []
    for name in SCENES:
        kids = children[name]
        first = [k["calls"]["first"]["wall_s"] for k in kids]
        calls = {}
        for call in CALL_NAMES:
            if call not in kids[0]["calls"]:
                continue
            entries = [k["calls"][call] for k in kids]
            walls = [e["wall_s"] for e in entries]
            compiled = sorted({p["program"] for e in entries for p in e["programs"]})
            calls[call] = {
                "n_steps": entries[0]["n_steps"],
                "dt": entries[0]["dt"],
                "wall_s_median": statistics.median(walls),
                "wall_s": walls,
                "over_first": statistics.median(walls) / statistics.median(first),
                "over_first_per_child": [w / f for w, f in zip(walls, first)],
                "compilations": [e["compilations"] for e in entries],
                "compile_s": [e["compile_s"] for e in entries],
                "programs_compiled": compiled,
                "tracings": [e["tracings"] for e in entries],
                "lowerings": [e["lowerings"] for e in entries],
                "method": entries[0]["method"],
                "form": entries[0]["form"],
                "order": entries[0]["order"],
            }
            if "construct" in entries[0]:
                calls[call]["construct_compilations"] = [e["construct"]["compilations"] for e in entries]
            if call == "first_again":
                calls[call]["max_abs_final_diff_vs_first"] = max(e["max_abs_final_diff_vs_first"] for e in entries)
        later = [c for c in CALL_NAMES[1:] if c in calls]
        rows.append(
            {
                "part": "compile_once",
                "scene": name,
                "children": len(kids),
                "parameters": scene(name)[5],
                "calls": calls,
                "process_first_jit_s": [k["process_first_jit_s"] for k in kids],
                "load_average_1min_at_child_start": [k["load_average_1min_at_start"] for k in kids],
                "max_compilations_calls_2_to_5": max(max(calls[c]["compilations"]) for c in later),
                "max_construct_compilations": max(calls.get("new_parameters", {}).get("construct_compilations", [0])),
            }
        )
    return rows


# --------------------------------------------------------------------------------------------
# Part 2: the heavy top's new default against the reduced left step and the midpoint principle.

HT_DT = 0.01
HT_N, HT_N_QUICK = 2000, 200
HT_REFINE = 16  # the reference: the default at dt / 16
HT_METHODS = (("default", {}), ("left", {"scheme": "left"}), ("midpoint", {"scheme": "midpoint"}))


def heavy_top_cost(run: harness.Run) -> dict:
    n = HT_N_QUICK if run.quick else HT_N
    system = cj.models.heavy_top(jnp.array(TOP_INERTIA), TOP_MGL)
    Q0, xi0 = top_start()

    def call(kwargs, dt=HT_DT, steps=n):
        return lambda: jax.block_until_ready(cj.integrate(system, Q0, xi0, dt=dt, n_steps=steps, **kwargs))

    timings, outs = run.time({name: call(kw) for name, kw in HT_METHODS}, what=f"heavy top, {n} steps")
    with run.guard("heavy top, reference runs"):
        reference = final_state(call({}, HT_DT / HT_REFINE, n * HT_REFINE)())
        half_reference = final_state(call({}, 2 * HT_DT / HT_REFINE, n * HT_REFINE // 2)())
    row = {
        "part": "heavy_top_cost",
        "n_steps": n,
        "dt": HT_DT,
        "t_final": n * HT_DT,
        "reference": f"default at dt/{HT_REFINE}",
        "reference_check_default_dt_over_8": float(np.max(np.abs(half_reference - reference))),
    }
    for name, kwargs in HT_METHODS:
        sol = outs[name]
        row[name] = {
            **timings[name],
            "keywords": kwargs,
            "seconds_per_step": timings[name]["per_call_s"] / n,
            "compile_s": timings[name]["first_call_s"] - timings[name]["per_call_s"],
            "method": sol.method,
            "form": sol.form,
            "order": sol.order,
            "solves_per_step": sol.solves_per_step,
            "newton_updates_per_step_mean": float(np.mean(np.asarray(sol.stats.iterations))),
            "final_error_vs_reference": float(np.max(np.abs(final_state(sol) - reference))),
        }
    row["ratios"] = {
        "default_over_left": row["default"]["per_call_s"] / row["left"]["per_call_s"],
        "midpoint_over_default": row["midpoint"]["per_call_s"] / row["default"]["per_call_s"],
    }
    row["paired_ratios"] = {
        "default_over_left": harness.paired_ratios(row["default"]["samples_s"], row["left"]["samples_s"]),
        "midpoint_over_default": harness.paired_ratios(row["midpoint"]["samples_s"], row["default"]["samples_s"]),
    }
    return row


# --------------------------------------------------------------------------------------------
# Part 3: measured order of the default.


def order_case(name: str, case, log: CompileLog) -> dict:
    system, Q0, xi0, P0, T, h0 = case
    plan = cj.step_plan(system, Q0=Q0, xi0=xi0)
    runs, per_run = {}, []
    for k in ORDER_DIVISORS + (ORDER_REFERENCE,):
        n = round(T / h0) * k
        mark = log.mark()
        tic = time.perf_counter()
        sol = jax.block_until_ready(cj.integrate(system, Q0, xi0, P0=P0, dt=h0 / k, n_steps=n))
        wall = time.perf_counter() - tic
        compiled = log.since(mark)
        runs[k] = final_state(sol)
        per_run.append(
            {
                "divisor": k,
                "dt": h0 / k,
                "n_steps": n,
                "wall_s": wall,
                "compilations": compiled["compilations"],
                "method": sol.method,
                "order": sol.order,
            }
        )
    hs = np.array([h0 / k for k in ORDER_DIVISORS])
    errors = np.array([np.max(np.abs(runs[k] - runs[ORDER_REFERENCE])) for k in ORDER_DIVISORS])
    slope = float(np.polyfit(np.log(hs), np.log(errors), 1)[0])
    return {
        "part": "order",
        "model": name,
        "t_final": T,
        "h0": h0,
        "reference_divisor": ORDER_REFERENCE,
        "plan": plan.name,
        "plan_order": plan.order,
        "plan_symmetric": bool(plan.symmetric),
        "method": per_run[0]["method"],
        "order": per_run[0]["order"],
        "form": sol.form,
        "hs": hs.tolist(),
        "errors": errors.tolist(),
        "slope": slope,
        "local_slopes": (np.diff(np.log(errors)) / np.diff(np.log(hs))).tolist(),
        "runs": per_run,
        "compilations_after_first_step_size": sum(r["compilations"] for r in per_run[1:]),
    }


def measured_orders(run: harness.Run) -> list:
    names = ORDER_MODELS_QUICK if run.quick else ORDER_MODELS
    cases = order_cases(names)
    log = CompileLog()
    rows = []
    for name in names:
        with run.case(f"part 3, order of the default, {name}"), run.guard(f"order, {name}"):
            rows.append(order_case(name, cases[name], log))
    return rows


# --------------------------------------------------------------------------------------------
# Targets.


def verdicts(scenes: list, top: dict, orders: list) -> dict:
    t = TARGETS
    new_n = {r["scene"]: r["calls"]["new_n_steps"]["over_first"] for r in scenes}
    compiles = {r["scene"]: r["max_compilations_calls_2_to_5"] for r in scenes}
    ratio = top["ratios"]["default_over_left"]
    slopes = {r["model"]: r["slope"] for r in orders}
    return {
        "new_n_steps_over_first": {
            "max": t["new_n_steps_over_first"],
            "per_scene": new_n,
            "met": all(v <= t["new_n_steps_over_first"] for v in new_n.values()),
        },
        "compilations_calls_2_to_5": {
            "max": t["compilations_calls_2_to_5"],
            "per_scene": compiles,
            "met": all(v <= t["compilations_calls_2_to_5"] for v in compiles.values()),
        },
        "heavy_top_default_over_left": {
            "max": t["heavy_top_default_over_left"],
            "value": ratio,
            "met": bool(ratio <= t["heavy_top_default_over_left"]),
        },
        "order": {
            "min_slope": t["min_order_slope"],
            "per_model": slopes,
            "met": all(s >= t["min_order_slope"] for s in slopes.values()),
        },
    }


# --------------------------------------------------------------------------------------------
# Printing and plotting.

_CALL_LABEL = {
    "first": "1 first",
    "new_n_steps": "2 new n",
    "new_dt": "3 new dt",
    "new_parameters": "4 new params",
    "first_again": "5 again",
}


def _met(v: dict) -> str:
    return "met" if v["met"] else "NOT met"


def print_report(summary: dict) -> None:
    rows = summary["results"]
    scenes = [r for r in rows if r["part"] == "compile_once"]
    top = next(r for r in rows if r["part"] == "heavy_top_cost")
    orders = [r for r in rows if r["part"] == "order"]
    targets = summary["targets"]
    cfg = summary["config"]
    quick = " (--quick: not a measurement)" if cfg["quick"] else ""

    print(
        f"\n1. Compile once per system and shapes{quick}: five calls in a fresh process per scene, "
        f"median over {scenes[0]['children']} children; wall time [s] (ratio to the first call) "
        "[XLA compilations, max over children]"
    )
    harness.print_table(
        f"{'scene':<15}{'method':<26}|" + "".join(f"{_CALL_LABEL[c]:>22}" for c in CALL_NAMES),
        (
            f"{r['scene']:<15}{r['calls']['first']['method']:<26}|"
            + "".join(
                f"{'-':>22}"
                if c not in r["calls"]
                else f"{r['calls'][c]['wall_s_median']:>8.3f} ({r['calls'][c]['over_first']:6.4f}) "
                f"[{max(r['calls'][c]['compilations'])}]"
                for c in CALL_NAMES
            )
            for r in scenes
        ),
    )
    for r in scenes:
        first = r["calls"]["first"]
        jit0 = statistics.median(r["process_first_jit_s"])
        print(
            f"  {r['scene']}: first call compiles {statistics.median(first['compilations']):.0f} programs "
            f"(XLA {statistics.median(first['compile_s']):.2f} s; backend start-up before it {jit0:.2f} s); "
            f"rebuilt model compiled {r['max_construct_compilations']} programs; call 5 vs call 1: "
            f"max |diff| {r['calls']['first_again']['max_abs_final_diff_vs_first']:.1e}"
        )
        for c in CALL_NAMES[1:]:
            if c in r["calls"] and r["calls"][c]["programs_compiled"]:
                print(f"  !! {r['scene']} call '{c}' compiled: {', '.join(r['calls'][c]['programs_compiled'])}")
    print(
        f"Targets: new n_steps <= {TARGETS['new_n_steps_over_first']} of the first call: "
        f"{_met(targets['new_n_steps_over_first'])}; no compilation in calls 2-5: "
        f"{_met(targets['compilations_calls_2_to_5'])}."
    )

    print(
        f"\n2. Heavy top, {top['n_steps']} steps of dt = {top['dt']} (T = {top['t_final']:g}), one trajectory{quick}; "
        f"error at T against {top['reference']} (the default at dt/8 is {top['reference_check_default_dt_over_8']:.1e} "
        "from it):"
    )
    harness.print_table(
        f"{'method':<10}{'Solution.method':<26}{'order':>6}{'form':>9}{'us/step':>10}{'compile s':>11}"
        f"{'updates/step':>14}{'error at T':>12}",
        (
            f"{m:<10}{top[m]['method']:<26}{top[m]['order']:>6}{top[m]['form']:>9}{top[m]['seconds_per_step'] * 1e6:>10.2f}"
            f"{top[m]['compile_s']:>11.2f}{top[m]['newton_updates_per_step_mean']:>14.2f}"
            f"{top[m]['final_error_vs_reference']:>12.2e}"
            for m, _ in HT_METHODS
        ),
    )
    q, p = top["ratios"], top["paired_ratios"]
    print(
        f"default/left {q['default_over_left']:.2f} (paired rounds {p['default_over_left']['min']:.2f}-"
        f"{p['default_over_left']['max']:.2f}; target <= {TARGETS['heavy_top_default_over_left']}: "
        f"{_met(targets['heavy_top_default_over_left'])}); midpoint/default {q['midpoint_over_default']:.2f} "
        f"(paired {p['midpoint_over_default']['min']:.2f}-{p['midpoint_over_default']['max']:.2f})"
    )

    print(
        f"\n3. Measured order of the default{quick}: error at the final time against the h0/{ORDER_REFERENCE} run; "
        "slope of the log-log least-squares fit"
    )
    harness.print_table(
        f"{'model':<19}{'method':<26}{'order':>6}{'h0':>6}"
        + "".join(f"{f'err h0/{k}':>11}" for k in ORDER_DIVISORS)
        + f"{'slope':>7}{'compiles after 1st':>20}",
        (
            f"{r['model']:<19}{r['method']:<26}{r['order']:>6}{r['h0']:>6g}"
            + "".join(f"{e:>11.2e}" for e in r["errors"])
            + f"{r['slope']:>7.2f}{r['compilations_after_first_step_size']:>20}"
            for r in orders
        ),
    )
    print(f"Target: slope >= {TARGETS['min_order_slope']} on every model: {_met(targets['order'])}.")


def plot(summary: dict, path: Path) -> None:
    rows = summary["results"]
    scenes = [r for r in rows if r["part"] == "compile_once"]
    top = next(r for r in rows if r["part"] == "heavy_top_cost")
    orders = [r for r in rows if r["part"] == "order"]
    fig, (ax1, ax2, ax3) = harness.figure((1.2, 1, 1.2), size=(15, 4.8))

    for i, r in enumerate(scenes):
        xs = [k for k, c in enumerate(CALL_NAMES) if c in r["calls"]]
        med = [r["calls"][CALL_NAMES[k]]["wall_s_median"] for k in xs]
        lo = [med[j] - min(r["calls"][CALL_NAMES[k]]["wall_s"]) for j, k in enumerate(xs)]
        hi = [max(r["calls"][CALL_NAMES[k]]["wall_s"]) - med[j] for j, k in enumerate(xs)]
        ax1.errorbar(
            [x + 0.08 * (i - 1) for x in xs],
            med,
            yerr=[lo, hi],
            marker="os^"[i % 3],
            ls="-",
            capsize=3,
            label=f"{r['scene']} ({r['calls']['first']['method']})",
        )
    ax1.set_yscale("log")
    ax1.set_xticks(range(len(CALL_NAMES)), [_CALL_LABEL[c] for c in CALL_NAMES], fontsize=8)
    ax1.set_ylabel("wall time of the call [s] (median, min-max over children)")
    ax1.grid(True, which="both", alpha=0.3)
    ax1.legend(fontsize=7)
    mach = summary["machine"]
    ax1.set_title(
        f"A fresh process per scene: five calls, median of {scenes[0]['children']} children"
        f"{' (--quick: not a measurement)' if summary['config']['quick'] else ''}\n"
        f"{mach['cpu_count']} CPUs, load {mach['load_average_1min_at_start']:.2f} at start, "
        f"jax {mach['jax']}",
        fontsize=8,
    )

    for (m, _), marker in zip(HT_METHODS, "os^"):
        e = top[m]
        ax2.loglog(
            [e["seconds_per_step"] * 1e6],
            [e["final_error_vs_reference"]],
            marker=marker,
            ms=9,
            ls="none",
            label=f"{m}: {e['method']} (order {e['order']})",
        )
        ax2.annotate(
            f"{e['seconds_per_step'] * 1e6:.3g} µs, {e['final_error_vs_reference']:.2g}",
            (e["seconds_per_step"] * 1e6, e["final_error_vs_reference"]),
            textcoords="offset points",
            xytext=(8, 6),
            fontsize=8,
        )
    ax2.margins(0.25)
    from matplotlib.ticker import NullFormatter

    for axis in (ax2.xaxis, ax2.yaxis):
        axis.set_minor_formatter(NullFormatter())  # decade labels only (a narrow range)
    ax2.set_xlabel("wall time per step [µs]")
    ax2.set_ylabel(f"error at T = {top['t_final']:g} ({top['reference']})")
    ax2.grid(True, which="both", alpha=0.3)
    ax2.legend(fontsize=7)
    ax2.set_title(
        f"Heavy top, dt = {top['dt']}, {top['n_steps']} steps: default/left {top['ratios']['default_over_left']:.2f}",
        fontsize=9,
    )

    for i, r in enumerate(orders):  # markers and dashes tell apart curves that coincide
        hs, errs = np.array(r["hs"]) / r["h0"], np.array(r["errors"])
        ax3.loglog(
            hs,
            errs,
            marker="os^vD<>p"[i % 8],
            ms=7 - (i % 2) * 3,
            ls="-" if i % 2 == 0 else "--",
            label=f"{r['model']} ({r['slope']:.2f})",
        )
    guide = np.array([1 / 8, 1.0])
    top_err = max(max(r["errors"]) for r in orders)
    ax3.loglog(guide, 2 * top_err * guide**2, "k--", lw=1, label="slope 2")
    ax3.set_xticks([1 / k for k in ORDER_DIVISORS], [f"1/{k}" if k > 1 else "1" for k in ORDER_DIVISORS])
    ax3.minorticks_off()
    ax3.set_xlabel("step size h / h0")
    ax3.set_ylabel(f"error at the final time (against h0/{ORDER_REFERENCE})")
    ax3.grid(True, which="both", alpha=0.3)
    ax3.legend(fontsize=6, ncol=2)
    ax3.set_title("Order of the default (fitted slope)", fontsize=9)
    fig.savefig(path, dpi=120)


# --------------------------------------------------------------------------------------------


def _add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", default=None, help=argparse.SUPPRESS)  # a child of part 1


def main(argv=None) -> dict | None:
    """Runs the three parts, prints the report, writes the JSON and the PNG; returns the summary."""
    run = harness.Run(
        RESULTS_NAME,
        argv,
        description="Compile once per system and shapes, the heavy top's "
        "default against the left step, and the order of the default (see module docstring).",
        add_arguments=_add_arguments,
    )
    if run.args.scene:  # a child of part 1
        with harness.quick_mode(run.quick):
            print(json.dumps(child_calls(run.args.scene)))
        return None
    with run:
        scenes = compile_once(run)
        with run.case("part 2, heavy top: default, left, midpoint"):
            top = heavy_top_cost(run)
        orders = measured_orders(run)
    summary = run.summary(
        config={
            "part1": {
                "scenes": list(SCENES),
                "children_per_scene": len(scenes[0]["process_first_jit_s"]),
                "calls": [{"call": c, "n_steps": n, "dt": dt, "parameters": p} for c, n, dt, p in CALLS],
                "persistent_cache_in_children": False,
                "compile_event": BACKEND_COMPILE,
                "chunk_steps": CHUNK_STEPS,
            },
            "part2": {
                "inertia": list(TOP_INERTIA),
                "mass_gravity_length": TOP_MGL,
                "Q0": "so3_exp((0.5, 0, 0))",
                "xi0": [0.3, -0.2, 2.0],
                "dt": HT_DT,
                "n_steps": top["n_steps"],
                "methods": {m: kw for m, kw in HT_METHODS},
                "reference": top["reference"],
            },
            "part3": {
                "models": [r["model"] for r in orders],
                "divisors": list(ORDER_DIVISORS),
                "reference_divisor": ORDER_REFERENCE,
                "setups": "tests/test_defaults.py",
            },
        },
        results=scenes + [top] + orders,
        targets=verdicts(scenes, top, orders),
    )
    return run.finish(summary, print_report, plot)


if __name__ == "__main__":
    main()
