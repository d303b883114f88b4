"""Digests of the online network's weights along a run (`digests.csv`), so that a resumed
run can say whether it retraces what the killed run did after the checkpoint.

A checkpoint holds the whole training state, so a resumed run computes what the killed
one would have computed, bit for bit, unless something outside the state differs:
the processor, the thread count, a library that chooses how to split a product by the
machine's load, or dqnlab's own code. The run writes a row every `digest_period_steps`
agent steps, flushed at once; a run killed (SIGKILL, the machine lost) between two
checkpoints leaves the rows of the steps it trained past the last one. The resumed run
reads them, drops them from the file, and compares its own digest at each of those steps
with the killed run's: the first that differs is said on stderr, with its step, and once
it has passed every one of them with the same weights it says so too. Nothing is compared
after a stop by SIGINT or SIGTERM, which checkpoints at the step it stops on.
"""

from __future__ import annotations

import csv
import hashlib
from pathlib import Path

import torch

from dqnlab.run.logs import truncate_after

DIGEST_FIELDS = ("step", "weights")


def weights_digest(network: torch.nn.Module) -> str:
    """BLAKE2b of the network's parameters and buffers, in `state_dict` order, byte for byte
    (16 bytes, hex): equal digests, equal weights."""
    digest = hashlib.blake2b(digest_size=16)
    for name, tensor in network.state_dict().items():
        digest.update(name.encode())
        digest.update(tensor.detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy())
    return digest.hexdigest()


class WeightDigests:
    """Appends `digests.csv` and compares a resumed run with the rows the killed run left
    after `resume_step` (None: a new run, the file started afresh)."""

    def __init__(self, path: Path, resume_step: int | None) -> None:
        self.path = path
        self.expected: dict[int, str] = {}  # the killed run's digests past the checkpoint
        self.compared = 0
        if resume_step is not None and path.exists():
            self.expected = {
                step: digest for step, digest in _read(path).items() if step > resume_step
            }
            truncate_after(path, resume_step)
        new = resume_step is None or not path.exists()
        self._handle = path.open("w" if new else "a", newline="")
        self._writer = csv.writer(self._handle)
        if new:
            self._writer.writerow(DIGEST_FIELDS)
            self._handle.flush()

    def record(self, step: int, network: torch.nn.Module) -> str | None:
        """Write the digest at `step`; returns what to tell the user, where there is
        something: the first step whose weights differ from the killed run's, or that the
        last step the killed run recorded was reached with the same weights."""
        digest = weights_digest(network)
        self._writer.writerow((step, digest))
        self._handle.flush()  # a SIGKILL loses nothing written before it
        expected = self.expected.pop(step, None)
        if expected is None:
            return None
        self.compared += 1
        if digest != expected:
            self.expected.clear()  # said once: from here the run has a course of its own
            return (
                f"dqnlab: warning: this resumed run is not retracing the run that was killed: its "
                f"online network at step {step:,} differs from the one the killed run "
                f"recorded there ({self.path.name}). The checkpoint loaded exactly, so "
                "something outside it changed the arithmetic since: the processor, the "
                "thread count, a library's own choice (a product split by the machine's "
                "load), or dqnlab's code. Training goes on from here on its own course."
            )
        if not self.expected:
            steps = "the one step" if self.compared == 1 else f"all {self.compared} steps"
            return (
                f"dqnlab: the resumed run retraces the killed run: the same weights at {steps} it "
                f"recorded past the checkpoint ({self.path.name})"
            )
        return None

    def close(self) -> None:
        self._handle.close()


def _read(path: Path) -> dict[int, str]:
    """The rows of a digests file (a torn last line, from a kill mid-write, left out)."""
    rows: dict[int, str] = {}
    with path.open(newline="") as handle:
        lines = handle.read().splitlines(keepends=True)
    for line in lines[1:]:
        if not line.endswith("\n"):
            break
        step, digest = line.rstrip("\r\n").split(",")
        rows[int(step)] = digest
    return rows
