"""Small test scenes for the renderer (test helper, not a test module).

Meshes are closed and welded (positions shared across UV seams, which only split UVs), so the
only discontinuities of I(x) are true silhouettes. Scenes put objects in front of a lit
backdrop so the jump across a silhouette is large (STACK.md: an outer silhouette against black
carries little).
"""

from __future__ import annotations

import numpy as np

from recon.io.cameras import Camera, intrinsics, look_at


def uv_sphere(n_lon: int = 24, n_lat: int = 12, radius: float = 1.0, center=(0.0, 0.0, 0.0)):
    """Welded UV sphere: ``(v_pos, t_pos_idx, v_tex, t_tex_idx)``, outward normals."""
    center = np.asarray(center, dtype=np.float64)
    theta = np.linspace(0.0, np.pi, n_lat + 1)[1:-1]  # ring polar angles
    phi = np.linspace(0.0, 2 * np.pi, n_lon + 1)
    # positions: north pole, rings (n_lat - 1) x n_lon, south pole
    ring = np.stack([
        np.sin(theta)[:, None] * np.cos(phi[None, :-1]),
        np.sin(theta)[:, None] * np.sin(phi[None, :-1]),
        np.repeat(np.cos(theta)[:, None], n_lon, axis=1),
    ], axis=-1).reshape(-1, 3)
    v_pos = np.concatenate([[[0, 0, 1]], ring, [[0, 0, -1]]]) * radius + center
    south = len(v_pos) - 1

    def pid(i, j):  # ring i (0..n_lat-2), longitude j (wraps)
        return 1 + i * n_lon + (j % n_lon)

    # UVs: a grid (n_lat + 1) x (n_lon + 1), v up (north pole at v = 1)
    uu, vv = np.meshgrid(np.linspace(0, 1, n_lon + 1), 1.0 - np.linspace(0, 1, n_lat + 1))
    v_tex = np.stack([uu.ravel(), vv.ravel()], axis=1)

    def tid(r, j):  # latitude row r (0..n_lat), longitude j (0..n_lon)
        return r * (n_lon + 1) + j

    faces, tfaces = [], []
    for j in range(n_lon):
        faces.append([0, pid(0, j), pid(0, j + 1)])
        tfaces.append([tid(0, j), tid(1, j), tid(1, j + 1)])
        faces.append([south, pid(n_lat - 2, j + 1), pid(n_lat - 2, j)])
        tfaces.append([tid(n_lat, j), tid(n_lat - 1, j + 1), tid(n_lat - 1, j)])
    for i in range(n_lat - 2):
        for j in range(n_lon):
            a, b, c, d = pid(i, j), pid(i + 1, j), pid(i + 1, j + 1), pid(i, j + 1)
            ta, tb, tc, td = tid(i + 1, j), tid(i + 2, j), tid(i + 2, j + 1), tid(i + 1, j + 1)
            faces += [[a, b, c], [a, c, d]]
            tfaces += [[ta, tb, tc], [ta, tc, td]]
    return v_pos, np.array(faces), v_tex, np.array(tfaces)


def backdrop(size: float = 6.0, n: int = 2, y: float = 1.5):
    """A square in the plane y = ``y`` facing -y (toward cameras on the -y side)."""
    s = np.linspace(-size / 2, size / 2, n + 1)
    X, Z = np.meshgrid(s, s, indexing="xy")
    v_pos = np.stack([X.ravel(), np.full(X.size, y), Z.ravel()], axis=1)
    v_tex = np.stack([(X.ravel() + size / 2) / size, (Z.ravel() + size / 2) / size], axis=1)
    faces = []
    for i in range(n):
        for j in range(n):
            a = i * (n + 1) + j
            faces += [[a, a + 1, a + n + 2], [a, a + n + 2, a + n + 1]]
    f = np.array(faces)
    return v_pos, f, v_tex, f.copy()


def merge(*meshes):
    """Concatenate ``(v_pos, t_pos_idx, v_tex, t_tex_idx)`` meshes; returns it and vertex offsets."""
    vs, fs, ts, fts, offsets = [], [], [], [], []
    ov = ot = 0
    for v, f, t, ft in meshes:
        offsets.append(ov)
        vs.append(v)
        fs.append(f + ov)
        ts.append(t)
        fts.append(ft + ot)
        ov += len(v)
        ot += len(t)
    return (np.concatenate(vs), np.concatenate(fs), np.concatenate(ts), np.concatenate(fts)), offsets


def camera(eye, width: int = 64, height: int = 64, fov_x: float = 45.0, target=(0.0, 0.0, 0.0),
           up=(0.0, 0.0, 1.0)) -> Camera:
    return Camera("view.png", width, height, intrinsics(width, height, fov_x),
                  look_at(eye, target, up))


def textures(rng: np.random.Generator, size: int = 16):
    """Smoothly varying diffuse (RGB), specular (1 ch) and roughness (1 ch) maps."""
    i, j = np.meshgrid(np.arange(size), np.arange(size), indexing="ij")
    base = 0.5 + 0.2 * np.sin(i / 3.0)[..., None] * np.cos(j / 4.0)[..., None] * np.array([1, -1, 0.5])
    diffuse = np.clip(base + 0.1 * rng.random((size, size, 3)), 0.05, 0.95).astype(np.float32)
    specular = (0.2 + 0.2 * rng.random((size, size, 1))).astype(np.float32)
    roughness = (0.3 + 0.4 * rng.random((size, size, 1))).astype(np.float32)
    return diffuse, specular, roughness


def two_spheres_scene():
    """A sphere partly hiding a second one, both in front of a backdrop; camera at -y.

    Returns ``(mesh, offsets, camera)`` with ``offsets`` the first vertex of each part
    (front sphere, rear sphere, backdrop).
    """
    front = uv_sphere(16, 8, radius=0.55, center=(-0.35, -0.6, 0.0))
    rear = uv_sphere(16, 8, radius=0.6, center=(0.45, 0.4, 0.1))
    mesh, offsets = merge(front, rear, backdrop())
    return mesh, offsets, camera((0.0, -4.0, 0.3))
