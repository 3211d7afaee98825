import numpy as np
import pytest

from recon import metrics
from recon.io.cameras import Camera, CameraSet, intrinsics, look_at
from recon.io.mesh import Mesh


def _sphere(radius: float = 1.0, center=(0.0, 0.0, 0.0)) -> Mesh:
    import open3d as o3d

    m = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=40)
    v = np.asarray(m.vertices)
    v = v / np.linalg.norm(v, axis=1, keepdims=True) * radius + np.asarray(center)
    return Mesh(v, np.asarray(m.triangles))


def _random_rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    return q


def _ring_cameras(n=12, radius=3.0) -> CameraSet:
    frames = []
    for i in range(n):
        a = 2 * np.pi * i / n
        eye = [radius * np.cos(a), radius * np.sin(a), 0.8 + 0.3 * np.sin(3 * a)]
        frames.append(Camera(f"images/{i:04d}.png", 64, 48, intrinsics(64, 48, 40), look_at(eye, [0, 0, 0])))
    return CameraSet(tuple(frames))


def _transform_cameras(cams: CameraSet, sim: metrics.Similarity) -> CameraSet:
    """The same cameras in a frame x' = s R x + t (world-to-camera stays rigid)."""
    out = []
    for c in cams:
        W = c.world_to_camera
        R2 = W[:3, :3] @ sim.rotation.T
        t2 = sim.scale * W[:3, 3] - R2 @ sim.translation
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = R2, t2
        out.append(Camera(c.image, c.width, c.height, c.K, M))
    return CameraSet(tuple(out))


def test_umeyama_recovers_known_similarity():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(50, 3))
    R = _random_rotation(rng)
    dst = 2.5 * src @ R.T + np.array([1.0, -2.0, 0.5])
    sim = metrics.umeyama(src, dst)
    assert sim.scale == pytest.approx(2.5, rel=1e-10)
    np.testing.assert_allclose(sim.rotation, R, atol=1e-10)
    np.testing.assert_allclose(sim.translation, [1.0, -2.0, 0.5], atol=1e-10)
    np.testing.assert_allclose(sim.apply(src), dst, atol=1e-10)
    np.testing.assert_allclose(sim.inverse().apply(dst), src, atol=1e-10)
    # a reflection in the data never gives an improper rotation
    sim2 = metrics.umeyama(src, src * np.array([1, 1, -1]))
    assert np.linalg.det(sim2.rotation) == pytest.approx(1.0)


