"""The cluster mode's one door to Ray: connecting a front, and what its actors ask of Ray.

Every module of the cluster wing that needs Ray's own calls (connecting, the
nodes and their resources, the cause inside a ``RayTaskError``) finds them
here: :func:`connect` (a front's connection, its runtime environment
:data:`WORKER_ENV` and the fast probe of the head's address),
:func:`machine_pin`, :func:`nodes_with` and :func:`one_machine` (where the
actors of a deployment on SQLite may go), :func:`node_cpus` (an actor's
threads, :func:`node_id`) and :func:`task_cause`. Ray itself is imported
here only, on first use (:func:`ray_api`; the ``cluster`` extra: the library
and the one-machine service do not need it), so that a missing extra is a
named error of :func:`connect`.
"""
from __future__ import annotations

import logging

from ..status import ShardUnavailableError


def ray_api():
    """Ray, with the parts of it the cluster wing calls (``ray.exceptions``,
    ``ray.util``, ``ray.util.scheduling_strategies``): the one place the cluster
    mode imports it, on first use (the ``cluster`` extra).

    Raises
    ------
    ImportError
        Ray is not installed (:func:`connect` names the extra).
    """
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
    machine's cores): the threads of a shard actor's pool, so that a node of one
    CPU inserts on one thread (at least 1)."""
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
    """Run first in every worker process of a front's job (Ray's
    ``worker_process_setup_hook``, :data:`WORKER_ENV`): importing this module
    imports ``flatserve`` and its extension from where the worker's interpreter
    finds them, the installed package, before the worker runs its first task.

    Ray puts the driver's working directory (and script directory) first on its
    workers' ``sys.path`` when they take their first task; a front started inside a
    source checkout would have its actors import the checkout, whose extension is
    not built (``cannot import name '_core'``): every shard actor would die at
    creation. Once imported here, ``flatserve`` stays the installed package in that
    process whatever comes first on ``sys.path`` later.
    """
    from ... import _core  # noqa: F401  (the extension: fails here, named, if missing)


#: the runtime environment of a front's Ray job: its shard and tile actors (tile
#: actors inherit it from the shard actor that makes them) import the installed
#: package whatever the front's working directory (:func:`import_installed`)
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
    """The resources that keep an actor on this machine's nodes in cluster mode on
    SQLite (its shard and tile workers read this machine's data directory): a
    share of the ``node:<address>`` resource Ray gives every node of this
    machine's address, so that a node that joins from elsewhere later holds none
    of them. Empty with a ``database_url`` (every node reaches the database).

    Called by a front (its own address) and by a shard actor for its tiles (the
    shard's node, itself pinned to the front's machine).
    """
    if settings.database_url is not None:
        return {}
    return {f"node:{ray.util.get_node_ip_address()}": PIN_SHARE}


def nodes_with(ray, need: dict[str, float]) -> list[dict]:
    """The live nodes of the cluster (``ray.nodes()``) whose resources, in all, hold
    ``need`` (an actor asking for it can be placed there once they are free)."""
    return [n for n in ray.nodes() if n.get("Alive")
            and all(n.get("Resources", {}).get(r, 0) >= v for r, v in need.items())]


def one_machine(ray, settings) -> None:
    """Cluster mode on SQLite: every node of the cluster is on this machine (the
    shard workers read the data directory this server holds, :class:`~.worker.shard.ShardWorker`).
    A node that joins from elsewhere later is not refused, but holds no actor of
    this deployment's (:func:`machine_pin`).

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
