"""Requests another site's page can make a browser send are refused: bodies of a
type the route does not take (415, on every route), a Host that is not this
server's (421: DNS rebinding), an Origin that is not allowed (403); no CORS
headers unless ``cors_origins`` names the origin."""
from __future__ import annotations

import json

import numpy as np
import pytest
from fastapi.testclient import TestClient

from flatserve.service import Settings
from flatserve.service.http.guard import allowed_hosts, host_name
from flatserve.service.supervisor import settings_env
from tests.harness.fields import paper_rays

LOCAL = "http://127.0.0.1"
CREATE = json.dumps({"name": "forged", "channels": 1}).encode()
#: what a form or a no-cors fetch of another site can send without a preflight
SIMPLE_TYPES = ["text/plain", "text/plain;charset=UTF-8", "application/x-www-form-urlencoded",
                "multipart/form-data; boundary=x"]


@pytest.fixture
def served(make_app, rng):
    """A started app with a field ``f`` holding a few samples."""
    with TestClient(make_app(), base_url=LOCAL) as tc:
        assert tc.post("/v1/fields", json={"name": "f", "channels": 1}).status_code == 201
        o, v = paper_rays(rng, 50)
        r = tc.post("/v1/fields/f/samples", json={"origins": o.tolist(), "directions": v.tolist(),
                                                 "values": rng.uniform(size=(50, 1)).tolist()})
        assert r.status_code == 200, r.text
        yield tc


def _names(tc) -> list[str]:
    return [f["name"] for f in tc.get("/v1/fields").json()["fields"]]


def _routes(rng):
    """(method, path, a JSON body the route would take as JSON) of every route with a body."""
    o, v = paper_rays(rng, 3)
    rays = {"origins": o.tolist(), "directions": v.tolist()}
    basis = {"kind": "tangent_simplex"}
    return [
        ("POST", "/v1/fields", {"name": "forged", "channels": 1}),
        ("POST", "/v1/fields/f/samples", {**rays, "values": [[0.0]] * 3}),
        ("POST", "/v1/fields/f/query", rays),
        ("POST", "/v1/fields/f/render", {"width": 4, "height": 4, "supersample": 1}),
        ("POST", "/v1/math/coordinates", {"k": 1, "d": 3, "basis": basis,
                                          "flats": {"origins": o.tolist(),
                                                    "directions": v.tolist()}}),
        ("POST", "/v1/math/project", {"k": 0, "d": 2, "flats": {"A": [[[]]] * 0, "b": []},
                                      "weights": [[]]}),
    ]


@pytest.mark.parametrize("ctype", SIMPLE_TYPES + [None])
def test_simple_bodies_are_refused_on_every_body_route(served, rng, ctype):
    """A JSON body under a type a page may send cross-site (or under none) is a 415,
    and changes nothing: no field is created, no sample stored."""
    before = served.get("/v1/fields/f").json()["nsamples"]
    for method, path, body in _routes(rng):
        headers = {} if ctype is None else {"content-type": ctype}
        r = served.request(method, path, content=json.dumps(body).encode(), headers=headers)
        assert r.status_code == 415, (path, ctype, r.status_code, r.text)
        assert "Content-Type" in r.json()["detail"]
    assert _names(served) == ["f"]
    assert served.get("/v1/fields/f").json()["nsamples"] == before


def test_json_routes_take_json_only(served):
    """A route whose body is JSON refuses the binary types (415), and the batch routes
    take all three (JSON, .npy, .npz) and nothing else."""
    for ctype in ("application/x-npy", "application/x-npz", "application/xml"):
        r = served.post("/v1/fields", content=CREATE, headers={"content-type": ctype})
        assert r.status_code == 415, (ctype, r.text)
    r = served.post("/v1/fields", content=CREATE,
                    headers={"content-type": "application/json; charset=utf-8"})
    assert r.status_code == 201, r.text
    r = served.post("/v1/fields/f/query", content=b"<q/>", headers={"content-type": "application/xml"})
    assert r.status_code == 415


@pytest.mark.parametrize("method,path", [("POST", "/v1/fields/f/snapshot"),
                                         ("DELETE", "/v1/fields/f"),
                                         ("GET", "/v1/fields"), ("GET", "/healthz")])
def test_bodyless_routes_refuse_bodies(served, method, path):
    """A route without a body refuses any Content-Type and any body (415): an empty
    form posted to the snapshot route does not write a snapshot."""
    for headers, content in ([{"content-type": "application/x-www-form-urlencoded"}, b""],
                             [{"content-type": "application/json"}, b"{}"],
                             [{}, b"x=1"]):
        r = served.request(method, path, content=content, headers=headers)
        assert r.status_code == 415, (method, path, headers, r.text)
    assert _names(served) == ["f"]
    assert served.get("/v1/fields/f").json().get("snapshot_batch") is None


@pytest.mark.parametrize("host", ["evil.example", "evil.example:8000", "127.0.0.1.evil.example",
                                  "localhost.evil.example", "10.0.0.1"])
