"""Tests of the one-off benches in scripts/ (outside the package): each script is loaded
from its file by `load_script`."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

SCRIPTS = Path(__file__).resolve().parents[2] / "scripts"


def load_script(name: str) -> ModuleType:
    """scripts/NAME.py as a module, `scripts.NAME` (loaded once: a second call gives the
    same module, so that a test's monkeypatch reaches the script's own calls)."""
    module_name = f"scripts.{name}"
    if module_name in sys.modules:
        return sys.modules[module_name]
    spec = importlib.util.spec_from_file_location(module_name, SCRIPTS / f"{name}.py")
    assert spec is not None and spec.loader is not None, name
    module = importlib.util.module_from_spec(spec)
    sys.modules[module_name] = module  # where dataclasses and pickling look it up
    spec.loader.exec_module(module)
    return module
