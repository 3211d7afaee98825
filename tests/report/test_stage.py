"""make_report: metrics.json equals what the inputs imply, files are complete, errors name files."""

from __future__ import annotations

import html.parser
import json
import math
import re
import shutil
from pathlib import Path
from urllib.parse import unquote

import numpy as np
import pytest
import report_scene

from recon.report import ReportError, ReportSettings, make_report


def test_metrics_json_matches_return_value_and_is_strict_json(report):
    out, returned, written = report
    assert returned == written
    json.loads((out / "metrics.json").read_text(), parse_constant=lambda c: pytest.fail(f"{c} in metrics.json"))


def test_top_level_keys(report):
    _, _, m = report
    assert m["capture"] == "cap"
    assert m["preset"] == "draft"
    assert m["material_model"] == report_scene.MATERIAL
    assert m["light_intensity"] == report_scene.LIGHT
    assert {"timings", "metrics", "per_view_rmse"} <= set(m)


def test_per_view_rmse_known_values(report, scene):
    """View 0's input is the re-render + 0.1 in sRGB everywhere: RMSE 0.1; the others equal it."""
    _, _, m = report
    assert set(m["per_view_rmse"]) == {c.stem for c in scene.cams.frames}
    for stem, expected in scene.expected_rmse.items():
        assert m["per_view_rmse"][stem] == pytest.approx(expected, abs=2e-6), stem
    assert m["per_view_rmse_mean"] == pytest.approx(np.mean(list(scene.expected_rmse.values())), abs=2e-6)


def test_timings_from_summary_and_benchmarks(report):
    _, _, m = report
    assert m["timings"]["optimize_phases"] == report_scene.SUMMARY["phase_seconds"]
    assert m["timings"]["stages"] == pytest.approx({s: float(np.mean(v)) for s, v in report_scene.BENCHMARKS.items()})
    o = m["optimize"]
    assert o["phases_source"] == "summary.json"
    assert o["final_loss"] == report_scene.LOG_RECORDS[-1]["loss"]
    assert o["iterations"] == len(report_scene.LOG_RECORDS)
    assert o["wall_seconds"] == report_scene.SUMMARY["wall_seconds"]
    assert o["stages"] == report_scene.SUMMARY["stages"]


def test_timings_from_the_log_without_summary(tmp_path, scene, fast_settings):
    args = _copy_inputs(scene, tmp_path)
    (tmp_path / "cap" / "optimize" / "summary.json").unlink()
    m = make_report(**args, settings=ReportSettings(**{**fast_settings.__dict__, "max_views": 1}))
    phases = {}
    for rec in report_scene.LOG_RECORDS:
        for key, value in rec.items():
            if key.startswith("t_"):
                phases[key[2:]] = phases.get(key[2:], 0.0) + value
    assert m["timings"]["optimize_phases"] == pytest.approx(phases)
    assert m["optimize"]["phases_source"] == "log.jsonl"
    assert "material_model" not in m


def test_empty_log_still_makes_a_report(tmp_path, scene, fast_settings):
    args = _copy_inputs(scene, tmp_path)
    (tmp_path / "cap" / "optimize" / "log.jsonl").write_text("")
    m = make_report(**args, settings=ReportSettings(**{**fast_settings.__dict__, "max_views": 1}))
    assert m["optimize"]["final_loss"] is None and m["optimize"]["records"] == 0
    assert "no loss values" in (tmp_path / "out" / "report" / "index.html").read_text()


def test_gt_metrics_zero_when_reconstruction_is_the_ground_truth(report):
    _, _, m = report
    g = m["metrics"]
    for key in ("accuracy", "completeness", "chamfer", "accuracy_seen", "completeness_seen"):
        assert 0.0 <= g[key] < 1e-6, key
    assert 0.5 < g["seen_fraction"] <= 1.0  # the part of the sphere the true cameras see
    assert g["unit"] == pytest.approx(1.0)  # the sphere's bbox side (radius 0.5)
    assert g["image_views"] == "held-out"
    assert set(g["image_rmse_per_view"]) == {"h000"}
    assert g["image_rmse"] == pytest.approx(0.0, abs=1e-6)
    t = g["texture_rmse"]
    assert t["fraction"] == 1.0
    for key in ("diffuse", "specular", "roughness"):
        assert 0.0 <= t[key] < 1e-5, key
    sim = np.array(g["alignment"]["similarity"]["matrix"])
    np.testing.assert_allclose(sim, np.eye(4), atol=1e-9)
    assert g["pose_errors"]["max_center"] < 1e-9


