"""Masks of an object standing on a table: the object apart from the table and the background.

Flash-falloff masks (:mod:`recon.masks`) take everything the flash lights; on a table that is
the object and the table around it in one piece. Here the geometry of the capture separates
them, with no learned weights:

1. **The support plane** (:func:`recon.support.fit_support_plane`) by RANSAC in sparse 3D points:
   the SfM points (``poses/points.ply``), or, with known cameras, points triangulated here from
   SIFT matches between neighbouring views (:func:`triangulate_points`).
2. **Plane consistency** (:func:`plane_consistency`), per view i: every pixel's ray meets the
   plane at P. If the pixel sees the table, the neighbouring views j see the same table texture
   at P: view j warped into view i by the homography the plane induces
   (:func:`plane_homography`), its flash shading ``cos / r^2`` at P swapped for view i's and one
   gain per view pair (exposure) removed, matches view i there. If it sees the object (which
   stands above the plane), view j sees something else at P. The relative difference, averaged
   over a small window that follows the image's edges (guided filter), and its minimum over
   the neighbours (a table point that the object hides from one neighbour is seen by another)
   give C_i: ~0.1-0.3 on the table, >~1 on the object. Dark pixels (far table, dim background)
   are consistent by construction (a noise floor); pixels below the flash-falloff threshold of
   :mod:`recon.masks` (the background the flash hardly reaches) are never object.
3. **A visual hull above the plane** (:func:`carve`) from the liberal masks C_i > ``carve_threshold``,
   tolerant of a few views' misses, restricted to what stands on the plane near the point the
   cameras aim at: the object's 3D region. Its projection bounds each view's mask (the seed
   region of step 4): a blob of a far background or a specular patch on the table that no 3D
   object explains is never object.
4. **Per view a graph cut** (:func:`graph_cut`, scipy's max-flow): data costs from C_i (logistic
   around ``threshold``), sure background outside the dilated hull projection, and a
   contrast-sensitive smoothness term on the photo, so the outline snaps to the image edge
   between object and table (where the object touches the table, the plane test alone cannot
   tell them apart: its points there lie on the plane).
5. **Cross-check across views**: a second hull from the cut masks; each mask keeps only what
   lies inside (a pixel of margin) its projection, and a hole in a mask is filled where the hull
   of the other views' masks is solid (chance agreement with the table in one view), kept where
   the other views see through it too (the table through a mug's handle), whatever its size
   (:func:`hole_support`).

Given masks (the capture's ``masks/``) still win, view by view. A capture without a support
plane (a void capture, a hand-held object) keeps the flash-falloff masks of :mod:`recon.masks`,
with a note in the log. A view whose object cannot be separated from the table (an empty mask,
a mask that fills its hull projection's whole box, or one the other views contradict) is named
in a :class:`SegmentError` with what to try.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from recon.io.cameras import Camera, CameraSet
from recon.masks.common import LUMA, MaskError, display_image
from recon.masks.falloff import MaskSettings, derive_mask
from recon.support import PlaneSettings, SupportPlane, aim_point, scene_scale

log = logging.getLogger(__name__)


class SegmentError(MaskError):
    """Masks that cannot be separated from the table; the message names the views and what to try."""


@dataclass(frozen=True)
class SegmentSettings:
    """Settings of the tabletop masks (:mod:`recon.segment`). Lengths in pixels are at the
    photos' own size; 3D lengths are fractions of the scene scale (median camera distance)."""

    neighbours: int = 6  # views compared with each view (nearest viewing directions)
    min_angle: float = 4.0  # degrees: neighbours closer than this give too little parallax
    max_angle: float = 70.0  # degrees: ... farther than this see too different a table
    floor: float = 0.03  # noise floor of the relative difference, x the view's 90th percentile
    window: int = 2  # radius (px) of the guided-filter window that averages the differences
    threshold: float = 0.7  # C above this: object (the logistic's middle)
    softness: float = 0.15  # the logistic's width
    carve_threshold: float = 0.5  # liberal masks for the hull
    carve_tolerance: float = 0.12  # a voxel survives this share of views that miss it
    hole_tolerance: float = 0.05  # ... when the other views decide whether a hole is real
    hull_resolution: int = 96  # voxels along the longest side of the fine hull
    hull_margin_px: int = 6  # the mask stays inside the hull projection dilated by this
    band_parallax_px: float = 3.0  # below the height where neighbours see less parallax, colours decide
    colour_weight: float = 1.0  # weight of the colour models' log-likelihood ratio there
    smoothness: float = 2.0  # weight of the contrast-sensitive pairwise term
    max_hole_fraction: float = 0.02  # liberal masks: holes smaller than this share of the object are filled
    min_views: int = 4  # fewer views: no tabletop masks
    plane: PlaneSettings = PlaneSettings()
    triangulate_pairs: int = 3  # known cameras: match each view with this many neighbours
    seed: int = 0

    def __post_init__(self):
        if self.neighbours < 1 or self.min_views < 2:
            raise ValueError("neighbours must be >= 1 and min_views >= 2")
        if not 0 <= self.min_angle < self.max_angle <= 180:
            raise ValueError(f"need 0 <= min_angle < max_angle <= 180, got {self.min_angle}, {self.max_angle}")
        if self.floor <= 0 or self.softness <= 0 or self.threshold <= 0 or self.carve_threshold <= 0:
            raise ValueError("floor, softness, threshold and carve_threshold must be > 0")
        if not 0 <= self.carve_tolerance < 0.5:
            raise ValueError(f"carve_tolerance must be in [0, 0.5), got {self.carve_tolerance}")
        if self.hull_resolution < 16:
            raise ValueError(f"hull_resolution must be >= 16, got {self.hull_resolution}")
        if isinstance(self.plane, dict):
            object.__setattr__(self, "plane", PlaneSettings(**self.plane))


