"""Geometry of views over a support plane: plane-induced homographies, pixel rays, the flash's
shading of the plane, neighbouring views and the parallax they see."""

from __future__ import annotations

import numpy as np

from recon.io.cameras import Camera, CameraSet
from recon.support import SupportPlane

_HALF = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
"""Pixel coordinates of DESIGN (centers at j + 0.5) from OpenCV's (centers at integers)."""


def plane_homography(cam_i: Camera, cam_j: Camera, plane: SupportPlane) -> np.ndarray:
    """(3, 3) homography taking OpenCV pixel coordinates of view i (centers at integers) to
    those of view j for points on ``plane``: x_j ~ H x_i.

    With the plane n_c . X_c + d_c = 0 in camera i's coordinates and X_j = R X_c + t the
    relative motion, H = K_j (R - t n_c^T / d_c) K_i^-1.
    """
    Ri, ti = cam_i.world_to_camera[:3, :3], cam_i.world_to_camera[:3, 3]
    Rj, tj = cam_j.world_to_camera[:3, :3], cam_j.world_to_camera[:3, 3]
    n_c = Ri @ plane.normal
    d_c = plane.offset - n_c @ ti
    R = Rj @ Ri.T
    t = tj - R @ ti
    H = cam_j.K @ (R - np.outer(t, n_c) / d_c) @ np.linalg.inv(cam_i.K)
    return np.linalg.inv(_HALF) @ H @ _HALF


def pixel_rays(cam: Camera) -> np.ndarray:
    """(H, W, 3) world directions (not normalized) of the rays through the pixel centers."""
    j, i = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    pix = np.stack([j, i, np.ones_like(j)], -1)
    return pix @ (cam.camera_to_world[:3, :3] @ np.linalg.inv(cam.K)).T


def plane_points(cam: Camera, plane: SupportPlane) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel's ray meets the plane: ``P (H, W, 3)`` and ``hit (H, W)`` bool (in front)."""
    d = pixel_rays(cam)
    t = plane.ray_hit(cam.center, d)
    hit = np.isfinite(t) & (t > 0)
    return cam.center + np.where(hit, t, 0.0)[..., None] * d, hit


def flash_shading(center: np.ndarray, points: np.ndarray, plane: SupportPlane) -> np.ndarray:
    """``cos / r^2`` of the flash at ``center`` on plane points ``(..., 3)``: height / r^3."""
    r = np.linalg.norm(points - center, axis=-1)
    return plane.height(center) / np.maximum(r, 1e-12) ** 3


def neighbours(cams: CameraSet, count: int, min_angle: float, max_angle: float) -> list[list[int]]:
    """For each view the indices of its ``count`` nearest views by viewing direction, between
    ``min_angle`` and ``max_angle`` degrees apart."""
    z = np.stack([c.camera_to_world[:3, 2] for c in cams])
    ang = np.degrees(np.arccos(np.clip(z @ z.T, -1.0, 1.0)))
    out = []
    for i in range(len(z)):
        order = [j for j in np.argsort(ang[i], kind="stable")
                 if j != i and min_angle <= ang[i, j] <= max_angle]
        out.append(order[:count])
    return out


def parallax_band(cams: CameraSet, nbrs: list[list[int]], foot: np.ndarray, parallax_px: float) -> float:
    """Height above the plane below which a point shows less than ``parallax_px`` of parallax to
    a typical neighbour (the median over views of the second nearest): there the plane test
    cannot tell the object from the table. About ``parallax_px * depth / (f sin(angle))``."""
    z = np.stack([c.camera_to_world[:3, 2] for c in cams])
    heights = []
    for i, cam in enumerate(cams):
        if not nbrs[i]:
            continue
        angles = np.sort(np.arccos(np.clip(z[nbrs[i]] @ z[i], -1.0, 1.0)))
        angle = angles[min(1, len(angles) - 1)]
        depth = float(np.linalg.norm(cam.center - foot))
        f = 0.5 * (cam.K[0, 0] + cam.K[1, 1])
        heights.append(parallax_px * depth / (f * max(np.sin(angle), 1e-3)))
    return float(np.median(heights)) if heights else 0.0
