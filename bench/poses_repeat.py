"""Benchmark: how often SfM gives a right model, over repeated runs of the poses stage.

Runs ``recon.poses.run_poses`` N times on one capture's linearize/masks outputs and prints per
run: the mapping trials (mapper, views registered, silhouette consistency), the chosen trial,
the final consistency and reprojection error, and the rotation error against reference cameras
(default: the capture's own ``poses/cameras.json``, i.e. consistency with an earlier run).
A wrong model shows as tens of degrees of rotation error.

Run after the demo: ``.venv/bin/python bench/poses_repeat.py results/demo --runs 8``
(about 4 s per run on the demo).

Run-to-run spread of the cameras themselves (tests/workflow/test_slurm.py's bounds): each run also
prints the largest rotation and centre difference of a view in the object frame, with no
alignment (the poses stage's contract), against the reference. ``--threads N`` sets
``poses.num_threads`` of the runs; ``--reference-threads N`` makes the reference by one run with N
threads first (1: COLMAP's deterministic order)::

    .venv/bin/python bench/poses_repeat.py results/demo --runs 8 --threads 2 --reference-threads 1 The behaviour before session 3's fixes:
``git checkout 6d9bc25 -- recon/poses.py``, run, ``git checkout HEAD -- recon/poses.py``.
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from recon import metrics  # noqa: E402
from recon.metrics import Similarity  # noqa: E402
from recon.io.cameras import CameraSet, load_cameras  # noqa: E402
from recon.poses import PoseSettings, run_poses  # noqa: E402


def _subset(cams: CameraSet, stems: set) -> CameraSet:
    return CameraSet(tuple(c for c in cams if c.stem in stems), cams.light_intensity)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results", type=Path, help="results/<capture> with linear/ and masks/")
    ap.add_argument("--runs", type=int, default=8)
    ap.add_argument("--reference", type=Path, default=None, help="cameras.json to compare with")
    ap.add_argument("--threads", type=int, default=-1, help="poses.num_threads of the runs (-1: every core)")
    ap.add_argument("--reference-threads", type=int, default=None,
                    help="make the reference by one run with this many threads first")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)

    def poses(out: Path, threads: int) -> dict:
        return run_poses(args.results / "linear", out, PoseSettings(num_threads=threads),
                         masks_dir=args.results / "masks", linear_json=args.results / "linear" / "linear.json")

    wrong = 0
    with tempfile.TemporaryDirectory() as tmp:
        if args.reference_threads is not None:
            poses(Path(tmp) / "reference", args.reference_threads)
            ref = load_cameras(Path(tmp) / "reference" / "cameras.json")
        else:
            ref = load_cameras(args.reference or args.results / "poses" / "cameras.json")
        for i in range(args.runs):
            out = Path(tmp) / f"poses{i}"
            t0 = time.perf_counter()
            d = poses(out, args.threads)
            wall = time.perf_counter() - t0
            est = load_cameras(out / "cameras.json")
            common = {c.stem for c in est} & {c.stem for c in ref}
            e = metrics.pose_errors(_subset(est, common), _subset(ref, common))
            raw = metrics.pose_errors(_subset(est, common), _subset(ref, common), Similarity.identity())
            wrong += e["mean_rotation_deg"] > 5.0
            trials = ", ".join(f"{t['mapper']} {t['registered']}"
                               + (f" ({t['silhouette_consistency']:.3f})" if t.get("silhouette_consistency") else "")
                               for t in d["trials"])
            sil = d.get("silhouette_consistency")
            sys.stdout.write(f"run {i} ({wall:.0f} s): trials [{trials}] chosen {d.get('chosen_trial')}, consistency "
                             f"{'-' if sil is None else f'{sil:.3f}'}, reprojection "
                             f"{d['mean_reprojection_error_px']:.3f} px, rotation error "
                             f"{e['mean_rotation_deg']:.2f} deg mean; in the object frame: views "
                             f"{len(common)}/{len(ref)}, max {raw['max_rotation_deg']:.4f} deg, max centre "
                             f"{raw['max_center']:.5f} (the frames' similarity: scale {e['similarity']['scale']:.4f}, "
                             f"rotation {metrics.rotation_angle_deg(np.asarray(e['similarity']['rotation'])):.3f} deg, "
                             f"shift {np.linalg.norm(e['similarity']['translation']):.4f})\n")
            sys.stdout.flush()
            shutil.rmtree(out, ignore_errors=True)
    sys.stdout.write(f"{wrong} of {args.runs} runs wrong (mean rotation error > 5 deg)\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
