"""`dqnlab games` and `dqnlab presets`."""

from __future__ import annotations

from pathlib import Path

from tests.helpers import dqnlab


def test_lists(tmp_path: Path) -> None:
    games = dqnlab("games")
    assert games.returncode == 0 and "space_invaders" in games.stdout.split()
    presets = dqnlab("presets")
    assert presets.stdout.split() == [
        "c51", "classic", "der", "double", "drq_epsilon", "dueling", "iqn", "machado",
        "nature", "prioritized", "qrdqn", "rainbow", "seed-paper", "tuned/Acrobot-v1",
        "tuned/CartPole-v1", "tuned/LunarLander-v3", "tuned/MountainCar-v0",
    ]  # fmt: skip
    nature = dqnlab("presets", "nature")
    assert "learning_rate = 0.00025" in nature.stdout
