"""A small synthetic flash capture made with the project's own renderer (test helper).

The ground truth is a smooth blob (a sphere with low-frequency radial bumps) with a diffuse
albedo that varies over the surface, constant specular albedo and roughness. Photos are
rendered at many samples per pixel; masks come from ray casting the true mesh (pixel coverage
from 4 x 4 sub-samples).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from recon.io.cameras import Camera, CameraSet, intrinsics, look_at, save_cameras
from recon.io.images import write_exr, write_mask
from recon.io.mesh import Mesh, write_obj


def icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    import open3d as o3d

    m = o3d.geometry.TriangleMesh.create_icosahedron(1.0)
    m = m.subdivide_loop(subdivisions)
    v = np.asarray(m.vertices, dtype=np.float64)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return v, np.asarray(m.triangles, dtype=np.int64)


def blob_radius(d: np.ndarray, amplitude: float = 0.12) -> np.ndarray:
    """Radius of the blob along unit directions ``d (n, 3)``."""
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    return 0.5 * (1.0 + amplitude * (np.sin(3 * x + 1.0) * np.cos(2 * y) + 0.6 * np.sin(4 * z + 0.5 * x)))


def blob_mesh(subdivisions: int = 4, amplitude: float = 0.12) -> Mesh:
    d, f = icosphere(subdivisions)
    return Mesh(d * blob_radius(d, amplitude)[:, None], f)


def diffuse_of(points: np.ndarray) -> np.ndarray:
    """A smooth RGB albedo in [0.1, 0.8] over 3D points (n, 3)."""
    p = np.asarray(points)
    r = 0.45 + 0.3 * np.sin(4 * p[:, 0] + 0.5)
    g = 0.45 + 0.3 * np.sin(5 * p[:, 1] + 1.0)
    b = 0.35 + 0.2 * np.cos(4 * p[:, 2])
    return np.clip(np.stack([r, g, b], axis=1), 0.05, 0.95)


def ring_cameras(n: int, size: int, distance: float = 2.6, fov: float = 40.0) -> list[Camera]:
    """``n`` cameras on a spiral around the origin, looking at it."""
    cams = []
    for i in range(n):
        t = (i + 0.5) / n
        elev = np.radians(-50 + 100 * t)
        azim = 2.4 * np.pi * i * 0.618034 * 2
        eye = distance * np.array([np.cos(elev) * np.cos(azim), np.cos(elev) * np.sin(azim), np.sin(elev)])
        cams.append(Camera(f"images/{i:04d}.exr", size, size, intrinsics(size, size, fov), look_at(eye, [0, 0, 0])))
    return cams


def coverage_masks(mesh: Mesh, cams: list[Camera], sub: int = 4) -> list[np.ndarray]:
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.v_pos.astype(np.float32)), o3d.core.Tensor(mesh.t_pos_idx.astype(np.uint32)))
    out = []
    for c in cams:
        o = (np.arange(sub) + 0.5) / sub
        jj, ii = np.meshgrid(np.arange(c.width * sub), np.arange(c.height * sub))
        x = (jj + 0.5) / sub
        y = (ii + 0.5) / sub
        pix = np.stack([x.ravel(), y.ravel(), np.ones(x.size)], 1)
        dirs_cam = pix @ np.linalg.inv(c.K).T
        R = c.world_to_camera[:3, :3]
        dirs = dirs_cam @ R
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        rays = np.concatenate([np.broadcast_to(c.center, dirs.shape), dirs], 1).astype(np.float32)
        hit = np.isfinite(scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy())
        cov = hit.reshape(c.height, sub, c.width, sub).mean(axis=(1, 3))
        out.append(cov)
        del o
    return out


def make_capture(root: Path, n_views: int = 12, size: int = 64, spp: int = 64, texture_size: int = 128,
                 subdivisions: int = 4, init: Mesh | None = None, specular: float = 0.3,
                 roughness: float = 0.35, seed: int = 7, state_light: bool = False) -> dict:
    """Write a capture (images/*.exr, masks/*.png, cameras.json, gt mesh + maps, init.obj) under ``root``.

    The photos are lit by I_e = 1; ``cameras.json`` states it only with ``state_light`` (else the
    optimize stage estimates the flash's scale, as for a user's capture).

    Returns the paths and the ground truth.
    """
    import torch

    from recon.optimize.remesh import rasterize_atlas, fill_gutters, unwrap
    from recon.render import CollocatedRenderer, RenderSettings

    root = Path(root)
    gt = blob_mesh(subdivisions)
    gt = unwrap(gt.v_pos, gt.t_pos_idx, texture_size)
    face, _, pts = rasterize_atlas(gt, texture_size)
    cov = face >= 0
    diffuse = np.zeros((texture_size, texture_size, 3))
    diffuse[cov] = diffuse_of(pts[cov])
    diffuse = fill_gutters(diffuse, cov).astype(np.float32)
    spec = np.full((texture_size, texture_size, 1), specular, np.float32)
    rough = np.full((texture_size, texture_size, 1), roughness, np.float32)
    cams = ring_cameras(n_views, size)
    r = CollocatedRenderer(gt.t_pos_idx, gt.v_tex, gt.t_tex_idx, RenderSettings(spp=spp, boundary="none"))
    with torch.no_grad():
        imgs = r.render_torch(torch.tensor(gt.v_pos, dtype=torch.float32), torch.from_numpy(diffuse),
                              torch.from_numpy(spec), torch.from_numpy(rough), cams, 1.0, seed=seed).numpy()
    masks = coverage_masks(gt, cams)
    images, mask_paths = [], []
    for c, img, m in zip(cams, imgs, masks, strict=True):
        p = root / c.image
        write_exr(p, img)
        mp = root / "masks" / f"{Path(c.image).stem}.png"
        write_mask(mp, m > 0.5)
        images.append(p)
        mask_paths.append(mp)
    save_cameras(root / "cameras.json", CameraSet(tuple(cams), 1.0, light_known=state_light))
    write_obj(root / "gt.obj", gt)
    if init is None:
        d, f = icosphere(3)
        init = Mesh(d * 0.56, f)
    write_obj(root / "init.obj", init)
    (root / "gt.json").write_text(json.dumps({"specular": specular, "roughness": roughness}))
    return {
        "images": images, "masks": mask_paths, "cameras": root / "cameras.json", "init": root / "init.obj",
        "gt": gt, "gt_maps": {"diffuse": diffuse, "specular": spec, "roughness": rough}, "cameras_list": cams,
    }
