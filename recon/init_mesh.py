"""Stage ``init_mesh``: a coarse, watertight, manifold starting shape (DESIGN section 2).

A given ``init_mesh.ply`` passes through after validation. Otherwise the visual hull of the
masks, built without CUDA:

1. Silhouette distance field (:func:`recon.hull.silhouette_field`) on a grid (``resolution``^3
   voxels in a cube fitted to a coarse 48^3 hull: the poses stage's object cube [-1, 1]^3
   first, else, for given cameras in other units, a cube around the point the cameras look
   at; or [-bound, bound]^3): the distance to the intersection of the silhouette cones, in
   world units, positive inside, with the silhouettes grown by ``mask_margin_px`` pixels of
   safety. Voxels seen by fewer than ``min_views`` views count as outside. The zero level set
   lies between voxels, so the hull's surface is placed to sub-voxel precision.
2. Zero level set by flying-edges marching cubes (``open3d.t.geometry.TriangleMesh.
   create_isosurfaces``); positive inside gives outward normals (checked: positive volume).
   The largest connected component is kept.
3. pymeshlab clean-up and isotropic remeshing (``meshing_isotropic_explicit_remeshing``) to
   the edge length that gives about ``target_faces`` faces.
4. Checks: watertight (no boundary edges), two-manifold, one component, positive volume;
   :class:`InitMeshError` otherwise.

The mesh is in the cameras.json frame. The visual hull contains the object (never cuts it when
the masks are right) but cannot see concavities; the optimizer carves those.

An object standing on a table (a support plane, ``plane.json`` of the masks or poses stage,
:mod:`recon.support`): cameras above the table see the silhouette cones reach down under it,
so the field is cut at the plane (the minimum of the hull field and the height above the
plane; before that a small grey-scale closing removes the thin tunnels that the ragged edges of
masks separated from a table leave, ``plane_closing_voxels``), and the vertices the remeshing leaves within half a voxel of the plane are put on it:
the unseen base is closed, flat and on the plane.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from recon.hull import Grid, HullError, silhouette_field
from recon.io.atomic import atomic_dir
from recon.io.cameras import CameraError, CameraSet, load_cameras
from recon.io.images import read_mask
from recon.io.mesh import Mesh, MeshError, read_mesh, write_ply
from recon.support import PlaneError, SupportPlane, plane_if_found

log = logging.getLogger(__name__)


class InitMeshError(ValueError):
    """An initial mesh that cannot be made or used; the message names the input and the fix."""


@dataclass(frozen=True)
class InitMeshSettings:
    resolution: int = 128  # grid cells per axis
    bound: float = 0.0  # > 0: the grid spans [-bound, bound]^3; 0: fitted to the hull (see hull_bounds)
    bound_margin: float = 0.05  # fitted grids extend the coarse hull's box by this fraction
    min_views: int = 2  # a voxel must be seen by this many views to be kept
    mask_margin_px: float = 0.5  # grow the silhouettes by this many pixels (mask edge safety)
    target_faces: int = 5000
    remesh_iterations: int = 8
    # with a support plane: a grey-scale closing of the hull field by this many voxels before the
    # cut. Masks separated from a table have ragged edges whose cones leave thin tunnels through
    # the hull (genus 10-16 on the 40-view tabletop benchmark captures, where the void peers gave
    # 0 and 1); a 2-voxel closing removed them and kept the mug's handle (volume +1-2 %)
    plane_closing_voxels: int = 2

    def __post_init__(self):
        if self.resolution < 8:
            raise ValueError(f"resolution must be >= 8, got {self.resolution}")
        if self.bound < 0 or self.target_faces < 100 or self.min_views < 1:
            raise ValueError("bound must be >= 0, target_faces >= 100 and min_views >= 1")
        if self.plane_closing_voxels < 0:
            raise ValueError(f"plane_closing_voxels must be >= 0, got {self.plane_closing_voxels}")


def _silhouette_field(cams: CameraSet, masks: dict[str, np.ndarray], grid: Grid,
                      settings: InitMeshSettings, plane: SupportPlane | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`recon.hull.silhouette_field` with the stage's settings and error, cut at the
    support plane when there is one (what lies below the table is outside)."""
    try:
        field, seen = silhouette_field(cams, masks, grid, settings.min_views, settings.mask_margin_px)
    except HullError as e:
        raise InitMeshError(str(e)) from e
    if plane is not None:
        if settings.plane_closing_voxels > 0:
            from scipy import ndimage

            size = 2 * settings.plane_closing_voxels + 1
            field = ndimage.grey_closing(field, size=(size, size, size), mode="nearest")
        height = plane.height(grid.points()).reshape(field.shape).astype(np.float32)
        field = np.minimum(field, height)
    return field, seen


