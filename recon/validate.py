"""The whole capture checked before its first stage runs (DESIGN section 1; issue 20).

:func:`validate_capture` reads everything a capture brings and that can be checked without
running a stage, and reports every problem at once, each naming the file and the fix:

- ``capture.yaml``: its keys and every stage's section, built into that stage's frozen
  settings dataclass (:func:`recon.config.build_settings`: unknown keys, a string for a
  number, a negative count, the dataclass's own range checks); ``light_intensity``.
- ``images/``: the photos (:func:`recon.linearize.stage.list_images`: unknown types,
  duplicate stems, an empty folder; hidden files such as macOS ``._*`` AppleDouble files are
  ignored with a note) and their metadata (:func:`recon.linearize.metadata.read_meta`:
  corrupt or truncated RAW files); at least :data:`MIN_VIEWS` views; photos that are black
  (no light) or white (clipped) (:func:`photo_levels`, on a reduced decode); photos whose
  EXIF says the flash did not fire (:func:`_check_flash`).
- ``cameras.json``: the contract (:func:`recon.io.cameras.load_cameras`), every frame names a
  photo that exists, with the photo's size; photos without a camera are named and dropped (a
  warning); at least :data:`MIN_VIEWS` views with a camera; its light intensity agrees with
  ``capture.yaml``'s.
- ``masks/``: each mask is readable, has its photo's size and marks some pixels; masks of no
  photo are named and ignored.
- ``init_mesh.ply``: readable, faces index existing vertices, watertight and two-manifold with
  outward normals (:func:`recon.init_mesh.check_closed_manifold`), and, with given cameras, at
  the cameras' scale: it projects inside the views (and matches the masks' silhouettes in size
  when the capture has masks).

Problems are errors (:class:`CaptureError`, raised once with all of them) or warnings (logged
and returned). Nothing in the capture is written or changed.
"""

from __future__ import annotations

import json
import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from recon.config import ConfigError, build_settings, read_capture_yaml, stage_settings
from recon.export import ExportSettings
from recon.init_mesh import InitMeshError, InitMeshSettings, check_closed_manifold
from recon.io.atomic import atomic_path
from recon.io.cameras import CameraError, CameraSet, load_cameras
from recon.io.images import (
    HDR_EXTENSIONS,
    HEIF_EXTENSIONS,
    RAW_EXTENSIONS,
    ImageError,
    read_exr,
    read_ldr_codes,
    read_mask,
    register_heif,
)
from recon.io.mesh import Mesh, MeshError, read_mesh
from recon.linearize import LinearizeSettings
from recon.linearize.metadata import flash_fired, read_meta
from recon.linearize.stage import list_images
from recon.masks import MaskSettings
from recon.optimize.settings import settings_from_dict
from recon.poses import PoseSettings
from recon.report import ReportSettings
from recon.stages import SETTINGS_STAGES
from recon.uv import UVSettings

log = logging.getLogger(__name__)

MIN_VIEWS = 3
"""Fewest views a capture may have (with known cameras, or for SfM): two views cannot constrain
a mesh (every shape between the two silhouette cones fits them)."""

BLACK_LEVEL = 0.01
"""A photo is black when its brightest pixels (99.9th percentile of the brightest channel) reach
at most this fraction of full scale: sRGB codes up to 2 of 255 (JPEG/PNG), or RAW counts up to
1 % of the range above the black level. No light reached the sensor; an underexposed photo of a
lit object is brighter, and the masks stage judges that (``masks.min_signal``)."""
WHITE_FRACTION = 0.9
"""A photo is white when at least this fraction of its pixels is clipped (every channel at full
scale; RAW: at the white level): overexposed, the object is gone."""

MESH_FIT_MIN_INSIDE = 0.5
"""A given mesh must have at least this fraction of its vertices inside the median view."""
MESH_FIT_MIN_SIZE = 0.05
"""... and project at least this fraction of the image's longer side across (not a dot)."""
MESH_FIT_MASK_RATIO = 2.0
"""... and, with masks, a projected size within this factor of the masks' silhouettes."""

