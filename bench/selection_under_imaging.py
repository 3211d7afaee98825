"""Benchmark: the material model chosen under the phone's imaging terms and under the ideal formation.

For each finished workflow run given (``<results>/<capture>``, optimized with ``imaging_loop``
and ``select_material``), redoes the optimize stage's part after the coarse-to-fine loop from the
run's own final checkpoints (held-out camera alignment, material selection, maps) twice, with
``select_material_under_imaging`` true and false, into ``<out>/<name>/{under,ideal}``, and prints
per run and way: the chosen model, its held-out error, the first specular step's gain and SE, and
(with the capture's ``gt/``) the texture RMSE of the maps against the truth by the report's
``texture_errors`` under the run's own alignment (report/metrics.json). ``--clustered``: for
every step compared under the imaging terms, the paired test's SE as the selection computes it
(tiles independent) beside SEs clustered by 2 x 2 and 4 x 4 blocks of tiles and by view.

The checkpoints are reused although the settings' fingerprint differs in this one key: it acts
after the loop only, so the loop's final state is the same either way (the bench says so in its
output; the optimize stage itself never resumes across a settings change).

    .venv/bin/python bench/selection_under_imaging.py --out /tmp/sel_imaging \\
        <results>/<capture>[:<capture folder with gt/>] ...

About 1-3 minutes per run and way on 2 cores (640-px phone captures at balanced).
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import recon.optimize.loop as loop_module  # noqa: E402
from recon.metrics import Similarity  # noqa: E402
from recon.optimize import checkpoint as ckpt  # noqa: E402
from recon.optimize import optimize_from_dirs, settings_from_record  # noqa: E402

log = logging.getLogger("bench.selection_under_imaging")


def out(line: str) -> None:
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


def _load_ignoring_fingerprint(ckpt_dir, fingerprint):
    """ckpt.load with the fingerprint taken as matching (see the module docstring)."""
    import torch

    path = Path(ckpt_dir) / ckpt.CHECKPOINT_NAME
    if not path.is_file():
        return None
    state = torch.load(path, map_location="cpu", weights_only=False)
    return dict(state, fingerprint=fingerprint) if state.get("format_version") == ckpt.FORMAT_VERSION else None


def redo(res: Path, out: Path, under: bool) -> dict:
    """The post-loop part of ``res``'s optimize stage into ``out``; its summary.json."""
    summary = json.loads((res / "optimize" / "summary.json").read_text())
    settings = dict(summary["settings"], select_material_under_imaging=under)
    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(res / "optimize" / "checkpoints", out / "checkpoints")
    views = res / "poses" / "undistorted"
    if not any(views.glob("*.exr")):  # given cameras: the linear views (workflow/rules/common.smk)
        views = res / "linear"
    plane = res / "poses" / "plane.json"
    load = loop_module.ckpt.load
    loop_module.ckpt.load = _load_ignoring_fingerprint
    try:
        optimize_from_dirs(views, res / "poses" / "undistorted" / "masks", res / "poses" / "cameras.json",
                           res / "uv" / "mesh.obj", out, settings_from_record(settings), progress=False,
                           plane_json=plane if plane.is_file() else None)
    finally:
        loop_module.ckpt.load = load
    return json.loads((out / "summary.json").read_text())


def texture_rmse(res: Path, out: Path, cap: Path) -> dict:
    from recon.report.gt import read_ground_truth, texture_errors
    from recon.report.inputs import read_model

    m = json.loads((res / "report" / "metrics.json").read_text())["metrics"]
    sd = m["alignment"]["similarity"]
    sim = Similarity(sd["scale"], np.asarray(sd["rotation"]), np.asarray(sd["translation"]))
    return texture_errors(read_model(out), read_ground_truth(cap / "gt").model, sim, m["unit"], 100_000, 0.02)


