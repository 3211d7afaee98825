"""The one fitting loop (recon/optimize/fitting.py) and the objective's list of terms."""

import numpy as np
import pytest
import torch

from recon.optimize import fitting, objective
from recon.optimize.settings import OptimizeSettings


def test_decay_runs_from_one_to_a_tenth():
    assert fitting.decay(0, 50) == 1.0
    assert fitting.decay(49, 50) == pytest.approx(0.1)
    assert fitting.decay(0, 1) == 1.0 and fitting.decay(0, 0) == 1.0  # no division by zero


def _problem(seed=0):
    g = torch.Generator().manual_seed(seed)
    target = torch.rand(16, generator=g)
    x = torch.zeros(16, requires_grad=True)
    y = torch.zeros(3, requires_grad=True)
    return target, x, y


def test_fit_is_adam_with_the_decay_bit_for_bit():
    """fit() equals Adam written out (the image term, then the priors, weighted; rates times
    decay; a projection after each step) to the last bit."""
    n, w = 25, {"render": 1.0, "roughness": 0.3}

    target, x, y = _problem()
    calls = []

    def image_term(it):
        calls.append(it)
        return ((x - target) ** 2).mean() + (y ** 2).sum()

    def project():
        with torch.no_grad():
            x.clamp_(0.0, 0.8)

    got = fitting.fit([{"params": [x], "lr": 0.05}, {"params": [y], "lr": 0.01}], n, image_term, w,
                      priors=lambda: {"roughness": (x[1:] - x[:-1]).abs().mean()}, project=project)
    assert calls == list(range(n + 1))  # one evaluation per step and one after the last

    target, x2, y2 = _problem()
    opt = torch.optim.Adam([{"params": [x2], "lr": 0.05}, {"params": [y2], "lr": 0.01}])
    for it in range(n):
        loss = ((x2 - target) ** 2).mean() + (y2 ** 2).sum()
        total = 0 + 1.0 * loss + 0.3 * (x2[1:] - x2[:-1]).abs().mean()
        for g, lr in zip(opt.param_groups, (0.05, 0.01), strict=True):
            g["lr"] = lr * 0.1 ** (it / (n - 1))
        opt.zero_grad(set_to_none=True)
        total.backward()
        opt.step()
        with torch.no_grad():
            x2.clamp_(0.0, 0.8)
    assert torch.equal(x, x2) and torch.equal(y, y2)
    assert torch.equal(got, ((x2 - target) ** 2).mean() + (y2 ** 2).sum())


def test_fit_without_final_loss_and_without_steps():
    target, x, _ = _problem()
    calls = []

    def image_term(it):
        calls.append(it)
        return ((x - target) ** 2).mean()

    fitting.fit([{"params": [x], "lr": 0.1}], 5, image_term, {"render": 1.0}, final_loss=False)
    assert calls == [0, 1, 2, 3, 4]
    calls.clear()
    x0 = x.detach().clone()
    out = fitting.fit([{"params": [x], "lr": 0.1}], 0, image_term, {"render": 1.0})
    assert calls == [0] and torch.equal(x.detach(), x0) and torch.isfinite(out)


def test_fit_refuses_a_term_without_a_weight():
    target, x, _ = _problem()
    with pytest.raises(KeyError, match="without a weight"):
        fitting.fit([{"params": [x], "lr": 0.1}], 2, lambda it: ((x - target) ** 2).mean(), {"render": 1.0},
                    priors=lambda: {"specular": x.sum()})


class _Refinement:
    def prior_loss(self, idx=None):
        return torch.tensor(1.0)


class _Tracks:
    def retriangulate(self, refinement, cameras):
        self.moved = True

    def loss(self, refinement, cameras):
        return torch.tensor(2.0)


def test_every_term_is_named_in_TERMS():
    """The terms the objective assembles (the main loop's weights, the camera prior, the imaging
    terms' prior, the tracks) are all in objective.TERMS; a term with weight 0 is not evaluated."""
    assert set(objective.weights(OptimizeSettings())) <= set(objective.TERMS)
    w = {"camera": 1.0, "imaging": 1.0, "tracks": 1.0}
    tracks = _Tracks()
    terms = {**objective.camera_terms(_Refinement(), None, w), **objective.imaging_terms(lambda: torch.tensor(3.0), w),
             **objective.tracks_terms(tracks, _Refinement(), [], w)}
    assert set(terms) == {"camera", "imaging", "tracks"} <= set(objective.TERMS)
    assert tracks.moved  # retriangulated before its loss
    zero = dict.fromkeys(w, 0.0)
    assert not objective.camera_terms(_Refinement(), None, zero)
    assert not objective.imaging_terms(lambda: 1 / 0, zero)
    assert not objective.tracks_terms(_Tracks(), None, [], zero)


def test_eq6_once():
    """render_loss (mean over views, pixels, channels) and pixel_loss (per pixel) reduce the
    same residual, objective.image_residual."""
    rng = np.random.default_rng(1)
    r = torch.tensor(rng.uniform(0, 2, (2, 4, 5, 3)), dtype=torch.float32)
    t = torch.tensor(rng.uniform(0, 2, (2, 4, 5, 3)), dtype=torch.float32)
    wpx = torch.tensor(rng.uniform(0, 1, (2, 4, 5, 1)), dtype=torch.float32)
    res = objective.image_residual(r, objective.tone_map(t, "log", 0.5), wpx, "log", 0.5)
    assert torch.equal(objective.render_loss(r, t, wpx, "log", 0.5), res.mean())
    assert torch.equal(objective.pixel_loss(r, objective.tone_map(t, "log", 0.5), wpx, "log", 0.5), res.mean(-1))
