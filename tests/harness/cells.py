"""Comparing answers cell by cell, whatever order a triangulation keeps a cell's
vertices in (the tiles of :mod:`flatserve.tiles` against the unsplit one)."""
from __future__ import annotations

import numpy as np


def assert_same_cells(ids_a, weights_a, ids_b, weights_b, rows) -> None:
    """Rows ``rows`` of two answers' ``(n, D+1)`` ids and weights name the same
    vertices with the same weight each (bits), in any order within a row."""
    a, b = np.argsort(ids_a[rows], axis=1), np.argsort(ids_b[rows], axis=1)
    assert np.array_equal(np.take_along_axis(ids_a[rows], a, 1),
                          np.take_along_axis(ids_b[rows], b, 1)), "cells differ"
    assert np.array_equal(np.take_along_axis(weights_a[rows], a, 1),
                          np.take_along_axis(weights_b[rows], b, 1)), "weights differ (bits)"
