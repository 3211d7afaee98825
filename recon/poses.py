"""Stage ``poses``: cameras in the object frame (DESIGN sections 1 and 2).

Known cameras (the capture's ``cameras.json``) pass through after validation: no SfM runs.
Otherwise COLMAP (pycolmap 4.2.1, CPU) recovers them:

1. The linear images are encoded to 8-bit PNGs for SIFT (``poses/work/images``), each scaled
   by its own 99.5th percentile (SIFT needs contrast, not radiometry; see :func:`sift_image`).
   Specular highlights get no features (``poses/work/feature_masks``): they move with the
   flash, so their matches belong to no fixed surface point.
2. SIFT features (peak threshold 0.001: smooth, flash-lit objects have little contrast) with
   one shared camera (``CameraMode.SINGLE``: one photo camera, one zoom) and the focal length
   prior from ``linear.json`` when the linearize stage found one.
3. Matching: exhaustive up to ``exhaustive_max_views`` views, else sequential (captures are
   shot walking around the object, so neighbours in file order overlap; no vocabulary tree
   is needed). The two-view RANSAC threshold scales with the image (0.4% of the long side,
   1 to 4 px): COLMAP's fixed 4 px lets chance matches of repeated texture pass as verified
   pairs on small images, and those wrong pairs broke the mapping in tests.
4. Mapping: global (rotation averaging, robust on orbits around an object) then incremental,
   alternating with new seeds while a trial registers fewer than ``accept_fraction`` of the
   views or ends with drifted intrinsics; the trial with most views wins. Views posed from
   fewer than ``min_view_points`` 3D points are dropped (global mapping places a view from
   rotations alone). A final bundle adjustment with a Cauchy loss lowers the pull of wrong
   matches (about 20% smaller pose errors in tests).
5. Undistortion of the linear EXRs, the masks and the clipped-pixel masks to the pinhole
   camera COLMAP derives (``pycolmap.undistort_camera``), by ``cv2.remap`` in float: the
   8-bit route of ``pycolmap.undistort_images`` would lose the linear data.
6. The object frame: z up (the mean of the cameras' up vectors: photographers hold the camera
   roughly upright), x and y along the principal axes of the sparse points that project
   inside the masks; then a coarse visual hull (64^3) of the undistorted masks around those
   points gives the object's extent (sparse points miss untextured parts, the hull never
   misses object); the object is centered and scaled to fill ``1 - margin`` of [-1, 1]^3.
   The similarity from COLMAP's frame is written to ``frame.json`` and to the
   ``colmap_to_object`` key of ``cameras.json``.

Outputs (``results/<capture>/poses/``, replaced atomically, nothing partial on error):
``cameras.json`` (pinhole, undistorted sizes, object frame), ``frame.json``, ``poses.json``
(diagnostics: registered and unregistered views with reasons, reprojection error, timings),
``points.ply`` (sparse points, object frame), ``sparse/`` (the COLMAP model, COLMAP frame,
original distorted camera), ``undistorted/<stem>.exr``, ``undistorted/<stem>.sat.png`` and
``undistorted/masks/<stem>.png`` (the pinhole views every later stage reads), ``work/`` (the
SIFT images and COLMAP database).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from recon.io.atomic import atomic_dir
from recon.io.cameras import Camera, CameraError, CameraSet, load_cameras, save_cameras
from recon.io.images import ImageError, linear_to_srgb, read_exr, read_mask, write_exr, write_mask, write_png
from recon.metrics import Similarity

log = logging.getLogger(__name__)


class PoseError(ValueError):
    """Cameras that cannot be recovered or used; the message lists the views and what to try."""


@dataclass(frozen=True)
class PoseSettings:
    """Settings of the SfM path (ignored when the capture gives cameras.json)."""

    # ---- features ----
    max_image_size: int = 1600  # SIFT runs on images downscaled to this long side (-1: full)
    max_num_features: int = 8192
    sift_encoding: str = "srgb"  # srgb | log: what SIFT sees (see sift_image)
    sift_upsample: int = 1  # enlarge the SIFT images by this factor; 0: auto (see sift_upsample_factor)
    max_num_features_upsampled: int = 2048  # feature cap on enlarged images (matching cost)
    peak_threshold: float = 0.001  # COLMAP's default 0.0067 finds too few on smooth objects
    highlight_factor: float = 4.0  # no features where luminance > this x the object's median (0: off)
    affine_features: bool = False  # affine-covariant SIFT + domain-size pooling (wide baselines)
    guided_matching: bool = False
    max_ratio: float = 0.8  # SIFT ratio test
    camera_model: str = "SIMPLE_RADIAL"  # shared camera; PINHOLE-like models skip distortion
    # ---- matching ----
    matcher: str = "auto"  # auto | exhaustive | sequential
    exhaustive_max_views: int = 120  # auto: exhaustive up to this many views
    sequential_overlap: int = 15
    min_num_inliers: int = 12  # verified two-view geometry
    verify_max_error: float = 0.0  # RANSAC epipolar threshold, pixels; 0: 0.4% of the long side in [1, 4]
    # ---- mapping ----
    mapper: str = "auto"  # auto (see _mapper_sequence) | incremental | incremental_fixed | global
    init_min_num_inliers: int = 50
    abs_pose_min_num_inliers: int = 15
    mapping_trials: int = 4  # retries (other mapper, other seed) while too many views are left out
    accept_fraction: float = 0.95  # a trial registering this fraction of the views ends the retries
    max_mapping_seconds: float = 600.0  # per incremental trial
    min_registered: int = 3
    min_view_points: int = 15  # views posed from fewer 3D points are dropped (unreliable)
    min_registered_fraction: float = 0.5  # fewer than this (largest model / views): error
    min_silhouette_consistency: float = 0.9  # with masks: see silhouette_consistency (0: off)
    refine: bool = True  # a final robust bundle adjustment
    refine_loss_scale: float = 0.5  # Cauchy loss scale, pixels
    distortion_gain: float = 0.05  # keep lens distortion only if it cuts the error by more (-1: always)
    seed: int = 0
    num_threads: int = -1
    # ---- object frame ----
    bbox_percentile: float = 1.0  # robust box of the sparse points: [p, 100 - p] percentiles
    margin: float = 0.1  # the object fills [-(1 - margin), 1 - margin]
    hull_resolution: int = 64  # coarse visual hull for the object's extent (0: sparse points only)
    light_intensity: float = 1.0  # written to cameras.json (unknown scale after SfM)

    def __post_init__(self):
        if self.matcher not in ("auto", "exhaustive", "sequential"):
            raise ValueError(f"matcher must be auto, exhaustive or sequential, got {self.matcher!r}")
        if self.sift_encoding not in ("log", "srgb"):
            raise ValueError(f"sift_encoding must be log or srgb, got {self.sift_encoding!r}")
        if self.mapper not in ("auto", "incremental", "incremental_fixed", "global"):
            raise ValueError(f"mapper must be auto, incremental, incremental_fixed or global, got {self.mapper!r}")
        if self.min_registered < 3:
            raise ValueError(f"min_registered must be >= 3, got {self.min_registered}")
        if not 0 <= self.margin < 1 or not 0 <= self.bbox_percentile < 50:
            raise ValueError("margin must be in [0, 1) and bbox_percentile in [0, 50)")
        if self.mapping_trials < 1:
            raise ValueError(f"mapping_trials must be >= 1, got {self.mapping_trials}")


# ---------------------------------------------------------------------------------------------
# Inputs
# ---------------------------------------------------------------------------------------------
def _stems(linear_dir: Path) -> list[str]:
    stems = sorted(p.stem for p in linear_dir.glob("*.exr") if not p.name.startswith("."))
    if not stems:
        raise PoseError(f"{linear_dir}: no linear images (<stem>.exr); run the linearize stage first")
    return stems


def _linear_entries(linear_json: Path | None) -> dict[str, dict]:
    """Per-view metadata of ``linear.json`` keyed by stem (tolerant of list or dict layouts)."""
    if linear_json is None or not Path(linear_json).is_file():
        return {}
    try:
        data = json.loads(Path(linear_json).read_text())
    except json.JSONDecodeError as e:
        raise PoseError(f"{linear_json}: not valid JSON ({e}); rerun the linearize stage") from e
    items = None
    for key in ("images", "views", "frames"):
        if isinstance(data.get(key), (dict, list)):
            items = data[key]
            break
    out = {}
    if isinstance(items, dict):
        out = {Path(k).stem: v for k, v in items.items() if isinstance(v, dict)}
    elif isinstance(items, list):
        for v in items:
            if isinstance(v, dict):
                name = v.get("stem") or v.get("image") or v.get("source") or v.get("file")
                if name:
                    out[Path(str(name)).stem] = v
    return out


_FOCAL_KEYS = ("focal_length_px", "focal_px", "focal_length_pixels", "f_px")


def focal_prior(linear_json: Path | None, stems: list[str]) -> float | None:
    """Median focal length in pixels from ``linear.json`` when every view agrees within 1%."""
    entries = _linear_entries(linear_json)
    vals = []
    for s in stems:
        e = entries.get(s, {})
        v = next((e[k] for k in _FOCAL_KEYS if isinstance(e.get(k), (int, float)) and e[k] > 0), None)
        if v is not None:
            vals.append(float(v))
    if not vals:
        return None
    f = float(np.median(vals))
    if max(vals) > 1.01 * min(vals):
        log.warning("focal lengths differ between views (%.1f..%.1f px): no prior used", min(vals), max(vals))
        return None
    return f


def _image_names(linear_json: Path | None, stems: list[str]) -> dict[str, str]:
    """The capture image path (``images/<file>``) of each stem, as cameras.json records it."""
    entries = _linear_entries(linear_json)
    out = {}
    for s in stems:
        e = entries.get(s, {})
        name = next((e[k] for k in ("image", "source", "file") if isinstance(e.get(k), str)), None)
        if name is None:
            out[s] = f"images/{s}"
        else:
            out[s] = name if "/" in name else f"images/{name}"
    return out


def _read_masks(masks_dir: Path | None, stems: list[str]) -> dict[str, np.ndarray]:
    if masks_dir is None:
        return {}
    return {s: read_mask(Path(masks_dir) / f"{s}.png") for s in stems if (Path(masks_dir) / f"{s}.png").is_file()}


# ---------------------------------------------------------------------------------------------
# COLMAP
# ---------------------------------------------------------------------------------------------
def _feature_mask(rgb: np.ndarray, mask: np.ndarray | None, factor: float) -> np.ndarray | None:
    """Where SIFT may look: not on specular highlights (they move with the flash, so their
    matches describe no fixed surface point). None when nothing needs masking."""
    import cv2

    if factor <= 0:
        return None
    lum = rgb @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    region = mask if mask is not None and mask.any() else lum > 0
    if not region.any():
        return None
    hot = lum > factor * float(np.median(lum[region]))
    if not hot.any():
        return None
    r = max(2, int(round(0.01 * min(lum.shape))))
    hot = cv2.dilate(hot.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
    return hot == 0


def sift_image(rgb_linear: np.ndarray, encoding: str = "log") -> np.ndarray:
    """The 8-bit image SIFT sees, (H, W, 3) in [0, 1].

    ``srgb``: the sRGB encoding of the image scaled by its 99.5th percentile. ``log``: log
    luminance over four decades below the 99.5th percentile, as gray. With the light at the
    camera, shading (n . l / d^2) changes from view to view and is multiplicative; in log it
    becomes an additive, smooth term that SIFT's difference of Gaussians cancels, so keypoints
    sit at the same surface points in every view instead of drifting toward the lit side.
    """
    top = float(np.percentile(rgb_linear.max(axis=2), 99.5))
    top = max(top, 1e-12)
    if encoding == "srgb":
        return linear_to_srgb(rgb_linear / top)
    lum = rgb_linear @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    decades = 4.0
    g = (np.log10(np.maximum(lum / top, 10**-decades)) + decades) / decades
    return np.repeat(np.clip(g, 0.0, 1.0)[:, :, None], 3, axis=2)


def sift_upsample_factor(settings: PoseSettings, shape) -> int:
    """How much the SIFT images are enlarged: ``sift_upsample``, or with 0 (auto) 2 for images
    whose long side is under 400 px. Measured on a synthetic torus at 256 px (40 views): 38
    instead of 27 views registered, but ten times the matching time (78 s) and one view posed
    8 degrees off; on blobs it changed nothing that mattered. Hence off by default."""
    if settings.sift_upsample > 0:
        return int(settings.sift_upsample)
    return 2 if max(shape) < 400 else 1


def _write_sift_images(linear_dir: Path, stems: list[str], folder: Path, masks: dict | None = None,
                       mask_folder: Path | None = None, highlight_factor: float = 0.0,
                       encoding: str = "log", settings: PoseSettings | None = None
                       ) -> tuple[dict[str, tuple[int, int]], int]:
    """8-bit PNGs for SIFT (and COLMAP feature masks), enlarged by :func:`sift_upsample_factor`;
    returns the (H, W) of every view (at its own size) and the enlargement."""
    import cv2

    shapes = {}
    up = None
    for s in stems:
        try:
            img = read_exr(linear_dir / f"{s}.exr")
        except ImageError as e:
            raise PoseError(f"{e}; rerun the linearize stage") from e
        rgb = img[:, :, :3] if img.shape[2] >= 3 else np.repeat(img[:, :, :1], 3, axis=2)
        rgb = np.nan_to_num(np.maximum(rgb, 0.0))
        if masks and s in masks and masks[s].shape != img.shape[:2]:
            raise PoseError(f"mask of {s} is {masks[s].shape[::-1]} but {linear_dir / s}.exr is "
                            f"{img.shape[1::-1]}; rerun the masks stage")
        shapes[s] = img.shape[:2]
        if up is None:
            up = sift_upsample_factor(settings or PoseSettings(), img.shape[:2])
        big = cv2.resize(rgb, None, fx=up, fy=up, interpolation=cv2.INTER_CUBIC) if up > 1 else rgb
        write_png(folder / f"{s}.png", sift_image(np.maximum(big, 0.0), encoding))
        if mask_folder is not None:
            fm = _feature_mask(rgb, (masks or {}).get(s), highlight_factor)
            fm = np.ones(img.shape[:2], bool) if fm is None else fm
            if up > 1:
                fm = cv2.resize(fm.astype(np.uint8), None, fx=up, fy=up, interpolation=cv2.INTER_NEAREST) > 0
            write_mask(mask_folder / f"{s}.png.png", fm)
    sizes = set(shapes.values())
    if len(sizes) > 1:
        raise PoseError(
            f"{linear_dir}: the views have different sizes {sorted(sizes)}; one camera needs one "
            "image size (rotate or crop the photos consistently)"
        )
    return shapes, up


def verify_max_error(settings: PoseSettings, shape) -> float:
    """RANSAC threshold of the two-view verification. COLMAP's 4 px suits large photos; on
    small images it lets chance matches of repeated texture pass as verified pairs."""
    if settings.verify_max_error > 0:
        return float(settings.verify_max_error)
    return float(np.clip(0.004 * max(shape), 1.0, 4.0))


def _extract_and_match(db: Path, images: Path, n_views: int, settings: PoseSettings, f_prior, shape,
                       feature_masks: Path | None = None, max_features: int | None = None) -> dict:
    import pycolmap

    t0 = time.perf_counter()
    reader = pycolmap.ImageReaderOptions(camera_model=settings.camera_model)
    if feature_masks is not None:
        reader.mask_path = str(feature_masks)
    if f_prior is not None:
        cam = pycolmap.Camera.create_from_model_name(1, settings.camera_model, f_prior, shape[1], shape[0])
        reader.camera_params = ",".join(f"{v:.10g}" for v in cam.params)
    sift = pycolmap.SiftExtractionOptions(
        max_num_features=max_features or settings.max_num_features, peak_threshold=settings.peak_threshold,
        estimate_affine_shape=settings.affine_features, domain_size_pooling=settings.affine_features,
    )
    extraction = pycolmap.FeatureExtractionOptions(
        max_image_size=settings.max_image_size, num_threads=settings.num_threads, sift=sift
    )
    pycolmap.extract_features(
        db, images, camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
        extraction_options=extraction, device=pycolmap.Device.cpu,
    )
    t1 = time.perf_counter()
    matching = pycolmap.FeatureMatchingOptions(num_threads=settings.num_threads,
                                               guided_matching=settings.guided_matching)
    matching.sift.max_ratio = settings.max_ratio
    verification = pycolmap.TwoViewGeometryOptions(min_num_inliers=settings.min_num_inliers)
    verification.ransac.max_error = verify_max_error(settings, shape)
    verification.ransac.random_seed = settings.seed  # unseeded, the verified pairs change run to run
    kind = settings.matcher
    if kind == "auto":
        kind = "exhaustive" if n_views <= settings.exhaustive_max_views else "sequential"
    if kind == "exhaustive":
        pycolmap.match_exhaustive(db, matching_options=matching, verification_options=verification,
                                  device=pycolmap.Device.cpu)
    else:
        pairing = pycolmap.SequentialPairingOptions(overlap=settings.sequential_overlap, quadratic_overlap=True)
        pycolmap.match_sequential(db, matching_options=matching, pairing_options=pairing,
                                  verification_options=verification, device=pycolmap.Device.cpu)
    t2 = time.perf_counter()
    return {"matcher": kind, "extract_s": t1 - t0, "match_s": t2 - t1}


def _intrinsics_ok(rec, shape, f_prior: float | None = None) -> bool:
    """False for the drifted intrinsics an ill-conditioned start can produce: a focal length
    far from plausible (or 30% off the prior), or distortion beyond what lenses have."""
    cam = next(iter(rec.cameras.values()))
    f = cam.mean_focal_length()
    idx = list(cam.extra_params_idxs())
    extra = np.abs(np.asarray(cam.params)[idx]) if idx else np.zeros(0)
    ratio = f / max(shape)
    prior_ok = f_prior is None or abs(f / f_prior - 1.0) < 0.3
    return bool(0.2 < ratio < 8.0 and np.all(extra < 0.5) and prior_ok)


def silhouette_consistency(rec, masks: dict[str, np.ndarray], up: int = 1) -> float | None:
    """Fraction of (sparse point, registered view) pairs whose projection lands inside the
    view's mask, over projections inside the image; None without masks or points.

    Every point of the object projects inside the object's silhouette in every view, seen or
    occluded, so a right model scores near 1 whatever its track lengths. A model that is wrong
    as a whole (a mirrored or folded solution of a symmetric object: all views ~1 px off,
    rotations 50-140 degrees wrong) still reprojects its points onto their own features but
    not into the other views' silhouettes: on the demo capture right models scored 0.97-0.98,
    wrong ones 0.59-0.61. ``up``: the model is on images enlarged by this factor.
    """
    if not masks or rec.num_points3D() == 0:
        return None
    xyz = np.array([rec.point3D(p).xyz for p in rec.point3D_ids()]).reshape(-1, 3)
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
        keep = (x >= 0) & (x < m.shape[1]) & (y >= 0) & (y < m.shape[0])
        total += int(keep.sum())
        inside += int(m[y[keep], x[keep]].sum())
    return inside / total if total else None


def _mapper_sequence(settings: PoseSettings, has_prior: bool, n: int | None = None) -> list[str]:
    """Mapping trials in order. ``auto``: global (rotation averaging suits orbits around an
    object), incremental, incremental with the intrinsics held at the prior (stable where free
    intrinsics drift; the final refinement frees them, guarded by ``_intrinsics_ok``), then
    alternating again with new seeds. With a focal length prior (EXIF), the held-intrinsics
    mapper goes first: on small or weakly textured captures free intrinsics drifted in most
    trials (the demo: 3 of 4 trials "bogus intrinsics", f 6x the prior), the held ones never."""
    n = settings.mapping_trials if n is None else n
    if settings.mapper != "auto":
        return [settings.mapper] * n
    if has_prior:
        cycle = ["incremental_fixed", "global", "incremental", "incremental_fixed"]
    else:
        cycle = ["global", "incremental", "global", "incremental"]
    return [cycle[t % len(cycle)] for t in range(n)]


def _map(db: Path, images: Path, sparse_root: Path, settings: PoseSettings, n_views: int, shape,
         f_prior: float | None = None, masks: dict | None = None, up: int = 1) -> tuple:
    """Run mapping trials; return (best reconstruction, all models of that trial, trial log,
    trial index, views dropped as weak)."""
    import pycolmap

    best = None
    trials = []
    # up to twice the trials while no model is both plausible and consistent with the masks
    for trial, kind in enumerate(_mapper_sequence(settings, f_prior is not None, 2 * settings.mapping_trials)):
        if trial >= settings.mapping_trials and best is not None and best[0][0] and best[0][1]:
            break
        seed = settings.seed + trial
        pycolmap.set_random_seed(seed)
        out = sparse_root / f"trial{trial}"
        out.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        try:
            if kind == "global":
                opts = pycolmap.GlobalPipelineOptions(
                    num_threads=settings.num_threads, random_seed=seed, min_num_matches=settings.min_num_inliers
                )
                models = pycolmap.global_mapping(db, images, out, options=opts)
                if not models:  # its retriangulation step can fail on small images: keep the BA result
                    opts.mapper.skip_retriangulation = True
                    models = pycolmap.global_mapping(db, images, out, options=opts)
            else:
                opts = pycolmap.IncrementalPipelineOptions(
                    num_threads=settings.num_threads, random_seed=seed, min_num_matches=settings.min_num_inliers,
                    min_model_size=3,
                )
                opts.mapper.init_min_num_inliers = settings.init_min_num_inliers
                opts.mapper.abs_pose_min_num_inliers = settings.abs_pose_min_num_inliers
                opts.max_runtime_seconds = int(settings.max_mapping_seconds)
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
        weak = _drop_weak_views(models[0], settings.min_view_points) if models else {}
        n_reg = models[0].num_reg_images() if models else 0
        sane = bool(models) and _intrinsics_ok(models[0], shape, f_prior)
        sil = silhouette_consistency(models[0], masks or {}, up) if models else None
        consistent = sil is None or sil >= settings.min_silhouette_consistency
        trials.append({"mapper": kind, "seed": seed, "registered": n_reg, "weak_views_dropped": weak,
                       "models": [m.num_reg_images() for m in models], "intrinsics_ok": sane,
                       "silhouette_consistency": sil, "seconds": time.perf_counter() - t0})
        log.info("mapping trial %d (%s, seed %d): %d/%d views registered in the largest of %d model(s)%s%s",
                 trial, kind, seed, n_reg, n_views, len(models),
                 "" if sil is None else f", silhouette consistency {sil:.3f}",
                 "" if sane or not models else ", bogus intrinsics")
        score = (sane, consistent, n_reg, sil or 0.0)
        if models and (best is None or score > best[0]):
            best = (score, models[0], models, trial, weak)
        if sane and consistent and n_reg >= settings.accept_fraction * n_views:
            break
    if best is None:
        return None, [], trials, None, {}
    return best[1], best[2], trials, best[3], best[4]


def _rescale_model(rec, shape, up: int) -> None:
    """Scale a model found on ``up`` x enlarged images back to the images' (H, W) ``shape``."""
    for cam in rec.cameras.values():
        cam.rescale(int(shape[1]), int(shape[0]))
    for i in rec.reg_image_ids():
        for p in rec.images[i].points2D:
            p.xy = p.xy / up
    rec.update_point_3d_errors()


