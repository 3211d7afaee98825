"""How to make a synthetic capture: :class:`SynthSettings`, in sections, and the presets.

:class:`SynthSettings` holds the object (``object``, ``mesh_level``), the ``scene``, the
``seed`` and the ``scale`` at its top, and the rest in sections: ``cameras`` (where the views
are), ``photos`` (how they are rendered and stored), ``outputs`` (which files besides the photos),
``material`` (the object's SVBRDF fields), ``tabletop`` (the table scene), ``phone`` (a phone's
imaging) and ``variations`` (what makes masks hard). ``python -m recon synth`` sets them by their
own names (:func:`recon.sections.replace`); ``gt/synth.json`` records them flat, as it did before
the sections (:func:`recorded_settings`), so older captures regenerate bit-identically.

Every random number of a capture derives from ``seed`` here (:meth:`SynthSettings.rng`,
:meth:`SynthSettings.view_seed`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from recon.brdf import R_MIN
from recon.sections import flatten, sectioned
from recon.synth.shapes import OBJECT_KINDS

FORMATS = ("dng", "exr", "png16", "png8", "jpg")
SCENES = ("void", "tabletop", "tabletop_void", "stand")
TABLES = ("wood", "plain")
EXTENT_RADIUS = 0.95 * 3**0.5
"""Radius of a ball holding every generated object."""


class SynthError(ValueError):
    """Settings that cannot make a capture; the message names the setting and the fix."""


def _floats(values) -> tuple:
    return tuple(float(v) for v in values)


@dataclass(frozen=True)
class CameraSettings:
    """Where the views are.

    n_views : number of photos.
    width, height : image size in pixels (even for DNG).
    fov : horizontal field of view in degrees (square pixels, principal point at the center).
    distance : camera distance from the object's center (the object lies in [-0.95, 0.95]^3).
    view_z_range : range of the view directions' z (up) component on the Fibonacci sphere
        (void scene): mostly the upper hemisphere, some views from below.
    """

    n_views: int = 40
    width: int = 256
    height: int = 192
    fov: float = 40.0
    distance: float = 4.2
    view_z_range: tuple = (-0.35, 0.92)

    def __post_init__(self):
        object.__setattr__(self, "view_z_range", _floats(self.view_z_range))


@dataclass(frozen=True)
class PhotoSettings:
    """How the photos are rendered and stored.

    format : ``dng`` (through the sensor model), ``exr`` (linear), ``png16`` or ``png8`` (sRGB),
        ``jpg`` (a phone's JPEG, see ``phone``).
    spp : samples per pixel of the renders.
    light_intensity : I_e of the point light at each camera center.
    exposure_variation : per-view exposure offsets in stops (DNG and JPEG only).
    noise : shot and read noise (sensor model for DNG; its equivalent for EXR/PNG).
    """

    format: str = "dng"
    spp: int = 64
    light_intensity: float = 28.0
    exposure_variation: float = 0.0
    noise: bool = True


@dataclass(frozen=True)
class OutputSettings:
    """Which files the capture holds besides the photos and gt/.

    write_cameras : the top-level cameras.json (without it the pipeline runs SfM).
    state_light : state the flash's intensity to the pipeline (``light.intensity`` in the
        top-level cameras.json and ``light_intensity`` in capture.yaml), as a calibrated flash
        would. Off by default: no user knows that number, so the pipeline estimates it from the
        photos; the true I_e is in ``gt/cameras.json`` either way.
    write_masks : masks/<stem>.png (pixel coverage > 0.5).
    write_gt_linear : gt/linear/<stem>.exr.
    """

    write_cameras: bool = True
    state_light: bool = False
    write_masks: bool = False
    write_gt_linear: bool = True


@dataclass(frozen=True)
class MaterialSettings:
    """The object's SVBRDF fields (:class:`recon.synth.materials.MaterialFields`).

    texture_size : size of the square ground-truth maps.
    texture_frequency : scale of the albedo pattern (about one dot per (1/frequency)^3).
    albedo, specular, roughness : a constant diffuse albedo (grey, no pattern), specular albedo
        or roughness everywhere instead of the spatially varying fields (None): ``specular=0``
        is a purely diffuse object.
    """

    texture_size: int = 1024
    texture_frequency: float = 16.0
    albedo: float | None = None
    specular: float | None = None
    roughness: float | None = None


@dataclass(frozen=True)
class TabletopSettings:
    """The tabletop scene (:mod:`recon.synth.tabletop`); the stand scene shares the cameras and
    the backdrop.

    elevation_range : camera elevations above the table, degrees (seen from the object's center).
    rings : number of hand-held rings of views (spread over ``elevation_range``).
    distance_jitter : per-view camera distances vary by this fraction around each ring's.
    aim_jitter : standard deviation of the aim point around the object's center (object units).
    roll_jitter : standard deviation of the roll around the optical axis, degrees.
    table_half_size : the table is a square of side 2 * this (object units, the object spans ~1.9).
    table_texture_size : texels along each side of the table's texture.
    background : albedo of a far backdrop lit by the flash (0: black beyond the table).
    background_distance : radius of that backdrop around the object.
    base_cut : the object is cut flat this fraction of its height above its lowest point (the
        mug has a flat base already).
    marker_square : side of the squares of a ChArUco mat printed on the table under the object
        (object units; 0: no mat).
    table : the table top: ``wood`` (grain, rings, blotches and knots: SIFT and the plane sweep find
        texture everywhere) or ``plain`` (a light laminate with faint mottling: almost no texture,
        like a white desk; the masks and SfM must do without the table's features).
    """

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
    table: str = "wood"

    def __post_init__(self):
        object.__setattr__(self, "elevation_range", _floats(self.elevation_range))


@dataclass(frozen=True)
class PhoneSettings:
    """A phone's imaging (:mod:`recon.synth.imaging`), each effect off by default.

    flash_offset : the flash's position in camera coordinates (object units at scale 1; x right,
        y down, z forward), e.g. (0.19, 0, 0): 1 cm beside the lens for a 10-cm object.
    ambient : a constant environment giving this fraction of the flash's irradiance at the
        object (:func:`recon.synth.imaging.ambient_radiance`).
    exposure_jitter : standard deviation (stops) of a per-view exposure error the EXIF does not
        record.
    wb_jitter : standard deviation of per-view, per-channel white-balance log gains.
    falloff : lens falloff ``1 + k1 r^2 + k2 r^4`` (r = 1 in the image corners).
    tone_curve : (``format="jpg"`` only) ``none`` (sRGB), ``phone`` (sRGB + an S-curve) or one the
        optimizer's model does not share (``gamma22``, ``filmic``, ``table``, ``toe_shoulder``:
        :data:`recon.synth.imaging.TONE_CURVES`).
    tone_contrast : the S-curve's exponent p (1 = no S-curve).
    jpeg_quality : JPEG quality (``format="jpg"``).
    falloff_gainmap : (``format="dng"``) the DNG carries the falloff's correction as an
        OpcodeList3 GainMap (17 x 13 points, 3 planes), as phone DNGs do; linearize applies it.
    """

    flash_offset: tuple = (0.0, 0.0, 0.0)
    ambient: float = 0.0
    exposure_jitter: float = 0.0
    wb_jitter: float = 0.0
    falloff: tuple = (0.0, 0.0)
    tone_curve: str = "none"
    tone_contrast: float = 1.4
    jpeg_quality: int = 95
    falloff_gainmap: bool = False

    def __post_init__(self):
        object.__setattr__(self, "flash_offset", _floats(self.flash_offset))
        object.__setattr__(self, "falloff", _floats(self.falloff))


@dataclass(frozen=True)
class VariationSettings:
    """Scene variations that make masks hard, each off by default.

    palette : the object's four diffuse colours (:data:`recon.synth.materials.PALETTES`):
        ``default``, ``wood`` (the table's colours), ``glaze`` (cream, blue, orange), ``dark``.
    texture_pattern : the albedo's fine pattern (dots and fractal shading); False: plain colour
        regions (a glaze).
    wall : tabletop/stand: albedo of a wall behind the object (0: none), a vertical plane
        ``wall_distance`` (x ``cameras.distance``) from the object on the -y side, lit by the flash.
    wall_distance : the wall's distance from the object's centre, in camera distances.
    lamps : tabletop/stand: two room lamps (point lights fixed in the room, above and to the
        sides) giving together this fraction of the flash's irradiance at the object.
    closeups : tabletop/stand: this share of the views is taken from ``closeup_distance`` (x the
        view's distance): the object is cut by the frame's edges there.
    closeup_distance : see ``closeups``.
    stand_height : stand scene: length of the thin pole under the object (object units).
    stand_base : stand scene: albedo of the pole's round base (a white disc: 0.8).
    """

    palette: str = "default"
    texture_pattern: bool = True
    wall: float = 0.0
    wall_distance: float = 2.0
    lamps: float = 0.0
    closeups: float = 0.0
    closeup_distance: float = 0.55
    stand_height: float = 1.2
    stand_base: float = 0.8


_STREAMS = {"noise": 0xA015E, "imaging": 0xF1A5, "tabletop_cameras": 0x7AB1E, "closeups": 0xC105E}
"""The random streams of a capture, each seeded by (seed, its number) (:meth:`SynthSettings.rng`)."""


@sectioned
@dataclass(frozen=True)
class SynthSettings:
    """How to make a synthetic capture (module docstring; each section's docstring has its keys).

    object : ``blob`` (bumps and grooves), ``torus`` (genus 1 with detail), ``smooth``, ...
        (:data:`recon.synth.shapes.OBJECT_KINDS`).
    mesh_level : icosphere subdivision level (the torus gets as many faces): 20 * 4**level faces.
    scene : ``void`` (the object alone, cameras all around), ``tabletop`` (on a table, cameras
        above it), ``tabletop_void`` (the tabletop object and cameras, no table: its peer in the
        void) or ``stand`` (on a pole in a dim room).
    seed : seeds the object, the materials, the table, the cameras' jitter, the renders, the
        noise and the phone's errors (:meth:`rng`, :meth:`view_seed`).
    scale : scene scale: the object, the camera distances and the ground truth are multiplied by
        it and the light intensity by ``scale**2``, so the photos are the same at every scale.
    """

    object: str = "blob"
    mesh_level: int = 6
    scene: str = "void"
    seed: int = 0
    scale: float = 1.0
    cameras: CameraSettings = field(default_factory=CameraSettings)
    photos: PhotoSettings = field(default_factory=PhotoSettings)
    outputs: OutputSettings = field(default_factory=OutputSettings)
    material: MaterialSettings = field(default_factory=MaterialSettings)
    tabletop: TabletopSettings = field(default_factory=TabletopSettings)
    phone: PhoneSettings = field(default_factory=PhoneSettings)
    variations: VariationSettings = field(default_factory=VariationSettings)

    def __post_init__(self):
        self._check_phone()
        c, p, t, v = self.cameras, self.photos, self.tabletop, self.variations
        if self.scene not in SCENES:
            raise SynthError(f"scene={self.scene!r}: choose one of {SCENES}")
        e0, e1 = t.elevation_range
        if not 0.0 < e0 <= e1 < 90.0:
            raise SynthError(f"elevation_range={t.elevation_range}: need 0 < low <= high < 90 degrees "
                             "(cameras above the table)")
        if t.rings < 1:
            raise SynthError(f"rings={t.rings}: need at least 1 ring of views")
        if not 0 <= t.distance_jitter < 0.5 or t.aim_jitter < 0 or t.roll_jitter < 0:
            raise SynthError("distance_jitter must be in [0, 0.5), aim_jitter and roll_jitter >= 0")
        if t.table_half_size <= 2.0:
            raise SynthError(f"table_half_size={t.table_half_size}: the table must be larger than the "
                             "object (> 2)")
        if not 16 <= t.table_texture_size <= 8192:
            raise SynthError(f"table_texture_size={t.table_texture_size}: use 16 to 8192")
        if t.table not in TABLES:
            raise SynthError(f"table={t.table!r}: use one of {', '.join(TABLES)}")
        if not 0.0 <= t.background <= 1.0:
            raise SynthError(f"background={t.background}: an albedo in [0, 1] (0: none)")
        if self.scene in ("tabletop", "stand") and t.background > 0 \
                and t.background_distance <= c.distance * 1.5:
            raise SynthError(f"background_distance={t.background_distance}: the backdrop must be far "
                             f"behind the cameras (> 1.5 x distance = {1.5 * c.distance})")
        if not 0.0 <= t.base_cut < 0.5:
            raise SynthError(f"base_cut={t.base_cut}: use a fraction of the height in [0, 0.5)")
        from recon.synth.materials import PALETTES

        if v.palette not in PALETTES:
            raise SynthError(f"palette={v.palette!r}: choose one of {tuple(PALETTES)}")
        if not 0.0 <= v.wall <= 1.0 or not 0.0 <= v.stand_base <= 1.0:
            raise SynthError(f"wall={v.wall}, stand_base={v.stand_base}: albedos in [0, 1]")
        if v.wall > 0 and not 1.2 <= v.wall_distance <= 20:
            raise SynthError(f"wall_distance={v.wall_distance}: use 1.2 to 20 camera distances")
        if not 0.0 <= v.lamps <= 10.0:
            raise SynthError(f"lamps={v.lamps}: a fraction of the flash irradiance in [0, 10]")
        if not 0.0 <= v.closeups <= 1.0 or not 0.25 <= v.closeup_distance <= 1.0:
            raise SynthError(f"closeups={v.closeups} (a share in [0, 1]) and closeup_distance="
                             f"{v.closeup_distance} (in [0.25, 1])")
        if (v.wall > 0 or v.lamps > 0 or v.closeups > 0) and self.scene not in ("tabletop", "stand"):
            raise SynthError("wall, lamps and closeups need scene='tabletop' or 'stand'")
        if not 0.2 <= v.stand_height <= 5.0:
            raise SynthError(f"stand_height={v.stand_height}: use 0.2 to 5 object units")
        if t.marker_square < 0:
            raise SynthError(f"marker_square={t.marker_square}: a length >= 0 (0: no mat)")
        if self.object not in OBJECT_KINDS:
            raise SynthError(f"object={self.object!r}: choose one of {OBJECT_KINDS}")
        if p.format not in FORMATS:
            raise SynthError(f"format={p.format!r}: choose one of {FORMATS}")
        if c.n_views < 1:
            raise SynthError(f"n_views={c.n_views}: need at least 1 view")
        if c.width < 8 or c.height < 8:
            raise SynthError(f"image size {c.width}x{c.height}: need at least 8x8 pixels")
        if p.format == "dng" and (c.width % 2 or c.height % 2):
            raise SynthError(f"image size {c.width}x{c.height}: DNG (Bayer) needs even sizes")
        if not 1.0 < c.fov < 170.0:
            raise SynthError(f"fov={c.fov}: use a horizontal field of view in (1, 170) degrees")
        if c.distance <= EXTENT_RADIUS:
            raise SynthError(f"distance={c.distance}: cameras must stay outside the object "
                             f"(distance > {EXTENT_RADIUS:.2f})")
        z0, z1 = c.view_z_range
        if not -1.0 <= z0 < z1 <= 1.0:
            raise SynthError(f"view_z_range={c.view_z_range}: need -1 <= z0 < z1 <= 1")
        if p.spp < 1:
            raise SynthError(f"spp={p.spp}: need at least 1 sample per pixel")
        if not np.isfinite(p.light_intensity) or p.light_intensity <= 0:
            raise SynthError(f"light_intensity={p.light_intensity}: must be positive")
        if p.exposure_variation < 0 or p.exposure_variation > 4:
            raise SynthError(f"exposure_variation={p.exposure_variation}: use 0 to 4 stops")
        if p.exposure_variation > 0 and p.format not in ("dng", "jpg"):
            raise SynthError("exposure_variation needs format='dng' or 'jpg' (only they record exposure)")
        if not 0 <= self.mesh_level <= 8:
            raise SynthError(f"mesh_level={self.mesh_level}: use 0 to 8")
        m = self.material
        if not 16 <= m.texture_size <= 8192:
            raise SynthError(f"texture_size={m.texture_size}: use 16 to 8192")
        if m.texture_frequency <= 0:
            raise SynthError(f"texture_frequency={m.texture_frequency}: must be positive")
        for name in ("albedo", "specular"):
            value = getattr(m, name)
            if value is not None and not 0.0 <= value <= 1.0:
                raise SynthError(f"{name}={value}: use a value in [0, 1] (or leave it out for the spatially varying field)")
        if m.roughness is not None and not R_MIN <= m.roughness <= 1.0:
            raise SynthError(f"roughness={m.roughness}: use a value in [{R_MIN}, 1]")
        if not (np.isfinite(self.scale) and 1e-6 <= self.scale <= 1e6):
            raise SynthError(f"scale={self.scale}: use a scene scale in [1e-6, 1e6]")

    def _check_phone(self):
        ph, fmt = self.phone, self.photos.format
        if len(ph.flash_offset) != 3 or not np.all(np.isfinite(ph.flash_offset)):
            raise SynthError(f"flash_offset={ph.flash_offset}: give 3 finite numbers (camera coordinates)")
        if float(np.linalg.norm(ph.flash_offset)) >= 0.5 * self.cameras.distance:
            raise SynthError(f"flash_offset={ph.flash_offset}: a flash beside the lens is much closer than "
                             f"the object (|offset| < distance / 2)")
        if not (np.isfinite(ph.ambient) and 0.0 <= ph.ambient <= 10.0):
            raise SynthError(f"ambient={ph.ambient}: a fraction of the flash irradiance in [0, 10]")
        if not 0.0 <= ph.exposure_jitter <= 2.0 or not 0.0 <= ph.wb_jitter <= 0.5:
            raise SynthError("exposure_jitter must be in [0, 2] stops and wb_jitter in [0, 0.5]")
        if len(ph.falloff) != 2:
            raise SynthError(f"falloff={ph.falloff}: give (k1, k2) of 1 + k1 r^2 + k2 r^4")
        k1, k2 = ph.falloff
        if not (np.isfinite(k1) and np.isfinite(k2)) or 1.0 + k1 + k2 <= 0.05 or 1.0 + min(k1, 0.0) <= 0.05:
            raise SynthError(f"falloff={ph.falloff}: the falloff must stay > 0.05 in the corners")
        from recon.synth.imaging import TONE_CURVES

        if ph.tone_curve not in TONE_CURVES:
            raise SynthError(f"tone_curve={ph.tone_curve!r}: choose one of {TONE_CURVES}")
        if ph.tone_curve != "none" and fmt != "jpg":
            raise SynthError(f"tone_curve={ph.tone_curve!r} needs format='jpg' (a phone's JPEG)")
        if not 0.5 <= ph.tone_contrast <= 4.0:
            raise SynthError(f"tone_contrast={ph.tone_contrast}: use 0.5 to 4")
        if ph.falloff_gainmap and (fmt != "dng" or not any(ph.falloff)):
            raise SynthError("falloff_gainmap needs format='dng' and a falloff to correct")
        if not 50 <= ph.jpeg_quality <= 100:
            raise SynthError(f"jpeg_quality={ph.jpeg_quality}: use 50 to 100")

    @property
    def phone_effects(self) -> bool:
        """Any of the phone's imaging effects switched on (format jpg counts)."""
        return self.photos.format == "jpg" or self.phone != PhoneSettings()

    @property
    def has_variations(self) -> bool:
        """Any of the scene variations (the ``variations`` section) differs from its default."""
        return self.variations != VariationSettings()

    def rng(self, stream: str) -> np.random.Generator:
        """The random generator of ``stream`` (``noise``: the sensor's; ``imaging``: the phone's
        per-view errors; ``tabletop_cameras``: the hand-held rings' jitter; ``closeups``: which
        views are close-ups), seeded by (``seed``, the stream's number)."""
        return np.random.default_rng(np.random.SeedSequence([int(self.seed), _STREAMS[stream]]))

    def view_seed(self, view: int) -> int:
        """The renderer's seed of view ``view`` (and of its coverage masks)."""
        return self.seed * 100003 + view


TABLETOP_FIELDS = ("scene",) + tuple(TabletopSettings.__dataclass_fields__)
"""Settings of the tabletop scene only; a void capture's gt/synth.json leaves them out (so the
files of void captures made before they existed regenerate bit-identically)."""
PHONE_FIELDS = tuple(PhoneSettings.__dataclass_fields__)
"""Settings of a phone's imaging (:mod:`recon.synth.imaging`); gt/synth.json records them only when
one differs from its default (so captures made before they existed regenerate bit-identically)."""
VARIATION_FIELDS = tuple(VariationSettings.__dataclass_fields__)
"""Scene variations that make masks hard; recorded in gt/synth.json only when one differs from its
default, like PHONE_FIELDS."""
RECORDED_ORDER = ("object", "n_views", "width", "height", "fov", "distance", "view_z_range", "format", "spp",
                  "seed", "light_intensity", "write_cameras", "state_light", "write_masks", "write_gt_linear",
                  "exposure_variation", "noise", "mesh_level", "texture_size", "texture_frequency", "albedo",
                  "specular", "roughness", "scale") + TABLETOP_FIELDS + PHONE_FIELDS + VARIATION_FIELDS
"""The order of the flat settings in gt/synth.json, as before the sections (settings added later
follow, in their sections' order)."""


def recorded_settings(s: SynthSettings) -> dict:
    """The settings as gt/synth.json records them: flat (leaf names), in :data:`RECORDED_ORDER`;
    a void capture leaves out TABLETOP_FIELDS, one without a phone's imaging PHONE_FIELDS and one
    without variations VARIATION_FIELDS."""
    flat = flatten(s)
    order = [k for k in RECORDED_ORDER if k in flat] + [k for k in flat if k not in RECORDED_ORDER]
    d = {k: flat[k] for k in order}
    if s.scene == "void":
        d = {k: v for k, v in d.items() if k not in TABLETOP_FIELDS}
    if not s.phone_effects:
        d = {k: v for k, v in d.items() if k not in PHONE_FIELDS}
    if not s.has_variations:
        d = {k: v for k, v in d.items() if k not in VARIATION_FIELDS}
    return d


PRESETS: dict[str, SynthSettings] = {
    # the bundled CI capture (captures/demo): small, DNG, SfM poses (no cameras.json).
    # 32 views ~26 degrees apart: COLMAP registers 31/32 at 192 x 144 when the focal length
    # is held at the DNG's value (28 views ~29 degrees apart: 25/28).
    "demo": SynthSettings(
        object="blob", mesh_level=4, seed=0,
        cameras={"n_views": 32, "width": 192, "height": 144, "fov": 40.0, "distance": 4.0,
                 "view_z_range": (-0.3, 0.9)},
        photos={"format": "dng", "spp": 32, "light_intensity": 28.0, "exposure_variation": 0.5, "noise": True},
        outputs={"write_cameras": False, "write_masks": False, "write_gt_linear": False},
        material={"texture_size": 256, "texture_frequency": 16.0}),
    # benchmark captures
    "blob": SynthSettings(object="blob"),
    "torus": SynthSettings(object="torus"),
    "smooth": SynthSettings(object="smooth"),
    # tabletop captures: the object fills ~40% of the image width, the table around it
    "tabletop": SynthSettings(scene="tabletop", cameras={"fov": 50.0, "distance": 5.0}),
    # tabletop benchmark captures (bench/tabletop.py): 48 views of 512 x 384 on three hand-held rings
    "tabletop-blob": SynthSettings(object="blob", scene="tabletop",
                                   cameras={"fov": 50.0, "distance": 5.0, "n_views": 48, "width": 512, "height": 384}),
    "tabletop-mug": SynthSettings(object="mug", scene="tabletop", seed=1,
                                  cameras={"fov": 50.0, "distance": 5.0, "n_views": 48, "width": 512, "height": 384}),
    # a phone's imaging, every effect on (recon.synth.imaging); switch effects off one by one with
    # the command line (--flash-offset 0 0 0, --ambient 0, ...). 1 cm flash offset at a 10-cm object.
    "phone": SynthSettings(object="blob", mesh_level=5,
                           cameras={"n_views": 32, "width": 192, "height": 144},
                           photos={"format": "jpg", "spp": 64, "exposure_variation": 0.5},
                           material={"texture_size": 512},
                           phone={"flash_offset": (0.19, 0.0, 0.0), "ambient": 0.05, "exposure_jitter": 0.25,
                                  "wb_jitter": 0.03, "falloff": (-0.3, 0.0), "tone_curve": "phone"}),
}
