"""Benchmark: the shape under a phone's imaging, with the imaging terms in the loop and without
(issue 16 items 2 and 5: "accuracy within 2x of the idealised capture at the balanced preset").

Two synthetic captures of the same object and cameras (``recon.synth``, void blob, sensor noise,
cameras and masks given so that only the imaging differs):

- ``ideal``: linear EXR photos, the flash at the lens, no ambient light, exact exposure;
- ``phone``: JPEG with the phone's tone curve and EXIF exposure, the flash 1 cm beside the lens
  (for a 10-cm object), per-view exposure error (0.25 stops) and exposure changes recorded in
  EXIF, ambient light 10 % of the flash, lens falloff -35 % in the corners, 2 % white-balance
  jitter (no term models it).

Runs the whole workflow (Snakemake up to ``report/metrics.json``) on ``ideal`` (with the loop's
imaging selection off and on: does it keep nothing there?), on ``phone``
with ``imaging.loop: off`` (the ideal formation in the loop) and on ``phone`` with
``imaging.loop: select`` (the selection on stage 0's model, the later stages under the chosen
terms), all at ``--preset``; reads the report's metrics (DESIGN section 5: accuracy and
completeness in the unit bounding box, held-out sRGB RMSE, texture RMSE) and the optimize
stage's wall time and chosen terms. Prints a table with ratios to ``ideal`` and writes
``<out>/phone_geometry.json``.

    .venv/bin/python bench/phone_geometry.py --out /tmp/phone_geom --preset balanced

Captures are cached in ``<out>/captures``; Snakemake redoes nothing that is done.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from recon import sections  # noqa: E402
from recon.synth.capture import SynthSettings, make_capture  # noqa: E402
from tabletop_e2e import snakemake  # noqa: E402  (the workflow run of the sibling bench)

log = logging.getLogger("bench.phone_geometry")

PHONE = {"format": "jpg", "tone_curve": "phone", "flash_offset": (0.19, 0.0, 0.0), "exposure_jitter": 0.25,
         "exposure_variation": 0.5, "ambient": 0.1, "falloff": (-0.35, 0.0), "wb_jitter": 0.02}
RUNS = {  # name -> (capture, optimize overrides in capture.yaml)
    "ideal": ("ideal", {"imaging": {"loop": "off"}}),
    "ideal_loop_select": ("ideal", {"imaging": {"loop": "select"}}),
    "phone_loop_off": ("phone", {"imaging": {"loop": "off"}}),
    "phone_loop_select": ("phone", {"imaging": {"loop": "select"}}),
}


def make(root: Path, name: str, args) -> Path:
    cap = root / "captures" / name
    if not (cap / "cameras.json").is_file():
        kw = dict(object="blob", n_views=args.views, width=args.width, height=args.height, format="exr",
                  spp=args.spp, seed=args.seed, write_masks=True, write_cameras=True, write_gt_linear=False,
                  scene=args.scene)
        if name == "phone":
            kw.update(PHONE)
        make_capture(cap, sections.replace(SynthSettings(), **kw))
    return cap


def run_folder(root: Path, run: str, cap: Path, overrides: dict, preset: str, leave_out: tuple[str, ...] = (),
               poses: dict | None = None) -> Path:
    """A capture folder for one run: the capture's files linked (but ``leave_out``, e.g.
    ``cameras.json`` so that SfM runs), its own capture.yaml (``overrides`` in its optimize
    section, ``poses`` in its poses section)."""
    d = root / "runs" / run
    d.mkdir(parents=True, exist_ok=True)
    for f in cap.iterdir():
        if f.name in ("capture.yaml", "gt", *leave_out):
            continue
        link = d / f.name
        if not link.exists():
            link.symlink_to(f.resolve())
    gt = d / "gt"
    if not gt.exists():
        gt.symlink_to((cap / "gt").resolve())
    import yaml

    base = yaml.safe_load((cap / "capture.yaml").read_text()) if (cap / "capture.yaml").is_file() else {}
    base = dict(base or {})
    base["preset"] = preset
    if overrides:
        base["optimize"] = {**(base.get("optimize") or {}), **overrides}
    if poses:
        base["poses"] = {**(base.get("poses") or {}), **poses}
    text = yaml.safe_dump(base, sort_keys=False)
    if not (d / "capture.yaml").is_file() or (d / "capture.yaml").read_text() != text:
        (d / "capture.yaml").write_text(text)
    return d


def measure(res: Path) -> dict:
    m = json.loads((res / "report" / "metrics.json").read_text())
    s = json.loads((res / "optimize" / "summary.json").read_text())
    loop = s.get("imaging_loop") or {}
    mm = m["metrics"]
    out = {"accuracy": mm.get("accuracy"), "completeness": mm.get("completeness"),
           "image_rmse": mm.get("image_rmse"), "textures": {k: v for k, v in mm.items() if isinstance(v, dict)},
           "optimize_seconds": s.get("wall_seconds"),
           "loop_terms": loop.get("chosen"),
           "loop_values": loop.get("values_after_loop"),
           "loop_selection_seconds": (loop.get("evidence") or {}).get("seconds")}
    return out


def table(results: dict) -> str:
    ideal = results["ideal"].get("accuracy")
    rows = ["| run | terms in the loop | accuracy | ratio to ideal | completeness | image RMSE (sRGB) | diffuse texture RMSE | optimize seconds |",
            "|---|---|---|---|---|---|---|---|"]
    for run, r in results.items():
        acc = r.get("accuracy")
        ratio = f"{acc / ideal:.2f}" if acc and ideal else "-"
        terms = ", ".join(r.get("loop_terms") or []) or ("none" if run.endswith("loop_select") else "-")
        rows.append(f"| {run} | {terms} | {acc:.5f} | {ratio} | {r.get('completeness', float('nan')):.5f} | "
                    f"{r.get('image_rmse') or float('nan'):.4f} | "
                    f"{((r.get('textures') or {}).get('texture_rmse') or {}).get('diffuse', float('nan')):.4f} | "
                    f"{r.get('optimize_seconds') or float('nan'):.0f} |")
    return "\n".join(rows)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--preset", default="balanced")
    p.add_argument("--views", type=int, default=32)
    p.add_argument("--width", type=int, default=256)
    p.add_argument("--height", type=int, default=192)
    p.add_argument("--spp", type=int, default=32)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--runs", default=",".join(RUNS))
    p.add_argument("--scene", default="void", choices=("void", "tabletop"),
                   help="tabletop: the object standing on a lit table (cameras and masks still given)")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    root = args.out
    runs = [r for r in args.runs.split(",") if r]
    caps = {c: make(root, c, args) for c in {RUNS[r][0] for r in runs}}
    folders = {r: run_folder(root, r, caps[RUNS[r][0]], RUNS[r][1], args.preset) for r in runs}
    results_dir = root / "results"
    t = snakemake(root / "runs", results_dir, [f"{results_dir}/{r}/report/metrics.json" for r in folders],
                  args.preset)
    results = {}
    for r in runs:
        try:
            results[r] = measure(results_dir / r)
        except (OSError, ValueError) as e:
            results[r] = {"error": str(e)}
    results_file = root / "phone_geometry.json"
    old = json.loads(results_file.read_text()) if results_file.is_file() else {}
    old.update(results)
    results_file.write_text(json.dumps({**old, "_meta": {"preset": args.preset, "snakemake_seconds": t,
                                                         "views": args.views, "size": [args.width, args.height]}},
                                       indent=1))
    sys.stdout.write(table({k: v for k, v in old.items() if not k.startswith("_") and "error" not in v}) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
