"""Mitsuba 3 BSDF ``recon_svbrdf``: the general model of DESIGN section 3 with textures.

This plugin, the mesh builder :func:`mitsuba_mesh` and :func:`render_reference` are the
project's FORWARD REFERENCE: they render the image formation of DESIGN section 3 (point light
of intensity I_e at the camera center, pixel-footprint average with a box filter, shading
normals = area-weighted vertex normals interpolated barycentrically) with Mitsuba, checked
against :mod:`recon.brdf` by the tests.

Plugin parameters (each a Mitsuba texture, or a constant):

- ``diffuse``: RGB diffuse albedo a_d.
- ``specular``: specular albedo a_s, one channel (broadcast to RGB) or RGB.
- ``roughness``: perceptual roughness r (one channel), clipped to [``r_min``, 1]; alpha = r^2.
- ``r_min``: float, default :data:`recon.brdf.R_MIN`.

``eval()`` returns f * cos(theta_o) (Mitsuba's convention), zero unless both directions are
above the shading frame's horizon (front side only). ``sample()`` draws from a mixture of
cosine-weighted hemisphere sampling and GGX normal sampling (pdf D(h) cos(theta_h)),
``pdf()`` is that mixture's density, so the plugin also works with the ``path`` integrator
under environment lighting. Component 0 is the diffuse lobe, component 1 the specular one.

Texture maps (numpy ``(H, W, C)``, first row = top) become Mitsuba ``bitmap`` textures with
``raw=True`` (no sRGB decoding), bilinear filtering and clamped borders. Mitsuba's texture
coordinates put uv.y = 0 at the first row, the OBJ convention (DESIGN section 2) puts v = 1
there: :func:`mitsuba_mesh` flips v, the one place where that happens.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping

import numpy as np

from recon.brdf import R_MIN
from recon.io.cameras import Camera, mitsuba_sensor_dict
from recon.io.mesh import Mesh
from recon.mi import load_variant
from recon import mi as recon_mi

log = logging.getLogger(__name__)

PLUGIN_NAME = "recon_svbrdf"
TEXTURE_KEYS = ("diffuse", "specular", "roughness")
_registered: set[str] = set()  # variants for which the plugin is registered


class TextureError(ValueError):
    """Texture maps that do not fit the model; the message names the map and the fix."""


# ---- The BSDF ----
def _make_bsdf_class(mi):
    """The plugin class for the current variant (``mi.BSDF`` differs per variant)."""
    import drjit as dr

    inv_pi = 1.0 / np.pi

    class ReconSVBRDF(mi.BSDF):
        """Textured diffuse + GGX/Schlick/Smith specular (DESIGN section 3), front side only."""

        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            self.diffuse = props.get_texture("diffuse", 0.5)
            self.specular = props.get_texture("specular", 0.04)
            self.roughness = props.get_texture("roughness", 0.5)
            self.r_min = float(props.get("r_min", R_MIN))
            if not (0.0 < self.r_min <= 1.0):
                raise ValueError(f"{PLUGIN_NAME}: r_min must lie in (0, 1], got {self.r_min}")
            common = mi.BSDFFlags.FrontSide | mi.BSDFFlags.SpatiallyVarying
            self.m_components = [
                mi.BSDFFlags.DiffuseReflection | common,
                mi.BSDFFlags.GlossyReflection | common,
            ]
            self.m_flags = self.m_components[0] | self.m_components[1]

        # -- the textures at a surface point --
        def _params(self, si, active):
            a_d = self.diffuse.eval(si, active)  # Color3f
            a_s = self.specular.eval(si, active)  # Color3f (one channel is broadcast)
            r = dr.clip(self.roughness.eval_1(si, active), self.r_min, 1.0)
            return a_d, a_s, r * r

        def _spec_prob(self, ctx, a_d, a_s):
            """Probability of sampling the specular lobe (the same in sample() and pdf())."""
            has_d = ctx.is_enabled(mi.BSDFFlags.DiffuseReflection, 0)
            has_s = ctx.is_enabled(mi.BSDFFlags.GlossyReflection, 1)
            if not has_s:
                return mi.Float(0.0)
            if not has_d:
                return mi.Float(1.0)
            s = dr.mean(a_s)
            d = dr.mean(a_d)
            # Schlick's term brightens the specular lobe at grazing angles: never sample it
            # (or the diffuse lobe) with less than 20 %.
            return dr.clip(s / dr.maximum(s + d, 1e-8), 0.2, 0.8)

        # -- the model --
        @staticmethod
        def _ggx_D(h, a2):
            """GGX D(h) for a unit local half vector h, 0 below the horizon.

            (n.h)^2 (alpha^2 - 1) + 1 is written sin^2 + cos^2 alpha^2 with sin^2 = h.x^2 + h.y^2:
            the DESIGN form cancels catastrophically in float32 near the peak at small alpha.
            """
            sin2 = h.x * h.x + h.y * h.y
            t = sin2 + h.z * h.z * a2
            return dr.select(h.z > 0, a2 * inv_pi / dr.maximum(t * t, 1e-38), 0.0)

        def _f_cos(self, ctx, si, wo, a_d, a_s, alpha):
            """f(wo, wi) * cos(theta_o) where both cosines are positive, else 0."""
            cos_i = mi.Frame3f.cos_theta(si.wi)  # n . v
            cos_o = mi.Frame3f.cos_theta(wo)  # n . l
            front = (cos_i > 0) & (cos_o > 0)
            h = dr.normalize(si.wi + wo)
            v_h = dr.maximum(dr.dot(si.wi, h), 0.0)
            a2 = alpha * alpha
            D = self._ggx_D(h, a2)
            F = a_s + (1.0 - a_s) * dr.power(1.0 - v_h, 5)  # Schlick
            ci, co = dr.maximum(cos_i, 0.0), dr.maximum(cos_o, 0.0)
            # G1(n.l) G1(n.v) / (4 (n.l)(n.v)), finite at grazing angles
            vis = dr.rcp((ci + dr.sqrt(a2 + (1.0 - a2) * ci * ci))
                         * (co + dr.sqrt(a2 + (1.0 - a2) * co * co)))
            f = mi.Color3f(0.0)
            if ctx.is_enabled(mi.BSDFFlags.DiffuseReflection, 0):
                f += a_d * inv_pi
            if ctx.is_enabled(mi.BSDFFlags.GlossyReflection, 1):
                f += F * (D * vis)
            return dr.select(front, f * co, 0.0)

        def _pdf(self, ctx, si, wo, a_d, a_s, alpha):
            cos_i = mi.Frame3f.cos_theta(si.wi)
            cos_o = mi.Frame3f.cos_theta(wo)
            p_spec = self._spec_prob(ctx, a_d, a_s)
            h = dr.normalize(si.wi + wo)
            cos_h = mi.Frame3f.cos_theta(h)
            a2 = alpha * alpha
            D = self._ggx_D(h, a2)
            o_h = dr.maximum(dr.dot(wo, h), 1e-12)
            pdf_spec = dr.select(cos_h > 0, D * cos_h / (4.0 * o_h), 0.0)
            pdf_diff = dr.maximum(cos_o, 0.0) * inv_pi
            pdf = (1.0 - p_spec) * pdf_diff + p_spec * pdf_spec
            return dr.select((cos_i > 0) & (cos_o > 0), pdf, 0.0)

        # -- the mi.BSDF interface --
        def eval(self, ctx, si, wo, active=True):
            a_d, a_s, alpha = self._params(si, active)
            return dr.select(active, self._f_cos(ctx, si, wo, a_d, a_s, alpha), 0.0)

        def pdf(self, ctx, si, wo, active=True):
            a_d, a_s, alpha = self._params(si, active)
            return dr.select(active, self._pdf(ctx, si, wo, a_d, a_s, alpha), 0.0)

        def eval_pdf(self, ctx, si, wo, active=True):
            a_d, a_s, alpha = self._params(si, active)
            value = self._f_cos(ctx, si, wo, a_d, a_s, alpha)
            pdf = self._pdf(ctx, si, wo, a_d, a_s, alpha)
            return dr.select(active, value, 0.0), dr.select(active, pdf, 0.0)

        def sample(self, ctx, si, sample1, sample2, active=True):
            a_d, a_s, alpha = self._params(si, active)
            cos_i = mi.Frame3f.cos_theta(si.wi)
            active = active & (cos_i > 0)
            p_spec = self._spec_prob(ctx, a_d, a_s)
            use_spec = sample1 < p_spec
            # diffuse: cosine-weighted hemisphere
            wo_d = mi.warp.square_to_cosine_hemisphere(sample2)
            # specular: half vector with pdf D(h) cos(theta_h), mirrored about it
            tan2 = alpha * alpha * sample2.x / dr.maximum(1.0 - sample2.x, 1e-12)
            cos_h = dr.rsqrt(1.0 + tan2)
            sin_h = dr.sqrt(tan2) * cos_h
            s, c = dr.sincos(2.0 * dr.pi * sample2.y)
            h = mi.Vector3f(sin_h * c, sin_h * s, cos_h)
            wo_s = 2.0 * dr.dot(si.wi, h) * h - si.wi
            wo = dr.select(use_spec, wo_s, wo_d)

            bs = dr.zeros(mi.BSDFSample3f)
            bs.wo = wo
            bs.pdf = self._pdf(ctx, si, wo, a_d, a_s, alpha)
            bs.eta = 1.0
            bs.sampled_type = dr.select(use_spec, mi.UInt32(+mi.BSDFFlags.GlossyReflection),
                                        mi.UInt32(+mi.BSDFFlags.DiffuseReflection))
            bs.sampled_component = dr.select(use_spec, mi.UInt32(1), mi.UInt32(0))
            value = self._f_cos(ctx, si, wo, a_d, a_s, alpha)
            ok = active & (bs.pdf > 0) & (mi.Frame3f.cos_theta(wo) > 0)
            weight = dr.select(ok, value / dr.maximum(bs.pdf, 1e-20), 0.0)
            bs.pdf = dr.select(ok, bs.pdf, 0.0)
            return bs, weight

        def eval_diffuse_reflectance(self, si, active=True):
            return self.diffuse.eval(si, active)

        def traverse(self, callback):
            flags = +mi.ParamFlags.Differentiable
            callback.put("diffuse", self.diffuse, flags)
            callback.put("specular", self.specular, flags)
            callback.put("roughness", self.roughness, flags)

        def parameters_changed(self, keys):
            pass

        def to_string(self):
            return (f"ReconSVBRDF[\n  diffuse = {self.diffuse},\n  specular = {self.specular},\n"
                    f"  roughness = {self.roughness},\n  r_min = {self.r_min}\n]")

    return ReconSVBRDF


def register(variant: str | None = None):
    """Register the ``recon_svbrdf`` plugin for ``variant`` (default: the current one).

    Idempotent: a second call for the same variant does nothing. Returns the ``mitsuba``
    module with that variant set.
    """
    mi = load_variant(variant)
    name = mi.variant()
    if name not in _registered:
        cls = _make_bsdf_class(mi)
        mi.register_bsdf(PLUGIN_NAME, lambda props: cls(props))
        _registered.add(name)
        log.debug("registered %s for %s", PLUGIN_NAME, name)
    return mi


# ---- Textures ----
def texture_dict(value, name: str) -> dict | float:
    """A Mitsuba texture dict for one map: a constant, an RGB triple, or an ``(H, W, C)`` array.

    Arrays are ``(H, W)``, ``(H, W, 1)`` or ``(H, W, 3)``, first row = top of the image,
    linear values (no sRGB decoding), looked up bilinearly with texel centers at
    ((j + 0.5)/W, (i + 0.5)/H) in Mitsuba's uv (= OBJ (u, 1 - v)).
    """
    mi = load_variant_current()
    a = np.asarray(value, dtype=np.float32)
    if a.ndim == 0:
        return float(a)
    if a.ndim == 1:
        if a.shape[0] == 1:
            return float(a[0])
        if a.shape[0] == 3:
            return {"type": "rgb", "value": a.astype(float).tolist()}
        raise TextureError(f"{name}: a constant must have 1 or 3 values, got {a.shape}")
    if a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3 or a.shape[2] not in (1, 3) or a.shape[0] < 1 or a.shape[1] < 1:
        raise TextureError(f"{name}: expected an (H, W), (H, W, 1) or (H, W, 3) map, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise TextureError(f"{name}: the map contains NaN or Inf; fix the texture file")
    return {
        "type": "bitmap",
        "bitmap": mi.Bitmap(np.ascontiguousarray(a)),
        "raw": True,
        "filter_type": "bilinear",
        "wrap_mode": "clamp",
    }


def load_variant_current():
    """The mitsuba module with the variant already chosen (or the default one)."""

    return load_variant(recon_mi.variant())


def bsdf_dict(textures: Mapping[str, object], r_min: float = R_MIN) -> dict:
    """A ``recon_svbrdf`` dict from ``{'diffuse': ..., 'specular': ..., 'roughness': ...}``.

    Each value is an array map or a constant (see :func:`texture_dict`); ``diffuse`` must be
    RGB, ``roughness`` one channel. Missing keys take the plugin's defaults.
    """
    unknown = set(textures) - set(TEXTURE_KEYS)
    if unknown:
        raise TextureError(f"unknown texture names {sorted(unknown)}; expected {TEXTURE_KEYS}")
    d: dict = {"type": PLUGIN_NAME, "r_min": float(r_min)}
    for key in TEXTURE_KEYS:
        if key not in textures:
            continue
        a = np.asarray(textures[key])
        channels = 1 if a.ndim in (0, 2) else a.shape[-1]
        if key == "roughness" and channels != 1:
            raise TextureError(f"roughness: must have one channel, got shape {a.shape}")
        if key == "diffuse" and channels not in (1, 3):
            raise TextureError(f"diffuse: must be RGB, got shape {a.shape}")
        d[key] = texture_dict(a, key)
    return d


# ---- Meshes ----
def mitsuba_mesh(mesh: Mesh, name: str = "mesh", bsdf=None):
    """A ``mi.Mesh`` with explicit area-weighted vertex normals (DESIGN section 3).

    Vertices are split where a position has several UVs (chart seams); every copy keeps the
    normal of its position, so shading stays smooth across seams. UVs are converted from the
    OBJ convention (v up) to Mitsuba's (uv.y = 0 at the first texture row).

    Parameters
    ----------
    mesh : Mesh
        ``v_pos (V, 3)``, ``t_pos_idx (F, 3)``, optional ``v_tex (T, 2)``/``t_tex_idx (F, 3)``.
    name : str
        The Mitsuba shape id.
    bsdf : mi.BSDF or None
        Attached to the mesh when given (a dict is loaded with ``mi.load_dict``).
    """
    mi = load_variant_current()
    if len(mesh.t_pos_idx) == 0:
        raise ValueError(f"{name}: the mesh has no faces")
    normals = mesh.vertex_normals()
    if mesh.has_uv:
        pairs = np.stack([mesh.t_pos_idx.reshape(-1), mesh.t_tex_idx.reshape(-1)], axis=1)
        uniq, inverse = np.unique(pairs, axis=0, return_inverse=True)
        faces = inverse.reshape(-1, 3)
        pos = mesh.v_pos[uniq[:, 0]]
        nrm = normals[uniq[:, 0]]
        uv = mesh.v_tex[uniq[:, 1]].copy()
        uv[:, 1] = 1.0 - uv[:, 1]  # OBJ (v up) -> Mitsuba (uv.y = 0 at the first row)
    else:
        faces, pos, nrm, uv = mesh.t_pos_idx, mesh.v_pos, normals, None

    props = mi.Properties()
    if bsdf is not None:
        props["bsdf"] = mi.load_dict(bsdf) if isinstance(bsdf, dict) else bsdf
    m = mi.Mesh(name, len(pos), len(faces), props=props, has_vertex_normals=True,
                has_vertex_texcoords=uv is not None)
    params = mi.traverse(m)
    params["vertex_positions"] = mi.Float(np.ascontiguousarray(pos, np.float32).reshape(-1))
    params["faces"] = mi.UInt32(np.ascontiguousarray(faces, np.uint32).reshape(-1))
    if uv is not None:
        params["vertex_texcoords"] = mi.Float(np.ascontiguousarray(uv, np.float32).reshape(-1))
    params.update()
    # Setting the positions recomputes Mitsuba's own (angle-weighted) normals: set ours after.
    params["vertex_normals"] = mi.Float(np.ascontiguousarray(nrm, np.float32).reshape(-1))
    params.update()
    return m


# ---- The forward reference ----
def clip_range(camera: Camera, points: np.ndarray) -> dict:
    """``near_clip`` and ``far_clip`` of a Mitsuba sensor for ``camera`` that keep ``points``.

    Mitsuba's perspective sensor clips at fixed distances (near 1e-3 in
    :func:`recon.io.cameras.mitsuba_sensor_dict`, far 1e4 by default), which blacks out a scene
    smaller than about 1e-3 or farther than 1e4 units: the planes are set from the depths of
    ``points (N, 3)`` (the scene's vertices) instead, with a factor 2 of margin (the range
    stays valid while vertices move a little).
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    z = p @ np.asarray(camera.world_to_camera, dtype=np.float64)[2, :3] + camera.world_to_camera[2, 3]
    z_max = float(z.max()) if len(z) else 0.0
    if not (np.isfinite(z_max) and z_max > 0):  # nothing in front of the camera: keep the defaults
        return {}
    ahead = z[z > 1e-6 * z_max]
    near = 0.5 * float(ahead.min()) if (z > 1e-6 * z_max).all() else 1e-6 * z_max
    return {"near_clip": near, "far_clip": 2.0 * z_max}


