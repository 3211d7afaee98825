import json

import numpy as np
import pytest
from _geometry_scene import synth_capture

from recon import masks as rm
from recon.io.cameras import load_cameras
from recon.io.images import read_exr, read_mask, write_exr, write_mask


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """Three noisy flash photos of a glossy blob (recon.synth, EXR) with true masks."""
    cap = synth_capture(tmp_path_factory.getbasetemp(), n_views=3, width=192, height=160,
                        write_masks=True, seed=3)
    return {"linear": cap / "images", "cameras": load_cameras(cap / "gt" / "cameras.json"),
            "masks": cap / "masks"}


def _iou(a, b):
    return (a & b).sum() / (a | b).sum()


def _grow(mask, px):
    import cv2

    return cv2.dilate(mask.astype(np.uint8), np.ones((2 * px + 1, 2 * px + 1), np.uint8)) > 0


def test_otsu_splits_two_modes():
    rng = np.random.default_rng(0)
    v = np.concatenate([rng.normal(-4, 0.2, 5000), rng.normal(-1, 0.2, 5000)])
    assert -3.0 < rm.otsu_threshold(v) < -2.0
    assert rm.otsu_threshold(np.full(10, 3.0)) == 3.0


def test_derived_mask_matches_the_silhouette(scene):
    for cam in scene["cameras"]:
        img = read_exr(scene["linear"] / f"{cam.stem}.exr")
        gt = read_mask(scene["masks"] / f"{cam.stem}.png")  # pixels more than half covered
        mask, info = rm.derive_mask(img)
        assert mask.dtype == bool and mask.shape == gt.shape
        # never loses object (the visual hull would carve it away); extra pixels only on the
        # outline (partly covered pixels, which the true masks leave out below half coverage)
        assert (gt & ~mask).sum() <= 0.002 * gt.sum()
        assert not (mask & ~_grow(gt, 2)).any()
        assert _iou(mask, gt) > 0.95
        assert info["threshold_log10"] <= info["otsu_log10"]
        assert 0 < info["coverage"] < 1


def test_derived_mask_with_noise_speckles_and_dark_spots(scene):
    rng = np.random.default_rng(1)
    cam = scene["cameras"].frames[0]
    gt = read_mask(scene["masks"] / f"{cam.stem}.png")
    img = read_exr(scene["linear"] / f"{cam.stem}.exr")
    img = img + rng.normal(0, 2e-3, img.shape).astype(np.float32)  # more read noise
    ys, xs = rng.integers(0, img.shape[0], 30), rng.integers(0, img.shape[1], 30)
    img[ys, xs] = 0.5  # hot pixels in the background
    cy, cx = np.round(np.argwhere(gt).mean(0)).astype(int)  # the middle of the object
    img[cy - 2:cy + 3, cx - 2:cx + 3] = 0.0  # a small black spot on the object
    mask, _ = rm.derive_mask(np.maximum(img, 0))
    assert mask[cy, cx]  # small hole filled
    assert _iou(mask, gt) > 0.95
    assert not mask[ys, xs][~gt[ys, xs]].any()  # speckles removed


def test_large_hole_is_kept_small_hole_filled():
    h = w = 200
    j, i = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    r = np.hypot(i - 100, j - 100)
    img = np.where(r < 80, 0.5, 0.0).astype(np.float32)
    img[r < 30] = 0.0  # a through-hole (a ring): 14% of the object
    img[40:44, 98:102] = 0.0  # a dark spot: a texture hole
    img = np.repeat(img[:, :, None], 3, axis=2)
    mask, _ = rm.derive_mask(img, rm.MaskSettings(close_radius=0.0))
    assert not mask[100, 100]
    assert mask[42, 100]


def test_black_image_is_an_error():
    with pytest.raises(rm.MaskError, match="black"):
        rm.derive_mask(np.zeros((16, 16, 3), np.float32))
    with pytest.raises(rm.MaskError, match="shape"):
        rm.derive_mask(np.zeros((16, 16, 2), np.float32))


