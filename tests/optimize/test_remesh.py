import numpy as np
import pytest

from recon.io.mesh import Mesh
from recon.optimize import remesh as rm
from synthetic import blob_mesh, diffuse_of, icosphere


@pytest.fixture(scope="module")
def blob():
    m = blob_mesh(4)
    u = rm.unwrap(m.v_pos, m.t_pos_idx, 128)
    np.testing.assert_array_equal(u.t_pos_idx, m.t_pos_idx)  # nothing dropped, face order kept
    return u


def baked_analytic(mesh: Mesh, size: int) -> np.ndarray:
    face, _, pts = rm.rasterize_atlas(mesh, size)
    cov = face >= 0
    img = np.zeros((size, size, 3))
    img[cov] = diffuse_of(pts[cov])
    return rm.fill_gutters(img, cov)


def test_remesh_hits_the_target_edge_length():
    d, f = icosphere(3)
    v, g = rm.remesh(d * 0.5, f, 0.05)
    e = np.linalg.norm(v[g[:, 0]] - v[g[:, 1]], axis=1)
    assert 0.7 * 0.05 < np.median(e) < 1.3 * 0.05
    rep = rm.topology_report(v, g)
    assert rep["is_mesh_two_manifold"] and rep["boundary_edges"] == 0
    # stays on the sphere
    assert np.abs(np.linalg.norm(v, axis=1) - 0.5).max() < 0.01
    with pytest.raises(ValueError, match="edge_length"):
        rm.remesh(d, f, 0.0)


def test_unwrap_and_rasterize(blob):
    assert blob.v_tex.min() >= 0 and blob.v_tex.max() <= 1
    assert blob.t_tex_idx.shape == blob.t_pos_idx.shape
    face, bary, pts = rm.rasterize_atlas(blob, 128, dilate=0)
    cov = face >= 0
    assert 0.3 < cov.mean() < 0.95
    np.testing.assert_allclose(bary[cov].sum(1), 1.0, atol=1e-6)
    assert bary[cov].min() > -1e-5
    # texel points lie on the surface, at the texel center's UV (points on a seam edge, where the
    # closest face may be the other chart's, are left out)
    ok = cov & (bary.min(-1) > 1e-4)
    assert ok.sum() > 0.98 * cov.sum()
    uv = rm.surface_uv(blob, pts[ok])
    np.testing.assert_allclose(uv, rm.texel_centers_uv(128)[ok], atol=2e-4)
    # no two charts overlap: every texel center lies in at most one UV triangle
    import open3d as o3d

    uv3 = np.concatenate([blob.v_tex, np.zeros((len(blob.v_tex), 1))], 1).astype(np.float32)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(uv3), o3d.core.Tensor(blob.t_tex_idx.astype(np.uint32)))
    c = rm.texel_centers_uv(512).reshape(-1, 2)
    rays = np.zeros((len(c), 6), np.float32)
    rays[:, :2], rays[:, 2], rays[:, 5] = c, 1.0, -1.0
    assert scene.count_intersections(o3d.core.Tensor(rays)).numpy().max() <= 1
    # dilation: a rim of texels just outside the charts is baked from the chart's own surface
    face_d, bary_d, pts_d = rm.rasterize_atlas(blob, 128, dilate=1.5)
    rim = (face_d >= 0) & ~cov
    assert rim.sum() > 0.05 * cov.sum()
    assert bary_d[rim].min() > -1e-5  # clamped onto the nearest triangle
    np.testing.assert_array_equal(face_d[cov], face[cov])


def test_bilinear_lookup_and_gutters():
    tex = np.arange(12, dtype=float).reshape(3, 4, 1)
    uv = np.array([[(j + 0.5) / 4, 1 - (i + 0.5) / 3] for i in range(3) for j in range(4)])
    np.testing.assert_allclose(rm.bilinear_lookup(tex, uv)[:, 0], np.arange(12))
    mid = np.array([[1.0 / 4, 1 - 0.5 / 3]])  # between texels (0, 0) and (0, 1)
    assert rm.bilinear_lookup(tex, mid)[0, 0] == pytest.approx(0.5)
    cov = np.zeros((3, 4), bool)
    cov[0, 0] = cov[2, 3] = True
    img = np.zeros((3, 4, 1))
    img[0, 0], img[2, 3] = 1.0, 2.0
    filled = rm.fill_gutters(img, cov)
    assert filled[0, 1, 0] == 1.0 and filled[2, 2, 0] == 2.0 and filled[0, 0, 0] == 1.0


