"""How a reconstruction's surface error is distributed: mean (DESIGN's accuracy), median, 90th and
99th percentile, and the mean *signed* distance (negative = inside the ground truth), per mesh.

    python bench/error_profile.py GT_MESH MESH [MESH ...]

e.g. ``python bench/error_profile.py bench/out/suite/captures/smooth-diffuse/gt/mesh.obj
bench/out/suite/runs/smooth-diffuse/*/optimize/mesh.obj``. Distances are divided by the longest side
of the ground truth's bounding box, as in ``recon.metrics.chamfer`` (100,000 area-uniform samples
of each reconstruction, seed 0).

``--cameras CAPTURE/cameras.json`` adds the same numbers per coverage class: the samples are
binned by how many of the capture's cameras face the true surface at their closest point
(cosine between the true normal and the direction to the camera > 0.2; occlusion ignored, so
this is an upper bound on the views that see a point). Where few views see the surface only the
priors hold it, and that is where a regularization change shows first.
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
    p.add_argument("--cameras", help="the capture's cameras.json: also bin the errors by views facing the surface")
    p.add_argument("--bins", default="0,8,16", help="lower edges of the view-count bins (with --cameras)")
    args = p.parse_args(argv)
    import open3d as o3d

    gt = read_mesh(args.ground_truth)
    lo, hi = gt.bbox()
    unit = float(np.max(hi - lo))
    inside = o3d.t.geometry.RaycastingScene()
    inside.add_triangles(o3d.core.Tensor(gt.v_pos.astype(np.float32)), o3d.core.Tensor(gt.t_pos_idx.astype(np.uint32)))
    centers = None
    if args.cameras:
        from recon.io.cameras import load_cameras

        centers = np.array([f.center for f in load_cameras(args.cameras).frames])
        edges = [int(b) for b in args.bins.split(",")]
    print(f"{'mesh':60s} {'faces':>7s} {'mean':>9s} {'median':>9s} {'p90':>9s} {'p99':>9s} {'signed':>10s}")  # noqa: T201
    for path in args.meshes:
        m = read_mesh(path)
        pts = m.sample_surface(args.samples, np.random.default_rng(0))
        d = distance_to_mesh(gt, pts) / unit
        occ = inside.compute_occupancy(o3d.core.Tensor(pts.astype(np.float32))).numpy() > 0
        signed = np.where(occ, -d, d)
        print(f"{path[-60:]:60s} {len(m.t_pos_idx):7d} {d.mean():9.6f} {np.median(d):9.6f} "  # noqa: T201
              f"{np.percentile(d, 90):9.6f} {np.percentile(d, 99):9.6f} {signed.mean():+10.6f}")
        if centers is not None:
            normal = inside.compute_closest_points(o3d.core.Tensor(pts.astype(np.float32)))["primitive_normals"].numpy()
            to_cam = centers[None] - pts[:, None]
            to_cam /= np.linalg.norm(to_cam, axis=2, keepdims=True)
            views = (np.einsum("pk,pck->pc", normal, to_cam) > 0.2).sum(1)
            for lo_v, hi_v in zip(edges, [*edges[1:], len(centers) + 1], strict=True):
                sel = (views >= lo_v) & (views < hi_v)
                if sel.any():
                    print(f"    facing views {lo_v:2d}-{hi_v - 1:2d}: {100 * sel.mean():5.1f} % of the surface, "  # noqa: T201
                          f"mean {d[sel].mean():9.6f}, signed {signed[sel].mean():+10.6f}, "
                          f"{100 * d[sel].sum() / d.sum():5.1f} % of the error")
    return 0


if __name__ == "__main__":
    sys.exit(main())
