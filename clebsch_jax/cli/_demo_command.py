"""`clebsch-jax demo`: the scene of Figure 1 of the paper (rigid body, Example 30), which writes
two PNGs and `summary.json` and prints a table of the conserved quantities and timings; then
every built-in scene briefly, each into a subfolder, and one combined table. `--only NAME` runs
one of them."""

from __future__ import annotations

import argparse
import os

import clebsch_jax as cj

from ._arguments import PROG, add_cache_flag, parse_scene, parse_steps, scene_names
from ._run_command import run_scene_into
from ._setup import check_out_dir, fail, make_out_dir, require_matplotlib, use_compilation_cache
from ._tables import combined_table, demo_table, failure_text, figure1_row, scene_row

FIGURE1 = "figure-1"
"""`demo --only` name of the Figure 1 scene."""


def _demo_figure1(args, out_dir: str, prog: str):
    """Run the Figure 1 scene; returns (exit code or None, summary or None)."""
    from ._demo import MissingPlotDependency, figure1

    print(
        f"{PROG} demo: integrating the Figure 1 scene"
        f"{' (quick)' if args.quick else ''}; compiling first takes a few seconds...",
        flush=True,
    )
    try:
        summary = figure1(out_dir, quick=args.quick, n_steps=args.steps)
    except MissingPlotDependency as err:
        return fail(str(err), prog=prog), None
    except cj.IntegrationError as err:
        return fail(str(err), prog=prog), None
    except OSError as err:
        return fail(f"could not write to {out_dir!r}: {err.strerror or err}", prog=prog), None
    print(demo_table(summary, out_dir))
    return None, summary


def run(args) -> int:
    from ._scenes import SCENES

    prog = f"{PROG} demo"
    out_dir = args.out
    code = check_out_dir(out_dir, prog)
    if code:
        return code
    use_compilation_cache(args, prog)
    only = args.only
    rows = []
    if only in (None, FIGURE1):
        code, fig = _demo_figure1(args, out_dir, prog)
        if code:
            return code
        if only == FIGURE1:
            return 0
        rows.append(figure1_row(fig))
    code = require_matplotlib(prog) or make_out_dir(out_dir, prog)
    if code:
        return code
    scenes = [SCENES[only]] if only else list(SCENES.values())
    failed = []
    print(
        f"{prog}: the built-in scenes, briefly ({'each' if len(scenes) > 1 else 'it'} mostly compiles: "
        "XLA optimisation off)...",
        flush=True,
    )
    for scene in scenes:
        steps = args.steps if only and args.steps is not None else scene.quick_steps
        sub = os.path.join(out_dir, scene.name)
        code = check_out_dir(sub, prog) or make_out_dir(sub, prog)
        if code:
            return code
        print(f"  {scene.name}: {steps} steps x {scene.quick_batch} members...", flush=True)
        try:
            summary = run_scene_into(scene, sub, steps=steps, batch=scene.quick_batch)
        except OSError as err:
            return fail(f"could not write to {sub!r}: {err.strerror or err}", prog=prog)
        rows.append(scene_row(summary))
        if summary["failures"]["count"]:
            failed.append(f"{scene.name}: {failure_text(summary)}")
    print(f"Built-in scenes (files in {out_dir}{os.sep}SCENE{os.sep}; clebsch-jax run SCENE for longer runs):")
    print(combined_table(rows))
    if failed:
        return fail("; ".join(failed), prog=prog)
    return 0


def add(subparsers) -> None:
    from ._demo import MAX_DEFAULT_STEPS, QUICK_STEPS, TARGET_PERIODS
    from ._scenes import SCENES

    p = subparsers.add_parser(
        "demo",
        help="the paper's Figure 1 scene (rigid body), then every built-in scene briefly",
        description=(
            "Integrate a batch of free rigid-body orbits (inertia (0.5, 0.6, 1), dt = 0.1, "
            "Cayley derivative map: Example 30 / Figure 1 of Cotter & Holm) under jax.vmap, "
            "write figure1_orbits.png, figure1_invariants.png and summary.json into the "
            "output folder, and print the conservation errors and timings. The paper shows "
            f"{TARGET_PERIODS} periods; by default the run is capped at {MAX_DEFAULT_STEPS} steps, "
            "and the table says how many periods it covered and which --steps covers all of "
            "them. Then run every built-in scene (" + ", ".join(SCENES) + ") for a few hundred "
            "steps, each into a subfolder, and print one combined table (each scene's time is "
            "mostly compilation)."
        ),
    )
    p.add_argument(
        "--out",
        metavar="DIR",
        default="clebsch-jax-demo",
        help="output folder, created if needed (default: ./clebsch-jax-demo)",
    )
    p.add_argument(
        "--steps",
        metavar="N",
        type=parse_steps,
        default=None,
        help=f"number of time steps of the Figure 1 scene (default: {TARGET_PERIODS} periods "
        f"of the slowest orbit, capped at {MAX_DEFAULT_STEPS}; {QUICK_STEPS} with --quick), "
        "or of the --only scene",
    )
    p.add_argument(
        "--quick",
        action="store_true",
        help="fewer orbits and steps in the Figure 1 scene: a smoke test (a few seconds plus compilation)",
    )
    p.add_argument(
        "--only",
        metavar="NAME",
        default=None,
        type=_demo_name,
        help=f"run only one scene: {FIGURE1} (the Figure 1 scene) or one of {', '.join(SCENES)}",
    )
    add_cache_flag(p)
    p.set_defaults(handler=run)


def _demo_name(text: str) -> str:
    if text.strip().lower().replace("_", "-") in (FIGURE1, "figure1"):
        return FIGURE1
    try:
        return parse_scene(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(
            f"unknown scene {text!r}; known: {FIGURE1}, {', '.join(scene_names())}"
        ) from None
