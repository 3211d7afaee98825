"""The material models and their fits on a fixed mesh (G-buffers).

After the coarse-to-fine shape optimization the geometry is fixed, so every photo becomes a
fixed set of surface samples (a G-buffer: per sample its pixel, UV, ``mu = n . w`` and ``1/d^2``,
traced once with open3d). Shading them in closed form (DESIGN section 3, collocated) is cheap
and exact for this image formation, so several material models can be fitted to the training
views (:func:`fit_model`, Adam through :func:`recon.optimize.fitting.fit` on the same
parameterizations and priors as the main loop) and scored on views the optimization never saw
(:func:`tile_errors`); :mod:`recon.optimize.material_select` chooses among them.

The models, in increasing complexity (the ``material_model`` object of ``summary.json`` and
``report/metrics.json``)::

    {"specular": "none" | "uniform" | "textured",
     "specular_color": "mono" | "rgb",
     "roughness": "uniform" | "textured"}

Diffuse albedo is always a texture. The held-out error is the rendering loss of the main loop
(eq. 6: mean |Phi(render) - Phi(target)| over unclipped pixels, Phi the same tone map) per
image tile.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np
import torch

from recon.io.mesh import Mesh
from recon.optimize.params import TexturePyramid, albedo_param, roughness_param
from recon.optimize import fitting, objective
from recon.optimize.formation import surface_radiance
from recon.optimize.gbuffer import GBuffer, build_gbuffer
from recon.optimize.views import ViewSet

SPECULAR_KINDS = ("none", "uniform", "textured")
SPECULAR_COLORS = ("mono", "rgb")
ROUGHNESS_KINDS = ("uniform", "textured")


@dataclass(frozen=True)
class MaterialModel:
    """Which parts of the SVBRDF vary over the surface (see the module docstring)."""

    specular: str = "textured"
    specular_color: str = "mono"
    roughness: str = "textured"

    def __post_init__(self):
        for name, allowed in (("specular", SPECULAR_KINDS), ("specular_color", SPECULAR_COLORS),
                              ("roughness", ROUGHNESS_KINDS)):
            if getattr(self, name) not in allowed:
                raise ValueError(f"material model: {name} must be one of {allowed}, got {getattr(self, name)!r}")

    @property
    def specular_channels(self) -> int:
        return 3 if self.specular_color == "rgb" else 1

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def label(self) -> str:
        if self.specular == "none":
            return "diffuse only"
        parts = [f"{self.specular} {'RGB ' if self.specular_color == 'rgb' else ''}specular",
                 f"{self.roughness} roughness"]
        return ", ".join(parts)


DIFFUSE_ONLY = MaterialModel("none", "mono", "uniform")


def model_from_settings(specular_channels: int) -> MaterialModel:
    """The model of the main loop: every map a texture."""
    return MaterialModel("textured", "rgb" if int(specular_channels) == 3 else "mono", "textured")


# ---------------------------------------------------------------------- the fit's problem
class MaterialProblem:
    """A G-buffer and its targets restricted to the pixels that can carry loss (object in the
    photo or surface in the render); the loss is still the mean over every pixel of every view."""

    def __init__(self, gb: GBuffer, targets: ViewSet, tone: str, scale: float):
        V, H, W = gb.shape
        keep = np.zeros(V * H * W, bool)
        keep[gb.pixel.numpy()] = True
        keep |= np.asarray(targets.masks).reshape(-1) > 0
        self.pixels = np.flatnonzero(keep)
        remap = np.full(V * H * W, -1, np.int64)
        remap[self.pixels] = np.arange(len(self.pixels))
        self.gb = gb
        self.sample_pixel = torch.from_numpy(remap[gb.pixel.numpy()])
        self.grid = gb.grid
        self.n_total = V * H * W
        self.tone, self.scale = tone, scale
        tgt = targets.images.reshape(-1, 3)[torch.from_numpy(self.pixels)]
        self.target_phi = objective.tone_map(tgt, tone, scale)
        self.weight = targets.weights.reshape(-1, 1)[torch.from_numpy(self.pixels)]

    def render(self, diffuse, specular, roughness, light, r_min) -> torch.Tensor:
        """(P, 3) radiance of the kept pixels under the ideal image formation (collocated light,
        known exposure, linear: :func:`recon.optimize.formation.surface_radiance` without terms)."""
        return self.pixel_mean(surface_radiance(self.gb, self.grid, None, None, None, diffuse, specular, roughness,
                                                light, r_min, None))

    def pixel_mean(self, rad: torch.Tensor) -> torch.Tensor:
        """(P, 3) mean of each kept pixel's samples ``rad`` (N, 3) (a miss counts as 0)."""
        out = torch.zeros((len(self.pixels), 3), dtype=rad.dtype).index_add(0, self.sample_pixel, rad)
        return out / self.gb.spp

    def pixel_errors(self, rendered: torch.Tensor) -> torch.Tensor:
        """(P,) loss per kept pixel (mean over channels, 0 on clipped pixels)."""
        return objective.pixel_loss(rendered, self.target_phi, self.weight, self.tone, self.scale)

    def loss(self, rendered: torch.Tensor) -> torch.Tensor:
        return self.pixel_errors(rendered).sum() / self.n_total


