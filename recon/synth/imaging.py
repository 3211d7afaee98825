"""A phone's imaging for synthetic captures: flash offset, ambient light, exposure and white
balance jitter, lens falloff, a phone tone curve and 8-bit JPEGs with EXIF (DESIGN section 7).

Each effect is a setting of :class:`recon.synth.capture.SynthSettings` that is off by default,
so it can be switched on alone. For view k, with ``x`` the linear Rec.709 render (flash at
``camera centre + R^T flash_offset``, plus a constant environment of radiance ``L_amb``)::

    y     = x * g_k * wb_k[c] * v(r)             the linear value the camera records
    g_k   = 2**(exposure_jitter * z_k)           auto-exposure error the EXIF does not record
    wb_k  = exp(wb_jitter * u_k[c]), geometric mean 1 over c (per-view white-balance error)
    v(r)  = 1 + k1 r^2 + k2 r^4                  radial lens falloff, r = |pixel - centre| /
                                                 half diagonal (1 in the corners)
    JPEG  = round(255 * T(y))                    T: the tone curve below, 8 bit, EXIF

z_k, u_k standard normal (seeded). ``L_amb = ambient * I_e / (pi d^2)`` with d the camera
distance: a diffuse, unoccluded surface facing the flash receives ``ambient`` times the flash's
irradiance I_e / d^2 from the environment (its radiance is then a_d L_amb). The exposure
variation of the EXIF (``exposure_variation`` stops) is the recorded part: linearize divides it
out, leaving g_k.

The tone curve T (``tone_curve``, :data:`TONE_CURVES`) acts on the value the camera records
(after the EXIF exposure, before linearize divides it out) and gives the encoded JPEG value:

- ``none``: plain sRGB.
- ``phone``: the sRGB encoding followed by a contrast S-curve ``S(s) = s^p / (s^p + (1 - s)^p)``
  (p = ``tone_contrast``; p = 1 is plain sRGB), flat (slope 0) at both ends for p > 1 like a
  phone's highlight/shadow roll-off (the curve the optimizer's tone term was designed on).
- ``gamma22``: ``y^(1/2.2)``, a pure power law (white at y = 1).
- ``filmic``: Hable's filmic curve (Uncharted 2) ``f(2 y) / f(2 w)``, w = :data:`FILMIC_WHITE`,
  then sRGB: a toe and a long shoulder, white only at y = 2 (highlights above 1 keep detail).
- ``table``: a monotone table over exposure stops as a phone's ISP tabulates it
  (:data:`TONE_TABLE`, linear in the stops between entries, white at y = 2^0.5).
- ``toe_shoulder``: ``(1 + m) y^a / (y^a + m)`` (a = 1.3, m = 0.15, :data:`TOE_SHOULDER`): a
  toe that crushes the shadows (slope 0 at 0) and a shoulder up to white at y = 1.

Only ``none`` and ``phone`` are shaped like the optimizer's model (a curve in the sRGB-encoded
domain with white at 1); the others test that the model recovers curves it does not share.
Linearize reads JPEGs as sRGB, so the optimizer sees ``srgb^-1(T(y))`` (divided by the EXIF
exposure): :func:`linearized_tone` is that map, and ``gt/imaging.json`` samples it.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from recon.io.atomic import atomic_path
from recon.io.images import linear_to_srgb, srgb_to_linear

TONE_CURVES = ("none", "phone", "gamma22", "filmic", "table", "toe_shoulder")
FILMIC_WHITE = 2.0
"""``filmic``: the linear value the curve maps to white (the encoded 1)."""
TONE_TABLE = ((-10.0, 0.0), (-8.0, 0.01), (-7.0, 0.025), (-6.0, 0.05), (-5.0, 0.09), (-4.0, 0.15),
              (-3.0, 0.24), (-2.5, 0.30), (-2.0, 0.37), (-1.5, 0.46), (-1.0, 0.58), (-0.5, 0.73), (0.0, 0.88),
              (0.5, 1.0))
"""``table``: (stops, encoded value) of a phone-like curve, log2 of the recorded linear value; below
the first entry the curve goes linearly to 0 at y = 0."""
TOE_SHOULDER = (1.3, 0.15)
"""``toe_shoulder``: (a, m) of ``(1 + m) y^a / (y^a + m)``."""
TONE_FORMULAS = {
    "none": "srgb(y)",
    "phone": "S(srgb(y)), S(s) = s^p / (s^p + (1 - s)^p)",
    "gamma22": "min(y, 1)^(1/2.2)",
    "filmic": "srgb(f(2 y) / f(2 w)), f Hable's filmic operator, w = 2 (white)",
    "table": "linear interpolation in log2(y) of the table 'table' (stops, encoded)",
    "toe_shoulder": "min(1, (1 + m) y^a / (y^a + m)), a = 1.3, m = 0.15",
}


def falloff_map(width: int, height: int, k1: float, k2: float) -> np.ndarray:
    """(H, W) float32 ``1 + k1 r^2 + k2 r^4`` at the pixel centres (r = 1 in the corners)."""
    jj, ii = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    r2 = ((jj - width / 2) ** 2 + (ii - height / 2) ** 2) / ((width / 2) ** 2 + (height / 2) ** 2)
    return (1.0 + k1 * r2 + k2 * r2 * r2).astype(np.float32)


def falloff_gainmap(width: int, height: int, k1: float, k2: float, points=(13, 17)):
    """The DNG OpcodeList3 GainMap (3 planes, the whole image) that undoes ``1 + k1 r^2 + k2 r^4``:
    gains 1 / falloff at ``points`` (rows, columns) map points spread over the image from edge to
    edge (relative coordinates 0..1, r = 1 in the corners)."""
    from recon.io.dng import GainMap

    pv, ph = points
    v, h = np.meshgrid(np.linspace(0, 1, pv), np.linspace(0, 1, ph), indexing="ij")
    r2 = (((h - 0.5) * width) ** 2 + ((v - 0.5) * height) ** 2) / ((width / 2) ** 2 + (height / 2) ** 2)
    g = 1.0 / (1.0 + k1 * r2 + k2 * r2 * r2)
    return GainMap(0, 0, 0, 0, 0, 3, 1, 1, (1 / (pv - 1), 1 / (ph - 1)), (0.0, 0.0),
                   np.repeat(g[:, :, None], 3, axis=2).astype(np.float32))


def s_curve(s: np.ndarray, p: float) -> np.ndarray:
    """``s^p / (s^p + (1 - s)^p)`` on [0, 1] (monotone, S(0) = 0, S(1/2) = 1/2, S(1) = 1)."""
    s = np.clip(np.asarray(s, dtype=np.float64), 0.0, 1.0)
    a, b = s**p, (1.0 - s) ** p
    return a / np.maximum(a + b, 1e-300)


def _hable(x: np.ndarray) -> np.ndarray:
    """Hable's filmic operator (A..F = 0.15, 0.50, 0.10, 0.20, 0.02, 0.30)."""
    a, b, c, d, e, f = 0.15, 0.50, 0.10, 0.20, 0.02, 0.30
    return (x * (a * x + c * b) + d * e) / (x * (a * x + b) + d * f) - e / f


