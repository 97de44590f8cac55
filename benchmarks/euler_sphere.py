r"""Time per step of the Euler–Zeitlin fluid (`cj.models.euler_sphere(N)`) at N = 64, 128, 256.

Run from the repository root:

    python benchmarks/euler_sphere.py            # default run (N = 64, 128, 256)
    python benchmarks/euler_sphere.py --quick    # smoke test, small N (not a measurement)
    python benchmarks/euler_sphere.py --long 128 --steps 10000   # the long run: invariants over time

Timed with the shared harness (`_timing.py`: the first call compiles and is timed alone, then
the median of `--repeats` samples, the methods of a case sampled in turn, every call ending in
`jax.block_until_ready`), in one process and one run. Per N, from one random vorticity with
its energy near degree 10 and a root-mean-square vorticity of 1, `STEPS[N]` steps of Δt = 0.01:

- **ours**: `integrate(euler_sphere(N), ..., reconstruct=False)` under `jax.jit` — the default
  form (`form="unitary"`: N² unknowns, complex N×N products) and method (the reduced Cayley
  march, solved by matrix-free sweeps preconditioned with the model's tridiagonal inverse
  Laplacian), to round-off; **ours_real**, the same march in the real 2N×2N form
  (`form="real"`, 4N² unknowns, real 2N×2N products), the paired measure of what the form
  pays; and **ours_quflow_tol**, the same
  march with `atol=` quflow's default tolerance (`quflow_tolerance`), the equal-accuracy peer
  of quflow's default;
- **numpy**: the isospectral midpoint method written directly in NumPy with complex N×N
  matrices (BLAS `zgemm`), its Poisson solves by a vectorised Thomas algorithm along the
  diagonals, its fixed-point iteration stopped at round-off like ours. An independent
  implementation of the same scheme, written for this benchmark.
- **quflow** (when `import quflow` works; otherwise the JSON says "not installed" and the run
  goes on): the anchor code of the issue, Modin & Viviani's numba-compiled `quflow.isomp`
  (the isospectral midpoint by fixed-point iterations, Poisson solves by numba Thomas sweeps).
  Not a dependency of this project: install numba and quflow yourself to run it. Three
  variants: its own default stopping rule (tolerance √ε·Δt/ħ·|W|, at most 10 iterations) on one
  numba thread and on numba's default threads, and on one thread stopped at round-off like ours
  (`_tight`). numba compiles in the first call, timed apart like JAX's compile.

NumPy's BLAS threads compete for the cores with XLA's and with other users: on a loaded
machine run with `OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1` (the JSON records these variables),
or the NumPy peer's small products slow down by an order of magnitude.

Reported per N: seconds per step of each, the ratios of ours to each, sweeps per step, and
the largest difference between the final vorticities (they are not the same map to round-off: the
centre of u(N) is weighted N² in ours, ∞ in the NumPy method: a difference far below the
method's error, near round-off). The
growth of the cost with N is fitted (log-log slope; the matrix products are O(N³)).
Outputs (in `--out`, default `benchmarks/results`): `euler_sphere.json` and `euler_sphere.png`.
Nothing here asserts a time.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _timing as harness  # noqa: E402

import clebsch_jax as cj  # noqa: E402

RESULTS_NAME = "euler_sphere"
DT = 0.01
PEAK = 10
DEFAULT_CASES = ((64, 40), (128, 20), (256, 10))
QUICK_CASES = ((12, 5), (16, 5))


def initial_vorticity(N: int, seed: int = 0) -> np.ndarray:
    """W of a random field, energy spectrum peaked near degree `PEAK`, rms vorticity 1."""
    rng = np.random.default_rng(seed)
    l = np.arange(N, dtype=float)
    amplitude = np.sqrt(l * (l + 1) * l**3 * np.exp(-2 * (l / PEAK) ** 2) / (2 * l + 1))
    c = np.tril(rng.normal(size=(N, N)) + 1j * rng.normal(size=(N, N))) * amplitude[:, None]
    c[:, 0] = c[:, 0].real * np.sqrt(2)
    c[0, 0] = 0.0
    c *= np.sqrt(4 * np.pi / (np.sum(np.abs(c[:, 0]) ** 2) + 2 * np.sum(np.abs(c[:, 1:]) ** 2)))
    return np.asarray(cj.models.euler_sphere_quantise(c))


# --- the NumPy peer ------------------------------------------------------------------------


class NumpyIsospectralMidpoint:
    r"""The isospectral midpoint step $W^n = (I + A)\tilde W(I - A)$, $W^{n+1} = (I - A)\tilde
    W(I + A)$, $A = -\tfrac{\Delta t}{2\hbar}\tilde P$, $\Delta_N\tilde P = \tilde W$ (trace-free),
    solved for $\tilde W$ by the iteration $\tilde W \leftarrow W^n - [A, \tilde W] + A\tilde WA$
    until its update is at round-off. Complex NumPy; the Poisson solve by a Thomas algorithm
    along every diagonal at once (diagonal 0, singular, in its eigenbasis)."""

    def __init__(self, N: int, dt: float):
        s = 0.5 * (N - 1)
        m = s - np.arange(N)
        c = np.sqrt(np.maximum(s * (s + 1) - m * (m + 1), 0.0))
        c_next = np.append(c[1:], 0.0)
        centre = -2 * s * (s + 1) + 2 * np.outer(m, m)
        up = np.outer(c_next, c_next)
        k, i = np.meshgrid(np.arange(N), np.arange(N), indexing="ij")
        self.valid = i < N - k
        self.rows, self.cols = np.where(self.valid, i, 0), np.where(self.valid, i + k, 0)
        self.d = np.where(self.valid, centre[self.rows, self.cols], 1.0)
        self.e = np.where(self.valid & (i + 1 < N - k), up[self.rows, self.cols], 0.0)
        T0 = np.diag(self.d[0]) + np.diag(self.e[0, :-1], 1) + np.diag(self.e[0, :-1], -1)
        lam, V = np.linalg.eigh(T0)
        lam[np.argmin(np.abs(lam))] = np.inf  # the kernel (the identity): dropped
        self.inv0 = (V / lam) @ V.T
        jj, ii = np.meshgrid(np.arange(N), np.arange(N))
        self.upper_index = (np.clip(jj - ii, 0, None), ii)
        self.lower_index = (np.clip(ii - jj, 0, None), jj)
        self.upper = jj >= ii
        self.N, self.dt, self.hbar = N, dt, 2.0 / np.sqrt(N * N - 1.0)
        # the Thomas factorisation of diagonals 1..N-1 (all at once): modified upper diagonal
        d, e = self.d[1:], self.e[1:]
        self.cp = np.zeros_like(d)
        self.denominator = np.zeros_like(d)
        self.denominator[:, 0] = d[:, 0]
        self.cp[:, 0] = e[:, 0] / d[:, 0]
        for j in range(1, N):
            self.denominator[:, j] = d[:, j] - e[:, j - 1] * self.cp[:, j - 1]
            self.cp[:, j] = e[:, j] / self.denominator[:, j]
        self.e_lower = e

    def _solve_skewed(self, B):
        """Δ X = B along diagonals 1..N−1 of the skewed arrays (rows: diagonals)."""
        N = self.N
        y = np.empty_like(B)
        y[:, 0] = B[:, 0] / self.denominator[:, 0]
        for j in range(1, N):
            y[:, j] = (B[:, j] - self.e_lower[:, j - 1] * y[:, j - 1]) / self.denominator[:, j]
        for j in range(N - 2, -1, -1):
            y[:, j] -= self.cp[:, j] * y[:, j + 1]
        return y

    def poisson(self, W):
        """P with Δ_N P = W − tr(W)/N·I and tr P = 0 (complex N×N)."""
        skew = [np.where(self.valid, M[self.rows, self.cols], 0.0) for M in (W, W.T)]
        solved = []
        for S in skew:
            X = np.empty_like(S)
            X[0] = self.inv0 @ S[0]
            X[1:] = self._solve_skewed(S[1:])
            solved.append(X)
        return np.where(self.upper, solved[0][self.upper_index], solved[1][self.lower_index])

    def step(self, W):
        eps = np.finfo(float).eps
        M = W.copy()
        scale = max(1.0, np.max(np.abs(W)))
        sweeps = 0
        for sweeps in range(1, 200):
            A = -(self.dt / (2 * self.hbar)) * self.poisson(M)
            AM = A @ M
            M_new = W - AM + M @ A + AM @ A
            update = np.max(np.abs(M_new - M))
            M = M_new
            if update <= 8 * eps * scale:
                break
        A = -(self.dt / (2 * self.hbar)) * self.poisson(M)
        AM = A @ M
        return M - AM + M @ A - AM @ A, sweeps  # (I − A) W̃ (I + A)

    def march(self, W, n_steps):
        sweeps = []
        for _ in range(n_steps):
            W, k = self.step(W)
            sweeps.append(k)
        return W, float(np.mean(sweeps))


# --- the anchor code: quflow ---------------------------------------------------------------


def _import_quflow():
    """quflow and numba, or (None, the reason) when they are not installed."""
    try:
        import numba
        import quflow
    except ImportError as error:  # an optional peer: the run goes on without it
        return None, f"not installed ({error})"
    return (quflow, numba), None


def quflow_tolerance(W0, N: int) -> float:
    r"""quflow's default tolerance of `isomp` (its `tol="auto"`): $\sqrt\varepsilon\,\Delta t/\hbar\,
    \|W\|_\infty$, the largest row sum of |W|. Ours runs at it as `atol` (`ours_quflow_tol`): its
    updates are judged in the max-norm of the entries and its estimate of the remaining error
    (θ/(1 − θ) times the update) must be below it, where quflow stops at an update below it.
    Ours iterates on the momentum, 2(Re W + Im W) in the model's default (unitary) form: twice
    the scale of W, so twice the tolerance."""
    return float(2 * np.sqrt(np.finfo(float).eps) * DT / cj.models.euler_sphere_hbar(N) * np.linalg.norm(W0, np.inf))


def quflow_calls(quflow, numba, W0, n_steps, tight_tol):
    """The timed quflow calls: its default isospectral midpoint (`quflow.isomp`, fixed-point
    iterations, its automatic tolerance) on one numba thread and on numba's default threads, and
    on one thread with the iteration stopped at `tight_tol` (the round-off rule of ours). Each call
    marches a copy of W0 (quflow overwrites its argument) and returns (W, iterations per step)."""
    default_threads = numba.config.NUMBA_NUM_THREADS

    def call(threads, tol):
        def run():
            numba.set_num_threads(threads)
            stats = {"iterations": 0.0}
            W = quflow.isomp(W0.copy(), DT, steps=n_steps, tol=tol, maxit=50 if tol != "auto" else 10, stats=stats)
            numba.set_num_threads(default_threads)
            return W, float(stats["iterations"])

        return run

    calls = {"quflow_1thread": call(1, "auto"), "quflow_tight_1thread": call(1, tight_tol)}
    if default_threads > 1:
        calls[f"quflow_{default_threads}threads"] = call(default_threads, "auto")
    return calls


# --- the long run --------------------------------------------------------------------------


def _invariants(W) -> np.ndarray:
    """tr W², tr W³, tr W⁴ (`euler_sphere_casimirs`) and the energy of the vorticity matrix W."""
    return np.append(np.asarray(cj.models.euler_sphere_casimirs(W)), float(cj.models.euler_sphere_energy(W)))


def long_run(N: int, n_steps: int, every: int, out: Path, quick: bool = False) -> dict:
    """`n_steps` steps of Δt = `DT` from `initial_vorticity(N)`, in chunks of `every` steps: each
    chunk one eager `integrate(..., reconstruct=False)` continued from the last one's end by
    `continue_from` (Q stays the identity: the reduced march does not carry it). After every chunk
    the relative errors of tr W², tr W³, tr W⁴ and the energy at its last node are appended, and
    `euler_sphere_long.json` is rewritten (a partial run keeps what it reached); the PNG at the
    end."""
    system = cj.models.euler_sphere(N)
    W0 = initial_vorticity(N)
    Q0, xi0 = cj.models.euler_sphere_start(W0)
    start = dict(Q0=Q0, xi0=xi0, P0=None, t0=0.0)
    ref = _invariants(W0)
    names = ("tr W^2", "tr W^3", "tr W^4", "energy")
    record = {
        "benchmark": "euler_sphere_long",
        "config": {"N": N, "dt": DT, "n_steps": n_steps, "every": every, "peak_degree": PEAK, "quick": quick},
        "machine": harness.machine_info(),
        "invariants": list(names),
        "initial_values": ref.tolist(),
        "error": "relative error |f(W^n) - f(W^0)| / |f(W^0)| at the last node of every chunk; "
        "relative_errors: W^0 the input vorticity; relative_errors_from_node_0: W^0 the march's "
        "first node (its momentum is the gradient of l at the start velocity, which differs from "
        "the input by the round-off of the Legendre map and its inverse)",
        "steps": [0],
        "relative_errors": {name: [0.0] for name in names},
        "relative_errors_from_node_0": {name: [0.0] for name in names},
        "sweeps_per_step": [],
        "chunk_seconds": [],
        "load_average_1min": [harness.load_average()],
        "status": "running",
    }
    out.mkdir(parents=True, exist_ok=True)
    json_path = out / "euler_sphere_long.json"
    done = 0
    tic0 = time.perf_counter()
    while done < n_steps:
        m = min(every, n_steps - done)
        tic = time.perf_counter()
        sol = cj.integrate(system, dt=DT, n_steps=m, reconstruct=False, **start)
        jax.block_until_ready(sol.momentum)
        record["chunk_seconds"].append(time.perf_counter() - tic)
        done += m
        W = cj.models.euler_sphere_vorticity(sol.momentum[-1])
        if done == m:
            ref_node = _invariants(cj.models.euler_sphere_vorticity(sol.momentum[0]))
            record["initial_values_node_0"] = ref_node.tolist()
        values = _invariants(W)
        errors = np.abs(values - ref) / np.abs(ref)
        for name, e, e_node in zip(names, errors, np.abs(values - ref_node) / np.abs(ref_node)):
            record["relative_errors"][name].append(float(e))
            record["relative_errors_from_node_0"][name].append(float(e_node))
        record["steps"].append(done)
        record["sweeps_per_step"].append(float(np.mean(np.asarray(sol.stats.iterations))))
        record["load_average_1min"].append(harness.load_average())
        record["elapsed_s"] = time.perf_counter() - tic0
        record["status"] = "finished" if done >= n_steps else "running"
        for key in ("relative_errors", "relative_errors_from_node_0"):
            record[f"max_{key}"] = {name: max(v) for name, v in record[key].items()}
        with open(json_path, "w") as fh:
            json.dump(record, fh, indent=2)
        print(
            f"step {done:>6}: " + " ".join(f"{n} {e:.1e}" for n, e in zip(names, errors)) + f" "
            f"({record['chunk_seconds'][-1]:.1f} s, load {record['load_average_1min'][-1]:.1f})",
            flush=True,
        )
        start = cj.continue_from(system, sol, Q=start["Q0"])._asdict()
    plot_long(record, out / "euler_sphere_long.png")
    print(f"wrote {json_path.name} and euler_sphere_long.png in {harness.display_path(out)}")
    return record


def plot_long(record: dict, path: Path) -> None:
    fig, ax = harness.figure([1], size=(6.5, 4.4))
    steps = np.array(record["steps"][1:])
    for (name, values), color in zip(record["relative_errors"].items(), ("C0", "C1", "C2", "C3")):
        t = steps * record["config"]["dt"]
        ax.semilogy(t, np.maximum(values[1:], 1e-17), color=color, label=f"{name} (from the input W)")
        if name in record.get("relative_errors_from_node_0", {}) and name != "energy":
            from_node = record["relative_errors_from_node_0"][name][1:]
            ax.semilogy(t, np.maximum(from_node, 1e-17), ":", color=color, label=f"{name} (from node 0)")
    ax.set_xlabel("t")
    ax.set_ylabel("relative error")
    ax.legend(fontsize=8)
    cfg, mach = record["config"], record["machine"]
    ax.set_title(
        f"Euler-Zeitlin N = {cfg['N']}, dt = {cfg['dt']}, {steps[-1]} of {cfg['n_steps']} steps\n"
        f"{mach['cpu_count']} CPUs, load {mach['load_average_1min_at_start']:.2f} at start, jax {mach['jax']}",
        fontsize=8,
    )
    fig.savefig(path, dpi=120)


# --- the cases -----------------------------------------------------------------------------


def run_case(N: int, n_steps: int, run: harness.Run) -> dict:
    W0 = initial_vorticity(N)
    system = cj.models.euler_sphere(N)
    Q0, xi0 = cj.models.euler_sphere_start(W0)
    marches = {
        name: jax.jit(
            lambda x, options=options: cj.integrate(
                system, Q0, x, dt=DT, n_steps=n_steps, reconstruct=False, throw=False, **options
            )
        )
        for name, options in (("ours", {}), ("ours_quflow_tol", {"atol": quflow_tolerance(W0, N)}))
    }
    real_system = cj.models.euler_sphere(N, form="real")
    Q0_real, xi0_real = cj.models.euler_sphere_start(W0, "real")
    march_real = jax.jit(
        lambda x: cj.integrate(real_system, Q0_real, x, dt=DT, n_steps=n_steps, reconstruct=False, throw=False)
    )
    peer = NumpyIsospectralMidpoint(N, DT)
    calls = {name: (lambda m=m: jax.block_until_ready(m(xi0))) for name, m in marches.items()}
    calls["ours_real"] = lambda: jax.block_until_ready(march_real(xi0_real))
    calls["numpy"] = lambda: peer.march(W0, n_steps)
    anchor, _ = _import_quflow()
    if anchor is not None:
        calls.update(quflow_calls(*anchor, W0, n_steps, 8 * np.finfo(float).eps * np.max(np.abs(W0))))
    timings, outs = run.time(calls, what=f"N={N}")
    sol = outs["ours"]
    if not np.all(np.asarray(sol.result) == cj.Status.SUCCESS):
        raise RuntimeError(f"N={N}: the march did not succeed")
    W_ours = np.asarray(cj.models.euler_sphere_vorticity(sol.momentum[-1]))
    sol_loose = outs["ours_quflow_tol"]
    W_loose = np.asarray(cj.models.euler_sphere_vorticity(sol_loose.momentum[-1]))
    W_numpy, numpy_sweeps = outs["numpy"]
    per_step = {name: t["per_call_s"] / n_steps for name, t in timings.items()}
    spectra = np.linalg.eigvalsh(1j * np.stack([W0, W_ours]))
    anchor_rows = {}
    for name in (k for k in calls if k.startswith("quflow")):
        W_q, iterations = outs[name]
        anchor_rows[name] = {
            "iterations_per_step": iterations,
            "max_difference_of_final_W_from_ours": float(np.max(np.abs(W_q - W_ours))),
            "max_difference_of_final_W_from_numpy": float(np.max(np.abs(W_q - W_numpy))),
            "ours_over_it": per_step["ours"] / per_step[name],
            "ours_quflow_tol_over_it": per_step["ours_quflow_tol"] / per_step[name],
        }
    return {
        "N": N,
        "n_steps": n_steps,
        "timings": timings,
        "seconds_per_step": per_step,
        "ours_over_numpy": per_step["ours"] / per_step["numpy"],
        "ours_over_ours_real": per_step["ours"] / per_step["ours_real"],
        "sweeps_per_step": {
            "ours": float(np.mean(np.asarray(sol.stats.iterations))),
            "ours_quflow_tol": float(np.mean(np.asarray(sol_loose.stats.iterations))),
            "ours_real": float(np.mean(np.asarray(outs["ours_real"].stats.iterations))),
            "numpy": numpy_sweeps,
        },
        "max_difference_of_final_W_quflow_tol_from_ours": float(np.max(np.abs(W_loose - W_ours))),
        "max_difference_of_final_W": float(np.max(np.abs(W_ours - W_numpy))),
        "max_abs_W": float(np.max(np.abs(W0))),
        "spectrum_change_ours": float(np.max(np.abs(spectra[1] - spectra[0]))),
        "quflow": anchor_rows,
    }


def _slope(rows, key):
    N = np.array([r["N"] for r in rows], float)
    t = np.array([r["seconds_per_step"][key] for r in rows])
    return float(np.polyfit(np.log(N), np.log(t), 1)[0]) if len(rows) > 1 else None


def print_report(summary: dict) -> None:
    harness.print_header(
        summary,
        "Euler-Zeitlin: seconds per step",
        "ours: integrate(euler_sphere(N)) under jit; numpy: the isospectral midpoint in NumPy "
        "(complex BLAS), an independent implementation; quflow: the anchor code's isomp "
        f"(numba), {summary['config']['anchor_code']}.",
    )
    head = (
        f"{'N':>5}{'steps':>7}{'ours s/step':>14}{'numpy s/step':>14}{'ours/numpy':>11}{'sweeps':>8}"
        f"{'numpy sw.':>10}{'|dW|':>10}{'at quflow tol: s/step':>23}{'sweeps':>8}{'|W - ours|':>12}"
    )
    lines = [
        f"{r['N']:>5}{r['n_steps']:>7}{r['seconds_per_step']['ours']:>14.4g}"
        f"{r['seconds_per_step']['numpy']:>14.4g}{r['ours_over_numpy']:>11.3f}"
        f"{r['sweeps_per_step']['ours']:>8.2f}{r['sweeps_per_step']['numpy']:>10.2f}"
        f"{r['max_difference_of_final_W']:>10.1e}{r['seconds_per_step']['ours_quflow_tol']:>23.4g}"
        f"{r['sweeps_per_step']['ours_quflow_tol']:>8.2f}{r['max_difference_of_final_W_quflow_tol_from_ours']:>12.1e}"
        for r in summary["results"]
    ]
    harness.print_table(head, lines)
    print(
        "real form (form='real'): "
        + "; ".join(
            f"N={r['N']} {r['seconds_per_step']['ours_real']:.4g} s/step, {r['sweeps_per_step']['ours_real']:.2f} "
            f"sweeps, ours/real {r['ours_over_ours_real']:.3f}"
            for r in summary["results"]
        )
    )
    anchor = [(r, name, q) for r in summary["results"] for name, q in r["quflow"].items()]
    if anchor:
        head = (
            f"{'N':>5}  {'quflow variant':<22}{'s/step':>12}{'ours/it':>9}{'ours at its tol/it':>20}"
            f"{'iter.':>7}{'|W - ours|':>12}{'|W - numpy|':>13}"
        )
        lines = [
            f"{r['N']:>5}  {name:<22}{r['seconds_per_step'][name]:>12.4g}{q['ours_over_it']:>9.3f}"
            f"{q['ours_quflow_tol_over_it']:>20.3f}"
            f"{q['iterations_per_step']:>7.2f}{q['max_difference_of_final_W_from_ours']:>12.1e}"
            f"{q['max_difference_of_final_W_from_numpy']:>13.1e}"
            for r, name, q in anchor
        ]
        print()
        harness.print_table(head, lines)
    slopes = ", ".join(f"{k} {v:.2f}" for k, v in summary["slopes"].items() if v is not None)
    print(f"cost growth (log-log slope in N): {slopes}")


def plot(summary: dict, path: Path) -> None:
    fig, ax = harness.figure([1], size=(6.5, 4.4))
    rows = summary["results"]
    N = np.array([r["N"] for r in rows])
    markers = iter(("o-", "s--", "^-.", "v:", "d-", "x--", "P-."))
    for key in summary["slopes"]:
        slope = summary["slopes"][key]
        ax.loglog(
            N,
            [r["seconds_per_step"][key] for r in rows],
            next(markers),
            label=f"{key} (slope {slope:.2f})" if slope is not None else key,
        )
    ref = rows[-1]["seconds_per_step"]["ours"] * (N / N[-1]) ** 3.0
    ax.loglog(N, ref, ":", color="0.5", label="N^3")
    ax.set_xlabel("N")
    ax.set_ylabel("seconds per step")
    ax.legend(fontsize=8)
    ax.set_title(harness.plot_title(summary, "Euler-Zeitlin, time per step"), fontsize=8)
    fig.savefig(path, dpi=120)


def _describe(N, n_steps) -> str:
    return f"N={N} n_steps={n_steps}"


def _add_arguments(parser) -> None:
    parser.add_argument(
        "--long",
        type=int,
        default=None,
        metavar="N",
        help="instead of timing: the long run at size N (invariants over time, euler_sphere_long.json/png)",
    )
    parser.add_argument("--steps", type=int, default=10_000, help="steps of the long run (default 10000)")
    parser.add_argument("--every", type=int, default=100, help="steps per chunk of the long run (default 100)")


def main(argv=None) -> dict:
    """Run the benchmark: the cases, the report, the JSON and the PNG; returns the summary."""
    with harness.Run(
        RESULTS_NAME,
        argv,
        description="Time per step of the Euler-Zeitlin fluid (see module docstring).",
        add_arguments=_add_arguments,
    ) as run:
        if run.args.long is not None:
            return long_run(run.args.long, run.args.steps, run.args.every, Path(run.args.out), run.quick)
        results = run.measure(DEFAULT_CASES, QUICK_CASES, _describe, lambda *case: run_case(*case, run))
    threads = {
        k: os.environ.get(k)
        for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")
    }
    anchor, missing = _import_quflow()
    if anchor is not None:
        quflow, numba = anchor
        anchor_code = (
            f"quflow {quflow.__version__} with numba {numba.__version__} "
            f"(default numba threads {numba.config.NUMBA_NUM_THREADS})"
        )
    else:
        anchor_code = f"quflow (Modin & Viviani): {missing}, not run"
    summary = run.summary(
        config={
            "dt": DT,
            "peak_degree": PEAK,
            "blas_thread_variables": threads,
            "cases": [{"N": N, "n_steps": n} for N, n in run.cases],
            "anchor_code": anchor_code,
        },
        results=results,
        slopes={key: _slope(results, key) for key in results[0]["seconds_per_step"]},
    )
    return run.finish(summary, print_report, plot)


if __name__ == "__main__":
    main()
