"""DNG files: the TIFF tags a RAW linearization reads, and Bayer DNGs written for synthetic captures.

Reading: :func:`read_tiff_tags` returns the tags of IFD0, of the raw IFD and of the EXIF IFD of
a DNG (or another TIFF-based RAW) by name, and refuses corrupt or truncated files;
:func:`tag_number` and :func:`tag_rationals` turn TIFF/EXIF values (rationals as (num, den)
pairs) into floats.

Writing: :func:`write_dng` (pidng) stores a CFA image with the tags a RAW linearization needs:
black and white level, CFA pattern, ColorMatrix1 with CalibrationIlluminant1 = D65,
AsShotNeutral, exposure (ExposureTime, PhotographicSensitivity, FNumber), FocalLength with the
focal plane resolution (so the focal length in pixels can be recovered) and, optionally, a
DefaultCrop and a LinearizationTable. The data are stored uncompressed, 12-bit sensors in packed
12-bit samples and others in 16-bit samples (pidng's ``compress=True`` crashes on
Python 3.11); rawpy reads them back bit-exact.
"""

from __future__ import annotations

import logging
import math
import os
from fractions import Fraction
from pathlib import Path

import numpy as np

from recon.io.atomic import atomic_path

CFA_CODES = {"R": 0, "G": 1, "B": 2}
CALIBRATION_ILLUMINANT_D65 = 21
"""EXIF LightSource code of D65 (DNG CalibrationIlluminant)."""
FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)
"""Diagonal of a 35 mm film frame (36 x 24 mm), the reference of FocalLengthIn35mmFilm."""


# ---- reading ----
def tag_number(v) -> float | None:
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


def tag_rationals(v, count: int) -> np.ndarray | None:
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


class _TiffWarnings(logging.Handler):
    """Collects tifffile's warnings while a file is parsed (a corrupt IFD only logs them)."""

    def __init__(self):
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record):
        self.messages.append(record.getMessage())


def read_tiff_tags(path: str | os.PathLike) -> tuple[dict, dict, dict]:
    """(IFD0 tags, raw IFD tags, EXIF tags) of a TIFF-based RAW by tag name; ValueError if corrupt.

    The raw IFD is the one with NewSubfileType 0 and a CFA or LinearRaw photometric (IFD0 itself
    for simple DNGs, a SubIFD for camera DNGs).
    """
    import tifffile

    path = Path(path)
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


# ---- writing ----
def _rational(x: float, max_den: int = 1_000_000) -> list[int]:
    f = Fraction(float(x)).limit_denominator(max_den)
    return [f.numerator, f.denominator]


def _srational_list(values, den: int = 1_000_000) -> list[list[int]]:
    return [[int(round(float(v) * den)), den] for v in np.ravel(values)]


