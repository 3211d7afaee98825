"""Differentiable renderer for a camera with a collocated point light (DESIGN section 3).

Forward: each pixel is the average of ``spp`` uniform samples of its footprint (a box filter);
each sample's ray from the camera center is traced against the mesh with Mitsuba (one
``mi.Scene`` holding the mesh, its vertex positions updated every call) and shaded in closed form

    I(x) = I_e * (a_d / pi + a_s D(mu) G1(mu)^2 / (4 mu^2)) * max(0, mu) / |y - o|^2,

with shading normals = area-weighted vertex normals computed here in drjit from the vertex
positions (so gradients flow through them), UVs interpolated barycentrically and bilinear
texture lookups (DESIGN UV convention, clamp to the edge texels).

Derivatives (the paper's eq. 4-5, Reynolds transport):
- interior: automatic differentiation of the integrand. The hit point is recomputed from the
  differentiable triangle (Moller-Trumbore on the fixed ray), so it slides along the ray as
  the triangle moves, and so do the barycentrics, the normal and the UV.
- boundary: edge sampling (Li et al. 2018) of the silhouettes, per view one stratified variable
  along the silhouette curve, the jump across the edge times the edge's normal velocity.

This module owns the control flow of a call (inputs, the Mitsuba scene, vertex normals, the
interior term, the torch entry point); the phases live in their own modules:
:mod:`recon.render.rays` (camera table, primary rays, tracing, the flash's position),
:mod:`recon.render.shading` (the hit and the BRDF's drjit copies),
:mod:`recon.render.boundary` (the edge-sampled boundary term), :mod:`recon.render.edges`
(silhouette edges), :mod:`recon.render.torch_bridge` (the autograd function) and
:mod:`recon.render.settings` (:class:`RenderSettings`, :class:`RenderError`).

Everything runs as drjit wavefronts (no Python loops over pixels or edges). Values that change
between calls (seed, light intensity, cameras, texture sizes) enter the kernels as opaque
values, so compiled kernels are reused across iterations; the image size and spp are literals
(kernels compile once per resolution).
"""

from __future__ import annotations

import logging
from typing import Sequence

import numpy as np

from recon.brdf import R_MIN
from recon.io.cameras import Camera
from recon.mi import load_variant
from recon.render.arrays import aligned
from recon.render.boundary import boundary_term
from recon.render.edges import EdgeTopology, edge_topology
from recon.render.rays import (camera_table, flash_positions, given_view_table, primary_rays, trace,
                               view_table)
from recon.render.settings import BOUNDARY_MODES, RenderError, RenderSettings
from recon.render.shading import Surface, safe_normalize, shade

log = logging.getLogger(__name__)

__all__ = ["RenderSettings", "CollocatedRenderer", "RenderError", "R_MIN", "camera_table",
           "BOUNDARY_MODES"]


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

    # RenderSettings is a frozen dataclass: one shared default is safe
    def __init__(self, t_pos_idx, v_tex, t_tex_idx, settings: RenderSettings = RenderSettings()):  # noqa: B008
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
        self._faces = mi.UInt32(aligned(self.t_pos_idx, np.uint32))
        # Per face corner UVs, (F*3, 2) flattened; gathered by face id at the hit.
        corner_uv = v_tex[self.t_tex_idx].reshape(-1, 2).astype(np.float32)
        self._corner_uv = mi.Float(aligned(corner_uv, np.float32))
        self.topology: EdgeTopology = edge_topology(self.t_pos_idx)
        self._scene = None
        self._scene_params = None
        self._n_vertices = None
        self._projective = None
        self.timings: dict[str, float] = {}
        self._t_mark = 0.0
        self._offset = None  # the call's flash offset (3 opaque Floats), see render_batch

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

    # ---- Inputs: checked, as flat drjit arrays ----
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
            flat = mi.Float(aligned(arr, np.float32))
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
            flat = mi.Float(aligned(arr, np.float32))
        return flat, int(shape[0]), int(shape[1]), int(shape[2])

    # ---- The scene: Mitsuba's BVH and the vertex normals ----
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
        nrm = safe_normalize(dr, dr.gather(mi.Vector3f, acc, vid))
        flat = dr.zeros(mi.Float, 3 * n_vertices)
        dr.scatter(flat, nrm, vid)
        dr.eval(flat)
        return flat

    # ---- Public: render, render_batch, render_torch ----
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
        ambient_e = dr.opaque(mi.Float, float(ambient) / float(light_intensity)) if ambient > 0 else None
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
        cam_table = view_table(dr, mi, cameras) if camera_table is None else \
            given_view_table(dr, mi, camera_table, B)
        self._mark("normals", n_flat)
        surface = Surface(self._faces, self._corner_uv, v_flat, n_flat, tex, self.settings.r_min,
                          ambient_e)
        spp = int(self.settings.spp)
        seed_o = dr.opaque(mi.UInt32, np.uint32(seed & 0xFFFFFFFF))
        # ---- Interior: MC over pixel footprints, AD through the integrand
        o, d, view = primary_rays(dr, mi, cam_table, B, w, h, spp, seed_o, self.settings.stratified)
        prim, valid, _ = trace(mi, scene, o, d)
        L = shade(dr, mi, surface, o, d, prim, valid,
                  flash_positions(dr, mi, cam_table, view, self._offset))
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
            boundary_term(self, flat, scene, surface, cameras, cam_table, float(light_intensity),
                          seed)
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
