"""Published learning curves to compare a run with, and the "on track?" verdict.

The references are Dopamine's published curves (`data/README.md`): DQN
(`data/dopamine_dqn_curves.csv`) and, for the DQN family, C51 and its compact Rainbow
(`data/dopamine_variant_curves.csv.gz`, which also holds IQN and QR-DQN, agents dqnlab does
not have). Each is 5 runs per game, a mean raw score of the training games that ended in
each 1M-frame iteration, 199 iterations. Each run is compared with the agent whose update
is made of the same parts (`reference_agent`), or with none. Dopamine's protocol is not the
Nature one (sticky actions, training returns at ε = 0.01, no life-loss signal): every
figure and table says so. A run is measured the way the reference is (its training games,
`episodes.csv`, in the same 1M-frame windows), so that its latest window can be set beside
the reference's mean and range at the same frames, hours into a three-day run.

Reading only: nothing here writes a file or plays a game.
"""

from __future__ import annotations

import csv
import functools
import gzip
import io
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from dqnlab.analysis.report.runs import Group, RunResults
from dqnlab.config import USER_PARTS, Config
from dqnlab.envs import is_atari
from dqnlab.run import rundir
from dqnlab.run.logs import read_csv

WINDOW_FRAMES = 1_000_000  # one Dopamine iteration: 250,000 agent steps of 4 frames
REFERENCES = ("dopamine", "der-paper", "none")  # der-paper: the Atari 100k table (atari100k.py)
REFERENCE_PROTOCOL = "training games (sticky actions, ε = 0.01): not the Nature protocol"
VERDICTS = ("below the range", "within the range", "above the range")
DQN_FILE = "dopamine_dqn_curves.csv"  # game,iteration,run,train_return: the agent is dqn
VARIANT_FILE = "dopamine_variant_curves.csv.gz"  # agent,game,iteration,run,train_return


@dataclass(frozen=True)
class ReferenceAgent:
    """One of Dopamine's agents a run can be compared with, as figures and tables show it."""

    key: str  # the agent's name in the data files ("dqn": the DQN file's)
    name: str
    color: str  # of its line and band: none of matplotlib's default cycle, which the runs take
    linestyle: str
    file: str  # in dqnlab/data


AGENTS = {
    agent.key: agent
    for agent in (
        ReferenceAgent("dqn", "Dopamine DQN", "0.35", "--", DQN_FILE),
        ReferenceAgent("c51", "Dopamine C51", "darkgoldenrod", ":", VARIANT_FILE),
        ReferenceAgent(
            "rainbow", "Dopamine Rainbow (compact: C51, 3-step, prioritized)", "teal", "-.",
            VARIANT_FILE,
        ),
        ReferenceAgent(
            "quantile", "Dopamine QR-DQN (3-step, prioritized)", "indigo", "-.", VARIANT_FILE
        ),
        ReferenceAgent("iqn", "Dopamine IQN (3-step)", "darkslategray", ":", VARIANT_FILE),
    )
}  # fmt: skip
# The shipped quantile parts (`algorithm/quantile.py`: head, loss) and Dopamine's agent of
# the same update, with the parts of Rainbow's regime its curves were trained with.
QUANTILE_AGENTS = {
    ("dqnlab.algorithm.quantile:quantile_head", "dqnlab.algorithm.quantile:QuantileLoss"): (
        "quantile",
        ("3-step returns", "prioritized replay"),
    ),
    (
        "dqnlab.algorithm.quantile:implicit_quantile_head",
        "dqnlab.algorithm.quantile:ImplicitQuantileLoss",
    ): ("iqn", ("3-step returns",)),
}


# Which agent matches a run -------------------------------------------------------------


@dataclass(frozen=True)
class ReferenceMatch:
    """The agent a configuration is compared with, or why none."""

    agent: str | None  # a key of AGENTS
    why_none: str | None = None  # when agent is None
    caveat: str | None = None  # what the match leaves out (a full Rainbow against the compact)


