"""What a photo's file says about it: exposure, focal length, camera, and for RAW files the
black/white levels' companions (DefaultCrop, LinearizationTable), the as-shot camera neutral and
the DNG colour tags.

RAW files: the DNG tags through :func:`recon.io.dng.read_tiff_tags` (rawpy's
``rgb_xyz_matrix`` is zeros for DNGs), LibRaw's values where a tag is missing; other TIFF-based
RAWs (CR2, NEF, ARW, ...) take LibRaw's colour matrix and white balance. JPEG/PNG: the EXIF
tags through Pillow. EXR: nothing (scene-linear, unchanged).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from pathlib import Path

import numpy as np

from recon.io.dng import (
    CALIBRATION_ILLUMINANT_D65,
    FULL_FRAME_DIAGONAL_MM,
    read_tiff_tags,
    tag_number,
    tag_rationals,
)
from recon.io.images import (
    HDR_EXTENSIONS,
    HEIF_EXTENSIONS,
    IMAGE_EXTENSIONS,
    LDR_EXTENSIONS,
    RAW_EXTENSIONS,
    register_heif,
)
from recon.linearize.color import D65_XY, xy_to_xyz, xyz_to_camera
from recon.linearize.opcodes import Opcodes, read_opcodes
from recon.linearize.settings import LinearizeError

log = logging.getLogger(__name__)


def exposure_value(exposure_time: float | None, iso: float | None, f_number: float | None) -> float:
    """H = exposure_time * iso / 100 / f_number**2; a missing factor counts as 1 (ISO 100)."""
    t = 1.0 if exposure_time is None else exposure_time
    s = 1.0 if iso is None else iso / 100.0
    n = 1.0 if f_number is None else f_number
    return float(t * s / n**2)


@dataclasses.dataclass
class View:
    """The metadata of one photo (None: the file does not say)."""

    path: Path
    kind: str  # 'raw' | 'ldr' | 'hdr'
    exposure_time: float | None = None
    iso: float | None = None
    f_number: float | None = None
    focal_length_mm: float | None = None
    focal_length_35mm: float | None = None
    focal_plane_px_per_mm: float | None = None
    # the image width (pixels) the focal plane resolution refers to: EXIF PixelXDimension of a
    # camera's JPEG (the width the camera wrote; None: the file's own width)
    focal_plane_width: int | None = None
    flash: int | None = None  # EXIF Flash (bit 0: fired; None: the file does not say)
    orientation: int | None = None  # EXIF Orientation 1-8: how the stored pixels are turned for display
    neutral: np.ndarray | None = None  # as-shot camera neutral (RAW)
    color: dict | None = None  # colour tags (RAW)
    is_dng: bool = False
    default_crop: tuple | None = None  # (x, y, w, h)
    linearization_table_max: int | None = None
    baseline_exposure: float | None = None
    opcodes: Opcodes = dataclasses.field(default_factory=Opcodes)  # DNG opcode lists (RAW)
    make: str | None = None
    model: str | None = None

    @property
    def stem(self) -> str:
        return self.path.stem


def _read_raw_meta(path: Path) -> View:
    import rawpy

    view = View(path, "raw")
    with open(path, "rb") as f:
        is_tiff = f.read(4) in (b"II*\x00", b"MM\x00*")
    tags0, tags_raw, exif = {}, {}, {}
    if path.suffix.lower() == ".dng":
        try:
            tags0, tags_raw, exif = read_tiff_tags(path)
        except Exception as e:
            raise LinearizeError(
                f"{path}: corrupt or truncated RAW file ({e}); "
                "copy the file from the camera again or remove it from images/"
            ) from e
    elif is_tiff:  # TIFF-based camera RAW (CR2, NEF, ARW, ...): EXIF when tifffile can read it
        try:
            tags0, tags_raw, exif = read_tiff_tags(path)
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
            flip = int(getattr(raw.sizes, "flip", 0) or 0)
    except rawpy.LibRawError as e:
        raise LinearizeError(
            f"{path}: not a RAW file rawpy can read ({type(e).__name__}: {e}); "
            "the file is corrupt or truncated, or the camera is not supported by LibRaw"
        ) from e
    if desc[:3] != b"RGB":
        raise LinearizeError(f"{path}: colour filter {desc!r} is not RGB; only RGB sensors are supported")

    view.exposure_time = tag_number(tag("ExposureTime")) or (other.shutter_speed or None)
    view.iso = tag_number(tag("ISOSpeedRatings")) or tag_number(tag("PhotographicSensitivity")) or (other.iso_speed or None)
    view.f_number = tag_number(tag("FNumber")) or (other.aperture or None)
    view.focal_length_mm = tag_number(tag("FocalLength")) or (other.focal_length or None)
    view.focal_length_35mm = tag_number(tag("FocalLengthIn35mmFilm")) or None
    view.focal_plane_px_per_mm = _focal_plane_px_per_mm(tag)
    view.flash = _flash(tag("Flash"))
    # IFD0's (the image as a whole), else LibRaw's flip of a camera's own RAW format
    view.orientation = _orientation(tags0.get("Orientation")) or _orientation(tag("Orientation")) \
        or {3: 3, 5: 8, 6: 6}.get(flip)
    view.make = tag("Make")
    view.model = tag("Model") or tag("UniqueCameraModel")

    if view.is_dng:
        color = {
            "color_matrix_1": tag_rationals(tag("ColorMatrix1"), 9),
            "color_matrix_2": tag_rationals(tag("ColorMatrix2"), 9),
            "forward_matrix_1": tag_rationals(tag("ForwardMatrix1"), 9),
            "forward_matrix_2": tag_rationals(tag("ForwardMatrix2"), 9),
            "camera_calibration_1": tag_rationals(tag("CameraCalibration1"), 9),
            "camera_calibration_2": tag_rationals(tag("CameraCalibration2"), 9),
            "analog_balance": tag_rationals(tag("AnalogBalance"), 3),
            "illuminant_1": int(tag_number(tag("CalibrationIlluminant1")) or 0),
            "illuminant_2": int(tag_number(tag("CalibrationIlluminant2")) or 0),
        }
        if color["color_matrix_1"] is None:
            raise LinearizeError(
                f"{path}: the DNG has no usable ColorMatrix1 (missing or corrupt), so camera colour "
                "cannot be converted to Rec.709; re-export the DNG with its colour profile"
            )
        neutral = tag_rationals(tag("AsShotNeutral"), 3)
        if neutral is None and tag("AsShotWhiteXY") is not None:
            xy = tag_rationals(tag("AsShotWhiteXY"), 2)
            if xy is not None:
                neutral = xyz_to_camera(color, xy) @ xy_to_xyz(xy)
        if neutral is None:
            neutral = xyz_to_camera(color, D65_XY) @ xy_to_xyz(D65_XY)
            log.warning("%s: no AsShotNeutral; assuming D65 light", path)
        view.neutral = neutral
        view.color = color
        origin = tag_rationals(tag("DefaultCropOrigin"), 2)
        size = tag_rationals(tag("DefaultCropSize"), 2)
        if origin is not None and size is not None:
            view.default_crop = tuple(int(round(v)) for v in (*origin, *size))
        lt = tag("LinearizationTable")
        if lt is not None:
            view.linearization_table_max = int(np.max(np.asarray(lt)))
        view.baseline_exposure = tag_number(tag_rationals(tag("BaselineExposure"), 1))
        view.opcodes = read_opcodes(path, tag)
    else:
        cm = rgb_xyz[:3]
        if not np.any(cm):
            raise LinearizeError(
                f"{path}: LibRaw has no colour matrix for this camera; convert the file to DNG "
                "(Adobe DNG Converter) so it carries one"
            )
        view.color = {"color_matrix_1": cm.ravel(), "illuminant_1": CALIBRATION_ILLUMINANT_D65}
        if cam_wb[:3].min() <= 0:
            view.neutral = cm @ xy_to_xyz(D65_XY)
            log.warning("%s: no as-shot white balance; assuming D65 light", path)
        else:
            view.neutral = 1.0 / cam_wb[:3]
    if view.neutral is None or not np.all(np.isfinite(view.neutral)) or np.min(view.neutral) <= 0:
        raise LinearizeError(f"{path}: unusable as-shot white balance {view.neutral}")
    view.neutral = np.asarray(view.neutral, dtype=np.float64) / float(np.max(view.neutral))
    return view


def _focal_plane_px_per_mm(tag) -> float | None:
    """EXIF FocalPlaneXResolution in pixels per millimetre (FocalPlaneResolutionUnit 2: inch,
    the default; 3: cm; 4: mm; 5: um); None when missing or not positive."""
    res = tag_number(tag("FocalPlaneXResolution"))
    unit = tag_number(tag("FocalPlaneResolutionUnit"))
    mm = {2: 25.4, 3: 10.0, 4: 1.0, 5: 1e-3}.get(int(unit) if unit else 2)
    if not res or res <= 0 or mm is None:
        return None
    return res / mm


def _flash(value) -> int | None:
    """EXIF Flash as an integer (bit 0: the flash fired); None when the file does not say."""
    v = tag_number(value)
    if v is None or not math.isfinite(v) or v < 0:
        return None
    return int(v)


def flash_fired(view: View) -> bool | None:
    """Did the flash fire for this photo (EXIF Flash, bit 0)? None when the file does not say."""
    return None if view.flash is None else bool(view.flash & 1)


def _read_ldr_meta(path: Path) -> View:
    from PIL import ExifTags, Image, UnidentifiedImageError

    if path.suffix.lower() in HEIF_EXTENSIONS:
        register_heif()
    view = View(path, "ldr")
    try:
        with Image.open(path) as im:
            exif = im.getexif()
            sub = dict(exif.get_ifd(0x8769)) if exif else {}
    except (UnidentifiedImageError, OSError, SyntaxError) as e:
        raise LinearizeError(f"{path}: not a readable {path.suffix} image ({e}); re-export it") from e
    tags = {**dict(exif or {}), **sub}

    def get(code):
        return tag_number(tags.get(code))

    view.exposure_time = get(0x829A)
    view.f_number = get(0x829D)
    view.iso = get(0x8827)
    view.focal_length_mm = get(0x920A)
    view.focal_length_35mm = get(0xA405) or None
    # FocalPlaneXResolution (0xA20E) and its unit (0xA210): pixels per unit of sensor width at
    # the width the camera wrote, PixelXDimension (0xA002); a resized copy scales with its width
    named = {ExifTags.TAGS.get(code, code): v for code, v in tags.items()}
    view.focal_plane_px_per_mm = _focal_plane_px_per_mm(named.get)
    width = get(0xA002)
    view.focal_plane_width = int(width) if width and width > 0 else None
    view.flash = _flash(tags.get(0x9209))
    view.orientation = _orientation(tags.get(0x0112))
    view.make = tags.get(0x010F)
    view.model = tags.get(0x0110)
    return view


def _orientation(value) -> int | None:
    """EXIF Orientation (1-8), None when absent or out of range."""
    v = tag_number(value)
    return int(v) if v is not None and float(v).is_integer() and 1 <= v <= 8 else None


# EXIF Orientation -> the direction (camera x right, y down) in the stored pixels that is up in the
# photo as displayed: 1-2 the top row is the top; 3-4 the bottom row is; 5-6 the first column is
# (a phone held upright, its sensor stored sideways); 7-8 the last column is
ORIENTATION_UP = {1: (0.0, -1.0, 0.0), 2: (0.0, -1.0, 0.0), 3: (0.0, 1.0, 0.0), 4: (0.0, 1.0, 0.0),
                  5: (-1.0, 0.0, 0.0), 6: (-1.0, 0.0, 0.0), 7: (1.0, 0.0, 0.0), 8: (1.0, 0.0, 0.0)}


def camera_up(orientation: int | None) -> tuple[float, float, float]:
    """The displayed photo's up direction in camera coordinates (x right, y down in the stored
    pixels), by its EXIF Orientation (None: the pixels are upright)."""
    return ORIENTATION_UP.get(orientation or 1, ORIENTATION_UP[1])


def read_meta(path: Path) -> View:
    """The metadata of the photo ``path`` by its kind (extension); LinearizeError for a file that
    cannot be read."""
    ext = path.suffix.lower()
    if ext in RAW_EXTENSIONS:
        return _read_raw_meta(path)
    if ext in LDR_EXTENSIONS:
        return _read_ldr_meta(path)
    if ext in HDR_EXTENSIONS:
        return View(path, "hdr")
    raise LinearizeError(
        f"{path}: unknown image type '{path.suffix}'; supported: {', '.join(IMAGE_EXTENSIONS)}"
    )


SENSOR_WIDTH_MM = (1.0, 80.0)
"""Sensor widths a focal plane resolution may imply (a phone's 4 mm to a medium-format 54 mm):
outside, the tag is taken for a wrong one and not used."""


_IMPLAUSIBLE_PLANE: set[tuple[float, float]] = set()  # (px/mm, width) values already warned about


def _focal_plane_px(view: View, width: int) -> float | None:
    """FocalLength x FocalPlaneXResolution in pixels of a ``width``-wide image: the resolution
    refers to the width the camera wrote (a JPEG's PixelXDimension, else the file's own), so a
    copy reduced later scales with it; None when the tags are missing or imply no plausible
    sensor."""
    if not (view.focal_length_mm and view.focal_plane_px_per_mm):
        return None
    ref = view.focal_plane_width or width
    sensor_mm = ref / view.focal_plane_px_per_mm
    if not SENSOR_WIDTH_MM[0] <= sensor_mm <= SENSOR_WIDTH_MM[1]:
        # once per value: a camera writes the same tag into every photo
        key = (round(float(view.focal_plane_px_per_mm), 6), round(float(ref), 3))
        (log.debug if key in _IMPLAUSIBLE_PLANE else log.warning)(
            "%s: FocalPlaneXResolution %.4g px/mm implies a %.3g mm wide sensor: not used for the focal length%s",
            view.path, view.focal_plane_px_per_mm, sensor_mm,
            "" if key in _IMPLAUSIBLE_PLANE else " (nor in the other photos that say the same)")
        _IMPLAUSIBLE_PLANE.add(key)
        return None
    return view.focal_length_mm * view.focal_plane_px_per_mm * width / ref


def focal_length_px(view: View, width: int, height: int) -> tuple[float | None, str | None]:
    """The focal length in pixels of a ``width`` x ``height`` image and where it came from;
    (None, None) when the file says nothing usable.

    RAW: the focal plane resolution (the sensor's own pixels), else the 35 mm equivalent over
    the diagonal. JPEG/PNG/HEIC: the 35 mm equivalent first (a phone computes it for the image
    it writes), else FocalLength x FocalPlaneXResolution (``focal_plane_resolution``): DSLRs such
    as the Canon EOS Rebel T3 write no 35 mm equivalent (55 mm x 4720.4 px/inch = 10,221 px at
    4272 px wide, SfM found 4.6 % less: a prior of a few percent, not the truth)."""
    f_plane = _focal_plane_px(view, width)
    f_35 = view.focal_length_35mm * math.hypot(width, height) / FULL_FRAME_DIAGONAL_MM \
        if view.focal_length_35mm else None
    order = (("focal_plane_resolution", f_plane), ("35mm_equivalent", f_35)) if view.kind == "raw" else \
        (("35mm_equivalent", f_35), ("focal_plane_resolution", f_plane))
    for source, f in order:
        if f is not None:
            return f, source
    return None, None
