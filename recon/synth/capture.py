"""Synthetic captures: a procedural object, baked SVBRDF maps, rendered flash photos (DESIGN 1).

:func:`make_capture` writes a capture folder exactly as DESIGN section 1 describes::

    OUT/images/<stem>.dng|.exr|.png   the photos
    OUT/cameras.json                  the true cameras (unless ``write_cameras`` is False)
    OUT/masks/<stem>.png              object masks (when ``write_masks``)
    OUT/capture.yaml                  light_intensity (the pipeline's I_e)
    OUT/gt/mesh.obj                   the true mesh with its UV atlas
    OUT/gt/diffuse.exr, specular.exr, roughness.exr   the true maps (linear, float32)
    OUT/gt/cameras.json               the true cameras, always
    OUT/gt/linear/<stem>.exr          noise-free linear renders (when ``write_gt_linear``)
    OUT/gt/synth.json, gt/README.md   settings, exposures, and how the numbers relate

Exposure and scale. Views are rendered in linear Rec.709 radiance for a point light of
intensity ``light_intensity`` at each camera center. DNG photos go through
:class:`recon.synth.sensor.SensorModel`; the base exposure is chosen so that the capture's
median exposure H equals the sensor's ``saturation_exposure``, which makes the sensor's
``linear_scale`` exactly 1: a correct linearization returns the renders themselves
(``gt/linear``), and ``light_intensity`` stays the right I_e for them. ``exposure_variation``
(stops) varies shutter time (and ISO) per view around that median: the views are written with
offsets 0, +v, 0, -v, ... so the median stays at offset 0. EXR photos are the renders (plus noise
when ``noise``), PNG photos their sRGB encoding (clipped to [0, 1]).

Everything is a function of the settings: the same settings give bit-identical files (except
for DNG metadata a library may stamp; pidng stamps none).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from recon.brdf import R_MIN
from recon.io.atomic import atomic_dir, atomic_path
from recon.io.cameras import Camera, CameraSet, intrinsics, look_at, save_cameras
from recon.io.images import linear_to_srgb, write_exr, write_mask, write_png
from recon.io.mesh import write_obj
from recon.synth.bake import bake, unwrap
from recon.synth.materials import MaterialFields
from recon.synth.shapes import OBJECT_KINDS, make_object

log = logging.getLogger(__name__)

FORMATS = ("dng", "exr", "png16", "png8")
_EXT = {"dng": ".dng", "exr": ".exr", "png16": ".png", "png8": ".png"}


EXTENT_RADIUS = 0.95 * 3**0.5
"""Radius of a ball holding every generated object."""


class SynthError(ValueError):
    """Settings that cannot make a capture; the message names the setting and the fix."""


@dataclass(frozen=True)
class SynthSettings:
    """How to make a synthetic capture.

    Attributes
    ----------
    object : str
        ``blob`` (bumps and grooves), ``torus`` (genus 1 with detail) or ``smooth``.
    n_views : int
        Number of photos.
    width, height : int
        Image size in pixels (even for DNG).
    fov : float
        Horizontal field of view in degrees (square pixels, principal point at the center).
    distance : float
        Camera distance from the object's center (the object lies in [-0.95, 0.95]^3).
    view_z_range : (float, float)
        Range of the view directions' z (up) component on the Fibonacci sphere: mostly the
        upper hemisphere, some views from below.
    format : str
        ``dng`` (through the sensor model), ``exr`` (linear), ``png16`` or ``png8`` (sRGB).
    spp : int
        Samples per pixel of the renders.
    seed : int
        Seeds the object, the materials, the renders and the noise.
    light_intensity : float
        I_e of the point light at each camera center.
    write_cameras : bool
        Write the top-level cameras.json (without it the pipeline runs SfM).
    write_masks : bool
        Write masks/<stem>.png (pixel coverage > 0.5).
    write_gt_linear : bool
        Write gt/linear/<stem>.exr.
    exposure_variation : float
        Per-view exposure offsets in stops (DNG only).
    noise : bool
        Shot and read noise (sensor model for DNG; its equivalent for EXR/PNG).
    mesh_level : int
        Icosphere subdivision level (the torus gets as many faces): 20 * 4**level faces.
    texture_size : int
        Size of the square ground-truth maps.
    texture_frequency : float
        Scale of the albedo pattern (about one dot per (1/frequency)^3, see MaterialFields).
    albedo, specular, roughness : float or None
        Constant diffuse albedo (grey, no pattern), specular albedo or roughness everywhere
        instead of the spatially varying fields (None): ``specular=0`` is a purely diffuse object.
    scale : float
        Scene scale: the object, the camera distances and the ground truth are multiplied by it
        and the light intensity by ``scale**2``, so the photos are the same at every scale.
    """

    object: str = "blob"
    n_views: int = 40
    width: int = 256
    height: int = 192
    fov: float = 40.0
    distance: float = 4.2
    view_z_range: tuple = (-0.35, 0.92)
    format: str = "dng"
    spp: int = 64
    seed: int = 0
    light_intensity: float = 28.0
    write_cameras: bool = True
    write_masks: bool = False
    write_gt_linear: bool = True
    exposure_variation: float = 0.0
    noise: bool = True
    mesh_level: int = 6
    texture_size: int = 1024
    texture_frequency: float = 16.0
    albedo: float | None = None
    specular: float | None = None
    roughness: float | None = None
    scale: float = 1.0

    def __post_init__(self):
        object.__setattr__(self, "view_z_range", tuple(float(z) for z in self.view_z_range))
        if self.object not in OBJECT_KINDS:
            raise SynthError(f"object={self.object!r}: choose one of {OBJECT_KINDS}")
        if self.format not in FORMATS:
            raise SynthError(f"format={self.format!r}: choose one of {FORMATS}")
        if self.n_views < 1:
            raise SynthError(f"n_views={self.n_views}: need at least 1 view")
        if self.width < 8 or self.height < 8:
            raise SynthError(f"image size {self.width}x{self.height}: need at least 8x8 pixels")
        if self.format == "dng" and (self.width % 2 or self.height % 2):
            raise SynthError(f"image size {self.width}x{self.height}: DNG (Bayer) needs even sizes")
        if not 1.0 < self.fov < 170.0:
            raise SynthError(f"fov={self.fov}: use a horizontal field of view in (1, 170) degrees")
        half_diag = EXTENT_RADIUS
        if self.distance <= half_diag:
            raise SynthError(f"distance={self.distance}: cameras must stay outside the object "
                             f"(distance > {half_diag:.2f})")
        z0, z1 = self.view_z_range
        if not -1.0 <= z0 < z1 <= 1.0:
            raise SynthError(f"view_z_range={self.view_z_range}: need -1 <= z0 < z1 <= 1")
        if self.spp < 1:
            raise SynthError(f"spp={self.spp}: need at least 1 sample per pixel")
        if not np.isfinite(self.light_intensity) or self.light_intensity <= 0:
            raise SynthError(f"light_intensity={self.light_intensity}: must be positive")
        if self.exposure_variation < 0 or self.exposure_variation > 4:
            raise SynthError(f"exposure_variation={self.exposure_variation}: use 0 to 4 stops")
        if self.exposure_variation > 0 and self.format != "dng":
            raise SynthError("exposure_variation needs format='dng' (only RAW files record exposure)")
        if not 0 <= self.mesh_level <= 8:
            raise SynthError(f"mesh_level={self.mesh_level}: use 0 to 8")
        if not 16 <= self.texture_size <= 8192:
            raise SynthError(f"texture_size={self.texture_size}: use 16 to 8192")
        if self.texture_frequency <= 0:
            raise SynthError(f"texture_frequency={self.texture_frequency}: must be positive")
        for name in ("albedo", "specular"):
            v = getattr(self, name)
            if v is not None and not 0.0 <= v <= 1.0:
                raise SynthError(f"{name}={v}: use a value in [0, 1] (or leave it out for the spatially varying field)")
        if self.roughness is not None and not R_MIN <= self.roughness <= 1.0:
            raise SynthError(f"roughness={self.roughness}: use a value in [{R_MIN}, 1]")
        if not (np.isfinite(self.scale) and 1e-6 <= self.scale <= 1e6):
            raise SynthError(f"scale={self.scale}: use a scene scale in [1e-6, 1e6]")


PRESETS: dict[str, SynthSettings] = {
    # the bundled CI capture (captures/demo): small, DNG, SfM poses (no cameras.json).
    # 32 views ~26 degrees apart: COLMAP registers 31/32 at 192 x 144 when the focal length
    # is held at the DNG's value (28 views ~29 degrees apart: 25/28).
    "demo": SynthSettings(object="blob", n_views=32, width=192, height=144, fov=40.0,
                          distance=4.0, view_z_range=(-0.3, 0.9), format="dng", spp=32, seed=0,
                          light_intensity=28.0,
                          write_cameras=False, write_masks=False, write_gt_linear=False,
                          exposure_variation=0.5, noise=True, mesh_level=4, texture_size=256,
                          texture_frequency=16.0),
    # benchmark captures
    "blob": SynthSettings(object="blob"),
    "torus": SynthSettings(object="torus"),
    "smooth": SynthSettings(object="smooth"),
}


# ---- cameras ----
def fibonacci_directions(n: int, z_range=(-0.35, 0.92)) -> np.ndarray:
    """``(n, 3)`` unit vectors spread evenly (Fibonacci lattice) over the band z0 <= z <= z1."""
    z0, z1 = z_range
    k = np.arange(n)
    z = z1 - (k + 0.5) / n * (z1 - z0)
    phi = k * np.pi * (3.0 - 5.0**0.5)
    s = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    return np.stack([s * np.cos(phi), s * np.sin(phi), z], -1)


def make_cameras(settings: SynthSettings) -> CameraSet:
    """N cameras on a sphere of radius ``distance`` looking at the origin, +z up in the image."""
    ext = _EXT[settings.format]
    K = intrinsics(settings.width, settings.height, settings.fov)
    frames = []
    for i, d in enumerate(fibonacci_directions(settings.n_views, settings.view_z_range)):
        eye = settings.distance * settings.scale * d
        frames.append(Camera(f"images/{i:04d}{ext}", settings.width, settings.height, K.copy(),
                             look_at(eye, [0.0, 0.0, 0.0], up=(0.0, 0.0, 1.0))))
    return CameraSet(tuple(frames), float(settings.light_intensity * settings.scale**2))


# ---- exposures ----
def view_exposures(settings: SynthSettings, sensor) -> list[dict]:
    """Per-view ``exposure_time``, ``iso``, ``f_number`` and offset (stops).

    Offsets cycle 0, +v, 0, -v so that the median exposure is the base one, which equals the
    sensor's ``saturation_exposure`` (linear scale 1). Every third view trades shutter time
    for ISO 200 (same exposure), to exercise ISO normalization.
    """
    f_number = 2.0
    out = []
    for i in range(settings.n_views):
        stops = settings.exposure_variation * (0.0, 1.0, 0.0, -1.0)[i % 4]
        iso = 200.0 if i % 3 == 2 else 100.0
        # H = t * iso/100 / N^2 = saturation_exposure * 2^stops
        t = sensor.saturation_exposure * 2.0**stops * f_number**2 / (iso / 100.0)
        out.append({"exposure_time": t, "iso": iso, "f_number": f_number, "stops": stops})
    return out


def _add_noise(rgb: np.ndarray, sensor, rng: np.random.Generator) -> np.ndarray:
    """Shot + read noise of ``sensor`` at its base exposure, in linear scene units."""
    full = sensor.full_well_electrons
    read = sensor.read_noise / (sensor.white_level - sensor.black_level)
    sigma = np.sqrt(np.maximum(rgb, 0.0) / full + read**2)
    return (rgb + rng.normal(size=rgb.shape) * sigma).astype(np.float32)


# ---- the capture ----
def make_capture(out_dir: str | os.PathLike, settings: SynthSettings,
                 command: str | None = None) -> Path:
    """Write a synthetic capture folder at ``out_dir`` (replaced atomically); return its path.

    ``command`` (the command line that regenerates it) is recorded in gt/README.md and
    gt/synth.json.
    """
    from recon.render.mitsuba_bsdf import render_reference
    from recon.synth.sensor import SensorModel, exposure_value

    out_dir = Path(out_dir)
    s = settings
    sensor = SensorModel()
    log.info("synth: %s object, level %d", s.object, s.mesh_level)
    mesh = make_object(s.object, s.mesh_level, s.seed)
    mesh = unwrap(mesh, resolution=s.texture_size, padding=3)
    fields = MaterialFields(seed=s.seed, frequency=s.texture_frequency, albedo=s.albedo,
                            specular=s.specular, roughness=s.roughness)
    (diffuse, specular, roughness), _ = bake(mesh, fields.evaluate, s.texture_size, pad=4)
    if s.scale != 1.0:  # the fields were evaluated at unit scale
        mesh = dataclasses.replace(mesh, v_pos=mesh.v_pos * s.scale)
    roughness = np.clip(roughness, R_MIN, 1.0)
    textures = {"diffuse": diffuse, "specular": specular, "roughness": roughness}
    cams = make_cameras(s)
    exposures = view_exposures(s, sensor)
    h_values = [exposure_value(e["exposure_time"], e["iso"], e["f_number"]) for e in exposures]
    h_ref = float(np.median(h_values))
    linear_scale = sensor.linear_scale(h_ref)
    # focal length in mm for the DNG tags: f_px * pixel pitch
    focal_mm = float(cams.frames[0].K[0, 0] * sensor.pixel_pitch_um * 1e-3)
    noise_rng = np.random.default_rng(np.random.SeedSequence([int(s.seed), 0xA015E]))

    with atomic_dir(out_dir) as tmp:
        (tmp / "images").mkdir()
        (tmp / "gt").mkdir()
        for i, cam in enumerate(cams.frames):
            log.info("synth: view %d/%d", i + 1, len(cams))
            rgba = render_reference(mesh, textures, cam, cams.light_intensity, s.spp,
                                    seed=s.seed * 100003 + i, alpha=True)
            rgb = np.ascontiguousarray(rgba[:, :, :3])
            path = tmp / cam.image
            if s.format == "dng":
                from recon.io.dng import write_dng

                e = exposures[i]
                cfa = sensor.capture(rgb, e["exposure_time"], e["iso"], e["f_number"],
                                     rng=noise_rng, noise=s.noise)
                write_dng(path, cfa, sensor, e["exposure_time"], e["iso"], e["f_number"],
                          focal_length_mm=focal_mm)
            else:
                photo = _add_noise(rgb, sensor, noise_rng) if s.noise else rgb
                if s.format == "exr":
                    write_exr(path, photo)
                else:
                    write_png(path, linear_to_srgb(photo), bits=16 if s.format == "png16" else 8)
            if s.write_masks:
                write_mask(tmp / "masks" / f"{cam.stem}.png", rgba[:, :, 3] > 0.5)
            if s.write_gt_linear:
                write_exr(tmp / "gt" / "linear" / f"{cam.stem}.exr", rgb * np.float32(linear_scale))
        # the light intensity that fits the linearized images (scale 1 by construction)
        gt_cams = CameraSet(cams.frames, float(cams.light_intensity * linear_scale))
        save_cameras(tmp / "gt" / "cameras.json", gt_cams)
        if s.write_cameras:
            save_cameras(tmp / "cameras.json", gt_cams)
        with atomic_path(tmp / "capture.yaml") as p:
            p.write_text(f"light_intensity: {gt_cams.light_intensity!r}\n")
        write_obj(tmp / "gt" / "mesh.obj", mesh)
        write_exr(tmp / "gt" / "diffuse.exr", diffuse)
        write_exr(tmp / "gt" / "specular.exr", specular)
        write_exr(tmp / "gt" / "roughness.exr", roughness)
        meta = {
            "generator": "recon.synth.capture.make_capture",
            "command": command,
            "settings": dataclasses.asdict(s),
            "linear_scale": linear_scale,
            "exposure_reference": h_ref,
            "sensor": dataclasses.asdict(sensor) if s.format == "dng" else None,
            "views": [{"image": c.image, **e} for c, e in zip(cams.frames, exposures, strict=True)],
            "mesh": {"vertices": int(len(mesh.v_pos)), "faces": int(len(mesh.t_pos_idx)),
                     "area": mesh.area(), "volume": mesh.volume()},
        }
        with atomic_path(tmp / "gt" / "synth.json") as p:
            p.write_text(json.dumps(meta, indent=1))
        with atomic_path(tmp / "gt" / "README.md") as p:
            p.write_text(_readme(s, linear_scale, command))
    return out_dir


def _readme(s: SynthSettings, linear_scale: float, command: str | None) -> str:
    regen = f"\nRegenerate (bit-identical on the same machine): `{command}`\n" if command else ""
    return f"""# Ground truth of a synthetic capture (never read by the pipeline)

Made by `recon.synth.capture.make_capture` (settings in `synth.json`), object `{s.object}`.
{regen}
- `mesh.obj`: the true mesh in the frame of `gt/cameras.json`, with its UV atlas (OBJ, v up).
- `diffuse.exr` (RGB), `specular.exr` (1 channel), `roughness.exr` (1 channel): the true maps,
  linear float32, texel (i, j) at u = (j + 0.5)/W, v = 1 - (i + 0.5)/H (DESIGN section 2).
- `cameras.json`: the true cameras; `light.intensity` is I_e for the linearized images.
- `linear/<stem>.exr` (if present): the noise-free linear renders BEFORE the sensor, at the
  exposure a correct linearization recovers: linearized = linear/<stem>.exr, i.e.
  linearized = render * linear_scale with linear_scale = {linear_scale!r} (see `synth.json`).
  Pixels brighter than 1 clip in the RAW files (`.sat.png` in the pipeline).
"""
