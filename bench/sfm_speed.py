"""Benchmark: the accuracy/time trade of the SfM choices (matcher, mapper, features) on one capture.

    .venv/bin/python bench/sfm_speed.py bench/out/sfm/captures/phone80 --out bench/out/sfm
    .venv/bin/python bench/sfm_speed.py <capture> --out <dir> --variants today ordered ordered_4096
    .venv/bin/python bench/sfm_speed.py <capture> --out <dir> --table-only

1. Linearizes the capture and makes its masks (``recon.linearize`` and ``recon.masks`` with the
   pipeline's settings, into ``<out>/results/<capture>/``; once).
2. Runs the poses stage (``recon.poses.run_poses``, the function the Snakemake rule calls, with the
   settings the pipeline builds for the capture: ``recon.config.stage_settings``) once per
   variant, in this process, one after the other, without the tabletop-masks pass that follows
   SfM on a capture with a table (the same work whatever the SfM choice; ``--support-plane``
   keeps it): ``today`` is the default before issue 16
   item 4 (exhaustive matching, which ``auto`` chose up to 120 views), the others change one or
   two settings (:data:`VARIANTS`). Each run's ``poses.json`` and errors are kept in
   ``<out>/runs/<capture>/<variant>.json``; a variant already there is not run again
   (``--rerun`` runs it anyway).
3. Prints one Markdown table: wall and CPU seconds (this process's CPU time: COLMAP's threads
   included), the time of SIFT, matching and mapping, matched pairs, registered views, mean and
   max rotation error (degrees) and mean camera-centre error (percent of the object's size)
   against ``gt/cameras.json`` after a similarity fit of the centres
   (:func:`recon.metrics.pose_errors`), the mean reprojection error, the final focal length and
   silhouette consistency, and the ratios of wall time and rotation error to ``today``'s (or
   ``before_32``'s). Real photos (no ``gt/``): the errors are nan; registered views, times and
   the silhouette consistency remain (docs/sfm_speed.md, the skull). A variant's
   ``no_exif_prior`` runs without linear.json, i.e. without the EXIF focal prior.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from recon import sections
from recon import metrics  # noqa: E402
from recon.io.cameras import load_cameras  # noqa: E402
from recon.io.mesh import read_obj  # noqa: E402

NO_EXIF_PRIOR = "no_exif_prior"  # a variant key, not a setting: run_poses without linear.json (no focal prior)

VARIANTS: dict[str, dict] = {
    # the default before issue 16 item 4: auto chose exhaustive up to 120 views
    "today": {"matcher": "exhaustive"},
    # the new default for > exhaustive_max_views views (auto): 5 neighbours in capture order with
    # wrap-around + the 5 most similar views by retrieval
    "ordered": {"matcher": "ordered"},
    "ordered_k3_m3": {"matcher": "ordered", "ordered_neighbors": 3, "retrieval_neighbors": 3},
    "ordered_no_retrieval": {"matcher": "ordered", "retrieval_neighbors": 0},
    "ordered_4096": {"matcher": "ordered", "max_num_features": 4096},
    "ordered_2048": {"matcher": "ordered", "max_num_features": 2048},
    "ordered_1024px": {"matcher": "ordered", "max_image_size": 1024},
    "ordered_global": {"matcher": "ordered", "mapper": "global"},
    "ordered_incremental": {"matcher": "ordered", "mapper": "incremental"},
    "sequential": {"matcher": "sequential"},  # COLMAP's sequential pairing (overlap 15, quadratic, no loop)
    "today_4096": {"matcher": "exhaustive", "max_num_features": 4096},
    # issue 32 (sparse real photos): the defaults now, and the choices they replaced, one at a time
    "defaults": {},
    "before_32": {"guided_matching": False, "peak_threshold": 0.001, NO_EXIF_PRIOR: True},  # the defaults before
    "no_guided": {"guided_matching": False},
    "low_peak": {"peak_threshold": 0.001},
    "no_exif_prior": {NO_EXIF_PRIOR: True},
    "ordered_defaults": {"matcher": "ordered"},  # the ordered matcher (bridging groups) on a set it would not choose
}


def prepare(capture: Path, results: Path) -> tuple[Path, Path]:
    """The linearize and masks stages' outputs (made once)."""
    from recon.config import build_settings, stage_settings
    from recon.linearize import LinearizeSettings, linearize_capture
    from recon.masks import MaskSettings, run_masks

    linear, masks = results / "linear", results / "masks"
    if not (linear / "linear.json").is_file():
        t0 = time.perf_counter()
        linearize_capture(capture, linear, build_settings(LinearizeSettings, stage_settings("linearize", "balanced",
                                                                                            capture)))
        print(f"linearize: {time.perf_counter() - t0:.1f} s", flush=True)  # noqa: T201
    if not (masks / "masks.json").is_file():
        t0 = time.perf_counter()
        run_masks(linear, masks, build_settings(MaskSettings, stage_settings("masks", "balanced", capture)))
        print(f"masks: {time.perf_counter() - t0:.1f} s", flush=True)  # noqa: T201
    return linear, masks


