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

from dqnlab.analysis.report.reference import (
    AGENTS,
    REFERENCE_PROTOCOL,
    WINDOW_FRAMES,
    ReferenceCurve,
)
from dqnlab.analysis.report.runs import Group, PeriodicEvaluation, RunResults


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
    # Nature Fig. 2's held-out figures at each step, the mean over the seeds that logged
    # them (None where none did; the whole tuple None when no seed ever did).
    heldout_max_q: tuple[float | None, ...] | None = None
    heldout_td_error: tuple[float | None, ...] | None = None

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
    # The same factor over all the game's evaluations, always measured: it places the
    # reference curve (in frames) on the steps axis.
    measured_frames_per_step: float = 1.0
    # Dopamine's curves of the agents the configurations match, by agent (a key of
    # reference.AGENTS), each drawn once behind the lines.
    references: dict[str, ReferenceCurve] = field(default_factory=dict)
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
        max_q: dict[int, list[float]] = {}
        td_error: dict[int, list[float]] = {}
        for run in runs:
            for point in run.evaluations:
                by_step.setdefault(point.step, []).append(point.mean)
                if point.heldout_max_q is not None and point.heldout_td_error is not None:
                    max_q.setdefault(point.step, []).append(point.heldout_max_q)
                    td_error.setdefault(point.step, []).append(point.heldout_td_error)
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
            heldout_max_q=_means_at(steps, max_q),
            heldout_td_error=_means_at(steps, td_error),
        )
        curves.setdefault(group.env, Curve(group.env, [], None)).series.append(series)
    for curve in curves.values():
        points = {  # each configuration's evaluations
            group.label: [p for run in group.runs for p in run.evaluations]
            for group in groups
            if group.env == curve.game
        }
        ratios = [_frames_per_step(p) for p in points.values() if p]
        curve.measured_frames_per_step = _frames_per_step([p for ps in points.values() for p in ps])
        # One top axis fits every line only if the configurations agree (they do not when
        # they differ in action_repeat_frames, say): otherwise steps alone.
        if any(ratio != 1.0 for ratio in ratios) and max(ratios) <= 1.05 * min(ratios):
            curve.frames_per_step = _frames_per_step([p for ps in points.values() for p in ps])
    return list(curves.values())


def _frames_per_step(points: Sequence[PeriodicEvaluation]) -> float:
    return sum(p.frames for p in points) / sum(p.step for p in points)


def _means_at(
    steps: Sequence[int], values: dict[int, list[float]]
) -> tuple[float | None, ...] | None:
    if not values:
        return None
    return tuple(float(np.mean(values[step])) if step in values else None for step in steps)


def curve_notes(
    runs: Sequence[RunResults], groups: Sequence[Group], curves: Sequence[Curve]
) -> list[str]:
    """What the report says of the curves: the runs that have none and why, the
    evaluations that finished no game, the games with no figure."""
    notes = []
    unevaluated = [run for run in runs if run.config.eval_period_steps == 0]
    if unevaluated:
        notes.append(
            f"{len(unevaluated)} run(s) with eval_period_steps = 0 (Atari 100k's protocol "
            "scores the last network alone): no periodic evaluation, no learning curve"
        )
    for group in groups:
        for run in group.runs:
            if run.config.eval_period_steps == 0:
                continue
            if not run.evaluations:
                notes.append(
                    f"{run.run_dir}: no periodic evaluation yet (evaluations.csv has no "
                    "rows): it has no learning curve"
                )
            elif any(point.episodes == 0 for point in run.evaluations):
                empty = sum(point.episodes == 0 for point in run.evaluations)
                notes.append(
                    f"{run.run_dir}: {empty} periodic evaluation(s) finished no game within "
                    "eval_steps; the curve shows 0 there (DeepMind's Lua convention)"
                )
    evaluated_periodically = [g for g in groups if any(r.config.eval_period_steps for r in g.runs)]
    games = list(dict.fromkeys(group.env for group in evaluated_periodically))
    for game in games:
        if not any(curve.game == game for curve in curves):
            notes.append(f"{game}: no run has a periodic evaluation yet: no figure")
    return notes


