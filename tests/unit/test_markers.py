"""Every test file under tests/unit carries the ``unit`` marker (``make test-unit`` selects by it)."""

import ast
from pathlib import Path

import pytest

pytestmark = pytest.mark.unit


def test_every_unit_test_module_is_marked_unit():
    unmarked = []
    for path in sorted(Path(__file__).parent.glob("test_*.py")):
        tree = ast.parse(path.read_text())
        marked = any(
            isinstance(node, ast.Assign)
            and any(isinstance(t, ast.Name) and t.id == "pytestmark" for t in node.targets)
            and "unit" in ast.unparse(node.value)
            for node in tree.body
        )
        if not marked:
            unmarked.append(path.name)
    assert unmarked == []
