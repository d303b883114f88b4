"""`dqnlab bench`: a group of one subcommand per question, each passing its options to the
measurement it names (measurements replaced here: their figures are tests/bench's), the
figures printed and written as JSON by one helper."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
import torch
import typer
from typer.testing import CliRunner

from dqnlab.bench import checkpoint, throughput, variants, vector
from dqnlab.cli import app
from dqnlab.cli.bench import report

SUBCOMMANDS = ["throughput", "envs", "variants", "small", "checkpoint", "gpu"]


def _invoke(*args: str) -> Any:
    result = CliRunner().invoke(app, ["bench", *args])
    assert result.exit_code == 0, result.output
    return result


def _recording(seen: dict[str, Any], figures: dict[str, Any]) -> Any:
    def measure(*args: Any, **kwargs: Any) -> dict[str, Any]:
        seen.update(args=args, kwargs=kwargs)
        return dict(figures)

    return measure


def test_the_group_lists_its_subcommands_and_shows_its_help_without_one() -> None:
    group = typer.main.get_command(app).get_command(None, "bench")  # type: ignore[attr-defined]
    assert group.list_commands(None) == SUBCOMMANDS
    for name in SUBCOMMANDS:
        assert group.get_command(None, name).help, name  # its docstring: its --help
    result = CliRunner().invoke(app, ["bench"])
    assert "Usage:" in result.output
    assert all(name in result.output for name in SUBCOMMANDS)


def test_report_prints_one_figure_a_line_and_writes_the_json(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    figures = {"update_ms": 12.3456789, "env": "pong", "runs": [1.5, 2.5]}
    report(figures, tmp_path / "out" / "figures.json", table="| a table |")
    assert capsys.readouterr().out.splitlines() == [
        "update_ms 12.35",
        "env       pong",
        "runs      [1.5, 2.5]",
        "",
        "| a table |",
    ]
    assert json.loads((tmp_path / "out" / "figures.json").read_text()) == figures


def test_throughput_passes_its_options(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    seen: dict[str, Any] = {}
    monkeypatch.setattr(throughput, "run_benchmark", _recording(seen, {"update_ms": 1.0}))
    path = tmp_path / "t.json"
    result = _invoke("throughput", "--env", "pong", "--steps", "50", "--device", "cpu",
                     "--compile", "--compression-fill-steps", "0", "--json", str(path))  # fmt: skip
    assert seen["args"] == ("pong", 50, 1_000_000, torch.device("cpu"))
    assert seen["kwargs"]["compile_update"] and seen["kwargs"]["compression_fill_steps"] == 0
    assert not seen["kwargs"]["peers"] and seen["kwargs"]["cleanrl_dir"] is None
    assert "update_ms 1" in result.output and json.loads(path.read_text()) == {"update_ms": 1.0}


def test_envs_measures_each_count_and_closes_with_the_table(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    seen: dict[str, Any] = {}
    stop: dict[str, Any] = {}
    monkeypatch.setattr(vector, "measure_num_envs", _recording(seen, {"num_envs_1_x": 1.0}))
    monkeypatch.setattr(
        checkpoint, "measure_stop_checkpoint",
        _recording(stop, {"checkpoint_steps": 25_000, "threads": 2}),
    )  # fmt: skip
    monkeypatch.setattr("dqnlab.bench.table.format_table", lambda figures: f"TABLE {figures}")
    result = _invoke("envs", "--num-envs", "1,4", "--concurrency", "none,actor-learner",
                     "--checkpoint", "--steps", "30", "--replay-capacity", "600",
                     "--device", "cpu")  # fmt: skip
    assert seen["args"] == ([1, 4], "breakout", 30, 600, torch.device("cpu"))
    assert seen["kwargs"]["concurrency"] == ("none", "actor-learner")
    assert stop["args"] == ("breakout",)
    # Only the checkpoint's own figures join the table's.
    assert result.output.splitlines()[-1] == (
        "TABLE {'num_envs_1_x': 1.0, 'checkpoint_steps': 25000}"
    )


def test_variants_takes_the_presets_as_an_argument(monkeypatch: pytest.MonkeyPatch) -> None:
    seen: dict[str, Any] = {}
    monkeypatch.setattr(variants, "measure_variants", _recording(seen, {}))
    _invoke("variants", "nature,rainbow", "--steps", "50", "--device", "cpu")
    assert seen["args"] == (["nature", "rainbow"], "breakout", 50, 100_000, torch.device("cpu"))
    _invoke("variants", "--device", "cpu")
    assert seen["args"][0] == list(variants.FAMILY)
    result = CliRunner().invoke(app, ["bench", "variants", "nature,rainbo"])
    assert result.exit_code != 0 and "not a shipped preset" in str(result.exception)


def test_checkpoint_passes_its_game(monkeypatch: pytest.MonkeyPatch) -> None:
    seen: dict[str, Any] = {}
    monkeypatch.setattr(checkpoint, "measure_stop_checkpoint", _recording(seen, {}))
    _invoke("checkpoint", "--env", "pong", "--device", "cpu")
    assert seen["args"] == ("pong",) and seen["kwargs"] == {"device": torch.device("cpu")}
