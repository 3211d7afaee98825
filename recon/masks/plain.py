"""A plain table: a support plane with no texture, told from the object by the flash's shading.

On a plain desk (white laminate, a painted board) SIFT finds almost no points on the table, so
the support plane cannot be fitted to the sparse points, and the flash-falloff masks that are
used without a plane take the lit table in with the object (on such a capture the visual hull
became a slab of table: silhouette IoU 0.37 with its masks, genus 8). The flash gives a model of
the table instead. It sits at the camera, so a plane point at distance r from it, whose normal
makes the angle theta with the ray, receives ``cos(theta) / r^2 = h / r^3`` (h: the camera's
height above the plane; :func:`recon.masks.geometry.flash_shading`). A plain table of one albedo
therefore shows, in each view, ``B = g (h / r^3)^b``: one gain per view (exposure, the flash's
power, the albedo) and an exponent b shared by the views (1 in linear photos; a phone's tone
curve, imperfectly undone by linearize, scales it). A phone's photos add the lens's falloff, a
bend of the tone curve, ambient light (additive) and white balance per view; the model takes
them (:func:`fit_plain_table`). No texture enters it.

:func:`fit_plain_table` fits that model over a ring of the plane around the object's foot and
says whether the table is plain: the model explains most of the ring's pixels to a few percent
and the table's chromaticity to 0.05, with a residual flat over 5 x 5 pixels. A wooden table is
not plain: its albedo varies by a factor of several (5-15 % of the ring explained on eight
tabletop captures of docs/masks.md, 31 % on glaze-torus's weakly textured table; on plain desks
56 % and 70 %; docs/masks.md, "A plain table"). :func:`plain_table` is what the
masks use when the sparse points give no plane: the plain table's pixels in every view, and
:func:`object_mask` what is neither that table nor the dark background.
"""

from __future__ import annotations

import logging
from collections.abc import Collection
from dataclasses import dataclass

import numpy as np

from recon.io.cameras import CameraSet
from recon.masks.common import LUMA
from recon.masks.evidence import resized, working_cameras
from recon.masks.geometry import flash_shading, plane_points
from recon.support import SupportPlane, aim_point, scene_scale

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PlainSettings:
    """Settings of the plain-table model. Distances on the plane are fractions of the scene scale
    (the median camera distance from the point the cameras aim at)."""

    ring: tuple = (0.3, 0.8)  # the model is fitted on plane points this far from the object's foot
    tolerance: float = 0.1  # |log residual| of a plain table's pixel (a 10 % brightness error)
    chroma_tolerance: float = 0.05  # ... and the largest difference of its chromaticity from the table's ...
    max_texture: float = 0.04  # ... and the std of its residual in a window of this radius (px at the working size)
    flat_radius: int = 2
    min_explained: float = 0.45  # the table is plain when the model explains this share of the ring's lit pixels
    # in the median view (the object hides part of the ring, its shadow another)
    slope: tuple = (0.5, 8.0)  # plausible exponents b of the shading (1: linear photos)
    work_size: int = 320  # long side of the images the model is fitted on
    # the plane's height (only the ring depends on it): the lowest level (bins of foot_bin x the scene scale) where
    # the points below the aim point gather, at least foot_points of them and foot_share of those
    foot_bin: float = 0.01
    foot_points: int = 10
    foot_share: float = 0.005

    close_px: int = 1  # object_mask: the table's pixels closed by this (px at the working size) ...
    open_px: int = 2  # ... the rest opened by this (px at the image's size) ...
    unlit_fraction: float = 0.1  # ... and the background darker than this share of the lit table left out, with
    edge_px: int = 14  # ... the band this close to both the table and the dark (the table's far edge, where its
    # grazing gloss leaves the model)

    def __post_init__(self):
        lo, hi = self.ring
        if not 0 <= lo < hi:
            raise ValueError(f"plain.ring must be 0 <= inner < outer, got {self.ring}")
        if not 0 < self.tolerance < 1 or not 0 < self.chroma_tolerance < 1 or not 0 < self.min_explained < 1:
            raise ValueError("plain.tolerance, chroma_tolerance and min_explained must be in (0, 1)")