# ---------------------------------------------------------------------------------------------
# Geometry helpers
# ---------------------------------------------------------------------------------------------
_HALF = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
"""Pixel coordinates of DESIGN (centers at j + 0.5) from OpenCV's (centers at integers)."""


def plane_homography(cam_i: Camera, cam_j: Camera, plane: SupportPlane) -> np.ndarray:
    """(3, 3) homography taking OpenCV pixel coordinates of view i (centers at integers) to
    those of view j for points on ``plane``: x_j ~ H x_i.

    With the plane n_c . X_c + d_c = 0 in camera i's coordinates and X_j = R X_c + t the
    relative motion, H = K_j (R - t n_c^T / d_c) K_i^-1.
    """
    Ri, ti = cam_i.world_to_camera[:3, :3], cam_i.world_to_camera[:3, 3]
    Rj, tj = cam_j.world_to_camera[:3, :3], cam_j.world_to_camera[:3, 3]
    n_c = Ri @ plane.normal
    d_c = plane.offset - n_c @ ti
    R = Rj @ Ri.T
    t = tj - R @ ti
    H = cam_j.K @ (R - np.outer(t, n_c) / d_c) @ np.linalg.inv(cam_i.K)
    return np.linalg.inv(_HALF) @ H @ _HALF


def pixel_rays(cam: Camera) -> np.ndarray:
    """(H, W, 3) world directions (not normalized) of the rays through the pixel centers."""
    j, i = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    pix = np.stack([j, i, np.ones_like(j)], -1)
    return pix @ (cam.camera_to_world[:3, :3] @ np.linalg.inv(cam.K)).T


def plane_points(cam: Camera, plane: SupportPlane) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel's ray meets the plane: ``P (H, W, 3)`` and ``hit (H, W)`` bool (in front)."""
    d = pixel_rays(cam)
    t = plane.ray_hit(cam.center, d)
    hit = np.isfinite(t) & (t > 0)
    return cam.center + np.where(hit, t, 0.0)[..., None] * d, hit


def flash_shading(center: np.ndarray, points: np.ndarray, plane: SupportPlane) -> np.ndarray:
    """``cos / r^2`` of the flash at ``center`` on plane points ``(..., 3)``: height / r^3."""
    r = np.linalg.norm(points - center, axis=-1)
    return plane.height(center) / np.maximum(r, 1e-12) ** 3


def neighbours(cams: CameraSet, settings: SegmentSettings) -> list[list[int]]:
    """For each view the indices of its ``settings.neighbours`` nearest views by viewing
    direction, between ``min_angle`` and ``max_angle`` apart."""
    z = np.stack([c.camera_to_world[:3, 2] for c in cams])
    ang = np.degrees(np.arccos(np.clip(z @ z.T, -1.0, 1.0)))
    out = []
    for i in range(len(z)):
        order = [j for j in np.argsort(ang[i], kind="stable")
                 if j != i and settings.min_angle <= ang[i, j] <= settings.max_angle]
        out.append(order[: settings.neighbours])
    return out


def parallax_band(cams: CameraSet, nbrs: list[list[int]], foot: np.ndarray, parallax_px: float) -> float:
    """Height above the plane below which a point shows less than ``parallax_px`` of parallax to
    a typical neighbour (the median over views of the second nearest): there the plane test
    cannot tell the object from the table. About ``parallax_px * depth / (f sin(angle))``."""
    z = np.stack([c.camera_to_world[:3, 2] for c in cams])
    heights = []
    for i, cam in enumerate(cams):
        if not nbrs[i]:
            continue
        angles = np.sort(np.arccos(np.clip(z[nbrs[i]] @ z[i], -1.0, 1.0)))
        angle = angles[min(1, len(angles) - 1)]
        depth = float(np.linalg.norm(cam.center - foot))
        f = 0.5 * (cam.K[0, 0] + cam.K[1, 1])
        heights.append(parallax_px * depth / (f * max(np.sin(angle), 1e-3)))
    return float(np.median(heights)) if heights else 0.0


