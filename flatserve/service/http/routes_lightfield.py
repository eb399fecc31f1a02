"""Light-field routes: render a camera's view of a field; the browser viewer.

* ``POST /v1/fields/{name}/render`` — body: a camera (JSON); response: the
  frame as PNG (default) or ``.npy`` (float32, (H, W, C), NaN where no ray
  has a value; ``Accept: application/x-npy`` or ``"format": "npy"``).
  The camera is one of: ``orbit`` (the viewer's), ``eye`` (+ ``target``/``up``
  or ``rotation``), or the pose of a captured frame in a capture's own
  convention — ``nerf`` (a ``transforms.json`` frame: camera-to-world
  ``transform_matrix`` in OpenGL axes, ``camera_angle_x`` or ``fl_x``/``fl_y``,
  ``cx``/``cy``, ``w``/``h``) or ``colmap`` (an ``images.txt`` pose
  ``qvec``/``tvec``, world-to-camera, with its ``cameras.txt`` ``model`` and
  ``params``, or ``fx``/``fy``/``cx``/``cy``, and ``width``/``height``); see
  :class:`flatserve.lightfield.camera.PinholeCamera`. A pose renders at the
  frame's size unless the body's ``width``/``height`` are given: then its
  intrinsics are scaled to that size (one of them given: the other keeps the
  frame's aspect ratio). A bad pose is a 422 naming its member
  (``nerf.transform_matrix``, ``colmap.params``, ...).
  Timing split in ``Server-Timing`` (rays, coordinates, locate, encode) and
  coverage in ``X-Coverage``. A field created with a ``rig`` (a capture with
  depth, its last channel the depth channel) renders through it
  (:func:`flatserve.lightfield.depth.render_guided`: the frame has the colour
  channels only; ``Server-Timing`` rays, guided, encode; ``interpolant`` linear
  only, else 422); ``X-Render`` says which: ``depth-guided`` or ``field``. One-chart and atlas fields alike (the demo is an
  oriented covering atlas: the camera's rays keep their direction, and the
  view exists from every side); an atlas field charts the rays inside its
  query, so its ``coordinates`` are counted in ``locate``.
* ``GET /viewer/{name}`` — a static page (HTML + JS, no build step): drag to
  orbit the eye (all the way round), wheel for the focal length; it shows each
  frame and its render time. ``/viewer/{name}?camera=<JSON>`` (URL-encoded)
  shows a captured frame's view instead: the JSON holds the ``nerf`` or
  ``colmap`` member of a render body (and optionally its ``width``,
  ``height``, ``supersample``, ``interpolant``; without a size the frame is
  scaled to 250 pixels on its longer side). That camera stays fixed — its
  intrinsics are the capture's, which the orbit cannot keep — and the page
  says so: dragging, the wheel and the keys do nothing until the page is
  opened without ``?camera=``. A ``#key=`` fragment works alongside.

Owned by the light-field engineer; included by :func:`flatserve.service.app.create_app`.
"""
from __future__ import annotations

import io
import math
import time
from pathlib import Path
from typing import Annotated, Literal, Optional

import numpy as np
from fastapi import APIRouter, Header, Response
from fastapi.responses import FileResponse, HTMLResponse
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field

from ...errors import InvalidInputError
from ...flats import MAX_ENTRY
from ...options import Interpolant
from ..status import BatchTooLargeError
from . import codec
from .deps import (FieldNamePath, NoBody, ReadAccess, ReadyField, SettingsDep, json_body,
                   json_body_doc)
from .errors import COMMON_RESPONSES, FIELD_RESPONSES
from ..logs import note
from .query import server_timing

__all__ = ["lightfield_api", "viewer", "CameraSpec", "NerfPose", "ColmapPose", "render_frame"]

STATIC = Path(__file__).parent / "static"
PNG = "image/png"
#: PNG compression: frames are small; speed matters more than bytes.
PNG_COMPRESS_LEVEL = 1
#: Largest rendered image side.
MAX_SIDE = 2048
#: The header naming what rendered a frame (:func:`render_kind`).
RENDER_HEADER = "X-Render"

Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]
#: A number of a pose: finite (a JSON number; NaN and infinities refused).
Finite = Annotated[float, Field(allow_inf_nan=False)]
#: Largest focal length or principal point coordinate of a pose, in pixels.
MAX_PIXELS = 1e7
Pixels = Annotated[float, Field(ge=-MAX_PIXELS, le=MAX_PIXELS, allow_inf_nan=False)]
FocalPixels = Annotated[float, Field(gt=0, le=MAX_PIXELS, allow_inf_nan=False)]
#: Largest side of a pose's own frame (a photograph's): rendered at the body's
#: ``width``/``height`` when larger than :data:`MAX_SIDE`.
MAX_POSE_SIDE = 100_000


