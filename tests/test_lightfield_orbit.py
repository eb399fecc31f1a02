"""The 360-degree light field (``flatserve lightfield orbit``) and its two-sphere baseline.

The issue's quality criteria are checked on the run that
``docs/orbit-results.md`` reports (:func:`orbit_figure` with its defaults: the
bunny, 200,000 rays from 448 eyes all around, 24 views of 128^2 pixels, 4
rays per pixel; about two minutes); a small run (20,000 rays from 142 eyes,
32^2 views) feeds the other checks and records, as strict expected failures,
where the criteria are not met with eyes that sparse.  The sampling, the
baseline and the routing are checked against independent oracles.
"""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

import flatserve
from flatserve.errors import InvalidInputError
from flatserve.atlas import Atlas
from flatserve.atlas_field import AtlasField
from flatserve.lightfield import render_field
from flatserve.lightfield.baselines import IDW_POWER, TWO_SPHERE_K, TwoSphere, two_sphere_coordinates
from flatserve.lightfield.camera import ORBIT_EYE_RADIUS, ORBIT_RADIUS, fibonacci_sphere, sphere_samples
from flatserve.lightfield.cli import add_arguments, run
from flatserve.lightfield.mesh import CGAL_DATA_TARBALL
from flatserve.lightfield.orbit import (AZIMUTHS, DEFAULT_SAMPLES, ELEVATIONS, SCENE_UNIT,
                                        VIEW_WIDTH, icosahedral_atlas,
                                        one_chart_atlas, orbit_figure, orbit_views, view_charts)
from flatserve.lightfield.sampling import build_atlas_field, bunny_scene, orbit_samples

pytestmark = pytest.mark.skipif(not CGAL_DATA_TARBALL.is_file(), reason="Debian libcgal-demo not installed")

#: Size of the module's run: small enough for seconds, large enough for a bunny.
N_SAMPLES = 20_000
WIDTH = 32
#: How much worse (dB) a view straddling chart borders may be than the same
#: view inside one chart (the issue's figure).
STRADDLE_TOL_DB = 0.5
#: Numerical tolerance between two computations of the same interpolant.
SAME_TOL = 1e-12


def _run(tmp_path_factory, atlas, n=N_SAMPLES, width=WIDTH):
    out = tmp_path_factory.mktemp(f"orbit-{atlas}-{n}")
    res = orbit_figure(out, n=n, width=width, supersample=4, atlas=atlas, one_chart=True,
                       log=lambda s: None, progress=False)
    return out, res


@pytest.fixture(scope="module")
def run_result(tmp_path_factory):
    """The command with the default covering atlas (32 charts) and unit (1/3), small."""
    return _run(tmp_path_factory, "covering")


@pytest.fixture(scope="module")
def documented_result(tmp_path_factory):
    """The command with all its defaults: the run docs/orbit-results.md reports."""
    return _run(tmp_path_factory, "covering", n=DEFAULT_SAMPLES, width=VIEW_WIDTH)


@pytest.fixture(scope="module")
def bunny_field():
    scene = bunny_scene(1)
    samples, values = orbit_samples(scene, N_SAMPLES, seed=0)
    # the 12 wide charts: some orbit views lie inside one of them (none inside one of
    # the default covering's 32, whose views all straddle)
    field, stats = build_atlas_field(samples.origins, samples.directions, values,
                                     atlas=icosahedral_atlas())
    return scene, samples, values, field, stats


# ------------------------------------------------------------------ sampling


def test_sphere_samples_are_rays_from_eyes_all_around_through_the_ball():
    rng = np.random.default_rng(3)
    s = sphere_samples(10_000, rng)
    eyes = np.unique(s.origins, axis=0)
    assert eyes.shape[0] == 100  # ceil(sqrt(n))
    np.testing.assert_allclose(np.linalg.norm(eyes, axis=1), ORBIT_EYE_RADIUS, rtol=1e-12)
    np.testing.assert_allclose(np.sort(eyes, axis=0), np.sort(ORBIT_EYE_RADIUS * fibonacci_sphere(100), axis=0))
    np.testing.assert_allclose(np.linalg.norm(s.directions, axis=1), 1.0, rtol=1e-12)
    # every ray's line passes within the ball, heading toward it
    dist = np.linalg.norm(np.cross(s.origins, s.directions), axis=1)
    assert dist.max() <= ORBIT_RADIUS * (1 + 1e-12)
    assert (np.einsum("ij,ij->i", s.origins, s.directions) < 0).all()
    np.testing.assert_allclose(np.linalg.norm(s.screen, axis=1), dist, atol=1e-12)
    # the same seed gives the same rays, another seed others
    again = sphere_samples(10_000, np.random.default_rng(3))
    np.testing.assert_array_equal(again.directions, s.directions)
    assert not np.allclose(sphere_samples(10_000, np.random.default_rng(4)).directions, s.directions)