_BUILDERS = {
    "linearize": lambda values: build_settings(LinearizeSettings, values),
    "masks": lambda values: build_settings(MaskSettings, values),
    "poses": lambda values: build_settings(PoseSettings, values),
    "init_mesh": lambda values: build_settings(InitMeshSettings, values),
    "uv": lambda values: build_settings(UVSettings, values),
    "optimize": lambda values: settings_from_dict(values, " / ".join(values.get("_sources", []))),
    "export": lambda values: build_settings(ExportSettings, values),
    "report": lambda values: build_settings(ReportSettings, values),
}


class CaptureError(ValueError):
    """A capture that cannot run; the message lists every problem, each naming its file and fix."""


@dataclass
class _Findings:
    errors: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    sizes: dict = field(default_factory=dict)  # stem -> (width, height), or None: unreadable (reported once)


def hidden_files(folder: str | os.PathLike) -> list[str]:
    """Names of the hidden files in ``folder`` (``.DS_Store``, macOS ``._*`` AppleDouble files):
    never photos or masks; every listing of the capture ignores them."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


def image_size(path: str | os.PathLike) -> tuple[int, int]:
    """``(width, height)`` of the linear image the linearize stage makes of ``path``, read from
    the file's header (RAW: the visible sensor area, cut to the DNG DefaultCrop; others: the
    stored pixels, EXIF orientation ignored as the stages do)."""
    path = Path(path)
    suffix = path.suffix.lower()
    try:
        if suffix in RAW_EXTENSIONS:
            import rawpy

            with rawpy.imread(str(path)) as raw:
                w, h = int(raw.sizes.width), int(raw.sizes.height)
            crop = read_meta(path).default_crop
            return (int(crop[2]), int(crop[3])) if crop is not None else (w, h)
        if suffix in HDR_EXTENSIONS:
            import OpenEXR

            with OpenEXR.File(str(path), header_only=True) as f:
                (x0, y0), (x1, y1) = f.header()["dataWindow"]
            return int(x1 - x0 + 1), int(y1 - y0 + 1)
        from PIL import Image

        if suffix in HEIF_EXTENSIONS:
            register_heif()
        with Image.open(path) as im:
            return int(im.size[0]), int(im.size[1])
    except (ImageError, ValueError) as e:
        raise ImageError(str(e) if str(path) in str(e) else f"{path}: cannot read the image size ({e})") from e
    except Exception as e:  # readers raise their own types for corrupt files
        raise ImageError(f"{path}: cannot read the image ({type(e).__name__}: {e}); replace or remove the "
                         "file") from e


# ---- capture.yaml ----
def _check_settings(capture_dir: Path, preset: str, presets_dir, found: _Findings) -> dict:
    try:
        cap = read_capture_yaml(capture_dir)
    except ConfigError as e:
        found.errors.append(str(e))
        return {}
    built = {}
    for stage in SETTINGS_STAGES:
        try:
            built[stage] = _BUILDERS[stage](stage_settings(stage, preset, capture_dir, presets_dir))
        except ConfigError as e:
            found.errors.append(str(e))
    if cap.get("preset"):
        found.notes.append(f"preset {cap['preset']} (from capture.yaml)")
    return built


# ---- images/ ----
def _check_images(capture_dir: Path, found: _Findings) -> dict[str, Path] | None:
    hidden = hidden_files(capture_dir / "images")
    if hidden:
        found.warnings.append(f"{capture_dir / 'images'}: ignoring hidden file(s) {', '.join(hidden)} (not photos: "
                              "macOS writes ._* AppleDouble files beside copied files)")
    try:
        files = list_images(capture_dir)
    except ValueError as e:
        found.errors.append(str(e))
        return None  # the checks against the photos would only repeat this error
    metas = {}
    for p in files:
        try:
            metas[p] = read_meta(p)
        except ValueError as e:
            found.errors.append(str(e))
            found.sizes[p.stem] = None
    sizes = _sizes({p.stem: p for p in files}, [p.stem for p in files], found)
    if len(set(sizes.values())) > 1:
        first = next(p for p in files if p.stem in sizes)
        odd = [p for p in files if p.stem in sizes and sizes[p.stem] != sizes[first.stem]]
        w, h = sizes[first.stem]
        found.errors.append(f"{odd[0]}: size {sizes[odd[0].stem][0]}x{sizes[odd[0].stem][1]} differs from "
                            f"{first.name}'s ({w}x{h}){f' (and {len(odd) - 1} more)' if len(odd) > 1 else ''}; every "
                            "view of a capture must come from the same camera at the same size")
    blank = _check_levels(capture_dir, [p for p in files if p in metas], found)
    _check_flash(capture_dir, files, metas, found)
    # copies of one black or white photo were named as such above (all-black PNGs are identical)
    copies = [g for g in identical_files(files) if not set(g) <= blank]
    if copies:
        found.warnings.append("identical photos (byte for byte; a copy adds no view and SfM cannot place it): "
                              + "; ".join(" = ".join(str(p) for p in group) for group in copies))
        distinct = len(files) - sum(len(g) - 1 for g in copies)
        if distinct < MIN_VIEWS:
            found.errors.append(f"{capture_dir / 'images'}: {len(files)} photos but only {distinct} different one(s) "
                                f"({', '.join(' = '.join(p.name for p in g) for g in copies)} are identical "
                                f"copies); at least {MIN_VIEWS} views from different directions are needed")
    return {p.stem: p for p in files}


def photo_levels(path: str | os.PathLike) -> tuple[float, float] | None:
    """``(top, clipped)`` of a photo read cheaply (JPEG decoded at 1/8 size, RAW counts
    subsampled, every third in each direction: all colours of the mosaic): ``top`` is the 99.9th percentile of the brightest channel as a fraction of full
    scale (RAW: of the range from the black to the white level), ``clipped`` the fraction of
    pixels at full scale in every channel (RAW: of the samples at the white level). EXR: ``top``
    is its 99.9th percentile in its own units (> 0 is lit), ``clipped`` 0 (no full scale).
    None when the pixels cannot be read (the stages name that error)."""
    import cv2

    path = Path(path)
    suffix = path.suffix.lower()
    try:
        if suffix in RAW_EXTENSIONS:
            import rawpy

            with rawpy.imread(str(path)) as raw:
                counts = np.asarray(raw.raw_image_visible)[::3, ::3].astype(np.float32)
                black = float(np.mean(raw.black_level_per_channel))
                white = float(raw.white_level)
            if not white > black:
                return None
            top = (float(np.percentile(counts, 99.9)) - black) / (white - black)
            return top, float(np.mean(counts >= white - 0.002 * (white - black)))
        if suffix in HDR_EXTENSIONS:
            img = np.nan_to_num(read_exr(path)[:, :, :3])
            return float(np.percentile(img.max(axis=2), 99.9)), 0.0
        if suffix in HEIF_EXTENSIONS:
            codes, bits = read_ldr_codes(path)
            img, full = codes[::4, ::4, :3], float(2**bits - 1)
        else:  # JPEG, PNG: libjpeg decodes at 1/8 size (a 24 MP JPEG in about 20 ms)
            img = cv2.imread(str(path), cv2.IMREAD_REDUCED_COLOR_8 | cv2.IMREAD_IGNORE_ORIENTATION)
            if img is None:
                return None
            full = 255.0
        img = img.reshape(img.shape[0], img.shape[1], -1).astype(np.float32) / full
        return float(np.percentile(img.max(axis=2), 99.9)), float(np.mean(img.min(axis=2) >= 254.0 / 255.0))
    except Exception:  # an unreadable photo is reported by read_meta / image_size, naming the file
        return None


def _check_levels(capture_dir: Path, files: list[Path], found: _Findings) -> set[Path]:
    """Errors for black and white photos, in the user's terms; returns those photos."""
    black, white = [], []
    for p in files:
        levels = photo_levels(p)
        if levels is None:
            continue
        top, clipped = levels
        if p.suffix.lower() in HDR_EXTENSIONS:
            if not top > 0:
                black.append((p, top))
        elif top <= BLACK_LEVEL:
            black.append((p, top))
        elif clipped >= WHITE_FRACTION:
            white.append((p, clipped))
    images = capture_dir / "images"
    if black:
        worst = max(t for _, t in black)
        lit = ("check that the flash fired and nothing covered it or the lens (the lens cap), and expose so "
               "that the object's brightest parts come near white")
        if len(black) == len(files):
            found.errors.append(
                f"{images}: all {len(files)} photos are black (their brightest pixels reach at most "
                f"{100 * max(worst, 0.0):.2g}% of full scale): nothing in them is lit. The method needs one "
                f"photo per view of the object lit by a flash at the camera: {lit}")
        else:
            found.errors.append(
                f"{len(black)} of the {len(files)} photos are black (brightest pixels at most "
                f"{100 * max(worst, 0.0):.2g}% of full scale: no light reached the sensor): "
                f"{', '.join(str(p) for p, _ in black)}; retake them ({lit}) or remove them from {images}")
    if white:
        least = min(c for _, c in white)
        fix = ("lower the exposure (a shorter shutter time, a smaller aperture, a lower ISO, or a weaker flash) "
               "until only small highlights are white")
        if len(white) == len(files):
            found.errors.append(
                f"{images}: all {len(files)} photos are white (at least {100 * least:.0f}% of their pixels are "
                f"clipped at full scale): overexposed, nothing of the object is left to see; {fix}")
        else:
            found.errors.append(
                f"{len(white)} of the {len(files)} photos are white (at least {100 * least:.0f}% of their pixels "
                f"clipped: overexposed): {', '.join(str(p) for p, _ in white)}; retake them ({fix}) or remove "
                f"them from {images}")
    return {p for p, _ in black + white}


