"""Tabletop masks (recon.masks.tabletop, recon.masks.views): the object apart from the table, against the true silhouettes."""

import json
import logging

import numpy as np
import pytest
from _geometry_scene import icosphere, silhouette, synth_capture
from _tabletop_scene import TABLETOP_TEST, tabletop_capture

from recon import sections
from recon.masks import evidence as ev
from recon.masks import tabletop as sg
from recon.masks.common import MaskError, dilate
from recon.masks.geometry import flash_shading, neighbours, plane_homography, plane_points
from recon.masks.graphcut import graph_cut
from recon.masks.vote import carve, extrude_band, votes_needed
from recon.masks.views import run_tabletop_masks
from recon.io.cameras import load_cameras
from recon.io.images import read_exr, read_mask, write_exr, write_mask
from recon.io.mesh import Mesh
from recon.masks import derive_mask, run_masks
from recon.support import SupportPlane, load_plane
from recon.synth.capture import SynthSettings
from recon.synth.shapes import bell
from recon.synth.tabletop import table_texture, tabletop_cameras
from recon.synth.textures import bilinear_lookup


def _iou(a, b):
    return (a & b).sum() / max((a | b).sum(), 1)


@pytest.fixture(scope="module")
def mug(tmp_path_factory):
    return tabletop_capture(tmp_path_factory.getbasetemp())


@pytest.fixture(scope="module")
def mug_masks(mug, tmp_path_factory):
    """The tabletop masks of the mug capture with its true cameras; the plane comes from points
    triangulated in the views (not from gt/plane.json)."""
    out = tmp_path_factory.mktemp("segment") / "masks"
    summary = run_tabletop_masks(mug / "images", mug / "gt" / "cameras.json", out)
    return out, summary


@pytest.fixture(scope="module")
def table_only():
    """Cameras of a tabletop capture and exact renders of the bare table (Lambertian wood, the
    flash at each camera: I a_d / pi * h / r^3), no object."""
    s = sections.replace(SynthSettings(), **{**TABLETOP_TEST, "n_views": 16, "width": 192, "height": 144})
    cams = tabletop_cameras(s)
    plane = SupportPlane(np.array([0.0, 0.0, 1.0]), 0.8)
    half = s.tabletop.table_half_size
    return cams, plane, _render_table(cams, plane, table_texture(256, half, seed=4), half)


def _render_table(cams, plane, tex, half):
    """Exact renders of a bare Lambertian table of albedo map ``tex`` over [-half, half]^2."""
    images = []
    for cam in cams:
        P, hit = plane_points(cam, plane)
        uv = np.stack([(P[..., 0] + half) / (2 * half), (P[..., 1] + half) / (2 * half)], -1)
        a = bilinear_lookup(tex, uv)
        shade = flash_shading(cam.center, P, plane)
        on = hit & (np.abs(P[..., :2]) < half).all(-1)
        images.append(np.where(on[..., None], cams.light_intensity * a / np.pi * shade[..., None], 0.0)
                      .astype(np.float32))
    return images


# ---- geometry ----
def test_plane_homography_maps_plane_points():
    cams = tabletop_cameras(sections.replace(SynthSettings(), **{**TABLETOP_TEST, "n_views": 6}))
    plane = SupportPlane(np.array([0.1, -0.05, 1.0]), 0.8)
    rng = np.random.default_rng(0)
    pts = plane.project(rng.uniform(-1.5, 1.5, (50, 3)))
    ci, cj = cams.frames[0], cams.frames[3]
    H = plane_homography(ci, cj, plane)
    xi, _ = ci.project(pts)
    xj, _ = cj.project(pts)
    h = np.c_[xi - 0.5, np.ones(len(pts))] @ H.T  # OpenCV pixel coordinates
    np.testing.assert_allclose(h[:, :2] / h[:, 2:], xj - 0.5, atol=1e-6)


def test_plane_points_and_flash_shading():
    cams = tabletop_cameras(sections.replace(SynthSettings(), **{**TABLETOP_TEST, "n_views": 3}))
    plane = SupportPlane(np.array([0.0, 0.0, 1.0]), 0.8)
    cam = cams.frames[1]
    P, hit = plane_points(cam, plane)
    assert hit[-1].all()  # the bottom row sees the table
    np.testing.assert_allclose(plane.height(P[hit]), 0.0, atol=1e-9)
    xy, _ = cam.project(P[hit])
    j, i = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    np.testing.assert_allclose(xy, np.stack([j, i], -1)[hit], atol=1e-6)
    r = np.linalg.norm(P[hit] - cam.center, axis=1)
    mu = plane.height(cam.center) / r
    np.testing.assert_allclose(flash_shading(cam.center, P[hit], plane), mu / r**2)


