"""Captures against the classic light fields: ``flatserve lightfield capture-figure``.

Synthetic captures of a scene (a photograph per camera: each pixel the scene's
shade of the ray through its centre), a field of their rays over the atlas a
capture gets (:func:`flatserve.lightfield.rig.capture_atlas`, what the importer
creates), held-out cameras between the rig's rendered by pose and compared
with their true photographs, against the classic baseline of the rig's kind
with its settings chosen in its favour (the best median over the held-out
views):

* ``forward``: a forward-facing rig (LLFF-like), 40 cameras on an 8 x 5 grid
  in the plane z = -3 (jittered by a tenth of the spacing), each looking at
  the origin, 96 x 72 pixels; 4 held-out cameras at the centres of grid cells.
  Baseline: the two-plane light field's ``k`` nearest rays
  (:class:`~flatserve.lightfield.baselines.TwoPlaneNearest`, camera plane
  z = -3), ``k`` and the focal plane swept.
* ``sphere``: 62 cameras all around (a Fibonacci sphere of radius 3, looking
  at the origin), 64 x 64 pixels; 6 held-out cameras in random directions.
  Baseline: the two-sphere ``k`` nearest rays
  (:class:`~flatserve.lightfield.baselines.TwoSphere`), ``k`` and the sphere's
  radius swept.
* ``hemisphere``: NeRF-synthetic-like, 60 cameras over the upper hemisphere,
  80 x 80 pixels; 6 held-out cameras above the horizon. Baseline: as
  ``sphere``.

Writes a contact sheet per rig and scene (held-out views: ours, the baseline,
the truth), ``capture-results.md`` (PSNR per view, the difference, the
median) and ``capture-results.json``.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InvalidInputError
from .camera import PinholeCamera, fibonacci_sphere
from .quality import psnr, ssim

__all__ = ["RIGS", "SCENES", "synthetic_rig", "photograph", "capture_depth", "capture_field", "compare_rig",
           "capture_figure", "TWO_PLANE_SWEEP", "TWO_SPHERE_SWEEP"]

#: The synthetic rigs: name -> (what it is, its sizes).
RIGS = {
    "forward": "forward-facing, 40 cameras (8 x 5) of 96 x 72 pixels, 4 held out",
    "sphere": "all around, 62 cameras of 64 x 64 pixels, 6 held out",
    "hemisphere": "NeRF-synthetic-like, 60 cameras over the upper hemisphere, 80 x 80 pixels, 6 held out",
}
#: Scenes of the figure (flatserve.lightfield.sampling).
SCENES = ("blocks", "bunny")
#: The two-plane baseline's settings tried: focal planes (z) and neighbours.
TWO_PLANE_SWEEP = ((-0.3, -0.2, -0.1, 0.0, 0.1, 0.2), (1, 2, 4, 6, 8))
#: The two-sphere baseline's settings tried: radii and neighbours.
TWO_SPHERE_SWEEP = ((0.5, 0.6, 0.8, 1.0), (1, 2, 4, 6, 8, 12))
#: Distance of every rig's eyes from the origin (the forward rig's plane z = -3).
RIG_DISTANCE = 3.0


def _camera(eye, width: int, height: int, focal: float, up=(0.0, 1.0, 0.0)) -> PinholeCamera:
    """Looking at the origin; ``focal`` in half image widths (the image spans
    [-1, 1] at distance ``focal``, as :class:`~flatserve.lightfield.Camera`)."""
    f = focal * width / 2
    return PinholeCamera.look_at(eye, (0.0, 0.0, 0.0), up, fx=f, fy=f, cx=width / 2, cy=height / 2,
                                 width=width, height=height)


def _around(e: np.ndarray, width: int, height: int, focal: float) -> PinholeCamera:
    up = (0.0, 1.0, 0.0) if abs(e[1]) < 0.95 else (0.0, 0.0, 1.0)
    return _camera(RIG_DISTANCE * e, width, height, focal, up)


def synthetic_rig(name: str, *, seed: int = 0, size: float = 1.0
                  ) -> tuple[list[PinholeCamera], list[PinholeCamera]]:
    """The cameras of a synthetic rig and its held-out cameras (:data:`RIGS`).

    Parameters
    ----------
    name : {"forward", "sphere", "hemisphere"}
    seed : int
        Of the jitter and of the held-out directions.
    size : float
        Image sides times this (0.5: a quick run).

    Returns
    -------
    cameras, held : list of PinholeCamera
    """
    if name not in RIGS:
        raise InvalidInputError(f"rig: expected one of {', '.join(RIGS)}, got {name!r}", "rig")
    if not (isinstance(size, (int, float)) and 0 < size <= 4):
        raise InvalidInputError(f"size: expected a factor in (0, 4], got {size!r}", "size")
    rng = np.random.default_rng(seed)
    side = lambda n: max(8, int(round(n * size)))  # noqa: E731
    if name == "forward":
        W, H, focal = side(96), side(72), 3.0
        xs, ys = np.linspace(-0.7, 0.7, 8), np.linspace(-0.4, 0.4, 5)
        step = xs[1] - xs[0]
        cams = [_camera((x + rng.uniform(-0.1, 0.1) * step, y + rng.uniform(-0.1, 0.1) * step,
                         -RIG_DISTANCE), W, H, focal) for y in ys for x in xs]
        held = [_camera((x, y, -RIG_DISTANCE), W, H, focal)
                for x, y in [(-0.4, -0.1), (0.0, 0.1), (0.2, -0.3), (-0.2, 0.3)]]
        return cams, held
    upper = name == "hemisphere"
    W = side(80) if upper else side(64)
    focal = 3.0 if upper else 3.5
    if upper:
        e = fibonacci_sphere(128)
        e = e[e[:, 1] > 0.05][:60]
    else:
        e = fibonacci_sphere(62)
    held = []
    while len(held) < 6:
        p = rng.normal(size=3)
        p /= np.linalg.norm(p)
        if not upper or p[1] >= 0.1:
            held.append(_around(p, W, W, focal))
    return [_around(p, W, W, focal) for p in e], held


def photograph(scene, camera: PinholeCamera) -> np.ndarray:
    """The camera's true photograph: each pixel the scene's shade of its centre's ray (H, W, C)."""
    o, d = camera.rays()
    return camera.resolve(scene.shade(o, d))


