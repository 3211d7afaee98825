"""What every kind of mask shares: the error, the luminance weights, morphology on bool masks."""

from __future__ import annotations

import numpy as np

LUMA = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
"""Rec.709 luminance weights of linear RGB."""


class MaskError(ValueError):
    """A mask that cannot be made or used; the message names the file and the fix."""


def disk(radius_px: int):
    """OpenCV's elliptic structuring element of radius ``radius_px`` (uint8, (2r+1)^2)."""
    import cv2

    d = 2 * int(radius_px) + 1
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (d, d))


def dilate(mask: np.ndarray, px: int) -> np.ndarray:
    """``mask`` (bool) grown by a disk of ``px`` pixels."""
    import cv2

    if px <= 0:
        return mask
    return cv2.dilate(mask.astype(np.uint8), disk(px)).astype(bool)


def erode(mask: np.ndarray, px: int) -> np.ndarray:
    """``mask`` (bool) shrunk by a disk of ``px`` pixels."""
    import cv2

    if px <= 0:
        return mask
    return cv2.erode(mask.astype(np.uint8), disk(px)).astype(bool)


def holes(mask: np.ndarray) -> np.ndarray:
    """(H, W) bool: the background pixels ``mask`` encloses (not connected to the image border)."""
    from scipy import ndimage

    return ndimage.binary_fill_holes(mask) & ~mask


def fill_small_holes(mask: np.ndarray, max_fraction: float) -> np.ndarray:
    """``mask`` with every hole of at most ``max_fraction`` of its area filled."""
    from scipy import ndimage

    h = holes(mask)
    if not h.any():
        return mask
    hl, nh = ndimage.label(h)
    sizes = ndimage.sum_labels(h, hl, index=np.arange(1, nh + 1))
    small = np.flatnonzero(sizes <= max_fraction * mask.sum()) + 1
    return mask | np.isin(hl, small)


def fill_holes_covered(mask: np.ndarray, solid: np.ndarray, fraction: float = 0.9) -> np.ndarray:
    """``mask`` with each hole filled where ``solid`` covers ``fraction`` of it (a hole that other
    evidence contradicts); the others stay open."""
    from scipy import ndimage

    h = holes(mask)
    if not h.any():
        return mask
    hl, nh = ndimage.label(h)
    covered = ndimage.mean(solid, hl, index=np.arange(1, nh + 1))
    return mask | np.isin(hl, np.flatnonzero(covered >= fraction) + 1)


def components_touching(mask: np.ndarray, region: np.ndarray) -> np.ndarray:
    """The connected components of ``mask`` that overlap ``region``."""
    from scipy import ndimage

    labels, n = ndimage.label(mask)
    if n == 0:
        return mask
    keep = np.unique(labels[region & mask])
    return np.isin(labels, keep[keep > 0])


def display_image(rgb_linear: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 sRGB of a linear image scaled by its 99.5th percentile (for edges, colours)."""
    from recon.io.images import linear_to_srgb

    rgb = np.nan_to_num(np.maximum(np.asarray(rgb_linear, np.float32)[:, :, :3], 0.0))
    top = max(float(np.percentile(rgb, 99.5)), 1e-12)
    return (np.clip(linear_to_srgb(np.clip(rgb / top, 0.0, 1.0)), 0, 1) * 255 + 0.5).astype(np.uint8)
