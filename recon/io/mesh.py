"""Triangle meshes: ``Mesh`` and OBJ/PLY files.

Arrays are named by what and where (nvdiffrec's habit): ``v_pos (V, 3)`` positions,
``t_pos_idx (F, 3)`` triangles, ``v_tex (T, 2)`` UVs in the OBJ convention (v up, the texel in
row i, column j of an H x W map at u = (j + 0.5)/W, v = 1 - (i + 0.5)/H), ``t_tex_idx (F, 3)``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from recon.io.atomic import atomic_path


class MeshError(ValueError):
    """A mesh file that cannot be used; the message names the file and the fix."""


@dataclass
class Mesh:
    v_pos: np.ndarray  # (V, 3) float64
    t_pos_idx: np.ndarray  # (F, 3) int64
    v_tex: np.ndarray | None = None  # (T, 2) float64, OBJ convention (v up)
    t_tex_idx: np.ndarray | None = None  # (F, 3) int64

    def __post_init__(self):
        self.v_pos = np.asarray(self.v_pos, dtype=np.float64).reshape(-1, 3)
        self.t_pos_idx = np.asarray(self.t_pos_idx, dtype=np.int64).reshape(-1, 3)
        if self.v_tex is not None:
            self.v_tex = np.asarray(self.v_tex, dtype=np.float64).reshape(-1, 2)
            self.t_tex_idx = np.asarray(self.t_tex_idx, dtype=np.int64).reshape(-1, 3)

    @property
    def has_uv(self) -> bool:
        return self.v_tex is not None and self.t_tex_idx is not None

    def face_normals(self) -> np.ndarray:
        """(F, 3) unnormalized face normals (length = 2 x area)."""
        v = self.v_pos[self.t_pos_idx]
        return np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])

    def vertex_normals(self) -> np.ndarray:
        """(V, 3) area-weighted vertex normals, normalized (DESIGN section 3)."""
        fn = self.face_normals()
        n = np.zeros_like(self.v_pos)
        for k in range(3):
            np.add.at(n, self.t_pos_idx[:, k], fn)
        length = np.linalg.norm(n, axis=1, keepdims=True)
        return n / np.maximum(length, 1e-20)

    def area(self) -> float:
        return float(0.5 * np.linalg.norm(self.face_normals(), axis=1).sum())

    def volume(self) -> float:
        """Signed volume (positive for a closed mesh with outward normals)."""
        v = self.v_pos[self.t_pos_idx]
        return float(np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0)

    def bbox(self) -> tuple[np.ndarray, np.ndarray]:
        return self.v_pos.min(axis=0), self.v_pos.max(axis=0)

    def sample_surface(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """(n, 3) area-uniform random points on the surface."""
        fn = np.linalg.norm(self.face_normals(), axis=1)
        if fn.sum() <= 0:
            raise MeshError("cannot sample a mesh of zero area")
        f = rng.choice(len(fn), size=n, p=fn / fn.sum())
        r1, r2 = rng.random(n), rng.random(n)
        s = np.sqrt(r1)
        b = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
        v = self.v_pos[self.t_pos_idx[f]]
        return np.einsum("ni,nij->nj", b, v)


# ---- OBJ ----
def write_obj(path: str | os.PathLike, mesh: Mesh) -> None:
    """Write ``v``, ``vt`` and ``f v/vt`` records, atomically."""
    lines = ["# recon mesh"]
    lines += [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in mesh.v_pos]
    if mesh.has_uv:
        lines += [f"vt {u:.9g} {v:.9g}" for u, v in mesh.v_tex]
        f = np.concatenate([mesh.t_pos_idx + 1, mesh.t_tex_idx + 1], axis=1)
        lines += [f"f {a}/{d} {b}/{e} {c}/{g}" for a, b, c, d, e, g in f]
    else:
        lines += [f"f {a} {b} {c}" for a, b, c in mesh.t_pos_idx + 1]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")


def read_obj(path: str | os.PathLike) -> Mesh:
    """Read positions, UVs and faces (polygons are fan-triangulated; normals are ignored)."""
    path = Path(path)
    v, vt, f, ft = [], [], [], []
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise MeshError(f"{path}: file not found") from None
    for ln, line in enumerate(text.splitlines(), 1):
        parts = line.split()
        if not parts:
            continue
        try:
            if parts[0] == "v":
                v.append([float(x) for x in parts[1:4]])
            elif parts[0] == "vt":
                vt.append([float(x) for x in parts[1:3]])
            elif parts[0] == "f":
                idx = [p.split("/") for p in parts[1:]]
                pi = [int(p[0]) for p in idx]
                ti = [int(p[1]) if len(p) > 1 and p[1] else 0 for p in idx]
                for k in range(1, len(pi) - 1):
                    f.append([pi[0], pi[k], pi[k + 1]])
                    ft.append([ti[0], ti[k], ti[k + 1]])
        except (ValueError, IndexError) as e:
            raise MeshError(f"{path}:{ln}: cannot parse '{line.strip()}' ({e})") from e
    if not v or not f:
        raise MeshError(f"{path}: no vertices or faces; is it a triangle mesh OBJ?")
    f = np.asarray(f, dtype=np.int64)
    f = np.where(f < 0, f + len(v), f - 1)
    mesh = Mesh(np.asarray(v), f)
    ft = np.asarray(ft, dtype=np.int64)
    if vt and np.all(ft != 0):
        ft = np.where(ft < 0, ft + len(vt), ft - 1)
        mesh.v_tex, mesh.t_tex_idx = np.asarray(vt, dtype=np.float64), ft
    if f.min() < 0 or f.max() >= len(v):
        raise MeshError(f"{path}: a face refers to a vertex that does not exist")
    return mesh


# ---- PLY (positions and faces) ----
def write_ply(path: str | os.PathLike, mesh: Mesh) -> None:
    """Binary little-endian PLY with float32 positions and int32 faces, atomically."""
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment recon mesh\n"
        f"element vertex {len(mesh.v_pos)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element face {len(mesh.t_pos_idx)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    faces = np.empty(len(mesh.t_pos_idx), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    faces["n"] = 3
    faces["i"] = mesh.t_pos_idx
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(header.encode("ascii"))
            fh.write(np.ascontiguousarray(mesh.v_pos, dtype="<f4").tobytes())
            fh.write(faces.tobytes())


def read_ply(path: str | os.PathLike) -> Mesh:
    """Read a triangle mesh PLY (ASCII or binary) through open3d."""
    import open3d as o3d

    path = Path(path)
    if not path.is_file():
        raise MeshError(f"{path}: file not found")
    m = o3d.io.read_triangle_mesh(str(path))
    if len(m.vertices) == 0 or len(m.triangles) == 0:
        raise MeshError(f"{path}: no vertices or triangles could be read; is it a triangle mesh PLY?")
    mesh = Mesh(np.asarray(m.vertices), np.asarray(m.triangles))
    bad = (mesh.t_pos_idx < 0) | (mesh.t_pos_idx >= len(mesh.v_pos))
    if bad.any():
        f = int(np.argmax(bad.any(axis=1)))
        raise MeshError(f"{path}: {int(bad.any(axis=1).sum())} face(s) refer to vertices that do not exist (face {f} "
                        f"uses vertex {int(mesh.t_pos_idx[f][bad[f]][0])}; the file has {len(mesh.v_pos)} vertices, "
                        "numbered from 0); re-export the mesh")
    if not np.isfinite(mesh.v_pos).all():
        raise MeshError(f"{path}: {int((~np.isfinite(mesh.v_pos)).any(axis=1).sum())} vertex position(s) are NaN "
                        "or Inf; re-export the mesh")
    return mesh


def read_points(path: str | os.PathLike) -> np.ndarray:
    """(N, 3) float64 vertex positions of a PLY point cloud (ASCII or binary; extra vertex
    properties, e.g. the ``in_mask`` flag of ``poses/points.ply``, are ignored). An empty cloud
    gives (0, 3); a file that is no PLY is a :class:`MeshError`."""
    import open3d as o3d

    path = Path(path)
    if not path.is_file():
        raise MeshError(f"{path}: file not found")
    pts = np.asarray(o3d.io.read_point_cloud(str(path)).points, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0:
        # open3d skips ASCII files with extra properties in some versions: read them by hand
        text = path.read_text(errors="replace").splitlines()
        if not text or text[0].strip() != "ply" or "end_header" not in text:
            raise MeshError(f"{path}: not a PLY point cloud")
        end = text.index("end_header")
        rows = [line.split()[:3] for line in text[end + 1:] if line.strip()]
        try:
            pts = np.array(rows, dtype=np.float64).reshape(-1, 3)
        except ValueError as e:
            raise MeshError(f"{path}: not an ASCII PLY point cloud ({e})") from e
    return pts


def read_mesh(path: str | os.PathLike) -> Mesh:
    """Read ``.obj`` or ``.ply`` by extension."""
    suffix = Path(path).suffix.lower()
    if suffix == ".obj":
        return read_obj(path)
    if suffix == ".ply":
        return read_ply(path)
    raise MeshError(f"{path}: unknown mesh format '{suffix}'; use .obj or .ply")


def write_mesh(path: str | os.PathLike, mesh: Mesh) -> None:
    suffix = Path(path).suffix.lower()
    if suffix == ".obj":
        return write_obj(path, mesh)
    if suffix == ".ply":
        return write_ply(path, mesh)
    raise MeshError(f"{path}: unknown mesh format '{suffix}'; use .obj or .ply")
