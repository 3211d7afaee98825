"""A visual hull standing on the support plane, decided by a vote of the views: a voxel is empty
when more than a share of the views that see it say so (views where it falls outside the frame
abstain). Its projection bounds each view's mask; leave-one-out hulls tell a hole that the other
views contradict from a real opening."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from recon.io.cameras import Camera, CameraSet
from recon.support import SupportPlane


@dataclass(frozen=True)
class Hull:
    """A carved hull: occupied voxel centers ``points (N, 3)``, the voxel size ``step``, the
    ``surface (M, 3)`` voxels (occupied, with an empty 6-neighbour: their footprints cover the
    hull's silhouette in any view), ``band (K, 3)``: the surface of the foot, the slab lower than
    the band where the plane test cannot see parallax (the section at its top, extruded down to
    the plane and widened by the band's height, see :func:`carve`), and ``upper (L, 3)``: the
    surface voxels above the band (None: all of ``surface``)."""

    points: np.ndarray
    step: float
    surface: np.ndarray
    band: np.ndarray
    upper: np.ndarray | None = None

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
        """(H, W) bool: the silhouette in ``cam`` of the hull (``which="surface"``), of its foot
        (``"band"``) or of its part above the foot (``"upper"``), voxels splatted at their footprint."""
        import cv2

        pts = {"surface": self.surface, "band": self.band,
               "upper": self.surface if self.upper is None else self.upper}[which]
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
            ij = np.floor(xy[radius == r]).astype(int)
            ij = ij[(ij[:, 0] >= 0) & (ij[:, 0] < cam.width) & (ij[:, 1] >= 0) & (ij[:, 1] < cam.height)]
            if not len(ij):
                continue
            # dilated within the layer's box grown by r only (the same pixels: nothing beyond r of
            # a point is reached): a hull reaching towards the cameras has a layer for every
            # radius up to 64, and each full-frame dilation of a 1600-px photo cost up to 0.4 s
            (x0, y0), (x1, y1) = np.maximum(ij.min(0) - r, 0), np.minimum(ij.max(0) + r + 1, [cam.width, cam.height])
            layer = np.zeros((y1 - y0, x1 - x0), np.uint8)
            layer[ij[:, 1] - y0, ij[:, 0] - x0] = 1
            out[y0:y1, x0:x1] |= cv2.dilate(layer, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r - 1, 2 * r - 1)))
        return out.astype(bool)


    def depth(self, cam: Camera) -> np.ndarray:
        """(H, W) float32: the depth (camera z) of the hull's nearest surface voxel at each pixel
        of ``cam`` (voxels splatted at their footprint), inf where the hull is not seen."""
        import cv2

        out = np.full((cam.height, cam.width), np.inf, np.float32)
        if len(self.surface) == 0:
            return out
        xy, z = cam.project(self.surface)
        ij = np.floor(xy).astype(int)
        ok = (z > 1e-9) & (ij[:, 0] >= 0) & (ij[:, 0] < cam.width) & (ij[:, 1] >= 0) & (ij[:, 1] < cam.height)
        ij, z = ij[ok], z[ok].astype(np.float32)
        f = 0.5 * (cam.K[0, 0] + cam.K[1, 1])
        radius = np.clip(np.ceil(0.5 * np.sqrt(3.0) * self.step * f / z), 1, 64).astype(int)
        for r in np.unique(radius):
            sel = radius == r
            # within the layer's box grown by r, as in project
            (x0, y0) = np.maximum(ij[sel].min(0) - r, 0)
            (x1, y1) = np.minimum(ij[sel].max(0) + r + 1, [cam.width, cam.height])
            layer = np.full((y1 - y0, x1 - x0), np.inf, np.float32)
            np.minimum.at(layer, (ij[sel, 1] - y0, ij[sel, 0] - x0), z[sel])
            k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r - 1, 2 * r - 1))
            out[y0:y1, x0:x1] = np.minimum(out[y0:y1, x0:x1],
                                           cv2.erode(layer, k, borderType=cv2.BORDER_CONSTANT, borderValue=np.inf))
        return out


UNKNOWN = 2
"""A mask value (uint8 masks of :func:`carve`): the view cannot tell; it neither keeps nor carves."""


def plane_grid(plane: SupportPlane, center, half: float, height: float, resolution: int, band: float):
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


def view_values(mask: np.ndarray, cam: Camera, points: np.ndarray) -> np.ndarray:
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


def shell(occ: np.ndarray) -> np.ndarray:
    from scipy import ndimage

    return occ & ~ndimage.binary_erosion(occ, border_value=0)


def extrude_band(occ: np.ndarray, k_band: int, step: float, band: float) -> np.ndarray:
    """``occ (nu, nv, nw)`` with the layers below ``k_band`` (the parallax band, where the plane
    test cannot tell the object's foot from the table) set to the section at the band's top,
    less the openings that run through the object above it.

    An opening through the object (a ring's hole, the gap under an arch) is an enclosed hole in
    its horizontal sections just above the band, and reaches the plane. The band's top layer,
    the lowest one the views test and the one they see through least, carves it only in part
    (a ring lying on a table: 25-90 % of its hole's voxels there, 100 % a few layers higher), so
    extruding it alone plugged the hole and gave the ring genus 0. A column inside an enclosed
    hole in at least half of the layers up to one band's height above the top is open down to
    the plane; holes smaller than 2 x 2 voxels (a few views' chance agreement with the table
    inside the object) do not count. A base that flares out below a narrower body (a bell's
    lip) is not enclosed by the body's sections and keeps its extruded section.
    """
    from scipy import ndimage

    if k_band <= 0:
        return occ
    base = occ[:, :, k_band].copy()
    m = max(1, int(np.ceil(band / step)))
    layers = occ[:, :, k_band + 1:k_band + 1 + m]
    if layers.shape[2]:
        enclosed = np.stack([ndimage.binary_fill_holes(layers[:, :, j]) & ~layers[:, :, j]
                             for j in range(layers.shape[2])], axis=-1)
        through = enclosed.mean(axis=2) >= 0.5
        if through.any():
            labels, n = ndimage.label(through)
            sizes = ndimage.sum_labels(through, labels, index=np.arange(1, n + 1))
            through = np.isin(labels, 1 + np.flatnonzero(sizes >= 4))
            base &= ~through
    occ[:, :, :k_band + 1] = base[:, :, None]
    return occ


def votes_needed(seen: np.ndarray, tolerance: float, min_votes: int = 1) -> np.ndarray:
    """How many views must put a voxel outside their masks to carve it, for ``seen`` views that
    see it: more than the share ``tolerance`` of them, and at least ``min_votes``."""
    return np.maximum(int(min_votes), 1 + np.floor(float(tolerance) * np.asarray(seen, np.float64) + 1e-9)
                      ).astype(np.int64)


def _seed_counts(labels, n, seeds, plane, center, half, step, shape, k_band):
    """Per component (1..n) of the grid ``labels``, how many ``seeds (K, 3)`` fall in it."""
    if seeds is None or len(seeds) == 0:
        return None
    B = plane.basis()
    foot = plane.project(np.asarray(center, float))
    q = (np.asarray(seeds, float) - foot) @ B.T
    ij = np.floor((q[:, :2] + half) / step).astype(int)
    k = np.floor(q[:, 2] / step).astype(int)
    ok = (ij >= 0).all(1) & (ij < shape[0]).all(1) & (k >= k_band) & (k < shape[2])
    if not ok.any():
        return None
    lab = labels[ij[ok, 0], ij[ok, 1], k[ok]]
    return np.bincount(lab[lab > 0] - 1, minlength=n)


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
    pts, shape, step, k_band, idx = plane_grid(plane, center, half, height, resolution, band)
    q = pts[idx].astype(np.float32)
    values = [view_values(m, cam, q) for m, cam in zip(masks, cams, strict=True)]
    seen = np.sum([v != UNKNOWN for v in values], axis=0)
    miss = np.sum([v == 0 for v in values], axis=0)
    out = {}
    for k in range(len(cams)) if views is None else views:
        cam, v = cams.frames[k], values[k]
        s_o = seen - (v != UNKNOWN)
        m_o = miss - (v == 0)
        occ = np.zeros(len(pts), bool)
        occ[idx[(s_o >= 2) & (m_o <= np.floor(tolerance * s_o))]] = True
        occ = extrude_band(occ.reshape(shape), k_band, step, band)
        hull = Hull(pts[occ.reshape(-1)], step, pts[shell(occ).reshape(-1)], np.zeros((0, 3)))
        out[k] = hull.project(cam) if len(hull.points) else np.zeros((cam.height, cam.width), bool)
    return out


def carve(masks: list[np.ndarray], cams: CameraSet, plane: SupportPlane, center: np.ndarray, half: float,
          height: float, resolution: int, tolerance: float, seed_point: np.ndarray | None = None,
          band: float = 0.0, min_voxels: int = 8, min_votes: int = 1, seeds: np.ndarray | None = None,
          standing: bool = False) -> Hull | None:
    """A visual hull standing on ``plane``, on a grid aligned with it.

    The box: ``half`` either side of ``center``'s foot on the plane, from the plane up to
    ``height``, ``resolution`` voxels across. A voxel is kept when it projects inside the masks
    of all views that see it but ``tolerance`` of them (a view's own misses do not carve), and
    always unless ``min_votes`` views put it outside (:func:`votes_needed`). Masks
    are bool, or uint8 with :data:`UNKNOWN` where the view cannot tell (that view does not count
    for the voxel). Voxels lower than ``band`` (where the plane test sees too little parallax to
    tell object from table) take the value of the first layer above it: the object stands on the
    plane (less the openings that run through the object above it, :func:`extrude_band`). The connected component holding most of ``seeds`` (sparse points of the object), else
    the one nearest ``seed_point``, else the largest, is returned (with ``standing``, among the
    components that stand on the plane only); None when fewer than ``min_voxels`` survive.

    Standing: a component stands when it reaches the plane, or comes within ``2 * band`` of it
    (at least two voxels): just above the band the plane test still sees little parallax, and an
    object whose foot resembles the table loses its lowest layers there to a few views' chance
    agreement (a wooden vase on a wooden table, photographed as JPEG). Its gap to the plane is
    then closed by extruding its lowest section down: the object stands on the plane.
    """
    from scipy import ndimage

    pts, shape, step, k_band, idx = plane_grid(plane, center, half, height, resolution, band)
    q = pts[idx].astype(np.float32)
    values = [view_values(m, cam, q) for m, cam in zip(masks, cams, strict=True)]
    seen = np.sum([v != UNKNOWN for v in values], axis=0)
    miss = np.sum([v == 0 for v in values], axis=0)
    ok = (seen >= 2) & (miss < votes_needed(seen, tolerance, min_votes))
    occ = np.zeros(len(pts), bool)
    occ[idx[ok]] = True
    occ = extrude_band(occ.reshape(shape), k_band, step, band)
    labels, n = ndimage.label(occ)
    if standing and n > 0:  # what floats above the plane (farther than the gap) does not stand on it
        k_gap = min(max(int(np.ceil(2.0 * band / step)), 2), shape[2] - 1)
        grounded = np.unique(labels[:, :, :k_gap + 1])
        occ &= np.isin(labels, grounded[grounded > 0])
        labels, n = ndimage.label(occ)
    if n == 0 or occ.sum() < min_voxels:
        return None
    sizes = ndimage.sum_labels(occ, labels, index=np.arange(1, n + 1))
    held = _seed_counts(labels, n, seeds, plane, center, half, step, shape, k_band) if n > 1 else None
    if held is not None and held.max() > 0:
        label = 1 + int(np.argmax(held))
    elif seed_point is not None and n > 1:
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
    if standing:
        low = int(np.flatnonzero(occ.any(axis=(0, 1)))[0])
        if low > 0:  # a gap within the band above the plane: the lowest section extruded down
            occ[:, :, :low] = occ[:, :, low:low + 1]
    surface = shell(occ)
    upper = surface.copy()
    upper[:, :, :k_band] = False
    if k_band > 0:
        # the foot: the band's slab under the section at its top, widened by the band's height
        # (a base flaring out below the band, like a bell's lip, lies in it)
        grow = int(np.ceil(band / step))
        foot = ndimage.binary_dilation(occ[:, :, k_band], iterations=grow) if grow > 0 else occ[:, :, k_band]
        slab = np.zeros(shape, bool)
        slab[:, :, :k_band] = foot[:, :, None]
        foot_pts = pts[shell(slab).reshape(-1)]
    else:
        foot_pts = np.zeros((0, 3))
    return Hull(pts[occ.reshape(-1)], step, pts[surface.reshape(-1)], foot_pts, pts[upper.reshape(-1)])
