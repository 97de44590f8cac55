"""Smoke test of the benchmark scripts in `--quick` mode: each runs and writes sane output.

No timing thresholds (tests never assert wall time; the benchmarks report it). Each script
runs in its own process: `--quick` turns XLA optimisation off globally for its run, and the
programs it compiles must not stay in this test session's cache. Measured on 2 cores at load
4-5 (other users): 42-71 s (rigid_body_step_cost), 33-44 s (vortex_step_cost), 42-58 s
(throughput), 2-3 min together, almost all of it compiling. Besides the JSON, the `defaults`
check asserts what its part 1 counts: no XLA compilation in a fresh process when `integrate` is
called again with a new `n_steps`, `dt` or model parameters (a count, not a time).
"""

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
RK4 = "numpy_rk4"


def _positive_finite(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and x > 0


def _check_timed(entry: dict, keys: tuple, where) -> None:
    """A method's timing entry: the given rates and times and every sample positive and finite."""
    for key in ("per_call_s", "first_call_s", "second_call_s", "cpu_per_call_s", *keys):
        assert _positive_finite(entry[key]), (where, key, entry[key])
    assert entry["calls_per_sample"] >= 1, where
    assert entry["samples_s"] and all(_positive_finite(s) for s in entry["samples_s"]), where


# --------------------------------------------------------------------------------------------
# What each script's JSON must hold besides the common part.

RIGID_VARIANTS = {  # variant -> (expected Solution.form, Q computed)
    "full": ("full", True),
    "reduced": ("reduced", True),
    "reduced_no_Q": ("reduced", False),
}
RIGID_RATIOS = (
    "full_over_rk4_per_body_step",
    "reduced_over_rk4_per_body_step",
    "reduced_no_Q_over_rk4_per_body_step",
    "full_over_reduced",
    "full_over_reduced_no_Q",
)


def check_rigid_body_step_cost(summary: dict) -> None:
    assert summary["target_full_over_reduced"] == 10.0
    assert summary["config"]["variants"] == {
        "full": {"reduce": False},
        "reduced": {"reduce": True, "reconstruct": True},
        "reduced_no_Q": {"reduce": True, "reconstruct": False},
    }
    assert {r["case"] for r in summary["results"]} == {"single", "vmap"}
    for row in summary["results"]:
        assert row["batch"] >= 1 and row["n_steps"] >= 1
        for method in (*RIGID_VARIANTS, RK4):
            entry = row[method]
            _check_timed(
                entry, ("seconds_per_step", "seconds_per_body_step", "body_steps_per_second"), (row["case"], method)
            )
            # accuracy at dt = 0.05 over a short run: small, finite (loose bounds, not a test
            # of either method)
            assert 0 <= entry["max_rel_energy_error"] < 1e-2, (row["case"], method)
        for variant, (form, has_Q) in RIGID_VARIANTS.items():
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
        assert 0 <= row[RK4]["max_orthogonality_error"] < 1e-4
        assert set(row["ratios"]) == set(RIGID_RATIOS)
        assert all(_positive_finite(row["ratios"][key]) for key in RIGID_RATIOS), row["ratios"]
        assert math.isclose(
            row["ratios"]["full_over_reduced"],
            row["full"]["seconds_per_body_step"] / row["reduced"]["seconds_per_body_step"],
        )


def check_vortex_step_cost(summary: dict) -> None:
    assert summary["config"]["dt"] == 0.01
    assert summary["target"]["N"] == 1000 and summary["target"]["max_ours_over_rk4"] == 3.0
    rows = summary["results"]
    assert {r["case"] for r in rows} == {"single", "vmap"}
    assert any("dense" in r["variants"] for r in rows)
    for row in rows:
        assert row["N"] >= 2 and row["batch"] >= 1 and row["n_steps"] >= 1
        for method in (*row["variants"], RK4):
            entry = row[method]
            _check_timed(
                entry, ("seconds_per_step", "seconds_per_vortex_step", "vortex_steps_per_second"), (row["case"], method)
            )
            # both conserve the linear impulse (ours to round-off; RK4 too, it is linear in the
            # velocities); loose bounds, not a test of either method
            assert 0 <= entry["max_linear_impulse_drift"] < 1e-9, (row["case"], method)
            assert 0 <= entry["max_rel_hamiltonian_error"] < 1e-3, (row["case"], method)
        for variant in row["variants"]:
            entry = row[variant]
            assert entry["form"] == "full" and entry["scheme"] == "midpoint", (row["case"], variant)
            assert math.isfinite(entry["compile_s"])
            assert entry["newton_iterations_per_step_mean"] >= 1
            # dense: a Jacobian every step; blocks: formed at step 0, then carried (refreshed when needed)
            minimum = 1.0 if variant == "dense" else 1.0 / row["n_steps"]
            assert entry["newton_jacobians_per_step_mean"] >= minimum - 1e-12, (row["case"], variant)
            assert entry["max_residual_norm"] < 1e-10
            # midpoint (order 2) against RK4 (order 4) over a few steps of dt = 0.01: close
            assert 0 <= entry["max_abs_final_position_diff_vs_rk4"] < 1e-4, (row["case"], variant)
            assert _positive_finite(row["ratios"][f"{variant}_over_rk4"])
            assert math.isclose(
                row["ratios"][f"{variant}_over_rk4"], entry["seconds_per_step"] / row[RK4]["seconds_per_step"]
            )
        if "dense" in row["variants"] and "blocks" in row["variants"]:
            assert row["dense"]["max_abs_Q_diff_vs_blocks"] < 1e-10  # the same root
        expected_ratios = {f"{v}_over_rk4" for v in row["variants"]}
        if row["n_steps_short"]:  # calls of fewer steps: a call's fixed cost and the marginal step cost
            assert 1 <= row["n_steps_short"] < row["n_steps"]
            expected_ratios |= {f"{v}_marginal_over_rk4" for v in row["variants"]}
            for variant in row["variants"]:
                entry = row[variant]
                assert _positive_finite(entry["short_call"]["per_call_s"])
                # a difference of two timings: finite, not necessarily positive in a smoke run
                assert math.isfinite(entry["marginal_seconds_per_step"])
                assert math.isfinite(entry["fixed_cost_per_call_s"])
        assert set(row["ratios"]) == expected_ratios
        assert set(row["paired_ratios"]) == expected_ratios
    assert any(r["n_steps_short"] for r in rows)


def check_throughput(summary: dict) -> None:
    parts = {}
    for row in summary["results"]:
        parts.setdefault(row["part"], []).append(row)
    assert set(parts) == {"rigid_body", "vortices", "compile"}
    for row in parts["rigid_body"]:
        assert row["batch"] >= 1 and row["n_steps"] >= 1
        ours = [m for m in row["methods"] if m not in (RK4, "jax_by_hand")]
        assert ours[0] == "vmap" and ("chunked" in ours) == (row["batch"] > summary["config"]["chunk"])
        assert ("batch_last" in ours) == (row["batch"] > 1)
        # the hand-written reference computes our momenta (3 chord updates from a linear predictor)
        assert "jax_by_hand" in row["methods"] and row["jax_by_hand"]["max_abs_momentum_diff_vs_vmap"] < 1e-12
        assert math.isclose(
            row["ratios"]["vmap_over_hand_rate"],
            row["vmap"]["body_steps_per_second"] / row["jax_by_hand"]["body_steps_per_second"],
        )
        for method in row["methods"]:
            _check_timed(
                row[method],
                ("seconds_per_step", "seconds_per_body_step", "body_steps_per_second"),
                (row["batch"], method),
            )
        for method in ours:
            assert math.isfinite(row[method]["compile_s"])
            # the same equations as the RK4 (order 2 against order 4, a few steps of dt = 0.05)
            assert 0 <= row[method]["max_abs_final_xi_diff_vs_rk4"] < 1e-2, (row["batch"], method)
            assert math.isclose(
                row["ratios"][f"{method}_over_rk4_rate"],
                row[method]["body_steps_per_second"] / row[RK4]["body_steps_per_second"],
            )
        assert row["best"] in ours
        assert row["newton_updates_per_step"]["slowest_of_batch_mean"] >= row["newton_updates_per_step"]["mean"] >= 1
        if "chunked" in ours:
            assert row["max_abs_xi_diff_chunked_vs_vmap"] < 1e-10  # the same march, in chunks
            assert _positive_finite(row["ratios"]["chunked_over_vmap_rate"])
        if "batch_last" in ours:
            assert row["max_abs_xi_diff_batch_last_vs_vmap"] < 1e-12  # the same program, batch-last (bitwise here)
            assert _positive_finite(row["ratios"]["batch_last_over_vmap_rate"])
    for row in parts["vortices"]:
        for method in ("ours", RK4):
            _check_timed(
                row[method],
                ("seconds_per_step", "seconds_per_vortex_step", "vortex_steps_per_second"),
                (row["case"], row["N"], method),
            )
        assert 0 <= row["ours"]["max_abs_final_position_diff_vs_rk4"] < 1e-4
        if row["case"] == "vmap":  # cj.batch runs the same program: positions to round-off
            _check_timed(
                row["batch_last"],
                ("seconds_per_step", "seconds_per_vortex_step", "vortex_steps_per_second"),
                (row["case"], row["N"], "batch_last"),
            )
            assert row["batch_last"]["max_abs_position_diff_vs_vmap"] < 1e-12
        assert row["newton_updates_per_step"]["slowest_of_batch_mean"] >= row["newton_updates_per_step"]["mean"] >= 1
        assert math.isclose(
            row["ratios"]["ours_over_rk4_time_per_step"], row["ours"]["seconds_per_step"] / row[RK4]["seconds_per_step"]
        )
    assert [r["case"] for r in parts["compile"]] == summary["config"]["compile"]["models"]
    for row in parts["compile"]:
        assert row["form"] in ("full", "reduced")
        assert _positive_finite(row["first_call_s"]) and _positive_finite(row["second_call_s"])
        assert math.isfinite(row["compile_s"])
        assert row["first_call_jax_events"]["backend_compile"]["count"] >= 1  # the march was compiled
        # the warm child loaded every program the cold one wrote: hits, no misses
        assert row["persistent_cache"]["misses"] >= 1
        warm = row["warm"]
        assert warm["persistent_cache"]["hits"] >= 1 and warm["persistent_cache"]["misses"] == 0, warm
        assert _positive_finite(warm["first_call_s"]) and math.isfinite(warm["compile_s"])
    targets = summary["targets"]
    assert set(targets) == {"rigid_body_rate", "rigid_body_over_rk4", "rigid_body_flat", "vortex_step_cost", "compile"}
    assert all(t["met"] in (True, False, None) for t in targets.values())
    assert set(targets["compile"]["per_model"]) == set(summary["config"]["compile"]["models"])
    assert set(targets["compile"]["warm_per_model"]) == set(summary["config"]["compile"]["models"])
    assert targets["compile"]["warm_met"] in (True, False)


def check_work_precision(summary: dict) -> None:
    scenes = {sc["scene"]: sc for sc in summary["results"]}
    assert set(scenes) == {"rigid_body", "vortices_4", "vortices_100"}
    for name, sc in scenes.items():
        assert _positive_finite(sc["reference"]["wall_s"]) and sc["reference"]["check"]
        families = {p["family"] for p in sc["points"]}
        assert families == {"ours", "diffrax", "scipy", "numpy"}, (name, families)
        for p in sc["points"]:
            where = (name, p["method"], p["param"])
            assert p["valid"] and _positive_finite(p["wall_s"]), where
            for key in ("global_error", "energy_error", "invariant_error"):
                assert math.isfinite(p[key]) and p[key] >= 0, (where, key)
            if p["family"] == "ours":
                assert p["order"] in (2, 4, 6, 8) and p["newton"]["updates_per_substep"] >= 1, where
                # a composition of discrete Clebsch steps keeps the Casimir / the angular
                # impulse to round-off (loose bound; tests check it tightly)
                assert p["invariant_error"] < 1e-10, where
    comparison = summary["targets"]["rigid_body_T20"]
    assert all(comparison[k]["met"] in (True, False, None) for k in ("energy", "global"))


def check_work_precision_clusters(summary: dict) -> None:
    (sc,) = summary["results"]
    assert sc["scene"] == "vortex_clusters" and sc["shape"] == [2, 4, 2]
    assert {p["family"] for p in sc["points"]} == {"ours", "diffrax"}
    for p in sc["points"]:
        where = (p["method"], p["param"])
        assert p["valid"] and _positive_finite(p["wall_s"]), where
        for key in ("global_error", "energy_error", "invariant_error"):
            assert math.isfinite(p[key]) and p[key] >= 0, (where, key)
        if p["family"] == "ours":
            # Gauss-Legendre keeps the angular impulse (quadratic) to round-off (loose bound)
            assert p["method"].startswith("gauss") and p["invariant_error"] < 1e-12, where
    ct = summary["cluster_targets"]["vortex_clusters"]
    assert ct["met"] in (True, False) and ct["rows"]  # the quick run's rtol 1e-8 points are compared
    for r in ct["rows"]:
        assert r["met"] in (True, False) and (r["ours"] is None or _positive_finite(r["time_ratio_ours_over_peer"]))


def check_work_precision_ensembles(summary: dict) -> None:
    scenes = {sc["scene"]: sc for sc in summary["results"]}
    assert set(scenes) == {"rigid_body", "vortex_clusters"}
    with_heyoka = summary["peers"]["heyoka"] is not None  # heyoka is in the bench extra only
    for name, sc in scenes.items():
        families = {p["family"] for p in sc["points"]}
        assert families == {"ours", "diffrax"} | ({"heyoka"} if with_heyoka else set()), (name, families)
        for p in sc["points"]:
            where = (name, p["method"], p["param"])
            assert p["valid"] and _positive_finite(p["wall_s"]) and p["samples_s"], where
            for key in ("global_error", "energy_error"):
                assert math.isfinite(p[key]) and p[key] >= 0, (where, key)
            # every peer's energy at t = 0 is the script's own energy (ours: the sweep's)
            assert p["energy0_mismatch"] < 1e-12, where
            if p["family"] == "ours":
                assert p["backend"] in ("native", "xla"), where
                if name == "rigid_body":  # the quick run's rigid-body methods run natively
                    assert p["backend"] == "native", where
        for tg in (summary["targets"][name], summary["targets_cpu"][name]):  # by wall and by CPU time
            assert tg["heyoka_met"] in (True, False) and tg["diffrax_met"] in (True, False)
            assert bool(tg["heyoka"]) == with_heyoka and tg["diffrax"]


def check_work_precision_ceiling(summary: dict) -> None:
    (sc,) = summary["results"]  # --quick: the rigid bodies only, one tolerance, one point of ours
    assert sc["scene"] == "rigid_body" and sc["rows"]
    for r in sc["rows"]:
        hy, ours = r["heyoka"], r["ours"]
        for who in (hy, ours):
            for key in ("steps_per_unit_time", "instructions_per_unit_time", "flops_per_unit_time", "wall_s", "cpu_s"):
                assert _positive_finite(who[key]), (key, who)
            # a vector instruction of 4 lanes does at most 8 flops (a fused multiply-add): fewer
            # instructions than flops / 8 per member would mean a miscounted region
            assert who["instructions_per_flop"] > 1 / 8, who
        # Euler's equations in heyoka's decomposition: 6 products of series, 5 linear operations
        assert (hy["series_ops"], hy["linear_ops"]) == (6, 5) and hy["order"] >= 8
        assert ours["valid"] and ours["stages"] == 4 and ours["sweeps_per_step"] >= 1  # Gauss 8
        assert math.isclose(ours["instructions_per_unit_time"], ours["instructions_per_step"] / ours["dt"])
        # the break-down: at the sweeps per step (or the cost per sweep) to match, the same count
        assert math.isclose(r["sweeps_per_step_to_match"] * ours["instructions_per_sweep"] / ours["dt"],
                            hy["instructions_per_unit_time"])  # fmt: skip


def check_work_precision_sphere(summary: dict) -> None:
    (sc,) = summary["results"]
    assert sc["reference"]["valid"] and 0 <= sc["reference"]["check"] < 1e-8
    assert {p["family"] for p in sc["points"]} == {"ours", "diffrax"}
    for p in sc["points"]:
        assert p["valid"] and _positive_finite(p["wall_s"]), p["method"]
        for key in ("global_error", "energy_error", "moment_error", "sphere_error"):
            assert math.isfinite(p[key]) and p[key] >= 0, (p["method"], key)
        if p["family"] == "ours":  # Gauss-Legendre keeps the sphere's quadratic invariant |z|^2
            assert p["sphere_error"] < 1e-13, p
    assert len(sc["dominance"]) == sum(p["family"] == "diffrax" for p in sc["points"])


def check_soak(summary: dict) -> None:
    cases = {r["case"]: r for r in summary["results"]}
    assert set(cases) == {"rigid_body", "rigid_body_order4", "vortices_4"}
    for name, r in cases.items():
        assert r["status"] == 0 and r["n_steps"] == summary["config"]["n_steps"]
        assert _positive_finite(r["wall_s"]) and _positive_finite(r["seconds_per_step"])
        assert r["form"] == ("full" if name == "vortices_4" else "reduced")
        for k, q in r["quantities"].items():
            assert math.isfinite(q["max_error"]) and q["max_error"] >= 0, (name, k)
            if q["kind"] == "momentum" and k != "orthogonality":
                # loose: 10^4 steps of round-off, a few units of sqrt(n) eps expected
                assert q["max_ratio_to_sqrt_n_eps_scale"] < 100, (name, k)
        assert abs(r["memory"]["max_growth_after_first_chunk_mb"]) < 50
        assert r["running_max"]["step"][-1] == r["n_steps"] and r["chunks"]["step"]


DEFAULT_METHODS = {
    "rigid_body": "left principle",
    "heavy_top": "right(h/2) o left(h/2)",
    "user_pendulum": "midpoint principle",
}


def check_defaults(summary: dict) -> None:
    parts = {}
    for row in summary["results"]:
        parts.setdefault(row["part"], []).append(row)
    assert set(parts) == {"compile_once", "heavy_top_cost", "order"}
    assert {r["scene"] for r in parts["compile_once"]} == set(DEFAULT_METHODS)
    assert summary["config"]["part1"]["persistent_cache_in_children"] is False
    for row in parts["compile_once"]:
        calls = row["calls"]
        expected = ["first", "new_n_steps", "new_dt", "new_parameters", "first_again"]
        if row["scene"] == "user_pendulum":  # no parameters to change
            expected.remove("new_parameters")
        assert list(calls) == expected, row["scene"]
        for name, call in calls.items():
            assert call["method"] == DEFAULT_METHODS[row["scene"]] and call["order"] == 2, (row["scene"], name)
            assert all(_positive_finite(w) for w in call["wall_s"]) and _positive_finite(call["over_first"])
        assert min(calls["first"]["compilations"]) >= 1  # a fresh process compiles the march
        # the same programs on the same input: the same numbers
        assert calls["first_again"]["max_abs_final_diff_vs_first"] == 0.0
        # compile once per system and shapes: a new n_steps, dt or parameter value compiles nothing
        assert row["max_compilations_calls_2_to_5"] == 0, {n: c["programs_compiled"] for n, c in calls.items()}
        assert row["max_construct_compilations"] == 0
    (top,) = parts["heavy_top_cost"]
    for method, (name, order, form) in {
        "default": ("right(h/2) o left(h/2)", 2, "reduced"),
        "left": ("left principle", 1, "reduced"),
        "midpoint": ("midpoint principle", 2, "full"),
    }.items():
        entry = top[method]
        _check_timed(entry, ("seconds_per_step",), method)
        assert (entry["method"], entry["order"], entry["form"]) == (name, order, form), method
        assert 0 < entry["final_error_vs_reference"] < 0.1, method
    # second order beats first order at the same step (loose: not a test of either method)
    assert top["default"]["final_error_vs_reference"] < top["left"]["final_error_vs_reference"]
    assert 0 <= top["reference_check_default_dt_over_8"] < top["default"]["final_error_vs_reference"]
    assert all(_positive_finite(v) for v in top["ratios"].values())
    assert math.isclose(top["ratios"]["default_over_left"], top["default"]["per_call_s"] / top["left"]["per_call_s"])
    for row in parts["order"]:
        assert row["order"] == 2 and row["plan_symmetric"] and row["method"] == row["plan"], row["model"]
        assert len(row["errors"]) == 4 and all(_positive_finite(e) for e in row["errors"]), row["model"]
        assert row["slope"] >= 1.8, (row["model"], row["slope"])
        assert row["compilations_after_first_step_size"] == 0, row["model"]
    targets = summary["targets"]
    assert set(targets) == {
        "new_n_steps_over_first",
        "compilations_calls_2_to_5",
        "heavy_top_default_over_left",
        "order",
    }
    assert all(t["met"] in (True, False) for t in targets.values())


def check_scale_out(summary: dict) -> None:
    assert summary["config"]["worker_env"]["OMP_NUM_THREADS"] == "1"
    (row,) = summary["results"]
    assert row["n_batches"] == -(-row["members"] // row["batch_size"]) >= 2
    for n in (1, 2):
        entry = row[f"workers_{n}"]
        assert _positive_finite(entry["per_sweep_s"]) and _positive_finite(entry["member_steps_per_second"])
        assert entry["samples_s"] and all(_positive_finite(s) for s in entry["samples_s"])
    q = row["scaling"]
    assert 0 < q["min"] <= q["median"] <= q["max"]
    assert row["stores_identical"] is True  # the same sweep on one worker or two: the same bits


def check_sweep_scaling(summary: dict) -> None:
    methods = ("in_process", "in_process_zarr", "cluster_zarr", "cluster")
    assert summary["config"]["methods"] == list(methods)
    assert summary["config"]["workers"] == 2 and summary["config"]["threads_per_worker"] == 1
    for row in summary["results"]:
        assert row["n_batches"] == -(-row["members"] // row["batch_size"]) >= 2
        for m in methods:
            _check_timed(row[m], ("member_steps_per_second",), m)
        assert set(row["tables_identical_to_in_process"]) == set(methods[1:])
        for q in row["ratios"].values():
            assert 0 < q["min"] <= q["median"] <= q["max"]
    for t in summary["targets"].values():
        assert t["met"] in (True, False) and math.isfinite(t["value"])


def check_euler_sphere(summary: dict) -> None:
    for row in summary["results"]:
        for m in ("ours", "ours_quflow_tol", "ours_real", "numpy"):
            _check_timed(row["timings"][m], ("per_call_s",), m)
            assert _positive_finite(row["seconds_per_step"][m]) and row["sweeps_per_step"][m] >= 1
        # at quflow's sqrt(eps)-relative tolerance: agreement with the round-off run to that level
        assert row["max_difference_of_final_W_quflow_tol_from_ours"] < 1e-8 * row["max_abs_W"]
        # the same scheme but for the weight of the centre of u(N): far below the method's error
        assert row["max_difference_of_final_W"] < 1e-10 * row["max_abs_W"]
        assert row["spectrum_change_ours"] < 1e-12 * row["max_abs_W"]  # isospectral
        for name, q in row["quflow"].items():  # the anchor code, when installed
            _check_timed(row["timings"][name], ("per_call_s",), name)
            # its default stopping rule is sqrt(eps)-relative: agreement to that level only
            limit = 1e-10 if "tight" in name else 1e-8
            assert q["max_difference_of_final_W_from_numpy"] < limit * row["max_abs_W"]
    assert math.isfinite(summary["slopes"]["ours"]) and math.isfinite(summary["slopes"]["numpy"])


def check_complex_products(summary: dict) -> None:
    for row in summary["results"]:
        for m, t in row["timings"].items():
            _check_timed(t, ("per_call_s",), m)
        # the complex product, its four real products and the real form: one product
        assert row["max_difference_between_forms"] < 1e-12 * row["N"]


def check_native(summary):
    """The native benchmark: every part ran, rates positive, the native and XLA sweeps agree."""
    parts = {r["part"] for r in summary["results"]}
    assert parts == {"sweep", "threads", "compile", "vortices"}, parts
    for r in summary["results"]:
        if r["part"] == "sweep":
            for m in ("sweep", "sweep_xla", "jax_by_hand_rows", "numpy_rk4"):
                assert 0 < r[m]["body_steps_per_second"] < float("inf"), m
            assert r["sweep"]["max_abs_final_momentum_diff_vs_xla"] < 1e-12
            assert r["sweep"]["max_energy_error"] == pytest.approx(r["jax_by_hand_rows"]["max_energy_error"], rel=1e-6)
        if r["part"] == "compile":
            assert r["cold"]["first_call_s"] > 0 and r["cached"]["first_call_s"] > 0
        if r["part"] == "vortices":
            assert r["sweep"]["failed_members"] == 0 and r["step_over_rk4_step"]["sweep"] > 0


def check_native_integrate(summary):
    """The single-trajectory benchmark: both backends timed, their Solutions agree."""
    for r in summary["results"]:
        for b in ("native", "xla"):
            assert _positive_finite(r[b]["per_step_s"]), b
        assert r["max_difference_Q"] < 1e-12  # entries of rotations: round-off apart
        assert _positive_finite(r["xla_over_native"]["median"])


def check_native_split(summary):
    """The sweep call's split: the kernel's CPU is part of the call's, every span recorded."""
    for r in summary["results"]:
        one = r["threads=1"]
        assert (
            _positive_finite(one["kernel_cpu"]["min_ms"]) and one["kernel_cpu"]["min_ms"] <= one["call_cpu"]["min_ms"]
        )
        for key in ("before_first_kernel", "after_last_kernel"):
            assert _positive_finite(r["default threads"][key]["median_ms"]), key


CHECKS = {
    "rigid_body_step_cost": check_rigid_body_step_cost,
    "vortex_step_cost": check_vortex_step_cost,
    "throughput": check_throughput,
    "work_precision": check_work_precision,
    "work_precision_clusters": check_work_precision_clusters,
    "work_precision_ensembles": check_work_precision_ensembles,
    "work_precision_sphere": check_work_precision_sphere,
    "work_precision_ceiling": check_work_precision_ceiling,
    "soak": check_soak,
    "defaults": check_defaults,
    "sweep_scaling": check_sweep_scaling,
    "scale_out": check_scale_out,
    "euler_sphere": check_euler_sphere,
    "complex_products": check_complex_products,
    "native": check_native,
    "native_integrate": check_native_integrate,
    "native_split": check_native_split,
}


SCRIPTS = {  # name -> (script, extra arguments)
    "work_precision_clusters": ("work_precision", ["--clusters"]),
    "work_precision_ensembles": ("work_precision", ["--ensembles"]),
    "work_precision_sphere": ("work_precision", ["--sphere-vortices"]),
}


@pytest.mark.slow  # minutes for the seven scripts (benchmarks/README.md): run with -m slow, and in CI
@pytest.mark.parametrize("name", list(CHECKS))
def test_benchmark_quick(name, tmp_path):
    script, extra = SCRIPTS.get(name, (name, []))
    if script == "work_precision":  # diffrax is a benchmark peer only: the optional extra [bench]
        pytest.importorskip("diffrax", reason="work_precision needs diffrax: pip install -e '.[bench]'")
    if name in ("sweep_scaling", "scale_out"):  # Dask and Zarr are the optional extra [sweep]
        pytest.importorskip("distributed", reason=f"{name} needs dask.distributed: pip install -e '.[sweep]'")
        pytest.importorskip("zarr", reason=f"{name} needs zarr: pip install -e '.[sweep]'")
    if name == "work_precision_ceiling":  # heyoka (the [bench] extra) is the peer; callgrind counts
        pytest.importorskip("heyoka", reason="work_precision_ceiling needs heyoka: pip install -e '.[bench]'")
        if shutil.which("valgrind") is None:
            pytest.skip("work_precision_ceiling counts instructions with valgrind's callgrind")
    if name == "scale_out" and shutil.which("taskset") is None:
        pytest.skip("scale_out pins workers with Linux's taskset")
    subprocess.run(
        [sys.executable, str(BENCHMARKS / f"{script}.py"), "--quick", *extra, "--out", str(tmp_path), "--timeout", "0"],
        check=True,
        capture_output=True,
        text=True,
    )

    assert (tmp_path / f"{name}.png").stat().st_size > 0
    summary = json.loads((tmp_path / f"{name}.json").read_text())
    assert {"benchmark", "config", "machine", "results", "total_runtime_s"} <= summary.keys()
    assert summary["benchmark"] == name
    assert summary["config"]["quick"] is True and summary["config"]["jax_disable_most_optimizations"] is True
    for key in ("platform", "cpu_count", "jax", "numpy", "date_utc"):
        assert summary["machine"][key], key
    assert "git_commit" in summary["machine"]
    assert _positive_finite(summary["machine"]["load_average_1min_at_start"] + 1)  # >= 0, recorded
    assert summary["results"]
    CHECKS[name](summary)


C_KERNEL_CHECK = r"""
import sys, numpy as np, jax.numpy as jnp
sys.path.insert(0, sys.argv[1])
import throughput
march, how = throughput.c_kernel()
if march is None:
    print("SKIP", how)
    raise SystemExit(0)
rng = np.random.default_rng(1)
xi0 = rng.normal(size=(37, 3))  # not a multiple of the kernel's lanes
inertia = np.array([0.5, 0.6, 1.0])
mu, err = march(inertia, 0.05, 50, xi0)
mu_h, err_h = (np.asarray(a) for a in throughput.hand_rows_march(inertia, 0.05, 50)(jnp.asarray(xi0)))
print("DIFF", float(np.max(np.abs(mu - mu_h))), float(np.max(np.abs(err - err_h))), float(np.max(err_h)))
"""


def test_the_c_kernel_marches_as_the_hand_kernel():
    # throughput.py's hardware reference (benchmarks/c/rigid_body_cay.c): the same step as
    # hand_rows_march, so the same final momenta and energy errors up to the rounding of a
    # different compiler (contracted multiply-adds); skipped where no C compiler builds it
    out = subprocess.run(
        [sys.executable, "-c", C_KERNEL_CHECK, str(BENCHMARKS)], capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr[-2000:]
    line = out.stdout.strip().splitlines()[-1]
    if line.startswith("SKIP"):
        pytest.skip(line)
    d_mu, d_err, err = (float(v) for v in line.split()[1:])
    assert d_mu < 1e-13 and d_err < 1e-13 and err > 1e-8  # the energy error is O(dt²), far above both


VERIFIED_CHECK = r"""
import sys, numpy as np, jax.numpy as jnp
sys.path.insert(0, sys.argv[1])
import throughput
inertia = np.array([0.5, 0.6, 1.0])
m = np.random.default_rng(2).normal(size=(8, 3))
xi0 = 0.3 * m / np.linalg.norm(m, axis=1, keepdims=True) / inertia  # slow bodies: every check passes
xi0[6] = np.nan  # not finite
xi0[7] = [0.0, 40.0, 40.0]  # dt |omega| ~ 3: the fixed updates do not reach round-off
mu_h, err_h = (np.asarray(a) for a in throughput.hand_rows_march(inertia, 0.05, 50)(jnp.asarray(xi0)))
mu_v, err_v, ok = (np.asarray(a) for a in throughput.hand_rows_march(inertia, 0.05, 50, verified=True)(jnp.asarray(xi0)))
print("VERIFIED", float(np.max(np.abs(mu_v[:6] - mu_h[:6]))), float(np.max(np.abs(err_v[:6] - err_h[:6]))),
      " ".join(str(int(v)) for v in ok))
"""


def test_the_verified_hand_kernel_marches_as_the_hand_kernel_and_flags_failures():
    # throughput.py's yardstick with the sweep's per-step checks written by hand: the same
    # momenta and energy errors as the hand kernel where every check passes, and a member
    # whose solve does not reach round-off or whose values are not finite is flagged
    out = subprocess.run(
        [sys.executable, "-c", VERIFIED_CHECK, str(BENCHMARKS)], capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr[-2000:]
    _, d_mu, d_err, *passed = out.stdout.strip().splitlines()[-1].split()
    # energies from the node's velocity (verified) and from mu alone (hand): round-off apart
    assert float(d_mu) < 1e-13 and float(d_err) < 1e-13
    assert passed == ["1"] * 6 + ["0", "0"], passed
