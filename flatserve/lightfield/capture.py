"""Real captures: posed photographs read as rays and colours.

A capture is a set of images with their cameras, as written by NeRF /
instant-ngp (``transforms.json``) or COLMAP (the text model ``cameras.txt`` +
``images.txt``). :func:`read_capture` reads and checks the poses, intrinsics and
image headers (no pixels); :func:`capture_batches` then streams the capture as
rays and values, one image at a time, and :func:`capture_rays` gathers them.
Each pixel gives one ray, from the camera's eye through the pixel's centre
(:class:`~flatserve.lightfield.camera.PinholeCamera`), with the pixel's colour
as its value.

Images are read with Pillow: grey (8- and 16-bit), RGB and RGBA, PNG (8- and
16-bit) and JPEG; values are floats in [0, 1] (8-bit / 255, 16-bit / 65535).
16-bit RGB, RGBA and grey-alpha PNGs, of which Pillow keeps only the high byte,
are read and written with pypng.

>>> cap = read_capture("scene")                               # doctest: +SKIP
>>> cap.format, len(cap.frames), cap.channels                  # doctest: +SKIP
('colmap', 120, 3)
>>> origins, directions, values = capture_rays(cap, target_rays=100_000)  # doctest: +SKIP

:func:`write_nerf` and :func:`write_colmap` write captures of given cameras and
images (synthetic rigs, tests, benchmarks).
"""
from __future__ import annotations

import json
import math
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from .._validate import as_array
from ..errors import InvalidInputError
from .camera import PinholeCamera

__all__ = [
    "BATCH_RAYS",
    "FORMATS",
    "IMAGE_EXTENSIONS",
    "Capture",
    "CaptureError",
    "CaptureFrame",
    "RayBatch",
    "capture_batches",
    "capture_rays",
    "check_background",
    "field_options",
    "read_capture",
    "read_image",
    "write_colmap",
    "write_nerf",
]

#: Most rays in one batch of :func:`capture_batches` (about 11 MB of float64
#: origins, directions and RGB values).
BATCH_RAYS = 200_000
#: Small grey views of frames (``depth.mvs_view``, at most ``MVS_SIDE`` pixels a side) a depth
#: channel's import keeps: a frame's neighbours are asked for again soon after it.
DEPTH_VIEWS = 64
#: Capture formats :func:`read_capture` reads.
FORMATS = ("nerf", "colmap")
#: Extensions tried, in this order, for a NeRF ``file_path`` without one.
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG")
#: NeRF files :func:`read_capture` looks for, in this order.
NERF_FILES = ("transforms.json", "transforms_train.json")
#: Where, under a capture's folder, :func:`read_capture` looks for a COLMAP model.
COLMAP_DIRS = (".", "sparse/0", "sparse")
#: ITU-R BT.601 luma weights (Pillow's RGB to "L").
LUMA = (0.299, 0.587, 0.114)

_CHANNELS = (1, 3, 4)
# Pillow modes read as grey with this divisor; other modes are converted.
_GREY_MODES = {"1": 255.0, "L": 255.0, "I;16": 65535.0, "I;16L": 65535.0, "I;16B": 65535.0, "I;16N": 65535.0}
# Pillow modes converted to RGB or RGBA before reading.
_CONVERT_MODES = {"RGB": "RGB", "RGBA": "RGBA", "LA": "RGBA", "PA": "RGBA", "La": "RGBA", "RGBa": "RGBA",
                  "CMYK": "RGB", "YCbCr": "RGB", "LAB": "RGB", "HSV": "RGB", "RGBX": "RGB"}
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# (bit depth, colour type) of 16-bit RGB, grey-alpha and RGBA PNGs: read with pypng.
_DEEP_COLOUR_PNG = {(16, 2), (16, 4), (16, 6)}

# COLMAP camera models: parameter names; the pinhole ones first.
_COLMAP_MODELS = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
    "FOV": ("fx", "fy", "cx", "cy", "omega"),
}
# Fisheye models: not a pinhole even without distortion.
_COLMAP_FISHEYE = {"OPENCV_FISHEYE", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "THIN_PRISM_FISHEYE",
                   "RAD_TAN_THIN_PRISM_FISHEYE"}
# instant-ngp's distortion keys: a frame is read only when all are 0.
_NERF_DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")
_NERF_INTRINSICS = ("camera_angle_x", "fl_x", "fl_y", "cx", "cy", "w", "h")
_UNDISTORT = "undistort the images first, e.g. `colmap image_undistorter`, which writes PINHOLE cameras"


class CaptureError(InvalidInputError):
    """A capture that cannot be read: names the file and the field.

    The message reads ``"FILE: FIELD: reason"``, e.g.
    ``"scene/transforms.json: frames[3].transform_matrix: not a rigid transform (...)"``.

    Attributes
    ----------
    file : pathlib.Path
        The file at fault (the pose file, or an image).
    field : str
        Where in it: a JSON path (``frames[3].file_path``), a line
        (``line 7``), or ``size``, ``channels``, ``pixels`` of an image.
    """

    def __init__(self, file, field: str, reason: str):
        self.file = Path(file)
        self.field = field
        self.reason = reason
        super().__init__(f"{file}: {field}: {reason}", field)

    def __reduce__(self):
        return type(self), (self.file, self.field, self.reason)


@dataclass(frozen=True)
class CaptureFrame:
    """One posed image of a capture.

    Attributes
    ----------
    name : str
        Unique in its capture: the image's path as the pose file gives it,
        without a leading ``./`` and without extension (``r_0``,
        ``train/r_0``, ``IMG_0042``).
    image : pathlib.Path
        The image file.
    camera : PinholeCamera
        Its camera; ``width`` and ``height`` are the image's.
    """

    name: str
    image: Path
    camera: PinholeCamera