def _drop_weak_views(rec, min_points: int) -> dict[str, int]:
    """Deregister views posed from fewer than ``min_points`` 3D points (global mapping places
    views by rotation averaging even when no point supports them); returns stem -> points."""
    weak = {}
    for i in list(rec.reg_image_ids()):
        im = rec.images[i]
        if im.num_points3D < min_points:
            weak[Path(im.name).stem] = int(im.num_points3D)
            rec.deregister_frame(im.frame_id)
    return weak


def _refine(rec, settings: PoseSettings, shape, f_prior: float | None = None):
    """Final bundle adjustment with a robust (Cauchy) loss; returns (reconstruction, info).

    Wrong matches that survived verification (repeated texture, highlights) then pull much
    less on the poses. When the camera model has distortion parameters, a second adjustment
    with them fixed at 0 runs too, and wins unless distortion lowers the reprojection error by
    more than ``distortion_gain``: an object in the middle of the frame hardly constrains lens
    distortion, which then trades off against the focal length (seen in tests: f 13% off with
    k = -0.37 on distortion-free images).

    A candidate (``shape``: the images' (H, W)) whose intrinsics drift to implausible values
    (``_intrinsics_ok``) is rejected, even with the lower error: on the 192x144 demo a free
    adjustment once went from f = 264 px to f = 1552 px with k = -58 (error 0.43 -> 0.35 px),
    which undistorted every view into nonsense and emptied the visual hull. If no free
    candidate is plausible, the adjustment runs with the intrinsics held as mapped.
    """
    import pycolmap

    def adjust(r, refine_extra: bool, refine_focal: bool = True):
        ba = pycolmap.BundleAdjustmentOptions(print_summary=False, refine_extra_params=refine_extra,
                                              refine_focal_length=refine_focal)
        ba.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
        ba.ceres.loss_function_scale = settings.refine_loss_scale
        ba.ceres.solver_options.num_threads = settings.num_threads
        pycolmap.bundle_adjustment(r, ba)
        return float(r.compute_mean_reprojection_error())

    def plausible(r) -> bool:
        return _intrinsics_ok(r, shape, f_prior)

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
    if extra and settings.distortion_gain >= 0:
        plain = pycolmap.Reconstruction(rec)
        for c in plain.cameras.values():
            p = np.asarray(c.params, dtype=float).copy()
            p[extra] = 0.0
            c.params = p
        e_plain = adjust(plain, False)
        info["reprojection_error_no_distortion_px"] = e_plain
        if plausible(plain):
            if not candidates or e_plain <= candidates[0][2] * (1.0 + settings.distortion_gain):
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
    cam = next(iter(chosen.cameras.values()))
    info["distortion"] = name
    info["reprojection_error_after_px"] = e
    log.info("robust refinement: mean reprojection error %.3f -> %.3f px (distortion %s); camera %s %s",
             before, e, info["distortion"], cam.model_name, np.round(cam.params, 4).tolist())
    return chosen, info


