"""Q-value inspection (`inspect_run`) on tiny real runs: the Q-values against a direct
forward pass of each saved network, the CSV, best and worst against evaluations.csv,
networks chosen by step, observations taken again, the figures' bars, determinism."""

from __future__ import annotations

import csv
import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from matplotlib.patches import Rectangle

from dqnlab.algorithm.networks import build_network
from dqnlab.analysis.inspection.figures import Q_VALUES_AXES, frame_figure
from dqnlab.analysis.inspection.qvalues import Inspection
from dqnlab.analysis.inspection.write import CSV_COLUMNS, inspect_run
from dqnlab.config import Config, config_from_dict, config_to_toml, derive_seeds, resolve_config
from dqnlab.envs import make_env
from dqnlab.envs.atari import preprocess
from dqnlab.errors import DqnlabError
from dqnlab.run import rundir
from dqnlab.run.logs import read_csv
from dqnlab.run.rundir import eval_network_path, prepare_run_dir
from dqnlab.run.train import train

FRAMES = 3
MAX_GAME_STEPS = 200  # enough for the test, cheap to play twice
CPU = torch.device("cpu")


def _train(root: Path, config: Config) -> Path:
    run = root / "run"
    prepare_run_dir(run, force=False)
    train(config, run, CPU, progress=False, tensorboard=False)
    return run


@pytest.fixture(scope="module")
def breakout_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    config = resolve_config(
        "nature",
        env="breakout",
        total_steps=400,
        replay_start_steps=100,
        replay_capacity=1000,
        eval_period_steps=100,
        eval_steps=100,
        batch_size=8,
        eval_networks_kept="all",  # the networks of steps 200, 300 and 400 are inspected
    )  # evaluations at steps 200, 300 and 400
    return _train(tmp_path_factory.mktemp("breakout"), config)


@pytest.fixture(scope="module")
def cartpole_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    config = resolve_config(
        "classic",
        env="CartPole-v1",
        total_steps=800,
        replay_start_steps=100,
        eval_period_steps=200,
        eval_steps=200,
        seed=0,
    )  # evaluations at steps 200, 400, 600 and 800
    return _train(tmp_path_factory.mktemp("cartpole"), config)


def _inspect(run: Path, out: Path, seed: int) -> Inspection:
    return inspect_run(
        run, out, frames=FRAMES, max_game_steps=MAX_GAME_STEPS, seed=seed, device=CPU
    )


@pytest.fixture(scope="module")
def breakout(breakout_run: Path) -> Inspection:
    return _inspect(breakout_run, breakout_run.parent / "inspect", seed=1)


@pytest.fixture(scope="module")
def cartpole(cartpole_run: Path) -> Inspection:
    return _inspect(cartpole_run, cartpole_run.parent / "inspect", seed=1)


def _direct_q_values(path: Path, observations: np.ndarray) -> np.ndarray:
    """The saved network rebuilt from its checkpoint alone, one forward pass in eval mode."""
    payload = rundir.load_network(path)
    config = config_from_dict(payload["config"])
    is_image = observations.dtype == np.uint8 and observations.ndim >= 4
    network = build_network(
        config.network,
        tuple(payload["input_shape"]),
        len(payload["action_names"]),
        is_image,
        config.mlp_hidden_sizes,
    )
    network.load_state_dict(payload["network"])
    network.eval()
    with torch.no_grad():
        return network(torch.from_numpy(observations)).numpy()


def _best_and_worst(run: Path, total_steps: int) -> tuple[tuple[int, float], tuple[int, float]]:
    """From evaluations.csv: the first highest mean, and the last lowest mean among the
    evaluations at step >= total_steps / 4."""
    rows = [(int(r["step"]), float(r["mean"])) for r in read_csv(run / "evaluations.csv")]
    best = max(rows, key=lambda row: (row[1], -row[0]))
    late = [row for row in rows if row[0] >= total_steps / 4]
    worst = min(late, key=lambda row: (row[1], -row[0]))
    return best, worst


