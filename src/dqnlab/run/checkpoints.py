"""Training checkpoints: the whole training state of a run, complete and verifiable (the
network files best.pt, last.pt ... are `rundir`'s).

`CheckpointStore` keeps complete, verifiable training checkpoints in RUN_DIR/checkpoints/:

    step-000001234/      one complete checkpoint
        state.pt         torch.save of the caller's small state (networks, optimizer, RNGs...):
                         tensors and plain Python values only, read with weights_only=True
        MANIFEST.json    written last: version, config fingerprint, step, and the size and
                         CRC-32 of state.pt and of every replay chunk file it needs
    replay/              chunk files shared by all checkpoints
        frames.00003.g000000007.bin   raw bytes of `frames` slots [3 * chunk_slots,
                                      4 * chunk_slots), written by save number 7
    .partial-step-.../   a save in progress (never read; removed when it fails)

Each replay array is cut into chunks of `chunk_slots` slots. A save writes only the chunks
holding slots written since the previous save and points the new manifest at the previous
checkpoint's files for the rest, so a checkpoint of a 1M replay writes about a quarter of
its 7 GB after 250k steps instead of all of it. Slots never written are zeros and are not
stored: a chunk none of whose slots was written is left out (null in the manifest), and a
raw chunk is cut after its last written slot, so the first checkpoint of a run holds the
filled part of the replay, not the whole preallocated one. A file that a checkpoint
references is never modified: rewritten chunks get a new generation in their name. A
checkpoint is complete when its manifest is valid and every file it names has the
recorded size (checked always) and CRC-32 (checked when loading); anything else is
skipped with a warning.

Checksum: CRC-32 (zlib), several times faster than BLAKE2b (figures in docs/benchmark.md,
"checkpoint"). A checksum here detects torn or flipped bytes, not
tampering, so the fast one is enough; chunk files are named by generation, not by content,
so nothing relies on the checksum being collision resistant.

Loading: a run directory may be writable by others (a shared cluster filesystem), and a
CRC-32 is no defence against a crafted file, so state.pt is read with torch's weights-only
unpickler, which builds tensors and plain Python values and calls nothing else. A state it
refuses is skipped as corrupted; `save` refuses to write one.

This module is the store: a save published whole or not at all, pruning, choosing the
checkpoint to resume. `checkpoint_manifest` is what a checkpoint records,
`checkpoint_chunks` the replay arrays as chunks (what changed, what to write or reuse,
loading), `checkpoint_files` the bytes on disk (written whole, read verified).
"""

from __future__ import annotations

import contextlib
import io
import os
import shutil
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from dqnlab import __version__
from dqnlab.algorithm.streams import WrittenSlots
from dqnlab.errors import DqnlabError, ResourceError
from dqnlab.run import checkpoint_chunks
from dqnlab.run.checkpoint_chunks import Arrays, ChunkedArray, Plan, load_arrays, written_slots
from dqnlab.run.checkpoint_files import (
    check_loadable,
    check_sizes,
    fsync_directory,
    load_state,
    pieces_of,
    remove_quietly,
    write_file,
)
from dqnlab.run.checkpoint_manifest import (
    MANIFEST_FILE,
    STEP_DIR,
    Incomplete,
    Manifest,
    read_manifest,
    step_of,
)
from dqnlab.run.rundir import checkpoints_dir

__all__ = [
    "DEFAULT_CHUNK_SLOTS",
    "Arrays",
    "CheckpointStore",
    "CheckpointWarning",
    "ChunkedArray",
    "LoadedCheckpoint",
    "written_slots",
]

# Training checkpoints ------------------------------------------------------------------

STATE_FILE = "state.pt"
REPLAY_DIR = "replay"
# 16,384 slots is 115 MB of 84x84 frames: a save rewrites at most two partly changed chunks
# per changed range (<= 230 MB wasted), and a 1M replay is 62 files per array.
DEFAULT_CHUNK_SLOTS = 16_384
_MANIFEST_SLACK_BYTES = 2**20
_PARTIAL_PREFIX = ".partial-"
_REPLACED_PREFIX = ".replaced-"


