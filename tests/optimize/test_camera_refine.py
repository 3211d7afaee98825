"""Camera refinement (recon/optimize/camera_refine.py): the parameterization, the similarity
gauge, the priors, and the recovery of perturbed cameras by the renderer's camera gradients."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from recon.io.cameras import Camera
from recon.optimize.camera_refine import CameraPrior, CameraRefinement, rotation_exp, rotation_log
from recon.render import CollocatedRenderer, RenderSettings, camera_table

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "render"))
from render_scenes import camera, textures, two_spheres_scene  # noqa: E402


def _ring(n=6, r=4.0, z=0.4):
    return [camera((r * np.sin(a), -r * np.cos(a), z + 0.2 * np.sin(3 * a)), width=48, height=40)
            for a in np.linspace(-0.5, 0.5, n)]


def test_zero_corrections_reproduce_the_cameras():
    cams = _ring()
    ref = CameraRefinement(cams)
    np.testing.assert_allclose(ref.table(range(len(cams)), cams).detach().numpy(), camera_table(cams), rtol=1e-6, atol=1e-6)
    for a, b in zip(ref.cameras(range(len(cams)), cams), cams, strict=True):
        np.testing.assert_allclose(a.world_to_camera, b.world_to_camera, atol=1e-12)
        np.testing.assert_allclose(a.K, b.K, atol=1e-12)
    assert ref.prior_loss().item() == 0.0
    c = ref.corrections()
    assert c["max_rotation_deg"] == 0.0 and c["max_center_shift"] == 0.0 and c["focal_scale"] == 1.0


def test_rotation_exp_log_round_trip_and_finite_gradients():
    rng = np.random.default_rng(0)
    for w in [np.zeros(3), np.full(3, 1e-9), rng.normal(size=3) * 0.3, np.array([0.0, 0.0, 3.0])]:
        R = rotation_exp(torch.tensor(w)).numpy()
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(rotation_log(R), w, atol=1e-9)
    w = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    rotation_exp(w).sum().backward()
    assert torch.isfinite(w.grad).all()


def test_a_whole_scene_similarity_is_gauge_and_is_removed():
    """Corrections that move every camera by one similarity of the world change no image:
    fix_gauge removes them; a single view's own correction survives almost whole."""
    cams = _ring(8)
    ref = CameraRefinement(cams)
    s, Q, u = 1.002, rotation_exp(torch.tensor([0.001, -0.002, 0.0015])).numpy(), np.array([0.003, -0.002, 0.004])
    with torch.no_grad():
        for i, c in enumerate(cams):
            R, t = c.world_to_camera[:3, :3], c.world_to_camera[:3, 3]
            R1, t1 = R @ Q.T, s * t - R @ Q.T @ u
            w = rotation_log(R1 @ R.T)
            ref.rotation[i] = torch.tensor(w)
            ref.translation[i] = torch.tensor(t1 - rotation_exp(torch.tensor(w)).numpy() @ t)
    before = torch.cat([ref.rotation, ref.translation], 1).norm().item()
    ref.fix_gauge()
    after = torch.cat([ref.rotation, ref.translation], 1).norm().item()
    assert after < 1e-3 * before, (before, after)
    with torch.no_grad():
        ref.rotation.zero_()
        ref.translation.zero_()
        ref.rotation[3] = torch.tensor([0.004, 0.0, -0.003])
    kept = ref.rotation[3].norm().item()
    ref.fix_gauge()
    assert ref.rotation[3].norm().item() > 0.6 * kept


def test_prior_validation():
    with pytest.raises(ValueError, match="sigma_rotation_deg"):
        CameraPrior(sigma_rotation_deg=0.0)
    with pytest.raises(ValueError, match="at least 3 views"):
        CameraRefinement(_ring(2))


def test_perturbed_cameras_are_pulled_back_by_the_images():
    """Images of the two-sphere scene from true cameras; refinement starts from cameras rotated
    by 0.6 degrees, shifted by 1.5 % of the scene and with a 2 % focal error, with the scene
    fixed: the renderer's camera gradients bring the views back (mean reprojection error of the
    scene's points and focal error down > 3x; a small rotation and a sideways shift differ only
    by parallax, so the two are not separately asserted)."""
    (v, f, t, ft), _, _ = two_spheres_scene()
    maps = [torch.tensor(m) for m in textures(np.random.default_rng(3))]
    true = _ring(6)
    r = CollocatedRenderer(f, t, ft, RenderSettings(spp=4, boundary="edge"))
    v_t = torch.tensor(v, dtype=torch.float32)
    targets = r.render_torch(v_t, *maps, true, 10.0, 0)
    rng = np.random.default_rng(1)
    start = []
    for c in true:
        w = rng.normal(size=3)
        w *= np.deg2rad(0.6) / np.linalg.norm(w)
        d = rng.normal(size=3)
        d *= 0.015 * 4.0 / np.linalg.norm(d)
        E = rotation_exp(torch.tensor(w)).numpy()
        T = c.world_to_camera.copy()
        T[:3, :3], T[:3, 3] = E @ T[:3, :3], E @ T[:3, 3] + d
        K = c.K.copy()
        K[0, 0] *= 1.02
        K[1, 1] *= 1.02
        start.append(Camera(c.image, c.width, c.height, K, T))

    def errors(cams):
        """Mean reprojection error of the scene's vertices (pixels) and mean focal error."""
        px = [np.linalg.norm(a.project(v)[0] - b.project(v)[0], axis=1).mean() for a, b in zip(cams, true, strict=True)]
        return float(np.mean(px)), float(np.mean([abs(a.K[0, 0] / b.K[0, 0] - 1) for a, b in zip(cams, true, strict=True)]))

    ref = CameraRefinement(start, CameraPrior(sigma_rotation_deg=2.0, sigma_translation=0.05, sigma_focal=0.1,
                                              lr_rotation_deg=0.05, lr_translation=0.002, lr_focal=0.002))
    opt = torch.optim.Adam(ref.param_groups())
    idx = list(range(len(start)))
    for it in range(60):
        opt.zero_grad()
        img = r.render_torch(v_t, *maps, ref.cameras(idx, start), 10.0, it, camera_table=ref.table(idx, start))
        loss = ((img - targets) ** 2).mean() + 1e-6 * ref.prior_loss()
        loss.backward()
        opt.step()
    px0, f0 = errors(start)
    px1, f1 = errors(ref.cameras(idx, start))
    assert px1 < px0 / 3 and f1 < f0 / 3, (px0, px1, f0, f1)
    c = ref.corrections()
    assert c["mean_rotation_deg"] > 0 and np.isfinite(c["max_center_shift"])


