"""Real captures over HTTP: importing a capture, and rendering a held-out view of it (issue 37).

Synthetic forward-facing captures are written to a temporary folder: pinhole
cameras (``PinholeCamera.look_at``) with eyes on a grid in the plane z = -3,
each looking at the origin; each image is the ground-truth shade of the ray
through each pixel's centre (``blocks_scene(channels=3).shade``), written as a
NeRF capture (``write_nerf``, 8-bit PNG), one image in memory at a time.

1. Import into a server: ``Client.import_capture`` of the import capture into
   a real ``flatserve serve`` (a free loopback port, a temporary data dir, no
   snapshots; a fresh server for each import), a field of the capture's
   ``field_options``; rays/s of the whole import (read, upload, and the
   server's indexing: ``wait=True``). The peer: the same rays, read into
   memory first (``capture_rays``), sent by ``Client.upload_rays`` (the
   client's own upload path) into a field of the same options; only the upload
   is timed. Each runs in a child process; its peak memory is the growth of
   the child's peak RSS (``VmHWM``, reset through ``/proc/self/clear_refs``
   after its modules, connection and capture headers are loaded) from its RSS
   then; the peer's counts the rays it holds. The server's peak RSS and its
   cells per vertex are printed too. A guard kills the server when its RSS
   passes ``--server-max-rss`` (the machine is shared): that import is then
   reported as stopped, with the rays acknowledged by then.
2. The importer alone, at the issue's capture size (100 photos of 200 x 150,
   3,000,000 rays): the same two calls against a stub server (another
   process; it answers ``/v1/limits`` as the real server does and acknowledges
   each batch after reading it, storing nothing), so that the importer's rays/s
   and peak memory can be measured at a size whose field does not fit this
   machine. Ours once more (untimed) with a full ``gc.collect()`` after each
   batch: the peak without the request bodies left in httpx's reference cycles.
3. Render: a held-out 512 x 384 view (supersample 1, eye off the grid) of a
   field made by the importer from the render capture, through
   ``Client.render`` (npy), ms per frame, median of ``--runs`` after a warm-up.
   The peer: the two-plane parameterisation of the same capture's rays (camera
   plane z = -3, focal plane z = 0) in a ``scipy.spatial.cKDTree``; the view's
   rays looked up with k = 4 neighbours and inverse-distance weights
   (``workers=-1``), median of as many; its time counts the view's two-plane
   coordinates, the query and the weighting (the tree's build is printed
   apart). PSNR of both against the scene's ground truth.

A table at the end (the peer's figure, ours, their ratio) and the load average
before and after.

    .venv/bin/python benchmarks/bench_capture.py            # sizes a 23 GB machine holds (~9 min)
    .venv/bin/python benchmarks/bench_capture.py --full     # the issue's sizes (a server needs ~100 GiB)
    .venv/bin/python benchmarks/bench_capture.py --quick    # smoke run (seconds)
"""
from __future__ import annotations

import argparse
import io
import json
import math
import multiprocessing as mp
import os
import re
import resource
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from timing import median_time  # first: the repository root on sys.path (tests.harness)
from flatserve.client import Client
from flatserve.lightfield.baselines import IDW_POWER, TWO_PLANE_Z, two_plane_coordinates
from flatserve.lightfield.camera import PinholeCamera
from flatserve.lightfield.capture import capture_rays, field_options, read_capture, write_nerf
from flatserve.lightfield.quality import psnr
from flatserve.lightfield.sampling import blocks_scene
from tests.harness.process import ServerProcess, free_port

EYE_Z = -3.0
#: Half the extent of the eyes' grid in x and y (the grid spans [-X, X] x [-Y, Y]).
GRID_HALF = (0.9, 0.675)
#: Focal length in units of the image's width (a field of view of 31 degrees across).
FOCAL_PER_WIDTH = 1.8
#: The held-out view's eye: between the render capture's eyes, off its grid.
HELD_EYE = (0.13, -0.07, EYE_Z)
#: Neighbours of the two-plane peer.
K_NEAREST = 4
#: Per size: (photos, width, height) of the capture imported into a server, of the
#: importer-alone capture, of the render capture, and the held-out view's (width, height).
SIZES = {
    "full": ((100, 200, 150), (100, 200, 150), (64, 144, 108), (512, 384)),
    "default": ((16, 100, 75), (100, 200, 150), (16, 100, 75), (512, 384)),
    "quick": ((2, 24, 18), (4, 40, 30), (4, 24, 18), (64, 48)),
}
#: Seconds a server waits to apply a committed upload before answering 503 (its default,
#: 60 s, is shorter than one batch's insert here).
APPLY_WAIT_S = 3600
MiB = 1 << 20
GiB = 1 << 30


