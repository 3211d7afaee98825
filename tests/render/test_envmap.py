"""Relighting under an environment map (recon.render.envmap): the map, the renderer, the metric."""

import numpy as np
import pytest
from _float_sums import SRGB_RELATIVE_SLOPE, U32, reorder_bound
from render_scenes import uv_sphere

from recon.io.cameras import Camera, intrinsics, look_at
from recon.io.mesh import Mesh
from recon.render import envmap as em

W, H = 48, 36  # small images: every test here renders in well under a second


@pytest.fixture(scope="module")
def sphere():
    return Mesh(*uv_sphere(64, 32))


def _cam(eye=(0.0, -4.0, 0.0), name="v.exr"):
    return Camera(name, W, H, intrinsics(W, H, 40.0), look_at(np.asarray(eye, float), [0, 0, 0]))


def _cams():
    return [_cam((0.0, -4.0, 0.5), "a.exr"), _cam((3.0, 2.5, 1.5), "b.exr")]


def _center_disk(cam, fraction=0.6):
    """Pixels whose centers lie within ``fraction`` of the unit sphere's image radius."""
    uv, _ = cam.project(np.zeros((1, 3)))
    c = np.asarray(uv).reshape(-1)[:2]
    d = np.linalg.norm(cam.center)
    radius_px = cam.K[0, 0] * np.tan(np.arcsin(1.0 / d))
    jj, ii = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    return np.hypot(jj - c[0], ii - c[1]) < fraction * radius_px


GLOSSY = {"diffuse": [0.4, 0.3, 0.2], "specular": 0.3, "roughness": 0.25}


# ---- the map ----
def test_envmap_image_is_deterministic_finite_and_lit_from_above():
    a, b = em.envmap_image(), em.envmap_image()
    assert a.shape == (64, 128, 3) and a.dtype == np.float32
    np.testing.assert_array_equal(a, b)
    assert np.all(np.isfinite(a)) and a.min() > 0
    lum = a.mean(2)
    assert lum[:32].mean() > 2 * lum[32:].mean()  # sky over a dark ground
    # the brightest texel is the key softbox's center direction (azimuth 35, elevation 40)
    d = em.envmap_directions(128, 64)
    i, j = np.unravel_index(np.argmax(lum), lum.shape)
    key = np.array([np.cos(np.radians(40)) * np.sin(np.radians(35)),
                    np.cos(np.radians(40)) * np.cos(np.radians(35)), np.sin(np.radians(40))])
    assert np.degrees(np.arccos(np.clip(d[i, j] @ key, -1, 1))) < 12.0
    assert lum.max() > 10 * np.median(lum)  # highlights matter
    off = em.envmap_image(32, 16, key=0.0, fill=0.0)
    assert off.max() < 1.0


def test_envmap_directions_convention():
    d = em.envmap_directions(8, 4)
    assert d.shape == (4, 8, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(d[0, :, 2], 1.0)  # first row = zenith, last = nadir
    np.testing.assert_allclose(d[-1, :, 2], -1.0)
    # the middle row of 3 is the horizon; azimuth runs from +y toward +x
    np.testing.assert_allclose(em.envmap_directions(4, 3)[1],
                               np.sqrt(0.5) * np.array([[1, 1, 0], [1, -1, 0], [-1, -1, 0], [-1, 1, 0]]),
                               atol=1e-12)
    s = em.envmap_directions(8, 4, supersample=3)
    assert s.shape == (4, 8, 9, 3)


def test_emitter_matches_the_map_convention(mi):
    """Mitsuba's envmap emitter, looked up along envmap_directions, returns each texel."""
    import drjit as dr

    from recon.render import mitsuba_bsdf

    mitsuba_bsdf.register("llvm_ad_rgb")
    rng = np.random.default_rng(0)
    img = rng.uniform(0.1, 2.0, (16, 32, 3)).astype(np.float32)
    emitter = mi.load_dict(em.envmap_emitter_dict(img))
    d = em.envmap_directions(32, 16).reshape(-1, 3)
    si = dr.zeros(mi.SurfaceInteraction3f, len(d))
    si.wi = mi.Vector3f(np.ascontiguousarray(-d.T, dtype=np.float32))  # wi points back
    val = np.array(emitter.eval(si)).T.reshape(16, 32, 3)
    # all but the pole rows (at a pole every column is the same direction)
    np.testing.assert_allclose(val[1:-1], img[1:-1], rtol=2e-3)


def test_lit_side_follows_the_light_direction(sphere):
    """A single softbox toward +x lights the side of the sphere that projects from +x."""
    img = np.full((32, 64, 3), 1e-3, np.float32)
    d = em.envmap_directions(64, 32)
    img[d[..., 0] > 0.95] = 5.0
    cam = _cam((0.0, -4.0, 0.0))
    out = em.render_envmap(sphere, {"diffuse": 0.5, "specular": 0.0, "roughness": 0.5}, cam,
                           img, spp=16)
    lum = out[:, :, :3].mean(2)
    jj = np.arange(W) + 0.5
    centroid = (lum.sum(0) * jj).sum() / lum.sum()
    xy, _ = cam.project(np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]))
    x_plus, x_zero = xy[0, 0], xy[1, 0]
    assert np.sign(centroid - x_zero) == np.sign(x_plus - x_zero)
    assert abs(centroid - x_zero) > 3.0


