"""SfM's points carve the space they were seen through from the visual hull (recon.freespace,
recon.init_mesh's free_space_* settings): a bowl's cavity, which no silhouette carves."""

import numpy as np
import pytest
from _geometry_scene import silhouette
from scipy import ndimage

from recon import freespace as fs
from recon import init_mesh as rim
from recon import metrics
from recon.io.cameras import Camera, CameraSet, intrinsics, look_at
from recon.io.mesh import Mesh
from recon.support import SupportPlane


def _cube(fill):
    c = np.zeros((3, 3, 3), bool)
    fill(c)
    c[1, 1, 1] = True
    return c


def test_simple_points():
    # on a flat surface (the half space below it): removing it dents the surface
    assert fs.is_simple(_cube(lambda c: c.__setitem__((slice(None), slice(None), 0), True)))
    # alone: removing it deletes a component
    assert not fs.is_simple(_cube(lambda c: None))
    # in a wall one voxel thick: removing it opens a tunnel through the wall
    assert not fs.is_simple(_cube(lambda c: c.__setitem__((slice(None), slice(None), 1), True)))
    # the only link of a rod: removing it cuts the rod in two
    assert not fs.is_simple(_cube(lambda c: c.__setitem__((1, 1, slice(None)), True)))
    # deep inside: removing it makes a cavity
    assert not fs.is_simple(np.ones((3, 3, 3), bool))
    # the end of a rod
    assert fs.is_simple(_cube(lambda c: c.__setitem__((1, 1, 0), True)))


def test_topology6_counts_components_cavities_and_tunnels():
    ball = np.zeros((12, 12, 12), bool)
    ball[2:10, 2:10, 2:10] = True
    assert fs.topology6(ball) == (1, 1, 1)
    ring = ball.copy()
    ring[4:8, 4:8, :] = False  # a square hole through it: a tunnel
    assert fs.topology6(ring) == (1, 1, 0)
    hollow = ball.copy()
    hollow[4:8, 4:8, 4:8] = False  # a closed cavity
    assert fs.topology6(hollow) == (1, 2, 2)
    two = np.concatenate([ball, ball], axis=0)
    assert fs.topology6(two) == (2, 1, 2)
    # touching along an edge only: two pieces for the 6-connected object
    diag = np.zeros((6, 6, 6), bool)
    diag[1:3, 1:3, 1:5] = True
    diag[3:5, 3:5, 1:5] = True
    assert fs.topology6(diag)[0] == 2 and fs.topology6(diag)[2] == 2


def _euler6(obj):
    """Components of the object (6-connected) and of the empty space (26-connected, padded)."""
    pad = np.pad(obj, 1)
    return (ndimage.label(pad, structure=ndimage.generate_binary_structure(3, 1))[1],
            ndimage.label(~pad, structure=np.ones((3, 3, 3), bool))[1])


def test_carving_keeps_the_topology():
    inside = np.zeros((20, 20, 20), bool)
    inside[2:18, 2:18, 2:18] = True
    # free: a slab through the middle (carving it all would cut the block in two), a pocket open
    # to the outside, and an enclosed bubble (unreachable: carving it would make a cavity)
    free = np.zeros_like(inside)
    free[9:11, :, :] = True
    free[2:6, 12:16, 12:16] = True
    free[13:16, 5:8, 5:8] = True
    removed = fs.carve(inside, free)
    after = inside & ~removed
    assert _euler6(after) == _euler6(inside) == (1, 1)
    assert removed[2:6, 12:16, 12:16].all()  # the open pocket goes
    assert not removed[13:16, 5:8, 5:8].any()  # the bubble stays
    assert not (removed & ~free).any()
    assert removed[9:11].sum() > 0.9 * 2 * 16 * 16 - 4 * 16  # most of the slab, a bridge stays


def _bowl_scene():
    from recon.synth.shapes import bowl

    m = bowl(level=5, seed=0)
    v = m.v_pos - [0.0, 0.0, m.v_pos[:, 2].min()]  # the base on z = 0
    obj = Mesh(v, m.t_pos_idx)
    cams = []
    for k, (elev, t) in enumerate([(e, t) for e in (25, 45, 65) for t in np.linspace(0, 2 * np.pi, 10, endpoint=False)]):
        e = np.radians(elev)
        eye = 4.0 * np.array([np.cos(e) * np.cos(t + e), np.cos(e) * np.sin(t + e), np.sin(e)])
        cams.append(Camera(f"images/{k:02d}.png", 96, 96, intrinsics(96, 96, 40), look_at(eye, [0, 0, 0.2])))
    return obj, CameraSet(tuple(cams)), SupportPlane(np.array([0.0, 0.0, 1.0]), 0.0)


