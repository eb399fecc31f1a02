"""The isometric warps of tangent-simplex charts (flatserve.warp): lines (LineWarp),
k-flats of any k >= 1 (FlatWarp, normal coordinates).

Oracles: finite differences of the chart (its Jacobian in turns and shifts
about each line), the measured structure of the paper's chart that the warp
relies on, round trips through the field file; for FlatWarp the exponential
map built with scipy's matrix exponential (normal coordinates are its
inverse) and the principal angles between nearby flats (the Grassmannian's
own distance).
"""
import io
import math

import numpy as np
import pytest

from flatserve import Basis, Field, Flats
from flatserve.atlas import Atlas
from flatserve.errors import InvalidInputError, SnapshotError
from flatserve.warp import FlatWarp, LineWarp, normal_coordinates

H = 1e-5  # finite-difference step (radians of turn, units of shift)


def _rotate(v, axis, a):
    axis = axis / np.linalg.norm(axis)
    return v * math.cos(a) + np.cross(axis, v) * math.sin(a) + axis * (axis @ v) * (1 - math.cos(a))


def jacobian(field: Field, o, u, unit: float = 1.0) -> np.ndarray:
    """(4, 4): the chart's points' derivatives along two turns of the line about
    its point ``o`` (radians) and two shifts across it (``unit`` lengths)."""
    e1 = np.cross(u, [0.3, 1.0, 0.2])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    # turns about the line's point closest to the chart centre's point
    c = field.basis.center[1]
    o0 = c + (o - c) - ((o - c) @ u) * u
    lines = [(o0, u)] + [(o0, _rotate(u, ax, H)) for ax in (e2, e1)] + \
            [(o0 + H * unit * e, u) for e in (e1, e2)]
    c = field.chart(Flats.from_rays(np.array([l[0] for l in lines]), np.array([l[1] for l in lines])))
    assert c.ok.all()
    return ((c.points[1:] - c.points[0]) / H).T


def cond(J) -> float:
    s = np.linalg.svd(J, compute_uv=False)
    return float(s[0] / s[-1])


def tilted(axis, n1, n2, phi_deg, psi_deg):
    p, q = math.radians(phi_deg), math.radians(psi_deg)
    return math.cos(p) * axis + math.sin(p) * (math.cos(q) * n1 + math.sin(q) * n2)


