"""Camera refinement inside the optimize stage (issue 17): given cameras untouched, SfM cameras
refined and written to optimize/cameras.json, checkpoints carry the corrections, the held-out
selection and what the report shows of it. The tiny capture of test_loop.py (same kernels)."""

import json
import shutil

import numpy as np
import pytest
import torch

from recon.io.cameras import Camera, CameraSet, load_cameras, save_cameras
from recon.io.mesh import read_obj
from recon.metrics import pose_errors
from recon.optimize import OptimizeSettings, StageSettings, optimize_capture
from recon.optimize import objective
from recon.optimize.camera_refine import rotation_exp
from recon.report.html import Page, render_page
from recon.report.stage import camera_refinement
from recon.sections import replace

TINY = OptimizeSettings(
    render={"resolution": 32, "spp": 1}, schedule={"views_per_iteration": 4, "checkpoint_every": 100},
    loss={"w_edge": 0.01}, stages=(StageSettings(0.12, 32, 4),),
    select={"select_material": False, "select_image_size": 32, "select_spp": 1}, cameras={"align_iterations": 6},
)


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    import synthetic

    root = tmp_path_factory.mktemp("capture")
    synthetic.make_capture(root, n_views=8, size=32, spp=16, subdivisions=3)
    return root


def _inputs(root):
    return sorted((root / "images").glob("*.exr")), sorted((root / "masks").glob("*.png"))


def _sfm_cameras(root, folder, deg=1.0, seed=0):
    """The capture's cameras, each rotated by ``deg`` about its centre, as an SfM result
    (poses.json source "sfm" beside cameras.json)."""
    true = load_cameras(root / "cameras.json")
    rng = np.random.default_rng(seed)
    out = []
    for c in true.frames:
        w = rng.normal(size=3)
        w *= np.deg2rad(deg) / np.linalg.norm(w)
        E = rotation_exp(torch.tensor(w)).numpy()
        T = c.world_to_camera.copy()
        T[:3, :3], T[:3, 3] = E @ T[:3, :3], E @ T[:3, 3]
        out.append(Camera(c.image, c.width, c.height, c.K.copy(), T))
    folder.mkdir(parents=True, exist_ok=True)
    save_cameras(folder / "cameras.json", CameraSet(tuple(out), true.light_intensity))
    (folder / "poses.json").write_text(json.dumps({"source": "sfm"}))
    return folder / "cameras.json", true


def _settings(**kw):
    return replace(TINY, **kw)


def test_camera_mode_and_settings():
    s = OptimizeSettings()
    assert s.cameras.refine == "select"
    assert s.camera_mode("sfm")[0] == "select"
    assert s.camera_mode("given")[0] == "off" and s.camera_mode(None)[0] == "off"
    assert OptimizeSettings(cameras={"refine_given": True}).camera_mode("given")[0] == "select"
    assert OptimizeSettings(cameras={"refine": "off"}).camera_mode("sfm")[0] == "off"
    with pytest.raises(ValueError, match="refine must be one of"):
        OptimizeSettings(cameras={"refine": "yes"})
    with pytest.raises(ValueError, match="sigma_rotation_deg"):
        OptimizeSettings(cameras={"sigma_rotation_deg": 0.0})
    with pytest.raises(ValueError, match="w_camera"):
        OptimizeSettings(loss={"w_camera": -1.0})
    assert objective.weights(s)["camera"] == s.loss.w_camera
    assert objective.camera_terms(None, [0], objective.weights(s)) == {}


def test_given_cameras_are_not_refined(capture, tmp_path):
    """No poses.json (or source "given"): the default "select" does nothing and
    optimize/cameras.json holds the input cameras unchanged."""
    images, masks = _inputs(capture)
    given = tmp_path / "poses"
    given.mkdir()
    shutil.copy(capture / "cameras.json", given / "cameras.json")
    (given / "poses.json").write_text(json.dumps({"source": "given"}))
    for cams_json in (capture / "cameras.json", given / "cameras.json"):
        out = tmp_path / cams_json.parent.name / "out"
        s = optimize_capture(images, masks, None, cams_json, capture / "init.obj", out, TINY, progress=False)
        info = s["camera_refinement"]
        assert info["mode"] == "off" and not info["refined"] and "corrections" not in info
        assert not any(k == "loss_camera" for k in s["final_losses"])
        a, b = load_cameras(out / "cameras.json"), load_cameras(cams_json)
        for x, y in zip(a.frames, b.frames, strict=True):
            assert x.image == y.image and np.array_equal(x.K, y.K)
            assert np.array_equal(x.world_to_camera, y.world_to_camera)
        assert a.extra["optimize_cameras"]["refined"] is False
        assert a.light_intensity == b.light_intensity


