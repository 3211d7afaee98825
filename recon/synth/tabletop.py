"""Tabletop scenes: the object standing on a large textured table, photographed by hand.

What a person does (DESIGN section 7): puts the object on a table, walks around it with the
phone 15-60 degrees above the table, the flash lighting the table around the object about as
brightly as the object itself. The base is never seen. This module makes that scene for
:func:`recon.synth.capture.make_capture` (``scene="tabletop"``):

- The object (:mod:`recon.synth.shapes`, cut flat at the bottom by ``base_cut`` so it stands)
  rests on the plane z = z_table (its lowest point); the ground truth (``gt/mesh.obj`` and the
  maps) is the object alone, and ``gt/plane.json`` (:mod:`recon.support`) records the plane.
- The table: a square of side ``2 * table_half_size`` with a procedural wood texture
  (:func:`table_texture`: grain, rings, blotches and knots, features at several scales for
  SfM), rendered with the same BSDF plugin as the object (``recon_svbrdf``, a little varnish:
  a_s = 0.04, r = 0.45), lit by the same flash. Optionally a printed ChArUco mat
  (``marker_mat``: OpenCV's 5 x 7 board, DICT_4X4_50) lies flat under the object.
- Beyond the table, optionally a dim far backdrop (``background`` albedo, a sphere of radius
  ``background_distance`` around the object, lit by the flash: about (distance /
  background_distance)^2 as bright as the object).
- Cameras (:func:`tabletop_cameras`) on ``rings`` hand-held rings: elevations spread over
  ``elevation_range`` (degrees above the table, seen from the object's center), per ring a
  distance around ``distance``, azimuths evenly spread with jitter, each view aimed near the
  object's center (``aim_jitter``) with a little roll (``roll_jitter`` degrees). None from below.
- ``gt/masks/<stem>.png``: the object's own silhouette (pixel coverage > 0.5 of the object
  rendered alone; nothing ever stands in front of it).

Variations (each off by default, see :class:`recon.synth.capture.SynthSettings`): a wall behind
the object (:func:`wall_mesh`), two room lamps fixed in the room (:func:`room_lamps`), views
taken closer so that the frame cuts the object (:func:`closeup_cameras`), and ``scene="stand"``:
no table, the object on a thin pole with a round white base (:func:`stand_meshes`) in a dim
room, like a skull on a display stand.
"""

from __future__ import annotations

import numpy as np

from recon.io.cameras import Camera, CameraSet, intrinsics, look_at
from recon.io.mesh import Mesh
from recon.support import SupportPlane
from recon.synth.noise import dots, fbm
from recon.render.mitsuba_bsdf import ambient_scene_dict, bsdf_dict, clip_range, mitsuba_mesh, register, scene_dict
from recon.render.mitsuba_bsdf import render_reference

TABLE_SPECULAR = 0.04
TABLE_ROUGHNESS = 0.45
MARKER_BOARD = {"squares": (5, 7), "dictionary": "DICT_4X4_50", "marker_fraction": 0.75}
"""The ChArUco mat: squares (x, y), the ArUco dictionary, marker side / square side."""


# ---- the table ----
def table_mesh(z_table: float, half_size: float) -> Mesh:
    """Two triangles at z = ``z_table`` covering [-half, half]^2, facing +z, with UVs.

    u runs with x, v with y (OBJ convention): texel row 0 of the table texture is at y = +half.
    """
    h = float(half_size)
    v = np.array([[-h, -h, z_table], [h, -h, z_table], [h, h, z_table], [-h, h, z_table]])
    f = np.array([[0, 1, 2], [0, 2, 3]])
    uv = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    return Mesh(v, f, uv, f.copy())


