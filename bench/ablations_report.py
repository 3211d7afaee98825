"""The report writer of the ablation studies: ``docs/ablations.md`` and its plots from the
``bench.json`` files of the runs (``bench/ablations.py --report-only`` calls :func:`write_report`).

The paper's numbers are quoted here; the study's definition is ``bench/ablation_runs.py``; the
true material levels of the synthetic objects and the optimizer's default loss weights come
from ``recon`` itself.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from ablation_runs import (
    BASE_SET,
    BASE_STAGES,
    CAPTURES,
    CRUDE,
    NEUTRAL_PINS,
    PRESET,
    REPO,
    RUN_BY_NAME,
    RUNS,
    SYNTH_COMMON,
    load,
    log,
)

sys.path.insert(0, str(REPO))
from recon.synth.materials import ROUGHNESS_LEVELS, SPECULAR_LEVELS  # noqa: E402


def _default_weights() -> str:
    """The optimizer's default prior weights, as the report states them (every run uses them)."""
    import dataclasses

    from recon.optimize.settings import LossSettings  # imports torch and the renderer: only when writing

    defaults = {f.name: f.default for f in dataclasses.fields(LossSettings)}
    return ", ".join(f"{k} {defaults[k]:g}" for k in ("w_laplacian", "w_normal", "w_specular", "w_roughness"))


# ---- The paper's numbers, quoted from shared/paper/luan2021-unified-shape-svbrdf.tex ----
# Figures are numbered in LaTeX source order (teaser = 1, fig:diff_render = 2, ...).
PAPER_GRADIENTS = {  # Fig. 3 (fig:ablation1): average point-to-mesh distance, unit bounding box
    "columns": ("Init. mesh", "SoftRas", "PyTorch3D", "Mitsuba 2", "Nvdiffrast", "Ours"),
    "kettle": (0.0411, 0.0051, 0.0072, 0.0071, 0.0013, 0.0004),
    "head": (0.0115, 0.0039, 0.0091, 0.0065, 0.0022, 0.0016),
    "maneki": (0.0878, 0.0053, 0.0066, 0.0071, 0.0023, 0.0010),
}
PAPER_GEOMETRY = {  # Fig. 4 (fig:ablation3): average point-to-mesh distance
    "columns": ("Init. mesh", "No Laplacian", "No normal/edge loss", "No coarse-to-fine", "Ours"),
    "pig": (0.0318, 0.0014, 0.0013, 0.0137, 0.0006),
    "bell": (0.0197, 0.0011, 0.0010, 0.0132, 0.0005),
}
PAPER_MATERIALS = {  # Fig. 5 (fig:ablation4): kitty, novel environment lighting, "RMSE"
    "No spec. correlation": 0.0472, "No roug. smoothness": 0.0636, "Ours": 0.0177,
}
PAPER_VIEWS = {  # Fig. 6 (fig:ablation_n_input): novel view under environmental lighting, "RMSE"
    "kitty": {10: 0.0494, 30: 0.0141, 50: 0.0072, 100: 0.0065},
    "pig": {10: 0.0860, 30: 0.0532, 50: 0.0416, 100: 0.0391},
}
VIEW_RUNS = {10: "views_10", 30: "views_30", 50: "base", 100: "views_100"}
SEED_RUNS = ("base", "base_seed1", "base_seed2")
# 200-iteration edge-sampling runs with large steps on blob_v50 (the per-iteration cost of edge sampling)
EDGE_200_RUNS = ("base", "base_seed1", "base_seed2", "geo_ls_nolap", "geo_ls_nonormaledge", "mat_nospec",
                 "mat_norough")


def metrics(out: Path, name: str) -> dict | None:
    """The numbers of one run that the report uses (None when the run has no bench.json)."""
    r = load(out, name)
    if r is None:
        return None
    meta_path = out / "runs" / name / "ablation_run.json"
    meta = json.loads(meta_path.read_text()) if meta_path.is_file() else {}
    iters = sum(int(st["iterations"]) for st in r.get("stages", [])) or None
    tex = r.get("texture_errors", {})
    load_avg = meta.get("load_average")
    return {
        "acc0": r["init_accuracy"]["accuracy"],
        "acc": r["final_accuracy"]["accuracy"],
        "comp": r["final_accuracy"]["completeness"],
        "chamfer": r["final_accuracy"]["chamfer"],
        "rmse": r["novel_view_rmse"],
        "relight": r.get("relight_rmse"),
        "floor": r.get("relight_noise_floor"),
        "mae_d": tex.get("diffuse", {}).get("mae"),
        "mae_s": tex.get("specular", {}).get("mae"),
        "mae_r": tex.get("roughness", {}).get("mae"),
        "wall": r["wall_seconds"],
        "iters": iters,
        "s_it": r["wall_seconds"] / iters if iters else None,
        "load": load_avg[0] if load_avg else None,
        "total": meta.get("seconds"),
        "manifold": r.get("manifold"),
        "capture": Path(r["capture"]).name,
        "backoffs": sum(int(st.get("guard_backoffs", 0)) for st in r.get("stages", [])),
        "material_model": r.get("material_model"),
        "commit": meta.get("commit"),
        "finished": meta.get("finished"),
    }


def _f(x, nd: int = 4) -> str:
    if x is None:
        return "—"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, int):
        return str(x)
    return f"{x:.{nd}f}"


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def _ratio(a, b) -> str:
    return "—" if a is None or b is None or b == 0 else f"{a / b:.2f}x"


def _order(items: dict) -> str:
    """``label (value) < label (value) ...`` ascending, missing values left out."""
    have = sorted(((v, k) for k, v in items.items() if v is not None))
    return " < ".join(f"{k} ({v:.5f})" for v, k in have) if have else "—"


# ---- Plots ----
def _log_curve(out: Path, name: str):
    """(cumulative optimize seconds, render loss) per iteration from the run's log.jsonl."""
    import numpy as np

    path = out / "runs" / name / "optimize" / "log.jsonl"
    if not path.is_file():
        return None
    recs = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    t = np.cumsum([sum(r.get(k, 0.0) for k in ("t_render", "t_loss", "t_backward", "t_step", "t_geometry"))
                   for r in recs])
    return t, np.array([r["loss_render"] for r in recs])


def _smooth(y, k: int = 15):
    import numpy as np

    k = max(1, min(k, len(y)))
    return np.convolve(y, np.ones(k) / k, mode="valid"), k


