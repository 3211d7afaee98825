"""Procedural objects with fine geometric detail, for synthetic captures and benchmarks.

Every object is a closed, manifold triangle mesh with outward normals, centered at the origin
and inside the cube [-0.95, 0.95]^3 (so inside DESIGN's [-1, 1]^3 object frame):

- ``blob``: a sphere deformed by low-frequency noise, with round bumps and dents and a few
  grooves (narrow circular channels) - genus 0, detail at several scales.
- ``torus``: a genus-1 ring with bumps, ridges around the tube and a spiral groove; its
  inner rim gives self-occlusion edges in front of lit surfaces.
- ``smooth``: the blob's low-frequency shape only (no bumps, no grooves).
- ``mug``: a cup with a flat base, an open cavity and a handle (genus 1), standing along +z:
  a concavity that no visual hull carves and a through-hole beside the body; made as the zero
  level set of a signed distance function (marching cubes, then isotropic remeshing).
- ``box``: a box with flat faces and edges rounded to a few percent of its size (a product box:
  planes a flash lights evenly, edges a smooth surface prior rounds off), standing on one face.
- ``figure``: a figurine: a body and a head on two legs that stand apart, two thin arms held out
  from the body (about 4 % of its height thick): parts thinner than a voxel of a coarse hull,
  and a gap between the legs that only some views see through. Genus 0.
- ``bell``, ``vase``, ``bowl``: surfaces of revolution standing along +z on a flat base
  (:func:`revolve`): a bell (a dome over a waist flaring out to a wide lip at the bottom, a
  knob on top), a tall vase (a belly, a narrow neck, an open mouth) and a low wide bowl (an
  open cavity). They cover what tabletop masks find hard: a wide flared base on the table,
  a tall thin object, a low one.

:func:`flatten_base` cuts an object flat at the bottom so that it can stand on a table
(tabletop captures, :mod:`recon.synth.tabletop`).

Shapes are functions of ``seed`` alone (numpy float64, no threads; the mug, the box and the figure also go through
open3d's marching cubes, run on one thread, and pymeshlab's remeshing).
"""

from __future__ import annotations

import numpy as np

from recon.io.mesh import Mesh
from recon.synth.noise import fbm

OBJECT_KINDS = ("blob", "torus", "smooth", "mug", "bell", "vase", "bowl", "box", "figure")
FLAT_BASE = ("mug", "bell", "vase", "bowl", "box", "figure")
"""Objects made standing on a flat base (a tabletop scene does not cut them flat)."""
EXTENT = 0.95
"""Largest absolute coordinate of a generated object."""


# ---- base tessellations ----
def icosphere(level: int) -> Mesh:
    """Unit icosphere after ``level`` 4:1 subdivisions: 10 * 4**level + 2 vertices."""
    if level < 0:
        raise ValueError(f"icosphere level must be >= 0, got {level}")
    t = (1.0 + 5.0**0.5) / 2.0
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
                  [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]],
                 dtype=np.float64)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9],
                  [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2],
                  [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10],
                  [8, 6, 7], [9, 8, 1]], dtype=np.int64)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(level):
        edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        key = np.sort(edges, axis=1)
        uniq, inv = np.unique(key, axis=0, return_inverse=True)
        mid = v[uniq[:, 0]] + v[uniq[:, 1]]
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        m = inv.reshape(3, -1).T + len(v)  # (F, 3): midpoints of edges 01, 12, 20
        v = np.concatenate([v, mid])
        a, b, c = f[:, 0], f[:, 1], f[:, 2]
        m01, m12, m20 = m[:, 0], m[:, 1], m[:, 2]
        f = np.concatenate([np.stack([a, m01, m20], 1), np.stack([b, m12, m01], 1),
                            np.stack([c, m20, m12], 1), np.stack([m01, m12, m20], 1)])
    return Mesh(v, f)


