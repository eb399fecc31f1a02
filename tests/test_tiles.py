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
from flatserve.tiles import TiledTriangulation, Tiling, spread
from flatserve.triangulation import Triangulation
from tests.harness.cells import assert_same_cells
from tests.harness.fig11 import fig11_rays


def _cells(tri: Triangulation) -> set:
    return {tuple(r) for r in np.sort(tri.simplices, axis=1).tolist()}


def _own_cells_exact(tt: TiledTriangulation, whole: set) -> int:
    """Cells of the tiles with an own vertex that are not cells of the whole."""
    bad = 0
    for t, tile in enumerate(tt.tiles):
        tri = tile.tri
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
    assert_same_cells(loc0.ids, loc0.weights, loc1.ids, loc1.weights, in0)


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


def test_inserts_in_a_row_share_one_exchange():
    """Inserts leave the exchange pending; the first read runs it once for all of
    them, and the tiles are then exact as if each insert had been settled."""
    rng = np.random.default_rng(11)
    D = 4
    tri, tt, each = Triangulation(D), TiledTriangulation(D, 3), TiledTriangulation(D, 3)
    first = rng.normal(size=(1500, D))
    batches = [first, rng.normal(size=(1500, D)) * 1.6,  # wider: the boxes grow
               np.vstack([rng.normal(size=(1500, D)) * 2.2, first[:300]])]  # duplicates
    for b in batches:
        vals = rng.random((len(b), 2))
        a, c, e = tri.insert(b, vals), tt.insert(b, vals), each.insert(b, vals)
        assert np.array_equal(a.ids, c.ids) and np.array_equal(a.ids, e.ids)
        each.settle()
        assert each.settled
    assert not tt.settled and tt.stats.rounds == []
    again = TiledTriangulation(D, 3)
    for b in batches:  # settle=True: each insert with its exchange
        again.insert(b, np.zeros((len(b), 2)), settle=True)
        assert again.settled
    assert len(again.stats.rounds) == 3
    q = rng.normal(size=(3000, D)) * 2.0
    assert tt.query(q, blocking=False) is None  # it would have to run the exchange
    _same_answers(tt, tri, q)  # a query settles first
    assert tt.settled and len(tt.stats.rounds) == 1 and len(each.stats.rounds) == 3
    assert _own_cells_exact(tt, _cells(tri)) == 0 and tt.nsimplex == tri.nsimplex
    assert np.array_equal(tt.values, tri.values)  # the duplicates' later values won
    assert (tt.star_halo() == each.star_halo()).all()  # the same stars, either way


def test_a_failed_exchange_is_never_answered_from(monkeypatch):
    """An exchange that raises leaves the tiles inexact: every later use raises
    (its owner rebuilds), none answers from them."""
    rng = np.random.default_rng(13)
    tt = TiledTriangulation(3, 2)
    tt.insert(rng.normal(size=(800, 3)), rng.random((800, 1)))

    def fail(*a, **k):
        raise MemoryError("no room for the halo")

    monkeypatch.setattr(tt, "_exchange", fail)
    with pytest.raises(MemoryError):
        tt.settle()
    monkeypatch.undo()
    for use in (lambda: tt.query(rng.normal(size=(5, 3))), tt.settle, lambda: tt.nsimplex,
                lambda: tt.insert(rng.normal(size=(5, 3)), np.zeros((5, 1)))):
        with pytest.raises(RuntimeError, match="exchange failed.*MemoryError"):
            use()
    assert "TiledTriangulation" in repr(tt)
    now = TiledTriangulation(3, 2)  # settle=True: the insert runs the exchange, and fails
    monkeypatch.setattr(now, "_exchange", fail)
    with pytest.raises(MemoryError):
        now.insert(rng.normal(size=(800, 3)), rng.random((800, 1)), settle=True)


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
    assert tt.stats.sent == int(tt.halo.sum()) + tt.stats.left_out
    assert tt.stats.left_out > 0  # (points sent that are in no star of the receiver's)
    assert (tt.halo >= tt.star_halo()).all()
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


