"""The data of a Q-value inspection: what the run's networks think of the same frames.

The seed paper (Roderick et al. 2017, "Implementing the Deep Q-Network", figure of
Q-values) shows the Q-values of the best network and of a network that performed poorly
late in training on the same Breakout frames. `compare_networks` does that for any run: it
picks frames from one evaluation game of the best network, or takes stacked network
inputs saved earlier (an earlier inspection's `observations.npy`, which `write.py` saves),
and gives each network's Q-value per action on them. No figures, no files: `figures.py`
draws an `Inspection`, `write.py` writes it.

Frames are picked from the first game the best network plays under the evaluation
protocol (`eval_epsilon`, random no-op starts, games of at most
`final_eval_max_episode_frames`), stacked as `play.play` stacks them, bounded to the
first `max_game_steps` agent steps: the game is played once to learn its length, then
replayed with the same actions to keep the chosen steps' inputs and screens (holding
every screen of a long game would take 100 kB a step).
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from dqnlab.algorithm.agent import Agent
from dqnlab.config import Config, derive_seeds
from dqnlab.envs import Environment, make_env
from dqnlab.envs.atari import AtariEnv
from dqnlab.envs.spaces import ObservationLayout
from dqnlab.errors import DqnlabError
from dqnlab.run import exported, rundir
from dqnlab.run.logs import read_csv
from dqnlab.run.play import EvaluationResult, play

CHECKPOINT_NAMES = ("best", "worst")
DEFAULT_FRAMES = 8
DEFAULT_MAX_GAME_STEPS = 2_000  # about 2 minutes of Atari play at 4 frames a step
# The inputs an inspection saves (`write.py`) and takes again with their screens.
OBSERVATIONS_FILE = "observations.npy"
SCREENS_FILE = "screens.npy"


@dataclass(frozen=True)
class InspectedNetwork:
    """One network compared: where it came from and how it scored when it was evaluated."""

    name: str  # "best", "worst" or "step 250000"
    path: Path
    step: int  # training step at which it was saved
    eval_mean: float  # its periodic evaluation's mean score; NaN if never evaluated

    @property
    def legend_label(self) -> str:
        mean = "not evaluated" if math.isnan(self.eval_mean) else f"eval mean {self.eval_mean:.1f}"
        if self.name.startswith("step"):
            return f"step {self.step:,} ({mean})"
        return f"{self.name} (step {self.step:,}, {mean})"


@dataclass
class Inspection:
    """The Q-values of several networks on the same frames, and the files written
    (`write.write_inspection` sets their paths)."""

    env: str
    action_names: list[str]
    networks: list[InspectedNetwork]
    observations: np.ndarray  # (frames, history, *observation_shape), the env's dtype
    screens: np.ndarray | None  # (frames, 210, 160, 3) RGB for Atari; None otherwise
    game_steps: list[int] | None  # the game's agent step of each frame; None if given
    q_values: np.ndarray  # (networks, frames, actions) float32
    note: str  # where the frames come from
    # How the observations are stored (`envs/spaces.py`); None: single frames.
    layout: ObservationLayout | None = None
    figure_paths: list[Path] = field(default_factory=list)  # one per frame
    overview_path: Path | None = None  # None above write.OVERVIEW_MAX_FRAMES frames
    csv_path: Path | None = None
    observations_path: Path | None = None
    screens_path: Path | None = None

    @property
    def greedy_actions(self) -> np.ndarray:
        """(networks, frames): the highest Q-value's action, the first of ties."""
        return self.q_values.argmax(axis=2)

    def summary(self) -> list[str]:
        """One line per network: its greedy actions over the frames and its mean max Q."""
        lines = []
        for k, network in enumerate(self.networks):
            counts = Counter(self.action_names[a] for a in self.greedy_actions[k])
            greedy = ", ".join(f"{name} x{count}" for name, count in counts.most_common())
            lines.append(
                f"{network.legend_label}: greedy {greedy}; "
                f"mean max Q {float(self.q_values[k].max(axis=1).mean()):.4g}"
            )
        return lines


