"""Fixtures of the sweep tests: a run trained alone by `dqnlab train`, the reference a
sweep's run must equal bit for bit."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest


@pytest.fixture(scope="module")
def trained_alone(tmp_path_factory: pytest.TempPathFactory) -> Callable[[Path, str], Path]:
    """The run directory of a preset file trained by `dqnlab train` alone, once per file."""
    cache: dict[str, Path] = {}

    def reference(config_path: Path, env: str) -> Path:
        key = config_path.read_text()
        if key not in cache:
            run_dir = tmp_path_factory.mktemp("alone") / "run"
            subprocess.run(
                [sys.executable, "-m", "dqnlab", "train", "--env", env, "--preset",
                 str(config_path), "--run-dir", str(run_dir), "--device", "cpu", "--no-progress"],
                check=True, capture_output=True, env={**os.environ, "OMP_NUM_THREADS": "1"},
            )  # fmt: skip
            cache[key] = run_dir
        return cache[key]

    return reference
