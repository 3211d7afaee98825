"""Masks of an object standing on a table: the object apart from the table and the background.

Flash-falloff masks (:mod:`recon.masks.falloff`) take everything the flash lights; on a table that
is the object and the table around it in one piece. Here the geometry of the capture separates
them, with no learned weights. The decision is made in 3D, by the views together:

1. **Where each view sees the table** (:func:`recon.masks.evidence.table_evidence`): pixels
   whose neighbouring views, warped by the homography the support plane induces, show the same
   texture (ZNCC of log luminance). Only positive evidence counts: a window without contrast
   (a plain glaze, a dark or dim region) or one that does not match says nothing, so an object
   whose colours, brightness or lack of texture resemble the table's is never called table for
   resembling it. (The former method called every pixel table whose plane-warped neighbours
   agreed with it, and a plain glaze agrees with itself wherever a warp lands on it: the lower
   half of a glazed bell, hidden behind the object from the neighbours, was lost; see
   docs/masks.md.) The sweep runs again at half the working size, and its table pixels count
   where the first leaves a window undecided: a table whose grain is wider than the windows
   looks smooth at the working size (docs/masks.md, "The sweep at two scales"). Those count
   in the 3D vote only; the outlines of step 3 keep the working size's evidence.
2. **A vote in 3D** (:func:`recon.masks.vote.carve`) on a grid standing on the plane: a voxel is
   empty when at least ``carve_votes`` views, and more than ``carve_fraction`` of the views that
   see it, see the table through it; views where it falls outside the frame abstain. What
   stays is the object's hull (the component holding the sparse points above the plane, else
   the one over the point the cameras aim at). Below the height where neighbouring views see
   too little parallax to tell the object's foot from the table (``band_parallax_px``), the hull
   is the extrusion of its section there: the object stands on the plane.
3. **Per view, the hull's silhouette refined by a graph cut** (:func:`recon.masks.graphcut.graph_cut`)
   at the photo's own size, in a band about the silhouette as wide as a few voxels: the
   silhouette is the prior, pixels that see the table say background, colour models of the
   object and the table (Gaussian mixtures of this view; the object's from the pixels the plane
   test sees differ from the table, and from the plain ones whose colour the table does not
   show) weigh in, and a contrast-sensitive smoothness term snaps the outline to the photo's
   edges. The cut also decides about patches where the view sees the table deep inside the
   silhouette: the table through a ring's hole, which the vote leaves closed where only the
   steep views see through it (:func:`refine_view`). The first sweep's table pixels count
   there, since the occlusion-aware sweep sees none through a hole that the hull fills.
4. **Cross-check** (:func:`cross_check`): a second hull voted from the cut masks, down to the
   plane (they are silhouettes: the band is no limit to them); each mask keeps what lies inside
   its projection, and a hole in a mask is filled where the hull of the other views is solid
   there (chance agreement with the table in one view), kept where the other views see through
   it too (the table through a mug's handle) (:func:`recon.masks.vote.hole_support`).

A view whose object cannot be separated from the table (an empty mask, a mask touching all four
image borders) is named in a :class:`SegmentError` with what to try.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from recon.io.cameras import CameraSet
from recon.masks.common import (MaskError, components_touching, dilate, display_image, erode, fill_holes_covered,
                                holes)
from recon.masks.evidence import (EvidenceSettings, log_luminance, plane_difference, resized, sweep_heights,
                                  table_evidence, unlit, window_stats, with_coarse, working_cameras)
from recon.masks.geometry import neighbours, parallax_band
from recon.masks.graphcut import colour_log_ratio, graph_cut
from recon.masks.shadow import ShadowSettings, shadow_direction, shadow_pixels, towards_foot
from recon.masks.vote import Hull, carve, hole_support
from recon.support import PlaneSettings, SupportPlane, aim_point, scene_scale

log = logging.getLogger(__name__)


class SegmentError(MaskError):
    """Masks that cannot be separated from the table; the message names the views and what to try."""


@dataclass(frozen=True)
class SegmentSettings:
    """Settings of the tabletop masks. Pixel lengths are at the working size of the evidence
    (``evidence.work_size``) unless named ``_full``; 3D lengths are fractions of the scene scale
    (the median camera distance)."""

    neighbours: int = 6  # views compared with each view (nearest viewing directions)
    min_angle: float = 4.0  # degrees: neighbours closer than this give too little parallax
    max_angle: float = 70.0  # degrees: ... farther than this see too different a table
    evidence: EvidenceSettings = field(default_factory=EvidenceSettings)
    band_parallax_px: float = 4.0  # below the height where neighbours see this parallax (about the evidence window), the
    # hull is extruded (object and table look alike there)
    unlit_fraction: float = 0.1  # the far background the flash misses is darker than this share of the lit table
    carve_votes: int = 3  # a voxel is empty when at least this many views see the table through it ...
    carve_fraction: float = 0.12  # ... and more than this share of the views that see it
    hull_resolution: int = 128  # voxels along the longest horizontal side of the fine hull
    prior: float = 1.0  # log-odds of the hull silhouette (inside: object) in the graph cut
    table_weight: float = 4.0  # log-odds against the object where the view sees the table
    difference: float = 0.7  # the pixel-sharp plane difference C: above this, object; below, table ...
    softness: float = 0.15  # ... with log-odds (C - difference) / this
    carve_difference: float = 0.4  # a textured pixel with C below this votes the voxels on its ray empty
    floor: float = 0.03  # noise floor of C, x the view's 90th percentile
    diff_window: int = 2  # radius of C's edge-following window (px at the working size)
    colour_weight: float = 0.5  # weight of the colour models' log-likelihood ratio ...
    foot_colour_weight: float = 1.0  # ... and at the foot, where nothing else tells the object from the table
    colour_novelty: float = 0.05  # a plain colour deep inside the silhouette is the object's when the table's colour
    # model explains it less than this share of the table's own pixels (graphcut.colour_log_ratio)
    smoothness: float = 2.0  # weight of the contrast-sensitive pairwise term
    hole_tolerance: float = 0.05  # cross-check: share of the other views' misses a voxel survives
    min_standing: float = 0.02  # the hull's silhouette holds at least this share of pixels unlike the table
    min_views: int = 4  # fewer views: no tabletop masks
    # up to this share of the views may fail (a mask that took the table): the other views' hull
    # stands in for them, with a warning; more is an error (the masks are not to be trusted)
    max_failed_views: float = 0.25
    plane: PlaneSettings = field(default_factory=PlaneSettings)
    triangulate_pairs: int = 3  # known cameras: match each view with this many neighbours
    shadow: ShadowSettings = field(default_factory=ShadowSettings)  # the flash's shadow beside the object

    def __post_init__(self):
        if isinstance(self.plane, dict):
            object.__setattr__(self, "plane", PlaneSettings(**self.plane))
        if isinstance(self.shadow, dict):
            object.__setattr__(self, "shadow", ShadowSettings(**self.shadow))
        if isinstance(self.evidence, dict):
            object.__setattr__(self, "evidence", EvidenceSettings(**self.evidence))
        if not 0.0 <= self.max_failed_views < 0.5:
            raise ValueError(f"max_failed_views must be in [0, 0.5), got {self.max_failed_views}")
        if self.neighbours < 1 or self.min_views < 2:
            raise ValueError("neighbours must be >= 1 and min_views >= 2")
        if not 0 <= self.min_angle < self.max_angle <= 180:
            raise ValueError(f"need 0 <= min_angle < max_angle <= 180, got {self.min_angle}, {self.max_angle}")
        if not 0 <= self.carve_fraction < 0.5 or self.carve_votes < 1:
            raise ValueError(f"carve_fraction must be in [0, 0.5) and carve_votes >= 1, got {self.carve_fraction}, "
                             f"{self.carve_votes}")
        if self.hull_resolution < 16:
            raise ValueError(f"hull_resolution must be >= 16, got {self.hull_resolution}")
        if self.prior < 0 or self.table_weight < 0 or self.colour_weight < 0 or self.smoothness < 0:
            raise ValueError("prior, table_weight, colour_weight and smoothness must be >= 0")
        if not 0 < self.colour_novelty < 1:
            raise ValueError(f"colour_novelty must be in (0, 1), got {self.colour_novelty}")


def _resize_mask(mask: np.ndarray, width: int, height: int) -> np.ndarray:
    import cv2

    if mask.shape == (height, width):
        return mask
    return cv2.resize(mask.astype(np.uint8), (width, height), interpolation=cv2.INTER_NEAREST) > 0


def _resize(x: np.ndarray, width: int, height: int) -> np.ndarray:
    import cv2

    if x.shape == (height, width):
        return x
    return cv2.resize(x, (width, height), interpolation=cv2.INTER_LINEAR)


def _footprint_px(cam, point: np.ndarray, length: float) -> float:
    """Pixels that ``length`` spans at ``point`` in ``cam``."""
    _, z = cam.project(np.asarray(point, float)[None])
    return float(length * 0.5 * (cam.K[0, 0] + cam.K[1, 1]) / max(float(z[0]), 1e-12))


def beyond_lit_table(cam, plane: SupportPlane, table: np.ndarray, foot: np.ndarray, share: float = 0.95
                     ) -> np.ndarray:
    """(H, W) bool at ``cam``'s size: the pixels whose ray misses the support plane, or meets it
    farther from ``foot`` than the table this view sees lit (the ``share`` quantile of the
    distances of its ``table`` pixels). Only there does a dark pixel see the far background: the
    flash at the camera lights the table nearer than that, so a dark pixel whose ray meets the
    plane there sees something dark in front of the lit table (a dark glaze), and says nothing.
    All True when the view sees too little table to tell."""
    from recon.masks.geometry import plane_points

    P, hit = plane_points(cam, plane)
    seen = table & hit
    if seen.sum() < 100:
        return np.ones(table.shape, bool)
    dist = np.linalg.norm(P - np.asarray(foot, float), axis=-1)
    return ~hit | (dist > float(np.quantile(dist[seen], share)))


def refine_view(rgb_linear: np.ndarray, silhouette: np.ndarray, table: np.ndarray, logodds: np.ndarray,
                low: np.ndarray, margin_px: int, settings: SegmentSettings = SegmentSettings(),
                seed: int = 0, table_deep: np.ndarray | None = None) -> np.ndarray:
    """Step 3 for one view: the object mask (H, W) bool from the hull's ``silhouette``, the pixels
    that see the ``table``, the pixel-sharp plane test as log-odds of the object ``logodds``
    (float, 0 where it says nothing) and the ``low`` region (the hull's extruded foot, where the
    table test cannot tell object from table), all (H, W) at the photo's size; the cut is
    confined to pixels within ``margin_px`` of the silhouette's outline, and of the patches where
    the view sees the table deep inside it (``table`` or ``table_deep``: pixels an earlier look saw
    as table, which count there only)."""
    from scipy import ndimage

    guide = display_image(rgb_linear)
    inner = erode(silhouette, margin_px) & ~low
    deep = np.zeros_like(inner)  # where the cut decides deep inside the silhouette
    # the table seen deep inside the silhouette (through a ring's hole the hull did not open): the
    # cut decides there too, within three bands' widths of a patch at least as wide as the band
    # about the outline (the plane test sees part of a hole's table; colours and edges find the rest)
    seen = (table if table_deep is None else table | table_deep) & inner
    if seen.any():
        labels, n = ndimage.label(seen)
        sizes = ndimage.sum_labels(seen, labels, index=np.arange(1, n + 1))
        patches = np.isin(labels, 1 + np.flatnonzero(sizes >= margin_px ** 2))
        if patches.any():
            table = table | patches
            deep = inner & dilate(patches, 3 * margin_px)
            inner &= ~deep
    active = dilate(silhouette, margin_px) | low | (silhouette & ~inner)
    z = np.where(silhouette, settings.prior, -settings.prior).astype(np.float64)
    z = z + np.where(low, 0.0, logodds)
    tab = table & ~low
    z = np.where(tab, np.minimum(z, -settings.table_weight), z)
    if settings.colour_weight > 0:
        ring = active & ~inner
        # the object's colours: where the plane test sees it differ from the table, and the plain
        # pixels (where the test says nothing) whose colour the table does not show
        llr = colour_log_ratio(guide, sure_fg=inner & ~table & (logodds > 0),
                               sure_bg=(dilate(silhouette, 3 * margin_px) & ~silhouette & ~low) | (active & tab),
                               where=ring, seed=seed, plain_fg=inner & ~table & (logodds == 0),
                               novelty=settings.colour_novelty)
        if llr is not None:
            # at the foot only the colours tell the object from the table
            z = z + np.where(low, settings.foot_colour_weight, settings.colour_weight) * llr
    z = np.clip(z, -30, 30)
    cost_fg = np.logaddexp(0.0, -z)  # -log sigmoid(z)
    cost_bg = np.logaddexp(0.0, z)
    cost_bg = np.where(inner, 1e6, cost_bg)  # deep inside the silhouette: object
    m = graph_cut(cost_fg, cost_bg, guide, settings.smoothness, active)
    if deep.any():
        # deep inside, only a hole the object encloses opens: a cut that reaches the outline from
        # there is chance evidence on the object (the dark far wall inside a bowl), not the table
        # seen through it
        m = m | (deep & ~holes(m))
    return components_touching(m, inner) if inner.any() else m


def cross_check(masks: list[np.ndarray], cams: CameraSet, plane: SupportPlane, hull: Hull, band: float,
                settings: SegmentSettings = SegmentSettings(), seeds: np.ndarray | None = None):
    """Step 4: the refined ``masks`` (one (H, W) bool per camera of ``cams``) cut to a second
    hull, carved from them in the box of the first ``hull``, and their holes filled where the
    other views' hull is solid (:func:`recon.masks.vote.hole_support`; ``band``: the parallax
    band, below which that hull is extruded). Returns the masks and the second hull (None when
    nothing survives its vote: the masks are returned as they came).

    The second hull is carved down to the plane: the refined masks are silhouettes, not the
    plane test, so they tell the object from the table below the band too. (Extruded from the
    band's top, as the first hull is, it cut off in every view whatever flares out below the
    band: the lip of a bell.)"""
    box_foot, box_half, box_height = hull.box_on(plane)
    box = (box_foot, box_half + 2 * hull.step, box_height + 2 * hull.step)
    framed = [np.where(m, 1, 0).astype(np.uint8) for m in masks]
    hull2 = carve(framed, cams, plane, *box, settings.hull_resolution, settings.carve_fraction,
                  seed_point=box_foot + 0.5 * box_height * plane.normal, seeds=seeds)
    if hull2 is None:
        return masks, None
    masks = [m & dilate(hull2.project(cam), 1) for m, cam in zip(masks, cams, strict=True)]
    with_holes = [i for i, m in enumerate(masks) if holes(m).any()]
    if with_holes:
        support = hole_support(masks, cams, plane, *box, settings.hull_resolution, settings.hole_tolerance,
                               band=band, views=with_holes)
        for i, s in support.items():
            masks[i] = fill_holes_covered(masks[i], s)
    return masks, hull2


def segment_tabletop(images: list[np.ndarray], cams: CameraSet, plane: SupportPlane,
                     settings: SegmentSettings = SegmentSettings(),
                     points: np.ndarray | None = None) -> tuple[list[np.ndarray], dict]:
    """Masks of the object standing on ``plane`` in every view (module docstring, steps 1-4).

    Parameters
    ----------
    images : list of (H, W, 3) float linear images, one per camera of ``cams``, pinhole.
    cams : the cameras (OpenCV axes) in the frame of ``plane``.
    points : (N, 3) sparse points in that frame (SfM's, or triangulated), optional: those standing
        above the plane mark the object's hull among the hull's components.

    Returns
    -------
    masks : list of (H, W) bool
    info : dict
        ``views`` (per view: coverage, share of pixels seen as table, hull coverage), ``hull``
        (voxel size, bounding box, height above the plane, the extrusion band), ``timings``.

    Raises
    ------
    SegmentError
        The object cannot be separated from the table (no hull, or views whose masks are empty
        or touch all four image borders); the message names the views and what to try.
    """
    t0 = time.perf_counter()
    n = len(cams)
    if len(images) != n:
        raise ValueError(f"segment_tabletop: {len(images)} images for {n} cameras")
    for img, cam in zip(images, cams, strict=True):
        if img.shape[:2] != (cam.height, cam.width):
            raise SegmentError(f"{cam.image}: image is {img.shape[1]}x{img.shape[0]} but its camera is "
                               f"{cam.width}x{cam.height}")
    ev = settings.evidence
    wcams = working_cameras(cams, ev.work_size)
    logs = [log_luminance(im, (w.width, w.height)) for im, w in zip(images, wcams, strict=True)]
    nbrs = neighbours(wcams, settings.neighbours, settings.min_angle, settings.max_angle)
    target = aim_point(cams)
    scale = scene_scale(cams, target)
    foot = plane.project(target)
    band = parallax_band(wcams, nbrs, foot, settings.band_parallax_px)
    heights = sweep_heights(band, 0.8 * scale)

    # the sweep again at a coarser working size, for the windows the first leaves undecided
    ccams = working_cameras(cams, ev.work_size // ev.coarse) if ev.coarse > 1 else None
    clogs = None if ccams is None else [log_luminance(im, (w.width, w.height))
                                        for im, w in zip(images, ccams, strict=True)]

    def sweep(previous=None, hidden=None, tolerance=0.0):
        """Per view (fine, coarse) evidence; ``previous``: an earlier call's (the raised planes kept)."""
        out = []
        for i in range(n):
            f = table_evidence(logs, wcams, plane, i, nbrs[i], heights, ev, hidden=None if hidden is None else hidden[0],
                               z_up=None if previous is None else previous[i][0]["z_up"], hidden_tolerance=tolerance)
            c = None if ccams is None else table_evidence(
                clogs, ccams, plane, i, nbrs[i], heights, ev, hidden=None if hidden is None else hidden[1],
                z_up=None if previous is None else previous[i][1]["z_up"], hidden_tolerance=tolerance)
            out.append((f, c))
        return out

    def table_pixels(evidence):
        """Per view the table pixels of the working size's sweep (pixel-sharp: they shape the
        outlines of step 3), and with the coarse sweep's added (they carve in the 3D vote only,
        where many views must agree: a coarse window reaches twice as far across an outline)."""
        fine = [f["table"] for f, _ in evidence]
        return fine, [t if c is None else with_coarse(f, c, ev.coarse_erode)
                      for t, (f, c) in zip(fine, evidence, strict=True)]

    # ---- step 1: where each view sees the table ----
    evidence = sweep()
    tables, carving = table_pixels(evidence)
    unlit_px = [unlit(im, t, settings.unlit_fraction, (w.width, w.height)) for im, t, w in zip(images, tables, wcams,
                                                                                              strict=True)]
    beyond = [beyond_lit_table(w, plane, t, foot) for t, w in zip(tables, wcams, strict=True)]
    dark = [u & b for u, b in zip(unlit_px, beyond, strict=True)]
    rgbs = [resized(im, (w.width, w.height)) for im, w in zip(images, wcams, strict=True)]
    textured = [window_stats(g, settings.diff_window)[1] >= ev.min_contrast for g in logs]

    def differences(hidden=None, tolerance=0.0):
        return [plane_difference(rgbs, wcams, plane, i, nbrs[i], settings.diff_window, settings.floor, hidden,
                                 tolerance) for i in range(n)]

    C = differences()
    timings = {"evidence_s": time.perf_counter() - t0}

    # ---- step 2: the vote in 3D, coarse then fine ----
    t1 = time.perf_counter()
    seeds = None
    if points is not None and len(points):
        p = np.asarray(points, float)
        h = plane.height(p)
        horiz = np.linalg.norm(plane.project(p) - foot, axis=1)
        seeds = p[(h > band) & (h < 0.8 * scale) & (horiz < 0.6 * scale)]
    kw = dict(tolerance=settings.carve_fraction, min_votes=settings.carve_votes, band=band, seeds=seeds,
              seed_point=foot + 0.05 * scale * plane.normal, standing=True)

    def vote(tables):  # 0: the view sees the voxel empty; 1: it may be object
        return [np.where(t | d | (x & (c <= settings.carve_difference)), 0, 1).astype(np.uint8)
                for t, d, x, c in zip(tables, dark, textured, C, strict=True)]

    hull = carve(vote(carving), wcams, plane, foot, 0.6 * scale, 0.8 * scale, max(32, settings.hull_resolution // 3),
                 **kw)
    if hull is None:
        raise SegmentError(
            "no object stands on the support plane: the views see the table everywhere around the point they "
            "aim at (views: " + ", ".join(c.stem for c in cams) + "). What to try: check that the object is in "
            "the middle of every photo, that the table is in focus and textured, or give masks/ in the capture")
    box_foot, box_half, box_height = hull.box_on(plane)
    pad = 3 * hull.step
    box = (box_foot, box_half + pad, box_height + pad)
    fine = carve(vote(carving), wcams, plane, *box, settings.hull_resolution, **kw)
    hull = fine if fine is not None else hull
    # the flash's shadow on the lit table beside the object, on the same side of the outline in
    # every view (recon.masks.shadow): table, in the votes below and in the graph cut
    shadow_info = {"found": False, "reason": "off"}
    if settings.shadow.enabled:
        sils = [hull.project(w) for w in wcams]
        near = [u & ~b for u, b in zip(unlit_px, beyond, strict=True)]
        down = towards_foot(wcams, box_foot, box_foot + 0.5 * box_height * plane.normal)
        direction, shadow_info = shadow_direction(near, sils, settings.shadow, down)
        shadow_info["found"] = direction is not None
        if direction is not None:
            cast = [shadow_pixels(d, s, direction, settings.shadow) for d, s in zip(near, sils, strict=True)]
            dark = [d | c for d, c in zip(dark, cast, strict=True)]
            shadow_info["share_of_silhouette"] = float(np.median([c.sum() / max(s.sum(), 1)
                                                                  for c, s in zip(cast, sils, strict=True)]))
            log.info("the flash's shadow beside the object: dark along the outlines towards (%.2f, %.2f) in the views' "
                     "pixels (resultant %.2f, %.0f%% of %d views agree), %.1f%% of the silhouette's area per view taken "
                     "for table", *direction, shadow_info["resultant"], 100 * shadow_info["agree"], shadow_info["views"],
                     100 * shadow_info["share_of_silhouette"])
        del sils, near
    # again, occlusion-aware: a neighbour counts where it sees the plane point past this hull
    hidden = ([hull.depth(w) for w in wcams], None if ccams is None else [hull.depth(w) for w in ccams])
    # the first sweep's table pixels: where this hull hides the plane from the neighbours (a ring's
    # hole it did not open), the occlusion-aware sweep below can see no table at all
    first_tables = tables
    evidence = sweep(evidence, hidden, 2 * hull.step)
    tables, carving = table_pixels(evidence)
    C = differences(hidden[0], 2 * hull.step)
    del evidence, hidden
    fine = carve(vote(carving), wcams, plane, *box, settings.hull_resolution, **kw)
    hull = fine if fine is not None else hull
    # something stands there only if the views see it: textured pixels in the hull's silhouette
    # that differ from the table (a bare table's leftovers of the vote hold none)
    seen_standing = []
    for w, c, x in zip(wcams, C, textured, strict=True):
        sil = hull.project(w) & ~hull.project(w, "band")
        seen_standing.append(float((x & (c > settings.difference))[sil].mean()) if sil.any() else 0.0)
    if np.median(seen_standing) < settings.min_standing:
        raise SegmentError(
            "no object stands on the support plane: what the views do not see as table differs from it nowhere "
            f"(median {100 * np.median(seen_standing):.2g}% of the hull's silhouette; views: "
            + ", ".join(c.stem for c in cams) + "). What to try: check that the object is in the middle of every "
            "photo, that the table is in focus and textured, or give masks/ in the capture")
    timings["hull_s"] = time.perf_counter() - t1

    # ---- step 3: per view, the silhouette refined at the photo's size ----
    t1 = time.perf_counter()
    masks, views = [], {}
    center = 0.5 * np.add(*hull.bbox())
    for i, cam in enumerate(cams):
        sil = hull.project(cam)
        low = hull.project(cam, "band") & ~hull.project(cam, "upper")
        table = _resize_mask(tables[i] | dark[i], cam.width, cam.height)
        c = np.where(np.isfinite(C[i]), C[i], settings.difference)
        logodds = np.where(textured[i], np.clip((c - settings.difference) / settings.softness,
                                                -settings.table_weight, settings.table_weight), 0.0)
        logodds = _resize(logodds.astype(np.float32), cam.width, cam.height)
        margin = int(np.clip(round(3 * _footprint_px(cam, center, hull.step) + 3), 4, 96))
        m = refine_view(images[i], sil, table, logodds, low, margin, settings, seed=i,
                        table_deep=_resize_mask(first_tables[i], cam.width, cam.height))
        masks.append(m)
        views[cam.stem] = {"hull_coverage": float(sil.mean()), "table_seen": float(tables[i].mean())}
    timings["refine_s"] = time.perf_counter() - t1

    # ---- step 4: cross-check with a hull of the refined masks ----
    t1 = time.perf_counter()
    masks, hull2 = cross_check(masks, cams, plane, hull, band, settings, seeds)
    timings["cross_check_s"] = time.perf_counter() - t1
    final = hull2 or hull
    bad = []

    def all_borders(m):
        return m[0].any() and m[-1].any() and m[:, 0].any() and m[:, -1].any()

    for i, (cam, m) in enumerate(zip(cams, masks, strict=True)):
        views[cam.stem]["coverage"] = float(m.mean())
        if not m.any():
            bad.append((i, f"{cam.stem}: empty mask"))
        elif all_borders(m) and not all_borders(final.project(cam)):
            # a close-up the object fills touches every border with the hull's silhouette too
            bad.append((i, f"{cam.stem}: the mask touches all four image borders"))
    if bad and len(bad) <= settings.max_failed_views * len(cams):
        # a few views failed: the other views' hull stands in for them (repairable, never a stop)
        for i, _ in bad:
            masks[i] = final.project(cams[i])
            views[cams[i].stem]["replaced_by_hull"] = True
        log.warning("the object could not be separated from the table in %d of %d views; their masks are the "
                    "silhouettes of the other views' hull (give masks/<stem>.png in the capture to do better):\n  %s",
                    len(bad), len(cams), "\n  ".join(b for _, b in bad))
    elif bad:
        raise SegmentError(
            "the object could not be separated from the table in these views:\n  " + "\n  ".join(b for _, b in bad)
            + "\nWhat to try: keep the whole object inside every photo with table around it, photograph from "
            "15-60 degrees above the table, use a textured table or a printed mat, or give masks/<stem>.png "
            "for these views in the capture")
    hb_lo, hb_hi = final.bbox()
    corners = np.array([[x, y, z] for x in (hb_lo[0], hb_hi[0]) for y in (hb_lo[1], hb_hi[1])
                        for z in (hb_lo[2], hb_hi[2])])
    info = {"views": views,
            "neighbours": {cams.frames[i].stem: [cams.frames[j].stem for j in nbrs[i]] for i in range(n)},
            "hull": {"step": final.step, "parallax_band": band, "voxels": int(len(final.points)),
                     "bbox_lo": hb_lo.tolist(), "bbox_hi": hb_hi.tolist(),
                     "height": float(plane.height(corners).max()),
                     "seeds": 0 if seeds is None else int(len(seeds))},
            "shadow": shadow_info,
            "timings": {**timings, "total_s": time.perf_counter() - t0}}
    return masks, info


__all__ = ["SegmentError", "SegmentSettings", "beyond_lit_table", "cross_check", "refine_view", "segment_tabletop"]
