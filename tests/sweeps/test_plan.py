"""The sweep's and the ablation's options planned without the command line: the grid, each
run's resources and device, the default sweep directory, and bad options refused."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from dqnlab.errors import DqnlabError
from dqnlab.sweeps.plan import ablation_jobs, plan_ablation_options, plan_sweep_options


def sweep_options(**changed: Any) -> dict[str, Any]:
    options: dict[str, Any] = {
        "env": "CartPole-v1", "games": None, "preset": None, "seeds": 2, "first_seed": 0,
        "vary": ["discount=0.9,0.99"], "settings": ["replay_capacity=1000"], "steps": 500,
        "sweep_dir": None, "cpus_per_run": 1.0, "gpus_per_run": 0.0, "memory_per_run_gb": 2.5,
        "max_retries": 3,
    }  # fmt: skip
    return {**options, **changed}


def test_a_sweep_plan_is_the_grid_its_resources_and_device(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)  # the default sweep directory is relative
    plan = plan_sweep_options(**sweep_options())
    assert [run.name for run in plan.sweep.runs] == [
        "CartPole-v1-discount=0.9-s0", "CartPole-v1-discount=0.9-s1",
        "CartPole-v1-discount=0.99-s0", "CartPole-v1-discount=0.99-s1",
    ]  # fmt: skip
    assert all(run.config.replay_capacity == 1000 for run in plan.sweep.runs)
    assert plan.sweep.directory.parts[0] == "sweeps"
    assert (plan.resources.cpus, plan.resources.memory_bytes) == (1.0, 2_500_000_000)
    assert plan.device == "cpu"
    on_gpus = plan_sweep_options(**sweep_options(gpus_per_run=0.5, sweep_dir=tmp_path / "g"))
    assert on_gpus.device == "cuda" and on_gpus.resources.gpus == 0.5
    assert not (tmp_path / "sweeps").exists()  # planning writes nothing


@pytest.mark.parametrize(
    ("changed", "message"),
    [
        ({"games": "atari57"}, "needs one of --env"),
        ({"max_retries": -1}, "--max-retries -1 must be 0 or more"),
        ({"memory_per_run_gb": 0.0}, "--memory-per-run 0.0 must be positive"),
        ({"vary": ["seed=1,2"]}, "use --seeds"),
    ],
)
def test_bad_sweep_options_are_refused(
    tmp_path: Path, changed: dict[str, Any], message: str
) -> None:
    with pytest.raises(DqnlabError, match=message):  # ConfigError is one
        plan_sweep_options(**sweep_options(sweep_dir=tmp_path / "sweep", **changed))


def test_an_ablation_plan_and_its_jobs(tmp_path: Path) -> None:
    sweep = plan_ablation_options(
        env="CartPole-v1", vary=["discount=0.9,0.99"], preset=None, settings=[], seeds=1,
        first_seed=0, steps=500, sweep_dir=tmp_path / "ablation",
    )  # fmt: skip
    assert [run.name for run in sweep.runs] == ["discount=0.9-s0", "discount=0.99-s0"]
    assert sweep.preset == "tuned/CartPole-v1"  # train's choice for the id
    assert ablation_jobs(sweep, 1) == 1
    assert 1 <= ablation_jobs(sweep, None) <= 2
    with pytest.raises(DqnlabError, match="--jobs 0 must be positive"):
        ablation_jobs(sweep, 0)


def test_env_kwargs_and_wrappers_reach_every_run_and_may_be_varied(tmp_path: Path) -> None:
    count = "tests.envs.test_env_args:CountEnv"
    sweep = plan_ablation_options(
        env=count, vary=["env_kwargs={length = 3},{length = 5, width = 4}"], preset=None,
        settings=["env_kwargs={width = 9}"], seeds=1, first_seed=0, steps=500,
        sweep_dir=tmp_path / "ablation", env_kwargs=["width=2"],
        wrappers=["tests.envs.test_env_args:first"],
    )  # fmt: skip
    assert [run.name for run in sweep.runs] == [
        "env_kwargs=length=3-s0", "env_kwargs=length=5+width=4-s0"
    ]  # fmt: skip
    # --env-kwarg adds to (and replaces a key of) the table that --set or --vary gives.
    assert [run.config.env_kwargs for run in sweep.runs] == [
        {"length": 3, "width": 2}, {"length": 5, "width": 2}
    ]  # fmt: skip
    assert all(run.config.env_wrappers == ("tests.envs.test_env_args:first",) for run in sweep.runs)
    with pytest.raises(DqnlabError, match="env_kwargs rejected: TypeError: .*'height'"):
        plan_ablation_options(
            env=count, vary=["env_kwargs={length = 3},{length = 5, height = 4}"], preset=None,
            settings=[], seeds=1, first_seed=0, steps=500, sweep_dir=tmp_path / "bad",
        )  # fmt: skip
    with pytest.raises(DqnlabError, match="^pong: env_kwargs apply to Gymnasium environments"):
        plan_sweep_options(**sweep_options(env="pong", vary=[], settings=[], env_kwargs=["a=1"]))


def test_an_atari100k_sweep_off_the_protocol_is_warned_of(tmp_path: Path) -> None:
    options = sweep_options(env=None, games="atari100k", preset="der", seeds=1, vary=[],
                            settings=[], steps=None, sweep_dir=tmp_path / "s")  # fmt: skip
    assert plan_sweep_options(**options).warnings == ()
    off = plan_sweep_options(**{**options, "settings": ["sticky_action_probability=0.25"]})
    (warning,) = off.warnings
    assert warning.startswith("--games atari100k with sticky_action_probability = 0.25 (the ")
    assert "not comparable with the published ones" in warning and "\n" not in warning
    shorter = plan_sweep_options(**{**options, "steps": 50_000}).warnings
    assert [w.split(" (")[0] for w in shorter] == ["--games atari100k with total_steps = 50000"]
