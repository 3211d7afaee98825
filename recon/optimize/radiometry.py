"""The flash's scale from the photos, and the checks that a run did not collapse.

The flash's intensity I_e (DESIGN section 3) is rarely known: SfM's frame has no physical scale,
and a phone's flash power and exposure are unknown. Only the product of I_e and the albedos is
seen in the photos (every term of the collocated model is linear in I_e a_d and I_e a_s), so I_e
is a *gauge*: any value works as long as the albedos can reach the photos' brightness inside
their range [0, 1]. A value far too small makes the photos unreachable (the image term stops
pulling and the regularizers shrink the surface to a point); far too large, the albedos are tiny
but the fit is the same.

The estimate, before the shape moves: the initial mesh is traced from every training view at a
low resolution (open3d, the G-buffer of :mod:`recon.optimize.gbuffer`); where a pixel is well
inside the mask, unclipped and seen between ``MIN_ANGLE_DEG`` and ``MAX_ANGLE_DEG`` from the
surface normal (the specular highlight of a collocated flash sits at normal incidence: on a
glossy blob, a_s 0.3 at roughness 0.35, the 98th percentile of all pixels was 2.6x the diffuse
one, of the pixels seen at 20-60 degrees 1.06x; the hull's normals are least reliable at grazing
angles), the
linear photo divided by the unit-albedo, unit-intensity collocated diffuse render
(``mu / (pi d^2)``) is that pixel's apparent I_e a_d per channel. The convention
(``WHITE_POINT``): I_e is set so that the ``WHITE_PERCENTILE``-th percentile of these values
(largest channel) is an albedo of ``WHITE_VALUE``, i.e. the albedo is *relative*: the object's
brightest common reflectance (excluding the top 2 % of pixels: highlights and outliers) sits at
0.85, leaving headroom below 1 for what the hull's shading misjudges. The initial diffuse map is
the per-channel median of the same values in that gauge. The maps are then refined with
everything else (the loop moves I_e a_d and I_e a_s; exposure gains are normalized to geometric
mean 1, so they cannot take the global scale), and :func:`clipped_fraction` reports how much of
the final diffuse map sits at 1 (a sign that the gauge was too low).

With ``light.intensity`` in ``cameras.json`` or ``light_intensity`` in ``capture.yaml`` (a
calibrated flash, a synthetic capture's truth) the given I_e is used as is and the albedo is
absolute; ``light.scale: estimate`` estimates it anyway (to measure the estimate).

Collapse: :func:`mask_coverage` projects the current mesh into views and measures how much of
the masks it covers and how much of it falls outside them; :func:`check_not_collapsed` turns a
surface that covers far less than the masks, or an area that shrank to a fraction of the initial
mesh's, into an :class:`CollapseError` naming the likely causes.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from recon.io.mesh import Mesh
from recon.optimize.gbuffer import build_gbuffer

log = logging.getLogger(__name__)

WHITE_PERCENTILE = 98.0
WHITE_VALUE = 0.85
MIN_ANGLE_DEG = 20.0
"""Pixels seen closer to the normal than this (on the initial mesh) are left out: the specular
highlight of the collocated flash."""
MAX_ANGLE_DEG = 60.0
"""Pixels lit more obliquely than this (on the initial mesh) are left out: the hull's normals
are least reliable at grazing angles, and mu -> 0 there makes the ratio ill-conditioned."""
ESTIMATE_SIZE = 128
MIN_PIXELS = 200
"""Pixels the estimate wants; with fewer (a heavily clipped capture: 99 pixels of 16x over-exposed
DNGs in tests/test_extremes.py) it takes the pixels at any angle and on the masks' border too
(logged), and refuses below ``MIN_PIXELS_LAST``."""
MIN_PIXELS_LAST = 20


class LightScaleError(ValueError):
    """The photos cannot give the flash's scale (no usable object pixel)."""


class CollapseError(ValueError):
    """The optimized surface collapsed or left the masks; the message names the likely cause."""