@pytest.mark.parametrize("case", ["mesh_without_uvs", "no_maps", "no_cameras", "broken_mesh"])
def test_partial_ground_truth_is_used_as_far_as_it_goes(tmp_path, scene, fast_settings, case):
    """gt/ is an optional diagnostic: the report computes what its files allow, says what was
    skipped and why (naming the file), and finishes (it used to abort after the asset was made)."""
    from recon.io.mesh import Mesh, read_mesh, write_obj

    gt = tmp_path / "gt"
    shutil.copytree(scene.capture_dir / "gt", gt)
    mesh_file = next(p for p in (gt / "mesh.obj", gt / "mesh.ply") if p.is_file())
    if case == "mesh_without_uvs":
        m = read_mesh(mesh_file)
        mesh_file.unlink()
        for name in ("diffuse", "specular", "roughness"):
            (gt / f"{name}.exr").unlink()
        write_obj(gt / "mesh.obj", Mesh(m.v_pos, m.t_pos_idx))
    elif case == "no_maps":
        (gt / "specular.exr").unlink()
    elif case == "no_cameras":
        (gt / "cameras.json").unlink()
    else:
        mesh_file.write_text("not a mesh")
    args = {**scene.report_args(tmp_path / "report"), "gt_dir": gt}
    m = make_report(**args, settings=ReportSettings(**{**fast_settings.__dict__, "max_views": 1}))
    g = m["metrics"]
    skipped = g["skipped"]
    page = (tmp_path / "report" / "index.html").read_text()
    assert "Skipped" in page
    if case == "broken_mesh":
        assert "accuracy" not in g and "accuracy_seen" not in g and str(mesh_file) in skipped["geometry"]
        assert {"texture_rmse", "image_rmse"} <= set(skipped)
        assert g["pose_errors"]["max_center"] < 1e-9  # the cameras alone still give pose errors
        return
    assert 0.0 <= g["accuracy"] < 1e-6 and 0.0 <= g["completeness"] < 1e-6
    if case == "mesh_without_uvs":
        assert "no UVs" in skipped["texture_rmse"] and "image_rmse" in skipped
        assert "texture_rmse" not in g and "image_rmse" not in g
    elif case == "no_maps":
        assert "specular.exr" in skipped["texture_rmse"]
    else:
        assert "cameras.json" in skipped["pose_errors"] and "cameras.json" in skipped["image_rmse"]
        assert "pose_errors" not in g and g["texture_rmse"]["fraction"] == 1.0
        assert g["alignment"]["method"].startswith("identity")


def test_report_files_are_complete_and_local(report):
    """Every file index.html refers to exists inside report/ (the page opens offline)."""
    out, _, m = report

    class Refs(html.parser.HTMLParser):
        refs: list = []

        def handle_starttag(self, tag, attrs):
            for k, v in attrs:
                if k in ("src", "href") and v:
                    self.refs.append(v)

    p = Refs()
    p.refs = []
    p.feed((out / "index.html").read_text())
    assert len(p.refs) > 10
    for ref in p.refs:
        assert "://" not in ref and not ref.startswith("/"), f"non-local reference {ref}"
        assert (out / unquote(ref)).is_file(), ref
    for stem in m["per_view_rmse"]:
        for role in ("input", "render", "error"):
            assert (out / "views" / f"{stem}.{role}.jpg").is_file()
    assert (out / "asset.glb").read_bytes()[:4] == b"glTF"
    assert (out / "model-viewer-umd.min.js").stat().st_size > 100_000
    assert not list(out.parent.glob(".report.*")), "temporary folders left behind"


def test_view_images_show_the_compared_pixels(report, scene):
    """The written input/re-render images are the sRGB views compared (JPEG: a few levels)."""
    from recon.io.images import linear_to_srgb, read_exr, read_ldr

    out, _, _ = report
    stem = scene.cams.frames[1].stem
    inp, _ = read_ldr(out / "views" / f"{stem}.input.jpg")
    ren, _ = read_ldr(out / "views" / f"{stem}.render.jpg")
    ref = linear_to_srgb(read_exr(scene.results / "linear" / f"{stem}.exr"))
    assert inp.shape == ref.shape
    assert np.abs(inp - ref).mean() < 0.01
    assert np.abs(ren - ref).mean() < 0.01
    err, _ = read_ldr(out / "views" / f"{stem}.error.jpg")
    assert np.all(np.isfinite(err))


