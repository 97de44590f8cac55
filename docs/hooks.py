"""MkDocs hooks of the documentation site (mkdocs.yml, `hooks:`).

- The notebooks of `notebooks/` become the Tutorials section (`notebooks/README.md` its index),
  the benchmark plots of `benchmarks/results/` are published at the same paths, and
  `benchmarks/README.md` (notes and history) as `benchmarks/notes.md`: the site shows the files
  the repository keeps, not copies.
- MathJax 3 is served from the site itself (the `django-static-mathjax` package of the docs
  extra ships its files; docs/javascripts/mathjax.js configures and loads it), so neither the
  build nor a reader's browser fetches anything from a CDN.
- The CLI reference ends with the `--help` text of the command and of each subcommand, taken
  from the command line itself at build time, so it cannot drift from it.
- A public name without an API reference entry (`docs/api_coverage.py`) is a warning, which
  `mkdocs build --strict` turns into an error.
"""

from __future__ import annotations

import importlib.util
import logging
import os
import pathlib
import re
import subprocess
import sys

from mkdocs.plugins import event_priority
from mkdocs.structure.files import File

ROOT = pathlib.Path(__file__).resolve().parents[1]
log = logging.getLogger("mkdocs.hooks.clebsch_jax")
if str(ROOT) not in sys.path:  # the API check imports the package of this tree, as mkdocstrings reads it
    sys.path.insert(0, str(ROOT))


def _load_api_coverage():
    spec = importlib.util.spec_from_file_location("api_coverage", ROOT / "docs" / "api_coverage.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


MATHJAX_FILES = ("tex-mml-chtml.js", "input/**/*", "output/chtml/**/*", "ui/**/*", "a11y/**/*", "adaptors/**/*")
"""What the site needs of MathJax's es5 distribution: the combined TeX/MathML → CommonHTML file and
what it loads on demand (TeX extensions, fonts, the menu, accessibility); not the other bundles."""


def _mathjax_dir() -> pathlib.Path:
    try:
        import mathjax  # the django-static-mathjax package; it does not need Django
    except ImportError as err:  # the docs extra is incomplete
        raise RuntimeError('MathJax for the site comes from django-static-mathjax: pip install -e ".[docs]"') from err
    return pathlib.Path(mathjax.__file__).resolve().parent / "static" / "mathjax" / "es5"


def _add_from_repository(files, config, pattern: str) -> None:
    """Repository files matching `pattern` at their own paths (mkdocs-jupyter needs real files)."""
    for path in sorted(ROOT.glob(pattern)):
        src_uri = path.relative_to(ROOT).as_posix()
        files.append(File(src_uri, str(ROOT), config["site_dir"], config["use_directory_urls"]))


@event_priority(100)  # before mkdocs-jupyter turns .ipynb files into pages
def on_files(files, config):
    for pattern in ("notebooks/README.md", "notebooks/*.ipynb", "benchmarks/results/*.png"):
        _add_from_repository(files, config, pattern)
    # the benchmarks' notes and history, beside the Benchmarks page (benchmarks.md)
    files.append(File.generated(config, "benchmarks/notes.md", abs_src_path=str(ROOT / "benchmarks" / "README.md")))
    mathjax = _mathjax_dir()
    for path in sorted({p for pattern in MATHJAX_FILES for p in mathjax.glob(pattern) if p.is_file()}):
        uri = f"assets/mathjax/{path.relative_to(mathjax).as_posix()}"
        files.append(File.generated(config, uri, abs_src_path=str(path)))
    return files


CLI_HELP = "<!-- the --help of each command, inserted here by docs/hooks.py -->"


def _cli_help(*command: str) -> str:
    """`clebsch-jax COMMAND --help` of the package in this tree, 100 columns wide."""
    path = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)
    env = dict(os.environ, COLUMNS="100", PYTHONPATH=path)
    run = subprocess.run(
        [sys.executable, "-m", "clebsch_jax", *command, "--help"],
        capture_output=True,
        text=True,
        env=env,
        cwd=ROOT,
        check=True,
    )
    return run.stdout.rstrip()


def on_page_markdown(markdown, page, config, files):
    if CLI_HELP not in markdown:
        return markdown
    top = _cli_help()
    commands = re.findall(r"^    (\w[\w-]*)  ", top.split("\ncommands:", 1)[1], re.MULTILINE)
    if not commands:
        log.warning("cli.md: no subcommands found in 'clebsch-jax --help'")
    sections = [f"### `clebsch-jax --help`\n\n```text\n{top}\n```\n"]
    for command in commands:
        sections.append(f"### `clebsch-jax {command} --help`\n\n```text\n{_cli_help(command)}\n```\n")
    return markdown.replace(CLI_HELP, "\n".join(sections))


def on_post_build(config):
    for name in _load_api_coverage().missing():
        log.warning(f"public name {name} has no entry in the API reference (docs/api/*.md): add '::: {name}'")
