"""Depth from a capture's photographs and renders through it (flatserve.lightfield.depth)."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from flatserve.cli import main as cli_main
from flatserve.errors import InvalidInputError
from flatserve.flats import Flats
from flatserve.lightfield import capture as capture_module
from flatserve.lightfield.camera import PinholeCamera
from flatserve.lightfield.capture import capture_batches, field_options, read_capture, write_nerf
from flatserve.lightfield.capture_figure import capture_depth, capture_field, photograph, synthetic_rig
from flatserve.lightfield.depth import (DEPTH_PLANES, depth_map, depth_values, guided_values, render_guided,
                                        sweep_range)
from flatserve.lightfield.render import render_field
from flatserve.lightfield.rig import (DepthRig, depth_rig, field_spec, rig_spacing_deg,
                                      wants_depth)
from flatserve.lightfield.sampling import blocks_scene


@pytest.fixture(scope="module")
def scene():
    return blocks_scene()


@pytest.fixture(scope="module")
def sphere(scene):
    """The sphere rig at a quarter of its size (16 x 16 pixels), its photographs and rig."""
    cams, held = synthetic_rig("sphere", size=0.25)
    return cams, held, [photograph(scene, c) for c in cams], depth_rig(cams)


def test_the_depth_channel_is_a_value_of_the_line():
    """The same line from another origin has the same value; the depth comes back."""
    rng = np.random.default_rng(0)
    o = rng.normal(size=(50, 3))
    d = rng.normal(size=(50, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t, c = rng.uniform(0.5, 4, 50), rng.normal(size=3)
    s = depth_values(o, d, t, c)
    shift = rng.uniform(-3, 3, 50)
    np.testing.assert_allclose(depth_values(o + shift[:, None] * d, d, t - shift, c), s, atol=1e-12)
    np.testing.assert_allclose(s + np.einsum("ij,ij->i", c - o, d), t, atol=1e-12)


@pytest.mark.parametrize("n", [8, 20])
def test_the_spacing_of_a_ring_is_its_turn(n):
    a = 2 * math.pi * np.arange(n) / n
    cams = [PinholeCamera.look_at((3 * math.cos(x), 0.0, 3 * math.sin(x)), (0, 0, 0), fx=20, fy=20, cx=8,
                                  cy=8, width=16, height=16) for x in a]
    assert rig_spacing_deg(cams) == pytest.approx(360 / n, rel=1e-9)


def test_sparse_rigs_all_around_want_depth_and_forward_facing_ones_do_not():
    for name, wanted in (("forward", False), ("sphere", True), ("hemisphere", True)):
        cams, _ = synthetic_rig(name, size=0.25)
        assert wants_depth(cams) is wanted, name
        spec = field_spec(cams, 3)
        assert ("rig" in spec) is wanted and spec["channels"] == 3 + wanted
    cams, _ = synthetic_rig("forward", size=0.25)
    assert field_spec(cams, 3, depth=True)["channels"] == 4  # asked for
    cams, _ = synthetic_rig("sphere", size=0.25)
    assert "rig" not in field_spec(cams, 3, depth=False)


def test_plane_sweep_finds_the_scenes_depth(scene):
    """Against the scene's own ray casts (the oracle), on the half-size sphere rig (32 x 32
    pixels; at 16 x 16 a 5-pixel patch is a third of the image and the median error is 4
    steps, at full size under 1): on pixels that hit the scene, the median depth within two
    of the sweep's steps, most within four."""
    cams, _ = synthetic_rig("sphere", size=0.5)
    photos = [photograph(scene, c) for c in cams]
    rig = depth_rig(cams)
    errors, steps = [], []
    for i in range(0, len(cams), 5):
        got = depth_map(i, cams, lambda j: photos[j], center=rig.center)
        o, d = cams[i].rays()
        truth = scene.cast(o, d).t.reshape(got.shape)
        hit = np.isfinite(truth)
        errors.append(np.abs(got - truth)[hit])
        near, far = sweep_range(cams[i], rig.center)
        steps.append((far - near) / (DEPTH_PLANES - 1))
    e = np.concatenate(errors)
    assert np.median(e) <= 2 * max(steps), (np.median(e), max(steps))
    assert np.mean(e <= 4 * max(steps)) > 0.7


def test_a_plain_background_is_far(scene, sphere):
    """Where many depths match (the background, 0 in every photograph) the farthest of them
    is taken: mostly behind the rig's centre, not in front of the scene (the nearest tie
    stood in front of the scene for every ray passing an object's edge)."""
    cams, _, photos, rig = sphere
    got = depth_map(7, cams, lambda j: photos[j], center=rig.center)
    o, d = cams[7].rays()
    miss = ~np.isfinite(scene.cast(o, d).t.reshape(got.shape))
    near, far = sweep_range(cams[7], rig.center)
    # pixels whose whole patch is background in this photograph
    from scipy.ndimage import binary_erosion

    deep = binary_erosion(miss, np.ones((7, 7)), border_value=1)
    assert deep.sum() > 10
    middle = np.linalg.norm(cams[7].eye - rig.center)
    # (the nearest tie: a median of 2.66 here, some at 1.99, in front of the scene's middle)
    assert np.median(got[deep]) > middle and (got[deep] <= far + 1e-9).all(), (got[deep], middle)


