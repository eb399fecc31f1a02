"""The container image, built from this repository and run as a user would.

Needs a Docker engine (``make test`` installs Debian's ``docker.io``:
``scripts/install-system-deps.sh --docker``). The session fixture starts the
engine if it is installed but not running (``scripts/docker-engine.sh``) and
builds the ``debian:bookworm-slim`` base from the Debian mirror when no
registry has it (``scripts/docker-base.sh``). The image is built once per
session (``DOCKER_BUILDKIT=1 docker build --network host``), with the CA bundle
named by ``SSL_CERT_FILE`` / ``PIP_CERT`` / ``REQUESTS_CA_BUNDLE`` handed to pip
as a build secret. The build log goes to a file that is dumped on failure;
progress lines reach the terminal even without ``pytest -s``.

Then a container serves on a named volume with an API key, takes uploads,
is ``docker kill``-ed, and a new container on the same volume must answer
with every acknowledged sample. And two containers serve one PostgreSQL on the
host (a throwaway cluster, tests/conftest.py): a write through one is read
through the other with its log position; a third container with nothing but
the database URL catches up. And the image as both halves of cluster mode: a
container running a Ray head node (``ray start --head --block``, the shard
actors run there, importing flatserve from the image's venv) and a front
container (``flatserve serve`` with ``FLATSERVE_RAY``, on a Ray node of its own
that offers nothing) on the same PostgreSQL; every Ray process binds and
advertises 127.0.0.1 only (``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0``).
"""
from __future__ import annotations

import os
import re
import shutil
import socket
import subprocess
import time
import uuid
from pathlib import Path

import numpy as np
import pytest

from flatserve.client import Client, ServiceError
from tests.harness.process import free_port

REPO = Path(__file__).resolve().parent.parent
IMAGE = "flatserve:test"
#: A cold build: Debian packages, the Python dependencies, CGAL compiled on two
#: cores, every layer copied in full by the vfs storage driver.
BUILD_TIMEOUT_S = 40 * 60
READY_TIMEOUT_S = 180


def docker_cli() -> str:
    """The client that came with the engine (Debian's ``docker.io``) first: a
    newer stand-alone client may refuse BuildKit builds without its buildx
    plugin."""
    if os.environ.get("FLATSERVE_DOCKER"):
        return os.environ["FLATSERVE_DOCKER"]
    if os.access("/usr/bin/docker", os.X_OK):
        return "/usr/bin/docker"
    return shutil.which("docker") or "docker"


DOCKER = docker_cli()


def docker(*args: str, timeout: float = 120, check: bool = True) -> subprocess.CompletedProcess:
    p = subprocess.run([DOCKER, *args], capture_output=True, text=True, timeout=timeout)
    if check and p.returncode != 0:
        raise AssertionError(f"docker {' '.join(args)} failed ({p.returncode}):\n{p.stdout}\n{p.stderr}")
    return p


def ca_bundle() -> str | None:
    """The CA bundle the environment names, for pip inside the build."""
    for var in ("SSL_CERT_FILE", "PIP_CERT", "REQUESTS_CA_BUNDLE"):
        path = os.environ.get(var)
        if path and os.path.isfile(path):
            return path
    return None


def _say(config, line: str) -> None:
    """One progress line on the terminal, whatever pytest captures."""
    capman = config.pluginmanager.getplugin("capturemanager")
    tr = config.pluginmanager.getplugin("terminalreporter")
    if capman is None or tr is None:
        return
    with capman.global_and_fixture_disabled():
        tr.write_line(f"[docker] {line}")


def _run_script(config, script: str, log: Path, timeout: float) -> None:
    with open(log, "ab") as fh:
        p = subprocess.run(["bash", str(REPO / "scripts" / script)], stdout=fh,
                           stderr=subprocess.STDOUT, timeout=timeout)
    if p.returncode != 0:
        raise AssertionError(f"scripts/{script} failed ({p.returncode}); its output:\n{log.read_text()[-6000:]}")


