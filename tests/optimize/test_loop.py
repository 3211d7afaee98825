"""The optimize stage end to end on a tiny synthetic capture: outputs, kill/resume, improvement."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from recon.io.images import read_exr
from recon.io.mesh import read_mesh, read_obj
from recon.optimize import OptimizeSettings, StageSettings, optimize_capture, settings_from_dict
from recon.optimize.guard import self_intersecting_faces
from recon.optimize.remesh import is_manifold
from recon.sections import replace


HERE = Path(__file__).parent
REPO = HERE.parents[1]

TINY = OptimizeSettings(
    render={"resolution": 32, "spp": 1}, schedule={"views_per_iteration": 2, "checkpoint_every": 2},
    loss={"w_edge": 0.01}, stages=(StageSettings(0.12, 32, 4), StageSettings(0.09, 64, 4)),
)


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    import synthetic

    root = tmp_path_factory.mktemp("capture")
    cap = synthetic.make_capture(root, n_views=8, size=32, spp=16, subdivisions=3)
    return root, cap


def _inputs(root):
    return (sorted((root / "images").glob("*.exr")), sorted((root / "masks").glob("*.png")), None,
            root / "cameras.json", root / "init.obj")


KILLER = """
import os, signal, sys, json, logging
logging.basicConfig(level=logging.INFO)
sys.path.insert(0, {here!r})
import drjit as dr
from recon.mi import load_variant
load_variant(); dr.set_thread_count(1)
from recon.optimize import optimize_capture, settings_from_record
args = json.loads(sys.argv[1])
count = 0
def cb(rec):
    global count
    count += 1
    if count == args["kill_after"]:
        os.kill(os.getpid(), signal.SIGKILL)
optimize_capture(args["images"], args["masks"], None, args["cameras"], args["init"], args["out"],
                 settings_from_record(args["settings"]), progress=False, callback=cb)
