"""Kernels found without tracing: the fingerprint of what a program is made from
(`clebsch_jax.native.fingerprint`) names it on disk, and what changes the program changes the key.

A changed closure constant, function body, default or global value must miss the cache (a
stale kernel would compute another model); an unchanged configuration in a fresh process must
find its kernel, and the checks that passed, without tracing anything.
"""

import json
import os
import re
import subprocess
import sys
import textwrap
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import clebsch_jax as cj
from clebsch_jax.native import compile_member
from clebsch_jax.native.fingerprint import fingerprint

pytest.importorskip("llvmlite")

MODEL = """
import jax.numpy as jnp
from jax.tree_util import Partial
import clebsch_jax as cj

OFFSET = {offset}


def kinetic(inertia, xi):
    return {body}


def velocity(xi, Q):
    return Q @ cj.lie.hat(xi)


def factory(scale):
    def make_system(inertia):
        return cj.ClebschSystem(
            lagrangian=Partial(kinetic, scale * inertia),
            velocity_map=velocity,
            derivative_map=cj.cayley,
            check_Q=cj.models.check_rotation,
        )

    return make_system
"""
BODY = "0.5 * jnp.sum(inertia * jnp.square(xi)) + OFFSET"
OTHER_BODY = "0.5 * jnp.sum(inertia * xi**2) + OFFSET"  # the same number, another jaxpr (integer_pow)


def _model(body=BODY, offset=0.0, name="user_model"):
    """A user's module (its functions' globals are its namespace, as a script's would be)."""
    module = types.ModuleType(name)
    exec(compile(MODEL.format(body=body, offset=offset), f"<{name}>", "exec"), module.__dict__)
    return module


def test_the_fingerprint_reads_code_closures_defaults_and_globals():
    """Equal for an equal function made again; different for a changed closure constant,
    default, global value read (directly or by a helper it calls) and function body."""
    m = _model()
    assert fingerprint(m.factory(1.0)) == fingerprint(m.factory(1.0)) == fingerprint(_model().factory(1.0))
    assert fingerprint(m.factory(1.0)) != fingerprint(m.factory(2.0))  # closure constant
    assert fingerprint(m.kinetic) != fingerprint(_model(body=OTHER_BODY).kinetic)  # body
    assert fingerprint(m.kinetic) != fingerprint(_model(offset=1.0).kinetic)  # global value
    # a helper's global, reached through the function that calls it
    namespace = {"__name__": "user_script", "jnp": jnp, "A": np.ones(3)}
    exec("def helper(x):\n    return A * x\n\ndef f(x):\n    return helper(x) + 1.0\n", namespace)
    before = fingerprint(namespace["f"])
    namespace["A"] = np.array([1.0, 1.0, 1.0 + 2**-52])  # one bit of one entry
    assert fingerprint(namespace["f"]) != before

    def with_default(x, c=2.0):
        return c * x

    def with_other_default(x, c=3.0):
        return c * x

    assert fingerprint(with_default) != fingerprint(with_other_default)
    # a library function is named, its closures and defaults read: the same object twice is equal
    assert fingerprint(cj.models.rigid_body) == fingerprint(cj.models.rigid_body) is not None


def test_the_fingerprint_refuses_what_it_cannot_read():
    """An object of a user class, a user module read by attribute and a tracer: None (the
    caller then traces, as without a key)."""

    class Settings:
        scale = 2.0

    settings = Settings()
    assert fingerprint(lambda x: settings.scale * x) is None
    user_module = types.ModuleType("user_helpers")
    namespace = {"__name__": "user_script", "helpers": user_module}
    exec("def f(x):\n    return helpers.g(x)\n", namespace)
    assert fingerprint(namespace["f"]) is None
    seen = []
    jax.jit(lambda x: seen.append(fingerprint(lambda y: x * y)) or x)(1.0)
    assert seen == [None]