def tone_encode(y: np.ndarray, curve: str, p: float = 1.4) -> np.ndarray:
    """Linear ``y`` (what the camera records) -> encoded value in [0, 1] by the tone curve
    ``curve`` (:data:`TONE_CURVES`, the module docstring); ``p``: the ``phone`` S-curve's exponent."""
    y = np.asarray(y)
    if curve in ("none", "phone"):
        s = linear_to_srgb(y.astype(np.float32)).astype(np.float64)
        return s_curve(s, p) if curve == "phone" else s
    x = np.clip(np.nan_to_num(y.astype(np.float64)), 0.0, None)
    if curve == "gamma22":
        return np.minimum(x, 1.0) ** (1 / 2.2)
    if curve == "filmic":
        lin = _hable(2.0 * np.minimum(x, FILMIC_WHITE)) / _hable(2.0 * FILMIC_WHITE)
        return linear_to_srgb(np.clip(lin, 0.0, 1.0)).astype(np.float64)
    if curve == "table":
        stops, enc = (np.array(v, np.float64) for v in zip(*TONE_TABLE, strict=True))
        y0 = 2.0 ** stops[0]
        u = np.log2(np.maximum(x, y0))
        return np.where(x < y0, x / y0 * enc[0], np.interp(u, stops, enc))
    if curve == "toe_shoulder":
        a, m = TOE_SHOULDER
        xa = x ** a
        return np.minimum((1.0 + m) * xa / (xa + m), 1.0)
    raise ValueError(f"tone curve {curve!r}: choose one of {TONE_CURVES}")


def tone_white(curve: str) -> float:
    """The smallest recorded linear value the curve maps to white (encoded 1)."""
    return {"filmic": FILMIC_WHITE, "table": 2.0 ** TONE_TABLE[-1][0]}.get(curve, 1.0)


def linearized_tone(y: np.ndarray, curve: str, p: float = 1.4) -> np.ndarray:
    """What linearize returns for a linear value ``y`` (before quantization): srgb^-1(T(y))."""
    return srgb_to_linear(tone_encode(y, curve, p).astype(np.float32)).astype(np.float64)


@dataclass(frozen=True)
class ViewImaging:
    """The imaging of one view: ``y = x * gain * wb[c] * falloff``."""

    gain: float
    wb: tuple

    def apply(self, rgb: np.ndarray, falloff: np.ndarray | None) -> np.ndarray:
        out = rgb * np.float32(self.gain) * np.asarray(self.wb, np.float32)[None, None, :]
        if falloff is not None:
            out = out * falloff[:, :, None]
        return out.astype(np.float32)


