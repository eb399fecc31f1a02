"""The geometry of a rig of cameras, and the field that suits a capture of it.

A capture (:mod:`flatserve.lightfield.capture`) samples rays densely within
each photograph and sparsely between photographs. Two choices decide how well
a field over an atlas of oriented lines interpolates such samples
(``docs/capture-results.md``):

* **where the charts are**: around the orientations the capture's rays have,
  through the point the cameras look at (:func:`rig_center`), so that a chart's
  shift coordinates are measured where the scene is: :func:`probe_rays` gives
  the flats :meth:`flatserve.atlas.Atlas.for_samples` places the charts for;
* **the unit of length** (:class:`flatserve.atlas.Atlas` ``unit``: the shift
  that weighs as much as a turn of one radian): :func:`rig_unit` makes the
  step between neighbouring pixels' rays at the rig's centre (a shift) weigh
  as much as the step between neighbouring cameras seen from there (a turn),
  so that the Delaunay cells join rays across photographs instead of
  stretching along one.

:func:`capture_atlas` is the library's atlas for a capture;
:func:`field_spec` the same choices as a service field's create options
(``Client.import_capture`` uses them).

>>> from flatserve.lightfield.capture import read_capture    # doctest: +SKIP
>>> cap = read_capture("scene")                               # doctest: +SKIP
>>> atlas = capture_atlas(cap.cameras)                        # doctest: +SKIP
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .._validate import as_array
from ..errors import InvalidInputError
from .camera import PinholeCamera

__all__ = ["PROBE_SIDE", "ATLAS_RADIUS_DEG", "DIGITS", "PARALLEL_DEG", "rig_center", "rig_unit", "probe_rays", "capture_atlas",
           "SPARSE_DEG", "DepthRig", "rig_spacing_deg", "wants_depth", "depth_rig", "field_spec"]

#: Rays per image side that :func:`probe_rays` takes (4 x 4 per camera, the
#: corners included): where a capture's rays are, for the atlas's charts.
PROBE_SIDE = 4
#: Degrees: every probe ray is this close to a chart's centre
#: (:meth:`flatserve.atlas.Atlas.for_samples` ``radius``).
ATLAS_RADIUS_DEG = 30.0
#: Degrees: cameras whose optical axes are all closer than this to their mean
#: direction look at no point that the poses determine (a forward-facing rig of
#: nearly parallel cameras: pose noise of 1e-3 radians moved :func:`rig_center`
#: from the scene to behind the cameras); :func:`rig_unit` then leaves the unit
#: to the data.
PARALLEL_DEG = 1.0
#: Degrees between neighbouring cameras, seen from the rig's centre, above which
#: a rig is sparse: :func:`wants_depth`.
SPARSE_DEG = 10.0
#: Significant digits the rig's choices are rounded to (:func:`rig_unit`, and
#: :func:`probe_rays`' coordinates): the same capture read from either format
#: (poses that differ by rounding) gets the same atlas, bit for bit, and so the
#: same answers (a Delaunay triangulation of grid-like samples may turn a cell
#: at a perturbation of 1e-16).
DIGITS = 9


def _round(x, digits: int = DIGITS):
    """``x`` rounded to ``digits`` significant digits (arrays elementwise; 0 stays 0)."""
    a = np.asarray(x, dtype=np.float64)
    with np.errstate(divide="ignore"):
        mag = np.where(a == 0, 0, np.floor(np.log10(np.abs(np.where(a == 0, 1.0, a)))))
    scale = 10.0 ** (digits - 1 - mag)
    return np.round(a * scale) / scale


def _cameras(cameras) -> list[PinholeCamera]:
    cams = list(cameras)
    if not cams:
        raise InvalidInputError("cameras: expected at least one camera", "cameras")
    for i, c in enumerate(cams):
        if not isinstance(c, PinholeCamera):
            raise InvalidInputError(f"cameras[{i}]: expected a PinholeCamera, got {type(c).__name__}",
                                    "cameras")
    return cams


def rig_center(cameras: Sequence[PinholeCamera]) -> np.ndarray:
    """The point the cameras look at: nearest to their optical axes in the least-squares sense.

    ``x = (sum_i Q_i)^+ sum_i Q_i e_i`` with ``Q_i = I - f_i f_i^T`` for
    camera ``i``'s eye ``e_i`` and forward direction ``f_i``: the extremum of
    the sum of the axes' quadratic distance fields (paper Eq. 2, Sec. 2.3).
    Parallel axes (a forward-facing rig of parallel cameras) leave the depth
    free; the pseudo-inverse takes the point nearest the origin along it.

    Parameters
    ----------
    cameras : sequence of PinholeCamera

    Returns
    -------
    (3,) float64

    Examples
    --------
    >>> cams = [PinholeCamera.look_at(e, (0, 0, 1), fx=50, fy=50, cx=16, cy=12, width=32,
    ...                               height=24) for e in [(-1, 0, -3), (1, 0, -3), (0, 1, -3)]]
    >>> np.round(rig_center(cams), 9) + 0.0
    array([0., 0., 1.])
    """
    cams = _cameras(cameras)
    f = np.stack([c.rotation[:, 2] for c in cams])
    e = np.stack([c.eye for c in cams])
    Q = np.eye(3)[None] - f[:, :, None] * f[:, None, :]
    return np.linalg.pinv(Q.sum(axis=0)) @ np.einsum("nij,nj->i", Q, e)


def _neighbour_turns(u: np.ndarray) -> np.ndarray:
    """Per camera, the angle (radians) to the nearest other camera, for unit directions
    ``u`` (m, 3) from the rig's centre to the eyes."""
    cos = np.clip(u @ u.T, -1.0, 1.0)
    np.fill_diagonal(cos, -2.0)  # not a camera's own neighbour
    return np.arccos(np.clip(cos.max(axis=1), -1.0, 1.0))


