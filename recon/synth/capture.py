"""Synthetic captures: a procedural object, baked SVBRDF maps, rendered flash photos (DESIGN 1).

:func:`make_capture` writes a capture folder exactly as DESIGN section 1 describes::

    OUT/images/<stem>.dng|.exr|.png   the photos
    OUT/cameras.json                  the true cameras (unless ``write_cameras`` is False)
    OUT/masks/<stem>.png              object masks (when ``write_masks``)
    OUT/capture.yaml                  light_intensity, only with ``state_light`` (a calibrated flash)
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

Scenes. ``scene="void"`` (the default): the object alone in a black void, cameras on a
Fibonacci sphere around it (some from below). ``scene="tabletop"``: the object stands on a
textured table lit by the same flash, cameras on hand-held rings 15-60 degrees above the table,
and the capture also holds ``gt/masks/<stem>.png`` (the object's true silhouettes) and
``gt/plane.json`` (the table, :mod:`recon.support`); see :mod:`recon.synth.tabletop`.
``scene="tabletop_void"``: the tabletop scene's object (base cut flat) and cameras without the
table or the backdrop: the same capture in the void, the peer benchmarks compare a tabletop
capture with (``gt/plane.json`` says where the table would be). ``scene="stand"``: no table, the
object on a thin pole with a round white base in a dim room (cameras as in the tabletop scene);
``gt/masks`` hold the object alone, ``gt/masks_with_stand`` the object with its stand.
Variations that make masks hard (object colours like the table's, no texture, a wall, room
lamps, views cut by the frame) are settings of their own, off by default (VARIATION_FIELDS).

Everything is a function of the settings: the same settings give bit-identical files (except
for DNG metadata a library may stamp; pidng stamps none).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from recon.brdf import R_MIN
from recon.io.atomic import atomic_dir, atomic_path
from recon.io.cameras import Camera, CameraSet, intrinsics, look_at, save_cameras
from recon.io.dng import FULL_FRAME_DIAGONAL_MM
from recon.io.images import linear_to_srgb, write_exr, write_mask, write_png
from recon.io.mesh import write_obj
from recon.synth.bake import bake, unwrap
from recon.synth.materials import MaterialFields
from recon.support import SupportPlane, save_plane
from recon.synth.shapes import FLAT_BASE, OBJECT_KINDS, flatten_base, make_object
from recon.render.mitsuba_bsdf import render_reference
from recon.synth import imaging as phone
from recon.synth.sensor import SensorModel, exposure_value
from recon.synth.tabletop import (TabletopScene, add_marker_mat, closeup_cameras, room_lamps, stand_meshes,
                                  table_texture, tabletop_cameras, wall_mesh)

log = logging.getLogger(__name__)

FORMATS = ("dng", "exr", "png16", "png8", "jpg")
SCENES = ("void", "tabletop", "tabletop_void", "stand")
TABLETOP_FIELDS = ("scene", "elevation_range", "rings", "distance_jitter", "aim_jitter", "roll_jitter",
                   "table_half_size", "table_texture_size", "background", "background_distance",
                   "base_cut", "marker_square")
"""Settings of the tabletop scene only; a void capture's gt/synth.json leaves them out (so the
files of void captures made before they existed regenerate bit-identically)."""
PHONE_FIELDS = ("flash_offset", "ambient", "exposure_jitter", "wb_jitter", "falloff", "tone_curve",
                "tone_contrast", "jpeg_quality", "falloff_gainmap")
"""Settings of a phone's imaging (:mod:`recon.synth.imaging`); gt/synth.json records them only when
one differs from its default (so captures made before they existed regenerate bit-identically)."""
VARIATION_FIELDS = ("palette", "texture_pattern", "wall", "wall_distance", "lamps", "closeups",
                    "closeup_distance", "stand_height", "stand_base")
"""Scene variations that make masks hard (object colours like the table's, no texture, a wall and
lamps in a dim room, views cut by the frame, an object on a stand); recorded in gt/synth.json only
when one differs from its default, like PHONE_FIELDS."""
_EXT = {"dng": ".dng", "exr": ".exr", "png16": ".png", "png8": ".png", "jpg": ".jpg"}


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
    state_light : bool
        State the flash's intensity to the pipeline (``light.intensity`` in the top-level
        cameras.json and ``light_intensity`` in capture.yaml), as a calibrated flash would. Off by
        default: no user knows that number, so the pipeline estimates it from the photos; the
        true I_e is in ``gt/cameras.json`` either way.
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
    scene : str
        ``void`` (the object alone, cameras all around) or ``tabletop`` (on a table, cameras
        above it; the settings below apply to it, see :mod:`recon.synth.tabletop`), or
        ``tabletop_void`` (the tabletop object and cameras, no table: its peer in the void).
    elevation_range : (float, float)
        Tabletop: camera elevations above the table, degrees (seen from the object's center).
    rings : int
        Tabletop: number of hand-held rings of views (spread over ``elevation_range``).
    distance_jitter : float
        Tabletop: per-view camera distances vary by this fraction around each ring's.
    aim_jitter : float
        Tabletop: standard deviation of the aim point around the object's center (object units).
    roll_jitter : float
        Tabletop: standard deviation of the roll around the optical axis, degrees.
    table_half_size : float
        Tabletop: the table is a square of side 2 * this (object units, the object spans ~1.9).
    table_texture_size : int
        Tabletop: texels along each side of the table's texture.
    background : float
        Tabletop: albedo of a far backdrop lit by the flash (0: black beyond the table).
    background_distance : float
        Tabletop: radius of that backdrop around the object.
    base_cut : float
        Tabletop: the object is cut flat this fraction of its height above its lowest point
        (the mug has a flat base already).
    marker_square : float
        Tabletop: side of the squares of a ChArUco mat printed on the table under the object
        (object units; 0: no mat).
    flash_offset : (float, float, float)
        Phone: the flash's position in camera coordinates (object units at scale 1; x right,
        y down, z forward), e.g. (0.19, 0, 0): 1 cm beside the lens for a 10-cm object.
    ambient : float
        Phone: a constant environment giving this fraction of the flash's irradiance at the
        object (:func:`recon.synth.imaging.ambient_radiance`).
    exposure_jitter : float
        Phone: standard deviation (stops) of a per-view exposure error the EXIF does not record.
    wb_jitter : float
        Phone: standard deviation of per-view, per-channel white-balance log gains.
    falloff : (float, float)
        Phone: lens falloff ``1 + k1 r^2 + k2 r^4`` (r = 1 in the image corners).
    tone_curve : str
        Phone (``format="jpg"`` only): ``none`` (sRGB), ``phone`` (sRGB + an S-curve) or one the
        optimizer's model does not share (``gamma22``, ``filmic``, ``table``, ``toe_shoulder``:
        :data:`recon.synth.imaging.TONE_CURVES`).
    tone_contrast : float
        Phone: the S-curve's exponent p (1 = no S-curve).
    jpeg_quality : int
        JPEG quality (``format="jpg"``).
    falloff_gainmap : bool
        Phone DNG (``format="dng"``): the DNG carries the falloff's correction as an OpcodeList3
        GainMap (17 x 13 points, 3 planes), as phone DNGs do; linearize applies it.
    palette : str
        The object's four diffuse colours (:data:`recon.synth.materials.PALETTES`): ``default``,
        ``wood`` (the table's colours), ``glaze`` (cream, blue, orange), ``dark``.
    texture_pattern : bool
        The albedo's fine pattern (dots and fractal shading); False: plain colour regions (a glaze).
    wall : float
        Tabletop/stand: albedo of a wall behind the object (0: none), a vertical plane
        ``wall_distance`` (x ``distance``) from the object on the -y side, lit by the flash.
    wall_distance : float
        Tabletop/stand: the wall's distance from the object's centre, in camera distances.
    lamps : float
        Tabletop/stand: two room lamps (point lights fixed in the room, above and to the sides)
        giving together this fraction of the flash's irradiance at the object.
    closeups : float
        Tabletop/stand: this share of the views is taken from ``closeup_distance`` (x the view's
        distance): the object is cut by the frame's edges there.
    closeup_distance : float
        Tabletop/stand: see ``closeups``.
    stand_height : float
        Stand scene: length of the thin pole under the object (object units).
    stand_base : float
        Stand scene: albedo of the pole's round base (a white disc: 0.8).
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
    state_light: bool = False
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
    scene: str = "void"
    elevation_range: tuple = (15.0, 60.0)
    rings: int = 3
    distance_jitter: float = 0.08
    aim_jitter: float = 0.06
    roll_jitter: float = 4.0
    table_half_size: float = 4.0
    table_texture_size: int = 2048
    background: float = 0.3
    background_distance: float = 30.0
    base_cut: float = 0.08
    marker_square: float = 0.0
    flash_offset: tuple = (0.0, 0.0, 0.0)
    ambient: float = 0.0
    exposure_jitter: float = 0.0
    wb_jitter: float = 0.0
    falloff: tuple = (0.0, 0.0)
    tone_curve: str = "none"
    tone_contrast: float = 1.4
    jpeg_quality: int = 95
    falloff_gainmap: bool = False
    palette: str = "default"
    texture_pattern: bool = True
    wall: float = 0.0
    wall_distance: float = 2.0
    lamps: float = 0.0
    closeups: float = 0.0
    closeup_distance: float = 0.55
    stand_height: float = 1.2
    stand_base: float = 0.8

    def __post_init__(self):
        object.__setattr__(self, "view_z_range", tuple(float(z) for z in self.view_z_range))
        object.__setattr__(self, "flash_offset", tuple(float(z) for z in self.flash_offset))
        object.__setattr__(self, "falloff", tuple(float(z) for z in self.falloff))
        self._check_phone()
        object.__setattr__(self, "elevation_range", tuple(float(z) for z in self.elevation_range))
        if self.scene not in SCENES:
            raise SynthError(f"scene={self.scene!r}: choose one of {SCENES}")
        e0, e1 = self.elevation_range
        if not 0.0 < e0 <= e1 < 90.0:
            raise SynthError(f"elevation_range={self.elevation_range}: need 0 < low <= high < 90 degrees "
                             "(cameras above the table)")
        if self.rings < 1:
            raise SynthError(f"rings={self.rings}: need at least 1 ring of views")
        if not 0 <= self.distance_jitter < 0.5 or self.aim_jitter < 0 or self.roll_jitter < 0:
            raise SynthError("distance_jitter must be in [0, 0.5), aim_jitter and roll_jitter >= 0")
        if self.table_half_size <= 2.0:
            raise SynthError(f"table_half_size={self.table_half_size}: the table must be larger than the "
                             "object (> 2)")
        if not 16 <= self.table_texture_size <= 8192:
            raise SynthError(f"table_texture_size={self.table_texture_size}: use 16 to 8192")
        if not 0.0 <= self.background <= 1.0:
            raise SynthError(f"background={self.background}: an albedo in [0, 1] (0: none)")
        if self.scene in ("tabletop", "stand") and self.background > 0 \
                and self.background_distance <= self.distance * 1.5:
            raise SynthError(f"background_distance={self.background_distance}: the backdrop must be far "
                             f"behind the cameras (> 1.5 x distance = {1.5 * self.distance})")
        if not 0.0 <= self.base_cut < 0.5:
            raise SynthError(f"base_cut={self.base_cut}: use a fraction of the height in [0, 0.5)")
        from recon.synth.materials import PALETTES

        if self.palette not in PALETTES:
            raise SynthError(f"palette={self.palette!r}: choose one of {tuple(PALETTES)}")
        if not 0.0 <= self.wall <= 1.0 or not 0.0 <= self.stand_base <= 1.0:
            raise SynthError(f"wall={self.wall}, stand_base={self.stand_base}: albedos in [0, 1]")
        if self.wall > 0 and not 1.2 <= self.wall_distance <= 20:
            raise SynthError(f"wall_distance={self.wall_distance}: use 1.2 to 20 camera distances")
        if not 0.0 <= self.lamps <= 10.0:
            raise SynthError(f"lamps={self.lamps}: a fraction of the flash irradiance in [0, 10]")
        if not 0.0 <= self.closeups <= 1.0 or not 0.25 <= self.closeup_distance <= 1.0:
            raise SynthError(f"closeups={self.closeups} (a share in [0, 1]) and closeup_distance="
                             f"{self.closeup_distance} (in [0.25, 1])")
        if (self.wall > 0 or self.lamps > 0 or self.closeups > 0) and self.scene not in ("tabletop", "stand"):
            raise SynthError("wall, lamps and closeups need scene='tabletop' or 'stand'")
        if not 0.2 <= self.stand_height <= 5.0:
            raise SynthError(f"stand_height={self.stand_height}: use 0.2 to 5 object units")
        if self.marker_square < 0:
            raise SynthError(f"marker_square={self.marker_square}: a length >= 0 (0: no mat)")
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
        if self.exposure_variation > 0 and self.format not in ("dng", "jpg"):
            raise SynthError("exposure_variation needs format='dng' or 'jpg' (only they record exposure)")
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


    def _check_phone(self):
        if len(self.flash_offset) != 3 or not np.all(np.isfinite(self.flash_offset)):
            raise SynthError(f"flash_offset={self.flash_offset}: give 3 finite numbers (camera coordinates)")
        if float(np.linalg.norm(self.flash_offset)) >= 0.5 * self.distance:
            raise SynthError(f"flash_offset={self.flash_offset}: a flash beside the lens is much closer than "
                             f"the object (|offset| < distance / 2)")
        if not (np.isfinite(self.ambient) and 0.0 <= self.ambient <= 10.0):
            raise SynthError(f"ambient={self.ambient}: a fraction of the flash irradiance in [0, 10]")
        if not 0.0 <= self.exposure_jitter <= 2.0 or not 0.0 <= self.wb_jitter <= 0.5:
            raise SynthError("exposure_jitter must be in [0, 2] stops and wb_jitter in [0, 0.5]")
        if len(self.falloff) != 2:
            raise SynthError(f"falloff={self.falloff}: give (k1, k2) of 1 + k1 r^2 + k2 r^4")
        k1, k2 = self.falloff
        if not (np.isfinite(k1) and np.isfinite(k2)) or 1.0 + k1 + k2 <= 0.05 or 1.0 + min(k1, 0.0) <= 0.05:
            raise SynthError(f"falloff={self.falloff}: the falloff must stay > 0.05 in the corners")
        from recon.synth.imaging import TONE_CURVES

        if self.tone_curve not in TONE_CURVES:
            raise SynthError(f"tone_curve={self.tone_curve!r}: choose one of {TONE_CURVES}")
        if self.tone_curve != "none" and self.format != "jpg":
            raise SynthError(f"tone_curve={self.tone_curve!r} needs format='jpg' (a phone's JPEG)")
        if not 0.5 <= self.tone_contrast <= 4.0:
            raise SynthError(f"tone_contrast={self.tone_contrast}: use 0.5 to 4")
        if self.falloff_gainmap and (self.format != "dng" or not any(self.falloff)):
            raise SynthError("falloff_gainmap needs format='dng' and a falloff to correct")
        if not 50 <= self.jpeg_quality <= 100:
            raise SynthError(f"jpeg_quality={self.jpeg_quality}: use 50 to 100")

    @property
    def phone_effects(self) -> bool:
        """Any of the phone's imaging effects switched on (format jpg counts)."""
        d = SynthSettings()
        return self.format == "jpg" or any(getattr(self, k) != getattr(d, k) for k in PHONE_FIELDS)

    @property
    def variations(self) -> bool:
        """Any of :data:`VARIATION_FIELDS` differs from its default."""
        d = SynthSettings()
        return any(getattr(self, k) != getattr(d, k) for k in VARIATION_FIELDS)


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
    # tabletop captures: the object fills ~40% of the image width, the table around it
    "tabletop": SynthSettings(scene="tabletop", fov=50.0, distance=5.0),
    # tabletop benchmark captures (bench/tabletop.py): 48 views of 512 x 384 on three hand-held rings
    "tabletop-blob": SynthSettings(object="blob", scene="tabletop", fov=50.0, distance=5.0, n_views=48,
                                   width=512, height=384),
    "tabletop-mug": SynthSettings(object="mug", scene="tabletop", fov=50.0, distance=5.0, n_views=48,
                                  width=512, height=384, seed=1),
    # a phone's imaging, every effect on (recon.synth.imaging); switch effects off one by one with
    # the command line (--flash-offset 0 0 0, --ambient 0, ...). 1 cm flash offset at a 10-cm object.
    "phone": SynthSettings(object="blob", n_views=32, width=192, height=144, format="jpg", spp=64,
                           mesh_level=5, texture_size=512, exposure_variation=0.5,
                           flash_offset=(0.19, 0.0, 0.0), ambient=0.05, exposure_jitter=0.25, wb_jitter=0.03,
                           falloff=(-0.3, 0.0), tone_curve="phone"),
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

    out_dir = Path(out_dir)
    s = settings
    tabletop = s.scene in ("tabletop", "tabletop_void")
    sensor = SensorModel()
    log.info("synth: %s object, level %d, %s scene", s.object, s.mesh_level, s.scene)
    mesh = make_object(s.object, s.mesh_level, s.seed)
    if tabletop and s.object not in FLAT_BASE:  # the mug (and the turned shapes) stand on their own flat base
        mesh = flatten_base(mesh, s.base_cut)
    mesh = unwrap(mesh, resolution=s.texture_size, padding=3)
    fields = MaterialFields(seed=s.seed, frequency=s.texture_frequency, albedo=s.albedo,
                            specular=s.specular, roughness=s.roughness, palette=s.palette,
                            pattern=s.texture_pattern)
    (diffuse, specular, roughness), _ = bake(mesh, fields.evaluate, s.texture_size, pad=4)
    if s.scale != 1.0:  # the fields were evaluated at unit scale
        mesh = dataclasses.replace(mesh, v_pos=mesh.v_pos * s.scale)
    roughness = np.clip(roughness, R_MIN, 1.0)
    textures = {"diffuse": diffuse, "specular": specular, "roughness": roughness}
    scene, marker, gt_plane, with_stand = None, None, None, None
    if s.scene == "tabletop_void":  # the tabletop object and cameras, rendered alone
        lo, hi = mesh.bbox()
        gt_plane = SupportPlane(np.array([0.0, 0.0, 1.0]), -float(lo[2]))
        cams = tabletop_cameras(s, target=0.5 * (lo + hi) / s.scale)
    elif tabletop:
        log.info("synth: table texture %d^2", s.table_texture_size)
        table_rgb = table_texture(s.table_texture_size, s.table_half_size, s.seed)
        if s.marker_square > 0:
            marker = add_marker_mat(table_rgb, s.table_half_size, s.marker_square)
            marker = {**marker, "square": marker["square"] * s.scale, "marker": marker["marker"] * s.scale,
                      "top_left": [v * s.scale for v in marker["top_left"]],
                      "size": [v * s.scale for v in marker["size"]]}
        lo, hi = mesh.bbox()
        scene = TabletopScene(mesh, textures, float(lo[2]), s.table_half_size * s.scale, table_rgb,
                              s.background, s.background_distance * s.scale,
                              *_room(s, mesh, float(lo[2]), ()))
        gt_plane = scene.plane
        cams = closeup_cameras(tabletop_cameras(s, target=0.5 * (lo + hi) / s.scale), s, 0.5 * (lo + hi) / s.scale)
    elif s.scene == "stand":  # no table: the object on a pole with a round base, in a dim room
        lo, hi = mesh.bbox()
        pole, base = stand_meshes(float(lo[2]), s.stand_height, s.scale)
        stand = (("pole", pole, {"diffuse": np.array([0.12, 0.08, 0.05]), "specular": 0.04, "roughness": 0.5}),
                 ("base", base, {"diffuse": np.full(3, s.stand_base), "specular": 0.04, "roughness": 0.4}))
        z_floor = float(base.v_pos[:, 2].min())
        scene = TabletopScene(mesh, textures, z_floor, 1.0, None, s.background, s.background_distance * s.scale,
                              *_room(s, mesh, z_floor, stand))
        with_stand = _merge([mesh, pole, base])
        cams = closeup_cameras(tabletop_cameras(s, target=0.5 * (lo + hi) / s.scale), s, 0.5 * (lo + hi) / s.scale)
    else:
        cams = make_cameras(s)
    exposures = view_exposures(s, sensor)
    h_values = [exposure_value(e["exposure_time"], e["iso"], e["f_number"]) for e in exposures]
    h_ref = float(np.median(h_values))
    linear_scale = sensor.linear_scale(h_ref)
    # focal length in mm for the DNG tags: f_px * pixel pitch
    focal_mm = float(cams.frames[0].K[0, 0] * sensor.pixel_pitch_um * 1e-3)
    # 35-mm equivalent: the same diagonal field of view on a 36 x 24 mm frame (the convention
    # of phones, of the DNG writer and of linearize's reader; by the width, a 4:3 photo's tag
    # was 4 % long: 49 mm, read back as 271.8 px for 263.8 px)
    focal_35mm = float(cams.frames[0].K[0, 0] * FULL_FRAME_DIAGONAL_MM / math.hypot(s.width, s.height))
    noise_rng = np.random.default_rng(np.random.SeedSequence([int(s.seed), 0xA015E]))
    views_im = phone.view_imaging(s, len(cams))
    offset = np.asarray(s.flash_offset) * s.scale
    l_amb = phone.ambient_radiance(s.ambient, cams.light_intensity, s.distance * s.scale)
    falloff = phone.falloff_map(s.width, s.height, *s.falloff) if any(s.falloff) else None
    gainmap = phone.falloff_gainmap(s.width, s.height, *s.falloff) if s.falloff_gainmap else None

    with atomic_dir(out_dir) as tmp:
        (tmp / "images").mkdir()
        (tmp / "gt").mkdir()
        for i, cam in enumerate(cams.frames):
            log.info("synth: view %d/%d", i + 1, len(cams))
            light_pos = phone.light_position(cam, offset) if np.any(offset) else None
            if scene is not None:
                rgb = scene.render(cam, cams.light_intensity, s.spp, seed=s.seed * 100003 + i,
                                   light_position=light_pos, ambient=l_amb)
                coverage = scene.object_coverage(cam, s.spp, seed=s.seed * 100003 + i)
                write_mask(tmp / "gt" / "masks" / f"{cam.stem}.png", coverage > 0.5)
                if with_stand is not None:
                    cov = scene.object_coverage(cam, s.spp, seed=s.seed * 100003 + i, mesh=with_stand)
                    write_mask(tmp / "gt" / "masks_with_stand" / f"{cam.stem}.png", cov > 0.5)
            else:
                rgba = render_reference(mesh, textures, cam, cams.light_intensity, s.spp,
                                        seed=s.seed * 100003 + i, alpha=True, light_position=light_pos,
                                        ambient=l_amb)
                rgb, coverage = np.ascontiguousarray(rgba[:, :, :3]), rgba[:, :, 3]
                if gt_plane is not None:  # tabletop_void: the same files as its tabletop peer
                    write_mask(tmp / "gt" / "masks" / f"{cam.stem}.png", coverage > 0.5)
            path = tmp / cam.image
            gt_rgb = rgb  # the scene's radiance, before the phone's imaging (gt/linear)
            if s.phone_effects:
                rgb = views_im[i].apply(rgb, falloff)
            if s.format == "dng":
                from recon.io.dng import write_dng

                e = exposures[i]
                cfa = sensor.capture(rgb, e["exposure_time"], e["iso"], e["f_number"],
                                     rng=noise_rng, noise=s.noise)
                write_dng(path, cfa, sensor, e["exposure_time"], e["iso"], e["f_number"],
                          focal_length_mm=focal_mm,
                          opcode_list3=[gainmap.to_opcode()] if s.falloff_gainmap else None)
            else:
                photo = _add_noise(rgb, sensor, noise_rng) if s.noise else rgb
                if s.format == "jpg":
                    e = exposures[i]
                    # the recorded exposure: linearize divides 2**stops back out
                    y = photo * np.float32(2.0 ** e["stops"])
                    phone.write_jpeg_exif(path, phone.tone_encode(y, s.tone_curve, s.tone_contrast),
                                          e["exposure_time"], e["iso"], e["f_number"], focal_mm,
                                          focal_35mm, quality=s.jpeg_quality)
                elif s.format == "exr":
                    write_exr(path, photo)
                else:
                    write_png(path, linear_to_srgb(photo), bits=16 if s.format == "png16" else 8)
            if s.write_masks:
                write_mask(tmp / "masks" / f"{cam.stem}.png", coverage > 0.5)
            if s.write_gt_linear:
                write_exr(tmp / "gt" / "linear" / f"{cam.stem}.exr", gt_rgb * np.float32(linear_scale))
        # the light intensity that fits the linearized images (scale 1 by construction)
        gt_cams = CameraSet(cams.frames, float(cams.light_intensity * linear_scale))
        save_cameras(tmp / "gt" / "cameras.json", gt_cams)
        if s.write_cameras:
            save_cameras(tmp / "cameras.json", dataclasses.replace(gt_cams, light_known=bool(s.state_light)))
        if s.state_light:
            with atomic_path(tmp / "capture.yaml") as p:
                p.write_text(f"light_intensity: {gt_cams.light_intensity!r}\n")
        write_obj(tmp / "gt" / "mesh.obj", mesh)
        write_exr(tmp / "gt" / "diffuse.exr", diffuse)
        write_exr(tmp / "gt" / "specular.exr", specular)
        write_exr(tmp / "gt" / "roughness.exr", roughness)
        if s.phone_effects:
            phone.save_imaging(tmp / "gt" / "imaging.json", phone.imaging_record(
                s, cams, views_im, exposures, gt_cams.light_intensity, l_amb * linear_scale))
        if gt_plane is not None:
            save_plane(tmp / "gt" / "plane.json", gt_plane, table_half_size=s.table_half_size * s.scale,
                       marker_mat=marker, table=scene is not None)
        meta = {
            "generator": "recon.synth.capture.make_capture",
            "command": command,
            "settings": recorded_settings(s),
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


def _room(s: SynthSettings, mesh, z_floor: float, props: tuple) -> tuple[tuple, tuple]:
    """``(props, lamps)`` of :class:`recon.synth.tabletop.TabletopScene` for the variations of
    ``s``: ``props`` plus a wall (``s.wall``), and the room lamps (``s.lamps``)."""
    lo, hi = mesh.bbox()
    center = 0.5 * (lo + hi)
    d = s.distance * s.scale
    props = tuple(props)
    if s.wall > 0:
        dist = s.wall_distance * d
        props += (("wall", wall_mesh(center, dist, z_floor, 3.0 * dist, 2.5 * dist),
                   {"diffuse": np.full(3, s.wall), "specular": 0.0, "roughness": 1.0}),)
    lamps = tuple(room_lamps(center, d, s.lamps, s.light_intensity * s.scale**2)) if s.lamps > 0 else ()
    return props, lamps


def _merge(meshes):
    """One :class:`recon.io.mesh.Mesh` (positions and faces only) of several."""
    from recon.io.mesh import Mesh

    v, f, n = [], [], 0
    for m in meshes:
        v.append(m.v_pos)
        f.append(m.t_pos_idx + n)
        n += len(m.v_pos)
    return Mesh(np.concatenate(v), np.concatenate(f))


def recorded_settings(s: SynthSettings) -> dict:
    """The settings as gt/synth.json records them (a void capture leaves out TABLETOP_FIELDS)."""
    d = dataclasses.asdict(s)
    if s.scene == "void":
        d = {k: v for k, v in d.items() if k not in TABLETOP_FIELDS}
    if not s.phone_effects:
        d = {k: v for k, v in d.items() if k not in PHONE_FIELDS}
    if not s.variations:
        d = {k: v for k, v in d.items() if k not in VARIATION_FIELDS}
    return d


def _readme(s: SynthSettings, linear_scale: float, command: str | None) -> str:
    regen = f"\nRegenerate (bit-identical on the same machine): `{command}`\n" if command else ""
    tabletop = "" if s.scene == "void" else """
Tabletop scene: the object stands on a textured table (and in front of a dim backdrop) that
are in every photo; everything in gt/ describes the object alone:
- `masks/<stem>.png`: the object's true silhouettes (pixel coverage of the object > 0.5).
- `plane.json`: the table, `normal . x + offset = 0` (normal up, towards the cameras), in the
  frame of `cameras.json`; `marker_mat` describes the printed ChArUco mat when there is one.
"""
    return f"""# Ground truth of a synthetic capture (never read by the pipeline)

Made by `recon.synth.capture.make_capture` (settings in `synth.json`), object `{s.object}`.
{regen}{tabletop}
- `mesh.obj`: the true mesh in the frame of `gt/cameras.json`, with its UV atlas (OBJ, v up).
- `diffuse.exr` (RGB), `specular.exr` (1 channel), `roughness.exr` (1 channel): the true maps,
  linear float32, texel (i, j) at u = (j + 0.5)/W, v = 1 - (i + 0.5)/H (DESIGN section 2).
- `cameras.json`: the true cameras; `light.intensity` is I_e for the linearized images.
- `linear/<stem>.exr` (if present): the noise-free linear renders BEFORE the sensor, at the
  exposure a correct linearization recovers: linearized = linear/<stem>.exr, i.e.
  linearized = render * linear_scale with linear_scale = {linear_scale!r} (see `synth.json`).
  Pixels brighter than 1 clip in the RAW files (`.sat.png` in the pipeline).
"""
