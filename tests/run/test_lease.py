"""The run directory's lease: one owner at a time, takeover only of a dead lease."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

from dqnlab.run import lease
from dqnlab.run.lease import LeaseHeld, LeaseLost, RunLease, read_lease


def test_a_live_lease_refuses_a_second_owner_until_released(tmp_path: Path) -> None:
    first = RunLease(tmp_path)
    first.acquire()
    with pytest.raises(LeaseHeld, match="is being trained by") as held:
        RunLease(tmp_path).acquire()
    assert held.value.exit_status == lease.LEASE_HELD_EXIT_STATUS
    first.check()  # still ours
    first.release()
    second = RunLease(tmp_path)
    second.acquire()  # released: taken at once
    second.check()
    assert not list(tmp_path.glob(".*.tmp"))


def test_an_expired_lease_is_taken_over_and_its_owner_stops(tmp_path: Path) -> None:
    old = RunLease(tmp_path)
    old.acquire()
    record = json.loads((tmp_path / "lease.json").read_text())
    record["expires_at"] = time.time() - lease.TAKEOVER_GRACE_SECONDS - 1  # owner cut off
    (tmp_path / "lease.json").write_text(json.dumps(record))
    new = RunLease(tmp_path)
    new.acquire()
    with pytest.raises(LeaseLost, match="taken over"):
        old.check()  # before its next checkpoint: it stops without writing
    old.renew()  # a renewal does not take it back
    assert old.lost.is_set()
    current = read_lease(tmp_path)
    assert current is not None and current.token == new.token


def test_a_dead_local_owner_is_released(tmp_path: Path) -> None:
    owner = RunLease(tmp_path)
    owner.acquire()
    lease.release_dead_owner(tmp_path, pid=owner_pid(tmp_path) + 1)  # another process: kept
    with pytest.raises(LeaseHeld):
        RunLease(tmp_path).acquire()
    lease.release_dead_owner(tmp_path, pid=owner_pid(tmp_path))
    RunLease(tmp_path).acquire()


def owner_pid(run_dir: Path) -> int:
    record = read_lease(run_dir)
    assert record is not None
    return record.pid


def test_a_killed_owner_on_this_machine_is_taken_over_at_once(tmp_path: Path) -> None:
    import subprocess
    import sys

    owner = RunLease(tmp_path)
    owner.acquire()
    record = json.loads((tmp_path / "lease.json").read_text())
    ended = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                           capture_output=True, text=True, check=True)  # fmt: skip
    (tmp_path / "lease.json").write_text(json.dumps(record | {"pid": int(ended.stdout)}))
    RunLease(tmp_path).acquire()  # its process is gone (as after SIGKILL): no waiting
    # The same on another machine, or in a lease that names no boot: only expiry frees it.
    for other in ({"host": "elsewhere"}, {"boot_id": ""}):
        (tmp_path / "lease.json").write_text(
            json.dumps(record | {"pid": int(ended.stdout)} | other)
        )
        with pytest.raises(LeaseHeld):
            RunLease(tmp_path).acquire()
