"""A plain table (no texture): its pixels from the flash's shading of the plane (recon.masks.plain).

The scenes are ray-cast here in numpy, with no renderer: a ball standing on a plane, lit by a
flash at each camera (cos / r^2), in linear units. The plane is plain (one albedo), or wooden
(the generator's table texture), or missing; the photos are raised to a power where a tone
curve is meant.
"""

import functools
import json

import numpy as np
import pytest

from recon.io.cameras import Camera, CameraSet, intrinsics, look_at, save_cameras
from recon.io.images import read_mask, write_exr
from recon.masks import run_view_masks
from recon.masks.plain import PlainSettings, fit_plain_table, object_mask, plain_table
from recon.support import SupportPlane
from recon.synth.tabletop import table_texture

RADIUS = 0.5
CENTER = np.array([0.0, 0.0, RADIUS])  # a ball standing on the plane z = 0
PLANE = SupportPlane(np.array([0.0, 0.0, 1.0]), 0.0)
TABLE_RGB = np.array([0.58, 0.55, 0.50])
BALL_RGB = np.array([0.15, 0.35, 0.7])


def cameras(n=12, width=320, height=240, distance=3.2):
    frames = []
    for k in range(n):
        az = 2 * np.pi * k / n
        el = np.radians([20.0, 35.0, 50.0][k % 3])
        eye = CENTER + distance * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        frames.append(Camera(f"images/{k:04d}.png", width, height, intrinsics(width, height, 50.0),
                             look_at(eye, CENTER)))
    return CameraSet(tuple(frames), light_known=False)


@functools.lru_cache(maxsize=2)
def _wood(table_half):
    return table_texture(512, table_half, seed=4)


def render(cam, table="plain", power=1.0, table_half=4.0):
    """(H, W, 3) linear image and the ball's (H, W) true mask."""
    j, i = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    d = np.stack([j, i, np.ones_like(j)], -1) @ (cam.camera_to_world[:3, :3] @ np.linalg.inv(cam.K)).T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    c = cam.center
    # the ball
    oc = c - CENTER
    b = d @ oc
    disc = b**2 - (oc @ oc - RADIUS**2)
    t_ball = np.where(disc > 0, -b - np.sqrt(np.maximum(disc, 0)), np.inf)
    t_ball = np.where(t_ball > 0, t_ball, np.inf)
    # the plane
    t_plane = np.where(d[..., 2] < -1e-9, -c[2] / np.where(d[..., 2] < -1e-9, d[..., 2], -1.0), np.inf)
    ball = t_ball < t_plane
    img = np.zeros((cam.height, cam.width, 3))
    X = c + np.where(ball, t_ball, 0)[..., None] * d
    n = (X - CENTER) / RADIUS
    img[ball] = BALL_RGB * (np.clip(-(d[ball] * n[ball]).sum(-1), 0, 1) / t_ball[ball] ** 2)[:, None]
    on = ~ball & np.isfinite(t_plane)
    P = c + np.where(on, t_plane, 0)[..., None] * d
    on &= (np.abs(P[..., 0]) < table_half) & (np.abs(P[..., 1]) < table_half)
    if table == "plain":
        albedo = np.broadcast_to(TABLE_RGB, P.shape)
    elif table == "wood":
        tex = _wood(table_half)
        u = np.clip(((P[..., 0] + table_half) / (2 * table_half) * 512).astype(int), 0, 511)
        v = np.clip(((table_half - P[..., 1]) / (2 * table_half) * 512).astype(int), 0, 511)
        albedo = tex[v, u]
    else:
        on[:] = False
        albedo = np.zeros_like(P)
    img[on] = albedo[on] * (c[2] / t_plane[on] ** 3)[:, None]  # cos / r^2 = h / r^3
    img = 4.0 * img
    return np.clip(img, 0, 1) ** power, ball


