"""The optimize stage: coarse-to-fine analysis by synthesis of shape and SVBRDF (sec. 3.2-3.4).

:func:`optimize_capture` is the stage's table of contents:

1. **inputs** (:func:`_base_run`): the training and held-out views (:mod:`recon.optimize.heldout`),
   the initial mesh, the flash's intensity, the support plane, what a run knows
   (:class:`recon.optimize.run.Run`);
2. **run(s)** (:func:`_runs`, :func:`recon.optimize.run.execute`): the coarse-to-fine loop
   (:mod:`recon.optimize.run`; one iteration: :mod:`recon.optimize.iteration`; its schedule:
   :mod:`recon.optimize.schedule`; its loss: :mod:`recon.optimize.objective`), once, or twice to
   decide on refined cameras (the control and the refined run, from the same start and seeds);
3. **selections**, each deciding with the paired held-out test of
   :func:`recon.optimize.heldout.compare`: the cameras (:mod:`recon.optimize.cameras`), then on
   the kept run's final model the material model (:mod:`recon.optimize.material_select`) and the imaging
   terms (:mod:`recon.optimize.imaging_select`) (:func:`_select_models`);
4. **outputs** (:func:`_write_outputs`): ``mesh.obj``, the maps, ``log.jsonl``, ``summary.json``
   and ``cameras.json``.

Every fit besides the loop (the material and imaging fits, the held-out views' gains and poses)
is :func:`recon.optimize.fitting.fit`.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from recon.io.atomic import atomic_path
from recon.io.cameras import CameraSet, load_cameras, save_cameras
from recon.io.images import write_exr
from recon.io.mesh import Mesh, read_mesh, write_obj
from recon.optimize import checkpoint as ckpt
from recon.optimize import objective
from recon.optimize.cameras import CameraFit, output_cameras, select_refinement
from recon.optimize.foot import foot_zone
from recon.optimize.guard import self_intersecting_faces
from recon.optimize.heldout import split_holdout
from recon.optimize.imaging import ImagingSettings, material_scorer_under, refit_under
from recon.optimize.imaging_select import run_imaging_selection
from recon.optimize.iteration import MAP_NAMES, Stage, map_values
from recon.optimize.loop_imaging import LoopImaging
from recon.optimize.material import model_from_settings
from recon.optimize.material_select import select_material
from recon.optimize.radiometry import ESTIMATE_SIZE, LightScale, LightScaleError, clipped_fraction, estimate_light_scale
from recon.optimize.remesh import topology_report
from recon.optimize.run import OptimizeError, Progress, Run, Timer, execute, save
from recon.optimize.settings import OptimizeSettings
from recon.optimize.views import Views, capture_is_ldr, recorded_exposures, view_exposures
from recon.support import PlaneError, plane_if_found

__all__ = ["CAMERAS_FILE", "OptimizeError", "optimize_capture", "optimize_from_dirs"]

log = logging.getLogger(__name__)

CAMERAS_FILE = "cameras.json"


def optimize_capture(
    images: Sequence[str | os.PathLike],
    masks: Sequence[str | os.PathLike] | None,
    saturation_masks: Sequence[str | os.PathLike | None] | None,
    cameras_json: str | os.PathLike,
    init_mesh_obj: str | os.PathLike,
    out_dir: str | os.PathLike,
    settings: OptimizeSettings | None = None,
    progress: bool = True,
    callback: Callable[[dict], None] | None = None,
    cameras_source: str | None = None,
    plane_json: str | os.PathLike | None = None,
) -> dict:
    """Optimize shape and SVBRDF maps from flash photos; write the optimize stage's outputs.

    Parameters
    ----------
    images : linear RGB ``.exr`` photos (``poses/undistorted/<stem>.exr`` or ``linear/<stem>.exr``),
        paired with cameras by stem.
    masks : one ``masks/<stem>.png`` per image (nonzero = object), or None (all object).
    saturation_masks : one ``linear/<stem>.sat.png`` per image (nonzero = clipped), or None.
    cameras_json : ``poses/cameras.json``.
    init_mesh_obj : ``uv/mesh.obj`` (positions are used; the stage makes its own atlas).
    out_dir : ``results/<capture>/optimize``; gets ``mesh.obj``, ``diffuse.exr``, ``specular.exr``,
        ``roughness.exr``, ``log.jsonl``, ``summary.json``, ``cameras.json`` (the cameras of the
        final model, in the frame of ``cameras_json``) and ``checkpoints/``.
    settings : OptimizeSettings (None = the defaults)
    progress : show a tqdm bar (loss and ETA).
    callback : called after every iteration with its log record (dict).
    cameras_source : where the cameras came from, "sfm" or "given" (None: the ``source`` of
        ``poses.json`` beside ``cameras_json``, else "given"); decides ``cameras.refine``.
    plane_json : the support plane (``plane.json`` beside the masks; absent when none was found):
        no vertex goes below it (:func:`recon.optimize.iteration._keep_above_plane`).

    Returns
    -------
    dict, the summary also written to ``summary.json``.

    A run whose ``checkpoints/last.pt`` matches these inputs and settings resumes from it and
    ends with the same result as an uninterrupted run.
    """
    t_start = time.perf_counter()
    settings = settings if settings is not None else OptimizeSettings()
    out_dir = Path(out_dir)
    cams = load_cameras(cameras_json)
    source = cameras_source if cameras_source is not None else cameras_source_of(cameras_json)

    # ---- inputs: the views (training and held out), the initial mesh, the flash, the table ----
    inputs = _Inputs(images, masks, saturation_masks, cameras_json, init_mesh_obj, plane_json)
    base, init, camera_info, holdout_info = _base_run(inputs, cams, settings, source, out_dir / "checkpoints")

    # ---- run(s): the control and, to decide on the cameras, the run that refines them ----
    runs = _runs(base, camera_info["mode"], camera_info["first_stage"])
    done = [execute(run, init, progress, callback) for run in runs]

    # ---- selections: the cameras, then the material and imaging models of the run kept ----
    cam_timer = Timer()
    chosen, held_cams = select_refinement(runs, done, camera_info, cams, cam_timer)
    run, (st, prog) = runs[chosen], done[chosen]
    timer = Timer()
    for t in [p.timer for _, p in done] + [cam_timer]:
        for k, v in t.total.items():
            timer.add(k, v)
    final = Mesh(st.mesh.v_pos.copy(), st.mesh.t_pos_idx, st.mesh.v_tex, st.mesh.t_tex_idx)
    final_maps, model, selections = _select_models(run, st, final, held_cams, images, timer)

    # ---- outputs ----
    summary = _summary(run, prog, timer, final, final_maps, st.covered, t_start)
    summary.update(material_model=model.to_dict(), material_model_label=model.label(), **selections,
                   holdout=holdout_info, camera_refinement=camera_info,
                   imaging_loop=None if run.imaging is None else {
                       "setting": settings.imaging.loop, "stage": int(settings.imaging.loop_stage),
                       **run.imaging.report()})
    save(run, prog, st, int(run.stages[-1].iterations), done=True)
    _write_outputs(out_dir, final, final_maps, prog.records, summary,
                   output_cameras(cams, run, held_cams, camera_info))
    log.info("optimize: done in %.1f s (geometry processing %.1f%% of the iteration time)", summary["wall_seconds"],
             100 * summary["phase_fraction"]["geometry"])
    return summary


@dataclass(frozen=True)
class _Inputs:
    """The stage's input files (see :func:`optimize_capture`)."""

    images: Sequence[str | os.PathLike]
    masks: Sequence[str | os.PathLike] | None
    saturation_masks: Sequence[str | os.PathLike | None] | None
    cameras_json: str | os.PathLike
    init_mesh_obj: str | os.PathLike
    plane_json: str | os.PathLike | None


