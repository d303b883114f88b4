"""Configuration: presets carry DeepMind's values, overrides are typed and validated."""

from __future__ import annotations

import dataclasses

import pytest
import tomllib

from dqnlab.config import (
    RESUMABLE_CHANGES,
    Config,
    config_fingerprint,
    config_from_dict,
    config_to_toml,
    differing_settings,
    load_preset,
    parse_overrides,
    parse_pairs,
    parse_value,
    preset_names,
    resolve_config,
    setting_text,
    toml_value,
    with_env_arguments,
)
from dqnlab.errors import ConfigError

# DeepMind's values (nature-dqn.md, Lua run_gpu and Nature ED Table 1).
NATURE = {
    "action_repeat_frames": 4, "frame_pooling": "max_rgb", "resize_interpolation": "area",
    "screen_size": 84, "noop_max_frames": 30, "sticky_action_probability": 0.0,
    "full_action_space": False, "life_loss_terminal": True, "max_episode_frames": 0,
    "reward_clip": 1.0, "history_length": 4, "replay_capacity": 1_000_000,
    "replay_start_steps": 50_000, "batch_size": 32, "update_period_steps": 4,
    "target_update_steps": 10_000, "discount": 0.99, "td_error_clip": 1.0,
    "loss_reduction": "sum", "optimizer": "deepmind_rmsprop", "learning_rate": 0.00025,
    "rmsprop_decay": 0.95, "rmsprop_epsilon": 0.01, "epsilon_start": 1.0, "epsilon_end": 0.1,
    "epsilon_decay_steps": 1_000_000, "eval_epsilon": 0.05, "eval_period_steps": 250_000,
    "eval_steps": 125_000, "final_eval_episodes": 30, "final_eval_max_episode_frames": 18_000,
    "total_steps": 50_000_000,
}  # fmt: skip


def test_nature_preset_has_deepminds_values() -> None:
    config = resolve_config("nature", env="breakout")
    for name, value in NATURE.items():
        assert getattr(config, name) == value, name


def test_every_shipped_preset_sets_every_field_and_is_valid() -> None:
    assert set(preset_names()) >= {"nature", "seed-paper", "machado", "classic"}
    # The environment's own settings are the user's environment's, not a preset's.
    environment = {"env", "seed", "env_kwargs", "env_wrappers", "observation_images"}
    # `parts` holds the settings a user's part declares; the shipped parts declare none.
    # `preset` records the name a preset is loaded by.
    fields = {f.name for f in dataclasses.fields(Config)} - environment - {"parts", "preset"}
    for name in preset_names():
        assert fields - {"mlp_hidden_sizes", "adam_epsilon"} <= set(load_preset(name)), name
        resolve_config(name, env="pong")


def test_seed_paper_and_machado_differ_where_their_papers_say() -> None:
    seed_paper = resolve_config("seed-paper", env="pong")
    assert (seed_paper.optimizer, seed_paper.learning_rate) == ("rmsprop", 0.00005)
    machado = resolve_config("machado", env="pong")
    assert machado.sticky_action_probability == 0.25 and machado.full_action_space
    assert not machado.life_loss_terminal and machado.max_episode_frames == 108_000


def test_overrides_are_typed() -> None:
    overrides = parse_overrides(
        ["learning_rate=1e-4", "life_loss_terminal=false", "optimizer=adam", "replay_capacity=5000",
         "mlp_hidden_sizes=[64, 32]", "network=my.module:factory"]
    )  # fmt: skip
    config = resolve_config("nature", overrides, env="pong")
    assert config.learning_rate == 1e-4 and config.life_loss_terminal is False
    assert config.optimizer == "adam" and config.replay_capacity == 5000
    assert config.mlp_hidden_sizes == (64, 32) and config.network == "my.module:factory"


