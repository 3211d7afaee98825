"""Coarse-to-fine stage changes (sec. 3.4): remesh, re-unwrap, carry the textures over.

Between stages the surface is remeshed isotropically to a smaller target edge length
(pymeshlab; the paper used Instant Meshes), unwrapped again (xatlas), and every texture map is
baked onto the new atlas from the old mesh: for each texel of the new atlas, its 3D point on
the new surface -> the closest point on the old surface -> the old UV there -> a bilinear
lookup in the old map. Baking straight into the new, larger map is the paper's bilinear
upsampling and the transfer in one resampling. Texels up to 1.5 texels outside a chart are
baked from the chart's own surface (the closest point of its nearest triangle), so bilinear
lookups at chart borders read the right surface; texels farther out (gutters) take the value of
the nearest baked texel.

UVs follow the OBJ convention (DESIGN section 2): texel (row i, col j) of an H x W map sits at
u = (j + 0.5)/W, v = 1 - (i + 0.5)/H.
"""

from __future__ import annotations

import logging

import numpy as np

from recon.io.mesh import Mesh
from recon.uv import UVError, pack_atlas

log = logging.getLogger(__name__)


class RemeshError(ValueError):
    """Remeshing produced a mesh that cannot be optimized; the message says what to change."""


# ---- Remeshing ----
def topology_report(v_pos: np.ndarray, t_pos_idx: np.ndarray) -> dict:
    """pymeshlab's topological measures (manifoldness, boundary edges, components, genus)."""
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(np.asarray(v_pos, dtype=np.float64), np.asarray(t_pos_idx, dtype=np.int32)))
    return dict(ms.get_topological_measures())


def is_manifold(v_pos: np.ndarray, t_pos_idx: np.ndarray) -> bool:
    """Edge- and vertex-manifold (every edge in at most two faces, every vertex one fan)."""
    return bool(topology_report(v_pos, t_pos_idx)["is_mesh_two_manifold"])


