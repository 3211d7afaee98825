"""The object's foot on a table: pixels whose masks cannot be trusted, made background or left out.

Tabletop masks (:mod:`recon.masks.tabletop`) tell the object from the table by the parallax the
support plane induces between neighbouring views. Within the *parallax band* above the table
(``poses/masks.json``: ``segment.hull.parallax_band``, about a tenth of the object's height) there is too little parallax, and the
masks there come from the hull's extruded section and the photo's colours. Where the object
overhangs its foot (a blob, a bowl's rim, a vase's belly), the masks take in the table under the
overhang: measured on the scene family of docs/tabletop.md, 77-91 % of the pixels the masks add
see the table under the object. The image term targets ``photo x mask``, so every such pixel
pulls the surface over it (uncovering it would render black against the table's colour), and
the optimizer grows a skirt between the bulge and the table instead of carving it (wood-blob:
8.7 % -> 14.2 % of the surface far from the object, accuracy 0.0065 -> 0.0080).

:func:`foot_classes` finds, per view, the pixels near a silhouette (the mask's or the initial
mesh's) whose ray meets the initial mesh, or else the table, within the band (its height above
the plane, its width around the mesh's foot). They get weight 0 in the image term, as clipped
pixels do: neither covering nor uncovering them is rewarded, and the surface there follows the
priors and the views that see it elsewhere. Only points under an overhang are doubted (the mesh
stands over them: a skirt is the extrusion of a wider section; a bell's flared lip is not, and
left to the priors it folds). A mask pixel there whose colour the table beside the
foot does not show (its chromaticity farther than ``TABLE_SIGMAS`` from that of the zone's pixels
outside the mask) is the object's and stays: without it the priors round a straight foot inward
(a mug's: docs/tabletop.md). Only views whose masks the tabletop method made are touched: given
masks are trusted, and a capture without a plane has no foot to doubt.

:func:`foot_classes` sorts those pixels (:data:`TABLE`: a mask pixel with the table's colour and
brightness; :data:`DOUBT`: one too dark to tell, or with the table's colour but not its brightness
(:func:`table_or_object`: an object in the table's colours, whose surface at the foot faces the
flash at another angle than the table); :data:`OUTSIDE`: outside the mask). With
``loss.uncertain_foot_mode: background`` (the default) a :data:`TABLE` pixel becomes background:
target 0 at full weight, so a surface over it is pushed off, as over any background pixel, and
the skirt is carved rather than only left to the priors (wood-blob 0.0041 -> 0.0028, the dark
bowl's rim 0.0235 -> 0.0166; docs/tabletop.md). ``exclude`` leaves every doubted pixel out.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from recon.io.mesh import Mesh
from recon.support import SupportPlane

log = logging.getLogger(__name__)


# a mask pixel at the foot whose chromaticity lies farther than this many standard deviations from
# the table's beside the foot is the object's, whatever the masks' doubt: it stays in the image term
TABLE_SIGMAS = 3.0

KEEP, DOUBT, TABLE, OUTSIDE = 0, 1, 2, 3  # foot_classes


@dataclass(frozen=True)
class FootZone:
    """The foot's zone: heights up to ``height`` above ``plane``, within ``height`` (horizontally)
    of the initial mesh's part there; ``stems``: the views whose masks are in doubt there."""

    plane: SupportPlane
    height: float
    mesh: Mesh
    stems: frozenset
    weight: float = 0.0  # the doubtful pixels' weight

    def weights(self, cameras, masks: np.ndarray, images: np.ndarray | None = None) -> np.ndarray:
        """(N, h, w) float32: ``weight`` on the doubtful foot pixels of the views in ``stems``, else 1.
        With ``images`` (N, h, w, 3), a mask pixel whose colour the table beside the foot does not
        show stays in (:func:`table_like`)."""
        return np.where(foot_classes(self, cameras, masks, images) > KEEP, np.float32(self.weight),
                        np.float32(1.0)).astype(np.float32)

    def classes(self, cameras, masks: np.ndarray, images: np.ndarray | None = None) -> np.ndarray:
        """(N, h, w) int8: :data:`KEEP`, :data:`DOUBT` (a mask pixel too dark to tell, or without
        ``images``), :data:`TABLE` (a mask pixel with the table's colour), :data:`OUTSIDE` (a
        doubted pixel outside the mask)."""
        return foot_classes(self, cameras, masks, images)