def flatten_base(mesh: Mesh, plane: SupportPlane, tolerance: float) -> tuple[Mesh, int]:
    """``mesh`` with every vertex lower than ``tolerance`` above ``plane`` moved onto it (the
    remeshed cut lies within a fraction of a voxel of the plane); returns the count moved."""
    h = plane.height(mesh.v_pos)
    low = h < tolerance
    v = mesh.v_pos.copy()
    v[low] = plane.project(v[low])
    return Mesh(v, mesh.t_pos_idx), int(low.sum())


def isosurface(field: np.ndarray, grid: Grid) -> Mesh:
    """Zero level set of ``field`` (positive inside) as a closed mesh with outward normals."""
    import open3d as o3d

    pad = np.pad(field.astype(np.float32), 1, constant_values=-abs(float(grid.step)))  # closes the surface
    if not (pad > 0).any():
        raise InitMeshError("the visual hull is empty: the masks and the cameras do not agree "
                            "(check the masks, and that the object lies inside [-1, 1]^3)")
    m = o3d.t.geometry.TriangleMesh.create_isosurfaces(o3d.core.Tensor(pad), [0.0])
    v = m.vertex.positions.numpy().astype(np.float64)[:, ::-1]  # open3d returns (k, j, i)
    f = m.triangle.indices.numpy().astype(np.int64)
    if len(f) == 0:
        raise InitMeshError("marching cubes returned no surface")
    v = (v - 1.0) * grid.step + grid.origin  # index space (padded) -> world
    mesh = Mesh(v, f)
    if mesh.volume() < 0:
        mesh = Mesh(v, f[:, ::-1])
    return mesh


def topology(mesh: Mesh) -> dict:
    """pymeshlab's topological measures plus the signed volume."""
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(mesh.v_pos, mesh.t_pos_idx))
    t = ms.get_topological_measures()
    t = {k: (bool(v) if isinstance(v, bool) else int(v)) for k, v in t.items()}
    t["volume"] = mesh.volume()
    return t


def check_closed_manifold(mesh: Mesh, what: str = "mesh") -> dict:
    """Raise :class:`InitMeshError` unless ``mesh`` is watertight, two-manifold and outward."""
    t = topology(mesh)
    problems = []
    if t["boundary_edges"]:
        problems.append(f"{t['boundary_edges']} boundary edges (holes)")
    if not t["is_mesh_two_manifold"] or t["non_two_manifold_edges"] or t["non_two_manifold_vertices"]:
        problems.append(f"{t['non_two_manifold_edges']} non-manifold edges, "
                        f"{t['non_two_manifold_vertices']} non-manifold vertices")
    if t["unreferenced_vertices"]:
        problems.append(f"{t['unreferenced_vertices']} unreferenced vertices")
    if t["volume"] <= 0:
        problems.append(f"non-positive volume {t['volume']:.3g} (inward normals)")
    if problems:
        raise InitMeshError(f"{what} is not a watertight two-manifold: " + "; ".join(problems))
    return t


