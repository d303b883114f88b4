"""CleanRL's DQN as a peer for `--cleanrl DIR` (`dqnlab bench throughput` and `envs`): its
`cleanrl/dqn_atari.py` run from a checkout, unchanged, in a venv of its own with the
versions CleanRL's lock pins.

No current CleanRL is on PyPI, so the script runs from the checkout at DIR with
`PYTHONPATH=DIR` (for `cleanrl_utils`). The venv is made once, under the user's cache, from
DIR's `requirements/requirements-atari.txt` used as pip constraints, for what the script and
`cleanrl_utils` import. One pin is changed: ale-py 0.8.1 needs ROMs that AutoROM downloads,
while ale-py 0.9 ships them in its wheels and runs under the pinned gymnasium 0.29.1. ale-py
0.9 registers its envs when imported, which gymnasium 0.29 does not do by itself (shimmy
1.1.0's registration imports the `ale_py.roms.utils` of 0.8), so a short launcher imports
ale_py and then runs the script as `__main__`.

Throughput: `dqn_atari.py` prints `SPS: n` before the update of every 100th agent step once
learning has started (n is its average since the start, replay start included, so not the
figure wanted). The times at which those lines arrive, through an unbuffered pipe, time the
agent steps between the first and the last line: the same window as dqnlab's, after replay
start, at the final epsilon. Frames count 4 per agent step (its MaxAndSkipEnv), as SB3's do.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dqnlab.config import Config
from dqnlab.errors import DqnlabError

SCRIPT = Path("cleanrl/dqn_atari.py")
LOCK_FILE = Path("requirements/requirements-atari.txt")
# ale-py's wheels ship the ROMs from 0.9 on; 0.9.1 runs dqn_atari.py under the pinned
# gymnasium 0.29.1 (checked by running it, 2026-12-03).
ALE_PY_PIN = "ale-py==0.9.1"
LOCK_LINES_DROPPED = ("ale-py", "autorom", "autorom-accept-rom-license")
# What dqn_atari.py imports (tensorboard through torch.utils.tensorboard; cv2 and psutil
# through cleanrl_utils); setuptools because tensorboard 2.11 imports pkg_resources.
PACKAGES: tuple[str, ...] = ("gymnasium", "numpy", "torch", "opencv-python", "tyro")
PACKAGES += ("tensorboard", "psutil", "setuptools")
VERSIONS_REPORTED = ("gymnasium", "ale-py", "numpy", "torch", "tyro", "opencv-python")
MARKER = "dqnlab-cleanrl-venv.json"  # written last: a venv without it is not complete
SPS_PERIOD_STEPS = 100  # dqn_atari.py: `if global_step % 100 == 0: print("SPS:", ...)`
SPS_LINE = re.compile(r"^SPS: (\d+)$")
LAUNCHER_PREFIX = "dqnlab-launcher "
# Imports ale_py so that its envs are registered, reports the versions it found, then runs
# the script given as the first argument as `python SCRIPT ARGS...` would.
LAUNCHER = f"""\
import importlib.metadata as m, json, runpy, sys
import ale_py
def version(name):
    try:
        return m.version(name)
    except m.PackageNotFoundError:
        return None
