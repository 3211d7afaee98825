"""Stage 'linearize': a capture's photos to scene-linear Rec.709 images on one common scale.

Input: ``<capture>/images/`` (DESIGN section 1). Output, written atomically as one folder
(DESIGN section 2)::

    <out_dir>/<stem>.exr           float32 (H, W, 3) linear Rec.709 (D65 white)
    <out_dir>/<stem>.sat.png       clipped-pixel mask (255 = clipped: never use in a loss)
    <out_dir>/preview/<stem>.jpg   sRGB preview, one gain for the whole capture
    <out_dir>/linear.json          per-image metadata (see :func:`linearize_capture`)

The scale of the output
-----------------------
Every view is scaled to the capture's reference exposure ``H_ref`` (by default the median over
the views of ``H = exposure_time * iso / 100 / f_number**2``) by the factor ``H_ref / H``. For
RAW files, 1.0 is the level of a neutral (white-balanced grey) surface whose brightest RAW
channel just reaches the white level at ``H_ref``: the camera-to-XYZ matrix is normalized so
that the camera neutral with largest channel 1 maps to Y = 1 (the DNG convention for
ForwardMatrix, applied to the ColorMatrix path too). For JPEG/PNG, 1.0 is the largest code
value at ``H_ref``; EXR files pass through unchanged (scale 1).

RAW pipeline (DNG specification 1.6, chapter 6)
-----------------------------------------------
rawpy/LibRaw applies the LinearizationTable, subtracts the black level and demosaics in the
camera's native space (no white balance, no colour conversion, linear 16-bit output scaled so
the white level is 65535). The DNG DefaultCrop is then applied. The camera neutral (one for the
whole capture: the median AsShotNeutral, or fixed multipliers) and the DNG colour tags
(ColorMatrix1/2 interpolated by the white's colour temperature, CameraCalibration,
AnalogBalance, ForwardMatrix when present) give camera -> XYZ; a Bradford adaptation takes the
scene white (or D50 for ForwardMatrix) to D65, then XYZ -> linear Rec.709. Clipped pixels are
found on the RAW values before demosaicing: any sample in the pixel's neighbourhood at or above
``black + saturation_threshold * (white - black)``.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
from fractions import Fraction
from pathlib import Path

import numpy as np

from recon.io.atomic import atomic_dir
from recon.io.images import (
    HDR_EXTENSIONS,
    IMAGE_EXTENSIONS,
    LDR_EXTENSIONS,
    RAW_EXTENSIONS,
    ImageError,
    linear_to_srgb,
    read_exr,
    read_ldr,
    srgb_to_linear,
    write_exr,
    write_jpg,
    write_mask,
)

log = logging.getLogger(__name__)

DEMOSAIC_ALGORITHMS = ("LINEAR", "VNG", "PPG", "AHD", "DCB", "DHT", "AAHD")
WHITE_BALANCE_MODES = ("as_shot_median", "fixed")
FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)
D50_XY = (0.3457, 0.3585)
D65_XY = (0.3127, 0.3290)

# DNG CalibrationIlluminant (EXIF LightSource) -> colour temperature in kelvin, as the DNG SDK
# (dng_camera_profile.cpp, IlluminantToTemperature) uses them for matrix interpolation.
ILLUMINANT_TEMPERATURE = {
    1: 5500.0, 2: 4150.0, 3: 2850.0, 4: 5500.0, 9: 5500.0, 10: 6500.0, 11: 7500.0,
    12: 6400.0, 13: 5050.0, 14: 4150.0, 15: 3525.0, 16: 2925.0, 17: 2850.0, 18: 5500.0,
    19: 6500.0, 20: 5500.0, 21: 6500.0, 22: 7500.0, 23: 5000.0, 24: 3200.0,
}


class LinearizeError(ValueError):
    """A capture that cannot be linearized; the message names the file and the fix."""


@dataclasses.dataclass(frozen=True)
class LinearizeSettings:
    """Settings of the linearize stage (config section ``linearize``).

    Attributes
    ----------
    demosaic : str
        LibRaw demosaic algorithm, one of :data:`DEMOSAIC_ALGORITHMS`. Default 'DHT': on
        synthetic renders with pixel-scale texture it had the smallest per-pixel error and
        colour bias (foreground channel means within 1 %, against up to 9 % red bias for AHD,
        PPG, DCB, AAHD and VNG), at about 2x AHD's time; every algorithm keeps the native
        CFA samples exactly. With 'VNG' (wider footprint) use ``saturation_radius`` 2 or more.
    white_balance : str
        'as_shot_median': ONE white balance for all views, the per-channel median of the views'
        as-shot camera neutrals (the flash does not change); 'fixed': ``wb_multipliers``.
        JPEG/PNG/EXR views are already white balanced and are never rebalanced.
    wb_multipliers : (3,) float, optional
        Camera-channel gains (R, G, B) for 'fixed'; the neutral is their reciprocal.
    saturation_threshold : float
        A RAW sample at or above ``black + threshold * (white - black)`` is clipped.
    saturation_radius : int
        A pixel is marked clipped when any RAW sample within this many pixels is (1 = 3x3, which
        holds every colour of a Bayer pattern).
    exposure_reference : str or float
        'median' (the capture's median exposure H) or an explicit H in seconds at f/1, ISO 100.
    clip_negative : bool
        Set negative output values (noise, colours outside Rec.709) to 0.
    preview_max_size : int
        Longest side of the previews in pixels (0 = full size).
    preview_exposure : str or float
        'auto' (one gain for the capture: the median over views of the 99th percentile of the
        unclipped luminance goes to 0.9) or a gain in EV applied to the linear values.
    preview_quality : int
        JPEG quality of the previews.
    """

    demosaic: str = "DHT"
    white_balance: str = "as_shot_median"
    wb_multipliers: tuple | None = None
    saturation_threshold: float = 0.98
    saturation_radius: int = 1
    exposure_reference: str | float = "median"
    clip_negative: bool = False
    preview_max_size: int = 1024
    preview_exposure: str | float = "auto"
    preview_quality: int = 90

    def __post_init__(self):
        if self.demosaic.upper() not in DEMOSAIC_ALGORITHMS:
            raise ValueError(f"demosaic must be one of {DEMOSAIC_ALGORITHMS}, got {self.demosaic!r}")
        if self.white_balance not in WHITE_BALANCE_MODES:
            raise ValueError(
                f"white_balance must be one of {WHITE_BALANCE_MODES}, got {self.white_balance!r}"
            )
        if self.white_balance == "fixed":
            m = self.wb_multipliers
            if m is None or len(m) != 3 or not all(float(v) > 0 and math.isfinite(float(v)) for v in m):
                raise ValueError(
                    "white_balance 'fixed' needs wb_multipliers: three positive gains (R, G, B)"
                )
            object.__setattr__(self, "wb_multipliers", tuple(float(v) for v in m))
        if not 0.0 < self.saturation_threshold <= 1.0:
            raise ValueError(f"saturation_threshold must be in (0, 1], got {self.saturation_threshold}")
        if self.saturation_radius < 0:
            raise ValueError(f"saturation_radius must be >= 0, got {self.saturation_radius}")
        ref = self.exposure_reference
        if isinstance(ref, str):
            if ref != "median":
                raise ValueError(f"exposure_reference must be 'median' or a number > 0, got {ref!r}")
        elif not (float(ref) > 0 and math.isfinite(float(ref))):
            raise ValueError(f"exposure_reference must be 'median' or a number > 0, got {ref!r}")
        pe = self.preview_exposure
        if isinstance(pe, str) and pe != "auto":
            raise ValueError(f"preview_exposure must be 'auto' or a number (EV), got {pe!r}")
        if self.preview_max_size < 0:
            raise ValueError(f"preview_max_size must be >= 0, got {self.preview_max_size}")
        if not 1 <= self.preview_quality <= 100:
            raise ValueError(f"preview_quality must be in [1, 100], got {self.preview_quality}")


# ---- small helpers ----
def _xy_to_xyz(xy) -> np.ndarray:
    x, y = float(xy[0]), float(xy[1])
    return np.array([x / y, 1.0, (1.0 - x - y) / y])


def _xyz_to_xy(xyz) -> np.ndarray:
    s = float(np.sum(xyz))
    return np.array([xyz[0] / s, xyz[1] / s])


def _num(v) -> float | None:
    """A TIFF/EXIF number (int, float, (num, den) tuple, Fraction) as float; None if unusable."""
    if v is None:
        return None
    if isinstance(v, np.ndarray):
        v = v.ravel().tolist()
    if isinstance(v, (tuple, list)) and len(v) == 1:
        v = v[0]
    if isinstance(v, (tuple, list)) and len(v) == 2:
        num, den = v
        if den == 0:
            return None
        v = num / den
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def _rationals(v, count: int) -> np.ndarray | None:
    """A TIFF (S)RATIONAL array tag (flat num, den pairs) as ``count`` floats."""
    if v is None:
        return None
    a = np.asarray(v, dtype=np.float64).ravel()
    if a.size == 2 * count:
        num, den = a[0::2], a[1::2]
        if np.any(den == 0):
            return None
        a = num / den
    if a.size != count or not np.all(np.isfinite(a)):
        return None
    return a


def exposure_value(exposure_time: float | None, iso: float | None, f_number: float | None) -> float:
    """H = exposure_time * iso / 100 / f_number**2; a missing factor counts as 1 (ISO 100)."""
    t = 1.0 if exposure_time is None else exposure_time
    s = 1.0 if iso is None else iso / 100.0
    n = 1.0 if f_number is None else f_number
    return float(t * s / n**2)


# ---- per-view metadata ----
@dataclasses.dataclass
class _View:
    path: Path
    kind: str  # 'raw' | 'ldr' | 'hdr'
    exposure_time: float | None = None
    iso: float | None = None
    f_number: float | None = None
    focal_length_mm: float | None = None
    focal_length_35mm: float | None = None
    focal_plane_px_per_mm: float | None = None
    neutral: np.ndarray | None = None  # as-shot camera neutral (RAW)
    color: dict | None = None  # colour tags (RAW)
    is_dng: bool = False
    default_crop: tuple | None = None  # (x, y, w, h)
    linearization_table_max: int | None = None
    baseline_exposure: float | None = None
    opcode_lists: list = dataclasses.field(default_factory=list)
    make: str | None = None
    model: str | None = None

    @property
    def stem(self) -> str:
        return self.path.stem


class _TiffWarnings(logging.Handler):
    """Collects tifffile's warnings while a file is parsed (a corrupt IFD only logs them)."""

    def __init__(self):
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record):
        self.messages.append(record.getMessage())


