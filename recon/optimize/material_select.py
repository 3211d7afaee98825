"""Model only what the scene requires: choose the material model on held-out views.

Greedy forward selection over the models of :mod:`recon.optimize.material`: start with diffuse
only and try, in order, a uniform specular lobe, a spatially varying specular albedo, an RGB
specular albedo, a spatially varying roughness (after each accepted step the others are tried
again on top of it, until none is accepted); each candidate is fitted
(:func:`recon.optimize.material.fit_model`, warm-started from the accepted simpler fit, see
:func:`nested_init`) and kept only when its held-out error is lower than that of a *control* --
the current model refitted from the same start for the same iterations, so extra iterations
(which overfit the diffuse texture a little) are not mistaken for a better model -- by more than
the noise of that difference (the paired held-out test, :func:`recon.optimize.heldout.compare`):
``gain > z * SE`` and ``gain > min_gain * error``, with the held-out images cut into tiles, the
paired per-tile differences giving the gain (their mean; ``trim`` > 0 gives Yuen's trimmed
mean) and its standard error ``SE``.
"""

from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np

from recon.io.mesh import Mesh
from recon.optimize.gbuffer import build_gbuffer
from recon.optimize.heldout import compare
from recon.optimize.material import (DIFFUSE_ONLY, Fit, MaterialModel, MaterialProblem, SelectionSettings,
                                     covered_mean, fit_model, tile_errors)
from recon.optimize.remesh import rasterize_atlas
from recon.optimize.views import ViewSet

log = logging.getLogger(__name__)

STEP_ORDER = ("uniform specular", "spatially varying specular", "RGB specular", "spatially varying roughness")


def selection_steps(current: MaterialModel) -> list[tuple[str, MaterialModel]]:
    """The candidates tried after ``current`` was accepted, as (step name, model)."""
    return [(name, m) for name, m in _steps(current) if m != current]


def _steps(m: MaterialModel):
    r = dataclasses.replace
    yield "uniform specular", (r(m, specular="uniform") if m.specular == "none" else m)
    yield "spatially varying specular", r(m, specular="textured")
    if m.specular != "none":
        yield "RGB specular", r(m, specular_color="rgb")
        yield "spatially varying roughness", r(m, roughness="textured")


def nested_init(current: Fit, init_maps: dict, candidate: MaterialModel | None = None,
                covered: np.ndarray | None = None) -> dict:
    """Where a richer candidate starts: the accepted (simpler) fit's maps, so the candidate begins
    at the simpler model's solution (a new texture starts flat at the fitted uniform value, a new
    RGB specular grey), and the main loop's maps only for what the current model lacks (specular
    and roughness after "diffuse only").

    A candidate that makes roughness vary starts its specular albedo flat too (at the fitted
    map's mean): under a uniform roughness the fitted specular map absorbs the roughness pattern
    (bright where the true lobe is sharp), a trade-off the pair does not leave when warm-started
    from it; restarted flat, both are learned together, coarse levels first. Starting every
    candidate from the main loop's maps (the first design) met the same trap with the main
    loop's jointly fitted roughness. ``bench/selection.py`` shows the current result.
    """
    init = {"diffuse": current.maps["diffuse"]}
    has_specular = current.model.specular != "none"
    init["specular"] = current.maps["specular"] if has_specular else init_maps["specular"]
    init["roughness"] = current.maps["roughness"] if has_specular else init_maps["roughness"]
    if candidate is not None and candidate.roughness == "textured" and current.model.roughness == "uniform":
        sp = np.asarray(init["specular"], np.float32)
        cov = covered if covered is not None else np.ones(sp.shape[:2], bool)
        init["specular"] = np.broadcast_to(covered_mean(sp, cov).astype(np.float32), sp.shape).copy()
    return init


