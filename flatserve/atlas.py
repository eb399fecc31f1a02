"""Atlases: several charts that together cover every orientation of k-flats.

One tangent-simplex basis (paper Sec. 5.1, Eq. 13-15) charts only the flats
whose direction space is within 45 degrees of its centre's (largest principal
angle; measured, and for lines derived in :mod:`flatserve.basis`: the smallest
eigenvector of ``Q*`` turns by ``phi`` with ``tan(2 phi) = 2 t``).  The paper
says why one chart cannot do (Sec. 1: Grassmannians cannot be covered by one
chart) and leaves the choice of bases open (Sec. 6).  An :class:`Atlas` is a
set of such charts, each with a *domain* given by an angle to its centre:

``inner`` (default 20 deg)
    the chart's blending weight is 1 up to here;
``trusted`` (default 40 deg)
    the blending weight falls smoothly to 0 here (the chart answers queries
    only below it);
``reach`` (default 44 deg)
    samples are inserted into every chart whose centre is closer than this,
    so that a chart's triangulation covers its whole blending domain with
    real samples; below the 45 deg limit (:data:`CHART_LIMIT_DEG`) where the
    coordinates stop round-tripping.

A *relative* atlas (``relative=True``) measures the three radii from the
flat's nearest centre instead of from zero: a flat is stored in every chart
whose centre is less than ``reach`` degrees farther than its nearest centre,
answered by those less than ``trusted`` farther, with blending weight 1 up to
``inner`` farther (defaults :data:`RELATIVE_RADII`); a chart stores nothing
beyond :data:`RELATIVE_LIMIT_DEG` (44) from its centre and its weight falls to
0 at :data:`RELATIVE_ANSWER_DEG` (40), so that with the default radii every
chart answering a query holds every sample within ``(reach - trusted) / 2`` =
4 degrees of it (a flat's angles move by at most its distance).  The nearest
chart always holds a flat and, in a covering atlas (covering radius below 39),
answers it.  Covering atlases are relative from R^4 on
(:data:`RELATIVE_FROM_D`).  A chart then holds its Voronoi region of the
orientations and a seam around it, not a ball as wide as the covering radius
plus margins: a sample of lines or hyperplanes in R^4 is stored about 2.4
times instead of 4.1, of planes in R^4 3.8 times instead of 7.3 (less with a
thinner seam, below; ``docs/costs.md``), and each query is answered near its
charts' centres;
1 % of random queries fall outside the samples' hulls where balls answer all.

A relative atlas may also thin its seam beyond ``dense_reach`` (< ``reach``)
degrees past a flat's nearest centre's angle. With ``seam_spacing`` a chart
stores such a flat only if none of the samples it holds, or that came before
the flat, lies within ``seam_spacing`` of it in the chart's coordinates (at
scale 1): its outer seam is a *net*, as wide as before (the samples' hull
still reaches past the chart's own share, which in 6 dimensions needs the
seam of 14 degrees at ~100 samples a chart) but no denser than the spacing,
so the outer seam's samples stop growing as the field fills. With
``dense_after`` a chart that holds that many samples as their nearest chart
(its *own* samples) stores nothing beyond ``dense_reach`` any more (the
samples it stored while sparse stay and keep its hull wide). Either way which
charts store a flat depends on the samples before it (the chart's samples at
its batch's start and the rows of the batch before it), not on how they were
cut into batches or slices, so a field's log, replayed in order, stores every
sample where it was stored first. The default for planes in R^4
(:data:`DENSE_COVERS`): 59 charts, a net of spacing 1 beyond 7 degrees: 2.41
copies and 98.9 % of random queries answered at 3,000 samples, 2.28 and
100 % at 12,000, where the 74 charts of the plain relative atlas store
3.76-3.78 and answer as many (``docs/costs.md``).

Coverage is a question of orientation only (offsets do not matter: the chart
is equivariant under translations), so a *covering* atlas
(:meth:`Atlas.covering`) chooses centre directions such that every
k-subspace is closer than ``trusted`` to some centre; a *data-driven* atlas
(:meth:`Atlas.for_samples`) places charts where given samples are.

:class:`~flatserve.atlas_field.AtlasField` holds one
:class:`~flatserve.field.Field` per chart and blends their answers; the
angles, frames and coverings underneath are :mod:`flatserve.grassmann`'s.

Example
-------
>>> import numpy as np, flatserve
>>> from flatserve.atlas import Atlas
>>> atlas = Atlas.covering(1, 3)                 # 16 icosahedral axes
>>> atlas.ncharts
16
>>> o, v = np.random.default_rng(0).normal(size=(2, 100, 3))
>>> ro = atlas.route(flatserve.Flats.from_rays(o, v), atlas.reach)
>>> sum(r.size for r in ro.rows) >= 100          # every line in some chart
True
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from . import flats as _flats
from .basis import Basis, select_scale
from .coordinates import OK, ROUNDTRIP_TOL
from .embedding import row_product
from .errors import InvalidInputError
from .field import Field
from .flats import Flats, basis_size
from .grassmann import (bump, complement, cos2_max_angle, cover_frames, cover_radius,
                        covering_radius, max_principal_angle, orientation_frames, use_normals)
from .triangulation import check_radius
from .warp import FlatWarp, LineWarp, warp_from_dict

__all__ = [
    "CHART_LIMIT_DEG",
    "INNER_DEG",
    "TRUSTED_DEG",
    "REACH_DEG",
    "COVER_TRAIN_DEG",
    "COVER_RADII_3D",
    "RELATIVE_RADII",
    "RELATIVE_LIMIT_DEG",
    "RELATIVE_ANSWER_DEG",
    "RELATIVE_FROM_D",
    "DEFAULT_UNIT",
    "object_unit",
    "data_unit",
    "UNIT_RULES",
    "AUTO_UNIT",
    "FIT_MAX_DIM",
    "default_unit_rule",
    "DEFAULT_SCALE",
    "Atlas",
    "Routing",
]

#: A tangent-simplex chart (Sec. 5.1) round-trips every flat whose largest
#: principal angle to its centre is below 45 degrees and none beyond.
CHART_LIMIT_DEG = 45.0
#: Blending weight 1 up to this angle to a chart's centre.
INNER_DEG = 20.0
#: Blending weight 0 from this angle on: a chart answers queries only below it.
#: Measured accuracy falls steeply toward the 45 degree limit (median error
#: 0.018 at 35-40 degrees from the centre, 0.063 at 40-45: docs/design.md,
#: "Atlas fields"), so queries are kept inside 40.
TRUSTED_DEG = 40.0
#: Samples are inserted into every chart whose centre is closer than this
#: (at least ``trusted``: a chart must hold the samples around every query it
#: answers; below the 45 degree limit).
REACH_DEG = 44.0
#: A covering atlas for general (k, d) adds centres until every subspace of a
#: training sample is within this angle of one; the radius measured on a fresh
#: sample is then checked to be below ``trusted``.
COVER_TRAIN_DEG = 35.0
#: Scale of the charts of a covering atlas.  The scale does not change the
#: chart: the weights are ``1/m + u / scale`` with ``u`` fixed per flat, so the
#: embedded points are scaled uniformly about the barycentre and their
#: Delaunay triangulation, hence the interpolant, is the same.  It changes the
#: rounding: measured on Haar-random flats with offsets uniform in
#: [-10^3, 10^3]^d, the largest round-trip residual within ``reach`` of a
#: centre is 2.3e-7 (lines in R^3) to 8.2e-7 (planes in R^5) at the paper's
#: 0.01 and 7e-9 to 3.9e-7 at 1; at offsets 10^4, 0.01 fails 16-28 % of the
#: flats against the absolute ``ROUNDTRIP_TOL`` and 1 fails 0-0.5 %.
DEFAULT_SCALE = 1.0
#: The unit of length of a chart (:class:`Atlas` ``unit``): the shift of a
#: line that its chart weighs as much as a turn of one radian.  1: lengths in
#: the flats' own units (the paper's tangent simplex).
DEFAULT_UNIT = 1.0
#: ``unit=`` of every atlas constructor left out: the rule of the kind,
#: :func:`default_unit_rule` (what the service does with a field's ``unit`` left out).
AUTO_UNIT = "auto"
#: Radii (``inner``, ``trusted``, ``reach``, degrees) of the covering atlases of
#: lines and planes in R^3 (:data:`GEODESIC_AXES`, covering radius 22.69
#: degrees): ``trusted`` 1.3 degrees beyond the covering radius, ``reach`` 3
#: beyond ``trusted``, blending weight 1 up to half of ``trusted``.  The paper's
#: chart stretches a tilt by at most ``1/cos^2(2 trusted)`` = 2.2 there (against
#: 14.5 at the 6 icosahedral axes' 37.4 degrees; the isometric charts of lines,
#: :mod:`flatserve.warp`, undo it); duplication (Haar-random lines) 1.75.
COVER_RADII_3D = (12.0, 24.0, 27.0)
#: A relative atlas (:class:`Atlas` ``relative``) stores and answers a flat in a
#: chart only below this angle to its centre (degrees), whatever its radii.
RELATIVE_LIMIT_DEG = 44.0
#: A chart of a relative atlas answers a flat only below this angle to its
#: centre (its weight falls to 0 over the last :data:`RELATIVE_TAPER_DEG`): the
#: limit less the default seam's half, (14 - 6) / 2, so that it holds every
#: sample within the seam of what it answers.
RELATIVE_ANSWER_DEG = 40.0
RELATIVE_TAPER_DEG = 4.0
#: Rows routed at a time by a relative atlas (its dense angles: rows x charts).
RELATIVE_BLOCK = 16_384
#: Radii (``inner``, ``trusted``, ``reach``, degrees) of a relative covering atlas:
#: angles beyond the nearest centre's (:class:`Atlas` ``relative``).
RELATIVE_RADII = (2.0, 6.0, 14.0)
#: Covering atlases are relative by default from this dimension of the space on:
#: in R^4 a sample of lines or hyperplanes is stored about 2.4 times instead of 4.1,
#: of planes 3.8 instead of 7.3 (2.3-2.4 with :data:`DENSE_COVERS`), built 2-4 times
#: faster, at about the same median error on the queries both answer
#: (``docs/costs.md``), where about 1 % of random queries fall outside the samples'
#: hulls (balls: none); in R^3 they store more (1.96 against 1.75) for the same error.
RELATIVE_FROM_D = 4
#: Relative covering atlases that thin their seam (:class:`Atlas` ``dense_reach``,
#: ``dense_after``, ``seam_spacing``), by kind ``(k, d)``: the greedy cover's
#: ``train_deg`` (fewer, larger charts: more samples each, so their hulls are
#: fuller), ``dense_reach`` (degrees), ``dense_after`` (own samples per chart, or
#: None) and ``seam_spacing`` (chart coordinates at scale 1, or None). Planes in
#: R^4 (``docs/costs.md``, ``benchmarks/dense_seam.py``): 59 charts (covering
#: radius 38.6 degrees, below the relative charts' answer of 40 less its margin),
#: stored 3.42 times with the radii 2/6/14 alone; with a net of spacing 1 beyond
#: 7: 2.41 copies and 98.9 % of random queries answered at 3,000 samples, 2.28
#: and 100 % at 12,000 (74 charts at 2/6/14: 3.76, 98.9 % and 3.78, 100 %; the
#: seam narrowed to 9 after 25 own samples, the default before: 2.85, 97.4 % and
#: 2.44, 99.9 %). Lines and hyperplanes in R^4 are stored 2.4-2.5 times without
#: it. The kind's relative covers take its ``train_deg`` whatever their radii
#: (``train_deg=COVER_TRAIN_DEG``: the 74 charts); the thinner seam is the
#: default only with no radius given.
DENSE_COVERS = {(2, 4): (37.6, 7.0, None, 1.0)}
#: Largest extra angle a covering must keep below ``trusted`` (degrees): the
#: margin the checks of :meth:`Atlas.covering` require.
COVER_MARGIN_DEG = 1.0
#: Training sample of the greedy cover, and the fresh sample that measures it.
COVER_TRAIN_N = 20_000
COVER_CHECK_N = 200_000


def _in_units(deg, name):
    if isinstance(deg, (bool, np.bool_)) or not (
            isinstance(deg, (int, float, np.floating, np.integer)) and math.isfinite(deg)):
        raise InvalidInputError(f"{name}: expected an angle in degrees, got {deg!r}", name)
    return float(deg)


# ---------------------------------------------------------------------------- atlas


class Routing(NamedTuple):
    """Which charts hold which flats (:meth:`Atlas.route`).

    Attributes
    ----------
    rows : list of ndarray (int64)
        Per chart, the flats (row indices, increasing) whose angle to the
        chart's centre is below the routing radius.
    angles : list of ndarray (float64)
        Per chart, those flats' angles to the centre (radians).
    nearest : ndarray, shape (n,), int64, or None
        The chart whose centre is closest to each flat (None when routed
        with ``nearest=False``).
    nearest_angle : ndarray, shape (n,), or None
        That angle (radians).
    """

    rows: list
    angles: list
    nearest: np.ndarray
    nearest_angle: np.ndarray


def _check_dense(dense_reach, dense_after, seam_spacing, relative: bool, trusted: float,
                 reach: float):
    """``(dense_reach, dense_after, seam_spacing)`` as an :class:`Atlas` takes them (all
    None, or ``dense_reach`` with one or both of the others, checked), or an error naming
    the one at fault."""
    if dense_reach is None and dense_after is None and seam_spacing is None:
        return None, None, None
    name = "dense_reach" if dense_reach is not None else \
        "dense_after" if dense_after is not None else "seam_spacing"
    if not relative:
        raise InvalidInputError(f"{name}: only a relative atlas narrows its seam (its radii "
                                f"are measured from each flat's nearest centre)", name)
    if dense_reach is None:
        raise InvalidInputError(f"dense_reach: expected with {name} (a chart thins or drops "
                                "its seam beyond dense_reach)", "dense_reach")
    if dense_after is None and seam_spacing is None:
        raise InvalidInputError("dense_after: expected dense_after or seam_spacing with "
                                "dense_reach (what a chart does beyond dense_reach)",
                                "dense_after")
    dense_reach = _in_units(dense_reach, "dense_reach")
    if not trusted < dense_reach <= reach:
        raise InvalidInputError(
            f"dense_reach: need trusted < dense_reach <= reach (a dense chart still holds a "
            f"seam beyond what it answers), got trusted={trusted:g}, "
            f"dense_reach={dense_reach:g}, reach={reach:g}", "dense_reach")
    if dense_after is not None and (isinstance(dense_after, (bool, np.bool_)) or not isinstance(
            dense_after, (int, np.integer)) or dense_after < 0):
        raise InvalidInputError(f"dense_after: expected a count of samples (an integer >= 0), "
                                f"got {dense_after!r}", "dense_after")
    if seam_spacing is not None and check_radius(seam_spacing, "seam_spacing") <= 0:
        raise InvalidInputError(f"seam_spacing: expected a distance in chart coordinates "
                                f"(finite, > 0), got {seam_spacing!r}", "seam_spacing")
    return (dense_reach, None if dense_after is None else int(dense_after),
            None if seam_spacing is None else float(seam_spacing))


def check_seam(atlas: "Atlas") -> "Atlas":
    """``atlas``, if a relative one has a seam (``reach > trusted``): the neighbours of
    the flats a chart answers, (reach - trusted) / 2 degrees, are in it. Checked
    where a relative atlas is made (:meth:`Atlas.covering`), not where a stored
    one is read (:meth:`Atlas.from_dict`: a field stored before keeps loading).

    Raises
    ------
    InvalidInputError
        Naming ``reach``.
    """
    if atlas.relative and not atlas.reach > atlas.trusted:
        raise InvalidInputError(
            f"reach: a relative atlas needs reach > trusted (its seam, (reach - trusted) / 2 "
            f"degrees, holds the neighbours of the flats a chart answers), got "
            f"trusted={atlas.trusted:g}, reach={atlas.reach:g}", "reach")
    return atlas


class Atlas:
    """Charts (tangent-simplex bases, Sec. 5.1) with angular domains.

    Build with :meth:`covering` (every orientation), :meth:`for_samples`
    (where given samples are) or :meth:`from_centers` (explicit centres,
    checked to cover what they claim).

    Parameters
    ----------
    k, d : int
        k-flats in R^d.
    center_A : array_like, shape (c, d, k)
        Orthonormal spanning frames of the centre flats (for oriented
        atlases the signed centre directions, (c, d, 1)).
    center_N : array_like, shape (c, d, d-k)
        Orthonormal normal frames, orthogonal to ``center_A``.
    center_r : array_like, shape (c, d)
        The centres' closest points to the origin (``Q r = r``, Eq. 3).
    scales : array_like, shape (c,)
        Tangent-simplex scale per chart.
    oriented : bool
        Rays keep their direction (k = 1 only).
    inner, trusted, reach : float
        Degrees, ``0 <= inner < trusted <= reach < 45`` (module docstring); a
        relative atlas made by :meth:`covering` needs ``reach > trusted``
        (:func:`check_seam`).
    unit : float
        The unit of length of the charts (positive, in the flats' units): the
        shift of a flat that a chart weighs as much as a turn of one radian.
        At a chart's centre the tangent simplex moves its flats by ``scale``
        radians of turn and ``scale * unit`` of shift, so a chart of unit
        ``u`` gives a flat the coordinates the unit-1 chart gives the flat
        scaled by ``1/u`` about the origin.  Samples whose values change
        along a shift about as fast as along a turn of ``1/u`` radians are
        interpolated best: for rays of an object, ``u`` about its half-size
        (rays that meet on its surface at depth ``z`` from its centre differ
        by a shift of ``z`` times their turn).  Default ``"auto"``
        (:data:`AUTO_UNIT`): the rule the service takes for a unit left out,
        :func:`default_unit_rule` of the kind (``"fit"`` up to R^4 but for
        points, ``"data"`` beyond); a length such as :data:`DEFAULT_UNIT`
        gives the paper's chart.  None (or ``"data"``):
        chosen from the first samples of a field over the atlas
        (:func:`data_unit`, :meth:`flatserve.atlas_field.AtlasField.settle_unit`);
        ``"fit"``: chosen among multiples of that by held-out validation on
        the first samples' values (:func:`flatserve.atlas_field.fitted_unit`;
        :data:`UNIT_RULES`); until then ``unit`` is :data:`DEFAULT_UNIT` and
        ``unit_from_data`` True.
    relative : bool
        Measure ``inner``, ``trusted`` and ``reach`` from each flat's nearest
        centre's angle (module docstring); default False: from the centre.
    dense_reach : float, optional
        Degrees, ``trusted < dense_reach <= reach``, relative atlases only:
        a chart holding ``dense_after`` own samples stores later flats only
        this far beyond their nearest centre's angle (module docstring).
        Default None: always ``reach``.
    dense_after : int, optional
        Own samples (flats it is the nearest chart of) from which a chart is
        dense and stores nothing beyond ``dense_reach``. 0: from the start (as
        ``reach = dense_reach``). Default None: never.
    seam_spacing : float, optional
        Beyond ``dense_reach`` a chart stores a flat only if none of the
        samples it holds or that came before the flat lies within this
        distance of it in the chart's coordinates at scale 1 (its
        triangulation's points, :attr:`flatserve.field.Field.points`, times
        its scale: :data:`DEFAULT_SCALE`): a net of its outer seam (module
        docstring). There a shift of one ``unit`` weighs as a turn of one
        radian: the spacing thins as measured in a unit matched to the
        offsets' spread (``unit=None`` or ``"fit"``); in a unit far shorter it
        thins little, far longer it thins more and answers fewer queries
        (``docs/costs.md``). Default None: every flat up to ``reach``.
        ``dense_reach`` comes with ``dense_after``, ``seam_spacing`` or both.
    isometric : bool, optional
        Warp each chart's points so that it measures turns and shifts
        everywhere as at its centre (:mod:`flatserve.warp`: lines by
        :class:`~flatserve.warp.LineWarp`, other flats with k >= 1 by
        :class:`~flatserve.warp.FlatWarp`).  Default: True for lines in R^3,
        False otherwise (and for atlases stored before there was a choice:
        :meth:`from_dict`).  Elsewhere it is an opt-in: at 3,000 random lines
        or planes in R^4 the warped atlas answered 78-79 % of the queries
        against 100 % (a warp that contracts the outer turns moves hull facets
        inwards; the samples are sparse in 6 dimensions), at about the same
        median error (``docs/costs.md``).

    Attributes
    ----------
    bases : list of Basis
        One tangent simplex per chart (``m = (k+1)(d-k)+1`` flats each).
    frames : ndarray, shape (c, d, j)
        What angles are measured against (``center_A`` or ``center_N``).
    info : dict
        How the atlas was built (method, covering radius measured, ...).
    """

    def __init__(self, k: int, d: int, center_A, center_N, center_r, scales, *,
                 oriented: bool = False, inner: float = INNER_DEG,
                 trusted: float = TRUSTED_DEG, reach: float = REACH_DEG,
                 unit: float | str | None = AUTO_UNIT, isometric: bool | None = None,
                 relative: bool = False, dense_reach: float | None = None,
                 dense_after: int | None = None, seam_spacing: float | None = None):
        d = int(d)
        k = _flats.check_k(k, d)
        if oriented and k != 1:
            raise InvalidInputError(f"oriented: only lines (k = 1) have an orientation, got "
                                    f"k = {k}", "oriented")
        inner = _in_units(inner, "inner")
        trusted = _in_units(trusted, "trusted")
        reach = _in_units(reach, "reach")
        provisional = _check_rule(unit)
        if isinstance(unit, str) and unit == AUTO_UNIT:
            unit = default_unit_rule(k, d)
        #: the unit is to be chosen from the field's first samples (:attr:`unit_rule`);
        #: until then the charts are built in :data:`DEFAULT_UNIT`
        self.unit_from_data = unit is None or isinstance(unit, str)
        #: how the unit is chosen from the first samples: ``"data"`` (the geometry of
        #: the flats, :func:`data_unit`) or ``"fit"`` (held-out validation on their
        #: values, :func:`flatserve.atlas_field.fitted_unit`); ``"given"`` once it
        #: is a length
        self.unit_rule = ("data" if unit is None else unit) if self.unit_from_data else "given"
        unit = provisional
        if not isinstance(relative, (bool, np.bool_)):
            raise InvalidInputError(f"relative: expected true or false, got {relative!r}",
                                    "relative")
        if not 0 <= inner < trusted <= reach < CHART_LIMIT_DEG:
            # named after the radius that breaks the order (reach: too small or too large)
            bad = "reach" if (0 <= inner < trusted and not trusted <= reach < CHART_LIMIT_DEG) \
                else "trusted"
            raise InvalidInputError(
                f"{bad}: need 0 <= inner < trusted <= reach < {CHART_LIMIT_DEG:g} degrees, got "
                f"inner={inner:g}, trusted={trusted:g}, reach={reach:g}", bad)
        self.dense_reach, self.dense_after, self.seam_spacing = _check_dense(
            dense_reach, dense_after, seam_spacing, relative, trusted, reach)
        r = np.ascontiguousarray(np.asarray(center_r, dtype=np.float64).reshape(-1, d))
        c = r.shape[0]  # (not from center_A: points, k = 0, have empty frames)
        A = np.ascontiguousarray(np.asarray(center_A, dtype=np.float64).reshape(c, d, k))
        N = np.ascontiguousarray(np.asarray(center_N, dtype=np.float64).reshape(c, d, d - k))
        s = np.asarray(scales, dtype=np.float64).reshape(-1)
        if c < 1 or s.shape != (c,):
            raise InvalidInputError(f"scales: expected one scale per centre ({c}), got "
                                    f"{s.shape}", "scales")
        self.k, self.d, self.oriented = k, d, bool(oriented)
        self.inner, self.trusted, self.reach, self.unit = inner, trusted, reach, unit
        self.relative = bool(relative)
        self.center_A, self.center_N, self.center_r, self.scales = A, N, r, s
        self.frames = N if use_normals(k, d) else A
        if isometric is None:
            isometric = (k, d) == (1, 3)
        if not isinstance(isometric, (bool, np.bool_)):
            raise InvalidInputError(f"isometric: expected true or false, got {isometric!r}",
                                    "isometric")
        if isometric and k < 1:
            raise InvalidInputError(f"isometric: only charts of flats with k >= 1 are warped; "
                                    f"a chart of points in R^{d} is isometric already (leave "
                                    f"it out or false)", "isometric")
        self.isometric = bool(isometric)
        self._warps: list | None = None  # calibrated on first use (warps)
        self.bases = []
        for i in range(c):
            Q = N[i] @ N[i].T
            try:
                B = _unit_simplex(Q, r[i], k, float(s[i]), (A[i], N[i]), unit)
            except InvalidInputError as exc:
                raise InvalidInputError(f"centers: chart {i}: {exc}", "centers") from None
            self.bases.append(B)
        self.info: dict = {}

    # ----------------------------------------------------------------- builders
    @classmethod
    def covering(cls, k: int, d: int, *, oriented: bool = False, scale: float = DEFAULT_SCALE,
                 inner: float | None = None, trusted: float | None = None,
                 reach: float | None = None, train_deg: float | None = None,
                 seed: int = 0, check_n: int = COVER_CHECK_N,
                 n_train: int = COVER_TRAIN_N, unit: float | str | None = AUTO_UNIT,
                 isometric: bool | None = None, relative: bool | None = None,
                 dense_reach: float | None = None,
                 dense_after: int | None = None,
                 seam_spacing: float | None = None) -> "Atlas":
        """An atlas whose charts hold every k-flat of R^d, centres through the origin.

        Centres.  A chart is accurate near its centre only: its embedding
        stretches a flat's tilt by ``1/cos^2(2 theta)`` at ``theta`` from the
        centre (4x at 30 degrees, 14.5x at 37.4), so its Delaunay cells join
        ever more distant flats (for lines in R^3 the isometric charts,
        :mod:`flatserve.warp`, undo the stretch; the covering was chosen
        before them, and measured again with them: 24 of 24 bunny views beat
        the baseline); and every sample is stored in each chart
        closer than ``reach`` (memory).  The centres are therefore as many
        as keep the charts narrow while the duplication (charts per sample)
        stays below 2: a covering of radius ``rho`` with ``c`` centres
        stores ``c * vol(reach) / vol(sphere)`` samples per sample, at least
        the covering's density (about 1.2-1.4 for good coverings) times
        ``vol(rho + margins) / vol(rho)``, which grows as ``rho`` shrinks.
        For lines and planes in R^3 (directions on the sphere) the 16 axes of
        :data:`GEODESIC_AXES` (icosahedron vertices and face centres;
        covering radius 22.69 degrees, radii :data:`COVER_RADII_3D`,
        duplication 1.75 for Haar-random lines; the 6 icosahedral axes'
        37.4 degrees stretch 14.5x, 42 subdivided-icosahedron directions
        need 2.0).  Otherwise (the space of k-subspaces grows as
        ``k (d - k)`` dimensions, so narrow charts would need hundreds to
        thousands of centres): a greedy farthest-point cover of ``n_train``
        Haar-random subspaces (seeded), started at the span of the last
        axes, until every one is within ``train_deg`` of a centre, with the
        radii :data:`INNER_DEG`, :data:`TRUSTED_DEG`, :data:`REACH_DEG`.  The covering radius is then
        measured on ``check_n`` fresh Haar-random subspaces and must be below
        ``trusted - COVER_MARGIN_DEG`` (stored in :attr:`info`).  Oriented
        atlases (rays) add every centre's negative.

        Parameters
        ----------
        k, d : int
        oriented : bool
        scale : float
            Tangent-simplex scale of every chart (:data:`DEFAULT_SCALE`).
        inner, trusted, reach : float, optional
            Degrees (module docstring); default :data:`COVER_RADII_3D` for
            d = 3, else :data:`INNER_DEG`, :data:`TRUSTED_DEG`,
            :data:`REACH_DEG`.
        train_deg : float, optional
            Radius of the greedy cover on the training sample. Default
            :data:`COVER_TRAIN_DEG`; a relative atlas of a kind in
            :data:`DENSE_COVERS`, that table's.
        seed : int
        check_n, n_train : int
        unit : float
            The charts' unit of length (:class:`Atlas`; default ``"auto"``, the kind's
            rule; None: from the first samples' geometry).
        isometric : bool, optional
            Warp the charts' points (:class:`Atlas`; default: lines in R^3).
        relative : bool, optional
            Radii beyond each flat's nearest centre (:class:`Atlas`; default
            radii :data:`RELATIVE_RADII`). Default: from d =
            :data:`RELATIVE_FROM_D` on. The covering radius must then be
            below ``RELATIVE_ANSWER_DEG - COVER_MARGIN_DEG``.
        dense_reach, dense_after, seam_spacing : optional
            A relative atlas's thinner or narrower seam (:class:`Atlas`).
            Default: :data:`DENSE_COVERS` for its kind when none of ``inner``,
            ``trusted``, ``reach`` is given, else none (so ``reach=14``, the
            default, keeps the plain seam of 14 degrees).

        Returns
        -------
        Atlas

        Raises
        ------
        InvalidInputError
            ``"trusted"`` when the measured covering radius is not below
            ``trusted - COVER_MARGIN_DEG`` (lower ``train_deg``); ``"train_deg"``
            for a relative atlas whose covering radius is not below its bound.
        """
        d = int(d)
        k = _flats.check_k(k, d)
        if relative is None:
            relative = d >= RELATIVE_FROM_D
        radii = RELATIVE_RADII if relative else COVER_RADII_3D if d == 3 else \
            (INNER_DEG, TRUSTED_DEG, REACH_DEG)
        dense = DENSE_COVERS.get((k, d)) if relative and not oriented else None
        if dense is not None and train_deg is None:
            train_deg = dense[0]
        if dense is not None and (inner, trusted, reach, dense_reach, dense_after,
                                  seam_spacing) == (None,) * 6:
            dense_reach, dense_after, seam_spacing = dense[1:]
        if train_deg is None:
            train_deg = COVER_TRAIN_DEG
        inner, trusted, reach = (radii[i] if v is None else v
                                 for i, v in enumerate((inner, trusted, reach)))
        C = cover_frames(k, d, float(train_deg), int(seed), int(n_train))
        normals = use_normals(k, d)
        comp = np.stack([complement(f) for f in C]) if k and C.shape[2] else None
        if k == 0:
            A, N = np.zeros((1, d, 0)), np.eye(d)[None]
        elif normals:
            A, N = comp, C
        else:
            A, N = C, comp
        if oriented:
            A, N = np.concatenate([A, -A]), np.concatenate([N, N])
        atlas = check_seam(cls(k, d, A, N, np.zeros((A.shape[0], d)),
                               np.full(A.shape[0], float(scale)), oriented=oriented, inner=inner,
                               trusted=trusted, reach=reach, unit=unit, isometric=isometric,
                               relative=relative, dense_reach=dense_reach,
                               dense_after=dense_after, seam_spacing=seam_spacing))
        # the same centres, the same seeded measurement: measured once
        radius = cover_radius(k, d, bool(oriented), float(train_deg), int(seed), int(n_train),
                              int(check_n))
        atlas.info = {"method": "covering", "centres": int(A.shape[0]),
                      "covering_radius_deg": radius, "train_deg": float(train_deg),
                      "check_n": int(check_n), "seed": int(seed)}
        if relative:
            # the nearest chart answers every flat (with a positive weight below
            # RELATIVE_ANSWER_DEG, where it holds the samples around it)
            bound = RELATIVE_ANSWER_DEG - COVER_MARGIN_DEG
            if not radius < bound:
                raise InvalidInputError(
                    f"train_deg: {A.shape[0]} centres leave {k}-subspaces of R^{d} "
                    f"{radius:.2f} degrees from every centre, not below the relative "
                    f"charts' {RELATIVE_ANSWER_DEG:g} - margin = {bound:g}", "train_deg")
        elif not radius < atlas.trusted - COVER_MARGIN_DEG:
            raise InvalidInputError(
                f"trusted: {A.shape[0]} centres leave {k}-subspaces of R^{d} {radius:.2f} "
                f"degrees from every centre, not below trusted - margin = "
                f"{atlas.trusted - COVER_MARGIN_DEG:g}", "trusted")
        return atlas

    @classmethod
    def from_centers(cls, centers: Flats, scales=DEFAULT_SCALE, *, oriented: bool = False,
                     inner: float = INNER_DEG, trusted: float = TRUSTED_DEG,
                     reach: float = REACH_DEG, require_cover: bool = True,
                     check_n: int = COVER_CHECK_N, seed: int = 0,
                     unit: float | str | None = AUTO_UNIT, isometric: bool | None = None) -> "Atlas":
        """An atlas with the given centre flats, checked to cover every orientation.

        Parameters
        ----------
        centers : Flats
            ``c`` k-flats (rays for oriented atlases: their directions are the
            chart orientations).
        scales : float or array_like, shape (c,)
        require_cover : bool
            Measure the covering radius on ``check_n`` Haar-random subspaces
            (oriented: directions) and refuse centres that leave some farther
            than ``trusted`` from every centre.
        unit : float
            The charts' unit of length (:class:`Atlas`; default ``"auto"``, the kind's
            rule; None: from the first samples' geometry).
        isometric : bool, optional
            Warp the charts' points (:class:`Atlas`; default: lines in R^3).

        Raises
        ------
        InvalidInputError
            ``"centers"`` naming the uncovered direction and its angle, or a
            chart whose basis is singular; ``"scales"`` for non-positive
            scales.
        """
        if not isinstance(centers, Flats):
            raise InvalidInputError("centers: expected a flatserve.Flats batch", "centers")
        if oriented and centers.form != "rays":
            raise InvalidInputError(f"centers: an oriented atlas needs rays as centres, got "
                                    f"the form {centers.form!r}", "centers")
        k, d = centers.k, centers.d
        Q, r = centers.quadrics()
        A, N = _flats.frames(Q, k)
        if oriented:
            A = orientation_frames(centers, normals=False)
        s = np.broadcast_to(np.asarray(scales, dtype=np.float64), (centers.n,))
        if not (np.isfinite(s).all() and (s > 0).all()):
            raise InvalidInputError("scales: expected positive numbers", "scales")
        atlas = cls(k, d, A, N, r, s, oriented=oriented, inner=inner, trusted=trusted,
                    reach=reach, unit=unit, isometric=isometric)
        for i, B in enumerate(atlas.bases):
            rep = B.check()
            if not rep.ok:
                raise InvalidInputError(f"centers: chart {i} (scale {s[i]:g}): "
                                        + "; ".join(rep.failures), "centers")
            bad = atlas.probe(i)
            if bad:
                raise InvalidInputError(f"centers: chart {i} (scale {s[i]:g}) does not chart "
                                        f"its domain: {bad}", "centers")
        atlas.info = {"method": "centers", "centres": int(centers.n)}
        if require_cover:
            radius, worst = atlas.covering_radius(check_n, seed=seed, return_worst=True)
            atlas.info.update(covering_radius_deg=radius, check_n=int(check_n))
            if not radius < atlas.trusted:
                raise InvalidInputError(
                    f"centers: {centers.n} centres do not cover every orientation: the "
                    f"direction space spanned by {np.round(worst, 4).tolist()} is "
                    f"{radius:.2f} degrees from every centre (trusted {atlas.trusted:g})",
                    "centers")
        return atlas

    @classmethod
    def for_samples(cls, flats: Flats, *, oriented: bool = False, radius: float = 30.0,
                    fraction: float = 0.99, inner: float = INNER_DEG,
                    trusted: float = TRUSTED_DEG, reach: float = REACH_DEG,
                    max_scale_samples: int = 5000, max_cluster_samples: int = 20_000,
                    seed: int = 0, refine: int = 3, unit: float | str | None = AUTO_UNIT,
                    isometric: bool | None = None) -> "Atlas":
        """A data-driven atlas: charts where the samples' orientations are.

        1. Greedy cover of the samples' direction spaces (largest principal
           angle; oriented: signed directions): the first centre is the
           extrinsic mean (top eigenvectors of the mean projector
           ``mean A A^T``), then the sample farthest from every centre, until
           every sample is within ``radius`` of one.
        2. ``refine`` rounds: each centre moves to the extrinsic mean of the
           samples nearest to it, kept only while every sample stays within
           ``radius``; then a centre is dropped (smallest clusters first)
           whenever the others, refined without it, still hold every sample
           within ``radius``.
        3. Each centre flat passes through the point nearest to its samples
           in the least-squares sense, ``(sum Q_i)^+ sum r_i`` (the extremum of
           ``q*``, Sec. 2.3); its scale is the paper's bisection
           (:func:`flatserve.basis.select_scale`, ``fraction`` of up to
           ``max_scale_samples`` of its samples inside the simplex).

        Parameters
        ----------
        flats : Flats
            The samples (rays for oriented atlases).
        oriented : bool
        radius : float
            Degrees, ``<= trusted``: the clustering radius.
        fraction : float
            Of :func:`~flatserve.basis.select_scale`.
        max_scale_samples, max_cluster_samples : int
            Steps 1-2 run on a seeded subsample of at most
            ``max_cluster_samples``; then the greedy cover continues on all
            samples until each is within ``radius``.  The bisection uses at
            most ``max_scale_samples`` per chart.
        seed, refine : int
        unit : float or {"data", "fit"} or None
            The charts' unit of length (:class:`Atlas`; the bisection
            chooses each chart's scale in this unit, in :data:`DEFAULT_UNIT`
            for a unit chosen from the first samples).
        isometric : bool, optional
            Warp the charts' points (:class:`Atlas`; default: lines in R^3).

        Returns
        -------
        Atlas
            ``info`` has the largest sample angle to its nearest centre and
            the samples per chart.
        """
        if not isinstance(flats, Flats):
            raise InvalidInputError(f"flats: expected a flatserve.Flats batch, got "
                                    f"{type(flats).__name__}", "flats")
        if flats.n < 1:
            raise InvalidInputError("flats: expected at least one sample", "flats")
        provisional = _check_rule(unit)  # the scales' unit until a rule chooses
        radius = _in_units(radius, "radius")
        if not 0 < radius <= trusted:
            raise InvalidInputError(f"radius: expected 0 < radius <= trusted = {trusted:g}, "
                                    f"got {radius:g}", "radius")
        k, d = flats.k, flats.d
        if oriented:
            _require_rays(flats, True)
        rad = math.radians(radius)
        F_all = orientation_frames(flats, normals=False if oriented else None)
        rng = np.random.default_rng(seed)
        F = F_all if flats.n <= max_cluster_samples else F_all[
            np.sort(rng.choice(flats.n, max_cluster_samples, replace=False))]
        j = F.shape[2]
        if oriented:
            def dist(C):
                return np.arccos(np.clip(F[:, :, 0] @ C[:, 0], -1.0, 1.0))

            def mean(rows):
                v = F[rows, :, 0].sum(axis=0)
                nv = np.linalg.norm(v)
                return (v / nv)[:, None] if nv > 0 else F[rows[0]]
        else:
            def dist(C):
                return np.arccos(np.sqrt(cos2_max_angle(C, F)))

            def mean(rows):
                P = np.einsum("ndj,nej->de", F[rows], F[rows]) / len(rows)
                return np.linalg.eigh(P)[1][:, d - j:]
        if j == 0:
            C = [np.zeros((d, 0))]
        else:
            C = [mean(np.arange(flats.n))]
            best = dist(C[0])
            while best.max() >= rad:
                i = int(np.argmax(best))
                C.append(F[i])
                np.minimum(best, dist(F[i]), out=best)
            C = _refine(C, dist, mean, rad, refine)
            # prune: drop the centres (smallest clusters first) that the others
            # cover without them, then refine again
            pruned = True
            while pruned and len(C) > 1:
                pruned = False
                D = np.stack([dist(c) for c in C], axis=1)
                for i in np.argsort(np.bincount(D.argmin(axis=1), minlength=len(C))):
                    rest = _refine(C[:i] + C[i + 1:], dist, mean, rad, refine, force=True)
                    if np.stack([dist(c) for c in rest], axis=1).min(axis=1).max() < rad:
                        C, pruned = rest, True
                        break
        F = F_all  # every sample within radius: continue the greedy cover on all of them
        if j:
            best = np.stack([dist(c) for c in C], axis=1).min(axis=1)
            while best.max() >= rad:
                i = int(np.argmax(best))
                C.append(F[i])
                np.minimum(best, dist(F[i]), out=best)
        D = np.stack([dist(c) for c in C], axis=1)
        near = D.argmin(axis=1)
        Q, r = flats.quadrics()
        normals = use_normals(k, d) and not oriented
        As, Ns, rs, ss, counts, cover = [], [], [], [], [], []
        for i, c in enumerate(C):
            rows = np.flatnonzero(near == i)
            if rows.size == 0:
                continue
            if k == 0:
                a, n = np.zeros((d, 0)), np.eye(d)
            elif normals:
                a, n = complement(c), c
            else:
                a, n = c, complement(c)
            Qc = n @ n.T
            x = np.linalg.pinv(Q[rows].sum(axis=0)) @ r[rows].sum(axis=0)
            rc = Qc @ x
            sub = rows if rows.size <= max_scale_samples else rng.choice(
                rows, max_scale_samples, replace=False)
            sel = select_scale(Q[sub], r[sub], lambda sc, Qc=Qc, rc=rc, a=a, n=n:
                               _unit_simplex(Qc, rc, k, sc, (a, n), provisional),
                               fraction=fraction, lo=1e-3, hi=1e3)
            As.append(a)
            Ns.append(n)
            rs.append(rc)
            ss.append(sel.scale)
            counts.append(int(rows.size))
            cover.append(sel.coverage)
        atlas = cls(k, d, np.stack(As), np.stack(Ns), np.stack(rs), np.array(ss),
                    oriented=oriented, inner=inner, trusted=trusted, reach=reach, unit=unit,
                    isometric=isometric)
        atlas.info = {"method": "samples", "centres": len(As), "radius_deg": radius,
                      "max_sample_angle_deg": float(np.degrees(D.min(axis=1).max())),
                      "samples_per_chart": counts, "convex_coverage": cover}
        return atlas

    # ------------------------------------------------------------------ queries
    def probe(self, chart: int, distance: float | None = None) -> str:
        """Check that a chart round-trips flats at the edge of its domain.

        Probe flats: the centre with each spanning vector ``a_i`` turned by
        ``reach`` toward each normal ``n_j``, moved by ``distance`` along
        ``n_j``; and the centre moved by ``distance`` along each ``n_j``
        (default: the atlas's ``unit``).

        Returns
        -------
        str
            Empty when every probe round-trips, else what failed.
        """
        A, N, r0 = self.center_A[chart], self.center_N[chart], self.center_r[chart]
        k, d = self.k, self.d
        distance = self.unit if distance is None else float(distance)
        t = math.radians(self.reach)
        As, bs = [], []
        for j in range(d - k):
            bs.append(r0 + distance * N[:, j])
            As.append(A.copy())
            for i in range(k):
                Ai = A.copy()
                Ai[:, i] = math.cos(t) * A[:, i] + math.sin(t) * N[:, j]
                As.append(Ai)
                bs.append(r0 + distance * N[:, j])
        if k == 0:
            Q = np.broadcast_to(np.eye(d), (len(bs), d, d))
            f = Flats.from_quadrics(Q, np.array(bs), 0)
        else:
            f = Flats.from_parametric(np.array(As), np.array(bs))
        co = self.bases[chart].coordinates_of(f)
        if (co.status == OK).all():
            return ""
        worst = float(np.nanmax(co.residual))
        return (f"{int((co.status != OK).sum())} of {len(bs)} probe flats ({self.reach:g} "
                f"degrees and {distance:g} from the centre) do not round-trip (largest "
                f"residual {worst:.3g})")

    def with_unit(self, unit: float, *, net: bool = True) -> "Atlas":
        """The same charts (centres, scales, radii, relative and isometric or not) in another unit
        of length: their tangent simplices rebuilt (:func:`_unit_simplex`), their
        warps calibrated again on first use; ``info["unit_from"]`` says
        ``"data"`` or ``"fit"`` when this atlas's unit was to be chosen from the
        data (:attr:`unit_rule`).

        Parameters
        ----------
        unit : float
            Positive, in the flats' units.
        net : bool
            Keep the net of the outer seam (``seam_spacing``). False: every flat
            up to ``dense_reach`` and, while sparse (``dense_after``), ``reach``
            (:func:`flatserve.atlas_field.fitted_unit`'s trial fields: a net in
            the charts' coordinates thins more in a longer unit).

        Returns
        -------
        Atlas
        """
        out = Atlas(self.k, self.d, self.center_A, self.center_N, self.center_r, self.scales,
                    oriented=self.oriented, inner=self.inner, trusted=self.trusted,
                    reach=self.reach, unit=unit, isometric=self.isometric,
                    relative=self.relative, **self._seam(net))
        out.info = {**self.info, **({"unit_from": self.unit_rule} if self.unit_from_data else {})}
        return out

    def _seam(self, net: bool = True) -> dict:
        """``dense_reach``, ``dense_after`` and ``seam_spacing`` as keywords (``net``
        False: without ``seam_spacing``, and without ``dense_reach`` if nothing else
        is done beyond it)."""
        if net or self.seam_spacing is None:
            return {"dense_reach": self.dense_reach, "dense_after": self.dense_after,
                    "seam_spacing": self.seam_spacing}
        return {"dense_reach": None if self.dense_after is None else self.dense_reach,
                "dense_after": self.dense_after, "seam_spacing": None}

    @property
    def unit_setting(self) -> float | str | None:
        """What ``unit=`` makes an atlas choose its unit as this one does: the length,
        None (:func:`data_unit`) or ``"fit"``."""
        if not self.unit_from_data:
            return self.unit
        return None if self.unit_rule == "data" else self.unit_rule

    @property
    def ncharts(self) -> int:
        return len(self.bases)

    def __len__(self) -> int:
        return self.ncharts

    def __repr__(self) -> str:
        return (f"Atlas(k={self.k}, d={self.d}, charts={self.ncharts}, oriented={self.oriented}, "
                f"inner={self.inner:g}, trusted={self.trusted:g}, reach={self.reach:g}, "
                f"unit={self.unit:g}" + (", relative=True)" if self.relative else ")"))

    def check_flats(self, flats: Flats) -> Flats:
        """Check that ``flats`` fit the atlas (dimension, orientation).

        Raises
        ------
        InvalidInputError
            Naming the first array of the batch: wrong (k, d), or a form
            without orientation (``parametric``, ``flats``) given to an
            oriented atlas.
        """
        _flats.check_batch(flats, self.k, self.d, "this atlas charts")
        _require_rays(flats, self.oriented)
        return flats

    def angles(self, flats: Flats) -> np.ndarray:
        """(n, c) angles (radians) of each flat to each chart's centre.

        The largest principal angle between direction spaces; for oriented
        atlases the angle between the ray's direction and the centre's
        (module docstring).
        """
        self.check_flats(flats)
        F = orientation_frames(flats, normals=False if self.oriented else None)
        return max_principal_angle(self.frames, F, oriented=self.oriented)

    def route(self, flats: Flats, radius: float, *, nearest: bool = True) -> Routing:
        """Per chart, the flats closer than ``radius`` (degrees) to its centre.

        Batched: one matrix product (lines) or one closed-form 2x2 eigenvalue
        per flat and chart, one comparison pass over all of them; ``arccos``
        only for the rows kept.

        Parameters
        ----------
        flats : Flats
        radius : float
            Degrees (``reach`` for samples, ``trusted`` for queries).
        nearest : bool
            Also find each flat's nearest chart (the upload path needs it, a
            query does not): ``Routing.nearest`` and ``nearest_angle`` are
            None when False.

        Returns
        -------
        Routing
        """
        self.check_flats(flats)
        F = orientation_frames(flats, normals=False if self.oriented else None)
        n, c = flats.n, self.ncharts
        if self.relative:
            return self._route_relative(F, radius, nearest)
        cr = math.cos(math.radians(radius))
        rows, angles = [], []
        if self.oriented or F.shape[2] == 1:
            # (n, c); row by row in a fixed order: a flat's routing (which
            # charts, what weights) must not depend on the rest of its batch
            dots = self._cosines(F)
            held = np.ascontiguousarray((dots > cr).T)  # (c, n): one pass, rows contiguous
            for i in range(c):
                sel = np.flatnonzero(held[i])
                rows.append(sel)
                angles.append(np.arccos(np.minimum(dots[sel, i], 1.0)))
            if not nearest:
                return Routing(rows, angles, None, None)
            near = dots.argmax(axis=1)
            best = dots[np.arange(n), near]
            return Routing(rows, angles, near, np.arccos(np.clip(best, -1.0, 1.0)))
        cr2 = cr * cr
        if nearest:
            best = np.full(n, -1.0)
            near = np.zeros(n, dtype=np.int64)
        for i in range(c):
            c2 = cos2_max_angle(self.frames[i], F)
            sel = np.flatnonzero(c2 > cr2)
            rows.append(sel)
            angles.append(np.arccos(np.sqrt(c2[sel])))
            if nearest:
                better = c2 > best
                best[better] = c2[better]
                near[better] = i
        if not nearest:
            return Routing(rows, angles, None, None)
        return Routing(rows, angles, near, np.arccos(np.sqrt(np.clip(best, 0.0, 1.0))))

    def _cosines(self, F) -> np.ndarray:
        """(n, c) cosines of each line's (ray's) angle to each centre (one product)."""
        dots = row_product(F[:, :, 0], self.frames[:, :, 0].T)
        if not self.oriented:
            np.abs(dots, out=dots)
        return dots

    def _angles_all(self, F) -> np.ndarray:
        """(n, c) angles (radians) of each flat to each centre, row by row."""
        if self.oriented or F.shape[2] == 1:
            return np.arccos(np.clip(self._cosines(F), -1.0, 1.0))
        out = np.empty((F.shape[0], self.ncharts))
        for i in range(self.ncharts):
            out[:, i] = np.arccos(np.sqrt(np.clip(cos2_max_angle(self.frames[i], F), 0.0, 1.0)))
        return out

    def _route_relative(self, F, radius: float, nearest: bool) -> Routing:
        """:meth:`route` of a relative atlas: per flat, the charts within ``radius``
        degrees of its nearest centre's angle and below :data:`RELATIVE_LIMIT_DEG`
        (the nearest chart always). Blocks of :data:`RELATIVE_BLOCK` rows, so the
        dense angles stay small; each row's result is its own."""
        n, c = F.shape[0], self.ncharts
        rows: list = [[] for _ in range(c)]
        angles: list = [[] for _ in range(c)]
        nears, bests = [], []
        for lo in range(0, n, RELATIVE_BLOCK):
            ang = self._angles_all(F[lo:lo + RELATIVE_BLOCK])
            m = ang.shape[0]
            near = ang.argmin(axis=1)
            best = ang[np.arange(m), near]
            limit = np.minimum(best + math.radians(radius), math.radians(RELATIVE_LIMIT_DEG))
            held = np.ascontiguousarray((ang <= limit[:, None]).T)
            held[near, np.arange(m)] = True  # (the nearest chart always holds it)
            for i in range(c):
                sel = np.flatnonzero(held[i])
                rows[i].append(sel + lo)
                angles[i].append(ang[sel, i])
            nears.append(near)
            bests.append(best)
        empty_i, empty_f = np.zeros(0, dtype=np.int64), np.zeros(0)
        rows = [np.concatenate(r) if r else empty_i for r in rows]
        angles = [np.concatenate(a) if a else empty_f for a in angles]
        if not nearest:
            return Routing(rows, angles, None, None)
        return Routing(rows, angles,
                       np.concatenate(nears) if nears else empty_i,
                       np.concatenate(bests) if bests else empty_f)

    def relative_weights(self, ro: Routing) -> list:
        """A relative atlas's blending weights of a query routing (``route(flats,
        trusted)`` with ``nearest``): per chart, ``bump`` of the angle beyond the
        nearest centre's (1 up to ``inner``, 0 from ``trusted``) times ``bump`` of
        the angle itself from :data:`RELATIVE_ANSWER_DEG` - 4 to
        :data:`RELATIVE_ANSWER_DEG` (a chart answers only where it holds every
        sample within ``(reach - trusted) / 2`` of the query). Continuous in the
        flat: both angles are."""
        inner, trusted = math.radians(self.inner), math.radians(self.trusted)
        top = math.radians(RELATIVE_ANSWER_DEG)
        taper = math.radians(RELATIVE_ANSWER_DEG - RELATIVE_TAPER_DEG)
        return [bump(a - ro.nearest_angle[r], inner, trusted) * bump(a, taper, top)
                for r, a in zip(ro.rows, ro.angles)]

    def beyond_dense(self, ro: Routing, c: int) -> np.ndarray:
        """(len(ro.rows[c]),) bool: which of chart ``c``'s rows of ``ro`` (a
        :meth:`route` with ``nearest``) lie beyond ``dense_reach`` of their nearest
        centre's angle, the seam a dense chart no longer stores (all False without
        a ``dense_reach``)."""
        rows = ro.rows[c]
        if self.dense_reach is None:
            return np.zeros(rows.size, dtype=bool)
        return ro.angles[c] - ro.nearest_angle[rows] > math.radians(self.dense_reach)

    def held(self, flats: Flats, radius: float) -> np.ndarray:
        """Per chart, how many flats are closer than ``radius`` (degrees) to its centre.

        The sizes of :meth:`route`'s ``rows`` (the same test), without the angles:
        one matrix product for lines.  ``held(flats, reach).sum()`` is the number
        of chart vertices a batch adds (before round-trip rejections).

        Returns
        -------
        ndarray, shape (c,), int64
        """
        if self.relative:
            return np.array([r.size for r in self.route(flats, radius, nearest=False).rows],
                            dtype=np.int64)
        self.check_flats(flats)
        F = orientation_frames(flats, normals=False if self.oriented else None)
        cr = math.cos(math.radians(radius))
        if self.oriented or F.shape[2] == 1:
            dots = self._cosines(F)  # (n, c), as route
            return np.count_nonzero(dots > cr, axis=0).astype(np.int64)
        return np.array([np.count_nonzero(cos2_max_angle(C, F) > cr * cr) for C in self.frames],
                        dtype=np.int64)

    def covering_radius(self, n: int = COVER_CHECK_N, *, seed: int = 1,
                        return_worst: bool = False, batch: int = 50_000):
        """Largest angle (degrees) of ``n`` Haar-random orientations to the nearest centre.

        Oriented atlases sample directions uniformly on the sphere.

        Returns
        -------
        float, or (float, ndarray (d, j)) with the worst orientation's frame
        """
        return covering_radius(self.frames, oriented=self.oriented, n=n, seed=seed,
                               return_worst=return_worst, batch=batch)

    # ------------------------------------------------------------- persistence
    @property
    def warps(self) -> list:
        """Per chart its warp (isometric atlases: :class:`~flatserve.warp.LineWarp` for
        lines, :class:`~flatserve.warp.FlatWarp` otherwise), else None.

        Calibrated on first use, or as stored (:meth:`from_dict`: a field
        rebuilt from its log keeps the warps it was built with, whatever
        the calibration of the code that rebuilds it)."""
        if self._warps is None:
            if not self.isometric:
                self._warps = [None] * self.ncharts
            else:
                out = []
                kind = LineWarp if self.k == 1 else FlatWarp
                for i, B in enumerate(self.bases):
                    try:
                        out.append(kind.calibrate(B))
                    except InvalidInputError as exc:
                        raise InvalidInputError(f"centers: chart {i} (scale "
                                                f"{self.scales[i]:g}): {exc}", "centers") from None
                self._warps = out
        return self._warps

    @staticmethod
    def spec_isometric(spec: dict) -> bool:
        """Whether the atlas stored as ``spec`` (:meth:`to_dict`) has isometric charts:
        a spec written before there was a choice has the paper's charts."""
        return bool(spec.get("isometric", False))

    @staticmethod
    def describe_spec(spec: dict) -> dict:
        """The description of the atlas stored as ``spec`` (:meth:`to_dict`), without samples.

        What a field's ``describe`` says of its atlas, available before the
        field is loaded (:func:`flatserve.contract.describe_definition`).

        Returns
        -------
        dict
            ``{"atlas": {"method", "oriented", "inner", "trusted", "reach",
            "relative", "dense_reach", "dense_after", "seam_spacing", "unit", "unit_from",
            "isometric",
            "covering_radius", "max_sample_angle", "info"}, "charts": [{"center":
            {"A", "r"}, "scale", "samples": None}, ...]}`` (``method``, ``covering_radius`` and
            ``max_sample_angle`` from ``info``, None where it has none;
            ``unit`` None while it is to be chosen from the first samples,
            ``unit_from`` its rule, ``"data"`` or ``"fit"``, then and once
            chosen, else ``"given"``).
        """
        info = dict(spec.get("info", {}))
        rule = (spec.get("unit_rule", "data") if spec.get("unit_from_data")
                else info.get("unit_from") if info.get("unit_from") in UNIT_RULES else "given")
        return {
            "atlas": {"method": info.get("method"), "oriented": bool(spec["oriented"]),
                      "inner": spec["inner"], "trusted": spec["trusted"],
                      "reach": spec["reach"], "relative": bool(spec.get("relative", False)),
                      "dense_reach": spec.get("dense_reach"),
                      "dense_after": spec.get("dense_after"),
                      "seam_spacing": spec.get("seam_spacing"),
                      "unit": None if spec.get("unit_from_data") else spec.get("unit",
                                                                               DEFAULT_UNIT),
                      "unit_from": rule,
                      "isometric": Atlas.spec_isometric(spec),
                      "covering_radius": info.get("covering_radius_deg"),
                      "max_sample_angle": info.get("max_sample_angle_deg"), "info": info},
            "charts": [{"center": {"A": A, "r": r}, "scale": s, "samples": None}
                       for A, r, s in zip(spec["center_A"], spec["center_r"], spec["scales"])],
        }

    def chart_field(self, i: int, channels: int = 1, *,
                    roundtrip_tol: float = ROUNDTRIP_TOL) -> Field:
        """An empty single-chart :class:`~flatserve.field.Field` of chart ``i``
        (its basis, and its warp when the atlas is isometric)."""
        return Field(self.bases[i], channels, roundtrip_tol=roundtrip_tol, warp=self.warps[i])

    def to_dict(self) -> dict:
        """JSON-able description (centres, scales, radii); :meth:`from_dict` inverts it."""
        return {"k": self.k, "d": self.d, "oriented": self.oriented, "inner": self.inner,
                "trusted": self.trusted, "reach": self.reach, "unit": self.unit,
                **({"unit_from_data": True} if self.unit_from_data else {}),
                **({"unit_rule": self.unit_rule} if self.unit_rule == "fit" else {}),
                "isometric": self.isometric, **({"relative": True} if self.relative else {}),
                **({"dense_reach": self.dense_reach, "dense_after": self.dense_after}
                   if self.dense_reach is not None else {}),
                **({"seam_spacing": self.seam_spacing} if self.seam_spacing is not None else {}),
                **({"warps": [w.to_dict() for w in self.warps]} if self.isometric else {}),
                "center_A": self.center_A.tolist(), "center_N": self.center_N.tolist(),
                "center_r": self.center_r.tolist(), "scales": self.scales.tolist(),
                "info": self.info}

    @classmethod
    def from_dict(cls, spec: dict) -> "Atlas":
        """The atlas described by :meth:`to_dict` (no covering measurement repeated)."""
        atlas = cls(int(spec["k"]), int(spec["d"]), np.array(spec["center_A"]),
                    np.array(spec["center_N"]), np.array(spec["center_r"]),
                    np.array(spec["scales"]), oriented=bool(spec["oriented"]),
                    inner=spec["inner"], trusted=spec["trusted"], reach=spec["reach"],
                    unit=(spec.get("unit_rule", "data") if spec.get("unit_from_data")
                          else spec.get("unit", DEFAULT_UNIT)),
                    isometric=cls.spec_isometric(spec), relative=spec.get("relative", False),
                    dense_reach=spec.get("dense_reach"), dense_after=spec.get("dense_after"),
                    seam_spacing=spec.get("seam_spacing"))
        if atlas.isometric and "warps" in spec:
            warps = [warp_from_dict(w) for w in spec["warps"]]
            if len(warps) != atlas.ncharts:
                raise InvalidInputError(f"warps: {len(warps)} for {atlas.ncharts} charts", "warps")
            atlas._warps = warps  # as stored
        atlas.info = dict(spec.get("info", {}))
        return atlas


