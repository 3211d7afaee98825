"""Synthetic captures: the folder contract of DESIGN section 1, and that gt/ describes the photos."""

import hashlib
import json

import numpy as np
import pytest

from recon import sections
from recon.io.cameras import load_cameras
from recon.io.images import read_exr, read_ldr, read_mask, srgb_to_linear
from recon.io.mesh import read_obj
from recon.synth.capture import PRESETS, SynthError, SynthSettings, make_capture, view_exposures

SMALL = sections.replace(SynthSettings(), object="blob", n_views=4, width=40, height=30, fov=40.0, distance=4.2,
                      spp=4, seed=3, light_intensity=28.0, mesh_level=2, texture_size=64,
                      noise=False, write_masks=True, write_cameras=True, write_gt_linear=True,
                      format="exr")


@pytest.fixture(scope="module")
def exr_capture(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth") / "cap"
    make_capture(out, SMALL)
    return out


def _tree(root):
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def test_folder_contract(exr_capture):
    files = set(_tree(exr_capture))
    stems = [f"{i:04d}" for i in range(4)]
    expect = {f"images/{s}.exr" for s in stems} | {f"masks/{s}.png" for s in stems} \
        | {f"gt/linear/{s}.exr" for s in stems} \
        | {"cameras.json", "gt/mesh.obj", "gt/diffuse.exr", "gt/specular.exr",
           "gt/roughness.exr", "gt/cameras.json", "gt/synth.json", "gt/README.md"}
    assert files == expect  # no capture.yaml: the flash's intensity is not stated (state_light off)
    cams = load_cameras(exr_capture / "cameras.json")
    gt = load_cameras(exr_capture / "gt" / "cameras.json")
    assert len(cams) == 4 and gt.light_intensity == 28.0 and gt.light_known
    assert not cams.light_known  # the pipeline estimates it, as for a user's capture
    for c, g in zip(cams, gt, strict=True):
        assert (exr_capture / c.image).is_file()
        np.testing.assert_array_equal(c.world_to_camera, g.world_to_camera)
        assert (c.width, c.height) == (40, 30)
        np.testing.assert_allclose(c.K[:2, 2], [20.0, 15.0])  # principal point at the center
    mesh = read_obj(exr_capture / "gt" / "mesh.obj")
    assert mesh.has_uv and mesh.volume() > 0
    assert read_exr(exr_capture / "gt" / "diffuse.exr").shape == (64, 64, 3)
    assert read_exr(exr_capture / "gt" / "specular.exr").shape == (64, 64, 1)
    r = read_exr(exr_capture / "gt" / "roughness.exr")
    assert r.shape == (64, 64, 1) and r.min() >= 0.02
    meta = json.loads((exr_capture / "gt" / "synth.json").read_text())
    assert meta["linear_scale"] == 1.0 and meta["settings"]["n_views"] == 4


def test_photos_match_gt(exr_capture, mi):
    """Noise-free EXR photos are gt/linear; re-rendering the gt files gives the photos again."""
    from recon.render.mitsuba_bsdf import render_reference

    cams = load_cameras(exr_capture / "gt" / "cameras.json")
    mesh = read_obj(exr_capture / "gt" / "mesh.obj")
    tex = {k: read_exr(exr_capture / "gt" / f"{k}.exr") for k in ("diffuse", "specular", "roughness")}
    for i, cam in enumerate(cams):
        photo = read_exr(exr_capture / cam.image)
        np.testing.assert_array_equal(photo, read_exr(exr_capture / "gt" / "linear" / f"{cam.stem}.exr"))
        mask = read_mask(exr_capture / "masks" / f"{cam.stem}.png")
        assert 0.1 < mask.mean() < 0.9
        assert photo[~mask].mean() < 0.1 * photo[mask].mean()
        # the gt mesh projects onto the mask: same bounding box within a pixel
        xy, z = cam.project(mesh.v_pos)
        assert np.all(z > 0)
        assert xy.min() > 0 and xy[:, 0].max() < cam.width and xy[:, 1].max() < cam.height
        rows, cols = np.nonzero(mask)
        np.testing.assert_allclose([cols.min(), rows.min()], np.floor(xy.min(0)), atol=1.01)
        np.testing.assert_allclose([cols.max(), rows.max()], np.floor(xy.max(0)), atol=1.01)
        if i == 0:
            again = render_reference(mesh, tex, cam, cams.light_intensity, SMALL.photos.spp,
                                     seed=SMALL.view_seed(i))
            assert np.abs(again - photo).mean() < 1e-3 * photo[mask].mean()


def test_dng_capture_follows_the_sensor(tmp_path):
    import rawpy

    from recon.synth.sensor import SensorModel

    s = sections.replace(SMALL, format="dng", exposure_variation=1.0, write_masks=False,
                            write_cameras=False, n_views=5)
    make_capture(tmp_path / "cap", s)
    cap = tmp_path / "cap"
    assert not (cap / "cameras.json").exists() and not (cap / "masks").exists()
    sensor = SensorModel()
    exposures = view_exposures(s, sensor)
    meta = json.loads((cap / "gt" / "synth.json").read_text())
    assert meta["linear_scale"] == 1.0
    assert meta["exposure_reference"] == pytest.approx(sensor.saturation_exposure)
    assert sorted(e["stops"] for e in exposures) == [-1.0, 0.0, 0.0, 0.0, 1.0]
    for cam, e in zip(load_cameras(cap / "gt" / "cameras.json"), exposures, strict=True):
        assert cam.image.endswith(".dng")
        linear = read_exr(cap / "gt" / "linear" / f"{cam.stem}.exr")
        expect = sensor.capture(linear, e["exposure_time"], e["iso"], e["f_number"], noise=False)
        with rawpy.imread(str(cap / cam.image)) as raw:
            np.testing.assert_array_equal(raw.raw_image_visible, expect)


def test_png_capture_is_srgb_of_the_renders(tmp_path):
    s = sections.replace(SMALL, format="png16", write_masks=False, n_views=2)
    make_capture(tmp_path / "cap", s)
    for cam in load_cameras(tmp_path / "cap" / "cameras.json"):
        img, bits = read_ldr(tmp_path / "cap" / cam.image)
        assert bits == 16
        linear = read_exr(tmp_path / "cap" / "gt" / "linear" / f"{cam.stem}.exr")
        np.testing.assert_allclose(srgb_to_linear(img), np.clip(linear, 0, 1), atol=2e-4)


def test_capture_is_reproducible(tmp_path, drjit_single_thread):
    """The same settings give the same files byte for byte. On one drjit thread: with several,
    the order in which a pixel's samples are added is the scheduler's, and a float32 EXR (or a
    DNG value at a rounding boundary) can differ in its last bit between two runs."""
    s = sections.replace(SMALL, format="dng", noise=True, n_views=2, write_masks=False)
    make_capture(tmp_path / "a", s)
    make_capture(tmp_path / "b", s)
    assert _tree(tmp_path / "a") == _tree(tmp_path / "b")
    make_capture(tmp_path / "c", sections.replace(s, seed=4))
    assert _tree(tmp_path / "a") != _tree(tmp_path / "c")


@pytest.mark.parametrize("change,match", [
    ({"object": "cube"}, "object"),
    ({"format": "tiff"}, "format"),
    ({"width": 41}, "even"),
    ({"n_views": 0}, "n_views"),
    ({"distance": 1.0}, "distance"),
    ({"view_z_range": (0.5, 0.2)}, "view_z_range"),
    ({"light_intensity": -1.0}, "light_intensity"),
    ({"exposure_variation": 1.0, "format": "exr"}, "exposure_variation"),
    ({"spp": 0}, "spp"),
])
def test_bad_settings_raise(change, match):
    with pytest.raises(SynthError, match=match):
        sections.replace(sections.replace(SMALL, format="dng"), **change)


def test_presets_are_valid():
    assert {"demo", "blob", "torus", "smooth"} <= set(PRESETS)
    demo = PRESETS["demo"]
    assert demo.photos.format == "dng" and not demo.outputs.write_cameras and 24 <= demo.cameras.n_views <= 32


def test_scene_scale_leaves_the_photos_unchanged(exr_capture, tmp_path):
    """scale s: object, cameras and gt mesh times s, light times s^2 -> the same photos."""
    s = 1e-3
    out = make_capture(tmp_path / "tiny", sections.replace(SMALL, scale=s))
    for stem in ("0000", "0003"):
        a = read_exr(exr_capture / "images" / f"{stem}.exr")
        b = read_exr(out / "images" / f"{stem}.exr")
        np.testing.assert_allclose(b, a, rtol=1e-4, atol=1e-6)
    ca, cb = load_cameras(exr_capture / "gt" / "cameras.json"), load_cameras(out / "gt" / "cameras.json")
    assert cb.light_intensity == pytest.approx(ca.light_intensity * s**2)
    np.testing.assert_allclose(read_obj(out / "gt" / "mesh.obj").v_pos,
                               read_obj(exr_capture / "gt" / "mesh.obj").v_pos * s, rtol=1e-6, atol=1e-12)


def test_constant_material_overrides(tmp_path):
    out = make_capture(tmp_path / "diffuse", sections.replace(SMALL, specular=0.0, roughness=1.0, albedo=0.5))
    assert read_exr(out / "gt" / "specular.exr").max() == 0.0
    np.testing.assert_allclose(read_exr(out / "gt" / "roughness.exr"), 1.0)
    np.testing.assert_allclose(read_exr(out / "gt" / "diffuse.exr"), 0.5)
    for bad in (dict(specular=1.5), dict(albedo=-0.1), dict(roughness=0.0), dict(scale=0.0)):
        with pytest.raises(SynthError, match=next(iter(bad))):
            sections.replace(SMALL, **bad)
