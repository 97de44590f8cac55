"""clebsch-jax: structure-preserving integrators from Clebsch variational principles.

Importing the package turns on 64-bit floats in JAX (`jax_enable_x64`): variational
integrators are judged by conservation to round-off, which float32 cannot show.

The data path, one folder each:
`core` (the system, derivative maps, validation) → `discrete` (the discrete action, its
residual by `jax.grad`, reduction, Gauss–Legendre collocation) → `roots` (Newton, lumped
blocks, fixed point, status codes) → `steppers` (one class per method, with its facts; the
rule that picks one) → `march` (one `lax.scan` over `stepper.step`, `integrate`, the
`Solution`) → `diagnostics`. `batching` holds the batch-last interpreter and parameter sweeps;
`cli` the command line, a client of this public API. The public API is this flat namespace.
"""

from ._startup import guard_startup as _guard_startup

_guard_startup()  # the command line only: Ctrl-C while JAX is imported exits cleanly

import jax as _jax  # noqa: E402

_jax.config.update("jax_enable_x64", True)

from . import diagnostics as diagnostics  # noqa: E402
from . import lie as lie  # noqa: E402
from . import models as models  # noqa: E402
from .batching.batch_last import batch as batch  # noqa: E402
from .batching.sweep import SweepProgress as SweepProgress, SweepResult as SweepResult, sweep as sweep  # noqa: E402
from .batching.store import SweepStoreError as SweepStoreError  # noqa: E402
from .batching.store_read import open_sweep as open_sweep  # noqa: E402
from .batching.ensemble_plan import choose_sweep_step as choose_sweep_step  # noqa: E402
from .core.compilation_cache import enable_compilation_cache as enable_compilation_cache  # noqa: E402
from .core.derivative_maps import (  # noqa: E402
    CayleyDifference as CayleyDifference,
    DerivativeMap as DerivativeMap,
    MatrixGroupDifference as MatrixGroupDifference,
    VectorSpaceDifference as VectorSpaceDifference,
    cayley as cayley,
    exponential as exponential,
    forward_difference as forward_difference,
    so3_exponential as so3_exponential,
)
from .core.isotropy import gauge_isotropy as gauge_isotropy  # noqa: E402
from .core.representation import (  # noqa: E402
    MatrixRepresentation as MatrixRepresentation,
    UnitaryAlgebra as UnitaryAlgebra,
)
from .core.system import ClebschSystem as ClebschSystem, diamond as diamond, momentum_map as momentum_map  # noqa: E402
from .discrete.action import (  # noqa: E402
    SCHEMES as SCHEMES,
    discrete_action as discrete_action,
    discrete_lagrangian as discrete_lagrangian,
)
from .discrete.closure import (  # noqa: E402
    ClosureResult as ClosureResult,
    check_closure as check_closure,
    euler_poincare_field as euler_poincare_field,
)
from .discrete.collocation import GAUSS_ORDERS as GAUSS_ORDERS  # noqa: E402
from .discrete.legendre import (  # noqa: E402
    cotangent_from_momentum as cotangent_from_momentum,
    initial_multiplier as initial_multiplier,
    nodal_velocity as nodal_velocity,
)
from .discrete.residual import (  # noqa: E402
    StepUnknowns as StepUnknowns,
    legendre_residual as legendre_residual,
    nodal_residual as nodal_residual,
    outgoing_momentum as outgoing_momentum,
    step_residual as step_residual,
)
from .march.accuracy import AccuracyPlan as AccuracyPlan, choose_step as choose_step  # noqa: E402
from .march.continuation import Start as Start, continue_from as continue_from  # noqa: E402
from .march.integrate import integrate as integrate, step_plan as step_plan  # noqa: E402
from .march.solution import IntegrationError as IntegrationError, Solution as Solution  # noqa: E402
from .roots.newton import newton_solve as newton_solve  # noqa: E402
from .roots.solvers import BlockNewton as BlockNewton, FixedPoint as FixedPoint, Newton as Newton  # noqa: E402
from .roots.status import NewtonStats as NewtonStats, Status as Status  # noqa: E402
from .steppers.base import (  # noqa: E402
    AbstractStepper as AbstractStepper,
    AbstractWrapper as AbstractWrapper,
    Facts as Facts,
    Principle as Principle,
)
from .steppers.composition import (  # noqa: E402
    COMPOSITIONS as COMPOSITIONS,
    KAHAN_LI_6 as KAHAN_LI_6,
    KAHAN_LI_8 as KAHAN_LI_8,
    SUZUKI_4 as SUZUKI_4,
    Composed as Composed,
    Composition as Composition,
    StepPlan as StepPlan,
    SymmetricPair as SymmetricPair,
)
from .steppers.full import FullStep as FullStep  # noqa: E402
from .steppers.gauss import GaussLegendre as GaussLegendre  # noqa: E402
from .steppers.reduced import ReducedStep as ReducedStep  # noqa: E402

__version__ = "0.1.0"


def __getattr__(name):
    # `clebsch_jax.control` imports optax, which takes a noticeable time: loaded on first use,
    # not with the package
    if name == "control":
        import importlib

        return importlib.import_module(".control", __name__)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