def test_tiling_cuts_the_axis_of_the_widest_bulk_not_of_the_farthest_point():
    """The extent of embedded coordinates is set by a few far points; the cut goes
    across the axis whose middle half is widest (less halo: docs/scaling.md)."""
    rng = np.random.default_rng(12)
    pts = rng.random((2000, 3)) * [1.0, 10.0, 3.0]
    pts[0, 0] = 1e7  # one point far out on axis 0: the widest extent
    tl = Tiling.split(pts, 2)
    assert tl.axis[0] == 1
    assert np.array_equal(spread(pts).argsort(), [0, 2, 1])
    same = np.zeros((100, 2))
    same[:3] = [[5.0, 1.0], [-5.0, 2.0], [1.0, 0.0]]  # every interquartile range 0
    assert Tiling.split(same, 2).axis[0] == 0  # the extent decides
    tied = np.column_stack([rng.random(1000) * 10, rng.random(1000) * 4])
    tied[:400, 0] = 5.0  # the widest bulk, 40 % of it at its median
    tl = Tiling.split(tied, 2)
    assert tl.axis[0] == 1 and np.bincount(tl.tile_of(tied)).tolist() == [500, 500]


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


def test_auto_tiles_follow_the_points_and_the_threads(monkeypatch):
    """``tiles="auto"``: one tile while small, then one per thread of the pool (cut
    again from every point), the unsplit answers throughout; kept in a field file."""
    import flatserve.tiles as tiles_mod
    from flatserve import Field, Flats
    from flatserve.basis import Basis

    monkeypatch.setattr(tiles_mod, "AUTO_MIN_SAMPLES", 2000)
    monkeypatch.setattr(tiles_mod, "shard_pool", lambda p=ShardPool(3): p)
    assert [tiles_mod.auto_tiles(n) for n in (1999, 2000, 2999, 3000, 10**6)] == [1, 2, 2, 3, 3]
    assert tiles_mod.auto_tiles(10**9, threads=64) == tiles_mod.AUTO_MAX_TILES
    rng = np.random.default_rng(12)
    D = 4
    tri, tt = Triangulation(D), TiledTriangulation(D, "auto")
    # 1500, 2200 (2 tiles: twice as many), 3100 (3 wanted: no cut before the points
    # double), 4600 points
    for n, want in ((1500, 1), (700, 2), (900, 2), (1500, 3)):
        b = rng.normal(size=(n, D))
        v = rng.random((n, 1))
        assert np.array_equal(tri.insert(b, v).ids, tt.insert(b, v).ids)
        assert tt.ntiles == want and tt.auto
        _same_answers(tt, tri, rng.normal(size=(2000, D)) * 1.5)
        assert _own_cells_exact(tt, _cells(tri)) == 0
    assert tt.stats.retiled == 2
    with pytest.raises(InvalidInputError, match="auto"):
        TiledTriangulation(D, "many")
    o, d, v = fig11_rays(60, seed=3)  # 3,600 rays at once: 3 tiles
    f = Field(Basis.around_axis(axis=2, scale=0.01), channels=1, tiles="auto")
    f.add(Flats.from_rays(o, d), v)
    assert f.triangulation.ntiles == 3 and f.triangulation.stats.retiled == 0  # cut at once
    back = Field.from_bytes(f.to_bytes())
    assert back.tiles == "auto" and back.triangulation.ntiles == 3 and back.triangulation.auto
    q = Flats.from_rays(o[:500] + 0.01, d[:500])
    assert np.array_equal(back.query(q).values, f.query(q).values, equal_nan=True)
    with pytest.raises(InvalidInputError, match="tiles"):
        Field(Basis.around_axis(), tiles="some")


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


def test_unequal_tiles_are_cut_again():
    """Batches that sweep the square from a corner: the first cut is made for the
    first corner; once the points have doubled and a tile holds more than its
    share, the tiles are cut again, with the same ids and answers."""
    rng = np.random.default_rng(4)
    pts = rng.random((8000, 2))
    pts = pts[np.argsort(pts.sum(axis=1))]
    vals = rng.random((8000, 1))
    tri, tt = Triangulation(2), TiledTriangulation(2, 4)
    for i in range(0, 8000, 1000):
        a, b = tri.insert(pts[i:i + 1000], vals[i:i + 1000]), tt.insert(pts[i:i + 1000],
                                                                        vals[i:i + 1000])
        assert np.array_equal(a.ids, b.ids)
    assert tt.stats.retiled >= 2
    counts = tt.own_counts
    assert counts.max() <= 1.5 * 8000 / 4
    _same_answers(tt, tri, rng.random((3000, 2)))