class CheckpointWarning(UserWarning):
    """A checkpoint was skipped or removed; the message says which and why."""


@dataclass
class LoadedCheckpoint:
    step: int
    state: dict[str, Any]
    directory: Path
    manifest: Manifest
    arrays_loaded: bool  # True when `latest(into=...)` already filled the arrays

    def load_arrays(self, into: Arrays) -> None:
        """Fill the preallocated arrays in place, verifying every chunk's CRC-32.

        There is no fallback from here: `CheckpointStore.latest(into=...)` loads the arrays
        while choosing the checkpoint, and falls back if one turns out corrupted.
        """
        try:
            load_arrays(self.manifest, self.directory.parent / REPLAY_DIR, into)
        except Incomplete as reason:
            raise DqnlabError(f"checkpoint {self.directory} is corrupted: {reason}") from None
        self.arrays_loaded = True


class CheckpointStore:
    """Complete, atomic, incremental training checkpoints in RUN_DIR/checkpoints/.

    One writer at a time. The store remembers the checkpoint it last saved or loaded: the
    next save takes the unchanged replay chunks from it. A fresh store has none, so its
    first save writes every chunk that holds a written slot (`save`).
    """

    def __init__(
        self, run_dir: Path, keep: int = 2, chunk_slots: int = DEFAULT_CHUNK_SLOTS
    ) -> None:
        if keep < 1:
            raise ValueError(f"keep must be at least 1, not {keep}")
        if chunk_slots < 1:
            raise ValueError(f"chunk_slots must be at least 1, not {chunk_slots}")
        self.directory = checkpoints_dir(Path(run_dir))
        self.replay_directory = self.directory / REPLAY_DIR
        self.keep = keep
        self.chunk_slots = chunk_slots
        self._base: Manifest | None = None

    # Saving ---------------------------------------------------------------------------

    def save(
        self,
        step: int,
        state: dict[str, Any],
        arrays: Arrays,
        changed_slots: WrittenSlots,
        config_fingerprint: str,
    ) -> Path:
        """Write a complete checkpoint of `step`; return its directory.

        `arrays` are the replay arrays (same first dimension, the capacity; a `ChunkedArray`
        is written chunk by chunk as it holds them); `changed_slots` is the ring range
        [start, stop) of slots written since the last save or load of this store (stop <
        start wraps around; start == stop is nothing; a list of them: one per replay stream),
        None for all. A store that has neither saved nor loaded counts from the arrays'
        creation: their slots outside the range are zeros, and are not stored.
        A failed save leaves the earlier checkpoints as they were and no files behind.
        """
        state_bytes = _serialized(state)
        plan = checkpoint_chunks.plan(
            arrays, changed_slots, self._base, self.replay_directory, self.chunk_slots
        )
        created: list[Path] = []
        staging = self.directory / f"{_PARTIAL_PREFIX}step-{step:09d}"
        final = self.directory / f"step-{step:09d}"
        replaced = self.directory / f"{_REPLACED_PREFIX}step-{step:09d}"
        try:
            self.replay_directory.mkdir(parents=True, exist_ok=True)
            self._check_free_space(step, len(state_bytes), arrays, plan)
            shutil.rmtree(staging, ignore_errors=True)
            generation = self._next_generation()
            records = checkpoint_chunks.write(
                arrays, plan, generation, self.replay_directory, created, self.chunk_slots
            )
            staging.mkdir()
            created.append(staging)
            manifest = Manifest(
                step=step,
                generation=generation,
                dqnlab_version=__version__,
                config_fingerprint=config_fingerprint,
                state=write_file(staging / STATE_FILE, pieces_of(state_bytes), created),
                arrays=records,
            )
            write_file(staging / MANIFEST_FILE, [memoryview(manifest.to_json())], created)
            fsync_directory(staging)
            self._publish(staging, final, replaced, created)
        except BaseException as error:
            self._undo_save(created, final, replaced)
            if isinstance(error, OSError):
                raise DqnlabError(
                    f"could not write the checkpoint of step {step} in {self.directory}: "
                    f"{os.strerror(error.errno) if error.errno else error}; "
                    "the earlier checkpoints are intact"
                ) from error
            raise
        self._base = manifest
        self._prune_or_warn(step)
        return final

    def _publish(self, staging: Path, final: Path, replaced: Path, created: list[Path]) -> None:
        if final.exists():  # saved twice at one step: replace it
            shutil.rmtree(replaced, ignore_errors=True)
            os.replace(final, replaced)
        os.replace(staging, final)
        created.append(final)
        fsync_directory(self.directory)

    @staticmethod
    def _undo_save(created: list[Path], final: Path, replaced: Path) -> None:
        """Remove what a failed save wrote; put back the checkpoint it was replacing."""
        for path in reversed(created):
            remove_quietly(path)
        if replaced.exists() and not final.exists():
            with contextlib.suppress(OSError):
                os.replace(replaced, final)

    def _check_free_space(self, step: int, state_size: int, arrays: Arrays, plan: Plan) -> None:
        """Room for the state, the manifest and the chunk files that are not reused."""
        needed = state_size + _MANIFEST_SLACK_BYTES + checkpoint_chunks.bytes_to_write(arrays, plan)
        free = shutil.disk_usage(self.directory).free
        if needed > free:
            raise ResourceError(
                f"the checkpoint of step {step} needs {needed / 2**30:.2f} GiB but only "
                f"{free / 2**30:.2f} GiB is free in {self.directory}; free some disk space"
            )

    def _next_generation(self) -> int:
        """One more than any generation in use, so a new chunk file never overwrites one."""
        latest = self._base.generation if self._base is not None else 0
        for directory in self._step_directories():
            with contextlib.suppress(Incomplete):
                latest = max(latest, read_manifest(directory).generation)
        for path in self.replay_directory.iterdir():
            latest = max(latest, checkpoint_chunks.generation_of(path) or 0)
        return latest + 1

    def _prune_or_warn(self, saved_step: int) -> None:
        try:
            self._prune(saved_step)
        except OSError as error:
            warnings.warn(
                f"checkpoint of step {saved_step} is complete, but removing old checkpoints in "
                f"{self.directory} failed: {error}",
                CheckpointWarning,
                stacklevel=3,
            )

    def _prune(self, saved_step: int) -> None:
        """Keep the newest `keep` complete checkpoints up to `saved_step`; delete the rest.

        Checkpoints after `saved_step` belong to a run that was resumed from an earlier
        one (the later ones were corrupted, or the user went back) and are removed too.
        Then every chunk file that no kept checkpoint references is deleted.
        """
        complete: list[tuple[int, Path, Manifest]] = []
        for directory in self._step_directories():
            step = step_of(directory)
            try:
                manifest = read_manifest(directory)
                check_sizes(manifest, directory, self.replay_directory)
            except Incomplete as reason:
                _warn(f"removing incomplete checkpoint {directory} ({reason})")
                shutil.rmtree(directory)
                continue
            if step > saved_step:
                _warn(
                    f"removing checkpoint {directory}: it is newer than step {saved_step}, "
                    "saved by a run that was resumed from an earlier checkpoint"
                )
                shutil.rmtree(directory)
                continue
            complete.append((step, directory, manifest))
        complete.sort(key=lambda entry: entry[0])
        for _, directory, _ in complete[: -self.keep]:
            shutil.rmtree(directory)
        for path in self.directory.iterdir():
            if path.name.startswith((_PARTIAL_PREFIX, _REPLACED_PREFIX)):
                shutil.rmtree(path)
        referenced = {
            chunk.name
            for _, _, manifest in complete[-self.keep :]
            for record in manifest.arrays.values()
            for chunk in record.chunks
            if chunk is not None
        }
        for path in self.replay_directory.iterdir():
            if path.name not in referenced:
                path.unlink()
        fsync_directory(self.replay_directory)
        fsync_directory(self.directory)

    # Loading --------------------------------------------------------------------------

    def steps(self) -> list[int]:
        """The steps of the checkpoints whose manifest and file sizes are right, oldest first."""
        steps = []
        for directory in self._step_directories():
            try:
                check_sizes(read_manifest(directory), directory, self.replay_directory)
            except Incomplete:
                continue
            steps.append(step_of(directory))
        return sorted(steps)

    def latest(
        self,
        config_fingerprint: str,
        into: Arrays | None = None,
        map_location: str | torch.device = "cpu",
    ) -> LoadedCheckpoint | None:
        """The newest complete checkpoint, checksums verified; None when there is none.

        With `into` (the preallocated replay arrays), the replay is read into them in
        place while it is verified: one pass over the files, no second copy. Without it the
        chunks are verified by reading, and `load_arrays` reads them again. A corrupted or
        incomplete checkpoint is skipped with a warning saying why; when every one is, the
        contents of `into` are undefined and DqnlabError says why each was skipped.
        Another dqnlab version or config fingerprint raises DqnlabError.
        """
        if not self.directory.is_dir():
            return None
        for path in self.directory.iterdir():
            if path.name.startswith(_PARTIAL_PREFIX):
                _warn(f"ignoring {path}: a save that was interrupted before it completed")
        reasons = []
        for directory in sorted(self._step_directories(), key=step_of, reverse=True):
            try:
                manifest = read_manifest(directory)
                self._check_compatible(manifest, directory, config_fingerprint)
                check_sizes(manifest, directory, self.replay_directory)
                state = load_state(directory / STATE_FILE, manifest.state, map_location)
                load_arrays(manifest, self.replay_directory, into)
            except Incomplete as reason:
                reasons.append(f"{directory.name}: {reason}")
                _warn(
                    f"skipping checkpoint {directory}: incomplete or corrupted ({reason}); "
                    "falling back to the previous one"
                )
                continue
            self._base = manifest
            return LoadedCheckpoint(
                step=manifest.step,
                state=state,
                directory=directory,
                manifest=manifest,
                arrays_loaded=into is not None,
            )
        if reasons:
            raise DqnlabError(f"no complete checkpoint in {self.directory}: " + "; ".join(reasons))
        return None

    @staticmethod
    def _check_compatible(manifest: Manifest, directory: Path, fingerprint: str) -> None:
        if manifest.dqnlab_version != __version__:
            raise DqnlabError(
                f"checkpoint {directory} was written by dqnlab {manifest.dqnlab_version} and "
                f"this is dqnlab {__version__}: resume it with dqnlab "
                f"{manifest.dqnlab_version}, or start a new run"
            )
        if manifest.config_fingerprint != fingerprint:
            raise DqnlabError(
                f"checkpoint {directory} was written with another configuration (fingerprint "
                f"{manifest.config_fingerprint[:12]}, this one {fingerprint[:12]}): resume "
                "with the run's own config.toml, or start a new run"
            )

    def _step_directories(self) -> list[Path]:
        if not self.directory.is_dir():
            return []
        return [
            path
            for path in self.directory.iterdir()
            if STEP_DIR.fullmatch(path.name) and path.is_dir()
        ]


def _serialized(state: dict[str, Any]) -> memoryview:
    """torch.save's bytes of `state`, refused here if resuming could not load them."""
    buffer = io.BytesIO()
    torch.save(state, buffer)
    check_loadable(buffer.getbuffer())
    return buffer.getbuffer()


def _warn(message: str) -> None:
    warnings.warn(message, CheckpointWarning, stacklevel=3)
