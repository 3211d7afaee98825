"""The reflectance model of DESIGN section 3, in numpy float64: the project's reference.

Per texel: diffuse albedo ``a_d`` (RGB, [0, 1]), specular albedo ``a_s`` (one channel or RGB,
[0, 1]), perceptual roughness ``r`` in [``r_min``, 1] with ``alpha = r**2``. The general model
(no cosine factor)::

    f(l, v) = a_d / pi + D(h) F(v.h) G1(n.l) G1(n.v) / (4 (n.l)(n.v))
    D(c)    = alpha^2 / (pi ((c^2 (alpha^2 - 1) + 1)^2)          GGX
    F(c)    = a_s + (1 - a_s)(1 - c)^5                            Schlick
    G1(c)   = 2c / (c + sqrt(alpha^2 + (1 - alpha^2) c^2))        Smith GGX

and its collocated special case (l = v = w, h = n.w = mu, F = a_s)::

    f = a_d / pi + a_s D(mu) G1(mu)^2 / (4 mu^2)

Shapes: per-point scalars (cosines, ``r``, distances) are ``(...)``; colours (``a_d``,
``a_s``) are ``(..., C)``; a model value is ``(..., C)`` with C broadcast from ``a_d``/``a_s``.
Everything broadcasts. ``G1(c) / (2 c) = 1 / (c + sqrt(alpha^2 + (1 - alpha^2) c^2))`` is used
for the specular term, so it stays finite as the cosines go to 0. Both sides of the surface
are not modelled: where n.l <= 0 or n.v <= 0, f = 0 (front side only).

The model exists six times, each for its own machinery, each tied to this reference by the tests
named (change one, change all):

- here, numpy float64: the reference (``tests/test_brdf.py``: known values, normalization of D,
  Smith G1's projected area, reciprocity, energy bounds, extremes);
- ``recon/render/shading.py`` ``shade_collocated``, drjit, the differentiable renderer
  (:mod:`recon.render.collocated`) with the light at the lens
  (``tests/render/test_collocated.py::test_forward_known_values_fronto_parallel_quad`` against
  :func:`radiance_collocated`; ``test_forward_matches_mitsuba_reference`` through the plugin
  below);
- ``recon/render/shading.py`` ``shade_offset``, drjit, the same renderer with the flash beside
  the lens (the general model)
  (``tests/render/test_collocated.py::test_forward_known_values_flash_offset_and_ambient``
  against :func:`eval_brdf`; ``test_flash_offset_matches_mitsuba_reference`` through the plugin
  below; ``test_flash_offset_and_ambient_match_the_formation`` against the G-buffer's
  ``radiance_offset`` as :mod:`recon.optimize.formation` applies it);
- ``recon/optimize/gbuffer.py`` ``radiance``, torch, the G-buffer shading of the material fits
  (``tests/optimize/test_material.py::test_shading_matches_reference_brdf`` against
  :func:`radiance_collocated`);
- ``recon/optimize/gbuffer.py`` ``radiance_offset``, torch, the G-buffer shading with the flash
  beside the lens (the imaging fits, :mod:`recon.optimize.formation`)
  (``tests/optimize/test_imaging.py::test_offset_light_matches_reference_brdf`` against
  :func:`eval_brdf`; ``test_zero_offset_equals_the_collocated_fast_path`` against ``radiance``);
- ``recon/render/mitsuba_bsdf.py``, a Mitsuba BSDF plugin: synthetic captures, reference renders
  and relighting (``tests/render/test_mitsuba_bsdf.py::test_eval_matches_reference`` against
  :func:`eval_brdf`; ``test_sampling_chi2``, a chi-square test of its sampling);
- and its diffuse lobe alone (a_d = 1) in ``recon/optimize/radiometry.py`` ``unit_render``, the
  light scale's estimate
  (``tests/optimize/test_radiometry.py::test_unit_render_is_the_collocated_diffuse_model``
  against :func:`radiance_collocated`).

``tests/test_brdf.py::test_every_copy_is_named_with_its_tests`` holds this list to the code: each
file and function named exists (the function found by its dotted name in the module the
file is), and so does each test.
"""

from __future__ import annotations

import numpy as np

R_MIN = 0.02
"""Smallest perceptual roughness (DESIGN section 3); alpha >= R_MIN**2."""

__all__ = [
    "R_MIN",
    "alpha_from_roughness",
    "ggx_D",
    "smith_G1",
    "schlick_F",
    "eval_brdf",
    "eval_collocated",
    "radiance_collocated",
]


def _f64(x) -> np.ndarray:
    return np.asarray(x, dtype=np.float64)


def alpha_from_roughness(r, r_min: float = R_MIN) -> np.ndarray:
    """``alpha = clip(r, r_min, 1)**2``; ``r`` any shape."""
    return np.clip(_f64(r), r_min, 1.0) ** 2


def ggx_D(cos_h, alpha) -> np.ndarray:
    """GGX normal distribution D as a function of ``cos_h = n.h`` (any shape, broadcast).

    Returns 0 where ``cos_h <= 0``.
    """
    c = _f64(cos_h)
    a2 = _f64(alpha) ** 2
    d = c * c * (a2 - 1.0) + 1.0
    return np.where(c > 0, a2 / (np.pi * d * d), 0.0)