@dataclass
class PlainTable:
    """The fitted model: ``plain`` (the photos show a plain table lit as the plane would be),
    the shared exponent ``slope``, per view ``gain`` and ``explained`` (the share of the ring's
    lit pixels within the tolerance), the table's ``chroma`` (rgb / luminance)."""

    plain: bool
    slope: float
    gain: np.ndarray
    explained: np.ndarray
    chroma: np.ndarray
    reason: str

    def summary(self) -> dict:
        return {"plain": bool(self.plain), "slope": float(self.slope),
                "explained_median": float(np.median(self.explained)) if len(self.explained) else 0.0,
                "chroma": [float(c) for c in self.chroma], "reason": self.reason}


def _view_terms(image: np.ndarray, cam, plane: SupportPlane, foot: np.ndarray):
    """Per pixel of ``cam`` (the working size): log luminance, log shading, chromaticity, the
    plane distance from ``foot`` and where the ray meets the plane in front of the camera."""
    import cv2

    rgb = np.nan_to_num(np.maximum(resized(image, (cam.width, cam.height))[:, :, :3], 0.0)).astype(np.float32)
    rgb = cv2.GaussianBlur(rgb, (0, 0), 1.0).astype(np.float64)  # sensor and JPEG noise, not the table, vary per pixel
    lum = rgb @ LUMA
    P, hit = plane_points(cam, plane)
    shade = flash_shading(cam.center, P, plane)
    ok = hit & (lum > 1e-8) & (shade > 0) & np.isfinite(shade)
    with np.errstate(divide="ignore", invalid="ignore"):
        log_l = np.where(ok, np.log(np.where(ok, lum, 1.0)), 0.0)
        log_s = np.where(ok, np.log(np.where(ok, shade, 1.0)), 0.0)
        chroma = np.where(ok[..., None], rgb / np.where(ok, lum, 1.0)[..., None], 0.0)
    dist = np.linalg.norm(P - np.asarray(foot, float), axis=-1)
    # the lens's falloff (vignetting, which a JPEG's linearization does not undo): a function of the
    # squared distance from the principal point, 1 in the corners
    j, i = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    rho2 = ((j - cam.K[0, 2]) ** 2 + (i - cam.K[1, 2]) ** 2) / (0.25 * (cam.width ** 2 + cam.height ** 2))
    # the tone curve's bend (a phone's shoulder compresses the bright table near the camera): the
    # square of the log shading about its middle, so that the exponent stays the slope there
    centred = np.where(ok, log_s - np.median(log_s[ok]) if ok.any() else 0.0, 0.0)
    shading = np.stack([log_s, centred * centred, rho2, rho2 * rho2], -1)
    return log_l, shading, chroma, dist, ok


