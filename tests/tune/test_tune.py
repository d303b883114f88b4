"""Tunes: pruning from fake evaluations, tiny real CartPole studies end to end, a killed
tune carried on with no trial run twice and none lost, best.toml trained, bad input
refused in one line with nothing written."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

optuna = pytest.importorskip(
    "optuna", reason="dqnlab tune needs the extra: pip install -e '.[tune]'"
)
from optuna.storages.journal import JournalFileBackend, JournalStorage  # noqa: E402
from optuna.trial import TrialState  # noqa: E402

from dqnlab.cli import tune as cli_tune  # noqa: E402
from dqnlab.config import resolve_config  # noqa: E402
from dqnlab.errors import DqnlabError  # noqa: E402
from dqnlab.run.rundir import prepare_run_dir  # noqa: E402
from dqnlab.run.train import STOPPED_BY_HOOK, TrainResult  # noqa: E402
from dqnlab.run.train import train as real_train  # noqa: E402
from dqnlab.tune import trials as trials_module  # noqa: E402
from dqnlab.tune.driver import tune  # noqa: E402
from dqnlab.tune.space import DEFAULT_SPACE, suggest  # noqa: E402
from dqnlab.tune.study import (  # noqa: E402
    STUDY_NAME,
    TunePlan,
    check_study_dir,
    open_study,
    trial_run_dir,
)
from dqnlab.tune.workers import shares  # noqa: E402
from tests.helpers import dqnlab_main  # noqa: E402

CPU = torch.device("cpu")
# Two evaluations of 50 steps in a budget of 300: a trial takes about a second.
TINY = TunePlan(
    env="CartPole-v1",
    preset="classic",
    steps=300,
    space=DEFAULT_SPACE,
    fixed={"eval_steps": 50, "heldout_transitions": 50},
    evaluations=2,
)


def _fake_train(scores: dict[int, list[float]], seen: list[tuple[int, int]]):
    """A train() that reports trial k's `scores[k]` at steps 100, 200... and stops when
    told to, as the training loop does."""

    def train(config, run_dir, device, progress, tensorboard, resume, on_evaluation):
        number = int(run_dir.name.split("-")[1])
        evaluations = []
        for index, mean in enumerate(scores[number]):
            evaluations.append(((index + 1) * 100, mean))
            seen.append((number, (index + 1) * 100))
            if on_evaluation((index + 1) * 100, mean):
                return TrainResult(
                    evaluations[-1][0],
                    0,
                    1.0,
                    0.0,
                    max(scores[number]),
                    evaluations,
                    0,
                    interrupted=STOPPED_BY_HOOK,
                )
        return TrainResult(300, 0, 1.0, 0.0, max(scores[number]), evaluations, 0)

    return train


def test_a_trial_below_the_median_is_pruned_at_its_first_evaluation(
    tmp_path: Path, monkeypatch
) -> None:
    seen: list[tuple[int, int]] = []
    scores = {0: [10.0, 20.0, 30.0], 1: [12.0, 22.0, 32.0], 2: [1.0, 50.0, 60.0]}
    monkeypatch.setattr(trials_module, "train", _fake_train(scores, seen))
    study = optuna.create_study(
        direction="maximize", pruner=optuna.pruners.MedianPruner(n_startup_trials=0)
    )
    states = [trials_module.run_trial(study, study.ask(), tmp_path, TINY, CPU) for _ in range(3)]
    assert states == [TrialState.COMPLETE, TrialState.COMPLETE, TrialState.PRUNED]
    assert [step for number, step in seen if number == 2] == [100]  # stopped there
    assert study.trials[2].value == 1.0 and study.best_trial.value == 32.0  # the last mean


@pytest.mark.parametrize(("objective", "value"), [("best", 40.0), ("last", 30.0)])
def test_a_runs_value_is_its_best_or_its_last_evaluation(
    tmp_path: Path, monkeypatch, objective: str, value: float
) -> None:
    monkeypatch.setattr(trials_module, "train", _fake_train({0: [10.0, 40.0, 30.0]}, []))
    study = optuna.create_study(direction="maximize")
    plan = TunePlan(**{**TINY.__dict__, "objective": objective})
    assert trials_module.run_trial(study, study.ask(), tmp_path, plan, CPU) == TrialState.COMPLETE
    assert study.trials[0].value == value


def test_the_objective_follows_the_network_the_final_evaluation_plays(
    tmp_path: Path, capsys, monkeypatch
) -> None:
    assert cli_tune._objective(None, "classic", {}, "CartPole-v1") == "best"  # classic keeps it
    last = {"final_eval_network": "last"}
    assert cli_tune._objective(None, "classic", last, "CartPole-v1") == "last"
    assert cli_tune._objective("last", "classic", {}, "CartPole-v1") == "last"
    status, err = dqnlab_main(
        capsys, monkeypatch, "tune", "--env", "CartPole-v1", "--trials", "1", "--steps", "300",
        "--objective", "peak", "--study-dir", str(tmp_path / "s"),
    )  # fmt: skip
    assert status == 2 and err.strip() == (
        "dqnlab: error: --objective 'peak' is not one of: best, last"
    )
    assert not (tmp_path / "s").exists()


def test_a_study_from_before_the_objective_carries_on_with_the_last_evaluation(
    tmp_path: Path,
) -> None:
    study_dir = tmp_path / "study"
    open_study(study_dir, TINY)  # TINY's objective: "last"
    record = json.loads((study_dir / "study.json").read_text())
    del record["objective"]  # as study.json was written before the setting
    (study_dir / "study.json").write_text(json.dumps(record))
    assert check_study_dir(study_dir, TINY)
    with pytest.raises(DqnlabError, match="differs in objective"):
        check_study_dir(study_dir, TunePlan(**{**TINY.__dict__, "objective": "best"}))
    # The same command, which gives no --objective, carries it on with its own.
    assert cli_tune._objective(None, "classic", {}, "CartPole-v1", study_dir) == "last"


def test_a_tiny_tune_writes_its_trials_best_preset_and_figures(tmp_path: Path) -> None:
    study_dir = tmp_path / "study"
    study = tune(study_dir, TINY, 3, CPU, "dqnlab tune --env CartPole-v1 --trials 3")
    assert len(study.trials) == 3
    with (study_dir / "trials.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert [row["number"] for row in rows] == ["0", "1", "2"]
    assert {"learning_rate", "batch_size", "state", "value", "duration_seconds"} <= set(rows[0])
    assert json.loads((study_dir / "study.json").read_text())["env"] == "CartPole-v1"
    assert (study_dir / "history.png").stat().st_size > 0
    text = (study_dir / "best.toml").read_text()
    assert text.startswith("# The best trial") and "# Study: dqnlab tune --env CartPole-v1" in text
    # The preset trains: a few steps of `dqnlab train --preset best.toml`.
    best = study.best_trial
    config = resolve_config(str(study_dir / "best.toml"), env="CartPole-v1", total_steps=100)
    assert config.learning_rate == best.params["learning_rate"]
    assert config.batch_size == best.params["batch_size"]
    prepare_run_dir(tmp_path / "again", force=False)
    assert real_train(config, tmp_path / "again", CPU, progress=False).steps == 100


def test_a_killed_tune_carries_on_with_no_trial_run_twice_and_none_lost(
    tmp_path: Path, monkeypatch
) -> None:
    study_dir = tmp_path / "study"
    tune(study_dir, TINY, 2, CPU, "dqnlab tune")

    class Killed(Exception):
        pass

    def killed_at_the_second_evaluation(*args, on_evaluation, **kwargs):
        def hook(step: int, mean: float) -> bool:
            if step >= 300:
                raise Killed  # as a kill: the checkpoint at step 150 stays, the trial RUNNING
            return on_evaluation(step, mean)

        return real_train(*args, on_evaluation=hook, **kwargs)

    monkeypatch.setattr(trials_module, "train", killed_at_the_second_evaluation)
    with pytest.raises(Killed):
        tune(study_dir, TINY, 4, CPU, "dqnlab tune")
    study = open_study(study_dir, TINY)
    assert [t.state for t in study.trials][2] == TrialState.RUNNING
    calls: list[tuple[str, bool]] = []

    def recorded(config, run_dir, device, *, resume, **kwargs):
        calls.append((run_dir.name, resume))
        return real_train(config, run_dir, device, resume=resume, **kwargs)

    monkeypatch.setattr(trials_module, "train", recorded)
    study = tune(study_dir, TINY, 4, CPU, "dqnlab tune")
    assert calls == [("trial-0002", True), ("trial-0003", False)]
    assert len(study.trials) == 4 and not study.get_trials(states=(TrialState.RUNNING,))
    with (trial_run_dir(study_dir, 2) / "evaluations.csv").open() as handle:
        assert [row["step"] for row in csv.DictReader(handle)] == ["150", "300"]


def _draw(study_dir: Path, trials: int) -> list[dict]:
    """Ask for `trials` trials in the study as a new tune process would (the study opened
    anew, its sampler made anew) and tell each a value; their settings."""
    study = open_study(study_dir, TINY)
    drawn = []
    for _ in range(trials):
        trial = study.ask()
        settings = suggest(trial, TINY.space, TINY.steps)
        study.tell(trial, float(len(study.get_trials())))
        drawn.append(settings)
    return drawn


def test_a_tune_carried_on_draws_what_one_left_alone_draws_and_no_trial_again(
    tmp_path: Path,
) -> None:
    # Five of the first ten trials are the sampler's random start-up draws: a study carried
    # on after trial 4 once drew trials 5 to 9 with trials 0 to 4's settings.
    alone = _draw(tmp_path / "alone", 8)
    carried = [*_draw(tmp_path / "carried", 3), *_draw(tmp_path / "carried", 2)]
    carried += _draw(tmp_path / "carried", 3)
    assert carried == alone
    assert len({json.dumps(settings, sort_keys=True) for settings in alone}) == 8


def test_a_study_dir_of_another_environment_is_refused_and_left_as_it_was(
    tmp_path: Path,
) -> None:
    study_dir = tmp_path / "study"
    open_study(study_dir, TINY)
    before = sorted(path.name for path in study_dir.iterdir())
    other = TunePlan(**{**TINY.__dict__, "env": "Acrobot-v1"})
    with pytest.raises(DqnlabError) as error:
        tune(study_dir, other, 1, CPU, "dqnlab tune")
    assert "made for env 'CartPole-v1'" in str(error.value) and "\n" not in str(error.value)
    assert sorted(path.name for path in study_dir.iterdir()) == before


def test_the_command_refuses_zero_trials_in_one_line(tmp_path: Path, capsys, monkeypatch) -> None:
    status, err = dqnlab_main(
        capsys,
        monkeypatch,
        "tune",
        "--env",
        "CartPole-v1",
        "--trials",
        "0",
        "--steps",
        "300",
        "--study-dir",
        str(tmp_path / "s"),
    )
    assert status == 2 and err.strip() == "dqnlab: error: --trials 0: must be at least 1"
    assert not (tmp_path / "s").exists()


def test_the_command_without_optuna_says_how_to_install_it(capsys, monkeypatch) -> None:
    monkeypatch.setitem(__import__("sys").modules, "optuna", None)
    status, err = dqnlab_main(
        capsys, monkeypatch, "tune", "--env", "CartPole-v1", "--trials", "1", "--steps", "300"
    )
    assert status == 2 and "pip install 'dqnlab[tune]'" in err and err.count("\n") == 1


def test_trials_are_shared_out_among_jobs() -> None:
    assert shares(5, 2) == [3, 2] and shares(1, 3) == [1] and shares(0, 2) == []


def test_two_jobs_train_a_trial_each_on_one_thread(tmp_path: Path) -> None:
    study = tune(tmp_path / "study", TINY, 2, CPU, "dqnlab tune --jobs 2", jobs=2)
    assert sorted(t.state for t in study.trials) == [TrialState.COMPLETE] * 2
    for number in (0, 1):
        assert (
            "threads = 1 "
            in (trial_run_dir(tmp_path / "study", number) / "config.toml").read_text()
        )
    # The thread count is the machine's: best.toml leaves it at the default, and says why.
    best = resolve_config(str(tmp_path / "study" / "best.toml"), env="CartPole-v1")
    assert best.threads == 0
    assert "the study's trials ran with 1" in (tmp_path / "study" / "best.toml").read_text()


def test_a_trial_of_several_seeds_is_their_mean_and_is_pruned_on_its_first_seed(
    tmp_path: Path, monkeypatch
) -> None:
    """With --seeds 2 each trial trains seeds 0 and 1 one after the other; the pruner sees
    seed 0's evaluations alone (a pruner holds a trial's best value so far, so a good first
    seed would shield a bad second one)."""
    seen: list[tuple[str, int]] = []
    scores = {  # (trial, seed): the means at steps 100, 200, 300
        (0, 0): [10.0, 20.0, 30.0], (0, 1): [12.0, 22.0, 50.0],
        (1, 0): [11.0, 21.0, 31.0], (1, 1): [1.0, 2.0, 3.0],  # a bad second seed: no pruning
        (2, 0): [1.0, 40.0, 50.0], (2, 1): [30.0, 40.0, 50.0],  # below both at step 100
    }  # fmt: skip

    def train(config, run_dir, device, progress, tensorboard, resume, on_evaluation):
        number = int(run_dir.name.split("-")[1])
        evaluations = []
        for index, mean in enumerate(scores[number, config.seed]):
            evaluations.append(((index + 1) * 100, mean))
            seen.append((run_dir.name, (index + 1) * 100))
            if on_evaluation is not None and on_evaluation((index + 1) * 100, mean):
                return TrainResult(300, 0, 1.0, 0.0, mean, evaluations, 0, STOPPED_BY_HOOK)
        return TrainResult(300, 0, 1.0, 0.0, max(scores[number, config.seed]), evaluations, 0)

    monkeypatch.setattr(trials_module, "train", train)
    plan = TunePlan(**{**TINY.__dict__, "seeds": 2})
    study = optuna.create_study(
        direction="maximize", pruner=optuna.pruners.MedianPruner(n_startup_trials=0)
    )
    states = [trials_module.run_trial(study, study.ask(), tmp_path, plan, CPU) for _ in range(3)]
    assert states == [TrialState.COMPLETE, TrialState.COMPLETE, TrialState.PRUNED]
    assert study.trials[0].value == 40.0 and study.trials[1].value == 17.0  # (30 + 50) / 2
    assert sorted(study.trials[1].intermediate_values) == [100, 200, 300]  # seed 0's
    assert seen[-1] == ("trial-0002-s0", 100)  # pruned there: seed 1 never trained
    assert study.trials[0].user_attrs["value_seed_1"] == 50.0


def test_a_tiny_tune_of_two_seeds_keeps_a_run_per_seed_and_carries_on_a_killed_one(
    tmp_path: Path, monkeypatch
) -> None:
    plan = TunePlan(**{**TINY.__dict__, "seeds": 2})
    study_dir = tmp_path / "study"

    class Killed(Exception):
        pass

    def killed_in_the_second_seed(config, run_dir, *args, on_evaluation, **kwargs):
        def hook(step: int, mean: float) -> bool:
            if config.seed == 1 and step >= 300:
                raise Killed  # the trial RUNNING, seed 0's value recorded, seed 1 half done
            return on_evaluation is not None and on_evaluation(step, mean)

        return real_train(config, run_dir, *args, on_evaluation=hook, **kwargs)

    monkeypatch.setattr(trials_module, "train", killed_in_the_second_seed)
    with pytest.raises(Killed):
        tune(study_dir, plan, 1, CPU, "dqnlab tune --seeds 2")
    calls: list[tuple[str, bool]] = []

    def recorded(config, run_dir, device, *, resume, **kwargs):
        calls.append((run_dir.name, resume))
        return real_train(config, run_dir, device, resume=resume, **kwargs)

    monkeypatch.setattr(trials_module, "train", recorded)
    study = tune(study_dir, plan, 1, CPU, "dqnlab tune --seeds 2")
    assert calls == [("trial-0000-s1", True)]  # seed 0 is not trained again
    last = []
    for seed in (0, 1):
        run = trial_run_dir(study_dir, 0, seed)
        assert f"seed = {seed} " in (run / "config.toml").read_text()
        with (run / "evaluations.csv").open() as handle:
            last.append(float(list(csv.DictReader(handle))[-1]["mean"]))
    assert study.trials[0].value == pytest.approx(sum(last) / 2)
    with (study_dir / "trials.csv").open() as handle:
        row = next(csv.DictReader(handle))
    assert row["seed_values"] == f"0:{last[0]:.6g};1:{last[1]:.6g}"
    assert "seed = 0 " in (study_dir / "best.toml").read_text()
    # A study of one seed per trial is another plan.
    with pytest.raises(DqnlabError, match="it differs in seeds"):
        open_study(study_dir, TINY)


def test_env_kwargs_and_wrappers_make_every_trials_environment(
    tmp_path: Path, capsys, monkeypatch
) -> None:
    """CountEnv cannot be made without `length`; every game of it lasts `length` steps of
    reward 1, doubled by the wrapper: a trial's value of 14 says both reached it."""
    count = "tests.envs.test_env_args"
    study_dir = tmp_path / "study"
    status, err = dqnlab_main(
        capsys, monkeypatch, "tune", "--env", f"{count}:CountEnv", "--trials", "1",
        "--steps", "300", "--evaluations", "2", "--set", "eval_steps=50",
        "--set", "mlp_hidden_sizes=[8]",
        "--env-kwarg", "length=7", "--env-kwarg", "width=3",
        "--wrapper", f"{count}:DoubleReward", "--study-dir", str(study_dir),
    )  # fmt: skip
    assert status == 0, err
    with (study_dir / "trials.csv").open() as handle:
        (row,) = list(csv.DictReader(handle))
    assert row["state"] == "COMPLETE" and float(row["value"]) == 14.0
    text = (study_dir / "best.toml").read_text()
    assert "env_kwargs = {length = 7, width = 3}" in text
    assert f'env_wrappers = ["{count}:DoubleReward"]' in text
    bad, err = dqnlab_main(
        capsys, monkeypatch, "tune", "--env", f"{count}:CountEnv", "--trials", "1",
        "--steps", "300", "--study-dir", str(tmp_path / "other"),
    )  # fmt: skip
    assert bad == 2 and err.count("\n") == 1 and not (tmp_path / "other").exists()


