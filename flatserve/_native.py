"""The one module that talks to the private extension ``flatserve._core``.

Other modules use ``_native.core`` (never ``import flatserve._core``) so that
the extension's location and failure mode live in one place.
"""
from __future__ import annotations

from . import _core

core = _core

CGAL_VERSION: str = _core.cgal_version
EIGEN_VERSION: str = _core.eigen_version

# ---- coordinates ----
# Hot path of flatserve.coordinates.coordinates_rays (lines in R^3, 5-element
# basis); flatserve/coordinates.py holds the NumPy reference and the wrapper.
coordinates_rays3 = getattr(_core, "coordinates_rays3", None)  # None until rebuilt
# ---- /coordinates ----

# ---- raycast ----
# CGAL AABB-tree ray casting (native/raycast.hpp); the Python face is
# flatserve.lightfield.scene.Scene.
RayCaster = getattr(_core, "RayCaster", None)  # None until rebuilt
# ---- /raycast ----