def _integral(v):
    """A whole number written as a float (``"w": 800.0``, as some NeRF writers do) as
    the integer it is (JSON Schema's ``integer`` holds it too); anything else as
    given, for the strict check to judge."""
    return int(v) if isinstance(v, float) and v.is_integer() else v


Side = Annotated[int, BeforeValidator(_integral), Field(ge=1, le=MAX_POSE_SIDE)]
#: The camera members of a render body, one of which gives the camera.
CAMERA_MEMBERS = ("orbit", "eye", "rotation", "nerf", "colmap")
#: COLMAP camera models a render takes, with their ``params`` in cameras.txt order.
COLMAP_PARAMS = {"PINHOLE": ("fx", "fy", "cx", "cy"), "SIMPLE_PINHOLE": ("f", "cx", "cy")}


class OrbitSpec(BaseModel):
    """Eye on a sphere around the origin, looking at it (the viewer's camera)."""

    # strict: a boolean for a number ("fill": false) is a 422, as in the other bodies
    model_config = ConfigDict(extra="forbid", strict=True)
    yaw: float = Field(0.0, ge=-360, le=360, allow_inf_nan=False, description="Degrees about +y.")
    pitch: float = Field(0.0, ge=-89, le=89, allow_inf_nan=False, description="Degrees up/down.")
    distance: float = Field(3.0, gt=0, le=1e3, allow_inf_nan=False, description="Eye distance from the origin.")


class NerfPose(BaseModel):
    """A frame of a NeRF capture (``transforms.json``): camera-to-world, OpenGL axes
    (x right, y up, looking along -z); see
    :meth:`flatserve.lightfield.camera.PinholeCamera.from_nerf`."""

    model_config = ConfigDict(extra="forbid", strict=True)
    transform_matrix: Annotated[list[Annotated[list[Finite], Field(min_length=4, max_length=4)]],
                                Field(min_length=3, max_length=4)] = Field(
        description="Camera-to-world: 4 rows of 4 (the last (0, 0, 0, 1)) or 3 rows of 4.")
    camera_angle_x: Optional[float] = Field(None, gt=0, lt=math.pi, allow_inf_nan=False,
                                            description="Horizontal field of view, radians.")
    fl_x: Optional[FocalPixels] = Field(None, description="Focal length in pixels (instead of "
                                                          "camera_angle_x).")
    fl_y: Optional[FocalPixels] = Field(None, description="Vertical focal length (default fl_x).")
    cx: Optional[Pixels] = Field(None, description="Principal point, pixels (default w / 2).")
    cy: Optional[Pixels] = Field(None, description="Principal point, pixels (default h / 2).")
    w: Side = Field(description="The frame's width in pixels.")
    h: Side = Field(description="The frame's height in pixels.")


