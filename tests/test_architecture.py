r"""The package's layering, read from its source with `ast` (no import, no JAX, no compile).

- No module imports a private name (a leading underscore, not a dunder) from another module
  of the package: a name used across modules is public within the package. A package may
  import its own private submodules (`from ._scenes import ...`, `from . import _rigid_body`:
  the layout of diffrax's `_term.py`, `_solver/`).
- The modules of `clebsch_jax.batching` import one another without a cycle — module-level
  and function-level imports alike: program of one member → backend → scheduling → store,
  each layer importing only the ones below it (`docs/architecture.md`).
- No file of the package is longer than `MAX_LINES`.

The exceptions below are what other work in progress still holds; each fails the test once it
is gone, so that the list only shrinks.
"""

import ast
import pathlib

PACKAGE = pathlib.Path(__file__).resolve().parent.parent / "clebsch_jax"

MAX_LINES = 500
"""500 lines per file at most: one concern per module."""

KNOWN_PRIVATE_IMPORTS: set = set()
"""(importer, module, name) of the private imports still to remove."""

BATCHING_LAYERS = """
walk rules prune batch_native batch_last rows scalarise member fast lean backends config probe chunks_xla chunks_native tables schedule
store_layout store_lock store store_read distributed choose ensemble_plan sweep
""".split()
"""The modules of `clebsch_jax.batching` in the order of `docs/architecture.md`: each imports only
modules before it."""

KNOWN_LONG_FILES: set = set()
"""Files above `MAX_LINES` still to split."""


def _modules() -> dict:
    """{dotted module name: path} of every module of the package."""
    found = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        found[".".join(parts)] = path
    return found


MODULES = _modules()


def _imports(name: str, path: pathlib.Path):
    """(module imported from, names imported) of every `from … import …` in the module, at any
    depth (function-level imports too), resolved to dotted names."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            yield target, [alias.name for alias in node.names]
        elif isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, []


def _is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def test_no_private_name_is_imported_across_modules():
    found = set()
    for importer, path in MODULES.items():
        own_package = importer if path.name == "__init__.py" else importer.rpartition(".")[0]
        for target, names in _imports(importer, path):
            if not target.startswith("clebsch_jax"):
                continue
            for name in names:
                submodule = f"{target}.{name}"
                if not _is_private(name) or (submodule in MODULES and target == own_package):
                    continue
                found.add((importer, target, name))
    new = [f"{who} imports {name} from {target}" for who, target, name in sorted(found - KNOWN_PRIVATE_IMPORTS)]
    assert not new, f"private names imported across modules (make them public within the package): {new}"
    gone = sorted(KNOWN_PRIVATE_IMPORTS - found)
    assert not gone, f"no longer imported: remove from KNOWN_PRIVATE_IMPORTS: {gone}"


def _batching_graph() -> dict:
    """{batching module: the batching modules it imports}."""
    graph = {}
    for importer, path in MODULES.items():
        if not importer.startswith("clebsch_jax.batching"):
            continue
        edges = set()
        for target, names in _imports(importer, path):
            if not target.startswith("clebsch_jax.batching"):
                continue
            submodules = [f"{target}.{n}" for n in names if f"{target}.{n}" in MODULES]
            edges.update(submodules or [target])
        edges.discard(importer)
        graph[importer] = edges
    return graph


def _cycle(graph: dict) -> list | None:
    """One cycle of the graph (a list of nodes, first = last), or None."""
    state, stack = {}, []

    def visit(node):
        state[node] = "open"
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == "open":
                return stack[stack.index(nxt) :] + [nxt]
            if nxt not in state:
                found = visit(nxt)
                if found:
                    return found
        state[node] = "done"
        stack.pop()
        return None

    for node in sorted(graph):
        if node not in state:
            found = visit(node)
            if found:
                return found
    return None


def test_the_batching_modules_import_one_another_without_a_cycle():
    graph = _batching_graph()
    assert "clebsch_jax.batching.sweep" in graph and graph["clebsch_jax.batching.sweep"]
    cycle = _cycle(graph)
    assert cycle is None, "an import cycle in clebsch_jax.batching: " + " -> ".join(cycle)
    # the layers, one way: nothing below the entry point imports it, the store is not imported
    # by the schedule or the programs, and Dask's tasks only by the entry point
    short = {m: {e.rpartition(".")[2] for e in edges} for m, edges in graph.items()}
    assert sorted(m.rpartition(".")[2] for m in short) == sorted(BATCHING_LAYERS + ["batching"])  # each in its place
    for k, module in enumerate(BATCHING_LAYERS):
        later = short[f"clebsch_jax.batching.{module}"] & set(BATCHING_LAYERS[k:])
        assert not later, f"batching.{module} imports {sorted(later)}, listed after it in docs/architecture.md"
    importers = lambda module: {m.rpartition(".")[2] for m, edges in short.items() if module in edges}
    assert importers("sweep") == set()
    assert importers("distributed") == {"sweep"}
    assert importers("store") <= {"sweep", "distributed", "choose", "store_read"}


def test_the_cycle_finder_finds_a_cycle():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None


def test_no_file_of_the_package_is_too_long():
    lengths = {path.relative_to(PACKAGE).as_posix(): len(path.read_text().splitlines()) for path in MODULES.values()}
    long = {f for f, n in lengths.items() if n > MAX_LINES}
    assert long <= KNOWN_LONG_FILES, {f: lengths[f] for f in sorted(long - KNOWN_LONG_FILES)}
    gone = KNOWN_LONG_FILES - long
    assert not gone, f"no longer above {MAX_LINES} lines: remove from KNOWN_LONG_FILES: {sorted(gone)}"
