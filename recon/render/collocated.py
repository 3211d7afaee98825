"""Differentiable renderer for a camera with a collocated point light (DESIGN section 3).

Forward: each pixel is the average of ``spp`` uniform samples of its footprint (a box filter);
each sample's ray from the camera center is traced against the mesh with Mitsuba (one
``mi.Scene`` holding the mesh, its vertex positions updated every call) and shaded in closed form

    I(x) = I_e * (a_d / pi + a_s D(mu) G1(mu)^2 / (4 mu^2)) * max(0, mu) / |y - o|^2,

with shading normals = area-weighted vertex normals computed here in drjit from the vertex
positions (so gradients flow through them), UVs interpolated barycentrically and bilinear
texture lookups (DESIGN UV convention, clamp to the edge texels).

Derivatives (the paper's eq. 4-5, Reynolds transport):
- interior: automatic differentiation of the integrand. The hit point is recomputed here from
  the differentiable triangle (Moller-Trumbore on the fixed ray), so it slides along the ray as
  the triangle moves, and so do the barycentrics, the normal and the UV.
- boundary: edge sampling (Li et al. 2018). Silhouette edges are found per view
  (:mod:`recon.render.edges`: edges between a front- and a back-facing face, plus open and
  non-manifold edges, clipped to the near plane and the image). Per view, one stratified
  variable runs along the concatenated silhouette curve, so each sample is uniform over the
  curve length (unbiased) and neighbouring samples are neighbours on the curve (coherent rays,
  low variance). At each sample the jump dI = I(x - eps n) - I(x + eps n) across the edge is
  evaluated with two rays; the normal velocity of the projected edge at the (fixed) sample
  point is n . dx/dtheta = -(dl/dtheta . x~) / |(l0, l1)|, with l = K^-T (X0 x X1) the image
  line through the edge's camera-space end points (valid also for edges clipped by the near
  plane). A term whose primal is zero and whose derivative is ``dI * (n . dx/dtheta) * L / M``
  is scattered into the pixel the sample lands in (eq. 5). Samples whose edge point is hidden
  behind other geometry (both side rays stop well before the edge) carry nothing.

Everything runs as drjit wavefronts (no Python loops over pixels or edges). Values that change
between calls (seed, light intensity, cameras, texture sizes) enter the kernels as opaque
values, so compiled kernels are reused across iterations; the image size and spp are literals
(kernels compile once per resolution).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from recon.brdf import R_MIN
from recon.io.cameras import Camera
from recon.mi import load_variant
from recon.render.edges import EdgeTopology, edge_topology, silhouette_segments

log = logging.getLogger(__name__)

__all__ = ["RenderSettings", "CollocatedRenderer", "RenderError", "R_MIN"]

BOUNDARY_MODES = ("edge", "none", "projective")

_CAM_STRIDE = 24  # floats per view in the camera table: Kinv(9) R_w2c(9) t_w2c(3) center(3)


class RenderError(ValueError):
    """Inputs the renderer cannot use; the message says what was received and what is expected."""


@dataclass(frozen=True)
class RenderSettings:
    """How to render and differentiate.

    Attributes
    ----------
    spp : int
        Samples per pixel (uniform over the pixel footprint).
    stratified : bool
        Where ``spp`` is a square k^2, place the samples on a jittered k x k grid over the
        pixel (each sample stays uniform over the pixel, so the estimate stays unbiased; the
        variance drops). Otherwise independent uniform samples.
    boundary : str
        ``"edge"``: interior + edge-sampled boundary term (unbiased); ``"none"``: interior term
        only (biased at silhouettes); ``"projective"``: Mitsuba's ``direct_projective``
        integrator on an equivalent Mitsuba scene (slow, for comparison).
    edge_samples_per_pixel : float
        Boundary samples per view = this x image width x height (used when ``edge_samples``
        is None).
    edge_samples : int or None
        Boundary samples per view, overriding ``edge_samples_per_pixel``.
    edge_eps_px : float
        Offset (pixels) of the two rays that evaluate the jump across a silhouette.
    r_min : float
        Roughness is clamped to [r_min, 1].
    variant : str or None
        Mitsuba variant (default: :func:`recon.mi.default_variant`, ``llvm_ad_rgb``).
    profile : bool
        Synchronize after each phase of a render and add its wall time (seconds) to
        ``CollocatedRenderer.timings`` (slows rendering a little; for benchmarks).
    """

    spp: int = 4
    boundary: str = "edge"
    stratified: bool = True
    edge_samples_per_pixel: float = 0.25
    edge_samples: int | None = None
    edge_eps_px: float = 1e-3
    r_min: float = R_MIN
    variant: str | None = None
    profile: bool = False

    def __post_init__(self):
        if int(self.spp) < 1:
            raise RenderError(f"RenderSettings.spp must be >= 1, got {self.spp}")
        if self.boundary not in BOUNDARY_MODES:
            raise RenderError(
                f"RenderSettings.boundary must be one of {BOUNDARY_MODES}, got {self.boundary!r}")
        if self.edge_samples is not None and int(self.edge_samples) < 0:
            raise RenderError(f"RenderSettings.edge_samples must be >= 0, got {self.edge_samples}")
        if not self.edge_samples_per_pixel >= 0:
            raise RenderError("RenderSettings.edge_samples_per_pixel must be >= 0, got "
                              f"{self.edge_samples_per_pixel}")
        if not 0 < self.edge_eps_px < 0.5:
            raise RenderError(f"RenderSettings.edge_eps_px must be in (0, 0.5), got {self.edge_eps_px}")
        if not 0 < self.r_min <= 1:
            raise RenderError(f"RenderSettings.r_min must be in (0, 1], got {self.r_min}")

    def edge_count(self, width: int, height: int) -> int:
        """Number of boundary samples for one view of ``width`` x ``height`` pixels."""
        if self.edge_samples is not None:
            return int(self.edge_samples)
        return int(round(self.edge_samples_per_pixel * width * height))


def camera_table(cameras: Sequence[Camera]) -> np.ndarray:
    """(B, 24) float64 per-view Kinv (row-major), R_w2c, t_w2c, camera center: the values the
    renderer's rays and projections read (see ``camera_table`` of :meth:`CollocatedRenderer.render_batch`)."""
    rows = []
    for cam in cameras:
        if not isinstance(cam, Camera):
            raise RenderError(f"cameras: expected recon.io.cameras.Camera objects, got {type(cam)}")
        R = cam.world_to_camera[:3, :3]
        t = cam.world_to_camera[:3, 3]
        rows.append(np.concatenate([np.linalg.inv(cam.K).ravel(), R.ravel(), t, cam.center]))
    return np.stack(rows)