def torus_grid(n_major: int, n_minor: int, R: float = 1.0, r: float = 0.4):
    """A torus around the z axis as a closed grid.

    Returns
    -------
    mesh : Mesh
    phi, theta : (V,) float
        Angle around the z axis and around the tube of every vertex.
    """
    if n_major < 3 or n_minor < 3:
        raise ValueError("a torus grid needs at least 3 x 3 vertices")
    phi = 2 * np.pi * np.arange(n_major) / n_major
    theta = 2 * np.pi * np.arange(n_minor) / n_minor
    P, T = np.meshgrid(phi, theta, indexing="ij")
    pos = np.stack([(R + r * np.cos(T)) * np.cos(P), (R + r * np.cos(T)) * np.sin(P),
                    r * np.sin(T)], -1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n_major), np.arange(n_minor), indexing="ij")
    a = i * n_minor + j
    b = ((i + 1) % n_major) * n_minor + j
    c = ((i + 1) % n_major) * n_minor + (j + 1) % n_minor
    d = i * n_minor + (j + 1) % n_minor
    f = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                        np.stack([a, c, d], -1).reshape(-1, 3)])
    return Mesh(pos, f), P.reshape(-1), T.reshape(-1)


# ---- detail fields ----
def _random_dirs(rng: np.random.Generator, n: int) -> np.ndarray:
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _bumps(dirs: np.ndarray, rng: np.random.Generator, n: int, size=(0.10, 0.22),
           height=(0.025, 0.055)) -> np.ndarray:
    """Sum of ``n`` Gaussian bumps (and dents) on the unit sphere of directions."""
    centers = _random_dirs(rng, n)
    sizes = rng.uniform(*size, n)
    heights = rng.uniform(*height, n) * rng.choice([-1.0, 1.0, 1.0], n)
    ang = np.arccos(np.clip(dirs @ centers.T, -1.0, 1.0))  # (V, n)
    return (heights * np.exp(-0.5 * (ang / sizes) ** 2)).sum(axis=1)


def _grooves(dirs: np.ndarray, rng: np.random.Generator, n: int, depth=0.022,
             width=0.035) -> np.ndarray:
    """``n`` circular grooves (small circles of the direction sphere), depth ``depth``."""
    axes = _random_dirs(rng, n)
    radii = rng.uniform(0.55, 1.35, n)  # angular radius of each circle
    ang = np.arccos(np.clip(dirs @ axes.T, -1.0, 1.0))
    return -(depth * np.exp(-(((ang - radii) / width) ** 2))).sum(axis=1)


def _fit_extent(mesh: Mesh) -> Mesh:
    lo, hi = mesh.bbox()
    center = 0.5 * (lo + hi)
    v = mesh.v_pos - center
    v *= EXTENT / np.abs(v).max()
    return Mesh(v, mesh.t_pos_idx)


