"""Stage ``masks``: one object mask per view (DESIGN section 2), before any camera is known.

Given masks (``<capture>/masks/<stem>.png``) are used as they are (:mod:`recon.masks.given`);
every other view gets a flash-falloff mask (:mod:`recon.masks.falloff`). With cameras (the
poses stage's, or the capture's ``cameras.json``), :func:`recon.masks.views.run_view_masks`
makes the masks again, consistent across the views (``run_masks(..., cameras=...)`` calls it).
"""

from __future__ import annotations

import json
import logging
import os
import time
from dataclasses import asdict
from pathlib import Path

from recon.io.atomic import atomic_dir
from recon.io.images import ImageError, read_exr, read_mask, write_mask
from recon.masks.common import MaskError
from recon.masks.falloff import WHITE_LEVEL_KINDS, MaskSettings, derive_mask
from recon.masks.given import fit_given_mask

log = logging.getLogger(__name__)


def list_linear_stems(linear_dir: str | os.PathLike) -> list[str]:
    """Stems of the linear images ``<stem>.exr`` in ``linear_dir`` (sorted)."""
    linear_dir = Path(linear_dir)
    stems = sorted(p.stem for p in linear_dir.glob("*.exr") if not p.name.startswith("."))
    if not stems:
        raise MaskError(f"{linear_dir}: no linear images (<stem>.exr); run the linearize stage first")
    return stems


def _linear_record(linear_dir: Path) -> dict:
    """The linearize stage's ``linear.json`` (empty when absent or unreadable: it is optional here)."""
    path = linear_dir / "linear.json"
    if not path.is_file():
        return {}
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        log.warning("%s: not readable (%s); treating the views as EXR (unknown white level)", path, e)
        return {}
    return record if isinstance(record, dict) else {}


def run_masks(
    linear_dir: str | os.PathLike,
    out_dir: str | os.PathLike,
    settings: MaskSettings | None = None,
    given_dir: str | os.PathLike | None = None,
    stems: list[str] | None = None,
    cameras: str | os.PathLike | None = None,
    points: str | os.PathLike | None = None,
    segment_settings=None,
) -> dict:
    """Write ``out_dir/<stem>.png`` for every view and ``out_dir/masks.json`` (per-view info).

    Parameters
    ----------
    linear_dir : folder with the linearize stage's ``<stem>.exr``.
    out_dir : the stage folder ``results/<capture>/masks``; replaced atomically.
    given_dir : the capture's ``masks/`` folder, if any: ``<stem>.png`` found there is used
        unchanged (after a size check); views without one get a derived mask.
    stems : the views; default all ``<stem>.exr`` in ``linear_dir``.
    cameras : a ``cameras.json`` of pinhole views ``linear_dir/<stem>.exr`` (the capture's own,
        or the poses stage's with its ``undistorted/`` folder as ``linear_dir``): the masks
        separate an object standing on a table from the table (:func:`recon.masks.views.run_tabletop_masks`,
        which keeps this module's masks, with a note, when no support plane is found) and
        ``out_dir/plane.json`` records the plane. ``stems`` is then the cameras' views.
    points : with ``cameras``: sparse points in their frame (``poses/points.ply``) to find the
        plane in; without, points are triangulated from the views.
    segment_settings : with ``cameras``: a :class:`recon.masks.views.SegmentSettings`.

    Returns
    -------
    The summary written to ``masks.json``.
    """
    settings = MaskSettings() if settings is None else settings
    if cameras is not None:
        from recon.masks.views import SegmentSettings, run_tabletop_masks

        return run_tabletop_masks(linear_dir, cameras, out_dir, segment_settings or SegmentSettings(),
                                  points=points, given_dir=given_dir, mask_settings=settings)
    linear_dir = Path(linear_dir)
    stems = list(stems) if stems is not None else list_linear_stems(linear_dir)
    record = _linear_record(linear_dir)
    white = 1.0 if record.get("kind") in WHITE_LEVEL_KINDS else None
    given = Path(given_dir) if given_dir is not None else None
    t0 = time.perf_counter()
    views = {}
    with atomic_dir(out_dir) as tmp:
        for stem in stems:
            exr = linear_dir / f"{stem}.exr"
            try:
                img = read_exr(exr)
            except ImageError as e:
                raise MaskError(f"{e}; rerun the linearize stage") from e
            given_png = given / f"{stem}.png" if given is not None else None
            if given_png is not None and given_png.is_file():
                mask = fit_given_mask(read_mask(given_png), given_png, img.shape[1::-1])
                if not mask.any():  # (recon.validate refuses it first; this covers a later edit)
                    raise MaskError(f"{given_png}: the mask is empty (every pixel 0), so it shows no object; draw "
                                    "the object (nonzero pixels) or delete the file to let this stage derive it")
                info = {"source": "given", "coverage": float(mask.mean())}
            else:
                try:
                    mask, info = derive_mask(img, settings, white_level=white)
                except MaskError as e:
                    source = (record.get("images") or {}).get(stem, {}).get("source")
                    where = f"{source} ({exr})" if source else str(exr)
                    raise MaskError(f"no object found in {where}: {e} (or provide masks/{stem}.png "
                                    "in the capture)") from e
                info["source"] = "derived"
            if not settings.min_coverage <= info["coverage"] <= settings.max_coverage:
                log.warning(
                    "%s: mask covers %.2f%% of the image; check it (or give masks/%s.png)",
                    stem, 100 * info["coverage"], stem,
                )
            write_mask(tmp / f"{stem}.png", mask)
            views[stem] = info
            log.info("%s: %s mask, %.1f%% of the image", stem, info["source"], 100 * info["coverage"])
        summary = {
            "method": "flash_falloff",
            "views": views,
            "settings": asdict(settings),
            "seconds": time.perf_counter() - t0,
        }
        (tmp / "masks.json").write_text(json.dumps(summary, indent=1))
    return summary
