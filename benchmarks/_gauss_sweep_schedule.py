r"""The schedule of a Gauss–Legendre step's fixed-point sweeps on the rigid-body ensemble of
`work_precision_ensembles.py` (64 bodies on R³, `models.rigid_body_vector`), `cj.sweep` on one
thread: CPU time per body and unit of simulated time, global error at T against heyoka's
extended-precision reference, the largest relative energy error, and sweeps per step. A
measurement kept for the record of `benchmarks/README.md` (the sweeps' schedule, issue 41), not
one of `clebsch-jax bench`'s scripts (no `--quick`, no JSON).

    python benchmarks/_gauss_sweep_schedule.py 16:1.0 16:1.0:untested=4:ahead=none
    T=1000 REPS=5 BACKEND=xla python benchmarks/_gauss_sweep_schedule.py 8:0.25

Each argument is one point, `ORDER:DT[:untested=U][:per_test=K][:ahead=A|none]`: a
`GaussLegendre(order=ORDER)` whose `FixedPoint` has those options (the others its defaults);
`untested=4:ahead=none` is the schedule before the sweep count was carried from step to step. The points
run interleaved, `REPS` times each (default 3; the best is reported), after a first call that
compiles; the reference is computed once per T and kept in the temporary directory. Compare
points only as ratios within one run. Needs heyoka (the `bench` extra).
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

import clebsch_jax as cj
import work_precision_ensembles as wpe

jax.config.update("jax_enable_x64", True)


def point(spec: str):
    """(label, stepper, dt) of one argument."""
    order, dt, *options = spec.split(":")
    options = dict(o.split("=") for o in options)
    ahead = options.pop("ahead", None)
    finder = {k: int(v) for k, v in options.items()}
    if ahead is not None:
        finder["tests_ahead"] = None if ahead == "none" else int(ahead)
    base = cj.GaussLegendre(order=int(order)).root_finder
    return spec, cj.GaussLegendre(order=int(order), root_finder=cj.FixedPoint(**{**vars(base), **finder})), float(dt)


def main(argv) -> None:
    T, reps, backend = (
        float(os.environ.get("T", 1000)),
        int(os.environ.get("REPS", 3)),
        os.environ.get("BACKEND", "native"),
    )
    scene = wpe.RigidEnsemble({**wpe.ENSEMBLES["rigid_body"], "T": T})
    cache = Path(tempfile.gettempdir()) / f"gauss_sweep_schedule_reference_T{T:g}.npy"
    if cache.exists():
        ref = np.load(cache)
    else:
        ref = wpe.heyoka_reference(wpe.heyoka_module(), scene, wpe.REF_TOL)
        np.save(cache, ref)

    def run(method, dt):  # the scene's documented sweep, warnings aside
        return wpe.ours_sweep(scene, {"model": "vector", "method": method}, dt, int(round(T / dt)), backend)[0]

    points = [point(a) for a in argv]
    for _, method, dt in points:
        run(method, dt)  # compile
    cpu = {label: [] for label, _, _ in points}
    results = {}
    for _ in range(reps):
        for label, method, dt in points:
            c0 = time.process_time()
            results[label] = run(method, dt)
            cpu[label].append(time.process_time() - c0)
    print(f"T = {T:g}, {scene.members} bodies, {backend}, threads=1; load {os.getloadavg()}")
    print(f"{'point':32} {'us/body/unit t':>14} {'global':>9} {'energy':>9} {'sweeps/step':>11}")
    for label, _, dt in points:
        r = results[label]
        glob = np.max(np.linalg.norm(np.asarray(r.final_momentum) - ref, axis=1))
        energy = np.max(np.asarray(r.energy_error) / np.abs(np.asarray(r.initial["energy"])))
        sweeps = np.mean(np.asarray(r.newton_iterations)) * dt / T
        print(f"{label:32} {min(cpu[label]) / scene.members / T * 1e6:14.3f} {glob:9.2e} {energy:9.2e} {sweeps:11.2f}")


if __name__ == "__main__":
    main(sys.argv[1:])
