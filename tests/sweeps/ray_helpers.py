"""A Ray cluster on 127.0.0.1 for the tests, and the check that Ray talks on loopback only."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import psutil

from dqnlab.sweeps.cluster import connect_to_cluster, import_ray, start_loopback_cluster

LOOPBACK_ADDRESSES = {"127.0.0.1", "::ffff:127.0.0.1"}
SANDBOX_PORTS = {2024}  # the sandbox's own listener on 0.0.0.0, not Ray's


@contextmanager
def loopback_ray(head_cpus: float, workers: list[dict[str, Any]]) -> Iterator[Any]:
    """A cluster of a head and `workers` nodes on 127.0.0.1, this process its driver."""
    cluster = start_loopback_cluster(head_cpus, workers)
    connect_to_cluster(cluster)
    try:
        yield cluster
    finally:
        import_ray().shutdown()
        cluster.shutdown()


def ray_processes(driver: int | None = None) -> list[psutil.Process]:
    """Every process of Ray's (its servers, raylets, workers) and of the runs they start;
    with `driver`, also that process (a `dqnlab sweep`) and every process under it."""
    found = []
    if driver is not None:
        with contextlib.suppress(psutil.NoSuchProcess):
            parent = psutil.Process(driver)
            found = [parent, *parent.children(recursive=True)]
            for process in found:
                process.info = {"cmdline": _cmdline(process)}
    for process in psutil.process_iter(["cmdline"]):
        command = " ".join(process.info["cmdline"] or [])
        if "ray" in command.split("/")[-1] or "/ray/" in command or "ray::" in command:
            found.append(process)
    return list({process.pid: process for process in found}.values())


def _cmdline(process: psutil.Process) -> list[str]:
    try:
        return process.cmdline()
    except (psutil.NoSuchProcess, psutil.AccessDenied):
        return []


def non_loopback_sockets(driver: int | None = None) -> list[str]:
    """The TCP/UDP sockets of Ray's processes (and of `driver`'s, see `ray_processes`) with
    a local or remote address other than 127.0.0.1: what the loopback rule forbids."""
    bad = []
    for process in ray_processes(driver):
        try:
            connections = process.net_connections(kind="inet")
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
        for connection in connections:
            local = connection.laddr
            remote = connection.raddr
            if local and local.port in SANDBOX_PORTS:
                continue
            addresses = [local.ip] if local else []
            addresses += [remote.ip] if remote else []
            if any(address not in LOOPBACK_ADDRESSES for address in addresses):
                bad.append(f"{process.pid} {process.info['cmdline'][:2]}: {local} -> {remote}")
    return bad