def test_a_kernel_named_by_its_key_loads_without_a_trace_and_what_changes_it_misses(tmp_path, monkeypatch):
    """`compile_member(..., key=fingerprint(f))`: the same function made again loads its kernel
    from the disk without tracing; a changed closure constant or body is traced and compiled
    again, and computes its own numbers."""
    monkeypatch.setenv("CLEBSCH_JAX_NATIVE_CACHE", str(tmp_path))

    def make(c, square):
        def f(x):
            return jnp.sin(c * jnp.square(x)) if square else jnp.sin(c * x * x)

        return f

    x = np.linspace(-1.0, 1.0, 16)
    first = compile_member(make(2.0, True), x[0], key=fingerprint(make(2.0, True)))
    assert not first.from_record
    traced = jax.make_jaxpr

    def no_trace(*a, **k):
        raise AssertionError("traced")

    monkeypatch.setattr(jax, "make_jaxpr", no_trace)
    again = compile_member(make(2.0, True), x[0], key=fingerprint(make(2.0, True)))
    assert again.from_record and again.kernel.key == first.kernel.key
    np.testing.assert_array_equal(again(x), first(x))
    monkeypatch.setattr(jax, "make_jaxpr", traced)
    for other in (make(3.0, True), make(2.0, False)):  # a closure constant, a body
        miss = compile_member(other, x[0], key=fingerprint(other))
        assert not miss.from_record and miss.kernel.key != first.kernel.key
        np.testing.assert_allclose(miss(x), jax.vmap(other)(x), rtol=1e-15, atol=0)


def _fresh_process(monkeypatch):
    """Forget what this process compiled, traced and checked, as a new process would."""
    from clebsch_jax.batching import backends, choose, chunks_native, probe

    monkeypatch.setattr(backends, "_PROGRAMS", {})
    monkeypatch.setattr(choose, "_COMPILED", {})
    monkeypatch.setattr(probe, "_TRACES", {})
    monkeypatch.setattr(probe, "_PASSED", {})
    monkeypatch.setattr(probe, "_FINGERPRINTS", {})
    monkeypatch.setattr(probe, "_SYSTEMS", {})
    monkeypatch.setattr(chunks_native, "_DISK_KEYS", {})


def _members(n=8):
    rng = np.random.default_rng(3)
    return rng.uniform(0.5, 3.0, size=(n, 3)), np.broadcast_to(np.eye(3), (n, 3, 3)), rng.standard_normal((n, 3))


RUN = dict(dt=0.05, n_steps=20, backend="native")


@pytest.mark.slow  # compiles two sweep kernels; test_a_kernel_named_by_its_key_loads_without_a_trace_and_what_changes_it_misses
# and test_a_kept_configuration_check_misses_on_changed_values_and_a_changed_check cover the keys in the default run
def test_a_sweep_from_the_disk_cache_traces_and_checks_nothing_and_a_changed_model_misses(tmp_path, monkeypatch):
    """A user's model swept once; then, with the in-process caches forgotten, the same sweep
    neither traces (no `make_jaxpr`, no `eval_shape`) nor runs `integrate`'s value checks,
    and gives the same table to the bit; with a changed closure constant it traces again and
    gives that model's table."""
    from clebsch_jax.batching import backends, probe

    monkeypatch.setenv("CLEBSCH_JAX_NATIVE_CACHE", str(tmp_path))
    model, (inertias, Q0, omegas) = _model(), _members()
    _fresh_process(monkeypatch)
    first = cj.sweep(model.factory(1.0), inertias, Q0, omegas, **RUN)
    assert [p.from_record for p in backends._PROGRAMS.values()] == [False]

    _fresh_process(monkeypatch)
    traced = {}
    for where, name in ((jax, "make_jaxpr"), (jax, "eval_shape"), (probe, "_check_member_eagerly")):
        traced[(where, name)] = getattr(where, name)
        monkeypatch.setattr(where, name, lambda *a, _n=name, **k: pytest.fail(f"{_n} ran on the cached path"))
    again = cj.sweep(_model().factory(1.0), inertias, Q0, omegas, **RUN)  # the model's module made again
    assert [p.from_record for p in backends._PROGRAMS.values()] == [True]
    for key in ("status", "final_Q", "final_p", "final_momentum", "energy_error", "newton_iterations"):
        np.testing.assert_array_equal(getattr(again, key), getattr(first, key))

    for (where, name), fn in traced.items():
        monkeypatch.setattr(where, name, fn)
    _fresh_process(monkeypatch)
    doubled = cj.sweep(model.factory(2.0), inertias, Q0, omegas, **RUN)
    assert [p.from_record for p in backends._PROGRAMS.values()] == [False]
    assert not np.allclose(doubled.final_momentum, first.final_momentum)
    xla = cj.sweep(model.factory(2.0), inertias, Q0, omegas, **{**RUN, "backend": "xla"})
    np.testing.assert_allclose(doubled.final_momentum, xla.final_momentum, rtol=1e-12, atol=1e-14)