def reference_agent(config: Config) -> ReferenceMatch:
    """Dopamine's agent whose update has the parts of `config`'s, the only one whose curve
    says whether the run learns as that update should.

    - `dqn`: the Nature DQN's parts (target max, one-step returns, no distribution, no
      dueling head, no noisy layers, uniform replay, dqnlab's own loss and torso). The
      settings of the Nature era (optimizer, sticky actions, epsilon, episode caps,
      network) leave the match as it is: Dopamine's DQN already differs from the Nature
      protocol in those, and every figure and table says so.
    - `c51`: C51 alone, every other part the Nature DQN's.
    - `rainbow`: C51 with n-step returns (n > 1) and prioritized replay, which is all of
      Dopamine's compact Rainbow; with double Q-learning, a dueling head or noisy nets
      on top (the full Rainbow of the `rainbow` preset) too, as the nearest published
      curve, named compact and with a caveat saying what it lacks.
    - none for anything else: a part alone (double, dueling, noisy, prioritized, n-step),
      C51 with some of Rainbow's parts but not both of n-step and prioritized, a user's
      loss or torso. Dopamine publishes no curve for them, and setting them beside another
      agent's would credit or blame the part for what another update does.
    - `quantile`, `iqn`: the shipped QR-DQN or IQN head and loss (`qrdqn`, `iqn` presets),
      every other part the Nature DQN's or those of Dopamine's regime (3-step returns, and
      for QR-DQN prioritized replay), with a caveat naming what differs."""
    quantile = QUANTILE_AGENTS.get((config.head, config.loss))
    if quantile is not None:
        return _quantile_match(config, *quantile)
    for setting, defaults in USER_PARTS.items():
        value = getattr(config, setting)
        if value not in defaults:
            return ReferenceMatch(
                None, f"Dopamine publishes no curve for your own {setting} ({value})"
            )
    parts = family_parts(config)
    if not parts:
        return ReferenceMatch("dqn")
    if parts == ["C51"]:
        return ReferenceMatch("c51")
    if (
        config.distributional == "c51"
        and config.n_step > 1
        and config.replay_sampling == "prioritized"
    ):
        compact = ("C51", f"{config.n_step}-step returns", "prioritized replay")
        extra = [part for part in parts if part not in compact]
        caveat = None
        if extra:
            caveat = (
                "compared with Dopamine's compact Rainbow (C51, 3-step returns, prioritized "
                f"replay), without the run's {_and(extra)}"
            )
        return ReferenceMatch("rainbow", caveat=caveat)
    return ReferenceMatch(None, f"Dopamine publishes no curve for DQN + {' + '.join(parts)}")


def _quantile_match(config: Config, agent: str, dopamine: tuple[str, ...]) -> ReferenceMatch:
    """Dopamine's QR-DQN or IQN for a run of the shipped quantile parts; none when the run
    adds a part Dopamine's agent lacks (double, dueling, a user's torso...). A run without
    all of Dopamine's regime (the `qrdqn` and `iqn` presets: one-step, uniform) is compared
    with a caveat naming the difference."""
    for setting in ("torso", "policy", "augmentation"):
        value = getattr(config, setting)
        if value not in USER_PARTS[setting]:
            why = f"Dopamine publishes no curve for your own {setting} ({value})"
            return ReferenceMatch(None, why)
    run = family_parts(config)
    extra = [part for part in run if part not in dopamine and not part.endswith("-step returns")]
    name = AGENTS[agent].name
    if extra:
        short = name.split(" (")[0].removeprefix("Dopamine ")
        why = f"Dopamine publishes no curve for {short} + {_and(extra)}"
        return ReferenceMatch(None, why)
    caveat = None
    if tuple(run) != dopamine:
        has = _and(run) if run else "one-step returns and uniform replay"
        caveat = f"compared with {name}; this run has {has}"
    return ReferenceMatch(agent, caveat=caveat)


def family_parts(config: Config) -> list[str]:
    """The parts of the DQN family that `config` adds to the Nature DQN's update, named."""
    parts = []
    if config.target != "max":
        parts.append(
            "double Q-learning" if config.target == "double" else f"target {config.target}"
        )
    if config.n_step > 1:
        parts.append(f"{config.n_step}-step returns")
    if config.distributional != "none":
        parts.append(config.distributional.upper())
    if config.replay_sampling != "uniform":
        parts.append(f"{config.replay_sampling} replay")
    if config.dueling:
        parts.append("dueling head")
    if config.noisy:
        parts.append("noisy nets")
    return parts


def _and(words: Sequence[str]) -> str:
    return words[0] if len(words) == 1 else f"{', '.join(words[:-1])} and {words[-1]}"


# The published curves --------------------------------------------------------------------


@dataclass(frozen=True)
class ReferenceCurve:
    """One agent's published curve of one game: per 1M-frame window, the mean, lowest and
    highest of its runs' scores."""

    game: str  # ale-py id
    agent: str  # a key of AGENTS
    runs: int
    mean: np.ndarray  # (windows,)
    low: np.ndarray
    high: np.ndarray

    @property
    def windows(self) -> int:
        return len(self.mean)


# Per agent, per game (ale-py id): the curves a report or a status draws and compares with.
References = dict[str, dict[str, ReferenceCurve]]


def reference_key(env: str) -> str:
    """A game's name as Dopamine spells it: ale-py's `space_invaders` is `spaceinvaders`."""
    return env.lower().replace("_", "")


def load_reference_curves(games: Sequence[str], agent: str = "dqn") -> dict[str, ReferenceCurve]:
    """`agent`'s curves of those of `games` (ale-py ids) the data covers."""
    tables = _published_tables(AGENTS[agent].file)
    curves = {}
    for game in games:
        table = tables.get((agent, reference_key(game)))
        if table is not None and is_atari(game):
            curves[game] = ReferenceCurve(
                game,
                agent,
                table.shape[1],
                np.nanmean(table, axis=1),
                np.nanmin(table, axis=1),
                np.nanmax(table, axis=1),
            )
    return curves


