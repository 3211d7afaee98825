"""Ground-truth helpers: texture lookups, closest-point UVs, texture errors, held-out views."""

from __future__ import annotations

import re

import numpy as np
import pytest
import report_scene

from recon.io.cameras import CameraSet
from recon.io.mesh import Mesh
from recon.metrics import Similarity
from recon.report.gt import closest_uv, image_views, read_ground_truth, sample_map, sample_surface_uv, texture_errors
from recon.report.inputs import Model


def test_sample_map_texel_centers_and_bilinear():
    t = np.arange(12, dtype=np.float32).reshape(3, 4, 1)
    H, W = t.shape[:2]
    i, j = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    uv = np.stack([(j.ravel() + 0.5) / W, 1 - (i.ravel() + 0.5) / H], 1)
    np.testing.assert_allclose(sample_map(t, uv)[:, 0], t.ravel())
    # halfway between texels (0,0) and (0,1); then clamped outside the map
    np.testing.assert_allclose(sample_map(t, np.array([[1.0 / W, 1 - 0.5 / H]])), [[0.5]])
    np.testing.assert_allclose(sample_map(t, np.array([[-3.0, 5.0]])), [[0.0]])


def test_surface_samples_carry_their_uvs_through_closest_points():
    mesh = report_scene.uv_sphere()
    rng = np.random.default_rng(1)
    p, uv = sample_surface_uv(mesh, 2000, rng)
    assert np.abs(np.linalg.norm(p, axis=1) - 0.5).max() < 0.02  # on the (tessellated) sphere
    dist, uv2 = closest_uv(mesh, p)
    assert dist.max() < 1e-6
    # identical except the few samples that sit within float precision of the u = 0/1 seam
    same = np.all(np.abs(uv - uv2) < 1e-5, axis=1)
    assert same.mean() > 0.995


def test_texture_errors_known_offset():
    mesh = report_scene.uv_sphere()
    tex = report_scene.maps()
    gt = Model(mesh, tex["diffuse"], tex["specular"], tex["roughness"])
    shifted = Model(mesh, np.clip(tex["diffuse"] - 0.04, 0, 1), np.repeat(tex["specular"], 3, axis=2),
                    tex["roughness"] + 0.1)
    e = texture_errors(shifted, gt, Similarity.identity(), 1.0, 5000, 0.01)
    assert e["fraction"] == 1.0
    assert e["diffuse"] == pytest.approx(0.04, abs=2e-3)  # a_d >= 0.03 nearly everywhere
    assert e["specular"] == pytest.approx(0.0, abs=1e-5)  # 1 channel against RGB of the same values
    assert e["roughness"] == pytest.approx(0.1, abs=1e-4)


def test_texture_errors_far_geometry_is_left_out():
    mesh = report_scene.uv_sphere()
    tex = report_scene.maps()
    gt = Model(mesh, tex["diffuse"], tex["specular"], tex["roughness"])
    far = Similarity(1.0, np.eye(3), np.array([5.0, 0.0, 0.0]))
    e = texture_errors(gt, gt, far, 1.0, 1000, 0.01)
    assert e["fraction"] == 0.0 and e["diffuse"] is None


def test_image_views_prefers_held_out():
    est = report_scene.cameras()
    true = CameraSet(est.frames + report_scene.cameras(("h0", "h1"), start=1.0).frames)
    cams, held = image_views(est, true, 0)
    assert held and [c.stem for c in cams] == ["h0", "h1"]
    cams, held = image_views(est, est, 2)
    assert not held and [c.stem for c in cams] == ["v000", "v002"]


def test_read_ground_truth_missing_map_names_it(scene, tmp_path):
    import shutil

    shutil.copytree(scene.capture_dir / "gt", tmp_path / "gt")
    g = read_ground_truth(tmp_path / "gt")
    assert isinstance(g.model.mesh, Mesh) and len(g.cameras) == 4 and g.skipped == {}
    (tmp_path / "gt" / "specular.exr").unlink()
    g = read_ground_truth(tmp_path / "gt")
    assert g.model is None and isinstance(g.mesh, Mesh) and len(g.cameras) == 4
    assert re.search(r"gt/specular\.exr: not found", g.skipped["texture_rmse"])
    assert set(g.skipped) == {"texture_rmse", "image_rmse"}