@pytest.mark.parametrize(
    ("pair", "message"),
    [
        ("discount=1.5", "discount = 1.5 must be between 0 and 1"),
        ("optimizer=sgd", "optimizer = 'sgd' is not one of: deepmind_rmsprop, rmsprop, adam"),
        ("batch_size=-1", "batch_size = -1 must be positive"),
        ("replay_capacity=many", "replay_capacity = 'many' is not a valid int"),
        ("learning_rat=0.1", "unknown setting 'learning_rat' in --set; did you mean learning_rate"),
        ("batch_size", "--set expects KEY=VALUE"),
        ("life_loss_terminal=3", "life_loss_terminal = 3 is not a valid bool"),
        ("seed=-1", "seed = -1 must be zero or more"),
        ("rmsprop_epsilon=0", "rmsprop_epsilon = 0.0 must be positive"),
        ("replay_start_steps=0", "replay_start_steps = 0 must be positive"),
        ("mlp_hidden_sizes=[1.5]", "mlp_hidden_sizes = [1.5] is not a valid list of integers"),
        ("n_step=0", "n_step = 0 must be positive"),
        ("target=triple", "target = 'triple' is not one of: max, double"),
        (
            "replay_sampling=ranked",
            "replay_sampling = 'ranked' is not one of: uniform, prioritized, or module:Name",
        ),
        ("distributional=qr", "distributional = 'qr' is not one of: none, c51"),
        ("loss=huber", "loss = 'huber' is not one of: auto, or module:Name"),
        ("torso=:f", "torso = ':f' is not one of: auto, or module:Name"),
        ("priority_exponent=-0.5", "priority_exponent = -0.5 must be zero or more"),
        (
            "importance_exponent_start=1.5",
            "importance_exponent_start = 1.5 must be between 0 and 1",
        ),
        ("max_gradient_norm=-1", "max_gradient_norm = -1.0 must be zero or more"),
        ("noisy_sigma0=0", "noisy_sigma0 = 0.0 must be positive"),
    ],
)
def test_bad_values_say_what_is_wrong(pair: str, message: str) -> None:
    with pytest.raises(ConfigError) as error:
        resolve_config("nature", parse_overrides([pair]), env="pong")
    assert message in str(error.value)


def test_unknown_preset_lists_the_accepted_ones() -> None:
    accepted = (
        "c51, classic, der, double, drq_epsilon, dueling, iqn, machado, nature, prioritized, "
        "qrdqn, rainbow, seed-paper, tuned/Acrobot-v1, tuned/CartPole-v1, tuned/LunarLander-v3, "
        "tuned/MountainCar-v0"
    )
    with pytest.raises(ConfigError, match=f"accepted: {accepted}"):
        load_preset("natur")


def test_resolved_config_round_trips_through_toml(tmp_path) -> None:
    import tomllib

    config = resolve_config("machado", parse_overrides(["seed=7"]), env="space_invaders")
    path = tmp_path / "config.toml"
    path.write_text(config_to_toml(config))
    assert config_from_dict(tomllib.loads(path.read_text())) == config
    assert resolve_config(str(path)) == config  # a saved config is itself a preset


def test_a_preset_file_with_bad_toml(tmp_path) -> None:
    path = tmp_path / "broken.toml"
    path.write_text("learning_rate = = 1\n")
    with pytest.raises(ConfigError, match="is not valid TOML"):
        load_preset(str(path))


def test_fingerprint_ignores_only_the_settings_a_resume_may_change() -> None:
    config = Config(env="pong")
    for name, value in (("total_steps", 10), ("checkpoints_kept", 5), ("replay_storage", "host")):
        assert name in RESUMABLE_CHANGES
        assert config_fingerprint(dataclasses.replace(config, **{name: value})) == (
            config_fingerprint(config)
        )
    changed = dataclasses.replace(config, discount=0.9, total_steps=10)
    assert config_fingerprint(changed) != config_fingerprint(config)
    assert differing_settings(config, changed) == ["discount"]
    assert differing_settings(config, dataclasses.replace(config, total_steps=10)) == []


def test_toml_values_read_back_and_labels_leave_strings_bare() -> None:
    for value in (True, 3, 0.00025, 5e-05, 'deep\\mind "rms"', (64, 64)):
        read = tomllib.loads(f"value = {toml_value(value)}")["value"]
        assert read == (list(value) if isinstance(value, tuple) else value)
    assert setting_text("deepmind_rmsprop") == "deepmind_rmsprop"
    assert setting_text(False) == "false" and setting_text((64, 64)) == "[64, 64]"


def test_where_a_run_logs_is_checked_and_outside_its_fingerprint() -> None:
    plain = resolve_config("nature", env="pong")
    assert (plain.logger, plain.wandb_project) == ("tensorboard", "dqnlab")
    overrides = parse_overrides(["logger=tensorboard+wandb", "wandb_project=atari-dqn"])
    to_wandb = resolve_config("nature", overrides, env="pong")
    assert config_fingerprint(to_wandb) == config_fingerprint(plain)  # a resume may turn it on
    assert differing_settings(plain, to_wandb) == []
    bad = {
        "logger=wandb": "logger = 'wandb' is not one of: tensorboard, tensorboard+wandb",
        "wandb_project=team/dqn": "wandb_project = 'team/dqn' must be 1 to 128 characters, none "
        "of / \\ # ? % :",
        "wandb_project=": "wandb_project = '' must be 1 to 128 characters",
    }
    for pair, message in bad.items():
        with pytest.raises(ConfigError) as error:
            resolve_config("nature", parse_overrides([pair]), env="pong")
        assert message in str(error.value)


