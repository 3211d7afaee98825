"""Procedural noise: deterministic, bounded, smooth, and the dot pattern's geometry."""

import numpy as np

from recon.synth.noise import cell_hash, dots, fbm, value_noise


def test_value_noise_deterministic_bounded_and_lattice_values():
    rng = np.random.default_rng(0)
    p = rng.uniform(-20, 20, (5000, 3))
    a = value_noise(p, seed=3)
    np.testing.assert_array_equal(a, value_noise(p, seed=3))
    assert np.all(np.abs(a) <= 1.0)
    assert not np.allclose(a, value_noise(p, seed=4))
    assert a.std() > 0.2  # not degenerate
    # at integer lattice points the field takes the table values: interpolation weights 0/1
    q = np.floor(p[:50])
    b = value_noise(q, seed=3)
    c = value_noise(q + 1e-9, seed=3)
    np.testing.assert_allclose(b, c, atol=1e-12)


def test_value_noise_is_smooth():
    rng = np.random.default_rng(1)
    p = rng.uniform(-5, 5, (2000, 3))
    d = rng.normal(size=(2000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    h = 1e-4
    diff = np.abs(value_noise(p + h * d) - value_noise(p))
    # Lipschitz bound: |grad| <= 8 corners * max value * quintic slope 1.875 * sqrt(3)
    assert diff.max() < h * 8 * 1.875 * 3**0.5


def test_fbm_normalized():
    p = np.random.default_rng(2).uniform(-3, 3, (3000, 3))
    f = fbm(p, 4.0, octaves=4, seed=1)
    assert np.all(np.abs(f) <= 1.0) and f.std() > 0.1


def test_cell_hash_uniform_and_deterministic():
    cells = np.stack(np.meshgrid(np.arange(-20, 20), np.arange(-20, 20), np.arange(-5, 5)), -1).reshape(-1, 3)
    u = cell_hash(cells, 0, 0)
    np.testing.assert_array_equal(u, cell_hash(cells, 0, 0))
    assert u.min() >= 0 and u.max() < 1
    hist = np.histogram(u, bins=10, range=(0, 1))[0] / len(u)
    assert np.all(np.abs(hist - 0.1) < 0.02)
    # channels and seeds are independent streams
    assert abs(np.corrcoef(u, cell_hash(cells, 0, 1))[0, 1]) < 0.05
    assert abs(np.corrcoef(u, cell_hash(cells, 1, 0))[0, 1]) < 0.05


def test_dots_cover_a_fraction_and_are_balls():
    rng = np.random.default_rng(3)
    p = rng.uniform(-1, 1, (40000, 3))
    cell = 0.1
    inside, level = dots(p, cell, seed=5)
    frac = inside.mean()
    # one ball per cell, radius 0.35..0.7 cell: expected volume fraction ~ 4/3 pi E[r^3] ~ 0.76
    # before overlaps; with overlaps (1 - exp(-0.76)) ~ 0.53
    assert 0.35 < frac < 0.7, frac
    assert np.all(level[~inside] == 0)
    assert np.all((level[inside] >= 0) & (level[inside] < 1))
    np.testing.assert_array_equal(inside, dots(p, cell, seed=5)[0])
