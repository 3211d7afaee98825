"""The linearize stage's entry point: one white balance and one exposure scale for a capture's
photos, written atomically as one folder (see :mod:`recon.linearize`)."""

from __future__ import annotations

import dataclasses
import json
import logging
import os
from fractions import Fraction
from pathlib import Path

import numpy as np

from recon.io.atomic import atomic_dir
from recon.io.images import IMAGE_EXTENSIONS, linear_to_srgb, read_exr, write_exr, write_jpg, write_mask
from recon.linearize.color import camera_to_rec709, xyz_to_camera
from recon.linearize.decode import decode_view
from recon.linearize.metadata import View, exposure_value, focal_length_px, read_meta
from recon.linearize.settings import LinearizeError, LinearizeSettings

log = logging.getLogger(__name__)


def list_images(capture_dir: str | os.PathLike) -> list[Path]:
    """The capture's photos (``images/<file>``, sorted); LinearizeError for a bad folder."""
    folder = Path(capture_dir) / "images"
    if not folder.is_dir():
        raise LinearizeError(
            f"{folder}: no images/ folder; a capture holds its photos in images/ (DESIGN section 1)"
        )
    files = sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith("."))
    hidden = sorted(p.name for p in folder.iterdir() if p.name.startswith("."))
    if hidden:  # .DS_Store, macOS ._* AppleDouble files: never photos
        log.info("%s: ignoring hidden file(s) %s", folder, ", ".join(hidden))
    if not files:
        raise LinearizeError(f"{folder}: images/ is empty; put the capture's photos there")
    for p in files:
        if p.suffix.lower() not in IMAGE_EXTENSIONS:
            raise LinearizeError(
                f"{p}: unknown image type '{p.suffix}'; supported: {', '.join(IMAGE_EXTENSIONS)} "
                "(remove or convert the file)"
            )
    stems: dict[str, Path] = {}
    for p in files:
        if p.stem in stems:
            raise LinearizeError(f"{p}: same name as {stems[p.stem]}; image stems must be unique")
        stems[p.stem] = p
    return files


def _check_exposure_fields(views: list[View]) -> None:
    for field in ("exposure_time", "iso", "f_number"):
        have = [getattr(v, field) is not None for v in views]
        if any(have) and not all(have):
            missing = next(v for v, h in zip(views, have, strict=True) if not h)
            raise LinearizeError(
                f"{missing.path}: no {field} in its metadata while other views have one, so its "
                "exposure cannot be matched to the rest; give every view the same metadata"
            )
        for v in views:
            val = getattr(v, field)
            if val is not None and not val > 0:
                raise LinearizeError(f"{v.path}: invalid {field} {val} in its metadata")


def _json_num(x):
    if x is None:
        return None
    if isinstance(x, Fraction):
        x = float(x)
    return float(x)