def test_sfm_cameras_refined_written_and_resumed(capture, tmp_path, drjit_single_thread):
    """Cameras 1 degree off, labelled SfM, refine "on": the renderer pulls them towards the
    truth (rotation error after the Umeyama fit down), optimize/cameras.json holds them, and a
    run interrupted after a checkpoint resumes to the same cameras and mesh (drjit on one thread:
    the backward pass's float atomics in a fixed order, so resumed == uninterrupted)."""
    images, masks = _inputs(capture)
    cams_json, true = _sfm_cameras(capture, tmp_path / "poses")
    s = _settings(refine="on", checkpoint_every=10, stages=(StageSettings(0.12, 32, 30),), lr_rotation_deg=0.05)
    ref = optimize_capture(images, masks, None, cams_json, capture / "init.obj", tmp_path / "ref", s,
                           progress=False)
    info = ref["camera_refinement"]
    assert info["mode"] == "on" and info["refined"] and len(info["corrections"]["views"]) == 8
    assert "loss_camera" in ref["final_losses"]
    out = load_cameras(tmp_path / "ref" / "cameras.json")
    assert out.extra["optimize_cameras"]["refined"] is True
    before = pose_errors(load_cameras(cams_json), true)["mean_rotation_deg"]
    after = pose_errors(out, true)["mean_rotation_deg"]
    assert after < 0.9 * before, (before, after)
    for c in out.frames:
        assert np.all(np.isfinite(c.K)) and np.all(np.isfinite(c.world_to_camera))

    class Stop(Exception):
        pass

    def stop_at(rec):
        if rec["iteration"] == 14:
            raise Stop

    with pytest.raises(Stop):
        optimize_capture(images, masks, None, cams_json, capture / "init.obj", tmp_path / "run", s,
                         progress=False, callback=stop_at)
    got = optimize_capture(images, masks, None, cams_json, capture / "init.obj", tmp_path / "run", s,
                           progress=False)
    assert got["iterations"] == ref["iterations"]
    a, b = load_cameras(tmp_path / "run" / "cameras.json"), out
    for x, y in zip(a.frames, b.frames, strict=True):
        np.testing.assert_allclose(x.world_to_camera, y.world_to_camera, atol=1e-6)
        np.testing.assert_allclose(x.K, y.K, rtol=1e-6)
    np.testing.assert_allclose(read_obj(tmp_path / "run" / "mesh.obj").v_pos,
                               read_obj(tmp_path / "ref" / "mesh.obj").v_pos, atol=1e-5)


def test_select_decides_on_held_out_views_and_the_report_shows_it(capture, tmp_path):
    """"select" on SfM-labelled cameras: two runs, held-out poses aligned for each, the paired
    test decides; the outputs are the chosen run's (mesh = its checkpoint, training cameras
    refined only when kept, held-out cameras aligned); metrics.json's section lists every view."""
    images, masks = _inputs(capture)
    cams_json, _ = _sfm_cameras(capture, tmp_path / "poses", deg=2.0, seed=1)
    s = _settings(refine="select", stages=(StageSettings(0.12, 32, 12),))
    summary = optimize_capture(images, masks, None, cams_json, capture / "init.obj", tmp_path / "out", s,
                               progress=False)
    info = summary["camera_refinement"]
    sel = info["selection"]
    assert info["mode"] == "select" and info["refined"] == sel["accepted"]
    assert np.isfinite(sel["control_heldout_error"]) and np.isfinite(sel["refined_heldout_error"])
    assert sel["gain"] == pytest.approx(sel["control_heldout_error"] - sel["refined_heldout_error"], abs=1e-9)
    assert summary["phase_seconds"]["cameras"] > 0 and len(sel["run_seconds"]) == 2
    held = summary["holdout"]["held_out"]
    assert len(held) == 2 and info["heldout_alignment"]["mean_rotation_deg"] > 0
    chosen = tmp_path / "out" / "checkpoints" / ("cameras" if info["refined"] else "")
    state = torch.load(chosen / "last.pt", map_location="cpu", weights_only=False)
    np.testing.assert_allclose(read_obj(tmp_path / "out" / "mesh.obj").v_pos, state["mesh"]["v_pos"], atol=1e-5)
    given, out = load_cameras(cams_json).by_stem(), load_cameras(tmp_path / "out" / "cameras.json").by_stem()
    for stem, c in out.items():
        moved = not np.array_equal(c.world_to_camera, given[stem].world_to_camera)
        assert moved == (stem in held or info["refined"]), stem
    m = camera_refinement(summary)
    assert set(m["corrections"]["views"]) == set(given) - set(held)
    for v in m["corrections"]["views"].values():
        assert v["rotation_deg"] >= 0 and v["center_shift"] >= 0
    assert set(m["corrections"]["intrinsics_before"]) >= {"fx", "fy", "cx", "cy"}
    assert m["corrections"]["intrinsics_before"]["width"] == 32
    assert m["selection"]["accepted"] == info["refined"]
    page = render_page(Page(capture="c", preset=None, camera_refinement=m))
    assert "Cameras refined by the renderer" in page and all(f"<td>{v}</td>" in page for v in m["corrections"]["views"])