def _check_flash(capture_dir: Path, files: list[Path], metas: dict, found: _Findings) -> None:
    """Photos whose EXIF says the flash did not fire (EXIF Flash, bit 0): an error naming them.

    The method models every view as lit by the flash at the camera (DESIGN section 3). A photo
    without it is lit by the room alone: its shading and brightness follow another light, which
    the fit of the shape and reflectance cannot tell from the flash-lit views (it would pull
    both wrong), and with the manual exposure flash photos are taken at (here f/18, 1/10 s) it
    is black or nearly so, which the masks stage refuses minutes later. So a capture in which no
    photo had the flash is refused, and so is one in which only some lack it: removing those
    photos (named) or retaking them is quick, a quietly wrong asset is not. Photos whose EXIF
    does not say (PNG, EXR, most synthetic files) are not judged."""
    off = [p for p in files if p in metas and flash_fired(metas[p]) is False]
    if not off:
        return
    images = capture_dir / "images"
    stated = sum(1 for p in files if p in metas and flash_fired(metas[p]) is not None)
    need = ("the method needs one photo per view lit by a flash at the camera (a flash photo per view: the light "
            "at the lens, the room dim)")
    if len(off) == len(files):
        found.errors.append(
            f"{images}: the EXIF of all {len(files)} photos says the flash did not fire; {need}. Take the "
            "photos again with the flash on (forced on, not automatic)")
    else:
        found.errors.append(
            f"the EXIF of {len(off)} of the {len(files)} photos ({stated} say whether the flash fired) says the flash "
            f"did not fire: {', '.join(str(p) for p in off)}; {need}. Remove these photos from {images} (the "
            "others still work if they surround the object) or take them again with the flash")


