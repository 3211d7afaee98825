import numpy as np

from recon.optimize.guard import SurfaceGuard, self_intersecting_faces
from recon.optimize.regularizers import MeshTopology
from synthetic import icosphere
from test_regularizers import grid


def sphere(sub=3):
    d, f = icosphere(sub)
    return d * 0.5, f


def test_small_step_is_accepted_unchanged():
    v, f = sphere()
    g = SurfaceGuard(f, MeshTopology.from_faces(f, len(v)), v)
    step = v + 1e-3 * np.random.default_rng(0).normal(size=v.shape)
    acc, info = g.accept(v, step)
    np.testing.assert_array_equal(acc, step)
    assert info == {"halvings": 0, "frozen": 0, "reverted": False}


def test_vertex_pushed_through_the_surface_is_backed_off():
    v, f = sphere()
    g = SurfaceGuard(f, MeshTopology.from_faces(f, len(v)), v)
    new = v.copy()
    new[0] = -1.6 * v[0]  # through the sphere and out of the far side
    assert self_intersecting_faces(new, f).any()
    acc, info = g.accept(v, new)
    assert info["halvings"] > 0 and not info["reverted"]
    assert not self_intersecting_faces(acc, f).any()
    assert g.new_bad_faces(acc).sum() == 0
    # the offending vertex moved towards its target, only part of the way
    t = np.dot(acc[0] - v[0], new[0] - v[0]) / np.dot(new[0] - v[0], new[0] - v[0])
    assert any(abs(t - 0.5**k) < 1e-9 for k in range(1, 9))
    # other vertices kept their (zero) step
    np.testing.assert_array_equal(acc[1:], v[1:])


def test_fold_in_a_plane_is_caught():
    n = 5
    v, f = grid(n)
    g = SurfaceGuard(f, MeshTopology.from_faces(f, len(v)), v)
    new = v.copy()
    c = 2 * n + 2  # center vertex (2, 2)
    new[c, :2] += 1.6  # slides past its neighbours: flipped triangles, no proper intersection
    assert not self_intersecting_faces(new, f).any()  # pymeshlab skips adjacent faces
    assert g.new_bad_faces(new).any()
    acc, info = g.accept(v, new)
    assert info["halvings"] > 0
    assert not g.new_bad_faces(acc).any()


def test_existing_defects_are_tolerated():
    v, f = sphere()
    bad = v.copy()
    bad[0] = -1.6 * v[0]
    g = SurfaceGuard(f, MeshTopology.from_faces(f, len(v)), bad)
    step = bad.copy()
    step[5] += 1e-3
    acc, info = g.accept(bad, step)
    assert info["halvings"] == 0
    np.testing.assert_array_equal(acc, step)
