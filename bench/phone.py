"""Benchmark: a phone's imaging effects, each modelled and not, on the true mesh (issue 16 item 5).

For each effect (``ideal``: none; ``flash_offset``, ``exposure``, ``ambient``, ``falloff``, ``tone``:
one each; ``phone``: all of them and a white-balance jitter, which no term models) it makes a
synthetic capture (``recon.synth``, void blob, sensor noise, JPEG for ``tone`` and ``phone``, EXR
otherwise), linearizes it with the real linearize stage, and on the TRUE mesh (geometry fixed:
this measures the imaging model, not the shape) fits

- the material model (textured mono specular, uniform roughness, 150 Adam steps) as the start,
- "not modelled": the ideal image formation refitted (``ImagingModel(())``),
- "modelled": the effect's term(s) fitted with the maps (``phone``: every term),
- the held-out selection of ``recon.optimize.imaging_select.select_imaging`` (which terms it keeps,
  with gain and SE),

and reports per case: held-out error (the selection's metric), held-out sRGB RMSE (DESIGN 5, on
every tile, each scored under the gains fitted on the other colour), diffuse albedo RMSE against gt/diffuse.exr over the covered
texels, the recovered parameters against gt/imaging.json (offset in mm for a 10-cm object),
and the seconds of each fit. Writes ``<out>/results.json``, ``docs/phone.md`` and
``docs/phone.png`` (unless ``--no-docs``).

Run: ``.venv/bin/python bench/phone.py --out bench/out/phone [--views 24 --width 128 --height 96
--iterations 100 --cases ideal,flash_offset,...]``.
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

from recon import sections
from recon.io.cameras import load_cameras  # noqa: E402
from recon.io.images import read_exr  # noqa: E402
from recon.io.mesh import read_obj  # noqa: E402
from recon.linearize.stage import linearize_capture  # noqa: E402
from recon.optimize.gbuffer import build_gbuffer  # noqa: E402
from recon.optimize.formation import TERMS, ImagingModel, falloff, srgb_encode  # noqa: E402
from recon.optimize.imaging import ImagingProblem, ImagingSettings, fit_imaging, heldout_tiles  # noqa: E402
from recon.optimize.imaging_select import select_imaging  # noqa: E402
from recon.optimize.material import MaterialModel, SelectionSettings, fit_model  # noqa: E402
from recon.optimize.remesh import rasterize_atlas  # noqa: E402
from recon.optimize.views import Views, recorded_exposures  # noqa: E402
from recon.synth.capture import SynthSettings, make_capture  # noqa: E402
from recon.synth.imaging import linearized_tone  # noqa: E402

EFFECTS = {
    "ideal": {},
    "flash_offset": {"flash_offset": (0.19, 0.0, 0.0)},
    "exposure": {"exposure_jitter": 0.25},
    "ambient": {"ambient": 0.1},
    "falloff": {"falloff": (-0.35, 0.0)},
    "tone": {"format": "jpg", "tone_curve": "phone"},
    "phone": {"format": "jpg", "tone_curve": "phone", "flash_offset": (0.19, 0.0, 0.0), "exposure_jitter": 0.25,
              "exposure_variation": 0.5, "ambient": 0.1, "falloff": (-0.35, 0.0), "wb_jitter": 0.02},
}
MATERIAL = MaterialModel("textured", "mono", "uniform")
T = 256


def out(line: str) -> None:
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


def prepare(root: Path, case: str, args) -> dict:
    """The capture, its linearized views on the true mesh, the start material fit."""
    cap, lin = root / "captures" / case, root / "linear" / case
    kw = dict(object="blob", n_views=args.views, width=args.width, height=args.height, format="exr", spp=args.spp,
              seed=args.seed, mesh_level=5, texture_size=T, write_masks=True, write_cameras=True,
              write_gt_linear=False, roughness=0.3)
    kw.update(EFFECTS[case])
    t0 = time.perf_counter()
    if not (cap / "cameras.json").is_file():
        make_capture(cap, sections.replace(SynthSettings(), **kw))
    if not (lin / "linear.json").is_file():
        linearize_capture(cap, lin)
    t_synth = time.perf_counter() - t0
    info = json.loads((lin / "linear.json").read_text())
    cams = load_cameras(cap / "gt" / "cameras.json")  # the true cameras and flash (the true mesh's problem)
    mesh = read_obj(cap / "gt" / "mesh.obj")
    views = Views([lin / info["images"][c.stem]["exr"] for c in cams.frames],
                  [cap / "masks" / f"{c.stem}.png" for c in cams.frames],
                  [lin / info["images"][c.stem]["sat"] for c in cams.frames], cams, args.width)
    held = [i for i in range(len(views)) if i % 4 == 2]
    train = [i for i in range(len(views)) if i % 4 != 2]
    size = args.width
    tr, he = views.subset(train).at(size), views.subset(held).at(size)
    light, scale = views.light_intensity, views.median_foreground
    covered = rasterize_atlas(mesh, T)[0] >= 0
    s = SelectionSettings(iterations=args.iterations)
    const = {"diffuse": np.full((T, T, 3), 0.3, np.float32), "specular": np.full((T, T, 1), 0.1, np.float32),
             "roughness": np.full((T, T, 1), 0.4, np.float32)}
    gb = build_gbuffer(mesh, list(tr.cameras), args.gspp, 0)
    start = fit_model(MATERIAL, gb, tr, const, covered, light, scale, SelectionSettings(iterations=150))
    gt = json.loads((cap / "gt" / "imaging.json").read_text()) if (cap / "gt" / "imaging.json").is_file() else None
    # the EXIF exposures linearize divided out: where the tone curve acts (JPEG captures)
    exposure = recorded_exposures([lin / info["images"][c.stem]["exr"] for c in cams.frames])
    return dict(cap=cap, mesh=mesh, train=tr, held=he, train_idx=train, light=light, scale=scale, covered=covered,
                exposure=exposure,
                s=s, start=start, gt=gt, ldr=kw["format"] == "jpg", t_synth=t_synth)


def albedo_rmse(cap: Path, maps: dict, covered: np.ndarray) -> float:
    gt = read_exr(cap / "gt" / "diffuse.exr")
    d = maps["diffuse"] - gt
    return float(np.sqrt((d[covered] ** 2).mean()))


def parameter_errors(p: dict, params, bbox: float, r2_max: float = 1.0) -> dict:
    """Recovered imaging values against gt/imaging.json (terms the fit has); the falloff over the
    image radii the object covers (r^2 <= ``r2_max``), the tone curve over linear 0.01-0.9."""
    gt, rep, errs = p["gt"], params.report(), {}
    if gt is None:
        return errs
    if "flash_offset" in rep:
        e = float(np.linalg.norm(np.array(rep["flash_offset"]) - np.array(gt["flash_offset_camera"])))
        errs["flash_offset_mm_at_10cm"] = e / bbox * 100.0
    if "exposure_gains" in rep:
        tg = np.array(gt["exposure_gains"])[p["train_idx"]]
        tg = tg / np.exp(np.log(tg).mean())
        errs["exposure_gain_max_rel"] = float(np.max(np.abs(np.array(rep["exposure_gains"]) / tg - 1)))
        errs["exposure_gain_rms_rel"] = float(np.sqrt(np.mean((np.array(rep["exposure_gains"]) / tg - 1) ** 2)))
    if "ambient" in rep:
        errs["ambient_ratio"] = rep["ambient"] / gt["ambient_radiance"] if gt["ambient_radiance"] > 0 else None
    if "falloff" in rep:
        r2 = torch.linspace(0, r2_max, 101)
        k_true = torch.tensor([gt["falloff"]["k1"], gt["falloff"]["k2"]])
        errs["falloff_r2_max"] = r2_max
        errs["falloff_max_abs"] = float((falloff(r2, params.falloff_k.detach()) - falloff(r2, k_true)).abs().max())
    if "tone_curve" in rep:
        x = torch.linspace(0.01, 0.9, 90)
        tc = gt["tone_curve"]
        truth = linearized_tone(x.numpy(), tc["name"], tc["contrast"])
        with torch.no_grad():
            fitted = params.tone(x).numpy()
        errs["tone_max_abs_encoded"] = float(np.max(np.abs(srgb_encode(torch.tensor(fitted)).numpy()
                                                           - srgb_encode(torch.tensor(truth)).numpy())))
    return errs


def run_case(root: Path, case: str, args) -> dict:
    p = prepare(root, case, args)
    s, im = p["s"], ImagingSettings()
    lo, hi = p["mesh"].bbox()
    bbox = float(np.max(hi - lo))
    gb_t = build_gbuffer(p["mesh"], list(p["train"].cameras), args.gspp, 0)
    gb_h = build_gbuffer(p["mesh"], list(p["held"].cameras), args.gspp, 1)
    pt = ImagingProblem(gb_t, p["train"], s.tone_map, p["scale"], s.tile, p["exposure"])
    ph = ImagingProblem(gb_h, p["held"], s.tone_map, p["scale"], s.tile, p["exposure"])
    terms = [t for t in TERMS if t != "tone" or p["ldr"]]
    r2_max = float(pt.r2[(pt.weight[:, 0] > 0) & (pt.target_linear.sum(1) > 0)].max())
    modelled_terms = terms if case == "phone" else ([case] if case in TERMS else [])
    row = {"case": case, "effects": EFFECTS[case], "synth_seconds": p["t_synth"]}
    for label, model in (("not_modelled", ImagingModel(())), ("modelled", ImagingModel(tuple(modelled_terms)))):
        if label == "modelled" and not modelled_terms:
            continue
        fit = fit_imaging(model, MATERIAL, pt, p["start"].maps, p["covered"], p["light"], s, im, None, bbox, p["scale"])
        tiles, rmse = heldout_tiles(fit, ph, p["light"], s, im)
        row[label] = {"terms": list(model.terms), "heldout_error": float(np.nanmean(tiles)), "heldout_rmse_srgb": rmse,
                      "albedo_rmse": albedo_rmse(p["cap"], fit.material.maps, p["covered"]), "seconds": fit.seconds,
                      "values": fit.params.report(), "errors": parameter_errors(p, fit.params, bbox, r2_max)}
        out(f"{case:13s} {label:13s} held-out {row[label]['heldout_error']:.5f} rmse {rmse:.4f} "
            f"albedo {row[label]['albedo_rmse']:.4f} {fit.seconds:6.1f} s {row[label]['errors']}")
    if not args.no_selection:
        t0 = time.perf_counter()
        _, ev = select_imaging(p["mesh"], p["start"], p["covered"], p["train"], p["held"], p["light"], p["scale"], s,
                               im, candidates=tuple(terms), spp=args.gspp, exposure=p["exposure"])
        row["selection"] = {"chosen": ev["chosen"], "seconds": time.perf_counter() - t0,
                            "steps": [{k: r.get(k) for k in ("step", "accepted", "gain", "se", "relative_gain",
                                                             "heldout_error", "control_heldout_error")}
                                      for r in ev["candidates"]]}
        out(f"{case:13s} selection keeps {ev['chosen']} ("
            + ", ".join(f"{r['step']}: {r['gain']:+.5f} +- {r['se']:.5f}" for r in ev["candidates"][1:]) + ")")
    return row


def write_docs(rows: list[dict], args, command: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lines = ["# A phone's imaging: each effect modelled and not (issue 16 item 5)", "",
             f"Measured with `{command}` (2 shared CPU cores). Synthetic void blob captures, "
             f"{args.views} views of {args.width}x{args.height}, every 4th held out, sensor noise on, roughness 0.3, "
             "textured mono specular; the TRUE mesh is used (geometry fixed), so this measures the imaging model "
             "on the material fit, not the shape: geometry accuracy is not part of it. "
             "`bench/phone.py` docstring says exactly what each column is.", "",
             "| capture | effect | held-out error not / modelled | sRGB RMSE not / modelled | albedo RMSE not / modelled "
             "| fit seconds not / modelled | recovered vs truth | selection keeps (gain +- SE) |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        n = r["not_modelled"]
        m = r.get("modelled", n)
        sel = r.get("selection", {})
        kept = ", ".join(f"{st['step']} ({st['gain']:+.4f} +- {st['se']:.4f})" for st in sel.get("steps", [])[1:]
                         if st["accepted"]) or "nothing"
        effects = ", ".join(f"{k}={v}" for k, v in r["effects"].items()) or "none"
        errs = ", ".join(f"{k} {v:.3g}" for k, v in m.get("errors", {}).items()
                         if isinstance(v, float) and k != "falloff_r2_max")
        lines.append(f"| {r['case']} | {effects} | {n['heldout_error']:.4f} / {m['heldout_error']:.4f} | "
                     f"{n['heldout_rmse_srgb']:.4f} / {m['heldout_rmse_srgb']:.4f} | {n['albedo_rmse']:.4f} / "
                     f"{m['albedo_rmse']:.4f} | {n['seconds']:.1f} / {m['seconds']:.1f} | {errs or '-'} | {kept} |")
    marker = "![held-out sRGB RMSE per capture, modelled and not](phone.png)"
    lines += ["", marker]
    # what follows the figure (the reading, the shape's measurements of bench/phone_geometry.py)
    # is written by hand: kept
    doc = Path("docs/phone.md")
    old = doc.read_text() if doc.is_file() else ""
    tail = old.split(marker, 1)[1] if marker in old else "\n"
    doc.write_text("\n".join(lines) + tail)
    fig, ax = plt.subplots(figsize=(7, 3.2))
    x = np.arange(len(rows))
    ax.bar(x - 0.2, [r["not_modelled"]["heldout_rmse_srgb"] for r in rows], 0.4, label="not modelled")
    ax.bar(x + 0.2, [r.get("modelled", r["not_modelled"])["heldout_rmse_srgb"] for r in rows], 0.4, label="modelled")
    ax.set_xticks(x, [r["case"] for r in rows])
    ax.set_ylabel("held-out sRGB RMSE")
    ax.legend()
    fig.tight_layout()
    fig.savefig("docs/phone.png", dpi=110)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("bench/out/phone"))
    ap.add_argument("--views", type=int, default=24)
    ap.add_argument("--width", type=int, default=128)
    ap.add_argument("--height", type=int, default=96)
    ap.add_argument("--spp", type=int, default=16, help="samples per pixel of the synthetic photos")
    ap.add_argument("--gspp", type=int, default=4, help="G-buffer samples per pixel")
    ap.add_argument("--iterations", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cases", default=",".join(EFFECTS))
    ap.add_argument("--no-selection", action="store_true")
    ap.add_argument("--no-docs", action="store_true")
    args = ap.parse_args(argv)
    torch.set_num_threads(max(1, min(2, os.cpu_count() or 1)))
    res = args.out / "results.json"
    # rows of cases not run now are kept from an earlier run (same settings: --cases reruns some)
    old = {r["case"]: r for r in json.loads(res.read_text())} if res.is_file() else {}
    for case in args.cases.split(","):
        old[case] = run_case(args.out, case, args)
        res.write_text(json.dumps([old[c] for c in EFFECTS if c in old], indent=1))
    rows = [old[c] for c in EFFECTS if c in old]
    if not args.no_docs:
        write_docs(rows, args, "python bench/phone.py " + " ".join(argv if argv is not None else sys.argv[1:]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
