"""The coarse-to-fine schedule: each stage's edge length, large-steps lambda and learning rates,
and the plateau test that ends the stages early.

A stage (:class:`recon.optimize.settings.StageSettings`) asks for an edge length (a fraction of
the initial mesh's bounding box), raised here to ``min_edge_pixels`` pixel footprints at its
image size; its large-steps lambda keeps the smoothing length on the surface as the edges
shorten; its rates are the base rates (``lr_geometry`` in bounding boxes per step,
``lr_texture``) times :meth:`recon.optimize.settings.StageSettings.lr_factor` of the iteration.
With ``stop_on_plateau`` the held-out error after each stage is compared with the previous
stage's by the paired held-out test (:func:`recon.optimize.heldout.compare`).
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np

from recon.optimize.heldout import compare
from recon.optimize.material import heldout_error
from recon.optimize.settings import OptimizeSettings, StageSettings
from recon.optimize.views import Views

if TYPE_CHECKING:
    from recon.optimize.run import Run

log = logging.getLogger(__name__)


def learning_rates(settings: OptimizeSettings, bbox_scale: float, factor: float = 1.0) -> tuple[float, float]:
    """Adam's (geometry, texture) rates times ``factor`` (the stage's schedule): ``lr_geometry``
    is a fraction of the bounding box (longest side ``bbox_scale``) per step."""
    return settings.optim.lr_geometry * bbox_scale * factor, settings.optim.lr_texture * factor


def stage_lambda(settings: OptimizeSettings, stage: StageSettings, edge_length: float) -> float:
    """The large-steps lambda of a stage whose edges are ``edge_length`` (fraction of the bbox):
    ``largesteps_lambda * lambda_scale``, times ``(largesteps_reference_edge / edge_length)^2`` when
    the edges are shorter than the reference (the smoothing length on the surface stays fixed)."""
    lam = float(settings.optim.largesteps_lambda) * float(stage.lambda_scale)
    ref = float(settings.optim.largesteps_reference_edge)
    if ref > 0 and edge_length < ref:
        lam *= (ref / edge_length) ** 2
    return lam


def stage_edge_length(stage: StageSettings, settings: OptimizeSettings, views: Views, footprint_full: float,
                       bbox_scale: float) -> tuple[float, float, float]:
    """(edge length, requested length, lower limit) of a stage in world units: the stage's
    ``edge_length``, raised to ``min_edge_pixels`` pixel footprints at the stage's image size."""
    longest = max(views.cameras[0].width, views.cameras[0].height)
    size = min(settings.stage_image_size(stage), longest)  # the photos are never upsampled
    h_min = float(settings.schedule.min_edge_pixels) * footprint_full * longest / size
    h = float(stage.edge_length) * bbox_scale
    if h < h_min:
        log.info("stage edge length %.4g is below %.3g pixel footprints at %d px: using %.4g",
                 h, settings.schedule.min_edge_pixels, size, h_min)
    return max(h, h_min), h, h_min


def plateau(run: Run, si, mesh, maps, stage_infos) -> bool:
    """Held-out error after stage ``si`` (kept in its stage info, so a resumed run decides the
    same); True when it is not lower than the previous stage's by more than its noise."""
    settings = run.settings
    info = stage_infos[si]
    if "heldout_tiles" not in info:
        s = settings.selection_settings()
        tiles = heldout_error(mesh, maps, run.heldout.at(int(settings.select.select_image_size)), run.light, run.tone_scale, s,
                              spp=int(settings.select.select_spp), seed=int(settings.seed))
        info["heldout_tiles"] = [float(x) for x in tiles]
        info["heldout_error"] = float(np.nanmean(tiles))
        prev = stage_infos[si - 1] if si > 0 else None
        if prev is not None and "heldout_tiles" in prev:
            cmp = compare(np.asarray(info["heldout_tiles"]), np.asarray(prev["heldout_tiles"]), s)
            info["heldout_vs_previous"] = cmp
            info["plateau_stop"] = not cmp["accepted"]
        else:
            info["plateau_stop"] = False
        log.info("stage %d: held-out error %.5f%s", si, info["heldout_error"],
                 " (no clear gain over the previous stage)" if info["plateau_stop"] else "")
    return bool(info["plateau_stop"])
