"""How well does each Atari game's frames compress under LZ4, the replay's codec? Answered
once for all 57 games by random play (2026-12-01): the table the replay's memory check
reads, `src/dqnlab/data/replay_compression.csv`, and docs/benchmark.md, "How much memory
does a run take, and what does the compressed replay save?" (#compressed-replay). Run:
`python scripts/compression_scan.py src/dqnlab/data/replay_compression.csv --steps 16384`
(a row is written as each game is measured).
"""

from __future__ import annotations

import csv
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer

from dqnlab.algorithm.compression import CHUNK_SLOTS, CompressedFrames
from dqnlab.algorithm.replay import ReplayMemory
from dqnlab.bench.compression import fill_by_random_play
from dqnlab.cli.common import run_command
from dqnlab.config import resolve_config


def scan(
    games: Iterable[str], steps: int, seed: int = 0, chunk_slots: int = CHUNK_SLOTS
) -> list[dict[str, Any]]:
    """Per game: the compressed bytes per frame of `steps` frames of random play (whole
    chunks only; `steps` is rounded up to a whole chunk)."""
    chunks = -(-steps // chunk_slots)
    rows = []
    for game in games:
        config = resolve_config("nature", env=game, seed=seed)
        capacity = chunks * chunk_slots
        replay = ReplayMemory(
            capacity + 1, (config.screen_size,) * 2, np.uint8, config.history_length, 1, seed,
            compression="lz4", chunk_slots=chunk_slots,
        )  # fmt: skip
        fill_by_random_play([replay], config, capacity, seed)
        frames = replay.frames
        assert isinstance(frames, CompressedFrames)
        per_frame = frames.sealed_bytes / frames.sealed_slots
        rows.append(
            {
                "game": game,
                "lz4_bytes_per_frame": round(per_frame, 1),
                "ratio": round(frames.frame_bytes / per_frame, 2),
                "frames_measured": frames.sealed_slots,
            }
        )
    return rows


def write_scan(path: Path, steps: int, echo: Callable[[str], Any] = print) -> None:
    """`scan` of every Atari-57 game into the CSV at `path`, under a comment line giving
    the command, a row written (and echoed) as each game is measured."""
    from dqnlab.analysis.report.scores import load_reference_scores  # the 57 games

    games = sorted(load_reference_scores())
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as handle:
        handle.write(f"# python scripts/compression_scan.py {path} --steps {steps}\n")
        writer = None
        for row in (scan([game], steps)[0] for game in games):
            if writer is None:
                writer = csv.DictWriter(handle, fieldnames=list(row))
                writer.writeheader()
            writer.writerow(row)
            handle.flush()
            echo(f"{row['game']:24s} {row['lz4_bytes_per_frame']:8.1f} B/frame  x{row['ratio']}")


app = typer.Typer(add_completion=False, pretty_exceptions_enable=False)


@app.command()
def main(
    path: Annotated[Path, typer.Argument(help="The CSV to write")],
    steps: Annotated[int, typer.Option(help="Frames of random play per game")] = 16_384,
) -> None:
    """Each Atari-57 game's compressed frame size (LZ4, blocks of 4 frames) under the
    random policy, into a CSV: the table of src/dqnlab/data/replay_compression.csv."""
    write_scan(path, steps, echo=typer.echo)


if __name__ == "__main__":
    run_command(app)
