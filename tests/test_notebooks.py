"""The notebooks in `notebooks/` run from top to bottom (issue 7: executed by the test suite so
they never rot), and they are committed stripped of outputs.

Every `notebooks/*.ipynb` is picked up automatically. Each notebook ends with `assert`s on the
mathematics it shows, so executing it is a test. It runs in a fresh `python3` kernel (nbclient)
whose working directory is `notebooks/`, with `MPLBACKEND=Agg`; under Agg nothing is drawn unless
asked, so one extra cell, appended here and never saved, renders every open figure — a broken
plot (bad mathtext, mismatched shapes) fails the test too.
"""

import json
import pathlib
import re

import pytest

NOTEBOOKS_DIR = pathlib.Path(__file__).resolve().parent.parent / "notebooks"
NOTEBOOKS = sorted(NOTEBOOKS_DIR.glob("*.ipynb"))
CELL_TIMEOUT = 600  # seconds per cell; a whole notebook takes well under a minute

RENDER_FIGURES = """\
import io as _io
import sys as _sys
if "matplotlib.pyplot" in _sys.modules:
    import matplotlib.pyplot as _plt
    for _number in _plt.get_fignums():
        _figure = _plt.figure(_number)
        try:
            _figure.savefig(_io.BytesIO(), format="png")
        except Exception as _err:
            _titles = [_ax.get_title() for _ax in _figure.axes]
            raise RuntimeError(f"figure {_number} (axes titled {_titles}) does not render: {_err}") from _err
    _plt.close("all")
"""

_ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")


def _require_kernel():
    """Skip (with the reason) when notebooks cannot be executed here."""
    nbformat = pytest.importorskip("nbformat", reason="executing notebooks needs nbformat (the test extra)")
    nbclient = pytest.importorskip("nbclient", reason="executing notebooks needs nbclient (the test extra)")
    from jupyter_client.kernelspec import KernelSpecManager, NoSuchKernel

    try:
        KernelSpecManager().get_kernel_spec("python3")
    except NoSuchKernel:
        pytest.skip("no 'python3' Jupyter kernel: install ipykernel (the test extra) to execute the notebooks")
    return nbformat, nbclient


@pytest.mark.slow  # 15-50 s each on 2 cores, mostly compiling: run with -m slow (and in CI)
@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_runs(path, monkeypatch):
    nbformat, nbclient = _require_kernel()
    from nbclient.exceptions import CellExecutionError, CellTimeoutError, DeadKernelError

    nb = nbformat.read(path, as_version=4)
    nb.cells.append(nbformat.v4.new_code_cell(RENDER_FIGURES))
    monkeypatch.setenv("MPLBACKEND", "Agg")  # inherited by the kernel
    client = nbclient.NotebookClient(
        nb, timeout=CELL_TIMEOUT, kernel_name="python3", resources={"metadata": {"path": str(NOTEBOOKS_DIR)}}
    )
    current = {}
    client.on_cell_start = lambda cell, cell_index: current.update(index=cell_index)
    failure = None
    try:
        client.execute()
    except (CellExecutionError, CellTimeoutError, DeadKernelError) as err:
        failure = err
    except RuntimeError as err:  # e.g. "Kernel didn't respond" / "Kernel died before replying"
        if "index" in current:
            raise
        pytest.skip(f"the python3 kernel could not start: {err}")
    if failure is None:
        return
    if "index" not in current:  # nothing ran: the kernel itself did not start
        pytest.skip(f"the python3 kernel could not start: {type(failure).__name__}: {failure}")
    # reported outside the except block, so the message is not buried under nbclient's own
    index = current["index"]
    cell = nb.cells[index]
    what = "the figure check appended by this test" if index == len(nb.cells) - 1 else f"cell {index}"
    errors = [out for out in cell.get("outputs", []) if out.get("output_type") == "error"]
    if errors:
        error = _ANSI.sub("", "\n".join(errors[0].get("traceback", [])))
    else:  # a timeout or a dead kernel leaves no error output
        error = f"{type(failure).__name__}: {_ANSI.sub('', str(failure))}"
    pytest.fail(f"{path.name}: {what} failed.\n--- source ---\n{cell.source}\n--- error ---\n{error}", pytrace=False)


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_is_committed_stripped(path):
    """No outputs and no execution counts in the committed file (so diffs stay readable and the
    repository small), and the kernel the runner uses."""
    nb = json.loads(path.read_text(encoding="utf-8"))
    dirty = [
        i
        for i, cell in enumerate(nb["cells"])
        if cell["cell_type"] == "code" and (cell.get("outputs") or cell.get("execution_count") is not None)
    ]
    assert not dirty, (
        f"{path.name}: code cells {dirty} have outputs or execution counts; clear them before committing "
        "(Jupyter's 'Clear All Outputs', or `jupyter nbconvert --clear-output --inplace`)"
    )
    assert nb["metadata"].get("kernelspec", {}).get("name") == "python3", (
        f"{path.name}: metadata.kernelspec.name should be 'python3' (the kernel the test suite runs)"
    )
