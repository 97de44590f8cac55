"""The documentation runs and stays complete.

- Every ```python block of the README and of the site's pages (`docs/**/*.md`) runs as written:
  a page's blocks in order, in one namespace, in a scratch working directory (an example that
  writes a Zarr store writes it there). A block fenced ```py is shown but not run (it needs
  something a test cannot have, such as a running Dask scheduler). Pages whose examples take
  long (long marches, high orders, a local Dask cluster) are marked slow.
- Every public name has an entry in the API reference (`docs/api_coverage.py`; the strict docs
  build checks the same).
- The paper table names every result the engine implements and links each to code; the tests it
  cites exist.
- The README stays short, its links resolve, and CI runs its quickstart commands as written.
"""

import importlib.util
import pathlib
import re

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
PAGES = [ROOT / "README.md", *sorted(DOCS.rglob("*.md")), ROOT / "notebooks" / "README.md"]

SLOW_PAGES = {
    "docs/guide/integrate.md",  # Gauss–Legendre of order 16, an order-8 composition, 1000-step marches
    "docs/guide/models.md",  # 20 000 steps of leapfrogging vortices
    "docs/guide/batches.md",  # a batch of 256 bodies through cj.batch (its own compilation)
    "docs/how-to/choose-by-accuracy.md",  # pilots of the default candidates: six methods compiled
    "docs/how-to/control.md",  # shooting by L-BFGS through the landmarks' march
    "docs/how-to/failures.md",  # the full march's compilation, for a failure to read
    "docs/how-to/sweeps.md",  # a sweep of 2000 members, then the same on a two-worker Dask cluster
    "docs/architecture.md",  # a stepper written out and marched, a sweep, each compiled
}

_BLOCK = re.compile(r"^( *)```(\w*)[^\n]*\n(.*?)^\1```", re.MULTILINE | re.DOTALL)


def blocks(page: pathlib.Path, language: str = "python") -> list[str]:
    """The fenced blocks of `page` in `language`, dedented by their fence's indentation."""
    found = []
    for indent, lang, body in _BLOCK.findall(page.read_text(encoding="utf-8")):
        if lang == language:
            found.append("".join(line[len(indent) :] + "\n" for line in body.splitlines()))
    return found


def _name(page: pathlib.Path) -> str:
    return page.relative_to(ROOT).as_posix()


RUNNABLE = [page for page in PAGES if blocks(page)]


@pytest.mark.parametrize(
    "page",
    [pytest.param(p, id=_name(p), marks=[pytest.mark.slow] if _name(p) in SLOW_PAGES else []) for p in RUNNABLE],
)
def test_page_examples_run(page, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    namespace = {"__name__": "__docs_example__"}
    for index, code in enumerate(blocks(page)):
        exec(compile(code, f"{_name(page)}[example {index}]", "exec"), namespace)  # noqa: S102 (running the examples is the test)


def test_the_pages_that_should_have_examples_have_them():
    # a fence typo (```Python, a missing newline) would silently drop an example from the runs above
    counts = {_name(p): len(blocks(p)) for p in RUNNABLE}
    assert counts["README.md"] == 1 and counts["docs/getting-started.md"] == 1
    assert counts["docs/architecture.md"] == 3  # a new model, a new derivative map, a new method
    assert SLOW_PAGES <= counts.keys()
    for page in PAGES:
        languages = set(re.findall(r"^ *```(\w+)", page.read_text(encoding="utf-8"), re.MULTILINE))
        assert languages <= {"python", "py", "bash", "toml", "text"}, (_name(page), languages)


def _api_coverage():
    spec = importlib.util.spec_from_file_location("api_coverage", DOCS / "api_coverage.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_every_public_name_has_an_api_reference_entry():
    coverage = _api_coverage()
    assert coverage.missing() == [], "add a '::: name' line to the page of its topic in docs/api/"
    # and the check itself sees the names: the flat namespace and each documented namespace
    assert {"integrate", "sweep", "ClebschSystem"} <= set(coverage.public_names("clebsch_jax"))
    assert "rigid_body" in coverage.public_names("clebsch_jax.models")
    assert "shoot" in coverage.public_names("clebsch_jax.control")


def test_api_coverage_reports_a_name_without_an_entry(tmp_path):
    coverage = _api_coverage()
    for page in (DOCS / "api").glob("*.md"):
        text = page.read_text(encoding="utf-8").replace("::: clebsch_jax.integrate\n", "")
        (tmp_path / page.name).write_text(text.replace("::: clebsch_jax.lie\n", ""), encoding="utf-8")
    missing = coverage.missing(tmp_path)
    assert "clebsch_jax.integrate" in missing and "clebsch_jax.lie.so3_exp" in missing


PAPER_RESULTS = [
    "Definition 1", "Definition 2", "Definition 4", "Definition 14", "Definition 18", "Definition 19",
    "Definition 25", "Lemma 7", "Lemma 20", "Theorem 12", "Theorem 16", "Theorem 27", "Example 30",
]  # fmt: skip


def test_the_paper_table_links_every_implemented_result_to_code():
    rows = [line for line in (DOCS / "paper.md").read_text(encoding="utf-8").splitlines() if line.startswith("| **")]
    for result in PAPER_RESULTS:
        (row,) = [r for r in rows if r.startswith(f"| **{result}**")]
        assert re.search(r"\]\[clebsch_jax\.[\w.]+\]", row), f"{result}: no link to code"


def test_the_tests_the_docs_cite_exist():
    cited = set()
    for page in PAGES:
        cited.update(re.findall(r"`(tests/test_\w+\.py)(?:::(\w+))?`", page.read_text(encoding="utf-8")))
    assert cited
    for path, name in cited:
        source = (ROOT / path).read_text(encoding="utf-8")
        assert not name or re.search(rf"^def {name}\(", source, re.MULTILINE), f"{path}::{name} does not exist"


def test_the_readme_is_two_screens_with_live_links():
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(readme.splitlines()) <= 150
    for target in re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", readme):
        assert target.startswith("http") or (ROOT / target).exists(), target


def test_ci_runs_the_readme_commands_as_written():
    commands = blocks(ROOT / "README.md", "bash")[:2]
    assert [c.strip() for c in commands] == ['pip install -e ".[test]" && clebsch-jax demo', "python -m pytest"]
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8").splitlines()
    for command in commands:
        assert command.strip() in ci
