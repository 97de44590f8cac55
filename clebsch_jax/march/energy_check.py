r"""The energy of the nodes and the march's per-step energy check (`ENERGY_STEP_RTOL`): a step
fails with `Status.ENERGY_JUMP` when it changes $E = \langle\delta l/\delta\xi, \xi\rangle - l$
by more than a fraction of the energy's size so far — on a whole run's records (`energy_jump`,
NumPy or traced) or one step at a time (`jump_step`, as a sweep's per-member program checks)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..roots.status import Status

__all__ = [
    "ENERGY_STEP_RTOL",
    "energy_rtol",
    "energy_terms",
    "node_energies",
    "node_energy",
    "energy_jump",
    "zero_nan",
    "jump_step",
]


ENERGY_STEP_RTOL = 0.1
r"""The energy check (`check_energy`), a per-step error indicator: step n fails with
`Status.ENERGY_JUMP` when it changes the energy $E = \langle\delta l/\delta\xi, \xi\rangle - l$ by
more than this fraction of the energy's size so far,

$$ |E^{n+1} - E^n| > \texttt{ENERGY\_STEP\_RTOL}\;\max_{k \le n}
\bigl(|\langle\delta l/\delta\xi, \xi^k\rangle| + |l(\xi^k, Q^k)|\bigr) . $$