def test_ctrl_c_stops_every_job_at_a_checkpoint_in_one_line_for_the_next_tune(
    tmp_path: Path,
) -> None:
    """SIGINT to the process group, as Ctrl-C sends it, while two jobs train a trial each."""
    study_dir = tmp_path / "study"
    args = [sys.executable, "-m", "dqnlab", "tune", "--env", "CartPole-v1", "--trials", "2",
            "--steps", "30000", "--evaluations", "2", "--pruner", "none", "--jobs", "2",
            "--set", "mlp_hidden_sizes=[8]", "--set", "checkpoint_period_steps=500",
            "--study-dir", str(study_dir)]  # fmt: skip
    process = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               start_new_session=True)  # fmt: skip
    checkpoints = [trial_run_dir(study_dir, n) / "checkpoints" for n in (0, 1)]
    deadline = time.monotonic() + 120
    while not all(path.is_dir() and any(path.iterdir()) for path in checkpoints):
        assert process.poll() is None and time.monotonic() < deadline, process.communicate()
        time.sleep(0.2)
    os.killpg(process.pid, signal.SIGINT)
    _, err = process.communicate(timeout=120)
    assert process.returncode == 130
    assert err == (
        "dqnlab: error: stopped by SIGINT in trials 0 and 1, each after saving a checkpoint; "
        "the same command carries the study on\n"
    )
    storage = JournalStorage(JournalFileBackend(str(study_dir / "journal.log")))
    study = optuna.load_study(study_name=STUDY_NAME, storage=storage)
    # Both trials wait, RUNNING, for the next tune (which carries stale trials on first).
    assert [(t.number, t.state) for t in study.trials] == [(0, TrialState.RUNNING),
                                                           (1, TrialState.RUNNING)]  # fmt: skip