def test_umeyama_rejects_bad_input():
    with pytest.raises(metrics.MetricsError, match="at least 3"):
        metrics.umeyama(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(metrics.MetricsError, match="same shape"):
        metrics.umeyama(np.zeros((4, 3)), np.zeros((5, 3)))
    line = np.outer(np.arange(5.0), [1, 2, 3])
    with pytest.raises(metrics.MetricsError, match="collinear"):
        metrics.umeyama(line, line)
    with pytest.raises(metrics.MetricsError, match="NaN"):
        metrics.umeyama(np.full((4, 3), np.nan), np.zeros((4, 3)))


def test_pose_errors_after_rotation_scale_translation():
    rng = np.random.default_rng(2)
    true = _ring_cameras()
    sim = metrics.Similarity(0.37, _random_rotation(rng), np.array([4.0, -1.0, 2.0]))
    est = _transform_cameras(true, sim)  # est = true seen in another frame
    fit = metrics.align_cameras(est, true)
    inv = sim.inverse()
    assert fit.scale == pytest.approx(inv.scale, rel=1e-9)
    np.testing.assert_allclose(fit.rotation, inv.rotation, atol=1e-9)
    np.testing.assert_allclose(fit.translation, inv.translation, atol=1e-8)
    err = metrics.pose_errors(est, true)
    assert err["mean_rotation_deg"] < 1e-5 and err["mean_center"] < 1e-8
    assert len(err["rotation_deg"]) == len(true)

    # a known perturbation: one camera turned 2 degrees about its optical axis
    c = est.frames[0]
    a = np.radians(2.0)
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    W = c.world_to_camera.copy()
    W[:3, :3] = Rz @ W[:3, :3]
    W[:3, 3] = Rz @ W[:3, 3]  # keep the center
    est2 = CameraSet((Camera(c.image, c.width, c.height, c.K, W),) + est.frames[1:])
    err2 = metrics.pose_errors(est2, true)
    assert err2["rotation_deg"][0] == pytest.approx(2.0, abs=1e-6)
    assert err2["mean_center"] < 1e-8


def test_pose_errors_need_common_views():
    a = _ring_cameras(4)
    b = CameraSet(tuple(Camera(f"images/x{i}.png", c.width, c.height, c.K, c.world_to_camera) for i, c in enumerate(a)))
    with pytest.raises(metrics.MetricsError, match="at least 3 views"):
        metrics.pose_errors(a, b)


def test_chamfer_identical_and_scaled_spheres():
    gt = _sphere(radius=0.5)
    same = metrics.chamfer(gt, gt, n_samples=20_000)
    assert same["accuracy"] < 1e-6 and same["completeness"] < 1e-6
    assert same["unit"] == pytest.approx(1.0, rel=1e-3)
    # concentric spheres: every distance is |r1 - r2|, divided by the gt bbox side 2 * 0.5
    big = _sphere(radius=0.55)
    r = metrics.chamfer(big, gt, n_samples=20_000)
    # the polygonal spheres are slightly inside the true ones: allow the chord error
    assert r["accuracy"] == pytest.approx(0.05, abs=2e-3)
    assert r["completeness"] == pytest.approx(0.05, abs=2e-3)
    assert r["chamfer"] == pytest.approx(0.5 * (r["accuracy"] + r["completeness"]))
    # the unit is the gt bbox: doubling everything leaves the numbers unchanged
    r2 = metrics.chamfer(Mesh(big.v_pos * 2, big.t_pos_idx), Mesh(gt.v_pos * 2, gt.t_pos_idx), n_samples=20_000)
    assert r2["accuracy"] == pytest.approx(r["accuracy"], rel=0.02)


def test_chamfer_partial_reconstruction_is_incomplete_but_accurate():
    gt = _sphere(radius=0.5)
    keep = gt.v_pos[gt.t_pos_idx].mean(1)[:, 2] > 0  # the upper half only
    half = Mesh(gt.v_pos, gt.t_pos_idx[keep])
    r = metrics.chamfer(half, gt, n_samples=20_000)
    assert r["accuracy"] < 1e-6
    # a lower-hemisphere point at angle p below the equator is 2 r sin(p / 2) from the rim;
    # area-uniform mean over the hemisphere: r * int 2 sin(p/2) cos(p) dp = 0.5523 r; half of
    # the gt samples are on the kept half (distance 0); unit = 2 r
    assert r["completeness"] == pytest.approx(0.5 * 0.5523 * 0.5, rel=0.03)


def test_chamfer_with_similarity():
    rng = np.random.default_rng(3)
    gt = _sphere(radius=0.5, center=(0.1, 0.2, 0.3))
    sim = metrics.Similarity(3.0, _random_rotation(rng), np.array([1.0, 2.0, 3.0]))
    moved = Mesh(sim.apply(gt.v_pos), gt.t_pos_idx)
    r = metrics.chamfer(moved, gt, similarity=sim.inverse(), n_samples=10_000)
    assert r["accuracy"] < 1e-6 and r["completeness"] < 1e-6


def test_chamfer_rejects_empty_mesh():
    gt = _sphere()
    with pytest.raises(metrics.MetricsError, match="no area"):
        metrics.chamfer(Mesh(np.zeros((3, 3)), np.array([[0, 1, 2]])), gt)


def test_image_rmse_known_value_and_union_mask():
    a = np.zeros((4, 4, 3), np.float32)
    b = np.zeros((4, 4, 3), np.float32)
    b[0, 0] = 1.0  # sRGB 1 vs 0 on one pixel
    ma = np.zeros((4, 4), bool)
    mb = np.zeros((4, 4), bool)
    ma[0, 0] = True
    mb[1, 1] = True
    assert metrics.image_rmse(a, b, ma, mb) == pytest.approx(np.sqrt(0.5))  # 2 pixels in the union
    # values are encoded: linear 0.214 is sRGB ~0.5
    c = np.full((4, 4, 3), 0.21404114, np.float32)
    m = np.ones((4, 4), bool)
    assert metrics.image_rmse(c, a, m, m) == pytest.approx(0.5, abs=1e-4)
    # clipping: values above 1 count as 1
    assert metrics.image_rmse(a + 5.0, a + 1.0, m, m) == pytest.approx(0.0, abs=1e-7)
    assert metrics.image_rmse(a, a, m, m) == 0.0


def test_image_rmse_errors():
    a = np.zeros((4, 4, 3), np.float32)
    m = np.zeros((4, 4), bool)
    with pytest.raises(metrics.MetricsError, match="both masks are empty"):
        metrics.image_rmse(a, a, m, m)
    with pytest.raises(metrics.MetricsError, match="one shape"):
        metrics.image_rmse(a, a[:2], m, m)
    bad = a.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(metrics.MetricsError, match="NaN"):
        metrics.image_rmse(bad, a, ~m, m)


def test_seen_by_cameras_above_and_occlusion():
    """Points a camera sees: in its image, in front of it, nothing of the mesh between. A ring
    of cameras 34 degrees above a sphere's equator (7.2 radii away) sees it down to
    about 48 degrees below the equator (the cap a camera sees from distance D has angular radius
    arccos(r / D)): 87 % of the area; the bottom pole is seen by none."""
    gt = _sphere(radius=0.5)
    frames = [Camera(f"images/{i:04d}.png", 64, 48, intrinsics(64, 48, 40),
                     look_at([3 * np.cos(a), 3 * np.sin(a), 2.0], [0, 0, 0]))
              for i, a in enumerate(np.linspace(0, 2 * np.pi, 24, endpoint=False))]
    above = CameraSet(tuple(frames))
    poles = np.array([[0, 0, 0.5], [0, 0, -0.5]])
    assert metrics.seen_by(poles, gt, above).tolist() == [True, False]
    one = CameraSet((Camera("images/a.png", 64, 48, intrinsics(64, 48, 40), look_at([3, 0, 0], [0, 0, 0])),))
    a = np.radians(70)  # 70 degrees from the camera's direction: before the horizon at arccos(0.5 / 3) = 80
    near_far = np.array([[0.5, 0, 0], [-0.5, 0, 0], [0.5 * np.cos(a), 0, 0.5 * np.sin(a)], [0, 0, 0.5]])
    # facing it, behind the sphere, near its rim, beyond the horizon (the top pole from the side)
    assert metrics.seen_by(near_far, gt, one).tolist() == [True, False, True, False]
    assert not metrics.seen_by(np.array([[0.0, 0.0, 5.0]]), gt, one).any()  # outside its image
    same = metrics.seen_chamfer(gt, gt, above, n_samples=20_000)
    assert same["accuracy_seen"] < 1e-6 and same["completeness_seen"] < 1e-6
    assert same["seen_fraction"] == pytest.approx(0.87, abs=0.03)


def test_seen_chamfer_leaves_out_what_no_camera_sees():
    """A reconstruction wrong only under the object (the bottom cap pushed down by 20 % of the
    unit) is wrong in chamfer's whole-surface numbers and right over the surface the cameras
    above see; a similarity is applied as in chamfer."""
    gt = _sphere(radius=0.5)
    frames = [Camera(f"images/{i:04d}.png", 64, 48, intrinsics(64, 48, 40),
                     look_at([3 * np.cos(a), 3 * np.sin(a), 2.0], [0, 0, 0]))
              for i, a in enumerate(np.linspace(0, 2 * np.pi, 24, endpoint=False))]
    above = CameraSet(tuple(frames))
    v = gt.v_pos.copy()
    v[v[:, 2] < -0.45, 2] -= 0.2
    rec = Mesh(v, gt.t_pos_idx)
    whole = metrics.chamfer(rec, gt, n_samples=50_000)
    seen = metrics.seen_chamfer(rec, gt, above, n_samples=50_000)
    assert whole["accuracy"] > 3e-3 and whole["completeness"] > 1e-3
    assert seen["accuracy_seen"] < 0.05 * whole["accuracy"] and seen["completeness_seen"] < 1e-4
    sim = metrics.Similarity(2.0, _random_rotation(np.random.default_rng(1)), np.array([0.3, -1.0, 2.0]))
    moved = Mesh((rec.v_pos - sim.translation) @ sim.rotation / sim.scale, rec.t_pos_idx)  # sim maps it back
    again = metrics.seen_chamfer(moved, gt, above, similarity=sim, n_samples=50_000)
    assert again["accuracy_seen"] == pytest.approx(seen["accuracy_seen"], abs=2e-5)
    with pytest.raises(metrics.MetricsError, match="no camera"):
        far = CameraSet((Camera("images/a.png", 64, 48, intrinsics(64, 48, 40), look_at([0, 0, 9], [0, 0, 20])),))
        metrics.seen_chamfer(gt, gt, far, n_samples=1000)
