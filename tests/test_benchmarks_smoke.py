"""Smoke test of `benchmarks/rigid_body_step_cost.py --quick`: it runs and writes sane output.

No timing thresholds (tests never assert wall time; the benchmark reports it). ~37 s on an
idle 2-core machine, almost all of it compiling the six marches (three variants, two cases)
with XLA optimisation off.
"""

import json
import math
import subprocess
import sys
from pathlib import Path

BENCHMARK = Path(__file__).resolve().parents[1] / "benchmarks" / "rigid_body_step_cost.py"

VARIANTS = {  # variant -> (expected Solution.form, Q computed)
    "full": ("full", True),
    "reduced": ("reduced", True),
    "reduced_no_Q": ("reduced", False),
}
METHODS = (*VARIANTS, "numpy_rk4")
RATIOS = ("full_over_rk4_per_body_step", "reduced_over_rk4_per_body_step",
          "reduced_no_Q_over_rk4_per_body_step", "full_over_reduced", "full_over_reduced_no_Q")


def _positive_finite(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and x > 0


def test_rigid_body_step_cost_quick(tmp_path):
    # In its own process: --quick turns XLA optimisation off globally for its run, and the
    # programs it compiles must not stay in this test session's cache.
    subprocess.run([sys.executable, str(BENCHMARK), "--quick", "--out", str(tmp_path), "--timeout", "0"],
                   check=True, capture_output=True, text=True)

    assert (tmp_path / "rigid_body_step_cost.png").stat().st_size > 0
    summary = json.loads((tmp_path / "rigid_body_step_cost.json").read_text())
    assert {"benchmark", "config", "machine", "results", "target_full_over_reduced"} <= summary.keys()
    assert summary["config"]["quick"] is True
    assert summary["config"]["variants"] == {
        "full": {"reduce": False},
        "reduced": {"reduce": True, "reconstruct": True},
        "reduced_no_Q": {"reduce": True, "reconstruct": False},
    }
    for key in ("platform", "cpu_count", "jax", "numpy", "date_utc"):
        assert summary["machine"][key], key
    assert "git_commit" in summary["machine"]

    cases = {r["case"] for r in summary["results"]}
    assert cases == {"single", "vmap"}
    for row in summary["results"]:
        assert row["batch"] >= 1 and row["n_steps"] >= 1
        for method in METHODS:
            entry = row[method]
            for key in ("seconds_per_step", "seconds_per_body_step", "body_steps_per_second", "per_call_s"):
                assert _positive_finite(entry[key]), (row["case"], method, key, entry[key])
            assert all(_positive_finite(s) for s in entry["samples_s"])
            # accuracy at dt = 0.05 over a short run: small, finite (loose bounds, not a test
            # of either method)
            assert 0 <= entry["max_rel_energy_error"] < 1e-2, (row["case"], method)
        for variant, (form, has_Q) in VARIANTS.items():
            entry = row[variant]
            assert entry["form"] == form, (row["case"], variant)
            assert entry["Q_computed"] is has_Q, (row["case"], variant)
            if has_Q:
                assert 0 <= entry["max_orthogonality_error"] < 1e-4, (row["case"], variant)
            else:
                assert entry["max_orthogonality_error"] is None, (row["case"], variant)
            assert math.isfinite(entry["compile_s"])
            assert entry["newton_iterations_per_step_mean"] >= 1
            assert entry["nodal_newton_iterations_per_node_mean"] >= 0
            # the reduced march follows the full march's trajectory (loose bound)
            if variant == "full":
                assert entry["max_abs_xi_diff_vs_full"] is None
            else:
                assert 0 <= entry["max_abs_xi_diff_vs_full"] < 1e-6, (row["case"], variant)
        assert 0 <= row["numpy_rk4"]["max_orthogonality_error"] < 1e-4
        assert set(row["ratios"]) == set(RATIOS)
        for key in RATIOS:
            assert _positive_finite(row["ratios"][key]), (row["case"], key, row["ratios"][key])
        assert math.isclose(row["ratios"]["full_over_reduced"],
                            row["full"]["seconds_per_body_step"] / row["reduced"]["seconds_per_body_step"])
