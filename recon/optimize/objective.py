"""The objective, in one place: the image term of the paper's equation 6 and the priors.

Every loss of the optimize stage is assembled here: the main loop's (:mod:`recon.optimize.iteration`)
and that of every other fit (:func:`recon.optimize.fitting.fit`: the material and imaging fits,
the held-out views' exposure gains and poses). A new term (an imaging-model parameter's prior,
a mask-restricted image term) is one edit here: its name in :data:`TERMS`, its weight in
:func:`weights`, its value in a ``*_terms`` function.

    L = w_render * mean(w_pix |Phi(I(theta)) - Phi(I_target)|)          image term (eq. 6)
      + w_laplacian * L_lap(V) + w_edge * L_edge(V) + w_normal * L_n(V)  mesh priors
      + w_specular * L_bilateral(a_s; a_d) + w_roughness * TV(r)         material priors
      + w_camera * L_camera(views in the batch)                          camera prior (when refined)
      + w_imaging * L_exposure                                           exposure prior (imaging terms)
      + w_tracks * L_tracks(cameras)                                     SfM tracks reprojected (bench)

``Phi`` is the tone map applied to both sides; ``w_pix`` is 0 on clipped pixels.
"""

from __future__ import annotations

from typing import Callable

import torch

from recon.optimize import regularizers as reg

# every term's name (the log's ``loss_<name>``): the image term (eq. 6), the mesh priors, the
# material priors, the camera prior, the imaging terms' prior (exposure gains, tone gain) and
# SfM's tracks reprojected through refined cameras
TERMS = ("render", "laplacian", "edge", "normal", "specular", "roughness", "camera", "imaging", "tracks")


# ---- Image term ----
def tone_map(x: torch.Tensor, kind: str, scale: float) -> torch.Tensor:
    """Phi: "log" = log(1 + x/scale), "srgb" = sRGB encoding of min(x, 1), "linear" = x."""
    if kind == "log":
        return torch.log1p(x.clamp(min=0.0) / scale)
    if kind == "srgb":
        c = x.clamp(0.0, 1.0)
        return torch.where(c <= 0.0031308, 12.92 * c, 1.055 * c.clamp(min=0.0031308) ** (1 / 2.4) - 0.055)
    if kind == "linear":
        return x
    raise ValueError(f"tone map must be 'log', 'srgb' or 'linear', got {kind!r}")


def image_residual(render: torch.Tensor, target_phi: torch.Tensor, weights: torch.Tensor, kind: str,
                   scale: float) -> torch.Tensor:
    """Eq. 6 before its mean: ``w |Phi(render) - Phi(target)|`` per pixel and channel, shape
    (..., 3); ``target_phi`` is the target already tone mapped, ``weights`` (..., 1)."""
    return (tone_map(render, kind, scale) - target_phi).abs() * weights


def pixel_loss(render: torch.Tensor, target_phi: torch.Tensor, weights: torch.Tensor, kind: str,
               scale: float) -> torch.Tensor:
    """Eq. 6 per pixel (:func:`image_residual` averaged over channels); ``target_phi`` is the
    target already tone mapped (it never changes during a fit). Shapes (..., 3), (..., 1)."""
    return image_residual(render, target_phi, weights, kind, scale).mean(-1)


def render_loss(render: torch.Tensor, target: torch.Tensor, weights: torch.Tensor, kind: str, scale: float) -> torch.Tensor:
    """Eq. 6 per pixel: ``mean(w |Phi(render) - Phi(target)|)`` over views, pixels and channels.

    render, target : (B, h, w, 3); weights : (B, h, w, 1) (0 = clipped pixel).
    """
    if render.shape != target.shape:
        raise ValueError(f"render {tuple(render.shape)} and target {tuple(target.shape)} differ")
    return image_residual(render, tone_map(target, kind, scale), weights, kind, scale).mean()


