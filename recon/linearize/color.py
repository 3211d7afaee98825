"""Camera colour to linear Rec.709 (DNG specification 1.6, chapter 6).

The camera neutral (the camera's response to the scene white) and the DNG colour tags
(ColorMatrix1/2 interpolated by the white's colour temperature, CameraCalibration,
AnalogBalance, ForwardMatrix when present) give camera -> XYZ; a Bradford adaptation takes the
scene white (or D50 for ForwardMatrix) to D65, then XYZ -> linear Rec.709. The matrix is
normalized so that the camera neutral with largest channel 1 maps to Y = 1 (the DNG convention
for ForwardMatrix, applied to the ColorMatrix path too).

A colour dict holds the DNG tags: ``color_matrix_1/2``, ``forward_matrix_1/2``,
``camera_calibration_1/2`` ((9,) arrays or None), ``analog_balance`` ((3,) or None),
``illuminant_1/2`` (EXIF LightSource codes).
"""

from __future__ import annotations

import numpy as np

D50_XY = (0.3457, 0.3585)
D65_XY = (0.3127, 0.3290)

# DNG CalibrationIlluminant (EXIF LightSource) -> colour temperature in kelvin, as the DNG SDK
# (dng_camera_profile.cpp, IlluminantToTemperature) uses them for matrix interpolation.
ILLUMINANT_TEMPERATURE = {
    1: 5500.0, 2: 4150.0, 3: 2850.0, 4: 5500.0, 9: 5500.0, 10: 6500.0, 11: 7500.0,
    12: 6400.0, 13: 5050.0, 14: 4150.0, 15: 3525.0, 16: 2925.0, 17: 2850.0, 18: 5500.0,
    19: 6500.0, 20: 5500.0, 21: 6500.0, 22: 7500.0, 23: 5000.0, 24: 3200.0,
}


def xy_to_xyz(xy) -> np.ndarray:
    """(3,) XYZ with Y = 1 of the chromaticity ``xy``."""
    x, y = float(xy[0]), float(xy[1])
    return np.array([x / y, 1.0, (1.0 - x - y) / y])


def xyz_to_xy(xyz) -> np.ndarray:
    """(2,) chromaticity of ``xyz``."""
    s = float(np.sum(xyz))
    return np.array([xyz[0] / s, xyz[1] / s])


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


def xyz_to_camera(color: dict, xy) -> np.ndarray:
    """(3, 3) XYZ -> camera native for a scene white of chromaticity ``xy`` (DNG ColorMatrix,
    interpolated by temperature, times AnalogBalance and CameraCalibration)."""
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
        xyz = np.linalg.solve(xyz_to_camera(color, xy), neutral)
        new = xyz_to_xy(xyz)
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
        source_white = xy_to_xyz(D50_XY)
    else:
        cam_to_xyz = np.linalg.inv(ab_cc @ _interp(color, "color_matrix", g))
        source_white = xy_to_xyz(xy)
    cat = colour.adaptation.matrix_chromatic_adaptation_VonKries(
        source_white, xy_to_xyz(D65_XY), transform="Bradford"
    )
    xyz_to_709 = colour.RGB_COLOURSPACES["ITU-R BT.709"].matrix_XYZ_to_RGB
    m = xyz_to_709 @ cat @ cam_to_xyz
    y = (cat @ cam_to_xyz @ (neutral / neutral.max()))[1]
    if not (np.isfinite(y) and y > 0):
        raise ValueError(f"camera neutral {neutral} has no positive luminance")
    return m / y, xy
