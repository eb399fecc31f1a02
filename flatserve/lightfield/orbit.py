"""The 360-degree light field: samples from eyes all around, views all around.

``flatserve lightfield orbit --out DIR`` calls :func:`orbit_figure`:

1. the scene (the bunny, or :func:`~flatserve.lightfield.sampling.blocks_scene`)
   sampled by ``n`` rays from eyes on a Fibonacci sphere of radius 3 around
   it, each ray through the ball of radius 1 that holds the object
   (:func:`~flatserve.lightfield.camera.sphere_samples`), coloured by the
   mesh renderer that gives the ground truth;
2. the rays in an oriented covering atlas field
   (``Atlas.covering(1, 3, oriented=True, unit=SCENE_UNIT)``: 32 charts,
   every direction; lengths in 2/3 of the scene's radius);
3. the same rays in the baseline for unstructured 360-degree data: the
   ``k = 5`` nearest sample rays in the two-sphere parameterisation,
   inverse-distance weighted (:class:`~flatserve.lightfield.baselines.TwoSphere`);
4. views all around (:func:`orbit_views`: 8 azimuths x 3 elevations, eye at
   distance 3, every ray of a view inside the sampled ball); each view is
   classified by the atlas's routing (:func:`view_charts`: does some ray get
   weight from more than one chart, i.e. straddle a chart border?), and
   optionally rendered also from a one-chart atlas centred on the view's
   axis (the same samples: the view then lies inside that one chart);
5. a contact sheet (ours, baseline, ground truth per elevation; azimuths
   across) and a table (Markdown + JSON): PSNR and SSIM against the ground
   truth on the pixels both methods cover, coverage, seconds per frame,
   winner.

Nothing is tuned per view; the baseline has its natural defaults.
"""
from __future__ import annotations

import json
import math
import os
import platform
import time
from pathlib import Path

import numpy as np

from ..atlas import UNIT_RULES, Atlas, object_unit
from ..atlas_field import AtlasField
from ..grassmann import ICOSAHEDRON_AXES
from ..errors import InvalidInputError
from ..flats import Flats
from ..options import Interpolant, choice
from .baselines import TWO_SPHERE_K, TwoSphere
from .camera import ORBIT_EYE_RADIUS, ORBIT_RADIUS, Camera
from .figure import contact_sheet, fmt
from .quality import psnr, ssim
from .render import frame_from_rays, render_field, render_truth
from .sampling import (BUILD_CHUNK, ProgressBar, blocks_scene, build_atlas_field, bunny_scene,
                       orbit_samples)

__all__ = ["orbit_views", "view_charts", "one_chart_atlas", "fine_atlas", "icosahedral_atlas", "SCENE_HALF_SIZE", "SCENE_UNIT", "orbit_figure", "SCENES", "ATLASES",
           "DEFAULT_SAMPLES", "AZIMUTHS", "ELEVATIONS", "VIEW_DISTANCE", "VIEW_FOCAL",
           "VIEW_WIDTH"]

#: Default number of sample rays of ``flatserve lightfield orbit``.
DEFAULT_SAMPLES = 200_000
#: Views: this many azimuths (evenly spaced, from 0) ...
AZIMUTHS = 8
#: ... at these elevations (degrees; the camera's pitch).
ELEVATIONS = (-30.0, 0.0, 30.0)
#: Eye distance of the views (the radius of the sample eyes' sphere).
VIEW_DISTANCE = ORBIT_EYE_RADIUS
#: Focal length of the views (units of half the image width): the corner
#: rays pass 0.82 from the centre, inside the sampled ball of radius 1, and
#: make 15.8 degrees with the view's axis (inside a chart's inner 20 degrees).
VIEW_FOCAL = 5.0
#: Default view side in pixels.
VIEW_WIDTH = 128
#: Scenes by name.
SCENES = {"bunny": bunny_scene, "blocks": blocks_scene}
#: The finer covering (:func:`fine_atlas`): its charts' radii (degrees).
FINE_RADII = (10.0, 24.0, 28.0)
_LABEL = {"ours": "atlas (ours)", "baseline": f"two-sphere {TWO_SPHERE_K}-NN", "truth": "ground truth"}


