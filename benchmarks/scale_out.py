"""Scale-out on one machine (issue "Nothing lost, nothing silently wrong", scale-out): the same
stored sweep on one pinned Dask worker and on two.

Run from the repository root (needs the extra `pip install -e ".[sweep]"` and Linux's `taskset`):

    python benchmarks/scale_out.py --repeats 3   # default size (about 40 s of work on one core)
    python benchmarks/scale_out.py --quick    # smoke run, tiny sizes (not a measurement)

A real deployment from Dask's own command line on loopback, driven by the command line a user
types:

- `dask scheduler` on 127.0.0.1, and `dask worker ADDRESS --nthreads 1` processes, each pinned to
  one core with `taskset -c K` and started with one XLA and one BLAS thread
  (`clebsch_jax.batching.distributed.worker_environment`, the scale-out recipe of the sweeps
  how-to);
- two such clusters side by side, one worker (core 0) and two workers (cores 0 and 1), idle but
  for the sweep sent to them;
- `clebsch-jax sweep CONFIG.toml --scheduler ADDRESS --store NEW.zarr --quiet` timed by wall
  clock from the command's start to its exit, into a fresh store each time.

Rigid bodies (`rigid_body`, a grid of inertias times random body velocities, the reduced march
with default options). Each cluster first runs the sweep once with one chunk of steps (its
workers compile their programs); then `--repeats` rounds each time the whole sweep on the one-
and the two-worker cluster, in turn (the first rotating), so that a change of load hits both.
Reported: the time per sweep (median), the scaling = one-worker time / two-worker time paired
per round (target of the issue: >= 1.8), and whether every store's table is identical to the
first one's, bit for bit. Nothing is asserted. Outputs: `scale_out.json` and `scale_out.png`
in `--out` (default `benchmarks/results`).
"""

from __future__ import annotations

import os
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _timing as harness  # noqa: E402

import clebsch_jax as cj  # noqa: E402
from clebsch_jax.batching.distributed import worker_environment  # noqa: E402

