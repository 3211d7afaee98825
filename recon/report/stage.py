"""The report stage: ``report/index.html`` and ``report/metrics.json`` (DESIGN sections 2, 5, 6).

The page opens offline (also from ``file://``): every image, plot, the glb and model-viewer's
bundle are files inside report/, which is written atomically as a whole. It shows

- the 3D asset (``export/asset.glb``) in model-viewer;
- for each view: the input (linear image, sRGB-encoded), the re-render of the optimized model
  from the same camera, an error map and the RMSE (:mod:`recon.report.views`);
- the texture maps, the loss curves, optimization phase times and per-stage wall times;
- with ``gt/``: accuracy, completeness, chamfer, image RMSE and texture errors
  (:mod:`recon.report.gt`).

``metrics.json``::

    {"capture": str, "preset": str | null,
     "timings": {"stages": {stage: seconds}, "optimize_phases": {phase: seconds}},
     "metrics": {...DESIGN section 5 metrics, only with gt/...},
     "per_view_rmse": {stem: rmse}, "per_view_rmse_mean": float,
     "material_model": ... (when the optimizer reports one),
     "optimize": {"records": n, "iterations": n, "final_loss": float, "wall_seconds": float,
                  "phases_source": "summary.json" | "log.jsonl" | null,
                  "stages": [...the summary's per coarse-to-fine stage entries, when present]},
     "initial_mesh": {"source", "faces", "genus", "mask_iou_mean", "mask_iou_min", "mask_iou_worst",
                      "repairs", "grid_source", "unseen_base"} (from init_mesh/init_mesh.json beside optimize/, when present),
     "light_intensity": float, "settings": {...}}

NaN and Inf never reach the file (they become null).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from recon.brdf import R_MIN
from recon.init_mesh import report_summary
from recon.io.atomic import atomic_dir
from recon.io.cameras import CameraSet, load_cameras
from recon.io.images import linear_to_srgb, write_png
from recon.io.mesh import Mesh
from recon.metrics import MetricsError, Similarity, chamfer, pose_errors, seen_chamfer
from recon.report import gt as gtm
from recon.report import html as page_html
from recon.report import plots
from recon.report.inputs import (
    LOG_FILE,
    SUMMARY_FILE,
    ReportError,
    loss_curves,
    material_model,
    optimize_phases,
    read_benchmarks,
    read_log,
    read_model,
    read_summary,
    summary_r_min,
)
from recon.report.views import (
    ERROR_COLORMAP,
    compare,
    compare_view,
    load_view,
    render_view,
    report_camera,
    write_view_images,
)
from recon.report.viewer import find_bundle, install_viewer, viewer_head, viewer_html
from recon.report.views import resize_area

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ReportSettings:
    """Settings of the report stage (the ``report:`` section of a preset / capture.yaml).

    Attributes
    ----------
    max_size : longest side (pixels) of the re-renders and error maps.
    spp : samples per pixel of the re-renders.
    seed : sampler seed: input view k is re-rendered with seed + k, ground-truth view k with
        seed + 1000 + k; the metrics' surface samples use seed.
    max_views : views to compare, evenly spread over cameras.json (0 = all).
    error_vmax : sRGB error at the top of the error maps' colour scale.
    gt_views : ground-truth views rendered for the image RMSE (0 = all).
    chamfer_samples : surface samples per mesh for accuracy/completeness (DESIGN 5: 100,000).
    texture_samples : surface samples for the texture-map errors.
    texture_max_distance : texture errors use ground-truth samples whose closest point on the
        reconstruction is at most this far (unit-bbox units).
    texture_display_size : longest side of the texture map images in the report.
    variant : Mitsuba variant of the re-renders ("" = the current one, else llvm_ad_rgb).
    viewer_js : path of model-viewer's UMD bundle ("" = tools/report-viewer's npm copy).
    """

    max_size: int = 384
    spp: int = 32
    seed: int = 0
    max_views: int = 0
    error_vmax: float = 0.2
    gt_views: int = 8
    chamfer_samples: int = 100_000
    texture_samples: int = 100_000
    texture_max_distance: float = 0.02
    texture_display_size: int = 1024
    variant: str = ""
    viewer_js: str = ""

    def __post_init__(self):
        for name in ("max_size", "spp", "chamfer_samples", "texture_samples", "texture_display_size"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("max_views", "gt_views", "seed"):
            if int(getattr(self, name)) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not (math.isfinite(self.error_vmax) and self.error_vmax > 0):
            raise ValueError(f"error_vmax must be a positive number, got {self.error_vmax}")
        if not (math.isfinite(self.texture_max_distance) and self.texture_max_distance > 0):
            raise ValueError(f"texture_max_distance must be positive, got {self.texture_max_distance}")


def _finite(x):
    """``x`` with NaN/Inf replaced by None, numpy scalars by Python numbers (recursively)."""
    if isinstance(x, dict):
        return {str(k): _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    if isinstance(x, np.ndarray):
        return _finite(x.tolist())
    if isinstance(x, (np.floating, float)):
        return float(x) if math.isfinite(float(x)) else None
    if isinstance(x, np.integer):
        return int(x)
    return x


def _spread(items: list, n: int) -> list:
    """At most ``n`` items evenly spread over ``items`` (all when n is 0)."""
    if not n or len(items) <= n:
        return list(items)
    idx = np.unique(np.round(np.linspace(0, len(items) - 1, n)).astype(int))
    return [items[i] for i in idx]


def _positive(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and x > 0


def _downsample(texture: np.ndarray, size: int) -> np.ndarray:

    h, w = texture.shape[:2]
    f = min(1.0, size / max(h, w))
    if f == 1.0:
        return texture
    return resize_area(texture, max(1, round(w * f)), max(1, round(h * f)))


def make_report(
    capture: str,
    optimize_dir: str | os.PathLike,
    glb: str | os.PathLike,
    cameras: str | os.PathLike,
    image_dirs: Sequence[str | os.PathLike],
    mask_dirs: Sequence[str | os.PathLike],
    out_dir: str | os.PathLike,
    settings: ReportSettings = ReportSettings(),
    gt_dir: str | os.PathLike | None = None,
    benchmarks_dir: str | os.PathLike | None = None,
    preset: str | None = None,
) -> dict:
    """Write ``out_dir/index.html``, ``out_dir/metrics.json`` and the files they show.

    Parameters
    ----------
    capture : the capture's name.
    optimize_dir : the optimize stage's folder: ``mesh.obj``, ``diffuse.exr``, ``specular.exr``,
        ``roughness.exr``, ``log.jsonl`` (required), ``summary.json`` (optional).
    glb : the export stage's ``asset.glb``.
    cameras : ``optimize/cameras.json`` (the cameras the model was fitted with: SfM's refined
        by the optimizer where it kept the refinement), or ``poses/cameras.json``.
    image_dirs : folders searched in order for each view's linear ``<stem>.exr`` (e.g.
        ``poses/undistorted`` then ``linear``).
    mask_dirs : folders searched in order for each view's ``<stem>.png`` mask.
    out_dir : ``results/<capture>/report``; replaced atomically.
    settings : :class:`ReportSettings`.
    gt_dir : ``<capture>/gt`` of a synthetic capture, or None.
    benchmarks_dir : folder of Snakemake benchmark files ``<stage>.tsv``, or None.
    preset : the preset the capture ran with (else ``preset`` of summary.json, if any).

    Returns
    -------
    The dict written to ``metrics.json``.
    """
    t0 = time.perf_counter()
    optimize_dir = Path(optimize_dir)
    image_dirs = [Path(p) for p in image_dirs]
    mask_dirs = [Path(p) for p in mask_dirs]

    # ---- Read and check every input before any work ----
    model = read_model(optimize_dir)
    records = read_log(optimize_dir / LOG_FILE)
    summary = read_summary(optimize_dir / SUMMARY_FILE)
    try:
        cams = load_cameras(cameras)
    except ValueError as e:
        raise ReportError(f"{e} (written by the poses stage: run it first)") from e
    if not Path(glb).is_file():
        raise ReportError(f"{glb}: not found; the report needs the export stage's asset.glb (run it first)")
    viewer_skipped = None
    try:
        find_bundle(settings.viewer_js or None)
    except ReportError as e:  # the 3D view is optional: the report goes on without it
        viewer_skipped = str(e)
        log.warning("3D view skipped: %s", viewer_skipped)
    # The views the optimizer held out (never fitted: a fair test of the asset) are always shown.
    holdout = summary.get("holdout") if isinstance(summary.get("holdout"), dict) else {}
    held = {str(s) for s in holdout.get("held_out") or []} & {c.stem for c in cams.frames}
    spread = {c.stem for c in _spread(list(cams.frames), settings.max_views)}
    chosen = [c for c in cams.frames if c.stem in spread or c.stem in held]
    views = {c.stem: load_view(c.stem, image_dirs, mask_dirs) for c in chosen}
    gt = None
    if gt_dir is not None and Path(gt_dir).is_dir():
        gt = gtm.read_ground_truth(gt_dir)

    preset = preset or (summary.get("preset") if isinstance(summary.get("preset"), str) else None)
    light = float(summary["light_intensity"]) if _positive(summary.get("light_intensity")) else cams.light_intensity
    r_min = summary_r_min(summary) or R_MIN
    variant = settings.variant or None
    textures = model.textures()
    phases, phase_source = optimize_phases(records, summary)
    stages = read_benchmarks(benchmarks_dir)
    material = material_model(summary, records)
    curves = loss_curves(records)

    metrics: dict = {
        "capture": capture,
        "preset": preset,
        "timings": {"stages": stages, "optimize_phases": phases},
        "metrics": {},
        "per_view_rmse": {},
        "per_view_rmse_mean": None,
    }
    if material is not None:
        metrics["material_model"] = material
    selection = summary.get("material_selection") if isinstance(summary.get("material_selection"), dict) else None
    if selection is not None:
        metrics["material_selection"] = {k: selection.get(k) for k in (
            "chosen", "criterion", "metric", "heldout_views", "train_views", "candidates", "seconds")}
    cameras_info = camera_refinement(summary)
    if cameras_info is not None:
        metrics["camera_refinement"] = cameras_info
    imaging = summary.get("imaging_selection") if isinstance(summary.get("imaging_selection"), dict) else None
    if imaging is not None:  # the camera's imaging terms kept, with each step's gain and SE
        metrics["imaging_model"] = imaging.get("chosen")
        metrics["imaging_selection"] = {k: imaging.get(k) for k in (
            "chosen", "criterion", "metric", "candidates_tried", "flash_offset_given", "values", "candidates",
            "tone_curve", "seconds")}
    loop = summary.get("imaging_loop") if isinstance(summary.get("imaging_loop"), dict) else None
    loop_ev = loop.get("evidence") if loop is not None and isinstance(loop.get("evidence"), dict) else None
    if loop_ev is not None:  # the imaging terms the shape was optimized under (imaging.loop: select)
        metrics["imaging_loop"] = {
            "chosen": loop.get("chosen"), "after_stage": loop_ev.get("after_stage"),
            "values_after_loop": loop.get("values_after_loop"),
            "selection": {k: loop_ev.get(k) for k in ("criterion", "metric", "candidates_tried", "flash_offset_given",
                                                      "values", "candidates", "tone_curve", "seconds")}}
    opt_stages = summary.get("stages")
    opt_stages = [st for st in opt_stages if isinstance(st, dict)] if isinstance(opt_stages, list) else []
    metrics["optimize"] = {
        "records": len(records),
        "iterations": summary["iterations"] if _positive(summary.get("iterations")) else len(records),
        "final_loss": curves.series["loss"][-1] if "loss" in curves.series and len(curves) else None,
        "wall_seconds": summary["wall_seconds"] if _positive(summary.get("wall_seconds")) else None,
        "phases_source": phase_source or None,
    }
    if opt_stages:
        metrics["optimize"]["stages"] = opt_stages
    metrics["asset"] = asset_frame(glb)
    metrics["light_intensity"] = light
    metrics["settings"] = dataclasses.asdict(settings)

    page = page_html.Page(capture=capture, preset=preset, material_model=material, material_selection=selection,
                          camera_refinement=cameras_info, imaging_selection=imaging, imaging_loop=loop_ev)
    light_info = summary.get("light") if isinstance(summary.get("light"), dict) else None
    if light_info is not None:  # the flash's I_e: given (absolute albedo) or estimated (relative)
        metrics["light"] = light_info
        if light_info.get("source") == "estimated":
            page.notes.append(
                f"Albedo is relative: the flash's intensity was not given, and I_e = {light:.4g} was estimated from "
                f"the photos ({light_info.get('convention')}); give light_intensity in capture.yaml for an absolute "
                "albedo.")
        else:
            page.notes.append(f"Albedo is absolute: the flash's intensity I_e = {light:.4g} was given.")
    initial = report_summary(optimize_dir.parent / "init_mesh" / "init_mesh.json")
    if initial is not None:  # the initial mesh's genus and how well it matched the masks
        metrics["initial_mesh"] = initial
        if initial["mask_iou_mean"] is not None:
            worst = ", ".join(f"{k} {v:.2f}" for k, v in initial["mask_iou_worst"])
            page.notes.append(
                f"Initial mesh (visual hull by vote): genus {initial['genus']}, silhouette IoU with the masks mean "
                f"{initial['mask_iou_mean']:.3f}, lowest {worst} (a view far below the others has a wrong mask)."
                + (f" Repaired: {'; '.join(initial['repairs'])}." if initial["repairs"] else ""))
        if str(initial.get("grid_source") or "").startswith("closed at the SfM points"):
            page.notes.append(
                f"The views cut the object at the frame's edge, so no mask bounds it there: the initial mesh was "
                f"{initial['grid_source']} (docs/init_mesh.md). That side of the asset is a guess; photos with the "
                "whole object in the frame would show it.")
        if initial.get("unseen_base"):
            page.notes.append(
                f"No photo saw the object from below: the initial mesh's base was closed flat under the lowest part "
                f"the views saw ({initial['unseen_base']:.0f} voxels of the visual hull cut away beneath it; "
                "docs/init_mesh.md). The underside is a guess; a textured cloth or the printed mat under the object "
                "gives the table's plane.")
    if metrics["asset"].get("scale_warning"):
        page.notes.append(f"Asset scale: {metrics['asset']['scale_source']}.")
        log.warning("the asset's scale is unknown: %s", metrics["asset"]["scale_source"])
    out_dir = Path(out_dir)
    with atomic_dir(out_dir) as tmp:
        # ---- 3D view ----
        if viewer_skipped is None:
            names = install_viewer(tmp, glb, settings.viewer_js or None)
            page.viewer_head = viewer_head(names)
            page.viewer_body = viewer_html(names, f"{capture}: optimized asset")
        else:
            metrics["skipped"] = {"3d_view": viewer_skipped}
            page.notes.append(f"3D view skipped: {viewer_skipped}")

        # ---- Views ----
        (tmp / "views").mkdir()
        index = {c.stem: k for k, c in enumerate(cams.frames)}  # a view's seed: its place among all views
        for cam in chosen:
            res = compare_view(views[cam.stem], cam, model.mesh, textures, light, settings.max_size,
                               settings.spp, settings.seed + index[cam.stem], variant, r_min)
            files = write_view_images(res, tmp / "views", settings.error_vmax)
            metrics["per_view_rmse"][cam.stem] = res.rmse
            page.views.append(page_html.ViewEntry(cam.stem, res.rmse, {r: f"views/{f}" for r, f in files.items()},
                                                  note="held out: never fitted" if cam.stem in held else ""))
            log.info("view %s: RMSE %.4f (%dx%d, %d spp)", cam.stem, res.rmse, res.camera.width,
                     res.camera.height, settings.spp)
        rmses = list(metrics["per_view_rmse"].values())
        metrics["per_view_rmse_mean"] = float(np.mean(rmses)) if rmses else None
        if held:  # the held-out photos re-rendered against the fitted ones: how far the asset generalizes
            per = metrics["per_view_rmse"]
            metrics["heldout_views"] = sorted(held)
            metrics["per_view_rmse_heldout_mean"] = float(np.mean([per[s] for s in held]))
            fitted = [v for s, v in per.items() if s not in held]
            metrics["per_view_rmse_fitted_mean"] = float(np.mean(fitted)) if fitted else None
        page.views_note = (
            f"{len(chosen)} of {len(cams)} views at up to {settings.max_size} px, {settings.spp} spp, "
            + (f"{len(held)} of them held out by the optimizer (never fitted), " if held else "")
            + f"light intensity {light:.4g}. RMSE of sRGB values over the union of the input mask and "
            "the re-render's coverage (clipped input pixels left out)."
        )
        page.error_colorbar = plots.colorbar_svg(settings.error_vmax, ERROR_COLORMAP,
                                                 "per-pixel sRGB error (RMS over channels)")

        # ---- Ground truth ----
        if gt is not None:
            metrics["metrics"] = _gt_metrics(model, cams, gt, light, settings, variant, r_min, tmp, page)

        # ---- Maps ----
        (tmp / "maps").mkdir()
        write_png(tmp / "maps/diffuse.png", linear_to_srgb(_downsample(model.diffuse, settings.texture_display_size)))
        page.maps.append(("maps/diffuse.png", f"diffuse albedo a_d (sRGB), {model.diffuse.shape[1]}x{model.diffuse.shape[0]}"))
        plots.map_plot(_downsample(model.specular, settings.texture_display_size), tmp / "maps/specular.png",
                       "specular albedo a_s", cmap="magma", vmax=max(float(model.specular.max()), 1e-3))
        page.maps.append(("maps/specular.png", f"specular albedo a_s (linear), {model.specular.shape[1]}x{model.specular.shape[0]}"))
        plots.map_plot(_downsample(model.roughness, settings.texture_display_size), tmp / "maps/roughness.png",
                       "roughness r", cmap="viridis")
        page.maps.append(("maps/roughness.png", f"perceptual roughness r, {model.roughness.shape[1]}x{model.roughness.shape[0]}"))

        # ---- Plots ----
        (tmp / "plots").mkdir()
        if len(curves) and curves.series:
            plots.loss_plot(curves, tmp / "plots/loss.png")
            page.plots.append(("plots/loss.png", f"loss per iteration ({len(curves)} records of {LOG_FILE})"))
        else:
            page.notes.append(f"{LOG_FILE} has no loss values to plot.")
        if phases:
            plots.bar_plot(phases, tmp / "plots/phases.png", title="optimization phases")
            page.plots.append(("plots/phases.png", f"seconds per optimization phase (from {phase_source})"))
        else:
            page.notes.append(f"No per-phase timings found in {LOG_FILE} or {SUMMARY_FILE}.")
        if stages:
            plots.bar_plot(stages, tmp / "plots/stages.png", title="wall time per stage")
            page.plots.append(("plots/stages.png", "wall seconds per stage (Snakemake benchmarks)"))
        if len(rmses) > 1:
            plots.bar_plot(dict(metrics["per_view_rmse"]), tmp / "plots/view_rmse.png", xlabel="RMSE (sRGB)",
                           title="RMSE per view")
            page.plots.append(("plots/view_rmse.png", "RMSE per view"))
        page.stage_times, page.phase_times, page.phase_source = stages, phases, phase_source
        page.optimize_stages = _stage_rows(opt_stages)

        # ---- Summary cards ----
        if metrics["per_view_rmse_mean"] is not None:
            page.cards.append(("mean view RMSE", f"{metrics['per_view_rmse_mean']:.4f}"))
        if metrics.get("per_view_rmse_heldout_mean") is not None:
            page.cards.append((f"held-out view RMSE ({len(held)} never fitted)",
                               f"{metrics['per_view_rmse_heldout_mean']:.4f}"))
        for key in ("chamfer", "accuracy", "completeness", "image_rmse"):
            if _positive_or_zero(metrics["metrics"].get(key)):
                page.cards.append((f"gt {key}", f"{metrics['metrics'][key]:.4g}"))
        seen = metrics["metrics"].get("seen_fraction")
        if _positive_or_zero(seen) and seen < 0.99:  # part of the truth no camera sees
            for key in ("accuracy_seen", "completeness_seen"):
                if _positive_or_zero(metrics["metrics"].get(key)):
                    page.cards.append((f"gt {key.replace('_seen', '')} over the seen {100 * seen:.0f} %",
                                       f"{metrics['metrics'][key]:.4g}"))
        if metrics["optimize"]["final_loss"] is not None and math.isfinite(metrics["optimize"]["final_loss"]):
            page.cards.append(("final loss", f"{metrics['optimize']['final_loss']:.4g}"))
        if stages:
            page.cards.append(("pipeline wall time", f"{sum(stages.values()):.1f} s"))
        page.cards.append(("faces", str(len(model.mesh.t_pos_idx))))

        metrics = _finite(metrics)
        (tmp / "metrics.json").write_text(json.dumps(metrics, indent=1, allow_nan=False) + "\n")
        (tmp / "index.html").write_text(page_html.render_page(page), encoding="utf-8")
    log.info("report written to %s in %.1f s", out_dir, time.perf_counter() - t0)
    return metrics


def camera_refinement(summary: dict) -> dict | None:
    """metrics.json's ``camera_refinement`` from summary.json's (issue 17): the mode and why,
    whether the refined cameras were used, the held-out decision, the intrinsics before and
    after and the correction per view (degrees, centre shift relative to the object size);
    None when the summary has none."""
    cam = summary.get("camera_refinement")
    if not isinstance(cam, dict):
        return None
    out = {k: cam.get(k) for k in ("requested", "mode", "reason", "source", "refined", "first_stage") if k in cam}
    if isinstance(cam.get("selection"), dict):
        out["selection"] = cam["selection"]
    cor = cam.get("corrections")
    if isinstance(cor, dict):
        views = cor.get("views") if isinstance(cor.get("views"), dict) else {}
        out["corrections"] = {
            "views": {s: {"rotation_deg": v.get("rotation_deg"), "center_shift": v.get("center_shift_object"),
                          "center_shift_scene": v.get("center_shift")} for s, v in views.items() if isinstance(v, dict)},
            "center_shift_unit": "fraction of the object size (the initial mesh's longest bounding-box side); "
                                 "center_shift_scene: of the mean camera distance from the cameras' centroid",
            **{k: cor.get(k) for k in ("mean_rotation_deg", "max_rotation_deg", "mean_center_shift_object",
                                       "max_center_shift_object", "focal_scale", "principal_shift",
                                       "intrinsics_before", "intrinsics_after")},
        }
    if isinstance(cam.get("heldout_alignment"), dict):
        h = cam["heldout_alignment"]
        out["heldout_alignment"] = {k: h.get(k) for k in ("mean_rotation_deg", "max_rotation_deg",
                                                          "mean_center_shift_object", "max_center_shift_object")}
    return out


def asset_frame(glb) -> dict:
    """How the export stage placed and scaled the asset (its ``asset.extras.recon``: placement,
    scale source, metres per unit); ``scale_warning`` when the scale is unknown."""
    import pygltflib

    try:
        extras = pygltflib.GLTF2().load(str(glb)).asset.extras or {}
    except Exception as e:  # noqa: BLE001 - a diagnostic: the report goes on without it
        return {"error": f"{glb}: {e}"}
    rec = extras.get("recon", {}) if isinstance(extras, dict) else {}
    out = {k: rec.get(k) for k in ("placement", "scale_source", "meters_per_unit")}
    out["scale_warning"] = isinstance(out["scale_source"], str) and out["scale_source"].startswith("unknown")
    return out


def _stage_rows(opt_stages: list[dict]) -> tuple[list[str], list[list]]:
    """Table of the optimizer's coarse-to-fine stages: scalar fields and summed seconds."""
    if not opt_stages:
        return [], []
    cols = []
    for st in opt_stages:
        for k, v in st.items():
            if k not in cols and (isinstance(v, (int, float, str)) and not isinstance(v, bool)):
                cols.append(k)
    cols = cols[:8]
    has_sec = any(isinstance(st.get("seconds"), dict) for st in opt_stages)
    rows = []
    for st in opt_stages:
        row = [st.get(k, "") for k in cols]
        if has_sec:
            sec = st.get("seconds") if isinstance(st.get("seconds"), dict) else {}
            row.append(float(sum(v for v in sec.values() if _positive_or_zero(v))))
        rows.append(row)
    return cols + (["seconds"] if has_sec else []), rows


