"""The flash's shadow on the table, beside the object: found across the views and called table.

A phone's flash sits a centimetre or two beside its lens. Every table point the camera sees is
then lit by the flash, except those the object hides from the flash: a thin band on the table
along the object's outline, on the side away from the flash, and nearly black in a dim room
(only the ambient light reaches it). The tabletop masks take it for the object: its pixels
carry no texture, so the plane test says nothing there (:mod:`recon.masks.evidence`: only
positive evidence counts), and its colour is no table colour. A vase 3 times taller than wide,
18 views, the flash 0.2 of the object's size beside and 0.1 below the lens: the masks held 6 %
of the object's area in shadow on top of what was right, mean IoU 0.877 against 0.946 for the
same capture with the flash at the lens, and the final accuracy was 0.0092 against 0.0040
(docs/masks.md, "The flash's shadow").

What tells the shadow from a dark part of the object is where it lies. The flash is fixed to
the camera, so in every photo the shadow falls on the same side of the object's outline (in
the camera's pixel axes: the photos' stored pixels, whatever way they are displayed), whatever
the object shows there; the object's own dark parts (a dark glaze, a dark rim at grazing
angles) fall on every side as the object turns between the views. So:

1. Per view, the dark pixels (the unlit test of :func:`recon.masks.evidence.unlit`: far below
   the lit table, where the ray meets the lit table) in a band about the hull's outline, but
   not those of a dark region reaching past the band (the table far behind the object, dim with
   the distance, is dark above the object in every view: a direction too), each with the
   outline's outward normal there (:func:`outline_normals`).
2. Over the views, the normals' mean resultant (:func:`shadow_direction`): a shadow gives one
   direction that most views share; dark parts of the object give none (their normals cancel).
3. Where there is a shadow, a view's dark pixels in the band whose outward normal points that
   way are the table in the flash's shadow (:func:`shadow_pixels`): they vote their rays empty
   in the 3D vote and are table in the graph cut.

One direction can show no shadow: towards the object's foot. Where the object stands on the
table the outline meets the table it stands on, with no gap behind it for a shadow to fall in,
and the table in front of the foot faces the flash. The object's own dark parts do lie there in
every view, though: a mug glazed dark on its lower half, photographed from above, is dark along
the bottom of its outline in all 36 views (resultant 0.52, every view agreeing), and 8 % of its
area was taken for table (masks 0.86 mean IoU). So a direction within ``foot_deg`` of the
views' direction towards the foot (the plane's normal, down, in each view's pixels) is refused.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ShadowSettings:
    """The flash's shadow in the tabletop masks (``SegmentSettings.shadow``)."""

    enabled: bool = True
    band: float = 0.12  # the band about the hull's outline searched, x the silhouette's equivalent diameter
    min_resultant: float = 0.15  # the dark pixels' outward normals over all views: mean resultant length at least
    min_agree: float = 0.75  # ... and this share of the views with dark pixels points within agree_deg of it
    agree_deg: float = 60.0
    min_pixels: int = 20  # a view's dark pixels in the band (working size) below this: it says nothing
    min_views: float = 0.5  # a shadow shows in most views: at least this share of them has dark pixels there
    cone_deg: float = 70.0  # the shadow side: outline normals within this of the shadow's direction
    foot_deg: float = 60.0  # a direction this close to the views' direction towards the object's foot: no shadow

    def __post_init__(self):
        if not 0 < self.band < 1 or not 0 <= self.min_resultant <= 1 or not 0 <= self.min_agree <= 1 \
                or not 0 <= self.min_views <= 1:
            raise ValueError("shadow: band must be in (0, 1), min_resultant, min_agree and min_views in [0, 1]")
        if not 0 < self.agree_deg <= 180 or not 0 < self.cone_deg < 90 or self.min_pixels < 1 \
                or not 0 <= self.foot_deg < 180:
            raise ValueError("shadow: agree_deg in (0, 180], cone_deg in (0, 90), foot_deg in [0, 180), min_pixels >= 1")


