"""The terminal tables of `run` and `demo`, from the summaries of their scenes: one scene's
table, the Figure 1 scene's, and the combined table of `demo` (a row per scene)."""

from __future__ import annotations


def _fmt(x, spec: str = ".2e") -> str:
    return "n/a" if x is None else format(x, spec)


def failure_text(summary: dict) -> str:
    """'none', or how many members failed, the first one's step, time and reason, the others' steps."""
    fails = summary["failures"]
    if not fails["count"]:
        return "none"
    first, others = fails["members"][0], fails["members"][1:6]
    text = (
        f"{fails['count']} of {summary['scene']['members']} members failed: member {first['member']} at "
        f"step {first['step']} (t = {first['t']:.4g}): {first['reason']}"
    )
    if others:
        text += "; also " + ", ".join(f"member {f['member']} (step {f['step']})" for f in others)
        if fails["count"] > 1 + len(others):
            text += f" and {fails['count'] - 1 - len(others)} more"
    return text


def run_table(scene, summary: dict, out_dir: str) -> str:
    """The terminal table of one `run`."""
    run, inv, newton, timing = summary["run"], summary["invariants"], summary["newton_iterations"], summary["timing"]
    members = summary["scene"]["members"]
    rows = [
        ("method", f"{run['method']} ({run['form']} march, order {run['order']}, {run['derivative_map']})"),
        (
            "steps",
            f"{run['n_steps']:,} x {members} member{'s' if members > 1 else ''}, dt = {run['dt']:g}, "
            f"t = 0 to {run['t_final']:g} ({run['chunks']} chunk{'s' if run['chunks'] > 1 else ''} "
            f"of {run['steps_per_chunk']:,})",
        ),
        ("wall time", f"{timing['wall_s']:.2f} s (compile + first chunk {timing['first_chunk_s']:.2f} s)"),
        ("energy error (max rel.)", _fmt(summary["errors"]["energy_rel_max"])),
    ]
    for name, entry in inv.items():
        if name == "energy":
            continue
        what = "max rel. drift" if entry["kind"] == "drift" else "max"
        rows.append((f"{entry['label']} ({what})", _fmt(entry["max"])))
    if summary["reference"] is not None:
        rows.append((f"{summary['reference']['label']} (max)", _fmt(summary["reference"]["max"])))
    rows += [
        ("Newton iterations/step", f"{_fmt(newton['mean'], '.2f')} mean, {newton['max']} max"),
        ("failures", failure_text(summary)),
    ]
    width = max(len(k) for k, _ in rows)
    lines = [f"{scene.name}: {scene.description}"]
    lines += [f"  {k:<{width}}  {v}" for k, v in rows]
    lines.append(f"wrote {', '.join(summary['files'])} to {out_dir}")
    return "\n".join(lines)


def _short_invariants(summary: dict) -> str:
    parts = [f"{e['label']} {_fmt(e['max'], '.1e')}" for k, e in summary["invariants"].items() if k != "energy"]
    if summary.get("reference"):
        parts.append(f"{summary['reference']['label']} {_fmt(summary['reference']['max'], '.1e')}")
    return "; ".join(parts)


def combined_table(rows: list) -> str:
    """Rows of (scene, method, steps, wall, energy, invariants, newton, failures) as columns."""
    header = (
        "scene",
        "method",
        "steps x members",
        "wall",
        "energy err.",
        "Newton it./step",
        "failures",
        "invariants (max rel. drift / max error)",
    )
    table = [header] + [tuple(r) for r in rows]
    widths = [max(len(r[i]) for r in table) for i in range(len(header) - 1)]
    fmt = lambda r: "  ".join(f"{c:<{w}}" for c, w in zip(r, widths)) + "  " + r[-1]
    return "\n".join(["  " + fmt(header)] + ["  " + fmt(r) for r in table[1:]])


