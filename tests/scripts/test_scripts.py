"""Every script in scripts/ runs as `python scripts/NAME.py --help`, and opens with a
docstring that says which section of docs/benchmark.md holds its figures, by an anchor the
page has (`docs/benchmark.md, "Section" (#anchor)`)."""

from __future__ import annotations

import ast
import re
import subprocess
import sys

import pytest

from tests.scripts import SCRIPTS

BENCHMARK_PAGE = SCRIPTS.parent / "docs" / "benchmark.md"
NAMES = sorted(path.stem for path in SCRIPTS.glob("*.py"))


def test_there_are_scripts() -> None:
    assert NAMES == ["compression_scan", "emulators", "sweep_overhead"]


@pytest.mark.parametrize("name", NAMES)
def test_the_script_runs_and_names_its_docs_section(name: str) -> None:
    path = SCRIPTS / f"{name}.py"
    docstring = ast.get_docstring(ast.parse(path.read_text())) or ""
    anchors = re.findall(r'docs/benchmark\.md, "[^"]+" \(#([\w-]+)\)', " ".join(docstring.split()))
    assert anchors and set(anchors) <= _anchors(BENCHMARK_PAGE.read_text()), (name, anchors)
    shown = subprocess.run(
        [sys.executable, str(path), "--help"], capture_output=True, text=True, timeout=300
    )
    assert shown.returncode == 0 and "Usage:" in shown.stdout, shown.stderr[-2000:]


def _anchors(page: str) -> set[str]:
    """The ids the page gives (`<a id="...">`) and its headings' own (Markdown's toc: lower
    case, punctuation dropped, spaces as hyphens)."""
    ids = set(re.findall(r'id="([^"]+)"', page))
    for line in page.splitlines():
        if line.startswith("#"):
            heading = re.sub(r"<[^>]+>", "", line.lstrip("#")).strip().lower()
            ids.add(re.sub(r"\s+", "-", re.sub(r"[^\w\s-]", "", heading)))
    return ids