def _read_tiff_tags(path: Path) -> tuple[dict, dict, dict]:
    """(IFD0 tags, raw IFD tags, EXIF tags) of a TIFF-based RAW by tag name; ValueError if corrupt.

    The raw IFD is the one with NewSubfileType 0 and a CFA or LinearRaw photometric (IFD0 itself
    for simple DNGs, a SubIFD for camera DNGs).
    """
    import tifffile

    tl = logging.getLogger("tifffile")
    handler = _TiffWarnings()
    tl.addHandler(handler)
    try:
        with tifffile.TiffFile(path) as tf:
            size = path.stat().st_size
            ifd0 = tf.pages[0]
            candidates = [ifd0]
            if ifd0.subifds:
                try:
                    candidates += list(ifd0.pages)
                except Exception as e:
                    raise ValueError(f"unreadable SubIFDs ({e})") from e
            raw = None
            for page in candidates:
                st = page.tags.get("NewSubfileType")
                st = 0 if st is None else int(st.value)
                if st == 0 and page.photometric in (32803, 34892):
                    raw = page
                    break
            tags0 = {t.name: t.value for t in ifd0.tags.values()}
            tags_raw = {t.name: t.value for t in raw.tags.values()} if raw is not None else {}
            exif = dict(tags0.get("ExifTag") or {})
            if raw is not None:
                offsets = raw.dataoffsets
                counts = raw.databytecounts
                if not offsets or any(o + c > size for o, c in zip(offsets, counts, strict=True)):
                    raise ValueError(
                        f"image data end beyond the end of the file ({size} bytes): truncated"
                    )
    finally:
        tl.removeHandler(handler)
    if handler.messages:
        raise ValueError("corrupt TIFF structure: " + "; ".join(handler.messages[:3]))
    return tags0, tags_raw, exif


