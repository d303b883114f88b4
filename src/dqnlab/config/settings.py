"""Typed, validated configuration: `Config` (its checks are `validation.py`'s; what a
checkpoint must match to be resumed is `fingerprint.py`'s).

Every faithful detail of the Nature DQN is one field of `Config`; the `nature` preset
(`presets/nature.toml`) sets each to DeepMind's value. Units are part of every name:
a *frame* is one raw emulator frame, a *step* is one agent decision.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from dqnlab.config.validation import validate


def _setting(default: Any, doc: str) -> Any:
    if isinstance(default, dict):  # a fresh table for each Config
        return field(default_factory=lambda: dict(default), metadata={"doc": doc})
    return field(default=default, metadata={"doc": doc})


@dataclass(frozen=True)
class Config:
    """One run's settings. Build with `resolve_config`, which validates every field."""

    # Environment.
    env: str = _setting(
        "",
        "Atari game as ale-py names it, a Gymnasium id (also one an installed package "
        "provides), module:Env-id, or module:EnvClass",
    )
    env_kwargs: dict[str, Any] = _setting(
        {},
        "Keyword arguments of a Gymnasium environment's constructor (gymnasium.make(env, "
        "**env_kwargs), or the module:Factory called with them), any TOML values",
    )
    env_wrappers: tuple[str, ...] = _setting(
        (),
        "module:callable wrappers applied in order around a Gymnasium environment "
        "(env = callable(env)), each returning a gymnasium.Env",
    )
    observation_images: str = _setting(
        "auto",
        "How Box observation parts are read: auto (rank 3, or rank 2 of uint8 or bool: an "
        "image; else a vector), all (every Box part of rank 2 or 3 is an image), none (every "
        "part flattened into the vector)",
    )
    seed: int = _setting(0, "Seeds every random stream (Python, NumPy, PyTorch, environments)")
    preset: str = _setting(
        "",
        "The preset the settings started from, recorded when they are resolved: a shipped "
        "name, tuned/ENV-ID for the tuned settings `train` chose by the environment id, or a "
        "file's path (a record: the values are the other settings)",
    )
    # Atari pipeline (ignored for other environments).
    action_repeat_frames: int = _setting(4, "Raw frames each agent action is repeated for")
    frame_pooling: str = _setting(
        "max_rgb", "max_rgb: max of the last two RGB frames, then gray; max_gray; none"
    )
    grayscale: str = _setting("luminance", "luminance (0.299/0.587/0.114, float) or ale")
    byte_conversion: str = _setting("truncate", "Observation to uint8: truncate (Lua) or round")
    resize_interpolation: str = _setting("area", "area or bilinear resize of the whole frame")
    screen_size: int = _setting(84, "Side of the square observation in pixels")
    noop_max_frames: int = _setting(
        30, "Raw no-op frames at episode start: k in 1..this (k+1 after a lost life)"
    )
    sticky_action_probability: float = _setting(0.0, "ALE repeat_action_probability")
    full_action_space: bool = _setting(False, "All 18 actions instead of the game's minimal set")
    life_loss_terminal: bool = _setting(
        True, "In training a lost life ends the episode for the TD target; the game continues"
    )
    max_episode_frames: int = _setting(0, "Training episode cap in raw frames (0: no cap)")
    reward_clip: float = _setting(1.0, "Rewards for learning are clipped to [-x, x] (0: off)")
    # Observation history and network.
    history_length: int = _setting(4, "Agent observations stacked into one network input")
    network: str = _setting(
        "auto",
        "auto, nature_cnn, der_cnn (Data-efficient Rainbow's two 5x5 stride-5 convolutions "
        "and 256 hidden units), small_cnn, multi_input, mlp, or module:factory(obs_shape, n)",
    )
    mlp_hidden_sizes: tuple[int, ...] = _setting((256, 256), "Hidden layer widths of the MLP")
    # Replay memory.
    replay_capacity: int = _setting(1_000_000, "Transitions held in replay memory")
    replay_start_steps: int = _setting(
        50_000, "Agent steps before the first update, acting at epsilon_start (1.0: uniformly)"
    )
    batch_size: int = _setting(32, "Transitions per gradient step, uniform with replacement")
    # Learning.
    update_period_steps: int = _setting(4, "Agent steps between gradient steps")
    target_update_steps: int = _setting(10_000, "Agent steps between target network copies")
    discount: float = _setting(0.99, "Discount factor gamma")
    td_error_clip: float = _setting(1.0, "TD error clipped to [-x, x] in the gradient (0: off)")
    loss_reduction: str = _setting("sum", "sum (DeepMind's Lua code) or mean over the batch")
    optimizer: str = _setting("deepmind_rmsprop", "deepmind_rmsprop, rmsprop or adam")
    learning_rate: float = _setting(0.00025, "Optimizer learning rate (constant)")
    rmsprop_decay: float = _setting(0.95, "RMSProp moving-average decay")
    rmsprop_epsilon: float = _setting(0.01, "RMSProp epsilon (inside the sqrt for DeepMind's)")
    adam_epsilon: float = _setting(0.00015, "Adam epsilon")
    # The update's parts (the DQN family). Every default is the Nature DQN's.
    target: str = _setting(
        "max",
        "Next action of the TD target: max (the target network picks and values it; Nature) "
        "or double (the online network picks, the target network values; van Hasselt et al. "
        "2016)",
    )
    n_step: int = _setting(
        1,
        "Rewards summed in one TD target before bootstrapping (Rainbow: 3), cut at terminals "
        "(lost lives too with life_loss_terminal), bootstrapped at time-limit truncation",
    )
    distributional: str = _setting(
        "none", "none (one Q-value per action) or c51 (Bellemare et al. 2017: a categorical "
        "return distribution on distributional_atoms atoms, cross-entropy loss)"
    )  # fmt: skip
    distributional_atoms: int = _setting(51, "Atoms of the C51 support")
    distributional_v_min: float = _setting(-10.0, "Lowest atom of the C51 support (return)")
    distributional_v_max: float = _setting(10.0, "Highest atom of the C51 support (return)")
    loss: str = _setting(
        "auto",
        "auto: the TD loss (Huber at td_error_clip), or the cross-entropy with distributional "
        "= c51; module:Class: your own loss part (docs: your own variant)",
    )
    dueling: bool = _setting(
        False,
        "Dueling head (Wang et al. 2016): value and mean-subtracted advantage streams, the "
        "gradient into the torso scaled by 1/sqrt(2)",
    )
    noisy: bool = _setting(
        False,
        "Factorised Gaussian noisy linear layers in the head (Fortunato et al. 2018), fresh "
        "noise for every action and every update; the mean weights when evaluating. On the "
        "Atari networks the head holds every linear layer; an MLP's hidden layers (the "
        "torso's) stay plain",
    )
    noisy_sigma0: float = _setting(
        0.5, "Initial noise scale sigma_0 of noisy layers (sigma = sigma_0 / sqrt(fan in))"
    )
    torso: str = _setting(
        "auto",
        "auto: the torso of the network setting (the Nature CNN's convolutions, the MLP's "
        "hidden layers); module:factory(input_shape) -> module giving (batch, features): the "
        "head of the other settings goes on it",
    )
    head: str = _setting(
        "auto",
        "auto: the head of the other settings (dueling, noisy, distributional); "
        "module:factory(in_features, num_actions, config, hidden_width) -> module giving "
        "(batch, actions, outputs per action), with an optional q_values(outputs) (else their "
        "mean): your own head part (docs: your own variant)",
    )
    policy: str = _setting(
        "epsilon_greedy",
        "How an action is chosen from the Q-values: epsilon_greedy (ties at random; Lua), or "
        "module:Class, your own policy part (docs: your own variant)",
    )
    replay_sampling: str = _setting(
        "uniform",
        "uniform, prioritized (Schaul et al. 2016, proportional: P(i) ~ (|error| + "
        "priority_epsilon)^priority_exponent, importance weights (N P(i))^-beta / batch max), "
        "or module:Class, a sampler of your own (docs/own-variant.md, A sampler)",
    )
    priority_exponent: float = _setting(0.6, "Prioritized replay's alpha")
    priority_epsilon: float = _setting(1e-6, "Added to |error| so that no priority is zero")
    importance_exponent_start: float = _setting(
        0.4, "Prioritized replay's beta at the first update, annealed linearly to 1 at total_steps"
    )
    augmentation: str = _setting(
        "none",
        "Data augmentation of the sampled observations inside the update, current and next "
        "each drawn independently from the agent's checkpointed generator: none, "
        "random_shift (DrQ, Kostrikov et al. 2020: pad 4 pixels by repeating the border, "
        "crop back at a random offset, one per observation), or module:Class (your own; "
        "docs: your own variant); image observations only",
    )
    parts: dict[str, Any] = _setting(
        {},
        "The parts' own settings, a table per part setting (loss, torso, head, policy, "
        "augmentation): [parts.loss] tau = 0.03 in TOML, --set parts.loss.tau=0.03; the part "
        "declares their names, types and defaults, which the run's config.toml records "
        "(docs: your own variant)",
    )
    max_gradient_norm: float = _setting(
        0.0, "Gradients rescaled to this global L2 norm when above it (0: off; dueling: 10)"
    )
    # Exploration.
    epsilon_start: float = _setting(1.0, "Epsilon at the end of the replay-start phase")
    epsilon_end: float = _setting(0.1, "Epsilon after the anneal")
    epsilon_decay_steps: int = _setting(1_000_000, "Agent steps of the linear epsilon anneal")
    epsilon_decay_fraction: float = _setting(
        0.0, "When above 0, the anneal's length as a fraction of total_steps (SB3's "
        "exploration_fraction): epsilon_decay_steps is set from it when the run's settings are "
        "resolved, unless given itself"
    )  # fmt: skip
    # Evaluation.
    eval_epsilon: float = _setting(0.05, "Epsilon while evaluating")
    eval_noise: str = _setting(
        "mean",
        "Noisy layers while evaluating: mean (their mean weights: Fortunato et al. 2018, "
        "Dopamine, Kaixhin's Rainbow) or sampled (fresh noise for every action, drawn as in "
        "training: dqn_zoo's Rainbow); sampled needs a network with noisy layers",
    )
    eval_period_steps: int = _setting(
        250_000, "Training steps between periodic evaluations (0: none; the best network is "
        "then the last)"
    )  # fmt: skip
    eval_steps: int = _setting(125_000, "Agent steps of one periodic evaluation")
    eval_max_episode_frames: int = _setting(
        0, "Episode cap in raw frames during periodic evaluation (0: none)"
    )
    heldout_transitions: int = _setting(
        500,
        "Transitions drawn once from replay when learning starts; their mean max-Q and "
        "|TD error| are logged at every periodic evaluation (Nature Fig. 2; 0: none)",
    )
    final_eval_episodes: int = _setting(30, "Episodes of the final evaluation")
    final_eval_max_episode_frames: int = _setting(
        18_000, "Episode cap of the final evaluation in raw frames (5 minutes)"
    )
    final_eval_network: str = _setting(
        "best",
        "The network the final evaluation plays (dqnlab report, dqnlab evaluate's default): "
        "best (the best periodic evaluation's; the Nature protocol) or last (the network at "
        "the end of training; Atari 100k)",
    )
    final_eval_after_training: bool = _setting(
        False,
        "Play the final evaluation (final_eval_network, final_eval_episodes) when training "
        "reaches total_steps, into final_evaluation.json: a sweep's runs then end with "
        "their scores (else dqnlab report or dqnlab evaluate plays it)",
    )
    eval_networks_kept: str = _setting(
        "best_and_worst",
        "Networks kept for inspection: best_and_worst (best.pt, and worst.pt: the worst after "
        "the first quarter; bounded disk) or all (also one per periodic evaluation, ~6.7 MB "
        "each for Atari: 1.3 GB per 50M-step run)",
    )
    periodic_eval: str = _setting(
        "inline",
        "inline: each periodic evaluation pauses training and draws from the agent's own "
        "generator, as the Lua code did; background: worker processes play a snapshot of the "
        "online network while training goes on, each evaluation with a generator and an "
        "environment seeded from the run's seed and its step (the scores are as meaningful; "
        "training's draws, no longer shared, differ from an inline run's)",
    )
    periodic_eval_workers: int = _setting(
        1,
        "Processes playing background periodic evaluations, one torch thread each (more "
        "where one evaluation outlasts an evaluation period of training; 0: played on the "
        "training thread in turn, the same results)",
    )
    # Budget.
    total_steps: int = _setting(50_000_000, "Training budget in agent steps")
    # Speed (no change of results beyond float rounding).
    compile_update: bool = _setting(
        False, "torch.compile the update (needs a C++ compiler; compiles once, at the first update)"
    )
    update_graph: str = _setting(
        "off",
        "off, or cuda: the update (forward, backward, optimizer step) captured once as a CUDA "
        "graph and replayed, one launch per update instead of dozens (a CUDA device only; "
        "not with compile_update)",
    )
    deterministic: bool = _setting(
        True,
        "On a CUDA device, PyTorch's deterministic algorithms (cuDNN, cuBLAS): a run repeats "
        "bit for bit and a resumed run continues exactly as an uninterrupted one; false is "
        "faster and neither holds (a resume then says so). No effect on the CPU, whose "
        "operations repeat bit for bit at a given thread count (`threads`)",
    )
    flush_denormals: bool = _setting(
        True,
        "On the CPU, float results below 1.2e-38 (denormal) flushed to zero in every PyTorch "
        "thread (the processor's flush-to-zero and denormals-are-zero modes): an optimizer's "
        "averages of a weight whose gradient stays zero otherwise stick there for good, and "
        "x86 computes on them tens of times slower (CartPole's classic 30% faster, the same "
        "weights; docs/benchmark.md). false: IEEE's gradual underflow",
    )
    threads: int = _setting(
        0,
        "PyTorch threads of a training process (torch.set_num_threads); 0: PyTorch's "
        "default, one per core (or OMP_NUM_THREADS). The CPU's arithmetic depends on the "
        "count, so a resumed run takes the count it trained with unless this says "
        "otherwise (then it warns that it will not continue bit for bit). 1 for each of "
        "two trainings at once on two cores",
    )
    replay_storage: str = _setting(
        "auto",
        "host: minibatches gathered in host memory and copied to the device; device: the "
        "frames also kept on the training device and minibatches gathered there (GPU memory "
        "for a copy of the frames); auto: device on a GPU with room for them, else host",
    )
    replay_compression: str = _setting(
        "none",
        "Replay frames kept compressed in host memory (image observations): none, or lz4 "
        "(each filled 16,384-slot chunk compressed in blocks of 4 frames; the same minibatches)",
    )
    # Speed that changes the data learned from (docs/benchmark.md, "Many environments").
    num_envs: int = _setting(
        1,
        "Training environments stepped side by side, their actions chosen by one batched "
        "forward pass; each has its own replay ring (capacity / num_envs slots). Steps, "
        "schedules and periods stay counted in agent steps summed over them",
    )
    concurrency: str = _setting(
        "none",
        "none: act, store, learn in turn (Nature, the Lua code); actor-learner: a thread steps "
        "the environments with a copy of the online network refreshed every "
        "actor_refresh_updates updates while the learner updates; the replay ratio is held; "
        "for machines with cores to spare (0.73-0.77x of none on 2 CPU cores) "
        '(docs/benchmark.md, "Acting while learning"; not with update_graph = cuda)',
    )
    actor_refresh_updates: int = _setting(
        4,
        "K, for actor-learner: the actor acts with the online network as it was after the "
        "last update whose number is a multiple of K and that is at least K updates old: "
        "K to 2K - 1 updates behind the sequential loop's",
    )
    # Checkpoints (the whole training state; a killed run resumes exactly).
    checkpoint_period_minutes: float = _setting(
        30.0, "Wall-clock minutes between checkpoints, besides one at every evaluation"
    )
    checkpoint_period_steps: int = _setting(0, "Agent steps between checkpoints (0: off)")
    checkpoints_kept: int = _setting(2, "Complete checkpoints kept on disk")
    digest_period_steps: int = _setting(
        1000,
        "Agent steps between digests of the online network's weights in digests.csv; a run "
        "resumed after a kill compares its own with those the killed run wrote past the "
        "checkpoint and says whether it retraces it (0: off; docs/resuming.md)",
    )
    on_checkpoint_error: str = _setting(
        "stop", "stop, or continue training when a checkpoint cannot be written"
    )
    # Logging (CSV files always; where else the same figures go).
    logger: str = _setting(
        "tensorboard",
        "tensorboard, or tensorboard+wandb: also to Weights & Biases (needs dqnlab[wandb]; "
        "entity, group, tags and offline mode through W&B's WANDB_* environment variables)",
    )
    wandb_project: str = _setting("dqnlab", "W&B project of the run (logger = tensorboard+wandb)")

    def __post_init__(self) -> None:
        validate(self)

    def to_dict(self) -> dict[str, Any]:
        values = dataclasses.asdict(self)
        values["mlp_hidden_sizes"] = list(self.mlp_hidden_sizes)
        values["env_wrappers"] = list(self.env_wrappers)
        return values


FIELD_NAMES = tuple(f.name for f in dataclasses.fields(Config))
