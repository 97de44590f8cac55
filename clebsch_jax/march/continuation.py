r"""`continue_from`: the state at the last node of a `Solution`, as the arguments that continue it.

A long run is often cut into chunks — to keep one chunk of trajectory in memory, to report
progress, to reuse one compiled program for any number of steps. Each chunk is one `integrate`
call that starts where the one before ended:

```python
start = cj.continue_from(system, sol)
sol = cj.integrate(system, **start._asdict(), dt=dt, n_steps=n)
```
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax

from ..core.system import ClebschSystem
from ..discrete.legendre import cotangent_from_momentum
from .solution import Solution

__all__ = ["Start", "continue_from"]


class Start(NamedTuple):
    r"""The arguments that start (or continue) a march:
    `integrate(system, **start._asdict(), dt=..., n_steps=...)`.

    **Fields:**

    - `Q0`: the configuration $Q^0$.
    - `xi0`: the velocity; with `P0` given it only fixes the shape of $V$ and seeds the
      nodal-velocity solve (see `integrate`).
    - `P0`: the canonical momentum $p^0 \in T^*_{Q^0}M$.
    - `t0`: the initial time.
    - `march_state`: None, or the march's state at that node (`Solution.march_state`): the
      stepper's guesses and predictor history, so that the continued run makes exactly the
      steps of the unbroken one.
    """

    Q0: jax.Array
    xi0: jax.Array
    P0: jax.Array
    t0: jax.Array
    march_state: Any = None


def continue_from(system: ClebschSystem, sol: Solution, Q: jax.Array | None = None) -> Start:
    r"""The canonical state $(Q^N, p^N)$ at the last node of `sol`, to continue its march.

    A step of the march is the symplectic map $(Q^n, p^n) \mapsto (Q^{n+1}, p^{n+1})$
    (Lemma 20): the next node is a function of the current canonical state alone. So
    `integrate(system, **continue_from(system, sol)._asdict(), dt=dt, n_steps=m)` after a run of
    $N$ steps gives nodes $N, \dots, N + m$ of one run of $N + m$ steps with the same `dt` and
    options. `Start.march_state` carries `sol.march_state` — the stepper's state with its guess of
    the next step and its predictor history — so the continued run makes the very steps of the
    unbroken one: the same Newton updates from the same guesses. (Built by hand without it, a
    `Start` restarts the guesses: only round-off and the updates differ, except near a method's
    step-size limit, where a restarted guess can fail to converge.) The reduced march (Theorem
    27), which carries the momentum map $\mu^n = -p^n \diamond Q^n$ instead of $p^n$, hands over
    the minimum-norm cotangent $p$ with $-p \diamond Q^N = \mu^N$ (`cotangent_from_momentum`, a
    least-squares solve) — any $p$ with that momentum map gives the same reduced step.

    **Arguments:**

    - `system`: the `ClebschSystem` that `sol` was integrated with.
    - `sol`: one trajectory's `Solution` (no batch axes). For a batch, `jax.vmap` this
      function over it: `jax.vmap(lambda s: continue_from(system, s))(sols)`.
    - `Q`: the configuration at the last node, needed only when the march did not carry it (a
      reduced march with `reconstruct=False`, where `sol.Q` is None); otherwise ignored.

    **Returns:** a `Start`: `Q0` = `sol.Q[-1]` (or `Q`); `P0` = `sol.p[-1]`, or in the reduced
    march the minimum-norm cotangent with momentum map `sol.momentum[-1]`; `xi0` =
    `sol.xi[-1]`, or for a degenerate system (where `sol.xi` is None) the last step's velocity
    `sol.xi_step[-1]`, which only seeds the next step's guess; `t0` = `sol.ts[-1]`;
    `march_state` = `sol.march_state`.

    Under `jax.jit`, a function of a `Start` is compiled once for `march_state=None` and once for
    a march state (another pytree): a loop whose first chunk starts from a hand-built `Start`
    and whose later chunks from `continue_from` compiles twice, unless it hands over
    `continue_from(system, sol)._replace(march_state=None)` (the guesses then restart).

    Raises `ValueError` for a batched `Solution` and when `sol.Q` is None and no `Q` is given.
    A failed march hands over NaN (its nodes after the failure are NaN), so the continued run
    fails at once.
    """
    if sol.batch_ndim:
        raise ValueError(
            f"continue_from: `sol` has {sol.batch_ndim} batch axes; it takes one trajectory. "
            "For a batch, jax.vmap it: jax.vmap(lambda s: cj.continue_from(system, s))(sol)."
        )
    if sol.Q is not None:
        Q = sol.Q[-1]
    elif Q is None:
        raise ValueError(
            "continue_from: the march did not carry Q (reduced march with reconstruct=False); "
            "pass the last configuration as `Q`."
        )
    P = sol.p[-1] if sol.p is not None else cotangent_from_momentum(system, Q, sol.momentum[-1])
    xi = sol.xi[-1] if sol.xi is not None else sol.xi_step[-1]
    return Start(Q0=Q, xi0=xi, P0=P, t0=sol.ts[-1], march_state=sol.march_state)
