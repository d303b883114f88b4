"""Typed, validated configuration and the presets that fill it.

Every faithful detail of the Nature DQN is one field of `Config` (`settings.py`); the
`nature` preset (`presets/nature.toml`) sets each to DeepMind's value. Units are part of
every name: a *frame* is one raw emulator frame, a *step* is one agent decision.
`files.py` reads and writes settings as text: presets, `--set` overrides, `config.toml`;
`validation.py` the accepted values and the combinations refused when a `Config` is made;
`fingerprint.py` says what a checkpoint must match to be resumed, and derives the seeds;
`protocols.py` holds what a benchmark fixes (Atari 100k).
"""

from dqnlab.config.files import (
    EVALUATION_SETTINGS,
    config_from_dict,
    config_to_toml,
    load_preset,
    parse_overrides,
    parse_pairs,
    parse_value,
    preset_names,
    preset_text,
    resolve_config,
    setting_text,
    toml_value,
    tuned_envs,
    tuned_preset,
    with_env_arguments,
    with_evaluation_settings,
)
from dqnlab.config.fingerprint import (
    ADDED_WITH_DEFAULTS,
    DEFAULT_EVALUATION_SEED,
    RESUMABLE_CHANGES,
    config_fingerprint,
    derive_seeds,
    differing_settings,
)
from dqnlab.config.protocols import ATARI100K_PROTOCOL, atari100k_departures
from dqnlab.config.settings import FIELD_NAMES, Config
from dqnlab.config.validation import CHOICES, USER_PARTS, WANDB_PROJECT_FORBIDDEN

__all__ = [
    "ADDED_WITH_DEFAULTS",
    "ATARI100K_PROTOCOL",
    "CHOICES",
    "DEFAULT_EVALUATION_SEED",
    "EVALUATION_SETTINGS",
    "FIELD_NAMES",
    "RESUMABLE_CHANGES",
    "USER_PARTS",
    "WANDB_PROJECT_FORBIDDEN",
    "Config",
    "atari100k_departures",
    "config_fingerprint",
    "config_from_dict",
    "config_to_toml",
    "derive_seeds",
    "differing_settings",
    "load_preset",
    "parse_overrides",
    "parse_pairs",
    "parse_value",
    "preset_names",
    "preset_text",
    "resolve_config",
    "setting_text",
    "toml_value",
    "tuned_envs",
    "tuned_preset",
    "with_env_arguments",
    "with_evaluation_settings",
]
