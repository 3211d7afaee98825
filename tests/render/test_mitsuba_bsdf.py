"""The Mitsuba plugin ``recon_svbrdf`` against the numpy reference of DESIGN section 3."""

import numpy as np
import pytest

from recon import brdf
from recon.io.cameras import Camera, intrinsics, look_at, mitsuba_sensor_dict
from recon.io.mesh import Mesh
from recon.synth.textures import bilinear_lookup, texel_centers_uv


@pytest.fixture(scope="module")
def mb(mi):
    from recon.render import mitsuba_bsdf

    mitsuba_bsdf.register("llvm_ad_rgb")
    return mitsuba_bsdf


def _hemisphere_dirs(rng, n, min_cos=0.0):
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[:, 2] = np.abs(d[:, 2])
    return d[d[:, 2] > min_cos]


def _np(x):
    """A drjit array of n vectors -> numpy (n, k); of n scalars -> (n,)."""
    a = np.array(x)
    return a.T if a.ndim == 2 else a


def _si(mi, dr, n, wi, uv=None):
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = mi.Vector3f(np.ascontiguousarray(wi.T, dtype=np.float32))
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    if uv is not None:
        si.uv = mi.Point2f(np.ascontiguousarray(uv.T, dtype=np.float32))
    return si


def jittered_uv_sphere(n_lon=24, n_lat=12, radius=1.0, jitter=0.06, seed=0):
    """A lat-long sphere with a UV seam, radii jittered so that area- and angle-weighted vertex
    normals differ. UVs: u = longitude / 2 pi, v = 1 - colatitude / pi (OBJ, v up)."""
    rng = np.random.default_rng(seed)
    th = np.linspace(0, np.pi, n_lat + 1)
    ph = np.linspace(0, 2 * np.pi, n_lon + 1)
    # positions: poles once, rings without the duplicate seam column
    pos = [[0, 0, radius]]
    for i in range(1, n_lat):
        for j in range(n_lon):
            pos.append([np.sin(th[i]) * np.cos(ph[j]), np.sin(th[i]) * np.sin(ph[j]), np.cos(th[i])])
    pos.append([0, 0, -radius])
    pos = np.asarray(pos) * radius
    pos *= (1 + jitter * rng.uniform(-1, 1, size=(len(pos), 1)))

    def pid(i, j):
        if i == 0:
            return 0
        if i == n_lat:
            return len(pos) - 1
        return 1 + (i - 1) * n_lon + (j % n_lon)

    uv = np.array([[ph[j] / (2 * np.pi), 1 - th[i] / np.pi]
                   for i in range(n_lat + 1) for j in range(n_lon + 1)])

    def tid(i, j):
        return i * (n_lon + 1) + j

    f, ft = [], []
    for i in range(n_lat):
        for j in range(n_lon):
            a, b, c, d = (i, j), (i, j + 1), (i + 1, j + 1), (i + 1, j)
            for tri in ((a, d, c), (a, c, b)):
                if len({pid(*p) for p in tri}) < 3:
                    continue
                f.append([pid(*p) for p in tri])
                ft.append([tid(*p) for p in tri])
    return Mesh(pos, np.asarray(f), uv, np.asarray(ft))


# ---- registration and the plugin's parameters ----
def test_register_is_idempotent(mi, mb):
    mb.register()
    mb.register("llvm_ad_rgb")
    b = mi.load_dict(mb.bsdf_dict({"diffuse": [0.1, 0.2, 0.3], "specular": 0.5, "roughness": 0.4}))
    assert "ReconSVBRDF" in str(b)
    keys = set(mi.traverse(b).keys())
    assert {"diffuse.value", "specular.value", "roughness.value"} <= keys


def test_bad_textures_raise(mb):
    with pytest.raises(mb.TextureError, match="roughness"):
        mb.bsdf_dict({"roughness": np.zeros((4, 4, 3))})
    with pytest.raises(mb.TextureError, match="unknown"):
        mb.bsdf_dict({"albedo": 0.5})
    with pytest.raises(mb.TextureError, match="NaN"):
        mb.bsdf_dict({"specular": np.full((2, 2), np.nan)})