def test_graph_cut_recovers_a_region():
    rng = np.random.default_rng(0)
    truth = np.zeros((60, 80), bool)
    truth[15:45, 20:60] = True
    p = np.clip(np.where(truth, 0.75, 0.25) + rng.normal(0, 0.25, truth.shape), 0.02, 0.98)
    guide = np.repeat((truth * 200 + 30).astype(np.uint8)[..., None], 3, 2)
    raw = p > 0.5
    cut = graph_cut(-np.log(p), -np.log(1 - p), guide, smoothness=2.0)
    assert (cut != truth).mean() < 0.2 * (raw != truth).mean()
    active = np.zeros_like(truth)
    active[:, :40] = True
    cut = graph_cut(-np.log(p), -np.log(1 - p), guide, smoothness=2.0, active=active)
    assert not cut[:, 40:].any() and _iou(cut, truth & active) > 0.95


def test_carve_tolerates_a_bad_view():
    """A sphere standing on the plane: the hull holds it even when one view's mask is empty, and
    its projection covers every silhouette."""
    cams = tabletop_cameras(sections.replace(SynthSettings(), **{**TABLETOP_TEST, "n_views": 12, "width": 96, "height": 72}))
    ball = icosphere(3)
    ball = Mesh(ball.v_pos * 0.6 + [0.0, 0.0, -0.2], ball.t_pos_idx)
    plane = SupportPlane(np.array([0.0, 0.0, 1.0]), 0.8)
    masks = [silhouette(ball, c) for c in cams]
    masks[4] = np.zeros_like(masks[4])
    hull = carve(masks, cams, plane, np.zeros(3), 1.5, 1.8, 48, 0.12)
    lo, hi = hull.bbox()
    np.testing.assert_allclose(lo, [-0.6, -0.6, -0.8], atol=2.5 * hull.step)
    np.testing.assert_allclose(hi, [0.6, 0.6, 0.4], atol=2.5 * hull.step)
    for cam, m in zip(cams, masks, strict=True):
        proj = hull.project(cam)
        if m.any():
            assert (m & ~proj).sum() <= 0.01 * m.sum()
            assert _iou(proj, m) > 0.75
    assert carve([np.zeros_like(m) for m in masks], cams, plane, np.zeros(3), 1.5, 1.8, 16, 0.12) is None
    # below the band the hull is the extrusion of its section at the band's height: the object
    # stands on the plane (at height 0.3 the ball's section has radius sqrt(0.6^2 - 0.3^2) = 0.52)
    banded = carve(masks, cams, plane, np.zeros(3), 1.5, 1.8, 48, 0.12, band=0.3)
    low = banded.points[plane.height(banded.points) < 0.3 - banded.step]
    r = np.linalg.norm(low[:, :2], axis=1)
    assert r.max() == pytest.approx(0.52, abs=2 * banded.step)
    assert len(banded.band) > 0 and plane.height(banded.band).max() < 0.3



def test_carve_stands_an_object_whose_foot_the_views_lost():
    """Just above the band the plane test sees little parallax, and a few views' chance agreement
    with the table can carve an object's lowest layers (a wooden vase on a wooden table: the
    masks stage stopped with "no object stands on the support plane"). A hull that comes within
    twice the band of the plane stands on it: its lowest section is extruded down. One floating
    farther up does not stand."""
    cams = tabletop_cameras(sections.replace(SynthSettings(), **{**TABLETOP_TEST, "n_views": 12, "width": 96,
                                                                 "height": 72}))
    plane = SupportPlane(np.array([0.0, 0.0, 1.0]), 0.8)
    ball = icosphere(3)

    def floating(gap):  # radius 0.6, its lowest point ``gap`` above the plane
        return Mesh(ball.v_pos * 0.6 + [0.0, 0.0, -0.2 + gap], ball.t_pos_idx)

    band = 0.1
    # 0.3 above the plane (grid step 0.0625): below the views' cone under the ball the lowest
    # layers hold nothing, and before the hull had to touch the plane to stand (None here)
    masks = [silhouette(floating(0.3), c) for c in cams]
    hull = carve(masks, cams, plane, np.zeros(3), 1.5, 1.8, 48, 0.12, band=band, standing=True)
    assert hull is not None
    h = plane.height(hull.points)
    assert h.min() < hull.step  # it reaches the plane ...
    assert h.max() == pytest.approx(1.5, abs=2.5 * hull.step)  # ... and keeps its top
    low = hull.points[h < 0.15]  # the extruded foot: the section at the lowest kept layer, small
    assert len(low) and np.linalg.norm(low[:, :2], axis=1).max() < 0.3
    for cam, m in zip(cams, masks, strict=True):  # the ball is all there
        assert (m & ~hull.project(cam)).sum() <= 0.01 * m.sum()
    high = [silhouette(floating(0.6), c) for c in cams]
    assert carve(high, cams, plane, np.zeros(3), 1.5, 1.8, 48, 0.12, band=band, standing=True) is None


