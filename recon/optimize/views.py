"""Target views: photos, masks and clipped-pixel masks at a stage's resolution, and the loss.

A photo is paired with its camera by file stem. At a stage's resolution (longest side ``s``)
each photo is box-filtered (area averaging) after its background is set to zero by the mask,
so a border pixel holds the mask-weighted average like a rendered pixel that the silhouette
crosses; the clipped-pixel mask is max-pooled (a low-resolution pixel touched by any clipped
photo pixel is excluded). Cameras are scaled with :meth:`Camera.scaled`.

The rendering loss (eq. 6) compares ``Phi(render)`` with ``Phi(target)``: the same tone map on
both sides, the same background (zero: the target's background is masked to zero and the
renderer has nothing there), clipped pixels weighted zero on both sides. The render is not
multiplied by the mask, since that would hide where the surface spills over the silhouette.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from recon.io.cameras import Camera, CameraSet
from recon.io.images import ImageError, read_exr, read_mask

log = logging.getLogger(__name__)


class ViewsError(ValueError):
    """Input photos/masks that do not fit the cameras; the message names the file and the fix."""


def _resize_area(a: np.ndarray, w: int, h: int) -> np.ndarray:
    import cv2

    a = np.asarray(a, dtype=np.float32)
    if a.shape[1] == w and a.shape[0] == h:
        return a.copy()
    out = cv2.resize(a, (w, h), interpolation=cv2.INTER_AREA)
    return out.reshape(h, w, -1) if a.ndim == 3 else out


@dataclass
class ViewSet:
    """Targets at one resolution (N views of h x w).

    images : (N, h, w, 3) float32 torch, linear, background zero
    weights : (N, h, w, 1) float32 torch, 0 on clipped pixels, else 1
    masks : (N, h, w) float32 numpy, object coverage in [0, 1]
    cameras : tuple of N cameras at this resolution
    """

    images: torch.Tensor
    weights: torch.Tensor
    masks: np.ndarray
    cameras: tuple[Camera, ...]

    def __len__(self) -> int:
        return len(self.cameras)


class Views:
    """All target photos of a capture, kept at the largest resolution any stage needs."""

    def __init__(
        self,
        images: Sequence[str | os.PathLike],
        masks: Sequence[str | os.PathLike] | None,
        saturation_masks: Sequence[str | os.PathLike | None] | None,
        cameras: CameraSet,
        max_size: int,
        keep_photos: bool = True,
    ):
        """``keep_photos``: keep the unmasked photos too (:attr:`photos`, float16, for the foot
        zone's colour test; 47 MB at 40 views of 512 x 384); False leaves :attr:`photos` None."""
        images = [Path(p) for p in images]
        if not images:
            raise ViewsError("no input images were given to the optimize stage")
        n = len(images)
        if masks is not None and len(masks) != n:
            raise ViewsError(f"{len(masks)} masks for {n} images; give one mask per image (same stems)")
        if saturation_masks is not None and len(saturation_masks) != n:
            raise ViewsError(f"{len(saturation_masks)} saturation masks for {n} images; give one per image")
        by_stem = cameras.by_stem()
        self.stems, self.cameras, imgs, msks, sats, photos = [], [], [], [], [], []
        for k, path in enumerate(images):
            cam = by_stem.get(path.stem)
            if cam is None:
                raise ViewsError(f"{path}: no camera with image stem '{path.stem}' in cameras.json")
            if path.suffix.lower() != ".exr":
                raise ViewsError(f"{path}: the optimize stage reads linear .exr images (the linearize/poses outputs)")
            rgb = read_exr(path)[:, :, :3]
            if rgb.shape[2] != 3:
                raise ViewsError(f"{path}: expected an RGB image, got {rgb.shape[2]} channel(s)")
            H, W = rgb.shape[:2]
            if (W, H) != (cam.width, cam.height):
                raise ViewsError(
                    f"{path}: image is {W}x{H} but its camera says {cam.width}x{cam.height}; "
                    "pass the undistorted images that belong to poses/cameras.json"
                )
            if not np.all(np.isfinite(rgb)):
                raise ViewsError(f"{path}: contains NaN or Inf pixels")
            m = np.ones((H, W), np.float32) if masks is None else self._mask(masks[k], (H, W), "mask")
            s = (
                np.zeros((H, W), np.float32)
                if saturation_masks is None or saturation_masks[k] is None
                else self._mask(saturation_masks[k], (H, W), "saturation mask")
            )
            factor = min(1.0, max_size / max(W, H))
            c = cam.scaled(factor) if factor < 1 else cam
            imgs.append(_resize_area(rgb * m[:, :, None], c.width, c.height))
            if keep_photos:
                photos.append(_resize_area(rgb, c.width, c.height).astype(np.float16))
            msks.append(_resize_area(m, c.width, c.height))
            sats.append(_resize_area(s, c.width, c.height) > 0)
            self.stems.append(path.stem)
            self.cameras.append(c)
        sizes = {(c.width, c.height) for c in self.cameras}
        if len(sizes) != 1:
            raise ViewsError(f"all views must have the same size; got {sorted(sizes)}")
        self.images = np.stack(imgs)
        # unmasked, float16: the table beside the object (recon.optimize.foot)
        self.photos = np.stack(photos) if keep_photos else None
        self.masks = np.stack(msks)
        self.saturated = np.stack(sats)
        self.light_intensity = float(cameras.light_intensity)
        fg = self.images[(self.masks > 0.5) & ~self.saturated]
        self.median_foreground = float(np.median(fg)) if fg.size else 1.0
        if not self.median_foreground > 0:
            self.median_foreground = float(np.mean(self.images)) or 1.0

    @staticmethod
    def _mask(path, shape, what) -> np.ndarray:
        try:
            m = read_mask(path)
        except ImageError as e:
            raise ViewsError(f"{path}: cannot read the {what} ({e})") from e
        if m.shape != shape:
            raise ViewsError(f"{path}: {what} is {m.shape[1]}x{m.shape[0]}, its image {shape[1]}x{shape[0]}")
        return m.astype(np.float32)

    def __len__(self) -> int:
        return len(self.cameras)

    def subset(self, indices) -> "Views":
        """The views ``indices`` (in that order) as a new :class:`Views` (arrays copied; the tone
        scale ``median_foreground`` recomputed from them)."""
        idx = [int(i) for i in indices]
        if not idx:
            raise ViewsError("a subset of the views must hold at least one view")
        out = object.__new__(Views)
        out.stems = [self.stems[i] for i in idx]
        out.cameras = [self.cameras[i] for i in idx]
        out.images = self.images[idx].copy()
        out.photos = None if self.photos is None else self.photos[idx].copy()
        out.masks = self.masks[idx].copy()
        out.saturated = self.saturated[idx].copy()
        out.light_intensity = self.light_intensity
        fg = out.images[(out.masks > 0.5) & ~out.saturated]
        out.median_foreground = float(np.median(fg)) if fg.size else self.median_foreground
        if not out.median_foreground > 0:
            out.median_foreground = self.median_foreground
        return out

    def photos_at(self, size: int) -> np.ndarray:
        """(N, h, w, 3) float32: the photos unmasked, at the size :meth:`at` gives."""
        if self.photos is None:
            raise ViewsError("the unmasked photos were not kept (Views(..., keep_photos=False))")
        W, H = self.cameras[0].width, self.cameras[0].height
        factor = min(1.0, size / max(W, H))
        cams = [c.scaled(factor) if factor < 1 else c for c in self.cameras[:1]]
        w, h = cams[0].width, cams[0].height
        return np.stack([_resize_area(p.astype(np.float32), w, h) for p in self.photos])

    def at(self, size: int) -> ViewSet:
        """The targets with longest side ``size`` (or the stored size when that is smaller)."""
        W, H = self.cameras[0].width, self.cameras[0].height
        factor = min(1.0, size / max(W, H))
        cams = tuple(c.scaled(factor) if factor < 1 else c for c in self.cameras)
        w, h = cams[0].width, cams[0].height
        imgs = np.stack([_resize_area(im, w, h) for im in self.images])
        msks = np.stack([_resize_area(m, w, h) for m in self.masks])
        sats = np.stack([_resize_area(s.astype(np.float32), w, h) > 0 for s in self.saturated])
        weights = (~sats).astype(np.float32)[..., None]
        return ViewSet(torch.from_numpy(imgs), torch.from_numpy(weights), msks, cams)


def pixel_footprint(cameras, point) -> float:
    """World length one pixel spans at ``point``: the median over the views in front of it of
    depth / focal length (pixels); 0 when no view sees the point in front of it."""
    p = np.asarray(point, dtype=np.float64).reshape(3)
    vals = []
    for c in cameras:
        w2c = np.asarray(c.world_to_camera, dtype=np.float64)
        depth = float(w2c[2, :3] @ p + w2c[2, 3])
        K = np.asarray(c.K, dtype=np.float64)
        if depth > 0:
            vals.append(depth / np.sqrt(K[0, 0] * K[1, 1]))
    return float(np.median(vals)) if vals else 0.0


# ---------------------------------------------------------------------- what linearize recorded
def _linear_record(images) -> dict | None:
    """The linearize stage's ``linear.json`` of the photos ``images`` (beside them, or in
    ``linear/`` of the same results folder for ``poses/undistorted``); None when not found or
    unreadable."""
    if not images:
        return None
    d = Path(images[0]).parent
    for cand in (d / "linear.json", d.parent.parent / "linear" / "linear.json"):
        if cand.is_file():
            try:
                return json.loads(cand.read_text())
            except (OSError, ValueError):
                return None
    return None


def capture_is_ldr(images) -> bool | None:
    """Whether the linearize stage read JPEG/PNG photos (its ``linear.json`` beside the views, or
    in ``linear/`` of the same results folder for ``poses/undistorted``); None when not found."""
    info = _linear_record(images)
    if info is None:
        return None
    kinds = {v.get("kind") for v in info.get("images", {}).values() if isinstance(v, dict)}
    return kinds == {"ldr"} if kinds else None


def recorded_exposures(images) -> dict | None:
    """Image stem -> the exposure linearize divided out (h_k / h_ref = 1 / ``exposure_scale`` of
    its ``linear.json``, found as :func:`capture_is_ldr` finds it), or None when not found or
    every view was taken at the reference exposure. A phone's auto-exposure changes the recorded
    exposure from shot to shot, and its tone curve acts before linearize divides it out
    (:mod:`recon.optimize.formation`)."""
    info = _linear_record(images)
    if info is None:
        return None
    out = {}
    for stem, v in info.get("images", {}).items():
        sc = v.get("exposure_scale") if isinstance(v, dict) else None
        if isinstance(sc, (int, float)) and np.isfinite(sc) and sc > 0:
            out[str(stem)] = 1.0 / float(sc)
    return out if out and any(abs(e - 1.0) > 1e-9 for e in out.values()) else None


def view_exposures(cameras, exposure: dict | None) -> torch.Tensor | None:
    """(V,) recorded exposures of ``cameras`` (by image stem) relative to the reference, or None
    when none is given or all are 1 (the tone curve then acts on the linearized values as they are)."""
    if not exposure:
        return None
    e = np.array([float(exposure.get(getattr(c, "stem", None), 1.0)) for c in cameras], np.float64)
    if not np.all(np.isfinite(e) & (e > 0)):
        raise ValueError(f"recorded exposures must be finite and > 0, got {e}")
    return None if np.all(e == 1.0) else torch.tensor(e, dtype=torch.float32)
