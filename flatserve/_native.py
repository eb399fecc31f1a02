"""The one module that talks to the private extension ``flatserve._core``."""
from __future__ import annotations

from . import _core

CGAL_VERSION: str = _core.cgal_version
EIGEN_VERSION: str = _core.eigen_version
