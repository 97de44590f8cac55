r"""The work-precision ceiling against heyoka (issue 41): machine instructions and arithmetic per
member and unit of simulated time of heyoka's Taylor steps and of our Gauss-Legendre sweeps, at
the points of ours that `work_precision_ensembles.py` found fastest at each of heyoka's errors.

    python benchmarks/work_precision_ceiling.py           # both scenes
    python benchmarks/work_precision_ceiling.py --quick   # smoke test: rigid bodies only, small

Written as `work_precision_ceiling.{json,png}`. Needs heyoka (the `bench` extra) and valgrind.

- **Scenes**: `work_precision_ensembles`' two (64 rigid bodies, T = 1e4; 16 clusters of 4
  vortices, T = 1e3), imported with their initial conditions and heyoka equations.
- **Points of ours**: for each heyoka tolerance 1e-8 ... 1e-14, our fastest point by CPU time at no
  larger global error and energy error no larger (or <= 1e-12) in the committed
  `results/work_precision_ensembles.json` (`--points`; the plans' points left out: their steps come
  from a pilot), else our most accurate point (marked).
- **The counted CPU**: valgrind presents an AVX2 CPU (no AVX-512), and LLVM compiles for it under
  callgrind. So that the timed code is the counted code, this process compiles our kernels for
  that CPU too (its LLVM name and features, asked of llvmlite under `valgrind --tool=none`; 4
  lanes) and runs heyoka in batches of 4 (which compiles for the host itself, 4 lanes wide).
- **Counts**: this script with `--count` under `valgrind --tool=callgrind`, 8 members; a call of
  `math.lcm` ends each region (`--dump-before=math_lcm`; all the process's instructions, Ir).
  heyoka: `propagate_until` from t = 0 to T1 and to T2 in batches of 4; ours: `cj.sweep(...,
  backend="native", threads=1)` of n1 and n2 steps; (count2 - count1) / (members (T2 - T1))
  leaves out compilation, setup and each call's fixed cost. heyoka's steps are a batch's.
- **Timing** (this process, natively): the whole ensembles, heyoka and ours (the counted
  kernels), by `work_precision_ensembles.time_calls`; ratios ours / heyoka.
- **Arithmetic from first principles** (flops per member). heyoka's step of order p, from its
  decomposition of the right-hand side: a product or quotient of series costs sum_{n<p} (2n+1) =
  p^2, a sum, difference or product with a constant p; each state variable p for x_{n+1} =
  f_n/(n+1), 2p for the Horner update, 4 for the step size's norms. Ours: the floating-point
  operations of the jaxpr of one member's sweep (`GaussLegendre._sweep`) and, per step, of the
  matrices formed once per step, the compensated update and the extrapolated guess.
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

import _timing as harness
from _arithmetic import sweep_flops, taylor_flops
import work_precision_ensembles as wpe
from clebsch_jax.native import kernel as K

TOLS = (1e-8, 1e-10, 1e-12, 1e-14)
LANES = 4  # float64 lanes of the AVX2 CPU valgrind presents: our kernels' and heyoka's batches
COUNT_MEMBERS = 8
OURS_STEPS = (100, 300)  # n1, n2 of the counted sweeps (the sweep's default chunk is 100 steps)
HEYOKA_T = {"rigid_body": (50.0, 150.0), "vortex_clusters": (10.0, 30.0)}  # T1, T2 counted
MARKER = "math_lcm"  # the C function of `math.lcm`, which ends a counted region
POINTS = harness.RESULTS_DIR / "work_precision_ensembles.json"
SCENES = {"rigid_body": wpe.RigidEnsemble, "vortex_clusters": wpe.ClusterEnsemble}
QUICK = {  # a smoke test: the bodies only, 8 of them, one point of ours given here (not read)
    "scenes": {"rigid_body": {"batch": 8, "T": 20.0}},
    "tols": (1e-10,),
    "points": {"rigid_body": [("vgauss8", 0.5)]},
    "heyoka_t": {"rigid_body": (5.0, 15.0)},
}
TARGET_PROBE = (
    "import json, llvmlite.binding as b; b.initialize_native_target(); "
    "print(json.dumps([b.get_host_cpu_name(), b.get_host_cpu_features().flatten()]))"
)


# --------------------------------------------------------------------------------------------
# The CPU valgrind presents, and our kernels compiled for it.


def valgrind_target() -> list:
    """[LLVM's CPU name, its features] as llvmlite sees them under valgrind."""
    out = subprocess.run(
        ["valgrind", "--tool=none", "-q", sys.executable, "-c", TARGET_PROBE],
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


class _Features:
    """What `llvmlite.binding.get_host_cpu_features()` returns, as far as the kernel module reads it."""

    def __init__(self, flat):
        self.flat = flat

    def flatten(self):
        return self.flat


def use_target(cpu: str, features: str) -> None:
    """Compile (and look up cached) kernels for `cpu` with `features` in this process."""
    import llvmlite.binding as llvm

    llvm.get_host_cpu_name = lambda: cpu
    llvm.get_host_cpu_features = lambda: _Features(features)
    K._LLVM.clear()


# --------------------------------------------------------------------------------------------
# The points: heyoka's errors and our fastest point at each.


def fastest_points(path: Path, scene: str, tols) -> list:
    """[(tol, method, dt, its errors and CPU time in that run, as accurate)]: for each heyoka tol,
    our fastest point by CPU time at heyoka's errors (`work_precision_ensembles._dominating`),
    else our most accurate point."""
    sc = next(s for s in json.loads(path.read_text())["results"] if s["scene"] == scene)
    valid = [p for p in sc["points"] if p["valid"]]
    ours = [p for p in valid if p["family"] == wpe.OURS and p["method"] != "plan"]
    rows = []
    for peer in (p for p in valid if p["family"] == wpe.HEYOKA and any(math.isclose(p["param"], t) for t in tols)):
        floor = wpe.HEYOKA_ENERGY_FLOOR

        def ok(e, pe=peer["energy_error"]):
            return e <= pe or e <= floor

        best = wpe._dominating(ours, peer, ok, "cpu_s")[1]
        o = best or min(ours, key=lambda o: o["global_error"])
        keep = ("global_error", "energy_error", "cpu_s", "wall_s")
        rows.append(
            {"tol": peer["param"], "method": o["method"], "dt": o["param"], "as_accurate": best is not None,
             "heyoka": {k: peer[k] for k in keep}, "ours": {k: o[k] for k in keep}}
        )  # fmt: skip
    return rows


def options_of(scene: str, method: str) -> dict:
    return next(dict(opts) for m, opts, _ in wpe.ENSEMBLES[scene]["ours"] if m == method)


def make_scene(name: str, cfg: dict, members: int | None = None):
    """The ensembles' scene `name` (its full batch, so the same initial conditions), its first
    `members` members if given."""
    scene = SCENES[name](dict(cfg, n_samples=1, chunk=wpe.CHUNK))
    if members is not None:
        scene.y0, scene.members = scene.y0[:members], members
    return scene


# --------------------------------------------------------------------------------------------
# The counts: this script under callgrind with --count.


def heyoka_propagate(hy, ta, y0, T) -> list:
    """Propagate each batch of `y0` (B, n) from t = 0 to T; the batch steps of each batch."""
    steps = []
    for g in range(0, len(y0), LANES):
        ta.set_time(0.0)
        ta.state[:] = y0[g : g + LANES].T
        ta.propagate_until(T)
        steps.append(max(int(r[3]) for r in ta.propagate_res))
    return steps


def counted_work(spec: dict, mark, hy=None) -> list:
    """The counted calls of every scene of `spec`, `mark(label)` after each region (heyoka's only
    with `hy`): what they found (heyoka's batch steps, our sweeps)."""
    found = []
    for name, job in spec["scenes"].items():
        scene = make_scene(name, job["cfg"], COUNT_MEMBERS)
        y0 = np.ascontiguousarray(scene.flat(scene.y0))
        T1, T2 = job["heyoka_t"]
        for tol in job["tols"] if hy is not None else ():
            ta = hy.taylor_adaptive_batch(scene.heyoka_system(hy), np.ascontiguousarray(y0[:LANES].T), tol=tol)
            heyoka_propagate(hy, ta, y0, T1)
            mark("setup")
            s1 = heyoka_propagate(hy, ta, y0, T1)
            mark(f"{name} heyoka {tol:g} T1")
            s2 = heyoka_propagate(hy, ta, y0, T2)
            mark(f"{name} heyoka {tol:g} T2")
            found.append({"scene": name, "who": "heyoka", "tol": tol, "order": ta.order, "steps": [s1, s2]})
        n1, n2 = job["ours_steps"]
        for method, dt in job["points"]:
            options = options_of(name, method)
            wpe.ours_sweep(scene, options, dt, n1, "native")
            mark("setup")
            r1, _ = wpe.ours_sweep(scene, options, dt, n1, "native")
            mark(f"{name} {method} {dt:g} n1")
            r2, _ = wpe.ours_sweep(scene, options, dt, n2, "native")
            mark(f"{name} {method} {dt:g} n2")
            sweeps = [float(np.sum(r.newton_iterations)) for r in (r1, r2)]
            found.append({"scene": name, "who": "ours", "method": method, "dt": dt, "sweeps": sweeps})
    return found


def count_child(spec_path: str, out_path: str) -> None:
    """The counted process: `counted_work` with regions ended by `math.lcm`; the regions' labels
    and what was found written to `out_path`."""
    spec = json.loads(Path(spec_path).read_text())
    use_target(*spec["target"])
    hy = wpe.heyoka_module()
    # heyoka's disk cache of compiled code is keyed without the CPU: the host's objects (AVX-512
    # on a wider host) would be loaded here, where valgrind runs AVX2 at most; a cache of its own
    hy.llvm_state.set_diskcache_path(str(Path(K.cache_dir()) / "heyoka-under-valgrind"))
    regions = []

    def mark(label):
        math.lcm(2, 3)  # the marker: callgrind dumps the region before it
        regions.append(label)

    found = counted_work(spec, mark, hy)
    Path(out_path).write_text(json.dumps({"regions": regions, "found": found}))


def run_counts(spec: dict, run) -> tuple[dict, list]:
    """Run `count_child` under valgrind, then callgrind: ({label: instructions}, what it found)."""
    with tempfile.TemporaryDirectory() as tmp:
        spec_path, out_path = Path(tmp) / "spec.json", Path(tmp) / "out.json"
        spec_path.write_text(json.dumps(spec))
        child = [sys.executable, str(Path(__file__).resolve()), "--count", str(spec_path), str(out_path)]
        # first without counting: heyoka compiles for the CPU valgrind presents (into its cache)
        for tool in (
            ["--tool=none"],
            ["--tool=callgrind", f"--dump-before={MARKER}", f"--callgrind-out-file={tmp}/cg"],
        ):
            with run.guard(f"valgrind {tool[0]}"):
                done = subprocess.run(["valgrind", *tool, "-q", *child], capture_output=True, text=True)
            if done.returncode:
                raise RuntimeError(f"the counted process failed ({done.returncode}):\n{done.stderr[-3000:]}")
        out = json.loads(out_path.read_text())
        totals = []
        for k in range(1, len(out["regions"]) + 1):
            text = (Path(tmp) / f"cg.{k}").read_text()
            totals.append(int(next(line for line in text.splitlines() if line.startswith("totals:")).split()[1]))
    return dict(zip(out["regions"], totals)), out["found"]


# --------------------------------------------------------------------------------------------
# One scene: timing, counts, first principles, the break-down.


def time_scene(run, hy, name, cfg, points, tols) -> dict:
    """The whole ensemble natively, heyoka (batches of 4) and ours: time, steps, sweeps."""
    scene = make_scene(name, cfg)
    ens = wpe.HeyokaEnsemble(hy, scene, np.array([0.0, scene.T]), batch_size=LANES)
    rows = {"heyoka": {}, "ours": {}}
    finals = {}
    with run.case(f"{name}: heyoka tol {list(tols)}, batches of {LANES}"):
        for tol in tols:
            ens.compile(tol)
            timing, res = wpe.time_calls(run, lambda t=tol: ens.run(t), f"heyoka {tol:g}", run.args.point_budget)
            ta = ens.integrators[tol]
            rows["heyoka"][tol] = {
                **timing, **taylor_flops(ta, len(ta.state)), "batch_steps_per_unit_time": res["steps"] / scene.T,
            }  # fmt: skip
            finals[tol] = res["ys"][-1]
    for method, dt in points:
        n = round(scene.T / dt)
        with run.case(f"{name}: ours {method} dt {dt:g} ({n} steps)"):
            options = options_of(name, method)
            with run.guard(f"warm-up {method}"):
                wpe.ours_sweep(scene, options, dt, min(n, wpe.CHUNK), "native")
            timing, (res, _) = wpe.time_calls(
                run,
                lambda o=options, d=dt: wpe.ours_sweep(scene, o, d, n, "native"),
                f"{method}",
                run.args.point_budget,
            )
            y = scene.flat(scene.sweep_final(res))
            rows["ours"][(method, dt)] = {
                **timing, "valid": bool(np.all(res.succeeded)), "sweeps_per_step": float(np.mean(res.newton_iterations)) / n,
                "distance_to_heyoka_tightest": float(np.max(np.abs(y - finals[min(tols)]))) / scene.scale,
                **({"flops": sweep_flops(scene, options, dt)} if options.get("scheme") == "gauss" else {}),
            }  # fmt: skip
    return rows


def breakdown(name, cfg, timed, counts, found, picks, n_steps) -> list:
    """The rows of a scene: heyoka against our fastest point at its error, counted and timed."""
    members, (T1, T2), rows = COUNT_MEMBERS, cfg["heyoka_t"], []
    (n1, n2) = n_steps
    hy_found = {f["tol"]: f for f in found if f["scene"] == name and f["who"] == "heyoka"}
    ours_found = {(f["method"], f["dt"]): f for f in found if f["scene"] == name and f["who"] == "ours"}
    for pick in picks:
        tol, key = pick["tol"], (pick["method"], pick["dt"])
        h, o = timed["heyoka"][tol], timed["ours"][key]
        hi = (counts[f"{name} heyoka {tol:g} T2"] - counts[f"{name} heyoka {tol:g} T1"]) / (members * (T2 - T1))
        s1, s2 = hy_found[tol]["steps"]
        hy_steps = (sum(s2) - sum(s1)) / (len(s1) * (T2 - T1))  # batch steps per unit time
        method, dt = key
        label = f"{name} {method} {dt:g}"
        per_step = (counts[f"{label} n2"] - counts[f"{label} n1"]) / (members * (n2 - n1))
        sw = ours_found[key]["sweeps"]
        sweeps = (sw[1] - sw[0]) / (members * (n2 - n1))
        oi = per_step / dt
        hy_flops = h["flops_per_step"] * hy_steps
        row = {
            "tol": tol, "point": f"{method} dt {dt:g}", "as_accurate": pick["as_accurate"], "errors": pick,
            "heyoka": {
                "order": h["order"], "series_ops": h["series_ops"], "linear_ops": h["linear_ops"],
                "steps_per_unit_time": hy_steps, "instructions_per_step": hi / hy_steps,
                "instructions_per_unit_time": hi, "flops_per_step": h["flops_per_step"], "flops_per_unit_time": hy_flops,
                "instructions_per_flop": hi / hy_flops, "wall_s": h["wall_s"], "cpu_s": h["cpu_s"],
            },
            "ours": {
                "dt": dt, "steps_per_unit_time": 1 / dt, "sweeps_per_step": sweeps, "instructions_per_step": per_step,
                "instructions_per_sweep": per_step / sweeps, "instructions_per_unit_time": oi,
                "sweeps_per_step_full_ensemble": o["sweeps_per_step"], "wall_s": o["wall_s"], "cpu_s": o["cpu_s"],
                "distance_to_heyoka_tightest": o["distance_to_heyoka_tightest"], "valid": o["valid"],
            },
            "instructions_ratio": oi / hi, "wall_ratio": o["wall_s"] / h["wall_s"], "cpu_ratio": o["cpu_s"] / h["cpu_s"],
            # to match heyoka's instructions per unit time at this step: the sweeps per step (at
            # this cost per sweep), or the instructions per sweep (at these sweeps per step)
            "sweeps_per_step_to_match": hi * dt / (per_step / sweeps),
            "instructions_per_sweep_to_match": hi * dt / sweeps,
        }  # fmt: skip
        if "flops" in o:
            f = o["flops"]
            of = (sweeps * f["sweep"] + f["per_step"]) / dt
            row["ours"].update(
                {"stages": f["stages"], "flops_per_sweep": f["sweep"], "flops_per_step_besides_sweeps": f["per_step"],
                 "flops_per_unit_time": of, "instructions_per_flop": oi / of}
            )  # fmt: skip
            row["flops_ratio"] = of / hy_flops
        rows.append(row)
    return rows


# --------------------------------------------------------------------------------------------
# Report and plot.


def print_report(summary) -> None:
    print(
        f"\nThe ceiling against heyoka ({'--quick: not a measurement' if summary['config']['quick'] else 'measured'}): "
        f"per member and unit of simulated time; instructions counted by callgrind on the CPU valgrind presents "
        f"({summary['config']['target_cpu']}), {LANES} lanes; times of the whole ensembles in this process."
    )
    for sc in summary["results"]:
        print(f"\n{sc['scene']}:")
        harness.print_table(
            f"{'tol':>6} {'ours':<16}|{'p':>3}{'steps':>6}{'instr':>8}{'flops':>8} |{'sweeps':>7}{'instr/sw':>9}"
            f"{'instr':>9}{'flops':>9} |{'instr':>6}{'flops':>6}{'wall':>6}{'cpu':>6} |{'sweeps':>7}{'/sweep':>8}",
            (
                f"{r['tol']:>6.0e} {r['point'] + ('' if r['as_accurate'] is not False else '*'):<16}|{r['heyoka']['order']:>3}"
                f"{r['heyoka']['steps_per_unit_time']:>6.2f}{r['heyoka']['instructions_per_unit_time']:>8.0f}"
                f"{r['heyoka']['flops_per_unit_time']:>8.0f} |{r['ours']['sweeps_per_step']:>7.2f}"
                f"{r['ours']['instructions_per_sweep']:>9.0f}{r['ours']['instructions_per_unit_time']:>9.0f}"
                f"{harness.fmt(r['ours'].get('flops_per_unit_time'), '.0f', 9)} |{r['instructions_ratio']:>6.2f}"
                f"{harness.fmt(r.get('flops_ratio'), '.2f', 6)}{r['wall_ratio']:>6.2f}{r['cpu_ratio']:>6.2f} |"
                f"{r['sweeps_per_step_to_match']:>7.2f}{r['instructions_per_sweep_to_match']:>8.0f}"
                for r in sc["rows"]
            ),
        )
    print("heyoka: order, batch steps, instructions, flops | ours: sweeps per step, instructions per sweep,")
    print("instructions, flops | ours / heyoka | to match heyoka: sweeps per step, or instructions per sweep.")
    print("* no point of ours as accurate (the most accurate stands in).")


def plot(summary, path: Path) -> None:
    scenes = summary["results"]
    fig, axes = harness.figure([1] * len(scenes), size=(5.5 * len(scenes), 4.6))
    for ax, sc in zip(np.atleast_1d(axes), scenes):
        x = np.arange(len(sc["rows"]))
        for k, (who, color) in enumerate((("heyoka", "C3"), ("ours", "C0"))):
            vals = [r[who]["instructions_per_unit_time"] for r in sc["rows"]]
            ax.bar(x + (k - 0.5) * 0.38, vals, 0.38, color=color, label=f"{who}: instructions")
            flops = [r[who].get("flops_per_unit_time") for r in sc["rows"]]
            ax.plot(x + (k - 0.5) * 0.38, [np.nan if f is None else f for f in flops], "k_", ms=14)
        for xi, r in zip(x, sc["rows"]):
            top = max(r[w]["instructions_per_unit_time"] for w in ("heyoka", "ours"))
            ax.annotate(
                f"{r['instructions_ratio']:.1f}x (wall {r['wall_ratio']:.1f}x)", (xi, top), ha="center", fontsize=7
            )
        ax.set_xticks(x, [f"{r['tol']:.0e}\n{r['point']}" for r in sc["rows"]], fontsize=7)
        ax.set_yscale("log")
        ax.set_ylabel("per member and unit of simulated time")
        ax.set_title(f"{sc['scene']} (heyoka tol; our point at its error)", fontsize=9)
        ax.plot([], [], "k_", ms=14, label="flops, first principles")
        ax.legend(fontsize=7)
    fig.suptitle(harness.plot_title(summary, "Instructions (callgrind) per member and unit time"), fontsize=9)
    fig.savefig(path, dpi=110)


# --------------------------------------------------------------------------------------------


def add_arguments(parser) -> None:
    parser.add_argument("--points", type=Path, default=POINTS, help="the ensembles' JSON to take our points from")
    parser.add_argument(
        "--point-budget", type=float, default=20.0, dest="point_budget", help="seconds of samples per timed point"
    )


def main(argv) -> dict:
    if argv[:1] == ["--count"]:
        return count_child(*argv[1:3])
    with harness.Run(
        "work_precision_ceiling",
        argv,
        description="Instructions and arithmetic per unit time, ours against heyoka (issue 41).",
        add_arguments=add_arguments,
    ) as run:
        hy = wpe.heyoka_module()
        if hy is None or shutil.which("valgrind") is None:
            raise SystemExit("work_precision_ceiling needs heyoka (pip install -e '.[bench]') and valgrind")
        with run.case("the CPU valgrind presents"):
            target = valgrind_target()
        use_target(*target)
        tols = QUICK["tols"] if run.quick else TOLS
        scenes = (
            QUICK["scenes"]
            if run.quick
            else {n: {"batch": wpe.ENSEMBLES[n]["batch"], "T": wpe.ENSEMBLES[n]["T"]} for n in SCENES}
        )
        n_steps = OURS_STEPS
        picks, timed, spec = {}, {}, {"target": target, "scenes": {}}
        for name, cfg in scenes.items():
            if run.quick:
                picks[name] = [
                    {"tol": t, "method": m, "dt": d, "as_accurate": None}
                    for t in tols
                    for m, d in QUICK["points"][name]
                ]
            else:
                picks[name] = fastest_points(run.args.points, name, tols)
            points = sorted({(p["method"], p["dt"]) for p in picks[name]})
            timed[name] = time_scene(run, hy, name, cfg, points, tols)
            horizons = (QUICK["heyoka_t"] if run.quick else HEYOKA_T)[name]
            spec["scenes"][name] = {
                "cfg": cfg,
                "tols": list(tols),
                "points": points,
                "heyoka_t": horizons,
                "ours_steps": n_steps,
            }
        with run.case(f"the counted sweeps natively ({COUNT_MEMBERS} members: their kernels compiled)"):
            counted_work(spec, lambda label: None)
        with run.case(f"valgrind: {COUNT_MEMBERS} members of {list(scenes)}"):
            counts, found = run_counts(spec, run)
        results = [
            {
                "scene": name,
                "rows": breakdown(name, spec["scenes"][name], timed[name], counts, found, picks[name], n_steps),
            }
            for name in scenes
        ]
    summary = run.summary(
        config={
            "tols": list(tols), "scenes": scenes, "points_from": None if run.quick else harness.display_path(run.args.points),
            "target_cpu": target[0], "lanes": LANES, "count_members": COUNT_MEMBERS, "ours_steps": list(n_steps),
            "heyoka_t": {n: spec["scenes"][n]["heyoka_t"] for n in scenes}, "marker": MARKER,
            "heyoka": hy.__version__, "point_budget_s": run.args.point_budget,
        },
        results=results,
        counts=counts,
    )  # fmt: skip
    return run.finish(summary, print_report, plot)


if __name__ == "__main__":
    main(sys.argv[1:])
