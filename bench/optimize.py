"""Benchmark of the optimize stage on a synthetic capture with ground truth.

Runs ``recon.optimize.optimize_capture`` on a capture made by ``python -m recon synth`` (known
cameras, masks, gt/), from the visual-hull initial mesh (``recon.init_mesh``) or a given one,
and reports against the ground truth (DESIGN section 5): accuracy / completeness of the initial
and the final mesh, their ratio (``recon.metrics.chamfer``: distances divided by the longest
side of the ground truth's bounding box, the paper's unit bounding box), novel-view image RMSE
(sRGB, union of masks) over views that were not optimized on, the relighting RMSE over the same
views under the procedural environment map of ``recon.render.envmap`` (and its Monte Carlo
noise floor: the ground truth against itself with other seeds, cached beside the capture),
texture errors, manifoldness and self-intersections, the phase timings (the
geometry-processing share against the paper's 55-70%), the peak memory (ru_maxrss) and the
material model the optimizer chose (when it reports one).

    python -m recon synth /tmp/blob --views 40 --res 256 --height 256 --format exr --object blob \
        --cameras --masks --no-noise
    python bench/optimize.py /tmp/blob --preset balanced --out bench/out/balanced
    python bench/optimize.py /tmp/blob --preset balanced --set optimizer=adam --out bench/out/adam
    python bench/optimize.py /tmp/blob --preset balanced --crude 0.04 --out bench/out/crude

``--crude A`` replaces the initial mesh by a smoothed, shrunk visual hull whose accuracy is
about A (the "crude initial mesh" scenario). ``--relight-spp 0`` skips the relighting metric.
``bench/suite.py`` runs this script over objects x presets.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import resource
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from recon.config import load_preset  # noqa: E402
from recon.io.atomic import atomic_path  # noqa: E402
from recon.io.cameras import Camera, load_cameras, look_at  # noqa: E402
from recon.io.images import read_exr  # noqa: E402
from recon.io.mesh import Mesh, read_mesh, write_obj  # noqa: E402
from recon.metrics import chamfer, image_rmse  # noqa: E402
from recon.optimize import OptimizeSettings, optimize_capture, settings_from_dict  # noqa: E402
from recon.optimize.guard import self_intersecting_faces  # noqa: E402
from recon.optimize.remesh import topology_report  # noqa: E402
from recon.render.envmap import envmap_image, relight_rmse  # noqa: E402
from recon.sections import move_flat  # noqa: E402

log = logging.getLogger("bench.optimize")


def novel_cameras(cams, n: int = 8) -> list[Camera]:
    """``n`` views between the capture's: other elevations, azimuths offset by a golden angle."""
    c0 = cams.frames[0]
    dist = float(np.median([np.linalg.norm(c.center) for c in cams.frames]))
    out = []
    for k in range(n):
        z = 0.75 - 1.0 * (k + 0.5) / n
        phi = 0.5 + k * 2 * np.pi / n
        s = np.sqrt(1 - z * z)
        eye = dist * np.array([s * np.cos(phi), s * np.sin(phi), z])
        out.append(Camera(f"novel/{k:02d}.exr", c0.width, c0.height, c0.K.copy(), look_at(eye, [0, 0, 0])))
    return out


def hit_masks(mesh: Mesh, cams: list[Camera]) -> list[np.ndarray]:
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.v_pos.astype(np.float32)), o3d.core.Tensor(mesh.t_pos_idx.astype(np.uint32)))
    out = []
    for c in cams:
        jj, ii = np.meshgrid(np.arange(c.width) + 0.5, np.arange(c.height) + 0.5)
        pix = np.stack([jj.ravel(), ii.ravel(), np.ones(jj.size)], 1)
        d = (pix @ np.linalg.inv(c.K).T) @ c.world_to_camera[:3, :3]
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        rays = np.concatenate([np.broadcast_to(c.center, d.shape), d], 1).astype(np.float32)
        out.append(np.isfinite(scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()).reshape(c.height, c.width))
    return out


def render(mesh: Mesh, maps: dict, cams: list[Camera], light: float, spp: int = 32) -> np.ndarray:
    import torch

    from recon.render import CollocatedRenderer, RenderSettings

    r = CollocatedRenderer(mesh.t_pos_idx, mesh.v_tex, mesh.t_tex_idx, RenderSettings(spp=spp, boundary="none"))
    with torch.no_grad():
        return r.render_torch(torch.tensor(mesh.v_pos, dtype=torch.float32),
                              *(torch.from_numpy(np.ascontiguousarray(maps[k])) for k in ("diffuse", "specular", "roughness")),
                              cams, light, seed=12345).numpy()


def texture_errors(rec: Mesh, maps: dict, gt: Mesh, gt_maps: dict, n: int = 20000) -> dict:
    """Per map: mean |rec - gt| over area-uniform gt surface points (rec looked up at the closest point)."""
    from recon.optimize.remesh import bilinear_lookup, surface_uv
    from recon.report.gt import sample_surface_uv

    p, uv_gt = sample_surface_uv(gt, n, np.random.default_rng(0))
    uv_rec = surface_uv(rec, p)
    out = {}
    for k in ("diffuse", "specular", "roughness"):
        a, c = bilinear_lookup(gt_maps[k], uv_gt), bilinear_lookup(maps[k], uv_rec)
        out[k] = {"mae": float(np.abs(a - c).mean()), "gt_mean": float(a.mean()), "rec_mean": float(c.mean())}
    return out


