r"""Engine regression: the same public-API calls timed on two checkouts of clebsch-jax, side by side.

Run from the repository root, with a checkout of the commit to compare against:

    git worktree add ../baseline <commit>                                   # once
    python benchmarks/engine_regression.py --baseline ../baseline           # default run
    python benchmarks/engine_regression.py --baseline ../baseline --scenes rigid_single,compile
    python benchmarks/engine_regression.py --quick                          # smoke test (not a measurement)

It answers "did a change of the engine make any scene slower?" (the redesign issue: no scene
may get slower by more than 10 %). **old** is the engine of the `--baseline` checkout, **new**
the engine of the checkout this script is in; without `--baseline` the engine is compared
with itself (an A/A run: both columns run the same code, so the spread of its ratios is the
noise of the measurement).

How: each engine runs in its own long-lived worker process (this script with `--worker`,
`PYTHONPATH` set to the engine's checkout; the worker checks that `clebsch_jax` came from
there), so both are imported once and every program is compiled once per engine. For each
scene both workers build the same call from the same inputs (public API only, the subset both
engines share) and make a first call (compiles) and a second; the faster engine's second call
fixes `number`, the calls per sample of both engines, so that a sample lasts at least
`--min-sample` s (one engine's slow warm-up call does not leave it samples of a few calls).
Then `--repeats` rounds each take one sample of old and one of new, one after the other — the
worker that goes first alternates from round to round, the other worker sleeps meanwhile — so
both see the same machine load. A
sample is timed inside its worker (`time.perf_counter` around `number` blocking calls, no
inter-process traffic inside); time per call = median over the rounds of (sample / number);
the ratio new/old is the ratio of the medians, and the ratios of the two samples of each round
(taken back to back) are reported as their median and range: how noisy the ratio is. A
ratio > 1.10 is flagged.

The two engines must compute the same thing, or the speed comparison means nothing: the
final state of each scene (every array the scene returns at its last node) is compared,
max |new − old| and whether the bits are identical; differences above 1e-12 are flagged, and
so are differences in the Newton work (updates per step), which would make a speed difference
a difference of the computation.

Compile time (scene `compile`): the first call of the reduced rigid body (`rigid_single`'s
call) and of the full march (`rigid_full`'s) in a fresh worker, without a persistent
compilation cache (the worker drops the cache variables from its environment and records
that no cache is on), after one tiny `jax.jit` that starts the backend; compile time = first
call − second call. A fresh pair of workers per round and program, old and new in turn.

Scenes (`SCENES`; `--quick` shrinks every size to a few steps and members):

| scene | call |
|---|---|
| `rigid_single` | `integrate(rigid_body(I), Q0, xi0, dt=0.05, n_steps=1000)`: reduced (Cayley), one plain call |
| `rigid_vmap` | `jax.jit(jax.vmap(integrate(..., throw=False)))`, 1000 bodies × 100 steps |
| `rigid_batch` | `jax.jit(cj.batch(...))`, 10⁴ bodies × 100 steps, final state only |
| `rigid_full` | `reduce=False`, 200 steps |
| `rigid_order4` | `order=4`, reduced, 200 steps |
| `top_midpoint` | `heavy_top`, `scheme="midpoint"` (full), 200 steps of 0.01 |
| `top_order2` | `heavy_top`, `order=2` (reduced), 200 steps |
| `vortices4_dense` | 4 leapfrogging vortices, midpoint, `jacobian="dense"`, 200 steps of 0.02 |
| `vortices100_blocks` | 100 random vortices, `jacobian="blocks"`, 50 steps of 0.01 |
| `clusters_batch` | 100 clusters of 4 random vortices, `jax.jit(cj.batch(..., chunk=64))`, 100 steps |
| `gauss_rigid_vector` | `rigid_body_vector`, `scheme="gauss", order=8`, dt 0.25, 200 bodies `jax.vmap`ped, 200 steps |
| `gauss_vortices4` | the 4 vortices, `scheme="gauss", order=16`, dt 0.5, 100 steps |
| `sweep` | `cj.sweep(rigid_body, ...)` of 1000 bodies × 200 steps |
| `compile` | first calls of `rigid_single` and `rigid_full` in fresh workers |

Outputs (in `--out`, default `benchmarks/results`): `engine_regression.json` (per scene both
engines' timings, samples, loads, ratios, the final-state comparison, Newton work; the
engines' commits — never the checkouts' paths) and `engine_regression.png` (the ratio per
scene with its per-round range, and the compile times). Nothing here asserts a wall time.
"""

from __future__ import annotations

