"""Weights & Biases (wandb_log.py), in W&B's offline mode: the history read back from the
offline transaction logs holds TensorBoard's scalars at TensorBoard's steps, each step
once across a resume; the final evaluation, its videos and the report's figures reach the
summary; without wandb, asking for it is one line."""

from __future__ import annotations

import dataclasses
import json
import shutil
import sys
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import torch

from dqnlab.cli import main
from dqnlab.config import Config, resolve_config
from dqnlab.errors import DqnlabError
from dqnlab.run import rundir
from dqnlab.run import train as train_module
from dqnlab.run.checkpoints import CheckpointStore
from dqnlab.run.logs import EPISODE_FIELDS, RunLogger, read_csv
from dqnlab.run.train import train
from dqnlab.run.wandb_log import WandbLog, add_to_summary, history_steps, transaction_records
from tests.run.test_resume import tensorboard_steps

PROGRESS_STEPS = 100  # instead of 1,000: progress scalars within a 600-step run
TIMING_TAGS = ("train/frames_per_second",)  # differ between a session and its resume


def wandb_config(**overrides: Any) -> Config:
    values = {"total_steps": 400, "replay_start_steps": 50, "eval_period_steps": 100,
              "eval_steps": 50, "checkpoint_period_steps": 50, "replay_capacity": 1000,
              "logger": "tensorboard+wandb", "wandb_project": "dqnlab-tests",
              "final_eval_episodes": 1,
              # A small network: what is logged is under test, not what is learned.
              "mlp_hidden_sizes": [16], "batch_size": 8, "update_period_steps": 4}  # fmt: skip
    return resolve_config("classic", env="CartPole-v1", **{**values, **overrides})


