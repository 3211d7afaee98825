"""Features and matching: the 8-bit images SIFT sees, COLMAP's SIFT extraction and matching.

SIFT runs on 8-bit PNGs of the linear views (:func:`sift_image`), without specular highlights
(feature masks: highlights move with the flash), with one shared camera and the EXIF focal
length as a prior. Matching is exhaustive up to ``exhaustive_max_views`` views, else
``ordered`` (:mod:`recon.poses.pairs`, :func:`matcher_kind`); the two-view RANSAC threshold
scales with the image (:func:`verify_max_error`).
"""

from __future__ import annotations

import sqlite3
import time
from pathlib import Path

import numpy as np

from recon.io.images import ImageError, linear_to_srgb, read_exr, write_mask, write_png
from recon.poses.settings import PoseError, PoseSettings


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
    8 degrees off; on blobs it changed nothing that mattered. Hence off by default; but a
    first pass on small photos that leaves views out is run again enlarged
    (``sift_upsample_retry``): on a noise-free 192 x 144 blob orbit (32 views) 24 -> 32 views
    registered and the pose errors halved (0.47 -> 0.25 degree), while on the noisy renders of
    the test captures the enlarged pass split the model (so it is kept only when it registers
    more views)."""
    if settings.features.sift_upsample > 0:
        return int(settings.features.sift_upsample)
    return 2 if max(shape) < 400 else 1


def write_sift_images(linear_dir: Path, stems: list[str], folder: Path, masks: dict | None = None,
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


LOW_PEAK_THRESHOLD = 0.001
"""SIFT's peak threshold on small images (long side under ``peak_threshold_size``): smooth,
flash-lit objects have little contrast, and COLMAP's 0.0067 finds too few features there."""
COLMAP_PEAK_THRESHOLD = 0.0067
"""COLMAP's default (0.02 / 3 octave levels), used on large images."""


def peak_threshold(settings: PoseSettings, shape) -> float:
    """SIFT's peak threshold for SIFT images of ``shape`` (H, W): ``settings.features.peak_threshold``, or
    with 0 :data:`LOW_PEAK_THRESHOLD` below ``peak_threshold_size`` px and COLMAP's 0.0067 from
    it. On the 33 real skull photos at 1600 px, 0.001 found 9-16k features per view (the
    8192 cap counts before orientations), mostly at the finest scales, where ISO 800 noise and
    the moving flash's shading change from view to view: 0.0067 kept 4.7k, registered as many
    views (guided matching: 32/33 against 27/33 for the 4096 largest at 0.001) and matched 2-4x
    faster (docs/sfm_speed.md)."""
    if settings.features.peak_threshold > 0:
        return float(settings.features.peak_threshold)
    return COLMAP_PEAK_THRESHOLD if max(shape) >= settings.features.peak_threshold_size else LOW_PEAK_THRESHOLD


def verify_max_error(settings: PoseSettings, shape) -> float:
    """RANSAC threshold of the two-view verification. COLMAP's 4 px suits large photos; on
    small images it lets chance matches of repeated texture pass as verified pairs."""
    if settings.matching.verify_max_error > 0:
        return float(settings.matching.verify_max_error)
    return float(np.clip(0.004 * max(shape), 1.0, 4.0))


def extract_and_match(db: Path, images: Path, n_views: int, settings: PoseSettings, f_prior, shape,
                      feature_masks: Path | None = None, max_features: int | None = None) -> dict:
    import pycolmap

    t0 = time.perf_counter()
    reader = pycolmap.ImageReaderOptions(camera_model=settings.camera.camera_model)
    if feature_masks is not None:
        reader.mask_path = str(feature_masks)
    if f_prior is not None:
        cam = pycolmap.Camera.create_from_model_name(1, settings.camera.camera_model, f_prior, shape[1], shape[0])
        reader.camera_params = ",".join(f"{v:.10g}" for v in cam.params)
    sift = pycolmap.SiftExtractionOptions(
        max_num_features=max_features or settings.features.max_num_features, peak_threshold=peak_threshold(settings, shape),
        estimate_affine_shape=settings.features.affine_features, domain_size_pooling=settings.features.affine_features,
    )
    extraction = pycolmap.FeatureExtractionOptions(
        max_image_size=settings.features.max_image_size, num_threads=settings.num_threads, sift=sift
    )
    pycolmap.extract_features(
        db, images, camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
        extraction_options=extraction, device=pycolmap.Device.cpu,
    )
    number_images_by_name(db)
    t1 = time.perf_counter()
    matching = pycolmap.FeatureMatchingOptions(num_threads=settings.num_threads,
                                               guided_matching=settings.matching.guided_matching)
    matching.sift.max_ratio = settings.matching.max_ratio
    verification = pycolmap.TwoViewGeometryOptions(min_num_inliers=settings.matching.min_num_inliers)
    verification.ransac.max_error = verify_max_error(settings, shape)
    verification.ransac.random_seed = settings.trial_seed()  # unseeded, the verified pairs change run to run
    kind = matcher_kind(settings, n_views)
    info = {}
    if kind == "exhaustive":
        pycolmap.match_exhaustive(db, matching_options=matching, verification_options=verification,
                                  device=pycolmap.Device.cpu)
    elif kind == "ordered":
        info = _match_ordered(db, n_views, settings, matching, verification)
    else:
        pairing = pycolmap.SequentialPairingOptions(overlap=settings.matching.sequential_overlap, quadratic_overlap=True)
        pycolmap.match_sequential(db, matching_options=matching, pairing_options=pairing,
                                  verification_options=verification, device=pycolmap.Device.cpu)
    t2 = time.perf_counter()
    info = {**info, "peak_threshold": peak_threshold(settings, shape), "guided_matching": settings.matching.guided_matching}
    return {"matcher": kind, "extract_s": t1 - t0, "match_s": t2 - t1, "matching": info}


