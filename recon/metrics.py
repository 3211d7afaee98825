"""Metrics of DESIGN section 5: the same numbers in tests, the optimizer and the report.

- :func:`umeyama`: least-squares similarity ``dst ~ s R src + t`` (Umeyama 1991).
- :func:`align_cameras`: that similarity from estimated camera centers onto true ones.
- :func:`pose_errors`: per-view rotation (degrees) and center errors after alignment.
- :func:`chamfer`: accuracy (reconstruction -> ground truth), completeness (ground truth ->
  reconstruction) and their mean, from 100,000 area-uniform samples, in the ground-truth frame
  scaled so that the ground-truth bounding box has longest side 1.
- :func:`image_rmse`: RMSE of sRGB-encoded values in [0, 1] over the union of two masks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from recon.io.cameras import CameraSet
from recon.io.images import linear_to_srgb
from recon.io.mesh import Mesh

N_SAMPLES = 100_000


class MetricsError(ValueError):
    """Inputs that a metric cannot be computed from; the message says what was received."""


@dataclass(frozen=True)
class Similarity:
    """``x -> scale * rotation @ x + translation``; ``rotation`` (3, 3), ``translation`` (3,)."""

    scale: float
    rotation: np.ndarray
    translation: np.ndarray

    @staticmethod
    def identity() -> "Similarity":
        return Similarity(1.0, np.eye(3), np.zeros(3))

    @property
    def matrix(self) -> np.ndarray:
        """(4, 4) homogeneous matrix of the similarity."""
        M = np.eye(4)
        M[:3, :3] = self.scale * self.rotation
        M[:3, 3] = self.translation
        return M

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Map ``(n, 3)`` points."""
        p = np.asarray(points, dtype=np.float64)
        return self.scale * p @ self.rotation.T + self.translation

    def inverse(self) -> "Similarity":
        R = self.rotation.T
        return Similarity(1.0 / self.scale, R, -(R @ self.translation) / self.scale)

    def to_dict(self) -> dict:
        return {
            "scale": float(self.scale),
            "rotation": np.asarray(self.rotation, dtype=float).tolist(),
            "translation": np.asarray(self.translation, dtype=float).tolist(),
            "matrix": self.matrix.tolist(),
        }


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> Similarity:
    """Least-squares similarity mapping ``src`` onto ``dst`` (Umeyama, PAMI 1991).

    Parameters
    ----------
    src, dst : (n, 3) float
        Corresponding points, n >= 3 and not all on one line.
    with_scale : bool
        False fits a rigid transform (scale 1).

    Returns
    -------
    Similarity minimizing ``sum |dst_i - (s R src_i + t)|^2`` with ``det R = +1``.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise MetricsError(f"umeyama needs two (n, 3) arrays of the same shape, got {src.shape} and {dst.shape}")
    if len(src) < 3:
        raise MetricsError(f"umeyama needs at least 3 point pairs, got {len(src)}")
    if not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst))):
        raise MetricsError("umeyama: the points contain NaN or Inf")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    var_s = (xs**2).sum() / len(src)
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    if D[1] < 1e-12 * max(D[0], 1e-300):
        raise MetricsError("umeyama: the points are (nearly) collinear; the rotation is not determined")
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / var_s) if with_scale else 1.0
    t = mu_d - s * R @ mu_s
    return Similarity(s, R, t)


def _matched(est: CameraSet, true: CameraSet):
    e, t = est.by_stem(), true.by_stem()
    stems = sorted(set(e) & set(t))
    if len(stems) < 3:
        raise MetricsError(
            f"need at least 3 views present in both camera sets to align them, found {len(stems)} "
            f"(estimated: {sorted(e)[:5]}..., true: {sorted(t)[:5]}...)"
        )
    return stems, [e[s] for s in stems], [t[s] for s in stems]


def align_cameras(est: CameraSet, true: CameraSet, with_scale: bool = True) -> Similarity:
    """The similarity mapping estimated camera centers onto the true ones (views matched by stem)."""
    _, ce, ct = _matched(est, true)
    return umeyama(np.stack([c.center for c in ce]), np.stack([c.center for c in ct]), with_scale)


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of the rotation ``R`` (3, 3) in degrees, in [0, 180]."""
    c = (np.trace(R) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def pose_errors(est: CameraSet, true: CameraSet, similarity: Similarity | None = None) -> dict:
    """Rotation and center errors of ``est`` against ``true`` after a similarity.

    ``similarity`` maps the estimated frame to the true one; by default the Umeyama fit of the
    camera centers (:func:`align_cameras`). Returns a dict with ``stems``, per-view
    ``rotation_deg`` and ``center`` (true-frame units) lists, their means and maxima, and the
    similarity used.
    """
    stems, ce, ct = _matched(est, true)
    sim = similarity if similarity is not None else align_cameras(est, true)
    rot, cen = [], []
    for a, b in zip(ce, ct, strict=True):
        # camera-to-world rotation of the estimate, expressed in the true frame
        R_est = sim.rotation @ a.camera_to_world[:3, :3]
        rot.append(rotation_angle_deg(b.camera_to_world[:3, :3].T @ R_est))
        cen.append(float(np.linalg.norm(sim.apply(a.center[None])[0] - b.center)))
    return {
        "stems": stems,
        "rotation_deg": rot,
        "center": cen,
        "mean_rotation_deg": float(np.mean(rot)),
        "max_rotation_deg": float(np.max(rot)),
        "mean_center": float(np.mean(cen)),
        "max_center": float(np.max(cen)),
        "similarity": sim.to_dict(),
    }


def distance_to_mesh(mesh: Mesh, points: np.ndarray) -> np.ndarray:
    """(N,) unsigned distance of each point ``(N, 3)`` to the closest point of the mesh's surface."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(mesh.v_pos.astype(np.float32)), o3d.core.Tensor(mesh.t_pos_idx.astype(np.uint32))
    )
    d = scene.compute_distance(o3d.core.Tensor(points.astype(np.float32)))
    return d.numpy().astype(np.float64)


def chamfer(
    reconstruction: Mesh,
    ground_truth: Mesh,
    similarity: Similarity | None = None,
    n_samples: int = N_SAMPLES,
    seed: int = 0,
) -> dict:
    """Accuracy, completeness and chamfer distance (DESIGN section 5).

    ``similarity`` first maps the reconstruction into the ground-truth frame (e.g. from
    :func:`align_cameras` when poses came from SfM). Distances are divided by the longest side
    of the ground truth's bounding box.

    Returns
    -------
    dict with ``accuracy`` (mean distance of reconstruction samples to the ground truth),
    ``completeness`` (ground-truth samples to the reconstruction), ``chamfer`` (their mean)
    and ``unit`` (the ground-truth bbox side the distances were divided by).
    """
    for name, m in (("reconstruction", reconstruction), ("ground truth", ground_truth)):
        if len(m.t_pos_idx) == 0 or m.area() <= 0:
            raise MetricsError(f"chamfer: the {name} mesh has no area ({len(m.t_pos_idx)} faces)")
        if not np.all(np.isfinite(m.v_pos)):
            raise MetricsError(f"chamfer: the {name} mesh has NaN or Inf vertices")
    rec = reconstruction
    if similarity is not None:
        rec = Mesh(similarity.apply(rec.v_pos), rec.t_pos_idx)
    lo, hi = ground_truth.bbox()
    unit = float(np.max(hi - lo))
    if unit <= 0:
        raise MetricsError("chamfer: the ground-truth mesh has an empty bounding box")
    rng = np.random.default_rng(seed)
    p_rec = rec.sample_surface(n_samples, rng)
    p_gt = ground_truth.sample_surface(n_samples, rng)
    acc = float(distance_to_mesh(ground_truth, p_rec).mean() / unit)
    comp = float(distance_to_mesh(rec, p_gt).mean() / unit)
    return {"accuracy": acc, "completeness": comp, "chamfer": 0.5 * (acc + comp), "unit": unit}


def seen_by(points: np.ndarray, mesh: Mesh, cameras: CameraSet) -> np.ndarray:
    """(N,) bool: which ``points`` on (or within 0.1 % of the bounding box from) the surface of
    ``mesh`` some camera sees: in front of it, inside its image, and nothing of ``mesh``
    between (a point on a table-standing object's underside or in a closed cavity: False)."""
    import open3d as o3d

    p = np.asarray(points, dtype=np.float64)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.v_pos.astype(np.float32)),
                        o3d.core.Tensor(mesh.t_pos_idx.astype(np.uint32)))
    lo, hi = mesh.bbox()
    eps = 1e-3 * float(np.max(hi - lo))
    seen = np.zeros(len(p), bool)
    for c in cameras.frames:
        uv, z = c.project(p)
        todo = ~seen & (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < c.width) & (uv[:, 1] >= 0) & (uv[:, 1] < c.height)
        if not todo.any():
            continue
        d = p[todo] - c.center
        dist = np.linalg.norm(d, axis=1)
        rays = np.concatenate([np.broadcast_to(c.center, d.shape), d / np.maximum(dist, 1e-300)[:, None]], 1)
        t = scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy()
        seen[np.flatnonzero(todo)[t >= dist - eps]] = True
    return seen


