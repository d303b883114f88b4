"""What does Ray add to a sweep's runs, and how soon does a run train again after its node is
lost? Answered once (2026-12-02: about a second per run, and 14-15 s from a lost node to
training again); the figures are in docs/benchmark.md, "What does Ray add to a sweep?"
(#what-ray-costs-a-sweep). Run:
`python scripts/sweep_overhead.py --runs 4 --repeats 2`.

Three measurements, each on a Ray cluster on 127.0.0.1 started here and shut down after:

    start-up     the loopback cluster of `--address local` started and joined
                 (`cluster.connect`), then a trivial task's round trip (its worker started)
    per run      the same N tiny CartPole runs trained by hand (`dqnlab train` subprocesses,
                 as many at once as the cluster places, with the threads a sweep gives
                 each) and by `run_sweep_on_ray` on the cluster just started, alternately
                 R times, each time in new run directories (a sweep skips finished runs)
    node loss    one run on a head that only schedules and two nodes of one CPU: once the
                 run has checkpointed, its node is removed, and timed from the removal:
                 the lost run's process gone, the retry's start (attempts.jsonl), and the
                 retry's first checkpoint past the step it resumed from (last.pt's step:
                 the finest a run's files show, episodes.csv reaches the disk at checkpoints)

The lease rule that let the retry take the run (`lease.LeaseRecord.takeable`):
"released" (the lost run's process stopped after a checkpoint and released it),
"owner_gone" (its process died on this machine without releasing it: taken at once) or
"expiry" (LEASE_SECONDS + TAKEOVER_GRACE_SECONDS after its last renewal).
"""

from __future__ import annotations

import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor, wait
from pathlib import Path
from typing import Annotated, Any

import psutil
import typer

from dqnlab import __version__
from dqnlab.analysis.status import read_attempts
from dqnlab.cli.bench import JsonPath, report
from dqnlab.cli.common import run_command
from dqnlab.config import config_to_toml
from dqnlab.errors import DqnlabError
from dqnlab.run import rundir
from dqnlab.run.lease import TAKEOVER_GRACE_SECONDS, LeaseRecord, read_lease
from dqnlab.sweeps.cluster import (
    connect,
    connect_to_cluster,
    import_ray,
    node_resources,
    start_loopback_cluster,
)
from dqnlab.sweeps.driver import run_sweep_on_ray
from dqnlab.sweeps.grid import PlannedRun, Sweep, plan_grid
from dqnlab.sweeps.resources import RunResources, check_resources, sweep_resources

ENV = "CartPole-v1"
# tests/sweeps/test_sweep_faults.py's settings: a run of 600 steps takes about 15 s here,
# most of it the process's start-up and the final evaluation.
RUN_SETTINGS = {
    "replay_start_steps": 200, "replay_capacity": 2000, "eval_period_steps": 500,
    "eval_steps": 200, "checkpoint_period_steps": 100, "final_eval_episodes": 2,
}  # fmt: skip
RUN_STEPS = 600
NODE_LOSS_STEPS = 1500  # outlasts the loss, the retry's start-up and its first checkpoint
CPUS_PER_RUN = 1.0
POLL_SECONDS = 0.1  # the resolution of the node-loss times
WAIT_SECONDS = 600.0  # a measurement waiting longer than this has hung


def run_sweep_benchmark(
    directory: Path,
    runs: int = 4,
    repeats: int = 2,
    run_steps: int = RUN_STEPS,
    node_loss_steps: int = NODE_LOSS_STEPS,
    echo: Callable[[str], Any] = print,
) -> dict[str, Any]:
    """All figures; the runs go into `directory` (new run directories for every repeat)."""
    ray = import_ray()
    if ray.is_initialized():
        raise DqnlabError("the sweep benchmark starts its own Ray clusters: run it unconnected")
    if runs <= 0 or repeats <= 0:
        raise DqnlabError(f"--runs {runs} and --repeats {repeats} must be positive")
    figures: dict[str, Any] = {
        "env": ENV,
        "cpu_count": psutil.cpu_count(),
        "dqnlab": __version__,
        "ray": ray.__version__,
        "python": platform.python_version(),
        "load_average_1min": os.getloadavg()[0],
        "runs": runs,
        "run_steps": run_steps,
        "cpus_per_run": CPUS_PER_RUN,
    }
    figures.update(measure_overhead(directory, runs, repeats, run_steps, echo))
    figures.update(measure_node_loss(directory / "node-loss", node_loss_steps, echo))
    echo(f"dqnlab: node lost: its run started again after "
         f"{figures['node_loss_to_retry_start_seconds']:.1f} s, trained past its checkpoint "
         f"after {figures['node_loss_to_training_seconds']:.1f} s")  # fmt: skip
    return figures


