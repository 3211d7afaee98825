"""The flash's shadow beside the object (recon.masks.shadow): one side of the outline in every
view, told from the object's own dark parts, which turn with the object."""

import numpy as np
import pytest

from recon.masks.shadow import ShadowSettings, outline_normals, shadow_direction, shadow_pixels


def _disc(shape, center, radius):
    yy, xx = np.mgrid[: shape[0], : shape[1]]
    return (xx - center[0]) ** 2 + (yy - center[1]) ** 2 <= radius**2


def _views(n=12, shadow=(-1.0, 0.0), width=6, rim=0, spots=0, seed=0, shape=(120, 160)):
    """Per view the hull's silhouette (the disc and its shadow: the masks took both) and the dark
    pixels: the shadow (the disc shifted by ``width`` px along ``shadow``, outside the disc), a
    dark rim of ``rim`` px inside the whole outline (grazing light on the object), ``spots`` dark
    patches of the object near its outline at random sides."""
    rng = np.random.default_rng(seed)
    sils, darks, truths, casts = [], [], [], []
    for _ in range(n):
        c = (80 + rng.uniform(-10, 10), 60 + rng.uniform(-8, 8))
        r = rng.uniform(25, 35)
        obj = _disc(shape, c, r)
        cast = np.zeros(shape, bool)
        if width:
            for t in np.linspace(0, width, 4 * width + 1):
                cast |= _disc(shape, (c[0] + t * shadow[0], c[1] + t * shadow[1]), r)
            cast &= ~obj
        dark = cast.copy()
        if rim:
            dark |= obj & ~_disc(shape, c, r - rim)
        for _ in range(spots):
            a = rng.uniform(0, 2 * np.pi)
            dark |= _disc(shape, (c[0] + (r - 5) * np.cos(a), c[1] + (r - 5) * np.sin(a)), 4) & obj
        sils.append(obj | cast)
        darks.append(dark)
        truths.append(obj)
        casts.append(cast)
    return sils, darks, truths, casts


def _centre_radius(disc, shrink=0):
    yy, xx = np.nonzero(disc)
    return (xx.mean(), yy.mean()), np.sqrt(disc.sum() / np.pi) + shrink


def test_outline_normals_point_out_of_the_silhouette():
    sil = _disc((100, 100), (50, 50), 30)
    sd, n = outline_normals(sil)
    assert sd[50, 50] > 25 and sd[2, 2] < -25
    # on the outline's left, right, top and bottom the normals point left, right, up and down
    for (x, y), want in [((20, 50), (-1, 0)), ((80, 50), (1, 0)), ((50, 20), (0, -1)), ((50, 80), (0, 1))]:
        np.testing.assert_allclose(n[y, x], want, atol=0.1)
    assert np.isfinite(n).all()


@pytest.mark.parametrize("direction", [(-1.0, 0.0), (0.0, -1.0), (0.6, 0.8)])
def test_a_shadow_on_one_side_in_every_view_is_found_and_taken(direction):
    """Dark along the outline towards the same side in every view, with the object's own dark
    parts (a rim all around, spots anywhere): the shadow's direction is found and its pixels are
    taken, the object's rim on the other sides is not."""
    sils, darks, truths, casts = _views(shadow=direction, rim=2, spots=3)
    u, info = shadow_direction(darks, sils)
    assert u is not None, info
    assert u @ np.array(direction) > np.cos(np.radians(20)), (u, info)
    taken = [shadow_pixels(d, s, u) for d, s in zip(darks, sils, strict=True)]
    cast = sum(int(c.sum()) for c in casts)
    got = sum(int((t & c).sum()) for t, c in zip(taken, casts, strict=True))
    assert got > 0.85 * cast  # all but the thin tips of the crescent, beyond the cone
    # of the object, only its dark pixels on the shadow's side go: the 2-px rim there and the spots
    # near it (one dark band with the shadow; the graph cut's edges decide there)
    lost = sum(int((t & o).sum()) for t, o in zip(taken, truths, strict=True))
    rim = sum(int((o & ~_disc(o.shape, *_centre_radius(o, -2))).sum()) for o in truths)
    assert lost < 0.6 * rim and lost < 0.05 * sum(int(o.sum()) for o in truths)


