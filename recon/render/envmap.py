"""Relighting under an environment map: the relighting image RMSE of DESIGN section 5.

DESIGN section 5 compares images "rendered with the collocated light (and, for relighting, an
environment map)". This module supplies the environment map and the renderer for that second
case:

- :func:`envmap_image`: a deterministic procedural HDR "studio" map (equirectangular, float32
  linear RGB): a sky gradient over a dark ground plus two small bright rectangular softboxes
  (a key and a fill light), so highlights move with the specular albedo and roughness.
- :func:`envmap_directions`: the world direction of every texel (the map's convention).
- :func:`render_envmap` / :func:`render_envmap_views`: the textured mesh with the
  ``recon_svbrdf`` BSDF (:mod:`recon.render.mitsuba_bsdf`, DESIGN section 3's general model)
  lit by the map, rendered with Mitsuba's ``path`` integrator (``max_depth`` 3 = direct light
  plus one indirect bounce). The map lights the object but is not seen behind it (black
  background, like the collocated images); the alpha channel is the pixel coverage.
- :func:`relight_rmse`: reconstruction against ground truth under the map, per view and mean:
  sRGB in [0, 1], over the union of the two coverage masks (:func:`recon.metrics.image_rmse`).

Convention of the map (world z up, like the synthetic captures' cameras): row i of an H x W
map holds the polar angle theta = pi i / (H - 1) from +z (the first row is the zenith, the last
the nadir: Mitsuba's envmap puts its row samples on the poles), column j the azimuth
phi = 2 pi (j + 0.5) / W measured from +y toward +x:
``d = (sin theta sin phi, sin theta cos phi, cos theta)``; lookups between samples are bilinear.
This is Mitsuba's ``envmap`` convention (y up, u = atan2(x, -z) / 2 pi) rotated by +90 degrees
about x, done once in :func:`envmap_emitter_dict`, and checked against Mitsuba's lookups by
``tests/render/test_envmap.py``.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence

import numpy as np

from recon.brdf import R_MIN
from recon.io.cameras import Camera, mitsuba_sensor_dict
from recon.io.mesh import Mesh
from recon.render.mitsuba_bsdf import load_variant_current
from recon.render import mitsuba_bsdf
from recon.metrics import image_rmse

log = logging.getLogger(__name__)

__all__ = [
    "EnvmapError",
    "envmap_directions",
    "envmap_image",
    "envmap_emitter_dict",
    "render_envmap",
    "render_envmap_views",
    "relight_rmse",
]

MAX_DEPTH = 3
"""Path length: 2 = direct lighting only, 3 = direct plus one indirect bounce."""


class EnvmapError(ValueError):
    """An environment map or a render request that cannot be used; the message says why."""


# ---- The map ----
def envmap_directions(width: int, height: int, supersample: int = 1) -> np.ndarray:
    """World directions of the texel centers (or of ``supersample``^2 points per texel).

    Returns
    -------
    (H, W, 3) float64 unit vectors, or (H, W, s*s, 3) when ``supersample`` s > 1; see the
    module docstring for the convention.
    """
    if width < 2 or height < 2:
        raise EnvmapError(f"envmap size must be at least 2 x 2, got {width} x {height}")
    s = int(supersample)
    off = (np.arange(s) + 0.5) / s - 0.5  # offsets within a texel, about its center
    # rows sit on theta = pi i / (H - 1); a row's texel spans half a row spacing each way
    theta = np.clip(np.pi * (np.arange(height)[:, None] + off[None, :]) / (height - 1), 0.0, np.pi)
    phi = 2 * np.pi * (np.arange(width)[:, None] + 0.5 + off[None, :]) / width  # (W, s)
    th = theta[:, None, :, None]  # (H, 1, s, 1)
    ph = phi[None, :, None, :]  # (1, W, 1, s)
    d = np.stack(np.broadcast_arrays(np.sin(th) * np.sin(ph), np.sin(th) * np.cos(ph),
                                     np.cos(th) + 0 * ph), axis=-1)  # (H, W, s, s, 3)
    d = d.reshape(height, width, s * s, 3)
    return d[:, :, 0] if s == 1 else d


def _softbox(d: np.ndarray, azimuth_deg: float, elevation_deg: float, half_width_deg: float,
             half_height_deg: float) -> np.ndarray:
    """1 inside an angular rectangle around (azimuth, elevation), else 0; ``d`` (..., 3)."""
    el = np.degrees(np.arcsin(np.clip(d[..., 2], -1, 1)))
    az = np.degrees(np.arctan2(d[..., 0], d[..., 1]))
    daz = (az - azimuth_deg + 180.0) % 360.0 - 180.0
    # the box's angular width is measured on the sphere: scale azimuth by cos(elevation)
    inside = (np.abs(daz) * np.cos(np.radians(el)) <= half_width_deg) \
        & (np.abs(el - elevation_deg) <= half_height_deg)
    return inside.astype(np.float64)


def envmap_image(width: int = 128, height: int = 64, sky: float = 1.0, key: float = 12.0,
                 fill: float = 4.0) -> np.ndarray:
    """The procedural "studio" environment map (deterministic, no randomness).

    Sky: a gradient from a warm grey horizon (0.60, 0.58, 0.55) to a blue zenith
    (0.30, 0.40, 0.60), times ``sky``. Ground (below the horizon): (0.16, 0.14, 0.12) x ``sky``.
    Key softbox: azimuth 35 deg, elevation 40 deg, 16 x 12 deg, radiance ``key`` x
    (1.0, 0.96, 0.90). Fill softbox: azimuth 210 deg, elevation 15 deg, 10 x 8 deg, radiance
    ``fill`` x (0.85, 0.92, 1.0). Texels are averaged over 4 x 4 directions (anti-aliased box
    edges).

    Parameters
    ----------
    width, height : int
        Map size (equirectangular: width = 2 x height is usual).
    sky, key, fill : float
        Scales of the three parts (0 switches a part off).

    Returns
    -------
    (height, width, 3) float32 linear RGB radiance, first row = zenith, last row = nadir.
    """
    for name, v in (("sky", sky), ("key", key), ("fill", fill)):
        if not np.isfinite(v) or v < 0:
            raise EnvmapError(f"envmap_image: {name} must be a finite number >= 0, got {v}")
    d = envmap_directions(width, height, supersample=4)  # (H, W, 16, 3)
    z = d[..., 2:3]
    t = np.sqrt(np.clip(z, 0.0, 1.0))
    horizon, zenith = np.array([0.60, 0.58, 0.55]), np.array([0.30, 0.40, 0.60])
    sky_rgb = np.where(z >= 0, horizon * (1 - t) + zenith * t, np.array([0.16, 0.14, 0.12]))
    img = sky * sky_rgb
    img = img + key * np.array([1.0, 0.96, 0.90]) * _softbox(d, 35.0, 40.0, 8.0, 6.0)[..., None]
    img = img + fill * np.array([0.85, 0.92, 1.0]) * _softbox(d, 210.0, 15.0, 5.0, 4.0)[..., None]
    return img.mean(axis=2).astype(np.float32)


def _check_envmap(envmap) -> np.ndarray:
    a = np.asarray(envmap, dtype=np.float32)
    if a.ndim != 3 or a.shape[2] != 3 or a.shape[0] < 2 or a.shape[1] < 2:
        raise EnvmapError(f"envmap must be an (H, W, 3) RGB image with H, W >= 2, got shape {a.shape}")
    if not np.all(np.isfinite(a)) or (a < 0).any():
        raise EnvmapError("envmap must hold finite radiance values >= 0 (found NaN, Inf or negatives)")
    return np.ascontiguousarray(a)


def envmap_emitter_dict(envmap: np.ndarray, scale: float = 1.0) -> dict:
    """A Mitsuba ``envmap`` emitter dict for an (H, W, 3) map in this module's convention."""

    mi = load_variant_current()
    a = _check_envmap(envmap)
    return {
        "type": "envmap",
        "bitmap": mi.Bitmap(a),
        "scale": float(scale),
        # Mitsuba's map has +y up; ours has +z up: rotate local y onto world z.
        "to_world": mi.ScalarTransform4f().rotate([1.0, 0.0, 0.0], 90.0),
    }


