"""Sparse 3D points for the support plane: the poses stage's (``poses/points.ply``, read with
:func:`recon.io.mesh.read_points`) or, with known cameras, triangulated here from SIFT matches."""

from __future__ import annotations

import numpy as np

from recon.io.cameras import CameraSet
from recon.masks.common import display_image


def triangulate_points(images: list[np.ndarray], cams: CameraSet, pairs_per_view: int = 3,
                       max_error_px: float = 1.5, min_angle_deg: float = 1.0) -> np.ndarray:
    """(N, 3) points triangulated from SIFT matches between neighbouring views with known cameras.

    Each view is matched with its ``pairs_per_view`` nearest views (viewing direction); a match
    passes Lowe's ratio test (0.8), triangulates in front of both cameras with a reprojection
    error below ``max_error_px`` in both and a triangulation angle above ``min_angle_deg``.
    """
    import cv2

    sift = cv2.SIFT_create(nfeatures=4000, contrastThreshold=0.01)
    feats = []
    for img in images:
        gray = cv2.cvtColor(display_image(np.nan_to_num(np.maximum(img[:, :, :3], 0.0))), cv2.COLOR_RGB2GRAY)
        kp, desc = sift.detectAndCompute(gray, None)
        pts = np.array([k.pt for k in kp], np.float64).reshape(-1, 2) + 0.5  # DESIGN pixel coordinates
        feats.append((pts, desc))
    z = np.stack([c.camera_to_world[:3, 2] for c in cams])
    ang = np.degrees(np.arccos(np.clip(z @ z.T, -1.0, 1.0)))
    pairs = set()
    for i in range(len(cams)):
        for j in [j for j in np.argsort(ang[i], kind="stable") if j != i][:pairs_per_view]:
            pairs.add((min(i, j), max(i, j)))
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    out = []
    for i, j in sorted(pairs):
        (pi, di), (pj, dj) = feats[i], feats[j]
        if di is None or dj is None or len(di) < 8 or len(dj) < 8:
            continue
        knn = matcher.knnMatch(di.astype(np.float32), dj.astype(np.float32), k=2)
        good = [m[0] for m in knn if len(m) == 2 and m[0].distance < 0.8 * m[1].distance]
        if len(good) < 8:
            continue
        a = pi[[m.queryIdx for m in good]]
        b = pj[[m.trainIdx for m in good]]
        ci, cj = cams.frames[i], cams.frames[j]
        Pi = ci.K @ ci.world_to_camera[:3, :]
        Pj = cj.K @ cj.world_to_camera[:3, :]
        X = cv2.triangulatePoints(Pi, Pj, a.T, b.T)
        X = (X[:3] / np.where(np.abs(X[3]) > 1e-12, X[3], 1e-12)).T
        ok = np.ones(len(X), bool)
        for cam, obs in ((ci, a), (cj, b)):
            xy, depth = cam.project(X)
            ok &= (depth > 0) & (np.linalg.norm(xy - obs, axis=1) < max_error_px)
        ri = X - ci.center
        rj = X - cj.center
        cosang = (ri * rj).sum(1) / np.maximum(np.linalg.norm(ri, axis=1) * np.linalg.norm(rj, axis=1), 1e-12)
        ok &= cosang < np.cos(np.radians(min_angle_deg))
        out.append(X[ok])
    return np.concatenate(out) if out else np.zeros((0, 3))


def sparse_point_masks(points: np.ndarray, cams: CameraSet, reach: float = 0.35, min_points: int = 100
                       ) -> dict[str, np.ndarray]:
    """Masks drawn from the object's sparse points, for a capture whose flash-falloff masks fail
    (a near-black object the flash lifts no more than the lit wall or base behind it).

    The points within ``reach`` of the scene scale (the median camera distance) of the point the
    cameras aim at are taken as the object's. Every point of an object projects inside its
    silhouette in every view, seen or hidden, so in each view the points are splatted at the
    spacing of their projections (the median distance to the third nearest), closed by as much,
    and the largest piece kept; holes stay (an opening the views see through, or a patch
    without points), for the vote across the views to tell apart. The outline is as good as the points reach:
    the object's texture decides (SfM found the points on it). Returns the masks by stem of the
    views where at least ``min_points`` points fall in the frame; the others are left out.
    """
    import cv2
    from scipy import ndimage
    from scipy.spatial import cKDTree

    from recon.support import aim_point, scene_scale

    pts = np.asarray(points, np.float64).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if len(pts) < min_points:
        return {}
    target = aim_point(cams)
    pts = pts[np.linalg.norm(pts - target, axis=1) < reach * scene_scale(cams, target)]
    out = {}
    for cam in cams:
        xy, z = cam.project(pts)
        ok = (z > 0) & np.all(np.isfinite(xy), axis=1)
        ok[ok] = (xy[ok, 0] >= 0) & (xy[ok, 0] < cam.width) & (xy[ok, 1] >= 0) & (xy[ok, 1] < cam.height)
        q = xy[ok]
        if len(q) < min_points:
            continue
        spacing, _ = cKDTree(q).query(q, k=4)
        radius = int(np.clip(np.ceil(np.median(spacing[:, 3])), 2, 0.05 * max(cam.width, cam.height)))
        m = np.zeros((cam.height, cam.width), np.uint8)
        for x, y in np.floor(q).astype(int):
            cv2.circle(m, (int(x), int(y)), radius, 1, -1)
        m = ndimage.binary_closing(m.astype(bool), iterations=radius)
        labels, n = ndimage.label(m)
        if n > 1:
            sizes = ndimage.sum_labels(m, labels, index=np.arange(1, n + 1))
            m = labels == 1 + int(np.argmax(sizes))
        out[cam.stem] = m
    return out