class ColmapPose(BaseModel):
    """A frame of a COLMAP capture: its ``images.txt`` pose (world-to-camera, OpenCV
    axes) and its ``cameras.txt`` camera; see
    :meth:`flatserve.lightfield.camera.PinholeCamera.from_colmap`."""

    model_config = ConfigDict(extra="forbid", strict=True)
    qvec: Annotated[list[Finite], Field(min_length=4, max_length=4)] = Field(
        description="Rotation world-to-camera as a unit quaternion (w, x, y, z).")
    tvec: Annotated[list[Finite], Field(min_length=3, max_length=3)] = Field(
        description="Translation world-to-camera.")
    model: Literal["PINHOLE", "SIMPLE_PINHOLE"] = Field(
        "PINHOLE", description="The cameras.txt model of `params`.")
    params: Optional[Annotated[list[Pixels], Field(min_length=3, max_length=4)]] = Field(
        None, description="As in cameras.txt: fx, fy, cx, cy (PINHOLE) or f, cx, cy "
                          "(SIMPLE_PINHOLE); or give fx, fy, cx, cy.")
    fx: Optional[FocalPixels] = None
    fy: Optional[FocalPixels] = Field(None, description="Default fx (SIMPLE_PINHOLE: must not "
                                                        "be given).")
    cx: Optional[Pixels] = None
    cy: Optional[Pixels] = None
    width: Side = Field(description="The frame's width in pixels.")
    height: Side = Field(description="The frame's height in pixels.")

    def intrinsics(self) -> dict:
        """``fx, fy, cx, cy`` from ``params`` or the members (422 naming the member)."""
        names = COLMAP_PARAMS[self.model]
        given = [k for k in ("fx", "fy", "cx", "cy") if getattr(self, k) is not None]
        if self.params is not None:
            if given:
                raise InvalidInputError(f"colmap.{given[0]}: give params or fx, fy, cx, cy, "
                                        "not both", f"colmap.{given[0]}")
            if len(self.params) != len(names):
                raise InvalidInputError(
                    f"colmap.params: a {self.model} camera has {len(names)} params "
                    f"({', '.join(names)}), got {len(self.params)}", "colmap.params")
            p = dict(zip(names, self.params))
            if "f" in p:
                p["fx"] = p["fy"] = p.pop("f")
            if not (p["fx"] > 0 and p["fy"] > 0):
                raise InvalidInputError("colmap.params: focal lengths must be positive",
                                        "colmap.params")
            return p
        for k in ("fx", "cx", "cy"):
            if getattr(self, k) is None:
                raise InvalidInputError(f"colmap.{k}: missing (give params, or fx, fy, cx, cy)",
                                        f"colmap.{k}")
        if self.model == "SIMPLE_PINHOLE" and self.fy is not None:
            raise InvalidInputError("colmap.fy: a SIMPLE_PINHOLE camera has one focal length "
                                    "(fx)", "colmap.fy")
        return {"fx": self.fx, "fy": self.fx if self.fy is None else self.fy,
                "cx": self.cx, "cy": self.cy}


#: What the library calls a pose's parts (:class:`PinholeCamera`'s arguments), by
#: the name of the request member that gave them.
_NERF_NAMES = {"width": "w", "height": "h", "rotation": "transform_matrix",
               "eye": "transform_matrix", "fx": "fl_x", "fy": "fl_y"}
_COLMAP_NAMES = {"rotation": "qvec", "eye": "tvec"}


def _pose_error(exc: InvalidInputError, member: str, names: dict[str, str],
                own: tuple[str, ...]) -> InvalidInputError:
    """The library's error about a pose, named by its place in the body
    (``transform_matrix`` -> ``nerf.transform_matrix``)."""
    arg = exc.argument or ""
    msg = str(exc)
    name = names.get(arg, arg)
    if arg and msg.startswith(f"{arg}:"):
        msg = msg[len(arg) + 1:].lstrip()
    if arg == "supersample":
        return InvalidInputError(f"supersample: {msg}", "supersample")
    path = f"{member}.{name}" if name in own else member
    return InvalidInputError(f"{path}: {msg}", path)