def test_a_fields_chart_in_tiles_answers_as_the_unsplit_field():
    """The Fig. 11 field (one chart) split into 2, 4 and 8 tiles: every query the
    unsplit field's bits, after batches that cross tile borders too; and a tiled
    field's file restores the same answers."""
    from flatserve import Field, Flats
    from flatserve.basis import Basis
    from flatserve.lightfield.camera import paper_samples

    o, d, v = fig11_rays(160, seed=1)  # 25,600 rays
    q = paper_samples(120, np.random.default_rng(9))
    qf = Flats.from_rays(q.origins, q.directions)
    basis = Basis.around_axis(axis=2, scale=0.01)
    whole = Field(basis, channels=1)
    tiled = {T: Field(basis, channels=1, tiles=T) for T in (2, 4, 8)}
    for f in (whole, *tiled.values()):
        for i in range(0, len(o), 8000):  # later batches land across the borders
            f.add(Flats.from_rays(o[i:i + 8000], d[i:i + 8000]), v[i:i + 8000])
    ref = whole.query(qf, return_weights=True)
    assert ref.inside.mean() > 0.5
    for T, f in tiled.items():
        assert f.nsamples == whole.nsamples and f.nsimplex == whole.nsimplex
        got = f.query(qf, return_weights=True)
        assert np.array_equal(got.values, ref.values, equal_nan=True), T
        assert np.array_equal(got.inside, ref.inside) and np.array_equal(got.status, ref.status)
        assert_same_cells(ref.ids, ref.weights, got.ids, got.weights, ref.inside)
        back = Field.from_bytes(f.to_bytes())
        assert back.tiles == T and back.nsamples == f.nsamples
        assert np.array_equal(back.query(qf).values, ref.values, equal_nan=True)
        assert np.array_equal(back.triangulation.halo, f.triangulation.halo)


def test_a_damaged_tiled_field_file_is_refused():
    from flatserve import Field, Flats
    from flatserve.basis import Basis
    from flatserve.errors import SnapshotError

    o, d, v = fig11_rays(40, seed=2)
    f = Field(Basis.around_axis(axis=2, scale=0.01), channels=1, tiles=2)
    f.add(Flats.from_rays(o, d), v)
    data = f.to_bytes()
    for bad in (data[:-7], data + b"\0"):
        with pytest.raises(SnapshotError):
            Field.from_bytes(bad)


def test_the_halo_holds_at_least_the_stars_foreign_vertices():
    rng = np.random.default_rng(8)
    tt = TiledTriangulation(4, 4)
    tt.insert(rng.normal(size=(4000, 4)), np.zeros((4000, 1)))
    star = tt.star_halo()
    assert (star > 0).all() and (star <= tt.halo).all()


def test_the_fig11_field_at_1m_rays_in_2_4_8_tiles():
    """Issue 19's check at full size: the Fig. 11 field of 1,000^2 rays (in random
    order, batches of 100,000 that land across the tiles' borders), split into 2, 4
    and 8 tiles, answers every query of a 250,000-ray sampling with the unsplit
    field's bits."""
    from flatserve import Field, Flats
    from flatserve.basis import Basis
    from flatserve.lightfield.camera import paper_samples
    from flatserve.lightfield.sampling import BASIS_SCALE

    o, d, v = fig11_rays(1000, seed=0)
    q = paper_samples(500, np.random.default_rng(1))
    qf = Flats.from_rays(q.origins, q.directions)
    basis = Basis.around_axis(axis=2, scale=BASIS_SCALE)

    def build(tiles):
        f = Field(basis, channels=1, tiles=tiles)
        for i in range(0, len(o), 100_000):
            f.add(Flats.from_rays(o[i:i + 100_000], d[i:i + 100_000]), v[i:i + 100_000])
        return f

    whole = build(1)
    chart = whole.chart(qf)
    ref = whole.query(chart)
    n, nsimplex = whole.nsamples, whole.nsimplex
    del whole
    assert n > 950_000 and ref.inside.mean() > 0.9
    for tiles in (2, 4, 8):
        f = build(tiles)
        assert f.nsamples == n and f.nsimplex == nsimplex
        got = f.query(chart)
        assert np.array_equal(got.values, ref.values, equal_nan=True), tiles
        assert np.array_equal(got.inside, ref.inside), tiles
        assert f.triangulation.stats.unresolved == 0
        del f