def test_dark_pixels_count_as_background_only_beyond_the_lit_table():
    """A dark pixel whose ray meets the table where the flash lights it sees something dark
    standing on the table (a dark glaze), not the far background: only pixels beyond the lit
    table, or above the horizon, may say "nothing here"."""
    cams = tabletop_cameras(sections.replace(SynthSettings(), **{**TABLETOP_TEST, "n_views": 3}))
    plane = SupportPlane(np.array([0.0, 0.0, 1.0]), 0.8)
    cam = cams.frames[1]
    P, hit = plane_points(cam, plane)
    foot = plane.project(np.zeros(3))
    dist = np.linalg.norm(P - foot, axis=-1)
    table = hit & (dist < 2.0)  # the view sees lit table out to 2 units from the object
    far = sg.beyond_lit_table(cam, plane, table, foot)
    assert not far[table & (dist < 1.8)].any()
    assert far[~hit].all() and far[hit & (dist > 2.05)].all()
    # a view that sees too little table cannot tell: every dark pixel keeps its say
    assert sg.beyond_lit_table(cam, plane, np.zeros_like(table), foot).all()


def test_a_plain_glaze_unlike_the_table_is_in_the_objects_colour_model():
    """The cut's colour model of the object also learns the plain pixels deep inside the hull's
    silhouette (where the plane test says nothing) whose colour the table does not show. From
    the pixels with positive plane-test evidence alone it never saw a plain glaze of a colour
    found nowhere textured (the blue lip of a glazed bell), and near the outline the colour term
    gave that glaze to the table (IoU 0.78 here)."""
    rng = np.random.default_rng(0)
    H, W = 120, 160
    i, j = np.mgrid[:H, :W]
    disk = (i - 60) ** 2 + (j - 80) ** 2 < 45**2
    cap = disk & (i < 40)  # a textured orange cap: the plane test sees the object there
    img = np.empty((H, W, 3), np.float32)
    img[:] = [0.30, 0.18, 0.09]  # brown wood ...
    img *= rng.uniform(0.7, 1.3, (H, W, 1))  # ... with texture
    img[disk] = [0.03, 0.05, 0.15]  # a plain dark blue glaze
    img[cap] = np.array([0.60, 0.30, 0.08]) * rng.uniform(0.7, 1.3, (cap.sum(), 1))
    table = ~disk & (rng.random((H, W)) < 0.5)
    logodds = np.where(cap, 2.0, np.where(~disk, -2.0, 0.0)).astype(np.float32)
    m = sg.refine_view(img, disk, table, logodds, np.zeros((H, W), bool), 8)
    assert _iou(m, disk) > 0.97
    assert m[disk & ~cap].mean() > 0.97


def test_cross_check_keeps_a_lip_flaring_out_below_the_band():
    """The cross-check's hull is carved from the refined masks down to the plane: a bell's lip
    flaring out below the parallax band is in every true silhouette, and the cross-check keeps
    it (its hull extruded from the band's top cut the lip off in every view, up to 1.3 % of a
    silhouette here)."""
    cams = tabletop_cameras(sections.replace(SynthSettings(), **{**TABLETOP_TEST, "n_views": 12}))
    plane = SupportPlane(np.array([0.0, 0.0, 1.0]), 0.8)
    b = bell(3)
    b = Mesh(b.v_pos + [0.0, 0.0, -0.8 - b.v_pos[:, 2].min()], b.t_pos_idx)  # standing on the plane
    masks = [silhouette(b, c) for c in cams]
    band = 0.15  # the lip's radius: 0.95 on the plane, 0.84 at the band's top
    hull = carve(masks, cams, plane, np.zeros(3), 1.5, 1.8, 48, 0.12, band=band, standing=True)
    kept, hull2 = sg.cross_check(masks, cams, plane, hull, band)
    assert hull2 is not None
    for m, k in zip(masks, kept, strict=True):
        assert not (k & ~m).any()
        assert (m & ~k).sum() <= 0.002 * m.sum()


