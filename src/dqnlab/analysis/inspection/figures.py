"""The figures of a Q-value inspection: a frame beside each network's Q-value per action,
each network's greedy action hatched, and an overview of several frames."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.patches import Patch

if TYPE_CHECKING:
    from dqnlab.analysis.inspection.qvalues import Inspection

Q_VALUES_AXES = "q_values"  # the label of the bar chart's axes in a figure
_GREEDY_HATCH = "//"


def frame_figure(inspection: Inspection, frame: int) -> Figure:
    """The frame (its screen, or the network's newest input) beside a grouped bar chart
    of each network's Q-value per action, each network's greedy action hatched."""
    figure = Figure(figsize=(11.0, 4.2), layout="constrained")
    left, right = figure.subplots(1, 2, width_ratios=(1, 2.2))
    right.set_label(Q_VALUES_AXES)
    _draw_frame(left, inspection, frame)
    _draw_q_values(right, inspection, frame, legend=True)
    figure.suptitle(_frame_title(inspection, frame))
    return figure


def overview_figure(inspection: Inspection) -> Figure:
    """All frames, a row each: the frame and its Q-values (the legend on the first row)."""
    count = len(inspection.observations)
    figure = Figure(figsize=(11.0, 2.8 * count + 0.6), layout="constrained")
    rows = figure.subplots(count, 2, width_ratios=(1, 2.2), squeeze=False)
    for frame, (left, right) in enumerate(rows):
        right.set_label(Q_VALUES_AXES)
        _draw_frame(left, inspection, frame)
        _draw_q_values(right, inspection, frame, legend=frame == 0)
        right.set_title(_frame_title(inspection, frame), fontsize="small")
    figure.suptitle(f"{inspection.env}: Q-values per action ({inspection.note})", fontsize="small")
    return figure


def _frame_title(inspection: Inspection, frame: int) -> str:
    where = f", game step {inspection.game_steps[frame]}" if inspection.game_steps else ""
    return f"{inspection.env}: frame {frame}{where}"


def _draw_frame(axes: Axes, inspection: Inspection, frame: int) -> None:
    """The screen when there is one; else the newest observation: its image, or its
    values as bars. A packed observation (`envs/spaces.py`) is unpacked first: its first
    image part is drawn if it has one, else all its values, labelled by part."""
    newest = inspection.observations[frame, -1]
    layout = inspection.layout
    if inspection.screens is not None:
        axes.imshow(inspection.screens[frame], interpolation="nearest")
        axes.set_title("screen", fontsize="small")
        axes.set_axis_off()
        return
    if layout is not None and layout.packed:
        parts = layout.unpack(newest)
        images = [(part, value) for part, value in parts if part.kind == "image"]
        if images:
            part, value = images[0]
            if part.channels_last and value.ndim == 3:
                value = np.moveaxis(value, -1, 0)
            _draw_image(
                axes, value.astype(np.float64), f"newest observation: {part.path or 'image'}"
            )
            return
        labels = [f"{part.path or 'obs'}[{i}]" for part, value in parts for i in range(value.size)]
        values = np.concatenate([value.astype(np.float64).ravel() for _, value in parts])
        _draw_values(axes, values, labels)
    elif newest.ndim >= 2:
        _draw_image(axes, newest, "network input, newest frame")
    else:
        values = np.asarray(newest, dtype=np.float64).ravel()
        _draw_values(axes, values, [f"[{i}]" for i in range(len(values))])


def _draw_image(axes: Axes, planes: np.ndarray, title: str) -> None:
    """An image stored channels-first (or without channels): RGB when it has three
    channels, else its first channel in grey."""
    image = planes if planes.ndim == 2 else np.moveaxis(planes, 0, -1)
    if image.ndim == 3 and image.shape[-1] != 3:
        image = image[..., 0]
    axes.imshow(image, cmap="gray" if image.ndim == 2 else None, interpolation="nearest")
    axes.set_title(title, fontsize="small")
    axes.set_axis_off()


def _draw_values(axes: Axes, values: np.ndarray, labels: list[str]) -> None:
    positions = np.arange(len(values))
    axes.barh(positions, values, color="0.5")
    ticks = [f"{label} {value:.3g}" for label, value in zip(labels, values, strict=True)]
    axes.set_yticks(positions, ticks)
    axes.invert_yaxis()
    axes.axvline(0.0, color="black", linewidth=0.6)
    axes.set_title("newest observation", fontsize="small")


def _draw_q_values(axes: Axes, inspection: Inspection, frame: int, legend: bool) -> None:
    count = len(inspection.networks)
    positions = np.arange(len(inspection.action_names))
    width = 0.8 / count
    greedy = inspection.greedy_actions
    for k in range(count):
        offset = (k - (count - 1) / 2) * width
        bars = axes.bar(positions + offset, inspection.q_values[k, frame], width, color=f"C{k}")
        chosen = bars.patches[int(greedy[k, frame])]
        chosen.set_hatch(_GREEDY_HATCH)
        chosen.set_edgecolor("black")
        chosen.set_linewidth(1.5)
    many = len(positions) > 8
    axes.set_xticks(
        positions,
        inspection.action_names,
        rotation=45 if many else 0,
        ha="right" if many else "center",
    )
    axes.set_xlabel("action")
    axes.axhline(0.0, color="black", linewidth=0.6)
    axes.set_ylabel("Q-value")
    axes.grid(axis="y", alpha=0.3)
    if legend:
        # Handles of their own: a network's first bar may be its hatched greedy one.
        handles = [
            Patch(facecolor=f"C{k}", label=network.legend_label)
            for k, network in enumerate(inspection.networks)
        ]
        handles.append(
            Patch(
                facecolor="white",
                edgecolor="black",
                hatch=_GREEDY_HATCH,
                label="greedy action (highest Q)",
            )
        )
        axes.legend(handles=handles, fontsize="small", loc="best")