@pytest.mark.parametrize("which", ["breakout", "cartpole"])
def test_q_values_are_a_forward_pass_of_each_saved_network(
    which: str, request: pytest.FixtureRequest
) -> None:
    inspection: Inspection = request.getfixturevalue(which)
    assert [n.name for n in inspection.networks] == ["best", "worst"]
    assert inspection.q_values.shape == (2, FRAMES, len(inspection.action_names))
    for k, network in enumerate(inspection.networks):
        expected = _direct_q_values(network.path, inspection.observations)
        np.testing.assert_array_equal(inspection.q_values[k], expected)
        np.testing.assert_array_equal(inspection.greedy_actions[k], expected.argmax(axis=1))


@pytest.mark.parametrize("which", ["breakout", "cartpole"])
def test_best_and_worst_are_those_of_the_evaluations(
    which: str, request: pytest.FixtureRequest
) -> None:
    inspection: Inspection = request.getfixturevalue(which)
    run = inspection.networks[0].path.parents[1]
    total_steps = 400 if which == "breakout" else 800
    best, worst = _best_and_worst(run, total_steps)
    assert (inspection.networks[0].step, inspection.networks[0].eval_mean) == best
    assert (inspection.networks[1].step, inspection.networks[1].eval_mean) == worst
    assert inspection.networks[0].path.name == "best.pt"
    assert inspection.networks[1].path.name == "worst.pt"


@pytest.mark.parametrize("which", ["breakout", "cartpole"])
def test_csv_holds_exactly_the_q_values_and_greedy_actions(
    which: str, request: pytest.FixtureRequest
) -> None:
    inspection: Inspection = request.getfixturevalue(which)
    assert inspection.csv_path is not None
    with inspection.csv_path.open(newline="") as handle:
        reader = csv.DictReader(handle)
        assert tuple(reader.fieldnames or ()) == CSV_COLUMNS
        rows = list(reader)
    networks, frames, actions = inspection.q_values.shape
    assert len(rows) == networks * frames * actions
    q_values = np.full(inspection.q_values.shape, np.nan, dtype=np.float32)
    flags = np.zeros(inspection.q_values.shape, dtype=bool)
    names = [n.name for n in inspection.networks]
    for row in rows:
        k, frame, action = names.index(row["network"]), int(row["frame"]), int(row["action_index"])
        network = inspection.networks[k]
        assert int(row["checkpoint_step"]) == network.step
        assert float(row["eval_mean"]) == network.eval_mean
        assert row["action_name"] == inspection.action_names[action]
        q_values[k, frame, action] = float(row["q_value"])
        flags[k, frame, action] = row["is_argmax"] == "1"
    for k, network in enumerate(inspection.networks):
        direct = _direct_q_values(network.path, inspection.observations)
        np.testing.assert_array_equal(q_values[k], direct)
        assert (flags[k].sum(axis=1) == 1).all()
        np.testing.assert_array_equal(flags[k].argmax(axis=1), direct.argmax(axis=1))


def test_atari_frames_are_screens_of_one_game_with_their_network_inputs(
    breakout: Inspection,
) -> None:
    assert breakout.action_names == ["NOOP", "FIRE", "RIGHT", "LEFT"]
    assert breakout.observations.shape == (FRAMES, 4, 84, 84)
    assert breakout.observations.dtype == np.uint8
    assert breakout.screens is not None and breakout.screens.shape == (FRAMES, 210, 160, 3)
    assert breakout.game_steps is not None
    assert breakout.game_steps == sorted(set(breakout.game_steps))
    assert all(0 < s < MAX_GAME_STEPS for s in breakout.game_steps)
    assert breakout.screens.any(axis=(1, 2, 3)).all()
    assert breakout.observations[:, -1].any(axis=(1, 2)).all()
    assert breakout.observations_path is not None and breakout.screens_path is not None
    np.testing.assert_array_equal(np.load(breakout.observations_path), breakout.observations)
    np.testing.assert_array_equal(np.load(breakout.screens_path), breakout.screens)


def test_figure_groups_a_bar_per_action_for_each_network_greedy_one_hatched(
    breakout: Inspection,
) -> None:
    for frame in range(FRAMES):
        figure = frame_figure(breakout, frame)
        (axes,) = [a for a in figure.axes if a.get_label() == Q_VALUES_AXES]
        assert [t.get_text() for t in axes.get_xticklabels()] == ["NOOP", "FIRE", "RIGHT", "LEFT"]
        assert len(axes.containers) == len(breakout.networks)
        for k, container in enumerate(axes.containers):
            bars = [p for p in container if isinstance(p, Rectangle)]
            assert len(bars) == 4
            np.testing.assert_allclose([b.get_height() for b in bars], breakout.q_values[k, frame])
            hatched = [i for i, b in enumerate(bars) if b.get_hatch()]
            assert hatched == [int(breakout.greedy_actions[k, frame])]
        legend = axes.get_legend()
        assert legend is not None
        texts = [t.get_text() for t in legend.get_texts()]
        for network in breakout.networks:
            assert any(f"step {network.step:,}" in t and network.name in t for t in texts)


