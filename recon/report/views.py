"""Per-view comparison: input photo, re-render of the optimized model, error map, RMSE.

The re-render is the project's forward reference
(:func:`recon.render.mitsuba_bsdf.render_reference`: Mitsuba with the ``recon_svbrdf`` plugin,
point light at the camera center, box pixel filter), from the view's camera at the report's
resolution (longest side at most ``max_size``; the input is area-averaged to the same size).

RMSE (DESIGN section 5, :func:`recon.metrics.image_rmse`): sRGB-encoded values clipped to
[0, 1], over the union of the input's mask and the re-render's coverage (pixels whose center
ray hits the mesh), leaving out clipped input pixels (``<stem>.sat.png`` beside the image)
when that file exists. The error map shows, per pixel, the RMS over the colour channels of the
same sRGB difference, on a fixed colour scale [0, ``vmax``], dark grey outside the union.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from recon.io.cameras import Camera
from recon.io.images import ImageError, linear_to_srgb, read_exr, read_mask
from recon.io.mesh import Mesh
from recon.report.inputs import ReportError
from recon.metrics import MetricsError, image_rmse
from recon.render.mitsuba_bsdf import render_reference
from recon.io.images import write_jpg

log = logging.getLogger(__name__)

ERROR_COLORMAP = "inferno"
OUTSIDE_GREY = 0.12
"""Display value of error-map pixels outside the union of the masks."""


# ---- Geometry helpers ----
def pixel_rays(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Rays through the pixel centers (j + 0.5, i + 0.5): origins and unit directions,
    both (H, W, 3) float64 in world coordinates."""
    j, i = np.meshgrid(np.arange(camera.width) + 0.5, np.arange(camera.height) + 0.5)
    pix = np.stack([j, i, np.ones_like(j)], axis=-1)
    d_cam = pix @ np.linalg.inv(camera.K).T
    R = camera.world_to_camera[:3, :3]
    d = d_cam @ R  # R^T d for each row vector
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    o = np.broadcast_to(camera.center, d.shape)
    return o, d


