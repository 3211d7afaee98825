"""Settings and the error of the linearize stage."""

from __future__ import annotations

import dataclasses
import math

DEMOSAIC_ALGORITHMS = ("LINEAR", "VNG", "PPG", "AHD", "DCB", "DHT", "AAHD")
WHITE_BALANCE_MODES = ("as_shot_median", "fixed")


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
    max_size : int
        Longest side of the linear images in pixels (0 = the photos' own size). Larger photos are
        reduced by area averaging in linear space (a clipped-pixel mask marks every output pixel
        that any clipped photo pixel touches) and the focal length in pixels follows. The
        default, 1600, is the largest size a later stage reads: SIFT runs at ``poses.features.max_image_size``
        (1600) and the presets optimize at 128-512 px. A 12-MP photo (4032 x 3024) becomes
        1600 x 1200: 6.3x less disk, memory and time in every later stage.
    half_float : bool
        Store the linear EXRs as 16-bit half floats (11 significant bits: relative steps of
        0.05-0.1 %, below 8-bit JPEG quantisation and RAW shot noise) instead of float32; half the
        disk. Off by default: DESIGN section 2 states float32, and EXR inputs keep their values
        exactly. ``poses/undistorted/`` is always half (resampled values, read by the optimizer).
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
    max_size: int = 1600
    half_float: bool = False
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
        if self.max_size < 0:
            raise ValueError(f"max_size must be >= 0 (0 = full size), got {self.max_size}")
        if self.preview_max_size < 0:
            raise ValueError(f"preview_max_size must be >= 0, got {self.preview_max_size}")
        if not 1 <= self.preview_quality <= 100:
            raise ValueError(f"preview_quality must be in [1, 100], got {self.preview_quality}")
