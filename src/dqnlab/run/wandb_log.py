"""Weights & Biases, opt-in (`logger = "tensorboard+wandb"`): every scalar TensorBoard gets,
at the same step, and the resolved configuration; after training, the final evaluation,
its videos and the report's figures in the W&B run's summary.

A run keeps one W&B run: its id is saved in RUN_DIR/wandb_run.json before it starts, and
`dqnlab resume` reopens it. W&B takes each step once and never one earlier than its last,
but a resumed run logs again the steps between its checkpoint and the moment the killed
process stopped. So a session sends only the steps after the last one W&B holds
(`first_step`): its history holds every step once. Those the killed process sent keep its
values, which a resume reproduces exactly but for timings (frames per second). Steps W&B
lacks up to the checkpoint (lost by a killed process, or logged before W&B was turned on)
are sent from TensorBoard's events when the run resumes.

`wandb` is imported here alone, and only when a run asks for it: dqnlab works without it.
"""

from __future__ import annotations

import json
import logging
import os
import secrets
import string
import struct
import warnings
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from types import ModuleType
from typing import Any

from dqnlab.config import Config
from dqnlab.errors import DqnlabError
from dqnlab.run import rundir

WANDB_LOGGER = "tensorboard+wandb"  # the `logger` setting that turns W&B on
INSTALL_COMMAND = "pip install 'dqnlab[wandb]'"
VIDEO_SUFFIXES = (".mp4", ".gif")  # files sent as wandb.Video; others as wandb.Image
_RUN_ID_CHARACTERS = string.ascii_lowercase + string.digits  # what W&B accepts in an id


def uses_wandb(config: Config) -> bool:
    return config.logger == WANDB_LOGGER


def import_wandb() -> ModuleType:
    """The wandb module, or a one-line error that says how to install it."""
    try:
        import wandb
    except ImportError:
        raise DqnlabError(
            f"logger = {WANDB_LOGGER!r} needs the wandb package, which is not installed: "
            f"{INSTALL_COMMAND}"
        ) from None
    return wandb


def open_run(run_dir: Path, config: Config) -> Any:
    """The W&B run of `run_dir`: started (its id saved first, so that a resume finds it),
    or reopened where wandb_run.json names one. Its project and entity are those of its
    first session, so that a resume with other WANDB_* variables still reopens it. W&B's
    files go to RUN_DIR/wandb/, unless W&B's own WANDB_DIR says otherwise."""
    wandb = import_wandb()
    path = rundir.wandb_run_path(run_dir)
    if path.is_file():
        try:
            identity = json.loads(path.read_text())
            run_id = identity["id"]
        except (json.JSONDecodeError, KeyError, TypeError):
            raise DqnlabError(f"{path} does not name a W&B run (an object with an id)") from None
    else:
        run_id = "".join(secrets.choice(_RUN_ID_CHARACTERS) for _ in range(8))
        identity = {"id": run_id, "project": config.wandb_project}
        _write_json(path, identity)
    try:
        run = wandb.init(
            id=run_id,
            resume="allow",
            project=identity.get("project", config.wandb_project),
            entity=identity.get("entity"),
            name=run_dir.resolve().name,
            dir=None if "WANDB_DIR" in os.environ else str(run_dir),
        )
    except Exception as error:  # noqa: BLE001 - wandb raises many kinds; each is one line
        raise DqnlabError(
            f"W&B could not start run {run_id} of {run_dir}: {error} (WANDB_MODE=offline "
            "logs without a connection; `wandb sync` sends it later)"
        ) from None
    connected = run.settings.mode in ("online", "run", "shared")  # offline: no entity yet
    if connected and run.entity and identity.get("entity") != run.entity:
        _write_json(path, {**identity, "entity": run.entity})
    return run


def finish(run: Any) -> None:
    """End `run`, and W&B's service process with it: the service writes the end of a
    session's log when it shuts down, not when the run finishes (read right after
    `finish()`, a log may hold its header alone), and the next session reads it
    (`first_step`)."""
    run.finish()
    import_wandb().teardown()


def _write_json(path: Path, value: dict[str, Any]) -> None:
    temporary = path.with_name(path.name + ".tmp")
    temporary.write_text(json.dumps(value, indent=2) + "\n")
    os.replace(temporary, path)