def select_material(mesh: Mesh, init_maps: dict, covered: np.ndarray, train: ViewSet, heldout: ViewSet,
                    light: float, tone_scale: float, s: SelectionSettings, spp: int = 4, seed: int = 0,
                    progress=None, scorer=None) -> tuple[Fit, dict]:
    """Greedy forward selection of the material model (module docstring).

    Parameters
    ----------
    mesh : the final mesh with its UV atlas (fixed).
    init_maps : the main loop's maps {"diffuse": (T,T,3), "specular": (T,T,1|3), "roughness": (T,T,1)}.
    covered : (T, T) bool, texels inside the charts.
    train, heldout : target views (images at the size to compare at).
    light, tone_scale : I_e and the tone map's scale (as in the main loop).
    scorer : optional ``scorer(model, init) -> Fit`` (its ``tile_errors`` set) that fits and scores
        a candidate instead of the ideal formation here, with a ``criterion`` string attribute
        for the evidence: :func:`recon.optimize.imaging.material_scorer_under` compares the
        models under a phone's imaging terms.

    Returns
    -------
    (the chosen Fit, evidence dict for summary.json / the report)
    """
    t0 = time.perf_counter()
    if scorer is None:
        gb_train = build_gbuffer(mesh, list(train.cameras), spp, seed)
        gb_held = build_gbuffer(mesh, list(heldout.cameras), spp, seed + 1)
        problem = MaterialProblem(gb_train, train, s.tone_map, tone_scale)

        def scorer(model: MaterialModel, init: dict) -> Fit:
            fit = fit_model(model, gb_train, train, init, covered, light, tone_scale, s, problem)
            fit.tile_errors = tile_errors(fit.maps, model, gb_held, heldout, light, tone_scale, s)
            return fit
    t_gbuf = time.perf_counter() - t0

    def evaluate(model: MaterialModel, init: dict) -> Fit:
        fit = scorer(model, init)
        fit.heldout = float(np.nanmean(fit.tile_errors))
        if progress is not None:
            progress(model, fit)
        return fit

    current = evaluate(DIFFUSE_ONLY, init_maps)
    rows = [{"step": "diffuse only", "model": DIFFUSE_ONLY.to_dict(), "heldout_error": current.heldout,
             "train_loss": current.train_loss, "seconds": current.seconds, "accepted": True,
             "gain": None, "se": None, "relative_gain": None}]
    tried = {DIFFUSE_ONLY}
    control = None  # the current model refitted from its own maps (same iterations as a candidate)
    # passes over the ladder until one adds nothing: a step rejected early is tried again on top
    # of a later one (a textured specular fitted under a uniform roughness can absorb the
    # roughness pattern and generalize worse, then win once the roughness varies)
    todo = [name for name in STEP_ORDER]
    while todo:
        name = todo.pop(0)
        cands = dict(selection_steps(current.model))
        cand = cands.get(name)
        if cand is None or cand in tried:
            continue
        tried.add(cand)
        if control is None:
            control = evaluate(current.model, current.maps)
        fit = evaluate(cand, nested_init(current, init_maps, cand, covered))
        cmp = compare(fit.tile_errors, control.tile_errors, s)
        rows.append({"step": name, "model": cand.to_dict(), "heldout_error": fit.heldout,
                     "control_heldout_error": control.heldout,
                     "train_loss": fit.train_loss, "seconds": fit.seconds, **cmp})
        log.info("material: %-28s held-out %.5f (gain %+.5f, SE %.5f) %s", name, fit.heldout, cmp["gain"], cmp["se"],
                 "kept" if cmp["accepted"] else "rejected")
        if cmp["accepted"]:
            current, control = fit, None
            todo = [n for n in STEP_ORDER if n != name]  # every other step again, in order
    evidence = {
        "criterion": f"keep a richer model when its held-out error is lower than the current model's (refitted "
                     f"as long) by > {s.z} x SE of the paired per-tile difference (over {s.tile}-pixel tiles"
                     + (f", {100 * s.trim:.3g} % trimmed mean" if s.trim else "") + ") and by "
                     f"> {100 * s.min_gain:.3g} %" + getattr(scorer, "criterion", ""),
        "metric": f"mean |Phi(render) - Phi(photo)| (Phi = {s.tone_map} tone map) over held-out pixels",
        "heldout_views": len(heldout),
        "train_views": len(train),
        "image_size": [int(train.cameras[0].width), int(train.cameras[0].height)],
        "spp": int(spp),
        "iterations": int(s.iterations),
        "candidates": rows,
        "chosen": current.model.to_dict(),
        "chosen_heldout_error": current.heldout,
        "seconds": time.perf_counter() - t0,
        "gbuffer_seconds": t_gbuf,
    }
    return current, evidence


def select_on_known_mesh(mesh: Mesh, train: ViewSet, heldout: ViewSet, light: float, tone_scale: float,
                         s: SelectionSettings, spp: int = 4, texture_size: int = 256, full_iterations: int = 300,
                         progress=None) -> tuple[Fit, dict]:
    """The selection on a given mesh without the main loop (benchmarks and tests of the selection):
    constant maps (diffuse 0.3, specular 0.1, roughness 0.4), the full model fitted from them for
    ``full_iterations`` steps as the main loop would leave it, then :func:`select_material`."""
    T = int(texture_size)
    covered = rasterize_atlas(mesh, T)[0] >= 0
    const = {"diffuse": np.full((T, T, 3), 0.3, np.float32), "specular": np.full((T, T, 1), 0.1, np.float32),
             "roughness": np.full((T, T, 1), 0.4, np.float32)}
    gb = build_gbuffer(mesh, list(train.cameras), spp, 0)
    full = fit_model(MaterialModel(), gb, train, const, covered, light, tone_scale,
                     dataclasses.replace(s, iterations=int(full_iterations)),
                     MaterialProblem(gb, train, s.tone_map, tone_scale))
    return select_material(mesh, full.maps, covered, train, heldout, light, tone_scale, s, spp=spp, progress=progress)