def test_dark_parts_of_the_object_alone_make_no_shadow():
    """No flash offset: a dark rim all around the outline and dark patches on every side as the
    object turns say nothing of a side, and nothing is taken."""
    sils, darks, _, _ = _views(width=0, rim=3, spots=4)
    u, info = shadow_direction(darks, sils)
    assert u is None and info["resultant"] < ShadowSettings().min_resultant, info


def test_extremes_give_no_shadow_and_no_nan():
    shape = (60, 80)
    empty = [np.zeros(shape, bool)] * 5
    full = [np.ones(shape, bool)] * 5
    for sils, darks in [(empty, empty), (full, full), (full, empty), ([_disc(shape, (40, 30), 10)] * 5, empty)]:
        u, info = shadow_direction(darks, sils)
        assert u is None and "reason" in info
    assert not shadow_pixels(full[0], empty[0], np.array([1.0, 0.0])).any()
    _, n = outline_normals(full[0])
    assert np.isfinite(n).all()
    with pytest.raises(ValueError):
        ShadowSettings(band=0.0)
    with pytest.raises(ValueError):
        ShadowSettings(cone_deg=95.0)


def test_a_dark_band_in_a_few_views_only_is_no_shadow():
    """A flash's shadow shows in most views; dark pixels on one side in 4 of 18 views (a lamp's
    shadow, dark wood grain in a few photos) are not one."""
    sils, darks, _, _ = _views(n=4, shadow=(1.0, 0.0))
    more, _, _, _ = _views(n=14, width=0, seed=1)
    u, info = shadow_direction(darks + [np.zeros_like(m) for m in more], sils + more)
    assert u is None and info["views"] == 4 and info["of_views"] == 18, info
    assert shadow_direction(darks, sils)[0] is not None  # those 4 views alone would be one


def test_the_dim_table_far_behind_the_object_is_no_shadow():
    """Above the object in every view the table far behind it is dim (the flash falls off with
    the distance) and may be as dark as a shadow: one side in every view, but a dark region that
    reaches past the band, not a thin band between the object and the lit table."""
    sils, _, _, _ = _views(width=0)
    darks = []
    for s in sils:
        yy, xx = np.nonzero(s)
        far = np.zeros_like(s)
        far[: int(yy.min()) + 3, :] = True  # everything above the object's top, down to its outline
        darks.append(far)
    u, info = shadow_direction(darks, sils)
    assert u is None, info


def test_dark_along_the_foot_in_every_view_is_the_object_not_a_shadow():
    """A mug glazed dark on its lower half, photographed from above: dark along the bottom of the
    outline in every view, one direction that all views share. The foot stands on the table,
    where no shadow can show: refused when the views' direction towards the foot is given; a
    shadow beside the object (the flash beside the lens) is still found."""
    sils, darks, _, _ = _views(shadow=(0.0, 1.0))  # the dark band, down in the pixels
    down = [np.array([0.0, 1.0])] * len(sils)
    assert shadow_direction(darks, sils)[0] is not None  # without the foot's side: taken, wrongly
    u, info = shadow_direction(darks, sils, down=down)
    assert u is None and info["foot_angle"] < 10 and "foot" in info["reason"], info
    # the photos turned a little about the lens (hand-held): the foot is 20 degrees off down
    tilted = [np.array([np.sin(a), np.cos(a)]) for a in np.radians(np.linspace(-20, 20, len(sils)))]
    assert shadow_direction(darks, sils, down=tilted)[0] is None
    sils, darks, _, _ = _views(shadow=(-1.0, 0.0))
    u, info = shadow_direction(darks, sils, down=down)
    assert u is not None and abs(info["foot_angle"] - 90) < 15, info
    with pytest.raises(ValueError):
        ShadowSettings(foot_deg=180.0)


def test_towards_foot_is_down_in_an_upright_view():
    from recon.io.cameras import Camera, intrinsics, look_at
    from recon.masks.shadow import towards_foot

    cam = Camera("images/a.png", 160, 120, intrinsics(160, 120, 50), look_at([0, -3, 2], [0, 0, 0.3]))
    (d,) = towards_foot([cam], np.zeros(3), np.array([0.0, 0.0, 0.5]))
    np.testing.assert_allclose(d, [0.0, 1.0], atol=1e-6)  # image y grows downwards
    (d,) = towards_foot([cam], np.zeros(3), np.zeros(3))  # one pixel: no direction, no NaN
    assert np.array_equal(d, [0.0, 0.0])