def largest_component(mesh: Mesh) -> Mesh:
    """The connected component (by shared vertices) with the most faces, compacted."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = mesh.t_pos_idx
    nv = len(mesh.v_pos)
    rows = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    cols = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    g = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(nv, nv))
    n, label = connected_components(g, directed=False)
    if n > 1:
        face_label = label[f[:, 0]]
        keep = face_label == np.argmax(np.bincount(face_label))
        f = f[keep]
    used = np.unique(f)
    remap = np.full(nv, -1)
    remap[used] = np.arange(len(used))
    return Mesh(mesh.v_pos[used], remap[f])


def remesh(mesh: Mesh, target_faces: int, iterations: int = 8) -> Mesh:
    """Clean and isotropically remesh to about ``target_faces`` faces (pymeshlab)."""
    import pymeshlab

    # equilateral triangles of edge L: area sqrt(3)/4 L^2 each
    edge = float(np.sqrt(4.0 * mesh.area() / (np.sqrt(3.0) * target_faces)))
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(mesh.v_pos, mesh.t_pos_idx))
    ms.meshing_remove_duplicate_vertices()
    ms.meshing_remove_null_faces()
    if len(mesh.t_pos_idx) > 8 * target_faces:  # cheaper remeshing from a decimated start
        ms.meshing_decimation_quadric_edge_collapse(targetfacenum=4 * target_faces, preservetopology=True,
                                                    preserveboundary=True, planarquadric=True)
    ms.meshing_isotropic_explicit_remeshing(iterations=iterations, targetlen=pymeshlab.PureValue(edge))
    ms.meshing_remove_unreferenced_vertices()
    pinched = int(ms.get_topological_measures()["non_two_manifold_vertices"])
    if pinched:  # remeshing can pinch a thin tunnel of the hull to a vertex: split it (stays closed)
        log.info("remeshing left %d non-manifold vertices; split", pinched)
        ms.meshing_repair_non_manifold_vertices()
    m = ms.current_mesh()
    out = Mesh(m.vertex_matrix(), m.face_matrix())
    if out.volume() < 0:
        out = Mesh(out.v_pos, out.t_pos_idx[:, ::-1])
    return out


def _touches(inside: np.ndarray) -> bool:
    return bool(inside[0].any() or inside[-1].any() or inside[:, 0].any() or inside[:, -1].any()
                or inside[:, :, 0].any() or inside[:, :, -1].any())


def _rays_meet(cams: CameraSet, masks: dict[str, np.ndarray]) -> tuple[np.ndarray, float]:
    """The point closest (least squares) to the rays through the masks' centroids, and the
    median camera distance to it: where the cameras look, and how far away they are."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    centers = []
    for cam in cams:
        m = masks.get(cam.stem)
        if m is None or not m.any():
            continue
        i, j = np.argwhere(m).mean(0) + 0.5
        d = cam.camera_to_world[:3, :3] @ np.linalg.solve(cam.K, [j, i, 1.0])
        d /= np.linalg.norm(d)
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ cam.center
        centers.append(cam.center)
    if len(centers) < 2 or np.linalg.cond(A) > 1e8:
        raise InitMeshError("the cameras do not look at a common point (parallel or too few masks); "
                            "check cameras.json and the masks")
    p = np.linalg.solve(A, b)
    return p, float(np.median(np.linalg.norm(np.asarray(centers) - p, axis=1)))


