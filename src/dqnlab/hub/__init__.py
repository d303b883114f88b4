"""Sharing a trained agent: a run exported to a folder anyone can read (`export.py`), its
model card (`card.py`), pushed to and pulled from the Hugging Face Hub (`remote.py`), and
the checks a folder from a stranger passes before dqnlab plays it (`checks.py`).

The layout of an exported folder is `run/exported.py`'s, so that `dqnlab evaluate` reads
one like a run directory. Needs the `hub` extra: huggingface_hub and safetensors.
"""

from __future__ import annotations

from dqnlab.errors import DqnlabError
from dqnlab.run.exported import HUB_EXTRA


def require_hub_extra() -> None:
    """A one-line error naming the extra when huggingface_hub or safetensors is missing."""
    missing = []
    for name in ("huggingface_hub", "safetensors"):
        try:
            __import__(name)
        except ImportError:
            missing.append(name)
    if missing:
        raise DqnlabError(f"dqnlab export, push and pull need {' and '.join(missing)}: {HUB_EXTRA}")
