"""`clebsch-jax run SCENE`: one built-in scene with `--dt`, `--steps`, `--order`, `--scheme`,
`--batch`, `--out`; a summary table on the terminal, `summary.json` and a PNG in the output
folder, a progress bar on stderr for long runs. `run_scene_into` (a scene's run and its files)
also serves `demo`."""

from __future__ import annotations

import argparse
import os
import sys
import textwrap
import time

from ._arguments import (
    GAUSS_ORDERS,
    LONG_RUN,
    MAX_BATCH,
    MAX_STEPS,
    ORDERS,
    PROG,
    SCHEMES,
    add_cache_flag,
    paragraphs,
    parse_batch,
    parse_chunk,
    parse_dt,
    parse_order,
    parse_scene,
    parse_seed,
    parse_steps,
)
from ._progress import ProgressBar, isatty
from ._setup import check_out_dir, fail, make_out_dir, require_matplotlib, use_compilation_cache
from ._tables import failure_text, run_table


def run_scene_into(
    scene, out_dir: str, *, dt=None, steps=None, order=None, batch=1, seed=0, chunk=None, progress=None, scheme=None
) -> dict:
    """`run_scene`, then write `<scene>.png` and `summary.json` into `out_dir` (which exists)."""
    from ._scene_report import write_plot, write_summary
    from ._scene_run import run_scene

    summary = run_scene(
        scene,
        dt=dt,
        n_steps=steps,
        order=order,
        batch=batch,
        seed=seed,
        chunk_steps=chunk,
        progress=progress,
        scheme=scheme,
    )
    tic = time.perf_counter()
    png = f"{scene.name}.png"
    write_plot(scene, summary, os.path.join(out_dir, png))
    summary["timing"]["plot_s"] = time.perf_counter() - tic
    write_summary(summary, out_dir, [png, "summary.json"])
    summary["files"] = [png, "summary.json"]
    return summary