def load_references(configs: Iterable[Config]) -> References:
    """The curves `configs` are compared with: each agent's, for the Atari games of the
    configurations it matches (`reference_agent`)."""
    games: dict[str, list[str]] = {}
    for config in configs:
        agent = reference_agent(config).agent
        if agent is not None and is_atari(config.env):
            games.setdefault(agent, []).append(config.env)
    return {agent: load_reference_curves(envs, agent) for agent, envs in games.items()}


def reference_curve(references: References, config: Config) -> ReferenceCurve | None:
    """The curve `config`'s run is compared with, if its agent has one of its game."""
    agent = reference_agent(config).agent
    return None if agent is None else references.get(agent, {}).get(config.env)


def group_references(groups: Sequence[Group], references: References) -> dict[str, ReferenceCurve]:
    """The curves to draw behind `groups` (the configurations of one game's figure): each
    matching agent's once, by agent, in the order of the configurations."""
    curves: dict[str, ReferenceCurve] = {}
    for group in groups:
        curve = reference_curve(references, group.runs[0].config)  # seeds share their parts
        if curve is not None:
            curves.setdefault(curve.agent, curve)
    return curves


def reference_notes(groups: Sequence[Group], references: References) -> list[str]:
    """What the report says of the references: the Atari configurations no agent matches
    (and why), the matches that leave parts out, the games the data does not cover."""
    notes, uncovered = [], []
    for group in groups:
        if not is_atari(group.env):
            continue
        match = reference_agent(group.runs[0].config)
        name = f"{group.env}, {group.label}"
        if match.agent is None:
            notes.append(f"{name}: {match.why_none}: no reference curve or on-track verdict")
        elif group.env not in references.get(match.agent, {}):
            uncovered.append(group.env)
        elif match.caveat is not None:
            notes.append(f"{name}: {match.caveat}")
    if uncovered:
        notes.append(
            f"Dopamine's curves do not cover {', '.join(dict.fromkeys(uncovered))}: no "
            "reference curve or verdict for them"
        )
    return notes


@functools.cache
def _published_tables(file: str) -> dict[tuple[str, str], np.ndarray]:
    """Every (agent, Dopamine game)'s scores in one data file, (iterations, runs), NaN where
    one is missing; read once (about 0.5 s for the 300,000 rows of the variants' file)."""
    data = (resources.files("dqnlab") / "data" / file).read_bytes()
    rows = csv.reader(
        io.StringIO((gzip.decompress(data) if file.endswith(".gz") else data).decode())
    )
    header = next(rows)
    agent_at = header.index("agent") if "agent" in header else None
    game_at, iteration_at, run_at, score_at = (
        header.index(name) for name in ("game", "iteration", "run", "train_return")
    )
    cells: dict[tuple[str, str], list[tuple[int, int, float]]] = {}
    for row in rows:
        key = ("dqn" if agent_at is None else row[agent_at], row[game_at])
        cell = (int(row[iteration_at]), int(row[run_at]), float(row[score_at]))
        cells.setdefault(key, []).append(cell)
    tables = {}
    for key, values in cells.items():
        iterations, runs, scores = (np.array(column) for column in zip(*values, strict=True))
        table = np.full((iterations.max() + 1, runs.max() + 1), np.nan)
        table[iterations, runs] = scores
        table.flags.writeable = False  # shared by every caller of the cache
        tables[key] = table
    return tables


# On track? -------------------------------------------------------------------------


@dataclass(frozen=True)
class OnTrackRow:
    """One run's latest 1M-frame window of training games against its agent's curve."""

    run_dir: Path
    game: str
    configuration: str
    reference: str | None  # the agent compared with (a key of AGENTS), None: no agent matches
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
    runs: Sequence[tuple[RunResults, str]], references: References
) -> list[OnTrackRow]:
    """A row per Atari run (with its configuration's label): its latest window with a
    finished training game, complete or not, against the same window of its agent's curve
    (`reference_agent`)."""
    return [
        on_track_row(
            run.run_dir,
            run.config.env,
            configuration,
            reference_agent(run.config),
            reference_curve(references, run.config),
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
    match: ReferenceMatch,
    curve: ReferenceCurve | None,
    *,
    steps: int,
    finished: bool,
    last_eval_mean: float | None,
) -> OnTrackRow:
    """One run's row, from its episodes.csv and what the caller knows of it (`match`: its
    agent, `curve`: that agent's of its game, if any; `steps`: of its newest checkpoint or
    logs, whichever it read; the larger of that and the logs' counts)."""
    frames, logged_steps, windows = training_windows(run_dir)
    window = max(windows) if windows else None
    score = reference = low = high = None
    games = 0
    why = None
    if window is not None:
        games = len(windows[window])
        score = float(np.mean(windows[window]))
    if match.agent is None:
        why = match.why_none
    elif window is None:
        why = "no training game has ended yet"
    elif curve is None:
        why = f"{AGENTS[match.agent].name} has no curve for {game}"
    elif window >= curve.windows:
        why = f"{AGENTS[match.agent].name} ends at {curve.windows}M frames"
    else:
        reference = float(curve.mean[window])
        low, high = float(curve.low[window]), float(curve.high[window])
    return OnTrackRow(
        run_dir=run_dir,
        game=game,
        configuration=configuration,
        reference=match.agent,
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