def _stride_first(n: int, stride: int) -> int:
    """The first pixel kept along a side of ``n`` pixels at ``stride``: ``stride // 2``,
    or the side's middle pixel when the side is shorter (every frame keeps a ray)."""
    return min(stride // 2, (n - 1) // 2)


def _stride_count(n: int, stride: int) -> int:
    """How many pixels of a side of ``n`` are kept at ``stride`` (at least one)."""
    return (n - _stride_first(n, stride) + stride - 1) // stride


def _check_stride(stride) -> int:
    if isinstance(stride, bool) or not isinstance(stride, (int, np.integer)) or stride < 1:
        raise InvalidInputError(f"stride: expected a positive integer, got {stride!r}", "stride")
    return int(stride)


@dataclass(frozen=True)
class Capture:
    """Posed images, as read by :func:`read_capture`.

    Attributes
    ----------
    root : pathlib.Path
        The folder of the pose file (NeRF) or the capture's folder (COLMAP).
    format : str
        ``"nerf"`` or ``"colmap"``.
    frames : tuple of CaptureFrame
        In the pose file's order; names unique.
    channels : int
        Channels of the images: 1 grey, 3 RGB, 4 RGBA (all images have the same).
    """

    root: Path
    format: str
    frames: tuple[CaptureFrame, ...]
    channels: int

    def __post_init__(self):
        object.__setattr__(self, "root", Path(self.root))
        if self.format not in FORMATS:
            raise InvalidInputError(f"format: expected one of {FORMATS}, got {self.format!r}", "format")
        frames = tuple(self.frames)
        if not frames:
            raise InvalidInputError("frames: a capture needs at least one frame", "frames")
        names = [f.name for f in frames]
        if len(set(names)) != len(names):
            dup = sorted({n for n in names if names.count(n) > 1})
            raise InvalidInputError(f"frames: names must be unique, repeated: {dup[:5]}", "frames")
        object.__setattr__(self, "frames", frames)
        if self.channels not in _CHANNELS:
            raise InvalidInputError(f"channels: expected 1, 3 or 4, got {self.channels!r}", "channels")

    @property
    def cameras(self) -> tuple[PinholeCamera, ...]:
        """The frames' cameras, in order."""
        return tuple(f.camera for f in self.frames)

    @property
    def names(self) -> tuple[str, ...]:
        """The frames' names, in order."""
        return tuple(f.name for f in self.frames)

    def nrays(self, stride: int = 1) -> int:
        """Rays of the capture at ``stride``: pixels ``(i, j)`` with ``i = j = stride // 2 (mod stride)``
        (a side shorter than that keeps its middle pixel: every frame gives a ray).

        Parameters
        ----------
        stride : int
            Keep every ``stride``-th pixel in each direction (>= 1).

        Returns
        -------
        int
        """
        s = _check_stride(stride)
        return sum(_stride_count(f.camera.width, s) * _stride_count(f.camera.height, s) for f in self.frames)

    def stride_for(self, target_rays: int) -> int:
        """The smallest stride ``s >= 1`` with ``nrays(s) <= target_rays``.

        Parameters
        ----------
        target_rays : int
            At least the number of frames (one ray each).

        Returns
        -------
        int
        """
        if isinstance(target_rays, bool) or not isinstance(target_rays, (int, np.integer)) \
                or target_rays < len(self.frames):
            raise InvalidInputError(f"target_rays: expected an integer >= the number of frames "
                                    f"({len(self.frames)}), got {target_rays!r}", "target_rays")
        # nrays is non-increasing in the stride; beyond twice every side, one ray a frame
        lo, hi = 1, 2 * max(max(f.camera.width, f.camera.height) for f in self.frames) + 2
        while lo < hi:
            mid = (lo + hi) // 2
            if self.nrays(mid) <= target_rays:
                hi = mid
            else:
                lo = mid + 1
        return lo

    def _pick(self, names, keep: bool) -> "Capture":
        if isinstance(names, str):
            names = [names]
        wanted = set(names)
        unknown = wanted - set(self.names)
        if unknown:
            raise InvalidInputError(f"names: no frames named {sorted(unknown)[:5]} in this capture", "names")
        frames = tuple(f for f in self.frames if (f.name in wanted) == keep)
        if not frames:
            raise InvalidInputError("names: no frames would be left", "names")
        return Capture(root=self.root, format=self.format, frames=frames, channels=self.channels)

    def without(self, names: Iterable[str]) -> "Capture":
        """The capture less the frames named (hold-out views); every name must be a frame's."""
        return self._pick(names, keep=False)

    def take(self, names: Iterable[str]) -> "Capture":
        """The frames named, in the capture's order; every name must be a frame's."""
        return self._pick(names, keep=True)


@dataclass(frozen=True)
class RayBatch:
    """Rays and values of consecutive frames of a capture (:func:`capture_batches`).

    Attributes
    ----------
    origins, directions : (n, 3) float64
        Eyes and unit directions, frame by frame, each frame's rays in
        scanline order.
    values : (n, C) float64
        Pixel values in [0, 1].
    frames : (int, int)
        First and one-past-last index of the frames the batch holds rays of
        (a frame split over batches appears in each).
    index : int
        Batch number, from 0.
    """

    origins: np.ndarray
    directions: np.ndarray
    values: np.ndarray
    frames: tuple[int, int]
    index: int


# ---------------------------------------------------------------- images
def _png_header(path: Path) -> tuple[int, int] | None:
    """(bit depth, colour type) of a PNG file, None for other files."""
    with open(path, "rb") as fh:
        head = fh.read(33)
    if len(head) < 33 or not head.startswith(_PNG_SIGNATURE) or head[12:16] != b"IHDR":
        return None
    return head[24], head[25]


def _is_deep_grey_png(path: Path, mode: str) -> bool:
    """A 16-bit grey PNG opened by Pillow as 32-bit integers (mode "I", as older Pillow versions do)."""
    return mode == "I" and _png_header(path) == (16, 0)


def _pypng():
    """The ``png`` module (pypng), with the extra to install when it is missing."""
    try:
        import png
    except ImportError:
        raise ImportError("16-bit colour PNGs are read and written with pypng: "
                          "pip install 'flatserve[lightfield]'") from None
    return png


def _image_info(path: Path) -> tuple[int, int, int]:
    """(width, height, channels) from an image's header; no pixels decoded."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            width, height = im.size
            mode = im.mode
            transparency = "transparency" in im.info
    except (OSError, ValueError, SyntaxError) as exc:
        raise CaptureError(path, "image", f"unreadable: {exc}") from None
    if mode in _GREY_MODES or _is_deep_grey_png(path, mode):
        return width, height, 1
    if mode == "P":
        return width, height, 4 if transparency else 3
    if mode in _CONVERT_MODES:
        return width, height, 4 if _CONVERT_MODES[mode] == "RGBA" else 3
    raise CaptureError(path, "image", f"unsupported pixel format {mode!r} (expected grey, RGB or RGBA, "
                                      "8 or 16 bits)")


def read_image(path) -> np.ndarray:
    """An image's pixels as floats in [0, 1].

    Parameters
    ----------
    path : str or pathlib.Path

    Returns
    -------
    (H, W, C) float64
        ``C`` 1 (grey), 3 (RGB) or 4 (RGBA); 8-bit values / 255, 16-bit / 65535.
        Grey with alpha is read as RGBA; palette images as RGB (RGBA with
        transparency).

    Raises
    ------
    CaptureError
        The file is missing, is not an image Pillow reads, or its pixels are
        corrupt.

    Notes
    -----
    Pixels are read in the order stored: an EXIF orientation tag is not applied.
    """
    from PIL import Image

    path = Path(path)
    try:
        if _png_header(path) in _DEEP_COLOUR_PNG:
            return _read_deep_png(path)
        with Image.open(path) as im:
            mode = im.mode
            if mode in _GREY_MODES or _is_deep_grey_png(path, mode):
                scale = _GREY_MODES.get(mode, 65535.0)
                a = np.asarray(im.convert("L") if mode == "1" else im)
                return (a.astype(np.float64) / scale)[:, :, None]
            if mode == "P":
                im = im.convert("RGBA" if "transparency" in im.info else "RGB")
            elif mode in _CONVERT_MODES:
                if mode != _CONVERT_MODES[mode]:
                    im = im.convert(_CONVERT_MODES[mode])
            else:
                raise CaptureError(path, "image", f"unsupported pixel format {mode!r}")
            return np.asarray(im).astype(np.float64) / 255.0
    except CaptureError:
        raise
    except FileNotFoundError:
        raise CaptureError(path, "image", "missing") from None
    except (OSError, ValueError, SyntaxError, zlib.error, struct.error) as exc:
        raise CaptureError(path, "pixels", f"unreadable: {exc}") from None


def _read_deep_png(path: Path) -> np.ndarray:
    """Pixels of a 16-bit RGB, RGBA or grey-alpha PNG, (H, W, 3 or 4) in [0, 1]; grey and alpha as RGBA.

    The samples as stored (pypng's ``read``, not ``asDirect``: no alpha
    channel made from ``tRNS``, no rescaling by ``sBIT``), as Pillow reads
    the other images and as :func:`_image_info` counts the channels.
    """
    png = _pypng()
    try:
        width, height, rows, info = png.Reader(filename=str(path)).read()
        samples = np.asarray(list(rows), dtype=np.uint16).reshape(height, width, info["planes"])
    except png.Error as exc:
        raise ValueError(str(exc)) from None
    a = samples.astype(np.float64) / 65535.0
    if info["greyscale"]:
        a = np.concatenate([np.repeat(a[..., :1], 3, axis=2), a[..., 1:]], axis=2)
    return a


def _write_image(path: Path, image: np.ndarray, bits: int) -> None:
    """Write (H, W, C) floats in [0, 1] as PNG (8 or 16 bits) or, by extension, JPEG (8 bits)."""
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    C = image.shape[2]
    top = 255 if bits == 8 else 65535
    q = np.rint(image * top).astype(np.uint8 if bits == 8 else np.uint16)
    if bits == 16 and C > 1:
        writer = _pypng().Writer(q.shape[1], q.shape[0], bitdepth=16, greyscale=False, alpha=C == 4)
        with open(path, "wb") as fh:
            writer.write(fh, q.reshape(q.shape[0], -1).tolist())
        return
    im = Image.fromarray(q[:, :, 0] if C == 1 else q)
    if path.suffix.lower() in (".jpg", ".jpeg"):
        im.save(path, quality=95)
    else:
        im.save(path)


def _convert(values: np.ndarray, want: int, background: np.ndarray) -> np.ndarray:
    """(n, C) values as ``want`` channels: grey repeated, RGB to luma, alpha composited over ``background``.

    ``background`` is (3,) RGB in [0, 1].
    """
    have = values.shape[1]
    if have == want:
        return values
    if have == 4:  # composite over the background
        alpha = values[:, 3:4]
        rgb = values[:, :3] * alpha + background[None, :] * (1.0 - alpha)
        return _convert(rgb, want, background)
    if have == 1:
        rgb = np.repeat(values, 3, axis=1)
        return rgb if want == 3 else _convert(rgb, want, background)
    # have == 3
    if want == 1:
        return (values @ np.asarray(LUMA))[:, None]
    return np.concatenate([values, np.ones((values.shape[0], 1))], axis=1)  # want == 4


# ---------------------------------------------------------------- reading
def _number(value, file, field: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise CaptureError(file, field, f"expected a finite number, got {value!r}")
    return float(value)


def _integer(value, file, field: str) -> int:
    v = _number(value, file, field)
    if v != int(v) or v < 1:
        raise CaptureError(file, field, f"expected a positive integer, got {value!r}")
    return int(v)


def _frame_name(written: str) -> str:
    """A frame's name from the image path a pose file gives: no ``./``, no extension."""
    p = written.replace("\\", "/")
    while p.startswith("./"):
        p = p[2:]
    stem, dot, ext = p.rpartition(".")
    if dot and "/" not in ext and ext.lower() in {e[1:].lower() for e in IMAGE_EXTENSIONS} | {"tif", "tiff", "bmp",
                                                                                              "webp", "exr"}:
        return stem
    return p


def _checked_image(path: Path, width: int | None, height: int | None, source: str) -> tuple[int, int, int]:
    """(width, height, channels) of the image at ``path``, checked against the size ``source`` gives."""
    w, h, c = _image_info(path)
    if width is not None and (w, h) != (width, height):
        raise CaptureError(path, "size", f"the image is {w}x{h} but {source} says {width}x{height} "
                                         "(images resized after the poses were made?)")
    return w, h, c


def _same_channels(frames_channels: list[tuple[Path, int]]) -> int:
    first_path, first = frames_channels[0]
    for path, c in frames_channels[1:]:
        if c != first:
            raise CaptureError(path, "channels", f"{c} channel(s), but the first image {first_path} has {first}")
    return first


def _read_nerf(file: Path) -> Capture:
    try:
        text = file.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise CaptureError(file, "file", f"unreadable: {exc}") from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise CaptureError(file, f"line {exc.lineno}", f"malformed JSON: {exc.msg} (column {exc.colno})") from None
    if not isinstance(doc, dict):
        raise CaptureError(file, "(top level)", f"expected a JSON object, got {type(doc).__name__}")
    frames = doc.get("frames")
    if not isinstance(frames, list):
        raise CaptureError(file, "frames", "expected a list of frames" + ("" if frames is not None else ", missing"))
    if not frames:
        raise CaptureError(file, "frames", "no frames")
    _check_nerf_model(doc, file, "")
    folder = file.parent
    out = []
    seen: dict[str, int] = {}
    channels = []
    for k, fr in enumerate(frames):
        where = f"frames[{k}]"
        if not isinstance(fr, dict):
            raise CaptureError(file, where, f"expected an object, got {type(fr).__name__}")
        _check_nerf_model(fr, file, where + ".")
        written = fr.get("file_path")
        if not isinstance(written, str) or not written:
            raise CaptureError(file, where + ".file_path", f"expected an image path, got {written!r}")
        image = _find_nerf_image(folder, written, file, where)
        name = _frame_name(written)
        if name in seen:
            raise CaptureError(file, where + ".file_path", f"frame name {name!r} repeats frames[{seen[name]}]")
        seen[name] = k
        if "transform_matrix" not in fr:
            raise CaptureError(file, where + ".transform_matrix", "missing")
        # intrinsics: the frame's own override the file's; a frame's focal length replaces both of the file's
        intr = {key: doc[key] for key in _NERF_INTRINSICS if key in doc}
        if "fl_x" in fr or "camera_angle_x" in fr:
            for key in ("fl_x", "fl_y", "camera_angle_x"):
                intr.pop(key, None)
        intr.update({key: fr[key] for key in _NERF_INTRINSICS if key in fr})
        field_of = {key: (where + "." if key in fr else "") + key for key in intr}
        for key in ("camera_angle_x", "fl_x", "fl_y", "cx", "cy"):
            if key in intr:
                intr[key] = _number(intr[key], file, field_of[key])
        size = None
        if "w" in intr or "h" in intr:
            if not ("w" in intr and "h" in intr):
                key = "h" if "w" in intr else "w"
                raise CaptureError(file, where + "." + key, "w and h go together, only one is given")
            size = (_integer(intr["w"], file, field_of["w"]), _integer(intr["h"], file, field_of["h"]))
        w, h, c = _checked_image(image, *(size or (None, None)), source=f"{file} ({where}: w, h)")
        channels.append((image, c))
        try:
            cam = PinholeCamera.from_nerf(fr["transform_matrix"], width=w, height=h,
                                          camera_angle_x=intr.get("camera_angle_x"), fl_x=intr.get("fl_x"),
                                          fl_y=intr.get("fl_y"), cx=intr.get("cx"), cy=intr.get("cy"))
        except InvalidInputError as exc:
            arg = exc.argument or "transform_matrix"
            key = {"width": "w", "height": "h"}.get(arg, arg)
            field = field_of.get(key, where + "." + key)
            raise CaptureError(file, field, _strip(str(exc), arg)) from None
        out.append(CaptureFrame(name=name, image=image, camera=cam))
    return Capture(root=folder, format="nerf", frames=tuple(out), channels=_same_channels(channels))


def _strip(message: str, argument: str) -> str:
    prefix = argument + ": "
    return message[len(prefix):] if message.startswith(prefix) else message


def _check_nerf_model(obj: dict, file: Path, where: str) -> None:
    """Refuse instant-ngp distortion and fisheye cameras."""
    if obj.get("is_fisheye"):
        raise CaptureError(file, where + "is_fisheye", "fisheye cameras are not pinholes: " + _UNDISTORT)
    model = obj.get("camera_model")
    if model is not None and model not in ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE"):
        raise CaptureError(file, where + "camera_model", f"camera model {model!r} is not a pinhole: " + _UNDISTORT)
    bad = {k: obj[k] for k in _NERF_DISTORTION if k in obj}
    for k, v in bad.items():
        _number(v, file, where + k)
    bad = {k: v for k, v in bad.items() if v != 0}
    if bad:
        listed = ", ".join(f"{k}={v!r}" for k, v in bad.items())
        raise CaptureError(file, where + next(iter(bad)), f"lens distortion {listed}: " + _UNDISTORT)


def _find_nerf_image(folder: Path, written: str, file: Path, where: str) -> Path:
    base = folder / written
    tried = [base]
    if base.is_file():
        return base
    for ext in IMAGE_EXTENSIONS:
        cand = base.with_name(base.name + ext)
        tried.append(cand)
        if cand.is_file():
            return cand
    raise CaptureError(file, where + ".file_path", f"no image {written!r}: tried {', '.join(map(str, tried))}")


def _data_lines(file: Path) -> list[tuple[int, str]]:
    """(line number, text) of a COLMAP text file, comments dropped, blank lines kept."""
    try:
        text = file.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise CaptureError(file, "file", f"unreadable: {exc}") from None
    return [(n, line.strip()) for n, line in enumerate(text.splitlines(), start=1)
            if not line.lstrip().startswith("#")]


def _colmap_cameras(file: Path) -> dict[int, tuple[int, int, dict, int]]:
    """camera id -> (width, height, PINHOLE intrinsics dict, line)."""
    cams = {}
    for n, line in _data_lines(file):
        if not line:
            continue
        where = f"line {n}"
        tok = line.split()
        if len(tok) < 4:
            raise CaptureError(file, where, "expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS...")
        try:
            cid, width, height = int(tok[0]), int(tok[2]), int(tok[3])
            params = [float(t) for t in tok[4:]]
        except ValueError as exc:
            raise CaptureError(file, where, f"expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS...: {exc}") from None
        if cid in cams:
            raise CaptureError(file, where, f"camera {cid} repeats line {cams[cid][3]}")
        model = tok[1]
        if model in _COLMAP_FISHEYE:
            raise CaptureError(file, where, f"camera {cid}: model {model} is a fisheye, not a pinhole: "
                                            + _UNDISTORT)
        if model not in _COLMAP_MODELS:
            raise CaptureError(file, where, f"camera {cid}: unknown camera model {model!r} (read: "
                                            f"{', '.join(_COLMAP_MODELS)})")
        names = _COLMAP_MODELS[model]
        if len(params) != len(names):
            raise CaptureError(file, where, f"camera {cid}: model {model} has {len(names)} parameters "
                                            f"({' '.join(names)}), got {len(params)}")
        if not all(math.isfinite(p) for p in params):
            raise CaptureError(file, where, f"camera {cid}: non-finite parameters {params}")
        p = dict(zip(names, params))
        distortion = {k: v for k, v in p.items() if k not in ("f", "fx", "fy", "cx", "cy") and v != 0}
        if distortion:
            listed = ", ".join(f"{k}={v:g}" for k, v in distortion.items())
            raise CaptureError(file, where, f"camera {cid}: model {model} with distortion {listed}: " + _UNDISTORT)
        fx = p.get("fx", p.get("f"))
        fy = p.get("fy", p.get("f"))
        if width < 1 or height < 1:
            raise CaptureError(file, where, f"camera {cid}: size {width}x{height} is not positive")
        cams[cid] = (width, height, {"fx": fx, "fy": fy, "cx": p["cx"], "cy": p["cy"]}, n)
    return cams


def _colmap_model_dir(root: Path) -> Path | None:
    for sub in COLMAP_DIRS:
        d = root / sub
        if (d / "cameras.txt").is_file() and (d / "images.txt").is_file():
            return d
    return None


def _read_colmap(root: Path, model: Path) -> Capture:
    cam_file, img_file = model / "cameras.txt", model / "images.txt"
    cams = _colmap_cameras(cam_file)
    lines = _data_lines(img_file)
    out = []
    channels = []
    ids: dict[int, int] = {}
    seen: dict[str, int] = {}
    k = 0
    while k < len(lines):
        n, line = lines[k]
        k += 1
        if not line:
            continue
        where = f"line {n}"
        tok = line.split(maxsplit=9)
        if len(tok) < 10:
            raise CaptureError(img_file, where, "expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME")
        try:
            iid = int(tok[0])
            q = [float(t) for t in tok[1:5]]
            t = [float(t) for t in tok[5:8]]
            cid = int(tok[8])
        except ValueError as exc:
            raise CaptureError(img_file, where, f"expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME: {exc}") \
                from None
        name_written = tok[9].strip()
        # the 2D points: the next line, possibly empty (triples X Y POINT3D_ID)
        if k < len(lines):
            pn, points = lines[k]
            if len(points.split()) % 3:
                raise CaptureError(img_file, f"line {pn}", f"expected the 2D points of image {iid} (triples "
                                                           "X Y POINT3D_ID) or an empty line")
            k += 1
        if iid in ids:
            raise CaptureError(img_file, where, f"image id {iid} repeats line {ids[iid]}")
        ids[iid] = n
        if cid not in cams:
            raise CaptureError(img_file, where, f"image {name_written}: camera {cid} is not in {cam_file}")
        name = _frame_name(name_written)
        if name in seen:
            raise CaptureError(img_file, where, f"image name {name_written!r} repeats line {seen[name]}")
        seen[name] = n
        tried = [root / "images" / name_written, model / name_written]
        image = next((p for p in tried if p.is_file()), None)
        if image is None:
            raise CaptureError(img_file, where, f"image {name_written}: not found (tried "
                                                f"{', '.join(map(str, tried))})")
        width, height, intr, cline = cams[cid]
        w, h, c = _checked_image(image, width, height, source=f"camera {cid} ({cam_file} line {cline})")
        channels.append((image, c))
        try:
            cam = PinholeCamera.from_colmap(q, t, width=w, height=h, **intr)
        except InvalidInputError as exc:
            arg = exc.argument or "qvec"
            file = cam_file if arg in ("fx", "fy", "cx", "cy") else img_file
            raise CaptureError(file, f"line {cline if file == cam_file else n}",
                               f"image {name_written}: {exc}") from None
        out.append(CaptureFrame(name=name, image=image, camera=cam))
    if not out:
        raise CaptureError(img_file, "images", "no frames")
    return Capture(root=root, format="colmap", frames=tuple(out), channels=_same_channels(channels))


def read_capture(path, format: str | None = None) -> Capture:
    """Read a capture's poses, intrinsics and image headers (no pixels).

    Parameters
    ----------
    path : str or pathlib.Path
        The capture's folder, or its NeRF ``.json`` file. In a folder, a NeRF
        capture is ``transforms.json`` (else ``transforms_train.json``); a
        COLMAP capture is the text model ``cameras.txt`` + ``images.txt`` in
        the folder, ``sparse/0`` or ``sparse`` (images in ``images/NAME``,
        else next to the model).
    format : {"nerf", "colmap"}, optional
        Detected when not given (NeRF first).

    Returns
    -------
    Capture

    Raises
    ------
    CaptureError
        Naming the file and the field: nothing found where looked; malformed
        JSON or text (with the line); no frames; a missing image (with the
        paths tried); a pose that is not rigid; a camera model that is not a
        pinhole, or one with lens distortion; an image whose size differs from
        its camera's; images of different channel counts; an unreadable image.

    Notes
    -----
    NeRF: top-level ``camera_angle_x`` or ``fl_x`` / ``fl_y`` / ``cx`` /
    ``cy``, and ``w`` / ``h`` (else each image's size), each of which a frame
    may override; ``file_path`` relative to the JSON file's folder, with or
    without extension (then :data:`IMAGE_EXTENSIONS` are tried in order).
    COLMAP: models PINHOLE and SIMPLE_PINHOLE; SIMPLE_RADIAL, RADIAL, OPENCV,
    FULL_OPENCV and FOV only with every distortion parameter 0.
    """
    path = Path(path)
    if format is not None and format not in FORMATS:
        raise InvalidInputError(f"format: expected one of {FORMATS} or None, got {format!r}", "format")
    if path.is_file():
        if format == "colmap":
            raise CaptureError(path, "format", "a COLMAP capture is a folder (cameras.txt and images.txt)")
        return _read_nerf(path)
    if not path.is_dir():
        raise CaptureError(path, "path", "no such file or folder")
    if format in (None, "nerf"):
        for name in NERF_FILES:
            if (path / name).is_file():
                return _read_nerf(path / name)
        if format == "nerf":
            raise CaptureError(path, "format", f"no NeRF capture: none of {', '.join(NERF_FILES)}")
    model = _colmap_model_dir(path)
    if model is not None:
        return _read_colmap(path, model)
    looked = ", ".join(str(path / d) for d in COLMAP_DIRS)
    binary = [str(path / d) for d in COLMAP_DIRS if (path / d / "images.bin").is_file()]
    hint = (f"; a binary model is in {binary[0]}: convert it with `colmap model_converter "
            "--output_type TXT`") if binary else ""
    if format == "colmap":
        raise CaptureError(path, "format", f"no COLMAP text model (cameras.txt and images.txt) in {looked}{hint}")
    raise CaptureError(path, "format", f"no capture found: looked for {' or '.join(NERF_FILES)} (NeRF) and for "
                                       f"cameras.txt and images.txt (COLMAP) in {looked}{hint}")


# ---------------------------------------------------------------- rays
def _check_options(capture: Capture, channels, background) -> tuple[int, np.ndarray]:
    if not isinstance(capture, Capture):
        raise InvalidInputError(f"capture: expected a Capture, got {type(capture).__name__}", "capture")
    if channels is None:
        channels = capture.channels
    elif isinstance(channels, bool) or channels not in _CHANNELS:
        raise InvalidInputError(f"channels: expected 1, 3, 4 or None, got {channels!r}", "channels")
    return int(channels), check_background(background)


def check_background(background) -> np.ndarray:
    """``background`` (a grey level or an RGB colour in [0, 1]) as a (3,) RGB colour.

    Raises
    ------
    InvalidInputError
        Naming ``background``: not a number or three, or outside [0, 1].

    Examples
    --------
    >>> check_background(0.5).tolist()
    [0.5, 0.5, 0.5]
    """
    try:
        bg = None if isinstance(background, bool) else np.asarray(background, dtype=np.float64)
    except (TypeError, ValueError):
        bg = None
    if bg is None or bg.shape not in ((), (1,), (3,)):
        raise InvalidInputError(f"background: expected a grey level or an RGB colour in [0, 1], got "
                                f"{background!r}"[:300], "background")
    bg = as_array(np.broadcast_to(bg.reshape(-1), (3,)), "background", (3,))
    if not (np.all(bg >= 0) and np.all(bg <= 1)):
        raise InvalidInputError(f"background: expected values in [0, 1], got {background!r}", "background")
    return bg


def _frame_image(frame: CaptureFrame, capture_channels: int) -> np.ndarray:
    """A frame's image read and checked against its camera and the capture (H, W, C)."""
    cam = frame.camera
    img = read_image(frame.image)
    H, W, C = img.shape
    if (W, H) != (cam.width, cam.height):
        raise CaptureError(frame.image, "size", f"the image is {W}x{H}, its camera {cam.width}x{cam.height}")
    if C != capture_channels:
        raise CaptureError(frame.image, "channels", f"{C} channel(s), the capture's images have {capture_channels}")
    return img


class _Images:
    """A capture's images read on demand, the last ``keep`` kept."""

    def __init__(self, capture: Capture, keep: int):
        self.capture, self.keep = capture, keep
        self.cache: dict[int, np.ndarray] = {}

    def __call__(self, k: int) -> np.ndarray:
        if k in self.cache:
            self.cache[k] = self.cache.pop(k)  # most recently used last
            return self.cache[k]
        img = _frame_image(self.capture.frames[k], self.capture.channels)
        self.cache[k] = img
        while len(self.cache) > self.keep:
            self.cache.pop(next(iter(self.cache)))
        return img


class _Recent(dict):
    """A mapping that keeps its ``keep`` most recently used entries (the depth maps' small
    grey views of the frames: bounded by their size, not the photographs')."""

    def __init__(self, keep: int):
        super().__init__()
        self.keep = keep

    def __getitem__(self, k):
        v = super().pop(k)
        super().__setitem__(k, v)
        return v

    def __setitem__(self, k, v):
        super().pop(k, None)
        super().__setitem__(k, v)
        while len(self) > self.keep:
            super().pop(next(iter(self)))


def _frame_rays(capture: Capture, k: int, stride: int, channels: int, background: np.ndarray,
                images: "_Images", rig, views) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays and values of frame ``k`` at ``stride`` (the depth channel last with a ``rig``)."""
    cam = capture.frames[k].camera
    img = images(k)
    H, W, C = img.shape
    cols = np.arange(_stride_first(W, stride), W, stride)
    rows = np.arange(_stride_first(H, stride), H, stride)
    o, d = cam.grid_rays(cols + 0.5, rows + 0.5)
    values = _convert(img[rows[:, None], cols[None, :]].reshape(-1, C), channels, background)
    if rig is None:
        return o, d, values
    from .depth import depth_map, depth_values

    t = depth_map(k, capture.cameras, images, center=rig.center, views=views)[rows[:, None], cols[None, :]]
    t = t.reshape(-1)
    return o, d, np.concatenate([values, depth_values(o, d, t, rig.center)[:, None]], axis=1)


def capture_batches(capture: Capture, *, stride: int = 1, channels: int | None = None, background=0.0,
                    batch_rays: int = BATCH_RAYS, depth=None) -> Iterator[RayBatch]:
    """Stream a capture as batches of rays and values, reading one image at a time.

    The rays are those of the pixels ``(i, j)`` (column, row) with ``i = j =
    stride // 2 (mod stride)`` (:meth:`Capture.nrays`: every frame gives at least
    one), each through its pixel's centre with the
    pixel's own value, frame by frame in the capture's order, each frame in
    scanline order. Whole frames are gathered into a batch while it holds at
    most ``batch_rays`` rays; a frame with more rays than that is split into
    nearly equal batches of its own. The same capture and options give the
    same batches.

    Parameters
    ----------
    capture : Capture
    stride : int
        Keep every ``stride``-th pixel in each direction.
    channels : {1, 3, 4}, optional
        Channels of the values; default the images'. Grey to RGB repeats the
        grey; RGB to grey is the ITU-R 601 luma (:data:`LUMA`); RGBA to RGB or
        grey composites over ``background``; RGB to RGBA has alpha 1.
    background : float or (3,) float
        Grey level or RGB colour in [0, 1] behind transparent pixels.
    batch_rays : int
        Most rays in a batch (:data:`BATCH_RAYS`).
    depth : flatserve.lightfield.rig.DepthRig, optional
        Append the depth channel: each frame's depth map
        (:func:`flatserve.lightfield.depth.depth_map`, from the frame and its
        nearest cameras' images, read as needed; their small grey views, at
        most :data:`DEPTH_VIEWS`, kept) as
        :func:`flatserve.lightfield.depth.depth_values` measured from the rig's
        centre. :func:`field_options` gives the rig when the capture wants it.

    Yields
    ------
    RayBatch
        ``origins``, ``directions`` (n, 3), ``values`` (n, channels, plus
        one with ``depth``), the frames covered and the batch number.

    Raises
    ------
    CaptureError
        An image that cannot be decoded, or whose size or channels changed
        since :func:`read_capture`.
    """
    stride = _check_stride(stride)
    want, bg = _check_options(capture, channels, background)
    if isinstance(batch_rays, bool) or not isinstance(batch_rays, (int, np.integer)) or batch_rays < 1:
        raise InvalidInputError(f"batch_rays: expected a positive integer, got {batch_rays!r}", "batch_rays")
    rig = _check_depth(capture, depth)
    images = _Images(capture, keep=1)
    views = None if rig is None else _Recent(DEPTH_VIEWS)
    index = 0
    pending: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    pending_rays = 0
    first = 0

    def flush(end: int) -> RayBatch:
        # the frames' arrays are let go before the batch is handed over (held once)
        nonlocal pending, pending_rays
        o, d, v = (np.concatenate([p[i] for p in pending]) for i in range(3))
        pending, pending_rays = [], 0
        return RayBatch(origins=o, directions=d, values=v, frames=(first, end), index=index)

    for k, frame in enumerate(capture.frames):
        n = _stride_count(frame.camera.width, stride) * _stride_count(frame.camera.height, stride)
        if pending and pending_rays + n > batch_rays:
            yield flush(k)
            index += 1
        rays = _frame_rays(capture, k, stride, want, bg, images, rig, views)
        if n > batch_rays:
            o, d, v = rays
            del rays
            pieces = -(-n // batch_rays)
            cuts = [n * p // pieces for p in range(pieces + 1)]
            for a, b in zip(cuts[:-1], cuts[1:]):
                yield RayBatch(origins=o[a:b], directions=d[a:b], values=v[a:b], frames=(k, k + 1), index=index)
                index += 1
            del o, d, v
            continue
        if not pending:
            first = k
        pending.append(rays)
        pending_rays += n
        del rays
    if pending:
        yield flush(len(capture.frames))


def _check_depth(capture: Capture, depth):
    if depth is None:
        return None
    from .rig import DepthRig

    if not isinstance(depth, DepthRig):
        raise InvalidInputError(f"depth: expected a DepthRig or None, got {type(depth).__name__}", "depth")
    if len(capture.frames) < 2:
        raise InvalidInputError("depth: a depth map needs at least 2 frames", "depth")
    return depth


def capture_rays(capture: Capture, *, stride: int = 1, target_rays: int | None = None, channels: int | None = None,
                 background=0.0, depth=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A capture as rays and values in memory (without a server).

    Parameters
    ----------
    capture : Capture
    stride : int
        Keep every ``stride``-th pixel in each direction (:func:`capture_batches`).
    target_rays : int, optional
        Instead of ``stride``: the smallest stride giving at most this many
        rays (:meth:`Capture.stride_for`).
    channels, background, depth
        As :func:`capture_batches`.

    Returns
    -------
    origins : (n, 3) float64
    directions : (n, 3) float64
        Unit.
    values : (n, C) float64
        In [0, 1] (the depth channel last with ``depth``).
    """
    if target_rays is not None:
        if not (isinstance(stride, (int, np.integer)) and stride == 1):
            raise InvalidInputError("target_rays: give stride or target_rays, not both", "target_rays")
        stride = capture.stride_for(target_rays)
    stride = _check_stride(stride)
    want, _ = _check_options(capture, channels, background)
    n = capture.nrays(stride)
    o, d, v = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, want + (depth is not None)))
    at = 0
    for batch in capture_batches(capture, stride=stride, channels=channels, background=background,
                                 depth=depth):
        m = batch.origins.shape[0]
        o[at:at + m], d[at:at + m], v[at:at + m] = batch.origins, batch.directions, batch.values
        at += m
    return o, d, v


