"""Where a view sees the table: pixels the support plane explains, and only those it explains alone.

A pixel sees the table when its neighbouring views, warped into it by the homography the plane
induces (:func:`recon.masks.geometry.plane_homography`), show the same texture around it. Two
things make that test lie, and both lose objects:

- **Texture-poor surfaces match anything.** A plain glaze looks the same wherever a warp lands
  on it, so a neighbour that sees the object's own glaze behind the plane point (the object hides
  the plane point from it: always so near the object's base) agrees with the view as well as the
  table would. A match is therefore evidence of the table only when it is *distinctive*: the
  same window must match clearly worse on planes raised above the table, where the object
  would be (a plane sweep over heights h_1 < h_2 < ... up to the object's height). A window that
  matches at every height says nothing and is left undecided.
- **Exposure, white balance, tone curves, vignetting, lamps.** Rather than a model of the
  flash's shading and one gain per pair, the windows are compared by zero-mean normalized cross
  correlation (ZNCC) of log luminance: invariant to any gain and offset, so to exposure, white
  balance, a power-law tone curve and shading that is smooth across a window. A window without
  contrast (the std of its log luminance under ``min_contrast``: glaze, a dark or dim region,
  sensor noise) gives no correlation and is undecided too; so does a shading ramp: each window's
  best-fitting plane is removed before the correlation, so what is left is texture, not the
  smooth shading of a curved glazed surface (which neighbouring views near the object's foot,
  where the warp moves little, would otherwise match).

Per height h and view pair the ZNCC of the window (radius ``window``); per height the second best
over the neighbours (a plane point that the object hides from one neighbour is seen by others);
the pixel is **table** where the correlation at h = 0 reaches ``match`` and exceeds the best
over the raised planes by ``margin``. Computed at a working size (long side ``work_size``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from recon.io.cameras import Camera, CameraSet
from recon.masks.common import LUMA
from recon.masks.geometry import plane_homography
from recon.support import SupportPlane


@dataclass(frozen=True)
class EvidenceSettings:
    """The plane sweep of :func:`table_evidence`."""

    window: int = 4  # ZNCC window radius (px at the working size)
    min_contrast: float = 0.02  # std of the window's log luminance below this: undecided
    match: float = 0.7  # second-best ZNCC at the table's height at least this ...
    margin: float = 0.0  # ... and this much above the best raised plane's
    rank: int = 2  # per height, the rank-th best neighbour counts (occlusion by the object)
    work_size: int = 640  # long side of the working images
    fine_window: int = 2  # the fine ZNCC at the table's height (best neighbour) for outlines
    coarse: int = 2  # the sweep again at work_size / coarse, for windows the working size leaves undecided (1: off)
    coarse_erode: int = 1  # its table pixels shrunk by this many (coarse) px before they count

    def __post_init__(self):
        if self.window < 1 or self.rank < 1 or self.work_size < 64:
            raise ValueError("window and rank must be >= 1, work_size >= 64")
        if self.coarse < 1 or self.coarse_erode < 0 or self.work_size // self.coarse < 32:
            raise ValueError("coarse must be >= 1 (1: off) with work_size / coarse >= 32, coarse_erode >= 0")
        if not -1 < self.match <= 1 or not -2 <= self.margin < 2 or self.min_contrast < 0:
            raise ValueError("match must be in (-1, 1], margin in [-2, 2), min_contrast >= 0")


def working_scale(cam: Camera, work_size: int) -> float:
    """The factor (<= 1) that brings ``cam``'s image to a long side of at most ``work_size``."""
    return min(1.0, float(work_size) / max(cam.width, cam.height))


def scaled_camera(cam: Camera, s: float) -> Camera:
    """``cam`` for its image resized by ``s`` (edges stay at 0 and W)."""
    if s == 1.0:
        return cam
    w, h = max(1, round(cam.width * s)), max(1, round(cam.height * s))
    K = cam.K.copy()
    K[0] *= w / cam.width
    K[1] *= h / cam.height
    return Camera(cam.image, w, h, K, cam.world_to_camera.copy())