def blob(level: int = 6, seed: int = 0, detail: bool = True) -> Mesh:
    """The ``blob`` (``detail=True``) or ``smooth`` object on an icosphere of ``level``."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0xB10B]))
    base = icosphere(level)
    d = base.v_pos
    radius = 1.0 + 0.16 * fbm(d * 0.9, 1.0, octaves=2, seed=seed + 7)
    # an elongation so that views differ in silhouette, not only in texture
    radius *= 1.0 + 0.12 * (d @ _random_dirs(rng, 1)[0]) ** 2
    if detail:
        radius += _bumps(d, rng, 14)
        radius += _grooves(d, rng, 4)
        radius += 0.006 * fbm(d, 9.0, octaves=2, seed=seed + 11)  # fine surface roughness
    return _fit_extent(Mesh(d * radius[:, None], base.t_pos_idx))


def torus(level: int = 6, seed: int = 0) -> Mesh:
    """The genus-1 ``torus`` object with about as many faces as an icosphere of ``level``."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x7085]))
    faces = 20 * 4**level
    n_minor = max(8, int(round(np.sqrt(faces / 2 / 3.0))))
    n_major = max(12, int(round(faces / 2 / n_minor)))
    R, r = 1.0, 0.42
    mesh, phi, theta = torus_grid(n_major, n_minor, R, r)
    center = np.stack([R * np.cos(phi), R * np.sin(phi), np.zeros_like(phi)], -1)
    normal = (mesh.v_pos - center) / r
    disp = 0.05 * fbm(mesh.v_pos * 0.8, 1.0, octaves=2, seed=seed + 3)
    # bumps: Gaussian in 3D distance to random surface points
    k = 12
    idx = rng.integers(0, len(phi), k)
    size = rng.uniform(0.08, 0.16, k)
    height = rng.uniform(0.02, 0.045, k) * rng.choice([-1.0, 1.0, 1.0], k)
    dist2 = ((mesh.v_pos[:, None, :] - mesh.v_pos[idx][None]) ** 2).sum(-1)
    disp += (height * np.exp(-0.5 * dist2 / size**2)).sum(1)
    # ridges around the tube at a few angles phi, and a spiral groove along it
    for phi0 in rng.uniform(0, 2 * np.pi, 3):
        dphi = np.angle(np.exp(1j * (phi - phi0)))
        disp += 0.018 * np.exp(-((dphi * R / 0.03) ** 2))
    spiral = np.angle(np.exp(1j * (theta - 3.0 * phi)))
    disp -= 0.02 * np.exp(-((spiral * r / 0.035) ** 2))
    v = center + normal * (r + disp)[:, None]
    # tilt the ring a little so that no view is exactly along its axis
    a = rng.uniform(0.25, 0.45)
    rot = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    return _fit_extent(Mesh(v @ rot.T, mesh.t_pos_idx))


def _smooth_min(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum of two distances (a fillet of radius about ``k``)."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b * (1.0 - h) + a * h - k * h * (1.0 - h)


def _rounded_cylinder(radial: np.ndarray, z: np.ndarray, radius: float, z0: float, z1: float,
                      rounding: float) -> np.ndarray:
    """Signed distance (negative inside) of a cylinder ``r <= radius, z0 <= z <= z1``, edges rounded."""
    dr = radial - (radius - rounding)
    dz = np.abs(z - 0.5 * (z0 + z1)) - (0.5 * (z1 - z0) - rounding)
    return (np.minimum(np.maximum(dr, dz), 0.0)
            + np.hypot(np.maximum(dr, 0.0), np.maximum(dz, 0.0)) - rounding)


def mug_sdf(points: np.ndarray, seed: int = 0) -> np.ndarray:
    """Signed distance (negative inside) of the ``mug`` at ``points (..., 3)``, before fitting.

    A rounded cylinder (outer radius ~0.62, height ~1.5) minus a cavity open at the top, and a
    handle (a torus in the xz plane) joined to the wall by a smooth union; ``seed`` varies the
    proportions a little.
    """
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x3C6]))
    r_out = 0.62 * rng.uniform(0.92, 1.08)
    height = 1.5 * rng.uniform(0.9, 1.05)
    wall, bottom, rounding = 0.08, 0.12, 0.03
    x, y, z = points[..., 0], points[..., 1], points[..., 2]
    radial = np.hypot(x, y)
    body = _rounded_cylinder(radial, z, r_out, -height / 2, height / 2, rounding)
    cavity = _rounded_cylinder(radial, z, r_out - wall, -height / 2 + bottom, height, rounding)
    # the handle: a torus around the y axis beside the wall, cut off inside the wall
    hx, hz = x - (r_out + 0.02), z - height * rng.uniform(0.0, 0.06)
    handle = np.hypot(np.hypot(hx, hz) - 0.40 * height / 1.5, y) - 0.085
    handle = np.maximum(handle, (r_out - 0.5 * wall) - x)
    return np.maximum(_smooth_min(body, handle, 0.06), -cavity)