def test_depth_maps_read_a_frame_and_its_neighbours_only(sphere):
    cams, _, photos, rig = sphere
    asked = []
    depth_map(3, cams, lambda j: asked.append(j) or photos[j], center=rig.center, neighbours=4)
    eyes = np.stack([c.eye for c in cams])
    nearest = set(np.argsort(np.linalg.norm(eyes - cams[3].eye, axis=1))[1:5].tolist())
    assert asked[0] == 3 and set(asked[1:]) == nearest and len(asked) == 5


def _field(cams, photos, rig, scene):
    """The field the importer makes of the rig (colour and depth channel)."""
    o = np.concatenate([c.rays()[0] for c in cams])
    d = np.concatenate([c.rays()[1] for c in cams])
    v = np.concatenate([scene.shade(*c.rays()) for c in cams])
    field, _ = capture_field(cams, o, d, np.c_[v, capture_depth(cams, photos, o, d, rig)])
    return field


@pytest.fixture(scope="module")
def sphere_field(scene, sphere):
    cams, _, photos, rig = sphere
    return _field(cams, photos, rig, scene)


def test_a_rig_camera_renders_its_own_photograph(sphere, sphere_field):
    """At a capture's own rays the guided render answers the photograph: the camera itself
    is the one nearest in angle (weight 1 / 0) and sees its own depth."""
    cams, _, photos, rig = sphere
    field = sphere_field

    def query(o, d):
        r = field.query(Flats.from_rays(o, d))
        return r.values, r.inside

    for i in (0, 17, 40):
        o, d = cams[i].rays()
        values, inside = guided_values(query, o, d, rig)
        assert values.shape == (o.shape[0], 1)
        ok = inside & np.isfinite(values[:, 0])
        assert ok.mean() > 0.99
        np.testing.assert_allclose(values[ok, 0], photos[i].reshape(-1)[ok], atol=1e-5)


def test_a_view_from_a_rig_eye_with_rays_the_field_has_no_value_for(sphere, sphere_field):
    """An eye on a rig camera's, looking half away from the scene: the rays without a value
    stay without one (NaN, not a depth of 0 at the eye), the others are rendered."""
    cams, _, photos, rig = sphere
    cam = cams[5].with_(rotation=cams[5].rotation @ np.array(
        [[math.cos(0.3), 0, math.sin(0.3)], [0, 1, 0], [-math.sin(0.3), 0, math.cos(0.3)]]))
    frame = render_guided(sphere_field, cam, rig, fill=np.nan)
    plain = render_field(sphere_field, cam, fill=np.nan)
    assert 0 < frame.coverage < 1
    np.testing.assert_array_equal(np.isnan(frame.image[..., 0]), np.isnan(plain.image[..., 0]))
    assert np.isfinite(frame.image[frame.covered]).all()


def test_a_query_without_the_depth_channel_is_refused(sphere):
    cams, _, _, rig = sphere
    o, d = cams[0].rays()
    with pytest.raises(InvalidInputError) as exc:
        guided_values(lambda o, d: (np.zeros((len(o), 1)), np.ones(len(o), dtype=bool)), o, d, rig)
    assert exc.value.argument == "query"


def test_the_sphere_rig_beats_the_two_sphere_light_field_on_every_held_out_view(tmp_path):
    """The quick sphere rig (half-size images, 62 cameras 24 degrees apart): the field the
    importer creates (with the depth channel) rendered through its depth, against the two-sphere
    k nearest rays with k and the radius chosen in the baseline's favour; the issue's bar:
    median at least 1 dB above, no view below (docs/capture-results.md: full size)."""
    assert cli_main(["lightfield", "capture-figure", "--out", str(tmp_path), "--quick",
                     "--rig", "sphere"]) == 0
    (res,) = json.loads((tmp_path / "capture-results.json").read_text())
    assert res["render"] == "depth-guided"
    gains = np.array([v["ours"] - v["baseline"] for v in res["views"]])
    assert np.median(gains) >= 1.0 and gains.min() > 0.0, gains
    # and the depth is what wins: the same field rendered without it does not
    assert np.median([v["ours"] - v["field"] for v in res["views"]]) > 0.5


