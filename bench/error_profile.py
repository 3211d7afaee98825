"""How a reconstruction's surface error is distributed: mean (DESIGN's accuracy), median, 90th and
99th percentile, and the mean *signed* distance (negative = inside the ground truth), per mesh.

    python bench/error_profile.py GT_MESH MESH [MESH ...]

e.g. ``python bench/error_profile.py bench/out/suite/captures/smooth-diffuse/gt/mesh.obj
bench/out/suite/runs/smooth-diffuse/*/optimize/mesh.obj``. Distances are divided by the longest side
of the ground truth's bounding box, as in ``recon.metrics.chamfer`` (100,000 area-uniform samples
of each reconstruction, seed 0).
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from recon.io.mesh import read_mesh  # noqa: E402
from recon.metrics import distance_to_mesh  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("ground_truth")
    p.add_argument("meshes", nargs="+")
    p.add_argument("--samples", type=int, default=100_000)
    args = p.parse_args(argv)
    import open3d as o3d

    gt = read_mesh(args.ground_truth)
    lo, hi = gt.bbox()
    unit = float(np.max(hi - lo))
    inside = o3d.t.geometry.RaycastingScene()
    inside.add_triangles(o3d.core.Tensor(gt.v_pos.astype(np.float32)), o3d.core.Tensor(gt.t_pos_idx.astype(np.uint32)))
    print(f"{'mesh':60s} {'faces':>7s} {'mean':>9s} {'median':>9s} {'p90':>9s} {'p99':>9s} {'signed':>10s}")  # noqa: T201
    for path in args.meshes:
        m = read_mesh(path)
        pts = m.sample_surface(args.samples, np.random.default_rng(0))
        d = distance_to_mesh(gt, pts) / unit
        occ = inside.compute_occupancy(o3d.core.Tensor(pts.astype(np.float32))).numpy() > 0
        signed = np.where(occ, -d, d)
        print(f"{path[-60:]:60s} {len(m.t_pos_idx):7d} {d.mean():9.6f} {np.median(d):9.6f} "  # noqa: T201
              f"{np.percentile(d, 90):9.6f} {np.percentile(d, 99):9.6f} {signed.mean():+10.6f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