def _aligned(a, dtype) -> np.ndarray:
    """A flat copy of ``a`` whose buffer starts on a 64-byte boundary.

    drjit maps numpy memory into its arrays without copying and compiles separate kernels
    for aligned and unaligned inputs; numpy's buffers are aligned to 16 bytes only, so the
    same call could compile a new kernel variant whenever an allocation landed elsewhere.
    Every numpy array the renderer hands to drjit goes through here (torch's CPU buffers are
    64-byte aligned already).
    """
    a = np.ascontiguousarray(a, dtype=dtype).reshape(-1)
    buf = np.empty(a.size + 64 // a.itemsize, dtype=dtype)
    start = (-buf.ctypes.data % 64) // a.itemsize
    out = buf[start:start + a.size]
    out[...] = a
    return out


def _as_int_array(a, name: str, cols: int) -> np.ndarray:
    arr = np.asarray(a)
    if arr.ndim != 2 or arr.shape[1] != cols or not np.issubdtype(arr.dtype, np.integer):
        raise RenderError(f"{name}: expected an (n, {cols}) integer array, got shape "
                          f"{arr.shape} dtype {arr.dtype}")
    if arr.size and arr.min() < 0:
        raise RenderError(f"{name}: indices must be >= 0")
    return arr.astype(np.int64)


class CollocatedRenderer:
    """Renders a textured triangle mesh under a point light at each camera, differentiably.

    Parameters
    ----------
    t_pos_idx : (F, 3) int
        Triangles (vertex ids). Topology is fixed for the renderer's life.
    v_tex : (T, 2) float
        UVs, OBJ convention (v up).
    t_tex_idx : (F, 3) int
        UV ids per triangle corner.
    settings : RenderSettings
    """

    def __init__(self, t_pos_idx, v_tex, t_tex_idx, settings: RenderSettings = RenderSettings()):
        self.settings = settings
        self.mi = load_variant(settings.variant)
        import drjit as dr

        self.dr = dr
        self.t_pos_idx = _as_int_array(t_pos_idx, "t_pos_idx", 3)
        self.t_tex_idx = _as_int_array(t_tex_idx, "t_tex_idx", 3)
        v_tex = np.asarray(v_tex, dtype=np.float64)
        if v_tex.ndim != 2 or v_tex.shape[1] != 2:
            raise RenderError(f"v_tex: expected a (T, 2) float array, got shape {v_tex.shape}")
        if len(self.t_tex_idx) != len(self.t_pos_idx):
            raise RenderError(f"t_tex_idx has {len(self.t_tex_idx)} rows but t_pos_idx has "
                              f"{len(self.t_pos_idx)}; both need one row per face")
        if len(self.t_pos_idx) == 0:
            raise RenderError("t_pos_idx: the mesh has no faces")
        if self.t_tex_idx.max() >= len(v_tex):
            raise RenderError(f"t_tex_idx refers to UV {self.t_tex_idx.max()} but v_tex has "
                              f"{len(v_tex)} rows")
        if not np.all(np.isfinite(v_tex)):
            raise RenderError("v_tex contains NaN or Inf")
        mi = self.mi
        self.n_faces = len(self.t_pos_idx)
        self.n_vertices_min = int(self.t_pos_idx.max()) + 1
        self._faces = mi.UInt32(_aligned(self.t_pos_idx, np.uint32))
        # Per face corner UVs, (F*3, 2) flattened; gathered by face id at the hit.
        corner_uv = v_tex[self.t_tex_idx].reshape(-1, 2).astype(np.float32)
        self._corner_uv = mi.Float(_aligned(corner_uv, np.float32))
        self.topology: EdgeTopology = edge_topology(self.t_pos_idx)
        self._scene = None
        self._scene_params = None
        self._n_vertices = None
        self._projective = None
        self.timings: dict[str, float] = {}
        self._t_mark = 0.0
        self._offset = None  # the call's flash offset (3 opaque Floats), see render_batch
        self._ambient = None  # the call's ambient radiance / I_e (opaque Float)

    def _mark(self, phase: str | None, *evaluate) -> None:
        """With ``settings.profile``: evaluate ``evaluate``, wait, and book the time since the
        previous mark to ``phase`` (None starts the clock)."""
        if not self.settings.profile:
            return
        import time

        if evaluate:
            self.dr.eval(*evaluate)
        self.dr.sync_thread()
        now = time.perf_counter()
        if phase is not None:
            self.timings[phase] = self.timings.get(phase, 0.0) + now - self._t_mark
        self._t_mark = now

    # ------------------------------------------------------------------ inputs
    def _vertex_array(self, v_pos):
        """(V, 3) drjit tensor / array or numpy -> flat mi.Float (3V), grads kept."""
        dr, mi = self.dr, self.mi
        if isinstance(v_pos, mi.TensorXf):
            if v_pos.ndim != 2 or v_pos.shape[1] != 3:
                raise RenderError(f"v_pos: expected shape (V, 3), got {v_pos.shape}")
            flat = v_pos.array
        elif isinstance(v_pos, mi.Float):
            if dr.width(v_pos) % 3:
                raise RenderError(f"v_pos: a flat array needs 3V entries, got {dr.width(v_pos)}")
            flat = v_pos
        else:
            arr = np.asarray(v_pos, dtype=np.float32)
            if arr.ndim != 2 or arr.shape[1] != 3:
                raise RenderError(f"v_pos: expected shape (V, 3), got {arr.shape}")
            flat = mi.Float(_aligned(arr, np.float32))
        n = dr.width(flat) // 3
        if n < self.n_vertices_min:
            raise RenderError(f"v_pos has {n} vertices but the faces refer to vertex "
                              f"{self.n_vertices_min - 1}")
        return flat, n

    def _texture(self, tex, name: str, channels: tuple[int, ...]):
        """(H, W, C) drjit tensor or numpy -> (flat mi.Float, H, W, C)."""
        mi = self.mi
        if isinstance(tex, mi.TensorXf):
            shape = tuple(tex.shape)
            flat = tex.array
        else:
            arr = np.asarray(tex, dtype=np.float32)
            shape = arr.shape
            flat = None
        if len(shape) != 3 or shape[2] not in channels or shape[0] < 1 or shape[1] < 1:
            raise RenderError(f"{name}: expected an (H, W, C) texture with C in {channels}, "
                              f"got shape {shape}")
        if flat is None:
            flat = mi.Float(_aligned(arr, np.float32))
        return flat, int(shape[0]), int(shape[1]), int(shape[2])

    def _cam_values(self, cam_table, view):
        """The 24 per-view camera values for each lane: gathers, or broadcast scalars for a
        single view (a list of opaque scalars)."""
        dr, mi = self.dr, self.mi
        if isinstance(cam_table, list):
            return cam_table
        base = view * _CAM_STRIDE
        return [dr.gather(mi.Float, cam_table, base + k) for k in range(_CAM_STRIDE)]

    def _camera_table(self, cameras: Sequence[Camera]):
        """Per-view Kinv, R_w2c, t_w2c, center (24 floats each): a flat mi.Float for several
        views, a list of 24 opaque scalars for one."""
        rows = camera_table(cameras)
        if len(rows) == 1:
            return [self.dr.opaque(self.mi.Float, float(x)) for x in rows[0]]
        return self.mi.Float(_aligned(rows, np.float32))

    def _given_camera_table(self, table, n_views: int):
        """A caller's (possibly differentiable) flat B x 24 table; one view: 24 broadcast scalars
        gathered from it (AD sums their lanes back into the table)."""
        dr, mi = self.dr, self.mi
        if not isinstance(table, mi.Float) or dr.width(table) != n_views * _CAM_STRIDE:
            raise RenderError(f"camera_table: expected a flat mi.Float of {n_views} x {_CAM_STRIDE} values")
        if n_views == 1:
            return [dr.gather(mi.Float, table, dr.opaque(mi.UInt32, k)) for k in range(_CAM_STRIDE)]
        return table

    # ------------------------------------------------------------------ scene
    def _update_scene(self, v_flat, n_vertices: int):
        """Mitsuba scene (one mesh) whose BVH matches the current (detached) positions."""
        dr, mi = self.dr, self.mi
        if self._scene is None or n_vertices != self._n_vertices:
            mesh = mi.Mesh("recon_mesh", n_vertices, self.n_faces,
                           has_vertex_normals=False, has_vertex_texcoords=False)
            mp = mi.traverse(mesh)
            mp["faces"] = self._faces
            mp["vertex_positions"] = dr.detach(v_flat)
            mp.update()
            self._scene = mi.load_dict({"type": "scene", "mesh": mesh})
            self._scene_params = mi.traverse(self._scene)
            self._n_vertices = n_vertices
        else:
            new = dr.detach(v_flat)
            old = self._scene_params["mesh.vertex_positions"]
            # The BVH rebuild is the largest fixed cost of a call: skip it when the positions
            # did not change (e.g. several view batches rendered per optimizer step).
            if not bool(dr.all(old == new, axis=None)):
                self._scene_params["mesh.vertex_positions"] = new
                self._scene_params.update()
        return self._scene

    def _vertex_normals(self, v_flat, n_vertices: int):
        """Area-weighted vertex normals (flat mi.Float 3V, normalized safely), differentiable."""
        dr, mi = self.dr, self.mi
        fidx = [dr.gather(mi.UInt32, self._faces, dr.arange(mi.UInt32, self.n_faces) * 3 + k)
                for k in range(3)]
        p = [dr.gather(mi.Point3f, v_flat, i) for i in fidx]
        fn = dr.cross(p[1] - p[0], p[2] - p[0])  # length = 2 x area: area weighting
        acc = dr.zeros(mi.Float, 3 * n_vertices)
        for i in fidx:
            dr.scatter_reduce(dr.ReduceOp.Add, acc, fn, i)
        vid = dr.arange(mi.UInt32, n_vertices)
        nrm = _safe_normalize(dr, dr.gather(mi.Vector3f, acc, vid))
        flat = dr.zeros(mi.Float, 3 * n_vertices)
        dr.scatter(flat, nrm, vid)
        dr.eval(flat)
        return flat

    # ------------------------------------------------------------------ shading
    def _trace(self, scene, o, d, coherent: bool = True):
        """Preliminary intersection of rays (o, d); returns (prim index, hit mask, distance)."""
        mi = self.mi
        ray = mi.Ray3f(o, d)
        pi = scene.ray_intersect_preliminary(ray, coherent=coherent)
        return pi.prim_index, pi.is_valid(), pi.t

    def _shade(self, o, d, prim, valid, v_flat, n_flat, tex, light=None):
        """Radiance/I_e toward the camera at the first hit of rays (o, d) (Color3f), differentiable.

        The hit is recomputed from the (differentiable) triangle ``prim`` on the fixed ray.
        ``light``: per-lane point light positions (the flash beside the lens) for the general
        model of DESIGN section 3 (l != v); None: the light is at ``o`` (the collocated model).
        The call's ambient radiance (``self._ambient``, relative to I_e) adds ``A (a_d + a_s)``
        at every hit (an unoccluded constant environment). Flash offset and ambient light are the
        scene side of the image formation of :mod:`recon.optimize.formation`, copied here in
        drjit for speed; ``test_flash_offset_and_ambient_match_the_formation`` in
        tests/render/test_collocated.py holds the copy to it.
        """
        dr, mi = self.dr, self.mi
        base = prim * 3
        vi = [dr.gather(mi.UInt32, self._faces, base + k, valid) for k in range(3)]
        p0, p1, p2 = (dr.gather(mi.Point3f, v_flat, i, valid) for i in vi)
        # ---- Moller-Trumbore on the fixed ray: t, barycentrics (b1, b2) move with the triangle
        e1, e2 = p1 - p0, p2 - p0
        pvec = dr.cross(d, e2)
        det = dr.dot(e1, pvec)
        # not a grazing / degenerate hit: |det| > 1e-7 |e1| |e2| (squared, no roots)
        ok = valid & (det * det > 1e-14 * dr.squared_norm(e1) * dr.squared_norm(e2))
        inv_det = dr.select(ok, dr.rcp(dr.select(ok, det, 1.0)), 0.0)
        tvec = o - p0
        b1 = dr.dot(tvec, pvec) * inv_det
        qvec = dr.cross(tvec, e1)
        b2 = dr.dot(d, qvec) * inv_det
        b0 = 1.0 - b1 - b2
        y = dr.fma(p0, b0, dr.fma(p1, b1, p2 * b2))
        # ---- shading normal: interpolated vertex normals, normalized
        n0, n1, n2 = (dr.gather(mi.Vector3f, n_flat, i, valid) for i in vi)
        n = _safe_normalize(dr, n0 * b0 + n1 * b1 + n2 * b2)
        to_o = o - y
        dist2 = dr.squared_norm(to_o)
        w = to_o * dr.rsqrt(dr.maximum(dist2, 1e-30))
        mu = dr.dot(n, w)
        # 1 - mu^2 as |n x w|^2: exact near the specular peak, where 1 - mu^2 cancels.
        sin2 = dr.squared_norm(dr.cross(n, w))
        # ---- textures at the interpolated UV
        uv = mi.Point2f(0.0)
        for k, bk in enumerate((b0, b1, b2)):
            uv += bk * dr.gather(mi.Point2f, self._corner_uv, prim * 3 + k, valid)
        a_d = _bilinear(dr, mi, tex["diffuse"], uv, valid)
        a_s = _bilinear(dr, mi, tex["specular"], uv, valid)
        r = _bilinear(dr, mi, tex["roughness"], uv, valid)
        r = dr.clip(r, self.settings.r_min, 1.0)
        alpha = r * r
        a2 = alpha * alpha
        if light is not None:
            out = self._shade_offset(y, n, w, mu, light, a_d, a_s, a2, valid)
        else:
            out = self._shade_collocated(mu, sin2, dist2, a_d, a_s, a2, valid)
        if self._ambient is not None:
            out = out + dr.select(valid, self._ambient * (a_d + a_s), 0.0)
        return out

    def _shade_collocated(self, mu, sin2, dist2, a_d, a_s, a2, valid):
        """The collocated BRDF (DESIGN section 3) times the cosine and the falloff."""
        dr = self.dr
        mu_p = dr.maximum(mu, 0.0)
        den = dr.fma(mu_p * mu_p, a2, sin2)  # mu^2 (a2 - 1) + 1
        D = a2 * dr.rcp(dr.pi * dr.maximum(den * den, 1e-30))
        g = dr.rcp(mu_p + dr.sqrt(dr.fma(1.0 - a2, mu_p * mu_p, a2)))  # G1(mu) / (2 mu)
        spec = D * g * g
        f = a_d * dr.inv_pi + a_s * spec
        lit = valid & (mu > 0)
        return dr.select(lit, f * (mu_p * dr.rcp(dr.maximum(dist2, 1e-30))), 0.0)

    def _shade_offset(self, y, n, w, nv, light, a_d, a_s, a2, valid):
        """The general model of DESIGN section 3 for a light at ``light`` seen from the camera
        (unit direction ``w`` from the hit ``y``, ``nv`` = n . w): GGX D(n . h), Schlick F(v . h),
        separable Smith G1, times n . l / |light - y|^2. No shadow test: the flash sits ~1 cm from
        the lens, so what the camera sees is lit except in slivers. One of the model's copies
        listed in :mod:`recon.brdf`."""
        dr = self.dr
        lv = light - y
        dl2 = dr.squared_norm(lv)
        l = lv * dr.rsqrt(dr.maximum(dl2, 1e-30))  # noqa: E741
        nl = dr.dot(n, l)
        nl_p = dr.maximum(nl, 0.0)
        nv_p = dr.maximum(nv, 0.0)
        hv = _safe_normalize(dr, l + w)
        nh = dr.clip(dr.dot(n, hv), 0.0, 1.0)
        vh = dr.clip(dr.dot(w, hv), 0.0, 1.0)
        # 1 - (n . h)^2 as |n x h|^2: exact near the specular peak
        den = dr.fma(nh * nh, a2, dr.squared_norm(dr.cross(n, hv)))
        D = a2 * dr.rcp(dr.pi * dr.maximum(den * den, 1e-30))
        one_vh = 1.0 - vh
        F = a_s + (1.0 - a_s) * (one_vh * one_vh) * (one_vh * one_vh) * one_vh
        gl = dr.rcp(nl_p + dr.sqrt(dr.fma(1.0 - a2, nl_p * nl_p, a2)))  # G1(n.l) / (2 n.l)
        gv = dr.rcp(nv_p + dr.sqrt(dr.fma(1.0 - a2, nv_p * nv_p, a2)))
        f = a_d * dr.inv_pi + D * F * gl * gv
        lit = valid & (nl > 0) & (nv > 0)
        return dr.select(lit, f * (nl_p * dr.rcp(dr.maximum(dl2, 1e-30))), 0.0)

    def _lights(self, cam_table, view):
        """Per-lane flash positions c + R^T t of the call's offset t (camera coordinates), or
        None when the light is at the camera centre."""
        if self._offset is None:
            return None
        mi = self.mi
        g = self._cam_values(cam_table, view)
        R, t = g[9:18], self._offset
        return mi.Point3f(g[21] + R[0] * t[0] + R[3] * t[1] + R[6] * t[2],
                          g[22] + R[1] * t[0] + R[4] * t[1] + R[7] * t[2],
                          g[23] + R[2] * t[0] + R[5] * t[1] + R[8] * t[2])

    # ------------------------------------------------------------------ rays
    def _primary_rays(self, cam_table, n_views: int, width: int, height: int, spp: int, seed):
        """Rays of all samples, lane = ((view * h + row) * w + col) * spp + s."""
        dr, mi = self.dr, self.mi
        n = n_views * width * height * spp
        idx = dr.arange(mi.UInt32, n)
        # Divisors are literals (LLVM turns the divisions into multiplications); the kernels
        # are compiled again only when the image size or spp changes.
        pix = idx // spp
        view = pix // (width * height)
        p = pix - view * (width * height)
        row = p // width
        col = p - row * width
        ux = mi.sample_tea_float32(idx, seed, 4)
        uy = mi.sample_tea_float32(idx, seed + 0x9E3779B9, 4)
        k = int(np.sqrt(spp) + 0.5)
        if self.settings.stratified and k * k == spp and spp > 1:
            # Jittered k x k grid over the pixel: each sample is still uniform over the pixel.
            s = idx - pix * spp
            sy = s // k
            sx = s - sy * k
            ux = (mi.Float(sx) + ux) * (1.0 / k)
            uy = (mi.Float(sy) + uy) * (1.0 / k)
        x = mi.Float(col) + ux
        yv = mi.Float(row) + uy
        o, d = self._rays_through(cam_table, view, x, yv)
        return o, d, view

    def _rays_through(self, cam_table, view, x, y):
        """World rays (origin, unit direction) through image points (x, y) of ``view``."""
        dr, mi = self.dr, self.mi
        g = self._cam_values(cam_table, view)
        Kinv = g[0:9]
        R = g[9:18]
        c = mi.Point3f(g[21], g[22], g[23])
        dc = mi.Vector3f(
            Kinv[0] * x + Kinv[1] * y + Kinv[2],
            Kinv[3] * x + Kinv[4] * y + Kinv[5],
            Kinv[6] * x + Kinv[7] * y + Kinv[8],
        )
        # camera -> world: R^T dc
        dw = mi.Vector3f(
            R[0] * dc.x + R[3] * dc.y + R[6] * dc.z,
            R[1] * dc.x + R[4] * dc.y + R[7] * dc.z,
            R[2] * dc.x + R[5] * dc.y + R[8] * dc.z,
        )
        return c, dr.normalize(dw)

    # ------------------------------------------------------------------ public
    def render(self, v_pos, diffuse, specular, roughness, cameras: Sequence[Camera],
               light_intensity: float = 1.0, seed: int = 0, flash_offset=None, ambient: float = 0.0):
        """Render a batch of views.

        Parameters
        ----------
        v_pos : (V, 3) mi.TensorXf, flat mi.Float (3V) or numpy
            Vertex positions; gradients flow where grads are enabled on a drjit input.
        diffuse : (H, W, 3), specular : (H, W, 1 or 3), roughness : (H, W, 1)
            Texture values (mi.TensorXf or numpy); each map may have its own size.
        cameras : sequence of :class:`recon.io.cameras.Camera`
        light_intensity : float
            I_e of the point light at each camera center.
        seed : int
            Seeds the pixel and edge samples (same seed, same samples).
        flash_offset, ambient :
            The flash beside the lens and a constant environment (see :meth:`render_batch`).

        Returns
        -------
        list of B mi.TensorXf (h, w, 3): linear radiance per view.
        """
        cameras = list(cameras)
        if not cameras:
            raise RenderError("cameras: need at least one camera")
        out = [None] * len(cameras)
        groups: dict[tuple[int, int], list[int]] = {}
        for i, cam in enumerate(cameras):
            groups.setdefault((int(cam.height), int(cam.width)), []).append(i)
        for g, ids in enumerate(groups.values()):
            batch = self.render_batch(v_pos, diffuse, specular, roughness,
                                      [cameras[i] for i in ids], light_intensity, seed + 7919 * g,
                                      flash_offset=flash_offset, ambient=ambient)
            for k, i in enumerate(ids):
                out[i] = batch[k]
        return out

    def render_batch(self, v_pos, diffuse, specular, roughness, cameras: Sequence[Camera],
                     light_intensity: float = 1.0, seed: int = 0, camera_table=None,
                     flash_offset=None, ambient: float = 0.0):
        """Like :meth:`render` for views of one size; returns one mi.TensorXf (B, h, w, 3).

        ``flash_offset`` : (3,) position of the point light relative to the camera centre, in
        camera coordinates (a phone's flash beside the lens; None or zeros: at the centre, the
        collocated model). ``ambient`` : radiance of a constant environment (>= 0), added as
        ``ambient (a_d + a_s)`` at every hit. Both are fixed values (no gradients).

        ``camera_table`` : optional flat mi.Float of B x 24 values (per view Kinv, R_w2c, t_w2c,
        center; :func:`camera_table`) at the values of ``cameras``; when its gradients are
        enabled, the image is differentiable with respect to the cameras: the interior term
        through the primary rays, the boundary term through the projected silhouettes'
        motion. ``cameras`` still give the image size and the silhouette sets.
        """
        dr, mi = self.dr, self.mi
        cameras = list(cameras)
        if not cameras:
            raise RenderError("cameras: need at least one camera")
        h, w = int(cameras[0].height), int(cameras[0].width)
        if any((int(c.height), int(c.width)) != (h, w) for c in cameras):
            raise RenderError("render_batch: all cameras need the same image size; use render()")
        if not np.isfinite(light_intensity) or light_intensity < 0:
            raise RenderError(f"light_intensity must be a finite number >= 0, got {light_intensity}")
        offset = None if flash_offset is None else np.asarray(flash_offset, np.float64).reshape(-1)
        if offset is not None and (offset.shape != (3,) or not np.all(np.isfinite(offset))):
            raise RenderError(f"flash_offset must be 3 finite numbers (camera coordinates), got {flash_offset!r}")
        if offset is not None and not np.any(offset):
            offset = None  # at the centre: the collocated model (and its kernels)
        if not np.isfinite(ambient) or ambient < 0:
            raise RenderError(f"ambient must be a finite number >= 0, got {ambient}")
        if ambient > 0 and not light_intensity > 0:
            raise RenderError("ambient light needs light_intensity > 0 (it is rendered relative to I_e)")
        if self.settings.boundary == "projective":
            from recon.render.mitsuba_scene import render_projective

            if camera_table is not None:
                raise RenderError("camera gradients need boundary='edge' or 'none', not 'projective'")

            if offset is not None or ambient > 0:
                raise RenderError("flash_offset and ambient need boundary='edge' or 'none', not 'projective'")
            return render_projective(self, v_pos, diffuse, specular, roughness, cameras,
                                     light_intensity, seed)
        self._offset = None if offset is None else [dr.opaque(mi.Float, float(x)) for x in offset]
        self._ambient = dr.opaque(mi.Float, float(ambient) / float(light_intensity)) if ambient > 0 else None
        self._mark(None)
        v_flat, nv = self._vertex_array(v_pos)
        tex = {
            "diffuse": self._texture(diffuse, "diffuse", (3,)),
            "specular": self._texture(specular, "specular", (1, 3)),
            "roughness": self._texture(roughness, "roughness", (1,)),
        }
        # Maps of one size share their opaque sizes, so their (identical) bilinear footprint
        # arithmetic is computed once per lane.
        sizes = {}
        for _, H, W, _ in tex.values():
            if (H, W) not in sizes:
                sizes[(H, W)] = (dr.opaque(mi.UInt32, H), dr.opaque(mi.UInt32, W))
        tex = {k: (flat, *sizes[(H, W)], C) for k, (flat, H, W, C) in tex.items()}
        self._mark("inputs", v_flat, *(t[0] for t in tex.values()))
        scene = self._update_scene(v_flat, nv)
        self._mark("bvh")
        n_flat = self._vertex_normals(v_flat, nv)
        B = len(cameras)
        cam_table = self._camera_table(cameras) if camera_table is None else \
            self._given_camera_table(camera_table, B)
        self._mark("normals", n_flat)
        spp = int(self.settings.spp)
        seed_o = dr.opaque(mi.UInt32, np.uint32(seed & 0xFFFFFFFF))
        # ---- Interior: MC over pixel footprints, AD through the integrand
        o, d, view = self._primary_rays(cam_table, B, w, h, spp, seed_o)
        prim, valid, _ = self._trace(scene, o, d)
        L = self._shade(o, d, prim, valid, v_flat, n_flat, tex, self._lights(cam_table, view))
        inv = dr.opaque(mi.Float, float(light_intensity) / spp)
        flat = dr.zeros(mi.Float, B * h * w * 3)
        pix3 = (dr.arange(mi.UInt32, B * h * w * spp) // spp) * 3
        for c, Lc in enumerate((L.x, L.y, L.z)):
            dr.scatter_reduce(dr.ReduceOp.Add, flat, Lc * inv, pix3 + c)
        # One kernel traces, shades and accumulates; it also stores the rays and hits so the
        # backward pass reads them instead of tracing again.
        dr.eval(flat, prim, valid, o, d)
        self._mark("primary")
        # ---- Boundary: edge sampling (primal zero, derivative = the silhouette term)
        if self.settings.boundary == "edge" and (dr.grad_enabled(v_flat) or (
                camera_table is not None and dr.grad_enabled(camera_table))):
            self._boundary_term(flat, scene, v_flat, n_flat, tex, cameras, cam_table,
                                float(light_intensity), seed, B, h, w)
            self._mark("edge_rays", flat)
        return mi.TensorXf(flat, shape=(B, h, w, 3))

    def render_torch(self, v_pos, diffuse, specular, roughness, cameras: Sequence[Camera],
                     light_intensity: float = 1.0, seed: int = 0, camera_table=None,
                     flash_offset=None, ambient: float = 0.0):
        """Render with PyTorch tensors; autograd reaches all four inputs (and the cameras).

        Parameters
        ----------
        v_pos : torch.Tensor (V, 3) float32
        diffuse : torch.Tensor (H, W, 3)
        specular : torch.Tensor (H, W, 1 or 3)
        roughness : torch.Tensor (H, W, 1)
        cameras : sequence of B :class:`Camera`, all of one image size
        light_intensity, seed : as in :meth:`render`
        flash_offset, ambient : as in :meth:`render_batch` (fixed values)
        camera_table : torch.Tensor (B, 24), optional
            The cameras' values (:func:`camera_table`; e.g. from
            :func:`recon.render.torch_bridge.camera_table_torch`); autograd reaches it.

        Returns
        -------
        torch.Tensor (B, h, w, 3) float32, linear radiance, on ``v_pos.device``.
        """
        import torch

        from recon.render.torch_bridge import RenderFunction

        for name, t in (("v_pos", v_pos), ("diffuse", diffuse), ("specular", specular),
                        ("roughness", roughness)):
            if not isinstance(t, torch.Tensor):
                raise RenderError(f"render_torch: {name} must be a torch.Tensor, got {type(t)}")
        tensors = (v_pos, diffuse, specular, roughness)
        cameras = list(cameras)
        if camera_table is not None and tuple(camera_table.shape) != (len(cameras), 24):
            raise RenderError(f"render_torch: camera_table must have shape ({len(cameras)}, 24), "
                              f"got {tuple(camera_table.shape)}")
        grads = any(t.requires_grad for t in tensors) or (camera_table is not None and camera_table.requires_grad)
        if not (torch.is_grad_enabled() and grads):
            mi = self.mi
            table = None if camera_table is None else mi.Float(
                camera_table.detach().to(torch.float32).reshape(-1).contiguous().clone())
            out = self.render_batch(
                *(mi.TensorXf(t.detach().to(torch.float32).contiguous().clone()) for t in tensors),
                cameras, float(light_intensity), int(seed), camera_table=table,
                flash_offset=flash_offset, ambient=float(ambient))
            return out.torch().clone().to(v_pos.device)
        return RenderFunction.apply(self, cameras, float(light_intensity), int(seed),
                                    *tensors, camera_table, (flash_offset, float(ambient)))

    # ------------------------------------------------------------------ boundary
    def _boundary_term(self, image, scene, v_flat, n_flat, tex, cameras, cam_table,
                       light_intensity, seed, B, h, w):
        """Scatter-add the edge-sampled boundary term (primal zero) into ``image`` (flat)."""
        dr, mi = self.dr, self.mi
        v_np = dr.detach(v_flat).numpy().reshape(-1, 3).astype(np.float64)
        seg = silhouette_segments(v_np, self.t_pos_idx, self.topology, cameras)
        self._mark("silhouettes")
        counts = np.array([self.settings.edge_count(c.width, c.height) for c in cameras])
        counts = np.where(seg.total_length > 0, counts, 0)
        M = int(counts.sum())
        if M == 0 or len(seg) == 0:
            return
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
            return mi.Float(_aligned(a, np.float32))

        def u32(a):
            return mi.UInt32(_aligned(a, np.uint32))

        s_cum, s_len = f32(cum_local), f32(seg.length)
        j = dr.arange(mi.UInt32, M)
        view = _search(dr, mi, u32(start[1:]), j, B - 1) if B > 1 else dr.zeros(
            mi.UInt32, M)
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
        self._mark("edge_sampling")
        self._boundary_from_samples(image, scene, v_flat, n_flat, tex, cam_table, view, vi0, vi1,
                                    x, y, weight, B, h, w)

    def _boundary_from_samples(self, image, scene, v_flat, n_flat, tex, cam_table, view, vi0,
                               vi1, x, y, wgt, B, h, w):
        dr, mi = self.dr, self.mi
        g = self._cam_values(cam_table, view)
        Kinv = g[0:9]
        R = g[9:18]
        tr = mi.Vector3f(g[18], g[19], g[20])

        def to_cam(p):
            return mi.Vector3f(
                R[0] * p.x + R[1] * p.y + R[2] * p.z,
                R[3] * p.x + R[4] * p.y + R[5] * p.z,
                R[6] * p.x + R[7] * p.y + R[8] * p.z,
            ) + tr

        X0 = to_cam(dr.gather(mi.Point3f, v_flat, vi0))
        X1 = to_cam(dr.gather(mi.Point3f, v_flat, vi1))
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
        eps = self.settings.edge_eps_px
        with dr.suspend_grad():
            vd = dr.detach(v_flat)
            nd = dr.detach(n_flat)
            tex_d = {k: (dr.detach(v[0]),) + tuple(v[1:]) for k, v in tex.items()}
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
            o, dvec = self._rays_through(cam_table, lane_view, sx, sy)
            self._mark("edge_setup")
            prim, valid, thit = self._trace(scene, o, dvec)
            thit = dr.select(valid, thit, dr.inf)
            dr.eval(prim, valid, thit)
            self._mark("edge_trace")
            Ls = self._shade(o, dvec, prim, valid, vd, nd, tex_d, self._lights(cam_table, lane_view))
            dr.eval(Ls)
            self._mark("edge_shade")
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


# ---------------------------------------------------------------------- helpers
def _safe_normalize(dr, v):
    """v / |v|, 0 where |v| == 0, finite gradient everywhere."""
    n2 = dr.squared_norm(v)
    ok = n2 > 1e-36
    return v * dr.select(ok, dr.rsqrt(dr.select(ok, n2, 1.0)), 0.0)


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


def _bilinear(dr, mi, texture, uv, active):
    """Bilinear lookup (clamp to edge) of a flat (H, W, C) texture at OBJ-convention UVs.

    Texel (i, j) sits at u = (j + 0.5)/W, v = 1 - (i + 0.5)/H. Returns Float (C = 1) or
    Color3f (C = 3).
    """
    data, H, W, C = texture
    Wf, Hf = mi.Float(W), mi.Float(H)
    u = dr.select(dr.isfinite(uv.x), uv.x, 0.0)
    v = dr.select(dr.isfinite(uv.y), uv.y, 0.0)
    x = u * Wf - 0.5
    y = (1.0 - v) * Hf - 0.5
    x = dr.clip(x, -1.0, Wf)
    y = dr.clip(y, -1.0, Hf)
    x0f, y0f = dr.floor(x), dr.floor(y)
    fx, fy = x - x0f, y - y0f
    x0, y0 = mi.Int32(x0f), mi.Int32(y0f)
    Wi, Hi = mi.Int32(W), mi.Int32(H)
    xa = mi.UInt32(dr.clip(x0, 0, Wi - 1))
    xb = mi.UInt32(dr.clip(x0 + 1, 0, Wi - 1))
    ya = mi.UInt32(dr.clip(y0, 0, Hi - 1))
    yb = mi.UInt32(dr.clip(y0 + 1, 0, Hi - 1))
    dtype = mi.Float if C == 1 else mi.Color3f
    t00 = dr.gather(dtype, data, ya * W + xa, active)
    t01 = dr.gather(dtype, data, ya * W + xb, active)
    t10 = dr.gather(dtype, data, yb * W + xa, active)
    t11 = dr.gather(dtype, data, yb * W + xb, active)
    top = dr.lerp(t00, t01, fx)
    bot = dr.lerp(t10, t11, fx)
    return dr.lerp(top, bot, fy)
