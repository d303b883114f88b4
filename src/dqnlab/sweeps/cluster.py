"""The Ray cluster a sweep runs on: a loopback-only one on this machine, or a running one.

`--address local` (the default) starts a Ray head on this machine with
`ray.cluster_utils.Cluster`, every process bound to 127.0.0.1 (nothing listens on the
machine's outward address), and connects to it. `auto`, `HOST:PORT` and
`ray://HOST:PORT` join a cluster that is already running (`auto` as Ray finds it:
RAY_ADDRESS, else the cluster `ray start` last started here); only a loopback HOST gets
the loopback treatment, a real cluster's address is used as Ray resolves it.

Ray is imported here, inside functions, so that `dqnlab --help` and the rest of the
package never import it.
"""

from __future__ import annotations

import contextlib
import logging
import os
import socket
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import psutil

from dqnlab.errors import DqnlabError

LOOPBACK = "127.0.0.1"
LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "::1")
REACH_TIMEOUT_SECONDS = 3.0  # an address that does not answer a TCP connect in this is down
# A dependency of dqnlab: missing only where it was left out of an install by hand.
RAY_INSTALL = 'pip install "ray>=2.40,<3"'
# Start-up work a sweep does not need: no usage report (it would reach the internet), no
# dashboard, no import warnings.
RAY_ENVIRONMENT = {"RAY_USAGE_STATS_ENABLED": "0", "RAY_DISABLE_IMPORT_WARNING": "1"}
# 0: Ray treats the machine as a one-machine Ray, whose node address is 127.0.0.1 (the
# switch Windows and macOS default to; `ray._private.ray_constants.ENABLE_RAY_CLUSTER`).
LOOPBACK_ONLY_VARIABLE = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"


# The driver prints its own lines: no Ray INFO lines, no copy of every worker's output.
QUIET_DRIVER: dict[str, Any] = {"log_to_driver": False, "logging_level": logging.WARNING}


def import_ray() -> Any:
    """The `ray` module, or a one-line error saying how to install it."""
    try:
        import ray
    except ImportError:
        raise DqnlabError(
            f"dqnlab sweep runs on Ray, which is not installed: {RAY_INSTALL}"
        ) from None
    return ray


def keep_loopback_addresses() -> None:
    """Make Ray keep 127.0.0.1 as 127.0.0.1 when a driver connects.

    Ray (checked with 2.60.0; the same code since 2.9) "canonicalizes" a loopback
    bootstrap address and `_node_ip_address` to the machine's outward address
    (`ray._private.services.resolve_ip_for_localhost`), and would then connect to a head
    that listens on loopback only through the outward address: traffic this project may
    not send, to a port nothing listens on. The replacement returns loopback hosts as
    they are and asks Ray for any other host, so a real cluster's address is untouched."""
    from ray._private import services

    original = services.resolve_ip_for_localhost
    if getattr(original, "keeps_loopback", False):
        return

    def resolve_ip_for_localhost(host: str) -> str:
        return host if host in LOOPBACK_HOSTS else original(host)

    resolve_ip_for_localhost.keeps_loopback = True  # type: ignore[attr-defined]
    services.resolve_ip_for_localhost = resolve_ip_for_localhost


def set_ray_environment() -> None:
    """RAY_ENVIRONMENT in this process and so in every Ray process it starts."""
    for name, value in RAY_ENVIRONMENT.items():
        os.environ.setdefault(name, value)


@dataclass
class Connection:
    """A driver's connection to Ray, and the local cluster it started, if it did."""

    address: str
    local_cluster: Any = None  # ray.cluster_utils.Cluster when `--address local`
    connected_here: bool = True  # False: the caller had connected already, keep it

    def close(self) -> None:
        ray = import_ray()
        if self.connected_here:
            ray.shutdown()
        if self.local_cluster is not None:
            self.local_cluster.shutdown()


def start_loopback_cluster(
    head_cpus: float, worker_nodes: list[dict[str, Any]] | None = None, **head_args: Any
) -> Any:
    """A Ray cluster on this machine whose every process binds to 127.0.0.1: a head with
    `head_cpus` CPUs for runs (0: the head only schedules), then one node per entry of
    `worker_nodes` (keyword arguments of `Cluster.add_node`, e.g. num_cpus, memory).
    `head_args` go to the head's `add_node` too (ray_client_server_port=PORT serves
    `ray://127.0.0.1:PORT`, on loopback like the rest)."""
    import_ray()
    from ray.cluster_utils import Cluster

    set_ray_environment()
    # Inherited by every process the cluster starts (and theirs): Ray's own switch for a
    # one-machine Ray, under which `resolve_ip_for_localhost` answers 127.0.0.1 instead of
    # the outward address. It reaches the processes this one does not patch: the Ray
    # Client server's per-driver server joined the head through the outward address
    # without it (and timed out: nothing listens there).
    os.environ[LOOPBACK_ONLY_VARIABLE] = "0"
    cluster = Cluster(
        initialize_head=True,
        head_node_args={
            "num_cpus": head_cpus,
            "include_dashboard": False,
            "node_ip_address": LOOPBACK,
            **head_args,
        },
    )
    for node in worker_nodes or []:
        cluster.add_node(node_ip_address=LOOPBACK, **node)
    return cluster