# Which networks ------------------------------------------------------------------------


def parse_checkpoints(text: str) -> list[str]:
    """`--checkpoints best,worst` or `250000,500000` (or a mix) as a list of names."""
    return _checked_names(piece.strip() for piece in text.split(",") if piece.strip())


def _checked_names(checkpoints: Iterable[str | int]) -> list[str]:
    """The names in order, each once; an error for one that is not best, worst or a step."""
    names = list(dict.fromkeys(str(int(c)) if str(c).isdigit() else str(c) for c in checkpoints))
    if not names:
        raise DqnlabError("--checkpoints is empty; give best, worst or evaluation steps")
    for name in names:
        if name not in CHECKPOINT_NAMES and not name.isdigit():
            raise DqnlabError(
                f"--checkpoints entry {name!r} is not best, worst or a training step (a number)"
            )
    return names


def network_path(run_dir: Path, checkpoint: str | int, config: Config) -> Path:
    """The file of `checkpoint` ("best", "worst" or a step) in the run, or a clear error.
    An exported folder has one network, its best: model.safetensors."""
    if exported.is_exported_dir(run_dir):
        if checkpoint != "best":
            raise DqnlabError(
                f"{run_dir} is an exported folder: its one network is {exported.MODEL_FILE} "
                f"(--checkpoints best), not {checkpoint}"
            )
        return exported.network_path(run_dir)
    if checkpoint in CHECKPOINT_NAMES:
        path = rundir.network_path(run_dir, checkpoint)
        if checkpoint == "worst" and not path.is_file():
            quarter = config.total_steps / 4
            raise DqnlabError(
                f"{run_dir} has no worst network yet: worst.pt is kept from the periodic "
                f"evaluations at step >= total_steps / 4 = {quarter:g} "
                f"({_evaluations_text(run_dir)})"
            )
        if not path.is_file():
            raise DqnlabError(f"{run_dir} has no {checkpoint} network ({path} is missing)")
        return path
    step = int(checkpoint)
    path = rundir.eval_network_path(run_dir, step)
    if path.is_file():
        return path
    available = rundir.eval_network_steps(run_dir)
    if not available and config.eval_networks_kept != "all":
        raise DqnlabError(
            f"{run_dir} keeps no network per evaluation (eval_networks_kept = "
            f"{config.eval_networks_kept!r}): choose from best and worst"
        )
    kept = ", ".join(str(s) for s in available) if available else "none yet"
    raise DqnlabError(f"{run_dir} has no network evaluated at step {step}; kept steps: {kept}")


def _evaluations_text(run_dir: Path) -> str:
    path = rundir.evaluations_path(run_dir)
    steps = [row["step"] for row in read_csv(path)] if path.is_file() else []
    return f"evaluations at steps {', '.join(steps)}" if steps else "no evaluation yet"


def load_network(
    name: str, path: Path, device: torch.device, seed: int
) -> tuple[InspectedNetwork, Agent, Config]:
    """The network saved at `path`, built with the configuration it was trained with, in
    an agent seeded with `seed` (its epsilon-greedy draws)."""
    if path.suffix == ".safetensors":  # an exported folder's
        payload = exported.load_network(path, map_location=device)
    else:
        payload = rundir.load_network(path, map_location=device)
    agent, config, _ = rundir.agent_from_network(payload, path, seed, device)
    agent.online.eval()
    step = int(payload["step"])
    eval_mean = float(payload.get("eval_mean", float("nan")))
    label = name if name in CHECKPOINT_NAMES else f"step {step}"
    return InspectedNetwork(label, path, step, eval_mean), agent, config


# Which frames --------------------------------------------------------------------------


@dataclass
class PickedFrames:
    observations: np.ndarray  # (frames, history, *observation_shape)
    screens: np.ndarray | None  # (frames, 210, 160, 3) for Atari
    game_steps: list[int]  # agent steps of the game (0: the first decision)
    steps_played: int  # agent steps played: the game's, or max_game_steps
    game_ended: bool  # False: the game went on past max_game_steps