def test_settings_are_checked():
    with pytest.raises(ValueError, match="floor"):
        rm.MaskSettings(floor=0.0)
    with pytest.raises(ValueError, match="max_hole_fraction"):
        rm.MaskSettings(max_hole_fraction=2.0)


def test_run_masks_given_and_derived(scene, tmp_path):
    given = tmp_path / "given"
    cam0 = scene["cameras"].frames[0]
    box = np.zeros((cam0.height, cam0.width), bool)
    box[10:50, 20:80] = True
    write_mask(given / f"{cam0.stem}.png", box)
    out = tmp_path / "masks"
    summary = rm.run_masks(scene["linear"], out, given_dir=given)
    stems = [c.stem for c in scene["cameras"]]
    assert sorted(summary["views"]) == stems
    assert summary["views"][cam0.stem]["source"] == "given"
    assert all(summary["views"][s]["source"] == "derived" for s in stems[1:])
    np.testing.assert_array_equal(read_mask(out / f"{cam0.stem}.png"), box)
    assert json.loads((out / "masks.json").read_text())["views"].keys() == summary["views"].keys()
    assert sorted(p.name for p in out.iterdir()) == sorted([f"{s}.png" for s in stems] + ["masks.json"])


def test_given_mask_of_the_full_photo_follows_the_reduced_image(tmp_path):
    """A capture's own mask at the photo's size when linearize reduced the photo
    (linearize.max_size): area-reduced, object where at least half the output pixel is."""
    full = np.zeros((300, 400), bool)
    full[40:200, 100:301] = True
    small = rm.fit_given_mask(full, "masks/a.png", (100, 75))
    expect = full.reshape(75, 4, 100, 4).mean(axis=(1, 3)) >= 0.5
    np.testing.assert_array_equal(small, expect)
    assert rm.fit_given_mask(full, "masks/a.png", (400, 300)) is full
    with pytest.raises(rm.MaskError, match=r"masks/a\.png: mask is 400x300 but the image is 100x80"):
        rm.fit_given_mask(full, "masks/a.png", (100, 80))


def test_run_masks_wrong_size_leaves_nothing(scene, tmp_path):
    given = tmp_path / "given"
    cam0 = scene["cameras"].frames[-1]
    write_mask(given / f"{cam0.stem}.png", np.ones((10, 10), bool))
    out = tmp_path / "masks"
    with pytest.raises(rm.MaskError, match=rf"{cam0.stem}\.png: mask is 10x10 but the image is"):
        rm.run_masks(scene["linear"], out, given_dir=given)
    assert not out.exists()
    assert list(tmp_path.iterdir()) == [given]


def test_run_masks_black_view_names_the_file(tmp_path):
    lin = tmp_path / "linear"
    write_exr(lin / "a.exr", np.zeros((8, 8, 3), np.float32))
    with pytest.raises(rm.MaskError, match=r"a\.exr: .*provide masks/a\.png"):
        rm.run_masks(lin, tmp_path / "masks")
    with pytest.raises(rm.MaskError, match="no linear images"):
        rm.run_masks(tmp_path / "empty", tmp_path / "masks")


def test_noise_only_or_no_light_is_no_object(scene):
    """Regression: a black object (or a flash that did not fire) gave masks of sensor noise
    or of float rounding residue, and the stages after masks failed with misleading messages."""
    cam = scene["cameras"].frames[0]
    img = read_exr(scene["linear"] / f"{cam.stem}.exr")
    # float rounding residue of a render of a black object: no light at all
    with pytest.raises(rm.MaskError, match=r"image is black \(brightest pixels 1e-34\)"):
        rm.derive_mask(np.where(img > 0, 1e-34, 0.0).astype(np.float32))
    # RAW-like noise (white level 1.0): read noise of 3e-4, no object
    rng = np.random.default_rng(2)
    noise = np.maximum(rng.normal(0.0, 3e-4, img.shape), 0.0).astype(np.float32)
    with pytest.raises(rm.MaskError, match=r"reach only 0\.\d+% of the white level \(masks\.min_signal = 0\.39%\)"):
        rm.derive_mask(noise, white_level=1.0)
    with pytest.raises(rm.MaskError, match="white level"):  # in any units
        rm.derive_mask(noise * 1e3, white_level=1e3)
    # the object 5 stops underexposed, in that noise, is still found
    dim = img / np.float32(32.0 * np.percentile(img, 99.9)) + noise
    gt = read_mask(scene["masks"] / f"{cam.stem}.png")
    mask, _ = rm.derive_mask(dim, white_level=1.0)
    assert _iou(mask, gt) > 0.9
    with pytest.raises(ValueError, match="min_signal"):
        rm.MaskSettings(min_signal=1.0)