import json
import math
import os
import select
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]  # the checkout this script is in: the "new" engine
WORKER_FLAG = "--worker"
if WORKER_FLAG not in sys.argv[1:]:
    # the parent records the machine with the new engine (the worker's engine comes from PYTHONPATH)
    sys.path.insert(0, str(REPO))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import _timing as harness  # noqa: E402
import clebsch_jax as cj  # noqa: E402

RESULTS_NAME = "engine_regression"
ENGINES = ("old", "new")
THRESHOLD = 1.10  # the limit: new/old time per call
SAME_TOLERANCE = 1e-12  # max |new - old| of the final state for "the same computation"
DT_RIGID = 0.05
DT_TOP = 0.01

# name -> (description, default sizes, quick sizes). Sizes are the keyword arguments of the
# scene's builder in the worker (`_build`).
SCENES = {
    "rigid_single": ("rigid body, reduced (Cayley), 1 plain call", {"n_steps": 1000}, {"n_steps": 10}),
    "rigid_vmap": ("rigid body, reduced, jit(vmap)", {"batch": 1000, "n_steps": 100}, {"batch": 4, "n_steps": 10}),
    "rigid_batch": (
        "rigid body, reduced, jit(cj.batch), final state only",
        {"batch": 10_000, "n_steps": 100},
        {"batch": 6, "n_steps": 10, "chunk": 4},
    ),
    "rigid_full": ("rigid body, full march (reduce=False)", {"n_steps": 200}, {"n_steps": 10}),
    "rigid_order4": ("rigid body, order-4 composition, reduced", {"n_steps": 200}, {"n_steps": 5}),
    "top_midpoint": ("heavy top, midpoint (full)", {"n_steps": 200}, {"n_steps": 10}),
    "top_order2": ("heavy top, order=2 (reduced)", {"n_steps": 200}, {"n_steps": 10}),
    "vortices4_dense": ("4 vortices, midpoint, jacobian=dense", {"n_steps": 200}, {"n_steps": 10}),
    "vortices100_blocks": ("100 random vortices, jacobian=blocks", {"N": 100, "n_steps": 50}, {"N": 10, "n_steps": 5}),
    "clusters_batch": (
        "4-vortex clusters, jit(cj.batch(chunk=64))",
        {"batch": 100, "n_steps": 100, "chunk": 64},
        {"batch": 6, "n_steps": 5, "chunk": 4},
    ),
    "gauss_rigid_vector": (
        "rigid_body_vector, Gauss order 8, dt 0.25, jit(vmap)",
        {"batch": 200, "n_steps": 200},
        {"batch": 3, "n_steps": 5},
    ),
    "gauss_vortices4": ("4 vortices, Gauss order 16, dt 0.5", {"n_steps": 100}, {"n_steps": 5}),
    "sweep": ("cj.sweep of rigid bodies", {"batch": 1000, "n_steps": 200}, {"batch": 4, "n_steps": 10}),
}
QUICK_SCENES = ("rigid_single", "rigid_batch", "clusters_batch", "sweep")
# the compile-time scene: first calls of these scenes' programs in fresh workers (--quick: the
# first one, one round)
COMPILE = "compile"
COMPILE_SCENES = ("rigid_single", "rigid_full")
DEFAULT_REPEATS = 9  # rounds when --repeats is not given (not --quick): the ratios are noisy on a shared machine

ENV_DROPPED = ("JAX_COMPILATION_CACHE_DIR", "CLEBSCH_JAX_CACHE_DIR", "PYTHONPATH")


# --------------------------------------------------------------------------------------------
# The worker: builds and times the scenes on the engine it imported.


def _leapfrog():
    """Two leapfrogging vortex pairs (the README's scene)."""
    return jnp.array([1.0, -1.0, 1.0, -1.0]), jnp.array([[0.0, 1.0], [0.0, -1.0], [0.0, 0.5], [0.0, -0.5]])


def _last(x, batched: bool) -> np.ndarray:
    """The last node of a trajectory array (time axis 0, or 1 under a batch)."""
    return np.asarray(x)[:, -1] if batched else np.asarray(x)[-1]


def _solution_report(sol, batched: bool) -> tuple[dict, dict]:
    """(final state, facts) of a Solution: the last node of every array it has; its form and
    the Newton work."""
    final = {k: _last(getattr(sol, k), batched) for k in ("Q", "p", "xi", "momentum") if getattr(sol, k) is not None}
    final["xi_step"] = _last(sol.xi_step, batched)
    iters = np.asarray(sol.stats.iterations, dtype=float)
    facts = {
        "form": sol.form,
        "scheme": sol.scheme,
        "order": int(sol.order),
        "method": sol.method,
        "all_valid": bool(np.all(np.asarray(sol.valid))),
        "newton_updates_per_step": float(iters.mean()),
        "newton_jacobians_per_step": float(np.mean(np.asarray(sol.stats.jacobians, dtype=float))),
    }
    return final, facts