def rig(photos: int, width: int, height: int) -> list[PinholeCamera]:
    """``photos`` cameras on a grid of eyes in the plane z = EYE_Z (cols x rows, as square
    as ``photos`` allows), row by row, looking at the origin."""
    cols = max(1, math.isqrt(photos))
    while photos % cols:
        cols -= 1
    cols, rows = max(cols, photos // cols), min(cols, photos // cols)
    xs = np.linspace(-GRID_HALF[0], GRID_HALF[0], cols) if cols > 1 else np.zeros(1)
    ys = np.linspace(-GRID_HALF[1], GRID_HALF[1], rows) if rows > 1 else np.zeros(1)
    f = FOCAL_PER_WIDTH * width
    return [PinholeCamera.look_at((x, y, EYE_Z), fx=f, fy=f, cx=width / 2, cy=height / 2,
                                  width=width, height=height)
            for y in ys for x in xs]


def photograph(scene, cam: PinholeCamera) -> np.ndarray:
    """(H, W, C): the ground-truth shade of the ray through each pixel's centre."""
    o, d = cam.rays()
    return scene.shade(o, d).reshape(cam.height, cam.width, -1)


def write_capture(root: Path, scene, cameras: list[PinholeCamera]) -> int:
    """A NeRF capture of ``cameras`` in ``root``, one image in memory at a time; its rays.

    ``write_nerf`` takes every image at once: each frame is written by its own call
    (the image and a one-frame ``transforms.json``), whose frame entries are then
    gathered into the capture's ``transforms.json`` (the intrinsics, shared, at
    the top)."""
    doc: dict = {}
    frames = []
    for k, cam in enumerate(cameras):
        pose = write_nerf(root, [cam], [photograph(scene, cam)], names=[f"frame_{k:04d}"], bits=8)
        one = json.loads(pose.read_text(encoding="utf-8"))
        frames += one.pop("frames")
        if doc and one != doc:
            raise AssertionError(f"frame {k}: intrinsics differ from the first frame's")
        doc = one
    (root / "transforms.json").write_text(json.dumps({**doc, "frames": frames}, indent=2) + "\n",
                                          encoding="utf-8")
    return sum(c.width * c.height for c in cameras)


def options_summary(options: dict) -> str:
    """``field_options`` without the arrays of a basis (their sizes instead)."""
    def short(v):
        if isinstance(v, dict):
            return {k: short(x) for k, x in v.items()}
        if isinstance(v, list) and len(v) > 4:
            return f"<{len(v)} rows>"
        return v
    return json.dumps(short(options))


# ------------------------------------------------------------------ memory
def _status_kib(key: str, pid: int | str = "self") -> int | None:
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith(key + ":"):
                    return int(line.split()[1])
    except OSError:
        pass
    return None


def _peak_start() -> tuple[int, bool]:
    """(RSS in bytes now, whether the peak was reset to it): the baseline of :func:`_peak_growth`."""
    reset = False
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")  # resets VmHWM to the current RSS (Linux >= 4.0)
        reset = True
    except OSError:
        pass
    rss = _status_kib("VmRSS")
    if rss is None:  # no /proc: the lifetime peak (ru_maxrss, KiB on Linux)
        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss * 1024, reset


def _peak_growth(start: tuple[int, bool]) -> int:
    """Bytes the peak RSS rose above the baseline since :func:`_peak_start`."""
    rss0, reset = start
    hwm = _status_kib("VmHWM") if reset else None
    if hwm is None:
        hwm = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return max(0, hwm * 1024 - rss0)


# ------------------------------------------------------------------ child processes
def _warm(c: Client, capture: str) -> None:
    """What both children do before their baseline: the connection, the server's
    limits, Pillow's plugins and the capture's headers (not the import's memory)."""
    from PIL import Image

    Image.init()
    c.limits()
    read_capture(capture)


def _import_child(url: str, field: str, capture: str, done, q, collect: bool = False) -> None:
    """Ours: ``Client.import_capture`` of the capture; (seconds, report, peak growth).
    ``done`` (a shared integer) follows the rays acknowledged. ``collect``: a full
    ``gc.collect()`` after each batch (a sent request's body stays in reference
    cycles of httpx's request objects until the garbage collector's oldest
    generation is collected, which may be many batches later)."""
    import gc

    def progress(rays, total):
        done.value = rays
        if collect:
            gc.collect()

    try:
        with Client(url, timeout=3600) as c:
            _warm(c, capture)
            start = _peak_start()
            t0 = time.perf_counter()
            rep = c.import_capture(field, capture, progress=progress)
            dt = time.perf_counter() - t0
            q.put(("ok", dt, rep, _peak_growth(start)))
    except BaseException as exc:  # noqa: BLE001 (reported to the parent)
        q.put(("error", f"{type(exc).__name__}: {exc}"))


def _import_child_collected(url: str, field: str, capture: str, done, q) -> None:
    """:func:`_import_child` with ``collect``."""
    _import_child(url, field, capture, done, q, collect=True)


def _upload_child(url: str, field: str, capture: str, done, q) -> None:
    """The peer: the capture's rays read into memory, then ``Client.upload_rays`` of them;
    (upload seconds, report, peak growth while holding the rays and uploading them)."""
    try:
        with Client(url, timeout=3600) as c:
            _warm(c, capture)
            start = _peak_start()
            cap = read_capture(capture)
            o, d, v = capture_rays(cap)
            c.create_field(field, **field_options(cap))
            t0 = time.perf_counter()
            rep = c.upload_rays(field, o, d, v)
            dt = time.perf_counter() - t0
            done.value = int(rep["accepted"])
            q.put(("ok", dt, rep, _peak_growth(start)))
    except BaseException as exc:  # noqa: BLE001
        q.put(("error", f"{type(exc).__name__}: {exc}"))


def in_child(target, *args):
    """Run ``target(*args, done, queue)`` in a fresh (spawned) process:
    ``(what it put on the queue, or None and the error, rays done)``."""
    ctx = mp.get_context("spawn")
    q, done = ctx.Queue(), ctx.Value("q", 0)
    p = ctx.Process(target=target, args=(*args, done, q))
    p.start()
    try:
        out = q.get()
    finally:
        p.join()
    if out[0] != "ok":
        return None, out[1], done.value
    return out[1:], None, done.value


# ------------------------------------------------------------------ servers
class Guarded:
    """A fresh ``flatserve serve`` (free loopback port, its own data dir under ``tmp``,
    no snapshots), killed if its RSS passes ``max_rss`` bytes; ``tripped`` then holds
    that RSS, ``peak`` the highest RSS seen."""

    def __init__(self, tmp: Path, tag: str, max_rss: int):
        script = Path(sys.executable).with_name("flatserve")
        command = ([str(script), "serve"] if script.exists()
                   else [sys.executable, "-m", "flatserve.cli", "serve"])
        data = tmp / f"data-{tag}"
        data.mkdir()
        self.srv = ServerProcess(data, tmp / f"server-{tag}.log", log_level="warning", command=command,
                                 snapshot_every=0, max_simplices=2**62, apply_wait_timeout=APPLY_WAIT_S)
        self.url = self.srv.url
        self.max_rss, self.tripped, self.peak = max_rss, None, 0
        self._stop = threading.Event()
        try:
            self.srv.wait_ready(120)
            with Client(self.url) as c:
                self.limits = c.limits()
        except BaseException:
            self.srv.kill9()
            raise
        self.t0, self.after = time.monotonic(), None
        self._thread = threading.Thread(target=self._watch, daemon=True)
        self._thread.start()

    def _watch(self) -> None:
        while not self._stop.wait(0.2):
            rss = _status_kib("VmRSS", self.srv.proc.pid)
            if rss is None:
                return
            self.peak = max(self.peak, rss * 1024)
            if rss * 1024 > self.max_rss:
                self.tripped, self.after = rss * 1024, time.monotonic() - self.t0
                try:
                    os.killpg(self.srv.proc.pid, 9)
                except OSError:
                    pass
                return

    def hwm(self) -> int:
        """The server's peak RSS so far (bytes)."""
        return max(self.peak, (_status_kib("VmHWM", self.srv.proc.pid) or 0) * 1024)

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self.srv.kill9()


def _stub_server(port: int, limits: dict, ready) -> None:
    """A stand-in for the service that stores nothing: ``/v1/limits`` answers ``limits``,
    a field create is acknowledged, an upload is read whole (its ``.npy`` header gives
    the rows) and acknowledged as accepted and indexed."""
    from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

    counts: dict[str, int] = {}
    lock = threading.Lock()

    class Handler(BaseHTTPRequestHandler):
        protocol_version = "HTTP/1.1"

        def log_message(self, *args):
            pass

        def _json(self, status: int, doc) -> None:
            body = json.dumps(doc).encode()
            self.send_response(status)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def do_GET(self):
            if self.path.startswith("/v1/limits"):
                return self._json(200, limits)
            return self._json(404, {"detail": "not found"})

        def do_POST(self):
            body = self.rfile.read(int(self.headers.get("Content-Length", 0)))
            path = self.path.split("?", 1)[0]
            if path == "/v1/fields":
                doc = json.loads(body)
                return self._json(201, {**doc, "nsamples": 0})
            m = re.fullmatch(r"/v1/fields/([^/]+)/samples", path)
            if not m:
                return self._json(404, {"detail": "not found"})
            fh = io.BytesIO(body)
            version = np.lib.format.read_magic(fh)
            read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                           else np.lib.format.read_array_header_2_0)
            shape = read_header(fh)[0]
            with lock:
                counts[m.group(1)] = counts.get(m.group(1), 0) + shape[0]
                k = total = counts[m.group(1)]
            return self._json(200, {"accepted": shape[0], "rejected": [], "reasons": [], "duplicates": 0,
                                    "nsamples": total, "batch": k, "indexed": True, "position": k})

    httpd = ThreadingHTTPServer(("127.0.0.1", port), Handler)
    ready.set()
    httpd.serve_forever()