def ball_points(count=400, seed=0):
    """Sparse points on the ball's upper three quarters (what SfM sees of it)."""
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(count * 3, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v = v[v[:, 2] > -0.5][:count]
    return CENTER + RADIUS * v


def stage_inputs(root, views, cams, lit_masks=False):
    """The views as EXRs in ``views`` (with ``masks/``: the whole lit image, as flash-falloff
    masks of a plain table are), ``root/cameras.json`` and ``root/points.ply`` (the ball's points
    only, as SfM finds on a plain table); returns the true masks by stem."""
    from recon.io.images import write_mask

    (views / "masks").mkdir(parents=True, exist_ok=True)
    truth = {}
    for c in cams:
        img, ball = render(c)
        write_exr(views / f"{c.stem}.exr", img.astype(np.float32))
        if lit_masks:
            write_mask(views / "masks" / f"{c.stem}.png", img.max(-1) > 0)
        truth[c.stem] = ball
    save_cameras(root / "cameras.json", cams)
    pts = ball_points()
    (root / "points.ply").write_text("ply\nformat ascii 1.0\nelement vertex %d\nproperty float x\nproperty float y\n"
                                     "property float z\nend_header\n" % len(pts) + "".join(f"{x} {y} {z}\n" for x, y, z in pts))
    return truth


@pytest.mark.parametrize("power", [1.0, 2.2])
def test_a_plain_table_is_found_and_its_pixels_are_the_table(power):
    cams = cameras()
    shots = [render(c, "plain", power) for c in cams]
    model, pixels = fit_plain_table([s for s, _ in shots], cams, PLANE)
    assert model.plain, model.reason
    assert model.slope == pytest.approx(power, rel=0.1)  # a tone curve scales the exponent
    chroma = TABLE_RGB ** power / (TABLE_RGB ** power @ [0.2126, 0.7152, 0.0722])
    np.testing.assert_allclose(model.chroma, chroma, rtol=0.03)
    for (img, ball), px in zip(shots, pixels, strict=True):
        assert px.shape == ball.shape  # the working size is above these photos' size
        lit_table = ~ball & (img.max(-1) > 0)
        assert not (px & ball).any()  # never the ball
        assert px[lit_table].mean() > 0.9


def test_a_wooden_table_and_a_void_are_not_plain():
    cams = cameras()
    for table in ("wood", "none"):
        model, pixels = fit_plain_table([render(c, table)[0] for c in cams], cams, PLANE)
        assert not model.plain, model.reason
        assert not any(p.any() for p in pixels)


def test_extremes_give_no_table_and_no_nan():
    cams = cameras(n=6)
    for img in (np.zeros((240, 320, 3)), np.ones((240, 320, 3)), np.full((240, 320, 3), np.nan)):
        model, pixels = fit_plain_table([img] * len(cams), cams, PLANE)
        assert not model.plain and np.isfinite(model.slope) and np.isfinite(model.gain).all()
    # a plane the cameras do not see
    model, _ = fit_plain_table([render(c)[0] for c in cams], cams, SupportPlane(np.array([0.0, 0.0, 1.0]), -50.0))
    assert not model.plain


def test_plain_table_from_the_points_when_no_plane_is_known():
    cams = cameras()
    pixels, info = plain_table(ball_points(), [render(c)[0] for c in cams], cams)
    assert pixels is not None and info["plain"], info["reason"]
    pixels, info = plain_table(ball_points(), [render(c, "wood")[0] for c in cams], cams)
    assert pixels is None and not info["plain"]


def test_object_mask_keeps_the_object_its_openings_and_fills_specks():
    img = np.full((100, 100, 3), 0.5)
    img[:10] = 0.0  # the dark background beyond the table
    table = np.ones((100, 100), bool)
    table[:10] = False
    table[20:80, 20:80] = False  # the object
    table[30, 30] = True  # a speck of the object the model took for table: filled
    table[45:60, 45:60] = True  # an opening through the object (6 % of it): kept
    table[90, 90] = False  # a speck of table the model missed: dropped
    table[12, :] = False  # the table's far edge, a line: opened away
    out, info = object_mask(img, table, PlainSettings(close_px=0, open_px=1, edge_px=3))
    # the table's pixels stop short of the outline: at the table's size the mask shrinks by 2 px
    assert out[30, 30] and not out[45:60, 45:60].any() and not out[90, 90] and not out[:15].any()
    assert out[22:78, 22:78].sum() == out.sum()
    assert abs(int(out.sum()) - (56 * 56 - 19 * 19)) <= 12  # the opening and the erosion round the corners
    assert info["coverage"] == pytest.approx(out.mean())


def test_masks_stage_takes_a_plain_table_out_of_the_flash_falloff_masks(tmp_path):
    """No plane in the points (all on the ball): the flash-falloff masks would hold the lit table;
    with the plain table's pixels taken out they are the ball's silhouettes."""
    cams = cameras()
    views = tmp_path / "views"
    truth = stage_inputs(tmp_path, views, cams)
    info = run_view_masks(views, tmp_path / "cameras.json", tmp_path / "masks", points=tmp_path / "points.ply")
    assert not info["plane"]["found"] and info["plane"]["plain_table"]["plain"]
    assert info["method"].startswith("flash_falloff_plain_table")
    ious = []
    for c in cams:
        m = read_mask(tmp_path / "masks" / f"{c.stem}.png") > 0.5
        t = truth[c.stem]
        ious.append((m & t).sum() / (m | t).sum())
    assert min(ious) > 0.85 and np.median(ious) > 0.9, ious
    summary = json.loads((tmp_path / "masks" / "masks.json").read_text())
    assert summary["plane"]["plain_table"]["plain"]
    assert not (tmp_path / "masks" / "plane.json").exists()  # the object stays in the void
    # the same without the table model: the masks take the lit table in
    plain_off = run_view_masks(views, tmp_path / "cameras.json", tmp_path / "off", points=tmp_path / "points.ply",
                               plain_settings=PlainSettings(min_explained=0.99))
    assert not plain_off["method"].startswith("flash_falloff_plain_table")
    off = [(read_mask(tmp_path / "off" / f"{c.stem}.png") > 0.5) for c in cams]
    assert np.median([(m & truth[c.stem]).sum() / (m | truth[c.stem]).sum() for m, c in zip(off, cams, strict=True)]) < 0.6


def test_poses_stage_without_a_plane_in_the_points_uses_the_plain_table(tmp_path):
    """After SfM (recon.poses.stage): no plane in the points, so the masks stage's masks (here the
    whole lit image, as flash-falloff masks of a plain table are) would be kept; the plain table's
    model replaces them with the ball's silhouettes, and no plane.json is written."""
    from recon.poses.stage import _support_plane_masks

    cams = cameras()
    truth = stage_inputs(tmp_path, tmp_path / "undistorted", cams, lit_masks=True)
    info = _support_plane_masks(tmp_path, None)
    assert not info["found"] and info["plain_table"]["plain"], info
    assert not (tmp_path / "plane.json").exists()
    ious = [((m := read_mask(tmp_path / "undistorted" / "masks" / f"{c.stem}.png") > 0.5) & truth[c.stem]).sum()
            / (m | truth[c.stem]).sum() for c in cams]
    assert min(ious) > 0.85 and np.median(ious) > 0.9, ious


def test_poses_stage_falls_back_to_the_plain_table_when_the_tabletop_masks_take_it(tmp_path):
    """A plain desk where SfM still finds a few points (enough for a plane): the tabletop masks,
    which need the table's texture, take the table, and the check against the table's points
    (recon.masks.views.table_points_share: the share of them inside the masks, over the views'
    frames) refuses them. The plain table's masks are then used, not the flash-falloff masks (a
    vase on a plain desk: IoU 0.15 against the truth before)."""
    import recon.poses.stage as stage

    cams = cameras()
    truth = stage_inputs(tmp_path, tmp_path / "undistorted", cams, lit_masks=True)
    rng = np.random.default_rng(3)
    r, a = rng.uniform(1.2, 2.5, 150), rng.uniform(0, 2 * np.pi, 150)
    table = np.stack([r * np.cos(a), r * np.sin(a), np.zeros(150)], 1)
    pts = np.concatenate([ball_points(), table])
    (tmp_path / "points.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex %d\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
        % len(pts) + "".join(f"{x} {y} {z}\n" for x, y, z in pts))
    info = stage._support_plane_masks(tmp_path, None)
    assert not info["found"] and "table's points" in info["reason"], info
    assert info["plain_table"]["plain"], info["plain_table"]
    assert not (tmp_path / "plane.json").exists()
    ious = [((m := read_mask(tmp_path / "undistorted" / "masks" / f"{c.stem}.png") > 0.5) & truth[c.stem]).sum()
            / (m | truth[c.stem]).sum() for c in cams]
    assert min(ious) > 0.85 and np.median(ious) > 0.9, ious


def _with_table_points(tmp_path, count=150, seed=3):
    rng = np.random.default_rng(seed)
    r, a = rng.uniform(1.2, 2.5, count), rng.uniform(0, 2 * np.pi, count)
    table = np.stack([r * np.cos(a), r * np.sin(a), np.zeros(count)], 1)
    pts = np.concatenate([ball_points(), table])
    (tmp_path / "points.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex %d\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
        % len(pts) + "".join(f"{x} {y} {z}\n" for x, y, z in pts))


def test_masks_that_took_the_table_after_every_fallback_stop_and_say_what_to_do(tmp_path):
    """A table in the points, tabletop masks that take it (refused), and no plain table's model
    (switched off here, as on a textured table it finds none): the flash-falloff masks hold the lit
    table around the ball. Before, they were used and every later stage made an asset of the table
    (a plain box on a wooden table by SfM: final accuracy 0.44 of its size, "success"). Now the masks
    stage stops, names the share of the table's points in them and what to do, and writes nothing."""
    from recon.masks.common import MaskError
    from recon.masks.views import refuse_masks_holding_the_table

    cams = cameras()
    views = tmp_path / "views"
    truth = stage_inputs(tmp_path, views, cams)
    _with_table_points(tmp_path)
    with pytest.raises(MaskError, match=r"the masks hold the table: \d+% of the table's points.*masks/<stem>.png"):
        run_view_masks(views, tmp_path / "cameras.json", tmp_path / "masks", points=tmp_path / "points.ply",
                       plain_settings=PlainSettings(min_explained=0.99))
    assert not (tmp_path / "masks").exists()
    # the check itself: the ball's true silhouettes hold only the table's points it hides (10-36 % measured
    # on tabletop captures), the whole frame all of them
    from recon.io.mesh import read_points

    pts = read_points(tmp_path / "points.ply")
    assert refuse_masks_holding_the_table(pts, PLANE, cams, truth) < 0.36
    with pytest.raises(MaskError, match="100%"):
        refuse_masks_holding_the_table(pts, PLANE, cams, {s: np.ones_like(m) for s, m in truth.items()})


def test_the_objects_foot_on_the_plane_is_not_counted_as_the_tables_points():
    """The object's foot touches the table: its points lie on the plane too, and every right mask
    holds them. A bell in 1600-px photos had 86 of its 97 points on the plane there, and its right
    masks were refused for holding 70 % of "the table's points". Points of the plane next to the
    object's low standing points are left out (0.02 of the cameras' spread) by the tabletop masks'
    check; the last check of the flash-falloff masks counts them (``foot=0``)."""
    from recon.masks.views import refuse_masks_holding_the_table, table_points_share

    cams = cameras()
    rng = np.random.default_rng(7)
    r, a = rng.uniform(1.2, 2.5, 150), rng.uniform(0, 2 * np.pi, 150)
    table = np.stack([r * np.cos(a), r * np.sin(a), np.zeros(150)], 1)
    a = rng.uniform(0, 2 * np.pi, 300)
    foot = np.stack([0.4 * np.cos(a), 0.4 * np.sin(a), np.zeros(300)], 1)  # under the ball's overhang
    masks = {c.stem: render(c)[1] for c in cams}  # the ball's true silhouettes
    alone = table_points_share(np.concatenate([ball_points(), table]), PLANE, cams, masks)
    with_foot = np.concatenate([ball_points(), table, foot])
    counted = table_points_share(with_foot, PLANE, cams, masks, foot=0.0)
    assert counted > alone + 0.2  # the foot, inside every mask, counted as table
    assert table_points_share(with_foot, PLANE, cams, masks) == pytest.approx(alone, abs=0.03)
    # masks that took the table still hold its points
    assert table_points_share(with_foot, PLANE, cams, {s: np.ones_like(m) for s, m in masks.items()}) == 1.0
    # the falloff masks' last check counts the foot
    assert refuse_masks_holding_the_table(with_foot, PLANE, cams, masks) == pytest.approx(counted)
