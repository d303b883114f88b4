"""What a checkpoint must match to be resumed (`config_fingerprint`), which settings a
resumed run may change, and the seeds every random stream derives from the run's seed."""

from __future__ import annotations

import hashlib
import json

import numpy as np

from dqnlab.config.settings import FIELD_NAMES, Config

# Settings that do not shape the training state: a run may resume with them changed.
RESUMABLE_CHANGES = (
    "logger", "wandb_project",
    "total_steps", "compile_update", "checkpoint_period_minutes", "checkpoint_period_steps",
    "checkpoints_kept", "digest_period_steps", "on_checkpoint_error", "eval_networks_kept",
    "replay_storage",
    "replay_compression", "heldout_transitions", "update_graph", "periodic_eval_workers",
    "final_eval_network", "final_eval_after_training", "threads", "flush_denormals",
    "preset",  # a record of where the settings came from, not a setting of the training
)  # fmt: skip


# Settings added after runs were first checkpointed (the DQN family's parts): left out of a
# fingerprint while they hold their default, so a run checkpointed before they existed
# resumes under this version.
ADDED_WITH_DEFAULTS = (
    "target", "n_step", "distributional", "distributional_atoms", "distributional_v_min",
    "distributional_v_max", "loss", "dueling", "noisy", "noisy_sigma0", "torso",
    "replay_sampling", "priority_exponent", "priority_epsilon", "importance_exponent_start",
    "max_gradient_norm", "policy", "env_kwargs", "env_wrappers", "observation_images",
    "update_graph", "num_envs", "concurrency", "actor_refresh_updates", "periodic_eval",
    "augmentation", "head", "parts", "deterministic", "epsilon_decay_fraction", "eval_noise",
)  # fmt: skip


_DEFAULTS = Config().to_dict()


def config_fingerprint(config: Config) -> str:
    """What a checkpoint must match to be resumed: SHA-256 of the canonical JSON of every
    setting but `RESUMABLE_CHANGES` (and `ADDED_WITH_DEFAULTS` at their defaults). Equal
    settings, equal fingerprints."""
    values = {
        k: v
        for k, v in config.to_dict().items()
        if k not in RESUMABLE_CHANGES and not (k in ADDED_WITH_DEFAULTS and v == _DEFAULTS[k])
    }
    canonical = json.dumps(  # str: a TOML date or time in env_kwargs
        values, sort_keys=True, separators=(",", ":"), ensure_ascii=True, default=str
    )
    return hashlib.sha256(canonical.encode()).hexdigest()


def differing_settings(saved: Config, config: Config) -> list[str]:
    """The settings, in `Config` order, in which `config` differs from `saved` and which a
    resumed run may not change (every one but `RESUMABLE_CHANGES`)."""
    before, after = saved.to_dict(), config.to_dict()
    return [
        name
        for name in FIELD_NAMES
        if name not in RESUMABLE_CHANGES and before[name] != after[name]
    ]


# Seeds a final evaluation's games unless `dqnlab evaluate --seed` says otherwise; a report
# plays missing final evaluations with it too.
DEFAULT_EVALUATION_SEED = 12345


def derive_seeds(seed: int, count: int) -> list[int]:
    """Independent child seeds for each random stream, all from the one run seed."""
    return [int(s.generate_state(1)[0]) for s in np.random.SeedSequence(seed).spawn(count)]
