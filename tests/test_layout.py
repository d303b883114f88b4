"""The package's layout, read from its source with `ast`: imports point down the layers
(errors < config < envs < algorithm < run < analysis < sweeps < tune < bench < hub < cli), no
modules import each other in a circle, no module is over 500 lines, no function over 60 (but the
listed ones, which may not grow), and the modules the
evaluation's worker processes import never import torch.

Every import counts: `import dqnlab.x`, `from dqnlab.x import y`, relative ones, and
those inside functions or under `if TYPE_CHECKING:`. An import of a package's
submodule (`from dqnlab.sweeps import grid`) points at the submodule, not at the
package's `__init__.py`."""

from __future__ import annotations

import ast
from pathlib import Path

import dqnlab

PACKAGE = Path(dqnlab.__file__).parent
# A module's layer, from its path; a module may import its own layer and those below.
LAYERS = [
    "errors", "parts", "config", "envs", "algorithm", "run", "analysis", "sweeps", "tune", "bench",
    "hub", "cli",
]  # fmt: skip
MAX_MODULE_LINES = 500


def _module_name(path: Path) -> str:
    relative = path.relative_to(PACKAGE.parent).with_suffix("")
    parts = list(relative.parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_name(path): path for path in sorted(PACKAGE.rglob("*.py"))}


def _layer(module: str) -> int:
    parts = module.split(".")
    name = parts[1] if len(parts) > 1 else ""
    if name in LAYERS:
        return LAYERS.index(name)
    if name == "__main__":
        return len(LAYERS)  # above everything
    return -1  # the package itself: its version


def _known(name: str) -> str:
    """The module of the package that `name` (a module, or a name inside one) is in."""
    while name not in MODULES:
        name = name.rpartition(".")[0]
    return name


def imported_modules(module: str) -> set[str]:
    """The package's modules that `module` imports, anywhere in its source."""
    path = MODULES[module]
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join(anchor + ([node.module] if node.module else []))
            names = [f"{base}.{alias.name}" for alias in node.names]
        else:
            continue
        found |= {_known(name) for name in names if name.split(".")[0] == "dqnlab"}
    return found - {module}


def import_graph() -> dict[str, set[str]]:
    return {module: imported_modules(module) for module in MODULES}


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Circles of imports (a -> b -> ... -> a): in each group of modules that reach each
    other (Tarjan's strongly connected components), the shortest circle through each
    module that no circle named before passes."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    groups: list[set[str]] = []

    def visit(module: str) -> None:
        index[module] = low[module] = len(index)
        stack.append(module)
        for target in sorted(graph[module]):
            if target not in index:
                visit(target)
                low[module] = min(low[module], low[target])
            elif target in stack:
                low[module] = min(low[module], index[target])
        if low[module] == index[module]:
            group = set()
            while True:
                member = stack.pop()
                group.add(member)
                if member == module:
                    break
            if len(group) > 1:
                groups.append(group)

    for module in sorted(graph):
        if module not in index:
            visit(module)
    found = []
    for group in groups:
        left = set(group)
        while left:
            found.append(_circle_through(min(left), graph, group))
            left -= set(found[-1])
    return sorted(found)


def _circle_through(start: str, graph: dict[str, set[str]], group: set[str]) -> list[str]:
    """The shortest way from `start` back to itself, within its group."""
    paths = {start: [start]}
    frontier = [start]
    while frontier:
        following = []
        for module in frontier:
            for target in sorted(graph[module] & group):
                if target == start:
                    return paths[module] + [start]
                if target not in paths:
                    paths[target] = paths[module] + [target]
                    following.append(target)
        frontier = following
    raise AssertionError(f"no circle through {start} in {sorted(group)}")


def test_imports_point_down_the_layers() -> None:
    upward = [
        f"{module} imports {target}"
        for module, targets in import_graph().items()
        for target in sorted(targets)
        if _layer(target) > _layer(module)
    ]
    assert upward == []


def test_no_modules_import_each_other_in_a_circle() -> None:
    found = [" -> ".join(circle) for circle in circles(import_graph())]
    assert found == [], "import circles:\n" + "\n".join(found)


def test_the_circle_check_names_a_circle() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a", "d"}, "d": set(), "e": {"d"}}
    assert circles(graph) == [["a", "b", "c", "a"]]
    graph.update({"d": {"e"}, "e": {"d"}})  # c reaches d and e, they do not reach back
    assert circles(graph) == [["a", "b", "c", "a"], ["d", "e", "d"]]
    graph["e"] = {"c", "d"}  # now one knot: a circle through each module is named
    assert circles(graph) == [["a", "b", "c", "a"], ["d", "e", "d"]]


def test_no_module_is_over_500_lines() -> None:
    lengths = {module: len(path.read_text().splitlines()) for module, path in MODULES.items()}
    long = [f"{MODULES[m].relative_to(PACKAGE.parent)}: {n} lines" for m, n in lengths.items()
            if n > MAX_MODULE_LINES]  # fmt: skip
    assert long == [], f"modules over {MAX_MODULE_LINES} lines (split them by concern)"


MAX_FUNCTION_LINES = 60
# The functions over MAX_FUNCTION_LINES when the limit came (2026-12-04), each at most as
# long as then: a ratchet. Each is to be split by what it does (issue 31's house); one
# that gets shorter lowers its entry, one split below the limit leaves the list.
LONG_FUNCTIONS: dict[str, int] = {}  # none left: a new one must be split, not listed


def function_lengths() -> dict[str, int]:
    """Every function's and method's lines (decorators left out), as `path::name`; the
    longest where a module has two of one name."""
    lengths: dict[str, int] = {}
    for path in MODULES.values():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                name = f"{path.relative_to(PACKAGE).as_posix()}::{node.name}"
                lines = (node.end_lineno or node.lineno) - node.lineno + 1
                lengths[name] = max(lines, lengths.get(name, 0))
    return lengths


def test_no_function_grows_past_60_lines() -> None:
    lengths = function_lengths()
    too_long = [f"{name}: {n} lines" for name, n in sorted(lengths.items())
                if n > LONG_FUNCTIONS.get(name, MAX_FUNCTION_LINES)]  # fmt: skip
    assert too_long == [], f"functions over {MAX_FUNCTION_LINES} lines (or longer than listed)"
    stale = [f"{name}: {n} listed, {lengths.get(name, 0)} now"
             for name, n in LONG_FUNCTIONS.items() if lengths.get(name, 0) < n]  # fmt: skip
    assert stale == [], "shorter than LONG_FUNCTIONS says: lower or remove their entries"


def test_worker_modules_import_no_torch() -> None:
    """envs/ (pool.py and what it imports) at module level: torch is imported inside the
    functions that need it, never by a worker process."""
    for path in sorted((PACKAGE / "envs").glob("*.py")):
        tree = ast.parse(path.read_text())
        top_level = [node for node in tree.body if isinstance(node, (ast.Import, ast.ImportFrom))]
        names = [alias.name for node in top_level for alias in node.names]
        names += [node.module for node in top_level if isinstance(node, ast.ImportFrom)]
        assert not any(name and name.split(".")[0] == "torch" for name in names), path