def table_texture(size: int, half_size: float, seed: int = 0, kind: str = "wood") -> np.ndarray:
    """``(size, size, 3)`` float32 linear diffuse albedo of a table top.

    Texel (i, j) is the table point x = -half + (j + 0.5) * 2 half / size, y = half - (i + 0.5) *
    2 half / size (see :func:`table_mesh`). ``kind="wood"``: long grain along x (stretched fractal
    noise), growth rings warped by low-frequency noise, blotches (a few tenths of a unit,
    SIFT-sized at typical distances) and small dark knots and marks. ``kind="plain"``: a light warm
    grey laminate (albedo about 0.55) whose mottling varies by +-2 %: a plain desk, with almost no
    texture for SIFT or the plane sweep.
    """
    step = 2.0 * half_size / size
    c = -half_size + (np.arange(size) + 0.5) * step
    x, y = np.meshgrid(c, c[::-1])
    p = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1)
    if kind == "plain":
        mottle = 0.02 * fbm(p, 1.5, octaves=4, seed=seed + 25)
        rgb = np.array([0.58, 0.55, 0.50]) * (1.0 + mottle[:, None])
        return rgb.reshape(size, size, 3).astype(np.float32)
    if kind != "wood":
        raise ValueError(f"table kind {kind!r}: use 'wood' or 'plain'")
    warp = fbm(p * np.array([0.15, 0.6, 0.0]), 1.0, octaves=3, seed=seed + 21)
    rings = 0.5 + 0.5 * np.sin(2 * np.pi * (3.0 * p[:, 1] + 1.6 * warp))
    rings = rings**3
    grain = fbm(p * np.array([0.35, 9.0, 0.0]), 1.0, octaves=3, seed=seed + 22)
    blotch = fbm(p, 2.2, octaves=4, seed=seed + 23)
    inside, level = dots(p, 0.22, seed=seed + 24, radius=(0.12, 0.3))
    t = 0.55 + 0.22 * rings + 0.22 * grain + 0.35 * blotch
    t = np.where(inside, t - 0.25 - 0.35 * level, t)
    t = np.clip(t, 0.0, 1.0)[:, None]
    light = np.array([0.56, 0.38, 0.21])
    dark = np.array([0.20, 0.11, 0.05])
    rgb = dark + (light - dark) * t
    return rgb.reshape(size, size, 3).astype(np.float32)


def add_marker_mat(texture: np.ndarray, half_size: float, square: float) -> dict:
    """Print OpenCV's ChArUco board (:data:`MARKER_BOARD`) into ``texture`` in place, centered
    on the table under the object; return its description (square size in world units, the
    board's corner positions). White paper is 0.8, black ink 0.04 (linear albedo)."""
    import cv2

    sx, sy = MARKER_BOARD["squares"]
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, MARKER_BOARD["dictionary"]))
    board = cv2.aruco.CharucoBoard((sx, sy), square, square * MARKER_BOARD["marker_fraction"], dictionary)
    size = texture.shape[0]
    per_unit = size / (2.0 * half_size)
    w_px, h_px = int(round(sx * square * per_unit)), int(round(sy * square * per_unit))
    margin = int(round(0.4 * square * per_unit))
    if w_px + 2 * margin >= size or h_px + 2 * margin >= size:
        raise ValueError(f"the marker mat ({sx * square:.2f} x {sy * square:.2f}) does not fit on the table")
    img = board.generateImage((w_px, h_px), marginSize=0, borderBits=1).astype(np.float32) / 255.0
    paper = 0.04 + (0.8 - 0.04) * img
    i0 = size // 2 - h_px // 2
    j0 = size // 2 - w_px // 2
    texture[i0 - margin:i0 + h_px + margin, j0 - margin:j0 + w_px + margin] = 0.8
    texture[i0:i0 + h_px, j0:j0 + w_px] = paper[:, :, None]
    x0 = -half_size + j0 / per_unit
    y0 = half_size - i0 / per_unit
    return {"board": {**MARKER_BOARD, "squares": [sx, sy]}, "square": float(square),
            "marker": float(square * MARKER_BOARD["marker_fraction"]),
            "top_left": [float(x0), float(y0)], "size": [w_px / per_unit, h_px / per_unit],
            "note": "board image row 0 lies along +y (top_left = board corner at image pixel (0, 0)); "
                    "x grows with the image column, y falls with the image row"}


# ---- cameras ----
def tabletop_cameras(settings, target=(0.0, 0.0, 0.0)) -> CameraSet:
    """Hand-held rings above the table (see the module docstring); ``settings`` a SynthSettings."""
    s = settings
    rng = s.rng("tabletop_cameras")
    ext = {"dng": ".dng", "exr": ".exr", "png16": ".png", "png8": ".png", "jpg": ".jpg"}[s.photos.format]
    K = intrinsics(s.cameras.width, s.cameras.height, s.cameras.fov)
    lo, hi = s.tabletop.elevation_range
    n_rings = max(1, min(s.tabletop.rings, s.cameras.n_views))
    # rings from low to high, a margin inside the range for the jitter
    pad = min(4.0, 0.15 * (hi - lo))
    elevs = np.linspace(lo + pad, hi - pad, n_rings) if n_rings > 1 else np.array([0.5 * (lo + hi)])
    # more views on the longer low rings (circumference ~ cos(elevation))
    weight = np.cos(np.radians(elevs))
    counts = np.floor(s.cameras.n_views * weight / weight.sum()).astype(int)
    for k in np.argsort(-weight)[: s.cameras.n_views - counts.sum()]:
        counts[k] += 1
    # people stand farther back for low views, closer for views from above
    ring_dist = s.cameras.distance * np.linspace(1.08, 0.92, n_rings) if n_rings > 1 else np.array([s.cameras.distance])
    target = np.asarray(target, dtype=np.float64)
    frames = []
    for r in range(n_rings):
        m = int(counts[r])
        phase = rng.uniform(0, 2 * np.pi)
        for k in range(m):
            az = phase + 2 * np.pi * (k + rng.uniform(-0.2, 0.2)) / m
            el = np.radians(np.clip(elevs[r] + rng.uniform(-pad, pad), lo, hi))
            dist = ring_dist[r] * (1.0 + rng.uniform(-1, 1) * s.tabletop.distance_jitter)
            d = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
            eye = target + dist * d
            aim = target + rng.normal(0.0, s.tabletop.aim_jitter, 3) * np.array([1.0, 1.0, 0.5])
            W = look_at(eye * s.scale, aim * s.scale, up=(0.0, 0.0, 1.0))
            roll = np.radians(rng.normal(0.0, s.tabletop.roll_jitter))
            Rz = np.array([[np.cos(roll), -np.sin(roll), 0], [np.sin(roll), np.cos(roll), 0], [0, 0, 1.0]])
            W[:3, :] = Rz @ W[:3, :]
            frames.append(Camera(f"images/{len(frames):04d}{ext}", s.cameras.width, s.cameras.height, K.copy(), W))
    return CameraSet(tuple(frames), float(s.photos.light_intensity * s.scale**2))


