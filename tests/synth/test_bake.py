"""UV atlases and baking: the texel convention of DESIGN section 2, end to end."""

import numpy as np
import pytest

from recon.io.mesh import Mesh
from recon.synth.bake import bake, dilate, rasterize_uv, unwrap
from recon.synth.shapes import make_object
from recon.synth.textures import bilinear_lookup, texel_centers_uv, uv_to_pixel

QUAD = Mesh([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]],
            [[0, 0], [1, 0], [1, 1], [0, 1]], [[0, 1, 2], [0, 2, 3]])


def test_texel_centers_follow_design():
    uv = texel_centers_uv(4, 8)
    assert uv.shape == (4, 8, 2)
    np.testing.assert_allclose(uv[0, 0], [0.5 / 8, 1 - 0.5 / 4])  # first row = top = v near 1
    np.testing.assert_allclose(uv[3, 7], [7.5 / 8, 0.5 / 4])
    np.testing.assert_allclose(uv_to_pixel(uv, 4, 8)[2, 5], [5.5, 2.5])


def test_bilinear_lookup_known_values():
    tex = np.arange(12, dtype=float).reshape(3, 4, 1)
    uv = texel_centers_uv(3, 4)
    np.testing.assert_allclose(bilinear_lookup(tex, uv), tex)  # exact at texel centers
    # halfway between texel (0, 0) and (0, 1); between rows 0 and 1
    np.testing.assert_allclose(bilinear_lookup(tex, [[1.0 / 4, 1 - 0.5 / 3]]), [[0.5]])
    np.testing.assert_allclose(bilinear_lookup(tex, [[0.5 / 4, 1 - 1.0 / 3]]), [[2.0]])
    # clamped outside the outer texel centers
    np.testing.assert_allclose(bilinear_lookup(tex, [[0.0, 1.0], [1.0, 0.0]]), [[0.0], [11.0]])


def test_rasterize_quad_covers_every_texel_at_its_uv():
    face, bary = rasterize_uv(QUAD, 6, 10)
    assert np.all(face >= 0)
    p = np.einsum("hwi,hwij->hwj", bary, QUAD.v_pos[QUAD.t_pos_idx[face]])
    # on this quad (x, y) = (u, v): every texel holds the point at its own center's uv
    np.testing.assert_allclose(p[..., :2], texel_centers_uv(6, 10), atol=1e-12)


def test_rasterize_partial_triangle():
    tri = Mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], [[0, 0], [1, 0], [0, 1]], [[0, 1, 2]])
    face, _ = rasterize_uv(tri, 16, 16)
    uv = texel_centers_uv(16, 16)
    inside = uv[..., 0] + uv[..., 1] <= 1.0
    np.testing.assert_array_equal(face >= 0, inside)
    with pytest.raises(ValueError, match="UVs"):
        rasterize_uv(Mesh(tri.v_pos, tri.t_pos_idx), 4, 4)


def test_dilate_grows_rings():
    img = np.zeros((7, 7, 1))
    filled = np.zeros((7, 7), bool)
    img[3, 3] = 5.0
    filled[3, 3] = True
    out, mask = dilate(img, filled, 2)
    assert mask.sum() == 25 and np.all(out[mask] == 5.0)
    assert np.all(out[~mask] == 0)


def test_unwrap_and_bake_roundtrip():
    """Bake p (the 3D position) and look it up through the mesh UVs at random surface points."""
    mesh = unwrap(make_object("blob", 3, 0), resolution=256)
    base = make_object("blob", 3, 0)
    np.testing.assert_array_equal(mesh.v_pos, base.v_pos)
    np.testing.assert_array_equal(mesh.t_pos_idx, base.t_pos_idx)
    assert mesh.v_tex.min() >= 0 and mesh.v_tex.max() <= 1
    (pos_map,), covered = bake(mesh, lambda p: (p,), 256, pad=4)
    assert 0.3 < covered.mean() < 0.95
    rng = np.random.default_rng(0)
    f = rng.integers(0, len(mesh.t_pos_idx), 3000)
    b = rng.dirichlet([1, 1, 1], 3000)
    p = np.einsum("ni,nij->nj", b, mesh.v_pos[mesh.t_pos_idx[f]])
    uv = np.einsum("ni,nij->nj", b, mesh.v_tex[mesh.t_tex_idx[f]])
    err = np.linalg.norm(bilinear_lookup(pos_map, uv) - p, axis=1)
    # the world size of a texel: sqrt(area / covered texels)
    texel = np.sqrt(mesh.area() / covered.sum())
    assert np.median(err) < 0.05 * texel, (np.median(err), texel)  # linear field: exact inside
    assert err.max() < 2.0 * texel, (err.max(), texel)  # chart borders: dilated neighbours