def orbit_views(width: int = VIEW_WIDTH, supersample: int = 4, *, azimuths: int = AZIMUTHS,
                elevations=ELEVATIONS, distance: float = VIEW_DISTANCE,
                focal: float = VIEW_FOCAL) -> list[tuple[str, Camera]]:
    """Views all around the origin: ``azimuths`` x ``elevations`` orbit cameras.

    Returns
    -------
    list of (name, Camera)
        Named ``az045_el+30`` (:meth:`Camera.orbit` yaw 45, pitch 30), elevation-major.
    """
    views = []
    for el in elevations:
        for i in range(int(azimuths)):
            az = 360.0 * i / azimuths
            cam = Camera.orbit(az, float(el), distance, focal=focal, width=width, height=width,
                               supersample=supersample)
            views.append((f"az{az:03.0f}_el{el:+03.0f}", cam))
    return views


def view_charts(atlas: Atlas, camera: Camera) -> dict:
    """Which charts of an atlas answer a view's rays (the atlas's query routing).

    A ray is answered by every chart whose centre is closer than
    ``atlas.trusted`` (there its blending weight is positive).

    Returns
    -------
    dict
        ``charts`` (sorted chart indices answering some ray), ``max_per_ray``
        (most charts blended at one ray), ``blended`` (share of rays answered
        by more than one chart) and ``straddles`` (some ray is: the view's
        pixels straddle a chart border).
    """
    o, d = camera.rays()
    ro = atlas.route(Flats.from_rays(o, d), atlas.trusted)
    count = np.zeros(o.shape[0], dtype=np.int64)
    for rows in ro.rows:
        count[rows] += 1
    return {"charts": [c for c, rows in enumerate(ro.rows) if rows.size],
            "max_per_ray": int(count.max(initial=0)),
            "blended": float((count > 1).mean()),
            "straddles": bool((count > 1).any())}


def one_chart_atlas(atlas: Atlas, axis) -> Atlas:
    """An atlas of one chart of ``atlas``'s kind, centred on the oriented line along ``axis``.

    Same scale, radii, unit and charts (isometric or the paper's) as ``atlas``
    (k = 1, d = 3, oriented); a view whose rays are all within ``inner`` of
    ``axis`` lies inside this one chart.
    """
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    _, V = np.linalg.eigh(np.outer(a, a))
    N = V[:, :2]  # the two eigenvectors orthogonal to a
    return Atlas(1, 3, a[None, :, None], N[None], np.zeros((1, 3)), atlas.scales[:1],
                 oriented=True, inner=atlas.inner, trusted=atlas.trusted, reach=atlas.reach,
                 unit=atlas.unit, isometric=atlas.isometric, relative=atlas.relative)


def fine_atlas(unit: float = 1.0, isometric: bool = True) -> Atlas:
    """A finer oriented covering: 42 charts, centred on the vertices of a once-subdivided icosahedron.

    Every direction is within 20.8 degrees of a centre (measured by
    :meth:`Atlas.from_centers`, which refuses centres that do not cover);
    ``inner``, ``trusted``, ``reach`` = :data:`FINE_RADII` (duplication 2.46:
    over the 2x memory budget).  For comparison with the default 32 charts.
    """
    from .mesh import icosphere

    c = icosphere(1).vertices
    inner, trusted, reach = FINE_RADII
    return Atlas.from_centers(Flats.from_rays(np.zeros_like(c), c), oriented=True, inner=inner,
                              trusted=trusted, reach=reach, unit=unit, isometric=isometric)


def icosahedral_atlas(unit: float = 1.0, isometric: bool = True) -> Atlas:
    """The former default covering: 12 charts around the 6 icosahedral axes and their
    negatives (covering radius 37.4 degrees), weight 1 up to 20 degrees, 0 from 40,
    samples in every chart closer than 44 (duplication 1.68): for comparison."""
    return Atlas.from_centers(Flats.from_rays(np.zeros((12, 3)), np.concatenate(
        [ICOSAHEDRON_AXES, -ICOSAHEDRON_AXES])), oriented=True, inner=20.0, trusted=40.0,
        reach=44.0, unit=unit, isometric=isometric)


#: Atlases of ``flatserve lightfield orbit --atlas``: name -> builder(unit, isometric).
ATLASES = {"covering": lambda unit=1.0, isometric=True: Atlas.covering(1, 3, oriented=True, unit=unit,
                                                                       isometric=isometric),
           "fine": fine_atlas, "icosahedral": icosahedral_atlas}
#: The scenes fill the unit box: half its side is their radius (about the origin).
SCENE_HALF_SIZE = 0.5
#: The atlas's unit of length for the scenes (:func:`flatserve.atlas.object_unit`
#: of their radius: 1/3).
SCENE_UNIT = object_unit(SCENE_HALF_SIZE)