# ---- eval() against recon.brdf ----
@pytest.mark.parametrize("spec_channels", [1, 3])
def test_eval_matches_reference(mi, mb, spec_channels):
    import drjit as dr

    rng = np.random.default_rng(spec_channels)
    side = 64  # power of two: texel centers are exact in float32, lookups are exact
    n = side * side
    wi = _hemisphere_dirs(rng, 3 * n, 0.02)[:n]
    wo = _hemisphere_dirs(rng, 3 * n, 0.02)[:n]
    # one texel per lane, looked up at its center: exact values, no interpolation
    a_d = rng.random((side, side, 3)).astype(np.float32)
    a_s = rng.random((side, side, spec_channels)).astype(np.float32)
    r = rng.uniform(0, 1, (side, side, 1)).astype(np.float32)  # includes r < r_min (clipped)
    uv = texel_centers_uv(side, side).reshape(-1, 2)
    uv_mi = np.stack([uv[:, 0], 1 - uv[:, 1]], 1)  # Mitsuba's texture coordinates
    b = mi.load_dict(mb.bsdf_dict({"diffuse": a_d, "specular": a_s, "roughness": r}))
    si = _si(mi, dr, n, wi, uv_mi)
    ctx = mi.BSDFContext()
    wo_mi = mi.Vector3f(np.ascontiguousarray(wo.T, dtype=np.float32))
    val = _np(b.eval(ctx, si, wo_mi))
    # reference at the float32 inputs Mitsuba saw
    wi64 = np.asarray(wi, np.float32).astype(np.float64)
    wo64 = np.asarray(wo, np.float32).astype(np.float64)
    ref = brdf.eval_brdf([0, 0, 1.0], wo64, wi64, a_d.reshape(n, 3), a_s.reshape(n, -1),
                         r.reshape(n)) * wo64[:, 2:3]
    rel = np.abs(val - ref) / np.abs(ref)
    assert np.all(np.isfinite(val))
    assert rel.max() < 1e-4, f"max rel err {rel.max():.2e}"
    # below the horizon: zero (front side only)
    val_below = _np(b.eval(ctx, si, mi.Vector3f(np.ascontiguousarray(
        (wo * [1, 1, -1]).T, dtype=np.float32))))
    assert np.all(val_below == 0)


def test_eval_collocated_small_roughness(mi, mb):
    """Near the GGX peak at r = r_min the float32 plugin stays within 1e-4 of float64."""
    import drjit as dr

    mu = np.concatenate([1 - np.geomspace(1e-7, 1e-2, 50), np.linspace(0.02, 0.99, 50)])
    w = np.stack([np.sqrt(1 - mu**2), np.zeros_like(mu), mu], 1).astype(np.float32)
    for r in (brdf.R_MIN, 0.05, 1.0):
        b = mi.load_dict(mb.bsdf_dict({"diffuse": [0.3, 0.3, 0.3], "specular": 0.6, "roughness": r}))
        si = _si(mi, dr, len(mu), w)
        val = _np(b.eval(mi.BSDFContext(), si, mi.Vector3f(np.ascontiguousarray(w.T))))
        w64 = w.astype(np.float64)
        mu64 = w64[:, 2] / np.linalg.norm(w64, axis=1)  # the float32 vector is not exactly unit
        ref = brdf.eval_collocated(mu64, [0.3] * 3, [0.6], r) * w64[:, 2:3]
        rel = np.abs(val - ref) / ref
        assert rel.max() < 1e-4, (r, rel.max())


# ---- sample() and pdf() ----
@pytest.mark.parametrize("params,theta_i", [
    ({"diffuse": [0.5, 0.4, 0.3], "specular": 0.3, "roughness": 0.3}, 0.3),
    ({"diffuse": [0.1, 0.1, 0.1], "specular": 0.9, "roughness": 0.6}, 1.1),
    ({"diffuse": [0.9, 0.9, 0.9], "specular": 0.0, "roughness": 1.0}, 0.8),
])
def test_sampling_chi2(mi, mb, params, theta_i):
    """Sampled directions follow pdf() (Mitsuba's own chi^2 test)."""
    from mitsuba.chi2 import BSDFAdapter, ChiSquareTest, SphericalDomain

    wi = mi.Vector3f(float(np.sin(theta_i)), 0.0, float(np.cos(theta_i)))
    sample_func, pdf_func = BSDFAdapter(mb.PLUGIN_NAME, mb.bsdf_dict(params), wi=wi)
    chi2 = ChiSquareTest(domain=SphericalDomain(), sample_func=sample_func, pdf_func=pdf_func,
                         sample_dim=3, sample_count=200_000, res=41, seed=3)
    assert chi2.run(), chi2.messages


