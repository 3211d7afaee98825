import numpy as np
import pytest
import torch

from recon.optimize import regularizers as reg
from synthetic import icosphere


def grid(n=6, z=None):
    """(n x n) planar grid in the z = 0 plane (or height field z(x, y)) with 2 (n-1)^2 faces."""
    ys, xs = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float), indexing="ij")
    zs = np.zeros_like(xs) if z is None else z(xs, ys)
    v = np.stack([xs.ravel(), ys.ravel(), zs.ravel()], 1)
    f = []
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j
            f += [[a, a + 1, a + n + 1], [a, a + n + 1, a + n]]
    return v, np.array(f)


def interior(n):
    idx = np.arange(n * n).reshape(n, n)
    return idx[1:-1, 1:-1].ravel()


def test_topology_of_a_tetrahedron():
    f = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
    t = reg.MeshTopology.from_faces(f, 4)
    assert t.edges.shape == (6, 2) and t.face_pairs.shape == (6, 2)
    assert t.degree.tolist() == [3, 3, 3, 3]
    with pytest.raises(ValueError, match="face indices"):
        reg.MeshTopology.from_faces(f, 3)


@pytest.mark.parametrize("kind", ["uniform", "cotangent"])
def test_laplacian_of_a_plane_is_zero_inside(kind):
    n = 6
    v, f = grid(n)
    # a tilted plane: still zero
    v = v @ np.array([[1.0, 0.2, 0.3], [0.0, 1.0, -0.4], [0.0, 0.0, 1.0]])
    t = reg.MeshTopology.from_faces(f, len(v))
    vt = torch.tensor(v)
    lap = (reg.uniform_laplacian if kind == "uniform" else reg.cotangent_laplacian)(vt, t)
    assert lap[interior(n)].abs().max() < 1e-12
    assert lap.abs().max() > 1e-3  # the boundary is not zero


def test_uniform_laplacian_known_value():
    v, f = grid(3)
    v[4, 2] = 0.6  # lift the center vertex
    t = reg.MeshTopology.from_faces(f, len(v))
    lap = reg.uniform_laplacian(torch.tensor(v), t)
    # the center has 6 neighbours (grid triangulated along one diagonal), all at z = 0
    assert int(t.degree[4]) == 6
    np.testing.assert_allclose(lap[4].numpy(), [0.0, 0.0, 0.6], atol=1e-12)


def test_cotangent_laplacian_of_a_sphere_is_twice_the_mean_curvature():
    d, f = icosphere(4)
    R = 0.7
    t = reg.MeshTopology.from_faces(f, len(d))
    lap = reg.cotangent_laplacian(torch.tensor(d * R), t).numpy()
    mag = np.linalg.norm(lap, axis=1)
    np.testing.assert_allclose(np.median(mag), 2 / R, rtol=0.02)
    # it points outward along the normal
    assert np.median(np.sum(lap * d, axis=1) / mag) > 0.999


@pytest.mark.parametrize("kind", ["uniform", "cotangent"])
def test_laplacian_loss_is_scale_invariant(kind):
    d, f = icosphere(3)
    t = reg.MeshTopology.from_faces(f, len(d))
    v = torch.tensor(d * 0.5)
    a = float(reg.laplacian_loss(v, t, 0.05, kind))
    b = float(reg.laplacian_loss(v * 3, t, 0.15, kind))
    assert a > 0 and a == pytest.approx(b, rel=1e-9)


@pytest.mark.parametrize("kind", ["uniform", "cotangent"])
def test_laplacian_magnitudes_agree_on_a_sphere(kind):
    d, f = icosphere(4)
    R = 0.5
    t = reg.MeshTopology.from_faces(f, len(d))
    v = torch.tensor(d * R)
    e = v[t.edges[:, 0]] - v[t.edges[:, 1]]
    h = float(e.norm(dim=1).mean())
    val = float(reg.laplacian_loss(v, t, h, kind))
    expected = (h / (2 * R)) ** 2  # (h/2 H)^2 with H = 1/R
    assert val == pytest.approx(expected, rel=0.35)


def test_gradients_match_finite_differences():
    rng = np.random.default_rng(0)
    v, f = grid(4, z=lambda x, y: 0.1 * np.sin(x) * np.cos(y))
    v = v + 0.05 * rng.normal(size=v.shape)
    t = reg.MeshTopology.from_faces(f, len(v))
    vt = torch.tensor(v, requires_grad=True)
    for fn in (
        lambda x: reg.edge_length_loss(x, t, 0.7),
        lambda x: reg.normal_consistency_loss(x, t),
        lambda x: reg.laplacian_loss(x, t, 0.7, "uniform"),
    ):
        assert torch.autograd.gradcheck(fn, (vt,), eps=1e-6, atol=1e-6)