def test_sphere_samples_spread_over_every_direction():
    """No direction is preferred: the 12 charts around the 6 icosahedral axes
    and their negatives (equal cells of the sphere by symmetry) each are the
    nearest chart of 1/12 of the rays, up to 5 standard deviations of a
    binomial count."""
    n = 24_000
    s = sphere_samples(n, np.random.default_rng(0))
    atlas = icosahedral_atlas()
    near = atlas.route(flatserve.Flats.from_rays(s.origins, s.directions), atlas.trusted).nearest
    counts = np.bincount(near, minlength=12)
    p = 1 / 12
    assert np.abs(counts - n * p).max() < 5 * math.sqrt(n * p * (1 - p)), counts


@pytest.mark.parametrize("bad", [dict(n=0), dict(n=10, eyes=11), dict(n=10, eyes=0),
                                 dict(n=10, radius=3.0), dict(n=10, radius=-1.0)])
def test_sphere_samples_refuse_bad_input(bad):
    n = bad.pop("n")
    with pytest.raises(InvalidInputError):
        sphere_samples(n, np.random.default_rng(0), **bad)


# ------------------------------------------------------------------ baseline


def test_two_sphere_coordinates_are_entry_then_exit():
    rng = np.random.default_rng(1)
    o = rng.normal(size=(500, 3)) * 3
    d = rng.normal(size=(500, 3))
    c, R = np.array([0.2, -0.1, 0.3]), 1.3
    x = two_sphere_coordinates(o, d, c, R)
    u = d / np.linalg.norm(d, axis=1, keepdims=True)
    miss = np.linalg.norm(np.cross(o - c, u), axis=1) > R  # the line's distance to the centre
    assert miss.any() and (~miss).any()
    assert np.isnan(x[miss]).all() and np.isfinite(x[~miss]).all()
    h = x[~miss]
    for part in (h[:, :3], h[:, 3:]):
        np.testing.assert_allclose(np.linalg.norm(part - c, axis=1), R, rtol=1e-9)
        # on the line
        np.testing.assert_allclose(np.linalg.norm(np.cross(part - o[~miss], u[~miss]), axis=1), 0, atol=1e-9)
    # entry before exit in the direction of travel; the reverse ray swaps them
    assert (np.einsum("ij,ij->i", h[:, 3:] - h[:, :3], u[~miss]) >= 0).all()
    r = two_sphere_coordinates(o, -d, c, R)[~miss]
    np.testing.assert_allclose(r, np.concatenate([h[:, 3:], h[:, :3]], axis=1), atol=1e-12)


def test_two_sphere_baseline_is_idw_of_the_k_nearest_rays():
    """Against a brute-force oracle: all distances in R^6, the k smallest, 1/d^2 weights."""
    rng = np.random.default_rng(2)
    s = sphere_samples(2000, rng)
    v = rng.uniform(size=(2000, 2))
    base = TwoSphere(s.origins, s.directions, v)
    assert (base.k, base.power) == (TWO_SPHERE_K, IDW_POWER)
    q = sphere_samples(300, np.random.default_rng(9))
    got, inside = base(q.origins, q.directions)
    assert inside.all()
    X = two_sphere_coordinates(s.origins, s.directions)
    Y = two_sphere_coordinates(q.origins, q.directions)
    D = np.linalg.norm(Y[:, None, :] - X[None, :, :], axis=2)
    nn = np.argsort(D, axis=1)[:, :TWO_SPHERE_K]
    w = 1 / np.take_along_axis(D, nn, axis=1) ** IDW_POWER
    want = np.einsum("qk,qkc->qc", w, v[nn]) / w.sum(axis=1, keepdims=True)
    np.testing.assert_allclose(got, want, rtol=1e-10)
    # a sample ray gives its own value; its reverse ray is another ray
    own, _ = base(s.origins[:50], s.directions[:50])
    np.testing.assert_array_equal(own, v[:50])
    back, _ = base(s.origins[:50] + 10 * s.directions[:50], -s.directions[:50])
    assert not np.allclose(back, v[:50])
    # lines that miss the sphere have no value
    far, ins = base(np.array([[5.0, 5.0, 0.0]]), np.array([[0.0, 0.0, 1.0]]))
    assert np.isnan(far).all() and not ins.any()


