"""A phone's imaging in synthetic captures (recon/synth/imaging.py): each effect switchable, the
photos made exactly as gt/imaging.json says, JPEG EXIF that linearize reads back."""

import json

import cv2
import numpy as np
import pytest

from recon import sections
from recon.io.cameras import load_cameras
from recon.io.images import read_exr
from recon.io.mesh import read_obj
from recon.linearize.stage import linearize_capture
from recon.render.mitsuba_bsdf import render_reference
from recon.synth import cli
from recon.synth.capture import PRESETS, SynthError, SynthSettings, make_capture, recorded_settings
from recon.synth.imaging import falloff_map, light_position, linearized_tone, s_curve, tone_encode

SMALL = sections.replace(SynthSettings(), object="blob", n_views=4, width=40, height=30, fov=40.0, distance=4.2, spp=4, seed=3,
                      light_intensity=28.0, mesh_level=2, texture_size=64, noise=False, write_masks=True,
                      write_cameras=True, write_gt_linear=True, format="jpg")
PHONE = sections.replace(SMALL, flash_offset=(0.19, -0.05, 0.0), exposure_variation=0.5, exposure_jitter=0.3,
                            wb_jitter=0.04, falloff=(-0.3, 0.05), tone_curve="phone", tone_contrast=1.4)


def test_tone_curve_and_falloff_functions():
    s = np.linspace(0, 1, 101)
    y = s_curve(s, 1.4)
    assert y[0] == 0 and y[-1] == 1 and abs(y[50] - 0.5) < 1e-12 and np.all(np.diff(y) > 0)
    np.testing.assert_allclose(s_curve(s, 1.0), s, atol=1e-12)  # p = 1: plain sRGB
    x = np.linspace(0, 1, 50)
    assert np.max(np.abs(linearized_tone(x, "phone", 1.4) - x)) > 0.03  # not sRGB
    np.testing.assert_allclose(linearized_tone(x, "none", 1.4), x, atol=2e-6)
    v = falloff_map(40, 30, -0.3, 0.05)
    assert abs(v[15, 20] - 1) < 0.01 and abs(v[0, 0] - (1 - 0.3 + 0.05)) < 0.02  # centre, corner


def test_settings_validation_and_command_line():
    with pytest.raises(SynthError, match="tone_curve"):
        sections.replace(SMALL, format="exr", tone_curve="phone")
    with pytest.raises(SynthError, match="falloff"):
        sections.replace(SMALL, falloff=(-0.97, 0.0))
    with pytest.raises(SynthError, match="flash_offset"):
        sections.replace(SMALL, flash_offset=(3.0, 0.0, 0.0))
    # the default settings record no phone fields (older captures regenerate bit-identically)
    assert "flash_offset" not in recorded_settings(SynthSettings())
    assert recorded_settings(PRESETS["phone"])["tone_curve"] == "phone"
    p = __import__("argparse").ArgumentParser()
    cli.add_arguments(p)
    args = p.parse_args(["/tmp/x", "--preset", "phone", "--flash-offset", "0", "0", "0", "--ambient", "0"])
    s = cli.settings_from_args(args)
    assert s.phone.flash_offset == (0.0, 0.0, 0.0) and s.phone.ambient == 0.0 and s.phone.tone_curve == "phone"
    assert "--flash-offset 0.0 0.0 0.0" in cli.command_line(args)


@pytest.fixture(scope="module")
def phone_capture(tmp_path_factory):
    root = tmp_path_factory.mktemp("phone")
    cap = make_capture(root / "cap", PHONE)
    lin = root / "lin"
    info = linearize_capture(cap, lin)
    return cap, lin, info


def test_photos_follow_gt_imaging(phone_capture):
    """Linearized JPEG = srgb^-1(T(x g wb v)) with everything from gt/imaging.json, x = gt/linear."""
    cap, lin, info = phone_capture
    gt = json.loads((cap / "gt" / "imaging.json").read_text())
    assert gt["flash_offset_camera"] == [0.19, -0.05, 0.0]
    assert gt["tone_curve"]["name"] == "phone" and gt["falloff"]["k1"] == -0.3
    g = np.array(gt["exposure_gains"])
    f_true = load_cameras(cap / "gt" / "cameras.json").frames[0].K[0, 0]
    assert np.std(np.log2(g)) > 0.05  # the jitter is there
    v = falloff_map(40, 30, -0.3, 0.05)
    for k, view in enumerate(gt["views"]):
        stem = f"{k:04d}"
        meta = info["images"][stem]
        # EXIF: exposure and focal length read back; linearize divided the recorded stops out
        assert meta["kind"] == "ldr" and abs(meta["exposure_time"] - view["exposure_time"]) < 1e-6
        assert meta["focal_length_mm"] is not None and meta["focal_length_35mm"] is not None
        # the 35 mm equivalent is an integer over the diagonal (as phones write it): read back
        # within half a unit of the true focal length (by the width it was 4 % long)
        w, h = meta["width"], meta["height"]
        assert abs(meta["focal_length_px"] - f_true) <= 0.5 * np.hypot(w, h) / 43.267 + 1e-9, (meta, f_true)
        x = read_exr(cap / "gt" / "linear" / f"{stem}.exr")
        y = x * view["exposure_gain"] * np.array(view["white_balance"]) * v[:, :, None] * 2.0 ** view["stops"]
        expect = linearized_tone(y, "phone", 1.4) / 2.0 ** view["stops"]
        got = read_exr(lin / f"{stem}.exr")
        fg = (x.sum(2) > 0.03) & (y.max(2) < 0.9)
        # 8-bit JPEG (quality 95, no chroma subsampling): a few codes in the encoded domain
        enc = tone_encode(expect * 2.0 ** view["stops"], "none", 1.0)
        enc_got = tone_encode(got * 2.0 ** view["stops"], "none", 1.0)
        assert np.median(np.abs(enc - enc_got)[fg]) < 4 / 255, k


