"""The run directory's lease: one training process owns a run directory at a time.

A run retried on another node, or a sweep started again, must never train a run that a
process elsewhere is still training, nor may a process on a node cut off from the cluster
keep writing into a run that was restarted elsewhere. The owner holds RUN_DIR/lease.json
(its host, pid, a random token and an expiry), renews it every third of LEASE_SECONDS
from a thread, and re-reads it before writing each checkpoint: if the token there is no
longer its own, it stops without writing.

Taking a lease: a lease that is absent, released, or expired for more than
TAKEOVER_GRACE_SECONDS may be taken, and so may one whose owner ran on this machine (same
host name and boot id) and is gone (its pid ended, or belongs to a process started at
another time): a run killed with SIGKILL, or by the OOM killer, resumes at once with
`dqnlab resume`. A live one refuses with the owner's name.

Why no file lock: `flock`/`fcntl` locks are not always honoured on NFS (NFSv3 without
lockd, some client mounts with `nolock`, and a node cut off from the cluster keeps its
lock until the server notices). The lease uses only what NFS does guarantee: `link()`
to create the file is atomic on the server (the classic NFS-safe lock file), `rename()`
replaces it atomically, and close-to-open consistency means a reader that opens the file
sees what the last writer closed. Two assumptions, stated in docs/clusters.md: the nodes'
clocks agree to well within TAKEOVER_GRACE_SECONDS (NTP), and the attribute cache
(`actimeo`, 60 s at most by default) is shorter than LEASE_SECONDS + the grace, so a
taker never acts on a stale view of a live lease.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import secrets
import socket
import threading
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path

import psutil

from dqnlab.errors import DqnlabError
from dqnlab.run.rundir import LEASE_FILE, lease_path

LEASE_SECONDS = float(os.environ.get("DQNLAB_LEASE_SECONDS", "120"))
TAKEOVER_GRACE_SECONDS = float(os.environ.get("DQNLAB_LEASE_GRACE_SECONDS", "30"))
LEASE_HELD_EXIT_STATUS = 75  # EX_TEMPFAIL: `dqnlab train` found the run owned elsewhere


class LeaseHeld(DqnlabError):
    """Another live process owns the run directory."""

    exit_status = LEASE_HELD_EXIT_STATUS


class LeaseLost(DqnlabError):
    """Another process took the run directory over: this one must stop writing."""


@dataclass(frozen=True)
class LeaseRecord:
    token: str
    host: str
    pid: int
    expires_at: float  # wall-clock seconds (time.time()), comparable across nodes (NTP)
    released: bool = False
    boot_id: str = ""  # the owner machine's boot (empty: unknown, in an older lease)
    started: float = 0.0  # the owner process's start time (psutil create_time)

    def describe(self) -> str:
        left = self.expires_at - time.time()
        return f"{self.host} pid {self.pid} (lease {'expires' if left >= 0 else 'expired'} " \
            f"{abs(left):.0f} s {'from now' if left >= 0 else 'ago'})"  # fmt: skip

    def takeable(self, now: float) -> bool:
        return (
            self.released
            or now > self.expires_at + TAKEOVER_GRACE_SECONDS
            or self.owner_gone_from_this_machine()
        )

    def owner_gone_from_this_machine(self) -> bool:
        """The owner ran on this machine and its process no longer exists."""
        return self._owner_on_this_machine() is False

    def owner_alive_on_this_machine(self) -> bool:
        """The owner runs on this machine and its process still exists (whether or not it
        renews the lease: a process stopped with SIGSTOP does not)."""
        return self._owner_on_this_machine() is True

    def _owner_on_this_machine(self) -> bool | None:
        """Whether the owner's process exists; None where it is not of this machine's boot."""
        if not self.boot_id or (self.host, self.boot_id) != (socket.gethostname(), boot_id()):
            return None
        try:
            return abs(psutil.Process(self.pid).create_time() - self.started) <= 0.01
        except psutil.NoSuchProcess:
            return False


def boot_id() -> str:
    """This machine's boot (Linux), so that a lease names a process of one machine; empty
    where unknown, and then only the expiry frees a killed owner's lease."""
    try:
        return Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    except OSError:
        return ""


def read_lease(run_dir: Path) -> LeaseRecord | None:
    """The run's lease, None if it has none (or an unreadable one, being replaced)."""
    try:
        return LeaseRecord(**json.loads(lease_path(run_dir).read_text()))
    except (OSError, ValueError, TypeError):
        return None


