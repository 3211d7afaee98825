"""One Snakemake run of the workflow for the slow end-to-end tests (tabletop, real photos)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path


def run_workflow(repo_root: Path, captures: Path, results: Path, target: str, timeout: float) -> None:
    """``snakemake --cores 2`` at draft on ``captures`` up to ``target`` (a path under ``results``);
    fails the test with the log's tail when it does not finish cleanly."""
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE", "PYTHONPATH": str(repo_root)}
    r = subprocess.run([sys.executable, "-m", "snakemake", "--cores", "2", "--config", f"captures={captures}",
                        f"results={results}", "preset=draft", "--", target],
                       cwd=repo_root, env=env, capture_output=True, text=True, timeout=timeout)
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-4000:]