def fit_plain_table(images: list[np.ndarray], cams: CameraSet, plane: SupportPlane,
                    settings: PlainSettings = PlainSettings()) -> tuple[PlainTable, list[np.ndarray]]:
    """Fit ``B_i = g_i S + a_i``, ``log S = slope log s + c (log s - m)^2 + d rho^2 + e rho^4`` (s the
    flash's shading ``h / r^3`` of ``plane``, rho the distance from the principal point, m the
    view's median log s) on the ring of the plane about the object's foot in every view: the
    shared terms by three fits (the shading alone; all terms jointly; all terms view by view, then
    their medians), the one that explains most of the plane the views see kept; the gain g_i,
    the ambient a_i and the table's chromaticity per view. Return the model and, per view, the
    pixels the model explains
    (``(H, W)`` bool at the working size of ``settings.work_size``: the plain table's pixels,
    anywhere on the plane)."""
    import cv2

    wcams = working_cameras(cams, settings.work_size)
    target = aim_point(cams)
    scale = scene_scale(cams, target)
    foot = plane.project(target)
    terms = [_view_terms(im, w, plane, foot) for im, w in zip(images, wcams, strict=True)]
    lo, hi = settings.ring[0] * scale, settings.ring[1] * scale
    rings = [ok & (dist >= lo) & (dist <= hi) for _, _, _, dist, ok in terms]
    n = len(terms)
    empty = PlainTable(False, 0.0, np.zeros(n), np.zeros(n), np.ones(3), "")
    if sum(int(r.sum()) for r in rings) < 100 * max(n, 1):
        empty.reason = "the views see too little of the plane around the object"
        return empty, [np.zeros(t[0].shape, bool) for t in terms]
    def solve(columns, joint=True):
        """The model with the shared terms ``columns`` (indices into the view terms' last axis),
        fitted over all the views at once (``joint``) or view by view, then their medians."""
        # the exponent, the tone curve's bend and the lens's falloff, shared by the views (one tone
        # curve, one lens), with a gain per view: one robust least-squares fit over the rings of all the
        # views (a term fitted view by view is confounded with the others over one view's ring)
        rows_x, rows_y, rows_k = [], [], []
        for k, ((log_l, X, _, _, _), ring) in enumerate(zip(terms, rings, strict=True)):
            if ring.sum() < 100:
                continue
            pick = np.linspace(0, ring.sum() - 1, min(int(ring.sum()), 4000)).astype(int)  # an even subsample
            rows_x.append(X[ring][pick])
            rows_y.append(log_l[ring][pick])
            rows_k.append(np.full(len(pick), k))
        x, y, view = np.concatenate(rows_x)[:, columns], np.concatenate(rows_y), np.concatenate(rows_k)
        used = np.unique(view)

        def robust(A, y, least):
            keep, coef = np.ones(len(y), bool), None
            for _ in range(5):  # the object and its shadow in the rings are outliers of the table's fit
                if keep.sum() < least:
                    break
                coef, *_ = np.linalg.lstsq(A[keep], y[keep], rcond=None)
                keep = np.abs(y - A @ coef) < 2.5 * settings.tolerance
            return coef

        if joint:
            coef = robust(np.concatenate([(view[:, None] == used[None, :]).astype(float), x], 1), y, 50 * len(used))
            coef = None if coef is None else coef[len(used):]
        else:  # view by view, then the median of each term
            per = [robust(np.concatenate([np.ones((int((view == k).sum()), 1)), x[view == k]], 1), y[view == k], 50)
                   for k in used]
            per = [c[1:] for c in per if c is not None]
            coef = np.median(np.array(per), axis=0) if per else None
        if coef is None or not np.all(np.isfinite(coef)):
            return None
        shared = np.zeros(terms[0][1].shape[-1])
        shared[columns] = coef  # slope, bend, falloff rho^2, rho^4
        slope = float(shared[0])
        # per view the gain g and the ambient light a of B = g S + a, S = the shared shading and falloff
        # (ambient light, a lamp in the room, lifts the far table where the flash is weak: additive, not
        # a factor), robustly in the linear domain; then the table's chromaticity (white balance varies)
        gains, ambient, chromas = np.zeros(n), np.zeros(n), np.full((n, 3), np.nan)
        for k, ((log_l, X, chroma, _, _), ring) in enumerate(zip(terms, rings, strict=True)):
            if ring.sum() < 100:
                continue
            S = np.exp(X[ring] @ shared)
            B = np.exp(log_l[ring])
            g, a = float(np.median(B / S)), 0.0
            for _ in range(4):
                r = np.log(B) - np.log(np.maximum(g * S + a, 1e-30))
                close = np.abs(r - np.median(r)) < 1.5 * settings.tolerance
                if close.sum() < 50:
                    break
                (g_new, a_new), *_ = np.linalg.lstsq(np.stack([S[close], np.ones(close.sum())], 1) / B[close, None],
                                                     np.ones(close.sum()), rcond=None)  # relative errors
                if not (g_new > 0 and np.isfinite(a_new)):
                    break
                g, a = float(g_new), float(max(a_new, 0.0))
            gains[k], ambient[k] = np.log(g), a
            r = np.log(B) - np.log(np.maximum(g * S + a, 1e-30))
            close = np.abs(r) < settings.tolerance
            if close.sum() >= 50:
                chromas[k] = np.median(chroma[ring][close], axis=0)
        seen = np.isfinite(chromas).all(1)
        table_chroma = np.median(chromas[seen], axis=0) if seen.any() else np.ones(3)
        chromas[~seen] = table_chroma
        explained, pixels, whole = np.zeros(n), [], []
        for k, ((log_l, X, chroma, _, ok), ring) in enumerate(zip(terms, rings, strict=True)):
            model_b = np.exp(gains[k] + X @ shared) + ambient[k]
            res = np.where(ok, log_l - np.log(np.maximum(model_b, 1e-30)), 0.0)
            # a plain table has no texture: its residual is flat in a small window (wood grain, a
            # pattern or the object's outline is not)
            w = 2 * settings.flat_radius + 1
            mean = cv2.blur(res, (w, w))
            flat = np.sqrt(np.maximum(cv2.blur(res * res, (w, w)) - mean * mean, 0.0)) < settings.max_texture
            fits = ok & flat & (np.abs(res) < settings.tolerance) \
                & (np.abs(chroma - chromas[k]).max(-1) < settings.chroma_tolerance)
            explained[k] = float(fits[ring].mean()) if ring.sum() >= 100 else 0.0
            whole.append(float(fits[ok].mean()) if ok.any() else 0.0)
            pixels.append(fits)
        return float(np.median(explained)), slope, gains, explained, table_chroma, pixels, float(np.median(whole))

    # the plain model (the flash's shading alone) and the full one (the tone curve's bend, the lens's
    # falloff), fitted jointly or view by view: the one that explains most of the rings. Measured
    # (docs/masks.md, "A plain table"): on a blob on a plain desk without vignetting the full model
    # also bends to the object, which fills much of the rings (38 % explained, the plain one 56 %);
    # on phone photos with vignetting the plain model explains 23 %, and the full one fitted view by
    # view does best
    fits = [f for f in (solve([0]), solve([0, 1, 2, 3]), solve([0, 1, 2, 3], joint=False)) if f is not None]
    log.debug("plain table: explained in the rings %s, in the views %s, exponents %s", [round(f[0], 3) for f in fits],
              [round(f[6], 3) for f in fits], [round(f[1], 3) for f in fits])
    if not fits:
        empty.reason = "no fit of the plane's shading over the views' rings"
        return empty, [np.zeros(t[0].shape, bool) for t in terms]
    # chosen by what it explains of the whole plane each view sees (the rings decide only whether the
    # table is plain): the table near the camera in the steep views lies outside the rings
    med, slope, gains, explained, table_chroma, pixels, _ = max(fits, key=lambda f: f[6])
    lo_s, hi_s = settings.slope
    plain = bool(med >= settings.min_explained and lo_s <= slope <= hi_s)
    reason = (f"the flash's shading of the plane explains {100 * med:.0f}% of the ring's lit pixels in the median "
              f"view (a plain table needs >= {100 * settings.min_explained:.0f}%), exponent {slope:.2f}")
    model = PlainTable(plain, slope, gains, explained, table_chroma, reason)
    if not plain:
        pixels = [np.zeros_like(p) for p in pixels]
    return model, pixels


