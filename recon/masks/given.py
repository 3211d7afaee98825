"""Given masks: a capture's own ``masks/<stem>.png`` (nonzero = object), used as they are."""

from __future__ import annotations

import os

import numpy as np

from recon.masks.common import MaskError


def fit_given_mask(mask: np.ndarray, path: str | os.PathLike, size: tuple[int, int]) -> np.ndarray:
    """A capture's own mask (bool ``(H, W)``, the photo's size) at the working ``size = (w, h)``
    of the linear images, which the linearize stage may have reduced (``linearize.max_size``):
    area-averaged and kept where at least half of the output pixel is object. MaskError naming
    ``path`` when the mask is neither that size nor the photo's shape at another scale."""
    w, h = size
    mh, mw = mask.shape
    if (mw, mh) == (w, h):
        return mask
    s = max(w, h) / max(mw, mh)
    if s < 1 and (max(1, round(mw * s)), max(1, round(mh * s))) == (w, h):  # as linearize reduced the photo
        import cv2

        return cv2.resize(mask.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA) >= 0.5
    raise MaskError(
        f"{path}: mask is {mw}x{mh} but the image is {w}x{h}; give masks the size of the photos"
    )