@dataclass(frozen=True)
class LightScale:
    """The flash intensity the run uses and where it came from.

    intensity : I_e in the frame of ``cameras.json``
    source : "given" (cameras.json / capture.yaml) or "estimated" (from the photos)
    init_diffuse : (3,) initial diffuse albedo in this gauge (None: the settings' constant)
    pixels : how many pixels the estimate used (0 when given)
    apparent : percentiles 50 / WHITE_PERCENTILE of the apparent I_e * albedo (largest channel)
    """

    intensity: float
    source: str
    init_diffuse: tuple | None = None
    pixels: int = 0
    apparent: tuple = ()

    @property
    def albedo(self) -> str:
        return "absolute" if self.source == "given" else "relative"

    def to_dict(self) -> dict:
        d = {"intensity": float(self.intensity), "source": self.source, "albedo": self.albedo,
             "pixels": int(self.pixels)}
        if self.source == "estimated":
            d["convention"] = (f"the {WHITE_PERCENTILE:g}th percentile of the object's apparent diffuse "
                               f"reflectance (largest channel) is albedo {WHITE_VALUE:g}")
            d["init_diffuse"] = None if self.init_diffuse is None else [float(x) for x in self.init_diffuse]
            d["apparent_median"], d["apparent_white"] = (float(x) for x in self.apparent)
        return d


def _with_uvs(mesh: Mesh) -> Mesh:
    if mesh.v_tex is not None:
        return mesh
    return Mesh(mesh.v_pos, mesh.t_pos_idx, np.zeros((1, 2)), np.zeros_like(mesh.t_pos_idx))


