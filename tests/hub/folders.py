"""Changing an exported folder as a stranger's repository might hold it."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path
from typing import Any

from dqnlab.config import toml_value
from dqnlab.run import exported

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


def copy_folder(folder: Path, to: Path) -> Path:
    shutil.copytree(folder, to)
    return to


def change_settings(folder: Path, where: str = "both", **changes: Any) -> None:
    """Set `changes` in config.toml ("toml"), in model.safetensors' metadata ("metadata"),
    or in both, unknown names included."""
    if where in ("toml", "both"):
        path = folder / exported.CONFIG_FILE
        values = {**tomllib.loads(path.read_text()), **changes}
        path.write_text("".join(f"{k} = {toml_value(v)}\n" for k, v in values.items()))
    if where in ("metadata", "both"):
        import safetensors.torch
        from safetensors import safe_open

        path = exported.network_path(folder)
        with safe_open(str(path), framework="pt") as handle:
            metadata = dict(handle.metadata())
        tensors = safetensors.torch.load_file(str(path))
        description = json.loads(metadata["dqnlab"])
        description["config"] = {**description["config"], **changes}
        metadata["dqnlab"] = json.dumps(description)
        safetensors.torch.save_file(tensors, str(path), metadata=metadata)
