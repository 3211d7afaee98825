"""Material fields: valid ranges, distinct regions per quantity, a high-frequency albedo pattern."""

import numpy as np

from recon.brdf import R_MIN
from recon.synth.materials import (
    DIFFUSE_PALETTE,
    ROUGHNESS_LEVELS,
    SPECULAR_LEVELS,
    MaterialFields,
)
from recon.synth.shapes import make_object


def test_ranges_and_regions():
    p = make_object("blob", 4, 0).sample_surface(20000, np.random.default_rng(0))
    a_d, a_s, r = MaterialFields(seed=0).evaluate(p)
    assert a_d.shape == (20000, 3) and a_s.shape == (20000, 1) and r.shape == (20000, 1)
    assert np.all((a_d >= 0) & (a_d <= 1)) and np.all((a_s >= 0) & (a_s <= 1))
    assert np.all((r >= R_MIN) & (r <= 1))
    # every specular and roughness level is used by a sizeable region
    for values, levels in ((a_s[:, 0], SPECULAR_LEVELS), (r[:, 0], ROUGHNESS_LEVELS)):
        frac = np.array([np.mean(values == v) for v in levels])
        assert frac.sum() == 1.0 and frac.min() > 0.08, frac
    # the diffuse regions: without the pattern, exactly the palette colours, each used
    base, _, _ = MaterialFields(seed=0, pattern=False).evaluate(p)
    used = np.array([np.mean(np.all(base == c, axis=1)) for c in DIFFUSE_PALETTE])
    assert used.sum() == 1.0 and used.min() > 0.05, used
    # the three partitions differ (each quantity has its own regions)
    cell = np.argmax(np.all(base[:, None, :] == DIFFUSE_PALETTE[None], axis=2), axis=1)
    for q in (a_s[:, 0], r[:, 0]):
        joint = {(c, v) for c, v in zip(cell, q, strict=True)}
        assert len(joint) > 6


def test_pattern_is_high_frequency_and_seeded():
    f = MaterialFields(seed=1, frequency=16.0)
    # along a short straight line the albedo changes many times (dots ~0.06 units across)
    t = np.linspace(0, 1.0, 4000)
    line = np.stack([0.3 + t, 0.2 + 0.0 * t, 0.5 + 0.2 * t], 1)
    lum = f.evaluate(line)[0].mean(axis=1)
    jumps = np.count_nonzero(np.abs(np.diff(lum)) > 0.05)
    assert jumps >= 10, jumps
    # the pattern's contrast: dark and light dots
    base = MaterialFields(seed=1, pattern=False).evaluate(line)[0].mean(axis=1)
    ratio = lum / base
    assert ratio.min() < 0.3 and ratio.max() > 1.3
    np.testing.assert_array_equal(f.evaluate(line)[0], MaterialFields(seed=1, frequency=16.0).evaluate(line)[0])
    assert not np.array_equal(f.evaluate(line)[0], MaterialFields(seed=2, frequency=16.0).evaluate(line)[0])
