"""The differentiable renderer's settings and its input error (:mod:`recon.render.collocated`)."""

from __future__ import annotations

from dataclasses import dataclass

from recon.brdf import R_MIN

__all__ = ["RenderSettings", "RenderError", "BOUNDARY_MODES"]

BOUNDARY_MODES = ("edge", "none", "projective")


class RenderError(ValueError):
    """Inputs the renderer cannot use; the message says what was received and what is expected."""


@dataclass(frozen=True)
class RenderSettings:
    """How to render and differentiate.

    Attributes
    ----------
    spp : int
        Samples per pixel (uniform over the pixel footprint).
    stratified : bool
        Where ``spp`` is a square k^2, place the samples on a jittered k x k grid over the
        pixel (each sample stays uniform over the pixel, so the estimate stays unbiased; the
        variance drops). Otherwise independent uniform samples.
    boundary : str
        ``"edge"``: interior + edge-sampled boundary term (unbiased); ``"none"``: interior term
        only (biased at silhouettes); ``"projective"``: Mitsuba's ``direct_projective``
        integrator on an equivalent Mitsuba scene (slow, for comparison).
    edge_samples_per_pixel : float
        Boundary samples per view = this x image width x height (used when ``edge_samples``
        is None).
    edge_samples : int or None
        Boundary samples per view, overriding ``edge_samples_per_pixel``.
    edge_eps_px : float
        Offset (pixels) of the two rays that evaluate the jump across a silhouette.
    r_min : float
        Roughness is clamped to [r_min, 1].
    variant : str or None
        Mitsuba variant (default: :func:`recon.mi.default_variant`, ``llvm_ad_rgb``).
    profile : bool
        Synchronize after each phase of a render and add its wall time (seconds) to
        ``CollocatedRenderer.timings`` (slows rendering a little; for benchmarks).
    """

    spp: int = 4
    boundary: str = "edge"
    stratified: bool = True
    edge_samples_per_pixel: float = 0.25
    edge_samples: int | None = None
    edge_eps_px: float = 1e-3
    r_min: float = R_MIN
    variant: str | None = None
    profile: bool = False

    def __post_init__(self):
        if int(self.spp) < 1:
            raise RenderError(f"RenderSettings.spp must be >= 1, got {self.spp}")
        if self.boundary not in BOUNDARY_MODES:
            raise RenderError(
                f"RenderSettings.boundary must be one of {BOUNDARY_MODES}, got {self.boundary!r}")
        if self.edge_samples is not None and int(self.edge_samples) < 0:
            raise RenderError(f"RenderSettings.edge_samples must be >= 0, got {self.edge_samples}")
        if not self.edge_samples_per_pixel >= 0:
            raise RenderError("RenderSettings.edge_samples_per_pixel must be >= 0, got "
                              f"{self.edge_samples_per_pixel}")
        if not 0 < self.edge_eps_px < 0.5:
            raise RenderError(f"RenderSettings.edge_eps_px must be in (0, 0.5), got {self.edge_eps_px}")
        if not 0 < self.r_min <= 1:
            raise RenderError(f"RenderSettings.r_min must be in (0, 1], got {self.r_min}")

    def edge_count(self, width: int, height: int) -> int:
        """Number of boundary samples for one view of ``width`` x ``height`` pixels."""
        if self.edge_samples is not None:
            return int(self.edge_samples)
        return int(round(self.edge_samples_per_pixel * width * height))