def _pyplot():
    """matplotlib.pyplot on the file-only Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, docs: Path, name: str) -> str:
    """Write ``fig`` to ``docs/name`` (the figures' common size and layout) and close it."""
    fig.tight_layout()
    fig.savefig(docs / name, dpi=110)
    _pyplot().close(fig)
    return name


def plot_gradients(out: Path, docs: Path, M: dict) -> str | None:
    import matplotlib.ticker

    plt = _pyplot()

    curves = {lab: _log_curve(out, n) for n, lab in (
        ("base", "edge sampling (ours)"), ("grad_none", "interior only"),
        ("grad_projective", "direct_projective, equal iterations"),
        ("grad_projective_time", "direct_projective, equal time"))}
    if not any(c is not None for c in curves.values()):
        return None
    fig, (a0, a1) = plt.subplots(1, 2, figsize=(11, 4.2))
    colors = {"edge": "C0", "interior": "C1", "direct_projective, equal iterations": "C2",
              "direct_projective, equal time": "C3"}
    for lab, c in curves.items():
        if c is None:
            continue
        t, y = c
        col = next(v for key, v in colors.items() if lab.startswith(key))
        if len(y) < 20:  # too short to smooth: every iteration
            a0.plot(t, y, label=lab + " (raw)", color=col, marker="o", ms=3)
        else:
            ys, k = _smooth(y, 10)
            a0.plot(t[k - 1:], ys, label=lab, color=col)
    a0.set_xscale("log")
    a0.set_xlabel("optimize seconds (log; shared 2-core machine)")
    a0.set_ylabel("rendering loss (moving mean of 10 iterations)")
    a0.set_title("Loss against time, same initial mesh and views")
    a0.legend(fontsize=7, loc="upper right")
    series = {"edge sampling": ("grad_edge_half", "base"), "interior only": ("grad_none_half", "grad_none"),
              "direct_projective": ("grad_projective_time", "grad_projective")}
    for (lab, names), col in zip(series.items(), ("C0", "C1", "C2"), strict=True):
        pts = [(M[n]["wall"], M[n]["acc"], M[n]["iters"]) for n in names if M.get(n)]
        if pts:
            a1.plot([p[0] for p in pts], [p[1] for p in pts], "o-", color=col, label=lab)
            for x, y, it in pts:
                a1.annotate(f"{it} it", (x, y), textcoords="offset points", xytext=(4, 4), fontsize=7)
    if M.get("base"):
        a1.axhline(M["base"]["acc0"], color="grey", ls="--", lw=1, label="initial mesh")
    a1.set_yscale("log")
    a1.set_xscale("log")
    a1.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    a1.set_xlabel("optimize wall seconds (log)")
    a1.set_ylabel("final accuracy (unit bbox)")
    a1.set_title("Accuracy against time per gradient method")
    a1.legend(fontsize=8)
    return _save(fig, docs, "ablations_gradients.png")


def plot_geometry(docs: Path, M: dict) -> str | None:
    plt = _pyplot()
    import numpy as np

    variants = ("No Laplacian", "No normal/edge loss", "No coarse-to-fine")
    ours = {"ours, Adam": ("geo_adam_full", ("geo_adam_nolap", "geo_adam_nonormaledge", "geo_adam_noc2f")),
            "ours, large steps": ("base", ("geo_ls_nolap", "geo_ls_nonormaledge", "geo_ls_noc2f"))}
    bars = {}
    for lab, (full, names) in ours.items():
        if M.get(full):
            bars[lab] = [M[n]["acc"] / M[full]["acc"] if M.get(n) else np.nan for n in names]
    if not bars:
        return None
    for obj in ("pig", "bell"):
        v = PAPER_GEOMETRY[obj]
        bars[f"paper, {obj}"] = [v[1] / v[4], v[2] / v[4], v[3] / v[4]]
    fig, ax = plt.subplots(figsize=(8, 4))
    x = np.arange(len(variants))
    w = 0.8 / len(bars)
    for i, (lab, vals) in enumerate(bars.items()):
        ax.bar(x + (i - (len(bars) - 1) / 2) * w, vals, w, label=lab, hatch="//" if lab.startswith("paper") else None)
    ax.axhline(1, color="k", lw=0.8)
    ax.set_xticks(x, variants)
    ax.set_yscale("log")
    ax.set_ylabel("final accuracy / full method's")
    ax.set_title("Geometry ablations: how much worse than the full method")
    ax.legend(fontsize=8)
    return _save(fig, docs, "ablations_geometry.png")


def plot_views(docs: Path, M: dict) -> str | None:
    plt = _pyplot()

    pts = [(n, M[r]) for n, r in VIEW_RUNS.items() if M.get(r)]
    if not pts:
        return None
    fig, (a0, a1) = plt.subplots(1, 2, figsize=(10, 4.8))
    n = [p[0] for p in pts]
    a0.plot(n, [p[1]["acc"] for p in pts], "o-", label="accuracy")
    a0.plot(n, [p[1]["comp"] for p in pts], "s--", label="completeness")
    seeds = [M[r]["acc"] for r in SEED_RUNS if M.get(r)]
    if len(seeds) > 1:
        a0.errorbar([50], [sum(seeds) / len(seeds)], yerr=[[sum(seeds) / len(seeds) - min(seeds)],
                    [max(seeds) - sum(seeds) / len(seeds)]], fmt="none", ecolor="k", capsize=4,
                    label=f"accuracy range over {len(seeds)} seeds (50 views)")
    a0.set_xscale("log")
    a0.set_ylim(bottom=0)
    a0.set_xticks([10, 30, 50, 100], ["10", "30", "50", "100"])
    a0.set_xlabel("input views")
    a0.set_ylabel("distance (unit bbox)")
    a0.set_title("Ours (blob): geometry against views")
    a0.legend(fontsize=8)
    a1.plot(n, [p[1]["rmse"] for p in pts], "o-", label="ours: novel views, collocated light")
    if any(p[1]["relight"] is not None for p in pts):
        a1.plot(n, [p[1]["relight"] for p in pts], "o-", label="ours: novel views, environment map")
    for obj, vals in PAPER_VIEWS.items():
        a1.plot(list(vals), list(vals.values()), "^:", label=f"paper ({obj}): novel view, environment map")
    a1.set_xscale("log")
    a1.set_xticks([10, 30, 50, 100], ["10", "30", "50", "100"])
    a1.set_xlabel("input views")
    a1.set_ylabel("image RMSE")
    a1.set_title("Image error against views")
    a1.set_ylim(bottom=0)
    a1.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.15), ncol=2)
    return _save(fig, docs, "ablations_views.png")


# ---- The report ----
def _runs_table(M: dict, names: list[str], cols: tuple[str, ...]) -> str:
    spec = {
        "iters": ("iterations", lambda m: _f(m["iters"])),
        "acc0": ("init accuracy", lambda m: _f(m["acc0"])),
        "acc": ("final accuracy", lambda m: _f(m["acc"], 5)),
        "comp": ("completeness", lambda m: _f(m["comp"], 5)),
        "rmse": ("novel RMSE (collocated)", lambda m: _f(m["rmse"])),
        "relight": ("novel RMSE (env. map)", lambda m: _f(m["relight"])),
        "mae_d": ("diffuse MAE", lambda m: _f(m["mae_d"])),
        "mae_s": ("specular MAE", lambda m: _f(m["mae_s"])),
        "mae_r": ("roughness MAE", lambda m: _f(m["mae_r"])),
        "wall": ("optimize s", lambda m: _f(m["wall"], 0)),
        "s_it": ("s / iteration", lambda m: _f(m["s_it"], 2)),
        "load": ("load avg", lambda m: _f(m["load"], 1)),
    }
    header = ["run", "variant"] + [spec[c][0] for c in cols]
    rows = []
    for n in names:
        run, m = RUN_BY_NAME[n], M.get(n)
        label = "full (base run)" if n == "base" else run.label
        rows.append([f"`{n}`", label] + ([spec[c][1](m) for c in cols] if m else ["not run"] + [""] * (len(cols) - 1)))
    return _table(header, rows)


def write_report(out: Path, docs: Path) -> Path:
    """Regenerate ``docs/ablations.md`` (and the plots) from the bench.json files under ``out``."""
    docs.mkdir(parents=True, exist_ok=True)
    M = {r.name: metrics(out, r.name) for r in RUNS}
    plots = {}
    for key, fn in (("gradients", lambda: plot_gradients(out, docs, M)), ("geometry", lambda: plot_geometry(docs, M)),
                    ("views", lambda: plot_views(docs, M))):
        try:
            plots[key] = fn()
        except Exception as e:  # a plot must never stop the report
            log(f"plot {key} failed: {e!r}")
            plots[key] = None
    run_seconds = sum(m["total"] or 0.0 for m in M.values() if m)
    synth_seconds = 0.0
    for key in CAPTURES:
        p = out / "captures" / f"{key}.json"
        if p.is_file():
            synth_seconds += json.loads(p.read_text())["seconds"]
    commits = sorted({m["commit"] for m in M.values() if m and m["commit"]})
    finished = sorted(m["finished"] for m in M.values() if m and m["finished"])
    text = report_text(out, M, plots, run_seconds, synth_seconds, commits, finished)
    path = docs / "ablations.md"
    tmp = path.with_suffix(".md.tmp")
    tmp.write_text(text)
    tmp.replace(path)
    return path


