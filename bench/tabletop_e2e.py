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

``--family SCENE...`` (issue 32 item 6): the scenes of the masks family instead (bench/masks.py's
``SCENES``: their object, palette, imaging, room and cameras), ``--views``/``--res``/``--spp``
overriding their size where given, each beside its void peer (``<scene>-void``: the same object,
palette, imaging and cameras with ``scene="tabletop_void"``; no wall, no lamps; the views the
scene takes close up, cut by the frame, are the peer's too; the stand's peer is its blob, base
not cut, alone: ``base_cut=0``). The captures hold the photos alone: no cameras, no masks, no
capture.yaml. One row per capture: whether ``export/asset.glb`` was made, or the stage that
stopped and its log's last line; the mask IoU; the initial mesh's genus (``init_mesh.json``)
and accuracy; final accuracy and seen completeness; the share of the surface that is not the
object; final accuracy over the void peer's (target: every scene makes an asset, within 1.5x).
A void peer that SfM cannot register (a plain glaze alone gives it nothing to match) is run
again with the true cameras in the capture (``<scene>-void-cams``), and the ratio uses that one.
A capture without a support plane (the stand) is measured against the horizontal plane through
the object's lowest point (the same plane its void peer's ``gt/plane.json`` names).

    OMP_WAIT_POLICY=PASSIVE .venv/bin/python bench/tabletop_e2e.py --out /tmp/e2e --views 40 --res 384 \
        --family wood-blob glossy-mug room-smooth wood-vase dark-bowl stand-blob --docs /tmp/e2e/table.md

``--variant NAME=JSON`` (repeatable): after the workflow, optimize alone again on each scene's
(or each ``--objects`` capture's) own upstream results (its poses, masks and uv mesh; the void peers are left as
they are) with the preset's optimize settings updated by JSON (nested like capture.yaml's
``optimize`` section), into ``<out>/variants/NAME/<scene>``; one row per scene gives the final
accuracy, seen completeness and share of the surface not the object of each variant. The
same inputs for every variant, so the rows differ by the setting and the renderer's
run-to-run noise only (up to 0.001 in accuracy measured). Example, the foot zone off and on
(docs/tabletop.md)::

    OMP_WAIT_POLICY=PASSIVE .venv/bin/python bench/tabletop_e2e.py --out /tmp/e2e --views 40 --res 384 \
        --family wood-blob wood-bell-1008 --measure-only \
        --variant 'foot-off={"loss": {"uncertain_foot": 0}}' --variant 'default={}'