class CameraSpec(BaseModel):
    """A pinhole camera (see :class:`flatserve.lightfield.Camera`).

    Give one camera: ``orbit``, ``eye`` (+ ``target``/``up``, or ``rotation``),
    ``nerf`` or ``colmap`` (a captured frame's pose and intrinsics,
    :class:`flatserve.lightfield.camera.PinholeCamera`); nothing: the default
    camera at (0, 0, -3) looking along +z.
    """

    # strict: a boolean for a number ("fill": false) is a 422, as in the other bodies
    model_config = ConfigDict(extra="forbid", strict=True, json_schema_extra={"examples": [
        {"orbit": {"yaw": 30.0, "pitch": 10.0, "distance": 3.0}, "width": 64, "height": 64},
        {"nerf": {"transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 0, 1]],
                  "camera_angle_x": 0.6911, "w": 64, "h": 48}, "supersample": 1},
        {"colmap": {"qvec": [1, 0, 0, 0], "tvec": [0, 0, 3], "model": "PINHOLE",
                    "params": [90.0, 90.0, 32.0, 24.0], "width": 64, "height": 48},
         "width": 32, "height": 24, "format": "npy"}]})
    orbit: Optional[OrbitSpec] = None
    eye: Optional[Vec3] = None
    target: Optional[Vec3] = Field(None, description="Point looked at (default the origin).")
    up: Optional[Vec3] = Field(None, description="Image up hint (default +y).")
    rotation: Optional[Annotated[list[Vec3], Field(min_length=3, max_length=3)]] = Field(
        None, description="Rows of a rotation matrix whose columns are right, up, forward.")
    focal: float = Field(3.0, gt=0, le=1e3, allow_inf_nan=False,
                         description="Image-plane distance in half image widths.")
    nerf: Optional[NerfPose] = Field(None, description="A NeRF frame's pose (transforms.json).")
    colmap: Optional[ColmapPose] = Field(None, description="A COLMAP frame's pose (images.txt, "
                                                           "cameras.txt).")
    width: int = Field(250, ge=1, le=MAX_SIDE, description="Pixels; of a pose: its frame's "
                                                            "width unless given.")
    height: int = Field(250, ge=1, le=MAX_SIDE, description="Pixels; of a pose: its frame's "
                                                             "height unless given.")
    supersample: Literal[1, 4, 9, 16] = Field(4, description="Rays per pixel.")
    fill: Optional[float] = Field(None, allow_inf_nan=False,
                                  description="PNG value of pixels without any ray inside (default 0).")
    format: Optional[Literal["png", "npy"]] = Field(None, description="Overrides the Accept header.")
    interpolant: Interpolant = Field(
        Interpolant.LINEAR, description="As the query's: `linear` (the paper's) or `gradient` "
                                        "(the Delaunay cell's Taylor expansions, slopes fitted "
                                        "to the nearest samples).")

    def camera(self):
        """The camera (:class:`~flatserve.lightfield.Camera` or, of a pose,
        :class:`~flatserve.lightfield.camera.PinholeCamera`); 422 naming the
        member that conflicts or is wrong."""
        from ...lightfield import Camera

        given = [k for k in CAMERA_MEMBERS if getattr(self, k) is not None]
        pose = [k for k in given if k in ("nerf", "colmap")]
        if pose:
            if len(given) > 1:
                other = next(k for k in given if k != pose[0])
                raise InvalidInputError(f"camera: give one camera: {pose[0]} and {other} were "
                                        f"both given", pose[-1] if len(pose) > 1 else pose[0])
            for k in ("focal", "target", "up"):
                if k in self.model_fields_set:
                    raise InvalidInputError(f"{k}: not with a {pose[0]} pose (its intrinsics "
                                            f"and orientation are the pose's)", k)
            return self._pose_camera()
        kw = dict(focal=self.focal, width=self.width, height=self.height, supersample=self.supersample)
        if self.orbit is not None:
            if self.eye is not None or self.rotation is not None:
                raise InvalidInputError("camera: give one camera: orbit or eye/rotation, "
                                        "not both", "orbit")
            return Camera.orbit(self.orbit.yaw, self.orbit.pitch, self.orbit.distance, **kw)
        if self.rotation is not None:
            return Camera(eye=self.eye if self.eye is not None else (0.0, 0.0, -3.0),
                          rotation=np.asarray(self.rotation), **kw)
        if self.eye is not None:
            return Camera.look_at(self.eye, self.target or (0.0, 0.0, 0.0), self.up or (0.0, 1.0, 0.0), **kw)
        return Camera(**kw)

    def _pose_camera(self):
        """The :class:`PinholeCamera` of ``nerf`` or ``colmap``, at the body's size
        if given."""
        from ...lightfield.camera import PinholeCamera

        if self.nerf is not None:
            n = self.nerf
            try:
                cam = PinholeCamera.from_nerf(
                    n.transform_matrix, width=n.w, height=n.h, camera_angle_x=n.camera_angle_x,
                    fl_x=n.fl_x, fl_y=n.fl_y, cx=n.cx, cy=n.cy, supersample=self.supersample)
            except InvalidInputError as exc:
                raise _pose_error(exc, "nerf", _NERF_NAMES, tuple(NerfPose.model_fields)) from None
        else:
            c = self.colmap
            k = c.intrinsics()
            try:
                cam = PinholeCamera.from_colmap(c.qvec, c.tvec, width=c.width, height=c.height,
                                                **k, supersample=self.supersample)
            except InvalidInputError as exc:
                names = _COLMAP_NAMES if c.params is None else {
                    **_COLMAP_NAMES, "fx": "params", "fy": "params", "cx": "params", "cy": "params"}
                raise _pose_error(exc, "colmap", names, tuple(ColmapPose.model_fields)) from None
        if not np.abs(cam.eye).max() <= MAX_ENTRY:  # as an eye's of look_at: rays that chart
            where = "nerf.transform_matrix" if self.nerf is not None else "colmap.tvec"
            raise InvalidInputError(f"{where}: the camera's centre {cam.eye.tolist()} is farther "
                                    f"than {MAX_ENTRY:g} from the origin", where)
        return self._sized(cam)

    def _sized(self, cam):
        """``cam`` scaled to the body's ``width``/``height`` when given (one of them:
        the other keeps the frame's aspect ratio); the rendered size at most
        :data:`MAX_SIDE` (a photograph's frame may be larger: give a size)."""
        has_w, has_h = "width" in self.model_fields_set, "height" in self.model_fields_set
        w = self.width if has_w else (cam.width if not has_h else
                                      max(1, round(self.height * cam.width / cam.height)))
        h = self.height if has_h else (cam.height if not has_w else
                                       max(1, round(self.width * cam.height / cam.width)))
        how = "at the frame's aspect ratio" if has_w or has_h else "the frame's"
        for name, v in (("width", w), ("height", h)):
            if v > MAX_SIDE:
                raise InvalidInputError(f"{name}: {v} pixels ({how}); at most {MAX_SIDE}: give "
                                        f"a smaller width or height", name)
        if (w, h) == (cam.width, cam.height):
            return cam
        return cam.scaled(w, h)


