"""Cameras: the ``cameras.json`` contract (DESIGN section 1) and axis conventions.

Camera axes are OpenCV's (x right, y down, z forward); ``world_to_camera`` is a 4x4 rigid
transform; ``K`` is a pinhole matrix with pixel centers at (j + 0.5, i + 0.5). The light is a
point light at each camera center. The only conversion to Mitsuba's axes is
:func:`camera_to_world_mitsuba`.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from recon.io.atomic import atomic_path


class CameraError(ValueError):
    """A cameras.json that does not follow the contract; the message names the file and the fix."""


@dataclass(frozen=True)
class Camera:
    """One view. ``K`` (3, 3) float64, ``world_to_camera`` (4, 4) float64, OpenCV axes."""

    image: str
    width: int
    height: int
    K: np.ndarray
    world_to_camera: np.ndarray

    @property
    def camera_to_world(self) -> np.ndarray:
        """(4, 4) inverse of ``world_to_camera``."""
        R = self.world_to_camera[:3, :3]
        t = self.world_to_camera[:3, 3]
        M = np.eye(4)
        M[:3, :3] = R.T
        M[:3, 3] = -R.T @ t
        return M

    @property
    def center(self) -> np.ndarray:
        """(3,) camera (and light) position in world units."""
        return self.camera_to_world[:3, 3]

    @property
    def stem(self) -> str:
        return Path(self.image).stem

    def project(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project ``(n, 3)`` world points: ``(n, 2)`` pixel coordinates (x=col, y=row) and depth."""
        p = np.asarray(points_world, dtype=np.float64)
        pc = p @ self.world_to_camera[:3, :3].T + self.world_to_camera[:3, 3]
        z = pc[:, 2]
        uvw = pc @ self.K.T
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = uvw[:, :2] / uvw[:, 2:3]
        return xy, z

    def scaled(self, factor: float, name: str | None = None) -> "Camera":
        """The same camera for an image resized by ``factor`` (pixel edges scale, centers follow)."""
        K = self.K.copy()
        K[:2, :] *= factor
        return Camera(
            image=name or self.image,
            width=int(round(self.width * factor)),
            height=int(round(self.height * factor)),
            K=K,
            world_to_camera=self.world_to_camera.copy(),
        )


@dataclass(frozen=True)
class CameraSet:
    """All views of a capture and the collocated light's intensity.

    ``light_known``: the intensity was stated (``light.intensity`` in the file, a calibrated
    flash or a synthetic capture's truth); False when the file leaves it out, as after SfM,
    whose frame has no physical scale: ``light_intensity`` is then a placeholder (1) and the
    optimize stage estimates the flash's scale from the photos (DESIGN section 3,
    :mod:`recon.optimize.radiometry`).
    """

    frames: tuple[Camera, ...]
    light_intensity: float = 1.0
    extra: dict = field(default_factory=dict)
    light_known: bool = True

    def __len__(self) -> int:
        return len(self.frames)

    def __iter__(self):
        return iter(self.frames)

    def by_stem(self) -> dict[str, Camera]:
        return {c.stem: c for c in self.frames}

    def up(self) -> np.ndarray:
        """The views' mean up direction, unit length (photos are taken upright: up is a camera's
        -y); +z when they cancel."""
        up = -np.mean([c.camera_to_world[:3, 1] for c in self.frames], axis=0)
        n = np.linalg.norm(up)
        return up / n if n > 1e-9 else np.array([0.0, 0.0, 1.0])


def _matrix(value, shape, where: str) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise CameraError(f"{where}: not a numeric matrix ({e})") from e
    if a.shape != shape:
        raise CameraError(f"{where}: expected shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise CameraError(f"{where}: contains NaN or Inf")
    return a


def parse_cameras(data: dict, source: str = "cameras.json") -> CameraSet:
    """Validate a decoded cameras.json and build a :class:`CameraSet`."""
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list) or not data["frames"]:
        raise CameraError(f"{source}: needs a non-empty list 'frames' (see DESIGN section 1)")
    frames = []
    for i, fr in enumerate(data["frames"]):
        where = f"{source}: frames[{i}]"
        for key in ("image", "width", "height", "K", "world_to_camera"):
            if key not in fr:
                raise CameraError(f"{where}: missing key '{key}'")
        K = _matrix(fr["K"], (3, 3), f"{where}.K")
        W2C = _matrix(fr["world_to_camera"], (4, 4), f"{where}.world_to_camera")
        R = W2C[:3, :3]
        if np.abs(R @ R.T - np.eye(3)).max() > 1e-4 or np.linalg.det(R) < 0:
            raise CameraError(f"{where}.world_to_camera: the 3x3 block is not a rotation")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise CameraError(f"{where}.K: focal lengths must be positive")
        w, h = int(fr["width"]), int(fr["height"])
        if w <= 0 or h <= 0:
            raise CameraError(f"{where}: width and height must be positive")
        frames.append(Camera(str(fr["image"]), w, h, K, W2C))
    light = data.get("light", {}) or {}
    if light.get("type", "collocated_point") != "collocated_point":
        raise CameraError(f"{source}: light.type must be 'collocated_point', got {light.get('type')!r}")
    known = light.get("intensity") is not None
    try:
        intensity = float(light["intensity"]) if known else 1.0
    except (TypeError, ValueError):
        raise CameraError(f"{source}: light.intensity must be a positive number, got {light['intensity']!r}") from None
    if not np.isfinite(intensity) or intensity <= 0:
        raise CameraError(f"{source}: light.intensity must be a positive number, got {intensity}")
    extra = {k: v for k, v in data.items() if k not in ("frames", "light")}
    return CameraSet(tuple(frames), intensity, extra, light_known=known)


