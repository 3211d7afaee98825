"""Scene variations that make masks hard (recon.synth: turned shapes, palettes, a wall, lamps,
close-ups, the stand scene): each is off by default and leaves the generator's outputs as they were."""

import json

import numpy as np
import pytest

from recon import sections
from recon.__main__ import build_parser
from recon.io.cameras import load_cameras
from recon.io.images import read_exr, read_mask
from recon.synth.capture import VARIATION_FIELDS, SynthError, SynthSettings, make_capture, recorded_settings
from recon.synth.cli import command_line, settings_from_args
from recon.synth.materials import PALETTES, MaterialFields
from recon.synth.shapes import FLAT_BASE, EXTENT, make_object, revolve


def _edges(mesh):
    f = mesh.t_pos_idx
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0, return_counts=True)


@pytest.mark.parametrize("kind", ["bell", "vase", "bowl", "box", "figure"])
def test_standing_shapes_are_closed_genus_0_and_stand_on_a_flat_base(kind):
    m = make_object(kind, 3, seed=2)
    uniq, counts = _edges(m)
    assert set(counts.tolist()) == {2}  # closed two-manifold
    assert len(m.v_pos) - len(uniq) + len(m.t_pos_idx) == 2  # genus 0
    assert m.volume() > 0 and abs(np.abs(m.v_pos).max() - EXTENT) < 1e-9
    z0 = m.v_pos[:, 2].min()
    base = np.abs(m.v_pos[:, 2] - z0) < 1e-9
    assert np.ptp(m.v_pos[base, 0]) > 0.3  # a flat base, not a point
    assert kind in FLAT_BASE
    lo, hi = m.bbox()
    size = hi - lo
    if kind == "vase":
        assert size[2] > 2.0 * size[0]  # tall
    if kind == "box":  # flat faces: most of the vertices lie on the six planes of the box's faces
        on_face = (np.abs(np.abs(m.v_pos) - np.abs(m.v_pos).max(0)) < 1e-2).any(1)
        assert on_face.mean() > 0.7
    if kind == "figure":  # two feet apart: the soles' vertices fall in two groups either side of x = 0
        sole = m.v_pos[base]
        assert (sole[:, 0] < -0.1).any() and (sole[:, 0] > 0.1).any() and not (np.abs(sole[:, 0]) < 0.05).any()
        assert size[0] > 1.5 * size[1]  # the arms held out sideways
    if kind == "bowl":
        assert size[2] < 0.4 * size[0]  # low
        # open: the axis (the two poles of the turned surface) runs from the base to the cavity's
        # floor, far below the rim
        r = np.hypot(*(m.v_pos[:, :2] - m.v_pos[:, :2].mean(0)).T)
        poles = m.v_pos[np.argsort(r)[:2], 2]
        assert poles.max() < hi[2] - 0.5 * size[2]


def test_revolve_needs_a_profile_from_axis_to_axis():
    with pytest.raises(ValueError, match="axis"):
        revolve(np.array([[0.5, 0.0], [0.5, 1.0], [0.0, 1.0]]), 2)


def test_palettes_colour_the_object():
    p = np.random.default_rng(0).normal(size=(2000, 3))
    for name, colours in PALETTES.items():
        a_d, _, _ = MaterialFields(seed=1, palette=name, pattern=False).evaluate(p)
        # no pattern: exactly the palette's colours
        assert {tuple(np.round(c, 6)) for c in a_d} <= {tuple(np.round(c, 6)) for c in colours}
    base, _, _ = MaterialFields(seed=1).evaluate(p)
    again, _, _ = MaterialFields(seed=1, palette="default", pattern=True).evaluate(p)
    np.testing.assert_array_equal(base, again)


def test_defaults_record_no_variation():
    s = SynthSettings()
    assert not s.has_variations and not set(VARIATION_FIELDS) & set(recorded_settings(s))
    v = sections.replace(SynthSettings(), scene="tabletop", palette="glaze", texture_pattern=False, wall=0.5, lamps=0.2, closeups=0.2)
    assert v.has_variations and set(VARIATION_FIELDS) <= set(recorded_settings(v))
    with pytest.raises(SynthError, match="palette"):
        sections.replace(SynthSettings(), palette="neon")
    with pytest.raises(SynthError, match="tabletop"):
        sections.replace(SynthSettings(), wall=0.5)  # a void scene has no room


def test_command_line_round_trip_of_variations():
    argv = ["synth", "out", "--scene", "stand", "--object", "bell", "--palette", "dark", "--no-pattern",
            "--wall", "0.4", "--lamps", "0.3", "--closeups", "0.25", "--stand-height", "1.5"]
    args = build_parser().parse_args(argv)
    s = settings_from_args(args)
    assert (s.scene, s.variations.palette, s.variations.texture_pattern, s.variations.wall, s.variations.lamps, s.variations.closeups, s.variations.stand_height) == \
        ("stand", "dark", False, 0.4, 0.3, 0.25, 1.5)
    again = settings_from_args(build_parser().parse_args(command_line(args).split()[3:]))
    assert again == s


def test_stand_scene_with_a_wall_lamps_and_close_ups(tmp_path):
    """A tiny stand capture: the stand under the object in gt/masks_with_stand only, the close-up
    view cut by the frame, the lamps lighting what the flash alone leaves darker."""
    kw = dict(scene="stand", object="bell", n_views=4, width=64, height=48, fov=50.0, distance=5.0, spp=4,
              mesh_level=3, texture_size=64, format="exr", noise=False, write_gt_linear=True,
              elevation_range=(10.0, 40.0), rings=1, wall=0.5, closeups=0.25, palette="glaze")
    cap = make_capture(tmp_path / "lit", sections.replace(SynthSettings(), **kw, lamps=0.5))
    dark = make_capture(tmp_path / "flash", sections.replace(SynthSettings(), **kw))
    meta = json.loads((cap / "gt" / "synth.json").read_text())
    assert meta["settings"]["scene"] == "stand" and meta["settings"]["lamps"] == 0.5
    assert not (cap / "gt" / "plane.json").exists()
    cams = load_cameras(cap / "gt" / "cameras.json")
    cut = stands = 0
    for c in cams:
        obj = read_mask(cap / "gt" / "masks" / f"{c.stem}.png")
        both = read_mask(cap / "gt" / "masks_with_stand" / f"{c.stem}.png")
        assert obj.any() and not (obj & ~both).any()
        if (both & ~obj).sum() > 0:  # the stand shows (a close-up may leave it out of the frame) ...
            stands += 1
            rows = np.flatnonzero((both & ~obj).any(1))
            assert rows.max() >= np.flatnonzero(obj.any(1)).max()  # ... under the object
        cut += int(obj[0].any() or obj[-1].any() or obj[:, 0].any() or obj[:, -1].any())
        lit = read_exr(cap / "gt" / "linear" / f"{c.stem}.exr")
        alone = read_exr(dark / "gt" / "linear" / f"{c.stem}.exr")
        assert lit[obj].mean() > 1.05 * alone[obj].mean()
    assert cut >= 1 and stands >= 3  # the close-up view cut by the frame; the stand in the others
