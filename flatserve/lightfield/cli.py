"""``flatserve lightfield ...``: the light-field application from the command line.

$ flatserve lightfield paper-figure --out figs/            # quick (300^2 samples)
$ flatserve lightfield paper-figure --out figs/ --full     # the paper's 1000^2
$ flatserve lightfield orbit --out figs360/                # 360 degrees: eyes all around
$ flatserve lightfield import captures/lego --url http://127.0.0.1:8000 --field lego --stride 2
$ flatserve lightfield capture-figure --out figs-captures/  # synthetic captures against the baselines

``import`` uploads a real capture (a NeRF ``transforms.json`` or a COLMAP text
model beside its images) to a running service (:meth:`flatserve.client.Client.import_capture`);
run again after an interruption, the same command stores only what is missing.
On a sparse rig all around an object it also stores each pixel's depth (``--depth``
to force it, ``--no-depth`` to leave it out), and the field renders through it.
Its key is ``--api-key`` or ``FLATSERVE_API_KEY`` (the server's variable).
Exit status 2 on a bad capture or a refused request (one line naming the file
or the request and the field), 0 once every batch is stored.
"""
from __future__ import annotations

import argparse
import os
import sys

from ..options import Interpolant


def _view_options(p: argparse.ArgumentParser, *, width: int, seed_of: str) -> None:
    """The options both figures share: where they go and how the views are rendered."""
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--seed", type=int, default=0, help=f"seed of the {seed_of} (default 0)")
    p.add_argument("--width", type=int, default=width, help=f"view resolution (default {width})")
    p.add_argument("--supersample", type=int, default=4, help="rays per pixel (square number; default 4)")
    p.add_argument("--rgb", action="store_true", help="RGB instead of grey")


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Sub-subcommands of ``flatserve lightfield``."""
    from .figure import DEFAULT_N, FULL_N

    sub = p.add_subparsers(dest="lightfield_command", required=True)
    fig = sub.add_parser("paper-figure", help="reproduce Fig. 11 (bunny light field, views, baselines)",
                         description="Build the bunny light field and write Fig. 11's views beside "
                                     "ground truth, a contact sheet and a table against baselines.")
    _view_options(fig, width=250, seed_of="eye positions")
    fig.add_argument("--full", action="store_true", help=f"the paper's {FULL_N}^2 samples (slow: minutes)")
    fig.add_argument("--n", type=int, default=None, help=f"screen side n (n^2 samples; default {DEFAULT_N})")
    fig.add_argument("--no-baselines", action="store_true", help="skip the two-plane and nearest baselines")

    from .orbit import ATLASES, DEFAULT_SAMPLES, SCENES, VIEW_WIDTH

    orb = sub.add_parser("orbit", help="360-degree light field: eyes all around, views all around, "
                                       "against the two-sphere nearest-rays baseline",
                         description="Sample a scene from eyes all around it into an oriented covering "
                                     "atlas field, render 8 azimuths x 3 elevations, and write a contact "
                                     "sheet and a table (PSNR, SSIM, coverage, time) against the k "
                                     "nearest rays in the two-sphere parameterisation.")
    _view_options(orb, width=VIEW_WIDTH, seed_of="ray directions")
    orb.add_argument("--samples", type=int, default=DEFAULT_SAMPLES,
                     help=f"sample rays (default {DEFAULT_SAMPLES:,})")
    orb.add_argument("--eyes", type=int, default=None, help="eyes on the sphere (default ceil(sqrt(samples)))")
    orb.add_argument("--scene", choices=sorted(SCENES), default="bunny", help="scene (default bunny)")
    orb.add_argument("--no-one-chart", action="store_true",
                     help="skip rendering each view from a one-chart atlas centred on its axis")
    atlas = orb.add_argument_group("the field's atlas")
    atlas.add_argument("--atlas", choices=sorted(ATLASES), default="covering",
                       help="covering: Atlas.covering (32 charts, the service's default); fine: 42 charts "
                            "within 20.8 degrees of every direction; icosahedral: the former 12-chart "
                            "default (default covering)")
    atlas.add_argument("--unit", type=_unit, default=None,
                       help="the atlas's unit of length in world units: the shift of a ray that counts "
                            "as much as a turn of one radian (default 1/3: 2/3 of the scenes' radius 0.5, "
                            "flatserve.atlas.object_unit; 1: world units; data: chosen by the field from "
                            "its first batch, flatserve.atlas.data_unit; fit: from its values, "
                            "flatserve.atlas_field.fitted_unit); the baseline is unchanged")
    atlas.add_argument("--reach", type=float, default=None,
                       help="degrees: store samples in every chart whose centre is closer (default "
                            "the atlas's: 27 for the covering); wider helps sparse eyes, at the cost "
                            "of storing each sample in more charts")
    orb.add_argument("--interpolant", choices=[m.value for m in Interpolant], default="linear",
                     help="ours: linear in each Delaunay cell (the paper's, default) or the cell's "
                          "Taylor expansions with slopes fitted to the nearest samples "
                          "(flatserve.gradient)")
    atlas.add_argument("--paper-charts", action="store_true",
                       help="the paper's tangent-simplex charts instead of the isometric ones "
                            "(flatserve.warp) in the atlas and the one-chart comparison")
    _import_arguments(sub)
    _capture_figure_arguments(sub)


#: The environment variable of ``import``'s default ``--api-key`` (the server reads
#: its read-write key from it too).
API_KEY_ENV = "FLATSERVE_API_KEY"


def _positive_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        v = 0
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return v


def _import_arguments(sub) -> None:
    imp = sub.add_parser("import", help="upload a real capture (NeRF transforms.json or COLMAP "
                                        "text model + images) to a service as a light field",
                         description="Read a capture (posed photographs), create the field and "
                                     "upload one ray per pixel with its colour, in batches whose "
                                     "idempotency keys follow from the capture: the same command "
                                     "run again after an interruption stores only what is missing.")
    imp.add_argument("dir", metavar="DIR", help="the capture's directory (or its transforms.json)")
    imp.add_argument("--url", required=True, help="the service, e.g. http://127.0.0.1:8000")
    imp.add_argument("--field", required=True, help="name of the field to create or resume")
    imp.add_argument("--format", choices=["nerf", "colmap"], default=None,
                     help="the capture's format (default: found from the files)")
    rays = imp.add_mutually_exclusive_group()
    rays.add_argument("--stride", type=_positive_int, default=None,
                      help="every N-th pixel of every N-th row (default 1)")
    rays.add_argument("--target-rays", type=_positive_int, default=None,
                      help="the smallest stride giving at most this many rays")
    imp.add_argument("--holdout", nargs="+", action="extend", default=[], metavar="NAME",
                     help="frames left out (by name), e.g. to compare renders with them "
                          "(repeatable)")
    imp.add_argument("--depth", action=argparse.BooleanOptionalAction, default=None,
                     help="give the field the depth channel (each pixel's depth from the "
                          "capture's own photographs) and render through it, or not "
                          "(--no-depth); default: when the rig is sparse and all around an "
                          "object (flatserve.lightfield.rig.wants_depth), not on a "
                          "forward-facing rig")
    imp.add_argument("--api-key", default=None,
                     help=f"the service's read-write key (default ${API_KEY_ENV})")
    imp.add_argument("--no-progress", action="store_true", help="no progress bar")


def _capture_figure_arguments(sub) -> None:
    from .capture_figure import RIGS, SCENES

    cf = sub.add_parser("capture-figure", help="synthetic captures (forward-facing and all around): "
                                               "held-out views, ours against the classic baselines",
                        description="Photograph a scene from synthetic rigs, store the rays in the "
                                    "field the importer creates, render held-out cameras by pose and "
                                    "write contact sheets and a table (PSNR per view) against the "
                                    "two-plane (forward-facing) or two-sphere (all around) k nearest "
                                    "rays, their settings swept in their favour.")
    cf.add_argument("--out", required=True, help="output directory")
    cf.add_argument("--rig", choices=[*RIGS, "all"], default="all", help="which rig (default all)")
    cf.add_argument("--scene", choices=[*SCENES, "all"], default="blocks",
                    help="which scene (default blocks)")
    cf.add_argument("--seed", type=int, default=0, help="seed of the jitter and held-out cameras")
    cf.add_argument("--quick", action="store_true", help="images at half the side (a smoke run)")


def _run_import(args: argparse.Namespace) -> int:
    """``flatserve lightfield import``: 0 once stored, 2 with one line on a bad capture
    or a refused request."""
    import httpx

    from ..client import Client, ServiceError
    from ..errors import FlatserveError

    command = "flatserve lightfield import"
    key = args.api_key if args.api_key is not None else os.environ.get(API_KEY_ENV) or None
    try:
        with Client(args.url, api_key=key) as c:
            rep = c.import_capture(args.field, args.dir, format=args.format, stride=args.stride,
                                   target_rays=args.target_rays, holdout=args.holdout,
                                   depth=args.depth, progress=not args.no_progress)
            held = rep["nsamples"]
            if held is None:  # no batch (no rays): the field as it is
                held = c.describe(args.field)["nsamples"]
    except ServiceError as exc:  # a refused request: the service's words
        print(f"{command}: {args.url} refused field {args.field!r}: {_one_line(exc)}",
              file=sys.stderr)
        return 2
    except (FlatserveError, ValueError, OSError, ImportError) as exc:  # a bad capture
        print(f"{command}: {_one_line(exc)}", file=sys.stderr)
        return 2
    except httpx.HTTPError as exc:
        print(f"{command}: {args.url}: {_one_line(exc)}", file=sys.stderr)
        return 2
    with_depth = ", with the depth channel" if rep.get("depth") else ""
    print(f"{command}: {rep['frames']} frames of {args.dir} ({rep['format']}, stride "
          f"{rep['stride']}){with_depth} into field {rep['field']!r} at {args.url}: "
          f"{rep['rays']:,} rays in {rep['batches']} batches, {rep['stored']:,} stored now, {rep['replayed']} "
          f"batches stored before, {rep['rejected']:,} refused; the field holds {held:,} samples")
    return 0


def _one_line(exc: BaseException) -> str:
    """An error as one line: a service's 422 as ``member: message``."""
    detail = getattr(exc, "detail", None)
    if isinstance(detail, list) and detail and isinstance(detail[0], dict):
        d = detail[0]
        loc = [str(x) for x in d.get("loc", ()) if x != "body"]
        msg = str(d.get("msg", ""))
        text = f"HTTP {getattr(exc, 'status', 422)}: " + (
            msg if not loc or msg.startswith(".".join(loc)) else f"{'.'.join(loc)}: {msg}")
    else:
        text = str(exc) or type(exc).__name__
    return " ".join(text.split())