def seen_chamfer(reconstruction: Mesh, ground_truth: Mesh, cameras: CameraSet, similarity: Similarity | None = None,
                 n_samples: int = N_SAMPLES, seed: int = 0) -> dict:
    """Accuracy and completeness over the part of the ground truth that ``cameras`` (true frame)
    see: ``accuracy_seen`` (reconstruction samples whose closest ground-truth point is seen),
    ``completeness_seen`` (seen ground-truth samples to the reconstruction) and ``seen_fraction``
    (of the ground truth's area). Views from above an object on a table never see its underside,
    whose reconstruction is a guess no photo can correct and which otherwise dominates the
    whole-surface mean of :func:`chamfer` (DESIGN section 5's numbers, kept as they are)."""
    import open3d as o3d

    rec = reconstruction if similarity is None else Mesh(similarity.apply(reconstruction.v_pos),
                                                         reconstruction.t_pos_idx)
    lo, hi = ground_truth.bbox()
    unit = float(np.max(hi - lo))
    rng = np.random.default_rng(seed)
    p_rec = rec.sample_surface(n_samples, rng)
    p_gt = ground_truth.sample_surface(n_samples, rng)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(ground_truth.v_pos.astype(np.float32)),
                        o3d.core.Tensor(ground_truth.t_pos_idx.astype(np.uint32)))
    q = scene.compute_closest_points(o3d.core.Tensor(p_rec.astype(np.float32)))["points"].numpy().astype(np.float64)
    keep = seen_by(q, ground_truth, cameras)
    gt_seen = seen_by(p_gt, ground_truth, cameras)
    if not keep.any() or not gt_seen.any():
        raise MetricsError("seen_chamfer: no camera sees the ground truth")
    return {"accuracy_seen": float(np.linalg.norm(p_rec[keep] - q[keep], axis=1).mean() / unit),
            "completeness_seen": float(distance_to_mesh(rec, p_gt[gt_seen]).mean() / unit),
            "seen_fraction": float(gt_seen.mean())}


