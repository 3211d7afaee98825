"""Probe: directional vertex derivatives of the Mitsuba comparison scene against ours and FD.

On ``bench/render.py``'s bumpy sphere (one view, per-vertex UVs without a seam) it prints, for
three displacement fields (translation, scale, a smooth normal field), the central finite
difference of the weighted-sum loss (our renderer, 256 spp, and Mitsuba ``direct``, 256 spp)
and the derivative predicted by: our renderer with edge sampling, ours interior only, Mitsuba
``direct`` (interior only) and Mitsuba ``direct_projective`` through
``recon.render.mitsuba_scene.MitsubaScene`` (16 spp, one run each: a few percent of noise).

Run: ``.venv/bin/python bench/mitsuba_grad_probe.py [--res 96]`` (about 2 minutes on 2 cores).
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

import render as bench_render  # noqa: E402

from recon.render import CollocatedRenderer, RenderSettings  # noqa: E402
from recon.render.mitsuba_scene import MitsubaScene  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--res", type=int, default=96)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--views", type=int, default=1, help="1, or 2: a second view from another side (own light)")
    args = ap.parse_args(argv)
    sc = bench_render.make_scene(args.res)
    ours = CollocatedRenderer(sc["f"], sc["t"], sc["ft"], RenderSettings(spp=args.spp, boundary="edge"))
    inter = CollocatedRenderer(sc["f"], sc["t"], sc["ft"], RenderSettings(spp=args.spp, boundary="none"))
    fd_r = CollocatedRenderer(sc["f"], sc["t"], sc["ft"], RenderSettings(spp=256, boundary="none"))
    mi, dr = ours.mi, ours.dr
    direct, proj = MitsubaScene(ours, "direct"), MitsubaScene(ours, "direct_projective")
    maps = (sc["diffuse"], sc["specular"], sc["roughness"])
    cams, light, h = [sc["cam"]], 12.0, 5e-3
    if args.views == 2:
        from recon.io.cameras import Camera, intrinsics, look_at

        cams.append(Camera("second.png", args.res, args.res, intrinsics(args.res, args.res, 40.0),
                           look_at((-2.8, -2.4, 1.4), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0))))
        sc["w"] = np.stack([sc["w"], sc["w"][::-1]])  # a different weighting per view

    def loss(img) -> float:
        return float((np.asarray(img, np.float64) * sc["w"]).sum())

    def ours_img(v):
        return np.stack([im.numpy() for im in fd_r.render(v, *maps, cams, light, 0)])

    def mi_img(v):
        return direct.render(mi.TensorXf(v.astype(np.float32)), *maps, cams, light, 0, 256).numpy()

    methods = {
        "ours (edge)": lambda v, s: ours.render_batch(v, *maps, cams, light, s),
        "ours interior": lambda v, s: inter.render_batch(v, *maps, cams, light, s),
        "mitsuba direct": lambda v, s: direct.render(v, *maps, cams, light, s, args.spp),
        "mitsuba direct_projective": lambda v, s: proj.render(v, *maps, cams, light, s, args.spp),
    }
    grads = {k: bench_render._loss_grad(fn, mi, dr, sc, 1)[0] for k, fn in methods.items()}
    for name, d in sc["dirs"].items():
        fd = (loss(ours_img(sc["v"] + h * d)) - loss(ours_img(sc["v"] - h * d))) / (2 * h)
        mfd = (loss(mi_img(sc["v"] + h * d)) - loss(mi_img(sc["v"] - h * d))) / (2 * h)
        pred = "  ".join(f"{k} {float((g * d).sum()):.4g}" for k, g in grads.items())
        bench_render.out(f"{name}: FD ours {fd:.4g}  FD mitsuba {mfd:.4g}  |  {pred}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
