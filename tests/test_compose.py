"""docker/compose.yaml and docker/nginx.conf agree with each other and with the
service: no registry is reachable where the suite runs, so the deployment they
describe is not started here (tests/test_docker.py runs the image itself, and
two containers on one PostgreSQL); these checks catch the drift a rename or a
new limit would cause."""
from __future__ import annotations

import re
from pathlib import Path

import yaml

from flatserve.service.backend import backend_class
from flatserve.service.settings import Settings

DOCKER = Path(__file__).resolve().parent.parent / "docker"


def compose() -> dict:
    return yaml.safe_load((DOCKER / "compose.yaml").read_text())


def nginx() -> str:
    return re.sub(r"#.*", "", (DOCKER / "nginx.conf").read_text())


def replicas(services: dict) -> dict:
    return {k: v for k, v in services.items() if k.startswith("flatserve-")}


def test_three_replicas_on_postgres_behind_nginx():
    services = compose()["services"]
    reps = replicas(services)
    assert len(reps) == 3
    pg = services["postgres"]
    assert pg["image"].startswith("postgres:")
    assert pg["healthcheck"]["test"][:2] == ["CMD", "pg_isready"]
    user, db = pg["environment"]["POSTGRES_USER"], pg["environment"]["POSTGRES_DB"]
    known = set(Settings.model_fields)
    for name, svc in reps.items():
        env = svc["environment"]
        # every variable is a setting of the server (a typo would be ignored silently)
        assert {k.removeprefix("FLATSERVE_").lower() for k in env} <= known, name
        url = env["FLATSERVE_DATABASE_URL"]
        m = re.fullmatch(r"postgresql://([^:]+):\$\{POSTGRES_PASSWORD[^}]*\}@postgres:5432/(\w+)", url)
        assert m and m.groups() == (user, db), url
        assert backend_class(url).__name__ == "PostgresBackend"
        assert svc["depends_on"]["postgres"]["condition"] == "service_healthy"
        assert "FLATSERVE_API_KEY" in env and svc["image"] == "flatserve:latest"
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
