"""COLMAP mapping: the mapper trials, the checks that pick a trial, the robust final refinement.

Mapping alternates global (rotation averaging, robust on orbits around an object) and
incremental mappers with new seeds (:func:`mapper_sequence`) while a trial registers fewer than
``accept_fraction`` of the views, drifts to implausible intrinsics (:func:`intrinsics_ok`) or
disagrees with the masks (:func:`silhouette_consistency`); the trial with most views wins.
Where the masks disagree with every model (the masks stage's masks of an object on a table
hold some of the lit table), two trials of different kinds registering the views with the
same cameras (every view's rotation within ``agree_deg``, :func:`relative_rotations_agree`)
end the retries.
Views posed from fewer than ``min_view_points`` 3D points are dropped. A final bundle
adjustment with a Cauchy loss (:func:`refine`) lowers the pull of wrong matches.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from recon.poses.settings import PoseSettings

log = logging.getLogger(__name__)


def intrinsics_ok(rec, shape, f_prior: float | None = None) -> bool:
    """False for the drifted intrinsics an ill-conditioned start can produce: a focal length
    far from plausible (or 30% off the prior), or distortion beyond what lenses have."""
    cam = next(iter(rec.cameras.values()))
    f = cam.mean_focal_length()
    idx = list(cam.extra_params_idxs())
    extra = np.abs(np.asarray(cam.params)[idx]) if idx else np.zeros(0)
    ratio = f / max(shape)
    prior_ok = f_prior is None or abs(f / f_prior - 1.0) < 0.3
    return bool(0.2 < ratio < 8.0 and np.all(extra < 0.5) and prior_ok)


def object_points(rec, masks: dict[str, np.ndarray], up: int = 1) -> dict[int, bool]:
    """Per sparse point (id -> bool): is it a point of the object, i.e. does every one of its
    observations in views with a mask (at least two) fall inside that mask?

    This is the test of the points' own features, independent of the cameras: a point of the
    table or of the background is seen outside the object's silhouette in its views (and where a
    mask holds some of the lit table, the table's points still leave it in some view), while a
    point on the object is seen inside in all of them, in a right model or a wrong one alike.
    ``up``: the model is on images enlarged by this factor."""
    out = {}
    for pid in rec.point3D_ids():
        inside = 0
        ok = True
        for el in rec.point3D(pid).track.elements:
            im = rec.images[el.image_id]
            m = masks.get(Path(im.name).stem)
            if m is None:
                continue
            x, y = np.floor(np.asarray(im.points2D[el.point2D_idx].xy) / up).astype(np.int64)
            if not (0 <= y < m.shape[0] and 0 <= x < m.shape[1] and m[y, x]):
                ok = False
                break
            inside += 1
        out[int(pid)] = ok and inside >= 2
    return out


def silhouette_consistency(rec, masks: dict[str, np.ndarray], up: int = 1, keep: dict[int, bool] | None = None
                           ) -> float | None:
    """Fraction of (object point, registered view) pairs whose projection lands inside the
    view's mask, over projections inside the image; None without masks or object points.

    Every point of the object projects inside the object's silhouette in every view, seen or
    occluded, so a right model scores near 1 whatever its track lengths. A model that is wrong
    as a whole (a mirrored or folded solution of a symmetric object: all views ~1 px off,
    rotations 50-140 degrees wrong) still reprojects its points onto their own features but
    not into the other views' silhouettes: on the demo capture right models scored 0.97-0.98,
    wrong ones 0.59-0.61. ``up``: the model is on images enlarged by this factor.

    Only the object's points count (:func:`object_points`): a point of the table projects
    outside the object's silhouette in most views however right the cameras are, so counting
    every point rated right models of tabletop captures below the 0.9 threshold (0.86-0.87 on
    an 80-view phone capture: all 8 mapping trials ran) in proportion to the table's share of
    the points. ``keep`` (point id -> bool) narrows the points further (e.g. to those above the
    support plane)."""
    if not masks or rec.num_points3D() == 0:
        return None
    selected = object_points(rec, masks, up)
    if keep is not None:
        selected = {pid: ok and keep.get(pid, False) for pid, ok in selected.items()}
    ids = [pid for pid, ok in selected.items() if ok]
    if not ids:
        return None
    xyz = np.array([rec.point3D(p).xyz for p in ids]).reshape(-1, 3)
    total = inside = 0
    for i in rec.reg_image_ids():
        im = rec.images[i]
        m = masks.get(Path(im.name).stem)
        if m is None:
            continue
        M = np.asarray(im.cam_from_world().matrix())
        pc = xyz @ M[:, :3].T + M[:, 3]
        pc = pc[pc[:, 2] > 1e-9]
        if not len(pc):
            continue
        uv = np.asarray(rec.cameras[im.camera_id].img_from_cam(pc)).reshape(-1, 2) / up
        ok = np.all(np.isfinite(uv), axis=1)
        x, y = np.floor(uv[ok, 0]).astype(np.int64), np.floor(uv[ok, 1]).astype(np.int64)
        keep_px = (x >= 0) & (x < m.shape[1]) & (y >= 0) & (y < m.shape[0])
        total += int(keep_px.sum())
        inside += int(m[y[keep_px], x[keep_px]].sum())
    return inside / total if total else None


def mapper_sequence(settings: PoseSettings, has_prior: bool, n: int | None = None) -> list[str]:
    """Mapping trials in order. ``auto``: global (rotation averaging suits orbits around an
    object), incremental, incremental with the intrinsics held at the prior (stable where free
    intrinsics drift; the final refinement frees them, guarded by ``intrinsics_ok``), then
    alternating again with new seeds. With a focal length prior (EXIF), the held-intrinsics
    mapper goes first: on small or weakly textured captures free intrinsics drifted in most
    trials (the demo: 3 of 4 trials "bogus intrinsics", f 6x the prior), the held ones never."""
    n = settings.mapping.mapping_trials if n is None else n
    if settings.mapping.mapper != "auto":
        return [settings.mapping.mapper] * n
    if has_prior:
        cycle = ["incremental_fixed", "global", "incremental", "incremental_fixed"]
    else:
        cycle = ["global", "incremental", "global", "incremental"]
    return [cycle[t % len(cycle)] for t in range(n)]


def relative_rotations_agree(a, b) -> float | None:
    """Largest angle (degrees) between the two models' rotations of their common views once the
    rotation between their frames is taken out (``R_a,i ~ R_b,i Q``, Q the best rotation over
    all common views: the gauge; a mirrored or folded model differs by tens of degrees); None
    with fewer than 3 common views. ``a``, ``b``: pycolmap reconstructions.

    Q from every view, not from one reference view (``R_i R_ref^T``): that one's own error
    entered every difference, so a weakly placed reference doubled them (the sparse skull
    photos: 0.99 degrees against a reference seen from below, 0.6 with Q)."""
    def rotations(rec):
        return {rec.images[i].name: np.asarray(rec.images[i].cam_from_world().rotation.matrix())
                for i in rec.reg_image_ids()}

    ra, rb = rotations(a), rotations(b)
    common = sorted(set(ra) & set(rb))
    if len(common) < 3:
        return None
    u, _, vt = np.linalg.svd(sum(rb[n].T @ ra[n] for n in common))
    q = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    angles = [np.degrees(np.arccos(np.clip((np.trace(ra[n] @ (rb[n] @ q).T) - 1.0) / 2.0, -1.0, 1.0)))
              for n in common]
    return float(np.max(angles))


SILHOUETTE_SLACK = 0.05
"""How far under ``min_silhouette_consistency`` a model may score and still rank as consistent
when the trials are compared (the retries still run until one passes the threshold itself).
Wrong (mirrored, folded) models score about 0.6; right ones of the sparse skull photos 0.87-0.89,
whose flash-falloff masks miss the shadowed face: with the threshold as the first key, a global
trial registering 21 of 33 views at 0.91 beat the incremental trials' 32 views at 0.87."""


