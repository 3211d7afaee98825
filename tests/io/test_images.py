import numpy as np
import pytest

from recon.io import images as im


def test_srgb_round_trip_and_known_values():
    x = np.linspace(0, 1, 1001, dtype=np.float32)
    assert np.abs(im.srgb_to_linear(im.linear_to_srgb(x)) - x).max() < 1e-5
    assert im.linear_to_srgb(np.float32(0.0031308)) == pytest.approx(0.04045, abs=1e-5)
    assert im.srgb_to_linear(np.float32(0.5)) == pytest.approx(0.21404, abs=1e-4)
    assert np.all(np.isfinite(im.linear_to_srgb(np.array([-1, np.inf, 2], np.float32))))


@pytest.mark.parametrize("shape", [(5, 7), (5, 7, 1), (5, 7, 3), (5, 7, 4)])
def test_exr_round_trip(tmp_path, shape):
    a = np.random.default_rng(0).random(shape).astype(np.float32) * 100
    im.write_exr(tmp_path / "a.exr", a)
    b = im.read_exr(tmp_path / "a.exr")
    assert b.shape == (a.shape if a.ndim == 3 else a.shape + (1,))
    np.testing.assert_array_equal(b.reshape(a.shape), a)


def test_bad_files_name_the_file(tmp_path):
    p = tmp_path / "broken.exr"
    p.write_bytes(b"not an exr")
    with pytest.raises(im.ImageError, match="broken.exr"):
        im.read_exr(p)
    p = tmp_path / "broken.png"
    p.write_bytes(b"\x89PNG\r\n")
    with pytest.raises(im.ImageError, match="broken.png"):
        im.read_ldr(p)


def test_png_16bit_and_mask_round_trip(tmp_path):
    a = np.random.default_rng(1).random((4, 6, 3)).astype(np.float32)
    im.write_png(tmp_path / "a.png", a, bits=16)
    b, bits = im.read_ldr(tmp_path / "a.png")
    assert bits == 16 and np.abs(a - b).max() <= 0.5 / 65535 + 1e-7
    m = np.zeros((4, 6), bool)
    m[1:3, 2:5] = True
    im.write_mask(tmp_path / "m.png", m)
    np.testing.assert_array_equal(im.read_mask(tmp_path / "m.png"), m)


def test_texture_map_checks_and_clips(tmp_path, caplog):
    p = tmp_path / "roughness.exr"
    a = np.full((4, 5, 1), 0.5, np.float32)
    a[0, 0] = 1.25
    a[1, 1] = -0.5
    im.write_exr(p, a)
    with caplog.at_level("WARNING"):
        out = im.read_texture_map(p, "roughness", (1,))
    assert out.dtype == np.float32 and out.shape == (4, 5, 1)
    assert out[0, 0, 0] == 1.0 and out[1, 1, 0] == 0.0 and out[2, 2, 0] == 0.5
    assert "2 texel(s) of the roughness map outside [0, 1]" in caplog.text
    with pytest.raises(im.ImageError, match=r"roughness\.exr: the specular map has 1 channel\(s\), expected 3"):
        im.read_texture_map(p, "specular", (3,))
    a[2, 3] = np.nan
    im.write_exr(p, a)
    with pytest.raises(im.ImageError, match=r"roughness\.exr: the roughness map has 1 texel\(s\) with NaN or Inf"):
        im.read_texture_map(p, "roughness", (1,))
    with pytest.raises(im.ImageError, match=r"absent\.exr: file not found"):
        im.read_texture_map(tmp_path / "absent.exr", "diffuse", (3,))


def test_half_float_exr_round_trip_and_fallbacks(tmp_path):
    """half=True: half the bytes, 11-bit values; float32 where half floats would not keep the
    image (values beyond 65504, an image of tiny values); NaN/Inf-free either way."""
    rng = np.random.default_rng(0)
    a = rng.random((60, 80, 3), dtype=np.float32) * 4.0
    im.write_exr(tmp_path / "f.exr", a)
    im.write_exr(tmp_path / "h.exr", a, half=True)
    h = im.read_exr(tmp_path / "h.exr")
    assert h.dtype == np.float32 and np.all(np.isfinite(h))
    big = a >= 2.0**-14  # normal halfs: relative rounding 2^-11
    assert np.max(np.abs(h[big] / a[big] - 1)) <= 2.0**-11
    assert (tmp_path / "h.exr").stat().st_size < 0.6 * (tmp_path / "f.exr").stat().st_size
    for name, img in (("huge", a * 1e5), ("tiny", a * 1e-6)):  # beyond the range / mostly subnormal
        im.write_exr(tmp_path / f"{name}.exr", img, half=True)
        np.testing.assert_array_equal(im.read_exr(tmp_path / f"{name}.exr"), img)
    assert im.half_precision_suffices(a) and not im.half_precision_suffices(a * 1e5)
    assert not im.half_precision_suffices(a * 1e-6) and im.half_precision_suffices(np.zeros((2, 2)))


def test_sRGB_codes_to_linear_lookup_equals_the_formula():
    codes = np.arange(256, dtype=np.uint8).reshape(16, 16)
    np.testing.assert_array_equal(im.srgb_codes_to_linear(codes, 8), im.srgb_to_linear(codes.astype(np.float32) / np.float32(255)))
    c16 = np.array([0, 1, 1000, 65535], dtype=np.uint16)
    np.testing.assert_allclose(im.srgb_codes_to_linear(c16, 16), im.srgb_to_linear(c16 / 65535.0), rtol=1e-6)