def linearize_capture(
    capture_dir: str | os.PathLike,
    out_dir: str | os.PathLike,
    settings: LinearizeSettings | None = None,
) -> dict:
    """Linearize every photo of a capture into ``out_dir`` (written atomically as one folder).

    Parameters
    ----------
    capture_dir : path-like
        The capture folder (holding ``images/``).
    out_dir : path-like
        The stage folder, ``results/<capture>/linear``; replaced on success, untouched on error.
    settings : LinearizeSettings, optional

    Returns
    -------
    dict
        The content of ``linear.json``: ``color_space``, ``scale`` (what 1.0 means),
        ``exposure_reference`` (H_ref), ``white_balance`` (mode, camera neutral, white xy),
        ``preview_gain``, ``width``, ``height`` (the linear images' size, see ``max_size``), ``source_width``, ``source_height`` (the photos'), and ``images``: per stem ``source`` (path
        relative to the capture), ``exr``, ``sat``, ``preview`` (relative to ``out_dir``),
        ``kind``, ``width``, ``height``, ``source_width``, ``source_height``, ``exposure_time``, ``iso``, ``f_number``, ``exposure``
        (H), ``exposure_scale`` (H_ref / H), ``as_shot_neutral``, ``camera_to_rec709``
        (3 x 3, RAW), ``color_matrix`` (XYZ -> camera as used), ``calibration_illuminant``,
        ``black_level``, ``white_level``, ``default_crop``, ``linearization_table``,
        ``opcodes_applied`` and ``opcodes_ignored`` (DNG opcode lists, "OpcodeListN: Name"),
        ``fraction_clipped``, ``focal_length_mm``, ``focal_length_35mm``, ``focal_length_px``
        and ``focal_length_source``.
    """
    settings = settings or LinearizeSettings()
    capture_dir = Path(capture_dir)
    out_dir = Path(out_dir)
    files = list_images(capture_dir)
    log.info("linearize %s: %d images", capture_dir, len(files))
    views = [read_meta(p) for p in files]
    kinds = sorted({v.kind for v in views})
    if len(kinds) > 1:
        first = {k: next(v.path for v in views if v.kind == k) for k in kinds}
        raise LinearizeError(
            f"{capture_dir / 'images'}: mixes image kinds ({', '.join(f'{k}: {p.name}' for k, p in first.items())}); "
            "RAW, JPEG/PNG and EXR have different radiometric scales: use one kind per capture"
        )
    kind = kinds[0]
    _check_exposure_fields(views)
    exposures = [exposure_value(v.exposure_time, v.iso, v.f_number) for v in views]
    if settings.exposure_reference == "median" or kind == "hdr":
        h_ref = float(np.median(exposures))
    else:
        h_ref = float(settings.exposure_reference)
    if kind == "hdr":  # EXR passes through unchanged
        exposures = [h_ref] * len(views)

    # ONE white balance for the capture
    matrix, white_xy, neutral = None, None, None
    if kind == "raw":
        if settings.white_balance == "fixed":
            neutral = 1.0 / np.asarray(settings.wb_multipliers, dtype=np.float64)
        else:
            neutral = np.median(np.stack([v.neutral for v in views]), axis=0)
        neutral = neutral / neutral.max()
        # same camera: the colour tags of the first view serve all
        try:
            matrix, white_xy = camera_to_rec709(views[0].color, neutral)
        except (ValueError, np.linalg.LinAlgError) as e:
            raise LinearizeError(f"{views[0].path}: unusable colour metadata ({e})") from e
    elif settings.white_balance == "fixed":
        log.info("JPEG/PNG/EXR views are already white balanced: wb_multipliers not applied")

    images: dict[str, dict] = {}
    size = None
    first_path = None
    p99 = []
    with atomic_dir(out_dir) as tmp:
        (tmp / "preview").mkdir()
        for i, (view, h) in enumerate(zip(views, exposures, strict=True)):
            rgb, clipped, levels = decode_view(view, settings, matrix)
            source_height, source_width = rgb.shape[:2]
            if size is None:
                size, first_path = (source_width, source_height), view.path
            elif (source_width, source_height) != size:
                raise LinearizeError(
                    f"{view.path}: size {source_width}x{source_height} differs from {first_path.name} "
                    f"({size[0]}x{size[1]}); every view of a capture must come from the same camera "
                    "at the same size"
                )
            width, height = working_size(source_width, source_height, settings.max_size)
            rgb, clipped = reduce_view(rgb, clipped, (width, height))
            scale = h_ref / h
            rgb *= np.float32(scale)
            if settings.clip_negative:
                np.maximum(rgb, 0.0, out=rgb)
            if not np.all(np.isfinite(rgb)):
                raise LinearizeError(f"{view.path}: linearization produced NaN/Inf values")
            write_exr(tmp / f"{view.stem}.exr", rgb, half=settings.half_float)
            write_mask(tmp / f"{view.stem}.sat.png", clipped)
            lum = rgb[~clipped] @ np.array([0.2126, 0.7152, 0.0722], np.float32)
            p99.append(float(np.percentile(lum, 99)) if lum.size else 0.0)
            frac = float(clipped.mean())
            f_px, f_src = focal_length_px(view, source_width, source_height)
            if f_px is not None:
                f_px *= width / source_width
            entry = {
                "source": os.path.relpath(view.path, capture_dir),
                "exr": f"{view.stem}.exr",
                "sat": f"{view.stem}.sat.png",
                "preview": f"preview/{view.stem}.jpg",
                "kind": view.kind,
                "width": width,
                "height": height,
                "source_width": source_width,
                "source_height": source_height,
                "exposure_time": _json_num(view.exposure_time),
                "iso": _json_num(view.iso),
                "f_number": _json_num(view.f_number),
                "exposure": h,
                "exposure_scale": scale,
                "fraction_clipped": frac,
                "focal_length_mm": _json_num(view.focal_length_mm),
                "focal_length_35mm": _json_num(view.focal_length_35mm),
                "focal_length_px": f_px,
                "focal_length_source": f_src,
                # the pixels stay as stored (every stage uses them so); the object frame's up
                # reads the orientation (recon.poses.frame)
                "orientation": view.orientation,
                "make": str(view.make) if view.make else None,
                "model": str(view.model) if view.model else None,
                **levels,
            }
            if view.kind == "raw":
                entry.update(
                    {
                        "as_shot_neutral": view.neutral.tolist(),
                        "camera_to_rec709": matrix.tolist(),
                        "color_matrix": xyz_to_camera(view.color, white_xy).tolist(),
                        "calibration_illuminant": [view.color.get("illuminant_1"), view.color.get("illuminant_2")],
                        "default_crop": list(view.default_crop) if view.default_crop else None,
                        "linearization_table": view.linearization_table_max is not None,
                        "baseline_exposure": view.baseline_exposure,
                        "opcodes_applied": view.opcodes.applied,
                        "opcodes_ignored": view.opcodes.ignored,
                        "dng": view.is_dng,
                    }
                )
            images[view.stem] = entry
            log.info(
                "linearize [%d/%d] %s: %dx%d, exposure scale %.4g, %.3f%% clipped",
                i + 1, len(views), view.path.name, width, height, scale, 100 * frac,
            )

        # previews: one gain for the capture
        if isinstance(settings.preview_exposure, str):
            ref = float(np.median(p99))
            gain = 0.9 / ref if ref > 0 else 1.0
        else:
            gain = 2.0 ** float(settings.preview_exposure)
        for view in views:
            rgb = read_exr(tmp / f"{view.stem}.exr")
            write_jpg(
                tmp / "preview" / f"{view.stem}.jpg",
                linear_to_srgb(_resize(rgb, settings.preview_max_size) * np.float32(gain)),
                quality=settings.preview_quality,
            )

        record = {
            "version": 1,
            "color_space": "linear Rec.709 (D65)",
            "scale": (
                "each view scaled to the reference exposure H_ref (H = exposure_time * iso / 100 / "
                "f_number^2); RAW: 1.0 = a neutral surface whose brightest RAW channel reaches the "
                "white level at H_ref; JPEG/PNG: 1.0 = the largest code value at H_ref; EXR: unchanged"
            ),
            "kind": kind,
            "width": width,
            "height": height,
            "source_width": size[0],
            "source_height": size[1],
            "exposure_reference": h_ref,
            "white_balance": {
                "mode": settings.white_balance if kind == "raw" else "none (already white balanced)",
                "camera_neutral": None if neutral is None else neutral.tolist(),
                "white_xy": None if white_xy is None else white_xy.tolist(),
            },
            "preview_gain": gain,
            "settings": dataclasses.asdict(settings),
            "images": images,
        }
        (tmp / "linear.json").write_text(json.dumps(record, indent=1))
    log.info("linearize %s: done -> %s", capture_dir, out_dir)
    return record


