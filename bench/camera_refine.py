"""Benchmark of camera refinement (issue 17): perturbed and SfM cameras, with and without.

One synthetic capture (``python -m recon synth``, known cameras in ``gt/cameras.json``) is
optimized from cameras with controlled errors and from SfM cameras, each time with
``cameras.refine: select`` (one call runs the control without refinement and the run with it,
from the same visual hull and seeds, and keeps one on the held-out views). Printed per
configuration:

- the camera errors of the training views against the truth (rotation in degrees, centre
  error as a fraction of the object size, after the Umeyama similarity of the centres, DESIGN
  section 5; focal error), before (the input cameras) and after the refinement;
- the final accuracy (DESIGN section 5, unit bounding box, both meshes aligned to the truth
  with the similarity of their own cameras) without and with the refinement, and the ratio to
  the accuracy with the exact cameras (the target for SfM cameras: within 1.2x);
- the held-out decision (errors, gain, SE, kept or not) and the seconds of each run and of the
  held-out alignment.

Perturbations: every training view rotated about its centre by ``deg`` degrees (random axis)
and its centre moved by ``pct`` % of the object size (random direction); level 0 is the exact
cameras labelled as SfM (does the refinement change anything?). The exact-camera baseline is
level 0's control run.

    python -m recon synth /tmp/camrefine/cap --object blob --views 32 --res 192 --format exr \\
        --cameras --masks --no-noise --seed 0
    python bench/camera_refine.py /tmp/camrefine/cap --out /tmp/camrefine/bench --preset draft

The two runs of a "select" call are read from its checkpoints (``checkpoints/last.pt``: the
control; ``checkpoints/cameras/last.pt``: the refined run, with its camera corrections), so
both results are measured whichever the selection kept.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np
import torch
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from recon import sections  # noqa: E402
from recon.config import load_preset  # noqa: E402
from recon.io.cameras import Camera, CameraSet, load_cameras, save_cameras  # noqa: E402
from recon.io.mesh import Mesh, read_mesh  # noqa: E402
from recon.metrics import align_cameras, chamfer, pose_errors, rotation_angle_deg  # noqa: E402
from recon.optimize import OptimizeSettings, optimize_capture, settings_from_dict  # noqa: E402
from recon.optimize.camera_refine import CameraRefinement, rotation_exp  # noqa: E402

STATE_LIGHT = False  # --state-light

log = logging.getLogger("bench.camera_refine")

LEVELS = {"exact": (0.0, 0.0), "0.2deg-0.5pct": (0.2, 0.5), "0.5deg-1pct": (0.5, 1.0), "1deg-2pct": (1.0, 2.0)}


def perturb(cams: CameraSet, deg: float, pct: float, size: float, seed: int) -> CameraSet:
    """Every camera rotated about its centre by ``deg`` degrees and its centre moved by ``pct``
    % of ``size``, random axis and direction per view."""
    rng = np.random.default_rng(seed)
    out = []
    for c in cams.frames:
        w = rng.normal(size=3)
        w *= np.deg2rad(deg) / np.linalg.norm(w)
        d = rng.normal(size=3)
        d *= pct / 100 * size / np.linalg.norm(d)
        R = rotation_exp(torch.tensor(w)).numpy() @ c.world_to_camera[:3, :3]
        center = c.center + d
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, -R @ center
        out.append(Camera(c.image, c.width, c.height, c.K.copy(), T))
    return CameraSet(tuple(out), cams.light_intensity)


def camera_errors(est: list[Camera], true: CameraSet, size: float, points: np.ndarray) -> dict:
    """Rotation (deg), centre (fraction of ``size``) and focal errors after the Umeyama fit of
    the centres, and the reprojection error (pixels of the photos) of the true surface's
    ``points`` (mean over points and views): what the images see of the camera errors (a small
    rotation and a sideways shift differ only by parallax, so the two errors alone overstate it)."""
    est_set = CameraSet(tuple(est), 1.0)
    sim = align_cameras(est_set, true)
    pe = pose_errors(est_set, true, sim)
    t = true.by_stem()
    # relative: the poses stage's undistorted views of a fitted distortion crop the border,
    # keeping the pixel pitch
    focal = [abs(c.K[0, 0] / t[c.stem].K[0, 0] - 1) for c in est]
    x_est = (sim.rotation.T @ (points - sim.translation).T).T / sim.scale  # true frame -> estimated
    px = [float(np.linalg.norm(c.project(x_est)[0] - t[c.stem].project(points)[0], axis=1).mean()) for c in est]
    return {"rotation_deg": pe["mean_rotation_deg"], "rotation_deg_max": pe["max_rotation_deg"],
            "center": pe["mean_center"] / size, "center_max": pe["max_center"] / size,
            "focal": float(np.mean(focal)), "reprojection_px": float(np.mean(px))}


def run_mesh(ckpt: Path) -> tuple[Mesh, dict]:
    state = torch.load(ckpt / "last.pt", map_location="cpu", weights_only=False)
    m = state["mesh"]
    return Mesh(np.asarray(m["v_pos"]), np.asarray(m["t_pos_idx"])), state


def accuracy(mesh: Mesh, cams: list[Camera], gt_mesh: Mesh, gt_cams: CameraSet) -> dict:
    """DESIGN section 5 accuracy (aligned by the cameras' centres), and as a diagnostic the
    accuracy after the best uniform scale of the aligned mesh about its centroid (0.95-1.05):
    what is left when the object's scale relative to the cameras is set right."""
    sim = align_cameras(CameraSet(tuple(cams), 1.0), gt_cams)
    r = chamfer(mesh, gt_mesh, similarity=sim, n_samples=100_000, seed=0)
    v = sim.apply(mesh.v_pos)
    c0 = v.mean(0)

    def scaled(k):
        return Mesh(c0 + k * (v - c0), mesh.t_pos_idx)

    grid = np.arange(0.95, 1.05001, 0.0025)
    best = min(grid, key=lambda k: chamfer(scaled(k), gt_mesh, n_samples=20_000, seed=0)["accuracy"])
    fitted = chamfer(scaled(best), gt_mesh, n_samples=100_000, seed=0)
    v_obj, frame = object_frame(v, mesh, gt_mesh)
    obj = chamfer(Mesh(v_obj, mesh.t_pos_idx), gt_mesh, n_samples=100_000, seed=0)
    return {**{k: r[k] for k in ("accuracy", "completeness", "chamfer")},
            "scale_fitted": float(best), "accuracy_scale_fitted": fitted["accuracy"],
            "accuracy_object_frame": obj["accuracy"], "frame_error": frame}


def object_frame(v: np.ndarray, mesh: Mesh, gt_mesh: Mesh, iterations: int = 30) -> tuple[np.ndarray, dict]:
    """Diagnostic: the aligned mesh's vertices ``v`` moved by the similarity that fits its surface
    to the ground truth's (trimmed ICP with scale: 20,000 area samples against their closest points, the nearest
    80 % of them in each step),
    and that similarity's size: the frame error the cameras' centres put into DESIGN section 5's
    accuracy, apart from the shape's own error. Returned: the vertices and
    {"rotation_deg", "translation" (fraction of the object size), "scale" (relative)}."""
    import open3d as o3d

    from recon.metrics import umeyama

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(gt_mesh.v_pos.astype(np.float32)),
                        o3d.core.Tensor(gt_mesh.t_pos_idx.astype(np.uint32)))
    p0 = Mesh(v, mesh.t_pos_idx).sample_surface(20_000, np.random.default_rng(1))
    p = p0.copy()
    for _ in range(iterations):
        q = scene.compute_closest_points(o3d.core.Tensor(p.astype(np.float32)))["points"].numpy().astype(np.float64)
        d = np.linalg.norm(q - p, axis=1)
        near = d <= np.quantile(d, 0.8)  # trimmed: a closed base or a hull lid the views never saw does not pull
        p = umeyama(p[near], q[near]).apply(p)
    total = umeyama(p0, p)  # the composition of the steps
    lo, hi = gt_mesh.bbox()
    c = 0.5 * (lo + hi)
    shift = total.apply(c[None])[0] - c  # how far the object's centre moves
    return total.apply(v), {"rotation_deg": float(rotation_angle_deg(total.rotation)),
                            "translation": float(np.linalg.norm(shift) / np.max(hi - lo)),
                            "scale": float(total.scale - 1.0)}


