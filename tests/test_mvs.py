"""The photos' depth maps inside the visual hull (recon.mvs) and their free-space carving
(recon.freespace.carve_hull with ``views``): checked against the true surface of a textured bowl
lit by a flash at the camera, rendered by ray casting."""

import numpy as np
import pytest
from _geometry_scene import silhouette

from recon import init_mesh as rim
from recon import metrics, mvs
from recon.hull import Grid
from recon.io.cameras import Camera, CameraSet, intrinsics, look_at
from recon.io.mesh import Mesh
from recon.support import SupportPlane

PLANE = SupportPlane(np.array([0.0, 0.0, 1.0]), 0.0)  # the bowl stands on z = 0, the cameras above


def _bowl(level=5):
    from recon.synth.shapes import bowl

    m = bowl(level=level, seed=0)
    return Mesh(m.v_pos - [0.0, 0.0, m.v_pos[:, 2].min()], m.t_pos_idx)


def _cams(n=24, size=128):
    cams = []
    for k in range(n):
        e = np.radians((35, 55)[k % 2])
        t = 2 * np.pi * k / n
        eye = 4.0 * np.array([np.cos(e) * np.cos(t), np.cos(e) * np.sin(t), np.sin(e)])
        cams.append(Camera(f"images/{k:02d}.png", size, size, intrinsics(size, size, 40), look_at(eye, [0, 0, 0.25])))
    return CameraSet(tuple(cams))


def _texture(x):
    """A procedural albedo in [0.15, 0.85] with detail at a few scales (world position)."""
    v = (np.sin(23 * x[:, 0] + 3 * np.sin(17 * x[:, 1])) + np.sin(19 * x[:, 1] - 11 * x[:, 2])
         + np.sin(29 * x[:, 2] + 13 * x[:, 0]))
    return 0.5 + 0.35 * np.tanh(v)