def test_a_tiles_box_stays_in_its_cell_of_the_partition():
    """Heavy-tailed points (as embedded ray coordinates are): a box grown with room
    to spare never reaches over the cut into another tile's cell."""
    rng = np.random.default_rng(12)
    pts = rng.standard_cauchy((6000, 3))
    tt = TiledTriangulation(3, 2)
    for i in range(0, 6000, 1000):
        tt.insert(pts[i:i + 1000], np.zeros((1000, 1)))
    lo, hi = tt.tiling.boxes()
    blo, bhi = tt.boxes
    assert (blo >= lo).all() and (bhi <= hi).all()
    own = [tt.tiling.tile_of(pts) == t for t in range(2)]
    for t in range(2):
        p = pts[own[t]]
        assert (p >= blo[t]).all() and (p <= bhi[t]).all()
    tri = Triangulation(3)
    tri.insert(pts, np.zeros((6000, 1)))
    _same_answers(tt, tri, rng.standard_cauchy((2000, 3)))


@pytest.mark.parametrize("D", [2, 3, 4])
def test_conflicts_since_a_generation_are_the_seeds_ones(D):
    """The exchange's two ways to the cells an insert made: a walk around its new
    vertices (seeds) and one pass over the cells stamped with their insert
    (since) find the same cells, hence the same vertices per group; every cell
    (neither) finds at least those."""
    rng = np.random.default_rng(D)
    tri = Triangulation(D)
    tri.insert(rng.random((2000, D)))
    g = tri.generation
    tri.insert(rng.random((150, D)))
    tri.insert(rng.random((50, D)))
    assert tri.generation == g + 2
    own = np.zeros(tri.npoints, np.uint8)
    own[::2] = 1
    lo = np.array([[0.0] * D, [0.5] + [0.0] * (D - 1), [0.0] * D])
    hi = np.array([[0.5] + [1.0] * (D - 1), [1.0] * D, [0.2] * D])
    start = np.array([0, 1, 2, 3])
    seeds = tri.conflicts(own, lo, hi, start, seeds=np.arange(2000, 2200))
    since = tri.conflicts(own, lo, hi, start, since=g)
    every = tri.conflicts(own, lo, hi, start)
    assert all(np.array_equal(a, b) for a, b in zip(seeds, since))
    assert all(np.isin(a, b).all() for a, b in zip(since, every))
    assert sum(len(a) for a in since) > 0
    assert all(len(a) == 0 for a in tri.conflicts(own, lo, hi, start, since=tri.generation))
    with pytest.raises(InvalidInputError, match="since: expected a generation in 0..3"):
        tri.conflicts(own, lo, hi, start, since=4)
    with pytest.raises(InvalidInputError, match="seeds, since: give one of them"):
        tri.conflicts(own, lo, hi, start, seeds=[0], since=0)


@pytest.mark.parametrize("D", [2, 3, 4])
def test_conflicts_of_every_cell_are_those_of_a_walk_around_every_vertex(D):
    """Every cell (neither seeds nor since) is a search from the cells holding the
    boxes' centres through the cells whose ball meets a box (then, past a third
    of the cells, a pass over the others): it finds what a walk around every
    vertex finds (every cell once), for points in a cube and heavy-tailed ones,
    boxes inside the hull, across it, beyond it and unbounded."""
    rng = np.random.default_rng(20 + D)
    for heavy in (False, True):
        pts = rng.standard_t(2, (3000, D)) if heavy else rng.random((3000, D))
        tri = Triangulation(D)
        tri.insert(pts)
        own = (pts[:, 0] < np.median(pts[:, 0])).astype(np.uint8)
        mine, other = pts[own == 1], pts[own == 0]
        far = pts.max(axis=0) + 1
        lo = np.stack([mine.min(0), other.min(0), np.quantile(pts, 0.4, axis=0), far])
        hi = np.stack([mine.max(0), other.max(0), np.quantile(pts, 0.45, axis=0), far + 1])
        for rows in ([0, 1, 2, 3], [0, 2, 3]):  # (the other half: past the search's
            start = np.arange(len(rows) + 1)    # budget, the rest in a pass)
            every = tri.conflicts(own, lo[rows], hi[rows], start, skip=0)
            walk = tri.conflicts(own, lo[rows], hi[rows], start, skip=0,
                                 seeds=np.arange(len(pts)))
            assert all(np.array_equal(a, b) for a, b in zip(every, walk))
            assert all(len(a) for a in every[1:])
        open_lo = np.stack([mine.min(0), np.full(D, 0.5), np.full(D, -np.inf)])
        open_hi = np.stack([mine.max(0), np.full(D, np.inf), np.full(D, np.inf)])
        every = tri.conflicts(own, open_lo, open_hi, np.arange(4), skip=0)  # (no centre:
        walk = tri.conflicts(own, open_lo, open_hi, np.arange(4), skip=0,   # a pass)
                             seeds=np.arange(len(pts)))
        assert all(np.array_equal(a, b) for a, b in zip(every, walk))
        assert all(len(a) for a in every[1:])