# ---- Weights: the one place where the ablation switches act ----
def weights(settings) -> dict[str, float]:
    """Each term's weight after the ablation switches (``loss.use_laplacian``,
    ``loss.use_normal_edge``, ``loss.use_material_priors``) of
    :class:`recon.optimize.settings.OptimizeSettings`."""
    loss = settings.loss
    return {
        "render": loss.w_render,
        "laplacian": loss.w_laplacian if loss.use_laplacian else 0.0,
        "edge": loss.w_edge if loss.use_normal_edge else 0.0,
        "normal": loss.w_normal if loss.use_normal_edge else 0.0,
        "specular": loss.w_specular if loss.use_material_priors else 0.0,
        "roughness": loss.w_roughness if loss.use_material_priors else 0.0,
        "camera": loss.w_camera,
        "imaging": loss.w_imaging,
    }


def fit_weights(s) -> dict[str, float]:
    """The weights of the fits on G-buffers (:class:`recon.optimize.material.SelectionSettings`
    ``s``): the image term's (1) and the material priors'."""
    return {"render": 1.0, "specular": s.w_specular, "roughness": s.w_roughness}


# ---- Priors ----
def geometry_terms(v: torch.Tensor, topo, h: float, laplacian: str, w: dict) -> dict[str, torch.Tensor]:
    """The mesh priors with a nonzero weight in ``w`` (vertex positions ``v``)."""
    terms = {}
    if w.get("laplacian"):
        terms["laplacian"] = reg.laplacian_loss(v, topo, h, laplacian)
    if w.get("edge"):
        terms["edge"] = reg.edge_length_loss(v, topo, h)
    if w.get("normal"):
        terms["normal"] = reg.normal_consistency_loss(v, topo)
    return terms


def material_terms(specular, diffuse, roughness, valid, w: dict, sigma_space: float, sigma_color: float,
                   radius: int) -> dict[str, torch.Tensor]:
    """The material priors with a nonzero weight in ``w``; pass ``specular``/``roughness`` as
    None where the map is not textured (a uniform or absent map has no spatial prior)."""
    terms = {}
    if w.get("specular") and specular is not None:
        terms["specular"] = reg.specular_bilateral_loss(specular, diffuse, sigma_space, sigma_color, radius, valid)
    if w.get("roughness") and roughness is not None:
        terms["roughness"] = reg.roughness_tv_loss(roughness, valid)
    return terms


def camera_terms(refinement, idx, w: dict) -> dict[str, torch.Tensor]:
    """The camera prior (:meth:`recon.optimize.camera_refine.CameraRefinement.prior_loss` over
    the views ``idx`` of the batch, None: all) when the cameras are refined and its weight is
    nonzero."""
    if refinement is None or not w.get("camera"):
        return {}
    return {"camera": refinement.prior_loss(idx)}


def imaging_terms(prior: Callable[[], torch.Tensor] | None, w: dict) -> dict[str, torch.Tensor]:
    """The imaging terms' prior (the exposure gains' and the tone curve's gain's, see
    :meth:`recon.optimize.formation.ImagingParams.prior`), evaluated by ``prior()`` only when
    there are imaging terms (``prior`` not None) and its weight is nonzero."""
    if prior is None or not w.get("imaging"):
        return {}
    return {"imaging": prior()}


def tracks_terms(tracks, refinement, cameras, w: dict) -> dict[str, torch.Tensor]:
    """SfM's tracks reprojected through the refined cameras (:class:`recon.optimize.tracks.TrackTerm`,
    its points retriangulated under them first) when given and its weight is nonzero."""
    if tracks is None or not w.get("tracks"):
        return {}
    tracks.retriangulate(refinement, cameras)
    return {"tracks": tracks.loss(refinement, cameras)}


def total(terms: dict[str, torch.Tensor], w: dict[str, float], dtype: torch.dtype | None = torch.float64) -> torch.Tensor:
    """The weighted sum of ``terms`` (each cast to ``dtype`` first unless it is None)."""
    unknown = set(terms) - set(w)
    if unknown:
        raise KeyError(f"objective terms without a weight: {sorted(unknown)}")
    return sum(w[k] * (t if dtype is None else t.to(dtype)) for k, t in terms.items())
