"""One attempt at one run of a sweep, in a Ray worker on any node: check that the node sees
the driver's sweep directory, wait for the run's lease, and train (resuming if started)
with `dqnlab train` in a subprocess that dies with the worker. A run whose subprocess was
killed raises RunProcessKilled, which Ray retries on any node."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from dqnlab.analysis import status as run_states
from dqnlab.errors import DqnlabError
from dqnlab.run import rundir
from dqnlab.run.lease import LEASE_HELD_EXIT_STATUS, release_dead_owner, wait_until_free
from dqnlab.run.rundir import trained_to_budget

STOP_WAIT_SECONDS = 300.0  # Ctrl-C: how long runs may take to write their checkpoint
# `dqnlab train` exit statuses after a stop request (SIGINT, SIGTERM) and SIGKILL by shell.
STOPPED_EXIT_STATUS, TERMINATED_EXIT_STATUS, KILLED_EXIT_STATUS = 130, 143, 137


class RunProcessKilled(Exception):
    """The run's process died by a signal: Ray retries the task (retry_exceptions)."""


# The Ray workers that run the runs, on any cluster. A worker that exits (its node lost,
# its raylet gone) SIGKILLs its child processes unless told not to (Ray 2.60: "Try killing
# all child processes of this worker as it exits" in the worker's log): the run's process
# would die without its stop checkpoint and without releasing its lease. Without that
# kill, `_DIE_WITH_PARENT`'s SIGTERM reaches it and it checkpoints and stops.
WORKER_ENVIRONMENT = {"RAY_kill_child_processes_on_worker_exit": "0"}

# Run first in the subprocess. It sends itself one SIGTERM when the worker that started it
# dies (a lost node, a killed Ray), so that it checkpoints and stops instead of training on
# unowned. One: `dqnlab train` takes a second stop request as "stop at once", and
# PR_SET_PDEATHSIG, tried first, fires each time a thread the child is reparented to exits
# (measured with strace on a lost node: two or three SIGTERMs from the dying worker, the
# second one often before the stop checkpoint was written). Hence a thread watching the
# parent's pid. It also unblocks SIGINT and SIGTERM: a Ray worker's threads block SIGINT, a
# child inherits the mask (measured with Ray 2.60: SigBlk 0x2 in /proc/PID/status), and a
# blocked SIGINT never reaches the training loop's stop handler.
PARENT_POLL_SECONDS = 0.5
_DIE_WITH_PARENT = (
    "import os, signal, sys, threading, time\n"
    "signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})\n"
    "parent = int(sys.argv.pop(1))\n"
    "if os.getppid() != parent:\n"
    "    sys.exit(143)\n"
    "def stop_when_orphaned():\n"
    "    while os.getppid() == parent:\n"
    f"        time.sleep({PARENT_POLL_SECONDS})\n"
    "    os.kill(os.getpid(), signal.SIGTERM)\n"
    "threading.Thread(target=stop_when_orphaned, daemon=True).start()\n"
    "sys.argv[0] = 'dqnlab'\n"
    "from dqnlab.cli import main\n"
    "main()\n"
)


def train_command(task: dict[str, Any]) -> list[str]:
    return [
        sys.executable, "-c", _DIE_WITH_PARENT, str(os.getpid()), "train",
        "--env", task["env"],
        "--preset", task["config_path"],
        "--run-dir", task["run_dir"],
        "--device", task["device"],
        "--no-progress",
    ]  # fmt: skip


def train_attempt(task: dict[str, Any]) -> dict[str, Any]:
    """One attempt at one run, in a Ray worker: check the shared storage, wait for the run's
    lease, train (resuming if started) in a subprocess. Returns {"outcome": done, ok,
    failed or stopped, ...}; raises RunProcessKilled for Ray to retry."""
    import ray

    host = socket.gethostname()
    sweep_dir, run_dir = Path(task["sweep_dir"]), Path(task["run_dir"])
    check_sweep_marker(sweep_dir, task["token"], host)
    if trained_to_budget(run_dir, task["total_steps"]):
        return {"outcome": "done", "host": host}
    run_dir.mkdir(parents=True, exist_ok=True)
    attempt = sum(e.get("event") == "start" for e in run_states.read_attempts(run_dir)) + 1
    node_id = ray.get_runtime_context().get_node_id()
    environment = {**os.environ, "OMP_NUM_THREADS": str(task["threads"]),
                   "MKL_NUM_THREADS": str(task["threads"])}  # fmt: skip
    while True:
        wait_until_free(run_dir)
        started = time.time()
        with open(task["log"], "ab") as log:
            process = subprocess.Popen(
                train_command(task), stdout=log, stderr=subprocess.STDOUT, env=environment,
                start_new_session=True,  # a Ctrl-C reaches it from the driver, not the terminal
            )  # fmt: skip
            run_states.record_attempt(run_dir, {
                "event": "start", "attempt": attempt, "node_id": node_id, "host": host,
                "pid": process.pid, "time": started,
            })  # fmt: skip
            code = _wait_for(process)
        if code != LEASE_HELD_EXIT_STATUS:
            break
        # Another process took the lease between our wait and the start: wait again.
    ended = time.time()
    if code == 0:
        outcome = "done"
    elif code == STOPPED_EXIT_STATUS:
        outcome = "stopped"
    elif code < 0 or code in (TERMINATED_EXIT_STATUS, KILLED_EXIT_STATUS):
        outcome = "killed"
        release_dead_owner(run_dir, process.pid)
    else:
        outcome = "failed"
    run_states.record_attempt(run_dir, {
        "event": "end", "attempt": attempt, "outcome": outcome, "exit_status": code,
        "time": ended,
    })  # fmt: skip
    if outcome == "killed":
        raise RunProcessKilled(f"{task['name']}: exit status {code} on {host}")
    return {"outcome": "ok" if outcome == "done" else outcome, "host": host,
            "exit_status": code, "seconds": ended - started}  # fmt: skip


def _wait_for(process: subprocess.Popen[bytes]) -> int:
    """The subprocess's exit status; a cancel (ray.cancel raises KeyboardInterrupt here)
    asks it to checkpoint and stop (SIGINT) and waits for that."""
    try:
        while True:
            try:
                return process.wait(timeout=1.0)  # wakes up to let a cancel in
            except subprocess.TimeoutExpired:
                continue
    except KeyboardInterrupt:
        process.send_signal(signal.SIGINT)
        return process.wait(timeout=STOP_WAIT_SECONDS)


def check_sweep_marker(sweep_dir: Path, token: str, host: str) -> None:
    """Fail on a node that does not see the driver's sweep directory (not shared storage):
    training there would go into a local directory lost with the node."""
    recorded = run_states.load_sweep_file(sweep_dir) if sweep_dir.is_dir() else None
    if recorded is None or recorded.get("token") != token:
        raise DqnlabError(
            f"node {host} does not see the sweep directory {sweep_dir} the driver created "
            f"({rundir.SWEEP_FILE} {'missing' if recorded is None else 'of another sweep'}): "
            "the sweep directory must be on storage every node mounts at the same path"
        )