def scene_row(summary: dict) -> tuple:
    run, newton = summary["run"], summary["newton_iterations"]
    fails = summary["failures"]["count"]
    return (
        summary["scene"]["name"],
        run["method"],
        f"{run['n_steps']} x {summary['scene']['members']}",
        f"{summary['timing']['wall_s']:.1f} s",
        _fmt(summary["errors"]["energy_rel_max"]),
        f"{_fmt(newton['mean'], '.1f')} / {newton['max']}",
        "0"
        if not fails
        else f"{fails} (member {summary['failures']['members'][0]['member']} "
        f"at step {summary['failures']['members'][0]['step']})",
        _short_invariants(summary),
    )


def figure1_row(summary: dict) -> tuple:
    err, newton, scene = summary["errors"], summary["newton_iterations"], summary["scene"]
    return (
        "figure-1",
        f"CAY, Example 30 ({scene['march']} march)",
        f"{scene['n_steps']} x {scene['n_orbits']}",
        f"{summary['timing']['total_s']:.1f} s",
        _fmt(err["energy_rel_max"]),
        f"{newton['mean']:.1f} / {newton['max']}",
        "0",
        f"Casimir |m|^2 {err['casimir_rel_max']:.1e}; spatial ang. momentum "
        f"{err['spatial_momentum_drift_rel_max']:.1e}; |Q^T Q - I| {err['orthogonality_max']:.1e}",
    )


def _fmt_time(seconds: float) -> str:
    return f"{seconds:.2f} s"


def demo_table(summary: dict, out_dir: str) -> str:
    """The terminal table of `figure1`'s summary."""
    scene, err, timing = summary["scene"], summary["errors"], summary["timing"]
    newton = summary["newton_iterations"]
    cov = summary["periods_covered"]
    inertia = ", ".join(f"{x:g}" for x in scene["inertia"])
    unoptimised = " (XLA optimisation off for --quick)" if scene.get("compiler_options") else ""
    rows = [
        ("orbits", f"{scene['n_orbits']} on |m| = 1 (vmapped)"),
        ("march", f"{scene['march']} (Solution.form)"),
        ("time steps", f"{scene['n_steps']} (t = 0 to {scene['t_final']:g})"),
        ("periods covered", f"{cov['min']:.3g} (slowest orbit) to {cov['max']:.3g} (fastest)"),
        ("energy error (max rel.)", f"{err['energy_rel_max']:.2e}"),
        ("Casimir |m|^2 error (max rel.)", f"{err['casimir_rel_max']:.2e}"),
        ("spatial momentum drift (max rel.)", f"{err['spatial_momentum_drift_rel_max']:.2e}"),
        ("orthogonality error (max)", f"{err['orthogonality_max']:.2e}"),
        ("Newton iterations/step", f"{newton['mean']:.2f} mean, {newton['max']} max"),
        (
            "steps/s (compiled)",
            f"{timing['steps_per_s']:,.0f} x {scene['n_orbits']} orbits "
            f"= {timing['orbit_steps_per_s']:,.0f} orbit-steps/s{unoptimised}",
        ),
        ("compile + first call", _fmt_time(timing["compile_and_first_call_s"])),
        ("demo total (after imports)", _fmt_time(timing["total_s"])),
    ]
    width = max(len(k) for k, _ in rows)
    lines = [
        f"Figure 1 scene: rigid body, I = ({inertia}), dt = {scene['dt']:g}, {scene['derivative_map']} derivative map"
    ]
    lines += [f"  {k:<{width}}  {v}" for k, v in rows]
    if not scene["quick"] and cov["min"] < summary["target_periods"] - 0.5:
        lines.append(
            f"  (the paper shows {summary['target_periods']} periods: "
            f"--steps {summary['steps_for_target_periods']} covers them for the slowest orbit)"
        )
    lines.append(f"wrote {', '.join(summary['files'])} to {out_dir}")
    return "\n".join(lines)