# ------------------------------------------------------------------ views and routing


def test_views_all_around():
    views = orbit_views(16, 1)
    assert len(views) == AZIMUTHS * len(ELEVATIONS) >= 24
    axes = np.array([cam.rotation[:, 2] for _, cam in views])
    eyes = np.array([cam.eye for _, cam in views])
    np.testing.assert_allclose(np.linalg.norm(eyes, axis=1), 3.0, rtol=1e-12)
    np.testing.assert_allclose(axes, -eyes / 3.0, atol=1e-12)  # every view looks at the object
    az = np.degrees(np.arctan2(eyes[:, 0], -eyes[:, 2])) % 360
    assert len(np.unique(np.round(az, 6))) == AZIMUTHS
    # every ray of every view meets the sampled ball
    for _, cam in views:
        o, d = cam.rays()
        assert np.linalg.norm(np.cross(o, d / np.linalg.norm(d, axis=1, keepdims=True)), axis=1).max() < ORBIT_RADIUS


def test_view_charts_against_the_centres():
    """The routing agrees with the angles to the centres computed here; a
    one-chart atlas on the view's axis holds the whole view in one chart."""
    atlas = Atlas.covering(1, 3, oriented=True)
    for name, cam in orbit_views(12, 1):
        o, d = cam.rays()
        u = d / np.linalg.norm(d, axis=1, keepdims=True)
        ang = np.degrees(np.arccos(np.clip(u @ atlas.center_A[:, :, 0].T, -1, 1)))
        count = (ang < atlas.trusted).sum(axis=1)
        vc = view_charts(atlas, cam)
        assert vc["charts"] == sorted(np.flatnonzero((ang < atlas.trusted).any(axis=0)).tolist()), name
        assert vc["straddles"] == bool((count > 1).any())
        assert vc["blended"] == pytest.approx((count > 1).mean())
        one = one_chart_atlas(atlas, cam.rotation[:, 2])
        assert view_charts(one, cam) == {"charts": [0], "max_per_ray": 1, "blended": 0.0, "straddles": False}


def test_inside_one_chart_the_atlas_answers_as_that_chart(bunny_field):
    """Views whose rays get weight from a single chart render exactly as a
    one-chart atlas with that chart's centre (the same samples)."""
    scene, samples, values, field, _ = bunny_field
    inside = [(n, c) for n, c in orbit_views(WIDTH, 4) if not view_charts(field.atlas, c)["straddles"]]
    assert inside, "some orbit view lies inside one chart"
    for name, cam in inside[:2]:
        c = view_charts(field.atlas, cam)["charts"][0]
        single = AtlasField(one_chart_atlas(field.atlas, field.atlas.center_A[c, :, 0]), 1)
        single.add(flatserve.Flats.from_rays(samples.origins, samples.directions), values)
        a, b = render_field(field, cam), render_field(single, cam)
        assert a.covered.all() and b.covered.all()
        np.testing.assert_allclose(a.image, b.image, atol=SAME_TOL, err_msg=name)


# ------------------------------------------------------------------ the command and its table


def test_orbit_command_writes_sheet_and_table(run_result):
    out, res = run_result
    assert (out / "contact_sheet.png").is_file()
    assert json.loads((out / "results.json").read_text())["samples"] == N_SAMPLES
    md = (out / "results.md").read_text()
    assert len(res["views"]) == AZIMUTHS * len(ELEVATIONS)
    assert res["rejected"] == 0 and res["atlas"]["charts"] == 32
    assert res["atlas"]["unit"] == SCENE_UNIT and res["duplication"] <= 2.0
    assert res["accepted"] == N_SAMPLES
    for r in res["views"]:
        assert r["view"] in md
        p = {m: r["methods"][m]["psnr"] for m in ("ours", "baseline")}
        assert r["winner"] == max(p, key=p.get)
        # every pixel of every view covered, by both methods
        assert r["methods"]["ours"]["coverage"] == 1.0 and r["methods"]["baseline"]["coverage"] == 1.0
        assert not r["one_chart"]["straddles"] and r["one_chart"]["coverage"] == 1.0
    used = {c for r in res["views"] for c in r["routing"]["charts"]}
    assert used <= set(range(32)) and len(used) >= 24


