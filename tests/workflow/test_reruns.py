"""What reruns after a change (issue 21 item 6): only the stages whose effective settings or
capture files changed, and what follows them.

Rules track each stage's effective settings and the names of its capture files as params; the
workflow profile (profiles/default) leaves out Snakemake's "input" trigger, which compares the
inputs' full paths. So a preset switch that leaves a stage's section equal reruns nothing of
it, moving the captures folder reruns nothing, and an edit of a stage's section in capture.yaml
reruns that stage and what follows.

The first test runs linearize and masks for real on tiny photos; the second marks a whole DAG
done with ``snakemake --touch`` (Snakemake records each job's params and inputs as after a real
run) and asks dry runs what would run, for a capture with SfM and one with its own cameras.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from recon.config import STAGES
from recon.io.images import write_png

# A real key of each stage's settings dataclass with a value that differs from every preset.
SECTION_EDITS = {
    "linearize": "preview_max_size: 32",
    "masks": "dilate_px: 1",
    "poses": "features: {max_image_size: 800}",
    "init_mesh": "resolution: 64",
    "uv": "padding: 3",
    "optimize": "holdout_every: 5",
    "export": "meters_per_unit: 0.5",
    "report": "max_views: 2",
}
# The stages after each stage in the DAG of a capture without cameras.json (SfM): the chain.
CHAIN = list(STAGES)


def _snakemake(repo_root, captures, results, target, *extra, dry=True, preset="draft"):
    """Run snakemake; with ``dry``, the set of rules it would run (``all`` left out)."""
    cmd = [sys.executable, "-m", "snakemake", "--cores", "1", "--config", f"captures={captures}",
           f"results={results}", f"preset={preset}", *extra, "--", target]
    if dry:
        cmd.insert(3, "-n")
    r = subprocess.run(cmd, cwd=repo_root, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    text = r.stdout + r.stderr
    if not dry:
        return set()
    if "Nothing to be done" in text:
        return set()
    table = text[text.index("Job stats:"):]
    return {m.group(1) for m in re.finditer(r"^(\w+)\s+\d+$", table, re.M)} - {"total", "all"}


def _write_photos(folder: Path, n: int = 3) -> None:
    img = np.zeros((32, 40, 3))
    img[8:24, 10:30] = 0.6  # a lit object on a dark background
    for k in range(n):
        write_png(folder / f"{k:04d}.png", np.roll(img, k, axis=1))


def _age(path: Path, seconds: float = 3600.0) -> None:
    """Date ``path`` back, so that only params (not file dates) can make a stage rerun."""
    t = path.stat().st_mtime - seconds
    os.utime(path, (t, t))


def test_real_run_reruns_only_what_changed(repo_root, tmp_path):
    caps = tmp_path / "captures"
    _write_photos(caps / "obj" / "images")
    for p in (caps / "obj" / "images").iterdir():
        _age(p)
    res = tmp_path / "results"
    target = f"{res}/obj/masks/masks.json"
    assert _snakemake(repo_root, caps, res, target) == {"check", "linearize", "masks"}
    _snakemake(repo_root, caps, res, target, dry=False)
    assert _snakemake(repo_root, caps, res, target) == set()
    # every preset has the same (empty) linearize and masks sections: nothing to do
    for preset in ("balanced", "accurate"):
        assert _snakemake(repo_root, caps, res, target, preset=preset) == set(), preset
    # the captures folder moved (dates kept, as mv keeps them): nothing to do
    moved = tmp_path / "elsewhere" / "captures"
    moved.parent.mkdir()
    caps.rename(moved)
    assert _snakemake(repo_root, moved, res, target) == set()
    # a photo more, older than the results: its name is tracked, so linearize reruns
    write_png(moved / "obj" / "images" / "0003.png", np.zeros((32, 40, 3)))
    _age(moved / "obj" / "images" / "0003.png")  # (the check step tracks the photos too)
    assert _snakemake(repo_root, moved, res, target) == {"check", "linearize", "masks"}
    (moved / "obj" / "images" / "0003.png").unlink()
    # a photo less
    (moved / "obj" / "images" / "0002.png").unlink()
    assert _snakemake(repo_root, moved, res, target) == {"check", "linearize", "masks"}
    _write_photos(moved / "obj" / "images")
    for p in (moved / "obj" / "images").iterdir():
        _age(p)
    assert _snakemake(repo_root, moved, res, target) == set()
    # an edit of the masks section reruns masks only; of the linearize section, both
    (moved / "obj" / "capture.yaml").write_text("masks:\n  dilate_px: 1\n")
    assert _snakemake(repo_root, moved, res, target) == {"masks"}
    (moved / "obj" / "capture.yaml").write_text("linearize:\n  preview_max_size: 32\n")
    assert _snakemake(repo_root, moved, res, target) == {"linearize", "masks"}
    # the rerun reads the photos where they are now
    _snakemake(repo_root, moved, res, target, dry=False)
    assert (res / "obj" / "linear" / "0002.exr").is_file()
    assert _snakemake(repo_root, moved, res, target) == set()
    # a given mask, dated back: its name is tracked, so masks reruns
    write_png(moved / "obj" / "masks" / "0000.png", np.ones((32, 40)))
    _age(moved / "obj" / "masks" / "0000.png")
    assert _snakemake(repo_root, moved, res, target) == {"masks"}


def _touch_all(repo_root, caps, res, preset="draft"):
    """Create every output of the DAG and mark every job done as after a real run."""
    r = subprocess.run(
        [sys.executable, "-m", "snakemake", "--cores", "1", "--summary", "--config", f"captures={caps}",
         f"results={res}", f"preset={preset}", "--", "all"],
        cwd=repo_root, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    outputs = [line.split("\t")[0] for line in r.stdout.splitlines() if line.startswith(str(res))]
    assert len(outputs) >= 9, r.stdout
    for f in outputs:
        Path(f).parent.mkdir(parents=True, exist_ok=True)
        Path(f).touch()
    _snakemake(repo_root, caps, res, "all", "--touch", "--forceall", dry=False, preset=preset)
    assert _snakemake(repo_root, caps, res, "all", preset=preset) == set()


@pytest.fixture(scope="module")
def _finished_dag(repo_root, tmp_path_factory):
    """A capture without cameras (the whole chain, COLMAP included) marked done with draft:
    made once per module (three Snakemake runs); the tests below only ask dry runs."""
    root = tmp_path_factory.mktemp("finished")
    caps = root / "captures"
    _write_photos(caps / "obj" / "images")
    for p in (caps / "obj" / "images").iterdir():
        _age(p)
    res = root / "results"
    _touch_all(repo_root, caps, res)
    return caps, res


def _files(folder: Path) -> dict:
    """Relative path -> (bytes, (atime_ns, mtime_ns)) of every file under ``folder``."""
    return {p.relative_to(folder): (p.read_bytes(), (p.stat().st_atime_ns, p.stat().st_mtime_ns))
            for p in folder.rglob("*") if p.is_file()}


@pytest.fixture
def finished(_finished_dag):
    """The module's finished DAG, its captures folder put back after each test as it was (files,
    contents and dates): the tests edit capture files and ask dry runs, which change nothing in
    the results or Snakemake's records."""
    caps, res = _finished_dag
    before, dirs = _files(caps), {p for p in caps.rglob("*") if p.is_dir()}
    yield caps, res
    assert caps.is_dir(), f"a test left {caps} moved away"
    for rel in set(_files(caps)) - set(before):
        (caps / rel).unlink()
    for d in sorted({p for p in caps.rglob("*") if p.is_dir()} - dirs, reverse=True):  # deepest first
        d.rmdir()
    now = _files(caps)
    for rel, (data, times) in before.items():
        if now.get(rel) != (data, times):
            (caps / rel).parent.mkdir(parents=True, exist_ok=True)
            (caps / rel).write_bytes(data)
            os.utime(caps / rel, ns=times)