class WandbLog:
    """A training session's W&B run: the scalars of each step gathered and sent together
    once the step is complete, and only the steps W&B does not hold yet (`first_step`).

    A step is complete when a later one is logged, and at every checkpoint (`commit`,
    which the loop reaches after all of a step's logging); not before an evaluation,
    which logs at the step of a game that may have just ended: a process killed during
    the evaluation has sent neither, and the resumed run sends both.
    """

    def __init__(self, run_dir: Path, config: Config, resume_step: int | None = None) -> None:
        self.run = open_run(run_dir, config)
        # The settings a resume may change (budget, checkpoint cadence) change here too.
        self.run.config.update(config.to_dict(), allow_val_change=True)
        self.first_step = first_step(self.run)
        if resume_step is not None and self.first_step <= resume_step:
            self._send_from_tensorboard(run_dir, resume_step)
        self._pending_step: int | None = None
        self._pending: dict[str, float] = {}

    def _send_from_tensorboard(self, run_dir: Path, last_step: int) -> None:
        """Send the steps from `first_step` to `last_step`, the checkpoint's, from the
        run's TensorBoard events: those W&B lost when a process was killed, or all before
        W&B was turned on. TensorBoard holds them (flushed before every checkpoint), as
        32-bit floats."""
        from tensorboard.backend.event_processing.event_accumulator import (
            SCALARS,
            EventAccumulator,
        )

        directory = rundir.tensorboard_dir(run_dir)
        if not directory.is_dir():
            return
        events = EventAccumulator(str(directory), size_guidance={SCALARS: 0})  # 0: keep all
        notes = logging.getLogger("tensorboard")
        level = notes.level
        notes.setLevel(logging.ERROR)  # not its warning that a resume purged steps: expected
        try:
            events.Reload()  # TensorBoard's view: what a resume purged is gone
        finally:
            notes.setLevel(level)
        rows: dict[int, dict[str, float]] = {}
        for tag in events.Tags()[SCALARS]:
            for event in events.Scalars(tag):
                if self.first_step <= event.step <= last_step:
                    rows.setdefault(event.step, {})[tag] = event.value
        for step in sorted(rows):
            self.run.log(rows[step], step=step, commit=True)
        self.first_step = last_step + 1

    def add_scalar(self, tag: str, value: float, step: int) -> None:
        if self._pending_step is not None and step != self._pending_step:
            self.commit()
        self._pending_step = step
        self._pending[tag] = float(value)

    def commit(self) -> None:
        """Send the step gathered, unless W&B holds it from a session before a resume."""
        step, values = self._pending_step, self._pending
        self._pending_step, self._pending = None, {}
        if step is not None and step >= self.first_step:
            self.run.log(values, step=step, commit=True)

    def mirroring(self, tensorboard: Any) -> MirroredWriter:
        """A writer that gives every scalar to `tensorboard` (a SummaryWriter, or None) and
        to this run: what TensorBoard gets, W&B gets, at the same step."""
        return MirroredWriter(tensorboard, self)

    def close(self) -> None:
        self.commit()
        finish(self.run)


def first_step(run: Any) -> int:
    """The first step W&B does not hold yet in the (resumed) `run`.

    Online, the server says: W&B's `starting_step` (it drops earlier steps, with a
    warning each). Offline, W&B holds what the transaction logs of the run's earlier
    offline sessions hold (what `wandb sync` sends). Not a count of what was sent: W&B
    writes its log in blocks, and a process killed by SIGKILL loses the steps of the
    block not yet written.
    """
    if run.settings.mode not in ("offline", "dryrun"):
        return int(run.starting_step)
    current = Path(run.sync_dir)
    sessions = current.parent.glob(f"offline-run-*-{run.id}*")  # W&B adds -1, -2 to a twin
    logs = [path / f"run-{run.id}.wandb" for path in sessions if path != current]
    last = 0
    for path in logs:
        try:
            last = max([last, *history_steps(path, run.id)])
        except DqnlabError as error:
            warnings.warn(f"{error}: the steps it holds may be sent again", stacklevel=2)
    return last + 1


class MirroredWriter:
    """TensorBoard's writer, or none, whose scalars also go to W&B (`WandbLog.mirroring`).
    Flushing is TensorBoard's: W&B's steps are committed by `WandbLog.commit`."""

    def __init__(self, tensorboard: Any, wandb_log: WandbLog) -> None:
        self.tensorboard = tensorboard
        self.wandb_log = wandb_log

    def add_scalar(self, tag: str, value: float, step: int) -> None:
        if self.tensorboard is not None:
            self.tensorboard.add_scalar(tag, value, step)
        self.wandb_log.add_scalar(tag, value, step)

    def flush(self) -> None:
        if self.tensorboard is not None:
            self.tensorboard.flush()

    def close(self) -> None:
        if self.tensorboard is not None:
            self.tensorboard.close()


