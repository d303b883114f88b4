"""The inspection's figures from Q-values given by hand: a bar per action and network, the
greedy one hatched, a legend naming each network."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dqnlab.analysis.inspection.figures import Q_VALUES_AXES, frame_figure, overview_figure
from dqnlab.analysis.inspection.qvalues import InspectedNetwork, Inspection


def _inspection() -> Inspection:
    networks = [
        InspectedNetwork("best", Path("best.pt"), 500, 21.0),
        InspectedNetwork("worst", Path("worst.pt"), 900, -3.0),
    ]
    q_values = np.array([[[0.1, 0.9, 0.2], [0.5, 0.1, 0.0]], [[0.3, 0.2, 0.8], [0.0, 0.0, 0.4]]])
    return Inspection(
        env="CartPole-v1",
        action_names=["NOOP", "LEFT", "RIGHT"],
        networks=networks,
        observations=np.zeros((2, 4, 4), np.float32),
        screens=None,
        game_steps=[10, 30],
        q_values=q_values.astype(np.float32),
        note="two frames",
    )


def test_the_greedy_action_of_each_network_is_hatched() -> None:
    inspection = _inspection()
    figure = frame_figure(inspection, 0)
    (axes,) = [a for a in figure.axes if a.get_label() == Q_VALUES_AXES]
    bars = list(axes.patches)
    hatched = [i for i, bar in enumerate(bars) if bar.get_hatch()]
    assert hatched == [1, 5]  # best: LEFT (its 2nd bar); worst: RIGHT (3rd of its 3)
    labels = [text.get_text() for text in axes.get_legend().get_texts()]
    assert labels[0] == "best (step 500, eval mean 21.0)" and "greedy" in labels[-1]
    assert "frame 0, game step 10" in figure.get_suptitle()


def test_the_overview_has_a_row_per_frame() -> None:
    figure = overview_figure(_inspection())
    assert len([a for a in figure.axes if a.get_label() == Q_VALUES_AXES]) == 2