def linearized(cap: Path, lin: Path) -> Path:
    """The capture's photos through the linearize stage (``lin``: its folder)."""
    from recon.linearize import linearize_capture

    if not (lin / "linear.json").is_file():
        linearize_capture(cap, lin)
    return lin


def sfm_inputs(cap: Path, work: Path, lin: Path, poses_settings: dict | None = None
               ) -> tuple[Path, list[Path], list[Path], float]:
    """Run the poses stage on the linearized capture without its cameras (SfM), with the
    default poses settings updated by ``poses_settings``."""
    from recon.poses import PoseSettings, run_poses

    poses = work / "poses"
    t0 = time.perf_counter()
    if not (poses / "cameras.json").is_file():
        run_poses(lin, poses, sections.replace(PoseSettings(), **(poses_settings or {})), masks_dir=cap / "masks",
                  linear_json=lin / "linear.json")
    secs = time.perf_counter() - t0
    cams = load_cameras(poses / "cameras.json")
    # SfM's frame has its own scale s (true = s * sfm): the collocated light of the true
    # intensity I falls off with the true distances, I / (s d)^2 = (I / s^2) / d^2. Until issue 31
    # the SfM frame's cameras.json got I / s^2 here by hand (a number no user has); with
    # --state-light it still does (the old measurement), by default the optimize stage estimates I_e
    gt = load_cameras(cap / "gt" / "cameras.json")
    s = align_cameras(cams, gt).scale
    cj = work / "cameras.json"
    save_cameras(cj, CameraSet(cams.frames, gt.light_intensity / s**2, cams.extra,
                               light_known=STATE_LIGHT))
    und = poses / "undistorted"
    return cj, [und / f"{c.stem}.exr" for c in cams.frames], \
        [und / "masks" / f"{c.stem}.png" for c in cams.frames], secs