def _foot_level(h: np.ndarray, step: float, least: float) -> float:
    """The lowest height of ``h`` where at least ``least`` values lie within two bins of ``step``
    (the lowest value when none does)."""
    edges = np.arange(h.min() - step, h.max() + 2 * step, step)
    counts, _ = np.histogram(h, edges)
    window = np.convolve(counts, np.ones(2, int), mode="valid")
    dense = np.flatnonzero(window >= least)
    return float(edges[dense[0]]) if len(dense) else float(h.min())


def plain_table(points: np.ndarray, images: list[np.ndarray], cams: CameraSet,
                settings: PlainSettings = PlainSettings()) -> tuple[list[np.ndarray] | None, dict]:
    """Per view the pixels of a plain table under the object (``(H, W)`` bool at the working
    size), or None when the photos show none; and the diagnostics with ``reason``.

    Used when the sparse points hold too few of the table's to fit its plane (a plain desk):
    the normal is the cameras' up (:func:`recon.support.up_candidates`), the height the foot of
    the object's points (the lowest level where the points below the point the cameras aim at,
    near its axis, gather). The table's pixels do not depend on that height (the shading's
    pattern is ``|cos|^3 / h^2``: the height scales each view by one gain), only the ring the
    model is fitted on does. The height itself is not known well enough to stand the object on
    it (SfM's stray points under a glossy table pull it down; the flash's shading cannot tell
    it), so the caller keeps the object in the void and uses the table's pixels only to take
    the table out of the flash-falloff masks."""
    from recon.support import up_candidates

    pts = np.asarray(points, float).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    target = aim_point(cams)
    scale = scene_scale(cams, target)
    centers = np.stack([c.center for c in cams])
    tried, best = [], None
    for up in up_candidates(cams, centers, target):
        h = pts @ up
        horiz = np.linalg.norm((pts - target) - np.outer(h - target @ up, up), axis=1)
        low = (h < target @ up) & (horiz < 0.6 * scale)
        if low.sum() < 20:
            tried.append("too few points below the aim point")
            continue
        level = _foot_level(h[low], settings.foot_bin * scale, max(settings.foot_points, settings.foot_share * low.sum()))
        plane = SupportPlane(up, -level)
        if plane.height(target) <= 0 or np.median(plane.height(centers)) <= 0:
            tried.append("the cameras are not above it")
            continue
        model, pixels = fit_plain_table(images, cams, plane, settings)
        tried.append(model.reason)
        if model.plain and (best is None or np.median(model.explained) > np.median(best[0].explained)):
            best = (model, pixels)
    if best is None:
        return None, {"plain": False, "reason": "no plain table shaded by the flash: " + "; ".join(tried)}
    model, pixels = best
    return pixels, {**model.summary(), "reason": f"a plain table under the object: {model.reason}"}


