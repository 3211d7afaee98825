"""The conda environment of the rules (envs/recon.yaml, for `snakemake --use-conda`).

Snakemake creates the environment from a copy of the file in .snakemake/conda/, so the file
cannot point at requirements.txt by a relative path: it repeats the pins, and these tests keep
the two lists equal. Its post-deploy script installs this checkout's recon package.
"""

from __future__ import annotations

import os
import subprocess

import yaml


def _requirements(repo_root) -> list[str]:
    lines = (repo_root / "requirements.txt").read_text().splitlines()
    return [line.strip() for line in lines if line.strip() and not line.lstrip().startswith("#")]


def test_env_pins_are_the_requirements(repo_root):
    env = yaml.safe_load((repo_root / "envs" / "recon.yaml").read_text())
    pips = [d["pip"] for d in env["dependencies"] if isinstance(d, dict) and "pip" in d]
    assert len(pips) == 1
    assert pips[0] == _requirements(repo_root), "envs/recon.yaml's pip list must equal requirements.txt"
    # nothing names a file: Snakemake builds the environment from a copy in another folder
    assert not any(p.startswith(("-r", "-e", ".", "/")) for p in pips[0])


def test_every_rule_uses_the_env(repo_root):
    rules = sorted((repo_root / "workflow" / "rules").glob("*.smk"))
    for path in rules:
        text = path.read_text()
        assert text.count("    conda:\n        \"../../envs/recon.yaml\"") == text.count("\nrule "), path


def test_post_deploy_refuses_another_folder(repo_root, tmp_path):
    script = repo_root / "envs" / "recon.post-deploy.sh"
    assert os.access(script, os.X_OK)
    r = subprocess.run(["bash", str(script)], cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert r.returncode == 1
    assert "not the recon repository" in r.stderr and str(tmp_path) in r.stderr
