"""An object standing on a table, end to end, beside the same object in the void (issue 15 item 5).

For each object (``--objects``, default ``blob mug``) two synthetic captures with the same
object (base cut flat), the same hand-held cameras 15-60 degrees above the table and the same
settings (``python -m recon synth --scene tabletop`` and ``--scene tabletop_void``; no cameras
and no masks in the captures unless ``--given-cameras``):

1. the whole workflow (Snakemake, ``--preset``, default draft) up to ``export/asset.glb``;
2. measured against the ground truth (``gt/``):

   - registration (views registered by SfM) and pose errors after aligning the cameras to the
     true ones (``recon.metrics.align_cameras``: rotation, centre error / scene size);
   - mask IoU: the masks the later stages use (``poses/undistorted/masks``) against the true silhouettes (the true mesh ray cast through the estimated
     cameras moved into the true frame);
   - initial-mesh and final accuracy (mean distance of the mesh's surface to the true surface)
     and completeness over the part of the true surface some camera sees (the base on the
     table is seen by none), in units of the true bounding box's longest side;
   - the fraction of the output surface farther than 2 % (and 5 %) of that unit from the
     object, and of that the part below the table or outside the object's footprint on it
     (table, background, hull left below the object; not a hull lid over a cavity);
   - novel-view RMSE (sRGB, union of the masks) in 8 views on a ring between the capture's,
     the model and the truth rendered alone with the collocated flash;
   - the asset's placement: the angle between the true table normal and the asset's +Y, the
     height of its lowest point above y = 0 (relative to the object's height), and its scale
     source.

``--phone``: the photos as a phone makes them (JPEG with a tone curve that is not sRGB, the flash
1 cm beside the lens, per-view exposure error and EXIF exposure changes, ambient light, lens
falloff, white-balance jitter; bench/phone_geometry.py's PHONE). ``--given-masks``: the true
masks in ``masks/`` (else the masks stage finds the object). No capture states the flash's
intensity (issue 31): the optimize stage estimates it; the table gives the estimate against the
truth in SfM's frame (I_e s^2 / I_true, s the frame's scale) beside what the convention predicts
(the true diffuse map's 98th percentile over 0.85), the imaging terms kept and the material model.

Prints a table (tabletop beside void per object, ratio of final accuracy) and writes
``<out>/tabletop_e2e.json``; ``--docs FILE`` writes the markdown table there.

    .venv/bin/python bench/tabletop_e2e.py --out /tmp/tabletop/e2e --views 40 --res 320

CPU is scarce on the development machine: captures are cached in ``<out>/captures`` and
Snakemake redoes nothing that is done.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from recon.io.cameras import Camera, CameraSet, load_cameras, look_at  # noqa: E402
from recon.io.images import read_exr, read_mask  # noqa: E402
from recon.io.mesh import Mesh, read_mesh, read_obj  # noqa: E402
from recon.metrics import align_cameras, distance_to_mesh, image_rmse, pose_errors, seen_by  # noqa: E402
from recon.poses.frame import rotate_cameras  # noqa: E402
from recon.support import load_plane  # noqa: E402
from recon.synth.capture import PRESETS, make_capture  # noqa: E402

log = logging.getLogger("bench.tabletop_e2e")
SCENES = ("tabletop", "tabletop_void")


PHONE = {"format": "jpg", "tone_curve": "phone", "flash_offset": (0.19, 0.0, 0.0), "exposure_jitter": 0.25,
         "exposure_variation": 0.5, "ambient": 0.1, "falloff": (-0.35, 0.0), "wb_jitter": 0.02}


def capture_settings(obj: str, scene: str, args):
    base = PRESETS[f"tabletop-{obj}"]
    h = int(round(args.res * 3 / 4 / 2)) * 2
    s = dataclasses.replace(base, scene=scene, n_views=args.views, width=args.res, height=h, spp=args.spp,
                            write_cameras=args.given_cameras, write_masks=args.given_masks, write_gt_linear=False)
    return dataclasses.replace(s, **PHONE) if args.phone else s


def snakemake(captures: Path, results: Path, targets: list[str], preset: str) -> float:
    t0 = time.perf_counter()
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_WAIT_POLICY": "PASSIVE"}
    cmd = [sys.executable, "-m", "snakemake", "--cores", "2", "--keep-going", "--config", f"captures={captures}",
           f"results={results}", f"preset={preset}", "--", *targets]
    r = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True)
    results.mkdir(parents=True, exist_ok=True)  # absent when Snakemake failed before any job
    (results / "snakemake.log").write_text(r.stdout + r.stderr)
    if r.returncode != 0:
        log.warning("snakemake failed (%s); see %s", r.returncode, results / "snakemake.log")
    return time.perf_counter() - t0


# ---- geometry ----
def visible_samples(gt: Mesh, cams: CameraSet, n: int, rng) -> np.ndarray:
    """Points on the true surface (area-uniform) that at least one camera sees."""
    p = gt.sample_surface(n, rng)
    return p[seen_by(p, gt, cams)]


def geometry(mesh: Mesh, gt: Mesh, visible: np.ndarray, sim, rng, plane, n: int = 20000) -> dict:
    """Accuracy, seen completeness, and the share of the surface far from the object: farther
    than 2 % / 5 % of the unit, and (``outside_2pct``: table or background) farther than 2 % and
    below the table or outside the object's footprint on it (a cup's hull lid over its cavity is
    far from the object but over its footprint)."""
    from scipy.spatial import Delaunay

    m = Mesh(sim.apply(mesh.v_pos), mesh.t_pos_idx)
    lo, hi = gt.bbox()
    unit = float(np.max(hi - lo))
    p = m.sample_surface(n, rng)
    d_rec = distance_to_mesh(gt, p) / unit
    d_vis = distance_to_mesh(m, visible) / unit
    B = plane.basis()[:2]
    outside = (Delaunay(gt.v_pos @ B.T).find_simplex(p @ B.T) < 0) | (plane.height(p) < -0.02 * unit)
    return {"accuracy": float(d_rec.mean()), "completeness_seen": float(d_vis.mean()),
            "far_2pct": float((d_rec > 0.02).mean()), "far_5pct": float((d_rec > 0.05).mean()),
            "outside_2pct": float(((d_rec > 0.02) & outside).mean()), "faces": int(len(mesh.t_pos_idx))}


def hit_masks(mesh: Mesh, cams) -> list[np.ndarray]:
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.v_pos.astype(np.float32)),
                        o3d.core.Tensor(mesh.t_pos_idx.astype(np.uint32)))
    out = []
    for c in cams:
        jj, ii = np.meshgrid(np.arange(c.width) + 0.5, np.arange(c.height) + 0.5)
        d = np.stack([jj, ii, np.ones_like(jj)], -1).reshape(-1, 3) @ np.linalg.inv(c.K).T
        d = d @ c.camera_to_world[:3, :3].T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        rays = np.concatenate([np.broadcast_to(c.center, d.shape), d], 1).astype(np.float32)
        t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        out.append(np.isfinite(t).reshape(c.height, c.width))
    return out


def novel_cameras(gt: Mesh, cams: CameraSet, n: int = 8) -> list[Camera]:
    lo, hi = gt.bbox()
    target = 0.5 * (lo + hi)
    dist = float(np.median([np.linalg.norm(c.center - target) for c in cams]))
    c0 = cams.frames[0]
    out = []
    for k in range(n):
        elev = np.radians(25 + 25 * (k % 2))
        phi = 0.3 + k * 2 * np.pi / n
        eye = target + dist * np.array([np.cos(elev) * np.cos(phi), np.cos(elev) * np.sin(phi), np.sin(elev)])
        out.append(Camera(f"novel/{k:02d}.exr", c0.width, c0.height, c0.K.copy(), look_at(eye, target)))
    return out


def render(mesh: Mesh, maps: dict, cams: list[Camera], light: float, spp: int = 32) -> np.ndarray:
    import torch

    from recon.render import CollocatedRenderer, RenderSettings

    r = CollocatedRenderer(mesh.t_pos_idx, mesh.v_tex, mesh.t_tex_idx, RenderSettings(spp=spp, boundary="none"))
    with torch.no_grad():
        return r.render_torch(torch.tensor(mesh.v_pos, dtype=torch.float32),
                              *(torch.from_numpy(np.ascontiguousarray(maps[k]))
                                for k in ("diffuse", "specular", "roughness")),
                              cams, light, seed=12345).numpy()


def asset_placement(glb: Path, gt_plane, sim, mesh: Mesh) -> dict:
    """The asset's +Y against the true table normal (both in the estimated frame), and where the
    asset's lowest point lies (y, relative to the object's height)."""
    import pygltflib

    g = pygltflib.GLTF2().load(str(glb))
    extras = g.asset.extras["recon"]
    T = np.asarray(extras["object_to_world"]).reshape(4, 4)
    n_est = sim.rotation.T @ gt_plane.normal  # the true normal in the estimated frame
    up = T[:3, :3] @ n_est
    angle = float(np.degrees(np.arccos(np.clip(up[1] / np.linalg.norm(up), -1, 1))))
    v = mesh.v_pos @ T[:3, :3].T + T[:3, 3]
    height = float(np.ptp(v[:, 1]))
    return {"up_error_deg": angle, "base_y_over_height": float(v[:, 1].min() / height),
            "placement": extras.get("placement"), "scale_source": extras.get("scale_source")}


def measure(cap: Path, res: Path, rng_seed: int = 0) -> dict:
    out: dict = {}
    gt = read_obj(cap / "gt" / "mesh.obj")
    true = load_cameras(cap / "gt" / "cameras.json")
    cams_file = res / "poses" / "cameras.json"
    if not cams_file.is_file():
        poses_log = res / "logs" / "poses.log"
        out["error"] = "no cameras (SfM failed?)" + (f": {poses_log}" if poses_log.is_file() else "")
        return out
    est = load_cameras(cams_file)
    sim = align_cameras(est, true)
    pe = pose_errors(est, true, sim)
    out["registered"] = f"{len(est)}/{len(true)}"
    out["pose"] = {k: pe[k] for k in pe if not isinstance(pe[k], (list, dict))}
    diag = json.loads((res / "poses" / "poses.json").read_text())
    out["support_plane"] = diag.get("support_plane")
    # masks in the stages' views
    mdir = res / "poses" / "undistorted" / "masks"
    est_in_gt = rotate_cameras(est, sim)
    truth = hit_masks(gt, est_in_gt.frames)
    ious = []
    for c, t in zip(est.frames, truth, strict=True):
        m = read_mask(mdir / f"{c.stem}.png")
        ious.append(float((m & t).sum() / max((m | t).sum(), 1)))
    out["mask_iou"] = {"mean": float(np.mean(ious)), "min": float(np.min(ious))}
    rng = np.random.default_rng(rng_seed)
    visible = visible_samples(gt, true, 20000, rng)
    plane = load_plane(cap / "gt" / "plane.json")
    init = res / "init_mesh" / "mesh.ply"
    if init.is_file():
        out["init"] = geometry(read_mesh(init), gt, visible, sim, rng, plane)
    final = res / "optimize" / "mesh.obj"
    if not final.is_file():
        out["error"] = "optimize did not finish"
        return out
    fm = read_obj(final)
    out["final"] = geometry(fm, gt, visible, sim, rng, plane)
    maps = {k: read_exr(res / "optimize" / f"{k}.exr") for k in ("diffuse", "specular", "roughness")}
    gt_maps = {k: read_exr(cap / "gt" / f"{k}.exr") for k in ("diffuse", "specular", "roughness")}
    novel = novel_cameras(gt, true)
    fm_gt = Mesh(sim.apply(fm.v_pos), fm.t_pos_idx, fm.v_tex, fm.t_tex_idx)
    # the model's light in the true frame: distances scale by s, so the intensity by s^2
    img_rec = render(fm_gt, maps, novel, est.light_intensity * sim.scale**2)
    img_gt = render(gt, gt_maps, novel, true.light_intensity)
    rm = [image_rmse(a, b, ma, mb) for a, b, ma, mb in
          zip(img_rec, img_gt, hit_masks(fm_gt, novel), hit_masks(gt, novel), strict=True)]
    out["novel_view_rmse"] = float(np.mean(rm))
    glb = res / "export" / "asset.glb"
    if glb.is_file() and (cap / "gt" / "plane.json").is_file():
        out["asset"] = asset_placement(glb, load_plane(cap / "gt" / "plane.json"), sim, fm)
    summary = res / "optimize" / "summary.json"
    if summary.is_file():
        s = json.loads(summary.read_text())
        out["optimize_seconds"] = s.get("wall_seconds")
        light = s.get("light") or {}
        d = gt_maps["diffuse"].reshape(-1, 3)
        out["light"] = {"source": light.get("source"), "estimate": light.get("intensity"),
                        # the estimate in the true frame over the true I_e, and what the convention predicts
                        "ratio_to_true": (light["intensity"] * sim.scale**2 / true.light_intensity
                                          if light.get("intensity") else None),
                        "convention_predicts": float(np.percentile(d[d.max(1) > 0].max(1), 98) / 0.85)}
        loop = s.get("imaging_loop") or {}
        out["imaging_terms"] = loop.get("chosen") if loop else (s.get("imaging_model") or [])
        out["material_model"] = s.get("material_model_label")
    out["stage_seconds"] = stage_seconds(res)
    return out


def stage_seconds(res: Path) -> dict:
    out = {}
    for f in sorted((res / "benchmarks").glob("*.tsv")):
        lines = f.read_text().splitlines()
        if len(lines) >= 2:
            out[f.stem] = float(lines[1].split("\t")[0])
    return out


def _f(x, spec=".4f"):
    return "-" if x is None else format(x, spec)


def table(results: dict) -> str:
    rows = ["| object | scene | registered | rot. err. (deg) | centre err. | mask IoU mean / min | init acc. / compl. "
            "| final acc. / compl. | final acc. / void's | far (>2% / >5%) / table or background | novel-view RMSE "
            "| asset up err. (deg) / base y | I_e est. / true (convention) | imaging terms | material |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for obj, r in results.items():
        void_acc = r.get("tabletop_void", {}).get("final", {}).get("accuracy")
        for scene in SCENES:
            m = r.get(scene, {})
            if "registered" not in m:
                rows.append(f"| {obj} | {scene} | {m.get('error', '-')} |" + " - |" * 12)
                continue
            p = m["pose"]
            i, f = m.get("init", {}), m.get("final", {})
            ratio = f.get("accuracy") / void_acc if f.get("accuracy") and void_acc else None
            a = m.get("asset", {})
            rows.append(
                f"| {obj} | {scene} | {m['registered']} | {_f(p.get('mean_rotation_deg'), '.3f')} "
                f"| {_f(p.get('mean_center'), '.4f')} "
                f"| {_f(m['mask_iou']['mean'])} / {_f(m['mask_iou']['min'])} "
                f"| {_f(i.get('accuracy'))} / {_f(i.get('completeness_seen'))} "
                f"| {_f(f.get('accuracy'))} / {_f(f.get('completeness_seen'))} | {_f(ratio, '.2f')} "
                f"| {_f(f.get('far_2pct'), '.2%')} / {_f(f.get('far_5pct'), '.2%')} / {_f(f.get('outside_2pct'), '.2%')} "
                f"| {_f(m.get('novel_view_rmse'))} "
                f"| {_f(a.get('up_error_deg'), '.2f')} / {_f(a.get('base_y_over_height'), '.4f')} "
                f"| {_f(m.get('light', {}).get('ratio_to_true'), '.3f')} ({_f(m.get('light', {}).get('convention_predicts'), '.3f')}) "
                f"| {', '.join(m.get('imaging_terms') or []) or 'none'} | {m.get('material_model') or '-'} |")
    return "\n".join(rows)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    p.add_argument("--out", type=Path, default=Path("bench/out/tabletop_e2e"))
    p.add_argument("--objects", nargs="+", default=["blob", "mug"], choices=["blob", "mug"])
    p.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    p.add_argument("--views", type=int, default=40)
    p.add_argument("--res", type=int, default=320)
    p.add_argument("--spp", type=int, default=32)
    p.add_argument("--preset", default="draft")
    p.add_argument("--given-cameras", action="store_true", help="write the true cameras into the captures")
    p.add_argument("--given-masks", action="store_true", help="write the true masks into the captures")
    p.add_argument("--phone", action="store_true", help="the photos as a phone makes them (JPEG, tone curve, ...)")
    p.add_argument("--measure-only", action="store_true")
    p.add_argument("--docs", type=Path, help="write the markdown table to this file")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    out = args.out.resolve()
    caps, res = out / "captures", out / "results"
    res.mkdir(parents=True, exist_ok=True)
    names = {(o, s): f"{o}-{s}" for o in args.objects for s in args.scenes}
    for (o, s), name in names.items():
        if not (caps / name / "gt" / "cameras.json").is_file():
            t0 = time.perf_counter()
            make_capture(caps / name, capture_settings(o, s, args), command=f"bench/tabletop_e2e.py ({name})")
            log.info("%s: made in %.0f s", name, time.perf_counter() - t0)
    seconds = None
    if not args.measure_only:
        seconds = snakemake(caps, res, [f"{res}/{n}/export/asset.glb" for n in names.values()], args.preset)
        log.info("workflow: %.0f s", seconds)
    results: dict = {}
    for (o, s), name in names.items():
        results.setdefault(o, {})[s] = measure(caps / name, res / name)
    text = table(results)
    settings = (f"{args.views} views of {args.res} x {int(round(args.res * 3 / 4 / 2)) * 2} px "
                f"({'phone JPEG' if args.phone else 'DNG'}, spp {args.spp}), preset {args.preset}, cameras "
                f"{'given' if args.given_cameras else 'withheld (SfM)'}, masks {'given' if args.given_masks else 'computed'}, "
                "no capture.yaml")
    (out / "tabletop_e2e.json").write_text(json.dumps({"command": " ".join(sys.argv), "settings": settings,
                                                       "workflow_seconds": seconds, "results": results},
                                                      indent=1, default=float))
    print(settings)  # noqa: T201
    print(text)  # noqa: T201
    if args.docs:
        args.docs.write_text(f"{settings}\n\n{text}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
