"""SfM's tracks as a camera term (recon/optimize/tracks.py): the points eliminated by
Gauss-Newton, the term's camera gradients against finite differences, and extremes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from recon.optimize.camera_refine import CameraRefinement
from recon.optimize.tracks import SfmTracks, TrackTerm
from tests.optimize.test_camera_refine import _ring


def _tracks(cams, n_points=60, noise=0.0, seed=0):
    """Points around the origin seen by every camera, their exact (or noisy) projections."""
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-0.6, 0.6, size=(n_points, 3))
    view, point, uv = [], [], []
    for k, c in enumerate(cams):
        x = pts @ c.world_to_camera[:3, :3].T + c.world_to_camera[:3, 3]
        p = x @ c.K.T
        view.append(np.full(n_points, k))
        point.append(np.arange(n_points))
        uv.append(p[:, :2] / p[:, 2:3] + noise * rng.normal(size=(n_points, 2)))
    return SfmTracks(tuple(c.stem for c in cams), pts, np.concatenate(view), np.concatenate(point),
                     np.concatenate(uv), max(noise, 0.25))


def test_exact_tracks_cost_nothing_and_moved_points_come_back():
    cams = _ring()
    tr = _tracks(cams)
    term = TrackTerm(tr)
    ref = CameraRefinement(cams, gauge=False)
    assert term.loss(ref, cams).item() < 1e-12
    assert np.abs(tr.reprojection(cams)).max() < 1e-9
    with torch.no_grad():
        term.points.add_(torch.tensor(np.random.default_rng(1).normal(scale=0.05, size=tr.points.shape)))
    assert term.loss(ref, cams).item() > 1.0
    term.retriangulate(ref, cams, iterations=3)
    np.testing.assert_allclose(term.points.detach().numpy(), tr.points, atol=1e-7)


def test_camera_gradients_match_finite_differences():
    """d(term)/d(rotation, translation, focal) at points eliminated for the perturbed cameras:
    by the envelope theorem the partial gradient is the reduced cost's."""
    cams = _ring()
    tr = _tracks(cams, noise=0.3, seed=2)
    ref = CameraRefinement(cams, gauge=False)
    with torch.no_grad():
        ref.rotation[2, 1] = np.deg2rad(0.3)
        ref.translation[4, 0] = 0.01
        ref.log_focal[0] = 0.004
    term = TrackTerm(tr)

    def reduced() -> float:
        term.retriangulate(ref, cams, iterations=6)
        return float(term.loss(ref, cams))

    reduced()
    ref.zero_grad()
    term.loss(ref, cams).backward()
    for p, i, eps in ((ref.rotation, (2, 1), 1e-5), (ref.translation, (4, 0), 1e-5), (ref.log_focal, (0,), 1e-6)):
        g = float(p.grad[i])
        with torch.no_grad():
            p[i] += eps
        up = reduced()
        with torch.no_grad():
            p[i] -= 2 * eps
        down = reduced()
        with torch.no_grad():
            p[i] += eps
        reduced()
        fd = (up - down) / (2 * eps)
        assert g == pytest.approx(fd, rel=0.02, abs=1e-3 * max(abs(fd), 1.0)), (p.shape, i, g, fd)


def test_points_behind_a_camera_and_far_outliers_stay_finite():
    cams = _ring()
    tr = _tracks(cams)
    pts = tr.points.copy()
    pts[0] = cams[0].center + 0.0  # at a camera's centre
    pts[1] = cams[1].center - 2.0 * cams[1].world_to_camera[2, :3]  # behind camera 1
    uv = tr.uv.copy()
    uv[5] += 1e4  # an outlier far outside the image
    term = TrackTerm(SfmTracks(tr.stems, pts, tr.view, tr.point, uv, tr.sigma_px))
    ref = CameraRefinement(cams, gauge=False)
    loss = term.loss(ref, cams)
    loss.backward()
    assert torch.isfinite(loss)
    assert torch.isfinite(ref.rotation.grad).all() and torch.isfinite(ref.translation.grad).all()
    term.retriangulate(ref, cams)
    assert torch.isfinite(term.points).all()
    # the Huber cost grows linearly: the outlier costs 2 h |r| / sigma (~2.4e5 over 360
    # observations), not (|r| / sigma)^2 (~1.6e9); points behind their camera cost nothing there
    assert term.loss(ref, cams).item() < 2e3
    r = term.residuals(ref, cams).detach().numpy()
    assert r[(tr.view == 1) & (tr.point == 1)].item() == 0.0
