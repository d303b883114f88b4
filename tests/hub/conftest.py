"""A tiny CartPole run trained once, and its export, shared by the tests of sharing."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from dqnlab.config import resolve_config
from dqnlab.run.rundir import prepare_run_dir
from dqnlab.run.train import train

pytest.importorskip("huggingface_hub", reason="the hub extra: pip install -e '.[hub]'")
pytest.importorskip("safetensors", reason="the hub extra: pip install -e '.[hub]'")

EVALUATION_SEED = 4


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """600 steps of CartPole-v1 under the classic preset with a tiny MLP, evaluated every
    200 steps: best, worst and last networks, a learning curve; no final evaluation."""
    config = resolve_config(
        "classic", env="CartPole-v1", total_steps=600, replay_start_steps=200,
        eval_period_steps=200, eval_steps=200, final_eval_episodes=3,
        mlp_hidden_sizes=(16, 16), replay_capacity=1000, seed=1,
    )  # fmt: skip
    run = tmp_path_factory.mktemp("hub") / "run"
    prepare_run_dir(run, force=False)
    train(config, run, torch.device("cpu"), progress=False, tensorboard=False)
    return run


@pytest.fixture(scope="session")
def exported_folder(tiny_run: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """`tiny_run` exported (with a video); tests that change it work on a copy."""
    from dqnlab.hub.export import export_run

    out = tmp_path_factory.mktemp("exported") / "cartpole"
    export_run(tiny_run, out, seed=EVALUATION_SEED, device=torch.device("cpu"), echo=lambda _: None)
    return out