def working_cameras(cams: CameraSet, work_size: int) -> CameraSet:
    """``cams`` for their images brought to a long side of at most ``work_size``."""
    return CameraSet(tuple(scaled_camera(c, working_scale(c, work_size)) for c in cams), cams.light_intensity)


def log_luminance(rgb_linear: np.ndarray, size: tuple[int, int] | None = None, highpass: float = 0.0) -> np.ndarray:
    """(H, W) float32 log luminance (natural log), floored 4 decades below the 99.5th percentile,
    area-resampled to ``size = (w, h)`` and lightly smoothed (sigma 0.7 px); with ``highpass`` > 0
    its Gaussian blur of that sigma is subtracted (the smooth shading goes, the texture stays)."""
    import cv2

    rgb = np.nan_to_num(np.maximum(np.asarray(rgb_linear, np.float32)[:, :, :3], 0.0))
    lum = rgb @ LUMA
    if size is not None and (lum.shape[1], lum.shape[0]) != tuple(size):
        lum = cv2.resize(lum, tuple(size), interpolation=cv2.INTER_AREA)
    top = max(float(np.percentile(lum, 99.5)), 1e-30)
    g = cv2.GaussianBlur(np.log(np.maximum(lum, 1e-4 * top)).astype(np.float32), (0, 0), 0.7)
    if highpass > 0:
        g = g - cv2.GaussianBlur(g, (0, 0), highpass)
    return g


def _box(x: np.ndarray, r: int) -> np.ndarray:
    import cv2

    return cv2.boxFilter(x, -1, (2 * r + 1, 2 * r + 1), normalize=True, borderType=cv2.BORDER_REFLECT)


def _moment(g: np.ndarray, r: int, axis: int) -> np.ndarray:
    """Window mean of ``g`` times the offset from the window's centre along ``axis`` (1: x, 0: y)."""
    import cv2

    d = np.arange(-r, r + 1, dtype=np.float32) / float((2 * r + 1) ** 2)
    k = np.tile(d, (2 * r + 1, 1)) if axis == 1 else np.tile(d[:, None], (1, 2 * r + 1))
    return cv2.filter2D(g, -1, k, borderType=cv2.BORDER_REFLECT)


def window_stats(g: np.ndarray, r: int) -> tuple[np.ndarray, ...]:
    """Per (2r+1)^2 window of ``g``: the mean, the standard deviation left after removing the
    window's best-fitting plane (a shading ramp is no contrast), and the moments along x and y
    that define that plane."""
    m = _box(g, r)
    sxx = r * (r + 1) / 3.0  # mean of the squared offsets
    gx, gy = _moment(g, r, 1), _moment(g, r, 0)
    v = np.maximum(_box(g * g, r) - m * m - (gx * gx + gy * gy) / sxx, 0.0)
    return m, np.sqrt(v), gx, gy


def zncc(g_i: np.ndarray, stats_i, g_j: np.ndarray, valid: np.ndarray, r: int,
         min_contrast: float) -> np.ndarray:
    """(H, W) zero-mean normalized cross correlation of ``g_i`` and ``g_j`` over (2r+1)^2 windows,
    after removing each window's best-fitting plane from both (so smooth shading that differs
    between the views does not count, and a shading ramp alone does not match); NaN where a
    window has less than ``min_contrast`` left in either image or ``valid`` (``g_j`` defined)
    does not cover it."""
    m_i, s_i, gx_i, gy_i = stats_i
    m_j, s_j, gx_j, gy_j = window_stats(g_j, r)
    sxx = r * (r + 1) / 3.0
    cov = _box(g_i * g_j, r) - m_i * m_j - (gx_i * gx_j + gy_i * gy_j) / sxx
    cover = _box(valid.astype(np.float32), r)
    with np.errstate(invalid="ignore", divide="ignore"):
        z = cov / (s_i * s_j)
    ok = (s_i >= min_contrast) & (s_j >= min_contrast) & (cover > 0.95)
    return np.where(ok, np.clip(z, -1.0, 1.0), np.nan).astype(np.float32)


