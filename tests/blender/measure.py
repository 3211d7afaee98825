"""Measure the asset in Blender against recon's renderer; write the side-by-side images of
docs/viewers.md. Reproduces every number there:

    .venv/bin/python tests/blender/measure.py --out docs/img/viewers [--results results/demo]

Without ``--results`` only the ground-truth asset of captures/demo is measured (as the tests
do); with it, also the export of that pipeline run (the demo's optimized asset).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from blender_case import DEMO_GT, asset_views, run_blender  # noqa: E402
from export_readers import read_glb, read_usdz  # noqa: E402

from recon.export import ExportSettings, export_asset  # noqa: E402
from recon.io.cameras import load_cameras  # noqa: E402
from recon.io.images import linear_to_srgb, read_exr, write_png  # noqa: E402
from recon.metrics import image_rmse  # noqa: E402
from recon.render.mitsuba_bsdf import render_reference  # noqa: E402

VARIANTS = [  # name, file, extra arguments of tools/blender/recon_blender.py
    ("glb", "glb", ()),
    ("glb, GGX (not multiscatter)", "glb", ("--distribution", "GGX")),
    ("usdz as imported", "usdz", ()),
    ("usdz + fix_usd_specular", "usdz", ("--fix-usd-specular",)),
]


def _say(line: str) -> None:
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


def _recon(asset, views, intensity, specular_only=False):
    tex = {"diffuse": np.zeros_like(asset.a_d) if specular_only else asset.a_d,
           "specular": asset.a_s, "roughness": asset.r}
    return [render_reference(asset.mesh, tex, c, intensity, spp=64, seed=k, alpha=True)
            for k, c in enumerate(views)]


def _rmse(folder: Path, prefix: str, refs) -> list[float]:
    out = []
    for k, ref in enumerate(refs):
        img = read_exr(folder / f"{prefix}_{k}.exr")
        out.append(image_rmse(img[..., :3], ref[..., :3], img[..., 3] > 0.5, ref[..., 3] > 0.5))
    return out


def measure(name: str, export: Path, cameras_json: Path, work: Path, img_out: Path | None):
    cams = load_cameras(cameras_json)
    _say(f"\n## {name}: {export}")
    _say("| in Blender | sRGB RMSE per view (full) | mean | specular lobe alone | mean |")
    _say("|---|---|---|---|---|")
    tiles = {}
    refs_full = None
    for label, fmt, extra in VARIANTS:
        asset = (read_glb if fmt == "glb" else read_usdz)(export / f"asset.{fmt}")
        views, intensity = asset_views(cams, asset.object_to_world)
        if refs_full is None:
            refs_full = _recon(asset, views, intensity)
            refs_spec = _recon(asset, views, intensity, specular_only=True)
            tiles["recon"] = [r[..., :3] for r in refs_full]
        out = work / f"{name}_{label.replace(' ', '_').replace(',', '').replace('+', 'plus')}"
        run_blender(export / f"asset.{fmt}", out, views, intensity, extra)
        full, spec = _rmse(out, "view", refs_full), _rmse(out, "specular", refs_spec)
        _say(f"| {label} | {' / '.join(f'{x:.4f}' for x in full)} | {np.mean(full):.4f} | "
              f"{' / '.join(f'{x:.4f}' for x in spec)} | {np.mean(spec):.4f} |")
        tiles[label] = [read_exr(out / f"view_{k}.exr")[..., :3] for k in range(len(views))]
    glb_out = work / f"{name}_glb"
    wrong = [render_reference(asset.mesh, {"diffuse": np.zeros_like(asset.a_d),
                                           "specular": asset.a_s, "roughness": asset.r ** 2},
                              c, intensity, spp=64, seed=k, alpha=True) for k, c in enumerate(views)]
    _say(f"negative control, glb specular lobe against recon with r -> r^2: "
          f"{' / '.join(f'{x:.4f}' for x in _rmse(glb_out, 'specular', wrong))}")
    if img_out is not None:
        cols = ["recon", "glb", "usdz as imported", "usdz + fix_usd_specular"]
        rows = []
        for k in range(len(tiles["recon"])):
            row = [linear_to_srgb(np.clip(tiles[c][k], 0, None)) for c in cols]
            diff = np.abs(row[1] - row[0]).mean(axis=2, keepdims=True)
            row.append(np.repeat(np.clip(4 * diff, 0, 1), 3, axis=2))
            rows.append(np.concatenate(row, axis=1))
        img = np.concatenate(rows, axis=0)
        img = np.repeat(np.repeat(img, 2, axis=0), 2, axis=1)
        img_out.mkdir(parents=True, exist_ok=True)
        path = img_out / f"blender_{name}.png"
        write_png(path, img)
        _say(f"wrote {path} (columns: {', '.join(cols)}, 4 x |glb - recon|)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, help="folder for the side-by-side PNGs")
    ap.add_argument("--results", type=Path, help="a pipeline run's results/<capture> folder")
    args = ap.parse_args()
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from recon.mi import load_variant

    load_variant("llvm_ad_rgb")
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        gt_export = work / "gt_export"
        export_asset(DEMO_GT / "mesh.obj", DEMO_GT / "diffuse.exr", DEMO_GT / "specular.exr",
                     DEMO_GT / "roughness.exr", gt_export, ExportSettings(),
                     cameras_json=DEMO_GT / "cameras.json")
        measure("demo_gt", gt_export, DEMO_GT / "cameras.json", work, args.out)
        if args.results:
            measure("demo_optimized", args.results / "export", args.results / "poses" / "cameras.json",
                    work, args.out)


if __name__ == "__main__":
    main()
