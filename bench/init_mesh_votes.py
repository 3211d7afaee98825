"""The initial mesh against wrong masks: the strict visual hull beside the hull by vote (issue 32).

Synthetic captures with exact cameras: a sphere (radius 0.5, genus 0) and a torus around the x
axis (radii 0.45 and 0.18, genus 1), seen by a ring of 12 views (96 px, 40 degrees, 3 units away,
elevation +-22 degrees, as in tests/test_init_mesh.py) or a spiral orbit of 33 views (128 px).
Masks are the exact silhouettes, some views spoiled: a round hole at the mask's deepest point
(half its depth: a dark concavity a flash-falloff mask missed) or the right 30 % cut off (a missing
part). Each row runs ``recon.init_mesh.visual_hull_mesh`` with each setting and prints the genus
(the object's is 0 or 1), DESIGN section 5's accuracy and completeness (unit bounding box), the
silhouette IoU with the masks and the seconds. docs/init_mesh.md quotes its output.

    .venv/bin/python bench/init_mesh_votes.py [--set ring12|orbit33|few|framecut|all] [--resolution 128]
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from recon import init_mesh as rim  # noqa: E402
from recon import metrics  # noqa: E402
from recon.io.cameras import Camera, CameraSet, intrinsics, look_at  # noqa: E402
from recon.io.mesh import Mesh  # noqa: E402


# ---- Objects ----
def icosphere(level: int = 4) -> Mesh:
    import open3d as o3d

    m = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=2 ** level * 2)
    mesh = Mesh(np.asarray(m.vertices), np.asarray(m.triangles))
    return mesh if mesh.volume() > 0 else Mesh(mesh.v_pos, mesh.t_pos_idx[:, ::-1])


def sphere() -> Mesh:
    m = icosphere()
    return Mesh(0.5 * m.v_pos, m.t_pos_idx)


def torus(R: float = 0.45, r: float = 0.18, n: int = 96, m: int = 48) -> Mesh:
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, n, endpoint=False), np.linspace(0, 2 * np.pi, m, endpoint=False),
                       indexing="ij")
    p = np.stack([r * np.sin(v), (R + r * np.cos(v)) * np.sin(u), (R + r * np.cos(v)) * np.cos(u)], -1).reshape(-1, 3)
    idx = np.arange(n * m).reshape(n, m)
    a, b = idx, np.roll(idx, -1, 0)
    c, d = np.roll(b, -1, 1), np.roll(idx, -1, 1)
    f = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    mesh = Mesh(p, f)
    return mesh if mesh.volume() > 0 else Mesh(p, f[:, ::-1])


# ---- Cameras ----
def ring(n: int = 12, res: int = 96) -> CameraSet:
    return CameraSet(tuple(
        Camera(f"images/{k:02d}.png", res, res, intrinsics(res, res, 40),
               look_at([3 * np.cos(t), 3 * np.sin(t), 1.2 * np.sin(2 * t + 0.3)], [0, 0, 0]))
        for k, t in enumerate(np.linspace(0, 2 * np.pi, n, endpoint=False))))


def orbit(n: int = 33, res: int = 128) -> CameraSet:
    cams = []
    for k in range(n):
        z = 0.8 * (1 - 2 * (k + 0.5) / n)
        t = k * 2.399963  # the golden angle: an even spiral
        eye = 3.0 * np.array([np.sqrt(1 - z * z) * np.cos(t), np.sqrt(1 - z * z) * np.sin(t), z])
        cams.append(Camera(f"images/{k:02d}.png", res, res, intrinsics(res, res, 40), look_at(eye, [0, 0, 0])))
    return CameraSet(tuple(cams))


def close_ups(n: int = 6, res: int = 96) -> tuple:
    """Views 1.3 units away that the objects overflow (the frame edge cuts them)."""
    return tuple(Camera(f"images/c{k}.png", res, res, intrinsics(res, res, 40),
                        look_at(1.3 * np.array([np.cos(t), np.sin(t), 0.3]), [0.2 * np.cos(t + 1), 0.2 * np.sin(t + 1), 0.1]))
                 for k, t in enumerate(np.linspace(0, 2 * np.pi, n, endpoint=False)))


# ---- Masks ----
def silhouette(mesh: Mesh, cam: Camera) -> np.ndarray:
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.v_pos.astype(np.float32)), o3d.core.Tensor(mesh.t_pos_idx.astype(np.uint32)))
    j, i = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    d = np.stack([j, i, np.ones_like(j)], -1).reshape(-1, 3) @ np.linalg.inv(cam.K).T @ cam.camera_to_world[:3, :3].T
    rays = np.concatenate([np.broadcast_to(cam.center, d.shape), d], 1).astype(np.float32)
    return np.isfinite(scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()).reshape(cam.height, cam.width)


def hole(mask: np.ndarray) -> np.ndarray:
    import cv2

    depth = cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, 5)
    i, j = np.unravel_index(np.argmax(depth), depth.shape)
    ii, jj = np.mgrid[:mask.shape[0], :mask.shape[1]]
    return mask & ((ii - i) ** 2 + (jj - j) ** 2 >= (0.5 * depth[i, j]) ** 2)


def cut(mask: np.ndarray) -> np.ndarray:
    out = mask.copy()
    cols = np.flatnonzero(mask.any(0))
    out[:, int(cols.max() - 0.3 * (cols.max() - cols.min())):] = False
    return out


# ---- Runs ----
def settings_list(res: int, full: bool) -> list:
    s = lambda **k: rim.InitMeshSettings(resolution=res, target_faces=3000, **k)  # noqa: E731
    out = [("strict (before)", s(outside_fraction=0.0, closing_radius=0.0)), ("default", s())]
    if full:
        out += [("f=0.2", s(outside_fraction=0.2)), ("no closing", s(closing_radius=0.0))]
    return out


def run(name: str, obj: Mesh, genus: int, cams: CameraSet, errors: dict, settings: list) -> None:
    masks = {c.stem: silhouette(obj, c) for c in cams}
    for k, spoil in errors.items():
        masks[cams.frames[k].stem] = spoil(masks[cams.frames[k].stem])
    for label, s in settings:
        t = time.perf_counter()
        mesh, st = rim.visual_hull_mesh(cams, masks, s)
        g = rim.topology(mesh)["genus"]
        r = metrics.chamfer(mesh, obj, n_samples=20_000)
        print(f"{'ok ' if g == genus else 'BAD'} {name:30s} {label:16s} genus {g:3d}  accuracy {r['accuracy']:.4f}  "  # noqa: T201
              f"completeness {r['completeness']:.4f}  IoU mean {st['mask_iou']['mean']:.3f} min {st['mask_iou']['min']:.3f}"
              f"  repaired {'yes' if st['repairs'] else 'no '}  {time.perf_counter() - t:.1f} s", flush=True)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--set", default="all", choices=["ring12", "orbit33", "few", "framecut", "all"])
    ap.add_argument("--resolution", type=int, default=128)
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    objects = [("sphere", sphere(), 0), ("torus", torus(), 1)]
    sets = ["ring12", "orbit33", "few", "framecut"] if a.set == "all" else [a.set]
    for which in sets:
        if which == "ring12":
            cases = [("clean", {}), ("1 hole", {3: hole}), ("1 cut", {2: cut}), ("2 holes", {3: hole, 6: hole}),
                     ("2 holes, opposite views", {3: hole, 8: hole})]
            for nm, obj, g in objects:
                for en, err in cases:
                    run(f"{nm}, 12 views, {en}", obj, g, ring(), err, settings_list(a.resolution, True))
        if which == "orbit33":
            cases = [("clean", {}), ("hole + cut", {3: hole, 17: cut}), ("3 holes", {3: hole, 10: hole, 20: hole})]
            for nm, obj, g in objects:
                for en, err in cases:
                    run(f"{nm}, 33 views, {en}", obj, g, orbit(), err, settings_list(a.resolution, True))
        if which == "few":
            for n in (4, 6, 8):
                for nm, obj, g in objects:
                    for en, err in (("clean", {}), ("1 hole", {1: hole})):
                        run(f"{nm}, {n} views, {en}", obj, g, ring(n), err, settings_list(a.resolution, False))
        if which == "framecut":
            cams = CameraSet(ring().frames + close_ups())
            for nm, obj, g in objects:
                for en, err in (("clean", {}), ("1 hole", {3: hole}), ("hole in a close-up", {14: hole})):
                    run(f"{nm}, 12 + 6 close-ups, {en}", obj, g, cams, err, settings_list(a.resolution, False))


if __name__ == "__main__":
    main()
