"""Rays that an atlas field stores in one chart alone (to change one shard)."""
from __future__ import annotations

import numpy as np

from flatserve import Flats


def rays_in_one_chart(field, rng: np.random.Generator, chart: int, n: int):
    """``(origins, directions)``: ``n`` random rays that ``field`` (an
    :class:`~flatserve.atlas_field.AtlasField`) stores in ``chart`` and in no
    other chart (:meth:`~flatserve.atlas_field.AtlasField.route`)."""
    got_o, got_v = [], []
    while sum(len(o) for o in got_o) < n:
        o, v = rng.uniform(-1, 1, (20 * n, 3)), rng.standard_normal((20 * n, 3))
        rows = field.route(Flats.from_rays(o, v))
        alone = np.zeros(len(o), bool)
        alone[rows[chart]] = True
        for c, rs in enumerate(rows):
            if c != chart:
                alone[rs] = False
        got_o.append(o[alone])
        got_v.append(v[alone])
    return np.concatenate(got_o)[:n], np.concatenate(got_v)[:n]