def relight_noise_floor(cap: Path, gt: Mesh, gt_maps: dict, novel: list[Camera], spp: int) -> dict:
    """The ground truth against itself under the envmap with independent seeds (cached).

    An upper bound on what Monte Carlo noise adds to ``relight_rmse``: the metric itself renders
    both sides with the same seeds, which cancels most of the noise where they agree.
    """
    cache = cap.parent / f"{cap.name}_bench" / f"relight_floor_n{len(novel)}_spp{spp}.json"
    if cache.is_file():
        return json.loads(cache.read_text())
    r = relight_rmse(gt, gt_maps, gt, gt_maps, novel, envmap_image(), spp=spp, seed_gt=100_003)
    with atomic_path(cache) as tmp:
        tmp.write_text(json.dumps(r))
    return r


class LoadSampler:
    """Samples the 1-minute load average every ``period`` seconds in a daemon thread.

    Other processes on the machine slow a run down; the mean load says by how much (on a
    machine with n cores, a load above n means the run did not have the cores to itself).
    """

    def __init__(self, period: float = 5.0):
        self.samples: list[float] = [os.getloadavg()[0]]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(period,), daemon=True)
        self._thread.start()

    def _run(self, period: float) -> None:
        while not self._stop.wait(period):
            self.samples.append(os.getloadavg()[0])

    def stop(self) -> dict:
        self._stop.set()
        self._thread.join()
        self.samples.append(os.getloadavg()[0])
        return {"mean": float(np.mean(self.samples)), "max": float(np.max(self.samples)),
                "cpu_count": os.cpu_count()}


def _cpu_seconds() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def code_version() -> dict:
    """The commit and the uncommitted changes of the code that ran (the working tree is shared)."""
    def git(*a):
        r = subprocess.run(["git", *a], cwd=REPO, capture_output=True, text=True)
        return r.stdout.rstrip() if r.returncode == 0 else None

    import hashlib

    status = git("status", "--porcelain", "--", "recon", "config", "bench")
    # a fingerprint of the uncommitted state: equal for runs of the same working tree
    h = hashlib.sha1((git("diff", "HEAD", "--", "recon", "config") or "").encode())
    for f in sorted((git("ls-files", "--others", "--exclude-standard", "--", "recon", "config") or "").split()):
        h.update(f.encode() + (REPO / f).read_bytes())
    return {"commit": git("rev-parse", "--short", "HEAD"),
            "uncommitted": status.splitlines() if status else [],
            "uncommitted_sha1": h.hexdigest()[:12]}


def material_report(summary: dict, out: Path) -> dict:
    """``material_model`` / ``material_selection`` of the optimize summary, where it has them."""
    path = out / "optimize" / "summary.json"
    src = dict(summary)
    if path.is_file():
        src = {**json.loads(path.read_text()), **src}
    return {k: src[k] for k in ("material_model", "material_selection") if k in src}


