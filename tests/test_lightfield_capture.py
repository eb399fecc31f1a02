"""Real captures (flatserve.lightfield.capture) and the pinhole camera they are read into."""
from __future__ import annotations

import json
import math
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import flatserve.lightfield.capture as capture_module
from flatserve.errors import InvalidInputError
from flatserve.lightfield import (BATCH_RAYS, Camera, Capture, CaptureError, PinholeCamera, capture_batches,
                                  capture_rays, field_options, read_capture, write_colmap, write_nerf)
from flatserve.lightfield.rig import field_spec
from flatserve.lightfield.camera import RIGID_TOL
from flatserve.lightfield.capture import LUMA, read_image
from flatserve.lightfield.sampling import blocks_scene

#: Geometry computed two ways agrees to rounding.
GEOM_TOL = 1e-12
#: Half a quantisation step of 8- and 16-bit images (plus rounding).
Q8 = 0.5 / 255 + 1e-12
Q16 = 0.5 / 65535 + 1e-12
#: JPEG (quality 95) of a smooth image: mean and worst error.
JPEG_MEAN_TOL = 0.01
JPEG_MAX_TOL = 0.08


# ---------------------------------------------------------------- helpers
def random_rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def random_camera(rng, width=None, height=None) -> PinholeCamera:
    w = int(rng.integers(8, 40)) if width is None else width
    h = int(rng.integers(8, 40)) if height is None else height
    return PinholeCamera(eye=rng.normal(size=3) * 3, rotation=random_rotation(rng), fx=rng.uniform(10, 80),
                         fy=rng.uniform(10, 80), cx=rng.uniform(0, w), cy=rng.uniform(0, h), width=w, height=h)


def nerf_directions(transform_matrix, fx, fy, cx, cy, x, y) -> np.ndarray:
    """NeRF's own ray directions (OpenGL camera axes) through image positions (x, y), unit."""
    M = np.asarray(transform_matrix, dtype=float)
    cam = np.stack([(x - cx) / fx, -(y - cy) / fy, -np.ones_like(x)], axis=1)
    d = cam @ M[:3, :3].T
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def pixel_centres(width, height, stride=1):
    """Image positions (x, y) of the pixels kept at ``stride``, scanline order."""
    first = stride // 2
    xs, ys = np.meshgrid(np.arange(first, width, stride) + 0.5, np.arange(first, height, stride) + 0.5)
    return xs.ravel(), ys.ravel()


def rig(rng, n=4, width=24, height=18) -> list[PinholeCamera]:
    """Cameras around the blocks scene, looking at its centre, square pixels, centred principal points."""
    cams = []
    for _ in range(n):
        v = rng.normal(size=3)
        v /= np.linalg.norm(v)
        cams.append(PinholeCamera.look_at(2.4 * v, target=rng.normal(size=3) * 0.05, fx=26.0, fy=26.0,
                                          cx=width / 2, cy=height / 2, width=width, height=height))
    return cams


def render_nerf_images(scene, cams) -> list[np.ndarray]:
    """Each pixel the scene's shade of its ray, the rays computed by NeRF's formula from the NeRF pose."""
    out = []
    for cam in cams:
        d = cam.to_nerf()
        x, y = pixel_centres(cam.width, cam.height)
        dirs = nerf_directions(d["transform_matrix"], d["fl_x"], d["fl_y"], d["cx"], d["cy"], x, y)
        eye = np.asarray(d["transform_matrix"])[:3, 3]
        v = scene.shade(np.broadcast_to(eye, dirs.shape), dirs)
        out.append(v.reshape(cam.height, cam.width, -1))
    return out


def refused(fn, *parts, error=CaptureError):
    """``fn()`` raises ``error`` whose message holds every one of ``parts``."""
    with pytest.raises(error) as info:
        fn()
    msg = str(info.value)
    for p in parts:
        assert str(p) in msg, (p, msg)
    return info.value


def png16(path: Path, a: np.ndarray, filters) -> None:
    """A 16-bit RGB / RGBA / grey-alpha PNG, row ``r`` filtered with ``filters[r % len(filters)]``
    (the PNG specification's filters, computed from the raw bytes)."""
    H, W, C = a.shape
    bpp = 2 * C
    raw = np.ascontiguousarray(a.astype(">u2")).view(np.uint8).reshape(H, W * bpp).astype(np.int64)
    lines = []
    for r in range(H):
        k = filters[r % len(filters)]
        x = raw[r]
        up = raw[r - 1] if r else np.zeros_like(x)
        left = np.concatenate([np.zeros(bpp, dtype=np.int64), x[:-bpp]])
        ul = np.concatenate([np.zeros(bpp, dtype=np.int64), up[:-bpp]])
        if k == 0:
            f = x
        elif k == 1:
            f = x - left
        elif k == 2:
            f = x - up
        elif k == 3:
            f = x - (left + up) // 2
        else:
            p = left + up - ul
            pa, pb, pc = np.abs(p - left), np.abs(p - up), np.abs(p - ul)
            f = x - np.where((pa <= pb) & (pa <= pc), left, np.where(pb <= pc, up, ul))
        lines.append(bytes([k]) + (f % 256).astype(np.uint8).tobytes())

    def chunk(kind, payload):
        return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", zlib.crc32(kind + payload))

    colour = {3: 2, 4: 6, 2: 4}[C]
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", W, H, 16, colour, 0, 0, 0))
                     + chunk(b"IDAT", zlib.compress(b"".join(lines))) + chunk(b"IEND", b""))


@pytest.fixture(scope="module")
def scene():
    return blocks_scene(channels=3)