def _build(name: str, compiler_options, *, n_steps, batch=None, chunk=None, N=None):
    """(call, report) of a scene: `call()` blocks until its result is ready; `report(out)` is
    (final state {name: array}, facts) of the first call's output."""
    import rigid_body_step_cost as rigid
    import vortex_step_cost as vortex

    def jit(f):
        return jax.jit(f, compiler_options=compiler_options)

    inertia = jnp.asarray(rigid.INERTIA)
    body = cj.models.rigid_body(inertia)

    def plain(system, Q0, xi0, dt, **kw):
        return (
            lambda: jax.block_until_ready(cj.integrate(system, Q0, xi0, dt=dt, n_steps=n_steps, **kw)),
            lambda sol: _solution_report(sol, batched=False),
        )

    if name in ("rigid_single", "rigid_full", "rigid_order4"):
        Q0, xi0 = rigid.initial_conditions(1)
        kw = {"rigid_single": {}, "rigid_full": {"reduce": False}, "rigid_order4": {"order": 4}}[name]
        return plain(body, jnp.asarray(Q0[0]), jnp.asarray(xi0[0]), DT_RIGID, **kw)
    if name == "rigid_vmap":
        Q0, xi0 = (jnp.asarray(a) for a in rigid.initial_conditions(batch))
        march = jit(jax.vmap(lambda q, x: cj.integrate(body, q, x, dt=DT_RIGID, n_steps=n_steps, throw=False)))
        return lambda: jax.block_until_ready(march(Q0, xi0)), lambda sol: _solution_report(sol, batched=True)
    if name == "rigid_batch":
        Q0, xi0 = (jnp.asarray(a) for a in rigid.initial_conditions(batch))

        def final_only(q, x):
            sol = cj.integrate(body, q, x, dt=DT_RIGID, n_steps=n_steps, throw=False)
            return {
                "Q": sol.Q[-1],
                "xi": sol.xi[-1],
                "momentum": sol.momentum[-1],
                "updates": jnp.mean(sol.stats.iterations.astype(float)),
                "valid": sol.valid[-1],
            }

        kw = {} if chunk is None else {"chunk": chunk}
        march = jit(cj.batch(final_only, **kw))

        def report(out):
            out = {k: np.asarray(v) for k, v in out.items()}
            return (
                {k: out[k] for k in ("Q", "xi", "momentum")},
                {"all_valid": bool(np.all(out["valid"])), "newton_updates_per_step": float(out["updates"].mean())},
            )

        return lambda: jax.block_until_ready(march(Q0, xi0)), report
    if name in ("top_midpoint", "top_order2"):
        system = cj.models.heavy_top(jnp.array([1.0, 1.2, 0.5]), 1.7, (0.0, 0.6, 0.8))
        Q0, xi0 = cj.lie.so3_exp(jnp.array([0.3, 0.2, -0.1])), jnp.array([0.5, -0.4, 3.0])
        kw = {"scheme": "midpoint"} if name == "top_midpoint" else {"order": 2}
        return plain(system, Q0, xi0, DT_TOP, **kw)
    if name in ("vortices4_dense", "gauss_vortices4"):
        G, Q0 = _leapfrog()
        kw = ({"jacobian": "dense"}, 0.02) if name == "vortices4_dense" else ({"scheme": "gauss", "order": 16}, 0.5)
        return plain(cj.models.point_vortices(G), Q0, cj.models.vortex_velocity(G, Q0), kw[1], **kw[0])
    if name == "vortices100_blocks":
        G, Q0 = (jnp.asarray(a[0]) for a in vortex.initial_conditions(N, 1))
        return plain(cj.models.point_vortices(G), Q0, cj.models.vortex_velocity(G, Q0), vortex.DT, jacobian="blocks")
    if name == "clusters_batch":
        G, Q0 = (jnp.asarray(a) for a in vortex.initial_conditions(4, batch))
        march = jit(
            cj.batch(
                lambda g, q: cj.integrate(
                    cj.models.point_vortices(g),
                    q,
                    cj.models.vortex_velocity(g, q),
                    dt=vortex.DT,
                    n_steps=n_steps,
                    throw=False,
                ),
                chunk=chunk,
            )
        )
        return lambda: jax.block_until_ready(march(G, Q0)), lambda sol: _solution_report(sol, batched=True)
    if name == "gauss_rigid_vector":
        system = cj.models.rigid_body_vector(inertia)
        _, xi0 = rigid.initial_conditions(batch)
        mu0 = jnp.asarray(xi0) * inertia  # unit body momenta
        Q0, P0 = jax.vmap(cj.models.rigid_body_vector_start)(mu0)
        march = jit(
            jax.vmap(
                lambda q, p, m: cj.integrate(
                    system, q, m / inertia, P0=p, dt=0.25, n_steps=n_steps, scheme="gauss", order=8, throw=False
                )
            )
        )
        return lambda: jax.block_until_ready(march(Q0, P0, mu0)), lambda sol: _solution_report(sol, batched=True)
    if name == "sweep":
        Q0, xi0 = (jnp.asarray(a) for a in rigid.initial_conditions(batch))

        def call():
            return cj.sweep(cj.models.rigid_body, inertia[None], Q0, xi0, dt=DT_RIGID, n_steps=n_steps, grid=True)

        def report(res):
            final = {
                k: np.asarray(getattr(res, f"final_{k}"))
                for k in ("Q", "xi", "momentum", "p")
                if getattr(res, f"final_{k}") is not None
            }
            return final, {
                "form": res.form,
                "scheme": res.scheme,
                "all_valid": bool(np.all(res.status == 0)),
                "newton_updates_per_step": float(np.mean(res.newton_iterations)) / n_steps,
                "max_energy_error": float(np.max(res.energy_error)),
            }

        return call, report
    raise ValueError(f"unknown scene {name!r}")


