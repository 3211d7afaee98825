"""Image files and colour encodings.

Arrays are float32 ``(H, W, C)`` with the first row at the top of the image. Colour spaces
change only here, at file boundaries: names say which one an array is in
(``rgb_linear``, ``rgb_srgb``).
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from recon.io.atomic import atomic_path

log = logging.getLogger(__name__)

RAW_EXTENSIONS = (".dng", ".cr2", ".cr3", ".nef", ".arw", ".raf", ".rw2", ".orf", ".pef", ".srw")
HEIF_EXTENSIONS = (".heic", ".heif")  # iPhones' default; decoded by pillow-heif
LDR_EXTENSIONS = (".jpg", ".jpeg", ".png") + HEIF_EXTENSIONS
HDR_EXTENSIONS = (".exr",)
IMAGE_EXTENSIONS = RAW_EXTENSIONS + LDR_EXTENSIONS + HDR_EXTENSIONS


class ImageError(ValueError):
    """An image file that cannot be used; the message names the file and the fix."""


# ---- sRGB transfer function (IEC 61966-2-1) ----
def srgb_to_linear(rgb_srgb: np.ndarray) -> np.ndarray:
    """Decode sRGB-encoded values in [0, 1] to linear."""
    c = np.asarray(rgb_srgb, dtype=np.float32)
    return np.where(c <= 0.04045, c / 12.92, ((np.maximum(c, 0.04045) + 0.055) / 1.055) ** 2.4).astype(
        np.float32
    )


def linear_to_srgb(rgb_linear: np.ndarray) -> np.ndarray:
    """Encode linear values to sRGB, clipped to [0, 1]."""
    c = np.clip(np.asarray(rgb_linear, dtype=np.float32), 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(np.maximum(c, 0.0031308), 1 / 2.4) - 0.055).astype(
        np.float32
    )


# ---- EXR ----
def _as_hwc(image: np.ndarray, path) -> np.ndarray:
    a = np.asarray(image)
    if a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3 or a.shape[2] not in (1, 3, 4):
        raise ValueError(f"{path}: expected an (H, W), (H, W, 1), (H, W, 3) or (H, W, 4) image, got {a.shape}")
    return a


HALF_MAX = 65504.0
"""Largest finite half float (IEEE 754 binary16)."""
HALF_MIN_SCALE = 2.0**-8
"""Smallest 99th percentile of |values| written as half: there the absolute step near zero (at most
6e-8, subnormal halfs) stays below 1.5e-5 of the image's scale."""


def half_precision_suffices(a: np.ndarray) -> bool:
    """Whether half floats keep ``a`` (any shape) to about 0.05 % of its scale: every finite value
    within the half range and the 99th percentile of its nonzero |a| at least
    :data:`HALF_MIN_SCALE` (an image of tiny values, e.g. radiance in far units, would lose its
    dark tones to subnormals). An image of zeros is kept exactly."""
    mag = np.abs(a[np.isfinite(a)])
    mag = mag[mag > 0]
    if mag.size == 0:
        return True
    return bool(mag.max() <= HALF_MAX and np.percentile(mag, 99) >= HALF_MIN_SCALE)


def write_exr(path: str | os.PathLike, image: np.ndarray, half: bool = False) -> None:
    """Write an EXR (1 channel 'Y', 3 channels RGB, 4 RGBA), ZIP-compressed, atomically.

    ``half``: store 16-bit half floats (11 significant bits, about 3 decimal digits; normal
    down to 6.1e-5, steps of 6e-8 below) instead of float32: half the size on disk and in
    memory, enough for photographs (8-bit sRGB steps are 0.4-8 %, RAW shot noise far above
    0.05 %). An image that half floats would not keep (:func:`half_precision_suffices`: values
    beyond 65504, or an image of tiny values) is written as float32 instead.
    """
    import OpenEXR

    a = _as_hwc(image, path)
    if half and half_precision_suffices(a):
        a = np.ascontiguousarray(a.astype(np.float16))
    else:
        if half:
            log.info("%s: values outside what half floats keep; written as float32", path)
        a = np.ascontiguousarray(a.astype(np.float32))
    if a.shape[2] == 1:
        channels = {"Y": np.ascontiguousarray(a[:, :, 0])}
    elif a.shape[2] == 3:
        channels = {"RGB": a}
    else:
        channels = {"RGBA": a}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path) as tmp:
        with OpenEXR.File(header, channels) as f:
            f.write(str(tmp))