def test_sample_weight_and_pdf_consistent(mi, mb):
    import drjit as dr

    rng = np.random.default_rng(5)
    n = 4000
    wi = _hemisphere_dirs(rng, 3 * n, 0.05)[:n]
    params = {"diffuse": rng.random((1, n, 3)).astype(np.float32),
              "specular": rng.random((1, n, 1)).astype(np.float32),
              "roughness": rng.uniform(0.02, 1, (1, n, 1)).astype(np.float32)}
    uv = texel_centers_uv(1, n)[0]
    b = mi.load_dict(mb.bsdf_dict(params))
    si = _si(mi, dr, n, wi, np.stack([uv[:, 0], 1 - uv[:, 1]], 1))
    ctx = mi.BSDFContext()
    u = rng.random((3, n)).astype(np.float32)
    bs, weight = b.sample(ctx, si, mi.Float(u[0]), mi.Point2f(u[1], u[2]))
    value, pdf = b.eval_pdf(ctx, si, bs.wo)
    pdf2 = b.pdf(ctx, si, bs.wo)
    w, val = _np(weight), _np(value)
    p_bs, p1, p2 = _np(bs.pdf), _np(pdf), _np(pdf2)
    ok = p_bs > 0
    assert ok.mean() > 0.8
    np.testing.assert_allclose(p_bs[ok], p1[ok], rtol=1e-5)
    np.testing.assert_allclose(p1, p2, rtol=1e-6)
    np.testing.assert_allclose(w[ok], val[ok] / p_bs[ok, None], rtol=1e-5)
    assert np.all(np.isfinite(w)) and np.all(w >= 0)
    assert np.all(w[~ok] == 0)


def test_pdf_integrates_to_at_most_one(mi, mb):
    import drjit as dr

    nt, nphi = 400, 200
    t = (np.arange(nt) + 0.5) * (np.pi / 2 / nt)
    p = (np.arange(nphi) + 0.5) * (2 * np.pi / nphi)
    T, P = np.meshgrid(t, p, indexing="ij")
    d = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1).reshape(-1, 3)
    dw = (np.sin(T) * (np.pi / 2 / nt) * (2 * np.pi / nphi)).reshape(-1)
    for r, theta_i in ((0.5, 0.0), (0.7, 1.0)):
        b = mi.load_dict(mb.bsdf_dict({"diffuse": [0.5] * 3, "specular": 0.5, "roughness": r}))
        wi = np.tile([np.sin(theta_i), 0, np.cos(theta_i)], (len(d), 1))
        si = _si(mi, dr, len(d), wi)
        pdf = _np(b.pdf(mi.BSDFContext(), si, mi.Vector3f(np.ascontiguousarray(d.T, np.float32))))
        total = float(np.sum(pdf * dw))
        # the specular half may be mirrored below the horizon (lost), never more than 1
        assert 0.8 < total <= 1.0 + 2e-3, (r, theta_i, total)
        if theta_i == 0.0:
            # at normal incidence the mirrored half vectors with tan^2 > 1 go below the horizon:
            # P = alpha^2 / (1 + alpha^2) of the specular strategy, chosen with p = 0.5 here
            a2 = r**4
            assert abs(total - (1.0 - 0.5 * a2 / (1 + a2))) < 2e-3, total


