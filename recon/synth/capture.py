"""Synthetic captures: a procedural object, baked SVBRDF maps, rendered flash photos (DESIGN 1).

:func:`make_capture` writes a capture folder exactly as DESIGN section 1 describes::

    OUT/images/<stem>.dng|.exr|.png   the photos
    OUT/cameras.json                  the true cameras (unless ``write_cameras`` is False)
    OUT/masks/<stem>.png              object masks (when ``write_masks``)
    OUT/capture.yaml                  light_intensity, only with ``state_light`` (a calibrated flash)
    OUT/gt/mesh.obj                   the true mesh with its UV atlas
    OUT/gt/diffuse.exr, specular.exr, roughness.exr   the true maps (linear, float32)
    OUT/gt/cameras.json               the true cameras, always
    OUT/gt/linear/<stem>.exr          noise-free linear renders (when ``write_gt_linear``)
    OUT/gt/synth.json, gt/README.md   settings, exposures, and how the numbers relate

Exposure and scale. Views are rendered in linear Rec.709 radiance for a point light of
intensity ``light_intensity`` at each camera center. DNG photos go through
:class:`recon.synth.sensor.SensorModel`; the base exposure is chosen so that the capture's
median exposure H equals the sensor's ``saturation_exposure``, which makes the sensor's
``linear_scale`` exactly 1: a correct linearization returns the renders themselves
(``gt/linear``), and ``light_intensity`` stays the right I_e for them. ``exposure_variation``
(stops) varies shutter time (and ISO) per view around that median: the views are written with
offsets 0, +v, 0, -v, ... so the median stays at offset 0. EXR photos are the renders (plus noise
when ``noise``), PNG photos their sRGB encoding (clipped to [0, 1]).

Scenes. ``scene="void"`` (the default): the object alone in a black void, cameras on a
Fibonacci sphere around it (some from below). ``scene="tabletop"``: the object stands on a
textured table lit by the same flash, cameras on hand-held rings 15-60 degrees above the table,
and the capture also holds ``gt/masks/<stem>.png`` (the object's true silhouettes) and
``gt/plane.json`` (the table, :mod:`recon.support`); see :mod:`recon.synth.tabletop`.
``scene="tabletop_void"``: the tabletop scene's object (base cut flat) and cameras without the
table or the backdrop: the same capture in the void, the peer benchmarks compare a tabletop
capture with (``gt/plane.json`` says where the table would be). ``scene="stand"``: no table, the
object on a thin pole with a round white base in a dim room (cameras as in the tabletop scene);
``gt/masks`` hold the object alone, ``gt/masks_with_stand`` the object with its stand.
Variations that make masks hard (object colours like the table's, no texture, a wall, room
lamps, views cut by the frame) are settings of their own, off by default (the ``variations``
section of :class:`recon.synth.settings.SynthSettings`).

Everything is a function of the settings: the same settings give bit-identical files (except
for DNG metadata a library may stamp; pidng stamps none).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
from pathlib import Path

import numpy as np

from recon.brdf import R_MIN
from recon.io.atomic import atomic_dir, atomic_path
from recon.io.cameras import Camera, CameraSet, intrinsics, look_at, save_cameras
from recon.io.dng import FULL_FRAME_DIAGONAL_MM
from recon.io.images import linear_to_srgb, write_exr, write_mask, write_png
from recon.io.mesh import write_obj
from recon.synth.bake import bake, unwrap
from recon.synth.materials import MaterialFields
from recon.support import SupportPlane, save_plane
from recon.synth.shapes import FLAT_BASE, flatten_base, make_object
from recon.render.mitsuba_bsdf import render_reference
from recon.synth import imaging as phone
from recon.synth.sensor import SensorModel, exposure_value
from recon.synth.settings import (EXTENT_RADIUS, FORMATS, PHONE_FIELDS, PRESETS, RECORDED_ORDER, SCENES,
                                  TABLETOP_FIELDS, VARIATION_FIELDS, SynthError, SynthSettings,
                                  recorded_settings)
from recon.synth.tabletop import (TabletopScene, add_marker_mat, closeup_cameras, room_lamps, stand_meshes,
                                  table_texture, tabletop_cameras, wall_mesh)

__all__ = ["EXTENT_RADIUS", "FORMATS", "PHONE_FIELDS", "PRESETS", "RECORDED_ORDER", "SCENES", "TABLETOP_FIELDS",
           "VARIATION_FIELDS", "SynthError", "SynthSettings", "make_cameras", "make_capture", "recorded_settings",
           "view_exposures"]  # the settings live in recon.synth.settings; these names stay importable here

log = logging.getLogger(__name__)

_EXT = {"dng": ".dng", "exr": ".exr", "png16": ".png", "png8": ".png", "jpg": ".jpg"}


# ---- cameras ----
def fibonacci_directions(n: int, z_range=(-0.35, 0.92)) -> np.ndarray:
    """``(n, 3)`` unit vectors spread evenly (Fibonacci lattice) over the band z0 <= z <= z1."""
    z0, z1 = z_range
    k = np.arange(n)
    z = z1 - (k + 0.5) / n * (z1 - z0)
    phi = k * np.pi * (3.0 - 5.0**0.5)
    s = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    return np.stack([s * np.cos(phi), s * np.sin(phi), z], -1)


def make_cameras(settings: SynthSettings) -> CameraSet:
    """N cameras on a sphere of radius ``distance`` looking at the origin, +z up in the image."""
    ext = _EXT[settings.photos.format]
    K = intrinsics(settings.cameras.width, settings.cameras.height, settings.cameras.fov)
    frames = []
    for i, d in enumerate(fibonacci_directions(settings.cameras.n_views, settings.cameras.view_z_range)):
        eye = settings.cameras.distance * settings.scale * d
        frames.append(Camera(f"images/{i:04d}{ext}", settings.cameras.width, settings.cameras.height, K.copy(),
                             look_at(eye, [0.0, 0.0, 0.0], up=(0.0, 0.0, 1.0))))
    return CameraSet(tuple(frames), float(settings.photos.light_intensity * settings.scale**2))


# ---- exposures ----
def view_exposures(settings: SynthSettings, sensor) -> list[dict]:
    """Per-view ``exposure_time``, ``iso``, ``f_number`` and offset (stops).

    Offsets cycle 0, +v, 0, -v so that the median exposure is the base one, which equals the
    sensor's ``saturation_exposure`` (linear scale 1). Every third view trades shutter time
    for ISO 200 (same exposure), to exercise ISO normalization.
    """
    f_number = 2.0
    out = []
    for i in range(settings.cameras.n_views):
        stops = settings.photos.exposure_variation * (0.0, 1.0, 0.0, -1.0)[i % 4]
        iso = 200.0 if i % 3 == 2 else 100.0
        # H = t * iso/100 / N^2 = saturation_exposure * 2^stops
        t = sensor.saturation_exposure * 2.0**stops * f_number**2 / (iso / 100.0)
        out.append({"exposure_time": t, "iso": iso, "f_number": f_number, "stops": stops})
    return out


def _add_noise(rgb: np.ndarray, sensor, rng: np.random.Generator) -> np.ndarray:
    """Shot + read noise of ``sensor`` at its base exposure, in linear scene units."""
    full = sensor.full_well_electrons
    read = sensor.read_noise / (sensor.white_level - sensor.black_level)
    sigma = np.sqrt(np.maximum(rgb, 0.0) / full + read**2)
    return (rgb + rng.normal(size=rgb.shape) * sigma).astype(np.float32)


# ---- the capture ----
def make_capture(out_dir: str | os.PathLike, settings: SynthSettings,
                 command: str | None = None) -> Path:
    """Write a synthetic capture folder at ``out_dir`` (replaced atomically); return its path.

    ``command`` (the command line that regenerates it) is recorded in gt/README.md and
    gt/synth.json.
    """

    out_dir = Path(out_dir)
    s = settings
    tabletop = s.scene in ("tabletop", "tabletop_void")
    sensor = SensorModel()
    log.info("synth: %s object, level %d, %s scene", s.object, s.mesh_level, s.scene)
    mesh = make_object(s.object, s.mesh_level, s.seed)
    if tabletop and s.object not in FLAT_BASE:  # the mug (and the turned shapes) stand on their own flat base
        mesh = flatten_base(mesh, s.tabletop.base_cut)
    mesh = unwrap(mesh, resolution=s.material.texture_size, padding=3)
    fields = MaterialFields(seed=s.seed, frequency=s.material.texture_frequency, albedo=s.material.albedo,
                            specular=s.material.specular, roughness=s.material.roughness, palette=s.variations.palette,
                            pattern=s.variations.texture_pattern)
    (diffuse, specular, roughness), _ = bake(mesh, fields.evaluate, s.material.texture_size, pad=4)
    if s.scale != 1.0:  # the fields were evaluated at unit scale
        mesh = dataclasses.replace(mesh, v_pos=mesh.v_pos * s.scale)
    roughness = np.clip(roughness, R_MIN, 1.0)
    textures = {"diffuse": diffuse, "specular": specular, "roughness": roughness}
    scene, marker, gt_plane, with_stand = None, None, None, None
    if s.scene == "tabletop_void":  # the tabletop object and cameras, rendered alone
        lo, hi = mesh.bbox()
        gt_plane = SupportPlane(np.array([0.0, 0.0, 1.0]), -float(lo[2]))
        cams = tabletop_cameras(s, target=0.5 * (lo + hi) / s.scale)
    elif tabletop:
        log.info("synth: table texture %d^2 (%s)", s.tabletop.table_texture_size, s.tabletop.table)
        table_rgb = table_texture(s.tabletop.table_texture_size, s.tabletop.table_half_size, s.seed,
                                  s.tabletop.table)
        if s.tabletop.marker_square > 0:
            marker = add_marker_mat(table_rgb, s.tabletop.table_half_size, s.tabletop.marker_square)
            marker = {**marker, "square": marker["square"] * s.scale, "marker": marker["marker"] * s.scale,
                      "top_left": [v * s.scale for v in marker["top_left"]],
                      "size": [v * s.scale for v in marker["size"]]}
        lo, hi = mesh.bbox()
        scene = TabletopScene(mesh, textures, float(lo[2]), s.tabletop.table_half_size * s.scale, table_rgb,
                              s.tabletop.background, s.tabletop.background_distance * s.scale,
                              *_room(s, mesh, float(lo[2]), ()))
        gt_plane = scene.plane
        cams = closeup_cameras(tabletop_cameras(s, target=0.5 * (lo + hi) / s.scale), s, 0.5 * (lo + hi) / s.scale)
    elif s.scene == "stand":  # no table: the object on a pole with a round base, in a dim room
        lo, hi = mesh.bbox()
        pole, base = stand_meshes(float(lo[2]), s.variations.stand_height, s.scale)
        stand = (("pole", pole, {"diffuse": np.array([0.12, 0.08, 0.05]), "specular": 0.04, "roughness": 0.5}),
                 ("base", base, {"diffuse": np.full(3, s.variations.stand_base), "specular": 0.04, "roughness": 0.4}))
        z_floor = float(base.v_pos[:, 2].min())
        scene = TabletopScene(mesh, textures, z_floor, 1.0, None, s.tabletop.background, s.tabletop.background_distance * s.scale,
                              *_room(s, mesh, z_floor, stand))
        with_stand = _merge([mesh, pole, base])
        cams = closeup_cameras(tabletop_cameras(s, target=0.5 * (lo + hi) / s.scale), s, 0.5 * (lo + hi) / s.scale)
    else:
        cams = make_cameras(s)
    exposures = view_exposures(s, sensor)
    h_values = [exposure_value(e["exposure_time"], e["iso"], e["f_number"]) for e in exposures]
    h_ref = float(np.median(h_values))
    linear_scale = sensor.linear_scale(h_ref)
    # focal length in mm for the DNG tags: f_px * pixel pitch
    focal_mm = float(cams.frames[0].K[0, 0] * sensor.pixel_pitch_um * 1e-3)
    # 35-mm equivalent: the same diagonal field of view on a 36 x 24 mm frame (the convention
    # of phones, of the DNG writer and of linearize's reader; by the width, a 4:3 photo's tag
    # was 4 % long: 49 mm, read back as 271.8 px for 263.8 px)
    focal_35mm = float(cams.frames[0].K[0, 0] * FULL_FRAME_DIAGONAL_MM / math.hypot(s.cameras.width, s.cameras.height))
    noise_rng = s.rng("noise")
    views_im = phone.view_imaging(s, len(cams))
    offset = np.asarray(s.phone.flash_offset) * s.scale
    l_amb = phone.ambient_radiance(s.phone.ambient, cams.light_intensity, s.cameras.distance * s.scale)
    falloff = phone.falloff_map(s.cameras.width, s.cameras.height, *s.phone.falloff) if any(s.phone.falloff) else None
    gainmap = phone.falloff_gainmap(s.cameras.width, s.cameras.height, *s.phone.falloff) if s.phone.falloff_gainmap else None

    with atomic_dir(out_dir) as tmp:
        (tmp / "images").mkdir()
        (tmp / "gt").mkdir()
        for i, cam in enumerate(cams.frames):
            log.info("synth: view %d/%d", i + 1, len(cams))
            light_pos = phone.light_position(cam, offset) if np.any(offset) else None
            if scene is not None:
                rgb = scene.render(cam, cams.light_intensity, s.photos.spp, seed=s.view_seed(i),
                                   light_position=light_pos, ambient=l_amb)
                coverage = scene.object_coverage(cam, s.photos.spp, seed=s.view_seed(i))
                write_mask(tmp / "gt" / "masks" / f"{cam.stem}.png", coverage > 0.5)
                if with_stand is not None:
                    cov = scene.object_coverage(cam, s.photos.spp, seed=s.view_seed(i), mesh=with_stand)
                    write_mask(tmp / "gt" / "masks_with_stand" / f"{cam.stem}.png", cov > 0.5)
            else:
                rgba = render_reference(mesh, textures, cam, cams.light_intensity, s.photos.spp,
                                        seed=s.view_seed(i), alpha=True, light_position=light_pos,
                                        ambient=l_amb)
                rgb, coverage = np.ascontiguousarray(rgba[:, :, :3]), rgba[:, :, 3]
                if gt_plane is not None:  # tabletop_void: the same files as its tabletop peer
                    write_mask(tmp / "gt" / "masks" / f"{cam.stem}.png", coverage > 0.5)
            path = tmp / cam.image
            gt_rgb = rgb  # the scene's radiance, before the phone's imaging (gt/linear)
            if s.phone_effects:
                rgb = views_im[i].apply(rgb, falloff)
            if s.photos.format == "dng":
                from recon.io.dng import write_dng

                e = exposures[i]
                cfa = sensor.capture(rgb, e["exposure_time"], e["iso"], e["f_number"],
                                     rng=noise_rng, noise=s.photos.noise)
                write_dng(path, cfa, sensor, e["exposure_time"], e["iso"], e["f_number"],
                          focal_length_mm=focal_mm,
                          opcode_list3=[gainmap.to_opcode()] if s.phone.falloff_gainmap else None)
            else:
                photo = _add_noise(rgb, sensor, noise_rng) if s.photos.noise else rgb
                if s.photos.format == "jpg":
                    e = exposures[i]
                    # the recorded exposure: linearize divides 2**stops back out
                    y = photo * np.float32(2.0 ** e["stops"])
                    phone.write_jpeg_exif(path, phone.tone_encode(y, s.phone.tone_curve, s.phone.tone_contrast),
                                          e["exposure_time"], e["iso"], e["f_number"], focal_mm,
                                          focal_35mm, quality=s.phone.jpeg_quality)
                elif s.photos.format == "exr":
                    write_exr(path, photo)
                else:
                    write_png(path, linear_to_srgb(photo), bits=16 if s.photos.format == "png16" else 8)
            if s.outputs.write_masks:
                write_mask(tmp / "masks" / f"{cam.stem}.png", coverage > 0.5)
            if s.outputs.write_gt_linear:
                write_exr(tmp / "gt" / "linear" / f"{cam.stem}.exr", gt_rgb * np.float32(linear_scale))
        # the light intensity that fits the linearized images (scale 1 by construction)
        gt_cams = CameraSet(cams.frames, float(cams.light_intensity * linear_scale))
        save_cameras(tmp / "gt" / "cameras.json", gt_cams)
        if s.outputs.write_cameras:
            save_cameras(tmp / "cameras.json", dataclasses.replace(gt_cams, light_known=bool(s.outputs.state_light)))
        if s.outputs.state_light:
            with atomic_path(tmp / "capture.yaml") as p:
                p.write_text(f"light_intensity: {gt_cams.light_intensity!r}\n")
        write_obj(tmp / "gt" / "mesh.obj", mesh)
        write_exr(tmp / "gt" / "diffuse.exr", diffuse)
        write_exr(tmp / "gt" / "specular.exr", specular)
        write_exr(tmp / "gt" / "roughness.exr", roughness)
        if s.phone_effects:
            phone.save_imaging(tmp / "gt" / "imaging.json", phone.imaging_record(
                s, cams, views_im, exposures, gt_cams.light_intensity, l_amb * linear_scale))
        if gt_plane is not None:
            save_plane(tmp / "gt" / "plane.json", gt_plane, table_half_size=s.tabletop.table_half_size * s.scale,
                       marker_mat=marker, table=scene is not None)
        meta = {
            "generator": "recon.synth.capture.make_capture",
            "command": command,
            "settings": recorded_settings(s),
            "linear_scale": linear_scale,
            "exposure_reference": h_ref,
            "sensor": dataclasses.asdict(sensor) if s.photos.format == "dng" else None,
            "views": [{"image": c.image, **e} for c, e in zip(cams.frames, exposures, strict=True)],
            "mesh": {"vertices": int(len(mesh.v_pos)), "faces": int(len(mesh.t_pos_idx)),
                     "area": mesh.area(), "volume": mesh.volume()},
        }
        with atomic_path(tmp / "gt" / "synth.json") as p:
            p.write_text(json.dumps(meta, indent=1))
        with atomic_path(tmp / "gt" / "README.md") as p:
            p.write_text(_readme(s, linear_scale, command))
    return out_dir


def _room(s: SynthSettings, mesh, z_floor: float, props: tuple) -> tuple[tuple, tuple]:
    """``(props, lamps)`` of :class:`recon.synth.tabletop.TabletopScene` for the variations of
    ``s``: ``props`` plus a wall (``s.variations.wall``), and the room lamps (``s.variations.lamps``)."""
    lo, hi = mesh.bbox()
    center = 0.5 * (lo + hi)
    d = s.cameras.distance * s.scale
    props = tuple(props)
    if s.variations.wall > 0:
        dist = s.variations.wall_distance * d
        props += (("wall", wall_mesh(center, dist, z_floor, 3.0 * dist, 2.5 * dist),
                   {"diffuse": np.full(3, s.variations.wall), "specular": 0.0, "roughness": 1.0}),)
    lamps = tuple(room_lamps(center, d, s.variations.lamps, s.photos.light_intensity * s.scale**2)) if s.variations.lamps > 0 else ()
    return props, lamps


def _merge(meshes):
    """One :class:`recon.io.mesh.Mesh` (positions and faces only) of several."""
    from recon.io.mesh import Mesh

    v, f, n = [], [], 0
    for m in meshes:
        v.append(m.v_pos)
        f.append(m.t_pos_idx + n)
        n += len(m.v_pos)
    return Mesh(np.concatenate(v), np.concatenate(f))


def _readme(s: SynthSettings, linear_scale: float, command: str | None) -> str:
    regen = f"\nRegenerate (bit-identical on the same machine): `{command}`\n" if command else ""
    tabletop = "" if s.scene == "void" else """
