"""Dense depth by plane sweep inside the visual hull: points for the free-space carving.

The visual hull closes every concavity (a bowl's inside, a skull's eye sockets): no silhouette
sees into one. SfM's points carve the space they were seen through (:mod:`recon.freespace`), but
they are sparse: a few per concavity where the texture gives SIFT a feature, none where it gives
none at SfM's scale. This module gives the carving many more, from the photos themselves:

- **Per view a depth map** (:func:`sweep_view`), by a plane sweep (fronto-parallel planes of the
  view, uniform in inverse depth) against its nearest views by viewing direction: each
  neighbour's image is warped onto the view through the plane's homography, and compared by
  zero-mean normalised cross-correlation (ZNCC) in a small window. ZNCC ignores a gain and an
  offset per window: the flash moves with the camera, so the same surface is lit differently in
  each view (1/r^2, the angle), but smoothly. A pixel's score is the mean of its best
  ``best_of`` neighbours' (a neighbour that does not see the point, hidden by the object, is left
  out). The sweep runs only between the hull's front and back along each ray: the object lies
  inside the hull, and a concavity's floor lies behind the hull's front.
- **Kept only where it holds**: a clear texture in the window, a score of at least ``min_zncc``,
  and the same depth in at least ``min_consistent`` neighbours' own depth maps (the geometric
  check of multi-view stereo fusion): a match that two views' independent sweeps agree on.
- The points are :class:`recon.freespace.SeenPoints`: observed by their view and by the
  neighbours that agree, so the carving takes the segments from those cameras to the point.

Where the surface has no texture (a plain glaze) the sweep gives nothing, and the hull stays
(the optimizer's shading is then what can move it). Measured in docs/init_mesh.md ("Dense
points").
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from recon.hull import Grid
from recon.io.cameras import Camera, CameraSet

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SweepSettings:
    work_size: int = 320  # the views' long side for the sweep (pixels)
    neighbours: int = 4  # views compared with each view: the nearest by viewing direction ...
    min_angle_deg: float = 3.0  # ... at least this far apart (a baseline) ...
    max_angle_deg: float = 40.0  # ... and at most this far (the surface still looks alike)
    depths: int = 96  # planes, uniform in inverse depth over the hull's depth range in the view
    window: int = 7  # ZNCC window (pixels at the working size)
    best_of: int = 2  # a pixel's score: the mean of its best neighbours' ZNCC
    min_zncc: float = 0.8
    min_texture: float = 0.02  # the window's standard deviation of the encoded luminance (0-1)
    consistency: float = 0.01  # relative depth agreement with a neighbour's own depth map
    min_consistent: int = 2
    margin_voxels: float = 1.5  # the sweep's range: the hull's front and back, widened by this
    highpass: float = 2.0  # the images' Gaussian blur of this sigma (pixels) is subtracted: the
    # texture is compared, not the smooth shading (which the flash changes from view to view)


def _encoded(rgb: np.ndarray, highpass: float = 0.0) -> np.ndarray:
    """(H, W) float32 luminance encoded with a 1/2.2 power (the texture's contrast evened out
    between the dark and the bright parts), finite; with ``highpass`` > 0 less its Gaussian
    blur of that sigma."""
    import cv2

    lum = np.nan_to_num(np.maximum(np.asarray(rgb, np.float32)[..., :3], 0.0)) @ np.float32([0.2126, 0.7152, 0.0722])
    top = float(np.quantile(lum, 0.995)) or 1.0
    enc = np.power(np.clip(lum / top, 0.0, 1.0), 1.0 / 2.2).astype(np.float32)
    if highpass > 0:
        enc = enc - cv2.GaussianBlur(enc, (0, 0), highpass)
    return enc


def _rays(cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel centre the world direction whose camera z is 1 (so that a distance along it is
    the depth), ``(H*W, 3)``, and the camera's centre."""
    j, i = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    d = np.stack([j, i, np.ones_like(j)], -1).reshape(-1, 3) @ np.linalg.inv(cam.K).T
    return d @ cam.world_to_camera[:3, :3], cam.center


