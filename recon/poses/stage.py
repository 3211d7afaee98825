"""The poses stage's entry point: pass given cameras through, or run SfM (see :mod:`recon.poses`)."""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from recon import sections
from recon.io.atomic import atomic_dir, atomic_path
from recon.io.cameras import Camera, CameraError, CameraSet, load_cameras, save_cameras
from recon.io.images import read_exr
from recon.poses.features import extract_and_match, sift_upsample_factor, write_sift_images
from recon.poses.frame import object_frame, points_in_masks, rotate_cameras
from recon.poses.inputs import image_names, linear_stems, prior_focal, prior_sigma, read_masks, view_orientations
from recon.poses.mapping import map_views, refine, rescale_model, silhouette_consistency, unregistered_reasons
from recon.poses.settings import PoseError, PoseSettings
from recon.poses.undistort import (distort_maps, keypoints_to_pinhole, pinhole_camera, remap, undistort_maps,
                                   undistort_view)
from recon.segment import read_points_ply, run_tabletop_masks, triangulate_points
from recon.metrics import Similarity
from recon.support import (FOOT_RADIUS, TABLE_TOLERANCE, SupportPlane, camera_spread, fit_support_plane,
                           load_plane, save_plane, table_points)

log = logging.getLogger(__name__)

DEFAULT_LIGHT_INTENSITY = 1.0
"""The placeholder I_e of a CameraSet whose light intensity is not known: after SfM the scale is
arbitrary, so cameras.json leaves ``light.intensity`` out and the optimize stage estimates the
flash's scale from the photos (:mod:`recon.optimize.radiometry`)."""


def run_poses(
    linear_dir: str | os.PathLike,
    out_dir: str | os.PathLike,
    settings: PoseSettings | None = None,
    masks_dir: str | os.PathLike | None = None,
    linear_json: str | os.PathLike | None = None,
    given_cameras: str | os.PathLike | None = None,
) -> dict:
    """Recover (or pass through) the cameras of a capture; write the stage folder ``out_dir``.

    Parameters
    ----------
    linear_dir : the linearize stage's folder (``<stem>.exr``, ``<stem>.sat.png``).
    out_dir : ``results/<capture>/poses``; replaced atomically (nothing partial on error).
    settings : the SfM settings and ``light_intensity``, which is written into ``cameras.json``
        in both cases (given cameras and SfM); default ``PoseSettings()``.
    masks_dir : the masks stage's folder (``<stem>.png``), optional but needed for a good frame.
    linear_json : the linearize stage's ``linear.json`` (focal length prior, image names).
    given_cameras : the capture's ``cameras.json``; when given it is validated and copied.

    Returns
    -------
    The diagnostics written to ``poses.json``.

    Raises
    ------
    PoseError
        Fewer than ``min_registered`` views registered, or the largest model holds less than
        ``min_registered_fraction`` of the views (the message lists every unregistered view
        with the reason and what to try); given cameras that do not fit the images, or whose
        ``light.intensity`` differs from ``settings.light_intensity``.
    """
    settings = settings or PoseSettings()
    linear_dir = Path(linear_dir)
    out_dir = Path(out_dir)
    t_start = time.perf_counter()
    with atomic_dir(out_dir) as tmp:
        if given_cameras is not None:
            diag = _passthrough(Path(given_cameras), linear_dir, Path(masks_dir) if masks_dir else None, tmp,
                                settings.light_intensity)
        else:
            diag = _sfm(linear_dir, tmp, settings, Path(masks_dir) if masks_dir else None,
                        Path(linear_json) if linear_json else None)
        diag["seconds"] = time.perf_counter() - t_start
        (tmp / "poses.json").write_text(json.dumps(diag, indent=1))
    return diag