def _unit(text: str):
    """``--unit``: a length, ``data`` or ``fit`` (chosen from the first samples)."""
    from ..atlas import UNIT_RULES

    if text in UNIT_RULES:
        return text
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a length, 'data' or 'fit', got {text!r}") \
            from None


def run(args: argparse.Namespace) -> int:
    from ..errors import InvalidInputError
    from .figure import DEFAULT_N, FULL_N, paper_figure

    if args.lightfield_command == "import":
        return _run_import(args)
    command = f"flatserve lightfield {args.lightfield_command}"
    if args.lightfield_command == "capture-figure":
        from .capture_figure import RIGS, SCENES, capture_figure

        def make():
            res = capture_figure(args.out, rigs=tuple(RIGS) if args.rig == "all" else (args.rig,),
                                 scenes=SCENES if args.scene == "all" else (args.scene,),
                                 seed=args.seed, size=0.5 if args.quick else 1.0,
                                 progress=lambda msg: print(msg, file=sys.stderr, flush=True))
            for r in res:
                print(f"{r['rig']} / {r['scene']}: ours - {r['baseline']['name']}: median "
                      f"{r['median_gain_db']:+.2f} dB, worst view {r['worst_gain_db']:+.2f} dB")
    elif args.lightfield_command == "paper-figure":
        n = args.n if args.n is not None else (FULL_N if args.full else DEFAULT_N)
        if n < 2:
            print(f"{command}: --n must be >= 2", file=sys.stderr)
            return 2

        def make():
            paper_figure(args.out, n=n, seed=args.seed, width=args.width, supersample=args.supersample,
                         channels=3 if args.rgb else 1, baselines=not args.no_baselines)
    else:
        from .orbit import orbit_figure

        if args.samples < 1 or (args.eyes is not None and not 1 <= args.eyes <= args.samples):
            print(f"{command}: need --samples >= 1 and 1 <= --eyes <= --samples", file=sys.stderr)
            return 2

        def make():
            orbit_figure(args.out, n=args.samples, eyes=args.eyes, seed=args.seed, width=args.width,
                         supersample=args.supersample, channels=3 if args.rgb else 1,
                         scene=args.scene, atlas=args.atlas, unit=args.unit,
                         isometric=not args.paper_charts, reach=args.reach,
                         one_chart=not args.no_one_chart, interpolant=args.interpolant)
    try:
        make()
    except (InvalidInputError, FileNotFoundError) as exc:
        print(f"{command}: {exc}", file=sys.stderr)
        return 2
    return 0
