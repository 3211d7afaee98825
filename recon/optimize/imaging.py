"""The camera's imaging in the objective (the paper's Phi_k of equation 6, DESIGN section 6), each
term kept only where the held-out views ask for it.

A phone breaks the renderer's idealised image formation a little: its flash sits beside the lens,
auto-exposure changes from shot to shot, its JPEGs carry a tone curve, its lens darkens the
corners and a dim room adds some ambient light. With the geometry fixed (after the
coarse-to-fine optimization, as for the material model, :mod:`recon.optimize.material`), the
prediction of the linearized photo of view k at pixel p is::

    x_p   = mean over the pixel's samples of  L_flash(y; light at o_k + R_k^T t) + A (a_d + a_s)
    pred  = h_k( x_p * g_k * v(r_p) )

with the terms (each optional, :data:`TERMS`):

- ``flash_offset`` t: the flash at a fixed offset from the camera centre in camera coordinates
  (given in ``capture.yaml`` as ``flash_offset``, or fitted in the plane of the lens, t_z = 0). The shading is the general model of
  DESIGN section 3 (l != v, Schlick F at v.h) at each G-buffer sample; without the term the
  collocated fast path (:func:`recon.optimize.gbuffer.radiance`) shades.
- ``exposure`` g_k: a per-view gain around the EXIF exposure that linearize already divided out
  (prior: log g_k ~ N(0, ``exposure_prior``)), normalized to geometric mean 1 over the training
  views (the albedo carries the common scale).
- ``ambient`` A >= 0: a constant environment's radiance; an unoccluded diffuse surface under it
  reflects a_d A (the specular lobe's hemispherical albedo is taken as a_s; no occlusion).
- ``falloff`` v(r) = 1 + k1 r^2 + k2 r^4 (r = 1 in the image corners), floored smoothly at
  ``FALLOFF_FLOOR`` so that it never reaches 0.
- ``tone`` h_k: a monotone curve H shared by the views of a JPEG capture (identity for RAW
  and EXR, never tried there) acting on what the camera recorded, before linearize divided the
  view's recorded (EXIF) exposure e_k out (:func:`recorded_exposures`; relative to the
  reference exposure): h_k(y) = srgb^-1(H(srgb(c e_k y))) / e_k. H is piecewise linear in the
  sRGB-encoded domain with ``tone_knots`` segments, h(0) = 0, h(1) = 1 (the camera's white, a
  JPEG's 255), increments softplus(raw) >= 0 (a flat segment is allowed), continued above white
  with its last segment's slope (a prediction over white keeps a gradient; the photo's pixels
  there are clipped and carry no loss); c is the curve's input scale (prior log c ~
  N(0, ``tone_gain_prior``)): where the camera's white sits in the model's units, which the
  albedo maps could only move texel by texel. The first design, srgb^-1(H(srgb(min(y, 1)))) on
  the linearized values, was a different curve for every recorded exposure: a phone's
  auto-exposure of +-0.3 to 0.5 stop made the tone term's held-out gain vanish on a glazed bell
  that one without the EXIF variation gains from (``bench/tone.py``, docs/phone.md "The tone
  curve however the phone made it").

Selection: forward selection in rounds: each remaining term is fitted on top of the current
terms with the material maps of the chosen material model (warm-started from the accepted fit)
and compared with a control (the current model refitted as long) by the same paired per-tile
test as the material model (:func:`recon.optimize.material.compare`); of the terms that pass,
the one with the largest gain is kept, and the next round tries the rest. Then each kept term
is checked backwards: dropped when the model without it (refitted) is not significantly worse. The
held-out views' own exposure gains are unknown: their tiles are split like a checkerboard and
the gains cross-fitted (maps and shared terms fixed): fitted on the black tiles to score the
white, on the white to score the black, so no tile scores a gain fitted on it and every tile
counts (scoring the white tiles only, the first design, halved the tiles the test sees: on a
glossy object with 0.5-stop exposure jitter a uniform specular lobe's gain fell from 3.3 to 1.9
SE, ``tests/optimize/test_imaging.py::test_material_selection_under_the_imaging_terms``).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
import torch

from recon.optimize import objective
from recon.optimize.gbuffer import GBuffer, build_gbuffer, lookup, radiance
from recon.optimize.material import (Fit, MaterialModel, MaterialParams, MaterialProblem, SelectionSettings,
                                     compare)
from recon.optimize.views import ViewSet

log = logging.getLogger(__name__)

TERMS = ("flash_offset", "exposure", "ambient", "falloff", "tone")
FALLOFF_FLOOR = 1e-3
_FALLOFF_BETA = 50.0


@dataclass(frozen=True)
class ImagingModel:
    """Which imaging terms are modelled (a subset of :data:`TERMS`, kept in that order)."""

    terms: tuple = ()

    def __post_init__(self):
        unknown = set(self.terms) - set(TERMS)
        if unknown:
            raise ValueError(f"imaging model: unknown terms {sorted(unknown)}; choose from {TERMS}")
        object.__setattr__(self, "terms", tuple(t for t in TERMS if t in self.terms))

    def has(self, term: str) -> bool:
        return term in self.terms

    def plus(self, term: str) -> "ImagingModel":
        return ImagingModel(self.terms + (term,))

    def label(self) -> str:
        return ", ".join(self.terms) if self.terms else "ideal (collocated light, known exposure, linear)"


@dataclass(frozen=True)
class ImagingSettings:
    """How the imaging terms are fitted (see the module docstring)."""

    lr: float = 0.05
    exposure_prior: float = 0.25  # standard deviation of log g_k around the EXIF exposure
    tone_knots: int = 16
    heldout_iterations: int = 60
    tone_gain: bool = True  # the curve's input scale c fitted (False: c = 1, the first design)
    tone_gain_prior: float = 1.0  # standard deviation of log c


# ---------------------------------------------------------------------- the terms
def srgb_encode(x: torch.Tensor) -> torch.Tensor:
    c = x.clamp(0.0, 1.0)
    return torch.where(c <= 0.0031308, 12.92 * c, 1.055 * c.clamp(min=0.0031308) ** (1 / 2.4) - 0.055)


def srgb_decode(s: torch.Tensor) -> torch.Tensor:
    c = s.clamp(0.0, 1.0)
    return torch.where(c <= 0.04045, c / 12.92, ((c.clamp(min=0.04045) + 0.055) / 1.055) ** 2.4)


def tone_knot_values(raw: torch.Tensor) -> torch.Tensor:
    """(K + 1,) knot values of the monotone curve: 0, cumulative softplus increments, 1."""
    inc = torch.nn.functional.softplus(raw) + 1e-12
    c = torch.cumsum(inc, 0) / inc.sum()
    return torch.cat([torch.zeros(1, dtype=c.dtype), c])


def _encode_ext(x: torch.Tensor) -> torch.Tensor:
    """The sRGB encoding on [0, inf) (the formula continued above 1, not clipped)."""
    c = x.clamp(min=0.0)
    return torch.where(c <= 0.0031308, 12.92 * c, 1.055 * c.clamp(min=0.0031308) ** (1 / 2.4) - 0.055)


def _decode_ext(s: torch.Tensor) -> torch.Tensor:
    """The inverse of :func:`_encode_ext` on [0, inf)."""
    c = s.clamp(min=0.0)
    return torch.where(c <= 0.04045, c / 12.92, ((c.clamp(min=0.04045) + 0.055) / 1.055) ** 2.4)


def apply_tone(y: torch.Tensor, raw: torch.Tensor, log_gain: torch.Tensor | None = None,
               exposure: torch.Tensor | None = None) -> torch.Tensor:
    """pred = srgb^-1(H(srgb(c e y))) / e with H piecewise linear through
    :func:`tone_knot_values` (h(0) = 0, h(1) = 1: the camera's white), c = exp(``log_gain``) the
    curve's input scale (1 when None) and e the recorded exposure of the pixel's view relative to
    the reference linearize scaled to (``exposure``, broadcast against ``y``; 1 when None): the
    curve acts on what the camera recorded, before linearize divided its exposure out. Above
    white (c e y > 1) H continues with its last segment's slope, so that a prediction over white
    keeps a gradient (a photo's pixels there are clipped and carry no loss)."""
    knots = tone_knot_values(raw)
    K = knots.shape[0] - 1
    u = y if log_gain is None else y * torch.exp(log_gain)
    if exposure is not None:
        u = u * exposure
    s = _encode_ext(u) * K
    i = s.detach().floor().clamp(0, K - 1).long()
    t = s - i.to(s.dtype)
    h = knots[i] + t * (knots[i + 1] - knots[i])
    out = _decode_ext(h)
    return out if exposure is None else out / exposure


def falloff(r2: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """``1 + k1 r^2 + k2 r^4`` floored smoothly at :data:`FALLOFF_FLOOR` (never 0, finite gradient)."""
    v = 1.0 + k[0] * r2 + k[1] * r2 * r2
    return FALLOFF_FLOOR + torch.nn.functional.softplus(v - FALLOFF_FLOOR, beta=_FALLOFF_BETA)


def radiance_offset(gb: GBuffer, grid: torch.Tensor, view: torch.Tensor, light_pos: torch.Tensor,
                    centers: torch.Tensor, diffuse, specular, roughness, light: float, r_min: float):
    """(N, 3) radiance of the samples lit by point lights at ``light_pos[view]`` (V, 3), seen from
    ``centers[view]``: the general model of DESIGN section 3 (front side only)."""
    y, n = gb.position.to(light_pos.dtype), gb.normal.to(light_pos.dtype)
    lv = light_pos[view] - y
    d2 = (lv * lv).sum(1).clamp(min=1e-20)
    l = lv * torch.rsqrt(d2)[:, None]  # noqa: E741
    v = centers[view].to(y.dtype) - y
    v = v / v.norm(dim=1, keepdim=True).clamp(min=1e-20)
    nl = (n * l).sum(1).clamp(min=0.0)
    nv = (n * v).sum(1).clamp(min=0.0)
    f = lookup(diffuse, grid) * (1.0 / np.pi)
    if specular is not None:
        h = l + v
        h = h / h.norm(dim=1, keepdim=True).clamp(min=1e-20)
        nh = (n * h).sum(1).clamp(min=0.0, max=1.0)[:, None]
        vh = (v * h).sum(1).clamp(min=0.0, max=1.0)[:, None]
        alpha = lookup(roughness, grid).clamp(min=r_min, max=1.0) ** 2
        a2 = alpha * alpha
        dd = (1 - nh) * (1 + nh) + nh * nh * a2
        D = a2 / (np.pi * dd * dd)
        a_s = lookup(specular, grid)
        F = a_s + (1 - a_s) * (1 - vh) ** 5
        # G1(c) / (2c) = 1 / (c + sqrt(a2 + (1 - a2) c^2)): finite as the cosines go to 0
        gl = 1.0 / (nl[:, None] + torch.sqrt(a2 + (1 - a2) * nl[:, None] ** 2))
        gv = 1.0 / (nv[:, None] + torch.sqrt(a2 + (1 - a2) * nv[:, None] ** 2))
        f = f + D * F * gl * gv * (nv[:, None] > 0)
    return f * (light * nl / d2)[:, None] * (nv > 0)[:, None]


class ImagingParams:
    """The raw parameters of the imaging terms and their values (see the module docstring).

    Parameters
    ----------
    model : ImagingModel
    n_views : number of views with their own exposure gain
    length : a length of the scene (the bounding box's longest side): the offset's unit step
    tone_scale : the foreground's median radiance (the ambient term's unit)
    offset_given : (3,) fixed flash offset (camera coordinates), or None
    knots : tone curve segments
    """

    def __init__(self, model: ImagingModel, n_views: int, length: float, tone_scale: float,
                 offset_given=None, knots: int = 16, normalize_gains: bool = True, tone_gain: bool = True):
        dt = torch.float32
        self.model = model
        self.length = float(length)
        self.tone_scale = float(tone_scale)
        self.normalize_gains = normalize_gains
        self.offset_given = None if offset_given is None else torch.tensor(np.asarray(offset_given, np.float32))
        self.offset_raw = torch.zeros(3, dtype=dt, requires_grad=True)
        self.log_gain = torch.zeros(n_views, dtype=dt, requires_grad=True)
        self.ambient_raw = torch.full((1,), -4.0, dtype=dt, requires_grad=True)
        self.falloff_k = torch.zeros(2, dtype=dt, requires_grad=True)
        self.tone_raw = torch.zeros(int(knots), dtype=dt, requires_grad=True)
        self.tone_gain = bool(tone_gain)
        self.tone_log_gain = torch.zeros((), dtype=dt, requires_grad=True)

    def groups(self, lr: float) -> list[dict]:
        """Adam parameter groups of the modelled terms."""
        m = self.model
        out = []
        if m.has("flash_offset") and self.offset_given is None:
            out.append({"params": [self.offset_raw], "lr": 2 * lr})
        if m.has("exposure"):
            out.append({"params": [self.log_gain], "lr": lr})
        if m.has("ambient"):
            out.append({"params": [self.ambient_raw], "lr": 4 * lr})
        if m.has("falloff"):
            out.append({"params": [self.falloff_k], "lr": 0.5 * lr})
        if m.has("tone"):
            out.append({"params": [self.tone_raw], "lr": lr})
            if self.tone_gain:
                out.append({"params": [self.tone_log_gain], "lr": lr})
        return out

    # ---- values ----
    def offset(self) -> torch.Tensor | None:
        if self.offset_given is not None:
            return self.offset_given
        if self.model.has("flash_offset"):
            # in the plane of the lens (z = 0): a phone's flash sits beside it; a fitted forward
            # component trades with the exposure and falloff (measured: 0.42 units on the phone capture)
            return self.offset_raw * torch.tensor([1.0, 1.0, 0.0]) * (0.1 * self.length)
        return None

    def gains(self) -> torch.Tensor | None:
        if not self.model.has("exposure"):
            return None
        lg = self.log_gain - self.log_gain.mean() if self.normalize_gains else self.log_gain
        return torch.exp(lg)

    def ambient(self) -> torch.Tensor | None:
        if not self.model.has("ambient"):
            return None
        return torch.nn.functional.softplus(self.ambient_raw) * self.tone_scale

    def tone_input_gain(self) -> torch.Tensor | None:
        """log c of the tone curve's input (None: without the term or with c fixed at 1)."""
        return self.tone_log_gain if self.model.has("tone") and self.tone_gain else None

    def tone(self, y: torch.Tensor, exposure: torch.Tensor | None = None) -> torch.Tensor:
        """The tone term on linear values ``y`` (:func:`apply_tone`; ``y`` unchanged without it)."""
        if not self.model.has("tone"):
            return y
        return apply_tone(y, self.tone_raw, self.tone_input_gain(), exposure)

    def prior(self, sigma: float, tone_sigma: float = 1.0) -> torch.Tensor:
        """The EXIF exposure prior: mean (log g_k / sigma)^2 / 2 (0 without the term), plus
        (log c / ``tone_sigma``)^2 / 2 for the tone curve's input scale."""
        out = torch.zeros(())
        if self.model.has("exposure"):
            g = self.gains()
            out = out + 0.5 * (torch.log(g) / sigma).pow(2).mean()
        lc = self.tone_input_gain()
        if lc is not None:
            out = out + 0.5 * (lc / tone_sigma).pow(2)
        return out

    def clone(self, n_views: int | None = None, normalize_gains: bool | None = None) -> "ImagingParams":
        """An independent copy (same terms, same values); for ``n_views`` other views (e.g.
        held-out ones) the exposure gains start at 1."""
        out = ImagingParams(self.model, int(self.log_gain.shape[0]) if n_views is None else int(n_views), self.length,
                            self.tone_scale, None if self.offset_given is None else self.offset_given.numpy(),
                            int(self.tone_raw.shape[0]),
                            self.normalize_gains if normalize_gains is None else bool(normalize_gains), self.tone_gain)
        return out.copy_from(self)

    def copy_from(self, other: "ImagingParams") -> "ImagingParams":
        with torch.no_grad():
            for name in ("offset_raw", "ambient_raw", "falloff_k", "tone_raw", "tone_log_gain"):
                getattr(self, name).copy_(getattr(other, name))
            if self.log_gain.shape == other.log_gain.shape:
                self.log_gain.copy_(other.log_gain)
        return self

    @torch.no_grad()
    def report(self, knots_out: int = 17) -> dict:
        """The fitted values (JSON)."""
        m = self.model
        out: dict = {"terms": list(m.terms)}
        off = self.offset()
        if off is not None:
            out["flash_offset"] = [float(x) for x in off]
            out["flash_offset_source"] = "given" if self.offset_given is not None else "fitted"
        if m.has("exposure"):
            out["exposure_gains"] = [float(x) for x in self.gains()]
        if m.has("ambient"):
            out["ambient"] = float(self.ambient())
        if m.has("falloff"):
            out["falloff"] = {"k1": float(self.falloff_k[0]), "k2": float(self.falloff_k[1]),
                              "corner": float(falloff(torch.ones(1), self.falloff_k)[0])}
        if m.has("tone"):
            x = torch.linspace(0, 1, knots_out)
            lc = self.tone_input_gain()
            out["tone_curve"] = {"linear_in": x.tolist(), "linearized_out": self.tone(x).tolist(),
                                 "input_gain": 1.0 if lc is None else float(torch.exp(lc)),
                                 "white_linear": 1.0 if lc is None else float(torch.exp(-lc))}
        return out


# ---------------------------------------------------------------------- the problem
def view_exposures(cameras, exposure: dict | None) -> torch.Tensor | None:
    """(V,) recorded exposures of ``cameras`` (by image stem) relative to the reference, or None
    when none is given or all are 1 (the tone curve then acts on the linearized values as they are)."""
    if not exposure:
        return None
    e = np.array([float(exposure.get(getattr(c, "stem", None), 1.0)) for c in cameras], np.float64)
    if not np.all(np.isfinite(e) & (e > 0)):
        raise ValueError(f"recorded exposures must be finite and > 0, got {e}")
    return None if np.all(e == 1.0) else torch.tensor(e, dtype=torch.float32)


def _camera_arrays(cameras) -> tuple[torch.Tensor, torch.Tensor]:
    R = torch.tensor(np.stack([c.world_to_camera[:3, :3] for c in cameras]), dtype=torch.float32)
    o = torch.tensor(np.stack([c.center for c in cameras]), dtype=torch.float32)
    return R, o


class ImagingProblem(MaterialProblem):
    """A G-buffer and its targets (the kept pixels as in the material fits,
    :class:`recon.optimize.material.MaterialProblem`) with the per-pixel data the imaging terms need:
    view index, squared image radius, checkerboard tile colour, and the recorded exposure of the
    pixel's view relative to the reference (``exposure``: image stem -> h_k / h_ref as linearize
    recorded it, :func:`recorded_exposures`; views not in it, or None, at 1): the tone curve acts
    before linearize divided it out."""

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
        self.R, self.o = _camera_arrays(targets.cameras)
        self.shape = (V, H, W)
        self.tile = int(tile)
        e = view_exposures(targets.cameras, exposure)
        self.view_exposure = e
        self.pixel_exposure = None if e is None else e[self.pixel_view][:, None]

    def render(self, d, sp, ro, light: float, r_min: float, im: ImagingParams) -> torch.Tensor:
        """(P, 3) predicted linearized values of the kept pixels."""
        off = im.offset()
        if off is None:  # the collocated fast path
            rad = radiance(self.gb, self.grid, d, sp, ro, light, r_min)
        else:
            light_pos = self.o + torch.einsum("vji,j->vi", self.R, off.to(self.R.dtype))
            rad = radiance_offset(self.gb, self.grid, self.sample_view, light_pos, self.o, d, sp, ro, light, r_min)
        A = im.ambient()
        if A is not None:
            refl = lookup(d, self.grid)
            if sp is not None:
                refl = refl + lookup(sp, self.grid)
            rad = rad + A * refl
        out = torch.zeros((len(self.pixels), 3), dtype=rad.dtype).index_add(0, self.sample_pixel, rad) / self.gb.spp
        g = im.gains()
        if g is not None:
            out = out * g[self.pixel_view][:, None]
        if im.model.has("falloff"):
            out = out * falloff(self.r2, im.falloff_k)[:, None]
        return im.tone(out, self.pixel_exposure)

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


def _lr_decay(opt, base: list[float], it: int, n: int) -> None:
    for g, lr in zip(opt.param_groups, base, strict=True):
        g["lr"] = lr * 0.1 ** (it / max(n - 1, 1))


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
    base = [g["lr"] for g in groups]
    opt = torch.optim.Adam(groups)
    valid = torch.from_numpy(covered)
    w = {"render": 1.0, "specular": s.w_specular, "roughness": s.w_roughness}
    n = max(int(s.iterations), 0)
    loss = torch.tensor(float("nan"))
    for it in range(n + 1):
        d, sp, ro = P.values()
        loss = prob.loss(prob.render(d, sp, ro, light, s.r_min, ip))
        if it == n:
            break
        terms = {"render": loss, **objective.material_terms(
            sp if material.specular == "textured" else None, d, ro if material.roughness == "textured" else None,
            valid, w, s.bilateral_sigma_space, s.bilateral_sigma_color, s.bilateral_radius)}
        total = objective.total(terms, w, dtype=None) + ip.prior(im.exposure_prior, im.tone_gain_prior) / prob.n_total
        _lr_decay(opt, base, it, n)
        opt.zero_grad(set_to_none=True)
        total.backward()
        opt.step()
        P.project_()
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
    opt = torch.optim.Adam([ip.log_gain], lr=0.05)
    sel = fit_on.to(torch.float32)
    n = int(im.heldout_iterations)
    for it in range(n):
        for g in opt.param_groups:
            g["lr"] = 0.05 * 0.1 ** (it / max(n - 1, 1))
        loss = prob.loss(render(ip), sel) + ip.prior(im.exposure_prior, im.tone_gain_prior) / prob.n_total
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()


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


def _problems(mesh, train: ViewSet, heldout: ViewSet, s: SelectionSettings, tone_scale: float, spp: int,
              seed: int, exposure: dict | None = None) -> tuple[ImagingProblem, ImagingProblem, float]:
    """The training and held-out views' problems on a fixed mesh and the mesh's size."""
    gb_train = build_gbuffer(mesh, list(train.cameras), spp, seed)
    gb_held = build_gbuffer(mesh, list(heldout.cameras), spp, seed + 1)
    lo, hi = mesh.bbox()
    return (ImagingProblem(gb_train, train, s.tone_map, tone_scale, s.tile, exposure),
            ImagingProblem(gb_held, heldout, s.tone_map, tone_scale, s.tile, exposure), float(np.max(hi - lo)))


def select_imaging(mesh, material_fit: Fit, covered: np.ndarray, train: ViewSet, heldout: ViewSet, light: float,
                   tone_scale: float, s: SelectionSettings, im: ImagingSettings | None = None,
                   candidates: tuple = TERMS, offset_given=None, spp: int = 4, seed: int = 0,
                   progress=None, exposure: dict | None = None) -> tuple[ImagingFit, dict]:
    """Greedy forward selection of the imaging terms (module docstring) on a fixed mesh.

    ``material_fit`` (the chosen material model and its maps) is the start; ``candidates`` the
    terms to try (leave ``tone`` out for RAW/EXR captures, ``flash_offset`` when it is given:
    ``offset_given`` (3,) then applies to every fit). Returns the chosen fit (its maps refitted
    under the chosen imaging) and the evidence for summary.json and the report. ``exposure``:
    the views' recorded exposures (image stem -> h_k / h_ref, :func:`recorded_exposures`), where
    the tone curve acts.
    """
    im = im or ImagingSettings()
    t0 = time.perf_counter()
    p_train, p_held, length = _problems(mesh, train, heldout, s, tone_scale, spp, seed, exposure)
    mat = material_fit.model
    base_model = ImagingModel()
    if offset_given is not None:
        candidates = tuple(c for c in candidates if c != "flash_offset")

    def evaluate(model: ImagingModel, init_maps: dict, init_params: ImagingParams | None) -> ImagingFit:
        fit = fit_imaging(model, mat, p_train, init_maps, covered, light, s, im, init_params, length, tone_scale,
                          offset_given)
        fit.tile_errors, fit.rmse_srgb = heldout_tiles(fit, p_held, light, s, im)
        fit.heldout = float(np.nanmean(fit.tile_errors))
        if progress is not None:
            progress(model, fit)
        return fit

    current = evaluate(base_model, material_fit.maps, None)
    rows = [{"step": "ideal" if offset_given is None else "ideal (flash offset given)", "terms": [],
             "heldout_error": current.heldout, "heldout_rmse_srgb": current.rmse_srgb,
             "train_loss": current.train_loss, "seconds": current.seconds,
             "accepted": True, "gain": None, "se": None, "relative_gain": None}]
    # forward selection in rounds: every remaining term is fitted on top of the current model
    # (one shared control per round) and the one with the largest passing gain is kept. Keeping
    # the first term that passes (the first design) depended on the order: on a JPEG capture
    # with the tone curve only, a falloff (tried before the tone curve) absorbed part of it.
    remaining = [c for c in TERMS if c in candidates]
    rnd = 0
    while remaining:
        rnd += 1
        control = evaluate(current.model, current.material.maps, current.params)
        best = None
        for term in remaining:
            cand = current.model.plus(term)
            fit = evaluate(cand, current.material.maps, current.params)
            cmp = compare(fit.tile_errors, control.tile_errors, s)
            rows.append({"step": term, "round": rnd, "terms": list(cand.terms), "heldout_error": fit.heldout,
                         "control_heldout_error": control.heldout, "heldout_rmse_srgb": fit.rmse_srgb,
                         "control_heldout_rmse_srgb": control.rmse_srgb, "train_loss": fit.train_loss,
                         "seconds": fit.seconds, "control_seconds": control.seconds,
                         "values": fit.params.report(), **cmp, "accepted": False, "passed": cmp["accepted"]})
            log.info("imaging: round %d %-13s held-out %.5f (gain %+.5f, SE %.5f) %s", rnd, term, fit.heldout,
                     cmp["gain"], cmp["se"], "passes" if cmp["accepted"] else "rejected")
            if cmp["accepted"] and (best is None or cmp["gain"] > best[2]):
                best = (term, fit, cmp["gain"], len(rows) - 1)
        if best is None:
            break
        term, current = best[0], best[1]
        rows[best[3]]["accepted"] = True
        log.info("imaging: round %d keeps %s", rnd, term)
        remaining = [c for c in remaining if c != term]
    # backward check: a term kept early may be explained by one kept later; drop each term
    # whose removal does not lose a significant gain (the kept model refitted as long as the
    # reduced one, the same paired test)
    for term in [t for t in current.model.terms if len(current.model.terms) > 1]:
        reduced_model = ImagingModel(tuple(t for t in current.model.terms if t != term))
        full = evaluate(current.model, current.material.maps, current.params)
        reduced = evaluate(reduced_model, current.material.maps, current.params)
        cmp = compare(full.tile_errors, reduced.tile_errors, s)
        keep = cmp["accepted"]
        rows.append({"step": f"without {term}", "round": "backward", "terms": list(reduced_model.terms),
                     "heldout_error": reduced.heldout, "control_heldout_error": full.heldout,
                     "heldout_rmse_srgb": reduced.rmse_srgb, "train_loss": reduced.train_loss,
                     "seconds": reduced.seconds, **cmp, "accepted": not keep, "passed": keep,
                     "note": "gain of keeping the term (the kept model over the model without it)"})
        log.info("imaging: without %-13s gain of keeping it %+.5f (SE %.5f): %s", term, cmp["gain"], cmp["se"],
                 "kept" if keep else "dropped")
        if not keep:
            current = reduced
    evidence = {
        "criterion": f"keep an imaging term when the held-out error drops below the current model's (refitted as "
                     f"long) by > {s.z} x SE of the paired per-tile difference and by > {100 * s.min_gain:.3g} %; "
                     "held-out exposure gains fitted on the tiles of one checkerboard colour, errors on the other "
                     "(both ways round)",
        "metric": f"mean |Phi(render) - Phi(photo)| (Phi = {s.tone_map} tone map) over held-out pixels",
        "candidates_tried": [c for c in TERMS if c in candidates],
        "flash_offset_given": None if offset_given is None else [float(x) for x in offset_given],
        "candidates": rows,
        "chosen": list(current.model.terms),
        "chosen_label": current.model.label(),
        "values": current.params.report(),
        "chosen_heldout_error": current.heldout,
        "chosen_heldout_rmse_srgb": current.rmse_srgb,
        "seconds": time.perf_counter() - t0,
    }
    return current, evidence



# ---------------------------------------------------------------------- the optimize stage's entry
def capture_is_ldr(images) -> bool | None:
    """Whether the linearize stage read JPEG/PNG photos (its ``linear.json`` beside the views, or
    in ``linear/`` of the same results folder for ``poses/undistorted``); None when not found."""
    import json
    from pathlib import Path

    if not images:
        return None
    d = Path(images[0]).parent
    for cand in (d / "linear.json", d.parent.parent / "linear" / "linear.json"):
        if cand.is_file():
            try:
                info = json.loads(cand.read_text())
            except (OSError, ValueError):
                return None
            kinds = {v.get("kind") for v in info.get("images", {}).values() if isinstance(v, dict)}
            return kinds == {"ldr"} if kinds else None
    return None


def recorded_exposures(images) -> dict | None:
    """Image stem -> the exposure linearize divided out (h_k / h_ref = 1 / ``exposure_scale`` of
    its ``linear.json``, found as :func:`capture_is_ldr` finds it), or None when not found or
    every view was taken at the reference exposure. A phone's auto-exposure changes the recorded
    exposure from shot to shot, and its tone curve acts before linearize divides it out."""
    import json
    from pathlib import Path

    if not images:
        return None
    d = Path(images[0]).parent
    for cand in (d / "linear.json", d.parent.parent / "linear" / "linear.json"):
        if cand.is_file():
            try:
                info = json.loads(cand.read_text())
            except (OSError, ValueError):
                return None
            out = {}
            for stem, v in info.get("images", {}).items():
                sc = v.get("exposure_scale") if isinstance(v, dict) else None
                if isinstance(sc, (int, float)) and np.isfinite(sc) and sc > 0:
                    out[str(stem)] = 1.0 / float(sc)
            return out if out and any(abs(e - 1.0) > 1e-9 for e in out.values()) else None
    return None


def candidate_terms(settings, ldr: bool | None) -> tuple[tuple, bool]:
    """The terms of ``imaging_terms`` to try and whether the tone curve is among them
    (``tone_curve``: fit, identity, or auto = only for JPEG/PNG photos)."""
    tone = settings.tone_curve == "fit" or (settings.tone_curve == "auto" and bool(ldr))
    return tuple(t for t in settings.imaging_terms if tone or t != "tone"), tone


def run_imaging_selection(settings, mesh, maps: dict, material: MaterialModel, covered: np.ndarray, views, heldout,
                          light: float, tone_scale: float, images, train_set=None,
                          heldout_set=None) -> tuple[dict, MaterialModel, dict]:
    """The optimize stage's imaging selection (``select_imaging``): the maps refitted under the
    chosen imaging terms, the material model, and the evidence for summary.json.
    ``train_set``/``heldout_set``: the views at ``select_image_size`` with the cameras the model
    goes with (refined by the optimizer, issue 17); default ``views.at(size)``/``heldout.at(size)``."""
    ldr = capture_is_ldr(images)
    terms, tone = candidate_terms(settings, ldr)
    size = int(settings.select_image_size)
    log.info("imaging model selection on %d held-out views: %s", len(heldout), ", ".join(terms))
    train_set = train_set if train_set is not None else views.at(size)
    heldout_set = heldout_set if heldout_set is not None else heldout.at(size)
    fit, ev = select_imaging(mesh, Fit(material, maps, float("nan")), covered, train_set, heldout_set,
                             light, tone_scale, settings.imaging_selection_settings(), candidates=terms,
                             offset_given=settings.flash_offset, spp=int(settings.select_spp),
                             seed=int(settings.seed) + 17, exposure=recorded_exposures(images) if tone else None)
    ev["tone_curve"] = {"setting": settings.tone_curve, "photos_are_ldr": ldr, "tried": tone}
    return fit.material.maps, material, ev


# ---------------------------------------------------------------------- inside the geometry loop
def image_radius2(h: int, w: int) -> torch.Tensor:
    """(h, w) squared radius from the image centre, 1 in the corners (the falloff's r^2)."""
    row = torch.arange(h, dtype=torch.float32)[:, None] + 0.5 - h / 2
    col = torch.arange(w, dtype=torch.float32)[None, :] + 0.5 - w / 2
    return (row * row + col * col) / ((w / 2) ** 2 + (h / 2) ** 2)


class LoopImaging:
    """The imaging terms chosen on the coarse model, inside the coarse-to-fine loop
    (``imaging_loop: select``): the flash offset and the ambient light go to the renderer as
    fixed values (:meth:`lighting`), the exposure gains, falloff and tone curve act on the
    rendered images (:meth:`apply`) and are refined with the shape (rate ``lr``; 0: fixed).

    ``params`` is None until the selection ran (the stages before it render the ideal formation).
    ``shared_from``: another run's loop imaging whose choice this run takes instead of selecting
    again (:meth:`share`): the camera refinement's paired runs, identical up to the selection.
    ``exposure``: (training views,) their recorded exposures relative to the reference (the
    views of :func:`recorded_exposures`; None: all 1), where the tone curve acts.
    """

    def __init__(self, lr: float, exposure_prior: float, shared_from: "LoopImaging | None" = None,
                 exposure: np.ndarray | None = None):
        self.exposure = None if exposure is None else torch.as_tensor(np.asarray(exposure, np.float32))
        self.lr = float(lr)
        self.exposure_prior = float(exposure_prior)
        self.shared_from = shared_from
        self.params: ImagingParams | None = None
        self.evidence: dict | None = None
        self.adopted: ImagingParams | None = None  # the values as chosen (before the loop refines them)
        self.opt: torch.optim.Optimizer | None = None
        self._r2: dict = {}

    @property
    def active(self) -> bool:
        return self.params is not None

    def adopt(self, params: ImagingParams | None, evidence: dict) -> None:
        """Take the selection's fitted terms (None: nothing chosen, the ideal formation stays)."""
        self.evidence = evidence
        self.params = params
        self.adopted = None if params is None else params.clone()
        self.opt = None
        if params is not None and self.lr > 0:
            groups = [g for g in params.groups(self.lr) if g["params"][0] is not params.offset_raw
                      and g["params"][0] is not params.ambient_raw]
            if groups:
                self.opt = torch.optim.Adam(groups)
                for g in self.opt.param_groups:
                    g["base_lr"] = g["lr"]

    def share(self) -> bool:
        """Adopt ``shared_from``'s choice and its values as chosen, if it has chosen (False: it
        has not, select anew)."""
        src = self.shared_from
        if src is None or src.evidence is None:
            return False
        self.adopt(None if src.adopted is None else src.adopted.clone(), {**src.evidence, "shared": True})
        return True

    def lighting(self) -> dict:
        """Renderer keywords: ``flash_offset`` (camera coordinates) and ``ambient`` (fixed)."""
        if self.params is None:
            return {}
        with torch.no_grad():
            off = self.params.offset()
            amb = self.params.ambient()
        return {"flash_offset": None if off is None else off.numpy().astype(np.float64),
                "ambient": 0.0 if amb is None else float(amb)}

    def apply(self, img: torch.Tensor, idx, gains: torch.Tensor | None = None,
              exposure: torch.Tensor | None = None) -> torch.Tensor:
        """(B, h, w, 3) rendered radiance of the training views ``idx`` -> predicted photo.
        ``gains``: (B,) exposure gains of these images instead of the training views' (views
        outside the training set, e.g. held-out views with their own fitted gains).
        ``exposure``: (B,) recorded exposures of these images relative to the reference (where
        the tone curve acts, :func:`apply_tone`); default: ``self.exposure[idx]`` for training
        views (``gains`` None), else 1."""
        p = self.params
        if p is None:
            return img
        m = p.model
        if m.has("exposure"):
            g = gains if gains is not None else p.gains()[torch.as_tensor(np.asarray(idx), dtype=torch.long)]
            img = img * g[:, None, None, None].to(img.dtype)
        if m.has("falloff"):
            h, w = int(img.shape[1]), int(img.shape[2])
            if (h, w) not in self._r2:
                self._r2[(h, w)] = image_radius2(h, w)
            img = img * falloff(self._r2[(h, w)], p.falloff_k)[None, :, :, None].to(img.dtype)
        if m.has("tone"):
            if exposure is None and gains is None and self.exposure is not None:
                exposure = self.exposure[torch.as_tensor(np.asarray(idx), dtype=torch.long)]
            e = None if exposure is None else torch.as_tensor(exposure, dtype=img.dtype).reshape(-1, 1, 1, 1)
            img = p.tone(img, e)
        return img

    def prior(self) -> torch.Tensor:
        """The exposure prior (0 without that term)."""
        return torch.zeros(()) if self.params is None else self.params.prior(self.exposure_prior)

    def zero_grad(self) -> None:
        if self.opt is not None:
            self.opt.zero_grad(set_to_none=True)

    def step(self, factor: float) -> None:
        if self.opt is not None:
            for g in self.opt.param_groups:
                g["lr"] = g["base_lr"] * factor
            self.opt.step()

    @torch.no_grad()
    def report(self) -> dict:
        out = {"evidence": self.evidence, "chosen": [] if self.params is None else list(self.params.model.terms)}
        if self.params is not None:
            out["values_after_loop"] = self.params.report()
        return out

    def state(self) -> dict:
        p = self.params
        return {"evidence": self.evidence,
                "params": None if p is None else {
                    "terms": list(p.model.terms), "n_views": int(p.log_gain.shape[0]), "length": p.length,
                    "tone_scale": p.tone_scale, "knots": int(p.tone_raw.shape[0]), "tone_gain": p.tone_gain,
                    "offset_given": None if p.offset_given is None else p.offset_given.tolist(),
                    "tensors": {k: getattr(p, k).detach().clone() for k in
                                ("offset_raw", "log_gain", "ambient_raw", "falloff_k", "tone_raw", "tone_log_gain")}},
                "optimizer": None if self.opt is None else self.opt.state_dict()}

    def load(self, state: dict) -> None:
        sp = state["params"]
        params = None
        if sp is not None:
            # a state saved before the tone curve's input scale existed: c = 1, not fitted
            params = ImagingParams(ImagingModel(tuple(sp["terms"])), sp["n_views"], sp["length"], sp["tone_scale"],
                                   sp["offset_given"], sp["knots"], tone_gain=bool(sp.get("tone_gain", False)))
            with torch.no_grad():
                for k, v in sp["tensors"].items():
                    getattr(params, k).copy_(v)
        self.adopt(params, state["evidence"])
        if self.opt is not None and state.get("optimizer") is not None:
            self.opt.load_state_dict(state["optimizer"])
            for g in self.opt.param_groups:
                g.setdefault("base_lr", g["lr"])


def select_for_loop(settings, mesh, maps: dict, material: MaterialModel, covered: np.ndarray, train_set: ViewSet,
                    heldout_set: ViewSet, light: float, tone_scale: float, ldr: bool | None,
                    exposure: dict | None = None):
    """The imaging selection on the coarse model (``imaging_loop: select``): (ImagingParams of
    the chosen terms, or None when the ideal formation is kept and no flash offset is given;
    the evidence). ``exposure``: :func:`recorded_exposures` of the photos (where the tone curve acts)."""
    terms, tone = candidate_terms(settings, ldr)
    fit, ev = select_imaging(mesh, Fit(material, maps, float("nan")), covered, train_set, heldout_set, light,
                             tone_scale, settings.imaging_selection_settings(), candidates=terms,
                             offset_given=settings.flash_offset, spp=int(settings.select_spp),
                             seed=int(settings.seed) + 23, exposure=exposure if tone else None)
    ev["tone_curve"] = {"setting": settings.tone_curve, "photos_are_ldr": ldr, "tried": tone}
    keep = bool(fit.model.terms) or settings.flash_offset is not None
    return (fit.params if keep else None), ev


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
    """A ``scorer`` for :func:`recon.optimize.material.select_material` that fits and compares the
    material models under the imaging terms the loop used (``params``: the start of each fit,
    refined with its maps, as :func:`refit_under` does) and scores them as the imaging selection
    does (:func:`heldout_tiles_under`: the held-out views' exposure gains fitted on one
    checkerboard colour, the errors on the other, both ways round). Under the ideal formation a
    phone's per-view exposure (up to +-50 % on the phone captures) is error every material model
    shares, and it buries a specular lobe's gain."""
    im = ImagingSettings()
    p_train, p_held, length = _problems(mesh, train_set, heldout_set, s, tone_scale, spp, seed, exposure)
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