# ---- meshes, UVs, normals ----
def test_mitsuba_mesh_normals_and_uv(mi, mb):
    """Shading normals are the area-weighted ones interpolated barycentrically; uv follow OBJ."""
    mesh = jittered_uv_sphere(seed=1)
    area_n = mesh.vertex_normals()
    m = mb.mitsuba_mesh(mesh, "sphere")
    # rays toward random surface points
    rng = np.random.default_rng(2)
    f = rng.integers(0, len(mesh.t_pos_idx), 500)
    bary = rng.dirichlet([2, 2, 2], 500)
    target = np.einsum("ni,nij->nj", bary, mesh.v_pos[mesh.t_pos_idx[f]])
    origin = target * 3.0
    scene = mi.load_dict({"type": "scene", "s": m})
    ray = mi.Ray3f(mi.Point3f(np.ascontiguousarray(origin.T, np.float32)),
                   mi.Vector3f(np.ascontiguousarray((target - origin).T / 2.0, np.float32)))
    si = scene.ray_intersect(ray)
    hit_f = _np(si.prim_index)
    hit_p = _np(si.p).astype(np.float64)
    ok = _np(si.is_valid()) & (hit_f == f)
    assert ok.mean() > 0.9
    # barycentrics of the hit points in their triangles (numpy)
    v = mesh.v_pos[mesh.t_pos_idx[hit_f]]
    e1, e2, q = v[:, 1] - v[:, 0], v[:, 2] - v[:, 0], hit_p - v[:, 0]
    d11, d12, d22 = np.sum(e1 * e1, 1), np.sum(e1 * e2, 1), np.sum(e2 * e2, 1)
    q1, q2 = np.sum(q * e1, 1), np.sum(q * e2, 1)
    den = d11 * d22 - d12**2
    b1 = (d22 * q1 - d12 * q2) / den
    b2 = (d11 * q2 - d12 * q1) / den
    b = np.stack([1 - b1 - b2, b1, b2], 1)
    n_ref = np.einsum("ni,nij->nj", b, area_n[mesh.t_pos_idx[hit_f]])
    n_ref /= np.linalg.norm(n_ref, axis=1, keepdims=True)
    n_mi = _np(si.sh_frame.n)
    err = np.degrees(np.arccos(np.clip(np.sum(n_ref * n_mi, 1), -1, 1)))[ok]
    assert err.max() < 0.05, err.max()
    # Mitsuba's own (angle-weighted) normals differ on this mesh: the test can tell them apart
    angle_n = _angle_weighted_normals(mesh)
    assert np.degrees(np.arccos(np.clip(np.sum(angle_n * area_n, 1), -1, 1))).max() > 0.5
    # texture coordinates: OBJ uv interpolated, then v flipped for Mitsuba
    uv_ref = np.einsum("ni,nij->nj", b, mesh.v_tex[mesh.t_tex_idx[hit_f]])
    uv_mi = _np(si.uv)
    np.testing.assert_allclose(uv_mi[ok, 0], uv_ref[ok, 0], atol=1e-5)
    np.testing.assert_allclose(uv_mi[ok, 1], 1 - uv_ref[ok, 1], atol=1e-5)