# W&B's transaction log (`run-ID.wandb`): a 7-byte header (":W&B", 0xBEE1 little-endian,
# version 0), then LevelDB's log format: 32 KiB blocks of chunks, each a 7-byte header
# (checksum uint32, length uint16, type uint8: 1 full, 2 first, 3 middle, 4 last) and its
# bytes; a block's last 6 bytes or fewer are padding. A chunk or record that a killed
# process left incomplete ends the log.
_LOG_HEADER = b":W&B\xe1\xbe\x00"
_BLOCK_BYTES = 32768
_CHUNK_HEADER = struct.Struct("<IHB")
_FULL, _FIRST, _MIDDLE, _LAST = 1, 2, 3, 4


def transaction_records(path: Path) -> Iterator[Any]:
    """The records (`wandb_internal_pb2.Record`) of a W&B transaction log, in order."""
    from google.protobuf.message import DecodeError
    from wandb.proto import wandb_internal_pb2

    data = path.read_bytes()
    if _LOG_HEADER.startswith(data):
        return  # killed before its header was written, or right after
    if not data.startswith(_LOG_HEADER):
        raise DqnlabError(f"{path} is not a W&B transaction log of the version dqnlab reads")
    offset, pieces = len(_LOG_HEADER), bytearray()
    while True:
        left_in_block = _BLOCK_BYTES - offset % _BLOCK_BYTES
        if left_in_block < _CHUNK_HEADER.size:
            offset += left_in_block
            continue
        if offset + _CHUNK_HEADER.size > len(data):
            return
        _, length, kind = _CHUNK_HEADER.unpack_from(data, offset)
        start = offset + _CHUNK_HEADER.size
        if kind not in (_FULL, _FIRST, _MIDDLE, _LAST) or start + length > len(data):
            return
        if kind in (_FULL, _FIRST):
            pieces.clear()
        pieces += data[start : start + length]
        offset = start + length
        if kind in (_FULL, _LAST):
            record = wandb_internal_pb2.Record()  # type: ignore[attr-defined]  # re-exported
            try:
                record.ParseFromString(bytes(pieces))
            except DecodeError:
                return
            yield record


def history_steps(path: Path, run_id: str) -> list[int]:
    """The steps of the history rows in a transaction log of the W&B run `run_id`."""
    if not path.is_file():
        return []
    steps = []
    for record in transaction_records(path):
        kind = record.WhichOneof("record_type")
        if kind == "run" and record.run.run_id != run_id:
            return []
        if kind == "history":
            steps.append(record.history.step.num)
    return steps


# After training: the summary ----------------------------------------------------------
#
# What comes after training goes to the run's summary, not its history: a history step
# after the last training step would be taken by W&B for good, and a later resume with a
# larger budget could not log its own steps there.


def final_evaluation_values(record: Mapping[str, Any]) -> dict[str, Any]:
    """A final evaluation record (`evaluate.final_evaluation_record`) as summary values."""
    names = ("mean", "std", "episodes", "checkpoint_step", "epsilon", "max_episode_frames", "seed")
    return {f"final_evaluation/{name}": record[name] for name in names if name in record}


def video_media(checkpoint: str, paths: Sequence[Path]) -> dict[str, Path]:
    """The videos of an evaluation of the run's network `checkpoint` (best or last), one
    summary key per game: `videos/best/game01`..."""
    return {f"videos/{checkpoint}/game{number:02d}": path for number, path in enumerate(paths, 1)}


def add_to_summary(
    run_dir: Path, values: Mapping[str, Any], media: Mapping[str, Path] | None = None
) -> bool:
    """Reopen the W&B run of `run_dir`, if it logs to W&B, and add `values` and the files
    `media` (videos by their suffix, else images) to its summary. True if it did. Where
    wandb is missing, a warning: the files in the run directory hold the same."""
    media = media or {}
    config = rundir.load_run_config(run_dir)
    if not (values or media) or not uses_wandb(config):
        return False
    try:
        wandb = import_wandb()
    except DqnlabError as error:
        warnings.warn(f"{run_dir}: not sent to W&B: {error}", stacklevel=2)
        return False
    run = open_run(run_dir, config)
    summary = dict(values)
    for key, path in media.items():
        kind = wandb.Video if path.suffix.lower() in VIDEO_SUFFIXES else wandb.Image
        summary[key] = kind(str(path))
    run.summary.update(summary)
    finish(run)
    return True