CPU is scarce on the development machine: captures are cached in ``<out>/captures`` and
Snakemake redoes nothing that is done.
"""

from __future__ import annotations

import argparse
import contextlib
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
from recon import sections  # noqa: E402
from recon.poses.frame import rotate_cameras  # noqa: E402
from recon.support import SupportPlane, load_plane  # noqa: E402
from recon.synth.capture import PRESETS, SynthSettings, make_capture, recorded_settings  # noqa: E402
from recon.stages import NAMES as STAGE_NAMES  # noqa: E402

sys.path.insert(0, str(REPO / "bench"))
from masks import SCENES as FAMILY  # noqa: E402  (bench/masks.py: the scene family)

log = logging.getLogger("bench.tabletop_e2e")
SCENES = ("tabletop", "tabletop_void")


PHONE = {"format": "jpg", "tone_curve": "phone", "flash_offset": (0.19, 0.0, 0.0), "exposure_jitter": 0.25,
         "exposure_variation": 0.5, "ambient": 0.1, "falloff": (-0.35, 0.0), "wb_jitter": 0.02}


def capture_settings(obj: str, scene: str, args):
    base = PRESETS[f"tabletop-{obj}"]
    views, res, spp = args.views or 40, args.res or 320, args.spp or 32
    h = int(round(res * 3 / 4 / 2)) * 2
    s = sections.replace(base, scene=scene, n_views=views, width=res, height=h, spp=spp,
                         write_cameras=args.given_cameras, write_masks=args.given_masks, write_gt_linear=False)
    return sections.replace(s, **PHONE) if args.phone else s


def family_settings(name: str, void: bool, args, cameras: bool = False) -> SynthSettings:
    """The family scene ``name`` (bench/masks.py) at the bench's size where given, the photos alone
    in the capture; ``void``: its void peer (same object, palette, imaging and cameras, no table,
    no room; the stand's peer keeps the blob's round base, as the stand scene does); ``cameras``:
    the true cameras in the capture too (the void peer that SfM cannot register)."""
    over = dict(FAMILY[name])
    if args.views:
        over["n_views"] = args.views
    if args.res:
        over["height"] = int(round(args.res * over["height"] / over["width"] / 2)) * 2
        over["width"] = args.res
    if args.spp:
        over["spp"] = args.spp
    over.update(write_cameras=args.given_cameras or cameras, write_masks=args.given_masks, write_gt_linear=False,
                state_light=False)
    if void:
        # recon.synth's tabletop_void cuts the base flat as the tabletop scene does; the stand scene
        # does not cut it: its peer keeps it whole (base_cut 0 returns the mesh unchanged)
        over.update(scene="tabletop_void", wall=0.0, lamps=0.0, closeups=0.0,
                    **({"base_cut": 0.0} if FAMILY[name].get("scene") == "stand" else {}))
    return sections.replace(SynthSettings(), **over)


@contextlib.contextmanager
def peer_cameras(scene_settings: SynthSettings):
    """recon.synth's tabletop_void scene has no close-up views (the setting is refused there); the
    peer of a scene that has them gets the scene's own: its hand-held rings with the same views
    moved close (the same seeded draw), so that the two captures share every camera."""
    import recon.synth.capture as capture
    from recon.synth.tabletop import closeup_cameras

    original = capture.tabletop_cameras
    if scene_settings.variations.closeups > 0:
        capture.tabletop_cameras = lambda s, target=(0.0, 0.0, 0.0): closeup_cameras(
            original(s, target), scene_settings, target)
    try:
        yield
    finally:
        capture.tabletop_cameras = original


def _jsonable(x):
    return json.loads(json.dumps(x, default=lambda v: v.tolist() if hasattr(v, "tolist") else str(v)))


def make_cached(cap: Path, settings: SynthSettings, command: str, peer_of: SynthSettings | None = None) -> None:
    """Make the capture unless ``cap`` holds one with these settings (another one there is an error:
    use another ``--out``)."""
    meta = cap / "gt" / "synth.json"
    if meta.is_file():
        if json.loads(meta.read_text())["settings"] != _jsonable(recorded_settings(settings)):
            raise SystemExit(f"{cap}: a cached capture with other settings; remove it or use another --out")
        return
    t0 = time.perf_counter()
    with peer_cameras(peer_of) if peer_of is not None else contextlib.nullcontext():
        make_capture(cap, settings, command=command)
    log.info("%s: made in %.0f s", cap.name, time.perf_counter() - t0)


def same_cameras(a: Path, b: Path) -> bool:
    ca, cb = load_cameras(a / "gt" / "cameras.json"), load_cameras(b / "gt" / "cameras.json")
    return len(ca) == len(cb) and all(
        x.width == y.width and np.allclose(x.K, y.K) and np.allclose(x.world_to_camera, y.world_to_camera)
        for x, y in zip(ca.frames, cb.frames, strict=True))


def snakemake(captures: Path, results: Path, targets: list[str], preset: str, log_name: str = "snakemake.log") -> float:
    t0 = time.perf_counter()
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_WAIT_POLICY": "PASSIVE"}
    cmd = [sys.executable, "-m", "snakemake", "--cores", "2", "--keep-going", "--config", f"captures={captures}",
           f"results={results}", f"preset={preset}", "--", *targets]
    r = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True)
    results.mkdir(parents=True, exist_ok=True)  # absent when Snakemake failed before any job
    (results / log_name).write_text(r.stdout + r.stderr)
    if r.returncode != 0:
        log.warning("snakemake failed (%s); see %s", r.returncode, results / log_name)
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
    far = p[d_rec > 0.02]
    up, down = _vertical_hits(gt, far, plane.normal)
    top = float(plane.height(gt.v_pos).max())
    return {"accuracy": float(d_rec.mean()), "completeness_seen": float(d_vis.mean()),
            "far_2pct": float((d_rec > 0.02).mean()), "far_5pct": float((d_rec > 0.05).mean()),
            "outside_2pct": float(((d_rec > 0.02) & outside).mean()), "faces": int(len(mesh.t_pos_idx)),
            # where the far surface lies: under (or inside) the object, a ray up from it meets the
            # true surface (a skirt, a thinned foot); a lid, only a ray down meets it (over a
            # cavity); its median height over the object's
            "far_under": float(up.mean()) if len(far) else None,
            "far_lid": float((down & ~up).mean()) if len(far) else None,
            "far_median_height": float(np.median(plane.height(far)) / top) if len(far) and top > 0 else None}


def _vertical_hits(gt: Mesh, points: np.ndarray, normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per point: whether a ray along ``normal`` (up), and one against it, meets ``gt``."""
    import open3d as o3d

    if not len(points):
        return np.zeros(0, bool), np.zeros(0, bool)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(gt.v_pos.astype(np.float32)), o3d.core.Tensor(gt.t_pos_idx.astype(np.uint32)))
    out = []
    for direction in (normal, -normal):
        rays = np.concatenate([points, np.broadcast_to(direction, points.shape)], 1).astype(np.float32)
        out.append(np.isfinite(scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()))
    return out[0], out[1]


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


