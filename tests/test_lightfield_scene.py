"""Meshes, CGAL AABB-tree ray casting and shading (flatserve.lightfield)."""
from __future__ import annotations

import numpy as np
import pytest

from flatserve.errors import InvalidInputError
from flatserve.lightfield import Scene, box_mesh, icosphere, load_mesh, normalize_to_unit_box
from flatserve.lightfield.mesh import CGAL_DATA_TARBALL, Mesh, bunny_path, read_off

#: Exact geometry (box faces are axis planes): hits agree to rounding.
BOX_T_TOL = 1e-12
#: Rays closer than this to a tangent/edge are not classified (rounding).
GRAZE_MARGIN = 1e-6


def random_rays(rng, n, radius=3.0):
    """Rays from a sphere of ``radius`` aimed at random points near the origin."""
    o = rng.normal(size=(n, 3))
    o *= radius / np.linalg.norm(o, axis=1, keepdims=True)
    target = rng.uniform(-1.2, 1.2, size=(n, 3))
    return o, target - o


def slab_hit(o, d, lo, hi):
    """Analytic first hit of rays with an axis-aligned box (slab method)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - o) / d
        t2 = (hi - o) / d
    tmin = np.nanmax(np.minimum(t1, t2), axis=1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=1)
    hit = (tmax >= np.maximum(tmin, 0)) & np.isfinite(tmin)
    return np.where(hit, np.maximum(tmin, 0), np.inf), tmin, tmax


def test_box_hits_match_slab_method():
    rng = np.random.default_rng(1)
    lo, hi = np.array([-0.5, -0.3, -0.2]), np.array([0.4, 0.6, 0.3])
    scene = Scene(box_mesh(lo, hi))
    o, d = random_rays(rng, 20000)
    hits = scene.cast(o, d)
    t_ref, tmin, tmax = slab_hit(o, d, lo, hi)
    clear = np.abs(tmax - tmin) > GRAZE_MARGIN * np.linalg.norm(d, axis=1)  # not grazing an edge
    clear |= ~np.isfinite(t_ref)
    assert np.array_equal(hits.hit[clear], np.isfinite(t_ref)[clear])
    both = clear & hits.hit
    assert both.sum() > 1000
    np.testing.assert_allclose(hits.t[both], t_ref[both], atol=BOX_T_TOL * 10, rtol=BOX_T_TOL)
    # the hit point lies on the box surface
    p = o[both] + hits.t[both, None] * d[both]
    on_face = np.isclose(p, lo, atol=1e-9) | np.isclose(p, hi, atol=1e-9)
    assert on_face.any(axis=1).all()
    assert np.all(hits.face[~hits.hit] == -1) and np.all(np.isinf(hits.t[~hits.hit]))


def test_sphere_hits_between_inscribed_and_circumscribed_spheres():
    rng = np.random.default_rng(2)
    R = 0.8
    mesh = icosphere(3, radius=R)
    # inscribed radius: smallest distance from the centre to a face plane
    n = mesh.face_normals()
    r_in = np.min(np.abs(np.einsum("ij,ij->i", n, mesh.vertices[mesh.faces[:, 0]])))
    scene = Scene(mesh)
    o, d = random_rays(rng, 20000)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    hits = scene.cast(o, d)
    b = np.linalg.norm(np.cross(o, d), axis=1)  # distance of the line from the centre
    along = -np.einsum("ij,ij->i", o, d)  # closest approach parameter (> 0: ahead)
    assert np.all(hits.hit[(b < r_in - GRAZE_MARGIN) & (along > 0)])
    assert not np.any(hits.hit[b > R + GRAZE_MARGIN])
    h = hits.hit & (b < r_in - GRAZE_MARGIN)
    t_outer = along[h] - np.sqrt(R**2 - b[h] ** 2)
    t_inner = along[h] - np.sqrt(r_in**2 - b[h] ** 2)
    assert np.all(hits.t[h] >= t_outer - GRAZE_MARGIN)
    assert np.all(hits.t[h] <= t_inner + GRAZE_MARGIN)


def test_threads_give_the_same_hits():
    rng = np.random.default_rng(3)
    mesh = icosphere(2, radius=0.5)
    o, d = random_rays(rng, 30000)
    one = Scene(mesh, threads=1).cast(o, d)
    two = Scene(mesh, threads=2).cast(o, d)
    assert np.array_equal(one.face, two.face)
    assert np.array_equal(one.t, two.t)


def test_rays_start_at_their_origin():
    scene = Scene(box_mesh())
    # origin inside the box: the first hit is the exit face ahead, at distance 0.5
    hits = scene.cast([[0.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]])
    np.testing.assert_allclose(hits.t, [0.5], atol=BOX_T_TOL)
    # pointing away from the box: miss
    assert not scene.cast([[0.0, 0.0, -2.0]], [[0.0, 0.0, -1.0]]).hit[0]


@pytest.mark.parametrize("channels", [1, 3])
def test_shading_range_background_and_light(channels):
    rng = np.random.default_rng(4)
    bg = np.linspace(0.1, 0.2, channels)
    scene = Scene(icosphere(3, radius=0.5), channels=channels, background=bg, ambient=0.2)
    o, d = random_rays(rng, 5000)
    v = scene.shade(o, d)
    hits = scene.cast(o, d)
    assert v.shape == (5000, channels)
    np.testing.assert_array_equal(v[~hits.hit], np.broadcast_to(bg, (int((~hits.hit).sum()), channels)))
    lo = scene.ambient * scene.albedo
    assert np.all(v[hits.hit] >= lo - 1e-12) and np.all(v[hits.hit] <= scene.albedo + 1e-12)
    # a ray coming from the light's side straight at the centre is fully lit
    L = np.asarray(scene.light) / np.linalg.norm(scene.light)
    lit = scene.shade([3 * L], [-L])
    np.testing.assert_allclose(lit[0], scene.albedo, atol=1e-2)


def test_bad_inputs_name_the_argument():
    scene = Scene(box_mesh())
    with pytest.raises(InvalidInputError) as e:
        scene.cast(np.zeros((3, 2)), np.zeros((3, 2)))
    assert e.value.argument == "origins"
    with pytest.raises(InvalidInputError) as e:
        scene.cast(np.zeros((3, 3)), np.zeros((2, 3)))
    assert e.value.argument == "directions"
    with pytest.raises(InvalidInputError):
        Mesh(np.zeros((3, 3)), [[0, 1, 3]])
    with pytest.raises(InvalidInputError):
        Scene(box_mesh(), channels=2)


def test_off_reader_and_trimesh_formats(tmp_path):
    box = box_mesh([0, 0, 0], [2, 1, 1])
    # OFF written with quads: the reader splits them into fans
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    lines = ["OFF", "# a comment", f"{len(box.vertices)} {len(quads)} 0"]
    lines += [" ".join(map(repr, v)) for v in box.vertices.tolist()]
    lines += ["4 " + " ".join(map(str, q)) for q in quads]
    (tmp_path / "box.off").write_text("\n".join(lines) + "\n")
    m = load_mesh(tmp_path / "box.off")
    assert m.faces.shape == (12, 3)
    np.testing.assert_array_equal(m.vertices, box.vertices)
    trimesh = pytest.importorskip("trimesh")
    for ext in ("ply", "obj"):
        trimesh.Trimesh(box.vertices, box.faces, process=False).export(tmp_path / f"box.{ext}")
        m2 = load_mesh(tmp_path / f"box.{ext}")
        assert m2.faces.shape == (12, 3)
        np.testing.assert_allclose(np.sort(m2.vertices, axis=0), np.sort(box.vertices, axis=0))
    with pytest.raises(InvalidInputError):
        load_mesh(tmp_path / "missing.off")


def test_normalize_to_unit_box():
    rng = np.random.default_rng(5)
    m = Mesh(rng.uniform([3, -7, 2], [5, -2, 3], (50, 3)), rng.integers(0, 50, (30, 3)))
    u = normalize_to_unit_box(m)
    lo, hi = u.bounds
    np.testing.assert_allclose((lo + hi) / 2, 0, atol=1e-12)
    np.testing.assert_allclose((hi - lo).max(), 1.0)
    ratio_before = np.ptp(m.vertices, axis=0) / np.ptp(m.vertices, axis=0).max()
    np.testing.assert_allclose(np.ptp(u.vertices, axis=0), ratio_before)


@pytest.mark.skipif(not CGAL_DATA_TARBALL.is_file(), reason="Debian libcgal-demo not installed")
def test_bunny_is_extracted_into_the_cache(tmp_path):
    p = bunny_path(tmp_path)
    assert p.parent.parent == tmp_path and p.is_file()
    m = read_off(p)
    assert m.vertices.shape[0] == 37706
    assert bunny_path(tmp_path) == p  # second call reuses the file