def _compile_events() -> list:
    """JAX's durations of tracing, lowering and XLA compilation from now on (`jax.monitoring`)."""
    events = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda event, secs, **kw: events.append((event.rsplit("/", 1)[-1].removesuffix("_duration"), secs))
    )
    return events


def _sum_events(events) -> dict:
    out = {}
    for event, secs in events:
        out[event] = out.get(event, 0.0) + secs
    return out


def worker_main(argv) -> None:
    """Serve commands, one JSON object a line on stdin, one reply a line on the original stdout
    (anything else printed goes to stderr): `prepare` (build a scene, first and second call,
    final state to an .npz), `sample` (`number` calls, timed here), `warmup`, `exit`."""
    quick = "--quick" in argv
    timeout = float(argv[argv.index("--timeout") + 1]) if "--timeout" in argv else 600.0
    expected_root = Path(os.environ["CLEBSCH_JAX_ENGINE_ROOT"]).resolve()
    proto = os.fdopen(os.dup(1), "w", buffering=1)
    os.dup2(2, 1)

    def reply(obj):
        proto.write(json.dumps(obj) + "\n")
        proto.flush()

    if not Path(cj.__file__).resolve().is_relative_to(expected_root):
        reply({"error": f"clebsch_jax was imported from outside the engine's checkout ({cj.__file__})"})
        return
    if quick:
        jax.config.update(harness.QUICK_FLAG, True)
    compiler_options = harness.QUICK_COMPILER_OPTIONS if quick else None
    events = _compile_events()
    reply(
        {
            "engine": {
                **harness.git_revision(),
                "clebsch_jax_source_sha256": harness.source_digest(),
                "clebsch_jax": cj.__version__,
                "jax": jax.__version__,
                "jax_persistent_compilation_cache": bool(jax.config.values.get("jax_compilation_cache_dir")),
                "jax_disable_most_optimizations": bool(jax.config.values.get(harness.QUICK_FLAG)),
            }
        }
    )
    scenes = {}
    for line in sys.stdin:
        cmd = json.loads(line)
        op = cmd["op"]
        try:
            with harness.Watchdog(timeout, f"{op} {cmd.get('scene', '')}", "engine_regression worker"):
                if op == "exit":
                    reply({"ok": True})
                    return
                if op == "warmup":  # backend and XLA start-up, before a compile-time measurement
                    tic = time.perf_counter()
                    jax.block_until_ready(jax.jit(jnp.sin)(jnp.arange(3.0)))
                    reply({"s": time.perf_counter() - tic})
                elif op == "prepare":
                    name = cmd["scene"]
                    call, report = _build(name, compiler_options, **cmd["sizes"])
                    events.clear()
                    tic = time.perf_counter()
                    out = call()
                    first = time.perf_counter() - tic
                    first_events = _sum_events(events)
                    second, _ = harness.sample(call, 1)
                    scenes[name] = call
                    final, facts = report(out)
                    np.savez(cmd["final_path"], **final)
                    reply(
                        {
                            "first_call_s": first,
                            "second_call_s": second,
                            "first_call_jax_events_s": first_events,
                            "facts": facts,
                        }
                    )
                elif op == "sample":
                    wall, cpu = harness.sample(scenes[cmd["scene"]], cmd["number"])
                    reply({"wall_s": wall, "cpu_s": cpu})
                else:
                    reply({"error": f"unknown op {op!r}"})
        except Exception as exc:  # reported to the parent, which stops with it
            import traceback

            reply({"error": f"{type(exc).__name__}: {exc}\n{traceback.format_exc()[-3000:]}"})


