"""Flash-falloff masks made consistent across the views, for an object without a support plane
(an object in the void, or on a stand), once the cameras are known.

One view's flash-falloff mask (:mod:`recon.masks.falloff`) errs in two ways, and the other views
correct both:

- **It cuts the object's dark parts**: a concavity or a shadow the flash barely lights (a
  skull's eye sockets and palate, the shade under a jaw) falls below the threshold and leaves a
  hole or a notch in the mask. The other views see the same 3D region inside their silhouettes:
  the hull voted from the *other* views' masks (leave-one-out, :func:`recon.masks.vote.hole_support`)
  covers it, and a hole or notch of the mask that this hull covers, and that the mask encloses
  (most of its outline borders the mask), is filled. A real opening (a handle) is seen through
  by other views too, which carve it from that hull: it stays open.
- **It cuts the object's outline**: the surfaces seen at grazing angles are lit at grazing angles,
  so a rim along the outline falls below the threshold (more so in a room whose lit wall raises
  the background's level), and a rim borders the background, so it is no notch. The other views
  see those surfaces face-on and lit: their leave-one-out hull covers the rim, and each mask
  takes that hull's silhouette shrunk by a voxel's footprint (``rim``; the hull is strict: a
  voxel stays only where all but ``hole_tolerance`` of the other views hold it in their masks).
- **It takes lit background**: a lamp, a lit wall or a table in the room touching the object's
  outline. No 3D region is inside most views' masks there: the hull voted from all views
  (:func:`recon.masks.vote.carve`: a voxel goes when more than ``tolerance`` of the views that
  see it put it outside their masks; views whose frame it leaves abstain) does not reach it,
  and each mask keeps what lies inside the hull's silhouette.

A stand under the object is kept where most of the views that see it hold it in their masks
(the flash lights a pole the object stands on as much as the object), and left out where they
do not (a base the views from above see apart from the object); every view gets what the vote
decided. The hull's grid stands on a plane across the cameras' mean up direction (no table is
needed; the object is not extruded down to it).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from recon.io.cameras import CameraSet
from recon.masks.common import dilate, erode, fill_holes_covered, holes
from recon.masks.evidence import working_cameras
from recon.masks.vote import carve, hole_support
from recon.support import SupportPlane, aim_point, scene_scale

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ConsistentSettings:
    """The vote of :func:`consistent_masks`."""

    tolerance: float = 0.25  # a voxel goes when more than this share of the views that see it say outside
    # (on the real skull 0.1 cut the teeth, which several views' flash-falloff masks miss)
    hole_tolerance: float = 0.05  # leave-one-out hulls: the share of the other views' misses a voxel survives
    enclosed: float = 0.6  # a notch is filled when at least this share of its outline borders the mask
    resolution: int = 128  # voxels along the longest side of the fine grid
    work_size: int = 800  # long side of the masks the vote reads
    min_views: int = 6  # fewer views: the masks stay as they are
    rim: bool = True  # each mask takes the other views' (strict) hull's silhouette, shrunk by a voxel's footprint
    # the vote is refused (the masks stay as they are) when the median view keeps less than this
    # share of its mask: the masks do not agree on one object (a dark, patterned object whose
    # masks are full of notches in most views), and masks cut to their hull are worse than each
    # view's own. Measured (SfM's cameras): median kept 0.994-1.000 on the skull, the demo,
    # stand-blob, wood-blob and stand-blob in the void, whose masks the vote mends; 0.000 on a
    # dark vase on a stand (IoU against the truth 0.41 -> 0.03); 0.85 on views of a torus each
    # cut by 12 random notches (tests/test_masks.py: IoU 0.66 -> 0.54)
    min_kept: float = 0.9
    # a refused vote is taken again among the views that agree (:func:`agreeing_views`): a mask
    # agrees when its IoU with the silhouette of the hull a bare majority votes (a voxel goes when
    # more than ``consensus_tolerance`` of the views say outside) is at least ``agreement`` times
    # the views' upper quartile; at least ``min_agreeing`` of the views must (0: no second vote)
    consensus_tolerance: float = 0.45
    agreement: float = 0.75
    min_agreeing: float = 1 / 3

    def __post_init__(self):
        if not 0 <= self.tolerance < 0.5 or not 0 <= self.hole_tolerance < 0.5:
            raise ValueError("tolerance and hole_tolerance must be in [0, 0.5)")
        if not 0 < self.enclosed <= 1 or self.resolution < 16 or self.min_views < 3:
            raise ValueError("enclosed must be in (0, 1], resolution >= 16, min_views >= 3")
        if not 0 <= self.min_kept <= 1:
            raise ValueError(f"min_kept must be in [0, 1], got {self.min_kept}")


def _resize_mask(mask: np.ndarray, width: int, height: int) -> np.ndarray:
    import cv2

    if mask.shape == (height, width):
        return mask
    return cv2.resize(mask.astype(np.float32), (width, height), interpolation=cv2.INTER_AREA) >= 0.5


def _footprint(cam, hull) -> int:
    """Pixels of a voxel's splat radius in ``cam`` at the hull's centre (:meth:`recon.masks.vote.Hull.project`)."""
    lo, hi = hull.bbox()
    _, z = cam.project(0.5 * (lo + hi)[None])
    f = 0.5 * (cam.K[0, 0] + cam.K[1, 1])
    return int(np.clip(np.ceil(0.5 * np.sqrt(3.0) * hull.step * f / max(float(z[0]), 1e-12)), 1, 64))


def fill_enclosed(mask: np.ndarray, support: np.ndarray, enclosed: float) -> np.ndarray:
    """``mask`` with the components of ``support & ~mask`` (less any rim thinner than 5 px) added
    whose outline borders the mask for at least the share ``enclosed`` (a notch or hole the mask
    surrounds), and the holes ``support`` covers."""
    from scipy import ndimage

    cand = support & ~mask
    # a hull's silhouette overlaps the mask's outline by a thin rim all round: open it away, so
    # that a notch is not one piece with the rim
    cand = dilate(erode(cand, 2), 2) & cand
    if cand.any():
        labels, n = ndimage.label(cand)
        ring = dilate(cand, 1) & ~cand
        # per component: its outline pixels (each given to the nearest component), how many are mask
        idx = ndimage.distance_transform_edt(~cand, return_distances=False, return_indices=True)
        owner = labels[idx[0], idx[1]]
        total = np.bincount(owner[ring], minlength=n + 1)
        inside = np.bincount(owner[ring & mask], minlength=n + 1)
        keep = np.flatnonzero((total > 0) & (inside >= enclosed * np.maximum(total, 1)))
        keep = keep[keep > 0]
        if len(keep):
            mask = mask | np.isin(labels, keep)
    return fill_holes_covered(mask, support) if holes(mask).any() else mask


def consistent_masks(masks: list[np.ndarray], cams: CameraSet, settings: ConsistentSettings = ConsistentSettings(),
                     trusted: frozenset[int] | set[int] = frozenset(), warn_refused: bool = True
                     ) -> tuple[list[np.ndarray], dict]:
    """The masks (one (H, W) bool per camera of ``cams``) made consistent across the views (module
    docstring); ``warn_refused``: say so when the vote is refused (:func:`warn_refusal`; a caller
    with another way to try says it itself). Returns the masks and ``info`` (per view the share of pixels added and removed,
    the hull's voxel size and bounding box); with fewer than ``min_views`` views the masks come
    back unchanged.

    When the vote of all views is refused (``min_kept``), the views that agree are found
    (:func:`agreeing_views`) and the vote is taken again among them (``trusted`` views, the
    capture's own masks, always count as agreeing); the others take the hull's silhouette.
    """
    n = len(cams)
    if n < settings.min_views:
        return [m.copy() for m in masks], {"applied": False, "reason": f"{n} views (need >= {settings.min_views})"}
    wcams = working_cameras(cams, settings.work_size)
    small = [_resize_mask(m, w.width, w.height) for m, w in zip(masks, wcams, strict=True)]
    values = [m.astype(np.uint8) for m in small]
    out, info = _vote(masks, cams, wcams, values, list(range(n)), settings)
    if info.get("applied"):
        return out, info
    voters = agreeing_views(values, wcams, settings, trusted) if settings.agreement > 0 else None
    out2, info2 = out, info
    if voters is not None and len(voters) < n:
        out2, info2 = _vote(masks, cams, wcams, values, voters, settings)
    if not info2.get("applied"):
        if "median_kept" in info and warn_refused:
            warn_refusal(info)
        return out, info
    outliers = [cams.frames[i].stem for i in range(n) if i not in set(voters)]
    log.warning("flash-falloff masks: %d of %d views disagree with the others (%s): those views take the silhouette "
                "of the hull the other %d voted (median kept %.0f%%)", len(outliers), n,
                ", ".join(outliers[:12]) + (", ..." if len(outliers) > 12 else ""), len(voters),
                100 * info2["median_kept"])
    return out2, {**info2, "outliers": outliers, "all_views_median_kept": info.get("median_kept")}


def warn_refusal(info: dict) -> None:
    """The warning for a vote that was refused (``info`` of :func:`consistent_masks`)."""
    log.warning("flash-falloff masks not made consistent: %s. The object is probably darker than what lies "
                "behind it in many views (a dark object before a lit wall or floor): give masks/<stem>.png in "
                "the capture, or photograph it with nothing lit behind it", info["reason"])


def agreeing_views(values: list[np.ndarray], wcams: CameraSet, settings: ConsistentSettings,
                   trusted: frozenset[int] | set[int] = frozenset()) -> list[int] | None:
    """The indices of the views whose masks agree with the hull a bare majority of the views
    votes (``consensus_tolerance``): IoU of the mask with that hull's silhouette at least
    ``agreement`` times the upper quartile of the views' IoUs. None when fewer than
    ``min_views`` and than ``min_agreeing`` of the views agree, or no majority hull exists.

    A dark object before a lit floor: the flash-falloff masks of a third of the views take the
    floor or the stand's base, not the object. No 3D region is inside their masks and the
    others' at once, so a vote over all views that tolerates a quarter of misses carves the
    object away; a bare majority keeps it, and the views that took something else stand out
    by their small overlap with its silhouette.
    """
    target, half, ground = _first_box(wcams)
    hull = carve(values, wcams, ground, target, half, 2 * half, 48, settings.consensus_tolerance, seed_point=target)
    if hull is None:
        return None
    iou = []
    for v, w in zip(values, wcams, strict=True):
        m, p = v > 0, hull.project(w)
        iou.append(float((m & p).sum()) / max(float((m | p).sum()), 1.0))
    bar = settings.agreement * float(np.percentile(iou, 75))
    voters = [i for i, a in enumerate(iou) if a >= bar or i in trusted]
    if len(voters) < max(settings.min_views, settings.min_agreeing * len(values)):
        return None
    return voters


def _first_box(cams: CameraSet) -> tuple[np.ndarray, float, SupportPlane]:
    """The coarse hull's box: the point the cameras aim at, a half size of 0.6 of the scene scale,
    and the floor that far below it across the cameras' mean up."""
    target = aim_point(cams)
    half = 0.6 * scene_scale(cams, target)
    up = cams.up()
    return target, half, SupportPlane.through(target - half * up, up)


def _vote(masks, cams, wcams, values, voters: list[int], settings: ConsistentSettings) -> tuple[list[np.ndarray], dict]:
    """:func:`consistent_masks`' vote among the views ``voters``; the other views take the hull's
    silhouette (shrunk by a voxel's footprint)."""
    target, half, ground = _first_box(cams)
    up = cams.up()  # as the floor's (unnormalised again: the same bits as before)

    def floor_under(center, h):
        return SupportPlane.through(np.asarray(center) - h * up, up)

    vcams = CameraSet(tuple(wcams.frames[i] for i in voters), wcams.light_intensity)
    vvalues = [values[i] for i in voters]
    coarse = carve(vvalues, vcams, ground, target, half, 2 * half, 48, settings.tolerance, seed_point=target)
    if coarse is None:
        return [m.copy() for m in masks], {"applied": False, "reason": "the views' masks share no 3D region"}
    lo, hi = coarse.bbox()
    center = 0.5 * (lo + hi)
    extent = 0.5 * float(np.max(hi - lo)) + 2 * coarse.step
    ground = floor_under(center, extent)
    box = (center, extent, 2 * extent)
    hull = carve(vvalues, vcams, ground, *box, settings.resolution, settings.tolerance, seed_point=center)
    if hull is None:
        return [m.copy() for m in masks], {"applied": False, "reason": "the fine hull vanished"}
    others = hole_support(vvalues, vcams, ground, *box, settings.resolution, settings.hole_tolerance)
    others = {voters[k]: v for k, v in others.items()}
    out, views = [], {}
    for i, (cam, w) in enumerate(zip(cams, wcams, strict=True)):
        m = masks[i]
        silhouette = hull.project(w)
        if i in others:
            keep = _resize_mask(dilate(silhouette, 1), cam.width, cam.height)
            support = _resize_mask(others[i], cam.width, cam.height)
            new = fill_enclosed(m, support, settings.enclosed)
            if settings.rim:
                # the silhouette of the voxels' centres: the splats reach a footprint beyond them
                new = new | _resize_mask(erode(others[i], _footprint(w, hull)), cam.width, cam.height)
            new = new & keep
        else:  # a view that disagrees with the others: its mask is the hull's silhouette
            new = _resize_mask(erode(silhouette, _footprint(w, hull)), cam.width, cam.height)
        views[cam.stem] = {"added": float((new & ~m).mean()), "removed": float((m & ~new).mean()),
                           "kept": float((new & m).sum() / max(int(m.sum()), 1))}
        out.append(new)
    lo, hi = hull.bbox()
    kept = float(np.median([views[cams.frames[i].stem]["kept"] for i in voters]))
    if kept < settings.min_kept:
        reason = (f"the views' masks do not agree on one object: their voted hull keeps a median {100 * kept:.0f}% "
                  f"of each mask (needs >= {100 * settings.min_kept:.0f}%)")
        return [m.copy() for m in masks], {"applied": False, "median_kept": kept, "reason": reason}
    return out, {"applied": True, "views": views, "step": hull.step, "bbox_lo": lo.tolist(), "bbox_hi": hi.tolist(),
                 "median_kept": kept}


def consistent_derived(masks: dict[str, np.ndarray], cams: CameraSet, given: set[str] | frozenset = frozenset(),
                       settings: ConsistentSettings = ConsistentSettings(), warn_refused: bool = True
                       ) -> tuple[dict[str, np.ndarray], dict]:
    """:func:`consistent_masks` over every view's mask (``masks`` by stem, one per camera), where
    the capture's own masks (``given``) vote but never change. Returns the masks by stem and
    ``info``, whose ``views`` hold the changed (derived) views only."""
    fixed, info = consistent_masks([masks[c.stem] for c in cams], cams, settings,
                                   trusted={i for i, c in enumerate(cams) if c.stem in given}, warn_refused=warn_refused)
    if not info.get("applied"):
        return dict(masks), info
    out = {c.stem: masks[c.stem] if c.stem in given else m for c, m in zip(cams, fixed, strict=True)}
    return out, {**info, "views": {s: v for s, v in info["views"].items() if s not in given}}
