"""One round of the peers, as `dqnlab bench` alternates them with dqnlab's own rounds."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from dqnlab.bench.cleanrl import CleanRLPeer, prepare_cleanrl, run_cleanrl_dqn
from dqnlab.bench.sb3 import peer_available, run_sb3_dqn
from dqnlab.config import Config
from dqnlab.errors import DqnlabError
from dqnlab.run.denormals import denormals_kept


def prepare_peers(
    sb3: bool, cleanrl_dir: Path | None, cleanrl_venv: Path | None
) -> CleanRLPeer | None:
    """Before anything is timed: Stable-Baselines3 importable (with `sb3`), and CleanRL's
    checkout checked and its venv checked or made (with `cleanrl_dir`); one line each
    when not."""
    if cleanrl_venv is not None and cleanrl_dir is None:
        raise DqnlabError("--cleanrl-venv is for --cleanrl DIR: give the CleanRL checkout")
    if sb3 and not peer_available():
        raise DqnlabError(
            "--peers needs Stable-Baselines3: pip install 'dqnlab[bench]' (or -e '.[bench]')"
        )
    return prepare_cleanrl(cleanrl_dir, cleanrl_venv) if cleanrl_dir is not None else None


def peer_round(
    config: Config,
    steps: int,
    learning_starts: int,
    device: torch.device,
    sb3: bool,
    cleanrl: CleanRLPeer | None,
) -> tuple[dict[str, Any] | None, dict[str, Any] | None]:
    """Stable-Baselines3's DQN (with `sb3`) and CleanRL's `dqn_atari.py` (with `cleanrl`)
    on `config`'s game and seed, each timed over `steps` agent steps after
    `learning_starts`, by the end of which its ε has reached 0.1, as dqnlab's rounds are
    measured; None for a peer not asked for."""
    sb3_run = None
    if sb3:
        with denormals_kept():  # SB3 as its users run it
            sb3_run = run_sb3_dqn(
                config.env, steps, learning_starts, config.seed, str(device),
                epsilon_decay_steps=learning_starts,
            )  # fmt: skip
    cleanrl_run = None
    if cleanrl is not None:
        cleanrl_run = run_cleanrl_dqn(cleanrl, config, steps, learning_starts, device)
    return sb3_run, cleanrl_run
