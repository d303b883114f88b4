"""The run directory: the one module that knows its files, their names, and what may be
kept or replaced. Everything else asks it.

    RUN_DIR/
        config.toml              the resolved configuration (`load_run_config`)
        episodes.csv             one row per training game (`logs.RunLogger`)
        evaluations.csv          one row per periodic evaluation
        tensorboard/             the same figures for TensorBoard
        final_evaluation.json    the final evaluation of the best network
        checkpoints/
            best.pt, worst.pt, last.pt    network files (`save_network`)
            evals/step-NNNNNNNNN.pt       every evaluated network (eval_networks_kept = "all")
            step-NNNNNNNNN/, replay/      training checkpoints (`checkpoints.CheckpointStore`)
        inspect/                 what `dqnlab inspect` writes by default
        wandb/                   W&B's own files: a directory per session, offline runs
                                 to `wandb sync` (logger = "tensorboard+wandb")
        wandb_run.json           the W&B run this run logs to, reopened on resume
        lease.json               who trains the run now (`lease.RunLease`)
        attempts.jsonl           one line per start and end of a sweep's attempt

    SWEEP/                       a sweep directory (`dqnlab sweep`, `dqnlab ablate`)
        sweep.json               the grid and the marker every node checks it sees
        logs/NAME.log, NAME.toml each run's output and its whole configuration
        RUN/ ...                 one run directory per run
        report/                  the sweep's report

A *network file* holds one network and what is needed to play it: the configuration it
was trained with, its input shape, dtype and action names, and the step (and periodic
evaluation mean) at which it was saved. A *training checkpoint* holds the whole training
state; `checkpoints` owns those.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shutil
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dqnlab import __version__
from dqnlab.algorithm.agent import Agent, agent_for_input
from dqnlab.algorithm.networks import ENCODED_NETWORKS
from dqnlab.config import (
    Config,
    config_fingerprint,
    config_from_dict,
    config_to_toml,
    derive_seeds,
    differing_settings,
    with_evaluation_settings,
)
from dqnlab.envs.spaces import ObservationLayout
from dqnlab.errors import DqnlabError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

CONFIG_FILE = "config.toml"
EPISODES_FILE = "episodes.csv"
EVALUATIONS_FILE = "evaluations.csv"
DIGESTS_FILE = "digests.csv"  # run/digests.py
TENSORBOARD_DIR = "tensorboard"
FINAL_EVALUATION_FILE = "final_evaluation.json"
CHECKPOINTS_DIR = "checkpoints"
NETWORK_NAMES = ("best", "worst", "last")
EVAL_NETWORKS_DIR = "evals"  # under checkpoints/: one network per periodic evaluation
INSPECT_DIR = "inspect"
WANDB_DIR = "wandb"  # wandb.init(dir=RUN_DIR) names it
WANDB_RUN_FILE = "wandb_run.json"
LEASE_FILE = "lease.json"
ATTEMPTS_FILE = "attempts.jsonl"
SESSION_FILES = (LEASE_FILE, ATTEMPTS_FILE)  # who trains it: a directory of only these is new
SWEEP_FILE = "sweep.json"
SWEEP_LOGS_DIR = "logs"
NETWORK_FORMAT = "dqnlab-checkpoint-1"  # the format tag of a network file
_EVAL_NETWORK_FILE = re.compile(r"step-(\d+)\.pt")


# Layout --------------------------------------------------------------------------------


def is_run_dir(path: Path) -> bool:
    return (path / CONFIG_FILE).is_file()


def episodes_path(run_dir: Path) -> Path:
    return run_dir / EPISODES_FILE


def evaluations_path(run_dir: Path) -> Path:
    return run_dir / EVALUATIONS_FILE


def digests_path(run_dir: Path) -> Path:
    return run_dir / DIGESTS_FILE


def tensorboard_dir(run_dir: Path) -> Path:
    return run_dir / TENSORBOARD_DIR


def checkpoints_dir(run_dir: Path) -> Path:
    return run_dir / CHECKPOINTS_DIR


def inspect_dir(run_dir: Path) -> Path:
    return run_dir / INSPECT_DIR


def wandb_dir(run_dir: Path) -> Path:
    return run_dir / WANDB_DIR


def wandb_run_path(run_dir: Path) -> Path:
    return run_dir / WANDB_RUN_FILE


def lease_path(run_dir: Path) -> Path:
    return run_dir / LEASE_FILE


def attempts_path(run_dir: Path) -> Path:
    return run_dir / ATTEMPTS_FILE


def sweep_file_path(sweep_dir: Path) -> Path:
    return sweep_dir / SWEEP_FILE


def sweep_logs_dir(sweep_dir: Path) -> Path:
    return sweep_dir / SWEEP_LOGS_DIR


def network_path(run_dir: Path, name: str) -> Path:
    """The network file `name` ("best", "worst" or "last") of the run."""
    if name not in NETWORK_NAMES:
        raise ValueError(f"network {name!r} is not one of {NETWORK_NAMES}")
    return checkpoints_dir(run_dir) / f"{name}.pt"


def eval_network_path(run_dir: Path, step: int) -> Path:
    """Where `eval_networks_kept = "all"` keeps the network evaluated at `step`."""
    return checkpoints_dir(run_dir) / EVAL_NETWORKS_DIR / f"step-{step:09d}.pt"


def eval_network_steps(run_dir: Path) -> list[int]:
    """The steps whose evaluated network is kept (`eval_networks_kept = "all"`)."""
    directory = checkpoints_dir(run_dir) / EVAL_NETWORKS_DIR
    if not directory.is_dir():
        return []
    matches = (_EVAL_NETWORK_FILE.fullmatch(path.name) for path in directory.iterdir())
    return sorted(int(match.group(1)) for match in matches if match)


def safe_name(text: str) -> str:
    """An environment name (module:Env, ALE/Pong-v5) as a directory name part."""
    return text.replace(":", "_").replace("/", "_")


def preset_label(preset: str) -> str:
    """A preset as a directory name part: a preset file by its stem, tuned settings as
    `tuned`."""
    return "tuned" if preset.startswith("tuned/") else safe_name(Path(preset).stem)


def default_run_dir(env: str, preset: str, seed: int) -> Path:
    return Path("runs") / f"{safe_name(env)}-{preset_label(preset)}-s{seed}"


def default_sweep_dir(env: str, keys: Sequence[str]) -> Path:
    return Path("sweeps") / f"{safe_name(env)}-{'+'.join(keys)}"


# The configuration ---------------------------------------------------------------------


def load_run_config(run_dir: Path) -> Config:
    path = run_dir / CONFIG_FILE
    if not path.is_file():
        raise DqnlabError(f"{run_dir} is not a dqnlab run directory (no {CONFIG_FILE})")
    try:
        with path.open("rb") as handle:
            return config_from_dict(tomllib.load(handle))
    except tomllib.TOMLDecodeError as error:
        raise DqnlabError(f"{path} is not valid TOML: {error}") from None


def write_run_config(run_dir: Path, config: Config) -> None:
    (run_dir / CONFIG_FILE).write_text(config_to_toml(config))


def prepare_run_dir(run_dir: Path, force: bool, config: Config | None = None) -> bool:
    """Make `run_dir` ready for `config`; True when it holds the same run, to be resumed.

    An existing run with the same settings (the step budget may differ) is resumed, its
    config.toml updated to the new budget; one with other settings is refused unless
    `force`, which deletes it. Only a directory holding a dqnlab run (its config.toml) is
    ever deleted, so a mistyped `--run-dir . --force` cannot wipe a project.
    """
    if run_dir.exists() and not run_dir.is_dir():
        raise DqnlabError(f"--run-dir {run_dir} exists and is not a directory")
    if run_dir.exists() and any(path.name not in SESSION_FILES for path in run_dir.iterdir()):
        if force and is_run_dir(run_dir):
            shutil.rmtree(run_dir)
        elif force:
            raise DqnlabError(
                f"--force refuses to delete {run_dir}: it is not a dqnlab run directory "
                f"(no {CONFIG_FILE}); choose an empty or new --run-dir"
            )
        elif is_run_dir(run_dir) and config is not None:
            saved = load_run_config(run_dir)
            config = with_recorded_network(config, saved)
            differing = differing_settings(saved, config)
            if not differing:
                update_run_config(run_dir, config)
                return True
            raise DqnlabError(
                f"run directory {run_dir} holds a run with other settings "
                f"({', '.join(differing)}); continue it with `dqnlab resume {run_dir}`, "
                "choose another --run-dir, or pass --force to delete it and start over"
            )
        else:
            raise DqnlabError(
                f"run directory {run_dir} already exists and is not empty; "
                "choose another --run-dir or pass --force to overwrite it"
            )
    run_dir.mkdir(parents=True, exist_ok=True)
    return False


def with_recorded_network(config: Config, saved: Config) -> Config:
    """`config` with `network = auto` read as the network the saved run wrote out for it
    (`networks.recorded_network_name`), so that the same command continues the run."""
    if config.network == "auto" and saved.network in ENCODED_NETWORKS:
        return dataclasses.replace(config, network=saved.network)
    return config


def update_run_config(run_dir: Path, config: Config) -> None:
    """Rewrite config.toml for a resume with settings a run may change (a new budget, a
    checkpoint cadence); any other change is refused."""
    saved = load_run_config(run_dir)
    if config_fingerprint(saved) != config_fingerprint(config):
        raise DqnlabError(
            f"{run_dir} holds a run with other settings "
            f"({', '.join(differing_settings(saved, config))})"
        )
    if saved != config:
        write_run_config(run_dir, config)


# Network files -------------------------------------------------------------------------


def network_payload(
    config: Config,
    input_shape: tuple[int, ...],
    observation_dtype: np.dtype,
    action_names: Sequence[str],
    step: int,
    network: torch.nn.Module | dict[str, torch.Tensor],
    eval_mean: float | None = None,
    layout: ObservationLayout | None = None,
) -> dict[str, Any]:
    """What a network file holds: the network (a module, or its state dict: a snapshot)
    and everything needed to play it (with the observation's layout when it is not a
    single frame: `envs/spaces.py`)."""
    payload = {
        "config": config.to_dict(),
        "input_shape": tuple(input_shape),
        "observation_dtype": np.dtype(observation_dtype).str,
        "action_names": list(action_names),
        "step": step,
        "network": network if isinstance(network, dict) else network.state_dict(),
    }
    if eval_mean is not None:
        payload["eval_mean"] = eval_mean
    if layout is not None:
        payload["observation_layout"] = layout.to_dict()
    return payload


def save_network(path: Path, payload: dict[str, Any]) -> None:
    """Write a network file atomically: to a temporary file, flushed to disk, then renamed
    over the old one, so a crash never leaves a half-written file under the real name."""
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(path.name + ".tmp")
    with temporary.open("wb") as handle:
        torch.save({"format": NETWORK_FORMAT, "version": __version__, **payload}, handle)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(temporary, path)


def load_network(path: Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """A network file's payload, read without unpickling anything but tensors and plain
    Python values."""
    if not path.is_file():
        raise DqnlabError(f"no network file at {path}")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as error:  # noqa: BLE001 - any unreadable file gets the same answer
        raise DqnlabError(f"network file {path} cannot be read: {error}") from None
    if not isinstance(payload, dict) or payload.get("format") != NETWORK_FORMAT:
        raise DqnlabError(f"{path} is not a dqnlab network file of format {NETWORK_FORMAT}")
    return payload


def network_step(run_dir: Path, name: str) -> int | None:
    """The training step of the run's network `name`, None if it has none yet."""
    path = network_path(run_dir, name)
    if not path.is_file():
        return None
    step = load_network(path).get("step")
    return int(step) if step is not None else None