def test_run_masks_names_the_photo_without_an_object(scene, tmp_path):
    lin = tmp_path / "linear"
    cam = scene["cameras"].frames[0]
    img = read_exr(scene["linear"] / f"{cam.stem}.exr")
    write_exr(lin / "a.exr", img / np.float32(img.max()))
    write_exr(lin / "b.exr", img / np.float32(1e3 * img.max()))  # 10 stops too dark
    record = {"kind": "raw", "images": {"a": {"source": "images/a.dng"}, "b": {"source": "images/b.dng"}}}
    (lin / "linear.json").write_text(json.dumps(record))
    out = tmp_path / "masks"
    with pytest.raises(rm.MaskError, match=r"no object found in images/b\.dng \(.*b\.exr\): .*white level"
                                           r".*provide masks/b\.png"):
        rm.run_masks(lin, out)
    assert not out.exists()
    # EXR views (unknown units): the dark view is a valid image
    record["kind"] = "hdr"
    (lin / "linear.json").write_text(json.dumps(record))
    summary = rm.run_masks(lin, out)
    assert summary["views"]["b"]["coverage"] == pytest.approx(summary["views"]["a"]["coverage"])


def test_run_masks_with_cameras_of_a_void_capture(scene, tmp_path):
    """With cameras, a capture without a support plane keeps the flash-falloff masks
    (recon.masks.views falls back to them); the summary says which method made them."""
    from recon.masks.views import SegmentSettings

    cams = scene["linear"].parent / "gt" / "cameras.json"
    plain = rm.run_masks(scene["linear"], tmp_path / "plain")
    assert plain["method"] == "flash_falloff"
    with_cams = rm.run_masks(scene["linear"], tmp_path / "cams", cameras=cams,
                             segment_settings=SegmentSettings(min_views=3))
    assert with_cams["method"] == "flash_falloff" and not with_cams["plane"]["found"]
    for stem in plain["views"]:
        np.testing.assert_array_equal(read_mask(tmp_path / "plain" / f"{stem}.png"),
                                      read_mask(tmp_path / "cams" / f"{stem}.png"))


# ---- flash-falloff masks made consistent across views (recon.masks.consistent) ----
@pytest.fixture(scope="module")
def ring_views():
    """16 cameras around a torus standing upright (its hole seen from the sides), true silhouettes."""
    from _geometry_scene import ring_of_views

    _, cams, truth = ring_of_views()
    return cams, truth


def test_consistent_masks_fill_what_one_view_misses_and_drop_what_it_adds(ring_views):
    from recon.masks.common import holes
    from recon.masks.consistent import consistent_masks

    cams, truth = ring_views
    masks = [m.copy() for m in truth]
    ys, xs = np.nonzero(truth[0])
    cy, cx = int(np.median(ys)), int(xs.min()) + 4
    masks[0][cy - 6:cy + 6, cx - 3:cx + 8] = False  # a dark patch the flash missed, at the outline
    ys, xs = np.nonzero(truth[5])
    masks[5][int(np.median(ys)) - 5:int(np.median(ys)) + 5, int(np.median(xs)) - 5:int(np.median(xs)) + 5] = False
    masks[9][:12, :] = True  # a lit wall along the top of the frame
    fixed, info = consistent_masks(masks, cams)
    assert info["applied"]
    for k in (0, 5, 9):
        assert _iou(fixed[k], truth[k]) > max(0.95, _iou(masks[k], truth[k]) + 0.02), k
    # the torus's hole is real: the views that see it keep it open
    opened = [k for k, m in enumerate(truth) if holes(m).sum() > 30]
    assert opened and all(holes(fixed[k]).sum() > 0.5 * holes(truth[k]).sum() for k in opened)
    for k in range(16):
        assert _iou(fixed[k], truth[k]) > 0.93


