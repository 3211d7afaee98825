"""Benchmark suite: speed against accuracy of the presets on three synthetic objects.

One command makes the captures (cached), runs ``bench/optimize.py`` for every object x preset
(each in its own process, so peak memory is per run; runs whose ``bench.json`` exists are
skipped, so the suite resumes where it stopped), and writes the report:

    .venv/bin/python bench/suite.py --out bench/out/suite
    .venv/bin/python bench/suite.py --out bench/out/suite --report-only     (docs from bench.json files)
    .venv/bin/python bench/suite.py --out bench/out/suite --quick           (tiny captures, draft only)

Objects (``python -m recon synth``, 40 views, 512 x 384 (every preset downsamples to its own
resolution: draft 128, balanced 256, accurate 512 px), EXR, known cameras and masks, sensor
noise on; the initial mesh is the visual hull that ``bench/optimize.py`` makes):

- ``smooth-diffuse``: ``--object smooth --specular 0``, smooth genus 0, purely diffuse;
- ``blob-glossy``: ``--object blob``, bumps and grooves, spatially varying specular/roughness;
- ``torus``: ``--object torus``, genus 1 with detail, spatially varying materials.

Writes ``docs/benchmarks.md`` (the table, the machine, the date, the command, an automatic
Pareto check, and the hand-written reading kept between the ``reading`` markers when the file
is regenerated) and ``docs/pareto.png``. ``--quick`` writes its report under the out folder
instead (``--docs`` chooses the folder). Layout of the out folder::

    captures/<object>/              the synthetic capture (+ <object>_init/ hull, _bench/ cache)
    runs/<object>/<preset>/         bench.json, log.txt, suite_run.json, optimize/
    suite.json                      the command, dates and seconds of the last invocations
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PY = sys.executable

OBJECTS = {
    "smooth-diffuse": ["--object", "smooth", "--specular", "0"],
    "blob-glossy": ["--object", "blob"],
    "torus": ["--object", "torus"],
}
CAPTURE = ["--views", "40", "--res", "512", "--height", "384", "--format", "exr", "--cameras", "--masks"]
PRESETS = ["draft", "balanced", "accurate"]

# --quick: tiny captures and a short optimization, to check the whole path in a few minutes
QUICK_CAPTURE = ["--views", "16", "--res", "128", "--height", "96", "--format", "exr", "--cameras",
                 "--masks", "--spp", "16", "--mesh-level", "5", "--texture-size", "256"]
QUICK_SET = ["stages=[{edge_length: 0.06, texture_size: 128, iterations: 15}]"]
QUICK_BENCH = ["--novel", "3", "--relight-spp", "16"]

# OpenMP's default (active) waiting makes torch's small parallel ops 20-30x slower when the
# cores are shared with other jobs (measured here: the bilateral prior on a 512^2 map took
# 2.4 s per call with 2 spinning threads against 0.12 s with passive waiting, load 4 on 2
# cores). `import recon` sets the same default (recon/__init__.py); the runs also get it in
# their environment, so the policy holds whatever the import order, unless the caller set one.
RUN_ENV = {"OMP_WAIT_POLICY": "PASSIVE"}

READING_START = "<!-- reading:start (hand-written; bench/suite.py keeps this part) -->"
READING_END = "<!-- reading:end -->"


def say(msg: str) -> None:
    print(f"[suite {time.strftime('%H:%M:%S')}] {msg}", flush=True)  # noqa: T201 (progress of a CLI)


# ---- captures and runs ----
def make_capture(folder: Path, args: list[str]) -> float:
    """Synthesize the capture unless it is complete; returns the seconds spent."""
    if (folder / "cameras.json").is_file() and (folder / "gt" / "mesh.obj").is_file():
        return 0.0
    say(f"making capture {folder.name}: python -m recon synth {folder} {' '.join(args)}")
    t0 = time.perf_counter()
    subprocess.run([PY, "-m", "recon", "synth", str(folder), *args], check=True, cwd=REPO)
    return time.perf_counter() - t0


def run_one(capture: Path, preset: str, run_dir: Path, extra: list[str]) -> tuple[bool, float]:
    """``bench/optimize.py`` in a subprocess, output to ``run_dir/log.txt``; (ok, seconds)."""
    if run_dir.exists():  # a stale partial run: start clean so the timings are whole
        shutil.rmtree(run_dir)
    run_dir.mkdir(parents=True)
    cmd = [PY, str(REPO / "bench" / "optimize.py"), str(capture), "--preset", preset,
           "--out", str(run_dir), *extra]
    env = {**RUN_ENV, **os.environ}
    t0 = time.perf_counter()
    with open(run_dir / "log.txt", "w") as log:
        rc = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=REPO, env=env).returncode
    seconds = time.perf_counter() - t0
    (run_dir / "suite_run.json").write_text(json.dumps(
        {"command": shlex.join(cmd), "seconds": seconds, "returncode": rc,
         "env": {k: env[k] for k in RUN_ENV},
         "finished": dt.datetime.now().isoformat(timespec="seconds")}, indent=1))
    return rc == 0 and (run_dir / "bench.json").is_file(), seconds


# ---- the report ----
def load_results(out: Path, objects: list[str], presets: list[str]) -> dict:
    res = {}
    for o in objects:
        for p in presets:
            f = out / "runs" / o / p / "bench.json"
            if f.is_file():
                res[(o, p)] = json.loads(f.read_text())
            elif (out / "runs" / o / p / "suite_run.json").is_file():
                res[(o, p)] = None  # ran and failed
    return res


def _fmt(x, spec=".4f") -> str:
    return "—" if x is None else format(x, spec)


def material_text(r: dict) -> str:
    m = r.get("material_model")
    if not m:
        s = (r.get("settings") or {}).get("specular_channels", 1)
        return f"fixed: textured/{'rgb' if s == 3 else 'mono'}, textured"
    spec = m.get("specular", "?")
    if spec != "none":
        spec += "/" + m.get("specular_color", "?")
    selected = (r.get("settings") or {}).get("select_material")
    return f"{'' if selected else 'fixed: '}{spec}, {m.get('roughness', '?')}"


def results_table(res: dict, objects: list[str], presets: list[str]) -> str:
    head = ("| object | preset | wall s | CPU s | load | selection s | render / loss / backward / step / geometry % | peak MB | accuracy | "
            "completeness | novel-view RMSE | relight RMSE | material model (specular, roughness) "
            "| texture MAE diffuse / specular / roughness |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    n_cols = head.count("|") - 1
    for o in objects:
        for p in presets:
            if (o, p) not in res:
                continue
            r = res[(o, p)]
            if r is None:
                lines.append(f"| {o} | {p} | failed (see runs/{o}/{p}/log.txt) |" + " |" * (n_cols - 3))
                continue
            ph = r["phase_fraction"]
            tex = r["texture_errors"]
            lines.append(
                f"| {o} | {p} | {r['wall_seconds']:.0f} | {_fmt(r.get('cpu_seconds'), '.0f')} | "
                f"{_fmt((r.get('load_average') or {}).get('mean'), '.1f')} | "
                f"{_fmt(r['phase_seconds'].get('material'), '.0f')} | "
                f"{' / '.join(f'{100 * ph[k]:.0f}' for k in ('render', 'loss', 'backward', 'step', 'geometry'))} | "
                f"{_fmt(r.get('peak_rss_mb'), '.0f')} | {r['final_accuracy']['accuracy']:.5f} | "
                f"{r['final_accuracy']['completeness']:.5f} | {r['novel_view_rmse']:.4f} | "
                f"{_fmt(r.get('relight_rmse'))} | {material_text(r)} | "
                f"{tex['diffuse']['mae']:.3f} / {tex['specular']['mae']:.3f} / {tex['roughness']['mae']:.3f} |")
    return "\n".join(lines)


def captures_table(res: dict, out: Path, objects: list[str], capture_args: dict) -> str:
    lines = ["| object | synth arguments | visual hull accuracy / completeness | relight noise floor |",
             "|---|---|---|---|"]
    for o in objects:
        rs = [r for (oo, _), r in res.items() if oo == o and r]
        if not rs:
            continue
        r = rs[0]
        floor = r.get("relight_noise_floor")
        spp = r.get("relight_spp")
        lines.append(f"| {o} | `{' '.join(capture_args[o])}` | {r['init_accuracy']['accuracy']:.5f} / "
                     f"{r['init_accuracy']['completeness']:.5f} | "
                     f"{_fmt(floor)}{f' ({spp} spp)' if spp else ''} |")
    return "\n".join(lines)


def pareto_check(res: dict, objects: list[str], presets: list[str]) -> str:
    """Per object: is every slower preset more accurate (accuracy, completeness, relight)?"""
    out = []
    for o in objects:
        rs = [(p, res.get((o, p))) for p in presets if res.get((o, p))]
        if len(rs) < 2:
            continue
        walls = [r["wall_seconds"] for _, r in rs]
        order = " -> ".join(f"{p} ({w:.0f} s)" for (p, _), w in zip(rs, walls, strict=True))
        slower = all(b > a for a, b in zip(walls, walls[1:], strict=False))
        line = [f"- **{o}**: {order}" + ("." if slower else " (NOT slower in this order: the load varied).")]
        for key, name in (("accuracy", "accuracy"), ("completeness", "completeness"),
                          ("relight_rmse", "relight RMSE"), ("novel_view_rmse", "novel-view RMSE")):
            vals = [(r["final_accuracy"][key] if key in ("accuracy", "completeness") else r.get(key))
                    for _, r in rs]
            if any(v is None for v in vals):
                continue
            bad = [f"{rs[i][0]} -> {rs[i + 1][0]} ({vals[i]:.5g} -> {vals[i + 1]:.5g})"
                   for i in range(len(vals) - 1) if vals[i + 1] >= vals[i]]
            seq = " -> ".join(f"{v:.5g}" for v in vals)
            line.append(f"{name} {seq}: " + ("improves with every slower preset." if not bad
                                              else "NOT monotone: " + "; ".join(bad) + "."))
        out.append(" ".join(line))
    return "\n".join(out) if out else "(fewer than two finished presets per object)"


def pareto_plot(res: dict, objects: list[str], presets: list[str], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.4))
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ci, o in enumerate(objects):
        rs = [(p, res[(o, p)]) for p in presets if res.get((o, p))]
        if not rs:
            continue
        c = colors[ci % len(colors)]
        t = [r["wall_seconds"] for _, r in rs]
        for ax, ys in ((axes[0], [r["final_accuracy"]["accuracy"] for _, r in rs]),
                       (axes[1], [r.get("relight_rmse") for _, r in rs])):
            pts = [(x, y, p) for x, y, (p, _) in zip(t, ys, rs, strict=True) if y is not None]
            if not pts:
                continue
            ax.plot([x for x, _, _ in pts], [y for _, y, _ in pts], "o-", color=c, label=o)
            for x, y, p in pts:
                ax.annotate(p, (x, y), textcoords="offset points", xytext=(5, 4), fontsize=8, color=c)
        floor = rs[0][1].get("relight_noise_floor")
        if floor:
            axes[1].axhline(floor, color=c, ls=":", lw=1)
    axes[0].set(xscale="log", yscale="log", xlabel="wall time of the optimize stage (s)",
                ylabel="accuracy (mean distance, unit bbox)", title="geometry")
    axes[1].set(xscale="log", yscale="log", xlabel="wall time of the optimize stage (s)",
                ylabel="relighting RMSE (sRGB)", title="relighting (dotted: noise floor)")
    from matplotlib.ticker import FormatStrFormatter, LogLocator, NullFormatter

    for ax in axes:
        ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(FormatStrFormatter("%g"))
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def machine_text() -> str:
    gpu = "no GPU"
    try:
        import torch

        if torch.cuda.is_available():
            gpu = f"GPU {torch.cuda.get_device_name(0)}"
    except Exception:  # noqa: BLE001 (a report line, never fatal)
        pass
    return f"{os.cpu_count()} CPU cores ({platform.processor() or platform.machine()}), {gpu}, " \
           f"Python {platform.python_version()}, Mitsuba variant llvm_ad_rgb (CPU)"


def old_reading(path: Path) -> str:
    if path.is_file():
        text = path.read_text()
        if READING_START in text and READING_END in text:
            return text.split(READING_START, 1)[1].split(READING_END, 1)[0].strip("\n")
    return "(No reading written yet: run the suite, then describe the results here.)"


def write_report(out: Path, docs: Path, objects: list[str], presets: list[str], capture_args: dict,
                 meta: dict) -> None:
    res = load_results(out, objects, presets)
    md = docs / "benchmarks.md"
    reading = old_reading(md)
    pareto_plot(res, objects, presets, docs / "pareto.png")
    done = [r for r in res.values() if r]
    spp = sorted({r.get("relight_spp") for r in done if r.get("relight_spp")})
    n_novel = ", ".join(map(str, sorted({len(r["novel_view_rmse_per_view"]) for r in done}))) or "—"
    dates = sorted(dt.datetime.fromtimestamp((out / "runs" / o / p / "bench.json").stat().st_mtime)
                   for (o, p), r in res.items() if r)
    date = dates[-1].strftime("%Y-%m-%d") if dates else "—"
    # what the report's runs cost: their processes (optimize + metrics) plus making the captures
    run_seconds = [json.loads(f.read_text())["seconds"] for (o, p), r in res.items() if r
                   for f in [out / "runs" / o / p / "suite_run.json"] if f.is_file()]
    total = (meta.get("capture_seconds", 0.0) + sum(run_seconds)) if run_seconds else None
    omp = ", ".join(sorted({(r.get("threads") or {}).get("OMP_WAIT_POLICY") or "unset" for r in done})) or "—"
    versions = sorted({(r.get("code_version") or {}).get("commit") or "?" for r in done})
    trees = sorted({(r.get("code_version") or {}).get("uncommitted_sha1") or "?" for r in done})
    dirty = sorted({f for r in done for f in (r.get("code_version") or {}).get("uncommitted", [])
                    if f[3:].startswith(("recon/", "config/"))})
    text = f"""# Benchmarks: speed against accuracy of the presets

