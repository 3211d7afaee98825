"""Undistortion of the views to the pinhole camera COLMAP derives (``pycolmap.undistort_camera``).

The linear EXRs, the clipped-pixel masks and the masks are resampled by ``cv2.remap`` in float:
the 8-bit route of ``pycolmap.undistort_images`` would lose the linear data.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from recon.io.images import read_exr, read_mask, write_exr, write_mask
from recon.poses.settings import PoseError


def keypoints_to_pinhole(colmap_camera, xy: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(N, 2) pixels in the undistorted pinhole image (intrinsics ``K``, cameras.json's) of
    keypoints ``xy`` (N, 2) that COLMAP located in its distorted photo (``colmap_camera``)."""
    rays = np.asarray(colmap_camera.cam_from_img(np.asarray(xy, np.float64)), dtype=np.float64).reshape(-1, 2)
    return np.stack([K[0, 0] * rays[:, 0] + K[0, 1] * rays[:, 1] + K[0, 2], K[1, 1] * rays[:, 1] + K[1, 2]], 1)


def pinhole_camera(cam, camera_model: str, max_shift_px: float = 0.01):
    """The pinhole camera (square pixels) of the undistorted images of COLMAP camera ``cam``.

    When ``cam``'s distortion moves no pixel by more than ``max_shift_px`` (:func:`distortion_shift`;
    e.g. a distortion fitted as 0), the pinhole camera of ``cam``'s own size, focal length and
    principal point: ``pycolmap.undistort_camera`` crops such views by 1 or 2 pixels on a
    knife edge (192 x 144 became 191 x 143 with k = 0 and 190 x 142 with k = 1e-12, so two
    SfM runs whose cameras agreed to 1e-15 gave views of different sizes).
    """
    import pycolmap

    if distortion_shift(cam) <= max_shift_px:
        fx, fy = cam.focal_length_x, cam.focal_length_y
        pinhole = pycolmap.Camera(model="PINHOLE", width=cam.width, height=cam.height,
                                  params=[fx, fy, cam.principal_point_x, cam.principal_point_y])
    else:
        pinhole = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), cam)
    fx, fy = pinhole.focal_length_x, pinhole.focal_length_y
    if abs(fx - fy) > 1e-6 * fx:  # models with two focal lengths: make pixels square
        raise PoseError(f"camera model {camera_model} gave fx={fx:.2f} != fy={fy:.2f}; use "
                        "SIMPLE_RADIAL, RADIAL or SIMPLE_PINHOLE (square pixels)")
    return pinhole


def distortion_shift(cam, grid: int = 17) -> float:
    """The largest distance (pixels) between where ``cam`` and the pinhole camera of its focal
    length and principal point image the same ray, over the image's border pixels and a
    ``grid`` x ``grid`` lattice inside (radial distortion is largest at the corners); inf when
    a ray does not map back."""
    import pycolmap

    w, h = cam.width, cam.height
    edge = [np.stack([np.arange(w) + 0.5, np.full(w, y)], 1) for y in (0.0, float(h))]
    edge += [np.stack([np.full(h, x), np.arange(h) + 0.5], 1) for x in (0.0, float(w))]
    gx, gy = np.meshgrid(np.linspace(0, w, grid), np.linspace(0, h, grid))
    pix = np.concatenate(edge + [np.stack([gx.ravel(), gy.ravel()], 1)]).astype(np.float64)
    plain = pycolmap.Camera(model="PINHOLE", width=w, height=h,
                            params=[cam.focal_length_x, cam.focal_length_y, cam.principal_point_x,
                                    cam.principal_point_y])
    xy = np.asarray(cam.cam_from_img(pix), dtype=np.float64).reshape(-1, 2)
    back = np.asarray(plain.img_from_cam(np.concatenate([xy, np.ones((len(xy), 1))], 1),
                                         check_cheirality=False), dtype=np.float64).reshape(-1, 2)
    d = np.linalg.norm(back - pix, axis=1)
    return float(d.max()) if np.all(np.isfinite(d)) else float("inf")


def undistort_maps(cam, pinhole):
    """cv2.remap maps (float32 (H', W')) from the pinhole image to the distorted one."""
    h, w = pinhole.height, pinhole.width
    j, i = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    pix = np.stack([j.ravel(), i.ravel()], axis=1)
    xy = pinhole.cam_from_img(pix)
    src = cam.img_from_cam(np.concatenate([xy, np.ones((len(xy), 1))], axis=1), check_cheirality=False)
    src = src.reshape(h, w, 2) - 0.5  # cv2 addresses pixel centers by integers
    return src[:, :, 0].astype(np.float32), src[:, :, 1].astype(np.float32)


def distort_maps(cam, pinhole):
    """cv2.remap maps (float32 (H, W)) from the distorted image to the pinhole one: the inverse of
    :func:`undistort_maps`, to take an undistorted mask back to the photo's own pixels."""
    h, w = cam.height, cam.width
    j, i = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    xy = cam.cam_from_img(np.stack([j.ravel(), i.ravel()], axis=1))
    dst = pinhole.img_from_cam(np.concatenate([xy, np.ones((len(xy), 1))], axis=1), check_cheirality=False)
    dst = dst.reshape(h, w, 2) - 0.5
    return dst[:, :, 0].astype(np.float32), dst[:, :, 1].astype(np.float32)


def remap(img: np.ndarray, maps) -> np.ndarray:
    import cv2

    out = cv2.remap(np.ascontiguousarray(img, dtype=np.float32), maps[0], maps[1], cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return out if out.ndim == 3 else out[:, :, None] if img.ndim == 3 else out


def undistort_view(linear_dir: Path, out_dir: Path, stem: str, maps, mask: np.ndarray | None) -> np.ndarray | None:
    """Write the undistorted ``<stem>.exr``, ``<stem>.sat.png`` (when the linear view has one) and
    ``masks/<stem>.png`` (when ``mask`` is given) under ``out_dir``; return the undistorted mask."""
    img = read_exr(linear_dir / f"{stem}.exr")
    write_exr(out_dir / f"{stem}.exr", remap(img, maps), half=True)  # resampled: half floats suffice
    sat = linear_dir / f"{stem}.sat.png"
    if sat.is_file():
        write_mask(out_dir / f"{stem}.sat.png", remap(read_mask(sat).astype(np.float32), maps) > 0)
    if mask is None:
        return None
    undistorted = remap(mask.astype(np.float32), maps) >= 0.5
    write_mask(out_dir / "masks" / f"{stem}.png", undistorted)
    return undistorted
