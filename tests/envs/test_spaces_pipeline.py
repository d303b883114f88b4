"""Every kind of observation space through what a user does with a run: train, resume,
evaluate, inspect and report (a few hundred steps each, the commands run in this process).
The bit-identical resume of a structured observation is in tests/run/test_resume.py."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dqnlab.run.rundir import load_run_config
from tests.envs import space_envs
from tests.helpers import dqnlab_main

SHORT = [
    "--steps", "240", "--seed", "3", "--no-progress", "--device", "cpu",
    "--set", "replay_start_steps=64", "--set", "eval_period_steps=120",
    "--set", "eval_steps=48", "--set", "replay_capacity=500", "--set", "batch_size=8",
    "--set", "history_length=2", "--set", "mlp_hidden_sizes=[16]",
    "--set", "final_eval_max_episode_frames=50",
]  # fmt: skip
NETWORKS = {  # what `auto` chose, as the run's config.toml records it
    "int-vector": "auto",  # the MLP, on the packed int16 vector
    "bool-image": "small_cnn",
    "float-image": "small_cnn",
    "discrete": "auto",
    "multi-discrete": "auto",
    "multi-binary": "auto",
    "tuple": "auto",
    "nested-dict": "multi_input",
}


def test_every_space_trains_resumes_evaluates_inspects_and_reports(
    tmp_path: Path, capsys, monkeypatch
) -> None:
    runs = []
    for name, env_class in space_envs.SPACE_ENVS.items():
        run = tmp_path / name
        env = f"tests.envs.space_envs:{env_class.__name__}"
        code, err = dqnlab_main(
            capsys, monkeypatch, "train", "--env", env, "--run-dir", str(run), *SHORT
        )
        assert code == 0, (name, err)
        assert load_run_config(run).network == NETWORKS[name]
        code, err = dqnlab_main(
            capsys, monkeypatch, "resume", str(run), "--steps", "300", "--no-progress"
        )
        assert code == 0, (name, err)
        code, err = dqnlab_main(
            capsys, monkeypatch, "evaluate", str(run), "--episodes", "2",
            "--json", str(tmp_path / f"{name}.json"),
        )  # fmt: skip
        assert code == 0, (name, err)
        result = json.loads((tmp_path / f"{name}.json").read_text())
        assert len(result["scores"]) == 2 and all(0 <= s <= 8 for s in result["scores"])
        runs.append(str(run))
    # Q-value figures of a structured observation: its parts' values beside the Q-values.
    code, err = dqnlab_main(capsys, monkeypatch, "inspect", runs[-1], "--frames", "2")
    assert code == 0, err
    assert len(list((Path(runs[-1]) / "inspect").glob("frame-*.png"))) == 2
    code, err = dqnlab_main(capsys, monkeypatch, "report", *runs, "--out", str(tmp_path / "r"))
    assert code == 0, err
    results = (tmp_path / "r" / "results.md").read_text()
    for env_class in space_envs.SPACE_ENVS.values():
        assert env_class.__name__ in results


@pytest.mark.parametrize("images", ["none", "all"])
def test_the_image_choice_can_be_overridden(tmp_path: Path, capsys, monkeypatch, images) -> None:
    run = tmp_path / images
    env = "tests.envs.space_envs:BoolImageEnv"
    code, err = dqnlab_main(
        capsys, monkeypatch, "train", "--env", env, "--run-dir", str(run), *SHORT,
        "--set", f"observation_images={images}",
    )  # fmt: skip
    assert code == 0, err
    assert load_run_config(run).network == ("auto" if images == "none" else "small_cnn")


class NoFramesEnv(space_envs.DiscreteEnv):
    """Says it renders rgb_array, but its render() gives nothing."""

    def render(self):  # type: ignore[override]
        return None


def test_a_structured_observation_is_filmed_and_an_env_without_frames_says_why_not(
    tmp_path: Path, capsys, monkeypatch
) -> None:
    for name, env in (
        ("dict", "tests.envs.space_envs:NestedDictEnv"),
        ("none", f"{__name__}:NoFramesEnv"),
    ):
        run = tmp_path / name
        code, err = dqnlab_main(
            capsys, monkeypatch, "train", "--env", env, "--run-dir", str(run), *SHORT
        )
        assert code == 0, err
        code, err = dqnlab_main(
            capsys, monkeypatch, "evaluate", str(run), "--episodes", "1",
            "--video", str(tmp_path / f"{name}-video"),
        )  # fmt: skip
        if name == "dict":
            assert code == 0, err
            assert list((tmp_path / "dict-video").glob("*.mp4")), err
        else:
            assert code != 0
            lines = [line for line in err.splitlines() if "error" in line]
            assert len(lines) == 1 and "renders None, not an RGB image" in lines[0], err
