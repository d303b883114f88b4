"""`dqnlab sweep`'s bad inputs: one line and exit status 2, before Ray or any run starts."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.helpers import dqnlab_main


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--games", "nature50"], "--games 'nature50' is not a game set; accepted: nature49"),
        (["--env", "pong,pongg"], "close matches: pong"),
        (["--env", "pong", "--games", "atari57"], "needs one of --env"),
        (["--env", "pong", "--cpus-per-run", "0"], "--cpus-per-run 0.0 must be positive"),
        (["--env", "pong", "--vary", "seed=1,2"], "use --seeds"),
        (["--env", "pong", "--address", "127.0.0.1:9"], "nothing answers at 127.0.0.1:9"),
        (["--env", "pong", "--address", "nowhere"], "is not one of: local, auto, HOST:PORT"),
        (["--env", "pong", "--env-kwarg", "mode=1"], "pong: env_kwargs apply to Gymnasium"),
        (
            ["--env", "CartPole-v1", "--wrapper", "no_such_dqnlab_module:W"],
            "wrapper 'no_such_dqnlab_module:W': cannot import no_such_dqnlab_module",
        ),
        (
            ["--env", "FrozenLake-v1", "--env-kwarg", "map_name=9x9"],
            "FrozenLake-v1: env_kwargs rejected: KeyError: '9x9'",
        ),
        (
            ["--env", "CartPole-v1", "--env-kwarg", "sutton_barto_reward"],
            "--env-kwarg expects KEY=VALUE, got 'sutton_barto_reward'",
        ),
    ],
)
def test_bad_input_gives_one_line_and_exit_2(
    tmp_path: Path,
    capsys,
    monkeypatch,
    args: list[str],
    message: str,  # noqa: ANN001
) -> None:
    sweep_dir = tmp_path / "sweep"
    code, stderr = dqnlab_main(capsys, monkeypatch, "sweep", *args, "--sweep-dir", str(sweep_dir))
    assert code == 2 and message in stderr, stderr
    assert len(stderr.strip().splitlines()) == 1 and "Traceback" not in stderr
    assert not sweep_dir.exists()


def test_address_auto_goes_where_ray_address_says(tmp_path: Path, capsys, monkeypatch) -> None:  # noqa: ANN001
    """`auto` resolves the address as Ray does (RAY_ADDRESS first, as `ray job submit` sets
    it for its entrypoint), and checks that it answers before Ray is asked to join it."""
    monkeypatch.setenv("RAY_ADDRESS", "127.0.0.1:9")
    sweep_dir = tmp_path / "sweep"
    code, stderr = dqnlab_main(
        capsys, monkeypatch, "sweep", "--env", "pong", "--address", "auto", "--sweep-dir",
        str(sweep_dir),
    )  # fmt: skip
    assert code == 2 and "--address auto (127.0.0.1:9): nothing answers at 127.0.0.1:9" in stderr
    assert len(stderr.strip().splitlines()) == 1 and not sweep_dir.exists()


def test_a_games_file_and_a_sweep_dir_of_another_sweep(tmp_path: Path, capsys, monkeypatch) -> None:  # noqa: ANN001
    games = tmp_path / "games.txt"
    games.write_text("pong  # the first\nbreakoutt\n")
    code, stderr = dqnlab_main(capsys, monkeypatch, "sweep", "--games", str(games))
    assert code == 2 and "breakoutt" in stderr and "close matches: breakout" in stderr
    sweep_dir = tmp_path / "sweep"
    sweep_dir.mkdir()
    recorded = {"token": "t", "preset": "nature", "vary_keys": ["discount"], "runs": []}
    (sweep_dir / "sweep.json").write_text(json.dumps(recorded))
    before = (sweep_dir / "sweep.json").read_text()
    code, stderr = dqnlab_main(
        capsys, monkeypatch, "sweep", "--env", "pong", "--sweep-dir", str(sweep_dir)
    )
    assert code == 2 and "holds a different sweep (preset nature, varied: discount)" in stderr
    assert (sweep_dir / "sweep.json").read_text() == before


def test_ablate_takes_env_kwargs_and_wrappers_too(tmp_path: Path, capsys, monkeypatch) -> None:  # noqa: ANN001
    sweep_dir = tmp_path / "ablation"
    code, stderr = dqnlab_main(
        capsys, monkeypatch, "ablate", "--env", "breakout", "--vary", "discount=0.9,0.99",
        "--wrapper", "tests.envs.test_env_args:first", "--sweep-dir", str(sweep_dir),
    )  # fmt: skip
    assert code == 2 and "breakout: env_wrappers apply to Gymnasium environments" in stderr
    code, stderr = dqnlab_main(
        capsys, monkeypatch, "ablate", "--env", "FrozenLake-v1", "--vary", "discount=0.9,0.99",
        "--env-kwarg", "slippery=false", "--sweep-dir", str(sweep_dir),
    )  # fmt: skip
    assert code == 2 and "FrozenLake-v1: env_kwargs rejected: TypeError: " in stderr
    assert len(stderr.strip().splitlines()) == 1 and not sweep_dir.exists()