WRONG_MODEL_GAP = 0.1
"""When no trial's model is consistent with the masks, one that scores this much below the best
sane model does not rank by its number of views: it is the folded or mirrored solution. A
figure on a stand (front and back alike, 36 views): 6 trials registered 16-17 views at
0.78-0.80, two registered 34 at 0.58 and 0.63, cameras 99-178 degrees wrong; ranked by views,
the 34 won and the asset was nothing like the figure (accuracy 1.95 of its size)."""


def _best(candidates: list[tuple]) -> tuple:
    """The best of the trials' ``(score, ...)`` tuples, ``score = (sane, near, n_reg, sil)``: sane
    intrinsics first, then near-consistent with the masks, then not :data:`WRONG_MODEL_GAP` below
    the best sane model's consistency, then most views, then the consistency."""
    sils = [c[0][3] for c in candidates if c[0][0] and c[0][3] is not None]
    top = max(sils) if sils else None

    def key(c):
        sane, near, n_reg, sil = c[0]
        plausible = top is None or sil is None or sil >= top - WRONG_MODEL_GAP
        return (sane, near, plausible, n_reg, sil or 0.0)

    return max(candidates, key=key)


def _partners(a, b) -> bool:
    """May trial ``b`` (full: registering accept_fraction of the views) be accepted on the
    agreement of trial ``a``? Different mappers, and when ``a`` is not full, of the other family
    (global against incremental, held intrinsics or not)."""
    family = {"global": "global"}
    if a[0] == b[0]:
        return False
    return a[2] or family.get(a[0], "incremental") != family.get(b[0], "incremental")


