"""A small but complete set of report inputs, built in a temporary folder.

A UV sphere (lat-long UVs, a seam at u = 0/1) with spatially varying maps, three views and one
held-out view, written in the layout of DESIGN section 2::

    <root>/results/cap/optimize/{mesh.obj, diffuse.exr, specular.exr, roughness.exr,
                                 log.jsonl, summary.json, cameras.json}
    <root>/results/cap/export/asset.glb           (recon.export.export_asset)
    <root>/results/cap/poses/cameras.json
    <root>/results/cap/linear/<stem>.exr          inputs: the model rendered by the forward
    <root>/results/cap/masks/<stem>.png           reference (view 0 brightened by +0.1 in sRGB)
    <root>/results/cap/benchmarks/<stage>.tsv     Snakemake benchmark files
    <root>/captures/cap/gt/                       the same model as ground truth (+ held-out view)
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from recon.io.cameras import Camera, CameraSet, intrinsics, look_at, save_cameras
from recon.io.images import linear_to_srgb, srgb_to_linear, write_exr, write_mask
from recon.io.mesh import Mesh, read_obj, write_obj

WIDTH, HEIGHT = 64, 48
SPP = 8
LIGHT = 6.0
OFFSET = 0.1  # sRGB offset added to view 0's input: its RMSE is exactly this
SRGB_MAX = 0.85  # every rendered sRGB value stays below 1 - OFFSET, so nothing clips


def uv_sphere(n_lat: int = 12, n_lon: int = 24, radius: float = 0.5) -> Mesh:
    """Lat-long sphere with outward faces; UVs in the OBJ convention (v up = north pole)."""
    theta = np.linspace(0, np.pi, n_lat + 1)  # from the north pole (z = +r)
    phi = np.linspace(0, 2 * np.pi, n_lon + 1)
    T, P = np.meshgrid(theta, phi, indexing="ij")
    uv = np.stack([P / (2 * np.pi), 1 - T / np.pi], axis=-1).reshape(-1, 2)
    # positions: the seam column (phi = 2 pi) and the pole rows map to shared vertices
    pos_index = {}
    v_pos, tex_to_pos = [], []
    for i in range(n_lat + 1):
        for j in range(n_lon + 1):
            jj = j % n_lon
            key = (0, 0) if i == 0 else ((n_lat, 0) if i == n_lat else (i, jj))
            if key not in pos_index:
                t, p = theta[i], phi[jj]
                pos_index[key] = len(v_pos)
                v_pos.append(radius * np.array([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)]))
            tex_to_pos.append(pos_index[key])
    tex_to_pos = np.array(tex_to_pos)
    faces = []
    for i in range(n_lat):
        for j in range(n_lon):
            a, b = i * (n_lon + 1) + j, i * (n_lon + 1) + j + 1
            c, d = a + (n_lon + 1), b + (n_lon + 1)
            if i > 0:
                faces.append([a, c, b])
            if i < n_lat - 1:
                faces.append([b, c, d])
    t_tex = np.array(faces)
    return Mesh(np.array(v_pos), tex_to_pos[t_tex], uv, t_tex)


def maps(size: int = 32) -> dict[str, np.ndarray]:
    """Saturated colours (red one half, blue-green the other) so a screenshot shows the model."""
    y, x = (np.mgrid[0:size, 0:2 * size] + 0.5) / np.array([size, 2 * size])[:, None, None]
    red = (x < 0.5)[..., None]
    a_d = np.where(red, [0.8, 0.05, 0.04], [0.05, 0.35, 0.7]) * (0.6 + 0.4 * y[..., None])
    a_s = (0.03 + 0.2 * x)[..., None]
    r = (0.35 + 0.5 * y)[..., None]
    return {"diffuse": a_d.astype(np.float32), "specular": a_s.astype(np.float32),
            "roughness": r.astype(np.float32)}


def cameras(stems=("v000", "v001", "v002"), start: float = 0.4) -> CameraSet:
    frames = []
    for k, stem in enumerate(stems):
        a = start + 2 * np.pi * k / len(stems)
        eye = 2.2 * np.array([np.cos(a), np.sin(a), 0.45])
        frames.append(Camera(f"images/{stem}.dng", WIDTH, HEIGHT, intrinsics(WIDTH, HEIGHT, 40.0),
                             look_at(eye, np.zeros(3), (0.0, 0.0, 1.0))))
    return CameraSet(tuple(frames), light_intensity=LIGHT)


LOG_RECORDS = [
    {"stage": 0, "iteration": 0, "views": [0, 2], "loss": 0.5, "loss_image": 0.45, "t_geometry": 0.1,
     "t_render": 0.25, "t_loss": 0.01, "t_backward": 0.5, "t_step": 0.01},
    {"stage": 0, "iteration": 1, "views": [1, 0], "loss": 0.3, "loss_image": 0.27, "t_geometry": 0.1,
     "t_render": 0.25, "t_loss": 0.01, "t_backward": 0.5, "t_step": 0.01},
    {"stage": 1, "iteration": 0, "views": [2, 1], "loss": 0.2, "loss_image": 0.18, "t_geometry": 0.3,
     "t_render": 0.5, "t_loss": 0.02, "t_backward": 1.0, "t_step": 0.02},
    {"stage": 1, "iteration": 1, "views": [0, 1], "loss": 0.1, "loss_image": 0.09, "t_geometry": 0.3,
     "t_render": 0.5, "t_loss": 0.02, "t_backward": 1.0, "t_step": 0.02},
]
"""A log in the optimize stage's format (recon.optimize.loop): one record per iteration, the
iteration counted per coarse-to-fine stage, per-phase seconds as ``t_<phase>``."""

SUMMARY = {
    "wall_seconds": 12.5,
    "phase_seconds": {"render": 1.5, "loss": 0.06, "backward": 3.0, "step": 0.06, "geometry": 1.3,
                      "setup": 0.7},
    "iterations": 4,
    "stages": [{"stage": 0, "texture_size": 32, "edge_length": 0.04, "iterations": 2,
                "seconds": {"render": 0.5, "backward": 1.0}},
               {"stage": 1, "texture_size": 64, "edge_length": 0.02, "iterations": 2,
                "seconds": {"render": 1.0, "backward": 2.0}}],
    "settings": {"specular_channels": 1, "r_min": 0.02, "lr": 0.01},
}
"""summary.json in the optimize stage's format: totals per phase (geometry includes remeshing
outside the iterations, so it is more than the log's sum)."""

