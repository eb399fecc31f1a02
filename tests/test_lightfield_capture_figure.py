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
