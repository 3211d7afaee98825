"""Only a stage whose effective settings changed reruns: a preset switch that leaves a stage's
section equal reruns nothing of it (issue 21 item 6); an edit of a stage's section in
capture.yaml reruns that stage and what follows. (A moved captures folder still reruns
linearize: the photos' paths are its inputs, and Snakemake's input trigger is what notices a
removed photo.)"""

from __future__ import annotations

import re
import subprocess
import sys

import numpy as np

from recon.io.images import write_png


def _snakemake(repo_root, captures, results, target, *extra, dry=True, preset="draft"):
    cmd = [sys.executable, "-m", "snakemake", "--cores", "1", "--config", f"captures={captures}",
           f"results={results}", f"preset={preset}", *extra, "--", target]
    if dry:
        cmd.insert(3, "-n")
    r = subprocess.run(cmd, cwd=repo_root, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    text = r.stdout + r.stderr
    if not dry or "Nothing to be done" in text:
        return set()
    table = text[text.index("Job stats:"):]
    return {m.group(1) for m in re.finditer(r"^(\w+)\s+\d+$", table, re.M)} - {"total"}


def test_only_changed_settings_rerun(repo_root, tmp_path):
    caps = tmp_path / "captures"
    img = np.zeros((32, 40, 3))
    img[8:24, 10:30] = 0.6  # a lit object on a dark background
    for k in range(3):
        write_png(caps / "obj" / "images" / f"{k:04d}.png", np.roll(img, k, axis=1))
    res = tmp_path / "results"
    target = f"{res}/obj/masks/masks.json"
    assert _snakemake(repo_root, caps, res, target) == {"linearize", "masks"}
    _snakemake(repo_root, caps, res, target, dry=False)
    assert _snakemake(repo_root, caps, res, target) == set()
    # every preset has the same (empty) linearize and masks sections: nothing to do
    for preset in ("balanced", "accurate"):
        assert _snakemake(repo_root, caps, res, target, preset=preset) == set(), preset
    moved = caps
    # an edit of the masks section reruns masks only; of the linearize section, both
    (moved / "obj" / "capture.yaml").write_text("masks:\n  dilate_px: 1\n")
    assert _snakemake(repo_root, moved, res, target) == {"masks"}
    (moved / "obj" / "capture.yaml").write_text("linearize:\n  preview_max_size: 32\n")
    assert _snakemake(repo_root, moved, res, target) == {"linearize", "masks"}
