"""A real multi-node Ray cluster on this machine, every node on loopback.

``ray.cluster_utils.Cluster`` starts a head (GCS and a raylet) and worker
raylets as processes of their own: several nodes on one machine, each with its
CPU and memory resources. Ray listens on all interfaces and advertises the
machine's outside address unless ``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0`` is in
the environment of every Ray process (the design notes): set here, before
anything starts, and inherited by the servers the tests start (their drivers).
Ray starts its worker processes (the shard actors) at niceness 15 unless
``RAY_worker_niceness`` says otherwise: set to 0 here, as on a deployment's
nodes (docker/compose-cluster.yaml), so that the actors share these cores on
equal terms with the fronts, PostgreSQL and the lone servers the benchmarks
compare them with (docs/scaling.md). Node death is detected within a few
seconds (health checks each second).
"""
from __future__ import annotations

import os
import time

os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"
os.environ["RAY_worker_niceness"] = "0"

GiB = 1 << 30

#: the head's settings: a node that stops answering is dead after ~3 s
SYSTEM_CONFIG = {"health_check_initial_delay_ms": 1000, "health_check_period_ms": 1000,
                 "health_check_failure_threshold": 3}


class RayNodes:
    """A head and ``workers`` worker nodes (``cpus`` and ``memory`` bytes each),
    all on 127.0.0.1; :meth:`shutdown` (or leaving the ``with`` block) stops them.

    Attributes
    ----------
    address : str
        The head's GCS address (``serve --ray``).
    """

    def __init__(self, workers: int = 2, *, cpus: int = 1, memory: int = 4 * GiB,
                 head_memory: int | None = None) -> None:
        from ray.cluster_utils import Cluster

        self.cpus, self.memory = cpus, memory
        self.cluster = Cluster(initialize_head=True, connect=False, head_node_args={
            "num_cpus": cpus, "memory": memory if head_memory is None else head_memory,
            "node_ip_address": "127.0.0.1", "_system_config": SYSTEM_CONFIG})
        self.workers = [self.add_worker() for _ in range(workers)]
        self.cluster.wait_for_nodes()
        self.address = self.cluster.address

    def add_worker(self):
        return self.cluster.add_node(num_cpus=self.cpus, memory=self.memory,
                                     node_ip_address="127.0.0.1")

    def kill(self, node) -> None:
        """The node dies (its raylet and its workers: the actors on it)."""
        self.cluster.remove_node(node, allow_graceful=False)
        if node in self.workers:
            self.workers.remove(node)

    def shutdown(self) -> None:
        self.cluster.shutdown()
        time.sleep(0.5)

    def __enter__(self) -> "RayNodes":
        return self

    def __exit__(self, *exc) -> None:
        self.shutdown()


def assigned_resources(actor, timeout: float = 60.0) -> dict:
    """The resources Ray assigned to an actor's process (asked inside it, from a
    driver connected to its cluster)."""
    import ray

    return ray.get(actor.__ray_call__.remote(
        lambda self: ray.get_runtime_context().get_assigned_resources()), timeout=timeout)


def unbuilt_checkout(tmp) -> tuple[dict[str, str], "os.PathLike"]:
    """A front's setting of the README: flatserve installed (a wheel, its extension
    built) and started from inside a source checkout that has no built extension.

    Returns the environment for the Ray nodes and the front (the installed package
    first on ``PYTHONPATH``) and the checkout's directory (the front's working
    directory). The installed package is a copy of the one this process imports,
    with its extension; the checkout a copy of its Python sources only. This
    repository's own install is editable: its import finder sends ``flatserve``
    to the source tree whatever ``sys.path`` says, except in a process whose
    ``SKBUILD_EDITABLE_SKIP`` names its build directory (scikit-build-core's rule
    for builds): set here, so that imports follow ``sys.path`` as they do for a
    wheel.
    """
    import shutil
    import sys
    from pathlib import Path

    import flatserve
    import flatserve._core as core

    tmp = Path(tmp)
    src = Path(flatserve.__file__).parent
    skip = shutil.ignore_patterns("__pycache__", "_core*.so", "_core*.pyd")
    installed, checkout = tmp / "site", tmp / "checkout"
    shutil.copytree(src, installed / "flatserve", ignore=skip)
    shutil.copy2(core.__file__, installed / "flatserve")
    shutil.copytree(src, checkout / "flatserve", ignore=skip)
    (checkout / "pyproject.toml").write_text("[project]\nname = \"flatserve\"\n")
    env = {"PYTHONPATH": os.pathsep.join(
        [str(installed), *filter(None, [os.environ.get("PYTHONPATH")])])}
    builds = [f.path for f in sys.meta_path
              if type(f).__name__ == "ScikitBuildRedirectingFinder" and getattr(f, "path", None)]
    if builds:
        env["SKBUILD_EDITABLE_SKIP"] = os.pathsep.join(builds)
    return env, checkout
