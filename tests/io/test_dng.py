"""write_dng: rawpy reads the CFA back bit-exact; the tags read back with tifffile and with
read_tiff_tags (the reader the linearize stage uses); DNG opcode lists and the GainMap opcode
round-trip bit-exact, and the GainMap's interpolation follows the DNG SDK's."""

from __future__ import annotations

import numpy as np
import pytest

from recon.io.dng import (
    GainMap,
    Opcode,
    read_opcode_list,
    read_tiff_tags,
    tag_number,
    tag_rationals,
    write_dng,
    write_opcode_list,
)
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


# ---- opcode lists and the GainMap opcode ----
def _gain_map(rng, points=(5, 7), planes=1, **kw):
    args = dict(top=0, left=1, bottom=40, right=64, plane=0, planes=1, row_pitch=2, col_pitch=2,
                spacing=(0.25, 1 / 6), origin=(0.0, 0.0))
    args.update(kw)
    return GainMap(gains=rng.uniform(0.8, 2.5, size=(*points, planes)).astype(np.float32), **args)


def test_opcode_list_round_trip_is_bit_exact(tmp_path):
    rng = np.random.default_rng(0)
    maps = [_gain_map(rng, top=r, left=c) for r in (0, 1) for c in (0, 1)]
    other = Opcode(1, 0x01030000, 1, bytes(range(20)))  # WarpRectilinear, optional: kept as bytes
    blob = write_opcode_list([*maps, other])
    ops = read_opcode_list(blob)
    assert [o.name for o in ops] == ["GainMap"] * 4 + ["WarpRectilinear"] and ops[4].optional
    assert ops[4] == other
    for gm, op in zip(maps, ops, strict=False):
        back = GainMap.from_opcode(op)
        assert back.gains.tobytes() == gm.gains.tobytes()  # float32, bit-exact
        assert (back.top, back.left, back.bottom, back.right, back.row_pitch, back.col_pitch) == \
            (gm.top, gm.left, gm.bottom, gm.right, 2, 2)
        assert back.spacing == gm.spacing and back.origin == gm.origin
        assert write_opcode_list([back]) == write_opcode_list([gm])
    # through a DNG file: tifffile hands the tag back as the bytes written
    sensor = SensorModel()
    path = write_dng(tmp_path / "o.dng", np.full((40, 64), 700, np.uint16), sensor, 1 / 50, 100, 2.0,
                     opcode_list2=maps, opcode_list3=[other])
    ifd0, raw, _ = read_tiff_tags(path)
    tags = {**ifd0, **raw}
    assert bytes(tags["OpcodeList2"]) == write_opcode_list(maps)
    assert read_opcode_list(tags["OpcodeList3"]) == [other]
    # lengths that do not add up
    with pytest.raises(ValueError, match="truncated"):
        read_opcode_list(blob[:-3])
    with pytest.raises(ValueError, match="needs"):
        GainMap.from_opcode(Opcode(9, 0x01030000, 0, maps[0].to_opcode().params[:-4]))
    with pytest.raises(ValueError, match="not a GainMap"):
        GainMap.from_opcode(other)
    with pytest.raises(ValueError, match="spacing"):
        GainMap(0, 0, 0, 0, 0, 1, 1, 1, (0.0, 0.5), (0, 0), np.ones((2, 2)))


def _sdk_gains(gm: GainMap, height, width, row, plane=0):
    """The DNG SDK's incremental interpolator (dng_gain_map.cpp), transcribed loop by loop:
    gains of one image row at every column from 0."""
    g = gm.gains[:, :, min(plane, gm.gains.shape[2] - 1)].astype(np.float64)
    (sv, sh), (ov, oh) = gm.spacing, gm.origin
    pv, ph = g.shape[:2]
    fv = ((row + 0.5) / height - ov) / sv
    if fv <= 0:
        r1 = r2 = 0
        frac = 0.0
    elif fv >= pv - 1:
        r1 = r2 = pv - 1
        frac = 0.0
    else:
        r1 = int(fv)
        r2, frac = r1 + 1, fv - r1

    def entry(c):
        return g[r1, c] * (1 - frac) + g[r2, c] * frac

    out = []
    col, reset, base, step, index = 0, -1, 0.0, 0.0, 0.0
    while col < width:
        if col >= reset:
            fh = ((col + 0.5) / width - oh) / sh
            if fh <= 0:
                base, step = entry(0), 0.0
                reset = int(np.ceil(oh * width - 0.5))
            elif fh >= ph - 1:
                base, step, reset = entry(ph - 1), 0.0, 2**31
            else:
                c = int(fh)
                b0, delta = entry(c), entry(c + 1) - entry(c)
                base = b0 + delta * (fh - c)
                step = delta / width / sh
                reset = int(np.ceil(((c + 1) * sh + oh) * width - 0.5))
            index = 0.0
        out.append(base + step * index)
        index += 1.0
        col += 1
    return np.array(out)


def test_gain_map_interpolation_follows_the_dng_sdk():
    rng = np.random.default_rng(1)
    height, width = 30, 44
    # a map whose first point sits inside the image and whose last lies beyond it (clamped)
    gm = _gain_map(rng, points=(4, 6), planes=3, spacing=(0.3, 0.21), origin=(0.1, 0.05))
    rows, cols = np.arange(height), np.arange(width)
    for plane in range(3):
        ours = gm.gains_at(rows, cols, height, width, plane)
        sdk = np.stack([_sdk_gains(gm, height, width, r, plane) for r in rows])
        np.testing.assert_allclose(ours, sdk, rtol=1e-6)
    # at a pixel centre on a map point the gain is that entry, bit-exact
    one = GainMap(0, 0, 0, 0, 0, 1, 1, 1, (0.25, 0.25), (1 / 16, 1 / 16), rng.uniform(1, 2, (4, 4)))
    g = one.gains_at(np.arange(0, 8, 2), np.arange(0, 8, 2), 8, 8)
    assert g.tobytes() == one.gains[:, :, 0].tobytes()
    # the area with its pitches; all-zero = the whole image
    assert one.area(8, 8) == (slice(0, 8, 1), slice(0, 8, 1))
    assert gm.area(30, 44) == (slice(0, 30, 2), slice(1, 44, 2))
