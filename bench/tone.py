"""Benchmark: the tone curve and per-view exposure recovered however the phone made them (issue 31 item 2).

For each tone curve of the generator (``recon.synth.imaging.TONE_CURVES``: plain sRGB, the
project's S-curve, gamma 2.2, Hable's filmic, a phone-like table, a toe-and-shoulder curve) it
makes a synthetic JPEG capture (void blob, glossy, sensor noise, EXIF exposure stepping by
``--exposure-variation`` stops, an unrecorded per-view exposure error of ``--exposure-jitter``
stops, bright enough that the lit side reaches the shoulder), linearizes it with the real
linearize stage and, on the TRUE mesh starting from the TRUE maps (G-buffer fits: geometry fixed),
fits

- ``control``: the material maps and the per-view exposure gains (``ImagingModel(("exposure",))``),
- ``first``: + the tone term as first designed (``ImagingSettings(tone_gain=False)``: the curve on
  the EXIF-normalized values, its input scale fixed at 1),
- ``fixed``: + the tone term as now (the curve on what the camera recorded, before linearize
  divided the EXIF exposure out, and its input scale fitted),

each refitted as long from the same start; held-out views (every 5th, all EXIF exposures among
them) are scored as the imaging selection scores them (gains cross-fitted on the checkerboard,
:func:`recon.optimize.imaging.heldout_tiles_under`), the gain over the control is the paired
per-tile test (:func:`recon.optimize.heldout.compare`). The curve error is
``max |H_fit(srgb(c y)) - T(s y)|`` (encoded) over the model's values y of the object's pixels
(1st-99.5th percentile), at the best scale s (the gauge the albedo shares); ``identity`` is the
same for no curve at all (linearize's plain sRGB decoding). Gains: max relative error of the
training views' fitted gains against the truth (both normalized to geometric mean 1).

Run: ``.venv/bin/python bench/tone.py --out bench/out/tone`` (``--prepare-only`` makes the captures
and problems; the fits need torch only). Prints one line per curve and writes ``<out>/results.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

CURVES = ("none", "phone", "gamma22", "filmic", "table", "toe_shoulder")
T = 128


def out(line: str) -> None:
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


def capture_settings(curve: str, args) -> dict:
    return dict(object="blob", format="jpg", seed=args.seed, mesh_level=4, texture_size=T, write_masks=True,
                write_cameras=True, write_gt_linear=False, roughness=0.3, n_views=args.views, width=args.width,
                height=args.height, spp=args.spp, tone_curve=curve, exposure_variation=args.exposure_variation,
                exposure_jitter=args.exposure_jitter, light_intensity=args.light)


def prepare(root: Path, curve: str, args) -> Path:
    """The capture, its linearized views, the true mesh's G-buffers and the true maps, saved to
    ``<root>/<curve>.pt`` (plain tensors and arrays: the fits need neither open3d nor mitsuba)."""
    from recon import sections
    from recon.io.cameras import load_cameras
    from recon.io.images import read_exr
    from recon.io.mesh import read_obj
    from recon.linearize.stage import linearize_capture
    from recon.optimize.gbuffer import build_gbuffer
    from recon.optimize.views import recorded_exposures
    from recon.optimize.remesh import rasterize_atlas
    from recon.optimize.views import Views
    from recon.synth.capture import SynthSettings, make_capture

    path = root / f"{curve}.pt"
    if path.is_file():
        return path
    cap, lin = root / "captures" / curve, root / "linear" / curve
    if not (cap / "cameras.json").is_file():
        make_capture(cap, sections.replace(SynthSettings(), **capture_settings(curve, args)))
    if not (lin / "linear.json").is_file():
        linearize_capture(cap, lin)
    info = json.loads((lin / "linear.json").read_text())
    cams = load_cameras(cap / "cameras.json")
    images = [lin / info["images"][c.stem]["exr"] for c in cams.frames]
    views = Views(images, [cap / "masks" / f"{c.stem}.png" for c in cams.frames],
                  [lin / info["images"][c.stem]["sat"] for c in cams.frames], cams, args.width)
    held = [i for i in range(len(views)) if i % 5 == 2]
    train = [i for i in range(len(views)) if i % 5 != 2]
    tr, he = views.subset(train).at(args.width), views.subset(held).at(args.width)
    mesh = read_obj(cap / "gt" / "mesh.obj")
    lo, hi = mesh.bbox()

    def gb(vs, seed):
        g = build_gbuffer(mesh, list(vs.cameras), args.gspp, seed)
        return {k: getattr(g, k) for k in ("pixel", "uv", "mu", "inv_d2", "spp", "shape", "position", "normal")}

    def vset(vs):
        return {"images": vs.images, "weights": vs.weights, "masks": vs.masks, "cameras": list(vs.cameras)}

    maps = {k: read_exr(cap / "gt" / f"{k}.exr") for k in ("diffuse", "specular", "roughness")}
    maps["specular"] = maps["specular"][:, :, :1]
    maps["roughness"] = np.full_like(maps["roughness"][:, :, :1], float(np.median(maps["roughness"])))
    torch.save({"curve": curve, "gb_train": gb(tr, 0), "gb_held": gb(he, 1), "train": vset(tr), "held": vset(he),
                "covered": rasterize_atlas(mesh, T)[0] >= 0, "maps": maps, "train_idx": train,
                "light": load_cameras(cap / "gt" / "cameras.json").light_intensity, "scale": views.median_foreground,
                "length": float(np.max(hi - lo)), "exposure": recorded_exposures(images),
                "gt": json.loads((cap / "gt" / "imaging.json").read_text())}, path)
    return path


def problems(d: dict, exposure: bool, s):
    from recon.optimize.gbuffer import GBuffer
    from recon.optimize.imaging import ImagingProblem
    from recon.optimize.views import ViewSet

    e = d["exposure"] if exposure else None
    out = []
    for g, v in ((d["gb_train"], d["train"]), (d["gb_held"], d["held"])):
        gbuf = GBuffer(**g)
        out.append(ImagingProblem(gbuf, ViewSet(v["images"], v["weights"], v["masks"], tuple(v["cameras"])),
                                  s.tone_map, d["scale"], s.tile, e))
    return out


def curve_error(fit, prob, true_curve: str, light: float, r_min: float = 0.02) -> dict:
    """The fitted curve against the truth up to the scale gauge (module docstring); also the
    error of no curve at all (the sRGB decoding alone) over the same values."""
    from recon.optimize.formation import ImagingModel, srgb_encode_ext
    from recon.synth.imaging import tone_encode

    p = fit.params
    q = p.clone()
    q.model = ImagingModel(tuple(t for t in p.model.terms if t != "tone"))
    m = fit.material.maps
    with torch.no_grad():
        y = prob.render(torch.tensor(m["diffuse"]), torch.tensor(m["specular"]), torch.tensor(m["roughness"]),
                        light, r_min, q)
        keep = (prob.weight[:, 0] > 0) & (prob.target_linear.max(1).values > 0)
        yv = y[keep].reshape(-1).numpy()
    lo, hi = np.percentile(yv[yv > 0], [1, 99.5])
    x = torch.tensor(np.geomspace(lo, hi, 200), dtype=torch.float32)
    with torch.no_grad():
        fitted = srgb_encode_ext(p.tone(x)).numpy() if p.model.has("tone") else srgb_encode_ext(x).numpy()
    scales = np.geomspace(0.2, 5.0, 801)
    errs = np.array([np.abs(fitted - tone_encode(x.numpy() * s, true_curve)).max() for s in scales])
    k = int(np.argmin(errs))
    return {"max_abs_encoded": float(errs[k]), "scale": float(scales[k]), "y_range": [float(lo), float(hi)]}


def gain_error(d: dict, fit) -> float:
    g_true = np.array(d["gt"]["exposure_gains"])[d["train_idx"]]
    g_true = g_true / np.exp(np.log(g_true).mean())
    return float(np.abs(fit.params.gains().detach().numpy() / g_true - 1).max())


def run_curve(path: Path, args) -> dict:
    from recon.optimize.formation import ImagingModel
    from recon.optimize.imaging import ImagingSettings, fit_imaging, heldout_tiles_under
    from recon.optimize.heldout import compare
    from recon.optimize.material import MaterialModel, SelectionSettings

    d = torch.load(path, weights_only=False)
    mat = MaterialModel("textured", "mono", "uniform")
    s = SelectionSettings(iterations=args.iterations, min_gain=0.015)
    row = {"curve": d["curve"]}
    fits = {}
    for label, terms, im, expo in (("control", ("exposure",), ImagingSettings(), False),
                                   ("first", ("exposure", "tone"), ImagingSettings(tone_gain=False), False),
                                   ("fixed", ("exposure", "tone"), ImagingSettings(), True)):
        pt, ph = problems(d, expo, s)
        t0 = time.perf_counter()
        fit = fit_imaging(ImagingModel(terms), mat, pt, d["maps"], d["covered"], d["light"], s, im, None, d["length"],
                          d["scale"])
        tiles, rmse = heldout_tiles_under(fit.material.maps, mat, fit.params, ph, d["light"], s, im)
        fits[label] = tiles
        r = {"heldout_error": float(np.nanmean(tiles)), "heldout_rmse_srgb": rmse, "train_loss": fit.train_loss,
             "gain_max_rel": gain_error(d, fit), "curve": curve_error(fit, pt, d["curve"], d["light"]),
             "seconds": time.perf_counter() - t0}
        if label != "control":
            r["vs_control"] = compare(tiles, fits["control"], s)
            r["input_gain"] = fit.params.report()["tone_curve"]["input_gain"]
        row[label] = r
    c, f, x = row["control"], row["first"], row["fixed"]
    out(f"{d['curve']:13s} curve err identity {c['curve']['max_abs_encoded']:.3f} first {f['curve']['max_abs_encoded']:.3f} "
        f"fixed {x['curve']['max_abs_encoded']:.3f} | held-out control {c['heldout_error']:.5f} first "
        f"{f['heldout_error']:.5f} ({f['vs_control']['gain']:+.5f} +- {f['vs_control']['se']:.5f}) fixed "
        f"{x['heldout_error']:.5f} ({x['vs_control']['gain']:+.5f} +- {x['vs_control']['se']:.5f}) | gains "
        f"{c['gain_max_rel']:.3f} / {f['gain_max_rel']:.3f} / {x['gain_max_rel']:.3f} | c {x['input_gain']:.3f}")
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("bench/out/tone"))
    ap.add_argument("--curves", default=",".join(CURVES))
    ap.add_argument("--views", type=int, default=20)
    ap.add_argument("--width", type=int, default=96)
    ap.add_argument("--height", type=int, default=72)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--gspp", type=int, default=4)
    ap.add_argument("--iterations", type=int, default=150)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--light", type=float, default=50.0, help="the flash's I_e (the generator's default is 28)")
    ap.add_argument("--exposure-variation", type=float, default=0.3, dest="exposure_variation")
    ap.add_argument("--exposure-jitter", type=float, default=0.15, dest="exposure_jitter")
    ap.add_argument("--prepare-only", action="store_true")
    ap.add_argument("--jobs", type=int, default=1, help="curves fitted in parallel processes (one torch thread each)")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    curves = args.curves.split(",")
    if args.prepare_only:
        for c in curves:
            prepare(args.out, c, args)
        return 0
    paths = [args.out / f"{c}.pt" if (args.out / f"{c}.pt").is_file() else prepare(args.out, c, args) for c in curves]
    if args.jobs > 1:
        from multiprocessing import Pool

        with Pool(args.jobs, initializer=torch.set_num_threads, initargs=(1,)) as pool:
            rows = pool.starmap(run_curve, [(p, args) for p in paths])
    else:
        torch.set_num_threads(max(1, min(2, os.cpu_count() or 1)))
        rows = [run_curve(p, args) for p in paths]
    (args.out / "results.json").write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