def colour_log_ratio(guide: np.ndarray, sure_fg: np.ndarray, sure_bg: np.ndarray, where: np.ndarray,
                     components: int = 5, samples: int = 1500, seed: int = 0) -> np.ndarray | None:
    """(H, W) log p(colour | object) - log p(colour | table) at ``where`` (0 elsewhere), from
    Gaussian mixtures (OpenCV EM, CIE Lab) fitted to this view's ``sure_fg`` and ``sure_bg``
    pixels; None when either has too few pixels or nothing is asked."""
    import cv2

    if not where.any() or sure_fg.sum() < 10 * components or sure_bg.sum() < 10 * components:
        return None
    lab = cv2.cvtColor(guide, cv2.COLOR_RGB2Lab).astype(np.float64)
    rng = np.random.default_rng(seed)
    out = np.zeros(guide.shape[:2])
    query = lab[where]
    logp = []
    for sel in (sure_fg, sure_bg):
        x = lab[sel]
        if len(x) > samples:
            x = x[rng.choice(len(x), samples, replace=False)]
        em = cv2.ml.EM_create()
        em.setClustersNumber(components)
        em.setCovarianceMatrixType(cv2.ml.EM_COV_MAT_DIAGONAL)
        em.setTermCriteria((cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 20, 1e-3))
        em.trainEM(x)
        logp.append(_em_loglik(em, query))
    out[where] = np.clip(logp[0] - logp[1], -10.0, 10.0)
    return out


def _em_loglik(em, x: np.ndarray) -> np.ndarray:
    """Log-likelihood of rows ``x (N, D)`` under a trained OpenCV EM model (diagonal covariances)."""
    means = em.getMeans()
    weights = em.getWeights().ravel()
    covs = em.getCovs()
    ll = []
    for k in range(len(weights)):
        var = np.maximum(np.diag(covs[k]), 1e-6)
        d = (x - means[k]) ** 2 / var
        ll.append(np.log(max(weights[k], 1e-12)) - 0.5 * (d.sum(1) + np.log(2 * np.pi * var).sum()))
    ll = np.stack(ll, 1)
    top = ll.max(1, keepdims=True)
    return (top + np.log(np.exp(ll - top).sum(1, keepdims=True))).ravel()


def unlit_pixels(rgb_linear: np.ndarray, settings: MaskSettings | None = None,
                 max_fraction: float = 0.05) -> np.ndarray:
    """(H, W) bool: the far background the flash hardly reaches, beyond the lit object and table:
    pixels darker than the flash-falloff threshold of :func:`recon.masks.derive_mask` and than
    ``max_fraction`` of the image's 90th percentile (a view filled by the lit table has no dark
    mode, and its darker texture must not count); all False when no threshold is found."""
    settings = MaskSettings() if settings is None else settings
    img = np.nan_to_num(np.maximum(np.asarray(rgb_linear, np.float32)[:, :, :3], 0.0))
    try:
        _, info = derive_mask(img, settings)
    except MaskError:
        return np.zeros(img.shape[:2], bool)
    lum = img @ LUMA
    top = float(np.percentile(lum, 99.9))
    t = min(info["threshold_log10"], float(np.log10(max(max_fraction * np.percentile(lum, 90), 1e-30))))
    return np.log10(np.maximum(lum, settings.floor * top)) <= t


