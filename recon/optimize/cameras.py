"""The cameras in the optimize stage: refined with the surface, their refinement selected on
held-out views, the held-out views aligned to a fixed model, the cameras the model goes with.

Cameras refined by the renderer (issue 17, :mod:`recon.optimize.camera_refine`): with
``cameras.refine`` on (cameras from SfM) every training view's pose and the shared intrinsics
are parameters of the same objective (their prior is its ``camera`` term), stepped by their own
Adam after the surface's (:class:`CameraFit`), the similarity gauge projected out after each
step. With "select" the run is made twice, without (the control) and with the refinement, from
the same start and seeds; each run's held-out poses are then aligned to its fixed final model
for the same number of steps (:func:`align_heldout`; their SfM errors would otherwise blur
both), and the refined run is kept only when its held-out error is lower by more than the noise
(:func:`select_refinement`, the paired test of :func:`recon.optimize.heldout.compare`).
``optimize/cameras.json`` holds the cameras the final model goes with (:func:`output_cameras`):
the refined training views, the aligned held-out views, the input cameras otherwise.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from typing import TYPE_CHECKING

import numpy as np
import torch

from recon.io.cameras import Camera, CameraSet
from recon.io.mesh import Mesh
from recon.optimize import checkpoint as ckpt
from recon.optimize import fitting, objective
from recon.optimize.camera_refine import CameraRefinement, scene_extent
from recon.optimize.formation import ImagingModel, ImagingParams
from recon.optimize.gbuffer import build_gbuffer
from recon.optimize.heldout import compare
from recon.optimize.imaging import ImagingProblem, ImagingSettings, heldout_tiles_under
from recon.optimize.iteration import Stage, make_renderer, map_values
from recon.optimize.loop_imaging import LoopImaging
from recon.optimize.material import heldout_error, model_from_settings
from recon.optimize.settings import OptimizeSettings
from recon.optimize.tracks import TrackTerm
from recon.optimize.views import Views, ViewSet, view_exposures

if TYPE_CHECKING:
    from recon.optimize.run import Run

log = logging.getLogger(__name__)


class CameraFit:
    """A run's camera refinement: the training views' corrections and their optimizer, which
    live across the coarse-to-fine stages (the views are the same in every stage)."""

    def __init__(self, views: Views, settings: OptimizeSettings, first_stage: int = 0):
        self.first_stage = int(first_stage)  # the cameras are held before this stage (cameras.first_stage)
        self.ref = CameraRefinement(views.cameras, settings.camera_prior(), intrinsics=settings.cameras.intrinsics)
        self.opt = torch.optim.Adam(self.ref.param_groups(), betas=settings.optim.betas)
        for g in self.opt.param_groups:
            g["base_lr"] = g["lr"]

    def step(self, factor: float) -> None:
        """Adam step at the base rates times ``factor`` (the stage's schedule), then the gauge."""
        for g in self.opt.param_groups:
            g["lr"] = g["base_lr"] * factor
        self.opt.step()
        self.ref.fix_gauge()

    def state(self) -> dict:
        return {"params": {k: v.detach().clone() for k, v in self.ref.state_dict().items()},
                "optimizer": self.opt.state_dict()}

    def load(self, state: dict) -> None:
        self.ref.load_state_dict(state["params"])
        self.opt.load_state_dict(state["optimizer"])


def align_heldout(run: Run, st: Stage) -> dict:
    """Align the held-out views' poses to a run's fixed final model; their held-out error.

    The held-out cameras (with the run's refined intrinsics, if any) get per-view pose
    corrections (no gauge: the model is fixed) fitted for ``cameras.align_iterations`` Adam steps
    on the rendering loss at ``select_image_size`` (rates decaying to 1/10, the camera prior
    added), as bundle-adjusting methods evaluate novel views. Returns ``viewset`` (the held-out
    targets with the aligned cameras), ``world_to_camera`` (stem -> aligned (4, 4) pose),
    ``tiles`` (per-tile held-out errors, :func:`recon.optimize.material.heldout_error`) and
    ``corrections`` (of the held-out poses).

    Under the loop's imaging terms (``imaging.loop``) the held-out views are rendered as the
    training views are (flash offset and ambient in the renderer, falloff and tone curve on the
    images) with exposure gains of their own, fitted with the poses (exposure prior); their
    errors are those of the imaging selection (gains cross-fitted on a checkerboard's tiles,
    fitted on one colour, errors on the other: :func:`recon.optimize.imaging.heldout_tiles_under`). Rendered
    under the ideal formation instead, a photo's exposure or tone would be explained by the pose
    (with the flash at the lens, brightness and distance trade) and the two runs compared on
    errors the cameras do not cause.
    """
    settings = run.settings
    size = int(settings.select.select_image_size)
    vs = run.heldout.at(size)
    at_size = list(vs.cameras)
    if run.cameras is not None:
        at_size = run.cameras.ref.with_intrinsics(at_size)
    with torch.no_grad():
        maps = map_values(settings, st.maps)
    mesh = Mesh(st.mesh.v_pos.copy(), st.mesh.t_pos_idx, st.mesh.v_tex, st.mesh.t_tex_idx)
    return align_views(mesh, maps, vs, at_size, settings, run.light, run.tone_scale, run.weights, run.imaging,
                       scene_extent(run.views.cameras), run.bbox_scale, exposure=run.exposure)


def align_views(mesh: Mesh, maps: dict, vs: ViewSet, cameras: list[Camera], settings: OptimizeSettings, light: float,
                tone_scale: float, weights: dict, imaging: LoopImaging | None, scene_size: float,
                object_size: float | None = None, tracks: tuple[TrackTerm, list[Camera]] | None = None,
                exposure: dict | None = None) -> dict:
    """:func:`align_heldout` of views ``vs`` (starting from ``cameras``, at the size of ``vs``)
    to a fixed model: ``mesh`` and its map values (``diffuse``, ``specular``, ``roughness``
    tensors), rendered under ``imaging`` (the loop's imaging terms, if it has chosen any; None:
    ``imaging.loop`` off). With the loop on the errors are always the imaging selection's white
    tiles (the ideal formation's when it chose nothing), so that two runs compare tile for tile
    whatever each chose. ``scene_size``: the translation unit of the camera prior (the training
    cameras' extent). ``tracks``: SfM's tracks of these views and the views' cameras at the
    photos' size, reprojected through the aligned cameras as a second term (weight
    ``weights["tracks"]``; :mod:`recon.optimize.tracks`). ``exposure``: stem -> recorded exposure
    (:func:`recon.optimize.views.recorded_exposures`), where the tone curve acts.

    The fit is :func:`recon.optimize.fitting.fit` on the objective's image term (weight 1),
    ``camera`` prior, ``imaging`` (exposure) prior and ``tracks`` term, weighted by ``weights``."""
    ali = CameraRefinement(cameras, settings.camera_prior(), intrinsics=False, gauge=False, scene_size=scene_size)
    idx = list(range(len(cameras)))
    im_settings = ImagingSettings()
    loop_on = imaging is not None
    if imaging is not None and not imaging.active:
        imaging = None  # the loop chose nothing: the ideal formation
    own = None  # these views' own exposure gains, fitted with their poses (the loop's other terms as they are)
    if imaging is not None and imaging.params.model.has("exposure"):
        own = imaging.params.clone(n_views=len(idx), normalize_gains=False)
        with torch.no_grad():
            own.log_gain.zero_()
    held_e = view_exposures(vs.cameras, exposure)  # these views' recorded exposures (None: all 1)
    n = int(settings.cameras.align_iterations)
    if n > 0:
        renderer = make_renderer(settings, mesh)
        v = torch.from_numpy(mesh.v_pos).to(torch.float32)
        groups = ali.param_groups() + ([] if own is None else [{"params": [own.log_gain], "lr": im_settings.lr}])
        w = {"render": 1.0, **{k: weights.get(k, 0.0) for k in ("camera", "imaging", "tracks")}}
        lighting = imaging.lighting() if imaging is not None else {}
        track_term, track_cameras = tracks if tracks is not None else (None, None)

        def image_term(it: int) -> torch.Tensor:
            img = renderer.render_torch(v, maps["diffuse"], maps["specular"], maps["roughness"], ali.cameras(idx, cameras),
                                        light, seed=ckpt.render_seed(settings.seed, 1000, it),
                                        camera_table=ali.table(idx, cameras), **lighting)
            if imaging is not None:
                img = imaging.apply(img, idx, gains=None if own is None else own.gains(), exposure=held_e)
            return objective.render_loss(img, vs.images, vs.weights, settings.loss.tone_map, tone_scale)

        def priors() -> dict:
            return {**objective.camera_terms(ali, None, w),
                    **objective.imaging_terms(None if own is None else lambda: own.prior(im_settings.exposure_prior), w),
                    **objective.tracks_terms(track_term, ali, track_cameras, w)}

        fitting.fit(groups, n, image_term, w, priors=priors, betas=settings.optim.betas, final_loss=False)
    aligned = dataclasses.replace(vs, cameras=tuple(ali.cameras(idx, cameras)))
    maps_np = {k: x.detach().numpy().astype(np.float32) for k, x in maps.items()}
    sel = settings.selection_settings()
    if not loop_on:
        tiles = heldout_error(mesh, maps_np, aligned, light, tone_scale, sel, spp=int(settings.select.select_spp),
                              seed=int(settings.seed))
    else:
        gb = build_gbuffer(mesh, list(aligned.cameras), int(settings.select.select_spp), int(settings.seed))
        prob = ImagingProblem(gb, aligned, sel.tone_map, tone_scale, sel.tile, exposure=exposure)
        params = imaging.params if imaging is not None else ImagingParams(ImagingModel(()), len(idx), 1.0, tone_scale)
        tiles, _ = heldout_tiles_under(maps_np, model_from_settings(maps_np["specular"].shape[2]), params,
                                       prob, light, sel, im_settings)
    return {"viewset": aligned, "world_to_camera": {c.stem: c.world_to_camera for c in aligned.cameras},
            "tiles": tiles, "corrections": ali.corrections(object_size=object_size)}


def select_refinement(runs: list, done: list, info: dict, cams: CameraSet, timer) -> tuple[int, dict | None]:
    """The camera refinement decided on held-out views: each run's held-out poses aligned to its
    final model (:func:`align_heldout`, timed as ``cameras`` in ``timer``); with ``info["mode"]``
    "select" (the control run first, the refined one second) the refined run kept only when the
    paired held-out test (:func:`recon.optimize.heldout.compare`) finds it better. Fills ``info``
    (the summary's ``camera_refinement``); returns (the index of the run kept, its aligned
    held-out views: :func:`align_heldout`'s dict, or None)."""
    run0 = runs[0]
    settings, mode = run0.settings, info["mode"]
    aligned = {}
    if mode != "off" and run0.heldout is not None:
        for run, (st, _) in zip(runs, done, strict=True):
            t0 = time.perf_counter()
            aligned[id(run)] = align_heldout(run, st)
            timer.add("cameras", time.perf_counter() - t0)
    chosen = len(runs) - 1  # "on": the refined run; "off": the only one
    if mode == "select":
        ctrl, cand = (aligned[id(r)] for r in runs)
        run_imaging_active = any(r.imaging is not None and r.imaging.active for r in runs)
        cmp = compare(cand["tiles"], ctrl["tiles"], settings.selection_settings())
        chosen = 1 if cmp["accepted"] else 0
        info["selection"] = {
            "criterion": f"keep the refined cameras when the held-out error (each run's held-out poses aligned "
                         f"to its fixed model for {int(settings.cameras.align_iterations)} steps"
                         + (", under the loop's imaging terms with the views' own exposure gains"
                            if run_imaging_active else "") + ") is lower than the "
                         f"control's (same run without refinement) by > {settings.select.select_z} x SE of the paired "
                         f"per-tile difference and by > {100 * settings.select.select_min_gain:.3g} %",
            "control_heldout_error": float(np.nanmean(ctrl["tiles"])),
            "refined_heldout_error": float(np.nanmean(cand["tiles"])),
            **cmp,
            "run_seconds": [float(sum(p.timer.total.values())) for _, p in done],
        }
        log.info("camera refinement: held-out %.5f (control %.5f, gain %+.5f, SE %.5f): %s",
                 info["selection"]["refined_heldout_error"], info["selection"]["control_heldout_error"],
                 cmp["gain"], cmp["se"], "kept" if cmp["accepted"] else "rejected")
    run = runs[chosen]
    if any(r.cameras is not None for r in runs):
        fit = next(r.cameras for r in runs if r.cameras is not None)
        info["refined"] = run.cameras is not None
        info["corrections"] = fit.ref.corrections(object_size=run.bbox_scale,
                                                  cameras=[cams.by_stem()[s] for s in run.views.stems])
        info["intrinsics_refined"] = bool(settings.cameras.intrinsics)
    held = aligned.get(id(run))
    if held is not None:
        info["heldout_alignment"] = held["corrections"]
    return chosen, held


def output_cameras(cams: CameraSet, run: Run, heldout: dict | None, info: dict) -> CameraSet:
    """The cameras of the final model, full size: refined training views, aligned held-out
    views, every other frame of ``cams`` as it was; ``optimize_cameras`` records how."""
    given = cams.by_stem()
    by_stem = {}
    if run.cameras is not None:
        ref = run.cameras.ref
        full = [given[s] for s in run.views.stems]
        by_stem.update({c.stem: c for c in ref.cameras(range(len(full)), full)})
        if run.heldout is not None:
            by_stem.update({c.stem: c for c in ref.with_intrinsics([given[s] for s in run.heldout.stems])})
    if heldout is not None:  # aligned poses (independent of the image size)
        for stem, w2c in heldout["world_to_camera"].items():
            c = by_stem.get(stem, given[stem])
            by_stem[stem] = Camera(c.image, c.width, c.height, c.K, np.array(w2c, dtype=np.float64))
    frames = tuple(by_stem.get(c.stem, c) for c in cams.frames)
    extra = dict(cams.extra)
    extra["optimize_cameras"] = {
        "refined": bool(run.cameras is not None),
        "heldout_aligned": heldout is not None,
        "mode": info.get("mode"),
        "reason": info.get("reason"),
    }
    return CameraSet(frames, cams.light_intensity, extra, light_known=cams.light_known)