@pytest.fixture(scope="session")
def docker_engine(request, tmp_path_factory):
    """A running engine and the base image (both made if missing)."""
    log = tmp_path_factory.mktemp("docker") / "engine.log"
    _run_script(request.config, "docker-engine.sh", log, timeout=180)
    if docker("image", "inspect", "debian:bookworm-slim", check=False).returncode != 0:
        _say(request.config, "no debian:bookworm-slim: building it with debootstrap (about 2 minutes)")
        _run_script(request.config, "docker-base.sh", log, timeout=20 * 60)
    return log


#: Free space the image's build and this module's containers need on the engine's
#: disk (vfs: a cold build stores about 6 GB of layers, every container a full copy
#: of the image's 0.6 GB, and a test runs up to three at once).
NEEDED_GB = 12


def _free_gb() -> float:
    root = docker("info", "--format", "{{.DockerRootDir}}").stdout.strip() or "/var/lib/docker"
    return shutil.disk_usage(root).free / 1e9


#: The label on this suite's containers and volumes: ``host:pid`` of the run that made them.
OWNER_LABEL = "flatserve-test.owner"
OWNER = f"{socket.gethostname()}:{os.getpid()}"


def _abandoned(owner: str) -> bool:
    """A container or volume of a run that is over: made by a process of this host that
    is gone (or unlabelled: made before the label). Another live run's are kept."""
    if not owner:
        return True
    host, _, pid = owner.rpartition(":")
    if host != socket.gethostname() or not pid.isdigit():
        return False  # another host's run (an engine shared between hosts): not ours to judge
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return True
    except PermissionError:  # alive, another user's
        return False
    return False


def _clean_up(config) -> None:
    """What earlier sessions left on the engine's disk: the containers and volumes of
    runs that are over (a run that was killed; a run still going on the same engine
    keeps its own), images no tag names any more (an earlier build of ``IMAGE``),
    and, when space is short, the whole build cache. A disk that fills across CI
    runs on one machine otherwise ends as ``no space left on device``."""
    label = '{{.Label "%s"}}' % OWNER_LABEL
    for kind, ls in (("container", ["ps", "-a", "--format", "{{.ID}} " + label]),
                     ("volume", ["volume", "ls", "--format", "{{.Name}} " + label])):
        rows = docker(*ls, "--filter", "name=flatserve-test-", check=False).stdout.splitlines()
        ids = [r.split(" ", 1)[0] for r in rows
               if r.strip() and _abandoned(r.split(" ", 1)[1].strip() if " " in r else "")]
        if ids:
            docker(*(["rm", "-f", "-v"] if kind == "container" else ["volume", "rm", "-f"]), *ids,
                   check=False)
    docker("image", "prune", "-f", check=False)
    if _free_gb() < NEEDED_GB:
        docker("builder", "prune", "-a", "-f", check=False, timeout=600)
    free = _free_gb()
    _say(config, f"{free:.1f} GB free on the engine's disk")
    if free < NEEDED_GB:
        raise AssertionError(f"the Docker engine's disk has {free:.1f} GB free after removing what "
                             f"earlier runs left; the image and its containers need about {NEEDED_GB} GB")


