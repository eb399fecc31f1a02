"""Image quality of reconstructions against ground truth, on covered pixels.

PSNR is computed here; SSIM comes from scikit-image
(:func:`skimage.metrics.structural_similarity`), averaged over the covered
pixels of its full SSIM map. Both take ``data_range`` (1 for images in [0, 1]).
"""
from __future__ import annotations

import math

import numpy as np

from .._validate import as_array
from ..errors import InvalidInputError

__all__ = ["psnr", "ssim", "DATA_RANGE"]

#: Pixel values live in [0, 1].
DATA_RANGE = 1.0


def _pair(image, truth, mask):
    a = np.asarray(image, dtype=np.float64)
    b = np.asarray(truth, dtype=np.float64)
    if a.shape != b.shape or a.ndim not in (2, 3):
        raise InvalidInputError(f"image: expected the shape of truth {b.shape} ((H, W) or (H, W, C)), got {a.shape}", "image")
    if a.ndim == 2:
        a, b = a[..., None], b[..., None]
    if mask is None:
        mask = np.ones(a.shape[:2], dtype=bool)
    mask = as_array(mask, "mask", a.shape[:2], dtype=bool, finite=False)
    return a, b, mask


def psnr(image, truth, mask=None, data_range: float = DATA_RANGE) -> float:
    """Peak signal-to-noise ratio in dB over the masked pixels.

    Parameters
    ----------
    image, truth : (H, W) or (H, W, C) float
    mask : (H, W) bool, optional
        Pixels to compare (default all).
    data_range : float
        Peak value.

    Returns
    -------
    float
        ``10 log10(data_range^2 / MSE)``; ``inf`` for identical pixels, NaN
        for an empty mask.
    """
    a, b, m = _pair(image, truth, mask)
    if not m.any():
        return float("nan")
    mse = float(np.mean((a[m] - b[m]) ** 2))
    if mse == 0:
        return float("inf")
    return 10.0 * math.log10(data_range**2 / mse)


def ssim(image, truth, mask=None, data_range: float = DATA_RANGE) -> float:
    """Mean structural similarity over the masked pixels (scikit-image's SSIM map).

    Parameters
    ----------
    image, truth : (H, W) or (H, W, C) float
    mask : (H, W) bool, optional
    data_range : float

    Returns
    -------
    float
        In [-1, 1]; NaN for an empty mask.
    """
    from skimage.metrics import structural_similarity

    a, b, m = _pair(image, truth, mask)
    if not m.any():
        return float("nan")
    _, smap = structural_similarity(a, b, data_range=data_range, channel_axis=2, full=True)
    return float(smap.mean(axis=2)[m].mean())
