"""The `clebsch-jax` command line: `demo` (Figure 1 and every scene), `run SCENE`, `bench`.

Compilation dominates. The `demo --quick` fixture compiles every scene program (each with its
`quick_steps` and `quick_batch`, XLA optimisation off); the tests that use it are slow-marked
(CI also runs the full demo). The default run's `run` tests compile only the scenes they run,
once each: same scene, steps per call, batch and compiler options; `dt` is traced, so the
failing run (huge dt) and the chunked run (`--chunk` = the quick steps) share one program. Numbers in the JSON are checked against the `Solution` of that program (`_scene_run.solve`)
with `clebsch_jax.diagnostics`, and against exact solutions where there are some.
"""

import contextlib
import io
import json
import subprocess
import sys
import textwrap

import jax
import numpy as np
import pytest

import clebsch_jax as cj
from clebsch_jax.cli import _bench_command, _commands, _progress, _scene_run, _scenes, main
from clebsch_jax.cli._scenes import SCENES

from .test_epdiff import two_peakons_exact  # an independent closed form, checked against DOP853 there

PNG = b"\x89PNG\r\n\x1a\n"


def _one_line_error(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


def _main_captured(argv):
    """`main(argv)` with stdout and stderr captured (for module-scoped fixtures)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    return code, out.getvalue(), err.getvalue()


def _png_ok(path) -> bool:
    data = path.read_bytes()
    return data.startswith(PNG) and len(data) > 10_000


# --------------------------------------------------------------------------------------------
# Help and bad command lines (cheap: nothing is compiled).


def test_help_at_every_level(capsys):
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    for command in ("demo", "run", "bench"):
        assert command in out
    assert main(["demo", "--help"]) == 0
    out = capsys.readouterr().out
    for option in ("--out", "--steps", "--quick", "--only"):
        assert option in out
    assert main(["run", "--help"]) == 0
    out = capsys.readouterr().out
    for option in ("--dt", "--steps", "--order", "--batch", "--seed", "--out", "--chunk", "--progress", "--quiet"):
        assert option in out
    for name, scene in SCENES.items():
        assert name in out and scene.description in out
    assert main(["bench", "--help"]) == 0
    out = capsys.readouterr().out
    for option in ("--quick", "--list", "--out", "NAME"):
        assert option in out
    assert main(["--version"]) == 0


@pytest.mark.parametrize(
    "argv",
    [
        ["demo", "--steps", "-3"],
        ["demo", "--steps", "0"],
        ["demo", "--steps=2.5"],
        ["demo", "--steps", "lots"],
        ["demo", "--bogus"],
        ["demo", "--only", "teapot"],
        ["frobnicate"],
        [],
        ["run"],
        ["run", "teapot"],
        ["run", "peakons", "--dt", "0"],
        ["run", "peakons", "--dt", "-0.1"],
        ["run", "peakons", "--dt", "fast"],
        ["run", "peakons", "--dt", "nan"],
        ["run", "peakons", "--dt", "inf"],
        ["run", "peakons", "--order", "3"],
        ["run", "peakons", "--order", "4.0"],
        ["run", "peakons", "--order", "18"],
        ["run", "peakons", "--order", "12"],  # an order of Gauss only, without --scheme gauss
        ["run", "peakons", "--scheme", "trapezoid"],
        ["run", "peakons", "--batch", "0"],
        ["run", "peakons", "--batch", "two"],
        ["run", "peakons", "--batch", str(_commands.MAX_BATCH + 1)],
        ["run", "peakons", "--steps", "0"],
        ["run", "peakons", "--seed", "-1"],
        ["run", "peakons", "--chunk", "0"],
        ["run", "peakons", "--bogus"],
        ["bench", "--bogus"],
    ],
)
def test_bad_command_lines_exit_2_with_one_line(argv, capsys):
    assert main(argv) == 2
    captured = capsys.readouterr()
    line = _one_line_error(captured.err)
    assert "error" in line
    assert captured.out == ""


def test_unknown_scene_lists_the_known_ones(capsys):
    assert main(["run", "double-pendulum"]) == 2
    line = _one_line_error(capsys.readouterr().err)
    assert "double-pendulum" in line
    assert all(name in line for name in SCENES)
    assert main(["run", "rigid_body", "--help"]) == 0  # underscores are accepted for dashes


@pytest.mark.parametrize("command", [["demo", "--quick"], ["run", "peakons"]])
def test_out_must_not_be_a_file(command, tmp_path, capsys):
    target = tmp_path / "taken"
    target.write_text("not a folder")
    assert main(command + ["--out", str(target)]) == 2
    assert "not a folder" in _one_line_error(capsys.readouterr().err)


@pytest.mark.parametrize("command", [["demo", "--quick"], ["run", "peakons"]])
def test_missing_matplotlib_is_one_line(command, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # makes `import matplotlib` fail
    assert main(command + ["--out", str(tmp_path / "out")]) == 1
    assert 'pip install "clebsch-jax[plot]"' in _one_line_error(capsys.readouterr().err)


def test_python_dash_m_bad_steps():
    proc = subprocess.run(
        [sys.executable, "-m", "clebsch_jax", "demo", "--steps", "-1"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert "--steps" in _one_line_error(proc.stderr)
    assert proc.stdout == ""


def _interrupt(argv, after: float = 0.0):
    """`python -m clebsch_jax ARGV`, sent SIGINT `after` seconds past the moment it maps jaxlib's
    extension (inside `import jax`, the first seconds of every command): (exit code, stderr)."""
    import os
    import signal
    import time

    if not os.path.exists("/proc/self/maps"):
        pytest.skip("needs Linux's /proc to see when JAX is being imported")
    proc = subprocess.Popen(
        [sys.executable, "-m", "clebsch_jax", *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        deadline = time.monotonic() + 120
        while proc.poll() is None and time.monotonic() < deadline:
            try:
                with open(f"/proc/{proc.pid}/maps") as f:
                    if "jaxlib" in f.read():
                        break
            except OSError:
                pass
            time.sleep(0.002)
        time.sleep(after)
        assert proc.poll() is None, proc.communicate()[1][-2000:]
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
        proc.wait()
    return proc.returncode, err


def test_ctrl_c_while_jax_is_imported_exits_with_130_and_one_line(tmp_path):
    """Issue 40: a Ctrl-C in the first fraction of a second (JAX being imported) was swallowed by
    a callback of jaxlib's, crashed its initialisation or printed a traceback of the import."""
    code, err = _interrupt(["run", "heavy-top", "--steps", "200000", "--out", str(tmp_path / "out")])
    assert code == 130 and _one_line_error(err) == "clebsch-jax: interrupted"


@pytest.mark.parametrize(
    "argv, cli",
    [
        (["python", "-m", "clebsch_jax", "run"], True),
        (["python", "-X", "importtime", "-W", "ignore", "-m", "clebsch_jax.cli", "sweep"], True),
        (["python", "/usr/local/bin/clebsch-jax", "demo"], True),
        (["python", "script.py", "-m", "clebsch_jax"], False),  # a program's own arguments
        (["python", "-c", "import clebsch_jax", "-m", "clebsch_jax"], False),
        (["python", "-m", "pytest", "-m", "slow"], False),
        (["python"], False),
    ],
)
def test_only_the_command_line_takes_ctrl_c_while_starting(argv, cli):
    """The start-up guard (exit at once on SIGINT) is for the command line's processes only: a
    program importing the package keeps its own Ctrl-C."""
    from clebsch_jax import _startup

    assert _startup._is_cli(argv) is cli


@pytest.mark.slow
@pytest.mark.parametrize("after", [0.05, 0.3, 1.0, 3.0])
def test_ctrl_c_at_any_moment_of_the_start_exits_with_130_and_one_line(after, tmp_path):
    """From JAX's import through the first compilations: the command's own KeyboardInterrupt
    handling, or the start-up guard, and never an interrupt lost in a callback."""
    code, err = _interrupt(["run", "heavy-top", "--steps", "200000", "--out", str(tmp_path / "out")], after)
    # an interrupt after the run has started follows its progress lines (stderr is not a
    # terminal here, so each update is a line of its own): the error itself is one line
    rest = "\n".join(line for line in err.splitlines() if not line.startswith("heavy-top ["))
    assert code == 130 and _one_line_error(rest) == "clebsch-jax: interrupted"


SWEEP_CONFIG = """
model = "rigid_body"
dt = 0.05
n_steps = 200000
batch_size = 2

[params]
values = [[2.0, 1.0, 0.6]]

[initial]
Q0 = {identity = 3}
xi0 = {normal = [4, 3], seed = 1}
"""


@pytest.mark.slow
@pytest.mark.parametrize("after", [0.05, 0.3])
def test_ctrl_c_at_the_start_of_a_sweep_exits_with_130_and_one_line(after, tmp_path):
    """Variant of the issue's case on the other long command, `sweep` into a store: interrupted
    while JAX is imported or the sweep starts, it exits with 130 and one line (the start-up
    guard's, or the sweep's own, which says how to resume), never a swallowed interrupt."""
    config = tmp_path / "sweep.toml"
    config.write_text(SWEEP_CONFIG)
    code, err = _interrupt(["sweep", str(config), "--store", str(tmp_path / "s.zarr"), "--quiet"], after)
    rest = [line for line in err.splitlines() if not line.startswith("clebsch-jax sweep: 4 members")]
    assert code == 130 and "Traceback" not in err, err[-2000:]
    assert len(rest) == 1 and rest[0] in (
        "clebsch-jax: interrupted",
        f"clebsch-jax sweep: stopped; the finished batches are in {tmp_path / 's.zarr'}: run the same command to resume",
    ), err


def test_help_does_not_import_matplotlib():
    script = textwrap.dedent("""
        import sys
        from clebsch_jax.cli import main
        codes = [main(argv) for argv in (["--help"], ["demo", "--help"], ["run", "--help"], ["bench", "--help"])]
        print(codes, "matplotlib" in sys.modules)
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip().splitlines()[-1] == "[0, 0, 0, 0] False"


def test_progress_bar_one_line_on_a_terminal_and_tenths_in_a_log():
    stream = io.StringIO()
    bar = _progress.ProgressBar("scene", stream=stream, tty=False)
    for done in range(0, 1001, 10):  # 0: before the first (compiling) call
        bar(done, 1000, done / 100)
    bar.close()
    lines = stream.getvalue().splitlines()
    assert len(lines) == 11 and "\r" not in stream.getvalue()
    assert lines[0].endswith("compiling...")
    assert lines[-1].startswith("scene [" + "#" * 28 + "] 100% 1,000/1,000 steps")
    assert "s left" in lines[len(lines) // 2]  # an estimate once the first (compiling) call is past
    stream = io.StringIO()
    bar = _progress.ProgressBar("scene", stream=stream, tty=True)
    bar(500, 1000, 1.0)
    bar(1000, 1000, 2.0)
    bar.close()
    text = stream.getvalue()
    assert text.count("\n") == 1 and text.endswith("\n") and text.count("\r") == 2


# --------------------------------------------------------------------------------------------
# bench: the scripts are found next to the package; a fake folder stands in for running them
# (the real scripts' quick runs are tests/test_benchmarks_smoke.py).


def test_bench_list_names_every_script(capsys):
    assert main(["bench", "--list"]) == 0
    out = capsys.readouterr().out
    folder = _bench_command._benchmarks_dir()
    expected = sorted(p.stem for p in folder.glob("*.py") if not p.name.startswith("_"))
    assert {"rigid_body_step_cost", "vortex_step_cost", "throughput", "work_precision"} <= set(expected)
    lines = {line.split()[0]: line for line in out.strip().splitlines()}
    assert list(lines) == expected
    for name in ("rigid_body_step_cost", "vortex_step_cost", "throughput", "work_precision"):
        assert len(lines[name].split()) > 3, name  # with the first line of its docstring


def test_bench_unknown_name_exit_2_lists_names(capsys):
    assert main(["bench", "rigid_body_step_cost", "warp_drive"]) == 2
    captured = capsys.readouterr()
    line = _one_line_error(captured.err)
    assert "warp_drive" in line and "rigid_body_step_cost" in line and "work_precision" in line
    assert captured.out == ""


def test_bench_without_the_folder_is_one_line_exit_1(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(_bench_command, "_benchmarks_dir", lambda: tmp_path / "benchmarks")
    assert main(["bench", "--list"]) == 1
    assert "clone" in _one_line_error(capsys.readouterr().err)


def test_bench_runs_scripts_with_this_python_passing_quick_and_out(tmp_path, capsys, monkeypatch):
    folder = tmp_path / "benchmarks"
    folder.mkdir()
    record = tmp_path / "calls.txt"
    for name, code in (("alpha", 0), ("beta", 3)):
        (folder / f"{name}.py").write_text(
            f'"""{name} benchmark."""\nimport json, os, sys\nopen({str(record)!r}, "a").write(\n'
            f'    json.dumps([sys.executable, os.path.basename(__file__)] + sys.argv[1:]) + "\\n")\n'
            f"sys.exit({code})\n"
        )
    (folder / "_helper.py").write_text("raise SystemExit('not a benchmark')\n")
    monkeypatch.setattr(_bench_command, "_benchmarks_dir", lambda: folder)
    out_dir = tmp_path / "results"
    assert main(["bench", "alpha", "--quick", "--out", str(out_dir)]) == 0
    called = json.loads(record.read_text().splitlines()[-1])
    assert called == [sys.executable, "alpha.py", "--quick", "--out", str(out_dir)]
    capsys.readouterr()
    assert main(["bench", "--out", str(out_dir)]) == 1  # all (not _helper), beta fails
    calls = [json.loads(line)[1] for line in record.read_text().splitlines()[1:]]
    assert calls == ["alpha.py", "beta.py"]
    captured = capsys.readouterr()
    assert "beta" in _one_line_error(captured.err) and "FAILED (exit code 3)" in captured.out


# --------------------------------------------------------------------------------------------
# demo --quick: the Figure 1 scene, then every scene (compiles every program the run tests use).


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo") / "demo"
    code, printed, err = _main_captured(["demo", "--quick", "--out", str(out)])
    return code, printed, err, out


@pytest.mark.slow  # the quick demo runs every scene (CI also runs the full demo)
def test_quick_demo(demo):
    code, printed, err, out = demo
    assert code == 0, err
    for row in (
        "energy error",
        "Casimir",
        "spatial momentum drift",
        "orthogonality error",
        "Newton iterations/step",
        "steps/s",
        "compile + first call",
        str(out),
    ):
        assert row in printed

    for name in ("figure1_orbits.png", "figure1_invariants.png"):
        assert _png_ok(out / name)
    summary = json.loads((out / "summary.json").read_text())

    errors = summary["errors"]
    assert 0.0 < errors["energy_rel_max"] < 1e-2
    assert errors["spatial_momentum_drift_rel_max"] < 1e-11
    assert errors["casimir_rel_max"] < 1e-11
    assert errors["orthogonality_max"] < 1e-11
    assert summary["scene"]["inertia"] == [0.5, 0.6, 1.0] and summary["scene"]["dt"] == 0.1
    # a solve to round-off makes one update to converge and one to confirm (a fresh Jacobian at
    # every step of the Cayley march: 2.1 on average here), fewer only from an exact guess
    assert 1.5 <= summary["newton_iterations"]["mean"] <= summary["newton_iterations"]["max"] <= 20
    assert summary["timing"]["steps_per_s"] > 0
    # The discrete period agrees with the exact (elliptic-integral) one to O(dt^2).
    measured = [o for o in summary["orbits"] if o["period_measured"] is not None]
    assert measured
    for orbit in measured:
        assert orbit["period_measured"] == pytest.approx(orbit["period_exact"], rel=0.03)


@pytest.mark.slow  # the quick demo runs every scene (CI also runs the full demo)
def test_quick_demo_runs_every_scene_into_a_subfolder(demo, tmp_path):
    code, printed, err, out = demo
    assert code == 0, err
    table = printed[printed.index("Built-in scenes") :].splitlines()
    assert table[1].split()[:2] == ["scene", "method"]
    rows = {line.split()[0]: line for line in table[2:]}
    assert list(rows) == ["figure-1", *SCENES]
    for name, scene in SCENES.items():
        summary = json.loads((out / name / "summary.json").read_text())
        assert summary["scene"]["name"] == name and summary["failures"]["count"] == 0
        assert summary["run"]["n_steps"] == scene.quick_steps and summary["scene"]["members"] == scene.quick_batch
        assert _png_ok(out / name / f"{name}.png")
        assert f"{summary['errors']['energy_rel_max']:.2e}" in rows[name]
        # `run` of the scene repeats the demo's run (same data, same compiled program).
        assert _run_quick(name, tmp_path / name) == 0
        assert json.loads((tmp_path / name / "summary.json").read_text())["errors"] == summary["errors"]


def test_demo_only_one_scene(tmp_path, capsys):
    out = tmp_path / "only"
    assert main(["demo", "--only", "rigid-body", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "Figure 1" not in printed and not (out / "summary.json").exists()
    rows = printed[printed.index("Built-in scenes") :].splitlines()[2:]
    assert [r.split()[0] for r in rows] == ["rigid-body"]
    assert sorted(p.name for p in out.iterdir()) == ["rigid-body"]
    assert _png_ok(out / "rigid-body" / "rigid-body.png")
    summary = json.loads((out / "rigid-body" / "summary.json").read_text())
    assert summary["run"]["n_steps"] == SCENES["rigid-body"].quick_steps  # the demo's short run


# --------------------------------------------------------------------------------------------
# run SCENE: the JSON against the Solution, the mathematics of each scene.


def _solution(name, *, dt=None):
    scene = SCENES[name]
    setup = scene.setup(scene.quick_batch, np.random.default_rng(0))
    out = _scene_run.solve(scene, setup, dt=scene.dt if dt is None else dt, n_steps=scene.quick_steps)
    return scene, setup, out["sol"]


def _energy(scene, sol):
    """`cj.diagnostics.energy` at every node of every member (jitted: one small compile instead
    of an op-by-op run of its autodiff)."""
    system = scene.system()
    return np.asarray(jax.jit(lambda s: cj.diagnostics.energy(system, s))(sol))


def _independent_invariants(name, setup, sol):
    """Each scene's conserved quantities from the Solution, written here from their formulas:
    {name: (values (B, N+1, k), scale (B,))}."""
    mu, Q = np.asarray(sol.momentum), None if sol.Q is None else np.asarray(sol.Q)
    if name == "rigid-body":
        c = np.sum(mu**2, -1)[..., None]
        return {"casimir": (c, c[:, 0, 0])}
    if name == "heavy-top":
        gamma = Q[..., 2, :]  # Γ = Qᵀe₃
        return {"gamma_norm": (np.abs(np.linalg.norm(gamma, axis=-1) - 1)[..., None], None)}
    if name == "vortices":
        G = np.asarray(_scenes.VORTEX_CIRCULATIONS)
        lin = np.einsum("a,bnai->bni", G, Q)
        ang = np.einsum("a,bna->bn", G, np.sum(Q**2, -1))[..., None]
        return {
            "linear_impulse": (lin, np.sum(np.abs(G) * np.linalg.norm(Q[:, 0], axis=-1), -1)),
            "angular_impulse": (ang, np.sum(np.abs(G) * np.sum(Q[:, 0] ** 2, -1), -1)),
        }
    if name == "peakons":
        return {"total_momentum": (mu.sum(-1)[..., None], np.abs(mu[:, 0]).sum(-1))}
    if name == "landmarks":
        ang = np.sum(Q[..., 0] * mu[..., 1] - Q[..., 1] * mu[..., 0], -1)[..., None]
        return {
            "linear_momentum": (mu.sum(-2), np.linalg.norm(mu[:, 0], axis=-1).sum(-1)),
            "angular_momentum": (ang, np.sum(np.linalg.norm(Q[:, 0], axis=-1) * np.linalg.norm(mu[:, 0], axis=-1), -1)),
        }
    if name == "euler-sphere":  # the spectrum of the vorticity matrix W (isospectral march)
        # the default (unitary) form: μ = 2(Re W + Im W), Re W antisymmetric, Im W symmetric
        mt = np.swapaxes(mu, -1, -2)
        W = 0.25 * (mu - mt) + 0.25j * (mu + mt)
        spectra = np.linalg.eigvalsh(1j * W)
        return {"spectrum": (spectra, np.max(np.abs(spectra[:, 0]), axis=-1))}
    raise AssertionError(name)


# Peakons, landmarks and the fluid compile the largest scene programs: slow-marked (CI runs them).
RUN_CASES = [
    pytest.param(n, marks=pytest.mark.slow) if n in ("peakons", "landmarks", "euler-sphere", "vortices") else n
    for n in SCENES
]  # the slow scenes each compile a program of their own; the rigid body and heavy top keep the command's path


def _run_quick(name, out):
    scene = SCENES[name]
    argv = ["run", name, "--steps", str(scene.quick_steps), "--batch", str(scene.quick_batch), "--out", str(out)]
    return main([*argv, "--quiet"])


@pytest.mark.parametrize("name", RUN_CASES)
def test_run_scene_writes_files_and_its_json_matches_the_solution(name, tmp_path, capsys):
    scene = SCENES[name]
    out = tmp_path / name
    assert _run_quick(name, out) == 0
    captured = capsys.readouterr()
    assert captured.err == ""  # --quiet: no bar, no status line
    for row in (
        "method",
        "steps",
        "wall time",
        "energy error (max rel.)",
        "Newton iterations/step",
        "failures",
        *(inv.label for inv in scene.invariants),
    ):
        assert row in captured.out, row
    assert _png_ok(out / f"{name}.png")
    summary = json.loads((out / "summary.json").read_text())
    assert summary["files"] == [f"{name}.png", "summary.json"]

    _, setup, sol = _solution(name)
    B, n = scene.quick_batch, scene.quick_steps
    run = summary["run"]
    assert run["method"] == sol.method and run["form"] == sol.form and run["order"] == sol.order == 2
    assert run["n_steps"] == n and run["dt"] == scene.dt and run["chunks"] == 1
    assert summary["scene"]["members"] == B and summary["failures"]["count"] == 0
    assert summary["per_member"]["status"] == [0] * B and np.all(np.asarray(sol.result) == 0)

    # The energy error is what cj.diagnostics.energy gives on the Solution. Inside and outside
    # jit (and batched or not: the peakons' Cholesky is LAPACK for one matrix, XLA operations for
    # a batch) the energies may differ in the last bits, ~1e-16 of E, so the relative errors
    # agree to an absolute 1e-14 (1e-7 of the smallest error here, ~1e-7).
    E = _energy(scene, sol)
    assert E.shape == (B, n + 1)
    rel = np.max(np.abs(E - E[:, :1]) / np.abs(E[:, :1]), axis=1)
    np.testing.assert_allclose(summary["invariants"]["energy"]["per_member"], rel, rtol=0, atol=1e-14)
    assert summary["errors"]["energy_rel_max"] == pytest.approx(rel.max(), rel=0, abs=1e-14)
    # bounded at O(dt^2) at the scenes' steps (measured 5e-7 to 1.1e-4), never at round-off
    assert 1e-9 < summary["errors"]["energy_rel_max"] < 1e-3

    iters = np.asarray(sol.stats.iterations)
    assert summary["newton_iterations"]["mean"] == pytest.approx(iters.mean(), rel=1e-12)
    assert summary["newton_iterations"]["max"] == iters.max()

    # Discrete Noether / Casimirs: conserved to round-off (measured <= 2.4e-14 over 600 steps).
    for inv in scene.invariants:
        assert summary["errors"][f"{inv.name}_max"] < 1e-13, inv.name
    for key, (values, scale) in _independent_invariants(name, setup, sol).items():
        err = np.max(np.abs(values - values[:, :1]), axis=(1, 2))
        err = err if scale is None else err / scale
        assert np.max(err) < 1e-13, key

    if name == "peakons":  # every member is an exact two-peakon solution
        m = summary["scene"]["initial"]
        ts = np.asarray(sol.ts)[0]
        err = []
        for b in range(B):
            q_ex, p_ex = two_peakons_exact(ts, m["c1"][b], m["c2"][b], m["t0"][b], m["X0"][b])
            err.append(np.max(np.abs(np.asarray(sol.Q[b]) - q_ex)))
            np.testing.assert_allclose(np.asarray(sol.momentum[b, 0]), p_ex[0], rtol=1e-13)  # P0 given
        np.testing.assert_allclose(summary["reference"]["per_member"], err, rtol=1e-9)
        assert summary["errors"]["reference_max"] < 1e-4  # second order at dt = 0.02 over t = 6


def test_failing_member_is_reported_with_its_step_and_exit_1(tmp_path, capsys):
    """dt = 10 on the rigid body: some member fails; the others run on. (The scene's traced
    march makes the first-step check: at dt = 10 member 1's first step is far from the node two
    half steps reach, `Status.FIRST_STEP` at step 0, and the other three pass; at dt >= 20 most
    members fail it.)"""
    scene = SCENES["rigid-body"]
    out = tmp_path / "fail"
    code = main(
        [
            "run",
            "rigid-body",
            "--dt",
            "10",
            "--steps",
            str(scene.quick_steps),
            "--batch",
            str(scene.quick_batch),
            "--out",
            str(out),
            "--quiet",
        ]
    )
    captured = capsys.readouterr()
    _, _, sol = _solution("rigid-body", dt=10.0)
    result, failed_step = np.asarray(sol.result), np.asarray(sol.failed_step)
    failing = np.flatnonzero(result != 0)
    assert 1 <= len(failing) < scene.quick_batch  # the test needs a failing and a surviving member
    assert code == 1
    line = _one_line_error(captured.err)
    first = int(failing[0])
    assert f"member {first} at step {failed_step[first]}" in line and "--dt" in line
    assert f"{len(failing)} of {scene.quick_batch} members failed" in captured.out
    summary = json.loads((out / "summary.json").read_text())
    assert summary["per_member"]["failed_step"] == [int(s) if r else -1 for r, s in zip(result, failed_step)]
    assert [f["member"] for f in summary["failures"]["members"]] == failing.tolist()
    assert _png_ok(out / "rigid-body.png")  # partial trajectories are still drawn
    # the nodes before the failure still conserve the Casimir, the survivors all the way
    assert summary["errors"]["casimir_max"] < 1e-13
    assert all(x is not None for x in summary["invariants"]["casimir"]["per_member"])


def test_chunked_run_continues_the_march_with_a_progress_bar(tmp_path, capsys):
    """Three calls of the demo's compiled 400-step program (the last one cut at 1000 steps),
    each continued from the last node's (Q, p). A wrong hand-over would break the spatial
    angular momentum, a function of (Q, p), at the chunk boundaries."""
    scene = SCENES["rigid-body"]
    out = tmp_path / "chunks"
    assert (
        main(
            [
                "run",
                "rigid-body",
                "--steps",
                "1000",
                "--chunk",
                str(scene.quick_steps),
                "--batch",
                str(scene.quick_batch),
                "--out",
                str(out),
                "--progress",
            ]
        )
        == 0
    )
    captured = capsys.readouterr()
    bar = captured.err.strip().splitlines()
    assert bar[-1].startswith("rigid-body [" + "#" * 28 + "] 100% 1,000/1,000 steps")
    assert len(bar) == 4  # compiling, then one line per chunk (stderr is not a terminal here)
    assert bar[0].endswith("0/1,000 steps, 0.0 s, compiling...")
    summary = json.loads((out / "summary.json").read_text())
    assert summary["run"]["chunks"] == 3 and summary["run"]["steps_per_chunk"] == scene.quick_steps
    assert summary["run"]["t_final"] == pytest.approx(1000 * scene.dt)
    assert summary["errors"]["spatial_momentum_max"] < 1e-13
    assert summary["errors"]["casimir_max"] < 1e-13
    # The energy error stays bounded (no jump at a boundary): within 1.5x of the first 400 steps'.
    _, _, sol = _solution("rigid-body")
    E = _energy(scene, sol)
    first = np.max(np.abs(E - E[:, :1]) / np.abs(E[:, :1]))
    assert first <= summary["errors"]["energy_rel_max"] < 1.5 * first


def test_scheme_and_order_lists_are_the_documented_ones():
    """`--scheme` and `--order` take the engine's public tables (`cj.SCHEMES`, `cj.COMPOSITIONS`,
    `cj.GAUSS_ORDERS`); the help text and the CLI reference (docs/cli.md) name these values."""
    assert _commands.SCHEMES == cj.SCHEMES + ("gauss",) == ("left", "right", "midpoint", "gauss")
    assert _commands.ORDERS == (2, 4, 6, 8)
    assert _commands.GAUSS_ORDERS == cj.GAUSS_ORDERS == tuple(range(2, 17, 2))


def test_scheme_a_system_refuses_is_one_line_exit_2(tmp_path, capsys):
    """The degenerate vortices have no left/right principle: integrate refuses it while tracing,
    before anything is compiled, and the CLI says so in one line."""
    code = main(["run", "vortices", "--scheme", "left", "--steps", "10", "--out", str(tmp_path / "x"), "--quiet"])
    assert code == 2
    line = _one_line_error(capsys.readouterr().err)
    assert "--scheme left on vortices" in line and "degenerate" in line


@pytest.mark.slow  # CI runs it; compiles the Gauss march of a scene; the scenes' default runs are checked by the demo fixture
def test_run_with_gauss_keeps_the_impulses_and_is_more_accurate(tmp_path, capsys):
    """`--scheme gauss --order 8` on the leapfrogging vortices: the summary records the
    Gauss-Legendre method; both impulses at round-off and H far closer than the default order-2
    midpoint run at the same dt (measured 3e-14 against 1e-5 relative at dt 0.1)."""
    out = tmp_path / "gauss"
    args = ["run", "vortices", "--dt", "0.1", "--steps", "200", "--batch", "2", "--quiet"]
    assert main(args + ["--scheme", "gauss", "--order", "8", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    run = summary["run"]
    assert run["scheme"] == "gauss" and run["order"] == 8 and "Gauss-Legendre" in run["method"]
    assert run["derivative_map"] == "none (collocation)"  # Gauss takes Q' from its collocation polynomial
    assert summary["failures"]["count"] == 0
    assert summary["errors"]["linear_impulse_max"] < 1e-13 and summary["errors"]["angular_impulse_max"] < 1e-13
    assert main(args + ["--out", str(tmp_path / "midpoint")]) == 0
    mid = json.loads((tmp_path / "midpoint" / "summary.json").read_text())
    assert mid["run"]["scheme"] == "midpoint" and mid["run"]["order"] == 2
    assert summary["errors"]["energy_rel_max"] < 1e-6 * mid["errors"]["energy_rel_max"]
