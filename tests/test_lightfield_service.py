"""The render route, the viewer page and the demo field, over HTTP (TestClient)."""
from __future__ import annotations

import io

import numpy as np
import pytest
from fastapi.testclient import TestClient

from flatserve.lightfield import Camera
from flatserve.service.demo import ensure_demo_field, viewer_url
from flatserve.lightfield.mesh import CGAL_DATA_TARBALL
from flatserve.lightfield.quality import psnr
from flatserve.lightfield.render import render_truth
from flatserve.lightfield.sampling import bunny_scene
from flatserve.service import Settings, create_app

pytestmark = pytest.mark.skipif(not CGAL_DATA_TARBALL.is_file(), reason="Debian libcgal-demo not installed")

DEMO_SAMPLES = 10_000  # all around the bunny: a coarse but recognisable 360 degree field
CONSTANT_MARGIN_DB = 2.0


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    settings = Settings(data_dir=tmp_path_factory.mktemp("lf") / "data", snapshot_every=0, max_batch_rows=200_000)
    with TestClient(base_url="http://127.0.0.1", app=create_app(settings)) as tc:
        reg = tc.app.state.rooms
        e = ensure_demo_field(reg, samples=DEMO_SAMPLES, batch=2500, progress=False)
        assert e.field.nsamples == DEMO_SAMPLES  # an oriented covering atlas takes every ray
        yield tc


def png_array(content: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(content)), dtype=np.float64) / 255.0


def test_demo_field_is_created_once(client):
    reg = client.app.state.rooms
    e = reg.catalogue.get("bunny")
    n_before = e.field.nsamples
    batches = reg.storage.batch_stats(e.id)[0]
    assert ensure_demo_field(reg, samples=DEMO_SAMPLES, batch=2500, progress=False) is e
    assert e.field.nsamples == n_before and reg.storage.batch_stats(e.id)[0] == batches
    assert viewer_url("127.0.0.1", 8000) == "http://127.0.0.1:8000/viewer/bunny"
    assert viewer_url("0.0.0.0", 9, "x") == "http://127.0.0.1:9/viewer/x"


def test_render_png_matches_ground_truth(client):
    body = {"eye": [0, 0, -3], "focal": 3.5, "width": 48, "height": 40, "supersample": 4}
    r = client.post("/v1/fields/bunny/render", json=body)
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "image/png"
    timing = r.headers["server-timing"]
    for stage in ("rays", "coordinates", "locate", "encode", "total"):
        assert f"{stage};dur=" in timing
    coverage = float(r.headers["x-coverage"])
    assert 0.8 < coverage <= 1.0
    img = png_array(r.content)
    assert img.shape == (40, 48)
    truth = render_truth(bunny_scene(1), Camera(eye=(0, 0, -3), focal=3.5, width=48, height=40)).image[..., 0]
    constant = np.full_like(truth, truth.mean())
    assert psnr(img, truth) > psnr(constant, truth) + CONSTANT_MARGIN_DB


def test_demo_field_is_a_360_degree_atlas(client):
    info = client.get("/v1/fields/bunny?verbose=true").json()
    assert info["atlas"]["oriented"] is True
    charts = info["charts"]
    assert len(charts) == 32  # 16 icosahedral vertex and face axes, both orientations
    assert info["atlas"]["unit"] == pytest.approx(1 / 3)  # object_unit of the bunny's 0.5
    # samples from eyes all around: every chart holds some
    assert all(c["samples"] > 0 for c in charts)


@pytest.mark.parametrize("yaw, pitch", [(180, 0), (90, 60), (-120, -75), (45, 85)])
def test_render_views_all_around_match_ground_truth(client, yaw, pitch):
    # from behind, the side and (nearly) the poles: no 45 degree limit, and oriented rays
    # (from behind the bunny's back is seen, not its front mirrored)
    w = 40
    r = client.post("/v1/fields/bunny/render",
                    json={"orbit": {"yaw": yaw, "pitch": pitch}, "focal": 4, "width": w,
                          "height": w, "supersample": 4})
    assert r.status_code == 200, r.text
    assert float(r.headers["x-coverage"]) > 0.8
    img = png_array(r.content)
    truth = render_truth(bunny_scene(1), Camera.orbit(yaw, pitch, 3.0, focal=4, width=w,
                                                      height=w)).image[..., 0]
    constant = np.full_like(truth, truth.mean())
    assert psnr(img, truth) > psnr(constant, truth) + CONSTANT_MARGIN_DB


