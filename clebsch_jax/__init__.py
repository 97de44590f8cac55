"""clebsch-jax: structure-preserving integrators from Clebsch variational principles.

Importing the package turns on 64-bit floats in JAX (`jax_enable_x64`): variational
integrators are judged by conservation to round-off, which float32 cannot show.

The data path, one module each:
system (`ClebschSystem`) → discrete action (`discrete_action`) → residual (Lemma 20, by
`jax.grad`) → Newton (`newton_solve`) → scan (`integrate`) → `Solution` → `diagnostics`.
`scheme="gauss"` takes the parallel path: the Gauss–Legendre discretisation of the same action
(`_collocation`: its stage equations by `jax.grad` of the Clebsch Hamiltonian) → fixed-point
sweeps (`_newton.fixed_point_solve`) → the same scan and `Solution`.
"""

import jax as _jax

_jax.config.update("jax_enable_x64", True)

from . import diagnostics as diagnostics  # noqa: E402
from . import lie as lie  # noqa: E402
from . import models as models  # noqa: E402
from ._derivative_maps import (  # noqa: E402
    DerivativeMap as DerivativeMap,
    MatrixGroupDifference as MatrixGroupDifference,
    VectorSpaceDifference as VectorSpaceDifference,
    cayley as cayley,
    exponential as exponential,
    forward_difference as forward_difference,
    so3_exponential as so3_exponential,
)
from ._discrete_action import (  # noqa: E402
    SCHEMES as SCHEMES,
    discrete_action as discrete_action,
    discrete_lagrangian as discrete_lagrangian,
)
from ._batch_last import batch as batch  # noqa: E402
from ._closure import (  # noqa: E402
    ClosureResult as ClosureResult,
    check_closure as check_closure,
    euler_poincare_field as euler_poincare_field,
)
from ._collocation import GAUSS_ORDERS as GAUSS_ORDERS  # noqa: E402
from ._compilation_cache import enable_compilation_cache as enable_compilation_cache  # noqa: E402
from ._composition import (  # noqa: E402
    COMPOSITIONS as COMPOSITIONS,
    Composition as Composition,
    StepPlan as StepPlan,
)
from ._continuation import Start as Start, continue_from as continue_from  # noqa: E402
from ._integrate import integrate as integrate, step_plan as step_plan  # noqa: E402
from ._march_full import (  # noqa: E402
    cotangent_from_momentum as cotangent_from_momentum,
    initial_multiplier as initial_multiplier,
    nodal_velocity as nodal_velocity,
)
from ._newton import NewtonStats as NewtonStats, Status as Status, newton_solve as newton_solve  # noqa: E402
from ._residual import (  # noqa: E402
    StepUnknowns as StepUnknowns,
    legendre_residual as legendre_residual,
    nodal_residual as nodal_residual,
    outgoing_momentum as outgoing_momentum,
    step_residual as step_residual,
)
from ._solution import IntegrationError as IntegrationError, Solution as Solution  # noqa: E402
from ._sweep import SweepProgress as SweepProgress, SweepResult as SweepResult, sweep as sweep  # noqa: E402
from ._system import ClebschSystem as ClebschSystem, diamond as diamond, momentum_map as momentum_map  # noqa: E402

__version__ = "0.1.0"


def __getattr__(name):
    # `clebsch_jax.control` imports optax (~1 s): loaded on first use, not with the package
    if name == "control":
        import importlib

        return importlib.import_module(".control", __name__)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