_ID_OFFSET = 1_000_000_000  # above any image or frame id; COLMAP's ids stay below 2^31 - 1
_CAMERA_SENSOR = 0  # COLMAP's SensorType::CAMERA in frame_data and pose_priors


def number_images_by_name(db: Path) -> bool:
    """Give the database's images (and their frames) the ids 1, 2, ... in file-name order.

    COLMAP's extraction threads hand their images to the database writer in the order they
    finish, so with several threads two runs number the same photos differently (the demo: 0000
    and 0001 swapped in 4 of 6 runs with identical keypoints), and incremental mapping, which
    walks images by id, then grows another model: every view 0.007 degrees apart. After this the
    ids depend only on the photos. True when anything was renumbered."""
    con = sqlite3.connect(db)
    try:
        with con:
            rows = con.execute("SELECT image_id, name FROM images").fetchall()
            new = {old: k + 1 for k, (old, _) in enumerate(sorted(rows, key=lambda r: r[1]))}
            frames = dict(con.execute("SELECT data_id, frame_id FROM frame_data WHERE sensor_type = ?",
                                      (_CAMERA_SENSOR,)).fetchall())
            # a frame takes the new id of its first image (one image per frame: the same id)
            new_frame = {}
            for old_image in sorted(new, key=new.get):
                if old_image in frames and frames[old_image] not in new_frame:
                    new_frame[frames[old_image]] = len(new_frame) + 1
            if all(o == n for o, n in new.items()) and all(o == n for o, n in new_frame.items()):
                return False
            columns = (("images", "image_id", "", new), ("keypoints", "image_id", "", new),
                       ("descriptors", "image_id", "", new),
                       ("frame_data", "data_id", f" AND sensor_type = {_CAMERA_SENSOR}", new),
                       ("pose_priors", "corr_data_id", f" AND corr_sensor_type = {_CAMERA_SENSOR}", new),
                       ("frames", "frame_id", "", new_frame), ("frame_data", "frame_id", "", new_frame))
            for table, col, extra, mapping in columns:  # two passes: no id is ever taken twice at once
                for old, n in mapping.items():
                    con.execute(f"UPDATE {table} SET {col} = ? WHERE {col} = ?{extra}", (n + _ID_OFFSET, old))
                con.execute(f"UPDATE {table} SET {col} = {col} - ? WHERE {col} > ?{extra}", (_ID_OFFSET, _ID_OFFSET))
        return True
    finally:
        con.close()


def matcher_kind(settings: PoseSettings, n_views: int) -> str:
    """The matcher that runs: ``settings.matching.matcher``, or for ``auto`` exhaustive up to
    ``exhaustive_max_views`` views (few pairs: every pair is cheap insurance) and ``ordered``
    beyond (see :mod:`recon.poses.pairs`; it falls back to exhaustive when the order does not
    hold)."""
    if settings.matching.matcher != "auto":
        return settings.matching.matcher
    return "exhaustive" if n_views <= settings.matching.exhaustive_max_views else "ordered"


def _image_ids(db) -> list[int]:
    """The database's image ids in capture (file name) order."""
    images = sorted(db.read_all_images(), key=lambda im: im.name)
    return [im.image_id for im in images]


def _verified_pairs(db, index: dict[int, int], min_inliers: int) -> set[tuple[int, int]]:
    import pycolmap

    pair_ids, inliers = db.read_two_view_geometry_num_inliers()
    out = set()
    for pid, k in zip(pair_ids, inliers, strict=True):
        a, b = pycolmap.pair_id_to_image_pair(pid)
        if k >= min_inliers and a in index and b in index:
            out.add((min(index[a], index[b]), max(index[a], index[b])))
    return out


