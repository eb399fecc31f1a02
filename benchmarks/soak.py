"""Durability soak: kill -9 a real server over and over and check that nothing
acknowledged is ever lost and nothing unacknowledged is ever half-stored.

Each cycle starts ``python -m flatserve.service`` on a temporary data dir, checks
the stored state against what the client was told (below), retries every batch
that was in flight at the last kill with the same idempotency key, then runs a
random workload for a random fraction of a second and kills the server with
SIGKILL in the middle of it. The workload mixes uploads (``wait=true`` and
``wait=false``, JSON and ``.npy``), idempotent retries of acknowledged batches,
snapshots, and deletes and re-creates of fields; fields are kept small so that a
restart takes about a second.

After every restart, for every field:

* every acknowledged batch is stored (``GET /v1/fields/{name}/batches``) with the
  rows sent and the accepted count of its acknowledgement;
* every other stored batch is one that was in flight at a kill, with exactly the
  rows sent (never half a batch), and no idempotency key is stored twice;
* once indexed, the field holds the sum of the accepted counts;
* a delete or create in flight at a kill happened entirely or not at all;
* a retry of a batch that was stored is answered as a replay with the stored
  count, and a retry of one that was not stores it once.

Any violation stops the run with a message and exit status 1.

With ``--postgres`` the log lives in a throwaway PostgreSQL cluster
(``tests/harness/pgcluster.py``) and ``--replicas N`` (default 2 there) servers,
each with a data directory of its own, follow it: in each cycle every field's
writes go to one replica chosen at random (the replicas append to the log at
once), every replica is killed with ``kill -9`` at the kill, and after the
restart the checks (and the retries of batches in flight) run on one replica,
in turn, while every other replica must hold the same indexed samples.

    python benchmarks/soak.py [--cycles 100] [--seconds 900] [--seed 0]
    python benchmarks/soak.py --postgres [--replicas 2] [--cycles 100]
"""
from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
import threading
import time
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

try:
    import timing  # noqa: F401  (run as a script: the repository root on sys.path, for tests.harness)
except ModuleNotFoundError:  # imported by its test, which has the root on sys.path
    pass
from flatserve.client import Client
from tests.harness.process import ServerProcess
from flatserve.service.status import FieldNotFoundError

FIELDS = ("soak-a", "soak-b", "soak-c")


class SoakFailure(AssertionError):
    """A durability check failed."""


@dataclass
class Batch:
    """One upload as sent: its arrays and how it was sent."""

    origins: np.ndarray
    directions: np.ndarray
    values: np.ndarray
    wait: bool
    binary: bool

    @property
    def rows(self) -> int:
        return len(self.origins)


@dataclass
class FieldModel:
    """What the client knows of one field.

    Attributes
    ----------
    exists : bool or None
        None: a create or a delete was in flight at a kill.
    acked : dict
        Idempotency key -> (rows, accepted) of every acknowledged batch.
    inflight : dict
        Idempotency key -> :class:`Batch` sent without an acknowledgement.
    """

    exists: bool | None = False
    acked: dict = field(default_factory=dict)
    inflight: dict = field(default_factory=dict)
    sent: dict = field(default_factory=dict)  # key -> Batch, every batch sent


@dataclass
class Figures:
    """What a soak did: ``n`` counts cycles, batches sent, acknowledged (deferred,
    as JSON), in flight at a kill (stored), retries (replayed, stored), replays
    of acknowledged batches, snapshots, deletes, creates and batches checked."""

    n: Counter = field(default_factory=Counter)
    restart_s: list = field(default_factory=list)
    elapsed: float = 0.0


