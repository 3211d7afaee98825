"""The support plane: the table (or sheet, or mat) the object stands on.

One convention, used by the synthetic ground truth (``gt/plane.json``) and by every stage that
finds or uses the plane (``plane.json`` of the masks' tabletop path, :mod:`recon.segment`)::

    n . x + offset = 0,   |n| = 1,   n points from the table towards the cameras ("up")

in the frame of the ``cameras.json`` beside it. :meth:`SupportPlane.height` is the signed
distance above the plane (positive on the cameras' side).

:func:`fit_support_plane` finds the plane in a cloud of 3D points (SfM points, or points
triangulated from known cameras): RANSAC over point triples, kept only when (a) the cameras
all look at it from above (a table is photographed from one side; a void capture's object
seen from all around is not a table), (b) it holds a good share of the points, and (c) it
passes below the point the cameras aim at, with points standing above it there (the object),
(d) its points lie around the object's foot, not under the object (a flat part of an object
alone is not a table), and (e) it is no slice through the object: points along the object's
outline alone, with the object under them as well as over them.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from recon.io.atomic import atomic_path
from recon.io.cameras import CameraSet

log = logging.getLogger(__name__)


class PlaneError(ValueError):
    """A plane file that does not follow the convention; the message names the file and the fix."""


@dataclass(frozen=True)
class SupportPlane:
    """``normal . x + offset = 0``; ``normal (3,)`` unit length, pointing up (to the cameras)."""

    normal: np.ndarray
    offset: float

    def __post_init__(self):
        n = np.asarray(self.normal, dtype=np.float64).reshape(3)
        length = float(np.linalg.norm(n))
        if not np.isfinite(length) or length < 1e-12 or not np.isfinite(self.offset):
            raise PlaneError(f"a plane needs a finite nonzero normal and offset, got {self.normal}, {self.offset}")
        object.__setattr__(self, "normal", n / length)
        object.__setattr__(self, "offset", float(self.offset) / length)

    @classmethod
    def through(cls, point, normal) -> "SupportPlane":
        """The plane through ``point (3,)`` with ``normal (3,)``."""
        n = np.asarray(normal, dtype=np.float64)
        n = n / np.linalg.norm(n)
        return cls(n, -float(n @ np.asarray(point, dtype=np.float64)))

    @property
    def point(self) -> np.ndarray:
        """(3,) the plane's point closest to the origin."""
        return -self.offset * self.normal

    def height(self, points: np.ndarray) -> np.ndarray:
        """Signed distance of ``points (..., 3)`` above the plane (positive on the normal's side)."""
        return np.asarray(points, dtype=np.float64) @ self.normal + self.offset

    def project(self, points: np.ndarray) -> np.ndarray:
        """``points (..., 3)`` moved along the normal onto the plane."""
        p = np.asarray(points, dtype=np.float64)
        return p - self.height(p)[..., None] * self.normal

    def clamp_above(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``points (..., 3)`` with those below the plane moved along the normal onto it, and the
        (...,) bool array of the moved ones (a projection onto the half-space above)."""
        p = np.asarray(points, dtype=np.float64)
        h = self.height(p)
        below = h < 0
        return p - np.minimum(h, 0.0)[..., None] * self.normal, below

    def resting(self, points: np.ndarray, normals: np.ndarray, tol: float) -> np.ndarray:
        """(V,) bool: the vertices the object stands on, within ``tol`` of the plane with their
        normal facing it (more than 60 degrees down). ``points, normals (V, 3)``."""
        n = np.asarray(normals, dtype=np.float64) @ self.normal
        return (self.height(points) < tol) & (n < -0.5)

    def hold(self, points: np.ndarray, resting: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``points (V, 3)`` projected onto the constraint: the ``resting`` ones onto the plane
        (they slide along it, never lift off), the others into the half-space above; and the
        (V,) bool array of the points that moved."""
        p = np.asarray(points, dtype=np.float64)
        h = self.height(p)
        dh = np.where(resting, h, np.minimum(h, 0.0))
        return p - dh[..., None] * self.normal, dh != 0

    def ray_hit(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Ray parameter t of ``origins + t * directions`` on the plane (inf where parallel)."""
        o = np.asarray(origins, dtype=np.float64)
        d = np.asarray(directions, dtype=np.float64)
        denom = d @ self.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -self.height(o) / denom
        return np.where(np.abs(denom) > 1e-12, t, np.inf)

    def basis(self) -> np.ndarray:
        """(3, 3) rows e1, e2, normal: an orthonormal frame with the normal last."""
        n = self.normal
        a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        e1 = np.cross(n, a)
        e1 /= np.linalg.norm(e1)
        return np.stack([e1, np.cross(n, e1), n])

    def to_dict(self) -> dict:
        return {"normal": self.normal.tolist(), "offset": self.offset, "point": self.point.tolist(),
                "convention": "normal . x + offset = 0 in the cameras.json frame; normal points up, "
                              "towards the cameras"}


def standing_points(points: np.ndarray, plane: SupportPlane | None, min_height: float) -> np.ndarray:
    """(N,) bool: which of ``points (N, 3)`` stand above ``plane`` by more than ``min_height`` (the
    object's points, not the table's). All True without a plane (an object in the void). Checks
    that compare sparse points with object masks (e.g. the share of them that project inside the
    masks) must count only these: a table point lies outside every object mask by right."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if plane is None:
        return np.ones(len(pts), bool)
    return plane.height(pts) > float(min_height)


# The table's points, as fractions of the cameras' spread (:func:`camera_spread`): within
# TABLE_TOLERANCE of the plane, and (:func:`table_points`) further than FOOT_RADIUS across it from
# the object's foot. The checks of masks that hold the table and the plane search share them.
TABLE_TOLERANCE = 0.01
FOOT_RADIUS = 0.02


def camera_spread(centers: np.ndarray) -> float:
    """The largest extent of the camera centres ``(V, 3)`` along an axis: the length the table's
    points are measured in (SfM's frame has no scale)."""
    return float(np.ptp(np.asarray(centers, dtype=np.float64).reshape(-1, 3), axis=0).max())


def _foot_distances(points: np.ndarray, h: np.ndarray, plane: SupportPlane, on: np.ndarray, tolerance: float
                    ) -> tuple[np.ndarray, np.ndarray]:
    """For the points ``on`` the plane (``h``: every point's height over it): the distance across
    it to the nearest point standing low over it (``tolerance`` to 10 ``tolerance`` above), and to
    the nearest as low under it (inf where there is none)."""
    from scipy.spatial import cKDTree

    xy = plane.project(points[on])
    out = []
    for band in ((h >= tolerance) & (h < 10 * tolerance), (h <= -tolerance) & (h > -10 * tolerance)):
        out.append(cKDTree(plane.project(points[band])).query(xy)[0] if band.any() and len(xy)
                   else np.full(len(xy), np.inf))
    return out[0], out[1]


def table_points(points: np.ndarray, plane: SupportPlane, tolerance: float, foot: float = 0.0) -> np.ndarray:
    """(N,) bool: which of ``points (N, 3)`` are the table's: within ``tolerance`` of ``plane``
    and, with ``foot`` > 0, not the object's foot: a point of the plane within ``foot`` across it
    of a point standing low on it (``tolerance`` to 10 ``tolerance`` above) and of none as low
    under it. The object's own foot, where it touches the table, lies on the plane too, and every
    mask of the object holds it: a bell in 1600-px phone photos had 86 of its 97 points on the
    plane about its rim (SfM found almost none on its wooden table at COLMAP's peak threshold),
    and its right masks (0.984 IoU) were refused for holding 70 % of "the table's points". A
    plane through the object itself (a slice above its foot) has the object under its points as
    well as over them: those stay counted, and masks cut at it are refused as before."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    h = plane.height(pts)
    on = np.abs(h) < tolerance
    if foot > 0 and on.any():
        d_over, d_under = _foot_distances(pts, h, plane, on, tolerance)
        on[np.flatnonzero(on)[(d_over < foot) & (d_under >= foot)]] = False
    return on


def save_plane(path: str | os.PathLike, plane: SupportPlane, **extra) -> None:
    """Write ``plane.json`` atomically (``extra`` keys are stored beside the plane)."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps({**plane.to_dict(), **extra}, indent=1))


def load_plane(path: str | os.PathLike) -> SupportPlane:
    """Read a ``plane.json`` written by :func:`save_plane`."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
        return SupportPlane(np.asarray(data["normal"], dtype=np.float64), float(data["offset"]))
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise PlaneError(f"{path}: not a plane file ({e}); it needs 'normal' (3 numbers) and 'offset'") from e


def plane_if_found(path: str | os.PathLike | None) -> SupportPlane | None:
    """The plane in ``path``, or None when ``path`` is None or names no file.

    The masks stage (given cameras) and the poses stage (SfM) write ``plane.json`` beside their
    masks only when they found a support plane; the later stages take its path and keep their
    behaviour for an object in the void when it is absent. A file that is there but unreadable
    is an error (:class:`PlaneError`).
    """
    if path is None or str(path) == "":
        return None
    path = Path(path)
    if not path.is_file():
        return None
    return load_plane(path)


# ---------------------------------------------------------------------------------------------
# Finding the plane
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PlaneSettings:
    """How :func:`fit_support_plane` finds the table. Lengths are fractions of the scene scale
    (the median distance from the cameras to the point they aim at)."""

    inlier_distance: float = 0.006  # a point within this of the plane lies on it
    min_inlier_fraction: float = 0.05  # the plane holds at least this share of the points ...
    min_inliers: int = 30  # ... and this many
    min_camera_elevation: float = 5.0  # degrees: every camera looks down on the plane by this much
    camera_fraction: float = 0.9  # ... or at least this share of them (a stray view or two)
    min_object_points: int = 8  # points standing above the plane near the aim point
    object_height: float = 0.03  # standing above means higher than this
    object_radius: float = 0.5  # near the aim point: within this horizontal distance
    # A table is seen around the object's foot: its points lie outside the object's footprint
    # (the object hides the table under it). A plane through the object itself (a flat face, the
    # coplanar rim of a vase or bowl photographed alone) has its points under the object. The
    # median horizontal distance of the plane's points from the foot must exceed this multiple
    # of the object points' (measured: tables 2.2-4.8 on seven tabletop captures, planes through
    # an object in the void 0.35 and 0.76; bench/tabletop_e2e.py --family, docs/tabletop.md).
    min_spread: float = 1.0
    # A slice through the object is no table: a plane whose points lie along the object's
    # outline, fewer than min_table_points of them further than foot_radius across it from every
    # point standing low over it (a table is seen beyond the object), with more than
    # max_object_under of them over points as low under it (the object goes on below), is refused
    # (lengths: fractions of the cameras' spread, within table_tolerance of the plane). A bell on a
    # stand, no table in its photos, was sliced above its rim by a plane of 867 points, 5 beyond
    # the bell, 99 % with the bell under them; a plain desk's plane under a vase 16 beyond, 94 %;
    # tables measured 85-2887 beyond (the fewest: a bell in 1600-px photos whose wooden table SfM
    # barely saw, its plane's points the bell's rim, none with anything under them; 17 captures
    # of sessions 24-28)
    min_table_points: int = 30
    max_object_under: float = 0.5
    table_tolerance: float = TABLE_TOLERANCE
    foot_radius: float = FOOT_RADIUS
    # The second look (planes across the cameras' up, when the plane with the most points fails):
    min_inlier_fraction_up: float = 0.02  # a table with few of the points ...
    max_below: float = 0.1  # ... under nearly all of them ...
    min_spread_up: float = 1.5  # ... and spread well around the object's foot
    # The plane with the most points is checked against the cameras' up too: when its normal is
    # further than this from every direction up_candidates gives, the second look is tried as
    # well and its plane, if it finds one, is taken. Tables measured 0.2-2.3 degrees from the
    # nearer candidate (18 captures of sessions 24-28); a plane through a bell's body, which held
    # more of the points of 1600-px photos than their table, 8.7; through a plain desk's few
    # points and a vase's foot, 8.5
    max_up_angle: float = 5.0
    iterations: int = 2000
    seed: int = 0

    def __post_init__(self):
        if not self.min_spread >= 0:
            raise ValueError(f"min_spread must be >= 0, got {self.min_spread}")
        if not 0 < self.inlier_distance < 1:
            raise ValueError(f"inlier_distance must be in (0, 1), got {self.inlier_distance}")
        if not 0 < self.min_inlier_fraction_up <= 1 or not 0 <= self.max_below <= 1 or self.min_spread_up < 0:
            raise ValueError("min_inlier_fraction_up must be in (0, 1], max_below in [0, 1], min_spread_up >= 0")
        if not 0 < self.min_inlier_fraction <= 1 or not 0 < self.camera_fraction <= 1:
            raise ValueError("min_inlier_fraction and camera_fraction must be in (0, 1]")
        if (self.min_table_points < 0 or not 0 < self.table_tolerance < 1 or not self.foot_radius >= 0
                or not 0 <= self.max_object_under <= 1):
            raise ValueError("min_table_points must be >= 0, table_tolerance in (0, 1), foot_radius >= 0 and "
                             "max_object_under in [0, 1]")
        if self.min_inliers < 3 or self.iterations < 1:
            raise ValueError("min_inliers must be >= 3 and iterations >= 1")


def aim_point(cams: CameraSet) -> np.ndarray:
    """(3,) the point closest (least squares) to every camera's optical axis."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c in cams:
        d = c.camera_to_world[:3, 2]
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c.center
    if np.linalg.cond(A) > 1e8:  # all axes parallel: no common point
        return np.mean([c.center + c.camera_to_world[:3, 2] for c in cams], axis=0)
    return np.linalg.solve(A, b)


def scene_scale(cams: CameraSet, target: np.ndarray | None = None) -> float:
    """The median distance from the camera centers to ``target`` (default :func:`aim_point`)."""
    t = aim_point(cams) if target is None else np.asarray(target, dtype=np.float64)
    return float(np.median([np.linalg.norm(c.center - t) for c in cams]))


def _plane_from(p: np.ndarray) -> tuple[np.ndarray, float] | None:
    n = np.cross(p[1] - p[0], p[2] - p[0])
    length = np.linalg.norm(n)
    if length < 1e-12:
        return None
    n = n / length
    return n, -float(n @ p[0])


def _refine(points: np.ndarray) -> tuple[np.ndarray, float]:
    c = points.mean(0)
    _, _, vt = np.linalg.svd(points - c, full_matrices=False)
    n = vt[-1]
    return n, -float(n @ c)


def _looks_down(heights: np.ndarray, centers: np.ndarray, target: np.ndarray, settings: PlaneSettings) -> bool:
    """Whether ``camera_fraction`` of the cameras (``centers``, at ``heights`` above a plane) look
    down on it by ``min_camera_elevation``, seen from the aim point ``target``."""
    rel = heights / np.linalg.norm(centers - target, axis=1)
    return bool(np.mean(rel > np.sin(np.radians(settings.min_camera_elevation))) >= settings.camera_fraction)


def up_candidates(cams: CameraSet, centers: np.ndarray, target: np.ndarray) -> list[np.ndarray]:
    """Directions the table's normal likely has, from the cameras alone: the mean of their image
    ups (-y; a photo's up is the room's unless the phone was turned, then the mean shrinks and
    is not used) and the normal of the plane through their centres (a person walks around the
    object at about one height), each towards the cameras (the heights searched lie below the
    point the cameras aim at)."""
    out = []
    ups = -np.stack([c.camera_to_world[:3, 1] for c in cams])
    m = ups.mean(0)
    if np.linalg.norm(m) > 0.5:
        out.append(m / np.linalg.norm(m))
    if len(centers) >= 3:
        _, sv, vt = np.linalg.svd(centers - centers.mean(0), full_matrices=False)
        if sv[1] > 1e-9 and sv[2] < 0.5 * sv[1]:  # the centres span a plane, not a line or a ball
            out.append(vt[-1] if (centers - target).mean(0) @ vt[-1] > 0 else -vt[-1])
    return out


def _height_levels(pts: np.ndarray, up: np.ndarray, below: float, tol: float, min_count: int) -> list[float]:
    """Heights along ``up`` (below ``below``) where at least ``min_count`` points lie within ``tol``:
    the local maxima of the points' height density, most populated first."""
    h = pts @ up
    h = h[h < below]
    if len(h) < min_count:
        return []
    edges = np.arange(h.min() - tol, h.max() + 2 * tol, tol)
    counts, _ = np.histogram(h, edges)
    window = np.convolve(counts, np.ones(2, int), mode="valid")  # two bins: a band of 2 tol
    peaks = [k for k in range(len(window)) if window[k] >= min_count
             and window[k] >= window[max(k - 1, 0)] and window[k] >= window[min(k + 1, len(window) - 1)]]
    peaks.sort(key=lambda k: -window[k])
    return [float(edges[k + 1]) for k in peaks[:8]]


def fit_support_plane(points: np.ndarray, cams: CameraSet,
                      settings: PlaneSettings = PlaneSettings()) -> tuple[SupportPlane | None, dict]:
    """The support plane in ``points (N, 3)`` seen by ``cams``, or None with the reason.

    A plane is kept only when the cameras look down on it (``camera_fraction`` of them by
    ``min_camera_elevation``), it holds ``min_inliers`` and ``min_inlier_fraction`` of the points
    (SfM on small photos of a textured object finds most points on the object), the cameras aim
    above it, and points stand on it near the aim point.

    The plane with the most points (RANSAC over triples) is tried first. When it fails, planes
    across the cameras' up (:func:`up_candidates`) at the heights where points gather are tried:
    a table that holds few of the points (a close-up capture of a strongly textured object: 4 %
    of SfM's points on the table) is rarely drawn by RANSAC's triples, and the plane with the
    most points is then a flat cap of the object. Such a plane must hold ``min_inlier_fraction_up``
    of the points, with at most ``max_below`` of them below it (a table is under everything the
    photos show of the object) and its points spread ``min_spread_up`` around the object's foot.

    Returns
    -------
    plane : SupportPlane or None
        Normal towards the cameras.
    info : dict
        ``found`` (bool), ``reason`` (why not, or what was found), ``inliers``, ``points``,
        ``object_points`` (standing above it near the aim point), ``scale`` (the scene scale),
        ``camera_elevation_deg`` (min/median/max of the cameras' elevation above the plane, seen
        from the aim point), ``proposal`` (``ransac`` or ``cameras' up``).
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    target = aim_point(cams)
    scale = scene_scale(cams, target)
    centers = np.stack([c.center for c in cams])
    info: dict = {"found": False, "points": int(len(pts)), "scale": scale}
    if len(pts) < settings.min_inliers:
        info["reason"] = f"only {len(pts)} 3D points (need >= {settings.min_inliers})"
        return None, info
    tol = settings.inlier_distance * scale
    rng = np.random.default_rng(settings.seed)
    best, best_count, rejected, tilted = None, 0, {"cameras": 0, "object": 0}, None
    ups = up_candidates(cams, centers, target)
    triples = rng.integers(0, len(pts), size=(settings.iterations, 3))
    for tri in triples:
        plane = _plane_from(pts[tri])
        if plane is None:
            continue
        n, d = plane
        dist = pts @ n + d
        count = int(np.count_nonzero(np.abs(dist) < tol))
        if count <= best_count:
            continue
        # the cameras must look down on it (from one side, above it)
        hc = centers @ n + d
        if np.median(hc) < 0:
            n, d, dist, hc = -n, -d, -dist, -hc
        if not _looks_down(hc, centers, target, settings):
            rejected["cameras"] += 1
            continue
        best, best_count = (n, d), count
    if best is None:
        info["reason"] = ("no plane with the cameras on one side, looking down on it by "
                          f">= {settings.min_camera_elevation} degrees (a void capture, or views from below)")
    else:
        plane, judged = _judge(best, pts, centers, target, scale, tol, settings)
        info.update(judged)
        if plane is not None:
            tilt = min((float(np.degrees(np.arccos(np.clip(abs(plane.normal @ u), 0.0, 1.0)))) for u in ups),
                       default=0.0)
            info["proposal"] = "ransac"
            info["ransac_up_angle_deg"] = tilt
            if tilt <= settings.max_up_angle:
                return plane, info
            tilted = (plane, dict(info))
    # a second look: planes across the cameras' up, at the heights where points gather
    found = []
    for up in ups:
        for level in _height_levels(pts, up, float(target @ up), tol, settings.min_inliers):
            plane, judged = _judge((up, -level), pts, centers, target, scale, tol, settings, second=True)
            if plane is not None:
                found.append((judged["inliers"], plane, judged))
    if found:
        first = info["reason"]
        _, plane, judged = max(found, key=lambda f: f[0])
        info.update(judged)
        info["proposal"] = "cameras' up"
        info["reason"] += (f" (across the cameras' up; the plane with the most points failed: {first})" if tilted is None
                           else f" (across the cameras' up; the plane with the most points, {first}, lies "
                                f"{tilted[1]['ransac_up_angle_deg']:.1f} degrees off the cameras' up)")
        return plane, info
    if tilted is not None:  # nothing across the cameras' up: the plane with the most points after all
        return tilted
    return None, info


def _judge(candidate: tuple[np.ndarray, float], pts: np.ndarray, centers: np.ndarray, target: np.ndarray,
           scale: float, tol: float, settings: PlaneSettings, second: bool = False) -> tuple[SupportPlane | None, dict]:
    """The candidate plane ``(n, d)`` refined on its points and checked (:func:`fit_support_plane`);
    ``second``: a candidate of the second look, held to its rules. Returns the plane or None, and
    the diagnostics with ``reason``."""
    n, d = candidate
    inl = np.abs(pts @ n + d) < tol
    if inl.sum() < 3:
        return None, {"reason": "no points on the plane"}
    for _ in range(2 if second else 1):  # a level of the second look: its points again about the fit
        n, d = _refine(pts[inl])
        inl = np.abs(pts @ n + d) < tol
        if inl.sum() < 3:
            return None, {"reason": "no points on the plane"}
    if (centers @ n + d).mean() < 0:
        n, d = -n, -d
    plane = SupportPlane(n, d)
    h = plane.height(pts)
    inl = np.abs(h) < tol
    # elevations as seen from the aim point (the object's middle)
    rise = plane.height(centers) - plane.height(target)
    elev = np.degrees(np.arcsin(np.clip(rise / np.linalg.norm(centers - target, axis=1), -1, 1)))
    foot = plane.project(target)
    horiz = np.linalg.norm(plane.project(pts) - foot, axis=1)
    above = (h > settings.object_height * scale) & (horiz < settings.object_radius * scale)
    info = {"inliers": int(inl.sum()), "inlier_fraction": float(inl.mean()),
            "object_points": int(above.sum()), "aim_height": float(plane.height(target) / scale),
            "below_fraction": float(np.mean(h < -tol)),
            "camera_elevation_deg": {"min": float(elev.min()), "median": float(np.median(elev)),
                                     "max": float(elev.max())}}
    min_fraction = settings.min_inlier_fraction_up if second else settings.min_inlier_fraction
    if second and not _looks_down(plane.height(centers), centers, target, settings):
        info["reason"] = "the cameras do not look down on it"
        return None, info
    if inl.sum() < settings.min_inliers or inl.mean() < min_fraction:
        info["reason"] = (f"the best plane holds {inl.sum()} of {len(pts)} points ({100 * inl.mean():.0f}%; "
                          f"need >= {settings.min_inliers} and >= {100 * min_fraction:.0f}%)")
        return None, info
    if plane.height(target) <= 0:
        info["reason"] = "the cameras aim below the plane: the object is not standing on it"
        return None, info
    if second and info["below_fraction"] > settings.max_below:
        info["reason"] = (f"{100 * info['below_fraction']:.0f}% of the points lie below it (at most "
                          f"{100 * settings.max_below:.0f}%)")
        return None, info
    if above.sum() < settings.min_object_points:
        info["reason"] = (f"only {above.sum()} points stand above the plane near the point the cameras aim at "
                          f"(need >= {settings.min_object_points}): nothing stands on it (a hand-held object?)")
        return None, info
    spread = float(np.median(horiz[inl]) / max(np.median(horiz[above]), 1e-12 * scale))
    info["spread"] = spread
    min_spread = settings.min_spread_up if second else settings.min_spread
    if spread <= min_spread:
        info["reason"] = (f"the plane's {inl.sum()} points lie under the object, not around it (their median "
                          f"distance from its foot is {spread:.2f}x the object points'): a flat part of the "
                          "object, not a table it stands on")
        return None, info
    spread_c = camera_spread(centers)
    ring = np.abs(h) < settings.table_tolerance * spread_c
    d_over, d_under = _foot_distances(pts, h, plane, ring, settings.table_tolerance * spread_c)
    beyond = int(np.count_nonzero(d_over >= settings.foot_radius * spread_c))
    sliced = float(np.mean(d_under < settings.foot_radius * spread_c)) if len(d_under) else 0.0
    info["beyond_object_points"], info["object_under"] = beyond, sliced
    if beyond < settings.min_table_points and sliced > settings.max_object_under:
        info["reason"] = (f"only {beyond} of the plane's {int(ring.sum())} points lie beyond the object's outline "
                          f"(need >= {settings.min_table_points}), and {100 * sliced:.0f}% of them have the object "
                          "under them too: a slice through the object, not a table around it")
        return None, info
    info["found"] = True
    info["reason"] = (f"plane with {inl.sum()} of {len(pts)} points, {above.sum()} points above it near the "
                      f"aim point, cameras {elev.min():.0f}-{elev.max():.0f} degrees above it")
    return plane, info
