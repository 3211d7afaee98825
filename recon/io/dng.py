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
Python 3.11); rawpy reads them back bit-exact. ``opcode_list2`` / ``opcode_list3`` add DNG
opcode lists (lens-shading GainMaps, as phones write them).

Opcode lists (DNG specification 1.6, chapter 7): :func:`read_opcode_list` parses an
OpcodeList1/2/3 tag into :class:`Opcode` records (always big-endian), :func:`write_opcode_list`
encodes them; :meth:`GainMap.from_opcode` / :meth:`GainMap.to_opcode` convert the GainMap
opcode (ID 9) and :meth:`GainMap.gains` evaluates its bilinear interpolation at pixel centres
exactly as the DNG SDK does (``dng_gain_map.cpp``). Applying the gains to an image is the
linearize stage's job (:mod:`recon.linearize.opcodes`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import struct
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


# ---- opcode lists (DNG specification 1.6, chapter 7) ----
OPCODE_NAMES = {
    1: "WarpRectilinear", 2: "WarpFisheye", 3: "FixVignetteRadial", 4: "FixBadPixelsConstant",
    5: "FixBadPixelsList", 6: "TrimBounds", 7: "MapTable", 8: "MapPolynomial", 9: "GainMap",
    10: "DeltaPerRow", 11: "DeltaPerColumn", 12: "ScalePerRow", 13: "ScalePerColumn", 14: "WarpRectilinear2",
}
"""DNG opcode IDs and their names (DNG specification 1.6, chapter 7)."""
OPCODE_GAIN_MAP = 9
OPCODE_FLAG_OPTIONAL = 1
"""Flag bit: a reader that does not know the opcode may skip it."""
OPCODE_FLAG_PREVIEW_SKIP = 2
"""Flag bit: the opcode may be skipped for previews."""
OPCODE_LIST_TAGS = ("OpcodeList1", "OpcodeList2", "OpcodeList3")
"""Tag names, in processing order: OpcodeList1 on the raw data as stored, OpcodeList2 after
linearization (LinearizationTable, black level, scaling to [0, 1]), OpcodeList3 after
demosaicing."""
_GAIN_MAP_HEADER = struct.Struct(">10I4dI")  # Top..ColPitch, MapPointsV/H, spacing, origin, MapPlanes


@dataclasses.dataclass(frozen=True)
class Opcode:
    """One opcode of an opcode list: its ID, the DNG version it needs, its flags and its
    parameter bytes (big-endian, as stored)."""

    id: int
    version: int
    flags: int
    params: bytes

    @property
    def name(self) -> str:
        return OPCODE_NAMES.get(self.id, f"unknown opcode {self.id}")

    @property
    def optional(self) -> bool:
        return bool(self.flags & OPCODE_FLAG_OPTIONAL)


def read_opcode_list(data) -> list[Opcode]:
    """Parse an OpcodeList1/2/3 tag value (bytes or a sequence of byte values).

    Raises ValueError for a list whose length fields do not add up (a truncated or corrupt tag).
    """
    buf = bytes(bytearray(np.asarray(data, dtype=np.uint8).ravel())) if not isinstance(data, bytes) else data
    if len(buf) < 4:
        raise ValueError(f"opcode list of {len(buf)} bytes: too short for its count")
    (count,) = struct.unpack_from(">I", buf, 0)
    pos, ops = 4, []
    for k in range(count):
        if pos + 16 > len(buf):
            raise ValueError(f"opcode list truncated in the header of opcode {k + 1} of {count}")
        op_id, version, flags, size = struct.unpack_from(">4I", buf, pos)
        pos += 16
        if pos + size > len(buf):
            raise ValueError(f"opcode list truncated in the parameters of opcode {k + 1} of {count} "
                             f"({OPCODE_NAMES.get(op_id, op_id)}: {size} bytes announced)")
        ops.append(Opcode(op_id, version, flags, buf[pos:pos + size]))
        pos += size
    return ops