#: ``X-Render`` of a frame rendered through the field's depth channel, and of one
#: rendered by the field alone.
RENDER_GUIDED, RENDER_FIELD = "depth-guided", "field"


def render_kind(rig: dict | None) -> str:
    """What renders a field's frames: :data:`RENDER_GUIDED` with a rig, else
    :data:`RENDER_FIELD` (the ``X-Render`` header)."""
    return RENDER_FIELD if rig is None else RENDER_GUIDED


def render_frame(field, camera, fill: float = 0.0, fmt: str = "png",
                 interpolant: Interpolant | str = Interpolant.LINEAR, rig: dict | None = None
                 ) -> tuple[bytes, str, dict, float]:
    """Render and encode one frame.

    Parameters
    ----------
    field : a field of the contract
        Lines in R^3.
    camera : Camera or PinholeCamera
    fill : float
        Of PNG pixels without a valued ray (a ``.npy`` frame has NaN there).
    fmt : {"png", "npy"}
    interpolant : {"linear", "gradient"}
        The field's (:func:`flatserve.lightfield.render.render_field`); with a
        ``rig`` only ``"linear"``.
    rig : dict, optional
        The field's stored ``rig`` (:class:`~..schemas.RigSpec`): the frame is
        rendered through its last channel, the depth channel
        (:func:`flatserve.lightfield.depth.render_guided`), and has the other
        channels, the colours.

    Returns
    -------
    body : bytes
    media_type : str
    timings : dict of str to float
        Seconds: ``rays``, ``coordinates``, ``locate``, ``encode``; with a rig
        ``rays``, ``guided`` (the field's lookups, the depth's refinement, the
        blend and the pixels' resolve) and ``encode``.
    coverage : float

    Raises
    ------
    InvalidInputError
        Not a field of lines in R^3 (``name``); ``interpolant`` other than
        linear with a rig.
    """
    from ...lightfield.figure import to_uint8

    if field.k != 1 or field.d != 3:
        raise InvalidInputError(f"render needs a field of lines in R^3 (k=1, d=3), this one has "
                                f"k={field.k}, d={field.d}", "name")
    fill_value = np.nan if fmt == "npy" else fill
    if rig is None:
        from ...lightfield.render import render_field

        frame = render_field(field, camera, fill=fill_value, interpolant=interpolant)
        t = frame.timings
        timings = {"rays": t["rays"], "coordinates": t["coordinates"],
                   "locate": t["locate_interpolate"] + t["resolve"]}
    else:
        if Interpolant(interpolant) is not Interpolant.LINEAR:
            raise InvalidInputError(
                f"interpolant: a field with a rig renders through its depth channel, which "
                f"blends the capture's nearest cameras' rays looked up linearly; "
                f"{Interpolant(interpolant).value!r} is for fields without one (leave it "
                f"out, or query the field's rays with it)", "interpolant")
        from ...lightfield.depth import DepthRig, render_guided

        frame = render_guided(field, camera, DepthRig.from_dict(rig), fill=fill_value)
        t = frame.timings
        timings = {"rays": t["rays"], "guided": t["guided"] + t["resolve"]}
    t0 = time.perf_counter()
    if fmt == "npy":
        body = codec.npy_bytes(frame.image.astype(np.float32))
        media = codec.NPY
    else:
        from PIL import Image

        img = frame.image
        if img.shape[2] not in (1, 3):
            img = img[..., :1]
        buf = io.BytesIO()
        Image.fromarray(to_uint8(img)).save(buf, format="PNG", compress_level=PNG_COMPRESS_LEVEL)
        body, media = buf.getvalue(), PNG
    timings["encode"] = time.perf_counter() - t0
    return body, media, timings, frame.coverage