# ---------------------------------------------------------------------------------------------
# Step 2: plane consistency
# ---------------------------------------------------------------------------------------------
def plane_consistency(images: list[np.ndarray], cams: CameraSet, plane: SupportPlane, i: int,
                      nbrs: list[int], settings: SegmentSettings = SegmentSettings(),
                      guide: np.ndarray | None = None) -> np.ndarray:
    """C_i (H, W) float32 of view ``i`` (module docstring, step 2); inf where no neighbour sees
    the pixel's plane point (or the ray misses the plane)."""
    import cv2

    ci = cams.frames[i]
    L_i = np.nan_to_num(np.maximum(images[i][:, :, :3], 0.0)).astype(np.float32)
    P, hit = plane_points(ci, plane)
    E_i = flash_shading(ci.center, P, plane)
    floor = settings.floor * max(float(np.percentile(L_i.mean(-1), 90)), 1e-12)
    if guide is None:
        guide = display_image(L_i)
    eps = 1e-3 * 255.0**2
    best = np.full(L_i.shape[:2], np.inf, np.float32)
    flat = P.reshape(-1, 3)
    for j in nbrs:
        cj = cams.frames[j]
        H = plane_homography(ci, cj, plane)
        L_j = cv2.warpPerspective(np.nan_to_num(np.maximum(images[j][:, :, :3], 0.0)).astype(np.float32), H,
                                  (ci.width, ci.height), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                  borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        xy, z = cj.project(flat)
        xy, z = xy.reshape(P.shape[:2] + (2,)), z.reshape(P.shape[:2])
        seen = hit & (z > 0) & (xy[..., 0] >= 1) & (xy[..., 0] <= cj.width - 1) \
            & (xy[..., 1] >= 1) & (xy[..., 1] <= cj.height - 1)
        if seen.sum() < 100:
            continue
        E_j = flash_shading(cj.center, P, plane)
        with np.errstate(divide="ignore", invalid="ignore"):
            pred = L_j * np.where(seen, E_i / E_j, 0.0)[..., None].astype(np.float32)
        bright = seen & (L_i.mean(-1) > floor) & (pred.mean(-1) > floor)
        if bright.sum() >= 100:  # one gain per pair (exposure, light): the median log ratio
            r = np.log(L_i[bright] + 1e-12) - np.log(pred[bright] + 1e-12)
            pred *= np.exp(np.median(r, axis=0)).astype(np.float32)
        D = (np.abs(L_i - pred) / (floor + 0.5 * (L_i + pred))).sum(-1)
        D = np.where(seen, D, 0.0).astype(np.float32)
        # average over a window that follows the photo's edges; unseen pixels do not count
        w = seen.astype(np.float32)
        num = cv2.ximgproc.guidedFilter(guide, D, settings.window, eps)
        den = cv2.ximgproc.guidedFilter(guide, w, settings.window, eps)
        with np.errstate(divide="ignore", invalid="ignore"):
            Dm = np.where(seen & (den > 0.3), num / np.maximum(den, 1e-6), np.inf)
        best = np.minimum(best, Dm.astype(np.float32))
    return best


# ---------------------------------------------------------------------------------------------
# Step 3: a tolerant visual hull above the plane
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Hull:
    """A carved hull: occupied voxel centers ``points (N, 3)``, the voxel size ``step``, the
    ``surface (M, 3)`` voxels (occupied, with an empty 6-neighbour: their footprints cover the
    hull's silhouette in any view), and ``band (K, 3)``: the surface voxels lower than the band
    where the plane test cannot see parallax (extruded down to the plane, see :func:`carve`)."""

    points: np.ndarray
    step: float
    surface: np.ndarray
    band: np.ndarray

    def bbox(self) -> tuple[np.ndarray, np.ndarray]:
        return self.points.min(0) - self.step, self.points.max(0) + self.step

    def box_on(self, plane: SupportPlane) -> tuple[np.ndarray, float, float]:
        """The hull's box on ``plane``: center of its footprint (on the plane), horizontal half
        size and height."""
        B = plane.basis()
        q = self.points @ B[:2].T
        lo, hi = q.min(0), q.max(0)
        mid = 0.5 * (lo + hi)
        foot = plane.project(mid[0] * B[0] + mid[1] * B[1])
        return foot, 0.5 * float(np.max(hi - lo)) + self.step, float(plane.height(self.points).max()) + self.step

    def project(self, cam: Camera, which: str = "surface") -> np.ndarray:
        """(H, W) bool: the silhouette in ``cam`` of the hull (``which="surface"``) or of its low
        band (``"band"``), voxels splatted at their footprint."""
        import cv2

        pts = self.surface if which == "surface" else self.band
        out = np.zeros((cam.height, cam.width), np.uint8)
        if len(pts) == 0:
            return out.astype(bool)
        xy, z = cam.project(pts)
        front = z > 1e-9
        if not front.any():
            return out.astype(bool)
        xy, z = xy[front], z[front]
        f = 0.5 * (cam.K[0, 0] + cam.K[1, 1])
        radius = np.clip(np.ceil(0.5 * np.sqrt(3.0) * self.step * f / z), 1, 64).astype(int)  # half diagonal
        for r in np.unique(radius):
            sel = radius == r
            layer = np.zeros_like(out)
            ij = np.floor(xy[sel]).astype(int)
            ok = (ij[:, 0] >= 0) & (ij[:, 0] < cam.width) & (ij[:, 1] >= 0) & (ij[:, 1] < cam.height)
            layer[ij[ok, 1], ij[ok, 0]] = 1
            out |= cv2.dilate(layer, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r - 1, 2 * r - 1)))
        return out.astype(bool)


UNKNOWN = 2
"""A mask value (uint8 masks of :func:`carve`): the view cannot tell; it neither keeps nor carves."""


