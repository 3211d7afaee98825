"""The camera's image formation Phi_k (the paper's equation 6; the phone's imaging of DESIGN
section 7), written once: its terms, their parameters and the two functions that apply them.

A phone breaks the renderer's idealised image formation a little: its flash sits beside the lens,
auto-exposure changes from shot to shot, its JPEGs carry a tone curve, its lens darkens the
corners and a dim room adds some ambient light. The prediction of the linearized photo of view k
at pixel p is::

    x_p   = mean over the pixel's samples of  L_flash(y; light at o_k + R_k^T t) + A (a_d + a_s)
    pred  = h_k( x_p * g_k * v(r_p) )

with the terms (each optional, :data:`TERMS`):

- ``flash_offset`` t: the flash at a fixed offset from the camera centre in camera coordinates
  (given in ``capture.yaml`` as ``flash_offset``, or fitted in the plane of the lens, t_z = 0).
  The shading is the general model of DESIGN section 3 (l != v, Schlick F at v.h) at each
  sample (:func:`recon.optimize.gbuffer.radiance_offset`); without the term the collocated fast
  path (:func:`recon.optimize.gbuffer.radiance`) shades.
- ``exposure`` g_k: a per-view gain around the EXIF exposure that linearize already divided out
  (prior: log g_k ~ N(0, ``exposure_prior``)), normalized to geometric mean 1 over the training
  views (the albedo carries the common scale).
- ``ambient`` A >= 0: a constant environment's radiance; an unoccluded diffuse surface under it
  reflects a_d A (the specular lobe's hemispherical albedo is taken as a_s; no occlusion).
- ``falloff`` v(r) = 1 + k1 r^2 + k2 r^4 (r = 1 in the image corners), floored smoothly at
  ``FALLOFF_FLOOR`` so that it never reaches 0.
- ``tone`` h_k: a monotone curve H shared by the views of a JPEG capture (identity for RAW
  and EXR, never tried there) acting on what the camera recorded, before linearize divided the
  view's recorded (EXIF) exposure e_k out (:func:`recon.optimize.views.recorded_exposures`;
  relative to the reference exposure): h_k(y) = srgb^-1(H(srgb(c e_k y))) / e_k. H is piecewise
  linear in the sRGB-encoded domain with ``tone_knots`` segments, h(0) = 0, h(1) = 1 (the
  camera's white, a JPEG's 255), increments softplus(raw) >= 0 (a flat segment is allowed),
  continued above white with its last segment's slope (a prediction over white keeps a
  gradient; the photo's pixels there are clipped and carry no loss); c is the curve's input
  scale (prior log c ~ N(0, ``tone_gain_prior``)): where the camera's white sits in the model's
  units, which the albedo maps could only move texel by texel. The first design,
  srgb^-1(H(srgb(min(y, 1)))) on the linearized values, was a different curve for every recorded
  exposure: a phone's auto-exposure of +-0.3 to 0.5 stop made the tone term's held-out gain
  vanish on a glazed bell that one without the EXIF variation gains from (``bench/tone.py``,
  docs/phone.md "The tone curve however the phone made it").

Where it is applied:

- the scene side (flash and ambient light, the first line) by :func:`surface_radiance` on the
  G-buffer's samples: the G-buffer fits and every held-out scorer
  (:meth:`recon.optimize.imaging.ImagingProblem.render`); in the main loop the differentiable
  renderer shades it with its own drjit copy (:func:`recon.render.shading.shade` and
  :func:`recon.render.shading.shade_offset`, keywords from :func:`renderer_lighting`), tested against
  :func:`surface_radiance` (``test_flash_offset_and_ambient_match_the_formation`` in
  tests/render/test_collocated.py);
- the camera side (the second line) by :func:`camera_response`, on the G-buffer's pixels and on
  the main loop's rendered images alike (:meth:`recon.optimize.loop_imaging.LoopImaging.apply`);
- without any term (the ideal formation: the flash at the lens, known exposure, linear) by the
  material fits and their held-out scores too
  (:meth:`recon.optimize.material.MaterialProblem.render`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from recon.optimize.gbuffer import GBuffer, lookup, radiance, radiance_offset

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


def srgb_encode_ext(x: torch.Tensor) -> torch.Tensor:
    """The sRGB encoding on [0, inf) (the formula continued above 1, not clipped)."""
    c = x.clamp(min=0.0)
    return torch.where(c <= 0.0031308, 12.92 * c, 1.055 * c.clamp(min=0.0031308) ** (1 / 2.4) - 0.055)


def srgb_decode_ext(s: torch.Tensor) -> torch.Tensor:
    """The inverse of :func:`srgb_encode_ext` on [0, inf)."""
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
    s = srgb_encode_ext(u) * K
    i = s.detach().floor().clamp(0, K - 1).long()
    t = s - i.to(s.dtype)
    h = knots[i] + t * (knots[i + 1] - knots[i])
    out = srgb_decode_ext(h)
    return out if exposure is None else out / exposure


def falloff(r2: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """``1 + k1 r^2 + k2 r^4`` floored smoothly at :data:`FALLOFF_FLOOR` (never 0, finite gradient)."""
    v = 1.0 + k[0] * r2 + k[1] * r2 * r2
    return FALLOFF_FLOOR + torch.nn.functional.softplus(v - FALLOFF_FLOOR, beta=_FALLOFF_BETA)


def image_radius2(h: int, w: int) -> torch.Tensor:
    """(h, w) squared radius from the image centre, 1 in the corners (the falloff's r^2)."""
    row = torch.arange(h, dtype=torch.float32)[:, None] + 0.5 - h / 2
    col = torch.arange(w, dtype=torch.float32)[None, :] + 0.5 - w / 2
    return (row * row + col * col) / ((w / 2) ** 2 + (h / 2) ** 2)


def flash_positions(R: torch.Tensor, o: torch.Tensor, offset: torch.Tensor) -> torch.Tensor:
    """(V, 3) flash positions o_k + R_k^T t of the views (``R`` (V, 3, 3) world-to-camera
    rotations, ``o`` (V, 3) camera centres) for the offset ``t`` (3,) in camera coordinates."""
    return o + torch.einsum("vji,j->vi", R, offset.to(R.dtype))


def ambient_reflected(ambient: torch.Tensor, diffuse: torch.Tensor, specular: torch.Tensor | None) -> torch.Tensor:
    """A (a_d + a_s): what an unoccluded surface reflects of a constant environment of radiance
    ``ambient`` (``diffuse``, ``specular``: the albedos at the samples; ``specular`` None: no lobe)."""
    refl = diffuse if specular is None else diffuse + specular
    return ambient * refl


# ---------------------------------------------------------------------- the parameters
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


# ---------------------------------------------------------------------- Phi_k
def surface_radiance(gb: GBuffer, grid: torch.Tensor, view: torch.Tensor | None, R: torch.Tensor | None,
                     o: torch.Tensor | None, diffuse, specular, roughness, light: float, r_min: float,
                     params: ImagingParams | None) -> torch.Tensor:
    """(N, 3) radiance toward the camera of the G-buffer's samples (the first line of the module
    docstring): the flash of intensity ``light`` at the view's camera centre (the collocated fast
    path) or at its offset (``view`` (N,): each sample's view, indexing ``R`` (V, 3, 3) and ``o``
    (V, 3), :func:`flash_positions`; needed only then), plus the ambient light's reflection.
    ``params`` None: the ideal formation (the material fits, :mod:`recon.optimize.material`)."""
    if params is None:
        return radiance(gb, grid, diffuse, specular, roughness, light, r_min)
    off = params.offset()
    if off is None:
        rad = radiance(gb, grid, diffuse, specular, roughness, light, r_min)
    else:
        rad = radiance_offset(gb, grid, view, flash_positions(R, o, off), o, diffuse, specular, roughness, light,
                              r_min)
    A = params.ambient()
    if A is not None:
        rad = rad + ambient_reflected(A, lookup(diffuse, grid), None if specular is None else lookup(specular, grid))
    return rad


def camera_response(x: torch.Tensor, params: ImagingParams | None, view: torch.Tensor,
                    r2: torch.Tensor | None = None,
                    exposure: torch.Tensor | None = None, gains: torch.Tensor | None = None) -> torch.Tensor:
    """h_k(x g_k v(r)) (the second line of the module docstring): ``x`` (..., 3) the pixels'
    radiance -> the predicted linearized photo. Per pixel, each broadcast against ``x[..., 0]``:
    ``view`` the index of its view's gain into ``gains`` (default: the parameters' own,
    :meth:`ImagingParams.gains`), ``r2`` its squared image radius (:func:`image_radius2`; needed
    with the falloff) and ``exposure`` its view's recorded exposure relative to the reference
    (where the tone curve acts; None: 1). The terms the model lacks leave ``x`` as it is, and so
    does the ideal formation (``params`` None)."""
    if params is None:
        return x
    m = params.model
    if m.has("exposure"):
        g = params.gains() if gains is None else gains
        x = x * g[view][..., None].to(x.dtype)
    if m.has("falloff"):
        x = x * falloff(r2, params.falloff_k)[..., None].to(x.dtype)
    if m.has("tone"):
        x = params.tone(x, None if exposure is None else exposure[..., None].to(x.dtype))
    return x


def renderer_lighting(params: ImagingParams | None) -> dict:
    """The scene side for :meth:`recon.render.CollocatedRenderer.render_torch`: its keywords
    ``flash_offset`` (camera coordinates) and ``ambient`` as fixed values ({} for None: the ideal
    formation). The renderer's drjit copy of :func:`surface_radiance` shades them."""
    if params is None:
        return {}
    with torch.no_grad():
        off = params.offset()
        amb = params.ambient()
    return {"flash_offset": None if off is None else off.numpy().astype(np.float64),
            "ambient": 0.0 if amb is None else float(amb)}
