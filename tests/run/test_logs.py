"""What a run logs: CSV rows of games and evaluations, cut back to a checkpoint on resume."""

from __future__ import annotations

from pathlib import Path

from dqnlab.run import rundir
from dqnlab.run.logs import EPISODE_FIELDS, EVALUATION_FIELDS, RunLogger, read_csv


def _episode(step: int) -> dict:
    return {"step": step, "frames": 4 * step, "episode": step // 10, "score": 1.0,
            "steps": 10, "epsilon": 1.0, "wall_seconds": 0.5}  # fmt: skip


def _evaluation(step: int) -> dict:
    return dict.fromkeys(EVALUATION_FIELDS, 0) | {"step": step, "mean": 2.5}


def test_rows_read_back_with_their_headers(tmp_path: Path) -> None:
    logger = RunLogger(tmp_path, tensorboard=False)
    logger.episode(_episode(10))
    logger.evaluation(_evaluation(100))
    # An evaluation reaches the file at once; episodes at the next flush.
    assert read_csv(rundir.evaluations_path(tmp_path))[0]["mean"] == "2.5"
    logger.close()
    rows = read_csv(rundir.episodes_path(tmp_path))
    assert list(rows[0]) == list(EPISODE_FIELDS) and rows[0]["step"] == "10"


def test_a_resume_drops_what_came_after_its_checkpoint(tmp_path: Path) -> None:
    logger = RunLogger(tmp_path, tensorboard=False)
    for step in (10, 20, 30, 40):
        logger.episode(_episode(step))
    logger.close()
    path = rundir.episodes_path(tmp_path)
    with path.open("a") as handle:
        handle.write("50,200,5")  # a row torn by a killed process
    logger = RunLogger(tmp_path, tensorboard=False, resume_step=25)
    logger.episode(_episode(30))
    logger.close()
    assert [row["step"] for row in read_csv(path)] == ["10", "20", "30"]
    assert path.read_text().count("step,frames") == 1


def test_tensorboard_events_are_written(tmp_path: Path) -> None:
    logger = RunLogger(tmp_path)
    logger.scalars(5, {"train/loss": 0.5})
    logger.close()
    assert list(rundir.tensorboard_dir(tmp_path).glob("events.out.tfevents.*"))


def test_a_live_run_is_readable_within_half_a_minute(tmp_path: Path, monkeypatch) -> None:
    from dqnlab.run import logs

    clock = [1000.0]
    monkeypatch.setattr(logs.time, "monotonic", lambda: clock[0])
    logger = RunLogger(tmp_path, tensorboard=False)
    path = rundir.episodes_path(tmp_path)
    assert path.read_bytes() == (",".join(EPISODE_FIELDS) + "\r\n").encode()  # header at once
    logger.episode(_episode(10))
    clock[0] += logs.FRESH_SECONDS - 1
    logger.keep_fresh()
    assert read_csv(path) == []  # still in the write buffer: no write per row
    clock[0] += 1
    logger.keep_fresh()
    assert [row["step"] for row in read_csv(path)] == ["10"]
    logger.episode(_episode(20))
    logger.keep_fresh(at_once=True)  # before an evaluation
    assert [row["step"] for row in read_csv(path)] == ["10", "20"]
    logger.close()


def test_an_older_runs_evaluations_get_the_new_columns_on_resume(tmp_path: Path) -> None:
    old_fields = EVALUATION_FIELDS[: EVALUATION_FIELDS.index("heldout_max_q")]
    path = rundir.evaluations_path(tmp_path)
    path.write_text(
        ",".join(old_fields) + "\n" + ",".join(["100"] + ["1"] * (len(old_fields) - 1)) + "\n"
    )
    logger = RunLogger(tmp_path, tensorboard=False, resume_step=100)
    logger.evaluation(_evaluation(200) | {"heldout_max_q": 0.25, "heldout_td_error": 0.5})
    logger.close()
    old, new = read_csv(path)
    assert list(old) == list(EVALUATION_FIELDS) and old["step"] == "100"
    assert old["heldout_max_q"] is None  # the older row leaves them empty
    assert new["step"] == "200" and new["heldout_max_q"] == "0.25"
