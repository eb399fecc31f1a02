"""The rig's geometry and the field a capture gets (flatserve.lightfield.rig)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from flatserve.errors import InvalidInputError
from flatserve.flats import Flats
from flatserve.lightfield.camera import PinholeCamera
from flatserve.lightfield.rig import (capture_atlas, field_spec, probe_rays, rig_center,
                                      rig_unit)

W, H, F = 40, 30, 55.0


def cam(eye, target, up=(0.0, 1.0, 0.0)) -> PinholeCamera:
    return PinholeCamera.look_at(eye, target, up, fx=F, fy=F, cx=W / 2, cy=H / 2, width=W, height=H)


def test_the_centre_is_the_point_every_axis_passes_through():
    rng = np.random.default_rng(0)
    p = rng.uniform(-2, 2, 3)
    eyes = p + 4 * rng.normal(size=(9, 3))
    np.testing.assert_allclose(rig_center([cam(e, p) for e in eyes]), p, atol=1e-9)


def test_the_centre_of_parallel_cameras_is_nearest_the_origin_along_them():
    cams = [cam((x, y, -3.0), (x, y, 0.0)) for x in (-1, 0, 1) for y in (-1, 1)]
    np.testing.assert_allclose(rig_center(cams), [0.0, 0.0, 0.0], atol=1e-9)


@pytest.mark.parametrize("n", [6, 12, 40])
def test_the_unit_of_a_ring_is_a_pixels_shift_over_the_turn_between_cameras(n):
    """Eyes evenly on a circle of radius R about the centre: neighbours 2 pi / n apart, a
    pixel's shift at the centre R / F."""
    rng = np.random.default_rng(n)
    c, R = rng.uniform(-1, 1, 3), 2.5
    a = 2 * math.pi * np.arange(n) / n
    cams = [cam(c + R * np.array([math.cos(t), 0.0, math.sin(t)]), c) for t in a]
    assert rig_unit(cams) == pytest.approx((R / F) / (2 * math.pi / n), rel=1e-8)


def test_a_rig_without_a_turn_has_no_unit():
    assert rig_unit([cam((0, 0, -3), (0, 0, 0))]) is None
    # two eyes in one direction from the centre (one behind the other)
    assert rig_unit([cam((0, 0, -3), (0, 0, 0)), cam((0, 0, -5), (0, 0, 0))]) is None
    with pytest.raises(InvalidInputError) as exc:
        rig_unit([])
    assert exc.value.argument == "cameras"


def test_probe_rays_span_each_image_corner_to_corner():
    cams = [cam((x, 0.0, -3.0), (0, 0, 0)) for x in (-1.0, 1.0)]
    o, d = probe_rays(cams, side=3)
    assert o.shape == d.shape == (18, 3)
    for k, c in enumerate(cams):
        want = c.grid_rays([0.5, W / 2, W - 0.5], [0.5, H / 2, H - 0.5])[1]
        np.testing.assert_allclose(d[9 * k:9 * k + 9], want, rtol=1e-8, atol=1e-12)
    with pytest.raises(InvalidInputError) as exc:
        probe_rays(cams, side=1)
    assert exc.value.argument == "side"


def test_the_atlas_holds_every_ray_of_the_capture():
    rng = np.random.default_rng(3)
    eyes = rng.normal(size=(20, 3))
    eyes = 3 * eyes / np.linalg.norm(eyes, axis=1, keepdims=True)  # all around the origin
    cams = [cam(e, (0, 0, 0), up=(0.0, 0.0, 1.0) if abs(e[1]) > 2.9 else (0.0, 1.0, 0.0))
            for e in eyes]
    atlas = capture_atlas(cams)
    assert atlas.oriented and atlas.unit == rig_unit(cams)
    o, d = zip(*(c.rays() for c in cams))
    rays = Flats.from_rays(np.concatenate(o), np.concatenate(d))
    stored = np.zeros(rays.n, dtype=bool)
    for rows in atlas.route(rays, atlas.reach).rows:
        stored[rows] = True
    assert stored.all()


def test_either_format_of_a_capture_gets_the_same_spec():
    """Poses that differ by rounding (a capture read from NeRF's or COLMAP's files) get
    the same choices, bit for bit."""
    rng = np.random.default_rng(4)
    cams = [cam((x, y, -3.0), (0, 0, 0)) for x in (-0.5, 0, 0.5) for y in (-0.3, 0.3)]
    nudged = [PinholeCamera(eye=c.eye * (1 + 1e-16 * rng.choice([-1, 1], 3)), rotation=c.rotation,
                            fx=c.fx, fy=c.fy, cx=c.cx, cy=c.cy, width=W, height=H) for c in cams]
    assert any((a.eye != b.eye).any() for a, b in zip(cams, nudged))
    assert field_spec(cams, 3) == field_spec(nudged, 3)
    spec = field_spec(cams, 3)
    assert spec["channels"] == 3 and spec["oriented"] is True and spec["unit"] == rig_unit(cams)
    assert spec["basis"]["atlas"] == "samples"


def test_nearly_parallel_cameras_leave_the_unit_to_the_data():
    """A forward-facing rig of parallel cameras with pose noise: the point their axes
    nearly meet is anywhere (noise of 1e-3 radians put it behind them), so no rig unit."""
    rng = np.random.default_rng(6)
    for noise in (0.0, 1e-4, 1e-3):  # radians
        cams = [cam((x, y, -3.0), (x + 3 * noise * rng.normal(), y + 3 * noise * rng.normal(), 0.0))
                for x in np.linspace(-0.7, 0.7, 8) for y in np.linspace(-0.4, 0.4, 5)]
        assert rig_unit(cams) is None, noise
        assert field_spec(cams, 1)["unit"] == "data"
    # toed in by a few degrees: the centre is where they look
    toed = [cam((x, y, -3.0), (0, 0, 0)) for x in (-0.7, 0.0, 0.7) for y in (-0.4, 0.4)]
    assert rig_unit(toed) is not None


def test_a_centre_behind_a_camera_gives_no_unit():
    # two cameras looking away from each other: their axes meet behind both
    cams = [cam((-1.0, 0.0, 0.0), (-2.0, 0.0, 0.3)), cam((1.0, 0.0, 0.0), (2.0, 0.0, 0.3))]
    assert rig_unit(cams) is None