# --------------------------------------------------------------------------------------------
# The parent: two workers, interleaved samples.


class WorkerError(RuntimeError):
    pass


class Worker:
    """A worker process on the engine of `root` (PYTHONPATH = root)."""

    def __init__(self, label: str, root: Path, run: harness.Run, tmp: Path):
        self.label, self.timeout = label, run.timeout_s
        self.log = open(tmp / f"worker-{label}-{time.monotonic_ns()}.log", "w+")
        env = {k: v for k, v in os.environ.items() if k not in ENV_DROPPED}
        env["PYTHONPATH"] = str(root)
        env["CLEBSCH_JAX_ENGINE_ROOT"] = str(root)
        cmd = [sys.executable, str(Path(__file__).resolve()), WORKER_FLAG, "--timeout", str(run.timeout_s)]
        if run.quick:
            cmd.append("--quick")
        self.proc = subprocess.Popen(
            cmd,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=self.log,
            text=True,
            bufsize=1,
            env=env,
            cwd=str(REPO),
        )
        self.engine = self._read()["engine"]

    def _read(self) -> dict:
        # backstop: the worker's own watchdog should fire first
        wait = None if self.timeout <= 0 else self.timeout + 120
        ready, _, _ = select.select([self.proc.stdout], [], [], wait)
        line = self.proc.stdout.readline() if ready else ""
        if not line:
            self.proc.kill()
            self.log.seek(0)
            raise WorkerError(
                f"the {self.label} worker {'stopped' if ready else 'timed out'}; its log ends:\n"
                f"{self.log.read()[-4000:]}"
            )
        msg = json.loads(line)
        if "error" in msg:
            raise WorkerError(f"the {self.label} worker: {msg['error']}")
        return msg

    def ask(self, op: str, **kw) -> dict:
        self.proc.stdin.write(json.dumps({"op": op, **kw}) + "\n")
        self.proc.stdin.flush()
        return self._read()

    def close(self) -> None:
        if self.proc.poll() is None:
            try:
                self.ask("exit")
                self.proc.wait(timeout=30)
            except (WorkerError, OSError, subprocess.TimeoutExpired):
                self.proc.kill()
        self.log.close()


def _load() -> list:
    return list(os.getloadavg()) if hasattr(os, "getloadavg") else []


def compare_final(old_path: Path, new_path: Path) -> dict:
    """max |new - old| over every array of the final state, and whether all bits are equal
    (NaN where both are NaN counts as equal)."""
    with np.load(old_path) as a, np.load(new_path) as b:
        if set(a.files) != set(b.files):
            return {
                "same_arrays": False,
                "arrays_old": sorted(a.files),
                "arrays_new": sorted(b.files),
                "max_abs_diff": math.inf,
                "bit_identical": False,
                "per_array": {},
            }
        per, identical = {}, True
        for k in sorted(a.files):
            x, y = a[k], b[k]
            if x.shape != y.shape:
                per[k], identical = math.inf, False
                continue
            both_nan = np.isnan(x) & np.isnan(y)
            d = np.where(both_nan, 0.0, np.abs(x - y))
            per[k] = float(np.max(d)) if d.size else 0.0
            if np.isnan(per[k]):
                per[k] = math.inf
            identical &= bool(np.array_equal(x, y, equal_nan=True))
    return {
        "same_arrays": True,
        "max_abs_diff": max(per.values(), default=0.0),
        "bit_identical": identical,
        "per_array": per,
    }


