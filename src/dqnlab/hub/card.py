"""The model card of an exported folder: README.md with the Hub's metadata in its YAML front
matter, then what a reader needs to trust and reuse the agent.

The metadata follows what the Hub's reinforcement-learning pages read, as the libraries
that publish agents there write it (huggingface_sb3's `generate_metadata`, CleanRL's
`cleanrl_utils/huggingface.py`): `library_name`, tags with the environment id,
`reinforcement-learning` and `deep-reinforcement-learning`, and a `model-index` whose one
result has task type `reinforcement-learning`, the environment as its dataset, and the
metric `mean_reward` with the value "mean +/- std". The front matter is written by
huggingface_hub's `ModelCardData` and `EvalResult`, which own the `model-index` schema.
"""

from __future__ import annotations

import shlex
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from huggingface_hub import EvalResult, ModelCard, ModelCardData

from dqnlab import __version__
from dqnlab.analysis.report.reference import family_parts
from dqnlab.analysis.report.scores import load_reference_scores
from dqnlab.config import Config, differing_settings, preset_names, resolve_config, setting_text
from dqnlab.envs import default_preset, is_atari
from dqnlab.run import exported
from dqnlab.run.rundir import safe_name, with_recorded_network

TASK = "reinforcement-learning"
TAGS = ("reinforcement-learning", "deep-reinforcement-learning", "dqnlab")
METRIC = "mean_reward"
# Set by their own options of `dqnlab train`, not by --set.
OWN_OPTIONS = ("env", "seed", "total_steps")


@dataclass(frozen=True)
class CardFacts:
    """What the card says, all read from the exported folder's files."""

    config: Config
    results: dict[str, Any]  # results.json
    step: int | None  # the training step of the network
    files: Sequence[str]  # the folder's file names
    repo_id: str | None = None  # where it is pushed; None: a placeholder in the commands


def model_name(config: Config, repo_id: str | None) -> str:
    """The name in the model-index: the repository's name, else dqn-ENV."""
    return repo_id.split("/")[-1] if repo_id else f"dqn-{safe_name(config.env)}"


def metric_value(results: dict[str, Any]) -> str:
    """`mean +/- std`, as the Hub's RL leaderboard and huggingface_sb3 write it."""
    return f"{float(results['mean']):.2f} +/- {float(results['std']):.2f}"


def card_data(facts: CardFacts) -> ModelCardData:
    env = facts.config.env
    result = EvalResult(
        task_type=TASK,
        task_name=TASK,
        dataset_type=env,
        dataset_name=env,
        metric_type=METRIC,
        metric_name=METRIC,
        metric_value=metric_value(facts.results),
    )
    return ModelCardData(
        library_name="dqnlab",
        tags=[env, *TAGS],
        model_name=model_name(facts.config, facts.repo_id),
        eval_results=[result],
    )


def nearest_preset(config: Config) -> tuple[str, list[str]]:
    """The shipped preset `config` differs from in the fewest settings (ties: the one a
    run of its environment gets by default), and those settings, in `Config` order,
    less those `dqnlab train` takes as options of their own."""
    default = default_preset(config.env)
    candidates = []
    for name in [default, *(n for n in preset_names() if n != default)]:
        # At the run's budget: a preset's budget-scaled settings (epsilon_decay_fraction)
        # are compared as `train --steps` makes them.
        resolved = resolve_config(name, env=config.env, total_steps=config.total_steps)
        preset = with_recorded_network(resolved, config)
        differing = [s for s in differing_settings(preset, config) if s not in OWN_OPTIONS]
        candidates.append((len(differing), name, differing))
    _, name, differing = min(candidates, key=lambda candidate: candidate[0])  # first on ties
    return name, differing


def train_command(config: Config, preset: str, differing: Sequence[str]) -> str:
    """The `dqnlab train` command that trains this configuration again."""
    words = ["dqnlab", "train", "--env", config.env, "--preset", preset]
    words += ["--seed", str(config.seed), "--steps", str(config.total_steps)]
    for name in differing:
        words += ["--set", f"{name}={setting_text(getattr(config, name))}"]
    return " ".join(shlex.quote(word) for word in words)