def unlit(rgb_linear: np.ndarray, table: np.ndarray, fraction: float, size: tuple[int, int] | None = None
          ) -> np.ndarray:
    """(H, W) bool at ``size``: the far background the flash hardly reaches. The flash falls off
    with the squared distance, so such a background forms a dark mode of the log luminance
    apart from the lit table and object: pixels below the flash-falloff threshold just above
    that mode (:func:`recon.masks.falloff.background_threshold`, on the luminance smoothed
    against sensor noise), and in any case below ``fraction`` of the median luminance of the
    pixels that see the ``table`` (the image's 90th percentile when it sees too little table),
    so that a view without a dark mode keeps its dark wood and a dark object in front of the
    lit table stays undecided."""
    import cv2

    from recon.masks.falloff import MaskSettings, background_threshold

    rgb = np.nan_to_num(np.maximum(np.asarray(rgb_linear, np.float32)[:, :, :3], 0.0))
    lum = rgb @ LUMA
    if size is not None and (lum.shape[1], lum.shape[0]) != tuple(size):
        lum = cv2.resize(lum, tuple(size), interpolation=cv2.INTER_AREA)
    lum = cv2.GaussianBlur(lum, (0, 0), 1.5)  # sensor noise is what a dim background shows
    ref = float(np.median(lum[table])) if table.sum() >= 100 else float(np.percentile(lum, 90))
    if not ref > 0:
        return np.zeros(lum.shape, bool)
    ms = MaskSettings()
    log_l = np.log10(np.maximum(lum, ms.floor * max(float(np.percentile(lum, 99.9)), 1e-30)))
    t, _ = background_threshold(log_l, ms)
    return log_l <= min(t, float(np.log10(fraction * ref)))


def raised(plane: SupportPlane, h: float) -> SupportPlane:
    """The plane parallel to ``plane``, ``h`` above it."""
    return SupportPlane(plane.normal, plane.offset - float(h))


def _rank(stack: np.ndarray, rank: int) -> np.ndarray:
    """Per pixel the ``rank``-th largest of ``stack (K, H, W)`` over its non-NaN entries (NaN with fewer)."""
    filled = np.where(np.isnan(stack), -np.inf, stack)
    kth = -np.sort(-filled, axis=0)[rank - 1]
    return np.where(np.isfinite(kth), kth, np.nan).astype(np.float32)


