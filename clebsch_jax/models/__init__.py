"""Built-in models. Each is a constructor returning a `ClebschSystem`: models are data.

Parameters are array leaves (held by `jax.tree_util.Partial`), so a parameter sweep is a
`jax.vmap` over the constructor's arguments.
"""

from ._heavy_top import heavy_top as heavy_top
from ._rigid_body import rigid_body as rigid_body

__all__ = ["rigid_body", "heavy_top"]