def _angle_weighted_normals(mesh):
    n = np.zeros_like(mesh.v_pos)
    fn = mesh.face_normals()
    fn /= np.linalg.norm(fn, axis=1, keepdims=True)
    for k in range(3):
        a = mesh.v_pos[mesh.t_pos_idx[:, k]]
        b = mesh.v_pos[mesh.t_pos_idx[:, (k + 1) % 3]] - a
        c = mesh.v_pos[mesh.t_pos_idx[:, (k + 2) % 3]] - a
        ang = np.arccos(np.clip(np.sum(b * c, 1) / np.linalg.norm(b, axis=1)
                                / np.linalg.norm(c, axis=1), -1, 1))
        np.add.at(n, mesh.t_pos_idx[:, k], fn * ang[:, None])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def test_texture_rows_follow_obj_convention(mi, mb):
    """Texel (i, j) sits at u = (j + 0.5)/W, v = 1 - (i + 0.5)/H: a quad whose top half (v > 0.5)
    has a red texture shows red at the top of the image, and lookups match bilinear_lookup."""
    tex = np.zeros((4, 6, 3), np.float32)
    tex[:2] = [1.0, 0.0, 0.0]  # first rows = top of the map = large v
    tex[2:] = [0.0, 0.0, 1.0]
    tex += np.random.default_rng(0).random(tex.shape).astype(np.float32) * 0.1
    # quad in the z = 0 plane facing +z, (u, v) = (x, y) for x, y in [0, 1]
    quad = Mesh([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]],
                [[0, 0], [1, 0], [1, 1], [0, 1]], [[0, 1, 2], [0, 2, 3]])
    W = H = 32
    cam = Camera("q.png", W, H, intrinsics(W, H, 40.0),
                 look_at([0.5, 0.5, 2.0], [0.5, 0.5, 0.0], up=(0, 1, 0)))
    img = mb.render_reference(quad, {"diffuse": tex, "specular": 0.0, "roughness": 1.0}, cam,
                              light_intensity=4.0, spp=16, seed=0)
    assert img.shape == (H, W, 3) and img.dtype == np.float32
    rgba = mb.render_reference(quad, {"diffuse": tex, "specular": 0.0, "roughness": 1.0}, cam,
                               light_intensity=4.0, spp=16, seed=0, alpha=True)
    assert rgba.shape == (H, W, 4)
    # two renders: each pixel sums 16 samples (all >= 0) in an order drjit's threads pick, so the
    # two agree within 2 (16 - 1) u = 1.8e-6 relative (tests/_float_sums.py)
    np.testing.assert_allclose(rgba[:, :, :3], img, rtol=1e-5, atol=1e-7)
    # coverage: the quad spans +-0.5 around the axis, the view +-2 tan(20 deg) = +-0.73
    edge = 0.5 * (1 - 0.5 / (2 * np.tan(np.radians(20)))) * W  # first covered column
    assert np.all(rgba[:, : int(edge), 3] == 0) and np.all(rgba[:, W - int(edge):, 3] == 0)
    assert np.all(rgba[int(edge) + 1: H - int(edge) - 1, int(edge) + 1: W - int(edge) - 1, 3] == 1)
    top, bottom = img[: H // 2 - 2], img[H // 2 + 2:]
    assert top[..., 0].mean() > 5 * top[..., 2].mean()
    assert bottom[..., 2].mean() > 5 * bottom[..., 0].mean()
    # direct lookups: the plugin's diffuse reflectance at points of the quad
    m = mb.mitsuba_mesh(quad, "q", bsdf=mb.bsdf_dict({"diffuse": tex}))
    scene = mi.load_dict({"type": "scene", "s": m})
    uv = np.random.default_rng(1).random((300, 2)) * 1.2 - 0.1  # also beyond the texel centers
    uv = uv[(uv >= 0.001).all(1) & (uv <= 0.999).all(1)]
    o = np.concatenate([uv, np.ones((len(uv), 1))], 1)
    ray = mi.Ray3f(mi.Point3f(np.ascontiguousarray(o.T, np.float32)), mi.Vector3f(0, 0, -1))
    si = scene.ray_intersect(ray)
    a = _np(si.bsdf().eval_diffuse_reflectance(si))
    np.testing.assert_allclose(a, bilinear_lookup(tex, uv), atol=2e-5)


def test_sensor_principal_point(mi):
    """mitsuba_sensor_dict's rays pass through the pixels cam.project gives (off-center c)."""
    W, H = 64, 48
    rng = np.random.default_rng(0)
    for cx, cy in ((0.5, 0.5), (0.3, 0.7), (0.62, 0.41)):
        K = intrinsics(W, H, 50.0)
        K[0, 2], K[1, 2] = cx * W, cy * H
        cam = Camera("a.png", W, H, K, look_at([0.3, -3, 0.5], [0, 0, 0]))
        sensor = mi.load_dict(mitsuba_sensor_dict(cam, 1))
        q = rng.uniform([0, 0], [W, H], (20, 2))
        ray, _ = sensor.sample_ray(0.0, 0.0, mi.Point2f(q[:, 0] / W, q[:, 1] / H),
                                   mi.Point2f(0.5, 0.5))
        d = _np(ray.d)
        xy, z = cam.project(cam.center + 2.0 * d)
        assert np.all(z > 0)
        assert np.abs(xy - q).max() < 1e-3, (cx, cy, np.abs(xy - q).max())


# ---- a full render against direct numerical evaluation of DESIGN section 3 ----
def _reference_image(mesh, textures, cam, intensity, n_sub=16):
    """Pixel averages of I(x) by stratified n_sub x n_sub samples, ray cast with open3d."""
    import open3d as o3d

    W, H = cam.width, cam.height
    s = (np.arange(n_sub) + 0.5) / n_sub
    jj, ii = np.meshgrid(np.arange(W), np.arange(H))
    sx, sy = np.meshgrid(s, s)
    x = (jj[:, :, None] + sx.reshape(-1)).reshape(-1)
    y = (ii[:, :, None] + sy.reshape(-1)).reshape(-1)
    rays_cam = np.linalg.solve(cam.K, np.stack([x, y, np.ones_like(x)]))  # (3, N)
    R = cam.world_to_camera[:3, :3]
    d = (R.T @ rays_cam).T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to(cam.center, d.shape)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(mesh.v_pos.astype(np.float32), mesh.t_pos_idx.astype(np.uint32))
    hit = scene.cast_rays(o3d.core.Tensor(np.concatenate([o, d], 1).astype(np.float32)))
    t = hit["t_hit"].numpy().astype(np.float64)
    valid = np.isfinite(t)
    f = hit["primitive_ids"].numpy()[valid].astype(np.int64)
    bu, bv = hit["primitive_uvs"].numpy()[valid].astype(np.float64).T
    b = np.stack([1 - bu - bv, bu, bv], 1)
    vn = mesh.vertex_normals()
    n = np.einsum("ni,nij->nj", b, vn[mesh.t_pos_idx[f]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    p = np.einsum("ni,nij->nj", b, mesh.v_pos[mesh.t_pos_idx[f]])
    uv = np.einsum("ni,nij->nj", b, mesh.v_tex[mesh.t_tex_idx[f]])
    to_cam = cam.center - p
    dist = np.linalg.norm(to_cam, axis=1)
    mu = np.sum(n * to_cam, 1) / dist
    a_d = bilinear_lookup(textures["diffuse"], uv)
    a_s = bilinear_lookup(textures["specular"], uv)
    r = bilinear_lookup(textures["roughness"], uv)[:, 0]
    L = np.zeros((len(t), 3))
    L[valid] = brdf.radiance_collocated(mu, dist, a_d, a_s, r, intensity)
    return L.reshape(H, W, n_sub * n_sub, 3).mean(axis=2)


def test_render_matches_numerical_reference(mb):
    """render_reference vs. direct evaluation of DESIGN section 3, off-center principal point.

    Measured (256 spp against 16 x 16 strata, errors relative to the mean foreground
    radiance): image means agree to 1e-4, per-pixel error mean 0.21 %, 99th percentile 1.6 %,
    max 3.7 %; all shrink as 1/sqrt(spp) (1024 spp: 0.11 %, 0.88 %). Tolerances below are
    about 2.5x those numbers.
    """
    mesh = jittered_uv_sphere(n_lon=20, n_lat=10, jitter=0.05, seed=3)
    rng = np.random.default_rng(4)
    textures = {
        "diffuse": rng.uniform(0.05, 0.9, (10, 20, 3)).astype(np.float32),
        "specular": rng.uniform(0.0, 0.8, (10, 20, 1)).astype(np.float32),
        "roughness": rng.uniform(0.25, 0.9, (10, 20, 1)).astype(np.float32),
    }
    W, H = 40, 32
    K = intrinsics(W, H, 45.0)
    K[0, 2] += 3.0
    K[1, 2] -= 2.0
    cam = Camera("v.exr", W, H, K, look_at([2.4, -2.0, 1.2], [0.0, 0.0, 0.0]))
    intensity = 7.0
    img = mb.render_reference(mesh, textures, cam, light_intensity=intensity, spp=256, seed=1)
    ref = _reference_image(mesh, textures, cam, intensity, n_sub=16)
    fg = ref.sum(-1) > 0
    assert fg.mean() > 0.25
    scale = ref[fg].mean()
    err = np.abs(img - ref) / scale
    assert abs(img.mean() / ref.mean() - 1) < 2e-3, img.mean() / ref.mean()
    assert err.mean() < 5e-3, err.mean()
    assert np.quantile(err, 0.99) < 4e-2, np.quantile(err, 0.99)
    assert err.max() < 1e-1, err.max()


# ---- sampling in a renderer: environment lighting ----
@pytest.mark.parametrize("strategy", ["emitter", "bsdf"])
def test_environment_lighting_matches_directional_albedo(mi, mb, strategy):
    """Under a uniform white environment a plane reflects its directional albedo
    int f(l, v) cos(theta_l) dl. Pure BSDF sampling exercises sample()'s weights, pure emitter
    sampling eval(); both must match the quadrature of recon.brdf within 0.5 %."""
    params = {"diffuse": [0.5, 0.3, 0.2], "specular": 0.4, "roughness": 0.35}
    theta_v = np.radians(50)
    v = np.array([np.sin(theta_v), 0.0, np.cos(theta_v)])
    W = H = 8
    cam = Camera("e.exr", W, H, intrinsics(W, H, 4.0), look_at(3.0 * v, [0, 0, 0], up=(0, 0, 1)))
    sensor = mitsuba_sensor_dict(cam, spp=4096)
    quad = Mesh([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], [[0, 1, 2], [0, 2, 3]])
    n_e, n_b = (1, 0) if strategy == "emitter" else (0, 1)
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "direct", "emitter_samples": n_e, "bsdf_samples": n_b},
        "sensor": sensor,
        "env": {"type": "constant", "radiance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}},
        "quad": mb.mitsuba_mesh(quad, "quad", bsdf=mb.bsdf_dict(params)),
    })
    img = np.array(mi.render(scene, seed=0), dtype=np.float64)[:, :, :3]
    # quadrature of the reference model
    nt, nphi = 600, 400
    t = (np.arange(nt) + 0.5) * (np.pi / 2 / nt)
    p = (np.arange(nphi) + 0.5) * (2 * np.pi / nphi)
    T, P = np.meshgrid(t, p, indexing="ij")
    d = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1).reshape(-1, 3)
    dw = (np.sin(T) * (np.pi / 2 / nt) * (2 * np.pi / nphi)).reshape(-1)
    f = brdf.eval_brdf([0, 0, 1.0], d, v, params["diffuse"], [params["specular"]], params["roughness"])
    albedo = np.sum(f * (d[:, 2] * dw)[:, None], axis=0)
    # measured: within 0.1 % for both strategies at 8 x 8 x 4096 samples
    np.testing.assert_allclose(img.mean(axis=(0, 1)), albedo, rtol=5e-3)


