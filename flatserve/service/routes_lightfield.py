"""Light-field routes: render a camera's view of a field; the browser viewer.

* ``POST /v1/fields/{name}/render`` — body: a camera (JSON); response: the
  frame as PNG (default) or ``.npy`` (float32, (H, W, C), NaN where no ray
  has a value; ``Accept: application/x-npy`` or ``"format": "npy"``).
  Timing split in ``Server-Timing`` (rays, coordinates, locate, encode) and
  coverage in ``X-Coverage``. One-chart and atlas fields alike (the demo is an
  oriented covering atlas: the camera's rays keep their direction, and the
  view exists from every side); an atlas field charts the rays inside its
  query, so its ``coordinates`` are counted in ``locate``.
* ``GET /viewer/{name}`` — a static page (HTML + JS, no build step): drag to
  orbit the eye (all the way round), wheel for the focal length; it shows each
  frame and its render time.

Owned by the light-field engineer; included by :func:`flatserve.service.app.create_app`.
"""
from __future__ import annotations

import io
import time
from pathlib import Path
from typing import Annotated, Literal, Optional

import numpy as np
from fastapi import APIRouter, Header, Response
from fastapi.responses import FileResponse, HTMLResponse
from pydantic import BaseModel, ConfigDict, Field

from ..errors import InvalidInputError
from ..options import Interpolant
from .status import BatchTooLargeError
from . import codec
from .deps import FieldNamePath, NoBody, ReadAccess, ReadyField, SettingsDep, json_body, json_body_doc
from .errors import COMMON_RESPONSES, FIELD_RESPONSES
from .logs import note
from .query import server_timing

__all__ = ["lightfield_api", "viewer", "CameraSpec", "render_frame"]

STATIC = Path(__file__).parent / "static"
PNG = "image/png"
#: PNG compression: frames are small; speed matters more than bytes.
PNG_COMPRESS_LEVEL = 1
#: Largest rendered image side.
MAX_SIDE = 2048

Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]


class OrbitSpec(BaseModel):
    """Eye on a sphere around the origin, looking at it (the viewer's camera)."""

    # strict: a boolean for a number ("fill": false) is a 422, as in the other bodies
    model_config = ConfigDict(extra="forbid", strict=True)
    yaw: float = Field(0.0, ge=-360, le=360, allow_inf_nan=False, description="Degrees about +y.")
    pitch: float = Field(0.0, ge=-89, le=89, allow_inf_nan=False, description="Degrees up/down.")
    distance: float = Field(3.0, gt=0, le=1e3, allow_inf_nan=False, description="Eye distance from the origin.")


class CameraSpec(BaseModel):
    """A pinhole camera (see :class:`flatserve.lightfield.Camera`).

    Give either ``orbit`` or ``eye`` (+ ``target``/``up``, or ``rotation``);
    nothing: the default camera at (0, 0, -3) looking along +z.
    """

    # strict: a boolean for a number ("fill": false) is a 422, as in the other bodies
    model_config = ConfigDict(extra="forbid", strict=True, json_schema_extra={"examples": [
        {"orbit": {"yaw": 30.0, "pitch": 10.0, "distance": 3.0}, "width": 64, "height": 64}]})
    orbit: Optional[OrbitSpec] = None
    eye: Optional[Vec3] = None
    target: Optional[Vec3] = Field(None, description="Point looked at (default the origin).")
    up: Optional[Vec3] = Field(None, description="Image up hint (default +y).")
    rotation: Optional[Annotated[list[Vec3], Field(min_length=3, max_length=3)]] = Field(
        None, description="Rows of a rotation matrix whose columns are right, up, forward.")
    focal: float = Field(3.0, gt=0, le=1e3, allow_inf_nan=False,
                         description="Image-plane distance in half image widths.")
    width: int = Field(250, ge=1, le=MAX_SIDE)
    height: int = Field(250, ge=1, le=MAX_SIDE)
    supersample: Literal[1, 4, 9, 16] = Field(4, description="Rays per pixel.")
    fill: Optional[float] = Field(None, allow_inf_nan=False,
                                  description="PNG value of pixels without any ray inside (default 0).")
    format: Optional[Literal["png", "npy"]] = Field(None, description="Overrides the Accept header.")
    interpolant: Interpolant = Field(
        Interpolant.LINEAR, description="As the query's: `linear` (the paper's) or `gradient` "
                                        "(the Delaunay cell's Taylor expansions, slopes fitted "
                                        "to the nearest samples).")

    def camera(self):
        from ..lightfield import Camera

        kw = dict(focal=self.focal, width=self.width, height=self.height, supersample=self.supersample)
        if self.orbit is not None:
            if self.eye is not None or self.rotation is not None:
                raise InvalidInputError("camera: give orbit or eye/rotation, not both", "orbit")
            return Camera.orbit(self.orbit.yaw, self.orbit.pitch, self.orbit.distance, **kw)
        if self.rotation is not None:
            return Camera(eye=self.eye if self.eye is not None else (0.0, 0.0, -3.0),
                          rotation=np.asarray(self.rotation), **kw)
        if self.eye is not None:
            return Camera.look_at(self.eye, self.target or (0.0, 0.0, 0.0), self.up or (0.0, 1.0, 0.0), **kw)
        return Camera(**kw)