def _seen(mesh, cams, points, min_views=3):
    """SeenPoints of ``points`` on ``mesh``: each seen by the cameras with a clear line to it."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.v_pos.astype(np.float32)),
                        o3d.core.Tensor(mesh.t_pos_idx.astype(np.uint32)))
    centers = np.array([c.center for c in cams])
    view, point = [], []
    for k, c in enumerate(centers):
        d = points - c
        dist = np.linalg.norm(d, axis=1)
        rays = np.concatenate([np.broadcast_to(c, d.shape), d / dist[:, None]], 1).astype(np.float32)
        hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        ok = hit > dist - 1e-3
        view += [k] * int(ok.sum())
        point += np.flatnonzero(ok).tolist()
    view, point = np.array(view), np.array(point)
    keep = np.bincount(point, minlength=len(points)) >= min_views
    sel = keep[point]
    remap = -np.ones(len(points), int)
    remap[keep] = np.arange(keep.sum())
    return fs.SeenPoints(centers, points[keep], view[sel], remap[point[sel]])


S = rim.InitMeshSettings(resolution=64, target_faces=3000)


def test_a_bowls_hull_is_carved_by_the_points_seen_inside_it():
    """The visual hull of a bowl is a dome over its cavity (every silhouette sees past it); the
    points on the cavity's floor, seen through the dome, carve it. The bowl keeps its genus, and
    nothing of the bowl itself is carved."""
    obj, cams, plane = _bowl_scene()
    masks = {c.stem: silhouette(obj, c) for c in cams}
    seen = _seen(obj, cams, obj.sample_surface(1500, np.random.default_rng(0)))
    hull, _ = rim.visual_hull_mesh(cams, masks, S, plane)
    carved, stats = rim.visual_hull_mesh(cams, masks, S, plane, seen)
    info = stats["free_space"]
    assert info["kept"] and info["voxels_carved"] > 0.2 * stats["voxels_inside"] / (1 - info["fraction_of_hull"])
    assert rim.topology(carved)["genus"] == rim.topology(hull)["genus"] == 0
    r0 = metrics.chamfer(hull, obj, n_samples=20_000)
    r1 = metrics.chamfer(carved, obj, n_samples=20_000)
    print(f"\nbowl: hull {r0['accuracy']:.4f}/{r0['completeness']:.4f}, carved {r1['accuracy']:.4f}/"  # noqa: T201
          f"{r1['completeness']:.4f}, {info['voxels_carved']} voxels ({100 * info['fraction_of_hull']:.0f} %)")
    # (the carved floor stays stop_voxels above the bowl's: 2 voxels of 64 here, hence the
    # completeness gains less than the accuracy)
    assert r1["accuracy"] < 0.6 * r0["accuracy"] and r1["completeness"] < 0.9 * r0["completeness"]
    # the bowl is not cut into: the carved mesh still holds its volume
    assert carved.volume() > 0.97 * obj.volume()


def test_wrong_points_carve_nothing_and_no_points_change_nothing():
    """Points triangulated inside a solid object (bad matches, scattered) are seen through its
    surface; their segments are thin streaks that the opening drops. (Thirty of them in a ball
    a third of the object's size, 90 segments converging, carve a dent of 174 voxels: the
    opening keeps what is free in bulk, and a dense cluster of wrong points looks like that.)"""
    obj, cams, plane = _solid_scene()
    masks = {c.stem: silhouette(obj, c) for c in cams}
    rng = np.random.default_rng(1)
    # 12 points well inside the sphere (radius 0.5 about (0, 0, 0.5)), each "seen" by 3 views
    d = rng.normal(size=(12, 3))
    pts = [0.0, 0.0, 0.5] + 0.35 * d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0.3, 1.0, (12, 1))
    view = np.concatenate([rng.choice(len(cams), 3, replace=False) for _ in range(12)])
    point = np.repeat(np.arange(12), 3)
    wrong = fs.SeenPoints(np.array([c.center for c in cams]), pts, view, point)
    hull, _ = rim.visual_hull_mesh(cams, masks, S, plane)
    mesh, stats = rim.visual_hull_mesh(cams, masks, S, plane, wrong)
    assert stats["free_space"]["voxels_carved"] == 0
    assert np.array_equal(mesh.v_pos, hull.v_pos)
    # the points of its surface carve nothing either (their segments stop short of it)
    right = _seen(obj, cams, obj.sample_surface(1500, np.random.default_rng(2)))
    mesh, stats = rim.visual_hull_mesh(cams, masks, S, plane, right)
    assert stats["free_space"]["voxels_carved"] == 0 and np.array_equal(mesh.v_pos, hull.v_pos)
    none, stats = rim.visual_hull_mesh(cams, masks, S, plane, fs.SeenPoints(np.zeros((0, 3)), np.zeros((0, 3)),
                                                                             np.zeros(0, int), np.zeros(0, int)))
    assert stats["free_space"]["voxels_carved"] == 0 and np.array_equal(none.v_pos, hull.v_pos)


def _solid_scene():
    from _geometry_scene import icosphere

    m = icosphere(4)
    obj = Mesh(m.v_pos * 0.5 + [0.0, 0.0, 0.5], m.t_pos_idx)
    _, cams, plane = _bowl_scene()
    return obj, cams, plane


@pytest.mark.parametrize("bad", [dict(free_space_points=-1), dict(free_space_max_error_px=0.0),
                                 dict(free_space_min_views=1), dict(free_space_stop_voxels=-1.0)])
def test_free_space_settings_are_checked(bad):
    with pytest.raises(ValueError, match="free_space"):
        rim.InitMeshSettings(**bad)