def measure_overhead(
    directory: Path, runs: int, repeats: int, run_steps: int, echo: Callable[[str], Any]
) -> dict[str, Any]:
    """Ray's start-up on a loopback cluster, then the same runs trained by hand and by the
    sweep, alternately, `repeats` times (`overhead_figures`)."""
    ray = import_ray()
    figures: dict[str, Any] = {}
    by_hand: list[tuple[float, list[float]]] = []
    on_ray: list[tuple[float, list[float]]] = []
    start = time.perf_counter()
    connection = connect("local")
    try:
        figures["ray_start_seconds"] = time.perf_counter() - start

        # Defined here: Ray sends a local function itself, a module's by name, which a
        # worker may not import from a script (tests load this as scripts.sweep_overhead).
        def nothing() -> None:
            return None

        start = time.perf_counter()
        ray.get(ray.remote(nothing).remote())
        figures["ray_first_task_seconds"] = time.perf_counter() - start
        echo(f"dqnlab: Ray started in {figures['ray_start_seconds']:.1f} s, first task "
             f"{figures['ray_first_task_seconds']:.1f} s")  # fmt: skip
        plans = [
            (plan_runs(directory / f"by-hand-{repeat}", runs, run_steps),
             plan_runs(directory / f"sweep-{repeat}", runs, run_steps))
            for repeat in range(1, repeats + 1)
        ]  # fmt: skip
        resources = sweep_resources(plans[0][1], CPUS_PER_RUN, 0)
        nodes = node_resources()
        check_resources(resources, nodes)
        at_once = min(runs, runs_at_once(resources, nodes))
        figures["runs_at_once"] = at_once
        threads = max(1, int(resources.cpus))  # as run_sweep_on_ray gives each run
        for repeat, (by_hand_plan, sweep_plan) in enumerate(plans, 1):
            by_hand.append(train_by_hand(by_hand_plan, at_once, threads))
            on_ray.append(train_on_ray(sweep_plan, resources))
            echo(f"dqnlab: repeat {repeat}/{repeats}: {runs} runs by hand in "
                 f"{by_hand[-1][0]:.1f} s, by the sweep in {on_ray[-1][0]:.1f} s")  # fmt: skip
    finally:
        connection.close()
    start_up = figures["ray_start_seconds"] + figures["ray_first_task_seconds"]
    figures.update(overhead_figures(by_hand, on_ray, runs, start_up))
    return figures


def plan_runs(sweep_dir: Path, runs: int, steps: int) -> Sweep:
    """`runs` seeds of the tiny CartPole run, as `dqnlab sweep --seeds RUNS` plans them."""
    return plan_grid(
        [ENV], [], preset=None, overrides=RUN_SETTINGS, seeds=runs, first_seed=0, steps=steps,
        sweep_dir=sweep_dir,
    )  # fmt: skip


