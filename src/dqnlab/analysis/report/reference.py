"""Published learning curves to compare a run with, and the "on track?" verdict.

The reference is Dopamine's DQN (`data/dopamine_dqn_curves.csv`, `data/README.md`): 5
runs per game, each a mean raw score of the training games that ended in each
1M-frame iteration, 200 iterations. Its protocol is not the Nature one (sticky actions,
training returns at ε = 0.01, no life-loss signal): every figure and table says so. A run
is measured the way the reference is (its training games, `episodes.csv`, in the same
1M-frame windows), so that its latest window can be set beside the reference's mean and
range at the same frames, hours into a three-day run.

Reading only: nothing here writes a file or plays a game.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from dqnlab.analysis.report.runs import RunResults
from dqnlab.envs import is_atari
from dqnlab.run import rundir
from dqnlab.run.logs import read_csv

WINDOW_FRAMES = 1_000_000  # one Dopamine iteration: 250,000 agent steps of 4 frames
REFERENCES = ("dopamine", "none")
REFERENCE_NAME = "Dopamine DQN"
REFERENCE_PROTOCOL = "training games (sticky actions, ε = 0.01): not the Nature protocol"
REFERENCE_LABEL = f"{REFERENCE_NAME}, {REFERENCE_PROTOCOL}"
VERDICTS = ("below the range", "within the range", "above the range")


@dataclass(frozen=True)
class ReferenceCurve:
    """One game's published curve: per 1M-frame window, the mean, lowest and highest of
    its runs' scores."""

    game: str  # ale-py id
    runs: int
    mean: np.ndarray  # (windows,)
    low: np.ndarray
    high: np.ndarray

    @property
    def windows(self) -> int:
        return len(self.mean)


def reference_key(env: str) -> str:
    """A game's name as Dopamine spells it: ale-py's `space_invaders` is `spaceinvaders`."""
    return env.lower().replace("_", "")


def load_reference_curves(games: Sequence[str]) -> dict[str, ReferenceCurve]:
    """The curves of those of `games` (ale-py ids) the reference covers."""
    wanted = {reference_key(game): game for game in games if is_atari(game)}
    if not wanted:
        return {}
    text = (resources.files("dqnlab") / "data" / "dopamine_dqn_curves.csv").read_text()
    scores: dict[str, dict[tuple[int, int], float]] = {}
    for row in csv.DictReader(io.StringIO(text)):
        if row["game"] in wanted:
            by_cell = scores.setdefault(row["game"], {})
            by_cell[int(row["iteration"]), int(row["run"])] = float(row["train_return"])
    curves = {}
    for key, cells in scores.items():
        windows = 1 + max(iteration for iteration, _ in cells)
        runs = 1 + max(run for _, run in cells)
        table = np.full((windows, runs), np.nan)
        for (iteration, run), value in cells.items():
            table[iteration, run] = value
        curves[wanted[key]] = ReferenceCurve(
            wanted[key],
            runs,
            np.nanmean(table, axis=1),
            np.nanmin(table, axis=1),
            np.nanmax(table, axis=1),
        )
    return curves


# On track? -------------------------------------------------------------------------


@dataclass(frozen=True)
class OnTrackRow:
    """One run's latest 1M-frame window of training games against the reference."""

    run_dir: Path
    game: str
    configuration: str
    frames: int  # training frames the run has logged so far (its latest game's end)
    steps: int  # agent steps so far (its latest game, evaluation or checkpoint)
    finished: bool  # trained its whole budget
    window: int | None  # index of the latest window with a finished game (None: no game)
    window_complete: bool  # the run has logged frames past the window's end
    games: int  # training games that ended in the window
    score: float | None  # their mean raw score
    reference_mean: float | None  # None: no reference for this game or window
    reference_low: float | None
    reference_high: float | None
    verdict: str | None  # one of VERDICTS, None without a score and a reference
    last_eval_mean: float | None  # the latest periodic evaluation (ε = 0.05), if any
    why_none: str | None  # why there is no verdict


def training_windows(run_dir: Path) -> tuple[int, int, dict[int, list[float]]]:
    """The run's training frames and steps so far (at its latest game's end) and the raw
    scores of its training games by the 1M-frame window each ended in (`episodes.csv`)."""
    path = rundir.episodes_path(run_dir)
    windows: dict[int, list[float]] = {}
    frames = steps = 0
    for row in read_csv(path) if path.is_file() else []:
        try:
            step, end, score = int(row["step"]), int(row["frames"]), float(row["score"])
        except (TypeError, ValueError):  # a line torn by a killed run
            continue
        frames, steps = max(frames, end), max(steps, step)
        windows.setdefault((end - 1) // WINDOW_FRAMES, []).append(score)
    return frames, steps, windows


def verdict(score: float, low: float, high: float) -> str:
    below, within, above = VERDICTS
    return below if score < low else above if score > high else within


def on_track_rows(
    runs: Sequence[tuple[RunResults, str]], curves: dict[str, ReferenceCurve]
) -> list[OnTrackRow]:
    """A row per Atari run (with its configuration's label): its latest window with a
    finished training game, complete or not, against the reference's same window."""
    return [
        on_track_row(
            run.run_dir,
            run.config.env,
            configuration,
            curves.get(run.config.env),
            steps=run.steps,
            finished=run.finished,
            last_eval_mean=run.evaluations[-1].mean if run.evaluations else None,
        )
        for run, configuration in runs
        if is_atari(run.config.env)
    ]


def on_track_row(
    run_dir: Path,
    game: str,
    configuration: str,
    curve: ReferenceCurve | None,
    *,
    steps: int,
    finished: bool,
    last_eval_mean: float | None,
) -> OnTrackRow:
    """One run's row, from its episodes.csv and what the caller knows of it (`steps`: of
    its newest checkpoint or logs, whichever it read; the larger of that and the logs'
    counts)."""
    frames, logged_steps, windows = training_windows(run_dir)
    window = max(windows) if windows else None
    score = reference = low = high = None
    games = 0
    why = None
    if window is not None:
        games = len(windows[window])
        score = float(np.mean(windows[window]))
    if window is None:
        why = "no training game has ended yet"
    elif curve is None:
        why = f"the reference has no curve for {game}"
    elif window >= curve.windows:
        why = f"the reference ends at {curve.windows}M frames"
    else:
        reference = float(curve.mean[window])
        low, high = float(curve.low[window]), float(curve.high[window])
    return OnTrackRow(
        run_dir=run_dir,
        game=game,
        configuration=configuration,
        frames=frames,
        steps=max(logged_steps, steps),
        finished=finished,
        window=window,
        window_complete=window is not None and frames >= (window + 1) * WINDOW_FRAMES,
        games=games,
        score=score,
        reference_mean=reference,
        reference_low=low,
        reference_high=high,
        verdict=None if score is None or low is None or high is None else verdict(score, low, high),
        last_eval_mean=last_eval_mean,
        why_none=why,
    )