def test_preset_switch_reruns_only_stages_whose_settings_differ(repo_root, finished):
    caps, res = finished
    # the presets differ in their optimize sections alone (and the report names the preset)
    for preset in ("balanced", "accurate"):
        assert _snakemake(repo_root, caps, res, "all", preset=preset) == {"optimize", "export", "report"}
    # a capture.yaml that picks a preset counts the same as the config's preset
    (caps / "obj" / "capture.yaml").write_text("preset: balanced\n")
    assert _snakemake(repo_root, caps, res, "all") == {"optimize", "export", "report"}
    # ... and one that restates draft's own optimize values changes nothing but the name
    (caps / "obj" / "capture.yaml").write_text("preset: balanced\noptimize:\n" + "".join(
        f"  {k}: {v}\n" for k, v in _draft_optimize_differences().items()))
    assert _snakemake(repo_root, caps, res, "all") == {"report"}


def _draft_optimize_differences() -> dict:
    """The keys of the optimize section in which balanced differs from draft, with draft's values."""
    import json

    from recon.config import load_preset

    draft, balanced = load_preset("draft")["optimize"], load_preset("balanced")["optimize"]
    assert set(draft) == set(balanced)
    # JSON is valid YAML (flow style), so lists of mappings (stages) go on one line
    return {k: json.dumps(draft[k]) for k in draft if draft[k] != balanced[k]}


def test_moved_captures_folder_reruns_nothing(repo_root, finished, tmp_path):
    caps, res = finished
    moved = tmp_path / "moved" / "all_my_captures"
    moved.parent.mkdir()
    caps.rename(moved)
    try:
        assert _snakemake(repo_root, moved, res, "all") == set()
    finally:
        moved.rename(caps)  # back for the module's other tests


def test_section_edit_reruns_that_stage_and_what_follows(repo_root, finished):
    caps, res = finished
    for stage in STAGES:
        (caps / "obj" / "capture.yaml").write_text(f"{stage}:\n  {SECTION_EDITS[stage]}\n")
        assert _snakemake(repo_root, caps, res, "all") == set(CHAIN[CHAIN.index(stage):]), stage


def test_given_files_rerun_the_stages_that_read_them(repo_root, finished):
    """Given cameras, a given initial mesh or ground truth, dated before the results, still
    rerun the stages that read them: their names are tracked (the input trigger that compared
    paths is off)."""
    caps, res = finished
    cams = caps / "obj" / "cameras.json"
    cams.write_text("{}")
    _age(cams)
    # poses passes them through; init_mesh carves with them, and so on
    assert _snakemake(repo_root, caps, res, "all") == set(CHAIN[CHAIN.index("poses"):])
    cams.unlink()
    mesh = caps / "obj" / "init_mesh.ply"
    mesh.write_text("ply\n")
    _age(mesh)
    # uv reads it in place of init_mesh's mesh (init_mesh leaves the DAG)
    assert _snakemake(repo_root, caps, res, "all") == set(CHAIN[CHAIN.index("uv"):])
    mesh.unlink()
    # ground truth, read by the report alone
    gt = caps / "obj" / "gt" / "mesh.ply"
    gt.parent.mkdir()
    gt.write_text("ply\n")
    _age(gt)
    assert _snakemake(repo_root, caps, res, "all") == {"report"}