Generated by `bench/suite.py` from the `bench.json` files of its runs (each run is
`bench/optimize.py`, i.e. the optimize stage from the visual hull, with known cameras and masks).
Regenerate the tables and the figure from existing runs with `--report-only`; the reading at
the end is hand-written and kept.

- Command: `{meta.get("command", "—")}`
- Machine: {meta.get("machine", machine_text())}; other jobs shared the machine during the
  runs, so wall times are upper bounds of an idle machine's.
- Code: commit {", ".join(versions) or "—"}{"; uncommitted changes in the working tree when runs started: "
  + ", ".join(f"`{f[3:]}`" for f in dirty) + f" (fingerprints of the uncommitted state: {', '.join(trees)})"
  if dirty else " (clean recon/ and config/)"}.
- Date of the newest run: {date}. Suite time for these results (making the captures + the
  {len(run_seconds)} benchmark processes, each optimize + metrics): {f"{total / 60:.1f} min" if total else "—"}.

## Captures

{captures_table(res, out, objects, capture_args)}

Each made by `python -m recon synth <folder> <arguments>` (sensor noise on, the default; other
settings at their defaults). The initial mesh of every run is the visual hull of the masks
(`recon.init_mesh`).

## Results

{results_table(res, objects, presets)}

Columns:
- **wall s**: the optimize stage (`optimize_capture`), not the metrics, run with
  `OMP_WAIT_POLICY={omp}` (see the reading); **CPU s**: its CPU time
  (user + system, all threads); **load**: the mean 1-minute load average of the machine while
  it ran (above the core count = the run shared the cores with other jobs); **selection s**:
  time of the held-out material-model selection and plateau tests (`phase_seconds.material`,
  inside the wall time, outside the loop shares); **render / loss /
  backward / step / geometry %**: shares of the optimization loop's time (`phase_fraction`;
  geometry = remeshing, UV atlas, surface checks; the paper reports 55-70 % for geometry).