@pytest.fixture(scope="module")
def scene_rig(scene):
    cams = rig(np.random.default_rng(7))
    return cams, render_nerf_images(scene, cams)


# ---------------------------------------------------------------- the camera
def test_poses_round_trip_nerf_camera_colmap():
    rng = np.random.default_rng(0)
    for _ in range(50):
        cam = random_camera(rng)
        d = cam.to_nerf()
        back = PinholeCamera.from_nerf(d["transform_matrix"], width=d["w"], height=d["h"], fl_x=d["fl_x"],
                                       fl_y=d["fl_y"], cx=d["cx"], cy=d["cy"])
        np.testing.assert_allclose(back.eye, cam.eye, atol=GEOM_TOL)
        np.testing.assert_allclose(back.rotation, cam.rotation, atol=GEOM_TOL)
        assert (back.fx, back.fy, back.cx, back.cy, back.width, back.height) == \
            (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height)
        c = cam.to_colmap()
        assert c["qvec"][0] >= 0
        via = PinholeCamera.from_colmap(**c)
        np.testing.assert_allclose(via.eye, cam.eye, atol=GEOM_TOL)
        np.testing.assert_allclose(via.rotation, cam.rotation, atol=GEOM_TOL)
        # NeRF -> camera -> COLMAP -> camera -> NeRF
        again = PinholeCamera.from_colmap(**back.to_colmap()).to_nerf()
        np.testing.assert_allclose(again["transform_matrix"], d["transform_matrix"], atol=GEOM_TOL)
        # the rays of cameras built from either convention are the same
        np.testing.assert_allclose(back.rays()[1], via.rays()[1], atol=GEOM_TOL)
        np.testing.assert_allclose(back.rays()[0], via.rays()[0], atol=GEOM_TOL)
        # a quaternion and its negative are the same rotation
        neg = PinholeCamera.from_colmap(**{**c, "qvec": [-q for q in c["qvec"]]})
        np.testing.assert_allclose(neg.rotation, cam.rotation, atol=GEOM_TOL)


def test_rays_follow_nerf_and_colmap_projection():
    rng = np.random.default_rng(1)
    for _ in range(20):
        cam = random_camera(rng)
        # NeRF's ray formula (OpenGL axes) through each pixel centre
        d = cam.to_nerf()
        x, y = pixel_centres(cam.width, cam.height)
        o, dirs = cam.rays()
        np.testing.assert_allclose(dirs, nerf_directions(d["transform_matrix"], cam.fx, cam.fy, cam.cx, cam.cy, x, y),
                                   atol=GEOM_TOL)
        np.testing.assert_allclose(o, np.broadcast_to(cam.eye, o.shape), atol=0)
        # COLMAP's projection of world points: the ray through the projection meets the point
        c = cam.to_colmap()
        qw, qx, qy, qz = c["qvec"]
        R = np.array([[1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)],
                      [2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)],
                      [2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)]])
        X = rng.normal(size=(30, 3)) * 2
        xc = X @ R.T + c["tvec"]
        X, xc = X[xc[:, 2] > 0.1], xc[xc[:, 2] > 0.1]
        u = c["fx"] * xc[:, 0] / xc[:, 2] + c["cx"]
        v = c["fy"] * xc[:, 1] / xc[:, 2] + c["cy"]
        for k in range(len(X)):
            ray = cam.grid_rays([u[k]], [v[k]])[1][0]
            want = (X[k] - cam.eye) / np.linalg.norm(X[k] - cam.eye)
            np.testing.assert_allclose(ray, want, atol=1e-10)


def test_supersampled_rays_and_resolve():
    rng = np.random.default_rng(2)
    cam = random_camera(rng, width=5, height=3).with_(supersample=4)
    assert cam.side == 2 and cam.nrays == 5 * 3 * 4
    o, d = cam.rays()
    # fine pixel (a, b) of pixel (i, j) looks through (i + (a + 1/2) / 2, j + (b + 1/2) / 2)
    fine = (np.arange(10) + 0.5) / 2, (np.arange(6) + 0.5) / 2
    np.testing.assert_allclose(d, cam.grid_rays(*fine)[1], atol=GEOM_TOL)
    values = rng.random((cam.nrays, 3))
    img = cam.resolve(values)
    assert img.shape == (3, 5, 3)
    blocks = values.reshape(3, 2, 5, 2, 3)
    np.testing.assert_allclose(img, blocks.mean(axis=(1, 3)), atol=GEOM_TOL)
    # one resolve for both cameras
    flat = Camera(width=5, height=3, supersample=4)
    w = (rng.random(cam.nrays) > 0.3).astype(float)
    np.testing.assert_array_equal(flat.resolve(values, w), cam.resolve(values, w))


def test_camera_angle_and_defaults():
    rng = np.random.default_rng(3)
    M = np.eye(4)
    M[:3, :3] = random_rotation(rng)
    cam = PinholeCamera.from_nerf(M[:3], width=40, height=30, camera_angle_x=0.9)
    assert math.isclose(cam.fx, 20 / math.tan(0.45), rel_tol=1e-15) and cam.fy == cam.fx
    assert (cam.cx, cam.cy) == (20.0, 15.0)
    # the image's left and right edges are camera_angle_x apart
    d = cam.grid_rays([0.0, 40.0], [15.0, 15.0])[1]
    assert math.isclose(math.acos(d[0] @ d[1]), 0.9, rel_tol=1e-12)
    # fl_x takes precedence over camera_angle_x
    assert PinholeCamera.from_nerf(M, width=40, height=30, camera_angle_x=0.9, fl_x=33.0).fx == 33.0
    # a pose off rigid within RIGID_TOL is read, as the nearest rotation
    noisy = M.copy()
    noisy[:3, :3] += rng.normal(size=(3, 3)) * RIGID_TOL / 20
    near = PinholeCamera.from_nerf(noisy, width=40, height=30, fl_x=30.0)
    np.testing.assert_allclose(near.rotation.T @ near.rotation, np.eye(3), atol=GEOM_TOL)


