"""The export stage: the optimized model as a glTF 2.0 binary and a USD(Z) asset.

Inputs (DESIGN section 2): ``optimize/mesh.obj`` (UVs in the OBJ convention, v up),
``optimize/diffuse.exr`` (RGB linear ``a_d``), ``optimize/specular.exr`` (1 or 3 channels,
linear ``a_s``), ``optimize/roughness.exr`` (1 channel, perceptual roughness ``r``) and,
for the up axis, ``poses/cameras.json``. Outputs, written atomically as one folder::

    export/asset.glb                 textures embedded
    export/asset.usda                root layer, textures referenced relative to it
    export/asset.usdz                asset.usda and the three PNGs, packaged
    export/diffuse.png               sRGB-encoded a_d               (8 bit RGB)
    export/specular.png              sRGB-encoded a_s               (8 bit RGB)
    export/metallic_roughness.png    G = r linear, R = B = 0        (8 bit RGB)

The same three PNG files serve both formats, so both carry the same quantized values.

Material mappings, texture encodings, frames, units and the UV origin: :mod:`recon.export.conventions`
(the one place they are written down; :mod:`recon.export.gltf` and :mod:`recon.export.usd`
implement them).
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from recon.export.conventions import SPECULAR_COLOR_FACTOR, TEXTURE_FILES
from recon.export.gltf import write_glb
from recon.export.usd import write_usd
from recon.io.atomic import atomic_dir
from recon.io.cameras import load_cameras
from recon.io.images import ImageError, linear_to_srgb, read_mask, read_texture_map, write_png
from recon.io.mesh import Mesh, MeshError, read_obj
from recon.marker import MarkerBoard, MarkerError, marker_scale_from_dirs
from recon.optimize.radiometry import mask_coverage
from recon.support import PlaneError, plane_if_found

log = logging.getLogger(__name__)

__all__ = [
    "ExportError",
    "ExportSettings",
    "Material",
    "load_material",
    "load_model",
    "up_rotation",
    "rotation_to_y",
    "object_to_world",
    "write_textures",
    "export_asset",
    "TEXTURE_FILES",
    "SPECULAR_COLOR_FACTOR",
]

class ExportError(ValueError):
    """Inputs that cannot be exported; the message names the file and the fix."""


@dataclass(frozen=True)
class ExportSettings:
    """Settings of the export stage (the ``export:`` section of a preset / capture.yaml).

    Attributes
    ----------
    up : str
        ``"cameras"``: rotate the cameras.json frame so the mean camera up vector is +Y (the
        up axis of glTF and of the USD stage); ``"identity"``: declare the cameras.json
        +Y up as it is.
    min_up_agreement : float
        With ``up = "cameras"``: the length the mean of the unit camera up vectors must reach
        (1 = all views agree) for it to define up; below it the identity is used.
    meters_per_unit : float
        Metres per cameras.json unit, applied as a uniform scale in the root transform.
    object_height_m : float
        A known length: the object's height in metres (0 = not known). With a support plane, the
        height of the mesh above the plane; without, its extent along the up axis. It sets the
        scale (and wins over ``meters_per_unit``; a scale measured from a marker mat in the
        mat wins over both).
    marker_square_m : float
        The side of a square of the ChArUco mat in the photos, in metres (0 = no mat): the scale
        comes from the mat (:mod:`recon.marker`; the board OpenCV's 5 x 7 ChArUco, DICT_4X4_50).
    min_mask_coverage : float
        With the masks and cameras given: the asset's silhouettes must cover at least this
        fraction of the masks (mean over views), or nothing is exported (a collapsed or
        misplaced surface is not an asset; a collapse covers a few %). 0 = no check.

    An object standing on a table (``plane.json``, :mod:`recon.support`): whatever ``up`` says,
    the plane's normal becomes +Y, the plane y = 0 (the object's base stands on the ground)
    and the object is centred over the origin (its bounding box's middle in x and z).
    """

    up: str = "cameras"
    min_up_agreement: float = 0.5
    meters_per_unit: float = 1.0
    object_height_m: float = 0.0
    marker_square_m: float = 0.0
    min_mask_coverage: float = 0.3

    def __post_init__(self):
        if not (0.0 <= self.min_mask_coverage < 1.0):
            raise ValueError(f"min_mask_coverage must be in [0, 1), got {self.min_mask_coverage}")
        if self.up not in ("cameras", "identity"):
            raise ValueError(f"up must be 'cameras' or 'identity', got {self.up!r}")
        if not (0.0 <= self.min_up_agreement <= 1.0):
            raise ValueError(f"min_up_agreement must be in [0, 1], got {self.min_up_agreement}")
        if not (math.isfinite(self.meters_per_unit) and self.meters_per_unit > 0):
            raise ValueError(f"meters_per_unit must be a positive number, got {self.meters_per_unit}")
        if not (math.isfinite(self.marker_square_m) and self.marker_square_m >= 0):
            raise ValueError(f"marker_square_m must be a length in metres >= 0 (0: no mat), got "
                             f"{self.marker_square_m}")
        if not (math.isfinite(self.object_height_m) and self.object_height_m >= 0):
            raise ValueError(f"object_height_m must be a length in metres >= 0 (0: unknown), got "
                             f"{self.object_height_m}")


@dataclass
class Material:
    """The texture maps of DESIGN section 3, linear float32, first row = top of the image.

    Attributes
    ----------
    a_d : (H, W, 3) float32
        Diffuse albedo in [0, 1].
    a_s : (H', W', 1) or (H', W', 3) float32
        Specular albedo in [0, 1].
    r : (H'', W'', 1) float32
        Perceptual roughness in [0, 1].
    """

    a_d: np.ndarray
    a_s: np.ndarray
    r: np.ndarray


# ---- Inputs ----
def _read_map(path: Path, what: str, channels: tuple[int, ...]) -> np.ndarray:
    try:
        return read_texture_map(path, what, channels)
    except ImageError as e:
        raise ExportError(f"{e} (the export reads the optimize stage's {what} map)") from e


def load_material(diffuse_exr, specular_exr, roughness_exr) -> Material:
    """Read and check the three maps (channel counts, NaN/Inf; values clipped to [0, 1])."""
    return Material(
        a_d=_read_map(Path(diffuse_exr), "diffuse", (3,)),
        a_s=_read_map(Path(specular_exr), "specular", (1, 3)),
        r=_read_map(Path(roughness_exr), "roughness", (1,)),
    )


def load_model(mesh_obj, diffuse_exr, specular_exr, roughness_exr) -> tuple[Mesh, Material]:
    """Read the optimized mesh (it must have UVs) and its maps; errors name the file."""
    path = Path(mesh_obj)
    try:
        mesh = read_obj(path)
    except MeshError as e:
        raise ExportError(str(e)) from e
    if not mesh.has_uv:
        raise ExportError(
            f"{path}: the mesh has no UVs (every face needs v/vt indices); the export needs "
            "the UV-mapped mesh of the optimize stage (DESIGN section 2)"
        )
    if not (np.all(np.isfinite(mesh.v_pos)) and np.all(np.isfinite(mesh.v_tex))):
        raise ExportError(f"{path}: vertex positions or UVs contain NaN or Inf")
    if mesh.t_tex_idx.min() < 0 or mesh.t_tex_idx.max() >= len(mesh.v_tex):
        raise ExportError(f"{path}: a face refers to a texture coordinate (vt) that does not exist")
    outside = (mesh.v_tex < -1e-6) | (mesh.v_tex > 1 + 1e-6)
    if outside.any():
        log.warning("%s: %d UV coordinate(s) outside [0, 1]; textures are clamped at the edge",
                    path, int(outside.any(axis=1).sum()))
    return mesh, load_material(diffuse_exr, specular_exr, roughness_exr)


# ---- Frame ----
def up_rotation(cameras, min_agreement: float = 0.5) -> np.ndarray:
    """(3, 3) rotation taking the mean camera up vector to +Y (the identity if views disagree).

    Parameters
    ----------
    cameras : CameraSet or sequence of Camera
        OpenCV axes: a camera's up in the world is its -y axis, ``-world_to_camera[1, :3]``.
    min_agreement : float
        The mean of the unit up vectors must be at least this long, else the identity.
    """
    ups = np.array([-np.asarray(c.world_to_camera, dtype=np.float64)[1, :3] for c in cameras])
    if len(ups) == 0:
        return np.eye(3)
    ups /= np.linalg.norm(ups, axis=1, keepdims=True)
    mean = ups.mean(axis=0)
    agreement = float(np.linalg.norm(mean))
    if agreement < min_agreement or agreement == 0.0:
        log.warning("camera up vectors disagree (mean length %.3f < %.3f); keeping the "
                    "cameras.json frame, its +Y declared up", agreement, min_agreement)
        return np.eye(3)
    return rotation_to_y(mean / agreement)


def rotation_to_y(u) -> np.ndarray:
    """(3, 3) the smallest rotation taking the unit vector ``u`` to +Y."""
    u = np.asarray(u, dtype=np.float64)
    u = u / np.linalg.norm(u)
    y = np.array([0.0, 1.0, 0.0])
    c = float(u @ y)
    if c < -1.0 + 1e-12:  # upside down: half a turn about x
        return np.diag([1.0, -1.0, -1.0])
    v = np.cross(u, y)
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def object_to_world(settings: ExportSettings, cameras_json=None, plane=None, mesh: Mesh | None = None,
                    info: dict | None = None, marker_scale: float | None = None) -> np.ndarray:
    """(4, 4) transform from the cameras.json frame to the exported +Y-up metre frame.

    With a support ``plane`` (:class:`recon.support.SupportPlane`) and the ``mesh``: its normal on
    +Y, the plane at y = 0, the mesh's bounding box centred in x and z. ``marker_scale``: metres
    per unit measured from a marker mat (the plane file's ``meters_per_unit``). ``info`` (a dict)
    receives how the frame and the scale were chosen (``frame``, ``scale_source``,
    ``meters_per_unit``).
    """
    info = {} if info is None else info
    if plane is not None:
        if mesh is None:
            raise ValueError("object_to_world: a support plane needs the mesh (to centre it)")
        R = rotation_to_y(plane.normal)
        v = mesh.v_pos @ R.T
        lo, hi = v.min(0), v.max(0)
        t = np.array([-(lo[0] + hi[0]) / 2, plane.offset, -(lo[2] + hi[2]) / 2])  # y = height above the plane
        height = float(hi[1] + plane.offset)
        info["frame"] = "support plane: its normal +Y, the plane at y = 0, centred in x and z"
    else:
        R = _up_from_cameras(settings, cameras_json)
        t = np.zeros(3)
        height = float(np.ptp((mesh.v_pos @ R.T)[:, 1])) if mesh is not None else 0.0
        info["frame"] = f"up = {settings.up}"
    scale = _scale(settings, marker_scale, height, info)
    T = np.eye(4)
    T[:3, :3] = scale * R
    T[:3, 3] = scale * t
    return T


def _scale(settings: ExportSettings, marker_scale: float | None, height: float, info: dict) -> float:
    """Metres per cameras.json unit: the marker mat's, the known object height, the
    ``meters_per_unit`` setting, in that order; a note in ``info`` says which."""
    if marker_scale is not None:
        info.update(scale_source="marker mat", meters_per_unit=float(marker_scale))
    elif settings.object_height_m > 0:
        if not height > 0:
            raise ExportError("export.object_height_m is set but the mesh has no height to scale")
        info.update(scale_source=f"object height {settings.object_height_m} m (export.object_height_m)",
                    meters_per_unit=settings.object_height_m / height)
    elif settings.meters_per_unit != 1.0:
        info.update(scale_source="export.meters_per_unit", meters_per_unit=settings.meters_per_unit)
    else:
        info.update(scale_source="unknown: unitless (1 unit = 1 m); give export.object_height_m in capture.yaml "
                                 "or photograph the object on a marker mat", meters_per_unit=1.0)
        info["scale_warning"] = "the asset's scale is unknown"
    return float(info["meters_per_unit"])


def _up_from_cameras(settings: ExportSettings, cameras_json) -> np.ndarray:
    R = np.eye(3)
    if settings.up == "cameras":
        if cameras_json is None:
            log.warning("no cameras.json given; keeping the mesh frame, its +Y declared up")
        else:
            try:
                cams = load_cameras(cameras_json)
            except ValueError as e:
                raise ExportError(str(e)) from e
            up = cams.extra.get("up")
            if isinstance(up, list) and len(up) == 3 and np.all(np.isfinite(up)) and np.linalg.norm(up) > 0:
                R = rotation_to_y(up)  # the poses stage's frame (SfM): its up, however the photos are turned
            else:
                R = up_rotation(cams, settings.min_up_agreement)
    return R


# ---- Textures ----
def write_textures(material: Material, folder) -> dict[str, Path]:
    """Write the three PNGs (:data:`recon.export.conventions.TEXTURE_FILES`, encoded as
    :mod:`recon.export.conventions` says) into ``folder``; returns their paths."""
    folder = Path(folder)
    a_s = material.a_s
    if a_s.shape[2] == 1:
        a_s = np.repeat(a_s, 3, axis=2)
    mr = np.zeros(material.r.shape[:2] + (3,), dtype=np.float32)
    mr[:, :, 1] = material.r[:, :, 0]
    paths = {k: folder / v for k, v in TEXTURE_FILES.items()}
    write_png(paths["diffuse"], linear_to_srgb(material.a_d))
    write_png(paths["specular"], linear_to_srgb(a_s))
    write_png(paths["metallic_roughness"], mr)
    return paths


# ---- The stage ----
def _share(folder: Path) -> None:
    """Give the folder and its files the umask's usual permissions (temporary files and
    folders are created private, 0600/0700; an asset is meant to be shared)."""
    mask = os.umask(0)
    os.umask(mask)
    folder.chmod(0o777 & ~mask)
    for p in folder.iterdir():
        p.chmod(0o666 & ~mask)


def check_covers_masks(mesh, cameras_json, masks_dir, min_covered: float, mesh_obj, size: int = 128) -> dict:
    """The mesh's silhouettes against the masks (:func:`recon.optimize.radiometry.mask_coverage`,
    at longest side ``size``); ExportError when they cover less than ``min_covered`` of them."""
    import cv2

    cams, masks = [], []
    for cam in load_cameras(cameras_json):
        path = Path(masks_dir) / f"{cam.stem}.png"
        if not path.is_file():
            continue
        m = read_mask(path).astype(np.float32)
        f = min(1.0, size / max(m.shape))
        c = cam.scaled(f * m.shape[1] / cam.width)  # the camera at the mask's size, then reduced
        masks.append(cv2.resize(m, (c.width, c.height), interpolation=cv2.INTER_AREA))
        cams.append(c)
    if not cams:
        return {}
    cov = mask_coverage(mesh, cams, np.stack(masks))
    log.info("the asset covers %.1f %% of the masks (worst view %.1f %%)", 100 * cov["covered_mean"],
             100 * cov["covered_min"])
    if cov["covered_mean"] < min_covered:
        raise ExportError(
            f"{mesh_obj}: the optimized surface covers only {100 * cov['covered_mean']:.0f} % of the masks in "
            f"{masks_dir} (need {100 * min_covered:.0f} %): it collapsed or left the object, and is not an asset; "
            "see the optimize stage's log (flash intensity, masks, cameras) and rerun optimize")
    return cov


def export_asset(
    mesh_obj: str | os.PathLike,
    diffuse_exr: str | os.PathLike,
    specular_exr: str | os.PathLike,
    roughness_exr: str | os.PathLike,
    out_dir: str | os.PathLike,
    settings: ExportSettings = ExportSettings(),
    cameras_json: str | os.PathLike | None = None,
    plane_json: str | os.PathLike | None = None,
    views_dir: str | os.PathLike | None = None,
    masks_dir: str | os.PathLike | None = None,
) -> dict[str, Path]:
    """Write ``out_dir/asset.glb``, ``asset.usdz``, ``asset.usda`` and the PNG textures.

    The whole folder is replaced atomically: on any error nothing of a new export is left
    and a previous export stays as it was. The mappings: :mod:`recon.export.conventions`.

    Parameters
    ----------
    mesh_obj, diffuse_exr, specular_exr, roughness_exr
        The optimize stage's outputs.
    out_dir
        The export folder (``results/<capture>/export``).
    settings
        :class:`ExportSettings`.
    cameras_json
        ``poses/cameras.json``, for the up axis (``settings.up = "cameras"``).
    plane_json
        The support plane (``plane.json`` beside the masks; absent when none was found): the
        asset stands on it (:func:`object_to_world`).
    views_dir
        The pinhole views of ``cameras_json`` (``<stem>.exr``), where ``settings.marker_square_m``
        asks for the scale of a marker mat in them.
    masks_dir
        The masks of those views (``<stem>.png``): the asset must cover them
        (``settings.min_mask_coverage``, :func:`check_covers_masks`).

    Returns
    -------
    dict of the written files: ``glb``, ``usdz``, ``usda`` and the texture names.
    """
    mesh, material = load_model(mesh_obj, diffuse_exr, specular_exr, roughness_exr)
    if masks_dir is not None and cameras_json is not None and settings.min_mask_coverage > 0:
        check_covers_masks(mesh, cameras_json, masks_dir, settings.min_mask_coverage, mesh_obj)
    try:
        plane = plane_if_found(plane_json)
    except PlaneError as e:
        raise ExportError(f"{e}; rerun the masks stage") from e
    how: dict = {}
    marker = None
    if settings.marker_square_m > 0:
        if views_dir is None or cameras_json is None:
            raise ExportError("export.marker_square_m is set but the export stage was given no views and cameras "
                              "to find the mat in")
        try:
            marker, marker_info = marker_scale_from_dirs(views_dir, cameras_json,
                                                         MarkerBoard(settings.marker_square_m))
        except MarkerError as e:
            raise ExportError(f"{views_dir}: {e}") from e
        how["marker"] = marker_info
    T = object_to_world(settings, cameras_json, plane, mesh, how, marker_scale=marker)
    if "scale_warning" in how:
        log.warning("%s: %s", how["scale_warning"], how["scale_source"])
    extras = {
        "object_to_world": [float(x) for x in T.ravel()],  # row-major 4x4
        "frame": "vertex data in the cameras.json frame; object_to_world maps it to +Y up, metres",
        "up": settings.up,
        "placement": how["frame"],
        "meters_per_unit": how["meters_per_unit"],
        "scale_source": how["scale_source"],
        **({"marker_mat": how["marker"]} if "marker" in how else {}),
    }
    out_dir = Path(out_dir)
    log.info("exporting %s (%d faces, maps %s / %s / %s) to %s", mesh_obj, len(mesh.t_pos_idx),
             material.a_d.shape[:2], material.a_s.shape[:2], material.r.shape[:2], out_dir)
    with atomic_dir(out_dir) as tmp:
        tex = write_textures(material, tmp)
        write_glb(tmp / "asset.glb", mesh, tex, T, extras)
        write_usd(tmp / "asset.usda", tmp / "asset.usdz", mesh, tex, T, extras)
        _share(tmp)
    names = {"glb": "asset.glb", "usdz": "asset.usdz", "usda": "asset.usda", **TEXTURE_FILES}
    return {k: out_dir / v for k, v in names.items()}
