"""Metrics against a synthetic capture's ground truth (``<capture>/gt/``, DESIGN section 5).

- Alignment: the similarity mapping the estimated camera centers onto the true ones
  (:func:`recon.metrics.align_cameras`, Umeyama) when at least 3 views are in both camera sets
  and their centers are not collinear, else the identity; it is reported either way.
- Geometry: accuracy, completeness and chamfer (:func:`recon.metrics.chamfer`) in the
  ground-truth frame scaled to a unit bounding box.
- Images: the ground truth (mesh + maps) and the reconstruction (mapped into the ground-truth
  frame) rendered from the true cameras with the collocated light, RMSE of sRGB values over the
  union of both coverage masks (:func:`recon.metrics.image_rmse`). Views of ``gt/cameras.json``
  that the pipeline never saw (stems not in the estimated cameras) are the held-out views; when
  there are none, every true view is used and the result says so.
- Texture maps: UV layouts of the two meshes differ, so maps are compared on the surface:
  area-uniform samples of the ground-truth surface carry its map values; each sample's closest
  point on the reconstruction carries the reconstruction's. RMSE per map over samples whose
  closest point lies within ``texture_max_distance`` (unit-bbox units), with the fraction used.

The reconstruction, when mapped by a similarity of scale ``s``, is lit with
``s**2 * I_est`` so that it reproduces the images it was fitted to (distances scale by ``s``,
irradiance by ``1/s**2``).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from recon.io.cameras import Camera, CameraSet, load_cameras
from recon.io.mesh import Mesh
from recon.report.inputs import Model, ReportError, read_map, read_surface_mesh
from recon.metrics import MetricsError, Similarity, align_cameras

log = logging.getLogger(__name__)

GT_PRODUCER = "part of the synthetic capture's ground truth, DESIGN section 1"


@dataclass
class GroundTruth:
    """What a capture's ``gt/`` folder allows; metrics against it are optional diagnostics.

    Attributes
    ----------
    mesh : the ground-truth surface (UVs optional), or None when it cannot be read
    model : the mesh with UVs and the three maps (images and texture errors need them), or None
    cameras : ``gt/cameras.json`` (pose errors and ground-truth images need them), or None
    skipped : ``{metric group: why}`` for each group the files do not allow; the report shows
        these and the log names them
    """

    mesh: Mesh | None
    model: Model | None
    cameras: CameraSet | None
    skipped: dict[str, str] = field(default_factory=dict)


def read_ground_truth(gt_dir: str | os.PathLike) -> GroundTruth:
    """Read what ``gt/`` holds: ``mesh.obj`` (or ``mesh.ply``), ``diffuse/specular/roughness.exr``
    and ``cameras.json``.

    Never raises for a missing or unreadable file: geometry metrics need only the mesh, pose
    errors only the cameras, images the textured model and the cameras, texture errors the
    textured model. Each group the files do not allow is listed in ``skipped`` with the reason
    (naming the file) and logged as a warning.
    """
    d = Path(gt_dir)
    skipped: dict[str, str] = {}
    mesh_path = d / "mesh.obj" if (d / "mesh.obj").is_file() or not (d / "mesh.ply").is_file() else d / "mesh.ply"
    mesh = model = cams = None
    try:
        mesh = read_surface_mesh(mesh_path, GT_PRODUCER)
    except ReportError as e:
        skipped["geometry"] = str(e)
    maps_why = None
    if mesh is not None and not mesh.has_uv:
        maps_why = f"{mesh_path}: the mesh has no UVs, so ground-truth maps cannot be placed on it"
    elif mesh is None:
        maps_why = "no ground-truth mesh"
    else:
        try:
            model = Model(
                mesh=mesh,
                diffuse=read_map(d / "diffuse.exr", "ground-truth diffuse", (1, 3), GT_PRODUCER),
                specular=read_map(d / "specular.exr", "ground-truth specular", (1, 3), GT_PRODUCER),
                roughness=read_map(d / "roughness.exr", "ground-truth roughness", (1,), GT_PRODUCER),
            )
        except ReportError as e:
            maps_why = str(e)
        else:
            if model.diffuse.shape[2] == 1:
                model.diffuse = np.repeat(model.diffuse, 3, axis=2)
    try:
        cams = load_cameras(d / "cameras.json")
    except (OSError, ValueError) as e:
        skipped["pose_errors"] = f"{e} ({GT_PRODUCER})"
    if maps_why is not None:
        skipped["texture_rmse"] = maps_why
    if maps_why is not None or cams is None:
        skipped["image_rmse"] = maps_why if maps_why is not None else skipped["pose_errors"]
    for what, why in skipped.items():
        log.warning("ground truth: %s skipped: %s", what, why)
    return GroundTruth(mesh, model, cams, skipped)


# ---- Texture lookups on the surface ----
def sample_map(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup of (H, W, C) ``texture`` at (n, 2) OBJ-convention UVs (v up), edges clamped.

    The texel in row i, column j sits at u = (j + 0.5)/W, v = 1 - (i + 0.5)/H (DESIGN section 2).
    Returns (n, C).
    """
    t = np.asarray(texture, dtype=np.float64)
    H, W = t.shape[:2]
    x = np.clip(uv[:, 0] * W - 0.5, 0.0, W - 1.0)
    y = np.clip((1.0 - uv[:, 1]) * H - 0.5, 0.0, H - 1.0)
    x0 = np.floor(x).astype(int)
    y0 = np.floor(y).astype(int)
    x1, y1 = np.minimum(x0 + 1, W - 1), np.minimum(y0 + 1, H - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    return ((1 - fy) * ((1 - fx) * t[y0, x0] + fx * t[y0, x1])
            + fy * ((1 - fx) * t[y1, x0] + fx * t[y1, x1]))


def sample_surface_uv(mesh: Mesh, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) area-uniform points on ``mesh`` and their (n, 2) interpolated UVs."""
    fa = np.linalg.norm(mesh.face_normals(), axis=1)
    f = rng.choice(len(fa), size=n, p=fa / fa.sum())
    s, r2 = np.sqrt(rng.random(n)), rng.random(n)
    b = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    p = np.einsum("ni,nij->nj", b, mesh.v_pos[mesh.t_pos_idx[f]])
    uv = np.einsum("ni,nij->nj", b, mesh.v_tex[mesh.t_tex_idx[f]])
    return p, uv


def closest_uv(mesh: Mesh, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For (n, 3) points: the distance to ``mesh`` and the UV at the closest point, (n,), (n, 2)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.v_pos.astype(np.float32)),
                        o3d.core.Tensor(mesh.t_pos_idx.astype(np.uint32)))
    res = scene.compute_closest_points(o3d.core.Tensor(points.astype(np.float32)))
    q = res["points"].numpy().astype(np.float64)
    prim = res["primitive_ids"].numpy().astype(np.int64)
    buv = res["primitive_uvs"].numpy().astype(np.float64)  # q = (1-u-v) v0 + u v1 + v v2
    b = np.stack([1 - buv[:, 0] - buv[:, 1], buv[:, 0], buv[:, 1]], axis=1)
    uv = np.einsum("ni,nij->nj", b, mesh.v_tex[mesh.t_tex_idx[prim]])
    return np.linalg.norm(q - points, axis=1), uv


def texture_errors(reconstruction: Model, ground_truth: Model, similarity, unit: float,
                   n_samples: int, max_distance: float, seed: int = 0, albedo_gauge: float = 1.0) -> dict:
    """Per-map RMSE on the surface (see the module docstring).

    ``albedo_gauge``: the reconstruction's albedos (diffuse, specular) are multiplied by it
    before the comparison: the reconstruction's I_e (in the ground truth's frame) over the true
    I_e. Only I_e times the albedo is seen in the photos; with an estimated flash the albedo is
    relative (:mod:`recon.optimize.radiometry`) and this puts it in the truth's units (1 when
    the flash was given).

    Returns ``{"diffuse": ..., "specular": ..., "roughness": ..., "fraction": f, "samples": n,
    "albedo_gauge": g}`` (map values in [0, 1], linear); the RMSEs are None when no sample is
    close enough.
    """
    rng = np.random.default_rng(seed)
    p_gt, uv_gt = sample_surface_uv(ground_truth.mesh, n_samples, rng)
    rec_mesh = Mesh(similarity.apply(reconstruction.mesh.v_pos), reconstruction.mesh.t_pos_idx,
                    reconstruction.mesh.v_tex, reconstruction.mesh.t_tex_idx)
    dist, uv_rec = closest_uv(rec_mesh, p_gt)
    near = dist / unit <= max_distance
    out: dict = {"samples": int(n_samples), "fraction": float(near.mean()),
                 "max_distance": float(max_distance), "albedo_gauge": float(albedo_gauge)}
    for key in ("diffuse", "specular", "roughness"):
        if not near.any():
            out[key] = None
            continue
        a = sample_map(getattr(ground_truth, key), uv_gt[near])
        b = sample_map(getattr(reconstruction, key), uv_rec[near])
        if key != "roughness":
            b = b * float(albedo_gauge)
        if a.shape[1] != b.shape[1]:  # one channel against RGB: compare RGB
            a, b = np.broadcast_to(a, (len(a), 3)), np.broadcast_to(b, (len(b), 3))
        out[key] = float(np.sqrt(np.mean((a - b) ** 2)))
    return out


# ---- Alignment ----
def alignment(estimated: CameraSet, true: CameraSet):
    """(similarity estimated -> true frame, how it was found)."""

    try:
        return align_cameras(estimated, true), "umeyama on camera centers"
    except MetricsError as e:
        log.warning("no camera alignment (%s); the reconstruction is taken to be in the "
                    "ground-truth frame", e)
        return Similarity.identity(), f"identity ({e})"


def image_views(estimated: CameraSet, true: CameraSet, max_views: int) -> tuple[list[Camera], bool]:
    """True cameras to compare images in: the held-out ones when there are any, else all;
    at most ``max_views`` (evenly spread, 0 = all). Returns (cameras, held_out)."""
    seen = set(estimated.by_stem())
    held = [c for c in true.frames if c.stem not in seen]
    cams = held if held else list(true.frames)
    if max_views and len(cams) > max_views:
        idx = np.round(np.linspace(0, len(cams) - 1, max_views)).astype(int)
        cams = [cams[i] for i in idx]
    return cams, bool(held)