def field_options(capture: Capture, channels: int | None = None, depth: bool | None = None) -> dict:
    """Keyword arguments of ``create_field`` for a field that will hold this capture.

    The choices that won on captures (``docs/capture-results.md``): an oriented
    atlas with charts where the capture's rays are, through the point its
    cameras look at, in the unit that weighs a pixel's shift as a camera's
    turn (:func:`flatserve.lightfield.rig.field_spec`); on a sparse rig all
    around (:func:`flatserve.lightfield.rig.wants_depth`) the depth channel
    too and the ``rig`` it is measured from: the field's renders go through it.

    Parameters
    ----------
    capture : Capture
    channels : {1, 3, 4}, optional
        The field's colour channels (default the images').
    depth : bool, optional
        Give the field the depth channel (True), not (False), or when the rig
        wants it (None: :func:`flatserve.lightfield.rig.wants_depth`).

    Returns
    -------
    dict
        ``channels`` (the colour channels, plus one for the depth channel),
        ``oriented``, ``basis``, ``unit``, and ``rig`` (a
        :meth:`flatserve.lightfield.rig.DepthRig.to_dict`) when the capture
        gets depth: pass ``depth=DepthRig.from_dict(options["rig"])`` to
        :func:`capture_batches`.
    """
    from .rig import field_spec

    want = capture.channels if channels is None else channels
    if depth is not None and not isinstance(depth, bool):
        raise InvalidInputError(f"depth: expected true, false or none, got {depth!r}", "depth")
    if depth and len(capture.frames) < 2:
        raise InvalidInputError("depth: a depth map needs at least 2 frames", "depth")
    return field_spec(capture.cameras, want, depth=depth)


