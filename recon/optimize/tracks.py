"""SfM's feature tracks as a second term of the camera refinement (a bundle adjustment with the
renderer's residuals).

The renderer's alignment of one view resolves what moves the object's image: a small rotation
of a camera and a sideways shift of its centre differ only by parallax, which an object alone
shows little of, so the per-view photometric alignment removes 30-40 % of SfM's sub-pixel
errors even against the exact model (docs/camera_refine.md). SfM's tracks tie the views to one
another through many points at many depths; reprojected through the refined cameras they keep
the views' joint geometry while the renderer moves them.

:class:`SfmTracks` reads the poses stage's sparse model (``poses/sparse``, COLMAP's frame and
its distorted photos' pixels) and brings it into the frame and the pinhole pixels of
``cameras.json`` (``colmap_to_object``; keypoints through COLMAP's camera model to rays and
back through the pinhole intrinsics). :class:`TrackTerm` holds the 3D points as parameters
(initialised at SfM's) and gives the mean robust reprojection cost of the observations of a
set of views through :meth:`recon.optimize.camera_refine.CameraRefinement.matrices`:
``rho(|r| / sigma)`` with Huber's ``rho`` (quadratic to ``huber`` sigmas, linear beyond), ``sigma``
SfM's own mean reprojection error (at least ``min_sigma_px``), so one unit of the term is one
observation at SfM's typical residual.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from recon.io.cameras import Camera, CameraSet


class TrackError(ValueError):
    """The sparse model is missing or does not fit the cameras (names the file and the fix)."""


@dataclass(frozen=True)
class SfmTracks:
    """Observations of SfM's 3D points in a list of views (in the order of ``stems``).

    ``points`` (P, 3) in the object frame of ``cameras.json``; ``view``, ``point`` (M,) indices;
    ``uv`` (M, 2) the keypoints in the pinhole pixels of the photos (``cameras.json``'s K);
    ``sigma_px`` SfM's mean reprojection error."""

    stems: tuple[str, ...]
    points: np.ndarray
    view: np.ndarray
    point: np.ndarray
    uv: np.ndarray
    sigma_px: float

    @property
    def n_observations(self) -> int:
        return len(self.view)

    @classmethod
    def load(cls, sparse_dir: str | Path, cams: CameraSet, stems: Sequence[str], min_views: int = 3) -> SfmTracks:
        """The tracks of ``sparse_dir`` (COLMAP's binary model) seen by views ``stems`` of
        ``cams`` (the poses stage's ``cameras.json``: its ``colmap_to_object`` maps COLMAP's
        frame to the cameras'); points seen by fewer than ``min_views`` of those views are left
        out (two views fix a point's depth only along one baseline)."""
        import pycolmap

        from recon.poses.undistort import keypoints_to_pinhole

        sparse_dir = Path(sparse_dir)
        if not (sparse_dir / "points3D.bin").is_file():
            raise TrackError(f"{sparse_dir}: no COLMAP model (points3D.bin); rerun the poses stage")
        if "colmap_to_object" not in cams.extra:
            raise TrackError(f"{sparse_dir.parent / 'cameras.json'}: no colmap_to_object transform; "
                             "rerun the poses stage")
        M = np.asarray(cams.extra["colmap_to_object"], dtype=np.float64)
        rec = pycolmap.Reconstruction(str(sparse_dir))
        by_stem = {c.stem: c for c in cams.frames}
        images = {Path(im.name).stem: im for im in rec.images.values() if im.has_pose}
        stems = tuple(stems)
        missing = [s for s in stems if s not in images or s not in by_stem]
        if missing:
            raise TrackError(f"{sparse_dir}: views {missing[:5]} are not in the sparse model or in cameras.json; "
                             "rerun the poses stage")
        view, pid, uv = [], [], []
        for k, s in enumerate(stems):
            im = images[s]
            obs = [(p.point3D_id, p.xy) for p in im.points2D if p.has_point3D()]
            if not obs:
                continue
            ids = np.array([o[0] for o in obs], dtype=np.int64)
            xy = np.array([o[1] for o in obs], dtype=np.float64)
            uv.append(keypoints_to_pinhole(rec.cameras[im.camera_id], xy, by_stem[s].K))
            view.append(np.full(len(ids), k, dtype=np.int64))
            pid.append(ids)
        if not view:
            raise TrackError(f"{sparse_dir}: none of the {len(stems)} views observes a 3D point; rerun the poses stage")
        view, pid, uv = np.concatenate(view), np.concatenate(pid), np.concatenate(uv)
        ok = np.all(np.isfinite(uv), axis=1)
        view, pid, uv = view[ok], pid[ok], uv[ok]
        ids, inverse, count = np.unique(pid, return_inverse=True, return_counts=True)
        # views per point (a point is seen once per view)
        keep_pt = count >= int(min_views)
        keep = keep_pt[inverse]
        ids = ids[keep_pt]
        remap = -np.ones(len(keep_pt), dtype=np.int64)
        remap[keep_pt] = np.arange(int(keep_pt.sum()))
        point = remap[inverse[keep]]
        xyz = np.array([rec.points3D[int(i)].xyz for i in ids], dtype=np.float64).reshape(-1, 3)
        xyz = xyz @ M[:3, :3].T + M[:3, 3]
        sigma = float(rec.compute_mean_reprojection_error()) if rec.num_points3D() else 1.0
        return cls(stems, xyz, view[keep], point, uv[keep], sigma)

    def reprojection(self, cameras: Sequence[Camera]) -> np.ndarray:
        """(M,) reprojection errors (pixels) of the observations through ``cameras`` (the views
        in the order of ``stems``, at the photos' size), SfM's points as they are."""
        from recon.optimize.camera_refine import CameraRefinement

        with torch.no_grad():
            return TrackTerm(self).residuals(CameraRefinement(cameras, gauge=False), cameras).numpy()


class TrackTerm(torch.nn.Module):
    """Reprojection cost of ``tracks`` through a :class:`CameraRefinement` (see the module
    docstring); the 3D points are parameters of their own."""

    def __init__(self, tracks: SfmTracks, min_sigma_px: float = 0.25, huber: float = 3.0):
        super().__init__()
        if not (np.isfinite(min_sigma_px) and min_sigma_px > 0 and np.isfinite(huber) and huber > 0):
            raise ValueError(f"min_sigma_px and huber must be positive, got {min_sigma_px!r}, {huber!r}")
        self.tracks = tracks
        self.sigma_px = max(float(tracks.sigma_px), float(min_sigma_px))
        self.huber = float(huber)
        self.points = torch.nn.Parameter(torch.tensor(tracks.points, dtype=torch.float64))
        self._view = torch.as_tensor(tracks.view)
        self._point = torch.as_tensor(tracks.point)
        self._uv = torch.tensor(tracks.uv, dtype=torch.float64)

    def residuals(self, refinement, cameras: Sequence[Camera]) -> torch.Tensor:
        """(M,) reprojection errors in pixels through the refined ``cameras`` (every view of
        the refinement, in its order, at the photos' size); 0 for a point behind its camera."""
        K, w2c = refinement.matrices(range(len(cameras)), cameras)
        K, w2c = K[self._view], w2c[self._view]
        X = self.points[self._point]
        x = (w2c[:, :3, :3] @ X[..., None])[..., 0] + w2c[:, :3, 3]
        p = (K @ x[..., None])[..., 0]
        front = p[:, 2] > 1e-9 * torch.linalg.norm(x, dim=-1)  # points behind a camera: no residual (cheirality)
        z = torch.where(front, p[:, 2], torch.ones_like(p[:, 2]))[:, None]
        r = torch.sqrt(((p[:, :2] / z - self._uv) ** 2).sum(-1) + 1e-24)
        return torch.where(front, r, torch.zeros_like(r))

    @torch.no_grad()
    def retriangulate(self, refinement, cameras: Sequence[Camera], iterations: int = 2) -> None:
        """Move every point to its least-squares position under the current cameras (Gauss-Newton,
        ``iterations`` steps of a 3 x 3 system per point; Huber-weighted as :meth:`loss`): the
        term is then the cost of the cameras with the points eliminated (variable projection),
        whose gradient with respect to the cameras is the partial one at the optimal points."""
        K, w2c = refinement.matrices(range(len(cameras)), cameras)
        K, w2c = K[self._view], w2c[self._view]
        P = K @ w2c[:, :3, :]  # (M, 3, 4) projection matrices
        A, b = P[:, :, :3], P[:, :, 3]
        n = len(self.points)
        for _ in range(int(iterations)):
            X = self.points[self._point]
            p = (A @ X[..., None])[..., 0] + b
            front = (p[:, 2] > 1e-9 * torch.linalg.norm(p, dim=-1))[:, None]
            z = torch.where(front, p[:, 2:3], torch.ones_like(p[:, 2:3]))
            r = torch.where(front, p[:, :2] / z - self._uv, torch.zeros_like(p[:, :2]))  # (M, 2)
            # d(p_xy / z)/dX = (A_xy - (p_xy / z) A_z) / z
            J = (A[:, :2, :] - (p[:, :2] / z)[..., None] * A[:, 2:3, :]) / z[..., None]  # (M, 2, 3)
            e = torch.sqrt((r * r).sum(-1)) / self.sigma_px
            wgt = torch.where(e <= self.huber, torch.ones_like(e), self.huber / e.clamp(min=1e-12)) * front[:, 0]
            H = torch.zeros(n, 3, 3, dtype=torch.float64).index_add_(0, self._point, wgt[:, None, None] * J.transpose(1, 2) @ J)
            g = torch.zeros(n, 3, dtype=torch.float64).index_add_(0, self._point, wgt[:, None] * (J.transpose(1, 2) @ r[..., None])[..., 0])
            H = H + 1e-9 * H.diagonal(dim1=1, dim2=2).mean(-1).clamp(min=1e-30)[:, None, None] * torch.eye(3, dtype=torch.float64)
            step = torch.linalg.solve(H, -g[..., None])[..., 0]
            ok = torch.isfinite(step).all(-1, keepdim=True)
            self.points.add_(torch.where(ok, step, torch.zeros_like(step)))

    def loss(self, refinement, cameras: Sequence[Camera]) -> torch.Tensor:
        """Mean Huber cost over the observations: ``(r / sigma)^2`` up to ``huber`` sigmas,
        ``2 huber r / sigma - huber^2`` beyond."""
        r = self.residuals(refinement, cameras) / self.sigma_px
        h = self.huber
        return torch.where(r <= h, r * r, 2 * h * r - h * h).mean()