def test_heldout_alignment_renders_the_loop_imaging(drjit_single_thread):
    """Held-out photos taken at exposures 1.6x and 0.6x (a phone's auto-exposure), aligned to
    the true model from the true cameras: under the loop's exposure term (the views' own gains
    fitted with their poses, recon.optimize.cameras.align_views) the poses stay where they are and
    the held-out errors are those of a right model; under the ideal formation the exposure is
    explained by the pose (with the flash at the lens, brightness and distance trade): the poses
    move and the errors are several times larger. drjit on one thread: the loop with nothing
    chosen must redo the ideal run's 40 pose steps (compared to 1e-4 below), and with threads'
    float atomics in any order each step's gradients differ in the last bits, which 40 steps
    can amplify past any fixed tolerance."""
    from recon.io.mesh import Mesh
    from recon.optimize.formation import ImagingModel, ImagingParams
    from recon.optimize.loop_imaging import LoopImaging
    from recon.optimize.cameras import align_views
    from recon.optimize.settings import OptimizeSettings
    from recon.optimize.views import ViewSet

    (v, f, t, ft), _, _ = two_spheres_scene()
    maps = {k: torch.tensor(m) for k, m in zip(("diffuse", "specular", "roughness"),
                                               textures(np.random.default_rng(3)), strict=True)}
    true = _ring(3)
    settings = OptimizeSettings(render={"spp": 4, "boundary": "edge"}, cameras={"align_iterations": 40},
                                select={"select_spp": 4})
    r = CollocatedRenderer(f, t, ft, RenderSettings(spp=16, boundary="edge"))
    gains = torch.tensor([1.6, 1.0, 0.6])
    clean = r.render_torch(torch.tensor(v, dtype=torch.float32), maps["diffuse"], maps["specular"],
                           maps["roughness"], true, 10.0, 7)
    photos = (clean * gains[:, None, None, None]).detach()
    vs = ViewSet(photos, torch.ones_like(photos[..., :1]), np.ones(photos.shape[:3], np.float32), tuple(true))
    tone_scale = float(clean[clean > 0].median())
    loop = LoopImaging(lr=0.01, exposure_prior=0.25)
    loop.adopt(ImagingParams(ImagingModel(("exposure",)), n_views=6, length=2.0, tone_scale=tone_scale), {})
    mesh = Mesh(v, f, t, ft)
    args = (settings, 10.0, tone_scale, {"camera": 0.001, "imaging": 0.001})
    under = align_views(mesh, maps, vs, list(true), *args, loop, 1.0)
    ideal = align_views(mesh, maps, vs, list(true), *args, None, 1.0)

    def reprojection(cams):
        return float(np.mean([np.linalg.norm(a.project(v)[0] - b.project(v)[0], axis=1).mean()
                              for a, b in zip(cams, true, strict=True)]))

    e_under, e_ideal = reprojection(under["viewset"].cameras), reprojection(ideal["viewset"].cameras)
    t_under, t_ideal = np.nanmean(under["tiles"]), np.nanmean(ideal["tiles"])
    assert np.isfinite(e_under) and np.isfinite(t_under)
    assert e_under < 0.1 and e_ideal > 3 * e_under, (e_under, e_ideal)
    assert t_ideal > 3 * t_under, (t_under, t_ideal)
    # the loop on but nothing chosen: the ideal formation, its errors on the same tiles, in the
    # same order, as a run that chose terms and as one without the loop (paired runs compare
    # tile for tile)
    nothing = align_views(mesh, maps, vs, list(true), *args, LoopImaging(lr=0.01, exposure_prior=0.25), 1.0)
    assert len(nothing["tiles"]) == len(under["tiles"]) == len(ideal["tiles"])
    np.testing.assert_allclose(nothing["tiles"], ideal["tiles"], rtol=1e-4, atol=1e-7)
    for a, b in zip(nothing["viewset"].cameras, ideal["viewset"].cameras, strict=True):
        np.testing.assert_allclose(a.world_to_camera, b.world_to_camera, atol=1e-6)
