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
from recon.io.images import ImageError, linear_to_srgb, read_texture_map, write_png
from recon.io.mesh import Mesh, MeshError, read_obj

log = logging.getLogger(__name__)

__all__ = [
    "ExportError",
    "ExportSettings",
    "Material",
    "load_material",
    "load_model",
    "up_rotation",
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
    """

    up: str = "cameras"
    min_up_agreement: float = 0.5
    meters_per_unit: float = 1.0

    def __post_init__(self):
        if self.up not in ("cameras", "identity"):
            raise ValueError(f"up must be 'cameras' or 'identity', got {self.up!r}")
        if not (0.0 <= self.min_up_agreement <= 1.0):
            raise ValueError(f"min_up_agreement must be in [0, 1], got {self.min_up_agreement}")
        if not (math.isfinite(self.meters_per_unit) and self.meters_per_unit > 0):
            raise ValueError(f"meters_per_unit must be a positive number, got {self.meters_per_unit}")


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
    u = mean / agreement
    y = np.array([0.0, 1.0, 0.0])
    c = float(u @ y)
    if c < -1.0 + 1e-12:  # upside down: half a turn about x
        return np.diag([1.0, -1.0, -1.0])
    v = np.cross(u, y)
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def object_to_world(settings: ExportSettings, cameras_json=None) -> np.ndarray:
    """(4, 4) transform from the cameras.json frame to the exported +Y-up metre frame."""
    R = np.eye(3)
    if settings.up == "cameras":
        if cameras_json is None:
            log.warning("no cameras.json given; keeping the mesh frame, its +Y declared up")
        else:
            try:
                cams = load_cameras(cameras_json)
            except ValueError as e:
                raise ExportError(str(e)) from e
            R = up_rotation(cams, settings.min_up_agreement)
    T = np.eye(4)
    T[:3, :3] = settings.meters_per_unit * R
    return T


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


def export_asset(
    mesh_obj: str | os.PathLike,
    diffuse_exr: str | os.PathLike,
    specular_exr: str | os.PathLike,
    roughness_exr: str | os.PathLike,
    out_dir: str | os.PathLike,
    settings: ExportSettings = ExportSettings(),
    cameras_json: str | os.PathLike | None = None,
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

    Returns
    -------
    dict of the written files: ``glb``, ``usdz``, ``usda`` and the texture names.
    """
    mesh, material = load_model(mesh_obj, diffuse_exr, specular_exr, roughness_exr)
    T = object_to_world(settings, cameras_json)
    extras = {
        "object_to_world": [float(x) for x in T.ravel()],  # row-major 4x4
        "frame": "vertex data in the cameras.json frame; object_to_world maps it to +Y up, metres",
        "up": settings.up,
        "meters_per_unit": settings.meters_per_unit,
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