def working_size(width: int, height: int, max_size: int) -> tuple[int, int]:
    """``(width, height)`` reduced so that the longer side is at most ``max_size`` (0 = no
    limit), aspect ratio kept to the nearest pixel."""
    if max_size <= 0 or max(width, height) <= max_size:
        return width, height
    s = max_size / max(width, height)
    return max(1, round(width * s)), max(1, round(height * s))


def reduce_view(rgb: np.ndarray, clipped: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """A linear view ``(H, W, 3)`` and its clipped-pixel mask ``(H, W)`` at ``size = (w, h)``.

    Area averaging of the linear values (what a sensor with larger pixels would record; image
    edges stay at 0 and W, so a camera matrix scales by w / W and h / H per axis). An output
    pixel is clipped when any clipped photo pixel overlaps it, so no clipped value reaches a loss.
    """
    h0, w0 = rgb.shape[:2]
    if (w0, h0) == tuple(size):
        return rgb, clipped
    import cv2

    small = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
    touched = cv2.resize(clipped.astype(np.float32), size, interpolation=cv2.INTER_AREA) > 0
    return small, touched


def _resize(rgb: np.ndarray, max_size: int) -> np.ndarray:
    h, w = rgb.shape[:2]
    size = working_size(w, h, max_size)
    if size == (w, h):
        return rgb
    import cv2

    return cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