def silhouette_contrast(cap: Path, max_views: int = 20, depths=(1, 2, 5, 10)) -> dict | None:
    """How bright the object is just inside its outline, against its median (from the photos).

    Per view and depth d (pixels): mean luminance of the mask pixels whose distance to the
    background is d (+- 0.5) over the median luminance of all mask pixels; means over views.
    Near the outline this is the relative size of the jump the boundary term integrates.
    """
    import cv2
    import numpy as np

    from recon.io.images import read_exr, read_mask

    if not (cap / "cameras.json").is_file():
        return None
    frames = json.loads((cap / "cameras.json").read_text())["frames"][:max_views]
    prof: dict[int, list[float]] = {d: [] for d in depths}
    for fr in frames:
        img = read_exr(cap / fr["image"])[:, :, :3]
        m = read_mask(cap / "masks" / (Path(fr["image"]).stem + ".png"))
        dist = cv2.distanceTransform(m.astype(np.uint8), cv2.DIST_L2, 3)
        lum = img @ np.array([0.2126, 0.7152, 0.0722], np.float32)
        med = float(np.median(lum[m])) if m.any() else 0.0
        for d in depths:
            sel = (dist > d - 0.5) & (dist <= d + 0.5)
            if sel.any() and med > 0:
                prof[d].append(float(lum[sel].mean()) / med)
    return {d: float(np.mean(v)) for d, v in prof.items() if v} or None


def _paper_table(paper: dict, first: str) -> str:
    rows = [[f"*{obj}*"] + [f"{v:.4f}" for v in vals] for obj, vals in paper.items() if obj != "columns"]
    return _table([first, *paper["columns"]], rows)


def _pct(a, b) -> str:
    """``a`` relative to ``b`` as a signed percentage."""
    return "—" if a is None or b is None else f"{100 * (a / b - 1):+.0f}%"


def _get(M, name, key):
    return M[name][key] if M.get(name) else None


def report_text(out: Path, M: dict, plots: dict, run_seconds: float, synth_seconds: float,
                commits: list, finished: list) -> str:
    base = M.get("base") or {}
    seeds = [M[n]["acc"] for n in SEED_RUNS if M.get(n)]
    spread = (max(seeds) - min(seeds)) / min(seeds) if len(seeds) > 1 else None
    spread_txt = (f"{100 * spread:.0f}%" if spread is not None else "not measured yet")
    loads = [m["load"] for m in M.values() if m and m["load"] is not None]
    n_done = sum(1 for m in M.values() if m)
    L = []
    w = L.append
    w("# Ablation studies: the paper's figures on our benchmark harness")
    w("")
    w("Generated by `python bench/ablations.py --out bench/out/ablations` (`--report-only` rewrites this page "
      "from the `bench.json` files that exist; do not edit it by hand, edit `bench/ablations_report.py`). "
      f"{n_done}/{len(RUNS)} runs present"
      + (f", finished {finished[0]} to {finished[-1]}" if finished else "")
      + (f", code at commit {', '.join(commits)} plus other engineers' uncommitted work in the tree" if commits else "")
      + ".")
    w("")
    w("Figure numbers follow the LaTeX source of `shared/paper/luan2021-unified-shape-svbrdf.tex` (the teaser "
      "is Figure 1 and the differentiable-rendering diagram Figure 2, so the renderer comparison is Figure 3); "
      "the label is given beside each, since the task brief counted them one lower (its \"Figure 2-5\").")
    w("")
    w("## Setup")
    w("")
    w("- **Captures**: `python -m recon synth DIR --object blob --views N "
      + " ".join(SYNTH_COMMON) + "` (glossy blob, textured diffuse albedo, three roughness sectors; the "
      "torus with `--object torus`), cached under `bench/out/ablations/captures/`. 50 views for every study "
      "but the views study.")
    base_stages = "; ".join(", ".join(f"{k} {v}" for k, v in st.items()) for st in BASE_STAGES)
    w(f"- **Base configuration** (every run; a row changes only what it names): preset `{PRESET}` with these keys "
      "pinned by `--set` so that a later preset edit cannot move them: "
      + ", ".join(f"`{k}={v}`" for k, v in BASE_SET.items())
      + f", stages: [{base_stages}] (200 iterations in all); "
      + ", ".join(f"`{k}={str(v).lower()}`" for k, v in NEUTRAL_PINS.items())
      + " (switches added to the optimize stage and turned on in the presets while this study ran) pinned off, "
      "as every run here had them (the last one changes nothing at these stages' edge lengths, all >= 0.03); everything else "
      "the defaults of "
      "`recon/optimize/settings.py` (loss weights " + _default_weights() + "; every term a mean, lengths divided "
      f"by the stage's edge length; `w_edge` {BASE_SET['w_edge']} as the presets set it, not the paper's 1).")
    if base:
        w(f"  It improves the geometry clearly: accuracy {base['acc0']:.4f} -> {base['acc']:.5f} "
          f"({base['acc0'] / base['acc']:.0f}x) in {base['wall']:.0f} s of optimization. It is a reduced "
          "configuration: 128x96 images, 2 spp, 200 iterations; the paper ran 500-1000 iterations for 0.5-2 h on "
          "a GPU per example, so the materials in particular are far from converged here (see study 3).")
    w(f"- **Initial mesh**: `bench/optimize.py --crude {CRUDE}` in the base run: the 50-view visual hull, 10 "
      "Laplacian smoothing steps, shrunk towards its centroid until its accuracy is about the target "
      + (f"(achieved: accuracy {base['acc0']:.4f}, completeness {_f(_init_comp(out))})" if base else "")
      + ". Every other run starts from that file (`--init`), the views study too, so only the photos change.")
    w("- **Metrics** (all from `bench/optimize.py`): accuracy / completeness = mean distance from the result to "
      "the ground truth / back, 100k samples, divided by the ground truth's longest bounding-box side (the "
      "paper's unit bounding box). *Novel RMSE (collocated)*: sRGB RMSE over the union of masks in 8 views at "
      "elevations and azimuths between the input views, lit by the collocated flash. *Novel RMSE (env. map)*: "
      "the same views relit by the procedural environment map of `recon.render.envmap` (`relight_rmse`, 64 spp"
      + (f"; its Monte Carlo noise floor, ground truth against itself with other seeds, is {base['floor']:.4f}"
         if base.get("floor") is not None else "") + "); the paper's Figures 5 and 6 report this kind of error. "
      "*Texture MAE*: |result - truth| at 20k area-uniform points of the true surface, the result looked up at "
      "its closest point.")
    w("- **Time**: the machine has 2 cores shared with other engineers' jobs running at the same time (the "
      + (f"1-minute load average at the end of the runs was {min(loads):.1f}-{max(loads):.1f}" if loads else
         "load was not recorded") + "), so wall times carry tens of percent of noise; per-iteration ratios "
      "measured back to back are more trustworthy than absolute seconds. Each run gets `OMP_NUM_THREADS=1`: "
      "with the default two OpenMP threads, torch stalled for seconds at barriers whenever the other core was "
      "busy (measured once on the base run, kept in `bench/out/ablations/old/`: loss phase median 0.13 s, "
      "mean 0.95 s, max 6 s per iteration; 353 s of optimization instead of about 45 s).")
    w(f"- **Spread of the method itself**: the base configuration with other seeds (`seed` = 0, 1, 2: other "
      f"views per iteration, other render noise) spans {spread_txt} in accuracy (max - min over min"
      + (": " + ", ".join(f"{M[n]['acc']:.5f}" for n in SEED_RUNS if M.get(n)) + "; novel RMSE "
         + ", ".join(f"{M[n]['rmse']:.4f}" for n in SEED_RUNS if M.get(n)) if spread is not None else "")
      + "). Differences of that size below are noise, not effects.")
    total = run_seconds + synth_seconds
    proj_s = sum(M[n]["total"] or 0.0 for n in ("grad_projective", "grad_projective_time") if M.get(n))
    w(f"- **Run time**: {run_seconds / 60:.1f} min in `bench/optimize.py` calls (optimization plus its metrics: "
      f"crude-mesh search, 8 novel views, relighting) + {synth_seconds / 60:.1f} min making captures = "
      f"{total / 60:.1f} min of wall time for everything here, {proj_s / 60:.1f} min of it in the two "
      "`direct_projective` runs, on the shared machine (about 30 min budgeted: the projective runs are the "
      "overrun; the other runs took about as long as planned under a load of 3-8).")
    w("")
    L += _section_gradients(out, M, plots, spread)
    L += _section_geometry(M, plots, spread)
    L += _section_materials(out, M, spread)
    L += _section_views(M, plots, spread)
    return "\n".join(L) + "\n"