def _read_raw_meta(path: Path) -> _View:
    import rawpy

    view = _View(path, "raw")
    with open(path, "rb") as f:
        is_tiff = f.read(4) in (b"II*\x00", b"MM\x00*")
    tags0, tags_raw, exif = {}, {}, {}
    if path.suffix.lower() == ".dng":
        try:
            tags0, tags_raw, exif = _read_tiff_tags(path)
        except Exception as e:
            raise LinearizeError(
                f"{path}: corrupt or truncated RAW file ({e}); "
                "copy the file from the camera again or remove it from images/"
            ) from e
    elif is_tiff:  # TIFF-based camera RAW (CR2, NEF, ARW, ...): EXIF when tifffile can read it
        try:
            tags0, tags_raw, exif = _read_tiff_tags(path)
        except Exception as e:
            log.warning("%s: TIFF metadata not readable (%s); using LibRaw's", path, e)
    view.is_dng = "DNGVersion" in tags0
    if path.suffix.lower() == ".dng" and not view.is_dng:
        raise LinearizeError(f"{path}: not a DNG file (no DNGVersion tag); re-export it as DNG")

    def tag(name):
        for d in (tags_raw, exif, tags0):
            if name in d:
                return d[name]
        return None

    try:
        with rawpy.RawPy() as raw:
            raw.open_file(str(path))
            other = raw.other
            desc = raw.color_desc
            cam_wb = np.asarray(raw.camera_whitebalance, dtype=np.float64)
            rgb_xyz = np.asarray(raw.rgb_xyz_matrix, dtype=np.float64).copy()
    except rawpy.LibRawError as e:
        raise LinearizeError(
            f"{path}: not a RAW file rawpy can read ({type(e).__name__}: {e}); "
            "the file is corrupt or truncated, or the camera is not supported by LibRaw"
        ) from e
    if desc[:3] != b"RGB":
        raise LinearizeError(f"{path}: colour filter {desc!r} is not RGB; only RGB sensors are supported")

    view.exposure_time = _num(tag("ExposureTime")) or (other.shutter_speed or None)
    view.iso = _num(tag("ISOSpeedRatings")) or _num(tag("PhotographicSensitivity")) or (other.iso_speed or None)
    view.f_number = _num(tag("FNumber")) or (other.aperture or None)
    view.focal_length_mm = _num(tag("FocalLength")) or (other.focal_length or None)
    view.focal_length_35mm = _num(tag("FocalLengthIn35mmFilm")) or None
    view.focal_plane_px_per_mm = _focal_plane_px_per_mm(tag)
    view.make = tag("Make")
    view.model = tag("Model") or tag("UniqueCameraModel")

    if view.is_dng:
        color = {
            "color_matrix_1": _rationals(tag("ColorMatrix1"), 9),
            "color_matrix_2": _rationals(tag("ColorMatrix2"), 9),
            "forward_matrix_1": _rationals(tag("ForwardMatrix1"), 9),
            "forward_matrix_2": _rationals(tag("ForwardMatrix2"), 9),
            "camera_calibration_1": _rationals(tag("CameraCalibration1"), 9),
            "camera_calibration_2": _rationals(tag("CameraCalibration2"), 9),
            "analog_balance": _rationals(tag("AnalogBalance"), 3),
            "illuminant_1": int(_num(tag("CalibrationIlluminant1")) or 0),
            "illuminant_2": int(_num(tag("CalibrationIlluminant2")) or 0),
        }
        if color["color_matrix_1"] is None:
            raise LinearizeError(
                f"{path}: the DNG has no usable ColorMatrix1 (missing or corrupt), so camera colour "
                "cannot be converted to Rec.709; re-export the DNG with its colour profile"
            )
        neutral = _rationals(tag("AsShotNeutral"), 3)
        if neutral is None and tag("AsShotWhiteXY") is not None:
            xy = _rationals(tag("AsShotWhiteXY"), 2)
            if xy is not None:
                neutral = _xyz_to_camera(color, xy) @ _xy_to_xyz(xy)
        if neutral is None:
            neutral = _xyz_to_camera(color, D65_XY) @ _xy_to_xyz(D65_XY)
            log.warning("%s: no AsShotNeutral; assuming D65 light", path)
        view.neutral = neutral
        view.color = color
        origin = _rationals(tag("DefaultCropOrigin"), 2)
        size = _rationals(tag("DefaultCropSize"), 2)
        if origin is not None and size is not None:
            view.default_crop = tuple(int(round(v)) for v in (*origin, *size))
        lt = tag("LinearizationTable")
        if lt is not None:
            view.linearization_table_max = int(np.max(np.asarray(lt)))
        view.baseline_exposure = _num(_rationals(tag("BaselineExposure"), 1))
        view.opcode_lists = [n for n in ("OpcodeList1", "OpcodeList2", "OpcodeList3") if tag(n) is not None]
        if view.opcode_lists:
            log.warning(
                "%s: DNG %s not applied (lens shading GainMap / distortion opcodes are ignored)",
                path, ", ".join(view.opcode_lists),
            )
    else:
        cm = rgb_xyz[:3]
        if not np.any(cm):
            raise LinearizeError(
                f"{path}: LibRaw has no colour matrix for this camera; convert the file to DNG "
                "(Adobe DNG Converter) so it carries one"
            )
        view.color = {"color_matrix_1": cm.ravel(), "illuminant_1": 21}
        if cam_wb[:3].min() <= 0:
            view.neutral = cm @ _xy_to_xyz(D65_XY)
            log.warning("%s: no as-shot white balance; assuming D65 light", path)
        else:
            view.neutral = 1.0 / cam_wb[:3]
    if view.neutral is None or not np.all(np.isfinite(view.neutral)) or np.min(view.neutral) <= 0:
        raise LinearizeError(f"{path}: unusable as-shot white balance {view.neutral}")
    view.neutral = np.asarray(view.neutral, dtype=np.float64) / float(np.max(view.neutral))
    return view


