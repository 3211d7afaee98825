"""Flash-falloff masks: the object in one flash-lit linear image, without cameras.

The only light is the flash at the camera, so irradiance falls off with the squared distance
and a background farther away than the object is much darker than the object (often pure
noise). Method (why each step):

1. Luminance (Rec.709 weights) of the linear image, floored at ``1e-4`` of its 99.9th
   percentile, in log10. The log turns "much darker" into "far apart" and makes the split
   independent of the exposure scale.
2. Otsu's threshold on the log-luminance histogram splits object from background when the
   histogram is bimodal (flash falloff makes it so). Otsu alone sits in the middle of the gap,
   which loses the object's own dark pixels (surfaces seen at grazing angles near the
   silhouette are lit at grazing angles too, so they are dark). The threshold is therefore
   lowered to just above the background class: ``min(otsu, max(median_bg + k * MAD_bg,
   P_bg))`` in log space (``k = background_sigmas``, ``P_bg`` its ``background_percentile``,
   which clears sensor noise). A pure black background (synthetic captures) then keeps every
   pixel that received any light.
3. A small opening removes speckles (noise, dust); the largest connected component is the
   object (a flash-lit capture has one object in the middle); holes smaller than
   ``max_hole_fraction`` of the object's area are filled (dark texture or specular-free spots
   inside the object), larger ones are kept (real through-holes, e.g. a handle); a small
   closing smooths the outline.

No object: a view whose brightest pixels (99.9th percentile of the luminance) carry no light
(below ``1e-20``: nothing but rounding residue) is an error; so is, for RAW and JPEG/PNG views
(whose linear scale puts the white level at 1.0, see :mod:`recon.linearize`), one whose
brightest pixels stay below ``min_signal`` of the white level (default 2^-8, 8 stops below
clipping): such a photo holds sensor noise, not a flash-lit object (a black object, a flash
that did not fire), and a mask derived from noise would only mislead the later stages. EXR
views are scene-referred in unknown units, so only the first test applies to them.

Masks feed the visual hull (:mod:`recon.init_mesh`), where a mask that is too small carves
away object, so every step errs on the side of a slightly larger mask.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from recon.masks.common import LUMA, MaskError, disk

NO_LIGHT = 1e-20
"""Brightest pixels at or below this (any units) mean the image holds no light at all."""
WHITE_LEVEL_KINDS = ("raw", "ldr")
"""linear.json kinds whose linear scale puts the white level at 1.0 (``min_signal`` applies)."""


@dataclass(frozen=True)
class MaskSettings:
    """Settings of the derived masks (given masks are used unchanged).

    Radii are fractions of the image's shorter side, so they mean the same at any resolution.
    """

    floor: float = 1e-4  # luminance floor relative to the 99.9th percentile
    background_sigmas: float = 4.0  # threshold >= bg median + this * bg MAD (log space) ...
    background_percentile: float = 99.5  # ... and >= this percentile of the background class
    open_radius: float = 0.004  # speckle removal
    close_radius: float = 0.008  # outline smoothing
    max_hole_fraction: float = 0.02  # holes smaller than this fraction of the object are filled
    dilate_px: int = 0  # extra safety margin in pixels (after everything else)
    min_coverage: float = 0.001  # warn when a mask covers less than this fraction of the image
    max_coverage: float = 0.95  # ... or more than this
    min_signal: float = 2.0**-8  # RAW/JPEG/PNG: the brightest pixels must reach this fraction of white


    def __post_init__(self):
        if not 0 < self.floor < 1:
            raise ValueError(f"floor must be in (0, 1), got {self.floor}")
        if self.background_sigmas < 0 or self.open_radius < 0 or self.close_radius < 0 or self.dilate_px < 0:
            raise ValueError("background_sigmas, open_radius, close_radius and dilate_px must be >= 0")
        if not 0 <= self.max_hole_fraction <= 1:
            raise ValueError(f"max_hole_fraction must be in [0, 1], got {self.max_hole_fraction}")
        if not 0 <= self.min_signal < 1:
            raise ValueError(f"min_signal must be in [0, 1) (a fraction of the white level), got {self.min_signal}")


def otsu_threshold(values: np.ndarray, bins: int = 256) -> float:
    """Otsu's threshold of 1-D ``values`` (maximizes the between-class variance)."""
    v = np.asarray(values, dtype=np.float64).ravel()
    lo, hi = float(v.min()), float(v.max())
    if hi - lo < 1e-12:
        return hi
    hist, edges = np.histogram(v, bins=bins, range=(lo, hi))
    centers = 0.5 * (edges[:-1] + edges[1:])
    w0 = np.cumsum(hist).astype(np.float64)
    w1 = w0[-1] - w0
    m0 = np.cumsum(hist * centers)
    mu0 = m0 / np.maximum(w0, 1)
    mu1 = (m0[-1] - m0) / np.maximum(w1, 1)
    between = (w0 * w1 * (mu0 - mu1) ** 2)[:-1]
    # the criterion is flat across an empty gap between the modes: take the plateau's middle
    best = np.flatnonzero(between >= between.max() * (1 - 1e-9))
    k = int(best[len(best) // 2])
    return float(edges[k + 1])


def background_threshold(log_l: np.ndarray, settings: MaskSettings = MaskSettings()) -> tuple[float, float]:
    """``(t, t_otsu)``: the threshold of step 2 (module docstring) on log10 luminances ``log_l``,
    just above the background class of Otsu's split, and Otsu's threshold itself."""
    t_otsu = otsu_threshold(log_l)
    bg = log_l[log_l <= t_otsu]
    med = float(np.median(bg))
    mad = 1.4826 * float(np.median(np.abs(bg - med)))
    # just above the background: its robust spread, and its upper tail where noise has one
    # (the smallest step above a constant background is a hair above the floor)
    t_bg = max(med + settings.background_sigmas * mad, float(np.percentile(bg, settings.background_percentile)))
    return min(t_otsu, t_bg + 1e-6), t_otsu


def derive_mask(rgb_linear: np.ndarray, settings: MaskSettings = MaskSettings(),
                white_level: float | None = None) -> tuple[np.ndarray, dict]:
    """Object mask of one flash-lit linear image (method in the module docstring).

    Parameters
    ----------
    rgb_linear : (H, W, C) float
        Linear image, C = 1 or 3 (a 4th channel is ignored).
    white_level : float, optional
        The linear value of the camera's clipping level (1.0 for RAW and JPEG/PNG views of the
        linearize stage); when given, brightest pixels below ``settings.min_signal`` of it
        mean no object is in the image (MaskError). None (EXR: unknown units): only an image
        without any light is rejected.

    Returns
    -------
    mask : (H, W) bool
    info : dict
        ``threshold_log10``, ``otsu_log10`` and ``coverage`` (fraction of the image).
    """
    import cv2
    from scipy import ndimage

    img = np.asarray(rgb_linear, dtype=np.float32)
    if img.ndim == 2:
        img = img[:, :, None]
    if img.ndim != 3 or img.shape[2] not in (1, 3, 4):
        raise MaskError(f"derive_mask needs an (H, W, C) image, got shape {img.shape}")
    img = np.nan_to_num(img, nan=0.0, posinf=0.0, neginf=0.0)
    lum = img[:, :, 0] if img.shape[2] == 1 else img[:, :, :3] @ LUMA
    lum = np.maximum(lum, 0.0)
    top = float(np.percentile(lum, 99.9))
    if not top > NO_LIGHT:
        raise MaskError(f"the image is black (brightest pixels {top:.3g}): is the flash in the photo?")
    if white_level is not None and top < settings.min_signal * white_level:
        stops = math.log2(white_level / top)
        raise MaskError(
            f"the brightest pixels (99.9th percentile of the luminance) reach only {100 * top / white_level:.2g}% "
            f"of the white level (masks.min_signal = {100 * settings.min_signal:.2g}%): the image is sensor "
            f"noise, a black object or a photo {stops:.0f} stops underexposed; check that the flash fired and "
            "expose so that the object's brightest parts come near clipping")
    log_l = np.log10(np.maximum(lum, settings.floor * top))
    t, t_otsu = background_threshold(log_l, settings)
    mask = log_l > t

    short = min(mask.shape)
    r_open = int(round(settings.open_radius * short))
    r_close = int(round(settings.close_radius * short))
    m8 = mask.astype(np.uint8)
    if r_open > 0:
        m8 = cv2.morphologyEx(m8, cv2.MORPH_OPEN, disk(r_open))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(m8, connectivity=8)
    if n <= 1:
        raise MaskError("no foreground left after removing speckles: the object is too dark or too small")
    largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    mask = labels == largest
    # fill small holes only: large ones may be real (a handle, the inside of a ring)
    holes = ndimage.binary_fill_holes(mask) & ~mask
    if holes.any():
        hl, nh = ndimage.label(holes)
        sizes = ndimage.sum_labels(holes, hl, index=np.arange(1, nh + 1))
        small = np.flatnonzero(sizes <= settings.max_hole_fraction * mask.sum()) + 1
        mask |= np.isin(hl, small)
    if r_close > 0:
        # pad so that the closing does not glue the object to the image border
        pad = r_close + 1
        m8 = np.pad(mask.astype(np.uint8), pad)
        m8 = cv2.morphologyEx(m8, cv2.MORPH_CLOSE, disk(r_close))[pad:-pad, pad:-pad]
        mask = m8.astype(bool)
    if settings.dilate_px > 0:
        mask = cv2.dilate(mask.astype(np.uint8), disk(settings.dilate_px)).astype(bool)
    info = {"threshold_log10": float(t), "otsu_log10": float(t_otsu), "coverage": float(mask.mean())}
    return mask, info