def box_sdf(points: np.ndarray, seed: int = 0) -> np.ndarray:
    """Signed distance (negative inside) of the ``box``: about 1.6 x 1.1 x 0.9, edges rounded by 0.04."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0xB0C5]))
    half = np.array([0.8, 0.55, 0.45]) * rng.uniform(0.9, 1.1, 3)
    q = np.abs(points) - (half - 0.04)
    return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(-1), 0.0) - 0.04


def _capsule(points: np.ndarray, a, b, r: float) -> np.ndarray:
    a, b = np.asarray(a, float), np.asarray(b, float)
    ab = b - a
    t = np.clip(((points - a) @ ab) / float(ab @ ab), 0.0, 1.0)
    return np.linalg.norm(points - (a + t[..., None] * ab), axis=-1) - r


def figure_sdf(points: np.ndarray, seed: int = 0) -> np.ndarray:
    """Signed distance (negative inside) of the ``figure``: legs (z from -1 up), a body, a head and
    two thin arms held out sideways and a little forward; flat soles at z = -1."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0xF16]))
    x, y, z = points[..., 0], points[..., 1], points[..., 2]
    spread = 0.22 * rng.uniform(0.9, 1.1)
    legs = np.minimum(_capsule(points, (-spread, 0.0, -0.95), (-0.12, 0.0, -0.2), 0.11),
                      _capsule(points, (spread, 0.0, -0.95), (0.12, 0.0, -0.2), 0.11))
    body = (np.sqrt((x / 0.34) ** 2 + (y / 0.24) ** 2 + ((z - 0.05) / 0.42) ** 2) - 1.0) * 0.24
    head = np.linalg.norm(points - np.array([0.0, 0.0, 0.72]), axis=-1) - 0.22 * rng.uniform(0.9, 1.1)
    reach = 0.85 * rng.uniform(0.9, 1.05)
    arms = np.minimum(_capsule(points, (-0.25, 0.0, 0.25), (-reach, 0.25, -0.05), 0.045),
                      _capsule(points, (0.25, 0.0, 0.25), (reach, 0.25, 0.15), 0.045))
    d = _smooth_min(_smooth_min(_smooth_min(body, legs, 0.08), head, 0.06), arms, 0.05)
    return np.maximum(d, -1.0 - z)  # the soles cut flat


def _sdf_mesh(sdf, level: int, seed: int, half: float = 1.25) -> Mesh:
    """Marching cubes of ``sdf(points, seed)`` (negative inside), remeshed to about ``20 * 4**level``
    faces and fitted to :data:`EXTENT`."""
    import open3d as o3d
    import pymeshlab

    n = int(np.clip(24 * 2 ** (level / 2), 64, 192))  # grid nodes per axis
    g = np.linspace(-half, half, n)
    step = g[1] - g[0]
    grid = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1)
    inside = -sdf(grid, seed).astype(np.float32)  # positive inside
    # open3d's marching cubes on one thread: on a busy machine its threads emit the triangles in
    # another order, and the remeshing below depends on that order (a mug of 767 vertices beside
    # its 784-vertex twin in one suite run); one thread gives the order of an idle machine's run
    threads = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(1)
    try:
        iso = o3d.t.geometry.TriangleMesh.create_isosurfaces(o3d.core.Tensor(inside), [0.0])
    finally:
        o3d.utility.set_max_threads(threads)
    v = iso.vertex.positions.numpy().astype(np.float64)[:, ::-1] * step - half  # (k, j, i) -> xyz
    f = iso.triangle.indices.numpy().astype(np.int64)
    target = 20 * 4**level
    edge = float(np.sqrt(4.0 * Mesh(v, f).area() / (np.sqrt(3.0) * target)))
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(v, f.astype(np.int32)))
    ms.meshing_remove_duplicate_vertices()
    ms.meshing_isotropic_explicit_remeshing(iterations=6, targetlen=pymeshlab.PureValue(edge))
    ms.meshing_remove_unreferenced_vertices()
    m = ms.current_mesh()
    out = Mesh(m.vertex_matrix(), m.face_matrix())
    if out.volume() < 0:
        out = Mesh(out.v_pos, out.t_pos_idx[:, ::-1])
    return _fit_extent(out)