def _init_comp(out: Path):
    r = load(out, "base")
    return r["init_accuracy"]["completeness"] if r else None


def _img(plots: dict, key: str, alt: str) -> list[str]:
    return [f"![{alt}]({plots[key]})", ""] if plots.get(key) else []


def _same(a, b, spread) -> bool | None:
    """Whether a and b differ by less than the measured seed spread (None: unknown)."""
    if a is None or b is None or spread is None:
        return None
    return abs(a / b - 1) <= max(spread, 0.02)


def _cached_gradient_check(out: Path) -> dict | None:
    p = out / "gradient_check.json"
    return json.loads(p.read_text()) if p.is_file() else None


def _first_loss(out: Path, name: str) -> float | None:
    p = out / "runs" / name / "optimize" / "log.jsonl"
    if not p.is_file():
        return None
    line = p.read_text().split("\n", 1)[0]
    return json.loads(line)["loss_render"] if line.strip() else None


def _section_gradients(out: Path, M: dict, plots: dict, spread) -> list[str]:
    g = lambda n, k: _get(M, n, k)  # noqa: E731
    L: list[str] = []
    w = L.append
    w("## 1. Gradients: edge sampling vs interior only vs Mitsuba's projective sampling "
      "(paper Fig. 3, `fig:ablation1`)")
    w("")
    w("**Paper**: average point-to-mesh distance (unit bounding box); shape only, known diffuse reflectance, plain "
      "Adam, the same initial mesh and settings for every renderer. The supplement repeats the figure with *head* "
      "SoftRas 0.0043 and Mitsuba 2 0.0064.")
    w("")
    w(_paper_table(PAPER_GRADIENTS, "object"))
    w("")
    w(f"**Ours**: blob, 50 views, the shared crude init (~{CRUDE}), base configuration (shape and materials "
      "together, large steps). `direct_projective` costs far more per iteration than our renderer here, so "
      "its *equal-iterations* run uses half the budget (100 iterations, against `grad_edge_half`), and its "
      "*equal wall time* run gets the base stages' iterations scaled by (seconds per iteration of `base_seed1`, "
      "the 200-iteration edge run made closest in time / seconds per iteration of the projective run), against "
      "the 200-iteration edge runs.")
    w("")
    w(_runs_table(M, ["base", "base_seed1", "base_seed2", "grad_none", "grad_projective", "grad_projective_time",
                      "grad_edge_half", "grad_none_half"], ("iters", "acc", "comp", "rmse", "relight", "wall", "s_it", "load")))
    w("")
    w("Cases where silhouettes should matter more: a cruder start (the paper's worst init, *maneki*, was 0.0878), "
      "a torus (self-occlusion at the inner rim hides a lit surface behind a lit surface), and 10 views (fewer "
      "views that see each surface point head-on):")
    w("")
    w(_runs_table(M, ["grad_crude09_edge", "grad_crude09_none", "grad_torus_edge", "grad_torus_none", "views_10",
                      "grad_v10_none"],
                  ("iters", "acc0", "acc", "comp", "rmse", "wall")))
    w("")
    L += _img(plots, "gradients", "loss against time and accuracy against time per gradient method")
    # ---- discussion ----
    contrast = {k: silhouette_contrast(out / "captures" / k) for k in ("blob_v50", "torus_v50")}
    ref = "base_seed1" if M.get("base_seed1") else "base"  # the edge run made just before the projective one
    r_proj = (g("grad_projective", "s_it") / g(ref, "s_it")) if g("grad_projective", "s_it") and g(ref, "s_it") else None
    w("**Ordering.** The paper: *Ours* < Nvdiffrast < SoftRas < Mitsuba 2 ~ PyTorch3D on every object, the biased "
      "methods 2-18x worse than edge sampling. Ours (final accuracy) at 200 iterations: " + _order({
          "edge": g("base", "acc"), "interior only": g("grad_none", "acc")})
      + "; at 100 iterations: " + _order({
          "edge": g("grad_edge_half", "acc"), "interior only": g("grad_none_half", "acc"),
          "projective": g("grad_projective", "acc")})
      + "; at equal wall time: " + _order({
          "edge, 200 it": g("base", "acc"),
          f"projective, {_f(g('grad_projective_time', 'iters'))} it": g("grad_projective_time", "acc")}) + ".")
    w("")
    pairs = {"200 iterations": ("grad_none", "base"), "100 iterations": ("grad_none_half", "grad_edge_half"),
             "0.09 start": ("grad_crude09_none", "grad_crude09_edge"), "torus": ("grad_torus_none", "grad_torus_edge"),
             "10 views": ("grad_v10_none", "views_10")}
    diffs = {k: (g(a, "acc") / g(b, "acc") - 1) for k, (a, b) in pairs.items() if g(a, "acc") and g(b, "acc")}
    txt = ("**Interior only vs edge sampling.** Dropping the boundary term changes the final accuracy by "
           + ", ".join(f"{100 * d:+.0f}% ({k})" for k, d in diffs.items())
           + f"; the seed-to-seed spread of the full method is "
           f"{'%.0f%%' % (100 * spread) if spread is not None else 'not measured'}. ")
    if diffs and spread is not None:
        worst = max(diffs, key=lambda k: diffs[k])
        tol = max(spread, 0.02)
        inside = [k for k, d in diffs.items() if abs(d) <= tol]
        if diffs[worst] <= tol:
            txt += ("Every difference is inside that spread: no measurable effect of the silhouette term in any "
                    "case tried (the previous session's finding on the blob holds, and extends to the other "
                    "cases). ")
        elif diffs[worst] <= 1.5 * tol:
            txt += (f"The largest, {100 * diffs[worst]:+.0f}% ({worst}), is at the edge of that spread (measured "
                    f"on the blob), {len(inside)} of {len(diffs)} are inside it: at most a small effect, far from "
                    "the paper's 2-18x. ")
        else:
            txt += (f"The largest, {100 * diffs[worst]:+.0f}% ({worst}), clearly exceeds that spread: an effect "
                    f"where silhouettes carry more; {len(inside)} of {len(diffs)} are inside it. ")
    gc0 = _cached_gradient_check(out)
    if gc0:
        txt += (f"The gradient check below says the same directly: on the crude init, with the real loss, our "
                f"boundary term is {100 * gc0['boundary_share']:.1f}% of the vertex gradient's norm (cosine between "
                f"the gradients with and without it: {gc0['cos_edge_none']:.3f}). ")
    txt += ("Why the silhouette term carries so little here: (1) *the jump is small*. With the light at the camera, "
            "the surface at an outline is seen and lit at a grazing angle, so I(x) -> 0 there (cos term, and a "
            "GGX lobe seen at grazing), and the jump dI across the outline against the black background, which the "
            "boundary integral weights, is small")
    cb = contrast.get("blob_v50")
    if cb:
        txt += (": in the blob's photos (256x192) the pixels " + " / ".join(str(d) for d in cb) + " px inside the "
                "outline average " + " / ".join(f"{v:.2f}" for v in cb.values()) + "x the object's median "
                "intensity, falling to zero at the outline (the optimization's 128x96 images halve those distances)")
    txt += (". (2) *The interior term already sees depth*: the point light's 1/|y - o|^2 falloff and the shading "
            "make a shrunk surface render darker than the photo at the same pixels, and the interior gradient "
            "moves it towards the camera, i.e. outwards. (3) *Views make outlines redundant*: a point on an "
            "outline in one view is seen head-on in others, where (2) constrains it; with 10-100 views around the "
            "object every point is frontal somewhere" + (
                ", and the 10-view case, where that redundancy is weakest, is where dropping the term costs most"
                if diffs and max(diffs, key=lambda k: diffs[k]) == "10 views" else "") + ". (4) *Large steps* (u = (I + lambda L) v) spread each "
            "vertex gradient over its neighbourhood, so outline vertices move with the interior ones. (5) The loss "
            "has no mask term: masks only black out the photos' background, so an outline mismatch shows only in "
            "the pixels between the two outlines, where dI is small. The term should matter for objects in front "
            "of a lit backdrop (large dI at every outline), for thin parts the initial mesh misses entirely (no "
            "surface there for the interior term to move), and with few, clustered views. The paper's gains in "
            "its Fig. 3 were measured against *biased* boundary handling (soft rasterization, "
            "reparameterization, antialiasing), not against dropping the term, a comparison this stack cannot "
            "repeat.")
    w(txt)
    w("")
    gc = _cached_gradient_check(out)
    first = {n: _first_loss(out, n) for n in ("grad_edge_half", "grad_projective")}
    pj = "**Mitsuba's `direct_projective`.** "
    if r_proj:
        edge_s_it = [M[n]["s_it"] for n in EDGE_200_RUNS if M.get(n) and M[n]["s_it"]]
        rng = (f"; {g('grad_projective', 's_it') / max(edge_s_it):.0f}-{g('grad_projective', 's_it') / min(edge_s_it):.0f}x "
               f"against all {len(edge_s_it)} 200-iteration edge-sampling runs on this capture, whose seconds per "
               "iteration vary with the load from other jobs" if len(edge_s_it) > 1 else "")
        pj += (f"It costs {r_proj:.0f}x our edge-sampled renderer per iteration "
               f"({_f(g('grad_projective', 's_it'), 2)} vs {_f(g(ref, 's_it'), 2)} s for `{ref}`{rng}). ")
    if g("grad_projective", "acc"):
        pj += (f"At equal iterations (100) it ends at {_f(g('grad_projective', 'acc'), 5)} against edge "
               f"sampling's {_f(g('grad_edge_half', 'acc'), 5)} "
               f"({_ratio(g('grad_projective', 'acc'), g('grad_edge_half', 'acc'))})")
        if first["grad_projective"] is not None and first["grad_edge_half"] is not None:
            pj += (f"; both start from the same loss (iteration 0, same views: "
                   f"{first['grad_projective']:.4f} vs {first['grad_edge_half']:.4f}, so the two forward renders agree)")
        pj += ". "
    if g("grad_projective_time", "acc"):
        pj += (f"At equal wall time it gets {_f(g('grad_projective_time', 'iters'))} iterations and ends at "
               f"{_f(g('grad_projective_time', 'acc'), 5)}, against {_f(g('base', 'acc'), 5)} for edge sampling's "
               f"200. ")
    if gc:
        de, dp = gc["directional"]["edge"], gc["directional"]["projective"]
        agree = gc["cos_edge_projective"] > 0.9 and 0.8 < gc["norm_projective_over_edge"] < 1.25
        pj += (f"Gradient check (below): the Mitsuba route's vertex gradient has cosine {gc['cos_edge_projective']:.3f} "
               f"with ours at {gc['norm_projective_over_edge']:.2f}x the norm; along our gradient's direction the "
               f"finite difference of the loss is {de['finite_difference']:+.4f}, ours predicts "
               f"{de['predicted_by_edge']:+.4f}, the Mitsuba route {de['predicted_by_projective']:+.4f}; along the "
               f"Mitsuba route's direction the finite difference is {dp['finite_difference']:+.4f}, ours predicts "
               f"{dp['predicted_by_edge']:+.4f}, it {dp['predicted_by_projective']:+.4f}. ")
        pj += (f"The two estimators agree in expectation (the check's gradients are means over {gc['spp']} samples per pixel), "
               "so the rows above compare the same gradient at different costs and per-step noise: a gap at equal "
               f"iterations beyond the seed spread comes from the noise of single {BASE_SET['spp']}-spp steps, where "
               "Mitsuba's estimator spends its samples differently from ours (not measured separately). "
               if agree else "The two estimators still disagree beyond their noise; the rows above measure that. ")
    pj += ("\n\n*History*: until session 4 these rows were invalid. `MitsubaScene` moved its one point light to "
           "each view of a batch and rendered them one by one, while Mitsuba's render op replays the scene in its "
           "backward pass in the state it has *then*, so every view got its gradient under the last view's light "
           "(then: cosine 0.09 with our gradient at 2.2x the norm; accuracy after 100 iterations 0.0062 against "
           "0.0011). It now keeps one scene per view of a batch; the regression test "
           "`tests/render/test_collocated.py::test_projective_batch_backward_uses_each_views_light` checks that a "
           "view's gradient in a batch equals its gradient alone. The paper's Mitsuba 2 column "
           "(reparameterization, biased) cannot be reproduced with this stack.")
    w(pj)
    w("")
    if gc:
        w(f"**Gradient check** (`gradient_check.json`; the shared crude init, views {gc['views']}, {gc['spp']} spp per "
          "route, the loss of eq. 6; finite differences with our forward at 64 spp and common random numbers, "
          f"step {gc['eps']:.1e}):")
        w("")
        rows = [["boundary share of our gradient, abs(edge - interior only) / abs(edge)", f"{gc['boundary_share']:.3f}"],
                ["cosine(edge, interior only)", f"{gc['cos_edge_none']:.3f}"],
                ["cosine(edge, Mitsuba direct_projective)", f"{gc['cos_edge_projective']:.3f}"],
                ["norm(direct_projective) / norm(edge)", f"{gc['norm_projective_over_edge']:.2f}"],
                ["cosine(interior only, Mitsuba direct)", f"{gc['cos_none_mitsuba_direct']:.3f}"],
                ["cosine(Mitsuba direct_projective, Mitsuba direct)", f"{gc['cos_projective_mitsuba_direct']:.3f}"]]
        for route, d in gc["directional"].items():
            rows.append([f"along the {route} gradient: finite difference / predicted by edge / by projective",
                         f"{d['finite_difference']:+.5f} / {d['predicted_by_edge']:+.5f} / {d['predicted_by_projective']:+.5f}"])
        w(_table(["quantity", "value"], rows))
        w("")
    w("**Differences from the paper's set-up.** The paper optimized shape only with known diffuse reflectance and "
      "plain Adam; here shape and SVBRDF are optimized together with large steps (the pipeline's default), on a "
      "synthetic glossy blob, 200 iterations at 128x96, 2 spp. The paper's baselines (soft rasterizers, "
      "reparameterization, nvdiffrast) are not in this stack; `boundary=none` is the crudest biased gradient "
      "(the silhouette term dropped entirely), and it costs less here than any of the paper's biased renderers did.")
    w("")
    return L


