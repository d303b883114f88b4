"""The checks a `Config` passes when it is made (`validate`): the accepted values of the
settings that take one of a few names (`CHOICES`) or a user's part (`USER_PARTS`), ranges,
and the combinations that cannot work, each refused in one line naming the setting."""

from __future__ import annotations

from typing import Any

from dqnlab.errors import ConfigError

# `settings.Config` calls `validate` on itself, so this module cannot import it (not even
# for annotations: tests/test_layout.py counts those as imports too): a config is `Any`.
Config = Any

WANDB_PROJECT_FORBIDDEN = tuple("/\\#?%:")  # as wandb's Settings.validate_project
# The accepted values of each setting that takes one of a few names; modules that
# dispatch on a setting read its list here.
CHOICES: dict[str, tuple[str, ...]] = {
    "observation_images": ("auto", "all", "none"),
    "frame_pooling": ("max_rgb", "max_gray", "none"),
    "grayscale": ("luminance", "ale"),
    "byte_conversion": ("truncate", "round"),
    "resize_interpolation": ("area", "bilinear"),
    "loss_reduction": ("sum", "mean"),
    "optimizer": ("deepmind_rmsprop", "rmsprop", "adam"),
    "on_checkpoint_error": ("stop", "continue"),
    "eval_networks_kept": ("all", "best_and_worst"),
    "replay_storage": ("auto", "host", "device"),
    "update_graph": ("off", "cuda"),
    "replay_compression": ("none", "lz4"),
    "logger": ("tensorboard", "tensorboard+wandb"),
    "target": ("max", "double"),
    "distributional": ("none", "c51"),
    "concurrency": ("none", "actor-learner"),
    "periodic_eval": ("inline", "background"),
    "final_eval_network": ("best", "last"),
    "eval_noise": ("mean", "sampled"),
}
# Settings that take one of `CHOICES` or the `module:Name` of a user's own part.
USER_PARTS: dict[str, tuple[str, ...]] = {
    "loss": ("auto",),
    "torso": ("auto",),
    "head": ("auto",),
    "policy": ("epsilon_greedy",),
    "augmentation": ("none", "random_shift"),
    "replay_sampling": ("uniform", "prioritized"),
}


def validate(config: Config) -> None:
    """Every check of one setting, and of settings that cannot go together: one-line
    ConfigErrors naming the setting."""
    _validate_names(config)
    _validate_ranges(config)
    _validate_combinations(config)
    _validate_parts(config)
    _validate_part_settings(config)
    _validate_env_arguments(config)
    _validate_periodic_eval(config)
    # W&B would refuse such a project name, but only once the run has started.
    project = config.wandb_project
    if not 0 < len(project) <= 128 or any(c in project for c in WANDB_PROJECT_FORBIDDEN):
        raise ConfigError(
            f"wandb_project = {project!r} must be 1 to 128 characters, none of "
            f"{' '.join(WANDB_PROJECT_FORBIDDEN)}"
        )


def _validate_names(config: Config) -> None:
    """Settings that take one of a few names, or a user's part."""
    for name, choices in CHOICES.items():
        value = getattr(config, name)
        if value not in choices:
            raise ConfigError(f"{name} = {value!r} is not one of: {', '.join(choices)}")
    for name, choices in USER_PARTS.items():
        value = getattr(config, name)
        if value not in choices and not _is_import_path(value):
            raise ConfigError(
                f"{name} = {value!r} is not one of: {', '.join(choices)}, or module:Name"
            )


def _validate_ranges(config: Config) -> None:
    """Numbers that must be positive, zero or more, or in [0, 1]."""
    positive = (
        "n_step", "noisy_sigma0", "action_repeat_frames", "screen_size", "history_length",
        "replay_capacity", "batch_size", "update_period_steps", "target_update_steps",
        "learning_rate", "eval_steps", "final_eval_episodes", "total_steps",
        "replay_start_steps", "rmsprop_epsilon", "adam_epsilon", "checkpoints_kept",
        "checkpoint_period_minutes", "num_envs", "actor_refresh_updates",
    )  # fmt: skip
    for name in positive:
        if getattr(config, name) <= 0:
            raise ConfigError(f"{name} = {getattr(config, name)} must be positive")
    non_negative = (
        "seed", "noop_max_frames", "max_episode_frames", "reward_clip", "td_error_clip",
        "epsilon_decay_steps", "eval_max_episode_frames", "final_eval_max_episode_frames",
        "checkpoint_period_steps", "digest_period_steps", "heldout_transitions", "priority_epsilon",
        "eval_period_steps",
        "priority_exponent", "max_gradient_norm", "periodic_eval_workers", "threads",
    )  # fmt: skip
    for name in non_negative:
        if getattr(config, name) < 0:
            raise ConfigError(f"{name} = {getattr(config, name)} must be zero or more")
    unit_interval = (
        "importance_exponent_start", "sticky_action_probability", "discount", "epsilon_start",
        "epsilon_decay_fraction",
        "epsilon_end", "eval_epsilon",
    )  # fmt: skip
    for name in unit_interval:
        if not 0.0 <= getattr(config, name) <= 1.0:
            raise ConfigError(f"{name} = {getattr(config, name)} must be between 0 and 1")
    if not 0.0 <= config.rmsprop_decay < 1.0:
        raise ConfigError(f"rmsprop_decay = {config.rmsprop_decay} must be in [0, 1)")
    if any(width <= 0 for width in config.mlp_hidden_sizes):
        raise ConfigError(f"mlp_hidden_sizes = {list(config.mlp_hidden_sizes)} must be positive")


