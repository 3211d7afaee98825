"""Procedural objects: closed manifold meshes of the right genus, inside the object cube."""

import numpy as np
import pytest

from recon.synth import shapes


def _edges(mesh):
    f = mesh.t_pos_idx
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    uniq, counts = np.unique(e, axis=0, return_counts=True)
    return uniq, counts


def _check_closed_manifold(mesh, genus):
    uniq, counts = _edges(mesh)
    assert np.all(counts == 2), "every edge must border exactly two faces"
    # consistent orientation: every directed edge appears once
    f = mesh.t_pos_idx
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    assert len(np.unique(directed, axis=0)) == len(directed)
    chi = len(mesh.v_pos) - len(uniq) + len(f)
    assert chi == 2 - 2 * genus
    assert mesh.volume() > 0  # outward normals
    assert np.abs(mesh.v_pos).max() <= shapes.EXTENT + 1e-9
    assert np.all(np.isfinite(mesh.v_pos))


@pytest.mark.parametrize("level", [0, 1, 3])
def test_icosphere(level):
    m = shapes.icosphere(level)
    assert len(m.v_pos) == 10 * 4**level + 2 and len(m.t_pos_idx) == 20 * 4**level
    np.testing.assert_allclose(np.linalg.norm(m.v_pos, axis=1), 1.0, rtol=1e-12)
    _check_closed_manifold(shapes.Mesh(m.v_pos * 0.9, m.t_pos_idx), genus=0)
    assert m.volume() < 4 / 3 * np.pi


@pytest.mark.parametrize("kind,genus", [("blob", 0), ("smooth", 0), ("torus", 1), ("mug", 1)])
def test_objects_are_closed_manifolds(kind, genus):
    m = shapes.make_object(kind, level=3, seed=1)
    _check_closed_manifold(m, genus)
    assert abs(np.abs(m.v_pos).max() - shapes.EXTENT) < 1e-9  # fills the extent
    np.testing.assert_array_equal(m.v_pos, shapes.make_object(kind, level=3, seed=1).v_pos)
    other = shapes.make_object(kind, level=3, seed=2).v_pos
    assert other.shape != m.v_pos.shape or not np.allclose(m.v_pos, other)


def test_blob_has_detail_that_smooth_lacks():
    """Bumps and grooves: the radius' umbrella Laplacian (curvature detail) is much larger."""
    def detail(m):
        r = np.linalg.norm(m.v_pos, axis=1)
        uniq, _ = _edges(m)
        acc = np.zeros(len(r))
        cnt = np.zeros(len(r))
        for a, b in ((0, 1), (1, 0)):
            np.add.at(acc, uniq[:, a], r[uniq[:, b]])
            np.add.at(cnt, uniq[:, a], 1)
        return np.abs(r - acc / cnt).mean()

    blob = shapes.make_object("blob", level=5, seed=0)
    smooth = shapes.make_object("smooth", level=5, seed=0)
    assert detail(blob) > 3 * detail(smooth), (detail(blob), detail(smooth))


def test_mug_has_a_cavity_and_a_flat_base():
    """The mug's inside is hollow (rays down the middle hit the inner bottom, far below the rim)
    and its base is flat: many vertices on the lowest plane."""
    m = shapes.make_object("mug", level=3, seed=0)
    lo, hi = m.bbox()
    z = m.v_pos[:, 2]
    assert (z < lo[2] + 1e-3 * (hi[2] - lo[2])).sum() > 10
    # the body's axis is at the center of the vertices without the handle (x > body radius)
    near_axis = np.hypot(m.v_pos[:, 0] - np.median(m.v_pos[:, 0]), m.v_pos[:, 1]) < 0.1
    assert near_axis.any() and z[near_axis].max() < lo[2] + 0.3 * (hi[2] - lo[2])  # only the bottoms
    # the volume is far below that of the full cylinder (hollow)
    assert m.volume() < 0.5 * np.pi * (0.5 * (hi[1] - lo[1])) ** 2 * (hi[2] - lo[2])


def test_flatten_base():
    m = shapes.make_object("blob", level=3, seed=1)
    f = shapes.flatten_base(m, 0.1)
    _check_closed_manifold(f, genus=0)
    z = f.v_pos[:, 2]
    assert (z == z.min()).sum() > 5  # a flat base
    np.testing.assert_array_equal(f.t_pos_idx, m.t_pos_idx)
    assert shapes.flatten_base(m, 0.0) is m
    with pytest.raises(ValueError, match="cut"):
        shapes.flatten_base(m, 0.6)


def test_unknown_kind_raises():
    with pytest.raises(ValueError, match="unknown object kind"):
        shapes.make_object("cube")
    with pytest.raises(ValueError):
        shapes.icosphere(-1)
