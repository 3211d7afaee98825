"""The object frame: the similarity from COLMAP's frame to a frame where the object is centered,
inside [-1, 1]^3, with z up.

z is the mean of the cameras' up vectors (photographers hold the camera roughly upright), x and
y the principal axes of the sparse points that project inside the masks; a coarse visual hull
(``hull_resolution``^3) of the undistorted masks around those points gives the object's extent
(sparse points miss untextured parts, the hull never misses object); the object is centered and
scaled to fill ``1 - margin`` of [-1, 1]^3.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from recon.hull import Grid, silhouette_field
from recon.io.cameras import Camera, CameraSet
from recon.metrics import Similarity
from recon.poses.settings import PoseError, PoseSettings

log = logging.getLogger(__name__)


def points_in_masks(rec, masks: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The sparse points of ``rec`` (N, 3) and whether each lies in the object: at least half of
    the observations in views with a mask fall inside it (all False without masks)."""
    pids = list(rec.point3D_ids())
    xyz = np.array([rec.point3D(p).xyz for p in pids]).reshape(-1, 3)
    in_mask = np.zeros(len(pids), bool)
    if masks:
        for k, pid in enumerate(pids):
            votes = []
            for el in rec.point3D(pid).track.elements:
                im = rec.images[el.image_id]
                st = Path(im.name).stem
                if st in masks:
                    x, y = im.points2D[el.point2D_idx].xy
                    mm = masks[st]
                    i, j = int(y), int(x)
                    votes.append(0 <= i < mm.shape[0] and 0 <= j < mm.shape[1] and bool(mm[i, j]))
            in_mask[k] = bool(votes) and np.mean(votes) >= 0.5
    return xyz, in_mask


def _rotation_from_axes(z_up: np.ndarray, points: np.ndarray, first_center: np.ndarray) -> np.ndarray:
    """Rows x, y, z of the object frame in COLMAP coordinates."""
    z = z_up / np.linalg.norm(z_up)
    flat = points - points.mean(0)
    flat = flat - np.outer(flat @ z, z)
    cov = flat.T @ flat
    w, v = np.linalg.eigh(cov)
    x = v[:, -1]
    x = x - (x @ z) * z
    if np.linalg.norm(x) < 1e-9:  # degenerate: any horizontal direction
        x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    if x @ (first_center - points.mean(0)) < 0:
        x = -x
    y = np.cross(z, x)
    return np.stack([x, y, z])


def _hull_box(cams: CameraSet, masks: dict, center: np.ndarray, half: float, resolution: int):
    """Bounding box (lo, hi) of a coarse visual hull in a cube, or (None, why) if unusable."""
    grid = Grid.cube(center, half, resolution)
    field, _ = silhouette_field(cams, masks, grid, min_views=max(2, len(masks) // 4))
    occ = field > 0
    if occ.sum() < 8:
        return None, "empty"
    idx = np.argwhere(occ)
    if idx.min() == 0 or idx.max() == resolution - 1:
        return None, "touches the box"
    lo = grid.origin + grid.step * idx.min(0) - grid.step  # one voxel of slack each side
    hi = grid.origin + grid.step * idx.max(0) + grid.step
    return (lo, hi), "ok"


def object_frame(cams_colmap: CameraSet, points: np.ndarray, in_mask: np.ndarray, masks: dict,
                 settings: PoseSettings, orientations: dict[str, int] | None = None) -> tuple[Similarity, dict]:
    """Similarity COLMAP -> object frame (centered, inside [-1, 1]^3, z up); see the module doc.

    ``orientations``: the EXIF Orientation of views whose stored pixels are turned for display
    (a phone held upright stores its pixels sideways): their up is a column direction, not -y."""
    from recon.linearize.metadata import camera_up

    orientations = orientations or {}
    centers = np.stack([c.center for c in cams_colmap])
    # each photo's up as displayed (-y of the camera for upright pixels), in COLMAP's frame
    ups = np.stack([c.world_to_camera[:3, :3].T @ np.asarray(camera_up(orientations.get(c.stem)))
                    for c in cams_colmap])
    z = ups.mean(0)
    if np.linalg.norm(z) < 1e-3:
        z = np.array([0.0, 0.0, 1.0])
    pts = points[in_mask] if in_mask.sum() >= 20 else points
    source = "sparse points in the masks" if in_mask.sum() >= 20 else "all sparse points (few inside the masks)"
    if len(pts) < 4:
        pts = centers  # nothing else to go by
        source = "camera centers"
    R = _rotation_from_axes(z, pts, centers[0])
    q = pts @ R.T
    p = settings.frame.bbox_percentile
    lo, hi = np.percentile(q, p, axis=0), np.percentile(q, 100 - p, axis=0)
    info = {"box_source": source, "n_points": int(len(pts))}
    if settings.frame.hull_resolution > 0 and len(masks) >= 2:
        c_box = R.T @ (0.5 * (lo + hi))
        half = float(np.max(hi - lo))  # a cube twice the sparse box's longest side
        rotated = rotate_cameras(cams_colmap, Similarity(1.0, R, np.zeros(3)))
        for _ in range(2):
            box, why = _hull_box(rotated, masks, R @ c_box, half, settings.frame.hull_resolution)
            if box is not None:
                lo, hi = box
                info["box_source"] = f"visual hull ({settings.frame.hull_resolution}^3) of the masks"
                break
            if why == "empty":
                log.warning("coarse visual hull is empty: masks and cameras disagree; using the sparse box")
                break
            half *= 2.0
        else:
            log.warning("the visual hull reaches the box edge: masks may include background; using the sparse box")
    center = 0.5 * (lo + hi)
    extent = float(np.max(hi - lo))
    if extent <= 0:
        raise PoseError("the sparse reconstruction has no extent: cannot place the object")
    s = 2.0 * (1.0 - settings.frame.margin) / extent
    sim = Similarity(s, R, -s * center)
    info.update({"box_lo": lo.tolist(), "box_hi": hi.tolist()})
    return sim, info


def rotate_cameras(cams: CameraSet, sim: Similarity) -> CameraSet:
    """The same cameras in the frame x' = s R x + t (world_to_camera stays rigid)."""
    out = []
    for c in cams:
        W = c.world_to_camera
        R2 = W[:3, :3] @ sim.rotation.T
        t2 = sim.scale * W[:3, 3] - R2 @ sim.translation
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = R2, t2
        out.append(Camera(c.image, c.width, c.height, c.K.copy(), M))
    return CameraSet(tuple(out), cams.light_intensity, dict(cams.extra), light_known=cams.light_known)