def remesh(v_pos: np.ndarray, t_pos_idx: np.ndarray, edge_length: float, iterations: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Isotropic remeshing to ``edge_length`` (absolute units): ``(v_pos (V', 3), t_pos_idx (F', 3))``.

    Small disconnected pieces (< 1% of the faces) and unreferenced vertices are dropped.
    Remeshed in units of the edge length around the bounding box's centre, the positions rounded
    to 2^-16 of it (MeshLab computes in float32, and files round positions): the same surface at
    any scale gets the same decisions (tests/test_extremes.py).
    """
    import pymeshlab

    if not edge_length > 0:
        raise ValueError(f"edge_length must be > 0, got {edge_length}")
    v = np.asarray(v_pos, dtype=np.float64)
    c = 0.5 * (v.min(axis=0) + v.max(axis=0))
    h = float(edge_length)
    ms = pymeshlab.MeshSet()
    q = 2.0**-16
    ms.add_mesh(pymeshlab.Mesh(np.round((v - c) / h / q) * q, np.asarray(t_pos_idx, dtype=np.int32)))
    ms.meshing_isotropic_explicit_remeshing(targetlen=pymeshlab.PureValue(1.0), iterations=int(iterations))
    n = ms.current_mesh().face_number()
    ms.meshing_remove_connected_component_by_face_number(mincomponentsize=max(1, n // 100))
    ms.meshing_remove_unreferenced_vertices()
    m = ms.current_mesh()
    return np.asarray(m.vertex_matrix(), dtype=np.float64) * h + c, np.asarray(m.face_matrix(), dtype=np.int64)


# ---- UV atlas ----
def unwrap(v_pos: np.ndarray, t_pos_idx: np.ndarray, texture_size: int, padding: int = 2,
           max_attempts: int = 12) -> Mesh:
    """The mesh with an xatlas atlas that fits one ``texture_size`` x ``texture_size`` map.

    :func:`recon.uv.pack_atlas` with ``padding`` empty texels between charts in the map itself,
    the first packing aimed at charts filling half the map (one xatlas run, ~4 s per 30k faces,
    is the cost, so the first attempt should fit). Faces keep their order (checked). When the
    charts do not fit with ``padding`` (many small charts in a small map: 34 charts of a
    three-view hull at 32^2), the padding is lowered to 1, then 0 (bilinear lookups then blend
    neighbouring charts' texels at their borders), with a warning.
    """
    err = None
    for pad in sorted({int(padding), min(int(padding), 1), 0}, reverse=True):
        try:
            v_tex, t_tex_idx, _ = pack_atlas(v_pos, t_pos_idx, texture_size, pad, fill=0.5,
                                             max_attempts=max_attempts)
        except UVError as e:
            err = e
            continue
        if pad != int(padding):
            log.warning("the remeshed surface's charts fit a %dx%d map only with %d-texel padding (asked %d)",
                        texture_size, texture_size, pad, padding)
        return Mesh(v_pos, t_pos_idx, v_tex, t_tex_idx)
    raise RemeshError(f"{err} (re-unwrapping the remeshed surface)") from err


def texel_centers_uv(size: int) -> np.ndarray:
    """(size, size, 2) UV of every texel center, OBJ convention (row 0 = top = v near 1)."""
    c = (np.arange(size) + 0.5) / size
    u, v = np.meshgrid(c, 1.0 - c)
    return np.stack([u, v], axis=-1)


def rasterize_atlas(mesh: Mesh, size: int, dilate: float = 1.5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which face each texel of a ``size`` x ``size`` map belongs to, and where it is in 3D.

    A texel belongs to the face whose UV triangle holds its center, or, within ``dilate``
    texels outside the charts, to the nearest UV triangle (its point then is the closest point
    of that triangle). Bilinear lookups inside a chart touch texels up to one texel outside
    it, so these rim texels must carry the chart's own surface, not a neighbouring chart's.

    Returns
    -------
    face : (size, size) int64, -1 for texels farther than ``dilate`` from every chart
    bary : (size, size, 3) float64 barycentric weights in that face
    points : (size, size, 3) float64 the 3D point of the texel (0 outside)
    """
    import open3d as o3d

    if not mesh.has_uv:
        raise ValueError("the mesh has no UVs to rasterize")
    uv3 = np.concatenate([mesh.v_tex, np.zeros((len(mesh.v_tex), 1))], axis=1).astype(np.float32)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(uv3), o3d.core.Tensor(mesh.t_tex_idx.astype(np.uint32)))
    c = texel_centers_uv(size).reshape(-1, 2)
    rays = np.zeros((len(c), 6), dtype=np.float32)
    rays[:, :2] = c
    rays[:, 2] = 1.0
    rays[:, 5] = -1.0
    hit = scene.cast_rays(o3d.core.Tensor(rays))
    face = hit["primitive_ids"].numpy().astype(np.int64)
    ok = np.isfinite(hit["t_hit"].numpy())
    buv = hit["primitive_uvs"].numpy().astype(np.float64)
    out = ~ok
    if dilate > 0 and out.any():
        q = np.zeros((int(out.sum()), 3), dtype=np.float32)
        q[:, :2] = c[out]
        near = scene.compute_closest_points(o3d.core.Tensor(q))
        d = np.linalg.norm(near["points"].numpy()[:, :2] - c[out], axis=1)
        close = d <= dilate / size
        idx = np.flatnonzero(out)[close]
        face[idx] = near["primitive_ids"].numpy().astype(np.int64)[close]
        buv[idx] = near["primitive_uvs"].numpy().astype(np.float64)[close]
        ok[idx] = True
    face[~ok] = -1
    bary = np.stack([1.0 - buv[:, 0] - buv[:, 1], buv[:, 0], buv[:, 1]], axis=1)
    bary[~ok] = 0.0
    points = np.zeros((len(c), 3))
    points[ok] = np.einsum("nk,nkd->nd", bary[ok], mesh.v_pos[mesh.t_pos_idx[face[ok]]])
    return face.reshape(size, size), bary.reshape(size, size, 3), points.reshape(size, size, 3)


def fill_gutters(image: np.ndarray, covered: np.ndarray) -> np.ndarray:
    """Copy into every texel outside ``covered (H, W)`` the value of the nearest covered texel."""
    from scipy import ndimage

    if covered.all() or not covered.any():
        return image.copy()
    idx = ndimage.distance_transform_edt(~covered, return_distances=False, return_indices=True)
    return image[idx[0], idx[1]]


# ---- Texture lookups and baking ----
def bilinear_lookup(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup of ``texture (H, W, C)`` at ``uv (N, 2)`` (OBJ convention, clamp to edge)."""
    H, W = texture.shape[:2]
    x = np.asarray(uv[:, 0]) * W - 0.5
    y = (1.0 - np.asarray(uv[:, 1])) * H - 0.5
    x0 = np.floor(x).astype(np.int64)
    y0 = np.floor(y).astype(np.int64)
    fx = (x - x0)[:, None]
    fy = (y - y0)[:, None]

    def at(yy, xx):
        return texture[np.clip(yy, 0, H - 1), np.clip(xx, 0, W - 1)]

    return ((1 - fy) * ((1 - fx) * at(y0, x0) + fx * at(y0, x0 + 1))
            + fy * ((1 - fx) * at(y0 + 1, x0) + fx * at(y0 + 1, x0 + 1)))


def surface_uv(mesh: Mesh, points: np.ndarray) -> np.ndarray:
    """UV (N, 2) of the closest point on ``mesh`` to each of ``points (N, 3)``."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.v_pos.astype(np.float32)),
                        o3d.core.Tensor(mesh.t_pos_idx.astype(np.uint32)))
    r = scene.compute_closest_points(o3d.core.Tensor(np.asarray(points, dtype=np.float32)))
    fid = r["primitive_ids"].numpy().astype(np.int64)
    buv = r["primitive_uvs"].numpy().astype(np.float64)
    bary = np.stack([1.0 - buv[:, 0] - buv[:, 1], buv[:, 0], buv[:, 1]], axis=1)
    return np.einsum("nk,nkd->nd", bary, mesh.v_tex[mesh.t_tex_idx[fid]])


def bake(old: Mesh, old_maps: dict[str, np.ndarray], new: Mesh, size: int) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Carry texture maps from ``old`` (with UVs) onto ``new``'s atlas at ``size`` x ``size``.

    Returns the new maps (same keys and channel counts, float32) and the (size, size) bool
    mask of texels inside the new charts.
    """
    face, _, points = rasterize_atlas(new, size)
    covered = face >= 0
    uv_old = surface_uv(old, points[covered])
    out = {}
    for name, tex in old_maps.items():
        tex = np.asarray(tex, dtype=np.float64)
        img = np.zeros((size, size, tex.shape[2]))
        img[covered] = bilinear_lookup(tex, uv_old)
        out[name] = fill_gutters(img, covered).astype(np.float32)
    return out, covered


def remesh_and_rebake(old: Mesh, old_maps: dict[str, np.ndarray], edge_length: float, texture_size: int,
                      remesh_iterations: int = 10) -> tuple[Mesh, dict[str, np.ndarray], np.ndarray]:
    """One stage change: remesh ``old`` to ``edge_length``, unwrap, bake ``old_maps``.

    Returns the new mesh (with UVs), its maps at ``texture_size`` and the chart mask.
    Raises :class:`RemeshError` when the remeshed surface is not manifold.
    """
    v, f = remesh(old.v_pos, old.t_pos_idx, edge_length, remesh_iterations)
    topo = topology_report(v, f)
    if not topo["is_mesh_two_manifold"]:
        raise RemeshError(
            f"remeshing to edge length {edge_length:.4g} gave a non-manifold mesh "
            f"({topo['non_two_manifold_edges']} edges, {topo['non_two_manifold_vertices']} vertices); "
            "use a larger edge_length for this stage"
        )
    new = unwrap(v, f, texture_size)
    maps, covered = bake(old, old_maps, new, texture_size)
    return new, maps, covered