# ---------------------------------------------------------------- writing
def _writer_inputs(cameras, images, names, bits) -> tuple[list[PinholeCamera], list[np.ndarray], list[str]]:
    cameras = list(cameras)
    images = list(images)
    if not cameras:
        raise InvalidInputError("cameras: expected at least one camera", "cameras")
    for k, cam in enumerate(cameras):
        if not isinstance(cam, PinholeCamera):
            raise InvalidInputError(f"cameras[{k}]: expected a PinholeCamera, got {type(cam).__name__}", "cameras")
    if len(images) != len(cameras):
        raise InvalidInputError(f"images: expected one per camera ({len(cameras)}), got {len(images)}", "images")
    if bits not in (8, 16):
        raise InvalidInputError(f"bits: expected 8 or 16, got {bits!r}", "bits")
    out = []
    for k, (cam, img) in enumerate(zip(cameras, images)):
        a = np.asarray(img, dtype=np.float64)
        if a.ndim == 2:
            a = a[:, :, None]
        a = as_array(a, f"images[{k}]", (cam.height, cam.width, None))
        if a.shape[2] not in _CHANNELS:
            raise InvalidInputError(f"images[{k}]: expected 1, 3 or 4 channels, got {a.shape[2]}", "images")
        if not (np.all(a >= 0) and np.all(a <= 1)):
            raise InvalidInputError(f"images[{k}]: expected values in [0, 1]", "images")
        out.append(a)
    if names is None:
        names = [f"frame_{k:04d}" for k in range(len(cameras))]
    names = [str(n) for n in names]
    if len(names) != len(cameras) or len(set(names)) != len(names):
        raise InvalidInputError("names: expected one unique name per camera", "names")
    return cameras, out, names


