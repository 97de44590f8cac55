r"""What the checks of issue 22 cost: the per-step energy check and the per-member input check.

Run from the repository root:

    python benchmarks/check_cost.py            # default run
    python benchmarks/check_cost.py --quick    # smoke test, tiny sizes (not a measurement)

Timed with the shared harness (`_timing.py`: the first call compiles and is timed alone, then
the median of `--repeats` samples, the methods of a case sampled in turn, every call ending in
`jax.block_until_ready`), in one process and one run:

- **energy check** (`integrate(..., check_energy=True)`, the default, against
  `check_energy=False`): one evaluation of the Lagrangian per node and a running maximum over
  the run. Cases: the free rigid body (reduced CAY march) as one plain call, and as a
  `jax.jit(jax.vmap(...))` batch of B bodies; a user system on the plane with a potential
  (the midpoint principle, full march) as one plain call.
  Also a `cj.sweep` of B rigid bodies (reduced CAY, default chunks), whose check is made by
  the sweep over the whole run, chunk by chunk.
- **input check under tracing** (`clebsch_jax.march.scan.march(..., check_inputs=True)`
  against `False`, the engine's own entry below `integrate`, which always checks under
  jit/vmap): dt, Q0, ξ0 and the model's parameters finite, Q0 a rotation and l and the
  velocity map finite at the start, once per member. Case: the jitted vmapped rigid-body
  batch above.

Reported per case: the time per call of each method and their ratio (checked / unchecked).
Outputs (in `--out`, default `benchmarks/results`): `check_cost.json` and `check_cost.png`.
Nothing here asserts a time.
"""

from __future__ import annotations

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax.tree_util import Partial

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _timing as harness  # noqa: E402

import clebsch_jax as cj  # noqa: E402
from clebsch_jax.march.scan import march  # noqa: E402
from clebsch_jax.steppers.choose import choose_method  # noqa: E402

RESULTS_NAME = "check_cost"
DT = 0.01
INERTIA = (2.0, 1.0, 2 / 3)
DEFAULT_CASES = (
    ("rigid_body", 1, 4000),
    ("rigid_body", 256, 1000),
    ("plane_potential", 1, 4000),
    ("rigid_sweep", 1000, 200),
)
QUICK_CASES = (("rigid_body", 1, 50), ("rigid_body", 4, 50), ("plane_potential", 1, 50), ("rigid_sweep", 4, 20))


def _plane_lagrangian(k, xi, Q):
    return 0.5 * xi @ xi - 0.5 * k * Q @ Q - 0.1 * Q[0] ** 4


def _translation(xi, Q):
    return xi + 0 * Q


def _setup(model: str, batch: int):
    rng = np.random.default_rng(0)
    if model in ("rigid_body", "rigid_sweep"):
        system = cj.models.rigid_body(jnp.array(INERTIA))
        Q0 = jnp.eye(3)
        xi0 = jnp.asarray(rng.normal(size=(batch, 3)) if batch > 1 else [1.3, 0.8, -0.4])
    else:
        system = cj.ClebschSystem(
            lagrangian=Partial(_plane_lagrangian, jnp.asarray(1.0)),
            velocity_map=_translation,
            derivative_map=cj.forward_difference,
        )
        Q0, xi0 = jnp.array([1.0, 0.0]), jnp.array([0.0, 1.0])
    return system, Q0, xi0


def _calls(model: str, batch: int, n_steps: int) -> dict:
    system, Q0, xi0 = _setup(model, batch)

    def plain(check_energy):
        return lambda: cj.integrate(system, Q0, xi0, dt=DT, n_steps=n_steps, check_energy=check_energy)

    def batched(check_energy):
        run = jax.jit(
            jax.vmap(
                lambda x: cj.integrate(system, Q0, x, dt=DT, n_steps=n_steps, throw=False, check_energy=check_energy)
            )
        )
        return lambda: run(xi0)

    def inputs(check_inputs):
        stepper = choose_method(system, Q0, xi0[0]).prepare(system, Q0, xi0[0])
        run = jax.jit(
            jax.vmap(
                lambda x: march(
                    stepper,
                    system,
                    Q0,
                    x,
                    None,
                    jnp.asarray(DT),
                    jnp.asarray(0.0),
                    n_steps,
                    check_energy=False,
                    check_inputs=check_inputs,
                )
            )
        )
        return lambda: run(xi0)

    def swept(check_energy):
        Qs = jnp.broadcast_to(Q0, (batch,) + Q0.shape)
        return lambda: cj.sweep(
            cj.models.rigid_body,
            jnp.array(INERTIA)[None],
            Qs,
            xi0,
            dt=DT,
            n_steps=n_steps,
            grid=True,
            check_energy=check_energy,
        )

    if model == "rigid_sweep":
        return {"energy_check": swept(True), "no_energy_check": swept(False)}
    if batch == 1:
        return {"energy_check": plain(True), "no_energy_check": plain(False)}
    return {
        "energy_check": batched(True),
        "no_energy_check": batched(False),
        "input_check": inputs(True),
        "no_input_check": inputs(False),
    }


