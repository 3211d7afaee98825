"""A plain Bayer camera sensor: linear Rec.709 scene values to RAW CFA counts.

Built from first principles and independent of :mod:`recon.linearize`, so that linearizing
its output tests the real RAW path against a known truth. The model, per pixel::

    xyz      = M_709 @ rgb_linear                  Rec.709 / D65 primaries -> CIE XYZ
    cam      = max(color_matrix @ xyz, 0)          XYZ -> camera native (DNG ColorMatrix1, D65)
    H        = exposure_time * (iso / 100) / f_number**2
    signal   = cam * H / saturation_exposure       fraction of (white_level - black_level)
    mosaic   one channel per site, CFA pattern (default RGGB)
    e-       = Poisson(signal_iso100 * full_well_electrons),
               signal_iso100 = cam * (exposure_time / f_number**2) / saturation_exposure
    DN       = e- * gain(iso) + Normal(0, read_noise * iso / 100),
               gain(iso) = (white_level - black_level) / full_well_electrons * iso / 100
    raw      = clip(round(DN + black_level), 0, white_level)

The exact scale (what a linearizer must recover)
------------------------------------------------
``color_matrix`` is normalized the DNG way: the camera response to D65 white with Y = 1
(``rgb_linear = (1, 1, 1)``) has its largest channel equal to 1. So a white scene value of 1
just reaches the white level at ``H = saturation_exposure``. A correct linearization (black
level, ``(raw - black) / (white - black)``, demosaic, white balance with the D65 neutral
:meth:`SensorModel.as_shot_neutral`, ``inv(color_matrix)``, XYZ -> Rec.709, and every view
scaled by ``H_ref / H_view``) returns, without noise::

    rgb_out = rgb_linear * H_ref / saturation_exposure          (see linear_scale)

i.e. ONE global factor for the whole capture. Where the camera response of a colour is negative
(outside the sensor's gamut; e.g. the blue channel of pure Rec.709 red is -0.7 % here), the
clip to 0 loses it, as in a real sensor.
"""

from __future__ import annotations

import dataclasses

import numpy as np

# ---- CIE reference values (first principles: primaries and white chromaticities) ----
D65_XY = (0.3127, 0.3290)
"""CIE 1931 2-degree chromaticity of D65 (ITU-R BT.709)."""
REC709_PRIMARIES_XY = ((0.640, 0.330), (0.300, 0.600), (0.150, 0.060))
"""ITU-R BT.709 R, G, B primaries (xy)."""


def _xy_to_xyz(xy) -> np.ndarray:
    x, y = xy
    return np.array([x / y, 1.0, (1.0 - x - y) / y])


def rec709_to_xyz_matrix() -> np.ndarray:
    """The (3, 3) matrix linear Rec.709 RGB -> CIE XYZ (D65 white, white Y = 1)."""
    p = np.stack([_xy_to_xyz(c) for c in REC709_PRIMARIES_XY], axis=1)  # columns = primaries, Y=1
    s = np.linalg.solve(p, _xy_to_xyz(D65_XY))
    return p * s[None, :]


D65_XYZ = _xy_to_xyz(D65_XY)
"""XYZ of D65 white with Y = 1, shape (3,)."""

# Adobe's published D65 ColorMatrix for the Canon EOS 5D Mark II (dcraw adobe_coeff, /10000), a
# typical Bayer CMOS response; normalized below so max(color_matrix @ D65_XYZ) = 1. Phone sensors
# have matrices of the same shape (weak red, strong green, off-diagonal negatives).
_TYPICAL_CM = np.array(
    [[4716, 603, -830], [-7798, 15474, 2480], [-1496, 1937, 6651]], dtype=np.float64
) / 10000.0


def normalize_color_matrix(color_matrix: np.ndarray) -> np.ndarray:
    """Scale an XYZ -> camera (3, 3) matrix so the camera response to D65 (Y = 1) peaks at 1."""
    cm = np.asarray(color_matrix, dtype=np.float64)
    return cm / float(np.max(cm @ D65_XYZ))


DEFAULT_COLOR_MATRIX = normalize_color_matrix(_TYPICAL_CM)

_CFA_PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")


def exposure_value(exposure_time: float, iso: float, f_number: float) -> float:
    """Relative exposure H = exposure_time * (iso / 100) / f_number**2 (seconds at f/1, ISO 100)."""
    return float(exposure_time) * float(iso) / 100.0 / float(f_number) ** 2