def hull_depths(cam: Camera, scene, far: float) -> tuple[np.ndarray, np.ndarray]:
    """The hull's front and back depth along each pixel's ray (``(H, W)``, inf where the ray
    misses it): ``scene`` an open3d RaycastingScene of the hull's surface, ``far`` a distance
    beyond it."""
    import open3d as o3d

    d, c = _rays(cam)
    o = np.broadcast_to(c, d.shape)
    front = scene.cast_rays(o3d.core.Tensor(np.concatenate([o, d], 1).astype(np.float32)))["t_hit"].numpy()
    back_o = o + far * d
    back = scene.cast_rays(o3d.core.Tensor(np.concatenate([back_o, -d], 1).astype(np.float32)))["t_hit"].numpy()
    back = np.where(np.isfinite(back), far - back, np.inf)
    shape = (cam.height, cam.width)
    return front.reshape(shape).astype(np.float64), back.reshape(shape)


def neighbours(cams, target: np.ndarray, settings: SweepSettings) -> list[list[int]]:
    """Per view the indices of its nearest views by the direction they see ``target`` from,
    between ``min_angle_deg`` and ``max_angle_deg`` apart, at most ``neighbours`` of them."""
    dirs = np.stack([c.center - target for c in cams])
    dirs /= np.maximum(np.linalg.norm(dirs, axis=1, keepdims=True), 1e-12)
    ang = np.degrees(np.arccos(np.clip(dirs @ dirs.T, -1.0, 1.0)))
    out = []
    for i in range(len(cams)):
        order = np.argsort(ang[i])
        ok = [int(j) for j in order if j != i and settings.min_angle_deg <= ang[i, j] <= settings.max_angle_deg]
        out.append(ok[: settings.neighbours])
    return out


def _homography(ref: Camera, other: Camera, depth: float) -> np.ndarray:
    """The map from ``ref``'s pixels to ``other``'s through ref's fronto-parallel plane at
    ``depth``, in OpenCV's pixel convention (integer coordinates at the pixel centres)."""
    Ri, ti = ref.world_to_camera[:3, :3], ref.world_to_camera[:3, 3]
    Rj, tj = other.world_to_camera[:3, :3], other.world_to_camera[:3, 3]
    R = Rj @ Ri.T
    t = tj - R @ ti
    H = other.K @ (R + np.outer(t, [0.0, 0.0, 1.0 / depth])) @ np.linalg.inv(ref.K)
    shift = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
    back = np.array([[1.0, 0.0, -0.5], [0.0, 1.0, -0.5], [0.0, 0.0, 1.0]])
    return back @ H @ shift


def _box(x: np.ndarray, k: int) -> np.ndarray:
    import cv2

    return cv2.boxFilter(x, -1, (k, k), normalize=True, borderType=cv2.BORDER_REFLECT)


