"""Fitting the camera's imaging terms (the image formation Phi_k of :mod:`recon.optimize.formation`)
with the material maps on a fixed mesh, and scoring them on held-out views: the G-buffer problem
(:class:`ImagingProblem`), the fit (:func:`fit_imaging`), the held-out scores
(:func:`heldout_tiles_under`) and the fits and scores under the terms the main loop used
(:func:`refit_under`, :func:`material_scorer_under`). Which terms to keep is decided in
:mod:`recon.optimize.imaging_select`.

The held-out views' own exposure gains are unknown: their tiles are split like a checkerboard and
the gains cross-fitted (maps and shared terms fixed): fitted on the black tiles to score the
white, on the white to score the black, so no tile scores a gain fitted on it and every tile
counts (scoring the white tiles only, the first design, halved the tiles the test sees: on a
glossy object with 0.5-stop exposure jitter a uniform specular lobe's gain fell from 3.3 to 1.9
SE, ``tests/optimize/test_imaging.py::test_material_selection_under_the_imaging_terms``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from recon.optimize import fitting, objective
from recon.optimize.formation import (ImagingModel, ImagingParams, camera_response, srgb_encode,
                                      surface_radiance)
from recon.optimize.gbuffer import GBuffer, build_gbuffer
from recon.optimize.material import Fit, MaterialModel, MaterialParams, MaterialProblem, SelectionSettings
from recon.optimize.views import ViewSet, view_exposures


@dataclass(frozen=True)
class ImagingSettings:
    """How the imaging terms are fitted (see the module docstring)."""

    lr: float = 0.05
    exposure_prior: float = 0.25  # standard deviation of log g_k around the EXIF exposure
    tone_knots: int = 16
    heldout_iterations: int = 60
    tone_gain: bool = True  # the curve's input scale c fitted (False: c = 1, the first design)
    tone_gain_prior: float = 1.0  # standard deviation of log c


# ---------------------------------------------------------------------- the problem
def camera_arrays(cameras) -> tuple[torch.Tensor, torch.Tensor]:
    """(V, 3, 3) world-to-camera rotations and (V, 3) centres of ``cameras`` (float32)."""
    R = torch.tensor(np.stack([c.world_to_camera[:3, :3] for c in cameras]), dtype=torch.float32)
    o = torch.tensor(np.stack([c.center for c in cameras]), dtype=torch.float32)
    return R, o


class ImagingProblem(MaterialProblem):
    """A G-buffer and its targets (the kept pixels as in the material fits,
    :class:`recon.optimize.material.MaterialProblem`) with the per-pixel data the imaging terms need:
    view index, squared image radius, checkerboard tile colour, and the recorded exposure of the
    pixel's view relative to the reference (``exposure``: image stem -> h_k / h_ref as linearize
    recorded it, :func:`recon.optimize.views.recorded_exposures`; views not in it, or None, at 1):
    the tone curve acts before linearize divided it out."""

    def __init__(self, gb: GBuffer, targets: ViewSet, tone: str, scale: float, tile: int = 8,
                 exposure: dict | None = None):
        if gb.position is None:
            raise ValueError("ImagingProblem needs a G-buffer with positions and normals (build_gbuffer)")
        super().__init__(gb, targets, tone, scale)
        V, H, W = gb.shape
        self.sample_view = gb.pixel // (H * W)
        self.target_linear = targets.images.reshape(-1, 3)[torch.from_numpy(self.pixels)]
        rest = self.pixels % (H * W)
        row, col = rest // W, rest % W
        self.pixel_view = torch.from_numpy(self.pixels // (H * W))
        r2 = ((col + 0.5 - W / 2) ** 2 + (row + 0.5 - H / 2) ** 2) / ((W / 2) ** 2 + (H / 2) ** 2)
        self.r2 = torch.tensor(r2, dtype=torch.float32)
        self.black = torch.from_numpy(((row // tile + col // tile) % 2 == 0))
        self.R, self.o = camera_arrays(targets.cameras)
        self.shape = (V, H, W)
        self.tile = int(tile)
        e = view_exposures(targets.cameras, exposure)
        self.view_exposure = e
        self.pixel_exposure = None if e is None else e[self.pixel_view]

    def render(self, d, sp, ro, light: float, r_min: float, im: ImagingParams) -> torch.Tensor:
        """(P, 3) predicted linearized values of the kept pixels (the image formation of
        :mod:`recon.optimize.formation`: :func:`surface_radiance` at the samples, their mean per
        pixel, :func:`camera_response`)."""
        rad = surface_radiance(self.gb, self.grid, self.sample_view, self.R, self.o, d, sp, ro, light, r_min, im)
        return camera_response(self.pixel_mean(rad), im, self.pixel_view, self.r2, self.pixel_exposure)

    def loss(self, rendered: torch.Tensor, select: torch.Tensor | None = None) -> torch.Tensor:
        e = self.pixel_errors(rendered)
        if select is not None:
            e = e * select
        return e.sum() / self.n_total

    def tile_errors(self, rendered: torch.Tensor, colour: str | None = "white") -> np.ndarray:
        """Mean loss per tile of the given checkerboard colour (None: every tile, in the order of
        :func:`recon.optimize.material.tile_errors`); NaN where a tile has no unclipped pixel."""
        V, H, W = self.shape
        e = np.zeros(V * H * W)
        e[self.pixels] = self.pixel_errors(rendered).detach().numpy()
        fg = np.zeros(V * H * W, bool)
        fg[self.pixels] = self.weight[:, 0].numpy() > 0
        e, fg = e.reshape(V, H, W), fg.reshape(V, H, W)
        t = self.tile
        out = []
        want = None if colour is None else (0 if colour == "black" else 1)
        for v in range(V):
            for y in range(0, H, t):
                for x in range(0, W, t):
                    if want is not None and ((y // t + x // t) % 2) != want:
                        continue
                    m = fg[v, y:y + t, x:x + t]
                    out.append(e[v, y:y + t, x:x + t][m].mean() if m.any() else np.nan)
        return np.asarray(out, dtype=np.float64)


# ---------------------------------------------------------------------- fitting
@dataclass
class ImagingFit:
    model: ImagingModel
    material: Fit
    params: ImagingParams
    train_loss: float
    heldout: float = float("nan")
    tile_errors: np.ndarray | None = None
    seconds: float = 0.0
    rmse_srgb: float = float("nan")


def fit_imaging(model: ImagingModel, material: MaterialModel, prob: ImagingProblem, init_maps: dict,
                covered: np.ndarray, light: float, s: SelectionSettings, im: ImagingSettings,
                init_params: ImagingParams | None = None, length: float = 1.0, tone_scale: float = 1.0,
                offset_given=None) -> ImagingFit:
    """Fit the material maps of ``material`` and the imaging terms of ``model`` to the training
    views of ``prob`` (full batch, Adam, the material fits' priors and schedule)."""
    t0 = time.perf_counter()
    P = MaterialParams(material, init_maps, covered, s)
    n_views = prob.shape[0]
    ip = ImagingParams(model, n_views, length, tone_scale, offset_given, im.tone_knots, tone_gain=im.tone_gain)
    if init_params is not None:
        ip.copy_from(init_params)
    groups = [{"params": P.parameters(), "lr": s.lr}] + ip.groups(im.lr)
    valid, w = torch.from_numpy(covered), {**objective.fit_weights(s), "imaging": 1.0}
    values = []  # the maps of the step's image term, for its priors

    def image_term(it: int) -> torch.Tensor:
        values[:] = P.values()
        return prob.loss(prob.render(*values, light, s.r_min, ip))

    def priors() -> dict:
        return {**P.priors(*values, valid, w, s), **objective.imaging_terms(
            lambda: ip.prior(im.exposure_prior, im.tone_gain_prior) / prob.n_total, w)}

    loss = fitting.fit(groups, max(int(s.iterations), 0), image_term, w, priors=priors, project=P.project_)
    fit = Fit(material, P.maps(), float(loss.detach()), seconds=time.perf_counter() - t0)
    return ImagingFit(model, fit, ip, float(loss.detach()), seconds=time.perf_counter() - t0)


def heldout_tiles(fit: ImagingFit, prob: ImagingProblem, light: float, s: SelectionSettings,
                  im: ImagingSettings) -> tuple[np.ndarray, float]:
    """Per-tile errors of the held-out views and the RMSE of sRGB-encoded values over their
    unclipped pixels (DESIGN section 5's image RMSE); a model with per-view exposure fits the
    held-out views' gains on the tiles of one checkerboard colour and is scored on the other
    (both ways round: :func:`heldout_tiles_under`)."""
    return heldout_tiles_under(fit.material.maps, fit.material.model, fit.params, prob, light, s, im)


def _heldout_gains(ip: ImagingParams, fit_on: torch.Tensor, render, prob: ImagingProblem, im: ImagingSettings) -> None:
    """The held-out views' exposure gains of ``ip`` fitted (from 1) on the pixels ``fit_on``."""
    with torch.no_grad():
        ip.log_gain.zero_()
    sel = fit_on.to(torch.float32)
    w = {"render": 1.0, "imaging": 1.0}
    fitting.fit([{"params": [ip.log_gain], "lr": 0.05}], int(im.heldout_iterations),
                lambda it: prob.loss(render(ip), sel), w, final_loss=False, priors=lambda: objective.imaging_terms(
                    lambda: ip.prior(im.exposure_prior, im.tone_gain_prior) / prob.n_total, w))


def heldout_tiles_under(maps: dict, material: MaterialModel, p: ImagingParams, prob: ImagingProblem, light: float,
                        s: SelectionSettings, im: ImagingSettings) -> tuple[np.ndarray, float]:
    """:func:`heldout_tiles` of given maps (of ``material``) under fitted imaging terms ``p``
    (their own views' exposure gains are not used: the held-out views' are fitted here).

    With exposure gains, each view's gain is fitted twice: on the black tiles of an 8-pixel
    checkerboard to score the white ones, and on the white to score the black (cross-fitting:
    no tile scores the gain it was fitted on, and every tile is scored). Returns every tile's
    error in the order of :func:`recon.optimize.material.tile_errors` (NaN where a tile has no
    unclipped pixel), so that runs under the imaging terms and under the ideal formation pair
    tile for tile; without exposure both colours are scored under ``p`` as they are."""
    with torch.no_grad():
        d = torch.tensor(np.asarray(maps["diffuse"], np.float32))
        sp = None if material.specular == "none" else torch.tensor(np.asarray(maps["specular"], np.float32))
        ro = torch.tensor(np.asarray(maps["roughness"], np.float32))
    ip = p.clone(n_views=prob.shape[0], normalize_gains=False)

    def render(q):
        return prob.render(d, sp, ro, light, s.r_min, q)

    kept = prob.weight[:, 0] > 0
    preds = {}
    for colour, fit_on in (("white", prob.black), ("black", ~prob.black)):
        if p.model.has("exposure"):
            _heldout_gains(ip, fit_on, render, prob, im)
        elif preds:
            preds[colour] = preds["white"]
            continue
        with torch.no_grad():
            preds[colour] = render(ip)
    with torch.no_grad():
        pred = torch.where(prob.black[:, None], preds["black"], preds["white"])
        tgt = prob.target_linear[kept]
        diff = srgb_encode(pred[kept]) - srgb_encode(tgt)
        rmse = float(torch.sqrt((diff * diff).mean())) if diff.numel() else float("nan")
    return prob.tile_errors(pred, None), rmse


def problems(mesh, train: ViewSet, heldout: ViewSet, s: SelectionSettings, tone_scale: float, spp: int,
              seed: int, exposure: dict | None = None) -> tuple[ImagingProblem, ImagingProblem, float]:
    """The training and held-out views' problems on a fixed mesh and the mesh's size."""
    gb_train = build_gbuffer(mesh, list(train.cameras), spp, seed)
    gb_held = build_gbuffer(mesh, list(heldout.cameras), spp, seed + 1)
    lo, hi = mesh.bbox()
    return (ImagingProblem(gb_train, train, s.tone_map, tone_scale, s.tile, exposure),
            ImagingProblem(gb_held, heldout, s.tone_map, tone_scale, s.tile, exposure), float(np.max(hi - lo)))


def refit_under(params: ImagingParams, material: MaterialModel, mesh, maps: dict, covered: np.ndarray,
                train_set: ViewSet, light: float, tone_scale: float, s: SelectionSettings, spp: int = 4,
                seed: int = 0, exposure: dict | None = None) -> ImagingFit:
    """The material maps of ``material`` refitted on the final mesh under the imaging terms the
    loop used (``params``: their values the start, refined with the maps), so that the maps the
    asset carries are those of the model the shape was fitted with (the material selection
    before it compares models under the ideal formation)."""
    gb = build_gbuffer(mesh, list(train_set.cameras), spp, seed)
    prob = ImagingProblem(gb, train_set, s.tone_map, tone_scale, s.tile, exposure)
    lo, hi = mesh.bbox()
    offset = None if params.offset_given is None else params.offset_given.numpy()
    return fit_imaging(params.model, material, prob, maps, covered, light, s, ImagingSettings(), params,
                       float(np.max(hi - lo)), tone_scale, offset)


def material_scorer_under(params: ImagingParams, mesh, covered: np.ndarray, train_set: ViewSet, heldout_set: ViewSet,
                          light: float, tone_scale: float, s: SelectionSettings, spp: int = 4, seed: int = 0,
                          exposure: dict | None = None):
    """A ``scorer`` for :func:`recon.optimize.material_select.select_material` that fits and compares the
    material models under the imaging terms the loop used (``params``: the start of each fit,
    refined with its maps, as :func:`refit_under` does) and scores them as the imaging selection
    does (:func:`heldout_tiles_under`: the held-out views' exposure gains fitted on one
    checkerboard colour, the errors on the other, both ways round). Under the ideal formation a
    phone's per-view exposure (up to +-50 % on the phone captures) is error every material model
    shares, and it buries a specular lobe's gain."""
    im = ImagingSettings()
    p_train, p_held, length = problems(mesh, train_set, heldout_set, s, tone_scale, spp, seed, exposure)
    offset = None if params.offset_given is None else params.offset_given.numpy()

    def scorer(material: MaterialModel, init: dict) -> Fit:
        fit = fit_imaging(params.model, material, p_train, init, covered, light, s, im, params, length,
                          tone_scale, offset)
        fit.material.tile_errors, _ = heldout_tiles(fit, p_held, light, s, im)
        return fit.material

    terms = ", ".join(params.model.terms) or "flash offset given"
    scorer.criterion = (f"; every model fitted under the loop's imaging terms ({terms}), held-out exposure gains "
                        "fitted on one checkerboard colour, errors on the other (both ways round)")
    return scorer