def _rays(scene, cameras):
    O, D, V = [], [], []
    for c in cameras:
        o, d = c.rays()
        O.append(o)
        D.append(d)
        V.append(scene.shade(o, d))
    return np.concatenate(O), np.concatenate(D), np.concatenate(V)


def capture_depth(cameras, photographs, origins, directions, rig) -> np.ndarray:
    """The depth channel of a synthetic capture's rays (one per pixel, camera by
    camera), as the importer computes it (:func:`flatserve.lightfield.depth.depth_map`).

    Returns
    -------
    (n, 1) float64
    """
    from .depth import depth_map, depth_values

    views: dict = {}  # each photograph's small grey view made once, not once per neighbour
    t = np.concatenate([depth_map(i, cameras, lambda j: photographs[j], center=rig.center,
                                  views=views).reshape(-1) for i in range(len(cameras))])
    return depth_values(origins, directions, t, rig.center)[:, None]


def capture_field(cameras, origins, directions, values, *, chunk: int = 100_000):
    """A field of a capture's rays over the atlas the importer gives it
    (:func:`flatserve.lightfield.rig.capture_atlas`).

    Returns
    -------
    field : flatserve.atlas_field.AtlasField
    seconds : float
    """
    from ..atlas_field import AtlasField
    from ..flats import Flats
    from .rig import capture_atlas

    t0 = time.perf_counter()
    field = AtlasField(capture_atlas(cameras), channels=values.shape[1])
    for lo in range(0, len(origins), chunk):
        field.add(Flats.from_rays(origins[lo:lo + chunk], directions[lo:lo + chunk]),
                  values[lo:lo + chunk])
    field.settle()
    return field, time.perf_counter() - t0


@dataclass
class _Baseline:
    name: str
    settings: dict
    images: list


def _best_baseline(rig: str, origins, directions, values, held, truths) -> _Baseline:
    """The baseline of the rig's kind with the settings of the best median PSNR."""
    from .baselines import TwoPlaneNearest, TwoSphere

    best, best_median = None, -np.inf
    if rig == "forward":
        planes, ks = TWO_PLANE_SWEEP
        tries = [("two-plane nearest rays", {"focal_z": z, "k": k},
                  lambda z=z, k=k: TwoPlaneNearest(origins, directions, values,
                                                   planes=(-RIG_DISTANCE, z), k=k))
                 for z in planes for k in ks]
    else:
        radii, ks = TWO_SPHERE_SWEEP
        tries = [("two-sphere nearest rays", {"radius": r, "k": k},
                  lambda r=r, k=k: TwoSphere(origins, directions, values, radius=r, k=k))
                 for r in radii for k in ks]
    for name, settings, make in tries:
        b = make()
        images = []
        for cam in held:
            v, ok = b(*cam.rays(), workers=-1)
            images.append(cam.resolve(np.where(ok[:, None], v, 0.0)))
        med = float(np.median([psnr(i, t) for i, t in zip(images, truths)]))
        if med > best_median:
            best, best_median = _Baseline(name, settings, images), med
    return best