def material_stats(out: Path, name: str, n: int = 20000) -> dict | None:
    """What the material priors act on, measured where the truth is constant (cached per run).

    At ``n`` area-uniform points of the true surface (the result's maps looked up at the closest
    point of the result): within each true specular band, the correlation of the recovered
    specular albedo with the true diffuse luminance (diffuse colour "baked" into specular: the
    paper's Fig. 5 claim for w_specular = 0) and its standard deviation; within each true
    roughness sector, the standard deviation of the recovered roughness (noise: the claim for
    w_roughness = 0). Means over bands/sectors weighted by their point counts.
    """
    import numpy as np

    rdir = out / "runs" / name
    bench = rdir / "bench.json"
    cache = rdir / "material_stats.json"
    if not bench.is_file():
        return None
    if cache.is_file() and cache.stat().st_mtime >= bench.stat().st_mtime:
        return json.loads(cache.read_text())
    from recon.io.images import read_exr
    from recon.io.mesh import read_mesh
    from recon.optimize.remesh import bilinear_lookup, surface_uv
    from recon.report.gt import sample_surface_uv

    cap = Path(json.loads(bench.read_text())["capture"])
    gt, rec = read_mesh(cap / "gt" / "mesh.obj"), read_mesh(rdir / "optimize" / "mesh.obj")
    p, uv_gt = sample_surface_uv(gt, n, np.random.default_rng(1))
    uv_rec = surface_uv(rec, p)
    look = lambda d, k, uv: bilinear_lookup(read_exr(d / f"{k}.exr"), uv)  # noqa: E731
    lum = look(cap / "gt", "diffuse", uv_gt)[:, :3] @ np.array([0.2126, 0.7152, 0.0722])
    s_gt, r_gt = look(cap / "gt", "specular", uv_gt)[:, 0], look(cap / "gt", "roughness", uv_gt)[:, 0]
    s_rec = look(rdir / "optimize", "specular", uv_rec).mean(axis=1)
    r_rec = look(rdir / "optimize", "roughness", uv_rec)[:, 0]
    corr, s_std, r_std, ns, nr = 0.0, 0.0, 0.0, 0, 0
    for v in SPECULAR_LEVELS:  # the true specular bands
        sel = np.abs(s_gt - v) < 0.005
        if sel.sum() > 100:
            corr += sel.sum() * float(np.corrcoef(s_rec[sel], lum[sel])[0, 1])
            s_std += sel.sum() * float(s_rec[sel].std())
            ns += int(sel.sum())
    for v in ROUGHNESS_LEVELS:  # the true roughness sectors
        sel = np.abs(r_gt - v) < 0.005
        if sel.sum() > 100:
            r_std += sel.sum() * float(r_rec[sel].std())
            nr += int(sel.sum())
    res = {"spec_diffuse_corr": corr / ns if ns else None, "spec_std_in_band": s_std / ns if ns else None,
           "rough_std_in_sector": r_std / nr if nr else None, "points_spec": ns, "points_rough": nr}
    cache.write_text(json.dumps(res, indent=1))
    return res