def object_mask(image: np.ndarray, table: np.ndarray, settings: PlainSettings = PlainSettings()
                ) -> tuple[np.ndarray, dict]:
    """The object's mask in a view of it on a plain table: what is neither the table
    (``table``: its pixels at the working size, from :func:`fit_plain_table`) nor the unlit
    background beyond it (:func:`recon.masks.evidence.unlit`, where it reaches the image's border
    or the table: a flash's shadow on the table goes with it, a dark spot inside the object
    stays), at the image's size. The flash-falloff mask cannot be used there: the
    lit table near the camera is often brighter than the object.

    The table's pixels are closed first (sensor and JPEG noise leave single pixels unexplained);
    the band within ``edge_px`` of both the table and the dark background (the table's far edge,
    whose gloss at grazing angles the model does not hold) goes with them; what remains is opened by ``open_px`` (specks of the table), and
    of it only the components holding at least 2 % are kept; holes the table's model opened
    inside the object (a patch of its own colour and brightness) are filled when smaller than
    1 % of it, while a real opening (a handle) shows more table than that. Returns the mask and
    ``plain_table_px`` (the share of the image the table's pixels cover)."""
    import cv2
    from scipy import ndimage

    from recon.masks.evidence import unlit

    h, w = image.shape[:2]
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * settings.close_px + 1, 2 * settings.close_px + 1))
    t = cv2.morphologyEx(table.astype(np.uint8), cv2.MORPH_CLOSE, k)
    t = cv2.resize(t, (w, h), interpolation=cv2.INTER_NEAREST).astype(bool)
    dark = unlit(image, t, settings.unlit_fraction)
    # dark is background where it reaches the image's border (the room beyond the table) or the
    # table (the flash's shadow on it); a dark patch inside the object (a dark glaze's spots) is
    # the object
    labels, n = ndimage.label(dark)
    if n:
        border = np.zeros_like(dark)
        border[0], border[-1], border[:, 0], border[:, -1] = True, True, True, True
        near_table = cv2.dilate(t.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        outside = np.unique(labels[(border | near_table) & dark])
        dark = np.isin(labels, outside[outside > 0])
    # the table's far edge: a band between the table and the dark background that neither takes
    # (the pixels mix the two, and unlit's smoothing widens it)
    k3 = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * settings.edge_px + 1, 2 * settings.edge_px + 1))
    edge = cv2.dilate(t.astype(np.uint8), k3).astype(bool) & cv2.dilate(dark.astype(np.uint8), k3).astype(bool)
    out = ~t & ~dark & ~edge
    if settings.open_px > 0:
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * settings.open_px + 1, 2 * settings.open_px + 1))
        out = cv2.morphologyEx(out.astype(np.uint8), cv2.MORPH_OPEN, k).astype(bool)
    # the table's pixels stop short of the object's outline by the smoothing and the flatness window
    # (about 1.5 px at the working size): the object's mask is shrunk by as much
    shrink = int(round((settings.flat_radius + 0.5) * max(h, w) / max(table.shape)))
    if shrink > 0:
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * shrink + 1, 2 * shrink + 1))
        out = cv2.erode(out.astype(np.uint8), k).astype(bool)
    labels, n = ndimage.label(out)
    if n > 1:
        sizes = ndimage.sum_labels(out, labels, index=np.arange(1, n + 1))
        out = np.isin(labels, 1 + np.flatnonzero(sizes >= 0.02 * sizes.sum()))
    filled = ndimage.binary_fill_holes(out)
    hole_labels, nh = ndimage.label(filled & ~out)
    if nh:
        sizes = ndimage.sum_labels(filled & ~out, hole_labels, index=np.arange(1, nh + 1))
        out |= np.isin(hole_labels, 1 + np.flatnonzero(sizes < 0.01 * max(int(out.sum()), 1)))
    return out, {"coverage": float(out.mean()), "plain_table_px": float(t.mean())}


