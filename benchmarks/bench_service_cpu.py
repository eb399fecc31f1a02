"""The server's CPU seconds for a fixed amount of work: two checkouts compared
in one run, alternating (a restructuring's "speed unchanged" check).

Wall-clock figures (``bench_service.py``) move by 2x on a shared 2-core
machine whatever the code does; the CPU time the server process spends on a
fixed workload moves much less. For each checkout given (a directory holding
a built venv, e.g. this one and an older commit checked out beside it), a real
server (``.venv/bin/python -m flatserve.service``) on a free loopback port with
a temporary data directory, a one-chart field of ``--samples`` paper rays, then
the workload of ``bench_service.py``, counted in the server's CPU time
(``/proc/<pid>/stat``: user + system):

1. ``--big`` queries of 100,000 rays (``.npy`` in and out)
2. ``--uploads`` ``.npy`` uploads of 20,000 rays acknowledged before indexing
   (``wait=false``), each awaited (its insert counted too)
3. ``--small`` small queries (1-8 rays, JSON) on the lean path, and as many
   through the FastAPI route (``?via=fastapi``)

Rounds alternate the checkouts; medians per checkout and the ratio.

    .venv/bin/python benchmarks/bench_service_cpu.py . ../flatserve-before [--rounds 3]
"""
from __future__ import annotations

import argparse
import io
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np
import orjson

import timing  # noqa: F401  (the repository root on sys.path, for tests.harness)
from tests.harness.process import free_port

TICK = os.sysconf("SC_CLK_TCK")


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICK  # utime, stime


def paper_rays(rng, n):
    eyes = rng.uniform([-1, -1, -4.5], [1, 1, -1.5], (n, 3))
    screen = np.c_[rng.uniform(-1, 1, (n, 2)), np.zeros(n)]
    return eyes, screen - eyes


def npz(**arrays) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def wait_ready(http: httpx.Client, proc, timeout=120.0) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if proc.poll() is not None:
            raise RuntimeError(f"server exited with {proc.returncode}")
        try:
            if http.get("/readyz").status_code == 200:
                return
        except httpx.TransportError:
            pass
        time.sleep(0.1)
    raise RuntimeError("server not ready")


def one_round(checkout: Path, args, rng_seed: int) -> dict[str, float]:
    rng = np.random.default_rng(rng_seed)
    port = free_port()
    with tempfile.TemporaryDirectory() as tmp:
        env = {**os.environ, "FLATSERVE_SNAPSHOT_EVERY": "0", "OPENBLAS_NUM_THREADS": "1"}
        proc = subprocess.Popen([str(checkout / ".venv/bin/python"), "-m", "flatserve.service",
                                 "--port", str(port), "--data-dir", tmp],
                                cwd=tmp, env=env, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
        try:
            with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=300) as http:
                wait_ready(http, proc)
                r = http.post("/v1/fields", json={"name": "bench", "k": 1, "d": 3, "channels": 3,
                                                  "basis": {"kind": "tangent_simplex"}})
                r.raise_for_status()
                o, v = paper_rays(rng, args.samples)
                r = http.post("/v1/fields/bench/samples?wait=true",
                              content=npz(origins=o, directions=v, values=rng.uniform(size=(args.samples, 3))),
                              headers={"content-type": "application/x-npz"})
                r.raise_for_status()
                out = {}
                qo, qv = paper_rays(rng, 100_000)
                big = npz(origins=qo, directions=qv)
                t0 = cpu_seconds(proc.pid)
                for _ in range(args.big):
                    r = http.post("/v1/fields/bench/query", content=big,
                                  headers={"content-type": "application/x-npz",
                                           "accept": "application/x-npy"})
                    r.raise_for_status()
                out["big query"] = (cpu_seconds(proc.pid) - t0) / args.big
                t0 = cpu_seconds(proc.pid)
                for i in range(args.uploads):
                    uo, uv = paper_rays(rng, 20_000)
                    r = http.post("/v1/fields/bench/samples?wait=false",
                                  content=npz(origins=uo, directions=uv,
                                              values=rng.uniform(size=(20_000, 3))),
                                  headers={"content-type": "application/x-npz"})
                    r.raise_for_status()
                    pos = r.json()["position"]
                    r = http.post(f"/v1/fields/bench/query?min_position={pos}",
                                  json={"origins": [[0, 0, -3]], "directions": [[0, 0, 1]]})
                    r.raise_for_status()
                out["upload (ack + insert)"] = (cpu_seconds(proc.pid) - t0) / args.uploads
                bodies = []
                for i in range(64):
                    m = int(rng.integers(1, 9))
                    so, sv = paper_rays(rng, m)
                    bodies.append(orjson.dumps({"origins": so.tolist(), "directions": sv.tolist()}))
                for label, query in (("small query, lean path", ""),
                                     ("small query, FastAPI route", "?via=fastapi")):
                    t0 = cpu_seconds(proc.pid)
                    for i in range(args.small):
                        r = http.post(f"/v1/fields/bench/query{query}", content=bodies[i % 64],
                                      headers={"content-type": "application/json"})
                        r.raise_for_status()
                    out[label] = (cpu_seconds(proc.pid) - t0) / args.small
                return out
        finally:
            proc.kill()
            proc.wait()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkouts", nargs=2, type=Path, help="ours, then the one to compare with")
    ap.add_argument("--samples", type=int, default=20_000)
    ap.add_argument("--big", type=int, default=10)
    ap.add_argument("--uploads", type=int, default=5)
    ap.add_argument("--small", type=int, default=3000)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    ours, peer = (c.resolve() for c in args.checkouts)
    got: dict[Path, list[dict]] = {ours: [], peer: []}
    for rnd in range(args.rounds):
        for c in (peer, ours) if rnd % 2 == 0 else (ours, peer):
            got[c].append(one_round(c, args, rnd))
            print(f"round {rnd + 1} {c.name}: " + ", ".join(
                f"{k} {v * 1e3:.2f} ms" for k, v in got[c][-1].items()), flush=True)
    print(f"\nserver CPU per operation, median of {args.rounds} (load {os.getloadavg()[0]:.1f}); "
          f"ours = {ours}, peer = {peer}")
    for key in got[ours][0]:
        a = statistics.median(r[key] for r in got[ours])
        b = statistics.median(r[key] for r in got[peer])
        print(f"  {key:28s} peer {b * 1e3:9.3f} ms | ours {a * 1e3:9.3f} ms | ours/peer {a / b:5.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