def _base_run(inputs: _Inputs, cams: CameraSet, settings: OptimizeSettings, source: str | None,
              ckpt_dir: Path) -> tuple[Run, Mesh, dict, dict]:
    """What every run knows (the views, held-out views, flash, plane, checkpoint fingerprint), the
    initial mesh, the camera refinement's mode (the summary's ``camera_refinement``, to be
    completed) and the held-out views' record."""
    mode, why = settings.camera_mode(source)
    stages = settings.effective_stages()
    init = read_mesh(inputs.init_mesh_obj)
    lo, hi = init.bbox()
    bbox_scale = float(np.max(hi - lo))
    if not bbox_scale > 0:
        raise OptimizeError(f"{inputs.init_mesh_obj}: the initial mesh has an empty bounding box")
    weights = objective.weights(settings)
    try:
        plane = plane_if_found(inputs.plane_json)
    except PlaneError as e:
        raise OptimizeError(f"{e}; rerun the masks stage") from e
    if plane is not None:
        log.info("support plane %s: the surface is kept above it", inputs.plane_json)
        if np.any(plane.height(init.v_pos) < -0.01 * bbox_scale):
            log.warning("%s: the initial mesh reaches %.3g below the support plane (%s); those vertices are "
                        "moved onto it", inputs.init_mesh_obj, -plane.height(init.v_pos).min(), inputs.plane_json)
    masks_json = Path(inputs.plane_json).parent / "masks.json" if plane is not None else None
    foot = foot_zone(masks_json, plane, init, settings.loss.uncertain_foot, settings.loss.uncertain_foot_weight)
    if foot is not None:
        log.info("tabletop masks (%s): the foot's pixels near a silhouette under an overhang, up to %.3g above the "
                 "table, are in doubt in %d views (%s)", masks_json, foot.height, len(foot.stems),
                 "those showing the table made background" if settings.loss.uncertain_foot_mode == "background"
                 else "left out of the image term")
    views = Views(inputs.images, inputs.masks, inputs.saturation_masks, cams,
                  max(settings.stage_image_size(s) for s in stages), keep_photos=foot is not None)
    views, heldout, holdout_info = split_holdout(views, settings, force=mode == "select")
    if mode != "off" and len(views) < 3:
        mode, why = "off", f"only {len(views)} training views (camera refinement needs at least 3)"
    if mode == "select" and heldout is None:
        mode, why = "off", "no held-out views to decide on (cameras.refine: select needs at least 6 views)"
    if mode != "off" or settings.cameras.refine != "off":
        log.info("camera refinement: %s (%s)", mode, why)
    files = [inputs.cameras_json, inputs.init_mesh_obj, *inputs.images, *(inputs.masks or []),
             *(inputs.saturation_masks or []), inputs.plane_json if plane is not None else None,
             masks_json if foot is not None else None]
    fp = ckpt.fingerprint(settings.to_dict(), [str(f) if f is not None else None for f in files])
    tone_scale = views.median_foreground
    light_scale = _light_scale(settings, cams, views, init, inputs.cameras_json)
    light = light_scale.intensity

    base = Run(settings, tuple(stages), views, heldout, bbox_scale, weights, tone_scale, light, ckpt_dir, fp,
               plane=plane, light_scale=light_scale, area_init=float(init.area()),
               exposure=recorded_exposures(inputs.images), foot=foot)
    if settings.imaging.loop != "off":
        if heldout is None:
            log.warning("imaging.loop: %s needs held-out views (at least 6 views); the loop renders the ideal "
                        "formation", settings.imaging.loop)
        else:
            base = dataclasses.replace(base, ldr=capture_is_ldr(inputs.images))
    # linear photos (RAW, EXR) carry their exposure: the cameras need not wait for the imaging terms
    camera_start = settings.camera_start(len(stages), settings.imaging.loop != "off" and heldout is not None
                                         and base.ldr is True)
    if mode != "off":
        log.info("camera refinement from stage %d (cameras.first_stage: %s)", camera_start, settings.cameras.first_stage)
    camera_info = {"requested": settings.cameras.refine, "mode": mode, "reason": why, "source": source,
                   "refined": False, "first_stage": camera_start if mode != "off" else None}
    return base, init, camera_info, holdout_info