def identical_files(paths: list[Path]) -> list[list[Path]]:
    """Groups (of two or more) of byte-identical files among ``paths``: sizes first, then the
    first 64 KiB, then the whole file, so that only likely copies are read in full."""
    import hashlib

    def digest(p: Path, limit: int | None) -> str:
        h = hashlib.sha256()
        with open(p, "rb") as f:
            if limit is not None:
                h.update(f.read(limit))
            else:
                for block in iter(lambda: f.read(1 << 20), b""):
                    h.update(block)
        return h.hexdigest()

    groups: list[list[Path]] = [list(paths)]
    for key in (lambda p: p.stat().st_size, lambda p: digest(p, 1 << 16), lambda p: digest(p, None)):
        refined = []
        for group in groups:
            by: dict = {}
            for p in group:
                by.setdefault(key(p), []).append(p)
            refined += [g for g in by.values() if len(g) > 1]
        groups = refined
    return sorted(sorted(g) for g in groups)


def _sizes(images: dict[str, Path], stems, found: _Findings) -> dict[str, tuple[int, int]]:
    for s in sorted(stems):
        if s not in found.sizes:
            try:
                found.sizes[s] = image_size(images[s])
            except ImageError as e:
                found.errors.append(str(e))
                found.sizes[s] = None
    return {s: found.sizes[s] for s in stems if found.sizes[s] is not None}