def test_scaled_and_rotated_frame_gives_the_same_numbers(tmp_path, scene, fast_settings):
    """Poses from SfM live in another frame: the reconstruction, its cameras and its light in a
    frame scaled by 1/2 and rotated must give the same per-view RMSE, and the gt metrics must
    find the similarity back (chamfer and image RMSE ~0)."""
    from recon.io.cameras import Camera, CameraSet, load_cameras, save_cameras
    from recon.io.mesh import Mesh, read_obj, write_obj

    root = tmp_path / "cap"
    shutil.copytree(scene.results, root, ignore=shutil.ignore_patterns("report", "optimize"))
    (root / "optimize").mkdir()
    for name in ("diffuse.exr", "specular.exr", "roughness.exr", "log.jsonl", "summary.json"):
        shutil.copy(scene.optimize / name, root / "optimize" / name)
    s = 0.5
    a = 0.7
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
    t = np.array([0.3, -0.2, 0.1])
    mesh = read_obj(scene.optimize / "mesh.obj")
    write_obj(root / "optimize" / "mesh.obj",
              Mesh(s * mesh.v_pos @ R.T + t, mesh.t_pos_idx, mesh.v_tex, mesh.t_tex_idx))
    cams = load_cameras(scene.results / "poses" / "cameras.json")
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = s * R, t  # est = M gt
    frames = []
    for c in cams.frames:
        c2w = M @ c.camera_to_world
        c2w[:3, :3] /= s
        frames.append(Camera(c.image, c.width, c.height, c.K, np.linalg.inv(c2w)))
    save_cameras(root / "poses" / "cameras.json", CameraSet(tuple(frames), cams.light_intensity * s**2))

    args = scene.report_args(tmp_path / "report")
    args.update(optimize_dir=root / "optimize", cameras=root / "poses" / "cameras.json")
    m = make_report(**args, settings=fast_settings)
    for stem, expected in scene.expected_rmse.items():
        assert m["per_view_rmse"][stem] == pytest.approx(expected, abs=2e-3), stem
    g = m["metrics"]
    assert g["alignment"]["similarity"]["scale"] == pytest.approx(1 / s, rel=1e-9)
    assert g["chamfer"] < 1e-6
    assert g["image_rmse"] < 2e-3
    assert max(g["texture_rmse"][k] for k in ("diffuse", "specular", "roughness")) < 1e-4


def test_without_gt_and_benchmarks(tmp_path, scene, fast_settings):
    args = scene.report_args(tmp_path / "report", gt=False, benchmarks=False)
    settings = ReportSettings(**{**fast_settings.__dict__, "max_views": 2})
    m = make_report(**args, settings=settings)
    assert m["metrics"] == {}
    assert m["timings"]["stages"] == {}
    assert len(m["per_view_rmse"]) == 2
    page = (tmp_path / "report" / "index.html").read_text()
    assert "Against the ground truth" not in page


def test_views_the_optimizer_held_out_are_shown_and_scored_apart(tmp_path, scene, fast_settings):
    """The optimizer's held-out views (summary.json "holdout") are always re-rendered, whatever
    max_views picks, labelled on the page and scored apart from the fitted ones (known values:
    the last view's input is offset by 0.1 in sRGB, the others equal the re-render)."""
    args = _copy_inputs(scene, tmp_path)
    summary_path = tmp_path / "cap" / "optimize" / "summary.json"
    stems = [c.stem for c in scene.cams.frames]
    offset = next(s for s in stems if scene.expected_rmse[s] > 0)
    held = [s for s in stems if s != stems[0]][-1:] + [offset]
    summary = json.loads(summary_path.read_text())
    summary["holdout"] = {"held_out": sorted(set(held)) + ["not-a-view"], "train_views": len(stems) - len(set(held))}
    summary_path.write_text(json.dumps(summary))
    m = make_report(**args, settings=ReportSettings(**{**fast_settings.__dict__, "max_views": 1}))
    assert m["heldout_views"] == sorted(set(held))  # a stem the cameras lack is left out
    assert set(held) <= set(m["per_view_rmse"])
    want = np.mean([scene.expected_rmse[s] for s in set(held)])
    assert m["per_view_rmse_heldout_mean"] == pytest.approx(want, abs=2e-6)
    fitted = [v for s, v in m["per_view_rmse"].items() if s not in held]
    assert m["per_view_rmse_fitted_mean"] == (pytest.approx(np.mean(fitted), abs=2e-6) if fitted else None)
    page = (tmp_path / "out" / "report" / "index.html").read_text()
    assert page.count("held out: never fitted") == len(set(held))
    assert "held-out view RMSE" in page


# ---- Errors: nothing partial left behind, and the message names the file ----
def _copy_inputs(scene, tmp_path) -> dict:
    root = tmp_path / "cap"
    shutil.copytree(scene.results, root, ignore=shutil.ignore_patterns("report"))
    args = scene.report_args(tmp_path / "out" / "report", gt=False)
    for key in ("optimize_dir", "glb", "cameras"):
        args[key] = root / Path(args[key]).relative_to(scene.results)
    args["image_dirs"] = [root / Path(p).relative_to(scene.results) for p in args["image_dirs"]]
    args["mask_dirs"] = [root / Path(p).relative_to(scene.results) for p in args["mask_dirs"]]
    return args