@pytest.fixture(scope="module")
def offline_wandb(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """W&B offline for this module: it sends nothing (no run, no error report, no
    telemetry: any address it might still use is the loopback's), and writes nothing
    outside the test's directories."""
    wandb = pytest.importorskip("wandb")
    home = tmp_path_factory.mktemp("wandb-home")
    with pytest.MonkeyPatch.context() as patch:
        for name, value in {
            "WANDB_MODE": "offline",
            "WANDB_BASE_URL": "http://127.0.0.1:9",
            "WANDB_ERROR_REPORTING": "false",  # also turns wandb-core's telemetry off
            "WANDB_SILENT": "true",
            "WANDB_CONSOLE": "off",
            "WANDB_DISABLE_GIT": "true",
            "WANDB_DISABLE_CODE": "true",
            "WANDB_X_DISABLE_STATS": "true",  # no system-metrics process
            "WANDB_CONFIG_DIR": str(home / "config"),
            "WANDB_CACHE_DIR": str(home / "cache"),
            "WANDB_DATA_DIR": str(home / "data"),
            "WANDB_ARTIFACT_DIR": str(home / "artifacts"),
        }.items():
            patch.setenv(name, value)
        for name in ("WANDB_DIR", "WANDB_PROJECT", "WANDB_ENTITY", "WANDB_RUN_ID", "WANDB_RESUME"):
            patch.delenv(name, raising=False)
        patch.setattr(train_module, "PROGRESS_PERIOD_STEPS", PROGRESS_STEPS)
        yield
        wandb.teardown()  # W&B's service process ends with this module


def sessions(run_dir: Path) -> list[dict[str, Any]]:
    """Each offline session of the run's W&B run, in the order they started: its run id,
    history ({step: {key: value}}), configuration and summary updates."""
    found = []
    for path in rundir.wandb_dir(run_dir).glob("offline-run-*/run-*.wandb"):
        session: dict[str, Any] = {"history": {}, "config": {}, "summary": {}}
        for record in transaction_records(path):
            kind = record.WhichOneof("record_type")
            if kind == "run":
                session["id"], session["start"] = record.run.run_id, record.run.start_time
                session["config"].update(_items(record.run.config.update))
            elif kind == "config":
                session["config"].update(_items(record.config.update))
            elif kind == "history":
                row = _items(record.history.item)
                assert record.history.step.num not in session["history"]  # one row per step
                session["history"][record.history.step.num] = row
            elif kind == "summary":
                session["summary"].update(_items(record.summary.update))
        found.append(session)
    return sorted(found, key=lambda session: session["start"].ToNanoseconds())


def _items(items: Any) -> dict[str, Any]:
    """Protobuf items (of a history row, a config or summary update) as a dict."""
    values = {}
    for item in items:
        key = item.key or "/".join(item.nested_key)
        if not key.startswith("_"):  # W&B's own: _step, _runtime, _timestamp
            values[key] = json.loads(item.value_json)
    return values


def cut_after_step(path: Path, step: int) -> int:
    """Cut a transaction log right after its first history row later than `step`, as a
    process killed before W&B wrote the rest leaves it; the row's step."""
    data = path.read_bytes()
    probe = path.with_name("probe.wandb")
    low, high = 7, len(data)  # the shortest prefix whose last row is later than `step`
    while low < high:
        middle = (low + high) // 2
        probe.write_bytes(data[:middle])
        if max(history_steps(probe, path.stem.removeprefix("run-")), default=0) > step:
            high = middle
        else:
            low = middle + 1
    probe.unlink()
    path.write_bytes(data[:low])
    return max(history_steps(path, path.stem.removeprefix("run-")))


@pytest.fixture(scope="module")
def resumed_run(offline_wandb: None, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """A run to step 400 that a kill stops at a moment W&B holds a step after its newest
    checkpoint but not all it was sent, resumed to 600. The kill is made up afterwards:
    the step-400 checkpoint removed (the resume starts from step 350) and W&B's log cut
    after the first step past 370 (the steps after it never reached the disk)."""
    run = tmp_path_factory.mktemp("wandb") / "run"
    rundir.prepare_run_dir(run, force=False)
    cpu = torch.device("cpu")
    train(wandb_config(), run, cpu, progress=False)
    store = CheckpointStore(run)
    assert store.steps()[-2:] == [350, 400]
    shutil.rmtree(run / rundir.CHECKPOINTS_DIR / "step-000000400")
    (first,) = sessions(run)
    log = next(rundir.wandb_dir(run).glob(f"offline-run-*/run-{first['id']}.wandb"))
    kept_step = cut_after_step(log, 370)
    # As `dqnlab resume --steps 600` extends it: the saved settings with a new budget.
    longer = dataclasses.replace(wandb_config(), total_steps=600)
    train(longer, run, cpu, progress=False, resume=True)
    return {"run": run, "kept_step": kept_step, "sent_step": max(first["history"])}


def test_a_resumed_run_continues_its_wandb_run_with_every_step_once(resumed_run) -> None:
    run, kept_step = resumed_run["run"], resumed_run["kept_step"]
    assert 370 < kept_step < resumed_run["sent_step"] == 400
    first, resumed = sessions(run)[:2]
    assert first["id"] == resumed["id"] == json.loads(rundir.wandb_run_path(run).read_text())["id"]
    # Each step once: the first session's up to the cut, the resumed one's after it (the
    # resume replays steps 351..400 and sends only those W&B lost).
    assert max(first["history"]) == kept_step < min(resumed["history"])
    history = {**first["history"], **resumed["history"]}
    assert len(history) == len(first["history"]) + len(resumed["history"])
    # TensorBoard's scalars at TensorBoard's steps (its events of the steps the resume
    # replays are purged and written again).
    logged = tensorboard_steps(run)
    wandb_steps = {tag: sorted(s for s, row in history.items() if tag in row) for tag in logged}
    assert wandb_steps == logged
    assert {"train/episode_score", "eval/mean_score", "eval/episodes", "train/loss"} <= set(logged)
    # The steps of the CSV files and of the progress scalars, nothing else.
    csv_steps = {int(row["step"]) for name in ("episodes.csv", "evaluations.csv")
                 for row in read_csv(run / name)}  # fmt: skip
    progress = set(range(PROGRESS_STEPS, 601, PROGRESS_STEPS))
    assert set(history) == csv_steps | progress
    # The same values: those the first session sent are those its resume computes again.
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(rundir.tensorboard_dir(run)))
    events.Reload()
    for tag in set(logged) - set(TIMING_TAGS):
        for event in events.Scalars(tag):
            assert history[event.step][tag] == pytest.approx(event.value, rel=1e-6), tag
    # The resolved configuration, with the budget of the resume.
    assert first["config"]["total_steps"] == 400
    assert resumed["config"]["total_steps"] == 600
    assert resumed["config"]["logger"] == "tensorboard+wandb"


def test_steps_wandb_lacks_before_the_checkpoint_come_from_tensorboard(
    offline_wandb, tmp_path: Path
) -> None:
    """W&B turned on at a resume (or its log of the killed process lost): the steps up to
    the checkpoint from TensorBoard, those after it live, each once."""
    run = tmp_path / "run"
    run.mkdir()
    rundir.write_run_config(run, wandb_config())
    logger = RunLogger(run)  # TensorBoard alone
    for step in (10, 20, 30, 40):
        logger.scalars(step, {"train/loss": step / 8})
    logger.episode(dict.fromkeys(EPISODE_FIELDS, 0) | {"step": 25, "score": 9.0})
    logger.close()
    wandb_log = WandbLog(run, wandb_config(), resume_step=30)  # resumed from step 30
    logger = RunLogger(run, resume_step=30, wandb_log=wandb_log)
    for step in (40, 50):
        logger.scalars(step, {"train/loss": step / 4, "train/epsilon": 0.5})
    logger.close()
    (session,) = sessions(run)
    assert session["history"] == {
        10: {"train/loss": 1.25}, 20: {"train/loss": 2.5}, 25: {"train/episode_score": 9.0},
        30: {"train/loss": 3.75}, 40: {"train/loss": 10.0, "train/epsilon": 0.5},
        50: {"train/loss": 12.5, "train/epsilon": 0.5},
    }  # fmt: skip


def test_the_final_evaluation_videos_and_report_figures_reach_the_summary(
    resumed_run, tmp_path: Path, capsys
) -> None:
    from dqnlab.analysis.report import write_report
    from dqnlab.cli.results import evaluate

    run = resumed_run["run"]
    evaluate(run, episodes=1, device="cpu", video=tmp_path / "videos", video_format="gif")
    assert "sent to the run's W&B summary" in capsys.readouterr().out
    record = rundir.load_final_evaluation(run)
    write_report([run], tmp_path / "report", inspect_frames=0)
    evaluated, reported = sessions(run)[-2:]
    assert evaluated["history"] == reported["history"] == {}  # no step after training
    assert evaluated["summary"]["final_evaluation/mean"] == record["mean"]
    assert evaluated["summary"]["final_evaluation/checkpoint_step"] == record["checkpoint_step"]
    assert evaluated["summary"]["videos/best/game01"]["_type"] == "video-file"
    assert reported["summary"]["report/learning_curves"]["_type"] == "image-file"
    assert reported["summary"]["final_evaluation/episodes"] == 1
    sent = [path for path in rundir.wandb_dir(run).glob("offline-run-*/files/media/**/*")]
    assert sorted(path.suffix for path in sent if path.is_file()) == [".gif", ".png"]


def test_without_wandb_asking_for_it_is_one_line(tmp_path: Path, monkeypatch, capsys) -> None:
    monkeypatch.setitem(sys.modules, "wandb", None)  # `import wandb` fails
    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)  # main() sets it
    monkeypatch.setattr(sys, "argv", [
        "dqnlab", "train", "--env", "CartPole-v1", "--steps", "10", "--no-progress",
        "--device", "cpu", "--set", "logger=tensorboard+wandb", "--run-dir", str(tmp_path / "run"),
    ])  # fmt: skip
    with pytest.raises(SystemExit) as stopped:
        main()
    assert stopped.value.code == 2
    error = capsys.readouterr().err
    assert error == (
        "dqnlab: error: logger = 'tensorboard+wandb' needs the wandb package, which is not "
        "installed: pip install 'dqnlab[wandb]'\n"
    )
    # A run trained with W&B, evaluated where wandb is missing: a warning, nothing sent.
    run = tmp_path / "trained-elsewhere"
    run.mkdir()
    rundir.write_run_config(run, wandb_config())
    with pytest.warns(UserWarning, match=r"not sent to W&B: .*pip install 'dqnlab\[wandb\]'"):
        assert not add_to_summary(run, {"final_evaluation/mean": 1.0})
    with pytest.raises(DqnlabError, match="needs the wandb package"):
        train(wandb_config(), run, torch.device("cpu"), progress=False)