def test_bake_onto_the_same_atlas_is_exact(blob):
    tex = baked_analytic(blob, 128)
    out, cov = rm.bake(blob, {"diffuse": tex}, blob, 128)
    face0, bary0, _ = rm.rasterize_atlas(blob, 128, dilate=0)
    inside = face0 >= 0  # texel centers inside triangles
    assert cov[inside].all()
    strict = inside & (bary0.min(-1) > 1e-4)  # not on a seam edge (the closest face may be the other chart's)
    assert strict.sum() > 0.98 * inside.sum()
    np.testing.assert_allclose(out["diffuse"][strict], tex[strict], atol=2e-4)
    # the rim texels hold the colour of the chart's own surface (a smooth function: close)
    rim = cov & ~inside
    assert np.abs(out["diffuse"][rim] - tex[rim]).mean() < 0.01


def test_stage_change_keeps_what_was_learned(blob):
    """Remesh + re-unwrap + bake at twice the texture size: the surface colour is unchanged."""
    tex = baked_analytic(blob, 128)
    new, maps, cov = rm.remesh_and_rebake(blob, {"diffuse": tex, "rough": tex[:, :, :1]}, 0.03, 256)
    assert maps["diffuse"].shape == (256, 256, 3) and maps["rough"].shape == (256, 256, 1)
    assert rm.is_manifold(new.v_pos, new.t_pos_idx)
    rng = np.random.default_rng(0)
    # random points of the new surface: new map there vs old map at the closest old point
    f = rng.integers(0, len(new.t_pos_idx), 4000)
    b = rng.dirichlet([1, 1, 1], 4000)
    p = np.einsum("nk,nkd->nd", b, new.v_pos[new.t_pos_idx[f]])
    uv_new = np.einsum("nk,nkd->nd", b, new.v_tex[new.t_tex_idx[f]])
    got = rm.bilinear_lookup(maps["diffuse"], uv_new)
    ref = rm.bilinear_lookup(tex, rm.surface_uv(blob, p))
    err = np.abs(got - ref)
    assert err.mean() < 2e-3 and np.quantile(err, 0.99) < 0.02
    # and against the analytic colour of the old surface point
    truth = diffuse_of(p)
    assert np.abs(got - truth).mean() < 5e-3


def test_stage_change_renders_the_same(blob):
    """Render-equivalence: the object looks the same before and after a stage change."""
    import torch
    from recon import render
    from synthetic import ring_cameras

    tex = baked_analytic(blob, 128).astype(np.float32)
    spec = np.full((128, 128, 1), 0.3, np.float32)
    rough = np.full((128, 128, 1), 0.3, np.float32)
    new, maps, _ = rm.remesh_and_rebake(blob, {"d": tex, "s": spec, "r": rough}, 0.03, 256)
    cams = ring_cameras(3, 64)
    rs = render.RenderSettings(spp=16, boundary="none")

    def draw(mesh, d, s, r):
        rr = render.CollocatedRenderer(mesh.t_pos_idx, mesh.v_tex, mesh.t_tex_idx, rs)
        with torch.no_grad():
            return rr.render_torch(torch.tensor(mesh.v_pos, dtype=torch.float32), torch.from_numpy(d),
                                   torch.from_numpy(s), torch.from_numpy(r), cams, 1.0, seed=3).numpy()

    before = draw(blob, tex, spec, rough)
    after = draw(new, maps["d"], maps["s"], maps["r"])
    lost = draw(new, np.full_like(maps["d"], 0.5), maps["s"], maps["r"])  # what forgetting looks like
    fg = before.sum(-1) > 0
    scale = before[fg].mean()
    err = np.abs(after - before)[fg].mean() / scale
    err_lost = np.abs(lost - before)[fg].mean() / scale
    assert err < 0.03 and err_lost > 5 * err, (err, err_lost)
