"""The report shows the initial mesh's genus and how well it matched the masks (issue 32),
read from init_mesh/init_mesh.json beside optimize/ when that file exists."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import numpy as np

from recon.report import ReportSettings, make_report


def _init_mesh_json(folder: Path) -> dict:
    """A real init_mesh run (a sphere seen by 12 views, one mask with a hole) into ``folder``."""
    sys.path.insert(0, str(Path(__file__).parents[1]))
    from _geometry_scene import icosphere, silhouette

    from recon.init_mesh import InitMeshSettings, run_init_mesh
    from recon.io.cameras import Camera, CameraSet, intrinsics, look_at, save_cameras
    from recon.io.images import write_mask
    from recon.io.mesh import Mesh

    m = icosphere(3)
    sphere = Mesh(m.v_pos * 0.5, m.t_pos_idx)
    cams = CameraSet(tuple(
        Camera(f"images/{k:02d}.png", 64, 64, intrinsics(64, 64, 40),
               look_at([3 * np.cos(t), 3 * np.sin(t), 1.2 * np.sin(2 * t + 0.3)], [0, 0, 0]))
        for k, t in enumerate(np.linspace(0, 2 * np.pi, 12, endpoint=False))))
    save_cameras(folder / "cameras.json", cams)
    for c in cams:
        mask = silhouette(sphere, c)
        if c.stem == "05":
            mask[28:36, 28:36] = False  # a hole the vote outvotes
        write_mask(folder / "masks" / f"{c.stem}.png", mask)
    return run_init_mesh(folder / "cameras.json", folder / "masks", folder / "init_mesh",
                         InitMeshSettings(resolution=32, target_faces=500))


def test_report_shows_the_initial_meshs_genus_and_mask_agreement(tmp_path, scene, fast_settings):
    root = tmp_path / "cap"
    shutil.copytree(scene.results, root, ignore=shutil.ignore_patterns("report"))
    args = scene.report_args(tmp_path / "out" / "report", gt=False, benchmarks=False)
    for key in ("optimize_dir", "glb", "cameras"):
        args[key] = root / Path(args[key]).relative_to(scene.results)
    settings = ReportSettings(**{**fast_settings.__dict__, "max_views": 1})
    assert "initial_mesh" not in make_report(**args, settings=settings)  # no init_mesh.json: nothing
    stats = _init_mesh_json(tmp_path / "run")
    shutil.copytree(tmp_path / "run" / "init_mesh", root / "init_mesh")
    m = make_report(**args, settings=settings)
    initial = m["initial_mesh"]
    assert initial["genus"] == stats["genus"] == 0 and initial["source"] == "visual_hull"
    assert initial["mask_iou_mean"] == stats["mask_iou"]["mean"] and initial["mask_iou_worst"][0][0] == "05"
    page = (tmp_path / "out" / "report" / "index.html").read_text()
    assert "Initial mesh (visual hull by vote): genus 0" in page and "lowest 05 " in page
    assert initial["grid_source"] == stats["grid"]["source"] and "frame's edge" not in page
    # a hull the masks left open and init_mesh closed at the SfM points: the report says that side is a guess
    import json

    saved = json.loads((root / "init_mesh" / "init_mesh.json").read_text())
    saved["grid"]["source"] = "closed at the SfM points on -z"
    (root / "init_mesh" / "init_mesh.json").write_text(json.dumps(saved))
    args["out_dir"] = tmp_path / "out2" / "report"
    assert make_report(**args, settings=settings)["initial_mesh"]["grid_source"] == "closed at the SfM points on -z"
    page = (tmp_path / "out2" / "report" / "index.html").read_text()
    assert "the initial mesh was closed at the SfM points on -z" in page and "is a guess" in page
    assert initial["unseen_base"] is None and "No photo saw the object from below" not in page
    # a base closed flat under what the views saw (recon.unseen): the report says the underside is a guess
    saved["unseen_base"] = {"cut": True, "depth_voxels": 9.2}
    (root / "init_mesh" / "init_mesh.json").write_text(json.dumps(saved))
    args["out_dir"] = tmp_path / "out3" / "report"
    assert make_report(**args, settings=settings)["initial_mesh"]["unseen_base"] == 9.2
    page = (tmp_path / "out3" / "report" / "index.html").read_text()
    assert "No photo saw the object from below" in page and "9 voxels of the visual hull cut away" in page
