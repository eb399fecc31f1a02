"""benchmarks/soak.py: a short run passes and prints its figures, and its checks
catch a lost, a half-stored and an unsent batch."""
from __future__ import annotations

import argparse
from contextlib import contextmanager
import importlib.util
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from flatserve.client import Client

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "soak.py"


@pytest.fixture(scope="module")
def soak():
    spec = importlib.util.spec_from_file_location("flatserve_soak", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up
    try:
        spec.loader.exec_module(mod)
        yield mod
    finally:
        del sys.modules[spec.name]


def test_short_soak_passes_and_prints_figures(soak, capsys):
    assert soak.main(["--cycles", "4", "--seed", "3"]) == 0
    out = capsys.readouterr().out
    assert "cycles (kill -9 / restart): 4" in out
    acked = int(re.search(r"acknowledged: (\d+)", out).group(1))
    assert acked > 0
    assert "lost: 0" in out


def _soak_on(soak, tmp_path):
    args = argparse.Namespace(seed=0, max_rows=100, max_work=0.2, snapshot_every=0,
                              cycles=1, seconds=60)
    return soak.Soak(args, str(tmp_path / "data"), str(tmp_path / "server.log"))


@contextmanager
def _served(soak, tmp_path):
    """A soak model and a real server on its data dir, with the field ``soak-a``."""
    s = _soak_on(soak, tmp_path)
    (tmp_path / "data").mkdir()
    srv = soak.Server(s.data_dir, s.log_path, 0)
    try:
        srv.wait_ready()
        with Client(srv.url, retries=0) as c:
            m = s.models["soak-a"]
            c.create_field("soak-a", channels=1)
            m.exists = True
            yield s, c, m
    finally:
        srv.kill9()


@pytest.mark.parametrize("tamper, message", [
    ("lost", "acknowledged batch ghost lost"),
    ("rows", "stored with rows"),
    ("unsent", "was never sent"),
    ("half", "half-stored"),
])
def test_checks_catch_violations(soak, tmp_path, tamper, message):
    with _served(soak, tmp_path) as (s, c, m):
        rng = np.random.default_rng(0)
        s.upload(c, rng, "soak-a", m)
        s.upload(c, rng, "soak-a", m)
        key = next(iter(m.acked))
        if tamper == "lost":
            m.acked["ghost"] = (10, 10)
        elif tamper == "rows":
            rows, acc = m.acked[key]
            m.acked[key] = (rows + 1, acc)
        elif tamper == "unsent":
            del m.acked[key]
        else:  # the batch is stored, the client thinks it sent more rows in flight
            b = m.sent[key]
            del m.acked[key]
            m.inflight[key] = soak.Batch(np.r_[b.origins, b.origins[:1]],
                                         np.r_[b.directions, b.directions[:1]],
                                         np.r_[b.values, b.values[:1]], b.wait, b.binary)
        for name in ("soak-b", "soak-c"):
            s.models[name].exists = False
        with pytest.raises(soak.SoakFailure, match=message):
            s.check(c)


def test_checks_pass_on_an_untampered_model(soak, tmp_path):
    with _served(soak, tmp_path) as (s, c, m):
        rng = np.random.default_rng(1)
        for _ in range(3):
            s.upload(c, rng, "soak-a", m)
        s.check(c)
        assert s.fig.n['checked_batches'] == 3


def test_short_soak_on_postgresql_with_two_replicas(soak, capsys):
    """The soak on PostgreSQL: two replicas, each killed with kill -9 every cycle."""
    assert soak.main(["--postgres", "--cycles", "3", "--seed", "5"]) == 0
    out = capsys.readouterr().out
    assert "cycles (kill -9 / restart): 3 (PostgreSQL, 2 replicas)" in out
    assert int(re.search(r"acknowledged: (\d+)", out).group(1)) > 0
    assert "lost: 0" in out