# ---- the renderer ----
def test_white_furnace(sphere):
    """Diffuse sphere (a_s = 0) under a constant map L: radiance a_d * L (the diffuse part).

    With a_s = 0 Schlick's term still reflects (1 - v.h)^5 at grazing angles: measured by a
    black (a_d = 0) render and subtracted; it is small.
    """
    L = 0.8
    env = np.full((16, 32, 3), L, np.float32)
    a_d = np.array([0.9, 0.5, 0.2])
    cam = _cam((0.0, -4.0, 0.3))
    c = _center_disk(cam)
    img = em.render_envmap(sphere, {"diffuse": a_d, "specular": 0.0, "roughness": 0.5}, cam, env,
                           spp=64)
    black = em.render_envmap(sphere, {"diffuse": [0.0] * 3, "specular": 0.0, "roughness": 0.5},
                             cam, env, spp=64)
    assert np.all(img[c, 3] > 0.999)
    diffuse = (img[c, :3] - black[c, :3]).mean(0)
    np.testing.assert_allclose(diffuse, a_d * L, rtol=0.015)
    assert black[c, :3].mean() < 0.01 * L
    # and the whole render, Schlick term included, is within 2 % of a_d * L at these albedos
    np.testing.assert_allclose(img[c, :3].mean(0), a_d * L, rtol=0.02)
    # background black (the map is hidden), alpha 0
    assert img[0, 0, 3] == 0 and np.all(img[0, 0, :3] == 0)


@pytest.mark.parametrize("a_d", [0.0, 1.0])
@pytest.mark.parametrize("a_s", [0.0, 1.0])
@pytest.mark.parametrize("r", [0.0, 1.0])  # 0 is clipped to r_min
def test_extremes_are_finite(sphere, a_d, a_s, r):
    out = em.render_envmap(sphere, {"diffuse": [a_d] * 3, "specular": a_s, "roughness": r},
                           _cam((1.0, -3.5, 1.0)), em.envmap_image(32, 16), spp=4)
    assert np.all(np.isfinite(out)) and out.min() >= 0
    assert out[:, :, 3].max() == pytest.approx(1.0)