def unit_render(mesh: Mesh, cameras, spp: int = 1, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Collocated diffuse render of ``mesh`` with albedo 1 and I_e = 1 (DESIGN section 3):
    (N, h, w) radiance ``mu / (pi d^2)`` averaged over the pixel's samples, (N, h, w) fraction
    of samples that hit, (N, h, w) mean ``mu`` of the hits."""
    cameras = list(cameras)
    gb = build_gbuffer(_with_uvs(mesh), cameras, spp=spp, seed=seed)
    n = int(np.prod(gb.shape))
    pix = gb.pixel.numpy()
    mu = gb.mu.numpy().astype(np.float64)
    rad = np.bincount(pix, mu * gb.inv_d2.numpy() / np.pi, minlength=n) / gb.spp
    hits = np.bincount(pix, minlength=n).astype(np.float64)
    mu_sum = np.bincount(pix, mu, minlength=n)
    mean_mu = np.where(hits > 0, mu_sum / np.maximum(hits, 1), 0.0)
    return (rad.reshape(gb.shape), (hits / gb.spp).reshape(gb.shape), mean_mu.reshape(gb.shape))


def estimate_light_scale(mesh: Mesh, images: np.ndarray, masks: np.ndarray, clipped: np.ndarray,
                         cameras, seed: int = 0) -> LightScale:
    """The flash's I_e from linear photos of the object and its initial mesh (module docstring).

    images : (N, h, w, 3) linear photos; masks : (N, h, w) object coverage in [0, 1];
    clipped : (N, h, w) bool, clipped pixels; cameras : N cameras at (w, h).
    """
    rad, hit, mu = unit_render(mesh, cameras, spp=4, seed=seed)
    cos_lo, cos_hi = float(np.cos(np.radians(MAX_ANGLE_DEG))), float(np.cos(np.radians(MIN_ANGLE_DEG)))
    usable = ~clipped & (rad > 0) & np.all(np.isfinite(images), axis=-1) & np.all(images >= 0, axis=-1)
    ok = usable & (masks > 0.99) & (hit > 0.99) & (mu > cos_lo) & (mu < cos_hi)
    n_ok = int(ok.sum())
    if n_ok < MIN_PIXELS:  # few unclipped pixels in the band: any angle, the masks' border too
        wide = usable & (masks > 0.5) & (hit > 0.5) & (mu > 0.05)
        log.info("the flash's scale: %d pixels seen 20-60 degrees off the normal; taking every unclipped pixel "
                 "of the object (%d)", n_ok, int(wide.sum()))
        ok, n_ok = wide, int(wide.sum())
    if n_ok < MIN_PIXELS_LAST:
        raise LightScaleError(
            f"only {n_ok} pixels of the object are seen by both the photos' masks and the initial mesh "
            f"(need {MIN_PIXELS_LAST}): the flash's brightness cannot be estimated; the initial mesh and the masks "
            "disagree (check masks/ and the init_mesh stage), or give light_intensity in capture.yaml")
    q = images[ok].astype(np.float64) / rad[ok][:, None]  # apparent I_e * a_d per channel
    q_max = q.max(axis=1)
    med = float(np.median(q_max))
    white = float(np.percentile(q_max, WHITE_PERCENTILE))
    if not (white > 0 and np.isfinite(white)):
        raise LightScaleError(
            "the object's pixels are black in every photo: the flash's brightness cannot be estimated; "
            "check that the flash fired and the photos are exposed (linear/preview/)")
    intensity = white / WHITE_VALUE
    init = np.clip(np.median(q, axis=0) / intensity, 0.02, WHITE_VALUE)
    return LightScale(float(intensity), "estimated", tuple(float(x) for x in init), n_ok, (med, white))


def clipped_fraction(diffuse: np.ndarray, covered: np.ndarray | None = None, level: float = 0.995) -> float:
    """Fraction of the (covered) texels whose largest diffuse channel is at the top of the range."""
    d = np.asarray(diffuse)
    top = d.max(axis=-1) >= level
    if covered is not None:
        cov = np.asarray(covered, bool)
        return float(top[cov].mean()) if cov.any() else 0.0
    return float(top.mean())


# ---------------------------------------------------------------------- collapse
def mask_coverage(mesh: Mesh, cameras, masks: np.ndarray, max_views: int = 8) -> dict:
    """How the mesh's silhouettes agree with the masks, over up to ``max_views`` views spread
    over the capture: ``covered`` = |silhouette & mask| / |mask| (mean and minimum over views),
    ``outside`` = |silhouette \\ mask| / |silhouette| (mean), ``iou`` (mean)."""
    cameras = list(cameras)
    n = len(cameras)
    pick = np.unique(np.linspace(0, n - 1, min(n, max_views)).round().astype(int))
    _, hit, _ = unit_render(mesh, [cameras[i] for i in pick], spp=1)
    sil = hit > 0.5
    m = np.asarray(masks)[pick] > 0.5
    inter = (sil & m).sum(axis=(1, 2)).astype(np.float64)
    area_m = m.sum(axis=(1, 2)).astype(np.float64)
    area_s = sil.sum(axis=(1, 2)).astype(np.float64)
    union = (sil | m).sum(axis=(1, 2)).astype(np.float64)
    has = area_m > 0
    covered = inter[has] / area_m[has] if has.any() else np.zeros(1)
    outside = np.where(area_s > 0, (area_s - inter) / np.maximum(area_s, 1), 0.0)
    iou = np.where(union > 0, inter / np.maximum(union, 1), 1.0)
    return {"views": [int(i) for i in pick], "covered_mean": float(covered.mean()), "covered_min": float(covered.min()),
            "outside_mean": float(outside.mean()), "iou_mean": float(iou.mean())}


def check_not_collapsed(where: str, coverage: dict, area: float, area_init: float, light: LightScale | None,
                        min_covered: float = 0.3, min_area_ratio: float = 0.1) -> None:
    """Raise :class:`CollapseError` when the surface covers less than ``min_covered`` of the masks
    (mean over views) or its area fell below ``min_area_ratio`` of the initial mesh's."""
    ratio = area / area_init if area_init > 0 else 0.0
    if coverage["covered_mean"] >= min_covered and ratio >= min_area_ratio:
        return
    causes = []
    if light is not None and light.source == "given":
        causes.append(f"the flash's intensity I_e = {light.intensity:.4g} given in cameras.json/capture.yaml is wrong "
                      "for these photos (remove it and the pipeline estimates it)")
    elif light is not None:
        causes.append(f"the estimated flash intensity I_e = {light.intensity:.4g} (from {light.pixels} pixels) is off")
    causes += ["the masks do not match the photos (check masks/ or results/<capture>/masks/)",
               "the cameras are wrong (check poses/cameras.json; a given cameras.json must match the photos)"]
    raise CollapseError(
        f"{where}: the surface collapsed: it covers {100 * coverage['covered_mean']:.0f} % of the masks "
        f"(worst view {100 * coverage['covered_min']:.0f} %) and its area is {100 * ratio:.1f} % of the initial "
        f"mesh's; no asset is written. Likely causes: " + "; ".join(causes) + ".")