def pick_frames(
    agent: Agent, config: Config, frames: int, seed: int, *, max_game_steps: int
) -> PickedFrames:
    """`frames` network inputs evenly spread over the first evaluation game that `agent`
    plays on an environment seeded with `seed` (or over its first `max_game_steps`
    steps): the inputs of the decisions at the middles of `frames` equal stretches, so
    neither the first decision (a history of zeros but one frame) nor the last.

    The game is played once to learn its length and actions, then replayed with those
    actions on an identically seeded environment to keep the chosen inputs and, for
    Atari, the RGB screen at that moment (`ale.getScreenRGB`, the last raw frame).
    """
    if frames <= 0 or max_game_steps <= 0:
        raise DqnlabError(f"frames ({frames}) and max_game_steps ({max_game_steps}) must be > 0")
    actions: list[int] = []

    def choose(step: int, history: np.ndarray) -> int:
        actions.append(agent.act(history, config.eval_epsilon))
        return actions[-1]

    first = _play_first_game(agent, config, _first_game_env(config, seed), max_game_steps, choose)
    played = len(actions)
    count = min(frames, played)
    chosen = [int((i + 0.5) * played / count) for i in range(count)]
    chosen_steps = set(chosen)
    observations: list[np.ndarray] = []
    screens: list[np.ndarray] = []
    env = _first_game_env(config, seed)

    def replay(step: int, history: np.ndarray) -> int:
        if step in chosen_steps:
            observations.append(history.copy())
            if isinstance(env, AtariEnv):
                screens.append(env.ale.getScreenRGB())
        return actions[step]

    again = _play_first_game(agent, config, env, played, replay)
    same = (again.scores, again.steps, again.frames) == (first.scores, first.steps, first.frames)
    if not same or len(observations) != count:
        raise DqnlabError(
            f"{config.env} did not replay its game identically from the same seed and "
            "actions; frames cannot be picked from it (save observations and pass them instead)"
        )
    return PickedFrames(
        np.stack(observations),
        np.stack(screens) if screens else None,
        chosen,
        played,
        game_ended=bool(first.scores),
    )


def _first_game_env(config: Config, seed: int) -> Environment:
    return make_env(
        config, training=False, seed=seed, max_episode_frames=config.final_eval_max_episode_frames
    )


def _play_first_game(
    agent: Agent,
    config: Config,
    env: Environment,
    max_steps: int,
    choose: Callable[[int, np.ndarray], int],
) -> EvaluationResult:
    """The first game of `env`, for at most `max_steps` agent steps, each action
    `choose(step, stacked_input)` (`play.play`); `env` is closed afterwards."""
    try:
        return play(agent, env, config.history_length, 0.0, max_steps=max_steps, max_episodes=1,
                    choose=choose)  # fmt: skip
    finally:
        env.close()


def load_observations(
    path: Path, history_length: int, observation_shape: tuple[int, ...], dtype: np.dtype
) -> np.ndarray:
    """Stacked network inputs saved as .npy, checked against the network's input; values
    of another dtype are accepted only if they convert without change."""
    try:
        array = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as error:
        raise DqnlabError(f"cannot read observations from {path}: {error}") from None
    expected = (history_length, *observation_shape)
    if array.ndim != 1 + len(expected) or tuple(array.shape[1:]) != expected or not len(array):
        raise DqnlabError(
            f"{path} holds an array of shape {array.shape}; this run's network takes "
            f"(N, {', '.join(str(n) for n in expected)}) with N >= 1"
        )
    if array.dtype != dtype:
        converted = array.astype(dtype)
        if not np.array_equal(converted, array):
            raise DqnlabError(
                f"{path} holds {array.dtype} values that {np.dtype(dtype)} (the environment's "
                "observations) cannot hold exactly"
            )
        array = converted
    return array


# Q-values ------------------------------------------------------------------------------