The exact flow conserves E, and a step of a convergent method of order p changes it by
$O(\Delta t^{p+1})$ relative to the sizes of its two terms, so $|E^{n+1} - E^n|$ over that size
is the step's own relative error in the one quantity the march can check for free. A step that
changes E by a tenth of its terms does not resolve the motion: it crossed a singularity of the
model (Newton found a root on the far side, in one step or in a few growing ones, as a particle
falling into a $1/r$ potential with the left principle does), or it is far too large for the
motion there. Runs that resolve their motion, even coarsely (the rigid body with the Cayley step
at steps of a large fraction of its period, an eccentric Kepler orbit with the first-order left
principle), stay far below it, and a particle that crosses a $1/r$ singularity with the left or
right principle exceeds it within a step or two of the crossing (`tests/test_step_error.py`).
The size is taken up to the node the step leaves, not the one it arrives at: a spurious root
near a singularity arrives where l is huge. It is the size of the energy's terms as written: a
constant added to l makes the check looser. It is the default: `check_energy=` a positive
number takes that fraction instead (`energy_rtol`)."""


def energy_rtol(check_energy) -> float | None:
    """The energy check's tolerance that `check_energy` asks for: True `ENERGY_STEP_RTOL`, a
    positive finite number that fraction, False None (no check). Anything else is refused,
    naming the argument."""
    if isinstance(check_energy, (bool, np.bool_)):
        return ENERGY_STEP_RTOL if check_energy else None
    if not isinstance(check_energy, (int, float, np.integer, np.floating)):
        raise TypeError(
            f"check_energy: expected True, False or a positive tolerance, got {type(check_energy).__name__}."
        )
    rtol = float(check_energy)
    if np.isfinite(rtol) and rtol > 0:
        return rtol
    raise ValueError(
        "check_energy: expected True, False or a positive finite tolerance (the largest energy change "
        f"of a step as a fraction of the energy's size so far; True means {ENERGY_STEP_RTOL}), got {check_energy!r}."
    )


def energy_terms(system, Q, xi):
    r"""The two terms of the energy $E = \langle \delta l/\delta\xi, \xi\rangle - l(\xi, Q)$ at one
    node: (the pairing, $l$). At a nodal velocity $\delta l/\delta\xi$ is the node's momentum
    (Lemma 7), so $E$ is the Hamiltonian of Lemma 8 there."""
    lval, g = jax.value_and_grad(lambda y: system.l(y, Q))(xi)
    return jnp.sum(g * xi), lval


def node_energies(system, Qs, xis):
    r"""The energy $E^n$ at every node (`energy_terms`) and its size
    $|\langle\delta l/\delta\xi, \xi^n\rangle| + |l(\xi^n, Q^n)|$, for the energy check. Read
    from the nodal velocities alone: the momenta are not needed (a program that does not
    return them never stores them)."""
    return jax.vmap(lambda q, x: node_energy(system, q, x))(Qs, xis)


def node_energy(system, Q, xi):
    """`node_energies` at one node: (E, its size)."""
    pairing, lagrangian = energy_terms(system, Q, xi)
    return pairing - lagrangian, jnp.abs(pairing) + jnp.abs(lagrangian)


def _running_max(a):
    """max(a[0], …, a[n]) for every n (NumPy), NaN entries counting as 0."""
    return np.maximum.accumulate(np.where(np.isnan(a), 0.0, a))


def energy_jump(xp, energy, size, status, largest=0.0, size_max=0.0, rtol=ENERGY_STEP_RTOL):
    """The first step that fails the energy check (tolerance `rtol`) before any other
    failure, and whether there is one, for nodes `energy`, `size` (`node_energies`) and steps
    `status`. Non-finite energies (after a failure, or at a node whose velocity was not
    recovered) are not compared. `largest` and `size_max` are the running maxima of the steps'
    changes and the nodes' sizes before these (a run checked in pieces, as `sweep` does; the
    largest change is carried for the sweep's records, the rule reads only the sizes); returned
    with the jump are their values after these steps: (jumped, step, largest, size_max).

    On NumPy arrays the running maxima are vectorised; traced, the check is one scan over the
    steps (XLA's cumulative max and sum on CPU, associative scans, cost several times more)."""
    change = xp.abs(energy[1:] - energy[:-1])
    if xp is np and not np.any(change > rtol * np.fmax(size_max, size[:-1])):
        # no step fails even against its own node's size, which its running maximum only
        # raises (fmax: a NaN size counts as 0): no jump, and the maxima are plain reductions
        # (the running ones below cost most of a long native run's assembly)
        return (
            np.False_,
            np.int64(0),
            np.maximum(largest, np.fmax.reduce(change, initial=0.0)),
            np.maximum(size_max, np.fmax.reduce(size, initial=0.0)),
        )
    if xp is np:
        running_change, running_size = _running_max(change), _running_max(size)
        size_before = np.maximum(size_max, running_size[:-1])
        jumped = change > rtol * size_before
        jumped = jumped & (np.cumsum(status != Status.SUCCESS) == 0)  # before any other failure
        return (
            np.any(jumped),
            np.argmax(jumped),
            np.maximum(largest, running_change[-1]),
            np.maximum(size_max, running_size[-1]),
        )

    def step(c, x):
        largest, size_max, clean, first, n = c
        d, s, st = x
        clean = clean & (st == Status.SUCCESS)
        largest, size_max, jumped = jump_step(largest, size_max, d, s, rtol)
        jumped = clean & jumped
        first = jnp.where(jumped & (first < 0), n, first)
        return (largest, size_max, clean, first, n + 1), None

    dtype = change.dtype
    init = (
        jnp.asarray(largest, dtype),
        jnp.asarray(size_max, dtype),
        jnp.asarray(True),
        jnp.asarray(-1, jnp.int32),
        jnp.asarray(0, jnp.int32),
    )
    (largest, size_max, _, first, _), _ = jax.lax.scan(step, init, (change, size[:-1], status))
    return first >= 0, jnp.maximum(first, 0), largest, jnp.maximum(size_max, zero_nan(size[-1]))


def zero_nan(a):
    """a with NaN made 0 (a size or change the running maxima of the energy check skip)."""
    return jnp.where(jnp.isnan(a), 0.0, a)


def jump_step(largest, size_max, change, size=None, rtol=ENERGY_STEP_RTOL):
    """One step of the energy check (tolerance `rtol`): (running largest change, running
    largest size after the step, whether the step failed it), for the step's energy change and
    the size at the node it leaves (`node_energies`); `size_max` holds the sizes of the nodes
    before that one — or, with `size` None, already that node's too (a march that takes each
    node's size into the maximum as it reaches the node)."""
    if size is not None:
        size_max = jnp.maximum(size_max, zero_nan(size))
    jumped = change > rtol * size_max
    return jnp.maximum(largest, zero_nan(change)), size_max, jumped
