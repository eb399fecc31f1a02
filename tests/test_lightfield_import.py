"""Real captures over HTTP: ``Client.import_capture``, ``flatserve lightfield import`` and
renders by a captured frame's pose (``nerf`` / ``colmap`` members of the render body).

A forward-facing rig of 12 pinhole cameras (32 x 24 pixels, eyes on a 4 x 3 grid in
the plane z = -3, each looking at the origin) photographs the blocks scene: each
pixel's value is the ground-truth shade of the ray through its centre. The rig is
written as a NeRF capture and as a COLMAP capture (16-bit PNGs), one frame held out,
and imported into a real server (uvicorn on a loopback port, a temporary data dir):
the NeRF capture by the client, the COLMAP capture by the command line. Oracles: the
capture's rays read by the library (:func:`~flatserve.lightfield.capture.capture_rays`)
are what the field stores; the held-out view rendered over HTTP is the library's
:func:`~flatserve.lightfield.render.render_field` of a library field of those rays,
the same from either format and either pose convention, and closer to the mesh's
ground truth than the nearest captured photograph.

A sparse rig all around (the capture results' 62-camera sphere at a quarter of its
size, :func:`~flatserve.lightfield.capture_figure.synthetic_rig`) is imported with the
depth channel and its rig: the stored values are the library's reading of the capture
with depth, a held-out camera's render is the library's
:func:`~flatserve.lightfield.depth.render_guided` of a library field of those rays,
the same from either format; ``--no-depth`` imports the plain field, and an
interrupted import with depth resumes without storing anything twice.
"""
from __future__ import annotations

import io
import subprocess
import sys
from contextlib import redirect_stdout

import httpx
import numpy as np
import pytest

from flatserve.atlas_field import AtlasField
from flatserve.cli import main as cli_main
from flatserve.client import Client, capture_key
from flatserve.errors import InvalidInputError
from flatserve.flats import Flats
from flatserve.lightfield.camera import PinholeCamera
from flatserve.lightfield.capture import CaptureError, capture_rays, read_capture, write_colmap, write_nerf
from flatserve.lightfield.capture_figure import photograph as photograph_of, synthetic_rig
from flatserve.lightfield.quality import psnr
from flatserve.lightfield.render import render_field, render_truth
from flatserve.lightfield.rig import capture_atlas, rig_unit
from flatserve.lightfield.sampling import blocks_scene
from flatserve.service import Settings, create_app
from flatserve.service.status import FieldExistsError
from tests.harness.browser import serving
from tests.harness.process import free_port

#: The rig: eyes at (x, y, EYE_Z) looking at the origin, frames numbered row by row.
RIG_X = (-0.6, -0.2, 0.2, 0.6)
RIG_Y = (-0.4, 0.0, 0.4)
EYE_Z = -3.0
WIDTH, HEIGHT, FOCAL = 32, 24, 60.0
#: The frame held out of both imports (eye (-0.2, 0, -3)) and rendered from the fields.
HELD = "frame_0005"
#: The held-out render beats the nearest captured photograph (the best one view can
#: do) by at least this (measured: 2.3 dB).
NEAREST_MARGIN_DB = 1.0
#: Rays per batch of the interrupted import, at stride 2 (2 frames of 192 rays a batch).
RESUME_BATCH = 400
WAIT_S = 60.0


