"""The paper's Fig. 11 rays of the bunny, for the library tests of big fields."""
from __future__ import annotations

import numpy as np


def fig11_rays(n_side: int, seed: int):
    """The paper's Fig. 11 sampling (``n_side**2`` rays of the bunny), in random order:
    ``(origins, directions, values)``."""
    from flatserve.lightfield.sampling import bunny_scene, sample_scene

    samples, values = sample_scene(bunny_scene(), n_side, seed=seed)
    perm = np.random.default_rng(seed).permutation(len(values))
    return samples.origins[perm], samples.directions[perm], values[perm]