@dataclasses.dataclass(frozen=True)
class SensorModel:
    """A Bayer sensor with a linear response, shot noise and read noise.

    Attributes
    ----------
    color_matrix : (3, 3) float
        XYZ -> camera native, the DNG ColorMatrix1 with CalibrationIlluminant1 = D65,
        normalized as :func:`normalize_color_matrix` does.
    black_level, white_level : int
        RAW counts of no light and of saturation.
    bits : int
        Bits per RAW sample (12, 14 or 16); ``white_level <= 2**bits - 1``.
    read_noise : float
        Standard deviation of the read noise in DN at ISO 100 (scales with ISO / 100).
    full_well_electrons : float
        Electrons at the white level at ISO 100; the gain is
        ``(white_level - black_level) / full_well_electrons * iso / 100`` DN per electron.
    saturation_exposure : float
        The exposure H (see :func:`exposure_value`) at which a camera-native value of 1 reaches
        the white level. Default 0.0025 = 1/100 s at f/2, ISO 100.
    cfa : str
        CFA pattern of the top-left 2 x 2 block, e.g. 'RGGB'.
    pixel_pitch_um : float
        Pixel size in micrometres (for the focal plane resolution tags).
    """

    color_matrix: tuple = tuple(map(tuple, DEFAULT_COLOR_MATRIX))
    black_level: int = 256
    white_level: int = 4095
    bits: int = 12
    read_noise: float = 2.0
    full_well_electrons: float = 6000.0
    saturation_exposure: float = 0.0025
    cfa: str = "RGGB"
    pixel_pitch_um: float = 1.4

    def __post_init__(self):
        cm = np.asarray(self.color_matrix, dtype=np.float64)
        if cm.shape != (3, 3) or not np.all(np.isfinite(cm)) or abs(np.linalg.det(cm)) < 1e-9:
            raise ValueError(f"color_matrix must be an invertible 3x3 matrix, got {self.color_matrix!r}")
        object.__setattr__(self, "color_matrix", tuple(map(tuple, cm.tolist())))
        if self.bits not in (12, 14, 16):
            raise ValueError(f"bits must be 12, 14 or 16, got {self.bits}")
        if not 0 <= self.black_level < self.white_level <= 2**self.bits - 1:
            raise ValueError(
                f"need 0 <= black_level < white_level <= 2**bits - 1, got black {self.black_level}, "
                f"white {self.white_level}, bits {self.bits}"
            )
        if self.cfa not in _CFA_PATTERNS:
            raise ValueError(f"cfa must be one of {_CFA_PATTERNS}, got {self.cfa!r}")
        if self.read_noise < 0 or self.full_well_electrons <= 0 or self.saturation_exposure <= 0:
            raise ValueError("read_noise must be >= 0, full_well_electrons and saturation_exposure > 0")

    # ---- derived quantities ----
    @property
    def color_matrix_array(self) -> np.ndarray:
        """``color_matrix`` as a float64 (3, 3) array."""
        return np.asarray(self.color_matrix, dtype=np.float64)

    def as_shot_neutral(self) -> np.ndarray:
        """Camera response to D65 white, normalized to max 1: the DNG AsShotNeutral, shape (3,)."""
        n = self.color_matrix_array @ D65_XYZ
        return n / n.max()

    def cfa_indices(self) -> np.ndarray:
        """The (2, 2) array of channel indices (0 = R, 1 = G, 2 = B) of the CFA pattern."""
        return np.array(["RGB".index(c) for c in self.cfa]).reshape(2, 2)

    def gain(self, iso: float) -> float:
        """Conversion gain in DN per electron at ``iso``."""
        return (self.white_level - self.black_level) / self.full_well_electrons * float(iso) / 100.0

    def linear_scale(self, exposure_reference: float) -> float:
        """The one factor a correct linearization applies: ``rgb_out = rgb_linear * scale``.

        ``exposure_reference`` is the H every view is normalized to (by default the capture's
        median :func:`exposure_value`).
        """
        return float(exposure_reference) / self.saturation_exposure

    # ---- image formation ----
    def camera_native(self, rgb_linear: np.ndarray) -> np.ndarray:
        """Linear Rec.709 ``(H, W, 3)`` -> camera native ``(H, W, 3)`` float64 (before exposure)."""
        rgb = np.maximum(np.asarray(rgb_linear, dtype=np.float64), 0.0)
        m = self.color_matrix_array @ rec709_to_xyz_matrix()
        return np.maximum(rgb @ m.T, 0.0)

    def mosaic(self, image: np.ndarray) -> np.ndarray:
        """Keep one channel per site of an ``(H, W, 3)`` image along the CFA: ``(H, W)``."""
        h, w, _ = image.shape
        idx = np.tile(self.cfa_indices(), ((h + 1) // 2, (w + 1) // 2))[:h, :w]
        return np.take_along_axis(image, idx[:, :, None], axis=2)[:, :, 0]

    def capture(
        self,
        rgb_linear: np.ndarray,
        exposure_time: float,
        iso: float,
        f_number: float,
        rng: np.random.Generator | None = None,
        noise: bool = True,
    ) -> np.ndarray:
        """Photograph a linear Rec.709 scene.

        Parameters
        ----------
        rgb_linear : (H, W, 3) float
            Scene values, linear Rec.709 (D65 white); negatives are treated as 0.
        exposure_time : float
            Seconds.
        iso : float
            ISO speed (gain relative to ISO 100).
        f_number : float
            Aperture f-number.
        rng : numpy Generator, optional
            Noise source (required when ``noise`` is True).
        noise : bool
            Add shot and read noise.

        Returns
        -------
        (H, W) uint16
            RAW CFA counts in [0, white_level].
        """
        rgb_linear = np.asarray(rgb_linear)
        if rgb_linear.ndim != 3 or rgb_linear.shape[2] != 3:
            raise ValueError(f"rgb_linear must be (H, W, 3), got {rgb_linear.shape}")
        if min(exposure_time, iso, f_number) <= 0:
            raise ValueError(
                f"exposure_time, iso and f_number must be > 0, got {exposure_time}, {iso}, {f_number}"
            )
        if not np.all(np.isfinite(rgb_linear)):
            raise ValueError("rgb_linear contains NaN or Inf")
        cam_cfa = self.mosaic(self.camera_native(rgb_linear))
        # signal at ISO 100, as a fraction of the full well
        signal100 = cam_cfa * (exposure_time / f_number**2) / self.saturation_exposure
        electrons = signal100 * self.full_well_electrons
        if noise:
            if rng is None:
                raise ValueError("capture(noise=True) needs an rng (numpy.random.Generator)")
            # Poisson's lambda must stay finite; far beyond the full well the pixel clips anyway
            electrons = rng.poisson(np.minimum(electrons, 1e12)).astype(np.float64)
        dn = electrons * self.gain(iso)
        if noise and self.read_noise > 0:
            dn = dn + rng.normal(0.0, self.read_noise * iso / 100.0, size=dn.shape)
        raw = np.clip(np.rint(dn + self.black_level), 0, self.white_level)
        return raw.astype(np.uint16)