def foot_zone(masks_json: str | os.PathLike | None, plane: SupportPlane | None, mesh: Mesh,
              factor: float, weight: float = 0.0) -> FootZone | None:
    """The zone from the poses stage's ``masks.json`` (beside ``plane.json``), or None: no plane,
    no tabletop masks, ``factor`` 0 (off), or no band recorded. The masks' band is recorded in
    the frame they were made in, with the height of their hull: the zone is the same share of
    ``mesh``'s height above ``plane``, times ``factor``."""
    if plane is None or factor <= 0 or masks_json is None or not Path(masks_json).is_file():
        return None
    summary = json.loads(Path(masks_json).read_text())
    stems = frozenset(s for s, v in (summary.get("views") or {}).items() if v.get("source") == "tabletop")
    hull = (summary.get("segment") or {}).get("hull") or {}
    band, height = hull.get("parallax_band"), hull.get("height")
    if not stems or not band or not height or not band > 0 or not height > 0:
        return None
    top = float(np.max(plane.height(mesh.v_pos)))
    if not top > 0:
        return None
    return FootZone(plane, float(factor) * min(float(band) / float(height), 1.0) * top, mesh, stems, float(weight))


def _disk(r: int) -> np.ndarray:
    y, x = np.mgrid[-r:r + 1, -r:r + 1]
    return (x * x + y * y <= r * r).astype(np.uint8)


def _chroma(rgb: np.ndarray) -> np.ndarray:
    """(n, 2) chromaticity r, g of linear RGB (brightness, which the flash's falloff and the
    grazing light under an overhang change, left out)."""
    s = np.maximum(rgb.sum(-1, keepdims=True), 1e-6)
    return (rgb / s)[:, :2]


def table_like(table: np.ndarray, pixels: np.ndarray, k: float = TABLE_SIGMAS) -> np.ndarray:
    """(m,) bool: ``pixels (m, 3)`` whose chromaticity lies within ``k`` standard deviations
    (Mahalanobis) of the ``table (n, 3)`` pixels', or too dark to tell (under a twentieth of the
    table's median brightness: their chromaticity is noise); all True when fewer than 20 table pixels."""
    if len(table) < 20:
        return np.ones(len(pixels), bool)
    c = _chroma(table)
    mu = c.mean(0)
    cov = np.cov(c.T) + 1e-6 * np.eye(2)
    x = _chroma(pixels) - mu
    return too_dark(table, pixels) | (np.einsum("ni,ij,nj->n", x, np.linalg.inv(cov), x) <= k * k)


# a doubted mask pixel brighter or darker than the table beside the foot by more than this factor
# (beyond the 5th-95th percentiles of its brightness) is not the table seen at that distance from
# the flash: it stays in doubt rather than being made background
BRIGHTNESS_MARGIN = 1.25


def table_or_object(table: np.ndarray, pixels: np.ndarray, k: float = TABLE_SIGMAS,
                    margin: float = BRIGHTNESS_MARGIN) -> np.ndarray:
    """(m,) int8: :data:`TABLE`, :data:`DOUBT` or :data:`KEEP` for the doubted mask ``pixels (m, 3)``.

    KEEP: not :func:`table_like` the ``table (n, 3)`` pixels beside the foot. TABLE: table-like in
    chromaticity and, in brightness, within ``margin`` of the 5th-95th percentiles of the table's:
    the table under an overhang is at the same distance from the flash and seen at the same angle
    as the table beside the foot, where the object's own surface there, turned towards or away
    from the camera, is brighter or darker (a vase in the table's colours whose foot would be made
    background: docs/tabletop.md, session 24). DOUBT: too dark to tell, or table-like in colour
    only. With fewer than 20 table pixels every pixel is DOUBT."""
    if len(table) < 20:
        return np.full(len(pixels), DOUBT, np.int8)
    like = table_like(table, pixels, k)
    dark = too_dark(table, pixels)
    lo, hi = np.percentile(table.sum(-1), [5, 95])
    b = pixels.sum(-1)
    bright = (b >= lo / margin) & (b <= hi * margin)
    return np.where(like, np.where(~dark & bright, TABLE, DOUBT), KEEP).astype(np.int8)