def coverage_mask(mesh: Mesh, camera: Camera) -> np.ndarray:
    """(H, W) bool: pixels whose center ray from the camera hits ``mesh``."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.v_pos.astype(np.float32)),
                        o3d.core.Tensor(mesh.t_pos_idx.astype(np.uint32)))
    o, d = pixel_rays(camera)
    rays = np.concatenate([o, d], axis=-1).astype(np.float32).reshape(-1, 6)
    t_hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    return np.isfinite(t_hit).reshape(camera.height, camera.width)


def fit_camera(camera: Camera, height: int, width: int, source: str) -> Camera:
    """``camera`` for an image of ``height`` x ``width`` pixels (the same view, resized)."""
    if (height, width) == (camera.height, camera.width):
        return camera
    fx, fy = width / camera.width, height / camera.height
    if abs(fx - fy) > 0.01 * max(fx, fy):
        raise ReportError(
            f"{source}: {width}x{height} pixels does not have the aspect ratio of its camera "
            f"({camera.width}x{camera.height} in cameras.json); the image and cameras.json must "
            "describe the same view"
        )
    return camera.scaled(fx)


def report_camera(camera: Camera, max_size: int) -> Camera:
    """``camera`` scaled down so that its longest side is at most ``max_size`` pixels."""
    f = min(1.0, max_size / max(camera.width, camera.height))
    return camera if f == 1.0 else camera.scaled(f)


def resize_area(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """Area-average (H, W, C) float to (height, width, C) (nearest match of a box filter)."""
    import cv2

    a = np.asarray(image, dtype=np.float32)
    if a.shape[:2] == (height, width):
        return a
    out = cv2.resize(a, (width, height), interpolation=cv2.INTER_AREA)
    return out.reshape(height, width, -1)


def resize_mask(mask: np.ndarray, width: int, height: int) -> np.ndarray:
    """(height, width) bool: pixels at least half covered by ``mask``."""
    return resize_area(mask.astype(np.float32)[:, :, None], width, height)[:, :, 0] >= 0.5


# ---- Error maps ----
def error_image(rgb_linear_a: np.ndarray, rgb_linear_b: np.ndarray) -> np.ndarray:
    """(H, W) per-pixel RMS over channels of the sRGB-encoded difference (values in [0, 1])."""
    d = linear_to_srgb(rgb_linear_a) - linear_to_srgb(rgb_linear_b)
    return np.sqrt(np.mean(d * d, axis=-1))


def colorize(values: np.ndarray, vmax: float, mask: np.ndarray | None = None,
             cmap: str = ERROR_COLORMAP) -> np.ndarray:
    """(H, W) values -> (H, W, 3) sRGB colours on [0, vmax]; grey outside ``mask``."""
    import matplotlib

    x = np.clip(np.nan_to_num(np.asarray(values, dtype=np.float64)) / vmax, 0.0, 1.0)
    rgb = matplotlib.colormaps[cmap](x)[..., :3].astype(np.float32)
    if mask is not None:
        rgb[~mask] = OUTSIDE_GREY
    return rgb


# ---- One view ----
@dataclass
class ViewInputs:
    """One input view at its file's resolution.

    rgb_linear (H, W, 3) float32; mask (H, W) bool; saturated (H, W) bool or None.
    """

    stem: str
    image_path: Path
    rgb_linear: np.ndarray
    mask: np.ndarray
    saturated: np.ndarray | None


def find_file(stem_file: str, folders, what: str) -> Path:
    """The first ``folder/stem_file`` that exists, else a ReportError listing the places tried."""
    tried = [Path(f) / stem_file for f in folders]
    for p in tried:
        if p.is_file():
            return p
    raise ReportError(
        f"{tried[0] if len(tried) == 1 else ', '.join(map(str, tried))}: not found; the report "
        f"needs the {what} of every view in cameras.json (written by the earlier stages)"
    )


def load_view(stem: str, image_dirs, mask_dirs) -> ViewInputs:
    """Read ``<stem>.exr`` (first of ``image_dirs`` that has it) and ``<stem>.png`` (masks).

    ``<stem>.sat.png`` beside the image, when present, marks clipped pixels.
    """
    path = find_file(f"{stem}.exr", image_dirs, "linear image")
    try:
        rgb = read_exr(path)
    except ImageError as e:
        raise ReportError(str(e)) from e
    if rgb.shape[2] == 1:
        rgb = np.repeat(rgb, 3, axis=2)
    rgb = np.nan_to_num(rgb[:, :, :3], nan=0.0, posinf=0.0, neginf=0.0)
    mpath = find_file(f"{stem}.png", mask_dirs, "mask")
    try:
        mask = read_mask(mpath)
    except ImageError as e:
        raise ReportError(str(e)) from e
    if mask.shape != rgb.shape[:2]:
        mask = resize_mask(mask, rgb.shape[1], rgb.shape[0])
    sat_path = path.with_name(f"{stem}.sat.png")
    sat = None
    if sat_path.is_file():
        try:
            sat = read_mask(sat_path)
        except ImageError as e:
            log.warning("%s; clipped pixels are not left out of the RMSE", e)
        else:
            if sat.shape != rgb.shape[:2]:
                sat = resize_mask(sat, rgb.shape[1], rgb.shape[0])
    return ViewInputs(stem, path, rgb.astype(np.float32), mask, sat)


@dataclass
class ViewResult:
    """The comparison of one view at the report's resolution.

    input_linear, render_linear (h, w, 3) float32; union (h, w) bool (pixels in the RMSE);
    error (h, w) float per-pixel sRGB RMS error.
    """

    stem: str
    camera: Camera
    input_linear: np.ndarray
    render_linear: np.ndarray
    union: np.ndarray
    error: np.ndarray
    rmse: float


def compare(stem: str, camera: Camera, target_linear: np.ndarray, target_mask: np.ndarray,
            render_linear: np.ndarray, render_mask: np.ndarray,
            saturated: np.ndarray | None = None) -> ViewResult:
    """RMSE and error map of ``render_linear`` against ``target_linear`` (same (h, w, 3))."""

    keep = ~saturated if saturated is not None else np.ones(target_mask.shape, bool)
    union = (target_mask | render_mask) & keep
    try:
        rmse = image_rmse(target_linear, render_linear, target_mask & keep, render_mask & keep)
    except MetricsError as e:
        raise ReportError(f"view {stem}: {e}") from e
    return ViewResult(stem, camera, target_linear, render_linear, union,
                      error_image(target_linear, render_linear), rmse)


def render_view(mesh: Mesh, textures: dict, camera: Camera, light_intensity: float, spp: int,
                seed: int, variant: str | None, r_min: float) -> tuple[np.ndarray, np.ndarray]:
    """Re-render ``mesh`` from ``camera``: (h, w, 3) linear image and (h, w) coverage mask."""

    img = render_reference(mesh, textures, camera, light_intensity=light_intensity, spp=spp,
                           seed=seed, variant=variant, r_min=r_min)
    return np.nan_to_num(img, nan=0.0, posinf=0.0, neginf=0.0), coverage_mask(mesh, camera)


def compare_view(view: ViewInputs, camera: Camera, mesh: Mesh, textures: dict,
                 light_intensity: float, max_size: int, spp: int, seed: int,
                 variant: str | None = None, r_min: float = 0.02) -> ViewResult:
    """Re-render one input view and compare (see the module docstring)."""
    h, w = view.rgb_linear.shape[:2]
    cam = report_camera(fit_camera(camera, h, w, str(view.image_path)), max_size)
    target = resize_area(view.rgb_linear, cam.width, cam.height)
    mask = resize_mask(view.mask, cam.width, cam.height)
    sat = None if view.saturated is None else resize_area(
        view.saturated.astype(np.float32)[:, :, None], cam.width, cam.height)[:, :, 0] > 0
    render, cover = render_view(mesh, textures, cam, light_intensity, spp, seed, variant, r_min)
    return compare(view.stem, cam, target, mask, render, cover, sat)


def write_view_images(result: ViewResult, folder: str | os.PathLike, vmax: float) -> dict[str, str]:
    """Write ``<stem>.input.jpg``, ``<stem>.render.jpg``, ``<stem>.error.jpg`` (sRGB);
    returns their file names by role."""

    folder = Path(folder)
    names = {k: f"{result.stem}.{k}.jpg" for k in ("input", "render", "error")}
    write_jpg(folder / names["input"], linear_to_srgb(result.input_linear))
    write_jpg(folder / names["render"], linear_to_srgb(result.render_linear))
    write_jpg(folder / names["error"], colorize(result.error, vmax, result.union))
    return names