def _validate_combinations(config: Config) -> None:
    """Settings that cannot go together."""
    per_env = config.replay_capacity // config.num_envs
    if config.num_envs > 1 and per_env < config.history_length + config.n_step + 1:
        raise ConfigError(
            f"num_envs = {config.num_envs} leaves {per_env} replay slots per environment "
            f"(replay_capacity // num_envs); one transition needs "
            f"{config.history_length + config.n_step + 1}"
        )
    if config.batch_size > config.replay_capacity:
        raise ConfigError(
            f"batch_size = {config.batch_size} exceeds replay_capacity = {config.replay_capacity}"
        )
    if config.update_graph != "off" and config.compile_update:
        raise ConfigError(
            f"update_graph = {config.update_graph!r} captures the update itself: leave "
            "compile_update = false"
        )
    if config.augmentation != "none" and config.update_graph != "off":
        raise ConfigError(
            f"augmentation = {config.augmentation!r} draws inside the update, which "
            f"update_graph = {config.update_graph!r} would replay with the same draws: leave "
            'update_graph = "off"'
        )
    if config.concurrency == "actor-learner" and config.update_graph != "off":
        raise ConfigError(
            f"update_graph = {config.update_graph!r} captures the update while the actor's "
            'thread would run on the same GPU: with concurrency = "actor-learner" leave '
            'update_graph = "off"'
        )


def _is_import_path(value: str) -> bool:
    module, sep, name = value.partition(":")
    return bool(sep and module and name)


def _validate_env_arguments(config: Config) -> None:
    if not isinstance(config.env_kwargs, dict):
        raise ConfigError(f"env_kwargs = {config.env_kwargs!r} must be a table (a dict)")
    for wrapper in config.env_wrappers:
        if not _is_import_path(wrapper):
            raise ConfigError(f"env_wrappers: {wrapper!r} is not module:callable")
    if "render_mode" in config.env_kwargs:  # videos ask for frames through it
        raise ConfigError("env_kwargs: render_mode is dqnlab's to set (videos); leave it out")


def _validate_periodic_eval(config: Config) -> None:
    if config.periodic_eval == "inline" and config.periodic_eval_workers != 1:
        raise ConfigError(
            f"periodic_eval_workers = {config.periodic_eval_workers} is for periodic_eval = "
            "'background'; an inline evaluation plays on the training thread"
        )
    # W&B takes each step once and never one earlier than its last: a result that arrives
    # after later steps were logged would be dropped.
    if config.periodic_eval == "background" and config.logger != "tensorboard":
        raise ConfigError(
            f"periodic_eval = 'background' logs each evaluation after later training steps, "
            f"which logger = {config.logger!r} (W&B) refuses: use periodic_eval = 'inline'"
        )


def _validate_part_settings(config: Config) -> None:
    """The shape of `parts`: a table per part setting, of bool, int, float or str values
    (which names a part has is the part's to say: `resolve_config` checks them)."""
    if not isinstance(config.parts, dict):
        raise ConfigError(f"parts = {config.parts!r} must be a table (a dict) of tables")
    for setting, values in config.parts.items():
        if setting not in USER_PARTS:
            raise ConfigError(
                f"parts.{setting}: {setting!r} is not a part setting; parts are "
                f"{', '.join(USER_PARTS)}"
            )
        if not isinstance(values, dict):
            raise ConfigError(f"parts.{setting} = {values!r} must be a table of settings")
        for key, value in values.items():
            if not isinstance(value, (bool, int, float, str)):
                message = f"parts.{setting}.{key} = {value!r} must be a bool, int, float or string"
                raise ConfigError(message)


def _validate_parts(config: Config) -> None:
    """Combinations of the update's parts that cannot work, refused before anything is built."""
    distributional = config.distributional != "none"
    if distributional and config.distributional_atoms < 2:
        raise ConfigError(
            f"distributional_atoms = {config.distributional_atoms} must be at least 2"
        )
    if distributional and not config.distributional_v_min < config.distributional_v_max:
        raise ConfigError(
            f"distributional_v_min = {config.distributional_v_min} must be below "
            f"distributional_v_max = {config.distributional_v_max}"
        )
    heads = [name for name in ("dueling", "noisy") if getattr(config, name)]
    heads += ["distributional"] if distributional else []
    if config.torso != "auto" and config.network != "auto":
        raise ConfigError(
            f"torso = {config.torso!r} replaces the network's torso: leave network = 'auto' "
            f"(it is {config.network!r})"
        )
    if config.head != "auto" and distributional:
        raise ConfigError(
            f"head = {config.head!r} is your own head, so distributional cannot be added to "
            "it: build it into your factory (heads.CategoricalHead is there to compose)"
        )
    heads += ["head"] if config.head != "auto" else []
    if ":" in config.network and heads:
        raise ConfigError(
            f"network = {config.network!r} is a whole Q-network, so {', '.join(heads)} cannot "
            "be added to it; give your torso as torso = module:factory instead"
        )