def read_exr(path: str | os.PathLike) -> np.ndarray:
    """Read an EXR as float32 ``(H, W, C)``: C = 1 (Y or a single channel), 3 (RGB) or 4 (RGBA)."""
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise ImageError(f"{path}: file not found")
    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            ch = {k: np.asarray(v.pixels) for k, v in f.channels().items()}
    except Exception as e:  # OpenEXR raises plain exceptions for corrupt files
        raise ImageError(f"{path}: not a readable OpenEXR file ({e}); re-export it as .exr") from e
    names = list(ch)
    if all(c in ch for c in "RGB"):
        order = ["R", "G", "B"] + (["A"] if "A" in ch else [])
    elif "Y" in ch:
        order = ["Y"]
    elif len(names) == 1:
        order = names
    else:
        raise ImageError(f"{path}: unsupported EXR channels {names}; expected R,G,B[,A] or Y")
    return np.stack([ch[c].astype(np.float32) for c in order], axis=-1)


def read_texture_map(path: str | os.PathLike, what: str, channels: tuple[int, ...],
                     tolerance: float = 1e-6) -> np.ndarray:
    """Read one material texture map (DESIGN section 2) as float32 ``(H, W, C)`` in [0, 1].

    Raises :class:`ImageError` naming ``path`` when the file is missing or unreadable, has a channel
    count not in ``channels``, is empty, or holds NaN/Inf texels. Values outside [0, 1] by more than
    ``tolerance`` are clipped with a warning (a map is a reflectance, never outside that range).
    """
    path = Path(path)
    a = read_exr(path)
    if a.shape[2] not in channels:
        want = " or ".join(str(c) for c in channels)
        raise ImageError(f"{path}: the {what} map has {a.shape[2]} channel(s), expected {want} (DESIGN section 2: "
                         "diffuse RGB, specular 1 channel or RGB, roughness 1 channel)")
    if a.shape[0] < 1 or a.shape[1] < 1:
        raise ImageError(f"{path}: the {what} map is empty ({a.shape})")
    bad = ~np.isfinite(a)
    if bad.any():
        raise ImageError(f"{path}: the {what} map has {int(bad.any(axis=2).sum())} texel(s) with NaN or Inf; "
                         "rerun the stage that wrote it")
    lo, hi = float(a.min()), float(a.max())
    if lo < -tolerance or hi > 1.0 + tolerance:
        n = int(((a < -tolerance) | (a > 1.0 + tolerance)).any(axis=2).sum())
        log.warning("%s: %d texel(s) of the %s map outside [0, 1] (range %.4g..%.4g); clipped", path, n, what, lo, hi)
    return np.clip(a, 0.0, 1.0).astype(np.float32)


# ---- 8/16-bit PNG and JPEG ----
def register_heif() -> None:
    """Let PIL open HEIC/HEIF files (pillow-heif); idempotent."""
    import pillow_heif

    pillow_heif.register_heif_opener()


def _read_heif(path: Path) -> tuple[np.ndarray, int]:
    """A HEIC/HEIF photo (8-bit sRGB as phones write it) as uint8 ``(H, W, 3)`` codes."""
    from PIL import Image, UnidentifiedImageError

    register_heif()
    try:
        with Image.open(path) as im:
            rgb = np.asarray(im.convert("RGB"))
    except (UnidentifiedImageError, OSError, ValueError) as e:
        raise ImageError(f"{path}: cannot decode the HEIC/HEIF image ({e}); re-export it as JPEG") from e
    return rgb, 8