def test_foreign_host_is_refused(served, host):
    """DNS rebinding: a page whose name resolves to 127.0.0.1 sends its own name as
    Host; every route answers 421 to it, reads and deletes included."""
    for method, path in [("GET", "/v1/fields"), ("GET", "/v1/fields/f"), ("DELETE", "/v1/fields/f"),
                         ("GET", "/readyz"), ("GET", "/healthz")]:
        r = served.request(method, path, headers={"host": host})
        assert r.status_code == 421, (method, path, host, r.text)
        assert host_name(host) in r.json()["detail"]
    assert _names(served) == ["f"]


@pytest.mark.parametrize("host", ["127.0.0.1", "127.0.0.1:8000", "localhost", "LOCALHOST:1",
                                  "[::1]:8000", "localhost."])
def test_local_hosts_are_served(served, host):
    assert served.get("/v1/fields", headers={"host": host}).status_code == 200


def test_allowed_hosts_setting(make_app):
    """``allowed_hosts`` replaces the default list; '*' accepts any; a server bound
    to a wildcard address (keys on) accepts any Host by default."""
    with TestClient(make_app(allowed_hosts="api.example, other.example"), base_url=LOCAL) as tc:
        assert tc.get("/healthz", headers={"host": "api.example:443"}).status_code == 200
        assert tc.get("/healthz", headers={"host": "other.example"}).status_code == 200
        assert tc.get("/healthz", headers={"host": "localhost"}).status_code == 421
    assert allowed_hosts(Settings(allowed_hosts="*")) is None
    assert allowed_hosts(Settings(host="0.0.0.0", api_key="k")) is None
    # without a key a wildcard bind falls back to loopback, and so does the list
    assert allowed_hosts(Settings(host="0.0.0.0")) == {"127.0.0.1", "localhost", "::1"}
    assert "192.168.1.5" in allowed_hosts(Settings(host="192.168.1.5", api_key="k"))


def test_cross_origin_requests_are_refused_without_cors(served):
    """No CORS by default: a request whose Origin is another site's is a 403 (a
    no-cors POST to the snapshot route included), the server's own origin is
    served, and no answer carries CORS headers."""
    for origin in ("https://evil.example", "null", "http://127.0.0.1:9999"):
        r = served.post("/v1/fields/f/snapshot", headers={"origin": origin})
        assert r.status_code == 403, (origin, r.text)
        r = served.post("/v1/fields", json={"name": "x", "channels": 1}, headers={"origin": origin})
        assert r.status_code == 403
        r = served.options("/v1/fields", headers={"origin": origin,
                                                  "access-control-request-method": "POST"})
        assert r.status_code == 403
    assert _names(served) == ["f"]
    r = served.get("/v1/fields", headers={"origin": LOCAL})  # the viewer's own page
    assert r.status_code == 200
    assert not any(k.startswith("access-control-") for k in r.headers)


def test_cors_origins_setting(make_app, rng):
    """With ``cors_origins``, those origins get preflights answered and CORS headers
    (the position header exposed); other origins are still refused."""
    app = make_app(cors_origins="https://app.example")
    with TestClient(app, base_url=LOCAL) as tc:
        pre = tc.options("/v1/fields", headers={"origin": "https://app.example",
                                                "access-control-request-method": "POST",
                                                "access-control-request-headers": "content-type"})
        assert pre.status_code == 200, pre.text
        assert pre.headers["access-control-allow-origin"] == "https://app.example"
        r = tc.post("/v1/fields", json={"name": "g", "channels": 1},
                    headers={"origin": "https://app.example"})
        assert r.status_code == 201, r.text
        assert r.headers["access-control-allow-origin"] == "https://app.example"
        assert "flatserve-position" in r.headers["access-control-expose-headers"].lower()
        r = tc.post("/v1/fields", json={"name": "h", "channels": 1},
                    headers={"origin": "https://evil.example"})
        assert r.status_code == 403
    with pytest.raises(ValueError, match="not an origin"):
        Settings(cors_origins="https://app.example/path")


def test_list_settings_reach_the_children():
    """The supervisor hands list settings to its children as the comma-separated
    variables they read back."""
    s = Settings(allowed_hosts="a.example,b.example", cors_origins="https://c.example")
    env = settings_env(s)
    assert env["FLATSERVE_ALLOWED_HOSTS"] == "a.example,b.example"
    back = Settings(allowed_hosts=env["FLATSERVE_ALLOWED_HOSTS"],
                    cors_origins=env["FLATSERVE_CORS_ORIGINS"])
    assert back.allowed_hosts == s.allowed_hosts and back.cors_origins == s.cors_origins


def test_env_lists(monkeypatch):
    monkeypatch.setenv("FLATSERVE_ALLOWED_HOSTS", "x.example, y.example")
    assert Settings().allowed_hosts == ["x.example", "y.example"]


def test_binary_bodies_still_work(served, rng):
    """The client's own requests (.npy with its type) are unaffected."""
    from flatserve.client import Client

    c = Client(http=served)
    o, v = paper_rays(rng, 20)
    out = c.query_rays("f", o, v)
    assert np.asarray(out.values).shape == (20, 1)