@pytest.mark.parametrize("which", ["breakout", "cartpole"])
def test_png_files_are_written(which: str, request: pytest.FixtureRequest) -> None:
    inspection: Inspection = request.getfixturevalue(which)
    assert [p.name for p in inspection.figure_paths] == [f"frame-00{i}.png" for i in range(FRAMES)]
    assert inspection.overview_path is not None
    for path in [*inspection.figure_paths, inspection.overview_path]:
        data = path.read_bytes()
        assert data.startswith(b"\x89PNG") and len(data) > 5_000


def test_cartpole_vector_observations(cartpole: Inspection) -> None:
    assert cartpole.observations.shape == (FRAMES, 1, 4)
    assert cartpole.observations.dtype == np.float32
    assert cartpole.screens is None and cartpole.screens_path is None
    assert cartpole.action_names == ["0", "1"]
    figure = frame_figure(cartpole, 0)
    (frame_axes,) = [a for a in figure.axes if a.get_label() != Q_VALUES_AXES]
    heights = [p.get_width() for p in frame_axes.containers[0]]  # horizontal bars
    np.testing.assert_allclose(heights, cartpole.observations[0, -1])


def test_networks_by_step_on_saved_observations(breakout: Inspection, tmp_path: Path) -> None:
    run = breakout.networks[0].path.parents[1]
    assert breakout.observations_path is not None
    again = inspect_run(
        run,
        tmp_path,
        checkpoints=["best", 200, "300", 400],
        observations=breakout.observations_path,
        device=CPU,
    )
    assert [n.name for n in again.networks] == ["best", "step 200", "step 300", "step 400"]
    np.testing.assert_array_equal(again.observations, breakout.observations)
    np.testing.assert_array_equal(again.q_values[0], breakout.q_values[0])  # the same best
    for k, network in enumerate(again.networks[1:], start=1):
        assert network.path == eval_network_path(run, network.step)
        expected = _direct_q_values(network.path, again.observations)
        np.testing.assert_array_equal(again.q_values[k], expected)
        for earlier, q_values in zip(breakout.networks, breakout.q_values, strict=True):
            if earlier.step == network.step:  # best and worst are evaluated networks too
                np.testing.assert_array_equal(again.q_values[k], q_values)
                assert earlier.eval_mean == network.eval_mean
    assert again.screens is not None and breakout.screens is not None  # screens.npy beside
    np.testing.assert_array_equal(again.screens, breakout.screens)
    assert again.game_steps is None
    # Inputs saved under another name are not an inspection's: a screens.npy beside them
    # shows other frames.
    saved = tmp_path / "saved"
    saved.mkdir()
    shutil.copy(breakout.observations_path, saved / "mine.npy")
    shutil.copy(breakout.observations_path.with_name("screens.npy"), saved / "screens.npy")
    other = inspect_run(
        run, tmp_path / "other", checkpoints=["best"], observations=saved / "mine.npy", device=CPU
    )
    assert other.screens is None


def test_missing_step_lists_the_kept_steps(breakout_run: Path, tmp_path: Path) -> None:
    with pytest.raises(DqnlabError, match="250.*kept steps: 200, 300, 400"):
        inspect_run(breakout_run, tmp_path, checkpoints=["best", "250"], device=CPU)
    with pytest.raises(DqnlabError, match="'last' is not best, worst or a training step"):
        inspect_run(breakout_run, tmp_path, checkpoints=["last"], device=CPU)


