"""Rendering from a light field against ground truth, baselines, the figure pipeline."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from flatserve.lightfield import Camera, Mesh, Scene, box_mesh, icosphere
from flatserve.lightfield.baselines import NearestEmbedded, TwoPlane, two_plane_coordinates
from flatserve.lightfield.mesh import CGAL_DATA_TARBALL
from flatserve.lightfield.quality import psnr
from flatserve.lightfield.render import render_field, render_truth
from flatserve.lightfield.sampling import build_field, sample_scene

#: Interpolating at a sample's own line returns its value up to rounding of
#: the coordinates (round trip 1e-6) and barycentric weights.
AT_SAMPLE_TOL = 1e-6
#: Better than the best constant image by at least this many dB.
CONSTANT_MARGIN_DB = 3.0
N_SAMPLES = 60  # 3600 rays: small enough for a test, enough to see the shapes


def two_shapes() -> Mesh:
    """A sphere and a box beside it (made in code)."""
    s = icosphere(3, radius=0.3, center=(-0.2, 0.05, 0.0))
    b = box_mesh((0.05, -0.35, -0.15), (0.4, 0.0, 0.2))
    return Mesh(np.vstack([s.vertices, b.vertices]), np.vstack([s.faces, b.faces + len(s.vertices)]))


@pytest.fixture(scope="module")
def scene():
    return Scene(two_shapes(), background=0.05)


@pytest.fixture(scope="module")
def sampled(scene):
    samples, values = sample_scene(scene, N_SAMPLES, seed=7)
    field, stats = build_field(samples.origins, samples.directions, values)
    return samples, values, field, stats


def test_a_field_in_tiles_renders_the_same_pixels(scene, monkeypatch):
    """build_field's default ``tiles="auto"`` (the threshold lowered so that these
    3,600 rays make 2 tiles) renders the very pixels of the field in one piece."""
    import flatserve.tiles as tiles_mod
    from flatserve.parallel import ShardPool

    monkeypatch.setattr(tiles_mod, "AUTO_MIN_SAMPLES", 2000)
    monkeypatch.setattr(tiles_mod, "shard_pool", lambda p=ShardPool(2): p)
    samples, values = sample_scene(scene, N_SAMPLES, seed=8)
    one, _ = build_field(samples.origins, samples.directions, values, tiles=1, chunk=1000)
    tiled, stats = build_field(samples.origins, samples.directions, values, chunk=1000)
    assert tiled.triangulation.ntiles == 2 and tiled.triangulation.settled
    cam = Camera.look_at(eye=(0.3, 0.2, -3.0), target=(0, 0, 0), width=24, height=24)
    a, b = render_field(one, cam), render_field(tiled, cam)
    assert a.covered.mean() > 0.5 and np.array_equal(a.covered, b.covered)
    assert np.array_equal(a.image, b.image)


def test_field_accounts_for_every_sample(sampled):
    samples, values, field, stats = sampled
    assert stats.samples == N_SAMPLES**2
    assert stats.accepted + stats.rejected == stats.samples
    assert field.nsamples == stats.accepted - stats.duplicates
    # the paper: all but very few rays are inside the chart
    assert stats.rejected < 0.1 * stats.samples


def test_field_reproduces_its_samples(sampled):
    samples, values, field, _ = sampled
    rng = np.random.default_rng(0)
    idx = rng.choice(values.shape[0], 300, replace=False)
    res = field.query_rays(samples.origins[idx], samples.directions[idx])
    ok = res.inside
    assert ok.mean() > 0.8
    np.testing.assert_allclose(res.values[ok], values[idx][ok], atol=AT_SAMPLE_TOL)


@pytest.mark.parametrize("view", ["front", "zoom", "turned"])
def test_render_beats_a_constant_image(scene, sampled, view):
    field = sampled[2]
    cam = Camera(width=40, height=40, supersample=4, focal=3.5)
    if view == "zoom":
        cam = cam.with_(focal=5.0)
    elif view == "turned":
        cam = cam.rotated("y", 10).rotated("x", -10)
    frame = render_field(field, cam, fill=0.05)
    truth = render_truth(scene, cam)
    assert frame.image.shape == truth.image.shape == (40, 40, 1)
    assert frame.covered.shape == (40, 40)
    assert frame.coverage > 0.8
    assert set(frame.timings) == {"rays", "coordinates", "locate_interpolate", "resolve"}
    cov = frame.covered
    ours = psnr(frame.image, truth.image, cov)
    constant = np.full_like(truth.image, truth.image[cov].mean())  # best constant in MSE
    assert math.isfinite(ours)
    assert ours > psnr(constant, truth.image, cov) + CONSTANT_MARGIN_DB


def test_render_order_does_not_change_values(sampled):
    field = sampled[2]
    cam = Camera(width=12, height=12, supersample=1, focal=4)
    o, d = cam.rays()
    a = field.query_rays(o, d, order="given")
    b = field.query_rays(o, d, order="hilbert")
    np.testing.assert_array_equal(a.inside, b.inside)
    np.testing.assert_allclose(a.values[a.inside], b.values[b.inside], atol=1e-12)


def test_baselines_on_the_same_samples(scene, sampled):
    samples, values, field, _ = sampled
    cam = Camera(width=24, height=24, supersample=1, focal=4)
    o, d = cam.rays()
    truth = scene.shade(o, d)
    tp = TwoPlane(samples.origins, samples.directions, values)
    v, inside = tp(o, d)
    assert v.shape == (o.shape[0], 1) and inside.mean() > 0.9
    err_tp = np.sqrt(np.mean((v[inside] - truth[inside]) ** 2))
    nn = NearestEmbedded.from_field(field)
    assert nn.points.shape == (field.nsamples, field.ndim)
    frame = render_field(field, cam)
    v_nn = nn(frame.chart.points)
    err_nn = np.sqrt(np.mean((v_nn - truth[frame.chart.ok]) ** 2))
    spread = truth.std()
    assert err_tp < spread and err_nn < spread * 1.5
    # nearest sample of a sample's own coordinates is itself
    np.testing.assert_array_equal(nn(nn.points[:50]), nn.values[:50])


def test_two_plane_coordinates_are_the_plane_crossings():
    rng = np.random.default_rng(1)
    o = rng.uniform(-1, 1, (100, 3)) + [0, 0, -4]
    d = rng.normal(size=(100, 3))
    d[:, 2] = np.abs(d[:, 2]) + 0.1
    st = two_plane_coordinates(o, d, planes=(0.0, -3.0))
    for j, z in enumerate((0.0, -3.0)):
        t = (z - o[:, 2]) / d[:, 2]
        np.testing.assert_allclose(st[:, 2 * j:2 * j + 2], (o + t[:, None] * d)[:, :2], atol=1e-12)
    d[0, 2] = 0.0
    assert np.all(np.isnan(two_plane_coordinates(o[:1], d[:1])))


@pytest.mark.skipif(not CGAL_DATA_TARBALL.is_file(), reason="Debian libcgal-demo not installed")
def test_paper_figure_small(tmp_path):
    from flatserve.lightfield.figure import paper_figure, paper_views

    res = paper_figure(tmp_path, n=40, width=24, supersample=4, log=lambda s: None, progress=False)
    names = [name for name, _ in paper_views()]
    assert [v["view"] for v in res["views"]] == names
    assert len(names) == 4 + 6
    for name in names:
        for suffix in ("field", "two_plane", "nearest", "truth"):
            assert (tmp_path / f"{name}_{suffix}.png").is_file()
    for f in ("contact_sheet.png", "samples.png", "results.md", "results.json"):
        assert (tmp_path / f).is_file()
    on_disk = json.loads((tmp_path / "results.json").read_text())
    assert sum(on_disk["wins"].values()) == len(names)
    for v in on_disk["views"]:
        assert v["winner"] in v["methods"]
        assert 0.0 <= v["methods"]["field"]["coverage"] <= 1.0


@pytest.mark.skipif(not CGAL_DATA_TARBALL.is_file(), reason="Debian libcgal-demo not installed")
def test_cli_paper_figure(tmp_path, capsys):
    from flatserve.cli import main

    out = tmp_path / "fig"
    assert main(["lightfield", "paper-figure", "--out", str(out), "--n", "30", "--width", "16",
                 "--no-baselines"]) == 0
    res = json.loads((out / "results.json").read_text())
    assert res["samples"] == 900 and set(res["wins"]) == {"field"}
    assert "winner" in capsys.readouterr().out
    assert main(["lightfield", "paper-figure", "--out", str(out), "--n", "1"]) == 2


@pytest.mark.parametrize("cam", [Camera(width=20, height=14, supersample=4, focal=4),
                                 Camera.orbit(70, 20, width=17, height=11, supersample=1, focal=1.2)])
def test_render_serpentine_lookup_matches_scanline_lookup(sampled, cam):
    # render_field locates in serpentine order (odd fine lines reversed); the
    # per-ray answers must be those of a plain scanline lookup, in scanline
    # order, with or without rays outside the chart, for any thread count
    from flatserve import Flats
    from flatserve.lightfield.render import frame_from_rays

    _, _, field, _ = sampled
    o, d = cam.rays()
    cp = field.chart(Flats.from_rays(o, d))
    values = np.full((o.shape[0], field.channels), np.nan)
    inside = np.zeros(o.shape[0], dtype=bool)
    v, ins = field.triangulation.interpolate(cp.points, outside="nan", order="hilbert")
    values[cp.ok], inside[cp.ok] = v, ins
    ref_img, ref_cov = frame_from_rays(cam, values, inside)
    for threads in (None, 1, 2):
        fr = render_field(field, cam, threads=threads)
        np.testing.assert_array_equal(fr.ray_inside, inside)
        np.testing.assert_allclose(fr.image, ref_img, atol=1e-12)
        np.testing.assert_array_equal(fr.covered, ref_cov)
        np.testing.assert_array_equal(fr.chart.ok, cp.ok)
        assert fr.chart.points.tobytes() == cp.points.tobytes()


def test_frame_from_rays_all_valued_is_the_weighted_mean():
    # the all-rays-valued shortcut (plain mean) gives the weighted path's numbers
    from flatserve.lightfield.render import frame_from_rays

    cam = Camera(width=9, height=7, supersample=9)
    rng = np.random.default_rng(3)
    v = rng.random((cam.nrays, 3))
    img, cov = frame_from_rays(cam, v, np.ones(cam.nrays, dtype=bool))
    ref = cam.resolve(v, weights=np.ones(cam.nrays))
    assert img.tobytes() == ref.tobytes() and cov.all()
    v[5, 1] = np.nan  # one ray without a value: its pixel uncovered, the rest unchanged
    img2, cov2 = frame_from_rays(cam, v, np.ones(cam.nrays, dtype=bool))
    assert (~cov2).sum() == 1
    np.testing.assert_array_equal(img2[cov2], img[cov2])