# ---- evidence and errors on the bare table ----
def test_bare_table_is_seen_as_table_and_holds_no_object(table_only):
    cams, plane, images = table_only
    logs = [ev.log_luminance(im) for im in images]
    nbrs = neighbours(cams, 6, 4.0, 70.0)
    for i in (0, 7):
        e = ev.table_evidence(logs, cams, plane, i, nbrs[i], [0.05, 0.1, 0.2, 0.4])
        P, hit = plane_points(cams.frames[i], plane)
        on = hit & (np.abs(P[..., :2]) < 3.0).all(-1)
        assert e["table"][on].mean() > 0.5
        C = ev.plane_difference(images, cams, plane, i, nbrs[i])
        assert np.median(C[on & np.isfinite(C)]) < 0.1
    with pytest.raises(sg.SegmentError, match=r"no object stands on the support plane.*0000.*What to try"):
        sg.segment_tabletop(images, cams, plane)


def test_plain_patch_is_never_table(table_only):
    """A plain surface matches whatever a warp lands on (the plane test's blind spot): without
    contrast the evidence says nothing, and a shading ramp across it is no contrast either."""
    cams, plane, images = table_only
    nbrs = neighbours(cams, 6, 4.0, 70.0)
    painted = []
    for im in images:
        h, w = im.shape[:2]
        j, i = np.meshgrid(np.arange(w), np.arange(h))
        disc = (j - w / 2) ** 2 + (i - h * 0.6) ** 2 < (0.2 * h) ** 2
        ramp = (0.4 + 0.3 * j / w)[..., None] * np.array([0.7, 0.6, 0.45])  # a lit glaze, shaded across
        painted.append(np.where(disc[..., None], ramp, im).astype(np.float32))
    logs = [ev.log_luminance(im) for im in painted]
    e = ev.table_evidence(logs, cams, plane, 3, nbrs[3], [0.05, 0.1, 0.2, 0.4])
    h, w = painted[3].shape[:2]
    j, i = np.meshgrid(np.arange(w), np.arange(h))
    inner = (j - w / 2) ** 2 + (i - h * 0.6) ** 2 < (0.2 * h - 7) ** 2  # windows inside the disc
    assert inner.sum() > 50 and not e["table"][inner].any() and not e["contrast"][inner].any()