def map_views(db: Path, images: Path, sparse_root: Path, settings: PoseSettings, n_views: int, shape,
              f_prior: float | None = None, masks: dict | None = None, up: int = 1) -> tuple:
    """Run mapping trials; return (best reconstruction, all models of that trial, trial log,
    trial index, views dropped as weak)."""
    import pycolmap

    best = None
    trials = []
    candidates = []
    partners = []  # (mapper, model, full, best-tuple, consistent): sane trials holding min_registered_fraction
    # up to twice the trials while no model is both plausible and consistent with the masks
    for trial, kind in enumerate(mapper_sequence(settings, f_prior is not None, 2 * settings.mapping.mapping_trials)):
        if trial >= settings.mapping.mapping_trials and best is not None and best[0][0] and best[0][1]:
            break
        seed = settings.trial_seed(trial)
        pycolmap.set_random_seed(seed)
        out = sparse_root / f"trial{trial}"
        out.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        try:
            if kind == "global":
                opts = pycolmap.GlobalPipelineOptions(
                    num_threads=settings.num_threads, random_seed=seed, min_num_matches=settings.matching.min_num_inliers
                )
                models = pycolmap.global_mapping(db, images, out, options=opts)
                if not models:  # its retriangulation step can fail on small images: keep the BA result
                    opts.mapper.skip_retriangulation = True
                    models = pycolmap.global_mapping(db, images, out, options=opts)
            else:
                opts = pycolmap.IncrementalPipelineOptions(
                    num_threads=settings.num_threads, random_seed=seed, min_num_matches=settings.matching.min_num_inliers,
                    min_model_size=3,
                )
                opts.mapper.init_min_num_inliers = settings.mapping.init_min_num_inliers
                opts.mapper.abs_pose_min_num_inliers = settings.mapping.abs_pose_min_num_inliers
                opts.max_runtime_seconds = int(settings.mapping.max_mapping_seconds)
                if kind == "incremental_fixed":
                    opts.ba_refine_focal_length = False
                    opts.ba_refine_extra_params = False
                    opts.mapper.abs_pose_refine_focal_length = False
                    opts.mapper.abs_pose_refine_extra_params = False
                models = pycolmap.incremental_mapping(db, images, out, options=opts)
        except Exception as e:  # pycolmap raises plain RuntimeErrors for failed mappings
            log.warning("mapping trial %d (%s) failed: %s", trial, kind, e)
            models = {}
        models = sorted(models.values(), key=lambda r: r.num_reg_images(), reverse=True)
        weak = _drop_weak_views(models[0], settings.mapping.min_view_points) if models else {}
        n_reg = models[0].num_reg_images() if models else 0
        sane = bool(models) and intrinsics_ok(models[0], shape, f_prior)
        sil = silhouette_consistency(models[0], masks or {}, up) if models else None
        consistent = sil is None or sil >= settings.mapping.min_silhouette_consistency
        trials.append({"mapper": kind, "seed": seed, "registered": n_reg, "weak_views_dropped": weak,
                       "models": [m.num_reg_images() for m in models], "intrinsics_ok": sane,
                       "silhouette_consistency": sil, "seconds": time.perf_counter() - t0})
        log.info("mapping trial %d (%s, seed %d): %d/%d views registered in the largest of %d model(s)%s%s",
                 trial, kind, seed, n_reg, n_views, len(models),
                 "" if sil is None else f", silhouette consistency {sil:.3f}",
                 "" if sane or not models else ", bogus intrinsics")
        # ranking: nearly consistent (within SILHOUETTE_SLACK) counts as consistent, so that a model
        # with more views is not lost to a smaller one that happens to pass the threshold
        near = sil is None or sil >= settings.mapping.min_silhouette_consistency - SILHOUETTE_SLACK
        score = (sane, near, n_reg, sil)
        if models:
            candidates.append((score, models[0], models, trial, weak))
            best = _best(candidates)
        if sane and consistent and n_reg >= settings.mapping.accept_fraction * n_views:
            break
        if not sane or n_reg < settings.mapping.min_registered_fraction * n_views:
            continue
        # masks that disagree with every model (the masks stage's masks of an object on a table
        # hold some of the lit table: a right model scored 0.87 on an 80-view tabletop capture,
        # and all 8 trials ran; flash-falloff masks miss an object's shadowed side: the sparse
        # skull photos' right models scored 0.87-0.88): two mappers of different kinds finding
        # the same cameras is the evidence the masks could not give. The largest difference,
        # not the mean: a global trial there placed 1 of 80 views 86 degrees off (median 0.04).
        # The partner may hold fewer views if it is of the other family (global against
        # incremental: independent methods), as long as it holds min_registered_fraction of
        # them (the skull: incremental 32/33 views, global 21 of them).
        this = (kind, models[0], n_reg >= settings.mapping.accept_fraction * n_views, (score, models[0], models, trial, weak),
                consistent)
        accepted = None
        if this[2] and not consistent:
            for prev in partners:
                if _partners(prev, this):
                    agree = relative_rotations_agree(prev[1], models[0])
                    trials[-1]["agrees_with_other_mapper_deg"] = agree
                    if agree is not None and agree < settings.mapping.agree_deg:
                        accepted = (this, prev, agree)
                        break
        if accepted is None:
            for prev in partners:
                if prev[2] and not prev[4] and _partners(this, prev):
                    agree = relative_rotations_agree(prev[1], models[0])
                    trials[-1]["agrees_with_other_mapper_deg"] = agree
                    if agree is not None and agree < settings.mapping.agree_deg:
                        accepted = (prev, this, agree)
                        break
        if accepted is not None:
            chosen, other, agree = accepted
            log.info("mapping: %s (%d views) and a trial of %s (%d views) agree (largest relative rotation difference "
                     "%.3f degrees): accepted although the masks disagree", chosen[0], chosen[1].num_reg_images(),
                     other[0], other[1].num_reg_images(), agree)
            # keep this model, not the best-scoring one: a third trial may score a little
            # higher on the masks with a view misplaced (seen: a global trial, 1 view 86 deg off)
            best = chosen[3]
            break
        partners.append(this)
    if best is None:
        return None, [], trials, None, {}
    return best[1], best[2], trials, best[3], best[4]