def _plane_grid(plane: SupportPlane, center, half: float, height: float, resolution: int, band: float):
    """Voxel centers ``pts (N, 3)`` of the grid of :func:`carve` (axes e1, e2, normal), its
    ``shape``, ``step``, the first layer above the band ``k_band`` and the tested voxels ``idx``."""
    B = plane.basis()
    foot = plane.project(np.asarray(center, float))
    step = 2.0 * float(half) / resolution
    nu = max(int(resolution), 1)
    nw = max(int(np.ceil(float(height) / step)), 1)
    u = -half + (np.arange(nu) + 0.5) * step
    w = (np.arange(nw) + 0.5) * step
    U, V, Wh = np.meshgrid(u, u, w, indexing="ij")
    pts = foot + U[..., None] * B[0] + V[..., None] * B[1] + Wh[..., None] * B[2]
    shape = pts.shape[:3]
    k_band = int(np.clip(np.ceil(band / step - 0.5), 0, nw - 1)) if band > 0 else 0
    tested = np.zeros(shape, bool)
    tested[:, :, k_band:] = True  # voxels tested against the masks; those below copy the band's top
    return pts.reshape(-1, 3), shape, step, k_band, np.flatnonzero(tested.reshape(-1))


def _view_values(mask: np.ndarray, cam: Camera, points: np.ndarray) -> np.ndarray:
    """(N,) uint8 mask value at each point's pixel: 0, 1, or :data:`UNKNOWN` (outside the view)."""
    P = (cam.K @ cam.world_to_camera[:3, :]).astype(np.float32)
    h = np.asarray(points, np.float32) @ P[:, :3].T + P[:, 3]
    z = h[:, 2]
    zs = np.where(z > 1e-12, z, np.float32(1.0))
    j = np.floor(h[:, 0] / zs).astype(np.int64)
    i = np.floor(h[:, 1] / zs).astype(np.int64)
    inside = (z > 0) & (j >= 0) & (j < cam.width) & (i >= 0) & (i < cam.height)
    value = np.full(len(points), UNKNOWN, np.uint8)
    value[inside] = mask[i[inside], j[inside]]
    return value


def _shell(occ: np.ndarray) -> np.ndarray:
    from scipy import ndimage

    return occ & ~ndimage.binary_erosion(occ, border_value=0)


def hole_support(masks: list[np.ndarray], cams: CameraSet, plane: SupportPlane, center: np.ndarray,
                 half: float, height: float, resolution: int, tolerance: float, band: float = 0.0,
                 views: list[int] | None = None) -> dict[int, np.ndarray]:
    """Per view (index: ``views``, default all), the silhouette of the hull carved by the OTHER
    views' masks (leave one out).

    A hole in view i's mask that this silhouette covers is contradicted by the other views (a
    patch where the object happened to agree with the table); a real opening (the table seen
    through a handle) is seen by a few other views too, which carve it away. ``tolerance`` is
    the share of the other views' misses a voxel survives (small: the few views that look
    through a handle must be enough).
    """
    pts, shape, step, k_band, idx = _plane_grid(plane, center, half, height, resolution, band)
    q = pts[idx].astype(np.float32)
    values = [_view_values(m, cam, q) for m, cam in zip(masks, cams, strict=True)]
    seen = np.sum([v != UNKNOWN for v in values], axis=0)
    miss = np.sum([v == 0 for v in values], axis=0)
    out = {}
    for k in range(len(cams)) if views is None else views:
        cam, v = cams.frames[k], values[k]
        s_o = seen - (v != UNKNOWN)
        m_o = miss - (v == 0)
        occ = np.zeros(len(pts), bool)
        occ[idx[(s_o >= 2) & (m_o <= np.floor(tolerance * s_o))]] = True
        occ = occ.reshape(shape)
        if k_band > 0:
            occ[:, :, :k_band] = occ[:, :, k_band:k_band + 1]
        hull = Hull(pts[occ.reshape(-1)], step, pts[_shell(occ).reshape(-1)], np.zeros((0, 3)))
        out[k] = hull.project(cam) if len(hull.points) else np.zeros((cam.height, cam.width), bool)
    return out


