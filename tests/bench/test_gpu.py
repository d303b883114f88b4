"""`dqnlab bench gpu` runs end to end on CPU with a tiny budget, and its figures say which
were skipped for want of CUDA (not their speed)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from dqnlab.bench import gpu
from dqnlab.cli import app
from dqnlab.errors import ConfigError


def test_the_command_end_to_end_on_cpu_quick(tmp_path: Path) -> None:
    path = tmp_path / "bench-gpu.json"
    result = CliRunner().invoke(
        app, ["bench", "gpu", "--device", "cpu", "--quick", "--json", str(path)]
    )
    assert result.exit_code == 0, result.output
    figures = json.loads(path.read_text())
    assert "update_ms_graph_off" in result.stdout  # the figures are printed too
    assert figures["machine"]["device"] == "cpu" and figures["machine"]["cores"] >= 1
    assert {"torch", "cuda", "cuda_available"} <= set(figures["machine"])
    for name in ("cpu_matches_device", "graph_matches_eager", "update_ms_graph_cuda",
                 "exact_loop_graph_cuda"):  # fmt: skip
        assert figures[name] == gpu.NO_CUDA, name
    assert figures["update_ms_graph_off"]["back_to_back_ms"] > 0
    loop = figures["exact_loop_graph_off"]
    assert loop["frames_per_second"] > 0
    assert loop["updates"] > 0 and abs(sum(loop["split"].values()) - 1.0) < 1e-3
    for count in gpu.VECTOR_ENVS:  # measured on CPU too: never a failure, never skipped
        entry = figures[f"num_envs_{count}"]
        assert isinstance(entry, dict) and entry["frames_per_second"] > 0, entry
    acting = figures[f"num_envs_{gpu.ACTOR_LEARNER_ENVS}_actor_learner"]
    assert isinstance(acting, dict) and acting["frames_per_second"] > 0, acting
    assert acting["concurrency"] == "actor-learner" and acting["updates"] > 0


def test_the_command_line_passes_its_options(tmp_path: Path, monkeypatch) -> None:  # noqa: ANN001
    seen = {}
    monkeypatch.setattr(
        gpu,
        "run_gpu_benchmark",
        lambda device, quick, env, echo, budget_seconds, only: seen.update(locals()) or {},
    )
    path = tmp_path / "out.json"
    result = CliRunner().invoke(
        app, ["bench", "gpu", "--quick", "--device", "cpu", "--json", str(path), "--env", "pong"]
    )
    assert result.exit_code == 0, result.output
    assert json.loads(path.read_text()) == {}
    assert seen["device"] == torch.device("cpu") and seen["quick"] and seen["env"] == "pong"
    assert seen["budget_seconds"] == gpu.BUDGET_SECONDS and seen["only"] is None
    result = CliRunner().invoke(
        app, ["bench", "gpu", "--device", "cpu", "--json", str(path), "--budget", "60",
              "--only", "update_ms_graph_off,exact_loop_graph_off"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    assert seen["budget_seconds"] == 60.0 and not seen["quick"]
    assert seen["only"] == frozenset({"update_ms_graph_off", "exact_loop_graph_off"})


def test_the_budget_skips_the_sections_not_yet_begun(tmp_path: Path) -> None:
    figures = gpu.run_gpu_benchmark(torch.device("cpu"), quick=True, echo=lambda _: None,
                                    budget_seconds=0.0)  # fmt: skip
    assert figures["cpu_matches_device"] == "skipped: the time budget was spent"
    assert figures["exact_loop_graph_off"] == "skipped: the time budget was spent"


def test_the_agreement_check_itself_on_cpu() -> None:
    """The CPU-against-GPU check, run with the CPU on both sides: the same bits, within
    tolerance; the code a GPU session relies on, exercised here."""
    agreement = gpu.cpu_matches_device(torch.device("cpu"), "pong", 0)
    assert agreement["bit_identical"] and agreement["within_tolerance"]
    assert agreement["largest_weight_change"] > 0


def test_only_the_named_sections_run_and_an_unknown_name_is_refused() -> None:
    figures = gpu.run_gpu_benchmark(torch.device("cpu"), quick=True, echo=lambda _: None,
                                    only=frozenset({"cpu_matches_device"}))  # fmt: skip
    assert figures["cpu_matches_device"] == gpu.NO_CUDA
    assert "exact_loop_graph_off" not in figures
    with pytest.raises(ConfigError, match="--only: unknown section nope; the sections: cpu_m"):
        gpu.run_gpu_benchmark(torch.device("cpu"), quick=True, only=frozenset({"nope"}))