def rescale_model(rec, shape, up: int) -> None:
    """Scale a model found on ``up`` x enlarged images back to the images' (H, W) ``shape``."""
    for cam in rec.cameras.values():
        cam.rescale(int(shape[1]), int(shape[0]))
    for i in rec.reg_image_ids():
        for p in rec.images[i].points2D:
            p.xy = p.xy / up
    rec.update_point_3d_errors()


def _drop_weak_views(rec, min_points: int) -> dict[str, int]:
    """Deregister views posed from fewer than ``min_points`` 3D points (global mapping places
    views by rotation averaging even when no point supports them), then views not anchored
    to the model (:func:`anchored_views`); returns stem -> the points that tie the view to
    the model (its own 3D points for the first kind)."""
    weak = {}
    for i in list(rec.reg_image_ids()):
        im = rec.images[i]
        if im.num_points3D < min_points:
            weak[Path(im.name).stem] = int(im.num_points3D)
            rec.deregister_frame(im.frame_id)
    keep, tied = anchored_views(rec, min_points)
    for i in list(rec.reg_image_ids()):
        if i not in keep:
            weak[Path(rec.images[i].name).stem] = int(tied[i])
            rec.deregister_frame(rec.images[i].frame_id)
    return weak


def anchored_views(rec, min_points: int) -> tuple[set[int], dict[int, int]]:
    """The registered views tied to the model's main part, and per view the 3D points it
    shares with it.

    A view is anchored when at least ``min_points`` of its 3D points are also seen by other
    anchored views; the set grows from each view in turn (a fixpoint) and the largest wins.
    A group of views whose points are seen mostly among themselves is not: its position and
    scale relative to the rest rest on a handful of points. On a 256x192 orbit (32 views)
    global mapping once placed two such views (16 points shared with each other, 6 and 3
    with the rest) 9x too far from the object along their viewing rays; every view had a
    0.15 px error and the silhouette consistency was 0.98 (a view too far away still sees
    the points inside its mask), but the similarity of the camera centres was 21 degrees
    off the truth.
    """
    ids = [int(i) for i in rec.reg_image_ids()]
    views_of = {}  # point -> the registered views that see it
    for pid in rec.point3D_ids():
        views_of[pid] = {int(e.image_id) for e in rec.point3D(pid).track.elements}
    points_of = {i: [] for i in ids}
    for pid, vs in views_of.items():
        for v in vs:
            if v in points_of:
                points_of[v].append(pid)

    def tied_to(i, group):
        return sum(1 for pid in points_of[i] if any(v != i and v in group for v in views_of[pid]))

    best: set[int] = set()
    for seed in sorted(ids, key=lambda i: -len(points_of[i])):
        if seed in best or len(points_of[seed]) < min_points:
            continue
        group = {seed}
        grown = True
        while grown:
            new = {i for i in ids if i not in group and tied_to(i, group) >= min_points}
            grown = bool(new)
            group |= new
        if len(group) > len(best):
            best = group
        if len(best) > len(ids) // 2:  # no other group can be larger
            break
    return best, {i: tied_to(i, best - {i}) for i in ids}