def render_frame(field, camera, fill: float = 0.0, fmt: str = "png",
                 interpolant: Interpolant | str = Interpolant.LINEAR
                 ) -> tuple[bytes, str, dict, float]:
    """Render and encode one frame.

    Returns
    -------
    body : bytes
    media_type : str
    timings : dict of str to float (seconds: rays, coordinates, locate, encode)
    coverage : float
    """
    from ..lightfield.figure import to_uint8
    from ..lightfield.render import render_field

    if field.k != 1 or field.d != 3:
        raise InvalidInputError(f"render needs a field of lines in R^3 (k=1, d=3), this one has "
                                f"k={field.k}, d={field.d}", "name")
    frame = render_field(field, camera, fill=np.nan if fmt == "npy" else fill,
                         interpolant=interpolant)
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
    t = frame.timings
    timings = {"rays": t["rays"], "coordinates": t["coordinates"],
               "locate": t["locate_interpolate"] + t["resolve"], "encode": time.perf_counter() - t0}
    return body, media, timings, frame.coverage


lightfield_api = APIRouter(prefix="/v1", tags=["lightfield"])
viewer = APIRouter(include_in_schema=False)


@lightfield_api.post(
    "/fields/{name}/render", dependencies=[ReadAccess],
    responses={**COMMON_RESPONSES, **FIELD_RESPONSES,
               200: {"content": {PNG: {}, codec.NPY: {}},
                     "description": "The frame (PNG, or .npy float32 (H, W, C))."}},
    response_class=Response, openapi_extra=json_body_doc(CameraSpec),
    summary="Render a camera's view of a light field (lines in R^3)")
def render(e: ReadyField, camera: json_body(CameraSpec), settings: SettingsDep,
           accept: Annotated[Optional[str], Header()] = None) -> Response:
    t0 = time.perf_counter()
    cam = camera.camera()
    note(rows=cam.nrays)
    if cam.nrays > settings.max_batch_rows:
        raise BatchTooLargeError(f"{cam.nrays} rays in one frame; the limit is {settings.max_batch_rows}")
    fmt = camera.format or ("npy" if accept and codec.NPY in accept else "png")
    if fmt == "npy":  # float32 (H, W, C): bounded before it is rendered
        codec.check_answer(cam.height * cam.width, e.spec.channels, "npy",
                           max_json=settings.max_json_answer_bytes,
                           max_binary=settings.max_answer_bytes, bytes_per_number=4)
    body, media, timings, coverage = render_frame(
        e.field, cam, fill=0.0 if camera.fill is None else camera.fill, fmt=fmt,
        interpolant=camera.interpolant)
    total = time.perf_counter() - t0
    return Response(body, media_type=media, headers={
        "Server-Timing": server_timing({**timings, "total": total}),
        "X-Coverage": f"{coverage:.6f}",
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