def _with_reach(atlas: Atlas, reach: float | None) -> Atlas:
    """``atlas`` with samples stored up to ``reach`` degrees from each centre (None: as is)."""
    if reach is None:
        return atlas
    out = Atlas(atlas.k, atlas.d, atlas.center_A, atlas.center_N, atlas.center_r, atlas.scales,
                oriented=atlas.oriented, inner=atlas.inner, trusted=atlas.trusted, reach=reach,
                unit=atlas.unit_setting, isometric=atlas.isometric,
                relative=atlas.relative)
    out.info = dict(atlas.info)
    return out


def _scores(image, truth, covered) -> dict:
    return {"coverage": float(covered.mean()), "psnr": psnr(image, truth, covered),
            "ssim": ssim(image, truth, covered)}


def orbit_figure(out, *, n: int = DEFAULT_SAMPLES, eyes: int | None = None, seed: int = 0,
                 width: int = VIEW_WIDTH, supersample: int = 4, channels: int = 1,
                 scene: str = "bunny", atlas: str = "covering", unit: float | str | None = None,
                 isometric: bool = True, reach: float | None = None, one_chart: bool = True,
                 interpolant: str = "linear", log=print,
                 progress: bool = True) -> dict:
    """Build the 360-degree light field and write the views, the contact sheet and the table.

    Parameters
    ----------
    out : path-like
        Output directory (created).
    n : int
        Sample rays.
    eyes : int, optional
        Eyes on the sphere (default ``ceil(sqrt(n))``).
    seed : int
        Seed of the ray directions.
    width, supersample : int
        Views are width x width pixels, ``supersample`` rays per pixel.
    channels : int
        1 (grey) or 3 (RGB).
    scene : str
        A key of :data:`SCENES`.
    atlas : str
        A key of :data:`ATLASES`: the library's default covering (32
        charts), the 42-chart :func:`fine_atlas` or the former 12-chart
        :func:`icosahedral_atlas`.
    unit : float, optional
        The atlas's unit of length (:class:`flatserve.atlas.Atlas` ``unit``),
        in world units: the shift of a ray that its charts weigh as much as a
        turn of one radian (isotropic at a chart's centre).  Default
        :data:`SCENE_UNIT` (1/3: :func:`flatserve.atlas.object_unit` of the
        scenes' radius 0.5, they fill the unit box); 1: world units (the
        paper's chart); ``"data"``: chosen by the field from its first batch
        of samples (:func:`flatserve.atlas.data_unit`), as a field created
        without ``unit`` does; ``"fit"``: chosen from the first batch's values
        (:func:`flatserve.atlas_field.fitted_unit`).
    isometric : bool
        The atlas's charts warped to be isometric (:mod:`flatserve.warp`, the
        library's default); False: the paper's charts.
    reach : float, optional
        Degrees: store the samples in every chart whose centre is closer than
        this (default the atlas's own; wider helps sparse eyes and stores
        each sample in more charts).
    one_chart : bool
        Also render every view from a one-chart atlas centred on its axis
        (:func:`one_chart_atlas`, the same samples).
    interpolant : {"linear", "gradient"}
        How ours (and the one-chart comparison) interpolate
        (:func:`flatserve.lightfield.render.render_field`).
    log, progress : callable(str), bool
        Where each step's line of text goes; whether a bar shows the field's
        build.

    Returns
    -------
    dict
        The JSON table of every view (also written to ``out/results.json``).
    """
    if scene not in SCENES:
        raise InvalidInputError(f"scene: expected one of {sorted(SCENES)}, got {scene!r}", "scene")
    if atlas not in ATLASES:
        raise InvalidInputError(f"atlas: expected one of {sorted(ATLASES)}, got {atlas!r}", "atlas")
    interpolant = choice(interpolant, Interpolant, "interpolant")
    if unit is None:
        unit = SCENE_UNIT
    if unit not in UNIT_RULES and not (isinstance(unit, (int, float)) and math.isfinite(unit)
                                       and unit > 0):
        raise InvalidInputError(f"unit: expected a positive length, \"data\" or \"fit\", got "
                                f"{unit!r}", "unit")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    sc = SCENES[scene](channels)
    samples, values = orbit_samples(sc, n, seed, eyes=eyes)
    neyes = eyes if eyes is not None else math.isqrt(n - 1) + 1
    timings["sample_and_shade"] = time.perf_counter() - t0
    log(f"sampled {n:,} rays of the {scene} from {neyes:,} eyes all around in "
        f"{timings['sample_and_shade']:.2f} s")

    bar = ProgressBar("building atlas field", n) if progress else None
    field, stats = build_atlas_field(samples.origins, samples.directions, values,
                                     atlas=_with_reach(ATLASES[atlas](
                                         None if unit == "data" else unit, isometric), reach),
                                     progress=bar)
    timings["field_build"] = stats.seconds
    if unit in UNIT_RULES:
        log(f"unit of length chosen ({unit}) from the first {min(n, BUILD_CHUNK):,} samples: "
            f"{field.atlas.unit:.4f}")
    log(f"atlas field: {field.atlas.ncharts} charts, {stats.accepted:,} samples accepted, "
        f"{stats.rejected:,} rejected, {field.nstored:,} vertices over the charts "
        f"(duplication {field.duplication:.2f}), built in {stats.seconds:.1f} s")
    base = TwoSphere(samples.origins, samples.directions, values)
    timings["baseline_build"] = base.build_seconds

    rows = []
    sheet: dict[float, dict[str, list]] = {}
    views = orbit_views(width, supersample)
    for name, cam in views:
        truth = render_truth(sc, cam)
        fr = render_field(field, cam, fill=sc.background, interpolant=interpolant)
        o, d = cam.rays()
        t = time.perf_counter()
        v, ins = base(o, d)
        bimg, bcov = frame_from_rays(cam, v, ins, sc.background)
        bsec = time.perf_counter() - t
        common = fr.covered & bcov
        row = {"view": name, "camera": cam.to_dict(), "routing": view_charts(field.atlas, cam),
               "common_coverage": float(common.mean()), "methods": {}}
        for key, img, cov, sec in (("ours", fr.image, fr.covered, fr.seconds),
                                   ("baseline", bimg, bcov, bsec)):
            row["methods"][key] = {**_scores(img, truth.image, common), "coverage": float(cov.mean()),
                                   "seconds": sec}
        if one_chart:
            t = time.perf_counter()
            single = AtlasField(one_chart_atlas(field.atlas, cam.rotation[:, 2]), channels)
            single.add(Flats.from_rays(samples.origins, samples.directions), values)
            build = time.perf_counter() - t
            sfr = render_field(single, cam, fill=sc.background, interpolant=interpolant)
            row["one_chart"] = {**_scores(sfr.image, truth.image, sfr.covered & common),
                                "coverage": float(sfr.covered.mean()), "seconds": sfr.seconds,
                                "build_seconds": build, "samples": single.nsamples,
                                "straddles": view_charts(single.atlas, cam)["straddles"]}
        p = {k: row["methods"][k]["psnr"] for k in row["methods"]}
        row["winner"] = max(p, key=lambda k: -math.inf if math.isnan(p[k]) else p[k])
        rows.append(row)
        s = sheet.setdefault(float(name.split("_el")[1]), {"ours": [], "baseline": [], "truth": []})
        s["ours"].append(fr.image)
        s["baseline"].append(bimg)
        s["truth"].append(truth.image)
        extra = ""
        if one_chart:
            extra = f"; one chart {fmt(row['one_chart']['psnr'])} dB"
        log(f"{name}: ours {fmt(p['ours'])} dB, baseline {fmt(p['baseline'])} dB, coverage "
            f"{row['methods']['ours']['coverage']:.1%}, charts {row['routing']['charts']} "
            f"(blended on {row['routing']['blended']:.0%} of rays){extra}; winner {row['winner']}")

    sheet_rows = [(f"el {el:+.0f}: {_LABEL[k]}", imgs[k])
                  for el, imgs in sorted(sheet.items(), reverse=True) for k in ("ours", "baseline", "truth")]
    azimuths = [name.split("_")[0] for name, _ in views[:AZIMUTHS]]
    contact_sheet(out / "contact_sheet.png", sheet_rows, azimuths)
    result = {
        "scene": scene, "atlas_kind": atlas, "unit": field.atlas.unit,
        "unit_from": unit if unit in UNIT_RULES else "given", "isometric": isometric,
        "interpolant": interpolant.value,
        "samples": n, "eyes": neyes, "seed": seed, "width": width,
        "supersample": supersample, "channels": channels,
        "eye_radius": ORBIT_EYE_RADIUS, "ball_radius": ORBIT_RADIUS,
        "atlas": {"charts": field.atlas.ncharts, "inner": field.atlas.inner,
                  "trusted": field.atlas.trusted, "reach": field.atlas.reach,
                  "unit": field.atlas.unit,
                  "covering_radius_deg": field.atlas.info.get("covering_radius_deg")},
        "accepted": stats.accepted, "rejected": stats.rejected, "nstored": field.nstored,
        "duplication": field.duplication,
        "baseline": {"k": base.k, "power": base.power, "radius": base.radius},
        "timings": timings,
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
        "views": rows,
        "wins": {m: sum(r["winner"] == m for r in rows) for m in ("ours", "baseline")},
    }
    (out / "results.json").write_text(json.dumps(result, indent=2, default=float))
    (out / "results.md").write_text(_markdown(result))
    log(f"wins: {result['wins']}; wrote {out}/contact_sheet.png, results.md, results.json")
    return result