@pytest.mark.parametrize("D", [2, 3, 4])
def test_insert_neighbours_of_leaves_out_exactly_the_points_no_marked_vertex_neighbours(D):
    """``neighbours_of``: a point is inserted when, inserted alone, it would be a
    neighbour of a marked vertex, else left out (id -1, nothing stored); the
    oracle is a plain insert of each point into a copy."""
    rng = np.random.default_rng(30 + D)
    base = rng.random((400, D))
    mark = (base[:, 0] < 0.5).astype(np.uint8)
    cand = rng.random((60, D)) * [1.6] + [[-0.3] + [0.0] * (D - 1)]
    expect = []
    for p in cand:
        t = Triangulation(D)
        t.insert(base)
        new = t.insert(p[None]).ids[0]
        s = t.simplices
        nb = np.unique(s[(s == new).any(axis=1)])
        expect.append(bool(mark[nb[nb < len(base)]].any()))
    expect = np.array(expect)
    assert expect.any() and not expect.all()
    for p, want in zip(cand, expect):  # one at a time: the same question as the oracle's
        t = Triangulation(D)
        t.insert(base, np.zeros((len(base), 1)))
        g0 = t.generation
        res = t.insert(p[None], np.ones((1, 1)), neighbours_of=mark)
        assert (res.ids[0] >= 0) == want and res.n_new == int(want) and res.n_duplicates == 0
        assert t.npoints == len(base) + int(want)
        assert t.generation == g0 + int(want)  # (nothing held: nothing changed)
    t = Triangulation(D)  # a batch: a point left out would be no neighbour of a
    t.insert(base)  # marked vertex with every point kept (nor with more points)
    res = t.insert(cand, neighbours_of=mark)
    kept = res.ids >= 0
    assert kept.any() and not kept.all()
    assert not kept[~expect].any()
    for p in cand[~kept]:
        u = Triangulation(D)
        u.insert(t.points)
        new = u.insert(p[None]).ids[0]
        s = u.simplices
        nb = np.unique(s[(s == new).any(axis=1)])
        assert not mark[nb[nb < len(base)]].any()
    g0 = t.generation
    again = t.insert(base[:3], neighbours_of=np.zeros(t.npoints, np.uint8))
    assert list(again.ids) == [0, 1, 2] and again.n_duplicates == 3  # duplicates land
    assert t.generation == g0 + 1  # (their values may change: a new generation)
    with pytest.raises(InvalidInputError, match=r"neighbours_of: expected shape \("):
        t.insert(cand[:1], neighbours_of=mark[:5])


def test_tiles_as_snapshot_parts_only_the_changed_ones():
    """A tiled triangulation's parts: one record per tile; a tile that did not change
    is not serialised again; new values on points only one tile holds change that
    tile's part alone; the parts rebuild the same tiles."""
    rng = np.random.default_rng(11)
    tt = TiledTriangulation(3, 3)
    tt.insert(rng.random((3000, 3)), rng.random((3000, 1)))
    first = tt.tile_parts()
    assert len(first) == 3 and all(blob is not None for _, blob in first)
    keys = [k for k, _ in first]
    assert tt.tile_parts(known=keys) == [(k, None) for k in keys]  # nothing changed
    # new values on own points of tile 0 that no other tile holds in its halo
    elsewhere = np.concatenate([tt.global_ids(t) for t in (1, 2)])
    g0 = tt.global_ids(0)
    only = tt.own(0) & ~np.isin(g0, elsewhere)
    assert only.sum() > 100
    tt.insert(tt.tiles[0].tri.points[only][:50], np.full((50, 1), 7.0))
    second = tt.tile_parts(known=keys)
    assert second[1:] == [(k, None) for k in keys[1:]]
    assert second[0][0] != keys[0] and second[0][1] is not None
    stored = {k: blob for k, blob in (*first, second[0])}
    back = TiledTriangulation.from_parts(stored.__getitem__, [k for k, _ in second], 3,
                                         tt.tiling_dict())
    q = rng.random((500, 3))
    assert np.array_equal(back.query(q)[0], tt.query(q)[0], equal_nan=True)
    assert np.array_equal(back.to_bytes(), tt.to_bytes())
    assert back.tile_parts(known=[k for k, _ in second]) == [(k, None) for k, _ in second]