def _focal_plane_px_per_mm(tag) -> float | None:
    res = _num(tag("FocalPlaneXResolution"))
    unit = _num(tag("FocalPlaneResolutionUnit"))
    mm = {2: 25.4, 3: 10.0, 4: 1.0, 5: 1e-3}.get(int(unit) if unit else 2)
    if not res or res <= 0 or mm is None:
        return None
    return res / mm


def _read_ldr_meta(path: Path) -> _View:
    from PIL import Image, UnidentifiedImageError

    view = _View(path, "ldr")
    try:
        with Image.open(path) as im:
            exif = im.getexif()
            sub = dict(exif.get_ifd(0x8769)) if exif else {}
    except (UnidentifiedImageError, OSError, SyntaxError) as e:
        raise LinearizeError(f"{path}: not a readable {path.suffix} image ({e}); re-export it") from e
    tags = {**dict(exif or {}), **sub}

    def get(code):
        return _num(tags.get(code))

    view.exposure_time = get(0x829A)
    view.f_number = get(0x829D)
    view.iso = get(0x8827)
    view.focal_length_mm = get(0x920A)
    view.focal_length_35mm = get(0xA405) or None
    view.make = tags.get(0x010F)
    view.model = tags.get(0x0110)
    # the focal plane resolution of a JPEG often refers to the sensor, not the (resized) JPEG
    return view


def _read_meta(path: Path) -> _View:
    ext = path.suffix.lower()
    if ext in RAW_EXTENSIONS:
        return _read_raw_meta(path)
    if ext in LDR_EXTENSIONS:
        return _read_ldr_meta(path)
    if ext in HDR_EXTENSIONS:
        return _View(path, "hdr")
    raise LinearizeError(
        f"{path}: unknown image type '{path.suffix}'; supported: {', '.join(IMAGE_EXTENSIONS)}"
    )


