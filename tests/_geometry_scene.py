"""Small flash-lit test scenes for the geometry stages (masks, poses, init_mesh).

A textured blob (a sphere with a few low-frequency bumps, albedo made of colored 3D Gaussian
splats so that SIFT finds features) rendered by Mitsuba with a point light at each camera
center and a black background, written as linear EXRs in the layout the geometry stages read:
``<root>/linear/<stem>.exr``, ``<root>/gt/cameras.json``, ``<root>/gt/mesh.obj``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from recon.io.cameras import Camera, CameraSet, intrinsics, look_at, mitsuba_sensor_dict, save_cameras
from recon.io.images import write_exr
from recon.io.mesh import Mesh, write_obj


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


def splat_albedo(points: np.ndarray, seed: int = 0, n: int = 1500) -> np.ndarray:
    """(n, 3) albedo in [0.05, 0.9]: colored dots of many sizes (a feature-rich texture)."""
    rng = np.random.default_rng(seed + 1)
    centers = points[rng.choice(len(points), size=n, replace=False)]
    sigma = rng.uniform(0.01, 0.05, size=n)
    colors = rng.uniform(-0.5, 0.5, size=(n, 3))
    alb = np.full((len(points), 3), 0.4)
    for c, s, col in zip(centers, sigma, colors, strict=True):
        w = np.clip((s - np.linalg.norm(points - c, axis=1)) / (0.3 * s), 0.0, 1.0)  # a dot
        alb += w[:, None] * col
    return np.clip(alb, 0.05, 0.9)


def orbit_cameras(n_views: int, res: int, radius: float = 2.6, fov: float = 40.0, seed: int = 0) -> CameraSet:
    """Cameras on a spiral over the upper 3/4 of a sphere, looking at the origin (z up)."""
    rng = np.random.default_rng(seed + 2)
    frames = []
    for i in range(n_views):
        z = 0.85 - 1.25 * (i + 0.5) / n_views  # elevation from high to a bit below the equator
        a = i * 2.39996 + rng.uniform(-0.1, 0.1)  # golden angle
        rxy = np.sqrt(1 - z * z)
        eye = radius * np.array([rxy * np.cos(a), rxy * np.sin(a), z])
        frames.append(Camera(f"images/{i:04d}.exr", res, res, intrinsics(res, res, fov), look_at(eye, [0, 0, 0])))
    return CameraSet(tuple(frames), light_intensity=float(radius**2 * 1.5))


def render(mesh: Mesh, albedo: np.ndarray, cams: CameraSet, spp: int = 16) -> list[np.ndarray]:
    """Linear RGB ``(H, W, 3)`` per camera; point light at the camera center, black background."""
    from recon.mi import load_variant

    mi = load_variant("llvm_ad_rgb")
    mm = mi.Mesh("blob", len(mesh.v_pos), len(mesh.t_pos_idx), has_vertex_normals=False)
    params = mi.traverse(mm)
    params["vertex_positions"] = mi.Float(mesh.v_pos.astype(np.float32).ravel())
    params["faces"] = mi.UInt32(mesh.t_pos_idx.astype(np.uint32).ravel())
    params.update()
    mm.add_attribute("vertex_color", 3, mi.Float(albedo.astype(np.float32).ravel()))
    mm.set_bsdf(mi.load_dict({"type": "diffuse", "reflectance": {"type": "mesh_attribute", "name": "vertex_color"}}))
    images = []
    for cam in cams:
        scene = mi.load_dict({
            "type": "scene",
            "integrator": {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0},
            "sensor": mitsuba_sensor_dict(cam, spp=spp),
            "light": {"type": "point", "position": cam.center.tolist(),
                      "intensity": {"type": "spectrum", "value": cams.light_intensity}},
            "blob": mm,
        })
        images.append(np.asarray(mi.render(scene, seed=len(images)), dtype=np.float32)[:, :, :3])
    return images


def make_scene(root: Path, n_views: int = 40, res: int = 256, seed: int = 0, spp: int = 16) -> dict:
    """Render a blob capture into ``root`` (linear/, gt/); return its paths and objects."""
    root = Path(root)
    mesh = blob_mesh(seed=seed)
    albedo = splat_albedo(mesh.v_pos, seed=seed)
    cams = orbit_cameras(n_views, res, seed=seed)
    for cam, img in zip(cams, render(mesh, albedo, cams, spp), strict=True):
        write_exr(root / "linear" / f"{cam.stem}.exr", img)
    save_cameras(root / "gt" / "cameras.json", cams)
    write_obj(root / "gt" / "mesh.obj", mesh)
    return {"root": root, "mesh": mesh, "cameras": cams, "linear": root / "linear"}


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


def synth_capture(base: Path, **overrides) -> Path:
    """A recon.synth capture for these settings, rendered into ``base`` unless already there.

    Pass pytest's ``tmp_path_factory.getbasetemp()`` as ``base`` to share one render between
    test modules of a session.
    """
    import hashlib

    from recon.synth.capture import SynthSettings, make_capture

    settings = SynthSettings(**{**SYNTH_TEST, **overrides})
    out = Path(base) / f"synth-{hashlib.sha1(repr(settings).encode()).hexdigest()[:12]}"
    if not (out / "gt" / "cameras.json").is_file():
        make_capture(out, settings)
    return out


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