def _markdown(res: dict) -> str:
    one = bool(res["views"]) and "one_chart" in res["views"][0]
    lines = [
        f"# 360° light field: {res['scene']}, eyes all around",
        "",
        f"{res['samples']:,} sample rays from {res['eyes']:,} eyes on a Fibonacci sphere of radius "
        f"{res['eye_radius']:g}, each ray through the ball of radius {res['ball_radius']:g} "
        f"(seed {res['seed']}); an oriented covering atlas of {res['atlas']['charts']} "
        f"{'isometric' if res.get('isometric', True) else 'paper'} charts "
        f"(covering radius {fmt(res['atlas']['covering_radius_deg'])}°; blending weight 1 up to "
        f"{res['atlas']['inner']:g}°, 0 from {res['atlas']['trusted']:g}°; samples in every chart "
        f"closer than {res['atlas']['reach']:g}°), {res['nstored']:,} "
        f"vertices over the charts (duplication {res['duplication']:.2f}), {res['rejected']:,} "
        f"samples rejected; lengths of our field in units of {res['unit']:g} (world: 1); "
        f"the {res.get('interpolant', 'linear')} interpolant. "
        f"Baseline: the {res['baseline']['k']} nearest sample rays in the "
        f"two-sphere parameterisation (sphere of radius {res['baseline']['radius']:g}), weights "
        f"1/distance^{res['baseline']['power']:g}. Views {res['width']}², "
        f"{res['supersample']} rays per pixel.",
        "",
        "PSNR (dB) and SSIM against the mesh's ground truth on the pixels both methods cover; "
        "coverage = share of pixels all of whose rays got a value; time = seconds per frame. "
        "Charts: the atlas charts whose blending weight is positive at some ray of the view, "
        "and the share of rays blended from more than one (the view straddles a chart border "
        "when it is not 0)."
        + (" One chart: the same view from a one-chart atlas centred on the view's axis "
           "(the same samples; every ray inside that chart), and ours minus it." if one else ""),
        "",
        "| view | charts (blended rays) | ours: PSNR / SSIM / coverage / time | baseline: PSNR / "
        "SSIM / coverage / time | winner |" + (" one chart: PSNR | ours − one chart |" if one else ""),
        "|---|---|---|---|---|" + ("---|---|" if one else ""),
    ]
    for r in res["views"]:
        cells = []
        for m in ("ours", "baseline"):
            x = r["methods"][m]
            cells.append(f"{fmt(x['psnr'])} / {fmt(x['ssim'], 3)} / {x['coverage']:.1%} / "
                         f"{x['seconds']:.2f}")
        ro = r["routing"]
        line = (f"| {r['view']} | {','.join(map(str, ro['charts']))} ({ro['blended']:.0%}) | "
                + " | ".join(cells) + f" | {r['winner']} |")
        if one:
            oc = r["one_chart"]
            line += f" {fmt(oc['psnr'])} | {fmt(r['methods']['ours']['psnr'] - oc['psnr'])} |"
        lines.append(line)
    ours = [r["methods"]["ours"]["psnr"] for r in res["views"]]
    basel = [r["methods"]["baseline"]["psnr"] for r in res["views"]]
    lines += ["", f"Wins: ours {res['wins']['ours']}, baseline {res['wins']['baseline']}. "
              f"Mean PSNR: ours {fmt(float(np.mean(ours)))} dB, baseline "
              f"{fmt(float(np.mean(basel)))} dB.", "",
              "Build times (s): " + ", ".join(f"{k} {v:.1f}" for k, v in res["timings"].items()), ""]
    return "\n".join(lines)