def run_variant(name: str, capture: Path, linear: Path, masks: Path, work: Path, support_plane: bool = False) -> dict:
    from recon.config import build_settings, stage_settings
    from recon.poses import PoseSettings, run_poses
    from recon.poses import stage as poses_stage

    if not support_plane:  # the tabletop masks after SfM cost the same whatever the SfM choice
        poses_stage._support_plane_masks = lambda tmp, masks_dir: {"found": False, "reason": "skipped (bench)"}

    base = build_settings(PoseSettings, stage_settings("poses", "balanced", capture))
    variant = {k: v for k, v in VARIANTS[name].items() if k != NO_EXIF_PRIOR}
    settings = sections.replace(base, **variant)
    out = work / f"poses_{name}"
    load = os.getloadavg()
    t0, c0 = time.perf_counter(), time.process_time()
    linear_json = None if VARIANTS[name].get(NO_EXIF_PRIOR) else linear / "linear.json"
    diag = run_poses(linear, out, settings, masks_dir=masks, linear_json=linear_json)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    err = {k: float("nan") for k in ("mean_rotation_deg", "max_rotation_deg", "mean_center", "max_center")}
    size = 1.0
    if (capture / "gt" / "cameras.json").is_file():  # a synthetic capture: errors against the truth
        est = load_cameras(out / "cameras.json")
        if linear_json is None:  # cameras.json names images/<stem>: the truth's names
            true_names = {c.stem: c.image for c in load_cameras(capture / "gt" / "cameras.json")}
            est = type(est)(tuple(dataclasses.replace(c, image=true_names.get(c.stem, c.image)) for c in est),
                            est.light_intensity)
        err = metrics.pose_errors(est, load_cameras(capture / "gt" / "cameras.json"))
        gt = read_obj(capture / "gt" / "mesh.obj")
        size = float(max(gt.bbox()[1] - gt.bbox()[0]))
    t = diag["timings"]
    row = {
        "variant": name, "settings": VARIANTS[name], "wall_s": wall, "cpu_s": cpu,
        "load_before": load, "load_after": os.getloadavg(),
        "sift_s": t.get("extract_s", 0.0) + t.get("sift_images_s", 0.0), "match_s": t.get("match_s", 0.0),
        "map_s": t.get("map_s", 0.0), "timings": t, "support_plane": support_plane, "matcher": diag["matcher"], "matching": diag.get("matching", {}),
        "views": diag["views"], "registered": diag["registered"],
        "mean_rotation_deg": err["mean_rotation_deg"], "max_rotation_deg": err["max_rotation_deg"],
        "mean_center_pct": 100 * err["mean_center"] / size, "max_center_pct": 100 * err["max_center"] / size,
        "reprojection_px": diag["mean_reprojection_error_px"],
        "trials": [(tr["mapper"], tr["registered"], round(tr["seconds"], 1)) for tr in diag["trials"]],
        "unregistered": diag["unregistered"], "silhouette_consistency": diag["silhouette_consistency"],
        "focal_px": diag["camera"]["params"][0], "focal_prior": [diag["camera"]["focal_prior_px"],
                                                                 diag["camera"]["focal_prior_source"]],
        "seconds": diag["seconds"],
    }
    import shutil

    shutil.rmtree(out, ignore_errors=True)
    return row