# ---- colour (DNG specification 1.6, chapter 6) ----
def _temperature_weight(color: dict, xy) -> float:
    """Weight of the first calibration illuminant for the white ``xy`` (inverse-CCT interpolation)."""
    t1 = ILLUMINANT_TEMPERATURE.get(color.get("illuminant_1", 0), 0.0)
    t2 = ILLUMINANT_TEMPERATURE.get(color.get("illuminant_2", 0), 0.0)
    if color.get("color_matrix_2") is None or t1 <= 0 or t2 <= 0 or t1 == t2:
        return 1.0
    import colour

    t = float(colour.xy_to_CCT(np.asarray(xy, dtype=np.float64), method="McCamy 1992"))
    t = min(max(t, 1000.0), 50000.0)
    (lo, w_lo), (hi, w_hi) = sorted([(t1, 1.0), (t2, 0.0)])
    if t <= lo:
        return w_lo
    if t >= hi:
        return w_hi
    g = (1.0 / t - 1.0 / hi) / (1.0 / lo - 1.0 / hi)  # weight of the lower temperature
    return g if w_lo == 1.0 else 1.0 - g


def _interp(color: dict, key: str, g: float) -> np.ndarray | None:
    m1 = color.get(f"{key}_1")
    m2 = color.get(f"{key}_2")
    if m1 is None:
        return None
    m1 = np.asarray(m1, dtype=np.float64).reshape(3, 3)
    if m2 is None or g >= 1.0:
        return m1
    return g * m1 + (1.0 - g) * np.asarray(m2, dtype=np.float64).reshape(3, 3)


def _ab_cc(color: dict, g: float) -> np.ndarray:
    cc = _interp(color, "camera_calibration", g)
    cc = np.eye(3) if cc is None else cc
    ab = color.get("analog_balance")
    ab = np.eye(3) if ab is None else np.diag(np.asarray(ab, dtype=np.float64))
    return ab @ cc


def _xyz_to_camera(color: dict, xy) -> np.ndarray:
    g = _temperature_weight(color, xy)
    return _ab_cc(color, g) @ _interp(color, "color_matrix", g)