def flash_photo(mesh, cam, albedo=_texture):
    """(H, W, 3) linear image of ``mesh`` lit by a flash at ``cam``'s centre: albedo |cos| / r^2,
    black where the ray misses."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.v_pos.astype(np.float32)), o3d.core.Tensor(mesh.t_pos_idx.astype(np.uint32)))
    d, c = mvs._rays(cam)
    ans = scene.cast_rays(o3d.core.Tensor(np.concatenate([np.broadcast_to(c, d.shape), d], 1).astype(np.float32)))
    t = ans["t_hit"].numpy().astype(np.float64)
    n = ans["primitive_normals"].numpy().astype(np.float64)
    hit = np.isfinite(t)
    x = c + d * np.where(hit, t, 0.0)[:, None]
    r = np.linalg.norm(x - c, axis=1)
    cos = np.abs(np.sum(n * (x - c), axis=1)) / np.maximum(r, 1e-9)
    val = np.where(hit, albedo(x) * cos / np.maximum(r, 1e-9) ** 2 * 12.0, 0.0)
    return np.repeat(val.reshape(cam.height, cam.width, 1), 3, axis=2).astype(np.float32)


def test_the_homography_maps_a_plane_point_to_its_projection():
    cams = list(_cams(4))
    rng = np.random.default_rng(0)
    for depth in (2.5, 4.0, 6.0):
        px = rng.uniform(10, 118, (20, 2))
        d, c = mvs._rays(cams[0])
        ray = np.stack([px[:, 0], px[:, 1], np.ones(20)], 1) @ np.linalg.inv(cams[0].K).T @ cams[0].world_to_camera[:3, :3]
        X = c + depth * ray
        want, _ = cams[1].project(X)
        H = mvs._homography(cams[0], cams[1], depth)
        p = np.concatenate([px - 0.5, np.ones((20, 1))], 1) @ H.T  # OpenCV pixel convention
        got = p[:, :2] / p[:, 2:] + 0.5
        assert np.abs(got - want).max() < 1e-6


def _scene():
    obj = _bowl()
    cams = _cams()
    masks = {c.stem: silhouette(obj, c) for c in cams}
    photos = {c.stem: flash_photo(obj, c) for c in cams}
    return obj, cams, masks, photos


S = rim.InitMeshSettings(resolution=64, target_faces=3000, dense_alone=True)
SWEEP = mvs.SweepSettings(work_size=128, depths=64)


def test_dense_points_lie_on_the_surface_and_carve_the_bowls_cavity():
    """The hull puts a dome over the bowl; the depth maps see its textured floor through it and
    carve it: the bowl's genus is kept, the hull's error falls, and the bowl is not cut into."""
    import open3d as o3d

    obj, cams, masks, photos = _scene()
    center, half, _ = rim.hull_bounds(cams, masks, S, plane=PLANE)
    grid = Grid.cube(center, half, S.resolution)
    field, _, _ = rim.hull_field(cams, masks, grid, S, PLANE)
    seen, info = mvs.dense_seen_points(cams, photos.__getitem__, masks, field, grid, 2000, SWEEP)
    assert seen is not None and info["points"] > 5000
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(obj.v_pos.astype(np.float32)), o3d.core.Tensor(obj.t_pos_idx.astype(np.uint32)))
    dist = scene.compute_distance(o3d.core.Tensor(seen.points.astype(np.float32))).numpy()
    size = float(np.ptp(obj.v_pos, axis=0).max())
    assert np.median(dist) < 0.01 * size and np.mean(dist > 0.03 * size) < 0.01
    # each point is observed by its own view and at least one that agrees
    assert np.all(np.bincount(seen.point, minlength=len(seen.points)) >= 2)
    assert np.all(np.isfinite(seen.points))

    hull, _ = rim.visual_hull_mesh(cams, masks, S, PLANE)
    carved, stats = rim.visual_hull_mesh(cams, masks, S, PLANE, views=photos.__getitem__)
    free = stats["free_space"]
    assert free["kept"] and free["dense"]["points"] > 5000
    assert rim.topology(carved)["genus"] == rim.topology(hull)["genus"] == 0
    r0 = metrics.chamfer(hull, obj, n_samples=20_000)
    r1 = metrics.chamfer(carved, obj, n_samples=20_000)
    print(f"\nbowl: hull {r0['accuracy']:.4f}/{r0['completeness']:.4f}, dense carving {r1['accuracy']:.4f}/"  # noqa: T201
          f"{r1['completeness']:.4f} ({free['voxels_carved']} voxels)")
    assert r1["accuracy"] < 0.5 * r0["accuracy"] and r1["completeness"] < 0.85 * r0["completeness"]
    assert carved.volume() > 0.97 * obj.volume()


def test_by_default_the_depth_maps_deepen_only_what_sfms_points_opened():
    """Without ``dense_alone`` the depth maps carve only the free space that SfM's points reach:
    none (given cameras) carves nothing; a few points seen inside the bowl open it, and the depth
    maps then carve it as well as those points alone, or better."""
    import test_freespace as tf

    obj, cams, masks, photos = _scene()
    default = rim.InitMeshSettings(resolution=64, target_faces=3000)
    hull, _ = rim.visual_hull_mesh(cams, masks, default, PLANE)
    alone, stats = rim.visual_hull_mesh(cams, masks, default, PLANE, views=photos.__getitem__)
    assert np.array_equal(alone.v_pos, hull.v_pos) and stats["free_space"]["dense"] is None
    rng = np.random.default_rng(0)
    floor = obj.sample_surface(4000, rng)
    floor = floor[(np.linalg.norm(floor[:, :2], axis=1) < 0.45) & (floor[:, 2] > 0.1)][:60]  # inside, near the floor
    seen = tf._seen(obj, cams, floor)
    sparse, s1 = rim.visual_hull_mesh(cams, masks, default, PLANE, seen)
    both, s2 = rim.visual_hull_mesh(cams, masks, default, PLANE, seen, views=photos.__getitem__)
    assert s1["free_space"]["kept"] and s2["free_space"]["kept"]
    r1 = metrics.chamfer(sparse, obj, n_samples=20_000)
    r2 = metrics.chamfer(both, obj, n_samples=20_000)
    print(f"\nsparse {r1['accuracy']:.4f}/{r1['completeness']:.4f} {s1['free_space']['voxels_carved']}, "  # noqa: T201
          f"+ depth maps {r2['accuracy']:.4f}/{r2['completeness']:.4f} {s2['free_space']['voxels_carved']}")
    # (the sparse points alone, with their wider stop, carve past the wall in places: completeness 0.12)
    assert r2["chamfer"] < r1["chamfer"] and both.volume() > 0.97 * obj.volume()


@pytest.mark.parametrize("kind", ["black", "white"])
def test_no_texture_gives_no_points_and_changes_nothing(kind):
    """Black photos and clipped white ones: no point, no carving, nothing non-finite."""
    obj = _bowl()
    cams = _cams(12)
    masks = {c.stem: silhouette(obj, c) for c in cams}
    photos = {c.stem: np.full((c.height, c.width, 3), 0.0 if kind == "black" else 1.0, np.float32) for c in cams}
    hull, _ = rim.visual_hull_mesh(cams, masks, S, PLANE)
    mesh, stats = rim.visual_hull_mesh(cams, masks, S, PLANE, views=photos.__getitem__)
    assert stats["free_space"].get("voxels_carved", 0) == 0, stats["free_space"]
    assert np.array_equal(mesh.v_pos, hull.v_pos)
    assert stats["free_space"]["dense"]["points"] == 0


def test_a_plain_bowl_is_not_cut_into():
    """A plain albedo: the sweep has only the shading and the rim's outline to match. What it
    matches wrongly lies in the air over the cavity (the rim's outline seen from neighbouring
    views), never inside the bowl: the carving cuts nothing of the bowl and does not make the
    hull worse."""
    import open3d as o3d

    obj = _bowl()
    cams = _cams(12)
    masks = {c.stem: silhouette(obj, c) for c in cams}
    photos = {c.stem: flash_photo(obj, c, lambda x: np.full(len(x), 0.6)) for c in cams}
    center, half, _ = rim.hull_bounds(cams, masks, S, plane=PLANE)
    grid = Grid.cube(center, half, S.resolution)
    field, _, _ = rim.hull_field(cams, masks, grid, S, PLANE)
    seen, _ = mvs.dense_seen_points(cams, photos.__getitem__, masks, field, grid, 2000, SWEEP)
    if seen is not None:
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(obj.v_pos.astype(np.float32)),
                            o3d.core.Tensor(obj.t_pos_idx.astype(np.uint32)))
        dist = scene.compute_distance(o3d.core.Tensor(seen.points.astype(np.float32))).numpy()
        inside = scene.compute_occupancy(o3d.core.Tensor(seen.points.astype(np.float32))).numpy() > 0.5
        assert not np.any(inside & (dist > 0.02 * float(np.ptp(obj.v_pos, axis=0).max())))
    hull, _ = rim.visual_hull_mesh(cams, masks, S, PLANE)
    mesh, stats = rim.visual_hull_mesh(cams, masks, S, PLANE, views=photos.__getitem__)
    assert mesh.volume() > 0.97 * obj.volume()
    r0 = metrics.chamfer(hull, obj, n_samples=20_000)
    r1 = metrics.chamfer(mesh, obj, n_samples=20_000)
    assert r1["accuracy"] <= 1.02 * r0["accuracy"] and r1["completeness"] <= 1.02 * r0["completeness"]


def test_dense_settings_are_checked():
    assert not rim.InitMeshSettings().dense_alone  # the depth maps alone carve only when asked
    with pytest.raises(ValueError, match="dense_points"):
        rim.InitMeshSettings(dense_points=-1)
