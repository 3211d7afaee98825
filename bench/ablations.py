"""Ablation studies of the paper (Luan et al. 2021), rerun on our benchmark harness.

Every run is one call of ``bench/optimize.py`` (its command line only, as a subprocess) on a
synthetic capture made by ``python -m recon synth`` (cached under ``OUT/captures``). All runs
share one reduced base configuration (``BASE_SET``, the draft preset pinned explicitly) and,
within a study, the same initial mesh: the base run shrinks and smooths the visual hull to an
accuracy of about 0.04 (``--crude 0.04``, inside the paper's 0.01-0.09) and every other run
starts from that mesh file (``--init``).

Studies (the paper's figures, numbered as the LaTeX source numbers them):

- ``gradients`` (Fig. 3, fig:ablation1): our edge sampling vs the interior term only vs
  Mitsuba 3's ``direct_projective``, at equal iterations and at equal wall time, plus harder
  cases for the silhouette term (a cruder init, a torus, 10 views), and a gradient check of the
  three routes against finite differences (``OUT/gradient_check.json``).
- ``geometry`` (Fig. 4, fig:ablation3): no Laplacian / no normal+edge loss / no coarse-to-fine,
  with plain Adam (the paper's optimizer) and with large steps (ours).
- ``materials`` (Fig. 5, fig:ablation4): no specular correlation / no roughness smoothness.
- ``views`` (Fig. 6, fig:ablation_n_input): 10 / 30 / 50 / 100 input views.

    python bench/ablations.py --out bench/out/ablations                 # everything (~30 min)
    python bench/ablations.py --out bench/out/ablations --study views   # one study
    python bench/ablations.py --out bench/out/ablations --report-only   # docs/ablations.md only

Resumable: a run whose ``bench.json`` exists (with the same command) is skipped; a run that was
interrupted is started again from scratch (so its wall time is whole). The report
(``docs/ablations.md`` and ``docs/ablations_*.png``) is regenerated from the ``bench.json``
files that exist.

This file is the runner (captures, runs, the gradient check) and the command line; the study's
definition (base configuration, captures, runs) is ``bench/ablation_runs.py`` and the report
writer ``bench/ablations_report.py``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from ablation_runs import (
    BASE_SET,
    CAPTURES,
    DOCS,
    NEUTRAL_PINS,
    PY,
    REPO,
    RUNS,
    STUDIES,
    SYNTH_COMMON,
    THREAD_ENV,
    Run,
    load,
    log,
    scaled_stages,
)
from ablations_report import write_report


def _comparable(cmd: list[str]) -> list[str]:
    """A command without the NEUTRAL_PINS --set pairs (for comparing with earlier runs)."""
    pins = {f"{k}={str(v).lower()}" for k, v in NEUTRAL_PINS.items()}
    out, skip = [], False
    for i, c in enumerate(cmd):
        if skip:
            skip = False
            continue
        if c == "--set" and i + 1 < len(cmd) and cmd[i + 1] in pins:
            skip = True
            continue
        out.append(c)
    return out


def make_capture(out: Path, key: str) -> float:
    """Synthesize OUT/captures/KEY unless it exists; returns the seconds spent."""
    dest = out / "captures" / key
    if (dest / "gt" / "mesh.obj").is_file() and (dest / "cameras.json").is_file():
        return 0.0
    log(f"synth {key} ...")
    dest.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with open(out / "captures" / f"{key}.log", "w") as f:
        subprocess.run([str(PY), "-m", "recon", "synth", str(dest), *CAPTURES[key], *SYNTH_COMMON],
                       cwd=REPO, stdout=f, stderr=subprocess.STDOUT, check=True)
    dt = time.perf_counter() - t0
    (out / "captures" / f"{key}.json").write_text(json.dumps({"seconds": dt, "args": [*CAPTURES[key], *SYNTH_COMMON]}))
    log(f"synth {key}: {dt:.0f} s")
    return dt


def derived_stages(out: Path, run: Run) -> list[dict] | None:
    """Equal wall time: the base stages scaled by edge / projective seconds per iteration.

    The edge-sampling reference is ``base_seed1`` (run just before ``grad_projective``, so both
    saw about the same load from other jobs), else ``base``.
    """
    edge, proj = load(out, "base_seed1") or load(out, "base"), load(out, "grad_projective")
    if edge is None or proj is None:
        return None
    per_it = lambda r: r["wall_seconds"] / sum(int(st["iterations"]) for st in r["stages"])  # noqa: E731
    return scaled_stages(per_it(edge) / per_it(proj))


def execute(out: Path, run: Run) -> float:
    """Run one bench/optimize.py call unless its bench.json exists; returns the seconds spent."""
    rdir = out / "runs" / run.name
    stages = None
    if run.derived:
        stages = derived_stages(out, run)
        if stages is None:
            log(f"{run.name}: skipped (needs base and grad_projective first)")
            return 0.0
    cmd = run.command(out, stages)
    meta_path = rdir / "ablation_run.json"
    if (rdir / "bench.json").is_file() and meta_path.is_file():
        meta = json.loads(meta_path.read_text())
        if (_comparable(meta.get("command", [])) == _comparable(cmd) and meta.get("env") == THREAD_ENV) or run.derived:
            log(f"{run.name}: done already")
            return 0.0
        log(f"{run.name}: command changed, running again")
    if run.init is not None and not (out / "runs" / run.init / "crude_init.obj").is_file():
        log(f"{run.name}: skipped (needs run {run.init} first for its initial mesh)")
        return 0.0
    synth_s = make_capture(out, run.capture)
    if rdir.exists():
        shutil.rmtree(rdir)  # a partial run restarts from scratch (no checkpoint resume: whole timings)
    rdir.mkdir(parents=True)
    log(f"{run.name}: {run.label} ...")
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True).stdout.strip()
    t0 = time.perf_counter()
    with open(rdir / "run.log", "w") as f:
        rc = subprocess.run(cmd, cwd=REPO, stdout=f, stderr=subprocess.STDOUT,
                            env={**os.environ, **THREAD_ENV}).returncode
    dt = time.perf_counter() - t0
    if rc != 0 or not (rdir / "bench.json").is_file():
        log(f"{run.name}: FAILED (exit {rc}) after {dt:.0f} s, see {rdir / 'run.log'}")
        return dt + synth_s
    meta = {"command": cmd, "env": THREAD_ENV, "seconds": dt, "commit": commit, "load_average": os.getloadavg(),
            "finished": time.strftime("%Y-%m-%d %H:%M:%S"), "stages": stages}
    meta_path.write_text(json.dumps(meta, indent=1))
    r = load(out, run.name)
    log(f"{run.name}: {dt:.0f} s (optimize {r['wall_seconds']:.0f} s), accuracy "
        f"{r['init_accuracy']['accuracy']:.4f} -> {r['final_accuracy']['accuracy']:.5f}, "
        f"novel RMSE {r['novel_view_rmse']:.4f}")
    return dt + synth_s


# ---- Gradient check: where the Fig. 3 differences come from ----
def gradient_check(out: Path, views=(3, 17, 30, 44), spp: int = 16, seeds: int = 4) -> dict | None:
    """Vertex gradients of the real loss on the shared crude init, per gradient route (cached).

    The base run's crude initial mesh (no UV seams: one UV for all vertices, constant maps at the
    optimizer's initial values), 4 of the 50 views at the optimization's 128x96, the rendering
    loss of eq. 6 (log tone map, L1, mean). Gradients (mean over ``seeds`` renders of ``spp``)
    from our edge sampling, our interior-only term, Mitsuba's ``direct_projective`` and
    Mitsuba's ``direct`` (interior only) through ``recon.render.mitsuba_scene.MitsubaScene``;
    then central finite differences of the same loss (our forward at 64 spp, common random
    numbers) along each route's gradient direction.
    """
    cache = out / "gradient_check.json"
    if cache.is_file():
        return json.loads(cache.read_text())
    init = out / "runs" / "base" / "crude_init.obj"
    cap = out / "captures" / "blob_v50"
    if not init.is_file() or not (cap / "cameras.json").is_file():
        return None
    import cv2
    import numpy as np
    import torch

    torch.set_num_threads(1)
    sys.path.insert(0, str(REPO))
    from recon.io.cameras import load_cameras
    from recon.io.images import read_exr, read_mask
    from recon.io.mesh import read_mesh
    from recon.render import CollocatedRenderer, RenderSettings
    from recon.render.mitsuba_scene import MitsubaScene

    log("gradient check (a few minutes) ...")
    m = read_mesh(init)
    cams = load_cameras(cap / "cameras.json")
    scale = BASE_SET["resolution"] / max(cams.frames[0].width, cams.frames[0].height)
    sel = [cams.frames[i].scaled(scale) for i in views]
    w, h = sel[0].width, sel[0].height
    tg = []
    for i in views:
        f = cams.frames[i]
        img = read_exr(cap / f.image)[:, :, :3] * read_mask(cap / "masks" / f"{f.stem}.png")[:, :, None]
        tg.append(cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA))
    tg = torch.from_numpy(np.stack(tg))
    tone = float(np.median(tg.numpy()[tg.numpy() > 0]))
    v_tex, t_tex = np.zeros((1, 2)), np.zeros_like(m.t_pos_idx)
    maps = [np.full((8, 8, 3), 0.3, np.float32), np.full((8, 8, 1), 0.1, np.float32), np.full((8, 8, 1), 0.4, np.float32)]

    def loss_of(img):
        return (torch.log1p(img.clamp(min=0) / tone) - torch.log1p(tg / tone)).abs().mean()

    grads = {}
    for route in ("edge", "none", "projective", "mitsuba_direct"):
        acc = np.zeros_like(m.v_pos)
        for seed in range(1, seeds + 1):
            boundary = "projective" if route == "mitsuba_direct" else route
            r = CollocatedRenderer(m.t_pos_idx, v_tex, t_tex, RenderSettings(spp=spp, boundary=boundary))
            if route == "mitsuba_direct":
                r._projective = MitsubaScene(r, "direct")  # the comparison scene's interior-only mode
            v = torch.tensor(m.v_pos, dtype=torch.float32, requires_grad=True)
            loss_of(r.render_torch(v, *[torch.from_numpy(x) for x in maps], sel, cams.light_intensity, seed=seed)).backward()
            acc += v.grad.numpy()
        grads[route] = acc / seeds

    def cos(a, b):
        return float(a.ravel() @ b.ravel() / (np.linalg.norm(a) * np.linalg.norm(b)))

    fwd = CollocatedRenderer(m.t_pos_idx, v_tex, t_tex, RenderSettings(spp=64, boundary="none"))

    def loss_at(vpos):
        with torch.no_grad():
            return float(loss_of(fwd.render_torch(torch.tensor(vpos, dtype=torch.float32),
                                                  *[torch.from_numpy(x) for x in maps], sel, cams.light_intensity, seed=7)))

    ext = float(np.ptp(m.v_pos, axis=0).max())
    eps = 1e-3 * ext
    fd = {}
    for route in ("edge", "projective"):
        u = grads[route] / np.linalg.norm(grads[route])
        fd[route] = {"finite_difference": (loss_at(m.v_pos + eps * u) - loss_at(m.v_pos - eps * u)) / (2 * eps),
                     **{f"predicted_by_{k}": float(grads[k].ravel() @ u.ravel()) for k in ("edge", "projective")}}
    e, n = grads["edge"], grads["none"]
    res = {
        "views": list(views), "spp": spp * seeds, "eps": eps,
        "boundary_share": float(np.linalg.norm(e - n) / np.linalg.norm(e)),
        "cos_edge_none": cos(e, n), "cos_edge_projective": cos(e, grads["projective"]),
        "norm_projective_over_edge": float(np.linalg.norm(grads["projective"]) / np.linalg.norm(e)),
        "cos_none_mitsuba_direct": cos(n, grads["mitsuba_direct"]),
        "cos_projective_mitsuba_direct": cos(grads["projective"], grads["mitsuba_direct"]),
        "directional": fd,
    }
    cache.write_text(json.dumps(res, indent=1))
    log(f"gradient check: {res}")
    return res


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="\n".join(__doc__.split("\n")[2:]))
    p.add_argument("--out", type=Path, default=REPO / "bench" / "out" / "ablations", help="results folder")
    p.add_argument("--study", action="append", choices=STUDIES,
                   help="run only this study (repeatable; the base run always comes first)")
    p.add_argument("--report-only", action="store_true", help="only regenerate docs/ablations.md from existing results")
    p.add_argument("--docs", type=Path, default=DOCS, help="where ablations.md and the plots go")
    args = p.parse_args(argv)
    out = args.out.resolve()

    if not args.report_only:
        studies = set(args.study or STUDIES)
        runs = [r for r in RUNS if r.study == "all" or r.study in studies]
        t0 = time.perf_counter()
        spent = 0.0
        for k, run in enumerate(runs):
            log(f"[{k + 1}/{len(runs)}] {run.name}")
            spent += execute(out, run)
        if "gradients" in studies:
            gradient_check(out)
        total = time.perf_counter() - t0
        log(f"all runs: {total:.0f} s wall in this call ({spent:.0f} s in runs and captures)")
        hist = out / "sessions.jsonl"
        with open(hist, "a") as f:
            f.write(json.dumps({"finished": time.strftime("%Y-%m-%d %H:%M:%S"), "studies": sorted(studies),
                                "seconds": total}) + "\n")

    path = write_report(out, args.docs)
    log(f"report: {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