# ---- cameras.json ----
def _check_cameras(capture_dir: Path, images: dict[str, Path], light_intensity, found: _Findings
                   ) -> CameraSet | None:
    path = capture_dir / "cameras.json"
    try:
        cams = load_cameras(path)
    except CameraError as e:
        found.errors.append(f"{e} (fix it, or delete it to recover the cameras by SfM)")
        return None
    seen: dict[str, int] = {}
    sizes = _sizes(images, {c.stem for c in cams if c.stem in images}, found)
    for i, c in enumerate(cams):
        if c.stem in seen:
            found.errors.append(f"{path}: frames[{i}] and frames[{seen[c.stem]}] are both for '{c.stem}'; give each "
                                "photo one camera")
            continue
        seen[c.stem] = i
        if c.stem not in images:
            found.errors.append(f"{path}: frames[{i}] is the camera of '{c.image}', but images/ has no photo named "
                                f"'{c.stem}.*'; the names in cameras.json must match the photos (add the photo or "
                                "remove the frame)")
        elif c.stem in sizes and sizes[c.stem] != (c.width, c.height):
            w, h = sizes[c.stem]
            found.errors.append(f"{path}: frames[{i}] ('{c.image}') is {c.width}x{c.height} but {images[c.stem]} is "
                                f"{w}x{h}; the cameras must describe these photos at their size")
    _check_convergence(path, cams, found)
    known = [s for s in seen if s in images]
    dropped = sorted(set(images) - set(seen))
    if dropped:
        found.warnings.append(f"{path} has no camera for {len(dropped)} of the {len(images)} photos: "
                              f"{', '.join(images[s].name for s in dropped)}; these photos are unused (dropped; add their cameras "
                              "to use them, or delete cameras.json to recover all cameras by SfM)")
    if images and len(known) < MIN_VIEWS:
        found.errors.append(f"{path}: {len(known)} view(s) with a camera and a photo, but at least {MIN_VIEWS} are "
                            "needed (two views cannot constrain a mesh); photograph the object from more sides "
                            "(a view every 10-15 degrees) and give their cameras")
    light = (json.loads(path.read_text()).get("light") or {})
    if light_intensity is not None and "intensity" in light and not math.isclose(
            cams.light_intensity, float(light_intensity), rel_tol=1e-6):
        found.errors.append(f"the light intensity is given twice with different values: {path} has light.intensity "
                            f"{cams.light_intensity:g} and {capture_dir / 'capture.yaml'} light_intensity "
                            f"{float(light_intensity):g}; remove it from one of the two files (or make them agree)")
    return cams