@pytest.fixture(scope="session")
def image(request, docker_engine, tmp_path_factory):
    """The image built from this checkout, once per session; afterwards the build
    cache this build did not use is dropped (an earlier source's layers), so the
    engine's disk holds one build's worth whatever the number of runs."""
    _clean_up(request.config)
    request.addfinalizer(lambda: (docker("builder", "prune", "-f", "--filter", "until=2h",
                                         check=False, timeout=600),
                                  docker("image", "prune", "-f", check=False)))
    log = tmp_path_factory.mktemp("docker-build") / "build.log"
    cmd = [DOCKER, "build", "--network", "host", "--progress", "plain",
           "-f", "docker/Dockerfile", "-t", IMAGE, "."]
    ca = ca_bundle()
    if ca:
        cmd[2:2] = ["--secret", f"id=ca,src={ca}"]
    env = dict(os.environ, DOCKER_BUILDKIT="1")
    _say(request.config, f"building {IMAGE} (log: {log}; a cold build takes several minutes)")
    t0 = time.monotonic()
    step = re.compile(r"^#\d+ \[[^\]]+\] ")
    with open(log, "w") as fh:
        fh.write(" ".join(cmd) + "\n")
        fh.flush()
        proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True, bufsize=1)
        seen = set()
        try:
            for line in proc.stdout:
                fh.write(line)
                if step.match(line) and line not in seen:  # BuildKit repeats a step's header
                    seen.add(line)
                    _say(request.config, f"{time.monotonic() - t0:6.0f} s  {line.strip()[:110]}")
                if time.monotonic() - t0 > BUILD_TIMEOUT_S:
                    proc.kill()
                    break
        finally:
            rc = proc.wait()
    elapsed = time.monotonic() - t0
    if rc != 0:
        raise AssertionError(f"docker build failed ({rc}) after {elapsed:.0f} s; the end of {log}:\n"
                             + log.read_text()[-8000:])
    size = docker("image", "inspect", IMAGE, "--format", "{{.Size}}").stdout.strip()
    _say(request.config, f"built {IMAGE} in {elapsed:.0f} s, {int(size) / 1e6:.0f} MB")
    return IMAGE


class Containers:
    """Containers and a volume of one test, removed whatever happens."""

    def __init__(self, image: str):
        self.image = image
        self.tag = uuid.uuid4().hex[:10]
        self.volume = f"flatserve-test-{self.tag}"
        self.names: list[str] = []
        docker("volume", "create", "--label", f"{OWNER_LABEL}={OWNER}", self.volume)

    def run(self, port: int, api_key: str, env: dict | None = None, volume: bool = True) -> str:
        """A container on the host's network; ``volume=False``: no data volume of
        its own (a replica on PostgreSQL keeps nothing)."""
        name = f"flatserve-test-{self.tag}-{len(self.names)}"
        self.names.append(name)
        extra = [a for k, v in (env or {}).items() for a in ("-e", f"{k}={v}")]
        if volume:
            extra += ["-v", f"{self.volume}:/var/lib/flatserve"]
        docker("run", "-d", "--name", name, "--label", f"{OWNER_LABEL}={OWNER}",
               "--network", "host",
               "-e", f"FLATSERVE_API_KEY={api_key}", "-e", f"FLATSERVE_PORT={port}",
               *extra, self.image)
        return name

    def start(self, command: list[str], env: dict, *options: str, shm_size: str = "512m") -> str:
        """A container running ``command`` on the host's network with the test's volume
        (a PID 1 that reaps, as compose's ``init: true``; more ``docker run`` options)."""
        name = f"flatserve-test-{self.tag}-{len(self.names)}"
        self.names.append(name)
        extra = [a for k, v in env.items() for a in ("-e", f"{k}={v}")]
        docker("run", "-d", "--init", "--name", name, "--label", f"{OWNER_LABEL}={OWNER}",
               "--network", "host",
               "--shm-size", shm_size, "-v", f"{self.volume}:/var/lib/flatserve", *options,
               *extra, self.image, *command)
        return name

    def running(self, name: str) -> bool:
        return docker("inspect", "-f", "{{.State.Running}}", name,
                      check=False).stdout.strip() == "true"

    def logs(self) -> str:
        out = []
        for name in self.names:
            p = docker("logs", "--tail", "60", name, check=False)
            out.append(f"--- docker logs {name} ---\n{p.stdout}{p.stderr}")
            # a Ray node's own logs (its processes' and its workers': an actor's traceback)
            p = docker("exec", name, "sh", "-c",
                       f"cd {RAY_TEMP}/session_latest/logs 2>/dev/null && "
                       "{ grep -v state-dump raylet.out | tail -n 15; "
                       "tail -n 25 gcs_server.err raylet.err worker-*.err; } 2>/dev/null",
                       check=False, timeout=30)
            if p.stdout.strip():
                out.append(f"--- Ray logs in {name} ---\n{p.stdout[-6000:]}")
        return "\n".join(out)

    def wait_ready(self, name: str, client: Client) -> None:
        end = time.monotonic() + READY_TIMEOUT_S
        while time.monotonic() < end:
            if client.ready():
                return
            state = docker("inspect", "-f", "{{.State.Running}}", name, check=False).stdout.strip()
            if state != "true":
                raise AssertionError(f"container {name} stopped before it was ready\n{self.logs()}")
            time.sleep(0.2)
        raise AssertionError(f"container {name} not ready after {READY_TIMEOUT_S} s\n{self.logs()}")

    def kill(self, name: str) -> None:
        docker("kill", name)  # SIGKILL: no shutdown handler runs

    def close(self) -> None:
        for name in self.names:
            docker("rm", "-f", "-v", name, check=False)  # with its anonymous volume
        docker("volume", "rm", "-f", self.volume, check=False)


