r"""The run of a built-in scene (`clebsch-jax run SCENE`, `clebsch-jax demo`): the compiled,
vmapped chunk of `integrate`, the chunks and their host-side reductions.

**The run** (`run_scene`): the march goes in chunks of steps, each one call of the same
compiled, vmapped program, continued from the last node's canonical state $(Q^n, p^n)$
(`clebsch_jax.continue_from`: the step is the symplectic map $(Q^n, p^n)\mapsto(Q^{n+1}, p^{n+1})$
of Lemma 20, so the continuation is the same trajectory up to round-off; in the reduced march
$p^n$ is the minimum-norm cotangent with momentum map $\mu^n$).
After every chunk the host keeps, per member, the worst error of every invariant over the
nodes known so far, and, for the plot, the first `PLOT_MEMBERS` members' trajectories and
errors on at most `PLOT_POINTS` nodes; so memory is one chunk, whatever the number of steps.
A failing member is a value: its later nodes are NaN and not counted, its status and first
failing step are reported, the other members run on.

**Errors reported** (max over members and over known nodes $n$, i.e. before any failure):
for a conserved quantity $f$ (`Invariant.kind == "drift"`), $\max_n\|f^n - f^0\|_\infty / s$
with $s$ the invariant's scale at node 0 ($|f^0|$ unless stated, e.g. $\sum_a|p_a|$ for a total
momentum that may vanish); for a quantity that is itself an error (`kind == "error"`, e.g.
$\max|Q^TQ - I|$) its largest value. The energy error is $\max_n |E^n - E^0| / |E^0|$ with
$E$ = `clebsch_jax.diagnostics.energy`.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

import clebsch_jax as cj

from ._scene_report import plot_data, summarise
from ._scene_types import ENERGY, Scene, Setup
from ._scenes import SCENES

__all__ = [
    "run_scene",
    "solve",
    "program",
    "chunk_steps_for",
    "QUICK_COMPILER_OPTIONS",
    "compiler_options_for",
]

PLOT_MEMBERS = 8
"""Members drawn in a scene's plot (the first ones)."""

PLOT_POINTS = 2000
"""At most this many nodes per member are kept for the plots (error envelopes: block maxima)."""

MAX_CHUNKS = 50
"""A long run is cut into at most about this many chunks (progress updates)."""

WORK_PER_CHUNK = 20_000
"""Member-steps per chunk at least (a call's fixed cost is then negligible)."""

NODE_BUDGET = 200_000
"""Member-nodes per chunk at most (bounds the memory of one chunk's `Solution`)."""

QUICK_WORK = 20_000
"""Runs of at most this many member-steps are compiled with XLA's backend optimisation off."""

QUICK_COMPILER_OPTIONS = {"xla_backend_optimization_level": 0}
"""Short runs are dominated by compilation: this shortens it (and slows the steps)."""


# --------------------------------------------------------------------------------------------
# The compiled chunk: integrate under vmap, with the scene's per-node invariants.


def _options_key(options) -> tuple:
    return tuple(sorted((options or {}).items()))


