"""Free space seen through the visual hull: SfM's observations carve the concavities that no
silhouette can (the inside of a bowl: the visual hull puts a dome over it; docs/init_mesh.md).

A 3-D point that a view observed is visible from that view: the segment from the camera's centre
to the point crosses empty space. Where such segments pass through the visual hull, the hull
holds space the photos saw through. No silhouette can carve a concavity (every view sees past
it), but the points SfM triangulated on a concavity's floor are seen through the hull over it.

SfM's points are sparse; the photos' own depth maps inside the hull (:mod:`recon.mvs`, a plane
sweep) add many more where the surface has texture, and carve the same way.

The pieces (the init_mesh stage puts them together, :func:`carve_hull`, with :func:`seen_points`):

- :func:`free_space_counts`: per voxel of the hull's grid, how many distinct points' segments
  cross it; each segment stops ``stop_voxels`` short of its point (the point's own error, and
  the surface it lies on).
- :func:`carve`: the voxels to remove, from the hull's surface inwards and only while removing
  one keeps the topology (:func:`is_simple`): a concavity is carved, never a hole or a tunnel.
- :func:`carved_field`: the hull's distance field with them outside, its zero level set midway
  between carved and kept voxels.

Measured (docs/init_mesh.md): of the hull voxels a bowl's 6,600 observations cross, 0.1 % lie
inside the bowl, against 37 % of the hull that is not the bowl. Wrong points (a reflection of
the table in a glaze, a bad match) are few and scattered; their segments are thin streaks, which
the stage's opening of the free space drops.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass

import numpy as np

from recon.hull import Grid
from recon.io.cameras import CameraSet

log = logging.getLogger(__name__)


def free_space_counts(centers: np.ndarray, points: np.ndarray, view: np.ndarray, point: np.ndarray,
                      grid: Grid, inside: np.ndarray, stop_voxels: float = 2.0,
                      chunk: int = 4096) -> np.ndarray:
    """(R, R, R) int32: per voxel inside the hull, how many distinct points' segments cross it.

    ``centers`` (V, 3) the cameras' centres; ``points`` (P, 3); observation m is point
    ``point[m]`` seen from view ``view[m]``. Segments are sampled every half voxel from the
    camera to ``stop_voxels`` voxels before the point; only the part inside the grid counts."""
    r = grid.resolution
    step = float(grid.step)
    n_pts = len(points)
    if n_pts == 0 or len(view) == 0:
        return np.zeros((r, r, r), np.int32)
    # in voxel index units (index = (world - origin) / step)
    C = (np.asarray(centers, np.float64)[view] - grid.origin) / step
    X = (np.asarray(points, np.float64)[point] - grid.origin) / step
    d = X - C
    length = np.linalg.norm(d, axis=1)
    ok = length > stop_voxels + 1.0
    C, d, length, pid = C[ok], d[ok], length[ok], np.asarray(point)[ok]
    u = d / length[:, None]
    # clip each segment to the grid's box [-0.5, r - 0.5]^3 (slab test)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(np.abs(u) > 1e-12, 1.0 / u, np.inf)
        t0 = (-0.5 - C) * inv
        t1 = (r - 0.5 - C) * inv
    tmin = np.nanmax(np.where(np.isfinite(inv), np.minimum(t0, t1), -np.inf), axis=1).clip(0.0)
    tmax = np.minimum(np.nanmin(np.where(np.isfinite(inv), np.maximum(t0, t1), np.inf), axis=1),
                      length - stop_voxels)
    live = tmax > tmin
    C, u, tmin, tmax, pid = C[live], u[live], tmin[live], tmax[live], pid[live]
    flat_inside = inside.ravel()
    keys = []
    n = np.ceil((tmax - tmin) / 0.5).astype(np.int64) + 1
    for s in range(0, len(C), chunk):
        e = min(len(C), s + chunk)
        ns = n[s:e]
        rows = np.repeat(np.arange(s, e), ns)
        k = np.arange(int(ns.sum())) - np.repeat(np.cumsum(ns) - ns, ns)
        t = np.minimum(tmin[rows] + 0.5 * k, tmax[rows])
        q = np.rint(C[rows] + t[:, None] * u[rows]).astype(np.int64)
        good = np.all((q >= 0) & (q < r), axis=1)
        lin = (q[good, 0] * r + q[good, 1]) * r + q[good, 2]
        rows = rows[good]
        hit = flat_inside[lin]
        keys.append(lin[hit] * n_pts + pid[rows[hit]])
    keys = np.unique(np.concatenate(keys)) if keys else np.zeros(0, np.int64)
    counts = np.bincount(keys // n_pts, minlength=r**3).astype(np.int32)
    return counts.reshape(r, r, r)


_OFFSETS26 = [(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1) if (a, b, c) != (0, 0, 0)]
_N6 = np.zeros((3, 3, 3), bool)
_N6[1, 1, :] = _N6[1, :, 1] = _N6[:, 1, 1] = True
_N6[1, 1, 1] = False
_N18 = np.ones((3, 3, 3), bool)
_N18[::2, ::2, ::2] = False  # the 8 corners
_N18[1, 1, 1] = False
_S26 = np.ones((3, 3, 3), bool)
_S6 = np.zeros((3, 3, 3), bool)
_S6[1, 1, :] = _S6[1, :, 1] = _S6[:, 1, 1] = True


def is_simple(cube: np.ndarray) -> bool:
    """Whether the centre of the (3, 3, 3) boolean neighbourhood ``cube`` (True: object) is a
    simple point for the (6, 26) connectivity pair: the object's neighbours in its
    18-neighbourhood that are 6-adjacent to it form one 6-connected component there, and the
    empty voxels of its 26-neighbourhood one 26-connected component. The object counts as
    6-connected because marching cubes joins two voxels that touch only along an edge or at a
    corner no more than the empty space between them: carved with the (26, 6) pair, a bowl's
    hull kept its voxel topology and its surface had genus 1,675."""
    from scipy import ndimage

    empty = ~cube
    empty[1, 1, 1] = False
    lab, n_empty = ndimage.label(empty, structure=_S26)
    if n_empty != 1:
        return False
    obj = cube & _N18
    lab, n = ndimage.label(obj, structure=_S6)
    if n == 0:
        return False
    touching = set(np.unique(lab[_N6 & obj]).tolist()) - {0}
    return len(touching) == 1


def topology6(obj: np.ndarray) -> tuple[int, int, int]:
    """The object's components (6-connected), the empty space's (26-connected, the outside
    counted) and the Euler characteristic of the (6, 26) pair (voxels - face-adjacent pairs +
    full 2x2 squares - full 2x2x2 cubes): equal for two voxel sets of the same topology."""
    from scipy import ndimage

    o = np.pad(np.asarray(obj, bool), 1)
    v = int(o.sum())
    e = int((o[1:] & o[:-1]).sum() + (o[:, 1:] & o[:, :-1]).sum() + (o[:, :, 1:] & o[:, :, :-1]).sum())
    f = int((o[1:, 1:] & o[:-1, 1:] & o[1:, :-1] & o[:-1, :-1]).sum()
            + (o[1:, :, 1:] & o[:-1, :, 1:] & o[1:, :, :-1] & o[:-1, :, :-1]).sum()
            + (o[:, 1:, 1:] & o[:, :-1, 1:] & o[:, 1:, :-1] & o[:, :-1, :-1]).sum())
    c = int((o[1:, 1:, 1:] & o[:-1, 1:, 1:] & o[1:, :-1, 1:] & o[1:, 1:, :-1] & o[:-1, :-1, 1:] & o[:-1, 1:, :-1]
             & o[1:, :-1, :-1] & o[:-1, :-1, :-1]).sum())
    return ndimage.label(o, structure=_S6)[1], ndimage.label(~o, structure=_S26)[1], v - e + f - c


def carve(inside: np.ndarray, free: np.ndarray, depth: np.ndarray | None = None) -> np.ndarray:
    """The voxels of ``inside`` (bool (R, R, R)) to remove: those marked ``free`` that are
    reachable from the empty space through other removed voxels, each removed only while it is
    a simple point (:func:`is_simple`), so the object's topology is kept. Of the reachable ones
    the deepest by ``depth`` goes first (the hull's distance field; None: the distance to the
    empty space): the carving dives through its first opening and grows one cavity outwards.
    Shallowest first, fronts start at many openings and meet, and the walls between them are
    not simple (removing one would open a tunnel): on a bowl's hull 7,000 free voxels stayed as
    such walls, against 1,700 deepest first. Returns a bool mask.

    First all of them at once: when that keeps the topology (:func:`topology6`), as it does for a
    bowl's cavity, the voxel-by-voxel carving (tens of seconds for 100,000 voxels) is not needed."""
    import heapq

    from scipy import ndimage

    lab, n = ndimage.label(free & inside, structure=_S6)
    if n:
        opening = np.unique(lab[ndimage.binary_dilation(~inside, structure=_S6) & (lab > 0)])
        bulk = np.isin(lab, opening[opening > 0])
        if bulk.any() and topology6(inside & ~bulk) == topology6(inside):
            return bulk

    obj = np.pad(inside, 1, constant_values=False)
    cand = np.pad(free & inside, 1, constant_values=False)
    if depth is None:
        depth = ndimage.distance_transform_edt(inside)
    prio = np.pad(-np.asarray(depth, np.float64), 1, constant_values=0.0)
    removed = np.zeros_like(obj)
    start = cand & ndimage.binary_dilation(~obj, structure=_S6)
    heap = [(prio[p], p) for p in map(tuple, np.argwhere(start))]
    heapq.heapify(heap)
    queued = np.zeros_like(obj)
    queued[start] = True
    while heap:
        _, (i, j, k) = heapq.heappop(heap)
        queued[i, j, k] = False
        if not obj[i, j, k]:
            continue
        if not is_simple(obj[i - 1:i + 2, j - 1:j + 2, k - 1:k + 2]):
            continue
        obj[i, j, k] = False
        removed[i, j, k] = True
        for a, b, c in _OFFSETS26:
            p = (i + a, j + b, k + c)
            if cand[p] and obj[p] and not queued[p]:
                queued[p] = True
                heapq.heappush(heap, (prio[p], p))
    return removed[1:-1, 1:-1, 1:-1]