def scene_dict(mesh: Mesh, textures: Mapping[str, object], camera: Camera,
               light_intensity: float, spp: int, r_min: float = R_MIN,
               light_position=None) -> dict:
    """The Mitsuba scene of DESIGN section 3 for one view (the plugin must be registered).

    ``light_position`` (3,) moves the point light away from the camera centre (a phone's flash,
    DESIGN section 7).
    """
    if not np.isfinite(light_intensity) or light_intensity <= 0:
        raise ValueError(f"light_intensity must be a positive number, got {light_intensity}")
    if spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    mi = load_variant_current()
    bsdf = mi.load_dict(bsdf_dict(textures, r_min))
    center = np.asarray(camera.center if light_position is None else light_position, dtype=float)
    return {
        "type": "scene",
        # A point light needs emitter sampling only; the pixel filter is a box (DESIGN 3).
        "integrator": {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0},
        "sensor": {**mitsuba_sensor_dict(camera, spp=spp, rfilter="box"), **clip_range(camera, mesh.v_pos)},
        "light": {"type": "point", "position": center.tolist(),
                  "intensity": {"type": "rgb", "value": [float(light_intensity)] * 3}},
        "object": mitsuba_mesh(mesh, "object", bsdf=bsdf),
    }


def ambient_scene_dict(flash_scene: dict, ambient: float) -> dict:
    """The ambient pass of a scene: ``flash_scene`` with its point light replaced by a constant
    environment of radiance ``ambient`` (hidden from camera rays: the background stays black),
    sampled with MIS. Rendered apart from the flash and added: Mitsuba 3.9's ``direct``
    integrator with ``emitter_samples`` > 1 counted the point light twice here."""
    if not np.isfinite(ambient) or ambient <= 0:
        raise ValueError(f"ambient must be a radiance > 0, got {ambient}")
    d = {k: v for k, v in flash_scene.items() if k != "light"}
    d["integrator"] = {"type": "direct", "emitter_samples": 2, "bsdf_samples": 2, "hide_emitters": True}
    d["ambient"] = {"type": "constant", "radiance": {"type": "rgb", "value": [float(ambient)] * 3}}
    return d