def _runs(base: Run, mode: str, camera_start: int | None) -> list[Run]:
    """The runs to make: the control (cameras.refine "off" or "select") and the run refining the
    cameras ("on" or "select"), each with its own imaging terms for the loop (``imaging.loop``)."""
    settings, views, heldout = base.settings, base.views, base.heldout
    runs = []
    if mode in ("off", "select"):
        runs.append(base)
    if mode in ("on", "select"):
        # its own checkpoints beside the control's, so either run resumes alone
        runs.append(dataclasses.replace(base, ckpt_dir=base.ckpt_dir / "cameras" if mode == "select" else base.ckpt_dir,
                                        fingerprint=base.fingerprint + "+cameras",
                                        cameras=CameraFit(views, settings, camera_start)))
    if settings.imaging.loop != "off" and heldout is not None:
        # one per run; when the cameras are held until the selection has run, the runs are the
        # same up to there and the refined run takes the control's choice: the held-out test then
        # compares cameras, not two draws of the imaging selection
        prior = ImagingSettings().exposure_prior
        e = view_exposures(views.cameras, base.exposure)  # the training views' (None: all 1)
        e = None if e is None else e.numpy()
        control = LoopImaging(settings.imaging.loop_lr, prior, exposure=e)
        shared = control if mode == "select" and camera_start > int(settings.imaging.loop_stage) else None
        runs = [dataclasses.replace(r, imaging=control if r.cameras is None else
                                    LoopImaging(settings.imaging.loop_lr, prior, shared_from=shared, exposure=e))
                for r in runs]
    return runs


