"""Peers for `--peers` (`dqnlab bench throughput` and `envs`): other DQN implementations,
run as new users run them.

Stable-Baselines3's DQN (optional extra `dqnlab[bench]`) with the Nature hyperparameters:
its documented Atari pipeline (`make_atari_env` + `VecFrameStack(n_stack=4)`, one
environment) and `DQN("CnnPolicy", ...)`. Where SB3 has no setting for a Nature detail it
keeps its own default (mean Huber loss, gradient-norm clipping at 10, torch's RMSprop with
epsilon outside the square root, epsilon annealed from step 0 rather than from the end of
replay start): that is what users run, and `peer_settings` records it. Throughput is
measured after the replay-start phase only.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

import psutil
import torch

from dqnlab.errors import EnvError, ResourceError

if TYPE_CHECKING:
    from stable_baselines3 import DQN

PEER_NAME = "stable-baselines3"
ACTION_REPEAT_FRAMES = 4  # Nature "action repeat", done by AtariWrapper's MaxAndSkipEnv
HISTORY_LENGTH = 4  # Nature "agent history length": VecFrameStack(n_stack=4)
EPSILON_DECAY_STEPS = 1_000_000  # Nature "final exploration frame" (agent steps)

# Nature hyperparameters (Extended Data Table 1) under SB3's names.
NATURE_DQN_KWARGS: dict[str, Any] = {
    "learning_rate": 0.00025,
    "batch_size": 32,
    "gamma": 0.99,
    "train_freq": 4,
    "gradient_steps": 1,
    "target_update_interval": 10_000,
    "exploration_initial_eps": 1.0,
    "exploration_final_eps": 0.1,
    "optimize_memory_usage": False,  # SB3's default: the replay stores obs and next_obs
}
# Nature RMSProp: squared-gradient momentum 0.95, min squared gradient 0.01, centred as in
# the Lua code; torch adds eps outside the square root, DeepMind's inside.
NATURE_RMSPROP_KWARGS: dict[str, Any] = {"alpha": 0.95, "eps": 0.01, "centered": True}
# SB3 docs for v5 ids: no frame skip and no sticky actions in the env, so that AtariWrapper's
# MaxAndSkipEnv repeats each action 4 frames and max-pools the last 2, as the Nature setup.
ATARI_ENV_KWARGS: dict[str, Any] = {"frameskip": 1, "repeat_action_probability": 0.0}


def peer_available() -> bool:
    """Whether Stable-Baselines3 can be imported (installed with `pip install dqnlab[bench]`)."""
    try:
        import stable_baselines3  # noqa: F401
    except ImportError:
        return False
    return True


def atari_env_id(game: str) -> str:
    """The Gymnasium id of an ale-py game: "space_invaders" -> "ALE/SpaceInvaders-v5"."""
    # Same conversion as ale_py.registration.rom_id_to_name.
    return f"ALE/{game.title().replace('_', '')}-v5"


def make_sb3_dqn(
    env: str,
    total_steps: int,
    learning_starts: int,
    buffer_size: int,
    seed: int = 0,
    device: str = "cpu",
    epsilon_decay_steps: int = EPSILON_DECAY_STEPS,
) -> DQN:
    """SB3's DQN with the Nature hyperparameters on one standard SB3 Atari environment.

    `total_steps` is what `learn()` will be given: SB3 anneals epsilon over a fraction of
    it, so the fraction is chosen for a 1M-step anneal.
    """
    if not peer_available():
        raise ImportError(
            "Stable-Baselines3 is not installed: pip install 'dqnlab[bench]' to compare with it"
        )
    import ale_py
    import gymnasium
    from stable_baselines3 import DQN
    from stable_baselines3.common.env_util import make_atari_env
    from stable_baselines3.common.vec_env import VecFrameStack

    gymnasium.register_envs(ale_py)
    env_id = atari_env_id(env)
    if env_id not in gymnasium.registry:
        raise EnvError(f"unknown Atari game {env!r} (no Gymnasium id {env_id})")
    vec_env = make_atari_env(env_id, n_envs=1, seed=seed, env_kwargs=ATARI_ENV_KWARGS)
    stacked_env = VecFrameStack(vec_env, n_stack=HISTORY_LENGTH)
    model = DQN(
        "CnnPolicy",
        stacked_env,
        buffer_size=buffer_size,
        learning_starts=learning_starts,
        exploration_fraction=epsilon_decay_steps / total_steps,
        policy_kwargs={
            "optimizer_class": torch.optim.RMSprop,
            "optimizer_kwargs": NATURE_RMSPROP_KWARGS,
        },
        seed=seed,
        device=device,
        verbose=0,
        **NATURE_DQN_KWARGS,
    )
    # SB3 only warns when its replay cannot fit (its arrays fill lazily); fail before running.
    resident_bytes = min(buffer_size, total_steps) * replay_bytes_per_transition(model)
    available_bytes = psutil.virtual_memory().available
    if resident_bytes > available_bytes:
        stacked_env.close()
        raise ResourceError(
            f"SB3's replay would hold {resident_bytes / 1e9:.1f} GB after {total_steps} steps "
            f"but {available_bytes / 1e9:.1f} GB is available: ask for fewer steps"
        )
    return model


def replay_bytes_per_transition(model: DQN) -> int:
    """Bytes per transition of the model's replay: stacked obs, next obs, action, reward, flags."""
    replay = model.replay_buffer
    assert replay is not None
    arrays = [replay.observations, replay.next_observations, replay.actions]
    arrays += [replay.rewards, replay.dones, replay.timeouts]
    return sum(array.nbytes for array in arrays) // replay.buffer_size