def closeup_cameras(cams: CameraSet, settings, target) -> CameraSet:
    """``cams`` with a share ``settings.variations.closeups`` of the views (chosen by a seeded draw) moved
    along their optical axis to ``closeup_distance`` of their distance from ``target`` (their
    aim and roll kept): the frame cuts the object there."""
    s = settings
    n = len(cams)
    k = int(round(s.variations.closeups * n))
    if k == 0:
        return cams
    rng = s.rng("closeups")
    chosen = set(rng.choice(n, size=k, replace=False).tolist())
    target = np.asarray(target, dtype=np.float64) * s.scale
    frames = []
    for i, cam in enumerate(cams.frames):
        if i in chosen:
            c = cam.center
            axis = cam.camera_to_world[:3, 2]
            along = float((target - c) @ axis)
            W = cam.world_to_camera.copy()
            new_c = c + (1.0 - s.variations.closeup_distance) * along * axis
            W[:3, 3] = -W[:3, :3] @ new_c
            cam = Camera(cam.image, cam.width, cam.height, cam.K.copy(), W)
        frames.append(cam)
    return CameraSet(tuple(frames), cams.light_intensity)


def wall_mesh(center, distance: float, z_floor: float, half_width: float, height: float) -> Mesh:
    """A vertical rectangle ``distance`` from ``center`` on the -y side, facing +y, from
    ``z_floor`` up ``height``, ``half_width`` either side (two triangles)."""
    cx, cy = float(center[0]), float(center[1])
    y = cy - distance
    v = np.array([[cx - half_width, y, z_floor], [cx + half_width, y, z_floor],
                  [cx + half_width, y, z_floor + height], [cx - half_width, y, z_floor + height]])
    return Mesh(v, np.array([[0, 2, 1], [0, 3, 2]]))


def room_lamps(center, distance: float, irradiance_fraction: float, flash_intensity: float) -> list:
    """Two lamps ``[(position (3,), intensity), ...]`` fixed in the room, above and to the sides of
    ``center``, giving together ``irradiance_fraction`` of the flash's irradiance at the object
    (a flash of ``flash_intensity`` at ``distance``)."""
    c = np.asarray(center, dtype=np.float64)
    out = []
    for offset in (np.array([1.3, 0.7, 1.5]), np.array([-1.1, 1.2, 1.1])):
        pos = c + distance * offset
        r2 = float(((pos - c) ** 2).sum())
        out.append((pos, 0.5 * irradiance_fraction * flash_intensity * r2 / distance**2))
    return out


def cylinder_mesh(radius: float, z0: float, z1: float, segments: int = 48) -> Mesh:
    """A closed cylinder around the z axis from ``z0`` to ``z1`` (caps fanned from their centres)."""
    t = 2 * np.pi * np.arange(segments) / segments
    ring = np.stack([radius * np.cos(t), radius * np.sin(t)], 1)
    v = np.concatenate([np.c_[ring, np.full(segments, z0)], np.c_[ring, np.full(segments, z1)],
                        [[0.0, 0.0, z0], [0.0, 0.0, z1]]])
    a = np.arange(segments)
    b = (a + 1) % segments
    bottom, top = 2 * segments, 2 * segments + 1
    f = np.concatenate([np.stack([a, b, b + segments], 1), np.stack([a, b + segments, a + segments], 1),
                        np.stack([np.full(segments, bottom), b, a], 1),
                        np.stack([np.full(segments, top), a + segments, b + segments], 1)])
    return Mesh(v, f)