def _select_models(run: Run, st: Stage, final: Mesh, held_cams: dict | None, images,
                   timer: Timer) -> tuple[dict, object, dict]:
    """The material model and the imaging terms of the kept run's final model (``final``, the
    maps of ``st``), each selected on the held-out views (with the final model's cameras):
    returns the final maps, the material model and the summary's selection entries.

    The maps the asset carries come from the last of these steps that runs:

    1. ``select_material``: the material selection (:mod:`recon.optimize.material_select`),
       its candidates fitted under the loop's imaging terms when the loop chose any and
       ``select_material_under_imaging`` is on, else under the ideal formation;
    2. when the loop chose imaging terms and neither step 1 fitted under them nor step 3 will
       run: the maps refitted under them (:func:`recon.optimize.imaging.refit_under`);
    3. ``select_imaging``: the imaging selection (:mod:`recon.optimize.imaging_select`) on the
       maps and model so far.
    """
    settings, views, heldout = run.settings, run.views, run.heldout
    light, tone_scale = run.light, run.tone_scale
    with torch.no_grad():
        final_maps = {k: v.numpy().astype(np.float32) for k, v in map_values(settings, st.maps).items()}
    model = model_from_settings(settings.material.specular_channels)
    selection = None
    train_vs = held_vs = None  # the views at the selections' size with the final model's cameras
    loop_imaging = run.imaging is not None and run.imaging.active
    if heldout is not None and (settings.select.select_material or settings.imaging.select_imaging or loop_imaging):
        size = int(settings.select.select_image_size)
        train_vs, held_vs = views.at(size), heldout.at(size)
        if run.cameras is not None:
            train_vs = dataclasses.replace(
                train_vs, cameras=tuple(run.cameras.ref.cameras(range(len(train_vs)), train_vs.cameras)))
        if held_cams is not None:
            held_vs = held_cams["viewset"]
    scorer = None  # the material selection's, when it fits the candidates under the loop's imaging terms
    if settings.select.select_material and heldout is not None:
        t0 = time.perf_counter()
        s_mat = settings.selection_settings()
        # under the loop's imaging terms the candidates' maps are fitted under them: the chosen
        # fit's maps are then those the asset carries (no refit after)
        if loop_imaging and settings.select.select_material_under_imaging:
            scorer = material_scorer_under(run.imaging.params, final, st.covered, train_vs, held_vs, light,
                                           tone_scale, s_mat, spp=int(settings.select.select_spp),
                                           seed=int(settings.seed) + 29, exposure=run.exposure)
        log.info("material model selection on %d held-out views%s", len(heldout),
                 "" if scorer is None else " under the loop's imaging terms")
        fit, selection = select_material(
            final, final_maps, st.covered, train_vs, held_vs, light, tone_scale,
            s_mat, spp=int(settings.select.select_spp), seed=int(settings.seed),
            progress=lambda m, f: log.info("material: fitted %s: held-out error %.5f", m.label(), f.heldout),
            scorer=scorer)
        final_maps, model = fit.maps, fit.model
        selection["under_imaging"] = scorer is not None
        timer.add("material", time.perf_counter() - t0)
        log.info("material model: %s", model.label())
    if loop_imaging and not settings.imaging.select_imaging and scorer is None:
        t0 = time.perf_counter()
        refit = refit_under(run.imaging.params, model, final, final_maps, st.covered, train_vs, light, tone_scale,
                            settings.imaging_selection_settings(), spp=int(settings.select.select_spp), seed=int(settings.seed) + 29,
                            exposure=run.exposure)
        final_maps = refit.material.maps
        timer.add("material", time.perf_counter() - t0)
        log.info("maps refitted under the loop's imaging terms (%s): %.1f s", ", ".join(run.imaging.params.model.terms)
                 or "flash offset given", time.perf_counter() - t0)
    imaging = None
    if settings.imaging.select_imaging and heldout is not None:
        t0 = time.perf_counter()
        final_maps, model, imaging = run_imaging_selection(
            settings, final, final_maps, model, st.covered, views, heldout, light, tone_scale, images,
            train_set=train_vs, heldout_set=held_vs)
        log.info("imaging model: %s (%.1f s)", ", ".join(imaging["chosen"]) or "ideal", time.perf_counter() - t0)
    return final_maps, model, {"material_selection": selection, "imaging_selection": imaging,
                               "imaging_model": imaging["chosen"] if imaging else []}