def measure_scene(name: str, workers: dict, run: harness.Run, tmp: Path) -> dict:
    """Prepare the scene in both workers, then `run.repeats` interleaved rounds."""
    description, sizes, quick_sizes = SCENES[name]
    sizes = quick_sizes if run.quick else sizes
    load_start = _load()
    prepared = {
        e: workers[e].ask("prepare", scene=name, sizes=sizes, final_path=str(tmp / f"{name}-{e}.npz")) for e in ENGINES
    }
    # one number of calls per sample for both engines, from the faster second call: a slow
    # warm-up call of one engine does not shrink its samples to a few calls that one slow
    # episode of the machine decides
    fastest = min(prepared[e]["second_call_s"] for e in ENGINES)
    number = dict.fromkeys(ENGINES, max(1, math.ceil(run.min_sample_s / max(fastest, 1e-9))))
    wall = {e: [] for e in ENGINES}
    cpu = {e: [] for e in ENGINES}
    firsts, round_loads = [], []
    for r in range(run.repeats):
        order = ENGINES if r % 2 == 0 else ENGINES[::-1]
        firsts.append(order[0])
        round_loads.append(harness.load_average())
        for e in order:
            s = workers[e].ask("sample", scene=name, number=number[e])
            wall[e].append(s["wall_s"])
            cpu[e].append(s["cpu_s"])
    row = {"scene": name, "description": description, "sizes": sizes}
    for e in ENGINES:
        p = prepared[e]
        row[e] = {
            "per_call_s": statistics.median(wall[e]),
            "samples_s": wall[e],
            "calls_per_sample": number[e],
            "cpu_per_call_s": statistics.median(cpu[e]),
            "first_call_s": p["first_call_s"],
            "second_call_s": p["second_call_s"],
            "first_call_jax_events_s": p["first_call_jax_events_s"],
            **p["facts"],
        }
    ratio = row["new"]["per_call_s"] / row["old"]["per_call_s"]
    row["ratio_new_over_old"] = ratio
    row["paired_ratio_new_over_old"] = harness.paired_ratios(wall["new"], wall["old"])
    row["slower_than_threshold"] = ratio > THRESHOLD
    row["first_in_round"] = firsts
    row["load_average_1min_per_round"] = round_loads
    row["load_average_at_start"], row["load_average_at_end"] = load_start, _load()
    row["same_result"] = compare_final(tmp / f"{name}-old.npz", tmp / f"{name}-new.npz")
    upd = [row[e].get("newton_updates_per_step") for e in ENGINES]
    row["same_newton_work"] = None if None in upd else math.isclose(upd[0], upd[1], rel_tol=1e-12)
    return row


def measure_compile(roots: dict, run: harness.Run, tmp: Path) -> dict:
    """First calls in fresh workers, old and new in turn, `run.repeats` rounds."""
    out = {"scene": COMPILE, "programs": {}}
    for name in COMPILE_SCENES[:1] if run.quick else COMPILE_SCENES:
        sizes = SCENES[name][2] if run.quick else SCENES[name][1]
        samples = {e: [] for e in ENGINES}
        for r in range(1 if run.quick else run.repeats):
            for e in ENGINES if r % 2 == 0 else ENGINES[::-1]:
                w = Worker(e, roots[e], run, tmp)
                try:
                    warm = w.ask("warmup")
                    load = harness.load_average()
                    p = w.ask("prepare", scene=name, sizes=sizes, final_path=str(tmp / f"compile-{name}-{e}.npz"))
                finally:
                    w.close()
                samples[e].append(
                    {
                        "first_call_s": p["first_call_s"],
                        "second_call_s": p["second_call_s"],
                        "compile_s": p["first_call_s"] - p["second_call_s"],
                        "warmup_jit_s": warm["s"],
                        "jax_events_s": p["first_call_jax_events_s"],
                        "load_average_1min": load,
                        "persistent_cache": w.engine["jax_persistent_compilation_cache"],
                    }
                )
        entry = {"description": SCENES[name][0], "sizes": sizes}
        for e in ENGINES:
            entry[e] = {
                "compile_s": statistics.median(s["compile_s"] for s in samples[e]),
                "first_call_s": statistics.median(s["first_call_s"] for s in samples[e]),
                "samples": samples[e],
            }
        entry["ratio_new_over_old"] = entry["new"]["compile_s"] / entry["old"]["compile_s"]
        entry["paired_ratio_new_over_old"] = harness.paired_ratios(
            [s["compile_s"] for s in samples["new"]], [s["compile_s"] for s in samples["old"]]
        )
        entry["slower_than_threshold"] = entry["ratio_new_over_old"] > THRESHOLD
        out["programs"][name] = entry
    return out


# --------------------------------------------------------------------------------------------
# Printing and plotting.


def _ms(s: float) -> str:
    return f"{s * 1e3:.4g}"