def test_texture_maps_are_used(sphere):
    """A map that is bright on the upper half (v > 0.5) brightens the upper half of the image."""
    diffuse = np.full((8, 16, 3), 0.05, np.float32)
    diffuse[:4] = 0.9  # first rows = top of the map = v near 1 = north pole (+z)
    cam = _cam((0.0, -4.0, 0.0))
    out = em.render_envmap(sphere, {"diffuse": diffuse, "specular": 0.0, "roughness": 0.5}, cam,
                           np.full((16, 32, 3), 1.0, np.float32), spp=8)
    lum = out[:, :, :3].mean(2)
    assert lum[: H // 2 - 2].sum() > 5 * lum[H // 2 + 2:].sum()  # image rows: up is +z


@pytest.mark.parametrize("scale", [1e-4, 1e4])
def test_scale_invariance(sphere, scale):
    """Radiance does not depend on the scene's units: the same view at 1e-4 and 1e4 units."""
    env = em.envmap_image(32, 16)
    eye = np.array([1.0, -3.5, 1.0])
    ref = em.render_envmap(sphere, GLOSSY, _cam(eye), env, spp=16)
    small = Mesh(sphere.v_pos * scale, sphere.t_pos_idx, sphere.v_tex, sphere.t_tex_idx)
    out = em.render_envmap(small, GLOSSY, _cam(eye * scale), env, spp=16)
    np.testing.assert_allclose(out[:, :, 3].sum(), ref[:, :, 3].sum(), rtol=0.01)
    np.testing.assert_allclose(out[:, :, :3].mean(), ref[:, :, :3].mean(), rtol=0.03)


# ---- the metric ----
def test_relight_rmse_self_is_noise_and_decreases_with_spp(sphere):
    env = em.envmap_image(64, 32)
    cams = _cams()
    same = em.relight_rmse(sphere, GLOSSY, sphere, GLOSSY, cams, env, spp=8)
    # common random numbers: identical scenes, the same samples; only the order in which drjit's
    # threads add each pixel's 8 samples (all >= 0) may differ: within 2 (spp - 1) u of the value,
    # at most 0.44 times that in sRGB, plus the float32 encoding's rounding (tests/_float_sums.py):
    # 4.9e-7, where another seed's noise is ~0.03
    assert max(same["per_view"]) <= SRGB_RELATIVE_SLOPE * reorder_bound(8) + 2 * U32, same
    lo = em.relight_rmse(sphere, GLOSSY, sphere, GLOSSY, cams, env, spp=8, seed_gt=1000)
    hi = em.relight_rmse(sphere, GLOSSY, sphere, GLOSSY, cams, env, spp=64, seed_gt=1000)
    # independent seeds: pure Monte Carlo noise, ~ 1/sqrt(spp) (expected ratio 0.35); measured
    # 0.026 at 64 spp on these 48 x 36 images (many silhouette pixels)
    assert 0 < hi["mean"] < 0.6 * lo["mean"]
    assert hi["mean"] < 0.04
    assert len(hi["per_view"]) == 2 and hi["spp"] == 64


@pytest.mark.parametrize(("change", "at_least"), [
    ({"roughness": 0.6}, 0.04), ({"specular": 0.0}, 0.1), ({"specular": 0.15}, 0.04),
    ({"diffuse": [0.3, 0.3, 0.3]}, 0.03)])
def test_relight_rmse_sees_material_changes(sphere, change, at_least):
    """A material change gives an RMSE well above zero that does not depend on the seed
    (the metric renders both sides with the same random numbers, so it measures the change,
    not the noise)."""
    env = em.envmap_image(64, 32)
    cams = _cams()
    other = dict(GLOSSY, **change)
    r1 = em.relight_rmse(sphere, other, sphere, GLOSSY, cams, env, spp=32, seed=0)["mean"]
    r2 = em.relight_rmse(sphere, other, sphere, GLOSSY, cams, env, spp=32, seed=777)["mean"]
    assert r1 > at_least
    assert abs(r1 - r2) < 0.2 * r1


def test_relight_rmse_grows_with_the_roughness_change(sphere):
    env = em.envmap_image(64, 32)
    r = [em.relight_rmse(sphere, dict(GLOSSY, roughness=x), sphere, GLOSSY, _cams(), env,
                         spp=32)["mean"] for x in (0.3, 0.45, 0.7)]
    assert r[0] < r[1] < r[2]


def test_relight_rmse_sees_geometry_changes(sphere):
    env = em.envmap_image(64, 32)
    bigger = Mesh(sphere.v_pos * 1.05, sphere.t_pos_idx, sphere.v_tex, sphere.t_tex_idx)
    r = em.relight_rmse(bigger, GLOSSY, sphere, GLOSSY, _cams(), env, spp=16)
    assert r["mean"] > 0.03


# ---- errors ----
def test_errors(sphere):
    cam = _cam()
    with pytest.raises(em.EnvmapError, match="RGB"):
        em.render_envmap(sphere, GLOSSY, cam, np.ones((8, 16)), spp=4)
    with pytest.raises(em.EnvmapError, match="NaN"):
        em.render_envmap(sphere, GLOSSY, cam, np.full((8, 16, 3), np.nan), spp=4)
    with pytest.raises(em.EnvmapError, match="spp"):
        em.render_envmap(sphere, GLOSSY, cam, np.ones((8, 16, 3)), spp=0)
    with pytest.raises(em.EnvmapError, match="max_depth"):
        em.render_envmap(sphere, GLOSSY, cam, np.ones((8, 16, 3)), spp=1, max_depth=1)
    with pytest.raises(em.EnvmapError, match="UVs"):
        em.render_envmap(Mesh(sphere.v_pos, sphere.t_pos_idx), {"diffuse": np.ones((4, 4, 3))},
                         cam, np.ones((8, 16, 3)), spp=1)
    with pytest.raises(em.EnvmapError, match="no cameras"):
        em.relight_rmse(sphere, GLOSSY, sphere, GLOSSY, [], np.ones((8, 16, 3)))
    with pytest.raises(em.EnvmapError, match="sky"):
        em.envmap_image(sky=-1.0)
    away = Camera("away.exr", W, H, intrinsics(W, H, 40.0), look_at(np.array([0, -4.0, 0]), [0, -8.0, 0]))
    with pytest.raises(em.EnvmapError, match="visible"):
        em.relight_rmse(sphere, GLOSSY, sphere, GLOSSY, [away], np.ones((8, 16, 3)), spp=1)
