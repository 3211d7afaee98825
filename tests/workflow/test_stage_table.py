"""The one stage table (recon.stages) and the files that cannot import it.

The Snakefile writes each rule's outputs in full (the catalog style) and profiles/slurm is YAML,
so neither reads the table; these tests hold them to it: the rules' names, order and named
outputs, and the profile's groups, threads and resources. The Python readers (recon.config,
recon.summary, recon.validate, the report's benchmarks) import it.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
import yaml

import recon.config as rc
import recon.summary as rs
from recon import stages as st

_LOAD_RULES = """
import json, sys
from pathlib import Path
from snakemake.api import SnakemakeApi
from snakemake.settings.types import ConfigSettings, OutputSettings, ResourceSettings

config = {"captures": sys.argv[1], "results": sys.argv[2]}
with SnakemakeApi(OutputSettings()) as api:
    wf = api.workflow(resource_settings=ResourceSettings(), config_settings=ConfigSettings(config=config),
                      snakefile=Path("Snakefile"), workdir=Path("."))
    rules = [(r.name, [(name, str(r.output[i])) for name, (i, _) in r.output._names.items()])
             for r in wf._workflow.rules]
print("RULES " + json.dumps(rules))
"""


def _snakefile_rules(repo_root, tmp_path):
    """``[(rule, [(output name, path relative to <results>/<capture>/)])]`` in the Snakefile's order."""
    (tmp_path / "captures" / "obj" / "images").mkdir(parents=True)
    (tmp_path / "captures" / "obj" / "images" / "0000.png").write_bytes(b"")
    results = tmp_path / "results"
    r = subprocess.run([sys.executable, "-c", _LOAD_RULES, str(tmp_path / "captures"), str(results)],
                       cwd=repo_root, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    line = next(x for x in r.stdout.splitlines() if x.startswith("RULES "))
    prefix = f"{results}/{{capture,[^/]+}}/"
    rules = []
    for name, outputs in json.loads(line[len("RULES "):]):
        assert all(path.startswith(prefix) for _, path in outputs), outputs
        rules.append((name, [(k, path[len(prefix):]) for k, path in outputs]))
    return rules


def test_snakefile_rules_and_outputs_are_the_table(repo_root, tmp_path):
    rules = [(name, outs) for name, outs in _snakefile_rules(repo_root, tmp_path) if name != "all"]
    assert [name for name, _ in rules] == [s.rule for s in st.STAGES]
    for (name, outputs), stage in zip(rules, st.STAGES, strict=True):
        assert tuple(map(tuple, outputs)) == stage.outputs, name
        assert all(path.startswith(stage.folder + "/") for path in stage.output_paths), name


def test_slurm_profile_follows_the_table(repo_root):
    profile = yaml.safe_load((repo_root / "profiles" / "slurm" / "config.yaml").read_text())
    assert profile["groups"] == st.slurm_groups()
    assert list(profile["set-threads"]) == list(st.NAMES)
    assert list(profile["set-resources"]) == list(st.NAMES)
    gpu_notes = (repo_root / "profiles" / "slurm" / "config.yaml").read_text()
    assert all(f"  {name}:" in gpu_notes for name in st.GPU_STAGES)


def test_readers_take_the_table():
    from recon.validate import _BUILDERS

    assert rs.STAGES == st.NAMES
    assert rc.STAGES == st.SETTINGS_STAGES == tuple(s.name for s in st.STAGES if s.settings)
    assert tuple(_BUILDERS) == st.SETTINGS_STAGES  # the check builds every section
    assert rc.CAPTURE_KEYS[-len(rc.STAGES):] == rc.STAGES
    assert st.FINAL.name == "report" and st.stage("poses").folder == "poses"
    assert st.stage("linearize").folder == "linear"  # the one stage whose folder is not its name


def test_unknown_stage_is_named():
    with pytest.raises(ValueError, match="unknown stage 'colmap'; stages are check, linearize"):
        st.stage("colmap")
