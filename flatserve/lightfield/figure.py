"""Reproduce the paper's Fig. 11: the bunny light field, novel views, baselines.

``flatserve lightfield paper-figure --out DIR`` calls :func:`paper_figure`:

1. the bunny sampled on a fixed n x n screen with random eyes (Sec. 5.2);
   the samples as an image (``samples.png``, Fig. 11 left);
2. a Field with the paper's basis (tangent simplex around the z-axis, scale
   0.01); samples outside the chart are counted;
3. the same samples in two baselines: the two-plane parameterisation with
   scipy's LinearNDInterpolator, and the nearest sample in the embedded
   coordinates (k-d tree);
4. views at 250^2 with 4x supersampling: four focal lengths, and eye +
   screen turned by +-10 degrees about x, y and z; each reconstruction is
   written beside its ground truth, plus a contact sheet;
5. a table (Markdown + JSON): PSNR (and SSIM) on each method's covered
   pixels and on the pixels all methods cover, coverage, timings, and the
   winner per view (PSNR on the common pixels).

All methods see the same samples and the same rays; none is tuned per view.
"""
from __future__ import annotations

import json
import math
import os
import platform
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .baselines import NearestEmbedded, TwoPlane
from .camera import Camera
from .quality import psnr, ssim
from .render import frame_from_rays, render_field, render_truth
from .sampling import BASIS_SCALE, ProgressBar, build_field, bunny_scene, sample_scene

__all__ = ["paper_views", "paper_figure", "to_uint8", "save_png", "contact_sheet", "fmt", "DEFAULT_N", "FULL_N",
           "FOCALS", "ROTATION_DEG", "ROTATION_FOCAL", "METHODS"]

#: Quick default: 300^2 = 90k samples: looks like the bunny; the two-plane
#: baseline (scipy Delaunay in R^4) stays within minutes.
DEFAULT_N = 300
#: The paper's 1000^2 samples.
FULL_N = 1000
#: Four focal lengths (eye at z = -3; 3 sees exactly the sampling screen).
FOCALS = (3.0, 4.0, 5.0, 6.0)
#: Eye and screen turned by +- this many degrees about each major axis.
ROTATION_DEG = 10.0
#: Focal length of the turned views.
ROTATION_FOCAL = 4.0
#: Methods in the table, ours first.
METHODS = ("field", "two_plane", "nearest")
_LABEL = {"field": "affine basis + Delaunay (ours)", "two_plane": "two-plane + LinearND",
          "nearest": "nearest (embedded)", "truth": "ground truth"}


def paper_views(width: int = 250, supersample: int = 4, focals=FOCALS, degrees: float = ROTATION_DEG,
                rot_focal: float = ROTATION_FOCAL) -> list[tuple[str, Camera]]:
    """The views of Fig. 11: focal lengths, then +-degrees about x, y, z.

    Returns
    -------
    list of (name, Camera)
    """
    base = Camera(width=width, height=width, supersample=supersample)
    views = [(f"focal{f:g}", base.with_(focal=float(f))) for f in focals]
    rot = base.with_(focal=float(rot_focal))
    for axis in "xyz":
        for sign in (+1, -1):
            views.append((f"rot{axis}{'+' if sign > 0 else '-'}{degrees:g}", rot.rotated(axis, sign * degrees)))
    return views


def to_uint8(image: np.ndarray) -> np.ndarray:
    """(H, W, C) float in [0, 1] -> (H, W) or (H, W, 3) uint8."""
    a = np.clip(np.nan_to_num(np.asarray(image, dtype=np.float64)), 0.0, 1.0)
    a = np.round(a * 255).astype(np.uint8)
    return a[..., 0] if a.ndim == 3 and a.shape[2] == 1 else a


def save_png(path, image: np.ndarray) -> None:
    """Write an image in [0, 1] as an 8-bit grey or RGB PNG."""
    from PIL import Image

    Image.fromarray(to_uint8(image)).save(path)


def _side_by_side(a: np.ndarray, b: np.ndarray, gap: int = 4) -> np.ndarray:
    H, W, C = a.shape
    out = np.ones((H, 2 * W + gap, C))
    out[:, :W], out[:, W + gap:] = a, b
    return out