def one(name: str, cameras_json: Path, images, masks, settings, gt_mesh, gt_cams, size, work: Path,
        evaluate_only: bool = False, reuse: bool = False) -> dict:
    from recon.init_mesh import run_init_mesh

    d = work / name
    init = d / "init"
    if evaluate_only or (reuse and (d / "optimize" / "summary.json").is_file()):  # the finished run, measured again
        summary = json.loads((d / "optimize" / "summary.json").read_text())
        wall = summary["wall_seconds"]
    else:
        if not (init / "mesh.ply").is_file():
            run_init_mesh(cameras_json, Path(masks[0]).parent, init)
        t0 = time.perf_counter()
        summary = optimize_capture(images, masks, None, cameras_json, init / "mesh.ply", d / "optimize", settings,
                                   progress=False, cameras_source="sfm")
        wall = time.perf_counter() - t0
    cams = load_cameras(cameras_json)
    points = gt_mesh.v_pos[np.random.default_rng(0).choice(len(gt_mesh.v_pos), 2000, replace=False)]
    info = summary["camera_refinement"]
    held = set(summary["holdout"]["held_out"]) if summary.get("holdout") else set()
    train = [c for c in cams.frames if c.stem not in held]
    ctrl_mesh, _ = run_mesh(d / "optimize" / "checkpoints")
    ref_mesh, state = run_mesh(d / "optimize" / "checkpoints" / "cameras")
    ref = CameraRefinement(train, settings.camera_prior(), intrinsics=settings.cameras.intrinsics)
    ref.load_state_dict(state["cameras"]["params"])
    refined = ref.cameras(range(len(train)), train)
    sel = info.get("selection", {})
    row = {
        "name": name,
        "cameras_before": camera_errors(train, gt_cams, size, points),
        "cameras_after": camera_errors(refined, gt_cams, size, points),
        "accuracy_without": accuracy(ctrl_mesh, train, gt_mesh, gt_cams),
        "accuracy_with": accuracy(ref_mesh, refined, gt_mesh, gt_cams),
        "kept": bool(info.get("refined")),
        "heldout_control": sel.get("control_heldout_error"),
        "heldout_refined": sel.get("refined_heldout_error"),
        "gain": sel.get("gain"), "se": sel.get("se"),
        "run_seconds": sel.get("run_seconds"),
        "align_seconds": summary["phase_seconds"].get("cameras"),
        "wall_seconds": wall,
        "corrections": {k: info["corrections"][k] for k in ("mean_rotation_deg", "mean_center_shift_object",
                                                             "focal_scale", "principal_shift")},
    }
    log.info("%s: %s", name, json.dumps(row))
    return row


