"""The bad-input corpus through the workflow, as a user runs it (issue 20): one Snakemake run over
a folder of captures, some broken. Each broken capture fails at its check step, before any stage
runs, with its message on the terminal naming the file and no Python traceback; its results hold
no stage output; its files are unchanged; the good captures in the same run go on."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest
from badinput_cases import CASES, sphere_capture, tree_hashes

from recon.stages import STAGES

BY_ID = {c.id: c for c in CASES}
# a representative few (one per file the check reads; test_corpus.py has every case at the library level)
BROKEN = ["light_intensity_string", "camera_of_missing_photo", "mask_all_zero", "mesh_10x_too_large"]
STAGE_FOLDERS = tuple(s.folder for s in STAGES)  # every stage's results folder (recon.stages)


@pytest.fixture(scope="module")
def run(repo_root, tmp_path_factory):
    """One run of ``snakemake -k`` over the broken captures, a good one and one with AppleDouble
    files, up to the masks stage (linearize and masks of the good ones)."""
    root = tmp_path_factory.mktemp("badinput_workflow")
    caps, res = root / "captures", root / "results"
    for name in ["good", "apple_double_files", *BROKEN]:
        sphere_capture(caps / name)
        if name in BY_ID:
            BY_ID[name].edit(caps / name)
    before = {p.name: tree_hashes(p) for p in caps.iterdir()}
    targets = [f"{res}/{p.name}/masks/masks.json" for p in caps.iterdir()]
    env = {k: v for k, v in os.environ.items() if k != "RECON_TRACEBACK"}
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "snakemake", "--cores", "2", "-k", "--config", f"captures={caps}",
                        f"results={res}", "preset=draft", "--", *targets],
                       cwd=repo_root, capture_output=True, text=True, timeout=600, env=env)
    return {"caps": caps, "res": res, "before": before, "result": r, "seconds": time.perf_counter() - t0,
            "terminal": r.stdout + r.stderr}


def test_run_fails(run):
    assert run["result"].returncode == 1, run["terminal"][-3000:]


@pytest.mark.parametrize("name", BROKEN)
def test_broken_capture_stops_at_its_check(run, name):
    case, caps, res = BY_ID[name], run["caps"], run["res"]
    terminal = run["terminal"]
    # the message, naming the file, on the terminal and as the last line of the check's log
    line = next((ln for ln in terminal.splitlines() if ln.startswith("recon check: error:")
                 and str(caps / name) + "/" in ln), None) or ""
    assert str(caps / name / case.names) in terminal and line, terminal[-3000:]
    log = (res / name / "logs" / "check.log").read_text().strip().splitlines()
    assert "ERROR recon.stage: check failed:" in log[-1] and str(caps / name) in log[-1]
    # no stage ran for it: no stage folder at all, only the check's log
    assert [f for f in STAGE_FOLDERS if (res / name / f).exists()] == []
    assert sorted(p.name for p in (res / name / "logs").iterdir()) == ["check.log"]
    # never a byte of the capture changed
    assert tree_hashes(caps / name) == run["before"][name]


def test_no_traceback_on_the_terminal(run):
    assert "Traceback" not in run["terminal"]
    assert run["terminal"].count("recon check: error:") == len(BROKEN)


def test_good_captures_go_on(run):
    res = run["res"]
    for name in ("good", "apple_double_files"):
        check = json.loads((res / name / "check" / "check.json").read_text())
        masks = json.loads((res / name / "masks" / "masks.json").read_text())
        stems = sorted(masks.get("views", masks.get("masks", masks)))
        assert check["views"] == [f"{k:04d}" for k in range(8)]
        assert not any(s.startswith(".") for s in stems) and "._0000" not in json.dumps(masks), masks
        assert tree_hashes(run["caps"] / name) == run["before"][name]
    hidden = [w for w in json.loads((res / "apple_double_files" / "check" / "check.json").read_text())["warnings"]
              if "._0000.png" in w]
    assert hidden and "ignoring hidden file(s)" in hidden[0]
    assert np.all([(res / "good" / "linear" / f"{k:04d}.exr").is_file() for k in range(8)])