def _median_clear(stack: np.ndarray, least: int) -> np.ndarray:
    """Per pixel the median of ``stack (K, H, W)`` over its non-NaN entries, NaN with fewer than ``least``."""
    count = np.sum(~np.isnan(stack), axis=0)
    with np.errstate(invalid="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(stack, axis=0)
    return np.where(count >= least, med, np.nan).astype(np.float32)


def table_evidence(logs: list[np.ndarray], cams: CameraSet, plane: SupportPlane, i: int, nbrs: list[int],
                   heights: list[float], settings: EvidenceSettings = EvidenceSettings(),
                   hidden: list[np.ndarray] | None = None, z_up: np.ndarray | None = None,
                   hidden_tolerance: float = 0.0) -> dict:
    """The plane sweep of view ``i`` (module docstring) on working-size log-luminance images
    ``logs`` of the (working-size) cameras ``cams``.

    ``hidden``: per view a (H, W) float32 depth map at the working size of what may hide the
    table (the front depth of a first hull, inf where there is none). With it the test at the
    table's height is occlusion-aware: a neighbour counts for a pixel only where it sees the
    pixel's plane point (nearer than its ``hidden`` depth there, by ``hidden_tolerance``).
    ``z_up``: the raised
    planes' score of an earlier call (they are not swept again).

    Returns
    -------
    dict with ``table`` (H, W) bool (the plane explains the pixel, distinctively), ``z0`` the
    ZNCC at the table's height and ``z_up`` the best over the raised planes (H, W) float32 (NaN:
    undecided), ``contrast`` (H, W) bool (the window has contrast), and ``z0_fine``: the ZNCC at
    the table's height over windows of radius ``fine_window`` (best neighbour; with ``hidden``
    the median over the neighbours that see the plane point), which places outlines sharply.
    """
    import cv2

    ci = cams.frames[i]
    g_i = logs[i]
    r = settings.window
    size = (ci.width, ci.height)
    stats_i = window_stats(g_i, r)
    stats_fine = window_stats(g_i, settings.fine_window)
    if hidden is not None:
        from recon.masks.geometry import plane_points

        P = plane_points(ci, plane)[0].reshape(-1, 3)
    per_height = []
    fine = []
    for h in [0.0, *(heights if z_up is None else [])]:
        p = raised(plane, h)
        scores = []
        for j in nbrs:
            cj = cams.frames[j]
            if p.height(ci.center) <= 0 or p.height(cj.center) <= 0:
                continue  # a camera below the raised plane: no homography of its top side
            H = plane_homography(ci, cj, p)
            warp = dict(flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            g_j = cv2.warpPerspective(logs[j], H, size, **warp)
            valid = cv2.warpPerspective(np.ones_like(logs[j]), H, size, **warp) > 0.999
            score = zncc(g_i, stats_i, g_j, valid, r, settings.min_contrast)
            if h == 0.0:
                f = zncc(g_i, stats_fine, g_j, valid, settings.fine_window, settings.min_contrast)
                if hidden is not None:
                    front = cv2.warpPerspective(hidden[j], H, size, flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                                                borderMode=cv2.BORDER_CONSTANT, borderValue=np.inf)
                    z_j = (P @ cj.world_to_camera[2, :3] + cj.world_to_camera[2, 3]).reshape(front.shape)
                    blocked = z_j > front + hidden_tolerance
                    score = np.where(blocked, np.nan, score)
                    f = np.where(blocked, np.nan, f)
                fine.append(f)
            scores.append(score)
        if len(scores) < settings.rank:
            per_height.append(np.full(g_i.shape, np.nan, np.float32))
        else:
            per_height.append(_rank(np.stack(scores), settings.rank))
    z0 = per_height[0]
    if z_up is None:
        z_up = _rank(np.stack(per_height[1:]), 1) if len(per_height) > 1 else np.full(g_i.shape, np.nan, np.float32)
    contrast = stats_i[1] >= settings.min_contrast
    z_up_filled = np.where(np.isnan(z_up), -1.0, z_up)
    with np.errstate(invalid="ignore"):
        table = contrast & (z0 >= settings.match) & (z0 - z_up_filled >= settings.margin)
    if not fine:
        z0_fine = np.full(g_i.shape, np.nan, np.float32)
    elif hidden is not None:
        z0_fine = _median_clear(np.stack(fine), 1)
    else:
        z0_fine = _rank(np.stack(fine), 1)
    return {"table": table, "z0": z0, "z_up": z_up.astype(np.float32), "contrast": contrast, "z0_fine": z0_fine}


def with_coarse(fine: dict, coarse: dict, erode: int) -> np.ndarray:
    """(H, W) bool: ``fine``'s table pixels (:func:`table_evidence` at the working size) with those of
    ``coarse`` (the same sweep at a smaller working size) added where ``fine`` is undecided: its
    window has no contrast, or no neighbour gave a correlation. A table's wood or a mat whose
    grain is finer than the working size's windows resolve looks smooth there and matches at a
    coarser scale (docs/masks.md, "The sweep at two scales"). The coarse table pixels are shrunk
    by ``erode`` coarse pixels first: a coarse window that straddles an outline matches the
    table where the table fills most of it, and its centre may be on the object."""
    import cv2

    table = coarse["table"].astype(np.uint8)
    if erode > 0:
        table = cv2.erode(table, np.ones((2 * erode + 1, 2 * erode + 1), np.uint8), borderType=cv2.BORDER_REPLICATE)
    h, w = fine["table"].shape
    up = cv2.resize(table, (w, h), interpolation=cv2.INTER_NEAREST) > 0
    undecided = ~fine["contrast"] | np.isnan(fine["z0"])
    return fine["table"] | (up & undecided)


def resized(rgb_linear: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(h, w, 3) float32 linear RGB (finite, >= 0) area-resampled to ``size = (w, h)``."""
    import cv2

    rgb = np.nan_to_num(np.maximum(np.asarray(rgb_linear, np.float32)[:, :, :3], 0.0))
    if (rgb.shape[1], rgb.shape[0]) == tuple(size):
        return rgb
    return cv2.resize(rgb, tuple(size), interpolation=cv2.INTER_AREA)


def plane_difference(rgbs: list[np.ndarray], cams: CameraSet, plane: SupportPlane, i: int, nbrs: list[int],
                     window: int = 2, floor: float = 0.03, hidden: list[np.ndarray] | None = None,
                     hidden_tolerance: float = 0.0) -> np.ndarray:
    """C (H, W) float32 of view ``i``: per pixel, the relative difference between the view and
    its neighbours warped by the plane's homography, the flash's shading ``cos / r^2`` on the
    plane swapped and one gain per pair (exposure) removed, averaged over a window that follows
    the photo's edges (guided filter, radius ``window``), the smallest over the neighbours that
    see the pixel's plane point (with ``hidden``, see :func:`table_evidence`). About 0.1-0.3
    where the view sees the table, > 1 where something stands in front of it; inf where no
    neighbour sees the plane point. Pixel-sharp, but a plain surface differs from nothing it is
    warped onto: read it only where the photo has contrast."""
    import cv2

    from recon.masks.common import display_image
    from recon.masks.geometry import flash_shading, plane_points

    ci = cams.frames[i]
    L_i = rgbs[i]
    P, hit = plane_points(ci, plane)
    E_i = flash_shading(ci.center, P, plane)
    fl = floor * max(float(np.percentile(L_i.mean(-1), 90)), 1e-12)
    guide = display_image(L_i)
    eps = 1e-3 * 255.0**2
    best = np.full(L_i.shape[:2], np.inf, np.float32)
    flat = P.reshape(-1, 3)
    size = (ci.width, ci.height)
    for j in nbrs:
        cj = cams.frames[j]
        H = plane_homography(ci, cj, plane)
        L_j = cv2.warpPerspective(rgbs[j], H, size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                  borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        xy, z = cj.project(flat)
        xy, z = xy.reshape(P.shape[:2] + (2,)), z.reshape(P.shape[:2])
        seen = hit & (z > 0) & (xy[..., 0] >= 1) & (xy[..., 0] <= cj.width - 1) \
            & (xy[..., 1] >= 1) & (xy[..., 1] <= cj.height - 1)
        if hidden is not None:
            front = cv2.warpPerspective(hidden[j], H, size, flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                                        borderMode=cv2.BORDER_CONSTANT, borderValue=np.inf)
            seen &= ~(z > front + hidden_tolerance)
        if seen.sum() < 100:
            continue
        E_j = flash_shading(cj.center, P, plane)
        with np.errstate(divide="ignore", invalid="ignore"):
            pred = L_j * np.where(seen, E_i / E_j, 0.0)[..., None].astype(np.float32)
        bright = seen & (L_i.mean(-1) > fl) & (pred.mean(-1) > fl)
        if bright.sum() >= 100:  # one gain per pair (exposure, light): the median log ratio
            r = np.log(L_i[bright] + 1e-12) - np.log(pred[bright] + 1e-12)
            pred *= np.exp(np.median(r, axis=0)).astype(np.float32)
        D = (np.abs(L_i - pred) / (fl + 0.5 * (L_i + pred))).sum(-1)
        D = np.where(seen, D, 0.0).astype(np.float32)
        w = seen.astype(np.float32)
        num = cv2.ximgproc.guidedFilter(guide, D, window, eps)
        den = cv2.ximgproc.guidedFilter(guide, w, window, eps)
        with np.errstate(divide="ignore", invalid="ignore"):
            Dm = np.where(seen & (den > 0.3), num / np.maximum(den, 1e-6), np.inf)
        best = np.minimum(best, Dm.astype(np.float32))
    return best


def sweep_heights(band: float, top: float, factor: float = 2.0) -> list[float]:
    """Heights of the raised planes: ``band`` (the lowest height whose parallax the windows see),
    then ``factor`` times more each, up to ``top`` (included)."""
    if not top > 0:
        return []
    band = max(float(band), 1e-3 * top)
    hs = []
    h = band
    while h < top:
        hs.append(h)
        h *= factor
    hs.append(float(top))
    return hs
