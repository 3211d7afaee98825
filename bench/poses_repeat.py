"""Benchmark: how often SfM gives a right model, over repeated runs of the poses stage.

Runs ``recon.poses.run_poses`` N times on one capture's linearize/masks outputs and prints per
run: the mapping trials (mapper, views registered, silhouette consistency), the chosen trial,
the final consistency and reprojection error, and the rotation error against reference cameras
(default: the capture's own ``poses/cameras.json``, i.e. consistency with an earlier run).
A wrong model shows as tens of degrees of rotation error.

Run after the demo: ``.venv/bin/python bench/poses_repeat.py results/demo --runs 8``
(about 4 s per run on the demo). The behaviour before session 3's fixes:
``git checkout 6d9bc25 -- recon/poses.py``, run, ``git checkout HEAD -- recon/poses.py``.
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from recon import metrics  # noqa: E402
from recon.io.cameras import CameraSet, load_cameras  # noqa: E402
from recon.poses import PoseSettings, run_poses  # noqa: E402


def _subset(cams: CameraSet, stems: set) -> CameraSet:
    return CameraSet(tuple(c for c in cams if c.stem in stems), cams.light_intensity)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results", type=Path, help="results/<capture> with linear/ and masks/")
    ap.add_argument("--runs", type=int, default=8)
    ap.add_argument("--reference", type=Path, default=None, help="cameras.json to compare with")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    ref = load_cameras(args.reference or args.results / "poses" / "cameras.json")
    wrong = 0
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.runs):
            out = Path(tmp) / f"poses{i}"
            d = run_poses(args.results / "linear", out, PoseSettings(), masks_dir=args.results / "masks",
                          linear_json=args.results / "linear" / "linear.json")
            est = load_cameras(out / "cameras.json")
            common = {c.stem for c in est} & {c.stem for c in ref}
            e = metrics.pose_errors(_subset(est, common), _subset(ref, common))
            wrong += e["mean_rotation_deg"] > 5.0
            trials = ", ".join(f"{t['mapper']} {t['registered']}"
                               + (f" ({t['silhouette_consistency']:.3f})" if t.get("silhouette_consistency") else "")
                               for t in d["trials"])
            sil = d.get("silhouette_consistency")
            sys.stdout.write(f"run {i}: trials [{trials}] chosen {d.get('chosen_trial')}, consistency "
                             f"{'-' if sil is None else f'{sil:.3f}'}, reprojection "
                             f"{d['mean_reprojection_error_px']:.3f} px, rotation error "
                             f"{e['mean_rotation_deg']:.2f} deg mean\n")
            sys.stdout.flush()
            shutil.rmtree(out, ignore_errors=True)
    sys.stdout.write(f"{wrong} of {args.runs} runs wrong (mean rotation error > 5 deg)\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
