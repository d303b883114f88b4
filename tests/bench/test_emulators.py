"""`dqnlab bench --emulators`: both ways of stepping N emulators are measured (not their
speed), and a bad count is one line."""

from __future__ import annotations

import pytest

from dqnlab.bench.emulators import measure_emulators
from tests.helpers import dqnlab_main


def test_each_way_gets_its_rounds_and_ratio() -> None:
    figures = measure_emulators(3, steps=5, rounds=2, game="pong")
    for name in ("in_process", "ale_vector_1_threads", "ale_vector_2_threads"):
        runs = figures[f"{name}_agent_steps_per_second_runs"]
        assert len(runs) == 2 and min(runs) > 0, name
        mean = figures[f"{name}_agent_steps_per_second"]
        expected = mean / figures["in_process_agent_steps_per_second"]
        assert figures[f"{name}_ratio"] == pytest.approx(expected)
    assert figures["in_process_ratio"] == 1.0


def test_a_count_below_one_is_one_line(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    code, stderr = dqnlab_main(capsys, monkeypatch, "bench", "--emulators", "0")
    assert code != 0
    assert "--emulators 0: give at least 1" in stderr