# ---- Rendering ----
def _check_maps(mesh: Mesh, maps: Mapping[str, object]) -> None:
    if any(np.asarray(v).ndim >= 2 for v in maps.values()) and not mesh.has_uv:
        raise EnvmapError("render_envmap: texture maps need a mesh with UVs (v_tex, t_tex_idx)")


def render_envmap_views(mesh: Mesh, maps: Mapping[str, object], cameras: Sequence[Camera],
                        envmap: np.ndarray, spp: int = 64, seed: int = 0,
                        max_depth: int = MAX_DEPTH, variant: str | None = None,
                        r_min: float = R_MIN) -> list[np.ndarray]:
    """Render several views of one textured mesh under ``envmap`` (the scene is built once).

    Parameters
    ----------
    mesh : Mesh
        With UVs when any map is an array.
    maps : mapping
        ``diffuse`` (H, W, 3), ``specular`` (H, W, 1|3), ``roughness`` (H, W, 1) float maps
        (or constants), first row = top, linear (see :func:`recon.render.mitsuba_bsdf.bsdf_dict`).
    cameras : sequence of Camera
        Pinhole, square pixels, OpenCV axes.
    envmap : (He, We, 3) float
        Linear radiance, this module's convention.
    spp, seed : int
        Samples per pixel (box pixel filter) and the sampler seed (view k uses seed + k).
    max_depth : int
        Mitsuba's path length (2 = direct lighting only).
    variant : str or None
        Mitsuba variant (default: the current one, else ``llvm_ad_rgb``).
    r_min : float
        Smallest roughness of the BSDF.

    Returns
    -------
    list of (h, w, 4) float32: linear RGB radiance, then the pixel coverage in [0, 1].
    """

    if int(spp) < 1:
        raise EnvmapError(f"spp must be >= 1, got {spp}")
    if int(max_depth) < 2:
        raise EnvmapError(f"max_depth must be >= 2 (direct lighting), got {max_depth}")
    if len(cameras) == 0:
        return []
    _check_maps(mesh, maps)
    mi = mitsuba_bsdf.register(variant)
    bsdf = mi.load_dict(mitsuba_bsdf.bsdf_dict(maps, r_min))
    sensors = []
    for cam in cameras:
        # clip planes from the mesh's depths: the fixed defaults black out tiny or far scenes
        sd = {**mitsuba_sensor_dict(cam, spp=int(spp)), **mitsuba_bsdf.clip_range(cam, mesh.v_pos)}
        sd["film"]["pixel_format"] = "rgba"
        sensors.append(sd)
    scene = mi.load_dict({
        "type": "scene",
        # hide_emitters: the map lights the object but the background stays black
        "integrator": {"type": "path", "max_depth": int(max_depth), "hide_emitters": True},
        "emitter": envmap_emitter_dict(envmap),
        "sensor": sensors[0],
        "object": mitsuba_bsdf.mitsuba_mesh(mesh, "object", bsdf=bsdf),
    })
    out = []
    for k, sd in enumerate(sensors):
        sensor = scene.sensors()[0] if k == 0 else mi.load_dict(sd)
        img = mi.render(scene, sensor=sensor, seed=int(seed) + k, spp=int(spp))
        out.append(np.array(img, dtype=np.float32)[:, :, :4])
    return out