def plain_table_masks(points: np.ndarray, load, cams: CameraSet, skip: Collection[str] = (),
                      settings: PlainSettings = PlainSettings()) -> tuple[dict[str, np.ndarray] | None, dict]:
    """The masks of an object on a plain table, when the sparse points give no plane: per view
    (but those in ``skip``: the capture's own masks) :func:`object_mask` of the table that
    :func:`plain_table` finds; ``load(stem)`` gives a view's linear image. None when the photos
    show no plain table. A view whose mask would be empty (every pixel the table or the dark) is
    left out and named in ``views_left``: the caller keeps its flash-falloff mask. Each image is
    read twice (at the working size for the model, then whole for its mask), so that the views
    are never all held at full size."""
    wcams = working_cameras(cams, settings.work_size)
    small = [resized(load(c.stem), (w.width, w.height)) for c, w in zip(cams, wcams, strict=True)]
    table, info = plain_table(points, small, cams, settings)
    del small
    if table is None:
        return None, info
    masks, empty = {}, []
    for c, t in zip(cams, table, strict=True):
        if c.stem in skip:
            continue
        m, _ = object_mask(load(c.stem), t, settings)
        if m.any():
            masks[c.stem] = m
        else:
            empty.append(c.stem)
    log.warning("%s; too few of the sparse points lie on it to fit its plane, so each view's mask is what is neither "
                "that table nor the dark background; the table's height is not known, so the object's base is closed "
                "flat below the lowest part the views see (a textured cloth or the printed mat under the object gives "
                "the plane and the base)%s",
                info["reason"], f"; views left with their flash-falloff masks (all table): {', '.join(empty)}"
                if empty else "")
    return masks, {**info, "views_left": empty}


__all__ = ["PlainSettings", "PlainTable", "fit_plain_table", "object_mask", "plain_table", "plain_table_masks"]