def test_a_table_smooth_at_the_working_size_is_found_at_a_coarser_one(table_only):
    """A weakly textured table (grain wider than the windows: the torus capture of docs/masks.md)
    looks smooth to the sweep at the working size, which leaves most of it undecided; the sweep
    at half that size matches it. Its table pixels count only where the fine sweep is undecided,
    and a plain disc stays undecided at both."""
    import cv2

    cams, plane, _ = table_only
    half = 4.0
    rng = np.random.default_rng(5)
    grain = cv2.resize(rng.normal(size=(8, 8)).astype(np.float32), (512, 512), interpolation=cv2.INTER_CUBIC)
    tex = np.repeat((0.3 * np.exp(grain) / np.exp(grain).mean())[..., None], 3, -1)
    images = _render_table(cams, plane, tex, half)
    h, w = images[0].shape[:2]
    j, i = np.meshgrid(np.arange(w), np.arange(h))
    disc = (j - w / 2) ** 2 + (i - h * 0.6) ** 2 < (0.2 * h) ** 2
    images = [np.where(disc[..., None], np.float32([0.3, 0.25, 0.2]), im).astype(np.float32) for im in images]
    settings = ev.EvidenceSettings(work_size=192)  # the views' own size; the coarse sweep at 96
    coarse = ev.working_cameras(cams, 192 // settings.coarse)
    logs = [ev.log_luminance(im) for im in images]
    clogs = [ev.log_luminance(im, (c.width, c.height)) for im, c in zip(images, coarse, strict=True)]
    nbrs = neighbours(cams, 6, 4.0, 70.0)
    heights = [0.05, 0.1, 0.2, 0.4]
    for v in (0, 7):
        fine = ev.table_evidence(logs, cams, plane, v, nbrs[v], heights, settings)
        both = ev.with_coarse(fine, ev.table_evidence(clogs, coarse, plane, v, nbrs[v], heights, settings),
                              settings.coarse_erode)  # (H, W) bool
        P, hit = plane_points(cams.frames[v], plane)
        on = hit & (np.abs(P[..., :2]) < 3.0).all(-1) & ~dilate(disc, 6)
        assert fine["table"][on].mean() < 0.6 and both[on].mean() > fine["table"][on].mean() + 0.2
        assert both[on].mean() > 0.7  # measured: 0.75 and 0.73
        # a coarse window reaches 2 x 4 working pixels across the outline (it carves in the 3D vote
        # only, never the outlines): windows wholly inside the disc are never table
        inner = (j - w / 2) ** 2 + (i - h * 0.6) ** 2 < (0.2 * h - 2 * settings.window - 4) ** 2
        assert inner.sum() > 200 and not both[inner].any()
        assert (both >= fine["table"]).all()  # it only adds


def test_coarse_evidence_counts_only_where_the_fine_is_undecided():
    shape = (8, 12)
    fine = {"table": np.zeros(shape, bool), "contrast": np.ones(shape, bool), "z0": np.full(shape, 0.1, np.float32)}
    fine["contrast"][:, :6] = False  # left half: no contrast at the working size
    fine["z0"][:, :6] = np.nan
    coarse = {"table": np.ones((4, 6), bool)}
    out = ev.with_coarse(fine, coarse, 0)
    assert out[:, :6].all() and not out[:, 6:].any()
    coarse["table"][0, 0] = False  # erosion by one coarse pixel: the hole grows to its 3x3 neighbourhood
    out = ev.with_coarse(fine, coarse, 1)
    assert not out[:4, :4].any() and out[4:, :6].all() and not out[:, 6:].any()
    with pytest.raises(ValueError, match="coarse"):
        ev.EvidenceSettings(coarse=0)


def test_zncc_ignores_gain_and_offset():
    rng = np.random.default_rng(0)
    g = rng.normal(size=(40, 50)).astype(np.float32)
    valid = np.ones_like(g, bool)
    z = ev.zncc(g, ev.window_stats(g, 3), 2.5 * g + 7.0, valid, 3, 0.01)
    np.testing.assert_allclose(z[5:-5, 5:-5], 1.0, atol=1e-3)
    flat = np.full_like(g, 3.0)
    assert np.isnan(ev.zncc(flat, ev.window_stats(flat, 3), g, valid, 3, 0.01)).all()


def test_band_opens_a_hole_through_the_object_and_keeps_a_flared_base():
    """The band below the parallax height is the section at its top, less the openings that run
    through the object above it: a ring lying on the table whose band-top layer the views carved
    only in part (glaze-torus: 25-90 % of the hole's voxels there, all of them higher up) is open
    down to the plane; a lip flaring out under a narrower body keeps its section."""
    n, k_band, step, band = 40, 4, 0.05, 0.2
    u = (np.arange(n) - n / 2 + 0.5) * step
    r = np.hypot(*np.meshgrid(u, u, indexing="ij"))
    ring = np.zeros((n, n, 12), bool)
    ring[:, :, :] = ((r > 0.3) & (r < 0.9))[..., None]
    plug = (r <= 0.3) & (np.random.default_rng(0).random((n, n)) < 0.6)  # the band's top, carved in part
    ring[:, :, k_band] |= plug
    out = extrude_band(ring.copy(), k_band, step, band)
    assert not (out[:, :, :k_band + 1] & (r <= 0.3)[..., None]).any()  # open down to the plane
    np.testing.assert_array_equal(out[:, :, 0], (r > 0.3) & (r < 0.9))
    # a chance speck of 1 voxel inside a solid section above does not open the band
    solid = np.zeros((n, n, 12), bool)
    solid[:, :, :] = (r < 0.9)[..., None]
    solid[n // 2, n // 2, k_band + 1:] = False
    np.testing.assert_array_equal(extrude_band(solid.copy(), k_band, step, band)[:, :, 0], r < 0.9)
    # a bell: the lip at the band's top is wider than the body above it, and stays
    bell = np.zeros((n, n, 12), bool)
    bell[:, :, k_band:] = (r < 0.5)[..., None]
    bell[:, :, k_band] = r < 0.9
    np.testing.assert_array_equal(extrude_band(bell.copy(), k_band, step, band)[:, :, 0], r < 0.9)


def test_refine_opens_the_table_seen_deep_inside_the_silhouette():
    """Step 3 decides where the view sees the table deep inside the hull's silhouette (through
    a ring's hole the hull did not open), not only along its outline; a speck of table evidence
    smaller than the band about the outline does not open a hole. (glaze-torus: its masks held
    no hole in any view, 0.902 / 0.829 mean / min IoU with the true cameras.)"""
    rng = np.random.default_rng(1)
    h, w = 120, 160
    yy, xx = np.mgrid[:h, :w]
    rr = np.hypot(yy - 60, xx - 80)
    truth = (rr < 50) & (rr > 18)  # the ring, its hole showing the table
    table_rgb, ring_rgb = np.array([0.35, 0.22, 0.12]), np.array([0.8, 0.8, 0.75])
    img = np.where(truth[..., None], ring_rgb, table_rgb) * rng.uniform(0.9, 1.1, (h, w, 1))
    silhouette = rr < 52  # the hull's: no hole
    seen = np.hypot(yy - 62, xx - 77) < 7  # the plane test sees the table in part of the hole
    speck = (np.abs(yy - 60) < 2) & (np.abs(xx - 110) < 2)  # and in 9 pixels of the ring
    logodds = np.zeros((h, w))
    none = np.zeros((h, w), bool)
    m = sg.refine_view(img.astype(np.float32), silhouette, seen | speck, logodds, none, 6)
    hole = rr < 15
    assert not m[hole].any() or m[hole].mean() < 0.05, m[hole].mean()
    assert m[(rr > 22) & (rr < 46)].all()  # the ring itself, the speck included
    before = sg.refine_view(img.astype(np.float32), silhouette, none, logodds, none, 6)
    assert before[hole].all()  # without evidence in the hole the prior holds it
    # the occlusion-aware sweep sees no table where the hull hides the plane (the hole it did not
    # open); the first sweep's table pixels, given as table_deep, open it alike
    deep = sg.refine_view(img.astype(np.float32), silhouette, speck, logodds, none, 6, table_deep=seen | speck)
    assert deep[hole].mean() < 0.05 and deep[(rr > 22) & (rr < 46)].all()


def test_votes_needed():
    np.testing.assert_array_equal(votes_needed(np.array([5, 10, 40]), 0.12, 3), [3, 3, 5])
    np.testing.assert_array_equal(votes_needed(np.array([5, 10, 40]), 0.0), [1, 1, 1])


# ---- the mug on the table ----
def test_hull_splats_are_those_of_full_frame_dilations():
    """Hull.project and Hull.depth splat each voxel at its footprint, one morphological pass per
    radius, within the box of that radius's voxels grown by it: the same pixels as the same pass
    over the whole frame (a hull reaching towards a 1600-px camera has a radius for every size up
    to 64, and the full-frame passes took 9-60 s a view). Here against that full-frame reference,
    for a slab reaching past the camera's near side and cut by the frame."""
    import cv2

    from recon.io.cameras import Camera, intrinsics, look_at
    from recon.masks.vote import Hull

    step = 4.0 / 48
    g = np.mgrid[-24:24, -24:24, 0:4].reshape(3, -1).T * step + [0.0, 0.0, step / 2]
    surface = g[(g[:, 2] > 3 * step) | (np.abs(g[:, 0]) > 23 * step) | (np.abs(g[:, 1]) > 23 * step)]
    hull = Hull(g, step, surface, surface)
    radii = []
    for eye in ([0.3, -1.2, 0.5], [0.0, -2.5, 1.2], [4.0, 1.0, 3.0]):
        cam = Camera("a.png", 160, 120, intrinsics(160, 120, 40.0), look_at(eye, [0.0, 0.0, 0.3]))
        xy, z = cam.project(surface)
        ij = np.floor(xy).astype(int)
        ok = (z > 1e-9) & (ij[:, 0] >= 0) & (ij[:, 0] < 160) & (ij[:, 1] >= 0) & (ij[:, 1] < 120)
        ij, z = ij[ok], z[ok].astype(np.float32)
        radius = np.clip(np.ceil(0.5 * np.sqrt(3.0) * step * cam.K[0, 0] / z), 1, 64).astype(int)
        sil, depth = np.zeros((120, 160), np.uint8), np.full((120, 160), np.inf, np.float32)
        for r in np.unique(radius):
            k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r - 1, 2 * r - 1))
            layer, near = np.zeros_like(sil), np.full_like(depth, np.inf)
            layer[ij[radius == r, 1], ij[radius == r, 0]] = 1
            np.minimum.at(near, (ij[radius == r, 1], ij[radius == r, 0]), z[radius == r])
            sil |= cv2.dilate(layer, k)
            depth = np.minimum(depth, cv2.erode(near, k, borderType=cv2.BORDER_CONSTANT, borderValue=np.inf))
        radii.append(len(np.unique(radius)))
        assert 0.05 < sil.mean() < 1.0
        np.testing.assert_array_equal(hull.project(cam), sil > 0)
        np.testing.assert_array_equal(hull.depth(cam), depth)
    assert max(radii) >= 8, radii


