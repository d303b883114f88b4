"""`dqnlab sweep`'s grid, resources and bad inputs: all checked before Ray or any run starts."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from dqnlab import cli
from dqnlab.config import resolve_config
from dqnlab.errors import DqnlabError
from dqnlab.sweeps.sweep import (
    PROCESS_OVERHEAD_BYTES,
    RunResources,
    check_resources,
    check_sweep_marker,
    game_set,
    parse_variation,
    plan_grid,
    run_memory_bytes,
    write_sweep_file,
)

NODE = {"CPU": 4.0, "memory": 8e9}


def test_grid_is_games_times_settings_times_seeds(tmp_path: Path) -> None:
    sweep = plan_grid(
        ["pong", "breakout"],
        [parse_variation("optimizer+learning_rate=rmsprop+0.00025,adam+0.0001")],
        preset=None, overrides={"replay_capacity": 1000}, seeds=2, first_seed=0, steps=500,
        sweep_dir=tmp_path,
    )  # fmt: skip
    assert len(sweep.runs) == 8
    assert sweep.runs[0].name == "pong-optimizer=rmsprop,learning_rate=0.00025-s0"
    assert {run.config.env for run in sweep.runs} == {"pong", "breakout"}
    assert sweep.preset == "nature" and all(
        run.config.replay_capacity == 1000 for run in sweep.runs
    )
    plain = plan_grid(["CartPole-v1"], [], preset=None, overrides={}, seeds=2, first_seed=3,
                      steps=None, sweep_dir=tmp_path)  # fmt: skip
    assert [run.name for run in plain.runs] == ["CartPole-v1-s3", "CartPole-v1-s4"]


def test_game_sets() -> None:
    nature = game_set("nature49")
    assert len(nature) == 49 and "pong" in nature and "surround" not in nature
    assert len(game_set("atari57")) == 57


def test_memory_asked_is_the_replay_plus_the_process() -> None:
    config = resolve_config("nature", env="pong")  # 1M frames of 84 × 84
    assert run_memory_bytes(config) > 1_000_000 * 84 * 84 + PROCESS_OVERHEAD_BYTES
    compressed = resolve_config("nature", {"replay_compression": "lz4"}, env="pong")
    assert run_memory_bytes(compressed) < run_memory_bytes(config) / 3


def test_resources_no_node_has_are_refused_with_the_numbers() -> None:
    check_resources(RunResources(2, 0, int(4e9)), [NODE])
    with pytest.raises(DqnlabError, match=r"8 CPUs, 0 GPUs and 4.0 GB.*4 CPUs/0 GPUs/8.0 GB"):
        check_resources(RunResources(8, 0, int(4e9)), [NODE])
    with pytest.raises(DqnlabError, match="more than any node has"):
        check_resources(RunResources(1, 0, int(9e9)), [NODE])
    with pytest.raises(DqnlabError, match="--gpus-per-run 0.25: the cluster has no GPUs"):
        check_resources(RunResources(1, 0.25, int(1e9)), [NODE])
    check_resources(RunResources(1, 0.25, int(1e9)), [{**NODE, "GPU": 1.0}])


def test_a_node_that_does_not_see_the_sweep_directory_fails_clearly(tmp_path: Path) -> None:
    sweep = plan_grid(["CartPole-v1"], [], preset=None, overrides={}, seeds=1, first_seed=0,
                      steps=None, sweep_dir=tmp_path / "sweep")  # fmt: skip
    token = write_sweep_file(sweep)
    check_sweep_marker(sweep.directory, token, "node-a")
    assert write_sweep_file(sweep) == token  # the same sweep again keeps its marker
    with pytest.raises(
        DqnlabError, match="node node-b does not see the sweep directory .* missing"
    ):
        check_sweep_marker(tmp_path / "local-copy", token, "node-b")
    with pytest.raises(DqnlabError, match="of another sweep"):
        check_sweep_marker(sweep.directory, "another", "node-b")


def dqnlab_main(capsys: pytest.CaptureFixture[str], monkeypatch, *args: str) -> tuple[int, str]:  # noqa: ANN001
    """`dqnlab ARGS` in this process (no interpreter start-up): its exit status and stderr."""
    monkeypatch.setattr(sys, "argv", ["dqnlab", *args])
    with pytest.raises(SystemExit) as exit_info:
        cli.main()
    return int(exit_info.value.code or 0), capsys.readouterr().err


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


def test_a_runs_subprocess_unblocks_the_stop_signals_its_ray_worker_blocks() -> None:
    """A Ray worker's threads block SIGINT and a child inherits the mask: without the
    preamble's unblock, Ctrl-C of the driver never reached `dqnlab train`."""
    import os
    import signal
    import subprocess
    import sys

    from dqnlab.sweeps.sweep import _DIE_WITH_PARENT

    preamble = _DIE_WITH_PARENT.split("from dqnlab.cli")[0]
    probe = preamble + "print(open('/proc/self/status').read())\n"

    def block() -> None:
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})

    def blocked(code: str) -> int:
        status = subprocess.run(
            [sys.executable, "-c", code, str(os.getpid())],
            preexec_fn=block, capture_output=True, text=True, check=True,
        ).stdout  # fmt: skip
        mask = next(line for line in status.splitlines() if line.startswith("SigBlk:"))
        return int(mask.split()[1], 16)

    both = (1 << (signal.SIGINT - 1)) | (1 << (signal.SIGTERM - 1))
    assert blocked("print(open('/proc/self/status').read())") & both  # inherited, as from Ray
    assert blocked(probe) & both == 0


def test_a_runs_subprocess_stops_itself_once_when_its_worker_dies(tmp_path: Path) -> None:
    """The preamble's watcher: the parent (a stand-in for the Ray worker) exits, and the run
    gets one SIGTERM, not one per exiting thread as PR_SET_PDEATHSIG gave (a second stop
    request means "stop at once", before the checkpoint)."""
    import subprocess
    import sys
    import time

    from dqnlab.sweeps.sweep import _DIE_WITH_PARENT, PARENT_POLL_SECONDS

    preamble = _DIE_WITH_PARENT.split("sys.argv[0] = ")[0]
    record = tmp_path / "signals.txt"
    run = preamble + (
        "import signal, time\n"
        f"signal.signal(signal.SIGTERM, lambda *_: open({str(record)!r}, 'a').write('TERM\\n'))\n"
        "open(" + repr(str(record)) + ", 'a').write('started\\n')\n"
        "time.sleep(3)\n"
    )
    worker = (
        "import os, subprocess, sys, threading, time\n"
        "def start():\n"
        f"    subprocess.Popen([sys.executable, '-c', {run!r}, str(os.getpid())])\n"
        "thread = threading.Thread(target=start)\n"  # started from a thread, as in a worker
        "thread.start(); thread.join(); time.sleep(1.0)\n"
    )
    subprocess.run([sys.executable, "-c", worker], check=True, timeout=30)
    deadline = time.monotonic() + 4 + 2 * PARENT_POLL_SECONDS
    while time.monotonic() < deadline and "TERM" not in (
        record.read_text() if record.exists() else ""
    ):
        time.sleep(0.1)
    time.sleep(1.5)  # a second signal would come now
    assert record.read_text().split() == ["started", "TERM"]