def connect_to_cluster(cluster: Any) -> None:
    """Connect this process as a driver to the loopback `cluster` (see
    `keep_loopback_addresses`)."""
    ray = import_ray()
    keep_loopback_addresses()
    ray.init(
        address=cluster.address, _node_ip_address=LOOPBACK, **QUIET_DRIVER,
    )  # fmt: skip


def connect(address: str) -> Connection:
    """Connect to Ray as `--address` says: `local` starts a loopback cluster of this
    machine's cores; `auto`, `HOST:PORT` or `ray://HOST:PORT` join a running one (checked
    to answer first, so that a wrong address fails in seconds with one line). A process
    already connected (tests, a Ray job) keeps its connection."""
    ray = import_ray()
    set_ray_environment()
    if ray.is_initialized():
        return Connection(address, connected_here=False)
    if address == "local":
        cluster = start_loopback_cluster(head_cpus=psutil.cpu_count() or 1)
        try:
            connect_to_cluster(cluster)
        except BaseException:
            cluster.shutdown()  # not left running behind a failed start
            raise
        return Connection(cluster.address, local_cluster=cluster)
    target = find_auto_address() if address == "auto" else address
    host, port = parse_address(target)
    check_reachable(address if target == address else f"auto ({target})", host, port)
    keep_loopback_addresses()  # changes nothing for a host that is not loopback
    options: dict[str, Any] = dict(QUIET_DRIVER)
    if host in LOOPBACK_HOSTS and not target.startswith("ray://"):
        options["_node_ip_address"] = LOOPBACK
    try:
        ray.init(address=target, **options)
    except (ConnectionError, RuntimeError, ValueError) as error:
        first_line = str(error).strip().splitlines()[0] if str(error).strip() else ""
        raise DqnlabError(
            f"--address {address}: cannot join a Ray cluster ({first_line}); accepted: "
            "local, auto (a cluster started on this node with `ray start`), HOST:PORT or "
            "ray://HOST:PORT"
        ) from None
    return Connection(address)


@contextlib.contextmanager
def connected(address: str) -> Iterator[Connection]:
    """Connected to Ray as `--address` says (`connect`) for the block; a local cluster
    started here ends with it."""
    connection = connect(address)
    try:
        yield connection
    finally:
        connection.close()


def find_auto_address() -> str:
    """The cluster `--address auto` joins, found as Ray finds it: RAY_ADDRESS (set for a
    `ray job submit` entrypoint), else the cluster last started on this node (`ray start`
    writes its address under Ray's temporary directory). Resolved here rather than by
    `ray.init`, so that a loopback cluster is joined on loopback (see
    `keep_loopback_addresses`) and a missing one fails with one line."""
    from ray._private import services

    try:
        found = services.get_ray_address_from_environment("auto", None)
    except ConnectionError:
        found = None
    if not found or found == "auto":
        raise DqnlabError(
            "--address auto: no running Ray cluster found on this node (RAY_ADDRESS is not "
            "set and no `ray start` left its address); start one with `ray start --head`, "
            "or use --address local or HOST:PORT"
        )
    return str(found)


def parse_address(address: str) -> tuple[str, int]:
    """HOST and PORT of `HOST:PORT` or `ray://HOST:PORT`, or a one-line error."""
    bare = address.removeprefix("ray://")
    host, sep, port = bare.rpartition(":")
    if not sep or not host or not port.isdigit():
        raise DqnlabError(
            f"--address {address!r} is not one of: local, auto, HOST:PORT, ray://HOST:PORT"
        )
    return host.strip("[]"), int(port)


def check_reachable(address: str, host: str, port: int) -> None:
    """A short TCP connect to the address the user gave: a cluster that is not there
    fails now, not after Ray's own minute of retries."""
    try:
        with socket.create_connection((host, port), timeout=REACH_TIMEOUT_SECONDS):
            pass
    except OSError as error:
        raise DqnlabError(
            f"--address {address}: nothing answers at {host}:{port} ({error.strerror or error}); "
            "start the cluster first (`ray start --head`) or use --address local"
        ) from None


def node_resources() -> list[dict[str, float]]:
    """The total resources of every live node (CPU, GPU, memory in bytes, ...)."""
    ray = import_ray()
    return [dict(node["Resources"]) for node in ray.nodes() if node.get("Alive")]


def node_names() -> dict[str, str]:
    """Host name (or address) of every node, by node id."""
    ray = import_ray()
    return {
        node["NodeID"]: str(node.get("NodeManagerHostname") or node.get("NodeManagerAddress"))
        for node in ray.nodes()
    }