def test_cli_orbit(tmp_path, capsys):
    import argparse

    p = argparse.ArgumentParser()
    add_arguments(p)
    args = p.parse_args(["orbit", "--out", str(tmp_path), "--samples", "0"])
    assert run(args) == 2
    assert "--samples" in capsys.readouterr().err
    with pytest.raises(InvalidInputError, match="scene"):
        orbit_figure(tmp_path, n=10, scene="teapot", log=lambda s: None, progress=False)
    with pytest.raises(InvalidInputError, match="atlas"):
        orbit_figure(tmp_path, n=10, atlas="dense", log=lambda s: None, progress=False)
    for unit in (0.0, -1.0, float("nan"), "mesh"):
        with pytest.raises(InvalidInputError, match="unit"):
            orbit_figure(tmp_path, n=10, unit=unit, log=lambda s: None, progress=False)
    with pytest.raises(InvalidInputError, match="interpolant: expected 'linear' or 'gradient'"):
        orbit_figure(tmp_path, n=10, interpolant="cubic", log=lambda s: None, progress=False)


def test_views_by_the_gradient_interpolant(tmp_path):
    """``--interpolant gradient``: the same field and baseline, ours rendered by the
    gradient interpolant (recorded); its pixels are the field's gradient answers,
    not the linear ones."""
    import argparse

    p = argparse.ArgumentParser()
    add_arguments(p)
    args = p.parse_args(["orbit", "--out", str(tmp_path / "g"), "--samples", "3000",
                         "--width", "8", "--supersample", "1", "--no-one-chart",
                         "--interpolant", "gradient"])
    assert run(args) == 0
    res = {k: orbit_figure(tmp_path / k, n=3000, width=8, supersample=1, one_chart=False,
                           interpolant=k, log=lambda s: None, progress=False)
           for k in ("linear", "gradient")}
    assert res["gradient"]["interpolant"] == "gradient" and res["linear"]["interpolant"] == "linear"
    saved = json.loads((tmp_path / "g" / "results.json").read_text())
    assert [r["methods"]["ours"]["psnr"] for r in saved["views"]] == \
        [r["methods"]["ours"]["psnr"] for r in res["gradient"]["views"]]
    assert "the gradient interpolant" in (tmp_path / "g" / "results.md").read_text()
    ours = {k: [r["methods"]["ours"]["psnr"] for r in v["views"]] for k, v in res.items()}
    assert ours["gradient"] != ours["linear"]
    assert [r["methods"]["baseline"]["psnr"] for r in res["gradient"]["views"]] == \
        [r["methods"]["baseline"]["psnr"] for r in res["linear"]["views"]]


def test_the_unit_from_the_data_is_chosen_by_the_first_chunk(tmp_path):
    """``unit="data"`` (``--unit data``): the field's first chunk of rays chooses
    data_unit of its samples, recorded in the results."""
    from flatserve import Flats
    from flatserve.atlas import data_unit

    n = 3000
    res = orbit_figure(tmp_path, n=n, width=8, supersample=1, unit="data", one_chart=False,
                       log=lambda s: None, progress=False)
    samples, values = orbit_samples(bunny_scene(1), n, seed=0)
    want = data_unit(Flats.from_rays(samples.origins, samples.directions), values)
    assert res["unit_from"] == "data" and res["unit"] == res["atlas"]["unit"] == want
    assert 0.2 < want < 0.45  # the bunny's rays, not the sampling ball's (0.67)


def _lost_views(res) -> list:
    """Views where ours is not above the baseline: (view, ours, baseline) dB."""
    lost = [(r["view"], round(r["methods"]["ours"]["psnr"], 2), round(r["methods"]["baseline"]["psnr"], 2))
            for r in res["views"] if not r["methods"]["ours"]["psnr"] > r["methods"]["baseline"]["psnr"]]
    diff = [r["methods"]["ours"]["psnr"] - r["methods"]["baseline"]["psnr"] for r in res["views"]]
    print(f"ours - baseline {min(diff):+.2f} to {max(diff):+.2f} dB; lost {lost}")
    return lost


