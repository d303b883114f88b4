"""scripts/emulators.py: both ways of stepping N emulators are measured (not their speed),
and a bad count is one line."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from tests.scripts import load_script

emulators = load_script("emulators")


def test_each_way_gets_its_rounds_and_ratio() -> None:
    figures = emulators.measure_emulators(3, steps=5, rounds=2, game="pong")
    for name in ("in_process", "ale_vector_1_threads", "ale_vector_2_threads"):
        runs = figures[f"{name}_agent_steps_per_second_runs"]
        assert len(runs) == 2 and min(runs) > 0, name
        mean = figures[f"{name}_agent_steps_per_second"]
        expected = mean / figures["in_process_agent_steps_per_second"]
        assert figures[f"{name}_ratio"] == pytest.approx(expected)
    assert figures["in_process_ratio"] == 1.0


def test_a_count_below_one_is_refused() -> None:
    result = CliRunner().invoke(emulators.app, ["--emulators", "0"])
    assert result.exit_code != 0
    assert "--emulators 0: give at least 1" in str(result.exception)
