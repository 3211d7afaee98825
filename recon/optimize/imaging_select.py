"""Which imaging terms (:mod:`recon.optimize.formation`) to keep, decided on held-out views,
and the optimize stage's entries to that selection.

Selection: forward selection in rounds: each remaining term is fitted on top of the current
terms with the material maps of the chosen material model (warm-started from the accepted fit)
and compared with a control (the current model refitted as long) by the same paired per-tile
test as the material model (:func:`recon.optimize.heldout.compare`); of the terms that pass,
the one with the largest gain is kept, and the next round tries the rest. Then each kept term
is checked backwards: dropped when the model without it (refitted) is not significantly worse.
Each fit is :func:`recon.optimize.imaging.fit_imaging`, each score
:func:`recon.optimize.imaging.heldout_tiles` (the held-out views' exposure gains cross-fitted on
a checkerboard's tiles).
"""

from __future__ import annotations

import logging
import time

import numpy as np

from recon.optimize.formation import TERMS, ImagingModel, ImagingParams
from recon.optimize.imaging import ImagingFit, ImagingSettings, fit_imaging, heldout_tiles, problems
from recon.optimize.heldout import compare
from recon.optimize.material import Fit, MaterialModel, SelectionSettings
from recon.optimize.views import ViewSet, capture_is_ldr, recorded_exposures

log = logging.getLogger(__name__)


def select_imaging(mesh, material_fit: Fit, covered: np.ndarray, train: ViewSet, heldout: ViewSet, light: float,
                   tone_scale: float, s: SelectionSettings, im: ImagingSettings | None = None,
                   candidates: tuple = TERMS, offset_given=None, spp: int = 4, seed: int = 0,
                   progress=None, exposure: dict | None = None) -> tuple[ImagingFit, dict]:
    """Greedy forward selection of the imaging terms (module docstring) on a fixed mesh.

    ``material_fit`` (the chosen material model and its maps) is the start; ``candidates`` the
    terms to try (leave ``tone`` out for RAW/EXR captures, ``flash_offset`` when it is given:
    ``offset_given`` (3,) then applies to every fit). Returns the chosen fit (its maps refitted
    under the chosen imaging) and the evidence for summary.json and the report. ``exposure``:
    the views' recorded exposures (image stem -> h_k / h_ref, :func:`recon.optimize.views.recorded_exposures`), where
    the tone curve acts.
    """
    im = im or ImagingSettings()
    t0 = time.perf_counter()
    p_train, p_held, length = problems(mesh, train, heldout, s, tone_scale, spp, seed, exposure)
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


# ---------------------------------------------------------------------- the optimize stage's entries
def candidate_terms(settings, ldr: bool | None) -> tuple[tuple, bool]:
    """The terms of ``imaging.terms`` to try and whether the tone curve is among them
    (``imaging.tone_curve``: fit, identity, or auto = only for JPEG/PNG photos)."""
    tone = settings.imaging.tone_curve == "fit" or (settings.imaging.tone_curve == "auto" and bool(ldr))
    return tuple(t for t in settings.imaging.terms if tone or t != "tone"), tone


def run_imaging_selection(settings, mesh, maps: dict, material: MaterialModel, covered: np.ndarray, views, heldout,
                          light: float, tone_scale: float, images, train_set=None,
                          heldout_set=None) -> tuple[dict, MaterialModel, dict]:
    """The optimize stage's imaging selection (``select_imaging``): the maps refitted under the
    chosen imaging terms, the material model, and the evidence for summary.json.
    ``train_set``/``heldout_set``: the views at ``select_image_size`` with the cameras the model
    goes with (refined by the optimizer, issue 17); default ``views.at(size)``/``heldout.at(size)``."""
    ldr = capture_is_ldr(images)
    terms, tone = candidate_terms(settings, ldr)
    size = int(settings.select.select_image_size)
    log.info("imaging model selection on %d held-out views: %s", len(heldout), ", ".join(terms))
    train_set = train_set if train_set is not None else views.at(size)
    heldout_set = heldout_set if heldout_set is not None else heldout.at(size)
    fit, ev = select_imaging(mesh, Fit(material, maps, float("nan")), covered, train_set, heldout_set,
                             light, tone_scale, settings.imaging_selection_settings(), candidates=terms,
                             offset_given=settings.imaging.flash_offset, spp=int(settings.select.select_spp),
                             seed=int(settings.seed) + 17, exposure=recorded_exposures(images) if tone else None)
    ev["tone_curve"] = {"setting": settings.imaging.tone_curve, "photos_are_ldr": ldr, "tried": tone}
    return fit.material.maps, material, ev


def select_for_loop(settings, mesh, maps: dict, material: MaterialModel, covered: np.ndarray, train_set: ViewSet,
                    heldout_set: ViewSet, light: float, tone_scale: float, ldr: bool | None,
                    exposure: dict | None = None):
    """The imaging selection on the coarse model (``imaging.loop: select``): (ImagingParams of
    the chosen terms, or None when the ideal formation is kept and no flash offset is given;
    the evidence). ``exposure``: :func:`recon.optimize.views.recorded_exposures` of the photos (where the tone curve acts)."""
    terms, tone = candidate_terms(settings, ldr)
    fit, ev = select_imaging(mesh, Fit(material, maps, float("nan")), covered, train_set, heldout_set, light,
                             tone_scale, settings.imaging_selection_settings(), candidates=terms,
                             offset_given=settings.imaging.flash_offset, spp=int(settings.select.select_spp),
                             seed=int(settings.seed) + 23, exposure=exposure if tone else None)
    ev["tone_curve"] = {"setting": settings.imaging.tone_curve, "photos_are_ldr": ldr, "tried": tone}
    keep = bool(fit.model.terms) or settings.imaging.flash_offset is not None
    return (fit.params if keep else None), ev
