"""The table's points in kept SfM runs: what the plane search and the two checks of masks that
hold the table read on each, with the object's foot counted (as before session 29) and left out.

For each results folder (of ``snakemake ... all`` by SfM): the support plane found in
``poses/points.ply`` (:func:`recon.support.fit_support_plane`: found or why not, its points beyond
the object's outline, the share of them with the object under them), then, on that plane, the
masks stage's check (:func:`recon.masks.views.table_points_share`: the table's points inside the
masks over the views' frames) and the poses stage's (:func:`recon.poses.stage.table_points_in_masks`:
SfM's observations of them inside their view's mask), of the run's ``poses/undistorted/masks``
and of masks of the whole frame, each with ``foot=0`` and with the default foot radius. When no
plane is found now, the checks are read on the plane the search finds with
``min_table_points=0`` (the one it found before). docs/tabletop.md, "Session 29".

    .venv/bin/python bench/table_points.py RESULTS/<capture> [...]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from recon.io.cameras import load_cameras
from recon.io.images import read_mask
from recon.io.mesh import read_points
from recon.masks.views import table_points_share
from recon.metrics import Similarity
from recon.poses.stage import table_points_in_masks
from recon.support import FOOT_RADIUS, TABLE_TOLERANCE, PlaneSettings, camera_spread, fit_support_plane


def row(run: Path) -> dict:
    import pycolmap

    cams = load_cameras(run / "poses" / "cameras.json")
    pts = read_points(run / "poses" / "points.ply")
    plane, info = fit_support_plane(pts, cams)
    out = {"run": run.name, "plane": plane is not None, "reason": info["reason"],
           "beyond_object_points": info.get("beyond_object_points"), "object_under": info.get("object_under")}
    if plane is None:
        plane, old = fit_support_plane(pts, cams, dataclasses.replace(PlaneSettings(), min_table_points=0))
        if plane is None:
            return out
        out["checks_on"] = "the plane found before session 29"
    f = json.loads((run / "poses" / "frame.json").read_text())["colmap_to_object"]
    sim = Similarity(f["scale"], np.array(f["rotation"]), np.array(f["translation"]))
    rec = pycolmap.Reconstruction(str(run / "poses" / "sparse"))
    masks = {c.stem: read_mask(run / "poses" / "undistorted" / "masks" / f"{c.stem}.png") > 0.5 for c in cams}
    whole = {s: np.ones_like(m) for s, m in masks.items()}
    spread = camera_spread([c.center for c in cams])
    for name, m in (("masks", masks), ("whole_frame", whole)):
        for foot in (0.0, FOOT_RADIUS):
            key = f"{name}_foot_{'counted' if foot == 0 else 'left_out'}"
            out[f"masks_stage_{key}"] = table_points_share(pts, plane, cams, m, foot=foot)
            out[f"poses_stage_{key}"] = table_points_in_masks(rec, sim, plane, cams, m, TABLE_TOLERANCE * spread,
                                                              foot * spread)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, help="results folders (RESULTS/<capture>) of SfM runs")
    for run in ap.parse_args().runs:
        print(json.dumps({k: (round(v, 3) if isinstance(v, float) else v) for k, v in row(run).items()}), flush=True)  # noqa: T201 (the CLI's output)


if __name__ == "__main__":
    main()
