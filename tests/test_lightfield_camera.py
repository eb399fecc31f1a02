"""Paper sampling, pinhole cameras and image metrics (flatserve.lightfield)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from flatserve.errors import InvalidInputError
from flatserve.lightfield import Camera, paper_samples, rotation_about
from flatserve.lightfield.camera import EYE_HIGH, EYE_LOW
from flatserve.lightfield.quality import psnr, ssim

#: Geometry computed two ways agrees to rounding.
GEOM_TOL = 1e-12


def test_paper_samples_shapes_and_geometry():
    rng = np.random.default_rng(0)
    n = 37
    s = paper_samples(n, rng)
    assert s.origins.shape == s.directions.shape == s.screen.shape == (n * n, 3)
    assert s.shape == (n, n)
    assert np.all(s.origins >= EYE_LOW) and np.all(s.origins <= EYE_HIGH)
    np.testing.assert_allclose(np.linalg.norm(s.directions, axis=1), 1, atol=GEOM_TOL)
    # each ray passes through its pixel centre on z = 0
    t = -s.origins[:, 2] / s.directions[:, 2]
    np.testing.assert_allclose(s.origins + t[:, None] * s.directions, s.screen, atol=1e-12)
    # scanline order: row 0 at the top, x increasing along a row
    grid = s.screen[:, :2].reshape(n, n, 2)
    assert np.all(np.diff(grid[..., 0], axis=1) > 0) and np.all(np.diff(grid[..., 1], axis=0) < 0)
    assert np.allclose(np.abs(grid).max(), 1 - 1 / n)
    # eyes cover the box (uniform): means near the centre
    se = (np.asarray(EYE_HIGH) - EYE_LOW) / math.sqrt(12 * n * n)
    assert np.all(np.abs(s.origins.mean(0) - (np.add(EYE_LOW, EYE_HIGH) / 2)) < 5 * se)
    # seeded: same rng seed, same samples
    s2 = paper_samples(n, np.random.default_rng(0))
    np.testing.assert_array_equal(s.origins, s2.origins)


def test_default_camera_sees_the_sampling_screen():
    cam = Camera(width=8, height=6, supersample=4)
    o, d = cam.rays()
    assert o.shape == d.shape == (8 * 6 * 4, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1, atol=GEOM_TOL)
    t = -o[:, 2] / d[:, 2]
    p = o + t[:, None] * d
    W, H = 16, 12
    xs = ((np.arange(W) + 0.5) / W * 2 - 1) * (-cam.eye[2] / cam.focal)  # u * depth / focal
    ys = (1 - (np.arange(H) + 0.5) / H * 2) * (H / W)
    np.testing.assert_allclose(p[:, 0].reshape(H, W), np.broadcast_to(xs, (H, W)), atol=GEOM_TOL)
    np.testing.assert_allclose(p[:, 1].reshape(H, W), np.broadcast_to(ys[:, None], (H, W)), atol=GEOM_TOL)


def test_focal_length_scales_the_view():
    a = Camera(width=4, height=4, supersample=1, focal=2.0).rays()[1]
    b = Camera(width=4, height=4, supersample=1, focal=4.0).rays()[1]
    # slopes x/z halve when the focal length doubles
    np.testing.assert_allclose(b[:, :2] / b[:, 2:], a[:, :2] / a[:, 2:] / 2, atol=GEOM_TOL)


@pytest.mark.parametrize("axis", ["x", "y", "z"])
def test_rotated_camera_turns_eye_and_rays_together(axis):
    cam = Camera(width=5, height=5, supersample=1)
    R = rotation_about(axis, 10)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=GEOM_TOL)
    rot = cam.rotated(axis, 10)
    o0, d0 = cam.rays()
    o1, d1 = rot.rays()
    np.testing.assert_allclose(o1, o0 @ R.T, atol=GEOM_TOL)
    np.testing.assert_allclose(d1, d0 @ R.T, atol=GEOM_TOL)
    np.testing.assert_allclose(np.linalg.norm(rot.eye), np.linalg.norm(cam.eye), atol=GEOM_TOL)


def test_look_at_and_orbit_point_at_the_target():
    rng = np.random.default_rng(1)
    for _ in range(10):
        eye = rng.normal(size=3) * 3
        cam = Camera.look_at(eye, target=(0, 0, 0))
        np.testing.assert_allclose(cam.rotation[:, 2], -eye / np.linalg.norm(eye), atol=GEOM_TOL)
        yaw, pitch = rng.uniform(-80, 80, 2)
        orb = Camera.orbit(yaw, pitch, distance=2.5)
        np.testing.assert_allclose(np.linalg.norm(orb.eye), 2.5, atol=GEOM_TOL)
        np.testing.assert_allclose(orb.rotation[:, 2], -orb.eye / 2.5, atol=GEOM_TOL)
    o = Camera.orbit(0, 0)
    np.testing.assert_allclose(o.eye, Camera().eye, atol=GEOM_TOL)
    np.testing.assert_allclose(o.rotation, np.eye(3), atol=GEOM_TOL)


def test_resolve_averages_supersamples():
    rng = np.random.default_rng(2)
    cam = Camera(width=3, height=2, supersample=9)
    v = rng.uniform(size=(cam.nrays, 2))
    img = cam.resolve(v)
    assert img.shape == (2, 3, 2)
    fine = v.reshape(6, 9, 2)
    np.testing.assert_allclose(img[1, 2], fine[3:6, 6:9].mean(axis=(0, 1)), atol=GEOM_TOL)
    # weights: a pixel with no weight is NaN, others average the weighted rays
    w = np.ones(cam.nrays)
    w.reshape(6, 9)[0:3, 0:3] = 0
    w.reshape(6, 9)[0, 3] = 0
    img = cam.resolve(v, weights=w)
    assert np.all(np.isnan(img[0, 0]))
    np.testing.assert_allclose(img[0, 1], (fine[0:3, 3:6].sum((0, 1)) - fine[0, 3]) / 8, atol=GEOM_TOL)


def test_camera_rejects_bad_parameters():
    for kwargs, arg in [({"supersample": 2}, "supersample"), ({"focal": 0.0}, "focal"),
                        ({"width": 0}, "width"), ({"rotation": np.diag([1, 1, -1])}, "rotation"),
                        ({"eye": [0, 1]}, "eye")]:
        with pytest.raises(InvalidInputError) as e:
            Camera(**kwargs)
        assert e.value.argument == arg
    with pytest.raises(InvalidInputError):
        paper_samples(0, np.random.default_rng(0))
    # an eye or target so far out that the view direction overflows is named, not up
    for kwargs, arg in [({"eye": [1e308, 0, 0]}, "eye"),
                        ({"eye": [3, 0, 0], "target": [0, -1e200, 0]}, "target"),
                        ({"eye": [0, 3, 0]}, "up")]:
        with pytest.raises(InvalidInputError) as e:
            Camera.look_at(**kwargs)
        assert e.value.argument == arg


def test_psnr_of_perfect_and_noisy_reconstructions():
    rng = np.random.default_rng(3)
    truth = rng.uniform(size=(64, 64))
    assert psnr(truth, truth) == math.inf
    sigma = 0.05
    noisy = truth + rng.normal(scale=sigma, size=truth.shape)
    p = psnr(noisy, truth)
    assert math.isfinite(p)
    # MSE ~ sigma^2: 4096 pixels give ~2% relative error of the MSE, ~0.1 dB
    assert abs(p - 10 * math.log10(1 / sigma**2)) < 0.5
    # the mask restricts the comparison
    bad = noisy.copy()
    bad[:, :10] = 10.0
    mask = np.ones_like(truth, dtype=bool)
    mask[:, :10] = False
    assert psnr(bad, truth, mask) == pytest.approx(psnr(noisy, truth, mask))
    assert psnr(bad, truth) < p
    assert math.isnan(psnr(noisy, truth, np.zeros_like(mask)))
    with pytest.raises(InvalidInputError):
        psnr(truth[:5], truth)


def test_ssim_is_one_for_identical_images_and_lower_for_noise():
    pytest.importorskip("skimage")
    rng = np.random.default_rng(4)
    truth = rng.uniform(size=(40, 40, 3))
    assert ssim(truth, truth) == pytest.approx(1.0)
    noisy = np.clip(truth + rng.normal(scale=0.2, size=truth.shape), 0, 1)
    assert ssim(noisy, truth) < 0.9
