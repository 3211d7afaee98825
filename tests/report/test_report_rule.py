"""The Snakemake rule and its adapter: `snakemake <results>/<capture>/report/index.html`."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time



def test_report_rule(scene, tmp_path, repo_root):
    captures, results = tmp_path / "captures", tmp_path / "results"
    cap = captures / "cap"
    (cap / "images").mkdir(parents=True)
    for c in scene.cams.frames:
        (cap / "images" / f"{c.stem}.exr").touch()
    shutil.copytree(scene.capture_dir / "gt", cap / "gt")
    (cap / "capture.yaml").write_text("report:\n  spp: 4\n  max_views: 2\n  chamfer_samples: 5000\n"
                                      "  texture_samples: 5000\n  gt_views: 1\n")
    out = results / "cap"
    shutil.copytree(scene.results, out, ignore=shutil.ignore_patterns("report", "benchmarks"))
    (out / "linear" / "linear.json").write_text("{}")
    (out / "masks" / "masks.json").write_text("{}")
    # Every earlier stage's output is newer than the photos: only the report has to run.
    old, now = time.time() - 3600, time.time()
    for p in cap.rglob("*"):
        os.utime(p, (old, old))
    for p in out.rglob("*"):
        os.utime(p, (now, now))

    target = out / "report" / "index.html"
    proc = subprocess.run(
        [sys.executable, "-m", "snakemake", "--cores", "1", str(target), "--allowed-rules", "report",
         "--config", f"captures={captures}", f"results={results}", "preset=draft"],
        cwd=repo_root, capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    m = json.loads((out / "report" / "metrics.json").read_text())
    assert m["capture"] == "cap" and m["preset"] == "draft"
    assert m["settings"]["spp"] == 4 and len(m["per_view_rmse"]) == 2  # capture.yaml reached it
    assert m["metrics"]["chamfer"] < 1e-6  # gt/ found through the capture folder
    assert "report written" in (out / "logs" / "report.log").read_text()
    assert (out / "benchmarks" / "report.tsv").is_file()