@pytest.fixture
def containers(image):
    c = Containers(image)
    yield c
    c.close()


def paper_rays(rng: np.random.Generator, n: int):
    eyes = rng.uniform([-1, -1, -4.5], [1, 1, -1.5], (n, 3))
    screen = np.c_[rng.uniform(-1, 1, (n, 2)), np.zeros(n)]
    return eyes, screen - eyes


def test_image_holds_no_build_secret_and_no_compiler(image):
    p = docker("run", "--rm", "--network", "none", "--entrypoint", "sh", image, "-c",
               "id -un; ls -A /run/secrets 2>/dev/null; env | grep -E '^(PIP_CERT|SSL_CERT_FILE)=';"
               " command -v cc c++ g++ gcc cmake; true")
    assert p.stdout.split() == ["flatserve"], p.stdout


def test_container_keeps_acknowledged_samples_across_docker_kill(containers):
    rng = np.random.default_rng(11)
    key = uuid.uuid4().hex
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    qo, qd = paper_rays(rng, 400)

    # 1. a fresh container on an empty volume: uploads acknowledged once indexed
    first = containers.run(port, key)
    with Client(url, api_key=key, retries=0) as c:
        containers.wait_ready(first, c)
        with Client(url, retries=0) as anonymous, pytest.raises(ServiceError) as err:
            anonymous.create_field("nokey")
        assert err.value.status == 401
        c.create_field("docker", channels=2)
        acked = []
        for i in range(3):
            o, d = paper_rays(rng, 1500)
            acked.append(c.upload_rays("docker", o, d, rng.uniform(size=(1500, 2)),
                                       idempotency_key=f"a{i}"))
        before = c.describe("docker")
        q1 = c.query_rays("docker", qo, qd)
    assert before["nsamples"] == acked[-1]["nsamples"] == sum(a["accepted"] for a in acked)
    assert before["nsamples"] == 4500  # the default field, an atlas, charts every ray
    assert q1.inside.mean() > 0.5
    containers.kill(first)

    # 2. a new container on the same volume: the same samples, the same answers;
    #    then one more batch acknowledged before it is indexed (wait=false)
    second = containers.run(port, key)
    with Client(url, api_key=key, retries=0) as c:
        containers.wait_ready(second, c)
        after = c.wait_indexed("docker", timeout=120)
        assert after["nsamples"] == before["nsamples"]
        q2 = c.query_rays("docker", qo, qd)
        np.testing.assert_array_equal(q2.inside, q1.inside)
        np.testing.assert_array_equal(q2.values, q1.values)
        o4, d4 = paper_rays(rng, 2000)
        v4 = rng.uniform(size=(2000, 2))
        late = c.upload_rays("docker", o4, d4, v4, idempotency_key="late", wait=False)
    containers.kill(second)  # at once: the batch may not be indexed yet

    # 3. and once more: the late batch is there too, its samples answer their own rays
    third = containers.run(port, key)
    with Client(url, api_key=key, retries=0) as c:
        containers.wait_ready(third, c)
        final = c.wait_indexed("docker", timeout=120)
        assert final["nsamples"] == before["nsamples"] + late["accepted"]
        assert len(c.batches("docker")) == 4
        own = c.query_rays("docker", o4, d4)
        q3 = c.query_rays("docker", qo, qd)
    assert late["accepted"] == 2000 and late["rejected"] == []
    assert own.inside.mean() > 0.5
    hit = own.inside
    np.testing.assert_allclose(own.values[hit], v4[hit], rtol=0, atol=1e-9)
    assert q3.inside.sum() >= q1.inside.sum()


