"""write_dng: rawpy reads the CFA back bit-exact; the tags read back with tifffile and with
read_tiff_tags (the reader the linearize stage uses)."""

from __future__ import annotations

import numpy as np
import pytest

from recon.io.dng import read_tiff_tags, tag_number, tag_rationals, write_dng
from recon.synth.sensor import SensorModel


def _tags(path):
    import tifffile

    with tifffile.TiffFile(path) as tf:
        return {t.name: t.value for t in tf.pages[0].tags.values()}


def _ratio(v):
    a = np.asarray(v, dtype=np.float64).ravel()
    return a[0::2] / a[1::2]


@pytest.mark.parametrize(
    "sensor",
    [
        SensorModel(),
        SensorModel(bits=14, black_level=512, white_level=16383, cfa="BGGR"),
        SensorModel(bits=16, black_level=2048, white_level=65000, cfa="GRBG"),
    ],
    ids=["12bit-RGGB", "14bit-BGGR", "16bit-GRBG"],
)
def test_round_trip_cfa_and_tags(tmp_path, sensor):
    import rawpy

    rng = np.random.default_rng(3)
    cfa = rng.integers(0, sensor.white_level + 1, size=(48, 70)).astype(np.uint16)
    path = write_dng(
        tmp_path / "x.dng", cfa, sensor, exposure_time=1 / 8000, iso=3200, f_number=1.8,
        focal_length_mm=4.25, make="Acme", model="Phone 1", default_crop=(2, 4, 60, 40),
    )
    assert list(tmp_path.iterdir()) == [path]  # nothing but the file (atomic write)
    with rawpy.imread(str(path)) as raw:
        assert np.array_equal(raw.raw_image_visible, cfa)
        assert raw.black_level_per_channel == [sensor.black_level] * 4
        assert raw.white_level == sensor.white_level
        pattern = "".join("RGBG"[c] for c in raw.raw_pattern.ravel())
        assert pattern == sensor.cfa
        assert (raw.sizes.crop_left_margin, raw.sizes.crop_top_margin) == (2, 4)
        assert (raw.sizes.crop_width, raw.sizes.crop_height) == (60, 40)
    t = _tags(path)
    assert t["BlackLevel"] == sensor.black_level and t["WhiteLevel"] == sensor.white_level
    assert bytes(t["CFAPattern"]) == bytes("RGB".index(c) for c in sensor.cfa)
    np.testing.assert_allclose(_ratio(t["ColorMatrix1"]).reshape(3, 3), sensor.color_matrix_array, atol=1e-6)
    assert t["CalibrationIlluminant1"] == 21
    np.testing.assert_allclose(_ratio(t["AsShotNeutral"]), sensor.as_shot_neutral(), atol=1e-6)
    assert _ratio(t["ExposureTime"])[0] == pytest.approx(1 / 8000, rel=1e-9)
    assert _ratio(t["FNumber"])[0] == pytest.approx(1.8)
    assert t["ISOSpeedRatings"] == 3200
    assert _ratio(t["FocalLength"])[0] == pytest.approx(4.25)
    assert _ratio(t["FocalPlaneXResolution"])[0] == pytest.approx(1e4 / sensor.pixel_pitch_um, rel=1e-6)
    assert t["FocalPlaneResolutionUnit"] == 3
    assert t["Make"] == "Acme" and t["Model"] == "Phone 1"
    assert tuple(t["DefaultCropOrigin"]) == (2, 4) and tuple(t["DefaultCropSize"]) == (60, 40)
    assert "DNGVersion" in t


def test_linearization_table_is_applied_by_rawpy(tmp_path):
    import rawpy

    sensor = SensorModel(bits=16, black_level=0, white_level=65280)
    table = np.round((np.arange(4096) / 4095.0) ** 2 * 65280).astype(np.uint16)
    cfa = np.random.default_rng(0).integers(0, 4096, size=(32, 32)).astype(np.uint16)
    path = write_dng(tmp_path / "t.dng", cfa, sensor, 1 / 60, 100, 2.0, linearization_table=table)
    assert np.array_equal(_tags(path)["LinearizationTable"], table)
    with rawpy.imread(str(path)) as raw:
        assert np.array_equal(raw.raw_image_visible, table[cfa])


def test_long_exposure_and_errors(tmp_path):
    s = SensorModel()
    cfa = np.full((24, 24), 300, np.uint16)
    p = write_dng(tmp_path / "long.dng", cfa, s, 30.0, 100, 22.0)
    assert _ratio(_tags(p)["ExposureTime"])[0] == 30.0
    with pytest.raises(ValueError, match="uint16"):
        write_dng(tmp_path / "a.dng", cfa.astype(np.float32), s, 1, 100, 2)
    with pytest.raises(ValueError, match="even"):
        write_dng(tmp_path / "a.dng", np.zeros((23, 24), np.uint16), s, 1, 100, 2)
    with pytest.raises(ValueError, match="white level"):
        write_dng(tmp_path / "a.dng", np.full((24, 24), 5000, np.uint16), s, 1, 100, 2)
    with pytest.raises(ValueError, match="default_crop"):
        write_dng(tmp_path / "a.dng", cfa, s, 1, 100, 2, default_crop=(4, 4, 24, 8))
    with pytest.raises(ValueError, match="22 pixels"):
        write_dng(tmp_path / "a.dng", np.zeros((20, 200), np.uint16), s, 1, 100, 2)
    with pytest.raises(ValueError, match="> 0"):
        write_dng(tmp_path / "a.dng", cfa, s, 0, 100, 2)
    assert not (tmp_path / "a.dng").exists()


def test_read_tiff_tags_reads_what_write_dng_writes(tmp_path):
    sensor = SensorModel()
    cfa = np.full((32, 40), 700, np.uint16)
    path = write_dng(tmp_path / "r.dng", cfa, sensor, 1 / 250, 400, 2.8, focal_length_mm=6.0,
                     make="Acme", model="Cam", default_crop=(2, 2, 36, 28))
    ifd0, raw, exif = read_tiff_tags(path)
    assert "DNGVersion" in ifd0 and raw["ImageWidth"] == 40 and raw["ImageLength"] == 32
    tag = {**ifd0, **exif, **raw}
    assert tag_number(tag["ExposureTime"]) == pytest.approx(1 / 250)
    assert tag_number(tag["FNumber"]) == pytest.approx(2.8)
    assert tag_number(tag["FocalLength"]) == pytest.approx(6.0)
    np.testing.assert_allclose(tag_rationals(tag["ColorMatrix1"], 9).reshape(3, 3), sensor.color_matrix_array,
                               atol=1e-6)
    np.testing.assert_allclose(tag_rationals(tag["AsShotNeutral"], 3), sensor.as_shot_neutral(), atol=1e-6)
    assert tag_rationals(tag["DefaultCropSize"], 2).tolist() == [36, 28]
    # values that are not numbers, and counts that do not fit
    assert tag_number((1, 0)) is None and tag_number("n/a") is None and tag_number(None) is None
    assert tag_rationals(tag["AsShotNeutral"], 9) is None
    # a truncated file: the image data end beyond its end
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(ValueError, match="truncated"):
        read_tiff_tags(path)