def test_consistent_masks_restore_a_dark_rim_along_the_outline(ring_views):
    """Surfaces seen at grazing angles are lit at grazing angles: a view's flash-falloff mask
    loses a rim along its outline, which borders the background (no notch to fill). The other
    views see those surfaces face-on: their hull gives the rim back."""
    from recon.masks.common import erode
    from recon.masks.consistent import consistent_masks

    cams, truth = ring_views
    masks = [m.copy() for m in truth]
    masks[2] = erode(truth[2], 3)
    fixed, info = consistent_masks(masks, cams)
    assert info["applied"]
    before, after = _iou(masks[2], truth[2]), _iou(fixed[2], truth[2])
    assert before < 0.85 and after > max(0.9, before + 0.08), (before, after)
    assert not (fixed[2] & ~truth[2]).sum() > 0.05 * truth[2].sum()  # nothing beyond the outline


def test_consistent_masks_refuse_masks_that_share_no_object(ring_views, caplog):
    """Every view's mask riddled with notches (a dark, patterned object the flash barely lifts
    above the background): their voted hull keeps little of any mask, and masks cut to it would
    be worse than each view's own. The vote is refused and the masks stay as they are."""
    from recon.masks.consistent import consistent_masks

    cams, truth = ring_views
    rng = np.random.default_rng(0)
    masks = []
    for t in truth:
        m = t.copy()
        ys, xs = np.nonzero(t)
        for k in rng.integers(len(ys), size=12):
            m[ys[k] - 6:ys[k] + 6, xs[k] - 6:xs[k] + 6] = False
        masks.append(m)
    assert 0.5 < np.mean([_iou(m, t) for m, t in zip(masks, truth, strict=True)]) < 0.8
    fixed, info = consistent_masks(masks, cams)
    assert not info["applied"] and info["median_kept"] < 0.9 and "do not agree on one object" in info["reason"]
    assert "give masks/<stem>.png" in caplog.text  # the user is told what to do
    for a, b in zip(fixed, masks, strict=True):
        np.testing.assert_array_equal(a, b)


def test_consistent_masks_outvote_the_views_that_took_something_else(ring_views):
    """A dark object before a lit floor: in 6 of the 16 views the flash-falloff mask took the
    floor's lit patch or the stand's base below the object and missed the object. A vote over
    all views that tolerates a quarter of misses carves the object away and is refused; the
    views that agree with the bare majority's hull vote again, and the 6 others take the
    silhouette of that hull."""
    from recon.masks.consistent import ConsistentSettings, consistent_masks

    cams, truth = ring_views
    wrong = (1, 3, 6, 9, 11, 14)
    masks = [t.copy() for t in truth]
    for k in wrong:
        h, w = truth[k].shape
        yy, xx = np.mgrid[:h, :w]
        ys, xs = np.nonzero(truth[k])
        cy, cx = ys.max() + 0.12 * h, xs.mean() + 0.1 * (k - 7) * w / 16  # a lit patch below the object
        masks[k] = ((yy - cy) / (0.1 * h)) ** 2 + ((xx - cx) / (0.2 * w)) ** 2 < 1
    alone, info = consistent_masks(masks, cams, ConsistentSettings(agreement=0))
    assert not info["applied"] and "share no 3D region" in info["reason"]
    fixed, info = consistent_masks(masks, cams)
    assert info["applied"]
    assert sorted(info["outliers"]) == sorted(cams.frames[k].stem for k in wrong)
    for k in range(16):
        # a wrong view's silhouette: the torus's hole is open where the 10 views carve it
        assert _iou(fixed[k], truth[k]) > (0.7 if k in wrong else 0.88), (k, _iou(fixed[k], truth[k]))
    assert np.mean([_iou(fixed[k], truth[k]) for k in range(16) if k not in wrong]) > 0.93
    # the capture's own masks always vote: given as trusted, a wrong view is no outlier (and the
    # vote over it is refused again)
    _, info = consistent_masks(masks, cams, trusted=set(wrong))
    assert not info["applied"]


