"""Peers for `dqnlab bench --peers`: other DQN implementations, run as new users run them.

Stable-Baselines3's DQN (optional extra `dqnlab[bench]`) with the Nature hyperparameters:
its documented Atari pipeline (`make_atari_env` + `VecFrameStack(n_stack=4)`, one
environment) and `DQN("CnnPolicy", ...)`. Where SB3 has no setting for a Nature detail it
keeps its own default (mean Huber loss, gradient-norm clipping at 10, torch's RMSprop with
epsilon outside the square root, epsilon annealed from step 0): that is what users run, and
`peer_settings` records it. Throughput is measured after the replay-start phase only.
"""

from __future__ import annotations

import time
from typing import Any

import psutil
import torch

from dqnlab.errors import EnvError, ResourceError

PEER_NAME = "stable-baselines3"
ACTION_REPEAT_FRAMES = 4  # Nature "action repeat", done by AtariWrapper's MaxAndSkipEnv
HISTORY_LENGTH = 4  # Nature "agent history length": VecFrameStack(n_stack=4)
SCREEN_SIZE = 84
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
    "optimize_memory_usage": False,  # SB3's default: stores obs and next_obs
}
# Nature RMSProp: squared-gradient momentum 0.95, min squared gradient 0.01, centred as in
# the Lua code; torch adds eps outside the square root, unlike DeepMind's.
NATURE_RMSPROP_KWARGS: dict[str, Any] = {"alpha": 0.95, "eps": 0.01, "centered": True}


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


def run_sb3_dqn(
    env: str = "breakout",
    steps: int = 2000,
    learning_starts: int = 5000,
    seed: int = 0,
    device: str = "cpu",
    buffer_size: int | None = None,
) -> dict[str, Any]:
    """Train SB3's DQN for `learning_starts + steps` agent steps; time the last `steps`.

    `env` is an ale-py game name ("breakout"). `buffer_size` defaults to
    `learning_starts + steps`, enough that nothing is overwritten during the measurement
    (SB3's 1M default would need about 56 GB once filled). Frames per second count
    `ACTION_REPEAT_FRAMES` raw frames per agent step, as the Nature paper counts frames.
    """
    if steps < 1 or learning_starts < 1:
        raise ValueError(
            f"steps and learning_starts must be at least 1, not {steps}, {learning_starts}"
        )
    if not peer_available():
        raise ImportError(
            "Stable-Baselines3 is not installed: pip install 'dqnlab[bench]' to compare with it"
        )
    import ale_py
    import gymnasium
    import stable_baselines3
    from stable_baselines3 import DQN
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.env_util import make_atari_env
    from stable_baselines3.common.vec_env import VecFrameStack

    gymnasium.register_envs(ale_py)
    env_id = atari_env_id(env)
    if env_id not in gymnasium.registry:
        raise EnvError(f"unknown Atari game {env!r} (no Gymnasium id {env_id})")

    total_steps = learning_starts + steps
    buffer_size = total_steps if buffer_size is None else buffer_size

    # SB3 docs for v5 ids: frameskip=1 and no sticky actions in the env, so that
    # AtariWrapper's MaxAndSkipEnv repeats each action 4 frames and max-pools the last 2.
    env_kwargs = {"frameskip": 1, "repeat_action_probability": 0.0}
    vec_env = make_atari_env(env_id, n_envs=1, seed=seed, env_kwargs=env_kwargs)
    stacked_env = VecFrameStack(vec_env, n_stack=HISTORY_LENGTH)
    ale = vec_env.envs[0].unwrapped.ale

    # SB3 anneals epsilon over a fraction of learn()'s total_timesteps, from step 0.
    exploration_fraction = EPSILON_DECAY_STEPS / total_steps
    model = DQN(
        "CnnPolicy",
        stacked_env,
        buffer_size=buffer_size,
        learning_starts=learning_starts,
        exploration_fraction=exploration_fraction,
        policy_kwargs={
            "optimizer_class": torch.optim.RMSprop,
            "optimizer_kwargs": NATURE_RMSPROP_KWARGS,
        },
        seed=seed,
        device=device,
        verbose=0,
        **NATURE_DQN_KWARGS,
    )
    # SB3 only warns when its replay does not fit (the arrays are filled lazily); fail here.
    replay = model.replay_buffer
    replay_arrays = (replay.observations, replay.next_observations, replay.actions)
    replay_arrays += (replay.rewards, replay.dones, replay.timeouts)
    bytes_per_transition = sum(array.nbytes for array in replay_arrays) // buffer_size
    resident_bytes = min(buffer_size, total_steps) * bytes_per_transition
    available_bytes = psutil.virtual_memory().available
    if resident_bytes > available_bytes:
        stacked_env.close()
        raise ResourceError(
            f"SB3's replay would hold {resident_bytes / 1e9:.1f} GB after {total_steps} steps "
            f"but {available_bytes / 1e9:.1f} GB is available: ask for fewer steps"
        )

    class ReplayStartClock(BaseCallback):
        """Notes the time, step and raw frame count when the replay-start phase ends."""

        def __init__(self) -> None:
            super().__init__()
            self.seconds: float | None = None
            self.steps = 0
            self.frames = 0

        def _on_step(self) -> bool:
            if self.seconds is None and self.num_timesteps >= learning_starts:
                self.steps, self.frames = self.num_timesteps, ale.getFrameNumber()
                self.seconds = time.perf_counter()
            return True

    clock = ReplayStartClock()
    model.learn(total_timesteps=total_steps, callback=clock)
    seconds = time.perf_counter() - (clock.seconds or 0.0)
    measured_steps = model.num_timesteps - clock.steps
    emulator_frames = ale.getFrameNumber() - clock.frames
    stacked_env.close()

    optimizer = model.policy.optimizer
    figures: dict[str, Any] = {
        "peer": PEER_NAME,
        "peer_version": stable_baselines3.__version__,
        "peer_train_frames_per_second": ACTION_REPEAT_FRAMES * measured_steps / seconds,
        "peer_emulator_frames_per_second": emulator_frames / seconds,
        "peer_steps": measured_steps,
        "peer_learning_starts": learning_starts,
        "peer_buffer_size": model.buffer_size,
        # Read back from the model, so they are what SB3 actually ran.
        "peer_settings": {
            "env_id": env_id,
            "env_kwargs": env_kwargs,
            "wrappers": "make_atari_env (AtariWrapper defaults: noop_max=30, frame_skip=4 "
            "with max of last 2 frames, terminal_on_life_loss, FireResetEnv, 84x84 gray, "
            "clip_reward) + VecFrameStack(n_stack=4) + VecTransposeImage",
            "n_envs": model.n_envs,
            "policy": type(model.policy).__name__,
            "learning_rate": model.learning_rate,
            "batch_size": model.batch_size,
            "gamma": model.gamma,
            "train_freq": model.train_freq.frequency,
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
            "replay_bytes_per_transition": bytes_per_transition,
            "updates": model._n_updates,
            "device": str(model.device),
            "threads": torch.get_num_threads(),
            "torch": torch.__version__,
        },
    }
    return figures
