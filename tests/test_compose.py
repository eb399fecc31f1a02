"""docker/compose.yaml, docker/compose-cluster.yaml and docker/nginx.conf agree
with each other and with the service: no registry is reachable where the suite
runs, so the deployments they describe are not started here
(tests/test_docker.py runs the image itself: two containers on one PostgreSQL,
and a Ray head node with a front on it); these checks catch the drift a rename,
a new limit or a moved port would cause."""
from __future__ import annotations

import re
from pathlib import Path

import yaml

from flatserve.service.log.backend import backend_class
from flatserve.service.settings import Settings

DOCKER = Path(__file__).resolve().parent.parent / "docker"


def compose(name: str = "compose.yaml") -> dict:
    return yaml.safe_load((DOCKER / name).read_text())


def cluster() -> dict:
    return compose("compose-cluster.yaml")


def nginx() -> str:
    return re.sub(r"#.*", "", (DOCKER / "nginx.conf").read_text())


def replicas(services: dict) -> dict:
    return {k: v for k, v in services.items() if k.startswith("flatserve-")}


def check_server(name: str, svc: dict, user: str, db: str) -> dict:
    """A flatserve service of a compose file: every variable a setting of the server
    (a typo would be ignored silently), on the compose file's PostgreSQL, with a key,
    from the one image. Its environment."""
    env = svc["environment"]
    assert {k.removeprefix("FLATSERVE_").lower() for k in env} <= set(Settings.model_fields), name
    url = env["FLATSERVE_DATABASE_URL"]
    m = re.fullmatch(r"postgresql://([^:]+):\$\{POSTGRES_PASSWORD[^}]*\}@postgres:5432/(\w+)", url)
    assert m and m.groups() == (user, db), url
    assert backend_class(url).__name__ == "PostgresBackend"
    assert "FLATSERVE_API_KEY" in env and svc["image"] == "flatserve:latest"
    return env


def test_three_replicas_on_postgres_behind_nginx():
    services = compose()["services"]
    reps = replicas(services)
    assert len(reps) == 3
    pg = services["postgres"]
    assert pg["image"].startswith("postgres:")
    assert pg["healthcheck"]["test"][:2] == ["CMD", "pg_isready"]
    user, db = pg["environment"]["POSTGRES_USER"], pg["environment"]["POSTGRES_DB"]
    for name, svc in reps.items():
        check_server(name, svc, user, db)
        assert svc["depends_on"]["postgres"]["condition"] == "service_healthy"
        assert svc["build"]["dockerfile"] == "docker/Dockerfile"
    lb = services["lb"]
    assert lb["image"].startswith("nginx:")
    assert set(lb["depends_on"]) == set(reps)
    assert any(v.startswith("./nginx.conf:/etc/nginx/conf.d/default.conf") for v in lb["volumes"])
    (port,) = lb["ports"]
    assert port.endswith(":80")


def test_nginx_sends_to_every_replica_and_lets_their_limits_decide():
    conf = nginx()
    servers = re.findall(r"^\s*server\s+([\w.-]+):(\d+)\b", conf, re.M)
    assert sorted(servers) == sorted((name, "8000") for name in replicas(compose()["services"]))
    dockerfile = (DOCKER / "Dockerfile").read_text()
    assert "FLATSERVE_PORT=8000" in dockerfile
    assert re.search(r"^\s*listen\s+80;", conf, re.M)
    assert re.search(r"proxy_pass\s+http://flatserve;", conf)
    size = re.search(r"client_max_body_size\s+(\d+)([km]?);", conf)
    limit = int(size.group(1)) * {"": 1, "k": 1 << 10, "m": 1 << 20}[size.group(2)]
    assert limit >= Settings().max_body_bytes
    assert "proxy_request_buffering off;" in conf  # bodies stream to the replica
    # uploads are POSTs: nginx must not replay them on another replica
    assert "non_idempotent" not in conf
    # every brace closes (a cheap syntax check; the image's nginx -t is the real one)
    assert conf.count("{") == conf.count("}")


# -- docker/compose-cluster.yaml: fronts on PostgreSQL and a Ray cluster ---------------------------

#: ``${VAR:-default}`` (what compose substitutes when VAR is unset)
DEFAULTED = re.compile(r"\$\{(\w+):-([^}]*)\}")


def by_default(value) -> str:
    """A value as compose gives it with none of the optional variables set."""
    return DEFAULTED.sub(lambda m: m.group(2), str(value))


def option(command: list[str], flag: str) -> str:
    """The value after ``flag`` in a command (exactly once)."""
    assert command.count(flag) == 1, (flag, command)
    return command[command.index(flag) + 1]


def ray_head(services: dict) -> tuple[str, int]:
    (name,) = [k for k, v in services.items() if "--head" in v.get("command", [])]
    return name, int(option(services[name]["command"], "--port"))


def ray_workers(services: dict) -> dict:
    return {k: v for k, v in services.items() if k.startswith("ray-worker-")}


def front_script(svc: dict) -> str:
    """A front's command: ``sh -c SCRIPT``."""
    cmd = svc["command"]
    assert cmd[:2] == ["sh", "-c"] and len(cmd) == 3, cmd
    return cmd[2]


def front_ray_start(svc: dict) -> list[str]:
    """The ``ray start`` a front runs before it serves (its driver's raylet)."""
    first, rest = front_script(svc).split("&&")
    assert rest.split() == ["exec", "flatserve", "serve"], rest
    return first.split()