def test_missing_networks_are_explained(cartpole_run: Path, tmp_path: Path) -> None:
    """A run with only best.pt (no evaluation after the first quarter, and one trained with
    eval_networks_kept = best_and_worst)."""
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    shutil.copy(cartpole_run / "checkpoints" / "best.pt", run / "checkpoints" / "best.pt")
    config = config_from_dict(rundir.load_network(run / "checkpoints" / "best.pt")["config"])
    kept = dataclasses.replace(config, eval_networks_kept="best_and_worst")
    (run / "config.toml").write_text(config_to_toml(kept))
    with pytest.raises(DqnlabError, match=r"no worst network.*total_steps / 4 = 200"):
        inspect_run(run, tmp_path / "out", device=CPU)
    with pytest.raises(DqnlabError, match="best_and_worst"):
        inspect_run(run, tmp_path / "out", checkpoints=["400"], device=CPU)
    with pytest.raises(DqnlabError, match="not a dqnlab run"):
        inspect_run(tmp_path / "out", tmp_path / "out", device=CPU)


def test_observations_of_another_shape_are_refused(cartpole_run: Path, tmp_path: Path) -> None:
    path = tmp_path / "observations.npy"
    np.save(path, np.zeros((2, 4, 84, 84), dtype=np.uint8))
    with pytest.raises(DqnlabError, match=r"shape \(2, 4, 84, 84\).*\(N, 1, 4\)"):
        inspect_run(cartpole_run, tmp_path / "out", observations=path, device=CPU)
    np.save(path, np.full((2, 1, 4), 0.1, dtype=np.float64))  # not exact in float32
    with pytest.raises(DqnlabError, match="float64"):
        inspect_run(cartpole_run, tmp_path / "out", observations=path, device=CPU)


@pytest.mark.parametrize("which", ["breakout_run", "cartpole_run"])
def test_same_seed_same_frames_and_q_values(
    which: str, request: pytest.FixtureRequest, tmp_path: Path
) -> None:
    run: Path = request.getfixturevalue(which)
    runs = [_inspect(run, tmp_path / f"out-{i}", seed=5) for i in range(2)]
    np.testing.assert_array_equal(runs[0].observations, runs[1].observations)
    np.testing.assert_array_equal(runs[0].q_values, runs[1].q_values)
    assert runs[0].game_steps == runs[1].game_steps
    csv_files = [(tmp_path / f"out-{i}" / "q_values.csv").read_bytes() for i in range(2)]
    assert csv_files[0] == csv_files[1]
    if runs[0].screens is not None:
        np.testing.assert_array_equal(runs[0].screens, runs[1].screens)
    other = _inspect(run, tmp_path / "out-other", seed=6)
    assert not np.array_equal(other.observations, runs[0].observations)


def test_cartpole_frames_are_those_of_the_best_networks_first_game(cartpole: Inspection) -> None:
    """Replayed by hand: the evaluation environment seeded as inspect_run seeds it, the
    best network acting greedily (the classic preset evaluates at epsilon 0)."""
    best = cartpole.networks[0]
    config = config_from_dict(rundir.load_network(best.path)["config"])
    assert config.eval_epsilon == 0.0 and config.history_length == 1
    env = make_env(config, training=False, seed=derive_seeds(1, 2)[0])
    observation = env.reset(new_game=True).copy()
    seen = []
    for _ in range(max(cartpole.game_steps or [0]) + 1):
        seen.append(observation)
        q_values = _direct_q_values(best.path, observation[None, None])
        observation, *_ = env.step(int(q_values.argmax()))
        observation = observation.copy()
    assert cartpole.game_steps is not None
    np.testing.assert_array_equal(
        cartpole.observations[:, -1], np.stack([seen[s] for s in cartpole.game_steps])
    )


def test_atari_screens_are_the_last_frames_of_their_inputs(breakout: Inspection) -> None:
    """An input frame pools the last two raw frames with a per-channel max, so the last
    frame alone, processed, is nowhere brighter and mostly equal."""
    assert breakout.screens is not None
    for screen, stacked in zip(breakout.screens, breakout.observations, strict=True):
        alone = preprocess(screen, screen)
        assert (alone <= stacked[-1]).all()
        assert (alone == stacked[-1]).mean() > 0.9


def test_fewer_frames_than_asked_when_the_game_is_short(cartpole_run: Path, tmp_path: Path) -> None:
    inspection = inspect_run(cartpole_run, tmp_path, frames=500, max_game_steps=7, device=CPU)
    assert inspection.game_steps == list(range(7))
    assert len(inspection.figure_paths) == 7
    assert "first 7 steps" in inspection.note or "its 7 steps" in inspection.note