BENCHMARKS = {"linearize": [1.5], "optimize": [40.0, 44.0]}
"""Stage -> benchmark repeats' seconds (the report shows their mean)."""

MATERIAL = {"specular_channels": 1, "r_min": 0.02}
"""What the report shows as the material model: the material settings of SUMMARY."""


@dataclass
class Scene:
    root: Path
    results: Path
    capture_dir: Path
    mesh: Mesh
    textures: dict
    cams: CameraSet
    expected_rmse: dict = field(default_factory=dict)

    @property
    def optimize(self) -> Path:
        return self.results / "optimize"

    def report_args(self, out: Path | None = None, gt: bool = True, benchmarks: bool = True) -> dict:
        return dict(
            capture="cap",
            optimize_dir=self.optimize,
            glb=self.results / "export" / "asset.glb",
            cameras=self.results / "poses" / "cameras.json",
            image_dirs=[self.results / "poses" / "undistorted", self.results / "linear"],
            mask_dirs=[self.results / "masks"],
            out_dir=out or self.results / "report",
            gt_dir=self.capture_dir / "gt" if gt else None,
            benchmarks_dir=self.results / "benchmarks" if benchmarks else None,
            preset="draft",
        )


def write_tsv(path: Path, seconds: list[float]) -> None:
    head = "s\th:m:s\tmax_rss\tmax_vms\tmax_uss\tmax_pss\tio_in\tio_out\tmean_load\tcpu_time\n"
    rows = "".join(f"{s}\t0:00:{s:05.2f}\t100.0\t200.0\t90.0\t95.0\t0.1\t0.2\t50.0\t{s}\n" for s in seconds)
    path.write_text(head + rows)


def build(root: Path) -> Scene:
    """Write every input the report reads; see the module docstring."""
    from recon.export import ExportSettings, export_asset
    from recon.render.mitsuba_bsdf import render_reference

    results = root / "results" / "cap"
    capture_dir = root / "captures" / "cap"
    opt = results / "optimize"
    opt.mkdir(parents=True)
    write_obj(opt / "mesh.obj", uv_sphere())
    mesh = read_obj(opt / "mesh.obj")  # exactly what the report will read
    tex = maps()
    for k, a in tex.items():
        write_exr(opt / f"{k}.exr", a)
    (opt / "log.jsonl").write_text("".join(json.dumps(r) + "\n" for r in LOG_RECORDS))
    (opt / "summary.json").write_text(json.dumps(SUMMARY))

    cams = cameras()
    save_cameras(results / "poses" / "cameras.json", cams)
    save_cameras(opt / "cameras.json", cams)  # the optimize stage's cameras (given ones pass unchanged)
    export_asset(opt / "mesh.obj", opt / "diffuse.exr", opt / "specular.exr", opt / "roughness.exr",
                 results / "export", ExportSettings(), cameras_json=results / "poses" / "cameras.json")

    # Inputs: the forward reference with the report's seeds (settings.seed + view index), so the
    # re-render of view k equals its input up to what is added here.
    (results / "linear").mkdir(parents=True)
    expected = {}
    for k, cam in enumerate(cams.frames):
        img = render_reference(mesh, tex, cam, light_intensity=LIGHT, spp=SPP, seed=k)
        srgb = linear_to_srgb(img)
        assert srgb.max() < SRGB_MAX, "test scene too bright: the +OFFSET input would clip"
        write_mask(results / "masks" / f"{cam.stem}.png", img.max(axis=2) > 0)
        if k == 0:
            img = srgb_to_linear(srgb + OFFSET)
            expected[cam.stem] = OFFSET
        else:
            expected[cam.stem] = 0.0
        write_exr(results / "linear" / f"{cam.stem}.exr", img)

    bench = results / "benchmarks"
    bench.mkdir()
    for stage, sec in BENCHMARKS.items():
        write_tsv(bench / f"{stage}.tsv", sec)

    gt = capture_dir / "gt"
    gt.mkdir(parents=True)
    write_obj(gt / "mesh.obj", mesh)
    for k, a in tex.items():
        write_exr(gt / f"{k}.exr", a)
    held_out = cameras(("h000",), start=1.3).frames
    save_cameras(gt / "cameras.json", CameraSet(cams.frames + held_out, light_intensity=LIGHT))
    return Scene(root, results, capture_dir, mesh, tex, cams, expected)