def rays(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Rays from eyes in [-1,1]^2 x [-4.5,-1.5] to the screen z = 0."""
    eyes = rng.uniform([-1, -1, -4.5], [1, 1, -1.5], (n, 3))
    screen = np.c_[rng.uniform(-1, 1, (n, 2)), np.zeros(n)]
    return eyes, screen - eyes


class Server(ServerProcess):
    """A server whose failures to start are soak failures."""

    def __init__(self, data_dir: str, log_path: str, snapshot_every: int,
                 database_url: str | None = None):
        extra = {"database_url": database_url} if database_url else {}
        super().__init__(data_dir, log_path, log_level="warning", snapshot_every=snapshot_every,
                         **extra)

    def wait_ready(self, timeout: float = 120.0, interval: float = 0.02) -> None:
        try:
            super().wait_ready(timeout, interval)
        except (RuntimeError, TimeoutError) as exc:
            raise SoakFailure(str(exc)) from None


class Soak:
    def __init__(self, args: argparse.Namespace, data_dir: str, log_path: str,
                 database_url: str | None = None):
        self.args = args
        self.data_dir = data_dir
        self.log_path = log_path
        self.database_url = database_url
        self.replicas = max(1, getattr(args, "replicas", None) or 1)
        self.rng = np.random.default_rng(args.seed)
        self.models = {name: FieldModel() for name in FIELDS}
        self.fig = Figures()
        self.nkey = 0

    # -- checks after a restart -------------------------------------------------
    def check(self, c: Client) -> None:
        for name, m in self.models.items():
            try:
                stored = c.batches(name)
            except FieldNotFoundError:
                if m.exists is True:
                    raise SoakFailure(f"field {name!r} lost") from None
                m.exists = False
                m.acked.clear()
                m.inflight.clear()
                continue
            if m.exists is False:
                raise SoakFailure(f"field {name!r} exists although its delete was acknowledged")
            m.exists = True
            keys = [b["idempotency_key"] for b in stored]
            if len(keys) != len(set(keys)):
                raise SoakFailure(f"field {name!r}: a batch is stored twice")
            by_key = {b["idempotency_key"]: b for b in stored}
            for key, (rows, accepted) in m.acked.items():
                b = by_key.get(key)
                if b is None:
                    raise SoakFailure(f"field {name!r}: acknowledged batch {key} lost")
                if (b["rows"], b["accepted"]) != (rows, accepted):
                    raise SoakFailure(f"field {name!r}: batch {key} stored with rows "
                                      f"{b['rows']}, accepted {b['accepted']}; acknowledged "
                                      f"rows {rows}, accepted {accepted}")
            for key, b in by_key.items():
                if key in m.acked:
                    continue
                sent = m.inflight.get(key)
                if sent is None:
                    raise SoakFailure(f"field {name!r}: stored batch {key} was never sent "
                                      "to this field")
                if b["rows"] != sent.rows:
                    raise SoakFailure(f"field {name!r}: batch {key} half-stored: {b['rows']} "
                                      f"of {sent.rows} rows")
            self.fig.n['checked_batches'] += len(stored)
            self.retry_inflight(c, name, m, by_key)
            stored = c.batches(name)  # every response known now (a retry recomputes a lost one)
            if {b["idempotency_key"]: (b["rows"], b["accepted"]) for b in stored} != m.acked:
                raise SoakFailure(f"field {name!r}: stored batches differ from the "
                                  "acknowledged ones after the retries")
            info = c.wait_indexed(name, timeout=120)
            total = sum(b["accepted"] for b in stored)
            if info["nsamples"] != total:
                raise SoakFailure(f"field {name!r}: {info['nsamples']} samples indexed, the "
                                  f"stored batches accepted {total}")

    def retry_inflight(self, c: Client, name: str, m: FieldModel, by_key: dict) -> None:
        """Retry every batch in flight at the kill with its key: a stored one is
        replayed with the stored count, an unstored one is stored once."""
        for key, b in list(m.inflight.items()):
            res = c.upload_rays(name, b.origins, b.directions, b.values, idempotency_key=key,
                                wait=b.wait, binary=b.binary)
            if key in by_key:
                self.fig.n['inflight_stored'] += 1
                known = by_key[key]["accepted"]  # None: the response was not stored yet
                if not res["replayed"] or known not in (None, res["accepted"]):
                    raise SoakFailure(f"field {name!r}: retry of stored batch {key} answered "
                                      f"{res}, stored {by_key[key]}")
                self.fig.n['retries_replayed'] += 1
            else:
                if res["replayed"]:
                    raise SoakFailure(f"field {name!r}: retry of unstored batch {key} "
                                      "answered as a replay")
                self.fig.n['retries_stored'] += 1
            m.acked[key] = (b.rows, res["accepted"])
            del m.inflight[key]

    # -- the workload between two kills ------------------------------------------
    def workload(self, urls: list[str], rng: np.random.Generator, stop: threading.Event) -> None:
        clients = [Client(u, retries=0, timeout=30) for u in urls]
        # each field's writes go to one replica this cycle (a replica answers a field
        # only once it has applied the field's create: no waits needed), so the
        # replicas append to the one log at once; its retries after the kill reach
        # whichever replica runs the checks
        via = {name: clients[int(rng.integers(len(clients)))] for name in FIELDS}
        try:
            for name, m in self.models.items():
                if not m.exists:
                    m.exists = None
                    via[name].create_field(name, channels=1)
                    m.exists = True
                    self.fig.n['creates'] += 1
            while not stop.is_set():
                op = rng.uniform()
                name = FIELDS[int(rng.integers(len(FIELDS)))]
                m = self.models[name]
                c = via[name]
                if op < 0.80:
                    self.upload(c, rng, name, m)
                elif op < 0.88 and m.acked:
                    key = list(m.acked)[int(rng.integers(len(m.acked)))]
                    b = m.sent[key]
                    res = c.upload_rays(name, b.origins, b.directions, b.values,
                                        idempotency_key=key, wait=b.wait, binary=b.binary)
                    if not res["replayed"] or res["accepted"] != m.acked[key][1]:
                        raise SoakFailure(f"retry of acknowledged {key}: {res}")
                    self.fig.n['replays_of_acked'] += 1
                elif op < 0.95:
                    c.snapshot(name)
                    self.fig.n['snapshots'] += 1
                elif m.acked or m.inflight:
                    m.exists = None  # in flight
                    c.delete_field(name)
                    m.exists = False
                    m.acked.clear()
                    m.inflight.clear()
                    self.fig.n['deletes'] += 1
                    m.exists = None
                    c.create_field(name, channels=1)
                    m.exists = True
                    self.fig.n['creates'] += 1
        except SoakFailure:
            raise
        except Exception:
            return  # the server was killed under us
        finally:
            for one in clients:
                one.close()

    def upload(self, c: Client, rng: np.random.Generator, name: str, m: FieldModel) -> None:
        n = int(rng.integers(20, self.args.max_rows))
        o, v = rays(rng, n)
        b = Batch(o, v, rng.uniform(size=(n, 1)), wait=bool(rng.integers(2)),
                  binary=bool(rng.uniform() < 0.7))
        key = f"b{self.nkey}"
        self.nkey += 1
        m.inflight[key] = b
        m.sent[key] = b
        self.fig.n['sent'] += 1
        res = c.upload_rays(name, o, v, b.values, idempotency_key=key, wait=b.wait,
                            binary=b.binary)
        if res["replayed"]:
            raise SoakFailure(f"new batch {key} answered as a replay")
        del m.inflight[key]
        m.acked[key] = (n, res["accepted"])
        self.fig.n['acked'] += 1
        self.fig.n['acked_deferred'] += not res["indexed"]
        self.fig.n['acked_json'] += not b.binary

    # -- the run -------------------------------------------------------------------
    def _start(self) -> list[Server]:
        """Start the replicas (one without PostgreSQL), each on its own data dir."""
        if self.database_url is None:
            return [Server(self.data_dir, self.log_path, self.args.snapshot_every)]
        return [Server(os.path.join(self.data_dir, f"r{i}"), self.log_path,
                       self.args.snapshot_every, self.database_url)
                for i in range(self.replicas)]

    def _check_all(self, servers: list[Server]) -> None:
        """The checks on one replica (chosen in turn); every other one must hold the
        same indexed samples of every field."""
        first = servers[self.fig.n['cycles'] % len(servers)]
        with Client(first.url, retries=0, timeout=60) as c:
            self.check(c)
            want = {name: c.describe(name)["nsamples"] for name, m in self.models.items()
                    if m.exists}
        for srv in servers:
            if srv is first:
                continue
            with Client(srv.url, retries=0, timeout=60) as c:
                for name, n in want.items():
                    got = c.wait_indexed(name, timeout=120)["nsamples"]
                    if got != n:
                        raise SoakFailure(f"field {name!r}: replica {srv.url} holds {got} "
                                          f"samples, replica {first.url} {n}")

    def run(self) -> Figures:
        t0 = time.monotonic()
        while self.fig.n['cycles'] < self.args.cycles:
            if time.monotonic() - t0 > self.args.seconds:
                print(f"time budget of {self.args.seconds} s reached", flush=True)
                break
            servers = self._start()
            try:
                ts = time.monotonic()
                for srv in servers:
                    srv.wait_ready()
                self.fig.restart_s.append(time.monotonic() - ts)
                self._check_all(servers)
                stop = threading.Event()
                failure: list[BaseException] = []

                def work():
                    try:
                        self.workload([srv.url for srv in servers],
                                      np.random.default_rng(self.rng.integers(2**63)), stop)
                    except BaseException as exc:  # a failed check: report it after the kill
                        failure.append(exc)

                t = threading.Thread(target=work)
                t.start()
                time.sleep(float(self.rng.uniform(0.05, self.args.max_work)))
            finally:
                for i in self.rng.permutation(len(servers)):
                    servers[i].kill9()
            stop.set()
            t.join(timeout=120)
            if failure:
                raise failure[0]
            self.fig.n['inflight_at_kill'] += sum(len(m.inflight) for m in self.models.values())
            self.fig.n['cycles'] += 1
            if self.fig.n['cycles'] % 10 == 0:
                print(f"cycle {self.fig.n['cycles']}: {self.fig.n['acked']} batches acknowledged, "
                      f"{time.monotonic() - t0:.0f} s", flush=True)
        # a last restart: everything checked once more, nothing left in flight
        servers = self._start()
        try:
            for srv in servers:
                srv.wait_ready()
            self._check_all(servers)
        finally:
            for srv in servers:
                srv.kill9()
        self.fig.elapsed = time.monotonic() - t0
        return self.fig


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cycles", type=int, default=100, help="kill -9 / restart cycles")
    p.add_argument("--seconds", type=float, default=900.0,
                   help="time budget: no new cycle starts after it")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-rows", type=int, default=400, help="most rows in one batch")
    p.add_argument("--max-work", type=float, default=0.8,
                   help="most seconds of workload before a kill")
    p.add_argument("--snapshot-every", type=int, default=1500,
                   help="the server's background snapshot interval (samples)")
    p.add_argument("--data-dir", help="data directory (default: a temporary one, removed)")
    p.add_argument("--postgres", action="store_true",
                   help="the log in a throwaway PostgreSQL cluster (Debian's postgresql)")
    p.add_argument("--replicas", type=int, default=None,
                   help="servers following the log (with --postgres; default 2)")
    args = p.parse_args(argv)
    if args.replicas is not None and not args.postgres:
        p.error("--replicas needs --postgres")
    if args.postgres and args.replicas is None:
        args.replicas = 2
    tmp = None if args.data_dir else tempfile.mkdtemp(prefix="flatserve-soak-")
    data_dir = args.data_dir or os.path.join(tmp, "data")
    log_path = os.path.join(tmp or data_dir, "server.log")
    os.makedirs(data_dir, exist_ok=True)
    pg = None
    if args.postgres:
        from tests.harness.pgcluster import PgCluster

        pg = PgCluster().start()
    soak = Soak(args, data_dir, log_path, pg.create_database("soak") if pg else None)
    try:
        fig = soak.run()
    except SoakFailure as exc:
        print(f"FAILED after {soak.fig.n['cycles']} cycles: {exc}", file=sys.stderr)
        with open(log_path, errors="replace") as fh:
            sys.stderr.write(fh.read()[-4000:])
        return 1
    finally:
        if pg is not None:
            pg.close()
        if tmp:
            shutil.rmtree(tmp, ignore_errors=True)
    rs = fig.restart_s
    where = (f"PostgreSQL, {args.replicas} replicas" if args.postgres else "SQLite, 1 server")
    print(f"cycles (kill -9 / restart): {fig.n['cycles']} ({where})")
    print(f"batches sent: {fig.n['sent']}; acknowledged: {fig.n['acked']} ({fig.n['acked_deferred']} with "
          f"wait=false, {fig.n['acked_json']} as JSON); in flight at a kill: {fig.n['inflight_at_kill']} "
          f"({fig.n['inflight_stored']} of them stored, retried as replays: {fig.n['retries_replayed']}; "
          f"stored by their retry: {fig.n['retries_stored']})")
    print(f"retries of acknowledged batches (replayed): {fig.n['replays_of_acked']}; snapshots: "
          f"{fig.n['snapshots']}; deletes: {fig.n['deletes']}; creates: {fig.n['creates']}")
    print(f"batches checked after restarts: {fig.n['checked_batches']}; lost: 0; half-stored: 0; "
          f"stored twice: 0")
    print(f"restart to ready: median {statistics.median(rs):.2f} s, max {max(rs):.2f} s; "
          f"total {fig.elapsed:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
