"""Learning curves: the periodic evaluations of each configuration against training
steps, a figure per game. Drawing only: `write.py` saves the figures.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter

from dqnlab.tools.report.runs import Group, PeriodicEvaluation


@dataclass(frozen=True)
class CurveSeries:
    """One configuration's line: at each evaluation step, the mean over the seeds that
    have an evaluation there, and their lowest and highest (several seeds only)."""

    label: str
    seeds: int  # runs with at least one periodic evaluation
    steps: tuple[int, ...]
    mean: tuple[float, ...]
    low: tuple[float, ...] | None
    high: tuple[float, ...] | None
    seeds_at_step: tuple[int, ...]

    @property
    def legend_label(self) -> str:
        return f"{self.label} ({self.seeds} seed{'s' if self.seeds > 1 else ''})"


@dataclass
class Curve:
    """One game's figure."""

    game: str
    series: list[CurveSeries]
    # Training frames per agent step for the top axis, from the runs' evaluations.csv;
    # None where a frame is a step (non-Atari environments).
    frames_per_step: float | None
    files: list[Path] = field(default_factory=list)


def learning_curves(groups: Sequence[Group]) -> list[Curve]:
    """One curve per game with a periodic evaluation, one series per group that has one.

    The top axis converts steps to frames with one factor per game, the frames of all its
    evaluations over their steps: an Atari step is `action_repeat_frames` frames, plus
    the no-op frames of each episode start and minus the frames a game over cuts short,
    so the factor is measured rather than assumed. No top axis where a frame is a step,
    or where the configurations' factors differ by more than 5%."""
    curves: dict[str, Curve] = {}
    for group in groups:
        runs = [run for run in group.runs if run.evaluations]
        if not runs:
            continue
        by_step: dict[int, list[float]] = {}
        for run in runs:
            for point in run.evaluations:
                by_step.setdefault(point.step, []).append(point.mean)
        steps = sorted(by_step)
        values = [np.array(by_step[step]) for step in steps]
        several = len(runs) >= 2
        series = CurveSeries(
            label=group.label,
            seeds=len(runs),
            steps=tuple(steps),
            mean=tuple(float(v.mean()) for v in values),
            low=tuple(float(v.min()) for v in values) if several else None,
            high=tuple(float(v.max()) for v in values) if several else None,
            seeds_at_step=tuple(len(v) for v in values),
        )
        curves.setdefault(group.env, Curve(group.env, [], None)).series.append(series)
    for curve in curves.values():
        points = {  # each configuration's evaluations
            group.label: [p for run in group.runs for p in run.evaluations]
            for group in groups
            if group.env == curve.game
        }
        ratios = [_frames_per_step(p) for p in points.values() if p]
        # One top axis fits every line only if the configurations agree (they do not when
        # they differ in action_repeat_frames, say): otherwise steps alone.
        if any(ratio != 1.0 for ratio in ratios) and max(ratios) <= 1.05 * min(ratios):
            curve.frames_per_step = _frames_per_step([p for ps in points.values() for p in ps])
    return list(curves.values())


def _frames_per_step(points: Sequence[PeriodicEvaluation]) -> float:
    return sum(p.frames for p in points) / sum(p.step for p in points)


def curve_figure(curve: Curve) -> Figure:
    """The figure of one game: mean score of the periodic evaluations against training
    steps (bottom) and frames (top), a line per configuration, shaded min–max over seeds."""
    figure = Figure(figsize=(7.0, 4.5), layout="constrained")
    axes = figure.add_subplot()
    for series in curve.series:
        (line,) = axes.plot(
            series.steps,
            series.mean,
            marker="o" if len(series.steps) <= 30 else None,
            markersize=3,
            label=series.legend_label,
        )
        if series.low is not None and series.high is not None:
            axes.fill_between(
                series.steps,
                series.low,
                series.high,
                color=line.get_color(),
                alpha=0.2,
                linewidth=0,
            )
    axes.set_title(curve.game)
    axes.set_xlabel("training steps (agent decisions)")
    axes.set_ylabel("mean score per game (periodic evaluation)")
    axes.xaxis.set_major_formatter(FuncFormatter(lambda value, _: _count_text(value)))
    axes.grid(alpha=0.3)
    if curve.frames_per_step is not None:
        ratio = curve.frames_per_step

        def to_frames(steps: Any) -> Any:
            return np.asarray(steps) * ratio

        def to_steps(frames: Any) -> Any:
            return np.asarray(frames) / ratio

        top = axes.secondary_xaxis("top", functions=(to_frames, to_steps))
        top.set_xlabel(f"training frames (≈ {ratio:.2f} per step, measured)")
        top.xaxis.set_major_formatter(FuncFormatter(lambda value, _: _count_text(value)))
    banded = any(series.low is not None for series in curve.series)
    axes.legend(
        title="line: mean over seeds; shaded: min–max over seeds" if banded else None,
        title_fontsize="small",
        fontsize="small",
        loc="best",
    )
    return figure


def _count_text(value: float) -> str:
    """50000000 -> 50M, 250000 -> 250k: axis ticks in the units budgets are spoken in."""
    for size, suffix in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if abs(value) >= size:
            return f"{value / size:g}{suffix}"
    return f"{value:g}"