def _image_file(name: str, bits: int) -> str:
    """The file of frame ``name``: ``NAME.png``, or ``name`` itself when it ends in .jpg / .jpeg / .png."""
    if name.lower().endswith((".jpg", ".jpeg", ".png")):
        if bits != 8 and not name.lower().endswith(".png"):
            raise InvalidInputError(f"names: {name!r}: JPEG holds 8 bits, not {bits}", "names")
        return name
    return name + ".png"


def write_nerf(dir, cameras: list[PinholeCamera], images: list[np.ndarray], *, names=None, bits: int = 8,
               angle: bool = True) -> Path:
    """Write a NeRF capture: ``transforms.json`` and the images beside it.

    Parameters
    ----------
    dir : str or pathlib.Path
        Folder (created).
    cameras : list of PinholeCamera
    images : list of (H, W) or (H, W, C) float
        In [0, 1], one per camera, of its size; ``C`` 1, 3 or 4.
    names : list of str, optional
        Frame names (default ``frame_0000``, ...); the image of ``NAME`` is
        ``NAME.png`` (or ``NAME`` itself if it ends in ``.png``, ``.jpg`` or
        ``.jpeg``: JPEG, quality 95).
    bits : {8, 16}
        PNG bit depth.
    angle : bool
        Write ``camera_angle_x`` (needs ``cx = w / 2``, ``cy = h / 2`` and
        ``fx = fy``); else ``fl_x``, ``fl_y``, ``cx``, ``cy``. ``w`` and ``h``
        are written either way; intrinsics shared by every frame are written
        once at the top, else per frame.

    Returns
    -------
    pathlib.Path
        The ``transforms.json`` written.
    """
    cameras, images, names = _writer_inputs(cameras, images, names, bits)
    root = Path(dir)
    root.mkdir(parents=True, exist_ok=True)
    intrinsics = []
    frames = []
    for k, (cam, img, name) in enumerate(zip(cameras, images, names)):
        d = cam.to_nerf()
        if angle:
            if not (math.isclose(cam.cx, cam.width / 2, rel_tol=1e-12) and math.isclose(cam.cy, cam.height / 2,
                                                                                       rel_tol=1e-12)
                    and math.isclose(cam.fx, cam.fy, rel_tol=1e-12)):
                raise InvalidInputError(f"cameras[{k}]: camera_angle_x needs cx = w/2, cy = h/2 and fx = fy "
                                        "(write with angle=False)", "cameras")
            intr = {"camera_angle_x": 2 * math.atan(0.5 * cam.width / cam.fx)}
        else:
            intr = {"fl_x": d["fl_x"], "fl_y": d["fl_y"], "cx": d["cx"], "cy": d["cy"]}
        intr.update(w=d["w"], h=d["h"])
        intrinsics.append(intr)
        file = _image_file(name, bits)
        _write_image(root / file, img, bits)
        frames.append({"file_path": "./" + file, "transform_matrix": d["transform_matrix"]})
    doc: dict = {}
    if all(i == intrinsics[0] for i in intrinsics):
        doc.update(intrinsics[0])
    else:
        for fr, intr in zip(frames, intrinsics):
            fr.update(intr)
    doc["frames"] = frames
    out = root / "transforms.json"
    out.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    return out