def test_capture_batches_append_the_depth_channel(tmp_path, sphere):
    cams, _, photos, _ = sphere
    write_nerf(tmp_path, cams[:12], photos[:12], angle=False, bits=16)
    cap = read_capture(tmp_path)
    options = field_options(cap, depth=True)
    rig = DepthRig.from_dict(options["rig"])
    assert options["channels"] == 2
    got = list(capture_batches(cap, stride=2, depth=rig, batch_rays=200))
    plain = list(capture_batches(cap, stride=2, batch_rays=200))
    split = list(capture_batches(cap, stride=2, depth=rig, batch_rays=40))  # frames cut in two
    assert len(split) > len(got)
    np.testing.assert_array_equal(np.concatenate([b.values for b in split]),
                                  np.concatenate([b.values for b in got]))
    images = [capture_module.read_image(f.image) for f in cap.frames]
    for b, p in zip(got, plain):
        np.testing.assert_array_equal(b.values[:, :1], p.values)
        k0, k1 = b.frames
        want = []
        for k in range(k0, k1):
            t = depth_map(k, cap.cameras, lambda j: images[j], center=rig.center)[1::2, 1::2].reshape(-1)
            o, d = cap.cameras[k].grid_rays(np.arange(1, 16, 2) + 0.5, np.arange(1, 16, 2) + 0.5)
            want.append(depth_values(o, d, t, rig.center))
        np.testing.assert_allclose(b.values[:, 1], np.concatenate(want), atol=1e-12)
    assert "rig" not in field_options(cap, depth=False)


def test_depth_reads_boundedly_many_images(tmp_path, sphere, monkeypatch):
    """Images are read on demand and a few kept: never the whole capture in memory."""
    cams, _, photos, _ = sphere
    write_nerf(tmp_path, cams[:20], photos[:20], angle=False)
    cap = read_capture(tmp_path)
    rig = DepthRig.from_dict(field_options(cap, depth=True)["rig"])
    alive = []
    real = capture_module.read_image

    class Tracked(np.ndarray):
        pass

    import weakref

    def read(p):
        img = real(p).view(Tracked)
        alive.append(weakref.ref(img))
        return img

    monkeypatch.setattr(capture_module, "read_image", read)
    most = 0
    for _ in capture_batches(cap, depth=rig, batch_rays=256):
        most = max(most, sum(r() is not None for r in alive))
    assert most <= 2 * 4 + 3, most


def test_bad_arguments_name_their_field(sphere):
    cams, _, photos, rig = sphere
    for kwargs, field in (({"eyes": [[0, 0, 1]], "center": [0, 0, 0]}, "eyes"),
                          ({"eyes": [[0, 0, 1, 2]] * 3, "center": [0, 0, 0]}, "eyes"),
                          ({"eyes": [[0, 0, 1]] * 3, "center": [0, 0]}, "center")):
        with pytest.raises(InvalidInputError) as exc:
            DepthRig(**kwargs)
        assert exc.value.argument == field
    with pytest.raises(InvalidInputError) as exc:
        depth_map(0, cams, lambda j: photos[j], center=rig.center, planes=1)
    assert exc.value.argument == "planes"
    with pytest.raises(InvalidInputError) as exc:
        depth_map(len(cams), cams, lambda j: photos[j], center=rig.center)
    assert exc.value.argument == "index"
    query = lambda o, d: (np.zeros((len(o), 2)), np.ones(len(o), dtype=bool))  # noqa: E731
    o, d = cams[0].rays()
    with pytest.raises(InvalidInputError) as exc:
        guided_values(query, o, d, rig, candidates=2, blend=3)
    assert exc.value.argument == "blend"
    with pytest.raises(InvalidInputError) as exc:
        guided_values(query, o, d, rig, visibility_tol=0)
    assert exc.value.argument == "visibility_tol"


def test_small_rgba_and_two_camera_captures_take_depth(tmp_path, sphere):
    """Two cameras (each the other's one neighbour), RGBA images: the depth channel is the
    fifth; transparent pixels match as what they are stored as."""
    cams, _, photos, _ = sphere
    rgba = [np.concatenate([np.repeat(p, 3, axis=2), (p > 0).astype(float)], axis=2) for p in photos[:2]]
    write_nerf(tmp_path, cams[:2], rgba, angle=False)
    cap = read_capture(tmp_path)
    options = field_options(cap, depth=True)
    assert options["channels"] == 5
    (batch,) = capture_batches(cap, depth=DepthRig.from_dict(options["rig"]))
    assert batch.values.shape == (2 * 16 * 16, 5) and np.isfinite(batch.values).all()


def test_depth_is_asked_for_only_where_it_can_be(tmp_path, sphere):
    cams, _, photos, _ = sphere
    write_nerf(tmp_path / "a", cams[:3], photos[:3], angle=False)
    cap = read_capture(tmp_path / "a")
    for bad in (1, 0, "yes"):
        with pytest.raises(InvalidInputError) as exc:
            field_options(cap, depth=bad)
        assert exc.value.argument == "depth"
    parallel = [PinholeCamera.look_at((x, 0.0, -3.0), (x, 0.0, 0.0), fx=20, fy=20, cx=8, cy=8, width=16,
                                      height=16) for x in (-1.0, 0.0, 1.0)]
    assert depth_rig(parallel) is None
    with pytest.raises(InvalidInputError) as exc:
        depth_rig(parallel, depth=True)
    assert exc.value.argument == "depth"
