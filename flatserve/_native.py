"""The one module that talks to the private extension ``flatserve._core``.

Other modules use the names below (never ``import flatserve._core``) so that
the extension's location and failure mode live in one place. Its exceptions
subclass :mod:`flatserve.errors` (``_core.SnapshotError`` is a
:class:`flatserve.errors.SnapshotError`): callers catch the library classes.
"""
from __future__ import annotations

from . import _core

core = _core

CGAL_VERSION: str = _core.cgal_version
EIGEN_VERSION: str = _core.eigen_version

# ---- triangulation ----
# CGAL dD Delaunay (native/triangulation*.hpp); the Python face is
# flatserve.triangulation.Triangulation.
Triangulation = _core.Triangulation
#: Where a query landed (an IntEnum: compares with the int8 ``kind`` arrays).
LocateKind = _core.LocateKind
#: Which candidates lie farther than a radius from every point before them
#: (native/net.hpp; the Python face is flatserve.triangulation.seam_net).
seam_net = _core.seam_net
# ---- /triangulation ----

# ---- coordinates ----
# Hot path of flatserve.coordinates.coordinates_rays (lines in R^3, 5-element
# basis); flatserve/coordinates.py holds the NumPy reference and the wrapper.
coordinates_rays3 = _core.coordinates_rays3
#: Status of one coordinate row (an IntEnum); reasons in flatserve.coordinates.
CoordinateStatus = _core.CoordinateStatus
# ---- /coordinates ----

# ---- raycast ----
# CGAL AABB-tree ray casting (native/raycast.hpp); the Python face is
# flatserve.lightfield.scene.Scene.
RayCaster = _core.RayCaster
# ---- /raycast ----
