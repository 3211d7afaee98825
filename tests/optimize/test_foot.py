"""The foot zone of tabletop masks (recon.optimize.foot): which pixels leave the image term."""

import json

import numpy as np
import pytest

from recon.io.cameras import Camera, look_at
from recon.io.mesh import Mesh
from recon.optimize.foot import FootZone, foot_zone
from recon.support import SupportPlane
from recon.synth.shapes import icosphere

PLANE = SupportPlane.through([0, 0, 0], [0, 0, 1])
W, H = 160, 120


def _ball() -> Mesh:
    """A ball of radius 1 resting on the plane z = 0: it overhangs its foot everywhere."""
    m = icosphere(4)
    return Mesh(m.v_pos / np.linalg.norm(m.v_pos, axis=1, keepdims=True) + [0, 0, 1], m.t_pos_idx)


def _camera(stem: str, elevation_deg: float, dist: float = 6.0) -> Camera:
    e = np.radians(elevation_deg)
    eye = [dist * np.cos(e), 0.0, 1.0 + dist * np.sin(e)]
    K = np.array([[150.0, 0, W / 2], [0, 150.0, H / 2], [0, 0, 1]])
    return Camera(f"images/{stem}.png", W, H, K, look_at(eye, [0, 0, 1.0]))


def _silhouette(mesh: Mesh, cam: Camera) -> np.ndarray:
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.v_pos.astype(np.float32)), o3d.core.Tensor(mesh.t_pos_idx.astype(np.uint32)))
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    d = (np.stack([jj.ravel(), ii.ravel(), np.ones(jj.size)], 1) @ np.linalg.inv(cam.K).T) @ cam.world_to_camera[:3, :3]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rays = np.concatenate([np.broadcast_to(cam.center, d.shape), d], 1).astype(np.float32)
    return np.isfinite(scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()).reshape(H, W)


def _hull(ball: Mesh, band: float) -> Mesh:
    """The tabletop hull of the ball: below the band, the section at its top extruded down to the
    table (a skirt under the overhang, as recon.masks.vote.carve makes it)."""
    v = ball.v_pos.copy()
    r = np.sqrt(1.0 - (1.0 - band) ** 2)
    low = v[:, 2] < band
    xy = np.linalg.norm(v[low, :2], axis=1, keepdims=True)
    v[low, :2] = np.where(xy > 1e-9, v[low, :2] / np.maximum(xy, 1e-12) * r, 0.0)
    return Mesh(v, ball.t_pos_idx)