def read_ldr_codes(path: str | os.PathLike) -> tuple[np.ndarray, int]:
    """Read a PNG/JPEG/HEIC as its code values: uint8 or uint16 ``(H, W, C)`` (RGB order, still
    encoded) and the bit depth. A quarter (8-bit) of the memory of :func:`read_ldr`'s floats.

    EXIF orientation is ignored: pixels are used as stored, like every other view.
    """
    import cv2

    path = Path(path)
    if path.suffix.lower() in HEIF_EXTENSIONS:
        return _read_heif(path)
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED | cv2.IMREAD_IGNORE_ORIENTATION)
    if img is None:
        raise ImageError(f"{path}: cannot decode the image (truncated or not a {path.suffix} file)")
    if img.ndim == 2:
        img = img[:, :, None]
    elif img.shape[2] == 3:
        img = img[:, :, ::-1]
    elif img.shape[2] == 4:
        img = img[:, :, [2, 1, 0, 3]]
    if img.dtype == np.uint8:
        bits = 8
    elif img.dtype == np.uint16:
        bits = 16
    else:
        raise ImageError(f"{path}: unsupported sample type {img.dtype}; use 8- or 16-bit PNG/JPEG")
    return img, bits


def read_ldr(path: str | os.PathLike) -> tuple[np.ndarray, int]:
    """Read a PNG/JPEG/HEIC as float32 ``(H, W, C)`` in [0, 1] (still encoded) and its bit depth.

    EXIF orientation is ignored: pixels are used as stored, like every other view.
    """
    codes, bits = read_ldr_codes(path)
    return codes.astype(np.float32) / np.float32(2**bits - 1), bits


def srgb_codes_to_linear(codes: np.ndarray, bits: int) -> np.ndarray:
    """sRGB code values (uint8/uint16, ``bits`` deep) to linear float32 through a lookup table:
    the same values as ``srgb_to_linear(codes / (2**bits - 1))`` without full-size temporaries."""
    lut = srgb_to_linear(np.arange(2**bits, dtype=np.float32) / np.float32(2**bits - 1))
    return lut[codes]


def write_png(path: str | os.PathLike, image: np.ndarray, bits: int = 8) -> None:
    """Write values in [0, 1] (already encoded) as an 8- or 16-bit PNG, atomically."""
    import cv2

    a = _as_hwc(image, path)
    scale = 2**bits - 1
    q = np.clip(np.rint(np.nan_to_num(a) * scale), 0, scale).astype(np.uint8 if bits == 8 else np.uint16)
    if q.shape[2] == 3:
        q = q[:, :, ::-1]
    elif q.shape[2] == 4:
        q = q[:, :, [2, 1, 0, 3]]
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), q):
            raise OSError(f"{path}: could not write PNG")


def write_jpg(path: str | os.PathLike, rgb_srgb: np.ndarray, quality: int = 92) -> None:
    """Write an sRGB-encoded image in [0, 1] as JPEG, atomically."""
    import cv2

    a = _as_hwc(rgb_srgb, path)
    q = np.clip(np.rint(np.nan_to_num(a) * 255), 0, 255).astype(np.uint8)
    if q.shape[2] == 3:
        q = q[:, :, ::-1]
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), q, [cv2.IMWRITE_JPEG_QUALITY, quality]):
            raise OSError(f"{path}: could not write JPEG")


def read_mask(path: str | os.PathLike) -> np.ndarray:
    """Read a mask PNG: bool ``(H, W)``, nonzero = True."""
    codes, _ = read_ldr_codes(path)
    return codes[:, :, 0] > 0


def write_mask(path: str | os.PathLike, mask: np.ndarray) -> None:
    """Write a bool ``(H, W)`` mask as an 8-bit PNG (0 or 255)."""
    write_png(path, np.asarray(mask, dtype=np.float32))