def test_masks_match_the_true_silhouettes(mug, mug_masks):
    out, summary = mug_masks
    cams = load_cameras(mug / "gt" / "cameras.json")
    assert summary["method"] == "tabletop" and summary["plane"]["found"]
    assert "triangulated" in summary["plane"]["source"]
    ious, today = [], []
    linear = {c.stem: read_exr(mug / c.image) for c in cams}
    for cam in cams:
        gt = read_mask(mug / "gt" / "masks" / f"{cam.stem}.png")
        ious.append(_iou(read_mask(out / f"{cam.stem}.png"), gt))
        today.append(_iou(derive_mask(linear[cam.stem])[0], gt))
        assert summary["views"][cam.stem]["source"] == "tabletop"
    assert np.mean(ious) > 0.96 and np.min(ious) > 0.93, np.round(ious, 3)
    assert np.mean(today) < 0.6  # the flash-falloff masks take the table too


def test_no_flash_shadow_is_seen_with_the_flash_at_the_lens(mug_masks):
    _, summary = mug_masks
    assert summary["segment"]["shadow"]["found"] is False


@pytest.mark.slow
def test_the_flash_shadow_beside_the_object_is_table(tmp_path_factory):
    """The flash 0.4 of the mug's size right of the lens and 0.2 below it (a phone's flash at a
    close distance): a black band on the table left of and above the mug in every view, which the
    masks took for the mug. The shadow is found, pointing away from the flash in the views'
    pixels, and the masks are closer to the truth than with the shadow model off (recon.masks.shadow;
    docs/masks.md "The flash's shadow")."""
    from recon.masks.shadow import ShadowSettings

    cap = tabletop_capture(tmp_path_factory.getbasetemp(), flash_offset=(0.4, 0.2, 0.0), width=320, height=240)
    out = tmp_path_factory.mktemp("shadow")
    runs = {}
    for name, on in [("on", True), ("off", False)]:
        summary = run_tabletop_masks(cap / "images", cap / "gt" / "cameras.json", out / name,
                                     settings=sg.SegmentSettings(shadow=ShadowSettings(enabled=on)))
        ious = [_iou(read_mask(out / name / f"{c.stem}.png"), read_mask(cap / "gt" / "masks" / f"{c.stem}.png"))
                for c in load_cameras(cap / "gt" / "cameras.json")]
        runs[name] = (summary, np.array(ious))
    shadow = runs["on"][0]["segment"]["shadow"]
    assert shadow["found"], shadow
    away = -np.array([0.4, 0.2]) / np.hypot(0.4, 0.2)
    assert np.array(shadow["direction"]) @ away > np.cos(np.radians(30)), shadow
    on, off = runs["on"][1], runs["off"][1]
    assert on.mean() > off.mean() + 0.01 and on.mean() > 0.93, (on.round(3), off.round(3))


