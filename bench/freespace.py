"""The initial mesh with and without the free space of SfM's points and of the photos' depth maps
(recon.freespace, recon.mvs; docs/init_mesh.md, "Carving what the photos saw through" and
"Dense points").

For each scene: the poses stage's results of a synthetic capture (``<results>/<scene>``: SfM's
cameras, masks, plane and sparse model) and the capture's ground truth (``<captures>/<scene>/gt``).
The hull's field is built once with the draft preset's init_mesh settings; then carved. Prints
per scene: the hull voxels that are not the object, the voxels the carving removed and how many
of them lie inside the true object (wrong), and the raw surface's genus, accuracy, completeness
and share of it farther than 2 % of the object's size from it (all in units of the true bounding
box's longest side), without carving, carved by SfM's points alone, and carved by them and the
depth maps (the views from ``poses/undistorted``, or ``linear`` for given cameras). ``--figure`` writes a vertical section
through each scene's true centre (true surface green, the surfaces red).

    .venv/bin/python bench/freespace.py --results /tmp/e2e/results --captures /tmp/e2e/captures \\
        --scenes dark-bowl wood-blob glossy-mug --figure docs/img/freespace.png
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from recon import freespace as fs_mod  # noqa: E402
from recon import init_mesh as rim  # noqa: E402
from recon.io.cameras import load_cameras  # noqa: E402
from recon.io.mesh import Mesh, read_obj  # noqa: E402
from recon.metrics import align_cameras, distance_to_mesh  # noqa: E402
from recon.support import plane_if_found  # noqa: E402


def _surface(field, grid, sim) -> Mesh:
    m = rim.largest_component(rim.isosurface(field, grid))
    return Mesh(sim.apply(m.v_pos), m.t_pos_idx)


def _measure(m: Mesh, gt: Mesh, unit: float) -> dict:
    rng = np.random.default_rng(0)
    d = distance_to_mesh(gt, m.sample_surface(20000, rng)) / unit
    c = distance_to_mesh(m, gt.sample_surface(20000, rng)) / unit
    return {"genus": rim.topology(m)["genus"], "accuracy": float(d.mean()), "completeness": float(c.mean()),
            "far_2pct": float((d > 0.02).mean())}


def scene(results: Path, captures: Path, name: str, settings: rim.InitMeshSettings) -> dict:
    import open3d as o3d

    res, cap = results / name, captures / name
    cams = load_cameras(res / "poses" / "cameras.json")
    masks = rim._read_masks_for(cams, res / "poses" / "undistorted" / "masks")
    plane_json = res / "poses" / "plane.json"
    plane = plane_if_found(plane_json) if plane_json.is_file() else None
    center, half, _ = rim.hull_bounds(cams, masks, settings, plane=plane)
    grid = rim.Grid.cube(center, half, settings.resolution)
    field, _, _ = rim.hull_field(cams, masks, grid, settings, plane)
    seen = fs_mod.seen_points(res / "poses" / "sparse", cams, settings) if (res / "poses" / "sparse").is_dir() else None
    carved, info = fs_mod.carve_hull(field, grid, seen, settings) if seen is not None else (field, {"kept": False})
    views_dir = res / "poses" / "undistorted" if seen is not None else res / "linear"
    from recon.io.images import read_exr

    dense, dinfo = fs_mod.carve_hull(field, grid, seen, settings, cams, masks,
                                     lambda stem: read_exr(views_dir / f"{stem}.exr"))
    sim = align_cameras(cams, load_cameras(cap / "gt" / "cameras.json"))
    gt = read_obj(cap / "gt" / "mesh.obj")
    lo, hi = gt.bbox()
    unit = float(np.max(hi - lo))
    scene_ = o3d.t.geometry.RaycastingScene()
    scene_.add_triangles(o3d.core.Tensor(gt.v_pos.astype(np.float32)), o3d.core.Tensor(gt.t_pos_idx.astype(np.uint32)))
    occ = scene_.compute_occupancy(o3d.core.Tensor(sim.apply(grid.points()).astype(np.float32))).numpy()
    occ = occ.reshape(field.shape) > 0
    inside = field > 0
    removed = inside & (carved <= 0)
    removed_d = inside & (dense <= 0)
    hull, cut, cut_d = _surface(field, grid, sim), _surface(carved, grid, sim), _surface(dense, grid, sim)
    return {"scene": name, "hull_not_object": int((inside & ~occ).sum()), "hull_voxels": int(inside.sum()),
            "carved": int(removed.sum()), "carved_wrong": int((removed & occ).sum()), "kept": info["kept"],
            "carved_dense": int(removed_d.sum()), "carved_dense_wrong": int((removed_d & occ).sum()),
            "kept_dense": dinfo["kept"], "dense_points": (dinfo.get("dense") or {}).get("points", 0),
            "hull": _measure(hull, gt, unit), "with": _measure(cut, gt, unit), "dense": _measure(cut_d, gt, unit),
            "meshes": (gt, hull, cut_d)}


def figure(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axs = plt.subplots(len(rows), 2, figsize=(8, 2.6 * len(rows)), squeeze=False)
    for r, ax_row in zip(rows, axs, strict=True):
        gt, hull, cut = r["meshes"]
        c = gt.v_pos.mean(0)

        def section(m, y=c[1]):
            p = m.sample_surface(300000, np.random.default_rng(0))
            return p[np.abs(p[:, 1] - y) < 0.01]

        g = section(gt)
        for ax, (title, m) in zip(ax_row, (("visual hull", hull), ("carved (SfM's points, depth maps)", cut)),
                                  strict=True):
            p = section(m)
            ax.scatter(g[:, 0], g[:, 2], s=0.2, c="tab:green")
            ax.scatter(p[:, 0], p[:, 2], s=0.2, c="tab:red")
            ax.set_aspect("equal")
            ax.set_title(f"{r['scene']}: {title}", fontsize=8)
            ax.set_xticks([])
            ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--results", type=Path, required=True)
    ap.add_argument("--captures", type=Path, required=True)
    ap.add_argument("--scenes", nargs="+", required=True)
    ap.add_argument("--preset", default="draft")
    ap.add_argument("--figure", type=Path, default=None)
    a = ap.parse_args(argv)
    preset = Path(__file__).resolve().parents[1] / "config" / "presets" / f"{a.preset}.yaml"
    settings = rim.InitMeshSettings(**(yaml.safe_load(preset.read_text()).get("init_mesh") or {}))
    rows = []
    out = sys.stdout
    out.write("| scene | hull voxels not the object | carved: SfM / + depth maps (inside the object) | dense points | "
              "genus | accuracy: hull / SfM / + depth maps | completeness | surface > 2 % away |\n"
              "|---|---|---|---|---|---|---|---|\n")
    for name in a.scenes:
        r = scene(a.results, a.captures, name, settings)
        rows.append(r)
        h, w, d = r["hull"], r["with"], r["dense"]
        kept = "" if r["kept"] or not r["carved"] else " (left out)"
        kept_d = "" if r["kept_dense"] or not r["carved_dense"] else " (left out)"
        out.write(f"| {name} | {r['hull_not_object']:,} of {r['hull_voxels']:,} | {r['carved']:,} ({r['carved_wrong']:,})"
                  f"{kept} / {r['carved_dense']:,} ({r['carved_dense_wrong']:,}){kept_d} | {r['dense_points']:,} "
                  f"| {h['genus']} / {w['genus']} / {d['genus']} | {h['accuracy']:.4f} / {w['accuracy']:.4f} / "
                  f"{d['accuracy']:.4f} | {h['completeness']:.4f} / {w['completeness']:.4f} / {d['completeness']:.4f} "
                  f"| {100 * h['far_2pct']:.1f} / {100 * w['far_2pct']:.1f} / {100 * d['far_2pct']:.1f} % |\n")
        out.flush()
    if a.figure is not None:
        os.makedirs(a.figure.parent, exist_ok=True)
        figure([r for r in rows if r["carved_dense"]] or rows[:1], a.figure)
    return 0


if __name__ == "__main__":
    sys.exit(main())