def stopped_at(res: Path) -> dict | None:
    """The first stage (pipeline order) whose log ends in failure: ``{"stage", "message", "log"}``
    (the message of the log's ``<stage> failed: ...`` line, which the terminal showed too)."""
    for name in STAGE_NAMES:
        f = res / "logs" / f"{name}.log"
        if not f.is_file():
            continue
        text = f.read_text(errors="replace")
        key = f" {name} failed: "
        if key in text:
            return {"stage": name, "message": text[text.rindex(key) + len(key):].strip(), "log": str(f)}
        for what in ("interrupted", "terminated"):
            if text.rstrip().endswith(f"{name} {what}"):
                return {"stage": name, "message": what, "log": str(f)}
    return None


def reference_plane(cap: Path, gt: Mesh) -> tuple[SupportPlane, str]:
    """The true table (``gt/plane.json``), or for a capture without one (the stand) the
    horizontal plane through the object's lowest point (synth scenes have +z up)."""
    f = cap / "gt" / "plane.json"
    if f.is_file():
        return load_plane(f), "gt/plane.json"
    return SupportPlane.through(gt.v_pos[np.argmin(gt.v_pos[:, 2])], [0.0, 0.0, 1.0]), "object's lowest point"


def init_stats(res: Path) -> dict:
    f = res / "init_mesh" / "init_mesh.json"
    if not f.is_file():
        return {}
    s = json.loads(f.read_text())
    iou = s.get("mask_iou") or {}
    return {"genus": s.get("genus", (s.get("topology") or {}).get("genus")), "faces": s.get("faces"),
            "silhouette_iou_mean": iou.get("mean"), "silhouette_iou_min": iou.get("min"),
            "repairs": s.get("repairs", [])}


def mask_ious(masks: Path, truth: list[np.ndarray], stems: list[str]) -> dict:
    ious = []
    for stem, t in zip(stems, truth, strict=True):
        m = read_mask(masks / f"{stem}.png")
        ious.append(float((m & t).sum() / max((m | t).sum(), 1)))
    worst = int(np.argmin(ious))
    return {"mean": float(np.mean(ious)), "min": float(ious[worst]), "worst_view": stems[worst],
            "masks": str(masks)}