def compare_networks(
    run_dir: Path,
    *,
    frames: int = DEFAULT_FRAMES,
    checkpoints: Sequence[str | int] = CHECKPOINT_NAMES,
    observations: Path | None = None,
    seed: int = 0,
    device: torch.device | None = None,
    max_game_steps: int = DEFAULT_MAX_GAME_STEPS,
) -> Inspection:
    """The Q-values of the run's `checkpoints` ("best", "worst", or steps of its periodic
    evaluations) on `frames` frames of the best network's first evaluation game
    (`pick_frames`; `seed` seeds the game), or on the stacked inputs saved in the .npy
    file `observations` (then `frames` is ignored, and a `screens.npy` beside it with one
    screen per input is taken as their screens)."""
    device = device or torch.device("cpu")
    config = rundir.load_run_config(run_dir)  # a clear error if RUN_DIR is not a run
    paths = [(name, network_path(run_dir, name, config)) for name in _checked_names(checkpoints)]
    best, best_agent, best_config = load_network(
        "best", network_path(run_dir, "best", config), device, seed
    )
    assert best_agent.action_names is not None
    action_names = best_agent.action_names
    inputs, screens, game_steps, note = _inputs_to_compare(
        best_agent, best_config, observations, frames, seed, max_game_steps
    )

    networks: list[InspectedNetwork] = []
    q_values = []
    for name, path in paths:
        if path == best.path:
            network, agent = best, best_agent
        else:
            network, agent, network_config = load_network(name, path, device, seed)
            if network_config.env != best_config.env:
                raise DqnlabError(
                    f"{path} was trained on {network_config.env}, not {best_config.env}"
                )
        networks.append(network)
        q_values.append(agent.q_values(inputs))  # eval mode, one forward pass of all frames
    return Inspection(
        env=best_config.env,
        action_names=action_names,
        networks=networks,
        observations=inputs,
        screens=screens,
        game_steps=game_steps,
        q_values=np.stack(q_values).astype(np.float32, copy=False),
        note=note,
        layout=best_agent.observation_layout,
    )


def _inputs_to_compare(
    agent: Agent,
    config: Config,
    observations: Path | None,
    frames: int,
    seed: int,
    max_game_steps: int,
) -> tuple[np.ndarray, np.ndarray | None, list[int] | None, str]:
    """The network inputs, their screens and game steps where known, and a note saying
    where they come from: those saved in `observations`, else frames picked from the first
    evaluation game that `agent` plays (`pick_frames`)."""
    env_seed = derive_seeds(seed, 2)[0]
    assert agent.input_shape is not None and agent.observation_dtype is not None
    shape, dtype = agent.input_shape[1:], agent.observation_dtype
    if observations is not None:
        inputs = load_observations(observations, config.history_length, shape, dtype)
        note = f"{len(inputs)} observations from {observations}"
        return inputs, _screens_beside(observations, len(inputs)), None, note
    picked = pick_frames(agent, config, frames, env_seed, max_game_steps=max_game_steps)
    extent = (
        f"its {picked.steps_played} steps"
        if picked.game_ended
        else f"its first {picked.steps_played} steps (it went on)"
    )
    note = (
        f"{len(picked.observations)} frames evenly spread over {extent} of the first "
        f"evaluation game of the best network (seed {seed}, epsilon {config.eval_epsilon:g})"
    )
    return picked.observations, picked.screens, picked.game_steps, note


def _screens_beside(observations: Path, count: int) -> np.ndarray | None:
    """The screens an earlier inspection saved with these inputs (its observations.npy
    and screens.npy), None for inputs saved otherwise."""
    path = observations.with_name(SCREENS_FILE)
    if observations.name != OBSERVATIONS_FILE or not path.is_file():
        return None
    try:
        screens = np.load(path, allow_pickle=False)
    except (OSError, ValueError):
        return None
    fits = screens.dtype == np.uint8 and screens.ndim == 4 and screens.shape[-1] == 3
    return screens if fits and len(screens) == count else None