@functools.lru_cache(maxsize=None)
def program(name: str, order: int, n_steps: int, compiler_options: tuple = (), scheme: str | None = None):
    r"""The jitted, vmapped march of `n_steps` steps of scene `name` (cached: one per arguments).

    `program(...)(Q0, xi0, P0, derive_P0, t0, dt)` with a leading member axis on `Q0`, `xi0`,
    `P0` runs `integrate(system, Q0, xi0, P0=P0, t0=t0, dt=dt, n_steps=n_steps, order=order,
    throw=False, **scene.options)` for every member (`scheme`, if given, in place of the
    scene's), with $P^0$ replaced by `initial_multiplier(system, Q0, xi0)` where `derive_P0` (a
    traced bool) is True.

    **Returns** a dict: `sol` (the batched `Solution`), `values` {name: (B, N+1, k)} and
    `scales` {name: (B,)} of the energy and the scene's invariants, `trajectory` (B, N+1, …),
    `known` (B, N+1) (valid nodes with a recovered nodal velocity), and `start`, the
    `clebsch_jax.Start` at the last node to continue from (fields (B, …)).
    """
    scene = SCENES[name]
    system = scene.system()
    invariants = (ENERGY,) + scene.invariants
    options = dict(scene.options)
    if scheme is not None:
        options["scheme"] = scheme

    def one(Q0, xi0, P0, derive_P0, t0, dt):
        P0 = jnp.where(derive_P0, cj.initial_multiplier(system, Q0, xi0), P0)
        # traced (under vmap and jit), where integrate's march is XLA's: asked for by name, so
        # that "auto" does not warn that it cannot run a native kernel here
        sol = cj.integrate(
            system, Q0, xi0, P0=P0, t0=t0, dt=dt, n_steps=n_steps, order=order, throw=False, backend="xla", **options
        )
        values, scales = {}, {}
        for inv in invariants:
            v = jnp.asarray(inv.values(system, sol))
            values[inv.name] = v = v.reshape(v.shape[0], -1)
            scales[inv.name] = (
                jnp.ones((), v.dtype)
                if inv.kind != "drift"
                else inv.scale(system, sol)
                if inv.scale is not None
                else jnp.max(jnp.abs(v[0]))
            )
        known = sol.valid & (sol.nodal_stats.status == cj.Status.SUCCESS)
        return dict(
            sol=sol,
            values=values,
            scales=scales,
            trajectory=scene.trajectory(system, sol),
            known=known,
            start=cj.continue_from(system, sol)._replace(march_state=None),  # one program for every chunk
        )

    mapped = jax.vmap(one, in_axes=(0, 0, 0, 0, None, None))
    return jax.jit(mapped, compiler_options=dict(compiler_options) or None)


def compiler_options_for(batch: int, n_steps: int) -> dict:
    """XLA options of a run: `QUICK_COMPILER_OPTIONS` when it is short (compile-dominated)."""
    return dict(QUICK_COMPILER_OPTIONS) if batch * n_steps <= QUICK_WORK else {}


