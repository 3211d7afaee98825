"""The visual hull's part below everything the views saw is cut flat (recon.unseen), and nothing
any view saw is cut: ray-cast silhouettes of a box on a table, a ball resting on a point and a
ball seen from all around."""

from dataclasses import replace
from functools import lru_cache

import numpy as np
from _geometry_scene import icosphere, silhouette

from recon import init_mesh as rim
from recon import metrics
from recon.io.cameras import Camera, CameraSet, intrinsics, look_at
from recon.io.mesh import Mesh
from recon.unseen import seen_heights, unseen_base

SETTINGS = rim.InitMeshSettings(resolution=64, target_faces=2000)


def _box(size=(0.8, 0.6, 0.5)) -> Mesh:
    """A box standing on z = 0 (12 outward triangles)."""
    x, y, z = size[0] / 2, size[1] / 2, size[2]
    v = np.array([[-x, -y, 0], [x, -y, 0], [x, y, 0], [-x, y, 0],
                  [-x, -y, z], [x, -y, z], [x, y, z], [-x, y, z]], float)
    f = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                  [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])
    return Mesh(v, f)


def _from_above(elevations=(20, 45, 65), n=8, target=(0, 0, 0.25)) -> CameraSet:
    cams = []
    for e_deg in elevations:
        e = np.radians(e_deg)
        for t in np.linspace(0, 2 * np.pi, n, endpoint=False) + e:
            eye = 3.0 * np.array([np.cos(e) * np.cos(t), np.cos(e) * np.sin(t), np.sin(e)])
            cams.append(Camera(f"images/{len(cams):02d}.png", 96, 96, intrinsics(96, 96, 40), look_at(eye, target)))
    return CameraSet(tuple(cams))


def _hulls(obj, cams, masks=None):
    masks = masks or {c.stem: silhouette(obj, c) for c in cams}
    cut, st = rim.visual_hull_mesh(cams, masks, SETTINGS)
    keel, st_keel = rim.visual_hull_mesh(cams, masks, replace(SETTINGS, unseen_base=False))
    return cut, st, keel, st_keel


@lru_cache(maxsize=1)
def _box_from_above():
    """The box, the views from above, their masks and the two hulls (shared by the tests)."""
    box, cams = _box(), _from_above()
    masks = {c.stem: silhouette(box, c) for c in cams}
    return box, cams, masks, *_hulls(box, cams, masks)


def test_the_keel_under_a_box_seen_from_above_is_cut_at_its_foot():
    box, _, _, cut, st, keel, st_keel = _box_from_above()
    voxel = st["grid"]["voxel"]
    # every view is above the table: the cones reach far below the box, where no view sees
    assert keel.v_pos[:, 2].min() < -0.1
    rim.check_closed_manifold(cut)
    assert st["unseen_base"]["cut"] and -2.5 * voxel < cut.v_pos[:, 2].min() < 0
    assert st["unseen_base"]["base_vertices"] > 30  # closed flat, along the cameras' up
    np.testing.assert_allclose(st["unseen_base"]["normal"], [0, 0, 1], atol=1e-6)
    # the views see the same silhouettes: nothing they saw was cut
    assert st["mask_iou"]["mean"] > st_keel["mask_iou"]["mean"] - 0.005
    a_cut = metrics.chamfer(cut, box, n_samples=20_000)["accuracy"]
    a_keel = metrics.chamfer(keel, box, n_samples=20_000)["accuracy"]
    assert a_cut < 0.7 * a_keel  # the rest: 24 views of 96 px leave a fat hull around a box


def test_a_strip_of_table_in_a_few_masks_does_not_lower_the_cut_to_the_keel():
    """A plain desk's shadow band at the foot, taken into 4 of 24 masks: those views see down into
    the keel through it; the cut follows what most views saw."""
    box, cams, clean, _, _, _, _ = _box_from_above()
    masks = {}
    for k, c in enumerate(cams):
        m = clean[c.stem]
        if k % 6 == 0:  # the mask grows 12 px down under the object (image rows grow downwards)
            grown = m.copy()
            for d in range(1, 13):
                grown[d:] |= m[:-d]
            m = grown
        masks[c.stem] = m
    cut, st, keel, _ = _hulls(box, cams, masks)
    heights = seen_heights(keel, cams, masks, cams.up())
    lowest_seen = min(np.quantile(h, 0.001) for h in heights.values())
    voxel = st["grid"]["voxel"]
    assert lowest_seen < -4 * voxel  # the strips' views see the keel
    assert -3.5 * voxel < cut.v_pos[:, 2].min() < 0


def test_a_ball_resting_on_a_point_loses_only_its_unseen_cap():
    ball = Mesh(icosphere(4).v_pos * 0.4 + [0, 0, 0.4], icosphere(4).t_pos_idx)
    cams = _from_above(target=(0, 0, 0.4))
    cut, st, keel, st_keel = _hulls(ball, cams)
    rim.check_closed_manifold(cut)
    z = cut.v_pos[:, 2]
    # the views from 20 degrees up see the ball down to about 20 degrees below its equator; the
    # cap under that is flat now (no view says what it is; on a table the keel is surely wrong)
    assert st["unseen_base"]["cut"] and 0.0 < z.min() < 0.4 - 0.4 * np.sin(np.radians(15))
    masks = {c.stem: silhouette(ball, c) for c in cams}
    seen_on_the_ball = min(np.quantile(h, 0.001) for h in seen_heights(ball, cams, masks, cams.up()).values())
    assert z.min() < seen_on_the_ball
    assert st["mask_iou"]["mean"] > st_keel["mask_iou"]["mean"] - 0.005


def test_nothing_is_cut_when_the_views_see_the_object_from_below_too():
    ball = Mesh(icosphere(4).v_pos * 0.5, icosphere(4).t_pos_idx)
    cams = _from_above(elevations=(-50, -10, 30, 60), target=(0, 0, 0))
    cut, st, keel, _ = _hulls(ball, cams)
    assert st["unseen_base"]["cut"] is False and "normal" not in st["unseen_base"]
    np.testing.assert_array_equal(cut.v_pos, keel.v_pos)


def test_a_support_plane_takes_precedence_and_few_views_cut_nothing():
    from recon.support import SupportPlane

    _, cams, masks, _, _, keel, _ = _box_from_above()
    _, st = rim.visual_hull_mesh(cams, masks, SETTINGS, SupportPlane(np.array([0.0, 0.0, 1.0]), 0.0))
    assert st["unseen_base"] is None and st["plane"]["cut"]
    # two views with a mask, and empty masks: too little seen to cut anything, no error, no NaN
    two = {c.stem: masks[c.stem] for c in list(cams)[:2]}
    base, info = unseen_base(keel, cams, two, 0.02)
    assert base is None and info["views"] == 2 and info["cut"] is False
    empty = {c.stem: np.zeros_like(masks[c.stem]) for c in cams}
    base, info = unseen_base(keel, cams, empty, 0.02)
    assert base is None and info["views"] == 0
