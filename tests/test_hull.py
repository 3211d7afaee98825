import numpy as np
import pytest
from _geometry_scene import icosphere, silhouette

from recon import hull
from recon.io.cameras import Camera, CameraSet, intrinsics, look_at
from recon.io.mesh import Mesh


def _ring(n=12, res=96, radius=3.0):
    return CameraSet(tuple(
        Camera(f"images/{k:02d}.png", res, res, intrinsics(res, res, 40),
               look_at([radius * np.cos(t), radius * np.sin(t), 1.2 * np.sin(2 * t + 0.3)], [0, 0, 0]))
        for k, t in enumerate(np.linspace(0, 2 * np.pi, n, endpoint=False))))


def _sphere(r=0.5):
    m = icosphere(4)
    return Mesh(m.v_pos * r, m.t_pos_idx)


def test_bilinear_lookup_convention():
    img = np.arange(12, dtype=np.float32).reshape(3, 4)
    # pixel (i, j) covers [j, j+1] x [i, i+1]: its center (j + 0.5, i + 0.5) returns it exactly
    assert hull.bilinear(img, np.array([2.5]), np.array([1.5]))[0] == img[1, 2]
    assert hull.bilinear(img, np.array([3.0]), np.array([1.5]))[0] == pytest.approx(0.5 * (img[1, 2] + img[1, 3]))
    assert hull.bilinear(img, np.array([-5.0]), np.array([0.0]))[0] == img[0, 0]  # clamped


def test_silhouette_field_sign_and_distance():
    sphere = _sphere(0.5)
    cams = _ring(n=16, res=128)
    masks = {c.stem: silhouette(sphere, c) for c in cams}
    grid = hull.Grid(np.array([-0.9, 0.0, 0.0]), 0.1, 19)  # a line of voxels along x
    pts = grid.points()
    line = np.flatnonzero((np.abs(pts[:, 1]) < 1e-9) & (np.abs(pts[:, 2]) < 1e-9))
    field, seen = hull.silhouette_field(cams, masks, grid, margin_px=0.0)
    f = field.ravel()[line]
    x = pts[line, 0]
    assert np.all(f[np.abs(x) < 0.4] > 0) and np.all(f[np.abs(x) > 0.6] < 0)
    near = np.abs(np.abs(x) - 0.5) < 0.25
    # inside, the field is the distance to the hull (within the pixel and view-band error)
    np.testing.assert_allclose(f[near], 0.5 - np.abs(x[near]), atol=0.03)
    assert seen.max() == 16


def test_silhouette_field_rejects_unusable_masks():
    cams = _ring(n=4, res=32)
    grid = hull.Grid.cube(np.zeros(3), 1.0, 8)
    with pytest.raises(hull.HullError, match=r"mask of 00 is \(16, 16\) but its camera is 32x32"):
        hull.silhouette_field(cams, {"00": np.ones((16, 16), bool), "01": np.ones((32, 32), bool)}, grid)
    with pytest.raises(hull.HullError, match="needs masks for at least 2 views, found 1"):
        hull.silhouette_field(cams, {"00": np.ones((32, 32), bool)}, grid)
