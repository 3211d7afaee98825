"""Shading of the differentiable renderer (:mod:`recon.render.collocated`): the radiance toward
the camera at a ray's first hit, in drjit.

    I(x) = I_e * (a_d / pi + a_s D(mu) G1(mu)^2 / (4 mu^2)) * max(0, mu) / |y - o|^2

for the flash at the lens (:func:`shade_collocated`), the general model of DESIGN section 3 for
the flash beside it (:func:`shade_offset`), plus ``A (a_d + a_s)`` for a constant ambient
environment. The hit is recomputed from the differentiable triangle on the fixed ray
(Moller-Trumbore), so it slides along the ray as the triangle moves, and so do the barycentrics,
the shading normal (interpolated area-weighted vertex normals) and the UV; the maps are looked
up bilinearly (DESIGN UV convention, clamp to the edge texels). Both shading kernels are copies
of the model listed in :mod:`recon.brdf`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

__all__ = ["Surface", "shade", "shade_collocated", "shade_offset", "bilinear", "safe_normalize"]


@dataclass(frozen=True)
class Surface:
    """What one render call shades: the mesh, its maps and the ambient light, as drjit arrays.

    Attributes
    ----------
    faces : mi.UInt32 (3F)
        Vertex ids per face corner.
    corner_uv : mi.Float (6F)
        UVs per face corner (OBJ convention, v up).
    v_flat : mi.Float (3V)
        Vertex positions (gradients flow where enabled).
    n_flat : mi.Float (3V)
        Area-weighted vertex normals computed from ``v_flat`` (differentiable).
    tex : dict
        ``"diffuse"``, ``"specular"``, ``"roughness"`` -> (flat mi.Float, H, W, C); H and W
        opaque UInt32 (maps of one size share them).
    r_min : float
        Roughness is clamped to [r_min, 1].
    ambient : opaque mi.Float or None
        The constant environment's radiance relative to I_e; None: no ambient light.
    """

    faces: object
    corner_uv: object
    v_flat: object
    n_flat: object
    tex: dict
    r_min: float
    ambient: object = None

    def detached(self, dr) -> "Surface":
        """The same surface without gradients (the boundary term's side rays)."""
        return replace(self, v_flat=dr.detach(self.v_flat), n_flat=dr.detach(self.n_flat),
                       tex={k: (dr.detach(v[0]),) + tuple(v[1:]) for k, v in self.tex.items()})


# ---- The hit: position, normal, maps ----
def shade(dr, mi, surface: Surface, o, d, prim, valid, light=None):
    """Radiance/I_e toward the camera at the first hit of rays (o, d) (Color3f), differentiable.

    The hit is recomputed from the (differentiable) triangle ``prim`` on the fixed ray.
    ``light``: per-lane point light positions (the flash beside the lens) for the general
    model of DESIGN section 3 (l != v); None: the light is at ``o`` (the collocated model).
    The surface's ambient radiance (relative to I_e) adds ``A (a_d + a_s)`` at every hit (an
    unoccluded constant environment). Flash offset and ambient light are the scene side of the
    image formation of :mod:`recon.optimize.formation`, copied here in drjit for speed;
    ``test_flash_offset_and_ambient_match_the_formation`` in tests/render/test_collocated.py
    holds the copy to it.
    """
    base = prim * 3
    vi = [dr.gather(mi.UInt32, surface.faces, base + k, valid) for k in range(3)]
    p0, p1, p2 = (dr.gather(mi.Point3f, surface.v_flat, i, valid) for i in vi)
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
    n0, n1, n2 = (dr.gather(mi.Vector3f, surface.n_flat, i, valid) for i in vi)
    n = safe_normalize(dr, n0 * b0 + n1 * b1 + n2 * b2)
    to_o = o - y
    dist2 = dr.squared_norm(to_o)
    w = to_o * dr.rsqrt(dr.maximum(dist2, 1e-30))
    mu = dr.dot(n, w)
    # 1 - mu^2 as |n x w|^2: exact near the specular peak, where 1 - mu^2 cancels.
    sin2 = dr.squared_norm(dr.cross(n, w))
    # ---- textures at the interpolated UV
    uv = mi.Point2f(0.0)
    for k, bk in enumerate((b0, b1, b2)):
        uv += bk * dr.gather(mi.Point2f, surface.corner_uv, prim * 3 + k, valid)
    a_d = bilinear(dr, mi, surface.tex["diffuse"], uv, valid)
    a_s = bilinear(dr, mi, surface.tex["specular"], uv, valid)
    r = bilinear(dr, mi, surface.tex["roughness"], uv, valid)
    r = dr.clip(r, surface.r_min, 1.0)
    alpha = r * r
    a2 = alpha * alpha
    # ---- the flash (at the lens or beside it), then the ambient light
    if light is not None:
        out = shade_offset(dr, y, n, w, mu, light, a_d, a_s, a2, valid)
    else:
        out = shade_collocated(dr, mu, sin2, dist2, a_d, a_s, a2, valid)
    if surface.ambient is not None:
        out = out + dr.select(valid, surface.ambient * (a_d + a_s), 0.0)
    return out


# ---- The flash at the lens ----
def shade_collocated(dr, mu, sin2, dist2, a_d, a_s, a2, valid):
    """The collocated BRDF (DESIGN section 3) times the cosine and the falloff. One of the
    model's copies listed in :mod:`recon.brdf`."""
    mu_p = dr.maximum(mu, 0.0)
    den = dr.fma(mu_p * mu_p, a2, sin2)  # mu^2 (a2 - 1) + 1
    D = a2 * dr.rcp(dr.pi * dr.maximum(den * den, 1e-30))
    g = dr.rcp(mu_p + dr.sqrt(dr.fma(1.0 - a2, mu_p * mu_p, a2)))  # G1(mu) / (2 mu)
    spec = D * g * g
    f = a_d * dr.inv_pi + a_s * spec
    lit = valid & (mu > 0)
    return dr.select(lit, f * (mu_p * dr.rcp(dr.maximum(dist2, 1e-30))), 0.0)


# ---- The flash beside the lens ----
def shade_offset(dr, y, n, w, nv, light, a_d, a_s, a2, valid):
    """The general model of DESIGN section 3 for a light at ``light`` seen from the camera
    (unit direction ``w`` from the hit ``y``, ``nv`` = n . w): GGX D(n . h), Schlick F(v . h),
    separable Smith G1, times n . l / |light - y|^2. No shadow test: the flash sits ~1 cm from
    the lens, so what the camera sees is lit except in slivers. One of the model's copies
    listed in :mod:`recon.brdf`."""
    lv = light - y
    dl2 = dr.squared_norm(lv)
    l = lv * dr.rsqrt(dr.maximum(dl2, 1e-30))  # noqa: E741
    nl = dr.dot(n, l)
    nl_p = dr.maximum(nl, 0.0)
    nv_p = dr.maximum(nv, 0.0)
    hv = safe_normalize(dr, l + w)
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


# ---- Helpers ----
def safe_normalize(dr, v):
    """v / |v|, 0 where |v| == 0, finite gradient everywhere."""
    n2 = dr.squared_norm(v)
    ok = n2 > 1e-36
    return v * dr.select(ok, dr.rsqrt(dr.select(ok, n2, 1.0)), 0.0)


def bilinear(dr, mi, texture, uv, active):
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