def runs_at_once(resources: RunResources, nodes: Sequence[dict[str, float]]) -> int:
    """How many runs asking for `resources` the nodes hold side by side."""
    held = 0
    for node in nodes:
        fits = [node.get("CPU", 0) // resources.cpus]
        if resources.gpus > 0:
            fits.append(node.get("GPU", 0) // resources.gpus)
        if resources.memory_bytes > 0:
            fits.append(node.get("memory", 0) // resources.memory_bytes)
        held += int(min(fits))
    return held


def overhead_figures(
    by_hand: Sequence[tuple[float, Sequence[float]]],
    on_ray: Sequence[tuple[float, Sequence[float]]],
    runs: int,
    start_up_seconds: float,
) -> dict[str, Any]:
    """Walls and what the sweep adds per run, from (wall seconds, each run's seconds) of
    every repeat: (sweep wall - by-hand wall) / runs, each repeat and their mean, and the
    mean with Ray's start-up (cluster and first task) shared among the runs."""
    hand_walls, ray_walls = [wall for wall, _ in by_hand], [wall for wall, _ in on_ray]
    per_run = [(ray - hand) / runs for hand, ray in zip(hand_walls, ray_walls, strict=True)]
    overhead = statistics.mean(per_run)
    return {
        "by_hand_seconds": statistics.mean(hand_walls),
        "by_hand_seconds_runs": [round(wall, 2) for wall in hand_walls],
        "sweep_seconds": statistics.mean(ray_walls),
        "sweep_seconds_runs": [round(wall, 2) for wall in ray_walls],
        "sweep_to_by_hand_ratio": statistics.mean(ray_walls) / statistics.mean(hand_walls),
        "overhead_per_run_seconds": overhead,
        "overhead_per_run_seconds_runs": [round(seconds, 2) for seconds in per_run],
        "overhead_per_run_with_start_up_seconds": overhead + start_up_seconds / runs,
        # Each run's process alone, from its start to its exit: Ray's own processes share
        # the cores with it, the scheduling gaps between runs are not in it.
        "by_hand_run_seconds": statistics.mean(s for _, seconds in by_hand for s in seconds),
        "sweep_run_seconds": statistics.mean(s for _, seconds in on_ray for s in seconds),
    }


# Per run -------------------------------------------------------------------------------


def train_by_hand(sweep: Sweep, at_once: int, threads: int) -> tuple[float, list[float]]:
    """Wall seconds of training every run of `sweep` with `dqnlab train`, `at_once` at a
    time, each with `threads` threads as a sweep gives it; and each run's seconds."""
    logs = rundir.sweep_logs_dir(sweep.directory)
    logs.mkdir(parents=True, exist_ok=True)
    environment = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}
    waiting = list(sweep.runs)
    running: dict[subprocess.Popen[bytes], tuple[PlannedRun, float]] = {}
    run_seconds = []
    start = time.perf_counter()
    try:
        while waiting or running:
            while waiting and len(running) < at_once:
                run = waiting.pop(0)
                process = _start_train(run, logs, environment)
                running[process] = (run, time.perf_counter())
            for process in [process for process in running if process.poll() is not None]:
                run, started = running.pop(process)
                run_seconds.append(time.perf_counter() - started)
                if process.returncode != 0:
                    raise DqnlabError(
                        f"{run.name}: dqnlab train exited with status {process.returncode}; "
                        f"see {run.log}"
                    )
            time.sleep(POLL_SECONDS / 10)
    finally:
        for process in running:
            process.terminate()
            process.wait()
    return time.perf_counter() - start, run_seconds


def _start_train(
    run: PlannedRun, logs: Path, environment: dict[str, str]
) -> subprocess.Popen[bytes]:
    """`dqnlab train` of the run's whole configuration, as a sweep's task starts it."""
    config_path = logs / f"{run.name}.toml"
    config_path.write_text(config_to_toml(run.config))
    run.log = logs / f"{run.name}.log"
    with run.log.open("wb") as log:
        return subprocess.Popen(
            [sys.executable, "-m", "dqnlab", "train", "--env", run.config.env,
             "--preset", str(config_path), "--run-dir", str(run.run_dir), "--device", "cpu",
             "--no-progress"],
            stdout=log, stderr=subprocess.STDOUT, env=environment,
        )  # fmt: skip


def train_on_ray(sweep: Sweep, resources: RunResources) -> tuple[float, list[float]]:
    """Wall seconds of `run_sweep_on_ray` training every run (connected already), and
    each run's seconds (its process's, as the task measured them)."""
    lines: list[str] = []
    start = time.perf_counter()
    run_sweep_on_ray(sweep, resources, device="cpu", echo=lines.append)
    wall = time.perf_counter() - start
    _check_trained(sweep, lines)
    return wall, [run.seconds for run in sweep.runs]


def _check_trained(sweep: Sweep, lines: list[str]) -> None:
    unfinished = [run.name for run in sweep.runs if run.status != "ok"]
    if unfinished:
        raise DqnlabError(
            f"the sweep did not train {', '.join(unfinished)}:\n  " + "\n  ".join(lines[-8:])
        )


# Node loss -----------------------------------------------------------------------------


def measure_node_loss(
    sweep_dir: Path, steps: int, echo: Callable[[str], Any] = print
) -> dict[str, Any]:
    """One run on a head of 0 CPUs and two nodes of one CPU: its node removed once the run
    has checkpointed, then the times from the removal (module docstring)."""
    sweep = plan_runs(sweep_dir, 1, steps)
    run = sweep.runs[0]
    resources = sweep_resources(sweep, CPUS_PER_RUN, 0)
    node = {"num_cpus": CPUS_PER_RUN}
    lines: list[str] = []
    driver = ThreadPoolExecutor(max_workers=1)
    cluster = start_loopback_cluster(0, [node, node])
    try:
        connect_to_cluster(cluster)
        sweeping = driver.submit(
            run_sweep_on_ray, sweep, resources, device="cpu", echo=lines.append
        )
        try:
            figures = _lose_the_node(cluster, run, sweeping, lines, echo)
        finally:
            wait([sweeping], timeout=WAIT_SECONDS)  # Ray shut down only once the driver is done
        sweeping.result()
    finally:
        driver.shutdown(wait=False)
        import_ray().shutdown()
        cluster.shutdown()
    _check_trained(sweep, lines)
    figures["node_loss_final_step"] = _last_step(run.run_dir)
    figures["node_loss_attempts"] = len(_starts(run.run_dir))
    return figures


def _lose_the_node(
    cluster: Any,
    run: PlannedRun,
    sweeping: Future[Sweep],
    lines: list[str],
    echo: Callable[[str], Any],
) -> dict[str, Any]:
    """Remove the node of the run's attempt once it has checkpointed; follow the retry."""
    checkpoint_steps = run.config.checkpoint_period_steps
    _wait_until(lambda: (_last_step(run.run_dir) or 0) >= checkpoint_steps,
                "the run's first checkpoint", sweeping, lines)  # fmt: skip
    lost_attempt = _starts(run.run_dir)[-1]
    lost = next(node for node in cluster.worker_nodes if node.node_id == lost_attempt["node_id"])
    held = read_lease(run.run_dir)  # the lost run's, before anything frees it
    echo(f"dqnlab: removing the node of {run.name} at step {_last_step(run.run_dir)} "
         "(Ray reports its raylet terminated: that is the measurement)")  # fmt: skip
    watch = NodeLossWatch(run, lost_attempt)
    cluster.remove_node(lost, allow_graceful=False)
    _wait_until(watch.observe, "the lost node's run to train again", sweeping, lines)
    return watch.figures(held)


class NodeLossWatch:
    """What follows a node's loss, each when a poll first sees it: the lost run's process
    gone, the retry's start, the retry's first checkpoint past the step it resumed from."""

    EVENTS = ("exit", "retry", "training")

    def __init__(self, run: PlannedRun, lost_attempt: dict[str, Any]) -> None:
        self.run = run
        self.pid, self.node_id = lost_attempt["pid"], lost_attempt["node_id"]
        self.lost_at = time.time()
        self.times: dict[str, float] = {}
        self.resumed_step: int | None = None
        self.seen_step: int | None = None
        self.released = False

    def observe(self) -> bool:
        """One poll; True once every event has been seen."""
        now, run_dir = time.time(), self.run.run_dir
        if "exit" not in self.times and not _alive(self.pid):
            self.times["exit"] = now
            # The newest complete checkpoint, which the retry resumes from: a checkpoint
            # the process wrote on its way out, or the last periodic one.
            self.resumed_step = _last_step(run_dir) or 0
            lease = read_lease(run_dir)
            self.released = lease is not None and lease.pid == self.pid and lease.released
            if self.resumed_step >= self.run.config.total_steps:
                raise DqnlabError(
                    f"the lost node's run trained on to its end (step {self.resumed_step}): "
                    "its process did not stop when its worker died"
                )
        starts = _starts(run_dir)
        if "retry" not in self.times and len(starts) > 1:
            if starts[-1]["node_id"] == self.node_id:
                raise DqnlabError("the run was retried on the node that was removed")
            self.times["retry"] = starts[-1]["time"]  # when the task started its process
        if "retry" in self.times and self.resumed_step is not None:
            step = _last_step(run_dir) or 0
            if "training" not in self.times and step > self.resumed_step:
                self.times["training"], self.seen_step = now, step
        return all(event in self.times for event in self.EVENTS)

    def figures(self, held: LeaseRecord | None) -> dict[str, Any]:
        """The times from the loss, and the lease rule that let the retry in (`held`: the
        lost process's lease, read before the loss)."""
        rule = "released" if self.released else "expiry"
        if not self.released and held is not None:
            before_expiry = self.times["retry"] < held.expires_at + TAKEOVER_GRACE_SECONDS
            rule = "owner_gone" if before_expiry else "expiry"
        seconds = {event: self.times[event] - self.lost_at for event in self.EVENTS}
        return {
            "node_loss_total_steps": self.run.config.total_steps,
            "node_loss_to_lost_process_exit_seconds": seconds["exit"],
            "node_loss_to_retry_start_seconds": seconds["retry"],
            "node_loss_to_training_seconds": seconds["training"],
            "node_loss_lease_rule": rule,
            "node_loss_resumed_step": self.resumed_step,
            # The first last.pt past it: training resumed up to a checkpoint period (and a
            # checkpoint's writing) before it was seen.
            "node_loss_step_seen": self.seen_step,
            "node_loss_checkpoint_period_steps": self.run.config.checkpoint_period_steps,
        }


def _starts(run_dir: Path) -> list[dict[str, Any]]:
    return [event for event in read_attempts(run_dir) if event.get("event") == "start"]


def _last_step(run_dir: Path) -> int | None:
    return rundir.network_step(run_dir, "last")


def _alive(pid: int) -> bool:
    try:
        return psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


def _wait_until(
    condition: Callable[[], bool], what: str, sweeping: Future[Sweep], lines: list[str]
) -> None:
    """Poll `condition` until it holds; an error if the sweep ended first or it took
    WAIT_SECONDS."""
    deadline = time.monotonic() + WAIT_SECONDS
    while not condition():
        if sweeping.done():
            sweeping.result()  # its exception, if it raised one
            raise DqnlabError(f"the sweep ended before {what}: " + " | ".join(lines[-8:]))
        if time.monotonic() >= deadline:
            raise DqnlabError(f"waited {WAIT_SECONDS:.0f} s for {what}: " + " | ".join(lines[-8:]))
        time.sleep(POLL_SECONDS)


app = typer.Typer(add_completion=False, pretty_exceptions_enable=False)


@app.command()
def main(
    runs: Annotated[
        int, typer.Option(help="Tiny CartPole runs trained each way in each repeat")
    ] = 4,
    repeats: Annotated[
        int, typer.Option(help="Times the runs are trained by hand and by the sweep, in turn")
    ] = 2,
    json_path: JsonPath = None,
) -> None:
    """What Ray adds to a sweep (its start-up, and per run against the same runs trained
    by hand), and the time from a lost node to its run training again, on loopback
    clusters of this machine."""
    with tempfile.TemporaryDirectory(prefix="dqnlab-sweep-bench-") as directory:
        figures = run_sweep_benchmark(
            Path(directory), runs, repeats, echo=lambda line: typer.echo(line, err=True)
        )
    report(figures, json_path)


if __name__ == "__main__":
    run_command(app)