def compare_rig(rig: str, scene, *, seed: int = 0, size: float = 1.0, progress=None) -> dict:
    """Ours against the rig's baseline on its held-out views.

    Returns
    -------
    dict
        ``rig``, ``rays``, ``cameras``, ``unit``, ``charts``, ``copies``,
        ``build_seconds``, ``baseline`` (name, settings), ``views`` (per
        held-out view: ``ours``, ``baseline`` PSNR and SSIM, ``coverage``),
        ``median_gain_db``, ``worst_gain_db``, and the images (``ours_images``,
        ``baseline_images``, ``truth_images``) for a contact sheet.
    """
    from .depth import render_guided
    from .render import render_field
    from .rig import depth_rig

    cams, held = synthetic_rig(rig, seed=seed, size=size)
    o, d, v = _rays(scene, cams)
    truths = [photograph(scene, c) for c in held]
    say = progress or (lambda *_: None)
    depth = depth_rig(cams)  # what the importer chooses for this rig
    t0 = time.perf_counter()
    if depth is not None:
        say(f"{rig}: {len(cams)} cameras: depth maps")
        photos = [photograph(scene, c) for c in cams]
        v = np.concatenate([v, capture_depth(cams, photos, o, d, depth)], axis=1)
        del photos
    depth_seconds = time.perf_counter() - t0
    say(f"{rig}: {len(cams)} cameras, {len(o):,} rays: building the field")
    field, seconds = capture_field(cams, o, d, v)
    C = truths[0].shape[2]
    plain = [render_field(field, c) for c in held]  # the field alone (colour channels)
    plain_psnr = [psnr(f.image[..., :C], t) for f, t in zip(plain, truths)]
    frames = plain if depth is None else [render_guided(field, c, depth) for c in held]
    say(f"{rig}: the baseline's settings swept")
    base = _best_baseline(rig, o, d, v[:, :C], held, truths)
    views = []
    for f, b, t, p in zip(frames, base.images, truths, plain_psnr):
        views.append({"ours": psnr(f.image[..., :C], t), "baseline": psnr(b, t), "field": p,
                      "ours_ssim": ssim(f.image[..., :C], t), "baseline_ssim": ssim(b, t),
                      "coverage": f.coverage})
    gains = np.array([x["ours"] - x["baseline"] for x in views])
    return {"rig": rig, "description": RIGS[rig], "cameras": len(cams), "rays": int(len(o)),
            "unit": field.atlas.unit, "charts": field.atlas.ncharts,
            "copies": float(field.duplication), "build_seconds": seconds,
            "render": "field" if depth is None else "depth-guided", "depth_seconds": depth_seconds,
            "baseline": {"name": base.name, "settings": base.settings}, "views": views,
            "median_gain_db": float(np.median(gains)), "worst_gain_db": float(gains.min()),
            "ours_images": [f.image[..., :C] for f in frames], "baseline_images": base.images,
            "truth_images": truths}


def capture_figure(out, *, rigs=tuple(RIGS), scenes=("blocks",), seed: int = 0, size: float = 1.0,
                   channels: int = 1, progress=None) -> list[dict]:
    """Every rig on every scene: contact sheets, ``capture-results.md`` and ``.json``.

    Returns
    -------
    list of dict
        :func:`compare_rig`'s results, without the images.
    """
    from .figure import contact_sheet
    from .sampling import blocks_scene, bunny_scene

    makers = {"blocks": blocks_scene, "bunny": bunny_scene}
    for s in scenes:
        if s not in makers:
            raise InvalidInputError(f"scene: expected one of {', '.join(SCENES)}, got {s!r}", "scene")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    results = []
    for s in scenes:
        scene = makers[s](channels=channels)
        for rig in rigs:
            res = compare_rig(rig, scene, seed=seed, size=size, progress=progress)
            res["scene"] = s
            rows = [(f"view {i}: {x['ours']:.1f} / {x['baseline']:.1f} dB", [a, b, t])
                    for i, (x, a, b, t) in enumerate(zip(res["views"], res.pop("ours_images"),
                                                         res.pop("baseline_images"),
                                                         res.pop("truth_images")))]
            contact_sheet(out / f"capture-{rig}-{s}.png", rows, ["ours", "baseline", "truth"])
            results.append(res)
    (out / "capture-results.json").write_text(json.dumps(results, indent=1))
    (out / "capture-results.md").write_text(_markdown(results))
    return results


def _markdown(results: list[dict]) -> str:
    lines = ["| rig | scene | rays | unit | charts | copies | render | baseline (settings in its favour) | "
             "ours, PSNR per held-out view (dB) | baseline | ours - baseline | median gain | worst | "
             "the field alone (median) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        b = r["baseline"]
        settings = ", ".join(f"{k} {v}" for k, v in b["settings"].items())
        ours = " ".join(f"{x['ours']:.2f}" for x in r["views"])
        base = " ".join(f"{x['baseline']:.2f}" for x in r["views"])
        gain = " ".join(f"{x['ours'] - x['baseline']:+.2f}" for x in r["views"])
        plain = float(np.median([x["field"] for x in r["views"]]))
        lines.append(f"| {r['rig']} | {r['scene']} | {r['rays']:,} | {r['unit']:.3g} | {r['charts']} | "
                     f"{r['copies']:.2f} | {r['render']} | {b['name']} ({settings}) | {ours} | {base} | {gain} | "
                     f"{r['median_gain_db']:+.2f} | {r['worst_gain_db']:+.2f} | {plain:.2f} |")
    return "\n".join(lines) + "\n"