def rig_unit(cameras: Sequence[PinholeCamera], center=None) -> float | None:
    """The unit of length for a field of a rig's rays: a pixel's shift over a camera's turn.

    Seen from the rig's centre ``c`` (:func:`rig_center`), camera ``i``'s
    neighbouring pixels' rays are ``p_i = |e_i - c| / f_i`` apart (a shift;
    ``f_i`` its focal length in pixels, the mean of ``fx`` and ``fy``) and the
    nearest other camera is ``t_i`` radians away (a turn: the angle between
    the directions from ``c`` to the two eyes). The unit is
    ``median(p) / median(t)``: in it the two steps weigh alike, so that the
    triangulation's cells join rays of neighbouring photographs rather than
    stretch along one. On the rigs of ``docs/capture-results.md`` it chose
    0.34 (forward-facing, 40 cameras) and 0.063 (62 cameras all around), where
    units from 0.05 to 0.4, and from 0.03 to 0.3, were within 0.15 and 0.3 dB
    of the best measured.

    Parameters
    ----------
    cameras : sequence of PinholeCamera
    center : (3,) float, optional
        Default :func:`rig_center`.

    Returns
    -------
    float or None
        None when there is no turn to measure (one camera, or all eyes in one
        direction from the centre), when the cameras are nearly parallel
        (within :data:`PARALLEL_DEG` of their mean direction: their centre is
        not determined by the poses) or the centre is behind a camera: then the
        field's own rule chooses (``"data"``).
    """
    cams = _cameras(cameras)
    f = np.stack([cam.rotation[:, 2] for cam in cams])
    if center is None:
        # the axes' mean squared sine to their mean direction: the conditioning of rig_center
        spread = np.linalg.eigvalsh(np.eye(3) - (f.T @ f) / len(cams))[0]
        if spread < math.sin(math.radians(PARALLEL_DEG)) ** 2:
            return None
        c = rig_center(cams)
    else:
        c = np.asarray(center, dtype=np.float64)
    e = np.stack([cam.eye for cam in cams]) - c
    dist = np.linalg.norm(e, axis=1)
    # a centre behind a camera is not what the rig looks at
    if len(cams) < 2 or not (dist > 0).all() or (np.einsum("ij,ij->i", -e, f) <= 0).any():
        return None
    turn = _neighbour_turns(e / dist[:, None])
    focal = np.array([0.5 * (cam.fx + cam.fy) for cam in cams])
    t = float(np.median(turn))
    if not (math.isfinite(t) and t > 1e-9):
        return None
    unit = float(_round(float(np.median(dist / focal)) / t))
    return unit if math.isfinite(unit) and unit > 0 else None


