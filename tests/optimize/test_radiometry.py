"""The flash's scale estimated from the photos, and the collapse checks (issue 31).

Reference: synthetic captures lit by a known I_e with known maps (tests/optimize/synthetic.py):
the estimate's gauge is checked against the true maps, its invariances exactly, its failures by
their messages; a capture built to collapse stops the optimize stage and export refuses it.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from recon.brdf import radiance_collocated
from recon.io.cameras import Camera, CameraSet, load_cameras, save_cameras
from recon.io.images import read_exr
from recon.io.mesh import Mesh, read_mesh
from recon.optimize import OptimizeError, OptimizeSettings, StageSettings, optimize_capture
from recon.optimize.radiometry import (ESTIMATE_SIZE, WHITE_PERCENTILE, WHITE_VALUE, CollapseError, LightScale,
                                       LightScaleError, check_not_collapsed, clipped_fraction,
                                       estimate_light_scale, mask_coverage, unit_render)
from recon.optimize.views import Views
from recon.sections import replace

TINY = OptimizeSettings(render={"resolution": 32, "spp": 1}, schedule={"views_per_iteration": 2, "checkpoint_every": 2},
                        loss={"w_edge": 0.01}, stages=(StageSettings(0.12, 32, 4), StageSettings(0.09, 64, 4)))


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    import synthetic

    root = tmp_path_factory.mktemp("radiometry")
    info = synthetic.make_capture(root, n_views=8, size=64, spp=16, texture_size=64)
    return root, info


def _views(root: Path, cams: CameraSet | None = None) -> tuple[Views, CameraSet]:
    cams = cams if cams is not None else load_cameras(root / "cameras.json")
    images = sorted((root / "images").glob("*.exr"))
    masks = [root / "masks" / f"{p.stem}.png" for p in images]
    return Views(images, masks, None, cams, 64), cams


def _estimate(mesh: Mesh, views: Views, scale_images: float = 1.0) -> LightScale:
    vs = views.at(ESTIMATE_SIZE)
    return estimate_light_scale(mesh, vs.images.numpy() * scale_images, vs.masks, vs.weights[..., 0].numpy() == 0,
                                vs.cameras)


def test_unit_render_is_the_collocated_diffuse_model():
    """A plane facing the camera at distance d: mu = 1 on the axis, radiance 1 / (pi d^2)."""
    from recon.io.cameras import intrinsics, look_at

    d = 3.0
    v = np.array([[-5, -5, 0], [5, -5, 0], [5, 5, 0], [-5, 5, 0]], float)
    mesh = Mesh(v, np.array([[0, 1, 2], [0, 2, 3]]))
    cam = Camera("a.exr", 9, 9, intrinsics(9, 9, 20.0), look_at([0, 0, d], [0, 0, 0], [0, 1, 0]))
    rad, hit, mu = unit_render(mesh, [cam], spp=4)
    assert hit.min() == 1.0 and np.all(np.isfinite(rad))
    assert rad[0, 4, 4] == pytest.approx(1 / (np.pi * d * d), rel=2e-3)
    # the reference model's diffuse lobe (recon.brdf, which lists this copy)
    ref = radiance_collocated(1.0, d, np.ones(1), np.zeros(1), 0.5)[0]
    assert rad[0, 4, 4] == pytest.approx(ref, rel=2e-3)
    assert mu[0, 4, 4] == pytest.approx(1.0, abs=1e-3)


def test_estimate_against_the_true_maps(capture):
    """On the true mesh, the estimate is the stated convention applied to the true maps: I_e is
    the true I_e (1) times the true diffuse albedo's WHITE_PERCENTILE-th percentile (largest
    channel) over WHITE_VALUE, and the initial albedo the true median in that gauge."""
    root, info = capture
    views, cams = _views(root)
    assert not cams.light_known  # the capture does not state the flash (synthetic.make_capture)
    gt = read_mesh(root / "gt.obj")
    est = _estimate(gt, views)
    true_d = info["gt_maps"]["diffuse"]
    from recon.optimize.remesh import rasterize_atlas

    face, _, _ = rasterize_atlas(gt, true_d.shape[0])
    texels = true_d[face >= 0]
    white_true = np.percentile(texels.max(axis=1), WHITE_PERCENTILE)
    # the photos see the texels by their projected area, not uniformly: 15 %
    assert est.intensity == pytest.approx(1.0 * white_true / WHITE_VALUE, rel=0.15)
    assert est.source == "estimated" and est.albedo == "relative" and est.pixels > 1000
    median_in_gauge = np.median(texels, axis=0) / est.intensity
    np.testing.assert_allclose(est.init_diffuse, median_in_gauge, rtol=0.2)


def test_estimate_is_a_gauge_exactly(capture):
    """Photos 10x brighter: I_e 10x, the albedo unchanged. Scene x s (mesh and cameras): the
    same photos need I_e x s^2 (inverse square law); at s = 1e-3 and 1e3 nothing is lost."""
    root, _ = capture
    views, cams = _views(root)
    gt = read_mesh(root / "gt.obj")
    base = _estimate(gt, views)
    bright = _estimate(gt, views, 10.0)
    assert bright.intensity == pytest.approx(10 * base.intensity, rel=1e-6)
    np.testing.assert_allclose(bright.init_diffuse, base.init_diffuse, rtol=1e-6)
    for s in (1e-3, 1e3):
        frames = []
        for c in views.cameras:
            w2c = c.world_to_camera.copy()
            w2c[:3, 3] *= s
            frames.append(Camera(c.image, c.width, c.height, c.K.copy(), w2c))
        scaled = views.subset(range(len(views)))
        scaled.cameras = frames
        est = _estimate(Mesh(gt.v_pos * s, gt.t_pos_idx, gt.v_tex, gt.t_tex_idx), scaled)
        assert np.isfinite(est.intensity)
        assert est.intensity == pytest.approx(base.intensity * s * s, rel=1e-3)


def test_estimate_refuses_what_cannot_work(capture):
    root, _ = capture
    views, _ = _views(root)
    gt = read_mesh(root / "gt.obj")
    vs = views.at(ESTIMATE_SIZE)
    clipped = vs.weights[..., 0].numpy() == 0
    with pytest.raises(LightScaleError, match="black in every photo"):
        estimate_light_scale(gt, np.zeros_like(vs.images.numpy()), vs.masks, clipped, vs.cameras)
    with pytest.raises(LightScaleError, match="masks"):  # a mesh nowhere near the views' masks
        far = Mesh(gt.v_pos + 100.0, gt.t_pos_idx, gt.v_tex, gt.t_tex_idx)
        estimate_light_scale(far, vs.images.numpy(), vs.masks, clipped, vs.cameras)
    # every pixel clipped: nothing to measure (clipped pixels never enter, DESIGN section 3)
    with pytest.raises(LightScaleError):
        estimate_light_scale(gt, vs.images.numpy(), vs.masks, np.ones_like(clipped), vs.cameras)
    # a few clipped pixels with absurd values change nothing
    imgs = vs.images.numpy().copy()
    hot = np.zeros_like(clipped)
    hot[:, ::7, ::5] = True
    imgs[hot] = 1e6
    a = estimate_light_scale(gt, imgs, vs.masks, clipped | hot, vs.cameras)
    b = estimate_light_scale(gt, vs.images.numpy(), vs.masks, clipped | hot, vs.cameras)
    assert a.intensity == b.intensity


def test_given_light_is_used_and_estimate_on_request(capture, tmp_path):
    """cameras.json with light.intensity: used as is (albedo absolute); light.scale: estimate
    ignores it; light.scale: given without one is an error naming the file and the fix."""
    from recon.optimize.loop import _light_scale

    root, _ = capture
    views, cams = _views(root)
    init = read_mesh(root / "init.obj")
    stated = dataclasses.replace(cams, light_intensity=1.0, light_known=True)
    ls = _light_scale(TINY, stated, views, init, "cameras.json")
    assert (ls.intensity, ls.source, ls.albedo) == (1.0, "given", "absolute")
    est = _light_scale(replace(TINY, scale="estimate"), stated, views, init, "cameras.json")
    assert est.source == "estimated" and est.intensity != 1.0
    with pytest.raises(OptimizeError, match=r"cameras.json: states no light.intensity.*light_intensity in capture.yaml"):
        _light_scale(replace(TINY, scale="given"), cams, views, init, "cameras.json")
    # the file round trip keeps "not stated"
    save_cameras(tmp_path / "c.json", cams)
    assert "intensity" not in json.loads((tmp_path / "c.json").read_text())["light"]
    assert not load_cameras(tmp_path / "c.json").light_known


def test_collapse_check_names_the_causes():
    cov = {"covered_mean": 0.05, "covered_min": 0.0, "outside_mean": 0.0, "iou_mean": 0.05}
    with pytest.raises(CollapseError, match=r"covers 5 % of the masks.*flash's intensity I_e = 0.01 given.*masks.*cameras"):
        check_not_collapsed("stage 1", cov, 0.5, 1.0, LightScale(0.01, "given"))
    with pytest.raises(CollapseError, match=r"area is 2.0 %"):
        check_not_collapsed("stage 1", {**cov, "covered_mean": 0.9}, 0.02, 1.0, None)
    check_not_collapsed("stage 1", {**cov, "covered_mean": 0.9}, 0.5, 1.0, None)


def test_clipped_fraction():
    d = np.full((4, 4, 3), 0.5, np.float32)
    d[0, 0, 1] = 1.0
    assert clipped_fraction(d) == pytest.approx(1 / 16)
    cov = np.zeros((4, 4), bool)
    cov[1:] = True
    assert clipped_fraction(d, cov) == 0.0


def test_a_capture_built_to_collapse_stops(capture, tmp_path):
    """A flash stated 1000x too weak: the photos are out of reach, the regularizers shrink the
    surface, and the stage stops with the collapse message instead of writing an asset; the same
    capture without the stated value (estimated) runs and covers the masks."""
    root, _ = capture
    cams = load_cameras(root / "cameras.json")
    save_cameras(tmp_path / "weak.json", dataclasses.replace(cams, light_intensity=1e-3, light_known=True))
    images = sorted((root / "images").glob("*.exr"))
    masks = [root / "masks" / f"{p.stem}.png" for p in images]
    s = replace(TINY, w_laplacian=TINY.loss.w_laplacian * 50, lr_geometry=0.02, stages=(StageSettings(0.12, 32, 40),))
    with pytest.raises(OptimizeError, match=r"collapsed.*I_e = 0.001 given"):
        optimize_capture(images, masks, None, tmp_path / "weak.json", root / "init.obj", tmp_path / "weak", s,
                         progress=False)
    assert not (tmp_path / "weak" / "mesh.obj").exists()
    out = optimize_capture(images, masks, None, root / "cameras.json", root / "init.obj", tmp_path / "ok", s,
                           progress=False)
    assert out["light"]["source"] == "estimated" and out["light"]["albedo"] == "relative"
    # the 50x Laplacian weight pulls the surface in a little even when the photos are in reach
    # (0.82 measured); the collapsed run was far below 0.5
    assert out["stages"][-1]["mask_coverage"]["covered_mean"] > 0.7
    mesh = read_mesh(tmp_path / "ok" / "mesh.obj")
    views, _ = _views(root)
    vs = views.at(64)
    assert mask_coverage(mesh, vs.cameras, vs.masks)["covered_mean"] > 0.7
    assert np.isfinite(read_exr(tmp_path / "ok" / "diffuse.exr")).all()

    # export: the asset covers the masks and is written; the same maps on the surface shrunk to a
    # twentieth are refused, naming the masks, and leave no export folder behind
    from recon.export import ExportError, ExportSettings, export_asset
    from recon.io.mesh import write_obj

    maps = [tmp_path / "ok" / f"{k}.exr" for k in ("diffuse", "specular", "roughness")]
    files = export_asset(tmp_path / "ok" / "mesh.obj", *maps, tmp_path / "export", ExportSettings(),
                         cameras_json=root / "cameras.json", masks_dir=root / "masks")
    assert files["glb"].is_file()
    c = mesh.v_pos.mean(axis=0)
    write_obj(tmp_path / "shrunk.obj", Mesh(c + 0.05 * (mesh.v_pos - c), mesh.t_pos_idx, mesh.v_tex, mesh.t_tex_idx))
    with pytest.raises(ExportError, match=r"shrunk.obj: the optimized surface covers only \d+ % of the masks in "
                                          r"\S*masks \(need 30 %\)"):
        export_asset(tmp_path / "shrunk.obj", *maps, tmp_path / "export2", ExportSettings(),
                     cameras_json=root / "cameras.json", masks_dir=root / "masks")
    assert not (tmp_path / "export2").exists()