def _section_geometry(M: dict, plots: dict, spread) -> list[str]:
    g = lambda n, k: _get(M, n, k)  # noqa: E731
    L: list[str] = []
    w = L.append
    w("## 2. Geometry priors and schedule (paper Fig. 4, `fig:ablation3`)")
    w("")
    w("**Paper**: average point-to-mesh distance, *pig* and *bell*, identical init and settings, plain Adam:")
    w("")
    w(_paper_table(PAPER_GEOMETRY, "object"))
    w("")
    w("**Ours**: blob, 50 views, shared init, base configuration; with `optimizer=adam` (plain Adam on the vertex "
      "positions, the paper's way) and with large steps (ours; its full run is the base run). *vs full* = final "
      "accuracy over the same optimizer's full run; the paper's ratios are No Laplacian 2.3x / 2.2x, No "
      "normal/edge 2.2x / 2.0x, No coarse-to-fine 23x / 26x (pig / bell).")
    w("")
    rows = []
    for n, full in (("geo_adam_full", "geo_adam_full"), ("geo_adam_nolap", "geo_adam_full"),
                    ("geo_adam_nonormaledge", "geo_adam_full"), ("geo_adam_noc2f", "geo_adam_full"),
                    ("base", "base"), ("geo_ls_nolap", "base"), ("geo_ls_nonormaledge", "base"),
                    ("geo_ls_noc2f", "base")):
        m = M.get(n)
        lab = "large steps: full (base run)" if n == "base" else RUN_BY_NAME[n].label
        rows.append([f"`{n}`", lab] + ([_f(m["acc"], 5), _ratio(m["acc"], g(full, "acc")), _f(m["comp"], 5),
                                         _f(m["rmse"]), _f(m["relight"]), _f(m["wall"], 0)] if m else ["not run"] + [""] * 5))
    w(_table(["run", "variant", "final accuracy", "vs full", "completeness", "novel RMSE (collocated)",
              "novel RMSE (env. map)", "optimize s"], rows))
    w("")
    L += _img(plots, "geometry", "final accuracy of each ablation over the full method's, ours and the paper's")
    w("**Ordering.** Paper (both objects): Ours < No normal/edge <~ No Laplacian << No coarse-to-fine. Ours with "
      "Adam: " + _order({"full": g("geo_adam_full", "acc"), "no Laplacian": g("geo_adam_nolap", "acc"),
                          "no normal/edge": g("geo_adam_nonormaledge", "acc"),
                          "no coarse-to-fine": g("geo_adam_noc2f", "acc")})
      + "; with large steps: " + _order({"full": g("base", "acc"), "no Laplacian": g("geo_ls_nolap", "acc"),
                                          "no normal/edge": g("geo_ls_nonormaledge", "acc"),
                                          "no coarse-to-fine": g("geo_ls_noc2f", "acc")}) + ".")
    w("")
    w("**Where it matches.** Dropping coarse-to-fine is the most harmful ablation in the paper and here "
      f"(Adam {_ratio(g('geo_adam_noc2f', 'acc'), g('geo_adam_full', 'acc'))}, large steps "
      f"{_ratio(g('geo_ls_noc2f', 'acc'), g('base', 'acc'))}, with the worst novel-view error of each group), "
      "and with plain Adam the Laplacian term matters next "
      f"({_ratio(g('geo_adam_nolap', 'acc'), g('geo_adam_full', 'acc'))}, close to the paper's 2.2-2.3x; it also "
      f"took {_ratio(g('geo_adam_nolap', 'wall'), g('geo_adam_full', 'wall'))} the time: the surface guard backed "
      f"off {_f(g('geo_adam_nolap', 'backoffs'))} steps that would have made the bumpy surface self-intersect, "
      f"against {_f(g('geo_adam_full', 'backoffs'))} with the Laplacian).")
    w("")
    w("**Where it differs, and why.** (1) *The magnitudes of no-coarse-to-fine*: the paper's run got stuck at "
      "0.0137 / 0.0132 (23-26x), ours ends only about 2x (Adam) or "
      f"{_ratio(g('geo_ls_noc2f', 'acc'), g('base', 'acc'))} (large steps) worse. Our schedule is short (two stages, "
      "edge length 0.05 then 0.03 of the bounding box): the single-stage ablation starts at 0.03, only 1.7x finer, "
      "where the paper jumped straight to its finest mesh; and the start is a smoothed, uniformly shrunk hull, "
      "a benign init without the wrong topology or concavities a Kinect-Fusion mesh has. "
      "(2) *Large steps absorb the priors*: the update u = (I + lambda L) v already moves vertices as smooth "
      "fields, which is what the Laplacian loss and coarse-to-fine are for, so with it no Laplacian costs "
      f"{_pct(g('geo_ls_nolap', 'acc'), g('base', 'acc'))} and no coarse-to-fine "
      f"{_pct(g('geo_ls_noc2f', 'acc'), g('base', 'acc'))}. "
      "(3) *No normal/edge loss changes nothing* here "
      f"(Adam {_pct(g('geo_adam_nonormaledge', 'acc'), g('geo_adam_full', 'acc'))}, large steps "
      f"{_pct(g('geo_ls_nonormaledge', 'acc'), g('base', 'acc'))}"
      + (", within the seed spread" if _same(g("geo_adam_nonormaledge", "acc"), g("geo_adam_full", "acc"), spread)
         and _same(g("geo_ls_nonormaledge", "acc"), g("base", "acc"), spread) else "") + ") where the paper "
      "measured 2x: the presets weigh the edge term 0.01 instead of the paper's 1 (our terms are means with "
      "lengths divided by the target edge length, so sqrt(mean e^2)/h ~ 1 and its gradient is a weak uniform "
      "shrink), every stage starts from an isotropic remesh, and the surface guard rejects folding and "
      "self-intersecting steps, so the ill-shaped triangles and sharp normal changes the paper's terms prevent "
      "do not arise in 200 iterations. (4) The paper says only that the pig's shape was optimized with "
      "otherwise identical configurations; here shape and materials are optimized together in every run, "
      "from a smooth blob rather than a pig or a bell with thin parts.")
    w("")
    return L