def load_cameras(path: str | os.PathLike) -> CameraSet:
    """Read and validate ``cameras.json``."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise CameraError(f"{path}: file not found") from None
    except json.JSONDecodeError as e:
        raise CameraError(f"{path}: not valid JSON ({e})") from e
    return parse_cameras(data, str(path))


def cameras_to_dict(cams: CameraSet) -> dict:
    out = dict(cams.extra)
    out["frames"] = [
        {
            "image": c.image,
            "width": int(c.width),
            "height": int(c.height),
            "K": np.asarray(c.K, dtype=float).tolist(),
            "world_to_camera": np.asarray(c.world_to_camera, dtype=float).tolist(),
        }
        for c in cams.frames
    ]
    out["light"] = {"type": "collocated_point"}
    if cams.light_known:
        out["light"]["intensity"] = float(cams.light_intensity)
    return out


def save_cameras(path: str | os.PathLike, cams: CameraSet) -> None:
    """Write ``cameras.json`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(cameras_to_dict(cams), indent=1))


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """(4, 4) ``world_to_camera`` (OpenCV axes) of a camera at ``eye`` looking at ``target``."""
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(x) < 1e-9:  # looking along `up`: pick any perpendicular
        x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)  # y down
    R = np.stack([x, y, z])
    M = np.eye(4)
    M[:3, :3] = R
    M[:3, 3] = -R @ eye
    return M


def intrinsics(width: int, height: int, fov_x_deg: float) -> np.ndarray:
    """(3, 3) ``K`` with square pixels and the principal point at the image center."""
    f = 0.5 * width / np.tan(np.radians(fov_x_deg) / 2)
    return np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])


# ---- The one conversion to Mitsuba's camera axes ----
OPENCV_TO_MITSUBA = np.diag([-1.0, -1.0, 1.0, 1.0])
"""Mitsuba's cameras look down +z with +y up and +x to the left: flip OpenCV's x and y."""


def camera_to_world_mitsuba(cam: Camera) -> np.ndarray:
    """(4, 4) ``to_world`` matrix of a Mitsuba ``perspective`` sensor for ``cam``."""
    return cam.camera_to_world @ OPENCV_TO_MITSUBA


def mitsuba_sensor_dict(cam: Camera, spp: int = 16, sample_border: bool = False,
                        rfilter: str = "box") -> dict:
    """A Mitsuba ``perspective`` sensor dict equal to ``cam`` (pinhole, square pixels).

    The pixel filter defaults to a box, i.e. the pixel-footprint average of DESIGN section 3.
    """
    import mitsuba as mi

    K = cam.K
    if abs(K[0, 0] - K[1, 1]) > 1e-6 * K[0, 0] or abs(K[0, 1]) > 1e-9:
        raise CameraError(f"{cam.image}: Mitsuba's perspective sensor needs square pixels (fx == fy, no skew)")
    fov_x = float(np.degrees(2 * np.arctan(0.5 * cam.width / K[0, 0])))
    return {
        "type": "perspective",
        "fov_axis": "x",
        "fov": fov_x,
        # Offsets of the principal point from the film center, in film fractions. Mitsuba
        # shifts the film window by MINUS the offset, so both signs are (center - c)/size;
        # verified by tests/render/test_mitsuba_bsdf.py::test_sensor_principal_point.
        "principal_point_offset_x": float((cam.width / 2 - K[0, 2]) / cam.width),
        "principal_point_offset_y": float((cam.height / 2 - K[1, 2]) / cam.height),
        "near_clip": 1e-3,
        "to_world": mi.ScalarTransform4f(camera_to_world_mitsuba(cam).tolist()),
        "film": {
            "type": "hdrfilm",
            "width": int(cam.width),
            "height": int(cam.height),
            "rfilter": {"type": rfilter},
            "pixel_format": "rgb",
            "sample_border": sample_border,
        },
        "sampler": {"type": "independent", "sample_count": int(spp)},
    }
