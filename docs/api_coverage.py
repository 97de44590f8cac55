"""Which public names of clebsch-jax have no entry in the API reference (docs/api/*.md).

The reference pages are written as mkdocstrings directives, `::: clebsch_jax.integrate` for one
name or `::: clebsch_jax.models` for a whole namespace (every name in its `__all__`). This
module lists the public names of each documented namespace and the ones no directive covers.
It is used twice: by the docs build (docs/hooks.py turns a missing name into a warning, which
`mkdocs build --strict` makes an error) and by `tests/test_docs.py`, which needs no docs extra.

A namespace's public names are its `__all__` when it declares one; otherwise its attributes
that do not start with `_`, are not modules, and come from this package (an object whose
`__module__` is another package's, such as `typing.Callable`, is an import, not an export).
Constants without a `__module__` (tuples, dicts, numbers) count as exports.
"""

from __future__ import annotations

import importlib
import inspect
import pathlib
import re

PACKAGE = "clebsch_jax"

NAMESPACES = (
    "clebsch_jax",
    "clebsch_jax.models",
    "clebsch_jax.lie",
    "clebsch_jax.diagnostics",
    "clebsch_jax.control",
)
"""The public namespaces: the flat package and the submodules users reach as `cj.<name>.…`."""

API_DIR = pathlib.Path(__file__).resolve().parent / "api"

_DIRECTIVE = re.compile(r"^:::\s+([\w.]+)\s*$", re.MULTILINE)


def public_names(namespace: str) -> list[str]:
    """The public names of `namespace` (a dotted module name), sorted."""
    module = importlib.import_module(namespace)
    declared = getattr(module, "__all__", None)
    if declared is not None:
        return sorted(declared)
    names = []
    for name, obj in vars(module).items():
        if name.startswith("_") or inspect.ismodule(obj):
            continue
        origin = getattr(obj, "__module__", None)
        if origin is None or origin == PACKAGE or origin.startswith(PACKAGE + "."):
            names.append(name)
    # a namespace loaded lazily (`clebsch_jax.control`) is documented on its own page
    return sorted(n for n in names if f"{namespace}.{n}" not in NAMESPACES)


def documented(api_dir: pathlib.Path = API_DIR) -> set[str]:
    """Every identifier named by a `::: identifier` directive on the reference pages."""
    found = set()
    for page in sorted(api_dir.glob("*.md")):
        found.update(_DIRECTIVE.findall(page.read_text(encoding="utf-8")))
    return found


def missing(api_dir: pathlib.Path = API_DIR) -> list[str]:
    """Public names (dotted) that no directive covers: neither `::: ns.name` nor `::: ns`."""
    covered = documented(api_dir)
    out = []
    for namespace in NAMESPACES:
        if namespace in covered and namespace != PACKAGE:
            continue  # the whole namespace is rendered (its __all__ or its public members)
        out.extend(f"{namespace}.{name}" for name in public_names(namespace) if f"{namespace}.{name}" not in covered)
    return out
