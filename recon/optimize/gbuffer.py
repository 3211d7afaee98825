"""The G-buffer renderer of the material and imaging fits: surface samples of fixed views of a
fixed mesh, shaded in torch with the collocated model (:func:`radiance`) or the general model for
a flash beside the lens (:func:`radiance_offset`) of DESIGN section 3 (two of the model's
implementations listed in :mod:`recon.brdf`).

With the mesh fixed, visibility never changes, so each view is traced once (open3d) and the fits
only re-shade the stored samples: a fit of many candidate material models costs torch
arithmetic, not ray tracing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from recon.io.cameras import Camera
from recon.io.mesh import Mesh


@dataclass
class GBuffer:
    """Surface samples of a set of views of a fixed mesh.

    pixel : (N,) int64 index into the flattened (views, h, w) images
    uv : (N, 2) float32 texture coordinates (OBJ convention, v up)
    mu : (N,) float32 ``max(0, n . w)``, shading normal against the direction to the camera
    inv_d2 : (N,) float32 ``1 / |y - o|^2``
    spp : samples per pixel (misses contribute zero)
    shape : (views, h, w)
    position, normal : (N, 3) float32 surface point and shading normal (world), for shading with
        a light away from the camera (:func:`radiance_offset`)
    """

    pixel: torch.Tensor
    uv: torch.Tensor
    mu: torch.Tensor
    inv_d2: torch.Tensor
    spp: int
    shape: tuple
    position: torch.Tensor | None = None
    normal: torch.Tensor | None = None

    @property
    def grid(self) -> torch.Tensor:
        """(1, 1, N, 2) ``grid_sample`` coordinates of the samples (DESIGN texel convention)."""
        return torch.stack([2 * self.uv[:, 0] - 1, 1 - 2 * self.uv[:, 1]], -1)[None, None]


def build_gbuffer(mesh: Mesh, cameras: list[Camera] | tuple[Camera, ...], spp: int = 4, seed: int = 0) -> GBuffer:
    """Trace ``spp`` stratified samples per pixel of every camera against ``mesh`` (open3d).

    Shading normals are the area-weighted vertex normals interpolated barycentrically
    (DESIGN section 3), UVs interpolated barycentrically.
    """
    import open3d as o3d

    if mesh.v_tex is None:
        raise ValueError("build_gbuffer needs a mesh with UVs")
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.v_pos.astype(np.float32)),
                        o3d.core.Tensor(mesh.t_pos_idx.astype(np.uint32)))
    vn = mesh.vertex_normals()
    k = max(int(round(np.sqrt(spp))), 1)
    spp = k * k
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x6B0F]))
    W, H = cameras[0].width, cameras[0].height
    jj, ii = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    pix_all, uv_all, mu_all, d2_all, pos_all, nrm_all = [], [], [], [], [], []
    for view, cam in enumerate(cameras):
        if (cam.width, cam.height) != (W, H):
            raise ValueError("build_gbuffer: all cameras must have the same image size")
        R = cam.world_to_camera[:3, :3]
        o = cam.center
        Kinv = np.linalg.inv(cam.K)
        for s in range(spp):
            sx, sy = s % k, s // k
            jx = (sx + rng.random(jj.shape)) / k
            jy = (sy + rng.random(jj.shape)) / k
            pix = np.stack([(jj + jx).ravel(), (ii + jy).ravel(), np.ones(jj.size)], 1)
            d = (pix @ Kinv.T) @ R  # camera -> world directions (rows)
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            rays = np.concatenate([np.broadcast_to(o, d.shape), d], 1).astype(np.float32)
            hit = scene.cast_rays(o3d.core.Tensor(rays))
            t = hit["t_hit"].numpy()
            ok = np.isfinite(t)
            if not ok.any():
                continue
            prim = hit["primitive_ids"].numpy()[ok].astype(np.int64)
            bu, bv = hit["primitive_uvs"].numpy()[ok].T.astype(np.float64)
            b = np.stack([1 - bu - bv, bu, bv], 1)
            f = mesh.t_pos_idx[prim]
            n = np.einsum("nk,nkd->nd", b, vn[f])
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-20)
            uv = np.einsum("nk,nkd->nd", b, mesh.v_tex[mesh.t_tex_idx[prim]])
            mu = np.maximum(-(n * d[ok]).sum(1), 0.0)
            tt = t[ok].astype(np.float64)
            pix_all.append(view * H * W + np.flatnonzero(ok))
            uv_all.append(uv.astype(np.float32))
            mu_all.append(mu.astype(np.float32))
            d2_all.append((1.0 / np.maximum(tt * tt, 1e-30)).astype(np.float32))
            pos_all.append((o + tt[:, None] * d[ok]).astype(np.float32))
            nrm_all.append(n.astype(np.float32))
    def cat(xs, dt, shp):
        if xs:
            return torch.from_numpy(np.concatenate(xs).astype(dt))
        return torch.zeros(shp, dtype=torch.float32 if dt != np.int64 else torch.int64)

    return GBuffer(cat(pix_all, np.int64, (0,)), cat(uv_all, np.float32, (0, 2)), cat(mu_all, np.float32, (0,)),
                   cat(d2_all, np.float32, (0,)), spp, (len(cameras), H, W),
                   cat(pos_all, np.float32, (0, 3)), cat(nrm_all, np.float32, (0, 3)))


def lookup(tex: torch.Tensor, grid: torch.Tensor) -> torch.Tensor:
    """Bilinear lookup, clamped to the edge texels: (T, T, C) map at (1, 1, N, 2) -> (N, C)."""
    if tex.shape[0] == 1 and tex.shape[1] == 1:  # uniform
        return tex.reshape(1, -1).expand(grid.shape[2], -1)
    out = torch.nn.functional.grid_sample(tex.permute(2, 0, 1)[None], grid, mode="bilinear",
                                          padding_mode="border", align_corners=False)
    return out[0, :, 0].T


def radiance(gb: GBuffer, grid: torch.Tensor, diffuse, specular, roughness, light: float, r_min: float):
    """(N, 3) radiance of the samples (DESIGN section 3, collocated), see :func:`shade`."""
    f = lookup(diffuse, grid) * (1.0 / np.pi)
    if specular is not None:
        alpha = lookup(roughness, grid).clamp(min=r_min, max=1.0) ** 2
        mu = gb.mu[:, None]
        a2 = alpha * alpha
        mu2 = mu * mu
        # mu^2 (a2 - 1) + 1 written as (1 - mu)(1 + mu) + mu^2 a2: no cancellation near mu = 1
        # at r_min (float32: 1 - 1 + 1.6e-7 would lose the peak of D by ~20 %)
        dd = (1 - mu) * (1 + mu) + mu2 * a2
        g = mu + torch.sqrt(a2 + (1 - a2) * mu2)  # 2 mu / G1(mu)
        f = f + lookup(specular, grid) * (a2 / (np.pi * (dd * g) ** 2))
    return f * (light * gb.mu * gb.inv_d2)[:, None]


def radiance_offset(gb: GBuffer, grid: torch.Tensor, view: torch.Tensor, light_pos: torch.Tensor,
                    centers: torch.Tensor, diffuse, specular, roughness, light: float, r_min: float):
    """(N, 3) radiance of the samples lit by point lights at ``light_pos[view]`` (V, 3), seen from
    ``centers[view]``: the general model of DESIGN section 3 (front side only), for a flash beside
    the lens (:mod:`recon.optimize.formation`). Needs the G-buffer's positions and normals."""
    y, n = gb.position.to(light_pos.dtype), gb.normal.to(light_pos.dtype)
    lv = light_pos[view] - y
    d2 = (lv * lv).sum(1).clamp(min=1e-20)
    l = lv * torch.rsqrt(d2)[:, None]  # noqa: E741
    v = centers[view].to(y.dtype) - y
    v = v / v.norm(dim=1, keepdim=True).clamp(min=1e-20)
    nl = (n * l).sum(1).clamp(min=0.0)
    nv = (n * v).sum(1).clamp(min=0.0)
    f = lookup(diffuse, grid) * (1.0 / np.pi)
    if specular is not None:
        h = l + v
        h = h / h.norm(dim=1, keepdim=True).clamp(min=1e-20)
        nh = (n * h).sum(1).clamp(min=0.0, max=1.0)[:, None]
        vh = (v * h).sum(1).clamp(min=0.0, max=1.0)[:, None]
        alpha = lookup(roughness, grid).clamp(min=r_min, max=1.0) ** 2
        a2 = alpha * alpha
        dd = (1 - nh) * (1 + nh) + nh * nh * a2
        D = a2 / (np.pi * dd * dd)
        a_s = lookup(specular, grid)
        F = a_s + (1 - a_s) * (1 - vh) ** 5
        # G1(c) / (2c) = 1 / (c + sqrt(a2 + (1 - a2) c^2)): finite as the cosines go to 0
        gl = 1.0 / (nl[:, None] + torch.sqrt(a2 + (1 - a2) * nl[:, None] ** 2))
        gv = 1.0 / (nv[:, None] + torch.sqrt(a2 + (1 - a2) * nv[:, None] ** 2))
        f = f + D * F * gl * gv * (nv[:, None] > 0)
    return f * (light * nl / d2)[:, None] * (nv > 0)[:, None]


def shade(gb: GBuffer, diffuse: torch.Tensor, specular: torch.Tensor | None, roughness: torch.Tensor,
          light: float, r_min: float) -> torch.Tensor:
    """Images ``(views, h, w, 3)`` of the G-buffer's views (DESIGN section 3, collocated).

    ``diffuse`` (T, T, 3); ``specular`` (T, T, 1|3) or None (no specular lobe); ``roughness``
    (T, T, 1). A (1, 1, C) map is uniform. Each pixel is the mean of its ``spp`` samples.
    """
    rad = radiance(gb, gb.grid, diffuse, specular, roughness, light, r_min)
    V, H, W = gb.shape
    img = torch.zeros((V * H * W, 3), dtype=rad.dtype).index_add(0, gb.pixel, rad) / gb.spp
    return img.reshape(V, H, W, 3)