def crude_mesh(mesh: Mesh, gt: Mesh, target: float) -> Mesh:
    """Shrink + smooth the visual hull until its accuracy is about ``target`` (bisection on the shrink)."""
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(mesh.v_pos, mesh.t_pos_idx))
    ms.apply_coord_laplacian_smoothing(stepsmoothnum=10)
    sm = ms.current_mesh()
    base = Mesh(sm.vertex_matrix(), sm.face_matrix())
    c = base.v_pos.mean(0)
    lo, hi = 0.0, 0.5
    best = base
    for _ in range(12):
        s = 0.5 * (lo + hi)
        m = Mesh(c + (base.v_pos - c) * (1 - s), base.t_pos_idx)
        acc = chamfer(m, gt, n_samples=20000)["accuracy"]
        best = m
        if acc < target:
            lo = s
        else:
            hi = s
    return best


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("capture", type=Path)
    p.add_argument("--preset", default="balanced")
    p.add_argument("--set", action="append", default=[], help="key=value (YAML) overriding the preset's optimize section")
    p.add_argument("--init", type=Path, help="initial mesh (default: visual hull of the masks)")
    p.add_argument("--crude", type=float, help="use a crude initial mesh of about this accuracy")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--novel", type=int, default=8)
    p.add_argument("--relight-spp", type=int, default=64,
                   help="samples per pixel of the envmap relighting renders (0: skip the metric)")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s", datefmt="%H:%M:%S")

    cap = args.capture
    values = dict(load_preset(args.preset).get("optimize") or {})
    for kv in args.set:
        k, v = kv.split("=", 1)
        values[k] = yaml.safe_load(v)
    values, _ = move_flat(OptimizeSettings, values)  # a --set key is a setting's own name: into its section
    settings = settings_from_dict(values, f"preset {args.preset} + --set")
    gt = read_mesh(cap / "gt" / "mesh.obj")
    args.out.mkdir(parents=True, exist_ok=True)

    init_path = args.init
    if init_path is None:
        from recon.init_mesh import run_init_mesh

        hull = cap.parent / f"{cap.name}_init"
        if not (hull / "mesh.ply").is_file():
            run_init_mesh(cap / "cameras.json", cap / "masks", hull)
        init_path = hull / "mesh.ply"
    if args.crude is not None:
        init = crude_mesh(read_mesh(init_path), gt, args.crude)
        init_path = args.out / "crude_init.obj"
        write_obj(init_path, init)
    init = read_mesh(init_path)

    cams = load_cameras(cap / "cameras.json")
    images = [cap / c.image for c in cams.frames]
    masks = [cap / "masks" / f"{c.stem}.png" for c in cams.frames]
    version = code_version()
    import torch

    threads = {"torch": torch.get_num_threads(),
               **{k: os.environ.get(k) for k in ("OMP_WAIT_POLICY", "OMP_NUM_THREADS")}}
    load = LoadSampler()
    cpu0 = _cpu_seconds()
    t0 = time.perf_counter()
    summary = optimize_capture(images, masks, None, cap / "cameras.json", init_path, args.out / "optimize", settings)
    wall = time.perf_counter() - t0
    cpu = _cpu_seconds() - cpu0
    load_avg = load.stop()

    final = read_mesh(args.out / "optimize" / "mesh.obj")
    acc0 = chamfer(init, gt)
    acc1 = chamfer(final, gt)
    maps = {k: read_exr(args.out / "optimize" / f"{k}.exr") for k in ("diffuse", "specular", "roughness")}
    gt_maps = {k: read_exr(cap / "gt" / f"{k}.exr") for k in ("diffuse", "specular", "roughness")}
    novel = novel_cameras(cams, args.novel)
    img_rec = render(final, maps, novel, cams.light_intensity)
    img_gt = render(gt, gt_maps, novel, cams.light_intensity)
    m_rec, m_gt = hit_masks(final, novel), hit_masks(gt, novel)
    rmse = [image_rmse(a, b, ma, mb) for a, b, ma, mb in zip(img_rec, img_gt, m_rec, m_gt, strict=True)]
    topo = topology_report(final.v_pos, final.t_pos_idx)
    tex = texture_errors(final, maps, gt, gt_maps)
    relight = {}
    if args.relight_spp > 0:
        t1 = time.perf_counter()
        rl = relight_rmse(final, maps, gt, gt_maps, novel, envmap_image(), spp=args.relight_spp)
        floor = relight_noise_floor(cap, gt, gt_maps, novel, args.relight_spp)
        relight = {
            "relight_rmse": rl["mean"],
            "relight_rmse_per_view": rl["per_view"],
            "relight_noise_floor": floor["mean"],
            "relight_spp": args.relight_spp,
            "relight_seconds": time.perf_counter() - t1,
        }
    result = {
        "capture": str(cap),
        "code_version": version,
        "preset": args.preset,
        "overrides": args.set,
        "init": str(init_path),
        # chamfer() divides by the GT bbox's longest side: the DESIGN section 5 unit scale
        "accuracy_units": "gt_bbox_longest_side",
        "init_accuracy": acc0,
        "final_accuracy": acc1,
        "accuracy_ratio": acc0["accuracy"] / acc1["accuracy"],
        "novel_view_rmse": float(np.mean(rmse)),
        "novel_view_rmse_per_view": rmse,
        **relight,
        "texture_errors": tex,
        "manifold": bool(topo["is_mesh_two_manifold"]),
        "boundary_edges": int(topo["boundary_edges"]),
        "self_intersecting_faces": int(self_intersecting_faces(final.v_pos, final.t_pos_idx).sum()),
        "wall_seconds": wall,
        # CPU time (user + system, all threads) of the optimize stage, and the machine's load
        # average while it ran: wall time depends on what else runs, CPU time much less
        "cpu_seconds": cpu,
        "load_average": load_avg,
        "threads": threads,
        "phase_fraction": summary["phase_fraction"],
        "phase_seconds": summary["phase_seconds"],
        "stages": summary["stages"],
        "final_losses": summary["final_losses"],
        "settings": summary.get("settings"),
        **material_report(summary, args.out),
        # Linux: ru_maxrss is in KiB; the peak of this process (optimize runs in it)
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }
    np.save(args.out / "novel_render.npy", np.stack([img_rec, img_gt]))
    with atomic_path(args.out / "bench.json") as tmp:  # last: its presence means "done"
        tmp.write_text(json.dumps(result, indent=1))
    keys = ("init_accuracy", "final_accuracy", "accuracy_ratio", "novel_view_rmse", "relight_rmse",
            "relight_noise_floor", "texture_errors", "manifold", "self_intersecting_faces", "wall_seconds",
            "phase_fraction", "peak_rss_mb", "material_model")
    print(json.dumps({k: result[k] for k in keys if k in result}, indent=1))  # noqa: T201 (a command line tool's report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