def contact_sheet(path, rows: list[tuple[str, list[np.ndarray]]], columns: list[str]) -> None:
    """Grid of images with row and column labels.

    Parameters
    ----------
    path : path-like
        PNG to write.
    rows : list of (label, images)
        Images (H, W, C) in [0, 1], all of one shape, one per column.
    columns : list of str
        Column labels.
    """
    from PIL import Image, ImageDraw

    H, W = rows[0][1][0].shape[:2]
    mode = "L" if rows[0][1][0].shape[2] == 1 else "RGB"
    left, top, pad = 190, 22, 4
    sheet = Image.new(mode, (left + len(columns) * (W + pad), top + len(rows) * (H + pad)), color=255 if mode == "L" else (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    ink = 0 if mode == "L" else (0, 0, 0)
    for j, name in enumerate(columns):
        draw.text((left + j * (W + pad) + 4, 5), name, fill=ink)
    for i, (label, images) in enumerate(rows):
        y = top + i * (H + pad)
        draw.text((6, y + H // 2 - 6), label, fill=ink)
        for j, img in enumerate(images):
            sheet.paste(Image.fromarray(to_uint8(img)), (left + j * (W + pad), y))
    sheet.save(path)


@dataclass
class _Method:
    image: np.ndarray
    covered: np.ndarray
    seconds: float
    split: dict


def fmt(x, digits=2) -> str:
    """A number for a table: ``digits`` decimals, "–" for None/NaN, "∞" for inf."""
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "–"
    if isinstance(x, float) and math.isinf(x):
        return "∞"
    return f"{x:.{digits}f}"


def paper_figure(out, *, n: int = DEFAULT_N, seed: int = 0, width: int = 250, supersample: int = 4,
                 channels: int = 1, baselines: bool = True, log=print, progress: bool = True) -> dict:
    """Build the bunny light field and write Fig. 11's views, baselines and table.

    Parameters
    ----------
    out : path-like
        Output directory (created).
    n : int
        Samples on an n x n screen (the paper: 1000).
    seed : int
        Seed of the eye positions.
    width : int
        Rendered views are width x width pixels.
    supersample : int
        Rays per pixel.
    channels : int
        1 (grey, as in the paper) or 3 (RGB).
    baselines : bool
        Also run the two-plane and nearest baselines.
    log : callable(str)
        Where progress text goes.
    progress : bool
        Show a progress bar while the field builds.

    Returns
    -------
    dict
        The JSON table (also written to ``out/results.json``).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    scene = bunny_scene(channels)
    samples, values = sample_scene(scene, n, seed)
    timings["sample_and_shade"] = time.perf_counter() - t0
    save_png(out / "samples.png", values.reshape(n, n, channels))
    log(f"sampled {n}x{n} = {n * n:,} rays of the bunny in {timings['sample_and_shade']:.2f} s -> samples.png")

    bar = ProgressBar("building field", n * n) if progress else None
    field, stats = build_field(samples.origins, samples.directions, values, progress=bar)
    timings["field_build"] = stats.seconds
    log(f"field: {stats.accepted:,} samples accepted, {stats.rejected:,} outside the basis chart "
        f"({stats.rejected / stats.samples:.2%}), {field.nsamples:,} vertices, built in {stats.seconds:.1f} s")

    two_plane = nearest = None
    if baselines:
        log(f"two-plane baseline: scipy Delaunay of {n * n:,} points in R^4 (slow for large n) ...")
        two_plane = TwoPlane(samples.origins, samples.directions, values)
        timings["two_plane_build"] = two_plane.build_seconds
        log(f"two-plane baseline built in {two_plane.build_seconds:.1f} s")
        nearest = NearestEmbedded.from_field(field)
        timings["nearest_build"] = nearest.build_seconds

    views = paper_views(width, supersample)
    rows = []
    sheet = {m: [] for m in ("truth",) + METHODS}
    for name, cam in views:
        truth = render_truth(scene, cam)
        methods: dict[str, _Method] = {}
        fr = render_field(field, cam, fill=scene.background)
        methods["field"] = _Method(fr.image, fr.covered, fr.seconds, dict(fr.timings))
        if baselines:
            o, d = cam.rays()
            t = time.perf_counter()
            v, ins = two_plane(o, d)
            img, cov = frame_from_rays(cam, v, ins, scene.background)
            methods["two_plane"] = _Method(img, cov, time.perf_counter() - t, {})
            t = time.perf_counter()
            cp = fr.chart  # the same chart coordinates the field used
            v = np.full((o.shape[0], channels), np.nan)
            v[cp.ok] = nearest(cp.points)
            img, cov = frame_from_rays(cam, v, cp.ok, scene.background)
            # nearest needs the coordinates too: charge it the same time
            methods["nearest"] = _Method(img, cov, time.perf_counter() - t + cp.seconds,
                                         {"coordinates": cp.seconds})
        common = np.logical_and.reduce([m.covered for m in methods.values()])
        row = {"view": name, "camera": cam.to_dict(), "common_coverage": float(common.mean()), "methods": {}}
        for key, m in methods.items():
            row["methods"][key] = {
                "coverage": float(m.covered.mean()),
                "psnr": psnr(m.image, truth.image, m.covered),
                "psnr_common": psnr(m.image, truth.image, common),
                "ssim_common": ssim(m.image, truth.image, common),
                "seconds": m.seconds,
                "split": m.split,
            }
            save_png(out / f"{name}_{key}.png", _side_by_side(m.image, truth.image))
            sheet[key].append(m.image)
        sheet["truth"].append(truth.image)
        save_png(out / f"{name}_truth.png", truth.image)
        scores = {k: v["psnr_common"] for k, v in row["methods"].items()}
        row["winner"] = max(scores, key=lambda k: -math.inf if math.isnan(scores[k]) else scores[k])
        rows.append(row)
        msg = ", ".join(f"{k} {fmt(v['psnr_common'])} dB" for k, v in row["methods"].items())
        log(f"{name:>10}: {msg}; coverage (ours) {row['methods']['field']['coverage']:.1%}; "
            f"winner: {row['winner']}")

    contact_sheet(out / "contact_sheet.png",
                   [(_LABEL[k], sheet[k]) for k in ("field",) + (METHODS[1:] if baselines else ()) + ("truth",)],
                   [name for name, _ in views])
    result = {
        "paper": "Affine bases for affine spaces, Sec. 5.2 / Fig. 11",
        "n": n, "samples": n * n, "seed": seed, "width": width, "supersample": supersample,
        "channels": channels, "basis_scale": BASIS_SCALE,
        "accepted": stats.accepted, "rejected_outside_chart": stats.rejected,
        "vertices": field.nsamples, "timings": timings,
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
        "views": rows,
        "wins": {m: sum(r["winner"] == m for r in rows) for m in (METHODS if baselines else ("field",))},
    }
    (out / "results.json").write_text(json.dumps(result, indent=2, default=float))
    (out / "results.md").write_text(_markdown(result))
    log(f"wins: {result['wins']}; wrote {out}/contact_sheet.png, results.md, results.json")
    return result


def _markdown(res: dict) -> str:
    methods = list(res["views"][0]["methods"]) if res["views"] else []
    lines = [
        "# Fig. 11 reproduction: bunny light field",
        "",
        f"{res['samples']:,} samples ({res['n']}^2 screen, seed {res['seed']}); "
        f"{res['rejected_outside_chart']:,} outside the basis chart; {res['vertices']:,} vertices. "
        f"Views {res['width']}^2, {res['supersample']} rays per pixel.",
        "",
        "PSNR in dB against the mesh's ground truth on the pixels **all** methods cover "
        "(own-coverage PSNR in brackets); coverage = share of pixels whose rays are all "
        "inside the chart and the samples' hull; time = seconds per frame.",
        "",
        "| view | " + " | ".join(f"{_LABEL[m]}: PSNR [own] / SSIM / coverage / time" for m in methods)
        + " | common coverage | winner |",
        "|---|" + "---|" * len(methods) + "---|---|",
    ]
    for r in res["views"]:
        cells = []
        for m in methods:
            x = r["methods"][m]
            cells.append(f"{fmt(x['psnr_common'])} [{fmt(x['psnr'])}] / {fmt(x['ssim_common'], 3)} / "
                         f"{x['coverage']:.1%} / {x['seconds']:.2f}")
        lines.append(f"| {r['view']} | " + " | ".join(cells) + f" | {r['common_coverage']:.1%} | {r['winner']} |")
    lines += ["", "Wins: " + ", ".join(f"{_LABEL[m]} {c}" for m, c in res["wins"].items()), "",
              "Build times (s): " + ", ".join(f"{k} {v:.1f}" for k, v in res["timings"].items()), ""]
    return "\n".join(lines)
