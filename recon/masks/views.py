"""Masks with cameras: the support plane, then tabletop masks on it (:mod:`recon.masks.tabletop`),
or flash-falloff masks (:mod:`recon.masks.falloff`) when nothing stands on a plane; given masks
(:mod:`recon.masks.given`) win view by view.

The poses stage calls :func:`run_view_masks` (also named ``run_tabletop_masks``) on its undistorted views, cameras and sparse
points; a capture with its own ``cameras.json`` gets the same through ``run_masks(..., cameras=)``.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import time
from collections.abc import Collection
from dataclasses import asdict
from pathlib import Path

import numpy as np

from recon.io.atomic import atomic_dir
from recon.io.cameras import Camera, CameraSet, load_cameras
from recon.io.images import ImageError, read_exr, read_mask, write_mask
from recon.io.mesh import read_points
from recon.masks.common import MaskError
from recon.masks.consistent import ConsistentSettings, consistent_derived
from recon.masks.falloff import MaskSettings, derive_mask
from recon.masks.given import fit_given_mask
from recon.masks.plain import PlainSettings, plain_table_masks
from recon.masks.points import triangulate_points
from recon.masks.tabletop import SegmentError, SegmentSettings, segment_tabletop
from recon.support import FOOT_RADIUS, TABLE_TOLERANCE, camera_spread, fit_support_plane, save_plane, table_points

log = logging.getLogger(__name__)

__all__ = ["SegmentError", "SegmentSettings", "run_tabletop_masks", "run_view_masks"]


def _cameras_at_image_size(cams: CameraSet, images: list[np.ndarray], source) -> CameraSet:
    """A capture's cameras.json at the photos' size for linear views that linearize reduced
    (``linearize.max_size``): K scaled per axis (image edges stay at 0 and W); MaskError for any
    other size mismatch."""
    frames = []
    for cam, img in zip(cams, images, strict=True):
        h, w = img.shape[:2]
        if (w, h) == (cam.width, cam.height):
            frames.append(cam)
            continue
        s = max(w, h) / max(cam.width, cam.height)
        if not (s < 1 and (max(1, round(cam.width * s)), max(1, round(cam.height * s))) == (w, h)):
            raise MaskError(f"{source}: '{cam.image}' is {cam.width}x{cam.height} but its image is {w}x{h}")
        K = cam.K.copy()
        K[0] *= w / cam.width
        K[1] *= h / cam.height
        frames.append(Camera(cam.image, w, h, K, cam.world_to_camera.copy()))
    return dataclasses.replace(cams, frames=tuple(frames))


def table_points_share(points: np.ndarray | None, plane, cams: CameraSet, masks: dict[str, np.ndarray],
                       tolerance: float = TABLE_TOLERANCE, foot: float = FOOT_RADIUS) -> float | None:
    """The share of the table's points (``points`` within ``tolerance`` of the cameras' spread of
    ``plane``, and with ``foot`` > 0 further than ``foot`` of it from the object's foot:
    :func:`recon.support.table_points`) that fall inside the views' ``masks``, over every view whose
    frame they fall in (in front of it). Masks of an object on a table hold only those the object
    hides; masks that took the table hold most. None with fewer than 20 such points."""
    if points is None:
        return None
    pts = np.asarray(points, float).reshape(-1, 3)
    spread = camera_spread([c.center for c in cams])
    pts = pts[table_points(pts, plane, tolerance * spread, foot * spread)]
    if len(pts) < 20:
        return None
    inside = total = 0
    for cam in cams:
        m = masks.get(cam.stem)
        if m is None:
            continue
        xy, z = cam.project(pts)
        j, i = np.floor(xy[:, 0]), np.floor(xy[:, 1])
        ok = np.isfinite(xy).all(1) & (z > 0) & (j >= 0) & (j < m.shape[1]) & (i >= 0) & (i < m.shape[0])
        inside += int(m[i[ok].astype(int), j[ok].astype(int)].sum())
        total += int(ok.sum())
    return inside / total if total else None


def refuse_masks_holding_the_table(points: np.ndarray | None, plane, cams: CameraSet, masks: dict[str, np.ndarray],
                                   max_share: float = 0.7, registered: str = "") -> float | None:
    """The last check of masks made when a plane was found in the ``points`` but neither the
    tabletop masks nor the plain table's model could be used: the flash-falloff masks take
    everything the flash lights, and on a lit, textured table that is the table around the object
    too. Masks holding more than ``max_share`` of the table's points in the views' frames
    (:func:`table_points_share`) are not masks of an object, and every later stage would make an
    asset of the table (a plain box on a wooden table by SfM: 87 % of the table's points inside
    them, final accuracy 0.44 of the object's size, exported as a success): a :class:`MaskError`
    that says what to do. ``registered`` is said in the message (e.g. how many views SfM
    registered). Returns the share (None: too few table points to tell).

    Unlike the tabletop masks' check, this one counts the object's foot on the plane as the
    table's (``foot=0``): it is the last check before masks of the lit table become an asset, and
    where SfM found almost no table points but the foot's (a bell in 1600-px photos: 11 of 97),
    leaving the foot out would leave nothing to check, and masks of the table would pass."""
    share = table_points_share(points, plane, cams, {s: np.asarray(m) > 0.5 for s, m in masks.items()}, foot=0.0)
    if share is not None and share > max_share:
        raise MaskError(
            f"the masks hold the table: {100 * share:.0f}% of the table's points fall inside them in the views' "
            "frames (the masks of an object on a table hold only those it hides: 10-36 % measured). A table was found "
            "in the points, but neither the tabletop masks (the table's texture, seen in 3D by several views) nor the "
            "flash falloff (everything the flash lights, here the table around the object too) could tell the object "
            f"from it{registered}. What to try: give masks/<stem>.png in the capture (white: the object) for every "
            "view; or photograph the object on a plain dark cloth or a printed mat, with texture on the object and a "
            "photo every 10-15 degrees all around it")
    return share


def run_view_masks(
    image_dir: str | os.PathLike,
    cameras: str | os.PathLike,
    out_dir: str | os.PathLike,
    settings: SegmentSettings | None = None,
    points: str | os.PathLike | None = None,
    given_dir: str | os.PathLike | None = None,
    mask_settings: MaskSettings | None = None,
    given_stems: Collection[str] | None = None,
    consistent_settings: ConsistentSettings | None = None,
    plain_settings: PlainSettings | None = None,
    max_table_in_masks: float = 0.7,
) -> dict:
    """Write ``out_dir/<stem>.png`` (object masks), ``out_dir/masks.json`` and, when a support
    plane is found, ``out_dir/plane.json`` (:mod:`recon.support`, in the frame of ``cameras``).

    Parameters
    ----------
    image_dir : the pinhole linear views ``<stem>.exr`` the cameras describe: ``poses/undistorted``
        after SfM, or the linearize stage's folder when the capture gives cameras.json.
    cameras : that ``cameras.json``.
    out_dir : replaced atomically.
    points : a PLY of sparse points in the frame of ``cameras`` (``poses/points.ply``); without
        it, points are triangulated from the views (:func:`triangulate_points`).
    given_dir : the capture's ``masks/``: ``<stem>.png`` there wins over the derived mask.
    given_stems : only these views' masks in ``given_dir`` count as given (e.g. after SfM,
        ``poses/undistorted/masks`` holds every view's mask of the masks stage; the views whose
        ``masks.json`` source is ``given`` are the capture's own).
    mask_settings : the flash-falloff masks' settings, used when no plane is found.
    consistent_settings : the vote that makes those masks consistent across the views
        (:mod:`recon.masks.consistent`).
    max_table_in_masks : tabletop masks holding more than this share of the table's points
        (:func:`table_points_share`) took the table and are not used: the object is then taken as
        in the void (a plain desk with a few points on it: the plain table's model follows). The masks of
        an object on a table hold 14-47 % of those away from its foot (the points the object hides
        from low views; ten captures of session 28), a vase's
        masks that took a plain desk 97 %.
    plain_settings : the model of a plain table (:mod:`recon.masks.plain`), whose pixels are taken
        out of the flash-falloff masks when no plane is found in the points but the photos show
        the object on a plain table.

    Returns
    -------
    The summary written to ``masks.json``: per view ``source`` (given | tabletop | derived) and
    ``coverage``; ``plane`` (found, reason, ...); ``method``; ``segment`` (diagnostics).
    """
    settings = SegmentSettings() if settings is None else settings
    t0 = time.perf_counter()
    mask_settings = MaskSettings() if mask_settings is None else mask_settings
    image_dir = Path(image_dir)
    cams = load_cameras(cameras)
    images = []
    for cam in cams:
        path = image_dir / f"{cam.stem}.exr"
        try:
            images.append(read_exr(path))
        except ImageError as e:
            raise MaskError(f"{e}; rerun the stage that writes {image_dir}") from e
    cams = _cameras_at_image_size(cams, images, cameras)
    given = {}
    if given_dir is not None:
        for cam in cams:
            p = Path(given_dir) / f"{cam.stem}.png"
            if p.is_file() and (given_stems is None or cam.stem in given_stems):
                given[cam.stem] = fit_given_mask(read_mask(p), p, (cam.width, cam.height))
    # the plane is looked for even when every view has a given mask: the later stages use it
    plane, plane_info, pts = None, {"found": False}, None
    if len(cams) < settings.min_views:
        plane_info = {"found": False, "reason": f"{len(cams)} views (need >= {settings.min_views})"}
    else:
        if points is not None:
            pts = read_points(points)
            plane_info_source = f"sparse points {points}"
        else:
            pts = triangulate_points(images, cams, settings.triangulate_pairs)
            plane_info_source = "points triangulated from the views with the known cameras"
        plane, plane_info = fit_support_plane(pts, cams, settings.plane)
        plane_info["source"] = plane_info_source
    masks: dict[str, np.ndarray] = {}
    views: dict[str, dict] = {}
    seg_info = None
    refused = None  # the plane the tabletop masks were refused on
    if plane is not None and len(given) == len(cams):
        log.info("support plane found (%s): %s; every view has a given mask", plane_info["source"],
                 plane_info["reason"])
        method = "given"
    elif plane is not None:
        log.info("support plane found (%s): %s", plane_info["source"], plane_info["reason"])
        derived, seg_info = segment_tabletop(images, cams, plane, settings, points=pts)
        share = table_points_share(pts, plane, cams, dict(zip([c.stem for c in cams], derived, strict=True)))
        if share is not None and share > max_table_in_masks:
            # the tabletop masks took the table (a plain desk with a few points on it: they need its
            # texture); as the poses stage does with SfM's observations, they are not used
            log.warning("a plane was found in the points, but the tabletop masks hold %.0f%% of the table's points in "
                        "the views' frames (masks of an object on a table hold only those it hides: 14-47 %% measured): they "
                        "took the table and are "
                        "not used; the object is taken as in the void", 100 * share)
            refused, plane, plane_info = plane, None, {
                **plane_info, "found": False, "reason": f"the tabletop masks hold {100 * share:.0f}% of the table's points"}
        else:
            for cam, m in zip(cams, derived, strict=True):
                masks[cam.stem] = m
                views[cam.stem] = {"source": "tabletop", **seg_info["views"][cam.stem]}
            method = "tabletop"
    if plane is None:
        if len(given) < len(cams):
            log.info("no support plane (%s): masks from the flash falloff, as for an object in the void "
                     "(recon.masks)", plane_info.get("reason"))
        plain = None
        if pts is not None and len(given) < len(cams):
            by_stem = {c.stem: im for c, im in zip(cams, images, strict=True)}
            plain, plane_info["plain_table"] = plain_table_masks(pts, by_stem.__getitem__, cams, set(given),
                                                                 plain_settings or PlainSettings())
        for cam, img in zip(cams, images, strict=True):
            if cam.stem in given:
                continue
            if plain is not None and cam.stem in plain:
                masks[cam.stem] = plain[cam.stem]
                views[cam.stem] = {"source": "derived_plain_table", "coverage": float(plain[cam.stem].mean())}
                continue
            try:
                m, inf = derive_mask(img, mask_settings)
            except MaskError as e:
                raise MaskError(f"no object found in {image_dir / cam.stem}.exr: {e} (or provide "
                                f"masks/{cam.stem}.png in the capture)") from e
            masks[cam.stem] = m
            views[cam.stem] = {"source": "derived", **inf}
        method = "flash_falloff" if plain is None else "flash_falloff_plain_table"
        # every view's mask, given or derived, votes; only the derived ones change
        fixed, seg_info = consistent_derived({**masks, **given}, cams, set(given),
                                             consistent_settings or ConsistentSettings())
        if seg_info.get("applied"):
            method += "_consistent"
            for stem, v in seg_info["views"].items():
                masks[stem] = fixed[stem]
                views[stem].update(v)
            log.info("flash-falloff masks made consistent across %d views (hull voxel %.3g)", len(cams),
                     seg_info["step"])
        else:
            log.info("flash-falloff masks kept view by view: %s", seg_info.get("reason"))
        if refused is not None and plain is None and len(given) < len(cams):
            plane_info["table_points_share_falloff"] = refuse_masks_holding_the_table(
                pts, refused, cams, {**masks, **given}, max_table_in_masks)
    for stem, m in given.items():
        masks[stem] = m
        views[stem] = {"source": "given", "coverage": float(m.mean())}
    with atomic_dir(out_dir) as tmp:
        for cam in cams:
            write_mask(tmp / f"{cam.stem}.png", masks[cam.stem])
        if plane is not None:
            bbox = {} if seg_info is None or "hull" not in seg_info else {
                "object_bbox": {"lo": seg_info["hull"]["bbox_lo"], "hi": seg_info["hull"]["bbox_hi"]}}
            save_plane(tmp / "plane.json", plane, source=plane_info["source"], **bbox)
        summary = {"method": method, "views": {c.stem: views[c.stem] for c in cams}, "plane": plane_info,
                   "segment": None if seg_info is None or method != "tabletop" else
                   {k: v for k, v in seg_info.items() if k != "views"},
                   "consistent": {k: v for k, v in seg_info.items() if k != "views"}
                   if seg_info is not None and method.startswith("flash_falloff") else None,
                   "settings": asdict(settings), "seconds": time.perf_counter() - t0}
        (tmp / "masks.json").write_text(json.dumps(summary, indent=1, default=float))
    return summary


run_tabletop_masks = run_view_masks
"""The former name of :func:`run_view_masks` (the poses stage calls it so)."""
