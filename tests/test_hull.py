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


def test_votes_needed():
    """A voxel is carved when more than the fraction of the views that see it say outside."""
    seen = np.array([0, 1, 2, 9, 10, 19, 20, 33, 66])
    np.testing.assert_array_equal(hull.votes_needed(seen, 0.0), 1)  # strict: one view carves
    np.testing.assert_array_equal(hull.votes_needed(seen, 0.1), [1, 1, 1, 1, 2, 2, 3, 4, 7])
    with pytest.raises(ValueError, match="outside_fraction"):
        hull.silhouette_fields(_ring(n=4, res=16), {}, hull.Grid.cube(np.zeros(3), 1.0, 4), outside_fraction=0.5)


def test_one_wrong_view_cannot_carve_the_vote():
    """A hole through the middle of one view's mask: the strict hull has a tunnel along that
    view's rays, the vote (16 views, 10 %: two views must agree) does not."""
    sphere = _sphere(0.5)
    cams = _ring(n=16, res=128)
    masks = {c.stem: silhouette(sphere, c) for c in cams}
    bad = cams.frames[5]
    i, j = np.mgrid[:128, :128]
    masks[bad.stem] = masks[bad.stem] & ((i - 64) ** 2 + (j - 64) ** 2 > 10**2)
    grid = hull.Grid.cube(np.zeros(3), 0.6, 24)
    h = hull.silhouette_fields(cams, masks, grid, outside_fraction=0.1)
    pts = grid.points()
    # the voxels on the bad view's central ray, well inside the sphere
    ray = bad.center / np.linalg.norm(bad.center)
    on_ray = (np.linalg.norm(np.cross(pts, ray), axis=1) < 0.03) & (np.linalg.norm(pts, axis=1) < 0.35)
    assert on_ray.sum() >= 4
    assert np.all(h.strict.ravel()[on_ray] < 0)  # the strict hull is carved there
    assert np.all(h.voted.ravel()[on_ray] > 0.1)  # the vote is not
    # elsewhere the vote is the hull of the 15 right views and the strict field never exceeds it
    assert np.all(h.strict <= h.voted)
    right = {k: v for k, v in masks.items() if k != bad.stem}
    strict15, _ = hull.silhouette_field(cams, right, grid)
    inside = strict15 > 0
    assert np.mean(h.voted[inside] > 0) > 0.99
    # with the fraction 0 both fields are the strict hull
    h0 = hull.silhouette_fields(cams, masks, grid)
    np.testing.assert_array_equal(h0.voted, h0.strict)
    far = -4 * grid.step  # voxels farther outside are no longer updated: equal up to that
    np.testing.assert_array_equal(np.maximum(h0.strict, far), np.maximum(h.strict, far))


def test_views_that_do_not_see_a_voxel_abstain():
    """An object cut by the frame edge in some views: those views neither carve nor count
    the part outside their frame."""
    sphere = _sphere(0.5)
    cams = list(_ring(n=12, res=96))
    # a close-up of one side: the sphere overflows its frame
    close = Camera("images/zz.png", 96, 96, intrinsics(96, 96, 40), look_at([1.0, 0.0, 0.0], [0.0, 0.0, 0.0]))
    cams = CameraSet(tuple(cams) + (close,))
    masks = {c.stem: silhouette(sphere, c) for c in cams}
    assert masks["zz"].all()  # the close-up sees the sphere everywhere in its frame
    grid = hull.Grid.cube(np.zeros(3), 0.6, 20)
    pts = grid.points()
    inside = np.linalg.norm(pts, axis=1) < 0.4
    for fraction in (0.0, 0.1):  # even the strict hull: a view that does not see a voxel cannot carve it
        field, seen = hull.silhouette_field(cams, masks, grid, outside_fraction=fraction)
        assert np.all(field.ravel()[inside] > 0)
        assert seen.max() == 13 and seen.ravel()[inside].min() == 12  # not all seen by the close-up


def test_few_views_give_the_strict_hull():
    """Below 10 views no minority can be outvoted (10 %): the voted field is the strict one."""
    sphere = _sphere(0.5)
    cams = _ring(n=9, res=64)
    masks = {c.stem: silhouette(sphere, c) for c in cams}
    masks["03"] = np.zeros_like(masks["03"])  # even a wrong view carves
    h = hull.silhouette_fields(cams, masks, hull.Grid.cube(np.zeros(3), 0.6, 16), outside_fraction=0.1)
    np.testing.assert_array_equal(h.voted, h.strict)
    assert not (h.voted > 0).any()
