"""Camera refinement: per-view pose and shared intrinsics corrections around given cameras.

Cameras from structure from motion carry residual errors (tenths of a degree, ~1 % of the
object in centre) that put a floor under the geometry; the renderer's images are
differentiable with respect to the cameras (``camera_table`` of
:meth:`recon.render.CollocatedRenderer.render_torch`), so the cameras can be optimized with the
surface, as bundle-adjusting neural-field methods (BARF and its successors) do.

Parameterization (minimal, zero = the given cameras):

- per view ``w`` (3): rotation vector in the camera frame, ``R' = exp([w]x) R``;
- per view ``d`` (3): translation in the camera frame, ``t' = exp([w]x) t + d``
  (so ``d`` is the shift of the world origin as the camera sees it, in scene units);
- shared ``log_f`` (1): ``fx' = fx e^log_f``, ``fy' = fy e^log_f``;
- shared ``pp`` (2): principal point shift in units of the image width / height
  (``cx' = cx + pp_x W``, ``cy' = cy + pp_y H``), so every image size reads the same values.

Gauge: a similarity of the whole scene (7 degrees of freedom: rotation, translation, scale)
moved together with all cameras leaves every image unchanged, so the pose corrections have a
7-dimensional null space that the priors alone would only damp. After every optimizer step
:meth:`CameraRefinement.fix_gauge` projects the pose corrections onto the orthogonal
complement of that null space (computed at the given cameras, to first order): the mean camera
motion and the cameras' overall scale stay those of the input, and so does the object frame.
Views aligned to a fixed scene (the held-out views after the optimization,
:func:`recon.optimize.cameras.align_heldout`) have no gauge: ``gauge=False``.

Observability (``docs/camera_refine.md``): at ordinary fields of view a focal length error and
the object scaled by the same factor give nearly the same images (perspective is the only cue),
as do a small rotation and a sideways shift of one camera (parallax is the only cue); the
refinement removes what the images see (the reprojection error) and its prior holds the rest.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from recon.io.cameras import Camera
from recon.render.torch_bridge import camera_table_torch

POSE_DIM = 6  # w (3) + d (3) per view


@dataclass(frozen=True)
class CameraPrior:
    """Gaussian priors on the corrections (standard deviations) and their learning rates.

    ``sigma_rotation_deg`` and ``sigma_translation`` (a fraction of the scene size: the mean
    distance of the cameras to their centroid) keep the poses near the input; ``sigma_focal``
    (relative) and ``sigma_principal`` (fraction of the image size) the intrinsics.
    """

    sigma_rotation_deg: float = 0.5
    sigma_translation: float = 0.01
    sigma_focal: float = 0.02
    sigma_principal: float = 0.01
    lr_rotation_deg: float = 0.02
    lr_translation: float = 0.0005
    lr_focal: float = 0.0005
    lr_principal: float = 0.0002

    def __post_init__(self):
        for k, v in self.__dict__.items():
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v > 0):
                raise ValueError(f"camera prior {k} must be a positive number, got {v!r}")


def scene_extent(cameras: Sequence[Camera]) -> float:
    """The scene size the translation units refer to: the mean distance of the camera centres
    from their centroid (1 when they coincide)."""
    centers = np.stack([c.center for c in cameras])
    return float(np.mean(np.linalg.norm(centers - centers.mean(0), axis=1))) or 1.0


def _skew(w: torch.Tensor) -> torch.Tensor:
    """(..., 3) -> (..., 3, 3) cross-product matrices."""
    z = torch.zeros_like(w[..., 0])
    return torch.stack([torch.stack([z, -w[..., 2], w[..., 1]], -1),
                        torch.stack([w[..., 2], z, -w[..., 0]], -1),
                        torch.stack([-w[..., 1], w[..., 0], z], -1)], -2)


def rotation_exp(w: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula for (..., 3) rotation vectors, smooth and finite at 0."""
    theta2 = (w * w).sum(-1, keepdim=True)[..., None]
    theta = torch.sqrt(theta2 + 1e-30)
    small = theta2 < 1e-8
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / torch.where(small, 1.0, theta2))
    K = _skew(w)
    eye = torch.eye(3, dtype=w.dtype).expand(K.shape)
    return eye + a * K + b * (K @ K)


