"""Material-model selection (recon/optimize/material.py): the G-buffer shading against the
reference BRDF and the renderer, the paired held-out test, and the choice on synthetic objects
whose true model is known (purely diffuse; glossy with spatially varying specular and roughness)."""

import dataclasses

import numpy as np
import pytest
import torch

from recon.brdf import radiance_collocated
from recon.io.cameras import load_cameras
from recon.io.images import read_exr
from recon.io.mesh import read_obj
from recon.optimize.gbuffer import GBuffer, shade
from recon.optimize.heldout import compare
from recon.optimize.material import DIFFUSE_ONLY, MaterialModel, SelectionSettings
from recon.optimize.material_select import select_on_known_mesh, selection_steps
from recon.optimize.remesh import rasterize_atlas
from recon.optimize.settings import OptimizeSettings
from recon.optimize.views import Views
from recon.synth.capture import SynthSettings, make_capture

R_MIN = 0.02


def _gbuffer(mu, dist, uv):
    n = len(mu)
    return GBuffer(torch.arange(n), torch.tensor(uv, dtype=torch.float32), torch.tensor(mu, dtype=torch.float32),
                   torch.tensor(1 / np.square(dist), dtype=torch.float32), 1, (1, 1, n))


@pytest.mark.parametrize("r", [R_MIN, 0.05, 0.3, 1.0])
@pytest.mark.parametrize("a_s", [0.0, 0.04, 1.0])
def test_shading_matches_reference_brdf(r, a_s):
    rng = np.random.default_rng(1)
    mu = np.concatenate([[0.0, 1e-7, 1e-3, 1.0], rng.uniform(0, 1, 60)])
    dist = rng.uniform(0.01, 100, mu.size)
    uv = rng.uniform(0, 1, (mu.size, 2))
    a_d = np.array([0.0, 0.5, 1.0])
    gb = _gbuffer(mu, dist, uv)
    img = shade(gb, torch.tensor(a_d, dtype=torch.float32).reshape(1, 1, 3),
                torch.full((1, 1, 1), a_s), torch.full((1, 1, 1), r), 3.0, R_MIN).reshape(-1, 3).numpy()
    ref = radiance_collocated(mu, dist, a_d[None], np.full((mu.size, 1), a_s), np.full(mu.size, r), 3.0, R_MIN)
    assert np.all(np.isfinite(img))
    np.testing.assert_allclose(img, ref, rtol=2e-4, atol=1e-7 * ref.max())


def test_shading_gradients_finite_at_extremes():
    mu = np.array([0.0, 1e-8, 0.5, 1.0])
    gb = _gbuffer(mu, np.ones(4), np.full((4, 2), 0.5))
    for r0 in (R_MIN, 1.0):
        for v0 in (0.0, 1.0):
            d = torch.full((4, 4, 3), v0, requires_grad=True)
            s = torch.full((4, 4, 1), v0, requires_grad=True)
            r = torch.full((4, 4, 1), r0, requires_grad=True)
            shade(gb, d, s, r, 1.0, R_MIN).sum().backward()
            for t in (d, s, r):
                assert torch.all(torch.isfinite(t.grad))


def test_texel_convention_and_uniform_maps():
    """Texel (i, j) of a T x T map sits at u = (j + .5)/T, v = 1 - (i + .5)/T (DESIGN section 2)."""
    T = 8
    tex = torch.zeros((T, T, 3))
    tex[2, 5] = 1.0
    gb = _gbuffer(np.ones(2), np.ones(2), [[(5 + 0.5) / T, 1 - (2 + 0.5) / T], [(4 + 0.5) / T, 1 - (2 + 0.5) / T]])
    img = shade(gb, tex, None, torch.ones((1, 1, 1)), np.pi, R_MIN).reshape(-1, 3)
    np.testing.assert_allclose(img.numpy(), [[1, 1, 1], [0, 0, 0]], atol=1e-6)


def test_compare_accepts_a_clear_gain_and_rejects_noise():
    rng = np.random.default_rng(0)
    s = SelectionSettings()
    base = rng.uniform(0.05, 0.1, 400)
    noise = rng.normal(0, 0.002, 400)
    assert not compare(base + noise, base, s)["accepted"]  # no real change
    better = base * 0.9 + noise
    c = compare(better, base, s)
    assert c["accepted"] and c["gain"] > 0 and c["relative_gain"] == pytest.approx(0.1, abs=0.02)
    # a gain only in the few highlight tiles (3 %) counts in full: no trimming by default
    highlight = base + noise
    highlight[:12] -= 0.05
    c = compare(highlight, base, s)
    assert c["accepted"] and c["gain"] == pytest.approx(0.05 * 12 / 400, rel=0.2)
    assert not compare(highlight, base, dataclasses.replace(s, trim=0.05))["accepted"]  # trimmed away
    # the same gain everywhere but a few tiles where the richer fit extrapolates badly: worse overall
    bad = better.copy()
    bad[:8] += 0.5
    assert not compare(bad, base, s)["accepted"]
    assert not compare(base * 0.999, base, s)["accepted"]  # consistent but below min_gain
    assert not compare(np.full(2, 0.0), np.full(2, 1.0), s)["accepted"]  # too few tiles to tell


def test_selection_steps_ladder():
    steps = dict(selection_steps(DIFFUSE_ONLY))
    assert set(steps) == {"uniform specular", "spatially varying specular"}
    full = MaterialModel("textured", "mono", "uniform")
    assert set(dict(selection_steps(full))) == {"RGB specular", "spatially varying roughness"}
    with pytest.raises(ValueError, match="specular"):
        MaterialModel("shiny")


