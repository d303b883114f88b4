"""A Q-value inspection into a directory: `inspect_run` compares the networks
(`qvalues.compare_networks`) and writes a figure per frame (`figures.py`), an overview,
q_values.csv and the inputs, which a later inspection can take again to compare other
networks on exactly those frames. The only module of the inspection with side effects.
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from dqnlab.analysis.inspection.figures import frame_figure, overview_figure
from dqnlab.analysis.inspection.qvalues import (
    CHECKPOINT_NAMES,
    DEFAULT_FRAMES,
    DEFAULT_MAX_GAME_STEPS,
    OBSERVATIONS_FILE,
    SCREENS_FILE,
    Inspection,
    compare_networks,
)

Q_VALUES_FILE = "q_values.csv"
OVERVIEW_FILE = "overview.png"
OVERVIEW_MAX_FRAMES = 16  # a row per frame: more would make an unreadably tall image
CSV_COLUMNS = (
    "frame", "network", "checkpoint_step", "eval_mean", "action_index", "action_name",
    "q_value", "is_argmax",
)  # fmt: skip


def inspect_run(
    run_dir: Path,
    out_dir: Path,
    *,
    frames: int = DEFAULT_FRAMES,
    checkpoints: Sequence[str | int] = CHECKPOINT_NAMES,
    observations: Path | None = None,
    seed: int = 0,
    device: torch.device | None = None,
    max_game_steps: int = DEFAULT_MAX_GAME_STEPS,
) -> Inspection:
    """Compare the Q-values of the run's `checkpoints` on the same frames
    (`qvalues.compare_networks`, which says which frames), and write into `out_dir` a figure
    per frame (frame-000.png, ...; older ones removed), an overview of up to 16 frames,
    q_values.csv, observations.npy and, for Atari, screens.npy."""
    inspection = compare_networks(
        run_dir, frames=frames, checkpoints=checkpoints, observations=observations, seed=seed,
        device=device, max_game_steps=max_game_steps,
    )  # fmt: skip
    write_inspection(inspection, out_dir)
    return inspection


def write_inspection(inspection: Inspection, out_dir: Path) -> None:
    """Write the figures, the CSV and the inputs; their paths are set in `inspection`."""
    out_dir.mkdir(parents=True, exist_ok=True)
    for old in out_dir.glob("frame-*.png"):
        old.unlink()
    inspection.figure_paths = []
    for frame in range(len(inspection.observations)):
        path = out_dir / f"frame-{frame:03d}.png"
        frame_figure(inspection, frame).savefig(path, dpi=100)
        inspection.figure_paths.append(path)
    overview = out_dir / OVERVIEW_FILE
    overview.unlink(missing_ok=True)
    inspection.overview_path = None
    if len(inspection.observations) <= OVERVIEW_MAX_FRAMES:
        overview_figure(inspection).savefig(overview, dpi=80)
        inspection.overview_path = overview
    inspection.csv_path = out_dir / Q_VALUES_FILE
    write_q_values_csv(inspection, inspection.csv_path)
    inspection.observations_path = out_dir / OBSERVATIONS_FILE
    np.save(inspection.observations_path, inspection.observations, allow_pickle=False)
    screens_path = out_dir / SCREENS_FILE
    screens_path.unlink(missing_ok=True)
    inspection.screens_path = None
    if inspection.screens is not None:
        np.save(screens_path, inspection.screens, allow_pickle=False)
        inspection.screens_path = screens_path


def write_q_values_csv(inspection: Inspection, path: Path) -> None:
    """A row per frame, network and action; Q-values written exactly (float32 round-trips)."""
    greedy = inspection.greedy_actions
    with path.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(CSV_COLUMNS)
        for frame in range(inspection.q_values.shape[1]):
            for k, network in enumerate(inspection.networks):
                for action, name in enumerate(inspection.action_names):
                    writer.writerow(
                        (
                            frame,
                            network.name,
                            network.step,
                            repr(network.eval_mean),
                            action,
                            name,
                            repr(float(inspection.q_values[k, frame, action])),
                            int(greedy[k, frame] == action),
                        )
                    )