def test_cameras_held_before_camera_first_stage(capture, tmp_path):
    """``cameras.first_stage``: the cameras are held through the stages before it (a value past
    the last stage holds them throughout: output cameras = input), stepped from it on; it is
    refused negative."""
    for bad in (-1, "first", True, 1.5):
        with pytest.raises(ValueError, match="first_stage"):
            OptimizeSettings(cameras={"first_stage": bad})
    images, masks = _inputs(capture)
    cams_json, _ = _sfm_cameras(capture, tmp_path / "poses", deg=1.5, seed=2)
    stages = (StageSettings(0.14, 32, 6), StageSettings(0.12, 32, 6))
    given = load_cameras(cams_json).by_stem()
    for first, moves in ((2, False), (1, True)):
        s = _settings(refine="on", stages=stages, first_stage=first, lr_rotation_deg=0.1)
        out = tmp_path / f"first{first}"
        summary = optimize_capture(images, masks, None, cams_json, capture / "init.obj", out, s, progress=False)
        views = summary["camera_refinement"]["corrections"]["views"]
        assert len(views) == 8
        got = load_cameras(out / "cameras.json").by_stem()
        for stem, c in got.items():
            assert np.all(np.isfinite(c.world_to_camera))
            assert (not np.allclose(c.world_to_camera, given[stem].world_to_camera, atol=1e-9)) == moves, (first, stem)
        assert all((v["rotation_deg"] > 1e-6) == moves for v in views.values()), (first, views)


def test_camera_first_stage_auto_waits_for_the_loop_imaging():
    """``cameras.first_stage: auto`` (the default): with the loop's imaging selection to come
    (``imaging.loop`` on, held-out views) the cameras are refined from the first stage rendered
    under its terms, ``imaging.loop_stage`` + 1, when there is such a stage; otherwise from
    stage 0. A number is taken as it is."""
    auto = OptimizeSettings()
    assert auto.cameras.first_stage == "auto"
    assert auto.camera_start(3, imaging_in_loop=True) == 1
    assert auto.camera_start(3, imaging_in_loop=False) == 0
    assert auto.camera_start(1, imaging_in_loop=True) == 0  # no stage after the selection: never selected
    later = OptimizeSettings(imaging={"loop_stage": 1})
    assert later.camera_start(3, True) == 2 and later.camera_start(2, True) == 0
    assert OptimizeSettings(cameras={"first_stage": 0}).camera_start(3, True) == 0
    assert OptimizeSettings(cameras={"first_stage": 2}).camera_start(3, False) == 2


def test_cameras_wait_for_the_loop_imaging_on_jpeg_photos(capture, tmp_path):
    """``cameras.first_stage: auto`` with ``imaging.loop: select``: photos from JPEG (the
    linearize stage's linear.json says "ldr") have their cameras held until the imaging terms
    are chosen on stage 0's model, and the refined run takes the control's choice (its
    checkpoint's evidence says so); linear photos have them refined from stage 0."""
    import torch as _torch

    images, masks = _inputs(capture)
    cams_json, _ = _sfm_cameras(capture, tmp_path / "poses", deg=0.5, seed=4)
    s = _settings(refine="select", loop="select", terms=("exposure",), holdout_every=4,
                  select_iterations=8, select_image_size=32, select_spp=1,
                  stages=(StageSettings(0.14, 32, 4), StageSettings(0.12, 32, 4)))
    jpeg = tmp_path / "jpeg_views"
    jpeg.mkdir()
    for p in images:
        (jpeg / p.name).symlink_to(p)
    (jpeg / "linear.json").write_text(json.dumps({"images": {p.stem: {"kind": "ldr"} for p in images}}))
    for views, first in ((images, 0), (sorted(jpeg.glob("*.exr")), 1)):
        out = tmp_path / f"first{first}"
        summary = optimize_capture(views, masks, None, cams_json, capture / "init.obj", out, s, progress=False)
        assert summary["camera_refinement"]["first_stage"] == first
        refined = _torch.load(out / "checkpoints" / "cameras" / "last.pt", map_location="cpu", weights_only=False)
        control = _torch.load(out / "checkpoints" / "last.pt", map_location="cpu", weights_only=False)
        ev_r, ev_c = refined["imaging"]["evidence"], control["imaging"]["evidence"]
        assert bool(ev_r.get("shared")) == (first == 1) and not ev_c.get("shared")
        if first == 1:
            assert ev_r["chosen"] == ev_c["chosen"]
