"""The figures of the aggregates across games: each statistic's interval per
configuration, and the performance profiles (`aggregate.py` computes them)."""

from __future__ import annotations

from matplotlib.figure import Figure

from dqnlab.analysis.report.aggregate import (
    HUMAN_PERCENT,
    STATISTIC_NAMES,
    STATISTICS,
    Aggregates,
)


def interval_figure(aggregates: Aggregates) -> Figure:
    """The four aggregates side by side: per configuration, a bar from the lower to the
    upper bound of the interval and a tick at the estimate."""
    names = [item.configuration for item in aggregates.configurations]
    figure = Figure(figsize=(11.0, 1.6 + 0.45 * len(names)), layout="constrained")
    panels = figure.subplots(1, len(STATISTICS), sharey=True, squeeze=False)[0]
    for axes, statistic in zip(panels, STATISTICS, strict=True):
        for index, item in enumerate(aggregates.configurations):
            interval = item.statistic(statistic)
            color = f"C{index}"
            axes.barh(
                index,
                interval.high - interval.low,
                left=interval.low,
                height=0.6,
                color=color,
                alpha=0.4,
                gid=f"interval-{statistic}-{index}",
            )
            axes.vlines(interval.estimate, index - 0.3, index + 0.3, colors=color, linewidth=2)
        title = STATISTIC_NAMES[statistic]
        lower = " (lower is better)" if statistic == "optimality_gap" else ""
        axes.set_title(title + lower, fontsize="medium")
        axes.set_xlabel(f"HNS % ({aggregates.baseline_name})")
        axes.grid(axis="x", alpha=0.3)
    panels[0].set_yticks(range(len(names)), names)
    panels[0].invert_yaxis()  # the first configuration on top, as in the tables
    figure.suptitle(
        f"Human-normalised score across {len(aggregates.games)} games, % of "
        f"{aggregates.baseline_name}\ntick: estimate; bar: {aggregates.bootstrap_text}",
        fontsize="medium",
    )
    return figure


def profile_figure(aggregates: Aggregates) -> Figure:
    """Performance profiles: per configuration, the fraction of runs scoring above each
    threshold, shaded over its interval, and the human score marked."""
    figure = Figure(figsize=(7.0, 4.5), layout="constrained")
    axes = figure.add_subplot()
    for index, (profile, item) in enumerate(
        zip(aggregates.profiles, aggregates.configurations, strict=True)
    ):
        runs = item.seeds_per_game * len(aggregates.games)
        (line,) = axes.plot(
            aggregates.thresholds,
            profile.fraction,
            color=f"C{index}",
            label=f"{profile.configuration} ({runs} runs)",
            gid=f"profile-{index}",
        )
        axes.fill_between(
            aggregates.thresholds,
            profile.low,
            profile.high,
            color=line.get_color(),
            alpha=0.2,
            linewidth=0,
        )
    axes.axvline(HUMAN_PERCENT, color="grey", linestyle=":", label=aggregates.baseline_name)
    axes.set_xlabel(f"human-normalised score τ, % of {aggregates.baseline_name}")
    axes.set_ylabel("fraction of runs with score > τ")
    axes.set_ylim(-0.02, 1.02)
    axes.grid(alpha=0.3)
    axes.set_title(
        f"Performance profiles over {len(aggregates.games)} games\n"
        f"shaded: {aggregates.bootstrap_text}",
        fontsize="medium",
    )
    axes.legend(fontsize="small", loc="best")
    return figure