def probe_rays(cameras: Sequence[PinholeCamera], side: int = PROBE_SIDE) -> tuple[np.ndarray, np.ndarray]:
    """A ``side`` x ``side`` grid of rays over each camera's image, the corners included.

    Coordinates rounded to :data:`DIGITS` significant digits.

    Where a capture's rays are, without its pixels: the flats an atlas for the
    capture is placed for (:func:`capture_atlas`).

    Returns
    -------
    origins, directions : (len(cameras) * side**2, 3) float64
    """
    cams = _cameras(cameras)
    if not (isinstance(side, (int, np.integer)) and not isinstance(side, bool) and side >= 2):
        raise InvalidInputError(f"side: expected an integer >= 2, got {side!r}", "side")
    O, D = [], []
    for cam in cams:
        o, d = cam.grid_rays(np.linspace(0.5, cam.width - 0.5, side),
                             np.linspace(0.5, cam.height - 0.5, side))
        O.append(o)
        D.append(d)
    return _round(np.concatenate(O)), _round(np.concatenate(D))


def capture_atlas(cameras: Sequence[PinholeCamera]):
    """The library's atlas for a capture: charts where its rays are, in its rig's unit.

    :meth:`flatserve.atlas.Atlas.for_samples` over :func:`probe_rays`
    (oriented; every probe ray within :data:`ATLAS_RADIUS_DEG` of a centre,
    each centre through the point nearest its rays), unit :func:`rig_unit`
    (``"data"`` when the rig has none). Put the capture's rays in
    ``AtlasField(capture_atlas(cams), channels)``.

    Returns
    -------
    flatserve.atlas.Atlas
    """
    from ..atlas import Atlas
    from ..flats import Flats

    o, d, unit = _choices(cameras)
    return Atlas.for_samples(Flats.from_rays(o, d), oriented=True, radius=ATLAS_RADIUS_DEG,
                             unit=unit)


