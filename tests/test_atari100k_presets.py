"""The Atari 100k presets: each value against the table of its paper and Dopamine's config
(written out here, not read from the preset), and the protocol they share."""

from __future__ import annotations

import pytest

from dqnlab.config import ATARI100K_PROTOCOL, atari100k_departures, resolve_config
from tests.test_presets import header

# The benchmark's protocol (Dopamine labs/atari_100k/configs/*.gin, atari_100k_runner.py).
PROTOCOL = {
    "sticky_action_probability": 0.0,
    "full_action_space": False,
    "life_loss_terminal": True,
    "action_repeat_frames": 4,
    "max_episode_frames": 108_000,  # 27,000 agent steps
    "total_steps": 100_000,
    "final_eval_network": "last",
    "final_eval_episodes": 100,
    "final_eval_max_episode_frames": 108_000,
    "eval_epsilon": 0.001,
}
# Data-Efficient Rainbow: van Hasselt et al. 2019, Appendix; n-step 20 (Dopamine: 10).
DER = {
    "network": "der_cnn",
    "target": "double",
    "dueling": True,
    "noisy": True,
    "noisy_sigma0": 0.1,
    "distributional": "c51",
    "distributional_atoms": 51,
    "distributional_v_min": -10.0,
    "distributional_v_max": 10.0,
    "n_step": 20,
    "replay_sampling": "prioritized",
    "priority_exponent": 0.5,
    "importance_exponent_start": 0.4,
    "replay_capacity": 100_000,
    "replay_start_steps": 1_600,
    "update_period_steps": 1,
    "target_update_steps": 2_000,
    "optimizer": "adam",
    "learning_rate": 0.0001,
    "adam_epsilon": 0.00015,
    "max_gradient_norm": 10.0,
    "batch_size": 32,
    "discount": 0.99,
    "epsilon_start": 0.0,
    "epsilon_end": 0.0,
    "augmentation": "none",
    "eval_period_steps": 0,
}
# DrQ(eps): Dopamine's DrQ_eps.gin (Agarwal et al. 2021's reference implementation).
DRQ_EPSILON = {
    "network": "auto",  # the Nature CNN
    "target": "double",
    "dueling": True,
    "noisy": False,
    "distributional": "none",
    "n_step": 10,
    "replay_sampling": "uniform",
    "replay_capacity": 100_000,
    "replay_start_steps": 1_600,
    "update_period_steps": 1,
    "target_update_steps": 1,
    "optimizer": "adam",
    "learning_rate": 0.0001,
    "adam_epsilon": 0.00015,
    "max_gradient_norm": 0.0,
    "td_error_clip": 1.0,
    "loss_reduction": "mean",
    "epsilon_start": 1.0,
    "epsilon_end": 0.01,
    "epsilon_decay_steps": 5_000,
    "augmentation": "random_shift",
    "eval_period_steps": 0,
}


@pytest.mark.parametrize(("name", "table"), [("der", DER), ("drq_epsilon", DRQ_EPSILON)])
def test_preset_holds_its_papers_values_and_the_protocol(name: str, table: dict) -> None:
    config = resolve_config(name, env="pong")
    expected = {**PROTOCOL, **table, "final_eval_after_training": True}
    assert {key: getattr(config, key) for key in expected} == expected
    assert atari100k_departures(config) == []


def test_the_protocol_in_the_code_is_the_one_written_here() -> None:
    assert ATARI100K_PROTOCOL == PROTOCOL


@pytest.mark.parametrize(
    ("name", "paper"), [("der", "arXiv:1906.05243"), ("drq_epsilon", "arXiv:2108.13264")]
)
def test_header_names_the_paper_and_dopamine(name: str, paper: str) -> None:
    text = header(name)
    assert paper in text and "google/dopamine at 5873f54" in text


def test_a_departure_is_named_with_the_protocols_value() -> None:
    config = resolve_config(
        "der", {"sticky_action_probability": 0.25, "final_eval_episodes": 30}, env="pong"
    )
    assert atari100k_departures(config) == [
        "sticky_action_probability = 0.25 (the protocol: 0.0)",
        "final_eval_episodes = 30 (the protocol: 100)",
    ]
