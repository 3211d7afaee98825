"""The visual hull as a distance field: the part of space the silhouette cones hold.

Used by the init_mesh stage (the initial mesh is the field's zero level set) and by the poses
stage (a coarse hull gives the object's extent for the object frame).

:func:`silhouette_fields` evaluates, on a :class:`Grid` of voxel centers, for every view the
signed 2-D distance of a voxel's projection to the mask's outline (positive inside, from
``cv2.distanceTransform``, looked up bilinearly), converted to world units at the voxel's depth
(``d_px * z / f``: the distance to the silhouette cone at that depth). A view sees a voxel when
the voxel projects into its frame, in front of it; the others abstain.

- The strict hull: the minimum over the views that see the voxel (the intersection of the
  cones). One view's wrong mask carves its error through the whole object: a hole in a mask is
  a tunnel, a part cut off one mask is missing.
- The hull by vote (``outside_fraction`` f > 0): a voxel is outside only when more than the
  fraction f of the views that see it say so (:func:`votes_needed`: k = 1 + floor(f * seen));
  the field is the k-th smallest of the views' distances, whose zero level set is where the
  k-th view's cone boundary passes.

Unlike binary carving of voxel centers, the zero level sets lie between voxels, so a surface
extracted from them is placed to sub-voxel precision.

Public API (stable; the masks stage's segmentation uses it too): :class:`Grid`,
:class:`HullFields`, :func:`silhouette_fields`, :func:`silhouette_field`,
:func:`votes_needed`, :func:`bilinear`, :class:`HullError`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from recon.io.cameras import CameraSet


class HullError(ValueError):
    """Masks and cameras that give no visual hull; the message says which."""


@dataclass(frozen=True)
class Grid:
    """Voxel centers ``origin + step * (i, j, k)`` for i, j, k in [0, resolution)."""

    origin: np.ndarray  # (3,) the center of voxel (0, 0, 0)
    step: float
    resolution: int

    @staticmethod
    def cube(center, half_size: float, resolution: int) -> "Grid":
        step = 2.0 * half_size / resolution
        return Grid(np.asarray(center, float) - half_size + 0.5 * step, step, resolution)

    def points(self) -> np.ndarray:
        """(R^3, 3) voxel centers in C order (i slowest)."""
        a = np.arange(self.resolution) * self.step
        g = np.stack(np.meshgrid(a, a, a, indexing="ij"), axis=-1).reshape(-1, 3)
        return g + self.origin


def _signed_distance_px(mask: np.ndarray) -> np.ndarray:
    """(H, W) float32 signed distance to the mask outline in pixels, positive inside.

    The outline sits between pixels: the values are +-0.5 on the two sides of it.
    """
    import cv2

    m = mask.astype(np.uint8)
    inside = cv2.distanceTransform(m, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    outside = cv2.distanceTransform(1 - m, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return np.where(m > 0, inside - 0.5, 0.5 - outside).astype(np.float32)


def bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear lookup of an (H, W) float map sampled at pixel centers, at continuous pixel
    coordinates ``x`` (column) and ``y`` (row) (pixel (i, j) covers [j, j+1] x [i, i+1]);
    clamped at the border. ``cv2.remap`` does the work (its maps are limited to 32767 rows, so
    the query points are laid out 1024 to a row); positions are resolved to 1/32 pixel."""
    import cv2

    n = len(x)
    width = 1024
    rows = max(1, -(-n // width))
    mx = np.zeros(rows * width, np.float32)
    my = np.zeros(rows * width, np.float32)
    mx[:n] = np.asarray(x, np.float32) - 0.5  # cv2 addresses pixel centers by integers
    my[:n] = np.asarray(y, np.float32) - 0.5
    out = cv2.remap(np.ascontiguousarray(image, np.float32), mx.reshape(rows, width), my.reshape(rows, width),
                    cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(-1)[:n]


def votes_needed(seen: np.ndarray, outside_fraction: float) -> np.ndarray:
    """How many "outside" votes carve a voxel seen by ``seen`` views: ``1 + floor(f * seen)``.

    A voxel is carved when more than the fraction ``f`` of the views that see it put it outside
    their mask. ``f = 0`` is the strict visual hull (one view carves); with ``f = 0.1`` one
    wrong view cannot carve a voxel that 10 or more views see, two cannot below 20, and so on,
    while with fewer than 10 views the hull stays strict (there is no majority to outvote an
    error with).
    """
    return 1 + np.floor(float(outside_fraction) * np.asarray(seen, np.float64) + 1e-9).astype(np.int64)


@dataclass(frozen=True)
class HullFields:
    """The visual hull's distance fields on a grid (each (R, R, R) float64, world units,
    positive inside) and how many views see each voxel (int16)."""

    voted: np.ndarray  # the k-th smallest view distance, k the votes needed (the vote's hull)
    strict: np.ndarray  # the smallest (the intersection of all cones, the strict hull)
    seen: np.ndarray


def silhouette_field(cams: CameraSet, masks: dict[str, np.ndarray], grid: Grid, min_views: int = 2,
                     margin_px: float = 0.5, outside_fraction: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Visual-hull distance field on ``grid``, by vote over the views: ``(voted, seen)`` of
    :func:`silhouette_fields` (see there)."""
    h = silhouette_fields(cams, masks, grid, min_views, margin_px, outside_fraction)
    return h.voted, h.seen


def silhouette_fields(cams: CameraSet, masks: dict[str, np.ndarray], grid: Grid, min_views: int = 2,
                      margin_px: float = 0.5, outside_fraction: float = 0.0) -> HullFields:
    """Visual-hull distance fields on ``grid``, by vote over the views and strict.

    Parameters
    ----------
    cams : cameras (pinhole, OpenCV axes); views without a mask are skipped.
    masks : stem -> (H, W) bool, the size of the camera's image.
    grid : the voxel centers.
    min_views : voxels seen by fewer views count as outside.
    margin_px : the silhouettes are grown by this many pixels.
    outside_fraction : the vote (:func:`votes_needed`): a voxel is outside when more than this
        fraction of the views that see it say so. A view sees a voxel when the voxel projects
        into its frame, in front of it; the others abstain, so an object cut by the frame edge
        is not carved by the views that miss part of it. 0: the strict hull (every view carves).

    Returns
    -------
    :class:`HullFields` with
    voted : (R, R, R) float64
        Approximate distance to the hull surface in world units, positive inside: per voxel the
        k-th smallest of the views' signed distances to their silhouette cones, k the votes
        needed (k = 1: the minimum, the intersection of the cones). Its zero level set is where
        the k-th view's cone boundary passes, so it is placed to sub-voxel precision too.
    strict : (R, R, R) float64
        The same with k = 1 (equal to ``voted`` when ``outside_fraction`` is 0).
    seen : (R, R, R) int16
        How many views see each voxel.

    Raises :class:`HullError` for a mask whose size is not its camera's and for fewer than 2
    views with a mask.
    """
    if not 0.0 <= outside_fraction < 0.5:
        raise ValueError(f"outside_fraction must be in [0, 0.5), got {outside_fraction}")
    # computed in voxel units (index space; distances in voxels): the same float32 arithmetic at
    # every scale of the capture, which keeps the initial mesh's connectivity scale-invariant
    # (tests/test_extremes.py); the fields are returned in world units (float64: step x voxels)
    r0 = np.arange(grid.resolution, dtype=np.float32)
    ii, jj, kk = np.meshgrid(r0, r0, r0, indexing="ij")
    pts = np.stack([ii.ravel(), jj.ravel(), kk.ravel()], 1)
    step = float(grid.step)
    n_views = sum(1 for cam in cams if cam.stem in masks)
    kmax = int(votes_needed(n_views, outside_fraction))
    # the kmax smallest signed distances per voxel, ascending (row 0 = the minimum)
    low = np.full((kmax, len(pts)), np.inf, np.float32)
    seen = np.zeros(len(pts), np.int16)
    used = 0
    for cam in cams:
        mask = masks.get(cam.stem)
        if mask is None:
            continue
        if mask.shape != (cam.height, cam.width):
            raise HullError(f"mask of {cam.stem} is {mask.shape[::-1]} but its camera is {cam.width}x{cam.height}")
        used += 1
        sd = _signed_distance_px(mask) + np.float32(margin_px)
        alive = np.flatnonzero(low[-1] > -4.0)  # outside at any vote: stays outside
        Pw = cam.K @ cam.world_to_camera[:3, :]  # (3, 4) projection of world points
        # of voxel indices (world = origin + step * index), divided by step (homogeneous)
        P = np.concatenate([Pw[:, :3], ((Pw[:, :3] @ grid.origin + Pw[:, 3]) / step)[:, None]], 1).astype(np.float32)
        h = pts[alive] @ P[:, :3].T + P[:, 3]
        z = h[:, 2]
        front = z > 1e-6
        zs = np.where(front, z, 1.0)
        x, y = h[:, 0] / zs, h[:, 1] / zs
        inimg = front & (x >= 0) & (x < cam.width) & (y >= 0) & (y < cam.height)
        sel = np.flatnonzero(inimg)
        f = 0.5 * (cam.K[0, 0] + cam.K[1, 1])
        d = bilinear(sd, x[sel], y[sel]) * (z[sel] / np.float32(f))  # voxels
        idx = alive[sel]
        for r in range(kmax):  # insert d into the sorted rows
            cur = low[r, idx]
            low[r, idx] = np.minimum(cur, d)
            d = np.maximum(cur, d)
        seen[idx] += 1
    if used < 2:
        raise HullError(f"a visual hull needs masks for at least 2 views, found {used}")
    k = np.minimum(votes_needed(seen, outside_fraction), kmax)
    r = grid.resolution

    def finish(field):
        field[seen < min_views] = -np.inf
        field = np.where(np.isfinite(field), field, np.where(field > 0, 4.0, -4.0))
        return field.reshape(r, r, r).astype(np.float64) * step

    voted = finish(np.take_along_axis(low, (k - 1)[None, :], axis=0)[0])
    strict = finish(low[0].copy()) if kmax > 1 else voted
    return HullFields(voted, strict, seen.reshape(r, r, r))
