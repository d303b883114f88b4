"""The model card: front matter the Hub reads (written by huggingface_hub's ModelCardData
and EvalResult), the command that trains the agent again, and Nature's score."""

from __future__ import annotations

import json
import shlex
from pathlib import Path

import yaml
from huggingface_hub import ModelCard

from dqnlab.config import differing_settings, parse_overrides, resolve_config
from dqnlab.hub.card import CardFacts, card_text, nearest_preset, train_command
from dqnlab.run.rundir import load_run_config


def front_matter(text: str) -> dict:
    assert text.startswith("---\n")
    yaml_text, _, _ = text[4:].partition("\n---\n")
    return yaml.safe_load(yaml_text)


def test_the_front_matter_parses_and_carries_the_model_index(exported_folder: Path) -> None:
    text = (exported_folder / "README.md").read_text()
    results = json.loads((exported_folder / "results.json").read_text())
    meta = front_matter(text)
    assert meta["library_name"] == "dqnlab"
    assert {"CartPole-v1", "reinforcement-learning", "deep-reinforcement-learning"} <= set(
        meta["tags"]
    )
    (index,) = meta["model-index"]
    assert index["name"] == "dqn-CartPole-v1"
    (result,) = index["results"]
    assert result["task"]["type"] == "reinforcement-learning"
    assert result["dataset"] == {"name": "CartPole-v1", "type": "CartPole-v1"}
    (metric,) = result["metrics"]
    assert metric["type"] == "mean_reward"
    assert metric["value"] == f"{results['mean']:.2f} +/- {results['std']:.2f}"
    # huggingface_hub reads it back as the evaluation result it wrote.
    card = ModelCard.load(exported_folder / "README.md")
    (evaluation,) = card.data.eval_results
    assert (evaluation.task_type, evaluation.dataset_type) == (
        "reinforcement-learning",
        "CartPole-v1",
    )
    assert evaluation.metric_value == metric["value"]
    assert "dqnlab pull OWNER/NAME --run-dir runs/NAME" in text
    assert "Nature DQN" not in text  # CartPole has no Nature score
    assert "![Learning curve](learning-curve.png)" in text


def test_the_train_command_of_the_card_trains_the_same_configuration(tiny_run: Path) -> None:
    config = load_run_config(tiny_run)
    preset, differing = nearest_preset(config)
    assert preset == "classic"
    assert differing == [
        "mlp_hidden_sizes", "replay_capacity", "replay_start_steps", "eval_period_steps",
        "eval_steps", "final_eval_episodes",
    ]  # fmt: skip
    command = train_command(config, preset, differing)
    words = shlex.split(command)
    assert words[:2] == ["dqnlab", "train"]
    options: dict[str, list[str]] = {}
    for option, value in zip(words[2::2], words[3::2], strict=True):
        options.setdefault(option, []).append(value)
    rebuilt = resolve_config(
        options["--preset"][0],
        parse_overrides(options["--set"]),
        env=options["--env"][0],
        seed=int(options["--seed"][0]),
        total_steps=int(options["--steps"][0]),
    )
    assert differing_settings(rebuilt, config) == [] and rebuilt.total_steps == config.total_steps


def test_an_atari_card_gives_nature_dqns_score_and_its_preset() -> None:
    config = resolve_config("nature", env="pong")
    results = {
        "mean": 20.5, "std": 0.5, "episodes": 30, "seed": 12345, "epsilon": 0.05,
        "max_episode_frames": 18_000, "checkpoint": "best",
    }  # fmt: skip
    text = card_text(CardFacts(config, results, 49_750_000, ["model.safetensors"], "me/pong"))
    assert "Nature DQN (Mnih et al. 2015, Extended Data Table 2) on this game: 18.9 ± 1.3." in text
    assert "dqnlab train --env pong --preset nature --seed 0 --steps 50000000\n" in text
    assert "Settings that differ" not in text
    assert "dqnlab pull me/pong --run-dir runs/pong" in text
    assert "up to 30 random no-op frames" in text
    double = resolve_config("double", env="breakout", learning_rate=1e-4)
    assert nearest_preset(double) == ("double", ["learning_rate"])