# ------------------------------------------------------------------ the two-plane peer
class TwoPlaneNearest:
    """Two-plane coordinates (z = -3 and z = 0) of sample rays in a cKDTree; a ray's value
    is the inverse-distance weighted mean of its ``k`` nearest samples'."""

    PLANES = (TWO_PLANE_Z[1], TWO_PLANE_Z[0])

    def __init__(self, origins, directions, values, k: int = K_NEAREST):
        from scipy.spatial import cKDTree

        t0 = time.perf_counter()
        st = two_plane_coordinates(origins, directions, self.PLANES)
        keep = np.all(np.isfinite(st), axis=1)
        self.tree = cKDTree(st[keep])
        self.values = np.asarray(values, np.float64)[keep]
        self.k = k
        self.build_seconds = time.perf_counter() - t0

    def __call__(self, origins, directions) -> np.ndarray:
        st = two_plane_coordinates(origins, directions, self.PLANES)
        ok = np.all(np.isfinite(st), axis=1)
        out = np.full((st.shape[0], self.values.shape[1]), np.nan)
        dist, idx = self.tree.query(st[ok], k=self.k, workers=-1)
        w = 1.0 / np.maximum(dist, 1e-12) ** IDW_POWER
        w /= w.sum(axis=1, keepdims=True)
        out[ok] = np.einsum("nk,nkc->nc", w, self.values[idx])
        return out