def _same(c: dict) -> str:
    if not c["same_arrays"]:
        return "DIFFERENT ARRAYS"
    if c["bit_identical"]:
        return "bit-identical"
    return f"{c['max_abs_diff']:.1e}" + ("" if c["max_abs_diff"] <= SAME_TOLERANCE else " DIFFERENT")


def print_report(summary: dict) -> None:
    cfg, eng = summary["config"], summary["engines"]
    old, new = ((eng[e]["git_commit"] or "?")[:9] + ("+dirty" if eng[e]["git_dirty"] else "") for e in ENGINES)
    harness.print_header(
        summary,
        f"Engine regression, old = {old}, new = {new}"
        + (" (A/A: the same checkout twice; the ratios show the noise)" if cfg["baseline_is_this_checkout"] else ""),
        "old and new in separate worker processes, sampled in turn (the first alternating); time per call in ms;\n"
        f"new/old: ratio of the medians, flagged SLOWER above {THRESHOLD:.2f}; paired: median [min-max] of the "
        "per-round ratios;\nsame result: max |new - old| of the final state; updates: Newton updates per step old/new.",
    )
    head = (
        f"{'scene':<20}{'old':>10}{'new':>10}{'new/old':>9}  {'paired [min-max]':<22}{'same result':<18}"
        f"{'updates':<14}{'load':>10}"
    )
    lines = []
    for r in summary["results"]:
        p = r["paired_ratio_new_over_old"]
        u = [r[e].get("newton_updates_per_step") for e in ENGINES]
        upd = "-" if None in u else (f"{u[0]:.3g}" if r["same_newton_work"] else f"{u[0]:.3g}/{u[1]:.3g}")
        loads = r["load_average_1min_per_round"]
        flag = "  SLOWER" if r["slower_than_threshold"] else ""
        lines.append(
            f"{r['scene']:<20}{_ms(r['old']['per_call_s']):>10}{_ms(r['new']['per_call_s']):>10}"
            f"{r['ratio_new_over_old']:>9.3f}  {p['median']:.3f} [{p['min']:.3f}-{p['max']:.3f}]".ljust(71)
            + f"{_same(r['same_result']):<18}{upd:<14}{min(loads):>4.1f}-{max(loads):<4.1f}{flag}"
        )
    print()
    harness.print_table(head, lines)
    comp = summary.get("compile")
    if comp:
        print(
            "\nCompile time [s], first call minus second call in a fresh worker (no persistent cache), median over "
            "rounds:"
        )
        harness.print_table(
            f"{'program':<20}{'old':>8}{'new':>8}{'new/old':>9}  {'paired [min-max]':<22}{'first call old/new':>20}",
            (
                f"{n:<20}{c['old']['compile_s']:>8.2f}{c['new']['compile_s']:>8.2f}{c['ratio_new_over_old']:>9.3f}  "
                f"{c['paired_ratio_new_over_old']['median']:.3f} [{c['paired_ratio_new_over_old']['min']:.3f}-"
                f"{c['paired_ratio_new_over_old']['max']:.3f}]".ljust(61)
                + f"{c['old']['first_call_s']:>9.2f} / {c['new']['first_call_s']:.2f}"
                + ("  SLOWER" if c["slower_than_threshold"] else "")
                for n, c in comp["programs"].items()
            ),
        )
    slower = [r["scene"] for r in summary["results"] if r["slower_than_threshold"]]
    if comp:
        slower += [f"compile {n}" for n, c in comp["programs"].items() if c["slower_than_threshold"]]
    differ = [
        r["scene"]
        for r in summary["results"]
        if not (r["same_result"]["same_arrays"] and r["same_result"]["max_abs_diff"] <= SAME_TOLERANCE)
    ]
    print(
        f"\nSlower than {THRESHOLD:.2f}x: {', '.join(slower) if slower else 'none'}. "
        f"Results differing by more than {SAME_TOLERANCE:g}: {', '.join(differ) if differ else 'none'}."
    )