def chart(axis=(0.0, 0.0, 1.0), point=(0.0, 0.0, 0.0), unit=1.0):
    """The isometric and the paper's single-chart fields of one covering-atlas chart kind
    centred on the line through ``point`` along ``axis``."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    _, V = np.linalg.eigh(np.outer(a, a))
    N = V[:, :2]
    p = np.asarray(point, float)
    p = p - (p @ a) * a
    iso = Atlas(1, 3, a[None, :, None], N[None], p[None], [1.0], unit=unit, inner=12,
                trusted=24, reach=27)
    raw = Atlas(1, 3, a[None, :, None], N[None], p[None], [1.0], unit=unit, inner=12,
                trusted=24, reach=27, isometric=False)
    return iso.chart_field(0), raw.chart_field(0), a, N[:, 0], N[:, 1], p


def test_the_paper_chart_has_the_structure_the_warp_relies_on():
    """Turn part: depends on the direction only, |T| = kT tan(2 phi)/2; shift part
    linear in the offset of lines along the axis (what :mod:`flatserve.warp` says)."""
    _, raw, a, n1, n2, p = chart()
    warp = LineWarp.calibrate(raw.basis)
    rng = np.random.default_rng(0)
    n = 300
    phi, psi = rng.uniform(0, 40, n), rng.uniform(0, 360, n)
    u = np.array([tilted(a, n1, n2, f, s) for f, s in zip(phi, psi)])
    x0 = raw.chart(Flats.from_rays(np.zeros((n, 3)), u)).points
    y0 = (x0 - warp.origin) @ warp.frame.T
    np.testing.assert_allclose(np.linalg.norm(y0[:, :2], axis=1),
                               warp.kT * np.tan(np.radians(2 * phi)) / 2, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(y0[:, 2:], 0, atol=1e-12)
    off = rng.normal(size=(n, 3)) * 2
    x1 = raw.chart(Flats.from_rays(off, u)).points
    y1 = (x1 - warp.origin) @ warp.frame.T
    np.testing.assert_allclose(y1[:, :2], y0[:, :2], atol=1e-12)  # the turn part ignores the offset
    par = raw.chart(Flats.from_rays(off, np.tile(a, (n, 1)))).points
    ys = (par - warp.origin) @ warp.frame.T
    M, res, *_ = np.linalg.lstsq(np.c_[off @ n1, off @ n2], ys[:, 2:], rcond=None)
    assert res.max() < 1e-20  # exactly linear in the offset
    # isotropic: kT times a rotation (or reflection) of the shift plane
    np.testing.assert_allclose(M @ M.T, warp.kT ** 2 * np.eye(2), atol=1e-9)


@pytest.mark.parametrize("axis,point", [((0, 0, 1), (0, 0, 0)), ((1, 2, -2), (0.4, -1, 0.3)),
                                        ((0, 0, -1), (0, 0, 0))])
def test_the_warped_chart_is_nearly_isometric_off_its_centre(axis, point):
    """Finite differences: at lines through the centre's point up to 24 degrees
    off its axis the warped chart's Jacobian has condition <= 1.05 (the paper's
    chart: up to 2.2); at offsets of one unit <= 1.3 (the paper's: up to 4)."""
    iso, raw, a, n1, n2, p = chart(axis, point, unit=0.5)
    worst_iso = {0: 1.0, 1: 1.0}
    worst_raw = {0: 1.0, 1: 1.0}
    for off in (np.zeros(3), 0.5 * n1, 0.5 * n2, 0.35 * (n1 + n2)):
        key = int(np.any(off))
        for phi in (0, 8, 16, 24):
            for psi in (0, 50, 130, 250):
                u = tilted(a, n1, n2, phi, psi)
                Ji = jacobian(iso, p + off, u, unit=0.5)
                Jr = jacobian(raw, p + off, u, unit=0.5)
                worst_iso[key] = max(worst_iso[key], cond(Ji))
                worst_raw[key] = max(worst_raw[key], cond(Jr))
    assert worst_iso[0] < 1.05 and worst_raw[0] > 2.0, (worst_iso, worst_raw)
    assert worst_iso[1] < 1.3 and worst_raw[1] > 3.0, (worst_iso, worst_raw)


def test_the_warp_is_the_identity_to_first_order_at_the_centre():
    iso, raw, a, n1, n2, p = chart((1, 1, 0), (0, 0, 2))
    np.testing.assert_allclose(jacobian(iso, p, a), jacobian(raw, p, a), atol=1e-6)
    c = Flats.from_rays(p[None], a[None])
    np.testing.assert_allclose(iso.chart(c).points, raw.chart(c).points, atol=1e-12)


def test_a_lines_warped_point_does_not_depend_on_its_batch():
    iso, *_ = chart((0.2, 1, 0.5))
    rng = np.random.default_rng(3)
    n = 700
    f = Flats.from_rays(rng.normal(size=(n, 3)), np.array([0.2, 1, 0.5]) + 0.4 * rng.normal(size=(n, 3)))
    whole = iso.chart(f)
    for i in range(0, n, 37):
        one = iso.chart(f.take([i]))
        if whole.ok[i]:
            rank = np.cumsum(whole.ok) - 1
            assert one.points[0].tobytes() == whole.points[rank[i]].tobytes()


def test_the_warp_is_continuous_and_one_to_one_on_the_domain():
    """Neighbouring lines stay neighbours (no fold): along a sweep of directions
    from the centre out to 44 degrees, the warped points move monotonically away."""
    iso, raw, a, n1, n2, p = chart()
    phis = np.linspace(0, 44, 400)
    u = np.array([tilted(a, n1, n2, f, 30) for f in phis])
    x = iso.chart(Flats.from_rays(np.zeros((400, 3)) + p, u)).points
    dist = np.linalg.norm(x - x[0], axis=1)
    assert (np.diff(dist) > 0).all()
    np.testing.assert_allclose(dist, iso.warp.kT * np.radians(phis), rtol=1e-9, atol=1e-12)


def test_a_warped_field_file_round_trips():
    iso, *_ = chart((0, 1, 1), (1, 0, 0))
    rng = np.random.default_rng(4)
    f = Flats.from_rays(rng.normal(size=(400, 3)), np.array([0, 1, 1.0]) + 0.3 * rng.normal(size=(400, 3)))
    iso.add(f, rng.uniform(size=400))
    buf = io.BytesIO()
    iso.write_to(buf)
    back = Field.from_bytes(buf.getvalue())
    assert back.warp is not None and back.warp.to_dict() == iso.warp.to_dict()
    q = Flats.from_rays(rng.normal(size=(200, 3)), np.array([0, 1, 1.0]) + 0.3 * rng.normal(size=(200, 3)))
    a, b = iso.query(q), back.query(q)
    assert a.values.tobytes() == b.values.tobytes()
    # a damaged warp in the metadata is a SnapshotError, not a crash
    data = buf.getvalue().replace(b'"kind": "lines3"', b'"kind": "lines4"')
    with pytest.raises(SnapshotError):
        Field.from_bytes(data)


def test_which_charts_take_which_warp():
    a = Atlas.covering(2, 4)
    # points have no warp; lines a LineWarp, other flats a FlatWarp
    with pytest.raises(InvalidInputError, match="isometric: only charts of flats with k >= 1"):
        Atlas(0, 3, np.zeros((1, 3, 0)), np.eye(3)[None], np.zeros((1, 3)), [1.0],
              isometric=True)
    with pytest.raises(InvalidInputError, match="isometric: expected true or false, got 'yes'"):
        Atlas(2, 4, a.center_A, a.center_N, a.center_r, a.scales, isometric="yes")
    assert isinstance(Atlas(2, 4, a.center_A, a.center_N, a.center_r, a.scales,
                            isometric=True).warps[0], FlatWarp)
    # lines in R^4 may be (opt in: below), R^3's are by default
    assert not Atlas.covering(1, 4).isometric and Atlas.covering(1, 3).isometric
    assert Atlas.covering(1, 4, isometric=True).warps[0].ndim == 6
    with pytest.raises(InvalidInputError, match="warp: only tangent-simplex charts of lines"):
        LineWarp.calibrate(a.bases[0])  # planes
    with pytest.raises(InvalidInputError, match="warp: expected a flatserve.warp.LineWarp"):
        Field(a.bases[0], warp=FlatWarp.calibrate(Atlas.covering(3, 4).bases[0]))
    with pytest.raises(InvalidInputError, match="another chart's basis"):
        Field(a.bases[0], warp=FlatWarp.calibrate(a.bases[1]))
    assert LineWarp.calibrate(Basis.around_axis(axis=2, d=4, scale=1.0)).ndim == 6
    with pytest.raises(InvalidInputError, match="warp"):  # a warp of lines in R^3 on R^4's
        Field(Basis.around_axis(axis=3, d=4, scale=1.0),
              warp=Atlas.covering(1, 3).warps[0])
    with pytest.raises(InvalidInputError, match="kind 'lines3' with 6 coordinates"):
        LineWarp.from_dict({**Atlas.covering(1, 4, isometric=True).warps[0].to_dict(),
                            "kind": "lines3"})


def _jacobian_d(field: Field, o, u) -> np.ndarray:
    """(2(d-1), 2(d-1)): the chart's points' derivatives along d - 1 turns of the
    line about its point ``o`` (radians, towards an orthonormal basis of the normals)
    and d - 1 shifts across it (lengths), for lines in any R^d."""
    d = len(u)
    q, _ = np.linalg.qr(np.c_[u, np.eye(d)])
    es = [q[:, i] * np.sign(q[:, 0] @ u) for i in range(1, d)]
    c = field.basis.center[1]
    o0 = c + (o - c) - ((o - c) @ u) * u
    lines = [(o0, u)] + [(o0, math.cos(H) * u + math.sin(H) * e) for e in es] + \
            [(o0 + H * e, u) for e in es]
    ch = field.chart(Flats.from_rays(np.array([x[0] for x in lines]),
                                     np.array([x[1] for x in lines])))
    assert ch.ok.all()
    return ((ch.points[1:] - ch.points[0]) / H).T


def test_the_warped_chart_of_lines_in_r4_is_nearly_isometric_as_in_r3():
    """Finite differences in R^4 (a 6-D chart): the same figures as the R^3 chart's
    above, turn by turn and shift by shift: at lines through the centre's point up
    to 24 degrees off its axis the warped chart's condition <= 1.05 (the paper's:
    above 2); at offsets of half a unit <= 1.3 (the paper's: above 2)."""
    atlas_iso = Atlas.covering(1, 4, isometric=True)
    atlas_raw = Atlas.covering(1, 4, isometric=False)
    iso, raw = atlas_iso.chart_field(0), atlas_raw.chart_field(0)
    Qc, p = raw.basis.center
    _, V = np.linalg.eigh(np.asarray(Qc))
    a, ns = V[:, 0], V[:, 1:].T
    rng = np.random.default_rng(4)
    worst_iso = {0: 1.0, 1: 1.0}
    worst_raw = {0: 1.0, 1: 1.0}
    for off in (np.zeros(4), 0.5 * ns[0], 0.5 * ns[2], 0.3 * (ns[0] + ns[1] - ns[2])):
        key = int(np.any(off))
        for phi in (0, 8, 16, 24):
            for _ in range(3):
                w = rng.normal(size=3)
                v = (w / np.linalg.norm(w)) @ ns
                u = math.cos(math.radians(phi)) * a + math.sin(math.radians(phi)) * v
                worst_iso[key] = max(worst_iso[key], cond(_jacobian_d(iso, p + off, u)))
                worst_raw[key] = max(worst_raw[key], cond(_jacobian_d(raw, p + off, u)))
    assert worst_iso[0] < 1.05 and worst_raw[0] > 2.0, (worst_iso, worst_raw)
    assert worst_iso[1] < 1.3 and worst_raw[1] > 2.0, (worst_iso, worst_raw)


def test_an_atlas_stored_without_the_choice_restores_unwarped():
    """Atlases stored before charts could be warped come back as they were built."""
    spec = Atlas.covering(1, 3).to_dict()
    assert spec["isometric"] is True
    del spec["isometric"]
    assert not Atlas.from_dict(spec).isometric


def test_charts_far_from_the_origin_calibrate():
    """A chart's rounding grows with its centre's distance from the origin; the
    calibration needs the points, not the field's trust (2.8e-6 at 1000 failed the
    field's 1e-6 before): every chart of centres up to 1e5 away is warped and
    nearly isometric, and a data-driven atlas of flats far away charts them all."""
    rng = np.random.default_rng(7)
    for dist in (1e3, 1e4, 1e5):
        for _ in range(6):
            a = rng.normal(size=3)
            iso, raw, a, n1, n2, p = chart(a, dist * rng.normal(size=3) / math.sqrt(3))
            u = tilted(a, n1, n2, 20, 40)
            assert cond(jacobian(iso, p, u)) < 1.05
    n = 2000
    o = rng.normal(size=(n, 3)) + [1000, 500, 0]
    v = np.array([1.0, 0.2, 0.1]) + 0.3 * rng.normal(size=(n, 3))
    f = Flats.from_rays(o, v)
    from flatserve.atlas_field import AtlasField
    field = AtlasField(Atlas.for_samples(f, unit=1.0))
    assert field.add(f, np.ones(n)).accepted == n


def test_a_stored_atlas_keeps_its_warps(monkeypatch):
    """The atlas spec carries its charts' warps: a field rebuilt from its log gets the
    warps it was built with even if the calibration changes (here: its angle)."""
    import flatserve.warp as W

    at = Atlas.covering(1, 3, oriented=True)
    spec = at.to_dict()
    monkeypatch.setattr(W.LineWarp.calibrate.__func__, "__kwdefaults__",
                        {"calibration_tol": W.CALIBRATION_TOL, "calibration_deg": 30.0})
    fresh = Atlas.covering(1, 3, oriented=True)
    assert any(a.to_dict() != b.to_dict() for a, b in zip(fresh.warps, at.warps))  # it moved
    back = Atlas.from_dict(spec)
    assert [w.to_dict() for w in back.warps] == [w.to_dict() for w in at.warps]


def test_damaged_or_mismatched_warps_are_snapshot_errors(tmp_path):
    from flatserve.atlas_field import AtlasField

    # a warp on a field of planes in R^4, a frame that is not orthonormal
    f4 = Field(Basis.around_axis(axis=3, d=4, scale=1.0))
    buf = io.BytesIO()
    f4.write_to(buf)
    data = buf.getvalue()
    import json
    import struct

    magic, version, mlen = struct.unpack_from("<8sIQ", data)
    meta = json.loads(data[20:20 + mlen])
    meta["warp"] = LineWarp.calibrate(Basis.around_axis(axis=2, scale=1.0)).to_dict()
    for m, v in ((meta, 2), ({**meta, "k": 1, "warp": {**meta["warp"], "frame": (
            2 * np.array(meta["warp"]["frame"])).tolist()}}, 2)):
        blob = json.dumps(m).encode()
        with pytest.raises(SnapshotError):
            Field.from_bytes(struct.pack("<8sIQ", magic, v, len(blob)) + blob + data[20 + mlen:])
    # an atlas file whose chart files have no warp while its atlas is isometric
    iso = AtlasField(Atlas.covering(1, 3))
    rng = np.random.default_rng(2)
    iso.add(Flats.from_rays(rng.normal(size=(300, 3)), rng.normal(size=(300, 3))), np.ones(300))
    iso.save(tmp_path / "a.atlas")
    raw = AtlasField(Atlas.covering(1, 3, isometric=False))
    raw.add(Flats.from_rays(rng.normal(size=(300, 3)), rng.normal(size=(300, 3))), np.ones(300))
    raw.atlas = iso.atlas  # an isometric atlas spec over paper charts: a damaged file
    raw.save(tmp_path / "b.atlas")
    assert AtlasField.load(tmp_path / "a.atlas").nsamples == 300
    with pytest.raises(SnapshotError, match="warp"):
        AtlasField.load(tmp_path / "b.atlas")


# ------------------------------------------------------------------ any (k, d)
KD = [(2, 3), (3, 4), (2, 4), (1, 4), (2, 5)]


def _frame(k, d, rng):
    """A random centre: orthonormal spanning vectors (d, k), normals (d, d-k), a point."""
    q, _ = np.linalg.qr(rng.normal(size=(d, d)))
    return q[:, :k], q[:, k:], rng.normal(size=d)


def _exp(A0, N0, p0, z):
    """The flat of normal coordinates ``z`` about (A0, N0, p0), by scipy's matrix
    exponential of the rotation that turns the centre: (its frame, a point)."""
    from scipy.linalg import expm

    k, dk = A0.shape[1], N0.shape[1]
    H = z[:dk * k].reshape(dk, k)
    G = N0 @ H @ A0.T
    R = expm(G - G.T)
    return R @ A0, p0 + R @ N0 @ z[dk * k:]


@pytest.mark.parametrize("k,d", KD)
def test_normal_coordinates_invert_the_exponential_map(k, d):
    rng = np.random.default_rng(k * 10 + d)
    A0, N0, p0 = _frame(k, d, rng)
    D = (k + 1) * (d - k)
    for _ in range(40):
        z = rng.normal(size=D)
        nt = (d - k) * k
        z[:nt] *= rng.uniform(0, math.radians(44)) / max(np.linalg.svd(
            z[:nt].reshape(d - k, k), compute_uv=False)[0], 1e-12)  # turns below 44 degrees
        z[nt:] *= 3.0
        U, c = _exp(A0, N0, p0, z)
        P = U @ U.T
        r = c - P @ c  # the point closest to the origin: any point of the flat will do
        got = normal_coordinates(P[None], r[None], A0, N0, p0)[0]
        np.testing.assert_allclose(got, z, atol=1e-9)


def _grassmann(U1, U2) -> float:
    """Geodesic distance of two k-subspaces: the root sum of squares of their
    principal angles (arccos of the singular values of U1^T U2)."""
    s = np.clip(np.linalg.svd(U1.T @ U2, compute_uv=False), -1, 1)
    return float(np.sqrt((np.arccos(s) ** 2).sum()))


@pytest.mark.parametrize("k,d", [(2, 3), (3, 4), (2, 4)])
def test_a_warped_chart_measures_turns_as_the_grassmannian_does(k, d):
    """Pairs of nearby flats through the centre's point, up to 40 degrees off it: the
    warped chart's distance over the Grassmannian's (principal angles) stays within
    the curvature's bounds (1 up to r / sin(r)), where the paper's chart stretches
    it 2x and more towards its edge; shifts of one flat are exact."""
    rng = np.random.default_rng(d)
    Qc, rc = Basis.default_center(k, d)
    basis = Basis.tangent_simplex(Qc, rc, k, scale=0.3)
    warp = FlatWarp.calibrate(basis)
    field = Field(basis, warp=warp)
    raw = Field(basis)
    Jinv = np.linalg.inv(warp.J)
    A0, N0 = warp.center_A, warp.center_N
    nt = (d - k) * k
    ratios, raws = [], []
    for _ in range(60):
        z = np.zeros((k + 1) * (d - k))
        z[:nt] = rng.normal(size=nt)
        z[:nt] *= math.radians(rng.uniform(5, 40)) / np.linalg.svd(
            z[:nt].reshape(d - k, k), compute_uv=False)[0]
        step = np.zeros_like(z)
        step[:nt] = 1e-4 * rng.normal(size=nt)
        flats = [_exp(A0, N0, warp.point, z + s) for s in (0 * step, step)]
        dist = _grassmann(flats[0][0], flats[1][0])
        fl = Flats.from_parametric(np.stack([f[0] for f in flats]), np.stack([f[1] for f in flats]))
        y, x = field.chart(fl), raw.chart(fl)
        assert y.ok.all() and x.ok.all()
        ratios.append(np.linalg.norm(Jinv @ (y.points[1] - y.points[0])) / dist)
        raws.append(np.linalg.norm(Jinv @ (x.points[1] - x.points[0])) / dist)
    # normal coordinates overstate a turn across the radius r by r / sin(r) at most
    # (curvature up to 2 here: 1.18 at 40 degrees), never understate one
    assert 1.0 - 1e-3 < min(ratios) and max(ratios) < 1.2, (min(ratios), max(ratios))
    assert max(raws) > 1.8, max(raws)  # what the warp undoes
    # a shift of a turned flat: its warped points move by the shift itself
    z[nt:] = 0
    U, c = _exp(A0, N0, warp.point, z)
    n = np.linalg.qr(np.c_[U, rng.normal(size=(d, d - k))])[0][:, k:][:, 0]
    fl = Flats.from_parametric(np.stack([U, U]), np.stack([c, c + 0.01 * n]))
    y = field.chart(fl).points
    assert abs(np.linalg.norm(Jinv @ (y[1] - y[0])) - 0.01) < 1e-9


@pytest.mark.parametrize("k,d", [(2, 3), (2, 4)])
def test_a_flat_warp_is_the_identity_to_first_order_and_batch_independent(k, d):
    rng = np.random.default_rng(3)
    Qc, rc = Basis.default_center(k, d)
    basis = Basis.tangent_simplex(Qc, rc, k, scale=0.5)
    warp = FlatWarp.calibrate(basis)
    field, raw = Field(basis, warp=warp), Field(basis)
    for eps in (1e-2, 1e-3):
        z = rng.normal(size=(k + 1) * (d - k))
        fl = Flats.from_parametric(*(a[None] for a in _exp(warp.center_A, warp.center_N,
                                                            warp.point, eps * z / np.linalg.norm(z))))
        x, y = raw.chart(fl).points[0], field.chart(fl).points[0]
        # second order: |y - x| / |x - x0| shrinks with the step
        assert np.linalg.norm(y - x) < 2.0 * eps * np.linalg.norm(x - warp.origin)
    A, c = haar_like(rng, 3000, k, d)
    fl = Flats.from_parametric(A, c)
    whole = field.chart(fl)
    ok = np.flatnonzero(whole.ok)
    part = field.chart(fl.take(np.arange(301)))
    assert part.points.tobytes() == whole.points[ok < 301].tobytes()
    for i in ok[:25]:
        alone = field.chart(fl.take([i]))
        assert alone.points.tobytes() == whole.points[ok == i].tobytes()


def haar_like(rng, n, k, d, spread=0.3):
    """Flats near the default centre (the last k axes): frames and points."""
    A = np.linalg.qr(np.eye(d)[:, d - k:] + spread * rng.normal(size=(n, d, k)))[0]
    return A, rng.uniform(-1, 1, (n, d))


def test_a_flat_warped_field_file_and_atlas_round_trip(tmp_path):
    from flatserve.atlas_field import AtlasField

    rng = np.random.default_rng(5)
    Qc, rc = Basis.default_center(2, 4)
    basis = Basis.tangent_simplex(Qc, rc, 2, scale=0.5)
    f = Field(basis, warp=FlatWarp.calibrate(basis))
    A, c = haar_like(rng, 600, 2, 4)
    f.add(Flats.from_parametric(A, c), rng.uniform(size=600))
    buf = io.BytesIO()
    f.write_to(buf)
    back = Field.from_bytes(buf.getvalue())
    assert isinstance(back.warp, FlatWarp) and back.warp.to_dict() == f.warp.to_dict()
    q = Flats.from_parametric(*haar_like(rng, 300, 2, 4))
    assert f.query(q).values.tobytes() == back.query(q).values.tobytes()
    # a damaged warp is a SnapshotError naming it
    data = buf.getvalue().replace(b'"kind": "flats"', b'"kind": "flatz"')
    with pytest.raises(SnapshotError, match="warp"):
        Field.from_bytes(data)
    # an isometric atlas of planes in R^3 keeps its warps through its file
    at = AtlasField(Atlas.covering(2, 3, isometric=True))
    A, c = haar_like(rng, 2000, 2, 3, spread=3.0)
    at.add(Flats.from_parametric(A, c), rng.uniform(size=2000))
    at.save(tmp_path / "p.atlas")
    again = AtlasField.load(tmp_path / "p.atlas")
    assert all(isinstance(w, FlatWarp) for w in again.atlas.warps)
    q = Flats.from_parametric(*haar_like(rng, 500, 2, 3, spread=3.0))
    a, b = at.query(q), again.query(q)
    assert a.inside.mean() > 0.8
    assert a.values.tobytes() == b.values.tobytes()