def measure(cap: Path, res: Path, rng_seed: int = 0) -> dict:
    out: dict = {"asset": (res / "export" / "asset.glb").is_file(), "stopped": stopped_at(res)}
    gt = read_obj(cap / "gt" / "mesh.obj")
    true = load_cameras(cap / "gt" / "cameras.json")
    plane, out["plane_source"] = reference_plane(cap, gt)
    cams_file = res / "poses" / "cameras.json"
    if not cams_file.is_file():
        poses_log = res / "logs" / "poses.log"
        out["error"] = "no cameras (SfM failed?)" + (f": {poses_log}" if poses_log.is_file() else "")
        if (res / "masks").is_dir() and (cap / "gt" / "masks").is_dir():
            # the masks stage's own masks (the photos' frames) against the true ones
            stems = [c.stem for c in true.frames]
            if all((res / "masks" / f"{s}.png").is_file() for s in stems):
                out["mask_iou"] = mask_ious(res / "masks", [read_mask(cap / "gt" / "masks" / f"{s}.png")
                                                           for s in stems], stems)
        return out
    est = load_cameras(cams_file)
    sim = align_cameras(est, true)
    pe = pose_errors(est, true, sim)
    out["registered"] = f"{len(est)}/{len(true)}"
    out["pose"] = {k: pe[k] for k in pe if not isinstance(pe[k], (list, dict))}
    diag = json.loads((res / "poses" / "poses.json").read_text())
    out["support_plane"] = diag.get("support_plane")
    # masks in the stages' views
    est_in_gt = rotate_cameras(est, sim)
    mdir = res / "poses" / "undistorted" / "masks"
    if mdir.is_dir():
        out["mask_iou"] = mask_ious(mdir, hit_masks(gt, est_in_gt.frames), [c.stem for c in est.frames])
    rng = np.random.default_rng(rng_seed)
    visible = visible_samples(gt, true, 20000, rng)
    init = res / "init_mesh" / "mesh.ply"
    if init.is_file():
        out["init"] = {**geometry(read_mesh(init), gt, visible, sim, rng, plane), **init_stats(res)}
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
    if glb.is_file():
        out["asset_placement"] = asset_placement(glb, plane, sim, fm)
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
            a = m.get("asset_placement", {})
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


def _stop_text(m: dict) -> str:
    s = m.get("stopped")
    if s:
        return f"stops at {s['stage']}: {s['message'].splitlines()[0]}".replace("|", "\\|")
    return "no asset" + (f" ({m['error']})" if m.get("error") else "")


def family_table(results: dict) -> str:
    """One row per capture of the family: the asset or where it stopped, and the measures."""
    rows = ["| scene | capture | asset | registered | mask IoU mean / min | init genus | init acc. / compl. "
            "| final acc. / compl. | final acc. / void's | not the object (>2% of the unit) / of it below or "
            "outside the footprint |",
            "|---|---|---|---|---|---|---|---|---|---|"]
    for name, r in results.items():
        ref, ref_kind = void_reference(r)
        for kind in ("scene", "void", "void_cams"):
            m = r.get(kind)
            if m is None:
                continue
            i, f, iou = m.get("init", {}), m.get("final", {}), m.get("mask_iou", {})
            ratio = f.get("accuracy") / ref if f.get("accuracy") and ref else None
            if kind == "scene":
                ratio_text = _f(ratio, ".2f") + (" (void, true cameras)" if ratio and ref_kind == "void_cams" else "")
            else:
                ratio_text = ""
            registered = m.get("registered", "-") if kind != "void_cams" else "given"
            rows.append(
                f"| {name} | {m['capture']} | {'yes' if m['asset'] else _stop_text(m)} | {registered} "
                f"| {_f(iou.get('mean'), '.3f')} / {_f(iou.get('min'), '.3f')} | {_f(i.get('genus'), 'd')} "
                f"| {_f(i.get('accuracy'))} / {_f(i.get('completeness_seen'))} "
                f"| {_f(f.get('accuracy'))} / {_f(f.get('completeness_seen'))} | {ratio_text} "
                f"| {_f(f.get('far_2pct'), '.1%')} / {_f(f.get('outside_2pct'), '.1%')} |")
    return "\n".join(rows)