def test_two_containers_on_one_postgresql(containers, pg_cluster):
    """Replicas in containers on PostgreSQL running on the host (``--network host``):
    written through one, read through the other with the upload's position."""
    rng = np.random.default_rng(12)
    key = uuid.uuid4().hex
    env = {"FLATSERVE_DATABASE_URL": pg_cluster.create_database(f"docker_{containers.tag}")}
    ports = [free_port(), free_port()]
    names = [containers.run(p, key, env=env, volume=False) for p in ports]
    clients = [Client(f"http://127.0.0.1:{p}", api_key=key, retries=0) for p in ports]
    try:
        for name, c in zip(names, clients):
            containers.wait_ready(name, c)
        a, b = clients
        a.create_field("pg", channels=2)
        qo, qd = paper_rays(rng, 300)
        total = 0
        for i in range(4):
            writer, reader = (a, b) if i % 2 == 0 else (b, a)
            o, d = paper_rays(rng, 1500)
            v = rng.uniform(size=(1500, 2))
            rep = writer.upload_rays("pg", o, d, v, idempotency_key=f"k{i}", wait=bool(i % 2))
            total += rep["accepted"]
            own = reader.query_rays("pg", o, d, min_position=rep["position"])
            mine = np.ones(1500, bool)
            mine[rep["rejected"]] = False
            hit = mine & own.inside
            assert hit.mean() > 0.9
            np.testing.assert_allclose(own.values[hit], v[hit], rtol=0, atol=1e-9)
        head = rep["position"]
        qa = a.query_rays("pg", qo, qd, min_position=head)
        qb = b.query_rays("pg", qo, qd, min_position=head)
        np.testing.assert_array_equal(qa.values, qb.values)  # same position, same answers
        assert a.describe("pg", min_position=head)["nsamples"] == total
        containers.kill(names[0])
        # a new container with nothing but the database URL catches up
        port = free_port()
        third = containers.run(port, key, env=env, volume=False)
        with Client(f"http://127.0.0.1:{port}", api_key=key, retries=0) as c:
            containers.wait_ready(third, c)
            assert c.describe("pg", min_position=head)["nsamples"] == total
            np.testing.assert_array_equal(c.query_rays("pg", qo, qd, min_position=head).values,
                                          qa.values)
    finally:
        for c in clients:
            c.close()


#: the head's Ray directory (sockets, logs), on the test's volume
RAY_TEMP = "/var/lib/flatserve/ray"
#: every Ray process binds and advertises 127.0.0.1 only (the design notes)
LOOPBACK_RAY = {"RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0"}
#: a node holding shard actors runs them at niceness 0 (docker/compose-cluster.yaml)
SHARD_NODE = {**LOOPBACK_RAY, "RAY_worker_niceness": "0"}
MiB = 1 << 20


def ray_node_ports() -> list[str]:
    """Flags for a Ray node on the host's network: ports of its own where Ray's
    defaults are fixed (the dashboard agent's) or a shared range (the workers')."""
    return ["--node-ip-address", "127.0.0.1", "--dashboard-agent-listen-port", str(free_port()),
            "--min-worker-port", "0", "--max-worker-port", "0", "--disable-usage-stats"]


def shard_actors(name: str) -> int:
    """The shard actors (Ray workers titled ``ray::ShardActor``) in a container."""
    p = docker("exec", name, "sh", "-c",
               "cat /proc/[0-9]*/cmdline 2>/dev/null | tr '\\000' '\\n' | grep -c '^ray::ShardActor'",
               check=False, timeout=30)
    return int(p.stdout.strip() or 0)


