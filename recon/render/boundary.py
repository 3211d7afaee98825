"""The boundary term of the differentiable renderer (:mod:`recon.render.collocated`): edge
sampling of the silhouettes (Li et al. 2018; the paper's eq. 4-5, Reynolds transport).

Silhouette edges are found per view (:mod:`recon.render.edges`: edges between a front- and a
back-facing face, plus open and non-manifold edges, clipped to the near plane and the image).
Per view, one stratified variable runs along the concatenated silhouette curve, so each sample
is uniform over the curve length (unbiased) and neighbouring samples are neighbours on the curve
(coherent rays, low variance). At each sample the jump dI = I(x - eps n) - I(x + eps n) across
the edge is evaluated with two rays; the normal velocity of the projected edge at the (fixed)
sample point is n . dx/dtheta = -(dl/dtheta . x~) / |(l0, l1)|, with l = K^-T (X0 x X1) the
image line through the edge's camera-space end points (valid also for edges clipped by the near
plane). A term whose primal is zero and whose derivative is ``dI * (n . dx/dtheta) * L / M`` is
scattered into the pixel the sample lands in (eq. 5). Samples whose edge point is hidden behind
other geometry (both side rays stop well before the edge) carry nothing.

The functions take the :class:`~recon.render.collocated.CollocatedRenderer` whose call they
serve (its drjit modules, settings, topology, profiling marks and the call's flash offset).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from recon.render.arrays import aligned
from recon.render.edges import silhouette_segments
from recon.render.rays import camera_values, flash_positions, rays_through, trace
from recon.render.shading import Surface, shade

__all__ = ["EdgeSamples", "boundary_term", "sample_edges", "boundary_from_samples"]


@dataclass(frozen=True)
class EdgeSamples:
    """M points on the views' silhouette curves (drjit arrays, one lane per sample).

    Attributes
    ----------
    view : mi.UInt32 (M)
        The view of each sample.
    vi0, vi1 : mi.UInt32 (M)
        End vertices of the sample's silhouette edge.
    x, y : mi.Float (M)
        The sample's image point (pixels).
    weight : mi.Float (M)
        I_e times the view's curve length over its sample count (L / M of eq. 5).
    """

    view: object
    vi0: object
    vi1: object
    x: object
    y: object
    weight: object


def boundary_term(renderer, image, scene, surface: Surface, cameras, cam_table, light_intensity, seed):
    """Scatter-add the edge-sampled boundary term (primal zero) into ``image`` (flat)."""
    samples = sample_edges(renderer, surface.v_flat, cameras, light_intensity, seed)
    if samples is None:
        return
    boundary_from_samples(renderer, image, scene, surface, cam_table, samples,
                          int(cameras[0].height), int(cameras[0].width))


# ---- Sampling the silhouettes ----
def sample_edges(renderer, v_flat, cameras, light_intensity, seed) -> EdgeSamples | None:
    """Stratified samples over each view's silhouette curve; None when there is none."""
    dr, mi = renderer.dr, renderer.mi
    B = len(cameras)
    v_np = dr.detach(v_flat).numpy().reshape(-1, 3).astype(np.float64)
    seg = silhouette_segments(v_np, renderer.t_pos_idx, renderer.topology, cameras)
    renderer._mark("silhouettes")
    counts = np.array([renderer.settings.edge_count(c.width, c.height) for c in cameras])
    counts = np.where(seg.total_length > 0, counts, 0)
    M = int(counts.sum())
    if M == 0 or len(seg) == 0:
        return None
    # Per view, one stratified variable over the concatenated silhouette curve (segments
    # come grouped by view): sample j of n lies uniformly in [j, j + 1) * L / n. Each point
    # is uniform over the curve length (unbiased), strata lower the variance, and
    # consecutive samples are neighbours on the curve (coherent rays). Generated in drjit.
    views = np.arange(B)
    first = np.searchsorted(seg.view, views, side="left")
    last = np.maximum(np.searchsorted(seg.view, views, side="right") - 1, first)
    before = np.concatenate([[0.0], np.cumsum(seg.length)])[first]
    cum_local = np.cumsum(seg.length) - before[seg.view]  # within each view
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    step = np.where(counts > 0, seg.total_length / np.maximum(counts, 1), 0.0)

    def f32(a):
        return mi.Float(aligned(a, np.float32))

    def u32(a):
        return mi.UInt32(aligned(a, np.uint32))

    s_cum, s_len = f32(cum_local), f32(seg.length)
    j = dr.arange(mi.UInt32, M)
    view = _search(dr, mi, u32(start[1:]), j, B - 1) if B > 1 else dr.zeros(mi.UInt32, M)
    jl = j - dr.gather(mi.UInt32, u32(start), view)
    xi = mi.sample_tea_float32(j, dr.opaque(mi.UInt32, (int(seed) * 2654435761 + 0xED9E)
                                            & 0xFFFFFFFF), 4)
    u = (mi.Float(jl) + xi) * dr.gather(mi.Float, f32(step), view)
    lo = dr.gather(mi.UInt32, u32(first), view)
    hi = dr.gather(mi.UInt32, u32(last), view)
    k = _search_range(dr, mi, s_cum, u, lo, hi, int(len(seg)).bit_length())
    length = dr.gather(mi.Float, s_len, k)
    t = dr.clip((u - (dr.gather(mi.Float, s_cum, k) - length)) / dr.maximum(length, 1e-30),
                0.0, 1.0)
    ax, ay = dr.gather(mi.Float, f32(seg.a[:, 0]), k), dr.gather(mi.Float, f32(seg.a[:, 1]), k)
    bx, by = dr.gather(mi.Float, f32(seg.b[:, 0]), k), dr.gather(mi.Float, f32(seg.b[:, 1]), k)
    x = dr.fma(t, bx - ax, ax)
    y = dr.fma(t, by - ay, ay)
    vi0 = dr.gather(mi.UInt32, u32(seg.v0), k)
    vi1 = dr.gather(mi.UInt32, u32(seg.v1), k)
    weight = dr.gather(mi.Float, f32(step * light_intensity), view)
    dr.eval(view, vi0, vi1, x, y, weight)
    renderer._mark("edge_sampling")
    return EdgeSamples(view, vi0, vi1, x, y, weight)


