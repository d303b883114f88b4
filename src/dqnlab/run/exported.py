"""An exported folder: one trained network and what describes it, in files that need
neither pickle nor dqnlab's run layout to read. The one module that knows its files.

    EXPORT/
        README.md               the model card (`hub/card.py`)
        config.toml             the run's configuration, as in a run directory
        model.safetensors       the network's tensors; its metadata holds, as JSON, what a
                                network file (`rundir`) holds beside them
        results.json            the final evaluation the exporter measured, with its protocol
        replay.mp4 | replay.gif one game of the final protocol, filmed
        learning-curve.png      the run's periodic evaluations
        episodes.csv, evaluations.csv   the run's logs
        final_evaluation.json   written by `dqnlab evaluate EXPORT`, as in a run directory
        pulled.json             where `dqnlab pull` took the folder from

Why safetensors: a `.pt` file is a pickle container, and the Hub's convention for weights
shared between strangers is safetensors, a header of JSON and raw tensor bytes that no
reader executes (huggingface/safetensors README, "Safety").
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import torch

from dqnlab import __version__
from dqnlab.errors import DqnlabError

MODEL_FILE = "model.safetensors"
CONFIG_FILE = "config.toml"  # the same name as a run directory's (`rundir.CONFIG_FILE`)
RESULTS_FILE = "results.json"
CARD_FILE = "README.md"
CURVE_FILE = "learning-curve.png"
VIDEO_STEM = "replay"  # replay.mp4 or replay.gif
LOG_FILES = ("episodes.csv", "evaluations.csv")
PULLED_FILE = "pulled.json"
# Every file an exported folder may hold: what `dqnlab pull` downloads, nothing else.
FOLDER_FILES = (
    CARD_FILE, CONFIG_FILE, MODEL_FILE, RESULTS_FILE, CURVE_FILE,
    f"{VIDEO_STEM}.mp4", f"{VIDEO_STEM}.gif", *LOG_FILES,
)  # fmt: skip
SAFETENSORS_FORMAT = "dqnlab-safetensors-1"  # the format tag in model.safetensors' metadata
# The keys of the network payload (`rundir.network_payload`) that are not tensors.
_DESCRIPTION_KEYS = (
    "config", "input_shape", "observation_dtype", "action_names", "step", "eval_mean",
    "observation_layout",
)  # fmt: skip
HUB_EXTRA = "pip install 'dqnlab[hub]'"


def is_exported_dir(path: Path) -> bool:
    """A folder `dqnlab export` wrote (or `dqnlab pull` fetched): its network is
    model.safetensors, and it has no run's checkpoints/."""
    return (path / MODEL_FILE).is_file() and not (path / "checkpoints").exists()


def network_path(folder: Path) -> Path:
    return folder / MODEL_FILE


def _safetensors_torch() -> Any:
    try:
        import safetensors.torch
    except ImportError:
        raise DqnlabError(
            f"reading or writing .safetensors needs safetensors: {HUB_EXTRA}"
        ) from None
    return safetensors.torch


def description_json(payload: dict[str, Any]) -> str:
    """What a network payload holds beside its tensors, as JSON (NaN, which strict JSON
    lacks, as null: a network saved before any evaluation has a NaN mean)."""
    description = {key: payload[key] for key in _DESCRIPTION_KEYS if key in payload}
    description["input_shape"] = [int(n) for n in description.get("input_shape", ())]
    mean = description.get("eval_mean")
    if isinstance(mean, float) and math.isnan(mean):
        description["eval_mean"] = None
    try:
        return json.dumps(description, allow_nan=False, sort_keys=True)
    except (TypeError, ValueError) as error:
        raise DqnlabError(
            f"the network's description cannot be written as JSON ({error}): a TOML date or "
            "time in env_kwargs, say"
        ) from None


def save_network(path: Path, payload: dict[str, Any]) -> None:
    """Write a network payload (`rundir.network_payload`) as safetensors: its tensors, and
    the rest as JSON in the file's metadata. Written to a temporary name, then renamed."""
    safetensors_torch = _safetensors_torch()
    state = payload["network"]
    tensors = {}
    for name, value in state.items():
        if not isinstance(value, torch.Tensor):
            raise DqnlabError(
                f"the network's state {name!r} is a {type(value).__name__}, not a tensor"
            )
        tensors[name] = value.detach().to("cpu").contiguous().clone()  # no shared storage
    metadata = {
        "format": SAFETENSORS_FORMAT,
        "dqnlab_version": __version__,
        "dqnlab": description_json(payload),
    }
    temporary = path.with_name(path.name + ".tmp")
    safetensors_torch.save_file(tensors, str(temporary), metadata=metadata)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(temporary, 0o666 & ~umask)  # as any file written here (safetensors: 0600)
    os.replace(temporary, path)


def read_metadata(path: Path) -> dict[str, str]:
    """model.safetensors' metadata (strings), read from its header alone."""
    _safetensors_torch()
    from safetensors import safe_open

    try:
        with safe_open(str(path), framework="pt") as handle:
            metadata = handle.metadata() or {}
    except Exception as error:  # noqa: BLE001 - SafetensorError, OSError: the same answer
        raise DqnlabError(f"{path} is not a readable safetensors file: {error}") from None
    if metadata.get("format") != SAFETENSORS_FORMAT:
        raise DqnlabError(
            f"{path} is not a dqnlab network (its metadata's format is "
            f"{metadata.get('format')!r}, not {SAFETENSORS_FORMAT!r})"
        )
    return metadata


def read_description(path: Path) -> dict[str, Any]:
    """The network's description (config, input shape, dtype, action names, step, ...)."""
    metadata = read_metadata(path)
    try:
        description = json.loads(metadata["dqnlab"])
    except (KeyError, json.JSONDecodeError) as error:
        raise DqnlabError(f"{path} has no readable description in its metadata: {error}") from None
    if not isinstance(description, dict):
        raise DqnlabError(f"{path}'s description is not a JSON object")
    if description.get("eval_mean", 0.0) is None:
        description["eval_mean"] = float("nan")
    description["dqnlab_version"] = metadata.get("dqnlab_version")
    return description


def load_network(path: Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """A network payload as `rundir.load_network` returns one, read from safetensors:
    nothing but tensors and JSON is parsed."""
    safetensors_torch = _safetensors_torch()
    if not path.is_file():
        raise DqnlabError(f"no network file at {path}")
    description = read_description(path)
    try:
        state = safetensors_torch.load_file(str(path), device=str(map_location))
    except Exception as error:  # noqa: BLE001 - a file whose header read but tensors do not
        raise DqnlabError(f"{path} cannot be read: {error}") from None
    return {**description, "format": SAFETENSORS_FORMAT, "network": state}


def save_json(path: Path, record: dict[str, Any]) -> None:
    path.write_text(json.dumps(record, indent=2) + "\n")
