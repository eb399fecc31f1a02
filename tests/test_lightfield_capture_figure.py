"""``flatserve lightfield capture-figure``: synthetic captures against the classic baselines."""
from __future__ import annotations

import json

import numpy as np
import pytest

from flatserve.cli import main as cli_main
from flatserve.errors import InvalidInputError
from flatserve.lightfield.capture_figure import RIGS, synthetic_rig
from flatserve.lightfield.rig import rig_center


def test_the_forward_rig_beats_the_two_plane_light_field_on_every_held_out_view(tmp_path):
    """The quick forward-facing rig (half-size images): the field the importer creates
    against the two-plane k nearest rays with k and the focal plane chosen in the
    baseline's favour (docs/capture-results.md has the full-size figures)."""
    assert cli_main(["lightfield", "capture-figure", "--out", str(tmp_path), "--quick",
                     "--rig", "forward"]) == 0
    (res,) = json.loads((tmp_path / "capture-results.json").read_text())
    gains = np.array([v["ours"] - v["baseline"] for v in res["views"]])
    assert res["rig"] == "forward" and len(gains) == 4
    assert np.median(gains) >= 1.0 and gains.min() > 0.0, gains
    assert all(v["coverage"] == 1.0 for v in res["views"])
    # the baseline was swept: its settings are among those tried, and the table and sheet written
    assert res["baseline"]["settings"]["k"] in (1, 2, 4, 6, 8)
    assert (tmp_path / "capture-forward-blocks.png").stat().st_size > 0
    assert "forward" in (tmp_path / "capture-results.md").read_text()


@pytest.mark.parametrize("rig", sorted(RIGS))
def test_the_rigs_look_at_the_scene_and_hold_out_other_cameras(rig):
    cams, held = synthetic_rig(rig, size=0.25)
    np.testing.assert_allclose(rig_center(cams), 0.0, atol=1e-9)
    eyes = np.stack([c.eye for c in cams])
    for h in held:  # held-out cameras are not the rig's
        assert np.linalg.norm(eyes - h.eye, axis=1).min() > 0.05
    with pytest.raises(InvalidInputError) as exc:
        synthetic_rig("ring")
    assert exc.value.argument == "rig"


def test_the_two_plane_baseline_is_idw_of_the_k_nearest_rays():
    """Against a brute-force oracle: all distances in R^4, the k smallest, 1/d^2 weights."""
    from flatserve.lightfield.baselines import IDW_POWER, TwoPlaneNearest, two_plane_coordinates

    rng = np.random.default_rng(5)
    o = np.c_[rng.uniform(-1, 1, (1500, 2)), np.full(1500, -3.0)]
    d = np.c_[rng.uniform(-0.3, 0.3, (1500, 2)), np.ones(1500)]
    v = rng.uniform(size=(1500, 3))
    planes, k = (-3.0, -0.2), 6
    base = TwoPlaneNearest(o, d, v, planes=planes, k=k)
    qo = np.c_[rng.uniform(-1, 1, (200, 2)), np.full(200, -3.0)]
    qd = np.c_[rng.uniform(-0.3, 0.3, (200, 2)), np.ones(200)]
    got, inside = base(qo, qd)
    assert inside.all()
    X, Y = two_plane_coordinates(o, d, planes), two_plane_coordinates(qo, qd, planes)
    D = np.linalg.norm(Y[:, None, :] - X[None, :, :], axis=2)
    nn = np.argsort(D, axis=1)[:, :k]
    w = 1 / np.take_along_axis(D, nn, axis=1) ** IDW_POWER
    np.testing.assert_allclose(got, np.einsum("qk,qkc->qc", w, v[nn]) / w.sum(axis=1, keepdims=True),
                               rtol=1e-10)
    np.testing.assert_array_equal(base(o[:20], d[:20])[0], v[:20])  # a sample gives its own value
    par, ins = base(np.zeros((1, 3)), np.array([[1.0, 0.0, 0.0]]))  # parallel to the planes
    assert np.isnan(par).all() and not ins.any()
    with pytest.raises(InvalidInputError) as exc:
        TwoPlaneNearest(o, d, v, k=0)
    assert exc.value.argument == "k"