def hull_bounds(cams: CameraSet, masks: dict[str, np.ndarray], settings: InitMeshSettings,
                coarse: int = 48, plane: SupportPlane | None = None) -> tuple[np.ndarray, float, str]:
    """Center (3,) and half size of a cube that holds the visual hull with a small margin.

    The poses stage's object cube [-1, 1]^3 is tried first (a coarse hull there that does not
    reach the cube's faces); otherwise (given cameras in other units or another frame) a cube
    around the point the cameras look at, grown until the coarse hull fits. Fitting the grid
    to the hull also spends the voxels on the object, not on empty space.
    """
    def attempt(center, half):
        grid = Grid.cube(center, half, coarse)
        field, _ = _silhouette_field(cams, masks, grid, settings, plane)
        inside = field > 0
        if not inside.any():
            return None, "empty"
        if _touches(inside):
            return None, "touches"
        idx = np.argwhere(inside)
        lo = grid.origin + grid.step * (idx.min(0) - 1)
        hi = grid.origin + grid.step * (idx.max(0) + 1)
        c = 0.5 * (lo + hi)
        return (c, 0.5 * float(np.max(hi - lo)) * (1.0 + settings.bound_margin) + grid.step), "ok"

    if sum(bool(m.any()) for m in masks.values()) < 2:
        raise InitMeshError("the visual hull is empty: fewer than 2 masks show any object "
                            "(check the masks stage's output, or give masks/ in the capture)")
    box, why = attempt(np.zeros(3), 1.0)
    if box is not None:
        return box[0], box[1], "object cube [-1, 1]^3"
    center, distance = _rays_meet(cams, masks)
    half = 0.25 * distance
    for _ in range(4):
        box, why = attempt(center, half)
        if box is not None:
            return box[0], box[1], "fitted around the cameras' focus"
        if why == "empty":
            raise InitMeshError("the visual hull is empty: the masks and the cameras do not agree "
                                "(check the masks, and that cameras.json belongs to these photos)")
        half *= 2.0
    raise InitMeshError(f"the visual hull does not fit in a cube of half size {half / 2:.3g} around the "
                        "cameras' focus: the masks probably include background")


def visual_hull_mesh(cams: CameraSet, masks: dict[str, np.ndarray],
                     settings: InitMeshSettings = InitMeshSettings(),
                     plane: SupportPlane | None = None) -> tuple[Mesh, dict]:
    """The remeshed visual hull and statistics; the grid is [-bound, bound]^3, or fitted to
    the hull (:func:`hull_bounds`) when ``bound`` is 0. With a support ``plane`` the hull is
    cut at it and the base is flat, on the plane."""
    t0 = time.perf_counter()
    if settings.bound > 0:
        center, half, source = np.zeros(3), settings.bound, "setting 'bound'"
    else:
        center, half, source = hull_bounds(cams, masks, settings, plane=plane)
    grid = Grid.cube(center, half, settings.resolution)
    field, seen = _silhouette_field(cams, masks, grid, settings, plane)
    t1 = time.perf_counter()
    inside = field > 0
    touches = _touches(inside)
    if touches:
        log.warning("the visual hull reaches the edge of the grid (center %s, half size %.3g): the "
                    "object may be cut off (masks including background?)", np.round(center, 3).tolist(), half)
    raw = largest_component(isosurface(field, grid))
    t2 = time.perf_counter()
    mesh = remesh(raw, settings.target_faces, settings.remesh_iterations)
    on_plane = 0
    if plane is not None:
        mesh, on_plane = flatten_base(mesh, plane, 0.5 * grid.step)
    t3 = time.perf_counter()
    stats = {
        "voxels_inside": int(inside.sum()),
        "raw_faces": int(len(raw.t_pos_idx)),
        "faces": int(len(mesh.t_pos_idx)),
        "vertices": int(len(mesh.v_pos)),
        "touches_bounds": touches,
        "plane": None if plane is None else {"cut": True, "base_vertices": on_plane, **plane.to_dict()},
        "grid": {"center": center.tolist(), "half_size": float(half), "resolution": settings.resolution,
                 "voxel": float(grid.step), "source": source},
        "timings": {"field_s": t1 - t0, "isosurface_s": t2 - t1, "remesh_s": t3 - t2},
    }
    return mesh, stats