def _busy_cpu_seconds() -> tuple[float, float]:
    """CPU seconds used so far by the whole machine (all processes) and by this process."""
    machine = psutil.cpu_times()
    process = psutil.Process().cpu_times()
    machine_busy = sum(machine) - machine.idle - getattr(machine, "iowait", 0.0)
    return machine_busy, process.user + process.system


def run_sb3_dqn(
    env: str = "breakout",
    steps: int = 2000,
    learning_starts: int = 5000,
    seed: int = 0,
    device: str = "cpu",
    buffer_size: int | None = None,
    epsilon_decay_steps: int = EPSILON_DECAY_STEPS,
) -> dict[str, Any]:
    """Train SB3's DQN for `learning_starts + steps` agent steps; time the last `steps`.

    `env` is an ale-py game name ("breakout"). `buffer_size` defaults to
    `learning_starts + steps`, so nothing is overwritten during the measurement (SB3's 1M
    default would need about 56 GB once filled). Frames per second count
    `ACTION_REPEAT_FRAMES` raw frames per agent step, as the Nature paper counts frames;
    `peer_emulator_frames_per_second` also counts the no-op and FIRE frames of resets.
    """
    if steps < 1 or learning_starts < 1:
        raise ValueError(
            f"steps and learning_starts must be at least 1: {steps}, {learning_starts}"
        )
    import stable_baselines3

    total_steps = learning_starts + steps
    buffer_size = total_steps if buffer_size is None else buffer_size
    model = make_sb3_dqn(
        env, total_steps, learning_starts, buffer_size, seed, device, epsilon_decay_steps
    )
    stacked_env = model.get_env()
    assert stacked_env is not None
    ale = stacked_env.unwrapped.envs[0].unwrapped.ale  # type: ignore[attr-defined]
    clock = _replay_start_clock(learning_starts, ale)
    try:
        # learn() ends with the update of the last 4 steps, so they are all in the time.
        model.learn(total_timesteps=total_steps, callback=clock)
        seconds = time.perf_counter() - clock.seconds
        emulator_frames = ale.getFrameNumber() - clock.frames
        machine_cpu, process_cpu = _busy_cpu_seconds()
    finally:
        stacked_env.close()
    measured_steps = model.num_timesteps - clock.steps
    machine_cores = (machine_cpu - clock.cpu_seconds[0]) / seconds
    process_cores = (process_cpu - clock.cpu_seconds[1]) / seconds
    cores = {
        # Cores this run used, and cores other processes took meanwhile: a shared or busy
        # machine shows here (a 2-thread update slows down badly when contended).
        "process_cpu_cores": process_cores,
        "other_processes_cpu_cores": machine_cores - process_cores,
    }
    return {
        "peer": PEER_NAME,
        "peer_version": stable_baselines3.__version__,
        "peer_train_frames_per_second": ACTION_REPEAT_FRAMES * measured_steps / seconds,
        "peer_emulator_frames_per_second": emulator_frames / seconds,
        "peer_steps": measured_steps,
        "peer_learning_starts": learning_starts,
        "peer_buffer_size": model.buffer_size,
        "peer_settings": {**_settings_read_back(model, env, total_steps), **cores},
    }


def _replay_start_clock(learning_starts: int, ale: Any) -> Any:
    """An SB3 callback that notes the time, step, emulator frame count and CPU seconds
    when replay start ends."""
    from stable_baselines3.common.callbacks import BaseCallback

    class ReplayStartClock(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.seconds = 0.0
            self.steps = -1
            self.frames = 0
            self.cpu_seconds = (0.0, 0.0)

        def _on_step(self) -> bool:
            if self.steps < 0 and self.num_timesteps >= learning_starts:
                self.steps, self.frames = self.num_timesteps, ale.getFrameNumber()
                self.cpu_seconds = _busy_cpu_seconds()
                self.seconds = time.perf_counter()
            return True

    return ReplayStartClock()


def _settings_read_back(model: DQN, env: str, total_steps: int) -> dict[str, Any]:
    """The settings SB3 actually ran, read back from the model."""
    from stable_baselines3.common.type_aliases import TrainFreq

    optimizer = model.policy.optimizer
    train_freq = model.train_freq  # a TrainFreq once the model is set up
    assert isinstance(train_freq, TrainFreq)
    return {
        "env_id": atari_env_id(env),
        "env_kwargs": ATARI_ENV_KWARGS,
        "wrappers": "make_atari_env (AtariWrapper defaults: noop_max=30, frame_skip=4 "
        "with max of the last 2 frames, terminal_on_life_loss, FireResetEnv, 84x84 gray, "
        "clip_reward) + VecFrameStack(n_stack=4) + VecTransposeImage",
        "n_envs": model.n_envs,
        "policy": type(model.policy).__name__,
        "learning_rate": model.learning_rate,
        "batch_size": model.batch_size,
        "gamma": model.gamma,
        "train_freq": train_freq.frequency,
        "gradient_steps": model.gradient_steps,
        "target_update_interval": model.target_update_interval,
        "tau": model.tau,
        "exploration_initial_eps": model.exploration_initial_eps,
        "exploration_final_eps": model.exploration_final_eps,
        "exploration_fraction": model.exploration_fraction,
        "exploration_decay_steps": round(model.exploration_fraction * total_steps),
        "optimizer": type(optimizer).__name__,
        "optimizer_kwargs": {name: optimizer.defaults[name] for name in NATURE_RMSPROP_KWARGS},
        "loss": "smooth_l1_loss (Huber, mean over the batch)",  # SB3 DQN.train
        "max_grad_norm": model.max_grad_norm,
        "optimize_memory_usage": model.optimize_memory_usage,
        "replay_bytes_per_transition": replay_bytes_per_transition(model),
        "updates": model._n_updates,
        "device": str(model.device),
        "threads": torch.get_num_threads(),
        "torch": torch.__version__,
    }