def run(args) -> int:
    from ._scene_run import chunk_steps_for
    from ._scenes import SCENES

    prog = f"{PROG} run"
    scene = SCENES[args.scene]
    out_dir = args.out if args.out is not None else os.path.join("clebsch-jax-run", scene.name)
    code = check_out_dir(out_dir, prog) or require_matplotlib(prog) or make_out_dir(out_dir, prog)
    if code:
        return code
    if args.order is not None and args.order not in (GAUSS_ORDERS if args.scheme == "gauss" else ORDERS):
        return fail(
            f"--order {args.order} needs --scheme gauss (the compositions have orders {', '.join(map(str, ORDERS))})",
            code=2,
            prog=prog,
        )
    use_compilation_cache(args, prog)
    steps = scene.steps if args.steps is None else args.steps
    chunk = args.chunk or chunk_steps_for(args.batch, steps)
    show = (
        not args.quiet
        and -(-steps // chunk) > 1
        and (args.progress or isatty(sys.stderr) or args.batch * steps >= LONG_RUN)
    )
    bar = ProgressBar(f"{scene.name}") if show else None
    if not args.quiet:
        print(
            f"{prog}: integrating {scene.name} ({steps:,} steps x {args.batch} member"
            f"{'s' if args.batch > 1 else ''}); compiling first takes a few seconds...",
            flush=True,
        )
    try:
        summary = run_scene_into(
            scene,
            out_dir,
            dt=args.dt,
            steps=steps,
            order=args.order,
            batch=args.batch,
            seed=args.seed,
            chunk=chunk,
            progress=bar,
            scheme=args.scheme,
        )
    except OSError as err:
        return fail(f"could not write to {out_dir!r}: {err.strerror or err}", prog=prog)
    except ValueError as err:  # integrate refused the scheme for this scene's system, before compiling
        if args.scheme is None:
            raise
        return fail(f"--scheme {args.scheme} on {scene.name}: {str(err).splitlines()[0]}", code=2, prog=prog)
    finally:
        if bar is not None:
            bar.close()
    print(run_table(scene, summary, out_dir))
    if summary["failures"]["count"]:
        return fail(f"{failure_text(summary)}. Try a smaller --dt.", prog=prog)
    return 0


def add(subparsers) -> None:
    from ._scenes import SCENES

    scenes = "\n".join(
        f"  {s.name:<11} {s.description}\n"
        + textwrap.fill(s.details, 79, initial_indent=" " * 14, subsequent_indent=" " * 14)
        for s in SCENES.values()
    )
    p = subparsers.add_parser(
        "run",
        help="integrate one built-in scene (rigid-body, heavy-top, vortices, peakons, landmarks)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=paragraphs(
            "Integrate a built-in scene with the discrete Clebsch integrator (integrate(..., "
            "throw=False) under jax.vmap over --batch members), print a summary table (method, "
            "steps, wall time, energy error, the scene's momentum/Casimir errors, Newton "
            "iterations, failures) and write summary.json and SCENE.png (trajectories and "
            "invariant errors against time) into --out.",
            "scenes:\n" + scenes,
            "Member 0 is the scene's canonical initial condition; with --batch B the others are "
            "drawn at random (--seed). A failing member (e.g. too large a --dt) does not stop "
            "the others: it is reported with its step, and the exit code is 1. Long runs go in "
            "chunks of steps with a progress bar on stderr (on a terminal, or for runs of "
            f"{LONG_RUN:,} member-steps and more); runs of at most 20,000 member-steps are "
            "compiled with XLA's backend optimisation off (compilation dominates them).",
        ),
        epilog="examples: clebsch-jax run vortices --steps 20000 --order 4 --batch 8\n"
        "          clebsch-jax run vortices --scheme gauss --order 12 --dt 0.25 --steps 2000",
    )
    p.add_argument("scene", type=parse_scene, metavar="SCENE", help=f"one of: {', '.join(SCENES)}")
    p.add_argument(
        "--dt",
        type=parse_dt,
        default=None,
        metavar="DT",
        help="time step > 0 (default: the scene's, " + ", ".join(f"{s.name} {s.dt:g}" for s in SCENES.values()) + ")",
    )
    p.add_argument(
        "--steps",
        type=parse_steps,
        default=None,
        metavar="N",
        help=f"number of time steps, 1 to {MAX_STEPS:,} (default: the scene's, "
        + ", ".join(f"{s.name} {s.steps}" for s in SCENES.values())
        + ")",
    )
    p.add_argument(
        "--order",
        type=parse_order,
        default=None,
        metavar="K",
        help="order of the method: 2, 4, 6 or 8 (symmetric compositions of discrete "
        "Clebsch steps; default 2); with --scheme gauss an even order up to 16 "
        "(order/2 Gauss-Legendre stages)",
    )
    p.add_argument(
        "--scheme",
        choices=SCHEMES,
        default=None,
        metavar="S",
        help="discrete principle: left, right, midpoint, or gauss (the Gauss-Legendre "
        "discretisation of the Clebsch principle); default the scene's. A scheme the "
        "scene's system does not admit (left/right for the degenerate vortices) is "
        "refused before compiling",
    )
    p.add_argument(
        "--batch",
        type=parse_batch,
        default=1,
        metavar="B",
        help=f"number of members, 1 to {MAX_BATCH:,} (default 1), run under jax.vmap",
    )
    p.add_argument(
        "--seed", type=parse_seed, default=0, metavar="S", help="seed of the random members 1, ..., B-1 (default 0)"
    )
    p.add_argument(
        "--out", metavar="DIR", default=None, help="output folder, created if needed (default: ./clebsch-jax-run/SCENE)"
    )
    p.add_argument(
        "--chunk",
        type=parse_chunk,
        default=None,
        metavar="N",
        help="steps per compiled call (default: automatic, at most ~50 chunks; "
        "smaller chunks use less memory and update the progress bar more often)",
    )
    p.add_argument("--progress", action="store_true", help="draw the progress bar even when stderr is not a terminal")
    p.add_argument(
        "--quiet", action="store_true", help="no progress bar or status line (the summary table is still printed)"
    )
    add_cache_flag(p)
    p.set_defaults(handler=run)
