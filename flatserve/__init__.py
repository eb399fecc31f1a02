"""flatserve: compute with flats (affine subspaces) the way you compute with points."""
from __future__ import annotations

__version__ = "0.1.0"