def _write_outputs(out_dir: Path, final: Mesh, final_maps: dict, records: list, summary: dict,
                   cameras: CameraSet) -> None:
    """The stage's files: the maps, ``log.jsonl``, ``summary.json``, ``cameras.json``, ``mesh.obj``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    for k in MAP_NAMES:
        write_exr(out_dir / f"{k}.exr", final_maps[k])
    with atomic_path(out_dir / "log.jsonl") as tmp:
        tmp.write_text("".join(json.dumps(r) + "\n" for r in records))
    with atomic_path(out_dir / "summary.json") as tmp:
        tmp.write_text(json.dumps(summary, indent=1))
    save_cameras(out_dir / CAMERAS_FILE, cameras)
    write_obj(out_dir / "mesh.obj", final)


def cameras_source_of(cameras_json: str | os.PathLike) -> str | None:
    """The ``source`` ("sfm" or "given") the poses stage recorded in ``poses.json`` beside
    ``cameras_json``; None when there is no such record."""
    p = Path(cameras_json).with_name("poses.json")
    if not p.is_file():
        return None
    try:
        src = json.loads(p.read_text()).get("source")
    except (json.JSONDecodeError, AttributeError, OSError) as e:
        raise OptimizeError(f"{p}: unreadable ({e}); rerun the poses stage") from e
    return src if isinstance(src, str) else None


def _light_scale(settings: OptimizeSettings, cams: CameraSet, views: Views, init: Mesh,
                 cameras_json) -> LightScale:
    """The flash's I_e: the one ``cameras.json`` states, else estimated from the training photos
    on the initial mesh (``light.scale``; :mod:`recon.optimize.radiometry`)."""
    if settings.light.scale == "given" and not cams.light_known:
        raise OptimizeError(f"{cameras_json}: states no light.intensity, and light.scale is 'given'; give "
                            "light_intensity in capture.yaml, or set optimize: {light: {scale: auto}} to estimate it")
    if cams.light_known and settings.light.scale != "estimate":
        log.info("flash intensity I_e = %.6g, given in %s: the albedo is absolute", cams.light_intensity, cameras_json)
        return LightScale(float(cams.light_intensity), "given")
    vs = views.at(ESTIMATE_SIZE)
    try:
        est = estimate_light_scale(init, vs.images.numpy(), vs.masks, vs.weights[..., 0].numpy() == 0, vs.cameras,
                                   seed=int(settings.seed))
    except LightScaleError as e:
        raise OptimizeError(f"{cameras_json}: {e}") from e
    log.info("flash intensity I_e = %.6g estimated from %d pixels of %d photos (the albedo is relative: %s); "
             "initial diffuse albedo %s", est.intensity, est.pixels, len(views), est.to_dict()["convention"],
             " ".join(f"{x:.3f}" for x in est.init_diffuse))
    if cams.light_known:
        log.info("the given I_e is %.6g: estimate / given = %.4f", cams.light_intensity,
                 est.intensity / cams.light_intensity)
    return est


def optimize_from_dirs(
    views_dir: str | os.PathLike,
    masks_dir: str | os.PathLike | None,
    cameras_json: str | os.PathLike,
    init_mesh_obj: str | os.PathLike,
    out_dir: str | os.PathLike,
    settings: OptimizeSettings | None = None,
    progress: bool = True,
    plane_json: str | os.PathLike | None = None,
) -> dict:
    """:func:`optimize_capture` over every view of ``cameras_json`` found in the stage folders.

    ``views_dir`` holds ``<stem>.exr`` and, where pixels clipped, ``<stem>.sat.png`` (the
    linearize stage's folder, or ``poses/undistorted``); ``masks_dir`` holds ``<stem>.png``
    (None: no masks). Views without a camera (e.g. not registered by SfM) are not used.
    """
    views_dir = Path(views_dir)
    cams = load_cameras(cameras_json)
    images, masks, sats = [], [], []
    for c in cams.frames:
        img = views_dir / f"{c.stem}.exr"
        if not img.is_file():
            raise OptimizeError(f"{img}: the linear view of camera '{c.image}' is missing; rerun the "
                                "linearize (or poses) stage")
        images.append(img)
        if masks_dir is not None:
            m = Path(masks_dir) / f"{c.stem}.png"
            if not m.is_file():
                raise OptimizeError(f"{m}: no mask for view '{c.stem}'; rerun the masks stage")
            masks.append(m)
        sat = views_dir / f"{c.stem}.sat.png"
        sats.append(sat if sat.is_file() else None)
    return optimize_capture(images, masks if masks_dir is not None else None, sats, cameras_json, init_mesh_obj,
                            out_dir, settings, progress, plane_json=plane_json)


def _mean_tail(recs: list[dict], key: str) -> float | None:
    tail = recs[-max(1, min(len(recs), 10)):]
    vals = [r[key] for r in tail if key in r]
    return float(np.mean(vals)) if vals else None


def _summary(run: Run, prog: Progress, timer: Timer, final: Mesh, final_maps: dict, covered: np.ndarray,
             t_start: float) -> dict:
    """The summary of the loop (per stage and overall: iterations, timings, final losses, guard
    back-offs), the final mesh and the flash; the selections are added by the caller."""
    settings, records, light_scale = run.settings, prog.records, run.light_scale
    topo = topology_report(final.v_pos, final.t_pos_idx)
    n_si = int(self_intersecting_faces(final.v_pos, final.t_pos_idx).sum())
    wall = time.perf_counter() - t_start
    loop_phases = ("render", "loss", "backward", "step", "geometry")
    stages = []
    for info in prog.stage_infos:
        recs = [r for r in records if r["stage"] == info["stage"]]
        keys = sorted({k for r in recs for k in r if k.startswith("loss")})
        stages.append(dict(
            {k: v for k, v in info.items() if k != "heldout_tiles"},
            iterations=len(recs),
            seconds={p: float(sum(r[f"t_{p}"] for r in recs)) for p in loop_phases},
            final_losses={k: _mean_tail(recs, k) for k in keys},
            guard_backoffs=int(sum(r["guard_halvings"] > 0 or r["guard_frozen"] > 0 for r in recs)),
            guard_reverted=int(sum(r["guard_reverted"] for r in recs)),
        ))
    phase = dict(timer.total)
    in_loop = sum(phase[p] for p in loop_phases)
    keys = sorted({k for k in (records[-1] if records else {}) if k.startswith("loss")})
    summary = {
        "wall_seconds": wall,
        "phase_seconds": phase,
        "phase_fraction": {p: (phase[p] / in_loop if in_loop > 0 else 0.0) for p in loop_phases},
        # CPU time of the surface checks in the worker thread; overlapped with the next
        # iteration's rendering, so only the waiting for them is in phase_seconds["geometry"]
        "guard_check_seconds": float(sum(r.get("t_guard_check", 0.0) for r in records)),
        "stages": stages,
        "iterations": len(records),
        "final_losses": {k: _mean_tail(records, k) for k in keys},
        "mesh": {
            "vertices": int(len(final.v_pos)),
            "faces": int(len(final.t_pos_idx)),
            "manifold": bool(topo["is_mesh_two_manifold"]),
            "boundary_edges": int(topo["boundary_edges"]),
            "self_intersecting_faces": n_si,
        },
        "bbox_scale": run.bbox_scale,
        "settings": settings.to_dict(),
        "light_intensity": float(run.light),
        "light": {**light_scale.to_dict(), "diffuse_clipped_fraction": clipped_fraction(final_maps["diffuse"], covered)},
    }
    if light_scale.source == "estimated" and summary["light"]["diffuse_clipped_fraction"] > 0.02:
        log.warning("%.1f %% of the diffuse map is at albedo 1: the estimated flash intensity is low for these "
                    "photos", 100 * summary["light"]["diffuse_clipped_fraction"])
    return summary