def test_scaled_keeps_pose_and_field_of_view():
    rng = np.random.default_rng(4)
    cam = random_camera(rng, width=20, height=10)
    big = cam.scaled(60, 20)
    assert (big.width, big.height) == (60, 20)
    np.testing.assert_array_equal(big.rotation, cam.rotation)
    x, y = rng.uniform(0, 20, 9), rng.uniform(0, 10, 9)
    # image position (x, y) of the original is (3x, 2y) of the scaled camera
    for k in range(9):
        np.testing.assert_allclose(big.grid_rays([3 * x[k]], [2 * y[k]])[1], cam.grid_rays([x[k]], [y[k]])[1],
                                   atol=GEOM_TOL)


@pytest.mark.parametrize("change, field", [
    ({"rotation": np.diag([1.0, 1.0, -1.0])}, "rotation"),
    ({"rotation": np.eye(3) * 1.01}, "rotation"),
    ({"fx": 0.0}, "fx"), ({"fy": float("nan")}, "fy"), ({"cx": float("inf")}, "cx"),
    ({"width": 0}, "width"), ({"height": 2.5}, "height"), ({"supersample": 2}, "supersample"),
    ({"eye": (0.0, 1.0)}, "eye"),
])
def test_camera_refuses_bad_fields(change, field):
    base = dict(eye=(0.0, 0.0, 0.0), rotation=np.eye(3), fx=10.0, fy=10.0, cx=5.0, cy=5.0, width=10, height=10)
    err = refused(lambda: PinholeCamera(**{**base, **change}), field, error=InvalidInputError)
    assert err.argument == field


def test_from_nerf_and_colmap_refuse_bad_poses():
    rng = np.random.default_rng(5)
    M = np.eye(4)
    M[:3, :3] = random_rotation(rng)
    kw = dict(width=10, height=10, fl_x=10.0)
    for bad, what in ((M * [[2], [2], [2], [1]], "not orthonormal"), (M * [[1], [1], [-1], [1]], "reflection"),
                      (M + np.r_[np.zeros((3, 4)), [[0.0, 0.0, 0.1, 0.0]]], "last row")):
        err = refused(lambda: PinholeCamera.from_nerf(bad, **kw), "transform_matrix", "not a rigid transform", what,
                      error=InvalidInputError)
        assert err.argument == "transform_matrix"
    err = refused(lambda: PinholeCamera.from_nerf(M, width=10, height=10), "camera_angle_x", error=InvalidInputError)
    assert err.argument == "camera_angle_x"
    q = np.array([1.0, 0.2, -0.3, 0.1])
    refused(lambda: PinholeCamera.from_colmap(q, [0, 0, 0], width=4, height=4, fx=1, fy=1, cx=2, cy=2), "qvec",
            "norm", error=InvalidInputError)
    q /= np.linalg.norm(q)
    ok = PinholeCamera.from_colmap(q * (1 + RIGID_TOL / 2), [0, 0, 0], width=4, height=4, fx=1, fy=1, cx=2, cy=2)
    np.testing.assert_allclose(ok.rotation.T @ ok.rotation, np.eye(3), atol=GEOM_TOL)


def test_to_dict_and_look_at():
    cam = PinholeCamera.look_at((0.0, 0.0, -3.0), fx=10, fy=12, cx=4, cy=3, width=8, height=6)
    # looking down +z with +y up, a right-handed world: image right is -x, image down -y
    np.testing.assert_allclose(cam.rotation, np.diag([-1.0, -1.0, 1.0]), atol=GEOM_TOL)
    back = PinholeCamera(**json.loads(json.dumps(cam.to_dict())))
    np.testing.assert_array_equal(back.rotation, cam.rotation)
    np.testing.assert_array_equal(back.eye, cam.eye)
    assert (back.fx, back.fy, back.cx, back.cy, back.width, back.height, back.supersample) == (10, 12, 4, 3, 8, 6, 1)
    # the top row of the image looks up (+y), the left column toward +x
    d = cam.rays()[1].reshape(6, 8, 3)
    assert np.all(d[0, :, 1] > 0) and np.all(d[:, 0, 0] > 0)


# ---------------------------------------------------------------- captures written and read
def test_capture_in_both_formats_reads_the_same(tmp_path, scene, scene_rig):
    cams, images = scene_rig
    write_nerf(tmp_path / "nerf", cams, images, bits=16)
    model = write_colmap(tmp_path / "colmap", cams, images, bits=16)
    assert model == tmp_path / "colmap" / "sparse" / "0"
    a, b = read_capture(tmp_path / "nerf"), read_capture(tmp_path / "colmap")
    assert (a.format, b.format) == ("nerf", "colmap")
    assert a.names == b.names and a.channels == b.channels == 3
    assert len(a.frames) == len(cams)
    for fa, fb, cam in zip(a.frames, b.frames, cams):
        for f in (fa, fb):
            np.testing.assert_allclose(f.camera.eye, cam.eye, atol=GEOM_TOL)
            np.testing.assert_allclose(f.camera.rotation, cam.rotation, atol=GEOM_TOL)
            assert (f.camera.width, f.camera.height) == (cam.width, cam.height)
            assert math.isclose(f.camera.fx, cam.fx, rel_tol=1e-14) and math.isclose(f.camera.fy, cam.fy,
                                                                                      rel_tol=1e-14)
    ra, rb = capture_rays(a), capture_rays(b)
    for x, y in zip(ra, rb):
        np.testing.assert_allclose(x, y, atol=GEOM_TOL)
    # the values are the images, frame by frame in scanline order
    np.testing.assert_allclose(ra[2], np.concatenate([im.reshape(-1, 3) for im in images]), atol=Q16)
    # and the scene's shade of the rays returned (the images were rendered by NeRF's own ray formula)
    np.testing.assert_allclose(ra[2], scene.shade(ra[0], ra[1]), atol=Q16)
    # either format gets the same field, the rig's (flatserve.lightfield.rig)
    assert field_options(a) == field_options(b) == field_spec(a.cameras, 3)