def _section_materials(out: Path, M: dict, spread) -> list[str]:
    g = lambda n, k: _get(M, n, k)  # noqa: E731
    L: list[str] = []
    w = L.append
    w("## 3. Material priors (paper Fig. 5, `fig:ablation4`)")
    w("")
    w("**Paper** (*kitty*, novel environment lighting; the figure shows pictures and the maps, one RMSE per "
      "result): " + ", ".join(f"{k} RMSE {v:.4f}" for k, v in PAPER_MATERIALS.items())
      + ". Text: without the specular correlation \"diffuse colors are baked into specular albedo\"; without "
      "roughness smoothness \"the resulting roughness map contains high-frequency noise\".")
    w("")
    names = ("base", "base_seed1", "base_seed2", "mat_nospec", "mat_norough")
    stats = {n: material_stats(out, n) for n in names}
    rows = []
    paper = {"base": f"{PAPER_MATERIALS['Ours']:.4f}", "mat_nospec": f"{PAPER_MATERIALS['No spec. correlation']:.4f}",
             "mat_norough": f"{PAPER_MATERIALS['No roug. smoothness']:.4f}", "base_seed1": "", "base_seed2": ""}
    for n in names:
        m, st = M.get(n), stats.get(n) or {}
        lab = "full (base run)" if n == "base" else RUN_BY_NAME[n].label
        rows.append([f"`{n}`", lab] + ([_f(m["mae_d"]), _f(m["mae_s"]), _f(m["mae_r"]),
                                         _f(st.get("spec_diffuse_corr"), 3), _f(st.get("spec_std_in_band"), 4),
                                         _f(st.get("rough_std_in_sector"), 4), _f(m["rmse"]), _f(m["relight"]),
                                         _f(m["acc"], 5)] if m else ["not run"] + [""] * 8) + [paper[n]])
    w("**Ours** (blob, 50 views, shared init, base configuration). *spec~diffuse corr*: within each true "
      "specular band (the truth is constant there), the correlation of the recovered specular albedo with the "
      "true diffuse luminance, i.e. diffuse pattern baked into specular; *spec std in band* / *rough std in "
      "sector*: spread of the recovered value where the truth is constant (noise and baking). True values: "
      "specular bands 0.03 / 0.25 / 0.6, roughness sectors 0.18 / 0.4 / 0.75. The two other-seed runs of the "
      "full method show how much of each difference is noise.")
    w("")
    w(_table(["run", "variant", "diffuse MAE", "specular MAE", "roughness MAE", "spec~diffuse corr",
              "spec std in band", "rough std in sector", "novel RMSE (collocated)", "novel RMSE (env. map)",
              "final accuracy", "paper RMSE (kitty, env.)"], rows))
    w("")
    s0, s1, s2 = (stats.get(n) or {} for n in ("base", "mat_nospec", "mat_norough"))
    w("**Ordering.** Paper: Ours (0.0177) < No spec. correlation (0.0472) < No roughness smoothness (0.0636), "
      "2.7x and 3.6x. Ours, environment-map RMSE: " + _order({
          "full": g("base", "relight"), "no spec. correlation": g("mat_nospec", "relight"),
          "no roughness TV": g("mat_norough", "relight")}) + "; collocated novel RMSE: " + _order({
          "full": g("base", "rmse"), "no spec. correlation": g("mat_nospec", "rmse"),
          "no roughness TV": g("mat_norough", "rmse")}) + ".")
    w("")
    agree = None
    if s0.get("rough_std_in_sector") and s1.get("spec_std_in_band") and s2.get("rough_std_in_sector"):
        agree = (s2["rough_std_in_sector"] > s0["rough_std_in_sector"]
                 and s1["spec_std_in_band"] > s0["spec_std_in_band"])
    lead = {True: "In the maps, the direction of each effect is the paper's, the size is not: ",
            False: "In the maps the effects do not even all point the paper's way: ",
            None: "In the maps: "}[agree]
    txt = ("**What the priors do here.** " + lead + "without "
           f"the roughness TV the roughness spread inside a sector grows {_pct(s2.get('rough_std_in_sector'), s0.get('rough_std_in_sector'))} "
           f"and the roughness MAE {_pct(g('mat_norough', 'mae_r'), g('base', 'mae_r'))}; without the specular "
           f"correlation the specular spread inside a band grows {_pct(s1.get('spec_std_in_band'), s0.get('spec_std_in_band'))} "
           f"and its correlation with the diffuse pattern moves {_f(s0.get('spec_diffuse_corr'), 3)} -> "
           f"{_f(s1.get('spec_diffuse_corr'), 3)}" + _noise_note(stats) + ". The image errors move by a few percent at most "
           f"(env. map {_pct(g('mat_nospec', 'relight'), g('base', 'relight'))} / "
           f"{_pct(g('mat_norough', 'relight'), g('base', 'relight'))}), nowhere near the paper's 2.7-3.6x. ")
    txt += ("Why: (1) *the materials are not converged*, with or without priors. Even the full run bakes "
            f"diffuse into specular (correlation {_f(s0.get('spec_diffuse_corr'), 2)}) and its specular MAE "
            f"({_f(g('base', 'mae_s'), 3)}) is dominated by a bias the priors cannot fix: the recovered specular "
            "albedo averages about half the true 0.30 (`texture_errors` rec_mean vs gt_mean), a specular-albedo / "
            "roughness trade that the collocated light leaves weakly constrained (earlier runs of the balanced and "
            "accurate presets, 500-750 iterations on a 40-view 256^2 blob, `bench/out/balanced_final2` and "
            "`bench/out/accurate`, show the same: specular MAE 0.17-0.18). "
            "(2) *The texture parameterization is itself a smoothness prior*: each map is a sum of 4 pyramid "
            "levels (`texture_levels`), so low frequencies are learnt from all texels they cover and "
            "single-texel noise is damped before any TV term acts. (3) *Weights*: ours are 0.01 / 0.001 on means "
            "over texels against a rendering loss that is a mean over all pixels of 4 views; the paper's are "
            "the same numbers on sums. With 256^2 texels against 4 x 128 x 96 pixels the ratio happens to be "
            "similar (1.3x), so by this count the weights are comparable; but the paper's figure came from "
            "full-length optimizations at full resolution, where the data term had had time to fit the noise the "
            "priors remove. "
            "(4) Our environment-map error is high for every run (")
    txt += (f"{_f(g('base', 'relight'))} against a Monte Carlo floor of {_f(g('base', 'floor'))}" if g("base", "floor")
            else "see the table") + "), most likely again the specular lobe (specular MAE " + _mae_s_range(M) + ")."
    w(txt)
    w("")
    return L