_WRITE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV", "SIMPLE_RADIAL")


def write_colmap(dir, cameras: list[PinholeCamera], images: list[np.ndarray], *, names=None, bits: int = 8,
                 model: str = "PINHOLE") -> Path:
    """Write a COLMAP text capture: ``sparse/0/{cameras,images,points3D}.txt`` and ``images/NAME``.

    Parameters
    ----------
    dir : str or pathlib.Path
        Folder (created).
    cameras, images, names, bits
        As :func:`write_nerf`; the image of ``NAME`` is ``images/NAME.png``
        (or ``images/NAME`` if it ends in ``.png``, ``.jpg``, ``.jpeg``).
    model : {"PINHOLE", "SIMPLE_PINHOLE", "OPENCV", "SIMPLE_RADIAL"}
        Camera model written; SIMPLE_* need ``fx = fy``; OPENCV and
        SIMPLE_RADIAL are written with zero distortion. Cameras of equal
        intrinsics share one camera id.

    Returns
    -------
    pathlib.Path
        The model's folder (``DIR/sparse/0``).
    """
    if model not in _WRITE_MODELS:
        raise InvalidInputError(f"model: expected one of {_WRITE_MODELS}, got {model!r}", "model")
    cameras, images, names = _writer_inputs(cameras, images, names, bits)
    root = Path(dir)
    sparse = root / "sparse" / "0"
    sparse.mkdir(parents=True, exist_ok=True)
    (root / "images").mkdir(parents=True, exist_ok=True)
    cam_ids: dict[tuple, int] = {}
    cam_lines = ["# Camera list with one line of data per camera:",
                 "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"]
    img_lines = ["# Image list with two lines of data per image:",
                 "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
                 "#   POINTS2D[] as (X, Y, POINT3D_ID)"]
    for k, (cam, img, name) in enumerate(zip(cameras, images, names)):
        d = cam.to_colmap()
        if model.startswith("SIMPLE"):
            if cam.fx != cam.fy:
                raise InvalidInputError(f"cameras[{k}]: model {model} needs fx = fy", "cameras")
            params = [cam.fx, cam.cx, cam.cy] + ([0.0] if model == "SIMPLE_RADIAL" else [])
        else:
            params = [cam.fx, cam.fy, cam.cx, cam.cy] + ([0.0] * 4 if model == "OPENCV" else [])
        key = (cam.width, cam.height, *params)
        if key not in cam_ids:
            cam_ids[key] = len(cam_ids) + 1
            cam_lines.append(" ".join([str(cam_ids[key]), model, str(cam.width), str(cam.height)]
                                      + [repr(float(p)) for p in params]))
        file = _image_file(name, bits)
        _write_image(root / "images" / file, img, bits)
        img_lines.append(" ".join([str(k + 1)] + [repr(float(x)) for x in d["qvec"] + d["tvec"]]
                                  + [str(cam_ids[key]), file]))
        img_lines.append("")
    (sparse / "cameras.txt").write_text("\n".join(cam_lines) + "\n", encoding="utf-8")
    (sparse / "images.txt").write_text("\n".join(img_lines) + "\n", encoding="utf-8")
    (sparse / "points3D.txt").write_text("# 3D point list (empty)\n", encoding="utf-8")
    return sparse
