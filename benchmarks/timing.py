"""Timing shared by the benchmark scripts (run as ``python benchmarks/bench_*.py``,
so this directory is on ``sys.path``).

Importing it also puts the repository root on ``sys.path``: the scripts that
start real servers or PostgreSQL clusters use the test harness
(``tests.harness``), which is not part of the installed package.
"""
from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def median_time(fn, runs: int):
    """``(median seconds of runs calls of fn(), the last call's result)``.

    The previous result is freed before each run, so a run never pays for the
    memory of the one before (machines here are shared and noisy: medians).
    """
    ts, out = [], None
    for _ in range(max(1, runs)):
        out = None
        t0 = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts), out