# ------------------------------------------------------------------ main
def mib(x: float) -> str:
    return f"{x / MiB:,.1f} MiB"


def gib(x: float) -> str:
    return f"{x / GiB:,.2f} GiB"


def capture_line(label: str, cams: list[PinholeCamera], n: int, C: int) -> str:
    return (f"  {label}: {len(cams)} photos of {cams[0].width}x{cams[0].height} = {n:,} rays "
            f"({mib(n * (6 + C) * 8)} as float64 rays and values)")


def run_imports(label: str, capture: Path, n: int, runs: int, make_server, C: int, rows: list,
                stored: bool = True) -> None:
    """Ours and the peer, ``runs`` times interleaved, each on a fresh server from
    ``make_server(tag)`` (``stored``: a real one, else the stub); their figures printed
    and added to ``rows`` as ``label``."""
    res = {"ours": [], "peer": []}
    stopped = {}
    for r in range(runs):
        for who, target in (("ours", _import_child), ("peer", _upload_child)):
            if who in stopped:
                continue
            srv = make_server(f"{who}{r}")
            try:
                field = f"capture-{who}{r}"  # (the stub counts rays per field)
                out, err, done = in_child(target, srv.url, field, str(capture))
                if out is not None:
                    dt, rep, grow = out
                    assert rep["nsamples"] == n, rep
                    info = None
                    if isinstance(srv, Guarded):
                        with Client(srv.url, timeout=600) as c:
                            info = c.describe(field)
                        info["server_hwm"] = srv.hwm()
                    res[who].append((dt, grow, rep, info))
                    print(f"  {label}, {who} run {r + 1}: {dt:.1f} s ({n / dt:,.0f} rays/s), importer's peak "
                          f"memory +{mib(grow)}" + (f", server peak RSS {gib(info['server_hwm'])}" if info else ""),
                          file=sys.stderr, flush=True)
                elif isinstance(srv, Guarded) and srv.tripped:
                    stopped[who] = (srv.tripped, srv.after, done)
                else:
                    raise RuntimeError(f"{label}, {who}: {err}")
            finally:
                srv.close()
    print(f"{label}: {n:,} rays (median of {runs}{', a fresh server each' if stored else ''}):")
    for who in ("ours", "peer"):
        call = ("Client.import_capture (read + upload" if who == "ours"
                else "Client.upload_rays of the rays in memory (upload")
        call += " + the server's indexing, wait=True)" if stored else ", acknowledged unstored)"
        if who in stopped:
            rss, after, done = stopped[who]
            print(f"   {who}  {call}: STOPPED after {after:.0f} s, the server's RSS passed {gib(rss)} "
                  f"(--server-max-rss) with {done:,} of {n:,} rays acknowledged")
            continue
        dt = statistics.median(x[0] for x in res[who])
        grow = statistics.median(x[1] for x in res[who])
        extra = ""
        info = res[who][-1][3]
        if info:
            extra = (f"; server peak RSS {gib(info['server_hwm'])} ({info['server_hwm'] / n / 1024:.1f} KiB per ray), "
                     f"{info['nsimplex']:,} cells, {info['nsimplex'] / max(info['nvertices'], 1):.0f} per vertex, "
                     f"{info.get('ncharts') or 1} chart(s)")
        batches = f" in {res[who][-1][2]['batches']} batch(es)" if who == "ours" else ""
        print(f"   {who}  {call}: {dt:.1f} s, {n / dt:,.0f} rays/s{batches}; importer's peak memory "
              f"+{mib(grow)}{' (holding all the rays)' if who == 'peer' else ''}{extra}")
    total = n * (6 + C) * 8
    if stopped:
        rows += [(f"{label}: rays/s ({n:,} rays)", "-", "-", None),
                 (f"{label}: importer peak memory", "-", "-", None)]
        return
    t_o, t_p = (statistics.median(x[0] for x in res[w]) for w in ("ours", "peer"))
    m_o, m_p = (statistics.median(x[1] for x in res[w]) for w in ("ours", "peer"))
    print(f"   ratio (ours / peer): {t_p / t_o:.2f}x rays/s, {m_o / m_p:.2f}x memory; the capture as float64 "
          f"rays + values is {mib(total)}")
    rows += [(f"{label}: rays/s ({n:,} rays)", f"{n / t_p:,.0f}", f"{n / t_o:,.0f}", t_p / t_o),
             (f"{label}: importer peak memory (capture {mib(total)})", mib(m_p), mib(m_o), m_o / m_p)]
    if not stored:  # what the importer itself holds: cyclic garbage collected after each batch
        srv = make_server("collect")
        try:
            out, err, _ = in_child(_import_child_collected, srv.url, "capture-collect", str(capture))
        finally:
            srv.close()
        if out is None:
            print(f"   ours  with gc.collect() after each batch: not measured ({err})")
            return
        m_t = out[2]
        print(f"   ours  again, gc.collect() after each batch (untimed): importer's peak memory +{mib(m_t)}")
        rows.append((f"{label}: importer peak memory, gc.collect() after each batch", mib(m_p), mib(m_t),
                     m_t / m_p))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    size = ap.add_mutually_exclusive_group()
    size.add_argument("--full", action="store_true",
                      help="the issue's sizes: import 100 x 200x150 (3M rays) into the server, render from "
                           "64 x 144x108 (995,328 rays), view 512x384")
    size.add_argument("--quick", action="store_true", help="a smoke run of a few seconds (tiny captures)")
    ap.add_argument("--import-photos", type=int, help="photographs of the capture imported into a server")
    ap.add_argument("--import-size", type=int, nargs=2, metavar=("W", "H"), help="their size")
    ap.add_argument("--alone-photos", type=int, help="photographs of the importer-alone capture")
    ap.add_argument("--alone-size", type=int, nargs=2, metavar=("W", "H"), help="their size")
    ap.add_argument("--render-photos", type=int, help="photographs of the render capture")
    ap.add_argument("--render-size", type=int, nargs=2, metavar=("W", "H"), help="their size")
    ap.add_argument("--view", type=int, nargs=2, metavar=("W", "H"), help="the held-out view's size")
    ap.add_argument("--runs", type=int, default=5, help="renders and two-plane lookups (medians)")
    ap.add_argument("--import-runs", type=int, default=1,
                    help="imports and peer uploads into a server, interleaved (medians)")
    ap.add_argument("--alone-runs", type=int, default=3, help="the same against the stub (medians)")
    ap.add_argument("--server-max-rss", type=float, default=6.0,
                    help="GiB: a server whose RSS passes this is killed and its import reported as stopped")
    args = ap.parse_args(argv)
    which = "full" if args.full else "quick" if args.quick else "default"
    (ip, iw, ih), (ap_, aw, ah), (rp, rw, rh), (vw, vh) = SIZES[which]
    ip, (iw, ih) = args.import_photos or ip, args.import_size or (iw, ih)
    ap_, (aw, ah) = args.alone_photos or ap_, args.alone_size or (aw, ah)
    rp, (rw, rh) = args.render_photos or rp, args.render_size or (rw, rh)
    vw, vh = args.view or (vw, vh)
    runs = 2 if args.quick and args.runs == 5 else args.runs
    alone_runs = 1 if args.quick and args.alone_runs == 3 else args.alone_runs
    max_rss = int(args.server_max_rss * GiB)

    load0 = os.getloadavg()
    print(f"load average before: {load0[0]:.2f} {load0[1]:.2f} {load0[2]:.2f} ({os.cpu_count()} cores)")
    scene = blocks_scene(channels=3)
    C = scene.channels
    tmpdir = tempfile.TemporaryDirectory(prefix="flatserve-bench-capture-")
    tmp = Path(tmpdir.name)
    rows: list = []
    stub = None
    try:
        # ---------------------------------------------------------- captures
        t0 = time.perf_counter()
        imp_cams, alone_cams, ren_cams = rig(ip, iw, ih), rig(ap_, aw, ah), rig(rp, rw, rh)
        n_imp = write_capture(tmp / "import", scene, imp_cams)
        n_alone = write_capture(tmp / "alone", scene, alone_cams)
        n_ren = write_capture(tmp / "render", scene, ren_cams)
        print(f"captures written in {time.perf_counter() - t0:.1f} s (NeRF, 8-bit PNG, blocks scene, eyes on "
              f"a grid in z = {EYE_Z:g} looking at the origin):")
        print(capture_line("import into a server", imp_cams, n_imp, C))
        print(capture_line("importer alone", alone_cams, n_alone, C))
        print(capture_line("render", ren_cams, n_ren, C))
        print(f"  field_options: {options_summary(field_options(read_capture(tmp / 'import')))}")

        # ---------------------------------------------------------- 1. into a server
        limits = {}

        def real(tag):
            srv = Guarded(tmp, tag, max_rss)
            limits.update(srv.limits)  # the stub answers the same
            return srv

        run_imports("1. import into flatserve serve", tmp / "import", n_imp, args.import_runs, real, C, rows)

        # ---------------------------------------------------------- 2. the importer alone
        ctx = mp.get_context("spawn")
        ready, port = ctx.Event(), free_port()
        stub = ctx.Process(target=_stub_server, args=(port, limits, ready), daemon=True)
        stub.start()
        if not ready.wait(60):
            raise RuntimeError("the stub server did not start")

        class Stub:
            url = f"http://127.0.0.1:{port}"

            def close(self):
                pass

        run_imports("2. importer alone (stub server)", tmp / "alone", n_alone, alone_runs,
                    lambda tag: Stub(), C, rows, stored=False)

        # ---------------------------------------------------------- 3. render
        f = FOCAL_PER_WIDTH * vw
        view = PinholeCamera.look_at(HELD_EYE, fx=f, fy=f, cx=vw / 2, cy=vh / 2, width=vw, height=vh)
        vo, vd = view.rays()
        truth = scene.shade(vo, vd).reshape(vh, vw, C)
        print(f"3. held-out view {vw}x{vh} (supersample 1, {view.nrays:,} rays, eye {HELD_EYE}) of the render "
              f"capture ({n_ren:,} rays):")
        srv = Guarded(tmp, "render", max_rss)
        t_render = build = None
        try:
            out, err, done = in_child(_import_child, srv.url, "render", str(tmp / "render"))
            if out is None:
                if not srv.tripped:
                    raise RuntimeError(f"render field: {err}")
                print(f"   ours  STOPPED after {srv.after:.0f} s building the field: the server's RSS passed "
                      f"{gib(srv.tripped)} "
                      f"(--server-max-rss) with {done:,} of {n_ren:,} rays acknowledged")
            else:
                build, rep, _ = out
                assert rep["nsamples"] == n_ren, rep
                with Client(srv.url, timeout=3600) as c:
                    info = c.describe("render")
                    c.render("render", view)  # warm-up
                    t_render, img = median_time(lambda: c.render("render", view, format="npy"), runs)
                hwm = srv.hwm()
        finally:
            srv.close()
        if t_render is not None:
            assert img.shape == (vh, vw, C), img.shape
            cov = np.isfinite(img).all(axis=2)
            print(f"   ours  field by Client.import_capture built in {build:.1f} s ({n_ren / build:,.0f} rays/s; "
                  f"{info['nsimplex']:,} cells, server peak RSS {gib(hwm)}); Client.render (npy) "
                  f"{t_render * 1e3:.1f} ms per frame (median of {runs} after a warm-up); "
                  f"PSNR {psnr(img, truth, cov):.2f} dB on its {cov.mean():.1%} coverage")
        o, d, v = capture_rays(read_capture(tmp / "render"))
        peer = TwoPlaneNearest(o, d, v)
        del o, d, v
        t_tp, tp_img = median_time(lambda: peer(vo, vd), runs)
        tp_img = tp_img.reshape(vh, vw, C)
        tp_cov = np.isfinite(tp_img).all(axis=2)
        print(f"   peer  two-plane (z = {TwoPlaneNearest.PLANES[0]:g}, z = {TwoPlaneNearest.PLANES[1]:g}) cKDTree, "
              f"k = {K_NEAREST}, inverse-distance weights, workers=-1: {t_tp * 1e3:.1f} ms per frame (median of "
              f"{runs}; tree built in {peer.build_seconds:.2f} s from the rays in memory); "
              f"PSNR {psnr(tp_img, truth, tp_cov):.2f} dB")
        if t_render is not None:
            print(f"   ratio (ours / peer): {t_render / t_tp:.2f}x ms per frame")
            rows += [(f"3. render ms/frame ({view.nrays:,} rays, field of {n_ren:,})", f"{t_tp * 1e3:.1f}",
                      f"{t_render * 1e3:.1f}", t_render / t_tp),
                     ("3. field build s (peer: cKDTree of rays in memory)", f"{peer.build_seconds:.2f}",
                      f"{build:.1f}", build / peer.build_seconds)]
        else:
            rows += [("3. render ms/frame", f"{t_tp * 1e3:.1f}", "-", None)]
    finally:
        if stub is not None:
            stub.kill()
            stub.join()
        tmpdir.cleanup()

    load1 = os.getloadavg()
    print()
    print("| measurement | peer | ours | ours / peer |")
    print("|---|---|---|---|")
    for what, p, o_, ratio in rows:
        print(f"| {what} | {p} | {o_} | {'-' if ratio is None else f'{ratio:.2f}x'} |")
    print(f"\nload average before: {load0[0]:.2f} {load0[1]:.2f} {load0[2]:.2f}; "
          f"after: {load1[0]:.2f} {load1[1]:.2f} {load1[2]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
