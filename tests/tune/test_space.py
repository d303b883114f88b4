"""The search space: the default one, a user's file over it, a trial's draw, and every bad
entry refused in one line naming it before any trial runs."""

from __future__ import annotations

from pathlib import Path

import pytest

optuna = pytest.importorskip(
    "optuna", reason="dqnlab tune needs the extra: pip install -e '.[tune]'"
)

from dqnlab.config import FIELD_NAMES, resolve_config  # noqa: E402
from dqnlab.errors import ConfigError  # noqa: E402
from dqnlab.tune.space import DEFAULT_SPACE, check_space, load_space, suggest  # noqa: E402

MUNCHAUSEN = "examples.munchausen:MunchausenLoss"


def test_the_default_space_names_real_settings_and_checks_against_classic() -> None:
    assert {entry.name for entry in DEFAULT_SPACE} <= set(FIELD_NAMES)
    check_space(DEFAULT_SPACE, "classic", {}, "CartPole-v1", 10_000)


def test_a_fixed_trial_draws_the_overrides_a_config_takes() -> None:
    params = {
        "learning_rate": 3e-4,
        "batch_size": 128,
        "update_period_steps": 4,
        "target_update_steps": 500,
        "target": "double",
        "epsilon_end": 0.05,
        "epsilon_decay_steps": 0.25 * 8000,
        "replay_capacity": 50_000,
        "replay_start_steps": 0.0501 * 8000,
        "n_step": 3,
        "dueling": True,
    }
    overrides = suggest(optuna.trial.FixedTrial(params), DEFAULT_SPACE, steps=8000)
    assert overrides["epsilon_decay_steps"] == 2000 and overrides["replay_start_steps"] == 401
    assert overrides["batch_size"] == 128 and overrides["dueling"] is True
    config = resolve_config("classic", overrides, env="CartPole-v1")
    assert config.learning_rate == 3e-4 and config.target == "double" and config.n_step == 3


def test_a_fraction_of_the_budget_is_drawn_between_its_bounds_in_steps() -> None:
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=1))
    for _ in range(20):
        overrides = suggest(study.ask(), DEFAULT_SPACE, steps=1000)
        assert 10 <= overrides["replay_start_steps"] <= 200
        assert 0 <= overrides["epsilon_decay_steps"] <= 500
        assert isinstance(overrides["replay_start_steps"], int)


def test_a_space_file_replaces_and_adds_entries(tmp_path: Path) -> None:
    path = tmp_path / "space.toml"
    path.write_text(
        '[learning_rate]\nkind = "float"\nlow = 0.001\nhigh = 0.01\n'
        "[discount]\nchoices = [0.95, 0.99]\n"
    )
    space = {entry.name: entry for entry in load_space(path)}
    assert space["learning_rate"].kind == "float" and space["learning_rate"].high == 0.01
    assert space["discount"].choices == (0.95, 0.99) and "batch_size" in space
    path.write_text("extend_default = false\n[discount]\nchoices = [0.95, 0.99]\n")
    assert [entry.name for entry in load_space(path)] == ["discount"]


def test_a_space_file_drops_default_entries_by_name(tmp_path: Path) -> None:
    path = tmp_path / "space.toml"
    path.write_text('drop = ["n_step", "learning_rate"]\n[discount]\nchoices = [0.95, 0.99]\n')
    names = [entry.name for entry in load_space(path)]
    defaults = [entry.name for entry in DEFAULT_SPACE]
    assert names == [name for name in defaults if name not in ("n_step", "learning_rate")] + [
        "discount"
    ]
    path.write_text('drop = ["n_step"]\n[n_step]\nchoices = [1, 3]\n')  # dropped, then given
    assert {entry.name: entry for entry in load_space(path)}["n_step"].choices == (1, 3)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('drop = ["nstep"]\n', "drop names 'nstep', which is not in the default space"),
        ('drop = "n_step"\n', "drop = 'n_step' must be a list of setting names"),
        (
            'extend_default = false\ndrop = ["n_step"]\n[discount]\nchoices = [0.9]\n',
            "with extend_default = false: there is no default entry to drop",
        ),
    ],
)
def test_a_bad_drop_is_refused_in_one_line(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "space.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as error:
        load_space(path)
    assert message in str(error.value) and "\n" not in str(error.value)


def test_a_parts_own_setting_is_searched_like_any_other(tmp_path: Path) -> None:
    path = tmp_path / "space.toml"
    path.write_text(
        'extend_default = false\n["parts.loss.tau"]\nkind = "float-log"\nlow = 0.01\nhigh = 0.1\n'
    )
    space = load_space(path)
    check_space(space, "classic", {"loss": MUNCHAUSEN}, "CartPole-v1", 1000)
    overrides = suggest(optuna.trial.FixedTrial({"parts.loss.tau": 0.02}), space, 1000)
    config = resolve_config("classic", {"loss": MUNCHAUSEN, **overrides}, env="CartPole-v1")
    assert config.parts["loss"]["tau"] == 0.02


@pytest.mark.parametrize(
    ("text", "fixed", "message"),
    [
        (
            '[learning_rat]\nkind = "float"\nlow = 0.1\nhigh = 0.2\n',
            {},
            "search space entry 'learning_rat': unknown setting",
        ),
        (
            '[batch_size]\nkind = "float"\nlow = 16\nhigh = 64\n',
            {},
            "search space entry 'batch_size': batch_size is a int setting",
        ),
        (
            '[dueling]\nkind = "int"\nlow = 0\nhigh = 1\n',
            {},
            "search space entry 'dueling': dueling is a bool setting",
        ),
        (
            '[target]\nchoices = ["max", "triple"]\n',
            {},
            "search space entry 'target': target = 'triple' is refused",
        ),
        ("[batch_size]\nchoices = [32, 0]\n", {}, "batch_size = 0 is refused"),
        (
            '[learning_rate]\nkind = "float-log"\nlow = 0\nhigh = 0.1\n',
            {},
            "search space entry 'learning_rate': low = 0 and high = 0.1 are not a float-log",
        ),
        (
            '[learning_rate]\nkind = "float"\nlow = "a"\nhigh = 0.1\n',
            {},
            "a float entry has numbers low and high",
        ),
        ('[learning_rate]\nkind = "normal"\n', {}, "kind = 'normal' is not one of"),
        (
            '[learning_rate]\nkind = "float"\nlow = 0.1\nhigh = 0.2\nstep = 1\n',
            {},
            "unknown key 'step'",
        ),
        (
            '["parts.loss.tau"]\nkind = "float"\nlow = 0.1\nhigh = 0.2\n',
            {},
            "the loss part of this configuration declares no setting 'tau'",
        ),
        ("[n_step]\nchoices = [1, 3]\n", {"n_step": 3}, "n_step is also fixed by --set"),
    ],
)
def test_a_bad_entry_is_refused_in_one_line_naming_it(
    tmp_path: Path, text: str, fixed: dict, message: str
) -> None:
    path = tmp_path / "space.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as error:
        check_space(load_space(path), "classic", fixed, "CartPole-v1", 1000)
    assert message in str(error.value) and "\n" not in str(error.value)


def test_a_space_file_that_is_not_toml_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "space.toml"
    path.write_text("[learning_rate\n")
    with pytest.raises(ConfigError, match="is not valid TOML"):
        load_space(path)