def too_dark(table: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """(m,) bool: ``pixels`` under a twentieth of the ``table`` pixels' median brightness (their
    chromaticity is noise); all True when fewer than 20 table pixels (nothing to compare with)."""
    if len(table) < 20:
        return np.ones(len(pixels), bool)
    return pixels.sum(-1) < 0.05 * np.median(table.sum(-1))


def _under_overhang(scene, zone: FootZone, axis, B, o, d, t, tp, doubt: np.ndarray) -> np.ndarray:
    """(H, W) bool: the ``doubt`` pixels whose point (on the mesh, else on the table) the mesh
    stands over: a vertical ray up from it, moved a tenth of the zone away from the foot's axis,
    meets the mesh. The masks' skirt lies under an overhang (the extrusion of a wider section);
    a flared foot (a bell's lip) does not, and keeps its pixels."""
    import open3d as o3d

    plane = zone.plane
    idx = np.flatnonzero(doubt.ravel())
    out = np.zeros(doubt.size, bool)
    if not len(idx):
        return out.reshape(doubt.shape)
    tt = np.where(np.isfinite(t[idx]), t[idx], np.where(np.isfinite(tp[idx]), tp[idx], 0.0))
    q = o + tt[:, None] * d[idx]
    away = (q - axis) @ B.T @ B
    away /= np.maximum(np.linalg.norm(away, axis=1, keepdims=True), 1e-12)
    start = q + 0.1 * zone.height * away + 1e-3 * zone.height * plane.normal
    up = np.concatenate([start, np.broadcast_to(plane.normal, start.shape)], 1).astype(np.float32)
    out[idx] = np.isfinite(scene.cast_rays(o3d.core.Tensor(up))["t_hit"].numpy())
    return out.reshape(doubt.shape)


def foot_classes(zone: FootZone, cameras, masks: np.ndarray, images: np.ndarray | None = None) -> np.ndarray:
    import cv2
    import open3d as o3d
    from scipy.spatial import cKDTree

    n, H, W = masks.shape
    out = np.zeros((n, H, W), np.int8)
    mesh, plane = zone.mesh, zone.plane
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.v_pos.astype(np.float32)),
                        o3d.core.Tensor(mesh.t_pos_idx.astype(np.uint32)))
    low = mesh.v_pos[plane.height(mesh.v_pos) <= zone.height]
    B = plane.basis()[:2]
    tree = cKDTree(low @ B.T) if len(low) else None
    axis = plane.project(low.mean(0) if len(low) else mesh.v_pos.mean(0))
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    pix = np.stack([jj.ravel(), ii.ravel(), np.ones(jj.size)], 1)
    for k, cam in enumerate(cameras):
        if cam.stem not in zone.stems:
            continue
        d = (pix @ np.linalg.inv(cam.K).T) @ cam.world_to_camera[:3, :3]
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        o = cam.center
        rays = np.concatenate([np.broadcast_to(o, d.shape), d], 1).astype(np.float32)
        t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)
        hit = np.isfinite(t)
        p = o + np.where(hit, t, 0.0)[:, None] * d
        in_zone = hit & (plane.height(p) <= zone.height)
        # rays that miss the mesh: where they meet the table near the mesh's foot
        tp = plane.ray_hit(o[None], d)
        ok = ~hit & np.isfinite(tp) & (tp > 0)
        if tree is not None and ok.any():
            q = (o + tp[ok, None] * d[ok]) @ B.T
            in_zone[np.flatnonzero(ok)] = tree.query(q, distance_upper_bound=zone.height)[0] <= zone.height
        in_zone = in_zone.reshape(H, W)
        if not in_zone.any():
            continue
        # only near a silhouette (the mask's or the mesh's): inside both, farther than the band's
        # width in pixels from either edge, the object surely hides the table
        depth = float(np.linalg.norm(low - o, axis=1).mean()) if len(low) else float(np.linalg.norm(mesh.v_pos - o, axis=1).mean())
        r = int(np.clip(np.ceil(zone.height * cam.K[0, 0] / max(depth, 1e-12)), 1, max(H, W)))
        both = ((masks[k] > 0.5) & hit.reshape(H, W)).astype(np.uint8)
        interior = cv2.erode(both, _disk(r), borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0
        doubt = in_zone & ~interior
        doubt &= _under_overhang(scene, zone, axis, B, o, d, t, tp, doubt)
        inside = doubt & (masks[k] > 0.5)
        out[k][doubt & ~inside] = OUTSIDE
        out[k][inside] = DOUBT
        if images is not None:
            # a mask pixel in the zone is doubted only when it looks like the table: the table's
            # colour and brightness from the zone's pixels outside the mask (the table beside the foot)
            table = images[k][doubt & (masks[k] <= 0.5)]
            out[k][inside] = table_or_object(table, images[k][inside])
    return out