def table(rows: list[dict]) -> str:
    ref = next((r for r in rows if r["variant"] == "today"), None) or \
        next((r for r in rows if r["variant"] == "before_32"), None)
    lines = ["| variant | pairs | wall (s) | CPU (s) | SIFT / match / map (s) | registered | rotation mean / max (deg) "
             "| centre mean (% of object) | reproj. (px) | focal (px) | silhouette | wall vs ref | rotation vs ref |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        m = r.get("matching") or {}
        n = r["views"]
        pairs = m.get("pairs", n * (n - 1) // 2 if r["matcher"] == "exhaustive" else "-")
        if m.get("exhaustive_fallback"):
            pairs = f"{pairs} + exhaustive fallback"
        ratio = (f"{r['wall_s'] / ref['wall_s']:.2f}", f"{r['mean_rotation_deg'] / ref['mean_rotation_deg']:.2f}") \
            if ref else ("-", "-")
        sil = r.get("silhouette_consistency")
        lines.append(
            f"| {r['variant']} | {pairs} | {r['wall_s']:.0f} | {r['cpu_s']:.0f} | {r['sift_s']:.0f} / {r['match_s']:.0f}"
            f" / {r['map_s']:.0f} | {r['registered']}/{n} | {r['mean_rotation_deg']:.3f} / {r['max_rotation_deg']:.3f}"
            f" | {r['mean_center_pct']:.2f} | {r['reprojection_px']:.3f} | {r.get('focal_px', float('nan')):.0f}"
            f" | {'-' if sil is None else f'{sil:.3f}'} | {ratio[0]} | {ratio[1]} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("capture", type=Path, help="a capture without cameras.json; a synthetic one's gt/cameras.json and "
                    "gt/mesh.obj give the pose errors (real photos: registered views, times, silhouette consistency)")
    ap.add_argument("--out", type=Path, default=Path("bench/out/sfm"))
    ap.add_argument("--variants", nargs="+", default=["today", "ordered", "ordered_4096", "ordered_2048",
                                                       "ordered_global", "ordered_1024px"],
                    choices=sorted(VARIANTS))
    ap.add_argument("--rerun", action="store_true", help="run variants that have a result already")
    ap.add_argument("--support-plane", action="store_true",
                    help="run the tabletop-masks pass after SfM too (minutes at 1600 px; the same for every variant)")
    ap.add_argument("--table-only", action="store_true")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    capture = args.capture.resolve()
    runs = args.out / "runs" / capture.name
    runs.mkdir(parents=True, exist_ok=True)
    if not args.table_only:
        linear, masks = prepare(capture, args.out / "results" / capture.name)
        print(f"{os.cpu_count()} cores, load average {os.getloadavg()}", flush=True)  # noqa: T201
        for name in args.variants:
            path = runs / f"{name}.json"
            if path.is_file() and not args.rerun:
                continue
            row = run_variant(name, capture, linear, masks, args.out / "work", args.support_plane)
            path.write_text(json.dumps(row, indent=1))
            print(f"{name}: {row['wall_s']:.0f} s, {row['registered']}/{row['views']} registered, rotation "  # noqa: T201
                  f"{row['mean_rotation_deg']:.3f} deg, load {row['load_before']} -> {row['load_after']}", flush=True)
    rows = [json.loads((runs / f"{v}.json").read_text()) for v in args.variants if (runs / f"{v}.json").is_file()]
    print(table(rows))  # noqa: T201
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