def test_cluster_fronts_use_postgres_and_the_ray_head():
    services = cluster()["services"]
    fronts = replicas(services)
    assert len(fronts) == 3
    # the same PostgreSQL service as the replicas' compose file
    assert services["postgres"] == compose()["services"]["postgres"]
    pg = services["postgres"]
    user, db = pg["environment"]["POSTGRES_USER"], pg["environment"]["POSTGRES_DB"]
    head, port = ray_head(services)
    for name, svc in fronts.items():
        env = check_server(name, svc, user, db)
        assert env["FLATSERVE_RAY"] == f"{head}:{port}"
        assert svc["build"]["dockerfile"] == "docker/Dockerfile"
        assert svc["depends_on"]["postgres"]["condition"] == "service_healthy"
        assert svc["depends_on"][head]["condition"] == "service_healthy"
        # the server takes these settings as they stand (cluster mode validates its database)
        values = {k.removeprefix("FLATSERVE_").lower(): by_default(v) for k, v in env.items()
                  if "${" not in by_default(v)}
        s = Settings(**values, database_url=env["FLATSERVE_DATABASE_URL"].replace("${", "").replace("}", ""),
                     api_key="k" * 32)
        assert s.ray == f"{head}:{port}" and s.port == 8000
        # its driver's raylet joins the cluster at FLATSERVE_RAY and offers nothing
        start = front_ray_start(svc)
        assert start[:2] == ["ray", "start"] and "--block" not in start and "--head" not in start
        assert option(start, "--address") == '"$$FLATSERVE_RAY"'
        assert option(start, "--num-cpus") == "0" and option(start, "--memory") == "0"
        assert svc["init"] is True


def test_cluster_ray_nodes_run_the_image_and_join_the_head():
    doc = cluster()
    services = doc["services"]
    head, port = ray_head(services)
    workers = ray_workers(services)
    assert len(workers) >= 2  # copies of a group go to different nodes
    image = {k: v for k, v in next(iter(replicas(services).values())).items()
             if k in ("build", "image")}
    for name, svc in {head: services[head], **workers}.items():
        cmd = svc["command"]
        assert cmd[:2] == ["ray", "start"] and "--block" in cmd, (name, cmd)
        # the same image as the fronts: the actors import flatserve from its venv
        assert {k: svc[k] for k in ("build", "image")} == image, name
        assert svc["init"] is True and svc["restart"] == "unless-stopped"
        assert re.fullmatch(r"\d+[kmg]b", svc["shm_size"]), name  # the object store
        # the actors get their settings from the fronts, never from a node's environment
        assert not any(k.startswith("FLATSERVE_") for k in svc.get("environment", {})), name
        # the image's health check asks a server: a node has its own or none
        assert svc["healthcheck"].get("disable") or svc["healthcheck"]["test"][:3] == [
            "CMD", "ray", "health-check"], name
    assert services[head]["healthcheck"]["test"] == [
        "CMD", "ray", "health-check", "--address", f"127.0.0.1:{port}"]
    for name, svc in workers.items():
        assert option(svc["command"], "--address") == f"{head}:{port}", name
        assert svc["depends_on"][head]["condition"] == "service_healthy", name
        # the shard actors run at niceness 0, not Ray's 15 for its workers
        assert svc["environment"]["RAY_worker_niceness"] == "0", name


def test_cluster_memory_budgets_hold_whole_shards():
    services = cluster()["services"]
    fronts = replicas(services)
    envs = [{k: by_default(v) for k, v in f["environment"].items() if k.startswith("FLATSERVE_RAY")}
            for f in fronts.values()]
    assert all(e == envs[0] for e in envs)  # every front places shards alike
    shard = int(envs[0]["FLATSERVE_RAY_SHARD_MEMORY"])
    groups = int(envs[0]["FLATSERVE_RAY_SHARDS"])
    assert Settings(ray_shard_memory=shard, ray_shards=groups).ray_shard_memory == shard
    head, _ = ray_head(services)
    # the head and the fronts' raylets hold no shard: their memory resource is 0
    assert option(services[head]["command"], "--memory") == "0"
    held = 0
    for name, svc in ray_workers(services).items():
        budget = int(by_default(option(svc["command"], "--memory")))
        assert budget >= shard and budget % shard == 0, (name, budget, shard)
        assert int(by_default(option(svc["command"], "--num-cpus"))) >= 1, name
        held += budget // shard
    # one field's groups fit, and a second field's as well
    assert held >= 2 * groups, (held, groups)


def test_cluster_nginx_sends_to_every_front():
    services = cluster()["services"]
    fronts = replicas(services)
    lb = services["lb"]
    assert lb["image"] == compose()["services"]["lb"]["image"]
    assert set(lb["depends_on"]) == set(fronts)
    (conf,) = [v.split(":")[0] for v in lb["volumes"] if v.endswith(":/etc/nginx/conf.d/default.conf:ro")]
    text = re.sub(r"#.*", "", (DOCKER / conf).read_text())
    servers = re.findall(r"^\s*server\s+([\w.-]+):(\d+)\b", text, re.M)
    # the fronts listen on the image's port (FLATSERVE_PORT=8000, not overridden)
    assert not any("FLATSERVE_PORT" in f["environment"] for f in fronts.values())
    assert sorted(servers) == sorted((name, "8000") for name in fronts)