"""


def _killed_run(root, out, kill_after, settings=TINY):
    images, masks, _, cams, init = _inputs(root)
    args = {"images": [str(p) for p in images], "masks": [str(p) for p in masks], "cameras": str(cams),
            "init": str(init), "out": str(out), "settings": settings.to_dict(), "kill_after": kill_after}
    p = subprocess.run([sys.executable, "-c", KILLER.format(here=str(HERE)), json.dumps(args)],
                       capture_output=True, text=True, cwd=REPO, timeout=300)
    assert p.returncode == -9, p.stderr[-3000:]  # SIGKILL
    return p.stderr


def test_outputs_resume_after_kill_and_match(capture, tmp_path, drjit_single_thread):
    """Killed twice and resumed: the outputs equal an uninterrupted run's bit for bit. drjit on
    one thread here and in the killed runs (KILLER): float atomics in the renderer's backward
    pass are ordered with one thread."""
    root, _ = capture
    images, masks, sats, cams, init = _inputs(root)
    ref = optimize_capture(images, masks, sats, cams, init, tmp_path / "ref", TINY, progress=False)
    # killed in stage 0 (iteration 2 lost: last checkpoint after iteration 1) ...
    err1 = _killed_run(root, tmp_path / "run", 3)
    assert "resuming" not in err1
    # ... resumed, killed again in stage 1 ...
    err2 = _killed_run(root, tmp_path / "run", 3)
    assert "resuming from checkpoint: stage 0, iteration 2" in err2
    # ... and finished here.
    got = optimize_capture(images, masks, sats, cams, init, tmp_path / "run", TINY, progress=False)
    a, b = tmp_path / "ref", tmp_path / "run"
    for name in ("mesh.obj", "diffuse.exr", "specular.exr", "roughness.exr", "log.jsonl", "summary.json"):
        assert (a / name).is_file() and (b / name).is_file()
    assert (b / "checkpoints" / "last.pt").is_file()
    # the iterations first: a difference shows where the runs parted (iterations 0-1 are the first
    # killed run's, 2-4 the second's, the rest this process's), the stages' meshes after
    la = [json.loads(x) for x in (a / "log.jsonl").read_text().splitlines()]
    lb = [json.loads(x) for x in (b / "log.jsonl").read_text().splitlines()]
    assert len(la) == len(lb) == 8
    for ra, rb in zip(la, lb, strict=True):
        assert {k: v for k, v in ra.items() if not k.startswith("t_")} == {
            k: v for k, v in rb.items() if not k.startswith("t_")}, (ra["stage"], ra["iteration"])
    sa, sb = (json.loads((d / "summary.json").read_text()) for d in (a, b))
    assert [s["vertices"] for s in sa["stages"]] == [s["vertices"] for s in sb["stages"]]
    assert sa["light"] == sb["light"]
    ma, mb = read_obj(a / "mesh.obj"), read_obj(b / "mesh.obj")
    np.testing.assert_array_equal(ma.v_pos, mb.v_pos)
    np.testing.assert_array_equal(ma.t_tex_idx, mb.t_tex_idx)
    for k in ("diffuse", "specular", "roughness"):
        np.testing.assert_array_equal(read_exr(a / f"{k}.exr"), read_exr(b / f"{k}.exr"))
    assert got["final_losses"] == ref["final_losses"]
    # outputs: the contract's maps and a clean mesh
    d = read_exr(a / "diffuse.exr")
    assert d.shape == (64, 64, 3) and read_exr(a / "roughness.exr").shape == (64, 64, 1)
    assert np.all((d >= 0) & (d <= 1)) and np.all(read_exr(a / "roughness.exr") >= TINY.material.r_min - 1e-6)
    assert ma.has_uv and is_manifold(ma.v_pos, ma.t_pos_idx)
    assert not self_intersecting_faces(ma.v_pos, ma.t_pos_idx).any()
    assert ref["mesh"]["manifold"] and ref["mesh"]["self_intersecting_faces"] == 0
    assert [s["iterations"] for s in ref["stages"]] == [4, 4]
    assert set(ref["phase_fraction"]) == {"render", "loss", "backward", "step", "geometry"}
    assert sum(ref["phase_fraction"].values()) == pytest.approx(1.0)
    # a finished checkpoint of the same inputs is reused: no new iterations
    again = optimize_capture(images, masks, sats, cams, init, a, TINY, progress=False)
    assert again["iterations"] == 8 and again["final_losses"] == ref["final_losses"]


def test_other_settings_start_afresh(capture, tmp_path):
    root, _ = capture
    images, masks, sats, cams, init = _inputs(root)
    short = replace(TINY, stages=(StageSettings(0.12, 32, 2),))
    optimize_capture(images, masks, sats, cams, init, tmp_path, short, progress=False)
    other = replace(short, seed=1)
    s = optimize_capture(images, masks, sats, cams, init, tmp_path, other, progress=False)
    log = [json.loads(x) for x in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert s["iterations"] == 2 and [r["iteration"] for r in log] == [0, 1]


def test_bad_inputs(capture, tmp_path):
    root, _ = capture
    images, masks, sats, cams, init = _inputs(root)
    from recon.optimize.views import ViewsError

    with pytest.raises(ViewsError, match="one mask per image"):
        optimize_capture(images, masks[:2], sats, cams, init, tmp_path, TINY, progress=False)
    assert not (tmp_path / "mesh.obj").exists()


def test_settings_from_preset_dict():
    s = settings_from_dict({"stages": [{"edge_length": 0.05, "texture_size": 64, "iterations": 3}],
                           "optim": {"optimizer": "adam"}})
    assert s.stages[0].texture_size == 64 and s.optim.optimizer == "adam"
    from recon.config import ConfigError

    with pytest.raises(ConfigError, match="unknown OptimizeSettings key"):
        settings_from_dict({"iters": 3})
    with pytest.raises(ConfigError, match="optimizer must be one of"):
        settings_from_dict({"optim": {"optimizer": "sgd"}})
    with pytest.raises(ConfigError, match="edge_length"):
        settings_from_dict({"stages": [{"edge_length": 2.0}]})
    abl = replace(OptimizeSettings(), coarse_to_fine=False, use_laplacian=False, use_material_priors=False)
    (only,) = abl.effective_stages()
    assert only.iterations == sum(st.iterations for st in abl.stages)
    assert only.edge_length == abl.stages[-1].edge_length
    w = abl.weights()
    assert w["laplacian"] == w["specular"] == w["roughness"] == 0 and w["edge"] > 0
    assert OptimizeSettings(loss={"use_normal_edge": False}).weights()["normal"] == 0
    st = StageSettings(iterations=11, lr_scale=0.5, lr_decay=0.1)
    assert st.lr_factor(0) == pytest.approx(0.5) and st.lr_factor(10) == pytest.approx(0.05)
    assert st.lr_factor(5) == pytest.approx(0.5 * 0.1**0.5)
    with pytest.raises(ValueError, match="lr_decay"):
        StageSettings(lr_decay=0.0)
    with pytest.raises(ValueError, match="lambda_scale"):
        StageSettings(lambda_scale=0.0)
    with pytest.raises(ValueError, match="largesteps_reference_edge"):
        OptimizeSettings(optim={"largesteps_reference_edge": -0.1})


def test_from_dirs_pairs_views_masks_and_clipped_pixels(capture, tmp_path):
    from recon.io.images import write_mask
    from recon.optimize import OptimizeError, optimize_from_dirs

    root, cap = capture
    sat = root / "images" / "0000.sat.png"
    write_mask(sat, np.zeros((32, 32), bool))
    short = replace(TINY, stages=(StageSettings(0.12, 32, 1),))
    s = optimize_from_dirs(root / "images", root / "masks", root / "cameras.json", root / "init.obj", tmp_path, short,
                           progress=False)
    assert s["iterations"] == 1
    sat.unlink()
    (tmp_path / "m").mkdir()
    with pytest.raises(OptimizeError, match=r"0000\.png: no mask for view '0000'"):
        optimize_from_dirs(root / "images", tmp_path / "m", root / "cameras.json", root / "init.obj", tmp_path, short)


@pytest.mark.parametrize("preset", ["draft", "balanced", "accurate"])
def test_presets_build(preset):
    from recon.config import load_preset

    section = load_preset(preset)["optimize"]
    s = settings_from_dict(section, f"{preset}.yaml")
    assert len(s.stages) >= 1 and all(st.iterations > 0 for st in s.stages)
    edges = [st.edge_length for st in s.stages]
    assert edges == sorted(edges, reverse=True)  # coarse to fine


@pytest.mark.parametrize("change", [
    {"optimizer": "adam", "laplacian": "cotangent"},
    {"boundary": "none", "use_laplacian": False, "use_normal_edge": False, "use_material_priors": False},
    {"coarse_to_fine": False, "parameterization": "clamp", "texture_levels": 1, "guard": False},
])
def test_options_and_ablations_run(capture, tmp_path, change):
    root, _ = capture
    images, masks, sats, cams, init = _inputs(root)
    s = replace(TINY, stages=(StageSettings(0.12, 32, 2), StageSettings(0.09, 32, 1)), **change)
    out = optimize_capture(images, masks, sats, cams, init, tmp_path, s, progress=False)
    n_stages = 1 if change.get("coarse_to_fine") is False else 2
    assert len(out["stages"]) == n_stages and out["iterations"] == 3
    log = [json.loads(x) for x in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert all(np.isfinite(r["loss"]) for r in log)
    if change.get("use_laplacian") is False:
        assert not any(k in log[0] for k in ("loss_laplacian", "loss_edge", "loss_normal", "loss_specular"))
    d = read_exr(tmp_path / "diffuse.exr")
    assert np.all((d >= 0) & (d <= 1))


def test_guard_under_large_steps_is_deterministic_and_clean(capture, tmp_path, drjit_single_thread):
    """Huge geometry steps: the guard backs off often (also in the pipelined check/redo path),
    the result has no self-intersections, and two runs agree exactly (drjit on one thread: the
    renderer's float atomics in a fixed order)."""
    root, _ = capture
    images, masks, sats, cams, init = _inputs(root)
    s = replace(TINY, optimizer="adam", lr_geometry=0.1, checkpoint_every=3, stages=(StageSettings(0.12, 32, 6),))
    runs = [optimize_capture(images, masks, sats, cams, init, tmp_path / str(k), s, progress=False) for k in (0, 1)]
    log = [json.loads(x) for x in (tmp_path / "0" / "log.jsonl").read_text().splitlines()]
    assert sum(r["guard_halvings"] > 0 for r in log) >= 3
    assert runs[0]["mesh"]["self_intersecting_faces"] == 0 and runs[0]["mesh"]["manifold"]
    np.testing.assert_array_equal(read_obj(tmp_path / "0" / "mesh.obj").v_pos, read_obj(tmp_path / "1" / "mesh.obj").v_pos)


def test_stages_never_remesh_finer_than_the_pixels(capture, tmp_path):
    """``schedule.min_edge_pixels``: a stage whose edge length is below that many pixel footprints (at its
    image size) is remeshed at the limit instead; 0 keeps the requested lengths. A stage's
    ``lambda_scale`` multiplies the large-steps lambda, and so does (reference / edge)^2 on stages
    finer than ``optim.largesteps_reference_edge``."""
    from recon.io.cameras import load_cameras
    from recon.optimize.views import pixel_footprint

    root, _ = capture
    images, masks, sats, cams, init = _inputs(root)
    stages = (StageSettings(0.12, 32, 1, image_size=16), StageSettings(0.06, 32, 1, lambda_scale=4.0))
    free = optimize_capture(images, masks, sats, cams, init, tmp_path / "free",
                            replace(TINY, stages=stages, min_edge_pixels=0.0, largesteps_reference_edge=0.1),
                            progress=False)
    capped = optimize_capture(images, masks, sats, cams, init, tmp_path / "capped",
                              replace(TINY, stages=stages, min_edge_pixels=3.0, largesteps_reference_edge=0.0),
                              progress=False)
    m = read_mesh(init)
    lo, hi = m.bbox()
    frames = load_cameras(cams).frames
    full = pixel_footprint(frames, (lo + hi) / 2)  # the capture's 32 px images
    scale = float(np.max(hi - lo))
    for k, (size, rel) in enumerate([(16, 0.12), (32, 0.06)]):
        a, b = free["stages"][k], capped["stages"][k]
        assert a["edge_length"] == pytest.approx(rel * scale)
        assert b["edge_length_min"] == pytest.approx(3.0 * full * 32 / size, rel=1e-6)
        assert b["edge_length"] == pytest.approx(max(rel * scale, b["edge_length_min"]))
    assert [st["largesteps_lambda"] for st in capped["stages"]] == [TINY.optim.largesteps_lambda, 4 * TINY.optim.largesteps_lambda]
    # the reference edge (0.1 of the bbox) leaves the 0.12 stage alone and scales the 0.06 one
    assert [st["largesteps_lambda"] for st in free["stages"]] == pytest.approx(
        [TINY.optim.largesteps_lambda, 4 * TINY.optim.largesteps_lambda * (0.1 / 0.06) ** 2])
    # the second stage (32 px) asks for less than 3 pixels and is held at the limit: fewer faces
    assert capped["stages"][1]["edge_length"] > 0.06 * scale
    assert capped["stages"][1]["faces"] < free["stages"][1]["faces"]


def test_support_plane_is_never_crossed(capture, tmp_path):
    """A support plane (plane.json) just under the initial mesh: large geometry steps push
    vertices down, each step's projection puts them back onto the plane (logged), the final
    surface stays above it; the same run without the plane goes below (the control)."""
    from recon.support import SupportPlane, save_plane

    root, _ = capture
    images, masks, sats, cams, init = _inputs(root)
    z0 = read_mesh(init).v_pos[:, 2].min() + 0.01
    save_plane(tmp_path / "plane.json", SupportPlane(np.array([0.0, 0.0, 1.0]), -z0))
    s = replace(TINY, optimizer="adam", lr_geometry=0.05, stages=(StageSettings(0.12, 32, 4), StageSettings(0.09, 32, 2)))
    optimize_capture(images, masks, sats, cams, init, tmp_path / "free", s, progress=False,
                     plane_json=tmp_path / "absent.json")
    optimize_capture(images, masks, sats, cams, init, tmp_path / "plane", s, progress=False,
                     plane_json=tmp_path / "plane.json")
    assert read_obj(tmp_path / "free" / "mesh.obj").v_pos[:, 2].min() < z0 - 0.005
    v = read_obj(tmp_path / "plane" / "mesh.obj").v_pos
    assert v[:, 2].min() >= z0 - 1e-6
    assert np.count_nonzero(np.abs(v[:, 2] - z0) < 1e-6) >= 1  # vertices resting on the plane
    log = [json.loads(x) for x in (tmp_path / "plane" / "log.jsonl").read_text().splitlines()]
    assert sum(r["plane_projected"] for r in log) > 0
    free_log = [json.loads(x) for x in (tmp_path / "free" / "log.jsonl").read_text().splitlines()]
    assert all(r["plane_projected"] == 0 for r in free_log)
    # the masks were given (no masks.json of the tabletop method beside plane.json): all trusted
    summary = json.loads((tmp_path / "plane" / "summary.json").read_text())
    assert all(st["foot_pixels_out"] is None for st in summary["stages"])


def test_tabletop_masks_leave_the_foot_out(capture, tmp_path):
    """With tabletop masks (masks.json beside plane.json says so, with its parallax band) the
    pixels near the silhouettes at the foot leave the image term (recon.optimize.foot): the
    summary gives their share per stage; views whose masks were given keep them all."""
    from recon.support import SupportPlane, save_plane

    root, _ = capture
    images, masks, sats, cams, init = _inputs(root)
    z0 = read_mesh(init).v_pos[:, 2].min()
    save_plane(tmp_path / "plane.json", SupportPlane(np.array([0.0, 0.0, 1.0]), -z0))
    stems = [Path(p).stem for p in images]
    views = {s: {"source": "tabletop"} for s in stems}
    (tmp_path / "masks.json").write_text(json.dumps({"method": "tabletop", "views": views,
                                                     "segment": {"hull": {"parallax_band": 0.1, "height": 1.0}}}))
    off = replace(TINY, stages=(StageSettings(0.12, 32, 2),), uncertain_foot=0.0)
    got = optimize_capture(images, masks, sats, cams, init, tmp_path / "off", off, progress=False,
                           plane_json=tmp_path / "plane.json")
    assert got["stages"][0]["foot_pixels_out"] is None  # turned off
    s = replace(off, uncertain_foot=1.5)
    got = optimize_capture(images, masks, sats, cams, init, tmp_path / "t", s, progress=False,
                           plane_json=tmp_path / "plane.json")
    assert 0.0 < got["stages"][0]["foot_pixels_out"] < 0.3
    # every doubted pixel left out instead (the table's not made background): the same pixels doubted
    ex = optimize_capture(images, masks, sats, cams, init, tmp_path / "ex", replace(s, uncertain_foot_mode="exclude"),
                          progress=False, plane_json=tmp_path / "plane.json")
    assert ex["stages"][0]["foot_pixels_out"] == got["stages"][0]["foot_pixels_out"]
    assert ex["settings"]["uncertain_foot_mode"] == "exclude" and got["settings"]["uncertain_foot_mode"] == "background"
    assert np.isfinite(ex["final_losses"]["loss_render"])
    for v in views.values():
        v["source"] = "given"
    (tmp_path / "masks.json").write_text(json.dumps({"method": "given", "views": views}))
    got = optimize_capture(images, masks, sats, cams, init, tmp_path / "g", s, progress=False,
                           plane_json=tmp_path / "plane.json")
    assert got["stages"][0]["foot_pixels_out"] is None


def test_imaging_loop_resumes_after_kill_and_matches(capture, tmp_path, drjit_single_thread):
    """imaging.loop: select, killed in stage 1 (after the selection on stage 0's model): the
    resumed run restores the chosen terms and their refined values and ends where the
    uninterrupted run does (bit for bit: drjit on one thread)."""
    root, _ = capture
    images, masks, sats, cams, init = _inputs(root)
    # the flash offset given (capture.yaml), so stage 1 renders with it whatever the selection keeps
    s = replace(TINY, loop="select", terms=("exposure", "falloff"), holdout_every=4, select_iterations=8,
                select_image_size=32, select_spp=1, flash_offset=(0.02, 0.0, 0.0))
    ref = optimize_capture(images, masks, sats, cams, init, tmp_path / "ref", s, progress=False)
    err = _killed_run(root, tmp_path / "run", 7, s)  # stage 1, iteration 2 (last checkpoint: iteration 1)
    assert "imaging terms for the loop" in err
    got = optimize_capture(images, masks, sats, cams, init, tmp_path / "run", s, progress=False)
    assert ref["imaging_loop"]["evidence"]["after_stage"] == 0
    np.testing.assert_allclose(ref["imaging_loop"]["values_after_loop"]["flash_offset"], [0.02, 0.0, 0.0], rtol=1e-6)
    assert got["imaging_loop"]["chosen"] == ref["imaging_loop"]["chosen"]
    assert got["imaging_loop"]["values_after_loop"] == ref["imaging_loop"]["values_after_loop"]
    np.testing.assert_array_equal(read_obj(tmp_path / "ref" / "mesh.obj").v_pos,
                                  read_obj(tmp_path / "run" / "mesh.obj").v_pos)
    np.testing.assert_array_equal(read_exr(tmp_path / "ref" / "diffuse.exr"), read_exr(tmp_path / "run" / "diffuse.exr"))
