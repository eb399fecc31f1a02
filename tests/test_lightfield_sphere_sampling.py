"""The 360 degree sampling (eyes all around an object) and its atlas field."""
from __future__ import annotations

import numpy as np
import pytest

from flatserve.errors import InvalidInputError
from flatserve.flats import Flats
from flatserve.lightfield import Scene, box_mesh
from flatserve.lightfield.sampling import (EYE_RADIUS, build_atlas_field, sample_scene_sphere,
                                           sphere_eyes, sphere_samples)

N = 100_000
#: Moments of n uniform unit vectors deviate from E[u] = 0, E[u u^T] = I/3 by
#: O(1/sqrt(n)); this many standard deviations are allowed.
SIGMAS = 6.0
#: A ray aimed at a point strictly inside a box passes within this of it.
BOX_TOL = 1e-9
#: A sample's own value is reproduced at its flat (interpolation at a vertex).
VERTEX_TOL = 1e-9


def test_sphere_eyes_are_uniform_in_direction_and_within_the_radii():
    e = sphere_eyes(N, np.random.default_rng(0))
    r = np.linalg.norm(e, axis=1)
    assert e.shape == (N, 3)
    assert r.min() >= EYE_RADIUS[0] and r.max() <= EYE_RADIUS[1]
    u = e / r[:, None]
    # E[u] = 0 (sd of each coordinate's mean sqrt(1/3n)), E[u u^T] = I/3 (sd about sqrt(4/45n))
    assert np.abs(u.mean(axis=0)).max() < SIGMAS * np.sqrt(1 / (3 * N))
    assert np.abs(u.T @ u / N - np.eye(3) / 3).max() < SIGMAS * np.sqrt(4 / (45 * N))
    # E[u_x^4] = 1/5 on the sphere (sd sqrt(16/225 n)); directions normalised from a cube
    # would give 0.18
    assert np.abs((u ** 4).mean(axis=0) - 0.2).max() < SIGMAS * np.sqrt(16 / (225 * N))
    # distances uniform in [lo, hi]: mean in the middle
    assert abs(r.mean() - sum(EYE_RADIUS) / 2) < SIGMAS * (EYE_RADIUS[1] - EYE_RADIUS[0]) / np.sqrt(12 * N)
    fixed = sphere_eyes(10, np.random.default_rng(1), radius=2.0)
    np.testing.assert_allclose(np.linalg.norm(fixed, axis=1), 2.0)


def test_sphere_samples_aim_each_ray_into_the_box():
    lo, hi = np.array([-0.5, -0.2, -0.3]), np.array([0.4, 0.6, 0.1])
    o, d = sphere_samples(20_000, np.random.default_rng(2), box=(lo, hi))
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)
    # slab test: each ray enters the box ahead of its eye
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - o) / d, (hi - o) / d
    tin = np.nanmax(np.minimum(t1, t2), axis=1)
    tout = np.nanmin(np.maximum(t1, t2), axis=1)
    assert np.all(tout >= np.maximum(tin, 0.0) - BOX_TOL)
    # directions cover the whole sphere: every octant is looked along
    octant = (d > 0) @ np.array([1, 2, 4])
    assert set(np.unique(octant)) == set(range(8))


@pytest.mark.parametrize("kw, member", [
    ({"radius": (3.0, 2.0)}, "radius"),
    ({"radius": (0.0, 2.0)}, "radius"),
    ({"radius": (1.0, 2.0, 3.0)}, "radius"),
    ({"box": ((0.0, 0.0, 0.0), (1.0, -1.0, 1.0))}, "box"),
])
def test_bad_sampling_parameters_are_refused_naming_them(kw, member):
    with pytest.raises(InvalidInputError) as ei:
        sphere_samples(10, np.random.default_rng(0), **kw)
    assert member in str(ei.value)
    with pytest.raises(InvalidInputError):
        sphere_eyes(-1, np.random.default_rng(0))


def test_a_box_scene_sampled_all_around_is_hit_by_every_ray():
    # rays aimed into the mesh's own box (margin 0) all hit a box mesh
    scene = Scene(box_mesh())
    o, d, v = sample_scene_sphere(scene, 5000, seed=3, margin=0.0)
    assert v.shape == (5000, 1)
    assert np.all(v > scene.background)
    # the same seed gives the same rays (the demo's uploads are idempotent across restarts)
    o2, d2, v2 = sample_scene_sphere(scene, 5000, seed=3, margin=0.0)
    assert np.array_equal(o, o2) and np.array_equal(d, d2) and np.array_equal(v, v2)


def test_build_atlas_field_takes_every_ray_and_reproduces_the_samples():
    rng = np.random.default_rng(4)
    o, d = sphere_samples(6000, rng)
    values = np.sin(o[:, :1]) + d[:, 1:2]  # differs between a ray and its reverse
    seen = []
    field, stats = build_atlas_field(o, d, values, chunk=2500, progress=lambda a, b: seen.append((a, b)))
    assert field.atlas.oriented and field.atlas.ncharts == 12
    assert stats.accepted == 6000 and stats.rejected == 0 and field.nsamples == 6000
    assert seen == [(2500, 6000), (5000, 6000), (6000, 6000)]
    res = field.query(Flats.from_rays(o[:500], d[:500]))
    np.testing.assert_allclose(res.values, values[:500], atol=VERTEX_TOL)
