"""Masks of objects standing on a table: the tabletop method (recon.segment) against today's
flash-falloff masks (recon.masks) on the same images, IoU against the synthetic ground truth.

For each object (``--objects``, default ``blob mug``):

1. makes the capture ``python -m recon synth <out>/captures/<object> --preset tabletop-<object>``
   (with ``--views/--res/--spp/--format`` when given; only when missing),
2. linearizes it (``recon.linearize.linearize_capture``),
3. today's masks: ``recon.masks.run_masks`` on the linear images,
4. tabletop masks with the true cameras (``gt/cameras.json``; the plane from points triangulated
   in the views): ``recon.segment.run_tabletop_masks``,
5. with ``--sfm``: SfM (``recon.poses.run_poses``, today's masks as its masks) and the tabletop
   masks on its undistorted views, cameras and sparse points (the plane from the SfM points),
6. a void capture of the same object (``--preset <object>``-like, same views and size, masks in
   the capture's gt): today's masks and ``run_tabletop_masks`` (which must find no plane and keep
   today's masks) - the void captures must not get worse.

Prints per capture and method: IoU mean, the worst view, per-view min/mean, seconds, and the
ratio to today's masks; writes ``<out>/tabletop.json``.

    .venv/bin/python bench/tabletop.py --out bench/out/tabletop [--sfm] [--objects blob mug]
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from recon import sections
from recon.io.cameras import load_cameras  # noqa: E402
from recon.io.images import read_mask  # noqa: E402
from recon.synth.capture import PRESETS, make_capture  # noqa: E402

log = logging.getLogger("bench.tabletop")


def iou_per_view(masks_dir: Path, gt_dir: Path, stems: list[str]) -> dict[str, float]:
    out = {}
    for s in stems:
        m, g = read_mask(masks_dir / f"{s}.png"), read_mask(gt_dir / f"{s}.png")
        if m.shape != g.shape:
            raise SystemExit(f"{masks_dir / s}.png is {m.shape[::-1]}, the ground truth {g.shape[::-1]}")
        out[s] = float((m & g).sum() / max((m | g).sum(), 1))
    return out


def summary(ious: dict[str, float], seconds: float) -> dict:
    v = np.array(list(ious.values()))
    worst = min(ious, key=ious.get)
    return {"iou_mean": float(v.mean()), "iou_min": float(v.min()), "iou_median": float(np.median(v)),
            "worst_view": worst, "views": len(v), "seconds": seconds, "per_view": ious}


def settings_for(obj: str, scene: str, args):
    base = PRESETS[f"tabletop-{obj}"] if scene == "tabletop" else sections.replace(
        PRESETS[f"tabletop-{obj}"], scene="void", view_z_range=(-0.35, 0.92), distance=4.2, fov=40.0)
    changes = {"write_cameras": True, "write_masks": False, "write_gt_linear": False}
    if scene == "void":
        changes["write_masks"] = True
    for key in ("n_views", "width", "spp", "format", "mesh_level", "texture_size", "table_texture_size"):
        v = getattr(args, key)
        if v is not None:
            changes[key] = v
    if args.width is not None:
        changes["height"] = int(round(args.width * 3 / 4 / 2)) * 2
    return sections.replace(base, **changes)


def plane_error(found: Path, true: Path, similarity=None) -> dict | None:
    from recon.support import SupportPlane, load_plane

    if not found.is_file():
        return None
    p, g = load_plane(found), load_plane(true)
    if similarity is not None:  # the found plane into the true frame
        n = similarity.rotation @ p.normal
        point = similarity.apply(p.point[None])[0]
        p = SupportPlane.through(point, n)
    return {"normal_deg": float(np.degrees(np.arccos(np.clip(p.normal @ g.normal, -1, 1)))),
            "offset": float(abs(g.height(p.point[None])[0]))}


def run_object(obj: str, out: Path, args) -> dict:
    from recon.linearize import linearize_capture
    from recon.masks import run_masks
    from recon.segment import run_tabletop_masks

    res: dict = {}
    for scene in ("tabletop", "void"):
        name = f"{obj}-{scene}"
        cap = out / "captures" / name
        s = settings_for(obj, scene, args)
        if not (cap / "gt" / "cameras.json").is_file():
            t0 = time.perf_counter()
            make_capture(cap, s, command=f"bench/tabletop.py ({name})")
            log.info("%s: made in %.0f s", name, time.perf_counter() - t0)
        work = out / "runs" / name
        cams = load_cameras(cap / "gt" / "cameras.json")
        stems = [c.stem for c in cams]
        gt = cap / "gt" / "masks" if scene == "tabletop" else cap / "masks"
        linear = work / "linear"
        if not (linear / "linear.json").is_file():
            linearize_capture(cap, linear)
        r = {"settings": {k: v for k, v in sections.flatten(s).items()
                          if k in ("object", "n_views", "width", "height", "fov", "distance", "format", "spp")}}
        t0 = time.perf_counter()
        run_masks(linear, work / "masks_today")
        r["today"] = summary(iou_per_view(work / "masks_today", gt, stems), time.perf_counter() - t0)
        t0 = time.perf_counter()
        seg = run_tabletop_masks(linear, cap / "gt" / "cameras.json", work / "masks_tabletop")
        r["tabletop_true_cameras"] = summary(iou_per_view(work / "masks_tabletop", gt, stems),
                                             time.perf_counter() - t0)
        r["tabletop_true_cameras"]["method"] = seg["method"]
        r["tabletop_true_cameras"]["plane"] = seg["plane"]
        if scene == "tabletop":
            r["tabletop_true_cameras"]["plane_error"] = plane_error(work / "masks_tabletop" / "plane.json",
                                                                    cap / "gt" / "plane.json")
        if args.sfm and scene == "tabletop":
            r["sfm"] = run_sfm(cap, work, stems, gt, run_tabletop_masks)
        res[scene] = r
    return res


def run_sfm(cap: Path, work: Path, stems: list[str], gt: Path, run_tabletop_masks) -> dict:
    from recon.metrics import align_cameras, pose_errors
    from recon.poses import run_poses

    poses = work / "poses"
    t0 = time.perf_counter()
    if not (poses / "cameras.json").is_file():
        try:
            run_poses(work / "linear", poses, masks_dir=work / "masks_today",
                      linear_json=work / "linear" / "linear.json")
        except ValueError as e:  # PoseError: recorded, the other numbers still count
            log.warning("SfM failed: %s", e)
            return {"error": str(e).splitlines()[0], "poses_seconds": time.perf_counter() - t0}
    t_poses = time.perf_counter() - t0
    est = load_cameras(poses / "cameras.json")
    true = load_cameras(cap / "gt" / "cameras.json")
    sim = align_cameras(est, true)
    out = {"poses_seconds": t_poses, "registered": len(est), "pose_errors": pose_errors(est, true, sim)}
    t0 = time.perf_counter()
    seg = run_tabletop_masks(poses / "undistorted", poses / "cameras.json", work / "masks_sfm",
                             points=poses / "points.ply")
    seconds = time.perf_counter() - t0
    registered = [c.stem for c in est]
    # the true masks in the undistorted pinhole views, resampled as the poses stage resamples masks
    gt_und = work / "gt_masks_undistorted"
    undistort_masks(poses, gt, gt_und, registered)
    out.update(summary(iou_per_view(work / "masks_sfm", gt_und, registered), seconds))
    out["method"] = seg["method"]
    out["plane"] = seg["plane"]
    out["plane_error"] = plane_error(work / "masks_sfm" / "plane.json", cap / "gt" / "plane.json", sim)
    out["unregistered"] = sorted(set(stems) - set(registered))
    return out


def undistort_masks(poses: Path, src: Path, dst: Path, stems: list[str]) -> None:
    """``src/<stem>.png`` (photo pixels) resampled into the poses stage's pinhole views."""
    import pycolmap

    from recon.io.images import write_mask
    from recon.poses.undistort import pinhole_camera, remap, undistort_maps

    rec = pycolmap.Reconstruction(str(poses / "sparse"))
    cam = next(iter(rec.cameras.values()))
    maps = undistort_maps(cam, pinhole_camera(cam, cam.model.name))
    for s in stems:
        write_mask(dst / f"{s}.png", remap(read_mask(src / f"{s}.png").astype(np.float32), maps) >= 0.5)