@pytest.mark.parametrize("stride", [2, 3, 5])
def test_strided_rays_are_their_pixels_centres(tmp_path, scene, scene_rig, stride):
    cams, images = scene_rig
    write_colmap(tmp_path, cams, images, bits=16)
    cap = read_capture(tmp_path)
    o, d, v = capture_rays(cap, stride=stride)
    assert len(o) == cap.nrays(stride)
    first = stride // 2
    np.testing.assert_allclose(v, np.concatenate([im[first::stride, first::stride].reshape(-1, 3)
                                                  for im in images]), atol=Q16)
    np.testing.assert_allclose(v, scene.shade(o, d), atol=Q16)
    want = []
    for cam in cams:
        x, y = pixel_centres(cam.width, cam.height, stride)
        t = cam.to_nerf()
        want.append(nerf_directions(t["transform_matrix"], cam.fx, cam.fy, cam.cx, cam.cy, x, y))
    np.testing.assert_allclose(d, np.concatenate(want), atol=GEOM_TOL)


@pytest.mark.parametrize("channels", [1, 3, 4])
@pytest.mark.parametrize("bits", [8, 16])
def test_png_depths_and_channels(tmp_path, channels, bits):
    rng = np.random.default_rng(10 * channels + bits)
    cams = [random_camera(rng, 12, 9) for _ in range(3)]
    images = [rng.random((9, 12, channels)) for _ in cams]
    if channels == 1:
        images[0] = images[0][:, :, 0]  # (H, W) is grey too
    tol = Q8 if bits == 8 else Q16
    for writer in (write_nerf, write_colmap):
        root = tmp_path / writer.__name__
        writer(root, cams, images, bits=bits, **({"angle": False} if writer is write_nerf else {}))
        cap = read_capture(root)
        assert cap.channels == channels
        v = capture_rays(cap)[2]
        np.testing.assert_allclose(v, np.concatenate([np.reshape(im, (-1, channels)) for im in images]), atol=tol)
        # values are exact multiples of the quantisation step
        top = 255 if bits == 8 else 65535
        np.testing.assert_allclose(v * top, np.rint(v * top), atol=1e-9)


def test_jpeg_values_close(tmp_path):
    rng = np.random.default_rng(11)
    cams = [random_camera(rng, 32, 24) for _ in range(2)]
    yy, xx = np.mgrid[0:24, 0:32] / 24.0
    images = [np.stack([0.5 + 0.4 * np.sin(xx * 2 + p), 0.5 + 0.4 * np.cos(yy * 3 - p), 0.3 + 0.2 * xx * yy], axis=2)
              for p in (0.0, 1.0)]
    write_colmap(tmp_path, cams, images, names=["a.jpg", "b.jpeg"])
    cap = read_capture(tmp_path)
    assert cap.names == ("a", "b") and cap.frames[0].image.suffix == ".jpg"
    v = capture_rays(cap)[2]
    err = np.abs(v - np.concatenate([im.reshape(-1, 3) for im in images]))
    assert err.mean() < JPEG_MEAN_TOL and err.max() < JPEG_MAX_TOL


@pytest.mark.parametrize("C", [2, 3, 4])
def test_16_bit_colour_png_every_filter(tmp_path, C):
    rng = np.random.default_rng(20 + C)
    a = rng.integers(0, 65536, size=(7, 9, C), dtype=np.uint16)
    a[2:5] = a[1]  # rows that filter well
    path = tmp_path / "deep.png"
    png16(path, a, filters=[0, 1, 2, 3, 4, 4, 3])
    got = read_image(path)
    want = a.astype(float) / 65535
    if C == 2:
        want = np.concatenate([np.repeat(want[..., :1], 3, axis=2), want[..., 1:]], axis=2)
    np.testing.assert_array_equal(got, want)
    # Pillow decodes the same file to its high bytes
    with Image.open(path) as im:
        hi = np.asarray(im.convert("RGBA" if C != 3 else "RGB"))
    np.testing.assert_array_equal(hi, np.floor(got * 65535 / 256 + 1e-9).astype(np.uint8))