def object_unit(radius: float) -> float:
    """The unit of length (:class:`Atlas` ``unit``) for rays of an object of this radius.

    ``2 radius / 3``: the mean depth, from the centre, of the surface of a
    ball of that radius as a viewer sees it (``sqrt(R^2 - rho^2)`` averaged
    over the disc ``rho < R`` it covers).  Two rays that meet on the surface
    at depth ``z`` differ by a shift of ``z`` times their turn, so in this
    unit a turn and the shift it makes on a typical visible point count
    alike.  Measured on the 360-degree bunny (docs/orbit-results.md, 100,000
    rays, 24 views, radius 0.5): units 0.7, 0.5 and 1/3 gave ours - baseline
    at least -0.71, -0.22 and +0.05 dB.

    Parameters
    ----------
    radius : float
        Positive: the radius of a ball about the atlas's origin that holds
        the object (something a user knows without rendering).

    Returns
    -------
    float
    """
    if not (isinstance(radius, (int, float, np.floating, np.integer))
            and not isinstance(radius, bool) and math.isfinite(radius) and radius > 0):
        raise InvalidInputError(f"radius: expected a positive length, got {radius!r}", "radius")
    return 2.0 * float(radius) / 3.0


#: The range of a unit of length (the service's bounds of ``unit`` too): a unit
#: chosen from the data is clipped to it.
MIN_UNIT, MAX_UNIT = 1e-6, 1e6
#: How an atlas made with ``unit`` left to its data chooses it from a field's first
#: samples (:attr:`Atlas.unit_rule`): ``"data"`` the geometry of the flats
#: (:func:`data_unit`, what ``unit=None`` means), ``"fit"`` held-out validation on
#: their values (:func:`flatserve.atlas_field.fitted_unit`).
UNIT_RULES = ("data", "fit")
#: The most dimensions of a chart's triangulation (``basis_size(k, d) - 1``) for which
#: a unit left out is fitted to the values (:func:`default_unit_rule`).
FIT_MAX_DIM = 6


