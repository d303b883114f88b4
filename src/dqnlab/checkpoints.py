"""Checkpoints: the best network, and the latest networks and optimizer, written atomically.

A checkpoint is written to a temporary file, flushed to disk, then renamed over the old
one, so a crash never leaves a half-written file under the real name.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from dqnlab import __version__
from dqnlab.errors import DqnlabError

FORMAT = "dqnlab-checkpoint-1"


def save(path: Path, payload: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(path.name + ".tmp")
    with temporary.open("wb") as handle:
        torch.save({"format": FORMAT, "version": __version__, **payload}, handle)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(temporary, path)


def load(path: Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    if not path.is_file():
        raise DqnlabError(f"no checkpoint at {path}")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as error:  # noqa: BLE001 - any unreadable file gets the same answer
        raise DqnlabError(f"checkpoint {path} cannot be read: {error}") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise DqnlabError(f"{path} is not a dqnlab checkpoint of format {FORMAT}")
    return payload
