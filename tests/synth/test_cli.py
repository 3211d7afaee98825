"""``python -m recon synth``: arguments map onto SynthSettings; user errors exit with a message."""

import json
import subprocess
import sys

from recon.__main__ import build_parser, main
from recon.io.cameras import load_cameras
from recon.synth.capture import PRESETS, TABLETOP_FIELDS, SynthSettings, recorded_settings
from recon.synth.cli import settings_from_args


def test_arguments_map_onto_settings():
    args = build_parser().parse_args(["synth", "out", "--preset", "demo", "--views", "7",
                                      "--res", "64", "--object", "torus", "--no-cameras",
                                      "--masks", "--format", "exr", "--exposure-variation", "0"])
    s = settings_from_args(args)
    assert (s.n_views, s.width, s.height, s.object, s.format) == (7, 64, 48, "torus", "exr")
    assert not s.write_cameras and s.write_masks
    assert s.spp == PRESETS["demo"].spp  # untouched options keep the preset's values
    s = settings_from_args(build_parser().parse_args(["synth", "out", "--res", "100", "--height", "60"]))
    assert (s.width, s.height) == (100, 60)


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
    assert tuple(meta["settings"]["view_z_range"]) == again.view_z_range
    # a void capture records no tabletop settings: they are at their defaults
    assert {k: getattr(again, k) for k in TABLETOP_FIELDS} == \
        {k: getattr(SynthSettings(), k) for k in TABLETOP_FIELDS}


def test_user_error_exits_2_with_message(tmp_path):
    r = subprocess.run([sys.executable, "-m", "recon", "synth", str(tmp_path / "x"), "--res", "33"],
                       capture_output=True, text=True)
    assert r.returncode == 2
    assert "even" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "x").exists()
