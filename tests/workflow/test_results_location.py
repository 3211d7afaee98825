"""A results folder that is, contains, or lies inside the captures folder is refused before
anything runs, naming both paths, and nothing is written (issue 21 item 1)."""

from __future__ import annotations

import hashlib
import subprocess
import sys

import numpy as np
import pytest

from recon.config import ConfigError, check_results_location
from recon.io.images import write_png


def _tree(root):
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("where", ["is", "inside_capture", "inside_root", "contains"])
def test_overlapping_results_are_refused_before_anything_runs(repo_root, tmp_path, where):
    caps = tmp_path / "captures"
    write_png(caps / "obj" / "images" / "0000.png", np.full((8, 8, 3), 0.5))
    write_png(caps / "obj" / "masks" / "0000.png", np.ones((8, 8)))
    (caps / "obj" / "masks" / "notes.txt").write_text("hand-made masks")
    results = {"is": caps, "inside_capture": caps / "obj", "inside_root": caps / "out", "contains": tmp_path}[where]
    before = _tree(caps)
    r = subprocess.run([sys.executable, "-m", "snakemake", "--cores", "1", "--config", f"captures={caps}",
                        f"results={results}", "preset=draft"], cwd=repo_root, capture_output=True, text=True,
                       timeout=300)
    text = r.stdout + r.stderr
    assert r.returncode != 0
    assert f"results folder '{results.resolve()}'" in text and f"captures folder '{caps.resolve()}'" in text
    assert 'File "' not in text and "Traceback" not in text  # the message alone (issue 20 item 4)
    assert _tree(caps) == before
    assert not (caps / "out").exists()


def test_separate_folders_are_accepted(tmp_path):
    (tmp_path / "captures").mkdir()
    check_results_location(tmp_path / "results", tmp_path / "captures")
    check_results_location(tmp_path / "captures-results", tmp_path / "captures")  # a prefix, not a parent
    with pytest.raises(ConfigError, match="lies inside"):
        check_results_location(tmp_path / "captures" / "r", tmp_path / "captures")
