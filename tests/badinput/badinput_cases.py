"""The bad-input corpus (issue 20): a small good capture, and one change per case that breaks it.

:func:`sphere_capture` writes a capture of a unit sphere seen from a ring of cameras, in
seconds and without rendering: PNG photos (the lit disk on black), exact masks (the sphere's
silhouette, pixel centres tested against the sphere), ``cameras.json`` and an icosphere
``init_mesh.ply``; each part optional. Each :class:`Case` edits a copy of it (or of the demo)
and states what the check must say: an error naming a file, or a warning.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from recon.io.cameras import Camera, CameraSet, intrinsics, look_at, save_cameras
from recon.io.images import write_mask, write_png
from recon.io.mesh import Mesh, read_obj, write_ply
from recon.synth.shapes import icosphere

REPO = Path(__file__).resolve().parents[2]
DEMO = REPO / "captures" / "demo"


def sphere_cameras(n_views: int = 8, width: int = 64, height: int = 48, distance: float = 4.0) -> list[Camera]:
    """A ring of ``n_views`` cameras around the origin at two alternating elevations."""
    K = intrinsics(width, height, 40.0)
    cams = []
    for k in range(n_views):
        a = 2 * np.pi * k / n_views
        e = np.radians(25.0 if k % 2 else 5.0)
        eye = distance * np.array([np.cos(a) * np.cos(e), np.sin(a) * np.cos(e), np.sin(e)])
        cams.append(Camera(f"images/{k:04d}.png", width, height, K, look_at(eye, [0, 0, 0])))
    return cams


def sphere_view(cam: Camera, radius: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """The sphere of ``radius`` at the origin in ``cam``: (H, W) bool mask (the pixels whose
    centre ray meets it) and (H, W, 3) sRGB photo (stripes of longitude, black background), so
    that every view differs."""
    j, i = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    d_cam = np.stack([j, i, np.ones_like(j)], -1) @ np.linalg.inv(cam.K).T
    d = d_cam @ cam.camera_to_world[:3, :3].T
    c = cam.center
    b = d @ c
    dd = np.einsum("...k,...k", d, d)
    disc = b * b - (c @ c - radius**2) * dd
    mask = disc >= 0
    t = (-b - np.sqrt(np.maximum(disc, 0))) / dd
    p = c + t[..., None] * d
    stripes = np.sin(5 * np.arctan2(p[..., 1], p[..., 0]) + 3 * p[..., 2]) > 0
    photo = np.where(mask[..., None], np.where(stripes[..., None], [0.7, 0.5, 0.3], [0.2, 0.3, 0.6]), 0.02)
    return mask, photo


def sphere_capture(folder: Path, n_views: int = 8, cameras: bool = True, masks: bool = True,
                   init_mesh: bool = True) -> Path:
    """Write the good sphere capture to ``folder`` (see the module docstring); returns it."""
    cams = sphere_cameras(n_views)
    for cam in cams:
        m, photo = sphere_view(cam)
        write_png(folder / cam.image, photo)
        if masks:
            write_mask(folder / "masks" / f"{cam.stem}.png", m)
    if cameras:
        save_cameras(folder / "cameras.json", CameraSet(tuple(cams), 1.0))
    if init_mesh:
        write_ply(folder / "init_mesh.ply", icosphere(3))
    return folder


def demo_capture(folder: Path, cameras: bool = False, init_mesh: bool = False) -> Path:
    """A copy of the bundled demo (32 DNGs), with its true cameras and mesh when asked."""
    shutil.copytree(DEMO, folder)
    if cameras:
        shutil.copyfile(DEMO / "gt" / "cameras.json", folder / "cameras.json")
    if init_mesh:
        write_ply(folder / "init_mesh.ply", read_obj(DEMO / "gt" / "mesh.obj"))
    return folder


def tree_hashes(root: Path) -> dict[str, str]:
    """sha256 of every file under ``root`` (relative path -> digest): "the capture unchanged"."""
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


PHOTOS = {"cameras": False, "masks": False, "init_mesh": False}  # sphere_capture: the photos alone

# ---- the edits ----
def _yaml(text: str) -> Callable[[Path], None]:
    return lambda cap: (cap / "capture.yaml").write_text(text)


def _edit_cameras(edit: Callable[[dict], None]) -> Callable[[Path], None]:
    def apply(cap: Path) -> None:
        data = json.loads((cap / "cameras.json").read_text())
        edit(data)
        (cap / "cameras.json").write_text(json.dumps(data))
    return apply


def _opengl(data: dict) -> None:
    """Cameras in OpenGL's axes (y up, looking down -z): OpenCV's y and z rows negated."""
    for frame in data["frames"]:
        w2c = np.array(frame["world_to_camera"])
        w2c[1:3] *= -1
        frame["world_to_camera"] = w2c.tolist()


def _mesh(transform: Callable[[Mesh], Mesh]) -> Callable[[Path], None]:
    return lambda cap: write_ply(cap / "init_mesh.ply", transform(icosphere(3)))


def _bad_index(m: Mesh) -> Mesh:
    f = m.t_pos_idx.copy()
    f[7, 1] = 999999
    return Mesh(m.v_pos, f)


def _fin(m: Mesh) -> Mesh:
    """Two faces more on an edge of the sphere: that edge has four faces (non-manifold)."""
    a, b = m.t_pos_idx[0, 0], m.t_pos_idx[0, 1]
    v = np.concatenate([m.v_pos, [[2.0, 0.0, 0.0], [0.0, 2.0, 0.0]]])
    n = len(m.v_pos)
    return Mesh(v, np.concatenate([m.t_pos_idx, [[a, b, n], [b, a, n + 1]]]))


def _rename_image(old: str, new: str) -> Callable[[Path], None]:
    return lambda cap: (cap / "images" / old).rename(cap / "images" / new)


def _write_mask(stem: str, value) -> Callable[[Path], None]:
    def apply(cap: Path) -> None:
        m = value(np.zeros((48, 64), bool)) if callable(value) else value
        write_mask(cap / "masks" / f"{stem}.png", m)
    return apply


def _apple_double(cap: Path) -> None:
    # what macOS writes beside a copied file on a non-HFS volume: an AppleDouble header, not a photo
    for folder, name in (("images", "._0000.png"), ("masks", "._0000.png")):
        (cap / folder / name).write_bytes(b"\x00\x05\x16\x07\x00\x02\x00\x00Mac OS X        " + bytes(50))
    (cap / "images" / ".DS_Store").write_bytes(b"\x00\x00\x00\x01Bud1" + bytes(20))


def _repeat_photo(n: int) -> Callable[[Path], None]:
    """The first ``n`` photos replaced by copies of the first: the same photo repeated."""
    def apply(cap: Path) -> None:
        for k in range(1, n):
            shutil.copyfile(cap / "images" / "0000.png", cap / "images" / f"{k:04d}.png")
    return apply


def _fill_photos(value: float) -> Callable[[Path], None]:
    """Every photo replaced by one of a single grey ``value`` (0: black, 1: white), same size."""
    def apply(cap: Path) -> None:
        for p in sorted((cap / "images").glob("*.png")):
            write_png(p, np.full((48, 64, 3), value))
    return apply


def _fill_photo(stem: str, value: float) -> Callable[[Path], None]:
    return lambda cap: write_png(cap / "images" / f"{stem}.png", np.full((48, 64, 3), value))


def _white_dngs(cap: Path) -> None:
    """The photos replaced by DNGs whose every sensor site is at the white level (a clipped sensor)."""
    from recon.io.dng import write_dng
    from recon.synth.sensor import SensorModel

    sensor = SensorModel()
    for p in sorted((cap / "images").glob("*.png")):
        write_dng(p.with_suffix(".dng"), np.full((48, 64), sensor.white_level, np.uint16), sensor, 1 / 60, 100, 5.6)
        p.unlink()


def flash_jpegs(cap: Path, flash: Callable[[int], int | None]) -> None:
    """The photos as JPEGs with EXIF: ``flash(k)`` is view k's EXIF Flash value (9: fired, forced
    on; 16: did not fire, forced off; None: no Flash tag), as a Canon EOS Rebel T3 writes it."""
    from PIL import Image

    for k, p in enumerate(sorted((cap / "images").glob("*.png"))):
        exif = Image.Exif()
        exif[0x010F], exif[0x0110] = "Canon", "Canon EOS REBEL T3"
        sub = {0x829A: 0.1, 0x829D: 18.0, 0x8827: 800, 0x920A: 55.0}
        if flash(k) is not None:
            sub[0x9209] = flash(k)
        exif.get_ifd(0x8769).update(sub)
        with Image.open(p) as im:
            im.convert("RGB").save(p.with_suffix(".jpg"), quality=95, exif=exif.tobytes())
        p.unlink()


@dataclass(frozen=True)
class Case:
    """One broken capture: ``edit`` applied to a good sphere capture; the check must fail with
    ``error`` (a regex) naming ``names`` (a path relative to the capture), or, for a warning
    case (``error`` None), pass and warn with ``warning`` naming ``names``."""

    id: str
    edit: Callable[[Path], None]
    names: str
    error: str | None = None
    warning: str | None = None
    base: dict | None = None  # sphere_capture arguments


CASES = [
    # capture.yaml: top level and every stage's section
    Case("light_intensity_string", _yaml('light_intensity: "bright"\n'), "capture.yaml",
         r"light_intensity must be a positive number, got 'bright'"),
    Case("light_intensity_negative", _yaml("light_intensity: -3\n"), "capture.yaml",
         r"light_intensity must be a positive number, got -3"),
    Case("light_intensity_twice", _yaml("light_intensity: 5\n"), "cameras.json",
         r"light intensity is given twice"),
    Case("unknown_key_in_section", _yaml("masks:\n  dilate_pixels: 2\n"), "capture.yaml",
         r"unknown MaskSettings key\(s\) \['dilate_pixels'\]"),
    Case("string_for_a_number", _yaml("init_mesh:\n  resolution: high\n"), "capture.yaml",
         r"InitMeshSettings setting 'resolution' must be a whole number, got 'high'"),
    Case("negative_iterations", _yaml("optimize:\n  stages:\n    - {edge_length: 0.04, iterations: -5}\n"),
         "capture.yaml", r"'iterations' must not be negative, got -5"),
    Case("negative_count_poses", _yaml("poses:\n  min_num_inliers: -1\n"), "capture.yaml",
         r"'min_num_inliers' must not be negative"),
    Case("bool_for_a_switch", _yaml("linearize:\n  clip_negative: maybe\n"), "capture.yaml",
         r"'clip_negative' must be true or false, got 'maybe'"),
    Case("bad_export_section", _yaml("export:\n  meters_per_unit: 0\n"), "capture.yaml", r"meters_per_unit"),
    # cameras.json against the photos
    Case("camera_of_missing_photo", _rename_image("0003.png", "0003b.png"), "cameras.json",
         r"camera of 'images/0003.png', but images/ has no photo named '0003\.\*'"),
    Case("camera_size_differs", _edit_cameras(lambda d: d["frames"][2].update(width=128)), "cameras.json",
         r"frames\[2\] \('images/0002.png'\) is 128x48 but .*0002.png is 64x48"),
    Case("two_views_with_cameras", _edit_cameras(lambda d: d.update(frames=d["frames"][:2])), "cameras.json",
         r"2 view\(s\) with a camera and a photo, but at least 3"),
    Case("duplicate_frames", _edit_cameras(lambda d: d["frames"].append(dict(d["frames"][0]))), "cameras.json",
         r"both for '0000'"),
    Case("photos_without_camera", _edit_cameras(lambda d: d.update(frames=d["frames"][:6])), "cameras.json",
         warning=r"no camera for 2 of the 8 photos: 0006.png, 0007.png; these photos are unused"),
    # masks against the photos
    Case("mask_all_zero", _write_mask("0004", np.zeros((48, 64), bool)), "masks/0004.png",
         r"the mask is empty \(every pixel 0\)"),
    Case("mask_wrong_size", _write_mask("0005", np.ones((24, 32), bool)), "masks/0005.png",
         r"mask is 32x24 but .*0005.png is 64x48"),
    Case("mask_of_no_photo", _write_mask("9999", np.ones((48, 64), bool)), "masks",
         warning=r"9999.png match\(es\) no photo in images/ and are ignored"),
    Case("apple_double_files", _apple_double, "images",
         warning=r"ignoring hidden file\(s\) \.DS_Store, \._0000\.png"),
    # init_mesh.ply
    Case("mesh_face_index_missing_vertex", _mesh(_bad_index), "init_mesh.ply",
         r"1 face\(s\) refer to vertices that do not exist \(face 7 uses vertex 999999"),
    Case("mesh_open", _mesh(lambda m: Mesh(m.v_pos, m.t_pos_idx[3:])), "init_mesh.ply",
         r"not a watertight two-manifold: \d+ boundary edges"),
    Case("mesh_non_manifold", _mesh(_fin), "init_mesh.ply", r"not a watertight two-manifold: .*non-manifold edges"),
    Case("mesh_inward_normals", _mesh(lambda m: Mesh(m.v_pos, m.t_pos_idx[:, ::-1])), "init_mesh.ply",
         r"non-positive volume"),
    Case("mesh_10x_too_large", _mesh(lambda m: Mesh(m.v_pos * 10, m.t_pos_idx)), "init_mesh.ply",
         r"does not fit the cameras: .* lie in front of the camera"),
    Case("mesh_100x_too_small", _mesh(lambda m: Mesh(m.v_pos * 0.01, m.t_pos_idx)), "init_mesh.ply",
         r"does not fit the cameras: it spans only"),
    Case("mesh_3x_too_small_masks", _mesh(lambda m: Mesh(m.v_pos / 3, m.t_pos_idx)), "init_mesh.ply",
         r"does not fit the masks: it projects 0.3\d* times the size"),
    Case("mesh_off_center", _mesh(lambda m: Mesh(m.v_pos + [0.0, 0.0, 3.0], m.t_pos_idx)), "init_mesh.ply",
         r"does not fit the cameras: in the median view only \d+% of its vertices project inside"),
    Case("mesh_garbage", lambda cap: (cap / "init_mesh.ply").write_bytes(b"ply\nformat ascii 1.0\nnonsense\n"),
         "init_mesh.ply", r"no vertices or triangles could be read"),
    # photos
    Case("two_photos_sfm", lambda cap: [p.unlink() for p in sorted((cap / "images").iterdir())[2:]], "images",
         r"2 photo\(s\), but at least 3 views", base={"cameras": False, "masks": False, "init_mesh": False}),
    Case("unknown_image_type", lambda cap: (cap / "images" / "notes.txt").write_text("my notes"),
         "images/notes.txt", r"unknown image type '.txt'"),
    Case("duplicate_stems", lambda cap: shutil.copyfile(cap / "images" / "0001.png", cap / "images" / "0001.jpg"),
         "images/0001", r"same name as .*0001\.(png|jpg); image stems must be unique"),
    Case("empty_images", lambda cap: [p.unlink() for p in (cap / "images").iterdir()], "images",
         r"images/ is empty"),
    Case("mixed_photo_sizes", lambda cap: write_png(cap / "images" / "0002.png", np.zeros((96, 128, 3))),
         "images/0002.png", r"size 128x96 differs from 0000.png's \(64x48\)",
         base={"cameras": False, "masks": False, "init_mesh": False}),
    Case("zero_byte_photo", lambda cap: (cap / "images" / "0002.png").write_bytes(b""), "images/0002.png",
         r"not a readable .png image"),
    Case("fake_photo", lambda cap: (cap / "images" / "0002.png").write_text("not an image"), "images/0002.png",
         r"not a readable .png image"),
    Case("corrupt_mask", lambda cap: (cap / "masks" / "0001.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(30)),
         "masks/0001.png", r"cannot decode the image"),
    Case("camera_nan", _edit_cameras(lambda d: d["frames"][1]["K"][0].__setitem__(0, float("nan"))), "cameras.json",
         r"frames\[1\]\.K: contains NaN or Inf"),
    Case("camera_not_a_rotation", _edit_cameras(lambda d: d["frames"][3]["world_to_camera"][0].__setitem__(0, 3.0)),
         "cameras.json", r"frames\[3\]\.world_to_camera: the 3x3 block is not a rotation"),
    Case("cameras_opengl_axes", _edit_cameras(_opengl), "cameras.json",
         r"viewing directions meet behind 8 of the 8 cameras: are they in OpenGL's", base={"init_mesh": False}),
    Case("same_photo_repeated", _repeat_photo(8), "images",
         r"8 photos but only 1 different one\(s\) \(0000.png = 0001.png = .* = 0007.png are identical",
         base={"cameras": False, "masks": False, "init_mesh": False}),
    Case("one_photo_copied", _repeat_photo(2), "images/0001.png",
         warning=r"identical photos .*0000.png = .*0001.png"),
    # what the photos show (issue 32 item 3): black, white, no flash; said as such, not as copies
    Case("all_photos_black", _fill_photos(0.0), "images",
         r"all 8 photos are black \(their brightest pixels reach at most 0% of full scale\): nothing in them is "
         r"lit\. The method needs one photo per view of the object lit by a flash", base=PHOTOS),
    Case("all_photos_white", _fill_photos(1.0), "images",
         r"all 8 photos are white \(at least 100% of their pixels are clipped at full scale\): overexposed",
         base=PHOTOS),
    Case("all_dngs_clipped", _white_dngs, "images", r"all 8 photos are white .*: overexposed", base=PHOTOS),
    Case("one_photo_black", _fill_photo("0003", 0.0), "images/0003.png",
         r"1 of the 8 photos are black .*images/0003.png; retake them"),
    Case("one_photo_white", _fill_photo("0005", 1.0), "images/0005.png",
         r"1 of the 8 photos are white .*images/0005.png; retake them"),
    Case("no_flash_fired", lambda cap: flash_jpegs(cap, lambda k: 16), "images",
         r"the EXIF of all 8 photos says the flash did not fire; the method needs one photo per view lit by a "
         r"flash at the camera", base=PHOTOS),
    Case("some_flash_not_fired", lambda cap: flash_jpegs(cap, lambda k: 16 if k in (2, 6) else 9),
         "images/0006.jpg",
         r"the EXIF of 2 of the 8 photos \(8 say whether the flash fired\) says the flash did not fire: "
         r".*images/0002.jpg, .*images/0006.jpg; the method needs", base=PHOTOS),
]