def refine(rec, settings: PoseSettings, shape, f_prior: float | None = None, prior_sigma: float | None = None):
    """Final bundle adjustment with a robust (Cauchy) loss; returns (reconstruction, info).

    Wrong matches that survived verification (repeated texture, highlights) then pull much
    less on the poses. When the camera model has distortion parameters, a second adjustment
    with them fixed at 0 runs too, and wins unless distortion lowers the reprojection error by
    more than ``distortion_gain``: an object in the middle of the frame hardly constrains lens
    distortion, which then trades off against the focal length (seen in tests: f 13% off with
    k = -0.37 on distortion-free images).

    A candidate (``shape``: the images' (H, W)) whose intrinsics drift to implausible values
    (:func:`intrinsics_ok`) is rejected, even with the lower error: on the 192x144 demo a free
    adjustment once went from f = 264 px to f = 1552 px with k = -58 (error 0.43 -> 0.35 px),
    which undistorted every view into nonsense and emptied the visual hull. If no free
    candidate is plausible, the adjustment runs with the intrinsics held as mapped.
    """
    import pycolmap

    def adjust(r, refine_extra: bool, refine_focal: bool = True):
        ba = pycolmap.BundleAdjustmentOptions(print_summary=False, refine_extra_params=refine_extra,
                                              refine_focal_length=refine_focal)
        ba.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
        ba.ceres.loss_function_scale = settings.camera.refine_loss_scale
        ba.ceres.solver_options.num_threads = settings.num_threads
        pycolmap.bundle_adjustment(r, ba)
        return float(r.compute_mean_reprojection_error())

    def plausible(r) -> bool:
        return intrinsics_ok(r, shape, f_prior)

    before = float(rec.compute_mean_reprojection_error())
    info = {"reprojection_error_before_px": before}
    candidates = []  # (name, reconstruction, error), most general first
    free = pycolmap.Reconstruction(rec)
    e_free = adjust(free, True)
    info["reprojection_error_free_px"] = e_free
    cam = next(iter(rec.cameras.values()))
    extra = list(cam.extra_params_idxs())
    if plausible(free):
        candidates.append(("estimated" if extra else "none", free, e_free))
    else:
        info["rejected_free"] = np.round(np.asarray(next(iter(free.cameras.values())).params), 4).tolist()
    if extra and settings.camera.distortion_gain >= 0:
        plain = pycolmap.Reconstruction(rec)
        for c in plain.cameras.values():
            p = np.asarray(c.params, dtype=float).copy()
            p[extra] = 0.0
            c.params = p
        e_plain = adjust(plain, False)
        info["reprojection_error_no_distortion_px"] = e_plain
        if plausible(plain):
            if not candidates or e_plain <= candidates[0][2] * (1.0 + settings.camera.distortion_gain):
                candidates.insert(0, ("none", plain, e_plain))
        else:
            info["rejected_no_distortion"] = np.round(np.asarray(next(iter(plain.cameras.values())).params),
                                                      4).tolist()
    if not candidates:  # both drifted: keep the mapped intrinsics
        held = pycolmap.Reconstruction(rec)
        e_held = adjust(held, False, refine_focal=False)
        candidates.append(("held as mapped", held, e_held))
        log.warning("robust refinement: free intrinsics drifted to implausible values %s; kept the mapped "
                    "camera", info.get("rejected_free"))
    name, chosen, e = candidates[0]
    if f_prior is not None and settings.camera.focal_refine != "free":
        info["focal"] = focal_with_prior(chosen, settings, f_prior, prior_sigma)
        c = next(iter(chosen.cameras.values()))
        c.params = np.where(np.isin(np.arange(len(c.params)), list(c.focal_length_idxs())),
                            info["focal"]["focal_px"], np.asarray(c.params, dtype=float))
        e = adjust(chosen, name == "estimated", refine_focal=False)
    cam = next(iter(chosen.cameras.values()))
    info["distortion"] = name
    info["reprojection_error_after_px"] = e
    log.info("robust refinement: mean reprojection error %.3f -> %.3f px (distortion %s); camera %s %s",
             before, e, info["distortion"], cam.model_name, np.round(cam.params, 4).tolist())
    return chosen, info