print({LAUNCHER_PREFIX!r} + json.dumps({{n: version(n) for n in {VERSIONS_REPORTED!r}}}))
sys.argv = sys.argv[1:]
runpy.run_path(sys.argv[0], run_name="__main__")
"""


@dataclass(frozen=True)
class CleanRLPeer:
    """A CleanRL checkout and the interpreter of the venv that runs it."""

    checkout: Path
    python: Path
    commit: str


def prepare_cleanrl(
    checkout: Path, venv: Path | None = None, echo: Callable[[str], None] | None = None
) -> CleanRLPeer:
    """Check the checkout, and make (once) or check the venv: before anything is timed."""
    checkout = checkout.expanduser().resolve()
    if not (checkout / SCRIPT).is_file():
        raise DqnlabError(f"--cleanrl {checkout}: no {SCRIPT} there (give a CleanRL checkout)")
    if venv is None:
        venv = ensure_venv(checkout, echo or _echo_to_stderr)
    python = venv.expanduser() / "bin" / "python"
    if not python.exists():
        raise DqnlabError(
            f"--cleanrl-venv {venv}: no bin/python there (leave it out to have one made)"
        )
    return CleanRLPeer(checkout, python, _commit(checkout))


def _echo_to_stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def _commit(checkout: Path) -> str:
    """The checkout's git commit, or "unknown" for a copy without git."""
    if not (checkout / ".git").exists():  # not the commit of a repository around it
        return "unknown"
    try:
        found = subprocess.run(
            ["git", "-C", str(checkout), "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            check=False,
        )
    except OSError:
        return "unknown"
    return found.stdout.strip() if found.returncode == 0 else "unknown"


def pinned_constraints(lock_text: str) -> str:
    """CleanRL's lock as pip constraints: without the checkout itself (`-e .`), ale-py 0.8.1
    and AutoROM, which fetched 0.8's ROMs."""
    kept = []
    for line in lock_text.splitlines():
        line = line.strip()
        if not line or line.startswith(("#", "-")):
            continue
        name = re.split(r"[=<>!~;\[ ]", line, maxsplit=1)[0].lower().replace("_", "-")
        if name not in LOCK_LINES_DROPPED:
            kept.append(line)
    return "\n".join(kept) + "\n"


def base_python() -> str:
    """An interpreter the pins have wheels for (numpy 1.24.4, torch 2.4.1: Python 3.8-3.11)."""
    if (3, 8) <= sys.version_info[:2] <= (3, 11):
        return sys.executable
    for name in ("python3.11", "python3.10", "python3.9"):
        found = shutil.which(name)
        if found:
            return found
    raise DqnlabError(
        "--cleanrl: CleanRL's pins (numpy 1.24.4, torch 2.4.1) need Python 3.8-3.11 and none "
        "was found: install python3.11, or give --cleanrl-venv"
    )


def cache_dir() -> Path:
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "dqnlab"


def ensure_venv(checkout: Path, echo: Callable[[str], None]) -> Path:
    """The venv for this checkout's pins, made under the cache the first time it is needed;
    its name holds a hash of the pins, the packages and the Python version, so a checkout
    with other pins gets its own."""
    lock = checkout / LOCK_FILE
    if not lock.is_file():
        raise DqnlabError(
            f"--cleanrl {checkout}: no {LOCK_FILE} to pin the venv by (or give --cleanrl-venv)"
        )
    constraints = pinned_constraints(lock.read_text())
    python = base_python()
    version = subprocess.run(
        [python, "-c", "import sys; print(sys.version.split()[0])"],
        capture_output=True,
        text=True,
        check=False,
    ).stdout.strip()
    venv = venv_path(constraints, version)
    if (venv / MARKER).is_file():
        return venv
    shutil.rmtree(venv, ignore_errors=True)  # an earlier attempt that did not finish
    venv.mkdir(parents=True)
    echo(
        f"--cleanrl: making a venv with CleanRL's pins ({ALE_PY_PIN}) at {venv}: once, about "
        "5 GB (torch with its CUDA libraries), a few minutes"
    )
    (venv / "constraints.txt").write_text(constraints)
    venv_python = venv / "bin" / "python"
    install = [str(venv_python), "-m", "pip", "install", "--disable-pip-version-check"]
    install += ["-c", str(venv / "constraints.txt"), *PACKAGES, ALE_PY_PIN]
    for step, command in (
        ("python -m venv", [python, "-m", "venv", str(venv)]),
        ("pip install", install),
    ):
        _run_logged(command, venv / "install.log", f"making the venv at {venv}: {step}")
    frozen = subprocess.run(
        [str(venv_python), "-m", "pip", "freeze"], capture_output=True, text=True, check=False
    )
    record = {"python": version, "packages": frozen.stdout.split(), "checkout": str(checkout)}
    (venv / MARKER).write_text(json.dumps(record, indent=1))
    return venv


def venv_path(constraints: str, python_version: str) -> Path:
    """Where the venv for these pins and this Python (major.minor) is kept."""
    key = "\n".join([constraints, *PACKAGES, ALE_PY_PIN, python_version.rsplit(".", 1)[0]])
    return cache_dir() / f"cleanrl-venv-{hashlib.sha256(key.encode()).hexdigest()[:12]}"


def _run_logged(command: list[str], log: Path, what: str) -> None:
    with log.open("a") as output:
        try:
            done = subprocess.run(command, stdout=output, stderr=subprocess.STDOUT, check=False)
        except OSError as error:
            raise DqnlabError(f"--cleanrl: {what} could not start: {error}") from None
    if done.returncode != 0:
        lines = [line for line in log.read_text().splitlines() if line.strip()]
        last = lines[-1].strip() if lines else "no output"
        raise DqnlabError(
            f"--cleanrl: {what} failed (exit {done.returncode}): {last} (log: {log}; or give "
            "--cleanrl-venv)"
        )


def cleanrl_arguments(
    config: Config, steps: int, learning_starts: int, device: torch.device | str
) -> tuple[list[str], int, int]:
    """dqn_atari.py's arguments for dqnlab's training settings, and the agent steps of the
    first and last SPS lines, which bound the timed window (`steps` rounded up to 100s).

    Epsilon anneals from 1 to dqnlab's final epsilon over the replay start, as for the SB3
    peer, so the whole window runs at dqnlab's epsilon. The replay holds every transition.
    """
    if steps < 1 or learning_starts < 1:
        raise ValueError(
            f"steps and learning_starts must be at least 1: {steps}, {learning_starts}"
        )
    period = math.lcm(SPS_PERIOD_STEPS, config.update_period_steps)  # steps with an SPS line
    first = (learning_starts // period + 1) * period  # dqn_atari trains once step > starts
    last = first + math.ceil(steps / period) * period
    total = last + 1  # range(total_timesteps) ends at `last`, whose line is printed
    arguments = {
        "--env-id": f"{config.env.title().replace('_', '')}NoFrameskip-v4",
        "--seed": config.seed,
        "--total-timesteps": total,
        "--learning-starts": learning_starts,
        "--buffer-size": total,
        "--batch-size": config.batch_size,
        "--train-frequency": config.update_period_steps,
        "--target-network-frequency": config.target_update_steps,
        "--gamma": config.discount,
        "--learning-rate": config.learning_rate,
        "--start-e": config.epsilon_start,
        "--end-e": config.epsilon_end,
        "--exploration-fraction": learning_starts / total,
    }
    flags = ["--cuda" if torch.device(device).type == "cuda" else "--no-cuda"]
    flags += ["--no-track", "--no-capture-video", "--no-save-model", "--no-upload-model"]
    return [*(f"{k}={v}" for k, v in arguments.items()), *flags], first, last


def cleanrl_environment(peer: CleanRLPeer, threads: int) -> dict[str, str]:
    """This process's environment less what would change the venv's Python; the threads of
    dqnlab's run."""
    environment = {
        name: value
        for name, value in os.environ.items()
        if not name.startswith("PYTHON") and name not in ("VIRTUAL_ENV", "__PYVENV_LAUNCHER__")
    }
    environment.update(
        PYTHONPATH=str(peer.checkout),  # cleanrl_utils
        PYTHONUNBUFFERED="1",  # each SPS line arrives when printed
        PYTHONNOUSERSITE="1",
        OMP_NUM_THREADS=str(threads),
        MKL_NUM_THREADS=str(threads),
    )
    return environment


def parse_sps_lines(
    lines: list[tuple[float, str]], first: int, last: int, frames_per_step: int
) -> dict[str, Any]:
    """Frames/s between the SPS lines of agent steps `first` and `last`, from the times
    (seconds) at which each output line arrived."""
    sps = [(seconds, int(m.group(1))) for seconds, line in lines if (m := SPS_LINE.match(line))]
    expected = (last - first) // SPS_PERIOD_STEPS + 1
    if len(sps) != expected:
        raise DqnlabError(
            f"--cleanrl: {SCRIPT} printed {len(sps)} 'SPS:' lines where {expected} were "
            f"expected (one per {SPS_PERIOD_STEPS} steps from step {first} to {last})"
        )
    seconds = sps[-1][0] - sps[0][0]
    if seconds <= 0:
        raise DqnlabError(f"--cleanrl: {SCRIPT}'s SPS lines all came at the same time")
    return {
        "cleanrl_train_frames_per_second": frames_per_step * (last - first) / seconds,
        "cleanrl_steps": last - first,
        "cleanrl_reported_sps": sps[-1][1],  # its own figure: replay start included
    }


def run_cleanrl_dqn(
    peer: CleanRLPeer,
    config: Config,
    steps: int,
    learning_starts: int,
    device: torch.device | str = "cpu",
) -> dict[str, Any]:
    """Run dqn_atari.py for `learning_starts` steps and then about `steps` timed ones."""
    arguments, first, last = cleanrl_arguments(config, steps, learning_starts, device)
    command = [str(peer.python), "-c", LAUNCHER, str(peer.checkout / SCRIPT), *arguments]
    threads = torch.get_num_threads()
    load_at_start = os.getloadavg()[0]
    start = time.perf_counter()
    lines = _timed_output(command, cleanrl_environment(peer, threads), peer.python)
    versions: dict[str, str | None] = next(
        (
            json.loads(line[len(LAUNCHER_PREFIX) :])
            for _, line in lines
            if line.startswith(LAUNCHER_PREFIX)
        ),
        {},
    )
    figures = parse_sps_lines(lines, first, last, config.action_repeat_frames)
    return {
        "cleanrl_commit": peer.commit,
        **figures,
        "cleanrl_learning_starts": learning_starts,
        "cleanrl_seconds": time.perf_counter() - start,
        "cleanrl_settings": {
            "arguments": arguments,
            "python": str(peer.python),
            "versions": versions,
            "threads": threads,  # OMP_NUM_THREADS and MKL_NUM_THREADS given to it
            "load_average_1min_at_start": load_at_start,  # others' work on the machine
            "timed_window_steps": [first, last],
            # What dqn_atari.py has no argument for, as its source fixes it.
            "fixed_in_script": "Adam (eps 1e-8), MSE loss (mean), no gradient clipping, "
            "ReplayBuffer(optimize_memory_usage=True), wrappers NoopReset(30), MaxAndSkip(4), "
            "EpisodicLife, FireReset, ClipReward, Resize 84, GrayScale, FrameStack(4)",
        },
    }


def _timed_output(
    command: list[str], environment: dict[str, str], python: Path
) -> list[tuple[float, str]]:
    """Each line the command prints, with the time it arrived; a one-line error with its
    last line if it fails. It runs in a temporary folder: its TensorBoard files go to
    runs/ under the working folder."""
    lines: list[tuple[float, str]] = []
    tail: deque[str] = deque(maxlen=20)
    with tempfile.TemporaryDirectory(prefix="dqnlab-cleanrl-") as folder:
        try:
            process = subprocess.Popen(
                command, cwd=folder, env=environment, stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT, text=True,
            )  # fmt: skip
        except OSError as error:
            raise DqnlabError(f"--cleanrl-venv: {python} could not start: {error}") from None
        assert process.stdout is not None
        for line in process.stdout:
            lines.append((time.perf_counter(), line.rstrip("\n")))
            if line.strip():
                tail.append(line.strip())
        status = process.wait()
    if status != 0:
        raise DqnlabError(
            f"--cleanrl: {SCRIPT} exited with status {status}: {tail[-1] if tail else 'no output'}"
        )
    return lines


def cleanrl_figures(
    runs: list[dict[str, Any]], train_frames_per_second_runs: list[float]
) -> dict[str, Any]:
    """The rounds' CleanRL figures for the bench's table: their mean, each round's, the
    ratio of dqnlab's mean to theirs and each round's ratio (other work on the machine
    can slow one round of both alike), and the last round's settings."""
    frames_per_second = [run["cleanrl_train_frames_per_second"] for run in runs]
    figures = dict(runs[-1])
    figures["cleanrl_train_frames_per_second"] = float(np.mean(frames_per_second))
    figures["cleanrl_train_frames_per_second_runs"] = [round(f, 1) for f in frames_per_second]
    figures["train_ratio_vs_cleanrl"] = float(
        np.mean(train_frames_per_second_runs) / np.mean(frames_per_second)
    )
    figures["train_ratio_vs_cleanrl_runs"] = [
        float(f"{ours / theirs:.4g}")
        for ours, theirs in zip(train_frames_per_second_runs, frames_per_second, strict=True)
    ]
    return figures