def test_handle_hole_stays_open(mug, mug_masks):
    """Where the table shows through the mug's handle, the masks keep it out."""
    from scipy import ndimage

    out, _ = mug_masks
    checked = 0
    for cam in load_cameras(mug / "gt" / "cameras.json"):
        gt = read_mask(mug / "gt" / "masks" / f"{cam.stem}.png")
        hole = ndimage.binary_fill_holes(gt) & ~gt
        hole = ndimage.binary_erosion(hole, iterations=2)  # open holes (not edge-on slivers), inner part
        if hole.sum() < 10:
            continue
        checked += 1
        assert read_mask(out / f"{cam.stem}.png")[hole].mean() < 0.2, cam.stem
    assert checked >= 3


def test_plane_and_outputs(mug, mug_masks):
    out, summary = mug_masks
    plane, true = load_plane(out / "plane.json"), load_plane(mug / "gt" / "plane.json")
    assert np.degrees(np.arccos(plane.normal @ true.normal)) < 0.5
    assert abs(true.height(plane.point[None])[0]) < 0.02
    record = json.loads((out / "plane.json").read_text())
    lo, hi = np.array(record["object_bbox"]["lo"]), np.array(record["object_bbox"]["hi"])
    bottom = true.height(np.array([lo]))[0]
    assert -0.1 < bottom < 0.1 and np.all(hi - lo > 1.0)  # the mug's box, standing on the table
    saved = json.loads((out / "masks.json").read_text())
    assert saved["method"] == "tabletop" and set(saved["views"]) == set(summary["views"])
    names = {p.name for p in out.iterdir()}
    assert names == {f"{s}.png" for s in summary["views"]} | {"masks.json", "plane.json"}