def test_flash_offset_moves_the_light(phone_capture):
    """gt/linear is the render with the flash at centre + R^T offset: it matches a render with
    the light there, not one with the light at the camera."""
    cap, _, _ = phone_capture
    mesh = read_obj(cap / "gt" / "mesh.obj")
    cams = load_cameras(cap / "gt" / "cameras.json")
    tex = {k: read_exr(cap / "gt" / f"{k}.exr") for k in ("diffuse", "specular", "roughness")}
    cam = cams.frames[1]
    x = read_exr(cap / "gt" / "linear" / "0001.exr")
    pos = light_position(cam, [0.19, -0.05, 0.0])
    assert abs(np.linalg.norm(pos - cam.center) - np.hypot(0.19, 0.05)) < 1e-9
    moved = render_reference(mesh, tex, cam, cams.light_intensity, PHONE.photos.spp, seed=PHONE.view_seed(1), light_position=pos)
    centred = render_reference(mesh, tex, cam, cams.light_intensity, PHONE.photos.spp, seed=PHONE.view_seed(1))
    np.testing.assert_allclose(moved, x, atol=1e-5)
    assert np.abs(centred - x).max() > 1e-3


def test_ambient_adds_the_recorded_radiance(tmp_path):
    """A grey diffuse object under the ambient term only: the lit-from-everywhere part of a flat
    facing region is a_d L_amb with L_amb = ambient I_e / (pi d^2) (gt/imaging.json)."""
    s = sections.replace(SMALL, format="exr", albedo=0.5, specular=0.0, ambient=0.2, n_views=1, spp=64,
                            write_masks=False)
    cap = make_capture(tmp_path / "amb", s)
    gt = json.loads((cap / "gt" / "imaging.json").read_text())
    assert abs(gt["ambient_radiance"] - 0.2 * 28.0 / (np.pi * 4.2**2)) < 1e-9
    mesh = read_obj(cap / "gt" / "mesh.obj")
    cam = load_cameras(cap / "cameras.json").frames[0]
    tex = {"diffuse": np.full(3, 0.5), "specular": 0.0, "roughness": 0.5}
    flash = render_reference(mesh, tex, cam, 28.0, 64, seed=3 * 100003)
    both = read_exr(cap / "images" / "0000.exr")
    hit = render_reference(mesh, tex, cam, 28.0, 4, alpha=True)[:, :, 3] > 0.99
    amb = (both - flash)[hit].mean()
    # occlusion (grooves) only lowers it; the unoccluded value is the upper bound
    assert 0.6 * 0.5 * gt["ambient_radiance"] < amb < 1.05 * 0.5 * gt["ambient_radiance"], amb


def test_dng_gainmap_undoes_the_falloff(tmp_path):
    """A phone DNG whose lens falloff is corrected by an OpcodeList3 GainMap: linearize applies
    it and returns the scene (gt/linear) again; without the map the corners stay dark."""
    base = sections.replace(SMALL, format="dng", width=64, height=48, falloff=(-0.4, 0.0), n_views=1,
                               distance=3.0, albedo=0.6)
    out = {}
    for gm in (True, False):
        cap = make_capture(tmp_path / f"gm{gm}", sections.replace(base, falloff_gainmap=gm))
        info = linearize_capture(cap, tmp_path / f"lin{gm}")
        assert bool(info["images"]["0000"]["opcodes_applied"]) == gm
        x = read_exr(cap / "gt" / "linear" / "0000.exr")
        got = read_exr(tmp_path / f"lin{gm}" / "0000.exr")
        # away from the silhouette (demosaicing mixes object and background there)
        fg = cv2.erode(((x.mean(2) > 0.05) & (x.max(2) < 0.9)).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        ratio = got.mean(2) / np.maximum(x.mean(2), 1e-6)
        r2 = falloff_map(64, 48, 1.0, 0.0) - 1.0
        out[gm] = [np.median(ratio[fg & (r2 >= lo) & (r2 < lo + 0.1)]) for lo in (0.1, 0.2, 0.3)]
    # corrected: flat within 1 % at every radius; uncorrected: the falloff 1 - 0.4 r^2
    np.testing.assert_allclose(out[True], 1.0, atol=0.01)
    np.testing.assert_allclose(out[False], [1 - 0.4 * 0.15, 1 - 0.4 * 0.25, 1 - 0.4 * 0.35], atol=0.015)