def _mae_s_range(M: dict) -> str:
    v = [m["mae_s"] for n, m in M.items()
         if m and m["mae_s"] is not None and "projective" not in n and m["capture"].startswith("blob")]
    return f"{min(v):.2f}-{max(v):.2f} over every blob run but the projective ones" if v else "not measured"


def _noise_note(stats: dict) -> str:
    """Whether each ablation's map statistic leaves the range of the full method's seeds."""
    seeds = [stats[n] for n in ("base", "base_seed1", "base_seed2") if stats.get(n)]
    if len(seeds) < 2:
        return ""
    out = []
    for run, key, what in (("mat_norough", "rough_std_in_sector", "roughness spread"),
                           ("mat_nospec", "spec_std_in_band", "specular spread"),
                           ("mat_nospec", "spec_diffuse_corr", "correlation")):
        v = (stats.get(run) or {}).get(key)
        vals = [st[key] for st in seeds if st.get(key) is not None]
        if v is None or not vals:
            continue
        lo, hi = min(vals), max(vals)
        out.append(f"{what} {'outside' if not lo <= v <= hi else 'inside'} the seeds' range "
                   f"{lo:.3f}-{hi:.3f}")
    return (" (" + "; ".join(out) + f", over {len(seeds)} seeds of the full method)") if out else ""


def _section_views(M: dict, plots: dict, spread) -> list[str]:
    g = lambda n, k: _get(M, n, k)  # noqa: E731
    L: list[str] = []
    w = L.append
    w("## 4. Number of input views (paper Fig. 6, `fig:ablation_n_input`)")
    w("")
    w("**Paper**: a novel view under environmental lighting, RMSE; input views uniformly around the object; "
      "no geometry numbers. *kitty*: " + ", ".join(f"{k} views {v:.4f}" for k, v in PAPER_VIEWS["kitty"].items())
      + "; *pig*: " + ", ".join(f"{k} views {v:.4f}" for k, v in PAPER_VIEWS["pig"].items()) + ".")
    w("")
    w("**Ours**: blob captures with 10 / 30 / 50 / 100 views (the same synthetic object; cameras on a sphere), the "
      "same initial mesh (the crude mesh made from the 50-view hull) and the base configuration, so 200 "
      "iterations of 4 views each in every run: with 100 views each photo is used 8 times, with 10 views 80 times.")
    w("")
    rows = []
    for nv, n in VIEW_RUNS.items():
        m = M.get(n)
        rows.append([str(nv), f"`{n}`"] + ([_f(m["acc"], 5), _f(m["comp"], 5), _f(m["rmse"]), _f(m["relight"]),
                                             _f(m["mae_d"]), _f(m["mae_s"]), _f(m["mae_r"])] if m else ["not run"] + [""] * 6)
                    + [f"{PAPER_VIEWS['kitty'][nv]:.4f}", f"{PAPER_VIEWS['pig'][nv]:.4f}"])
    w(_table(["views", "run", "final accuracy", "completeness", "novel RMSE (collocated)", "novel RMSE (env. map)",
              "diffuse MAE", "specular MAE", "roughness MAE", "paper kitty RMSE", "paper pig RMSE"], rows))
    w("")
    L += _img(plots, "views", "accuracy and image error against the number of views")
    accs = {nv: g(n, "acc") for nv, n in VIEW_RUNS.items()}
    rm = {nv: g(n, "rmse") for nv, n in VIEW_RUNS.items()}
    rl = {nv: g(n, "relight") for nv, n in VIEW_RUNS.items()}
    mono = lambda d: all(d[a] >= d[b] for a, b in ((10, 30), (30, 50), (50, 100)) if d[a] is not None and d[b] is not None)  # noqa: E731
    w("**Ordering.** Paper: the error falls monotonically with views, steeply from 10 to 30 (kitty 3.5x, pig "
      "1.6x), then flattens (50 -> 100: kitty 1.1x, pig 1.06x): \"with 50 or more input images, our renderings "
      "closely match the groundtruth\". Ours: geometry accuracy "
      + " / ".join(_f(accs[k], 5) for k in accs) + (" (monotone)" if mono(accs) else " (not monotone)")
      + ", collocated novel RMSE " + " / ".join(_f(rm[k]) for k in rm) + (" (monotone)" if mono(rm) else " (not monotone)")
      + ", environment-map RMSE " + " / ".join(_f(rl[k]) for k in rl) + (" (monotone)" if mono(rl) else " (not monotone)")
      + " for 10 / 30 / 50 / 100 views.")
    w("")
    if all(accs[k] is not None for k in accs) and all(rm[k] is not None for k in rm):
        env = (f" (env. map {_ratio(rl[10], rl[30])} / {_ratio(rl[10], rl[100])})" if rl[10] and rl[30] and rl[100]
               else "")
        w(f"**Shape of the curve: as in the paper.** Most of the gain is from 10 to 30 views (accuracy "
          f"{_ratio(accs[10], accs[30])} better, collocated RMSE {_ratio(rm[10], rm[30])}), then it flattens: "
          f"30 -> 100 views moves the accuracy {_pct(accs[100], accs[30])} and 50 -> 100 {_pct(accs[100], accs[50])} "
          + ("(within the seed spread)" if _same(accs[100], accs[30], spread) else
             "(beyond the seed spread)" if _same(accs[100], accs[30], spread) is False else "")
          + ", while the image errors keep creeping down "
          f"(collocated {_pct(rm[100], rm[50])}, env. map {_pct(rl[100], rl[50])} from 50 to 100; the paper: kitty "
          "-10%, pig -6%). Our geometry plateau starts at 30 views, the paper's renderings at 50.")
        w("")
        w(f"**Magnitudes: much flatter than the paper's.** From 10 to 30 / 100 views our collocated RMSE falls "
          f"{_ratio(rm[10], rm[30])} / {_ratio(rm[10], rm[100])}{env}; the paper's kitty 3.5x / 7.6x and pig "
          "1.6x / 2.2x. Reasons: (1) our image errors are dominated by the unconverged specular lobe (study 3), "
          "which more photos do not fix in 200 iterations, so the part that views can improve is a small share; "
          "(2) the iteration budget is fixed (800 view renders in every run): more views only spread the same "
          "work thinner, while the paper presumably ran each to convergence; (3) a smooth blob is easy to "
          "constrain with 10 views on a sphere, and the study holds the initial mesh fixed (the crude mesh from "
          "the 50-view hull), where a real 10-photo capture would also start from a worse hull. The paper's "
          "numbers are environment-lit renderings of a single novel view of kitty and pig; ours average 8 novel "
          "views of a blob, so only the shapes of the curves compare, not the values.")
    w("")
    return L
