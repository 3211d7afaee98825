"""Benchmark: material-model selection on a synthetic capture with the true mesh.

Makes (or reuses) a capture with ``recon synth`` settings, fits the full model on the training
views as the main loop would (300 Adam steps from constant maps), runs ``select_material`` with
every 4th view held out, and prints every step: held-out error of the candidate and of its
control, gain, SE, the gain with a 2 % trim, and the share of the net gain carried by the top
2 % of tiles (where highlights are); then the chosen model and the correlation of the recovered
specular and roughness maps with the truth over the covered texels.

Run: ``.venv/bin/python bench/selection.py --out bench/out/selection [--views 40 --width 192
--height 144 --seed 0 --spp 2]`` (1-4 minutes on 2 cores at these sizes). ``--specular 0``
makes the purely diffuse object.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from recon.io.cameras import load_cameras  # noqa: E402
from recon.io.images import read_exr  # noqa: E402
from recon.io.mesh import read_obj  # noqa: E402
from recon.optimize.heldout import compare  # noqa: E402
from recon.optimize.material import DIFFUSE_ONLY, SelectionSettings  # noqa: E402
from recon.optimize.material_select import select_on_known_mesh  # noqa: E402
from recon.optimize.remesh import rasterize_atlas  # noqa: E402
from recon.optimize.views import Views  # noqa: E402
from recon.synth.capture import SynthSettings, make_capture  # noqa: E402


def out(line: str) -> None:
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("bench/out/selection"))
    ap.add_argument("--views", type=int, default=40)
    ap.add_argument("--width", type=int, default=192)
    ap.add_argument("--height", type=int, default=144)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--spp", type=int, default=2, help="G-buffer samples per pixel")
    ap.add_argument("--specular", type=float, default=None, help="constant specular albedo (0: diffuse object)")
    args = ap.parse_args(argv)
    tag = f"blob_{args.views}v_{args.width}x{args.height}_s{args.seed}" + (
        "" if args.specular is None else f"_spec{args.specular:g}")
    cap = args.out / tag
    if not (cap / "cameras.json").is_file():
        make_capture(cap, SynthSettings(object="blob", n_views=args.views, width=args.width, height=args.height,
                                        format="exr", spp=16, seed=args.seed, mesh_level=5, texture_size=256,
                                        write_masks=True, write_cameras=True, write_gt_linear=False,
                                        specular=args.specular))
    t0 = time.perf_counter()
    mesh, cams = read_obj(cap / "gt" / "mesh.obj"), load_cameras(cap / "gt" / "cameras.json")  # the true cameras and flash (the true mesh's problem)
    size = args.width
    views = Views([cap / c.image for c in cams.frames], [cap / "masks" / f"{c.stem}.png" for c in cams.frames],
                  None, cams, size)
    held = [i for i in range(len(views)) if i % 4 == 2]
    train = views.subset([i for i in range(len(views)) if i % 4 != 2]).at(size)
    heldout = views.subset(held).at(size)
    s = SelectionSettings(iterations=150)
    light, scale = views.light_intensity, views.median_foreground
    evals = []  # every fit in order: controls and candidates
    fit, ev = select_on_known_mesh(mesh, train, heldout, light, scale, s, spp=args.spp,
                                   progress=lambda m, f: evals.append((m, f.tile_errors)))
    out(f"{tag}: {len(train)} training / {len(heldout)} held-out views at {size} px, "
        f"{time.perf_counter() - t0:.0f} s; chosen {ev['chosen']}")
    # pair each candidate with the control it was compared against (see select_material)
    current, control, rows = DIFFUSE_ONLY, None, iter(ev["candidates"][1:])
    for model, tiles in evals[1:]:
        if model == current:
            control = tiles
            continue
        r = next(rows)
        ok = np.isfinite(tiles) & np.isfinite(control)
        d = np.sort(control[ok] - tiles[ok])
        top = d[-max(1, int(0.02 * d.size)):].sum()
        trimmed = compare(tiles, control, dataclasses.replace(s, trim=0.02))
        out(f"  {r['step']:28s} held-out {r['heldout_error']:.5f} (control {r['control_heldout_error']:.5f}) "
            f"gain {r['gain']:+.5f} = {100 * r['relative_gain']:+.1f} % at {r['gain'] / r['se']:.1f} SE "
            f"[2 % trim: {trimmed['gain']:+.5f}; top 2 % of tiles carry "
            f"{100 * top / d.sum() if d.sum() else float('nan'):.0f} % of the net gain] "
            f"{'kept' if r['accepted'] else 'rejected'}")
        if r["accepted"]:
            current, control = model, None
    T = fit.maps["roughness"].shape[0]  # the ground truth maps share the true mesh's atlas
    covered = rasterize_atlas(mesh, T)[0] >= 0
    for name in ("specular", "roughness"):
        gt = read_exr(cap / "gt" / f"{name}.exr").reshape(T, T)
        rec = fit.maps[name][..., 0]
        if np.std(gt[covered]) > 0 and np.std(rec[covered]) > 0:
            out(f"  {name}: correlation with the truth {np.corrcoef(rec[covered], gt[covered])[0, 1]:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