def write_dng(
    path: str | os.PathLike,
    cfa: np.ndarray,
    sensor,
    exposure_time: float,
    iso: float,
    f_number: float,
    focal_length_mm: float | None = None,
    make: str = "recon",
    model: str = "synthetic sensor",
    as_shot_neutral: np.ndarray | None = None,
    default_crop: tuple[int, int, int, int] | None = None,
    linearization_table: np.ndarray | None = None,
) -> Path:
    """Write a Bayer CFA image as an uncompressed DNG, atomically.

    Parameters
    ----------
    path : path-like
        Destination ``.dng``.
    cfa : (H, W) uint16
        RAW counts (as stored: when ``linearization_table`` is given, indices into it).
    sensor : recon.synth.sensor.SensorModel
        Supplies black/white level, bits, CFA pattern, ColorMatrix1 (D65), the default
        AsShotNeutral and the pixel pitch.
    exposure_time, iso, f_number : float
        Seconds, ISO speed, aperture f-number (EXIF ExposureTime, PhotographicSensitivity,
        FNumber).
    focal_length_mm : float, optional
        Lens focal length; written with FocalPlaneX/YResolution (from the pixel pitch) and
        FocalLengthIn35mmFilm.
    make, model : str
        Camera make and model (UniqueCameraModel = "make model").
    as_shot_neutral : (3,) float, optional
        Defaults to ``sensor.as_shot_neutral()`` (D65 white).
    default_crop : (x, y, width, height), optional
        DNG DefaultCropOrigin / DefaultCropSize, in pixels.
    linearization_table : (N,) uint16, optional
        DNG LinearizationTable: the stored value v stands for ``table[v]``.

    Returns
    -------
    Path
        ``path``.
    """
    from pidng.core import RAW2DNG
    from pidng.defs import PhotometricInterpretation
    from pidng.dng import DNGTags, Tag

    path = Path(path)
    cfa = np.asarray(cfa)
    if cfa.ndim != 2 or cfa.dtype != np.uint16:
        raise ValueError(f"{path}: cfa must be a (H, W) uint16 array, got {cfa.shape} {cfa.dtype}")
    h, w = cfa.shape
    if h % 2 or w % 2:
        raise ValueError(f"{path}: CFA width and height must be even, got {w} x {h}")
    if min(h, w) < 22:
        raise ValueError(f"{path}: LibRaw refuses RAW images smaller than 22 pixels, got {w} x {h}")
    if min(exposure_time, iso, f_number) <= 0:
        raise ValueError(f"{path}: exposure_time, iso, f_number must be > 0")
    if not 1 <= iso <= 65535:
        raise ValueError(f"{path}: iso must be in [1, 65535] (a TIFF SHORT), got {iso}")
    if linearization_table is None and int(cfa.max(initial=0)) > sensor.white_level:
        raise ValueError(f"{path}: CFA values exceed the white level {sensor.white_level}")
    neutral = sensor.as_shot_neutral() if as_shot_neutral is None else np.asarray(as_shot_neutral, float)
    if neutral.shape != (3,) or not np.all(neutral > 0):
        raise ValueError(f"{path}: as_shot_neutral must be 3 positive values, got {neutral}")

    t = DNGTags()
    t.set(Tag.ImageWidth, w)
    t.set(Tag.ImageLength, h)
    t.set(Tag.TileWidth, w)
    t.set(Tag.TileLength, h)
    t.set(Tag.Orientation, 1)
    t.set(Tag.PhotometricInterpretation, PhotometricInterpretation.Color_Filter_Array)
    t.set(Tag.SamplesPerPixel, 1)
    # pidng's 14-bit packer is broken (shape mismatch): 14-bit data are stored in 16-bit samples
    t.set(Tag.BitsPerSample, 12 if (sensor.bits == 12 and linearization_table is None) else 16)
    t.set(Tag.CFARepeatPatternDim, [2, 2])
    t.set(Tag.CFAPattern, [CFA_CODES[c] for c in sensor.cfa])
    t.set(Tag.CFAPlaneColor, [0, 1, 2])
    t.set(Tag.CFALayout, 1)
    t.set(Tag.BlackLevelRepeatDim, [1, 1])
    t.set(Tag.BlackLevel, int(sensor.black_level))
    t.set(Tag.WhiteLevel, int(sensor.white_level))
    t.set(Tag.ColorMatrix1, _srational_list(sensor.color_matrix_array))
    t.set(Tag.CalibrationIlluminant1, CALIBRATION_ILLUMINANT_D65)
    t.set(Tag.AsShotNeutral, [_rational(v) for v in neutral])
    t.set(Tag.BaselineExposure, [[0, 1]])
    t.set(Tag.Make, make)
    t.set(Tag.Model, model)
    t.set(Tag.UniqueCameraModel, f"{make} {model}")
    t.set(Tag.ExposureTime, [_rational(exposure_time)])
    t.set(Tag.FNumber, [_rational(f_number, 1000)])
    t.set(Tag.PhotographicSensitivity, int(round(iso)))
    if focal_length_mm is not None:
        if focal_length_mm <= 0:
            raise ValueError(f"{path}: focal_length_mm must be > 0, got {focal_length_mm}")
        t.set(Tag.FocalLength, [_rational(focal_length_mm, 10000)])
        px_per_cm = 1e4 / sensor.pixel_pitch_um
        t.set(Tag.FocalPlaneXResolution, [_rational(px_per_cm, 10000)])
        t.set(Tag.FocalPlaneYResolution, [_rational(px_per_cm, 10000)])
        t.set(Tag.FocalPlaneResolutionUnit, 3)  # centimetres
        diag_mm = math.hypot(w, h) * sensor.pixel_pitch_um * 1e-3
        f35 = int(round(focal_length_mm * FULL_FRAME_DIAGONAL_MM / diag_mm))
        t.set(Tag.FocalLengthIn35mmFilm, max(1, min(f35, 65535)))
    if default_crop is not None:
        x, y, cw, ch = (int(v) for v in default_crop)
        if x < 0 or y < 0 or cw <= 0 or ch <= 0 or x + cw > w or y + ch > h:
            raise ValueError(f"{path}: default_crop {default_crop} does not fit in {w} x {h}")
        t.set(Tag.DefaultCropOrigin, [x, y])
        t.set(Tag.DefaultCropSize, [cw, ch])
    if linearization_table is not None:
        table = np.asarray(linearization_table)
        if table.ndim != 1 or len(table) < 2 or table.max() > 65535 or table.min() < 0:
            raise ValueError(f"{path}: linearization_table must be 1-D with values in [0, 65535]")
        if int(cfa.max(initial=0)) >= len(table):
            raise ValueError(f"{path}: CFA values exceed the linearization table ({len(table)} entries)")
        t.set(Tag.LinearizationTable, [int(v) for v in table])

    converter = RAW2DNG()
    converter.options(t, path="", compress=False)
    buf = converter.convert(np.ascontiguousarray(cfa), filename="")
    with atomic_path(path) as tmp:
        tmp.write_bytes(bytes(buf))
    return path
