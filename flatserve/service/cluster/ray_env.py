"""The cluster mode's one door to Ray: connecting a front (:func:`connect`, its
workers' runtime environment :data:`WORKER_ENV`), where actors may go
(:func:`machine_pin`, :func:`nodes_with`, :func:`one_machine`), an actor's node
(:func:`node_id`, :func:`node_cpus`) and a worker's own error (:func:`task_cause`).
Ray is imported here only, on first use (:func:`ray_api`; the ``cluster`` extra).
"""
from __future__ import annotations

import logging

from ..status import ShardUnavailableError


def ray_api():
    """Ray, with ``ray.exceptions``, ``ray.util`` and its scheduling strategies
    (ImportError without the ``cluster`` extra: :func:`connect` names it)."""
    import ray
    import ray.exceptions
    import ray.util
    import ray.util.scheduling_strategies  # noqa: F401  (reached as ray.util....)

    return ray


def node_id() -> str:
    """The id of the Ray node this process runs on."""
    return ray_api().get_runtime_context().get_node_id()


def task_cause(exc: Exception) -> Exception:
    """The worker's own error inside Ray's ``RayTaskError`` (else the error itself)."""
    cause = getattr(exc, "cause", None)
    return cause if isinstance(cause, Exception) else exc


def node_cpus() -> int:
    """The CPUs of the Ray node this process runs on (its ``num_cpus``, not the
    machine's cores; at least 1): the threads of an actor's pool."""
    me = node_id()
    for n in ray_api().nodes():
        if n.get("NodeID") == me:
            return max(1, int(n.get("Resources", {}).get("CPU", 1)))
    return 1


#: seconds the head's address gets to answer a TCP connection before it is called unreachable
PROBE_TIMEOUT_S = 10.0


def probe_address(address: str, timeout: float = PROBE_TIMEOUT_S) -> None:
    """Fail fast when nothing answers at the head's ``host:port`` (Ray's own client
    retries for minutes); ``auto`` and ``ray://`` addresses are left to Ray.

    Raises
    ------
    ShardUnavailableError
        Naming the address and what the connection said.
    """
    if address == "auto" or "://" in address or ":" not in address:
        return
    import socket

    host, _, port = address.rpartition(":")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout):
            return
    except (OSError, ValueError) as exc:
        raise ShardUnavailableError(f"ray: the Ray cluster at {address!r} cannot be reached: "
                                    f"{exc}") from None


def import_installed() -> None:
    """Run first in every worker process of a front's job (:data:`WORKER_ENV`): it
    imports ``flatserve`` and its extension, the installed package, before Ray puts
    the front's working directory first on ``sys.path`` (a source checkout, whose
    extension is not built: docs/design.md, "Workers import the installed package")."""
    from ... import _core  # noqa: F401  (the extension: fails here, named, if missing)


#: the runtime environment of a front's Ray job (tile actors inherit it from the shard
#: actor that makes them): :func:`import_installed` first
WORKER_ENV = {"worker_process_setup_hook": f"{__name__}.import_installed"}


def connect(settings) -> None:
    """Connect this process to the Ray cluster at ``settings.ray`` (once).

    Raises
    ------
    ShardUnavailableError
        Ray is not installed, or the cluster cannot be reached (naming the address).
    """
    try:
        ray = ray_api()
    except ImportError as exc:
        raise ShardUnavailableError(
            "ray: cluster mode needs the cluster extra: pip install 'flatserve[cluster]' "
            f"({exc})") from None
    if ray.is_initialized():
        return
    probe_address(settings.ray)
    try:
        ray.init(address=settings.ray, namespace=settings.ray_namespace, log_to_driver=False,
                 logging_level=logging.WARNING, runtime_env=WORKER_ENV)
    except Exception as exc:
        raise ShardUnavailableError(
            f"ray: the Ray cluster at {settings.ray!r} cannot be reached: "
            f"{type(exc).__name__}: {exc}") from None


#: the share of a node's ``node:<address>`` resource (Ray gives each node 1 of its
#: own address's) an actor asks for to be placed on a node of that address: Ray's
#: resolution, so that it never limits how many actors a node holds (10,000)
PIN_SHARE = 0.0001


def machine_pin(ray, settings) -> dict[str, float]:
    """The resources that keep an actor on this machine's nodes on SQLite (its
    workers read this machine's data directory): a share of the ``node:<address>``
    resource Ray gives every node of this address. Empty with a ``database_url``."""
    if settings.database_url is not None:
        return {}
    return {f"node:{ray.util.get_node_ip_address()}": PIN_SHARE}


def nodes_with(ray, need: dict[str, float]) -> list[dict]:
    """The live nodes of the cluster (``ray.nodes()``) whose resources, in all, hold
    ``need`` (an actor asking for it can be placed there once they are free)."""
    return [n for n in ray.nodes() if n.get("Alive")
            and all(n.get("Resources", {}).get(r, 0) >= v for r, v in need.items())]


def one_machine(ray, settings) -> None:
    """Cluster mode on SQLite: every node of the cluster is on this machine (the shard
    workers read its data directory; a node that joins from elsewhere later holds no
    actor of this deployment's, :func:`machine_pin`).

    Raises
    ------
    ShardUnavailableError
        A node is on another machine (naming it).
    """
    here = ray.util.get_node_ip_address()
    away = sorted({n.get("NodeManagerAddress") for n in ray.nodes() if n.get("Alive")}
                  - {here})
    if away:
        raise ShardUnavailableError(
            f"ray: cluster mode on SQLite (no database_url) needs every node of the cluster on "
            f"this machine ({here}), whose data directory {settings.data_dir} the shards read; "
            f"nodes at {', '.join(away)} are elsewhere: name a PostgreSQL database in "
            "database_url for a cluster of several machines")


def rss_bytes() -> int:
    """Resident memory of this process (``/proc/self/status``; 0 where unknown)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
    except OSError:  # pragma: no cover - not Linux
        pass
    return 0