@pytest.mark.parametrize("scale", [1e-5, 1e5])
def test_render_reference_at_any_scene_scale(mb, scale):
    """Regression: the sensor's fixed clip planes (near 1e-3, far 1e4) blacked out scenes
    below ~1e-3 or beyond ~1e4 units. Scaling the scene by s and the light by s^2 leaves the
    image unchanged."""
    mesh = jittered_uv_sphere(n_lon=12, n_lat=6, jitter=0.0)
    textures = {"diffuse": 0.5, "specular": 0.2, "roughness": 0.3}
    eye = np.array([0.5, -3.0, 1.0])

    def render(s):
        cam = Camera("v.exr", 24, 18, intrinsics(24, 18, 40.0), look_at(eye * s, [0.0, 0.0, 0.0]))
        m = Mesh(mesh.v_pos * s, mesh.t_pos_idx, mesh.v_tex, mesh.t_tex_idx)
        return mb.render_reference(m, textures, cam, light_intensity=5.0 * s * s, spp=4, seed=2)

    ref = render(1.0)
    assert (ref.sum(-1) > 0).mean() > 0.2
    np.testing.assert_allclose(render(scale), ref, rtol=1e-4, atol=1e-6 * ref.max())


def test_clip_range_holds_the_points(mb):
    cam = Camera("v.exr", 8, 8, intrinsics(8, 8, 40.0), look_at([0.0, -5.0, 0.0], [0.0, 0.0, 0.0]))
    r = mb.clip_range(cam, np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, -2.0, 0.0]]))
    assert r == pytest.approx({"near_clip": 1.5, "far_clip": 12.0})
    # points behind or at the camera: a near plane just in front of it
    r = mb.clip_range(cam, np.array([[0.0, -6.0, 0.0], [0.0, 1.0, 0.0]]))
    assert r == pytest.approx({"near_clip": 6e-6, "far_clip": 12.0})
    assert mb.clip_range(cam, np.array([[0.0, -6.0, 0.0]])) == {}  # nothing visible: defaults