def trained_to_budget(run_dir: Path, total_steps: int) -> bool:
    """Whether the run is done: its last network has reached `total_steps` and, for a run
    whose protocol ends with its final evaluation (`final_eval_after_training`, Atari
    100k's), that evaluation is saved, so a run killed while playing it is not done."""
    step = network_step(run_dir, "last") if is_run_dir(run_dir) else None
    if step is None or step < total_steps:
        return False
    if not load_run_config(run_dir).final_eval_after_training:
        return True
    return load_final_evaluation(run_dir) is not None


def agent_from_network(
    payload: dict[str, Any],
    path: Path,
    seed: int,
    device: torch.device,
    settings: dict[str, Any] | None = None,
) -> tuple[Agent, Config, int]:
    """An agent with the network saved in `payload` (read from `path`), built from the
    configuration, input shape and action names stored beside it (with `settings`, how it
    plays: `with_evaluation_settings`), its epsilon-greedy draws seeded with child 1 of
    `seed`; and child 0, which seeds the environments it plays."""
    config = with_evaluation_settings(config_from_dict(payload["config"]), settings or {})
    env_seed, agent_seed = derive_seeds(seed, 2)
    try:
        input_shape = tuple(int(n) for n in payload["input_shape"])
        action_names = [str(name) for name in payload["action_names"]]
    except KeyError as error:
        raise DqnlabError(f"network file {path} lacks {error}") from None
    agent = agent_for_input(
        config,
        input_shape,
        _observation_dtype(payload, input_shape),
        action_names,
        device,
        agent_seed,
        _observation_layout(payload, path),
    )
    try:
        agent.online.load_state_dict(payload["network"])
    except RuntimeError as error:
        raise DqnlabError(f"network file {path} does not fit its network: {error}") from None
    return agent, config, env_seed


