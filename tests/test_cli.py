"""The `clebsch-jax` command line and the Figure 1 demo (`clebsch-jax demo --quick`).

Fast: one quick demo run in-process (~10 s, mostly compilation) and one subprocess.
"""

import json
import subprocess
import sys

import pytest

from clebsch_jax._cli import main


def _one_line_error(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


def test_help_at_every_level(capsys):
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    assert "demo" in out
    assert main(["demo", "--help"]) == 0
    out = capsys.readouterr().out
    for option in ("--out", "--steps", "--quick"):
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
        ["frobnicate"],
        [],
    ],
)
def test_bad_command_lines_exit_2_with_one_line(argv, capsys):
    assert main(argv) == 2
    captured = capsys.readouterr()
    line = _one_line_error(captured.err)
    assert "error" in line
    assert captured.out == ""


def test_out_must_not_be_a_file(tmp_path, capsys):
    target = tmp_path / "taken"
    target.write_text("not a folder")
    assert main(["demo", "--quick", "--out", str(target)]) == 2
    assert "not a folder" in _one_line_error(capsys.readouterr().err)


def test_missing_matplotlib_is_one_line(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # makes `import matplotlib` fail
    assert main(["demo", "--quick", "--out", str(tmp_path / "demo")]) == 1
    assert 'pip install "clebsch-jax[plot]"' in _one_line_error(capsys.readouterr().err)


def test_python_dash_m_bad_steps():
    proc = subprocess.run(
        [sys.executable, "-m", "clebsch_jax", "demo", "--steps", "-1"],
        capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 2
    assert "--steps" in _one_line_error(proc.stderr)
    assert proc.stdout == ""


def test_quick_demo(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--quick", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    for row in ("energy error", "Casimir", "spatial momentum drift", "orthogonality error",
                "Newton iterations/step", "steps/s", "compile + first call", str(out)):
        assert row in printed

    for name in ("figure1_orbits.png", "figure1_invariants.png"):
        data = (out / name).read_bytes()
        assert data.startswith(b"\x89PNG\r\n\x1a\n") and len(data) > 10_000
    summary = json.loads((out / "summary.json").read_text())

    errors = summary["errors"]
    assert 0.0 < errors["energy_rel_max"] < 1e-2
    assert errors["spatial_momentum_drift_rel_max"] < 1e-11
    assert errors["casimir_rel_max"] < 1e-11
    assert errors["orthogonality_max"] < 1e-11
    assert summary["scene"]["inertia"] == [0.5, 0.6, 1.0] and summary["scene"]["dt"] == 0.1
    assert 3 <= summary["newton_iterations"]["mean"] <= summary["newton_iterations"]["max"] <= 20
    assert summary["timing"]["steps_per_s"] > 0
    # The discrete period agrees with the exact (elliptic-integral) one to O(dt^2).
    measured = [o for o in summary["orbits"] if o["period_measured"] is not None]
    assert measured
    for orbit in measured:
        assert orbit["period_measured"] == pytest.approx(orbit["period_exact"], rel=0.03)
