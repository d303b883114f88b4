"""Which networks an inspection compares: the --checkpoints list (the Q-values themselves
are checked on real runs in test_write.py)."""

from __future__ import annotations

import pytest

from dqnlab.analysis.inspection.qvalues import parse_checkpoints
from dqnlab.errors import DqnlabError


def test_parse_checkpoints() -> None:
    assert parse_checkpoints("best, worst") == ["best", "worst"]
    assert parse_checkpoints("250000,500000") == ["250000", "500000"]
    assert parse_checkpoints("best,300,best") == ["best", "300"]
    assert parse_checkpoints("600,0600") == ["600"]  # one network, not twice
    for bad in ("", "best,last", "-5"):
        with pytest.raises(DqnlabError):
            parse_checkpoints(bad)