def test_settings_validation():
    with pytest.raises(ValueError, match="holdout_every"):
        OptimizeSettings(select={"holdout_every": 1})
    assert OptimizeSettings(select={"select_material": True}).holds_out
    assert not OptimizeSettings().holds_out


# ---------------------------------------------------------------------- selection on known objects
SMALL = dict(object="blob", n_views=24, width=128, height=96, format="exr", spp=16, seed=0, mesh_level=5,
             texture_size=256, write_masks=True, write_cameras=True, write_gt_linear=False)


def _problem(cap, size=128):
    mesh = read_obj(cap / "gt" / "mesh.obj")
    cams = load_cameras(cap / "gt" / "cameras.json")  # the true cameras and flash (the true mesh's problem)
    views = Views([cap / c.image for c in cams.frames], [cap / "masks" / f"{c.stem}.png" for c in cams.frames],
                  None, cams, size)
    held = [i for i in range(len(views)) if i % 4 == 2]
    train = [i for i in range(len(views)) if i % 4 != 2]
    return mesh, views, views.subset(train).at(size), views.subset(held).at(size)


def _select(cap, size=128, spp=4, full_iterations=300):
    """Fit the full model on the true mesh (as the main loop would), then select."""
    mesh, views, train, held = _problem(cap, size)
    light, scale = views.light_intensity, views.median_foreground
    fit, evidence = select_on_known_mesh(mesh, train, held, light, scale, SelectionSettings(iterations=150), spp=spp,
                                         full_iterations=full_iterations)
    for m in fit.maps.values():
        assert np.all(np.isfinite(m))
    return fit, evidence


def test_diffuse_object_selects_diffuse_only(tmp_path):
    """24 views of 96 x 72 (the full model's start fit 150 steps): every richer model loses on
    the held-out views (measured: uniform specular -2.3 SE, spatially varying -3.5 SE; at
    128 x 96 with a 300-step start -4.8 and -4.1 SE, for 2.1 times the CPU seconds)."""
    cap = make_capture(tmp_path / "diffuse", SynthSettings(**{**SMALL, "width": 96, "height": 72}, specular=0.0))
    fit, ev = _select(cap, size=96, full_iterations=150)
    assert ev["chosen"] == {"specular": "none", "specular_color": "mono", "roughness": "uniform"}, ev["candidates"]
    assert np.all(fit.maps["specular"] == 0)
    # every richer candidate was tried and none helped on held-out views
    assert [r["step"] for r in ev["candidates"]] == ["diffuse only", "uniform specular", "spatially varying specular"]
    assert all(not r["accepted"] for r in ev["candidates"][1:])


@pytest.fixture(scope="module")
def glossy_selection(tmp_path_factory):
    """The glossy spatially varying blob (specular bands, three roughness sectors 0.18/0.4/0.75),
    40 views 192x144, every 4th held out. ``bench/selection.py --seed 0`` / ``--seed 1``: textured
    mono specular and textured roughness chosen, roughness gain 6.1 % / 5.2 % of the held-out error
    at 3.0 / 4.6 SE. On 24 views of 128x96 (``--views 24 --width 128 --height 96 --spp 4``) the
    roughness model does not generalize and is rejected."""
    cap = make_capture(tmp_path_factory.mktemp("glossy") / "cap",
                       SynthSettings(**{**SMALL, "n_views": 40, "width": 192, "height": 144}))
    fit, ev = _select(cap, size=192, spp=2)
    return cap, fit, ev


def _corr_with_truth(cap, fit, name):
    """Correlation of a recovered map with the true one over the covered texels (same atlas:
    the true mesh is used)."""
    gt = read_exr(cap / "gt" / f"{name}.exr").reshape(256, 256)
    covered = rasterize_atlas(read_obj(cap / "gt" / "mesh.obj"), 256)[0] >= 0
    rec = fit.maps[name][..., 0]
    return float(np.corrcoef(rec[covered], gt[covered])[0, 1])


# The glossy selection fits ~10 candidate models on 40 views (about 4 minutes of torch compute on
# 2 cores, not kernel compilation): slow-marked, so the unit suite stays under 10 minutes, and
# run by CI as its own step (.ci/run).
@pytest.mark.slow
def test_glossy_spatially_varying_object_selects_textured_specular(glossy_selection):
    cap, fit, ev = glossy_selection
    assert ev["chosen"]["specular"] == "textured", ev["candidates"]
    # the true specular albedo is grey: RGB must not pay off
    assert ev["chosen"]["specular_color"] == "mono", ev["candidates"]
    for r in ev["candidates"][1:]:  # every accepted step beat its control
        if r["accepted"]:
            assert r["heldout_error"] < r["control_heldout_error"]
    # the recovered specular albedo follows the true bands over the surface
    corr = _corr_with_truth(cap, fit, "specular")
    assert corr > 0.3, corr


@pytest.mark.slow
def test_glossy_spatially_varying_object_selects_textured_roughness(glossy_selection):
    cap, fit, ev = glossy_selection
    assert ev["chosen"]["roughness"] == "textured", ev["candidates"]
    corr = _corr_with_truth(cap, fit, "roughness")
    print(f"\nroughness correlation with the truth {corr:.2f}; specular {_corr_with_truth(cap, fit, 'specular'):.2f}")  # noqa: T201
    assert corr > 0.3, corr