def _match_list(db_path: Path, pairs, ids: list[int], names: dict[int, str], matching, verification,
                name: str = "pairs.txt") -> None:
    """Match and verify the view pairs (i, j) (indices into ``ids``) through COLMAP."""
    import pycolmap

    pairs_file = Path(db_path).parent / name
    pairs_file.write_text("".join(f"{names[ids[i]]} {names[ids[j]]}\n" for i, j in sorted(pairs)))
    pycolmap.match_image_pairs(db_path, matching_options=matching,
                               pairing_options=pycolmap.ImportedPairingOptions(match_list_path=str(pairs_file)),
                               verification_options=verification, device=pycolmap.Device.cpu)


def _read_verified(db_path: Path, ids: list[int], min_inliers: int) -> set[tuple[int, int]]:
    import pycolmap

    db = pycolmap.Database.open(db_path)
    try:
        return _verified_pairs(db, {i: k for k, i in enumerate(ids)}, min_inliers)
    finally:
        db.close()


def _match_ordered(db_path: Path, n_views: int, settings: PoseSettings, matching, verification) -> dict:
    """The ``ordered`` matcher (:mod:`recon.poses.pairs`): neighbours in capture order with
    wrap-around, plus the most similar views by retrieval. When the verified pairs leave the
    views in separate groups, up to ``bridge_rounds`` rounds of the pairs most likely to join
    them (:func:`~recon.poses.pairs.bridge_pairs`), then, if groups remain, every pair between
    the groups (:func:`~recon.poses.pairs.cross_group_pairs`); exhaustive for the rest only
    when the files are not in capture order. Returns what was matched."""
    import logging

    import pycolmap

    from recon.poses.pairs import (bridge_pairs, cross_group_pairs, groups, in_capture_order, ordered_matching_ok,
                                   ordered_pairs, retrieval_pairs, similarity)

    logger = logging.getLogger(__name__)
    t0 = time.perf_counter()
    db = pycolmap.Database.open(db_path)
    try:
        ids = _image_ids(db)
        names = {im.image_id: im.name for im in db.read_all_images()}
        seq = ordered_pairs(len(ids), settings.matching.ordered_neighbors, wrap=True)
        descriptors = [np.asarray(db.read_descriptors(i).data) for i in ids]
    finally:
        db.close()
    sim = similarity(descriptors, seed=settings.trial_seed())  # retrieval, and the bridges between groups
    loops = retrieval_pairs(descriptors, settings.matching.retrieval_neighbors, exclude=seq, sim=sim)
    pairs = seq | loops
    t1 = time.perf_counter()
    _match_list(db_path, pairs, ids, names, matching, verification)
    matched = set(pairs)
    verified = _read_verified(db_path, ids, settings.matching.min_num_inliers)
    ok, why = ordered_matching_ok(len(ids), verified)
    info = {"pairs": len(pairs), "ordered_pairs": len(seq), "retrieval_pairs": len(loops),
            "retrieval_s": t1 - t0, "verified_pairs": len(verified), "order_check": why,
            "bridges": [], "cross_group_pairs": 0, "exhaustive_fallback": False}
    if ok:
        return info
    if not in_capture_order(len(ids), verified):
        logger.warning("ordered matching: %s; matching the remaining pairs exhaustively", why)
        info["exhaustive_fallback"] = True
        pycolmap.match_exhaustive(db_path, matching_options=matching, verification_options=verification,
                                  device=pycolmap.Device.cpu)
        return info
    for r in range(settings.matching.bridge_rounds):
        parts = groups(len(ids), verified)
        if len(parts) == 1:
            break
        new = bridge_pairs(parts, sim, exclude=matched, per_group_pair=settings.matching.bridge_pairs * (r + 1),
                           window=settings.matching.bridge_window + r)
        if not new:
            break
        _match_list(db_path, new, ids, names, matching, verification, f"bridge{r}.txt")
        matched |= new
        verified = _read_verified(db_path, ids, settings.matching.min_num_inliers)
        left = groups(len(ids), verified)
        info["bridges"].append({"groups": [len(g) for g in parts], "pairs": len(new),
                                "verified": len(new & verified), "groups_after": [len(g) for g in left]})
        logger.info("ordered matching: %d groups of %s views; %d bridging pairs (%d verified) leave %d group(s)",
                    len(parts), [len(g) for g in parts], len(new), len(new & verified), len(left))
    parts = groups(len(ids), verified)
    if len(parts) > 1:
        rest = cross_group_pairs(parts, exclude=matched)
        logger.warning("ordered matching: the views are still in %d groups (%s views); matching the %d pairs "
                       "between them", len(parts), [len(g) for g in parts], len(rest))
        if rest:
            _match_list(db_path, rest, ids, names, matching, verification, "cross_groups.txt")
            matched |= rest
            verified = _read_verified(db_path, ids, settings.matching.min_num_inliers)
        info["cross_group_pairs"] = len(rest)
    info["pairs"] = len(matched)
    info["verified_pairs"] = len(verified)
    info["groups_left"] = [len(g) for g in groups(len(ids), verified)]
    return info