def test_ours_beats_the_nearest_rays_baseline_on_every_view(documented_result):
    """The issue's criterion: on the 360-degree bunny, at equal samples (the
    same rays in both), ours has the higher PSNR on every view."""
    _, res = documented_result
    lost = _lost_views(res)
    assert not lost, lost


def _straddle_penalties(res) -> list[tuple[str, float]]:
    """(view, ours - one chart) in dB for the views that straddle chart borders."""
    return [(r["view"], round(r["methods"]["ours"]["psnr"] - r["one_chart"]["psnr"], 2))
            for r in res["views"] if r["routing"]["straddles"]]


def _worse_straddling(res) -> list:
    pen = _straddle_penalties(res)
    assert len(pen) >= len(res["views"]) // 2  # most views straddle: the check has a subject
    worse = [(v, p) for v, p in pen if p < -STRADDLE_TOL_DB]
    print(f"{len(pen)} views straddle; ours - one chart {min(p for _, p in pen):+.2f} to "
          f"{max(p for _, p in pen):+.2f} dB; worse by more than {STRADDLE_TOL_DB}: {worse}")
    return worse


def test_straddling_views_are_no_worse_than_inside_one_chart(documented_result):
    """The issue's criterion: a view whose pixels straddle chart borders is no
    worse (within ``STRADDLE_TOL_DB``) than a view inside one chart at equal
    sample density, with the default covering (32 charts, every direction
    within 22.7 degrees of a centre, weights 0 from 24 degrees).

    Equal density, honestly: the *same* view and the *same* sample rays,
    rendered twice: by the covering atlas (where the atlas's routing blends
    two or more charts at some of the view's rays: it straddles) and by a
    one-chart atlas of the same kind and radii centred on the view's axis
    (every ray of the view answered by that chart alone: inside one chart).
    Comparing different views instead would compare different parts of the
    bunny, and the difference between them (several dB) would drown the
    border's.
    """
    _, res = documented_result
    worse = _worse_straddling(res)
    assert not worse, worse


SPARSE = "with eyes 3x sparser (20,000 rays from 142 eyes, about 17 degrees apart; 32^2 views)"


@pytest.mark.parametrize("failures", [
    pytest.param(_lost_views, id="ours_beats_the_nearest_rays_baseline", marks=pytest.mark.xfail(
        strict=True, reason=f"{SPARSE} ours loses 3 of 24 views, by up to 0.34 dB (before the "
        "isometric charts: 6 of 24, by up to 0.61 dB; with reach 40: 1 of 24, 0.36 dB; "
        "docs/orbit-results.md)")),
    pytest.param(_worse_straddling, id="straddling_views_no_worse_than_one_chart",
                 marks=pytest.mark.xfail(
        strict=True, reason=f"{SPARSE} 5 of 24 views are more than 0.5 dB worse than one chart "
        "centred on the view, down to -2.21 dB (az000_el+00): a chart holds samples only 3 "
        "degrees beyond where it answers, less than the eyes' spacing; with reach 40 "
        "(duplication 3.7, over the 2x budget) every view is within 0.5 dB "
        "(docs/orbit-results.md)")),
])
def test_with_sparse_eyes(run_result, failures):
    """Both criteria above on the sparse-eyes run (the views each one fails)."""
    _, res = run_result
    found = failures(res)
    assert not found, found


@pytest.mark.parametrize("theta", [0.0, 10.0, 20.0, 30.0, 37.4, 40.0])
def test_chart_stretch_off_centre(theta):
    """Why wide charts blur light fields: a chart's embedding (tangent simplex
    around its centre line) stretches a ray's tilt *within the plane of its
    tilt* by ``1 / cos^2(2 theta)`` at ``theta`` from the centre, relative to
    the centre, while a shift of the line stays as at the centre (largest and
    smallest singular values of the Jacobian of ray -> embedded point).
    Measured by finite differences: 14.5x at the 12-chart covering's radius of
    37.4 degrees, 1.8x at the 42-chart covering's 20.8."""
    from flatserve.basis import Basis
    from flatserve.field import Field

    f = Field(Basis.around_axis(axis=2, scale=1.0), channels=1)
    t = math.radians(theta)
    v = np.array([0.0, math.sin(t), math.cos(t)])
    e1, h = np.array([1.0, 0.0, 0.0]), 1e-6
    e2 = np.cross(v, e1)
    O = [np.zeros(3), h * e1, h * e2, np.zeros(3), np.zeros(3)]
    D = [v, v, v, v + h * e1, v + h * e2]
    P = f.chart(flatserve.Flats.from_rays(np.array(O), np.array(D))).points
    sv = np.linalg.svd((P[1:] - P[0]).T / h, compute_uv=False)
    centre = 0.5  # every singular value at theta = 0
    assert sv.max() / centre == pytest.approx(1 / math.cos(2 * t) ** 2, rel=1e-4)
    assert sv.min() / centre == pytest.approx(1.0, rel=1e-4)


