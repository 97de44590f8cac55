"""The worked examples of docs/architecture.md run as written (a new model, a new derivative map,
a new method), so the guide cannot drift from the code."""

import pathlib
import re

import pytest

DOC = pathlib.Path(__file__).resolve().parents[1] / "docs" / "architecture.md"
BLOCKS = re.findall(r"```python\n(.*?)```", DOC.read_text(), re.S)


def test_the_guide_has_its_three_worked_examples():
    assert len(BLOCKS) == 3


@pytest.mark.parametrize("index", range(len(BLOCKS)))
def test_worked_example_runs(index):
    exec(compile(BLOCKS[index], f"{DOC.name}[example {index}]", "exec"), {})