- **peak MB**: peak resident memory of the benchmark process (`ru_maxrss`, optimize + metrics).
- **accuracy / completeness**: DESIGN section 5, mean distance of 100,000 area-uniform samples
  reconstruction -> ground truth / ground truth -> reconstruction; `recon.metrics.chamfer`
  divides by the longest side of the ground truth's bounding box, so these are already on the
  unit-bounding-box scale (the bench does not rescale).
- **novel-view RMSE**: sRGB RMSE over the union of the masks, {n_novel} views between the
  capture's (other elevations), collocated light, 32 spp.
- **relight RMSE**: the same {n_novel} views under the procedural studio environment map of
  `recon.render.envmap` (sky gradient + two softboxes), Mitsuba `path` integrator with the
  `recon_svbrdf` BSDF, {", ".join(map(str, spp)) or "—"} spp, ground truth and reconstruction
  rendered with the same random numbers. The noise floor (Captures table) is the ground truth
  against itself with independent seeds: an upper bound of the noise in the metric.
- **material model**: what the optimizer chose (held-out selection) where it reports
  `material_model`; "fixed" where the run had no selection (the preset's model).
- **texture MAE**: mean |reconstructed - true| of each map over 20,000 area-uniform points of
  the true surface (the reconstruction looked up at the closest point).

![wall time against accuracy and relighting RMSE](pareto.png)

## Pareto check (automatic)

Presets in the order given (meant from fastest to slowest) with their wall times; each metric
should fall with every slower preset.

{pareto_check(res, objects, presets)}

## Reading

{READING_START}
{reading}
{READING_END}
"""
    docs.mkdir(parents=True, exist_ok=True)
    md.write_text(text)
    say(f"wrote {md} and {docs / 'pareto.png'} ({len(done)} finished runs)")


# ---- main ----
def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    p.add_argument("--out", type=Path, default=REPO / "bench" / "out" / "suite")
    p.add_argument("--objects", nargs="+", choices=list(OBJECTS), default=list(OBJECTS))
    p.add_argument("--presets", nargs="+", default=None, help=f"default: {' '.join(PRESETS)} (quick: draft)")
    p.add_argument("--quick", action="store_true",
                   help="tiny captures (16 views, 128 x 96), 15 iterations, draft only, report under OUT/quick")
    p.add_argument("--report-only", action="store_true", help="only regenerate the report from bench.json files")
    p.add_argument("--captures-only", action="store_true", help="only make the (missing) captures")
    p.add_argument("--docs", type=Path, help="report folder (default: docs/, or OUT/quick with --quick)")
    args = p.parse_args(argv)

    out = args.out.resolve() / "quick" if args.quick else args.out.resolve()
    docs = (args.docs or (out if args.quick else REPO / "docs")).resolve()
    presets = args.presets or (["draft"] if args.quick else PRESETS)
    capture_args = {o: [*OBJECTS[o], *(QUICK_CAPTURE if args.quick else CAPTURE)] for o in args.objects}
    extra = [*(a for kv in QUICK_SET for a in ("--set", kv)), *QUICK_BENCH] if args.quick else []
    meta_path = out / "suite.json"
    meta = json.loads(meta_path.read_text()) if meta_path.is_file() else {}

    if not args.report_only:
        t_start = time.perf_counter()
        spent = 0.0
        capture_seconds = float(meta.get("capture_seconds", 0.0))
        for o in args.objects:
            sec = make_capture(out / "captures" / o, capture_args[o])
            spent += sec
            capture_seconds += sec
        jobs = [] if args.captures_only else [(o, pr) for pr in presets for o in args.objects]
        for k, (o, pr) in enumerate(jobs, 1):
            run_dir = out / "runs" / o / pr
            if (run_dir / "bench.json").is_file():
                say(f"[{k}/{len(jobs)}] {o} / {pr}: done before, skipped")
                continue
            say(f"[{k}/{len(jobs)}] {o} / {pr}: running (log: {run_dir / 'log.txt'})")
            ok, sec = run_one(out / "captures" / o, pr, run_dir, extra)
            spent += sec
            if ok:
                r = json.loads((run_dir / "bench.json").read_text())
                say(f"[{k}/{len(jobs)}] {o} / {pr}: {sec:.0f} s (optimize {r['wall_seconds']:.0f} s), "
                    f"accuracy {r['final_accuracy']['accuracy']:.5f}, relight {_fmt(r.get('relight_rmse'))}")
            else:
                say(f"[{k}/{len(jobs)}] {o} / {pr}: FAILED after {sec:.0f} s, see {run_dir / 'log.txt'}")
        argv_used = sys.argv[1:] if argv is None else list(argv)
        meta = {
            "command": shlex.join(["python", "bench/suite.py", *argv_used]),
            "machine": machine_text(),
            "finished": dt.datetime.now().isoformat(timespec="seconds"),
            "capture_seconds": capture_seconds,
            "invocations": meta.get("invocations", []) + [
                {"seconds": time.perf_counter() - t_start, "work_seconds": spent}],
        }
        meta["total_seconds"] = sum(i["work_seconds"] for i in meta["invocations"])
        out.mkdir(parents=True, exist_ok=True)
        meta_path.write_text(json.dumps(meta, indent=1))
    if not args.captures_only:
        write_report(out, docs, args.objects, presets, capture_args, meta)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
