import numpy as np
import pytest
import torch

from recon.optimize.params import Parameterization, albedo_param, constant_map, roughness_param


@pytest.mark.parametrize("kind", ["sigmoid", "clamp"])
def test_round_trip_and_range(kind):
    p = roughness_param(0.02, kind)
    vals = np.array([0.02, 0.05, 0.5, 0.99, 1.0], np.float32)
    back = p.value(p.raw(vals)).numpy()
    tol = 1e-3 if kind == "sigmoid" else 0  # sigmoid keeps the ends 1e-4 of the range inside
    np.testing.assert_allclose(back, vals, atol=tol)
    raw = torch.linspace(-1e3, 1e3, 101)
    v = p.value(raw)
    assert torch.all(v >= 0.02) and torch.all(v <= 1.0)


@pytest.mark.parametrize("kind", ["sigmoid", "clamp"])
@pytest.mark.parametrize("value", [0.0, 1.0])
def test_albedo_extremes_have_finite_gradients(kind, value):
    p = albedo_param(kind)
    raw = p.raw(np.full((4, 4, 3), value, np.float32)).requires_grad_(True)
    v = p.value(raw)
    assert torch.allclose(v, torch.full_like(v, value), atol=2e-4)
    (v * torch.linspace(-1, 1, v.numel()).reshape(v.shape)).sum().backward()
    assert torch.isfinite(raw.grad).all()
    assert raw.grad.abs().max() > 0  # still moves away from the end


@pytest.mark.parametrize("kind", ["sigmoid", "clamp"])
@pytest.mark.parametrize("value", [0.02, 1.0])
def test_roughness_extremes_have_finite_gradients(kind, value):
    p = roughness_param(0.02, kind)
    raw = p.raw(np.full((2, 2, 1), value, np.float32)).requires_grad_(True)
    p.value(raw).pow(2).sum().backward()
    assert torch.isfinite(raw.grad).all() and raw.grad.abs().max() > 0


def test_sigmoid_gradient_matches_formula():
    p = Parameterization(0.2, 1.0, "sigmoid")
    raw = torch.tensor([-3.0, 0.0, 2.0], dtype=torch.float64, requires_grad=True)
    p.value(raw).sum().backward()
    s = torch.sigmoid(raw.detach())
    torch.testing.assert_close(raw.grad, 0.8 * s * (1 - s))


def test_clamp_projection():
    p = albedo_param("clamp")
    raw = torch.tensor([-0.5, 0.3, 1.7])
    p.project_(raw)
    assert raw.tolist() == pytest.approx([0.0, 0.3, 1.0])
    q = albedo_param("sigmoid")
    raw2 = torch.tensor([-5.0, 5.0])
    q.project_(raw2)  # nothing to do for sigmoid logits
    assert raw2.tolist() == [-5.0, 5.0]


def test_errors_and_constant_map():
    with pytest.raises(ValueError, match="hi > lo"):
        Parameterization(1.0, 0.5)
    with pytest.raises(ValueError, match="kind"):
        Parameterization(0.0, 1.0, "tanh")
    m = constant_map(8, 3, 0.25)
    assert m.shape == (8, 8, 3) and m.dtype == np.float32 and np.all(m == 0.25)


def test_texture_pyramid():
    from recon.optimize.params import TexturePyramid

    raw = torch.randn(16, 16, 3)
    p = TexturePyramid(raw, levels=4)
    assert [tuple(lv.shape) for lv in p.levels] == [(16, 16, 3), (8, 8, 3), (4, 4, 3)]  # stops at 4 texels
    torch.testing.assert_close(p.full(), raw)
    w = torch.rand(16, 16, 3)
    (p.full() * w).sum().backward()
    torch.testing.assert_close(p.levels[0].grad, w)
    for lv in p.levels[1:]:
        # a coarse texel collects the gradient of every texel it covers (bilinear adjoint)
        assert lv.grad.sum().item() == pytest.approx(w.sum().item(), rel=1e-5)
        assert torch.all(lv.grad > 0)
    with torch.no_grad():
        p.levels[2].add_(1.0)
    q = TexturePyramid.from_state(p.state())
    torch.testing.assert_close(q.full(), p.full())
    # the clamp parameterization keeps the sum of levels in range
    c = albedo_param("clamp")
    p.project_(c)
    assert p.full().min() >= -1e-6 and p.full().max() <= 1 + 1e-6
    assert len(TexturePyramid(raw, levels=1).parameters()) == 1
    with pytest.raises(ValueError, match=r"\(T, T, C\)"):
        TexturePyramid(torch.zeros(4, 4))