def void_reference(r: dict) -> tuple[float | None, str | None]:
    """The void peer's final accuracy: SfM's (photos alone, as the scene), else with the true
    cameras given (a plain object alone gives SfM nothing to match)."""
    for kind in ("void", "void_cams"):
        acc = r.get(kind, {}).get("final", {}).get("accuracy")
        if acc:
            return acc, kind
    return None, None


def family_verdict(results: dict, given_cameras: bool = False) -> str:
    scenes = {n: r["scene"] for n, r in results.items() if "scene" in r}
    made = [n for n, m in scenes.items() if m["asset"]]
    text = (f"assets: {len(made)}/{len(scenes)} scenes"
            f"{' (none: ' + ', '.join(n for n in scenes if n not in made) + ')' if len(made) < len(scenes) else ''}")
    for kind, what in (("void", "the void peer" + (" (true cameras, as the scene)" if given_cameras else " by SfM")),
                       ("void_cams", "the void peer with the true cameras "
                                                                         "(SfM registers too few of its views)")):
        compared = [n for n, r in results.items() if void_reference(r)[1] == kind
                    and r.get("scene", {}).get("final", {}).get("accuracy")]
        within = [n for n in compared if results[n]["scene"]["final"]["accuracy"] <= 1.5 * void_reference(results[n])[0]]
        if compared:
            text += (f"; final accuracy within 1.5x of {what}: {len(within)}/{len(compared)} "
                     f"({', '.join(within) or 'none'}; beyond: {', '.join(n for n in compared if n not in within) or 'none'})")
    return text


def parse_variant(text: str) -> tuple[str, dict]:
    """``NAME=JSON`` of ``--variant``: a folder-safe name and a mapping of optimize settings."""
    name, sep, body = text.partition("=")
    if not sep or not name or not all(ch.isalnum() or ch in "-_." for ch in name):
        raise argparse.ArgumentTypeError(f"--variant {text!r}: expected NAME=JSON, NAME of letters, digits, - _ .")
    try:
        value = json.loads(body)
    except json.JSONDecodeError as e:
        raise argparse.ArgumentTypeError(f"--variant {name}: not JSON ({e})") from None
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError(f"--variant {name}: expected a JSON object of optimize settings")
    return name, value