def stand_meshes(z_bottom: float, height: float, scale: float = 1.0) -> tuple[Mesh, Mesh]:
    """The pole (radius 0.05, from ``height`` below ``z_bottom`` to 0.15 into the object) and its
    round base (radius 0.6, 0.06 thick) of the stand scene, in object units times ``scale``."""
    pole = cylinder_mesh(0.05 * scale, z_bottom - height * scale, z_bottom + 0.15 * scale)
    base = cylinder_mesh(0.6 * scale, z_bottom - (height + 0.06) * scale, z_bottom - height * scale, 96)
    return pole, base


# ---- rendering ----
class TabletopScene:
    """The object, the table and the backdrop, ready to render views (one Mitsuba scene per view)."""

    def __init__(self, mesh: Mesh, textures: dict, plane_z: float, half_size: float,
                 table_diffuse: np.ndarray | None, background: float, background_distance: float,
                 props: tuple = (), lamps: tuple = ()):
        """``table_diffuse`` None: no table (the stand scene); ``props``: more ``(name, mesh,
        textures)`` in the room (a wall, a stand); ``lamps``: ``(position, intensity)`` point
        lights fixed in the room, rendered in passes of their own and added."""
        self.mesh = mesh
        self.textures = textures
        self.plane_z = float(plane_z)
        self.table = table_mesh(plane_z, half_size) if table_diffuse is not None else None
        self.table_textures = {"diffuse": table_diffuse, "specular": TABLE_SPECULAR,
                               "roughness": TABLE_ROUGHNESS}
        self.props = tuple(props)
        self.lamps = tuple(lamps)
        self.background = float(background)
        self.background_distance = float(background_distance)
        lo, hi = mesh.bbox()
        self.center = 0.5 * (lo + hi)

    @property
    def plane(self) -> SupportPlane:
        return SupportPlane(np.array([0.0, 0.0, 1.0]), -self.plane_z)

    def render(self, cam: Camera, light_intensity: float, spp: int, seed: int, light_position=None,
               ambient: float = 0.0) -> np.ndarray:
        """(H, W, 3) float32 linear radiance of the whole scene for ``cam`` (flash at
        ``light_position``, default the camera centre; ``ambient``: a room of that radiance, the
        backdrop glowing with it where there is one, else a constant environment)."""

        mi = register()
        d = scene_dict(self.mesh, self.textures, cam, light_intensity, spp, light_position=light_position)
        corners = [self.mesh.v_pos]
        if self.table is not None:
            d["table"] = mitsuba_mesh(self.table, "table", bsdf=mi.load_dict(bsdf_dict(self.table_textures)))
            corners.append(self.table.v_pos)
        for name, prop, tex in self.props:
            d[name] = mitsuba_mesh(prop, name, bsdf=mi.load_dict(bsdf_dict(tex)))
            corners.append(prop.v_pos)
        if self.background > 0:
            r = self.background_distance
            d["background"] = {"type": "sphere", "center": self.center.tolist(), "radius": r,
                               "flip_normals": True,
                               "bsdf": bsdf_dict({"diffuse": np.full(3, self.background), "specular": 0.0,
                                                  "roughness": 1.0})}
            corners.append(self.center + r * np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1)
                                                       for sz in (-1, 1)]))
        d["sensor"].update(clip_range(cam, np.concatenate(corners)))
        scene = mi.load_dict(d)
        img = np.array(mi.render(scene, seed=int(seed), spp=int(spp)), dtype=np.float32)[:, :, :3]
        if ambient > 0:
            da = ambient_scene_dict(d, ambient)
            if "background" in da:  # the closed backdrop would hide the environment: it is the room's light
                da["background"] = {**da["background"],
                                    "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [float(ambient)] * 3}}}
            amb = mi.render(mi.load_dict(da), seed=int(seed) + 1, spp=int(spp))
            img += np.array(amb, dtype=np.float32)[:, :, :3]
        for k, (position, intensity) in enumerate(self.lamps):
            dl = {**d, "light": {"type": "point", "position": np.asarray(position, float).tolist(),
                                 "intensity": {"type": "rgb", "value": [float(intensity)] * 3}}}
            lamp = mi.render(mi.load_dict(dl), seed=int(seed) + 2 + k, spp=int(spp))
            img += np.array(lamp, dtype=np.float32)[:, :, :3]
        return img

    def object_coverage(self, cam: Camera, spp: int, seed: int, mesh: Mesh | None = None) -> np.ndarray:
        """(H, W) float32 fraction of each pixel's footprint on the object alone (or on ``mesh``)."""

        if mesh is None:
            rgba = render_reference(self.mesh, self.textures, cam, 1.0, spp, seed=seed, alpha=True)
        else:
            rgba = render_reference(mesh, {"diffuse": np.full(3, 0.5), "specular": 0.0, "roughness": 1.0}, cam,
                                    1.0, spp, seed=seed, alpha=True)
        return rgba[:, :, 3]
