"""Cameras and rays of the differentiable renderer (:mod:`recon.render.collocated`).

The per-view camera table (Kinv, R_w2c, t_w2c, center: 24 values per view), the primary rays
over the pixel footprints, rays through image points (the boundary term's side rays), the
Mitsuba ray cast and the flash's position beside each camera. All functions read the camera
values from the table, so gradients reach the cameras where the table is differentiable.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from recon.io.cameras import Camera
from recon.render.arrays import aligned
from recon.render.settings import RenderError

__all__ = ["CAM_STRIDE", "camera_table", "view_table", "given_view_table", "camera_values",
           "primary_rays", "rays_through", "trace", "flash_positions"]

CAM_STRIDE = 24  # floats per view in the camera table: Kinv(9) R_w2c(9) t_w2c(3) center(3)


# ---- The camera table ----
def camera_table(cameras: Sequence[Camera]) -> np.ndarray:
    """(B, 24) float64 per-view Kinv (row-major), R_w2c, t_w2c, camera center: the values the
    renderer's rays and projections read (see ``camera_table`` of
    :meth:`recon.render.collocated.CollocatedRenderer.render_batch`)."""
    rows = []
    for cam in cameras:
        if not isinstance(cam, Camera):
            raise RenderError(f"cameras: expected recon.io.cameras.Camera objects, got {type(cam)}")
        R = cam.world_to_camera[:3, :3]
        t = cam.world_to_camera[:3, 3]
        rows.append(np.concatenate([np.linalg.inv(cam.K).ravel(), R.ravel(), t, cam.center]))
    return np.stack(rows)


def view_table(dr, mi, cameras: Sequence[Camera]):
    """Per-view Kinv, R_w2c, t_w2c, center (24 floats each): a flat mi.Float for several
    views, a list of 24 opaque scalars for one."""
    rows = camera_table(cameras)
    if len(rows) == 1:
        return [dr.opaque(mi.Float, float(x)) for x in rows[0]]
    return mi.Float(aligned(rows, np.float32))


def given_view_table(dr, mi, table, n_views: int):
    """A caller's (possibly differentiable) flat B x 24 table; one view: 24 broadcast scalars
    gathered from it (AD sums their lanes back into the table)."""
    if not isinstance(table, mi.Float) or dr.width(table) != n_views * CAM_STRIDE:
        raise RenderError(f"camera_table: expected a flat mi.Float of {n_views} x {CAM_STRIDE} values")
    if n_views == 1:
        return [dr.gather(mi.Float, table, dr.opaque(mi.UInt32, k)) for k in range(CAM_STRIDE)]
    return table


def camera_values(dr, mi, cam_table, view):
    """The 24 per-view camera values for each lane: gathers, or broadcast scalars for a
    single view (a list of opaque scalars)."""
    if isinstance(cam_table, list):
        return cam_table
    base = view * CAM_STRIDE
    return [dr.gather(mi.Float, cam_table, base + k) for k in range(CAM_STRIDE)]


# ---- Rays ----
def primary_rays(dr, mi, cam_table, n_views: int, width: int, height: int, spp: int, seed,
                 stratified: bool):
    """Rays of all samples, lane = ((view * h + row) * w + col) * spp + s."""
    n = n_views * width * height * spp
    idx = dr.arange(mi.UInt32, n)
    # Divisors are literals (LLVM turns the divisions into multiplications); the kernels
    # are compiled again only when the image size or spp changes.
    pix = idx // spp
    view = pix // (width * height)
    p = pix - view * (width * height)
    row = p // width
    col = p - row * width
    ux = mi.sample_tea_float32(idx, seed, 4)
    uy = mi.sample_tea_float32(idx, seed + 0x9E3779B9, 4)
    k = int(np.sqrt(spp) + 0.5)
    if stratified and k * k == spp and spp > 1:
        # Jittered k x k grid over the pixel: each sample is still uniform over the pixel.
        s = idx - pix * spp
        sy = s // k
        sx = s - sy * k
        ux = (mi.Float(sx) + ux) * (1.0 / k)
        uy = (mi.Float(sy) + uy) * (1.0 / k)
    x = mi.Float(col) + ux
    yv = mi.Float(row) + uy
    o, d = rays_through(dr, mi, cam_table, view, x, yv)
    return o, d, view


def rays_through(dr, mi, cam_table, view, x, y):
    """World rays (origin, unit direction) through image points (x, y) of ``view``."""
    g = camera_values(dr, mi, cam_table, view)
    Kinv = g[0:9]
    R = g[9:18]
    c = mi.Point3f(g[21], g[22], g[23])
    dc = mi.Vector3f(
        Kinv[0] * x + Kinv[1] * y + Kinv[2],
        Kinv[3] * x + Kinv[4] * y + Kinv[5],
        Kinv[6] * x + Kinv[7] * y + Kinv[8],
    )
    # camera -> world: R^T dc
    dw = mi.Vector3f(
        R[0] * dc.x + R[3] * dc.y + R[6] * dc.z,
        R[1] * dc.x + R[4] * dc.y + R[7] * dc.z,
        R[2] * dc.x + R[5] * dc.y + R[8] * dc.z,
    )
    return c, dr.normalize(dw)


def trace(mi, scene, o, d, coherent: bool = True):
    """Preliminary intersection of rays (o, d); returns (prim index, hit mask, distance)."""
    ray = mi.Ray3f(o, d)
    pi = scene.ray_intersect_preliminary(ray, coherent=coherent)
    return pi.prim_index, pi.is_valid(), pi.t


# ---- The flash ----
def flash_positions(dr, mi, cam_table, view, offset):
    """Per-lane flash positions c + R^T t of the call's offset t (camera coordinates; 3 opaque
    Floats), or None when the light is at the camera centre (``offset`` None)."""
    if offset is None:
        return None
    g = camera_values(dr, mi, cam_table, view)
    R, t = g[9:18], offset
    return mi.Point3f(g[21] + R[0] * t[0] + R[3] * t[1] + R[6] * t[2],
                      g[22] + R[1] * t[0] + R[4] * t[1] + R[7] * t[2],
                      g[23] + R[2] * t[0] + R[5] * t[1] + R[8] * t[2])
