"""The synthetic sensor: colour science against colour-science, exposure law, noise statistics."""

from __future__ import annotations

import numpy as np
import pytest

from recon.synth.sensor import (
    D65_XYZ,
    SensorModel,
    exposure_value,
    normalize_color_matrix,
    rec709_to_xyz_matrix,
)


def test_rec709_matrix_matches_colour_science():
    import colour

    ref = colour.RGB_COLOURSPACES["ITU-R BT.709"].matrix_RGB_to_XYZ
    np.testing.assert_allclose(rec709_to_xyz_matrix(), ref, atol=2e-4)
    # white (1, 1, 1) is D65 with Y = 1
    np.testing.assert_allclose(rec709_to_xyz_matrix() @ np.ones(3), D65_XYZ, atol=1e-12)


def test_default_matrix_normalization_and_neutral():
    s = SensorModel()
    resp = s.color_matrix_array @ D65_XYZ
    assert resp.max() == pytest.approx(1.0)
    n = s.as_shot_neutral()
    assert n.max() == pytest.approx(1.0) and np.all(n > 0.2)
    # a D65-white scene seen by the camera is the neutral
    cam = s.camera_native(np.ones((1, 1, 3)))[0, 0]
    np.testing.assert_allclose(cam / cam.max(), n, atol=1e-12)
    np.testing.assert_allclose(normalize_color_matrix(3.0 * s.color_matrix_array), s.color_matrix_array)


def test_noise_free_exposure_law_and_cfa():
    s = SensorModel()
    rgb = np.full((4, 6, 3), 0.3, np.float32)
    t, iso, fn = 1 / 200, 200, 2.8
    raw = s.capture(rgb, t, iso, fn, noise=False)
    assert raw.dtype == np.uint16 and raw.shape == (4, 6)
    h = exposure_value(t, iso, fn)
    cam = s.camera_native(rgb[:1, :1])[0, 0]
    expect = np.rint(s.black_level + cam * h / s.saturation_exposure * (s.white_level - s.black_level))
    # RGGB: (0,0) R, (0,1) G, (1,0) G, (1,1) B
    assert raw[0, 0] == expect[0] and raw[0, 1] == expect[1] and raw[1, 0] == expect[1]
    assert raw[1, 1] == expect[2]
    # doubling exposure time doubles the signal above black
    raw2 = s.capture(rgb, 2 * t, iso, fn, noise=False).astype(float) - s.black_level
    np.testing.assert_allclose(raw2, 2 * (raw.astype(float) - s.black_level), atol=1.0)
    # other pattern
    b = SensorModel(cfa="BGGR").capture(rgb, t, iso, fn, noise=False)
    assert b[0, 0] == expect[2] and b[1, 1] == expect[0]


def test_white_reaches_white_level_at_saturation_exposure():
    s = SensorModel()
    raw = s.capture(np.ones((2, 2, 3)), s.saturation_exposure, 100, 1.0, noise=False)
    assert raw.max() == s.white_level  # the peak (green) channel exactly saturates
    over = s.capture(np.full((2, 2, 3), 50.0), 1.0, 100, 1.0, noise=False)
    assert np.all(over == s.white_level)
    black = s.capture(np.zeros((2, 2, 3)), 30.0, 100, 1.0, noise=False)
    assert np.all(black == s.black_level)


def test_noise_statistics_match_the_model():
    s = SensorModel(read_noise=3.0)
    rng = np.random.default_rng(0)
    iso = 400
    grey = np.full((200, 200, 3), 0.2, np.float32)
    t, fn = 1 / 400, 2.0
    raw = s.capture(grey, t, iso, fn, rng=rng).astype(float)
    green = np.concatenate([raw[0::2, 1::2].ravel(), raw[1::2, 0::2].ravel()])
    cam_g = s.camera_native(grey[:1, :1])[0, 0, 1]
    e = cam_g * (t / fn**2) / s.saturation_exposure * s.full_well_electrons
    g = s.gain(iso)
    mean = s.black_level + e * g
    var = e * g**2 + (s.read_noise * iso / 100) ** 2 + 1 / 12
    assert green.mean() == pytest.approx(mean, rel=2e-3)
    assert green.var() == pytest.approx(var, rel=0.05)
    # dark frame: only read noise around the black level
    dark = s.capture(np.zeros((200, 200, 3)), t, iso, fn, rng=rng).astype(float)
    assert dark.mean() == pytest.approx(s.black_level, abs=0.1)
    assert dark.std() == pytest.approx(s.read_noise * iso / 100, rel=0.05)


def test_extreme_inputs_and_errors():
    s = SensorModel(bits=14, black_level=512, white_level=16383)
    rng = np.random.default_rng(1)
    raw = s.capture(np.full((8, 8, 3), 1e6, np.float32), 30.0, 6400, 1.4, rng=rng)
    assert np.all(raw == 16383)
    raw = s.capture(np.full((8, 8, 3), -1.0, np.float32), 1 / 8000, 100, 16, rng=rng)
    assert raw.max() <= 512 + 20
    with pytest.raises(ValueError, match="H, W, 3"):
        s.capture(np.zeros((4, 4)), 1, 100, 2)
    with pytest.raises(ValueError, match="> 0"):
        s.capture(np.zeros((4, 4, 3)), 0, 100, 2)
    with pytest.raises(ValueError, match="rng"):
        s.capture(np.zeros((4, 4, 3)), 1, 100, 2)
    with pytest.raises(ValueError, match="NaN"):
        s.capture(np.full((4, 4, 3), np.nan), 1, 100, 2, noise=False)
    with pytest.raises(ValueError, match="bits"):
        SensorModel(bits=10)
    with pytest.raises(ValueError, match="black_level"):
        SensorModel(white_level=5000)
    with pytest.raises(ValueError, match="cfa"):
        SensorModel(cfa="RGBG")
    with pytest.raises(ValueError, match="invertible"):
        SensorModel(color_matrix=np.zeros((3, 3)))