def clustered_ses(pairs: list, evidence: dict, tile: int) -> list[str]:
    """Rows of SEs of the recorded paired comparisons (richer, current, result) under clustering;
    the tiles come per held-out view, row by row (recon.optimize.material.tile_errors)."""
    w, h = evidence["image_size"]
    ty, tx = -(-h // tile), -(-w // tile)
    v, y, x = np.meshgrid(np.arange(evidence["heldout_views"]), np.arange(ty), np.arange(tx), indexing="ij")
    v, y, x = v.ravel(), y.ravel(), x.ravel()
    groups = {"2 x 2 tiles": v * 10**6 + (y // 2) * 1000 + x // 2, "4 x 4 tiles": v * 10**6 + (y // 4) * 1000 + x // 4,
              "view": v}
    rows = []
    for richer, current, res in pairs:
        d = current - richer
        ok = np.isfinite(d)
        cells = [f"{res['gain']:+.5f}", f"{res['se']:.5f} ({res['gain'] / res['se']:.2f})"]
        for g in groups.values():
            dd, gg = d[ok], g[ok]
            sums = np.array([(dd[gg == k] - dd.mean()).sum() for k in np.unique(gg)])
            se = np.sqrt(len(sums) / (len(sums) - 1) * (sums**2).sum()) / dd.size
            cells.append(f"{se:.5f} ({res['gain'] / se:.2f})")
        rows.append(cells)
    return rows


def row(name: str, way: str, s: dict, tex: dict | None) -> str:
    sel = s["material_selection"]
    steps = {c["step"]: c for c in sel["candidates"]}
    first = steps.get("uniform specular") or {}
    gain = f"{first['gain']:.4f} / {first['se']:.4f}" if first.get("se") else "-"
    t = f"{tex['diffuse']:.3f} / {tex['specular']:.3f} / {tex['roughness']:.3f}" if tex else "-"
    return (f"| {name} | {way} | {s['material_model_label']} | {sel['chosen_heldout_error']:.4f} | {gain} | "
            f"{t} | {sel['seconds']:.0f} |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", help="<results>/<capture>[:<capture folder with gt/>]")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--clustered", action="store_true", help="SEs clustered by tile blocks and views")
    args = ap.parse_args(argv)
    import recon.optimize.material as material
    import recon.optimize.material_select as material_select

    pairs = []
    compare = material_select.compare

    def recording(richer, current, s):
        res = compare(richer, current, s)
        pairs.append((np.asarray(richer, float), np.asarray(current, float), res))
        return res

    material_select.compare = recording
    logging.basicConfig(level=logging.WARNING)
    lines = ["| run | compared | chosen | held-out error | uniform specular: gain / SE | "
             "texture RMSE diffuse / specular / roughness | selection s |", "|---|---|---|---|---|---|---|"]
    for spec in args.runs:
        res, _, cap = spec.partition(":")
        res = Path(res)
        name = f"{res.parent.parent.name}/{res.parent.name}/{res.name}"
        for way, under in (("ideal formation", False), ("under the imaging terms", True)):
            folder = args.out / res.parent.parent.name / res.name / ("under" if under else "ideal")
            pairs.clear()
            s = redo(res, folder, under)
            if args.clustered and under:
                steps = [c["step"] for c in s["material_selection"]["candidates"][1:]]
                out(f"SEs of {name}, under the imaging terms: step | gain | independent tiles (z) | "
                    + " | ".join(["2 x 2 tiles (z)", "4 x 4 tiles (z)", "view (z)"]))
                for step, cells in zip(steps, clustered_ses(pairs, s["material_selection"], material.SelectionSettings().tile), strict=True):
                    out(f"| {step} | " + " | ".join(cells) + " |")
            tex = texture_rmse(res, folder, Path(cap)) if cap else None
            lines.append(row(name, way, s, tex))
            out(lines[-1])
    out("\n(the runs' loop checkpoints reused across the one setting that acts after the loop)")
    out("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