def _agent_name(config: Config) -> str:
    parts = family_parts(config)
    return "DQN" + (f" with {', '.join(parts)}" if parts else "")


def _evaluation_lines(facts: CardFacts) -> list[str]:
    config, results = facts.config, facts.results
    frames = int(results.get("max_episode_frames", 0))
    cap = (
        f"games of at most {frames:,} frames"
        if frames
        else "games as long as the environment lets them run"
    )
    lines = [
        "## Evaluation",
        "",
        f"**{float(results['mean']):.2f} ± {float(results['std']):.2f}** (mean ± s.d. over "
        f"{results['episodes']} games) on `{config.env}`, with dqnlab's final protocol: "
        f"ε = {results['epsilon']}, {cap}"
        + (
            f", up to {config.noop_max_frames} random no-op frames at each start"
            if is_atari(config.env)
            else ""
        )
        + f"; evaluation seed {results['seed']}. The network is the one of training step "
        f"{facts.step if facts.step is not None else 'unknown'}"
        + (" (the best periodic evaluation)." if results.get("checkpoint") == "best" else "."),
    ]
    if is_atari(config.env):
        reference = load_reference_scores().get(config.env)
        if reference is not None and reference.nature_dqn is not None:
            spread = (
                f" ± {reference.nature_dqn_std:g}" if reference.nature_dqn_std is not None else ""
            )
            lines += [
                "",
                f"Nature DQN (Mnih et al. 2015, Extended Data Table 2) on this game: "
                f"{reference.nature_dqn:g}{spread}.",
            ]
    return lines


def card_text(facts: CardFacts) -> str:
    """The body of README.md, below the front matter."""
    config = facts.config
    repo = facts.repo_id or "OWNER/NAME"
    preset, differing = nearest_preset(config)
    files = set(facts.files)
    lines = [
        f"# {_agent_name(config)} playing {config.env}",
        "",
        f"A {_agent_name(config)} agent trained with [dqnlab](https://pypi.org/project/dqnlab/) "
        f"{__version__} for {config.total_steps:,} agent steps (seed {config.seed}), settings "
        f"closest to the `{preset}` preset. The network is `{exported.MODEL_FILE}` (no pickle); "
        f"its configuration, input shape and action names are in the file's metadata and in "
        f"`{exported.CONFIG_FILE}`.",
        "",
        *_evaluation_lines(facts),
        "",
    ]
    for video in (f"{exported.VIDEO_STEM}.mp4", f"{exported.VIDEO_STEM}.gif"):
        if video in files:
            lines += [f"One evaluation game, filmed: [{video}]({video}).", ""]
    if exported.CURVE_FILE in files:
        lines += [f"![Learning curve]({exported.CURVE_FILE})", ""]
    lines += [
        "## Evaluate it yourself",
        "",
        "```",
        "pip install 'dqnlab[hub]'",
        f"dqnlab pull {repo} --run-dir runs/{repo.split('/')[-1]}",
        f"dqnlab evaluate runs/{repo.split('/')[-1]} --seed {facts.results['seed']} "
        f"--episodes {facts.results['episodes']}",
        "```",
        "",
        "## Train it again",
        "",
        "```",
        train_command(config, preset, differing),
        "```",
        "",
        f"or with every setting of this folder's `{exported.CONFIG_FILE}`, in the folder: "
        f"`dqnlab train --env {shlex.quote(config.env)} --preset {exported.CONFIG_FILE}`.",
        "",
    ]
    if differing:
        preset_config = resolve_config(preset, env=config.env, total_steps=config.total_steps)
        lines += [
            f"## Settings that differ from the `{preset}` preset",
            "",
            "| setting | this agent | preset |",
            "| --- | --- | --- |",
        ]
        for name in differing:
            mine = setting_text(getattr(config, name))
            theirs = setting_text(getattr(preset_config, name))
            lines.append(f"| `{name}` | `{mine}` | `{theirs}` |")
        lines.append("")
    return "\n".join(lines).rstrip("\n") + "\n"


def model_card(facts: CardFacts) -> ModelCard:
    """README.md: the front matter from `card_data`, then `card_text`."""
    return ModelCard(f"---\n{card_data(facts).to_yaml()}\n---\n\n{card_text(facts)}")