def carved_field(field: np.ndarray, removed: np.ndarray, step: float) -> np.ndarray:
    """``field`` (world units, positive inside) with the ``removed`` voxels outside: its zero
    level set runs midway between a removed voxel and a kept one, and is the field's own
    elsewhere."""
    from scipy import ndimage

    if not removed.any():
        return field
    to_removed = ndimage.distance_transform_edt(~removed)  # kept voxels: distance to the nearest removed one
    to_kept = ndimage.distance_transform_edt(removed)  # removed voxels: distance to the nearest kept one
    g = np.where(removed, -(to_kept - 0.5), to_removed - 0.5) * float(step)
    return np.minimum(field, g)


@dataclass(frozen=True)
class SeenPoints:
    """SfM's points and who saw them: observation m is ``points[point[m]]`` seen from the
    camera centred at ``centers[view[m]]`` (the cameras.json frame)."""

    centers: np.ndarray
    points: np.ndarray
    view: np.ndarray
    point: np.ndarray


def seen_points(sparse_dir: str | os.PathLike, cams: CameraSet, settings) -> SeenPoints | None:
    """The poses stage's sparse model as :class:`SeenPoints` (None, with a log line, when it
    cannot be read): points seen by at least ``free_space_min_views`` views, each of its
    observations within ``free_space_max_error_px`` pixels of it through ``cams``."""
    from recon.optimize.tracks import SfmTracks, TrackError

    stems = [c.stem for c in cams]
    try:
        tracks = SfmTracks.load(sparse_dir, cams, stems, min_views=settings.free_space_min_views)
    except TrackError as e:
        log.info("no free-space carving: %s", e)
        return None
    err = tracks.reprojection(list(cams))
    bad = np.zeros(len(tracks.points), bool)
    np.logical_or.at(bad, tracks.point, ~(np.isfinite(err) & (err <= settings.free_space_max_error_px)))
    ok = ~bad[tracks.point]
    keep = np.flatnonzero(~bad)
    remap = -np.ones(len(bad), np.int64)
    remap[keep] = np.arange(len(keep))
    centers = np.array([c.center for c in cams])
    return SeenPoints(centers, tracks.points[keep], tracks.view[ok], remap[tracks.point[ok]])


