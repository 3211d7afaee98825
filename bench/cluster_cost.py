"""What a capture costs per stage, and how that grows with the number of views and the image size.

Makes synthetic captures (``python -m recon synth``: the blob, known cameras, linear EXR photos)
on two axes through one base capture, runs the whole pipeline over them locally (Snakemake,
``--cores 2``, the draft preset unless ``--preset``), and reads each stage's own
``benchmarks/<stage>.tsv`` (Snakemake's: wall seconds, peak resident memory, CPU seconds):

    .venv/bin/python bench/cluster_cost.py --out bench/out/cluster_cost
    .venv/bin/python bench/cluster_cost.py --out bench/out/cluster_cost --report-only

Writes ``<out>/cost.json``, ``<out>/cost.md`` (the table docs/cluster.md quotes) and
``docs/cluster_cost.png`` (``--plot``). The CPU seconds are what a cluster charges and what the
profile's runtimes are made from; wall seconds on a shared 2-core machine are only indicative.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

from recon.stages import SETTINGS_STAGES

REPO = Path(__file__).resolve().parents[1]
STAGES = SETTINGS_STAGES  # the stages that run a job of their own per capture (check aside)
BASE = {"views": 16, "width": 128}
VIEWS = (8, 16, 32)
WIDTHS = (64, 128, 256)


def say(msg: str) -> None:
    print(f"[cluster_cost {time.strftime('%H:%M:%S')}] {msg}", flush=True)  # noqa: T201 (progress of a CLI)


def captures_to_make() -> list[dict]:
    grid = [{"views": v, "width": BASE["width"]} for v in VIEWS]
    grid += [{"views": BASE["views"], "width": w} for w in WIDTHS if w != BASE["width"]]
    for g in grid:
        g["name"] = f"v{g['views']:03d}_w{g['width']:04d}"
    return grid


def make_captures(root: Path, grid: list[dict]) -> None:
    for g in grid:
        folder = root / g["name"]
        if (folder / "cameras.json").is_file():
            continue
        cmd = [sys.executable, "-m", "recon", "synth", str(folder), "--object", "blob", "--views",
               str(g["views"]), "--res", str(g["width"]), "--format", "exr", "--cameras",
               "--mesh-level", "3", "--texture-size", "128", "--seed", "0"]
        say(" ".join(cmd[2:]))
        subprocess.run(cmd, cwd=REPO, check=True, env=_env())


def _env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    env["PATH"] = str(Path(sys.executable).parent) + os.pathsep + env.get("PATH", "")
    return env


def read_benchmark(path: Path) -> dict:
    with open(path) as fh:
        row = next(csv.DictReader(fh, delimiter="\t"))
    return {"s": float(row["s"]), "max_rss_mb": float(row["max_rss"]), "cpu_s": float(row["cpu_time"])}


def collect(results: Path, grid: list[dict]) -> list[dict]:
    rows = []
    for g in grid:
        stages = {}
        for s in STAGES:
            tsv = results / g["name"] / "benchmarks" / f"{s}.tsv"
            if tsv.is_file():
                stages[s] = read_benchmark(tsv)
        rows.append({**g, "pixels": g["width"] * (g["width"] * 3 // 4), "stages": stages})
    return rows


def table(rows: list[dict]) -> str:
    head = ("| capture | views | image | " + " | ".join(STAGES) + " | total CPU s | peak MB |\n"
            "|---|---|---|" + "---|" * len(STAGES) + "---|---|")
    lines = [head]
    for r in rows:
        st = r["stages"]
        cells = [f"{st[s]['cpu_s']:.1f}" if s in st else "-" for s in STAGES]
        total = sum(v["cpu_s"] for v in st.values())
        peak = max((v["max_rss_mb"] for v in st.values()), default=0)
        lines.append(f"| {r['name']} | {r['views']} | {r['width']}x{r['width'] * 3 // 4} | "
                     + " | ".join(cells) + f" | {total:.1f} | {peak:.0f} |")
    mem = ["", "Peak resident memory (MB) per stage:", "",
           "| capture | " + " | ".join(STAGES) + " |", "|---|" + "---|" * len(STAGES)]
    for r in rows:
        st = r["stages"]
        mem.append(f"| {r['name']} | " + " | ".join(f"{st[s]['max_rss_mb']:.0f}" if s in st else "-"
                                                  for s in STAGES) + " |")
    return "\n".join(lines + mem) + "\n"


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    axes_def = ((axes[0], "views", "number of views", [r for r in rows if r["width"] == BASE["width"]]),
                (axes[1], "pixels", "pixels per photo", [r for r in rows if r["views"] == BASE["views"]]))
    for ax, key, label, sel in axes_def:
        sel = sorted(sel, key=lambda r: r[key])
        xs = [r[key] for r in sel]
        for s in STAGES:
            ys = [r["stages"].get(s, {}).get("cpu_s", float("nan")) for r in sel]
            ax.plot(xs, ys, marker="o", label=s)
        ax.plot(xs, [sum(v["cpu_s"] for v in r["stages"].values()) for r in sel], "k--", marker="s",
                label="all stages")
        ax.set_xscale("log", base=2)
        ax.set_yscale("log")
        ax.set_xlabel(label)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("CPU seconds (Snakemake benchmark)")
    axes[0].set_title(f"{BASE['width']} px wide photos")
    axes[1].set_title(f"{BASE['views']} views")
    handles, labels = axes[1].get_legend_handles_labels()
    fig.legend(handles, labels, fontsize=8, loc="center right")
    fig.suptitle("Cost of a capture per stage (draft preset, 2-core machine)")
    fig.tight_layout(rect=(0, 0, 0.86, 1))
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="bench/out/cluster_cost")
    ap.add_argument("--preset", default="draft")
    ap.add_argument("--report-only", action="store_true")
    ap.add_argument("--plot", default=str(REPO / "docs" / "cluster_cost.png"))
    args = ap.parse_args(argv)
    out = Path(args.out).resolve()
    grid = captures_to_make()
    results = out / "results"
    meta = {}
    if not args.report_only:
        make_captures(out / "captures", grid)
        t0 = time.time()
        cmd = [sys.executable, "-m", "snakemake", "--cores", "2", "all", "--config",
               f"captures={out / 'captures'}", f"results={results}", f"preset={args.preset}"]
        say(" ".join(cmd[2:]))
        with open(out / "snakemake.log", "w") as fh:
            subprocess.run(cmd, cwd=REPO, env=_env(), stdout=fh, stderr=subprocess.STDOUT, check=True)
        meta = {"seconds": time.time() - t0, "command": " ".join(cmd[2:])}
    rows = collect(results, grid)
    info = {"preset": args.preset, "machine": f"{platform.node()} {os.cpu_count()} CPUs", **meta,
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "rows": rows}
    (out / "cost.json").write_text(json.dumps(info, indent=1))
    (out / "cost.md").write_text(table(rows))
    plot(rows, Path(args.plot))
    say(f"wrote {out / 'cost.md'}, {args.plot}\n{table(rows)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