def mug(level: int = 6, seed: int = 0) -> Mesh:
    """The ``mug``: marching cubes of :func:`mug_sdf`, remeshed to about ``20 * 4**level`` faces."""
    return _sdf_mesh(mug_sdf, level, seed)


def box(level: int = 6, seed: int = 0) -> Mesh:
    """The ``box``: marching cubes of :func:`box_sdf`, remeshed."""
    return _sdf_mesh(box_sdf, level, seed)


def figure(level: int = 6, seed: int = 0) -> Mesh:
    """The ``figure``: marching cubes of :func:`figure_sdf`, remeshed."""
    return _sdf_mesh(figure_sdf, level, seed)


def flatten_base(mesh: Mesh, cut: float) -> Mesh:
    """The object cut flat at ``cut`` (a fraction of its height) above its lowest point.

    Vertices below the cut move straight up onto the cut plane, so the mesh stays closed
    and keeps its faces (the base is flat and lies on the plane); the result is re-centered and
    re-scaled to fill :data:`EXTENT`. ``cut = 0`` returns the mesh unchanged.
    """
    if not 0.0 <= cut < 0.5:
        raise ValueError(f"flatten_base: cut must be in [0, 0.5), got {cut}")
    if cut == 0.0:
        return mesh
    lo, hi = mesh.bbox()
    z_cut = lo[2] + cut * (hi[2] - lo[2])
    v = mesh.v_pos.copy()
    v[:, 2] = np.maximum(v[:, 2], z_cut)
    return _fit_extent(Mesh(v, mesh.t_pos_idx))


def revolve(profile: np.ndarray, level: int) -> Mesh:
    """A closed surface of revolution around the z axis from ``profile (K, 2)`` of (radius, z).

    The profile runs from a point on the axis (radius 0) to another point on the axis, with
    the inside of the solid on its left when read in the (r, z) half plane (e.g. from the
    bottom centre out along the base, up the outside, back to the axis at the top); its
    points are resampled by arc length. The mesh has about ``20 * 4**level`` faces, genus 0.
    """
    prof = np.asarray(profile, dtype=np.float64)
    if prof.ndim != 2 or prof.shape[1] != 2 or abs(prof[0, 0]) > 1e-12 or abs(prof[-1, 0]) > 1e-12:
        raise ValueError("revolve: the profile must run from the axis (r = 0) to the axis")
    seg = np.linalg.norm(np.diff(prof, axis=0), axis=1)
    t = np.concatenate([[0.0], np.cumsum(seg)])
    faces = 20 * 4**level
    n_theta = max(12, int(round(np.sqrt(faces * np.pi / max(t[-1], 1e-9) * np.max(prof[:, 0]) / 2))))
    n_prof = max(4, int(round(faces / (2 * n_theta))))
    s = np.linspace(0.0, t[-1], n_prof + 1)
    r = np.interp(s, t, prof[:, 0])
    z = np.interp(s, t, prof[:, 1])
    theta = 2 * np.pi * np.arange(n_theta) / n_theta
    rings = r[1:-1]
    ring_z = z[1:-1]
    v = [np.array([[0.0, 0.0, z[0]]])]
    v.append(np.stack([np.outer(rings, np.cos(theta)).ravel(), np.outer(rings, np.sin(theta)).ravel(),
                       np.repeat(ring_z, n_theta)], 1))
    v.append(np.array([[0.0, 0.0, z[-1]]]))
    v = np.concatenate(v)
    top = len(v) - 1
    n_rings = len(rings)
    idx = 1 + np.arange(n_rings * n_theta).reshape(n_rings, n_theta)
    nxt = np.roll(idx, -1, axis=1)
    f = [np.stack([np.zeros(n_theta, np.int64), nxt[0], idx[0]], 1)]
    for k in range(n_rings - 1):
        a, b, c, d = idx[k], nxt[k], idx[k + 1], nxt[k + 1]
        f.append(np.stack([a, b, d], 1))
        f.append(np.stack([a, d, c], 1))
    f.append(np.stack([idx[-1], nxt[-1], np.full(n_theta, top)], 1))
    f = np.concatenate(f).astype(np.int64)
    mesh = Mesh(v, f)
    if mesh.volume() < 0:
        mesh = Mesh(v, f[:, ::-1])
    return mesh


