"""flatserve.tiles: one triangulation over tiles (Tile & Merge) against the unsplit one.

The oracle is a :class:`flatserve.Triangulation` of the same points: the tiles'
answers must be its bits (values, inside), its cells (ids as sets) and weights;
every cell a tile holds around an own vertex must be one of its cells.
"""
from __future__ import annotations

import numpy as np
import pytest

from flatserve.errors import InvalidInputError
from flatserve.parallel import ShardPool
from flatserve.tiles import TiledTriangulation, Tiling
from flatserve.triangulation import Triangulation


def _cells(tri: Triangulation) -> set:
    return {tuple(r) for r in np.sort(tri.simplices, axis=1).tolist()}


def _own_cells_exact(tt: TiledTriangulation, whole: set) -> int:
    """Cells of the tiles with an own vertex that are not cells of the whole."""
    bad = 0
    for t, tri in enumerate(tt.tiles):
        if tri.npoints <= tt.ndim:
            continue
        s = tri.simplices
        keep = tt.own(t)[s].any(axis=1)
        g = np.sort(tt.global_ids(t)[s[keep]], axis=1)
        bad += sum(tuple(r) not in whole for r in g.tolist())
    return bad


def _same_answers(tt, tri, q, **kw):
    v0, in0, loc0 = tri.query(q, locate=True, **kw)
    v1, in1, loc1 = tt.query(q, locate=True, **kw)
    assert np.array_equal(in0, in1)
    assert np.array_equal(v0, v1, equal_nan=True), "values differ (bits)"
    inside = in0
    # the same cell and the same weight per vertex (cell order aside)
    a = np.argsort(loc0.ids[inside], axis=1)
    b = np.argsort(loc1.ids[inside], axis=1)
    assert np.array_equal(np.take_along_axis(loc0.ids[inside], a, 1),
                          np.take_along_axis(loc1.ids[inside], b, 1))
    assert np.array_equal(np.take_along_axis(loc0.weights[inside], a, 1),
                          np.take_along_axis(loc1.weights[inside], b, 1))


@pytest.mark.parametrize("D,n,tiles", [(2, 3000, 2), (3, 4000, 4), (4, 3000, 8), (4, 5000, 3)])
def test_answers_are_the_unsplit_triangulations_bits(D, n, tiles):
    rng = np.random.default_rng(D * 100 + tiles)
    pts, vals = rng.normal(size=(n, D)), rng.random((n, 3))
    tri = Triangulation(D)
    tri.insert(pts, vals)
    tt = TiledTriangulation(D, tiles)
    res = tt.insert(pts, vals)
    assert np.array_equal(res.ids, np.arange(n)) and res.n_new == n
    assert tt.npoints == n and sorted(tt.own_counts) == sorted(np.bincount(
        tt.tiling.tile_of(pts), minlength=tiles))
    assert abs(int(tt.own_counts.max()) - int(tt.own_counts.min())) <= tiles
    assert _own_cells_exact(tt, _cells(tri)) == 0
    assert tt.nsimplex == tri.nsimplex
    q = rng.normal(size=(4000, D)) * 1.2  # some outside the hull
    _same_answers(tt, tri, q)
    assert np.array_equal(tt.points, tri.points) and np.array_equal(tt.values, tri.values)


def test_batches_across_tile_borders_and_duplicates():
    rng = np.random.default_rng(7)
    D = 4
    tri, tt = Triangulation(D), TiledTriangulation(D, 4)
    first = rng.normal(size=(2000, D))
    for T in (tri, tt):
        T.insert(first, first[:, :2])
    for step in range(3):  # later batches: wider (boxes grow), some duplicates
        new = rng.normal(size=(1500, D)) * (1.3 + step)
        dup = first[rng.choice(len(first), 200, replace=False)]
        batch = np.vstack([new, dup, new[:50]])
        vals = rng.random((len(batch), 2))
        a, b = tri.insert(batch, vals), tt.insert(batch, vals)
        assert np.array_equal(a.ids, b.ids) and a.n_new == b.n_new
        assert _own_cells_exact(tt, _cells(tri)) == 0
        _same_answers(tt, tri, rng.normal(size=(3000, D)) * 2.0)
        assert np.array_equal(tt.values, tri.values)  # a duplicate's later value won
    assert tt.stats.rounds and all(r >= 1 for r in tt.stats.rounds)


def test_answers_do_not_depend_on_threads_or_order():
    rng = np.random.default_rng(3)
    D = 3
    pts = rng.random((3000, D))
    vals = rng.random((3000, 1))
    tt = TiledTriangulation(D, 4)
    tt.insert(pts, vals)
    q = rng.random((2000, D))
    ref = tt.query(q, threads=1)
    for kw in ({"threads": 2}, {"order": "given"}):
        got = tt.query(q, **kw)
        assert np.array_equal(ref[0], got[0], equal_nan=True) and np.array_equal(ref[1], got[1])


def test_halo_and_forwarding_are_reported():
    rng = np.random.default_rng(5)
    tt = TiledTriangulation(3, 2)
    tt.insert(rng.random((4000, 3)), rng.random((4000, 1)))
    assert (tt.halo > 0).all() and (tt.halo < tt.own_counts).all()
    assert tt.stats.sent == int(tt.halo.sum())
    tt.query(rng.random((5000, 3)))
    assert tt.stats.unresolved == 0
    assert 0 <= tt.stats.forwarded < 500


def test_tiling_cuts_equal_counts_and_routes_every_point():
    rng = np.random.default_rng(11)
    pts = rng.standard_exponential((10_001, 4))
    for T in (1, 2, 5, 8):
        tl = Tiling.split(pts, T)
        counts = np.bincount(tl.tile_of(pts), minlength=T)
        assert tl.ntiles == T and counts.sum() == len(pts)
        assert counts.max() - counts.min() <= T
        far = rng.normal(size=(100, 4)) * 1e6  # any point of R^D has a tile
        assert ((tl.tile_of(far) >= 0) & (tl.tile_of(far) < T)).all()


def test_bad_input_is_named():
    tt = TiledTriangulation(3, 2)
    with pytest.raises(InvalidInputError, match="points"):
        tt.insert(np.zeros((5, 2)))
    with pytest.raises(InvalidInputError, match="tiles"):
        TiledTriangulation(3, 0)
    tt.insert(np.random.default_rng(0).random((50, 3)), np.zeros((50, 1)))
    with pytest.raises(InvalidInputError, match="values"):
        tt.insert(np.random.default_rng(1).random((5, 3)))
    with pytest.raises(InvalidInputError, match="xi"):
        tt.query(np.zeros((3, 4)))


def test_sequential_pool_gives_the_same_tiles(monkeypatch):
    """One thread or several: the same tiles, halos and answers."""
    import flatserve.tiles as tiles_mod

    rng = np.random.default_rng(2)
    pts, vals = rng.random((3000, 3)), rng.random((3000, 1))
    q = rng.random((1000, 3))
    out = []
    for threads in (1, 3):
        monkeypatch.setattr(tiles_mod, "shard_pool", lambda p=ShardPool(threads): p)
        tt = TiledTriangulation(3, 4)
        tt.insert(pts, vals)
        out.append((tt.halo, tt.query(q)[0]))
    assert np.array_equal(out[0][0], out[1][0])
    assert np.array_equal(out[0][1], out[1][1], equal_nan=True)
