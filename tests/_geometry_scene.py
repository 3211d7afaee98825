"""Test scenes for the geometry stages (masks, poses, init_mesh, uv).

Analytic meshes (an icosphere, a bumpy blob), exact silhouettes by ray casting, and recon.synth
captures rendered once per test session and shared between modules.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from recon import sections
from recon.io.cameras import Camera
from recon.io.mesh import Mesh


def icosphere(subdivisions: int) -> Mesh:
    """Unit icosphere (outward winding)."""
    t = (1 + 5**0.5) / 2
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
                  [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], float)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
                  [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
                  [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(subdivisions):
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        uniq, inv = np.unique(edges, axis=0, return_inverse=True)
        mid = v[uniq].mean(1)
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        m = inv.reshape(3, -1).T + len(v)  # midpoints of edges (01, 12, 20)
        v = np.concatenate([v, mid])
        a, b, c = f.T
        ab, bc, ca = m.T
        f = np.concatenate([np.stack([a, ab, ca], 1), np.stack([b, bc, ab], 1),
                            np.stack([c, ca, bc], 1), np.stack([ab, bc, ca], 1)])
    return Mesh(v, f)


def blob_mesh(subdivisions: int = 6, seed: int = 0) -> Mesh:
    """A star-shaped blob of radius ~0.6 around the origin."""
    rng = np.random.default_rng(seed)
    m = icosphere(subdivisions)
    d = m.v_pos
    r = 0.6 * np.ones(len(d))
    for _ in range(5):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        r += 0.12 * np.exp(6.0 * (d @ axis - 1.0))
    r *= np.array([1.0, 0.85, 0.75]) @ np.abs(d.T) ** 2 + 0.2  # squash a little
    return Mesh(d * r[:, None], m.t_pos_idx)


def silhouette(mesh: Mesh, cam: Camera) -> np.ndarray:
    """(H, W) bool: the pixel center's ray hits ``mesh`` (open3d ray casting)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.v_pos.astype(np.float32)),
                        o3d.core.Tensor(mesh.t_pos_idx.astype(np.uint32)))
    j, i = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    pix = np.stack([j, i, np.ones_like(j)], -1).reshape(-1, 3)
    d_cam = pix @ np.linalg.inv(cam.K).T
    c2w = cam.camera_to_world
    d_world = d_cam @ c2w[:3, :3].T
    rays = np.concatenate([np.broadcast_to(c2w[:3, 3], d_world.shape), d_world], 1).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    return np.isfinite(hit).reshape(cam.height, cam.width)


# ---- recon.synth captures shared by the geometry tests (rendered once per session) ----
SYNTH_TEST = dict(object="blob", n_views=40, width=256, height=256, format="exr", spp=16, seed=0,
                  write_cameras=False, write_gt_linear=False, mesh_level=5, texture_size=512)


def ring_of_views():
    """16 cameras of 160 x 120 px around a torus standing upright (its hole seen from the sides),
    and its true silhouettes: ``(torus mesh, CameraSet, [mask])``."""
    from recon.io.cameras import CameraSet, intrinsics, look_at
    from recon.synth.shapes import torus_grid

    torus, _, _ = torus_grid(64, 24, 0.6, 0.22)
    v = torus.v_pos @ np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], float).T  # the hole's axis along y
    torus = type(torus)(v, torus.t_pos_idx)
    K = intrinsics(160, 120, 40.0)
    frames = []
    for k in range(16):
        az = 2 * np.pi * k / 16
        el = np.radians(10 + 30 * (k % 3))
        eye = 4.0 * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        frames.append(Camera(f"images/{k:04d}.exr", 160, 120, K.copy(), look_at(eye, [0, 0, 0])))
    cams = CameraSet(tuple(frames), 1.0)
    return torus, cams, [silhouette(torus, c) for c in cams]


def synth_capture(base: Path, **overrides) -> Path:
    """A recon.synth capture for these settings, rendered into ``base`` unless already there.

    Pass pytest's ``tmp_path_factory.getbasetemp()`` as ``base`` to share one render between
    test modules of a session.
    """
    import hashlib

    from recon.synth.capture import SynthSettings, make_capture

    from _shared import made_once

    settings = sections.replace(SynthSettings(), **{**SYNTH_TEST, **overrides})
    name = f"synth-{hashlib.sha1(repr(settings).encode()).hexdigest()[:12]}"
    return made_once(base, name, lambda out: make_capture(out, settings))


def linearize_and_mask(capture: Path, results: Path) -> tuple[Path, Path]:
    """Run the linearize and masks stages of ``capture`` into ``results``; return their folders."""
    from recon.linearize import linearize_capture
    from recon.masks import run_masks

    linear = results / "linear"
    if not (linear / "linear.json").is_file():
        linearize_capture(capture, linear)
    masks = results / "masks"
    if not (masks / "masks.json").is_file():
        run_masks(linear, masks)
    return linear, masks