def test_image_as_a_ray_head_node_and_a_front_on_it(containers, pg_cluster):
    """One image, two commands: a Ray head node holds the shard actors, a front routes
    to them; a field created, filled (wait=true) and queried through the front."""
    rng = np.random.default_rng(13)
    key = uuid.uuid4().hex
    gcs = free_port()
    address = f"127.0.0.1:{gcs}"
    # 1. the head: the cluster's control store and the only node with shard memory
    head = containers.start(
        ["ray", "start", "--head", "--port", str(gcs), "--block", "--num-cpus", "1",
         "--memory", str(2048 * MiB), "--object-store-memory", str(200 * MiB),
         "--include-dashboard", "false", "--temp-dir", RAY_TEMP, *ray_node_ports()],
        SHARD_NODE)
    end = time.monotonic() + READY_TIMEOUT_S
    while True:  # compose's health check of the head
        p = docker("exec", head, "ray", "health-check", "--address", address, check=False,
                   timeout=60)
        if p.returncode == 0:
            break
        if not containers.running(head) or time.monotonic() > end:
            raise AssertionError(f"the Ray head in {head} did not come up at {address} "
                                 f"({p.stdout}{p.stderr})\n{containers.logs()}")
        time.sleep(1.0)

    # 2. a front: plain `flatserve serve` with FLATSERVE_RAY, a driver on the head's node.
    #    A Ray driver needs a raylet on its own machine; a deployment runs a resource-less
    #    node in the front's container (docker/compose-cluster.yaml: `ray start --address`),
    #    which the loopback-only switch forbids (`ray start` refuses to join a second node
    #    with RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0). Here the front sees the head's raylet:
    #    the head's processes (--pid) and its Ray directory (the volume).
    port = free_port()
    env = {**LOOPBACK_RAY, "FLATSERVE_RAY": address, "FLATSERVE_API_KEY": key,
           "FLATSERVE_PORT": str(port),
           "FLATSERVE_DATABASE_URL": pg_cluster.create_database(f"ray_{containers.tag}"),
           "FLATSERVE_RAY_SHARDS": "2", "FLATSERVE_RAY_SHARD_MEMORY": str(256 * MiB),
           "FLATSERVE_RAY_NAMESPACE": f"test-{containers.tag}"}
    front = containers.start(["flatserve", "serve"], env, "--pid", f"container:{head}")
    url = f"http://127.0.0.1:{port}"
    with Client(url, api_key=key, retries=0, timeout=180) as c:
        containers.wait_ready(front, c)
        try:
            info = c.create_field("ray", channels=2)
            total = 0
            for i in range(2):
                o, d = paper_rays(rng, 1500)
                rep = c.upload_rays("ray", o, d, rng.uniform(size=(1500, 2)),
                                    idempotency_key=f"r{i}", wait=True)
                total += rep["accepted"]
            qo, qd = paper_rays(rng, 500)
            end = time.monotonic() + 120
            while True:
                try:
                    q = c.query_rays("ray", qo, qd, min_position=rep["position"])
                    break
                except ServiceError as exc:  # a shard still restoring: 503, never a partial answer
                    if exc.status != 503 or time.monotonic() > end:
                        raise
                    time.sleep(1.0)
            own = c.query_rays("ray", o, d, min_position=rep["position"])
            end = time.monotonic() + 60
            while True:  # the shards report their sizes to the front each second
                described = c.describe("ray", min_position=rep["position"])
                if described["nsamples"] == total or time.monotonic() > end:
                    break
                time.sleep(0.5)
        except (ServiceError, AssertionError, OSError) as exc:
            raise AssertionError(f"cluster mode in containers failed: {exc!r}\n"
                                 f"{containers.logs()}") from exc
    context = f"\n{containers.logs()}"
    assert info["ncharts"] > 1, info  # an atlas: its charts dealt into 2 shard groups
    assert total == 3000 and described["nsamples"] == total, (described, context)
    assert q.inside.mean() > 0.5, (q.inside.mean(), context)
    assert np.isfinite(q.values[q.inside]).all(), context
    assert own.inside.mean() > 0.9, (own.inside.mean(), context)
    assert np.isfinite(own.values[own.inside]).all(), context
    # the actors are Ray workers of the head's node (a process each)
    assert shard_actors(head) == 2, (shard_actors(head), context)