def render_envmap(mesh: Mesh, maps: Mapping[str, object], camera: Camera, envmap: np.ndarray,
                  spp: int = 64, seed: int = 0, max_depth: int = MAX_DEPTH,
                  variant: str | None = None, r_min: float = R_MIN) -> np.ndarray:
    """One view under ``envmap``: (h, w, 4) float32 linear RGB + coverage.

    See :func:`render_envmap_views` for the parameters.
    """
    return render_envmap_views(mesh, maps, [camera], envmap, spp, seed, max_depth, variant,
                               r_min)[0]


# ---- The metric ----
def relight_rmse(rec_mesh: Mesh, rec_maps: Mapping[str, object], gt_mesh: Mesh,
                 gt_maps: Mapping[str, object], cameras: Sequence[Camera],
                 envmap: np.ndarray | None = None, spp: int = 64, seed: int = 0,
                 max_depth: int = MAX_DEPTH, variant: str | None = None,
                 coverage_threshold: float = 0.5, seed_gt: int | None = None) -> dict:
    """Relighting image RMSE (DESIGN section 5) of a reconstruction against the ground truth.

    Both are rendered under ``envmap`` (default :func:`envmap_image`) from the same cameras,
    by default with the same seeds (common random numbers: equal scenes give equal images;
    ``seed_gt`` renders the ground truth with other seeds, e.g. to measure the Monte Carlo
    noise floor of the metric by comparing the ground truth with itself); the RMSE
    of sRGB values in [0, 1] runs over the union of the two masks (coverage >
    ``coverage_threshold``). Both meshes must be in the same frame.

    Returns
    -------
    dict with ``per_view`` (list of float), ``mean`` (float) and ``spp``.
    """

    if len(cameras) == 0:
        raise EnvmapError("relight_rmse: no cameras given")
    env = envmap_image() if envmap is None else envmap
    rec = render_envmap_views(rec_mesh, rec_maps, cameras, env, spp, seed, max_depth, variant)
    gt = render_envmap_views(gt_mesh, gt_maps, cameras, env, spp,
                             seed if seed_gt is None else seed_gt, max_depth, variant)
    per_view = []
    for a, b, cam in zip(rec, gt, cameras, strict=True):
        ma, mb = a[:, :, 3] > coverage_threshold, b[:, :, 3] > coverage_threshold
        if not (ma | mb).any():
            raise EnvmapError(f"relight_rmse: neither mesh is visible from camera {cam.image}")
        per_view.append(image_rmse(a[:, :, :3], b[:, :, :3], ma, mb))
    return {"per_view": per_view, "mean": float(np.mean(per_view)), "spp": int(spp)}