CHECKED = """
import numpy as np
import clebsch_jax as cj

LIMIT = {limit}
CALLS = []


def check(Q):
    CALLS.append(1)
    return None if np.max(np.abs(np.asarray(Q))) <= LIMIT else "an entry past LIMIT"


def make_system(inertia):
    rigid = cj.models.rigid_body(inertia)
    return cj.ClebschSystem(
        lagrangian=rigid.lagrangian, velocity_map=rigid.velocity_map, derivative_map=cj.cayley, check_Q=check
    )
"""


class _Checked(Exception):
    """Raised right after a sweep's checks of its members: nothing is compiled."""


def test_a_kept_configuration_check_misses_on_changed_values_and_a_changed_check(tmp_path, monkeypatch):
    """The check of every Q0 is kept once it passed (per fingerprint of the configuration and
    digest of the values checked): the same call does not run it again, and the same sweep
    with one Q0 a reflection, or with a model whose check's global is changed so that it
    fails, raises as a first call would."""
    from clebsch_jax.batching import probe

    monkeypatch.setenv("CLEBSCH_JAX_NATIVE_CACHE", str(tmp_path))
    _fresh_process(monkeypatch)
    monkeypatch.setattr(probe, "warn_isotropic_xi0", lambda *a: (_ for _ in ()).throw(_Checked()))
    inertias, Q0, omegas = _members()
    with pytest.raises(_Checked):
        cj.sweep(cj.models.rigid_body, inertias, Q0, omegas, **RUN)
    flipped = np.array(Q0)
    flipped[3, :, 0] *= -1.0
    with pytest.raises(ValueError, match=r"Q0\[3\].*reflection"):
        cj.sweep(cj.models.rigid_body, inertias, flipped, omegas, **RUN)

    def module(limit):
        m = types.ModuleType("checked_model")
        exec(compile(CHECKED.format(limit=limit), "<checked_model>", "exec"), m.__dict__)
        return m

    m = module(2.0)
    for _ in range(2):
        with pytest.raises(_Checked):
            cj.sweep(m.make_system, inertias, Q0, omegas, **RUN)
        assert len(m.CALLS) == len(Q0)  # each Q0 once, by the first call
    # the model's module made again with the check's global changed (in a process, as for the
    # member's program, a function object is taken as the code it was when first fingerprinted)
    with pytest.raises(ValueError, match=r"Q0\[0\]: an entry past LIMIT"):
        cj.sweep(module(0.5).make_system, inertias, Q0, omegas, **RUN)


_CHILD = """
import json, sys, types
import numpy as np
import jax
import clebsch_jax as cj
from clebsch_jax.batching import backends, probe

body, scale, forbid = sys.argv[1], float(sys.argv[2]), sys.argv[3] == "1"
module = types.ModuleType("user_model")
exec(compile(MODEL.format(body=body, offset=0.0), "<user_model>", "exec"), module.__dict__)
ran = []
if forbid:
    for where, name in ((jax, "make_jaxpr"), (jax, "eval_shape"), (probe, "_check_member_eagerly")):
        setattr(where, name, lambda *a, _n=name, **k: ran.append(_n))
rng = np.random.default_rng(3)
inertias, omegas = rng.uniform(0.5, 3.0, size=(8, 3)), rng.standard_normal((8, 3))
try:
    res = cj.sweep(module.factory(scale), inertias, np.broadcast_to(np.eye(3), (8, 3, 3)), omegas,
                   dt=0.05, n_steps=20, backend="native")
    out = res.final_momentum.tolist()
except Exception as err:  # a forbidden call that broke the run
    out = repr(err)
print(json.dumps({"from_record": [p.from_record for p in backends._PROGRAMS.values()], "ran": ran, "out": out}))
"""


