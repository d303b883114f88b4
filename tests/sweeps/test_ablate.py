"""Ablation sweeps: the grid from --vary, runs in their own directories, re-runs carry on."""

from __future__ import annotations

from pathlib import Path

import pytest

from dqnlab.errors import ConfigError, DqnlabError
from dqnlab.run import rundir
from dqnlab.run.rundir import load_run_config
from dqnlab.sweeps.ablate import Variation, check_sweep_dir, parse_variation, plan_sweep, run_sweep
from tests.helpers import dqnlab_main
from tests.sweeps.ray_helpers import loopback_ray, non_loopback_sockets

TINY = {
    "replay_start_steps": 100,
    "eval_period_steps": 150,
    "eval_steps": 100,
    "final_eval_episodes": 2,
}


@pytest.fixture(scope="module")
def ray_cluster():  # noqa: ANN201
    """One Ray cluster for the module (start-up takes 10-20 s): a head that only schedules
    and a node of 2 CPUs, all on 127.0.0.1; the sweeps below run on it."""
    with loopback_ray(0, [{"num_cpus": 2}]) as cluster:
        yield cluster


def test_parse_single_and_linked_variations() -> None:
    assert parse_variation("life_loss_terminal=true,false") == Variation(
        ("life_loss_terminal",), ((True,), (False,))
    )
    linked = parse_variation("optimizer+learning_rate=deepmind_rmsprop+0.00025,rmsprop+0.00005")
    assert linked.keys == ("optimizer", "learning_rate")
    assert linked.choices == (("deepmind_rmsprop", 0.00025), ("rmsprop", 0.00005))
    sizes = parse_variation("mlp_hidden_sizes=[64,64],[256]")  # commas inside brackets
    assert sizes.choices == (([64, 64],), ([256],))


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("life_loss_terminal", "KEY=V1,V2"),
        ("optimizer+learning_rate=rmsprop", "gives 1 values for 2 settings"),
        ("learning_rat=0.1,0.2", "did you mean learning_rate"),
        ("discount=0.9,0.9", "twice"),
        ("discount=0.9,,0.8", "empty value"),
    ],
)
def test_bad_variations_are_refused(text: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        parse_variation(text)


def test_plan_is_the_product_of_variations_times_seeds(tmp_path: Path) -> None:
    sweep = plan_sweep(
        "CartPole-v1",
        [parse_variation("discount=0.9,0.99"), parse_variation("batch_size=16,32")],
        preset="classic", overrides={}, seeds=2, first_seed=5, steps=300, sweep_dir=tmp_path,
    )  # fmt: skip
    assert len(sweep.runs) == 8
    assert sweep.runs[0].name == "discount=0.9,batch_size=16-s5"
    assert {(r.config.discount, r.config.batch_size, r.config.seed) for r in sweep.runs} == {
        (d, b, s) for d in (0.9, 0.99) for b in (16, 32) for s in (5, 6)
    }
    assert all(run.config.total_steps == 300 for run in sweep.runs)
    assert all(run.run_dir.parent == tmp_path for run in sweep.runs)


def test_plan_refuses_bad_grids_before_anything_runs(tmp_path: Path) -> None:
    def plan(*texts: str, seeds: int = 1) -> None:
        plan_sweep(
            "CartPole-v1", [parse_variation(t) for t in texts], preset="classic",
            overrides={}, seeds=seeds, first_seed=0, steps=None, sweep_dir=tmp_path / "s",
        )  # fmt: skip

    with pytest.raises(ConfigError, match="optimizer = 'sgd' is not one of"):
        plan("optimizer=rmsprop,sgd")
    with pytest.raises(ConfigError, match="use --seeds"):
        plan("seed=1,2")
    with pytest.raises(ConfigError, match="more than once"):
        plan("discount=0.9,0.99", "discount+batch_size=0.5+8,0.6+8")
    with pytest.raises(ConfigError, match="--seeds 0"):
        plan("discount=0.9,0.99", seeds=0)
    assert not (tmp_path / "s").exists()


@pytest.mark.slow  # three sweeps, about a minute: CI keeps the cheaper one below
def test_sweep_trains_each_run_then_skips_finished_ones(tmp_path: Path, ray_cluster) -> None:
    sweep_dir = tmp_path / "sweep"
    variation = parse_variation("life_loss_terminal=true,false")
    sweep = plan_sweep(
        "CartPole-v1", [variation], preset="classic", overrides=TINY, seeds=1, first_seed=0,
        steps=300, sweep_dir=sweep_dir,
    )  # fmt: skip
    lines: list[str] = []
    run_sweep(sweep, jobs=2, device="cpu", echo=lines.append, poll_seconds=0.1)
    assert [run.status for run in sweep.runs] == ["ok", "ok"], lines
    assert non_loopback_sockets() == []  # Ray and the runs talked on 127.0.0.1 only
    for run in sweep.runs:
        assert load_run_config(run.run_dir) == run.config
        assert rundir.load_network(run.run_dir / "checkpoints" / "last.pt")["step"] == 300
        assert (run.run_dir / "evaluations.csv").read_text().count("\n") == 3  # header + 2
    assert {load_run_config(r.run_dir).life_loss_terminal for r in sweep.runs} == {True, False}

    # The same command again: nothing to train.
    again = plan_sweep(
        "CartPole-v1", [variation], preset="classic", overrides=TINY, seeds=1, first_seed=0,
        steps=300, sweep_dir=sweep_dir,
    )  # fmt: skip
    check_sweep_dir(again)
    lines.clear()
    run_sweep(again, jobs=1, device="cpu", echo=lines.append, poll_seconds=0.1)
    assert [run.status for run in again.runs] == ["done", "done"]
    assert all("already finished" in line for line in lines)

    # A longer budget resumes both runs from their last checkpoint.
    longer = plan_sweep(
        "CartPole-v1", [variation], preset="classic", overrides=TINY, seeds=1, first_seed=0,
        steps=450, sweep_dir=sweep_dir,
    )  # fmt: skip
    check_sweep_dir(longer)
    run_sweep(longer, jobs=1, device="cpu", echo=lines.append, poll_seconds=0.1)
    assert [run.status for run in longer.runs] == ["ok", "ok"]
    for run in longer.runs:
        steps = [line.split(",")[0] for line in (run.run_dir / "evaluations.csv").open()]
        assert steps == ["step", "150", "300", "450"]  # continued, not restarted


def test_a_failed_run_does_not_stop_the_others(tmp_path: Path, ray_cluster) -> None:
    sweep = plan_sweep(
        "CartPole-v1", [parse_variation("discount=0.9,0.99")], preset="classic",
        overrides=TINY, seeds=1, first_seed=0, steps=150, sweep_dir=tmp_path,
    )  # fmt: skip
    sweep.runs[0].run_dir.mkdir()
    (sweep.runs[0].run_dir / "notes.txt").write_text("not a run")  # train refuses this dir
    lines: list[str] = []
    run_sweep(sweep, jobs=1, device="cpu", echo=lines.append, poll_seconds=0.1)
    assert [run.status for run in sweep.runs] == ["failed", "ok"]
    assert non_loopback_sockets() == []  # Ray and the run talked on 127.0.0.1 only
    assert [run.name for run in sweep.failed] == ["discount=0.9-s0"]
    assert any("FAILED" in line and "already exists and is not empty" in line for line in lines)


def test_a_sweep_dir_holding_other_runs_is_refused(tmp_path: Path, ray_cluster) -> None:
    def plan(values: str):  # noqa: ANN202
        return plan_sweep(
            "CartPole-v1", [parse_variation(f"discount={values}")], preset="classic",
            overrides=TINY, seeds=1, first_seed=0, steps=150, sweep_dir=tmp_path,
        )  # fmt: skip

    run_sweep(plan("0.9"), jobs=1, device="cpu", echo=lambda _: None, poll_seconds=0.1)
    other = plan("0.9")
    other.runs[0].config = plan_sweep(
        "CartPole-v1", [parse_variation("discount=0.9")], preset="classic",
        overrides={**TINY, "batch_size": 8}, seeds=1, first_seed=0, steps=150,
        sweep_dir=tmp_path,
    ).runs[0].config  # fmt: skip
    with pytest.raises(DqnlabError, match=r"other settings \(batch_size\)"):
        check_sweep_dir(other)
    (tmp_path / "config.toml").write_text("")
    with pytest.raises(DqnlabError, match="is a run directory"):
        check_sweep_dir(plan("0.9"))


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (["--gpus-per-run", "0.25"], "--gpus-per-run 0.25: the cluster has no GPUs (2 nodes)"),
        (["--memory-per-run", "100000"], "100000.0 GB of memory, more than any node has"),
        (["--cpus-per-run", "3"], "each run asks for 3 CPUs"),
    ],
)
def test_resources_the_cluster_lacks_are_refused_before_any_run(
    tmp_path: Path,
    capsys,
    monkeypatch,
    ray_cluster,
    options: list[str],
    message: str,  # noqa: ANN001
) -> None:
    """On a running cluster (this module's: a head and a node of 2 CPUs, no GPU), through
    the command: one line, exit 2, nothing written."""
    sweep_dir = tmp_path / "sweep"
    code, stderr = dqnlab_main(
        capsys, monkeypatch, "sweep", "--env", "CartPole-v1", "--sweep-dir", str(sweep_dir),
        *options,
    )  # fmt: skip
    assert code == 2 and message in stderr, stderr
    assert len(stderr.strip().splitlines()) == 1 and not sweep_dir.exists()