def _observation_layout(payload: dict[str, Any], path: Path) -> ObservationLayout | None:
    """The layout stored beside the network; None (a single frame) in files without one."""
    if "observation_layout" not in payload:
        return None
    try:
        return ObservationLayout.from_dict(payload["observation_layout"])
    except (KeyError, TypeError, ValueError) as error:
        raise DqnlabError(
            f"network file {path} has an unreadable observation layout: {error}"
        ) from None


def _observation_dtype(payload: dict[str, Any], input_shape: tuple[int, ...]) -> np.dtype:
    """The stored dtype; files written before it was stored hold images (uint8) when an
    observation has two axes or more, vectors (float32) otherwise."""
    if "observation_dtype" in payload:
        return np.dtype(payload["observation_dtype"])
    return np.dtype(np.uint8 if len(input_shape) >= 3 else np.float32)


def keep_evaluated_network(
    run_dir: Path,
    config: Config,
    earlier: list[tuple[int, float]],
    step: int,
    mean: float,
    payload: dict[str, Any],
) -> None:
    """Keep the network just evaluated for `dqnlab inspect`: a file per evaluation
    (`eval_networks_kept = "all"`), and `worst.pt`, the lowest mean among evaluations in
    the last three quarters of the budget (the seed paper compares the best network with
    "a network that performed poorly very late into training"; ties go to the later)."""
    if config.eval_networks_kept == "all":
        save_network(eval_network_path(run_dir, step), payload)
    quarter = config.total_steps / 4
    if step >= quarter and all(mean <= m for s, m in earlier if s >= quarter):
        save_network(network_path(run_dir, "worst"), payload)