def view_imaging(settings, n_views: int) -> list[ViewImaging]:
    """Per-view exposure and white-balance errors of ``settings`` (SynthSettings), seeded."""
    rng = settings.rng("imaging")
    z = rng.standard_normal(n_views)
    u = rng.standard_normal((n_views, 3))
    u -= u.mean(1, keepdims=True)
    out = []
    for k in range(n_views):
        g = 2.0 ** (settings.phone.exposure_jitter * z[k]) if settings.phone.exposure_jitter > 0 else 1.0
        wb = np.exp(settings.phone.wb_jitter * u[k]) if settings.phone.wb_jitter > 0 else np.ones(3)
        out.append(ViewImaging(float(g), tuple(float(x) for x in wb)))
    return out


def light_position(camera, offset_camera) -> np.ndarray:
    """(3,) world position of a flash at ``offset_camera`` (camera coordinates) from ``camera``."""
    R = camera.world_to_camera[:3, :3]
    return camera.center + R.T @ np.asarray(offset_camera, dtype=np.float64)


def ambient_radiance(ambient: float, light_intensity: float, distance: float) -> float:
    """``L_amb = ambient * I_e / (pi d^2)`` (see the module docstring)."""
    return float(ambient) * float(light_intensity) / (np.pi * float(distance) ** 2)


def write_jpeg_exif(path: str | os.PathLike, encoded: np.ndarray, exposure_time: float, iso: float,
                    f_number: float, focal_length_mm: float, focal_length_35mm: float | None = None,
                    quality: int = 95) -> None:
    """Write an encoded (H, W, 3) image in [0, 1] as an 8-bit JPEG with the EXIF exposure and
    focal length tags a phone writes (ExposureTime, ISOSpeedRatings, FNumber, FocalLength,
    FocalLengthIn35mmFilm), atomically."""
    from fractions import Fraction

    from PIL import Image
    from PIL.TiffImagePlugin import IFDRational

    q = np.clip(np.rint(np.nan_to_num(np.asarray(encoded, np.float64)) * 255), 0, 255).astype(np.uint8)
    im = Image.fromarray(q, "RGB")
    exif = Image.Exif()
    exif[0x010F] = "recon"
    exif[0x0110] = "synthetic phone"
    sub = exif.get_ifd(0x8769)

    def rational(x, den=1000000):
        f = Fraction(float(x)).limit_denominator(den)
        return IFDRational(f.numerator, f.denominator)

    sub[0x829A] = rational(exposure_time)
    sub[0x829D] = rational(f_number, 1000)
    sub[0x8827] = int(round(iso))
    sub[0x920A] = rational(focal_length_mm, 1000)
    if focal_length_35mm:
        sub[0xA405] = int(round(focal_length_35mm))
    with atomic_path(path) as tmp:
        im.save(tmp, "JPEG", quality=int(quality), exif=exif, subsampling=0)


def imaging_record(settings, cams, views: list[ViewImaging], exposures: list[dict], light_intensity: float,
                   l_amb: float) -> dict:
    """The ground truth of ``gt/imaging.json``: every parameter of the imaging above."""
    s = settings
    g = np.array([v.gain for v in views])
    xs = np.linspace(0.0, 1.0, 33)
    return {
        "model": "y = x * exposure_gain[k] * white_balance[k][c] * falloff(r); photo = T(y) (recon.synth.imaging)",
        "flash_offset_camera": [float(x) * s.scale for x in s.phone.flash_offset],
        "flash_offset_units": "world units of cameras.json, camera axes (x right, y down, z forward)",
        "light_intensity": float(light_intensity),
        "ambient_fraction": float(s.phone.ambient),
        "ambient_radiance": float(l_amb),
        "exposure_jitter_stops": float(s.phone.exposure_jitter),
        "exposure_gains": g.tolist(),
        "exposure_gains_normalized": (g / np.exp(np.log(g).mean())).tolist(),
        "white_balance_jitter": float(s.phone.wb_jitter),
        "white_balance_gains": [list(v.wb) for v in views],
        "falloff": {"model": "1 + k1 r^2 + k2 r^4, r = distance from the image centre / half diagonal",
                    "k1": float(s.phone.falloff[0]), "k2": float(s.phone.falloff[1]),
                    "dng_gainmap": bool(s.phone.falloff_gainmap)},
        "tone_curve": {"name": s.phone.tone_curve, "contrast": float(s.phone.tone_contrast),
                       "formula": TONE_FORMULAS[s.phone.tone_curve] if s.photos.format == "jpg"
                       else "srgb(y)" if s.photos.format in ("png8", "png16") else "identity",
                       "linear_in": xs.tolist(),
                       "linearized_out": linearized_tone(xs, s.phone.tone_curve, s.phone.tone_contrast).tolist()
                       if s.photos.format == "jpg" else None,
                       **({"table": [list(r) for r in TONE_TABLE]} if s.phone.tone_curve == "table" else {}),
                       **({"white": tone_white(s.phone.tone_curve)} if s.photos.format == "jpg" else {})},
        "views": [{"image": c.image, "exposure_gain": v.gain, "white_balance": list(v.wb), **e}
                  for c, v, e in zip(cams.frames, views, exposures, strict=True)],
    }


def save_imaging(path: Path, record: dict) -> None:
    with atomic_path(path) as p:
        p.write_text(json.dumps(record, indent=1))