@pytest.mark.slow  # three fresh processes, each importing JAX; the test above covers the same in-process
def test_fresh_processes_hit_the_disk_cache_without_tracing_and_miss_on_a_changed_body(tmp_path):
    env = {**os.environ, "CLEBSCH_JAX_NATIVE_CACHE": str(tmp_path)}
    script = f"MODEL = {MODEL!r}\n" + textwrap.dedent(_CHILD)

    def child(body, scale, forbid):
        out = subprocess.run(
            [sys.executable, "-c", script, body, str(scale), "1" if forbid else "0"],
            env=env,
            capture_output=True,
            text=True,
            check=True,
        )
        return json.loads(out.stdout.strip().splitlines()[-1])

    cold = child(BODY, 1.0, False)
    assert cold["from_record"] == [False]
    warm = child(BODY, 1.0, True)
    assert warm == {"from_record": [True], "ran": [], "out": cold["out"]}
    other = child(OTHER_BODY, 1.0, False)  # the same numbers from another jaxpr: traced and compiled
    assert other["from_record"] == [False]
    np.testing.assert_allclose(other["out"], cold["out"], rtol=1e-13, atol=1e-15)


_REFUSED_CHILD = """
import json, sys
import jax.numpy as jnp
import numpy as np
import clebsch_jax as cj

def zero_moment_body(inertia):  # no constructor check: only integrate's checks refuse a zero moment
    return cj.ClebschSystem(lagrangian=lambda xi: 0.5 * jnp.sum(inertia * xi**2),
                            velocity_map=lambda xi, Q: Q @ cj.lie.hat(xi), derivative_map=cj.cayley)

make, Q = {"rigid_body": (cj.models.rigid_body, 2.0 * np.eye(3)), "zero_moment": (zero_moment_body, np.eye(3))}[sys.argv[1]]
params = np.array([[2.0, 1.0, 0.5 if sys.argv[1] == "rigid_body" else 0.0]] * 2)
said = {}
for backend in ("xla", "native"):
    try:
        cj.sweep(make, params, np.broadcast_to(Q, (2, 3, 3)), np.tile([0.3, 0.1, 1.0], (2, 1)), dt=0.05, n_steps=4,
                 backend=backend)
    except ValueError as err:
        said[backend] = str(err)
print(json.dumps(said))
"""


# two fresh processes, each importing JAX and compiling the first member's checks;
# tests/test_first_step_check.py and tests/test_model_checks.py check by default that a refused
# sweep with backend="native" stops before any native work
@pytest.mark.slow
@pytest.mark.parametrize(
    "case, match", [("rigid_body", r"rotation"), ("zero_moment", r"rejected by integrate's checks: lagrangian")]
)
def test_a_refused_native_sweep_writes_no_kernel_and_says_what_xla_says(case, match, tmp_path):
    """A sweep that `integrate`'s checks refuse (Q0 not a rotation: a check of values only; a
    degenerate Lagrangian) is refused with backend="native" in XLA's words, and leaves no kernel
    (object code, its record, a refusal for its size) in the disk cache — also none written
    after the refusal, by work left running (the process has ended when the cache is read)."""
    env = {**os.environ, "CLEBSCH_JAX_NATIVE_CACHE": str(tmp_path)}
    out = subprocess.run(
        [sys.executable, "-c", _REFUSED_CHILD, case], env=env, capture_output=True, text=True, check=True
    )
    said = json.loads(out.stdout.strip().splitlines()[-1])
    assert set(said) == {"xla", "native"}, said
    assert re.search(match, said["native"]) and said["native"] == said["xla"], said
    kept = [name for _, _, names in os.walk(tmp_path) for name in names]
    assert not [name for name in kept if name.endswith((".o", ".member", ".refused"))], kept