def outline_normals(sil: np.ndarray, smooth: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """The signed distance to the outline of ``sil`` ((H, W) bool; positive inside, pixels) and
    the outward unit normal of the outline ``(H, W, 2)`` (x, y in pixels: the direction that
    leaves the silhouette), from the smoothed distance's gradient; zero where it is flat."""
    import cv2

    from recon.hull import _signed_distance_px

    # a silhouette that fills the image or is empty has no outline: its distances are cv2's "none"
    big = float(max(sil.shape))
    sd = np.clip(_signed_distance_px(np.asarray(sil, bool)), -big, big)
    g = cv2.GaussianBlur(sd, (0, 0), smooth)
    gy, gx = np.gradient(g)
    norm = np.hypot(gx, gy)
    n = np.where(norm[..., None] > 1e-6, -np.stack([gx, gy], -1) / np.maximum(norm, 1e-6)[..., None], 0.0)
    return sd, n.astype(np.float32)


def _thin(dark: np.ndarray, sil: np.ndarray, sd: np.ndarray, band: float) -> np.ndarray:
    """The ``dark`` pixels in the band about the outline that belong to no dark region reaching
    past the band's outer edge: a shadow is a thin band between the object and the lit table,
    while the table far behind the object, dim with the distance, stays dark beyond it."""
    from scipy import ndimage

    width = max(2.0, band * 2.0 * np.sqrt(max(float(sil.sum()), 1.0) / np.pi))
    zone = dark & (sd >= -width - 2.0)
    lab, n = ndimage.label(zone)
    if n == 0:
        return zone
    reach = np.unique(lab[zone & (sd < -width)])
    return zone & ~np.isin(lab, reach[reach > 0]) & (np.abs(sd) <= width)


def towards_foot(cams, foot: np.ndarray, top: np.ndarray) -> list[np.ndarray]:
    """Per camera, the unit direction ``(x, y)`` in its pixels from the object's ``top`` (3,) down
    to its ``foot`` (3,) on the table; zero where the two project to one pixel."""
    out = []
    for c in cams:
        uv, _ = c.project(np.stack([np.asarray(foot, float), np.asarray(top, float)]))
        d = uv[0] - uv[1]
        n = float(np.linalg.norm(d))
        out.append(d / n if n > 1e-6 and np.all(np.isfinite(d)) else np.zeros(2))
    return out


def shadow_direction(dark: list[np.ndarray], sils: list[np.ndarray], settings: ShadowSettings = ShadowSettings(),
                     down: list[np.ndarray] | None = None) -> tuple[np.ndarray | None, dict]:
    """The direction (unit ``(x, y)`` in pixels, pointing from the object into its shadow) that
    the views' ``dark`` pixels near the outlines of their silhouettes ``sils`` share, or None,
    and what was measured (``resultant``, ``agree``, ``views``: how many of the ``of_views``
    views with a silhouette had dark pixels there: a shadow shows in most of them). ``down``
    (:func:`towards_foot`, per view): a direction within ``foot_deg`` of the views' median
    direction towards the object's foot is refused (``foot_angle``, degrees)."""
    vecs, counts, seen = [], [], 0
    for d, s in zip(dark, sils, strict=True):
        if not s.any():
            continue
        seen += 1
        sd, n = outline_normals(s)
        cand = _thin(d, s, sd, settings.band) & (np.abs(n).sum(-1) > 0)
        k = int(cand.sum())
        if k < settings.min_pixels:
            continue
        vecs.append(n[cand].sum(0))
        counts.append(k)
    info = {"views": len(vecs), "of_views": seen}
    if len(vecs) < max(3, settings.min_views * seen):
        return None, {**info, "reason": f"{len(vecs)} of {seen} views show dark pixels along the outline"}
    vecs = np.asarray(vecs, np.float64)
    total = vecs.sum(0)
    resultant = float(np.linalg.norm(total) / sum(counts))
    u = total / max(np.linalg.norm(total), 1e-12)
    per = vecs / np.maximum(np.linalg.norm(vecs, axis=1, keepdims=True), 1e-12)
    agree = float(np.mean(per @ u >= np.cos(np.radians(settings.agree_deg))))
    info.update(resultant=resultant, agree=agree, direction=[float(u[0]), float(u[1])])
    if resultant < settings.min_resultant or agree < settings.min_agree:
        return None, {**info, "reason": f"the dark pixels along the outlines point no one way (resultant "
                                        f"{resultant:.2f}, {100 * agree:.0f}% of the views agree)"}
    if down is not None:
        cos = [float(u @ d) for d, s in zip(down, sils, strict=True) if s.any() and np.any(d)]
        if cos:
            angle = float(np.degrees(np.arccos(np.clip(np.median(cos), -1.0, 1.0))))
            info["foot_angle"] = angle
            if angle < settings.foot_deg:
                return None, {**info, "reason": f"the dark pixels lie along the outline towards the object's foot "
                                                f"({angle:.0f} degrees from it), where no shadow can show: the object's "
                                                "own dark lower part"}
    return u, info


def shadow_pixels(dark: np.ndarray, sil: np.ndarray, direction: np.ndarray,
                  settings: ShadowSettings = ShadowSettings()) -> np.ndarray:
    """(H, W) bool: the ``dark`` pixels in the band about the outline of ``sil`` whose outward
    normal lies within ``cone_deg`` of the shadow's ``direction``."""
    if not sil.any():
        return np.zeros_like(dark)
    sd, n = outline_normals(sil)
    side = (n @ np.asarray(direction, np.float32)) >= np.cos(np.radians(settings.cone_deg))
    return _thin(dark, sil, sd, settings.band) & side


__all__ = ["ShadowSettings", "outline_normals", "shadow_direction", "shadow_pixels", "towards_foot"]