def carve(masks: list[np.ndarray], cams: CameraSet, plane: SupportPlane, center: np.ndarray, half: float,
          height: float, resolution: int, tolerance: float, seed_point: np.ndarray | None = None,
          band: float = 0.0, min_voxels: int = 8) -> Hull | None:
    """A visual hull standing on ``plane``, on a grid aligned with it.

    The box: ``half`` either side of ``center``'s foot on the plane, from the plane up to
    ``height``, ``resolution`` voxels across. A voxel is kept when it projects inside the masks
    of all views that see it but ``tolerance`` of them (a view's own misses do not carve). Masks
    are bool, or uint8 with :data:`UNKNOWN` where the view cannot tell (that view does not count
    for the voxel). Voxels lower than ``band`` (where the plane test sees too little parallax to
    tell object from table) take the value of the first layer above it: the object stands on the
    plane. The connected component nearest ``seed_point`` (default the largest) is returned;
    None when fewer than ``min_voxels`` survive.
    """
    from scipy import ndimage

    pts, shape, step, k_band, idx = _plane_grid(plane, center, half, height, resolution, band)
    q = pts[idx].astype(np.float32)
    values = [_view_values(m, cam, q) for m, cam in zip(masks, cams, strict=True)]
    seen = np.sum([v != UNKNOWN for v in values], axis=0)
    miss = np.sum([v == 0 for v in values], axis=0)
    ok = (seen >= 2) & (miss <= np.floor(tolerance * seen))
    occ = np.zeros(len(pts), bool)
    occ[idx[ok]] = True
    occ = occ.reshape(shape)
    if k_band > 0:
        occ[:, :, :k_band] = occ[:, :, k_band:k_band + 1]
    labels, n = ndimage.label(occ)
    if n == 0 or occ.sum() < min_voxels:
        return None
    sizes = ndimage.sum_labels(occ, labels, index=np.arange(1, n + 1))
    if seed_point is not None and n > 1:
        # the component nearest the seed, among those of at least 1% of the largest one's size
        dist = np.linalg.norm(pts - np.asarray(seed_point, float), axis=1).reshape(shape)
        nearest = ndimage.minimum(dist, labels, index=np.arange(1, n + 1))
        nearest = np.where(sizes >= 0.01 * sizes.max(), nearest, np.inf)
        label = 1 + int(np.argmin(nearest))
    else:
        label = 1 + int(np.argmax(sizes))
    occ = labels == label
    if occ.sum() < min_voxels:
        return None
    shell = _shell(occ)
    low = np.zeros(shape, bool)
    low[:, :, :max(k_band, 0)] = True
    return Hull(pts[occ.reshape(-1)], step, pts[shell.reshape(-1)], pts[(shell & low).reshape(-1)])