def render_reference(mesh: Mesh, textures: Mapping[str, object], camera: Camera,
                     light_intensity: float = 1.0, spp: int = 64, seed: int = 0,
                     variant: str | None = None, r_min: float = R_MIN,
                     alpha: bool = False, light_position=None, ambient: float = 0.0) -> np.ndarray:
    """Render one view of the textured mesh lit by the point light at the camera center
    (or at ``light_position``, plus a constant environment ``ambient``: see :func:`scene_dict`).

    Parameters
    ----------
    mesh : Mesh
        With UVs when any texture is a map.
    textures : mapping
        ``diffuse`` (H, W, 3), ``specular`` (H, W, 1|3), ``roughness`` (H, W, 1) float maps
        (or constants), first row = top, linear.
    camera : Camera
        Pinhole, square pixels (OpenCV axes, DESIGN section 1).
    light_intensity : float
        I_e of the collocated point light.
    spp, seed : int
        Samples per pixel (box filter) and the sampler seed.
    variant : str or None
        Mitsuba variant (default: the current one, else ``llvm_ad_rgb``).
    r_min : float
        Smallest roughness.
    alpha : bool
        Also return the pixel coverage (fraction of the pixel's footprint on the mesh).

    Returns
    -------
    (H, W, 3) float32 linear radiance, the pixel average of I(x) of DESIGN section 3
    ((H, W, 4) with the coverage last when ``alpha``).
    """
    if any(not np.isscalar(v) and np.asarray(v).ndim >= 2 for v in textures.values()) \
            and not mesh.has_uv:
        raise TextureError("render_reference: texture maps need a mesh with UVs")
    mi = register(variant)
    d = scene_dict(mesh, textures, camera, light_intensity, spp, r_min, light_position)
    if alpha:
        d["sensor"]["film"]["pixel_format"] = "rgba"
    scene = mi.load_dict(d)
    img = np.array(mi.render(scene, seed=int(seed), spp=int(spp)), dtype=np.float32)[:, :, : 4 if alpha else 3]
    if ambient > 0:
        amb = mi.render(mi.load_dict(ambient_scene_dict(d, ambient)), seed=int(seed) + 1, spp=int(spp))
        img[:, :, :3] += np.array(amb, dtype=np.float32)[:, :, :3]
    return img