@pytest.mark.parametrize(
    ("pairs", "message"),
    [
        (["distributional=c51", "distributional_atoms=1"], "distributional_atoms = 1 must be at"),
        (["distributional=c51", "distributional_v_min=10"], "distributional_v_min = 10.0 must be"),
        (["network=my.nets:q", "dueling=true"], "whole Q-network, so dueling cannot be added"),
        (["network=my.nets:q", "distributional=c51"], "so distributional cannot be added"),
        (["network=mlp", "torso=my.nets:torso"], "torso = 'my.nets:torso' replaces the network"),
    ],
)
def test_combinations_of_parts_that_cannot_work_name_the_setting(pairs, message) -> None:
    with pytest.raises(ConfigError) as error:
        resolve_config("nature", parse_overrides(pairs), env="pong")
    assert message in str(error.value) and "\n" not in str(error.value)


def test_the_familys_settings_at_their_defaults_leave_the_fingerprint_as_before() -> None:
    # The fingerprint of the nature preset on Pong before the family's settings existed
    # (commit 77fcc14): a run checkpointed then resumes under this version.
    assert config_fingerprint(resolve_config("nature", env="pong")).startswith("0ec1391b4c39d2a6")
    changed = resolve_config("nature", parse_overrides(["n_step=3"]), env="pong")
    assert config_fingerprint(changed) != config_fingerprint(resolve_config("nature", env="pong"))


def test_environment_arguments_round_trip_through_config_toml(tmp_path) -> None:
    overrides = parse_overrides([
        'env_kwargs={map_name = "8x8", is_slippery = false, "odd key" = [1, 2.5], sub = {a = 1}}',
        "env_wrappers=[\"my.wrappers:Clip\", \"my.wrappers:Stack\"]", "observation_images=all",
    ])  # fmt: skip
    config = resolve_config("classic", overrides, env="FrozenLake-v1")
    assert config.env_kwargs == {
        "map_name": "8x8", "is_slippery": False, "odd key": [1, 2.5], "sub": {"a": 1}
    }  # fmt: skip
    assert config.env_wrappers == ("my.wrappers:Clip", "my.wrappers:Stack")
    assert config.observation_images == "all"
    text = config_to_toml(config)
    assert 'env_kwargs = {map_name = "8x8", is_slippery = false, "odd key" = [1, 2.5], ' in text
    path = tmp_path / "config.toml"
    path.write_text(text)
    assert config_from_dict(tomllib.loads(path.read_text())) == config
    assert config_from_dict(config.to_dict()) == config
    assert resolve_config(str(path)) == config
    # A bare string is one wrapper (commas separate several), as mlp_hidden_sizes' integers.
    one = resolve_config("classic", parse_overrides(["env_wrappers=a.b:C,d:E"]), env="x")
    assert one.env_wrappers == ("a.b:C", "d:E")


def test_environment_arguments_are_part_of_the_fingerprint_unless_at_their_defaults() -> None:
    plain = resolve_config("classic", env="FrozenLake-v1")
    assert plain.env_kwargs == {} and plain.env_wrappers == ()
    assert plain.observation_images == "auto"
    assert {"env_kwargs", "env_wrappers", "observation_images"}.isdisjoint(RESUMABLE_CHANGES)
    for name, value in (("env_kwargs", {"is_slippery": False}), ("env_wrappers", ("m:W",)),
                        ("observation_images", "none")):  # fmt: skip
        changed = dataclasses.replace(plain, **{name: value})
        assert config_fingerprint(changed) != config_fingerprint(plain), name
        assert differing_settings(plain, changed) == [name]
    other = dataclasses.replace(plain, env_kwargs={"is_slippery": True})
    slippery = dataclasses.replace(plain, env_kwargs={"is_slippery": False})
    assert config_fingerprint(other) != config_fingerprint(slippery)
    # Each Config has its own table: the default is not shared.
    assert Config().env_kwargs is not Config().env_kwargs
    with pytest.raises(ConfigError, match=r"env_kwargs = \[1\] must be a table"):
        Config(env_kwargs=[1])  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("pair", "message"),
    [
        ("env_kwargs=3", "env_kwargs = 3 is not a valid table"),
        ("env_kwargs=map_name", "env_kwargs = 'map_name' is not a valid table"),
        ("env_wrappers=[1]", "env_wrappers = [1] is not a valid list of strings"),
        ("env_wrappers=no_colon", "env_wrappers: 'no_colon' is not module:callable"),
        ('env_kwargs={render_mode = "human"}', "env_kwargs: render_mode is dqnlab's to set"),
        ("observation_images=some", "observation_images = 'some' is not one of: auto, all, none"),
    ],
)
def test_bad_environment_arguments_are_one_line(pair, message) -> None:
    with pytest.raises(ConfigError) as error:
        resolve_config("classic", parse_overrides([pair]), env="CartPole-v1")
    assert message in str(error.value) and "\n" not in str(error.value)