def _profile(points, n: int = 24) -> np.ndarray:
    """A smooth (Catmull-Rom) curve through ``points`` [(r, z), ...], ``n`` samples per span."""
    p = np.asarray(points, dtype=np.float64)
    q = np.concatenate([p[:1], p, p[-1:]])
    out = [p[:1]]
    u = np.linspace(0, 1, n + 1)[1:, None]
    for k in range(1, len(q) - 2):
        p0, p1, p2, p3 = q[k - 1], q[k], q[k + 1], q[k + 2]
        out.append(0.5 * (2 * p1 + (-p0 + p2) * u + (2 * p0 - 5 * p1 + 4 * p2 - p3) * u**2
                          + (-p0 + 3 * p1 - 3 * p2 + p3) * u**3))
    return np.concatenate(out)


def bell(level: int = 6, seed: int = 0) -> Mesh:
    """The ``bell``: a wide flared lip on the base, a waist, a dome and a knob on top."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0xBE11]))
    lip = 1.0 * rng.uniform(0.95, 1.05)
    waist = 0.62 * rng.uniform(0.95, 1.05)
    outside = _profile([(lip, 0.0), (lip * 0.97, 0.08), (lip * 0.82, 0.22), (waist, 0.55), (waist * 0.98, 0.95),
                        (waist * 0.9, 1.2), (waist * 0.62, 1.38), (0.2, 1.46), (0.12, 1.5), (0.13, 1.62),
                        (0.08, 1.7), (0.0, 1.72)])
    return _fit_extent(revolve(np.concatenate([[[0.0, 0.0]], outside]), level))


def vase(level: int = 6, seed: int = 0) -> Mesh:
    """The ``vase``: tall (3 x its width), a belly, a narrow neck and an open mouth."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x7A5E]))
    belly = 0.5 * rng.uniform(0.95, 1.05)
    outside = _profile([(0.3, 0.0), (belly, 0.45), (belly * 0.95, 0.9), (0.2, 1.6), (0.17, 2.1), (0.27, 2.45),
                        (0.28, 2.5)])
    inside = _profile([(0.23, 2.5), (0.13, 2.2), (0.0, 2.05)])
    return _fit_extent(revolve(np.concatenate([[[0.0, 0.0]], outside, inside]), level))


def bowl(level: int = 6, seed: int = 0) -> Mesh:
    """The ``bowl``: low and wide (about 3 x as wide as tall) with an open cavity."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0xB0A1]))
    rim = 1.0 * rng.uniform(0.95, 1.05)
    outside = _profile([(0.45, 0.0), (0.5, 0.06), (0.8, 0.25), (rim, 0.55), (rim, 0.62)])
    inside = _profile([(rim - 0.07, 0.62), (rim - 0.1, 0.52), (0.7, 0.3), (0.3, 0.16), (0.0, 0.14)])
    return _fit_extent(revolve(np.concatenate([[[0.0, 0.0]], outside, inside]), level))


def make_object(kind: str, level: int = 6, seed: int = 0) -> Mesh:
    """One of :data:`OBJECT_KINDS` (no UVs yet)."""
    if kind == "mug":
        return mug(level, seed)
    if kind == "bell":
        return bell(level, seed)
    if kind == "vase":
        return vase(level, seed)
    if kind == "bowl":
        return bowl(level, seed)
    if kind == "box":
        return box(level, seed)
    if kind == "figure":
        return figure(level, seed)
    if kind == "blob":
        return blob(level, seed, detail=True)
    if kind == "smooth":
        return blob(level, seed, detail=False)
    if kind == "torus":
        return torus(level, seed)
    raise ValueError(f"unknown object kind {kind!r}; choose one of {OBJECT_KINDS}")
