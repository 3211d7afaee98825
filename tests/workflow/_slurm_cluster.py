"""Helpers of the SLURM tests (tests/workflow/test_slurm.py) and bench/cluster_cost.py: the running
cluster's account and partition, a copy of profiles/slurm filled in for it, tiny synthetic
captures, Snakemake runs, and what sacct says about their jobs."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[2]
SNAKEMAKE = [sys.executable, "-m", "snakemake"]

# A small capture's settings: few iterations, small textures, a cheap report (capture.yaml).
TINY_SETTINGS = {
    "init_mesh": {"resolution": 48, "target_faces": 1000, "remesh_iterations": 2},
    "uv": {"texture_size": 64},
    "optimize": {
        "select": {"select_material": False},
        "schedule": {"checkpoint_every": 5},
        "stages": [{"edge_length": 0.08, "texture_size": 64, "iterations": 20}],
    },
    "report": {"spp": 4, "gt_views": 2, "max_views": 2, "chamfer_samples": 20000,
               "texture_samples": 20000, "max_size": 96, "texture_display_size": 64},
}


def env() -> dict:
    """The environment of a Snakemake run: this checkout's recon first, OpenMP threads passive."""
    e = dict(os.environ)
    e["PYTHONPATH"] = str(REPO) + (os.pathsep + e["PYTHONPATH"] if e.get("PYTHONPATH") else "")
    e.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    e["PATH"] = str(Path(sys.executable).parent) + os.pathsep + e.get("PATH", "")
    return e


def cluster_problem() -> str | None:
    """None when a SLURM cluster with accounting answers here, else what is missing."""
    for tool in ("sbatch", "sacct", "sacctmgr", "sinfo", "srun"):
        if shutil.which(tool) is None:
            return f"{tool} not found: start a cluster with `bash scripts/slurm_local.sh` (root)"
    try:
        out = subprocess.run(["srun", "-Q", "-N1", "-n1", "-t", "1", "hostname"], capture_output=True,
                             text=True, timeout=60)
    except subprocess.TimeoutExpired:
        return "srun hostname did not return in 60 s"
    if out.returncode != 0:
        return f"srun hostname failed: {out.stderr.strip()}"
    sacct = subprocess.run(["sacct", "-n", "-X", "-o", "JobID"], capture_output=True, text=True)
    if sacct.returncode != 0:
        return f"sacct failed (accounting off?): {sacct.stderr.strip()}"
    return None


def account_and_partition() -> tuple[str, str]:
    """The calling user's default account (sacctmgr) and the default partition (sinfo)."""
    user = subprocess.run(["id", "-un"], capture_output=True, text=True, check=True).stdout.strip()
    account = subprocess.run(["sacctmgr", "-n", "-P", "list", "user", user, "format=defaultaccount"],
                             capture_output=True, text=True, check=True).stdout.strip()
    parts = subprocess.run(["sinfo", "-h", "-o", "%P"], capture_output=True, text=True,
                           check=True).stdout.split()
    default = next((p.rstrip("*") for p in parts if p.endswith("*")), parts[0].rstrip("*"))
    return account, default


def make_profile(dest: Path, retries: int | None = None, set_resources: dict | None = None,
                 status_check_seconds: int = 2, threads: int | None = 1) -> Path:
    """profiles/slurm/config.yaml copied to ``dest`` with the cluster's account and partition
    filled in (as a user does), the first status check after ``status_check_seconds`` (the
    plugin waits 40 s by default), every stage on ``threads`` CPUs (small jobs: the test node
    has the machine's real CPUs, 2 here, and two jobs should run side by side), and optional
    overrides."""
    cfg = yaml.safe_load((REPO / "profiles" / "slurm" / "config.yaml").read_text())
    account, partition = account_and_partition()
    cfg["default-resources"].update({"slurm_account": account, "slurm_partition": partition})
    cfg["slurm-init-seconds-before-status-checks"] = status_check_seconds
    cfg["slurm-keep-successful-logs"] = True  # the tests read every job's log
    if threads is not None:
        cfg["set-threads"] = {rule: threads for rule in cfg["set-threads"]}
    if retries is not None:
        cfg["retries"] = retries
    for rule, values in (set_resources or {}).items():
        cfg["set-resources"].setdefault(rule, {}).update(values)
    dest.mkdir(parents=True, exist_ok=True)
    (dest / "config.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    return dest


def make_tiny_capture(folder: Path, seed: int, views: int = 6, width: int = 64,
                      settings: dict | None = None) -> Path:
    """A small synthetic capture (known cameras, EXR photos) with :data:`TINY_SETTINGS`."""
    from recon import sections
    from recon.synth.capture import SynthSettings, make_capture

    make_capture(folder, sections.replace(SynthSettings(), n_views=views, width=width, height=width * 3 // 4,
                                       format="exr", seed=seed, mesh_level=3, texture_size=64,
                                       write_cameras=True, write_masks=False))
    yaml_path = folder / "capture.yaml"  # the generator writes one only where it states something
    cap = (yaml.safe_load(yaml_path.read_text()) if yaml_path.exists() else None) or {}
    cap.update(json.loads(json.dumps(settings if settings is not None else TINY_SETTINGS)))
    yaml_path.write_text(yaml.safe_dump(cap, sort_keys=False))
    return folder


def snakemake(args: list[str], log: Path, timeout: float = 1200) -> subprocess.CompletedProcess:
    """Run Snakemake from the repository root (its workflow profile applies); output to ``log``."""
    with open(log, "w") as fh:
        return subprocess.run(SNAKEMAKE + args, cwd=REPO, env=env(), stdout=fh,
                               stderr=subprocess.STDOUT, timeout=timeout)


def slurm_job_ids(log: Path) -> list[str]:
    """The SLURM job ids a Snakemake run submitted (from its output)."""
    return re.findall(r"has been submitted with SLURM jobid (\d+)", log.read_text())


def sacct(job_ids: list[str]) -> list[dict]:
    """sacct's record of each job (allocation line only): id, state, rule (the plugin's comment),
    submit/start/end times, elapsed seconds, exit code."""
    if not job_ids:
        return []
    fields = ["JobIDRaw", "State", "Comment", "Submit", "Start", "End", "ElapsedRaw", "ExitCode",
              "AllocCPUS", "ReqMem", "Timelimit", "Account", "Partition"]
    for _ in range(30):  # slurmdbd records a finished job within seconds
        out = subprocess.run(["sacct", "-X", "-n", "-P", "-j", ",".join(job_ids), "-o", ",".join(fields)],
                             capture_output=True, text=True, check=True).stdout
        rows = [dict(zip(fields, line.split("|"), strict=True)) for line in out.splitlines() if line]
        if len(rows) == len(job_ids) and all(r["End"] not in ("", "Unknown") for r in rows):
            return rows
        time.sleep(1)
    return rows


def wait_for(predicate, timeout: float, what: str, poll: float = 1.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(poll)
    raise TimeoutError(f"gave up after {timeout:.0f} s waiting for {what}")