def test_given_masks_win(mug, tmp_path):
    cams = load_cameras(mug / "gt" / "cameras.json")
    given = tmp_path / "given"
    box = np.zeros((cams.frames[2].height, cams.frames[2].width), bool)
    box[10:40, 20:70] = True
    write_mask(given / f"{cams.frames[2].stem}.png", box)
    write_mask(given / f"{cams.frames[3].stem}.png", np.ones((5, 5), bool))
    with pytest.raises(MaskError, match=r"0003\.png: mask is 5x5"):
        run_tabletop_masks(mug / "images", mug / "gt" / "cameras.json", tmp_path / "m", given_dir=given)
    (given / f"{cams.frames[3].stem}.png").unlink()
    # every view given: nothing is derived, but the plane is still found (the later stages use it)
    for cam in cams:
        write_mask(given / f"{cam.stem}.png", box)
    summary = run_tabletop_masks(mug / "images", mug / "gt" / "cameras.json", tmp_path / "m", given_dir=given)
    assert {v["source"] for v in summary["views"].values()} == {"given"} and summary["method"] == "given"
    assert summary["plane"]["found"] and (tmp_path / "m" / "plane.json").is_file()
    np.testing.assert_array_equal(read_mask(tmp_path / "m" / f"{cams.frames[2].stem}.png"), box)


def test_void_capture_keeps_the_flash_falloff_masks(tmp_path_factory, tmp_path, caplog):
    """No support plane (a blob alone, cameras all around): today's masks, with a note."""
    cap = synth_capture(tmp_path_factory.getbasetemp(), n_views=3, width=192, height=160, write_masks=True,
                        seed=3)
    cams_path = cap / "gt" / "cameras.json"
    given = tmp_path / "given"  # a mask beside the photos that is not the capture's own
    write_mask(given / "0000.png", np.ones((160, 192), bool))
    with caplog.at_level(logging.INFO, logger="recon.masks.views"):
        summary = run_tabletop_masks(cap / "images", cams_path, tmp_path / "tab",
                                        settings=sg.SegmentSettings(min_views=3), given_dir=given, given_stems=[])
    assert summary["method"] == "flash_falloff" and not summary["plane"]["found"]
    assert {v["source"] for v in summary["views"].values()} == {"derived"}
    assert "no support plane" in caplog.text
    run_masks(cap / "images", tmp_path / "today")
    for cam in load_cameras(cams_path):
        np.testing.assert_array_equal(read_mask(tmp_path / "tab" / f"{cam.stem}.png"),
                                      read_mask(tmp_path / "today" / f"{cam.stem}.png"))
    assert not (tmp_path / "tab" / "plane.json").exists()


def test_missing_image_names_the_file(mug, tmp_path):
    cams = load_cameras(mug / "gt" / "cameras.json")
    imgs = tmp_path / "images"
    for cam in cams.frames[:-1]:
        write_exr(imgs / f"{cam.stem}.exr", read_exr(mug / cam.image))
    with pytest.raises(MaskError, match=rf"{cams.frames[-1].stem}\.exr"):
        run_tabletop_masks(imgs, mug / "gt" / "cameras.json", tmp_path / "m")


def test_settings_are_checked():
    with pytest.raises(ValueError, match="min_angle"):
        sg.SegmentSettings(min_angle=50.0, max_angle=40.0)
    with pytest.raises(ValueError, match="carve_fraction"):
        sg.SegmentSettings(carve_fraction=0.6)
    s = sg.SegmentSettings(plane={"inlier_distance": 0.01})
    assert s.plane.inlier_distance == 0.01
