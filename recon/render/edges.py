"""Silhouette edges of a triangle mesh seen from a camera, as clipped image-space segments.

The boundary term of the rendering derivative (DESIGN section 3, the paper's eq. 4-5) lives on
the image-plane projections of the mesh's silhouettes. This module finds them (numpy, vectorized
over edges and views): the edge topology once per mesh (:func:`edge_topology`), then per call
the edges whose two faces face opposite ways from each camera center, plus open and non-manifold
edges, clipped to the camera's near plane and to the image rectangle
(:func:`silhouette_segments`). Occlusion is not decided here; the renderer tests it per sample.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from recon.io.cameras import Camera

__all__ = ["EdgeTopology", "SilhouetteSegments", "edge_topology", "silhouette_segments"]


@dataclass(frozen=True)
class EdgeTopology:
    """Unique edges of a triangle mesh and the faces beside them.

    Attributes
    ----------
    edges : (E, 2) int64
        Vertex ids, smaller id first.
    face_a, face_b : (E,) int64
        The two faces sharing the edge; ``face_b`` is -1 for an open (boundary) edge.
    consistent : (E,) bool
        True where ``face_a`` and ``face_b`` run along the edge in opposite directions
        (consistently oriented neighbours); the silhouette test flips where they do not.
    always : (E,) bool
        Open or non-manifold (> 2 faces) edges: a candidate silhouette in every view.
    """

    edges: np.ndarray
    face_a: np.ndarray
    face_b: np.ndarray
    consistent: np.ndarray
    always: np.ndarray

    def __len__(self) -> int:
        return len(self.edges)


def edge_topology(t_pos_idx: np.ndarray) -> EdgeTopology:
    """Edges of a mesh with faces ``t_pos_idx`` (F, 3) int.

    Degenerate faces (a repeated vertex) contribute their non-degenerate edges.
    """
    f = np.asarray(t_pos_idx, dtype=np.int64).reshape(-1, 3)
    nf = len(f)
    # Directed half-edges (v_k -> v_{k+1}) of every face.
    src = f.reshape(-1)
    dst = f[:, [1, 2, 0]].reshape(-1)
    face = np.repeat(np.arange(nf, dtype=np.int64), 3)
    keep = src != dst
    src, dst, face = src[keep], dst[keep], face[keep]
    lo, hi = np.minimum(src, dst), np.maximum(src, dst)
    forward = src < dst
    key = lo * (int(hi.max(initial=0)) + 1) + hi
    order = np.argsort(key, kind="stable")
    key, lo, hi, forward, face = key[order], lo[order], hi[order], forward[order], face[order]
    first = np.ones(len(key), dtype=bool)
    first[1:] = key[1:] != key[:-1]
    start = np.flatnonzero(first)
    count = np.diff(np.append(start, len(key)))
    second = np.minimum(start + 1, len(key) - 1)
    two = count == 2
    face_a = face[start]
    face_b = np.where(two, face[second], -1)
    consistent = np.where(two, forward[start] != forward[second], True)
    edges = np.stack([lo[start], hi[start]], axis=1)
    return EdgeTopology(edges, face_a, face_b, consistent, count != 2)


@dataclass(frozen=True)
class SilhouetteSegments:
    """Silhouette candidates of a batch of views, clipped to each view's image.

    Attributes
    ----------
    view : (S,) int64
        Index of the camera in the batch.
    v0, v1 : (S,) int64
        Vertex ids of the mesh edge.
    a, b : (S, 2) float64
        Clipped segment end points in pixel coordinates (x = column, y = row).
    length : (S,) float64
        ``|b - a|`` in pixels (> 0).
    total_length : (B,) float64
        Sum of ``length`` per view.
    """

    view: np.ndarray
    v0: np.ndarray
    v1: np.ndarray
    a: np.ndarray
    b: np.ndarray
    length: np.ndarray
    total_length: np.ndarray

    def __len__(self) -> int:
        return len(self.view)


def _liang_barsky(p: np.ndarray, q: np.ndarray, width: np.ndarray, height: np.ndarray):
    """Clip segments ``p -> q`` ((n, 2) each) to [0, width] x [0, height] (per row).

    Returns the parameter interval ``(t0, t1)`` of the part inside (empty where t0 >= t1).
    """
    d = q - p
    t0 = np.zeros(len(p))
    t1 = np.ones(len(p))
    bounds = (
        (-d[:, 0], p[:, 0]),  # x >= 0
        (d[:, 0], width - p[:, 0]),  # x <= width
        (-d[:, 1], p[:, 1]),  # y >= 0
        (d[:, 1], height - p[:, 1]),  # y <= height
    )
    for pk, qk in bounds:
        parallel = pk == 0
        outside = parallel & (qk < 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.where(parallel, 0.0, qk / np.where(parallel, 1.0, pk))
        entering = (pk < 0) & ~parallel
        leaving = (pk > 0) & ~parallel
        t0 = np.where(entering, np.maximum(t0, r), t0)
        t1 = np.where(leaving, np.minimum(t1, r), t1)
        t1 = np.where(outside, -1.0, t1)
    return t0, t1


def silhouette_segments(
    v_pos: np.ndarray,
    t_pos_idx: np.ndarray,
    topo: EdgeTopology,
    cameras: Sequence[Camera],
    near_fraction: float = 1e-6,
) -> SilhouetteSegments:
    """Image-space silhouette segments of a mesh in each camera.

    Parameters
    ----------
    v_pos : (V, 3) float
        Vertex positions (world).
    t_pos_idx : (F, 3) int
        Faces; ``topo`` must be ``edge_topology(t_pos_idx)``.
    topo : EdgeTopology
    cameras : sequence of B :class:`Camera`
    near_fraction : float
        The near plane sits at this fraction of the farthest vertex depth (> 0), so edges that
        cross the camera plane are clipped before projection.

    Returns
    -------
    SilhouetteSegments
        Edges whose two faces face opposite ways from the camera center (a front and a back
        face), and open or non-manifold edges, clipped to z > near and to the image rectangle.
    """
    v = np.asarray(v_pos, dtype=np.float64)
    f = np.asarray(t_pos_idx, dtype=np.int64)
    p0 = v[f[:, 0]]
    fn = np.cross(v[f[:, 1]] - p0, v[f[:, 2]] - p0)  # (F, 3)
    e0, e1 = topo.edges[:, 0], topo.edges[:, 1]
    has_b = topo.face_b >= 0
    fb = np.where(has_b, topo.face_b, 0)
    out = {k: [] for k in ("view", "v0", "v1", "a", "b", "length")}
    totals = np.zeros(len(cameras))
    for vi, cam in enumerate(cameras):
        center = cam.center
        # Front-facing faces: the camera center lies on the side the face normal points to.
        front = np.einsum("ij,ij->i", fn, center[None, :] - p0) > 0
        flip = front[topo.face_a] != front[fb]
        sil = topo.always | (has_b & (flip == topo.consistent))
        idx = np.flatnonzero(sil)
        if len(idx) == 0:
            continue
        R = cam.world_to_camera[:3, :3]
        t = cam.world_to_camera[:3, 3]
        x0 = v[e0[idx]] @ R.T + t
        x1 = v[e1[idx]] @ R.T + t
        zmax = max(float(np.max(np.abs(v @ R.T + t)[:, 2])), 1e-300)
        near = near_fraction * zmax
        z0, z1 = x0[:, 2], x1[:, 2]
        keep = (z0 > near) | (z1 > near)
        x0, x1, z0, z1, idx = x0[keep], x1[keep], z0[keep], z1[keep], idx[keep]
        # Near-plane clip in 3D: move the end behind the plane onto it.
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.clip((near - z0) / (z1 - z0), 0.0, 1.0)
        c0 = np.where((z0 < near)[:, None], x0 + s[:, None] * (x1 - x0), x0)
        c1 = np.where((z1 < near)[:, None], x0 + s[:, None] * (x1 - x0), x1)
        K = cam.K
        q0 = c0 @ K.T
        q1 = c1 @ K.T
        q0 = q0[:, :2] / np.maximum(q0[:, 2:3], near)
        q1 = q1[:, :2] / np.maximum(q1[:, 2:3], near)
        w = np.full(len(q0), float(cam.width))
        h = np.full(len(q0), float(cam.height))
        t0, t1 = _liang_barsky(q0, q1, w, h)
        a = q0 + t0[:, None] * (q1 - q0)
        b = q0 + t1[:, None] * (q1 - q0)
        length = np.linalg.norm(b - a, axis=1)
        ok = (t1 > t0) & (length > 0) & np.all(np.isfinite(a), axis=1) & np.all(np.isfinite(b), axis=1)
        n = int(ok.sum())
        if n == 0:
            continue
        out["view"].append(np.full(n, vi, dtype=np.int64))
        out["v0"].append(e0[idx[ok]])
        out["v1"].append(e1[idx[ok]])
        out["a"].append(a[ok])
        out["b"].append(b[ok])
        out["length"].append(length[ok])
        totals[vi] = float(length[ok].sum())
    if not out["view"]:
        z2 = np.zeros((0, 2))
        zi = np.zeros(0, dtype=np.int64)
        return SilhouetteSegments(zi, zi, zi, z2, z2, np.zeros(0), totals)
    cat = {k: np.concatenate(vals) for k, vals in out.items()}
    return SilhouetteSegments(cat["view"], cat["v0"], cat["v1"], cat["a"], cat["b"],
                              cat["length"], totals)