# ---- The jump across each sample's edge, times the edge's normal velocity ----
def boundary_from_samples(renderer, image, scene, surface: Surface, cam_table, samples: EdgeSamples,
                          height: int, width: int):
    """Scatter-add ``dI * (n . dx/dtheta) * weight`` (primal zero) of each sample into the pixel
    of ``image`` (flat, B x ``height`` x ``width`` x 3) it lands in."""
    dr, mi = renderer.dr, renderer.mi
    view, vi0, vi1, x, y, wgt = (samples.view, samples.vi0, samples.vi1, samples.x, samples.y,
                                 samples.weight)
    h, w = height, width
    g = camera_values(dr, mi, cam_table, view)
    Kinv = g[0:9]
    R = g[9:18]
    tr = mi.Vector3f(g[18], g[19], g[20])

    def to_cam(p):
        return mi.Vector3f(
            R[0] * p.x + R[1] * p.y + R[2] * p.z,
            R[3] * p.x + R[4] * p.y + R[5] * p.z,
            R[6] * p.x + R[7] * p.y + R[8] * p.z,
        ) + tr

    X0 = to_cam(dr.gather(mi.Point3f, surface.v_flat, vi0))
    X1 = to_cam(dr.gather(mi.Point3f, surface.v_flat, vi1))
    lc = dr.cross(X0, X1)
    # Image line l = K^-T lc: l . (x, y, 1) = 0 on the projected edge.
    l0 = Kinv[0] * lc.x + Kinv[3] * lc.y + Kinv[6] * lc.z
    l1 = Kinv[1] * lc.x + Kinv[4] * lc.y + Kinv[7] * lc.z
    l2 = Kinv[2] * lc.x + Kinv[5] * lc.y + Kinv[8] * lc.z
    gnorm = dr.detach(dr.sqrt(dr.maximum(l0 * l0 + l1 * l1, 1e-30)))
    nx = dr.detach(l0) / gnorm
    ny = dr.detach(l1) / gnorm
    # Normal displacement of the line at the fixed point (x, y): -(l . x~)/|grad|.
    q = -(l0 * x + l1 * y + l2) / gnorm
    vel = q - dr.detach(q)
    eps = renderer.settings.edge_eps_px
    with dr.suspend_grad():
        surface_d = surface.detached(dr)
        # One wavefront of 2M rays: lane 2k is sample k offset by -eps n, lane 2k + 1 by
        # +eps n (neighbouring lanes, coherent rays).
        M = dr.width(x)
        dr.eval(nx, ny)
        lane = dr.arange(mi.UInt32, 2 * M)
        sid = lane >> 1
        off = dr.select((lane & 1) == 1, eps, -eps)
        sx = dr.gather(mi.Float, x, sid) + off * dr.gather(mi.Float, nx, sid)
        sy = dr.gather(mi.Float, y, sid) + off * dr.gather(mi.Float, ny, sid)
        lane_view = dr.gather(mi.UInt32, view, sid)
        o, dvec = rays_through(dr, mi, cam_table, lane_view, sx, sy)
        renderer._mark("edge_setup")
        prim, valid, thit = trace(mi, scene, o, dvec)
        thit = dr.select(valid, thit, dr.inf)
        dr.eval(prim, valid, thit)
        renderer._mark("edge_trace")
        Ls = shade(dr, mi, surface_d, o, dvec, prim, valid,
                   flash_positions(dr, mi, cam_table, lane_view, renderer._offset))
        dr.eval(Ls)
        renderer._mark("edge_shade")
        even = dr.arange(mi.UInt32, M) * 2
        Lm = dr.gather(mi.Color3f, Ls, even)
        Lp = dr.gather(mi.Color3f, Ls, even + 1)
        tm = dr.gather(mi.Float, thit, even)  # inf where the ray escaped
        tp = dr.gather(mi.Float, thit, even + 1)
        # Depth (along the unit ray) of the edge point under (x, y): closest point of the
        # camera ray and the edge line, in camera coordinates.
        r = mi.Vector3f(Kinv[0] * x + Kinv[1] * y + Kinv[2], Kinv[3] * x + Kinv[4] * y + Kinv[5],
                        Kinv[6] * x + Kinv[7] * y + Kinv[8])
        X0d, X1d = dr.detach(X0), dr.detach(X1)
        e = X1d - X0d
        a_ = dr.dot(r, r)
        b_ = dr.dot(r, e)
        c_ = dr.dot(e, e)
        d_ = dr.dot(r, X0d)
        e_ = dr.dot(e, X0d)
        den = a_ * c_ - b_ * b_
        s_r = dr.select(dr.abs(den) > 1e-30, (d_ * c_ - b_ * e_) / den, d_ / a_)
        t_edge = s_r * dr.norm(r)
        tol = 1e-3 * t_edge
        hidden = (tm < t_edge - tol) & (tp < t_edge - tol)
        dI = dr.select(hidden, 0.0, Lm - Lp) * wgt
        inside = (x >= 0) & (x < w) & (y >= 0) & (y < h)
        px = mi.UInt32(dr.clip(mi.Int32(dr.floor(x)), 0, w - 1))
        py = mi.UInt32(dr.clip(mi.Int32(dr.floor(y)), 0, h - 1))
        pix = (view * h + py) * w + px
        dr.eval(dI, pix, inside)
    for c, dIc in enumerate((dI.x, dI.y, dI.z)):
        dr.scatter_reduce(dr.ReduceOp.Add, image, dIc * vel, pix * 3 + c, inside,
                          mode=dr.ReduceMode.Direct)


# ---- Helpers: binary searches in drjit ----
def _search_range(dr, mi, cum, u, lo, hi, iterations: int):
    """Per lane, the first index k in [lo, hi] with cum[k] > u (hi if none); cum ascending.

    ``iterations`` must be >= log2(hi - lo + 1) (e.g. the bit length of the array size).
    """
    for _ in range(iterations):
        active = lo < hi
        mid = (lo + hi) >> 1
        go_right = active & (dr.gather(mi.Float, cum, mid, active) <= u)
        lo, hi = dr.select(go_right, mid + 1, lo), dr.select(active & ~go_right, mid, hi)
    return lo


def _search(dr, mi, starts, j, n: int):
    """Per lane, how many of the n entries of the ascending UInt32 array ``starts`` are <= j."""
    lo = dr.zeros(mi.UInt32, dr.width(j))
    hi = lo + n
    for _ in range(max(int(n).bit_length(), 1)):
        active = lo < hi
        mid = (lo + hi) >> 1
        go_right = active & (dr.gather(mi.UInt32, starts, mid, active) <= j)
        lo, hi = dr.select(go_right, mid + 1, lo), dr.select(active & ~go_right, mid, hi)
    return lo