def default_unit_rule(k: int, d: int) -> str:
    """How a field of k-flats in R^d whose unit is left out chooses it (the service's
    default, :data:`flatserve.atlas.UNIT_RULES`): ``"fit"`` (:func:`flatserve.atlas_field.fitted_unit`)
    while a chart's triangulation has at most :data:`FIT_MAX_DIM` dimensions
    (every kind up to R^3, and in R^4), ``"data"`` (:func:`data_unit`)
    beyond, where a fit costs minutes (lines in R^5, 8 dimensions, a first batch
    of 1,000 rows: its upload took 163 s with the fit, 70 s without, on a
    loaded machine). Points (k = 0) take ``"data"``: their chart's coordinates are
    the points' own scaled by the unit, and a uniform scale changes neither their
    Delaunay cells nor the weights, so a fit could only cost time (1,500 points in
    R^6: 35 s against 8 s, the same answers).

    >>> default_unit_rule(1, 3), default_unit_rule(2, 4), default_unit_rule(1, 5)
    ('fit', 'fit', 'data')
    >>> default_unit_rule(0, 3)
    'data'
    """
    return "fit" if k > 0 and (basis_size(k, d) - 1) <= FIT_MAX_DIM else "data"


#: A value row shared by at least this share of a batch's samples is a
#: background (:func:`data_unit`): samples of a continuous function repeat no
#: value exactly, rays that miss every object all carry the background's.
BACKGROUND_SHARE = 0.05