def test_env_kwarg_and_wrapper_options_add_to_the_settings() -> None:
    config = resolve_config(
        "classic", parse_overrides(["env_kwargs={a = 1, b = 2}", "env_wrappers=m:First"]), env="x"
    )
    added = with_env_arguments(config, parse_pairs(["b=3", "c=8x8"], "--env-kwarg"), ["m:Second"])
    assert added.env_kwargs == {"a": 1, "b": 3, "c": "8x8"}
    assert added.env_wrappers == ("m:First", "m:Second")
    assert config.env_kwargs == {"a": 1, "b": 2}  # unchanged
    assert with_env_arguments(config, {}, []) is config


def test_values_read_as_toml_literals_else_as_plain_strings() -> None:
    assert parse_value("false") is False and parse_value(" 3 ") == 3
    assert parse_value("[4, 4]") == [4, 4] and parse_value("{x = 1}") == {"x": 1}
    assert parse_value('"8x8"') == "8x8" and parse_value("8x8") == "8x8"
    assert parse_value("LunarLander-v3") == "LunarLander-v3"
    with pytest.raises(ConfigError, match="--env-kwarg expects KEY=VALUE, got 'is_slippery'"):
        parse_pairs(["is_slippery"], "--env-kwarg")


def test_toml_tables_and_dates_read_back() -> None:
    import datetime

    for value in ({}, {"a": 1, "b c": "d", "e": {"f": [1, 2]}}, datetime.date(2026, 1, 2),
                  {"when": datetime.datetime(2026, 1, 2, 3, 4, 5)}):  # fmt: skip
        assert tomllib.loads(f"value = {toml_value(value)}")["value"] == value
    assert setting_text({"is_slippery": False}) == "{is_slippery = false}"
    with_date = resolve_config("classic", {"env_kwargs": {"day": datetime.date(2026, 1, 2)}})
    assert len(config_fingerprint(with_date)) == 64


def test_classic_anneals_epsilon_over_a_fraction_of_the_budget() -> None:
    # Issue 33: `--steps` scales classic's anneal as SB3's exploration_fraction does; at the
    # preset's own budget the anneal is the 8,000 steps it always was (the same run).
    assert resolve_config("classic", env="CartPole-v1").epsilon_decay_steps == 8_000
    assert (
        resolve_config("classic", env="CartPole-v1", total_steps=300_000).epsilon_decay_steps
        == 24_000
    )
    assert (
        resolve_config("classic", {"total_steps": 1_000}, env="CartPole-v1").epsilon_decay_steps
        == 80
    )
    # Steps given by the user win and turn the fraction off, so config.toml says what ran.
    given = resolve_config("classic", {"epsilon_decay_steps": 5_000}, total_steps=300_000)
    assert (given.epsilon_decay_steps, given.epsilon_decay_fraction) == (5_000, 0.0)
    # A fraction given with --set scales a preset that anneals in steps.
    nature = resolve_config("nature", {"epsilon_decay_fraction": 0.1}, total_steps=2_000_000)
    assert nature.epsilon_decay_steps == 200_000
    assert resolve_config("nature", total_steps=2_000_000).epsilon_decay_steps == 1_000_000


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"epsilon_decay_fraction": 1.5}, "epsilon_decay_fraction = 1.5 must be between 0 and 1"),
        ({"epsilon_decay_fraction": 0.2, "epsilon_decay_steps": 10}, "are both given"),
    ],
)
def test_a_bad_epsilon_fraction_is_one_line(overrides: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        resolve_config("classic", overrides, env="CartPole-v1")