def _near_points(points: np.ndarray, grid: Grid, radius: float) -> np.ndarray:
    """(R, R, R) bool: the voxels within ``radius`` voxels of a point (its own voxel at least)."""
    from scipy import ndimage

    from recon.init_mesh import _ball

    r = grid.resolution
    at = np.rint((np.asarray(points, np.float64).reshape(-1, 3) - grid.origin) / grid.step).astype(np.int64)
    at = at[np.all((at >= 0) & (at < r), axis=1)]
    near = np.zeros((r, r, r), bool)
    near[at[:, 0], at[:, 1], at[:, 2]] = True
    return ndimage.binary_dilation(near, structure=_ball(radius)) if radius >= 1.0 and at.size else near


def carve_hull(field: np.ndarray, grid: Grid, seen: SeenPoints | None, settings, cams: CameraSet | None = None,
               masks: dict | None = None, views=None) -> tuple[np.ndarray, dict]:
    """``field`` (the visual hull's, :func:`recon.init_mesh.hull_field`) with the voxels that
    SfM's points (``seen``, or None) were seen through removed, and what was done (the module
    docstring; settings: :class:`recon.init_mesh.InitMeshSettings`' ``free_space_*``). With
    ``views`` (``views(stem)``: the linear image of a view of ``cams``, whose ``masks`` these are)
    and ``dense_points`` > 0, the points of the views' depth maps inside the hull
    (:func:`recon.mvs.dense_seen_points`) carve too, their segments stopping
    ``dense_stop_voxels`` short of them, but only in the free space SfM's points reach (unless
    ``dense_alone``). Kept only if the surface's genus stays."""
    from recon.init_mesh import _ball, isosurface, largest_component, topology

    t0 = time.perf_counter()
    inside = field > 0
    from scipy import ndimage

    closing = settings.free_space_closing_voxels

    def bulk(free: np.ndarray, near: np.ndarray) -> np.ndarray:
        if closing >= 1.0:
            # the segments are a few voxels apart: the space between them is free too
            free = ndimage.binary_closing(free, structure=_ball(closing)) & inside
        if settings.free_space_opening_voxels >= 1.0:
            # and only where the space is free in bulk: an opening drops the thin streaks of the
            # segments that graze the surface or cross the hull alone (a wrong point, a reflection)
            free = ndimage.binary_opening(free, structure=_ball(settings.free_space_opening_voxels))
        if closing >= 1.0:
            # the hull's outer layer, which the segments cross only where they enter, goes with what
            # lies under it (else it stays as a lid with one opening: the carving keeps the topology)
            skin = inside & (field < closing * grid.step)
            free |= ndimage.binary_dilation(free, structure=_ball(closing)) & skin
        return free & ~near  # never within stop_voxels of a point: a point is on the surface

    counts, near, sfm = [], [], np.zeros_like(inside)
    if seen is not None:
        counts.append(free_space_counts(seen.centers, seen.points, seen.view, seen.point, grid, inside,
                                        settings.free_space_stop_voxels))
        near.append(_near_points(seen.points, grid, settings.free_space_stop_voxels))
        sfm = bulk(counts[0] >= settings.free_space_points, near[0])
    # the depth maps only widen and deepen a cavity that SfM's points alone open (a glossy glaze's
    # reflections of the table match at their mirror depth, inside the object: glossy-mug and
    # wood-vase lost 7,098 and 9,650 voxels of the object to them alone); none: not computed
    dense, dense_info = None, None
    if views is not None and cams is not None and settings.dense_points > 0 and (sfm.any() or settings.dense_alone):
        from recon.mvs import dense_seen_points

        dense, dense_info = dense_seen_points(cams, views, masks or {}, field, grid, settings.dense_points)
        log.info("dense points: %d from the photos' depth maps inside the hull (median %.0f per view), %.1f s%s",
                 dense_info.get("points", 0), dense_info.get("per_view_median", 0.0), dense_info.get("seconds", 0.0),
                 f" ({dense_info['reason']})" if dense is None and "reason" in dense_info else "")
    sets = [(s, stop) for s, stop in ((seen, settings.free_space_stop_voxels), (dense, settings.dense_stop_voxels))
            if s is not None]
    if not sets:
        return field, {"points": 0, "dense": dense_info, "kept": False}
    if dense is not None:
        counts.append(free_space_counts(dense.centers, dense.points, dense.view, dense.point, grid, inside,
                                        settings.dense_stop_voxels))
        near.append(_near_points(dense.points, grid, settings.dense_stop_voxels))
    free = bulk(sum(counts) >= settings.free_space_points, np.logical_or.reduce(near))
    if dense is not None and not settings.dense_alone:
        lab, n = ndimage.label(free, structure=_S6)
        confirmed = np.unique(lab[sfm & (lab > 0)])
        free = np.isin(lab, confirmed[confirmed > 0])

    def near_any(extra: float) -> np.ndarray:
        return np.logical_or.reduce([_near_points(s.points, grid, stop + extra) for s, stop in sets])

    removed = carve(inside, free, field)
    info = {"points": int(sum(len(s.points) for s, _ in sets)), "observations": int(sum(len(s.view) for s, _ in sets)),
            "dense": dense_info,
            "min_points": settings.free_space_points, "voxels_free": int(free.sum()),
            "voxels_carved": int(removed.sum()),
            "fraction_of_hull": float(removed.sum() / max(1, inside.sum())), "kept": False}
    if removed.any():
        # what the carving leaves of the hull's outer layer over the cavity (pieces of a lid
        # that the topology held: a thread of voxels, a flap) goes: the object is opened by a
        # ball where the carving was, and only its largest part kept
        around = ndimage.binary_dilation(removed, structure=_ball(settings.free_space_closing_voxels + 1.0))
        kept = inside & ~removed
        thin = kept & around & ~ndimage.binary_opening(kept, structure=_ball(settings.free_space_opening_voxels))
        thin &= ~near_any(1.0)  # a thin wall holds points
        # removed as the carving removes: from the surface inwards and only where the topology
        # stays (removed whole, a remnant over a thin wall opened a tunnel through it: a bowl's
        # hull went from genus 0 to 6 with dense points, docs/init_mesh.md)
        kept &= ~carve(kept, thin, field)
        lab, n = ndimage.label(kept, structure=ndimage.generate_binary_structure(3, 1))
        if n > 1:
            kept = lab == 1 + int(np.argmax(np.bincount(lab.ravel())[1:]))
        removed = inside & ~kept
        info["voxels_carved"] = int(removed.sum())
        info["fraction_of_hull"] = float(removed.sum() / max(1, inside.sum()))
        carved = carved_field(field, removed, grid.step)
        # the carved surface is as rough as the voxels: smoothed where it was carved
        # (the sign at every voxel kept: the smoothing moves the surface, never a voxel across it,
        # so it cannot open a thin wall)
        smooth = ndimage.gaussian_filter(carved, 1.0)
        floor = 0.05 * grid.step
        smooth = np.where(carved > 0, np.maximum(smooth, floor), np.minimum(smooth, -floor))
        carved = np.where(around, smooth, carved)
        before = topology(largest_component(isosurface(field, grid, space="grid")))["genus"]
        after = topology(largest_component(isosurface(carved, grid, space="grid")))["genus"]
        info.update(genus_before=before, genus_after=after)
        if after == before:
            field, info["kept"] = carved, True
        else:
            log.info("free-space carving left out: it changed the hull's genus from %d to %d", before, after)
    info["seconds"] = time.perf_counter() - t0
    log.info("free space: %d voxels inside the hull seen through by >= %d of the %d points; %d carved "
             "(%.1f %% of the hull)%s, %.1f s", info["voxels_free"], settings.free_space_points, info["points"],
             info["voxels_carved"], 100 * info["fraction_of_hull"], "" if info["kept"] or not removed.any()
             else " and left out", info["seconds"])
    return field, info


def object_points(seen: SeenPoints, cams: CameraSet, masks: dict[str, np.ndarray], share: float = 0.5) -> np.ndarray:
    """The points of ``seen`` that are the object's: inside the masks in at least ``share`` of the
    views that observed them (a wall's or a table's points fall outside). ``(n, 3)``."""
    inside = np.zeros(len(seen.points))
    count = np.zeros(len(seen.points))
    for k, cam in enumerate(cams):
        m = masks.get(cam.stem)
        obs = np.flatnonzero(seen.view == k)
        if m is None or not len(obs):
            continue
        xy, z = cam.project(seen.points[seen.point[obs]])
        j, i = np.floor(xy[:, 0]), np.floor(xy[:, 1])
        ok = np.isfinite(xy).all(1) & (z > 0) & (j >= 0) & (j < m.shape[1]) & (i >= 0) & (i < m.shape[0])
        hit = np.zeros(len(obs), bool)
        hit[ok] = m[i[ok].astype(int), j[ok].astype(int)]
        np.add.at(count, seen.point[obs], 1.0)
        np.add.at(inside, seen.point[obs], hit.astype(float))
    return seen.points[(count > 0) & (inside >= share * np.maximum(count, 1))]
