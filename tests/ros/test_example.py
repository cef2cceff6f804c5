"""examples/ros2_node.py needs ROS 2 and is not run; what it takes from elevmap must exist."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "ros2_node.py"


def test_the_ros2_example_imports_only_names_elevmap_has():
    tree = ast.parse(EXAMPLE.read_text())
    doc = ast.get_docstring(tree)
    assert "NEEDS ROS 2" in doc and "NOT run by the tests" in doc
    used = [(n.module, a.name) for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module
            and n.module.split(".")[0] == "elevmap" for a in n.names]
    assert used
    for module, name in used:
        assert hasattr(importlib.import_module(module), name), f"{module}.{name}"
