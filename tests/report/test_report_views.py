"""Per-view comparison: coverage masks, cameras at the report's size, error maps, RMSE."""

from __future__ import annotations

import numpy as np
import pytest
import report_scene

from recon.io.cameras import Camera, intrinsics, look_at
from recon.io.images import linear_to_srgb, srgb_to_linear
from recon.report.inputs import ReportError
from recon.report.views import (
    OUTSIDE_GREY,
    colorize,
    compare,
    coverage_mask,
    error_image,
    fit_camera,
    pixel_rays,
    report_camera,
    resize_area,
    resize_mask,
)


def _camera(w=80, h=60, dist=3.0, fov=30.0) -> Camera:
    return Camera("x.exr", w, h, intrinsics(w, h, fov), look_at((0, 0, dist), (0, 0, 0), (0, 1, 0)))


def test_pixel_rays_hit_the_pixel_centers():
    cam = _camera()
    o, d = pixel_rays(cam)
    p = o + 2.0 * d  # points along the rays project back onto the pixel centers
    xy, z = cam.project(p.reshape(-1, 3))
    j, i = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    np.testing.assert_allclose(xy, np.stack([j.ravel(), i.ravel()], 1), atol=1e-9)
    assert np.all(z > 0)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0)


def test_coverage_mask_of_a_sphere_is_its_projected_disk():
    """A sphere of radius r at distance D projects to a disk of radius f tan(asin(r/D))."""
    cam = _camera()
    mesh = report_scene.uv_sphere(48, 96, radius=0.5)
    mask = coverage_mask(mesh, cam)
    f = cam.K[0, 0]
    R = f * np.tan(np.arcsin(0.5 / 3.0))
    j, i = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    rho = np.hypot(j - cam.K[0, 2], i - cam.K[1, 2])
    inside, outside = rho < R - 0.6, rho > R + 0.6  # the tessellation shrinks it by < 0.3 px
    assert mask[inside].all() and not mask[outside].any()
    assert mask.sum() == pytest.approx(np.pi * R**2, rel=0.05)


def test_fit_and_report_camera():
    cam = _camera(800, 600)
    small = report_camera(cam, 200)
    assert (small.width, small.height) == (200, 150)
    np.testing.assert_allclose(small.K[:2], cam.K[:2] / 4)
    assert report_camera(cam, 1000) is cam
    assert fit_camera(cam, 300, 400, "x.exr").width == 400
    with pytest.raises(ReportError, match=r"x\.exr: 400x200 pixels does not have the aspect ratio"):
        fit_camera(cam, 200, 400, "x.exr")


def test_resize_area_averages_and_masks_need_half_coverage():
    a = np.arange(16, dtype=np.float32).reshape(4, 4, 1)
    np.testing.assert_allclose(resize_area(a, 2, 2)[:, :, 0], [[2.5, 4.5], [10.5, 12.5]])
    m = np.zeros((4, 4), bool)
    m[:2, :2] = True
    m[2, 2] = True
    np.testing.assert_array_equal(resize_mask(m, 2, 2), [[True, False], [False, False]])


def test_error_image_and_rmse_known_values():
    """sRGB difference of 0.2 in one channel of every pixel: per-pixel error 0.2/sqrt(3)."""
    h, w = 10, 12
    a_srgb = np.full((h, w, 3), 0.3, np.float32)
    b_srgb = a_srgb.copy()
    b_srgb[..., 1] += 0.2
    a, b = srgb_to_linear(a_srgb), srgb_to_linear(b_srgb)
    err = error_image(a, b)
    np.testing.assert_allclose(err, 0.2 / np.sqrt(3), atol=1e-6)

    m_a = np.zeros((h, w), bool)
    m_a[:5] = True
    m_b = np.zeros((h, w), bool)
    m_b[:, :3] = True
    # Outside the union the images differ by much more; it must not count.
    a[8:, 6:] = 1.0
    res = compare("v", _camera(w, h), a, m_a, b, m_b)
    np.testing.assert_array_equal(res.union, m_a | m_b)
    assert res.rmse == pytest.approx(0.2 / np.sqrt(3), abs=1e-6)
    sat = np.zeros((h, w), bool)
    sat[:5] = True
    b[:5] = 0.9  # only where saturated: left out
    res = compare("v", _camera(w, h), a, m_a, b, m_b, saturated=sat)
    assert res.rmse == pytest.approx(0.2 / np.sqrt(3), abs=1e-6)
    assert not res.union[:5].any()


def test_compare_both_masks_empty_is_a_report_error():
    z = np.zeros((4, 4, 3), np.float32)
    m = np.zeros((4, 4), bool)
    with pytest.raises(ReportError, match="view v: .*both masks are empty"):
        compare("v", _camera(4, 4), z, m, z, m)


def test_colorize_scale_and_outside():
    v = np.array([[0.0, 0.1, 0.2, 5.0, np.nan]])
    mask = np.array([[True, True, True, True, False]])
    rgb = colorize(v, 0.2, mask)
    assert rgb.shape == (1, 5, 3) and np.all(np.isfinite(rgb))
    np.testing.assert_allclose(rgb[0, 2], rgb[0, 3])  # clipped at vmax
    assert rgb[0, 0].sum() < rgb[0, 1].sum() < rgb[0, 2].sum()  # inferno brightens
    np.testing.assert_allclose(rgb[0, 4], OUTSIDE_GREY)


def test_error_image_is_finite_for_extreme_inputs():
    a = np.array([[[np.inf, -1.0, 1e30]]], np.float32)
    b = np.zeros_like(a)
    e = error_image(np.nan_to_num(a, posinf=1e30), b)
    assert np.all(np.isfinite(e)) and e.max() <= 1.0
    assert linear_to_srgb(a).max() <= 1.0