def _merged(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merged(out.get(k) or {}, v) if isinstance(v, dict) else v
    return out


def optimize_variant(cap: Path, res: Path, out: Path, preset: str, override: dict) -> dict:
    """Optimize alone on the workflow's results ``res`` of capture ``cap`` (the stage's inputs as
    workflow/rules/optimize.smk passes them) with the preset's settings updated by ``override``;
    the final mesh measured as :func:`measure` does."""
    from recon.config import effective_settings
    from recon.optimize import optimize_from_dirs, settings_from_dict

    settings = _merged(effective_settings("optimize", preset, cap, REPO / "config" / "presets"), override)
    views = res / "poses" / "undistorted"
    plane = res / "poses" / "plane.json"
    t0 = time.perf_counter()
    optimize_from_dirs(views, views / "masks", res / "poses" / "cameras.json", res / "uv" / "mesh.obj", out,
                       settings_from_dict(settings), progress=False, plane_json=plane if plane.is_file() else None)
    seconds = time.perf_counter() - t0
    gt = read_obj(cap / "gt" / "mesh.obj")
    sim = align_cameras(load_cameras(res / "poses" / "cameras.json"), load_cameras(cap / "gt" / "cameras.json"))
    plane_ref, _ = reference_plane(cap, gt)
    rng = np.random.default_rng(0)  # the same draws as measure(): the visible samples, then the surface's
    visible = visible_samples(gt, load_cameras(cap / "gt" / "cameras.json"), 20000, rng)
    summary = json.loads((out / "summary.json").read_text())
    return {**geometry(read_obj(out / "mesh.obj"), gt, visible, sim, rng, plane_ref), "seconds": seconds,
            "foot_pixels_out": [st.get("foot_pixels_out") for st in summary.get("stages", [])]}


def variants_table(rows: dict) -> str:
    names = sorted({v for r in rows.values() for v in r})
    head = ("| scene | " + " | ".join(f"{n}: acc. / compl. / not the object (of it: under, lid)" for n in names)
            + " |")
    lines = [head, "|---|" + "---|" * len(names)]
    for scene, r in rows.items():
        cells = [f"{_f(r[n].get('accuracy'))} / {_f(r[n].get('completeness_seen'))} / {_f(r[n].get('far_2pct'), '.1%')}"
                 f" ({_f(r[n].get('far_under'), '.0%')}, {_f(r[n].get('far_lid'), '.0%')})"
                 if n in r else "-" for n in names]
        lines.append(f"| {scene} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def run_variants(args, out: Path, names: list[str]) -> None:
    """--variant: optimize alone again per scene and variant; prints and saves the table."""
    path = out / "tabletop_e2e_variants.json"
    rows: dict = json.loads(path.read_text()).get("results", {}) if path.is_file() else {}
    for name in names:
        res = out / "results" / name
        if not (res / "uv" / "mesh.obj").is_file():
            log.warning("%s: no uv mesh in %s (the workflow stopped before uv); no variants", name, res)
            continue
        for vname, override in args.variant:
            log.info("%s: optimize with %s %s", name, vname, json.dumps(override))
            rows.setdefault(name, {})[vname] = {"settings": override, **optimize_variant(
                out / "captures" / name, res, out / "variants" / vname / name, args.preset, override)}
            path.write_text(json.dumps({"command": " ".join(sys.argv), "results": rows}, indent=1, default=float))
    print(variants_table({n: rows[n] for n in names if n in rows}))  # noqa: T201


def run_family(args, out: Path) -> int:
    caps, res = out / "captures", out / "results"
    res.mkdir(parents=True, exist_ok=True)
    path = out / "tabletop_e2e_family.json"
    saved = json.loads(path.read_text()) if path.is_file() else {}
    results: dict = saved.get("results", {})
    seconds: dict = saved.get("workflow_seconds", {})
    sizes = {}
    for name in args.family:
        scene_s, void_s = family_settings(name, False, args), family_settings(name, True, args)
        sizes[name] = (f"{scene_s.cameras.n_views} views of {scene_s.cameras.width} x {scene_s.cameras.height} "
                       f"({scene_s.photos.format}, spp {scene_s.photos.spp})")
        caps_of = {"scene": name, "void": f"{name}-void"}
        make_cached(caps / name, scene_s, f"bench/tabletop_e2e.py --family {name}")
        make_cached(caps / caps_of["void"], void_s, f"bench/tabletop_e2e.py --family {name} (void peer)",
                    peer_of=scene_s)
        if not same_cameras(caps / name, caps / caps_of["void"]):
            raise SystemExit(f"{name}: the void peer's cameras differ from the scene's")
        if not args.measure_only:
            seconds[name] = snakemake(caps, res, [f"{res}/{c}/export/asset.glb" for c in caps_of.values()],
                                      args.preset, f"snakemake-{name}.log")
            log.info("%s: workflow %.0f s", name, seconds[name])
        results[name] = {k: {"capture": c, **measure(caps / c, res / c)} for k, c in caps_of.items()}
        if not results[name]["void"]["asset"] and (results[name]["void"].get("stopped") or {}).get("stage") == "poses":
            # SfM found nothing to match on the object alone: the void peer with the true cameras
            c = f"{name}-void-cams"
            make_cached(caps / c, family_settings(name, True, args, cameras=True),
                        f"bench/tabletop_e2e.py --family {name} (void peer, true cameras)", peer_of=scene_s)
            if not args.measure_only:
                seconds[c] = snakemake(caps, res, [f"{res}/{c}/export/asset.glb"], args.preset, f"snakemake-{c}.log")
            results[name]["void_cams"] = {"capture": c, **measure(caps / c, res / c)}
        print(family_table({name: results[name]}).split("\n", 2)[-1], flush=True)  # noqa: T201
        path.write_text(json.dumps({"command": " ".join(sys.argv), "results": results, "sizes": sizes,
                                    "workflow_seconds": seconds}, indent=1, default=float))
    done = {n: results[n] for n in args.family}
    text = family_table(done)
    size = sorted(set(sizes.values()))
    settings = (f"{'; '.join(size)}, preset {args.preset}, no cameras, no masks, no capture.yaml in the captures "
                f"(SfM, masks computed, flash intensity estimated)")
    verdict = family_verdict(done, args.given_cameras)
    print(settings)  # noqa: T201
    print(text)  # noqa: T201
    print(verdict)  # noqa: T201
    if args.docs:
        args.docs.write_text(f"{settings}\n\n{text}\n\n{verdict}\n")
    if args.variant:
        run_variants(args, out, list(args.family))
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    p.add_argument("--out", type=Path, default=Path("bench/out/tabletop_e2e"))
    p.add_argument("--objects", nargs="+", default=["blob", "mug"], choices=["blob", "mug"])
    p.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    p.add_argument("--family", nargs="+", choices=sorted(FAMILY), metavar="SCENE",
                   help=f"the scenes of bench/masks.py's family instead of --objects ({', '.join(FAMILY)})")
    p.add_argument("--views", type=int, help="views per capture (default 40; --family: the scene's)")
    p.add_argument("--res", type=int, help="photo width, height at 3:4 (default 320; --family: the scene's)")
    p.add_argument("--spp", type=int, help="samples per pixel of the photos (default 32; --family: the scene's)")
    p.add_argument("--preset", default="draft")
    p.add_argument("--given-cameras", action="store_true", help="write the true cameras into the captures")
    p.add_argument("--given-masks", action="store_true", help="write the true masks into the captures")
    p.add_argument("--phone", action="store_true", help="the photos as a phone makes them (JPEG, tone curve, ...)")
    p.add_argument("--measure-only", action="store_true")
    p.add_argument("--docs", type=Path, help="write the markdown table to this file")
    p.add_argument("--variant", type=parse_variant, action="append", default=[], metavar="NAME=JSON",
                   help="optimize alone again with these optimize settings (see above)")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    out = args.out.resolve()
    if args.family:
        return run_family(args, out)
    caps, res = out / "captures", out / "results"
    res.mkdir(parents=True, exist_ok=True)
    names = {(o, s): f"{o}-{s}" for o in args.objects for s in args.scenes}
    for (o, s), name in names.items():
        make_cached(caps / name, capture_settings(o, s, args), f"bench/tabletop_e2e.py ({name})")
    seconds = None
    if not args.measure_only:
        seconds = snakemake(caps, res, [f"{res}/{n}/export/asset.glb" for n in names.values()], args.preset)
        log.info("workflow: %.0f s", seconds)
    results: dict = {}
    for (o, s), name in names.items():
        results.setdefault(o, {})[s] = measure(caps / name, res / name)
    text = table(results)
    cs = capture_settings(args.objects[0], args.scenes[0], args)
    settings = (f"{cs.cameras.n_views} views of {cs.cameras.width} x {cs.cameras.height} px "
                f"({'phone JPEG' if args.phone else 'DNG'}, spp {cs.photos.spp}), preset {args.preset}, cameras "
                f"{'given' if args.given_cameras else 'withheld (SfM)'}, masks {'given' if args.given_masks else 'computed'}, "
                "no capture.yaml")
    (out / "tabletop_e2e.json").write_text(json.dumps({"command": " ".join(sys.argv), "settings": settings,
                                                       "workflow_seconds": seconds, "results": results},
                                                      indent=1, default=float))
    print(settings)  # noqa: T201
    print(text)  # noqa: T201
    if args.docs:
        args.docs.write_text(f"{settings}\n\n{text}\n")
    if args.variant:
        run_variants(args, out, list(names.values()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