def test_edge_length_loss_known_value_and_gradient():
    v = torch.tensor([[0.0, 0, 0], [3.0, 0, 0], [0.0, 4.0, 0]], dtype=torch.float64, requires_grad=True)
    t = reg.MeshTopology.from_faces(np.array([[0, 1, 2]]), 3)
    loss = reg.edge_length_loss(v, t, h=2.0)
    # edges 3, 4, 5: sqrt(mean(9, 16, 25)) / 2
    assert loss.item() == pytest.approx(np.sqrt(50 / 3) / 2)
    loss.backward()
    # d/dv0 of sqrt(S/3)/2 with S = |v1-v0|^2 + |v2-v0|^2 + |v1-v2|^2: -(v1-v0 + v2-v0) / (6 sqrt(S/3))
    expected = -(np.array([3.0, 0, 0]) + np.array([0, 4.0, 0])) / (6 * np.sqrt(50 / 3))
    np.testing.assert_allclose(v.grad[0].numpy(), expected, rtol=1e-10)


def test_normal_consistency_known_values():
    f = np.array([[0, 1, 2], [0, 3, 1]])  # two triangles sharing edge (0, 1)
    t = reg.MeshTopology.from_faces(f, 4)
    flat = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0]], dtype=torch.float64)
    assert float(reg.normal_consistency_loss(flat, t)) == pytest.approx(0.0, abs=1e-15)
    bent = flat.clone()
    bent[3] = torch.tensor([0.5, 0.0, -1.0])  # second face turned by 90 degrees
    assert float(reg.normal_consistency_loss(bent, t)) == pytest.approx(1.0)


def bilateral_reference(s, d, s1, s2, r, valid):
    """Brute-force eq. 9 in numpy."""
    H, W, _ = s.shape
    err, n = 0.0, 0
    for i in range(H):
        for j in range(W):
            if not valid[i, j]:
                continue
            num = np.zeros(s.shape[2])
            den = 0.0
            for a in range(max(0, i - r), min(H, i + r + 1)):
                for b in range(max(0, j - r), min(W, j + r + 1)):
                    if not valid[a, b]:
                        continue
                    w = np.exp(-((a - i) ** 2 + (b - j) ** 2) / (2 * s1**2) - np.sum((d[i, j] - d[a, b]) ** 2) / (2 * s2**2))
                    num += w * s[a, b]
                    den += w
            err += np.abs(s[i, j] - num / den).mean()
            n += 1
    return err / n


def test_specular_bilateral_matches_brute_force():
    rng = np.random.default_rng(1)
    s = rng.random((7, 9, 1))
    d = rng.random((7, 9, 3))
    valid = rng.random((7, 9)) > 0.2
    got = reg.specular_bilateral_loss(torch.tensor(s), torch.tensor(d), 1.3, 0.4, 2, torch.tensor(valid))
    assert float(got) == pytest.approx(bilateral_reference(s, d, 1.3, 0.4, 2, valid), rel=1e-9)


def test_specular_bilateral_respects_diffuse_edges():
    s = np.zeros((8, 8, 1))
    s[:, 4:] = 0.8
    d_edge = np.zeros((8, 8, 3))
    d_edge[:, 4:] = 1.0  # diffuse changes where specular does: no penalty
    d_flat = np.full((8, 8, 3), 0.5)  # flat diffuse: the specular step is penalized
    a = float(reg.specular_bilateral_loss(torch.tensor(s), torch.tensor(d_edge), 1.0, 0.1, 2))
    b = float(reg.specular_bilateral_loss(torch.tensor(s), torch.tensor(d_flat), 1.0, 0.1, 2))
    assert a < 1e-12 and b > 0.05
    const = float(reg.specular_bilateral_loss(torch.full((8, 8, 1), 0.3), torch.rand(8, 8, 3)))
    assert const == pytest.approx(0.0, abs=1e-6)
    # no gradient reaches the diffuse map (it only steers the weights)
    dd = torch.tensor(d_flat, requires_grad=True)
    ss = torch.tensor(s, requires_grad=True)
    reg.specular_bilateral_loss(ss, dd).backward()
    assert dd.grad is None and torch.isfinite(ss.grad).all()


def test_roughness_tv_known_value():
    H, W = 5, 4
    r = torch.tensor(np.tile(0.1 * np.arange(H)[:, None, None], (1, W, 1)))
    # vertical differences 0.1 on (H-1) x W pairs, none horizontal
    assert float(reg.roughness_tv_loss(r)) == pytest.approx(0.1 * (H - 1) * W / (H * W))
    valid = torch.ones(H, W, dtype=torch.bool)
    valid[:, 0] = False
    assert float(reg.roughness_tv_loss(r, valid)) == pytest.approx(0.1 * (H - 1) * (W - 1) / ((W - 1) * H))


def test_shape_errors():
    t = reg.MeshTopology.from_faces(np.array([[0, 1, 2]]), 3)
    with pytest.raises(ValueError, match=r"v_pos must be \(3, 3\)"):
        reg.edge_length_loss(torch.zeros(4, 3), t, 1.0)
    with pytest.raises(ValueError, match="h must be > 0"):
        reg.laplacian_loss(torch.zeros(3, 3), t, 0.0)
    with pytest.raises(ValueError, match="differ in size"):
        reg.specular_bilateral_loss(torch.zeros(4, 4, 1), torch.zeros(5, 5, 3))
    with pytest.raises(ValueError, match=r"\(H, W, C\)"):
        reg.roughness_tv_loss(torch.zeros(4, 4))