def lease_is_live(run_dir: Path) -> bool:
    """Whether a process holds the run now (for `dqnlab status`)."""
    record = read_lease(run_dir)
    return record is not None and not record.takeable(time.time())


class RunLease:
    """The lease of one training session: `acquire`, then `renew_in_background`; `check`
    before each checkpoint; `release` at the end."""

    def __init__(self, run_dir: Path) -> None:
        self.run_dir = run_dir
        self.token = secrets.token_hex(8)
        self.lost = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _record(self, released: bool = False) -> LeaseRecord:
        return LeaseRecord(
            self.token,
            socket.gethostname(),
            os.getpid(),
            time.time() + LEASE_SECONDS,
            released,
            boot_id(),
            psutil.Process().create_time(),
        )

    def _write_temporary(self, record: LeaseRecord) -> Path:
        temporary = self.run_dir / f".{LEASE_FILE}.{self.token}.tmp"
        with temporary.open("w") as handle:
            handle.write(json.dumps(asdict(record)))
            handle.flush()
            os.fsync(handle.fileno())
        return temporary

    def acquire(self) -> None:
        """Own the run directory, or raise LeaseHeld naming the live owner."""
        temporary = self._write_temporary(self._record())
        try:
            os.link(temporary, lease_path(self.run_dir))  # atomic create, also on NFS
            return
        except FileExistsError:
            current = read_lease(self.run_dir)
            if current is not None and not current.takeable(time.time()):
                raise LeaseHeld(
                    f"{self.run_dir} is being trained by {current.describe()}; "
                    "it carries on when that process stops"
                ) from None
            os.replace(temporary, lease_path(self.run_dir))
        finally:
            temporary.unlink(missing_ok=True)
        # Two takers of one expired lease: the last rename wins, the other sees its token.
        time.sleep(0.05)
        self.check()

    def check(self) -> None:
        """Raise LeaseLost unless the lease on disk is still this session's."""
        current = read_lease(self.run_dir)
        if self.lost.is_set() or current is None or current.token != self.token:
            self.lost.set()
            owner = current.describe() if current else "nobody"
            raise LeaseLost(
                f"{self.run_dir} was taken over by {owner}; this process stops without writing more"
            )

    def renew(self) -> None:
        """Extend the expiry, if the lease is still ours (else mark it lost)."""
        current = read_lease(self.run_dir)
        if current is None or current.token != self.token:
            self.lost.set()
            return
        os.replace(self._write_temporary(self._record()), lease_path(self.run_dir))

    def renew_in_background(self) -> None:
        def loop() -> None:
            while not self._stop.wait(LEASE_SECONDS / 3):
                with contextlib.suppress(OSError):  # storage briefly away: try again next time
                    self.renew()

        self._thread = threading.Thread(target=loop, name="run-lease", daemon=True)
        self._thread.start()

    def release(self) -> None:
        """Mark the lease released (if still ours), so the next owner need not wait."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        current = read_lease(self.run_dir)
        if current is not None and current.token == self.token:
            os.replace(self._write_temporary(self._record(released=True)), lease_path(self.run_dir))


@contextlib.contextmanager
def held(run_dir: Path) -> Iterator[RunLease]:
    """The run's lease for a `with` block: acquired (else LeaseHeld), renewed from a thread,
    released at the end, whatever ends the block."""
    lease = RunLease(run_dir)
    lease.acquire()
    lease.renew_in_background()
    try:
        yield lease
    finally:
        lease.release()


def release_dead_owner(run_dir: Path, pid: int) -> None:
    """Release the lease of process `pid` of this host, known to be dead (a run killed by
    SIGKILL or the OOM killer), so that its retry need not wait for the expiry."""
    current = read_lease(run_dir)
    if current is None or current.pid != pid or current.host != socket.gethostname():
        return
    released = dataclasses.replace(current, released=True)
    temporary = run_dir / f".{LEASE_FILE}.released.tmp"
    temporary.write_text(json.dumps(asdict(released)))
    os.replace(temporary, lease_path(run_dir))


def wait_until_free(run_dir: Path, poll_seconds: float = 2.0) -> None:
    """Block until nobody holds the run's lease (a retried run waits for a cut-off
    predecessor's lease to expire or be released)."""
    while True:
        record = read_lease(run_dir)
        if record is None or record.takeable(time.time()):
            return
        time.sleep(poll_seconds)
