"""`enable_compilation_cache`: a second process loads the compiled march instead of compiling
it, and computes the same numbers to the bit. Runs in subprocesses, since the cache is a
process-wide JAX setting (conftest switches the command line's cache off for the other tests).
No timing is asserted: that the cache saves time is measured by `benchmarks/throughput.py`."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

import clebsch_jax as cj
from clebsch_jax.cli import _commands, _setup

SCRIPT = r"""
import json, sys
import jax
import numpy as np
counts = {"hits": 0, "misses": 0}
def listen(event, **kwargs):
    if event == "/jax/compilation_cache/cache_hits":
        counts["hits"] += 1
    elif event == "/jax/compilation_cache/cache_misses":
        counts["misses"] += 1
jax.monitoring.register_event_listener(listen)
import clebsch_jax as cj
from clebsch_jax.models import rigid_body
if sys.argv[1] != "off":
    cj.enable_compilation_cache(sys.argv[1])
sol = cj.integrate(rigid_body((2.0, 1.0, 2.0 / 3.0)), np.eye(3), np.array([0.5, 0.1, 0.8]), dt=0.05, n_steps=50)
print(json.dumps({"counts": counts, "xi": [float(x).hex() for x in np.ravel(sol.xi)],
                  "Q": [float(x).hex() for x in np.ravel(sol.Q)]}))
"""


def _run(cache: str) -> dict:
    env = dict(os.environ)
    env.pop("CLEBSCH_JAX_NO_CACHE", None)
    proc = subprocess.run([sys.executable, "-c", SCRIPT, cache], capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.slow  # CI runs it; two processes, each compiling a march
def test_second_process_loads_the_compiled_march_and_matches_to_the_bit(tmp_path):
    cache = tmp_path / "xla"
    first, second, uncached = _run(str(cache)), _run(str(cache)), _run("off")
    # (the first process may hit its own entries: some small programs are compiled twice)
    assert first["counts"]["misses"] > 0
    assert any(cache.iterdir()), "nothing was written to the cache directory"
    # every program the second process needed was on disk
    assert second["counts"]["hits"] >= 1 and second["counts"]["misses"] == 0, second["counts"]
    for key in ("xi", "Q"):
        assert first[key] == second[key] == uncached[key], key


def test_bad_arguments_are_refused_before_touching_jax(tmp_path):
    a_file = tmp_path / "file"
    a_file.write_text("not a directory")
    with pytest.raises(ValueError, match="`directory`.*not a directory"):
        cj.enable_compilation_cache(a_file)
    with pytest.raises(TypeError, match="`directory` must be a path"):
        cj.enable_compilation_cache(3)
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="`min_compile_time`"):
            cj.enable_compilation_cache(tmp_path, min_compile_time=bad)
    with pytest.raises(TypeError, match="`min_compile_time`"):
        cj.enable_compilation_cache(tmp_path, min_compile_time=True)
    import jax

    # unchanged in this process (the test run keeps no persistent cache, tests/conftest.py)
    assert jax.config.jax_compilation_cache_dir is None


def test_default_directory_follows_the_environment(monkeypatch, tmp_path):
    from clebsch_jax.core.compilation_cache import default_cache_directory

    monkeypatch.setenv("CLEBSCH_JAX_CACHE_DIR", str(tmp_path / "mine"))
    assert default_cache_directory() == tmp_path / "mine"
    monkeypatch.delenv("CLEBSCH_JAX_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert default_cache_directory() == tmp_path / "xdg" / "clebsch-jax" / "xla"


class _Args:
    def __init__(self, no_cache):
        self.no_cache = no_cache


def test_command_line_switch(monkeypatch, capsys):
    """The command line enables the cache unless --no-cache or CLEBSCH_JAX_NO_CACHE; a cache it
    cannot use is reported and the run goes on."""
    calls = []
    monkeypatch.setattr(cj, "enable_compilation_cache", lambda: calls.append(1))
    monkeypatch.delenv("CLEBSCH_JAX_NO_CACHE", raising=False)
    _setup.use_compilation_cache(_Args(no_cache=False), "clebsch-jax run")
    _setup.use_compilation_cache(_Args(no_cache=True), "clebsch-jax run")
    monkeypatch.setenv("CLEBSCH_JAX_NO_CACHE", "1")
    _setup.use_compilation_cache(_Args(no_cache=False), "clebsch-jax run")
    assert calls == [1]

    def refuse():
        raise ValueError("enable_compilation_cache: `directory` '/x' is not writable")

    monkeypatch.setattr(cj, "enable_compilation_cache", refuse)
    monkeypatch.delenv("CLEBSCH_JAX_NO_CACHE")
    _setup.use_compilation_cache(_Args(no_cache=False), "clebsch-jax run")
    assert "compiling without the cache" in capsys.readouterr().err
    for command in ("run", "demo"):
        args = _commands._build_parser().parse_args(
            [command, "rigid-body", "--no-cache"] if command == "run" else [command, "--no-cache"]
        )
        assert args.no_cache