lightfield_api = APIRouter(prefix="/v1", tags=["lightfield"])
viewer = APIRouter(include_in_schema=False)


@lightfield_api.post(
    "/fields/{name}/render", dependencies=[ReadAccess],
    responses={**COMMON_RESPONSES, **FIELD_RESPONSES,
               200: {"content": {PNG: {}, codec.NPY: {}},
                     "description": "The frame (PNG, or .npy float32 (H, W, C)). "
                                    "`X-Render`: `depth-guided` for a field with a `rig` "
                                    "(C its channels but the last, the depth), `field` "
                                    "otherwise.",
                     "headers": {
                         "X-Render": {"description": "What rendered the frame: "
                                                     "`depth-guided` or `field`.",
                                      "schema": {"type": "string",
                                                 "enum": ["depth-guided", "field"]}},
                         "X-Coverage": {"description": "The part of the frame's pixels "
                                                       "whose rays all have a value.",
                                        "schema": {"type": "string"}}}}},
    response_class=Response, openapi_extra=json_body_doc(CameraSpec),
    summary="Render a camera's view of a light field (lines in R^3)",
    description="A field created with a `rig` (a capture with depth: its last channel is "
                "the depth channel) renders through it: each ray's depth interpolated by "
                "the field and refined among the capture's nearest cameras, its colour "
                "blended from their rays through the surface point "
                "(flatserve.lightfield.depth.render_guided); the frame has the colour "
                "channels only, and `interpolant` must be `linear` (422 otherwise). "
                "Such a render looks the field up to 49 times per ray (about 44 measured).")
def render(e: ReadyField, camera: json_body(CameraSpec), settings: SettingsDep,
           accept: Annotated[Optional[str], Header()] = None) -> Response:
    t0 = time.perf_counter()
    cam = camera.camera()
    note(rows=cam.nrays)
    if cam.nrays > settings.max_batch_rows:
        raise BatchTooLargeError(f"{cam.nrays} rays in one frame ({cam.width} x {cam.height} pixels, "
                                 f"{cam.supersample} rays per pixel); the limit is "
                                 f"{settings.max_batch_rows}: give a smaller width/height or "
                                 f"supersample")
    fmt = camera.format or ("npy" if accept and codec.NPY in accept else "png")
    rig = e.spec.rig
    if fmt == "npy":  # float32 (H, W, C): bounded before it is rendered
        colours = e.spec.channels - (rig is not None)  # (a rig's depth channel is not drawn)
        codec.check_answer(cam.height * cam.width, colours, "npy",
                           max_json=settings.max_json_answer_bytes,
                           max_binary=settings.max_answer_bytes, bytes_per_number=4)
    body, media, timings, coverage = render_frame(
        e.field, cam, fill=0.0 if camera.fill is None else camera.fill, fmt=fmt,
        interpolant=camera.interpolant, rig=rig)
    total = time.perf_counter() - t0
    return Response(body, media_type=media, headers={
        "Server-Timing": server_timing({**timings, "total": total}),
        "X-Coverage": f"{coverage:.6f}", RENDER_HEADER: render_kind(rig),
        "X-Render-Seconds": f"{total:.6f}", "Cache-Control": "no-store"})


@viewer.get("/viewer/assets/{file}", dependencies=[NoBody])
def viewer_asset(file: Literal["viewer.js", "viewer.css"]) -> FileResponse:
    media = "text/javascript" if file.endswith(".js") else "text/css"
    return FileResponse(STATIC / file, media_type=media, headers={"Cache-Control": "no-cache"})


@viewer.get("/viewer/{name}", response_class=HTMLResponse, dependencies=[NoBody])
def viewer_page(name: FieldNamePath) -> HTMLResponse:
    # static page: the field name is read from the URL by viewer.js
    return HTMLResponse((STATIC / "viewer.html").read_text(encoding="utf-8"),
                        headers={"Cache-Control": "no-cache"})
