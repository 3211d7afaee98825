"""The poses stage's inputs: the linearize stage's views and ``linear.json``, the masks."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from recon.io.images import read_mask
from recon.poses.settings import PoseError

log = logging.getLogger(__name__)


def linear_stems(linear_dir: Path) -> list[str]:
    """The stems of the linearize stage's views (``<stem>.exr``), sorted."""
    stems = sorted(p.stem for p in linear_dir.glob("*.exr") if not p.name.startswith("."))
    if not stems:
        raise PoseError(f"{linear_dir}: no linear images (<stem>.exr); run the linearize stage first")
    return stems


def _linear_entries(linear_json: Path | None) -> dict[str, dict]:
    """Per-view metadata of ``linear.json`` keyed by stem (tolerant of list or dict layouts)."""
    if linear_json is None or not Path(linear_json).is_file():
        return {}
    try:
        data = json.loads(Path(linear_json).read_text())
    except json.JSONDecodeError as e:
        raise PoseError(f"{linear_json}: not valid JSON ({e}); rerun the linearize stage") from e
    items = None
    for key in ("images", "views", "frames"):
        if isinstance(data.get(key), (dict, list)):
            items = data[key]
            break
    out = {}
    if isinstance(items, dict):
        out = {Path(k).stem: v for k, v in items.items() if isinstance(v, dict)}
    elif isinstance(items, list):
        for v in items:
            if isinstance(v, dict):
                name = v.get("stem") or v.get("image") or v.get("source") or v.get("file")
                if name:
                    out[Path(str(name)).stem] = v
    return out


_FOCAL_KEYS = ("focal_length_px", "focal_px", "focal_length_pixels", "f_px")


def focal_prior(linear_json: Path | None, stems: list[str]) -> float | None:
    """Median focal length in pixels from ``linear.json`` when every view agrees within 1%."""
    entries = _linear_entries(linear_json)
    vals = []
    for s in stems:
        e = entries.get(s, {})
        v = next((e[k] for k in _FOCAL_KEYS if isinstance(e.get(k), (int, float)) and e[k] > 0), None)
        if v is not None:
            vals.append(float(v))
    if not vals:
        return None
    f = float(np.median(vals))
    if max(vals) > 1.01 * min(vals):
        log.warning("focal lengths differ between views (%.1f..%.1f px): no prior used", min(vals), max(vals))
        return None
    return f


def given_focal(linear_json: Path | None, focal_px: float) -> float:
    """``focal_px`` (pixels of the photos at their full size) in pixels of the linear views: scaled
    by their width over the photos' (``linear.json``'s ``width`` / ``source_width``; the
    linearize stage may reduce large photos)."""
    data = {}
    if linear_json is not None and Path(linear_json).is_file():
        try:
            data = json.loads(Path(linear_json).read_text())
        except json.JSONDecodeError as e:
            raise PoseError(f"{linear_json}: not valid JSON ({e}); rerun the linearize stage") from e
    w, w0 = data.get("width"), data.get("source_width")
    if isinstance(w, (int, float)) and isinstance(w0, (int, float)) and w > 0 and w0 > 0:
        return float(focal_px) * float(w) / float(w0)
    return float(focal_px)


def prior_focal(settings, linear_json: Path | None, stems: list[str]) -> tuple[float | None, str | None]:
    """(the focal length prior in pixels of the linear views, its source): ``poses.camera.focal_px``
    (a calibration) when set, else the photos' EXIF (:func:`focal_prior`; the source names the
    tags, linear.json's ``focal_length_source``: "EXIF (35mm_equivalent)", "EXIF
    (focal_plane_resolution)"), else (None, None)."""
    if settings.camera.focal_px is not None:
        return given_focal(linear_json, settings.camera.focal_px), "poses.camera.focal_px"
    f = focal_prior(linear_json, stems)
    if f is None:
        return None, None
    entries = _linear_entries(linear_json)
    kinds = sorted({str(entries[s]["focal_length_source"]) for s in stems
                    if entries.get(s, {}).get("focal_length_source")})
    return f, "EXIF" + (f" ({', '.join(kinds)})" if kinds else "")


def prior_sigma(settings, source: str | None) -> float:
    """The relative standard deviation of a focal length prior from ``source``
    (:func:`prior_focal`): ``focal_plane_prior_sigma`` for EXIF's focal plane resolution (a
    DSLR's, a few percent off), ``focal_prior_sigma`` otherwise."""
    if source is not None and "focal_plane_resolution" in source:
        return float(settings.camera.focal_plane_prior_sigma)
    return float(settings.camera.focal_prior_sigma)


def image_names(linear_json: Path | None, stems: list[str]) -> dict[str, str]:
    """The capture image path (``images/<file>``) of each stem, as cameras.json records it."""
    entries = _linear_entries(linear_json)
    out = {}
    for s in stems:
        e = entries.get(s, {})
        name = next((e[k] for k in ("image", "source", "file") if isinstance(e.get(k), str)), None)
        if name is None:
            out[s] = f"images/{s}"
        else:
            out[s] = name if "/" in name else f"images/{name}"
    return out


def view_orientations(linear_json: Path | None, stems: list[str]) -> dict[str, int]:
    """The EXIF Orientation of each stem's photo where linear.json records one other than upright."""
    entries = _linear_entries(linear_json)
    out = {}
    for s in stems:
        o = entries.get(s, {}).get("orientation")
        if isinstance(o, int) and 2 <= o <= 8:
            out[s] = o
    return out


def read_masks(masks_dir: Path | None, stems: list[str]) -> dict[str, np.ndarray]:
    """The masks stage's masks of ``stems`` (stem -> (H, W) bool); views without one are left out."""
    if masks_dir is None:
        return {}
    return {s: read_mask(Path(masks_dir) / f"{s}.png") for s in stems if (Path(masks_dir) / f"{s}.png").is_file()}
