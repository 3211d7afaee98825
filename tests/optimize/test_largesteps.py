import numpy as np
import pytest
import torch

from recon.optimize.largesteps import AdamUniform, LargeSteps, combinatorial_laplacian
from synthetic import icosphere


def test_combinatorial_laplacian_rows_sum_to_zero():
    d, f = icosphere(2)
    L = combinatorial_laplacian(f, len(d))
    assert abs(L - L.T).max() == 0
    np.testing.assert_allclose(np.asarray(L.sum(axis=1)).ravel(), 0.0)
    deg = L.diagonal()
    assert set(np.unique(deg)) <= {5.0, 6.0}  # icosphere valences


def test_round_trip_and_gradient():
    d, f = icosphere(2)
    ls = LargeSteps(f, len(d), lam=3.0)
    v = torch.tensor(d * 0.4 + 0.1)
    u = ls.to_differential(v)
    torch.testing.assert_close(ls.from_differential(u), v, rtol=0, atol=1e-12)
    # d/du of <w, M^-1 u> = M^-1 w (M symmetric)
    w = torch.randn(len(d), 3, dtype=torch.float64)
    uu = u.clone().requires_grad_(True)
    (ls.from_differential(uu) * w).sum().backward()
    np.testing.assert_allclose(uu.grad.numpy(), ls.solve_np(w.numpy()), atol=1e-12)
    uu2 = u[:30].clone()
    with pytest.raises(ValueError, match="u must be"):
        ls.from_differential(uu2)
    with pytest.raises(ValueError, match="lambda"):
        LargeSteps(f, len(d), lam=0.0)


def test_smoothing_of_a_spike():
    """A gradient on one vertex becomes a smooth bump: M^-1 e_i decays with graph distance."""
    d, f = icosphere(3)
    ls = LargeSteps(f, len(d), lam=5.0)
    g = np.zeros((len(d), 3))
    g[0] = 1.0
    x = ls.solve_np(g)[:, 0]
    assert x[0] == x.max() and x[0] < 0.5
    far = np.argmax(np.linalg.norm(d - d[0], axis=1))
    assert x[far] < 1e-3 * x[0] and np.all(x > -1e-12)


def test_adam_uniform_step():
    p = torch.zeros(4, requires_grad=True)
    opt = AdamUniform([p], lr=0.1)
    p.grad = torch.tensor([1.0, 2.0, -4.0, 0.0])
    opt.step()
    # first step: m_hat = g, v_hat = g^2, divided by the max |g| = 4
    torch.testing.assert_close(p.detach(), -0.1 * torch.tensor([0.25, 0.5, -1.0, 0.0]), rtol=1e-5, atol=1e-7)
    sd = opt.state_dict()
    opt2 = AdamUniform([p], lr=0.1)
    opt2.load_state_dict(sd)
    assert opt2.state[p]["step"] == 1
