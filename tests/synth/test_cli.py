"""``python -m recon synth``: arguments map onto SynthSettings; user errors exit with a message."""

import json
import subprocess
import sys

from recon import sections
from recon.__main__ import build_parser, main
from recon.io.cameras import load_cameras
from recon.synth.capture import PRESETS, TABLETOP_FIELDS, SynthSettings, recorded_settings
from recon.synth.cli import command_line, settings_from_args


def test_arguments_map_onto_settings():
    args = build_parser().parse_args(["synth", "out", "--preset", "demo", "--views", "7",
                                      "--res", "64", "--object", "torus", "--no-cameras",
                                      "--masks", "--format", "exr", "--exposure-variation", "0"])
    s = settings_from_args(args)
    c = s.cameras
    assert (c.n_views, c.width, c.height, s.object, s.photos.format) == (7, 64, 48, "torus", "exr")
    assert not s.outputs.write_cameras and s.outputs.write_masks
    assert s.photos.spp == PRESETS["demo"].photos.spp  # untouched options keep the preset's values
    s = settings_from_args(build_parser().parse_args(["synth", "out", "--res", "100", "--height", "60"]))
    assert (s.cameras.width, s.cameras.height) == (100, 60)


def test_main_writes_a_capture(tmp_path):
    rc = main(["synth", str(tmp_path / "c"), "--views", "2", "--res", "32", "--spp", "2",
               "--mesh-level", "2", "--texture-size", "32", "--format", "exr", "--no-noise"])
    assert rc == 0
    assert len(load_cameras(tmp_path / "c" / "cameras.json")) == 2
    meta = json.loads((tmp_path / "c" / "gt" / "synth.json").read_text())
    # the recorded command line gives the same settings back
    recorded = meta["command"].split()[5:]
    again = settings_from_args(build_parser().parse_args(["synth", "o", *recorded]))
    recorded_again = json.loads(json.dumps(recorded_settings(again)))
    assert recorded_again == meta["settings"]
    assert tuple(meta["settings"]["view_z_range"]) == again.cameras.view_z_range
    # a void capture records no tabletop settings: they are at their defaults
    assert {k: sections.flatten(again)[k] for k in TABLETOP_FIELDS} == \
        {k: sections.flatten(SynthSettings())[k] for k in TABLETOP_FIELDS}


def test_user_error_exits_2_with_message(tmp_path):
    r = subprocess.run([sys.executable, "-m", "recon", "synth", str(tmp_path / "x"), "--res", "33"],
                       capture_output=True, text=True)
    assert r.returncode == 2
    assert "even" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "x").exists()


def test_every_option_still_sets_its_setting():
    """The command line's options keep their names and reach their settings in the sections."""
    args = build_parser().parse_args([
        "synth", "out", "--scene", "tabletop", "--elevations", "20", "50", "--rings", "2", "--background", "0.2",
        "--table-texture-size", "64", "--marker-square", "0.2", "--palette", "glaze", "--no-pattern",
        "--wall", "0.4", "--lamps", "0.2", "--closeups", "0.1", "--format", "jpg", "--flash-offset", "0.1", "0", "0",
        "--ambient", "0.05", "--exposure-jitter", "0.2", "--wb-jitter", "0.02", "--falloff", "-0.2", "0",
        "--tone-curve", "phone", "--jpeg-quality", "90", "--seed", "3", "--scale", "2", "--spp", "8",
        "--no-gt-linear", "--state-light"])
    s = settings_from_args(args)
    assert s.tabletop.elevation_range == (20.0, 50.0) and s.tabletop.rings == 2 and s.tabletop.background == 0.2
    assert (s.tabletop.table_texture_size, s.tabletop.marker_square) == (64, 0.2)
    assert (s.variations.palette, s.variations.texture_pattern, s.variations.wall) == ("glaze", False, 0.4)
    assert s.phone.flash_offset == (0.1, 0.0, 0.0) and s.phone.tone_curve == "phone" and s.phone.jpeg_quality == 90
    assert (s.seed, s.scale, s.photos.spp, s.outputs.write_gt_linear, s.outputs.state_light) == (3, 2.0, 8, False, True)
    again = settings_from_args(build_parser().parse_args(["synth", *command_line(args).split()[4:]]))
    assert again == s
