"""Benchmark: SfM cameras against the true cameras on a phone capture, the whole workflow
(issue 17's target: "with SfM cameras, final accuracy within 1.2x of the same capture with
exact cameras").

One synthetic phone capture (``recon.synth``: the ``phone`` preset's JPEGs with tone curve,
exposure jitter, white-balance jitter, vignetting, the flash 1 cm beside the lens and ambient
light; ``--scene tabletop`` by default: the object standing on a textured table, views from
rings above it; no masks), run through the whole workflow (Snakemake up to
``report/metrics.json``) three ways:

- ``given``: the capture's true ``cameras.json`` (exact by contract; SfM skipped);
- ``sfm``: the same photos without ``cameras.json``: COLMAP's cameras, refined by the renderer
  as the preset says (``cameras.refine: select`` in balanced and accurate: the held-out views
  decide);
- ``sfm_refine_off``: the same with ``cameras.refine: off`` (what the refinement changes).

Printed per run, from the report (DESIGN section 5; SfM runs aligned to the truth by the
similarity of the camera centres): accuracy and completeness in the unit bounding box and their
ratio to ``given``; the pose errors after that similarity (rotation, centre / object size) and
the focal length's error; as a diagnostic, the accuracy after the similarity that best fits the
surface to the truth (ICP; ``object frame``) and the size of that correction: how much of the
gap is the frame that the camera centres fix, not the shape; and the accuracy the true mesh
itself scores when placed by that frame error (what a perfect shape would score under the
camera-centre alignment); the camera refinement's decision;
the poses and optimize stages' seconds.

    .venv/bin/python bench/sfm_cameras.py --out /tmp/sfm_cameras --preset balanced --res 640
    .venv/bin/python bench/sfm_cameras.py --out /tmp/sfm_alone --preset balanced --scene void \
        --seed 3 --sift-upsample 2 --runs given,sfm      # the object alone (docs/camera_refine.md)

Captures and runs are cached in ``<out>``; Snakemake redoes nothing that is done.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from camera_refine import object_frame  # noqa: E402  (the sibling benches' diagnostic and run folders)
from phone_geometry import run_folder  # noqa: E402
from tabletop_e2e import snakemake  # noqa: E402

from recon import sections  # noqa: E402
from recon.io.cameras import load_cameras  # noqa: E402
from recon.io.mesh import Mesh, read_mesh  # noqa: E402
from recon.metrics import Similarity, chamfer, seen_chamfer, umeyama  # noqa: E402
from recon.synth.capture import PRESETS  # noqa: E402

log = logging.getLogger("bench.sfm_cameras")
RUNS = {"given": {}, "sfm": {}, "sfm_refine_off": {"cameras": {"refine": "off"}}}


def make(root: Path, args) -> Path:
    from recon.synth.capture import make_capture

    cap = root / "capture"
    if not (cap / "cameras.json").is_file():
        s = sections.replace(PRESETS["phone"], scene=args.scene, fov=args.fov, distance=args.distance,
                                n_views=args.views, width=args.res, height=int(round(args.res * 3 / 4 / 2)) * 2,
                                spp=args.spp, seed=args.seed, write_cameras=True, write_masks=False,
                                write_gt_linear=False)
        make_capture(cap, s)
    return cap


def measure(res: Path, cap: Path) -> dict:
    m = json.loads((res / "report" / "metrics.json").read_text())
    s = json.loads((res / "optimize" / "summary.json").read_text())
    mm = m["metrics"]
    gt_mesh = read_mesh(cap / "gt" / "mesh.obj")
    gt_cams = load_cameras(cap / "gt" / "cameras.json")
    est = load_cameras(res / "poses" / "cameras.json")
    f_true = {c.stem: c.K[0, 0] for c in gt_cams.frames}
    focal = float(np.mean([c.K[0, 0] / f_true[c.stem] - 1.0 for c in est.frames]))
    sim_d = mm["alignment"]["similarity"]
    sim = Similarity(sim_d["scale"], np.asarray(sim_d["rotation"]), np.asarray(sim_d["translation"]))
    mesh = read_mesh(res / "optimize" / "mesh.obj")
    v = sim.apply(mesh.v_pos)
    v_obj, frame = object_frame(v, mesh, gt_mesh)
    obj = chamfer(Mesh(v_obj, mesh.t_pos_idx), gt_mesh, n_samples=100_000, seed=0)
    # the frame's share: the true mesh placed where the camera-centre alignment puts this run's
    # shape (moved by the inverse of the surface fit), i.e. what a perfect shape would score
    placed = Mesh(umeyama(v_obj, v).apply(gt_mesh.v_pos), gt_mesh.t_pos_idx)
    frame["perfect_shape_accuracy"] = chamfer(placed, gt_mesh, n_samples=100_000, seed=0)["accuracy"]
    seen = seen_chamfer(Mesh(v, mesh.t_pos_idx), gt_mesh, gt_cams)
    cam = m.get("camera_refinement") or {}
    pe = mm.get("pose_errors") or {}
    lo, hi = gt_mesh.bbox()
    size = float(np.max(hi - lo))
    return {"accuracy": mm.get("accuracy"), "completeness": mm.get("completeness"),
            "accuracy_object_frame": obj["accuracy"], "frame_error": frame, **seen,
            "registered": len(est.frames), "views": len(gt_cams.frames),
            "rotation_deg": pe.get("mean_rotation_deg"), "center": (pe.get("mean_center") or 0.0) / size,
            "focal": focal, "camera_mode": cam.get("mode"), "camera_refined": cam.get("refined"),
            "camera_selection": cam.get("selection"),
            "poses_seconds": m["timings"]["stages"].get("poses"),
            "optimize_seconds": s.get("wall_seconds")}


def table(results: dict) -> str:
    g = results.get("given") or {}
    rows = ["| cameras | registered | rot. error (deg) | centre error (% object) | focal error (%) | accuracy | "
            "ratio to given | completeness | ratio | seen surface: accuracy, ratio / completeness, ratio | object frame: accuracy, ratio (frame error: % object, scale %) | "
            "a perfect shape in this frame: accuracy | "
            "renderer's refinement | poses s | optimize s |", "|" + "---|" * 15]
    for run, r in results.items():
        def ratio(k, r=r):
            return f"{r[k] / g[k]:.2f}" if g.get(k) else "-"
        sel = r.get("camera_selection") or {}
        refine = r.get("camera_mode") or "-"
        if sel:
            refine += f": {'kept' if r.get('camera_refined') else 'rejected'} (gain {sel.get('gain', 0):+.5f}, SE {sel.get('se', 0):.5f})"
        fe = r["frame_error"]
        rows.append(f"| {run} | {r['registered']}/{r['views']} | {r['rotation_deg']:.3f} | {100 * r['center']:.2f} | "
                    f"{100 * r['focal']:+.2f} | {r['accuracy']:.5f} | {ratio('accuracy')} | {r['completeness']:.5f} | "
                    f"{ratio('completeness')} | {r['accuracy_seen']:.5f}, {ratio('accuracy_seen')} / "
                    f"{r['completeness_seen']:.5f}, {ratio('completeness_seen')} | {r['accuracy_object_frame']:.5f}, {ratio('accuracy_object_frame')} "
                    f"({100 * fe['translation']:.2f}, {100 * fe['scale']:+.2f}) | "
                    f"{fe.get('perfect_shape_accuracy', float('nan')):.5f} | {refine} | "
                    f"{r['poses_seconds'] or 0:.0f} | {r['optimize_seconds'] or 0:.0f} |")
    return "\n".join(rows)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--preset", default="balanced")
    p.add_argument("--scene", default="tabletop", choices=("void", "tabletop"))
    p.add_argument("--views", type=int, default=40)
    p.add_argument("--res", type=int, default=640, help="photo width (height 3/4 of it)")
    p.add_argument("--fov", type=float, default=50.0)
    p.add_argument("--distance", type=float, default=5.0)
    p.add_argument("--spp", type=int, default=16)
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--runs", default=",".join(RUNS))
    p.add_argument("--sift-upsample", type=int, default=1,
                   help="poses.sift_upsample of the SfM runs (2: SIFT on 2x enlarged images, config/README.md)")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    root = args.out
    cap = make(root, args)
    runs = [r for r in args.runs.split(",") if r]
    unknown = set(runs) - set(RUNS)
    if unknown:
        p.error(f"unknown runs {sorted(unknown)}; choose from {sorted(RUNS)}")
    for r in runs:
        sfm = r != "given"
        run_folder(root, r, cap, RUNS[r], args.preset, leave_out=("cameras.json",) if sfm else (),
                   poses={"sift_upsample": args.sift_upsample} if sfm and args.sift_upsample != 1 else None)
    results_dir = root / "results"
    for r in runs:  # one at a time: each run's wall times are its own
        log.info("run %s: %.0f s", r, snakemake(root / "runs", results_dir,
                                                 [f"{results_dir}/{r}/report/metrics.json"], args.preset))
    results = {}
    for r in runs:
        try:
            results[r] = measure(results_dir / r, cap)
        except FileNotFoundError as e:
            log.warning("run %s has no results (%s); see %s", r, e, results_dir / "snakemake.log")
    out = {"settings": vars(args) | {"out": str(root)}, "results": results}
    (root / "sfm_cameras.json").write_text(json.dumps(out, indent=1, default=str))
    md = table(results)
    (root / "sfm_cameras.md").write_text(md + "\n")
    print(md)  # noqa: T201 (a command line tool's report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
