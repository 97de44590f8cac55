r"""What complex N×N matrices would save the Euler–Zeitlin fluid's sweeps on XLA's CPU backend:
the product of two complex N×N matrices, against the product of their real 2N×2N forms
$R(A + iB) = \begin{pmatrix} A & -B \\ B & A\end{pmatrix}$ (what `cj.models.euler_sphere` carries
today) and against the complex product written as four real N×N products
($(A + iB)(C + iD) = AC - BD + i(AD + BC)$), with one real N×N product for scale. NumPy's
complex product (BLAS `zgemm`, what quflow's iteration calls) is the peer.

Run from the repository root:

    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 python benchmarks/complex_products.py
    python benchmarks/complex_products.py --quick    # smoke test, small N (not a measurement)

Timed with the shared harness (`_timing.py`: median of `--repeats` samples, the methods of a
case sampled in turn, every JAX call ending in `jax.block_until_ready`). Reported per N: seconds
per product of each, and each over the real 2N×2N product. Outputs (in `--out`, default
`benchmarks/results`): `complex_products.json` and `complex_products.png`. Nothing here asserts
a time.
"""

from __future__ import annotations

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _timing as harness  # noqa: E402

RESULTS_NAME = "complex_products"
DEFAULT_CASES = ((64,), (128,), (256,))
QUICK_CASES = ((8,), (16,))
METHODS = ("real_N", "complex_N", "real_2N", "four_real_N", "numpy_complex_N")


def run_case(N: int, run: harness.Run) -> dict:
    rng = np.random.default_rng(N)
    A, B, C, D = (jnp.asarray(rng.normal(size=(N, N))) for _ in range(4))
    Z1, Z2 = A + 1j * B, C + 1j * D
    R1 = jnp.block([[A, -B], [B, A]])
    R2 = jnp.block([[C, -D], [D, C]])
    product = jax.jit(lambda x, y: x @ y)
    four = jax.jit(lambda a, b, c, d: (a @ c - b @ d, a @ d + b @ c))
    Z1n, Z2n = np.asarray(Z1), np.asarray(Z2)
    calls = {
        "real_N": lambda: jax.block_until_ready(product(A, C)),
        "complex_N": lambda: jax.block_until_ready(product(Z1, Z2)),
        "real_2N": lambda: jax.block_until_ready(product(R1, R2)),
        "four_real_N": lambda: jax.block_until_ready(four(A, B, C, D)),
        "numpy_complex_N": lambda: Z1n @ Z2n,
    }
    timings, outs = run.time(calls, what=f"N={N}")
    re, im = outs["four_real_N"]
    agree = max(
        float(np.max(np.abs(outs["complex_N"] - (re + 1j * im)))),
        float(np.max(np.abs(outs["real_2N"][:N, :N] - re))),
    )
    per = {name: t["per_call_s"] for name, t in timings.items()}
    return {
        "N": N,
        "timings": timings,
        "seconds_per_product": per,
        "over_real_2N": {name: per[name] / per["real_2N"] for name in per},
        "max_difference_between_forms": agree,
    }


def print_report(summary: dict) -> None:
    harness.print_header(
        summary,
        "Complex N x N products against real 2N x 2N forms (XLA CPU)",
        "complex_N: jnp complex128 @; real_2N: the real form R(Z); four_real_N: four float64 N x N "
        "products; numpy_complex_N: NumPy's zgemm.",
    )
    head = f"{'N':>5}" + "".join(f"{name:>18}" for name in METHODS) + f"{'|diff|':>10}"
    lines = []
    for r in summary["results"]:
        cells = "".join(f"{r['seconds_per_product'][m]:>10.3g} ({r['over_real_2N'][m]:.2f})".rjust(18) for m in METHODS)
        lines.append(f"{r['N']:>5}{cells}{r['max_difference_between_forms']:>10.1e}")
    harness.print_table(head, lines)
    print("seconds per product (over the real 2N x 2N product)")


def plot(summary: dict, path: Path) -> None:
    fig, ax = harness.figure([1], size=(6.5, 4.4))
    rows = summary["results"]
    N = np.array([r["N"] for r in rows])
    for marker, name in zip(("o-", "s--", "^-.", "v:", "d-"), METHODS):
        ax.loglog(N, [r["seconds_per_product"][name] for r in rows], marker, label=name)
    ax.set_xlabel("N")
    ax.set_ylabel("seconds per product")
    ax.legend(fontsize=8)
    ax.set_title(harness.plot_title(summary, "complex N x N against real 2N x 2N products"), fontsize=8)
    fig.savefig(path, dpi=120)


def main(argv=None) -> dict:
    """Run the benchmark: the cases, the report, the JSON and the PNG; returns the summary."""
    with harness.Run(RESULTS_NAME, argv, description="Complex against real-form matrix products.") as run:
        results = run.measure(DEFAULT_CASES, QUICK_CASES, lambda N: f"N={N}", lambda N: run_case(N, run))
    summary = run.summary(config={"cases": [{"N": N} for (N,) in run.cases]}, results=results)
    return run.finish(summary, print_report, plot)


if __name__ == "__main__":
    main()