def write_opcode_list(opcodes) -> bytes:
    """Encode opcodes (:class:`Opcode` or :class:`GainMap`) as an OpcodeList tag value."""
    out = [struct.pack(">I", len(opcodes))]
    for op in opcodes:
        op = op.to_opcode() if isinstance(op, GainMap) else op
        out.append(struct.pack(">4I", op.id, op.version, op.flags, len(op.params)) + op.params)
    return b"".join(out)


@dataclasses.dataclass(frozen=True, eq=False)
class GainMap:
    """The GainMap opcode (ID 9, DNG 1.3): a 2-D map of gains, bilinearly interpolated, that
    multiplies the pixels of a rectangle (lens shading, colour shading).

    Attributes
    ----------
    top, left, bottom, right : int
        The rectangle (rows top..bottom-1, columns left..right-1) it applies to, in the
        coordinates of the image at its stage; all 0 = the whole image.
    plane, planes : int
        The first image plane and the number of planes it applies to.
    row_pitch, col_pitch : int
        It applies to every ``row_pitch``-th row and ``col_pitch``-th column from ``top`` /
        ``left`` (2 and 2 with a top/left offset address one colour of a Bayer pattern).
    spacing : (float, float)
        MapSpacingV, MapSpacingH: distance between map points in relative image coordinates
        (0 = top/left edge, 1 = bottom/right edge of the whole image).
    origin : (float, float)
        MapOriginV, MapOriginH: relative position of the first map point.
    gains : (MapPointsV, MapPointsH, MapPlanes) float32
        Image plane ``plane + k`` uses map plane ``min(k + plane, MapPlanes - 1)`` as the SDK does.
    version, flags : int
        The opcode's DNG version and flags.
    """

    top: int
    left: int
    bottom: int
    right: int
    plane: int
    planes: int
    row_pitch: int
    col_pitch: int
    spacing: tuple[float, float]
    origin: tuple[float, float]
    gains: np.ndarray
    version: int = 0x01030000
    flags: int = 0

    def __post_init__(self):
        g = np.asarray(self.gains, dtype=np.float32)
        if g.ndim == 2:
            g = g[:, :, None]
        if g.ndim != 3 or min(g.shape) < 1:
            raise ValueError(f"GainMap gains must be (MapPointsV, MapPointsH, MapPlanes), got {g.shape}")
        if not np.all(np.isfinite(g)):
            raise ValueError("GainMap gains must be finite")
        object.__setattr__(self, "gains", g)
        spacing = [float(v) for v in self.spacing]
        origin = [float(v) for v in self.origin]
        for axis in (0, 1):  # a single map point: the SDK ignores spacing and origin
            if g.shape[axis] == 1:
                spacing[axis], origin[axis] = 1.0, 0.0
        if min(spacing) <= 0 or not all(math.isfinite(v) for v in spacing + origin):
            raise ValueError(f"GainMap spacing must be > 0 and origin finite, got {self.spacing}, {self.origin}")
        object.__setattr__(self, "spacing", tuple(spacing))
        object.__setattr__(self, "origin", tuple(origin))
        if self.row_pitch < 1 or self.col_pitch < 1 or self.planes < 1:
            raise ValueError(f"GainMap row/column pitch and planes must be >= 1, got {self.row_pitch}, "
                             f"{self.col_pitch}, {self.planes}")
        if self.bottom < self.top or self.right < self.left or min(self.top, self.left) < 0:
            raise ValueError(f"GainMap area top {self.top}, left {self.left}, bottom {self.bottom}, "
                             f"right {self.right} is not a rectangle")

    @property
    def points(self) -> tuple[int, int]:
        return self.gains.shape[0], self.gains.shape[1]

    @classmethod
    def from_opcode(cls, op: Opcode) -> GainMap:
        """The GainMap of an opcode with ID 9; ValueError when its parameters do not add up."""
        if op.id != OPCODE_GAIN_MAP:
            raise ValueError(f"opcode {op.name} is not a GainMap")
        n = _GAIN_MAP_HEADER.size
        if len(op.params) < n:
            raise ValueError(f"GainMap parameters of {len(op.params)} bytes: shorter than its header ({n})")
        (top, left, bottom, right, plane, planes, row_pitch, col_pitch, pv, ph, sv, sh, ov, oh,
         map_planes) = _GAIN_MAP_HEADER.unpack_from(op.params, 0)
        count = pv * ph * map_planes
        if count < 1 or len(op.params) != n + 4 * count:
            raise ValueError(f"GainMap of {pv} x {ph} points x {map_planes} planes needs {n + 4 * count} "
                             f"parameter bytes, the opcode has {len(op.params)}")
        gains = np.frombuffer(op.params, dtype=">f4", count=count, offset=n).astype(np.float32)
        return cls(top, left, bottom, right, plane, planes, row_pitch, col_pitch, (sv, sh), (ov, oh),
                   gains.reshape(pv, ph, map_planes), op.version, op.flags)

    def to_opcode(self) -> Opcode:
        pv, ph, mp = self.gains.shape
        params = _GAIN_MAP_HEADER.pack(self.top, self.left, self.bottom, self.right, self.plane, self.planes,
                                       self.row_pitch, self.col_pitch, pv, ph, *self.spacing, *self.origin, mp)
        return Opcode(OPCODE_GAIN_MAP, self.version, self.flags, params + self.gains.astype(">f4").tobytes())

    def area(self, height: int, width: int) -> tuple[slice, slice]:
        """The rows and columns (slices with the pitches) it applies to in a ``height`` x ``width``
        image, as the SDK's ``dng_area_spec::Overlap``; an all-zero rectangle covers the image."""
        if self.top == self.left == self.bottom == self.right == 0:
            top, left, bottom, right = 0, 0, height, width
        else:
            top, left, bottom, right = self.top, self.left, min(self.bottom, height), min(self.right, width)
        return slice(top, max(top, bottom), self.row_pitch), slice(left, max(left, right), self.col_pitch)

    def gains_at(self, rows: np.ndarray, cols: np.ndarray, height: int, width: int, map_plane: int = 0) -> np.ndarray:
        """(len(rows), len(cols)) float32 gains of map plane ``map_plane`` at the centres of the
        pixels ``rows`` x ``cols`` of a ``height`` x ``width`` image: relative position
        ``(row + 0.5) / height`` (the same for columns), minus the origin, over the spacing gives
        a map index, clamped to the map; bilinear between map points (dng_gain_map.cpp)."""
        g = self.gains[:, :, min(map_plane, self.gains.shape[2] - 1)].astype(np.float64)

        def index(pix, size, origin, spacing, points):
            f = ((np.asarray(pix, dtype=np.float64) + 0.5) / size - origin) / spacing
            f = np.clip(f, 0.0, points - 1)
            i0 = np.minimum(np.floor(f).astype(np.int64), points - 1)
            return i0, np.minimum(i0 + 1, points - 1), f - i0

        r0, r1, fr = index(rows, height, self.origin[0], self.spacing[0], g.shape[0])
        c0, c1, fc = index(cols, width, self.origin[1], self.spacing[1], g.shape[1])
        fr = fr[:, None]
        top = g[r0][:, c0] * (1 - fc) + g[r0][:, c1] * fc
        bottom = g[r1][:, c0] * (1 - fc) + g[r1][:, c1] * fc
        return (top * (1 - fr) + bottom * fr).astype(np.float32)


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
    opcode_list2=None,
    opcode_list3=None,
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
    opcode_list2, opcode_list3 : sequence of Opcode or GainMap, or bytes, optional
        DNG OpcodeList2 (applied to the linearized CFA data, e.g. per-colour lens-shading
        GainMaps) and OpcodeList3 (applied after demosaicing).

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

    for tag, ops in (((51009, (7, 1)), opcode_list2), ((51022, (7, 1)), opcode_list3)):  # UNDEFINED
        if ops is not None:
            blob = ops if isinstance(ops, bytes) else write_opcode_list(list(ops))
            read_opcode_list(blob)  # refuse what a reader could not parse
            t.set(tag, list(blob))

    converter = RAW2DNG()
    converter.options(t, path="", compress=False)
    buf = converter.convert(np.ascontiguousarray(cfa), filename="")
    with atomic_path(path) as tmp:
        tmp.write_bytes(bytes(buf))
    return path