def camera_to_rec709(color: dict, neutral: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The (3, 3) matrix camera native -> linear Rec.709 (D65) for the camera neutral ``neutral``.

    Parameters
    ----------
    color : dict
        DNG colour tags: ``color_matrix_1/2``, ``forward_matrix_1/2``, ``camera_calibration_1/2``
        ((9,) arrays or None), ``analog_balance`` ((3,) or None), ``illuminant_1/2`` (EXIF codes).
    neutral : (3,) float
        Camera response to the scene white.

    Returns
    -------
    matrix : (3, 3) float64
        Normalized so that ``neutral / max(neutral)`` maps to Rec.709 (1, 1, 1).
    white_xy : (2,) float64
        Chromaticity of the scene white.
    """
    import colour

    neutral = np.asarray(neutral, dtype=np.float64)
    # the white's chromaticity: fixed point of xy -> xy(inv(XYZtoCamera(xy)) @ neutral)
    xy = np.array(D50_XY)
    for _ in range(50):
        xyz = np.linalg.solve(_xyz_to_camera(color, xy), neutral)
        new = _xyz_to_xy(xyz)
        if not np.all(np.isfinite(new)):
            raise ValueError(f"camera neutral {neutral} maps to no valid white chromaticity")
        done = np.max(np.abs(new - xy)) < 1e-7
        xy = new
        if done:
            break
    g = _temperature_weight(color, xy)
    ab_cc = _ab_cc(color, g)
    fm = _interp(color, "forward_matrix", g)
    if fm is not None:
        ref_neutral = np.linalg.solve(ab_cc, neutral)
        cam_to_xyz = fm @ np.diag(1.0 / ref_neutral) @ np.linalg.inv(ab_cc)
        source_white = _xy_to_xyz(D50_XY)
    else:
        cam_to_xyz = np.linalg.inv(ab_cc @ _interp(color, "color_matrix", g))
        source_white = _xy_to_xyz(xy)
    cat = colour.adaptation.matrix_chromatic_adaptation_VonKries(
        source_white, _xy_to_xyz(D65_XY), transform="Bradford"
    )
    xyz_to_709 = colour.RGB_COLOURSPACES["ITU-R BT.709"].matrix_XYZ_to_RGB
    m = xyz_to_709 @ cat @ cam_to_xyz
    y = (cat @ cam_to_xyz @ (neutral / neutral.max()))[1]
    if not (np.isfinite(y) and y > 0):
        raise ValueError(f"camera neutral {neutral} has no positive luminance")
    return m / y, xy


# ---- decoding one view ----
def _decode_raw(view: _View, settings: LinearizeSettings) -> tuple[np.ndarray, np.ndarray, dict]:
    """Camera-native linear (H, W, 3) float32 (1 = white level), clipped mask (H, W), levels."""
    import rawpy

    path = view.path
    try:
        with rawpy.imread(str(path)) as raw:
            raw_visible = raw.raw_image_visible.copy()
            colors = raw.raw_colors_visible.copy()
            black = np.asarray(raw.black_level_per_channel, dtype=np.float64)
            white = libraw_white = float(raw.white_level)
            cam_white = raw.camera_white_level_per_channel
            if cam_white is not None and min(cam_white) > 0:
                white = min(white, float(min(cam_white)))
            if view.linearization_table_max is not None:
                white = min(white, float(view.linearization_table_max))
            if white <= black.max():
                raise LinearizeError(f"{path}: white level {white} is not above the black level {black}")
            rgb16 = raw.postprocess(
                demosaic_algorithm=getattr(rawpy.DemosaicAlgorithm, settings.demosaic.upper()),
                output_color=rawpy.ColorSpace.raw,
                use_camera_wb=False,
                use_auto_wb=False,
                user_wb=[1.0, 1.0, 1.0, 1.0],
                no_auto_bright=True,
                no_auto_scale=False,
                gamma=(1, 1),
                output_bps=16,
                user_flip=0,
                adjust_maximum_thr=0.0,
                highlight_mode=rawpy.HighlightMode.Clip,
                fbdd_noise_reduction=rawpy.FBDDNoiseReductionMode.Off,
            )
    except rawpy.LibRawError as e:
        raise LinearizeError(
            f"{path}: the RAW data cannot be decoded ({type(e).__name__}: {e}); the file is "
            "truncated or corrupt: copy it from the camera again or remove it from images/"
        ) from e
    if rgb16.shape[:2] != raw_visible.shape[:2]:
        raise LinearizeError(
            f"{path}: demosaiced size {rgb16.shape[:2]} differs from the RAW size "
            f"{raw_visible.shape[:2]}; this RAW layout is not supported"
        )
    # clipped samples, on RAW values before demosaicing
    if raw_visible.ndim == 3:  # LinearRaw: all channels per pixel
        thr = black[: raw_visible.shape[2]] + settings.saturation_threshold * (white - black[: raw_visible.shape[2]])
        clipped = np.any(raw_visible >= thr, axis=2)
    else:
        black_px = black[np.clip(colors, 0, 3)]
        clipped = raw_visible >= black_px + settings.saturation_threshold * (white - black_px)
    if settings.saturation_radius > 0 and clipped.any():
        import cv2

        k = 2 * settings.saturation_radius + 1
        clipped = cv2.dilate(clipped.astype(np.uint8), np.ones((k, k), np.uint8)) > 0
    # LibRaw scales (raw - black) by 65535 / (its white level - black); rescale so that the
    # effective white level (a LinearizationTable may end below WhiteLevel) is 1
    libraw_white = float(libraw_white)
    b = float(np.mean(black))
    cam = rgb16.astype(np.float32) * np.float32((libraw_white - b) / (white - b) / 65535.0)
    if view.default_crop is not None:
        x, y, w, h = view.default_crop
        H, W = cam.shape[:2]
        if x < 0 or y < 0 or w <= 0 or h <= 0 or x + w > W or y + h > H:
            raise LinearizeError(
                f"{path}: DefaultCrop (origin {x},{y}, size {w}x{h}) does not fit the {W}x{H} image"
            )
        cam = cam[y : y + h, x : x + w]
        clipped = clipped[y : y + h, x : x + w]
    levels = {"black_level": black.tolist(), "white_level": white}
    return np.ascontiguousarray(cam), clipped, levels


def _as_rgb(img: np.ndarray) -> np.ndarray:
    if img.shape[2] == 1:
        return np.repeat(img, 3, axis=2)
    return img[:, :, :3]


def _decode(view: _View, settings: LinearizeSettings, matrix: np.ndarray | None) -> tuple:
    """Linear Rec.709 (H, W, 3) float32 before the exposure scale, clipped mask, levels."""
    if view.kind == "raw":
        cam, clipped, levels = _decode_raw(view, settings)
        rgb = cam.reshape(-1, 3) @ matrix.T.astype(np.float32)
        return rgb.reshape(cam.shape).astype(np.float32), clipped, levels
    if view.kind == "ldr":
        try:
            img, bits = read_ldr(view.path)
        except ImageError as e:
            raise LinearizeError(str(e)) from e
        img = _as_rgb(img)
        clipped = np.any(img >= 1.0, axis=2)
        return srgb_to_linear(img), clipped, {"bits": bits}
    try:
        img = _as_rgb(read_exr(view.path))
    except ImageError as e:
        raise LinearizeError(str(e)) from e
    if not np.all(np.isfinite(img)):
        raise LinearizeError(f"{view.path}: the EXR contains NaN or Inf values; fix the file")
    return img.astype(np.float32), np.zeros(img.shape[:2], bool), {}


# ---- the capture ----
def list_images(capture_dir: str | os.PathLike) -> list[Path]:
    """The capture's photos (``images/<file>``, sorted); LinearizeError for a bad folder."""
    folder = Path(capture_dir) / "images"
    if not folder.is_dir():
        raise LinearizeError(
            f"{folder}: no images/ folder; a capture holds its photos in images/ (DESIGN section 1)"
        )
    files = sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith("."))
    if not files:
        raise LinearizeError(f"{folder}: images/ is empty; put the capture's photos there")
    for p in files:
        if p.suffix.lower() not in IMAGE_EXTENSIONS:
            raise LinearizeError(
                f"{p}: unknown image type '{p.suffix}'; supported: {', '.join(IMAGE_EXTENSIONS)} "
                "(remove or convert the file)"
            )
    stems: dict[str, Path] = {}
    for p in files:
        if p.stem in stems:
            raise LinearizeError(f"{p}: same name as {stems[p.stem]}; image stems must be unique")
        stems[p.stem] = p
    return files


