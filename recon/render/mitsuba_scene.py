"""The renderer's scene as a differentiable Mitsuba scene, for comparisons.

:class:`MitsubaScene` renders the same image formation as :class:`CollocatedRenderer` with
Mitsuba's own integrators: the ``recon_svbrdf`` plugin (:mod:`recon.render.mitsuba_bsdf`),
a point light moved to each camera center, a box-filtered perspective sensor per view, and
the mesh's shading normals set to the renderer's differentiable area-weighted vertex normals
(so gradients through normals match). With ``integrator="direct_projective"`` it gives
Mitsuba's projective-sampling gradients (``RenderSettings(boundary="projective")`` routes
here); with ``"direct"`` the interior term only. It is slow and exists to check and benchmark
the renderer against.

Caveat (measured with Mitsuba 3.9.1): vertices are split where a position has several UVs,
which gives Mitsuba's mesh open edges along UV seams, and ``direct_projective`` is biased
there (20-60 % off finite differences on a 16 x 8 UV sphere); it is also a few percent off on
coarse smooth-shaded meshes without seams. Compare on seamless, fine meshes.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from recon.io.cameras import Camera, mitsuba_sensor_dict
from recon.render.mitsuba_bsdf import clip_range
from recon.render import mitsuba_bsdf
from recon.render.mitsuba_bsdf import bsdf_dict

__all__ = ["MitsubaScene", "render_projective"]

INTEGRATORS = ("direct_projective", "direct")


class MitsubaScene:
    """A Mitsuba scene mirroring a :class:`CollocatedRenderer`'s mesh topology and UVs.

    Parameters
    ----------
    renderer : CollocatedRenderer
        Supplies the topology, UVs, variant and the vertex-normal computation.
    integrator : str
        ``"direct_projective"`` (interior + boundary) or ``"direct"`` (interior only).
    """

    def __init__(self, renderer, integrator: str = "direct_projective"):

        if integrator not in INTEGRATORS:
            raise ValueError(f"integrator must be one of {INTEGRATORS}, got {integrator!r}")
        self.renderer = renderer
        self.integrator_name = integrator
        self.mi = mitsuba_bsdf.register(renderer.settings.variant)
        self.dr = renderer.dr
        mi = self.mi
        r = renderer
        # Split vertices where a position has several UVs (chart seams).
        pairs = np.stack([r.t_pos_idx.reshape(-1), r.t_tex_idx.reshape(-1)], axis=1)
        uniq, inverse = np.unique(pairs, axis=0, return_inverse=True)
        self._split_pos = mi.UInt32(uniq[:, 0].astype(np.uint32))
        self.n_split = len(uniq)
        faces = inverse.reshape(-1, 3).astype(np.uint32)
        corner_uv = np.asarray(r._corner_uv.numpy()).reshape(-1, 2)  # per face corner
        uv = np.zeros((len(uniq), 2), np.float32)
        uv[inverse.reshape(-1)] = corner_uv
        uv[:, 1] = 1.0 - uv[:, 1]  # OBJ (v up) -> Mitsuba (uv.y = 0 at the first row)
        self._faces = faces
        self._uv = uv
        self._scenes: list = []  # (scene, params) per view of a batch, see render()
        self._tex_shapes = None
        if integrator == "direct_projective":
            self._integrator = mi.load_dict({"type": "direct_projective", "sppi": 0})
        else:
            self._integrator = mi.load_dict(
                {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0})

    def _build_scene(self, textures: dict):
        """One scene (mesh, BSDF, point light) and its parameters; textures get their shapes."""

        mi = self.mi
        bsdf = mi.load_dict(bsdf_dict({k: np.zeros(s, np.float32) + 0.5
                                       for k, s in textures.items()},
                                      self.renderer.settings.r_min))
        props = mi.Properties()
        props["bsdf"] = bsdf
        mesh = mi.Mesh("object", self.n_split, len(self._faces), props=props,
                       has_vertex_normals=True, has_vertex_texcoords=True)
        mp = mi.traverse(mesh)
        mp["faces"] = mi.UInt32(self._faces.reshape(-1))
        mp["vertex_texcoords"] = mi.Float(self._uv.reshape(-1))
        mp["vertex_positions"] = self.dr.zeros(mi.Float, 3 * self.n_split)
        mp.update()
        scene = mi.load_dict({
            "type": "scene",
            "integrator": self._integrator,
            "light": {"type": "point", "position": [0.0, 0.0, 0.0],
                      "intensity": {"type": "rgb", "value": [1.0, 1.0, 1.0]}},
            "object": mesh,
        })
        return scene, mi.traverse(scene)

    def render(self, v_pos, diffuse, specular, roughness, cameras: Sequence[Camera],
               light_intensity: float, seed: int, spp: int):
        """(B, h, w, 3) mi.TensorXf, differentiable w.r.t. drjit inputs with grads enabled."""
        dr, mi, r = self.dr, self.mi, self.renderer
        v_flat, nv = r._vertex_array(v_pos)
        tex = {
            "diffuse": _as_tensor(mi, diffuse),
            "specular": _as_tensor(mi, specular),
            "roughness": _as_tensor(mi, roughness),
        }
        shapes = {k: tuple(t.shape) for k, t in tex.items()}
        if shapes != self._tex_shapes:
            self._scenes, self._tex_shapes = [], shapes
        while len(self._scenes) < len(cameras):
            self._scenes.append(self._build_scene(shapes))
        n_flat = r._vertex_normals(v_flat, nv)
        v_np = dr.detach(v_flat).numpy().reshape(-1, 3)  # for the sensors' clip planes
        pos = dr.ravel(dr.gather(mi.Point3f, v_flat, self._split_pos))
        nrm = dr.ravel(dr.gather(mi.Vector3f, n_flat, self._split_pos))
        images = []
        for i, cam in enumerate(cameras):
            # One scene per view of the batch: mi.render's backward pass replays the scene in the
            # state it has then, so a light moved for a later view would light every earlier one.
            scene, p = self._scenes[i]
            p["object.vertex_positions"] = pos
            p.update()
            # Setting positions makes Mitsuba recompute its own (angle-weighted) normals: use ours.
            p["object.vertex_normals"] = nrm
            p["object.bsdf.diffuse.data"] = tex["diffuse"]
            p["object.bsdf.specular.data"] = tex["specular"]
            p["object.bsdf.roughness.data"] = tex["roughness"]
            # Opaque: literal values would be baked into the kernels (recompiled per view and call).
            p["light.intensity.value"] = dr.opaque(mi.Color3f, float(light_intensity))
            p["light.position"] = dr.opaque(mi.Point3f, [float(x) for x in cam.center])
            p.update()
            sensor = mi.load_dict({**mitsuba_sensor_dict(cam, spp=spp, sample_border=True),
                                   **clip_range(cam, v_np)})
            # Opaque seeds: a literal seed would be baked into the kernels (recompiled every call).
            img = mi.render(scene, p, sensor=sensor, spp=spp,
                            seed=dr.opaque(mi.UInt32, (int(seed) * 1009 + i) % 2**32),
                            seed_grad=dr.opaque(mi.UInt32, (int(seed) * 1009 + i + 7) % 2**32))
            images.append(img[:, :, :3])
        h, w = int(cameras[0].height), int(cameras[0].width)
        flat = dr.concat([im.array for im in images]) if len(images) > 1 else images[0].array
        return mi.TensorXf(flat, shape=(len(images), h, w, 3))


def _as_tensor(mi, x):
    if isinstance(x, mi.TensorXf):
        return x
    return mi.TensorXf(np.ascontiguousarray(np.asarray(x, dtype=np.float32)))


def render_projective(renderer, v_pos, diffuse, specular, roughness, cameras, light_intensity,
                      seed):
    """``RenderSettings(boundary="projective")``: Mitsuba ``direct_projective`` render."""
    if renderer._projective is None:
        renderer._projective = MitsubaScene(renderer, "direct_projective")
    return renderer._projective.render(v_pos, diffuse, specular, roughness, cameras,
                                       light_intensity, seed, int(renderer.settings.spp))