def sweep_view(i: int, cams: list[Camera], images: list[np.ndarray], nbrs: list[int], front: np.ndarray,
               back: np.ndarray, mask: np.ndarray, margin: float, settings: SweepSettings
               ) -> tuple[np.ndarray, np.ndarray]:
    """View ``i``'s depth map and score (``(H, W)``; depth nan where no depth was found):
    the plane sweep of the module docstring between ``front - margin`` and ``back + margin``."""
    import cv2

    ref = cams[i]
    A = images[i]
    k = settings.window
    mA = _box(A, k)
    vA = np.maximum(_box(A * A, k) - mA * mA, 0.0)
    # the window wholly inside the mask: across the outline it holds the background's edge
    inner = cv2.erode(mask.astype(np.uint8), np.ones((k + 2, k + 2), np.uint8)).astype(bool)
    hit = np.isfinite(front) & np.isfinite(back) & inner & (np.sqrt(vA) >= settings.min_texture)
    h, w = A.shape
    depth = np.full((h, w), np.nan)
    score = np.full((h, w), -np.inf, np.float32)
    if not hit.any() or not nbrs:
        return depth, score
    lo = max(float(front[hit].min()) - margin, 1e-6)
    hi = float(back[hit].max()) + margin
    inv = np.linspace(1.0 / lo, 1.0 / hi, settings.depths)
    scores = np.full((settings.depths, h, w), -np.inf, np.float32)
    ones = np.ones((h, w), np.float32)
    best_of = min(settings.best_of, len(nbrs))
    for d_i, z in enumerate(1.0 / inv):
        per = np.full((len(nbrs), h, w), -1.0, np.float32)
        for n, j in enumerate(nbrs):
            H = _homography(ref, cams[j], z)
            flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
            B = cv2.warpPerspective(images[j], H, (w, h), flags=flags, borderValue=0.0)
            valid = cv2.warpPerspective(ones, H, (w, h), flags=flags, borderValue=0.0)
            mB = _box(B, k)
            vB = np.maximum(_box(B * B, k) - mB * mB, 0.0)
            cov = _box(A * B, k) - mA * mB
            zncc = cov / np.sqrt(vA * vB + 1e-8)
            per[n] = np.where((_box(valid, k) > 0.999) & (vB > 1e-6), zncc, -1.0)
        per.sort(axis=0)
        scores[d_i] = per[-best_of:].mean(0)
    # the sweep's range per pixel: inside the hull, widened by the margin
    zs = 1.0 / inv
    inside = (zs[:, None, None] >= front[None] - margin) & (zs[:, None, None] <= back[None] + margin)
    scores = np.where(inside, scores, -np.inf)
    best = np.argmax(scores, axis=0)
    s_best = np.take_along_axis(scores, best[None], 0)[0]
    # sub-plane: a parabola through the best plane and its neighbours (in inverse depth)
    scores = np.maximum(scores, np.float32(-2.0))  # outside the range: below any ZNCC, finite
    b0 = np.clip(best, 1, settings.depths - 2)
    s_m = np.take_along_axis(scores, (b0 - 1)[None], 0)[0]
    s_0 = np.take_along_axis(scores, b0[None], 0)[0]
    s_p = np.take_along_axis(scores, (b0 + 1)[None], 0)[0]
    den = s_m - 2 * s_0 + s_p
    with np.errstate(invalid="ignore", divide="ignore"):
        off = np.where(np.isfinite(den) & (den < 0) & (best == b0), 0.5 * (s_m - s_p) / den, 0.0)
    off = np.clip(np.nan_to_num(off), -0.5, 0.5)
    step = inv[1] - inv[0] if settings.depths > 1 else 0.0
    inv_best = inv[best] + off * step
    ok = hit & (s_best >= settings.min_zncc) & (inv_best > 0)
    depth[ok] = 1.0 / inv_best[ok]
    score[ok] = s_best[ok]
    return depth, score