def _check_exposure_fields(views: list[_View]) -> None:
    for field in ("exposure_time", "iso", "f_number"):
        have = [getattr(v, field) is not None for v in views]
        if any(have) and not all(have):
            missing = next(v for v, h in zip(views, have, strict=True) if not h)
            raise LinearizeError(
                f"{missing.path}: no {field} in its metadata while other views have one, so its "
                "exposure cannot be matched to the rest; give every view the same metadata"
            )
        for v in views:
            val = getattr(v, field)
            if val is not None and not val > 0:
                raise LinearizeError(f"{v.path}: invalid {field} {val} in its metadata")


def _focal_length_px(view: _View, width: int, height: int) -> tuple[float | None, str | None]:
    if view.focal_length_mm and view.focal_plane_px_per_mm:
        return view.focal_length_mm * view.focal_plane_px_per_mm, "focal_plane_resolution"
    if view.focal_length_35mm:
        return view.focal_length_35mm * math.hypot(width, height) / FULL_FRAME_DIAGONAL_MM, "35mm_equivalent"
    return None, None


def _json_num(x):
    if x is None:
        return None
    if isinstance(x, Fraction):
        x = float(x)
    return float(x)


def linearize_capture(
    capture_dir: str | os.PathLike,
    out_dir: str | os.PathLike,
    settings: LinearizeSettings | None = None,
) -> dict:
    """Linearize every photo of a capture into ``out_dir`` (written atomically as one folder).

    Parameters
    ----------
    capture_dir : path-like
        The capture folder (holding ``images/``).
    out_dir : path-like
        The stage folder, ``results/<capture>/linear``; replaced on success, untouched on error.
    settings : LinearizeSettings, optional

    Returns
    -------
    dict
        The content of ``linear.json``: ``color_space``, ``scale`` (what 1.0 means),
        ``exposure_reference`` (H_ref), ``white_balance`` (mode, camera neutral, white xy),
        ``preview_gain``, ``width``, ``height``, and ``images``: per stem ``source`` (path
        relative to the capture), ``exr``, ``sat``, ``preview`` (relative to ``out_dir``),
        ``kind``, ``width``, ``height``, ``exposure_time``, ``iso``, ``f_number``, ``exposure``
        (H), ``exposure_scale`` (H_ref / H), ``as_shot_neutral``, ``camera_to_rec709``
        (3 x 3, RAW), ``color_matrix`` (XYZ -> camera as used), ``calibration_illuminant``,
        ``black_level``, ``white_level``, ``default_crop``, ``linearization_table``,
        ``fraction_clipped``, ``focal_length_mm``, ``focal_length_35mm``, ``focal_length_px``
        and ``focal_length_source``.
    """
    settings = settings or LinearizeSettings()
    capture_dir = Path(capture_dir)
    out_dir = Path(out_dir)
    files = list_images(capture_dir)
    log.info("linearize %s: %d images", capture_dir, len(files))
    views = [_read_meta(p) for p in files]
    kinds = sorted({v.kind for v in views})
    if len(kinds) > 1:
        first = {k: next(v.path for v in views if v.kind == k) for k in kinds}
        raise LinearizeError(
            f"{capture_dir / 'images'}: mixes image kinds ({', '.join(f'{k}: {p.name}' for k, p in first.items())}); "
            "RAW, JPEG/PNG and EXR have different radiometric scales: use one kind per capture"
        )
    kind = kinds[0]
    _check_exposure_fields(views)
    exposures = [exposure_value(v.exposure_time, v.iso, v.f_number) for v in views]
    if settings.exposure_reference == "median" or kind == "hdr":
        h_ref = float(np.median(exposures))
    else:
        h_ref = float(settings.exposure_reference)
    if kind == "hdr":  # EXR passes through unchanged
        exposures = [h_ref] * len(views)

    # ONE white balance for the capture
    matrix, white_xy, neutral = None, None, None
    if kind == "raw":
        if settings.white_balance == "fixed":
            neutral = 1.0 / np.asarray(settings.wb_multipliers, dtype=np.float64)
        else:
            neutral = np.median(np.stack([v.neutral for v in views]), axis=0)
        neutral = neutral / neutral.max()
        # same camera: the colour tags of the first view serve all
        try:
            matrix, white_xy = camera_to_rec709(views[0].color, neutral)
        except (ValueError, np.linalg.LinAlgError) as e:
            raise LinearizeError(f"{views[0].path}: unusable colour metadata ({e})") from e
    elif settings.white_balance == "fixed":
        log.info("JPEG/PNG/EXR views are already white balanced: wb_multipliers not applied")

    images: dict[str, dict] = {}
    size = None
    first_path = None
    p99 = []
    with atomic_dir(out_dir) as tmp:
        (tmp / "preview").mkdir()
        for i, (view, h) in enumerate(zip(views, exposures, strict=True)):
            rgb, clipped, levels = _decode(view, settings, matrix)
            height, width = rgb.shape[:2]
            if size is None:
                size, first_path = (width, height), view.path
            elif (width, height) != size:
                raise LinearizeError(
                    f"{view.path}: size {width}x{height} differs from {first_path.name} "
                    f"({size[0]}x{size[1]}); every view of a capture must come from the same camera "
                    "at the same size"
                )
            scale = h_ref / h
            rgb *= np.float32(scale)
            if settings.clip_negative:
                np.maximum(rgb, 0.0, out=rgb)
            if not np.all(np.isfinite(rgb)):
                raise LinearizeError(f"{view.path}: linearization produced NaN/Inf values")
            write_exr(tmp / f"{view.stem}.exr", rgb)
            write_mask(tmp / f"{view.stem}.sat.png", clipped)
            lum = rgb[~clipped] @ np.array([0.2126, 0.7152, 0.0722], np.float32)
            p99.append(float(np.percentile(lum, 99)) if lum.size else 0.0)
            frac = float(clipped.mean())
            f_px, f_src = _focal_length_px(view, width, height)
            entry = {
                "source": os.path.relpath(view.path, capture_dir),
                "exr": f"{view.stem}.exr",
                "sat": f"{view.stem}.sat.png",
                "preview": f"preview/{view.stem}.jpg",
                "kind": view.kind,
                "width": width,
                "height": height,
                "exposure_time": _json_num(view.exposure_time),
                "iso": _json_num(view.iso),
                "f_number": _json_num(view.f_number),
                "exposure": h,
                "exposure_scale": scale,
                "fraction_clipped": frac,
                "focal_length_mm": _json_num(view.focal_length_mm),
                "focal_length_35mm": _json_num(view.focal_length_35mm),
                "focal_length_px": f_px,
                "focal_length_source": f_src,
                "make": str(view.make) if view.make else None,
                "model": str(view.model) if view.model else None,
                **levels,
            }
            if view.kind == "raw":
                entry.update(
                    {
                        "as_shot_neutral": view.neutral.tolist(),
                        "camera_to_rec709": matrix.tolist(),
                        "color_matrix": _xyz_to_camera(view.color, white_xy).tolist(),
                        "calibration_illuminant": [view.color.get("illuminant_1"), view.color.get("illuminant_2")],
                        "default_crop": list(view.default_crop) if view.default_crop else None,
                        "linearization_table": view.linearization_table_max is not None,
                        "baseline_exposure": view.baseline_exposure,
                        "opcode_lists_ignored": view.opcode_lists,
                        "dng": view.is_dng,
                    }
                )
            images[view.stem] = entry
            log.info(
                "linearize [%d/%d] %s: %dx%d, exposure scale %.4g, %.3f%% clipped",
                i + 1, len(views), view.path.name, width, height, scale, 100 * frac,
            )

        # previews: one gain for the capture
        if isinstance(settings.preview_exposure, str):
            ref = float(np.median(p99))
            gain = 0.9 / ref if ref > 0 else 1.0
        else:
            gain = 2.0 ** float(settings.preview_exposure)
        for view in views:
            rgb = read_exr(tmp / f"{view.stem}.exr")
            write_jpg(
                tmp / "preview" / f"{view.stem}.jpg",
                linear_to_srgb(_resize(rgb, settings.preview_max_size) * np.float32(gain)),
                quality=settings.preview_quality,
            )

        record = {
            "version": 1,
            "color_space": "linear Rec.709 (D65)",
            "scale": (
                "each view scaled to the reference exposure H_ref (H = exposure_time * iso / 100 / "
                "f_number^2); RAW: 1.0 = a neutral surface whose brightest RAW channel reaches the "
                "white level at H_ref; JPEG/PNG: 1.0 = the largest code value at H_ref; EXR: unchanged"
            ),
            "kind": kind,
            "width": size[0],
            "height": size[1],
            "exposure_reference": h_ref,
            "white_balance": {
                "mode": settings.white_balance if kind == "raw" else "none (already white balanced)",
                "camera_neutral": None if neutral is None else neutral.tolist(),
                "white_xy": None if white_xy is None else white_xy.tolist(),
            },
            "preview_gain": gain,
            "settings": dataclasses.asdict(settings),
            "images": images,
        }
        (tmp / "linear.json").write_text(json.dumps(record, indent=1))
    log.info("linearize %s: done -> %s", capture_dir, out_dir)
    return record


def _resize(rgb: np.ndarray, max_size: int) -> np.ndarray:
    h, w = rgb.shape[:2]
    if max_size <= 0 or max(h, w) <= max_size:
        return rgb
    import cv2

    s = max_size / max(h, w)
    return cv2.resize(rgb, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA)