def test_channel_conversions(tmp_path):
    rng = np.random.default_rng(12)
    cams = [random_camera(rng, 10, 8)]
    rgba = rng.random((8, 10, 4))
    write_nerf(tmp_path / "rgba", cams, [rgba], angle=False)
    cap = read_capture(tmp_path / "rgba")
    stored = capture_rays(cap)[2]  # the 8-bit values read
    assert stored.shape[1] == 4
    bg = np.array([0.2, 0.5, 0.9])
    rgb = capture_rays(cap, channels=3, background=bg)[2]
    np.testing.assert_allclose(rgb, stored[:, :3] * stored[:, 3:] + bg * (1 - stored[:, 3:]), atol=GEOM_TOL)
    grey = capture_rays(cap, channels=1, background=0.25)[2]
    comp = stored[:, :3] * stored[:, 3:] + 0.25 * (1 - stored[:, 3:])
    np.testing.assert_allclose(grey[:, 0], comp @ np.asarray(LUMA), atol=GEOM_TOL)
    # RGB to grey is Pillow's "L", in float
    write_nerf(tmp_path / "rgb", cams, [rgba[:, :, :3]], angle=False)
    cap3 = read_capture(tmp_path / "rgb")
    with Image.open(cap3.frames[0].image) as im:
        pil_l = np.asarray(im.convert("L")).reshape(-1) / 255
    np.testing.assert_allclose(capture_rays(cap3, channels=1)[2][:, 0], pil_l, atol=Q8)
    as4 = capture_rays(cap3, channels=4)[2]
    np.testing.assert_array_equal(as4[:, 3], 1.0)
    np.testing.assert_array_equal(as4[:, :3], capture_rays(cap3)[2])
    # grey to RGB repeats
    write_nerf(tmp_path / "grey", cams, [rgba[:, :, 0]], angle=False)
    capg = read_capture(tmp_path / "grey")
    g = capture_rays(capg)[2]
    np.testing.assert_array_equal(capture_rays(capg, channels=3)[2], np.repeat(g, 3, axis=1))
    # grey with alpha is read as RGBA
    la = (rng.random((8, 10, 2)) * 255).astype(np.uint8)
    Image.fromarray(la, mode="LA").save(tmp_path / "grey" / "frame_0000.png")
    np.testing.assert_array_equal(read_image(tmp_path / "grey" / "frame_0000.png"),
                                  np.concatenate([np.repeat(la[..., :1], 3, axis=2), la[..., 1:]], axis=2) / 255)
    refused(lambda: capture_rays(cap, channels=2), "channels", error=InvalidInputError)
    refused(lambda: capture_rays(cap, background=1.5), "background", error=InvalidInputError)


# ---------------------------------------------------------------- strides and batches
def small_capture(tmp_path, sizes, seed=13) -> tuple[Capture, list[np.ndarray]]:
    rng = np.random.default_rng(seed)
    cams = [random_camera(rng, w, h) for w, h in sizes]
    images = [rng.random((h, w, 3)) for w, h in sizes]
    write_nerf(tmp_path, cams, images, angle=False)
    return read_capture(tmp_path), images