def _inv_g1_denominator(c: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """``1 / (c + sqrt(alpha^2 + (1 - alpha^2) c^2)) = G1(c) / (2c)`` for c >= 0."""
    a2 = alpha * alpha
    return 1.0 / (c + np.sqrt(a2 + (1.0 - a2) * c * c))


def smith_G1(c, alpha) -> np.ndarray:
    """Smith masking for GGX, ``G1(c) = 2c / (c + sqrt(alpha^2 + (1 - alpha^2) c^2))``.

    ``c`` is a cosine with the normal (any shape); returns 0 where ``c <= 0``.
    """
    c = _f64(c)
    alpha = _f64(alpha)
    cp = np.maximum(c, 0.0)
    return np.where(c > 0, 2.0 * cp * _inv_g1_denominator(cp, alpha), 0.0)


def schlick_F(c, a_s) -> np.ndarray:
    """Schlick's Fresnel ``F(c) = a_s + (1 - a_s)(1 - c)^5``; ``c`` clipped to [0, 1]."""
    c = np.clip(_f64(c), 0.0, 1.0)
    a_s = _f64(a_s)
    return a_s + (1.0 - a_s) * (1.0 - c) ** 5


def _unit(x: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(x, axis=-1, keepdims=True)
    return x / np.maximum(n, 1e-300)


def eval_brdf(n, l, v, a_d, a_s, r, r_min: float = R_MIN) -> np.ndarray:  # noqa: E741
    """The general model f(l, v) of DESIGN section 3, without the cosine factor.

    Parameters
    ----------
    n, l, v : (..., 3) float
        Shading normal, direction to the light, direction to the viewer (normalized here).
    a_d : (..., C) float
        Diffuse albedo.
    a_s : (..., 1) or (..., C) float
        Specular albedo.
    r : (...) float
        Perceptual roughness, clipped to [r_min, 1].

    Returns
    -------
    (..., C) float64; 0 where n.l <= 0 or n.v <= 0.
    """
    n, l, v = _unit(_f64(n)), _unit(_f64(l)), _unit(_f64(v))  # noqa: E741
    a_d, a_s = _f64(a_d), _f64(a_s)
    alpha = alpha_from_roughness(r, r_min)
    h = _unit(l + v)
    nl = np.sum(n * l, axis=-1)
    nv = np.sum(n * v, axis=-1)
    nh = np.sum(n * h, axis=-1)
    vh = np.sum(v * h, axis=-1)
    front = (nl > 0) & (nv > 0)
    nl_, nv_ = np.maximum(nl, 0.0), np.maximum(nv, 0.0)
    # G1(nl) G1(nv) / (4 nl nv) written without the divisions by the cosines.
    vis = _inv_g1_denominator(nl_, alpha) * _inv_g1_denominator(nv_, alpha)
    spec = (ggx_D(nh, alpha) * vis)[..., None] * schlick_F(vh[..., None], a_s)
    f = a_d / np.pi + spec
    return np.where(front[..., None], f, 0.0)


def eval_collocated(mu, a_d, a_s, r, r_min: float = R_MIN) -> np.ndarray:
    """Collocated model ``f = a_d/pi + a_s D(mu) G1(mu)^2 / (4 mu^2)`` (no cosine factor).

    Parameters
    ----------
    mu : (...) float
        ``n . w`` with w the direction to the (collocated) camera and light.
    a_d : (..., C), a_s : (..., 1) or (..., C), r : (...)

    Returns
    -------
    (..., C) float64; 0 where mu <= 0. Finite as mu -> 0+ (the limit is
    a_d/pi + a_s D(0) / alpha^2 = (a_d + a_s)/pi).
    """
    mu = _f64(mu)
    a_d, a_s = _f64(a_d), _f64(a_s)
    alpha = alpha_from_roughness(r, r_min)
    mp = np.maximum(mu, 0.0)
    g = _inv_g1_denominator(mp, alpha)
    spec = (ggx_D(mp, alpha) * g * g)[..., None] * a_s
    f = a_d / np.pi + spec
    return np.where((mu > 0)[..., None], f, 0.0)


def radiance_collocated(mu, dist, a_d, a_s, r, light_intensity: float = 1.0,
                        r_min: float = R_MIN) -> np.ndarray:
    """Radiance seen with the point light at the camera: ``I_e f max(0, mu) / dist^2``.

    Parameters
    ----------
    mu : (...) float
        ``n(y) . w``, w = (o - y)/|o - y|.
    dist : (...) float
        ``|y - o|`` (> 0).
    a_d, a_s, r : as in :func:`eval_collocated`.
    light_intensity : float
        I_e.

    Returns
    -------
    (..., C) float64.
    """
    mu = _f64(mu)
    dist = _f64(dist)
    f = eval_collocated(mu, a_d, a_s, r, r_min)
    return light_intensity * f * (np.maximum(mu, 0.0) / (dist * dist))[..., None]