def _read_masks_for(cams: CameraSet, masks_dir: Path) -> dict[str, np.ndarray]:
    masks = {}
    for c in cams:
        p = masks_dir / f"{c.stem}.png"
        if p.is_file():
            m = read_mask(p)
            if m.shape != (c.height, c.width):
                raise InitMeshError(f"{p}: mask is {m.shape[1]}x{m.shape[0]} but the camera of {c.image} "
                                    f"is {c.width}x{c.height}; masks must be in the cameras' (pinhole) images")
            masks[c.stem] = m
    if len(masks) < 2:
        raise InitMeshError(f"{masks_dir}: masks for {len(masks)} of {len(cams)} views; the visual hull "
                            "needs the masks stage's output (or give init_mesh.ply in the capture)")
    return masks


def run_init_mesh(
    cameras_json: str | os.PathLike,
    masks_dir: str | os.PathLike | None,
    out_dir: str | os.PathLike,
    settings: InitMeshSettings = InitMeshSettings(),
    given_mesh: str | os.PathLike | None = None,
    plane_json: str | os.PathLike | None = None,
) -> dict:
    """Write ``out_dir/mesh.ply`` (and ``init_mesh.json``); ``out_dir`` is replaced atomically.

    Parameters
    ----------
    cameras_json : the cameras (the capture's, or the poses stage's).
    masks_dir : masks in the cameras' pinhole images (``<stem>.png``): the masks stage's folder
        for given cameras, ``poses/undistorted/masks`` after SfM.
    given_mesh : the capture's ``init_mesh.ply``: validated and copied unchanged.
    plane_json : the support plane (``plane.json`` beside the masks; absent when none was found):
        the hull is cut at it and its base is flat on it (:func:`visual_hull_mesh`).
    """
    out_dir = Path(out_dir)
    t0 = time.perf_counter()
    with atomic_dir(out_dir) as tmp:
        if given_mesh is not None:
            given_mesh = Path(given_mesh)
            try:
                mesh = read_mesh(given_mesh)
            except MeshError as e:
                raise InitMeshError(str(e)) from e
            try:
                topo = check_closed_manifold(mesh, str(given_mesh))
            except InitMeshError as e:
                raise InitMeshError(f"{e}; repair it (e.g. MeshLab) or delete it to use the visual hull") from e
            if given_mesh.suffix.lower() == ".ply":
                shutil.copyfile(given_mesh, tmp / "mesh.ply")
            else:
                write_ply(tmp / "mesh.ply", mesh)
            stats = {"source": "given", "mesh": str(given_mesh), "faces": int(len(mesh.t_pos_idx))}
        else:
            try:
                cams = load_cameras(cameras_json)
            except CameraError as e:
                raise InitMeshError(f"{e}; rerun the poses stage") from e
            need = max(2, settings.min_views)
            if len(cams) < need:
                raise InitMeshError(
                    f"{cameras_json}: {len(cams)} view(s), but a visual hull needs at least {need} views from "
                    f"different directions (init_mesh.min_views = {settings.min_views}); photograph the object "
                    "from more sides, or give init_mesh.ply in the capture")
            if masks_dir is None:
                raise InitMeshError("no masks folder given: the visual hull needs masks")
            masks = _read_masks_for(cams, Path(masks_dir))
            try:
                plane = plane_if_found(plane_json)
            except PlaneError as e:
                raise InitMeshError(f"{e}; rerun the masks stage") from e
            if plane is None and plane_json is not None:
                log.info("no support plane (%s absent): the visual hull of an object in the void", plane_json)
            mesh, stats = visual_hull_mesh(cams, masks, settings, plane)
            topo = check_closed_manifold(mesh, "the visual hull mesh")
            write_ply(tmp / "mesh.ply", mesh)
            stats["source"] = "visual_hull"
            stats["views_with_masks"] = len(masks)
        stats["topology"] = topo
        stats["settings"] = asdict(settings)
        stats["seconds"] = time.perf_counter() - t0
        (tmp / "init_mesh.json").write_text(json.dumps(stats, indent=1))
    log.info("initial mesh (%s): %d faces, genus %d, %.1f s", stats["source"], stats["faces"],
             topo["genus"], stats["seconds"])
    return stats