def plot(summary: dict, path: Path) -> None:
    rows, comp = summary["results"], summary.get("compile")
    fig, (ax, bx) = harness.figure((3, 1), size=(12, 5.2))
    names = [r["scene"] for r in rows]
    y = np.arange(len(rows))[::-1]
    ratio = np.array([r["ratio_new_over_old"] for r in rows])
    lo = np.array([r["paired_ratio_new_over_old"]["min"] for r in rows])
    hi = np.array([r["paired_ratio_new_over_old"]["max"] for r in rows])
    colors = ["#d62728" if r["slower_than_threshold"] else "#1f77b4" for r in rows]
    ax.barh(y, ratio - 1.0, left=1.0, color=colors, alpha=0.7)
    ax.errorbar(
        ratio, y, xerr=[np.maximum(ratio - lo, 0), np.maximum(hi - ratio, 0)], fmt="none", ecolor="0.2", capsize=3
    )
    ax.axvline(1.0, color="0.3", lw=0.8)
    ax.axvline(THRESHOLD, color="#d62728", ls=":", label=f"limit {THRESHOLD:.2f}")
    ax.set_yticks(y, names)
    ax.set_xlabel("time per call, new / old (bar: ratio of medians; whisker: per-round range)")
    ax.legend(loc="lower right")
    if comp:
        progs = list(comp["programs"])
        x = np.arange(len(progs))
        for k, (e, c) in enumerate(zip(ENGINES, ("0.6", "#1f77b4"))):
            bx.bar(x + (k - 0.5) * 0.38, [comp["programs"][p][e]["compile_s"] for p in progs], 0.38, color=c, label=e)
        bx.set_xticks(x, progs)
        bx.set_ylabel("compile time, fresh process [s]")
        bx.legend()
    else:
        bx.set_axis_off()
    eng = summary["engines"]
    fig.suptitle(
        harness.plot_title(
            summary,
            f"Engine regression, old {(eng['old']['git_commit'] or '?')[:9]} vs "
            f"new {(eng['new']['git_commit'] or '?')[:9]}",
        ),
        fontsize=10,
    )
    fig.savefig(path, dpi=110)


# --------------------------------------------------------------------------------------------


def _add_arguments(parser) -> None:
    parser.add_argument(
        "--baseline",
        type=Path,
        default=None,
        help="checkout of the engine to compare against (e.g. made with git worktree add); "
        "default: this checkout (an A/A run, which measures the noise)",
    )
    parser.add_argument(
        "--scenes",
        default=None,
        help=f"comma-separated scenes to run (default: all; '{COMPILE}' is the compile-time scene): "
        + ", ".join((*SCENES, COMPILE)),
    )


def main(argv=None) -> dict:
    argv = list(sys.argv[1:] if argv is None else argv)
    if "--quick" not in argv and not any(a.startswith("--repeats") for a in argv):
        argv += ["--repeats", str(DEFAULT_REPEATS)]
    run = harness.Run(
        RESULTS_NAME,
        argv,
        add_arguments=_add_arguments,
        description="Time the same public-API calls on two engines (old: --baseline, new: this "
        "checkout), interleaved; flag any scene slower by more than 10 %.",
    )
    baseline = (run.args.baseline or REPO).resolve()
    if not (baseline / "clebsch_jax" / "__init__.py").is_file():
        raise SystemExit(f"--baseline: no clebsch_jax package in {run.args.baseline}")
    roots = {"old": baseline, "new": REPO}
    names = list(QUICK_SCENES if run.quick else SCENES) + [COMPILE]
    if run.args.scenes:
        names = [s.strip() for s in run.args.scenes.split(",") if s.strip()]
        unknown = [s for s in names if s not in SCENES and s != COMPILE]
        if unknown:
            raise SystemExit(f"--scenes: unknown {unknown}; choose from {', '.join((*SCENES, COMPILE))}")
    with run, tempfile.TemporaryDirectory(prefix="clebsch-jax-regression-") as tmp_name:
        tmp = Path(tmp_name)
        workers = {}
        try:
            for e in ENGINES:
                workers[e] = Worker(e, roots[e], run, tmp)
            rows = run.measure(
                [(s,) for s in names if s != COMPILE],
                [(s,) for s in names if s != COMPILE],
                lambda s: f"{s} ({SCENES[s][0]})",
                lambda s: measure_scene(s, workers, run, tmp),
            )
        finally:
            for w in workers.values():
                w.close()
        compile_row = None
        if COMPILE in names:
            with run.case("compile time, fresh workers"):
                compile_row = measure_compile(roots, run, tmp)
    engines = {e: workers[e].engine for e in ENGINES}
    summary = run.summary(
        config={
            "threshold_new_over_old": THRESHOLD,
            "same_result_tolerance": SAME_TOLERANCE,
            "baseline_is_this_checkout": baseline == REPO,
            "scenes": names,
            "sizes": {s: SCENES[s][2 if run.quick else 1] for s in names if s != COMPILE},
            "dt": {"rigid": DT_RIGID, "heavy_top": DT_TOP},
        },
        results=rows,
        engines=engines,
        compile=compile_row,
    )
    return run.finish(summary, print_report, plot)


if __name__ == "__main__":
    if WORKER_FLAG in sys.argv[1:]:
        worker_main(sys.argv[1:])
    else:
        main()