def _positive_or_zero(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and x >= 0


def _gt_metrics(model, cams: CameraSet, gt, light: float, settings: ReportSettings, variant, r_min,
                folder: Path, page) -> dict:
    """DESIGN section 5 metrics against ``gt`` (see :mod:`recon.report.gt`); adds gt views to the page.

    Ground-truth metrics are an optional diagnostic: each group is computed when the files of
    ``gt/`` allow it, and what was skipped is recorded (``skipped``: group -> reason) and shown,
    never raised.
    """
    out: dict = {}
    skipped = dict(gt.skipped)
    if gt.cameras is not None:
        sim, how = gtm.alignment(cams, gt.cameras)
    else:
        sim, how = Similarity.identity(), "identity (no ground-truth cameras)"
    out["alignment"] = {"method": how, "similarity": sim.to_dict()}
    if gt.mesh is not None:
        try:
            out.update(chamfer(model.mesh, gt.mesh, similarity=sim, n_samples=settings.chamfer_samples,
                               seed=settings.seed))
        except MetricsError as e:
            skipped["geometry"] = f"ground-truth geometry metrics: {e}"
        if gt.cameras is not None and "geometry" not in skipped:
            try:  # the same over the surface the true cameras see (a tabletop object's underside: none)
                out.update(seen_chamfer(model.mesh, gt.mesh, gt.cameras, similarity=sim,
                                        n_samples=settings.chamfer_samples, seed=settings.seed))
            except MetricsError as e:
                skipped["geometry_seen"] = f"ground-truth metrics over the seen surface: {e}"
    if gt.cameras is not None:
        try:
            pe = pose_errors(cams, gt.cameras, sim)
            out["pose_errors"] = {k: pe[k] for k in ("mean_rotation_deg", "max_rotation_deg", "mean_center",
                                                     "max_center")}
        except MetricsError as e:
            log.info("no pose errors: %s", e)

    # Images from the true cameras: ground truth against the reconstruction in the gt frame.
    per_view: dict = {}
    if gt.model is not None and gt.cameras is not None:
        rec_mesh = Mesh(sim.apply(model.mesh.v_pos), model.mesh.t_pos_idx, model.mesh.v_tex, model.mesh.t_tex_idx)
        rec_light = light * sim.scale**2
        gt_cams, held_out = gtm.image_views(cams, gt.cameras, settings.gt_views)
        (folder / "gt").mkdir()
        for k, cam in enumerate(gt_cams):
            cam = report_camera(cam, settings.max_size)
            seed = settings.seed + 1000 + k
            img_gt, cov_gt = render_view(gt.model.mesh, gt.model.textures(), cam, gt.cameras.light_intensity,
                                         settings.spp, seed, variant, r_min)
            img_rec, cov_rec = render_view(rec_mesh, model.textures(), cam, rec_light, settings.spp, seed, variant,
                                           r_min)
            res = compare(cam.stem, cam, img_gt, cov_gt, img_rec, cov_rec)
            per_view[cam.stem] = res.rmse
            files = write_view_images(res, folder / "gt", settings.error_vmax)
            page.gt_views.append(page_html.ViewEntry(cam.stem, res.rmse, {r: f"gt/{f}" for r, f in files.items()},
                                                     labels=("ground truth", "reconstruction", "error")))
        out["image_rmse"] = float(np.mean(list(per_view.values()))) if per_view else None
        out["image_rmse_per_view"] = per_view
        out["image_views"] = "held-out" if held_out else "all true views (none held out)"
    if gt.model is not None and "unit" in out:
        gauge = 1.0
        if gt.cameras is not None and gt.cameras.light_known:
            gauge = light * sim.scale**2 / gt.cameras.light_intensity
        out["texture_rmse"] = gtm.texture_errors(model, gt.model, sim, out["unit"], settings.texture_samples,
                                                 settings.texture_max_distance, seed=settings.seed,
                                                 albedo_gauge=gauge)
    elif gt.model is not None:
        skipped.setdefault("texture_rmse", "needs the geometry metrics' unit bounding box")

    notes = []
    if "unit" in out:
        notes.append(f"Geometry in the ground-truth frame scaled to a unit bounding box ({settings.chamfer_samples} "
                     f"samples per surface); alignment: {how}.")
    if per_view:
        notes.append(f"Image RMSE over {len(per_view)} {out['image_views']} rendered with the collocated light.")
    if "texture_rmse" in out:
        notes.append("Texture RMSE compares map values at closest surface points (linear values in [0, 1]).")
        if out["texture_rmse"]["fraction"] == 0.0:
            notes.append(f"No ground-truth surface sample has reconstructed surface within "
                         f"{settings.texture_max_distance} (unit bbox): texture errors not computed.")
    for what, why in skipped.items():
        notes.append(f"Skipped {what}: {why}.")
        log.warning("ground-truth %s skipped: %s", what, why)
    if skipped:
        out["skipped"] = skipped
    page.gt_note = " ".join(notes)
    page.gt_metrics = out
    return out