# ---------------------------------------------------------------------- fitting
@dataclass(frozen=True)
class SelectionSettings:
    """How candidates are fitted and compared (from OptimizeSettings, see there)."""

    iterations: int = 150
    lr: float = 0.05
    z: float = 2.0
    min_gain: float = 0.005
    tile: int = 8
    trim: float = 0.0  # the gain of specular and roughness sits in the few highlight tiles: do not trim them
    tone_map: str = "log"
    r_min: float = 0.02
    parameterization: str = "sigmoid"
    texture_levels: int = 4
    w_specular: float = 0.01
    w_roughness: float = 0.001
    bilateral_sigma_space: float = 1.0
    bilateral_sigma_color: float = 0.1
    bilateral_radius: int = 2


@dataclass
class Fit:
    model: MaterialModel
    maps: dict  # name -> (T, T, C) float32 numpy, full size (uniform maps broadcast)
    train_loss: float
    heldout: float = float("nan")
    tile_errors: np.ndarray | None = None
    seconds: float = 0.0


def covered_mean(m: np.ndarray, covered: np.ndarray) -> np.ndarray:
    sel = m[covered] if covered.any() else m.reshape(-1, m.shape[-1])
    return sel.reshape(-1, m.shape[-1]).mean(0)


class MaterialParams:
    """The raw parameters of one candidate and their values as maps."""

    def __init__(self, model: MaterialModel, init: dict, covered: np.ndarray, s: SelectionSettings):
        self.model = model
        self.T = init["diffuse"].shape[0]
        kind = s.parameterization
        self.p_alb, self.p_rough = albedo_param(kind), roughness_param(s.r_min, kind)
        self.diffuse = TexturePyramid(self.p_alb.raw(init["diffuse"]), s.texture_levels)
        self.specular = self.roughness = None
        C = model.specular_channels
        spec = init["specular"]
        if spec.shape[2] != C:
            spec = np.repeat(spec.mean(2, keepdims=True), C, axis=2)
        if model.specular == "uniform":
            self.specular = TexturePyramid(self.p_alb.raw(covered_mean(spec, covered)[None, None]), 1)
        elif model.specular == "textured":
            self.specular = TexturePyramid(self.p_alb.raw(spec), s.texture_levels)
        rough = init["roughness"]
        if model.specular != "none":
            if model.roughness == "uniform":
                self.roughness = TexturePyramid(self.p_rough.raw(covered_mean(rough, covered)[None, None]), 1)
            else:
                self.roughness = TexturePyramid(self.p_rough.raw(rough), s.texture_levels)

    def parameters(self):
        out = self.diffuse.parameters()
        for p in (self.specular, self.roughness):
            if p is not None:
                out += p.parameters()
        return out

    def values(self):
        d = self.p_alb.value(self.diffuse.full())
        sp = self.p_alb.value(self.specular.full()) if self.specular is not None else None
        ro = self.p_rough.value(self.roughness.full()) if self.roughness is not None else None
        return d, sp, ro

    def priors(self, d, sp, ro, valid: torch.Tensor, w: dict, s: SelectionSettings) -> dict:
        """The material priors of the maps ``d``, ``sp``, ``ro`` (:meth:`values`) where they are
        textures (:func:`recon.optimize.objective.material_terms`; ``valid``: the covered texels)."""
        return objective.material_terms(
            sp if self.model.specular == "textured" else None, d, ro if self.model.roughness == "textured" else None,
            valid, w, s.bilateral_sigma_space, s.bilateral_sigma_color, s.bilateral_radius)

    def project_(self):
        self.diffuse.project_(self.p_alb)
        if self.specular is not None:
            self.specular.project_(self.p_alb)
        if self.roughness is not None:
            self.roughness.project_(self.p_rough)

    @torch.no_grad()
    def maps(self) -> dict:
        d, sp, ro = self.values()
        T = self.T
        C = self.model.specular_channels
        spec = np.zeros((T, T, C), np.float32) if sp is None else np.broadcast_to(sp.numpy(), (T, T, C))
        rough = np.ones((T, T, 1), np.float32) if ro is None else np.broadcast_to(ro.numpy(), (T, T, 1))
        return {"diffuse": d.numpy().astype(np.float32), "specular": np.ascontiguousarray(spec, np.float32),
                "roughness": np.ascontiguousarray(rough, np.float32)}