@dataclass(frozen=True)
class DepthRig:
    """What a depth-guided render needs to know of a capture: its cameras' eyes and centre.

    Attributes
    ----------
    eyes : (m, 3) float64
        The cameras' centres of projection.
    center : (3,) float64
        The point the depth channel is measured from
        (:func:`flatserve.lightfield.depth.depth_values`):
        the rig's centre, :func:`rig_center`.

    Examples
    --------
    >>> rig = DepthRig(eyes=[[0, 0, -3], [3, 0, 0]], center=[0, 0, 0])
    >>> DepthRig.from_dict(rig.to_dict()) == rig
    True
    """

    eyes: np.ndarray
    center: np.ndarray

    def __post_init__(self):
        object.__setattr__(self, "eyes", as_array(self.eyes, "eyes", (None, 3)))
        object.__setattr__(self, "center", as_array(self.center, "center", (3,)))
        if self.eyes.shape[0] < 2:
            raise InvalidInputError(f"eyes: expected at least 2 cameras, got {self.eyes.shape[0]}", "eyes")

    def __eq__(self, other):
        return (isinstance(other, DepthRig) and np.array_equal(self.eyes, other.eyes)
                and np.array_equal(self.center, other.center))

    __hash__ = None

    @classmethod
    def of(cls, cameras: Sequence[PinholeCamera]) -> "DepthRig":
        """The rig of a capture's cameras (its centre :func:`~flatserve.lightfield.rig.rig_center`)."""
        cams = list(cameras)
        return cls(eyes=np.stack([c.eye for c in cams]), center=rig_center(cams))

    def to_dict(self) -> dict:
        """JSON-ready (``eyes``, ``center``)."""
        return {"eyes": self.eyes.tolist(), "center": self.center.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "DepthRig":
        """The inverse of :meth:`to_dict`."""
        return cls(eyes=d["eyes"], center=d["center"])


def rig_spacing_deg(cameras: Sequence[PinholeCamera], center=None) -> float:
    """Median angle (degrees) between each camera and its nearest neighbour, seen from ``center``.

    Parameters
    ----------
    cameras : sequence of PinholeCamera
    center : (3,) float, optional
        Default :func:`rig_center`.

    Returns
    -------
    float
        0 for fewer than two cameras.
    """
    cams = list(cameras)
    if len(cams) < 2:
        return 0.0
    c = rig_center(cams) if center is None else np.asarray(center, dtype=np.float64)
    e = np.stack([cam.eye for cam in cams]) - c
    n = np.linalg.norm(e, axis=1)
    if not (n > 0).all():
        return 0.0
    return float(np.degrees(np.median(_neighbour_turns(e / n[:, None]))))


def wants_depth(cameras: Sequence[PinholeCamera], sparse_deg: float = SPARSE_DEG) -> bool:
    """Whether a capture's field should carry depth and render through it.

    True when the rig looks at a point (:func:`rig_unit`
    finds one: not a forward-facing rig of nearly parallel cameras) and its
    neighbouring cameras are more than ``sparse_deg`` apart seen from there
    (:func:`rig_spacing_deg`). Measured: the depth-guided render wins all
    around (17-24 degrees apart) and loses to the plain field on a
    forward-facing rig (4 degrees apart), where the field alone beats the
    classic light field by 2.5 dB or more.
    """
    cams = list(cameras)
    if len(cams) < 2 or rig_unit(cams) is None:
        return False
    return rig_spacing_deg(cams) > sparse_deg


def depth_rig(cameras: Sequence[PinholeCamera], depth: bool | None = None):
    """The rig a capture's depth channel is measured from, or None when the capture wants none.

    :class:`DepthRig` of the cameras (eyes and
    centre rounded to :data:`DIGITS` significant digits of the rig's size: the
    same capture read from either format gets the same rig) when
    :func:`wants_depth`.

    Parameters
    ----------
    cameras : sequence of PinholeCamera
    depth : bool, optional
        True: the rig whatever :func:`wants_depth`
        says (at least 2 cameras that look at a common point, else an
        :class:`~flatserve.errors.InvalidInputError` naming ``depth``); False: None.

    Returns
    -------
    DepthRig or None
    """
    cams = _cameras(cameras)
    if depth is False or (depth is None and not wants_depth(cams)) or len(cams) < 2:
        return None
    if rig_unit(cams) is None:  # asked for: a sweep needs the point the cameras look at
        raise InvalidInputError("depth: these cameras look at no common point (nearly parallel, or "
                                "the point is behind a camera): a depth sweep needs one; import "
                                "without depth", "depth")
    eyes, center = np.stack([c.eye for c in cams]), rig_center(cams)
    # on one grid for the whole rig (DIGITS significant digits of its size), not digit by
    # coordinate: a centre at the origin read from either format is rounding noise (1e-16
    # apart) that significant digits keep
    size = float(np.abs(eyes - center).max())
    return DepthRig(eyes=_round_on(eyes, size), center=_round_on(center, size))


def _round_on(x, size: float, digits: int = DIGITS) -> np.ndarray:
    """``x`` rounded to multiples of ``10**(e - digits + 1)`` for ``size``'s decimal
    exponent ``e`` (as given when ``size`` is not positive and finite); no -0."""
    a = np.asarray(x, dtype=np.float64)
    if not (np.isfinite(size) and size > 0):
        return a
    step = 10.0 ** (math.floor(math.log10(size)) - (digits - 1))
    return np.round(a / step) * step + 0.0


def field_spec(cameras: Sequence[PinholeCamera], channels: int, depth: bool | None = None) -> dict:
    """The same choices as :func:`capture_atlas`, as a service field's create options.

    Parameters
    ----------
    cameras : sequence of PinholeCamera
    channels : int
        The colour channels.
    depth : bool, optional
        :func:`depth_rig`'s.

    Returns
    -------
    dict
        Keyword arguments of ``flatserve.client.Client.create_field``:
        ``channels``, ``oriented`` (true), ``basis`` (an atlas for the probe
        rays, ``{"kind": "atlas", "atlas": "samples", ...}``) and ``unit``
        (:func:`rig_unit`, or ``"data"``); on a rig that wants depth
        (:func:`depth_rig`), ``rig`` (its ``to_dict()``) and one channel
        more: the depth channel, last.
    """
    o, d, unit = _choices(cameras)
    spec = {"channels": int(channels), "oriented": True,
            "basis": {"kind": "atlas", "atlas": "samples", "radius": ATLAS_RADIUS_DEG,
                      "samples": {"origins": o.tolist(), "directions": d.tolist()}},
            "unit": unit}
    rig = depth_rig(cameras, depth)
    if rig is not None:
        spec["channels"] += 1
        spec["rig"] = rig.to_dict()
    return spec


def _choices(cameras):
    """The probe rays and the unit (or ``"data"``) of a capture's field."""
    cams = _cameras(cameras)
    o, d = probe_rays(cams)
    unit = rig_unit(cams)
    return o, d, "data" if unit is None else unit