def _unregistered_reasons(db_path: Path, stems: list[str], registered: set[str], settings: PoseSettings,
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
            if a in stem_of and b in stem_of and n >= settings.min_num_inliers:
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
                reasons[s] = (f"{nkp} features but no verified match (>= {settings.min_num_inliers} inliers) "
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
                              f"place it (needs >= {settings.abs_pose_min_num_inliers} 2D-3D inliers)")
        return reasons
    finally:
        db.close()


# ---------------------------------------------------------------------------------------------
# Undistortion
# ---------------------------------------------------------------------------------------------
def _undistort_maps(cam, pinhole):
    """cv2.remap maps (float32 (H', W')) from the pinhole image to the distorted one."""
    h, w = pinhole.height, pinhole.width
    j, i = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    pix = np.stack([j.ravel(), i.ravel()], axis=1)
    xy = pinhole.cam_from_img(pix)
    src = cam.img_from_cam(np.concatenate([xy, np.ones((len(xy), 1))], axis=1), check_cheirality=False)
    src = src.reshape(h, w, 2) - 0.5  # cv2 addresses pixel centers by integers
    return src[:, :, 0].astype(np.float32), src[:, :, 1].astype(np.float32)


def _remap(img: np.ndarray, maps) -> np.ndarray:
    import cv2

    out = cv2.remap(np.ascontiguousarray(img, dtype=np.float32), maps[0], maps[1], cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return out if out.ndim == 3 else out[:, :, None] if img.ndim == 3 else out


# ---------------------------------------------------------------------------------------------
# Object frame
# ---------------------------------------------------------------------------------------------
def _rotation_from_axes(z_up: np.ndarray, points: np.ndarray, first_center: np.ndarray) -> np.ndarray:
    """Rows x, y, z of the object frame in COLMAP coordinates."""
    z = z_up / np.linalg.norm(z_up)
    flat = points - points.mean(0)
    flat = flat - np.outer(flat @ z, z)
    cov = flat.T @ flat
    w, v = np.linalg.eigh(cov)
    x = v[:, -1]
    x = x - (x @ z) * z
    if np.linalg.norm(x) < 1e-9:  # degenerate: any horizontal direction
        x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    if x @ (first_center - points.mean(0)) < 0:
        x = -x
    y = np.cross(z, x)
    return np.stack([x, y, z])


def _hull_box(cams: CameraSet, masks: dict, center: np.ndarray, half: float, resolution: int):
    """Bounding box (lo, hi) of a coarse visual hull in a cube, or (None, why) if unusable."""
    from recon.init_mesh import Grid, silhouette_field

    grid = Grid.cube(center, half, resolution)
    field, _ = silhouette_field(cams, masks, grid, min_views=max(2, len(masks) // 4))
    occ = field > 0
    if occ.sum() < 8:
        return None, "empty"
    idx = np.argwhere(occ)
    if idx.min() == 0 or idx.max() == resolution - 1:
        return None, "touches the box"
    lo = grid.origin + grid.step * idx.min(0) - grid.step  # one voxel of slack each side
    hi = grid.origin + grid.step * idx.max(0) + grid.step
    return (lo, hi), "ok"


def object_frame(cams_colmap: CameraSet, points: np.ndarray, in_mask: np.ndarray, masks: dict,
                 settings: PoseSettings) -> tuple[Similarity, dict]:
    """Similarity COLMAP -> object frame (centered, inside [-1, 1]^3, z up); see the module doc."""
    centers = np.stack([c.center for c in cams_colmap])
    ups = np.stack([-c.world_to_camera[1, :3] for c in cams_colmap])  # -y of each camera
    z = ups.mean(0)
    if np.linalg.norm(z) < 1e-3:
        z = np.array([0.0, 0.0, 1.0])
    pts = points[in_mask] if in_mask.sum() >= 20 else points
    source = "sparse points in the masks" if in_mask.sum() >= 20 else "all sparse points (few inside the masks)"
    if len(pts) < 4:
        pts = centers  # nothing else to go by
        source = "camera centers"
    R = _rotation_from_axes(z, pts, centers[0])
    q = pts @ R.T
    p = settings.bbox_percentile
    lo, hi = np.percentile(q, p, axis=0), np.percentile(q, 100 - p, axis=0)
    info = {"box_source": source, "n_points": int(len(pts))}
    if settings.hull_resolution > 0 and len(masks) >= 2:
        c_box = R.T @ (0.5 * (lo + hi))
        half = float(np.max(hi - lo))  # a cube twice the sparse box's longest side
        rotated = _rotate_cameras(cams_colmap, Similarity(1.0, R, np.zeros(3)))
        for _ in range(2):
            box, why = _hull_box(rotated, masks, R @ c_box, half, settings.hull_resolution)
            if box is not None:
                lo, hi = box
                info["box_source"] = f"visual hull ({settings.hull_resolution}^3) of the masks"
                break
            if why == "empty":
                log.warning("coarse visual hull is empty: masks and cameras disagree; using the sparse box")
                break
            half *= 2.0
        else:
            log.warning("the visual hull reaches the box edge: masks may include background; using the sparse box")
    center = 0.5 * (lo + hi)
    extent = float(np.max(hi - lo))
    if extent <= 0:
        raise PoseError("the sparse reconstruction has no extent: cannot place the object")
    s = 2.0 * (1.0 - settings.margin) / extent
    sim = Similarity(s, R, -s * center)
    info.update({"box_lo": lo.tolist(), "box_hi": hi.tolist()})
    return sim, info


def _rotate_cameras(cams: CameraSet, sim: Similarity) -> CameraSet:
    """The same cameras in the frame x' = s R x + t (world_to_camera stays rigid)."""
    out = []
    for c in cams:
        W = c.world_to_camera
        R2 = W[:3, :3] @ sim.rotation.T
        t2 = sim.scale * W[:3, 3] - R2 @ sim.translation
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = R2, t2
        out.append(Camera(c.image, c.width, c.height, c.K.copy(), M))
    return CameraSet(tuple(out), cams.light_intensity, dict(cams.extra))


# ---------------------------------------------------------------------------------------------
# The stage
# ---------------------------------------------------------------------------------------------
def _link_or_copy(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def _passthrough(given: Path, linear_dir: Path, masks_dir: Path | None, tmp: Path) -> dict:
    try:
        cams = load_cameras(given)
    except CameraError as e:
        raise PoseError(f"{e} (fix the capture's cameras.json, or delete it to run SfM)") from e
    stems = set(_stems(linear_dir))
    for c in cams:
        exr = linear_dir / f"{c.stem}.exr"
        if c.stem not in stems:
            raise PoseError(f"{given}: camera for '{c.image}' but no linear image {exr}; the names must match images/")
        h, w = read_exr(exr).shape[:2]
        if (w, h) != (c.width, c.height):
            raise PoseError(f"{given}: '{c.image}' is {c.width}x{c.height} in cameras.json but the image is {w}x{h}")
        _link_or_copy(exr, tmp / "undistorted" / f"{c.stem}.exr")
        sat = linear_dir / f"{c.stem}.sat.png"
        if sat.is_file():
            _link_or_copy(sat, tmp / "undistorted" / f"{c.stem}.sat.png")
        if masks_dir is not None and (Path(masks_dir) / f"{c.stem}.png").is_file():
            _link_or_copy(Path(masks_dir) / f"{c.stem}.png", tmp / "undistorted" / "masks" / f"{c.stem}.png")
    shutil.copyfile(given, tmp / "cameras.json")
    missing = sorted(stems - {c.stem for c in cams})
    if missing:
        log.warning("views without a camera in %s are not used: %s", given, ", ".join(missing))
    return {"source": "given", "cameras": str(given), "registered": len(cams),
            "unregistered": {m: "no camera in cameras.json" for m in missing}}


def run_poses(
    linear_dir: str | os.PathLike,
    out_dir: str | os.PathLike,
    settings: PoseSettings = PoseSettings(),
    masks_dir: str | os.PathLike | None = None,
    linear_json: str | os.PathLike | None = None,
    given_cameras: str | os.PathLike | None = None,
) -> dict:
    """Recover (or pass through) the cameras of a capture; write the stage folder ``out_dir``.

    Parameters
    ----------
    linear_dir : the linearize stage's folder (``<stem>.exr``, ``<stem>.sat.png``).
    out_dir : ``results/<capture>/poses``; replaced atomically (nothing partial on error).
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
        ``min_registered_fraction`` of the views; the message lists every unregistered view
        with the reason and what to try.
    """
    linear_dir = Path(linear_dir)
    out_dir = Path(out_dir)
    t_start = time.perf_counter()
    with atomic_dir(out_dir) as tmp:
        if given_cameras is not None:
            diag = _passthrough(Path(given_cameras), linear_dir, Path(masks_dir) if masks_dir else None, tmp)
        else:
            diag = _sfm(linear_dir, tmp, settings, Path(masks_dir) if masks_dir else None,
                        Path(linear_json) if linear_json else None)
        diag["seconds"] = time.perf_counter() - t_start
        (tmp / "poses.json").write_text(json.dumps(diag, indent=1))
    return diag


def _sfm(linear_dir: Path, tmp: Path, settings: PoseSettings, masks_dir: Path | None,
         linear_json: Path | None) -> dict:
    import pycolmap

    timings = {}
    stems = _stems(linear_dir)
    n = len(stems)
    if n < settings.min_registered:
        raise PoseError(
            f"{linear_dir}: {n} view(s), but SfM needs at least {settings.min_registered} overlapping photos "
            f"(poses.min_registered = {settings.min_registered}); photograph the object from more sides "
            "(a view every 10-15 degrees), or provide cameras.json in the capture so SfM is skipped"
        )
    t0 = time.perf_counter()
    work = tmp / "work"
    images = work / "images"
    images.mkdir(parents=True)
    masks = _read_masks(masks_dir, stems)
    feature_masks = work / "feature_masks" if settings.highlight_factor > 0 else None
    shapes, up = _write_sift_images(linear_dir, stems, images, masks, feature_masks, settings.highlight_factor,
                                    settings.sift_encoding, settings)
    shape = shapes[stems[0]]
    timings["sift_images_s"] = time.perf_counter() - t0
    f_prior = focal_prior(linear_json, stems)
    log.info("SfM on %d views of %dx%d (SIFT on %dx enlarged images), focal prior %s", n, shape[1], shape[0],
             up, f"{f_prior:.1f} px" if f_prior else "none")
    # COLMAP works at the SIFT images' size; the model is scaled back after refinement
    f_sift = f_prior * up if f_prior else None
    shape_sift = (shape[0] * up, shape[1] * up)
    db = work / "database.db"
    timings.update(_extract_and_match(db, images, n, settings, f_sift, shape_sift, feature_masks,
                                      max_features=settings.max_num_features if up == 1
                                      else min(settings.max_num_features, settings.max_num_features_upsampled)))
    matcher = timings.pop("matcher")
    t0 = time.perf_counter()
    rec, models, trials, trial, weak = _map(db, images, work / "mapping", settings, n, shape_sift, f_sift, masks, up)
    timings["map_s"] = time.perf_counter() - t0

    registered = set()
    if rec is not None:
        registered = {Path(rec.images[i].name).stem for i in rec.reg_image_ids()}
    others = [sorted(Path(m.images[i].name).stem for i in m.reg_image_ids()) for m in models[1:]]
    reasons = _unregistered_reasons(db, stems, registered, settings, others)
    for s, k in weak.items():
        reasons[s] = (f"posed from only {k} 3D points (needs >= {settings.min_view_points}): too little "
                      "overlap with the other views")
    if len(registered) < settings.min_registered or len(registered) < settings.min_registered_fraction * n:
        lines = "\n".join(f"  {s}: {reasons[s]}" for s in sorted(reasons))
        split = f" The views split into separate models ({len(models)} models)." if len(models) > 1 else ""
        raise PoseError(
            f"{linear_dir.parent}: only {len(registered)} of {n} views could be registered by SfM "
            f"(need >= {settings.min_registered} and >= {settings.min_registered_fraction:.0%}).{split}\n"
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
    if settings.refine:
        rec, refinement = _refine(rec, settings, shape_sift, f_sift)
    if up > 1:
        _rescale_model(rec, shape, up)
    (tmp / "sparse").mkdir()
    rec.write(tmp / "sparse")

    # ---- undistortion to the pinhole camera ----
    t0 = time.perf_counter()
    colmap_cam = next(iter(rec.cameras.values()))
    pinhole = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), colmap_cam)
    fx, fy = pinhole.focal_length_x, pinhole.focal_length_y
    if abs(fx - fy) > 1e-6 * fx:  # models with two focal lengths: make pixels square
        raise PoseError(f"camera model {settings.camera_model} gave fx={fx:.2f} != fy={fy:.2f}; use "
                        "SIMPLE_RADIAL, RADIAL or SIMPLE_PINHOLE (square pixels)")
    maps = _undistort_maps(colmap_cam, pinhole)
    K = pinhole.calibration_matrix()
    und = tmp / "undistorted"
    names = _image_names(linear_json, stems)
    frames = []
    und_masks = {}
    by_stem = {Path(rec.images[i].name).stem: rec.images[i] for i in rec.reg_image_ids()}
    for s in sorted(by_stem):
        img = read_exr(linear_dir / f"{s}.exr")
        write_exr(und / f"{s}.exr", _remap(img, maps))
        sat = linear_dir / f"{s}.sat.png"
        if sat.is_file():
            write_mask(und / f"{s}.sat.png", _remap(read_mask(sat).astype(np.float32), maps) > 0)
        if s in masks:
            m = _remap(masks[s].astype(np.float32), maps) >= 0.5
            write_mask(und / "masks" / f"{s}.png", m)
            und_masks[s] = m
        W = np.eye(4)
        W[:3, :4] = by_stem[s].cam_from_world().matrix()
        frames.append(Camera(names[s], pinhole.width, pinhole.height, K.copy(), W))
    cams_colmap = CameraSet(tuple(frames), settings.light_intensity)
    timings["undistort_s"] = time.perf_counter() - t0

    # ---- object frame ----
    t0 = time.perf_counter()
    pids = list(rec.point3D_ids())
    xyz = np.array([rec.point3D(p).xyz for p in pids]).reshape(-1, 3)
    in_mask = np.zeros(len(pids), bool)
    if masks:
        for k, pid in enumerate(pids):
            votes = []
            for el in rec.point3D(pid).track.elements:
                im = rec.images[el.image_id]
                st = Path(im.name).stem
                if st in masks:
                    x, y = im.points2D[el.point2D_idx].xy
                    mm = masks[st]
                    i, j = int(y), int(x)
                    votes.append(0 <= i < mm.shape[0] and 0 <= j < mm.shape[1] and bool(mm[i, j]))
            in_mask[k] = bool(votes) and np.mean(votes) >= 0.5
    sim, frame_info = object_frame(cams_colmap, xyz, in_mask, und_masks, settings)
    cams = _rotate_cameras(cams_colmap, sim)
    cams = CameraSet(cams.frames, settings.light_intensity, {"colmap_to_object": sim.matrix.tolist()})
    timings["frame_s"] = time.perf_counter() - t0
    save_cameras(tmp / "cameras.json", cams)
    _write_points(tmp / "points.ply", sim.apply(xyz) if len(xyz) else xyz, in_mask)
    frame = {"colmap_to_object": sim.to_dict(), **frame_info,
             "note": "x_object = scale * rotation @ x_colmap + translation; sparse/ is in COLMAP's frame"}
    (tmp / "frame.json").write_text(json.dumps(frame, indent=1))

    mre = float(rec.compute_mean_reprojection_error())
    sil = silhouette_consistency(rec, masks)
    if sil is not None and sil < settings.min_silhouette_consistency:
        log.warning("only %.0f%% of the sparse points project inside the other views' masks (a right model: "
                    "> %.0f%%): the cameras and the masks disagree; either the masks miss parts of the object "
                    "(check results/<capture>/masks) or SfM found a wrong (e.g. mirrored) solution; more "
                    "texture on the object or a textured support helps SfM", 100 * sil,
                    100 * settings.min_silhouette_consistency)
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
        "camera": {"model": colmap_cam.model_name, "params": list(map(float, colmap_cam.params)),
                   "width": colmap_cam.width, "height": colmap_cam.height,
                   "focal_prior_px": f_prior},
        "pinhole": {"width": pinhole.width, "height": pinhole.height, "K": K.tolist()},
        "matcher": matcher,
        "sift_upsample": up,
        "mapper": settings.mapper,
        "trials": trials,
        "chosen_trial": trial,
        "refinement": refinement,
        "frame": frame,
        "timings": timings,
        "settings": asdict(settings),
    }
    log.info("registered %d/%d views, mean reprojection error %.3f px, %d points (%d in masks); %s",
             len(registered), n, mre, rec.num_points3D(), in_mask.sum(),
             ", ".join(f"{k} {v:.1f}" for k, v in timings.items()))
    return diag


def _write_points(path: Path, xyz: np.ndarray, flag: np.ndarray) -> None:
    """ASCII PLY of points with an ``in_mask`` property."""
    from recon.io.atomic import atomic_path

    lines = ["ply", "format ascii 1.0", f"element vertex {len(xyz)}", "property float x", "property float y",
             "property float z", "property uchar in_mask", "end_header"]
    lines += [f"{x:.6g} {y:.6g} {z:.6g} {int(f)}" for (x, y, z), f in zip(xyz, flag, strict=True)]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
