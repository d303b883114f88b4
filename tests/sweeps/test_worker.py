"""A run's attempt on a Ray worker: the shared-storage check, and the subprocess that
unblocks the stop signals and stops itself once when its worker dies."""

from __future__ import annotations

from pathlib import Path

import pytest

from dqnlab.errors import DqnlabError
from dqnlab.sweeps.grid import plan_grid, write_sweep_file
from dqnlab.sweeps.worker import check_sweep_marker


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


def test_a_runs_subprocess_unblocks_the_stop_signals_its_ray_worker_blocks() -> None:
    """A Ray worker's threads block SIGINT and a child inherits the mask: without the
    preamble's unblock, Ctrl-C of the driver never reached `dqnlab train`."""
    import os
    import signal
    import subprocess
    import sys

    from dqnlab.sweeps.worker import _DIE_WITH_PARENT

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

    from dqnlab.sweeps.worker import _DIE_WITH_PARENT, PARENT_POLL_SECONDS

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


def test_a_run_is_done_once_trained_and_evaluated_where_its_protocol_says_so(
    tmp_path: Path,
) -> None:
    """A run killed while playing the final evaluation its protocol ends with (Atari 100k's)
    is not done: the sweep starts it again and it plays the evaluation, and `dqnlab status`
    does not call it done meanwhile."""
    import torch

    from dqnlab.analysis.status import run_status
    from dqnlab.config import resolve_config
    from dqnlab.run.rundir import prepare_run_dir, save_final_evaluation, trained_to_budget
    from dqnlab.run.train import train

    for ends_with_evaluation in (False, True):
        run_dir = tmp_path / f"run-{ends_with_evaluation}"
        config = resolve_config(
            "classic", env="CartPole-v1", total_steps=200, replay_start_steps=100,
            eval_period_steps=0, final_eval_after_training=ends_with_evaluation,
        )  # fmt: skip
        prepare_run_dir(run_dir, force=False)
        train(config, run_dir, torch.device("cpu"), progress=False, tensorboard=False)
        assert not trained_to_budget(run_dir, 300)
        assert trained_to_budget(run_dir, 200) is not ends_with_evaluation
        assert (run_status(run_dir).state == "done") is not ends_with_evaluation
        save_final_evaluation(run_dir, {"mean": 1.0, "checkpoint_step": 200})
        assert trained_to_budget(run_dir, 200)
        assert run_status(run_dir).state == "done"