# ---------------------------------------------------------------------------------------------
# Given cameras
# ---------------------------------------------------------------------------------------------
def _link_or_copy(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def _passthrough(given: Path, linear_dir: Path, masks_dir: Path | None, tmp: Path,
                 light_intensity: float | None) -> dict:
    try:
        cams = load_cameras(given)
    except CameraError as e:
        raise PoseError(f"{e} (fix the capture's cameras.json, or delete it to run SfM)") from e
    stems = set(linear_stems(linear_dir))
    reduced = {}
    for c in cams:
        exr = linear_dir / f"{c.stem}.exr"
        if c.stem not in stems:
            raise PoseError(f"{given}: camera for '{c.image}' but no linear image {exr}; the names must match images/")
        h, w = read_exr(exr).shape[:2]
        if (w, h) != (c.width, c.height):
            s = max(w, h) / max(c.width, c.height)
            if not (s < 1 and (max(1, round(c.width * s)), max(1, round(c.height * s))) == (w, h)):
                raise PoseError(f"{given}: '{c.image}' is {c.width}x{c.height} in cameras.json but the image is {w}x{h}")
            reduced[c.image] = (w, h)  # linearize reduced the photo (linearize.max_size)
        _link_or_copy(exr, tmp / "undistorted" / f"{c.stem}.exr")
        sat = linear_dir / f"{c.stem}.sat.png"
        if sat.is_file():
            _link_or_copy(sat, tmp / "undistorted" / f"{c.stem}.sat.png")
        if masks_dir is not None and (Path(masks_dir) / f"{c.stem}.png").is_file():
            _link_or_copy(Path(masks_dir) / f"{c.stem}.png", tmp / "undistorted" / "masks" / f"{c.stem}.png")
    light = _copy_given_cameras(given, tmp / "cameras.json", cams.light_intensity, light_intensity)
    if reduced:
        _reduce_cameras(tmp / "cameras.json", reduced)
        log.info("%s: %d camera(s) scaled to the linear images' size (linearize.max_size)", given, len(reduced))
    missing = sorted(stems - {c.stem for c in cams})
    if missing:
        log.warning("views without a camera in %s are not used: %s", given, ", ".join(missing))
    support = {"found": False, "reason": "no masks to replace"}
    if masks_dir is not None and all((tmp / "undistorted" / "masks" / f"{c.stem}.png").is_file() for c in cams):
        # an object standing on a table (issue 15): the plane from points triangulated in the
        # views with the given cameras (the cameras' frame is the user's: it is kept)
        known = load_cameras(tmp / "cameras.json")
        pts = triangulate_points([read_exr(tmp / "undistorted" / f"{c.stem}.exr") for c in known], known)
        _write_points(tmp / "points.ply", pts, np.zeros(len(pts), bool))
        support = _support_plane_masks(tmp, masks_dir)
    return {"source": "given", "cameras": str(given), "registered": len(cams),
            "unregistered": {m: "no camera in cameras.json" for m in missing}, "light_intensity": light,
            "support_plane": support}


def _reduce_cameras(path: Path, sizes: dict[str, tuple[int, int]]) -> None:
    """Rewrite the frames of ``path`` named in ``sizes`` (image -> (w, h)) for their images
    reduced to that size: image edges stay at 0 and W (area resampling), so K's rows scale by
    w / W and h / H (DESIGN section 1's pixel convention)."""
    data = json.loads(path.read_text())
    for frame in data["frames"]:
        if frame["image"] not in sizes:
            continue
        w, h = sizes[frame["image"]]
        K = np.asarray(frame["K"], dtype=np.float64)
        K[0] *= w / float(frame["width"])
        K[1] *= h / float(frame["height"])
        frame.update(width=w, height=h, K=K.tolist())
    path.write_text(json.dumps(data, indent=1))


def _copy_given_cameras(given: Path, dest: Path, given_intensity: float,
                        light_intensity: float | None) -> float | None:
    """Copy the capture's cameras.json to ``dest`` with ``light_intensity`` (the settings', i.e.
    capture.yaml's) as its ``light.intensity``; the file is copied unchanged when that adds
    nothing. Returns the intensity ``dest`` holds (None: neither states one; optimize estimates it).

    ``given_intensity`` is the validated value :func:`load_cameras` read (1 when the file has
    none). A file that states its own intensity and settings that give another: PoseError
    naming both sources, since either may be the stale one.
    """
    data = json.loads(given.read_text())
    light = data.get("light") or {}
    if light_intensity is None or ("intensity" in light and math.isclose(given_intensity, light_intensity,
                                                                          rel_tol=1e-6)):
        shutil.copyfile(given, dest)
        return given_intensity if light.get("intensity") is not None else None  # None: estimated by optimize
    if "intensity" in light:
        capture_yaml = given.parent / "capture.yaml"
        other = f"{capture_yaml} (light_intensity)" if capture_yaml.is_file() else "the poses settings (light_intensity)"
        raise PoseError(
            f"the light intensity is given twice with different values: {given} has light.intensity "
            f"{given_intensity:g} and {other} gives {light_intensity:g}; remove it from one of the two files "
            "(or make them agree)"
        )
    data["light"] = {**light, "type": "collocated_point", "intensity": float(light_intensity)}
    dest.write_text(json.dumps(data, indent=1))
    return float(light_intensity)


# ---------------------------------------------------------------------------------------------
# Structure from motion
# ---------------------------------------------------------------------------------------------
def _features_and_mapping(linear_dir: Path, work: Path, stems: list[str], settings: PoseSettings, masks: dict,
                          f_prior: float | None, timings: dict) -> tuple:
    """SIFT images, features, matches and the mapping trials in ``work``; returns (model, all
    models, trials, chosen trial, weak views dropped, SIFT enlargement, view shape, database,
    matcher), ``timings`` updated."""
    t0 = time.perf_counter()
    images = work / "images"
    images.mkdir(parents=True)
    feature_masks = work / "feature_masks" if settings.features.highlight_factor > 0 else None
    shapes, up = write_sift_images(linear_dir, stems, images, masks, feature_masks, settings.features.highlight_factor,
                                   settings.features.sift_encoding, settings)
    shape = shapes[stems[0]]
    timings["sift_images_s"] = time.perf_counter() - t0
    log.info("SfM on %d views of %dx%d (SIFT on %dx enlarged images), focal prior %s", len(stems), shape[1],
             shape[0], up, f"{f_prior:.1f} px" if f_prior else "none")
    # COLMAP works at the SIFT images' size; the model is scaled back after refinement
    f_sift = f_prior * up if f_prior else None
    shape_sift = (shape[0] * up, shape[1] * up)
    db = work / "database.db"
    timings.update(extract_and_match(db, images, len(stems), settings, f_sift, shape_sift, feature_masks,
                                     max_features=settings.features.max_num_features if up == 1
                                     else min(settings.features.max_num_features, settings.features.max_num_features_upsampled)))
    matcher = (timings.pop("matcher"), timings.pop("matching"))
    t0 = time.perf_counter()
    rec, models, trials, trial, weak = map_views(db, images, work / "mapping", settings, len(stems), shape_sift,
                                                 f_sift, masks, up)
    if rec is not None and f_sift is None and not trials[trial].get("intrinsics_ok"):
        rec, models, trials, trial, weak = _held_at_a_focal_guess(db, images, work, settings, len(stems), shape_sift,
                                                                  masks, up, (rec, models, trials, trial, weak),
                                                                  linear_dir.parent)
    timings["map_s"] = time.perf_counter() - t0
    return rec, models, trials, trial, weak, up, shape, db, matcher


def _held_at_a_focal_guess(db: Path, images: Path, work: Path, settings: PoseSettings, n: int, shape, masks: dict,
                           up: int, mapped: tuple, where: Path) -> tuple:
    """No focal length stated (no EXIF, no ``poses.camera.focal_px``) and every mapping trial's
    intrinsics drifted (:func:`recon.poses.mapping.intrinsics_ok`): the best such model can still
    give the focal length. Its robust refinement with the distortion held at 0 (the guard of
    :func:`recon.poses.mapping.refine`) is kept only if plausible, and the mapping runs again with
    the intrinsics held at it; its models are judged as before. A blob in the void in 16 PNGs
    without EXIF and strong vignetting: 8 trials "bogus intrinsics" (f 1005 px, k -1.5 for a true
    703 px), the cameras of the one kept 13 % of their distance off, and the asset nothing like the
    object. Without a plausible model after that, a stop that says what to give."""
    import pycolmap

    rec, models, trials, trial, weak = mapped
    guess, ginfo = refine(pycolmap.Reconstruction(rec), settings, shape, None)
    f_guess = float(next(iter(guess.cameras.values())).mean_focal_length())
    held = None
    if ginfo.get("distortion") != "held as mapped":
        log.warning("no mapping trial kept plausible intrinsics (%s) and the photos state no focal length: SfM again "
                    "with the intrinsics held at %.1f px (%.2f x the image's width), the best model's refined focal "
                    "length", ", ".join(sorted({t["mapper"] for t in trials})), f_guess / up, f_guess / shape[1])
        again = map_views(db, images, work / "mapping_held", settings, n, shape, f_guess, masks, up)
        for t in again[2]:
            t["held_at_focal_px"] = f_guess / up
        if again[0] is not None and again[2][again[3]].get("intrinsics_ok") \
                and len(again[0].reg_image_ids()) >= settings.mapping.min_registered_fraction * n:
            held = (again[0], again[1], trials + again[2], len(trials) + again[3], again[4])
    if held is None:
        raise PoseError(
            f"{where}: SfM found no camera model with plausible intrinsics in {len(trials)} trials "
            f"(the focal length and the lens distortion drifted), and the photos state no focal length (no EXIF "
            "FocalLength). What to try: give poses.camera.focal_px in the capture's capture.yaml (the focal length in "
            "pixels of the photos as they are; a phone's main camera: about 0.8 x the image's width), or use the "
            "photos as the camera wrote them, with their EXIF")
    return held


def _sfm(linear_dir: Path, tmp: Path, settings: PoseSettings, masks_dir: Path | None,
         linear_json: Path | None) -> dict:
    timings = {}
    stems = linear_stems(linear_dir)
    n = len(stems)
    if n < settings.mapping.min_registered:
        raise PoseError(
            f"{linear_dir}: {n} view(s), but SfM needs at least {settings.mapping.min_registered} overlapping photos "
            f"(poses.mapping.min_registered = {settings.mapping.min_registered}); photograph the object from more sides "
            "(a view every 10-15 degrees), or provide cameras.json in the capture so SfM is skipped"
        )
    light_known = settings.light_intensity is not None
    light_intensity = settings.light_intensity if light_known else DEFAULT_LIGHT_INTENSITY

    f_prior, f_source = prior_focal(settings, linear_json, stems)
    if f_prior:
        log.info("focal length prior %.1f px +- %.0f%% from %s", f_prior, 100 * prior_sigma(settings, f_source), f_source)
    else:
        log.info("no focal length prior (no usable EXIF focal length, no poses.camera.focal_px)")
    masks = read_masks(masks_dir, stems)
    work = tmp / "work"
    rec, models, trials, trial, weak, up, shape, db, matcher = _features_and_mapping(
        linear_dir, work, stems, settings, masks, f_prior, timings)
    n_reg = len(rec.reg_image_ids()) if rec is not None else 0
    retry = None
    if settings.features.sift_upsample_retry and up == 1 and n_reg < settings.mapping.accept_fraction * n \
            and sift_upsample_factor(sections.replace(settings, sift_upsample=0), shape) > 1:
        # small photos: too few SIFT features on some views; once more on enlarged images
        # (sift_upsample_factor), kept when it registers more views
        log.info("%d of %d views registered; SfM again with SIFT on enlarged images", n_reg, n)
        t_retry = {}
        again = _features_and_mapping(linear_dir, tmp / "work_upsampled", stems,
                                      sections.replace(settings, sift_upsample=0), masks, f_prior, t_retry)
        n_again = len(again[0].reg_image_ids()) if again[0] is not None else 0
        retry = {"registered_before": n_reg, "registered_upsampled": n_again, "kept": n_again > n_reg,
                 "seconds": sum(t_retry.values())}
        timings["retry_upsampled_s"] = retry["seconds"]
        if n_again > n_reg:
            shutil.rmtree(work, ignore_errors=True)
            (tmp / "work_upsampled").rename(work)
            rec, models, trials, trial, weak, up, shape, db, matcher = again
            db = work / db.name
        else:
            shutil.rmtree(tmp / "work_upsampled", ignore_errors=True)
    f_sift = f_prior * up if f_prior else None
    shape_sift = (shape[0] * up, shape[1] * up)
    matcher, matching = matcher

    registered = set()
    if rec is not None:
        registered = {Path(rec.images[i].name).stem for i in rec.reg_image_ids()}
    others = [sorted(Path(m.images[i].name).stem for i in m.reg_image_ids()) for m in models[1:]]
    reasons = unregistered_reasons(db, stems, registered, settings, others)
    for s, k in weak.items():
        reasons[s] = (f"posed from only {k} 3D points seen by the registered views (needs >= "
                      f"{settings.mapping.min_view_points}): too little overlap with the other views")
    if len(registered) < settings.mapping.min_registered or len(registered) < settings.mapping.min_registered_fraction * n:
        lines = "\n".join(f"  {s}: {reasons[s]}" for s in sorted(reasons))
        split = f" The views split into separate models ({len(models)} models)." if len(models) > 1 else ""
        raise PoseError(
            f"{linear_dir.parent}: only {len(registered)} of {n} views could be registered by SfM "
            f"(need >= {settings.mapping.min_registered} and >= {settings.mapping.min_registered_fraction:.0%}).{split}\n"
            f"Unregistered views:\n{lines}\n"
            "What to try: photos with more overlap (a view every 10-15 degrees around the object), "
            "more texture on the object or a textured support, sharper photos; or provide "
            "cameras.json (and masks/) in the capture so SfM is skipped."
        )
    if reasons:
        log.warning("%d of %d views not registered and dropped:\n%s", len(reasons), n,
                    "\n".join(f"  {s}: {r}" for s, r in sorted(reasons.items())))
    shutil.rmtree(work / "mapping", ignore_errors=True)
    refinement = {}
    if settings.camera.refine:
        rec, refinement = refine(rec, settings, shape_sift, f_sift, prior_sigma(settings, f_source))
    if up > 1:
        rescale_model(rec, shape, up)
    (tmp / "sparse").mkdir()
    rec.write(tmp / "sparse")

    # ---- undistortion to the pinhole camera ----
    t0 = time.perf_counter()
    colmap_cam = next(iter(rec.cameras.values()))
    pinhole = pinhole_camera(colmap_cam, settings.camera.camera_model)
    maps = undistort_maps(colmap_cam, pinhole)
    K = pinhole.calibration_matrix()
    names = image_names(linear_json, stems)
    orientations = view_orientations(linear_json, stems)
    frames = []
    und_masks = {}
    by_stem = {Path(rec.images[i].name).stem: rec.images[i] for i in rec.reg_image_ids()}
    for s in sorted(by_stem):
        m = undistort_view(linear_dir, tmp / "undistorted", s, maps, masks.get(s))
        if m is not None:
            und_masks[s] = m
        W = np.eye(4)
        W[:3, :4] = by_stem[s].cam_from_world().matrix()
        frames.append(Camera(names[s], pinhole.width, pinhole.height, K.copy(), W))
    cams_colmap = CameraSet(tuple(frames), light_intensity, light_known=light_known)
    timings["undistort_s"] = time.perf_counter() - t0

    # ---- object frame ----
    t0 = time.perf_counter()
    xyz, in_mask = points_in_masks(rec, masks)

    def place(view_masks: dict) -> tuple[Similarity, CameraSet, dict]:
        sim, frame_info = object_frame(cams_colmap, xyz, in_mask, view_masks, settings, orientations)
        cams = rotate_cameras(cams_colmap, sim)
        cams = CameraSet(cams.frames, light_intensity, {"colmap_to_object": sim.matrix.tolist(), **FRAME_UP},
                         light_known=light_known)
        save_cameras(tmp / "cameras.json", cams)
        _write_points(tmp / "points.ply", sim.apply(xyz) if len(xyz) else xyz, in_mask)
        frame = {"colmap_to_object": sim.to_dict(), **frame_info,
                 "note": "x_object = scale * rotation @ x_colmap + translation; sparse/ is in COLMAP's frame"}
        (tmp / "frame.json").write_text(json.dumps(frame, indent=1))
        return sim, cams, frame

    sim, cams, frame = place(und_masks)
    timings["frame_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    support = _support_plane_masks(tmp, masks_dir, rec=rec, sim=sim)
    if support.get("consistent", {}).get("applied"):
        # the flash-falloff masks changed (made consistent across the views): the object's box
        # is fitted again to their hull
        from recon.io.images import read_mask

        sim, cams, frame = place({s: read_mask(tmp / "undistorted" / "masks" / f"{s}.png") for s in und_masks})
    if support.get("found"):
        # the frame was fitted to the masks stage's masks, which hold the lit table: fit it again
        # to the object alone (it fills [-1, 1]^3, z along the table's normal), as in the void
        refit = _object_frame_on_plane(tmp, settings.frame.margin)
        if refit is not None:
            sim = Similarity(refit.scale * sim.scale, refit.rotation @ sim.rotation,
                             refit.scale * refit.rotation @ sim.translation + refit.translation)
            cams = load_cameras(tmp / "cameras.json")
            cams = CameraSet(cams.frames, cams.light_intensity, {"colmap_to_object": sim.matrix.tolist(), **FRAME_UP},
                             light_known=cams.light_known)
            save_cameras(tmp / "cameras.json", cams)
            frame["colmap_to_object"] = sim.to_dict()
            frame["refit_on_support_plane"] = refit.to_dict()
            (tmp / "frame.json").write_text(json.dumps(frame, indent=1))
    timings["support_plane_s"] = time.perf_counter() - t0

    mre = float(rec.compute_mean_reprojection_error())
    above = _points_on_the_object(rec, sim, tmp / "plane.json") if support.get("found") else None
    checked = masks
    if support.get("consistent", {}).get("applied"):
        # the masks the later stages read: the consistent ones, taken back to the photos' pixels
        from recon.io.images import read_mask

        back = distort_maps(colmap_cam, pinhole)
        checked = {**masks, **{s: remap(read_mask(tmp / "undistorted" / "masks" / f"{s}.png").astype(np.float32),
                                        back) >= 0.5 for s in support["consistent"].get("views", {})}}
    sil = silhouette_consistency(rec, checked, keep=above)
    if sil is not None and sil < settings.mapping.min_silhouette_consistency:
        log.warning("only %.0f%% of the object's sparse points (those seen inside the masks%s) project inside "
                    "the other views' masks (a right model: > %.0f%%): the cameras and the masks disagree; either "
                    "the masks miss parts of the object (check results/<capture>/masks) or SfM found a wrong (e.g. "
                    "mirrored) solution; more texture on the object or a textured support helps SfM", 100 * sil,
                    ", above the table" if above is not None else "", 100 * settings.mapping.min_silhouette_consistency)
    diag = {
        "source": "sfm",
        "views": n,
        "registered": len(registered),
        "registered_views": sorted(registered),
        "unregistered": reasons,
        "mean_reprojection_error_px": mre,
        "points3D": int(rec.num_points3D()),
        "points3D_in_masks": int(in_mask.sum()),
        "silhouette_consistency": sil,
        "silhouette_points": ("the object's points: seen inside the masks in every view that sees them"
                              + (", above the support plane, inside the object's box" if above is not None else "")),
        "camera": {"model": colmap_cam.model_name, "params": list(map(float, colmap_cam.params)),
                   "width": colmap_cam.width, "height": colmap_cam.height,
                   "focal_prior_px": f_prior, "focal_prior_source": f_source,
                   "focal_prior_sigma": prior_sigma(settings, f_source) if f_prior else None},
        "pinhole": {"width": pinhole.width, "height": pinhole.height, "K": K.tolist()},
        "matcher": matcher,
        "matching": matching,
        "sift_upsample": up,
        "sift_upsample_retry": retry,
        "mapper": settings.mapping.mapper,
        "trials": trials,
        "chosen_trial": trial,
        "refinement": refinement,
        "frame": frame,
        "support_plane": support,
        "light_intensity": light_intensity if light_known else None,  # None: estimated by optimize
        "timings": timings,
        "settings": asdict(settings),
    }
    log.info("registered %d/%d views, mean reprojection error %.3f px, %d points (%d in masks); %s",
             len(registered), n, mre, rec.num_points3D(), in_mask.sum(),
             ", ".join(f"{k} {v:.1f}" for k, v in timings.items()))
    return diag


def _points_on_the_object(rec, sim: Similarity, plane_json: Path, margin: float = 0.01) -> dict[int, bool] | None:
    """Per sparse point of ``rec`` (COLMAP's frame; ``sim`` maps it to the object frame of
    ``plane_json``): does it lie above the support plane by more than ``margin`` of the object's
    size, and inside the object's box (``object_bbox``, grown by 10 %) where the file has one?
    The table's points are then never counted as the object's. None without ``plane_json``."""
    if not plane_json.is_file():
        return None
    data = json.loads(plane_json.read_text())
    plane = load_plane(plane_json)
    ids = [int(p) for p in rec.point3D_ids()]
    if not ids:
        return {}
    xyz = sim.apply(np.array([rec.point3D(p).xyz for p in ids]).reshape(-1, 3))
    box = data.get("object_bbox")
    size = 2.0
    ok = np.ones(len(ids), bool)
    if box is not None:
        lo, hi = np.asarray(box["lo"], float), np.asarray(box["hi"], float)
        size = float(np.max(hi - lo))
        grow = 0.1 * (hi - lo)
        ok &= np.all((xyz >= lo - grow) & (xyz <= hi + grow), axis=1)
    ok &= plane.height(xyz) > margin * size
    return dict(zip(ids, ok.tolist(), strict=True))


def table_points_in_masks(rec, sim: Similarity, plane: SupportPlane, cams: CameraSet,
                          masks: dict[str, np.ndarray], tolerance: float, foot: float = 0.0) -> float | None:
    """The share of SfM's observations of the table's points (within ``tolerance`` of
    ``plane``, in the object frame that ``sim`` maps COLMAP's to, and with ``foot`` > 0 further
    than ``foot`` from the object's foot: :func:`recon.support.table_points`) that fall inside
    their view's mask (``masks``: stem -> (H, W) bool in the pinhole images of ``cams``). A point a
    view observed is visible there, so a mask that holds it holds the table: near 0 for masks of an
    object on a table, most of them for masks that took the table. None without such points."""
    ids = list(rec.points3D)
    xyz_all = sim.apply(np.array([rec.point3D(i).xyz for i in ids]).reshape(-1, 3))
    table = set(np.asarray(ids)[table_points(xyz_all, plane, tolerance, foot)].tolist()) if ids else set()
    by_stem = {c.stem: c for c in cams}
    inside = total = 0
    for im in rec.images.values():
        stem = Path(im.name).stem
        if not im.has_pose or stem not in by_stem or stem not in masks:
            continue
        obs = [(p.point3D_id, p.xy) for p in im.points2D if p.has_point3D()]
        if not obs:
            continue
        on = np.array([i in table for i, _ in obs])
        if not on.any():
            continue
        xy = np.array([o[1] for o, keep in zip(obs, on, strict=True) if keep], dtype=np.float64)
        u, v = keypoints_to_pinhole(rec.cameras[im.camera_id], xy, by_stem[stem].K).T
        m = masks[stem]
        j, i = np.floor(u).astype(int), np.floor(v).astype(int)
        ok = np.isfinite(u) & np.isfinite(v) & (j >= 0) & (j < m.shape[1]) & (i >= 0) & (i < m.shape[0])
        inside += int(m[i[ok], j[ok]].sum())
        total += int(ok.sum())
    return inside / total if total else None


def _support_plane_masks(tmp: Path, masks_dir: Path | None, rec=None, sim: Similarity | None = None,
                         max_table_in_masks: float = 0.3) -> dict:
    """An object standing on a table (issue 15): when the SfM points hold a support plane
    (:func:`recon.support.fit_support_plane`), the masks in ``undistorted/masks`` are replaced by
    the tabletop masks (:func:`recon.segment.run_tabletop_masks` on the undistorted views, the
    capture's own masks still winning) and ``plane.json`` is written beside ``cameras.json``;
    otherwise (an object in the void) the masks stage's masks stay, with a note in the log.

    With SfM's model (``rec``, ``sim``: COLMAP's frame to the stage's) the tabletop masks are
    checked against the table's points that the views observed (:func:`table_points_in_masks`):
    masks that hold more than ``max_table_in_masks`` of them took the table, and are not used
    (a warning; the masks stage's masks stay), as when the segmentation fails outright. Measured
    on the points within 1 % of the cameras' spread of the plane: 0.3-5.4 % for eight tabletop
    captures whose masks hold (docs/masks.md), 53 % for a torus on a weakly textured table and
    100 % for a vase on a stand over a floor, whose masks took the table."""
    cams = load_cameras(tmp / "cameras.json")
    given = None
    if masks_dir is not None and (masks_dir / "masks.json").is_file():
        views = json.loads((masks_dir / "masks.json").read_text()).get("views", {})
        given = {s for s, v in views.items() if v.get("source") == "given"}
    und_masks = tmp / "undistorted" / "masks"
    plane, info = fit_support_plane(read_points_ply(tmp / "points.ply"), cams)
    if plane is None:
        log.info("no support plane in the SfM points (%s): the masks stage's masks are kept, made consistent "
                 "across the views", info["reason"])
        plain = _plain_table_masks(cams, tmp, und_masks, given or set())
        return {**{k: v for k, v in info.items() if k in ("found", "reason")}, "plain_table": plain,
                "consistent": _consistent_falloff_masks(cams, und_masks, given or set(), tmp / "points.ply")}
    from recon.masks.tabletop import SegmentError

    try:
        summary = run_tabletop_masks(tmp / "undistorted", tmp / "cameras.json", tmp / "tabletop",
                                     points=tmp / "points.ply", given_dir=und_masks if und_masks.is_dir() else None,
                                     given_stems=given or set())
    except SegmentError as e:
        # a plane in the points, but nothing separates from it as an object on a table does (a
        # floor under a stand, a flat part of the object): the masks stage's masks stay
        shutil.rmtree(tmp / "tabletop", ignore_errors=True)
        log.warning("a plane was found in the SfM points, but the tabletop masks failed, so the masks stage's "
                    "masks are kept (no support plane), made consistent across the views. %s", e)
        return _masks_without_the_plane(cams, tmp, und_masks, given or set(), plane, rec,
                                        {"found": False, "reason": f"tabletop masks failed: {str(e).splitlines()[0]}"})
    if not (tmp / "tabletop" / "plane.json").is_file():
        # the tabletop masks refused there (they took the table: recon.masks.views.table_points_share)
        shutil.rmtree(tmp / "tabletop")
        log.warning("a plane was found in the SfM points, but the tabletop masks took the table (%s) and are not "
                    "used", summary["plane"].get("reason"))
        return _masks_without_the_plane(cams, tmp, und_masks, given or set(), plane, rec,
                                        {"found": False, "reason": summary["plane"].get("reason")})
    if rec is not None and sim is not None:
        from recon.io.images import read_mask

        new = {c.stem: read_mask(tmp / "tabletop" / f"{c.stem}.png") for c in cams
               if (tmp / "tabletop" / f"{c.stem}.png").is_file()}
        spread = camera_spread([c.center for c in cams])
        share = table_points_in_masks(rec, sim, load_plane(tmp / "tabletop" / "plane.json"), cams, new,
                                      tolerance=TABLE_TOLERANCE * spread, foot=FOOT_RADIUS * spread)
        if share is not None and share > max_table_in_masks:
            shutil.rmtree(tmp / "tabletop", ignore_errors=True)
            log.warning("a plane was found in the SfM points, but the tabletop masks hold %.0f%% of the table's "
                        "points that the views saw (masks of an object on a table: a few %%): they took the table "
                        "and are not used, the masks stage's masks are kept (no support plane), made consistent "
                        "across the views. Give masks/<stem>.png in the capture if these fail too", 100 * share)
            return _masks_without_the_plane(
                cams, tmp, und_masks, given or set(), plane, rec,
                {"found": False, "reason": f"the tabletop masks hold {100 * share:.0f}% of the table's points"})
    und_masks.mkdir(parents=True, exist_ok=True)
    for c in cams:
        os.replace(tmp / "tabletop" / f"{c.stem}.png", und_masks / f"{c.stem}.png")
    os.replace(tmp / "tabletop" / "plane.json", tmp / "plane.json")
    os.replace(tmp / "tabletop" / "masks.json", tmp / "masks.json")
    shutil.rmtree(tmp / "tabletop")
    log.info("support plane found in the SfM points: tabletop masks in undistorted/masks, plane.json written")
    return {k: v for k, v in summary["plane"].items() if not isinstance(v, (list, dict)) or k == "camera_elevation_deg"}


def _masks_without_the_plane(cams: CameraSet, tmp: Path, und_masks: Path, given: set[str], plane: SupportPlane,
                             rec, info: dict) -> dict:
    """A plane in the SfM points whose tabletop masks failed or were refused: the plain table's
    model, else the masks stage's flash-falloff masks made consistent, as for an object in the
    void; then, unless the plain table's model was used, the check that those masks did not take
    the lit table with the object (:func:`recon.masks.views.refuse_masks_holding_the_table`: a
    stop that says what to do)."""
    plain = _plain_table_masks(cams, tmp, und_masks, given)
    out = {**info, "plain_table": plain,
           "consistent": _consistent_falloff_masks(cams, und_masks, given, tmp / "points.ply")}
    if not plain.get("plain") and len(given) < len(cams):
        from recon.io.images import read_mask
        from recon.masks.views import refuse_masks_holding_the_table

        masks = {c.stem: read_mask(und_masks / f"{c.stem}.png") for c in cams if (und_masks / f"{c.stem}.png").is_file()}
        registered = "" if rec is None else f" ({rec.num_reg_images()} views registered by SfM)"
        out["table_points_share_falloff"] = refuse_masks_holding_the_table(
            read_points_ply(tmp / "points.ply"), plane, cams, masks, registered=registered)
    return out


# cameras.json of SfM: the object frame's z is up (the photos' up as displayed, or the table's
# normal), which the export stands on +Y whatever way each photo's pixels are stored
FRAME_UP = {"up": [0.0, 0.0, 1.0]}


def _plain_table_masks(cams: CameraSet, tmp: Path, und_masks: Path, given: set[str]) -> dict:
    """No support plane in the points, but perhaps a plain table (:mod:`recon.masks.plain`): SfM
    finds almost no points on a plain desk, and the masks stage's flash-falloff masks then hold
    the lit table with the object. When the undistorted views show a plain table shaded by the
    flash, each view's mask (but the capture's own) becomes what is neither that table nor the
    dark background (:func:`recon.masks.plain.plain_table_masks`). The object stays in the void
    (no plane.json: the table's height is not known well enough to stand it on). Returns the
    model's summary (``plain``, ``reason``, ...)."""
    from recon.io.images import read_exr, write_mask
    from recon.masks.plain import plain_table_masks

    paths = {c.stem: tmp / "undistorted" / f"{c.stem}.exr" for c in cams}
    if all(c.stem in given for c in cams) or not all(p.is_file() for p in paths.values()):
        return {"plain": False, "reason": "every view's mask is given, or a view is missing"}
    masks, info = plain_table_masks(read_points_ply(tmp / "points.ply"), lambda stem: read_exr(paths[stem]), cams,
                                    given)
    if masks is not None:
        und_masks.mkdir(parents=True, exist_ok=True)
        for stem, m in masks.items():
            write_mask(und_masks / f"{stem}.png", m)
    return info


def _consistent_falloff_masks(cams: CameraSet, und_masks: Path, given: set[str], points_ply: Path | None = None
                              ) -> dict:
    """No support plane: the masks stage's flash-falloff masks in ``und_masks`` (one per view of
    ``cams``) made consistent across the views with SfM's cameras
    (:func:`recon.masks.consistent.consistent_masks`: holes and notches the other views cover are
    filled, the dark rim along the outline comes back, lit background outside the voted hull
    goes), as the masks stage does for a capture that gives its cameras. The capture's own masks
    (``given``) vote but are never changed. Returns what was done (``applied``; per view the share
    of pixels added and removed)."""
    from recon.io.images import read_mask, write_mask
    from recon.masks.consistent import consistent_derived, warn_refusal

    paths = {c.stem: und_masks / f"{c.stem}.png" for c in cams}
    if not all(p.is_file() for p in paths.values()):
        return {"applied": False, "reason": "not every registered view has a mask"}
    if all(c.stem in given for c in cams):
        return {"applied": False, "reason": "every view's mask is given"}
    current = {s: read_mask(p) for s, p in paths.items()}
    after, info = consistent_derived(current, cams, given, warn_refused=False)  # said below, unless mended
    source = "flash falloff"
    if not info.get("applied") and points_ply is not None and points_ply.is_file():
        # no subset of the views agrees on one object (a near-black object before a lit wall or
        # base): masks drawn from SfM's points on the object, made consistent the same way
        from recon.masks.points import sparse_point_masks

        drawn = sparse_point_masks(read_points_ply(points_ply), cams)
        if sum(s not in given for s in drawn) >= 0.75 * sum(c.stem not in given for c in cams):
            after2, info2 = consistent_derived({**current, **{s: m for s, m in drawn.items() if s not in given}},
                                               cams, given)
            if info2.get("applied"):
                log.warning("the flash-falloff masks do not agree on one object (%s): the masks are drawn from "
                            "SfM's points on the object instead (%d of %d views), made consistent across the views. "
                            "Their outline is only as good as the object's texture: give masks/<stem>.png in the "
                            "capture for a better asset", info.get("reason"), len(drawn), len(cams))
                after, info, source = after2, {**info2, "views": {s: v for s, v in info2["views"].items()
                                                                  if s not in given}}, "sparse points"
    if not info.get("applied"):
        if "median_kept" in info:
            warn_refusal(info)
        log.info("flash-falloff masks kept view by view: %s", info.get("reason"))
        return {"applied": False, **{k: info[k] for k in ("reason", "median_kept") if k in info}}
    changed = info["views"]
    for stem in changed:
        write_mask(paths[stem], after[stem])
    added = float(np.mean([v["added"] for v in changed.values()]))
    removed = float(np.mean([v["removed"] for v in changed.values()]))
    log.info("masks (%s) made consistent across the %d registered views (hull voxel %.3g): %.1f%% of each image "
             "added, %.1f%% removed on average", source, len(cams), info["step"], 100 * added, 100 * removed)
    # views whose masks took something else (the floor, a stand's base) and that took the hull of
    # the agreeing views instead (recon.masks.consistent.agreeing_views)
    return {"applied": True, "source": source, "step": info["step"], "added": added, "removed": removed,
            "views": changed, "outliers": info.get("outliers", [])}


def _object_frame_on_plane(tmp: Path, margin: float) -> Similarity | None:
    """After the tabletop masks: the similarity from the stage's frame to one where the object
    alone (the box of its hull in ``plane.json``'s ``object_bbox``) is centred and fills
    [-(1 - margin), 1 - margin]^3, z along the plane's normal; ``cameras.json``, ``points.ply``
    and ``plane.json`` are rewritten in it. None (nothing changed) without an object box."""
    data = json.loads((tmp / "plane.json").read_text())
    if "object_bbox" not in data:
        return None
    plane = load_plane(tmp / "plane.json")
    lo, hi = np.asarray(data["object_bbox"]["lo"], float), np.asarray(data["object_bbox"]["hi"], float)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    n = plane.normal
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(a, n)
    e1 /= np.linalg.norm(e1)
    R = np.stack([e1, np.cross(n, e1), n])  # rows: x, y, z = the plane's normal
    q = corners @ R.T
    qlo, qhi = q.min(0), q.max(0)
    extent = float(np.max(qhi - qlo))
    if not extent > 0:
        return None
    s = 2.0 * (1.0 - margin) / extent
    refit = Similarity(s, R, -s * 0.5 * (qlo + qhi))
    cams = load_cameras(tmp / "cameras.json")
    save_cameras(tmp / "cameras.json", rotate_cameras(cams, refit))
    lines = (tmp / "points.ply").read_text().splitlines()
    start = lines.index("end_header") + 1
    rows = np.array([[float(x) for x in ln.split()] for ln in lines[start:]]).reshape(-1, 4)
    _write_points(tmp / "points.ply", refit.apply(rows[:, :3]) if len(rows) else rows[:, :3],
                  rows[:, 3].astype(bool))
    moved = SupportPlane.through(refit.apply(plane.point[None])[0], R @ n)
    new_lo, new_hi = refit.apply(corners).min(0), refit.apply(corners).max(0)
    extra = {k: v for k, v in data.items() if k not in ("normal", "offset", "point", "convention", "object_bbox")}
    save_plane(tmp / "plane.json", moved, **extra, object_bbox={"lo": new_lo.tolist(), "hi": new_hi.tolist()})
    log.info("object frame fitted again to the object standing on the table (scale x%.3g)", s)
    return refit


def _write_points(path: Path, xyz: np.ndarray, flag: np.ndarray) -> None:
    """ASCII PLY of points with an ``in_mask`` property."""
    lines = ["ply", "format ascii 1.0", f"element vertex {len(xyz)}", "property float x", "property float y",
             "property float z", "property uchar in_mask", "end_header"]
    lines += [f"{x:.6g} {y:.6g} {z:.6g} {int(f)}" for (x, y, z), f in zip(xyz, flag, strict=True)]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
