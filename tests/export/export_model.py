"""Builders of a small optimize-stage output to export: an xatlas-unwrapped bumpy icosphere with
spatially varying maps, and cameras whose up vector is the world's +Z (so the export must
rotate it to +Y)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from recon.io.cameras import Camera, CameraSet, intrinsics, look_at, save_cameras
from recon.io.images import write_exr
from recon.io.mesh import Mesh, write_obj

WORLD_UP = np.array([0.0, 0.0, 1.0])


def icosphere(subdivisions: int = 3) -> tuple[np.ndarray, np.ndarray]:
    t = (1 + 5**0.5) / 2
    v = [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t],
         [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]]
    f = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
         [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
         [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]]
    v = [np.asarray(p, float) / np.linalg.norm(p) for p in v]
    for _ in range(subdivisions):
        cache: dict[tuple[int, int], int] = {}
        f2 = []

        def mid(a, b, cache=cache):
            key = (min(a, b), max(a, b))
            if key not in cache:
                p = v[a] + v[b]
                v.append(p / np.linalg.norm(p))
                cache[key] = len(v) - 1
            return cache[key]

        for a, b, c in f:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            f2 += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        f = f2
    return np.asarray(v), np.asarray(f)


def make_mesh() -> Mesh:
    import xatlas

    v, f = icosphere(3)
    # Bumps, so vertex normals are not the radial direction.
    v = v * (0.7 + 0.06 * np.sin(5 * v[:, :1]) * np.cos(4 * v[:, 1:2]) + 0.04 * v[:, 2:3] ** 2)
    vmapping, indices, uvs = xatlas.parametrize(v.astype(np.float32), f.astype(np.uint32))
    return Mesh(v, vmapping[indices].astype(np.int64), uvs.astype(np.float64),
                indices.astype(np.int64))


def make_maps(size: int = 96) -> dict[str, np.ndarray]:
    y, x = (np.mgrid[0:size, 0:size] + 0.5) / size
    a_d = np.stack([0.15 + 0.7 * x, 0.1 + 0.5 * (0.5 + 0.5 * np.sin(9 * y)),
                    0.6 - 0.5 * x * y], axis=-1)
    a_s = (0.02 + 0.35 * (0.5 + 0.5 * np.cos(7 * x + 3 * y)))[..., None]
    r = (0.15 + 0.6 * (0.5 + 0.5 * np.sin(5 * x * y + 4 * x)))[..., None]
    return {"diffuse": a_d.astype(np.float32), "specular": a_s.astype(np.float32),
            "roughness": r.astype(np.float32)}


def make_cameras(n: int = 4, size: int = 96) -> CameraSet:
    frames = []
    for k in range(n):
        a = 2 * np.pi * k / n + 0.3
        eye = 2.6 * np.array([np.cos(a), np.sin(a), 0.35 + 0.2 * (k % 2)])
        frames.append(Camera(f"images/{k:04d}.exr", size, size, intrinsics(size, size, 45.0),
                             look_at(eye, np.zeros(3), WORLD_UP)))
    return CameraSet(tuple(frames), light_intensity=6.0)


@dataclass
class Model:
    folder: Path
    mesh: Mesh
    maps: dict
    cameras: CameraSet

    @property
    def mesh_obj(self) -> Path:
        return self.folder / "optimize" / "mesh.obj"

    def exr(self, name: str) -> Path:
        return self.folder / "optimize" / f"{name}.exr"

    @property
    def cameras_json(self) -> Path:
        return self.folder / "poses" / "cameras.json"

    def inputs(self) -> tuple[Path, Path, Path, Path]:
        return self.mesh_obj, self.exr("diffuse"), self.exr("specular"), self.exr("roughness")


def write_model(folder: Path) -> Model:
    """Write the model as ``folder/optimize/*`` (``cameras.json`` included) and ``folder/poses/cameras.json``."""
    mesh, maps, cams = make_mesh(), make_maps(), make_cameras()
    write_obj(folder / "optimize" / "mesh.obj", mesh)
    for name, a in maps.items():
        write_exr(folder / "optimize" / f"{name}.exr", a)
    save_cameras(folder / "poses" / "cameras.json", cams)
    save_cameras(folder / "optimize" / "cameras.json", cams)  # the optimize stage's (given cameras pass unchanged)
    (folder / "poses" / "poses.json").write_text('{"source": "given"}')  # the poses stage's record beside it
    return Model(folder, mesh, maps, cams)