def print_table(results: dict) -> None:
    rows = []
    for obj, r in results.items():
        for scene, rr in r.items():
            today = rr["today"]["iou_mean"]
            for key in ("today", "tabletop_true_cameras", "sfm"):
                if key not in rr or "iou_mean" not in rr[key]:
                    continue
                m = rr[key]
                rows.append((f"{obj}-{scene}", key, m.get("method", "flash_falloff"), m["iou_mean"], m["iou_min"],
                             m["worst_view"], m["seconds"], m["iou_mean"] / today))
    head = f"{'capture':<16} {'masks':<22} {'method':<14} {'IoU mean':>9} {'IoU min':>8} {'worst':>6} " \
           f"{'seconds':>8} {'/today':>7}"
    print(head)  # noqa: T201
    print("-" * len(head))  # noqa: T201
    for c, k, meth, mean, mn, worst, sec, ratio in rows:
        print(f"{c:<16} {k:<22} {meth:<14} {mean:9.4f} {mn:8.4f} {worst:>6} {sec:8.1f} {ratio:7.3f}")  # noqa: T201
    for obj, r in results.items():
        tt = r["tabletop"]
        for key in ("tabletop_true_cameras", "sfm"):
            if key in tt and tt[key].get("plane_error"):
                pe = tt[key]["plane_error"]
                print(f"{obj}: plane ({key}) normal error {pe['normal_deg']:.3f} deg, offset "  # noqa: T201
                      f"{pe['offset']:.4f} units; {tt[key]['plane']['reason']}")
        if "sfm" in tt and "error" in tt["sfm"]:
            print(f"{obj}: SfM failed: {tt['sfm']['error']}")  # noqa: T201
        elif "sfm" in tt:
            e = tt["sfm"]["pose_errors"]
            print(f"{obj}: SfM registered {tt['sfm']['registered']} views in {tt['sfm']['poses_seconds']:.0f} s, "  # noqa: T201
                  f"{json.dumps({k: e[k] for k in e if not isinstance(e[k], (list, dict))})}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    p.add_argument("--out", type=Path, default=Path("bench/out/tabletop"))
    p.add_argument("--objects", nargs="+", default=["blob", "mug"], choices=["blob", "mug"])
    p.add_argument("--sfm", action="store_true", help="also run SfM and the masks on its cameras and points")
    p.add_argument("--views", type=int, dest="n_views")
    p.add_argument("--res", type=int, dest="width")
    p.add_argument("--spp", type=int)
    p.add_argument("--format", choices=["dng", "exr", "png16", "png8"])
    p.add_argument("--mesh-level", type=int, dest="mesh_level")
    p.add_argument("--texture-size", type=int, dest="texture_size")
    p.add_argument("--table-texture-size", type=int, dest="table_texture_size")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    args.out.mkdir(parents=True, exist_ok=True)
    results = {}
    t0 = time.perf_counter()
    for obj in args.objects:
        results[obj] = run_object(obj, args.out, args)
    (args.out / "tabletop.json").write_text(json.dumps({"command": " ".join(sys.argv), "results": results,
                                                        "seconds": time.perf_counter() - t0}, indent=1,
                                                       default=float))
    print_table(results)
    return 0


if __name__ == "__main__":
    sys.exit(main())