def test_a_tiled_fields_snapshot_in_parts_loads_and_checks_its_parts(tmp_path):
    from flatserve import Field, Flats
    from flatserve.basis import Basis
    from flatserve.contract import load_field
    from flatserve.errors import SnapshotError

    o, d, v = fig11_rays(60, seed=3)
    f = Field(Basis.around_axis(axis=2, scale=0.01), channels=1, tiles=2)
    f.add(Flats.from_rays(o, d), v)
    stage = tmp_path / "parts"
    stage.mkdir()
    keys = f.save_parts(tmp_path / "f.snap", stage)
    assert sorted(p.name for p in stage.iterdir()) == sorted(keys) and len(keys) == 2
    stored = {p.name: p.read_bytes() for p in stage.iterdir()}
    back = load_field(tmp_path / "f.snap", stored.__getitem__)
    q = Flats.from_rays(o[:300] + 0.01, d[:300])
    assert back.tiles == 2 and back.nsamples == f.nsamples
    assert np.array_equal(back.query(q).values, f.query(q).values, equal_nan=True)
    # nothing changed: no part written again
    again = tmp_path / "again"
    again.mkdir()
    assert f.save_parts(tmp_path / "g.snap", again, known=keys) == keys
    assert list(again.iterdir()) == []
    with pytest.raises(SnapshotError, match="no parts were given"):
        load_field(tmp_path / "f.snap")
    bad = dict(stored)
    bad[keys[1]] = bad[keys[1]][:-1] + b"x"
    with pytest.raises(SnapshotError, match="part of tile 1 .* is damaged"):
        load_field(tmp_path / "f.snap", bad.__getitem__)


def test_an_insert_that_raises_the_dimension_makes_every_cell_new():
    """CGAL raises a triangulation's dimension by changing the cells that are there
    in place (they keep their generation): a scan since before it sees every cell,
    as the walk around the new vertex does; and tiles whose points were all on a
    line answer the unsplit triangulation's bits once a point leaves it."""
    for D, first, second in ((2, [[0, 0], [1, 0]], [[0.5, 1]]),
                             (3, [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], [[0.5, 0.5, 1]])):
        tri = Triangulation(D)
        tri.insert(np.asarray(first, float))
        g, n0 = tri.generation, tri.npoints
        tri.insert(np.asarray(second, float))
        own = np.ones(tri.npoints, np.uint8)
        lo, hi, start = np.full((1, D), -10.0), np.full((1, D), 10.0), np.array([0, 1])
        walk = tri.conflicts(own, lo, hi, start, seeds=np.arange(n0, tri.npoints))
        one_pass = tri.conflicts(own, lo, hi, start, since=g)
        assert np.array_equal(walk[0], one_pass[0]) and len(walk[0]) == tri.npoints
    t = np.linspace(0, 1, 40)
    whole, tt = Triangulation(2), TiledTriangulation(2, 2)
    for x in (whole, tt):
        x.insert(np.c_[t, t], np.ones((40, 1)))
        x.insert(np.array([[0.2, 0.25]]), np.full((1, 1), 5.0))
    q = np.array([[0.6, 0.61], [0.8, 0.805], [0.3, 0.33], [0.15, 0.17]])
    v0, in0 = whole.query(q)[:2]
    v1, in1 = tt.query(q)[:2]
    assert in0.all() and np.array_equal(in0, in1)
    assert np.array_equal(v0, v1, equal_nan=True)


def test_within_over_tiles_is_the_unsplit_triangulations():
    rng = np.random.default_rng(71)
    pts = rng.normal(size=(3000, 3))
    tri, tt = Triangulation(3), TiledTriangulation(3, 4)
    tri.insert(pts)
    tt.insert(pts)
    q = rng.normal(size=(2000, 3)) * 1.3
    for radius in (0.05, 0.1, 0.3):
        np.testing.assert_array_equal(tt.within(q, radius), tri.within(q, radius))
    assert 0.1 < tt.within(q, 0.1).mean() < 0.9
    assert tt.within(q.reshape(2, -1, 3), 0.1).shape == (2, 1000)
    with pytest.raises(InvalidInputError, match="radius"):
        tt.within(q, -1)