def rotation_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector of a rotation matrix (angles below pi)."""
    c = np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)
    theta = np.arccos(c)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if theta < 1e-8:
        return v / 2
    return v * theta / (2 * np.sin(theta))


class CameraRefinement(torch.nn.Module):
    """Corrections for ``cameras`` (the training views, in order); see the module docstring."""

    def __init__(self, cameras: Sequence[Camera], prior: CameraPrior = CameraPrior(), intrinsics: bool = True,
                 gauge: bool = True, scene_size: float | None = None):
        super().__init__()
        self.base = list(cameras)
        self.gauge = bool(gauge)
        if self.gauge and len(self.base) < 3:
            raise ValueError(f"camera refinement needs at least 3 views, got {len(self.base)}")
        if not self.base:
            raise ValueError("camera refinement needs at least one view")
        n = len(self.base)
        self.prior = prior
        self.refine_intrinsics = bool(intrinsics)
        self.rotation = torch.nn.Parameter(torch.zeros(n, 3, dtype=torch.float64))
        self.translation = torch.nn.Parameter(torch.zeros(n, 3, dtype=torch.float64))
        self.log_focal = torch.nn.Parameter(torch.zeros(1, dtype=torch.float64), requires_grad=self.refine_intrinsics)
        self.principal = torch.nn.Parameter(torch.zeros(2, dtype=torch.float64), requires_grad=self.refine_intrinsics)
        if scene_size is not None:
            if not (np.isfinite(scene_size) and scene_size > 0):
                raise ValueError(f"scene_size must be a positive number, got {scene_size!r}")
            self.scene_size = float(scene_size)
        else:
            self.scene_size = scene_extent(self.base)
        self._R0 = torch.tensor(np.stack([c.world_to_camera[:3, :3] for c in self.base]), dtype=torch.float64)
        self._t0 = torch.tensor(np.stack([c.world_to_camera[:3, 3] for c in self.base]), dtype=torch.float64)
        self._gauge = torch.tensor(self._gauge_basis(), dtype=torch.float64) if self.gauge else None

    # ---- parameters -> cameras ----
    def param_groups(self) -> list[dict]:
        """Adam parameter groups with the prior's learning rates (scene units for translation)."""
        p = self.prior
        groups = [{"params": [self.rotation], "lr": np.deg2rad(p.lr_rotation_deg)},
                  {"params": [self.translation], "lr": p.lr_translation * self.scene_size}]
        if self.refine_intrinsics:
            groups += [{"params": [self.log_focal], "lr": p.lr_focal},
                       {"params": [self.principal], "lr": p.lr_principal}]
        return groups

    def matrices(self, idx: Sequence[int], cameras: Sequence[Camera]) -> tuple[torch.Tensor, torch.Tensor]:
        """Corrected (B, 3, 3) K and (B, 4, 4) world_to_camera of views ``idx``, with the
        intrinsics of ``cameras`` (the same views at the image size being fitted)."""
        idx_t = torch.as_tensor(np.asarray(idx, dtype=np.int64))
        E = rotation_exp(self.rotation[idx_t])
        R = E @ self._R0[idx_t]
        t = (E @ self._t0[idx_t][..., None])[..., 0] + self.translation[idx_t]
        bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64).expand(len(idx_t), 1, 4)
        w2c = torch.cat([torch.cat([R, t[..., None]], -1), bottom], 1)
        K0 = torch.tensor(np.stack([c.K for c in cameras]), dtype=torch.float64)
        size = torch.tensor([[c.width, c.height] for c in cameras], dtype=torch.float64)
        f = torch.exp(self.log_focal)
        K = torch.stack([
            torch.stack([K0[:, 0, 0] * f, K0[:, 0, 1] * f, K0[:, 0, 2] + self.principal[0] * size[:, 0]], -1),
            torch.stack([K0[:, 1, 0], K0[:, 1, 1] * f, K0[:, 1, 2] + self.principal[1] * size[:, 1]], -1),
            K0[:, 2],
        ], 1)
        return K, w2c

    def cameras(self, idx: Sequence[int], cameras: Sequence[Camera]) -> list[Camera]:
        """The corrected cameras (detached), e.g. for silhouette sets and outputs."""
        with torch.no_grad():
            K, w2c = self.matrices(idx, cameras)
        return [Camera(c.image, c.width, c.height, K[i].numpy(), w2c[i].numpy()) for i, c in enumerate(cameras)]

    def table(self, idx: Sequence[int], cameras: Sequence[Camera]) -> torch.Tensor:
        """(B, 24) float32 camera table of views ``idx`` for the renderer, differentiable."""
        K, w2c = self.matrices(idx, cameras)
        return camera_table_torch(K, w2c).to(torch.float32)

    def with_intrinsics(self, cameras: Sequence[Camera]) -> list[Camera]:
        """``cameras`` (any views, any image size) with the refined shared intrinsics, poses
        unchanged: e.g. views held out of the refinement."""
        f = float(torch.exp(self.log_focal.detach())[0])
        px, py = (float(x) for x in self.principal.detach())
        out = []
        for c in cameras:
            K = np.array(c.K, dtype=np.float64)
            K[0, :2] *= f
            K[1, 1] *= f
            K[0, 2] += px * c.width
            K[1, 2] += py * c.height
            out.append(Camera(c.image, c.width, c.height, K, np.array(c.world_to_camera, dtype=np.float64)))
        return out

    # ---- prior and gauge ----
    def prior_loss(self, idx: Sequence[int] | None = None) -> torch.Tensor:
        """Mean squared corrections over their prior standard deviations (a Gaussian's -log,
        up to 1/2 and a constant), per view for the poses: over the views ``idx`` (None = all),
        so that a view outside a batch is not pulled back by the prior alone."""
        p = self.prior
        rot, tra = self.rotation, self.translation
        if idx is not None:
            idx_t = torch.as_tensor(np.asarray(idx, dtype=np.int64))
            rot, tra = rot[idx_t], tra[idx_t]
        loss = ((rot / np.deg2rad(p.sigma_rotation_deg)) ** 2).sum(-1).mean()
        loss = loss + ((tra / (p.sigma_translation * self.scene_size)) ** 2).sum(-1).mean()
        if self.refine_intrinsics:
            loss = loss + (self.log_focal[0] / p.sigma_focal) ** 2 + ((self.principal / p.sigma_principal) ** 2).sum()
        return loss

    def _gauge_basis(self) -> np.ndarray:
        """(6N, 7) orthonormal basis of the pose corrections that move all cameras by one
        similarity of the world (first order, by central differences of the exact motion)."""
        n = len(self.base)
        R0 = [c.world_to_camera[:3, :3] for c in self.base]
        t0 = [c.world_to_camera[:3, 3] for c in self.base]
        eps = 1e-6
        cols = []
        for g in range(7):
            out = []
            for sgn in (1.0, -1.0):
                w = np.zeros(3)
                u = np.zeros(3)
                s = 1.0
                if g < 3:
                    w[g] = sgn * eps
                elif g < 6:
                    u[g - 3] = sgn * eps * self.scene_size
                else:
                    s = 1.0 + sgn * eps
                Q = rotation_exp(torch.tensor(w)).numpy()
                x = np.zeros((n, POSE_DIM))
                for i in range(n):
                    # world x -> s Q x + u; camera i sees the same image with R' = R Q^T,
                    # t' = s t - R Q^T u (camera coordinates scaled by s)
                    R1 = R0[i] @ Q.T
                    t1 = s * t0[i] - R1 @ u
                    wi = rotation_log(R1 @ R0[i].T)
                    Ei = rotation_exp(torch.tensor(wi)).numpy()
                    x[i, :3] = wi
                    x[i, 3:] = t1 - Ei @ t0[i]
                out.append(x.reshape(-1))
            cols.append((out[0] - out[1]) / (2 * eps))
        q, _ = np.linalg.qr(np.stack(cols, 1))
        return q

    @torch.no_grad()
    def fix_gauge(self) -> None:
        """Project the pose corrections onto the complement of the similarity gauge (nothing
        to do without a gauge: views aligned to a fixed scene)."""
        if self._gauge is None:
            return
        x = torch.cat([self.rotation, self.translation], 1).reshape(-1)
        x = x - self._gauge @ (self._gauge.T @ x)
        x = x.reshape(-1, POSE_DIM)
        self.rotation.copy_(x[:, :3])
        self.translation.copy_(x[:, 3:])

    # ---- reporting ----
    @torch.no_grad()
    def corrections(self, object_size: float | None = None, cameras: Sequence[Camera] | None = None) -> dict:
        """Per view rotation (degrees) and centre shift (fraction of the scene size, and of
        ``object_size`` when given: ``center_shift_object``); the intrinsics scale and shift,
        and the first view's intrinsics before and after in the pixels of ``cameras`` (the
        same views at another image size, e.g. the photos'; default: the base cameras')."""
        _, w2c = self.matrices(range(len(self.base)), self.base)
        ref = list(cameras) if cameras is not None else self.base
        if len(ref) != len(self.base):
            raise ValueError(f"corrections: {len(ref)} cameras for {len(self.base)} views")
        K_ref, _ = self.matrices(range(len(ref)), ref)
        views = {}
        for i, c in enumerate(self.base):
            R, t = w2c[i, :3, :3].numpy(), w2c[i, :3, 3].numpy()
            center = -R.T @ t
            shift = float(np.linalg.norm(center - c.center))
            views[c.stem] = {
                "rotation_deg": float(np.rad2deg(np.linalg.norm(self.rotation[i].numpy()))),
                "center_shift": shift / self.scene_size,
            }
            if object_size:
                views[c.stem]["center_shift_object"] = shift / float(object_size)
        rot = [v["rotation_deg"] for v in views.values()]
        shift = [v["center_shift"] for v in views.values()]
        extra = {}
        if object_size:
            so = [v["center_shift_object"] for v in views.values()]
            extra = {"mean_center_shift_object": float(np.mean(so)), "max_center_shift_object": float(np.max(so)),
                     "object_size": float(object_size)}
        return {
            "views": views,
            "mean_rotation_deg": float(np.mean(rot)), "max_rotation_deg": float(np.max(rot)),
            "mean_center_shift": float(np.mean(shift)), "max_center_shift": float(np.max(shift)),
            "scene_size": self.scene_size, **extra,
            "focal_scale": float(torch.exp(self.log_focal)[0]),
            "principal_shift": [float(x) for x in self.principal],
            "intrinsics_before": {"fx": float(ref[0].K[0, 0]), "fy": float(ref[0].K[1, 1]),
                                  "cx": float(ref[0].K[0, 2]), "cy": float(ref[0].K[1, 2]),
                                  "width": int(ref[0].width), "height": int(ref[0].height)},
            "intrinsics_after": {"fx": float(K_ref[0, 0, 0]), "fy": float(K_ref[0, 1, 1]),
                                 "cx": float(K_ref[0, 0, 2]), "cy": float(K_ref[0, 1, 2]),
                                 "width": int(ref[0].width), "height": int(ref[0].height)},
        }