# ------------------------------------------------------------------ the second scene's parts


def test_merge_meshes_casts_as_the_nearest_part():
    """A merged mesh's first hit is the nearest of the parts' first hits."""
    from flatserve.lightfield import Scene, box_mesh, icosphere, rotation_about
    from flatserve.lightfield.mesh import merge_meshes

    box, ball = box_mesh(), icosphere(2, 0.3)
    R, t = rotation_about("y", 30.0), np.array([0.2, 0.1, -0.6])
    merged = merge_meshes(box, ball, transforms=[None, (R, t)])
    assert merged.faces.shape[0] == box.faces.shape[0] + ball.faces.shape[0]
    np.testing.assert_allclose(merged.vertices[box.vertices.shape[0]:], ball.vertices @ R.T + t)
    moved = merge_meshes(ball, transforms=[(R, t)])
    s = sphere_samples(2000, np.random.default_rng(5))
    tm = Scene(merged).cast(s.origins, s.directions).t
    tb = Scene(box).cast(s.origins, s.directions).t
    ts = Scene(moved).cast(s.origins, s.directions).t
    np.testing.assert_allclose(tm, np.minimum(tb, ts), rtol=1e-12)
    assert np.isfinite(ts).any() and (ts < tb).any()  # the ball is in front of the box for some rays
    with pytest.raises(InvalidInputError, match="transforms"):
        merge_meshes(box, ball, transforms=[None])


def test_checker_texture_shades_by_the_hit_point():
    """A textured scene's value is the untextured scene's with the checker's
    albedo at the hit point (cells of ``period``, parity of the cell sum)."""
    from flatserve.lightfield import Scene, icosphere
    from flatserve.lightfield.scene import Checker

    mesh = icosphere(3, 0.45)
    chk = Checker(period=0.1, low=0.2, high=0.8)
    s = sphere_samples(3000, np.random.default_rng(6))
    textured = Scene(mesh, texture=chk).shade(s.origins, s.directions)
    plain = Scene(mesh, albedo=1.0).shade(s.origins, s.directions)
    hits = Scene(mesh).cast(s.origins, s.directions)
    h = hits.hit
    p = s.origins[h] + hits.t[h, None] * s.directions[h]
    parity = np.floor(p / 0.1).astype(int).sum(axis=1) % 2
    want = plain[h, 0] * np.where(parity == 0, 0.8, 0.2)
    np.testing.assert_allclose(textured[h, 0], want, rtol=1e-12)
    assert (parity == 0).any() and (parity == 1).any()
    np.testing.assert_array_equal(textured[~h], 0.0)


def test_cli_orbit_with_the_papers_charts(tmp_path):
    """``--paper-charts``: the atlas and the one-chart comparison both use the
    paper's charts (no warp), and the table says so."""
    import argparse

    p = argparse.ArgumentParser()
    add_arguments(p)
    args = p.parse_args(["orbit", "--out", str(tmp_path), "--samples", "3000", "--width", "8",
                         "--supersample", "1", "--paper-charts", "--reach", "31"])
    assert run(args) == 0
    res = json.loads((tmp_path / "results.json").read_text())
    assert res["isometric"] is False and res["atlas"]["reach"] == 31.0
    bad = p.parse_args(["orbit", "--out", str(tmp_path), "--samples", "30", "--reach", "20"])
    assert run(bad) == 2  # below trusted (24): refused, naming reach
    assert "paper charts" in (tmp_path / "results.md").read_text()
    at = Atlas.covering(1, 3, oriented=True, isometric=False)
    assert not one_chart_atlas(at, [0, 0, 1]).isometric
    assert one_chart_atlas(Atlas.covering(1, 3, oriented=True), [0, 0, 1]).isometric