def test_masks_from_the_sparse_points_where_no_views_agree(tmp_path):
    """A near-black object before a lit wall: every view's flash-falloff mask holds a different
    piece of the background, so neither the vote of all views nor of any subset stands. The
    poses stage then draws the masks from SfM's points on the object (the wall's points, beyond
    the object's reach from the point the cameras aim at, are left out) and makes them
    consistent: every view near its true silhouette."""
    from _geometry_scene import ring_of_views

    from recon.io.cameras import save_cameras
    from recon.poses.stage import _consistent_falloff_masks, _write_points

    torus, cams, truth = ring_of_views()
    rng = np.random.default_rng(0)
    tri = torus.v_pos[torus.t_pos_idx]
    pick = rng.integers(len(tri), size=1500)
    w = rng.dirichlet(np.ones(3), size=len(pick))
    on_object = np.einsum("nk,nkd->nd", w, tri[pick])
    wall = np.c_[rng.uniform(-3, 3, 300), np.full(300, -3.5), rng.uniform(-1, 3, 300)]  # far behind, lit
    folder = tmp_path / "poses"
    (folder / "undistorted" / "masks").mkdir(parents=True)
    save_cameras(folder / "cameras.json", cams)
    _write_points(folder / "points.ply", np.r_[on_object, wall], np.ones(1800, bool))
    for k, (cam, t) in enumerate(zip(cams, truth, strict=True)):
        h, wd = t.shape
        yy, xx = np.mgrid[:h, :wd]
        cy, cx = (0.15 + 0.7 * ((k * 7) % 16) / 16) * h, (0.1 + 0.8 * ((k * 5) % 16) / 16) * wd
        write_mask(folder / "undistorted" / "masks" / f"{cam.stem}.png", (yy - cy) ** 2 + (xx - cx) ** 2 < 15 ** 2)
    # without the points the vote is refused and the masks stay as they are
    info = _consistent_falloff_masks(cams, folder / "undistorted" / "masks", set())
    assert not info["applied"]
    info = _consistent_falloff_masks(cams, folder / "undistorted" / "masks", set(), folder / "points.ply")
    assert info["applied"] and info["source"] == "sparse points"
    ious = [_iou(read_mask(folder / "undistorted" / "masks" / f"{c.stem}.png"), t) for c, t in zip(cams, truth, strict=True)]
    assert np.mean(ious) > 0.85 and min(ious) > 0.75, np.round(ious, 3)


def test_consistent_masks_need_views(ring_views):
    from recon.io.cameras import CameraSet
    from recon.masks.consistent import consistent_masks

    cams, truth = ring_views
    few = CameraSet(cams.frames[:4], 1.0)
    out, info = consistent_masks(truth[:4], few)
    assert not info["applied"] and "4 views" in info["reason"]
    assert all((a == b).all() for a, b in zip(out, truth[:4], strict=True))


def test_fill_enclosed_fills_notches_not_the_outside():
    from recon.masks.consistent import fill_enclosed

    mask = np.zeros((60, 60), bool)
    mask[10:50, 10:50] = True
    mask[25:35, 10:22] = False  # a notch open to the left
    support = np.zeros_like(mask)
    support[8:52, 8:52] = True  # a little wider than the object all round
    out = fill_enclosed(mask, support, 0.6)
    assert out[25:35, 12:22].all()  # the notch (mostly bordered by the mask) is filled
    assert not out[8:10, :].any() and not out[:, 50:].any()  # the thin outer rim is not