Tabletop scene: the object stands on a textured table (and in front of a dim backdrop) that
are in every photo; everything in gt/ describes the object alone:
- `masks/<stem>.png`: the object's true silhouettes (pixel coverage of the object > 0.5).
- `plane.json`: the table, `normal . x + offset = 0` (normal up, towards the cameras), in the
  frame of `cameras.json`; `marker_mat` describes the printed ChArUco mat when there is one.
"""
    return f"""# Ground truth of a synthetic capture (never read by the pipeline)

Made by `recon.synth.capture.make_capture` (settings in `synth.json`), object `{s.object}`.
{regen}{tabletop}
- `mesh.obj`: the true mesh in the frame of `gt/cameras.json`, with its UV atlas (OBJ, v up).
- `diffuse.exr` (RGB), `specular.exr` (1 channel), `roughness.exr` (1 channel): the true maps,
  linear float32, texel (i, j) at u = (j + 0.5)/W, v = 1 - (i + 0.5)/H (DESIGN section 2).
- `cameras.json`: the true cameras; `light.intensity` is I_e for the linearized images.
- `linear/<stem>.exr` (if present): the noise-free linear renders BEFORE the sensor, at the
  exposure a correct linearization recovers: linearized = linear/<stem>.exr, i.e.
  linearized = render * linear_scale with linear_scale = {linear_scale!r} (see `synth.json`).
  Pixels brighter than 1 clip in the RAW files (`.sat.png` in the pipeline).
"""