def table(rows: list[dict], exact: float, exact_object: float | None = None) -> str:
    head = ("| cameras | rot. error before -> after (deg) | centre error before -> after (% object) | "
            "focal error before -> after (%) | reprojection before -> after (px) | accuracy without | accuracy with | "
            "ratio to exact without / with | object frame: ratio without / with (frame error, % object) | "
            "held-out control / refined (gain, SE) | kept | seconds control / refined / alignment |")
    lines = [head, "|" + "---|" * 12]
    for r in rows:
        b, a = r["cameras_before"], r["cameras_after"]
        aw, ar = r["accuracy_without"]["accuracy"], r["accuracy_with"]["accuracy"]
        ow, orf = (r[k].get("accuracy_object_frame", float("nan")) for k in ("accuracy_without", "accuracy_with"))
        fw, fr = (100 * r[k].get("frame_error", {}).get("translation", float("nan"))
                  for k in ("accuracy_without", "accuracy_with"))
        eo = exact_object or float("nan")
        rs = r["run_seconds"] or [float("nan"), float("nan")]
        lines.append(
            f"| {r['name']} | {b['rotation_deg']:.3f} -> {a['rotation_deg']:.3f} | {100 * b['center']:.2f} -> "
            f"{100 * a['center']:.2f} | {100 * b['focal']:.2f} -> {100 * a['focal']:.2f} | "
            f"{b['reprojection_px']:.2f} -> {a['reprojection_px']:.2f} | {aw:.5f} | {ar:.5f} | "
            f"{aw / exact:.2f} / {ar / exact:.2f} | {ow / eo:.2f} / {orf / eo:.2f} ({fw:.2f} / {fr:.2f}) | "
            f"{r['heldout_control']:.5f} / {r['heldout_refined']:.5f} "
            f"({r['gain']:+.5f}, {r['se']:.5f}) | {'yes' if r['kept'] else 'no'} | "
            f"{rs[0]:.0f} / {rs[1]:.0f} / {r['align_seconds']:.0f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("capture", type=Path, help="a synthetic capture (python -m recon synth ... --cameras --masks)")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--preset", default="draft")
    p.add_argument("--set", action="append", default=[], help="key=value (YAML) overriding the preset's optimize section")
    p.add_argument("--levels", nargs="*", default=list(LEVELS), choices=list(LEVELS))
    p.add_argument("--sfm", action=argparse.BooleanOptionalAction, default=True, help="also the SfM cameras")
    p.add_argument("--sfm-views-exact", action="store_true",
                   help="also the exact cameras of only the views SfM registered (row exact-<sfm row>-views): "
                        "what the unregistered views cost, apart from the cameras' errors")
    p.add_argument("--poses-set", action="append", default=[],
                   help="key=value (YAML) of the poses settings for the SfM row (its name and folder: sfm-key=value)")
    p.add_argument("--seed", type=int, default=1, help="seed of the perturbations")
    p.add_argument("--state-light", action="store_true",
                   help="give the SfM runs the true flash intensity in SfM's frame (the measurements before "
                        "issue 31); by default the optimize stage estimates it")
    p.add_argument("--reuse", action="store_true", help="measure the finished runs in --out again, run the others")
    p.add_argument("--evaluate-only", action="store_true",
                   help="measure the runs already in --out again (no optimization; e.g. after a metric was added)")
    args = p.parse_args(argv)
    global STATE_LIGHT
    STATE_LIGHT = bool(args.state_light)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s", datefmt="%H:%M:%S")
    for name in ("recon.optimize.remesh", "recon.optimize.guard"):
        logging.getLogger(name).setLevel(logging.WARNING)

    cap = args.capture
    values = dict(load_preset(args.preset).get("optimize") or {})
    for kv in args.set:
        k, v = kv.split("=", 1)
        values[k] = yaml.safe_load(v)
    values, _ = sections.move_flat(OptimizeSettings, values)  # a --set key is a setting's own name: into its section
    values["cameras"] = {**values.get("cameras", {}), "refine": "select"}
    settings = settings_from_dict(values, f"preset {args.preset} + --set")
    gt_mesh = read_mesh(cap / "gt" / "mesh.obj")
    gt_cams = load_cameras(cap / "gt" / "cameras.json")
    lo, hi = gt_mesh.bbox()
    size = float(np.max(hi - lo))
    args.out.mkdir(parents=True, exist_ok=True)
    images = [cap / c.image for c in gt_cams.frames]
    lin = None
    if any(Path(i).suffix.lower() != ".exr" for i in images):  # JPEG/PNG/DNG photos: their linear EXRs
        lin = linearized(cap, args.out / "linear")
        images = [lin / f"{c.stem}.exr" for c in gt_cams.frames]
    masks = [cap / "masks" / f"{c.stem}.png" for c in gt_cams.frames]

    rows = []
    for name in args.levels:
        deg, pct = LEVELS[name]
        d = args.out / name
        d.mkdir(parents=True, exist_ok=True)
        cj = d / "cameras.json"
        if not cj.is_file():
            save_cameras(cj, perturb(gt_cams, deg, pct, size, args.seed))
        rows.append(one(name, cj, images, masks, settings, gt_mesh, gt_cams, size, args.out, args.evaluate_only, args.reuse))
    if args.sfm:
        poses_settings = {k: yaml.safe_load(v) for k, v in (kv.split("=", 1) for kv in args.poses_set)}
        name = "-".join(["sfm"] + args.poses_set)
        lin = lin or linearized(cap, args.out / "linear")
        cj, imgs, msks, secs = sfm_inputs(cap, args.out / name, lin, poses_settings)
        row = one(name, cj, imgs, msks, settings, gt_mesh, gt_cams, size, args.out, args.evaluate_only, args.reuse)
        row["sfm_seconds"] = secs
        rows.append(row)
        if args.sfm_views_exact:
            stems = {c.stem for c in load_cameras(cj).frames}
            keep = [k for k, c in enumerate(gt_cams.frames) if c.stem in stems]
            d = args.out / f"exact-{name}-views"
            d.mkdir(parents=True, exist_ok=True)
            save_cameras(d / "cameras.json", CameraSet(tuple(gt_cams.frames[k] for k in keep), gt_cams.light_intensity))
            rows.append(one(d.name, d / "cameras.json", [images[k] for k in keep], [masks[k] for k in keep], settings,
                            gt_mesh, gt_cams, size, args.out, args.evaluate_only, args.reuse))
    exact = next((r["accuracy_without"]["accuracy"] for r in rows if r["name"] == "exact"), None)
    result = {"capture": str(cap), "preset": args.preset, "overrides": args.set, "object_size": size,
              "exact_accuracy": exact, "rows": rows}
    (args.out / "camera_refine.json").write_text(json.dumps(result, indent=1))
    if exact is not None:
        exact_obj = next(r["accuracy_without"].get("accuracy_object_frame") for r in rows if r["name"] == "exact")
        result["exact_accuracy_object_frame"] = exact_obj
        (args.out / "camera_refine.json").write_text(json.dumps(result, indent=1))
        md = table(rows, exact, exact_obj)
        (args.out / "camera_refine.md").write_text(md + "\n")
        print(md)  # noqa: T201 (a command line tool's report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
