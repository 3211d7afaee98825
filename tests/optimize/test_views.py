import numpy as np
import pytest
import torch

from recon.io.cameras import Camera, CameraSet, intrinsics, look_at, save_cameras
from recon.io.images import write_exr, write_mask
from recon.optimize.objective import render_loss, tone_map
from recon.optimize.views import Views, ViewsError


def make(tmp_path, n=2, W=8, H=6, sat=True):
    cams, imgs, masks, sats = [], [], [], []
    rng = np.random.default_rng(0)
    for i in range(n):
        c = Camera(f"images/{i:02d}.dng", W, H, intrinsics(W, H, 40), look_at([0, -3, 0], [0, 0, 0]))
        cams.append(c)
        img = rng.random((H, W, 3)).astype(np.float32)
        write_exr(tmp_path / f"{i:02d}.exr", img)
        m = np.zeros((H, W), bool)
        m[1:5, 2:6] = True
        write_mask(tmp_path / f"{i:02d}.png", m)
        s = np.zeros((H, W), bool)
        s[0, 0] = True
        write_mask(tmp_path / f"{i:02d}.sat.png", s)
        imgs.append(tmp_path / f"{i:02d}.exr")
        masks.append(tmp_path / f"{i:02d}.png")
        sats.append(tmp_path / f"{i:02d}.sat.png")
    cs = CameraSet(tuple(cams), 2.5)
    return imgs, masks, sats if sat else None, cs


def test_pairs_masks_and_downsamples(tmp_path):
    imgs, masks, sats, cs = make(tmp_path)
    v = Views(imgs, masks, sats, cs, max_size=8)
    assert len(v) == 2 and v.light_intensity == 2.5
    full = v.at(8)
    assert full.images.shape == (2, 6, 8, 3) and full.weights.shape == (2, 6, 8, 1)
    # background is zero, clipped pixel weighs zero
    assert float(full.images[0, 0, 0].abs().sum()) == 0 and float(full.weights[0, 0, 0, 0]) == 0
    assert float(full.weights.sum()) == 2 * (48 - 1)
    half = v.at(4)
    assert half.images.shape == (2, 3, 4, 3)
    assert half.cameras[0].width == 4 and half.cameras[0].K[0, 0] == pytest.approx(full.cameras[0].K[0, 0] / 2)
    # area average of the masked image; the clipped pixel poisons its whole 2x2 block
    np.testing.assert_allclose(half.images[0, 1, 1].numpy(), full.images[0, 2:4, 2:4].mean((0, 1)).numpy(), rtol=1e-5)
    assert float(half.weights[0, 0, 0, 0]) == 0 and float(half.weights[0, 0, 1, 0]) == 1
    np.testing.assert_allclose(half.masks[0, 1, 1], 1.0)
    np.testing.assert_allclose(half.masks[0, 0, 1], 0.5)


def test_unmasked_photos_only_when_asked(tmp_path):
    """The unmasked photos (the foot zone's colour test) at any stage size; none kept otherwise."""
    imgs, masks, sats, cs = make(tmp_path)
    v = Views(imgs, masks, sats, cs, max_size=8)
    photos = v.photos_at(4)
    assert photos.shape == (2, 3, 4, 3) and photos.dtype == np.float32
    assert float(photos[0, 0, 0].sum()) > 0  # the background is kept, unlike v.at(4).images
    np.testing.assert_allclose(v.subset([1]).photos_at(8)[0], v.photos_at(8)[1])
    lean = Views(imgs, masks, sats, cs, max_size=8, keep_photos=False)
    assert lean.photos is None and lean.subset([1, 0]).photos is None
    np.testing.assert_array_equal(lean.at(8).images.numpy(), v.at(8).images.numpy())
    with pytest.raises(ViewsError, match="keep_photos"):
        lean.photos_at(8)


def test_errors_name_the_file(tmp_path):
    imgs, masks, sats, cs = make(tmp_path)
    with pytest.raises(ViewsError, match="one mask per image"):
        Views(imgs, masks[:1], sats, cs, 8)
    other = CameraSet((cs.frames[0],), 1.0)
    with pytest.raises(ViewsError, match=r"01\.exr: no camera"):
        Views(imgs, masks, sats, other, 8)
    big = Camera("images/00.dng", 16, 12, intrinsics(16, 12, 40), np.eye(4))
    with pytest.raises(ViewsError, match=r"00\.exr: image is 8x6 but its camera says 16x12"):
        Views(imgs[:1], None, None, CameraSet((big,), 1.0), 8)
    write_mask(tmp_path / "bad.png", np.ones((3, 3), bool))
    with pytest.raises(ViewsError, match="bad.png: mask is 3x3"):
        Views(imgs[:1], [tmp_path / "bad.png"], None, cs, 8)
    with pytest.raises(ViewsError, match="no input images"):
        Views([], None, None, cs, 8)


def test_tone_maps_and_loss():
    x = torch.tensor([0.0, 0.5, 2.0])
    torch.testing.assert_close(tone_map(x, "log", 0.5), torch.log1p(x / 0.5))
    torch.testing.assert_close(tone_map(x, "linear", 1.0), x)
    s = tone_map(torch.tensor([0.0, 0.0031308, 0.5, 3.0]), "srgb", 1.0)
    assert s[0] == 0 and s[3] == pytest.approx(1.0) and s[2] == pytest.approx(0.7353569, rel=1e-5)
    with pytest.raises(ValueError):
        tone_map(x, "aces", 1.0)
    r = torch.zeros(1, 2, 2, 3, requires_grad=True)
    t = torch.full((1, 2, 2, 3), 1.0)
    w = torch.ones(1, 2, 2, 1)
    w[0, 0, 0] = 0  # clipped
    loss = render_loss(r, t, w, "linear", 1.0)
    assert loss.item() == pytest.approx(0.75)
    loss.backward()
    assert float(r.grad[0, 0, 0].abs().sum()) == 0  # clipped pixels never enter the loss
    with pytest.raises(ValueError, match="differ"):
        render_loss(r, t[:, :1], w, "linear", 1.0)


def test_camera_file_round_trip(tmp_path):
    imgs, masks, sats, cs = make(tmp_path)
    save_cameras(tmp_path / "cameras.json", cs)
    from recon.io.cameras import load_cameras

    v = Views(imgs, masks, None, load_cameras(tmp_path / "cameras.json"), 4)
    assert v.cameras[0].width == 4 and v.saturated.sum() == 0


def test_pixel_footprint_is_depth_over_focal_length():
    from recon.optimize.views import pixel_footprint

    W, H = 64, 48
    K = intrinsics(W, H, 40)
    near = Camera("a.png", W, H, K, look_at([0, -3, 0], [0, 0, 0]))
    far = Camera("b.png", W, H, K, look_at([5, 0, 0], [0, 0, 0]))
    behind = Camera("c.png", W, H, K, look_at([0, 3, 0], [0, 6, 0]))  # looks away from the point
    f = K[0, 0]
    assert pixel_footprint([near], [0, 0, 0]) == pytest.approx(3 / f)
    assert pixel_footprint([near, far, behind], [0, 0, 0]) == pytest.approx(4 / f)  # median of 3 and 5
    assert pixel_footprint([near.scaled(0.5)], [0, 0, 0]) == pytest.approx(6 / f)  # half the pixels
    assert pixel_footprint([behind], [0, 0, 0]) == 0.0