# ---------------------------------------------------------------------------------------------
# Step 4: graph cut
# ---------------------------------------------------------------------------------------------
def graph_cut(cost_fg: np.ndarray, cost_bg: np.ndarray, guide: np.ndarray, smoothness: float,
              active: np.ndarray | None = None) -> np.ndarray:
    """Minimum of sum(cost) + smoothness * sum over 4-neighbours of exp(-|dI|^2 / (2 <|dI|^2>))
    [labels differ]; returns the (H, W) bool foreground. ``active`` limits the graph to a
    region (pixels outside it are background). Costs are in units of one pairwise weight."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import breadth_first_order, maximum_flow

    H, W = cost_fg.shape
    act = np.ones((H, W), bool) if active is None else active.copy()
    fg = np.zeros((H, W), bool)
    if not act.any():
        return fg
    rows, cols = np.nonzero(act)
    i0, i1, j0, j1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
    act = act[i0:i1, j0:j1]
    g = guide[i0:i1, j0:j1].astype(np.float32)
    cf, cb = cost_fg[i0:i1, j0:j1], cost_bg[i0:i1, j0:j1]
    h, w = act.shape
    dx = ((g[:, 1:] - g[:, :-1]) ** 2).sum(-1)
    dy = ((g[1:, :] - g[:-1, :]) ** 2).sum(-1)
    beta = 1.0 / (2.0 * max(float(np.concatenate([dx.ravel(), dy.ravel()]).mean()), 1e-6))
    scale = 100.0
    wx = np.rint(scale * smoothness * np.exp(-beta * dx)).astype(np.int64)
    wy = np.rint(scale * smoothness * np.exp(-beta * dy)).astype(np.int64)
    n = h * w
    s, t = n, n + 1
    idx = np.arange(n).reshape(h, w)
    # a pixel outside the active region is tied to the background
    cf = np.where(act, cf, 1e6)
    cb = np.where(act, cb, 0.0)
    cap_s = np.rint(scale * np.clip(cb, 0, 1e6)).astype(np.int64)  # cut s->p: p is background
    cap_t = np.rint(scale * np.clip(cf, 0, 1e6)).astype(np.int64)  # cut p->t: p is foreground
    r = [np.full(n, s), idx.ravel(), idx[:, :-1].ravel(), idx[:, 1:].ravel(), idx[:-1].ravel(), idx[1:].ravel()]
    c = [idx.ravel(), np.full(n, t), idx[:, 1:].ravel(), idx[:, :-1].ravel(), idx[1:].ravel(), idx[:-1].ravel()]
    cap = [cap_s.ravel(), cap_t.ravel(), wx.ravel(), wx.ravel(), wy.ravel(), wy.ravel()]
    r, c, cap = np.concatenate(r), np.concatenate(c), np.concatenate(cap)
    keep = cap > 0
    G = csr_matrix((cap[keep].astype(np.int32), (r[keep], c[keep])), shape=(n + 2, n + 2))
    flow = maximum_flow(G, s, t).flow
    resid = (G - flow).tocsr()
    resid.data = np.maximum(resid.data, 0)
    resid.eliminate_zeros()
    reach = breadth_first_order(resid, s, directed=True, return_predecessors=False)
    side = np.zeros(n + 2, bool)
    side[reach] = True
    fg[i0:i1, j0:j1] = side[:n].reshape(h, w) & act
    return fg


def _fill_small_holes(mask: np.ndarray, max_fraction: float) -> np.ndarray:
    from scipy import ndimage

    holes = ndimage.binary_fill_holes(mask) & ~mask
    if not holes.any():
        return mask
    hl, nh = ndimage.label(holes)
    sizes = ndimage.sum_labels(holes, hl, index=np.arange(1, nh + 1))
    small = np.flatnonzero(sizes <= max_fraction * mask.sum()) + 1
    return mask | np.isin(hl, small)


def _has_holes(mask: np.ndarray) -> bool:
    from scipy import ndimage

    return bool((ndimage.binary_fill_holes(mask) & ~mask).any())


def _fill_holes_inside(mask: np.ndarray, solid: np.ndarray) -> np.ndarray:
    """``mask`` with each hole filled where ``solid`` (a hull projection) covers 90% of it: a
    hole the other views contradict (a patch of chance agreement with the table) is filled, one
    they share (the table seen through a handle) stays open."""
    from scipy import ndimage

    holes = ndimage.binary_fill_holes(mask) & ~mask
    if not holes.any():
        return mask
    hl, nh = ndimage.label(holes)
    covered = ndimage.mean(solid, hl, index=np.arange(1, nh + 1))
    return mask | np.isin(hl, np.flatnonzero(covered >= 0.9) + 1)


def _components_touching(mask: np.ndarray, region: np.ndarray) -> np.ndarray:
    from scipy import ndimage

    labels, n = ndimage.label(mask)
    if n == 0:
        return mask
    keep = np.unique(labels[region & mask])
    return np.isin(labels, keep[keep > 0])


def _dilate(mask: np.ndarray, px: int) -> np.ndarray:
    import cv2

    if px <= 0:
        return mask
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * px + 1, 2 * px + 1))
    return cv2.dilate(mask.astype(np.uint8), k).astype(bool)


def _erode(mask: np.ndarray, px: int) -> np.ndarray:
    import cv2

    if px <= 0:
        return mask
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * px + 1, 2 * px + 1))
    return cv2.erode(mask.astype(np.uint8), k).astype(bool)


# ---------------------------------------------------------------------------------------------
# The whole method
# ---------------------------------------------------------------------------------------------
def segment_tabletop(images: list[np.ndarray], cams: CameraSet, plane: SupportPlane,
                     settings: SegmentSettings = SegmentSettings()) -> tuple[list[np.ndarray], dict]:
    """Masks of the object standing on ``plane`` in every view (module docstring, steps 2-5).

    Parameters
    ----------
    images : list of (H, W, 3) float linear images, one per camera of ``cams``, pinhole.
    cams : the cameras (OpenCV axes) in the frame of ``plane``.

    Returns
    -------
    masks : list of (H, W) bool
    info : dict
        ``views`` (per view: coverage, hull coverage, C statistics), ``hull`` (voxel size,
        bounding box, height above the plane), ``seconds``.

    Raises
    ------
    SegmentError
        The object cannot be separated from the table (no hull, or views whose masks are empty
        or fill their whole region); the message names the views and what to try.
    """
    t0 = time.perf_counter()
    n = len(cams)
    if len(images) != n:
        raise ValueError(f"segment_tabletop: {len(images)} images for {n} cameras")
    for img, cam in zip(images, cams, strict=True):
        if img.shape[:2] != (cam.height, cam.width):
            raise SegmentError(f"{cam.image}: image is {img.shape[1]}x{img.shape[0]} but its camera is "
                               f"{cam.width}x{cam.height}")
    guides = [display_image(np.nan_to_num(np.maximum(im[:, :, :3], 0.0))) for im in images]
    nbrs = neighbours(cams, settings)
    C = []
    for i in range(n):
        C.append(plane_consistency(images, cams, plane, i, nbrs[i], settings, guides[i]))
    timings = {"consistency_s": time.perf_counter() - t0}

    # ---- step 3: the hull of the liberal masks, near the aim point, above the plane ----
    t1 = time.perf_counter()
    target = aim_point(cams)
    scale = scene_scale(cams, target)
    foot = plane.project(target)
    # pixels the flash does not light (a far background) are never object, whatever C says
    unlit = [unlit_pixels(im) for im in images]
    liberal = [np.where(u, 0, np.where(np.isfinite(c), _fill_small_holes(c > settings.carve_threshold,
                                                                         settings.max_hole_fraction), UNKNOWN))
               .astype(np.uint8) for c, u in zip(C, unlit, strict=True)]
    band = parallax_band(cams, nbrs, foot, settings.band_parallax_px)
    hull = carve(liberal, cams, plane, foot, 0.6 * scale, 0.8 * scale, max(32, settings.hull_resolution // 2),
                 settings.carve_tolerance, seed_point=foot + 0.05 * scale * plane.normal, band=band)
    if hull is None:
        raise SegmentError(
            "no object stands on the support plane: no region of the views is inconsistent with the table in "
            "all of them (views: " + ", ".join(c.stem for c in cams) + "). What to try: check that the object "
            "is in the middle of every photo, that the table is in focus and textured, or give masks/ in the "
            "capture")
    box_foot, box_half, box_height = hull.box_on(plane)
    pad = 4 * hull.step
    box = (box_foot, box_half + pad, box_height + pad)
    hull = carve(liberal, cams, plane, *box, settings.hull_resolution, settings.carve_tolerance,
                 seed_point=box_foot + 0.5 * box_height * plane.normal, band=band)
    if hull is None:
        raise SegmentError("the object's hull vanished at full resolution: the views disagree about it (views: "
                           + ", ".join(c.stem for c in cams) + "); check the cameras, or give masks/ in the capture")
    timings["hull_s"] = time.perf_counter() - t1

    # ---- step 4: graph cut per view inside the hull projection ----
    t1 = time.perf_counter()
    masks, views = [], {}
    for i, cam in enumerate(cams):
        region = hull.project(cam)
        active = _dilate(region, settings.hull_margin_px)
        c = np.where(np.isfinite(C[i]), C[i], settings.threshold)
        z = np.clip((c - settings.threshold) / settings.softness, -30, 30)
        z = np.where(unlit[i], np.minimum(z, -4.0), z)
        # where the object stands low on the table the plane test sees no parallax: a table-like C
        # there says nothing; the colours of this view's sure object and sure table decide
        low = hull.project(cam, "band") & (z < 0)
        llr = colour_log_ratio(guides[i], sure_fg=region & (z > 2) & ~low,
                               sure_bg=_dilate(region, 3 * settings.hull_margin_px) & (z < -2) & ~low,
                               where=low)
        if llr is not None:
            z = np.where(low, np.clip(settings.colour_weight * llr, -30, 30), z)
        cost_fg = np.logaddexp(0.0, -z)  # -log sigmoid(z)
        cost_bg = np.logaddexp(0.0, z)
        m = graph_cut(cost_fg, cost_bg, guides[i], settings.smoothness, active)
        m = _components_touching(m, _erode(region, settings.hull_margin_px))
        masks.append(m)
        views[cam.stem] = {"hull_coverage": float(region.mean())}
    timings["graph_cut_s"] = time.perf_counter() - t1

    # ---- step 5: cross-check with a hull of the cut masks ----
    t1 = time.perf_counter()
    hull2 = carve(masks, cams, plane, *box, settings.hull_resolution, settings.carve_tolerance,
                  seed_point=box_foot + 0.5 * box_height * plane.normal)
    if hull2 is not None:
        masks = [m & _dilate(hull2.project(cam), 1) for m, cam in zip(masks, cams, strict=True)]
        with_holes = [i for i, m in enumerate(masks) if _has_holes(m)]
        support = hole_support(masks, cams, plane, *box, settings.hull_resolution, settings.hole_tolerance,
                               band=band, views=with_holes)
    bad = []
    for i, cam in enumerate(cams):
        m = masks[i]
        if hull2 is not None:
            if i in support:
                m = _fill_holes_inside(m, support[i])
        else:
            m = _fill_small_holes(m, settings.max_hole_fraction)
        masks[i] = m
        v = views[cam.stem]
        v["coverage"] = float(m.mean())
        c = C[i][np.isfinite(C[i])]
        v["consistency_median"] = float(np.median(c)) if c.size else None
        if not m.any():
            bad.append(f"{cam.stem}: empty mask")
        elif m[0].any() and m[-1].any() and m[:, 0].any() and m[:, -1].any():
            bad.append(f"{cam.stem}: the mask touches all four image borders")
    timings["cross_check_s"] = time.perf_counter() - t1
    if bad:
        raise SegmentError(
            "the object could not be separated from the table in these views:\n  " + "\n  ".join(bad)
            + "\nWhat to try: keep the whole object inside every photo with table around it, photograph from "
            "15-60 degrees above the table, use a textured table or a printed mat, or give masks/<stem>.png "
            "for these views in the capture")
    hb_lo, hb_hi = (hull2 or hull).bbox()
    corners = np.array([[x, y, z] for x in (hb_lo[0], hb_hi[0]) for y in (hb_lo[1], hb_hi[1])
                        for z in (hb_lo[2], hb_hi[2])])
    info = {"views": views, "neighbours": {cams.frames[i].stem: [cams.frames[j].stem for j in nbrs[i]]
                                           for i in range(n)},
            "hull": {"step": (hull2 or hull).step, "parallax_band": band, "voxels": int(len((hull2 or hull).points)),
                     "bbox_lo": hb_lo.tolist(), "bbox_hi": hb_hi.tolist(),
                     "height": float(plane.height(corners).max())},
            "timings": {**timings, "total_s": time.perf_counter() - t0}}
    return masks, info