def test_foot_pixels_near_the_silhouette_leave_the_loss_and_the_rest_stay():
    ball = _ball()
    hull = _hull(ball, 0.2)
    cams = [_camera("low", 10.0), _camera("high", 60.0), _camera("given", 10.0)]
    true = np.stack([_silhouette(ball, c) for c in cams])
    masks = np.stack([_silhouette(hull, c) for c in cams])  # the masks hold the skirt
    zone = FootZone(PLANE, 0.2, hull, frozenset({"low", "high"}))
    w = zone.weights(cams, masks.astype(np.float32))
    assert w.shape == masks.shape and w.dtype == np.float32 and set(np.unique(w)) <= {0.0, 1.0}
    low = w[0]
    skirt = masks[0] & ~true[0]
    assert skirt.sum() > 20
    assert (low[skirt] == 0).mean() > 0.9  # the table the masks took in under the overhang: out
    # the ball's top half, its middle row and the background far from it stay in
    rows = np.flatnonzero(masks[0].any(1))
    assert np.all(low[:(rows[0] + rows[-1]) // 2 + 1] == 1)
    assert low[:, :10].min() == 1 and low[:, -10:].min() == 1 and np.all(low[rows[-1] + 12:] == 1)
    # from above the foot hides under the ball: most of the mask stays in
    assert (w[1][masks[1]] == 1).mean() > 0.9
    # a view whose masks were given is trusted whole
    assert np.all(w[2] == 1)
    # with the photos: the ball's own pixels at its foot (its colour, not the table's) stay in;
    # the skirt, which shows the table, still leaves
    table, ball_rgb = np.array([0.5, 0.35, 0.2], np.float32), np.array([0.2, 0.3, 0.6], np.float32)
    rng = np.random.default_rng(0)
    photos = np.where(true[..., None], ball_rgb, table) * rng.uniform(0.3, 1.0, true.shape + (1,)).astype(np.float32)
    wc = zone.weights(cams, masks.astype(np.float32), photos)
    assert (wc[0][skirt] == 0).mean() > 0.9
    assert (w[0][true[0]] == 0).any() and np.all(wc[0][true[0]] == 1)
    assert np.all(wc[w == 1] == 1)  # the colour test only keeps pixels
    # the classes behind the weights (loss.uncertain_foot_mode: background makes TABLE background)
    from recon.optimize.foot import DOUBT, KEEP, OUTSIDE, TABLE

    cls = zone.classes(cams, masks.astype(np.float32), photos)
    assert np.array_equal(cls > KEEP, wc < 1)
    assert (cls[0][skirt] == TABLE).mean() > 0.9 and np.all(cls[0][true[0]] == KEEP)
    assert (cls[0] == OUTSIDE).any() and not (masks[0] & (cls[0] == OUTSIDE)).any()  # the table beside it
    dark = photos.copy()
    dark[0][skirt] = 0.0  # too dark to tell: doubted, never made background
    cls_dark = zone.classes(cams, masks.astype(np.float32), dark)
    assert np.all(cls_dark[0][skirt & (cls[0] == TABLE)] == DOUBT)
    assert set(np.unique(zone.classes(cams, masks.astype(np.float32)))) <= {KEEP, DOUBT, OUTSIDE}  # no photos
    # a weight instead of leaving them out (loss.uncertain_foot_weight)
    w3 = FootZone(PLANE, 0.2, hull, frozenset({"low", "high"}), 0.3).weights(cams, masks.astype(np.float32))
    assert np.array_equal(w3 == 1, w == 1) and set(np.unique(w3)) == {np.float32(0.3), 1.0}


def test_table_like_by_chromaticity_not_brightness():
    from recon.optimize.foot import table_like

    rng = np.random.default_rng(1)
    wood = np.array([0.5, 0.35, 0.2]) * rng.uniform(0.2, 1.0, (200, 1)) * (1 + 0.02 * rng.standard_normal((200, 3)))
    pix = np.array([[0.05, 0.035, 0.02], [1.0, 0.7, 0.4], [0.2, 0.3, 0.6], [0.0, 0.0, 0.0]])
    assert table_like(wood, pix).tolist() == [True, True, False, True]  # dim or bright wood; blue; too dark to tell
    assert table_like(wood[:5], pix).all()  # too few table pixels to tell: all doubted


def test_settings_bounds():
    from recon.optimize.settings import LossSettings

    assert LossSettings().uncertain_foot == 1.5 and LossSettings().uncertain_foot_weight == 0.0
    assert LossSettings().uncertain_foot_mode == "background"
    for bad in ({"uncertain_foot": -0.1}, {"uncertain_foot": 11.0}, {"uncertain_foot_weight": 1.5},
                {"uncertain_foot_weight": float("nan")}, {"uncertain_foot_mode": "carve"}):
        with pytest.raises(ValueError, match="uncertain_foot"):
            LossSettings(**bad)


def test_a_flared_foot_keeps_its_pixels():
    """A foot wider than what stands on it (a bell's lip, a cone on its base) is not under an
    overhang: the masks there are no extrusion of a wider section, and every pixel stays in."""
    ball = _ball()
    v = ball.v_pos.copy()
    xy = np.linalg.norm(v[:, :2], axis=1, keepdims=True)
    r = 1.0 - 0.3 * v[:, 2:3]  # radius 1 on the table, 0.4 at the top
    v[:, :2] = np.where(xy > 1e-9, v[:, :2] / np.maximum(xy, 1e-12) * r, 0.0)
    cone = Mesh(v, ball.t_pos_idx)
    cams = [_camera("low", 10.0), _camera("mid", 35.0)]
    masks = np.stack([_silhouette(cone, c) for c in cams]).astype(np.float32)
    w = FootZone(PLANE, 0.2, cone, frozenset({"low", "mid"})).weights(cams, masks)
    assert (w < 1).sum() <= 0.005 * masks.sum()  # (a few rim pixels, where the ray grazes the base)
    # the same zone on the ball's skirt does doubt pixels (the control)
    hull = _hull(ball, 0.2)
    m2 = np.stack([_silhouette(hull, c) for c in cams]).astype(np.float32)
    assert (FootZone(PLANE, 0.2, hull, frozenset({"low", "mid"})).weights(cams, m2) == 0).any()


def test_cameras_level_with_the_table_give_no_nan():
    ball = _ball()
    cams = [_camera("level", 0.0, dist=4.0), _camera("below", -5.0, dist=4.0)]
    masks = np.stack([_silhouette(ball, c) for c in cams]).astype(np.float32)
    w = FootZone(PLANE, 0.2, ball, frozenset({"level", "below"})).weights(cams, masks)
    assert np.all(np.isfinite(w)) and (w == 0).any()


def test_zone_only_for_tabletop_masks_with_a_band(tmp_path):
    ball = _ball()
    p = tmp_path / "masks.json"
    summary = {"method": "tabletop", "views": {"a": {"source": "tabletop"}, "b": {"source": "given"}},
               "segment": {"hull": {"parallax_band": 0.1, "height": 0.5}}}  # another frame
    p.write_text(json.dumps(summary))
    z = foot_zone(p, PLANE, ball, 1.5)
    # the band's share of the height (0.2) of the ball's height (2) above the table, times 1.5
    assert z is not None and z.stems == {"a"} and z.height == pytest.approx(0.6)
    assert foot_zone(p, None, ball, 1.0) is None  # no table
    assert foot_zone(p, PLANE, ball, 0.0) is None  # off
    assert foot_zone(tmp_path / "absent.json", PLANE, ball, 1.0) is None
    summary["views"] = {"a": {"source": "given"}}
    p.write_text(json.dumps(summary))
    assert foot_zone(p, PLANE, ball, 1.0) is None  # every mask given
    summary.update(views={"a": {"source": "tabletop"}}, segment=None)
    p.write_text(json.dumps(summary))
    assert foot_zone(p, PLANE, ball, 1.0) is None  # no band recorded


@pytest.mark.parametrize("shade", [0.2, 1.8])
def test_an_object_in_the_tables_colours_is_not_made_background(shade):
    """A ball in the table's own colour (wood on wood): chromaticity cannot tell its foot from the
    table, but its surface there, turned away from or towards the flash, is darker or brighter
    than the table beside it at the same distance. Its pixels stay in doubt, never background;
    the skirt, which shows the table, is still made background."""
    from recon.optimize.foot import DOUBT, TABLE

    ball = _ball()
    hull = _hull(ball, 0.2)
    cams = [_camera("low", 10.0), _camera("high", 60.0)]
    true = np.stack([_silhouette(ball, c) for c in cams])
    masks = np.stack([_silhouette(hull, c) for c in cams])
    zone = FootZone(PLANE, 0.2, hull, frozenset({"low", "high"}))
    wood = np.array([0.5, 0.35, 0.2], np.float32)
    rng = np.random.default_rng(2)
    table = rng.uniform(0.6, 1.0, true.shape + (1,)).astype(np.float32)
    photos = wood * np.where(true[..., None], np.float32(shade), table)
    cls = zone.classes(cams, masks.astype(np.float32), photos)
    skirt = masks[0] & ~true[0]
    assert (cls[0][skirt] == TABLE).mean() > 0.9
    foot = true[0] & (cls[0] != 0)
    assert foot.sum() > 10 and np.all(cls[0][foot] == DOUBT)
    # the same ball in the table's brightness too: colours cannot tell it, and it is made background
    # (the limit of the test: docs/tabletop.md)
    same = wood * np.where(true[..., None], np.float32(0.8), table)
    assert (zone.classes(cams, masks.astype(np.float32), same)[0][foot] == TABLE).mean() > 0.9


def test_table_or_object_extremes():
    from recon.optimize.foot import DOUBT, KEEP, TABLE, table_or_object

    rng = np.random.default_rng(3)
    wood = np.array([0.5, 0.35, 0.2]) * rng.uniform(0.5, 1.0, (100, 1))
    pix = np.array([[0.35, 0.245, 0.14], [5.0, 3.5, 2.0], [0.2, 0.3, 0.6], [0.0, 0.0, 0.0], [1e-30, 0, 0]])
    assert table_or_object(wood, pix).tolist() == [TABLE, DOUBT, KEEP, DOUBT, DOUBT]
    assert np.all(table_or_object(wood[:5], pix) == DOUBT)  # too few table pixels to compare with
    assert table_or_object(np.zeros((100, 3)), pix).dtype == np.int8  # a black table: no NaN, no error
    assert table_or_object(wood, np.zeros((0, 3))).shape == (0,)