@pytest.mark.parametrize("missing", ["optimize/mesh.obj", "optimize/roughness.exr", "optimize/log.jsonl",
                                     "export/asset.glb", "poses/cameras.json", "masks/v001.png",
                                     "linear/v002.exr"])
def test_missing_input_names_the_file(tmp_path, scene, fast_settings, missing):
    args = _copy_inputs(scene, tmp_path)
    (tmp_path / "cap" / missing).unlink()
    with pytest.raises(ReportError, match=str(tmp_path / "cap" / missing).replace(".", r"\.")):
        make_report(**args, settings=fast_settings)
    out = tmp_path / "out"
    assert not out.exists() or not any(out.iterdir()), "a failed report left files behind"


def test_failed_rerun_keeps_the_previous_report(tmp_path, scene, fast_settings):
    args = _copy_inputs(scene, tmp_path)
    make_report(**args, settings=ReportSettings(**{**fast_settings.__dict__, "max_views": 1}))
    before = (tmp_path / "out" / "report" / "metrics.json").read_text()
    (tmp_path / "cap" / "optimize" / "diffuse.exr").write_bytes(b"not an exr")
    with pytest.raises(ReportError, match="diffuse.exr"):
        make_report(**args, settings=fast_settings)
    assert (tmp_path / "out" / "report" / "metrics.json").read_text() == before
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["report"]


def test_mesh_without_uvs_and_nan_map_are_rejected(tmp_path, scene, fast_settings):
    from recon.io.images import write_exr
    from recon.io.mesh import Mesh, read_obj, write_obj

    args = _copy_inputs(scene, tmp_path)
    opt = tmp_path / "cap" / "optimize"
    m = read_obj(opt / "mesh.obj")
    write_obj(opt / "mesh.obj", Mesh(m.v_pos, m.t_pos_idx))
    with pytest.raises(ReportError, match=r"mesh\.obj: the mesh has no UVs"):
        make_report(**args, settings=fast_settings)
    write_obj(opt / "mesh.obj", m)
    bad = report_scene.maps()["roughness"].copy()
    bad[3, 4] = math.nan
    write_exr(opt / "roughness.exr", bad)
    with pytest.raises(ReportError, match=r"roughness\.exr: .*NaN"):
        make_report(**args, settings=fast_settings)


def test_missing_viewer_bundle_is_skipped_with_how_to_install(tmp_path, scene, fast_settings):
    """The 3D view is optional: without model-viewer's bundle the report finishes and says how to install it."""
    settings = ReportSettings(**{**fast_settings.__dict__, "viewer_js": str(tmp_path / "nope.js"), "max_views": 1})
    m = make_report(**scene.report_args(tmp_path / "report", gt=False), settings=settings)
    assert re.search(r"nope\.js.*npm ci --prefix tools/report-viewer", m["skipped"]["3d_view"])
    page = (tmp_path / "report" / "index.html").read_text()
    assert "3D view skipped" in page and "npm ci --prefix tools/report-viewer" in page
    assert not (tmp_path / "report" / "asset.glb.js").exists()
    assert len(m["per_view_rmse"]) == 1


def test_image_with_another_aspect_ratio_is_rejected(tmp_path, scene, fast_settings):
    from recon.io.images import write_exr

    args = _copy_inputs(scene, tmp_path)
    write_exr(tmp_path / "cap" / "linear" / "v001.exr", np.zeros((20, 60, 3), np.float32))
    with pytest.raises(ReportError, match=r"v001\.exr: 60x20 pixels does not have the aspect ratio"):
        make_report(**args, settings=fast_settings)


@pytest.mark.parametrize("bad", [{"spp": 0}, {"max_size": 0}, {"error_vmax": 0.0}, {"max_views": -1},
                                 {"texture_max_distance": float("nan")}])
def test_settings_reject_bad_values(bad):
    with pytest.raises(ValueError):
        ReportSettings(**bad)


def test_unknown_asset_scale_is_a_warning_on_the_page(report):
    """The export stage had no known length (no mat, no export.object_height_m): the report
    records how the asset was placed and scaled and says on the page that the scale is unknown."""
    out, _, m = report
    assert m["asset"]["scale_warning"] is True and m["asset"]["meters_per_unit"] == 1.0
    assert m["asset"]["scale_source"].startswith("unknown")
    assert "Asset scale: unknown" in (out / "index.html").read_text()
