"""A part's own settings (`SETTINGS`, `parts.PART.NAME`): declared, filled in with their
defaults, set from TOML and `--set`, validated in one line, saved in config.toml, in the
fingerprint, varied by a sweep and named in the report's labels; a factory part reads them
as a class part does."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from torch import nn

from dqnlab.algorithm.networks import build_q_network
from dqnlab.analysis.report.runs import RunResults, group_runs, label_keys
from dqnlab.config import (
    Config,
    config_fingerprint,
    config_from_dict,
    config_to_toml,
    parse_overrides,
    resolve_config,
)
from dqnlab.config.files import tomllib
from dqnlab.errors import ConfigError
from dqnlab.parts import PartSetting, part_settings
from dqnlab.sweeps.grid import parse_variation, plan_grid

MUNCHAUSEN = "examples.munchausen:MunchausenLoss"
HERE = "tests.test_part_settings"
DEFAULTS = {"tau": 0.03, "alpha": 0.9, "l0": -1.0}


def wide_head(
    in_features: int, num_actions: int, config: Config, hidden_width: int | None
) -> nn.Module:
    """A head factory with a setting of its own: the width of its hidden layer."""
    width = part_settings("head", wide_head, config)["width"]
    layers = [nn.Linear(in_features, width), nn.ReLU(), nn.Linear(width, num_actions)]
    return nn.Sequential(*layers, nn.Unflatten(1, (num_actions, 1)))


wide_head.SETTINGS = {"width": PartSetting(24, "Units of the hidden layer")}  # type: ignore[attr-defined]


def _munchausen(*pairs: str) -> Config:
    return resolve_config(
        "classic", parse_overrides(list(pairs)), env="CartPole-v1", loss=MUNCHAUSEN
    )


def test_declared_defaults_are_filled_in_and_set_values_replace_them() -> None:
    assert _munchausen().parts == {"loss": DEFAULTS}
    config = _munchausen("parts.loss.tau=0.1", "parts.loss.alpha=1")
    assert config.parts == {"loss": {"tau": 0.1, "alpha": 1.0, "l0": -1.0}}
    assert isinstance(config.parts["loss"]["alpha"], float)  # an int given for a float
    assert resolve_config("classic", env="CartPole-v1").parts == {}  # shipped parts: none


def test_a_toml_table_sets_them_and_config_toml_keeps_them(tmp_path: Path) -> None:
    preset = tmp_path / "mine.toml"
    preset.write_text(f'loss = "{MUNCHAUSEN}"\n\n[parts.loss]\ntau = 0.2\n')
    config = resolve_config(str(preset), env="CartPole-v1")
    assert config.parts == {"loss": {**DEFAULTS, "tau": 0.2}}
    saved = tomllib.loads(config_to_toml(config))
    assert saved["parts"] == {"loss": {**DEFAULTS, "tau": 0.2}}
    assert config_from_dict(saved) == config


def test_they_are_part_of_the_fingerprint_and_the_default_fingerprint_is_unchanged() -> None:
    assert config_fingerprint(_munchausen()) != config_fingerprint(
        _munchausen("parts.loss.tau=0.1")
    )
    assert config_fingerprint(_munchausen()) == config_fingerprint(
        _munchausen("parts.loss.tau=0.03")
    )
    # `parts = {}` is left out, as every setting added with its default is.
    nature = resolve_config("nature", env="pong")
    assert config_fingerprint(nature).startswith("0ec1391b4c39d2a6")


@pytest.mark.parametrize(
    ("pairs", "message"),
    [
        (
            ["parts.loss.temp=1"],
            r"parts.loss.temp: loss part MunchausenLoss has no setting 'temp' "
            r"\(its settings: tau, alpha, l0\)",
        ),
        (["parts.loss.l0=true"], "parts.loss.l0 = True is not a valid float"),
        (["parts.loss=1"], "a part's setting is parts.PART.NAME"),
        (
            ["parts.network.depth=3"],
            "'network' is not a part setting; parts are loss, torso, head, policy, augmentation",
        ),
        (["parts.loss.tau=[1, 2]"], "must be a bool, int, float or string"),
    ],
)  # fmt: skip
def test_a_setting_that_does_not_fit_is_one_line(pairs: list[str], message: str) -> None:
    with pytest.raises(ConfigError, match=message) as error:
        _munchausen(*pairs)
    assert "\n" not in str(error.value)


def test_a_setting_for_a_shipped_part_is_refused() -> None:
    with pytest.raises(ConfigError, match="loss = 'auto' is a shipped part with no settings"):
        resolve_config("classic", {"parts.loss.tau": 0.1}, env="CartPole-v1")


def test_settings_for_a_part_that_cannot_be_loaded_say_so() -> None:
    with pytest.raises(ConfigError, match="loss = 'no_such_module:Loss' cannot be loaded"):
        resolve_config(
            "classic", {"parts.loss.tau": 0.1}, env="CartPole-v1", loss="no_such_module:Loss"
        )
    # Without settings, a part that is not importable here is the run's to refuse (as before).
    assert resolve_config("classic", env="CartPole-v1", loss="no_such_module:Loss").parts == {}


def test_a_factory_part_reads_its_settings_like_a_class() -> None:
    config = resolve_config(
        "classic", {"parts.head.width": 9}, env="CartPole-v1", head=f"{HERE}:wide_head"
    )
    assert config.parts == {"head": {"width": 9}}
    network = build_q_network(config, (1, 4), 2, is_image=False)
    assert network.head[0].out_features == 9
    default = resolve_config("classic", env="CartPole-v1", head=f"{HERE}:wide_head")
    assert build_q_network(default, (1, 4), 2, is_image=False).head[0].out_features == 24


def test_a_sweep_varies_them_and_the_report_labels_them(tmp_path: Path) -> None:
    sweep = plan_grid(
        ["CartPole-v1"], [parse_variation("parts.loss.tau=0.01,0.1")], preset="classic",
        overrides={"loss": MUNCHAUSEN}, seeds=1, first_seed=0, steps=None, sweep_dir=tmp_path,
    )  # fmt: skip
    assert [run.name for run in sweep.runs] == [
        "CartPole-v1-parts.loss.tau=0.01-s0",
        "CartPole-v1-parts.loss.tau=0.1-s0",
    ]
    assert [run.config.parts["loss"]["tau"] for run in sweep.runs] == [0.01, 0.1]
    results = [RunResults(run.run_dir, run.config, [], None) for run in sweep.runs]
    assert label_keys(results) == ["parts.loss.tau"]
    assert [group.label for group in group_runs(results)] == [
        "parts.loss.tau=0.01",
        "parts.loss.tau=0.1",
    ]


def test_a_munchausen_run_trains_with_a_setting_of_its_own() -> None:
    from dqnlab.run.state import TrainingState

    config = resolve_config(
        "classic", {"parts.loss.tau": 0.5}, env="CartPole-v1", loss=MUNCHAUSEN,
        replay_start_steps=50, total_steps=120, mlp_hidden_sizes=[16],
    )  # fmt: skip
    state = TrainingState(config, torch.device("cpu"))
    for _ in range(120):
        state.advance()
    assert state.agent.loss.tau == 0.5 and state.agent.updates == 35