def image_rmse(
    rgb_linear_a: np.ndarray,
    rgb_linear_b: np.ndarray,
    mask_a: np.ndarray,
    mask_b: np.ndarray,
) -> float:
    """RMSE of sRGB-encoded values in [0, 1] over the union of two foreground masks.

    Parameters
    ----------
    rgb_linear_a, rgb_linear_b : (H, W, C) float
        Linear images (encoded and clipped to [0, 1] here).
    mask_a, mask_b : (H, W) bool
        Foreground masks; the RMSE runs over all channels of pixels in either mask.
    """
    a = np.asarray(rgb_linear_a, dtype=np.float32)
    b = np.asarray(rgb_linear_b, dtype=np.float32)
    if a.shape != b.shape or a.ndim != 3:
        raise MetricsError(f"image_rmse needs two (H, W, C) images of one shape, got {a.shape} and {b.shape}")
    ma, mb = np.asarray(mask_a, dtype=bool), np.asarray(mask_b, dtype=bool)
    if ma.shape != a.shape[:2] or mb.shape != a.shape[:2]:
        raise MetricsError(f"image_rmse: masks {ma.shape}, {mb.shape} do not match the images {a.shape[:2]}")
    union = ma | mb
    if not union.any():
        raise MetricsError("image_rmse: both masks are empty")
    if not (np.all(np.isfinite(a[union])) and np.all(np.isfinite(b[union]))):
        raise MetricsError("image_rmse: an image has NaN or Inf inside the masks")
    d = linear_to_srgb(a) - linear_to_srgb(b)
    return float(np.sqrt(np.mean(d[union] ** 2)))


def mask_agreement(mesh: Mesh, cams: CameraSet, masks: dict[str, np.ndarray], max_side: int = 400) -> dict:
    """How well ``mesh``'s silhouettes match the masks: per view the IoU of the pixels whose
    center ray hits the mesh and the mask's pixels (open3d ray casting, on every s-th pixel for
    images larger than ``max_side``).

    Returns ``{"mean", "min", "worst": [[stem, iou], ...] (the 3 lowest), "per_view": {stem: iou}}``;
    views the vote outvoted show up among the worst.
    """
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.v_pos.astype(np.float32)),
                        o3d.core.Tensor(mesh.t_pos_idx.astype(np.uint32)))
    per_view = {}
    for cam in cams:
        mask = masks.get(cam.stem)
        if mask is None:
            continue
        stride = max(1, int(np.ceil(max(cam.width, cam.height) / max_side)))
        rows = np.arange(stride // 2, cam.height, stride)
        cols = np.arange(stride // 2, cam.width, stride)
        j, i = np.meshgrid(cols + 0.5, rows + 0.5)
        d_cam = np.stack([j, i, np.ones_like(j)], -1).reshape(-1, 3) @ np.linalg.inv(cam.K).T
        c2w = cam.camera_to_world
        d_world = d_cam @ c2w[:3, :3].T
        rays = np.concatenate([np.broadcast_to(c2w[:3, 3], d_world.shape), d_world], 1).astype(np.float32)
        hit = np.isfinite(scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy())
        m = mask[np.ix_(rows, cols)].reshape(-1).astype(bool)
        union = int((hit | m).sum())
        per_view[cam.stem] = float((hit & m).sum() / union) if union else 1.0
    if not per_view:
        return {"mean": None, "min": None, "worst": [], "per_view": {}}
    worst = sorted(per_view.items(), key=lambda kv: kv[1])[:3]
    values = np.array(list(per_view.values()))
    return {"mean": float(values.mean()), "min": float(values.min()), "worst": [[k, v] for k, v in worst],
            "per_view": per_view}