def _check_convergence(path: Path, cams: CameraSet, found: _Findings) -> None:
    """The point nearest (least squares) to every camera's optical axis must lie in front of most
    cameras: it does not for cameras in OpenGL's or Blender's axes (looking down -z). Skipped
    when the axes are (nearly) parallel, e.g. a forward-facing capture."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for c in cams:
        d = c.camera_to_world[:3, 2]  # OpenCV: +z is the viewing direction
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c.center
    if len(cams) < 2 or np.linalg.cond(A) > 1e6:
        return
    p = np.linalg.solve(A, b)
    behind = [c.stem for c in cams if (c.world_to_camera[:3, :3] @ p + c.world_to_camera[:3, 3])[2] <= 0]
    if len(behind) > len(cams) / 2:
        found.errors.append(f"{path}: the cameras' viewing directions meet behind {len(behind)} of the {len(cams)} "
                            "cameras: are they in OpenGL's or Blender's axes (looking down -z, y up)? cameras.json "
                            "uses OpenCV's (x right, y down, z forward; DESIGN section 1): flip the y and z rows "
                            "of world_to_camera (the object must be in front of the cameras)")


# ---- masks/ ----
def _check_masks(capture_dir: Path, images: dict[str, Path], found: _Findings) -> dict[str, np.ndarray]:
    folder = capture_dir / "masks"
    if not folder.is_dir():
        return {}
    hidden = hidden_files(folder)
    if hidden:
        found.warnings.append(f"{folder}: ignoring hidden file(s) {', '.join(hidden)} (not masks)")
    files = sorted(p for p in folder.iterdir() if not p.name.startswith("."))
    other = [p.name for p in files if p.suffix.lower() != ".png"]
    if other:
        found.warnings.append(f"{folder}: ignoring {', '.join(other)} (masks are <photo stem>.png)")
    pngs = {p.stem: p for p in files if p.suffix.lower() == ".png"}
    orphans = sorted(s for s in pngs if s not in images)
    if orphans and images:
        found.warnings.append(f"{folder}: {', '.join(pngs[s].name for s in orphans)} match(es) no photo in images/ "
                              "and are ignored (a mask is named after its photo: masks/<stem>.png)")
    sizes = _sizes(images, {s for s in pngs if s in images}, found)
    masks = {}
    for s, p in sorted(pngs.items()):
        if s not in images:
            continue
        try:
            m = read_mask(p)
        except (ImageError, ValueError) as e:
            found.errors.append(str(e) if str(p) in str(e) else f"{p}: {e}")
            continue
        if s in sizes and sizes[s] != (m.shape[1], m.shape[0]):
            w, h = sizes[s]
            found.errors.append(f"{p}: mask is {m.shape[1]}x{m.shape[0]} but {images[s]} is {w}x{h}; a mask must "
                                "have its photo's size")
        elif not m.any():
            found.errors.append(f"{p}: the mask is empty (every pixel 0), so it shows no object; draw the object "
                                "(nonzero pixels) or delete the file to let the masks stage derive the mask")
        else:
            masks[s] = m
    if pngs:
        found.notes.append(f"{len(masks)} given mask(s)")
    return masks


# ---- init_mesh.ply ----
def check_mesh_fit(mesh: Mesh, cams: CameraSet, source: str, masks: dict[str, np.ndarray] | None = None
                   ) -> dict:
    """Check that ``mesh`` (from the file ``source``) sits where the cameras look, at their scale.

    Per view: the fraction of the vertices in front of the camera and inside the image, and
    the projected size; with ``masks``, the ratio of the projected size to the silhouette's.
    Raises :class:`CaptureError` naming ``source`` when, in the median view, fewer than 99% of
    the vertices lie in front of the camera or fewer than :data:`MESH_FIT_MIN_INSIDE` inside
    the image, when the mesh spans less than :data:`MESH_FIT_MIN_SIZE` of the image, or when
    its size differs from the masks' by more than :data:`MESH_FIT_MASK_RATIO` times.
    Returns the medians.
    """
    v = mesh.v_pos
    if len(v) > 4000:
        v = v[np.random.default_rng(0).choice(len(v), 4000, replace=False)]
    front, inside, size, ratio = [], [], [], []
    for cam in cams:
        xy, z = cam.project(v)
        f = z > 0
        ins = f & (xy[:, 0] >= 0) & (xy[:, 0] <= cam.width) & (xy[:, 1] >= 0) & (xy[:, 1] <= cam.height)
        front.append(f.mean())
        inside.append(ins.mean())
        if f.any():
            lo = np.clip(xy[f].min(0), 0, [cam.width, cam.height])
            hi = np.clip(xy[f].max(0), 0, [cam.width, cam.height])
            extent = float(np.max(hi - lo))
        else:
            extent = 0.0
        size.append(extent / max(cam.width, cam.height))
        m = (masks or {}).get(cam.stem)
        if m is not None and m.any() and m.shape == (cam.height, cam.width) and extent > 0:
            rows, cols = np.nonzero(m)
            ratio.append(extent / max(rows.max() - rows.min() + 1, cols.max() - cols.min() + 1))
    med = {"in_front": float(np.median(front)), "inside": float(np.median(inside)),
           "size": float(np.median(size)), "size_to_masks": float(np.median(ratio)) if ratio else None}
    lo, hi = mesh.bbox()
    across = float(np.linalg.norm(hi - lo))
    distance = float(np.median([np.linalg.norm(c.center - 0.5 * (lo + hi)) for c in cams]))
    scale = (f"the mesh is {across:.3g} across and its center {distance:.3g} from the cameras (median); a mesh "
             "made in other units or another frame than cameras.json's must be scaled and moved into it")
    fix = "; fix the mesh, or delete it to use the visual hull of the masks"
    if med["in_front"] < 0.99:
        raise CaptureError(f"{source}: does not fit the cameras: in the median view only {med['in_front']:.0%} of "
                           f"its vertices lie in front of the camera (the cameras are inside or beside it); {scale}{fix}")
    if med["inside"] < MESH_FIT_MIN_INSIDE:
        raise CaptureError(f"{source}: does not fit the cameras: in the median view only {med['inside']:.0%} of its "
                           f"vertices project inside the image; {scale}{fix}")
    if med["size"] < MESH_FIT_MIN_SIZE:
        raise CaptureError(f"{source}: does not fit the cameras: it spans only {med['size']:.1%} of the image in the "
                           f"median view (far too small for them); {scale}{fix}")
    r = med["size_to_masks"]
    if r is not None and not 1 / MESH_FIT_MASK_RATIO <= r <= MESH_FIT_MASK_RATIO:
        raise CaptureError(f"{source}: does not fit the masks: it projects {r:.2g} times the size of the masks' "
                           f"silhouettes (median view); {scale}{fix}")
    return med


def _check_init_mesh(capture_dir: Path, cams: CameraSet | None, masks: dict[str, np.ndarray],
                     found: _Findings) -> None:
    path = capture_dir / "init_mesh.ply"
    if not path.is_file():
        return
    fix = "repair it (e.g. in MeshLab: Filters > Cleaning and Repairing) or delete it to use the visual hull"
    try:
        mesh = read_mesh(path)
        check_closed_manifold(mesh, str(path))
    except (MeshError, InitMeshError) as e:
        found.errors.append(f"{e}; {fix}" if isinstance(e, InitMeshError) else str(e))
        return
    if cams is None:
        if not (capture_dir / "cameras.json").is_file():
            found.warnings.append(f"{path} is given without cameras.json: it must lie in the frame of the cameras that "
                                  "SfM recovers (the poses stage's object frame), which is not checked here; give "
                                  "cameras.json in the mesh's frame (DESIGN section 1)")
        return
    try:
        check_mesh_fit(mesh, cams, str(path), masks)
    except CaptureError as e:
        found.errors.append(str(e))


# ---- the whole capture ----
def validate_capture(capture_dir: str | os.PathLike, preset: str = "balanced",
                     presets_dir: str | os.PathLike | None = None) -> dict:
    """Check everything the capture at ``capture_dir`` brings (module docstring) before a stage runs.

    Parameters
    ----------
    capture_dir : the capture folder (``images/``, optional ``masks/``, ``cameras.json``,
        ``init_mesh.ply``, ``capture.yaml``).
    preset : the preset the run uses (the capture.yaml's ``preset`` replaces it).
    presets_dir : the folder of the presets (default: the repository's ``config/presets``).

    Returns
    -------
    dict
        ``capture``, ``views`` (stems of the photos the stages use), ``dropped`` (stems of
        photos without a camera), ``cameras`` ('given' or 'sfm'), ``masks`` (stems of the given
        masks), ``init_mesh`` ('given' or 'visual_hull'), ``warnings`` and ``notes``.

    Raises
    ------
    CaptureError
        Listing every error found, each naming its file and the fix; nothing is written.
    """
    capture_dir = Path(capture_dir)
    found = _Findings()
    if not capture_dir.is_dir():
        raise CaptureError(f"{capture_dir}: capture folder not found")
    _check_settings(capture_dir, preset, presets_dir, found)
    images = _check_images(capture_dir, found)
    listed = images is not None
    images = images or {}
    cams = None
    if listed and (capture_dir / "cameras.json").is_file():
        try:
            light = read_capture_yaml(capture_dir).get("light_intensity")
        except ConfigError:
            light = None  # reported above
        cams = _check_cameras(capture_dir, images, light, found)
    elif images and len(images) < MIN_VIEWS:
        found.errors.append(f"{capture_dir / 'images'}: {len(images)} photo(s), but at least {MIN_VIEWS} views are "
                            "needed (two views cannot constrain a mesh; SfM needs overlapping views); photograph the "
                            "object from more sides (a view every 10-15 degrees)")
    masks = _check_masks(capture_dir, images, found) if listed else {}
    _check_init_mesh(capture_dir, cams, masks, found)
    for w in found.warnings:
        log.warning("%s", w)
    if found.errors:
        if len(found.errors) == 1:
            raise CaptureError(found.errors[0])
        raise CaptureError(f"capture {capture_dir} has {len(found.errors)} problems:\n"
                           + "\n".join(f"  - {e}" for e in found.errors))
    given = {c.stem for c in cams} if cams is not None else set(images)
    report = {
        "capture": str(capture_dir),
        "views": sorted(s for s in images if s in given),
        "dropped": sorted(set(images) - given),
        "cameras": "given" if cams is not None else "sfm",
        "masks": sorted(masks),
        "init_mesh": "given" if (capture_dir / "init_mesh.ply").is_file() else "visual_hull",
        "warnings": found.warnings,
        "notes": found.notes,
    }
    log.info("capture %s checked: %d views (%s cameras)%s", capture_dir, len(report["views"]), report["cameras"],
             "".join(f"; {n}" for n in found.notes))
    return report


def run_check(capture_dir: str | os.PathLike, out_path: str | os.PathLike, preset: str = "balanced",
              presets_dir: str | os.PathLike | None = None) -> dict:
    """:func:`validate_capture`, and its report written to ``out_path`` (``results/<capture>/check/
    check.json``) atomically: the file exists only for a capture that passed."""
    report = validate_capture(capture_dir, preset, presets_dir)
    with atomic_path(out_path) as tmp:
        tmp.write_text(json.dumps(report, indent=1))
    return report
