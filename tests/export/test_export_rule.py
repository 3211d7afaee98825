"""The Snakemake rule and its adapter script: `snakemake <results>/<capture>/export/asset.glb`."""

from __future__ import annotations

import shutil
import subprocess
import sys

import pygltflib

from recon.export import validate_usdz


def test_export_rule(model, tmp_path, repo_root):
    captures, results = tmp_path / "captures", tmp_path / "results"
    (captures / "demo" / "images").mkdir(parents=True)
    (captures / "demo" / "images" / "0000.exr").touch()
    shutil.copytree(model.folder / "optimize", results / "demo" / "optimize")
    shutil.copytree(model.folder / "poses", results / "demo" / "poses")
    # the export reads the poses stage's views and masks marker (poses.json): for the support
    # plane (poses/plane.json, absent here: no plane) and a marker mat's views
    (results / "demo" / "poses" / "poses.json").write_text("{}")
    (captures / "demo" / "capture.yaml").write_text("export:\n  meters_per_unit: 0.5\n")
    target = results / "demo" / "export" / "asset.glb"
    proc = subprocess.run(
        [sys.executable, "-m", "snakemake", "--cores", "1", str(target), "--allowed-rules", "export",
         "--config", f"captures={captures}", f"results={results}", "preset=draft"],
        cwd=repo_root, capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    export = results / "demo" / "export"
    assert {p.name for p in export.iterdir()} >= {"asset.glb", "asset.usdz", "asset.usda"}
    assert "exporting" in (results / "demo" / "logs" / "export.log").read_text()
    assert (results / "demo" / "benchmarks" / "export.tsv").is_file()
    assert validate_usdz(export / "asset.usdz") == []
    # capture.yaml's export section reached the settings
    gltf = pygltflib.GLTF2().load(str(export / "asset.glb"))
    assert gltf.asset.extras["recon"]["meters_per_unit"] == 0.5