def _check_rule(unit) -> float:
    """``unit`` as an atlas takes it: a word must be one of :data:`UNIT_RULES` or
    :data:`AUTO_UNIT`; the unit its charts have until the rule chooses
    (:data:`DEFAULT_UNIT`), or the length itself (checked)."""
    if isinstance(unit, str) and unit not in UNIT_RULES + (AUTO_UNIT,):
        raise InvalidInputError(f"unit: expected a positive length or one of "
                                f"{', '.join(map(repr, UNIT_RULES + (AUTO_UNIT,)))}, got "
                                f"{unit!r}", "unit")
    return DEFAULT_UNIT if unit is None or isinstance(unit, str) else _check_unit(unit)


def _check_unit(unit) -> float:
    if not (isinstance(unit, (int, float, np.floating, np.integer))
            and not isinstance(unit, bool) and math.isfinite(unit) and unit > 0):
        raise InvalidInputError(f"unit: expected a positive length, got {unit!r}", "unit")
    return float(unit)


def data_unit(flats: Flats, values=None) -> float:
    """The unit of length (:class:`Atlas` ``unit``) of a field, from its first samples.

    The mean distance of the sample flats from their centre: the point ``x*``
    that minimises the sum of their quadratic distance fields,
    ``sum_i q_i(x) = sum_i (x^T Q_i x - 2 r_i^T x + r_i^T r_i)`` (Eq. 2),
    ``x* = (sum_i Q_i)^+ sum_i r_i`` (the extremum of ``q*``, Sec. 2.3), and
    ``unit = mean_i sqrt(q_i(x*)) = mean_i ||Q_i x* - r_i||``.  Samples whose value row is a
    background (one value row shared by at least :data:`BACKGROUND_SHARE`
    of the samples) are left out when the others are at least as many as
    ``k + 1``: for rays of an object they are the rays that miss it.

    Why: for rays that meet an object of radius ``R`` about ``x*``, their
    distances from ``x*`` are spread over its disc, mean ``2R/3``, which is
    :func:`object_unit` ``(R)``, the hand-set rule (a turn and the shift it
    makes on a typical visible point count alike) without knowing ``R``.
    Rays of the 360-degree scenes (``flatserve.lightfield.orbit``, through
    the ball of radius 1, the objects within 0.5 of its centre; the first
    100,000 of 200,000 rays): 0.304 (the bunny) and 0.294 (the blocks)
    against the hand-set 1/3; all rays, without the background rule: 0.67.

    Parameters
    ----------
    flats : Flats
        ``n >= 1`` k-flats in R^d.
    values : (n, C) or (n,) array_like, optional
        Their values (the background rule); None: every flat counts.

    Returns
    -------
    float
        In [:data:`MIN_UNIT`, :data:`MAX_UNIT`]; :data:`DEFAULT_UNIT` when the
        flats all pass through one point (the mean distance below 1e-9 of the
        data's size about the origin: rounding), or k = 0 and all coincide.
    """
    n = flats.n
    if n == 0:
        raise InvalidInputError("flats: a unit from the data needs at least one flat", "flats")
    keep = np.ones(n, dtype=bool)
    if values is not None:
        v = np.ascontiguousarray(np.asarray(values, dtype=np.float64).reshape(n, -1))
        _, inverse, counts = np.unique(v, axis=0, return_inverse=True, return_counts=True)
        top = int(counts.argmax())
        if counts[top] >= BACKGROUND_SHARE * n and n - counts[top] >= flats.k + 1:
            keep = inverse.reshape(-1) != top
    Q, r = flats.quadrics()
    Q, r = Q[keep], r[keep]
    x = np.linalg.pinv(Q.sum(axis=0)) @ r.sum(axis=0)
    # sqrt(q_i(x*)) = ||Q_i x* - r_i|| (Q_i an orthogonal projector, Q_i r_i = r_i),
    # written so, without the cancellation of the expanded quadric
    unit = float(np.linalg.norm(Q @ x - r, axis=1).mean())
    size = float(np.sqrt(np.einsum("ni,ni->n", r, r)).mean() + np.linalg.norm(x))
    if not (math.isfinite(unit) and unit > 1e-9 * max(size, MIN_UNIT)):  # through one point
        return DEFAULT_UNIT
    return min(max(unit, MIN_UNIT), MAX_UNIT)