def test_stride_and_target_rays(tmp_path):
    cap, images = small_capture(tmp_path, [(17, 11), (9, 14), (30, 3), (1, 1)])
    for s in range(1, 35):
        o, d, v = capture_rays(cap, stride=s)
        assert len(o) == len(d) == len(v) == cap.nrays(s)
        # every frame keeps a ray however long the stride (a side shorter than half
        # the stride keeps its middle pixel), each with its own pixel's value
        for name, im in zip(cap.names, images):
            one = cap.take(name)
            assert one.nrays(s) >= 1
            ov, dv, vv = capture_rays(one, stride=s)
            H, W = im.shape[:2]
            rows = np.arange(min(s // 2, (H - 1) // 2), H, s)
            cols = np.arange(min(s // 2, (W - 1) // 2), W, s)
            np.testing.assert_allclose(vv, im[rows[:, None], cols[None, :]].reshape(len(vv), -1),
                                       atol=0.5 / 255 + 1e-12)  # 8-bit PNGs
    assert cap.nrays(1) == 17 * 11 + 9 * 14 + 30 * 3 + 1
    for target in [4, 5, 50, 100, 300, 400, cap.nrays(1), 10 ** 6]:
        s = cap.stride_for(target)
        assert cap.nrays(s) <= target and (s == 1 or cap.nrays(s - 1) > target)
        assert len(capture_rays(cap, target_rays=target)[0]) == cap.nrays(s)
    refused(lambda: cap.stride_for(3), "target_rays", error=InvalidInputError)
    refused(lambda: capture_rays(cap, stride=2, target_rays=100), "target_rays", error=InvalidInputError)
    refused(lambda: cap.nrays(0), "stride", error=InvalidInputError)


@pytest.mark.parametrize("stride", [1, 2])
def test_batches_concatenate_to_the_rays(tmp_path, stride):
    cap, _ = small_capture(tmp_path, [(16, 10), (12, 12), (20, 5), (7, 3), (25, 9)])
    o, d, v = capture_rays(cap, stride=stride)
    sizes = [len(capture_rays(cap.take([f.name]), stride=stride)[0]) for f in cap.frames]
    for batch_rays in (1, 7, 50, 100, 144, 200, 299, 1000, BATCH_RAYS):
        batches = list(capture_batches(cap, stride=stride, batch_rays=batch_rays))
        assert [b.index for b in batches] == list(range(len(batches)))
        assert all(len(b.origins) <= batch_rays for b in batches)  # memory bounded
        for x, y in zip((o, d, v), ("origins", "directions", "values")):
            np.testing.assert_array_equal(np.concatenate([getattr(b, y) for b in batches]), x)
        # frames: consecutive ranges; a frame is split only when it has more rays than a batch holds
        for b in batches:
            lo, hi = b.frames
            n = len(b.origins)
            if hi - lo > 1 or sum(sizes[lo:hi]) == n:
                assert sum(sizes[lo:hi]) == n
            else:
                assert sizes[lo] > batch_rays
        # deterministic
        again = list(capture_batches(cap, stride=stride, batch_rays=batch_rays))
        assert len(again) == len(batches)
        for a, b in zip(again, batches):
            assert a.frames == b.frames and a.index == b.index
            np.testing.assert_array_equal(a.values, b.values)
            np.testing.assert_array_equal(a.directions, b.directions)


def test_batches_read_one_image_at_a_time(tmp_path, monkeypatch):
    cap, _ = small_capture(tmp_path, [(10, 10)] * 6)
    read = []
    real = capture_module.read_image
    monkeypatch.setattr(capture_module, "read_image", lambda p: read.append(p) or real(p))
    it = capture_batches(cap, batch_rays=250)  # two frames a batch
    first = next(it)
    assert first.frames == (0, 2) and len(read) == 2
    next(it)
    assert len(read) == 4


def test_take_and_without(tmp_path):
    cap, images = small_capture(tmp_path, [(6, 4), (5, 5), (4, 6)])
    names = cap.names
    held = cap.without([names[1]])
    assert held.names == (names[0], names[2])
    assert cap.take([names[2], names[0]]).names == (names[0], names[2])
    np.testing.assert_allclose(capture_rays(cap.take([names[1]]))[2], images[1].reshape(-1, 3), atol=Q8)
    refused(lambda: cap.take(["nope"]), "names", "nope", error=InvalidInputError)
    refused(lambda: cap.without(list(names)), "names", error=InvalidInputError)


# ---------------------------------------------------------------- reading NeRF files
def nerf_capture(tmp_path, n=3, channels=3, seed=14, **kw) -> tuple[Path, dict]:
    rng = np.random.default_rng(seed)
    cams = [random_camera(rng, 8, 6) for _ in range(n)]
    path = write_nerf(tmp_path, cams, [rng.random((6, 8, channels)) for _ in cams], angle=False, **kw)
    return path, json.loads(path.read_text())


def rewrite(path: Path, doc: dict) -> None:
    path.write_text(json.dumps(doc))


def test_nerf_file_paths_and_per_frame_intrinsics(tmp_path):
    rng = np.random.default_rng(15)
    cams = [random_camera(rng, 8, 6) for _ in range(3)]
    images = [rng.random((6, 8, 3)) for _ in cams]
    path = write_nerf(tmp_path, cams, images, names=["train/r_0", "train/r_1", "r_2"], angle=False)
    doc = json.loads(path.read_text())
    assert "fl_x" in doc["frames"][0]  # intrinsics differ: written per frame
    doc["frames"][0]["file_path"] = "train/r_0"  # no extension, no ./
    doc["frames"][1]["file_path"] = "./train/r_1.png"
    doc["frames"][2]["file_path"] = "./r_2"
    rewrite(path, doc)
    cap = read_capture(path)  # the .json file itself
    assert cap.names == ("train/r_0", "train/r_1", "r_2")
    for f, cam in zip(cap.frames, cams):
        np.testing.assert_allclose(f.camera.rays()[1], cam.rays()[1], atol=GEOM_TOL)
    # top-level intrinsics with one frame's own
    doc2 = {"fl_x": 30.0, "cx": 4.0, "cy": 3.0, "frames": [dict(doc["frames"][k]) for k in range(3)]}
    for fr in doc2["frames"]:
        for key in ("fl_x", "fl_y", "cx", "cy", "w", "h"):
            fr.pop(key)
    doc2["frames"][1]["camera_angle_x"] = 1.0
    rewrite(path, doc2)
    cap = read_capture(tmp_path)
    f0, f1 = cap.frames[0].camera, cap.frames[1].camera
    assert (f0.fx, f0.fy, f0.cx, f0.cy, f0.width, f0.height) == (30.0, 30.0, 4.0, 3.0, 8, 6)
    assert math.isclose(f1.fx, 4 / math.tan(0.5)) and (f1.cx, f1.cy) == (4.0, 3.0)
    # a byte-order mark is read past
    path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
    assert read_capture(tmp_path).names == cap.names
    # transforms_train.json when there is no transforms.json
    path.rename(tmp_path / "transforms_train.json")
    assert read_capture(tmp_path, format="nerf").names == cap.names


def test_nerf_bad_captures(tmp_path):
    path, doc = nerf_capture(tmp_path)
    name = str(path)

    def bad(mutate, *parts):
        d = json.loads(json.dumps(doc))
        mutate(d)
        rewrite(path, d)
        return refused(lambda: read_capture(tmp_path), name, *parts)  # always names the file

    # missing image: the frame and the paths tried
    e = bad(lambda d: d["frames"][1].update(file_path="./gone"), name, "frames[1].file_path", "gone.png", "gone.jpg")
    assert e.field == "frames[1].file_path" and e.file == path
    # not rigid
    def scale(d):
        d["frames"][2]["transform_matrix"][0][0] *= 1.5
    e = bad(scale, name, "frames[2].transform_matrix", "not a rigid transform")
    assert e.field == "frames[2].transform_matrix"
    def last_row(d):
        d["frames"][0]["transform_matrix"][3] = [0, 0, 0.5, 1]
    bad(last_row, "frames[0].transform_matrix", "last row")
    bad(lambda d: d["frames"][0].update(transform_matrix=[[1, 0], [0, 1]]), "frames[0].transform_matrix")
    bad(lambda d: d["frames"][0].pop("transform_matrix"), "frames[0].transform_matrix", "missing")
    # size against w / h: names the image
    e = bad(lambda d: d["frames"][1].update(w=9), "frame_0001.png", "size", "8x6", "9x6")
    assert e.field == "size"
    bad(lambda d: d["frames"][1].pop("h"), "frames[1].h", "w and h")
    # no focal length; bad numbers
    def no_focal(d):
        for fr in d["frames"]:
            fr.pop("fl_x")
    bad(no_focal, name, "frames[0].camera_angle_x")
    bad(lambda d: d["frames"][0].update(fl_x="wide"), "frames[0].fl_x")
    bad(lambda d: d["frames"][0].update(fl_y=-3.0), "frames[0].fl_y")
    # distortion
    bad(lambda d: d.update(k1=0.02, p1=0.0), name, "k1", "k1=0.02", "colmap image_undistorter")
    bad(lambda d: d["frames"][2].update(camera_model="OPENCV_FISHEYE"), "frames[2].camera_model")
    # no frames, not a list, malformed JSON with its line
    bad(lambda d: d.update(frames=[]), name, "frames", "no frames")
    bad(lambda d: d.pop("frames"), name, "frames", "missing")
    bad(lambda d: d["frames"].append(3), "frames[3]")
    bad(lambda d: d["frames"][1].update(file_path=doc["frames"][0]["file_path"]), "frames[1].file_path", "repeats")
    path.write_text('{\n  "frames": [\n    {"file_path": "a",,}\n  ]\n}')
    e = refused(lambda: read_capture(tmp_path), name, "line 3", "malformed JSON")
    assert e.field == "line 3"


def test_bad_images(tmp_path):
    path, doc = nerf_capture(tmp_path)
    img = tmp_path / "frame_0001.png"
    good = img.read_bytes()
    # not an image
    img.write_bytes(b"not a picture at all")
    refused(lambda: read_capture(tmp_path), str(img), "image", "unreadable")
    # header fine, pixels corrupt: found when the pixels are read
    img.write_bytes(good[:60])
    cap = read_capture(tmp_path)
    e = refused(lambda: capture_rays(cap), str(img), "pixels")
    assert e.file == img
    # a different channel count
    Image.fromarray(np.zeros((6, 8), dtype=np.uint8)).save(img)
    refused(lambda: read_capture(tmp_path), str(img), "channels", "1 channel", "has 3")
    # changed after read_capture
    img.write_bytes(good)
    cap = read_capture(tmp_path)
    Image.fromarray(np.zeros((6, 8, 4), dtype=np.uint8)).save(img)
    refused(lambda: capture_rays(cap), str(img), "channels")
    img.unlink()
    refused(lambda: capture_rays(cap), str(img), "image", "missing")


def test_capture_errors_are_invalid_input_and_pickle():
    import pickle

    e = CaptureError("scene/transforms.json", "frames[3].transform_matrix", "not a rigid transform")
    assert isinstance(e, InvalidInputError) and isinstance(e, ValueError)
    assert str(e) == "scene/transforms.json: frames[3].transform_matrix: not a rigid transform"
    assert e.argument == e.field == "frames[3].transform_matrix"
    back = pickle.loads(pickle.dumps(e))
    assert str(back) == str(e) and back.field == e.field


# ---------------------------------------------------------------- reading COLMAP files
def colmap_capture(tmp_path, n=3, **kw) -> tuple[Path, list[PinholeCamera]]:
    rng = np.random.default_rng(16)
    cams = [random_camera(rng, 8, 6) for _ in range(n)]
    model = write_colmap(tmp_path, cams, [rng.random((6, 8, 3)) for _ in cams], **kw)
    return model, cams


def edit(file: Path, old: str, new: str) -> None:
    text = file.read_text()
    assert old in text
    file.write_text(text.replace(old, new, 1))


@pytest.mark.parametrize("model", ["SIMPLE_PINHOLE", "SIMPLE_RADIAL", "OPENCV"])
def test_colmap_models_without_distortion_are_pinholes(tmp_path, model):
    rng = np.random.default_rng(17)
    cams = [random_camera(rng, 8, 6).with_(fy=20.0, fx=20.0) for _ in range(3)]
    images = [rng.random((6, 8)) for _ in cams]
    write_colmap(tmp_path / "a", cams, images)
    write_colmap(tmp_path / "b", cams, images, model=model)
    a, b = read_capture(tmp_path / "a"), read_capture(tmp_path / "b")
    assert model in (tmp_path / "b" / "sparse" / "0" / "cameras.txt").read_text()
    for x, y in zip(capture_rays(a), capture_rays(b)):
        np.testing.assert_array_equal(x, y)


def test_colmap_model_places(tmp_path):
    model, cams = colmap_capture(tmp_path)
    # the model in DIR/sparse, in DIR itself; images next to the model
    for f in ("cameras.txt", "images.txt", "points3D.txt"):
        (model / f).rename(tmp_path / "sparse" / f)
    assert read_capture(tmp_path).format == "colmap"
    for f in ("cameras.txt", "images.txt", "points3D.txt"):
        (tmp_path / "sparse" / f).rename(tmp_path / f)
    rays = capture_rays(read_capture(tmp_path, format="colmap"))
    for p in (tmp_path / "images").iterdir():
        p.rename(tmp_path / p.name)
    moved = read_capture(tmp_path)
    assert [f.image.parent for f in moved.frames] == [tmp_path] * 3
    for x, y in zip(rays, capture_rays(moved)):
        np.testing.assert_array_equal(x, y)


def test_capture_not_found(tmp_path):
    refused(lambda: read_capture(tmp_path), str(tmp_path), "transforms.json", "cameras.txt")
    refused(lambda: read_capture(tmp_path / "nothing"), "nothing", "no such")
    (tmp_path / "sparse" / "0").mkdir(parents=True)
    (tmp_path / "sparse" / "0" / "images.bin").write_bytes(b"\0")
    refused(lambda: read_capture(tmp_path), "model_converter")
    nerf_capture(tmp_path / "n")
    refused(lambda: read_capture(tmp_path / "n", format="colmap"), "cameras.txt")
    colmap_capture(tmp_path / "c")
    refused(lambda: read_capture(tmp_path / "c", format="nerf"), "transforms.json")
    refused(lambda: read_capture(tmp_path / "c", format="blender"), "format", error=InvalidInputError)


def test_colmap_bad_captures(tmp_path):
    model, cams = colmap_capture(tmp_path)
    cam_file, img_file = model / "cameras.txt", model / "images.txt"
    cam_text, img_text = cam_file.read_text(), img_file.read_text()
    cam_lines = cam_text.splitlines()
    line = next(k for k, t in enumerate(cam_lines, 1) if t.startswith("1 PINHOLE"))
    _, _, w, h, fx, fy, cx, cy = cam_lines[line - 1].split()

    def bad_camera(new_line, *parts):
        cam_file.write_text(cam_text.replace(cam_lines[line - 1], new_line))
        e = refused(lambda: read_capture(tmp_path), str(cam_file), f"line {line}", *parts)
        cam_file.write_text(cam_text)
        assert e.field == f"line {line}"

    bad_camera(f"1 OPENCV {w} {h} {fx} {fy} {cx} {cy} 0.01 0 0 0.002", "camera 1", "model OPENCV",
               "k1=0.01", "p2=0.002", "colmap image_undistorter", "PINHOLE")
    bad_camera(f"1 SIMPLE_RADIAL {w} {h} {fx} {cx} {cy} -0.1", "SIMPLE_RADIAL", "k=-0.1")
    bad_camera(f"1 WEIRD_LENS {w} {h} {fx} {fy} {cx} {cy}", "camera 1", "unknown camera model", "WEIRD_LENS")
    bad_camera(f"1 OPENCV_FISHEYE {w} {h} {fx} {fy} {cx} {cy} 0 0 0 0", "fisheye")
    bad_camera(f"1 PINHOLE {w} {h} {fx} {fy} {cx}", "PINHOLE has 4 parameters", "got 3")
    bad_camera(f"1 PINHOLE {w} {h} {fx} {fy} {cx} big", "expected CAMERA_ID")
    bad_camera(f"1 PINHOLE {w} {h} -{fx} {fy} {cx} {cy}", "fx")
    # an image whose size differs from its camera's: names the image
    cam_file.write_text(cam_text.replace(cam_lines[line - 1], f"1 PINHOLE 16 12 {fx} {fy} {cx} {cy}"))
    e = refused(lambda: read_capture(tmp_path), "frame_0000.png", "size", "8x6", "16x12", str(cam_file))
    assert e.field == "size"
    cam_file.write_text(cam_text)

    img_lines = img_text.splitlines()
    first = next(k for k, t in enumerate(img_lines, 1) if t.startswith("1 "))
    tok = img_lines[first - 1].split()

    def bad_image(new_line, *parts, at=None):
        img_file.write_text(img_text.replace(img_lines[first - 1], new_line))
        e = refused(lambda: read_capture(tmp_path), str(img_file), f"line {at or first}", *parts)
        img_file.write_text(img_text)
        return e

    bad_image(" ".join(tok[:8] + ["9", tok[9]]), "camera 9", "not in")
    bad_image(" ".join(tok[:9] + ["gone.png"]), "gone.png", "not found", str(tmp_path / "images" / "gone.png"))
    bad_image(" ".join(tok[:1] + ["2.0"] + tok[2:]), "qvec", "norm")
    bad_image(" ".join(tok[:1] + ["x"] + tok[2:]), "expected IMAGE_ID")
    bad_image(" ".join(tok[:9]), "expected IMAGE_ID")
    bad_image(img_lines[first - 1] + "\n1.0 2.0", "2D points", at=first + 1)
    bad_image(" ".join(["2"] + tok[1:]), "image id 2 repeats")
    # no images
    img_file.write_text("# nothing\n")
    refused(lambda: read_capture(tmp_path), str(img_file), "no frames")
    img_file.write_text(img_text)
    # 2D points lines (triples) are read past
    with_points = img_text.splitlines()
    with_points[first] = "1.5 2.5 -1 3.0 4.0 17"
    img_file.write_text("\n".join(with_points) + "\n")
    assert len(read_capture(tmp_path).frames) == 3


def test_writers_refuse_bad_input(tmp_path):
    rng = np.random.default_rng(18)
    cam = random_camera(rng, 8, 6)
    img = rng.random((6, 8, 3))
    refused(lambda: write_nerf(tmp_path, [cam], [img]), "camera_angle_x", error=InvalidInputError)
    refused(lambda: write_nerf(tmp_path, [cam], [img[:5]], angle=False), "images[0]", error=InvalidInputError)
    refused(lambda: write_nerf(tmp_path, [cam], [img * 2], angle=False), "[0, 1]", error=InvalidInputError)
    refused(lambda: write_nerf(tmp_path, [cam], [img], bits=12, angle=False), "bits", error=InvalidInputError)
    refused(lambda: write_colmap(tmp_path, [cam, cam], [img]), "images", error=InvalidInputError)
    refused(lambda: write_colmap(tmp_path, [cam], [img], model="OPENCV_FISHEYE"), "model", error=InvalidInputError)
    refused(lambda: write_colmap(tmp_path, [cam], [img], model="SIMPLE_PINHOLE"), "fx = fy",
            error=InvalidInputError)
    refused(lambda: write_colmap(tmp_path, [cam], [img], names=["a.jpg"], bits=16), "JPEG",
            error=InvalidInputError)