def dense_seen_points(cams: CameraSet, load: Callable[[str], np.ndarray], masks: dict[str, np.ndarray],
                      field: np.ndarray, grid: Grid, max_points: int, settings: SweepSettings = SweepSettings(),
                      seed: int = 0):
    """Depth maps of every view inside the hull of ``field`` on ``grid`` (positive inside),
    checked against each other, as :class:`recon.freespace.SeenPoints` in ``cams``' frame (at
    most ``max_points`` per view, drawn at random), and what was done. ``load(stem)`` gives a
    view's linear image (the pinhole view of the camera), ``masks`` the views' masks at the
    cameras' size. None (and the reason) when the hull has no surface or no view a neighbour."""
    import open3d as o3d

    from recon.freespace import SeenPoints
    from recon.init_mesh import isosurface, largest_component
    from recon.masks.evidence import resized, working_cameras
    import cv2

    t0 = time.perf_counter()
    surf = largest_component(isosurface(field, grid, space="grid"))
    if len(surf.t_pos_idx) == 0:
        return None, {"reason": "the hull has no surface"}
    verts = surf.v_pos * grid.step + grid.origin
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(verts.astype(np.float32)), o3d.core.Tensor(surf.t_pos_idx.astype(np.uint32)))
    target = verts.mean(0)
    wcams = working_cameras(cams, settings.work_size).frames
    cams = list(cams)
    nbrs = neighbours(wcams, target, settings)
    if not any(nbrs):
        return None, {"reason": f"no two views between {settings.min_angle_deg} and {settings.max_angle_deg} degrees apart"}
    images = [_encoded(resized(load(c.stem), (w.width, w.height)), settings.highpass)
              for c, w in zip(cams, wcams, strict=True)]
    far = float(np.linalg.norm(np.stack([c.center for c in cams]) - target, axis=1).max()) + 2.0 * grid.step * grid.resolution
    margin = settings.margin_voxels * grid.step
    depths = []
    for i, w in enumerate(wcams):
        front, back = hull_depths(w, scene, far)
        m = masks.get(cams[i].stem)
        m = np.ones((w.height, w.width), bool) if m is None else \
            cv2.resize(m.astype(np.uint8), (w.width, w.height), interpolation=cv2.INTER_NEAREST).astype(bool)
        depths.append(sweep_view(i, list(wcams), images, nbrs[i], front, back, m, margin, settings)[0])
        if (i + 1) % max(1, len(wcams) // 4) == 0 and i + 1 < len(wcams):
            log.info("depth maps: %d of %d views, %.0f s", i + 1, len(wcams), time.perf_counter() - t0)
    # the geometric check: a neighbour's own depth map agrees at the point's projection
    rng = np.random.default_rng(seed)
    pts, obs_view, obs_point = [], [], []
    kept_views = {}
    for i, w in enumerate(wcams):
        ok = np.isfinite(depths[i])
        if not ok.any():
            continue
        rays, c = _rays(w)
        sel = np.flatnonzero(ok.ravel())
        X = c + rays[sel] * depths[i].ravel()[sel, None]
        agree = [np.ones(len(sel), bool)]
        views = [i]
        for j in nbrs[i]:
            xy, z = wcams[j].project(X)
            col, row = np.floor(xy[:, 0]).astype(np.int64), np.floor(xy[:, 1]).astype(np.int64)
            inb = (z > 0) & (col >= 0) & (col < wcams[j].width) & (row >= 0) & (row < wcams[j].height)
            dj = np.full(len(sel), np.nan)
            dj[inb] = depths[j][row[inb], col[inb]]
            with np.errstate(invalid="ignore"):
                agree.append(np.abs(dj - z) <= settings.consistency * np.abs(z))
            views.append(j)
        agree = np.stack(agree, 1)
        good = agree[:, 1:].sum(1) >= settings.min_consistent
        idx = np.flatnonzero(good)
        if len(idx) > max_points:
            idx = np.sort(rng.choice(idx, max_points, replace=False))
        kept_views[cams[i].stem] = int(len(idx))
        base = sum(len(p) for p in pts)
        pts.append(X[idx])
        for col_k, v in enumerate(views):
            a = np.flatnonzero(agree[idx, col_k])
            obs_view.append(np.full(len(a), v, np.int64))
            obs_point.append(base + a)
    info = {"views": len(cams), "points": int(sum(len(p) for p in pts)), "per_view_median":
            float(np.median(list(kept_views.values()))) if kept_views else 0.0,
            "seconds": time.perf_counter() - t0}
    if not pts or info["points"] == 0:
        return None, {**info, "reason": "no depth held in any view (no texture the views agree on)"}
    seen = SeenPoints(np.stack([c.center for c in cams]), np.concatenate(pts), np.concatenate(obs_view),
                      np.concatenate(obs_point))
    return seen, info


__all__ = ["SweepSettings", "dense_seen_points", "hull_depths", "neighbours", "sweep_view"]