def focal_sigma(rec, settings: PoseSettings, step: float = 0.01) -> float | None:
    """The relative standard deviation of the focal length that a bundle adjustment of ``rec``
    determines, from the profile of its cost: adjusted with the focal length free (cost C0,
    f0), then held at f0 (1 +- ``step``) with every pose and point adjusted (C+, C-), the cost
    rises by a (f - f0)^2 / 2 with a = (C+ + C- - 2 C0) / (step f0)^2, and sigma_f^2 =
    sigma_px^2 / a, sigma_px^2 = 2 C0 / residuals (the pixel noise the residuals show). The
    profile is the marginal of the focal length over poses and points, free of the gauge
    (COLMAP's ``estimate_ba_covariance`` returned None or values that depended on its damping
    on the test orbit). None when the cost does not rise (not determined at all). It counts
    the random part of the matching error only."""
    import pycolmap

    def solve(r, refine_focal):
        opts = pycolmap.BundleAdjustmentOptions(print_summary=False, refine_extra_params=False,
                                                refine_focal_length=refine_focal)
        opts.ceres.solver_options.num_threads = settings.num_threads
        config = pycolmap.BundleAdjustmentConfig()
        for i in r.reg_image_ids():
            config.add_image(i)
        summary = pycolmap.create_default_ceres_bundle_adjuster(opts, config, r).solve()
        return float(summary.ceres_summary.final_cost), int(summary.num_residuals)

    base = pycolmap.Reconstruction(rec)
    c0, n_res = solve(base, True)
    cam = next(iter(base.cameras.values()))
    f0 = float(cam.mean_focal_length())
    idx = list(cam.focal_length_idxs())
    costs = []
    for sign in (1.0, -1.0):
        r = pycolmap.Reconstruction(base)
        c = next(iter(r.cameras.values()))
        params = np.asarray(c.params, dtype=float).copy()
        params[idx] = f0 * (1.0 + sign * step)
        c.params = params
        costs.append(solve(r, False)[0])
    a = (costs[0] + costs[1] - 2.0 * c0) / (step * f0) ** 2
    if not (np.isfinite(a) and a > 0 and n_res > 0 and c0 > 0):
        return None
    sigma = float(np.sqrt(2.0 * c0 / n_res / a)) / f0
    return sigma if np.isfinite(sigma) else None