def curve_figure(curve: Curve) -> Figure:
    """The figure of one game: mean score of the periodic evaluations against training
    steps (bottom) and frames (top), a line per configuration, shaded min–max over seeds;
    behind them the curve of each agent in `references`; under them, where the runs logged
    them, Nature Fig. 2's held-out figures (mean max-Q, mean |TD error|)."""
    heldout = [series for series in curve.series if series.heldout_max_q is not None]
    figure = Figure(figsize=(7.0, 7.5 if heldout else 4.5), layout="constrained")
    if heldout:
        axes, q_axes, td_axes = figure.subplots(
            3, 1, sharex=True, gridspec_kw={"height_ratios": [3, 1.4, 1.4]}
        )
    else:
        axes = figure.add_subplot()
    colors = _draw_series(axes, curve)
    for reference in curve.references.values():
        _draw_reference(axes, curve, reference)
    axes.set_title(curve.game)
    axes.set_ylabel("mean score per game (periodic evaluation)")
    bottom = axes
    if heldout:
        _draw_heldout(q_axes, td_axes, heldout, colors)
        bottom = td_axes
    bottom.set_xlabel("training steps (agent decisions)")
    bottom.xaxis.set_major_formatter(FuncFormatter(lambda value, _: _count_text(value)))
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


def _draw_series(axes: Any, curve: Curve) -> dict[str, str]:
    """Each configuration's mean line and, with several seeds, its min–max band; the colour
    of each configuration's line."""
    colors = {}
    for series in curve.series:
        (line,) = axes.plot(
            series.steps,
            series.mean,
            marker="o" if len(series.steps) <= 30 else None,
            markersize=3,
            label=series.legend_label,
        )
        colors[series.label] = line.get_color()
        if series.low is not None and series.high is not None:
            axes.fill_between(
                series.steps,
                series.low,
                series.high,
                color=line.get_color(),
                alpha=0.2,
                linewidth=0,
            )
    return colors


def _draw_heldout(
    q_axes: Any, td_axes: Any, heldout: Sequence[CurveSeries], colors: dict[str, str]
) -> None:
    """Nature Fig. 2's held-out mean max-Q and mean |TD error| of each series that logged
    them, in its line's colour, where it logged them."""
    for panel, name, label in (
        (q_axes, "heldout_max_q", "held-out mean max Q"),
        (td_axes, "heldout_td_error", "held-out mean |TD error|"),
    ):
        for series in heldout:
            points = [
                (step, value)
                for step, value in zip(series.steps, getattr(series, name), strict=True)
                if value is not None
            ]
            panel.plot(
                [step for step, _ in points],
                [value for _, value in points],
                marker="o" if len(points) <= 30 else None,
                markersize=3,
                color=colors[series.label],
            )
        panel.set_ylabel(label, fontsize="small")
        panel.grid(alpha=0.3)
    q_axes.set_title(
        "Nature Fig. 2: held-out transitions drawn once at replay start (Lua valid_size)",
        fontsize="small",
    )


def _draw_reference(axes: Any, curve: Curve, reference: ReferenceCurve) -> None:
    """An agent's mean and min–max band in each 1M-frame window (a step each: its value is
    the mean over the window's games), placed on the steps axis with the game's measured
    frames per step, over the windows the runs have reached, in the agent's colour."""
    agent = AGENTS[reference.agent]
    last_step = max(max(series.steps) for series in curve.series)
    ratio = curve.measured_frames_per_step
    windows = min(reference.windows, max(1, int(np.ceil(last_step * ratio / WINDOW_FRAMES))))
    edges = np.arange(windows + 1) * WINDOW_FRAMES / ratio

    def stepped(values: np.ndarray) -> np.ndarray:
        return np.append(values[:windows], values[windows - 1])

    axes.fill_between(
        edges, stepped(reference.low), stepped(reference.high), step="post",
        color=agent.color, alpha=0.15, linewidth=0,
    )  # fmt: skip
    axes.step(
        edges, stepped(reference.mean), where="post", color=agent.color,
        linestyle=agent.linestyle, linewidth=1.2, label=reference_legend(reference),
    )  # fmt: skip
    axes.set_xlim(0, last_step * 1.03)


def reference_legend(reference: ReferenceCurve) -> str:
    """The legend of an agent's curve: its name, what is drawn, its protocol."""
    name = AGENTS[reference.agent].name
    return f"{name}: mean of {reference.runs} runs, band min–max\n{REFERENCE_PROTOCOL}"


def _count_text(value: float) -> str:
    """50000000 -> 50M, 250000 -> 250k: axis ticks in the units budgets are spoken in."""
    for size, suffix in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if abs(value) >= size:
            return f"{value / size:g}{suffix}"
    return f"{value:g}"
