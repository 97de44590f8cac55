r"""A scene run's report: the JSON summary (errors, failures, timings) and the plot."""

from __future__ import annotations

import json
import math
import os

import jax
import numpy as np

import clebsch_jax as cj

from ._scene_types import ENERGY, Scene, Setup

__all__ = ["summarise", "plot_data", "write_summary", "write_plot"]


def _finite_max(a) -> float | None:
    """The largest finite entry of `a`, None if there is none."""
    a = np.asarray(a, float)
    a = a[np.isfinite(a)]
    return float(np.max(a)) if a.size else None


def _finite_list(a) -> list:
    return [None if not np.isfinite(x) else float(x) for x in a]


def _failures(tally, dt: float) -> list:
    """One entry per failed member: its index, step, time, status code and the reason."""
    return [
        {
            "member": int(m),
            "step": int(tally.failed_step[m]),
            "t": float(tally.failed_step[m] * dt),
            "status": int(tally.status[m]),
            "reason": cj.Status.MESSAGES.get(int(tally.status[m]), f"status {int(tally.status[m])}"),
        }
        for m in np.flatnonzero(tally.status != cj.Status.SUCCESS)
    ]


def summarise(scene: Scene, setup: Setup, plan, tally, wall: float, first_s: float) -> dict:
    """`run_scene`'s summary (without the plot data) from the tally of its chunks."""
    facts, worst = tally.facts, tally.worst
    failures = _failures(tally, plan.dt)
    errors = {"energy_rel_max": _finite_max(worst["energy"])}
    errors.update({f"{inv.name}_max": _finite_max(worst[inv.name]) for inv in scene.invariants})
    if scene.reference is not None:
        errors["reference_max"] = _finite_max(tally.ref_worst)
    compiled_steps = (plan.n_chunks - 1) * plan.chunk
    return {
        "scene": {
            "name": scene.name,
            "description": scene.description,
            "model": scene.model,
            "options": dict(scene.options),
            "members": plan.batch,
            "seed": plan.seed,
            "initial": setup.members if plan.batch <= 64 else None,
        },
        "run": {
            "dt": plan.dt,
            "n_steps": plan.n_steps,
            "t_final": plan.n_steps * plan.dt,
            "order": facts["order"],
            "order_requested": plan.order,
            "method": facts["method"],
            "form": facts["form"],
            "scheme": facts["scheme"],
            "derivative_map": facts["derivative_map"],
            "chunks": plan.n_chunks,
            "steps_per_chunk": plan.chunk,
            "compiler_options": plan.compiler_options,
        },
        "errors": errors,
        "invariants": {
            inv.name: {
                "label": inv.label,
                "kind": inv.kind,
                "conserved_exactly": inv.roundoff,
                "max": _finite_max(worst[inv.name]),
                "per_member": _finite_list(worst[inv.name]),
            }
            for inv in tally.invariants
        },
        "reference": None
        if scene.reference is None
        else {
            "label": scene.reference_label,
            "max": _finite_max(tally.ref_worst),
            "per_member": _finite_list(tally.ref_worst),
        },
        "newton_iterations": {
            "mean": tally.iter_sum / tally.iter_count if tally.iter_count else None,
            "max": tally.iter_max,
            "per": "step (updates summed over the sub-steps of a composition)",
        },
        "failures": {"count": len(failures), "members": failures[:100]},
        "per_member": {"status": tally.status.tolist(), "failed_step": tally.failed_step.tolist()},
        "timing": {
            "wall_s": wall,
            "first_chunk_s": first_s,
            "steps_per_s_compiled": (compiled_steps / (wall - first_s) if compiled_steps and wall > first_s else None),
        },
        "versions": {"jax": jax.__version__, "numpy": np.__version__},
    }


def plot_data(setup: Setup, plan, tally) -> dict:
    """What `write_plot` draws: the plotted members' trajectories and their errors' envelopes,
    with their times."""
    stride, n_bins = tally.stride, tally.errors_binned["energy"].data.shape[1]
    return {
        "setup": setup,
        "t_traj": np.concatenate(tally.traj_nodes) * plan.dt,
        "trajectory": np.concatenate(tally.traj_pieces, axis=1),
        "t_err": np.minimum(np.arange(n_bins) * stride + stride - 1, plan.n_steps) * plan.dt,
        "errors": {inv.name: tally.errors_binned[inv.name].result() for inv in tally.invariants},
        "reference": None if tally.ref_binned is None else tally.ref_binned.result(),
    }


def write_summary(summary: dict, out_dir: str, files: list) -> str:
    """Write `summary.json` (without the private plot data) into `out_dir`; returns its path."""
    path = os.path.join(out_dir, "summary.json")
    public = {k: v for k, v in summary.items() if not k.startswith("_")} | {"files": files}
    with open(path, "w") as fh:
        json.dump(public, fh, indent=2)
        fh.write("\n")
    return path


def write_plot(scene: Scene, summary: dict, path: str) -> None:
    """One PNG: the plotted members' trajectories (left) and the invariants' errors against
    time (right, log scale; conserved quantities with machine epsilon)."""
    from matplotlib import colormaps
    from matplotlib.figure import Figure

    data = summary["_plot"]
    invariants = (ENERGY,) + scene.invariants
    panels = [(inv.label, inv, data["errors"][inv.name]) for inv in invariants]
    if data["reference"] is not None:
        panels.append((scene.reference_label, None, data["reference"]))
    n_members = data["trajectory"].shape[0]
    colors = [colormaps["tab10"](k % 10) for k in range(n_members)]
    run = summary["run"]
    fig = Figure(figsize=(12, 6.5), dpi=90)
    fig.suptitle(
        f"{scene.name}: {scene.description}\n{run['method']} ({run['form']} march), order "
        f"{run['order']}, dt = {run['dt']:g}, {run['n_steps']} steps, "
        f"{summary['scene']['members']} member(s), first {n_members} shown",
        fontsize=10,
    )
    grid = fig.add_gridspec(
        len(panels), 2, width_ratios=(1.1, 1.0), left=0.06, right=0.97, bottom=0.08, top=0.86, hspace=0.35, wspace=0.22
    )
    scene.plot(fig.add_subplot(grid[:, 0]), data["t_traj"], data["trajectory"], data["setup"], colors)
    eps = float(np.finfo(float).eps)
    floor = 1e-17
    axes = []
    for row, (label, inv, err) in enumerate(panels):
        ax = fig.add_subplot(grid[row, 1], sharex=axes[0] if axes else None)
        axes.append(ax)
        t = data["t_err"][: err.shape[1]]
        for y, col in zip(err, colors):
            ax.plot(t, np.maximum(y, floor), color=col, lw=0.7)
        ax.set_yscale("log")
        if inv is not None and inv.roundoff:
            ax.axhline(eps, color="k", lw=0.6, ls=":")
        kind = "" if inv is None else (" (rel. drift)" if inv.kind == "drift" else "")
        worst = np.nanmax(err) if np.any(np.isfinite(err)) else math.nan
        ax.set_title(f"{label}{kind}: max {worst:.2e}", fontsize=9, pad=2)
        ax.tick_params(labelsize=8)
        ax.grid(True, lw=0.3, alpha=0.5)
        if row < len(panels) - 1:
            ax.tick_params(labelbottom=False)
    axes[-1].set_xlabel("t")
    fig.savefig(path)