def run_case(model, batch, n_steps, run: harness.Run) -> dict:
    calls = _calls(model, batch, n_steps)
    blocked = {name: (lambda f=f: jax.block_until_ready(f())) for name, f in calls.items()}
    timings, outs = run.time(blocked, what=f"{model} B={batch}")
    for name, sol in outs.items():
        status = sol.status if isinstance(sol, cj.SweepResult) else sol.result
        if not np.all(np.asarray(status) == cj.Status.SUCCESS):
            raise RuntimeError(f"{model} B={batch}: {name} did not succeed")
    seconds = {name: t["per_call_s"] for name, t in timings.items()}
    ratios = {"energy_check_over_none": seconds["energy_check"] / seconds["no_energy_check"]}
    if "input_check" in seconds:
        ratios["input_check_over_none"] = seconds["input_check"] / seconds["no_input_check"]
    return {
        "case": model,
        "batch": batch,
        "n_steps": n_steps,
        "timings": timings,
        "seconds_per_call": seconds,
        "ratios": ratios,
    }


def print_report(summary: dict) -> None:
    harness.print_header(
        summary,
        "What the checks cost (seconds per call)",
        "energy_check: integrate(..., check_energy=True), the default; input_check: the "
        "per-member input check under jit/vmap.",
    )
    head = f"{'case':<16}{'B':>5}{'steps':>7}{'energy on':>12}{'off':>11}{'ratio':>8}{'inputs on':>12}{'off':>11}{'ratio':>8}"
    lines = []
    for r in summary["results"]:
        s, q = r["seconds_per_call"], r["ratios"]
        lines.append(
            f"{r['case']:<16}{r['batch']:>5}{r['n_steps']:>7}"
            f"{s['energy_check']:>12.4g}{s['no_energy_check']:>11.4g}{q['energy_check_over_none']:>8.3f}"
            f"{harness.fmt(s.get('input_check'), '.4g', 12)}{harness.fmt(s.get('no_input_check'), '.4g', 11)}"
            f"{harness.fmt(q.get('input_check_over_none'), '.3f', 8)}"
        )
    harness.print_table(head, lines)


def plot(summary: dict, path: Path) -> None:
    fig, ax = harness.figure([1], size=(7, 4))
    rows = summary["results"]
    labels = [f"{r['case']}\nB={r['batch']}, {r['n_steps']} steps" for r in rows]
    x = np.arange(len(rows))
    ax.bar(x - 0.2, [r["ratios"]["energy_check_over_none"] for r in rows], 0.4, label="energy check")
    ax.bar(x + 0.2, [r["ratios"].get("input_check_over_none", np.nan) for r in rows], 0.4, label="input check")
    ax.axhline(1.0, color="0.3", lw=0.8)
    ax.set_xticks(x, labels, fontsize=8)
    ax.set_ylabel("time with the check / without")
    ax.legend(fontsize=8)
    ax.set_title(harness.plot_title(summary, "What the checks cost"), fontsize=9)
    fig.savefig(path, dpi=120)


def _describe(model, batch, n_steps) -> str:
    return f"{model} B={batch} n_steps={n_steps}"


def main(argv=None) -> dict:
    """Run the benchmark: the cases, the report, the JSON and the PNG; returns the summary."""
    with harness.Run(RESULTS_NAME, argv, description="What the checks of issue 22 cost (see module docstring).") as run:
        results = run.measure(DEFAULT_CASES, QUICK_CASES, _describe, lambda *case: run_case(*case, run))
    summary = run.summary(
        config={
            "dt": DT,
            "inertia": INERTIA,
            "cases": [{"case": c, "batch": b, "n_steps": n} for c, b, n in run.cases],
        },
        results=results,
    )
    return run.finish(summary, print_report, plot)


if __name__ == "__main__":
    main()