def focal_with_prior(rec, settings: PoseSettings, f_prior: float, prior_sigma: float | None = None) -> dict:
    """The focal length to hold in the final adjustment of ``rec`` given a prior (EXIF).

    ``fixed``: the prior. ``auto``: the adjustment's estimate and the prior weighted by the
    inverse of their variances (the estimate's: :func:`focal_sigma` x ``focal_sigma_scale``;
    the prior's: ``focal_prior_sigma``), i.e. a Gaussian prior on the focal length in the
    adjustment: the prior wins where the capture's geometry cannot determine the focal length
    (a narrow field of view, an object far from the cameras, few small images: a focal length
    error and an object scaled by the same factor then differ only by perspective), the
    adjustment where it can. On blob orbits (40 degrees field of view, no prior) the
    adjustment's focal length was short by 1.9 % at 192x144 (32 views; sigma 0.90 %), 1.1 %
    at 256x192 (32 views; 0.46 %), 0.63 % at 256x256 (40 views; 0.34 %) and 3.4 % on 192x144
    JPEGs (0.89 %): 1.9-3.8 sigma, always short (docs/camera_refine.md), hence
    ``focal_sigma_scale`` 2. A prior more than 5 combined standard
    deviations from the estimate contradicts the photos and is not used. Without an estimate
    of the variance (the cost did not rise), the prior. ``prior_sigma``: the prior's relative
    standard deviation (default ``focal_prior_sigma``; :func:`recon.poses.inputs.prior_sigma`).
    """
    s_prior = settings.camera.focal_prior_sigma if prior_sigma is None else float(prior_sigma)
    f_ba = float(next(iter(rec.cameras.values())).mean_focal_length())
    out = {"mode": settings.camera.focal_refine, "prior_px": float(f_prior), "prior_sigma": s_prior,
           "adjusted_px": f_ba, "adjusted_sigma": None}
    f = float(f_prior)
    if settings.camera.focal_refine == "auto":
        sigma = focal_sigma(rec, settings)
        out["adjusted_sigma"] = sigma
        if sigma is not None:
            s_ba = settings.camera.focal_sigma_scale * sigma
            z = abs(f_ba / f_prior - 1.0) / float(np.hypot(s_ba, s_prior))
            out["disagreement_sigma"] = z
            if z > 5.0:  # the photos contradict the prior (a digital zoom, a crop, a wrong tag)
                f = f_ba
                log.warning("focal length: the adjustment's %.2f px and the prior %.2f px differ by %.1f standard "
                            "deviations: the prior is not used (poses.camera.focal_refine: fixed holds it)", f_ba, f_prior, z)
            else:
                f = (f_ba / s_ba**2 + f_prior / s_prior**2) / (1.0 / s_ba**2 + 1.0 / s_prior**2)
    out["focal_px"] = f
    log.info("focal length: %.2f px (prior %.2f px +- %.1f%%, adjusted %.2f px +- %s; %s)", f, f_prior,
             100 * s_prior, f_ba,
             "?" if out["adjusted_sigma"] is None else f"{100 * out['adjusted_sigma']:.2f}%", settings.camera.focal_refine)
    return out


def unregistered_reasons(db_path: Path, stems: list[str], registered: set[str], settings: PoseSettings,
                         other_models: list[list[str]]) -> dict[str, str]:
    """A reason, in words, for every view the mapper left out."""
    import pycolmap

    db = pycolmap.Database.open(db_path)
    try:
        id_of, stem_of = {}, {}
        for s in stems:
            im = db.read_image_with_name(f"{s}.png")
            if im is not None:
                id_of[s] = im.image_id
                stem_of[im.image_id] = s
        pair_ids, inliers = db.read_two_view_geometry_num_inliers()
        best: dict[str, list] = {s: [] for s in stems}
        for pid, n in zip(pair_ids, inliers, strict=True):
            a, b = pycolmap.pair_id_to_image_pair(pid)
            if a in stem_of and b in stem_of and n >= settings.matching.min_num_inliers:
                best[stem_of[a]].append((n, stem_of[b]))
                best[stem_of[b]].append((n, stem_of[a]))
        reasons = {}
        for s in stems:
            if s in registered:
                continue
            other = next((m for m in other_models if s in m), None)
            nkp = db.num_keypoints_for_image(id_of[s]) if s in id_of else 0
            partners = sorted(best[s], reverse=True)
            if nkp < 100:
                reasons[s] = f"only {nkp} SIFT features (too little texture, blur or a dark image)"
            elif not partners:
                reasons[s] = (f"{nkp} features but no verified match (>= {settings.matching.min_num_inliers} inliers) "
                              "with any other view (too little overlap)")
            elif other is not None:
                mates = ", ".join(o for o in other if o != s)
                reasons[s] = (f"registered in a separate model with {mates}: the two groups "
                              "share too few matches to be placed in one frame")
            elif not any(p in registered for _, p in partners):
                reasons[s] = f"matches only views that are not registered either ({', '.join(p for _, p in partners[:3])})"
            else:
                n, p = next((n, p) for n, p in partners if p in registered)
                reasons[s] = (f"best match with a registered view: {n} inliers with {p}; the mapper could not "
                              f"place it (needs >= {settings.mapping.abs_pose_min_num_inliers} 2D-3D inliers)")
        return reasons
    finally:
        db.close()

