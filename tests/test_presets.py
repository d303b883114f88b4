"""The shipped presets: each resolves, and each DQN-family preset is its paper's agent.

What each family preset must be, from docs/dqn-family.md: the nature preset with the
settings its paper changes, and the nature preset's Atari pipeline and evaluation protocol.
"""

from __future__ import annotations

import pytest

from dqnlab.config import Config, load_preset, preset_names, resolve_config

# The paper each family preset reproduces, as its header must name it (arXiv id and year).
FAMILY = {
    "double": ("van Hasselt", "2016", "1509.06461"),
    "dueling": ("Wang", "2016", "1511.06581"),
    "prioritized": ("Schaul", "2016", "1511.05952"),
    "c51": ("Bellemare", "2017", "1707.06887"),
    "rainbow": ("Hessel", "2018", "1710.02298"),
    "qrdqn": ("Dabney", "2018", "1710.10044"),
    "iqn": ("Dabney", "2018", "1806.06923"),
}
# The presets whose loss is the idea tested (their own loss part), not Nature's.
OWN_LOSS = ("qrdqn", "iqn")

# The team's decision: the pipeline and the evaluation protocol stay the Nature DQN's in
# every family preset, so that presets differ only by the idea tested.
NATURE_EVERYWHERE = (
    "action_repeat_frames", "frame_pooling", "grayscale", "byte_conversion",
    "resize_interpolation", "screen_size", "noop_max_frames", "sticky_action_probability",
    "full_action_space", "life_loss_terminal", "max_episode_frames", "reward_clip",
    "history_length", "network", "torso", "loss", "replay_capacity", "batch_size",
    "update_period_steps", "discount", "eval_epsilon", "eval_period_steps", "eval_steps",
    "eval_max_episode_frames", "heldout_transitions", "final_eval_episodes",
    "final_eval_max_episode_frames", "total_steps",
)  # fmt: skip


def resolved(name: str) -> Config:
    return resolve_config(name, env="pong")


def differences(name: str) -> dict[str, tuple[object, object]]:
    nature, preset = resolved("nature").to_dict(), resolved(name).to_dict()
    # `preset` records the name each was loaded by.
    return {k: (nature[k], v) for k, v in preset.items() if nature[k] != v and k != "preset"}


def header(name: str) -> str:
    """The leading comment block of a shipped preset's file."""
    from importlib import resources

    text = (resources.files("dqnlab") / "presets" / f"{name}.toml").read_text()
    lines = []
    for line in text.splitlines():
        if not line.startswith("#"):
            break
        lines.append(line)
    return "\n".join(lines)


@pytest.mark.parametrize("name", preset_names())
@pytest.mark.parametrize("env", ["pong", "CartPole-v1"])
def test_every_shipped_preset_resolves(name: str, env: str) -> None:
    assert resolve_config(name, env=env).env == env


def test_the_family_presets_are_shipped() -> None:
    assert set(FAMILY) <= set(preset_names())


@pytest.mark.parametrize("name", FAMILY)
def test_header_names_the_paper(name: str) -> None:
    author, year, arxiv = FAMILY[name]
    text = header(name)
    assert author in text and year in text and f"arXiv:{arxiv}" in text, name


@pytest.mark.parametrize("name", FAMILY)
def test_pipeline_and_evaluation_stay_natures(name: str) -> None:
    changed = set(differences(name)) & set(NATURE_EVERYWHERE)
    changed -= {"loss"} if name in OWN_LOSS else set()
    assert not changed, f"{name} changes {sorted(changed)}"


@pytest.mark.parametrize("name", FAMILY)
def test_every_changed_setting_cites_a_source(name: str) -> None:
    """Each line that sets a value differing from nature carries a comment."""
    changed = differences(name)
    values = load_preset(name)
    assert set(changed) <= set(values)
    from importlib import resources

    text = (resources.files("dqnlab") / "presets" / f"{name}.toml").read_text()
    table = None  # within a [parts.PART] table: the part's own settings
    for line in text.splitlines():
        if line.startswith("["):
            table = line.strip("[]")
        key = line.split("=", 1)[0].strip()
        if key in changed or (table and "=" in line):
            assert "#" in line, f"{name}: {table or ''} {key} has no source"


def test_double_differs_from_nature_only_in_the_target() -> None:
    assert differences("double") == {"target": ("max", "double")}


def test_dueling_is_double_dqn_with_a_dueling_head_and_clipped_gradients() -> None:
    config = resolved("dueling")
    assert config.dueling and config.target == "double"
    assert config.max_gradient_norm == 10.0
    assert config.learning_rate < resolved("double").learning_rate  # "slightly lower"
    assert not config.noisy and config.distributional == "none"
    assert config.replay_sampling == "uniform"


def test_prioritized_is_proportional_replay_on_the_tuned_double_dqn() -> None:
    config, nature = resolved("prioritized"), resolved("nature")
    assert config.replay_sampling == "prioritized" and config.target == "double"
    assert (config.priority_exponent, config.importance_exponent_start) == (0.6, 0.4)
    assert config.learning_rate == nature.learning_rate / 4  # Appendix B.2.2, Table 3
    assert (config.target_update_steps, config.epsilon_end) == (30_000, 0.01)  # tuned DDQN
    assert not config.dueling and config.distributional == "none" and config.n_step == 1


def test_c51_is_the_categorical_loss_with_uniform_one_step_replay() -> None:
    config = resolved("c51")
    assert config.distributional == "c51" and config.distributional_atoms == 51
    assert (config.distributional_v_min, config.distributional_v_max) == (-10.0, 10.0)
    assert config.replay_sampling == "uniform" and config.n_step == 1
    assert config.target == "max"  # the target network picks the next action
    assert (config.optimizer, config.adam_epsilon) == ("adam", 0.01 / 32)
    assert config.loss_reduction == "mean" and config.target_update_steps == 10_000
    assert not config.dueling and not config.noisy


def test_rainbow_combines_all_six_parts() -> None:
    config = resolved("rainbow")
    assert config.target == "double" and config.dueling and config.noisy
    assert config.distributional == "c51" and config.distributional_atoms == 51
    assert config.n_step == 3
    assert config.replay_sampling == "prioritized" and config.priority_exponent == 0.5
    assert (config.optimizer, config.learning_rate, config.adam_epsilon) == (
        "adam",
        0.0000625,
        0.00015,
    )
    # Table 1 in frames, dqnlab in agent steps of 4 frames.
    assert config.target_update_steps * config.action_repeat_frames == 32_000
    assert config.replay_start_steps * config.action_repeat_frames == 80_000
    assert config.epsilon_start == config.epsilon_end == 0.0  # noisy nets explore