def test_a_kept_refusal_keeps_no_traceback_and_is_raised_again_without_compiling():
    """`compiled_once` keeps a refusal so that the program is not translated again; the kept
    exception must never hold a traceback, whose frames reach the callers' frames and values (a
    long run in chunks that fell back kept every chunk's Solution alive until memory ran out):
    each call raises a new copy, and the kept one stays without a traceback."""
    import threading

    from clebsch_jax.native import TooLarge, compiled_once

    cache, lock, compiles, raised = {}, threading.Lock(), [], []

    def refuse():
        compiles.append(1)
        raise TooLarge("a program of more than 60000 entries", entries=60001)

    for _ in range(3):
        with pytest.raises(TooLarge, match="more than 60000 entries") as info:
            compiled_once(cache, lock, 8, "key", refuse)
        raised.append(info.value)
        assert info.value.entries == 60001
        assert info.value is not cache["key"]  # the caller's exception, with the caller's traceback
        assert cache["key"].__traceback__ is None  # the kept one holds no frames
    assert len(compiles) == 1  # raised again from the cache, not compiled again
    assert len({id(e) for e in raised}) == 3


def test_a_kept_refusal_keeps_no_traceback_where_exceptions_pickle_theirs():
    """tblib's pickling support (installed by importing dask.distributed, as a Dask sweep does)
    makes a copy of an exception carry its traceback: the kept refusal must not."""
    import threading

    pickling_support = pytest.importorskip("tblib.pickling_support")
    from clebsch_jax.native import TooLarge, compiled_once

    class Refusal(TooLarge):  # a class of its own: the installed pickling stays on it alone
        pass

    pickling_support.install(Refusal)

    def refuse():
        raise Refusal("a program of more than 60000 entries", entries=60001)

    cache = {}
    with pytest.raises(Refusal):
        compiled_once(cache, threading.Lock(), 8, "key", refuse)
    assert cache["key"].__traceback__ is None and cache["key"].entries == 60001


def test_one_kernel_serves_every_n_steps_and_chunk_length(tmp_path, monkeypatch):
    """The native kernel takes a chunk's steps as an argument: sweeps of other `n_steps` and
    `chunk_steps` (a short last chunk included) compile one kernel, and a run cut into chunks
    makes the steps of the unbroken run — the same state, momentum, iterations and statuses to
    the bit (node energies at a chunk's start are evaluated again: `drift` may move in its last
    bit) — and agrees with XLA."""
    from clebsch_jax.batching import backends
    from clebsch_jax.native import kernel

    monkeypatch.setenv("CLEBSCH_JAX_NATIVE_CACHE", str(tmp_path))
    _fresh_process(monkeypatch)
    compiled, real = [], kernel.compile_ir
    monkeypatch.setattr(kernel, "compile_ir", lambda text: compiled.append(1) or real(text))
    inertias, Q0, omegas = _members()
    run = lambda n, **k: cj.sweep(cj.models.rigid_body, inertias, Q0, omegas, **{**RUN, "n_steps": n, **k})  # noqa: E731
    whole, chunked = run(23), run(23, chunk_steps=5)
    shorter = run(9)
    assert len(compiled) == 1 and len(backends._PROGRAMS) == 1
    assert whole.chunk_steps == 23 and chunked.chunk_steps == 5
    for key in ("status", "failed_step", "final_Q", "final_p", "final_momentum", "final_xi", "newton_iterations"):
        np.testing.assert_array_equal(getattr(whole, key), getattr(chunked, key))
    xla = run(9, backend="xla")
    np.testing.assert_allclose(shorter.final_momentum, xla.final_momentum, rtol=1e-12, atol=1e-14)
    np.testing.assert_array_equal(shorter.status, xla.status)
