"""The package's layers: imports point down (envs < algorithm < run < analysis < sweeps <
bench < cli), and the modules the evaluation's worker processes import never import torch."""

from __future__ import annotations

import ast
from pathlib import Path

import dqnlab

PACKAGE = Path(dqnlab.__file__).parent
# A module's layer, from its path; a module may import its own layer and those below.
LAYERS = ["errors", "config", "envs", "algorithm", "run", "analysis", "sweeps", "bench", "cli"]


def _layer(module: str) -> int:
    parts = module.split(".")
    name = parts[1] if len(parts) > 1 else ""
    if name in LAYERS:
        return LAYERS.index(name)
    if name == "__main__":
        return len(LAYERS)  # above everything
    return -1  # the package itself: its version


def _imports(path: Path) -> list[str]:
    tree = ast.parse(path.read_text())
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found += [node.module] + [f"{node.module}.{alias.name}" for alias in node.names]
        elif isinstance(node, ast.Import):
            found += [alias.name for alias in node.names]
    return found


def _module_name(path: Path) -> str:
    relative = path.relative_to(PACKAGE.parent).with_suffix("")
    parts = list(relative.parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def test_imports_point_down_the_layers() -> None:
    upward = []
    for path in sorted(PACKAGE.rglob("*.py")):
        module = _module_name(path)
        for imported in _imports(path):
            if imported.startswith("dqnlab.") and _layer(imported) > _layer(module):
                upward.append(f"{module} imports {imported}")
    assert upward == []


def test_worker_modules_import_no_torch() -> None:
    """envs/ (pool.py and what it imports) at module level: torch is imported inside the
    functions that need it, never by a worker process."""
    for path in sorted((PACKAGE / "envs").glob("*.py")):
        tree = ast.parse(path.read_text())
        top_level = [node for node in tree.body if isinstance(node, (ast.Import, ast.ImportFrom))]
        names = [alias.name for node in top_level for alias in node.names]
        names += [node.module for node in top_level if isinstance(node, ast.ImportFrom)]
        assert not any(name and name.split(".")[0] == "torch" for name in names), path