# Final evaluations ---------------------------------------------------------------------


def final_evaluation_path(run_dir: Path) -> Path:
    return run_dir / FINAL_EVALUATION_FILE


def save_final_evaluation(run_dir: Path, record: dict[str, Any]) -> Path:
    """Write `record` as the run's final evaluation (read by `dqnlab report`)."""
    return write_json_file(final_evaluation_path(run_dir), record)


def write_json_file(path: Path, record: dict[str, Any]) -> Path:
    """`record` as an indented JSON file, written whole or not at all (a temporary file
    replaced), so a kill never leaves half a record for `read_json_file`."""
    temporary = path.with_name(path.name + ".tmp")
    temporary.write_text(json.dumps(record, indent=2) + "\n")
    os.replace(temporary, path)
    return path


def load_final_evaluation(run_dir: Path) -> dict[str, Any] | None:
    """The run's saved final evaluation, or None if it has none yet."""
    return read_json_file(final_evaluation_path(run_dir))


def read_json_file(path: Path) -> dict[str, Any] | None:
    """A JSON file of a run or sweep directory, None if it does not exist; a damaged one
    is a one-line error naming it."""
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise DqnlabError(f"{path} is not valid JSON: {error}") from None


def record_final_evaluation(run_dir: Path, record: dict[str, Any]) -> tuple[Path, bool]:
    """Save `record` (an evaluation of the best network) as the run's final evaluation,
    unless the saved one holds more games of the same network, which is kept. Returns the
    file and whether it was written."""
    saved = load_final_evaluation(run_dir)
    if (
        saved is not None
        and saved.get("checkpoint_step") == record["checkpoint_step"]
        and int(saved["episodes"]) > int(record["episodes"])
    ):
        return final_evaluation_path(run_dir), False
    return save_final_evaluation(run_dir, record), True