def _unit_simplex(Q, r, k: int, scale: float, frames, unit: float) -> Basis:
    """The tangent simplex around the flat (Q, r) whose shifts are ``unit`` times
    its turns: the unit-1 simplex around (Q, r / unit), scaled by ``unit`` about
    the origin (Atlas ``unit``)."""
    if unit == 1.0:
        return Basis.tangent_simplex(Q, r, k, scale, frames=frames)
    B = Basis.tangent_simplex(Q, np.asarray(r) / unit, k, scale, frames=frames)
    U = Basis(B.Q, B.r * unit, k)
    U.center, U.scale, U.variant = (B.center[0], B.center[1] * unit), B.scale, B.variant
    return U


def _refine(C, dist, mean, rad, rounds, force=False):
    """Move each centre to the mean of its nearest samples while all stay within ``rad``.

    ``force``: take the moves whatever the coverage (to test a pruned set).
    """
    for _ in range(rounds):
        near = np.stack([dist(c) for c in C], axis=1).argmin(axis=1)
        C2 = [mean(np.flatnonzero(near == i)) if (near == i).any() else C[i]
              for i in range(len(C))]
        if not force and not np.stack([dist(c) for c in C2], axis=1).min(axis=1).max() < rad:
            break
        C = C2
    return C


def _require_rays(flats: Flats, oriented: bool) -> None:
    if oriented and flats.form != "rays":
        arg = next(iter(flats.arrays))
        raise InvalidInputError(
            f"{arg}: this atlas is oriented (a ray and its reverse are different samples); "
            f"the form {flats.form!r} ({' + '.join(flats.arrays)}) has no orientation: give "
            "rays (origins + directions)", arg)


# ---------------------------------------------------------------------- atlas field