def test_an_older_one_chart_demo_field_is_left_alone(tmp_path):
    settings = Settings(data_dir=tmp_path / "data", snapshot_every=0)
    with TestClient(base_url="http://127.0.0.1", app=create_app(settings)) as tc:
        r = tc.post("/v1/fields", json={"name": "bunny", "k": 1, "d": 3,
                                         "basis": {"kind": "tangent_simplex"}})
        assert r.status_code == 201, r.text
        e = tc.app.state.rooms.catalogue.get("bunny")
        assert ensure_demo_field(tc.app.state.rooms, samples=100, progress=False) is e
        assert e.field.nsamples == 0 and tc.app.state.rooms.storage.batch_stats(e.id)[0] == 0


def test_render_npy_and_orbit(client):
    r = client.post("/v1/fields/bunny/render",
                    json={"orbit": {"yaw": 5, "pitch": -5}, "focal": 4, "width": 20, "height": 20,
                          "supersample": 1}, headers={"Accept": "application/x-npy"})
    assert r.status_code == 200, r.text
    arr = np.load(io.BytesIO(r.content))
    assert arr.shape == (20, 20, 1) and arr.dtype == np.float32
    assert np.isfinite(arr).mean() > 0.8
    # another view gives another image
    r2 = client.post("/v1/fields/bunny/render",
                     json={"orbit": {"yaw": -15, "pitch": 10}, "focal": 4, "width": 20, "height": 20,
                           "supersample": 1, "format": "npy"})
    arr2 = np.load(io.BytesIO(r2.content))
    both = np.isfinite(arr) & np.isfinite(arr2)
    assert np.abs(arr[both] - arr2[both]).max() > 0.1


def test_render_by_the_gradient_interpolant(client):
    """``interpolant: gradient``: the library's render of the same field by it, bit for bit
    (and not the linear frame)."""
    from flatserve.lightfield.render import render_field

    body = {"orbit": {"yaw": 25, "pitch": 10}, "focal": 4, "width": 24, "height": 24,
            "supersample": 1, "format": "npy"}
    got = {k: np.load(io.BytesIO(client.post("/v1/fields/bunny/render",
                                             json={**body, "interpolant": k}).content))
           for k in ("linear", "gradient")}
    field = client.app.state.rooms.catalogue.get("bunny").field
    cam = Camera.orbit(25, 10, 3.0, focal=4, width=24, height=24, supersample=1)
    want = render_field(field, cam, fill=np.nan, interpolant="gradient").image.astype(np.float32)
    np.testing.assert_array_equal(got["gradient"], want)
    both = np.isfinite(got["linear"])
    assert both.mean() > 0.8 and np.abs(got["gradient"] - got["linear"])[both].max() > 1e-4


@pytest.mark.parametrize("body, status", [
    ({"supersample": 2}, 422),
    ({"width": 0}, 422),
    ({"eye": [0, 0]}, 422),
    ({"orbit": {"yaw": 0}, "eye": [0, 0, -3]}, 422),
    ({"width": 500, "height": 500, "supersample": 4}, 413),  # 1M rays > max_batch_rows
    ({"interpolant": "cubic"}, 422),
])
def test_render_rejects_bad_cameras(client, body, status):
    r = client.post("/v1/fields/bunny/render", json=body)
    assert r.status_code == status, r.text


def test_render_unknown_field_is_404(client):
    assert client.post("/v1/fields/nope/render", json={}).status_code == 404


def test_render_needs_lines_in_3d(client):
    r = client.post("/v1/fields", json={"name": "planes", "k": 2, "d": 3})
    assert r.status_code == 201, r.text
    r = client.post("/v1/fields/planes/render", json={"width": 4, "height": 4})
    assert r.status_code == 422


def test_viewer_page_and_assets(client):
    r = client.get("/viewer/bunny")
    assert r.status_code == 200 and "text/html" in r.headers["content-type"]
    assert "/viewer/assets/viewer.js" in r.text
    js = client.get("/viewer/assets/viewer.js")
    assert js.status_code == 200 and "render" in js.text
    assert client.get("/viewer/assets/other.js").status_code in (404, 422)
    assert client.get("/viewer/bad%2Fname").status_code in (404, 422)


def test_start_demo_field_in_the_background(client):
    from flatserve.service.demo import start_demo_field

    lines = []
    th = start_demo_field(client.app.state.rooms, "127.0.0.1", 8000, name="bunny2", samples=400,
                          announce=lines.append)
    th.join(timeout=120)
    assert not th.is_alive()
    assert client.app.state.rooms.catalogue.get("bunny2").field.nsamples > 300
    assert lines and all("http://127.0.0.1:8000/viewer/bunny2" in s for s in lines)
    assert "ready" in lines[-1]