def look_at(eye, target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """Camera-to-world rotation of OpenCV's axes (right, down, forward) at ``eye``."""
    eye = np.asarray(eye, np.float64)
    fwd = np.asarray(target, np.float64) - eye
    fwd /= np.linalg.norm(fwd)
    right = np.cross(-np.asarray(up, np.float64), fwd)
    right /= np.linalg.norm(right)
    return np.stack([right, np.cross(fwd, right), fwd], axis=1)


def rig_camera(x: float, y: float, **kw) -> PinholeCamera:
    eye = (x, y, EYE_Z)
    return PinholeCamera(eye=eye, rotation=look_at(eye), fx=FOCAL, fy=FOCAL, cx=WIDTH / 2,
                         cy=HEIGHT / 2, width=WIDTH, height=HEIGHT, **kw)


RIG = [rig_camera(x, y) for y in RIG_Y for x in RIG_X]
NAMES = [f"frame_{k:04d}" for k in range(len(RIG))]
HELD_CAMERA = RIG[NAMES.index(HELD)]


def photograph(scene, cam: PinholeCamera) -> np.ndarray:
    """(H, W, C): the shade of the ray through each pixel's centre (the capture's image)."""
    o, d = cam.rays()
    return scene.shade(o, d).reshape(cam.height, cam.width, -1)


@pytest.fixture(scope="module")
def scene():
    return blocks_scene(1)


@pytest.fixture(scope="module")
def captures(tmp_path_factory, scene):
    """``{"nerf": dir, "colmap": dir}`` of the rig (16-bit PNGs) and its images."""
    root = tmp_path_factory.mktemp("captures")
    images = [photograph(scene, cam) for cam in RIG]
    write_nerf(root / "nerf", RIG, images, names=NAMES, bits=16)
    write_colmap(root / "colmap", RIG, images, names=NAMES, bits=16)
    return {"nerf": root / "nerf", "colmap": root / "colmap", "images": images}


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """The URL of a real server (uvicorn in a thread) on a temporary data dir, and its app."""
    port = free_port()
    app = create_app(Settings(data_dir=tmp_path_factory.mktemp("import") / "data",
                              snapshot_every=0, port=port))
    with serving(app, port, WAIT_S) as url:
        with Client(url, retries=0) as c:
            c.wait_ready(WAIT_S)
        yield url, app


@pytest.fixture(scope="module")
def client(server):
    with Client(server[0], retries=0) as c:
        yield c


def cli_command(url: str, capture, field: str, *args: str) -> list[str]:
    """``flatserve lightfield import`` of ``capture`` into ``field`` in another process."""
    return [sys.executable, "-m", "flatserve.cli", "lightfield", "import", str(capture),
            "--url", url, "--field", field, "--holdout", HELD, "--no-progress", *args]


@pytest.fixture(scope="module")
def imported(server, captures, client):
    """The NeRF capture imported by the client into ``nerf`` while the command line (in
    another process) imports the COLMAP capture into ``colmap``, both without the
    held-out frame: the client's report and the command's exit status and output."""
    url, _ = server
    cli = subprocess.Popen(cli_command(url, captures["colmap"], "colmap"), text=True,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        report = client.import_capture("nerf", captures["nerf"], holdout=[HELD], progress=False)
        out, err = cli.communicate(timeout=120)
    finally:
        if cli.poll() is None:
            cli.kill()
            cli.wait()
    return {"nerf": report, "cli": (cli.returncode, out, err)}


def export_arrays(client, name) -> dict[str, np.ndarray]:
    with np.load(io.BytesIO(client.export_field(name)), allow_pickle=False) as z:
        return {k: z[k] for k in ("rays_origins", "rays_directions", "values")}


def training(captures, fmt):
    return read_capture(captures[fmt]).without([HELD])


# -- imports ------------------------------------------------------------------------------
def test_the_client_stores_every_ray_of_the_capture(imported, captures, client):
    cap = training(captures, "nerf")
    n = cap.nrays()
    assert n == (len(RIG) - 1) * WIDTH * HEIGHT
    rep = imported["nerf"]
    assert rep["field"] == "nerf" and rep["format"] == "nerf" and rep["stride"] == 1
    assert rep["frames"] == len(RIG) - 1
    assert rep["rays"] == rep["stored"] == rep["nsamples"] == n
    assert rep["replayed"] == 0 and rep["rejected"] == 0 and rep["batches"] >= 1
    assert rep["key"].startswith("capture-")
    info = client.describe("nerf")
    assert info["nsamples"] == n and info["channels"] == 1
    # the stored rays are the library's reading of the capture, bit for bit, in order
    o, d, v = capture_rays(cap)
    got = export_arrays(client, "nerf")
    np.testing.assert_array_equal(got["rays_origins"], o)
    np.testing.assert_array_equal(got["rays_directions"], d)
    np.testing.assert_array_equal(got["values"], v)
    # and the pixels are the photographs' (16 bits: within half a step of 1/65535)
    truth = np.concatenate([img.reshape(-1, 1) for name, img in zip(NAMES, captures["images"])
                            if name != HELD])
    assert np.abs(got["values"] - truth).max() <= 0.5 / 65535 + 1e-12


def test_the_command_line_imports_and_prints_one_line(imported, captures, client):
    status, out, err = imported["cli"]
    assert status == 0, err
    n = training(captures, "colmap").nrays()
    lines = out.strip().splitlines()
    assert len(lines) == 1, out
    assert f"{len(RIG) - 1} frames" in lines[0] and "(colmap, stride 1)" in lines[0]
    assert f"{n:,} rays" in lines[0] and f"{n:,} stored now" in lines[0]
    assert "0 batches stored before" in lines[0] and f"holds {n:,} samples" in lines[0]
    assert client.describe("colmap")["nsamples"] == n


def test_the_same_command_again_stores_nothing(imported, server, captures, client, capsys):
    """The keys do not depend on the process: run again (here, in this one) every batch
    is replayed, nothing stored twice."""
    url, _ = server
    n = training(captures, "colmap").nrays()
    status = cli_main(cli_command(url, captures["colmap"], "colmap")[3:])
    out = capsys.readouterr()
    assert status == 0, out.err
    assert "0 stored now" in out.out and f"holds {n:,} samples" in out.out
    assert client.describe("colmap")["nsamples"] == n
    rep = client.import_capture("nerf", captures["nerf"], holdout=[HELD], progress=False)
    assert rep["replayed"] == rep["batches"] and rep["stored"] == 0 and rep["nsamples"] == n


def test_either_format_stores_the_same_rays(imported, client):
    a, b = export_arrays(client, "nerf"), export_arrays(client, "colmap")
    # a pose read from a NeRF matrix or a COLMAP quaternion: the same rotation up to rounding
    np.testing.assert_allclose(a["rays_origins"], b["rays_origins"], rtol=0, atol=1e-12)
    np.testing.assert_allclose(a["rays_directions"], b["rays_directions"], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(a["values"], b["values"])


class _Stop(Exception):
    """An import's progress callback cutting it off (an interruption)."""


def _stop_after(n: int, ticks: list):
    """A progress callback recording its calls in ``ticks`` that raises :class:`_Stop` at the ``n``-th."""
    def progress(done, total):
        ticks.append((done, total))
        if len(ticks) == n:
            raise _Stop
    return progress


def test_an_interrupted_import_resumes_without_storing_twice(server, captures, client):
    cap = training(captures, "nerf")
    n = cap.nrays(2)
    per_batch = 2 * (WIDTH // 2) * (HEIGHT // 2)
    nbatches = -(-(len(RIG) - 1) // 2)
    ticks = []
    stop_after_two = _stop_after(2, ticks)

    kw = dict(stride=2, holdout=[HELD], batch_rays=RESUME_BATCH)
    with pytest.raises(_Stop):
        client.import_capture("resumed", captures["nerf"], progress=stop_after_two, **kw)
    assert ticks == [(per_batch, n), (2 * per_batch, n)]
    assert client.describe("resumed")["nsamples"] == 2 * per_batch
    seen = []
    rep = client.import_capture("resumed", captures["nerf"],
                                progress=lambda done, total: seen.append(done), **kw)
    assert rep["batches"] == nbatches and rep["replayed"] == 2
    assert rep["stored"] == n - 2 * per_batch and rep["rays"] == n
    assert seen[-1] == n and seen == sorted(seen)
    assert client.describe("resumed")["nsamples"] == n == rep["nsamples"]
    # once more: all replayed
    again = client.import_capture("resumed", captures["nerf"], progress=False, **kw)
    assert again["replayed"] == nbatches and again["stored"] == 0
    assert client.describe("resumed")["nsamples"] == n
    assert [b["rows"] for b in client.batches("resumed")] == \
        [per_batch] * (nbatches - 1) + [n - (nbatches - 1) * per_batch]


def test_target_rays_picks_the_stride(server, captures, client):
    cap = training(captures, "nerf")
    rep = client.import_capture("target", captures["nerf"], holdout=[HELD], progress=False,
                                target_rays=cap.nrays(3))
    assert rep["stride"] == 3 and rep["rays"] == cap.nrays(3)
    assert client.describe("target")["nsamples"] == cap.nrays(3)
    with pytest.raises(InvalidInputError) as exc:
        client.import_capture("target", captures["nerf"], stride=2, target_rays=100)
    assert exc.value.argument == "stride"
    with pytest.raises(InvalidInputError) as exc:
        client.import_capture("target", captures["nerf"], holdout=["no_such_frame"])
    assert exc.value.argument == "holdout" and "no_such_frame" in str(exc.value)


def test_rgba_imported_as_rgb_over_a_background(server, client, tmp_path):
    """RGBA photographs imported into an RGB field: each stored value is its pixel
    composited over the background asked; the background is part of the keys (a second
    import over another background is another set of batches, not a replay); a bad
    background is refused before the field is created."""
    rng = np.random.default_rng(37)
    cams = RIG[:4]
    images = [rng.random((cam.height, cam.width, 4)) for cam in cams]
    write_nerf(tmp_path, cams, images, names=NAMES[:4], bits=16)
    bg = np.array([0.2, 0.5, 0.9])
    rep = client.import_capture("rgba", tmp_path, channels=3, background=bg.tolist(),
                                target_rays=64, progress=False)
    cap = read_capture(tmp_path)
    o, d, v = capture_rays(cap, stride=rep["stride"])  # RGBA as read
    want = v[:, :3] * v[:, 3:] + bg * (1 - v[:, 3:])
    got = export_arrays(client, "rgba")
    np.testing.assert_allclose(got["rays_origins"], o, atol=1e-12)
    np.testing.assert_allclose(got["values"], want, atol=1e-12)
    other = client.import_capture("rgba", tmp_path, channels=3, background=0.0,
                                  target_rays=64, progress=False)
    assert other["key"] != rep["key"] and other["replayed"] == 0
    for bad in ("white", [0.1, 0.2], 1.5, True):
        with pytest.raises(InvalidInputError) as exc:
            client.import_capture("rgba-bad", tmp_path, channels=3, background=bad,
                                  progress=False)
        assert exc.value.argument == "background"
    assert "rgba-bad" not in [f["name"] for f in client.list_fields()]


# -- renders by pose -------------------------------------------------------------------------
def render_pair(client):
    """The held-out view from the NeRF field by its NeRF pose, from the COLMAP field by
    its COLMAP pose."""
    a = client.render("nerf", {"nerf": HELD_CAMERA.to_nerf(), "supersample": 1})
    b = client.render("colmap", {"colmap": HELD_CAMERA.to_colmap(), "supersample": 1})
    return a, b


def test_the_held_out_view_is_the_same_from_either_format(imported, client):
    a, b = render_pair(client)
    assert a.shape == (HEIGHT, WIDTH, 1) and a.dtype == np.float32
    assert np.isfinite(a).mean() > 0.95
    np.testing.assert_array_equal(a, b)
    # a PinholeCamera (sent as its COLMAP pose), and the pose as cameras.txt params
    np.testing.assert_array_equal(client.render("nerf", HELD_CAMERA), a)
    c = HELD_CAMERA.to_colmap()
    body = {"colmap": {"qvec": c["qvec"], "tvec": c["tvec"], "model": "SIMPLE_PINHOLE",
                       "params": [c["fx"], c["cx"], c["cy"]], "width": c["width"],
                       "height": c["height"]}, "supersample": 1}
    np.testing.assert_array_equal(client.render("colmap", body), b)


def test_the_held_out_view_is_the_library_render(imported, server, captures, client):
    """The library is the oracle: a field of the capture's rays over the library's atlas
    for the capture (the importer's choices, flatserve.lightfield.rig)."""
    cap = training(captures, "nerf")
    o, d, v = capture_rays(cap)
    assert client.describe("nerf")["atlas"]["unit"] == rig_unit(cap.cameras)
    ref = AtlasField(capture_atlas(cap.cameras), channels=1)
    ref.add(Flats.from_rays(o, d), v)
    assert imported["nerf"]["batches"] == 1
    for ss in (1, 4):
        want = render_field(ref, HELD_CAMERA.with_(supersample=ss), fill=np.nan).image
        got = client.render("nerf", {"nerf": HELD_CAMERA.to_nerf(), "supersample": ss})
        np.testing.assert_array_equal(got, want.astype(np.float32))


def test_the_held_out_view_beats_the_nearest_photograph(imported, scene, captures, client):
    a, _ = render_pair(client)
    truth = render_truth(scene, HELD_CAMERA).image[..., 0]
    covered = np.isfinite(a[..., 0])
    ours = psnr(np.where(covered, a[..., 0], 0.0), truth)
    nearest = min((k for k in range(len(RIG)) if NAMES[k] != HELD),
                  key=lambda k: np.linalg.norm(RIG[k].eye - HELD_CAMERA.eye))
    baseline = psnr(captures["images"][nearest][..., 0], truth)
    constant = psnr(np.full_like(truth, truth.mean()), truth)
    assert baseline > constant  # the baseline is a fair one
    assert ours > baseline + NEAREST_MARGIN_DB, (ours, baseline)


def test_render_takes_a_library_camera(imported, client):
    """A :class:`flatserve.lightfield.Camera` is sent as its eye, rotation, focal, size."""
    from flatserve.lightfield import Camera

    cam = Camera.look_at((0.1, 0.0, -3.0), focal=4.0, width=20, height=16, supersample=1)
    got = client.render("nerf", cam)
    assert got.shape == (16, 20, 1) and np.isfinite(got).mean() > 0.5
    body = {"eye": cam.eye.tolist(), "rotation": cam.rotation.tolist(), "focal": 4.0,
            "width": 20, "height": 16, "supersample": 1}
    np.testing.assert_array_equal(client.render("nerf", body), got)


def test_a_pose_renders_at_the_size_asked(imported, client):
    half = HELD_CAMERA.scaled(WIDTH // 2, HEIGHT // 2)
    want = client.render("nerf", half)
    assert want.shape == (HEIGHT // 2, WIDTH // 2, 1)
    pose = {"nerf": HELD_CAMERA.to_nerf(), "supersample": 1}
    np.testing.assert_array_equal(client.render("nerf", pose, width=WIDTH // 2,
                                                height=HEIGHT // 2), want)
    # one side given: the other keeps the frame's aspect ratio
    np.testing.assert_array_equal(client.render("nerf", pose, width=WIDTH // 2), want)
    np.testing.assert_array_equal(client.render("nerf", pose, height=HEIGHT // 2), want)
    # a frame's size written as whole floats ("w": 800.0, as some writers do) is that size
    floats = {"nerf": {**pose["nerf"], "w": float(WIDTH), "h": float(HEIGHT)}, "supersample": 1}
    np.testing.assert_array_equal(client.render("nerf", floats, width=WIDTH // 2), want)
    png = client.render("nerf", pose, format="png")
    assert png.startswith(b"\x89PNG")
    from PIL import Image

    assert Image.open(io.BytesIO(png)).size == (WIDTH, HEIGHT)


NERF = HELD_CAMERA.to_nerf()
COLMAP = HELD_CAMERA.to_colmap()
SCALED = [[2.0, 0, 0, 0], [0, 2.0, 0, 0], [0, 0, 2.0, 3.0], [0, 0, 0, 1.0]]


def _nerf(**kw):
    return {"nerf": {**NERF, **kw}}


def _colmap(**kw):
    return {"colmap": {**COLMAP, **kw}}


@pytest.mark.parametrize("body, loc", [
    (_nerf(transform_matrix=SCALED), ["nerf", "transform_matrix"]),
    (_nerf(transform_matrix=[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 1, 1]]),
     ["nerf", "transform_matrix"]),
    (_nerf(transform_matrix=[[1, 0, 0], [0, 1, 0], [0, 0, 1]]), ["nerf", "transform_matrix"]),
    (_nerf(transform_matrix=[[-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3]]),
     ["nerf", "transform_matrix"]),
    ({"nerf": {"transform_matrix": NERF["transform_matrix"], "w": 4, "h": 4}},
     ["nerf", "camera_angle_x"]),
    (_nerf(camera_angle_x=True), ["nerf", "camera_angle_x"]),
    (_nerf(fl_x=-1.0), ["nerf", "fl_x"]),
    (_nerf(w=0), ["nerf", "w"]),
    (_nerf(w=32.5), ["nerf", "w"]),
    (_nerf(h=True), ["nerf", "h"]),
    (_colmap(width=24.25), ["colmap", "width"]),
    (_nerf(k1=0.1), ["nerf", "k1"]),
    (_nerf(transform_matrix=[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1e200]]),
     ["nerf", "transform_matrix"]),
    (_colmap(qvec=[2.0, 0, 0, 0]), ["colmap", "qvec"]),
    (_colmap(tvec=[0, 0]), ["colmap", "tvec"]),
    ({"colmap": {"qvec": COLMAP["qvec"], "tvec": COLMAP["tvec"], "params": [60.0, 16.0, 12.0],
                 "width": 32, "height": 24}}, ["colmap", "params"]),
    ({"colmap": {"qvec": COLMAP["qvec"], "tvec": COLMAP["tvec"], "params": [-60.0, 60.0, 16, 12],
                 "width": 32, "height": 24}}, ["colmap", "params"]),
    (_colmap(params=[60.0, 60.0, 16.0, 12.0]), ["colmap", "fx"]),
    (_colmap(model="SIMPLE_PINHOLE"), ["colmap", "fy"]),
    (_colmap(model="OPENCV"), ["colmap", "model"]),
    ({"colmap": {k: v for k, v in COLMAP.items() if k != "cx"}}, ["colmap", "cx"]),
    ({**_colmap(), "orbit": {"yaw": 10.0}}, ["colmap"]),
    ({**_nerf(), **_colmap()}, ["colmap"]),
    ({**_nerf(), "eye": [0, 0, -3]}, ["nerf"]),
    ({**_colmap(), "focal": 3.0}, ["focal"]),
    ({**_colmap(), "target": [0, 0, 0]}, ["target"]),
    ({**_colmap(width=2, height=64), "width": 2048}, ["height"]),
    ({**_colmap(), "supersample": 2}, ["supersample"]),
])
def test_a_bad_pose_is_a_422_naming_the_member(server, body, loc):
    r = httpx.post(f"{server[0]}/v1/fields/nerf/render", json=body, timeout=WAIT_S)
    assert r.status_code == 422, r.text
    got = r.json()["detail"][0]["loc"]
    assert got[0] == "body" and got[1:1 + len(loc)] == loc, got


def test_the_client_names_a_bad_pose(imported, client):
    with pytest.raises(InvalidInputError) as exc:
        client.render("nerf", _nerf(transform_matrix=SCALED))
    assert exc.value.argument == "transform_matrix" and "nerf.transform_matrix" in str(exc.value)
    with pytest.raises(InvalidInputError) as exc:
        client.render("nerf", HELD_CAMERA, format="jpeg")
    assert exc.value.argument == "format"


def test_a_photographs_pose_renders_at_a_size_given(imported, server):
    """A frame larger than a render may be (a 4032 x 3024 photograph) renders at the body's
    size; without one it is a 422 naming the side and saying what to do."""
    from flatserve.service.http.routes_lightfield import MAX_SIDE

    big = HELD_CAMERA.scaled(4032, 3024)
    small = HELD_CAMERA.scaled(40, 30).to_colmap()
    r = httpx.post(f"{server[0]}/v1/fields/nerf/render", timeout=WAIT_S,
                   json={"colmap": big.to_colmap(), "width": 40, "supersample": 1, "format": "npy"})
    want = httpx.post(f"{server[0]}/v1/fields/nerf/render", timeout=WAIT_S,
                      json={"colmap": small, "supersample": 1, "format": "npy"})
    assert r.status_code == want.status_code == 200, r.text
    np.testing.assert_allclose(np.load(io.BytesIO(r.content)), np.load(io.BytesIO(want.content)),
                               atol=1e-6, equal_nan=True)
    r = httpx.post(f"{server[0]}/v1/fields/nerf/render", json={"colmap": big.to_colmap()},
                   timeout=WAIT_S)
    assert r.status_code == 422 and r.json()["detail"][0]["loc"][-1] == "width"
    assert str(MAX_SIDE) in r.text and "smaller width or height" in r.text


def test_a_pose_too_large_is_413(server):
    from flatserve.service.http.routes_lightfield import MAX_SIDE

    r = httpx.post(f"{server[0]}/v1/fields/nerf/render",
                   json=_colmap(width=MAX_SIDE, height=MAX_SIDE), timeout=WAIT_S)
    assert r.status_code == 413 and "rays in one frame" in r.json()["detail"]


# -- bad captures and refusals ------------------------------------------------------------------
def _cli(argv, capsys) -> tuple[int, str, str]:
    status = cli_main(argv)
    out = capsys.readouterr()
    return status, out.out, out.err


def test_a_bad_capture_exits_2_naming_the_file_and_the_field(server, scene, tmp_path, capsys,
                                                             client):
    import json

    url, _ = server
    cams, images = RIG[:3], [photograph(scene, cam) for cam in RIG[:3]]
    nerf = write_nerf(tmp_path / "nerf", cams, images, bits=8)
    doc = json.loads(nerf.read_text())
    doc["frames"][1]["transform_matrix"] = SCALED
    nerf.write_text(json.dumps(doc))
    status, out, err = _cli(["lightfield", "import", str(tmp_path / "nerf"), "--url", url,
                             "--field", "bad-nerf", "--no-progress"], capsys)
    assert status == 2 and out == ""
    assert len(err.strip().splitlines()) == 1
    assert "transforms.json" in err and "frames[1].transform_matrix" in err
    with pytest.raises(CaptureError) as exc:
        client.import_capture("bad-nerf", tmp_path / "nerf", progress=False)
    assert exc.value.file == nerf and exc.value.field == "frames[1].transform_matrix"
    # a lens with distortion (COLMAP), an image whose size is not its camera's
    model = write_colmap(tmp_path / "colmap", cams, images, bits=8, model="OPENCV") / "cameras.txt"
    text = model.read_text()
    assert text.count(" 0.0 0.0 0.0 0.0\n") == 1  # one camera, no distortion: give it some
    model.write_text(text.replace(" 0.0 0.0 0.0 0.0\n", " 0.1 0.0 0.0 0.0\n"))
    status, _, err = _cli(["lightfield", "import", str(tmp_path / "colmap"), "--url", url,
                           "--field", "bad-colmap", "--format", "colmap", "--no-progress"], capsys)
    assert status == 2 and "cameras.txt" in err and "line" in err and "distortion" in err
    from PIL import Image

    write_nerf(tmp_path / "small", cams, images, bits=8)
    Image.new("L", (WIDTH // 2, HEIGHT)).save(tmp_path / "small" / "frame_0002.png")
    status, _, err = _cli(["lightfield", "import", str(tmp_path / "small"), "--url", url,
                           "--field", "bad-size", "--no-progress"], capsys)
    assert status == 2 and "frame_0002.png" in err and "size" in err
    names = {f["name"] for f in client.list_fields()}
    assert not {"bad-nerf", "bad-colmap"} & names  # refused before the field was made
    # nothing there at all
    status, _, err = _cli(["lightfield", "import", str(tmp_path / "nowhere"), "--url", url,
                           "--field", "none", "--no-progress"], capsys)
    assert status == 2 and "nowhere" in err


def test_a_refused_request_exits_2_naming_the_field(server, captures, client, capsys):
    url, _ = server
    client.create_field("rgb", channels=3)
    status, out, err = _cli(["lightfield", "import", str(captures["nerf"]), "--url", url,
                             "--field", "rgb", "--no-progress"], capsys)
    assert status == 2 and out == ""
    assert len(err.strip().splitlines()) == 1
    assert "'rgb'" in err and "409" in err and "channels" in err
    assert client.describe("rgb")["nsamples"] == 0
    status, _, err = _cli(["lightfield", "import", str(captures["nerf"]), "--url", url,
                           "--field", "no/such", "--no-progress"], capsys)
    assert status == 2 and "'no/such'" in err
    # an argument error is argparse's (2 too)
    with pytest.raises(SystemExit) as exc:
        cli_main(["lightfield", "import", str(captures["nerf"]), "--url", url, "--field", "x",
                  "--stride", "2", "--target-rays", "100"])
    assert exc.value.code == 2
    capsys.readouterr()


def test_the_key_of_the_command_line_comes_from_the_environment(tmp_path, captures, monkeypatch,
                                                               capsys):
    key = "import-key-0123456789"
    port = free_port()
    app = create_app(Settings(data_dir=tmp_path / "data", snapshot_every=0, port=port,
                              api_key=key))
    argv = ["lightfield", "import", str(captures["nerf"]), "--field", "keyed", "--stride", "4",
            "--no-progress"]
    with serving(app, port, WAIT_S) as url:
        monkeypatch.delenv("FLATSERVE_API_KEY", raising=False)
        status, _, err = _cli([*argv, "--url", url], capsys)
        assert status == 2 and "401" in err and "'keyed'" in err
        monkeypatch.setenv("FLATSERVE_API_KEY", key)
        status, out, err = _cli([*argv, "--url", url], capsys)
        assert status == 0, err
        monkeypatch.setenv("FLATSERVE_API_KEY", "wrong")
        status, out, err = _cli([*argv, "--url", url, "--api-key", key], capsys)
        assert status == 0 and "0 stored now" in out, err


def test_import_without_pillow_says_which_extra(monkeypatch, captures, client):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "PIL" else real(name, *a))
    with pytest.raises(ImportError, match=r"pip install 'flatserve\[lightfield\]'"):
        client.import_capture("x", captures["nerf"])


def test_the_viewer_reads_a_pose_from_its_url(server):
    """The page and its script (the browser test drives them): a ``?camera=`` pose
    leaves the page as it is, and the script reads it."""
    url, _ = server
    page = httpx.get(f"{url}/viewer/nerf", params={"camera": '{"nerf": {}}'}, timeout=WAIT_S)
    assert page.status_code == 200 and 'id="pose-note"' in page.text
    js = httpx.get(f"{url}/viewer/assets/viewer.js", timeout=WAIT_S).text
    assert 'get("camera")' in js and "poseBody" in js


# -- a sparse rig all around: captures with depth ------------------------------------------------
#: The rig of the capture results' 360-degree captures (62 cameras all around the blocks
#: scene, 17-24 degrees apart) at a quarter of their side: 16 x 16 photographs.
SPHERE_SIZE = 0.25
#: The sphere's imports take every second pixel of every second row (3,968 rays).
SPHERE_STRIDE = 2
#: The interrupted import's stride and rays per batch (2 frames of 16 rays a batch).
SPHERE_RESUME_STRIDE, SPHERE_RESUME_BATCH = 4, 40


@pytest.fixture(scope="module")
def sphere(tmp_path_factory):
    """The sphere rig's capture written as NeRF and COLMAP (16-bit PNGs), its held-out
    cameras (not in the capture), and the capture read back."""
    cams, held = synthetic_rig("sphere", size=SPHERE_SIZE)
    scene = blocks_scene()
    images = [photograph_of(scene, cam) for cam in cams]
    root = tmp_path_factory.mktemp("sphere")
    write_nerf(root / "nerf", cams, images, bits=16)
    write_colmap(root / "colmap", cams, images, bits=16)
    return {"nerf": root / "nerf", "colmap": root / "colmap", "cameras": cams, "held": held,
            "scene": scene, "capture": read_capture(root / "nerf")}


@pytest.fixture(scope="module")
def sphere_rays(sphere):
    """The library's reading of the sphere capture with its depth channel: the field's
    options (:func:`~flatserve.lightfield.capture.field_options`), its rig and its rays."""
    from flatserve.lightfield.capture import field_options
    from flatserve.lightfield.rig import DepthRig

    options = field_options(sphere["capture"])
    rig = DepthRig.from_dict(options["rig"])
    return {"options": options, "rig": rig,
            "rays": capture_rays(sphere["capture"], stride=SPHERE_STRIDE, depth=rig)}


@pytest.fixture(scope="module")
def sphere_imported(server, sphere, client):
    """The NeRF capture imported by the client into ``sphere-nerf``, the COLMAP capture by
    the command line (in this process) into ``sphere-colmap``, depth left to the rig."""
    url, _ = server
    report = client.import_capture("sphere-nerf", sphere["nerf"], stride=SPHERE_STRIDE,
                                   progress=False)
    out = io.StringIO()
    with redirect_stdout(out):
        status = cli_main(["lightfield", "import", str(sphere["colmap"]), "--url", url,
                           "--field", "sphere-colmap", "--stride", str(SPHERE_STRIDE),
                           "--no-progress"])
    return {"nerf": report, "cli": (status, out.getvalue())}


def render_response(url: str, name: str, body: dict) -> httpx.Response:
    r = httpx.post(f"{url}/v1/fields/{name}/render", json=body, timeout=WAIT_S)
    assert r.status_code == 200, r.text
    return r


def test_a_sparse_rig_all_around_is_imported_with_depth(sphere_imported, sphere, sphere_rays,
                                                        client):
    """The field gets the capture's rig and one channel more; the stored values are the
    library's reading of the capture with its depth channel, bit for bit."""
    cap, options = sphere["capture"], sphere_rays["options"]
    n = cap.nrays(SPHERE_STRIDE)
    rep = sphere_imported["nerf"]
    assert rep["depth"] is True and rep["rays"] == rep["stored"] == rep["nsamples"] == n
    assert options["channels"] == cap.channels + 1
    for name in ("sphere-nerf", "sphere-colmap"):
        info = client.describe(name)
        assert info["channels"] == options["channels"] and info["oriented"]
        assert info["rig"] == options["rig"] and info["nsamples"] == n
    o, d, v = sphere_rays["rays"]
    got = export_arrays(client, "sphere-nerf")
    np.testing.assert_array_equal(got["rays_origins"], o)
    np.testing.assert_array_equal(got["rays_directions"], d)
    np.testing.assert_array_equal(got["values"], v)
    status, out = sphere_imported["cli"]
    assert status == 0 and "(colmap, stride 2), with the depth channel" in out, out


def test_the_held_out_view_of_a_rig_field_is_the_depth_guided_render(sphere_imported, server,
                                                                     sphere, sphere_rays):
    """The render route on a field with a rig is the library's
    :func:`~flatserve.lightfield.depth.render_guided` of a library field of the same
    samples over the importer's atlas (the same numbers), colour channels only."""
    from flatserve.lightfield.depth import render_guided

    url, _ = server
    o, d, v = sphere_rays["rays"]
    ref = AtlasField(capture_atlas(sphere["cameras"]), channels=v.shape[1])
    ref.add(Flats.from_rays(o, d), v)
    assert sphere_imported["nerf"]["batches"] == 1
    for cam in sphere["held"][:2]:
        r = render_response(url, "sphere-nerf", {"nerf": cam.to_nerf(), "supersample": 1,
                                                 "format": "npy"})
        assert r.headers["X-Render"] == "depth-guided" and "guided" in r.headers["Server-Timing"]
        got = np.load(io.BytesIO(r.content))
        assert got.shape == (cam.height, cam.width, v.shape[1] - 1)
        want = render_guided(ref, cam.with_(supersample=1), sphere_rays["rig"], fill=np.nan).image
        np.testing.assert_array_equal(got, want.astype(np.float32))
        # and a view of the scene: nearer its true photograph than its mean grey is
        truth = photograph_of(sphere["scene"], cam)[..., 0]
        seen = np.isfinite(got[..., 0])
        assert seen.mean() > 0.5
        image = np.where(seen, got[..., 0], 0.0)
        ours = psnr(image, truth, mask=seen)
        assert ours > psnr(np.full_like(truth, truth[seen].mean()), truth, mask=seen), ours
    png = render_response(url, "sphere-nerf", {"nerf": sphere["held"][0].to_nerf(),
                                               "supersample": 1, "format": "png"})
    from PIL import Image

    img = Image.open(io.BytesIO(png.content))
    assert img.size == (16, 16) and img.mode == "L" and png.headers["X-Render"] == "depth-guided"


def test_a_capture_with_depth_renders_the_same_pixels_from_either_format(sphere_imported, sphere,
                                                                         client):
    for cam in sphere["held"]:
        a = client.render("sphere-nerf", {"nerf": cam.to_nerf(), "supersample": 1})
        b = client.render("sphere-colmap", {"colmap": cam.to_colmap(), "supersample": 1})
        assert a.shape == (cam.height, cam.width, 1)
        np.testing.assert_array_equal(a, b)


def test_a_rig_field_refuses_the_gradient_interpolant(sphere_imported, server, sphere):
    url, _ = server
    r = httpx.post(f"{url}/v1/fields/sphere-nerf/render", timeout=WAIT_S,
                   json={"nerf": sphere["held"][0].to_nerf(), "interpolant": "gradient"})
    assert r.status_code == 422, r.text
    err = r.json()["detail"][0]
    assert err["loc"] == ["body", "interpolant"] and "depth channel" in err["msg"]


def test_no_depth_imports_the_plain_field(server, sphere, client, capsys):
    """``--no-depth``: the colours alone, no rig, rendered by the field; the keys are not
    those of the import with depth."""
    url, _ = server
    status, out, err = _cli(["lightfield", "import", str(sphere["nerf"]), "--url", url,
                             "--field", "sphere-plain", "--stride", "4", "--no-depth",
                             "--no-progress"], capsys)
    assert status == 0 and "depth channel" not in out, err
    info = client.describe("sphere-plain")
    assert info["channels"] == 1 and "rig" not in info
    r = render_response(url, "sphere-plain", {"nerf": sphere["held"][0].to_nerf(),
                                              "supersample": 1, "format": "npy"})
    assert r.headers["X-Render"] == "field"
    # the same import asked with depth is another field's worth of batches: refused here
    with pytest.raises(FieldExistsError, match="channels"):
        client.import_capture("sphere-plain", sphere["nerf"], stride=4, depth=True,
                              progress=False)


def test_the_depth_choice_is_part_of_the_keys(sphere, sphere_rays):
    cap = sphere["capture"]
    kw = dict(stride=2, channels=1, batch_rays=1000)
    plain = capture_key("f", cap, **kw)
    assert capture_key("f", cap, rig=None, **kw) == plain  # (the keys before depth existed)
    deep = capture_key("f", cap, rig=sphere_rays["rig"].to_dict(), **kw)
    assert deep != plain and deep.startswith("capture-")
    moved = sphere_rays["rig"].to_dict()
    moved["center"] = np.add(moved["center"], 0.01).tolist()
    assert capture_key("f", cap, rig=moved, **kw) != deep


def test_an_interrupted_import_with_depth_resumes_without_storing_twice(server, sphere, client):
    cap = sphere["capture"]
    n = cap.nrays(SPHERE_RESUME_STRIDE)
    per_frame = (cap.frames[0].camera.width // SPHERE_RESUME_STRIDE) ** 2
    per_batch = (SPHERE_RESUME_BATCH // per_frame) * per_frame
    nbatches = -(-n // per_batch)
    ticks = []
    stop_after_two = _stop_after(2, ticks)

    kw = dict(stride=SPHERE_RESUME_STRIDE, batch_rays=SPHERE_RESUME_BATCH)
    with pytest.raises(_Stop):
        client.import_capture("sphere-resumed", sphere["nerf"], progress=stop_after_two, **kw)
    assert ticks == [(per_batch, n), (2 * per_batch, n)]
    info = client.describe("sphere-resumed")
    assert info["nsamples"] == 2 * per_batch and info["channels"] == 2 and "rig" in info
    rep = client.import_capture("sphere-resumed", sphere["nerf"], progress=False, **kw)
    assert rep["depth"] and rep["batches"] == nbatches and rep["replayed"] == 2
    assert rep["stored"] == n - 2 * per_batch and rep["rays"] == n
    assert client.describe("sphere-resumed")["nsamples"] == n == rep["nsamples"]
    stored = client.batches("sphere-resumed")
    keys = [b["idempotency_key"] for b in stored]
    assert len(keys) == len(set(keys)) == nbatches
    assert keys == [f"{rep['key']}.{i}" for i in range(nbatches)]
    assert sum(b["rows"] for b in stored) == n