def chunk_steps_for(batch: int, n_steps: int) -> int:
    """Steps per compiled call: at most ~`MAX_CHUNKS` chunks, at least `WORK_PER_CHUNK`
    member-steps each, at most `NODE_BUDGET` member-nodes (memory); `n_steps` if one call does."""
    chunk = max(-(-n_steps // MAX_CHUNKS), -(-WORK_PER_CHUNK // batch))
    chunk = min(chunk, max(10, NODE_BUDGET // batch))
    return min(chunk, n_steps)


# --------------------------------------------------------------------------------------------
# The run: chunks, host-side reductions, summary, plot.


def _initial_state(setup: Setup):
    """(Q0, xi0, P0, derive_P0) as `program` takes them (P0 zeros where it is derived)."""
    Q = jnp.asarray(setup.Q0)
    derive = setup.P0 is None
    P = jnp.zeros_like(Q) if derive else jnp.asarray(setup.P0)
    return Q, jnp.asarray(setup.xi0), P, jnp.full((Q.shape[0],), derive)


def solve(
    scene: Scene,
    setup: Setup,
    *,
    dt: float,
    n_steps: int,
    order: int | None = None,
    compiler_options=None,
    scheme: str | None = None,
) -> dict:
    """One call of `program` from `setup`'s initial data, $t_0 = 0$ (no chunks): what `run_scene`
    computes first, as the dict `program` returns (its `"sol"` is the batched `Solution`).
    `compiler_options` default as in `run_scene` (the same compiled program)."""
    batch = setup.Q0.shape[0]
    copts = compiler_options_for(batch, n_steps) if compiler_options is None else dict(compiler_options)
    run = program(scene.name, scene.order if order is None else int(order), n_steps, _options_key(copts), scheme)
    return run(*_initial_state(setup), jnp.asarray(0.0, jnp.float64), jnp.asarray(dt, jnp.float64))


class _Binned:
    """Per-member maxima of per-node values over bins of `stride` nodes (plot envelopes)."""

    def __init__(self, members: int, n_nodes: int, stride: int):
        self.stride = stride
        self.data = np.full((members, -(-n_nodes // stride)), -np.inf)

    def add(self, nodes: np.ndarray, values: np.ndarray) -> None:
        bins = nodes // self.stride
        for m in range(self.data.shape[0]):
            np.maximum.at(self.data[m], bins, np.where(np.isnan(values[m]), -np.inf, values[m]))

    def result(self) -> np.ndarray:
        return np.where(np.isfinite(self.data), self.data, np.nan)


def run_scene(
    scene: Scene,
    *,
    dt: float | None = None,
    n_steps: int | None = None,
    order: int | None = None,
    batch: int = 1,
    seed: int = 0,
    chunk_steps: int | None = None,
    compiler_options=None,
    progress: Callable | None = None,
    scheme: str | None = None,
) -> dict:
    r"""Integrate a scene's batch and reduce it to a summary (no files written).

    **Arguments:**

    - `scene`: a `Scene` (e.g. `SCENES["rigid-body"]`).
    - `dt`, `n_steps`, `order`: default the scene's; `scheme`: None (the scene's) or a scheme of
      `integrate` (e.g. "gauss", with an even `order` up to 16).
    - `batch`: members B (member 0 is the canonical one); `seed`: of the other members' draw.
    - `chunk_steps`: steps per compiled call (default `chunk_steps_for(batch, n_steps)`).
    - `compiler_options`: XLA options (default `compiler_options_for(batch, n_steps)`).
    - `progress`: None or `progress(steps_done, n_steps, elapsed_s)`, called before the first
      chunk (0 steps done: compiling) and after every chunk.

    **Returns:** the summary, JSON-serialisable but for its private entry `"_plot"` (NumPy
    arrays for `write_plot`, dropped by `write_summary`): `scene` (name, model, members, seed,
    initial data for B <= 64), `run` (dt, steps, t_final, the `Solution`'s `method`, `form`,
    `scheme`, `order`, `derivative_map`, chunks, compiler options), `errors` (`energy_rel_max`,
    `<invariant>_max`, `reference_max`: maxima over members and known nodes, None if no node is
    known), `invariants` {name: label, kind, max, per_member}, `reference`, `newton_iterations`
    (mean and max updates per step), `failures` (count; member, step, t, status, reason of
    each), `per_member` (status, failed_step: -1 if none), `timing` and `versions`.
    """
    plan = _plan(
        scene,
        dt=dt,
        n_steps=n_steps,
        order=order,
        batch=batch,
        seed=seed,
        chunk_steps=chunk_steps,
        compiler_options=compiler_options,
    )
    setup = scene.setup(batch, np.random.default_rng(seed))
    run = program(scene.name, plan.order, plan.chunk, _options_key(plan.compiler_options), scheme)
    tally = _Tally(scene, setup, plan)
    wall, first_s = _march(run, setup, plan, tally, progress)
    summary = summarise(scene, setup, plan, tally, wall, first_s)
    summary["_plot"] = plot_data(setup, plan, tally)
    return summary


@dataclasses.dataclass(frozen=True)
class _Plan:
    """A run's settings, the scene's defaults filled in."""

    dt: float
    n_steps: int
    order: int  # as requested (the `Solution` says which order ran)
    batch: int
    seed: int
    chunk: int  # steps per compiled call
    n_chunks: int
    compiler_options: dict


def _plan(scene: Scene, *, dt, n_steps, order, batch, seed, chunk_steps, compiler_options) -> _Plan:
    """`run_scene`'s settings: None takes the scene's default, or `chunk_steps_for` and
    `compiler_options_for`; a chunk is at most the whole run."""
    dt = scene.dt if dt is None else float(dt)
    n_steps = scene.steps if n_steps is None else int(n_steps)
    chunk = chunk_steps_for(batch, n_steps) if chunk_steps is None else min(int(chunk_steps), n_steps)
    copts = compiler_options_for(batch, n_steps) if compiler_options is None else dict(compiler_options)
    return _Plan(
        dt=dt,
        n_steps=n_steps,
        order=scene.order if order is None else int(order),
        batch=batch,
        seed=seed,
        chunk=chunk,
        n_chunks=-(-n_steps // chunk),
        compiler_options=copts,
    )


def _march(run, setup: Setup, plan: _Plan, tally: _Tally, progress: Callable | None) -> tuple:
    """Call the compiled chunk `run` `plan.n_chunks` times, each chunk continued from the
    `clebsch_jax.Start` at the last node of the one before, and hand every chunk to `tally`.

    **Returns:** (wall time, time of the first chunk, which includes the compilation), seconds.
    """
    Q, xi, P, derive_P0 = _initial_state(setup)
    t_start = time.perf_counter()
    if progress is not None:
        progress(0, plan.n_steps, 0.0)
    first_s = None
    for c in range(plan.n_chunks):
        offset = c * plan.chunk
        t0 = offset * plan.dt  # on the host, so no round-off accumulates from chunk to chunk
        out = run(Q, xi, P, derive_P0, jnp.asarray(t0, jnp.float64), jnp.asarray(plan.dt, jnp.float64))
        out = jax.block_until_ready(out)
        if first_s is None:
            first_s = time.perf_counter() - t_start
        tally.add(out, offset)
        start = out["start"]
        Q, P, xi = start.Q0, start.P0, start.xi0
        derive_P0 = jnp.zeros((plan.batch,), bool)
        if progress is not None:
            progress(min(offset + plan.chunk, plan.n_steps), plan.n_steps, time.perf_counter() - t_start)
    return time.perf_counter() - t_start, first_s


class _Tally:
    """What the host keeps of a run, chunk after chunk, so that memory is one chunk whatever the
    number of steps: per member the worst error of every invariant and against the reference
    over the known nodes, the first failure, the Newton updates; for the first `PLOT_MEMBERS`
    members the errors' envelopes (`_Binned`) and the trajectory at every `stride`-th node; and
    the facts of the `Solution` (method, form, ...)."""

    def __init__(self, scene: Scene, setup: Setup, plan: _Plan):
        self.scene, self.setup, self.n_steps, self.chunk = scene, setup, plan.n_steps, plan.chunk
        self.invariants = (ENERGY,) + scene.invariants
        batch, n_nodes = plan.batch, plan.n_steps + 1
        self.n_plot = min(batch, PLOT_MEMBERS)
        self.stride = max(1, -(-n_nodes // PLOT_POINTS))
        self.errors_binned = {inv.name: _Binned(self.n_plot, n_nodes, self.stride) for inv in self.invariants}
        self.ref_binned = _Binned(self.n_plot, n_nodes, self.stride) if scene.reference else None
        self.worst = {inv.name: np.full(batch, -np.inf) for inv in self.invariants}
        self.ref_worst = np.full(batch, -np.inf)
        self.traj_nodes, self.traj_pieces = [], []
        self.status = np.zeros(batch, np.int64)
        self.failed_step = np.full(batch, -1, np.int64)
        self.iter_sum, self.iter_count, self.iter_max = 0, 0, 0
        self.ref0 = self.scale0 = self.facts = None

    def add(self, out: dict, offset: int) -> None:
        """Take in one chunk (what `program` returns) whose node 0 is the run's node `offset`."""
        sol = out["sol"]
        if self.facts is None:
            self.facts = dict(
                method=sol.method,
                form=sol.form,
                scheme=sol.scheme,
                order=int(sol.order),
                derivative_map=sol.derivative_map,
            )
        # nodes of this chunk kept: 0 only in the first chunk (later it is the previous end), and
        # none past n_steps (the last chunk may run over)
        lo, hi = (0 if offset == 0 else 1), min(self.chunk, self.n_steps - offset)
        keep = slice(lo, hi + 1)
        nodes = offset + np.arange(lo, hi + 1)
        known = np.asarray(out["known"])[:, keep]
        self._add_invariants(out, nodes, known, keep)
        traj = np.asarray(out["trajectory"][: None if self.scene.reference is not None else self.n_plot])[:, keep]
        if self.scene.reference is not None:
            self._add_reference(np.asarray(sol.ts)[0, keep], traj, nodes, known)
        self._add_trajectory(traj, nodes, known)
        self._add_newton(sol, hi)
        self._add_failures(sol, offset)

    def _add_invariants(self, out: dict, nodes, known, keep: slice) -> None:
        """Per node the drift of each conserved quantity from node 0 of the run, relative to its
        scale there (or the value of an error quantity): worst per member, and plot envelopes."""
        values = {k: np.asarray(v)[:, keep] for k, v in out["values"].items()}
        if self.ref0 is None:  # the first chunk: its node 0 is the run's
            self.ref0 = {k: v[:, 0] for k, v in values.items()}
            self.scale0 = {k: np.asarray(v) for k, v in out["scales"].items()}
        for inv in self.invariants:
            v = values[inv.name]
            if inv.kind == "drift":
                err = np.max(np.abs(v - self.ref0[inv.name][:, None]), axis=-1)
                err = err / np.maximum(np.abs(self.scale0[inv.name]), np.finfo(float).tiny)[:, None]
            else:
                err = np.max(v, axis=-1)
            err = np.where(known, err, np.nan)
            worst = np.nanmax(np.where(known, err, -np.inf), axis=-1)
            self.worst[inv.name] = np.fmax(self.worst[inv.name], worst)
            self.errors_binned[inv.name].add(nodes, err[: self.n_plot])

    def _add_reference(self, ts, traj, nodes, known) -> None:
        """Every member's error against the scene's exact solution at the known nodes."""
        rerr = np.where(known, self.scene.reference(self.setup.members, ts, traj), np.nan)
        self.ref_worst = np.fmax(self.ref_worst, np.max(np.where(known, rerr, -np.inf), axis=-1))
        self.ref_binned.add(nodes, rerr[: self.n_plot])

    def _add_trajectory(self, traj, nodes, known) -> None:
        """The plotted members' trajectories at every `stride`-th node and the last (NaN where
        not known)."""
        pick = (nodes % self.stride == 0) | (nodes == self.n_steps)
        self.traj_nodes.append(nodes[pick])
        mask = known[: self.n_plot, pick]
        mask = mask.reshape(mask.shape + (1,) * (traj.ndim - 2))
        self.traj_pieces.append(np.where(mask, traj[: self.n_plot][:, pick], np.nan))

    def _add_newton(self, sol, n: int) -> None:
        """Newton updates per step (summed over a composition's sub-steps) of the chunk's first
        `n` steps, attempted steps only."""
        st = np.asarray(sol.stats.status)[:, :n]
        it = np.asarray(sol.stats.iterations)[:, :n]
        tried = st != cj.Status.SKIPPED
        self.iter_sum += int(np.sum(it[tried]))
        self.iter_count += int(np.sum(tried))
        self.iter_max = max(self.iter_max, int(np.max(it[tried], initial=0)))

    def _add_failures(self, sol, offset: int) -> None:
        """The first failure of each member, in the run's steps (a failure past n_steps does not
        count)."""
        result = np.asarray(sol.result)
        local = np.asarray(sol.failed_step)
        last = self.n_steps - offset + (result == cj.Status.LEGENDRE)  # a node failure may be at node n_steps
        new = (self.status == cj.Status.SUCCESS) & (result != cj.Status.SUCCESS) & (local < last)
        self.status = np.where(new, result, self.status)
        self.failed_step = np.where(new, offset + local, self.failed_step)