def fit_model(model: MaterialModel, gb: GBuffer, targets: ViewSet, init: dict, covered: np.ndarray,
              light: float, tone_scale: float, s: SelectionSettings,
              problem: MaterialProblem | None = None) -> Fit:
    """Fit the maps of ``model`` to the training views (full batch, Adam); return the maps."""
    t0 = time.perf_counter()
    prob = problem if problem is not None else MaterialProblem(gb, targets, s.tone_map, tone_scale)
    P = MaterialParams(model, init, covered, s)
    valid, w = torch.from_numpy(covered), objective.fit_weights(s)
    values = []  # the maps of the step's image term, for its priors

    def image_term(it: int) -> torch.Tensor:
        values[:] = P.values()
        return prob.loss(prob.render(*values, light, s.r_min))

    loss = fitting.fit([{"params": P.parameters(), "lr": s.lr}], max(int(s.iterations), 0), image_term, w,
                       priors=lambda: P.priors(*values, valid, w, s), project=P.project_)
    return Fit(model, P.maps(), float(loss.detach()), seconds=time.perf_counter() - t0)


def tile_errors(maps: dict, model: MaterialModel, gb: GBuffer, targets: ViewSet, light: float, tone_scale: float,
                s: SelectionSettings) -> np.ndarray:
    """Mean loss per image tile (``s.tile`` pixels square) of the views; NaN where a tile has no
    unclipped pixel of either the object or the render."""
    prob = MaterialProblem(gb, targets, s.tone_map, tone_scale)
    with torch.no_grad():
        spec = None if model.specular == "none" else torch.tensor(np.asarray(maps["specular"], dtype=np.float32))
        rad = prob.render(torch.tensor(np.asarray(maps["diffuse"], dtype=np.float32)), spec,
                          torch.tensor(np.asarray(maps["roughness"], dtype=np.float32)), light, s.r_min)
        pe = prob.pixel_errors(rad).numpy()
    V, H, W = gb.shape
    e = np.zeros(V * H * W)
    e[prob.pixels] = pe
    e = e.reshape(V, H, W)
    fg = np.zeros(V * H * W, bool)
    fg[prob.pixels] = prob.weight[:, 0].numpy() > 0
    fg = fg.reshape(V, H, W)
    t = int(s.tile)
    out = []
    for v in range(V):
        for y in range(0, H, t):
            for x in range(0, W, t):
                m = fg[v, y:y + t, x:x + t]
                out.append(e[v, y:y + t, x:x + t][m].mean() if m.any() else np.nan)
    return np.asarray(out, dtype=np.float64)


def heldout_error(mesh: Mesh, maps: dict, heldout: ViewSet, light: float, tone_scale: float, s: SelectionSettings,
                  spp: int = 4, seed: int = 0, model: MaterialModel | None = None) -> np.ndarray:
    """Per-tile held-out errors of a mesh and its maps (for the coarse-to-fine plateau test)."""
    gb = build_gbuffer(mesh, list(heldout.cameras), spp, seed)
    m = model or model_from_settings(maps["specular"].shape[2])
    return tile_errors(maps, m, gb, heldout, light, tone_scale, s)