RESULTS_NAME = "scale_out"
TARGET_SCALING = 1.8
WORKER_ENV = worker_environment({})  # what the workers are started with (besides the environment)
# (inertias per axis, velocities, steps, batch_size, chunk_steps): 16·16·256 = 65 536 bodies,
# about 40 s of one core's work, so that the command's own start (Python, JAX, the client) is
# a small part of the time.
DEFAULT_CASE = (16, 256, 8000, 4096, 1000)
QUICK_CASE = (2, 8, 20, 8, 10)
CONFIG = """\
model = "rigid_body"
dt = 0.05
n_steps = {steps}
grid = true
batch_size = {batch}
chunk_steps = {chunk}
[params]
linspace = [[0.5, 1.5, {axis}], [0.5, 1.5, {axis}], [1, 1, 1]]
[initial]
Q0 = {{identity = 3}}
xi0 = {{normal = [{velocities}, 3], seed = 0}}
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _dask() -> list:
    exe = shutil.which("dask")
    return [exe] if exe else [sys.executable, "-m", "dask"]


class Cluster:
    """A `dask scheduler` and `n` pinned single-threaded `dask worker`s on loopback."""

    def __init__(self, n: int, scratch: Path, env: dict):
        self.n, self.port = n, _free_port()
        self.address = f"tcp://127.0.0.1:{self.port}"
        self.log = open(scratch / f"cluster-{n}.log", "w")
        common = dict(stdout=self.log, stderr=subprocess.STDOUT, env=env)
        self.procs = [
            subprocess.Popen(
                [*_dask(), "scheduler", "--host", "127.0.0.1", "--port", str(self.port), "--no-dashboard"], **common
            )
        ]
        self._wait_for_port()
        worker = [*_dask(), "worker", self.address, "--nthreads", "1", "--nworkers", "1", "--no-dashboard"]
        for core in range(n):
            self.procs.append(
                subprocess.Popen(
                    ["taskset", "-c", str(core), *worker, "--memory-limit", "0", "--name", f"core{core}"],
                    **common,
                )
            )
        import distributed

        with distributed.Client(self.address, timeout=60) as client:
            client.wait_for_workers(n, timeout=120)

    def _wait_for_port(self, timeout: float = 60.0) -> None:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            with socket.socket() as s:
                if s.connect_ex(("127.0.0.1", self.port)) == 0:
                    return
            time.sleep(0.1)
        raise RuntimeError(f"the Dask scheduler did not open port {self.port}; see {self.log.name}")

    def close(self) -> None:
        for p in reversed(self.procs):
            p.terminate()
        for p in self.procs:
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
        self.log.close()


def sweep_command(config: Path, cluster: Cluster, store: Path, env: dict) -> float:
    """Wall time of `clebsch-jax sweep CONFIG --scheduler ADDRESS --store STORE --quiet`."""
    argv = [sys.executable, "-m", "clebsch_jax", "sweep", str(config), "--scheduler", cluster.address]
    tic = time.perf_counter()
    done = subprocess.run([*argv, "--store", str(store), "--quiet"], env=env, capture_output=True, text=True)
    wall = time.perf_counter() - tic
    if done.returncode != 0:
        raise RuntimeError(f"the sweep command failed ({done.returncode}):\n{done.stdout}\n{done.stderr}")
    return wall


def _same_table(a: Path, b: Path) -> bool:
    x, y = cj.open_sweep(str(a)), cj.open_sweep(str(b))
    leaves_x, leaves_y = jax.tree_util.tree_leaves(x), jax.tree_util.tree_leaves(y)
    return len(leaves_x) == len(leaves_y) and all(
        np.array_equal(np.asarray(u), np.asarray(v), equal_nan=True) for u, v in zip(leaves_x, leaves_y)
    )


def run_case(axis, velocities, steps, batch, chunk, run: harness.Run, scratch: Path) -> dict:
    members = axis * axis * velocities
    env = {**worker_environment(), "CLEBSCH_JAX_NATIVE_CACHE": str(scratch / "native-cache")}
    config, warm = scratch / "sweep.toml", scratch / "warm.toml"
    text = dict(axis=axis, velocities=velocities, batch=batch, chunk=chunk)
    config.write_text(CONFIG.format(steps=steps, **text))
    warm.write_text(CONFIG.format(steps=chunk, **text))
    clusters = {}
    try:
        for n in (1, 2):
            clusters[n] = Cluster(n, scratch, env)
        count = iter(range(10**6))
        stores: list[Path] = []

        def store() -> Path:
            stores.append(scratch / f"store-{next(count)}.zarr")
            return stores[-1]

        first = {n: sweep_command(warm, clusters[n], store(), env) for n in clusters}  # workers compile
        stores.clear()
        samples = {1: [], 2: []}
        for r in range(run.repeats):
            order = (1, 2) if r % 2 == 0 else (2, 1)
            for n in order:
                with run.guard(f"{n} worker(s), round {r}"):
                    samples[n].append(sweep_command(config, clusters[n], store(), env))
        identical = all(_same_table(stores[0], s) for s in stores[1:])
    finally:
        for c in clusters.values():
            c.close()
    row = {"members": members, "n_steps": steps, "batch_size": batch, "chunk_steps": chunk}
    row["n_batches"] = -(-members // batch)
    for n in (1, 2):
        t = statistics.median(samples[n])
        row[f"workers_{n}"] = {
            "samples_s": samples[n],
            "per_sweep_s": t,
            "member_steps_per_second": members * steps / t,
            "warm_up_s": first[n],
        }
    row["scaling"] = harness.paired_ratios(samples[1], samples[2])
    row["stores_identical"] = bool(identical)
    return row


def print_report(summary: dict) -> None:
    r = summary["results"][0]
    harness.print_header(
        summary,
        "A stored rigid-body sweep from `clebsch-jax sweep --scheduler` on 1 and on 2 pinned Dask workers",
        "workers: `taskset -c K dask worker ADDRESS --nthreads 1`, one XLA and BLAS thread each; "
        "wall time of the whole command",
    )
    print(f"\n{r['members']} members x {r['n_steps']} steps, {r['n_batches']} batches of {r['batch_size']}:")
    harness.print_table(
        f"{'workers':>8}{'time per sweep [s]':>20}{'member-steps/s':>18}{'warm-up [s]':>13}",
        (
            f"{n:>8}{r[f'workers_{n}']['per_sweep_s']:>20.2f}{r[f'workers_{n}']['member_steps_per_second']:>18.3e}"
            f"{r[f'workers_{n}']['warm_up_s']:>13.2f}"
            for n in (1, 2)
        ),
    )
    s = r["scaling"]
    print(
        f"\nScaling, one worker / two (paired per round): {s['median']:.3f} [{s['min']:.3f}, {s['max']:.3f}] "
        f"(target >= {TARGET_SCALING}: {'met' if s['median'] >= TARGET_SCALING else 'not met'}); "
        f"stores identical bit for bit: {r['stores_identical']}"
    )


def plot(summary: dict, path: Path) -> None:
    r = summary["results"][0]
    fig, (ax, ax_r) = harness.figure((2, 1))
    ax.bar([0, 1], [r["workers_1"]["per_sweep_s"], r["workers_2"]["per_sweep_s"]], color=["C0", "C2"])
    ax.set_xticks([0, 1], ["1 pinned worker", "2 pinned workers"])
    ax.set_ylabel("wall time per sweep [s]")
    ax.set_title(harness.plot_title(summary, f"{r['members']} rigid bodies x {r['n_steps']} steps"), fontsize=9)
    ax.grid(True, axis="y", alpha=0.3)
    s = r["scaling"]
    ax_r.bar([0], [s["median"]], yerr=[[s["median"] - s["min"]], [s["max"] - s["median"]]], color="C2", capsize=4)
    ax_r.axhline(TARGET_SCALING, color="C3", ls=":", label=f"target {TARGET_SCALING}")
    ax_r.set_xticks([0], ["1 worker / 2 workers"])
    ax_r.set_ylim(0, 2.2)
    ax_r.legend(fontsize=8)
    ax_r.grid(True, axis="y", alpha=0.3)
    ax_r.set_title("scaling (median, min-max)", fontsize=9)
    fig.savefig(path, dpi=120)


def main(argv=None) -> dict:
    try:
        import distributed  # noqa: F401
    except ImportError:
        raise SystemExit('scale_out needs the extra [sweep]: pip install -e ".[sweep]"') from None
    if shutil.which("taskset") is None:
        raise SystemExit("scale_out pins workers to cores with Linux's taskset, which is not on this machine")
    if (os.cpu_count() or 1) < 2:
        raise SystemExit("scale_out needs at least 2 CPU cores")
    with harness.Run(RESULTS_NAME, argv, description=__doc__.splitlines()[0]) as run:
        scratch = Path(tempfile.mkdtemp(prefix="clebsch-scale-out-"))
        try:
            rows = run.measure(
                [DEFAULT_CASE],
                [QUICK_CASE],
                lambda a, v, s, b, c: f"{a * a * v} members x {s} steps on 1 and 2 pinned workers",
                lambda *case: run_case(*case, run, scratch),
            )
        finally:
            shutil.rmtree(scratch, ignore_errors=True)
    cfg = {"worker_env": WORKER_ENV, "target_scaling": TARGET_SCALING, "config_toml": CONFIG}
    summary = run.summary(config=cfg, results=rows)
    summary["targets"] = {"scaling": {"target": TARGET_SCALING, "met": rows[0]["scaling"]["median"] >= TARGET_SCALING}}
    return run.finish(summary, print_report, plot)


if __name__ == "__main__":
    main()
